"""Satellite position/velocity/clock from broadcast ephemeris vs an independent scalar evaluation
of IS-GPS-200 Table 20-IV written here (plain math, bisection Kepler solver)."""

import math

import numpy as np
import pytest

from ultratight.signals.ephemeris import Ephemeris, in_fit_interval, sat_clock, sat_state
from ultratight.signals.rinex import read_rinex_nav

MU = 3.986005e14
WE = 7.2921151467e-5
F = -4.442807633e-10


def _kepler_bisect(m, e):
    lo, hi = m - 1.0, m + 1.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if mid - e * math.sin(mid) - m > 0:
            hi = mid
        else:
            lo = mid
    return 0.5 * (lo + hi)


def reference_state(eph, tk, t_minus_toc):
    """Table 20-IV for one tk (no wrapping: the caller gives tk); returns (xyz, clk_bias)."""
    a = eph.sqrt_a ** 2
    n = math.sqrt(MU / a ** 3) + eph.delta_n
    m = eph.m0 + n * tk
    ea = _kepler_bisect(m, eph.e)
    nu = 2.0 * math.atan(math.sqrt((1 + eph.e) / (1 - eph.e)) * math.tan(ea / 2.0))
    phi = nu + eph.omega
    u = phi + eph.cus * math.sin(2 * phi) + eph.cuc * math.cos(2 * phi)
    r = a * (1 - eph.e * math.cos(ea)) + eph.crs * math.sin(2 * phi) + eph.crc * math.cos(2 * phi)
    i = eph.i0 + eph.idot * tk + eph.cis * math.sin(2 * phi) + eph.cic * math.cos(2 * phi)
    x1, y1 = r * math.cos(u), r * math.sin(u)
    om = eph.omega0 + (eph.omega_dot - WE) * tk - WE * eph.toe
    xyz = (x1 * math.cos(om) - y1 * math.cos(i) * math.sin(om),
           x1 * math.sin(om) + y1 * math.cos(i) * math.cos(om),
           y1 * math.sin(i))
    dt = t_minus_toc
    clk = (eph.af0 + eph.af1 * dt + eph.af2 * dt * dt + F * eph.e * eph.sqrt_a * math.sin(ea)
           - eph.tgd)
    return np.array(xyz), clk


@pytest.fixture(scope="module")
def nav(rinex_path):
    return read_rinex_nav(rinex_path)


def test_position_and_clock_match_independent_evaluation(nav):
    max_pos, max_clk, count = 0.0, 0.0, 0
    for prn, ephs in nav.ephemerides.items():
        for eph in ephs[::3]:
            offsets = np.array([-7199.0, -3600.5, -1.0, 0.0, 1234.5, 7200.0])
            pos, _, clk, _ = sat_state(eph, eph.toe + offsets)
            for k, dt in enumerate(offsets):
                ref, ref_clk = reference_state(eph, dt, eph.toe + dt - eph.toc)
                max_pos = max(max_pos, np.max(np.abs(pos[k] - ref)))
                max_clk = max(max_clk, abs(clk[k] - ref_clk))
                count += 1
    assert count > 500
    assert max_pos < 1e-3, max_pos
    assert max_clk < 1e-15, max_clk


def test_velocity_and_drift_match_central_difference(nav):
    h = 0.01
    worst_v, worst_d = 0.0, 0.0
    for prn in nav.prns:
        eph = nav.ephemerides[prn][0]
        t = eph.toe + np.linspace(-7000.0, 7000.0, 15)
        _, vel, _, drift = sat_state(eph, t)
        pp, _, cp, _ = sat_state(eph, t + h)
        pm, _, cm, _ = sat_state(eph, t - h)
        worst_v = max(worst_v, np.max(np.abs((pp - pm) / (2 * h) - vel)))
        worst_d = max(worst_d, np.max(np.abs((cp - cm) / (2 * h) - drift)))
        speed = np.linalg.norm(vel, axis=1)
        assert np.all((speed > 2500.0) & (speed < 4500.0))   # ECEF speed of a GPS satellite
    assert worst_v < 1e-3, worst_v
    assert worst_d < 1e-13, worst_d


def test_week_rollover_wraps_tk():
    eph = Ephemeris(prn=5, week=2190, toe=604000.0, toc=604000.0, sqrt_a=5153.7, e=0.01, i0=0.96,
                    omega0=1.0, omega=-2.0, m0=0.5, delta_n=4e-9, idot=1e-10, omega_dot=-8e-9,
                    crs=50.0, crc=200.0, cus=5e-6, cuc=-3e-6, cis=1e-7, cic=-1e-7,
                    af0=1e-4, af1=1e-11, af2=1e-19, tgd=5e-9)
    # t = 200 s into the next week is tk = +1000 s; t = 603000 is tk = -1000 s
    pos, _, clk, _ = sat_state(eph, np.array([200.0, 603000.0]))
    for k, tk in enumerate((1000.0, -1000.0)):
        ref, ref_clk = reference_state(eph, tk, tk)
        assert np.max(np.abs(pos[k] - ref)) < 1e-3
        assert abs(clk[k] - ref_clk) < 1e-16
    bias, drift = sat_clock(eph, 200.0)
    assert bias[0] == pytest.approx(clk[0], abs=1e-18)
    assert in_fit_interval(eph, 2191, 200.0)
    assert not in_fit_interval(eph, 2191, 604000.0 - 604800.0 + 3 * 3600.0)


def test_scalar_time_gives_one_row(nav):
    eph = nav.ephemerides[1][0]
    pos, vel, clk, drift = sat_state(eph, eph.toe)
    assert pos.shape == (1, 3) and vel.shape == (1, 3) and clk.shape == (1,) and drift.shape == (1,)
    r = np.linalg.norm(pos[0])
    assert 2.55e7 < r < 2.70e7


def test_gpstime_helpers():
    from ultratight.signals.gpstime import (datetime_to_gps, full_week, normalize, wrap_week_diff,
                                            week_of_nearby)
    assert datetime_to_gps(2022, 1, 1) == (2190, 518400.0)       # per the data README
    assert datetime_to_gps(1980, 1, 6) == (0, 0.0)
    assert wrap_week_diff(302401.0) == -302399.0
    assert wrap_week_diff(-302401.0) == 302399.0
    assert wrap_week_diff(100.0) == 100.0
    assert np.allclose(wrap_week_diff(np.array([604000.0, -604000.0])), [-800.0, 800.0])
    assert normalize(2190, 604800.0 + 5.0) == (2191, 5.0)
    assert normalize(2191, -12.0) == (2190, 604788.0)
    # 10-bit week: 2190 % 1024 = 142
    assert full_week(142, 2190) == 2190
    assert full_week(142, 2190 + 400) == 2190
    assert full_week(1023, 2048) == 2047                          # just before the 2nd rollover
    assert full_week(0, 2047) == 2048
    assert week_of_nearby(2190, 604000.0, 100.0) == 2191
    assert week_of_nearby(2191, 100.0, 604000.0) == 2190
