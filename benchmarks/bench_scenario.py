"""Benchmark the README's main job, ``ultratight scenario paper-highdyn``, end to end.

    python benchmarks/bench_scenario.py [--quick] [--json OUT.json] [--duration S]

Runs the command in fresh processes, each into a fresh output folder (IF generation included, as a
user's first run): the default (methods in worker processes and threads where cores are free), the
same code on one core (``--workers 1 --threads 1``: the methods one after the other in one process,
one thread) and the same command on the baseline commit (``--baseline``, default the receiver
before it was rebuilt from stages, run from an export of that commit). It reports for each the wall
time, the CPU time of the process and its children and the peak resident set size of the largest
process, the sizes of ``results.h5`` and of the data cache (truth, trajectory, IMU), and the ratios of
the wall times ``default / baseline`` and ``default / one core``. Every
code version first runs a 2 s cut (numba compilation or cache loading stays out of the figures).
``--repeat N`` times the default and the baseline N times each, alternately, and compares the median
runs (the wall time of one run varies by up to about 10 % on a shared 2-core VM). Baseline exports are
kept (``_common.baseline_root``), so a baseline compiles once. ``--quick``: a 10 s cut at 2.046 MHz, no
baseline.
"""

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _common import add_baseline_arg, add_common_args, baseline_env, finish


def _run(args, cwd, env=None):
    """Wall time, CPU time (user + system of the process and its descendants) and peak RSS (MB) of
    the largest of them, for one command."""
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    with tempfile.TemporaryFile() as fo, tempfile.TemporaryFile() as fe:
        t0 = time.perf_counter()
        p = subprocess.Popen(args, cwd=cwd, stdout=fo, stderr=fe, env=env)
        _, status, ru = os.wait4(p.pid, 0)
        r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
        p.returncode = os.waitstatus_to_exitcode(status)
        wall = time.perf_counter() - t0
        fe.seek(0)
        err = fe.read().decode(errors="replace")
    if p.returncode != 0:
        raise RuntimeError(f"{' '.join(args)} failed: {err.strip().splitlines()[-1:]}")
    cpu = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)
    return {"wall_s": wall, "cpu_s": cpu, "maxrss_mb": ru.ru_maxrss / 1024.0}   # wait4: the process tree


def output_sizes(out):
    """Sizes (MB = 1e6 bytes) of a run's ``results.h5`` and of its data cache (``OUT/cache``: truth,
    trajectory, IMU; the IF only with ``--cache``), by file."""
    out = Path(out)
    res = out / "results.h5"
    files = sorted(p for p in (out / "cache").rglob("*") if p.is_file() and p.suffix not in (".lock", ".json")) \
        if (out / "cache").is_dir() else []
    by_file = {p.name: p.stat().st_size / 1e6 for p in files}
    return {"results_h5_mb": res.stat().st_size / 1e6 if res.exists() else 0.0,
            "cache_mb": sum(by_file.values()), "cache_files_mb": by_file}


def main(argv=None):
    ap = add_baseline_arg(add_common_args(argparse.ArgumentParser(description=__doc__.splitlines()[0])))
    ap.add_argument("--duration", type=float, default=None, help="cut length, s (default: the scenario's 60 s)")
    ap.add_argument("--repeat", type=int, default=1, metavar="N",
                    help="time the default and the baseline N times each, alternately, and compare their "
                         "medians (the one-core reference runs once); default 1")
    a = ap.parse_args(argv)
    if a.repeat < 1:
        ap.error(f"--repeat must be >= 1, got {a.repeat}")
    extra = []
    if a.quick:
        extra = ["--duration", str(a.duration or 10.0), "--fs-hz", "2.046e6"]
    elif a.duration:
        extra = ["--duration", str(a.duration)]
    base = [sys.executable, "-m", "ultratight.receiver.cli", "scenario", "paper-highdyn", "--no-plots", "--quiet",
            "--json"]
    res = {}
    with tempfile.TemporaryDirectory() as tmp:
        versions = [("default", [], None), ("reference_one_core", ["--workers", "1", "--threads", "1"], None)]
        baseline = None
        if not a.quick and a.baseline.lower() != "none":
            env, baseline = baseline_env(a.baseline, tmp)
            if env is None:
                print(f"{baseline}: measuring without it", flush=True)
                baseline = None
            else:
                versions.append(("baseline", [], env))
        for name, flags, env in versions:
            # compile (or load the numba cache of) this code version outside the timing
            _run(base + ["--duration", "2", "--out", str(Path(tmp) / f"warm-{name}")] + flags, tmp, env)
        # alternate the versions (default, baseline, default, ...) so a change of the machine's load
        # during the run falls on both; the one-core reference once, at the end
        order = [v for _ in range(max(1, a.repeat)) for v in versions if v[0] != "reference_one_core"]
        order += [v for v in versions if v[0] == "reference_one_core"]
        samples = {}
        for k, (name, flags, env) in enumerate(order):
            out = Path(tmp) / f"{name}-{k}"
            r = _run(base + extra + ["--out", str(out)] + flags, tmp, env)
            r.update(output_sizes(out))
            samples.setdefault(name, []).append(r)
            print(f"{name:20s} wall {r['wall_s']:6.1f} s, CPU {r['cpu_s']:6.1f} s, "
                  f"peak RSS {r['maxrss_mb']:.0f} MB", flush=True)
            print(f"{name:20s} outputs: results.h5 {r['results_h5_mb']:.1f} MB, cache {r['cache_mb']:.1f} MB "
                  f"({', '.join(f'{k} {v:.1f} MB' for k, v in r['cache_files_mb'].items())})", flush=True)
        for name, rs in samples.items():
            mid = sorted(rs, key=lambda r: r["wall_s"])[(len(rs) - 1) // 2]     # the median run
            res[name] = dict(mid, walls_s=[r["wall_s"] for r in rs])
    rep = {"scenario": "paper-highdyn", "args": extra, "runs": res, "quick": a.quick, "repeat": a.repeat}
    rep["wall_ratio"] = res["default"]["wall_s"] / res["reference_one_core"]["wall_s"]
    print(f"default / one core: {rep['wall_ratio']:.2f} of the wall time")
    if baseline:
        rep["baseline"] = baseline
        rep["wall_ratio_baseline"] = res["default"]["wall_s"] / res["baseline"]["wall_s"]
        print(f"default / baseline ({baseline}): {rep['wall_ratio_baseline']:.2f} of the wall time")
    finish(a, rep)
    return 0


if __name__ == "__main__":
    sys.exit(main())
