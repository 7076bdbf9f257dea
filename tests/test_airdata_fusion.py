"""The 9-state ESD total-state air-data filter (Duan et al. 2024): mechanization, eq. 4, eqs. 9–10, CKF/EKF."""

import math

import numpy as np
import pytest

from ultratight.airdata.flight import Flight
from ultratight.fusion.coupling import airdata as AF
@pytest.fixture(scope="module")
def flight100():
    fl = Flight()
    dth, dv = fl.imu_increments(100.0, 120.0)
    return fl, dth, dv


def _x(tr, i):
    return np.array([tr["lon"][i], tr["lat"][i], tr["h"][i], *tr["vel"][i], tr["pitch"][i], tr["yaw"][i], tr["roll"][i]])


def test_mechanization_reproduces_the_truth_with_an_ideal_imu(flight100):
    fl, dth, dv = flight100
    tr = fl.truth(np.array([0.0, 120.0]))
    y = AF.propagate(_x(tr, 0)[None], dth, dv, 0.01)[0]
    e = y - _x(tr, 1)
    assert abs(e[AF.I_LON]) * 6.4e6 < 0.5 and abs(e[AF.I_LAT]) * 6.4e6 < 0.5
    assert abs(e[AF.I_H]) < 0.5
    assert np.max(np.abs(e[AF.VEL])) < 0.01
    assert np.max(np.abs(e[AF.ATT])) < math.radians(1e-4)
    # and the truth really moves: 120 s of climb at Mach 1..1.7
    assert tr["h"][1] - tr["h"][0] > 3000.0


def test_ekf_jacobian_matches_a_perturbation(flight100):
    fl, dth, dv = flight100
    x = _x(fl.truth(np.array([50.0])), 0)
    fx, F = AF.jacobian(x, dth[:10], dv[:10], 0.01)
    d = np.array([1e-6, -1e-6, 5.0, 0.3, -0.2, 0.1, 1e-3, -1e-3, 5e-4])
    lin = fx + F @ d
    full = AF.propagate((x + d)[None], dth[:10], dv[:10], 0.01)[0]
    assert np.max(np.abs((full - lin)[AF.VEL])) < 1e-4
    # specific force ~ g along body z: dVx/dpitch over 0.1 s is about -g*0.1 rotated (order 1)
    assert 0.5 < abs(F[3, AF.I_PITCH]) < 1.5


def test_eq4_blend_limits_and_weight():
    R_g, R1, R2 = 400.0, 4.0, 100.0
    zg, zf = 1000.0, 1010.0
    m1 = (R_g * zf + R1 * zg) / (R_g + R1)
    m2 = (R_g * zf + R2 * zg) / (R_g + R2)
    assert AF.blend(500.0, zg, zf, R_g, R1, R2) == pytest.approx(m1)
    assert AF.blend(15000.0, zg, zf, R_g, R1, R2) == pytest.approx(m2)
    assert AF.blend(5500.0, zg, zf, R_g, R1, R2) == pytest.approx(m1 + (m2 - m1) * 0.5)
    for h in (0.0, 3000.0, 12000.0):
        c = AF.fads_weight(h, R_g, R1, R2)
        assert AF.blend(h, zg, zf, R_g, R1, R2) == pytest.approx((1 - c) * zg + c * zf)
    assert AF.fused_variance(0.0, R_g, R1, R2) == pytest.approx(R_g * R1 / (R_g + R1))


def test_eq10_adaptive_altitude_noise():
    rmin, rmax = 10.0, 400.0
    assert AF.adaptive_altitude_variance(0.5, rmin, rmax) == rmin
    assert AF.adaptive_altitude_variance(1.0, rmin, rmax) == pytest.approx(rmin)
    assert AF.adaptive_altitude_variance(-2.0, rmin, rmax) == pytest.approx((rmin + rmax) / 2)
    v = np.linspace(1.0, 1e4, 1000)
    r = AF.adaptive_altitude_variance(v, rmin, rmax)
    assert np.all(np.diff(r) > 0) and r[-1] == pytest.approx(rmax, rel=1e-3)


def test_fads_velocity_measurement_is_v_at_the_predicted_attitude():
    from ultratight.airdata.frames import euler_to_dcm
    x = np.array([1.8, 0.5, 5000.0, 1500.0, 3.0, -80.0, 0.05, 0.02, 0.001])
    C = euler_to_dcm(*x[AF.ATT])
    h = AF.fads_velocity_h(C, np.array([0.1, 0.9, 0.8]))
    assert np.allclose(h(x)[0], x[:6], rtol=1e-14, atol=1e-9)
    x2 = x.copy()
    x2[AF.I_YAW] += 1e-3       # a yaw error shows in the FADS part of V_y: c_F * |V| * dψ
    assert h(x2)[0, 4] - x[4] == pytest.approx(-0.9 * 1500.0 * 1e-3, rel=0.02)


@pytest.mark.parametrize("kind", ["ckf", "ekf"])
def test_gnss_ins_filter_is_consistent(flight100, kind):
    """Normalised squared state errors e²/P of the 9-state filter with GNSS updates average ≈ 1
    (6 seeds × 12 epochs 10 s apart × 9 states; measured 1.00 for the CKF)."""
    fl, dth, dv = flight100
    tr = fl.truth(np.arange(0, 1201) / 10.0)
    truth = np.stack([_x(tr, i) for i in range(1, 1201)])
    dt, per, R_earth = 0.01, 10, 6.38e6
    sig = np.array([10.0 / (R_earth * math.cos(tr["lat"][0])), 10.0 / R_earth, 20.0, 0.5, 0.5, 0.5])
    sd0 = np.concatenate([sig, np.full(3, math.radians(0.1))])
    q = np.concatenate([[1e-6 / R_earth ** 2] * 2, [1e-6], [per * (0.05 * dt) ** 2] * 3,
                        [per * (math.radians(0.01) * dt) ** 2] * 3])
    norm = []
    for seed in range(6):
        rng = np.random.default_rng(seed)
        dthn = dth + rng.standard_normal(dth.shape) * math.radians(0.01) * dt
        dvn = dv + rng.standard_normal(dv.shape) * 0.05 * dt
        Z = truth[:, :6] + rng.standard_normal((1200, 6)) * sig
        x0 = _x(tr, 0) + rng.standard_normal(9) * sd0
        xs, pd, nis = AF.run(kind, x0, np.diag(sd0 ** 2), np.diag(q), dthn, dvn, dt, per,
                             lambda k, x, P: (Z[k], np.diag(sig ** 2)))
        norm.append(((xs - truth) ** 2 / pd)[::100])
        assert 0.7 < np.nanmean(nis) / 6.0 < 1.3
    norm = np.array(norm)
    assert 0.7 < norm.mean() < 1.4
    assert np.all(norm.mean(axis=(0, 1)) < 2.5), norm.mean(axis=(0, 1))
