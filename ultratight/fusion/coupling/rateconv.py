"""Rate converters of the double-loop structure (Zhao et al. 2014, Fig. 1): averaging decimator and CIC interpolator.

Averaging decimator (prefilter 1000 Hz -> integration filter N Hz)
------------------------------------------------------------------
Each output is the mean of ``R`` consecutive inputs (``R = f_in / f_out``), tagged with the
mean of their time tags (the window centre: for uniform sampling t_first + (R-1)/(2 f_in)).
Before down-sampling this is the boxcar FIR with

    |H(f)| = | sin(pi R f / f_in) / (R sin(pi f / f_in)) |,   group delay (R-1)/2 input samples,

so constants and ramps pass exactly when read at the window centre (the tag).
Zeros at multiples of f_out: what aliases onto DC after down-sampling is rejected.

CIC interpolator (SINS 100 Hz -> NCO aiding 1000 Hz)
-----------------------------------------------------
Hogenauer structure: N comb stages at the low rate (differential delay M:
y = x - x[-M]), zero-stuffing by R, N integrator stages at the high rate, and the
gain normalisation R / (R M)^N so that the DC gain is 1.  Equivalent high-rate
FIR: h = (boxcar of length R M) convolved with itself N times, length
N (R M - 1) + 1, symmetric, hence linear phase with

    group delay  D = N (R M - 1) / 2   high-rate samples,
    |H(f)| / |H(0)| = | sin(pi R M f / f_hi) / (R M sin(pi f / f_hi)) |^N        (f_hi = R f_lo).

(The often-quoted form ``sin(pi M R f/f_hi) / (R sin(pi M f/f_hi))`` is the same only for
M = 1.)  Passband droop at f: 20 N log10|sin(pi R M f/f_hi)/(R M sin(pi f/f_hi))| dB, e.g.
R = 10, M = 1, N = 3 at 10 Hz (f_lo = 100 Hz): -0.43 dB, at 20 Hz: -1.7 dB.  Images sit at
k f_lo +- f and fall in the nulls at multiples of f_lo / M: rejection of the first image of a
10 Hz tone (90 Hz) = 20 N log10(|H(10 Hz)|/|H(90 Hz)|) ~= 57 dB for R = 10, M = 1, N = 3
(:func:`cic_image_rejection_db`).  B-spline property: for N >= 2 the interpolator reproduces
ramps exactly (after the start-up transient of N (R M - 1) samples) with the delay D; for
N >= 1 constants.

Time tags: the input sample m with tag t_m is stuffed at high-rate index m R; output
sample n then represents the input signal at time ``t_0 + (n - D) / f_hi``, which is the tag
returned (:meth:`CicInterpolator.push`).  For NCO aiding the engine should therefore feed the
SINS prediction ``D / f_hi`` ahead (or accept the delay).

Arithmetic: float64 integrators.  The comb/integrator pair is exact in integer
arithmetic; in float64 the integrators accumulate rounding error ~1e-16 relative per sample
of the integrator magnitude — negligible for Doppler aiding over hours at these magnitudes.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ultratight.errors import ConfigError, FilterError


def _check_rate_factor(R, name):
    if int(R) != R or R < 1:
        raise ConfigError(f"{name}: rate factor R={R!r} must be a positive integer")
    return int(R)


def decimation_factor(f_in_hz, f_out_hz):
    """R = f_in / f_out, which must be an integer."""
    r = f_in_hz / f_out_hz
    if not (f_out_hz > 0 and abs(r - round(r)) < 1e-9 and round(r) >= 1):
        raise ConfigError(f"rate conversion {f_in_hz} Hz -> {f_out_hz} Hz: the ratio must be a positive integer")
    return int(round(r))


def average_decimate(x, R, t=None):
    """Block-average x (n, ...) by R along axis 0 (complete windows only).

    Returns (y, t_out) with t_out the window-centre tags (mean of t, or sample index centres
    (R-1)/2 + k R when t is None).
    """
    R = _check_rate_factor(R, "average_decimate")
    x = np.asarray(x, dtype=float)
    m = x.shape[0] // R
    y = x[: m * R].reshape((m, R) + x.shape[1:]).mean(axis=1)
    if t is None:
        tt = (R - 1) / 2.0 + R * np.arange(m)
    else:
        tt = np.asarray(t, dtype=float)[: m * R].reshape(m, R).mean(axis=1)
    return y, tt


class AveragingDecimator:
    """Streaming averaging decimator for vectors of shape ``shape`` (e.g. (n_ch, 5)).

    ``push(t, x)`` adds one high-rate sample; returns (t_centre, mean) when a window of R
    samples completes, else None.  Non-finite samples raise FilterError unless
    ``skip_nonfinite``, in which case they are left out of the mean (the tag stays the centre
    of the finite samples; an all-invalid window yields NaN).
    """

    def __init__(self, R, shape=(), skip_nonfinite=False):
        self.R = _check_rate_factor(R, "AveragingDecimator")
        self.shape = tuple(shape)
        self.skip_nonfinite = bool(skip_nonfinite)
        self._sum = np.zeros(self.shape)
        self._cnt = np.zeros(self.shape)
        self._tsum = np.zeros(self.shape)
        self._n = 0

    @property
    def group_delay_samples(self):
        return (self.R - 1) / 2.0

    def reset(self):
        self._sum[...] = 0.0
        self._cnt[...] = 0.0
        self._tsum[...] = 0.0
        self._n = 0

    def push(self, t, x):
        x = np.asarray(x, dtype=float)
        if x.shape != self.shape:
            raise FilterError(f"AveragingDecimator.push: sample shape {x.shape}, expected {self.shape}")
        ok = np.isfinite(x)
        if not ok.all():
            if not self.skip_nonfinite:
                raise FilterError("AveragingDecimator.push: non-finite sample")
            x = np.where(ok, x, 0.0)
        self._sum += x
        self._cnt += ok
        self._tsum += ok * float(t)
        self._n += 1
        if self._n < self.R:
            return None
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = self._sum / self._cnt
            tc = self._tsum / self._cnt
        if tc.ndim:
            tc_all = float(np.nanmean(tc)) if np.isfinite(tc).any() else math.nan
        else:
            tc_all = float(tc)
        self.reset()
        return tc_all, mean


class ResidualDecimator:
    """The averaging decimator between the tracking channels (1 kHz) and the tight filter
    (``tight_rate_hz``): per channel, the window sums of the code and Doppler residuals against the
    outer loop's predictions, of the tracking bank's code / frequency variances and of the amplitude
    estimate, then their means as pseudorange / pseudorange-rate residuals with variances.

    The window is *time-based*: an epoch counts when its interval starts before the update time
    (channels are up to one code period apart, so the count per window can differ by one between
    channels). The sums ``acc`` (rows: n, code chips, Doppler Hz, P_tautau, P_ff, amplitude) are
    accumulated by the compiled epoch stage (:func:`ultratight.receiver.deep.epochs.epoch_post`).
    """

    ROWS = ("n", "code_chips", "doppler_hz", "P_tautau", "P_ff", "amplitude")

    def __init__(self, n_ch, rate_hz):
        self.acc = np.zeros((len(self.ROWS), int(n_ch)))
        self.step_s = 1.0 / float(rate_hz)
        self.t_next = self.step_s            # end of the current window (s of receiver time)

    def means(self, chip_m, wavelength_m, corr_factor, pr_floor_m, prr_floor_mps):
        """The window's measurement means and variances: a dict of (n_ch,) arrays ``ok`` (at least one
        epoch), ``amp``, ``doppler_hz``, ``dz_pr`` (m), ``dz_prr`` (m/s), ``var_pr``, ``var_prr``.
        The tracking variances are inflated by ``corr_factor`` (consecutive outputs are correlated)
        and floored by ``pr_floor_m`` / ``prr_floor_mps``."""
        acc_n, acc_cp, acc_f, acc_pt, acc_pf, acc_a = self.acc
        nn = np.maximum(acc_n, 1)
        m_cp = acc_cp / nn
        m_f = acc_f / nn
        return {"ok": acc_n > 0, "amp": acc_a / nn, "doppler_hz": m_f,
                "dz_pr": chip_m * m_cp, "dz_prr": wavelength_m * m_f,
                "var_pr": chip_m ** 2 * (acc_pt / nn) * corr_factor + pr_floor_m ** 2,
                "var_prr": (wavelength_m / (2.0 * math.pi)) ** 2 * (acc_pf / nn) * corr_factor
                + prr_floor_mps ** 2}

    def next_window(self):
        """Clear the sums and move the window end by one output period."""
        self.acc[:] = 0.0
        self.t_next += self.step_s


def cic_impulse_response(R, N, M=1, normalised=True):
    """High-rate impulse response of the CIC interpolator (convolution of N boxcars of length RM)."""
    R = _check_rate_factor(R, "cic_impulse_response")
    h = np.ones(1)
    box = np.ones(R * M)
    for _ in range(N):
        h = np.convolve(h, box)
    if normalised:
        h = h * (R / float(R * M) ** N)
    return h


def cic_response(f_hz, R, N, M=1, f_hi_hz=1.0):
    """|H(f)|/|H(0)| = |sin(pi R M f/f_hi) / (R M sin(pi f/f_hi))|^N (closed form)."""
    f = np.asarray(f_hz, dtype=float)
    x = np.pi * f / f_hi_hz
    num = np.sin(R * M * x)
    den = R * M * np.sin(x)
    with np.errstate(invalid="ignore", divide="ignore"):
        r = np.where(np.abs(den) < 1e-300, 1.0, num / np.where(den == 0, 1.0, den))
    # exact limit at multiples of f_hi (den -> 0): |num/den| -> 1
    r = np.where(np.isclose(np.sin(x), 0.0, atol=1e-15), 1.0, r)
    return np.abs(r) ** N


def cic_droop_db(f_hz, R, N, M=1, f_hi_hz=1.0):
    """Passband droop (dB, <= 0) of the gain-normalised CIC interpolator at f."""
    return 20.0 * np.log10(cic_response(f_hz, R, N, M, f_hi_hz))


def cic_image_rejection_db(f_hz, R, N, M=1, f_lo_hz=1.0):
    """Attenuation (dB) of the first image (f_lo - f) relative to the wanted tone f."""
    f_hi = R * f_lo_hz
    return 20.0 * np.log10(cic_response(f_hz, R, N, M, f_hi) / cic_response(f_lo_hz - f_hz, R, N, M, f_hi))


@njit(cache=True)
def _cic_run(comb, integ, j, x, gain, out):
    """One low-rate sample ``x`` (K,) through the CIC: the combs (delay lines ``comb`` (N, M, K), slot
    ``j``) at the low rate, then R zero-stuffed high-rate samples through the integrators ``integ``
    (N, K) into ``out`` (R, K), scaled by ``gain``. Each element sees the operations of the
    textbook structure in their order (Hogenauer 1981)."""
    n_st = comb.shape[0]
    for i in range(x.shape[0]):
        v = x[i]
        for s in range(n_st):
            old = comb[s, j, i]
            comb[s, j, i] = v
            v = v - old
        for k in range(out.shape[0]):
            u = v if k == 0 else 0.0
            for s in range(n_st):
                integ[s, i] = integ[s, i] + u
                u = integ[s, i]
            out[k, i] = u * gain


class CicInterpolator:
    """Streaming CIC interpolator by R (order N, differential delay M), gain-normalised.

    ``push(t, x)`` takes one low-rate sample (vector of shape ``shape``) with tag t (s) and
    returns (t_out (R,), y (R, *shape)): the R high-rate outputs and their time tags
    ``t0 + (n - D)/f_hi`` (see module docstring), where ``f_hi = R / T_lo`` and ``T_lo`` is
    the low-rate period (``f_lo_hz``).  ``prime(x)`` fills the filter state as if ``x`` had
    been applied forever (no start-up transient for a constant).
    """

    def __init__(self, R, N=3, M=1, f_lo_hz=100.0, shape=()):
        self.R = _check_rate_factor(R, "CicInterpolator")
        if int(N) != N or N < 1:
            raise ConfigError(f"CicInterpolator: order N={N!r} must be a positive integer")
        if int(M) != M or M < 1:
            raise ConfigError(f"CicInterpolator: differential delay M={M!r} must be a positive integer")
        if not f_lo_hz > 0:
            raise ConfigError(f"CicInterpolator: f_lo_hz={f_lo_hz!r} must be > 0")
        self.N = int(N)
        self.M = int(M)
        self.f_lo = float(f_lo_hz)
        self.f_hi = self.R * self.f_lo
        self.shape = tuple(shape)
        self._k = int(np.prod(self.shape, dtype=np.int64))    # elements per sample
        self.gain = self.R / float(self.R * self.M) ** self.N
        self.delay_samples = self.N * (self.R * self.M - 1) / 2.0
        self.delay_s = self.delay_samples / self.f_hi
        self._comb = np.zeros((self.N, self.M) + self.shape)   # delay lines of each comb
        self._cptr = 0
        self._integ = np.zeros((self.N,) + self.shape)
        self._t0 = None
        self._n_out = 0

    def reset(self):
        self._comb[...] = 0.0
        self._integ[...] = 0.0
        self._cptr = 0
        self._t0 = None
        self._n_out = 0

    def prime(self, x):
        """Steady state for a constant input x (comb delay lines = x at each stage, integrators)."""
        x = np.broadcast_to(np.asarray(x, dtype=float), self.shape)
        # run the structure on the constant past its start-up transient (N (RM-1) samples):
        # afterwards every comb outputs 0 and the integrators hold the steady state
        self._comb[...] = 0.0
        self._integ[...] = 0.0
        self._cptr = 0
        for _ in range(self.N * self.M + 2):
            self._run(x)
        self._n_out = 0

    def _run(self, x):
        k = self._k
        out = np.empty((self.R,) + self.shape)
        _cic_run(self._comb.reshape(self.N, self.M, k), self._integ.reshape(self.N, k), self._cptr,
                 np.ascontiguousarray(x, dtype=float).reshape(k), self.gain, out.reshape(self.R, k))
        self._cptr = (self._cptr + 1) % self.M
        return out

    def push(self, t, x):
        x = np.asarray(x, dtype=float)
        if x.shape != self.shape:
            raise FilterError(f"CicInterpolator.push: sample shape {x.shape}, expected {self.shape}")
        if not np.all(np.isfinite(x)):
            raise FilterError("CicInterpolator.push: non-finite input sample")
        if self._t0 is None:
            self._t0 = float(t) - self._n_out / self.f_hi
        y = self._run(x)
        n = self._n_out + np.arange(self.R)
        self._n_out += self.R
        return self._t0 + (n - self.delay_samples) / self.f_hi, y
