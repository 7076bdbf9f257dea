"""Generic Gaussian filters (numpy reference implementations, for 1–20 Hz use and cross-checks).

One uniform functional interface::

    x, P = <kind>_predict(x, P, f_or_F, Q, ...)
    res  = <kind>_update(x, P, z, h_or_H, R, ...)   # -> UpdateResult(x, P, innovation, S, K, nis, z_pred, P_xz)

with ``kind`` in ``kf`` (linear, Joseph-form update), ``ekf``, ``ukf`` (scaled sigma points α, β, κ),
``aukf`` (augmented UKF for non-additive noise), ``ckf`` (third-degree cubature, 2n points) and
``srckf`` (square-root CKF, carries S with P = S Sᵀ instead of P).  A small stateful wrapper
:class:`Filter` adds divergence flagging on top of the pure functions.

Equation map (Zhao et al. 2014 §2.2, after Arasaratnam & Haykin 2009; see docs/references.md)
------------------------------------------------------------------------------------------
* CKF time update: P = S Sᵀ (4); points X = S ξ_j + x̂ (5), ξ_j = ±√n e_j; X* = f(X) (6);
  x̂⁻ = mean X* (7); P⁻ = mean X* X*ᵀ − x̂⁻x̂⁻ᵀ + Q (8).
* CKF measurement update: P⁻ = S Sᵀ (9); points **redrawn** from (x̂⁻, P⁻) (10) – the propagated
  points of (6) are never reused; Z = h(X) (11); ẑ (12); P_zz (13); P_xz (14); W = P_xz P_zz⁻¹ (15);
  x̂ = x̂⁻ + W (z − ẑ) (16); P = P⁻ − W P_zz Wᵀ (17).
* UKF / AUKF (Sun et al. 2012 §3): 2L+1 scaled sigma points, λ = α²(L+κ) − L, W0m = λ/(L+λ),
  W0c = W0m + 1 − α² + β, Wi = 1/(2(L+λ)); the AUKF augments the state with the process noise for
  the time update (L = n+q) and with the measurement noise for the update (L' = n+m, Sun et al. 2012 step 5).
* KF: x⁻ = Φx, P⁻ = ΦPΦᵀ + Q; K = P⁻Hᵀ S⁻¹, S = HP⁻Hᵀ + R;
  P = (I − KH)P⁻(I − KH)ᵀ + KRKᵀ (Joseph form, Cai et al. 2020 eq. 5).

All covariances are symmetrised after every step; inputs are validated by
:mod:`ultratight.fusion.estimators.guards` (FilterError) and a non-finite result raises DivergenceError.
Sigma points are stored as rows: ``X[j] = x + L @ xi[j]`` with ``P = L Lᵀ`` (lower Cholesky).
Callables ``f``/``h`` take one vector unless ``vectorized=True`` (then an (N, n) array of rows).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache
from typing import Callable

import numpy as np

from ultratight.errors import DivergenceError, FilterError
from ultratight.fusion.estimators.guards import (
    check_linear_update,
    DivergenceMonitor,
    as_matrix,
    as_vector,
    check_covariance,
    check_state,
    cholesky_lower,
    symmetrize,
)

__all__ = [
    "UpdateResult",
    "SigmaScheme",
    "cubature_scheme",
    "unscented_scheme",
    "kf_predict",
    "kf_update",
    "ekf_predict",
    "ekf_update",
    "sigma_predict",
    "sigma_measure",
    "sigma_update",
    "gain_update",
    "ukf_predict",
    "ukf_update",
    "ckf_predict",
    "ckf_update",
    "aukf_predict",
    "aukf_update",
    "srckf_predict",
    "srckf_update",
    "tria",
    "Filter",
]


@dataclass
class UpdateResult:
    """Result of a measurement update.

    x, P: posterior state and covariance; innovation r = z − ẑ; S = innovation covariance P_zz
    (including the R actually used); K gain; nis = rᵀ S⁻¹ r; z_pred = ẑ; P_xz cross covariance
    (sigma-point filters; P⁻Hᵀ for KF/EKF). ``sqrt_P`` is set by the square-root CKF (P = S Sᵀ).
    ``info`` carries extras of the robust/adaptive variants (R̄, ϑ, fault masks, ...).
    """

    x: np.ndarray
    P: np.ndarray
    innovation: np.ndarray
    S: np.ndarray
    K: np.ndarray
    nis: float
    z_pred: np.ndarray
    P_xz: np.ndarray
    sqrt_P: np.ndarray | None = None
    info: dict = field(default_factory=dict)


# --------------------------------------------------------------------------- point sets


@dataclass(frozen=True)
class SigmaScheme:
    """Unit point set: rows ``xi`` (N, n), mean weights ``wm`` and covariance weights ``wc``."""

    name: str
    xi: np.ndarray
    wm: np.ndarray
    wc: np.ndarray
    params: tuple = ()


@lru_cache(maxsize=64)
def cubature_scheme(n: int) -> SigmaScheme:
    """Third-degree spherical-radial cubature rule: ξ_j = √n e_j, ξ_{n+j} = −√n e_j, w = 1/(2n)."""
    if n < 1:
        raise FilterError(f"state dimension must be ≥ 1, got {n}")
    e = np.sqrt(n) * np.eye(n)
    xi = np.vstack([e, -e])
    w = np.full(2 * n, 1.0 / (2 * n))
    xi.setflags(write=False)
    w.setflags(write=False)
    return SigmaScheme("ckf", xi, w, w, (n,))


@lru_cache(maxsize=64)
def unscented_scheme(n: int, alpha: float = 1.0, beta: float = 2.0, kappa: float = 0.0) -> SigmaScheme:
    """Scaled unscented transform (Julier & Uhlmann 2004, van der Merwe & Wan 2004; Sun et al. 2012 §3 step 2), 2n+1 points.

    λ = α²(n+κ) − n; points 0, ±√(n+λ) e_j; W0m = λ/(n+λ), W0c = W0m + 1 − α² + β,
    Wi = 1/(2(n+λ)).  Requires n + λ > 0.
    """
    if n < 1:
        raise FilterError(f"state dimension must be ≥ 1, got {n}")
    lam = alpha * alpha * (n + kappa) - n
    if not (alpha > 0 and n + lam > 0):
        raise FilterError(f"unscented parameters give n+λ = {n + lam:.3g} ≤ 0 (alpha={alpha}, kappa={kappa})")
    c = np.sqrt(n + lam)
    e = c * np.eye(n)
    xi = np.vstack([np.zeros((1, n)), e, -e])
    wm = np.full(2 * n + 1, 0.5 / (n + lam))
    wc = wm.copy()
    wm[0] = lam / (n + lam)
    wc[0] = wm[0] + 1.0 - alpha * alpha + beta
    for a in (xi, wm, wc):
        a.setflags(write=False)
    return SigmaScheme("ukf", xi, wm, wc, (n, alpha, beta, kappa))


def _points(x: np.ndarray, L: np.ndarray, scheme: SigmaScheme) -> np.ndarray:
    return x[None, :] + scheme.xi @ L.T


def _apply(fun: Callable, X: np.ndarray, vectorized: bool, name: str, out_dim: int | None = None) -> np.ndarray:
    if vectorized:
        Y = np.asarray(fun(X), dtype=float)
    else:
        Y = np.array([np.asarray(fun(X[j]), dtype=float).reshape(-1) for j in range(X.shape[0])])
    if Y.ndim != 2 or Y.shape[0] != X.shape[0] or (out_dim is not None and Y.shape[1] != out_dim):
        raise FilterError(f"{name}: returned shape {Y.shape}, expected ({X.shape[0]}, {out_dim or 'm'})")
    if not np.all(np.isfinite(Y)):
        raise DivergenceError(f"{name}: returned non-finite values at the sigma points")
    return Y


def _stats(X: np.ndarray, scheme: SigmaScheme):
    mean = scheme.wm @ X
    D = X - mean
    return mean, D


# note: numpy's LAPACK solve is used rather than scipy.linalg.solve_triangular, which was measured
# ~100x slower for these small matrices on this machine (per-call overhead).


def _nis(r: np.ndarray, S: np.ndarray) -> float:
    """rᵀ S⁻¹ r (S checked PD by Cholesky)."""
    Ls = cholesky_lower(S, "innovation covariance S")
    y = np.linalg.solve(Ls, r)
    return float(y @ y)


def _gain(P_xz: np.ndarray, S: np.ndarray) -> np.ndarray:
    """K = P_xz S⁻¹ (eq. 15); S is checked PD by Cholesky first."""
    cholesky_lower(S, "innovation covariance S")
    return np.linalg.solve(S, P_xz.T).T


# --------------------------------------------------------------------------- linear KF


def kf_predict(x, P, F, Q, u=None, B=None):
    """Linear time update: x⁻ = F x (+ B u), P⁻ = F P Fᵀ + Q."""
    x = as_vector("x", x)
    n = x.shape[0]
    P = check_covariance("P", P, n)
    F = as_matrix("F", F, (n, n))
    Q = as_matrix("Q", Q, (n, n))
    xp = F @ x
    if u is not None:
        u = as_vector("u", u)
        B = as_matrix("B", B if B is not None else np.eye(n, u.shape[0]), (n, u.shape[0]))
        xp = xp + B @ u
    Pp = symmetrize(F @ P @ F.T + Q)
    check_state(xp, Pp, "kf_predict")
    return xp, Pp


def _joseph(x, P, z, zhat, H, R):
    n = x.shape[0]
    r = z - zhat
    PHt = P @ H.T
    S = symmetrize(H @ PHt + R)
    K = _gain(PHt, S)
    IKH = np.eye(n) - K @ H
    Pn = symmetrize(IKH @ P @ IKH.T + K @ R @ K.T)
    xn = x + K @ r
    check_state(xn, Pn, "update")
    return UpdateResult(xn, Pn, r, S, K, _nis(r, S), zhat, PHt)


def kf_update(x, P, z, H, R):
    """Linear measurement update with the Joseph-form covariance (Cai et al. 2020 eqs. 2–5)."""
    x, P, z, H, R = check_linear_update(x, P, z, H, R)
    return _joseph(x, P, z, H @ x, H, R)


# --------------------------------------------------------------------------- EKF


def ekf_predict(x, P, f, F, Q):
    """EKF time update: x⁻ = f(x), P⁻ = F P Fᵀ + Q with F the Jacobian (matrix or callable F(x))."""
    x = as_vector("x", x)
    n = x.shape[0]
    P = check_covariance("P", P, n)
    Fm = as_matrix("F", F(x) if callable(F) else F, (n, n))
    Q = as_matrix("Q", Q, (n, n))
    xp = np.asarray(f(x), dtype=float).reshape(-1)
    if xp.shape != (n,):
        raise FilterError(f"f: returned shape {xp.shape}, expected ({n},)")
    Pp = symmetrize(Fm @ P @ Fm.T + Q)
    check_state(xp, Pp, "ekf_predict")
    return xp, Pp


def ekf_update(x, P, z, h, H, R):
    """EKF measurement update (Joseph form); H is the Jacobian of h (matrix or callable H(x))."""
    x = as_vector("x", x)
    n = x.shape[0]
    P = check_covariance("P", P, n)
    z = as_vector("z", z)
    m = z.shape[0]
    Hm = as_matrix("H", H(x) if callable(H) else H, (m, n))
    R = check_covariance("R", R, m)
    zhat = np.asarray(h(x), dtype=float).reshape(-1)
    if zhat.shape != (m,):
        raise FilterError(f"h: returned shape {zhat.shape}, expected ({m},)")
    return _joseph(x, P, z, zhat, Hm, R)


# --------------------------------------------------------------------------- sigma-point filters


def sigma_predict(x, P, f, Q, scheme: SigmaScheme, vectorized: bool = False, return_noiseless: bool = False):
    """Sigma-point time update with additive process noise (CKF eqs. 4–8 / UKF).

    Returns (x⁻, P⁻) or, with ``return_noiseless``, (x⁻, P⁻, P′) where P′ = P⁻ − Q is the propagated
    covariance without process noise (Sun et al. 2012 eq. 12, A = P′).
    """
    x = as_vector("x", x)
    n = x.shape[0]
    P = check_covariance("P", P, n)
    Q = as_matrix("Q", Q, (n, n))
    if scheme.xi.shape[1] != n:
        raise FilterError(f"sigma scheme is for dimension {scheme.xi.shape[1]}, state has {n}")
    L = cholesky_lower(P, "P")  # eq. 4
    X = _points(x, L, scheme)  # eq. 5
    Xs = _apply(f, X, vectorized, "f", n)  # eq. 6
    xp, D = _stats(Xs, scheme)  # eq. 7
    Pnl = symmetrize((D.T * scheme.wc) @ D)
    Pp = symmetrize(Pnl + Q)  # eq. 8
    check_state(xp, Pp, "sigma_predict")
    if return_noiseless:
        return xp, Pp, Pnl
    return xp, Pp


def sigma_measure(x, P, h, scheme: SigmaScheme, scale: float = 1.0, vectorized: bool = False, m: int | None = None):
    """Predicted measurement statistics from points **redrawn** from (x, scale·P) (eqs. 9–14).

    ``scale`` = 1/ϑ implements the RACKF point redraw x + sqrt(1/ϑ)·S ξ_j (Zhao et al. 2014 eq. 40).
    Returns (ẑ, P_zz without R, P_xz).
    """
    L = cholesky_lower(P, "P")  # eq. 9
    if scale != 1.0:
        L = np.sqrt(scale) * L
    X = _points(x, L, scheme)  # eq. 10 / 40
    Z = _apply(h, X, vectorized, "h", m)  # eq. 11
    zhat, DZ = _stats(Z, scheme)  # eq. 12
    DX = X - x[None, :]
    Pzz = symmetrize((DZ.T * scheme.wc) @ DZ)  # eq. 13 (without R)
    Pxz = (DX.T * scheme.wc) @ DZ  # eq. 14
    return zhat, Pzz, Pxz


def gain_update(x, P, z, zhat, Pzz, Pxz, R) -> UpdateResult:
    """Eqs. 15–17: W = P_xz S⁻¹, x = x⁻ + W r, P = P⁻ − W S Wᵀ, with S = P_zz + R."""
    S = symmetrize(Pzz + R)
    r = z - zhat
    K = _gain(Pxz, S)  # eq. 15
    xn = x + K @ r  # eq. 16
    Pn = symmetrize(P - K @ S @ K.T)  # eq. 17
    # guard: posterior must stay PD; repair round-off, reject genuine loss of definiteness
    try:
        cholesky_lower(Pn, "posterior P")
    except FilterError as exc:
        raise DivergenceError(f"measurement update lost positive definiteness: {exc}") from None
    check_state(xn, Pn, "update")
    return UpdateResult(xn, Pn, r, S, K, _nis(r, S), zhat, Pxz)


def sigma_update(x, P, z, h, R, scheme: SigmaScheme, vectorized: bool = False) -> UpdateResult:
    """Sigma-point measurement update with additive noise (eqs. 9–17), points redrawn from P."""
    x = as_vector("x", x)
    n = x.shape[0]
    P = check_covariance("P", P, n)
    z = as_vector("z", z)
    m = z.shape[0]
    R = check_covariance("R", R, m)
    if scheme.xi.shape[1] != n:
        raise FilterError(f"sigma scheme is for dimension {scheme.xi.shape[1]}, state has {n}")
    zhat, Pzz, Pxz = sigma_measure(x, P, h, scheme, 1.0, vectorized, m)
    return gain_update(x, P, z, zhat, Pzz, Pxz, R)


def ukf_predict(x, P, f, Q, alpha=1.0, beta=2.0, kappa=0.0, vectorized=False, return_noiseless=False):
    """UKF time update with scaled sigma points (α, β, κ)."""
    n = np.asarray(x).reshape(-1).shape[0]
    return sigma_predict(x, P, f, Q, unscented_scheme(n, alpha, beta, kappa), vectorized, return_noiseless)


def ukf_update(x, P, z, h, R, alpha=1.0, beta=2.0, kappa=0.0, vectorized=False) -> UpdateResult:
    """UKF measurement update (points redrawn from the predicted covariance)."""
    n = np.asarray(x).reshape(-1).shape[0]
    return sigma_update(x, P, z, h, R, unscented_scheme(n, alpha, beta, kappa), vectorized)


def ckf_predict(x, P, f, Q, vectorized=False, return_noiseless=False):
    """CKF time update (Zhao et al. 2014, eqs. 4–8)."""
    n = np.asarray(x).reshape(-1).shape[0]
    return sigma_predict(x, P, f, Q, cubature_scheme(n), vectorized, return_noiseless)


def ckf_update(x, P, z, h, R, vectorized=False) -> UpdateResult:
    """CKF measurement update (Zhao et al. 2014 eqs. 9–17), cubature points redrawn from P⁻."""
    n = np.asarray(x).reshape(-1).shape[0]
    return sigma_update(x, P, z, h, R, cubature_scheme(n), vectorized)


# --------------------------------------------------------------------------- augmented UKF


def aukf_predict(x, P, f, Q, alpha=1.0, beta=2.0, kappa=0.0, return_noiseless=False):
    """Augmented-UKF time update for non-additive process noise ``x⁺ = f(x, w)``, w ~ N(0, Q).

    Augmented state [x; w] with P^a = diag(P, Q), L = n + q, 2L+1 points (Sun et al. 2012 §3 steps 1–3).
    With ``return_noiseless`` also returns P′: the n-dimensional unscented propagation of P through
    f(·, 0) (process noise not applied; Sun et al. 2012 eq. 12, used by the fading matrix).
    """
    x = as_vector("x", x)
    n = x.shape[0]
    P = check_covariance("P", P, n)
    Q = check_covariance("Q", Q, None)
    q = Q.shape[0]
    Lx = cholesky_lower(P, "P")
    Lw = cholesky_lower(Q, "Q")
    La = np.zeros((n + q, n + q))
    La[:n, :n] = Lx
    La[n:, n:] = Lw
    sch = unscented_scheme(n + q, alpha, beta, kappa)
    Xa = _points(np.concatenate([x, np.zeros(q)]), La, sch)
    Xs = _apply(lambda xa: f(xa[:n], xa[n:]), Xa, False, "f", n)
    xp, D = _stats(Xs, sch)
    Pp = symmetrize((D.T * sch.wc) @ D)
    check_state(xp, Pp, "aukf_predict")
    try:
        cholesky_lower(Pp, "AUKF predicted P")
    except FilterError as exc:
        raise DivergenceError(str(exc)) from None
    if not return_noiseless:
        return xp, Pp
    sch0 = unscented_scheme(n, alpha, beta, kappa)
    X0 = _points(x, Lx, sch0)
    zero = np.zeros(q)
    Xs0 = _apply(lambda xx: f(xx, zero), X0, False, "f", n)
    _, D0 = _stats(Xs0, sch0)
    Pnl = symmetrize((D0.T * sch0.wc) @ D0)
    return xp, Pp, Pnl


def aukf_measure(x, P, h, R, alpha=1.0, beta=2.0, kappa=0.0, m=None):
    """Measurement statistics for non-additive noise ``z = h(x, v)``, v ~ N(0, R).

    Points redrawn from diag(P, R) (L' = n + m, Sun et al. 2012 step 5). Returns (ẑ, P_zz incl. noise, P_xz).
    """
    n = x.shape[0]
    mm = R.shape[0]
    La = np.zeros((n + mm, n + mm))
    La[:n, :n] = cholesky_lower(P, "P")
    La[n:, n:] = cholesky_lower(R, "R")
    sch = unscented_scheme(n + mm, alpha, beta, kappa)
    Xa = _points(np.concatenate([x, np.zeros(mm)]), La, sch)
    Z = _apply(lambda xa: h(xa[:n], xa[n:]), Xa, False, "h", m)
    zhat, DZ = _stats(Z, sch)
    DX = Xa[:, :n] - x[None, :]
    Pzz = symmetrize((DZ.T * sch.wc) @ DZ)
    Pxz = (DX.T * sch.wc) @ DZ
    return zhat, Pzz, Pxz


def aukf_update(x, P, z, h, R, alpha=1.0, beta=2.0, kappa=0.0) -> UpdateResult:
    """Augmented-UKF measurement update for ``z = h(x, v)`` (Sun et al. 2012 §3 steps 5–8)."""
    x = as_vector("x", x)
    n = x.shape[0]
    P = check_covariance("P", P, n)
    z = as_vector("z", z)
    m = z.shape[0]
    R = check_covariance("R", R, None)
    zhat, Pzz, Pxz = aukf_measure(x, P, h, R, alpha, beta, kappa, m)
    return gain_update(x, P, z, zhat, Pzz, Pxz, np.zeros((m, m)))


# --------------------------------------------------------------------------- square-root CKF


def tria(A: np.ndarray) -> np.ndarray:
    """Lower-triangular S with S Sᵀ = A Aᵀ (QR of Aᵀ), positive diagonal."""
    Rq = np.linalg.qr(A.T, mode="r")
    S = Rq.T
    sgn = np.sign(np.diag(S))
    sgn[sgn == 0] = 1.0
    return S * sgn[None, :]


def _check_sqrt(name, S, n):
    S = as_matrix(name, S, (n, n))
    if not np.allclose(S, np.tril(S)):
        raise FilterError(f"{name}: expected a lower-triangular square-root factor")
    d = np.abs(np.diag(S))
    if np.any(d <= 1e-300 * max(1.0, d.max())):
        raise FilterError(f"{name}: singular square-root factor (zero on the diagonal)")
    return S


def srckf_predict(x, S, f, SQ, vectorized=False):
    """Square-root CKF time update (Arasaratnam & Haykin 2009): returns (x⁻, S⁻), P⁻ = S⁻S⁻ᵀ.

    S and SQ are lower-triangular square roots of P and Q.  S⁻ = tria([X*_c, SQ]) with the centred,
    weighted propagated points X*_c = (X* − x⁻)/√(2n).
    """
    x = as_vector("x", x)
    n = x.shape[0]
    S = _check_sqrt("S", S, n)
    SQ = as_matrix("SQ", SQ, (n, n))
    sch = cubature_scheme(n)
    X = _points(x, S, sch)
    Xs = _apply(f, X, vectorized, "f", n)
    xp = sch.wm @ Xs
    Xc = (Xs - xp).T / np.sqrt(2 * n)
    Sp = tria(np.hstack([Xc, SQ]))
    check_state(xp, Sp, "srckf_predict")
    return xp, Sp


def srckf_update(x, S, z, h, SR, vectorized=False) -> UpdateResult:
    """Square-root CKF measurement update; points redrawn from S⁻.  Result carries ``sqrt_P``."""
    x = as_vector("x", x)
    n = x.shape[0]
    S = _check_sqrt("S", S, n)
    z = as_vector("z", z)
    m = z.shape[0]
    SR = as_matrix("SR", SR, (m, m))
    sch = cubature_scheme(n)
    X = _points(x, S, sch)
    Z = _apply(h, X, vectorized, "h", m)
    zhat = sch.wm @ Z
    w = 1.0 / np.sqrt(2 * n)
    Zc = (Z - zhat).T * w
    Xc = (X - x).T * w
    Szz = tria(np.hstack([Zc, SR]))
    Pxz = Xc @ Zc.T
    K = np.linalg.solve(Szz.T, np.linalg.solve(Szz, Pxz.T)).T
    r = z - zhat
    xn = x + K @ r
    Sn = tria(np.hstack([Xc - K @ Zc, K @ SR]))
    Pn = Sn @ Sn.T
    check_state(xn, Pn, "srckf_update")
    y = np.linalg.solve(Szz, r)
    return UpdateResult(xn, Pn, r, Szz @ Szz.T, K, float(y @ y), zhat, Pxz, sqrt_P=Sn)


# --------------------------------------------------------------------------- stateful wrapper


class Filter:
    """Stateful wrapper with divergence flagging around the pure predict/update functions.

    ``Filter(kind, x0, P0, monitor=None, **params)`` with kind in {"kf", "ekf", "ukf", "ckf", "srckf"}
    (``params`` are passed on, e.g. alpha/beta/kappa for the UKF).  ``predict(f_or_F, Q)`` and
    ``update(z, h_or_H, R[, H_jac])``; on a non-finite result or a tripped :class:`DivergenceMonitor`
    the filter keeps its last finite state, sets ``diverged = True`` and (with
    ``raise_on_divergence``) raises DivergenceError.  It never returns NaNs.
    """

    KINDS = ("kf", "ekf", "ukf", "ckf", "srckf")

    def __init__(self, kind: str, x0, P0, monitor: DivergenceMonitor | None = None,
                 raise_on_divergence: bool = False, **params):
        if kind not in self.KINDS:
            raise FilterError(f"kind: expected one of {self.KINDS}, got {kind!r}")
        self.kind = kind
        self.x = as_vector("x0", x0)
        self.P = check_covariance("P0", P0, self.x.shape[0])
        self.params = params
        self.monitor = monitor if monitor is not None else DivergenceMonitor()
        self.raise_on_divergence = raise_on_divergence
        self.diverged = False
        self.last: UpdateResult | None = None
        self.S = cholesky_lower(self.P, "P0") if kind == "srckf" else None  # square root (SRCKF)

    def _fail(self, exc: Exception):
        self.diverged = True
        if self.raise_on_divergence:
            raise DivergenceError(str(exc)) from exc

    def predict(self, f, Q, F=None):
        if self.diverged:
            return self.x, self.P
        try:
            if self.kind == "kf":
                x, P = kf_predict(self.x, self.P, f, Q)
            elif self.kind == "ekf":
                x, P = ekf_predict(self.x, self.P, f, F, Q)
            elif self.kind == "ukf":
                x, P = ukf_predict(self.x, self.P, f, Q, **self.params)
            elif self.kind == "ckf":
                x, P = ckf_predict(self.x, self.P, f, Q)
            else:
                x, S = srckf_predict(self.x, self.S, f, cholesky_lower(as_matrix("Q", Q, self.P.shape), "Q"))
                P = S @ S.T
                self.S = S
        except DivergenceError as exc:
            self._fail(exc)
            return self.x, self.P
        self.x, self.P = x, P
        return x, P

    def update(self, z, h, R, H=None) -> UpdateResult | None:
        if self.diverged:
            return None
        try:
            if self.kind == "kf":
                res = kf_update(self.x, self.P, z, h, R)
            elif self.kind == "ekf":
                res = ekf_update(self.x, self.P, z, h, H, R)
            elif self.kind == "ukf":
                res = ukf_update(self.x, self.P, z, h, R, **self.params)
            elif self.kind == "ckf":
                res = ckf_update(self.x, self.P, z, h, R)
            else:
                res = srckf_update(self.x, self.S, z, h, cholesky_lower(check_covariance("R", R), "R"))
            self.monitor.update(res.nis, res.innovation.shape[0])
        except DivergenceError as exc:
            self._fail(exc)
            return None
        if self.monitor.diverged:
            self._fail(DivergenceError(f"NIS beyond bound for {self.monitor.count} consecutive updates"))
            return None
        self.x, self.P, self.last = res.x, res.P, res
        if self.kind == "srckf":
            self.S = res.sqrt_P
        return res
