"""Tight 17-state integration filter: measurement model against an independent geometric
computation, estimator cores cross-checked on the linear model, covariance projections,
time update from the SINS error model."""

import numpy as np
import pytest

from ultratight.constants import LAMBDA_L1
from ultratight.errors import FilterError
from ultratight.fusion.coupling import tight
from ultratight.ins.earth import dcm_ecef_from_enu, llh_to_ecef, radii

LAT, LON, H = np.deg2rad(28.246), np.deg2rad(102.0266), 50000.0


def _sats(n=8, seed=3):
    """Satellite positions (ECEF) spread over the sky of the test point."""
    rng = np.random.default_rng(seed)
    rx = np.array(llh_to_ecef(LAT, LON, H))
    C_el = dcm_ecef_from_enu(LAT, LON)
    az = rng.uniform(0, 2 * np.pi, n)
    el = rng.uniform(np.deg2rad(10), np.deg2rad(80), n)
    u_l = np.stack([np.cos(el) * np.sin(az), np.cos(el) * np.cos(az), np.sin(el)], axis=1)
    return rx + 2.2e7 * (u_l @ C_el.T), rx, C_el


def _range(sat, pos):
    return np.linalg.norm(sat - pos, axis=1)


def test_pseudorange_rows_match_geometry():
    """dz = rho(INS) - rho(true) computed from positions equals H dx for a small INS error."""
    sat, rx, C_el = _sats()
    rm, rn = radii(LAT)
    dx = np.zeros(tight.NX)
    dx[6:9] = [2.0 / (rm + H), -3.0 / ((rn + H) * np.cos(LAT)), 1.5]   # (lat, lon, h) error, est - true
    dx[tight.CLK_B] = 4.0
    ins = np.array(llh_to_ecef(LAT + dx[6], LON + dx[7], H + dx[8]))
    los_e = (sat - rx) / _range(sat, rx)[:, None]
    dz = (_range(sat, ins) + dx[tight.CLK_B]) - _range(sat, rx)
    H_ = tight.measurement_matrix(los_e @ C_el, tight.pos_error_to_enu(LAT, H, rm, rn))
    m = sat.shape[0]
    np.testing.assert_allclose(H_[:m] @ dx, dz, atol=2e-3)      # linearisation error < 2 mm


def test_rate_rows_match_geometry():
    sat, rx, C_el = _sats()
    vsat = np.random.default_rng(1).normal(0, 3000, sat.shape)
    v_true_l = np.array([1500.0, 30.0, -2.0])
    dv_l = np.array([0.03, -0.02, 0.05])
    drift_err = 0.07
    los_e = (sat - rx) / _range(sat, rx)[:, None]

    def rate(v_l):
        return np.einsum("ij,ij->i", los_e, vsat - C_el @ v_l)

    dz = (rate(v_true_l + dv_l) + drift_err) - rate(v_true_l)
    dx = np.zeros(tight.NX)
    dx[3:6] = dv_l
    dx[tight.CLK_D] = drift_err
    rm, rn = radii(LAT)
    H_ = tight.measurement_matrix(los_e @ C_el, tight.pos_error_to_enu(LAT, H, rm, rn))
    np.testing.assert_allclose(H_[sat.shape[0]:] @ dx, dz, atol=1e-9)


def _linear_case(n_sat):
    """(ENU lines of sight, position map M, prior P0, injected error state) of the linear model."""
    sat, rx, C_el = _sats(n_sat)
    los_l = ((sat - rx) / _range(sat, rx)[:, None]) @ C_el
    rm, rn = radii(LAT)
    M = tight.pos_error_to_enu(LAT, H, rm, rn)
    P0 = np.diag([1e-8] * 3 + [0.1 ** 2] * 3 + [(10 / (rm + H)) ** 2, (10 / ((rn + H) * np.cos(LAT))) ** 2, 100.0]
                 + [1e-14] * 3 + [1e-8] * 3 + [100.0, 1.0])
    x_true = np.zeros(tight.NX)
    x_true[6:9] = [5.0 / (rm + H), -4.0 / ((rn + H) * np.cos(LAT)), 6.0]
    x_true[tight.CLK_B] = -7.0
    return los_l, M, P0, x_true


@pytest.mark.parametrize("core", ["ekf", "ckf", "ukf"])
def test_cores_agree_and_recover_the_error(core):
    """On the linear measurement model all cores give the same update and estimate the
    injected position/clock error to well within its prior."""
    los_l, M, P0, x_true = _linear_case(10)
    x_true[tight.CLK_D] = 0.3
    x_true[3:6] = [0.05, -0.08, 0.02]
    Hm = tight.measurement_matrix(los_l, M)
    rng = np.random.default_rng(5)
    m = los_l.shape[0]
    z = Hm @ x_true + np.concatenate([rng.normal(0, 0.5, m), rng.normal(0, 0.01, m)])
    tf = tight.TightFilter(P0, core=core, gate_sigma=100.0)
    dx = tf.update(z[:m], z[m:], los_l, M, 0.25, 1e-4)
    ref = tight.TightFilter(P0, core="ekf", gate_sigma=100.0).update(z[:m], z[m:], los_l, M, 0.25, 1e-4)
    np.testing.assert_allclose(dx, ref, rtol=1e-6, atol=1e-9)
    pos_err_m = (M @ (dx[6:9] - x_true[6:9]))
    assert np.all(np.abs(pos_err_m) < 1.5)
    assert abs(dx[tight.CLK_B] - x_true[tight.CLK_B]) < 1.5
    assert np.all(np.abs(dx[3:6] - x_true[3:6]) < 0.03)


def test_gate_rejects_outlier_rows():
    sat, rx, C_el = _sats(8)
    los_l = ((sat - rx) / _range(sat, rx)[:, None]) @ C_el
    rm, rn = radii(LAT)
    M = tight.pos_error_to_enu(LAT, H, rm, rn)
    from ultratight.ins.imu import imu_errors_from_config
    P0 = tight.initial_covariance([LAT, 0.0, H], {"pos_m": 1.0, "clk_bias_m": 1.0},
                                  imu_errors_from_config({"preset": "paper"}))
    tf = tight.TightFilter(P0, gate_sigma=5.0)
    dz_pr = np.zeros(8)
    dz_pr[2] = 500.0                   # one gross pseudorange error
    tf.update(dz_pr, np.zeros(8), los_l, M, 1.0, 1e-2)
    assert tf.n_rejected == 1 and tf.last_used == 15
    assert abs(tf.x[tight.CLK_B]) < 1e-9          # the outlier did not reach the clock
    tf2 = tight.TightFilter(P0, gate_sigma=1e6)
    tf2.update(dz_pr, np.zeros(8), los_l, M, 1.0, 1e-2)
    assert abs(tf2.x[tight.CLK_B]) > 10.0          # ... which it would have without the gate


def test_doppler_sigma_is_the_projected_covariance():
    rng = np.random.default_rng(2)
    A = rng.normal(size=(tight.NX, tight.NX))
    P = A @ A.T * 1e-3
    u = rng.normal(size=(5, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    h = np.zeros((5, tight.NX))
    h[:, 3:6] = -u
    h[:, tight.CLK_D] = 1.0
    expect = np.sqrt(np.einsum("ij,jk,ik->i", h, P, h)) / LAMBDA_L1
    np.testing.assert_allclose(tight.doppler_sigma_hz(P, u, LAMBDA_L1), expect, rtol=1e-12)


def test_time_update_propagates_velocity_error_into_position():
    class Ins:
        q_lb = np.array([1.0, 0.0, 0.0, 0.0])
        vel_l = np.zeros(3)
        llh = np.array([LAT, LON, H])
        f_b = np.array([0.0, 0.0, 9.7])

    from ultratight.ins.imu import imu_errors_from_config
    errs = imu_errors_from_config({"preset": "paper"})
    Phi, Qd = tight.phi_q(Ins(), 0.1, errs)
    assert Phi.shape == (17, 17) and Qd.shape == (17, 17)
    x = np.zeros(17)
    x[5] = 1.0                               # 1 m/s up-velocity error
    x1 = Phi @ x
    assert x1[8] == pytest.approx(0.1, rel=1e-3)          # height error after 0.1 s
    assert x1[tight.CLK_B] == 0.0
    x = np.zeros(17)
    x[tight.CLK_D] = 2.0
    assert (Phi @ x)[tight.CLK_B] == pytest.approx(0.2)
    np.testing.assert_allclose(Qd, Qd.T)
    ev = np.linalg.eigvalsh(Qd)
    assert ev.min() > -1e-12 * ev.max()


def test_initial_covariance_matches_sigmas():
    from ultratight.ins.imu import imu_errors_from_config
    P = tight.initial_covariance([LAT, LON, H], {"pos_m": 2.0, "vel_mps": 0.1, "att_deg": 0.05,
                                                 "clk_bias_m": 3.0, "clk_drift_mps": 0.2},
                                 imu_errors_from_config({"preset": "paper"}))
    rm, rn = radii(LAT)
    M = tight.pos_error_to_enu(LAT, H, rm, rn)
    np.testing.assert_allclose(np.diag(M @ P[6:9, 6:9] @ M.T), [4.0, 4.0, 4.0], rtol=1e-9)
    assert P[tight.CLK_B, tight.CLK_B] == pytest.approx(9.0)
    assert P[tight.CLK_D, tight.CLK_D] == pytest.approx(0.04)


def test_bad_core_and_shapes():
    with pytest.raises(FilterError):
        tight.TightFilter(np.eye(17), core="pf")
    with pytest.raises(FilterError):
        tight.TightFilter(np.eye(15))


def test_iakf_core_updates_and_converges():
    """The "iakf" core (Fang 2017 IAKF) runs repeated updates on the linear model (it raised
    FilterError on its first update when GDOP was passed as the line-of-sight matrix) and, started
    with a 25x too large R, estimates a constant injected error as well as the EKF given the true R."""
    los_l, M, P0, x_true = _linear_case(8)
    Hm = tight.measurement_matrix(los_l, M)
    m = los_l.shape[0]
    rng = np.random.default_rng(11)
    Qd = np.diag(np.full(tight.NX, 1e-16))
    errs = {}
    for core, r_pr in (("iakf", 25.0), ("ekf", 1.0)):
        tf = tight.TightFilter(P0, core=core, gate_sigma=1e6, iakf_window=10)
        for _ in range(60):
            tf.predict(np.eye(tight.NX), Qd)
            z = Hm @ x_true + np.concatenate([rng.normal(0, 1.0, m), rng.normal(0, 0.01, m)])
            dx = tf.update(z[:m], z[m:], los_l, M, r_pr, 1e-4)
        assert tf.n_updates == 60
        assert np.all(np.isfinite(tf.P)) and np.all(np.linalg.eigvalsh(tf.P) > 0)
        errs[core] = np.linalg.norm(M @ (dx[6:9] - x_true[6:9]))
    # both recover the 9 m position error to < 1.5 m; the adaptive R costs at most a factor 2
    assert errs["ekf"] < 1.5 and errs["iakf"] < 1.5, errs
    assert errs["iakf"] < 2.0 * errs["ekf"] + 0.3, errs
