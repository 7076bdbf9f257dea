"""χ² and gamma tail quantiles: the regularised incomplete gamma functions and their inverses.

The receiver's detection thresholds (acquisition's CFAR, RAIM, the filters' χ² gates and
consistency tests) need ``chi2.isf(p, k)``.  scipy has it (``scipy.special.chdtri``,
``gammainccinv``), but importing ``scipy.special`` loads scipy's array-API layer and parses its
docstrings: 0.1–0.2 s on every command that gates a measurement, more than the thresholds of a
whole run cost.  These compiled versions give the same values (tests/test_chi2.py compares them
with scipy's over a grid of shapes and probabilities) from the textbook expansions:

* lower function P(a, x) = γ(a, x)/Γ(a) by its power series (Abramowitz & Stegun 6.5.29),
  ``x^a e^-x / Γ(a+1) · Σ x^n / ((a+1)…(a+n))``, used for x < a + 1;
* upper function Q(a, x) = 1 − P = Γ(a, x)/Γ(a) by Legendre's continued fraction (A&S 6.5.31),
  evaluated with the modified Lentz method, for x ≥ a + 1 (each is computed directly where it is
  small, so a tail probability keeps its relative accuracy);
* the inverses by Newton's method on the logarithm of the smaller tail, kept inside a bracket by
  bisection.

The exponent ``a ln x − x − ln Γ(a)`` of both expansions cancels for large shapes: relative accuracy
a few 1e-15 · a (1e-12 up to the few hundred degrees of freedom the receiver's tests use).

``chdtri(k, p)`` is the χ² inverse survival function with k degrees of freedom (x with
P(χ²_k > x) = p): 2 · ``gammainccinv(k/2, p)``.  Scalars or arrays; NaN outside the domain
(a ≤ 0, p outside [0, 1]), as scipy.
"""

import math

import numba
import numpy as np

_EPS = 1e-15
_TINY = 1e-300
_MAX_TERMS = 10_000


@numba.njit(cache=True)
def _log_p_series(a, x):
    """ln P(a, x) by the power series (x > 0)."""
    term = 1.0
    s = 1.0
    n = 1
    while n < _MAX_TERMS:
        term *= x / (a + n)
        s += term
        if term < s * _EPS:
            break
        n += 1
    return a * math.log(x) - x - math.lgamma(a + 1.0) + math.log(s)


@numba.njit(cache=True)
def _log_q_fraction(a, x):
    """ln Q(a, x) by Legendre's continued fraction (modified Lentz; x > 0)."""
    b = x + 1.0 - a
    f = b if abs(b) > _TINY else _TINY
    c = f
    d = 0.0
    n = 1
    while n < _MAX_TERMS:
        an = -n * (n - a)
        b += 2.0
        d = b + an * d
        d = d if abs(d) > _TINY else _TINY
        c = b + an / c
        c = c if abs(c) > _TINY else _TINY
        d = 1.0 / d
        delta = c * d
        f *= delta
        if abs(delta - 1.0) < _EPS:
            break
        n += 1
    return a * math.log(x) - x - math.lgamma(a) - math.log(f)


@numba.njit(cache=True)
def _log_tails(a, x):
    """(ln P(a, x), ln Q(a, x)), each from the expansion where it is accurate."""
    if x <= 0.0:
        return -math.inf, 0.0
    if x < a + 1.0:
        lp = _log_p_series(a, x)
        return lp, math.log1p(-math.exp(lp)) if lp < 0.0 else -math.inf
    lq = _log_q_fraction(a, x)
    return math.log1p(-math.exp(lq)) if lq < 0.0 else -math.inf, lq


@numba.njit(cache=True)
def _gammaincc(a, x):
    if not (a > 0.0) or not (x >= 0.0):
        return math.nan
    if math.isinf(x):
        return 0.0
    return math.exp(_log_tails(a, x)[1])


@numba.njit(cache=True)
def _wilson_hilferty_log(a, p):
    """ln of the Wilson-Hilferty approximation of x with Q(a, x) = p (the normal quantile by
    Abramowitz & Stegun 26.2.23); ln max(2a, 1) where the approximation is not positive."""
    t = math.sqrt(-2.0 * math.log(min(p, 1.0 - p)))
    z = t - (2.515517 + t * (0.802853 + t * 0.010328)) / (1.0 + t * (1.432788 + t * (0.189269 + t * 0.001308)))
    if p > 0.5:
        z = -z
    c = 1.0 / (9.0 * a)
    w = 1.0 - c + z * math.sqrt(c)
    return math.log(a * w * w * w) if w > 0.0 else math.log(max(2.0 * a, 1.0))


@numba.njit(cache=True)
def _gammainccinv(a, p):
    """x with Q(a, x) = p: safeguarded Newton in u = ln x on ln Q (p ≤ 1/2) or ln P (p > 1/2)."""
    if not (a > 0.0) or not (0.0 <= p <= 1.0):
        return math.nan
    if p == 0.0:
        return math.inf
    if p == 1.0:
        return 0.0
    upper = p <= 0.5
    target = math.log(p) if upper else math.log1p(-p)
    # g(u) = ln Q(a, e^u) - ln p, or ln(1 - p) - ln P(a, e^u): decreasing in u; start at the
    # Wilson-Hilferty approximation and bracket the root in [lo, hi] around it
    u0 = u = _wilson_hilferty_log(a, p)
    lo, hi = -math.inf, math.inf
    step = 0.1
    while lo == -math.inf or hi == math.inf:
        lp, lq = _log_tails(a, math.exp(u))
        if ((lq - target) if upper else (target - lp)) > 0.0:
            lo = u
            if hi == math.inf:
                u += step
        else:
            hi = u
            if lo == -math.inf:
                u -= step
        step *= 2.0
    u = u0
    for _ in range(200):
        x = math.exp(u)
        lp, lq = _log_tails(a, x)
        g = (lq - target) if upper else (target - lp)
        if g == 0.0:
            return x
        if g > 0.0:
            lo = u
        else:
            hi = u
        # dg/du = x dg/dx = -x pdf(x) / Q (or / P)
        log_slope = a * u - x - math.lgamma(a) - (lq if upper else lp)
        u_new = u + g * math.exp(-log_slope)
        if not (lo < u_new < hi):
            u_new = 0.5 * (lo + hi)
        if abs(u_new - u) <= 4.0 * _EPS or hi - lo <= 4.0 * _EPS:
            return math.exp(u_new)
        u = u_new
    return math.exp(u)


@numba.njit(cache=True)
def gamma_map(fn_id, a, b):
    """Q(a, x) (``fn_id`` 0) or its inverse in x (1) element by element over two flat arrays."""
    out = np.empty(a.size)
    for i in range(a.size):
        out[i] = _gammaincc(a[i], b[i]) if fn_id == 0 else _gammainccinv(a[i], b[i])
    return out


def _apply(fn_id, a, b):
    a_arr, b_arr = np.broadcast_arrays(np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64))
    out = gamma_map(fn_id, np.ascontiguousarray(a_arr).ravel(), np.ascontiguousarray(b_arr).ravel())
    return float(out[0]) if a_arr.ndim == 0 else out.reshape(a_arr.shape)


def gammaincc(a, x):
    """Q(a, x) = Γ(a, x) / Γ(a), the regularised upper incomplete gamma function."""
    return _apply(0, a, x)


def gammainccinv(a, p):
    """x with Q(a, x) = p (the inverse of :func:`gammaincc` in x)."""
    return _apply(1, a, p)


def chdtri(k, p):
    """The χ² inverse survival function: x with P(χ²_k > x) = p (k degrees of freedom)."""
    return 2.0 * gammainccinv(np.asarray(k, dtype=np.float64) * 0.5, p)


__all__ = ["chdtri", "gammaincc", "gammainccinv"]
