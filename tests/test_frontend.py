"""Front-end model: validation, quantiser levels and loading, quantisation loss, streaming filter."""

import numpy as np
import pytest
from scipy import signal as sps
from scipy.stats import norm

from ultratight.errors import ConfigError
from ultratight.signals.synth.frontend import FrontEnd, max_level, noise_lsb, quantize


@pytest.mark.parametrize("kw,msg", [
    (dict(fs_hz=0.0), "fs_hz"),
    (dict(fs_hz=-4e6), "fs_hz"),
    (dict(fs_hz=4e6, if_hz=2e6), "Nyquist"),
    (dict(fs_hz=4e6, if_hz=2.5e6, is_complex=False), r"fs/2"),
    (dict(fs_hz=4e6, if_hz=0.0, is_complex=False), r"fs/2"),
    (dict(fs_hz=4e6, bits=3), "bits"),
    (dict(fs_hz=4e6, bits=32), "bits"),
    (dict(fs_hz=4e6, filter_bw_hz=5e6), "filter_bw_hz"),
    (dict(fs_hz=8e6, if_hz=3e6, is_complex=False, filter_bw_hz=3e6), "band-pass"),
])
def test_impossible_parameters(kw, msg):
    with pytest.raises(ConfigError, match=msg):
        FrontEnd(**kw)


def test_from_config_sampling_checked():
    with pytest.raises(ConfigError, match="sampling"):
        FrontEnd.from_config({"fs_hz": 4e6, "sampling": "iq"})
    fe = FrontEnd.from_config({"fs_hz": 24e6, "if_hz": 6e6, "sampling": "real", "bits": 2})
    assert not fe.is_complex and fe.bits == 2


def test_quantiser_levels():
    x = np.array([-9.0, -4.5, -2.1, -1.9, -0.1, 0.1, 1.9, 2.1, 4.5, 9.0], np.float32)
    np.testing.assert_array_equal(quantize(x, 2), [-3, -3, -3, -1, -1, 1, 1, 3, 3, 3])
    np.testing.assert_array_equal(quantize(x, 1), np.sign(x))
    np.testing.assert_array_equal(quantize(np.array([-300, -126.6, 0.4, 126.4, 200], np.float32), 8),
                                  [-127, -127, 0, 126, 127])
    np.testing.assert_array_equal(quantize(np.array([-9.0, 6.6], np.float32), 4), [-7, 7])
    assert max_level(16) == 32767 and noise_lsb(2) == 2.0


def test_agc_loading_2bit_and_8bit():
    rng = np.random.default_rng(0)
    n = 400_000
    for sigma in (1.0, 20.0):
        x = (rng.standard_normal(2 * n).astype(np.float32) * sigma).view(np.complex64)
        y = FrontEnd(4e6, bits=2).quantize_block(x.copy(), sigma)
        frac_big = np.mean(np.abs(y.real) == 3)
        assert frac_big == pytest.approx(2 * norm.sf(1.0), abs=0.005)     # thresholds at +-1 sigma
        y8 = FrontEnd(4e6, bits=8).quantize_block(x.copy(), sigma)
        assert np.std(y8.real) == pytest.approx(31.75, rel=0.01)
        assert np.mean(np.abs(y8.real) == 127) < 1e-3


def test_fixed_gain_does_not_follow_noise_events():
    """Fixed gain: the nominal noise sits at noise_lsb/headroom LSB and a x20 noise event raises
    the sample power x400 (no AGC), still inside the clip level with headroom 20 at 16 bits."""
    rng = np.random.default_rng(5)
    n = 400_000
    fe = FrontEnd(4e6, bits=16, gain_mode="fixed", headroom=20.0)
    assert fe.lsb_per_sigma == pytest.approx(8191.75 / 20.0)
    stds = []
    for sigma in (1.0, 20.0):
        x = (rng.standard_normal(2 * n).astype(np.float32) * sigma).view(np.complex64)
        y = fe.quantize_block(x.copy(), sigma)
        stds.append(float(np.std(y.real)))
        assert np.mean(np.abs(y.real) == 32767) < 1e-3      # 4-sigma clip of the loudest noise
    assert stds[0] == pytest.approx(8191.75 / 20.0, rel=0.01)
    assert stds[1] / stds[0] == pytest.approx(20.0, rel=0.01)
    # the AGC (default) keeps the level instead
    agc = FrontEnd(4e6, bits=16)
    ya = agc.quantize_block((rng.standard_normal(2 * n).astype(np.float32) * 20.0).view(np.complex64), 20.0)
    assert np.std(ya.real) == pytest.approx(8191.75, rel=0.01)
    d = FrontEnd.from_config({"fs_hz": 4e6, "gain": "fixed", "headroom": 20.0}).to_dict()
    assert d["gain"] == "fixed" and d["headroom"] == 20.0


def test_gain_mode_validation():
    with pytest.raises(ConfigError, match="frontend.gain"):
        FrontEnd(4e6, gain_mode="slow")
    with pytest.raises(ConfigError, match="frontend.headroom"):
        FrontEnd(4e6, gain_mode="fixed", headroom=0.5)


@pytest.mark.parametrize("bits,loss_db", [(1, 1.96), (2, 0.55), (8, 0.0)])
def test_quantisation_loss(bits, loss_db):
    """Correlation SNR loss of a weak signal through the quantiser (classic values)."""
    rng = np.random.default_rng(bits)
    n = 2_000_000
    s = rng.choice(np.array([-1.0, 1.0], np.float32), size=n)
    a = 0.05
    x = (a * s + rng.standard_normal(n).astype(np.float32)).astype(np.float32)
    fe = FrontEnd(4e6, if_hz=1e6, is_complex=False, bits=bits)
    y = fe.quantize_block(x.copy(), 1.0).astype(np.float64)
    # output SNR of the correlation sum, relative to the unquantised one (a^2 per sample)
    snr = np.mean(y * s) ** 2 / np.var(y)
    loss = 10 * np.log10(a * a / snr)
    assert loss == pytest.approx(loss_db, abs=0.12)


def test_streaming_filter_equals_one_shot_and_keeps_sigma():
    rng = np.random.default_rng(2)
    x = (rng.standard_normal(2 * 100_000).astype(np.float32)).view(np.complex64)
    fe = FrontEnd(8e6, filter_bw_hz=2.5e6)
    parts = [fe.filter(x[i:i + 7777].copy()) for i in range(0, len(x), 7777)]
    y = np.concatenate(parts)
    ref = sps.sosfilt(sps.butter(4, 1.25e6, fs=8e6, output="sos"), x.astype(np.complex128)) / fe.noise_gain
    np.testing.assert_allclose(y, ref, atol=2e-5)
    assert np.std(y[1000:].real) == pytest.approx(1.0, rel=0.02)


def test_lowpass_and_bandpass_selectivity():
    fs = 8e6
    n = np.arange(40000)
    fe = FrontEnd(fs, filter_bw_hz=2e6)
    inband = fe.filter(np.exp(2j * np.pi * 0.2e6 * n / fs).astype(np.complex64))
    outband = FrontEnd(fs, filter_bw_hz=2e6).filter(np.exp(2j * np.pi * 3.2e6 * n / fs).astype(np.complex64))
    g_in = np.abs(inband[5000:]).mean() * fe.noise_gain
    g_out = np.abs(outband[5000:]).mean() * fe.noise_gain
    assert g_in == pytest.approx(1.0, abs=0.02)
    assert 20 * np.log10(g_out) < -35
    fr = FrontEnd(fs, if_hz=2e6, is_complex=False, filter_bw_hz=2e6)
    tone = fr.filter(np.cos(2 * np.pi * 2.1e6 * n / fs).astype(np.float32))
    assert np.max(np.abs(tone[5000:])) * fr.noise_gain == pytest.approx(1.0, abs=0.03)
    far = FrontEnd(fs, if_hz=2e6, is_complex=False, filter_bw_hz=2e6).filter(
        np.cos(2 * np.pi * 0.2e6 * n / fs).astype(np.float32))
    assert np.max(np.abs(far[5000:])) * fr.noise_gain < 0.02
