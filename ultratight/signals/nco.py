"""Numerically controlled oscillators of a bank of tracking channels: the interface between the
tracking loops that command them and the correlators (or a correlator-level simulator) that
follow them.

Per channel (float64 arrays, moved in place by the loop that owns the command):

* ``code_phase`` — chips of the prompt replica at the start of the next integration;
* ``code_rate`` — chips per second;
* ``carr_phase`` — cycles in [0, 1) at the start of the next integration;
* ``carr_freq`` — Hz, intermediate frequency plus Doppler (``if_hz`` + Doppler).

:class:`ultratight.receiver.dsp.correlator.CorrelatorBank` owns one (``bank.nco``) and
:class:`ultratight.fusion.channel.innerloop.InnerLoop` commands it; the correlator-level simulator's NCO
is one too.
"""

import numpy as np


class NcoBank:
    """Code and carrier NCO state of ``n_ch`` channels at ``if_hz`` (see module docstring)."""

    def __init__(self, n_ch, if_hz=0.0, chip_rate_hz=0.0):
        n_ch = int(n_ch)
        self.if_hz = float(if_hz)
        self.code_phase = np.zeros(n_ch)
        self.code_rate = np.full(n_ch, float(chip_rate_hz))
        self.carr_phase = np.zeros(n_ch)
        self.carr_freq = np.full(n_ch, self.if_hz)

    @property
    def n_ch(self):
        return self.code_phase.shape[0]

    def grow(self, k, chip_rate_hz):
        """Append ``k`` channels (code at ``chip_rate_hz``, carrier at the IF)."""
        self.code_phase = np.concatenate([self.code_phase, np.zeros(k)])
        self.code_rate = np.concatenate([self.code_rate, np.full(k, float(chip_rate_hz))])
        self.carr_phase = np.concatenate([self.carr_phase, np.zeros(k)])
        self.carr_freq = np.concatenate([self.carr_freq, np.full(k, self.if_hz)])
