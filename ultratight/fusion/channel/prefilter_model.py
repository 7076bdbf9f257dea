"""The prefilter's model (Zhao et al. 2014, §2.1, eqs. 2–3) and the layout of a bank's packed buffers.

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

Time update: the dynamics (eq. 2) are linear, so eqs. 4–8 (cubature points
propagated through f and averaged) equal x <- Phi x, P <- Phi P Phi^T + Q
exactly; :func:`prefilter_model` gives (Phi, Q) by the exact (Van Loan)
discretisation.

This module holds: the state and measurement indices, the prefilter kinds and
option codes, the per-channel status flags, the process model (eq. 2) and its
discretisation, the numpy reference of eq. 3, the unscented-transform weights,
the default initial covariance, and the layout of a bank's packed buffers (the
named segments, the named entries of its parameter vectors and work arrays)
that the compiled kernels (``prefilter_kernels``) and the bank
(``prefilter.PrefilterBank``) share.
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

# --- prefilter kinds and options (the compiled kernels take the integer codes) -------
KIND_CKF, KIND_UKF, KIND_RACKF = 0, 1, 2
KIND_CODES = {"ckf": KIND_CKF, "ukf": KIND_UKF, "rackf": KIND_RACKF}
KINDS = tuple(KIND_CODES)
ROBUST_MODES = ("period", "every")
ADAPT_EPOCH, ADAPT_WINDOW, ADAPT_MEAN = 0, 1, 2   # RACKF adaptive statistic (eq. 38 or windowed)
ADAPTIVE_STAT_CODES = {"epoch": ADAPT_EPOCH, "window": ADAPT_WINDOW, "mean": ADAPT_MEAN}
ADAPTIVE_STATS = tuple(ADAPTIVE_STAT_CODES)

# --- status flags (bit field, per channel, per epoch) ---------------------------------
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


# --- packed buffers of a bank ---------------------------------------------------------
# The float parameters of a bank (segment FSEG_PRM); names are compile-time constants in the kernels.
PRM_T = 0                           # coherent integration time T (s)
PRM_BETA = 1                        # code-carrier ratio beta (chips per carrier radian)
PRM_DHALF = 2                       # half the early-late spacing (chips)
PRM_HUBER_C = 3                     # Huber constant c
PRM_THETA_MIN = 4                   # lower bound of the adaptive factor theta
PRM_UT_WM0 = 5                      # UKF: weight of the centre point in the mean
PRM_UT_WC0 = 6                      # UKF: weight of the centre point in the covariance
PRM_UT_WI = 7                       # UKF: weight of each other point
PRM_UT_SCALE = 8                    # UKF: point spread sqrt(n + lambda)
PRM_P_LIMITS = 9                    # NX entries: divergence limits on the covariance diagonal
PRM_ADAPT_KSIG = PRM_P_LIMITS + NX  # significance margin (sigmas) of the windowed statistics
PRM_MIN_WINDOW = PRM_ADAPT_KSIG + 1   # fewest epochs in a window before the windowed statistics adapt
PRM_PHI_VAR_MAX = PRM_MIN_WINDOW + 1  # phase variance cap phi_sigma_max^2 (rad^2)
N_PRM = 20                          # segment length: the entries above and 3 spare, the size of the packed
                                    # layout that compiled callers cached in other modules were built against
                                    # (numba's cache does not see a change of layout made here)

# The integer parameters of a bank (segment ISEG_IPRM).
IPRM_DO_CORRECTION = 0              # 1 on a RACKF correction epoch (set per epoch)
IPRM_ROBUST_EVERY = 1               # 1: robust_mode "every", 0: "period"
IPRM_ADAPTIVE_STAT = 2              # ADAPT_EPOCH | ADAPT_WINDOW | ADAPT_MEAN
N_IPRM = 3

# The bank's counters (segment ISEG_COUNTERS).
CNT_EPOCH = 0                       # epochs stepped (the RACKF correction phase counts from it)
CNT_CORRECTION_PERIOD = 1           # RACKF correction period (epochs)
N_COUNTERS = 2

# Per-channel RACKF accumulators over the correction period (segment FSEG_ACC, one row per channel).
ACC_TR_PZZ = 0                      # sum of tr(P_zz_bar)
ACC_R_WINSOR = 1                    # sum of |r_winsorised|^2
ACC_R_FULL = 2                      # sum of |r|^2
ACC_E_EXPLAINED = 3                 # sum of the innovation energy a state error can explain
ACC_TR_R = 4                        # sum of tr(R) (with the epoch's R scale)
ACC_LAM = 5                         # held measurement-noise scale lam (kept across windows)
ACC_COUNT = 6                       # epochs in the window
ACC_INNOV_SUM = 7                   # NZ columns: sum of the bit-wiped, winsorised innovations
NACC = ACC_INNOV_SUM + NZ

# Work arrays of one channel update: W1 (N_W1, NZ) rows, W2 (N_W2, NZ, NZ) matrices.
N_PTS = 2 * NX + 1                  # sigma points (UKF; the CKF uses the first 2 NX rows)
W1_PTS = 0                          # N_PTS rows: the points (first NX columns)
W1_ZP = W1_PTS + N_PTS              # N_PTS rows: their noise-free outputs h(point)
W1_ZHAT = W1_ZP + N_PTS             # predicted output z_hat
W1_R = W1_ZHAT + 1                  # innovation r
W1_Y = W1_R + 1                     # whitened innovation Lz^-1 r
W1_GAMMA = W1_Y + 1                 # Huber factors gamma
W1_HX = W1_GAMMA + 1                # h(x_pred; D = +1) for the bit decision
W1_TMPV = W1_HX + 1                 # state-sized scratch (first NX columns)
N_W1 = W1_TMPV + 1
W2_S = 0                            # Cholesky factor of P (NX x NX corner)
W2_PZZ0 = 1                         # P_zz without R
W2_PZZ = 2                          # P_zz with the (robust) R
W2_PXZ = 3                          # P_xz (first NX rows)
W2_LZ = 4                           # Cholesky factor of P_zz (or of R_bar)
W2_K = 5                            # gain K (first NX rows)
W2_RBAR = 6                         # Huber equivalent noise R_bar
W2_TMPM = 7                         # state-sized scratch matrix (NX x NX corner)
N_W2 = 8

# Segments of the packed float buffer, in order; packed_float_offsets(n)[FSEG_k] is where segment k starts.
(FSEG_X, FSEG_P, FSEG_XPOST, FSEG_X0, FSEG_P0, FSEG_INNOV, FSEG_NIS, FSEG_THETA, FSEG_ACC, FSEG_PHI, FSEG_QD,
 FSEG_R, FSEG_PRM, FSEG_W1, FSEG_W2, FSEG_END) = range(16)
# Segments of the packed int buffer, in order.
ISEG_FLAGS, ISEG_ACTIVE, ISEG_IPRM, ISEG_RESETS, ISEG_COUNTERS, ISEG_END = range(6)


@njit(cache=True)
def packed_float_offsets(n):
    """Start offsets of the packed float buffer's segments for ``n`` channels, indexed by ``FSEG_*``:
    x (n, NX), P (n, NX, NX), x_post (n, NX), x0 (n, NX), P0 (n, NX, NX), innov (n, NZ), nis (n),
    theta (n), acc (n, NACC), Phi (NX, NX), Qd (NX, NX), R (NZ, NZ), prm (N_PRM), W1 (N_W1, NZ),
    W2 (N_W2, NZ, NZ), and the end (a tuple: the per-channel epoch asks for it and allocates nothing)."""
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
def packed_int_offsets(n):
    """Start offsets of the packed int buffer's segments for ``n`` channels, indexed by ``ISEG_*``:
    flags (n), active (n), iprm (N_IPRM), n_resets (n), counters (N_COUNTERS), and the end; a tuple."""
    return (0, n, 2 * n, 2 * n + N_IPRM, 3 * n + N_IPRM, 3 * n + N_IPRM + N_COUNTERS)
