"""Adaptive parts: AKF / IAKF (Fang 2017) and AFF / AFM fading UKF/AUKF (Sun et al. 2012)."""

import numpy as np
import pytest

from ultratight.errors import FilterError
from ultratight.fusion.estimators import adaptive as AD
from ultratight.fusion.estimators import filters as F
# ----------------------------------------------------------------------------- GDOP


def test_gdop_closed_form_and_rotation_invariance():
    e = np.vstack([np.eye(3), -np.eye(3)])  # ±x, ±y, ±z: HᵀH = diag(2, 2, 2, 6)
    assert AD.gdop(e) == pytest.approx(np.sqrt(3 * 0.5 + 1 / 6))
    rng = np.random.default_rng(0)
    los = rng.standard_normal((7, 3))
    los /= np.linalg.norm(los, axis=1, keepdims=True)
    C, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    assert AD.gdop(los, C) == pytest.approx(AD.gdop(los), rel=1e-12)
    with pytest.raises(FilterError, match="at least 4"):
        AD.gdop(los[:3])


# ----------------------------------------------------------------------------- tight-like model
NSAT = 7
_g = np.random.default_rng(5)
_az = _g.uniform(0, 2 * np.pi, NSAT)
_el = _g.uniform(np.radians(15), np.radians(80), NSAT)
LOS = np.c_[np.cos(_el) * np.sin(_az), np.cos(_el) * np.cos(_az), np.sin(_el)]
POS, VEL, CLK_B, CLK_D = slice(0, 3), slice(3, 6), 6, 7
NX = 8
PHI = np.eye(NX)
PHI[POS, VEL] = np.eye(3)
PHI[CLK_B, CLK_D] = 1.0
Q_TRUE = np.zeros((NX, NX))
for _i in range(3):
    Q_TRUE[np.ix_([_i, _i + 3], [_i, _i + 3])] = 0.01 * np.array([[1 / 3, 1 / 2], [1 / 2, 1]])
Q_TRUE[np.ix_([6, 7], [6, 7])] = np.array([[0.1 + 0.01 / 3, 0.01 / 2], [0.01 / 2, 0.01]])
H_TC = np.zeros((2 * NSAT, NX))
H_TC[:NSAT, POS] = LOS
H_TC[:NSAT, CLK_B] = 1.0
H_TC[NSAT:, VEL] = LOS
H_TC[NSAT:, CLK_D] = 1.0
SIG = np.array([2.0] * NSAT + [0.1] * NSAT)  # pseudorange 2 m, rate 0.1 m/s
R_TRUE = np.diag(SIG**2)
R_WRONG = np.diag([50.0**2] * NSAT + [0.6**2] * NSAT)  # paper: (50 m)², (0.6 m/s)²
P0 = np.diag([15.0**2] * 3 + [0.2**2] * 3 + [35.0**2, 0.3**2])


def _tc_run(seed, make, T=400):
    rng = np.random.default_rng(seed)
    x = np.zeros(NX)
    Lq = np.linalg.cholesky(Q_TRUE)
    x0 = np.sqrt(np.diag(P0)) * rng.standard_normal(NX)
    filt = make(x0)
    err = []
    for _ in range(T):
        x = PHI @ x + Lq @ rng.standard_normal(NX)
        z = H_TC @ x + SIG * rng.standard_normal(2 * NSAT)
        filt.predict(PHI)
        if isinstance(filt, AD.IAKF):
            filt.update(z, H_TC, LOS)
        else:
            filt.update(z, H_TC)
        assert np.all(np.isfinite(filt.x))
        err.append(filt.x - x)
    E = np.array(err)[T // 3:]
    return np.array([np.sqrt(np.mean(np.sum(E[:, POS] ** 2, 1))), np.sqrt(np.mean(np.sum(E[:, VEL] ** 2, 1)))])


def _mean(make, seeds=range(3)):
    return np.mean([_tc_run(s, make) for s in seeds], axis=0)


def _iakf(x0, **kw):
    return AD.IAKF(x0, P0, 100 * Q_TRUE, R_WRONG, range(NSAT), range(NSAT, 2 * NSAT),
                   [0, 1, 2, CLK_B], [3, 4, 5, CLK_D], window=50, **kw)


def test_iakf_with_wrong_noise_matches_akf_with_true_noise():
    akf0 = _mean(lambda x0: AD.AKF(x0, P0, Q_TRUE, R_TRUE, window=50))
    akf = _mean(lambda x0: AD.AKF(x0, P0, 100 * Q_TRUE, R_WRONG, window=50))
    iakf = _mean(_iakf)
    # Fang 2017, Table 1: IAKF (wrong initial noise) ≈ AKF0 (true noise) ≪ AKF (wrong initial noise)
    assert np.all(np.abs(iakf - akf0) <= 0.3 * akf0), (akf0, iakf)
    assert np.all(akf > 3 * iakf), (akf, iakf)


def test_iakf_noise_estimates_converge():
    rng = np.random.default_rng(7)
    x = np.zeros(NX)
    filt = _iakf(np.sqrt(np.diag(P0)) * rng.standard_normal(NX))
    Lq = np.linalg.cholesky(Q_TRUE)
    for _ in range(400):
        x = PHI @ x + Lq @ rng.standard_normal(NX)
        filt.predict(PHI)
        filt.update(H_TC @ x + SIG * rng.standard_normal(2 * NSAT), H_TC, LOS)
    r = np.diag(filt.R)
    # GDOP-based R̂ (eqs. 21–25) lands within a factor 3 of the true variances (start: ×625, ×36);
    # the least-squares reading includes the prior spread, so it errs on the high side
    assert 4.0 / 3 < r[0] < 3 * 4.0 and 0.01 / 3 < r[NSAT] < 3 * 0.01, r
    assert np.all(np.linalg.eigvalsh(filt.Q) > 0)
    with pytest.raises(FilterError, match="los_unit"):
        filt.update(np.zeros(2 * NSAT), H_TC)


def test_project_q_recovers_the_model_noises_and_drops_the_rest():
    """Q̂ of eq. 26 projected onto the eq. 3 structure: a Q built from the basis plus noise on a state
    no white noise drives (and a coupling outside the span) projects back onto the basis weights."""
    rng = np.random.default_rng(3)
    n = 6
    B = np.zeros((3, n, n))
    for i, g in enumerate((np.array([1.0, 0.5, 0, 0, 0, 0]), np.array([0, 1.0, 2.0, 0, 0, 0]),
                           np.array([0, 0, 0, 1.0, 0, 0]))):
        B[i] = np.outer(g, g) + np.diag(rng.uniform(0.1, 0.2, n) * (g != 0))
    q_true = np.array([2.0, 0.3, 5.0])
    fixed = np.diag([0, 0, 0, 0, 0, 1e-9])
    junk = np.zeros((n, n))
    junk[4, 4] = 7.0                      # noise on a state outside the model's structure
    junk[0, 3] = junk[3, 0] = 0.4         # a coupling no single noise produces
    Qh = fixed + np.tensordot(q_true, B, axes=1) + junk
    for diagonal in (False, True):
        Q, q = AD.project_q(Qh, B, fixed, scale=np.full(n, 2.0), diagonal=diagonal)
        np.testing.assert_allclose(q, q_true, rtol=1e-9)
        assert Q[4, 4] == 0.0 and Q[0, 3] == 0.0 and Q[5, 5] == 1e-9
        assert np.all(np.linalg.eigvalsh(Q) >= -1e-12)
    # a negative fit is clipped to the floor (Q stays PSD)
    Q, q = AD.project_q(-Qh, B, floor=1e-6)
    np.testing.assert_allclose(q * np.max(np.diagonal(B, axis1=1, axis2=2), axis=1), 1e-6)
    with pytest.raises(FilterError, match="q_basis"):
        AD.project_q(Qh, B[:, :3, :3])


def test_iakf_model_structure_needs_a_basis():
    with pytest.raises(FilterError, match="q_structure"):
        _iakf(np.zeros(NX), q_structure="blocks")
    rng = np.random.default_rng(5)
    filt = _iakf(np.zeros(NX), q_structure="model")
    filt.N = 2
    with pytest.raises(FilterError, match="q_basis"):
        for _ in range(3):
            filt.predict(PHI)
            filt.update(H_TC @ np.zeros(NX) + SIG * rng.standard_normal(2 * NSAT), H_TC, LOS)


def test_iakf_growing_start_estimates_r_from_the_first_epoch():
    """start="growing": R̂ of eqs. 21–25 after k < N epochs is the mean of the k per-epoch terms
    tr(M Mᵀ)/GDOP², M = (AᵀA)⁻¹Aᵀ ε (an independent computation here); "full-window" keeps R0
    until N innovations exist."""
    rng = np.random.default_rng(2)
    x0 = np.sqrt(np.diag(P0)) * rng.standard_normal(NX)
    grow = _iakf(x0, start="growing")
    full = _iakf(x0)
    A = np.hstack([LOS, np.ones((NSAT, 1))])
    L = np.linalg.solve(A.T @ A, A.T)
    g2 = AD.gdop(LOS) ** 2
    terms = []
    for _ in range(3):
        z = H_TC @ np.zeros(NX) + SIG * rng.standard_normal(2 * NSAT)
        for f in (grow, full):
            f.predict(PHI)
        eps = z - H_TC @ grow.x
        grow.update(z, H_TC, LOS)
        full.update(z, H_TC, LOS)
        m_pr, m_prr = L @ eps[:NSAT], L @ eps[NSAT:]
        terms.append((m_pr @ m_pr / g2, m_prr @ m_prr / g2))
        r = np.diag(grow.R)
        np.testing.assert_allclose([r[0], r[NSAT]], np.mean(terms, axis=0), rtol=1e-10)
        np.testing.assert_array_equal(full.R, R_WRONG)
    with pytest.raises(FilterError, match="start"):
        _iakf(x0, start="later")


def test_iakf_q_ceiling_caps_the_projected_noise_at_the_given_one():
    """q_ceiling: the projected Q̂ weights never exceed those of the given Q on the same basis; a
    ceiling below the floor is raised to it; the ceiling needs a model structure."""
    rng = np.random.default_rng(4)
    B = np.zeros((2, 3, 3))
    B[0, 0, 0] = B[1, 1, 1] = 1.0
    Qh = np.diag([5.0, 0.2, 0.0])
    Q, q = AD.project_q(Qh, B, ceiling=[1.0, 1.0])
    np.testing.assert_allclose(q, [1.0, 0.2])
    Q, q = AD.project_q(Qh, B, ceiling=[1.0, 0.0], floor=1e-6)
    np.testing.assert_allclose(q, [1.0, 1e-6])
    with pytest.raises(FilterError, match="q_ceiling"):
        _iakf(np.zeros(NX), q_ceiling=True)
    # the 8-state model: position/velocity noise per axis and the clock pair as the basis
    Bm = np.zeros((4, NX, NX))
    for i in range(3):
        Bm[0][np.ix_([i, i + 3], [i, i + 3])] = np.array([[1 / 3, 1 / 2], [1 / 2, 1]])
    Bm[1, CLK_B, CLK_B] = 1.0
    Bm[2][np.ix_([6, 7], [6, 7])] = np.array([[1 / 3, 1 / 2], [1 / 2, 1]])
    Bm[3, 0, 0] = 1e-9          # a noise the given Q does not have
    Q_given = 0.01 * Bm[0] + 0.1 * Bm[1] + 0.01 * Bm[2]
    f = AD.IAKF(np.zeros(NX), P0, Q_given, R_WRONG, range(NSAT), range(NSAT, 2 * NSAT), [0, 1, 2, CLK_B],
                [3, 4, 5, CLK_D], window=10, q_structure="model-diag", start="growing", q_ceiling=True)
    f.q_basis, f.q_fixed = Bm, np.zeros((NX, NX))
    _, cap = AD.project_q(Q_given, Bm, None, np.ones(NX), diagonal=True)
    x = np.zeros(NX)
    Lq = np.linalg.cholesky(Q_TRUE)
    for _ in range(40):
        x = PHI @ x + Lq @ rng.standard_normal(NX)
        f.predict(PHI)
        f.update(H_TC @ x + SIG * rng.standard_normal(2 * NSAT), H_TC, LOS)
        assert np.all(f.q_w <= np.maximum(cap, 1e-12 / np.max(np.diagonal(Bm, axis1=1, axis2=2), axis=1)) * (1 + 1e-9))
    np.testing.assert_allclose(f.Q, np.tensordot(f.q_w, Bm, axes=1), atol=1e-15)


def test_akf_bad_input():
    with pytest.raises(FilterError):
        AD.AKF(np.zeros(2), np.eye(2), np.eye(2), np.eye(1), window=0)
    akf = AD.AKF(np.zeros(2), np.eye(2), np.eye(2), np.eye(1))
    akf.predict(np.eye(2))
    with pytest.raises(FilterError, match="non-finite"):
        akf.update([np.nan], np.eye(1, 2))
    with pytest.raises(FilterError, match="does not match"):
        akf.update([0.0, 0.0], np.eye(2))


# ----------------------------------------------------------------------------- fading


def test_fading_terms_recover_linear_H():
    rng = np.random.default_rng(1)
    n, m = 4, 3
    A = np.eye(n) + 0.1 * rng.standard_normal((n, n))
    H = rng.standard_normal((m, n))
    Q = 0.1 * np.eye(n)
    R = 0.2 * np.eye(m)
    x, P = rng.standard_normal(n), np.eye(n)
    xp, Pp, Pnl = F.ukf_predict(x, P, lambda v: A @ v, Q, return_noiseless=True)
    np.testing.assert_allclose(Pnl, A @ P @ A.T, atol=1e-12)
    zhat, Pzz0, Pxz = F.sigma_measure(xp, Pp, lambda v: H @ v, F.unscented_scheme(n))
    Hs, Am, B = AD.fading_terms(Pxz, Pp, Pnl, Pzz0 + R)
    np.testing.assert_allclose(Hs, H, atol=1e-10)
    np.testing.assert_allclose(Am, H @ A @ P @ A.T @ H.T, atol=1e-10)
    np.testing.assert_allclose(B, H @ Q @ H.T + R, atol=1e-10)


def test_fading_factor_and_matrix_closed_form():
    A = np.diag([1.0, 2.0])
    B = np.diag([0.5, 0.5])
    T = 3.841
    y = np.array([3.0, 0.1])
    s1 = (9.0 / T - 0.5) / 1.0
    assert AD.fading_factor(y, A, B, T) == pytest.approx(s1)
    assert AD.fading_factor(np.zeros(2), A, B, T) == 1.0
    # H with an all-zero column (eqs. 8–10): S = blockdiag((H'ᵀH')⁻¹H'ᵀΩH', I)
    H = np.array([[1.0, 0.0, 0.0], [0.0, 2.0, 0.0]])
    S = AD.fading_matrix(y, A, B, H, T)
    np.testing.assert_allclose(S, np.diag([s1, 1.0, 1.0]), atol=1e-12)
    # full-column H (eq. 7)
    H2 = np.array([[1.0, 1.0], [0.0, 1.0]])
    S2 = AD.fading_matrix(y, A, B, H2, T)
    np.testing.assert_allclose(S2, np.linalg.solve(H2.T @ H2, H2.T @ np.diag([s1, 1.0]) @ H2), atol=1e-12)
    Pn = np.diag([1.0, 2.0])
    np.testing.assert_allclose(AD.apply_fading(Pn + 0.1 * np.eye(2), Pn, 3.0), 3 * Pn + 0.1 * np.eye(2))
    Pf = AD.apply_fading(Pn + 0.1 * np.eye(2), Pn, np.diag([4.0, 1.0]))
    np.testing.assert_allclose(Pf, np.diag([4.1, 2.1]))


BEAC = np.array([[1000.0, 0, 0], [0, 1000.0, 0], [0, 0, 1000.0]])
N6 = 6
Q6 = np.eye(N6) * 0.01
SR = 0.5


def _h6(x):
    return np.concatenate([np.linalg.norm(BEAC - x[None, :3], axis=1), x[3:] + 0.01 * x[3:] ** 2])


def _fading_rms(seed, mode, augmented=False, T=200):
    """Random-walk states; at mid-run the process noise of state 0 only becomes ×100."""
    rng = np.random.default_rng(seed)
    x = np.zeros(N6)
    xs, zs = [], []
    for k in range(T):
        q = np.diag(Q6).copy()
        if k >= T // 2:
            q[0] *= 100.0
        x = x + np.sqrt(q) * rng.standard_normal(N6)
        xs.append(x.copy())
        zs.append(_h6(x) + SR * rng.standard_normal(N6))
    filt = AD.FadingUKF(np.zeros(N6), np.eye(N6), mode=mode, augmented=augmented, alpha_chi2=0.05)
    R = np.eye(N6) * SR**2
    err = []
    for k in range(T):
        if augmented:
            filt.step(zs[k], lambda v, w: v + w, lambda v, e: _h6(v) + e, Q6, R)
        else:
            filt.step(zs[k], lambda v: v, _h6, Q6, R)
        err.append(filt.x - xs[k])
    E = np.array(err)[T // 2:]
    return np.sqrt(np.mean(np.sum(E**2, 1)))


@pytest.mark.parametrize("augmented", [False, True])
def test_afm_beats_aff_beats_ukf_when_one_noise_term_changes(augmented):
    seeds = range(3) if augmented else range(5)
    rms = {m: np.mean([_fading_rms(s, m, augmented) for s in seeds]) for m in (None, "aff", "afm")}
    assert rms["afm"] < 0.95 * rms["aff"] < 0.95 * rms[None], rms
