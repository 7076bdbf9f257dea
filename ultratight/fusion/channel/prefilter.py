"""Per-channel nonlinear I/Q prefilters (Zhao et al. 2014, §2.1–2.3): CKF, UKF and RACKF, batched in numba.

State (Zhao et al. 2014, §2.1), one row per channel::

    x = [A, dtau, dphi, df, da]
    A     normalised prompt amplitude (the correlator units of
          ultratight.signals.corr_model: A = sqrt(2 C/N0 T), unit noise per arm)
    dtau  code phase error, chips      = true code phase   - replica (NCO) code phase
    dphi  carrier phase error, rad     = true carrier phase - NCO carrier phase
    df    carrier frequency error, rad/s   (d dphi / dt)
    da    carrier phase acceleration error, rad/s^2 (d df / dt)

All errors are *true minus NCO* and refer to the **start** of the coherent
integration interval [t_k, t_k + T].

Measurement (Zhao et al. 2014, eq. 3), z = [I_P, I_E, I_L, Q_P, Q_E, Q_L]::

    I_x = A D R(dtau_m + d_x) sinc(df T/2) cos(df T/2 + dphi)
    Q_x = A D R(dtau_m + d_x) sinc(df T/2) sin(df T/2 + dphi)
    d = corr_model.tap_offsets(spacing) = [0, -spacing/2, +spacing/2]   (P, E, L)

with ``dtau_m = dtau + beta df T/2`` the code error at the middle of the
interval (the eq. 3 value; the beta df T/2 term is < 1e-5 chip and only keeps
the model exact for a state defined at the interval start).  The carrier part
is the exact mean of exp(j(dphi + df t)) over [0, T].  With the errors defined
as true - replica, the early replica runs *ahead* of the prompt by spacing/2
chips (replica code phase + spacing/2), so its correlation with the signal is
R(dtau - spacing/2): the early tap grows when dtau > 0 — which is eq. 3 with
d_E = -spacing/2.  ``A`` here is the paper's ``A*T`` (corr_model docstring).
Noise: R = corr_model.epl_noise_covariance(spacing) (unit variance, taps
correlated by R(d)).

Data bit D: per channel, a known bit (+1/-1, i.e. wiped) or 0 = unknown.
Unknown bits are decided from the data (decision-directed, "2-quadrant"
formulation): D = sign(z . h(x_pred; D=+1)), the sign of the projection of the
six measured outputs onto the predicted noise-free outputs — the ML bit given
the predicted state.  Like a Costas loop this is insensitive to 180° phase
jumps of the data and costs a squaring loss at low C/N0.

Cycle (one call per 1 ms epoch for all channels): the bank holds the *prior*
x_{k|k-1}, P_{k|k-1} for the interval that was just integrated; ``step(z)``
does the measurement update (eqs. 9–17, or Algorithm 1 for RACKF), then the
time update (eqs. 4–8) to the start of the next interval and returns that
predicted state.  The inner-loop law (``ultratight.fusion.channel.innerloop``) then
moves the NCOs by (part of) the predicted errors and removes the applied part
from the state with :meth:`PrefilterBank.correct` (error-state feedback).

Time update: the dynamics (eq. 2) are linear, so eqs. 4–8 (cubature points
propagated through f and averaged) equal x <- Phi x, P <- Phi P Phi^T + Q
exactly; that closed form is used (same numbers, 10x cheaper).  The
measurement update always *redraws* points from the predicted covariance.

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
"""

from __future__ import annotations

import math

import numpy as np
import scipy.linalg
from numba import njit

from ultratight.constants import BETA_CODE_CARRIER, T_CA
from ultratight.errors import FilterError
from ultratight.signals import corr_model

# --- state and measurement layout -------------------------------------------------
NX = 5
NZ = 6
IA, ITAU, IPHI, IF, IDA = 0, 1, 2, 3, 4           # state indices
STATE_NAMES = ("A", "dtau_chips", "dphi_rad", "df_radps", "da_radps2")
IP, IE, IL, QP, QE, QL = 0, 1, 2, 3, 4, 5         # measurement indices
MEAS_NAMES = ("I_P", "I_E", "I_L", "Q_P", "Q_E", "Q_L")

KINDS = ("ckf", "ukf", "rackf")
_KIND_CODE = {"ckf": 0, "ukf": 1, "rackf": 2}
ROBUST_MODES = ("period", "every")
ADAPTIVE_STATS = ("epoch", "window", "mean")   # iprm[2] = index

# status flags (bit field, per channel, per epoch)
# The max rule of eq. 21 is positive definite only for moderate factors (with the P/E/L taps
# 0.5-correlated, a single tap's factor g gives det ~ g (1 - g/2)): near g = 2 it is PD but
# nearly singular, and P_zz = P_zz0 + R_bar inherits a near-null direction -> a gain that moved
# the code state by ~20 sigma in one epoch (paper-highdyn seed 1, 14.59 s).  Squared Cholesky
# pivots below this fraction of their diagonal element switch to the bifactor form (R itself:
# >= 0.67 for 1 chip spacing).
RB_REL_PIVOT_MIN = 0.1

FLAG_DIVERGED = 1        # non-finite / blown-up covariance -> channel reset
FLAG_CHOL_GUARD = 2      # a Cholesky pivot had to be floored
FLAG_THETA = 4           # adaptive factor < 1 applied this epoch (RACKF)
FLAG_ROBUST = 8          # Huber inflation active on at least one output (RACKF)

# default divergence limits on the covariance diagonal (1-sigma: 3 chips, 10 kHz, ...)
DEFAULT_P_LIMITS = np.array([1e4, 9.0, 1e6, (2 * math.pi * 1e4) ** 2, (2 * math.pi * 1e6) ** 2])


# --- process model ----------------------------------------------------------------
DEFAULT_Q = {
    # continuous-time white-noise spectral densities of w in eq. 2
    "q_amp": 1e-4,        # (amplitude units)^2 / s: ~2 %/sqrt(s) amplitude random walk at 20 dB-Hz
    "q_tau": 1e-6,        # chips^2 / s: code-carrier divergence
    "q_phi": 0.1,         # rad^2 / s: clock phase noise (white frequency)
    "q_f": 40.0,          # rad^2 / s^3: clock frequency random walk (TCXO class)
    "q_a": 10.0,          # rad^2 / s^5: residual line-of-sight jerk after outer-loop aiding (well aided)
}


def continuous_model(q=None, beta=BETA_CODE_CARRIER):
    """F, G and the continuous noise spectral matrix Qc = G diag(q) G^T of eq. 2."""
    qq = dict(DEFAULT_Q)
    if q:
        unknown = set(q) - set(DEFAULT_Q)
        if unknown:
            raise FilterError(f"prefilter process noise: unknown keys {sorted(unknown)}; expected {sorted(DEFAULT_Q)}")
        qq.update(q)
    for k, v in qq.items():
        if not (np.isfinite(v) and v >= 0.0):
            raise FilterError(f"prefilter process noise {k}={v!r}: expected a finite value >= 0")
    F = np.zeros((NX, NX))
    F[ITAU, IF] = beta
    F[IPHI, IF] = 1.0
    F[IF, IDA] = 1.0
    G = np.eye(NX)
    G[ITAU, IPHI] = beta
    qd = np.array([qq["q_amp"], qq["q_tau"], qq["q_phi"], qq["q_f"], qq["q_a"]])
    Qc = G @ np.diag(qd) @ G.T
    return F, G, Qc


def discretize(F, Qc, T):
    """Exact discretisation (Van Loan): Phi = exp(F T), Q = int_0^T Phi(s) Qc Phi(s)^T ds."""
    n = F.shape[0]
    M = np.zeros((2 * n, 2 * n))
    M[:n, :n] = -F
    M[:n, n:] = Qc
    M[n:, n:] = F.T
    E = scipy.linalg.expm(M * T)
    Phi = E[n:, n:].T
    Qd = Phi @ E[:n, n:]
    Qd = 0.5 * (Qd + Qd.T)
    return Phi, Qd


def prefilter_model(T=T_CA, q=None, beta=BETA_CODE_CARRIER):
    """(Phi, Qd) of the 5-state prefilter over one epoch of length T (s)."""
    if not (np.isfinite(T) and T > 0):
        raise FilterError(f"prefilter epoch T={T!r}: expected a positive duration in seconds")
    F, _, Qc = continuous_model(q, beta)
    return discretize(F, Qc, T)


# --- numba kernels ------------------------------------------------------------------
@njit(cache=True, inline="always")
def _tri(t):
    a = abs(t)
    return 1.0 - a if a < 1.0 else 0.0


@njit(cache=True)
def _h(x, D, T, beta, dhalf, out):
    """Eq. 3 for one state vector x -> out[6]."""
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
    out[0] = rp * c
    out[1] = re * c
    out[2] = rl * c
    out[3] = rp * sn
    out[4] = re * sn
    out[5] = rl * sn


@njit(cache=True)
def _chol(A, L, n):
    """Guarded Cholesky A = L L^T (lower). Returns 0 ok, 1 pivot floored, 2 non-finite."""
    scale = 0.0
    for i in range(n):
        d = A[i, i]
        if not np.isfinite(d):
            return 2
        if d > scale:
            scale = d
    if scale <= 0.0:
        scale = 1.0
    floor = 1e-12 * scale
    status = 0
    for j in range(n):
        s = A[j, j]
        for k in range(j):
            s -= L[j, k] * L[j, k]
        if not (s > floor):
            if not np.isfinite(s):
                return 2
            s = floor
            status = 1
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
def _moments(xc, S, scale, kind, ut_w, D, T, beta, dhalf, pts, zp, zhat, Pzz0, Pxz):
    """Draw points around xc with spread scale*S, push through h, return moments (no R)."""
    if kind == 1:  # UKF: centre + 2n points
        npts = 2 * NX + 1
        wm0 = ut_w[0]
        wc0 = ut_w[1]
        wi = ut_w[2]
        for i in range(NX):
            pts[0, i] = xc[i]
        for j in range(NX):
            for i in range(NX):
                d = scale * S[i, j]
                pts[1 + j, i] = xc[i] + d
                pts[1 + NX + j, i] = xc[i] - d
    else:          # CKF: 2n points
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
    if st == 2:
        return np.nan, 2
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


N_PRM = 20
NACC_FIX = 7          # accumulator columns before the innovation sums
NACC = NACC_FIX + NZ  # per-channel accumulator width
N_W1 = 28
N_W2 = 8


@njit(cache=True)
def _layout(n):
    """Offsets of the packed float buffer: x, P, xpost, x0, P0, innov, nis, theta, acc, Phi, Qd, R, prm, W1, W2
    (a tuple: the per-channel epoch asks for it and allocates nothing)."""
    o1 = n * NX
    o2 = o1 + n * NX * NX
    o3 = o2 + n * NX
    o4 = o3 + n * NX
    o5 = o4 + n * NX * NX
    o6 = o5 + n * NZ
    o7 = o6 + n
    o8 = o7 + n
    o9 = o8 + n * NACC
    o10 = o9 + NX * NX
    o11 = o10 + NX * NX
    o12 = o11 + NZ * NZ
    o13 = o12 + N_PRM
    o14 = o13 + N_W1 * NZ
    o15 = o14 + N_W2 * NZ * NZ
    return (0, o1, o2, o3, o4, o5, o6, o7, o8, o9, o10, o11, o12, o13, o14, o15)


@njit(cache=True)
def _ilayout(n):
    """Offsets of the packed int buffer: flags (n), active (n), iprm (3), n_resets (n), counters
    (epoch, correction_period); a tuple."""
    return (0, n, 2 * n, 2 * n + 3, 3 * n + 3, 3 * n + 5)


@njit(cache=True)
def bank_epoch(kind, fbuf, ibuf, z, bits, rscale):
    """One epoch of a packed bank, bookkeeping included: sets the correction flag from the epoch
    counter (every ``correction_period`` epochs), steps, counts divergences in ``n_resets`` and
    advances the counter. Returns the status of :func:`_bank_step`."""
    n = z.shape[0]
    io = _ilayout(n)
    epoch = ibuf[io[4]]
    period = ibuf[io[4] + 1]
    ibuf[2 * n] = 1 if epoch % period == 0 else 0
    st = _bank_step_packed(kind, fbuf, ibuf, z, bits, rscale)
    if st < 0:
        return st
    ibuf[io[4]] = epoch + 1
    for c in range(n):
        if (ibuf[c] & FLAG_DIVERGED) != 0:
            ibuf[io[3] + c] += 1
    return st


@njit(cache=True)
def _views(fbuf, ibuf, n):
    """The bank's arrays as views of its packed buffers (layouts :func:`_layout`, :func:`_ilayout`)."""
    o = _layout(n)
    x = fbuf[o[0]:o[1]].reshape((n, NX))
    P = fbuf[o[1]:o[2]].reshape((n, NX, NX))
    xpost = fbuf[o[2]:o[3]].reshape((n, NX))
    x0 = fbuf[o[3]:o[4]].reshape((n, NX))
    P0 = fbuf[o[4]:o[5]].reshape((n, NX, NX))
    innov = fbuf[o[5]:o[6]].reshape((n, NZ))
    nis = fbuf[o[6]:o[7]]
    theta = fbuf[o[7]:o[8]]
    acc = fbuf[o[8]:o[9]].reshape((n, NACC))
    Phi = fbuf[o[9]:o[10]].reshape((NX, NX))
    Qd = fbuf[o[10]:o[11]].reshape((NX, NX))
    R = fbuf[o[11]:o[12]].reshape((NZ, NZ))
    prm = fbuf[o[12]:o[13]]
    W1 = fbuf[o[13]:o[14]].reshape((N_W1, NZ))
    W2 = fbuf[o[14]:o[15]].reshape((N_W2, NZ, NZ))
    flags = ibuf[0:n]
    active = ibuf[n:2 * n]
    iprm = ibuf[2 * n:2 * n + 3]
    return x, P, xpost, x0, P0, innov, nis, theta, acc, Phi, Qd, R, prm, W1, W2, flags, active, iprm


@njit(cache=True)
def _bank_step_packed(kind, fbuf, ibuf, z, bits, rscale):
    """Packed-argument entry point (few arguments = low dispatch cost).

    ibuf = [flags (n), active (n), do_correction, robust_every, windowed_adaptive, ...]
    (layout :func:`_ilayout`).
    """
    x, P, xpost, x0, P0, innov, nis, theta, acc, Phi, Qd, R, prm, W1, W2, flags, active, iprm = \
        _views(fbuf, ibuf, z.shape[0])
    return _bank_step(kind, x, P, xpost, x0, P0, Phi, Qd, R, z, bits, rscale, active, prm, iprm,
                      innov, nis, theta, flags, W1, W2, acc)


@njit(cache=True)
def bank_channel_epoch(kind, fbuf, ibuf, c, z, bits, rscale, epoch, W1, W2):
    """Channel ``c``'s part of :func:`bank_epoch` at epoch count ``epoch`` (the counter itself is not
    advanced), with work arrays ``W1`` (N_W1, 6) / ``W2`` (N_W2, 6, 6) of the caller's: channels
    stepped by different threads need their own. Returns -1 - c for a non-finite input, else 0."""
    n = z.shape[0]
    x, P, xpost, x0, P0, innov, nis, theta, acc, Phi, Qd, R, prm, _, _, flags, active, iprm = _views(fbuf, ibuf, n)
    if active[c]:
        for m in range(NZ):
            if not np.isfinite(z[c, m]):
                return -1 - c
        if not np.isfinite(bits[c]):
            return -1 - c
    io = _ilayout(n)
    _channel_update(kind, c, x, P, xpost, x0, P0, Phi, Qd, R, z, bits, rscale, active, prm,
                    epoch % ibuf[io[4] + 1] == 0, iprm[1] != 0, iprm[2], innov, nis, theta, flags, W1, W2, acc)
    if (flags[c] & FLAG_DIVERGED) != 0:
        ibuf[io[3] + c] += 1
    return 0


@njit(cache=True)
def _channel_update(kind, c, x, P, xpost, x0, P0, Phi, Qd, R, z, bits, rscale, active, prm, do_corr, robust_every,
                    win_mode, innov, nis, theta, flags, W1, W2, acc):
    """One epoch of channel ``c`` (the loop body of :func:`_bank_step`; touches only row ``c`` and the
    work arrays ``W1``/``W2``, so channels with work arrays of their own may run concurrently).
    ``do_corr``, ``robust_every``, ``win_mode``: the entries of ``iprm`` (see :func:`_bank_step`)."""
    T = prm[0]
    beta = prm[1]
    dhalf = prm[2]
    hc = prm[3]
    theta_min = prm[4]
    ut_w = prm[5:8]
    ut_scale = prm[8]
    windowed = win_mode != 0
    ksig = prm[14]
    min_win = prm[15]
    phi_var_max = prm[16]
    plim = prm[9:14]
    # work views
    pts = W1[0:11, 0:NX]
    zp = W1[11:22, :]
    zhat = W1[22, :]
    r = W1[23, :]
    y = W1[24, :]
    gam = W1[25, :]
    hx = W1[26, :]
    tmpv = W1[27, 0:NX]
    S = W2[0, 0:NX, 0:NX]
    Pzz0 = W2[1]
    Pzz = W2[2]
    Pxz = W2[3, 0:NX, :]
    Lz = W2[4]
    K = W2[5, 0:NX, :]
    Rb = W2[6]
    tmpm = W2[7, 0:NX, 0:NX]
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
    if st == 1:
        flags[c] |= FLAG_CHOL_GUARD
    bad = st == 2
    if not bad:
        scale = ut_scale if kind == 1 else math.sqrt(NX)
        # eqs. 10-14 (eq. 40 with theta = 1)
        _moments(xc, S, scale, kind, ut_w, D, T, beta, dhalf, pts, zp, zhat, Pzz0, Pxz)
        for m in range(NZ):
            r[m] = z[c, m] - zhat[m]
        pscale = 1.0
        robust = kind == 2 and (do_corr or robust_every)
        if kind == 2:
            lam = acc[c, 5]          # measurement-noise scale held over this period
            if lam < 1.0:
                lam = 1.0
            lam *= rs                # (a filter-R noise event: receiver.burst)
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
                    acc[c, NACC_FIX + a] += D * r[a] / gam[a]   # bit-wiped, winsorised innovation sum
                acc[c, 0] += trp
                acc[c, 1] += rr
                acc[c, 2] += e_full
                acc[c, 3] += e_expl
                acc[c, 4] += trr
                acc[c, 6] += 1.0
                if do_corr:
                    cnt = acc[c, 6]
                    trp = acc[c, 0]
                    if win_mode == 2:
                        # energy of the window-mean innovation, scaled to a sum of epochs
                        rr = 0.0
                        for a in range(NZ):
                            rr += acc[c, NACC_FIX + a] * acc[c, NACC_FIX + a]
                    else:
                        rr = acc[c, 1]
                    # significance margin of a chi-square sum with 6 N degrees of freedom
                    # (the window-mean statistic |sum r|^2 has only 6 degrees of freedom)
                    marg = 1.0 + ksig * math.sqrt(2.0 / (NZ * cnt))
                    marg_th = 1.0 + ksig * math.sqrt(2.0 / NZ) if win_mode == 2 else marg
                    if cnt < min_win:
                        rr = 0.0                 # too few epochs: no adaptation
                    elif rr <= marg_th * trp:
                        rr = 0.0
                    # residual energy no state error can explain -> measurement noise scale
                    lam_new = (acc[c, 2] - acc[c, 3]) / acc[c, 4]
                    if cnt >= min_win and lam_new > marg:
                        acc[c, 5] = lam_new
                    else:
                        acc[c, 5] = 1.0
                    for a in range(NACC):
                        if a != 5:
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
                _moments(xc, S, scale * math.sqrt(pscale), kind, ut_w, D, T, beta, dhalf,
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
        if st2 == 1:
            flags[c] |= FLAG_CHOL_GUARD
        bad = st2 == 2
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

    prm  = [T, beta, dhalf, huber_c, theta_min, wm0, wc0, wi, ut_scale]
    iprm = [do_correction, robust_every, windowed_adaptive]
    acc (n_ch, 6): per-channel sums over the correction period (windowed statistics):
    [tr(P_zz_bar), |r_winsorised|^2, |r|^2, explainable energy, tr(R)] and the held
    measurement-noise scale lam in column 5.
    W1 (n_w1, 6) and W2 (n_w2, 6, 6) are work arrays (no allocation per epoch).
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
        _channel_update(kind, c, x, P, xpost, x0, P0, Phi, Qd, R, z, bits, rscale, active, prm, iprm[0] != 0,
                        iprm[1] != 0, iprm[2], innov, nis, theta, flags, W1, W2, acc)
    return 0


def ut_weights(alpha, beta_ut, kappa, n=NX):
    """Scaled unscented transform: (spread sqrt(n+lambda), wm0, wc0, wi)."""
    lam = alpha * alpha * (n + kappa) - n
    if not (n + lam > 0):
        raise FilterError(f"UKF parameters alpha={alpha}, kappa={kappa}: need n + lambda > 0 (got {n + lam})")
    wm0 = lam / (n + lam)
    wc0 = wm0 + (1.0 - alpha * alpha + beta_ut)
    wi = 1.0 / (2.0 * (n + lam))
    return math.sqrt(n + lam), wm0, wc0, wi


def default_initial_covariance(cn0_dbhz=35.0, T=T_CA, sigma_tau_chips=0.1, sigma_phi_rad=0.3,
                               sigma_f_hz=5.0, sigma_a_hzps=10.0, rel_sigma_amp=0.1):
    """Diagonal initial covariance (e.g. after acquisition / from an outer-loop prediction)."""
    a = float(corr_model.amplitude_from_cn0(cn0_dbhz, T))
    sig = np.array([rel_sigma_amp * a, sigma_tau_chips, sigma_phi_rad,
                    2 * math.pi * sigma_f_hz, 2 * math.pi * sigma_a_hzps])
    return np.diag(sig ** 2)


class PackedActiveMask:
    """The ``active`` mask of a bank that keeps it as integers in its packed buffer (``_active_i``)."""

    @property
    def active(self):
        """Per-channel active mask (read-only copy; change it with set_active / reset)."""
        a = self._active_i != 0
        a.flags.writeable = False
        return a

    def set_active(self, mask):
        m = np.asarray(mask, dtype=np.bool_)
        if m.shape != (self.n_ch,):
            raise FilterError(f"{type(self).__name__} active mask: expected shape ({self.n_ch},), got {m.shape}")
        self._active_i[:] = m


class PrefilterBank(PackedActiveMask):
    """Batched 5-state I/Q prefilters ("ckf" | "ukf" | "rackf") for ``n_ch`` channels.

    Parameters
    ----------
    n_ch : number of channels.
    kind : "ckf", "ukf" or "rackf".
    T : coherent integration time (s), default one C/A period.
    spacing_chips : early-late spacing (the correlator's).
    q : dict overriding DEFAULT_Q (continuous process noise densities, eq. 2).
    huber_c : Huber constant c (Zhao et al. 2014, §2.3: 1.3–2.0).
    correction_period : RACKF robust-adaptive correction period in epochs (50 = 50 ms).
    robust_mode : "every" (default: Huber every epoch, adaptive factor on correction epochs)
        or "period" (paper: Huber + adaptive only on correction epochs, plain CKF between).
    adaptive_stat : "mean" (default), "window" or "epoch" (paper-literal eq. 38), see above.
    adapt_ksig : significance margin (sigmas) of the windowed statistics.
    theta_min : lower bound of the adaptive factor.
    phi_sigma_max : cap of the phase standard deviation (rad), all kinds.
    ukf_alpha, ukf_beta, ukf_kappa : UKF scaled sigma-point parameters.
    p_limits : per-state covariance-diagonal limits beyond which a channel is declared diverged.

    Attributes (views, updated in place): ``x`` (n_ch, 5) predicted state for the next
    interval, ``P`` (n_ch, 5, 5), ``x_post`` (n_ch, 5) posterior of the last interval,
    ``innov`` (n_ch, 6), ``nis`` (n_ch,), ``theta`` (n_ch,), ``flags`` (n_ch,) bit field,
    ``diverged`` (n_ch,) bool for the last epoch, ``n_resets`` (n_ch,), ``active`` (n_ch,).
    """

    P_ITAU, P_IF = ITAU, IF        # code and frequency errors in the covariance P (the bank's state layout)

    def __init__(self, n_ch, kind="rackf", T=T_CA, spacing_chips=1.0, q=None, huber_c=1.5,
                 correction_period=50, robust_mode="every", adaptive_stat="mean", adapt_ksig=3.0,
                 theta_min=1e-3, phi_sigma_max=0.8,
                 ukf_alpha=0.5,
                 ukf_beta=2.0, ukf_kappa=0.0, p_limits=None, cn0_dbhz_init=35.0):
        if kind not in _KIND_CODE:
            raise FilterError(f"prefilter kind {kind!r}: expected one of {KINDS}")
        if robust_mode not in ROBUST_MODES:
            raise FilterError(f"prefilter robust_mode {robust_mode!r}: expected one of {ROBUST_MODES}")
        n_ch = int(n_ch)
        if n_ch < 1:
            raise FilterError(f"prefilter n_ch={n_ch}: expected >= 1")
        if not (np.isfinite(spacing_chips) and 0 < spacing_chips <= 2.0):
            raise FilterError(f"prefilter spacing_chips={spacing_chips!r}: expected 0 < spacing <= 2")
        if not (1.0 <= huber_c <= 10.0):
            raise FilterError(f"prefilter huber_c={huber_c!r}: expected 1 <= c <= 10 (paper: 1.3-2.0)")
        if int(correction_period) < 1:
            raise FilterError(f"prefilter correction_period={correction_period!r}: expected >= 1 epoch")
        if adaptive_stat not in ADAPTIVE_STATS:
            raise FilterError(f"prefilter adaptive_stat {adaptive_stat!r}: expected one of {ADAPTIVE_STATS}")
        if not (0 < theta_min <= 1):
            raise FilterError(f"prefilter theta_min={theta_min!r}: expected 0 < theta_min <= 1")
        self.n_ch = n_ch
        self.kind = kind
        self._kind = _KIND_CODE[kind]
        self.T = float(T)
        self.spacing_chips = float(spacing_chips)
        self.q = dict(DEFAULT_Q, **(q or {}))
        Phi, Qd = prefilter_model(self.T, q)
        R = corr_model.epl_noise_covariance(self.spacing_chips)
        self.huber_c = float(huber_c)
        self.correction_period = int(correction_period)
        self.robust_mode = robust_mode
        self.adaptive_stat = adaptive_stat
        self.theta_min = float(theta_min)
        self.ukf_params = dict(alpha=float(ukf_alpha), beta=float(ukf_beta), kappa=float(ukf_kappa))
        ut_scale, wm0, wc0, wi = ut_weights(ukf_alpha, ukf_beta, ukf_kappa)
        lim = DEFAULT_P_LIMITS if p_limits is None else np.asarray(p_limits, dtype=float)
        if lim.shape != (NX,):
            raise FilterError(f"prefilter p_limits: expected shape ({NX},), got {lim.shape}")
        dhalf = float(corr_model.tap_offsets(self.spacing_chips)[2])
        # one packed float buffer and one int buffer (few kernel arguments); attributes are views
        o = _layout(n_ch)
        self._fbuf = np.zeros(int(o[-1]))
        io = _ilayout(n_ch)
        self._ibuf = np.zeros(int(io[5]), dtype=np.int64)
        fb = self._fbuf
        self.x = fb[o[0]:o[1]].reshape(n_ch, NX)
        self.P = fb[o[1]:o[2]].reshape(n_ch, NX, NX)
        self.x_post = fb[o[2]:o[3]].reshape(n_ch, NX)
        self.x0 = fb[o[3]:o[4]].reshape(n_ch, NX)
        self.P0 = fb[o[4]:o[5]].reshape(n_ch, NX, NX)
        self.innov = fb[o[5]:o[6]].reshape(n_ch, NZ)
        self.nis = fb[o[6]:o[7]]
        self.theta = fb[o[7]:o[8]]
        self._acc = fb[o[8]:o[9]].reshape(n_ch, NACC)
        self.Phi = fb[o[9]:o[10]].reshape(NX, NX)
        self.Qd = fb[o[10]:o[11]].reshape(NX, NX)
        self.R = fb[o[11]:o[12]].reshape(NZ, NZ)
        self._prm = fb[o[12]:o[13]]
        self.flags = self._ibuf[0:n_ch]
        self._active_i = self._ibuf[n_ch:2 * n_ch]
        self._iprm = self._ibuf[io[2]:io[3]]
        self.n_resets = self._ibuf[io[3]:io[4]]
        self._counters = self._ibuf[io[4]:io[5]]       # epoch, correction period
        self.Phi[:] = Phi
        self.Qd[:] = Qd
        self.R[:] = R
        self._prm[:17] = [self.T, BETA_CODE_CARRIER, dhalf, self.huber_c, self.theta_min,
                          wm0, wc0, wi, ut_scale, *lim, float(adapt_ksig),
                          float(max(2, self.correction_period // 2)), float(phi_sigma_max) ** 2]
        self._iprm[1] = 1 if robust_mode == "every" else 0
        self._iprm[2] = ADAPTIVE_STATS.index(adaptive_stat)
        self._acc[:, 5] = 1.0
        self.phi_sigma_max = float(phi_sigma_max)
        self.adapt_ksig = float(adapt_ksig)
        self.innov[:] = np.nan
        self.nis[:] = np.nan
        self.theta[:] = 1.0
        self._counters[1] = self.correction_period
        self._bits_unknown = np.zeros(n_ch)
        self._rscale_one = np.ones(n_ch)
        a0 = float(corr_model.amplitude_from_cn0(cn0_dbhz_init, self.T))
        P_init = default_initial_covariance(cn0_dbhz_init, self.T)
        for c in range(n_ch):
            self.x0[c, IA] = a0
            self.P0[c] = P_init
        self.x[:] = self.x0
        self.P[:] = self.P0
        self.x_post[:] = self.x0

    # -- initialisation -------------------------------------------------------------
    def reset(self, channels, x0=None, P0=None, activate=True):
        """(Re)initialise channels: x0 (k,5) or (5,), P0 (k,5,5) or (5,5) (defaults: the stored ones).

        The given P0 and the amplitude of x0 also become the state the channel returns to after a
        divergence; its code, phase, frequency and acceleration errors return to zero. They are
        errors against the NCOs of the reset epoch, which the inner-loop feedback moves into the
        NCOs: returning to them later would apply the same correction twice (a channel restarted
        far off its aiding then doubles its offset at every divergence).
        """
        ch = np.atleast_1d(np.asarray(channels, dtype=np.int64))
        if ch.size and (ch.min() < 0 or ch.max() >= self.n_ch):
            raise FilterError(f"prefilter reset: channel index out of range 0..{self.n_ch - 1}: {ch}")
        xa = None
        if x0 is not None:
            xa = np.broadcast_to(np.asarray(x0, dtype=float), (ch.size, NX))
            if not np.all(np.isfinite(xa)):
                raise FilterError("prefilter reset: x0 must be finite")
            self.x0[ch] = 0.0
            self.x0[ch, IA] = xa[:, IA]
        if P0 is not None:
            Pa = np.broadcast_to(np.asarray(P0, dtype=float), (ch.size, NX, NX))
            for k in range(ch.size):
                Pk = Pa[k]
                if not (np.all(np.isfinite(Pk)) and np.allclose(Pk, Pk.T)):
                    raise FilterError("prefilter reset: P0 must be finite and symmetric")
                try:
                    np.linalg.cholesky(Pk)
                except np.linalg.LinAlgError:
                    raise FilterError("prefilter reset: P0 must be positive definite") from None
            self.P0[ch] = Pa
        self.x[ch] = self.x0[ch] if xa is None else xa
        self.P[ch] = self.P0[ch]
        self.x_post[ch] = self.x[ch]
        self.nis[ch] = np.nan
        self.innov[ch] = np.nan
        self._acc[ch] = 0.0
        self._acc[ch, 5] = 1.0
        if activate:
            self._active_i[ch] = 1


    # -- one epoch -----------------------------------------------------------------
    def step(self, z, bits=None, rscale=None):
        """Measurement update with z (n_ch, 6) then predict; returns the predicted x (n_ch, 5).

        bits: None (all unknown -> decision-directed) or (n_ch,) of +1/-1 (known) / 0 (unknown).
        rscale: None or (n_ch,) factors on R for this epoch (a filter-R noise event,
        :mod:`ultratight.receiver.dsp.burst`).
        """
        z = np.asarray(z, dtype=np.float64)
        if z.shape != (self.n_ch, NZ):
            raise FilterError(f"prefilter step: z must have shape ({self.n_ch}, {NZ}) "
                              f"[I_P, I_E, I_L, Q_P, Q_E, Q_L], got {z.shape}")
        if bits is None:
            b = self._bits_unknown
        else:
            b = np.asarray(bits, dtype=np.float64)
            if b.shape != (self.n_ch,):
                raise FilterError(f"prefilter step: bits must have shape ({self.n_ch},), got {b.shape}")
        rs = self._rscale_one if rscale is None else np.asarray(rscale, dtype=np.float64)
        if rs.shape != (self.n_ch,):
            raise FilterError(f"prefilter step: rscale must have shape ({self.n_ch},), got {rs.shape}")
        st = bank_epoch(self._kind, self._fbuf, self._ibuf, z, b, rs)
        if st < 0:
            c = -1 - st
            raise FilterError(f"prefilter step: non-finite measurement or bit on active channel {c}: "
                              f"z={z[c]}, bit={b[c]}")
        return self.x

    @property
    def epoch(self):
        """Epochs stepped since construction (the RACKF correction phase counts from it)."""
        return int(self._counters[0])

    @epoch.setter
    def epoch(self, value):
        self._counters[0] = int(value)

    @property
    def packed(self):
        """``(kind code, float buffer, int buffer)``: the bank's whole state for compiled callers
        (:func:`bank_epoch`); the attributes are views of these buffers."""
        return self._kind, self._fbuf, self._ibuf

    @property
    def diverged(self):
        return (self.flags & FLAG_DIVERGED) != 0

    def correct(self, dx):
        """Error-state feedback: subtract the part dx (n_ch, 5) applied to the NCOs from the state."""
        self.x -= dx

    def state_sigma(self):
        """1-sigma of each state (n_ch, 5)."""
        return np.sqrt(np.maximum(np.diagonal(self.P, axis1=1, axis2=2), 0.0))

    def note_correction(self, dx):
        """Called by the inner-loop law after it moved the NCOs by ``dx``: the prefilter's state is
        already corrected in place (``x``), nothing else to update."""

    def describe(self):
        """Parameters for logs and outputs."""
        d = dict(kind=self.kind, T=self.T, spacing_chips=self.spacing_chips, q=self.q)
        if self.kind == "ukf":
            d["ukf"] = self.ukf_params
        if self.kind == "rackf":
            d.update(huber_c=self.huber_c, correction_period=self.correction_period,
                     robust_mode=self.robust_mode, adaptive_stat=self.adaptive_stat,
                     theta_min=self.theta_min)
        return d


def measurement_model(x, D=1.0, T=T_CA, spacing_chips=1.0):
    """Eq. 3 (noise-free) for states x (..., 5) -> (..., 6); numpy reference of the numba model."""
    x = np.asarray(x, dtype=float)
    d = corr_model.tap_offsets(spacing_chips)
    s = 0.5 * x[..., IF] * T
    snc = np.sinc(s / np.pi)
    amp = x[..., IA] * D * snc
    ang = s + x[..., IPHI]
    tau = x[..., ITAU] + BETA_CODE_CARRIER * s
    Rv = corr_model.code_autocorr(tau[..., None] + d)
    out = np.empty(x.shape[:-1] + (NZ,))
    out[..., 0:3] = (amp * np.cos(ang))[..., None] * Rv
    out[..., 3:6] = (amp * np.sin(ang))[..., None] * Rv
    return out
