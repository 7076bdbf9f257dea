"""Data wipe-off stage of the ultra-tight engine: the sign of each channel's data bit for the
code period it integrates next.

The bits come from a *bit source* with ``bits`` (n_ch, n_bits) ±1 and ``t0_ms`` (n_ch,), the
transmit-time code-period count of each row's first bit (today the assisted LNAV bits of
:class:`ultratight.receiver.startup.BitWipeoff`). The stage keeps, per channel, the transmit-time
count of the code period about to be integrated (``ms``), starting from the first full period
(:func:`ultratight.receiver.startup.first_period_ms`), and advances it by one per epoch.
"""

import numpy as np
from numba import njit


@njit(cache=True)
def wipe_one(c, bits, t0_ms, ms, out, per_bit):
    """:func:`wipe_bits` for channel ``c`` alone."""
    nb = bits.shape[1]
    k = (ms[c] - t0_ms[c]) // per_bit
    if k < 0:
        k = 0
    if k > nb - 1:
        k = nb - 1
    out[c] = bits[c, k]
    ms[c] += 1


@njit(cache=True)
def wipe_bits(bits, t0_ms, ms, out, per_bit):
    """Data bit of the code period starting at transmit code-period count ``ms`` (per channel;
    ``per_bit`` code periods per bit, :attr:`ultratight.signals.signal.SignalDescription.codes_per_bit`)
    into ``out``; advances ``ms`` by one period."""
    for c in range(bits.shape[0]):
        wipe_one(c, bits, t0_ms, ms, out, per_bit)


class DataWipeoff:
    """Per-channel data-bit signs, epoch by epoch (module docstring).

    ``source``: the bit source (``bits``, ``t0_ms``, ``mode``); ``first_ms``: (n_ch,) transmit-time
    count of each channel's first integrated code period; ``codes_per_bit``: the signal's.
    ``D`` (n_ch,) holds the signs of the last :meth:`step`.
    """

    def __init__(self, source, first_ms, codes_per_bit):
        self.source = source
        self.mode = source.mode
        self.bits = source.bits
        self.t0_ms = source.t0_ms
        self.ms = np.asarray(first_ms, dtype=np.int64).copy()
        self.per_bit = int(codes_per_bit)
        self.D = np.ones(self.ms.shape[0])

    def step(self):
        """Signs of this epoch's code period (n_ch,); advances to the next period."""
        wipe_bits(self.bits, self.t0_ms, self.ms, self.D, self.per_bit)
        return self.D
