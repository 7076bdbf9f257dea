"""Per-channel LNAV decoding: tracked bits -> TOW (transmit-time mapping) and ephemeris.

Wraps :class:`ultratight.signals.lnav.LnavDecoder`.  The tracking kernel emits one soft bit
(sum of 20 prompt I values) per bit, tagged with the epoch index (C/A period count of the
channel) of the bit's first period.  When the decoder finds a subframe, its HOW gives the GPS
TOW (satellite clock) of the subframe's first bit, which fixes the satellite transmit time of
every code period of the channel: ``t_tx(epoch) = tow_sf + (epoch - epoch_sf) * T_CA`` (the C/A
period is exactly 1 ms of satellite time).
"""

import numpy as np

from ultratight.constants import T_CA
from ultratight.signals.lnav import LnavDecoder


class ChannelNav:
    """Nav-data state of one tracking channel (reset when the channel is re-acquired)."""

    def __init__(self, prn, ref_week=None):
        self.prn = int(prn)
        self.ref_week = ref_week
        self.reset()

    def reset(self):
        self.decoder = LnavDecoder(prn=self.prn, ref_week=self.ref_week)
        self.bit_epochs = []          # epoch of the first period of every bit fed (stream order)
        self.epoch_ref = None         # epoch whose period starts at satellite time tow_ref
        self.tow_ref = None
        self.ephemeris = None         # decoder's ephemeris with tx_tow = start of its subframe 1
        self._decoded = None
        self.n_bits = 0
        self.n_subframes = 0
        self.first_tow_epoch = None   # epoch at which the TOW became known (for reporting)
        self.eph_epoch = None         # epoch at which subframes 1-3 became complete
        self.parity_errors = 0
        self._offset = 0              # stream index of bit_epochs[0]

    def feed(self, bits_soft, bit_start_epochs, now_epoch):
        """Feed soft bits (float, sign = bit) with their start epochs; returns new subframes."""
        if len(bits_soft) == 0:
            return []
        e = np.asarray(bit_start_epochs, dtype=np.int64)
        if self.bit_epochs and e[0] != self.bit_epochs[-1] + 20:
            # a gap in the bit stream: the decoder's stream indices would be wrong -> restart
            eph = self.ephemeris
            self.reset()
            self.ephemeris = eph
        self.bit_epochs.extend(int(v) for v in e)
        self.n_bits += len(e)
        subframes = self.decoder.feed(np.asarray(bits_soft, dtype=float))
        for sf in subframes:
            self.n_subframes += 1
            self.parity_errors += len(sf.bad_words)
            if sf.bad_words and (1 in sf.bad_words or 2 in sf.bad_words):
                continue
            ep = self.bit_epochs[sf.start_bit - self._offset]
            if self.epoch_ref is None:
                self.first_tow_epoch = now_epoch
            self.epoch_ref = ep
            self.tow_ref = float(sf.tow_s)
        if self.decoder.ephemeris is not None and self.decoder.ephemeris is not self._decoded:
            if self.eph_epoch is None:
                self.eph_epoch = now_epoch
            self._decoded = self.decoder.ephemeris
            self.ephemeris = self._decoded.copy(tx_tow=self.decoder.ephemeris_tx_tow)
        # keep memory bounded: epochs older than two subframes are not needed any more
        if len(self.bit_epochs) > 4000:
            drop = len(self.bit_epochs) - 2000
            self._offset += drop      # the decoder reports absolute stream indices
            del self.bit_epochs[:drop]
        return subframes

    @property
    def has_time(self):
        return self.epoch_ref is not None

    def tx_time(self, epoch):
        """Satellite-clock transmit time (s of week) of the start of C/A period ``epoch``."""
        return self.tow_ref + (np.asarray(epoch, dtype=float) - self.epoch_ref) * T_CA
