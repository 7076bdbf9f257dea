"""``ultratight integrate`` as a user waits for it: a 9-minute, 100 Hz IMU with 4 Hz GNSS, one core.

    python benchmarks/bench_integrate.py [--quick] [--repeat R] [--json OUT.json]

The data are the project's own synthetic drive, written once into a temporary folder as a user would
hand them over (not timed): a car that stands 20 s, accelerates to 15 m/s and drives 9 minutes of
straight legs and 10 °/s turns, then stops; a MEMS-grade IMU at 100 Hz (errors drawn from the grade,
seed 1) as the project's CSV with its declaration sidecar (GPS seconds of week), and an RTK-class
4 Hz solution (truth + seeded noise, σ 2 cm horizontal, 4 cm up, 3 cm/s) as an RTKLIB ``.pos``.

Timed: the whole command ``ultratight integrate --imu IMU.csv --gnss GNSS.pos --imu-grade mems
--out OUT.pos --json`` in a fresh process pinned to one core (``taskset -c 0``, ``NUMBA_NUM_THREADS=1``),
best and median of --repeat runs after one untimed warm-up run (the first run's wall time, numba cache
included, is reported separately); and the command's own split (reading, filter) from its summary.
Acceptance figure (issue: whole command ≤ 5 s on one core).  Loose forward ``kf`` and, for the cost of
smoothing, the same with ``--smooth``.
"""

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from _common import add_common_args, finish

WEEK, TOW0 = 2381, 400000.0


def _trajectory(duration_s):
    from ultratight.ins.trajectory import build_trajectory
    segs = [{"t0": 0.0, "turn_rate_dps": 0.0, "acc_mps2": 0.0}, {"t0": 20.0, "turn_rate_dps": 0.0, "acc_mps2": 1.5},
            {"t0": 30.0, "turn_rate_dps": 0.0, "acc_mps2": 0.0}]
    t, sign = 60.0, 1.0
    while t + 40.0 < duration_s - 30.0:
        segs += [{"t0": t, "turn_rate_dps": 10.0 * sign, "acc_mps2": 0.0},
                 {"t0": t + 9.0, "turn_rate_dps": 0.0, "acc_mps2": 0.0}]
        t, sign = t + 40.0, -sign
    segs += [{"t0": duration_s - 30.0, "turn_rate_dps": 0.0, "acc_mps2": -1.5},
             {"t0": duration_s - 20.0, "turn_rate_dps": 0.0, "acc_mps2": 0.0}]
    cfg = {"kind": "turns", "speed0_mps": 0.0, "heading0_deg": 30.0, "attitude": "velocity",
           "att0_deg": [0.0, 0.0, 30.0], "segments": segs}
    return build_trajectory(cfg, {"lat_deg": 40.0967, "lon_deg": -105.1472, "h_m": 1601.0}, duration_s)


def make_data(folder, duration_s, seed=1):
    """Write IMU.csv (+ sidecar) and GNSS.pos of the synthetic drive into ``folder``; returns the paths."""
    from ultratight.ins.imu import imu_errors_from_config, synthesize_imu
    from ultratight.ins.imu_data import write_imu_csv
    from ultratight.ins.imu_decl import ImuDeclaration
    from ultratight.receiver.io.solution_files import write_pos
    from ultratight.signals.observations import GnssFixes, gps_seconds

    traj = _trajectory(duration_s)
    rng = np.random.default_rng(seed)
    imu = synthesize_imu(traj, 100.0, errors=imu_errors_from_config({"preset": "mems", "rate_hz": 100.0}), rng=rng,
                         with_truth=False)
    imu.t = imu.t + TOW0
    imu.t0 = TOW0
    dec = ImuDeclaration(kind="increments", axes="FLU", time_ref="gps_tow", gps_week=WEEK, rate_hz=100.0)
    imu_path = Path(folder) / "imu.csv"
    write_imu_csv(imu_path, imu, dec)
    tg = np.arange(0.0, duration_s + 1e-9, 0.25)
    k = traj.kinematics(tg, extras=False)
    n = tg.size
    sig_p = np.tile([0.02, 0.02, 0.04], (n, 1))
    sig_v = np.full((n, 3), 0.03)
    llh = k["llh"].copy()
    d = rng.standard_normal((n, 3)) * sig_p
    rm = 6378137.0
    llh[:, 0] += d[:, 1] / rm
    llh[:, 1] += d[:, 0] / (rm * np.cos(llh[:, 0]))
    llh[:, 2] += d[:, 2]
    vel = k["vel_l"] + rng.standard_normal((n, 3)) * sig_v
    fx = GnssFixes(gps_seconds(WEEK, TOW0 + tg), llh, vel, sig_p, sig_v, np.ones(n, int), np.full(n, 9))
    gnss_path = Path(folder) / "gnss.pos"
    write_pos(gnss_path, fx, program="bench_integrate (synthetic)")
    return imu_path, gnss_path


def _command(imu_path, gnss_path, out, extra=()):
    exe = shutil.which("ultratight")
    base = [exe] if exe else [sys.executable, "-m", "ultratight.receiver.cli"]
    pin = ["taskset", "-c", "0"] if shutil.which("taskset") else []
    return pin + base + ["integrate", "--imu", str(imu_path), "--gnss", str(gnss_path), "--imu-grade", "mems",
                         "--out", str(out), "--json", *extra]


def _run(cmd):
    env = dict(os.environ, NUMBA_NUM_THREADS="1")
    t0 = time.perf_counter()
    p = subprocess.run(cmd, capture_output=True, text=True, env=env)
    wall = time.perf_counter() - t0
    if p.returncode != 0:
        raise SystemExit(f"bench_integrate: the command failed ({p.returncode}): {p.stderr.strip()[-400:]}")
    return wall, json.loads(p.stdout)


def main():
    ap = add_common_args(argparse.ArgumentParser(description=__doc__.splitlines()[0]))
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    duration = 120.0 if args.quick else 540.0
    repeat = 1 if args.quick else max(1, args.repeat)
    res = {"duration_s": duration, "imu_rate_hz": 100.0, "gnss_rate_hz": 4.0, "cores": 1}
    with tempfile.TemporaryDirectory(prefix="bench-integrate-") as tmp:
        imu_path, gnss_path = make_data(tmp, duration)
        for name, extra in (("forward_kf", ()), ("smoothed_kf", ("--smooth",))):
            cmd = _command(imu_path, gnss_path, Path(tmp) / f"{name}.pos", extra)
            first, _ = _run(cmd)
            runs = [_run(cmd) for _ in range(repeat)]
            walls = [w for w, _ in runs]
            summ = runs[int(np.argmin(walls))][1]
            res[name] = {"first_run_s": first, "best_s": min(walls), "median_s": statistics.median(walls),
                         "read_s": summ["timing_s"]["read_s"], "filter_s": summ["timing_s"]["filter_s"],
                         "epochs_used": summ["gnss"]["epochs_used"]}
            print(f"integrate {duration:.0f} s at 100 Hz + 4 Hz GNSS, one core, {name}: best {min(walls):.2f} s, "
                  f"median {statistics.median(walls):.2f} s (first run {first:.2f} s; inside: reading "
                  f"{summ['timing_s']['read_s']:.2f} s, filter {summ['timing_s']['filter_s']:.2f} s)")
    finish(args, res)


if __name__ == "__main__":
    main()
