"""Scalar tracking: FLL-assisted Costas PLL, carrier-aided DLL, C/N0, lock indicators, bit sync.

This module holds the tracking bank, :class:`ScalarTracker` (NCOs, loop state, one compiled call
per IF block), its state :class:`TrackingState`, and the numpy C/N0 estimators :func:`cn0_power`
and :func:`cn0_m2m4`. The bank is built from:

* :mod:`ultratight.receiver.dsp.tracking_config`: the loop parameters (:class:`TrackingConfig`)
  and the profiles by receiver dynamics (:data:`DYNAMICS_PROFILES`);
* :mod:`ultratight.receiver.dsp.tracking_layout`: channel modes, the columns of the loop state,
  the parameter vector and the epoch records (``R_*``, ``RI_*``, flags ``FL_*``);
* :mod:`ultratight.receiver.dsp.tracking_kernels`: discriminators, loop filters (the loop
  equations) and the one-pass prompt / early-minus-late integration;
* :mod:`ultratight.receiver.dsp.tracking_block`: the per-epoch logic (modes, C/N0, phase-lock
  indicator, loss of lock, bit sync, coherent sums) and the fused block kernel.

The signal is a :class:`ultratight.signals.signal.SignalDescription` (default GPS L1 C/A): its
code (length ``L`` chips at ``f_chip``), carrier ``f_carrier`` and code periods per data bit reach
the kernel as parameters (``prm[P_CODE_LEN]``, ``prm[P_CHIP_RATE]``, ``prm[P_CARRIER]``, the width
of the bit-sync histogram); an epoch is one code period (1 ms for C/A).

All per-epoch work runs in one numba call per IF block
(:func:`ultratight.receiver.dsp.tracking_block.track_block`): for every active channel it
integrates code periods, runs the discriminators and loop filters, updates the NCOs, and writes
one record per epoch.  Python only handles blocks (≈10 Hz).
"""

import math
from dataclasses import asdict

import numpy as np

from ultratight.errors import ConfigError
from ultratight.receiver.dsp.correlator import CorrelatorBank
from ultratight.receiver.dsp.tracking_block import CN0_FLOOR_LIN, track_block, track_block_parallel
from ultratight.receiver.dsp.tracking_config import TrackingConfig
from ultratight.receiver.dsp.tracking_kernels import half_chip_tables
from ultratight.receiver.dsp.tracking_layout import (
    F_CN0_DB, F_DOPP, F_PLL_X, F_PLL_Y, MODE_OFF, MODE_PULL, N_RF, N_RI, N_SF, N_SI, P_DLL_Z, P_DOPP, P_PLL_X,
    P_PLL_Y, S_BIT_PHASE, S_CN0_VALID, S_MODE, STATE_NAMES)
from ultratight.signals.signal import GPS_L1CA


# ------------------------------------------------------------------------------ estimators (numpy)
def cn0_power(i_p, q_p, t_int):
    """C/N0 (dB-Hz) from prompt outputs with unit noise per arm: (mean P - 2)/(2T)."""
    p = np.mean(np.asarray(i_p) ** 2 + np.asarray(q_p) ** 2)
    lin = max((p - 2.0) / (2.0 * t_int), CN0_FLOOR_LIN)
    return 10.0 * np.log10(lin)


def cn0_m2m4(i_p, q_p, t_int):
    """Moments (M2M4) C/N0 estimator (dB-Hz), needs no noise reference (complex signal, real noise arms).

    M2 = E|z|^2 = S + N, M4 = E|z|^4 = S^2 + 4 S N + 2 N^2 (N = total noise power of both arms)
    -> S = sqrt(2 M2^2 - M4), N = M2 - S; C/N0 = S/(N T) with N = 2 (per-arm unit variance) ...
    normalised form: C/N0 = (S/N)/T."""
    z2 = np.asarray(i_p) ** 2 + np.asarray(q_p) ** 2
    m2 = np.mean(z2)
    m4 = np.mean(z2 * z2)
    s = math.sqrt(max(2.0 * m2 * m2 - m4, 0.0))
    n = m2 - s
    if s <= 0.0 or n <= 0.0:
        return float("nan")
    return 10.0 * math.log10(s / n / t_int)


# ------------------------------------------------------------------------------ channel bank state
class TrackingState:
    """Loop state of ``n_ch`` channels (arrays for the numba kernel) plus record buffers.

    ``sf`` (n_ch, N_SF) float state (columns ``F_*``, names :data:`STATE_NAMES`), ``si`` (n_ch, N_SI)
    int state (``S_*``), ``hist`` (n_ch, codes per bit) bit-edge histogram, ``prm`` the kernel
    parameters (:meth:`TrackingConfig.params` with the signal's code length, chip rate and carrier),
    ``rec_f`` / ``rec_i`` / ``n_rec`` the records of the last block (columns ``R_*`` / ``RI_*``)."""

    def __init__(self, n_ch, config=None, max_rows=256, signal=GPS_L1CA):
        self.config = config or TrackingConfig()
        self.config.validate()
        self.prm = self.config.params(signal)
        self.sf = np.zeros((n_ch, N_SF))
        self.si = np.zeros((n_ch, N_SI), dtype=np.int64)
        self.hist = np.zeros((n_ch, int(signal.codes_per_bit)), dtype=np.int64)
        # bit-energy sync: running window sums, energies, epochs seen (see tracking_block._bit_sync_energy)
        self.bse = np.zeros((n_ch, 2 * int(signal.codes_per_bit) + 1))
        self.rec_f = np.zeros((n_ch, max_rows, N_RF))
        self.rec_i = np.zeros((n_ch, max_rows, N_RI), dtype=np.int64)
        self.n_rec = np.zeros(n_ch, dtype=np.int64)

    def reset_channel(self, ch, doppler_hz, cn0_dbhz=None, rate_hz_s=None):
        """(Re)start a channel in pull-in mode with the acquisition Doppler (and C/N0 when known);
        ``rate_hz_s`` (a Doppler-rate search) presets the third-order loop's rate integrator."""
        self.sf[ch] = 0.0
        self.si[ch] = 0
        self.hist[ch] = 0
        self.bse[ch] = 0.0
        self.sf[ch, F_DOPP] = doppler_hz
        self.sf[ch, F_PLL_X] = doppler_hz
        if rate_hz_s is not None and np.isfinite(rate_hz_s):
            self.sf[ch, F_PLL_Y] = rate_hz_s
        if cn0_dbhz is not None and np.isfinite(cn0_dbhz):
            self.sf[ch, F_CN0_DB] = cn0_dbhz
            self.si[ch, S_CN0_VALID] = 1
        self.si[ch, S_MODE] = MODE_PULL
        self.si[ch, S_BIT_PHASE] = -1

    def mode(self, ch):
        return int(self.si[ch, S_MODE])

    def cn0_dbhz(self, ch):
        return float(self.sf[ch, F_CN0_DB]) if self.si[ch, S_CN0_VALID] else float("nan")


class ScalarTracker:
    """The scalar tracking bank: code/carrier NCOs + FLL-assisted PLL and DLL per channel.

    The vocabulary of the ultra-tight prefilter banks (``fusion.channel.prefilter.PrefilterBank``,
    ``fusion.channel.pbkf.PbKfBank``): :meth:`reset` (channels, optional initial state), :meth:`describe`
    (the loop parameters), :data:`STATE_NAMES` and the indices ``P_DOPP``, ``P_PLL_X``,
    ``P_PLL_Y``, ``P_DLL_Z`` of the recorded loop state; :meth:`run` is its ``step`` over a block.
    Unlike the prefilter banks, whose ``step`` takes correlator outputs, the scalar loops take the
    IF samples: correlation and loop update are one fused numba kernel per block
    (:func:`ultratight.receiver.dsp.tracking_block.track_block`), which keeps the 1 ms loop closure inside compiled code (speed).

    ``signal``: the :class:`ultratight.signals.signal.SignalDescription` tracked (code, chip rate,
    carrier, codes per data bit; default GPS L1 C/A). ``channels`` start with :meth:`start_channel`
    (from acquisition); each :meth:`run` tracks every active channel through the buffer and returns
    the new epoch records ``(rec_f (n_ch, rows, N_RF), rec_i (n_ch, rows, N_RI), n_rec (n_ch,))``
    (copies).
    """

    def __init__(self, n_ch, fs_hz, if_hz, is_complex, config=None, max_rows=256, parallel=False,
                 signal=GPS_L1CA):
        self.parallel = bool(parallel) and n_ch > 1
        self.config = config or TrackingConfig()
        self.signal = signal
        # the channels' NCOs and code tables: a correlator bank of the signal (its kernels' layout);
        # the fused tracking kernel integrates, the bank's own step is not used
        self.nco = CorrelatorBank([signal.prns[0]] * n_ch, fs_hz, if_hz, is_complex,
                                  spacing_chips=self.config.spacing_chips, signal=signal)
        self.state = TrackingState(n_ch, self.config, max_rows, signal)
        self.fs_hz = float(fs_hz)
        self.if_hz = float(if_hz)
        self.is_complex = bool(is_complex)
        self.n_ch = n_ch
        nh = 2 * (signal.code_length + 2 * self.nco.pad)
        self.half_tab = np.zeros((n_ch, 2 * nh), dtype=np.float32)

    @property
    def active(self):
        return self.nco.active

    def describe(self):
        """The loop parameters (TrackingConfig fields) and the signal tracked."""
        return {**asdict(self.config), "signal": self.signal.name, "channels": self.n_ch,
                "fs_hz": self.fs_hz, "if_hz": self.if_hz}

    STATE_NAMES = STATE_NAMES
    P_DOPP, P_PLL_X, P_PLL_Y, P_DLL_Z = P_DOPP, P_PLL_X, P_PLL_Y, P_DLL_Z

    def _channels(self, channels):
        ch = np.atleast_1d(np.asarray(channels, dtype=np.int64))
        if ch.size and (ch.min() < 0 or ch.max() >= self.n_ch):
            raise ConfigError(f"scalar tracking: channel index out of range 0..{self.n_ch - 1}: {ch}")
        return ch

    def reset(self, channels, x0=None, P0=None):
        """Restart ``channels`` in pull-in mode from their current NCO Doppler, or from ``x0``
        (per channel: Doppler in Hz); ``P0`` is accepted for the bank protocol (the scalar loops
        carry no covariance)."""
        for k, ch in enumerate(self._channels(channels)):
            d = float(self.nco.carr_freq[ch] - self.if_hz) if x0 is None else float(np.atleast_1d(x0)[k])
            self.state.reset_channel(int(ch), d)

    def correct(self, dx):
        """Apply external corrections ``dx`` (n_ch, 2): [Doppler (Hz), code phase (chips)] per channel
        to the NCOs and the carrier loop's frequency states (an aided scalar loop)."""
        dx = np.asarray(dx, dtype=float).reshape(self.n_ch, 2)
        if not np.all(np.isfinite(dx)):
            raise ConfigError("scalar tracking: corrections must be finite")
        self.nco.carr_freq += dx[:, 0]
        self.state.sf[:, F_DOPP] += dx[:, 0]
        self.state.sf[:, F_PLL_X] += dx[:, 0]
        self.nco.code_phase += dx[:, 1]

    def start_channel(self, ch, prn, code_phase_chips, doppler_hz, sample_index, cn0_dbhz=None, rate_hz_s=None):
        """Start (or restart) channel ``ch`` from an acquisition result valid at ``sample_index``
        (``rate_hz_s``: the Doppler rate there, when searched)."""
        self.nco.init_channel(ch, int(prn), code_phase_chips, doppler_hz, int(sample_index))
        self.half_tab[ch] = half_chip_tables(prn, self.nco.pad, self.signal)
        self.state.reset_channel(ch, float(doppler_hz), cn0_dbhz, rate_hz_s)

    def stop_channel(self, ch):
        self.nco.active[ch] = False
        self.state.si[ch, S_MODE] = MODE_OFF

    def next_needed_sample(self):
        """Smallest sample_ptr of the active channels (None if none is active)."""
        if not self.nco.active.any():
            return None
        return int(self.nco.sample_ptr[self.nco.active].min())

    def run(self, buf, buf_start, sigma_arm, stop_sample=None):
        b = self.nco
        st = self.state
        if self.is_complex:
            raw = np.ascontiguousarray(buf, dtype=np.complex64).view(np.float32)
        else:
            raw = np.ascontiguousarray(buf, dtype=np.float32)
        n_buf = int(np.asarray(buf).shape[0])
        stop = np.int64(buf_start + n_buf if stop_sample is None else stop_sample)
        sig = np.broadcast_to(np.asarray(sigma_arm, dtype=float), (self.n_ch,)).copy()
        st.n_rec[:] = 0
        fn = track_block_parallel if self.parallel else track_block
        fn(raw, self.is_complex, np.int64(buf_start), np.int64(n_buf), stop, b.code_ext,
           b.pad, b.active, b.sample_ptr, b.code_phase, b.code_rate, b.carr_phase, b.carr_freq,
           self.fs_hz, self.if_hz, b.tap_offsets_chips, sig, st.sf, st.si, st.hist, st.prm,
           st.rec_f, st.rec_i, st.n_rec, self.half_tab, st.bse)
        m = int(st.n_rec.max()) if st.n_rec.size else 0
        return st.rec_f[:, :m].copy(), st.rec_i[:, :m].copy(), st.n_rec.copy()

    step = run

    def track_at(self, stream, start, count, head, min_samples, stop_sample):
        """Track through ``count`` samples of ``stream`` (:class:`ultratight.receiver.dsp.blockstream.BlockStream`)
        read at ``start``, normalised by the noise estimate of their first ``head`` samples (the
        scalar receiver: channels stop, re-acquire and restart anywhere). Returns the records as
        :meth:`run`, or None when fewer than ``min_samples`` samples are left."""
        buf, sigma_arm = stream.read_at(start, count, head)
        if buf.shape[0] < min_samples:
            return None
        return self.run(buf, start, sigma_arm, stop_sample=stop_sample)

    def track_aligned(self, stream, n_total):
        """Track through the aligned blocks ``[k L, (k + 1) L)`` of ``stream`` up to sample ``n_total``,
        each normalised by its own noise estimate; yields the records of every block (as :meth:`run`).
        The samples a channel still needs before a block stay in the stream's buffer."""
        blk = stream.block_len
        start = 0
        while start < n_total:
            lo = self.next_needed_sample()
            if lo is None:
                return
            lo = min(lo, start)
            stream.ensure(start + blk, keep_from=lo)
            buf, lo = stream.view(lo)
            if buf.shape[0] == 0:
                return
            sig = float(stream.sigma_at(start))
            yield self.run(buf, lo, sig, stop_sample=min(start + blk, n_total))
            start += blk
