"""docs/integrate.md's walk_0827 table: ``ultratight integrate`` with every core, with and without NHC and
the χ² gate, forward and smoothed, through the authors' two outage windows; plus the tight runs.

    python benchmarks/acceptance_integrate_walk.py [--quick] [--json OUT.json]

Reads ../shared/data/real-imu-gnss/walk_0827 in place (``$ULTRATIGHT_DATA`` or the folder beside the
checkout); prints one markdown row per run, in the order of the document's table, the tight run's line
(the signals and ionosphere handling of its pseudoranges, the horizontal RMS, the mean error and the
scatter about it) and the 20 s window's lines (tight with three satellites kept, with none, loose; the
tight lines also give the error's growth from the window's start, docs/gins-tight.md).  ``--quick``: the
kf rows only.  Each run is the command as a user types it (a subprocess), declared with what the
recording's authors state (tests/test_integrate_cli.py: AUTHORS).
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from _common import add_common_args, finish

ROOT = Path(__file__).resolve().parents[1]
AUTHORS = ["--imu-axes", "FRD", "--mount", "180", "0", "-90", "--lever-arm", "0", "-0.05", "0",
           "--imu-gyro-noise", "0.0038", "--imu-accel-noise", "70", "--imu-accel-bias-rw", "7",
           "--imu-gyro-bias-rw", "3.8e-5", "--imu-gyro-bias", "0.2", "--imu-accel-bias", "0.2"]
OUTAGES = ["--outage", "408664.75:14.75", "--outage", "408710.00:14.5"]
FILTERS = ("kf", "akf", "iakf", "chi2-newton", "afm-aukf")


def walk_dir():
    base = os.environ.get("ULTRATIGHT_DATA") or str(ROOT.parent / "shared" / "data")
    return Path(base) / "real-imu-gnss" / "walk_0827"


def run(args):
    p = subprocess.run([sys.executable, "-m", "ultratight.receiver.cli", *args, "--json"], capture_output=True,
                       text=True, check=False)
    if p.returncode != 0:
        return {"error": p.stderr.strip()[-300:]}
    return json.loads(p.stdout)


def main():
    ap = add_common_args(argparse.ArgumentParser(description=__doc__.splitlines()[0]))
    args = ap.parse_args()
    w = walk_dir()
    if not w.is_dir():
        print(f"walk_0827 not found at {w}: nothing to run")
        finish(args, {"skipped": str(w)})
        return
    ref = ["--reference", str(w / "gnss_1730_sf.pos")]
    base = ["integrate", "--imu", str(w / "imu_1730.csv"), *AUTHORS]
    rows = []
    print("| filter | gate | NHC | forward H / V (m) | 3σ | smoothed H / V (m) | 3σ | outside (m) | used / rejected |")
    for f in FILTERS[:1] if args.quick else FILTERS:
        for gate in ("1e-3", "off"):
            for nhc in ((), ("--nhc",)):
                s = run(base + ["--gnss", str(w / "gnss_1730_sf.pos"), "--filter", f, "--gate", gate, *nhc,
                                "--smooth", *OUTAGES, *ref])
                if "error" in s:
                    print(f"| {f} | {gate} | {'yes' if nhc else '—'} | failed: {s['error']} |")
                    continue
                e, fw = s["evaluation"], s["evaluation"]["forward"]
                row = {"filter": f, "gate": gate, "nhc": bool(nhc), "forward": fw, "smoothed": e,
                       "used": s["gnss"]["epochs_used"], "rejected": s["gnss"]["epochs_rejected"]}
                rows.append(row)
                print(f"| {f} | {gate} | {'yes' if nhc else '—'} | {fw['outage_max_h_rms_m']:.2f} / "
                      f"{fw['outage_max_v_rms_m']:.2f} | {100 * fw['within_3sigma']:.0f} % | "
                      f"{e['outage_max_h_rms_m']:.2f} / {e['outage_max_v_rms_m']:.2f} | {100 * e['within_3sigma']:.0f} % | "
                      f"{fw['rms_outside_h_m']:.2f} | {row['used']} / {row['rejected']} |", flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "tight.pos"
        tight = run(base + ["--gnss", str(w / "gnss_1730.ubx"), "--coupling", "tight", "--reference-geoid", "-21.39",
                            *ref, "--out", str(out)])
        if "error" not in tight:
            d = horizontal_errors(out, w / "gnss_1730_sf.pos")
            mean = d[:, 1:].mean(axis=0)
            scatter = float(np.sqrt(np.mean(np.sum((d[:, 1:] - mean) ** 2, axis=1))))
            tight["evaluation"]["mean_error_en_m"] = [float(v) for v in mean]
            tight["evaluation"]["scatter_h_m"] = scatter
            print(f"tight, kf, all satellites ({'; '.join(tight['gnss']['warnings']) or 'no warning'}): "
                  f"{tight['evaluation']['rms_outside_h_m']:.2f} m horizontal RMS at the "
                  f"{tight['evaluation']['reference_fixed_epochs']} fixed epochs; mean error E {mean[0]:+.2f} "
                  f"N {mean[1]:+.2f} m, scatter about it {scatter:.2f} m")
    window = window_runs(base, w, ref)
    finish(args, {"walk_loose": rows, "walk_tight": tight.get("evaluation", tight), "walk_window": window})


def horizontal_errors(sol_path, ref_path, t_from=None, t_to=None, geoid=-21.39):
    """(t, east, north) of a solution .pos minus the reference's fixed epochs (seconds of week within
    [t_from, t_to] when given; the solution's nearest output within 51 ms; reference heights above mean
    sea level, ``geoid`` the undulation)."""
    from ultratight.ins.earth import dcm_ecef_from_enu, llh_to_ecef
    from ultratight.receiver.io.solution_files import read_pos
    ref, sol = read_pos(ref_path), read_pos(sol_path)
    rows = []
    for k in np.flatnonzero(ref.quality == 1):
        tow = ref.t[k] % 604800.0
        if (t_from is not None and tow < t_from - 0.01) or (t_to is not None and tow > t_to + 0.01):
            continue
        j = int(np.argmin(np.abs(sol.t - ref.t[k])))
        if abs(sol.t[j] - ref.t[k]) <= 0.051:
            lat, lon, h = ref.llh[k]
            d = np.asarray(llh_to_ecef(*sol.llh[j])) - np.asarray(llh_to_ecef(lat, lon, h + geoid))
            rows.append((tow, *(dcm_ecef_from_enu(lat, lon).T @ d)[:2]))
    return np.array(rows)


def window_runs(base, w, ref):
    """docs/integrate.md: a 20 s window at 408710 s (kf, NHC) with three satellites kept in the tight
    run, with none, and loose coupling (no gate) on the RTK solution; the largest horizontal error in it."""
    tight = ["--gnss", str(w / "gnss_1730.ubx"), "--coupling", "tight", "--reference-geoid", "-21.39"]
    out = {}
    for label, extra in (("tight, 3 satellites kept", tight + ["--outage-keep-sats", "3"]),
                         ("tight, none kept", tight),
                         ("loose, no gate, none kept", ["--gnss", str(w / "gnss_1730_sf.pos"), "--gate", "off"])):
        with tempfile.TemporaryDirectory() as tmp:
            sol = Path(tmp) / "window.pos"
            s = run(base + extra + ["--outage", "408710:20", "--filter", "kf", "--nhc", *ref, "--out", str(sol)])
            if "error" in s:
                print(f"20 s window at 408710 s, kf, NHC, {label}: failed: {s['error']}")
                continue
            o = s["evaluation"]["outages"][0]
            growth = ""
            if label.startswith("tight"):
                d = horizontal_errors(sol, w / "gnss_1730_sf.pos", 408710.0, 408730.0)
                o["growth_h_m"] = float(np.max(np.hypot(d[:, 1] - d[0, 1], d[:, 2] - d[0, 2])))
                growth = f", {o['growth_h_m']:.2f} m growth from the window's start"
        out[label] = o
        print(f"20 s window at 408710 s, kf, NHC, {label}: largest horizontal error {o['max_h_m']:.2f} m"
              f"{growth} ({o['reference_epochs']} reference epochs)", flush=True)
    return out


if __name__ == "__main__":
    main()
