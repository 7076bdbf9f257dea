"""Compiled kernels of the per-channel I/Q prefilters (Zhao et al. 2014, §2.2–2.3): CKF, UKF and RACKF.

One call updates one channel (:func:`channel_update`, with the bank's arrays; the receiver's epoch
chain calls it, :func:`channel_settings`) or steps all channels (:func:`bank_epoch`) of a bank held in
two packed buffers (layout and the model: ``prefilter_model``): the measurement update
of the interval just integrated (eqs. 9–17, or Algorithm 1 for RACKF), then the time update (eqs.
4–8, in the closed form x <- Phi x, P <- Phi P Phi^T + Q of the linear dynamics) to the start of the
next interval.  The measurement update always *redraws* points from the predicted covariance.

Data bit D: per channel, a known bit (+1/-1, i.e. wiped) or 0 = unknown.
Unknown bits are decided from the data (decision-directed, "2-quadrant"
formulation): D = sign(z . h(x_pred; D=+1)), the sign of the projection of the
six measured outputs onto the predicted noise-free outputs — the ML bit given
the predicted state.  Like a Costas loop this is insensitive to 180° phase
jumps of the data and costs a squaring loss at low C/N0.

Filters
-------
* CKF: 2n = 10 equally weighted points x + sqrt(n) S e_j (Arasaratnam & Haykin).
* UKF: 2n+1 = 11 scaled sigma points (Wan & van der Merwe), defaults
  alpha = 0.5, beta = 2, kappa = 0 (lambda = alpha^2 (n+kappa) - n = -3.75).
* RACKF (Algorithm 1): on correction epochs (every ``correction_period``
  epochs, default 50 = 50 ms): points (eq. 40, theta = 1) -> z_hat, P_zz
  (eqs. 11–13) -> Huber equivalent noise R_bar (eqs. 18–23) -> adaptive factor
  theta (eq. 37) -> if theta < 1 redraw points with sqrt(1/theta) S (eq. 40)
  and redo eqs. 11, 12, 18 -> update (14–17) with P/theta as the prior
  covariance.  ``robust_mode="every"`` (default) applies the cheap Huber step
  at every epoch and the adaptive factor on correction epochs;
  ``robust_mode="period"`` (the paper's scheme) uses a plain CKF update between
  correction epochs.

  Deviations, measured on the correlator-level simulator at 20 dB-Hz (see
  docs/prefilter.md): (1) ``adaptive_stat``: the paper estimates tr(P^_zz) from
  the current epoch alone, r^T r (eq. 38; ``"epoch"``).  With six outputs at an
  SNR of 0.1 per epoch that statistic is almost pure noise: theta < 1 on ~40 %
  of correction epochs, and with measurement outliers r^T r grows like the
  square of the outlier while the Huber-inflated tr(P_zz) grows only linearly,
  so theta collapses and P/theta throws the filter out of lock.  The default
  ``"mean"`` uses the bit-wiped, Huber-winsorised innovations accumulated over
  the correction period, tr(P^_zz) = |sum_k D_k r_k / gamma_k|^2 compared with
  sum_k tr(P_zz,k) (both sums over the window), and applies eq. 37 only when
  the excess is significant (chi-square margin ``adapt_ksig`` sigma, 6 degrees
  of freedom); ``"window"`` uses the windowed winsorised energy instead.
  (2) A held measurement-noise scale ``lam`` (R <- lam R for the next period):
  the part of the window's innovation energy that no state error can explain
  (more than tr(P_zz0) + 2 |z_hat|^2 per epoch) is attributed to measurement
  noise when significant — the robust part's answer to a sustained noise
  increase (noise x20), where the per-output Huber factor |r'|/c alone inflates
  the variance ~10x for a 400x variance increase.
Huber equivalent noise (Zhao et al. 2014, eqs. 20–21): with standardised residuals
r'_i = r_i / sqrt((P_zz)_ii) and gamma_i = max(1, |r'_i| / c), the equivalent
weights shrink the weight of element (i, j) by 1/gamma_ij with gamma_ii =
gamma_i and gamma_ij = max(gamma_i, gamma_j) (the off-diagonal rule); applied
to the correlated R this is R_bar_ij = R_ij gamma_ij.  The max rule does not
guarantee positive definiteness for correlated taps; when the Cholesky factor
of R_bar fails the bifactor form R_bar_ij = R_ij sqrt(gamma_i gamma_j) (always
PD) is used instead.

Guards: Cholesky with a pivot floor (relative 1e-12) and explicit
symmetrisation; theta >= theta_min (default 1e-3); the phase standard deviation
is capped at ``phi_sigma_max`` (default 0.8 rad) after each prediction — beyond
~1 rad the Gaussian picture of a 2pi-periodic measurement breaks down and the
filter falls into a non-coherent "false lock" (observed at 20 dB-Hz after any
covariance inflation; the cap applies equally to CKF, UKF and RACKF).  A capped
phase is known only modulo 2pi, so the cap also zeroes the phase's covariances
with the other states: otherwise the phase-frequency correlation built up while
coasting (rho -> 1) turns the re-lock's phase correction into a frequency jump
(0.3-0.9 Hz per channel after the paper-highdyn noise burst, docs/ultratight.md);
a channel whose state or
covariance becomes non-finite or whose covariance exceeds the blow-up limits
is flagged (``diverged``), counted (``n_resets``) and re-initialised to its
initial state — the bank never returns NaN.

All kernels work on preallocated arrays (no allocation per epoch).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ultratight.fusion.channel.prefilter_model import (
    ACC_COUNT, ACC_E_EXPLAINED, ACC_INNOV_SUM, ACC_LAM, ACC_R_FULL, ACC_R_WINSOR, ACC_TR_PZZ, ACC_TR_R, ADAPT_EPOCH,
    ADAPT_MEAN, CNT_CORRECTION_PERIOD, CNT_EPOCH, FLAG_CHOL_GUARD, FLAG_DIVERGED, FLAG_ROBUST, FLAG_THETA, FSEG_ACC,
    FSEG_END, FSEG_INNOV, FSEG_NIS, FSEG_P, FSEG_P0, FSEG_PHI, FSEG_PRM, FSEG_QD, FSEG_R, FSEG_THETA, FSEG_W1, FSEG_W2,
    FSEG_X, FSEG_X0, FSEG_XPOST, IA, IE, IF, IL, IP, IPHI, IPRM_ADAPTIVE_STAT, IPRM_DO_CORRECTION, IPRM_ROBUST_EVERY,
    ISEG_ACTIVE, ISEG_COUNTERS, ISEG_FLAGS, ISEG_IPRM, ISEG_RESETS, ITAU, KIND_RACKF, KIND_UKF, N_IPRM, N_PTS, N_W1,
    N_W2, NACC, NX, NZ, PRM_ADAPT_KSIG, PRM_BETA, PRM_DHALF, PRM_HUBER_C, PRM_MIN_WINDOW, PRM_P_LIMITS, PRM_PHI_VAR_MAX,
    PRM_T, PRM_THETA_MIN, PRM_UT_SCALE, PRM_UT_WC0, PRM_UT_WI, PRM_UT_WM0, QE, QL, QP, W1_GAMMA, W1_HX, W1_PTS, W1_R,
    W1_TMPV, W1_Y, W1_ZHAT, W1_ZP, W2_K, W2_LZ, W2_PXZ, W2_PZZ, W2_PZZ0, W2_RBAR, W2_S, W2_TMPM, packed_float_offsets,
    packed_int_offsets,
)

# The max rule of eq. 21 is positive definite only for moderate factors (with the P/E/L taps
# 0.5-correlated, a single tap's factor g gives det ~ g (1 - g/2)): near g = 2 it is PD but
# nearly singular, and P_zz = P_zz0 + R_bar inherits a near-null direction -> a gain that moved
# the code state by ~20 sigma in one epoch (paper-highdyn seed 1, 14.59 s).  Squared Cholesky
# pivots below this fraction of their diagonal element switch to the bifactor form (R itself:
# >= 0.67 for 1 chip spacing).
RB_REL_PIVOT_MIN = 0.1

CHOL_OK, CHOL_FLOORED, CHOL_FAILED = 0, 1, 2     # status of the guarded Cholesky factorisation


@njit(cache=True, inline="always")
def _tri(t):
    a = abs(t)
    return 1.0 - a if a < 1.0 else 0.0


@njit(cache=True)
def _h(x, D, T, beta, dhalf, out):
    """Eq. 3 for one state vector x -> out[6] (checked against the numpy reference
    ``prefilter_model.measurement_model`` by the tests)."""
    s = 0.5 * x[IF] * T
    if abs(s) > 1e-6:
        snc = math.sin(s) / s
    else:
        snc = 1.0 - s * s / 6.0
    amp = x[IA] * D * snc
    ang = s + x[IPHI]
    c = math.cos(ang)
    sn = math.sin(ang)
    tau = x[ITAU] + beta * s
    rp = amp * _tri(tau)
    re = amp * _tri(tau - dhalf)
    rl = amp * _tri(tau + dhalf)
    out[IP] = rp * c
    out[IE] = re * c
    out[IL] = rl * c
    out[QP] = rp * sn
    out[QE] = re * sn
    out[QL] = rl * sn


@njit(cache=True)
def _chol(A, L, n):
    """Guarded Cholesky A = L L^T (lower). Returns CHOL_OK, CHOL_FLOORED or CHOL_FAILED."""
    scale = 0.0
    for i in range(n):
        d = A[i, i]
        if not np.isfinite(d):
            return CHOL_FAILED
        if d > scale:
            scale = d
    if scale <= 0.0:
        scale = 1.0
    floor = 1e-12 * scale
    status = CHOL_OK
    for j in range(n):
        s = A[j, j]
        for k in range(j):
            s -= L[j, k] * L[j, k]
        if not (s > floor):
            if not np.isfinite(s):
                return CHOL_FAILED
            s = floor
            status = CHOL_FLOORED
        d = math.sqrt(s)
        L[j, j] = d
        for i in range(j + 1, n):
            t = A[i, j]
            for k in range(j):
                t -= L[i, k] * L[j, k]
            L[i, j] = t / d
        for i in range(j):
            L[i, j] = 0.0
    return status


@njit(cache=True)
def _chol_strict(A, L, n, rel_pivot_min=0.0):
    """Cholesky without floor: False if A is not (numerically) positive definite, or if a
    squared pivot falls below ``rel_pivot_min`` times its diagonal element (ill-conditioned)."""
    for j in range(n):
        s = A[j, j]
        for k in range(j):
            s -= L[j, k] * L[j, k]
        if not (s > rel_pivot_min * A[j, j]) or not (s > 0.0):
            return False
        d = math.sqrt(s)
        L[j, j] = d
        for i in range(j + 1, n):
            t = A[i, j]
            for k in range(j):
                t -= L[i, k] * L[j, k]
            L[i, j] = t / d
    return True


@njit(cache=True)
def _moments(xc, S, scale, kind, prm, D, T, beta, dhalf, pts, zp, zhat, Pzz0, Pxz):
    """Draw points around xc with spread scale*S, push through h, return moments (no R)."""
    if kind == KIND_UKF:  # centre + 2n points
        npts = N_PTS
        wm0 = prm[PRM_UT_WM0]
        wc0 = prm[PRM_UT_WC0]
        wi = prm[PRM_UT_WI]
        for i in range(NX):
            pts[0, i] = xc[i]
        for j in range(NX):
            for i in range(NX):
                d = scale * S[i, j]
                pts[1 + j, i] = xc[i] + d
                pts[1 + NX + j, i] = xc[i] - d
    else:          # CKF and RACKF: 2n cubature points
        npts = 2 * NX
        wm0 = 1.0 / npts
        wc0 = wm0
        wi = wm0
        for j in range(NX):
            for i in range(NX):
                d = scale * S[i, j]
                pts[j, i] = xc[i] + d
                pts[NX + j, i] = xc[i] - d
    for p in range(npts):
        _h(pts[p], D, T, beta, dhalf, zp[p])
    for m in range(NZ):
        acc = wm0 * zp[0, m]
        for p in range(1, npts):
            acc += wi * zp[p, m]
        zhat[m] = acc
    for a in range(NZ):
        for b in range(NZ):
            Pzz0[a, b] = 0.0
        for i in range(NX):
            Pxz[i, a] = 0.0
    for p in range(npts):
        w = wc0 if p == 0 else wi
        for a in range(NZ):
            da = w * (zp[p, a] - zhat[a])
            for b in range(a, NZ):
                Pzz0[a, b] += da * (zp[p, b] - zhat[b])
            for i in range(NX):
                Pxz[i, a] += (pts[p, i] - xc[i]) * da
    for a in range(NZ):
        for b in range(a + 1, NZ):
            Pzz0[b, a] = Pzz0[a, b]


@njit(cache=True)
def _gain_update(xc, Pc, Pprior_scale, Pzz, Pxz, r, Lz, K, y):
    """x += K r, P = P/theta - K Pzz K^T with K = Pxz Pzz^-1. Returns (NIS, chol status)."""
    st = _chol(Pzz, Lz, NZ)
    if st == CHOL_FAILED:
        return np.nan, CHOL_FAILED
    # y = Lz^-1 r  (NIS = |y|^2)
    nis = 0.0
    for a in range(NZ):
        t = r[a]
        for b in range(a):
            t -= Lz[a, b] * y[b]
        y[a] = t / Lz[a, a]
        nis += y[a] * y[a]
    # K^T = Pzz^-1 Pxz^T : solve Lz Lz^T K^T = Pxz^T column by column (per state)
    for i in range(NX):
        # forward
        for a in range(NZ):
            t = Pxz[i, a]
            for b in range(a):
                t -= Lz[a, b] * K[i, b]
            K[i, a] = t / Lz[a, a]
        # backward
        for a in range(NZ - 1, -1, -1):
            t = K[i, a]
            for b in range(a + 1, NZ):
                t -= Lz[b, a] * K[i, b]
            K[i, a] = t / Lz[a, a]
    for i in range(NX):
        acc = 0.0
        for a in range(NZ):
            acc += K[i, a] * r[a]
        xc[i] += acc
    # P = P/theta - K Pxz^T  (= K Pzz K^T)
    for i in range(NX):
        for j in range(i, NX):
            acc = 0.0
            for a in range(NZ):
                acc += K[i, a] * Pxz[j, a]
            v = 0.5 * (Pc[i, j] + Pc[j, i]) * Pprior_scale - acc
            Pc[i, j] = v
            Pc[j, i] = v
    return nis, st


@njit(cache=True)
def _predict(xc, Pc, Phi, Qd, tmpv, tmpm):
    for i in range(NX):
        acc = 0.0
        for k in range(NX):
            acc += Phi[i, k] * xc[k]
        tmpv[i] = acc
    for i in range(NX):
        xc[i] = tmpv[i]
    for i in range(NX):
        for j in range(NX):
            acc = 0.0
            for k in range(NX):
                acc += Phi[i, k] * Pc[k, j]
            tmpm[i, j] = acc
    for i in range(NX):
        for j in range(i, NX):
            acc = Qd[i, j]
            for k in range(NX):
                acc += tmpm[i, k] * Phi[j, k]
            Pc[i, j] = acc
            Pc[j, i] = acc


@njit(cache=True)
def bank_epoch(kind, fbuf, ibuf, z, bits, rscale):
    """One epoch of a packed bank, bookkeeping included: sets the correction flag from the epoch
    counter (every ``correction_period`` epochs), steps, counts divergences in ``n_resets`` and
    advances the counter. Returns the status of :func:`bank_step`."""
    n = z.shape[0]
    io = packed_int_offsets(n)
    epoch = ibuf[io[ISEG_COUNTERS] + CNT_EPOCH]
    period = ibuf[io[ISEG_COUNTERS] + CNT_CORRECTION_PERIOD]
    ibuf[io[ISEG_IPRM] + IPRM_DO_CORRECTION] = 1 if epoch % period == 0 else 0
    st = bank_step(kind, fbuf, ibuf, z, bits, rscale)
    if st < 0:
        return st
    ibuf[io[ISEG_COUNTERS] + CNT_EPOCH] = epoch + 1
    for c in range(n):
        if (ibuf[io[ISEG_FLAGS] + c] & FLAG_DIVERGED) != 0:
            ibuf[io[ISEG_RESETS] + c] += 1
    return st


@njit(cache=True)
def _views(fbuf, ibuf, n):
    """The bank's arrays as views of its packed buffers (segments ``FSEG_*`` / ``ISEG_*`` of
    :func:`packed_float_offsets` / :func:`packed_int_offsets`)."""
    o = packed_float_offsets(n)
    x = fbuf[o[FSEG_X]:o[FSEG_P]].reshape((n, NX))
    P = fbuf[o[FSEG_P]:o[FSEG_XPOST]].reshape((n, NX, NX))
    xpost = fbuf[o[FSEG_XPOST]:o[FSEG_X0]].reshape((n, NX))
    x0 = fbuf[o[FSEG_X0]:o[FSEG_P0]].reshape((n, NX))
    P0 = fbuf[o[FSEG_P0]:o[FSEG_INNOV]].reshape((n, NX, NX))
    innov = fbuf[o[FSEG_INNOV]:o[FSEG_NIS]].reshape((n, NZ))
    nis = fbuf[o[FSEG_NIS]:o[FSEG_THETA]]
    theta = fbuf[o[FSEG_THETA]:o[FSEG_ACC]]
    acc = fbuf[o[FSEG_ACC]:o[FSEG_PHI]].reshape((n, NACC))
    Phi = fbuf[o[FSEG_PHI]:o[FSEG_QD]].reshape((NX, NX))
    Qd = fbuf[o[FSEG_QD]:o[FSEG_R]].reshape((NX, NX))
    R = fbuf[o[FSEG_R]:o[FSEG_PRM]].reshape((NZ, NZ))
    prm = fbuf[o[FSEG_PRM]:o[FSEG_W1]]
    W1 = fbuf[o[FSEG_W1]:o[FSEG_W2]].reshape((N_W1, NZ))
    W2 = fbuf[o[FSEG_W2]:o[FSEG_END]].reshape((N_W2, NZ, NZ))
    io = packed_int_offsets(n)
    flags = ibuf[io[ISEG_FLAGS]:io[ISEG_ACTIVE]]
    active = ibuf[io[ISEG_ACTIVE]:io[ISEG_IPRM]]
    iprm = ibuf[io[ISEG_IPRM]:io[ISEG_IPRM] + N_IPRM]
    return x, P, xpost, x0, P0, innov, nis, theta, acc, Phi, Qd, R, prm, W1, W2, flags, active, iprm


@njit(cache=True)
def bank_step(kind, fbuf, ibuf, z, bits, rscale):
    """One epoch of all channels of a packed bank, without the bookkeeping of :func:`bank_epoch`
    (the correction flag ``iprm[IPRM_DO_CORRECTION]`` is the caller's); few arguments = low dispatch
    cost. Returns the status of :func:`_bank_step`."""
    x, P, xpost, x0, P0, innov, nis, theta, acc, Phi, Qd, R, prm, W1, W2, flags, active, iprm = \
        _views(fbuf, ibuf, z.shape[0])
    return _bank_step(kind, x, P, xpost, x0, P0, Phi, Qd, R, z, bits, rscale, active, prm, iprm,
                      innov, nis, theta, flags, W1, W2, acc)


@njit(cache=True)
def channel_settings(ibuf, n):
    """A packed bank's settings as one channel's epoch needs them: ``(correction period, robust every
    epoch, adaptive statistic, offset of the per-channel reset counts in ibuf)``. A channel's epoch (the
    receiver's compiled chain, ``receiver.deep.epochs.epoch_channel``) is: inputs checked
    (:func:`inputs_finite`, active channels only), :func:`channel_update` with ``do_corr = epoch % period
    == 0``, and the channel's reset count raised when the update flags it diverged."""
    io = packed_int_offsets(n)
    return (ibuf[io[ISEG_COUNTERS] + CNT_CORRECTION_PERIOD], ibuf[io[ISEG_IPRM] + IPRM_ROBUST_EVERY] != 0,
            ibuf[io[ISEG_IPRM] + IPRM_ADAPTIVE_STAT], io[ISEG_RESETS])


@njit(cache=True)
def inputs_finite(c, z, bits):
    """Channel ``c``'s six correlator outputs and its data bit are finite."""
    for m in range(NZ):
        if not np.isfinite(z[c, m]):
            return False
    return bool(np.isfinite(bits[c]))


@njit(cache=True)
def channel_update(kind, c, x, P, xpost, x0, P0, Phi, Qd, R, z, bits, rscale, active, prm, do_corr, robust_every,
                   win_mode, innov, nis, theta, flags, W1, W2, acc):
    """One epoch of channel ``c`` (the loop body of :func:`_bank_step`; touches only row ``c`` and the
    work arrays ``W1``/``W2``, so channels with work arrays of their own may run concurrently).
    ``do_corr``, ``robust_every``, ``win_mode``: the entries of ``iprm`` (see :func:`_bank_step`).

    Kept as one kernel because the steps of an update share the channel's live values (the bit
    decision, the point spread, the prior scale 1/theta, the noise scale lam, the Huber factors, the
    Cholesky status) and its row views: split into helpers they would be passed back and forth on
    every call, and this body runs once per channel per epoch inside the receiver's compiled loop."""
    T = prm[PRM_T]
    beta = prm[PRM_BETA]
    dhalf = prm[PRM_DHALF]
    hc = prm[PRM_HUBER_C]
    theta_min = prm[PRM_THETA_MIN]
    ut_scale = prm[PRM_UT_SCALE]
    windowed = win_mode != ADAPT_EPOCH
    ksig = prm[PRM_ADAPT_KSIG]
    min_win = prm[PRM_MIN_WINDOW]
    phi_var_max = prm[PRM_PHI_VAR_MAX]
    plim = prm[PRM_P_LIMITS:PRM_P_LIMITS + NX]
    # work views
    pts = W1[W1_PTS:W1_PTS + N_PTS, 0:NX]
    zp = W1[W1_ZP:W1_ZP + N_PTS, :]
    zhat = W1[W1_ZHAT, :]
    r = W1[W1_R, :]
    y = W1[W1_Y, :]
    gam = W1[W1_GAMMA, :]
    hx = W1[W1_HX, :]
    tmpv = W1[W1_TMPV, 0:NX]
    S = W2[W2_S, 0:NX, 0:NX]
    Pzz0 = W2[W2_PZZ0]
    Pzz = W2[W2_PZZ]
    Pxz = W2[W2_PXZ, 0:NX, :]
    Lz = W2[W2_LZ]
    K = W2[W2_K, 0:NX, :]
    Rb = W2[W2_RBAR]
    tmpm = W2[W2_TMPM, 0:NX, 0:NX]
    flags[c] = 0
    theta[c] = 1.0
    if not active[c]:
        nis[c] = np.nan
        for m in range(NZ):
            innov[c, m] = np.nan
        return
    xc = x[c]
    Pc = P[c]
    rs = rscale[c]           # R scale of this epoch (1 but for a filter-R noise event)
    # data bit
    D = bits[c]
    if D == 0.0:
        _h(xc, 1.0, T, beta, dhalf, hx)
        proj = 0.0
        for m in range(NZ):
            proj += z[c, m] * hx[m]
        D = -1.0 if proj < 0.0 else 1.0
    # eq. 9: factor the predicted covariance
    for i in range(NX):
        for j in range(i + 1, NX):
            v = 0.5 * (Pc[i, j] + Pc[j, i])
            Pc[i, j] = v
            Pc[j, i] = v
    st = _chol(Pc, S, NX)
    if st == CHOL_FLOORED:
        flags[c] |= FLAG_CHOL_GUARD
    bad = st == CHOL_FAILED
    if not bad:
        scale = ut_scale if kind == KIND_UKF else math.sqrt(NX)
        # eqs. 10-14 (eq. 40 with theta = 1)
        _moments(xc, S, scale, kind, prm, D, T, beta, dhalf, pts, zp, zhat, Pzz0, Pxz)
        for m in range(NZ):
            r[m] = z[c, m] - zhat[m]
        pscale = 1.0
        robust = kind == KIND_RACKF and (do_corr or robust_every)
        if kind == KIND_RACKF:
            lam = acc[c, ACC_LAM]    # measurement-noise scale held over this period
            if lam < 1.0:
                lam = 1.0
            lam *= rs                # (a filter-R noise event: receiver.dsp.burst)
            # eqs. 20-23: standardised residuals against P_zz of eq. 13 (with lam R)
            any_out = False
            for m in range(NZ):
                sr = math.sqrt(Pzz0[m, m] + lam * R[m, m])
                g = abs(r[m]) / (hc * sr)
                if g > 1.0:
                    any_out = True
                else:
                    g = 1.0
                gam[m] = g
            if not robust:
                any_out = False
            if any_out:
                flags[c] |= FLAG_ROBUST
                for a in range(NZ):
                    for b in range(NZ):
                        ga = gam[a] if gam[a] > gam[b] else gam[b]
                        Rb[a, b] = lam * R[a, b] * ga
                if not _chol_strict(Rb, Lz, NZ, RB_REL_PIVOT_MIN):
                    for a in range(NZ):
                        for b in range(NZ):
                            Rb[a, b] = lam * R[a, b] * math.sqrt(gam[a] * gam[b])
            else:
                for a in range(NZ):
                    for b in range(NZ):
                        Rb[a, b] = lam * R[a, b]
            # eq. 18
            trp = 0.0
            rr = 0.0
            for a in range(NZ):
                trp += Pzz0[a, a] + Rb[a, a]
                if windowed:
                    rw = r[a] / gam[a]       # Huber-winsorised residual
                    rr += rw * rw
                else:
                    rr += r[a] * r[a]
            if windowed:
                e_full = 0.0
                e_expl = 0.0
                trr = 0.0
                for a in range(NZ):
                    e_full += r[a] * r[a]
                    e_expl += Pzz0[a, a] + 2.0 * zhat[a] * zhat[a]
                    trr += rs * R[a, a]
                    acc[c, ACC_INNOV_SUM + a] += D * r[a] / gam[a]   # bit-wiped, winsorised innovation sum
                acc[c, ACC_TR_PZZ] += trp
                acc[c, ACC_R_WINSOR] += rr
                acc[c, ACC_R_FULL] += e_full
                acc[c, ACC_E_EXPLAINED] += e_expl
                acc[c, ACC_TR_R] += trr
                acc[c, ACC_COUNT] += 1.0
                if do_corr:
                    cnt = acc[c, ACC_COUNT]
                    trp = acc[c, ACC_TR_PZZ]
                    if win_mode == ADAPT_MEAN:
                        # energy of the window-mean innovation, scaled to a sum of epochs
                        rr = 0.0
                        for a in range(NZ):
                            rr += acc[c, ACC_INNOV_SUM + a] * acc[c, ACC_INNOV_SUM + a]
                    else:
                        rr = acc[c, ACC_R_WINSOR]
                    # significance margin of a chi-square sum with 6 N degrees of freedom
                    # (the window-mean statistic |sum r|^2 has only 6 degrees of freedom)
                    marg = 1.0 + ksig * math.sqrt(2.0 / (NZ * cnt))
                    marg_th = 1.0 + ksig * math.sqrt(2.0 / NZ) if win_mode == ADAPT_MEAN else marg
                    if cnt < min_win:
                        rr = 0.0                 # too few epochs: no adaptation
                    elif rr <= marg_th * trp:
                        rr = 0.0
                    # residual energy no state error can explain -> measurement noise scale
                    lam_new = (acc[c, ACC_R_FULL] - acc[c, ACC_E_EXPLAINED]) / acc[c, ACC_TR_R]
                    if cnt >= min_win and lam_new > marg:
                        acc[c, ACC_LAM] = lam_new
                    else:
                        acc[c, ACC_LAM] = 1.0
                    for a in range(NACC):
                        if a != ACC_LAM:
                            acc[c, a] = 0.0
            # eqs. 37-38: adaptive factor (correction epochs only)
            if do_corr and rr > trp:
                th = trp / rr
                if th < theta_min:
                    th = theta_min
                theta[c] = th
                flags[c] |= FLAG_THETA
                pscale = 1.0 / th
                # eq. 40: redraw with sqrt(1/theta) S, redo 11, 12, 18
                _moments(xc, S, scale * math.sqrt(pscale), kind, prm, D, T, beta, dhalf,
                         pts, zp, zhat, Pzz0, Pxz)
                for m in range(NZ):
                    r[m] = z[c, m] - zhat[m]
            for a in range(NZ):
                for b in range(NZ):
                    Pzz[a, b] = Pzz0[a, b] + Rb[a, b]
        else:
            for a in range(NZ):
                for b in range(NZ):
                    Pzz[a, b] = Pzz0[a, b] + rs * R[a, b]
        for m in range(NZ):
            innov[c, m] = r[m]
        # eqs. 15-17
        nv, st2 = _gain_update(xc, Pc, pscale, Pzz, Pxz, r, Lz, K, y)
        nis[c] = nv
        if st2 == CHOL_FLOORED:
            flags[c] |= FLAG_CHOL_GUARD
        bad = st2 == CHOL_FAILED
    if not bad:
        for i in range(NX):
            xpost[c, i] = xc[i]
        # eqs. 4-8 (linear dynamics: closed form of the cubature time update)
        _predict(xc, Pc, Phi, Qd, tmpv, tmpm)
        # phase-uncertainty cap: beyond ~1 rad the Gaussian/cubature picture of a 2pi-periodic
        # measurement breaks down (the filter would fall into a non-coherent false lock);
        # the phase sigma stays <= phi_sigma_max and, being known only modulo 2 pi, the phase
        # is decorrelated from the other states (a re-lock corrects phase, not frequency)
        vphi = Pc[IPHI, IPHI]
        if vphi > phi_var_max:
            for j in range(NX):
                Pc[IPHI, j] = 0.0
                Pc[j, IPHI] = 0.0
            Pc[IPHI, IPHI] = phi_var_max
        for i in range(NX):
            if not np.isfinite(xc[i]):
                bad = True
            d = Pc[i, i]
            if not (d >= 0.0 and d <= plim[i]):
                bad = True
            for j in range(NX):
                if not np.isfinite(Pc[i, j]):
                    bad = True
    if bad:
        flags[c] |= FLAG_DIVERGED
        for i in range(NX):
            xc[i] = x0[c, i]
            xpost[c, i] = x0[c, i]
            for j in range(NX):
                Pc[i, j] = P0[c, i, j]
        nis[c] = np.nan
        for m in range(NZ):
            innov[c, m] = np.nan


@njit(cache=True)
def _bank_step(kind, x, P, xpost, x0, P0, Phi, Qd, R, z, bits, rscale, active, prm, iprm,
               innov, nis, theta, flags, W1, W2, acc):
    """One epoch for all channels. Returns -1 - ch if z of an active channel is non-finite.

    prm (N_PRM): the float parameters, entries ``PRM_*``; iprm (N_IPRM): the integer ones,
    entries ``IPRM_*`` (correction epoch, robust mode, adaptive statistic); acc (n_ch, NACC):
    per-channel sums over the correction period (windowed statistics) and the held
    measurement-noise scale lam, columns ``ACC_*``. W1 (N_W1, 6) and W2 (N_W2, 6, 6) are work
    arrays (rows ``W1_*`` / ``W2_*``; no allocation per epoch); layouts in ``prefilter_model``.
    """
    n_ch = x.shape[0]
    for c in range(n_ch):
        if active[c]:
            for m in range(NZ):
                if not np.isfinite(z[c, m]):
                    return -1 - c
            if not np.isfinite(bits[c]):
                return -1 - c
    for c in range(n_ch):
        channel_update(kind, c, x, P, xpost, x0, P0, Phi, Qd, R, z, bits, rscale, active, prm,
                       iprm[IPRM_DO_CORRECTION] != 0, iprm[IPRM_ROBUST_EVERY] != 0, iprm[IPRM_ADAPTIVE_STAT],
                       innov, nis, theta, flags, W1, W2, acc)
    return 0

