"""Per-channel navigation decoding: tracked bits -> TOW (transmit-time mapping) and ephemeris.

The decoder of a signal is found by the name in its description
(:attr:`ultratight.signals.signal.SignalDescription.navigation`) with :func:`channel_nav`; GPS
LNAV (IS-GPS-200 section 20.3) is the one decoder now, :class:`ChannelNav`, which wraps
:class:`ultratight.signals.lnav.LnavDecoder`.  The tracking kernel emits one soft bit (sum of the
prompt I values of the ``codes_per_bit`` code periods of a bit, 20 for C/A) per bit, tagged with
the epoch index (code-period count of the channel) of the bit's first period.  When the decoder
finds a subframe, its HOW gives the GPS TOW (satellite clock) of the subframe's first bit, which
fixes the satellite transmit time of every code period of the channel:
``t_tx(epoch) = tow_sf + (epoch - epoch_sf) * T`` (T the code period, exactly 1 ms of satellite
time for C/A).
"""

import numpy as np

from ultratight.errors import ConfigError
from ultratight.signals.lnav import LnavDecoder
from ultratight.signals.signal import GPS_L1CA


class ChannelNav:
    """LNAV state of one tracking channel (reset when the channel is re-acquired)."""

    def __init__(self, prn, ref_week=None, signal=GPS_L1CA):
        self.prn = int(prn)
        self.ref_week = ref_week
        self.signal = signal
        self.log = None               # a list to keep every (soft bits, start epochs) fed, or None
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
        if self.log is not None:
            self.log.append((np.array(bits_soft, dtype=float), e.copy()))
        if self.bit_epochs and e[0] != self.bit_epochs[-1] + self.signal.codes_per_bit:
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
        """Satellite-clock transmit time (s of week) of the start of code period ``epoch``."""
        return self.tow_ref + (np.asarray(epoch, dtype=float) - self.epoch_ref) * self.signal.code_period_s


NAV_DECODERS = {"LNAV": ChannelNav}
"""Channel navigation decoders by the ``navigation`` name of a signal description."""


def channel_nav(signal, prn, ref_week=None):
    """The navigation-decoding state of one channel of ``signal`` (by ``signal.navigation``)."""
    try:
        cls = NAV_DECODERS[signal.navigation]
    except KeyError:
        raise ConfigError(f"no navigation decoder for {signal.name} (navigation {signal.navigation!r}; "
                          f"known: {', '.join(NAV_DECODERS)})") from None
    return cls(prn, ref_week=ref_week, signal=signal)
