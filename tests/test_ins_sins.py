"""SINS mechanisation and error-state model: error-free reproduction, Schuler closed form, linearisation."""

import math

import numpy as np
import pytest
from scipy.linalg import expm

from ultratight.ins import error_model as em
from ultratight.ins.attitude import quat_mult, quat_to_dcm, rotvec_to_quat
from ultratight.ins.earth import normal_gravity, radii
from ultratight.ins.imu import apply_errors, imu_errors_from_config, synthesize_imu
from ultratight.ins.sins import (SINS_STATE_LEN, make_state, nav_errors, sins_run, sins_step, state_from_trajectory,
                                 state_pos_vel_e)
from ultratight.ins.trajectory import PAPER_HIGHDYN_RECEIVER, PAPER_HIGHDYN_TRAJECTORY, build_trajectory


@pytest.fixture(scope="module")
def paper_traj():
    return build_trajectory(PAPER_HIGHDYN_TRAJECTORY, PAPER_HIGHDYN_RECEIVER, 60.0)


@pytest.fixture(scope="module")
def paper_imu100(paper_traj):
    return synthesize_imu(paper_traj, 100.0)


def _free_inertial(imu, dth=None, dv=None, x0=None):
    T = imu.truth
    if x0 is None:
        x0 = make_state(T["q_lb"][0], T["vel_l"][0], T["llh"][0])
    q, v, p = sins_run(x0, imu.dtheta_b if dth is None else dth, imu.dv_b if dv is None else dv, 1.0 / imu.rate_hz)
    return (q, v, p), nav_errors(q, v, p, T["q_lb"], T["vel_l"], T["llh"])


def test_error_free_paper_highdyn(paper_traj, paper_imu100):
    # acceptance: 60 s of Zhao et al. 2014, Table 2 (20 g, 6 km/s) at 100 Hz: <= 0.05 m, 5 mm/s, 1e-4 deg
    _, (dp, dv, da) = _free_inertial(paper_imu100)
    e100 = (np.linalg.norm(dp[-1]), np.linalg.norm(dv[-1]), math.degrees(np.linalg.norm(da[-1])))
    assert np.max(np.linalg.norm(dp, axis=1)) <= 0.05
    assert e100[1] <= 5e-3 and e100[2] <= 1e-4
    # second-order convergence: 200 Hz at least 3x better in position
    _, (dp2, _, _) = _free_inertial(synthesize_imu(paper_traj, 200.0))
    assert np.linalg.norm(dp2[-1]) < e100[0] / 3.0


def test_step_function_matches_batch(paper_imu100):
    imu = paper_imu100
    T = imu.truth
    x = make_state(T["q_lb"][0], T["vel_l"][0], T["llh"][0])
    assert x.shape == (SINS_STATE_LEN,)
    q, v, p = sins_run(x, imu.dtheta_b[:300], imu.dv_b[:300], 0.01)
    for k in range(300):
        sins_step(x, imu.dtheta_b[k], imu.dv_b[k], 0.01)
    assert np.array_equal(x[0:4], q[-1]) and np.array_equal(x[4:7], v[-1]) and np.array_equal(x[7:10], p[-1])


def test_static_paper_biases_follow_schuler_closed_form():
    # 10 min static at 50 km with the 'paper' biases (noise off): Schuler-limited horizontal errors and
    # the unstable vertical channel against their closed forms (Foucault coupling ignored)
    tr = build_trajectory({"kind": "static", "attitude": "fixed", "att0_deg": [0, 0, 0]}, PAPER_HIGHDYN_RECEIVER,
                          600.0)
    imu = synthesize_imu(tr, 100.0)
    err = imu_errors_from_config({"preset": "paper"})
    err.gyro_arw[:] = 0.0
    err.accel_vrw[:] = 0.0
    dth, dv = apply_errors(imu.dtheta_b, imu.dv_b, err, None, 0.01)
    _, (dp, dvel, _) = _free_inertial(imu, dth, dv)
    T = imu.truth
    lat, h = T["llh"][0, 0], T["llh"][0, 2]
    rm, rn = radii(lat)
    R = math.sqrt(rm * rn) + h
    g = normal_gravity(lat, h)
    ws, k = math.sqrt(g / R), math.sqrt(2 * g / R)
    t = T["t"]
    C = quat_to_dcm(T["q_lb"][0])
    eps, nab = C @ err.gyro_bias, C @ err.accel_bias
    s, c = np.sin(ws * t), np.cos(ws * t)
    v_cf = np.stack([nab[0] * s / ws + R * eps[1] * (1 - c), nab[1] * s / ws - R * eps[0] * (1 - c),
                     nab[2] * np.sinh(k * t) / k], axis=1)
    p_cf = np.stack([nab[0] * (1 - c) / ws ** 2 + R * eps[1] * (t - s / ws),
                     nab[1] * (1 - c) / ws ** 2 - R * eps[0] * (t - s / ws),
                     nab[2] * (np.cosh(k * t) - 1) / k ** 2], axis=1)
    for a, m in ((dvel, v_cf), (dp, p_cf)):
        for ax in range(3):
            assert np.max(np.abs(a[:, ax] - m[:, ax])) < 0.10 * np.max(np.abs(m[:, ax]))
    assert abs(p_cf[-1, 2]) > 40.0          # the check is not trivial: ~58 m of height error


def test_error_model_linearisation_paper_highdyn(paper_imu100):
    imu = paper_imu100
    T = imu.truth
    dt = 0.01
    err = imu_errors_from_config({"preset": "paper"})
    err.gyro_arw[:] = 0.0
    err.accel_vrw[:] = 0.0
    dth, dv = apply_errors(imu.dtheta_b, imu.dv_b, err, None, dt)
    lat0, h0 = T["llh"][0, 0], T["llh"][0, 2]
    rm, rn = radii(lat0)
    phi0 = np.array([2e-4, -1e-4, 3e-4])
    dv0 = np.array([0.05, -0.03, 0.02])
    dp0 = np.array([10.0 / (rm + h0), -8.0 / ((rn + h0) * math.cos(lat0)), 5.0])
    x0 = make_state(quat_mult(rotvec_to_quat(-phi0), T["q_lb"][0]), T["vel_l"][0] + dv0, T["llh"][0] + dp0)
    (q, v, p), _ = _free_inertial(imu, dth, dv, x0)
    step = 10                                 # propagate the model at 10 Hz (F at mid-interval truth)
    idx = np.arange(0, imu.n + 1, step)
    actual = np.array([em.true_error_state(q[k], v[k], p[k], T["q_lb"][k], T["vel_l"][k], T["llh"][k])
                       for k in idx])
    dx = np.concatenate([phi0, dv0, dp0, err.gyro_bias, err.accel_bias])
    model = [dx[:9].copy()]
    for j in range(len(idx) - 1):
        k = idx[j] + step // 2
        F = em.F_matrix(T["q_lb"][k], T["vel_l"][k], T["llh"][k], imu.dv_b[k] / dt)
        dx = expm(F * step * dt) @ dx
        model.append(dx[:9].copy())
    model = np.array(model)
    scale = np.array([1, 1, 1, 1, 1, 1, rm + h0, (rn + h0) * math.cos(lat0), 1.0])
    for sl in (em.ATT, em.VEL, em.POS):
        a, m = actual[:, sl] * scale[sl], model[:, sl] * scale[sl]
        assert np.max(np.abs(a - m)) < 0.05 * np.max(np.abs(a))
    assert np.max(np.abs(actual[:, em.POS][:, 0] * scale[6])) > 20.0    # errors grew well beyond the start


def test_van_loan_clock_block():
    # 17-state model: the clock part is a double integrator with white noise on bias and drift
    F = em.F_matrix(np.array([1.0, 0, 0, 0]), np.zeros(3), np.array([0.5, 1.0, 0.0]), np.array([0, 0, 9.8]),
                    n_states=em.N17)
    G = em.G_matrix(np.array([1.0, 0, 0, 0]), n_states=em.N17)
    Qc = np.zeros(em.NW17)
    Qc[em.NOISE_CLK], Qc[em.NOISE_DRIFT] = 0.3, 0.02
    dt = 0.5
    Phi, Qd = em.discretize(F, G, Qc, dt)
    c, d = em.CLK, em.DRIFT
    assert np.allclose(Phi[c, [c, d]], [1.0, dt]) and Phi[d, d] == pytest.approx(1.0)
    assert Qd[c, c] == pytest.approx(0.3 * dt + 0.02 * dt ** 3 / 3)
    assert Qd[c, d] == pytest.approx(0.02 * dt ** 2 / 2)
    assert Qd[d, d] == pytest.approx(0.02 * dt)
    assert np.allclose(Phi, expm(F * dt))
    # Taylor discretisation agrees to second order for small steps
    Phi2, Qd2 = em.discretize_taylor(F, G, Qc, 1e-3)
    Phi1, Qd1 = em.discretize(F, G, Qc, 1e-3)
    assert np.allclose(Phi1, Phi2, atol=1e-9) and np.allclose(Qd1, Qd2, rtol=1e-3, atol=1e-15)


def test_gauss_markov_bias_psd_and_F():
    e = imu_errors_from_config({"preset": "tactical"})
    q = em.noise_psd(e)
    assert np.allclose(q[em.NOISE_BG], 2 * e.gyro_gm_sigma ** 2 / e.gyro_gm_tau)
    F = em.F_matrix(np.array([1.0, 0, 0, 0]), np.zeros(3), np.array([0.5, 1.0, 0.0]), np.zeros(3),
                    tau_g=e.gyro_gm_tau, tau_a=e.accel_gm_tau)
    assert np.allclose(np.diag(F)[em.BG], -1 / e.gyro_gm_tau)
    # steady-state bias variance of the discretised model equals sigma^2
    Phi, Qd = em.discretize(F, em.G_matrix(np.array([1.0, 0, 0, 0])), q, 1.0)
    a = Phi[9, 9]
    assert Qd[9, 9] / (1 - a * a) == pytest.approx(e.gyro_gm_sigma[0] ** 2, rel=1e-9)


def test_feedback_restores_truth(paper_imu100):
    T = paper_imu100.truth
    k = 1234
    phi = np.array([1e-3, -2e-3, 5e-4])
    x = make_state(quat_mult(rotvec_to_quat(-phi), T["q_lb"][k]), T["vel_l"][k] + [0.3, -0.1, 0.2],
                   T["llh"][k] + [1e-6, -2e-6, 7.0])
    dx = np.zeros(em.N17)
    dx[:9] = em.true_error_state(x[0:4], x[4:7], x[7:10], T["q_lb"][k], T["vel_l"][k], T["llh"][k])
    assert np.allclose(dx[em.ATT], phi, atol=1e-15)
    em.apply_feedback(x, dx)
    assert np.allclose(x[0:4], T["q_lb"][k], atol=1e-15)
    assert np.allclose(x[4:7], T["vel_l"][k], atol=1e-12) and np.allclose(x[7:10], T["llh"][k], atol=1e-12)


def test_turning_vehicle_error_free_and_state_helpers():
    # 2 g turns at 30 m/s (37.45 deg/s body rate) exercise coning/sculling
    cfg = {"kind": "turns", "speed0_mps": 30.0, "heading0_deg": 0.0,
           "segments": [{"t0": 0.0, "turn_rate_dps": 0.0}, {"t0": 10.0, "turn_rate_dps": 37.45},
                        {"t0": 20.0, "turn_rate_dps": 0.0}, {"t0": 30.0, "turn_rate_dps": -37.45},
                        {"t0": 40.0, "turn_rate_dps": 0.0, "speed_mps": 20.0}]}
    tr = build_trajectory(cfg, {"lat_deg": 45.0, "lon_deg": 7.0, "h_m": 200.0}, 60.0)
    imu = synthesize_imu(tr, 100.0)
    x0 = state_from_trajectory(tr, 0.0)
    _, (dp, dv, da) = _free_inertial(imu, x0=x0)
    assert np.max(np.linalg.norm(dp, axis=1)) < 0.02
    assert np.max(np.linalg.norm(dv, axis=1)) < 2e-3
    assert math.degrees(np.max(np.linalg.norm(da, axis=1))) < 1e-6
    pos, vel = state_pos_vel_e(state_from_trajectory(tr, 25.0))
    p_ref, v_ref = tr.pos_vel_e(np.array([25.0]))
    assert np.allclose(pos, p_ref[0], atol=1e-6) and np.allclose(vel, v_ref[0], atol=1e-9)


def test_feedback_and_reset_bias_accumulation():
    x = make_state(np.array([1.0, 0, 0, 0]), np.zeros(3), np.array([0.5, 1.0, 10.0]))
    dx = np.zeros(em.N17)
    dx[em.BG] = [1e-6, 2e-6, 3e-6]
    dx[em.BA] = [1e-3, 0.0, -1e-3]
    dx[em.POS] = [0.0, 0.0, 2.0]
    dx[em.CLK], dx[em.DRIFT] = 5.0, 0.1
    bias = np.zeros(6)
    em.feedback_and_reset(x, dx, bias)
    assert np.allclose(bias, [1e-6, 2e-6, 3e-6, 1e-3, 0.0, -1e-3]) and x[9] == pytest.approx(8.0)
    assert not np.any(dx[:em.N15]) and dx[em.CLK] == 5.0 and dx[em.DRIFT] == 0.1
    a, b = em.compensate_increments(np.full(3, 1e-5), np.full(3, 0.1), bias[:3], bias[3:], 0.01)
    assert np.allclose(a, 1e-5 - bias[:3] * 0.01) and np.allclose(b, 0.1 - bias[3:] * 0.01)


def test_gauss_markov_recursion_is_lfilter_bit_for_bit():
    # the first-order recursion of the Gauss-Markov biases against scipy.signal.lfilter (what it replaced:
    # every simulated sensor of every seed keeps its values), over signs, magnitudes and correlation times
    from scipy.signal import lfilter
    from ultratight.ins.imu import _first_order_recursion
    rng = np.random.default_rng(11)
    drive = rng.standard_normal((5000, 3)) * np.array([1e-6, 3.0, 1e4])
    drive[::7] *= -1e-3
    for phi in (0.0, 0.5, 0.999, 1.0 - 1e-9, np.exp(-0.01 / 300.0)):
        ref = np.stack([lfilter([1.0], [1.0, -phi], drive[:, j]) for j in range(3)], axis=1)
        assert np.array_equal(_first_order_recursion(drive, phi), ref), phi
