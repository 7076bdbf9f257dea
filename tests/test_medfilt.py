"""The running median of the CW excision against scipy.ndimage.median_filter (wrap mode)."""

import numpy as np
import pytest
from scipy.ndimage import median_filter

from ultratight.receiver.dsp.medfilt import running_median_wrap


@pytest.mark.parametrize("n, win", [(40000, 1001), (2600, 65), (100, 9), (5, 9), (7, 7), (1000, 999), (1, 1), (3, 1),
                                    (10, 3)])
def test_equals_scipy_with_ties_and_windows_longer_than_the_sequence(n, win):
    rng = np.random.default_rng(n + win)
    v = rng.exponential(size=n).astype(np.float32)
    v[::7] = v[n // 2]                               # repeated values
    got = running_median_wrap(v, win)
    assert got.dtype == np.float32
    np.testing.assert_array_equal(got, median_filter(v, size=win, mode="wrap"))


def test_float64_and_a_direct_median():
    v = np.random.default_rng(5).standard_normal(50)
    got = running_median_wrap(v, 11)
    direct = [np.median(np.take(v, range(i - 5, i + 6), mode="wrap")) for i in range(50)]
    np.testing.assert_array_equal(got, direct)


@pytest.mark.parametrize("win", [0, 2, -3])
def test_even_or_empty_window_is_refused(win):
    with pytest.raises(ValueError, match="odd"):
        running_median_wrap(np.ones(5), win)
