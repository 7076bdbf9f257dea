"""Benchmark the ultra-tight engine end to end on paper-highdyn (13 channels from IF samples).

    python benchmarks/bench_ultratight.py [--quick] [--json OUT.json] [--duration S] [--fs HZ]
        [--methods dlb-rackf,dlb-ukf,dlb-ckf] [--workdir DIR]

Generates (once, cached in ``--workdir`` like ``ultratight scenario``) a cut of the scenario
(20 s at its native 4 MHz int16; ``--quick``: 5 s at 2.046 MHz), compiles every method on a 0.2 s
run, then runs each method on the cut in this process twice — on one thread (the reference,
``EngineOptions(threads=1)``) and with the channels spread over ``--threads`` threads (default 2,
both cores of the reference machine) — and reports:

* ``realtime_factor``: wall time / signal time on ``--threads`` threads (< 1 = faster than real
  time); ``realtime_factor_1thread`` the reference's, and ``speedup`` their ratio;
* ``timing_s``: the engine's own split (compiled 1 kHz epochs, one-epoch path of the start-up,
  SINS + outer loop, tight filter);
* ``ratio_rackf_over_ukf`` (whole run, one thread; the paper's Table 4 reports ≈ 0.5 for its
  filters);
* ``maxrss_mb``: peak resident set size of this process;
* with ``--baseline REV``: the same benchmark of commit ``REV`` (its own ``bench_ultratight.py``,
  exported with ``git archive`` and run in a subprocess right after, same cut and threads) under
  ``baseline``, and per method ``ratio_baseline``: this run's real-time factor over the baseline's;
* with ``--scenario``: per method, ``ultratight scenario paper-highdyn --methods M`` on the same cut
  as a user runs it (the IF generated in memory beside the engine), its ``runtime_s``, its ratio to
  the engine-only run (``scenario.ratio_to_engine_only``) and the engine's split of it (``if_read``:
  waiting for the generator).
"""

import argparse
import resource
import sys
import tempfile
import time
from pathlib import Path

from _common import add_common_args, baseline_env, finish


def main(argv=None):
    ap = add_common_args(argparse.ArgumentParser(description=__doc__.splitlines()[0]))
    ap.add_argument("--duration", type=float, default=None, help="cut length, s (20; --quick 5)")
    ap.add_argument("--fs", type=float, default=None, help="sampling rate, Hz (scenario's 4 MHz; --quick 2.046 MHz)")
    ap.add_argument("--methods", default="dlb-rackf,dlb-ukf,dlb-ckf")
    ap.add_argument("--workdir", default=None, help="data cache (default: a temporary folder)")
    ap.add_argument("--threads", type=int, default=2, help="threads of the measured run (reference: 1)")
    ap.add_argument("--scenario", action="store_true",
                    help="also run `ultratight scenario paper-highdyn` per method on the same cut (streamed IF) and "
                         "compare its runtime_s with the engine-only run")
    ap.add_argument("--baseline", metavar="REV", default="none",
                    help="also run this commit's own bench_ultratight.py on the same cut (default: none)")
    a = ap.parse_args(argv)
    dur = a.duration or (5.0 if a.quick else 20.0)
    methods = [m.strip() for m in a.methods.split(",") if m.strip()]

    from ultratight.errors import UltratightError
    from ultratight.receiver.deep.options import EngineOptions
    from ultratight.receiver.cli.scenario_config import load_scenario
    from ultratight.receiver.cli.scenario_runner import prepare_data, run_method

    ov = {"duration_s": dur}
    fs = a.fs or (2.046e6 if a.quick else None)
    if fs:
        ov["frontend.fs_hz"] = fs
    try:
        cfg = load_scenario("paper-highdyn", ov)
    except UltratightError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(a.workdir or tmp)
        t0 = time.perf_counter()
        paths, cached = prepare_data(cfg, 1, work)
        gen_s = 0.0 if cached else time.perf_counter() - t0
        opts = {k: EngineOptions(threads=k) for k in (1, a.threads)}
        for m in methods:                      # numba compilation / cache load outside the timing
            for o in opts.values():
                run_method(paths, cfg, m, 1, duration_s=0.2, options=o)
        res = {}
        for m in methods:
            ref, _ = run_method(paths, cfg, m, 1, options=opts[1])
            r, _ = run_method(paths, cfg, m, 1, options=opts[a.threads])
            tm = {k: float(v) for k, v in r.info.get("timing_s", {}).items()}
            res[m] = {"runtime_s": r.runtime_s, "signal_s": r.duration_s, "threads": r.info.get("threads"),
                      "realtime_factor": r.runtime_s / r.duration_s,
                      "runtime_1thread_s": ref.runtime_s, "realtime_factor_1thread": ref.runtime_s / ref.duration_s,
                      "speedup": ref.runtime_s / r.runtime_s, "timing_s": tm}
            print(f"{m:10s} {r.runtime_s:6.2f} s for {r.duration_s:.1f} s of signal on {r.info.get('threads')} "
                  f"threads: real-time factor {res[m]['realtime_factor']:.3f} (one thread: "
                  f"{res[m]['realtime_factor_1thread']:.3f}, speed-up {res[m]['speedup']:.2f}); epochs "
                  f"{tm.get('epochs', float('nan')):.2f} s, SINS + outer loop {tm.get('sins_outer', float('nan')):.2f} s,"
                  f" tight {tm.get('tight', float('nan')):.2f} s", flush=True)
    out = {"scenario": "paper-highdyn", "duration_s": dur, "fs_hz": float(cfg["frontend"]["fs_hz"]),
           "format": cfg["frontend"]["format"], "channels": 13, "generate_s": gen_s, "methods": res,
           "maxrss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0}
    if "dlb-rackf" in res and "dlb-ukf" in res:
        rk, uk = res["dlb-rackf"], res["dlb-ukf"]
        out["ratio_rackf_over_ukf"] = rk["runtime_1thread_s"] / uk["runtime_1thread_s"]
        print(f"dlb-rackf / dlb-ukf (one thread): whole run {out['ratio_rackf_over_ukf']:.2f} (paper Table 4: 0.52)")
    print(f"peak RSS {out['maxrss_mb']:.0f} MB; {cfg['frontend']['fs_hz'] / 1e6:g} MHz {cfg['frontend']['format']}, "
          f"{dur:g} s cut of paper-highdyn")
    if a.scenario:
        _compare_scenario(out, methods, dur, fs)
    if a.baseline.lower() != "none":
        _compare_baseline(a, out, dur, fs)
    finish(a, out)
    return 0


def _compare_scenario(out, methods, dur, fs):
    """``ultratight scenario paper-highdyn --methods M --duration D`` per method, as a user runs it (its
    defaults: on two or more cores the IF written ahead into the cache and read by the method, else
    generated beside it; its own choice of threads), in a fresh process right after the engine-only runs:
    its ``runtime_s`` against the engine-only run's, the engine's split of it (``timing_s``, ``if_read`` =
    waiting for the samples) and the command's split of its wall time (``command_timing_s``: start-up,
    data, methods; the rest is the outputs and the exit)."""
    import json
    import subprocess

    for m in methods:
        with tempfile.TemporaryDirectory() as tmp:
            cmd = [sys.executable, "-m", "ultratight.receiver.cli.main", "scenario", "paper-highdyn", "--methods", m,
                   "--duration", f"{dur:g}", "--no-plots", "--json", "--out", tmp]
            if fs:
                cmd += ["--fs-hz", f"{fs:g}"]
            t0 = time.perf_counter()
            subprocess.run(cmd, capture_output=True, text=True, check=True)
            wall = time.perf_counter() - t0
            with open(Path(tmp) / "metrics.json") as f:
                js = json.load(f)
        run, split = js["per_run"][m][0], js.get("command_timing_s", {})
        eng = out["methods"][m]
        parts = {k: split.get(k) for k in ("start_up_s", "data_s", "methods_s")}
        parts["outputs_and_exit_s"] = wall - sum(v or 0.0 for v in parts.values())
        sc = {"runtime_s": run["runtime_s"], "timing_s": run["timing_s"], "command_wall_s": wall,
              "command_split_s": parts, "ratio_to_engine_only": run["runtime_s"] / eng["runtime_s"]}
        eng["scenario"] = sc
        tm = run["timing_s"]
        print(f"{m:10s} scenario: runtime_s {run['runtime_s']:.2f} s = "
              f"{sc['ratio_to_engine_only']:.2f} x the engine alone ({eng['runtime_s']:.2f} s); epochs "
              f"{tm.get('epochs', 0):.2f} s, waiting for IF {tm.get('if_read', 0):.2f} s, SINS + outer loop "
              f"{tm.get('sins_outer', 0):.2f} s, tight {tm.get('tight', 0):.2f} s; whole command {wall:.1f} s = "
              + ", ".join(f"{k[:-2].replace('_', ' ')} {v:.2f} s" for k, v in parts.items() if v is not None),
              flush=True)


def _compare_baseline(a, out, dur, fs):
    """Run commit ``a.baseline``'s own bench_ultratight.py on the same cut; add its figures and the
    ratios of the real-time factors to ``out``."""
    import json
    import os
    import subprocess

    with tempfile.TemporaryDirectory() as tmp:
        env, name = baseline_env(a.baseline, tmp, folders=("ultratight", "benchmarks"))
        if env is None:
            print(f"{name}: no baseline", flush=True)
            return
        rep = os.path.join(tmp, "baseline.json")
        cmd = [sys.executable, os.path.join(env["ULTRATIGHT_BASELINE_DIR"], "benchmarks", "bench_ultratight.py"),
               "--duration", str(dur), "--methods", a.methods, "--threads", str(a.threads), "--json", rep]
        if fs:
            cmd += ["--fs", str(fs)]
        subprocess.run(cmd, env=env, check=True)
        with open(rep) as f:
            base = json.load(f)
    out["baseline"] = {"commit": name, "methods": base["methods"]}
    for m, r in out["methods"].items():
        b = base["methods"].get(m)
        if b:
            r["ratio_baseline"] = r["realtime_factor"] / b["realtime_factor"]
            print(f"{m:10s} real-time factor {r['realtime_factor']:.3f} against {b['realtime_factor']:.3f} on "
                  f"{name}: {r['ratio_baseline']:.3f}", flush=True)


if __name__ == "__main__":
    sys.exit(main())
