"""Noise events inside the receiver: the readings of Zhao et al. 2014 §3's "measurement noise
parameters x20" that do not act on the IF samples (docs/ultratight.md "Noise-burst readings").

A scenario's ``[[noise_events]]`` carry a ``place``:

* ``"if"`` (default): the IF noise std x ``noise_factor`` over ``[t0_s, t1_s)`` — made by the
  generator (:func:`ultratight.signals.synth.generator.noise_factor`); nothing here.
* ``"correlator"``: zero-mean Gaussian noise added to every correlator output of the ultra-tight
  engine so that each arm's noise std is ``noise_factor`` x its thermal value (the outputs carry unit
  noise per arm). The added noise has the thermal noise's own structure: the E/P/L taps of an arm
  share the fraction ``R(d_i - d_j)`` of it (:func:`ultratight.signals.corr_model.code_autocorr`, the
  taps' offsets), I and Q are independent. It is drawn once per run from its own seed, so every
  method of a run sees the same samples.
* ``"filter-r"``: the tracking filters' measurement-noise covariance (the prefilters' R, the PB-KF's
  discriminator variances) x ``noise_factor``², the signal unchanged — a model mismatch, not noise.

An epoch is inside an event when its code period starts in ``[t0_s, t1_s)`` of receiver time; the
factors of overlapping events multiply, as the generator's do.
"""

from collections import namedtuple

import numpy as np
from numba import njit

from ultratight.errors import ConfigError
from ultratight.signals.corr_model import code_autocorr

PLACES = ("if", "correlator", "filter-r")
PLACE_IF = "if"

# the compiled stage's arrays: correlator-noise events (t0, t1, factor), the unit noise of the epochs
# ``k0 .. k0 + K - 1`` (n_ch, K, 6, coloured), filter-R events (t0, t1, factor^2) and the per-channel
# R scale of the epoch just run
Burst = namedtuple("Burst", "cn_t0 cn_t1 cn_f k0 unit rr_t0 rr_t1 rr_f2 rscale")


def event_place(ev):
    """The ``place`` of a ``[[noise_events]]`` entry (default ``"if"``)."""
    return ev.get("place", PLACE_IF)


def if_events(events):
    """The events the IF generator applies."""
    return [ev for ev in events or [] if event_place(ev) == PLACE_IF]


def validate_place(ev, i):
    p = event_place(ev)
    if p not in PLACES:
        raise ConfigError(f"noise_events[{i}].place must be one of {', '.join(PLACES)}; got {p!r}")
    if p == "correlator" and float(ev["noise_factor"]) < 1.0:
        raise ConfigError(f"noise_events[{i}]: noise at the correlator outputs can only be added "
                          f"(noise_factor >= 1), got {ev['noise_factor']!r}")


def _arrays(events, place):
    evs = [ev for ev in events or [] if event_place(ev) == place]
    return (np.array([float(ev["t0_s"]) for ev in evs]), np.array([float(ev["t1_s"]) for ev in evs]),
            np.array([float(ev["noise_factor"]) for ev in evs]))


def make_burst(events, n_ch, tap_off, code_period_s, seed):
    """The :class:`Burst` of a run: ``events`` (the scenario's ``[[noise_events]]``), ``n_ch``
    channels, correlator tap offsets ``tap_off`` (chips, [P, E, L]), the code period, and the seed of
    the correlator noise (``numpy.random.SeedSequence([seed, 11])``)."""
    c0, c1, cf = _arrays(events, "correlator")
    r0, r1, rf = _arrays(events, "filter-r")
    if c0.size:
        k0 = max(0, int(np.floor(c0.min() / code_period_s)) - 2)
        K = int(np.ceil(c1.max() / code_period_s)) + 2 - k0
        d = np.asarray(tap_off, dtype=float)
        L3 = np.linalg.cholesky(code_autocorr(d[:, None] - d[None, :]) + 1e-12 * np.eye(3))
        rng = np.random.default_rng(np.random.SeedSequence([int(seed), 11]))
        w = rng.standard_normal((n_ch, K, 2, 3)) @ L3.T          # coloured per arm (I, Q)
        unit = np.ascontiguousarray(w.reshape(n_ch, K, 6))
    else:
        k0, unit = 0, np.zeros((n_ch, 1, 6))
    return Burst(c0, c1, cf, np.int64(k0), unit, r0, r1, rf * rf, np.ones(n_ch))


@njit(cache=True)
def burst_one(c, k_ep, t_s, burst, out):
    """Channel ``c`` at epoch ``k_ep`` whose code period starts at receiver time ``t_s``: adds the
    correlator noise of the events it is inside to ``out[c]`` and sets ``burst.rscale[c]``."""
    f = 1.0
    for e in range(burst.cn_t0.shape[0]):
        if burst.cn_t0[e] <= t_s < burst.cn_t1[e]:
            f *= burst.cn_f[e]
    if f != 1.0:
        i = k_ep - burst.k0
        if i < 0:
            i = 0
        if i > burst.unit.shape[1] - 1:
            i = burst.unit.shape[1] - 1
        a = _sqrt_pos(f * f - 1.0)
        for m in range(6):
            out[c, m] += a * burst.unit[c, i, m]
    s = 1.0
    for e in range(burst.rr_t0.shape[0]):
        if burst.rr_t0[e] <= t_s < burst.rr_t1[e]:
            s *= burst.rr_f2[e]
    burst.rscale[c] = s


@njit(cache=True)
def burst_all(k_ep, t_start, fs, burst, out):
    """:func:`burst_one` for every channel (``t_start``: each channel's first sample, ``fs`` Hz)."""
    for c in range(out.shape[0]):
        burst_one(c, k_ep, t_start[c] / fs, burst, out)


@njit(cache=True)
def _sqrt_pos(v):
    """sqrt of ``v``, 0 for ``v`` <= 0."""
    return np.sqrt(v) if v > 0.0 else 0.0
