"""The outer-loop Doppler aiding each channel's next interval receives (``epochs.record_one``):
sampled on the 1 kHz aiding grid at the middle of the next interval + ``aid_time_offset_s``, i.e.
at the interval's end (docs/ultratight.md, "Aiding sample instant"), checked on Doppler ramps
whose value at any instant is known in closed form; and the recorded Doppler estimate for the
middle of the interval just tracked, NCO + (df + da T/2) / 2 pi."""

import math

import numpy as np

from ultratight.receiver.deep.epochs import record_one
from ultratight.receiver.deep.options import EngineOptions


def test_aiding_is_sampled_at_the_end_of_the_next_interval():
    opt = EngineOptions()
    assert opt.aid_time_offset_s == 0.5e-3                    # the documented choice
    fs, if_hz, T = 2.046e6, 4.092e6 / 4, 1e-3
    half = T / 2
    n_ch, n_grid = 3, 400
    f_start = np.array([1234.5, -2710.25, 80.0])               # Hz at grid time 0
    rate = np.array([2500.0, -900.0, 40.0])                    # Hz/s: ramps of the outer-loop Doppler
    aid_grid = f_start + rate * (np.arange(n_grid)[:, None] / 1000.0)   # grid row j is t = j ms
    # next-interval starts of the channels (samples), not on the 1 ms grid
    sample_ptr = np.array([int(0.1003 * fs) + 17, int(0.2171 * fs) + 5, int(0.0502 * fs)], dtype=np.int64)
    t_start = sample_ptr - int(T * fs)                         # the interval just tracked
    f0 = if_hz + np.array([1200.0, -2700.0, 75.0])             # NCO frequencies during it
    cp0 = np.array([100.25, 7.5, 1000.0])
    x_post = np.zeros((n_ch, 5))
    x_post[:, 3] = 2 * math.pi * np.array([3.0, -1.5, 0.25])   # df (rad/s)
    x_post[:, 4] = 2 * math.pi * np.array([400.0, 0.0, -80.0])  # da (rad/s^2)
    x_post[:, 1] = [0.01, -0.02, 0.003]
    P = np.tile(np.eye(5), (n_ch, 1, 1))
    n_ep = 4
    rec_t, rec_f, rec_cp, rec_a = (np.zeros((n_ep, n_ch)) for _ in range(4))
    rec_mode = np.zeros((n_ep, n_ch), dtype=np.int8)
    mode_now = np.ones(n_ch, dtype=np.int8)
    aid_out = np.zeros(n_ch)
    pend = np.zeros((n_ch, 6))
    pend_ts = np.zeros(n_ch, dtype=np.int64)
    for c in range(n_ch):
        record_one(c, 2, t_start, fs, if_hz, f0, cp0, x_post, P, 1, 3, rec_t, rec_f, rec_cp, rec_a, rec_mode,
                   mode_now, aid_grid, n_grid, sample_ptr, half, 1023.0, aid_out, opt.aid_time_offset_s, pend,
                   pend_ts)
    t_end_next = sample_ptr / fs + T                           # end of the next interval
    np.testing.assert_allclose(aid_out, f_start + rate * t_end_next, rtol=0, atol=1e-9)
    f_mid = f0 - if_hz + (x_post[:, 3] + x_post[:, 4] * half) / (2 * math.pi)
    np.testing.assert_allclose(rec_f[2], f_mid, rtol=0, atol=1e-9)
    np.testing.assert_allclose(rec_t[2], t_start / fs, rtol=0, atol=0)
