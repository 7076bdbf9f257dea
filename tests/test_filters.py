"""Generic filters: linear equivalence (KF = EKF = UKF = CKF = SRCKF = AUKF), NEES/NIS consistency,
input validation and divergence flagging."""

import numpy as np
import pytest
from scipy.stats import chi2

from ultratight.errors import DivergenceError, FilterError
from ultratight.fusion.estimators import filters as F
from ultratight.fusion.estimators.guards import DivergenceMonitor, check_covariance, cholesky_lower, nearest_pd


def _linear_system(seed=0, n=4, m=3):
    rng = np.random.default_rng(seed)
    A = np.eye(n) + 0.1 * rng.standard_normal((n, n))
    H = rng.standard_normal((m, n))
    Q = np.diag(rng.uniform(0.1, 1.0, n))
    Q[0, 1] = Q[1, 0] = 0.05
    R = np.diag(rng.uniform(0.1, 1.0, m))
    return rng, A, H, Q, R


def test_point_sets_match_gaussian_moments():
    for n in (1, 3, 6):
        for sch in (F.cubature_scheme(n), F.unscented_scheme(n, 1.0, 2.0, 0.0), F.unscented_scheme(n, 0.5, 2.0, 1.0)):
            assert np.isclose(sch.wm.sum(), 1.0)
            np.testing.assert_allclose(sch.wm @ sch.xi, np.zeros(n), atol=1e-14)
            D = sch.xi - sch.wm @ sch.xi
            np.testing.assert_allclose((D.T * sch.wc) @ D, np.eye(n), atol=1e-12)
    assert F.cubature_scheme(4).xi.shape == (8, 4)  # 2n equally weighted points
    assert F.unscented_scheme(4).xi.shape == (9, 4)


def test_linear_gaussian_all_filters_equal_kf():
    rng, A, H, Q, R = _linear_system()
    n, m = A.shape[0], H.shape[0]
    x0 = rng.standard_normal(n)
    P0 = 2.0 * np.eye(n)
    kinds = ["kf", "ekf", "ukf", "ukf_small_alpha", "ckf", "srckf", "aukf"]
    st = {k: (x0.copy(), P0.copy()) for k in kinds}
    f = lambda v: A @ v  # noqa: E731
    h = lambda v: H @ v  # noqa: E731
    for _ in range(25):
        z = rng.standard_normal(m) * 3
        for k, (x, P) in st.items():
            if k == "kf":
                x, P = F.kf_predict(x, P, A, Q)
                r = F.kf_update(x, P, z, H, R)
            elif k == "ekf":
                x, P = F.ekf_predict(x, P, f, lambda v: A, Q)
                r = F.ekf_update(x, P, z, h, H, R)
            elif k == "ukf":
                x, P = F.ukf_predict(x, P, f, Q)
                r = F.ukf_update(x, P, z, h, R)
            elif k == "ukf_small_alpha":
                x, P = F.ukf_predict(x, P, f, Q, alpha=0.1, beta=2.0, kappa=0.0)
                r = F.ukf_update(x, P, z, h, R, alpha=0.1, beta=2.0, kappa=0.0)
            elif k == "ckf":
                x, P = F.ckf_predict(x, P, f, Q)
                r = F.ckf_update(x, P, z, h, R)
            elif k == "aukf":
                x, P = F.aukf_predict(x, P, lambda v, w: A @ v + w, Q)
                r = F.aukf_update(x, P, z, lambda v, e: H @ v + e, R)
            else:
                x, S = F.srckf_predict(x, np.linalg.cholesky(P), f, np.linalg.cholesky(Q))
                r = F.srckf_update(x, S, z, h, np.linalg.cholesky(R))
                np.testing.assert_allclose(r.sqrt_P @ r.sqrt_P.T, r.P, atol=1e-12)
            st[k] = (r.x, r.P)
        xk, Pk = st["kf"]
        for k in kinds:
            np.testing.assert_allclose(st[k][0], xk, atol=1e-9, rtol=0, err_msg=k)
            np.testing.assert_allclose(st[k][1], Pk, atol=1e-9, rtol=0, err_msg=k)


# range/bearing tracking of a constant-velocity target (mildly nonlinear)
DT = 1.0
A_CV = np.array([[1, 0, DT, 0], [0, 1, 0, DT], [0, 0, 1, 0], [0, 0, 0, 1.0]])
Q_CV = 0.02 * np.array([[DT**3 / 3, 0, DT**2 / 2, 0], [0, DT**3 / 3, 0, DT**2 / 2],
                        [DT**2 / 2, 0, DT, 0], [0, DT**2 / 2, 0, DT]])
R_RB = np.diag([0.5**2, 0.004**2])


def f_cv(x):
    return A_CV @ x


def h_rb(x):
    return np.array([np.hypot(x[0], x[1]), np.arctan2(x[1], x[0])])


def H_rb(x):
    r2 = x[0] ** 2 + x[1] ** 2
    r = np.sqrt(r2)
    return np.array([[x[0] / r, x[1] / r, 0, 0], [-x[1] / r2, x[0] / r2, 0, 0]])


def test_srckf_equals_ckf_nonlinear():
    rng = np.random.default_rng(3)
    x = np.array([200.0, 50.0, -2.0, 3.0])
    P = np.diag([20.0, 20.0, 1.0, 1.0])
    xs, S = x.copy(), np.linalg.cholesky(P)
    xt = x + np.linalg.cholesky(P) @ rng.standard_normal(4)
    for _ in range(30):
        xt = A_CV @ xt + np.linalg.cholesky(Q_CV) @ rng.standard_normal(4)
        z = h_rb(xt) + np.sqrt(np.diag(R_RB)) * rng.standard_normal(2)
        x, P = F.ckf_predict(x, P, f_cv, Q_CV)
        r = F.ckf_update(x, P, z, h_rb, R_RB)
        x, P = r.x, r.P
        xs, S = F.srckf_predict(xs, S, f_cv, np.linalg.cholesky(Q_CV))
        rs = F.srckf_update(xs, S, z, h_rb, np.linalg.cholesky(R_RB))
        xs, S = rs.x, rs.sqrt_P
        np.testing.assert_allclose(xs, x, atol=1e-9, rtol=0)
        np.testing.assert_allclose(S @ S.T, P, atol=1e-9, rtol=0)
        assert abs(rs.nis - r.nis) < 1e-9


N_MC, T_MC = 40, 25


def _mc_consistency(kind):
    rng = np.random.default_rng(11)
    P0 = np.diag([4.0, 4.0, 0.25, 0.25])
    Lq, L0 = np.linalg.cholesky(Q_CV), np.linalg.cholesky(P0)
    nees = np.zeros((N_MC, T_MC))
    nis = np.zeros((N_MC, T_MC))
    for i in range(N_MC):
        xt = np.array([150.0, 80.0, -1.0, 2.0])
        x = xt + L0 @ rng.standard_normal(4)
        P = P0.copy()
        for k in range(T_MC):
            xt = A_CV @ xt + Lq @ rng.standard_normal(4)
            z = h_rb(xt) + np.sqrt(np.diag(R_RB)) * rng.standard_normal(2)
            if kind == "ekf":
                x, P = F.ekf_predict(x, P, f_cv, A_CV, Q_CV)
                r = F.ekf_update(x, P, z, h_rb, H_rb, R_RB)
            elif kind == "ukf":
                x, P = F.ukf_predict(x, P, f_cv, Q_CV)
                r = F.ukf_update(x, P, z, h_rb, R_RB)
            elif kind == "ckf":
                x, P = F.ckf_predict(x, P, f_cv, Q_CV)
                r = F.ckf_update(x, P, z, h_rb, R_RB)
            else:
                x, S = F.srckf_predict(x, np.linalg.cholesky(P), f_cv, Lq)
                r = F.srckf_update(x, S, z, h_rb, np.linalg.cholesky(R_RB))
            x, P = r.x, r.P
            e = xt - x
            nees[i, k] = e @ np.linalg.solve(P, e)
            nis[i, k] = r.nis
    return nees.mean(axis=0), nis.mean(axis=0)


@pytest.mark.parametrize("kind", ["ekf", "ukf", "ckf", "srckf"])
def test_nees_nis_within_chi2_bounds(kind):
    anees, anis = _mc_consistency(kind)
    lo4, hi4 = chi2.ppf([0.025, 0.975], N_MC * 4) / N_MC
    lo2, hi2 = chi2.ppf([0.025, 0.975], N_MC * 2) / N_MC
    in_nees = np.mean((anees > lo4) & (anees < hi4))
    in_nis = np.mean((anis > lo2) & (anis < hi2))
    # 95 % two-sided interval: "most time steps" inside; time-averaged values near n and m
    assert in_nees >= 0.85, (kind, in_nees, anees)
    assert in_nis >= 0.85, (kind, in_nis, anis)
    assert abs(anees.mean() - 4.0) < 0.4
    assert abs(anis.mean() - 2.0) < 0.2


# ----------------------------------------------------------------------------- bad input


def test_bad_inputs_raise_filter_error():
    x = np.zeros(2)
    P = np.eye(2)
    Fm = np.eye(2)
    Q = 0.1 * np.eye(2)
    H = np.eye(1, 2)
    R = np.eye(1)
    with pytest.raises(FilterError, match="not positive definite"):
        F.kf_predict(x, np.array([[1.0, 2.0], [2.0, 1.0]]), Fm, Q)
    with pytest.raises(FilterError, match="not symmetric"):
        F.kf_predict(x, np.array([[1.0, 0.5], [0.0, 1.0]]), Fm, Q)
    with pytest.raises(FilterError, match="non-finite"):
        F.kf_update(x, P, np.array([np.nan]), H, R)
    with pytest.raises(FilterError, match="non-finite"):
        F.ckf_update(x, P, [np.inf], lambda v: v[:1], R)
    with pytest.raises(FilterError, match=r"P: expected shape \(3, 3\)"):
        F.kf_predict(np.zeros(3), P, Fm, Q)
    with pytest.raises(FilterError, match="H: expected shape"):
        F.kf_update(x, P, np.zeros(1), np.eye(2), R)
    with pytest.raises(FilterError, match="R"):
        F.ukf_update(x, P, np.zeros(1), lambda v: v[:1], -np.eye(1))
    with pytest.raises(FilterError, match="h: returned shape"):
        F.ckf_update(x, P, np.zeros(2), lambda v: v[:1], np.eye(2))
    with pytest.raises(FilterError, match="1-D vector"):
        F.ckf_predict(np.zeros((2, 1)), P, lambda v: v, Q)
    with pytest.raises(FilterError, match="lower-triangular"):
        F.srckf_predict(x, np.array([[1.0, 1.0], [0.0, 1.0]]), lambda v: v, np.eye(2))
    with pytest.raises(FilterError):
        F.unscented_scheme(2, alpha=1.0, kappa=-3.0)
    with pytest.raises(FilterError, match="kind"):
        F.Filter("pf", x, P)


def test_guards_repair_round_off_but_not_indefinite():
    # PSD up to round-off (rank-deficient): Cholesky with jitter succeeds
    v = np.array([1.0, 2.0, 3.0])
    L = cholesky_lower(np.outer(v, v))
    np.testing.assert_allclose(L @ L.T, np.outer(v, v), atol=1e-5)
    with pytest.raises(FilterError):
        check_covariance("P", np.diag([1.0, -1e-3, 1.0]))
    M = nearest_pd(np.array([[1.0, 2.0], [2.0, 1.0]]), 1e-3)
    assert np.all(np.linalg.eigvalsh(M) >= 1e-3 - 1e-12)


def test_divergence_is_flagged_not_nan():
    # measurements that the model cannot explain: NIS stays far beyond the bound
    x0, P0 = np.zeros(2), np.eye(2) * 1e-6
    filt = F.Filter("ckf", x0, P0, monitor=DivergenceMonitor(max_consecutive=5))
    Q = np.eye(2) * 1e-12
    for k in range(20):
        filt.predict(lambda v: v, Q)
        filt.update(np.array([1e3 * (k + 1)]), lambda v: v[:1], np.eye(1) * 1e-6)
        assert np.all(np.isfinite(filt.x)) and np.all(np.isfinite(filt.P))
    assert filt.diverged
    # a model producing non-finite values: flagged, state kept finite
    filt2 = F.Filter("ukf", x0, np.eye(2))
    filt2.predict(lambda v: v + np.inf, Q)
    assert filt2.diverged and np.all(np.isfinite(filt2.x))
    filt3 = F.Filter("ekf", x0, np.eye(2), raise_on_divergence=True)
    with pytest.raises(DivergenceError):
        filt3.predict(lambda v: v + np.nan, np.eye(2), F=np.eye(2))
    with pytest.raises(DivergenceError):
        F.ckf_predict(x0, np.eye(2), lambda v: np.array([np.nan, 0.0]), Q)


def test_consistent_filter_does_not_flag():
    rng = np.random.default_rng(2)
    filt = F.Filter("kf", np.zeros(1), np.eye(1))
    xt = 0.0
    for _ in range(300):
        xt += 0.1 * rng.standard_normal()
        filt.predict(np.eye(1), np.eye(1) * 0.01)
        filt.update(np.array([xt + rng.standard_normal()]), np.eye(1), np.eye(1))
    assert not filt.diverged


def test_filter_wrapper_srckf_matches_ckf():
    rng = np.random.default_rng(4)
    x0 = np.array([200.0, 50.0, -2.0, 3.0])
    P0 = np.diag([20.0, 20.0, 1.0, 1.0])
    a = F.Filter("srckf", x0, P0)
    b = F.Filter("ckf", x0, P0)
    for _ in range(10):
        z = h_rb(x0) + np.sqrt(np.diag(R_RB)) * rng.standard_normal(2)
        for flt in (a, b):
            flt.predict(f_cv, Q_CV)
            flt.update(z, h_rb, R_RB)
    np.testing.assert_allclose(a.x, b.x, atol=1e-9)
    np.testing.assert_allclose(a.S @ a.S.T, b.P, atol=1e-9)
    assert not a.diverged and not b.diverged


def test_vectorized_callables_give_same_result():
    x = np.array([200.0, 50.0, -2.0, 3.0])
    P = np.diag([20.0, 20.0, 1.0, 1.0])
    z = np.array([206.0, 0.25])

    def h_vec(X):
        return np.c_[np.hypot(X[:, 0], X[:, 1]), np.arctan2(X[:, 1], X[:, 0])]

    for pred, upd in ((F.ckf_predict, F.ckf_update), (F.ukf_predict, F.ukf_update)):
        a = pred(x, P, f_cv, Q_CV)
        b = pred(x, P, lambda X: X @ A_CV.T, Q_CV, vectorized=True)
        np.testing.assert_allclose(a[1], b[1], atol=1e-12)
        ra = upd(a[0], a[1], z, h_rb, R_RB)
        rb = upd(b[0], b[1], z, h_vec, R_RB, vectorized=True)
        np.testing.assert_allclose(ra.x, rb.x, atol=1e-12)
        np.testing.assert_allclose(ra.P, rb.P, atol=1e-12)


from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402


@settings(max_examples=40, deadline=None)
@given(st.integers(min_value=0, max_value=10_000), st.integers(1, 5), st.integers(1, 4))
def test_update_keeps_covariance_symmetric_pd_and_not_larger(seed, n, m):
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((n, n))
    P = A @ A.T + 1e-3 * np.eye(n)
    B = rng.standard_normal((m, m))
    R = B @ B.T + 1e-3 * np.eye(m)
    H = rng.standard_normal((m, n))
    x = rng.standard_normal(n)
    z = rng.standard_normal(m)
    for res in (F.kf_update(x, P, z, H, R), F.ckf_update(x, P, z, lambda v: H @ v, R)):
        assert np.array_equal(res.P, res.P.T)
        assert np.linalg.eigvalsh(res.P).min() > 0
        # information never increases the covariance: P⁻ − P⁺ is PSD
        assert np.linalg.eigvalsh(P - res.P).min() > -1e-9 * np.abs(P).max()
