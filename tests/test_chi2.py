"""The χ² and gamma quantiles of :mod:`ultratight.chi2` against scipy.special (an independent
implementation, Cephes) and closed forms."""

import math

import numpy as np
import pytest
from scipy import special

from ultratight import chi2

SHAPES = (0.01, 0.05, 0.5, 1.0, 1.5, 2.0, 3.7, 5.0, 9.99, 10.0, 20.3, 60.0, 200.0, 1000.0, 1e5)
PROBS = (1e-300, 1e-100, 1e-12, 1e-8, 1e-4, 1e-3, 0.01, 0.3, 0.5, 0.5000001, 0.9, 0.99, 0.999, 1 - 1e-9)


@pytest.mark.parametrize("a", SHAPES)
def test_inverse_matches_scipy(a):
    for p in PROBS:
        want = special.gammainccinv(a, p)
        got = chi2.gammainccinv(a, p)
        if want == 0.0:                              # below the smallest double: scipy's 0
            assert got < 1e-300
        else:
            assert got == pytest.approx(want, rel=1e-11), (a, p)
        assert chi2.gammaincc(a, got) == pytest.approx(p, rel=1e-9, abs=1e-300)


@pytest.mark.parametrize("a", SHAPES)
def test_upper_function_matches_scipy_in_both_expansions(a):
    # the exponent a ln x - x - ln Γ(a) cancels: a few 1e-15 a of relative error (module docstring)
    rel = max(1e-12, 5e-15 * a)
    for x in (1e-5, 0.1, 0.9, 1.0, 2.5, a, a + 1.0, a + 1.0001, 3 * a + 10, 10 * a + 50):
        assert chi2.gammaincc(a, x) == pytest.approx(special.gammaincc(a, x), rel=rel, abs=1e-300), (a, x)


def test_closed_forms():
    # a = 1: Q = exp(-x); chi2 with 2 dof: isf(p) = -2 ln p; with 1 dof: (Φ^-1(1 - p/2))^2
    for p in (1e-9, 1e-3, 0.05, 0.5, 0.95):
        assert chi2.gammainccinv(1.0, p) == pytest.approx(-math.log(p), rel=1e-13)
        assert chi2.chdtri(2, p) == pytest.approx(-2.0 * math.log(p), rel=1e-13)
    assert chi2.chdtri(1, 0.05) == pytest.approx(1.959963984540054 ** 2, rel=1e-13)
    # a = 2: Q = exp(-x) (1 + x)
    x = chi2.gammainccinv(2.0, 1e-6)
    assert math.exp(-x) * (1.0 + x) == pytest.approx(1e-6, rel=1e-12)


def test_arrays_and_the_domain():
    k = np.array([[1, 2, 3], [12, 120, 17]])
    np.testing.assert_allclose(chi2.chdtri(k, 1e-3), special.chdtri(k, 1e-3), rtol=1e-12)
    assert chi2.chdtri(k, 1e-3).shape == (2, 3)
    assert isinstance(chi2.chdtri(3, 0.5), float)
    np.testing.assert_allclose(chi2.gammainccinv(np.array([2.0, 4.0]), np.array([0.1, 0.2])),
                               special.gammainccinv([2.0, 4.0], [0.1, 0.2]), rtol=1e-12)
    assert chi2.gammainccinv(2.0, 0.0) == math.inf
    assert chi2.gammainccinv(2.0, 1.0) == 0.0
    assert chi2.gammaincc(2.0, math.inf) == 0.0
    for a, p in ((-1.0, 0.5), (0.0, 0.5), (2.0, 1.5), (2.0, -0.1), (math.nan, 0.5), (2.0, math.nan)):
        assert math.isnan(chi2.gammainccinv(a, p))
    assert math.isnan(chi2.gammaincc(2.0, -1.0))
