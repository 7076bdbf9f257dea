"""Campaign throughput: one worker against two, the pairs of docs/campaign.md "Throughput".

    python benchmarks/acceptance_campaign.py [--quick] [--only robust,highdyn-cache,highdyn-stream]
        [--json OUT.json]

Each pair runs ``ultratight campaign SCENARIO ... --workers 1`` and then ``--workers 2`` in fresh
processes and fresh output folders, and prints the wall time of each (the cluster start included,
as the document's), runs per hour, wall seconds per run and the throughput ratio 2 workers / 1
worker; the two campaigns' non-timing figures must be equal (``campaign.json``), which the line
says.  Pairs: ``robust`` = paper-robust-flight, 8 runs; ``highdyn-cache`` / ``highdyn-stream`` =
paper-highdyn cut to 20 s, 20 runs, with and without ``--cache``.  The ratio depends on the free
cores: compare on an idle machine (the document's target: ≥ 1.7× for paper-highdyn on two free
cores).  ``--quick``: paper-robust-flight, 2 runs cut to 100 s.
"""

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _common import add_common_args, finish

PAIRS = {
    "robust": ("paper-robust-flight", ["--runs", "8"]),
    "highdyn-cache": ("paper-highdyn", ["--runs", "20", "--duration", "20", "--cache"]),
    "highdyn-stream": ("paper-highdyn", ["--runs", "20", "--duration", "20"]),
}


TIMING_WORDS = ("time", "timing", "wall", "elapsed")        # keys naming a time: runtime_s, timing, ...
OTHER_KEYS = {"where", "host", "machine", "out", "out_dir", "path"}


def _figures(obj):
    """The campaign.json without its timing entries (keys naming a time) and where it ran, for
    comparing two campaigns."""
    if isinstance(obj, dict):
        return {k: _figures(v) for k, v in obj.items()
                if k not in OTHER_KEYS and not any(w in k for w in TIMING_WORDS)}
    if isinstance(obj, list):
        return [_figures(v) for v in obj]
    return obj


def one(scenario, args, workers, out):
    cmd = [sys.executable, "-m", "ultratight.receiver.cli", "campaign", scenario, *args, "--workers",
           str(workers), "--out", str(out), "--quiet", "--json"]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        tail = (proc.stderr.strip().splitlines() or ["(no output)"])[-1]
        raise SystemExit(f"acceptance_campaign: {' '.join(cmd[3:])} failed: {tail}")
    return wall, json.loads((Path(out) / "campaign.json").read_text())


def main(argv=None):
    ap = add_common_args(argparse.ArgumentParser(description=__doc__.splitlines()[0]))
    ap.add_argument("--only", default=None, help="comma-separated pairs: " + ",".join(PAIRS))
    a = ap.parse_args(argv)
    names = [n.strip() for n in (a.only or ",".join(PAIRS)).split(",") if n.strip()]
    unknown = [n for n in names if n not in PAIRS]
    if unknown:
        print(f"acceptance_campaign: unknown pair(s) {', '.join(unknown)}; known: {', '.join(PAIRS)}", file=sys.stderr)
        return 2
    pairs = {"robust-quick": ("paper-robust-flight", ["--runs", "2", "--duration", "100"])} if a.quick \
        else {n: PAIRS[n] for n in names}
    res = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name, (scen, args) in pairs.items():
            runs = int(args[args.index("--runs") + 1])
            w1, j1 = one(scen, args, 1, Path(tmp) / f"{name}-w1")
            w2, j2 = one(scen, args, 2, Path(tmp) / f"{name}-w2")
            same = _figures(j1) == _figures(j2)
            res[name] = {"scenario": scen, "args": args, "wall_1_s": w1, "wall_2_s": w2, "ratio": w1 / w2,
                         "runs_per_h_1": runs * 3600.0 / w1, "runs_per_h_2": runs * 3600.0 / w2,
                         "same_figures": same}
            print(f"{name:15s} 1 worker {w1:6.1f} s ({runs * 3600.0 / w1:.0f} runs/h), 2 workers {w2:6.1f} s "
                  f"({runs * 3600.0 / w2:.0f} runs/h): ratio 2/1 {w1 / w2:.2f}; "
                  f"non-timing figures {'equal' if same else 'DIFFER'}", flush=True)
    finish(a, {"pairs": res})
    return 0 if all(r["same_figures"] for r in res.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
