"""The inner loop at the epoch rate (1 kHz), compiled: Zhao et al. 2014, Fig. 1, from the IF block to the
NCO command, for every channel, epoch after epoch, until the outer part of the engine is needed.

One epoch (:func:`run_epochs`, in this order; every step is a compiled stage of its own module)::

    IF block (noise sigma of its aligned block) ─► correlators (one code period per channel,
    receiver.dsp.correlator; channels spread over the threads)
    ─► noise events inside the receiver (receiver.dsp.burst; none by default) ─► data wipe-off
    (receiver.dsp.wipeoff) ─► tracking bank epoch (fusion.channel.prefilter.channel_update or
    fusion.channel.pbkf.pbkf_channel_epoch) ─► recorder + residuals against the outer loop's predictions
    + decimator window + outer-loop aiding of the next interval (:func:`epoch_post`)
    ─► inner-loop NCO command (fusion.channel.innerloop)

:func:`run_epochs` stops *before* an epoch that needs something only the Python side has — IF
samples beyond the buffer (``NEED_IF``), outer-loop aiding beyond the SINS (``NEED_SINS``), the end
of the run (``END``) — and *after* an epoch that completes a decimator window (``TIGHT``: the
tight filter updates), so the engine's outer part runs at the same points of the data as a
one-epoch-at-a-time loop would and every result is the same.

The stage arguments are named tuples of arrays (views of the stage objects' own state): ``If``,
``Corr``, ``Wipe``, ``Bank``, ``Outer``, ``Window``, ``Rec``, ``Law``, ``Sig`` and
:class:`ultratight.receiver.dsp.burst.Burst`.
"""

import math
from collections import namedtuple

import numpy as np
from numba import njit, prange

from ultratight.fusion.channel.innerloop import feedback_one
from ultratight.fusion.channel.pbkf import pbkf_channel_epoch, pbkf_note_correction_one
from ultratight.fusion.channel.prefilter import (FLAG_DIVERGED, N_W1, N_W2, NZ, channel_settings, channel_update,
                                                 inputs_finite)
from ultratight.fusion.channel.prefilter_model import CNT_EPOCH, ISEG_COUNTERS, packed_int_offsets
from ultratight.receiver.dsp.burst import burst_one
from ultratight.receiver.dsp.correlator import correlate_one, step_bank, tap_fixed_point
from ultratight.receiver.dsp.wipeoff import wipe_channel
from ultratight.receiver.deep.borrow import borrowed

# status of run_epochs
CONTINUE = 0       # (internal) the next epoch can run
NEED_IF = 1        # the next epoch needs samples beyond the buffer
NEED_SINS = 2      # the next epoch needs outer-loop aiding beyond the SINS
TIGHT = 3          # the epoch just run completed the decimator window: tight update due
END = 4            # the run's samples or epochs are exhausted
ERR_CORR = 5       # a channel could not integrate (buffer management): ``n_s`` tells which
ERR_BANK = 6       # non-finite input to the tracking bank: ``info`` is the channel

BANK_PREFILTER = 0     # fusion.channel.prefilter.PrefilterBank (ckf, ukf, rackf)
BANK_PBKF = 1          # fusion.channel.pbkf.PbKfBank

If = namedtuple("If", "buf is_complex buf_start n_buf n_total block_len sigma")
Corr = namedtuple("Corr", "code_ext pad active sample_ptr code_phase code_rate carr_phase carr_freq fs "
                          "tap_off per_max parallel out t_start n_s cp0 f0 sig")
Wipe = namedtuple("Wipe", "bits t0_ms ms D per_bit code adapt kb acc pol ps pss pn src rec_src soft half_t")
# x0 ... flags: the prefilter's arrays (PrefilterBank.kernel_arrays; empty for a PB-KF bank)
Bank = namedtuple("Bank", "bank_type kind fbuf ibuf n_prm n_tab x x_post P i_ptau i_pf active "
                          "x0 P0 innov nis theta acc Phi Qd R prm flags")
Outer = namedtuple("Outer", "ring_t ring_cp ring_r ring_f ring_nf ring_k imu_dt aid_grid n_filled aid_dt sins_more")
Window = namedtuple("Window", "t_next_upd acc pend pend_ts")
Rec = namedtuple("Rec", "rec_t rec_f rec_cp rec_a rec_mode mode_now n_ep_max")
Law = namedtuple("Law", "aid aid_prev rate_prev hist use_aid prm dx aid_prev_ff")
Sig = namedtuple("Sig", "if_hz half_period_s code_len")


@njit(cache=True)
def record_one(c, k_ep, t_start, fs, if_hz, f0, cp0, x_post, P, i_ptau, i_pf, rec_t, rec_f, rec_cp, rec_a, rec_mode,
               mode_now, aid_grid, n_filled, sample_ptr, half_period_s, code_len, aid_out, aid_dt, pend, pend_ts):
    """Channel ``c``'s estimates of epoch ``k_ep`` into the records and into its row of ``pend`` (the
    inputs of :func:`residual_one`, formed later), and the outer-loop aiding of its next interval."""
    two_pi = 2.0 * math.pi
    tk = float(t_start[c]) / fs
    # Doppler estimate for the middle of the interval: NCO + df + da T/2 (state at the start)
    f_meas = f0[c] - if_hz + (x_post[c, 3] + x_post[c, 4] * half_period_s) / two_pi
    cp_meas = cp0[c] + x_post[c, 1]
    rec_t[k_ep, c] = tk
    rec_f[k_ep, c] = f_meas
    rec_cp[k_ep, c] = cp_meas % code_len
    rec_a[k_ep, c] = x_post[c, 0]
    rec_mode[k_ep, c] = mode_now[c]
    pend[c, 0] = tk
    pend[c, 1] = f_meas
    pend[c, 2] = cp_meas
    pend[c, 3] = P[c, i_ptau, i_ptau]
    pend[c, 4] = P[c, i_pf, i_pf]
    pend[c, 5] = x_post[c, 0]
    pend_ts[c] = t_start[c]
    u = (sample_ptr[c] / fs + half_period_s + aid_dt) * 1000.0
    j = int(math.floor(u))
    if j < 0:
        j = 0
    if j > n_filled - 2:
        j = n_filled - 2
    fr = u - j
    aid_out[c] = aid_grid[j, c] * (1.0 - fr) + aid_grid[j + 1, c] * fr


@njit(cache=True)
def residual_one(c, pend, ring_t, ring_cp, ring_r, ring_f, ring_latest, imu_dt, t_next_upd, acc, half_period_s,
                 code_len):
    """Channel ``c``'s code and Doppler residuals of one epoch against the SINS predictions (the ring
    of 100 Hz predictions whose latest entry is the absolute count ``ring_latest``; linear in between),
    summed into the decimator window ``acc`` (rows: n, code, Doppler, P_tautau, P_ff, amplitude)
    when the epoch starts before the window end."""
    ring_n = ring_t.shape[0]
    half = 0.5 * code_len
    tk = pend[c, 0]
    f_meas = pend[c, 1]
    cp_meas = pend[c, 2]
    t_last = ring_t[ring_latest % ring_n]
    back = int(math.floor((t_last - tk) / imu_dt)) + 1
    if back < 1:
        back = 1
    if back > ring_n - 2:
        back = ring_n - 2
    ia = (ring_latest - back) % ring_n
    ib = (ia + 1) % ring_n
    ta = ring_t[ia]
    w = (tk - ta) / imu_dt
    cp_pred = ring_cp[ia, c] + ring_r[ia, c] * (tk - ta)
    # the Doppler estimate is the interval mean: compare with the prediction at mid-interval
    w += half_period_s / imu_dt
    f_pred = ring_f[ia, c] + w * (ring_f[ib, c] - ring_f[ia, c])
    r_cp = (cp_meas - cp_pred + half) % code_len - half
    r_f = f_meas - f_pred
    if tk < t_next_upd:
        acc[0, c] += 1.0
        acc[1, c] += r_cp
        acc[2, c] += r_f
        acc[3, c] += pend[c, 3]
        acc[4, c] += pend[c, 4]
        acc[5, c] += pend[c, 5]


@njit(cache=True)
def ring_latest_for(ring_nf, ring_k, j_need):
    """The absolute count of the SINS's latest prediction when an epoch with ``j_need`` runs in a loop
    that steps the SINS only as the epochs need its aiding: the first entry whose aiding grid end
    ``ring_nf`` exceeds ``j_need`` (the latest one when the IMU data ended before)."""
    ring_n = ring_nf.shape[0]
    k = ring_k - 1
    oldest = max(0, ring_k - ring_n + 2)
    while k - 1 >= oldest and ring_nf[(k - 1) % ring_n] > j_need:
        k -= 1
    return k


@njit(cache=True)
def settle(E, pend, pend_ts, per_max, fs, outer, window, sig):
    """The residuals of ``E`` recorded epochs (``pend[e]``, ``pend_ts[e]``), in epoch order, each against
    the SINS predictions as a one-epoch loop would have had them (:func:`ring_latest_for` of the
    epoch's ``j_need``)."""
    pend, pend_ts, outer, window, sig = borrowed(pend), borrowed(pend_ts), borrowed(outer), borrowed(window), \
        borrowed(sig)       # held by the caller (ultratight.receiver.deep.borrow)
    n_ch = pend.shape[1]
    for e in range(E):
        sp_max = pend_ts[e, 0]
        for c in range(1, n_ch):
            if pend_ts[e, c] > sp_max:
                sp_max = pend_ts[e, c]
        j_need = int((sp_max + per_max) / fs * 1000.0) + 2
        latest = ring_latest_for(outer.ring_nf, outer.ring_k, j_need)
        for c in range(n_ch):
            residual_one(c, pend[e], outer.ring_t, outer.ring_cp, outer.ring_r, outer.ring_f, latest, outer.imu_dt,
                         window.t_next_upd, window.acc, sig.half_period_s, sig.code_len)


@njit(cache=True)
def epoch_post(k_ep, t_start, fs, if_hz, f0, cp0, x_post, P, i_ptau, i_pf, per_max, src_outer, window, rec_t,
               rec_f, rec_cp, rec_a, rec_mode, mode_now, sample_ptr, sig, aid_out, aid_dt, pend, pend_ts):
    """Per-epoch bookkeeping for all channels in one compiled call: records the estimates
    (NCO + tracking-bank posterior at the interval start), the residuals against the SINS
    predictions summed into the decimator window, and the 1 kHz outer-loop Doppler aiding at the
    middle of each channel's next interval (:func:`record_one`, :func:`settle`)."""
    for c in range(t_start.shape[0]):
        record_one(c, k_ep, t_start, fs, if_hz, f0, cp0, x_post, P, i_ptau, i_pf, rec_t, rec_f, rec_cp, rec_a,
                   rec_mode, mode_now, src_outer.aid_grid, src_outer.n_filled, sample_ptr, sig.half_period_s,
                   sig.code_len, aid_out, aid_dt, pend[0], pend_ts[0])
    settle(np.int64(1), pend, pend_ts, per_max, fs, src_outer, window, sig)


@njit(cache=True)
def epoch_gate(k_ep, src, corr, outer, rec):
    """What the next epoch needs before it can run: CONTINUE, NEED_IF, NEED_SINS or END."""
    sp_max = corr.sample_ptr.max()
    hi = sp_max + corr.per_max
    if hi > src.n_total or k_ep >= rec.n_ep_max:
        return END
    if hi > src.buf_start + src.n_buf:
        return NEED_IF
    j_need = int((sp_max + corr.per_max) / corr.fs * 1000.0) + 2
    if outer.sins_more and outer.n_filled <= j_need:
        return NEED_SINS
    return CONTINUE


@njit(cache=True)
def correlate(src, corr, sig):
    """Correlators of one epoch: the noise sigma of each channel's aligned block, one code period."""
    n_ch = corr.sample_ptr.shape[0]
    for c in range(n_ch):
        corr.cp0[c] = corr.code_phase[c]
        corr.f0[c] = corr.carr_freq[c]
        corr.sig[c] = src.sigma[corr.sample_ptr[c] // src.block_len]
    step_bank(src.buf, src.is_complex, src.buf_start, src.n_buf, corr.code_ext, corr.pad, corr.active,
              corr.sample_ptr, corr.code_phase, corr.code_rate, corr.carr_phase, corr.carr_freq, corr.fs,
              corr.tap_off, corr.sig, corr.out, corr.t_start, corr.n_s, sig.code_len)
    return corr.n_s.min() > 0


@njit(cache=True)
def _prefilter_settings(bank_type, ibuf, n):
    """:func:`~ultratight.fusion.channel.prefilter_kernels.channel_settings` of a prefilter bank; placeholders
    for a PB-KF bank, whose buffer has another layout."""
    if bank_type == BANK_PBKF:
        return 1, False, 0, 0
    return channel_settings(ibuf, n)


@njit(cache=True)
def epoch_channel(c, E, k_ep0, epoch0, src, corr, wipe, bank, outer, window, rec, law, sig, burst, tap_fix, W1, W2,
                  WA):
    """``E`` epochs of channel ``c`` from epoch ``k_ep0`` (the tracking bank's epoch count ``epoch0``)
    through every stage (touches only channel ``c``'s rows): 0, or ERR_CORR / ERR_BANK at the epoch
    that failed. Epoch ``e`` of the call puts its residual inputs in row ``e`` of ``window.pend``
    (:func:`settle` forms them); ``W1``/``W2``: the tracking bank's work arrays, ``WA`` the
    correlator's (2 * number of taps). The epochs loop here rather than in the callers: numba counts
    a reference to every array of the records at every call, and one call per epoch and channel spent
    a tenth of a run in those counts (docs/ultratight.md, "Where an engine's time goes")."""
    # the stages get borrowed arrays (ultratight.receiver.deep.borrow): this call's caller holds the records
    # and work arrays until it returns
    src, corr, wipe, bank, outer, window = borrowed(src), borrowed(corr), borrowed(wipe), borrowed(bank), \
        borrowed(outer), borrowed(window)
    rec, law, sig, burst = borrowed(rec), borrowed(law), borrowed(sig), borrowed(burst)
    tap_fix, W1, W2, WA = borrowed(tap_fix), borrowed(W1), borrowed(W2), borrowed(WA)
    # the records' fields taken once per call: numba counts a reference at every field access, which
    # inside the loop was once per epoch
    corr_active, corr_carr_freq, corr_carr_phase = corr.active, corr.carr_freq, corr.carr_phase
    corr_code_ext, corr_code_phase, corr_code_rate = corr.code_ext, corr.code_phase, corr.code_rate
    corr_cp0, corr_f0, corr_fs, corr_n_s, corr_out = corr.cp0, corr.f0, corr.fs, corr.n_s, corr.out
    corr_pad, corr_sample_ptr, corr_sig, corr_t_start = corr.pad, corr.sample_ptr, corr.sig, corr.t_start
    src_block_len, src_buf, src_buf_start, src_is_complex = src.block_len, src.buf, src.buf_start, src.is_complex
    src_n_buf, src_sigma = src.n_buf, src.sigma
    sig_code_len, sig_half_period_s, sig_if_hz = sig.code_len, sig.half_period_s, sig.if_hz
    wipe_D, wipe_acc, wipe_adapt, wipe_bits, wipe_code = wipe.D, wipe.acc, wipe.adapt, wipe.bits, wipe.code
    wipe_half_t, wipe_kb, wipe_ms, wipe_per_bit, wipe_pn = wipe.half_t, wipe.kb, wipe.ms, wipe.per_bit, wipe.pn
    wipe_pol, wipe_ps, wipe_pss, wipe_rec_src, wipe_soft = wipe.pol, wipe.ps, wipe.pss, wipe.rec_src, wipe.soft
    wipe_src, wipe_t0_ms = wipe.src, wipe.t0_ms
    bank_P, bank_active, bank_bank_type, bank_fbuf = bank.P, bank.active, bank.bank_type, bank.fbuf
    bank_i_pf, bank_i_ptau, bank_ibuf, bank_kind = bank.i_pf, bank.i_ptau, bank.ibuf, bank.kind
    bank_n_prm, bank_n_tab, bank_x, bank_x_post = bank.n_prm, bank.n_tab, bank.x, bank.x_post
    rec_mode_now, rec_rec_a, rec_rec_cp, rec_rec_f = rec.mode_now, rec.rec_a, rec.rec_cp, rec.rec_f
    rec_rec_mode, rec_rec_t = rec.rec_mode, rec.rec_t
    outer_aid_dt, outer_aid_grid, outer_n_filled = outer.aid_dt, outer.aid_grid, outer.n_filled
    law_aid, law_aid_prev, law_aid_prev_ff, law_dx = law.aid, law.aid_prev, law.aid_prev_ff, law.dx
    law_hist, law_prm, law_rate_prev, law_use_aid = law.hist, law.prm, law.rate_prev, law.use_aid
    window_pend, window_pend_ts, burst_rscale = window.pend, window.pend_ts, burst.rscale
    b_x0, b_P0, b_innov, b_nis, b_theta, b_acc = bank.x0, bank.P0, bank.innov, bank.nis, bank.theta, bank.acc
    b_Phi, b_Qd, b_R, b_prm, b_flags = bank.Phi, bank.Qd, bank.R, bank.prm, bank.flags
    period, robust_every, win_mode, resets_at = _prefilter_settings(bank_bank_type, bank_ibuf, corr_sample_ptr.shape[0])
    for e in range(E):
        k_ep = k_ep0 + e
        epoch = epoch0 + e
        corr_cp0[c] = corr_code_phase[c]
        corr_f0[c] = corr_carr_freq[c]
        corr_sig[c] = src_sigma[corr_sample_ptr[c] // src_block_len]
        correlate_one(c, src_buf, src_is_complex, src_buf_start, src_n_buf, corr_code_ext, corr_pad, corr_active,
                      corr_sample_ptr, corr_code_phase, corr_code_rate, corr_carr_phase, corr_carr_freq, corr_fs,
                      tap_fix, corr_sig, corr_out, corr_t_start, corr_n_s, sig_code_len, WA)
        if corr_n_s[c] <= 0:
            return ERR_CORR
        burst_one(c, k_ep, corr_t_start[c] / corr_fs, burst, corr_out)
        wipe_channel(c, k_ep, wipe_bits, wipe_t0_ms, wipe_ms, wipe_D, wipe_per_bit, wipe_code, wipe_adapt, wipe_kb,
                     wipe_acc, wipe_pol, wipe_ps, wipe_pss, wipe_pn, wipe_src, wipe_rec_src, wipe_soft,
                     corr_out, bank_x, wipe_half_t)
        if bank_bank_type == BANK_PBKF:
            if pbkf_channel_epoch(bank_fbuf, bank_ibuf, c, corr_out, wipe_D, burst_rscale, bank_n_prm, bank_n_tab) < 0:
                return ERR_BANK
        else:       # the prefilter's epoch (prefilter_kernels.channel_settings) with its arrays held
            if bank_active[c] and not inputs_finite(c, corr_out, wipe_D):
                return ERR_BANK
            channel_update(bank_kind, c, bank_x, bank_P, bank_x_post, b_x0, b_P0, b_Phi, b_Qd, b_R, corr_out, wipe_D,
                           burst_rscale, bank_active, b_prm, epoch % period == 0, robust_every, win_mode, b_innov,
                           b_nis, b_theta, b_flags, W1, W2, b_acc)
            if (b_flags[c] & FLAG_DIVERGED) != 0:
                bank_ibuf[resets_at + c] += 1
        record_one(c, k_ep, corr_t_start, corr_fs, sig_if_hz, corr_f0, corr_cp0, bank_x_post, bank_P, bank_i_ptau,
                   bank_i_pf, rec_rec_t, rec_rec_f, rec_rec_cp, rec_rec_a, rec_rec_mode, rec_mode_now, outer_aid_grid,
                   outer_n_filled, corr_sample_ptr, sig_half_period_s, sig_code_len, law_aid, outer_aid_dt,
                   window_pend[e], window_pend_ts[e])
        feedback_one(c, bank_x, bank_active, corr_code_phase, corr_code_rate, corr_carr_phase, corr_carr_freq,
                     law_aid, law_aid_prev, law_rate_prev, law_hist, law_use_aid, law_prm, law_dx)
        if bank_bank_type == BANK_PBKF:
            pbkf_note_correction_one(bank_fbuf, bank_ibuf, c, law_dx, bank_n_prm, bank_n_tab)
        law_aid_prev_ff[c] = law_aid[c]
    return 0


@njit(cache=True)
def _bank_epoch_count(bank, n):
    """The tracking bank's epoch counter (the prefilter's correction phase counts from it)."""
    if bank.bank_type == BANK_PBKF:
        return 0
    return bank.ibuf[packed_int_offsets(n)[ISEG_COUNTERS] + CNT_EPOCH]


@njit(cache=True)
def _bank_epoch_advance(bank, n, k):
    if bank.bank_type != BANK_PBKF:
        bank.ibuf[packed_int_offsets(n)[ISEG_COUNTERS] + CNT_EPOCH] += k


@njit(cache=True)
def safe_epochs(k_ep, src, corr, outer, window, rec):
    """How many epochs can run from here with no stop condition possible before the last one (each
    channel takes at most ``per_max`` samples per epoch; one epoch of margin); TIGHT after the last
    one is checked afterwards."""
    pm = corr.per_max
    sp_max = corr.sample_ptr.max()
    sp_min = corr.sample_ptr.min()
    limit = min(src.n_total, src.buf_start + src.n_buf)
    E = min(rec.n_ep_max - k_ep, (limit - sp_max) // pm, window.pend.shape[0] + 1)
    if outer.sins_more:
        E = min(E, int(math.floor(((outer.n_filled - 2) * corr.fs / 1000.0 - sp_max) / pm)))
    E = min(E, int(math.floor((window.t_next_upd * corr.fs - sp_min) / pm)) + 1)
    return E - 1


@njit(cache=True, parallel=True)
def _channels_parallel(E, k_ep, epoch0, src, corr, wipe, bank, outer, window, rec, law, sig, burst, tap_fix, err):
    """``E`` epochs of every channel, the channels spread over numba's threads (each with its own
    work arrays); ``err[c]``: 0 or the first error of channel ``c``."""
    for cu in prange(corr.sample_ptr.shape[0]):
        # prange's index is unsigned: as int64 the per-channel kernels get the one signature the serial
        # path compiles (not a second copy of every one of them)
        c = np.int64(cu)
        W1 = np.empty((N_W1, NZ))
        W2 = np.empty((N_W2, NZ, NZ))
        WA = np.empty(2 * tap_fix.shape[0])
        r = epoch_channel(c, E, k_ep, epoch0, src, corr, wipe, bank, outer, window, rec, law, sig, burst, tap_fix,
                          W1, W2, WA)
        if r != 0:
            err[c] = r


@njit(cache=True)
def _channels_serial(E, k_ep, epoch0, src, corr, wipe, bank, outer, window, rec, law, sig, burst, tap_fix, W1, W2,
                     WA, err):
    """:func:`_channels_parallel` on this thread: ``E`` epochs of one channel after the other."""
    for c in range(corr.sample_ptr.shape[0]):
        r = epoch_channel(c, E, k_ep, epoch0, src, corr, wipe, bank, outer, window, rec, law, sig, burst, tap_fix,
                          W1, W2, WA)
        if r != 0:
            err[c] = r


@njit(cache=True)
def _serial_epoch(n, k_ep, src, corr, wipe, bank, outer, window, rec, law, sig, burst, tap_fix, W1, W2, WA, err):
    """One epoch of every channel, one after the other (``err`` as :func:`_channels_parallel`)."""
    epoch = _bank_epoch_count(bank, n)
    for c in range(n):
        # E as int64, not the literal 1: one compiled epoch_channel for every path
        r = epoch_channel(c, np.int64(1), k_ep, epoch, src, corr, wipe, bank, outer, window, rec, law, sig, burst,
                          tap_fix, W1, W2, WA)
        if r != 0:
            err[c] = r
            break


@njit(cache=True)
def _work_arrays(corr):
    """The channel count, the taps in fixed point, the tracking bank's and the correlator's work arrays
    and the per-channel error flags of the steady-epoch loops."""
    n = corr.sample_ptr.shape[0]
    tap_fix = tap_fixed_point(corr.tap_off)
    return (n, tap_fix, np.empty((N_W1, NZ)), np.empty((N_W2, NZ, NZ)), np.empty(2 * tap_fix.shape[0]),
            np.zeros(n, dtype=np.int64))


@njit(cache=True)
def _after_epochs(E, n, k_ep, corr, bank, outer, window, sig, err):
    """After ``E`` epochs of every channel: ``(status, k_ep, info)`` with status CONTINUE, TIGHT or a
    channel's error (info: the channel)."""
    for c in range(n):
        if err[c] != 0:
            return err[c], k_ep, c
    settle(E, window.pend, window.pend_ts, corr.per_max, corr.fs, outer, window, sig)
    _bank_epoch_advance(bank, n, E)
    k_ep += E
    if corr.t_start.min() >= window.t_next_upd * corr.fs:
        return TIGHT, k_ep, 0
    return CONTINUE, k_ep, 0


@njit(cache=True)
def run_epochs(k_ep, src, corr, wipe, bank, outer, window, rec, law, sig, burst):
    """Steady epochs (no start-up phase initialisation, no restart, no coasting channel) from epoch
    ``k_ep`` on, until a stop (module docstring), one channel after the other. Returns ``(status,
    k_ep, info)``. :func:`run_epochs_threaded` is the same with the channels over the threads; they
    are two kernels so that a one-thread run (each worker of the main job) neither compiles nor loads
    the threaded one (a quarter of the engine's first compilation)."""
    n, tap_fix, W1, W2, WA, err = _work_arrays(corr)
    while True:
        st = epoch_gate(k_ep, src, corr, outer, rec)
        if st != CONTINUE:
            return st, k_ep, 0
        E = safe_epochs(k_ep, src, corr, outer, window, rec)
        if E >= 2:
            _channels_serial(E, k_ep, _bank_epoch_count(bank, n), src, corr, wipe, bank, outer, window, rec, law, sig,
                             burst, tap_fix, W1, W2, WA, err)
        else:
            E = 1
            _serial_epoch(n, k_ep, src, corr, wipe, bank, outer, window, rec, law, sig, burst, tap_fix, W1, W2, WA,
                          err)
        st, k_ep, info = _after_epochs(E, n, k_ep, corr, bank, outer, window, sig, err)
        if st != CONTINUE:
            return st, k_ep, info


@njit(cache=True)
def run_epochs_threaded(k_ep, src, corr, wipe, bank, outer, window, rec, law, sig, burst):
    """:func:`run_epochs` with the channels spread over numba's threads for the epochs that provably
    need no stop (:func:`safe_epochs`); the last few before a stop run one epoch at a time."""
    n, tap_fix, W1, W2, WA, err = _work_arrays(corr)
    while True:
        st = epoch_gate(k_ep, src, corr, outer, rec)
        if st != CONTINUE:
            return st, k_ep, 0
        E = safe_epochs(k_ep, src, corr, outer, window, rec)
        if E >= 2:
            _channels_parallel(E, k_ep, _bank_epoch_count(bank, n), src, corr, wipe, bank, outer, window, rec,
                               law, sig, burst, tap_fix, err)
        else:
            E = 1
            _serial_epoch(n, k_ep, src, corr, wipe, bank, outer, window, rec, law, sig, burst, tap_fix, W1, W2, WA,
                          err)
        st, k_ep, info = _after_epochs(E, n, k_ep, corr, bank, outer, window, sig, err)
        if st != CONTINUE:
            return st, k_ep, info
