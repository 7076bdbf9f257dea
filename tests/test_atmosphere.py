"""Atmosphere models (Klobuchar, Saastamoinen), LNAV subframe 4 page 18, the generator's delays
and the PVT corrections."""

import math

import h5py
import numpy as np
import pytest

from ultratight.constants import C, LAMBDA_L1
from ultratight.errors import ConfigError
from ultratight.signals.atmosphere import (AtmosphereModel, klobuchar_delay_s, mapping, saastamoinen_delay_m,
                                           saastamoinen_zenith_m, standard_atmosphere)

# broadcast coefficients of the IGS file brdc0010.22n (2022-01-01)
ALPHA = (1.211e-08, -7.451e-09, -5.960e-08, 1.192e-07)
BETA = (1.167e+05, -2.458e+05, -6.554e+04, 1.114e+06)


# ----------------------------------------------------------------------------- Klobuchar
def test_klobuchar_night_is_the_constant_5ns_times_the_slant_factor():
    # IS-GPS-200 20.3.3.5.2.5: |x| >= 1.57 -> T = F * 5e-9 s, F = 1 + 16 (0.53 - E)^3
    for el_deg in (10.0, 30.0, 90.0):
        e = el_deg / 180.0
        f = 1.0 + 16.0 * (0.53 - e) ** 3
        # local time at the pierce point ~02:00 (lon 0, tow 2 h into a day)
        t = klobuchar_delay_s(ALPHA, BETA, 0.0, 0.0, math.radians(el_deg), 0.0, 7200.0)
        assert t == pytest.approx(f * 5e-9, rel=1e-12)


def test_klobuchar_zenith_at_1400_local_is_5ns_plus_amplitude():
    # zenith: psi = 0.0137/(0.5 + 0.11) - 0.022 = 0.000459 semicircles; at 14:00 local (x = 0) the
    # delay is F (5 ns + AMP(phi_m))
    lat, lon = math.radians(30.0), 0.0
    el = math.pi / 2
    psi = 0.0137 / (0.5 + 0.11) - 0.022
    phi_i = 30.0 / 180.0 + psi            # azimuth 0: pierce point north of the user
    phi_m = phi_i + 0.064 * math.cos((0.0 - 1.617) * math.pi)
    amp = sum(a * phi_m ** n for n, a in enumerate(ALPHA))
    f = 1.0 + 16.0 * (0.53 - 0.5) ** 3
    t = klobuchar_delay_s(ALPHA, BETA, lat, lon, el, 0.0, 50400.0)
    assert t == pytest.approx(f * (5e-9 + amp), rel=1e-12)
    assert C * t > 3.0                   # a day-time zenith delay of metres at this alpha


def test_klobuchar_matches_rtklib_ionmodel():
    p = pytest.importorskip("pyrtklib", reason="pyrtklib (RTKLIB binding) not installed")
    ion = p.Arr1Ddouble(8)
    for i, v in enumerate(ALPHA + BETA):
        ion[i] = v
    rng = np.random.default_rng(3)
    for _ in range(200):
        lat, lon = rng.uniform(-80, 80), rng.uniform(-180, 180)
        el, az, tow = rng.uniform(1, 90), rng.uniform(0, 360), rng.uniform(0, 604800)
        pos = p.Arr1Ddouble(3)
        pos[0], pos[1], pos[2] = math.radians(lat), math.radians(lon), 100.0
        azel = p.Arr1Ddouble(2)
        azel[0], azel[1] = math.radians(az), math.radians(el)
        ref = p.ionmodel(p.gpst2time(2190, tow), ion, pos, azel)
        ours = C * klobuchar_delay_s(ALPHA, BETA, math.radians(lat), math.radians(lon), math.radians(el),
                                     math.radians(az), tow)
        assert ours == pytest.approx(ref, abs=1e-6)


# ------------------------------------------------------------------------------ Saastamoinen
def test_saastamoinen_zenith_hydrostatic_textbook_value():
    # Davis et al. (1985): ZHD = 0.0022768 P / f(phi, H); at P = 1013.25 hPa, 45 deg, sea level: 2.3070 m
    zhd, zwd = saastamoinen_zenith_m(math.radians(45.0), 0.0)
    assert zhd == pytest.approx(2.3070, abs=5e-4)
    # standard atmosphere at sea level: 1013.25 hPa, 15 degC; wet part of the order of 0.1 m
    p, t, e = standard_atmosphere(0.0)
    assert p == pytest.approx(1013.25) and t == pytest.approx(288.16)
    assert 0.05 < zwd < 0.2
    # pressure halves near 5.5 km (ISA: 505 hPa at 5500 m)
    assert standard_atmosphere(5500.0)[0] == pytest.approx(505.0, rel=0.01)


def test_mapping_functions():
    assert mapping(math.pi / 2, "cosz") == pytest.approx(1.0)
    assert mapping(math.pi / 2, "black-eisner") == pytest.approx(1.0, abs=1e-6)
    assert mapping(math.radians(30), "cosz") == pytest.approx(2.0)
    # Black & Eisner stays finite at the horizon: 1.001/sqrt(0.002001) = 22.4
    assert mapping(0.0, "black-eisner") == pytest.approx(22.377, abs=1e-3)
    with pytest.raises(ConfigError):
        mapping(0.3, "niel")
    assert saastamoinen_delay_m(0.7, 0.0, -0.01) == 0.0


def test_saastamoinen_matches_rtklib_tropmodel():
    p = pytest.importorskip("pyrtklib", reason="pyrtklib (RTKLIB binding) not installed")
    rng = np.random.default_rng(4)
    for _ in range(100):
        lat, h, el = rng.uniform(-80, 80), rng.uniform(0, 3000), rng.uniform(3, 90)
        pos = p.Arr1Ddouble(3)
        pos[0], pos[1], pos[2] = math.radians(lat), 0.3, h
        azel = p.Arr1Ddouble(2)
        azel[0], azel[1] = 1.0, math.radians(el)
        ref = p.tropmodel(p.gpst2time(2190, 1000.0), pos, azel, 0.7)
        assert saastamoinen_delay_m(math.radians(lat), h, math.radians(el)) == pytest.approx(ref, abs=1e-6)


def test_model_options_are_checked():
    with pytest.raises(ConfigError, match="ionosphere"):
        AtmosphereModel(iono="nequick")
    with pytest.raises(ConfigError, match="troposphere"):
        AtmosphereModel(tropo="hopfield")
    m = AtmosphereModel(iono="klobuchar", tropo="off")
    assert not m.iono_active and not m.active      # no coefficients: no ionosphere


# ------------------------------------------------------------------------- LNAV page 18
def test_subframe4_page18_round_trip_and_layout():
    from ultratight.signals.constellation import nominal_ephemerides
    from ultratight.signals.lnav import decode_bits, encode_subframe, nav_bits
    from ultratight.signals.lnav_message import ALPHA_SCALE, IonoUtc, quantise_iono

    eph = nominal_ephemerides(2190, 569026.0)[5]
    io = IonoUtc(alpha=ALPHA, beta=BETA, a0=2.7939677e-09, a1=7.9936058e-15, tot=147456.0, wnt=2191 % 256,
                 dt_ls=18, wn_lsf=137, dn=7, dt_lsf=18)
    bits = nav_bits(eph, 2190, 568800.0, 300 * 130, iono=io)   # 13 min: every page once
    dec = decode_bits(bits, prn=eph.prn, ref_week=2190)
    qa, qb = quantise_iono(ALPHA, BETA)
    assert dec.iono.alpha == qa and dec.iono.beta == qb
    assert np.allclose(dec.iono.alpha, ALPHA, atol=2 ** -31) and np.allclose(dec.iono.beta, BETA, atol=2 ** 15)
    assert dec.iono.a1 == pytest.approx(io.a1, abs=2 ** -51) and dec.iono.a0 == pytest.approx(io.a0, abs=2 ** -31)
    assert (dec.iono.tot, dec.iono.wnt, dec.iono.dt_ls, dec.iono.wn_lsf, dec.iono.dn, dec.iono.dt_lsf) == \
        (147456.0, 2191 % 256, 18, 137, 7, 18)
    # Figure 20-1 sheet 8: word 3 = data ID (2) | SV ID 56 (6) | alpha0 (8) | alpha1 (8) | parity;
    # subframe 4 page 18 starts at a TOW with (TOW/30 mod 25) = 17 and TOW mod 30 = 18
    tow = 30 * (25 * 760 + 17) + 18
    b = encode_subframe(4, eph, tow, week=2190, iono=io)
    d30_prev = b[59]
    w3 = b[60:84] ^ d30_prev                      # source bits (complemented when D30* = 1)
    val = int("".join(str(int(x)) for x in w3), 2)
    assert val >> 22 == 0b01 and (val >> 16) & 0x3F == 56
    a0 = (val >> 8) & 0xFF
    assert a0 == round(ALPHA[0] / 2.0 ** ALPHA_SCALE[0])
    # without coefficients the page is the filler pattern and nothing is decoded
    dec0 = decode_bits(nav_bits(eph, 2190, 568800.0, 300 * 130), prn=eph.prn, ref_week=2190)
    assert dec0.iono is None


# ------------------------------------------------------------------------------ scenario table
def test_atmosphere_table_validation():
    from ultratight.receiver.cli.scenario_config import load_scenario
    cfg = load_scenario("static-open-sky-atmosphere")
    assert cfg["atmosphere"]["iono"] == "klobuchar" and cfg["atmosphere"]["iono_scale"] == 1.0
    for over, msg in ((({"atmosphere.iono": "nequick"}), "atmosphere.iono"),
                      ({"atmosphere.tropo_mapping": "niel"}, "tropo_mapping"),
                      ({"atmosphere.iono_scale": -1.0}, "iono_scale"),
                      ({"atmosphere.alpha": [1.0, 2.0]}, "atmosphere.alpha"),
                      ({"atmosphere.broadcast": "yes"}, "broadcast"),
                      ({"atmosphere.ionosphere": "klobuchar"}, "did you mean")):
        with pytest.raises(ConfigError, match=msg):
            load_scenario("static-open-sky-atmosphere", over)


# ------------------------------------------------------------------------------ generator
@pytest.fixture(scope="module")
def gen_pair(tmp_path_factory):
    """1 s of the atmosphere scenario at 2 MHz, with and without the [atmosphere] delays."""
    from ultratight.receiver.cli.scenario_config import load_scenario
    from ultratight.signals.synth.generator import generate
    d = tmp_path_factory.mktemp("atm")
    out = {}
    for name, over in (("on", {}), ("off", {"atmosphere.iono": "off", "atmosphere.tropo": "off"})):
        cfg = load_scenario("static-open-sky-atmosphere", {"duration_s": 1.0, "frontend.fs_hz": 2.0e6, **over})
        out[name] = generate(cfg, d, name, progress=False)
    return out


def test_generator_applies_the_delays_code_late_carrier_early(gen_pair):
    from ultratight.ins.earth import ecef_to_llh as geodetic_llh
    with h5py.File(gen_pair["on"]["truth"], "r") as on, h5py.File(gen_pair["off"]["truth"], "r") as off:
        iono, tropo = on["iono_m"][:], on["tropo_m"][:]
        assert np.all(off["iono_m"][:] == 0) and np.all(off["tropo_m"][:] == 0)
        # metres of delay: Klobuchar day time, Saastamoinen 2.4 m at zenith and more at 5 deg
        assert 1.0 < iono.min() and iono.max() < 30.0 and 2.4 < tropo.min() and tropo.max() < 30.0
        # the recorded delays are the models at the truth geometry
        lat, lon, h = geodetic_llh(on["pos_e"][0])
        m = AtmosphereModel("klobuchar", *__import__("ultratight.signals.lnav_message", fromlist=["x"]).quantise_iono(ALPHA, BETA),
                            tropo="saastamoinen")
        i_ref, t_ref = m.delays_m(lat, lon, h, np.radians(on["elev_deg"][0]), np.radians(on["azim_deg"][0]),
                                  on["t_true_tow_s"][0])
        assert np.allclose(iono[0], i_ref, atol=1e-9) and np.allclose(tropo[0], t_ref, atol=1e-9)
        # code: delayed by I + T; carrier: advanced by I, delayed by T
        dpr = on["pseudorange_m"][:] - off["pseudorange_m"][:]
        assert np.allclose(dpr, iono + tropo, atol=1e-6)
        dcarr_m = -(on["carrier_phase_cycles"][:] - off["carrier_phase_cycles"][:]) * LAMBDA_L1
        assert np.allclose(dcarr_m, tropo - iono, atol=1e-6)
        # transmit time (code and data bits) moves with the code delay
        dtx = (off["t_tx_tow_s"][:] - on["t_tx_tow_s"][:]) * C
        assert np.allclose(dtx, iono + tropo, atol=0.05)     # a TOW in float64 resolves ~1e-10 s = 3 cm


def test_tgd_enters_the_satellite_clock():
    """The L1 C/A clock correction includes -T_GD (IS-GPS-200 20.3.3.3.3.2), so a receiver using
    sat_state's clock applies the group delay."""
    from ultratight.signals.constellation import nominal_ephemerides
    from ultratight.signals.ephemeris import sat_state
    eph = nominal_ephemerides(2190, 569026.0)[5]
    _, _, c0, _ = sat_state(eph, 569030.0)
    _, _, c1, _ = sat_state(eph.copy(tgd=-1.1641532e-08), 569030.0)
    assert (c1 - c0)[0] == pytest.approx(1.1641532e-08, abs=1e-18)


# ------------------------------------------------------------------------------ PVT
def test_pvt_removes_the_delays():
    from ultratight.ins.earth import elev_azim as elevations, llh_to_ecef
    from ultratight.receiver.scalar.pvt import atmosphere_delays, solve_pvt
    from ultratight.signals.constellation import nominal_ephemerides
    from ultratight.signals.ephemeris import sat_state
    from ultratight.signals.geometry import visible_prns
    tow = 569030.0
    rx = np.asarray(llh_to_ecef(math.radians(41.275), math.radians(1.987), 50.0))
    ephs = nominal_ephemerides(2190, tow)
    prns = visible_prns(ephs, rx, 2190, tow, 5.0)
    sp = np.array([sat_state(ephs[p], tow - 0.075)[0][0] for p in prns])
    from ultratight.receiver.scalar.pvt import rotate_sagnac
    rng = np.linalg.norm(sp - rx, axis=1)
    rng = np.linalg.norm(rotate_sagnac(sp, rng / C) - rx, axis=1)
    model = AtmosphereModel("klobuchar", ALPHA, BETA, "saastamoinen")
    el, az = elevations(rx, sp)
    iono, tropo = model.delays_m(math.radians(41.275), math.radians(1.987), 50.0, el, az, tow)
    pr = rng + 1234.5 + iono + tropo
    parts = {}
    sol = solve_pvt(sp, pr, mask_deg=5.0, delays=atmosphere_delays(model, tow, parts))
    assert np.linalg.norm(sol.pos_e - rx) < 1e-3 and sol.clk_bias_m == pytest.approx(1234.5, abs=1e-3)
    assert np.allclose(parts["iono_m"], iono, atol=1e-6) and np.allclose(sol.delays_m, iono + tropo, atol=1e-6)
    bad = solve_pvt(sp, pr, mask_deg=5.0)
    assert np.linalg.norm(bad.pos_e - rx) > 5.0


# ------------------------------------------------------------------------------ end to end
@pytest.mark.slow
def test_acceptance_atmosphere_60s(tmp_path):
    """Generated 60 s static-open-sky-atmosphere (14 satellites, 45 dB-Hz, seed 1): the receiver
    with the coefficients decoded from subframe 4 page 18 meets 3D RMS <= 0.5 m and |mean up| <= 0.3 m;
    without corrections the error is metres."""
    import sys
    from pathlib import Path
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    from acceptance_atmosphere import run_case
    r = run_case(tmp_path, "same", {}, [("klobuchar", "saastamoinen"), ("off", "off")], 1)
    on, off = r["iono=klobuchar,tropo=saastamoinen"], r["iono=off,tropo=off"]
    print("\n", r)
    assert on["corrections"]["iono_source"] == "lnav" and on["n_used_median"] >= 10
    assert on["rms_3d_m"] <= 0.5 and abs(on["mean_enu_m"][2]) <= 0.3
    assert off["rms_3d_m"] > 5.0 and off["mean_enu_m"][2] > 5.0


def test_saastamoinen_is_continuous_through_the_tropopause_and_fades_to_the_top():
    """A climbing vehicle: no step at 10-11 km (RTKLIB's model stops there: up to 5 m at 5 deg);
    the pressure above follows the US Standard Atmosphere 1976 (geometric 20 km: 5529 Pa, 32 km:
    889 Pa; NOAA-S/T 76-1562 Table I) to within the 0.3 % that joins it to the closed form at
    11 km; a dry stratosphere (wet delay under 1 mm above 15 km); nothing above 81 km."""
    el = math.radians(5.0)
    h = np.linspace(0.0, 80000.0, 8001)
    d = saastamoinen_delay_m(0.5, h, el)
    assert np.all(np.diff(d) < 0.0) and d[-1] > 0.0
    assert np.max(np.abs(np.diff(d))) < 0.04                  # 10 m steps: no more than at sea level (3.7 cm)
    near = saastamoinen_delay_m(0.5, np.array([10999.9, 11000.0, 11000.1]), el)
    assert np.ptp(near) < 1e-3
    assert standard_atmosphere(20000.0)[0] == pytest.approx(55.29, rel=0.004)
    assert standard_atmosphere(32000.0)[0] == pytest.approx(8.89, rel=0.004)
    assert saastamoinen_zenith_m(0.5, 15000.0)[1] < 1e-3
    assert saastamoinen_delay_m(0.5, 81000.0, el) == 0.0
    # arrays of any shape, scalars stay scalars
    assert standard_atmosphere(np.array([[0.0, 12000.0], [5e4, 9e4]]))[0].shape == (2, 2)
    assert np.ndim(standard_atmosphere(12000.0)[0]) == 0
