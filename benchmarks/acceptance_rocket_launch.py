"""Ultra-tight on a recording as a user has it: the rocket-launch scenario (docs/ultratight.md).

    python benchmarks/acceptance_rocket_launch.py [--cn0-list 45,30] [--seed 3] [--duration S] [--fs HZ]
        [--no-tropo] [--data DIR] [--quick] [--json OUT.json] [-- EXTRA PROCESS FLAGS]

Per C/N0: ``ultratight generate`` writes the rocket-launch scenario (60 s on the pad, then the launch
to 1177 m/s; broadcast ionosphere and Saastamoinen troposphere on the signals; data bits the receiver
cannot know: random subframes 4-5, ``[nav] data = "lnav-random-sf45"``; the IMU 0.5 m below the
antenna along the body's x axis). Then a *user* directory is made with what a user of such a
recording has and nothing else:

* ``rec.ci8`` (a link to the generated samples) and a sidecar with the sampling parameters and the
  start time only (no generator block, no PRN list);
* ``nav.rnx``: RINEX 3.04 navigation of the constellation with the broadcast Klobuchar coefficients;
* ``imu.csv`` in FRD axes with its declaration sidecar (axes, units, lever arm), no truth.

``ultratight process rec.ci8 --mode ultratight --imu imu.csv --ephemeris nav.rnx`` runs there with
its defaults (no other flags) and writes ``res.h5``; only then is the generator's truth (the IMU
file's truth group, the IMU point) read to score the SINS-rate solution: 3D position and velocity
RMS over the whole run from the hand-over, the largest error, the fraction of rows whose ENU error
lies inside the reported 3σ on every axis, channels lost, the integrity state, the wall time.
``--fs`` samples the recording at another rate than the scenario's 4 MHz (e.g. 2.6e6, the rate of
common front ends and of other simulators' files); ``--no-tropo`` leaves the troposphere out of the
signals (as some simulators do; the ionosphere stays), the receiver still run with its defaults.
"""

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from _common import add_common_args, finish

LEVER_FLU_M = [-0.5, 0.0, 0.0]    # the antenna 0.5 m from the IMU along the body's -x (tail) axis
TARGETS = {45.0: (1.0, 0.1), 30.0: (2.5, 0.15)}     # 3D position RMS (m), velocity RMS (m/s)


def scenario_text(duration_s, tropo=True):
    from ultratight.config import locate_scenario

    path = locate_scenario("rocket-launch")
    txt = path.read_text()
    # the trajectory file beside the built-in scenario (a relative path reads from the TOML's folder)
    txt = txt.replace('path = "rocket-launch.csv"', f'path = "{path.with_suffix(".csv")}"')
    txt, n = re.subn(r"\[nav\]\n", '[nav]\ndata = "lnav-random-sf45"\n', txt)
    assert n == 1, "rocket-launch.toml: no [nav] table"
    txt, n = re.subn(r"\[imu\]\n", f"[imu]\nlever_arm_m = {LEVER_FLU_M}\n", txt)
    assert n == 1, "rocket-launch.toml: no [imu] table"
    if duration_s:
        txt = re.sub(r"(?m)^duration_s = .*$", f"duration_s = {float(duration_s)}", txt)
    if not tropo:
        txt, n = re.subn(r'(?m)^tropo = "saastamoinen"$', 'tropo = "off"', txt)
        assert n == 1, "rocket-launch.toml: no [atmosphere] tropo line"
    return txt


def user_directory(gen, stem, user):
    """The user's files from the generated ones (see the module docstring)."""
    from ultratight.ins.imu_data import read_imu_h5, write_imu_csv
    from ultratight.ins.imu_decl import ImuDeclaration
    from ultratight.receiver.deep.atmosphere_terms import broadcast_of_generator
    from ultratight.receiver.io.rinex_out import write_rinex_nav
    from ultratight.signals.constellation import nominal_ephemerides

    side = json.loads((gen / f"{stem}.ci8.json").read_text())
    keep = ("format", "fs_hz", "if_hz", "is_complex", "iq_conj", "start_week", "start_tow_s", "bits")
    (user / "rec.ci8.json").write_text(json.dumps({k: side[k] for k in keep if k in side}))
    os.symlink((gen / f"{stem}.ci8").resolve(), user / "rec.ci8")
    alpha, beta = broadcast_of_generator(side.get("generator"))
    write_rinex_nav(user / "nav.rnx", list(nominal_ephemerides(side["start_week"], side["start_tow_s"]).values()),
                    iono=(alpha, beta) if alpha is not None else None)
    imu = read_imu_h5(gen / f"{stem}.imu.h5")
    truth = imu.truth
    imu.truth = None
    # the declaration a user writes: axes, lever arm (in those axes) and the grade of the unit
    side_path = write_imu_csv(user / "imu.csv", imu, ImuDeclaration(axes="FRD"))
    side = json.loads(side_path.read_text())
    side["noise"] = {"grade": "tactical"}
    side_path.write_text(json.dumps(side, indent=2))
    return truth


def score(res_h5, truth):
    """Errors of the SINS-rate solution against the IMU point's truth."""
    import h5py

    from ultratight.ins.earth import dcm_ecef_from_enu, llh_to_ecef_batch

    with h5py.File(res_h5) as f:
        t = f["sins/t_s"][()]
        llh = f["sins/llh"][()]
        vel = f["sins/vel_l"][()]
        sig = f["sins/sigma_pos_l_m"][()]
        info = json.loads(f.attrs["info_json"])
    tt = np.asarray(truth["t"], float)
    ref_llh = np.stack([np.interp(t, tt, truth["llh"][:, i]) for i in range(3)], 1)
    ref_vel = np.stack([np.interp(t, tt, truth["vel_l"][:, i]) for i in range(3)], 1)
    d_e = llh_to_ecef_batch(llh) - llh_to_ecef_batch(ref_llh)
    C = dcm_ecef_from_enu(ref_llh[0, 0], ref_llh[0, 1])
    enu = d_e @ C
    e3 = np.linalg.norm(d_e, axis=1)
    ev = np.linalg.norm(vel - ref_vel, axis=1)       # ENU at the solution and the truth: same frame to 1e-6
    inside = np.all(np.abs(enu) <= 3.0 * sig, axis=1)
    big = (e3 > 20.0) & (np.linalg.norm(sig, axis=1) < 2.0)
    return {"rows": int(t.size), "t_from_s": float(t[0]), "t_to_s": float(t[-1]),
            "rms_3d_m": float(np.sqrt(np.mean(e3 ** 2))), "max_3d_m": float(e3.max()),
            "rms_vel_mps": float(np.sqrt(np.mean(ev ** 2))), "max_vel_mps": float(ev.max()),
            "within_3sigma": float(np.mean(inside)),
            "rows_over_20m_with_sigma_under_2m": int(big.sum()),
            "integrity": (info.get("integrity") or {}).get("state")}


def run_one(data, cn0, seed, duration_s, extra, fs_hz=None, tropo=True):
    from ultratight.receiver.cli import main as cli_main

    base = data / (f"cn0_{cn0:g}_seed{seed}" + (f"_fs{fs_hz:g}" if fs_hz else "") + ("" if tropo else "_notropo"))
    gen, user = base / "gen", base / "user"
    for p in (gen, user):
        p.mkdir(parents=True, exist_ok=True)
    (base / "rl.toml").write_text(scenario_text(duration_s, tropo))
    t0 = time.perf_counter()
    if not (gen / "rl.ci8").is_file():
        fs_args = ["--fs", repr(float(fs_hz))] if fs_hz else []
        assert cli_main(["generate", str(base / "rl.toml"), "--cn0", str(cn0), "--seed", str(seed), "--out",
                         str(gen / "rl"), "--no-progress", *fs_args]) == 0
    gen_s = time.perf_counter() - t0
    for p in user.iterdir():
        p.unlink()
    truth = user_directory(gen, "rl", user)
    assert sorted(p.name for p in user.iterdir()) == ["imu.csv", "imu.csv.json", "nav.rnx", "rec.ci8",
                                                      "rec.ci8.json"], "the user directory holds more than a user has"
    out = base / "res.h5"
    cmd = [sys.executable, "-m", "ultratight.receiver.cli", "process", "rec.ci8", "--mode", "ultratight", "--imu",
           "imu.csv", "--ephemeris", "nav.rnx", "--json", "--no-progress", "--out", str(out), *extra]
    t0 = time.perf_counter()
    r = subprocess.run(cmd, cwd=user, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    row = {"cn0_dbhz": cn0, "seed": seed, "fs_hz": fs_hz or 4e6, "tropo_in_signal": tropo,
           "generate_s": round(gen_s, 1),
           "wall_s": round(wall, 1),
           "exit": r.returncode, "stderr": r.stderr.strip().splitlines()[-3:]}
    if r.returncode in (0, 3) and out.is_file():
        summ = json.loads(r.stdout)
        row.update(prns=summ["prns"], startup=summ["startup"], bits=summ["bit_strategy"],
                   assisted=summ.get("assisted"), lock_lost_channels=summ["lock_lost_channels"],
                   handover_t_s=(summ.get("handover") or {}).get("handover_t_s"),
                   troposphere=((summ.get("handover") or {}).get("troposphere") or {}).get("troposphere"))
        row.update(score(out, truth))
        pos_t, vel_t = TARGETS.get(float(cn0), (None, None))
        if pos_t is not None:
            row["met"] = bool(row["rms_3d_m"] <= pos_t and row["rms_vel_mps"] <= vel_t
                              and not row["lock_lost_channels"] and (cn0 < 45 or row["within_3sigma"] >= 0.95))
    return row


def main():
    ap = add_common_args(argparse.ArgumentParser(description=__doc__.splitlines()[0]))
    ap.add_argument("--cn0-list", default="45,30", help="C/N0 values, dB-Hz (default 45,30)")
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--duration", type=float, default=None, help="seconds (default: the scenario's 100 s)")
    ap.add_argument("--fs", type=float, default=None, help="sampling rate of the recording, Hz (default: 4 MHz)")
    ap.add_argument("--no-tropo", action="store_true", help="no troposphere on the signals")
    ap.add_argument("--data", default=None, help="folder for the generated files (kept; reused when present)")
    ap.add_argument("extra", nargs="*", help="further process flags (after --)")
    args = ap.parse_args()
    cn0s = [float(x) for x in args.cn0_list.split(",")]
    duration = args.duration if args.duration else (75.0 if args.quick else None)
    if args.quick:
        cn0s = cn0s[:1]
    tmp = None if args.data else tempfile.TemporaryDirectory(prefix="ut_rocket_")
    data = Path(args.data or tmp.name)
    rows = [run_one(data, c, args.seed, duration, args.extra, args.fs, not args.no_tropo) for c in cn0s]
    print("rocket-launch, a user's files, `process --mode ultratight` with its defaults")
    print(f"{'C/N0':>5} {'exit':>4} {'3D RMS':>8} {'max':>8} {'vel RMS':>8} {'in 3σ':>6} {'lost':>6} "
          f"{'integrity':>9} {'wall':>7}  met")
    for r in rows:
        if "rms_3d_m" not in r:
            print(f"{r['cn0_dbhz']:5.0f} {r['exit']:4d}  no solution: {' | '.join(r['stderr'])}")
            continue
        print(f"{r['cn0_dbhz']:5.0f} {r['exit']:4d} {r['rms_3d_m']:7.2f}m {r['max_3d_m']:7.1f}m "
              f"{r['rms_vel_mps']:7.3f}  {100 * r['within_3sigma']:5.1f}% {len(r['lock_lost_channels']):6d} "
              f"{str(r['integrity']):>9} {r['wall_s']:6.1f}s  {r.get('met')}")
    finish(args, {"rows": rows})
    if tmp is not None:
        tmp.cleanup()


if __name__ == "__main__":
    main()
