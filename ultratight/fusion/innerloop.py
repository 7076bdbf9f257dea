"""Inner-loop NCO feedback law of the double-loop (DLB) structure (SPEC §1).

Every epoch, after the prefilter bank has predicted the tracking errors for
the start of the next integration interval (``bank.x``, rows
``[A, dtau, dphi, df, da]``, all *true minus NCO*), each channel's code and
carrier NCOs are moved by the estimated errors and the applied part is removed
from the state (error-state feedback)::

    carrier frequency  f_new = f_old + k_f (df + da T/2) / 2pi          (inner correction)
                                     + use_aid (aid_now - aid_prev)    (outer-loop feed-forward)
    carrier phase      phi  += k_phi dphi / 2pi                         (cycles)
    code phase         p    += k_tau dtau                               (chips)
    code rate          r     = F_CA (1 + (f_new - IF) / F_L1)           (carrier aiding of the code)

``da T/2`` centres the (constant) NCO frequency on the interval: with a
carrier acceleration ``da`` the mean frequency error over the next interval is
then zero.  The code NCO rate is always slaved to the carrier NCO Doppler
(code and carrier aid each other: the carrier sets the code rate, the code
phase error is corrected from dtau), which is what makes the model's
``d dtau/dt = beta df`` hold.  The state change is then

    dx = [0, k_tau dtau, k_phi dphi, k_f (df + k_da da T/2), 0]      x <- x - dx

The outer loop enters as a feed-forward of its predicted Doppler *increments*
(``aid_now - aid_prev``, Hz; ``aid_now`` should be the prediction for the
middle of the next interval).  An aiding increment stands for the change of the
*true* Doppler over the epoch, so it is not booked into ``df``: while
``use_aid`` holds, the NCO follows the outer-loop dynamics and the error
acceleration ``da`` is only the residual (aiding error) dynamics.  When the
arbitration clears ``use_aid`` for a channel, its NCO keeps its frequency and
the inner loop alone steers it; the NCO's lost rate is then added to ``da``
(``+2pi (aid_now - aid_prev)/T``), and removed again when aiding resumes.
Switching is continuous (no frequency jump).  The carrier
acceleration ``da`` is not fed back (the NCO has no rate term): it stays in the
state and acts through ``df`` every epoch.

``code_phase`` is not wrapped: the correlator bank integrates to the end of the
current code period from whatever (slightly negative or > 0) code phase it
holds (see ultratight.receiver.correlator).

The same law serves the PB-KF-UTC baseline (its bank uses the same state
layout), and the correlator-level simulator (``ultratight.fusion.corrsim``)
exposes NCO arrays with the correlator's names, so the engine, the simulator
and the tests call exactly the same code.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ultratight.constants import F_CA, F_L1, T_CA
from ultratight.errors import FilterError

NX = 5
ITAU, IPHI, IF, IDA = 1, 2, 3, 4
TWO_PI = 2.0 * math.pi


@njit(cache=True)
def _feedback_kernel(x, active, code_phase, code_rate, carr_phase, carr_freq, aid_now, aid_prev,
                     use_aid, was_aided, prm, dx):
    """prm = [T, if_hz, k_tau, k_phi, k_f, k_da, f_ca, f_l1]."""
    T = prm[0]
    if_hz = prm[1]
    k_tau = prm[2]
    k_phi = prm[3]
    k_f = prm[4]
    k_da = prm[5]
    f_ca = prm[6]
    f_l1 = prm[7]
    n = x.shape[0]
    for c in range(n):
        for i in range(NX):
            dx[c, i] = 0.0
        if not active[c]:
            continue
        f_old = carr_freq[c]
        u_f = k_f * (x[c, IF] + k_da * x[c, IDA] * 0.5 * T)      # rad/s, inner correction
        f_new = f_old + u_f / TWO_PI
        d_aid = aid_now[c] - aid_prev[c]
        if not (d_aid == d_aid):          # no aiding history -> no increment
            d_aid = 0.0
        if use_aid[c]:
            # outer-loop feed-forward: models the true Doppler change, not booked into df
            f_new += d_aid
            if not was_aided[c]:
                # the NCO starts following the outer loop: the error acceleration loses it
                x[c, IDA] -= TWO_PI * d_aid / T
                dx[c, IDA] = TWO_PI * d_aid / T
        elif was_aided[c]:
            # the NCO stops following the outer loop: its rate returns to the error acceleration
            x[c, IDA] += TWO_PI * d_aid / T
            dx[c, IDA] = -TWO_PI * d_aid / T
        was_aided[c] = use_aid[c]
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


class InnerLoop:
    """Inner-loop feedback law for ``n_ch`` channels (see module docstring).

    Parameters: ``T`` epoch (s), ``if_hz`` the correlator's IF, gains ``k_tau``, ``k_phi``,
    ``k_f`` in [0, 1] (1 = full error-state feedback every epoch), ``k_da`` (1: centre the
    frequency on the next interval using the acceleration estimate).

    ``apply(bank, nco, aid_doppler_hz=None, use_aid=None)``: ``bank`` has ``x`` (n_ch, 5),
    ``active`` and ``correct(dx)``; ``nco`` has float arrays ``code_phase``, ``code_rate``,
    ``carr_phase``, ``carr_freq`` (a CorrelatorBank or corrsim.SimNco).  ``aid_doppler_hz``
    (n_ch,) is the outer loop's Doppler prediction for the next interval (None: no aiding);
    ``use_aid`` (n_ch,) bool is the arbitration mask (None: aid every channel when aiding is
    given).  Returns dx (n_ch, 5), the state change booked into the bank.
    """

    def __init__(self, n_ch, T=T_CA, if_hz=0.0, k_tau=1.0, k_phi=1.0, k_f=1.0, k_da=1.0):
        for name, g in (("k_tau", k_tau), ("k_phi", k_phi), ("k_f", k_f), ("k_da", k_da)):
            if not (0.0 <= g <= 1.0):
                raise FilterError(f"InnerLoop {name}={g!r}: expected a gain in [0, 1]")
        self.n_ch = int(n_ch)
        self.prm = np.array([float(T), float(if_hz), k_tau, k_phi, k_f, k_da, F_CA, F_L1])
        self.aid_prev = np.zeros(self.n_ch)
        self.have_prev = np.zeros(self.n_ch, dtype=np.bool_)
        self.was_aided = np.zeros(self.n_ch, dtype=np.bool_)
        self.dx = np.zeros((self.n_ch, NX))
        self._zeros = np.zeros(self.n_ch)
        self._false = np.zeros(self.n_ch, dtype=np.bool_)
        self._mask = np.zeros(self.n_ch, dtype=np.bool_)

    def reset_aiding(self, channels=None):
        """Forget the previous aiding value (e.g. after a channel (re)start)."""
        if channels is None:
            self.have_prev[:] = False
        else:
            self.have_prev[np.asarray(channels)] = False

    def apply(self, bank, nco, aid_doppler_hz=None, use_aid=None):
        x = bank.x
        if x.shape != (self.n_ch, NX):
            raise FilterError(f"InnerLoop.apply: state must have shape ({self.n_ch}, {NX}), got {x.shape}")
        if aid_doppler_hz is None:
            aid_now = self._zeros
            mask = self._false
        else:
            aid_now = np.asarray(aid_doppler_hz, dtype=np.float64)
            if aid_now.shape != (self.n_ch,):
                raise FilterError(f"InnerLoop.apply: aid_doppler_hz must have shape ({self.n_ch},), "
                                  f"got {aid_now.shape}")
            if use_aid is None:
                mask = self._mask
                mask[:] = True
            else:
                mask = np.asarray(use_aid, dtype=np.bool_)
                if mask.shape != (self.n_ch,):
                    raise FilterError(f"InnerLoop.apply: use_aid must have shape ({self.n_ch},)")
            # first aiding value of a channel: no increment yet
            if not self.have_prev.all():
                first = ~self.have_prev
                self.aid_prev[first] = aid_now[first]
                self.have_prev[:] = True
            bad = mask & ~np.isfinite(aid_now)
            if bad.any():
                raise FilterError(f"InnerLoop.apply: non-finite aiding Doppler on channels {np.flatnonzero(bad)}")
        _feedback_kernel(x, bank.active, nco.code_phase, nco.code_rate, nco.carr_phase, nco.carr_freq,
                         aid_now, self.aid_prev, mask, self.was_aided, self.prm, self.dx)
        if aid_doppler_hz is not None:
            self.aid_prev[:] = aid_now
        if hasattr(bank, "note_correction"):
            bank.note_correction(self.dx)
        return self.dx
