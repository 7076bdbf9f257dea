"""Inner-loop NCO feedback law of the double-loop (DLB) structure (Zhao et al. 2014, Fig. 1).

Every epoch, after the prefilter bank has predicted the tracking errors for
the start of the next integration interval (``bank.x``, rows
``[A, dtau, dphi, df, da]``, all *true minus NCO*, the NCO frequency being
constant within an interval), each channel's code and carrier NCOs are moved
by the estimated errors and the applied part is removed from the state
(error-state feedback)::

    carrier frequency  f   += k_f (df + k_da da T/2) / 2pi       (Hz)
    carrier phase      phi += k_phi dphi / 2pi                  (cycles)
    code phase         p   += k_tau dtau                        (chips)
    code rate          r    = F_CA (1 + (f - IF) / F_L1)        (carrier aiding of the code)
    dx = [0, k_tau dtau, k_phi dphi, k_f (df + k_da da T/2), 0],    x <- x - dx

``da T/2`` centres the constant NCO frequency on the next interval (with a
carrier acceleration ``da`` the mean frequency error over it is then zero).
The code NCO rate is always slaved to the carrier NCO Doppler (code and
carrier aid each other: the carrier sets the code rate, the code phase error
is corrected from dtau), which is what makes the model's ``d dtau/dt = beta df``
hold.  ``da`` itself is never fed back (the NCO has no rate term): it is the
line-of-sight acceleration relative to the piecewise-constant NCO and acts
through the predicted ``df`` every epoch.

Outer loop (aiding): its Doppler prediction ``aid`` (Hz, for the middle of the
next interval) enters as a *known input* to the error dynamics: the change of
the outer loop's Doppler rate, ``2pi (rate_k - rate_{k-1})`` with
``rate_k = (aid_k - aid_{k-1})/T``, is added to ``da`` every epoch while
``use_aid`` holds (:meth:`InnerLoop.prime_aiding` injects the initial rate).
The prefilter then only has to estimate the *residual* dynamics (aiding
error), and the NCO command is "outer prediction + inner correction" through
the predicted state.  When the arbitration clears ``use_aid`` for a channel the
injection stops and the inner loop alone estimates the dynamics (its ``da``
keeps the last value: no jump); when aiding resumes the history restarts
(the first rate change is taken after two aided epochs).  (A direct NCO
feed-forward of the aiding increments would also need the state to be
told about the within-interval frequency ramp; injecting into ``da`` keeps
the model exact.)

``code_phase`` is not wrapped: the correlator bank integrates to the end of the
current code period from whatever (slightly negative or > 0) code phase it
holds (see ultratight.receiver.dsp.correlator).

The same law serves the PB-KF-UTC baseline (its bank uses the same state
layout), and the correlator-level simulator (``ultratight.signals.synth.corrsim``)
drives an :class:`ultratight.signals.nco.NcoBank` like the correlator bank, so the engine, the simulator
and the tests call exactly the same code.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ultratight.constants import F_CA, F_L1, T_CA
from ultratight.errors import FilterError
from ultratight.fusion.channel.prefilter_model import IDA, IF, IPHI, ITAU, NX
from ultratight.signals.nco import NcoBank
from ultratight.signals.signal import GPS_L1CA

TWO_PI = 2.0 * math.pi

# The law's parameters (its ``prm`` vector); names are compile-time constants in the kernels.
LAW_T = 0                   # epoch T (s)
LAW_IF_HZ = 1               # the correlator's IF (Hz)
LAW_K_TAU = 2               # code phase gain
LAW_K_PHI = 3               # carrier phase gain
LAW_K_F = 4                 # carrier frequency gain
LAW_K_DA = 5                # weight of the acceleration term da T/2 in the frequency command
LAW_CHIP_RATE_HZ = 6        # code chip rate (Hz) of the code-rate aiding
LAW_CARRIER_HZ = 7          # carrier frequency (Hz) of the code-rate aiding
N_LAW_PRM = 8

# Aiding history of a channel (``hist``).
HIST_NONE = 0               # no aiding history
HIST_AID = 1                # previous aiding value known
HIST_RATE = 2               # previous aiding rate known


@njit(cache=True)
def feedback_one(c, x, active, code_phase, code_rate, carr_phase, carr_freq, aid_now, aid_prev,
                 rate_prev, hist, use_aid, prm, dx):
    """The law for channel ``c`` (the loop body of :func:`feedback_kernel`; touches only row ``c``)."""
    T = prm[LAW_T]
    if_hz = prm[LAW_IF_HZ]
    k_tau = prm[LAW_K_TAU]
    k_phi = prm[LAW_K_PHI]
    k_f = prm[LAW_K_F]
    k_da = prm[LAW_K_DA]
    f_ca = prm[LAW_CHIP_RATE_HZ]
    f_l1 = prm[LAW_CARRIER_HZ]
    for i in range(NX):
        dx[c, i] = 0.0
    if not active[c]:
        return
    # outer-loop aiding: its Doppler rate is a known input to the error acceleration
    if use_aid[c] and aid_now[c] == aid_now[c]:
        if hist[c] >= HIST_AID:
            rate = (aid_now[c] - aid_prev[c]) / T
            if hist[c] >= HIST_RATE:
                d_in = TWO_PI * (rate - rate_prev[c])
                x[c, IDA] += d_in
                dx[c, IDA] = -d_in
            rate_prev[c] = rate
            hist[c] = HIST_RATE
        else:
            hist[c] = HIST_AID
        aid_prev[c] = aid_now[c]
    else:
        hist[c] = HIST_NONE
    f_old = carr_freq[c]
    u_f = k_f * (x[c, IF] + k_da * x[c, IDA] * 0.5 * T)      # rad/s
    f_new = f_old + u_f / TWO_PI
    carr_freq[c] = f_new
    dphi = k_phi * x[c, IPHI]
    ph = carr_phase[c] + dphi / TWO_PI
    carr_phase[c] = ph - math.floor(ph)
    dtau = k_tau * x[c, ITAU]
    code_phase[c] += dtau
    code_rate[c] = f_ca * (1.0 + (f_new - if_hz) / f_l1)
    dx[c, ITAU] = dtau
    dx[c, IPHI] = dphi
    dx[c, IF] = u_f
    x[c, ITAU] -= dtau
    x[c, IPHI] -= dphi
    x[c, IF] -= u_f


@njit(cache=True)
def feedback_kernel(x, active, code_phase, code_rate, carr_phase, carr_freq, aid_now, aid_prev,
                    rate_prev, hist, use_aid, prm, dx):
    """The law for every channel; prm (N_LAW_PRM): entries ``LAW_*`` (:func:`law_parameters`);
    hist[c]: the aiding history, ``HIST_NONE`` | ``HIST_AID`` | ``HIST_RATE``."""
    for c in range(x.shape[0]):
        feedback_one(c, x, active, code_phase, code_rate, carr_phase, carr_freq, aid_now, aid_prev,
                     rate_prev, hist, use_aid, prm, dx)


def law_parameters(T, if_hz, k_tau, k_phi, k_f, k_da, chip_rate_hz, carrier_hz):
    """The law's parameter vector (entries ``LAW_*``)."""
    prm = np.zeros(N_LAW_PRM)
    prm[LAW_T] = T
    prm[LAW_IF_HZ] = if_hz
    prm[LAW_K_TAU] = k_tau
    prm[LAW_K_PHI] = k_phi
    prm[LAW_K_F] = k_f
    prm[LAW_K_DA] = k_da
    prm[LAW_CHIP_RATE_HZ] = chip_rate_hz
    prm[LAW_CARRIER_HZ] = carrier_hz
    return prm


def apply_feedback(x, active, code_phase, code_rate, carr_phase, carr_freq, T=T_CA, if_hz=0.0,
                   k_tau=1.0, k_phi=1.0, k_f=1.0, k_da=1.0):
    """Stateless form of the law without outer-loop aiding: moves the NCO arrays (in place)
    by the predicted errors ``x`` (n_ch, 5) of the ``active`` channels, removes the applied part
    from ``x`` (in place) and returns the state change dx (n_ch, 5).  With aiding use
    :class:`InnerLoop` (it keeps the aiding history)."""
    n = x.shape[0]
    prm = law_parameters(float(T), float(if_hz), k_tau, k_phi, k_f, k_da, F_CA, F_L1)
    dx = np.zeros((n, NX))
    nan = np.full(n, np.nan)
    feedback_kernel(x, np.asarray(active), code_phase, code_rate, carr_phase, carr_freq, nan, nan.copy(),
                     np.zeros(n), np.zeros(n, dtype=np.int64), np.zeros(n, dtype=np.bool_), prm, dx)
    return dx


class InnerLoop:
    """Inner-loop feedback law for ``n_ch`` channels (see module docstring).

    Parameters: ``T`` epoch (s), ``if_hz`` the correlator's IF, gains ``k_tau``, ``k_phi``,
    ``k_f`` in [0, 1] (1 = full error-state feedback every epoch), ``k_da`` (1: centre the
    frequency on the next interval using the acceleration estimate); ``signal`` (a
    :class:`ultratight.signals.signal.SignalDescription`) gives the code-carrier ratio of the
    code-rate aiding.

    ``apply(bank, nco, aid_doppler_hz=None, use_aid=None)``: ``bank`` is a tracking bank
    (``PrefilterBank``, ``PbKfBank`` or a view of one) with ``x`` (n_ch, 5) (modified in place),
    ``active`` (n_ch,) bool and ``note_correction(dx)`` (told the correction just applied);
    ``nco`` is an :class:`ultratight.signals.nco.NcoBank` (a correlator bank's ``nco``, or the
    correlator-level simulator's), moved in place.  ``aid_doppler_hz``
    (n_ch,) is the outer loop's Doppler prediction for the next interval (None: no aiding);
    ``use_aid`` (n_ch,) bool is the arbitration mask (None: aid every channel when aiding is
    given).  Returns dx (n_ch, 5), the state change booked into the bank.
    """

    def __init__(self, n_ch, T=T_CA, if_hz=0.0, k_tau=1.0, k_phi=1.0, k_f=1.0, k_da=1.0, signal=GPS_L1CA):
        for name, g in (("k_tau", k_tau), ("k_phi", k_phi), ("k_f", k_f), ("k_da", k_da)):
            if not (0.0 <= g <= 1.0):
                raise FilterError(f"InnerLoop {name}={g!r}: expected a gain in [0, 1]")
        self.n_ch = int(n_ch)
        self.T = float(T)
        self.prm = law_parameters(float(T), float(if_hz), k_tau, k_phi, k_f, k_da, signal.chip_rate_hz,
                                  signal.carrier_hz)
        self.aid_prev = np.zeros(self.n_ch)
        self.rate_prev = np.zeros(self.n_ch)
        self.hist = np.zeros(self.n_ch, dtype=np.int64)
        self.dx = np.zeros((self.n_ch, NX))
        self._nan = np.full(self.n_ch, np.nan)
        self._false = np.zeros(self.n_ch, dtype=np.bool_)
        self._true = np.ones(self.n_ch, dtype=np.bool_)

    def prime_aiding(self, bank, aid_doppler_hz, aid_rate_hzps, channels=None):
        """Start aiding channels whose NCO was started on the outer-loop Doppler: the aiding
        history starts here and the outer loop's Doppler rate (Hz/s) is injected into da."""
        ch = np.arange(self.n_ch) if channels is None else np.atleast_1d(np.asarray(channels))
        self.aid_prev[ch] = np.broadcast_to(np.asarray(aid_doppler_hz, dtype=float), (self.n_ch,))[ch]
        self.rate_prev[ch] = np.broadcast_to(np.asarray(aid_rate_hzps, dtype=float), (self.n_ch,))[ch]
        self.hist[ch] = HIST_RATE
        bank.x[ch, IDA] += TWO_PI * self.rate_prev[ch]

    def reset_aiding(self, channels=None):
        """Forget the aiding history (e.g. after a channel (re)start)."""
        if channels is None:
            self.hist[:] = HIST_NONE
        else:
            self.hist[np.asarray(channels)] = HIST_NONE

    def apply(self, bank, nco, aid_doppler_hz=None, use_aid=None):
        if not isinstance(nco, NcoBank):
            raise FilterError(f"InnerLoop.apply: nco must be an ultratight.signals.nco.NcoBank, got "
                              f"{type(nco).__name__}")
        x = bank.x
        if aid_doppler_hz is None:
            aid_now = self._nan
            mask = self._false
        else:
            aid_now = aid_doppler_hz
            if use_aid is None:
                mask = self._true
            else:
                mask = use_aid
            if aid_now.shape != (self.n_ch,) or mask.shape != (self.n_ch,):
                raise FilterError(f"InnerLoop.apply: aid_doppler_hz and use_aid must have shape ({self.n_ch},)")
        feedback_kernel(x, bank.active, nco.code_phase, nco.code_rate, nco.carr_phase, nco.carr_freq,
                         aid_now, self.aid_prev, self.rate_prev, self.hist, mask, self.prm, self.dx)
        bank.note_correction(self.dx)
        return self.dx
