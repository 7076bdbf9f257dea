"""Geometry: light-time/Sagnac vs a brute-force root find and the closed-form Sagnac term,
Doppler / carrier / code phase consistency, elevation/azimuth closed forms, visibility masks."""

import math

import numpy as np
import pytest
from scipy.optimize import brentq

from ultratight.ins.earth import elev_azim, enu_frames, llh_to_ecef
from ultratight.signals.constellation import nominal_ephemerides
from ultratight.signals.ephemeris import sat_state
from ultratight.signals.geometry import light_time, light_time_many, visible_prns
from ultratight.signals.rinex import read_rinex_nav

C = 299792458.0
WE = 7.2921151467e-5
LAMBDA = C / 1575.42e6
WEEK = 2190
TOW = 518400.0 + 1800.0
A = 6378137.0


def rot(theta, r):
    c, s = math.cos(theta), math.sin(theta)
    return np.array([c * r[0] + s * r[1], -s * r[0] + c * r[1], r[2]])


@pytest.fixture(scope="module")
def nav(rinex_path):
    return read_rinex_nav(rinex_path)


@pytest.fixture(scope="module")
def rx_static():
    return np.asarray(llh_to_ecef(math.radians(36.8103), math.radians(117.9996), 76.68))


def test_light_time_matches_brute_force_root(nav, rx_static):
    ephs = nav.select_all(WEEK, TOW)
    prns = visible_prns(ephs, rx_static, WEEK, TOW, 0.0)
    assert len(prns) >= 6
    bias_m = 1234.5
    t_rx = np.array([TOW, TOW + 0.3371, TOW + 40.0])
    worst = 0.0
    for prn in prns:
        eph = ephs[prn]
        out = light_time(eph, rx_static, np.zeros(3), WEEK, t_rx, rx_clk_bias_m=bias_m)
        for k, t in enumerate(t_rx):
            f = lambda tau: np.linalg.norm(rot(WE * tau, sat_state(eph, t - tau)[0][0]) - rx_static) - C * tau
            tau = brentq(f, 0.05, 0.1, xtol=1e-16, rtol=1e-15, maxiter=200)
            clk = sat_state(eph, t - tau)[2][0]
            worst = max(worst, abs(out["tau_s"][k] - tau) * C)
            assert out["pseudorange_m"][k] == pytest.approx(C * tau + bias_m - C * clk, abs=1e-6)
            assert out["t_tx_gps"][k] == pytest.approx(t - tau, abs=1e-12)
            assert out["t_tx_tow"][k] == pytest.approx(t - tau + clk, abs=1e-12)
    assert worst < 1e-6


def test_sagnac_term_closed_form(nav, rx_static):
    ephs = nav.select_all(WEEK, TOW)
    for prn in visible_prns(ephs, rx_static, WEEK, TOW, 5.0):
        out = light_time(ephs[prn], rx_static, np.zeros(3), WEEK, np.array([TOW]))
        r_s = sat_state(ephs[prn], out["t_tx_gps"])[0][0]          # ECEF at transmission
        plain = np.linalg.norm(r_s - rx_static)
        sagnac = WE / C * (r_s[0] * rx_static[1] - r_s[1] * rx_static[0])
        assert out["range_m"][0] - plain == pytest.approx(sagnac, abs=2e-3)
        assert abs(sagnac) > 1.0 or abs(sagnac) < 40.0


def test_rates_and_phases_are_consistent(nav, rx_static):
    ephs = nav.select_all(WEEK, TOW)
    prns = visible_prns(ephs, rx_static, WEEK, TOW, 5.0)
    h = 1e-3
    t = TOW + np.arange(0.0, 2.0, h)
    vel = np.array([-150.0, 220.0, 35.0])
    pos = rx_static + np.outer(t - TOW, vel)
    b0, drift = 3.0e4, 75.0                       # receiver clock in metres and m/s
    bias = b0 + drift * (t - TOW)
    for prn in prns:
        o = light_time(ephs[prn], pos, vel, WEEK, t, rx_clk_bias_m=bias, rx_clk_drift_mps=drift)
        pr = o["pseudorange_m"]
        num_rate = (pr[2:] - pr[:-2]) / (2 * h)
        assert np.max(np.abs(num_rate - o["range_rate_mps"][1:-1])) < 1e-4
        assert np.allclose(o["doppler_hz"], -o["range_rate_mps"] / LAMBDA, rtol=0, atol=1e-9)
        cp = o["carrier_phase_cycles"]
        num_dopp = (cp[2:] - cp[:-2]) / (2 * h)
        assert np.max(np.abs(num_dopp - o["doppler_hz"][1:-1])) < 1e-3
        # code phase of the arriving signal = C/A phase at the satellite-clock transmit time
        t_tx_sv = t + bias / C - pr / C
        assert np.max(np.abs(o["t_tx_tow"] - t_tx_sv)) < 2e-10     # 1 ulp of a TOW is 5.8e-11 s
        expect = np.mod(t_tx_sv * 1.023e6, 1023.0)
        d = np.abs(o["code_phase_chips"] - expect)
        d = np.minimum(d, 1023.0 - d)
        assert np.max(d) < 1e-3
        assert np.all((o["code_phase_chips"] >= 0) & (o["code_phase_chips"] < 1023.0))
        # code phase advances at F_CA·(1 − (range_rate − rx clock drift)/c) chips per second of
        # true time (the arriving code does not depend on the receiver clock)
        dcp = np.mod(np.diff(o["code_phase_chips"]) + 511.5, 1023.0) - 511.5   # minus 1023/ms
        rate = 1.023e6 * (1.0 - (o["range_rate_mps"] - drift) / C) - 1.023e6
        integral = np.sum(0.5 * (rate[1:] + rate[:-1])) * h
        assert abs(np.sum(dcp) - integral) < 1e-3
        # unit LOS and elevation agree with elev_azim
        el, az = elev_azim(pos, o["sat_pos_e"])
        assert np.allclose(el, o["elev_rad"], atol=1e-8)
        assert np.allclose(np.linalg.norm(o["los_e"], axis=1), 1.0)


def test_vectorised_equals_one_by_one(nav, rx_static):
    eph = nav.select(24, WEEK, TOW)
    t = TOW + np.array([0.0, 0.001, 17.3, 0.5, 3000.0])
    o = light_time(eph, rx_static, np.zeros(3), WEEK, t)
    for k in range(len(t)):
        o1 = light_time(eph, rx_static, np.zeros(3), WEEK, t[k:k + 1])
        assert abs(o1["pseudorange_m"][0] - o["pseudorange_m"][k]) < 1e-7


def test_many_satellites_equal_one_at_a_time(nav):
    """light_time_many (the generator's path: receivers prepared once, their frames passed) gives
    every value light_time gives, bit for bit, on a moving receiver with a clock."""
    ephs = nav.select_all(WEEK, TOW)
    t = TOW + np.linspace(0.0, 0.2, 41)
    pos = np.asarray(llh_to_ecef(math.radians(28.246), math.radians(102.0266), 50e3)) + np.outer(t - TOW, [300.0, -40.0, 80.0])
    vel = np.tile([300.0, -40.0, 80.0], (t.size, 1))
    bias = 12.5 + 0.3 * (t - TOW)
    frames = enu_frames(pos)
    for fr in (frames, None):
        many = light_time_many([e for e in ephs.values()], pos, vel, t, bias, 0.3, fr)
        assert len(many) == len(ephs)
        for got, eph in zip(many, ephs.values()):
            ref = light_time(eph, pos, vel, WEEK, t, bias, 0.3, fr)
            assert got.keys() == ref.keys()
            for k in ref:
                np.testing.assert_array_equal(got[k], ref[k], err_msg=k)
            # the fast path (frames given) against the general broadcasting function
            el, az = elev_azim(pos, got["sat_pos_e"])
            np.testing.assert_array_equal(got["elev_rad"], el)
            np.testing.assert_array_equal(got["azim_rad"], az)


def test_elev_azim_closed_forms():
    rx = np.array([A, 0.0, 0.0])                  # equator, lon 0: up = +x, east = +y, north = +z
    cases = [((A + 2e7, 0.0, 0.0), 90.0, None), ((A, 0.0, 1e6), 0.0, 0.0), ((A, 1e6, 0.0), 0.0, 90.0),
             ((A + 1e6, 0.0, 1e6), 45.0, 0.0), ((A + 1e6, -1e6, 0.0), 45.0, 270.0),
             ((A - 1e5, 0.0, -1e5), -45.0, 180.0)]
    for sat, el_deg, az_deg in cases:
        el, az = elev_azim(rx, np.array(sat))
        assert math.degrees(el) == pytest.approx(el_deg, abs=1e-9)
        if az_deg is not None:
            assert math.degrees(az) == pytest.approx(az_deg, abs=1e-9)
    # at a geodetic latitude the up vector is the ellipsoid normal, not the radial direction
    lat = math.radians(45.0)
    rx = np.asarray(llh_to_ecef(lat, 0.0, 0.0))
    up = np.array([math.cos(lat), 0.0, math.sin(lat)])
    el, _ = elev_azim(rx, rx + 1e7 * up)
    assert math.degrees(el) == pytest.approx(90.0, abs=1e-7)


def test_negative_mask_at_altitude_sees_more(nav):
    rx = np.asarray(llh_to_ecef(math.radians(28.2460), math.radians(102.0266), 50000.0))
    for ephs in (nav.select_all(WEEK, TOW), nominal_ephemerides(WEEK, TOW)):
        high = visible_prns(ephs, rx, WEEK, TOW, 5.0)
        low = visible_prns(ephs, rx, WEEK, TOW, -5.0, return_elev=True)
        assert len(low) > len(high)
        assert set(high) <= {p for p, _ in low}
        assert min(e for _, e in low) < 0.0
        els = [e for _, e in low]
        assert els == sorted(els, reverse=True)
        assert visible_prns(ephs, rx, WEEK, TOW, -5.0, max_count=4) == [p for p, _ in low[:4]]
    # a receiver on the ground cannot see below its horizon: the Earth blocks those lines of sight
    rx0 = np.asarray(llh_to_ecef(math.radians(28.2460), math.radians(102.0266), 0.0))
    ephs = nav.select_all(WEEK, TOW)
    assert visible_prns(ephs, rx0, WEEK, TOW, -10.0) == visible_prns(ephs, rx0, WEEK, TOW, -0.5)
