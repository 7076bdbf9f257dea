"""The fused block kernel of the scalar tracking bank: one numba call per IF block
(:func:`track_block`, or :func:`track_block_parallel` with the channels on numba's threads).

For every active channel it integrates code periods with the correlator kernel of
:mod:`ultratight.receiver.dsp.correlator` (E/P/L, normalised per
:mod:`ultratight.signals.corr_model`: unit noise per arm, prompt amplitude
``A = sqrt(2 C/N0 T)``) or the prompt / E-L pass of :mod:`ultratight.receiver.dsp.tracking_kernels`,
runs the per-epoch logic below, the discriminators and loop filters, updates the NCOs, and writes
one record per epoch (columns of :mod:`ultratight.receiver.dsp.tracking_layout`). An epoch is one
code period (1 ms for C/A); the bit-sync histogram has one bin per code period of a data bit.

Per-epoch logic:

* Pull-in mode (after (re)acquisition): wide PLL + FLL assist, 1 ms. Track mode (after the
  phase-lock indicator has held for ``lock_s``): track bandwidths, and after bit sync the
  coherent integration grows to ``coh_ms`` (aligned to bit edges; the effective PLL
  bandwidth is capped at ``max_bnt / T`` to keep the discrete loop stable).
* C/N0: the outputs have unit noise per arm, so ``E[I_P^2 + Q_P^2] = 2 + 2 C/N0 T``; the
  estimate over ``cn0_win_ms`` epochs is ``(mean P - 2)/(2 T)``, smoothed exponentially in dB
  (the moments/M2M4 estimator, which needs no noise reference, is
  :func:`ultratight.receiver.dsp.tracking.cn0_m2m4`).
* Phase-lock indicator ``PLI = LP((I^2 - Q^2)/n) / (LP((I^2 + Q^2)/n) - 2)`` ≈ cos(2 dphi) on the
  coherent sums of ``n`` epochs (noise bias removed with the known unit noise), low-pass time
  constant ``pli_tau_s``.
* Loss of lock: C/N0 estimate below ``cn0_lost_dbhz`` for ``lost_s`` -> channel mode LOST and
  deactivated (the pipeline re-acquires it).
* Bit sync: sign changes of the per-period I_P counted in one bin per code period of a bit (20 for
  C/A: epoch mod 20); declared when the largest
  bin leads the second by ``bs_margin`` and stands 6 sigma above the mean of the others (Poisson
  noise transitions; works before phase lock too: a
  residual beat adds transitions to every bin alike).  Coherent integration then grows to
  ``coh_ms`` in both modes (the FLL then sees the higher SNR of the longer sums).

The per-epoch logic (:func:`_epoch_update`) is split into small numba functions (C/N0, mode,
bit sync, coherent sums, PLI, bandwidths, loop filters) compiled into the block kernel.
"""

import math

import numpy as np
from numba import njit, prange

from ultratight.receiver.dsp.chipbits import unit_chips
from ultratight.receiver.dsp.correlator import (COS_LUT, SIN_LUT, integrate_channel, nco_fixed_point,
                                                period_samples, tap_fixed_point)
from ultratight.receiver.dsp.tracking_kernels import (costas_disc, dll_disc, dll_disc_dot, dll_update, fll_disc,
                                                      integrate_pel, pll_fll_update)
from ultratight.receiver.dsp.tracking_layout import (
    F_AIE, F_AIL, F_AIP, F_AQE, F_AQL, F_AQP, F_AT, F_BIT_SUM, F_CARR_ACC, F_CN0_DB, F_CN0_P, F_CN0_T,
    F_DLL_ERR, F_DLL_U, F_DLL_Z, F_DOPP, F_FLL_ERR, F_LAST_I, F_LOCK_T, F_LOW_T, F_PLI, F_PLI_D, F_PLI_N,
    F_PLL_ERR, F_PLL_X, F_PLL_Y, F_PREV_I, F_PREV_Q, F_UNLOCK_T, FL_BIT_DONE, FL_BIT_SYNC, FL_LOOP_UPD,
    FL_PLL_LOCK, MODE_LOST, MODE_PULL, MODE_TRACK, P_BS_ENERGY, P_BS_MARGIN, P_CARRIER, P_CHIP_RATE,
    P_CN0_ALPHA, P_CN0_LOST, P_CN0_WIN, P_CODE_LEN, P_COH_MS, P_DLL_ORDER, P_LOCK_S, P_LOST_S, P_MAX_BNT,
    P_PEL, P_PLI_LOCK, P_PLI_TAU, P_PLL_ORDER, P_PULL_COH_MS, P_PULL_DLL_BW, P_PULL_FLL_BW, P_PULL_PLL_BW,
    P_SPACING, P_TRK_DLL_BW, P_TRK_FLL_BW, P_TRK_PLL_BW, P_UNLOCK_S, P_WEAK_DBHZ, P_WEAK_LONG_COH_MS,
    P_WEAK_PLL_BW, R_BIT, R_CARR_ACC, R_CN0, R_CODE_PHASE, R_CODE_RATE, R_DLL_ERR, R_DOPP, R_FLL_ERR, R_IE,
    R_IL, R_IP, R_PLI, R_PLL_ERR, R_QE, R_QL, R_QP, RI_EPOCH, RI_FLAGS, RI_MODE, RI_N, RI_PTR, S_ACC_COH,
    S_ACC_N, S_BIT_N, S_BIT_PHASE, S_CN0_N, S_CN0_VALID, S_EPOCH, S_HAVE_PREV, S_MODE, S_NTRANS)

PLI_MIN_POWER = 0.1     # LP signal power (A^2 per epoch, ~17 dB-Hz at 1 ms) below which PLI = 0
CN0_FLOOR_LIN = 1.0     # 0 dB-Hz: reported when the power estimate is at or below the noise


# ------------------------------------------------------------------------------ per-epoch logic
@njit(cache=True)
def _cn0_update(ch, p, t_ep, sf, si, prm):
    """C/N0 from the prompt power ``p`` with the unit-noise reference: ``(mean P - 2)/(2 T)`` over
    ``cn0_win_ms`` epochs, smoothed exponentially in dB."""
    sf[ch, F_CN0_P] += p
    sf[ch, F_CN0_T] += t_ep
    si[ch, S_CN0_N] += 1
    if si[ch, S_CN0_N] >= prm[P_CN0_WIN]:
        nwin = si[ch, S_CN0_N]
        tbar = sf[ch, F_CN0_T] / nwin
        lin = (sf[ch, F_CN0_P] / nwin - 2.0) / (2.0 * tbar)
        if lin < CN0_FLOOR_LIN:
            lin = CN0_FLOOR_LIN
        db = 10.0 * math.log10(lin)
        if si[ch, S_CN0_VALID] == 0:
            sf[ch, F_CN0_DB] = db
            si[ch, S_CN0_VALID] = 1
        else:
            sf[ch, F_CN0_DB] += prm[P_CN0_ALPHA] * (db - sf[ch, F_CN0_DB])
        sf[ch, F_CN0_P] = 0.0
        sf[ch, F_CN0_T] = 0.0
        si[ch, S_CN0_N] = 0


@njit(cache=True)
def _mode_update(ch, mode, t_ep, sf, si, prm):
    """Pull-in / track / lost transitions; returns (mode, flags with FL_PLL_LOCK)."""
    flags = 0
    if mode == MODE_PULL and sf[ch, F_LOCK_T] >= prm[P_LOCK_S]:
        mode = MODE_TRACK
    elif mode == MODE_TRACK and sf[ch, F_UNLOCK_T] >= prm[P_UNLOCK_S]:
        mode = MODE_PULL
    if mode == MODE_TRACK and (si[ch, S_CN0_VALID] == 0 or sf[ch, F_CN0_DB] >= prm[P_CN0_LOST]):
        flags |= FL_PLL_LOCK
    # loss of lock (code): C/N0 too low for too long
    if si[ch, S_CN0_VALID] == 1 and sf[ch, F_CN0_DB] < prm[P_CN0_LOST]:
        sf[ch, F_LOW_T] += t_ep
    else:
        sf[ch, F_LOW_T] = 0.0
    if sf[ch, F_LOW_T] >= prm[P_LOST_S]:
        mode = MODE_LOST
    return mode, flags


@njit(cache=True)
def _bit_sync_energy(ch, ip, epoch, bse, cpb):
    """Bit-energy bit synchronisation: the bit-edge phase k maximising ``E_k = sum |S_k|`` over the
    sums ``S_k`` of the 1 ms prompts I_P of every bit-long window starting at an epoch = k (mod cpb)
    (the maximum-likelihood edge of a phase-locked BPSK signal, Kaplan & Hegarty ch. 5 / van Dierendonck).
    Two phases k1, k2 that are m epochs apart differ by m epochs in and m out of each window: the
    noise of ``|S_k1| - |S_k2|`` is at most ``sqrt(2 m)`` per window (unit noise per arm), so k1 is
    declared when, after N >= 25 windows, ``E_k1 - E_k2 >= 6 sqrt(2 m N)`` for every other k2.

    ``bse[ch]``: running sums (cpb), energies (cpb), epochs seen. Returns the edge phase or -1."""
    n_e = bse[ch, 2 * cpb]
    k = epoch % cpb
    found = -1
    if n_e >= cpb:
        bse[ch, cpb + k] += abs(bse[ch, k])
        nb = n_e // cpb
        if nb >= 25:
            k1 = 0
            for j in range(cpb):
                if bse[ch, cpb + j] > bse[ch, cpb + k1]:
                    k1 = j
            ok = True
            for j in range(cpb):
                if j == k1:
                    continue
                m = abs(j - k1)
                if cpb - m < m:
                    m = cpb - m
                if bse[ch, cpb + k1] - bse[ch, cpb + j] < 6.0 * math.sqrt(2.0 * m * nb):
                    ok = False
                    break
            if ok:
                found = k1
    bse[ch, k] = 0.0
    for j in range(cpb):
        bse[ch, j] += ip
    bse[ch, 2 * cpb] = n_e + 1.0
    return found


@njit(cache=True)
def _bit_sync(ch, ip, epoch, mode, sf, si, hist, prm, bse):
    """Bit synchronisation (sign-change histogram over the ``hist.shape[1]`` code periods of a data
    bit) and the bit sums after it; returns (bit phase or -1, flags, soft bit)."""
    cpb = hist.shape[1]
    flags = 0
    bit_soft = 0.0
    bph = si[ch, S_BIT_PHASE]
    if bph < 0 and mode != MODE_LOST:
        if sf[ch, F_LAST_I] != 0.0 and (ip > 0.0) != (sf[ch, F_LAST_I] > 0.0):
            b = epoch % cpb
            hist[ch, b] += 1
            si[ch, S_NTRANS] += 1
            m1 = 0
            m2 = 0
            kbest = 0
            for k in range(cpb):
                h = hist[ch, k]
                if h > m1:
                    m2 = m1
                    m1 = h
                    kbest = k
                elif h > m2:
                    m2 = h
            # the other bins collect noise transitions (Poisson, mean mu): the edge bin must stand
            # 6 sigma above them and lead the runner-up by the margin
            mu = (si[ch, S_NTRANS] - m1) / (cpb - 1.0)
            if m1 - m2 >= prm[P_BS_MARGIN] and m1 - mu >= 6.0 * math.sqrt(max(mu, 1.0)):
                bph = kbest
                si[ch, S_BIT_PHASE] = bph
                si[ch, S_BIT_N] = -1      # wait for the next bit edge
    if bph < 0 and mode != MODE_LOST and prm[P_BS_ENERGY] > 0.0:
        kb = _bit_sync_energy(ch, ip, epoch, bse, cpb)
        if kb >= 0:
            bph = kb
            si[ch, S_BIT_PHASE] = bph
            si[ch, S_BIT_N] = -1
    sf[ch, F_LAST_I] = ip
    if bph >= 0:
        flags |= FL_BIT_SYNC
        pos = (epoch - bph) % cpb
        if pos == 0:
            sf[ch, F_BIT_SUM] = 0.0
            si[ch, S_BIT_N] = 0
        if si[ch, S_BIT_N] >= 0:
            sf[ch, F_BIT_SUM] += ip
            si[ch, S_BIT_N] += 1
            if pos == cpb - 1 and si[ch, S_BIT_N] == cpb:
                flags |= FL_BIT_DONE
                bit_soft = sf[ch, F_BIT_SUM]
    return bph, flags, bit_soft


@njit(cache=True)
def _coherent_length(ch, bph, weak, si, prm):
    """Coherent integration (epochs) and its reference epoch for this epoch."""
    coh = 1
    ref = 0
    if bph >= 0:
        coh = int(prm[P_COH_MS])
        ref = bph
        if weak and prm[P_WEAK_LONG_COH_MS] > coh:
            coh = int(prm[P_WEAK_LONG_COH_MS])     # bit-synchronised long integration for weak signals
    elif weak:
        # weak signal before bit sync: short coherent sums (a bit edge spoils at most one of them)
        # give the FLL/PLL a usable SNR per update
        coh = int(prm[P_PULL_COH_MS])
    return coh, ref


@njit(cache=True)
def _accumulate(ch, o, t_ep, epoch, coh, ref, sf, si, acc7):
    """Coherent sums of ``coh`` epochs aligned to ``ref``; fills ``acc7`` = [I_P, Q_P, I_E, Q_E, I_L,
    Q_L, T] of the sum and returns True when the sum is complete (a loop update is due)."""
    ip, ie, il, qp, qe, ql = o[0], o[1], o[2], o[3], o[4], o[5]
    if coh <= 1:
        si[ch, S_ACC_N] = 0
        acc7[0], acc7[1], acc7[2], acc7[3], acc7[4], acc7[5], acc7[6] = ip, qp, ie, qe, il, ql, t_ep
        return True
    if (epoch - ref) % coh == 0:
        sf[ch, F_AIP] = 0.0
        sf[ch, F_AQP] = 0.0
        sf[ch, F_AIE] = 0.0
        sf[ch, F_AQE] = 0.0
        sf[ch, F_AIL] = 0.0
        sf[ch, F_AQL] = 0.0
        sf[ch, F_AT] = 0.0
        si[ch, S_ACC_N] = 0
        si[ch, S_ACC_COH] = coh
    elif si[ch, S_ACC_COH] != coh:
        # the integration length changed mid-way: no update until the next boundary
        si[ch, S_ACC_N] = -(1 << 30)
        si[ch, S_ACC_COH] = coh
    sf[ch, F_AIP] += ip
    sf[ch, F_AQP] += qp
    sf[ch, F_AIE] += ie
    sf[ch, F_AQE] += qe
    sf[ch, F_AIL] += il
    sf[ch, F_AQL] += ql
    sf[ch, F_AT] += t_ep
    si[ch, S_ACC_N] += 1
    acc7[0], acc7[1], acc7[2], acc7[3], acc7[4], acc7[5], acc7[6] = (
        sf[ch, F_AIP], sf[ch, F_AQP], sf[ch, F_AIE], sf[ch, F_AQE], sf[ch, F_AIL], sf[ch, F_AQL], sf[ch, F_AT])
    return si[ch, S_ACC_N] == coh


@njit(cache=True)
def _pli_update(ch, cip, cqp, tc, n_acc, sf, prm):
    """Phase-lock indicator LP(I^2 - Q^2) / (LP(I^2 + Q^2) - 2 n) on sums of n unit-noise epochs
    (~ cos 2 dphi) and the lock / unlock timers."""
    a = tc / prm[P_PLI_TAU]
    if a > 1.0:
        a = 1.0
    sf[ch, F_PLI_N] += a * ((cip * cip - cqp * cqp) / n_acc - sf[ch, F_PLI_N])
    sf[ch, F_PLI_D] += a * ((cip * cip + cqp * cqp) / n_acc - 2.0 - sf[ch, F_PLI_D])
    den = sf[ch, F_PLI_D]
    pli = sf[ch, F_PLI_N] / den if den > PLI_MIN_POWER else 0.0     # no signal power: no lock
    sf[ch, F_PLI] = pli
    if pli > prm[P_PLI_LOCK]:
        sf[ch, F_LOCK_T] += tc
        sf[ch, F_UNLOCK_T] = 0.0
    else:
        sf[ch, F_UNLOCK_T] += tc
        sf[ch, F_LOCK_T] = 0.0


@njit(cache=True)
def _bandwidths(ch, mode, weak, tc, sf, si, prm):
    """Noise bandwidths (PLL, FLL, DLL) of this update: mode, FLL SNR scaling, weak-signal and
    stability caps."""
    if mode == MODE_TRACK:
        bn_p, bn_f, bn_d = prm[P_TRK_PLL_BW], prm[P_TRK_FLL_BW], prm[P_TRK_DLL_BW]
    else:
        bn_p, bn_f, bn_d = prm[P_PULL_PLL_BW], prm[P_PULL_FLL_BW], prm[P_PULL_DLL_BW]
    if mode != MODE_TRACK and si[ch, S_CN0_VALID] == 1:
        # the cross-product FLL's noise variance grows like 1/(C/N0 T)^2 at low SNR and then
        # drags the PLL off lock: scale the assist bandwidth by the squared per-update SNR
        # relative to 10 (40 dB-Hz at 1 ms)
        snr = 10.0 ** (sf[ch, F_CN0_DB] / 10.0) * tc / 10.0
        if snr < 1.0:
            bn_f = bn_f * snr * snr
    if weak and bn_p > prm[P_WEAK_PLL_BW]:
        bn_p = prm[P_WEAK_PLL_BW]
    cap = prm[P_MAX_BNT] / tc
    if bn_p > cap:
        bn_p = cap
    if bn_f > cap:
        bn_f = cap
    return bn_p, bn_f, bn_d


@njit(cache=True)
def _loop_update(ch, mode, weak, n_acc, acc7, sf, si, prm, tmp2):
    """Discriminators and loop filters on a complete coherent sum; returns (doppler_hz, u)."""
    cip, cqp, cie, cqe, cil, cql, tc = acc7[0], acc7[1], acc7[2], acc7[3], acc7[4], acc7[5], acc7[6]
    _pli_update(ch, cip, cqp, tc, n_acc, sf, prm)
    ep = costas_disc(cip, cqp)
    ef = 0.0
    if si[ch, S_HAVE_PREV] == 1:
        ef = fll_disc(sf[ch, F_PREV_I], sf[ch, F_PREV_Q], cip, cqp, tc)
    sf[ch, F_PREV_I] = cip
    sf[ch, F_PREV_Q] = cqp
    si[ch, S_HAVE_PREV] = 1
    if prm[P_PEL] > 0.0:
        dtau = dll_disc_dot(cie, cqe, cip, cqp)      # cie, cqe hold E - L
    else:
        dtau = dll_disc(cie, cqe, cil, cql, prm[P_SPACING])
    bn_p, bn_f, bn_d = _bandwidths(ch, mode, weak, tc, sf, si, prm)
    tmp2[0] = sf[ch, F_PLL_X]
    tmp2[1] = sf[ch, F_PLL_Y]
    dopp = pll_fll_update(tmp2, ep, ef, tc, bn_p, bn_f, int(prm[P_PLL_ORDER]))
    sf[ch, F_PLL_X] = tmp2[0]
    sf[ch, F_PLL_Y] = tmp2[1]
    u, z = dll_update(sf[ch, F_DLL_Z], dtau, tc, bn_d, int(prm[P_DLL_ORDER]))
    sf[ch, F_DLL_Z] = z
    sf[ch, F_DOPP] = dopp
    sf[ch, F_DLL_U] = u
    sf[ch, F_DLL_ERR] = dtau
    sf[ch, F_PLL_ERR] = ep
    sf[ch, F_FLL_ERR] = ef
    return dopp, u


@njit(cache=True)
def _epoch_update(ch, o, t_ep, sf, si, hist, prm, tmp2, acc7, bse):
    """Bookkeeping + loops for one channel after one code-period epoch with outputs o[0:6]
    (C/N0, mode, bit sync, coherent sums, then the loops when a sum is complete).

    ``tmp2`` (2) and ``acc7`` (7) are scratch arrays. Returns (doppler_hz, code_rate_corr, flags, bit_soft)."""
    ip, qp = o[0], o[3]
    epoch = si[ch, S_EPOCH]
    _cn0_update(ch, ip * ip + qp * qp, t_ep, sf, si, prm)
    mode, flags = _mode_update(ch, si[ch, S_MODE], t_ep, sf, si, prm)
    bph, fl_bit, bit_soft = _bit_sync(ch, ip, epoch, mode, sf, si, hist, prm, bse)
    flags |= fl_bit
    weak = si[ch, S_CN0_VALID] == 1 and sf[ch, F_CN0_DB] < prm[P_WEAK_DBHZ]
    coh, ref = _coherent_length(ch, bph, weak, si, prm)
    do_upd = _accumulate(ch, o, t_ep, epoch, coh, ref, sf, si, acc7)
    dopp = sf[ch, F_DOPP]
    u = sf[ch, F_DLL_U]
    if do_upd and mode != MODE_LOST:
        flags |= FL_LOOP_UPD
        n_acc = si[ch, S_ACC_N] if coh > 1 else 1
        dopp, u = _loop_update(ch, mode, weak, n_acc, acc7, sf, si, prm, tmp2)
    si[ch, S_MODE] = mode
    si[ch, S_EPOCH] = epoch + 1
    return dopp, u, flags, bit_soft


@njit(cache=True)
def _track_channel(ch, buf, is_complex, buf_start, n_buf, stop_sample, code_ext, pad, active, sample_ptr,
                   code_phase, code_rate, carr_phase, carr_freq, fs, if_hz, tap_off, sigma_arm,
                   sf, si, hist, prm, rec_f, rec_i, n_rec, half_tab, bse):
    """Closed-loop tracking of channel ``ch`` through the buffer (see :func:`track_block`)."""
    n_taps = tap_off.shape[0]
    tap_fix = tap_fixed_point(tap_off)
    acc = np.zeros(2 * n_taps)
    o = np.zeros(6)
    tmp2 = np.zeros(2)
    acc7 = np.zeros(7)
    code_len = prm[P_CODE_LEN]
    chip_rate = prm[P_CHIP_RATE]
    carrier = prm[P_CARRIER]
    max_rows = rec_f.shape[1]
    unit = unit_chips(code_ext[ch])
    while active[ch] and n_rec[ch] < max_rows:
        dp = code_rate[ch] / fs
        n = period_samples(code_phase[ch], dp, code_len)
        off = sample_ptr[ch] - buf_start
        if off < 0 or off + n > n_buf or sample_ptr[ch] + n > stop_sample:
            break
        cp_fix0, cstep, ph0, phstep = nco_fixed_point(code_phase[ch], pad, dp, carr_phase[ch], carr_freq[ch], fs)
        if prm[P_PEL] > 0.0:
            integrate_pel(buf, is_complex, off, n, code_ext[ch], unit, half_tab[ch], cp_fix0, cstep, ph0, phstep,
                          tap_fix, acc)
        else:
            integrate_channel(buf, is_complex, off, n, code_ext[ch], cp_fix0, cstep, ph0, phstep,
                              tap_fix, COS_LUT, SIN_LUT, acc)
        scale = 1.0 / (sigma_arm[ch] * np.sqrt(n))
        for t in range(3):
            o[t] = acc[t] * scale
            o[3 + t] = acc[n_taps + t] * scale
        r = n_rec[ch]
        rec_i[ch, r, RI_PTR] = sample_ptr[ch]
        rec_i[ch, r, RI_N] = n
        rec_i[ch, r, RI_EPOCH] = si[ch, S_EPOCH]
        rec_f[ch, r, R_CODE_PHASE] = code_phase[ch]
        rec_f[ch, r, R_CODE_RATE] = code_rate[ch]
        rec_f[ch, r, R_CARR_ACC] = sf[ch, F_CARR_ACC]
        rec_f[ch, r, R_DOPP] = carr_freq[ch] - if_hz
        # advance NCOs exactly (as the correlator bank does)
        code_phase[ch] = code_phase[ch] + n * dp - code_len
        ph = carr_phase[ch] + n * (carr_freq[ch] / fs)
        carr_phase[ch] = ph - np.floor(ph)
        sf[ch, F_CARR_ACC] += n * ((carr_freq[ch] - if_hz) / fs)
        sample_ptr[ch] = sample_ptr[ch] + n
        t_ep = n / fs
        dopp, u, flags, bit_soft = _epoch_update(ch, o, t_ep, sf, si, hist, prm, tmp2, acc7, bse)
        carr_freq[ch] = if_hz + dopp
        code_rate[ch] = chip_rate * (1.0 + dopp / carrier) + u
        rec_f[ch, r, R_IP] = o[0]
        rec_f[ch, r, R_QP] = o[3]
        rec_f[ch, r, R_IE] = o[1]
        rec_f[ch, r, R_QE] = o[4]
        rec_f[ch, r, R_IL] = o[2]
        rec_f[ch, r, R_QL] = o[5]
        rec_f[ch, r, R_CN0] = sf[ch, F_CN0_DB] if si[ch, S_CN0_VALID] else np.nan
        rec_f[ch, r, R_PLI] = sf[ch, F_PLI]
        rec_f[ch, r, R_DLL_ERR] = sf[ch, F_DLL_ERR]
        rec_f[ch, r, R_PLL_ERR] = sf[ch, F_PLL_ERR]
        rec_f[ch, r, R_FLL_ERR] = sf[ch, F_FLL_ERR]
        rec_f[ch, r, R_BIT] = bit_soft
        rec_i[ch, r, RI_MODE] = si[ch, S_MODE]
        rec_i[ch, r, RI_FLAGS] = flags
        n_rec[ch] = r + 1
        if si[ch, S_MODE] == MODE_LOST:
            active[ch] = False


@njit(cache=True, nogil=True)
def track_block(buf, is_complex, buf_start, n_buf, stop_sample, code_ext, pad, active, sample_ptr,
                 code_phase, code_rate, carr_phase, carr_freq, fs, if_hz, tap_off, sigma_arm,
                 sf, si, hist, prm, rec_f, rec_i, n_rec, half_tab, bse):
    """Closed-loop tracking of every active channel over the buffer (see module docstring).

    A channel stops when its next period would pass the buffer end or ``stop_sample``, or when its
    record rows are full; ``n_rec[ch]`` counts the rows written (appended after existing ones)."""
    for ch in range(code_phase.shape[0]):
        _track_channel(ch, buf, is_complex, buf_start, n_buf, stop_sample, code_ext, pad, active, sample_ptr,
                       code_phase, code_rate, carr_phase, carr_freq, fs, if_hz, tap_off, sigma_arm,
                       sf, si, hist, prm, rec_f, rec_i, n_rec, half_tab, bse)


@njit(cache=True, parallel=True, nogil=True)
def track_block_parallel(buf, is_complex, buf_start, n_buf, stop_sample, code_ext, pad, active, sample_ptr,
                     code_phase, code_rate, carr_phase, carr_freq, fs, if_hz, tap_off, sigma_arm,
                     sf, si, hist, prm, rec_f, rec_i, n_rec, half_tab, bse):
    """:func:`track_block` with channels spread over threads (channels are independent). The loop runs
    over the channels active at the start of the block only: numba gives each thread an equal share of
    the loop's range, and the idle channels of an all-in-view receiver (a block of them after the
    tracked ones) would otherwise leave one thread all the work."""
    act = np.flatnonzero(active)
    for k in prange(act.shape[0]):
        ch = act[k]
        _track_channel(ch, buf, is_complex, buf_start, n_buf, stop_sample, code_ext, pad, active, sample_ptr,
                       code_phase, code_rate, carr_phase, carr_freq, fs, if_hz, tap_off, sigma_arm,
                       sf, si, hist, prm, rec_f, rec_i, n_rec, half_tab, bse)
