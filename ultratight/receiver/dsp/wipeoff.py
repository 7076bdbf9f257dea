"""Data wipe-off stage of the ultra-tight engine: the sign of each channel's data bit for the
code period it integrates next.

The bits come from a *bit source* (:mod:`ultratight.receiver.deep.bitsources`) with ``bits``
(n_ch, n_bits) int8 — +1 / -1 a known bit, 0 an unknown one — ``t0_ms`` (n_ch,), the
transmit-time code-period count of each row's first bit, and ``code`` (n_ch,), the channel's
strategy (``BIT_ASSISTED``, ``BIT_DECODED``, ``BIT_FILE``, ``BIT_NONE``). The stage keeps, per
channel, the transmit-time count of the code period about to be integrated (``ms``), starting from
the first full period (:func:`ultratight.receiver.deep.startup.first_period_ms`), and advances it by one
per epoch. Bit boundaries are therefore known (transmit time from the hot start): no bit
synchronisation search is needed.

Unknown bits (``blind``): a decision-directed sign per bit. Each epoch the prompt is projected on the
carrier phase the tracking bank predicts for the middle of the interval,
``p = I_P cos(dphi + df T/2) + Q_P sin(dphi + df T/2)`` (prior state ``x`` of the bank, prefilter
layout), the projections are summed over the current bit so far (this epoch included), and the bit
is the sign of that sum. The decision gets better as the bit goes on (after n epochs its error
probability is Q(sqrt(2 n C/N0 T)) for a phase-locked channel); like a Costas loop the channel is
insensitive to a 180 degree ambiguity of its phase.

Polarity of known bits on such channels: a channel that ran blind (or started on a two-quadrant
phase estimate) may track the carrier half a cycle off; the first known bits would then look like a
180 degree phase jump. Channels whose row holds unknown bits (``adapt``) therefore keep a polarity
``pol`` (+1 / -1; the wiped sign is ``pol * bit``): over the known bits the sum ``S = sum bit * p``
and ``Q = sum p^2`` are kept, and ``pol`` flips when ``pol * S < -POL_KSIG sqrt(Q)`` after at least
``POL_MIN_EPOCHS`` epochs (a self-normalising test: noise bursts scale S and sqrt(Q) alike); the sums
restart every ``POL_WINDOW`` epochs and after a flip. Channels with every bit known (assisted bits,
a complete bit file) use the bits as they are, exactly as before this stage knew unknown bits.

Per channel per epoch the stage records where the bit came from (``rec_src``: the channel's
``code``, or ``BIT_BLIND`` for a decision), and on channels with unknown bits the projection sum of
every bit (``soft``, per bit column: the soft bit of a decoding pass).
"""

import math

import numpy as np
from numba import njit

BIT_NONE = 0        # no wipe-off (all +1: the ephemeris could not be encoded)
BIT_ASSISTED = 1    # re-encoded from the ephemeris (signals.lnav.nav_bits)
BIT_DECODED = 2     # from a parity-checked word of the scalar pass over the same file
BIT_FILE = 3        # from an external bit file
BIT_BLIND = 4       # decision-directed sign (no bit known)
BIT_SOURCE_NAMES = {BIT_NONE: "none", BIT_ASSISTED: "assisted", BIT_DECODED: "decoded", BIT_FILE: "file",
                    BIT_BLIND: "blind"}

POL_MIN_EPOCHS = 20     # known-bit epochs before the polarity test may flip
POL_WINDOW = 1000       # epochs after which the polarity sums restart
POL_KSIG = 4.0          # flip threshold (standard deviations)


@njit(cache=True)
def wipe_channel(c, k_ep, bits, t0_ms, ms, out, per_bit, code, adapt, kb, acc, pol, ps, pss, pn, src, rec_src,
                 soft, z, x, half_t):
    """Channel ``c``'s data-bit sign of epoch ``k_ep`` into ``out[c]`` (module docstring); ``z``: the
    correlator outputs (``[I_P, I_E, I_L, Q_P, Q_E, Q_L]`` per row), ``x``: the tracking bank's prior
    state (prefilter layout), ``half_t``: half the code period. Touches only row ``c``."""
    nb = bits.shape[1]
    k = (ms[c] - t0_ms[c]) // per_bit
    if k < 0:
        k = 0
    if k > nb - 1:
        k = nb - 1
    b = bits[c, k]
    ms[c] += 1
    if not adapt[c]:
        out[c] = b
        src[c] = code[c]
    else:
        ph = x[c, 2] + x[c, 3] * half_t
        p = z[c, 0] * math.cos(ph) + z[c, 3] * math.sin(ph)
        if k != kb[c]:
            kb[c] = k
            acc[c] = 0.0
        acc[c] += p
        soft[c, k] = acc[c]
        if b != 0:
            ps[c] += b * p
            pss[c] += p * p
            pn[c] += 1
            if pn[c] >= POL_MIN_EPOCHS and pol[c] * ps[c] < -POL_KSIG * math.sqrt(pss[c]):
                pol[c] = -pol[c]
                ps[c] = 0.0
                pss[c] = 0.0
                pn[c] = 0
            elif pn[c] >= POL_WINDOW:
                ps[c] = 0.0
                pss[c] = 0.0
                pn[c] = 0
            out[c] = b * pol[c]
            src[c] = code[c]
        else:
            out[c] = 1.0 if acc[c] >= 0.0 else -1.0
            src[c] = BIT_BLIND
    if k_ep < rec_src.shape[0]:
        rec_src[k_ep, c] = src[c]


@njit(cache=True)
def wipe_all(k_ep, bits, t0_ms, ms, out, per_bit, code, adapt, kb, acc, pol, ps, pss, pn, src, rec_src, soft, z,
             x, half_t):
    """:func:`wipe_channel` for every channel."""
    for c in range(bits.shape[0]):
        wipe_channel(c, k_ep, bits, t0_ms, ms, out, per_bit, code, adapt, kb, acc, pol, ps, pss, pn, src, rec_src,
                     soft, z, x, half_t)


class DataWipeoff:
    """Per-channel data-bit signs, epoch by epoch (module docstring).

    ``source``: the bit source (``bits``, ``t0_ms``, ``mode``, and ``code`` (n_ch,) — default
    ``BIT_ASSISTED``, or ``BIT_NONE`` for mode "none"); ``first_ms``: (n_ch,) transmit-time count of
    each channel's first integrated code period; ``codes_per_bit``: the signal's; ``n_ep_max``:
    rows of the per-epoch source record ``rec_src``; ``half_t``: half the code period (s).
    ``D`` (n_ch,) holds the signs of the last :meth:`step`, ``src`` their sources.
    """

    def __init__(self, source, first_ms, codes_per_bit, n_ep_max=0, half_t=0.5e-3):
        self.source = source
        self.mode = source.mode
        self.bits = np.ascontiguousarray(source.bits, dtype=np.int8)
        self.t0_ms = source.t0_ms
        n = self.bits.shape[0]
        code = getattr(source, "code", None)
        if code is None:
            code = np.full(n, BIT_NONE if source.mode == "none" else BIT_ASSISTED, dtype=np.int8)
        self.code = np.asarray(code, dtype=np.int8)
        self.adapt = np.array([bool(np.any(self.bits[c] == 0)) for c in range(n)], dtype=np.bool_)
        self.ms = np.asarray(first_ms, dtype=np.int64).copy()
        self.per_bit = int(codes_per_bit)
        self.half_t = float(half_t)
        self.D = np.ones(n)
        self.kb = np.full(n, -1, dtype=np.int64)
        self.acc = np.zeros(n)
        self.pol = np.ones(n)
        self.ps = np.zeros(n)
        self.pss = np.zeros(n)
        self.pn = np.zeros(n, dtype=np.int64)
        self.src = self.code.copy()
        self.rec_src = np.zeros((int(n_ep_max), n), dtype=np.int8)
        self.soft = np.zeros(self.bits.shape)      # channels with unknown bits: the projection sum of each bit

    @property
    def adaptive(self):
        """Any channel with unknown bits (decisions, polarity tracking)."""
        return bool(self.adapt.any())

    def view_args(self):
        """The stage's arrays in the order of the compiled functions (after ``c, k_ep``), up to ``z``."""
        return (self.bits, self.t0_ms, self.ms, self.D, self.per_bit, self.code, self.adapt, self.kb, self.acc,
                self.pol, self.ps, self.pss, self.pn, self.src, self.rec_src, self.soft)

    def step(self, z=None, x=None, k_ep=0):
        """Signs of this epoch's code period (n_ch,); advances to the next period. ``z``/``x`` (the
        correlator outputs and the bank's prior state) are needed when a channel has unknown bits."""
        if z is None:
            if self.adaptive:
                raise ValueError("data wipe-off: unknown bits need the correlator outputs and the bank state")
            z = np.zeros((self.bits.shape[0], 6))
            x = np.zeros((self.bits.shape[0], 5))
        wipe_all(k_ep, *self.view_args(), z, x, self.half_t)
        return self.D

    def counts(self, n_ep):
        """Per channel: epochs by bit source over the first ``n_ep`` epochs (dict name -> list)."""
        r = self.rec_src[:int(n_ep)]
        return {name: np.count_nonzero(r == k, axis=0).tolist() for k, name in BIT_SOURCE_NAMES.items()
                if np.any(r == k)}
