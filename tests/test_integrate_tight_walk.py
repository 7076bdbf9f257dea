"""``ultratight integrate --coupling tight`` on the real walk's u-blox log (../shared/data/real-imu-gnss/
walk_0827; skipped without it), declared with what the recording's authors state (tests/test_integrate_cli.py
AUTHORS).  The log is read as by default: the L1 C/A + L2C ionosphere-free pseudoranges of seven satellites
(four LNAV ephemerides, three CNAV ones).  Reference: the RTK solution's fixed epochs, heights above mean
sea level (the receiver's own NAV-PVT puts the geoid 21.39 m below the ellipsoid).

What the figures are made of (docs/gins-tight.md): the RTK track itself sits 6-7 m from where the broadcast
orbits put the antenna — GPS's L1/L2C and Galileo's E1/E5a ionosphere-free single-point solutions, two
constellations with their own orbits, clocks and group delays, both see it (mean horizontal offsets
6.6 m and 6.6 m) — so the horizontal RMS against it cannot go below that offset whatever the filter; the
tests assert the RMS reached, the scatter about the mean error (what the filter controls) and, through a
20 s window with three satellites, the error's growth from the window's start against loose coupling's
3.5 m with no GNSS at all."""

import json
import math
import subprocess
import sys

import numpy as np
import pytest
from conftest import SHARED_DATA

WALK = SHARED_DATA / "real-imu-gnss" / "walk_0827"
needs_walk = pytest.mark.skipif(not (WALK / "gnss_1730.ubx").is_file(), reason=f"real walk data not found at {WALK}")
AUTHORS = ("--imu-axes", "FRD", "--mount", "180", "0", "-90", "--lever-arm", "0", "-0.05", "0",
           "--imu-gyro-noise", "0.0038", "--imu-accel-noise", "70", "--imu-accel-bias-rw", "7",
           "--imu-gyro-bias-rw", "3.8e-5", "--imu-gyro-bias", "0.2", "--imu-accel-bias", "0.2")
GEOID = -21.39
LOOSE_NONE_WINDOW_MAX_H_M = 3.5          # docs/integrate.md: loose, kf, NHC, no gate, no GNSS in the window


def _run(tmp_path, *extra):
    out = tmp_path / "tight.pos"
    args = [sys.executable, "-m", "ultratight.receiver.cli", "integrate", "--imu", str(WALK / "imu_1730.csv"),
            *AUTHORS, "--gnss", str(WALK / "gnss_1730.ubx"), "--coupling", "tight", "--reference-geoid", str(GEOID),
            "--reference", str(WALK / "gnss_1730_sf.pos"), "--out", str(out), "--json", *extra]
    res = subprocess.run(args, capture_output=True, text=True, timeout=600, check=False)
    assert res.returncode == 0, res.stderr
    return json.loads(res.stdout), out


def _errors_enu(sol_path, t_from=None, t_to=None):
    """(t, east, north) of the solution minus the reference at the reference's fixed epochs (seconds of
    week in [t_from, t_to] when given); the solution's nearest output within 51 ms (it is written at the
    IMU's epochs)."""
    from ultratight.ins.earth import dcm_ecef_from_enu, llh_to_ecef
    from ultratight.receiver.io.solution_files import read_pos
    ref, sol = read_pos(WALK / "gnss_1730_sf.pos"), read_pos(sol_path)
    rows = []
    for k in np.flatnonzero(ref.quality == 1):
        tow = ref.t[k] % 604800.0
        if (t_from is not None and tow < t_from - 0.01) or (t_to is not None and tow > t_to + 0.01):
            continue
        j = int(np.argmin(np.abs(sol.t - ref.t[k])))
        if abs(sol.t[j] - ref.t[k]) > 0.051:
            continue
        lat, lon, h = ref.llh[k]
        d = np.asarray(llh_to_ecef(*sol.llh[j])) - np.asarray(llh_to_ecef(lat, lon, h + GEOID))
        rows.append((tow, *(dcm_ecef_from_enu(lat, lon).T @ d)[:2]))
    return np.array(rows)


@needs_walk
def test_tight_walk_with_all_satellites(tmp_path):
    """Measured (2026-11-27): 7.05 m horizontal RMS at the fixed epochs after the alignment (10.5 m on
    L1 C/A with four satellites before), mean error (E, N) = (+6.21, +3.20) m — the RTK track's offset
    (module doc) — and a scatter about that mean of 1.01 m.  The acceptance value of 3 m RMS is not
    reached: the offset alone is more.  Bounds: 1.1 × the measured RMS and scatter."""
    s, out = _run(tmp_path)
    e = s["evaluation"]
    assert s["gnss"]["source"].endswith("7 ephemeris PRNs") and e["reference_fixed_epochs"] >= 290
    assert any("ionosphere-free" in w for w in s["gnss"]["warnings"])      # rows without L2C left out
    assert not any("Klobuchar" in w for w in s["gnss"]["warnings"])
    d = _errors_enu(out)
    mean = d[:, 1:].mean(axis=0)
    scatter = float(np.sqrt(np.mean(np.sum((d[:, 1:] - mean) ** 2, axis=1))))
    print(f"\ntight walk: horizontal RMS {e['rms_outside_h_m']:.2f} m, mean error E {mean[0]:+.2f} N {mean[1]:+.2f} m, "
          f"scatter {scatter:.2f} m over {len(d)} epochs")
    assert e["rms_outside_h_m"] <= 1.1 * 7.05
    assert scatter <= 1.1 * 1.01
    assert math.hypot(*mean) > 5.0                      # the offset, not the filter, makes the RMS


@needs_walk
def test_tight_walk_three_satellites_through_a_window(tmp_path):
    """Three satellites kept (the highest) for 20 s from 408710 s of week (kf, NHC): measured largest
    horizontal error in the window 7.94 m (the track offset of about 7 m at the window's start included)
    and 1.77 m of growth from the window's start; loose coupling with no GNSS at all drifts 3.5 m over the same
    window (docs/integrate.md) — the tight solution's growth must stay below it."""
    s, out = _run(tmp_path, "--outage", "408710:20", "--outage-keep-sats", "3", "--filter", "kf", "--nhc")
    (o,) = s["evaluation"]["outages"]
    d = _errors_enu(out, 408710.0, 408730.0)
    growth = np.hypot(d[:, 1] - d[0, 1], d[:, 2] - d[0, 2])
    print(f"\n20 s window, 3 satellites: largest horizontal error {o['max_h_m']:.2f} m, growth from the start "
          f"{growth.max():.2f} m ({len(d)} fixed epochs, first at {d[0, 0]:.2f} s)")
    assert len(d) >= 60 and d[0, 0] < 408710.1
    assert growth.max() < LOOSE_NONE_WINDOW_MAX_H_M
    assert o["max_h_m"] <= 1.1 * 7.94
