"""The one definition of correlator output normalisation (used by the correlator
bank, the IF generator's truth, the correlator-level simulator and the
prefilters' measurement model).

Convention
----------
Every correlator output (I and Q of every tap) is the coherent sum of the
carrier-wiped, code-multiplied samples divided by ``sigma_arm * sqrt(N)``,
where ``N`` is the number of samples in the integration and ``sigma_arm`` is
the standard deviation of the input noise *per arm after carrier wipe-off*:

* complex input ``x = a * c * d * exp(j phi) + n`` with per-component noise
  std ``sigma``: ``sigma_arm = sigma``;
* real input ``x = a * c * d * cos(w t + phi) + n`` with noise std ``sigma``:
  ``sigma_arm = sigma / sqrt(2)`` (mixing halves the noise per arm).

With this scaling the noise on each arm of each tap has unit variance, whatever
the sampling rate, integration time or front-end gain, and the prompt amplitude
of a perfectly tracked signal is

    A = sqrt(2 * C/N0 * T)          (C/N0 in Hz, T in s)

so that ``(I_P^2 + Q_P^2) / 2 = C/N0 * T`` on average (signal part).  This
``A`` is the ``A*T`` of Zhao et al. 2014, eq. 3 (see docs/references.md): the prefilter state ``A`` is in
these units.  Taps spaced ``d`` chips apart have noise correlation ``R(d)``
(the code autocorrelation), which gives the non-diagonal measurement
covariance of the six outputs ``[I_P, I_E, I_L, Q_P, Q_E, Q_L]``.

In practice ``sigma`` is estimated from the block's sample power (the signal is
far below the noise for GPS), see :func:`noise_sigma_arm`.
"""

import math

import numpy as np


def amplitude_from_cn0(cn0_dbhz, t_int):
    """Normalised prompt amplitude A = sqrt(2 * C/N0 * T) for C/N0 in dB-Hz and T in s."""
    return np.sqrt(2.0 * 10.0 ** (np.asarray(cn0_dbhz, dtype=float) / 10.0) * t_int)


def cn0_from_amplitude(amplitude, t_int):
    """Inverse of :func:`amplitude_from_cn0`: C/N0 in dB-Hz."""
    return 10.0 * np.log10(np.asarray(amplitude, dtype=float) ** 2 / (2.0 * t_int))


def signal_amplitude(cn0_dbhz, fs, sigma, complex_sampling):
    """Per-sample signal amplitude ``a`` giving C/N0 against noise of std ``sigma``.

    Complex sampling: C = a^2, N0 = 2 sigma^2 / fs  ->  a = sigma * sqrt(2 C/N0 / fs).
    Real sampling:    C = a^2/2, N0 = 2 sigma^2 / fs (one-sided over fs/2)
                      ->  a = sigma * sqrt(4 C/N0 / fs).
    """
    cn0 = 10.0 ** (np.asarray(cn0_dbhz, dtype=float) / 10.0)
    k = 2.0 if complex_sampling else 4.0
    return sigma * np.sqrt(k * cn0 / fs)


def noise_sigma_arm(sigma, complex_sampling):
    """Per-arm noise std after carrier wipe-off, from the input noise std."""
    return sigma if complex_sampling else sigma / math.sqrt(2.0)


def output_scale(sigma_arm, n_samples):
    """Factor applied to raw correlator sums: 1 / (sigma_arm * sqrt(N))."""
    return 1.0 / (sigma_arm * math.sqrt(n_samples))


def code_autocorr(tau_chips):
    """Ideal C/A autocorrelation R(tau): triangle of half-width one chip."""
    t = np.abs(np.asarray(tau_chips, dtype=float))
    return np.where(t < 1.0, 1.0 - t, 0.0)


def tap_offsets(spacing_chips=1.0):
    """Code offsets (chips) of the taps [P, E, L]: d_P = 0, d_E = -D/2, d_L = +D/2."""
    h = 0.5 * spacing_chips
    return np.array([0.0, -h, h])


def epl_noise_covariance(spacing_chips=1.0):
    """6x6 unit-variance noise covariance of [I_P, I_E, I_L, Q_P, Q_E, Q_L].

    Taps offset by ``d`` chips share a fraction ``R(d)`` of their noise; I and Q
    arms are independent.
    """
    d = tap_offsets(spacing_chips)
    r3 = code_autocorr(d[:, None] - d[None, :])
    cov = np.zeros((6, 6))
    cov[:3, :3] = r3
    cov[3:, 3:] = r3
    return cov
