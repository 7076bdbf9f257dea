"""Rate converters: CIC interpolator against its closed form, delays and time tags."""

import numpy as np
import pytest

from ultratight.errors import ConfigError, FilterError
from ultratight.fusion.coupling.rateconv import (AveragingDecimator, CicInterpolator, average_decimate,
                                         cic_droop_db, cic_image_rejection_db, cic_impulse_response,
                                         cic_response, decimation_factor)


def _stream_impulse(R, N, M, n_in):
    c = CicInterpolator(R, N, M, f_lo_hz=100.0)
    out = [c.push(m * 0.01, np.array(1.0 if m == 0 else 0.0))[1] for m in range(n_in)]
    return np.concatenate(out)


@pytest.mark.parametrize("R,N,M", [(10, 3, 1), (10, 2, 2), (5, 4, 1), (8, 1, 1)])
def test_cic_response_matches_closed_form(R, N, M):
    h = _stream_impulse(R, N, M, N * M + 4)
    L = N * (R * M - 1) + 1
    assert np.all(h[L:] == 0.0)
    # independent FIR: N-fold convolution of boxcars, gain R/(RM)^N
    box = np.ones(R * M)
    ref = np.ones(1)
    for _ in range(N):
        ref = np.convolve(ref, box)
    np.testing.assert_allclose(h[:L], ref * R / (R * M) ** N, atol=1e-12)
    f_hi = R * 100.0
    H = np.fft.rfft(h, 8192)
    f = np.fft.rfftfreq(8192, 1.0 / f_hi)
    closed = np.abs(np.sin(np.pi * R * M * f / f_hi) / (R * M * np.sin(np.pi * f / f_hi) + (f == 0))) ** N
    closed[0] = 1.0
    assert np.max(np.abs(np.abs(H) / np.abs(H[0]) - closed)) < 1e-6
    assert np.max(np.abs(cic_response(f, R, N, M, f_hi) - closed)) < 1e-9
    # linear phase with delay D: H(f) exp(+j 2 pi f D / f_hi) is real
    D = N * (R * M - 1) / 2.0
    rot = H * np.exp(2j * np.pi * f * D / f_hi)
    assert np.max(np.abs(rot.imag)) < 1e-9 * np.max(np.abs(H))


def test_cic_dc_gain_droop_and_images():
    assert cic_impulse_response(10, 3).sum() == pytest.approx(10.0)   # R: zero-stuffed DC -> 1
    d = cic_droop_db(np.array([10.0, 20.0]), 10, 3, 1, 1000.0)
    assert d[0] == pytest.approx(20 * 3 * np.log10(np.sin(np.pi * 0.1) / (10 * np.sin(np.pi * 0.01))), rel=1e-12)
    assert -0.5 < d[0] < -0.4 and -1.8 < d[1] < -1.6
    assert cic_image_rejection_db(10.0, 10, 3, 1, 100.0) > 55.0


@pytest.mark.parametrize("R,N,M", [(10, 3, 1), (10, 2, 1), (4, 3, 2)])
def test_cic_passes_constant_and_ramp_with_delay(R, N, M):
    c = CicInterpolator(R, N, M, f_lo_hz=100.0, shape=(2,))
    tt, yy = [], []
    for m in range(40):
        tm = 2.0 + m * 0.01
        t, y = c.push(tm, np.array([4.0, -1.0 + 7.0 * tm]))
        tt.append(t)
        yy.append(y)
    tt = np.concatenate(tt)
    yy = np.concatenate(yy)
    assert c.delay_s == pytest.approx(N * (R * M - 1) / 2.0 / (R * 100.0))
    settled = np.arange(tt.size) >= N * (R * M - 1)
    np.testing.assert_allclose(yy[settled, 0], 4.0, atol=1e-12)
    # the ramp read at the returned tags (which include the group delay)
    np.testing.assert_allclose(yy[settled, 1], -1.0 + 7.0 * tt[settled], atol=1e-10)
    np.testing.assert_allclose(np.diff(tt), 1.0 / (R * 100.0), rtol=1e-9)


def test_cic_prime_removes_transient():
    c = CicInterpolator(10, 3, 1, f_lo_hz=100.0)
    c.prime(3.5)
    _, y = c.push(0.0, np.array(3.5))
    np.testing.assert_allclose(y, 3.5, atol=1e-12)


def test_averaging_decimator_constant_ramp_and_tag():
    R = 20
    t = 1.0 + np.arange(200) * 1e-3
    x = np.stack([np.full_like(t, 2.0), 3.0 - 5.0 * t], axis=1)
    dec = AveragingDecimator(R, shape=(2,))
    outs = [dec.push(tk, xk) for tk, xk in zip(t, x)]
    got = [o for o in outs if o is not None]
    assert len(got) == 10
    for k, (tc, m) in enumerate(got):
        assert tc == pytest.approx(t[k * R] + (R - 1) / 2 * 1e-3, abs=1e-12)
        np.testing.assert_allclose(m, [2.0, 3.0 - 5.0 * tc], atol=1e-12)
    y, tt = average_decimate(x, R, t)
    np.testing.assert_allclose(y[:, 1], 3.0 - 5.0 * tt, atol=1e-12)
    assert dec.group_delay_samples == (R - 1) / 2


def test_rate_converter_bad_input():
    with pytest.raises(ConfigError):
        CicInterpolator(0)
    with pytest.raises(ConfigError):
        decimation_factor(1000.0, 300.0)
    assert decimation_factor(1000.0, 20.0) == 50
    c = CicInterpolator(10, 3, shape=(2,))
    with pytest.raises(FilterError):
        c.push(0.0, np.zeros(3))
    with pytest.raises(FilterError):
        c.push(0.0, np.array([np.nan, 0.0]))
    d = AveragingDecimator(5, shape=(2,))
    with pytest.raises(FilterError):
        d.push(0.0, np.array([np.nan, 0.0]))
    d2 = AveragingDecimator(2, shape=(2,), skip_nonfinite=True)
    assert d2.push(0.0, np.array([np.nan, 1.0])) is None
    tc, m = d2.push(1.0, np.array([2.0, 3.0]))
    np.testing.assert_allclose(m, [2.0, 2.0])
