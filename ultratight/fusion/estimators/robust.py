"""Robust parts composable with the generic filters.

1. RACKF – robust adaptive cubature Kalman filter (Zhao et al. 2014, §2.3)
   * Huber equivalent weights → equivalent noise R̄ (eqs. 18–23), with this project's readings:
     σ_ri = sqrt((P_zz)_ii) (a standard deviation, eq. 22), r'_i = r_i/σ_ri, γ_i = max(1, |r'_i|/c);
     diagonal R̄_ii = R_ii γ_i (eq. 20 inverted), off-diagonal R̄_ij = R_ij max(γ_i, γ_j) (eq. 21
     inverted).  The element-wise off-diagonal rule can lose positive definiteness; then the
     congruence form R̄ = D R D, D = diag(√γ) (same diagonal, PD by construction) is used instead.
   * Adaptive factor ϑ (eqs. 37–38): ϑ = 1 if rᵀr ≤ tr(P̄_zz) else tr(P̄_zz)/rᵀr, with P̄_zz from
     the robust eq. 18 and tr(P̂_zz) = rᵀr (the squared innovations).
   * When ϑ < 1 the cubature points are redrawn as x̂ + sqrt(1/ϑ)·S ξ_j (eq. 40) and eqs. 11, 12,
     18 are recomputed (with the same R̄), then the update eqs. 14–17 use P⁻/ϑ.
   * Algorithm 1 order: predict (4–8) → factor (9) → points (40, ϑ = 1) → ẑ, P_zz (11–13) →
     R̄ (18–21) → ϑ (37) [→ redraw, 11, 12, 18] → update (14–17).
   * :class:`RACKF` applies the robust/adaptive corrections only on every ``correction_period``-th
     update (the paper: once per 50 ms at 1 kHz); the other updates are plain CKF updates.

2. Chi-square fault detection + Newton-extrapolated noise (Cai et al. 2020)
   * Per-dimension statistic S_k(i) = J_k(i)²/D_k(i,i) (eq. 15), J = innovation, D = H P⁻ Hᵀ + R
     (eq. 13), tested against χ²₁ at significance α (threshold 6.635 for α = 0.01, 7.879 for 0.005).
   * A faulty dimension's noise value is replaced by the 4th-order Newton (binomial) extrapolation
     of its previous four values divided by the improvement factor δ = 4 (eqs. 21, 23, 27 with the
     misprinted coefficients corrected): V'_k = (4V_{k−1} − 6V_{k−2} + 4V_{k−3} − V_{k−4})/δ.
   * Reading of "noise value" V_k(i): the filter cannot observe the noise realisation, so it uses
     the innovation J_k(i) (= H x̃ + V, ≈ V for a converged filter) as its estimate; a faulty
     measurement is replaced by z'(i) = ẑ(i) + V'_k(i), and the history stores the values actually
     used (so gross errors never enter later extrapolations).  Until four values exist, a faulty
     dimension's innovation is set to 0 (the measurement is replaced by its prediction).
"""

from __future__ import annotations

from math import comb

import numpy as np

from ultratight.chi2 import chdtri
from ultratight.errors import FilterError
from ultratight.fusion.estimators.filters import (
    UpdateResult,
    _joseph,
    ckf_predict,
    ckf_update,
    cubature_scheme,
    gain_update,
    sigma_measure,
)
from ultratight.fusion.estimators.guards import (
    check_linear_update,
    as_matrix,
    as_vector,
    check_covariance,
    cholesky_lower,
    symmetrize,
)

__all__ = [
    "huber_equivalent_R",
    "adaptive_factor",
    "rackf_update",
    "RACKF",
    "newton_coefficients",
    "newton_extrapolate",
    "chi2_threshold",
    "ChiSquareNewton",
    "chi2_newton_kf_update",
]


# --------------------------------------------------------------------------- RACKF


def huber_equivalent_R(r, Pzz, R, c: float = 1.5):
    """Huber equivalent measurement noise R̄ (Zhao et al. 2014 eqs. 19–23, this project's readings).

    r: innovation z − ẑ (23); Pzz: innovation covariance of eq. 13 (including R); R: nominal noise.
    Returns (R̄, γ) with γ_i = max(1, |r'_i|/c) the per-measurement variance inflation.
    """
    if not (c > 0):
        raise FilterError(f"Huber constant c must be > 0 (typically 1.3–2.0), got {c}")
    sigma_r = np.sqrt(np.diag(Pzz))  # eq. 22 (standard deviation reading)
    rs = np.abs(r) / sigma_r  # standardised residual r'
    gamma = np.maximum(1.0, rs / c)  # eq. 20: 1/p̄_ii = σ_ii |r'|/c when |r'| > c
    G = np.maximum(gamma[:, None], gamma[None, :])  # eq. 21: max(|r'_i|, |r'_j|)
    Rbar = symmetrize(R * G)
    try:
        np.linalg.cholesky(Rbar)
    except np.linalg.LinAlgError:
        d = np.sqrt(gamma)
        Rbar = symmetrize(R * d[:, None] * d[None, :])  # PD congruence fallback (same diagonal)
    return Rbar, gamma


def adaptive_factor(r, Pzz_bar) -> float:
    """Approximate optimal adaptive factor ϑ (Zhao et al. 2014 eqs. 37–38): ϑ = min(1, tr(P̄_zz)/rᵀr)."""
    tr_hat = float(r @ r)  # eq. 38: tr(P̂_zz) = rᵀr
    tr_p = float(np.trace(Pzz_bar))
    if tr_hat <= tr_p:
        return 1.0
    return tr_p / tr_hat


def rackf_update(x, P, z, h, R, c: float = 1.5, robust: bool = True, adaptive: bool = True,
                 theta_min: float = 1e-6, vectorized: bool = False, window=None) -> UpdateResult:
    """RACKF measurement update (Zhao et al. 2014, Algorithm 1 steps 3–7).

    Returns an UpdateResult whose ``P`` is the posterior of the adapted prior P⁻/ϑ and whose
    ``info`` holds ``Rbar`` (R̄), ``gamma`` (per-measurement inflation), ``theta`` (ϑ) and
    ``S_nominal`` (P_zz of eq. 13).  ``S`` is the robust P̄_zz used in the gain (eq. 18).
    ``theta_min`` bounds the covariance inflation 1/ϑ (numerical guard).
    """
    x = as_vector("x", x)
    n = x.shape[0]
    P = check_covariance("P", P, n)
    z = as_vector("z", z)
    m = z.shape[0]
    R = check_covariance("R", R, m)
    sch = cubature_scheme(n)
    # step 3–4: points with ϑ = 1 (eqs. 9, 40), ẑ (11–12), P_zz (13)
    zhat, Pzz0, Pxz = sigma_measure(x, P, h, sch, 1.0, vectorized, m)
    Pzz = Pzz0 + R  # eq. 13
    r = z - zhat  # eq. 23
    # step 5: robust correction (18–21)
    if robust:
        Rbar, gamma = huber_equivalent_R(r, Pzz, R, c)
    else:
        Rbar, gamma = R, np.ones(m)
    Pzz_bar = Pzz0 + Rbar  # eq. 18
    # step 6: adaptive factor (37–38)
    if adaptive and window is not None:
        # strategy 1 of Zhao et al. 2014, §2.3 (sliding window of the last N residual vectors):
        # mean of the Huber-clipped standardised residuals u = clip(r', −c, c);
        # tr(P̂_zz) = N·Σ_i (ū_i σ_ri)²  (equals rᵀr for N = 1 without clipping)
        sig = np.sqrt(np.diag(Pzz))
        window.append(np.clip(r / sig, -c, c))
        U = np.array(window)
        ubar = U.mean(axis=0)
        tr_hat = U.shape[0] * float(np.sum((ubar * sig) ** 2))
        tr_p = float(np.trace(Pzz_bar))
        theta = 1.0 if tr_hat <= tr_p else tr_p / tr_hat
    else:
        theta = adaptive_factor(r, Pzz_bar) if adaptive else 1.0
    theta = max(theta, theta_min)
    Pprior = P
    if theta < 1.0:
        # redraw the cubature points with sqrt(1/ϑ)·S (eq. 40); recompute 11, 12, 18
        zhat, Pzz0, Pxz = sigma_measure(x, P, h, sch, 1.0 / theta, vectorized, m)
        Pprior = P / theta
    # step 7: update (14–17) with R̄ in P̄_zz
    res = gain_update(x, Pprior, z, zhat, Pzz0, Pxz, Rbar)
    res.info.update(Rbar=Rbar, gamma=gamma, theta=theta, S_nominal=Pzz)
    return res


class RACKF:
    """Stateful RACKF: CKF time update + robust/adaptive measurement update.

    Corrections (Huber R̄ and the adaptive factor ϑ) are applied on every ``correction_period``-th
    update (updates number period, 2·period, …); the others are plain CKF updates
    (Zhao et al. 2014 use 50 ms at 1 kHz, i.e. ``correction_period = 50``).

    ``window=None`` (default) is the paper's Algorithm 1 with the single-residual tr(P̂_zz) = rᵀr
    (eq. 38).  ``window=N`` uses the paper's alternative strategy 1: the mean of the last N
    Huber-clipped standardised residual vectors of the correction steps,
    tr(P̂_zz) = N·Σ_i (ū_i σ_ri)², which does not mistake a white noise burst for a dynamics
    change (see docs/filters.md for the measured difference).
    """

    def __init__(self, x0, P0, c: float = 1.5, correction_period: int = 1, robust: bool = True,
                 adaptive: bool = True, theta_min: float = 1e-6, window: int | None = None):
        if window is not None and int(window) < 1:
            raise FilterError(f"window must be None or an integer ≥ 1, got {window}")
        from collections import deque

        self._window = deque(maxlen=int(window)) if window is not None else None
        if int(correction_period) < 1:
            raise FilterError(f"correction_period must be an integer ≥ 1, got {correction_period}")
        self.x = as_vector("x0", x0)
        self.P = check_covariance("P0", P0, self.x.shape[0])
        self.c = c
        self.period = int(correction_period)
        self.robust = robust
        self.adaptive = adaptive
        self.theta_min = theta_min
        self.n_updates = 0
        self.last: UpdateResult | None = None

    def predict(self, f, Q, vectorized=False):
        """CKF time update (eqs. 4–8)."""
        self.x, self.P = ckf_predict(self.x, self.P, f, Q, vectorized)
        return self.x, self.P

    def update(self, z, h, R, vectorized=False) -> UpdateResult:
        self.n_updates += 1
        if self.n_updates % self.period == 0:
            res = rackf_update(self.x, self.P, z, h, R, self.c, self.robust, self.adaptive,
                               self.theta_min, vectorized, self._window)
        else:
            res = ckf_update(self.x, self.P, z, h, R, vectorized)
            res.info.update(theta=1.0, gamma=np.ones(res.innovation.shape[0]), Rbar=np.asarray(R, dtype=float))
        self.x, self.P, self.last = res.x, res.P, res
        return res


# --------------------------------------------------------------------------- chi-square + Newton


def newton_coefficients(order: int = 4) -> np.ndarray:
    """Coefficients M of the equidistant Newton extrapolation f_k = Σ_a M_a f_{k−a}, a = 1..order.

    M_a = (−1)^(a+1) C(order, a): order 4 gives [4, −6, 4, −1] (Cai et al. 2020 eqs. 20, 26–27
    with the misprinted last coefficient corrected).  Exact for polynomials of degree < order.
    """
    if order < 1:
        raise FilterError(f"Newton extrapolation order must be ≥ 1, got {order}")
    return np.array([(-1) ** (a + 1) * comb(order, a) for a in range(1, order + 1)], dtype=float)


def newton_extrapolate(history, order: int = 4) -> np.ndarray:
    """Extrapolate the next value from ``history`` (rows oldest → newest, at least ``order`` rows)."""
    h = np.asarray(history, dtype=float)
    if h.shape[0] < order:
        raise FilterError(f"Newton extrapolation of order {order} needs {order} past values, got {h.shape[0]}")
    M = newton_coefficients(order)
    recent = h[::-1][:order]  # f_{k−1}, f_{k−2}, ...
    return np.tensordot(M, recent, axes=(0, 0))


def chi2_threshold(alpha: float, dof: int = 1) -> float:
    """χ² threshold T = χ²_α(dof) (upper-α quantile; 6.635 for α = 0.01, 7.879 for α = 0.005)."""
    if not (0.0 < alpha < 1.0):
        raise FilterError(f"significance level alpha must be in (0, 1), got {alpha}")
    return float(chdtri(dof, alpha))


class ChiSquareNewton:
    """Per-dimension χ² fault detector with Newton-extrapolated replacement noise (Cai et al. 2020).

    ``screen(r, S)`` returns (r_used, faulty, stat): stat_i = r_i²/S_ii (eq. 15); dimensions with
    stat_i > T (eq. 16, T = χ²_α(1)) get r_i replaced by newton_extrapolate(past values)/δ
    (eqs. 21, 27).  The history keeps the values actually used.

    ``guard``: a replacement that itself fails the test (ext_i²/S_ii > T) is set to 0 (the
    measurement is replaced by its prediction).  Not in the paper; without it a run of consecutive
    faults feeds replaced values back into the extrapolation, whose recursion
    f_k = (4f₋₁ − 6f₋₂ + 4f₋₃ − f₋₄)/δ has roots of modulus 1.07 > 1 at δ = 4 (it grows without
    bound; seen in the paper-robust-flight sweep at small gross-error factors).
    ``release_after``: a dimension flagged in this many consecutive epochs is used unchanged
    (counted in ``n_released``): the innovation is the filter's proxy of V, and a persistent
    "fault" is the filter's own error, which replacing would hide from it for good (divergence,
    the paper's Fig. 1).  Not in the paper; None (default) = never.
    ``weight_replacements`` (used by :func:`chi2_newton_kf_update`): a replaced innovation enters
    the update with the variance of its extrapolation instead of R's, and one zeroed by the guard
    is left out.  Not in the paper; False (default) = the update uses R for every dimension.
    """

    def __init__(self, m: int, alpha: float = 0.01, delta: float = 4.0, order: int = 4, guard: bool = False,
                 release_after: int | None = None, weight_replacements: bool = False):
        if m < 1:
            raise FilterError(f"measurement dimension must be ≥ 1, got {m}")
        if not delta > 0:
            raise FilterError(f"improvement factor delta must be > 0, got {delta}")
        self.m = m
        self.alpha = alpha
        self.threshold = chi2_threshold(alpha, 1)
        self.delta = float(delta)
        self.order = int(order)
        self.coeffs = newton_coefficients(self.order)
        self._hist = np.zeros((self.order, m))  # newest last
        self._count = 0
        self.n_faults = 0
        self.guard = bool(guard)
        self.release_after = None if release_after is None else int(release_after)
        self._run = np.zeros(m, dtype=int)      # consecutive flagged epochs per dimension
        self.n_released = 0
        self.weight_replacements = bool(weight_replacements)

    def screen(self, r, S):
        r = as_vector("innovation", r, self.m)
        S = as_matrix("S", S, (self.m, self.m))
        stat = r * r / np.diag(S)  # eq. 15
        faulty = stat > self.threshold  # eq. 16
        self._run = np.where(faulty, self._run + 1, 0)
        if self.release_after is not None:
            released = faulty & (self._run > self.release_after)
            self.n_released += int(released.sum())
            faulty = faulty & ~released
        used = r.copy()
        if np.any(faulty):
            if self._count >= self.order:
                ext = (self.coeffs @ self._hist[::-1]) / self.delta  # eqs. 21, 27
            else:
                ext = np.zeros(self.m)
            if self.guard:
                ext = np.where(ext * ext / np.diag(S) > self.threshold, 0.0, ext)
            used[faulty] = ext[faulty]
            self.n_faults += int(faulty.sum())
        self._hist = np.roll(self._hist, -1, axis=0)
        self._hist[-1] = used
        self._count += 1
        return used, faulty, stat


def chi2_newton_kf_update(x, P, z, H, R, detector: ChiSquareNewton) -> UpdateResult:
    """Linear KF update (Joseph form) with per-dimension χ² screening and Newton replacement.

    Faulty measurements are replaced by z'(i) = ẑ(i) + V'_k(i) before the update (Cai et al. 2020 eq. 28).
    ``info`` has ``faulty`` (bool mask), ``stat`` (χ² statistics) and ``z_used``.
    The reported innovation/nis are those of the raw measurement.
    """
    x, P, z, H, R = check_linear_update(x, P, z, H, R)
    zhat = H @ x
    D = symmetrize(H @ P @ H.T + R)  # eq. 13
    used, faulty, stat = detector.screen(z - zhat, D)
    z_used = zhat + used
    if detector.weight_replacements and np.any(faulty):
        # a replaced value is a measurement with the error of its extrapolation: the Newton
        # combination of white innovations has variance Σc²/δ² · D_ii, so R_ii = that − (H P Hᵀ)_ii
        # (never below R_ii); a replacement zeroed by the guard carries no information and is
        # left out (used with R it would shrink P by a measurement that was not made)
        R = R.copy()
        idx = np.flatnonzero(faulty)
        g = float(np.sum(detector.coeffs ** 2)) / detector.delta ** 2
        Dd = np.diag(D)
        R[idx, idx] = np.maximum(R[idx, idx], g * Dd[idx] - (Dd[idx] - np.diag(R)[idx]))
        keep = ~(faulty & (used == 0.0))
        if not keep.any():
            res = UpdateResult(x.copy(), P.copy(), z - zhat, D, np.zeros((x.shape[0], z.shape[0])), 0.0, zhat, P @ H.T)
        else:
            res = _joseph(x, P, z_used[keep], zhat[keep], H[keep], R[np.ix_(keep, keep)])
    else:
        res = _joseph(x, P, z_used, zhat, H, R)
    raw = z - zhat
    y = np.linalg.solve(cholesky_lower(D), raw)
    res.innovation = raw
    res.nis = float(y @ y)
    res.info.update(faulty=faulty, stat=stat, z_used=z_used)
    return res
