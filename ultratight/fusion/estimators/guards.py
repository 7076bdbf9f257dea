"""Numerical guards for the generic filters: input validation, covariance symmetry / PD repair,
divergence monitoring.

Every public filter function in :mod:`ultratight.fusion.estimators.filters`, :mod:`~ultratight.fusion.estimators.robust`
and :mod:`~ultratight.fusion.estimators.adaptive` validates its inputs here, at the boundary, so a user error
(wrong shape, NaN measurement, non-PD covariance) raises :class:`~ultratight.errors.FilterError`
with a message naming the argument and what was expected, and a numerically diverging filter raises
:class:`~ultratight.errors.DivergenceError` (or sets a flag) instead of emitting NaNs.

Conventions
-----------
* ``symmetrize(P)`` returns ``(P + Pᵀ)/2``.
* ``cholesky_lower(P)`` factors ``P = L Lᵀ``; when plain Cholesky fails on a matrix that is PSD up
  to round-off it retries with a relative diagonal jitter (1e-12 … 1e-6 of the mean diagonal);
  if that also fails the matrix is not repairable and ``FilterError`` is raised.
* ``nearest_pd(P, floor)`` clips eigenvalues from below (used for *estimated* noise covariances
  Q̂ and R̂ of the adaptive filters, which can legitimately come out indefinite).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.linalg.lapack import dpotrf as _potrf     # LAPACK Cholesky: the PD test of check_covariance

from ultratight.chi2 import chdtri
from ultratight.errors import DivergenceError, FilterError

__all__ = [
    "symmetrize",
    "as_vector",
    "as_matrix",
    "check_covariance",
    "cholesky_lower",
    "nearest_pd",
    "check_state",
    "DivergenceMonitor",
]

#: relative jitters tried (times the mean diagonal) when Cholesky of a PSD matrix fails
_JITTERS = (0.0, 1e-12, 1e-10, 1e-8, 1e-6)
#: relative asymmetry tolerated on input covariances (beyond round-off it is a user error)
_SYM_RTOL = 1e-6


def symmetrize(P: np.ndarray) -> np.ndarray:
    """Return the symmetric part ``(P + Pᵀ)/2``."""
    return 0.5 * (P + P.T)


def as_vector(name: str, v, n: int | None = None) -> np.ndarray:
    """Validate a finite 1-D float vector (optionally of length ``n``); scalars become length 1."""
    a = np.asarray(v, dtype=float)
    if a.ndim == 0:
        a = a.reshape(1)
    if a.ndim != 1:
        raise FilterError(f"{name}: expected a 1-D vector, got an array of shape {a.shape}")
    if n is not None and a.shape[0] != n:
        raise FilterError(f"{name}: expected length {n}, got length {a.shape[0]}")
    if not np.all(np.isfinite(a)):
        bad = np.flatnonzero(~np.isfinite(a))
        raise FilterError(f"{name}: non-finite value(s) at index {bad.tolist()} (NaN/inf not allowed)")
    return a


def as_matrix(name: str, A, shape: tuple[int | None, int | None]) -> np.ndarray:
    """Validate a finite 2-D float matrix of the given shape (``None`` = any size)."""
    a = np.asarray(A, dtype=float)
    if a.ndim == 0 and shape == (1, 1):
        a = a.reshape(1, 1)
    if a.ndim != 2:
        raise FilterError(f"{name}: expected a 2-D matrix of shape {shape}, got shape {a.shape}")
    for k in range(2):
        if shape[k] is not None and a.shape[k] != shape[k]:
            raise FilterError(f"{name}: expected shape {shape}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise FilterError(f"{name}: contains non-finite values (NaN/inf not allowed)")
    return a


def cholesky_lower(P: np.ndarray, name: str = "covariance") -> np.ndarray:
    """Lower Cholesky factor of a symmetric PSD matrix, with a small relative jitter fallback.

    Raises FilterError when the matrix is not positive (semi-)definite beyond round-off.
    """
    P = symmetrize(P)
    n = P.shape[0]
    scale = float(np.trace(P)) / max(n, 1)
    if not np.isfinite(scale):
        raise FilterError(f"{name}: contains non-finite values")
    if scale <= 0.0:
        scale = 1.0
    eye = np.eye(n)
    for j in _JITTERS:
        try:
            return np.linalg.cholesky(P + (j * scale) * eye)
        except np.linalg.LinAlgError:
            continue
    w = np.linalg.eigvalsh(P)
    raise FilterError(
        f"{name}: not positive definite (smallest eigenvalue {w[0]:.3e}, largest {w[-1]:.3e}); "
        "expected a symmetric positive-definite covariance"
    )


def check_covariance(name: str, P, n: int | None = None) -> np.ndarray:
    """Validate an input covariance: square (n×n), finite, symmetric to 1e-6 relative, PD.

    Returns the symmetrised matrix. Raises FilterError otherwise.
    """
    a = as_matrix(name, P, (n, n))
    if a.shape[0] != a.shape[1]:
        raise FilterError(f"{name}: expected a square matrix, got shape {a.shape}")
    asym = np.max(np.abs(a - a.T)) if a.size else 0.0
    mag = max(np.max(np.abs(a)) if a.size else 0.0, 1e-300)
    if asym > _SYM_RTOL * mag:
        raise FilterError(f"{name}: not symmetric (max |P - Pᵀ| = {asym:.3e}, max |P| = {mag:.3e})")
    a = symmetrize(a)
    if a.size and _potrf(a, lower=1, clean=0)[1] != 0:
        cholesky_lower(a, name)  # the jittered retries; raises FilterError when not PD beyond round-off
    return a


def nearest_pd(P: np.ndarray, floor: float | np.ndarray) -> np.ndarray:
    """Symmetrise and clip the eigenvalues of ``P`` from below at ``floor`` (> 0).

    Used for estimated noise covariances (Q̂, R̂ of the adaptive filters), which are differences of
    sample covariances and can come out indefinite.  ``floor`` may be a scalar or a per-eigenvalue
    minimum; it must be positive.
    """
    P = symmetrize(np.asarray(P, dtype=float))
    if not np.all(np.isfinite(P)):
        raise DivergenceError("estimated covariance became non-finite")
    w, V = np.linalg.eigh(P)
    w = np.maximum(w, floor)
    return symmetrize((V * w) @ V.T)


def check_state(x: np.ndarray, P: np.ndarray, where: str) -> None:
    """Raise DivergenceError when the state or covariance became non-finite (never emit NaNs)."""
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(P))):
        raise DivergenceError(f"{where}: state or covariance became non-finite (filter diverged)")


@dataclass
class DivergenceMonitor:
    """Flags a filter whose normalised innovation squared stays beyond its chi-square bound.

    ``update(nis, dof)`` returns True once ``max_consecutive`` consecutive NIS values exceeded the
    ``1 - p_false`` quantile of χ²(dof) times ``factor`` (default: 99.9 % quantile ×10, so a
    consistent filter essentially never trips it).  ``diverged`` stays True afterwards.
    With ``raise_on_divergence`` it raises DivergenceError instead.
    """

    max_consecutive: int = 10
    p_false: float = 1e-3
    factor: float = 10.0
    raise_on_divergence: bool = False
    count: int = 0
    diverged: bool = False
    history: list = field(default_factory=list)

    def bound(self, dof: int) -> float:
        return float(self.factor * chdtri(dof, self.p_false))

    def update(self, nis: float, dof: int) -> bool:
        self.history.append(float(nis))
        if not np.isfinite(nis) or nis > self.bound(dof):
            self.count += 1
        else:
            self.count = 0
        if self.count >= self.max_consecutive or not np.isfinite(nis):
            self.diverged = True
            if self.raise_on_divergence:
                raise DivergenceError(
                    f"filter diverged: NIS above {self.bound(dof):.1f} (χ²({dof}) bound) for "
                    f"{self.count} consecutive updates (last NIS {nis:.3g})"
                )
        return self.diverged


def check_linear_update(x, P, z, H, R):
    """Validate the inputs of a linear measurement update; return them as checked arrays.

    ``x`` (n,), ``P`` (n, n) PD, ``z`` (m,), ``H`` (m, n), ``R`` (m, m) PD; raises FilterError.
    """
    x = as_vector("x", x)
    n = x.shape[0]
    P = check_covariance("P", P, n)
    z = as_vector("z", z)
    m = z.shape[0]
    H = as_matrix("H", H, (m, n))
    R = check_covariance("R", R, m)
    return x, P, z, H, R
