"""Observables at a common receive time from the tracking records.

Every tracking epoch record holds the NCO state at the first sample of a C/A period
(``sample_index``, ``code_phase_chips`` there, ``code_rate_cps`` and ``doppler_hz`` applied
over the period, ``carr_acc_cycles`` = accumulated Doppler phase at its start).  Between two
epochs the NCOs are linear, so at any receive sample ``s`` inside period ``e``:

* replica code phase  ``p(s) = code_phase + (s - sample_index) code_rate / fs`` chips into the
  period, hence the satellite-clock transmit time ``t_tx(s) = t_tx(e) + p(s)/f_chip`` (the
  signal's chip rate, :class:`ultratight.signals.signal.SignalDescription`) with
  ``t_tx(e)`` from the decoded TOW (:class:`ultratight.receiver.scalar.navdecode.ChannelNav`);
* accumulated carrier (Doppler) phase ``acc(s) = carr_acc + (s - sample_index) doppler / fs``.

Observables at receive sample ``s`` (receiver-clock time ``t_rx``):

* pseudorange ``c (t_rx - t_tx(s))`` (m);
* Doppler ``(acc(s + h) - acc(s - h)) / (2 h / fs)`` (Hz): the mean NCO frequency over a window
  centred on ``s`` (removes the loop's frequency jitter; centring removes the lag under
  acceleration);
* carrier phase ``-acc(s)`` (cycles; RINEX sign: changes like the range);
* C/N0 (dB-Hz) and lock flags of the epoch.
"""

import numpy as np

from ultratight.constants import C
from ultratight.receiver.dsp.tracking_layout import (R_CODE_PHASE, R_CODE_RATE, R_CARR_ACC, R_DOPP, R_CN0,
                                                 RI_PTR, RI_N, RI_EPOCH, RI_FLAGS, FL_PLL_LOCK)
from ultratight.signals.signal import GPS_L1CA

HIST_KEEP_S = 1.0      # seconds of epoch records kept per channel


class ChannelHistory:
    """Rolling window of one channel's epoch records (append blocks, look up by sample)."""

    FIELDS = ("ptr", "n", "epoch", "flags", "code_phase", "code_rate", "carr_acc", "dopp", "cn0")

    def __init__(self, fs_hz):
        self.fs = float(fs_hz)
        self.clear()

    def clear(self):
        self.ptr = np.zeros(0, np.int64)
        self.n = np.zeros(0, np.int64)
        self.epoch = np.zeros(0, np.int64)
        self.flags = np.zeros(0, np.int64)
        self.code_phase = np.zeros(0)
        self.code_rate = np.zeros(0)
        self.carr_acc = np.zeros(0)
        self.dopp = np.zeros(0)
        self.cn0 = np.zeros(0)

    def append(self, rf, ri):
        """Append records rf (rows, N_RF), ri (rows, N_RI) of this channel."""
        if rf.shape[0] == 0:
            return
        keep_from = 0
        if self.ptr.size:
            # drop old rows beyond the window
            cut = self.ptr[-1] - int(HIST_KEEP_S * self.fs)
            keep_from = int(np.searchsorted(self.ptr, cut))
        self.ptr = np.concatenate((self.ptr[keep_from:], ri[:, RI_PTR]))
        self.n = np.concatenate((self.n[keep_from:], ri[:, RI_N]))
        self.epoch = np.concatenate((self.epoch[keep_from:], ri[:, RI_EPOCH]))
        self.flags = np.concatenate((self.flags[keep_from:], ri[:, RI_FLAGS]))
        self.code_phase = np.concatenate((self.code_phase[keep_from:], rf[:, R_CODE_PHASE]))
        self.code_rate = np.concatenate((self.code_rate[keep_from:], rf[:, R_CODE_RATE]))
        self.carr_acc = np.concatenate((self.carr_acc[keep_from:], rf[:, R_CARR_ACC]))
        self.dopp = np.concatenate((self.dopp[keep_from:], rf[:, R_DOPP]))
        self.cn0 = np.concatenate((self.cn0[keep_from:], rf[:, R_CN0]))

    @property
    def end_sample(self):
        return int(self.ptr[-1] + self.n[-1]) if self.ptr.size else -1

    def locate(self, s):
        """Row index of the period containing sample ``s`` (or -1)."""
        if not self.ptr.size:
            return -1
        i = int(np.searchsorted(self.ptr, s, side="right")) - 1
        if i < 0 or s >= self.ptr[i] + self.n[i]:
            return -1
        return i

    def code_chips(self, i, s):
        return self.code_phase[i] + (s - self.ptr[i]) * self.code_rate[i] / self.fs

    def carr(self, i, s):
        return self.carr_acc[i] + (s - self.ptr[i]) * self.dopp[i] / self.fs


def observe(hist, nav, s_obs, h_samples, signal=GPS_L1CA):
    """Raw observables of one channel of ``signal`` at receive sample ``s_obs`` or None if not available.

    Returns dict(t_tx_sv (s of week, satellite clock), doppler_hz, carrier_cycles, cn0_dbhz,
    pll_lock, epoch)."""
    i0 = hist.locate(s_obs)
    im = hist.locate(s_obs - h_samples)
    ip = hist.locate(s_obs + h_samples)
    if i0 < 0 or im < 0 or ip < 0:
        return None
    # no restart inside the window: epoch counts consecutive
    if hist.epoch[ip] - hist.epoch[im] != ip - im:
        return None
    acc_p = hist.carr(ip, s_obs + h_samples)
    acc_m = hist.carr(im, s_obs - h_samples)
    out = {
        "doppler_hz": (acc_p - acc_m) / (2.0 * h_samples / hist.fs),
        "carrier_cycles": -hist.carr(i0, s_obs),
        "cn0_dbhz": float(hist.cn0[i0]),
        "pll_lock": bool(hist.flags[i0] & FL_PLL_LOCK),
        "epoch": int(hist.epoch[i0]),
        "code_phase_chips": float(hist.code_chips(i0, s_obs)),
        "t_tx_sv": np.nan,
    }
    if nav is not None and nav.has_time:
        out["t_tx_sv"] = float(nav.tx_time(hist.epoch[i0])) + out["code_phase_chips"] / signal.chip_rate_hz
    return out


def pseudorange(t_rx, t_tx_sv):
    """c (t_rx - t_tx) in metres (week rollover folded)."""
    dt = np.asarray(t_rx, dtype=float) - np.asarray(t_tx_sv, dtype=float)
    dt = np.where(dt > 302400.0, dt - 604800.0, np.where(dt < -302400.0, dt + 604800.0, dt))
    return C * dt


NOISE_SETTLE_EPOCHS = 10      # a channel's smoothed range settles this many epochs before its noise counts
NOISE_WINDOW_S = 2.0          # time constant of the code-noise average (s)


def noise_weights(code_noise_m, min_channels=4, max_factor=10.0):
    """Factors on the pseudoranges' a-priori sigmas from the channels' measured code noise
    (:meth:`CarrierSmoother.code_noise_m`): a channel's noise over the median of the channels that have
    one, at least 1 (no channel is trusted more than the a-priori sigma says) and at most
    ``max_factor``; 1 for a channel without a measurement. None (no weighting) while fewer than
    ``min_channels`` channels have one."""
    nz = np.asarray(code_noise_m, dtype=float)
    have = np.isfinite(nz)
    if have.sum() < min_channels:
        return None
    med = float(np.median(nz[have]))
    if not med > 0.0:
        return None
    return np.where(have, np.clip(nz / med, 1.0, max_factor), 1.0)


class CarrierSmoother:
    """Hatch filter: carrier-smoothed pseudoranges, per channel.

    ``ps_k = pr_k / M + (M - 1)/M (ps_{k-1} + lambda (phi_k - phi_{k-1}))`` with ``M`` growing by one
    per epoch up to ``max_epochs`` (``phi`` in cycles with the range sign, as
    :func:`observe` returns it).  A channel restarts (``M = 1``) when it has no phase lock, a
    missing value or a code-carrier jump larger than ``reset_m`` (cycle slip / re-acquisition).

    Each channel's code noise is measured on the way: the RMS of the raw range minus its carrier
    prediction, ``pr_k - (ps_{k-1} + lambda (phi_k - phi_{k-1}))``, once ``M`` has reached
    :data:`NOISE_SETTLE_EPOCHS`, averaged exponentially over ``noise_epochs`` (:meth:`code_noise_m`).
    The carrier is millimetre-precise, so this is the code's own error: thermal noise, and what a
    cross-correlation or multipath adds to it.
    """

    def __init__(self, n_ch, max_epochs, reset_m=15.0, wavelength_m=GPS_L1CA.wavelength_m, noise_epochs=20):
        self.lam = float(wavelength_m)
        self.max_m = max(1, int(max_epochs))
        self.reset_m = float(reset_m)
        self.m = np.zeros(n_ch, dtype=np.int64)
        self.ps = np.full(n_ch, np.nan)
        self.phi = np.full(n_ch, np.nan)
        self.noise_epochs = max(1, int(noise_epochs))
        self.ms = np.full(n_ch, np.nan)               # mean square of the code-minus-carrier innovation
        self.n_ms = np.zeros(n_ch, dtype=np.int64)    # innovations in it since the channel's last restart

    def code_noise_m(self, min_epochs=5):
        """Per channel, the RMS of the code-minus-carrier innovation (m), NaN until ``min_epochs`` of
        them since the channel's last restart."""
        out = np.sqrt(self.ms)
        out[self.n_ms < min_epochs] = np.nan
        return out

    def _note_innovation(self, ch, d):
        k = self.n_ms[ch] = self.n_ms[ch] + 1
        a = max(1.0 / k, 1.0 / self.noise_epochs)
        self.ms[ch] = d * d if k == 1 else (1.0 - a) * self.ms[ch] + a * d * d

    def update(self, pr_m, phi_cycles, lock):
        pr_m = np.asarray(pr_m, dtype=float)
        phi = np.asarray(phi_cycles, dtype=float)
        out = np.full(pr_m.shape, np.nan)
        for ch in range(pr_m.size):
            ok = bool(lock[ch]) and np.isfinite(pr_m[ch]) and np.isfinite(phi[ch])
            if not ok:
                self.m[ch] = self.n_ms[ch] = 0
                continue
            if self.m[ch] > 0:
                pred = self.ps[ch] + self.lam * (phi[ch] - self.phi[ch])
                if abs(pred - pr_m[ch]) > self.reset_m:
                    self.m[ch] = self.n_ms[ch] = 0
                elif self.m[ch] >= NOISE_SETTLE_EPOCHS:
                    self._note_innovation(ch, pr_m[ch] - pred)
            if self.m[ch] == 0:
                self.ps[ch] = pr_m[ch]
                self.m[ch] = 1
            else:
                m = min(self.m[ch] + 1, self.max_m)
                self.ps[ch] = pr_m[ch] / m + (m - 1.0) / m * pred
                self.m[ch] = m
            self.phi[ch] = phi[ch]
            out[ch] = self.ps[ch]
        return out

    def shift(self, delta_m):
        """Apply a common receiver-time step (clock steering) of ``delta_m`` metres to the state."""
        self.ps = self.ps + delta_m
