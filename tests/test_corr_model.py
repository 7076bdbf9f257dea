"""The correlator normalisation convention, checked against a direct simulation."""

import numpy as np

from ultratight.signals.corr_model import (
    amplitude_from_cn0,
    cn0_from_amplitude,
    code_autocorr,
    epl_noise_covariance,
    noise_sigma_arm,
    output_scale,
    signal_amplitude,
)


def test_amplitude_cn0_round_trip():
    for cn0 in (20.0, 35.0, 45.0):
        a = amplitude_from_cn0(cn0, 1e-3)
        assert np.isclose(cn0_from_amplitude(a, 1e-3), cn0)
    # 20 dB-Hz, 1 ms: C/N0*T = 0.1 -> A = sqrt(0.2)
    assert np.isclose(amplitude_from_cn0(20.0, 1e-3), np.sqrt(0.2))


def _simulate(complex_sampling, cn0_dbhz, fs=2.0e6, n_epochs=400, seed=3):
    """Carrier-only signal (code and data wiped) through the documented scaling."""
    rng = np.random.default_rng(seed)
    n = int(fs * 1e-3)
    sigma = 7.0
    a = float(signal_amplitude(cn0_dbhz, fs, sigma, complex_sampling))
    f_if = 0.0 if complex_sampling else fs / 4.3
    t = np.arange(n) / fs
    scale = output_scale(noise_sigma_arm(sigma, complex_sampling), n)
    out = np.empty(n_epochs, dtype=complex)
    for k in range(n_epochs):
        if complex_sampling:
            x = a * np.exp(1j * 2 * np.pi * f_if * t) + sigma * (rng.standard_normal(n) + 1j * rng.standard_normal(n))
        else:
            x = a * np.cos(2 * np.pi * f_if * t) + sigma * rng.standard_normal(n)
        out[k] = np.sum(x * np.exp(-1j * 2 * np.pi * f_if * t)) * scale
    return out


def test_scaling_gives_unit_noise_and_sqrt_2cn0t_amplitude():
    for complex_sampling in (True, False):
        noise_only = _simulate(complex_sampling, -100.0)
        assert abs(np.var(noise_only.real) - 1.0) < 0.2
        assert abs(np.var(noise_only.imag) - 1.0) < 0.2
        sig = _simulate(complex_sampling, 45.0)
        expected = amplitude_from_cn0(45.0, 1e-3)
        assert abs(np.mean(sig.real) / expected - 1.0) < 0.03


def test_epl_covariance_structure():
    cov = epl_noise_covariance(1.0)
    assert np.allclose(np.diag(cov), 1.0)
    assert np.isclose(cov[0, 1], 0.5) and np.isclose(cov[1, 2], 0.0)
    assert np.allclose(cov[:3, 3:], 0.0)
    assert np.all(np.linalg.eigvalsh(cov) > 0)
    half = epl_noise_covariance(0.5)
    assert np.isclose(half[1, 2], 0.5) and np.isclose(half[0, 1], 0.75)
    assert np.allclose(code_autocorr([-1.5, -0.5, 0.0, 0.25, 1.0]), [0.0, 0.5, 1.0, 0.75, 0.0])
