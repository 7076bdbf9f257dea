"""PB-KF-UTC baseline (Zhao et al. 2014, §3 "method 1"): discriminators -> linear KF per channel.

The single-loop cascaded ultra-tight baseline does not feed raw I/Q to a nonlinear filter:
each epoch three classical discriminators are formed from the correlator outputs and a
*linear* Kalman filter per channel estimates the code/carrier tracking errors from them.

Discriminators (z = [I_P, I_E, I_L, Q_P, Q_E, Q_L], bits wiped when known):

* DLL — normalised early-minus-late envelope:
  ``y_tau = (2 - D)/2 * (|E| - |L|) / (|E| + |L|)`` chips (D = early-late spacing); with the
  conventions of ``ultratight.fusion.channel.prefilter`` (dtau = true - replica, early tap sees
  R(dtau - D/2)) this equals dtau for |dtau| < D/2 on the ideal triangle.
* PLL — ``atan2(Q_P, I_P)`` when the data bit is known (wiped), Costas ``atan(Q_P/I_P)``
  (two-quadrant) when it is not; measures the mean phase error over the interval,
  ``dphi + df T/2``.
* FLL — cross-product discriminator on consecutive prompts,
  ``cross = I1 Q2 - I2 Q1``, ``dot = I1 I2 + Q1 Q2``, ``y_f = atan2(cross, dot) / T``
  (``atan(cross/dot)/T`` when bits are unknown), after rotating the previous prompt by the
  NCO corrections applied between the two intervals (``note_correction``), so that it
  measures the current df.

Linear KF: state ``[dtau, dphi, df, da]`` (the same error definitions and dynamics as the
prefilter, eq. 2, discretised exactly), measurement rows
``H = [[1, 0, beta T/2, 0], [0, 1, T/2, 0], [0, 0, 1, 0]]`` and a diagonal R from the
textbook discriminator variances at the estimated C/N0 (c = C/N0 T = A^2/2 per epoch):

    var_tau = D/(4c) (1 + 2/((2-D) c))       chips^2   (normalised E-L envelope)
    var_phi = 1/(2c) (1 + 1/(2c))            rad^2     (Costas/atan)
    var_f   = 2 var_phi / T^2                (rad/s)^2 (difference of two phases)

each capped at the variance of a uniform distribution over the discriminator's range
(at 20 dB-Hz the 1 ms discriminators are nearly saturated noise).  The amplitude A
(column 0 of ``x``) is a running C/N0 estimate: an exponential average (time constant
``amp_tau_s``) of the prompt moments |P|^2 and |P|^4 and the moment C/N0 estimator
A^2 = sqrt(2 m2^2 - m4), noise 2 s^2 = m2 - A^2 (scale-free: a noise burst lowers the
estimated C/N0 instead of raising the apparent amplitude); column 0 holds A/s.

NCO steering: the bank exposes ``x`` (n_ch, 5) in the prefilter layout, so the same
``ultratight.fusion.channel.innerloop.InnerLoop`` applies the estimates. In the paper's single-loop
structure the estimates go to the integration filter and the NCOs are driven by the outer
loop only; at correlator level (ultratight.signals.synth.corrsim) that is modelled as the outer-loop Doppler
feed-forward plus the KF estimates applied to the NCO (an outer loop that absorbs the
estimates immediately).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ultratight.constants import BETA_CODE_CARRIER, T_CA
from ultratight.errors import FilterError
from ultratight.fusion.channel.prefilter import PackedActiveMask
from ultratight.fusion.channel.prefilter_model import (
    DEFAULT_P_LIMITS,
    FLAG_DIVERGED,
    IA,
    IE,
    IF,
    IL,
    IP,
    IPHI,
    ITAU,
    NX,
    NZ,
    QE,
    QL,
    QP,
    prefilter_model,
)
from ultratight.signals import corr_model

NK = 4                              # KF states: dtau, dphi, df, da (prefilter indices ITAU + K_*)
K_TAU, K_PHI, K_F, K_A = 0, 1, 2, 3
NM = 3                              # measurements: the DLL, PLL and FLL discriminators
M_DLL, M_PLL, M_FLL = 0, 1, 2       # (the FLL last: it is left out of the first epoch's update)

# The float parameters of a bank (its ``prm`` vector); names are compile-time constants in the kernels.
PB_PRM_T = 0                        # coherent integration time T (s)
PB_PRM_BETA = 1                     # code-carrier ratio beta
PB_PRM_SPACING = 2                  # early-late spacing (chips)
PB_PRM_AMP_ALPHA = 3                # weight of the newest epoch in the prompt moments (T / amp_tau_s)
PB_PRM_AMP_MIN = 4                  # amplitude floor of the C/N0 estimate
PB_PRM_P_LIMITS = 5                 # NK entries: divergence limits on the covariance diagonal
PB_PRM_CAL_LG0 = PB_PRM_P_LIMITS + NK   # CAL_LG0 of the calibration tables
PB_PRM_CAL_DLG = PB_PRM_CAL_LG0 + 1     # CAL_DLG of the calibration tables
N_PB_PRM = PB_PRM_CAL_DLG + 1

MOM_P2, MOM_P4 = 0, 1               # columns of the running prompt moments E|P|^2, E|P|^4
PREV_I, PREV_Q = 0, 1               # columns of the previous (bit-wiped) prompt

DEFAULT_Q_PBKF = {"q_tau": 1e-6, "q_phi": 0.1, "q_f": 40.0, "q_a": 10.0}


CAL_LG0 = -2.5           # log10(C/N0 T) of the first calibration point
CAL_DLG = 0.125          # grid step in log10
CAL_N = 41               # grid points: C/N0 T from 10^-2.5 to 10^2.5 (~15 .. 65 dB-Hz at 1 ms)
CAL_GAIN, CAL_VAR = 0, NM    # calibration table columns: gains CAL_GAIN + M_*, variances CAL_VAR + M_*
_CAL_CACHE = {}


def _disc_outputs(z, zprev, spacing, T, known):
    """Vectorised discriminators (numpy) for the calibration: z, zprev (m, 6)."""
    e = np.hypot(z[:, IE], z[:, QE])
    l = np.hypot(z[:, IL], z[:, QL])
    y_tau = 0.5 * (2.0 - spacing) * (e - l) / (e + l)
    if known:
        y_phi = np.arctan2(z[:, QP], z[:, IP])
    else:
        y_phi = np.arctan(z[:, QP] / z[:, IP])
    cross = zprev[:, IP] * z[:, QP] - z[:, IP] * zprev[:, QP]
    dot = zprev[:, IP] * z[:, IP] + zprev[:, QP] * z[:, QP]
    y_f = (np.arctan2(cross, dot) if known else np.arctan(cross / dot)) / T
    return y_tau, y_phi, y_f


def discriminator_calibration(spacing_chips, T, known_bits, n_mc=20000, seed=12345):
    """Gain (slope at zero error) and variance of the three discriminators vs C/N0 T.

    Monte Carlo over the correlator model of ultratight.signals.corr_model (unit noise per arm,
    correlated taps), fixed seed, cached per (spacing, T, known_bits).  Returns (CAL_N, 2 NM):
    [k_tau, k_phi, k_f, var_tau, var_phi, var_f] (columns CAL_GAIN + M_*, CAL_VAR + M_*) at
    C/N0 T = 10**(CAL_LG0 + i CAL_DLG).
    At low C/N0 the envelope DLL, the atan PLL and the FLL lose gain (squaring/suppression
    loss); a KF that assumed unit gain would be mistuned, so the baseline uses these figures.
    """
    key = (round(float(spacing_chips), 9), round(float(T), 12), bool(known_bits))
    if key in _CAL_CACHE:
        return _CAL_CACHE[key]
    rng = np.random.default_rng(seed)
    Lc = np.linalg.cholesky(corr_model.epl_noise_covariance(spacing_chips))
    d = corr_model.tap_offsets(spacing_chips)
    n1 = rng.standard_normal((n_mc, 6)) @ Lc.T
    n2 = rng.standard_normal((n_mc, 6)) @ Lc.T
    out = np.zeros((CAL_N, 2 * NM))
    dtau = 0.05 * min(1.0, spacing_chips)
    dphi = 0.05
    dfT = 0.05
    for i in range(CAL_N):
        cn = 10.0 ** (CAL_LG0 + i * CAL_DLG)
        a = math.sqrt(2.0 * cn)

        def zs(tau, ph, noise):
            r = corr_model.code_autocorr(tau + d)
            return np.concatenate([a * r * math.cos(ph), a * r * math.sin(ph)])[None, :] + noise

        z0 = zs(0.0, 0.0, n1)
        zp0 = zs(0.0, 0.0, n2)
        yt0, yp0, yf0 = _disc_outputs(z0, zp0, spacing_chips, T, known_bits)
        yt1, _, _ = _disc_outputs(zs(dtau, 0.0, n1), zp0, spacing_chips, T, known_bits)
        _, yp1, _ = _disc_outputs(zs(0.0, dphi, n1), zp0, spacing_chips, T, known_bits)
        _, _, yf1 = _disc_outputs(zs(0.0, dfT, n1), zp0, spacing_chips, T, known_bits)
        # common random numbers: the slope estimate is the mean paired difference
        k_tau = float(np.mean(yt1 - yt0)) / dtau
        k_phi = float(np.mean(yp1 - yp0)) / dphi
        k_f = float(np.mean(yf1 - yf0)) / (dfT / T)
        out[i] = [max(k_tau, 1e-3), max(k_phi, 1e-3), max(k_f, 1e-3),
                  float(np.var(yt0)), float(np.var(yp0)), float(np.var(yf0))]
    _CAL_CACHE[key] = out
    return out


@njit(cache=True)
def _pbkf_channel(c, x, P, Phi, Qd, z, bits, rscale, active, prm, prev, have_prev, rot, innov, flags, x0, P0, mom,
                  tab_k, tab_u):
    """One epoch of channel ``c`` (the loop body of :func:`_pbkf_step`; touches only row ``c``).

    Kept as one kernel because the C/N0 estimate, the discriminators, the calibrated gains and the
    sequential scalar updates hand each other the channel's live values (the bit, the prompt, the
    C/N0, the residuals corrected row by row): split into helpers they would be passed back and
    forth on every call, and this body runs once per channel per epoch inside the receiver's
    compiled loop."""
    T = prm[PB_PRM_T]
    beta = prm[PB_PRM_BETA]
    sp = prm[PB_PRM_SPACING]
    alpha = prm[PB_PRM_AMP_ALPHA]
    amin = prm[PB_PRM_AMP_MIN]
    H0 = np.zeros((NM, NK))
    H0[M_DLL, K_TAU] = 1.0
    H0[M_DLL, K_F] = beta * T * 0.5
    H0[M_PLL, K_PHI] = 1.0
    H0[M_PLL, K_F] = T * 0.5
    H0[M_FLL, K_F] = 1.0
    H = np.zeros((NM, NK))
    gk = np.zeros(NM)
    lg0 = prm[PB_PRM_CAL_LG0]
    dlg = prm[PB_PRM_CAL_DLG]
    y = np.zeros(NM)
    Rv = np.zeros(NM)
    PHt = np.zeros((NK, NM))
    K = np.zeros((NK, NM))
    tmp = np.zeros((NK, NK))
    xs = np.zeros(NK)
    flags[c] = 0
    if not active[c]:
        return
    D = bits[c]
    known = D != 0.0
    w = D if known else 1.0
    ip = z[c, IP] * w
    qp = z[c, QP] * w
    # C/N0 by the moment method (scale-free): with m2 = E|P|^2 = A^2 + 2 s^2 and
    # m4 = E|P|^4 = A^4 + 8 A^2 s^2 + 8 s^4:  A^2 = sqrt(2 m2^2 - m4), s^2 = (m2 - A^2)/2
    p2 = ip * ip + qp * qp
    mom[c, MOM_P2] = (1.0 - alpha) * mom[c, MOM_P2] + alpha * p2
    mom[c, MOM_P4] = (1.0 - alpha) * mom[c, MOM_P4] + alpha * p2 * p2
    dd = 2.0 * mom[c, MOM_P2] * mom[c, MOM_P2] - mom[c, MOM_P4]
    a2 = math.sqrt(dd) if dd > 0.0 else 0.0
    s2 = 0.5 * (mom[c, MOM_P2] - a2)
    if s2 < 1e-3 * mom[c, MOM_P2]:
        s2 = 1e-3 * mom[c, MOM_P2]
    if s2 <= 0.0:
        s2 = 1.0
    cn = 0.5 * a2 / s2                          # C/N0 * T
    if cn < 0.5 * amin * amin:
        cn = 0.5 * amin * amin
    x[c, IA] = math.sqrt(2.0 * cn)              # amplitude in unit-noise terms
    # discriminators
    e = math.sqrt(z[c, IE] * z[c, IE] + z[c, QE] * z[c, QE])
    l = math.sqrt(z[c, IL] * z[c, IL] + z[c, QL] * z[c, QL])
    y[M_DLL] = 0.5 * (2.0 - sp) * (e - l) / (e + l) if e + l > 0 else 0.0
    if known:
        y[M_PLL] = math.atan2(qp, ip)
    else:
        y[M_PLL] = math.atan(qp / ip) if ip != 0.0 else 0.0
    # previous prompt rotated by the NCO corrections applied in between
    use_f = have_prev[c] != 0
    if use_f:
        cr = math.cos(rot[c])
        sr = math.sin(rot[c])
        i1 = prev[c, PREV_I] * cr + prev[c, PREV_Q] * sr
        q1 = -prev[c, PREV_I] * sr + prev[c, PREV_Q] * cr
        cross = i1 * qp - ip * q1
        dot = i1 * ip + q1 * qp
        if known:
            y[M_FLL] = math.atan2(cross, dot) / T
        else:
            y[M_FLL] = math.atan(cross / dot) / T if dot != 0.0 else 0.0
    prev[c, PREV_I] = ip
    prev[c, PREV_Q] = qp
    have_prev[c] = 1
    rot[c] = 0.0
    # calibrated discriminator gains and variances at this C/N0 (table on log10(cn))
    tab = tab_k if known else tab_u
    u = (math.log10(cn) - lg0) / dlg
    if u < 0.0:
        u = 0.0
    if u > tab.shape[0] - 1.001:
        u = tab.shape[0] - 1.001
    i0 = int(u)
    fr = u - i0
    for m in range(NM):
        gk[m] = tab[i0, CAL_GAIN + m] * (1.0 - fr) + tab[i0 + 1, CAL_GAIN + m] * fr
        Rv[m] = (tab[i0, CAL_VAR + m] * (1.0 - fr) + tab[i0 + 1, CAL_VAR + m] * fr) * rscale[c]
    for m in range(NM):
        for i in range(NK):
            H[m, i] = gk[m] * H0[m, i]
    nm = NM if use_f else M_FLL             # rows used: the FLL needs the previous prompt
    # innovation (PLL residual wrapped)
    for i in range(NK):
        xs[i] = x[c, ITAU + i]
    for m in range(NM):
        acc = 0.0
        for i in range(NK):
            acc += H[m, i] * xs[i]
        r = y[m] - acc
        if m == M_PLL:
            per = 2.0 * math.pi if known else math.pi
            r = r - per * math.floor(r / per + 0.5)
        innov[c, m] = r if m < nm else np.nan
        y[m] = r
    # sequential scalar updates (R diagonal)
    Pc = P[c]
    for m in range(nm):
        s = Rv[m]
        for i in range(NK):
            acc = 0.0
            for j in range(NK):
                acc += Pc[i, j] * H[m, j]
            PHt[i, 0] = acc
            s += H[m, i] * acc
        for i in range(NK):
            K[i, 0] = PHt[i, 0] / s
        r = y[m]     # residual already corrected for the earlier rows' state change
        for i in range(NK):
            xs[i] += K[i, 0] * r
        for i in range(NK):
            for j in range(NK):
                Pc[i, j] -= K[i, 0] * PHt[j, 0]
        # update the remaining residuals for the state change (sequential processing)
        for m2 in range(m + 1, nm):
            acc = 0.0
            for i in range(NK):
                acc += H[m2, i] * K[i, 0] * r
            y[m2] -= acc
    # predict
    for i in range(NK):
        acc = 0.0
        for j in range(NK):
            acc += Phi[i, j] * xs[j]
        x[c, ITAU + i] = acc
    for i in range(NK):
        for j in range(NK):
            acc = 0.0
            for k in range(NK):
                acc += Phi[i, k] * Pc[k, j]
            tmp[i, j] = acc
    bad = False
    for i in range(NK):
        for j in range(i, NK):
            acc = Qd[i, j]
            for k in range(NK):
                acc += tmp[i, k] * Phi[j, k]
            Pc[i, j] = acc
            Pc[j, i] = acc
        if not (np.isfinite(x[c, ITAU + i]) and Pc[i, i] >= 0.0 and Pc[i, i] <= prm[PB_PRM_P_LIMITS + i]):
            bad = True
    if bad:
        flags[c] |= FLAG_DIVERGED
        for i in range(NX):
            x[c, i] = x0[c, i]
        for i in range(NK):
            for j in range(NK):
                Pc[i, j] = P0[c, i, j]
        have_prev[c] = 0


@njit(cache=True)
def _pbkf_step(x, P, Phi, Qd, z, bits, rscale, active, prm, prev, have_prev, rot, innov, flags, x0, P0, mom,
               tab_k, tab_u):
    """One epoch of all channels; prm (N_PB_PRM): entries ``PB_PRM_*``; prev (n, 2): the last epoch's
    prompt (columns PREV_I, PREV_Q); mom (n, 2): the running prompt moments (MOM_P2, MOM_P4)."""
    n = x.shape[0]
    for c in range(n):
        for m in range(NZ):
            if active[c] and not np.isfinite(z[c, m]):
                return -1 - c
    for c in range(n):
        _pbkf_channel(c, x, P, Phi, Qd, z, bits, rscale, active, prm, prev, have_prev, rot, innov, flags, x0, P0, mom,
                      tab_k, tab_u)
    return 0


def _pbkf_float_size(n, n_prm, n_tab):
    """Length of the packed float buffer of ``n`` channels (the segments of :func:`_pbkf_views`)."""
    return n * (3 * NX + 2 * NK * NK + 2 + 1 + NM + 2) + 2 * NK * NK + n_prm + 2 * n_tab


@njit(cache=True)
def _pbkf_views(fbuf, ibuf, n, n_prm, n_tab):
    """Views of the packed buffers (layout of :class:`PbKfBank`)."""
    o = 0
    x = fbuf[o:o + n * NX].reshape((n, NX)); o += n * NX
    x_post = fbuf[o:o + n * NX].reshape((n, NX)); o += n * NX
    P = fbuf[o:o + n * NK * NK].reshape((n, NK, NK)); o += n * NK * NK
    x0 = fbuf[o:o + n * NX].reshape((n, NX)); o += n * NX
    P0 = fbuf[o:o + n * NK * NK].reshape((n, NK, NK)); o += n * NK * NK
    Phi = fbuf[o:o + NK * NK].reshape((NK, NK)); o += NK * NK
    Qd = fbuf[o:o + NK * NK].reshape((NK, NK)); o += NK * NK
    prm = fbuf[o:o + n_prm]; o += n_prm
    prev = fbuf[o:o + 2 * n].reshape((n, 2)); o += 2 * n
    rot = fbuf[o:o + n]; o += n
    innov = fbuf[o:o + n * NM].reshape((n, NM)); o += n * NM
    mom = fbuf[o:o + 2 * n].reshape((n, 2)); o += 2 * n
    tab_k = fbuf[o:o + n_tab].reshape((CAL_N, -1)); o += n_tab
    tab_u = fbuf[o:o + n_tab].reshape((CAL_N, -1)); o += n_tab
    flags = ibuf[0:n]
    active = ibuf[n:2 * n]
    have_prev = ibuf[2 * n:3 * n]
    n_resets = ibuf[3 * n:4 * n]
    return x, x_post, P, x0, P0, Phi, Qd, prm, prev, rot, innov, mom, tab_k, tab_u, flags, active, have_prev, \
        n_resets


@njit(cache=True)
def pbkf_channel_epoch(fbuf, ibuf, c, z, bits, rscale, n_prm, n_tab):
    """Channel ``c``'s part of :func:`pbkf_epoch` (touches only row ``c``); -1 - c for a non-finite input."""
    n = z.shape[0]
    (x, x_post, P, x0, P0, Phi, Qd, prm, prev, rot, innov, mom, tab_k, tab_u, flags, active,
     have_prev, n_resets) = _pbkf_views(fbuf, ibuf, n, n_prm, n_tab)
    for m in range(NZ):
        if active[c] and not np.isfinite(z[c, m]):
            return -1 - c
    _pbkf_channel(c, x, P, Phi, Qd, z, bits, rscale, active, prm, prev, have_prev, rot, innov, flags, x0, P0, mom,
                  tab_k, tab_u)
    if (flags[c] & FLAG_DIVERGED) != 0:
        n_resets[c] += 1
    # posterior at the interval start: the time update undone (LAPACK's solve, as numpy's)
    x_post[c, IA] = x[c, IA]
    x_post[c, ITAU:] = np.linalg.solve(Phi, np.ascontiguousarray(x[c, ITAU:]))
    return 0


@njit(cache=True)
def pbkf_epoch(fbuf, ibuf, z, bits, rscale, n_prm, n_tab):
    """One epoch of a packed PB-KF bank: discriminators + KF (:func:`_pbkf_step`), divergence count,
    and the posterior at the interval start (the time update undone: x_post solves Phi x_post = x)."""
    n = z.shape[0]
    (x, x_post, P, x0, P0, Phi, Qd, prm, prev, rot, innov, mom, tab_k, tab_u, flags, active,
     have_prev, n_resets) = _pbkf_views(fbuf, ibuf, n, n_prm, n_tab)
    st = _pbkf_step(x, P, Phi, Qd, z, bits, rscale, active, prm, prev, have_prev, rot, innov, flags, x0, P0, mom,
                    tab_k, tab_u)
    if st < 0:
        return st
    for c in range(n):
        if (flags[c] & FLAG_DIVERGED) != 0:
            n_resets[c] += 1
        x_post[c, IA] = x[c, IA]
    x_post[:, ITAU:] = np.linalg.solve(Phi, np.ascontiguousarray(x[:, ITAU:].T)).T
    return st


@njit(cache=True)
def _pbkf_prm_rot(fbuf, ibuf, n, n_prm, n_tab):
    """The parameter vector and the per-channel FLL rotation of a packed bank."""
    (_, _, _, _, _, _, _, prm, _, rot, _, _, _, _, _, _, _, _) = _pbkf_views(fbuf, ibuf, n, n_prm, n_tab)
    return prm, rot


@njit(cache=True)
def pbkf_note_correction_one(fbuf, ibuf, c, dx, n_prm, n_tab):
    """:func:`pbkf_note_correction` for channel ``c`` alone."""
    prm, rot = _pbkf_prm_rot(fbuf, ibuf, dx.shape[0], n_prm, n_tab)
    rot[c] += dx[c, IPHI] - 0.5 * prm[PB_PRM_T] * dx[c, IF]


@njit(cache=True)
def pbkf_note_correction(fbuf, ibuf, dx, n_prm, n_tab):
    """The NCO corrections (state changes) applied before the next interval, for the FLL:
    angle(P_k conj(P_{k-1})) + u_phi - u_f T/2 measures the corrected df (module docstring)."""
    n = dx.shape[0]
    prm, rot = _pbkf_prm_rot(fbuf, ibuf, n, n_prm, n_tab)
    T = prm[PB_PRM_T]
    for c in range(n):
        rot[c] += dx[c, IPHI] - 0.5 * T * dx[c, IF]


class PbKfBank(PackedActiveMask):
    """Batched PB-KF-UTC discriminator + linear-KF baseline (see module docstring).

    ``step(z, bits=None) -> x`` (n_ch, 5) predicted errors in the prefilter layout
    ``[A, dtau, dphi, df, da]``; ``x_post`` is the state after the update (before the time
    update); ``note_correction(dx)`` is called by the inner-loop law after it moved the NCOs.
    """

    kind = "pbkf"
    P_ITAU, P_IF = K_TAU, K_F       # code and frequency errors in the covariance P (states dtau, dphi, df, da)

    def __init__(self, n_ch, T=T_CA, spacing_chips=1.0, q=None, cn0_dbhz_init=35.0, amp_tau_s=1.0,
                 cn0_min_dbhz=15.0, p_limits=None):
        n_ch = int(n_ch)
        if n_ch < 1:
            raise FilterError(f"PbKfBank n_ch={n_ch}: expected >= 1")
        if not (0 < spacing_chips < 2):
            raise FilterError(f"PbKfBank spacing_chips={spacing_chips!r}: expected 0 < spacing < 2")
        qq = dict(DEFAULT_Q_PBKF, **(q or {}))
        unknown = set(qq) - set(DEFAULT_Q_PBKF)
        if unknown:
            raise FilterError(f"PbKfBank process noise: unknown keys {sorted(unknown)}")
        self.n_ch = n_ch
        self.T = float(T)
        self.spacing_chips = float(spacing_chips)
        self.q = qq
        Phi5, Q5 = prefilter_model(self.T, dict(q_amp=0.0, **qq))
        Phi4 = Phi5[ITAU:, ITAU:]
        Qd4 = Q5[ITAU:, ITAU:]
        lim = DEFAULT_P_LIMITS[ITAU:] if p_limits is None else np.asarray(p_limits, dtype=float)
        amin = float(corr_model.amplitude_from_cn0(cn0_min_dbhz, self.T))
        prm = np.zeros(N_PB_PRM)
        prm[PB_PRM_T] = self.T
        prm[PB_PRM_BETA] = BETA_CODE_CARRIER
        prm[PB_PRM_SPACING] = self.spacing_chips
        prm[PB_PRM_AMP_ALPHA] = self.T / amp_tau_s
        prm[PB_PRM_AMP_MIN] = amin
        prm[PB_PRM_P_LIMITS:PB_PRM_P_LIMITS + NK] = lim
        prm[PB_PRM_CAL_LG0] = CAL_LG0
        prm[PB_PRM_CAL_DLG] = CAL_DLG
        tab_k = discriminator_calibration(self.spacing_chips, self.T, True)
        tab_u = discriminator_calibration(self.spacing_chips, self.T, False)
        # one packed float buffer and one int buffer (compiled callers take the whole bank as two
        # arrays, :attr:`packed`); the attributes below are views of them
        self._n_prm = prm.size
        self._n_tab = tab_k.size
        self._fbuf = np.zeros(_pbkf_float_size(n_ch, self._n_prm, self._n_tab))
        self._ibuf = np.zeros(4 * n_ch, dtype=np.int64)
        (self.x, self.x_post, self.P, self.x0, self.P0, self.Phi, self.Qd, self._prm, self._prev,
         self._rot, self.innov, self._mom, self._tab_k, self._tab_u, self.flags, self._active_i, self._have_prev,
         self.n_resets) = _pbkf_views(self._fbuf, self._ibuf, n_ch, self._n_prm, self._n_tab)
        self.Phi[:] = Phi4
        self.Qd[:] = Qd4
        self._prm[:] = prm
        self._tab_k[:] = tab_k
        self._tab_u[:] = tab_u
        a0 = float(corr_model.amplitude_from_cn0(cn0_dbhz_init, self.T))
        self.x0[:, IA] = a0
        self.P0[:] = np.diag([0.1 ** 2, 0.3 ** 2, (2 * math.pi * 5.0) ** 2, (2 * math.pi * 10.0) ** 2])
        self.x[:] = self.x0
        self.P[:] = self.P0
        self.innov[:] = np.nan
        self.nis = np.full(n_ch, np.nan)
        self.theta = np.ones(n_ch)
        self._mom[:, MOM_P2] = a0 * a0 + 2.0
        self._mom[:, MOM_P4] = a0 ** 4 + 8 * a0 * a0 + 8.0
        self._bits_unknown = np.zeros(n_ch)
        self._rscale_one = np.ones(n_ch)

    def reset(self, channels, x0=None, P0=None, activate=True):
        """(Re)initialise channels; P0 is the 4x4 covariance of [dtau, dphi, df, da]. As for the
        prefilter bank (:meth:`ultratight.fusion.channel.prefilter.PrefilterBank.reset`), only P0 and the
        amplitude of x0 are kept as the state a divergence returns to: the errors of x0 are against
        the reset epoch's NCOs."""
        ch = np.atleast_1d(np.asarray(channels, dtype=np.int64))
        xa = None
        if x0 is not None:
            xa = np.broadcast_to(np.asarray(x0, dtype=float), (ch.size, NX))
            self.x0[ch] = 0.0
            self.x0[ch, IA] = xa[:, IA]
        if P0 is not None:
            self.P0[ch] = np.broadcast_to(np.asarray(P0, dtype=float), (ch.size, NK, NK))
        self.x[ch] = self.x0[ch] if xa is None else xa
        self.x_post[ch] = self.x[ch]
        self.P[ch] = self.P0[ch]
        self._have_prev[ch] = 0
        self._rot[ch] = 0.0
        a0 = self.x0[ch, IA]
        self._mom[ch, MOM_P2] = a0 * a0 + 2.0
        self._mom[ch, MOM_P4] = a0 ** 4 + 8 * a0 * a0 + 8.0
        if activate:
            self._active_i[ch] = 1


    @property
    def packed(self):
        """``(float buffer, int buffer, n_prm, n_tab)``: the bank's whole state for compiled callers
        (:func:`pbkf_epoch`, :func:`pbkf_note_correction`)."""
        return self._fbuf, self._ibuf, self._n_prm, self._n_tab

    def step(self, z, bits=None, rscale=None):
        """One epoch; ``rscale``: None or (n_ch,) factors on the discriminator variances (a filter-R
        noise event, :mod:`ultratight.receiver.dsp.burst`)."""
        z = np.asarray(z, dtype=np.float64)
        if z.shape != (self.n_ch, NZ):
            raise FilterError(f"PbKfBank.step: z must have shape ({self.n_ch}, {NZ}), got {z.shape}")
        b = self._bits_unknown if bits is None else np.asarray(bits, dtype=np.float64)
        if b.shape != (self.n_ch,):
            raise FilterError(f"PbKfBank.step: bits must have shape ({self.n_ch},), got {b.shape}")
        rs = self._rscale_one if rscale is None else np.asarray(rscale, dtype=np.float64)
        if rs.shape != (self.n_ch,):
            raise FilterError(f"PbKfBank.step: rscale must have shape ({self.n_ch},), got {rs.shape}")
        st = pbkf_epoch(self._fbuf, self._ibuf, z, b, rs, self._n_prm, self._n_tab)
        if st < 0:
            raise FilterError(f"PbKfBank.step: non-finite measurement on active channel {-1 - st}")
        return self.x

    @property
    def diverged(self):
        return (self.flags & FLAG_DIVERGED) != 0

    def note_correction(self, dx):
        """Record the NCO corrections (state changes) applied before the next interval (FLL)."""
        pbkf_note_correction(self._fbuf, self._ibuf, np.ascontiguousarray(dx, dtype=float), self._n_prm,
                             self._n_tab)

    def correct(self, dx):
        self.x -= dx
        self.note_correction(dx)

    def describe(self):
        return dict(kind="pbkf", T=self.T, spacing_chips=self.spacing_chips, q=self.q)
