"""Ionosphere-free rows in the tight measurement model (ultratight.fusion.gins.tight_meas): no ionosphere
delay in their prediction (nor its rate in the Doppler's), and the noise model of the module docstring,
σ² = k² (a² + (b/sin E)² + c² 10^((C0 − C/N0)/10)) + (σ_T/(sin E + 0.1))² with k = √(γ²+1)/(γ−1), against
its closed form written here; single-frequency rows of the same epoch keep the Klobuchar delay and its
term.  Satellite states are given directly (a hand-made sky), so the test needs no ephemeris."""

import math

import numpy as np
import pytest

from ultratight.errors import ConfigError
from ultratight.fusion.gins.tight_meas import TightMeasurements
from ultratight.ins.earth import dcm_ecef_from_enu, llh_to_ecef
from ultratight.signals.obs_geometry import SatStates
from ultratight.signals.observations import F_L2_HZ, F_L5_HZ, RawEpochs
from ultratight.signals.rinex import NavData

LAT, LON, H = math.radians(40.1), math.radians(-105.1), 1600.0
ALPHA = (2.4e-8, 1.5e-8, -1.2e-7, -6e-8)
BETA = (1.3e5, 6.6e4, -2.0e5, 3.3e5)


def _sky():
    """Receiver position and six satellites (elevation, azimuth in degrees) at 20 200 km."""
    rx = np.asarray(llh_to_ecef(LAT, LON, H))
    c = dcm_ecef_from_enu(LAT, LON)
    sats = []
    for el, az in ((80, 10), (50, 120), (35, 230), (25, 300), (60, 200), (15, 60)):
        e, a = math.radians(el), math.radians(az)
        u = c @ np.array([math.cos(e) * math.sin(a), math.cos(e) * math.cos(a), math.sin(e)])
        # the range along u that puts the satellite at the GPS orbit's radius
        b = rx @ u
        rng = -b + math.sqrt(b * b - rx @ rx + 26_560e3 ** 2)
        sats.append(rx + rng * u)
    return rx, np.array(sats)


def _sagnac_range(rx, sats):
    """|R3(Ω_E τ) s − r| with τ the travel time (fixed point; IS-GPS-200 §20.3.3.4.3.4)."""
    tau = np.linalg.norm(sats - rx, axis=1) / 299792458.0
    for _ in range(4):
        th = 7.2921151467e-5 * tau
        rot = np.stack([np.cos(th) * sats[:, 0] + np.sin(th) * sats[:, 1],
                        -np.sin(th) * sats[:, 0] + np.cos(th) * sats[:, 1], sats[:, 2]], axis=1)
        tau = np.linalg.norm(rot - rx, axis=1) / 299792458.0
    return tau * 299792458.0


def _measurements(f2):
    rx, sats = _sky()
    n = len(sats)
    rng = _sagnac_range(rx, sats)
    raw = RawEpochs(t=np.array([2381 * 604800.0 + 408700.0]), start=np.array([0, n]), prn=np.arange(1, n + 1),
                    pr_m=rng, doppler_hz=np.zeros(n), cn0_dbhz=np.array([48.0, 44.0, 40.0, 36.0, 45.0, 30.0]),
                    iono_free_f2_hz=f2)
    states = SatStates(pos_e=sats, vel_e=np.zeros((n, 3)), clk_m=np.zeros(n), drift_mps=np.zeros(n),
                       valid=np.ones(n, dtype=bool))
    nav = NavData(path="sky", version=3.0, ion_alpha=ALPHA, ion_beta=BETA)
    return TightMeasurements(raw, nav, states=states, mask_deg=5.0), rx


def test_combined_rows_have_no_ionosphere_and_the_combined_noise():
    f2 = np.array([F_L2_HZ, F_L2_HZ, F_L5_HZ, F_L2_HZ, 0.0, 0.0])          # two single-frequency rows
    meas, rx = _measurements(f2)
    r = meas.rows(0, rx, np.zeros(3), 0.0, 0.0)
    assert r.n == 6
    single = f2 == 0.0
    assert np.all(r.iono_m[~single] == 0.0) and np.all(r.iono_m[single] > 1.0)
    assert np.all(r.tropo_m > 1.9)
    # predicted − measured: geometry is exact, so only the modelled delays remain
    assert np.allclose(r.dz_pr, r.iono_m + r.tropo_m, atol=1e-6)
    # the ionosphere's rate does not enter the combined rows' Doppler: only the troposphere's (static)
    assert np.all(np.abs(r.dz_rr[~single]) < 1e-3)
    s = np.maximum(np.sin(r.elev_rad), 0.05)
    cn0 = 10.0 ** ((45.0 - r.cn0_dbhz) / 10.0)
    g = (1575.42e6 / np.where(single, 1.0, f2)) ** 2
    k = np.where(single, 1.0, np.sqrt(g ** 2 + 1.0) / (g - 1.0))
    code = 0.3 ** 2 + (0.3 / s) ** 2 + 0.5 ** 2 * cn0
    expect = np.sqrt(k ** 2 * code + (0.5 * r.iono_m) ** 2 + (0.3 / (s + 0.1)) ** 2)
    assert np.allclose(r.sigma_pr, expect, rtol=1e-12)
    assert k[0] == pytest.approx(2.978, abs=1e-3) and k[2] == pytest.approx(2.588, abs=1e-3)
    assert meas.info["ionosphere"] == ("4 rows ionosphere-free (dual frequency); 2 single-frequency rows with the "
                                       "broadcast Klobuchar model")


def test_all_rows_combined_need_no_klobuchar_coefficients():
    meas, _ = _measurements(np.full(6, F_L2_HZ))
    bare = NavData(path="sky", version=3.0)
    quiet = TightMeasurements(meas.raw, bare, states=meas.states)
    assert not quiet.warnings and quiet.info["ionosphere"] == "6 rows ionosphere-free (dual frequency)"
    single = TightMeasurements(RawEpochs(**{**meas.raw.__dict__, "iono_free_f2_hz": None}), bare, states=meas.states)
    assert any("Klobuchar" in w for w in single.warnings)


def test_a_wrong_length_of_the_combination_marks_is_one_error():
    meas, _ = _measurements(np.full(6, F_L2_HZ))
    raw = RawEpochs(**{**meas.raw.__dict__, "iono_free_f2_hz": np.full(5, F_L2_HZ)})
    with pytest.raises(ConfigError, match="iono_free_f2_hz must have one value per row"):
        TightMeasurements(raw, NavData(path="sky", version=3.0), states=meas.states)
