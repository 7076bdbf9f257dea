"""All-in-view acceptance: a satellite rising above the mask during a 10-minute generated run.

    python benchmarks/acceptance_all_in_view.py [--quick] [--json OUT.json]

Scenario: static-open-sky-atmosphere moved to TOW 567000 (week 2190), 600 s, 2 MHz complex int8,
45 dB-Hz, seed 1, with ``satellites.horizon_deg = 5`` (signals only above 5 deg: PRN 16 appears when
it crosses the 5 deg mask, ~505 s into the run).  The receiver runs with its defaults (all in view,
search every 15 s).  Figures: the time each satellite crosses the mask (truth), the time it was
acquired, the delay, and the first fix that used it; every satellite above the mask used within
30 s of the first fix.
"""

import argparse
import sys
import tempfile
import time

import numpy as np

from _common import add_common_args, finish


def run(tmp, duration_s=600.0, seed=1):
    import h5py

    from ultratight.receiver.scalar.receiver import ProcessConfig, process
    from ultratight.receiver.cli.scenario_config import load_scenario
    from ultratight.signals.synth.generator import generate

    cfg = load_scenario("static-open-sky-atmosphere", {"time.tow_s": 567000.0, "duration_s": duration_s,
                                                       "frontend.fs_hz": 2.0e6, "satellites.horizon_deg": 5.0,
                                                       "seed": seed})
    t0 = time.perf_counter()
    files = generate(cfg, tmp, "rise", progress=False)
    gen_s = time.perf_counter() - t0
    with h5py.File(files["truth"], "r") as f:
        prns = [int(p) for p in f.attrs["prn"]]
        el = f["elev_deg"][:]
        t = f["t_s"][:]
    t0 = time.perf_counter()
    res = process(files["if"], ProcessConfig())
    proc_s = time.perf_counter() - t0
    first_fix = res.first_fix_s
    out = {"generate_s": round(gen_s, 1), "process_s": round(proc_s, 1), "first_fix_s": first_fix,
           "searches": res.searches, "fixes": len(res.fixes), "satellites": {}}
    by_prn = {c["prn"]: c for c in res.channels}
    for k, p in enumerate(prns):
        above = np.flatnonzero(el[:, k] >= 5.0)
        rise = float(t[above[0]]) if above.size else None
        c = by_prn.get(p, {})
        used = [f["t_s"] for f in res.fixes if p in f["used_prn"]]
        out["satellites"][p] = {"above_mask_s": rise, "acquired_s": c.get("acquired_s"),
                                "first_used_s": used[0] if used else None}
    return out


def main(argv=None):
    ap = add_common_args(argparse.ArgumentParser(description=__doc__.splitlines()[0]))
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        r = run(tmp, 120.0 if args.quick else 600.0)
    print(f"first fix {r['first_fix_s']} s, {r['fixes']} fixes, {r['searches']} searches, "
          f"generate {r['generate_s']} s, process {r['process_s']} s")
    for p, v in r["satellites"].items():
        print(f"PRN {p:2d}: above the mask at {v['above_mask_s']} s, acquired at {v['acquired_s']} s, "
              f"first used at {v['first_used_s']} s")
    finish(args, r)
    return 0


if __name__ == "__main__":
    sys.exit(main())
