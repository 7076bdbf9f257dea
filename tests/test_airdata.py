"""Air-data physics: standard atmosphere, pitot relations, FADS model and inversion (Duan et al. 2024)."""

import math

import numpy as np
import pytest
from scipy import stats

from ultratight.airdata import atmosphere, fads
from ultratight.airdata.frames import dcm_to_euler, euler_to_dcm, wind_axes_dcm
from ultratight.errors import ConfigError

# U.S. Standard Atmosphere 1976 tables (geometric altitude): h m, T K, p Pa, rho kg/m^3
USSA76 = [
    (0.0, 288.150, 1.01325e5, 1.2250),
    (1000.0, 281.651, 8.9876e4, 1.1117),
    (5000.0, 255.676, 5.4048e4, 0.73643),
    (10000.0, 223.252, 2.6500e4, 0.41351),
    (15000.0, 216.650, 1.2111e4, 0.19476),
    (20000.0, 216.650, 5.5293e3, 0.088910),
]


@pytest.mark.parametrize("h, T, p, rho", USSA76)
def test_atmosphere_matches_ussa76_table(h, T, p, rho):
    s = atmosphere.state(h)
    assert s["T"] == pytest.approx(T, rel=1e-3)
    assert s["p"] == pytest.approx(p, rel=1e-3)
    assert s["rho"] == pytest.approx(rho, rel=1e-3)
    assert s["a"] == pytest.approx(math.sqrt(1.4 * 287.053 * T), rel=1e-3)


def test_altitude_from_pressure_inverts_and_range_is_checked():
    h = np.linspace(0.0, 30000.0, 301)
    assert np.max(np.abs(atmosphere.altitude_from_pressure(atmosphere.pressure(h)) - h)) < 1e-6
    with pytest.raises(ConfigError, match="altitude"):
        atmosphere.state(90000.0)
    # hydrostatic slope: dp/dh = -rho g
    d = (atmosphere.pressure(1001.0) - atmosphere.pressure(999.0)) / 2.0
    assert d == pytest.approx(atmosphere.dpressure_dh(1000.0), rel=1e-4)


def test_pitot_relations_known_values_and_continuity_at_mach_1():
    assert fads.impact_ratio(0.5) == pytest.approx(1.05 ** 3.5 - 1.0, rel=1e-12)
    # normal-shock tables: p02/p1 = 5.6404 at M = 2, 12.061 at M = 3
    assert fads.impact_ratio(2.0) + 1.0 == pytest.approx(5.6404, rel=1e-4)
    assert fads.impact_ratio(3.0) + 1.0 == pytest.approx(12.061, rel=1e-4)
    lo, hi = 1.0 - 1e-9, 1.0 + 1e-9
    assert abs(fads.impact_ratio(lo) - fads.impact_ratio(hi)) < 1e-8
    assert abs(fads.impact_ratio_dmach(lo) - fads.impact_ratio_dmach(hi)) < 1e-7
    # the usual rounded constant 166.92 is the exact 1.2^3.5 6^2.5 to 5 digits
    assert fads.RAYLEIGH_K == pytest.approx(166.92, abs=5e-3)
    m = np.linspace(0.3, 10.0, 500)
    assert np.max(np.abs(fads.mach_from_impact_ratio(fads.impact_ratio(m)) - m)) < 1e-10
    # derivative matches a finite difference on both branches
    for mm in (0.7, 1.5, 6.0):
        fd = (fads.impact_ratio(mm + 1e-6) - fads.impact_ratio(mm - 1e-6)) / 2e-6
        assert fads.impact_ratio_dmach(mm) == pytest.approx(fd, rel=1e-7)


def _grid():
    rng = np.random.default_rng(7)
    n = 200
    h = rng.uniform(0.0, 25000.0, n)
    mach = rng.uniform(0.4, 8.0, n)
    alpha = np.radians(rng.uniform(-5.0, 15.0, n))
    beta = np.radians(rng.uniform(-5.0, 5.0, n))
    p = atmosphere.pressure(h)
    return alpha, beta, mach, p * fads.impact_ratio(mach), p, h


def test_inversion_recovers_noise_free_air_data():
    cone, clock = fads.default_ports()
    alpha, beta, mach, qc, p, h = _grid()
    P = fads.port_pressures(alpha, beta, qc, p, cone, clock)
    y, cov = fads.invert(P, cone, clock, 100.0)
    assert np.max(np.abs(y[:, 0] - alpha)) < 1e-6
    assert np.max(np.abs(y[:, 1] - beta)) < 1e-6
    assert np.max(np.abs(y[:, 3] / p - 1.0)) < 1e-6
    d = fads.derived(y, cov)
    assert np.max(np.abs(d["mach"] - mach)) < 1e-6
    assert np.max(np.abs(d["h_m"] - h)) < 1e-3


def test_inversion_error_matches_its_covariance():
    cone, clock = fads.default_ports()
    alpha, beta, mach, qc, p, h = _grid()
    rng = np.random.default_rng(11)
    P = fads.port_pressures(alpha, beta, qc, p, cone, clock)
    nees, z_h, z_m = [], [], []
    truth = np.stack([alpha, beta, qc, p], axis=1)
    for _ in range(10):
        y, cov = fads.invert(P + rng.standard_normal(P.shape) * 100.0, cone, clock, 100.0)
        e = y - truth
        nees.append(np.einsum("ni,nij,nj->n", e, np.linalg.inv(cov), e))
        d = fads.derived(y, cov)
        z_h.append((d["h_m"] - h) / np.sqrt(d["var_h"]))
        z_m.append((d["mach"] - mach) / np.sqrt(d["var_mach"]))
    nees = np.concatenate(nees)
    lo, hi = stats.chi2.ppf([0.025, 0.975], 4)
    inside = np.mean((nees >= lo) & (nees <= hi))
    assert inside >= 0.90                      # 95 % band: expect ~0.95
    assert 3.6 < nees.mean() < 4.4             # E[chi2_4] = 4; 2000 samples: sd of the mean 0.063
    for z in (np.concatenate(z_h), np.concatenate(z_m)):
        assert 0.9 < z.std() < 1.1


def test_fads_velocity_covariance_and_air_data_round_trip():
    cone, clock = fads.default_ports()
    rng = np.random.default_rng(3)
    n = 400
    alpha, beta = np.full(n, np.radians(3.0)), np.full(n, np.radians(-1.0))
    h = np.full(n, 8000.0)
    p = atmosphere.pressure(h)
    mach = np.full(n, 4.0)
    C = euler_to_dcm(np.full(n, 0.1), np.full(n, 0.2), np.full(n, 0.01))
    P = fads.port_pressures(alpha, beta, p * fads.impact_ratio(mach), p, cone, clock)
    y, cov = fads.invert(P + rng.standard_normal(P.shape) * 100.0, cone, clock, 100.0)
    d = fads.derived(y, cov, C)
    v_true = np.einsum("nij,nj->ni", C, (mach * atmosphere.speed_of_sound(h))[:, None] * wind_axes_dcm(alpha, beta)[:, 0])
    e = d["vel_n"] - v_true
    nees = np.einsum("ni,nij,nj->n", e, np.linalg.inv(d["cov_vel_n"]), e)
    assert 2.6 < nees.mean() < 3.4
    ad = fads.air_data(v_true, C, h)
    assert np.allclose(ad["alpha"], alpha, atol=1e-12) and np.allclose(ad["beta"], beta, atol=1e-12)
    assert np.allclose(ad["mach"], mach, rtol=1e-12)


def test_direct_altitude_curve_and_frames():
    assert fads.direct_altitude_sigma(0.0) == pytest.approx(1.0)
    assert fads.direct_altitude_sigma(10000.0) == pytest.approx(10.0)
    assert fads.direct_altitude_sigma(20000.0) == pytest.approx(100.0)
    assert fads.direct_altitude_sigma(30000.0) == pytest.approx(100.0)          # clipped at the top of the curve
    # the linear shape: 1 m + 99 m * h / 20 km
    assert fads.direct_altitude_sigma(10000.0, shape="linear") == pytest.approx(50.5)
    assert fads.direct_altitude_sigma(np.array([0.0, 20000.0]), shape="linear") == pytest.approx([1.0, 100.0])
    with pytest.raises(ConfigError, match="shape"):
        fads.direct_altitude_sigma(1000.0, shape="cubic")
    th, ps, ph = 0.3, -1.2, 0.05
    C = euler_to_dcm(th, ps, ph)
    assert np.allclose(C @ C.T, np.eye(3), atol=1e-14)
    assert np.allclose(dcm_to_euler(C), (th, ps, ph))
    # yaw +90 deg turns the nose from East to South (ESD y)
    assert np.allclose(euler_to_dcm(0.0, math.pi / 2, 0.0) @ [1, 0, 0], [0, 1, 0], atol=1e-15)
    # pitch up: nose toward -z (up)
    assert euler_to_dcm(0.1, 0.0, 0.0)[2, 0] < 0
