"""Sun et al. 2012: augmented UKF (L = n + q + m) with AFF / AFM, the quaternion SINS/GPS model, the swing base."""

import math

import numpy as np
import pytest
from scipy.stats import chi2

from ultratight.fusion.estimators.adaptive import aukf_fading_step
from ultratight.fusion.estimators.filters import kf_predict, kf_update
from ultratight.fusion.estimators.quat_aukf import (ATT, C_lb_from_C_nb, NavModel, Nominal, QuatAUKF, QuatEKF,
                                         euler_from_q_nb, process_noise, q_nb_from_euler)
from ultratight.ins.attitude import quat_to_dcm
from ultratight.ins.trajectory import build_trajectory
from ultratight.errors import ConfigError

SITE = {"lat_deg": 45.75, "lon_deg": 126.63, "h_m": 150.0}


# --------------------------------------------------------------------------- linear-Gaussian cases


def _linear_case(seed):
    rng = np.random.default_rng(seed)
    n, q, m = 5, 3, 3
    F = np.eye(n) + 0.2 * rng.standard_normal((n, n))
    G = rng.standard_normal((n, q))
    H = np.zeros((m, n))
    H[:, :m] = np.eye(m) + 0.1 * rng.standard_normal((m, m))   # last columns all zero (eq. 8 case)
    Q = np.diag(rng.uniform(0.1, 0.5, q))
    R = np.diag(rng.uniform(0.2, 0.6, m))
    A0 = rng.standard_normal((n, n))
    P = A0 @ A0.T / n + 0.1 * np.eye(n)
    x = rng.standard_normal(n)
    return rng, F, G, H, Q, R, P, x


def _f(F, G):
    return lambda X, W: X @ F.T + W @ G.T


def _h(H):
    return lambda X, V: X @ H.T + V


def test_augmented_ukf_equals_kf_on_linear_gaussian():
    rng, F, G, H, Q, R, P, x = _linear_case(1)
    xk, Pk = x.copy(), P.copy()
    xu, Pu = x.copy(), P.copy()
    for _ in range(20):
        z = rng.standard_normal(3) * 2.0
        xp, Pp = kf_predict(xk, Pk, F, G @ Q @ G.T)
        rk = kf_update(xp, Pp, z, H, R)
        xk, Pk = rk.x, rk.P
        ru = aukf_fading_step(xu, Pu, z, _f(F, G), _h(H), Q, R, mode=None)
        xu, Pu = ru.x, ru.P
        np.testing.assert_allclose(xu, xk, atol=1e-9, rtol=0)
        np.testing.assert_allclose(Pu, Pk, atol=1e-9, rtol=0)


@pytest.mark.parametrize("mode", ["aff", "afm"])
def test_fading_on_linear_case_matches_the_kalman_form(mode):
    """Eqs. 11–13 in sigma-point form equal eqs. 1, 5–10 written with Φ, H (independent computation)."""
    rng, F, G, H, Q, R, P, x = _linear_case(2)
    T = float(chi2.isf(0.01, 1))
    faded = 0
    for _ in range(15):
        z = H @ (F @ x) + rng.standard_normal(3) * 6.0          # innovations larger than modelled
        Pn = F @ P @ F.T                                          # ΦPΦᵀ
        A = H @ Pn @ H.T                                          # eq. 1
        B = H @ G @ Q @ G.T @ H.T + R
        y = z - H @ (F @ x)
        w = np.maximum(1.0, (y * y / T - np.diag(B)) / np.diag(A))
        if mode == "aff":
            Pf = w.max() * Pn + G @ Q @ G.T
        else:
            Hp = H[:, :3]
            S = np.eye(5)
            S[:3, :3] = np.linalg.solve(Hp.T @ Hp, Hp.T @ np.diag(w) @ Hp)   # eqs. 9–10
            Pf = 0.5 * (S @ Pn + Pn @ S.T) + G @ Q @ G.T      # eq. 13, this project's reading
            if np.linalg.eigvalsh(Pf).min() <= 0:             # documented guard: D P′ D, D = √diag S
                d = np.sqrt(np.maximum(np.diag(S), 1.0))
                Pf = Pn * np.outer(d, d) + G @ Q @ G.T
        faded += w.max() > 1.0
        rk = kf_update(F @ x, Pf, z, H, R)
        ru = aukf_fading_step(x, P, z, _f(F, G), _h(H), Q, R, mode=mode, threshold=T,
                              nonzero_cols=[0, 1, 2] if mode == "afm" else None)
        np.testing.assert_allclose(ru.x, rk.x, atol=1e-9, rtol=0)
        np.testing.assert_allclose(ru.P, rk.P, atol=1e-9, rtol=0)
        x, P = ru.x, ru.P
    assert faded >= 5        # the fading was exercised, not only the λ = 1 branch


def test_fading_inflates_on_a_jump_and_not_on_consistent_data():
    rng, F, G, H, Q, R, P, x = _linear_case(3)
    xt = x.copy()
    quiet = []
    for _ in range(30):
        xt = F @ xt * 0.0 + rng.multivariate_normal(np.zeros(5), P) * 0.0 + x   # truth = estimate
        z = H @ (F @ x) + rng.multivariate_normal(np.zeros(3), H @ (F @ P @ F.T + G @ Q @ G.T) @ H.T + R) * 0.5
        r = aukf_fading_step(x, P, z, _f(F, G), _h(H), Q, R, mode="aff")
        quiet.append(r.info["fade"])
    assert np.mean(np.array(quiet) == 1.0) > 0.9
    z = H @ (F @ x) + 50.0
    r = aukf_fading_step(x, P, z, _f(F, G), _h(H), Q, R, mode="aff")
    assert r.info["fade"] > 10.0


# --------------------------------------------------------------------------- frames and model


def test_ned_euler_matches_the_project_convention():
    e = np.radians([12.0, -7.0, 250.0])
    q = q_nb_from_euler(e)
    # NED yaw-pitch-roll sequence written out independently
    r, p, y = e
    Rz = np.array([[math.cos(y), -math.sin(y), 0], [math.sin(y), math.cos(y), 0], [0, 0, 1]])
    Ry = np.array([[math.cos(p), 0, math.sin(p)], [0, 1, 0], [-math.sin(p), 0, math.cos(p)]])
    Rx = np.array([[1, 0, 0], [0, math.cos(r), -math.sin(r)], [0, math.sin(r), math.cos(r)]])
    np.testing.assert_allclose(quat_to_dcm(q), Rz @ Ry @ Rx, atol=1e-12)
    np.testing.assert_allclose(euler_from_q_nb(q), e, atol=1e-12)
    assert C_lb_from_C_nb(np.eye(3)).shape == (3, 3)


def test_swing_trajectory_rates_and_exact_increments():
    from ultratight.ins.imu import synthesize_imu
    from ultratight.ins.sins import sins_run, state_from_trajectory
    from ultratight.ins.attitude import quat_to_dcm_vec
    tr = build_trajectory({"kind": "swing"}, SITE, 40.0)
    t = np.linspace(0.0, 40.0, 401)
    C, w = tr.attitude_l0(t)
    e, _ = tr.swing_euler(t)
    np.testing.assert_allclose(np.degrees(e).max(axis=0), [10.0, 8.0, 5.0], atol=0.05)
    hstep = 1e-5
    dC = (tr.attitude_l0(t + hstep)[0] - tr.attitude_l0(t - hstep)[0]) / (2 * hstep)
    Wx = np.einsum("nji,njk->nik", C, dC)                       # C^T dC/dt = [w x]
    np.testing.assert_allclose(np.stack([Wx[:, 2, 1], Wx[:, 0, 2], Wx[:, 1, 0]], 1), w, atol=1e-8)
    imu = synthesize_imu(tr, 100.0)
    q, v, _ = sins_run(state_from_trajectory(tr, 0.0), imu.dtheta_b, imu.dv_b, 0.01)
    k = tr.kinematics(np.concatenate([[0.0], imu.t]))
    d = np.einsum("nji,njk->nik", k["C_lb"], quat_to_dcm_vec(q))
    assert np.abs(d - np.eye(3)).max() < 1e-8                   # attitude error < 1e-8 rad after 40 s
    assert np.abs(v - k["vel_l"]).max() < 1e-3


def test_swing_trajectory_config_errors():
    with pytest.raises(ConfigError, match="swing_period_s"):
        build_trajectory({"kind": "swing", "swing_period_s": [8.0, 0.0, 1.0]}, SITE, 10.0)
    with pytest.raises(ConfigError, match="does not go with"):
        build_trajectory({"kind": "static", "attitude": "swing"}, SITE, 10.0)


# --------------------------------------------------------------------------- SINS/GPS filters vs EKF


@pytest.fixture(scope="module")
def quiet_run():
    """A 60 s swinging-base run without fault, all four filters on identical data."""
    from ultratight.fusion.experiments import paper_afm
    raw = {"experiment": "paper-afm", "paper_experiment": "4.2", "duration_s": 60.0, "name": "quiet",
           "trajectory": {"kind": "swing", "att0_deg": [0.0, 0.0, 30.0]}, "fault": {"kind": "none"},
           # the filter's own error model (no accelerometer bias: the 13-state model has none)
           "imu": {"accel_bias_ug": 0.0}}
    cfg = paper_afm.load("quiet", raw, {})
    sim = paper_afm.simulate(cfg, 7)
    nom0, P0, Q, R = paper_afm.filter_setup(cfg, sim)
    return {m: paper_afm.run_filter(m, cfg, sim, nom0, P0, Q, R) for m in ("ekf", "ukf", "aff", "afm")}


@pytest.mark.parametrize("method", ["ukf", "aff", "afm"])
def test_sigma_point_filters_equal_the_ekf_on_a_quiet_run(quiet_run, method):
    ekf, other = quiet_run["ekf"], quiet_run[method]
    t = ekf["t"]
    late = t >= 5.0
    diff = np.abs(other["att_err"] - ekf["att_err"])[late]
    sig = other["att_sigma"][late]
    assert np.all(diff < sig), (method, (diff / sig).max())
    # and both are consistent with the truth: attitude error within 3 σ at ≥ 99 % of the samples
    z = np.abs(other["att_err"][late]) / sig
    assert np.mean(z < 3.0) > 0.99


def test_quat_aukf_input_errors():
    from ultratight.errors import FilterError
    model = NavModel.at_site(0.8, 100.0, 0.01)
    nom = Nominal(np.array([1.0, 0, 0, 0]), np.zeros(3), np.zeros(3), np.zeros(3))
    Q = process_noise(1e-4, 1e-3, 1e-6, 0.01)
    with pytest.raises(FilterError, match="mode"):
        QuatAUKF(model, nom, np.eye(12), Q, np.eye(6), mode="fading")
    f = QuatAUKF(model, nom, np.eye(12) * 1e-4, Q, np.eye(6))
    with pytest.raises(FilterError, match="needs a predict"):
        f.update(np.zeros(6))
    f.predict(np.zeros(3), np.array([0.0, 0.0, -9.8 * 0.01]))
    with pytest.raises(FilterError, match="6 finite"):
        f.update(np.zeros(5))
    e = QuatEKF(model, nom, np.eye(12) * 1e-4, Q, np.eye(6))
    e.predict(np.zeros(3), np.array([0.0, 0.0, -9.8 * 0.01]))
    assert np.all(np.isfinite(e.P[ATT, ATT]))


def test_swing_kind_runs_through_the_ins_command(tmp_path, capsys):
    """The swing kind is a trajectory kind like the others: `ultratight ins` on an IF scenario using it."""
    import json
    from ultratight.receiver.cli import main
    from ultratight.config import locate_scenario
    src = locate_scenario("static-open-sky").read_text()
    src = src.replace('kind = "static"\nattitude = "fixed"', 'kind = "swing"\nswing_period_s = [4.0, 5.0, 6.0]')
    assert 'kind = "swing"' in src
    p = tmp_path / "swing.toml"
    p.write_text(src)
    imu_path = tmp_path / "imu.h5"
    assert main(["ins", str(p), "--errors", "ideal", "--duration", "20", "--json", "--save-imu", str(imu_path)]) == 0
    js = json.loads(capsys.readouterr().out)
    assert js["max_att_err_deg"] < 1e-5 and js["max_vel_err_mps"] < 1e-3
    from ultratight.ins.imu_data import read_imu_h5
    imu = read_imu_h5(imu_path)
    rate = np.abs(imu.dtheta_b).max(axis=0) * imu.rate_hz
    # peak body rates of the swing: roll 10° at 4 s, pitch 8° at 5 s → ≥ 0.15 / 0.1 rad/s on some axis
    assert rate.max() > 0.1
