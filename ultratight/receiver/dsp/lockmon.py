"""Signal / lock monitor of the ultra-tight engine (not part of the paper's structure; off by
default, see docs/ultratight.md "Signal monitor").

On the wiped prompt of every channel (unit noise per arm), a sliding window of W epochs: while the
signal is ``present``, the mean in-phase prompt ``mean(I_P D)`` (coherent: the carrier loop keeps
the phase) below ``thr_off`` declares it lost; while absent, the coherent magnitude
``|mean((I_P + j Q_P) D)|`` above ``thr_on`` declares it back, with the angle of that mean as the
carrier-phase estimate for the restart.
"""

import math

import numpy as np
from numba import njit


@njit(cache=True)
def lock_monitor_step(out, D, win_i, win_c, sums_i, sums_c, ptr, count, present, thr_off, thr_on, events, phase):
    """One epoch of the monitor for all channels; ``events[c]``: 0 none, -1 lost, +1 regained."""
    W = win_i.shape[1]
    k = ptr[0]
    for c in range(out.shape[0]):
        vi = out[c, 0] * D[c]
        vq = out[c, 3] * D[c]
        sums_i[c] += vi - win_i[c, k]
        sums_c[c] += complex(vi, vq) - win_c[c, k]
        win_i[c, k] = vi
        win_c[c, k] = complex(vi, vq)
        events[c] = 0
        if count[c] < W:
            count[c] += 1
            continue
        if present[c]:
            if abs(sums_i[c].real) / W < thr_off:
                present[c] = False
                events[c] = -1
        else:
            m = sums_c[c] / W
            if abs(m) > thr_on:
                present[c] = True
                events[c] = 1
                phase[c] = math.atan2(m.imag, m.real)
                # restart the window so the next decision uses post-restart data only
                count[c] = 0
    ptr[0] = (k + 1) % W


def amplitude_threshold(cn0_dbhz, code_period_s):
    """Prompt amplitude (unit noise per arm) of a signal at ``cn0_dbhz`` over one code period."""
    return float(np.sqrt(2.0 * 10 ** (cn0_dbhz / 10.0) * code_period_s))


class LockMonitor:
    """The monitor's state for ``n_ch`` channels over a ``window`` of epochs (module docstring).

    ``present`` (n_ch,) bool; :meth:`update` returns ``events`` (n_ch,) of the epoch; ``phase`` the
    coherent angle of the channels just regained; ``coherent_sum`` the window's complex sums.
    """

    def __init__(self, n_ch, window, off_dbhz, on_dbhz, code_period_s):
        W = int(window)
        self.W = W
        self.win_i = np.zeros((n_ch, W))
        self.win_c = np.zeros((n_ch, W), dtype=np.complex128)
        self.sums_i = np.zeros(n_ch)
        self.coherent_sum = np.zeros(n_ch, dtype=np.complex128)
        self.ptr = np.zeros(1, dtype=np.int64)
        self.count = np.zeros(n_ch, dtype=np.int64)
        self.present = np.ones(n_ch, dtype=np.bool_)
        self.events = np.zeros(n_ch, dtype=np.int64)
        self.phase = np.zeros(n_ch)
        self.thr_off = amplitude_threshold(off_dbhz, code_period_s)
        self.thr_on = amplitude_threshold(on_dbhz, code_period_s)

    def update(self, out, D):
        lock_monitor_step(out, D, self.win_i, self.win_c, self.sums_i, self.coherent_sum, self.ptr, self.count,
                          self.present, self.thr_off, self.thr_on, self.events, self.phase)
        return self.events
