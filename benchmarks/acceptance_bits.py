"""Acceptance of the navigation-data bit strategies (issue 13, "Unknown bits"): paper-highdyn
generated with bits the receiver cannot know (``nav.data``), dlb-rackf with each ``--bits``
strategy.

    python benchmarks/acceptance_bits.py check [--seeds 1,2,3,4,5] [--cn0 30] [--strategies decoded,blind]
    python benchmarks/acceptance_bits.py sweep [--seeds 1] [--cn0-list 20,22.5,...,35]
        [--strategies assisted,decoded,blind]
    common: [--nav-data lnav-random-sf45] [--method dlb-rackf] [--data DIR] [--json OUT.json]

``check``: per seed and strategy, the channels that lost lock (metrics.loss_of_lock) and the Doppler
RMS over all channels in each paper segment (0-20, 20-40, 40-60 s); passes when no channel is lost
and every segment's RMS is <= 0.2 Hz. ``sweep``: the same runs over a C/N0 grid; reports per
strategy the lowest C/N0 at which every channel of every seed keeps lock (and the Doppler RMS
there). Data (IF/IMU/truth per seed and C/N0) are cached under DIR/cache as ``ultratight scenario``
does; the engine's hot start is the same draw for every strategy of a seed.
"""

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

DOPPLER_LIMIT_HZ = 0.2


def one(cfg, seed, strategy, method, data_dir):
    from ultratight.receiver.cli import metrics as M
    from ultratight.receiver.deep.options import EngineOptions
    from ultratight.receiver.cli.scenario_runner import errors_vs_truth, prepare_data, run_method
    from ultratight.receiver.dsp.wipeoff import BIT_BLIND

    paths, _ = prepare_data(cfg, seed, data_dir, progress=False)
    t0 = time.perf_counter()
    res, truth = run_method(paths, cfg, method, seed, options=EngineOptions(bits=strategy))
    wall = time.perf_counter() - t0
    d_err, c_err = errors_vs_truth(res, truth)
    summ = M.summarize(res.t_start, d_err, c_err, M.SEGMENTS_S)
    blind = float(np.mean(np.asarray(res.bit_source) == BIT_BLIND)) if res.bit_source is not None else None
    return {"seed": seed, "strategy": strategy, "cn0_dbhz": float(cfg["satellites"]["cn0_dbhz"]),
            "lock_lost_channels": summ["lock_lost_channels"],
            "doppler_rms_hz": [None if not np.isfinite(v) else round(float(v), 4) for v in summ["doppler_rms_hz"]],
            "code_rms_chips": [None if not np.isfinite(v) else round(float(v), 5) for v in summ["code_rms_chips"]],
            "blind_fraction": None if blind is None else round(blind, 4), "wall_s": round(wall, 1)}


def _cfg(cn0, nav_data):
    from ultratight.receiver.cli.scenario_config import load_scenario
    return load_scenario("paper-highdyn", {"satellites.cn0_dbhz": float(cn0), "nav.data": nav_data})


def _ok(r):
    return r["lock_lost_channels"] == 0 and all(v is not None and v <= DOPPLER_LIMIT_HZ for v in r["doppler_rms_hz"])


def check(args):
    rows = []
    cfg = _cfg(args.cn0, args.nav_data)
    for s in args.seeds:
        for st in args.strategies:
            r = one(cfg, s, st, args.method, args.data)
            r["pass"] = _ok(r)
            rows.append(r)
            print(json.dumps(r), flush=True)
    print("\nstrategy   seeds  lost  max Doppler RMS per segment (Hz)  pass")
    for st in args.strategies:
        rr = [r for r in rows if r["strategy"] == st]
        mx = [max(r["doppler_rms_hz"][i] for r in rr) for i in range(3)]
        print(f"{st:10s} {len(rr):5d} {sum(r['lock_lost_channels'] for r in rr):5d}  "
              f"{' / '.join(f'{v:.3f}' for v in mx):30s}  {all(r['pass'] for r in rr)}")
    return rows


def sweep(args):
    rows = []
    for cn0 in args.cn0_list:
        cfg = _cfg(cn0, args.nav_data)
        for s in args.seeds:
            for st in args.strategies:
                r = one(cfg, s, st, args.method, args.data)
                rows.append(r)
                print(json.dumps(r), flush=True)
    print("\nC/N0 dB-Hz  " + "  ".join(f"{st:>22s}" for st in args.strategies))
    for cn0 in args.cn0_list:
        cells = []
        for st in args.strategies:
            rr = [r for r in rows if r["strategy"] == st and r["cn0_dbhz"] == cn0]
            lost = sum(r["lock_lost_channels"] for r in rr)
            worst = max(max(v if v is not None else np.inf for v in r["doppler_rms_hz"]) for r in rr)
            cells.append(f"lost {lost:2d}, RMS<= {worst:7.3f}")
        print(f"{cn0:10.1f}  " + "  ".join(f"{c:>22s}" for c in cells))
    print("\nlowest C/N0 with every channel of every seed in lock:")
    for st in args.strategies:
        good = [cn0 for cn0 in args.cn0_list
                if all(r["lock_lost_channels"] == 0 for r in rows if r["strategy"] == st and r["cn0_dbhz"] == cn0)]
        # the threshold: the lowest C/N0 from which every higher grid point keeps lock too
        thr = None
        for cn0 in sorted(args.cn0_list, reverse=True):
            if cn0 in good:
                thr = cn0
            else:
                break
        print(f"  {st:10s} {thr if thr is not None else 'none'} dB-Hz")
    return rows


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("what", choices=("check", "sweep"))
    p.add_argument("--seeds", default=None, help="comma-separated seeds (check: 1,2,3,4,5; sweep: 1)")
    p.add_argument("--cn0", type=float, default=30.0)
    p.add_argument("--cn0-list", default="20,22.5,25,27.5,30,32.5,35")
    p.add_argument("--strategies", default=None, help="check: decoded,blind; sweep: assisted,decoded,blind")
    p.add_argument("--nav-data", default="lnav-random-sf45")
    p.add_argument("--method", default="dlb-rackf")
    p.add_argument("--data", default="scenario_out", help="data cache directory (as ultratight scenario --out)")
    p.add_argument("--json", default=None, help="write the rows as JSON here")
    a = p.parse_args(argv)
    a.seeds = [int(s) for s in (a.seeds or ("1,2,3,4,5" if a.what == "check" else "1")).split(",")]
    a.strategies = (a.strategies or ("decoded,blind" if a.what == "check" else "assisted,decoded,blind")).split(",")
    a.cn0_list = [float(v) for v in a.cn0_list.split(",")]
    Path(a.data).mkdir(parents=True, exist_ok=True)
    rows = check(a) if a.what == "check" else sweep(a)
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
