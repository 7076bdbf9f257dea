"""Adaptive filters composable with the generic filters.

1. Innovation-based adaptive KF, AKF (Fang 2017 §2, eqs. 6–15) – :class:`AKF`
   ε_k = z − H x⁻ (6); P̂_ε = (1/N) Σ_window ε εᵀ (7, window of the last N innovations);
   R̂ = P̂_ε − H P⁻ Hᵀ (8); Q̂ = K P̂_ε Kᵀ + P_k − Φ P_{k−1} Φᵀ (14); filter eq. 15 with the gain
   K = P⁻ Hᵀ (H P⁻ Hᵀ + R̂)⁻¹ (= P⁻ Hᵀ P̂_ε⁻¹ whenever the PD guard leaves R̂ untouched) and the
   Joseph covariance with R̂.  Until the window is full the nominal Q₀, R₀ are used.
2. Improved AKF, IAKF (Fang 2017 §3, eqs. 16–26) – :class:`IAKF`
   R from the geometry: G = (H_SIᵀ H_SI)⁻¹ with H_SI = [e_j, 1] the line-of-sight rows of the
   corrected-SINS position (17–19), GDOP = sqrt(tr G) (20); σ² = [sum of the four position/clock
   error variances]/GDOP² (24–25), the same for rates with GDOP_ENU (the trace of G is invariant
   under the ECEF→ENU rotation, so GDOP_ENU = GDOP for the same geometry).  The four variances
   come either from E(M Mᵀ), M = (AᵀA)⁻¹Aᵀ ε the least-squares solution of the windowed
   innovations (eqs. 21–22, ``r_source="lsq"``, default), or from the diagonal of the windowed
   correction covariance P_Δx̂ = K P̂_ε Kᵀ (eq. 13, ``r_source="correction"``, the paper's
   wording, which collapses R̂ when the prior is tight).
   Q̂ = (1/N) Σ_{i=k−N+1..k} (Δx̂_i Δx̂_iᵀ + P_i − Φ P_{i−1} Φᵀ) (26), Δx̂_i = K_i ε_i (12).
   R̂ feeds the next update (it needs this update's gain).  Both Q̂ and R̂ are guarded PD.
   Start (``start``): "full-window" keeps the given Q₀, R₀ until the window holds N terms (the
   AKF's rule); "growing" estimates from the first epoch on with the n < N terms available (each
   estimate is the mean of its terms, so it is weighted by their count), then slides with N.
   Q̂ may be projected onto the model's noise structure (``q_structure``, :func:`project_q`) and
   capped there by the given noise (``q_ceiling``): the noise variances of Q̂ may fall below
   those of the given Q (projected the same way) but not exceed them.
3. Adaptive fading factor (AFF) and adaptive fading matrix (AFM) for UKF/AUKF (Sun et al. 2012) –
   :func:`fading_terms`, :func:`fading_factor`, :func:`fading_matrix`, :func:`apply_fading`,
   :class:`FadingUKF`.
   Sigma-point equivalents (eqs. 11–12): H = P_xzᵀ P⁻⁻¹, A = H P′ Hᵀ (P′ = propagated covariance
   without process noise; eq. 12's printed "A = P′" read in measurement space, as eq. 1 requires an m×m
   A), B = P_zz − A.  Per-innovation χ² reasoning (eqs. 1, 5–6): the i-th innovation is consistent
   when y_i²/(ω_i A_ii + B_ii) ≤ T (T = χ²₁ quantile), giving
   ω_i = max(1, (y_i²/T − B_ii)/A_ii).  AFF: λ = max(1, ω_1..ω_m) (eq. 1) scales the whole P′;
   AFM: Ω = diag(ω) mapped to state space S = (H′ᵀH′)⁻¹ H′ᵀ Ω H′ over the non-zero columns H′ of
   H (eqs. 7–9), identity on the all-zero columns (eq. 10).  The faded prediction is
   P⁻_f = S ⊙ P′ + (P⁻ − P′) (eq. 13, read as "fade the noiseless part, keep the process noise");
   the product S P′ is symmetrised (and, if that is not PD, replaced by D P′ D with
   D = diag(√diag S)).  Then the sigma points are redrawn from P⁻_f and the measurement update is
   redone (Sun et al. 2012, steps 5–8).
"""

from __future__ import annotations

from collections import deque

import numpy as np

from ultratight.chi2 import chdtri
from ultratight.errors import FilterError
from ultratight.fusion.estimators.filters import (
    UpdateResult,
    _gain,
    _nis,
    aukf_measure,
    aukf_predict,
    gain_update,
    sigma_measure,
    sigma_predict,
    unscented_scheme,
)
from ultratight.fusion.estimators.guards import (
    as_matrix,
    as_vector,
    check_covariance,
    check_state,
    cholesky_lower,
    nearest_pd,
    symmetrize,
)

__all__ = [
    "AKF",
    "IAKF",
    "gdop",
    "project_q",
    "fading_terms",
    "fading_factor",
    "fading_matrix",
    "apply_fading",
    "FadingUKF",
    "aukf_fading_step",
]


Q_STRUCTURES = ("full", "model", "model-diag")
IAKF_STARTS = ("full-window", "growing")


def _floor(M: np.ndarray, rel: float, absolute: float) -> float:
    return max(absolute, rel * float(np.max(np.abs(np.diag(M)))) if M.size else absolute)


class AKF:
    """Innovation-based adaptive Kalman filter (Fang 2017 eqs. 6–15).

    ``AKF(x0, P0, Q0, R0, window=N)``; ``predict(Phi)``; ``update(z, H) -> UpdateResult`` (info has
    ``Q_hat``, ``R_hat``).  ``adapt_q``/``adapt_r`` switch the two estimators; ``floor`` is the
    absolute eigenvalue floor of the PD guard (relative floor 1e-9 of the largest diagonal).
    """

    def __init__(self, x0, P0, Q0, R0, window: int = 20, adapt_q: bool = True, adapt_r: bool = True,
                 floor: float = 1e-12):
        if int(window) < 1:
            raise FilterError(f"window must be an integer ≥ 1, got {window}")
        self.x = as_vector("x0", x0)
        n = self.x.shape[0]
        self.P = check_covariance("P0", P0, n)
        self.Q = check_covariance("Q0", Q0, n)
        self.R = check_covariance("R0", R0, None)
        self.N = int(window)
        self.eps = deque(maxlen=self.N)
        self.adapt_q, self.adapt_r = adapt_q, adapt_r
        self.floor = floor
        self._Phi = np.eye(n)
        self._P_prev = self.P.copy()

    def predict(self, Phi):
        n = self.x.shape[0]
        Phi = as_matrix("Phi", Phi, (n, n))
        self._Phi, self._P_prev = Phi, self.P
        self.x = Phi @ self.x
        self.P = symmetrize(Phi @ self.P @ Phi.T + self.Q)  # eq. 15, line 2
        return self.x, self.P

    def _innovation_cov(self):
        E = np.array(self.eps)
        return symmetrize(E.T @ E / E.shape[0])  # eq. 7

    def update(self, z, H) -> UpdateResult:
        n = self.x.shape[0]
        z = as_vector("z", z)
        m = z.shape[0]
        H = as_matrix("H", H, (m, n))
        if self.R.shape != (m, m):
            raise FilterError(f"z: length {m} does not match R0 of shape {self.R.shape}")
        Pp = self.P
        eps = z - H @ self.x  # eq. 6
        self.eps.append(eps)
        HPH = symmetrize(H @ Pp @ H.T)
        full = len(self.eps) == self.N
        if full:
            Pe = self._innovation_cov()
            if self.adapt_r:
                self.R = nearest_pd(Pe - HPH, _floor(Pe, 1e-9, self.floor))  # eq. 8 (guarded)
        else:
            Pe = HPH + self.R
        S = symmetrize(HPH + self.R)
        K = _gain(Pp @ H.T, S)  # eq. 15, line 3
        self.x = self.x + K @ eps
        IKH = np.eye(n) - K @ H
        self.P = symmetrize(IKH @ Pp @ IKH.T + K @ self.R @ K.T)  # eq. 15, line 5
        if full and self.adapt_q:
            Qh = K @ Pe @ K.T + self.P - self._Phi @ self._P_prev @ self._Phi.T  # eq. 14
            self.Q = nearest_pd(Qh, _floor(Qh, 1e-9, self.floor))
        check_state(self.x, self.P, "AKF.update")
        res = UpdateResult(self.x, self.P, eps, S, K, _nis(eps, S), H @ (self.x - K @ eps), Pp @ H.T)
        res.info.update(Q_hat=self.Q, R_hat=self.R)
        return res


def gdop(los_unit, C=None) -> float:
    """GDOP = sqrt(tr (H_SIᵀ H_SI)⁻¹), H_SI = [e_j, 1] (Fang 2017 eqs. 17–20).

    ``los_unit`` (k, 3) unit line-of-sight vectors (any frame; ``C`` optionally rotates them first,
    e.g. ECEF→ENU for GDOP_ENU — the trace, hence GDOP, is rotation invariant).
    """
    e = as_matrix("los_unit", los_unit, (None, 3))
    if e.shape[0] < 4:
        raise FilterError(f"los_unit: GDOP needs at least 4 satellites, got {e.shape[0]}")
    if C is not None:
        e = e @ as_matrix("C", C, (3, 3)).T
    Hs = np.hstack([e, np.ones((e.shape[0], 1))])
    try:
        G = np.linalg.inv(Hs.T @ Hs)  # eq. 19
    except np.linalg.LinAlgError:
        raise FilterError("los_unit: degenerate satellite geometry (HᵀH singular)") from None
    return float(np.sqrt(np.trace(G)))  # eq. 20


class IAKF:
    """Improved adaptive KF (Fang 2017 §3): GDOP-based R̂ (eqs. 16–25) and windowed Q̂ (eq. 26).

    Parameters: ``pr_rows``/``prr_rows`` index the pseudorange / pseudorange-rate rows of z;
    ``pos_clk_idx`` the four state indices (δx, δy, δz, δt_u) and ``vel_drift_idx`` the four
    (δv_E, δv_N, δv_U, δt_ru) summed in eq. 25.  ``update(z, H, los_unit)``.
    ``r_source``: "lsq" (default) takes the numerator of eq. 24 as tr E(M Mᵀ) with M the
    least-squares position/clock solution of the windowed pseudorange innovations (eqs. 21–22 read
    directly; likewise for rates); "correction" takes it from P_Δx̂ = K P̂_ε Kᵀ (eq. 13, the
    paper's "结合式(13)").  The latter is the paper's literal wording but collapses R̂ when the
    prior is tight (K → 0), see docs/filters.md.
    ``q_structure``: "full" (default) uses eq. 26's window matrix as Q̂; "model" / "model-diag"
    project it onto the noise structure of the model (eq. 3: Q = Σ q_i Q_i over the white noises
    of W, :func:`project_q`, fitted on all entries / on the diagonal), with the basis ``q_basis``
    (k, n, n) and the fixed part ``q_fixed`` set by the caller before each update.
    ``start``: "full-window" (default: Q₀, R₀ until N terms exist) or "growing" (estimates from the
    first epoch with the terms available).  ``q_ceiling`` (model structures only): the projected
    noise variances are capped at those of ``Q_given`` (the given noise, Q₀ unless the caller
    sets it each epoch), projected onto the same basis.
    With ``r_source="lsq"`` each epoch's term is tr E(M Mᵀ)/GDOP² with that epoch's geometry A
    and GDOP (the best satellites change over a window).
    """

    def __init__(self, x0, P0, Q0, R0, pr_rows, prr_rows, pos_clk_idx, vel_drift_idx,
                 window: int = 20, adapt_q: bool = True, adapt_r: bool = True,
                 floor: float = 1e-12, r_source: str = "lsq", q_structure: str = "full",
                 start: str = "full-window", q_ceiling: bool = False):
        if int(window) < 1:
            raise FilterError(f"window must be an integer ≥ 1, got {window}")
        if r_source not in ("lsq", "correction"):
            raise FilterError(f"r_source: expected 'lsq' or 'correction', got {r_source!r}")
        if q_structure not in Q_STRUCTURES:
            raise FilterError(f"q_structure: expected one of {', '.join(Q_STRUCTURES)}, got {q_structure!r}")
        if start not in IAKF_STARTS:
            raise FilterError(f"start: expected one of {', '.join(IAKF_STARTS)}, got {start!r}")
        if q_ceiling and q_structure == "full":
            raise FilterError("q_ceiling: needs a model q_structure ('model' or 'model-diag'), got 'full'")
        self.r_source = r_source
        self.q_structure = q_structure
        self.start = start
        self.q_ceiling = bool(q_ceiling)
        self.q_basis = None      # (k, n, n) discretised Q of each model noise at unit PSD ("model*")
        self.q_fixed = None      # (n, n) the part of Q that is not estimated
        self.q_w = None          # the last estimated noise variances (PSDs) of the basis
        self.x = as_vector("x0", x0)
        n = self.x.shape[0]
        self.P = check_covariance("P0", P0, n)
        self.Q = check_covariance("Q0", Q0, n)
        self.Q_given = self.Q.copy()
        self.R = check_covariance("R0", R0, None)
        self.pr_rows = np.asarray(pr_rows, dtype=int)
        self.prr_rows = np.asarray(prr_rows, dtype=int)
        self.pos_clk_idx = np.asarray(pos_clk_idx, dtype=int)
        self.vel_drift_idx = np.asarray(vel_drift_idx, dtype=int)
        for name, idx, lim in (("pr_rows", self.pr_rows, self.R.shape[0]), ("prr_rows", self.prr_rows, self.R.shape[0]),
                               ("pos_clk_idx", self.pos_clk_idx, n), ("vel_drift_idx", self.vel_drift_idx, n)):
            if idx.size and (idx.min() < 0 or idx.max() >= lim):
                raise FilterError(f"{name}: indices must lie in [0, {lim}), got {idx.tolist()}")
        self.N = int(window)
        self.eps = deque(maxlen=self.N)
        self.rterms = deque(maxlen=self.N)   # r_source="lsq": per-epoch (pseudorange, rate) terms of eq. 24
        self.qterms = deque(maxlen=self.N)
        self.adapt_q, self.adapt_r = adapt_q, adapt_r
        self.floor = floor
        self._Phi = np.eye(n)
        self._P_prev = self.P.copy()

    def ready(self, n_terms: int) -> bool:
        """Whether a window of ``n_terms`` terms gives an estimate (all N, or ≥ 1 when growing)."""
        return n_terms >= (1 if self.start == "growing" else self.N)

    # same time update as the AKF (eq. 15), keeping Phi and P_{k-1} for the windowed Q estimate
    predict = AKF.predict

    def update(self, z, H, los_unit=None, gdop_pr: float | None = None, gdop_prr: float | None = None) -> UpdateResult:
        """One IAKF update. ``los_unit`` (k, 3): line-of-sight unit vectors of the satellites, in the
        order of ``pr_rows`` (and ``prr_rows``); it gives GDOP (eqs. 17–20) and, for
        ``r_source="lsq"``, the geometry A.  ``gdop_pr``/``gdop_prr`` may be given instead
        (``r_source="correction"`` only)."""
        n = self.x.shape[0]
        z = as_vector("z", z)
        m = z.shape[0]
        H = as_matrix("H", H, (m, n))
        if self.R.shape != (m, m):
            raise FilterError(f"z: length {m} does not match R0 of shape {self.R.shape}")
        A = None
        if los_unit is not None:
            e = as_matrix("los_unit", los_unit, (self.pr_rows.size, 3))
            A = np.hstack([e, np.ones((e.shape[0], 1))])  # eq. 17
            gdop_pr = gdop(e) if gdop_pr is None else gdop_pr
        elif self.r_source == "lsq":
            raise FilterError("los_unit: required with r_source='lsq' (satellite geometry)")
        if gdop_pr is None or not (np.isfinite(gdop_pr) and gdop_pr > 0):
            raise FilterError(f"gdop_pr: expected a positive finite GDOP (or los_unit), got {gdop_pr}")
        gdop_prr = gdop_pr if gdop_prr is None else gdop_prr  # ENU rotation leaves tr G unchanged
        Pp = self.P
        eps = z - H @ self.x  # eq. 6
        self.eps.append(eps)
        S = symmetrize(H @ Pp @ H.T + self.R)
        K = _gain(Pp @ H.T, S)
        dx = K @ eps  # eq. 12
        self.x = self.x + dx
        IKH = np.eye(n) - K @ H
        self.P = symmetrize(IKH @ Pp @ IKH.T + K @ self.R @ K.T)
        if self.adapt_r:
            if self.r_source == "correction":
                if self.ready(len(self.eps)):
                    E = np.array(self.eps)
                    Pe = symmetrize(E.T @ E / E.shape[0])  # eq. 7
                    d = np.diag(K @ Pe @ K.T)  # eq. 13
                    r_pr = d[self.pos_clk_idx].sum() / gdop_pr**2  # eqs. 24–25, pseudorange
                    r_prr = d[self.vel_drift_idx].sum() / gdop_prr**2  # eq. 25, rate
                    self._set_r(r_pr, r_prr)
            else:
                # eqs. 21–22 read directly: M = (AᵀA)⁻¹Aᵀ Δδρ of this epoch's innovations, tr E(M Mᵀ) = σ² GDOP²
                Lsq = np.linalg.solve(A.T @ A, A.T)
                Mpr = Lsq @ eps[self.pr_rows]
                Mprr = Lsq @ eps[self.prr_rows]
                self.rterms.append((float(Mpr @ Mpr) / gdop_pr**2, float(Mprr @ Mprr) / gdop_prr**2))
                if self.ready(len(self.rterms)):
                    r_pr, r_prr = np.mean(np.array(self.rterms), axis=0)  # eqs. 24–25 over the window
                    self._set_r(r_pr, r_prr)
        self.qterms.append(np.outer(dx, dx) + self.P - self._Phi @ self._P_prev @ self._Phi.T)
        if self.adapt_q and self.ready(len(self.qterms)):
            Qh = sum(self.qterms) / len(self.qterms)  # eq. 26 (growing: over the terms available)
            if self.q_structure == "full":
                self.Q = nearest_pd(Qh, _floor(Qh, 1e-9, self.floor))
            else:
                diagonal = self.q_structure == "model-diag"
                ceiling = None
                if self.q_ceiling:
                    _, ceiling = project_q(self.Q_given, self.q_basis, self.q_fixed, np.diag(Pp), diagonal=diagonal,
                                           floor=self.floor)
                self.Q, self.q_w = project_q(Qh, self.q_basis, self.q_fixed, np.diag(Pp), diagonal=diagonal,
                                             floor=self.floor, ceiling=ceiling)
        check_state(self.x, self.P, "IAKF.update")
        res = UpdateResult(self.x, self.P, eps, S, K, _nis(eps, S), H @ (self.x - dx), Pp @ H.T)
        res.info.update(Q_hat=self.Q, R_hat=self.R)
        return res

    def _set_r(self, r_pr, r_prr):
        Rn = self.R.copy()
        Rn[self.pr_rows, self.pr_rows] = max(float(r_pr), self.floor)
        Rn[self.prr_rows, self.prr_rows] = max(float(r_prr), self.floor)
        self.R = Rn


def project_q(Q_hat, basis, fixed=None, scale=None, diagonal=False, floor=1e-12, ceiling=None):
    """Q̂ of eq. 26 projected onto the noise structure of the model (Fang 2017 eq. 3).

    The model admits only Q = Q_fixed + Σ_i q_i Q_i, q_i ≥ 0, with Q_i the discretised process
    noise of the i-th white noise of W alone at unit PSD (G_i Q_w,i G_iᵀ through the
    discretisation).  The noise variances are the non-negative least-squares fit
    q = argmin ‖D⁻¹(Q̂ − Q_fixed − Σ q_i Q_i)D⁻¹‖_F (all entries, or the diagonal only with
    ``diagonal=True``), D = diag(√scale) — the fit is made relative to the predicted covariance
    (``scale`` = its diagonal), so states of different units weigh alike; each q_i is then
    floored so that its Q_i adds at least ``floor`` on its largest diagonal entry.  Whatever of
    Q̂ falls outside the span (noise on states the model drives by no white noise, arbitrary
    couplings) is discarded.  ``ceiling`` (k,), optional: upper bounds of the q_i (applied after
    the floor; a bound below the floor is raised to it).  Returns (Q, q).
    """
    if basis is None:
        raise FilterError("q_basis: the model noise basis must be set before a projected Q estimate")
    B = np.asarray(basis, float)
    if B.ndim != 3 or B.shape[1:] != Q_hat.shape:
        raise FilterError(f"q_basis: expected (k, {Q_hat.shape[0]}, {Q_hat.shape[0]}), got {B.shape}")
    F = np.zeros_like(Q_hat) if fixed is None else np.asarray(fixed, float)
    d = np.ones(Q_hat.shape[0]) if scale is None else 1.0 / np.sqrt(np.maximum(np.asarray(scale, float), 1e-300))
    W = d[:, None] * d[None, :]
    Bn = B * W[None]
    Rn = (Q_hat - F) * W
    if diagonal:
        A, b = np.diagonal(Bn, axis1=1, axis2=2), np.diag(Rn)
    else:
        A, b = Bn.reshape(B.shape[0], -1), Rn.ravel()
    from scipy.optimize import nnls       # here: scipy.optimize is slow to import and rarely needed
    q, _ = nnls(A.T, b)
    qmin = floor / np.maximum(np.max(np.diagonal(B, axis1=1, axis2=2), axis=1), 1e-300)
    q = np.maximum(q, qmin)
    if ceiling is not None:
        q = np.minimum(q, np.maximum(np.asarray(ceiling, float), qmin))
    return symmetrize(F + np.tensordot(q, B, axes=1)), q


# --------------------------------------------------------------------------- fading (Sun et al. 2012)


def fading_terms(Pxz, P_pred, P_noiseless, Pzz):
    """Sigma-point equivalents (Sun et al. 2012 eqs. 11–12): H = P_xzᵀ P⁻⁻¹, A = H P′ Hᵀ, B = P_zz − A."""
    L = cholesky_lower(P_pred, "P_pred")
    H = np.linalg.solve(L.T, np.linalg.solve(L, Pxz)).T  # P_xzᵀ P⁻¹ (P symmetric)
    A = symmetrize(H @ P_noiseless @ H.T)
    B = symmetrize(Pzz - A)
    return H, A, B


def _omega(y, A, B, threshold):
    a = np.diag(A)
    b = np.diag(B)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (y * y / threshold - b) / a  # eq. 6 (χ² consistency solved for the factor)
    s = np.where(a > 0, s, 1.0)
    return np.maximum(1.0, s)


def fading_factor(y, A, B, threshold: float) -> float:
    """AFF (Sun et al. 2012 eq. 1): λ = max(1, s_1..s_m), s_i = (y_i²/T − B_ii)/A_ii."""
    return float(np.max(_omega(np.asarray(y, float), A, B, threshold)))


def fading_matrix(y, A, B, H, threshold: float, zero_tol: float = 1e-12, nonzero_cols=None) -> np.ndarray:
    """AFM (Sun et al. 2012 eqs. 5–10): S = (H′ᵀH′)⁻¹ H′ᵀ Ω H′ on the non-zero columns of H, I elsewhere.

    The all-zero columns are found numerically (``zero_tol`` relative to the largest column) unless
    ``nonzero_cols`` gives them from the model's structure (this project's choice for the SINS model, whose
    sigma-point H = P_xzᵀ P⁻¹ is only numerically ≈ 0 on the unmeasured states).
    """
    y = np.asarray(y, float)
    H = np.asarray(H, float)
    n = H.shape[1]
    omega = _omega(y, A, B, threshold)  # eq. 5–6
    Om = np.diag(omega)
    if nonzero_cols is None:
        colmax = np.max(np.abs(H), axis=0)
        nz = colmax > zero_tol * max(colmax.max(), 1e-300)  # eq. 8: partition off all-zero columns
    else:
        nz = np.zeros(n, bool)
        nz[np.asarray(nonzero_cols, int)] = True
    S = np.eye(n)
    Hp = H[:, nz]
    HtH = Hp.T @ Hp
    try:
        Snz = np.linalg.solve(HtH, Hp.T @ Om @ Hp)  # eqs. 7 / 9
    except np.linalg.LinAlgError:
        Snz = np.linalg.lstsq(HtH, Hp.T @ Om @ Hp, rcond=None)[0]
    idx = np.flatnonzero(nz)
    S[np.ix_(idx, idx)] = Snz  # eq. 10
    return S


def apply_fading(P_pred, P_noiseless, fade) -> np.ndarray:
    """Faded prediction P⁻_f = fade ⊙ P′ + (P⁻ − P′) (Sun et al. 2012 eq. 13); ``fade`` scalar λ or matrix S."""
    Qpart = P_pred - P_noiseless
    if np.isscalar(fade) or np.ndim(fade) == 0:
        return symmetrize(float(fade) * P_noiseless + Qpart)
    S = np.asarray(fade, float)
    SP = symmetrize(S @ P_noiseless)
    try:
        np.linalg.cholesky(SP + Qpart)
        return symmetrize(SP + Qpart)
    except np.linalg.LinAlgError:
        d = np.sqrt(np.maximum(np.diag(S), 1.0))
        return symmetrize(P_noiseless * d[:, None] * d[None, :] + Qpart)


class FadingUKF:
    """UKF / AUKF with adaptive fading factor (``mode="aff"``) or matrix (``mode="afm"``).

    ``mode=None`` gives the plain (A)UKF.  ``augmented=True`` uses the AUKF with f(x, w), h(x, v)
    (non-additive noise); otherwise f(x), h(x) with additive Q, R.  ``alpha_chi2`` is the χ²₁
    significance of the per-innovation test (threshold T = χ²₁ upper-α quantile).
    ``step(z, f, h, Q, R) -> UpdateResult`` with ``info["fade"]`` (λ or S).
    """

    def __init__(self, x0, P0, mode: str | None = "afm", augmented: bool = False, alpha_chi2: float = 0.05,
                 alpha: float = 1.0, beta: float = 2.0, kappa: float = 0.0):
        if mode not in (None, "aff", "afm"):
            raise FilterError(f"mode: expected None, 'aff' or 'afm', got {mode!r}")
        if not (0.0 < alpha_chi2 < 1.0):
            raise FilterError(f"alpha_chi2 must be in (0, 1), got {alpha_chi2}")
        self.x = as_vector("x0", x0)
        self.P = check_covariance("P0", P0, self.x.shape[0])
        self.mode = mode
        self.augmented = augmented
        self.threshold = float(chdtri(1, alpha_chi2))
        self.ut = (alpha, beta, kappa)

    def _measure(self, x, P, h, R, m):
        if self.augmented:
            return aukf_measure(x, P, h, R, *self.ut, m=m)
        zhat, Pzz0, Pxz = sigma_measure(x, P, h, unscented_scheme(x.shape[0], *self.ut), 1.0, False, m)
        return zhat, symmetrize(Pzz0 + R), Pxz

    def step(self, z, f, h, Q, R) -> UpdateResult:
        n = self.x.shape[0]
        z = as_vector("z", z)
        m = z.shape[0]
        R = check_covariance("R", R, None)
        if self.augmented:
            xp, Pp, Pnl = aukf_predict(self.x, self.P, f, Q, *self.ut, return_noiseless=True)
        else:
            Q = check_covariance("Q", Q, n)
            xp, Pp, Pnl = sigma_predict(self.x, self.P, f, Q, unscented_scheme(n, *self.ut), return_noiseless=True)
        fade = 1.0
        Pf = Pp
        if self.mode is not None:
            zhat, Pzz, Pxz = self._measure(xp, Pp, h, R, m)
            y = z - zhat
            H, A, B = fading_terms(Pxz, Pp, Pnl, Pzz)
            if self.mode == "aff":
                fade = fading_factor(y, A, B, self.threshold)
            else:
                fade = fading_matrix(y, A, B, H, self.threshold)
            Pf = apply_fading(Pp, Pnl, fade)
        # redraw the sigma points from the (faded) prediction and update (Sun et al. 2012, steps 5–8)
        zhat, Pzz, Pxz = self._measure(xp, Pf, h, R, m)
        res = gain_update(xp, Pf, z, zhat, Pzz, Pxz, np.zeros((m, m)))
        res.info["fade"] = fade
        self.x, self.P = res.x, res.P
        return res


def aukf_fading_step(x, P, z, f, h, Q, R, mode=None, threshold: float | None = None, alpha: float = 1.0,
                     beta: float = 2.0, kappa: float = 0.0, nonzero_cols=None) -> UpdateResult:
    """One step of Sun et al. 2012's augmented UKF with process *and* measurement noise in the state (§3).

    ``f(X, W) -> X⁺`` and ``h(X, V) -> Z`` act on arrays of points (rows).  Steps 1–3:
    ``x^a = [x; w; v]``, ``P^a = diag(P, Q, R)``, L = n + q + m, 2L+1 points through f → x̂⁻, P⁻; the
    same points with the noise parts zero → P′.  Step 4: ζ_i = h(χ_i^x, χ_i^v) of the propagated
    points → ẑ, P_xz, P_zz.  ``mode=None`` (the "UKF"): K = P_xz P_zz⁻¹ from these points (step 8).
    ``mode="aff"``/``"afm"``: λ (eq. 1) or S (eqs. 5–10) from eqs. 11–12, P^l by eq. 13, then the
    redraw ``x^b = [x; v]``, L′ = n + m (steps 5–7) and the update (step 8).  ``threshold``: the
    χ²₁ bound ε_i (default the 1 % quantile; the paper gives no α).  ``info["fade"]`` holds λ or S.
    """
    x = as_vector("x", x)
    n = x.shape[0]
    P = check_covariance("P", P, n)
    Q = check_covariance("Q", Q, None)
    R = check_covariance("R", R, None)
    z = as_vector("z", z, R.shape[0])
    q, m = Q.shape[0], R.shape[0]
    if mode not in (None, "aff", "afm"):
        raise FilterError(f"mode: expected None, 'aff' or 'afm', got {mode!r}")
    T = float(chdtri(1, 0.01)) if threshold is None else float(threshold)
    La = np.zeros((n + q + m, n + q + m))
    La[:n, :n] = cholesky_lower(P, "P")
    La[n:n + q, n:n + q] = cholesky_lower(Q, "Q")
    La[n + q:, n + q:] = cholesky_lower(R, "R")
    sch = unscented_scheme(n + q + m, alpha, beta, kappa)          # steps 1–2
    Xa = np.concatenate([x, np.zeros(q + m)])[None, :] + sch.xi @ La.T
    X, W, V = Xa[:, :n], Xa[:, n:n + q], Xa[:, n + q:]
    Xs = np.asarray(f(X, W), float)                                 # step 3
    xp = sch.wm @ Xs
    D = Xs - xp
    Pp = symmetrize((D.T * sch.wc) @ D)
    Z = np.asarray(h(Xs, V), float)                                 # step 4
    zhat = sch.wm @ Z
    DZ = Z - zhat
    Pzz = symmetrize((DZ.T * sch.wc) @ DZ)
    Pxz = (D.T * sch.wc) @ DZ
    if mode is None:
        res = gain_update(xp, Pp, z, zhat, Pzz, Pxz, np.zeros((m, m)))
        res.info["fade"] = 1.0
        return res
    X0 = np.asarray(f(X, np.zeros_like(W)), float)                  # step 3, noise parts zero
    D0 = X0 - sch.wm @ X0
    Pnl = symmetrize((D0.T * sch.wc) @ D0)
    Hs, A, B = fading_terms(Pxz, Pp, Pnl, Pzz)                      # eqs. 11–12
    y = z - zhat
    fade = fading_factor(y, A, B, T) if mode == "aff" else fading_matrix(y, A, B, Hs, T, nonzero_cols=nonzero_cols)
    Pl = apply_fading(Pp, Pnl, fade)                                # eq. 13
    sch2 = unscented_scheme(n + m, alpha, beta, kappa)             # steps 5–6
    Lb = np.zeros((n + m, n + m))
    Lb[:n, :n] = cholesky_lower(Pl, "faded P")
    Lb[n:, n:] = La[n + q:, n + q:]
    Xb = np.concatenate([xp, np.zeros(m)])[None, :] + sch2.xi @ Lb.T
    Zb = np.asarray(h(Xb[:, :n], Xb[:, n:]), float)                 # step 7
    zb = sch2.wm @ Zb
    DZb = Zb - zb
    Pzzb = symmetrize((DZb.T * sch2.wc) @ DZb)
    Pxzb = ((Xb[:, :n] - xp).T * sch2.wc) @ DZb
    res = gain_update(xp, Pl, z, zb, Pzzb, Pxzb, np.zeros((m, m)))  # step 8
    res.info["fade"] = fade
    return res
