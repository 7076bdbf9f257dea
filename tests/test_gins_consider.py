"""The covariance of the filter as built with the sensors' scale-factor and cross-axis errors
considered (ultratight.fusion.gins.consider) and the datasheet keys that declare them
(ultratight.ins.imu_noise).

Checks: closed forms of a constant rotation and a constant specific force (the heading variance
after t seconds is (σ_sf ω t)², the velocity variance (σ_sf f t)²); the update against an
independent augmented-state Joseph form and against a Monte Carlo run of the same linear system
(the true error of a filter whose gain comes from a model without the parameters); the NHC rows'
constant offsets; nothing considered gives the design covariance back; the grade defaults."""

import math

import numpy as np
import pytest

from ultratight.errors import ConfigError
from ultratight.fusion.gins.consider import CROSS_PAIRS, ConsiderCovariance, consider_sensitivity
from ultratight.ins import error_model as em
from ultratight.ins.imu_noise import GRADES, imu_noise, nearest_grade


def _noise(**pct):
    keys = {"gyro_scale_factor_pct": 0.0, "gyro_cross_axis_pct": 0.0, "accel_scale_factor_pct": 0.0,
            "accel_cross_axis_pct": 0.0}
    keys.update(pct)
    return imu_noise("consumer", **keys)


def test_constant_rotation_heading_variance_is_sigma_sf_omega_t_squared():
    """A body turning at a constant ω about its vertical axis, level, no update, no white noise:
    the heading error is −s ω t, so its variance is (σ_sf ω t)² (and nothing else grows)."""
    sigma, w, dt = 0.01, math.radians(30.0), 0.1
    cc = ConsiderCovariance(_noise(gyro_scale_factor_pct=100 * sigma), np.zeros((15, 15)))
    Phi, Q = np.eye(15), np.zeros((15, 15))
    for k in range(1, 201):
        yaw = w * k * dt
        C = np.array([[math.cos(yaw), -math.sin(yaw), 0.0], [math.sin(yaw), math.cos(yaw), 0.0], [0.0, 0.0, 1.0]])
        cc.predict(Phi, Q, C, np.array([0.0, 0.0, w * dt]), np.zeros(3))
        if k in (10, 50, 200):
            t = k * dt
            assert cc.Pt[2, 2] == pytest.approx((sigma * w * t) ** 2, rel=1e-12)
            assert cc.Pt[0, 0] == pytest.approx(0.0, abs=1e-18) and cc.Pt[1, 1] == pytest.approx(0.0, abs=1e-18)
            assert np.all(cc.Pt[3:, 3:] == 0.0)


def test_constant_specific_force_velocity_variance_is_sigma_sf_f_t_squared():
    """A constant specific force f along the body x axis (body = ENU): the velocity error along
    east is s f t → variance (σ_sf f t)²; cross-axis terms move north and up by (σ_m f t)²."""
    s_sf, s_m, f, dt = 0.005, 0.02, 2.0, 0.1
    cc = ConsiderCovariance(_noise(accel_scale_factor_pct=100 * s_sf, accel_cross_axis_pct=100 * s_m),
                            np.zeros((15, 15)))
    for _ in range(100):
        cc.predict(np.eye(15), np.zeros((15, 15)), np.eye(3), np.zeros(3), np.array([f * dt, 0.0, 0.0]))
    t = 100 * dt
    v = np.diag(cc.Pt)[em.VEL]
    assert v == pytest.approx([(s_sf * f * t) ** 2, (s_m * f * t) ** 2, (s_m * f * t) ** 2], rel=1e-12)


def test_sensitivity_columns_follow_the_bias_columns_of_the_error_model():
    """Γ's columns are the gyro- and accelerometer-bias columns of F (−C and C) times the increment
    of the axis the error reads: scale factor (i, i), cross-axis (i, j) in CROSS_PAIRS order."""
    rng = np.random.default_rng(7)
    C = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    dth, dv = rng.normal(size=3), rng.normal(size=3)
    G = consider_sensitivity(C, dth, dv, 15)
    F = em.F_matrix(C, np.zeros(3), np.array([0.7, 0.1, 100.0]), np.zeros(3))
    for i in range(3):
        np.testing.assert_allclose(G[:, i], F[:, em.BG.start + i] * dth[i], atol=1e-15)
        np.testing.assert_allclose(G[:, 9 + i], F[:, em.BA.start + i] * dv[i], atol=1e-15)
    for c, (i, j) in enumerate(CROSS_PAIRS):
        np.testing.assert_allclose(G[:, 3 + c], F[:, em.BG.start + i] * dth[j], atol=1e-15)
        np.testing.assert_allclose(G[:, 12 + c], F[:, em.BA.start + i] * dv[j], atol=1e-15)


def _random_system(rng, n=15, q=1e-3, r=(0.2, 0.3)):
    Phi = np.eye(n) + 0.05 * rng.normal(size=(n, n))
    A = rng.normal(size=(n, n))
    Q = q * A @ A.T
    H = rng.normal(size=(2, n))
    R = np.diag(r)
    return Phi, Q, H, R


def test_update_equals_the_augmented_joseph_form_with_a_zero_gain_on_the_parameters():
    """The update of P_t, P_ts is the Joseph form of the augmented state [e; s] with the gain
    [K; 0] (K from the design prior) and, for NHC rows, H_s = I on the two offsets."""
    rng = np.random.default_rng(3)
    Phi, Q, H, R = _random_system(rng)
    nz = _noise(gyro_scale_factor_pct=1.0, gyro_cross_axis_pct=1.0, accel_scale_factor_pct=0.5,
                accel_cross_axis_pct=2.0)
    P0 = np.diag(rng.uniform(0.01, 0.1, 15))
    cc = ConsiderCovariance(nz, P0, nhc_sigma=0.1)
    Pd = P0.copy()
    C = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    for _ in range(5):
        cc.predict(Phi, Q, C, rng.normal(size=3) * 0.1, rng.normal(size=3))
        Pd = Phi @ Pd @ Phi.T + Q
    ns = cc.pss.size
    for nhc in (False, True):
        Pa = np.block([[cc.Pt, cc.Pts], [cc.Pts.T, np.diag(cc.pss)]])
        K = Pd @ H.T @ np.linalg.inv(H @ Pd @ H.T + R)
        Ka = np.vstack([K, np.zeros((ns, 2))])
        Ha = np.hstack([H, np.zeros((2, ns))])
        if nhc:
            Ha[:, 15 + ns - 2:] = np.eye(2)
        A = np.eye(15 + ns) - Ka @ Ha
        expect = A @ Pa @ A.T + Ka @ R @ Ka.T
        cc.update(Pd, H, R, nhc=nhc)
        np.testing.assert_allclose(cc.Pt, expect[:15, :15], rtol=1e-10, atol=1e-14)
        np.testing.assert_allclose(cc.Pts, expect[:15, 15:], rtol=1e-10, atol=1e-14)
        Pd = Pd - K @ H @ Pd


def test_monte_carlo_error_of_the_filter_as_built_matches_the_considered_covariance():
    """Simulate the true error of a filter whose gain ignores the parameters: e⁻ = Φ e⁺ + Γ s + w,
    e⁺ = (I − K H) e⁻ − K (b) − K v with s, b drawn once per run; 4000 runs, seed 11.  Every
    diagonal element of the sample covariance lies within 10 % of P_t; the design P is several
    times smaller on the attitude (what the filter used to report)."""
    rng = np.random.default_rng(11)
    n, runs, steps = 15, 4000, 12
    Phi, Q, H, R = _random_system(rng, q=1e-7, r=(1e-4, 2e-4))
    nz = _noise(gyro_scale_factor_pct=1.0, gyro_cross_axis_pct=1.0, accel_scale_factor_pct=0.5,
                accel_cross_axis_pct=2.0)
    P0 = np.diag(rng.uniform(1e-6, 1e-5, n))
    cc = ConsiderCovariance(nz, P0, nhc_sigma=0.1)
    sd = np.sqrt(cc.pss)
    s = rng.normal(size=(runs, sd.size)) * sd
    e = rng.multivariate_normal(np.zeros(n), P0, size=runs)
    Lq = np.linalg.cholesky(Q)
    Pd = P0.copy()
    C = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    for k in range(steps):
        dth, dv = np.array([0.05, -0.02, 0.3]), np.array([0.3, -0.2, 1.0])
        G = consider_sensitivity(C, dth, dv, n)[:, cc.keep]
        cc.predict(Phi, Q, C, dth, dv)
        Pd = Phi @ Pd @ Phi.T + Q
        e = e @ Phi.T + s[:, :G.shape[1]] @ G.T + rng.normal(size=(runs, n)) @ Lq.T
        if k % 3 == 2:
            nhc = k % 2 == 1
            K = Pd @ H.T @ np.linalg.inv(H @ Pd @ H.T + R)
            innov = e @ H.T + rng.normal(size=(runs, 2)) * np.sqrt(np.diag(R))
            if nhc:
                innov += s[:, -2:]
            e = e - innov @ K.T
            cc.update(Pd, H, R, nhc=nhc)
            Pd = Pd - K @ H @ Pd
    sample = np.cov(e.T)
    np.testing.assert_allclose(np.diag(sample), np.diag(cc.Pt), rtol=0.1)
    assert np.all(np.diag(cc.Pt)[em.ATT] > 3.0 * np.diag(Pd)[em.ATT])


def test_nothing_considered_reports_the_design_covariance():
    nz = _noise()
    P0 = np.diag(np.arange(1.0, 16.0))
    cc = ConsiderCovariance(nz, P0)
    assert not cc.on
    Pd = 2.0 * P0
    cc.predict(np.eye(15), np.eye(15), np.eye(3), np.ones(3), np.ones(3))
    assert cc.covariance(Pd) is Pd


def test_scale_factor_keys_grades_and_the_nearest_grade():
    full = dict(gyro_noise_dps_rthz=0.0038, accel_noise_ug_rthz=70, gyro_bias_rw_dps2_rthz=3.8e-5,
                accel_bias_rw_ug_rthz=7, gyro_bias_dps=0.2, accel_bias_mps2=0.2)
    nz = imu_noise(**full)                      # no grade: the nearest by turn-on gyro bias (0.2 deg/s)
    assert nearest_grade(0.2) == "consumer" and nearest_grade(5.0 / 3600.0) == "tactical"
    assert nz.gyro_sf == pytest.approx(GRADES["consumer"]["gyro_scale_factor_pct"] / 100.0)
    assert nz.accel_cross == pytest.approx(0.02) and "nearest" in nz.source
    nz = imu_noise(gyro_scale_factor_pct=0.0, gyro_cross_axis_pct=0.5, accel_scale_factor_pct=0.1,
                   accel_cross_axis_pct=0.0, **full)
    assert (nz.gyro_sf, nz.gyro_cross, nz.accel_sf, nz.accel_cross) == pytest.approx((0.0, 0.005, 0.001, 0.0))
    assert "nearest" not in nz.source
    assert imu_noise("tactical").gyro_sf == pytest.approx(3e-4)
    assert nz.to_datasheet()["gyro_cross_axis_pct"] == pytest.approx(0.5)
    with pytest.raises(ConfigError, match="gyro_scale_factor_pct must be a non-negative"):
        imu_noise("consumer", gyro_scale_factor_pct=-1.0)
    with pytest.raises(ConfigError, match="gyro_noise_dps_rthz must be a positive"):
        imu_noise("consumer", gyro_noise_dps_rthz=0.0)


class _Nodes:
    """Per-node arrays as ultratight.fusion.gins.results.ConsiderNodes holds them."""

    def __init__(self, K, n, pss):
        m = pss.size
        self.pss = pss
        self.Pt, self.Pts = np.zeros((K, n, n)), np.zeros((K, n, m))
        self.L, self.J, self.N = np.tile(np.eye(n), (K, 1, 1)), np.zeros((K, n, m)), np.zeros((K, n, n))
        self.G, self.Q = np.zeros((K, n, m)), np.zeros((K, n, n))


def _smoother_run(rng, runs, nz, K=10, n=15, nhc_every=2, q=1e-6):
    """A linear system through K nodes: the considered covariances, the design filter's stored
    covariances, and the simulated smoothed errors of the filter as built at every node."""
    Phi, Q, H, R = _random_system(rng, q=q, r=(1e-4, 2e-4))
    P0 = np.diag(rng.uniform(1e-6, 1e-5, n))
    cc = ConsiderCovariance(nz, P0, nhc_sigma=0.1)
    cc.track = True
    st = _Nodes(K, n, cc.pss)
    Phis, Pp, Pq = np.tile(np.eye(n), (K, 1, 1)), np.zeros((K, n, n)), np.zeros((K, n, n))
    Pd = P0.copy()
    Pp[0] = Pq[0] = st.Pt[0] = P0
    s = rng.normal(size=(runs, cc.pss.size)) * np.sqrt(cc.pss)
    e = rng.multivariate_normal(np.zeros(n), P0, size=runs)
    ep, ws = [e], [None]
    C = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    for k in range(1, K):
        dth, dv = np.array([0.05, -0.02, 0.3]), np.array([0.3, -0.2, 1.0])
        cc.predict(Phi, Q, C, dth, dv)
        Pd = Phi @ Pd @ Phi.T + Q
        w = rng.normal(size=(runs, n)) @ np.linalg.cholesky(Q).T
        e = e @ Phi.T + s @ cc.G.T + w
        Phis[k], Pp[k] = Phi, Pd
        for nhc in ((False, True) if k % nhc_every == 0 else (False,)):
            Kg = Pd @ H.T @ np.linalg.inv(H @ Pd @ H.T + R)
            innov = e @ H.T + rng.normal(size=(runs, 2)) * np.sqrt(np.diag(R)) + (s[:, -2:] if nhc else 0.0)
            e = e - innov @ Kg.T
            cc.update(Pd, H, R, nhc=nhc)
            Pd = Pd - Kg @ H @ Pd
        Pq[k] = Pd
        st.Pt[k], st.Pts[k], st.L[k], st.J[k], st.N[k], st.G[k], st.Q[k] = cc.Pt, cc.Pts, cc.L, cc.J, cc.N, cc.G, Q
        ep.append(e)
        ws.append((w, s @ cc.G.T))
    es = [None] * K
    es[-1] = ep[-1]
    for k in range(K - 2, -1, -1):       # the design RTS gains on the simulated errors
        Cg = np.linalg.solve(Pp[k + 1], Phis[k + 1] @ Pq[k]).T
        w, gs = ws[k + 1]
        em_next = ep[k] @ Phis[k + 1].T + gs + w
        es[k] = ep[k] + (es[k + 1] - em_next) @ Cg.T
    return Phis, Pp, Pq, st, es


@pytest.mark.parametrize("q, pct", [
    (1e-6, dict(gyro_scale_factor_pct=1.0, gyro_cross_axis_pct=1.0, accel_scale_factor_pct=0.5,
                accel_cross_axis_pct=2.0)),      # the considered errors dominate
    (1e-4, dict(gyro_scale_factor_pct=0.1)),     # the process and update noises weigh (F_k: up to 24 %)
])
def test_consider_smoother_matches_a_monte_carlo_of_the_smoothed_error(q, pct):
    """The smoothed error of the filter as built (design RTS gains, e^s_k = e⁺_k + C_k (e^s_{k+1} −
    e⁻_{k+1})), simulated 4000 times (seed 5), has the covariance consider_smoother gives at the
    first, a middle and the last node (each diagonal element within 10 %)."""
    from ultratight.fusion.gins.consider import consider_smoother
    rng = np.random.default_rng(5)
    Phis, Pp, Pq, st, es = _smoother_run(rng, 4000, _noise(**pct), q=q)
    Ps = consider_smoother(Phis, Pp, Pq, st)
    for k in (0, 5, 9):
        np.testing.assert_allclose(np.diag(np.cov(es[k].T)), np.diag(Ps[k]), rtol=0.1)


def test_consider_smoother_without_considered_terms_is_the_rts_covariance():
    """With the design model the truth (no parameter moves anything: Γ = 0, J = 0, no NHC offset
    in the rows), the recursion gives the RTS smoother's own covariance."""
    from ultratight.fusion.gins.consider import consider_smoother
    from ultratight.fusion.gins.smoother import rts_backward
    rng = np.random.default_rng(9)
    nz = _noise(gyro_scale_factor_pct=1.0)
    Phis, Pp, Pq, st, _ = _smoother_run(rng, 2, nz, nhc_every=10 ** 6)
    st.G[:] = 0.0
    st.J[:] = 0.0
    st.Pt, st.Pts = Pq.copy(), np.zeros_like(st.Pts)
    _, Ps_rts = rts_backward(Phis, Pp, Pq, np.zeros((Pq.shape[0], Pq.shape[1])))
    np.testing.assert_allclose(consider_smoother(Phis, Pp, Pq, st), Ps_rts, rtol=1e-7, atol=1e-15)
