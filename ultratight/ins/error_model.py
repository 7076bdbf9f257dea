"""SINS error-state models (15 and 17 states) in the ENU local-level frame.

Error state (all "estimated minus true"), named slices/indices:

===========  =====  ==========================================================
ATT          0:3    attitude error phi (rad, ENU), C_lb_est = (I - [phi x]) C_lb
VEL          3:6    velocity error dv_l (m/s, ENU)
POS          6:9    position error [dlat (rad), dlon (rad), dh (m)]
BG           9:12   gyro bias (rad/s, body FLU): measured rate = true + BG
BA           12:15  accelerometer bias (m/s^2, body FLU): measured f = true + BA
CLK          15     receiver clock bias c*dt (m)              (17-state model only)
DRIFT        16     receiver clock drift c*d(dt)/dt (m/s)     (17-state model only)
===========  =====  ==========================================================

Continuous model ``dx/dt = F x + G w`` with white noise ``w`` of power spectral
density ``Qc`` (diagonal) ordered as NOISE_* below: gyro white noise (ARW, rad/sqrt(s)),
accelerometer white noise (VRW, (m/s)/sqrt(s)), gyro-bias and accel-bias driving noise
(first-order Gauss-Markov with correlation time tau, or random walk when tau = inf), and
clock-bias / clock-drift white noise (17-state only).

Equations (psi-angle form of the phi-angle model, Groves 2013 and Savage 1998; see
docs/references.md):
    phi'  = -w_in x phi + dw_in - C_lb bg
    dv'   = f_l x phi + v x (2 dw_ie + dw_en) - (2 w_ie + w_en) x dv + dg + C_lb ba
    dlat' = dvN/(M+h) - vN dh/(M+h)^2
    dlon' = dvE/((N+h) cos lat) + vE tan(lat) dlat/((N+h) cos lat) - vE dh/((N+h)^2 cos lat)
    dh'   = dvU
(derivatives of M, N w.r.t. latitude neglected; gravity partials from
:func:`ultratight.ins.earth.gravity_l` by central differences).
"""

import math

import numpy as np
from numba import njit
from scipy.linalg import expm

from ultratight.constants import OMEGA_E
from ultratight.ins.attitude import dcm_to_rotvec, quat_mult, quat_normalize, quat_to_dcm, rotvec_to_quat
from ultratight.ins.earth import gravity_l, radii

ATT = slice(0, 3)
VEL = slice(3, 6)
POS = slice(6, 9)
BG = slice(9, 12)
BA = slice(12, 15)
CLK = 15
DRIFT = 16
N15 = 15
N17 = 17

NOISE_GYRO = slice(0, 3)
NOISE_ACCEL = slice(3, 6)
NOISE_BG = slice(6, 9)
NOISE_BA = slice(9, 12)
NOISE_CLK = 12
NOISE_DRIFT = 13
NW15 = 12
NW17 = 14


def _skew(v):
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _as_dcm(att):
    att = np.asarray(att, float)
    return quat_to_dcm(att) if att.shape == (4,) else att


def F_matrix(att, vel_l, llh, f_b, n_states=N15, tau_g=math.inf, tau_a=math.inf):
    """Continuous-time error dynamics matrix F (n_states x n_states).

    ``att``: q_lb (4,) or C_lb (3, 3); ``vel_l`` ENU m/s; ``llh`` [lat, lon, h];
    ``f_b`` specific force in body (m/s^2; e.g. dv_b / dt); bias correlation times (s).
    """
    if n_states not in (N15, N17):
        raise ValueError("n_states must be 15 or 17")
    F = np.zeros((n_states, n_states))
    fill_f_matrix(F, np.ascontiguousarray(_as_dcm(att), dtype=float), np.asarray(vel_l, float), float(llh[0]),
                  float(llh[2]), np.asarray(f_b, float), float(tau_g), float(tau_a))
    if n_states == N17:
        F[CLK, DRIFT] = 1.0
    return F


@njit(cache=True)
def _skew_into(F, r0, c0, v, sign):
    """``F[r0:r0+3, c0:c0+3] = sign * [v x]``."""
    F[r0, c0 + 1] = -sign * v[2]
    F[r0, c0 + 2] = sign * v[1]
    F[r0 + 1, c0] = sign * v[2]
    F[r0 + 1, c0 + 2] = -sign * v[0]
    F[r0 + 2, c0] = -sign * v[1]
    F[r0 + 2, c0 + 1] = sign * v[0]


@njit(cache=True)
def fill_f_matrix(F, C, vel, lat, h, f_b, tau_g, tau_a):
    """The 15 navigation / bias rows and columns of :func:`F_matrix` written into the zeroed ``F``
    (Groves 2013 ch. 14 in ENU; gravity partials by central differences of the model the
    mechanisation uses), compiled: one call instead of a few dozen small array operations."""
    vE, vN = vel[0], vel[1]
    rm, rn = radii(lat)
    sl, cl = math.sin(lat), math.cos(lat)
    tl = sl / cl
    Rm, Rn = rm + h, rn + h
    w_ie = np.array([0.0, OMEGA_E * cl, OMEGA_E * sl])
    w_en = np.array([-vN / Rm, vE / Rn, vE * tl / Rn])
    f_l = np.zeros(3)
    for i in range(3):
        for k in range(3):
            f_l[i] += C[i, k] * f_b[k]
    M1 = np.zeros((3, 3))            # d w_ie / d pos
    M1[1, 0] = -OMEGA_E * sl
    M1[2, 0] = OMEGA_E * cl
    Mav = np.zeros((3, 3))           # d w_en / d vel
    Mav[0, 1] = -1.0 / Rm
    Mav[1, 0] = 1.0 / Rn
    Mav[2, 0] = tl / Rn
    M2 = np.zeros((3, 3))            # d w_en / d pos
    M2[0, 2] = vN / (Rm * Rm)
    M2[1, 2] = -vE / (Rn * Rn)
    M2[2, 0] = vE / (Rn * cl * cl)
    M2[2, 2] = -vE * tl / (Rn * Rn)
    dlat, dh = 1e-6, 1.0
    g_n, g_s = gravity_l(lat + dlat, h), gravity_l(lat - dlat, h)
    g_u, g_d = gravity_l(lat, h + dh), gravity_l(lat, h - dh)
    Mg = np.zeros((3, 3))
    for i in range(3):
        Mg[i, 0] = (g_n[i] - g_s[i]) / (2 * dlat)
        Mg[i, 2] = (g_u[i] - g_d[i]) / (2 * dh)
    _skew_into(F, 0, 0, w_ie + w_en, -1.0)                 # attitude <- attitude
    _skew_into(F, 3, 0, f_l, 1.0)                          # velocity <- attitude
    _skew_into(F, 3, 3, 2.0 * w_ie + w_en, -1.0)           # velocity <- velocity (Coriolis part)
    sv = np.zeros((3, 3))
    _skew_into(sv, 0, 0, vel, 1.0)
    M12 = 2.0 * M1 + M2
    for i in range(3):
        for j in range(3):
            F[i, 3 + j] = Mav[i, j]
            F[i, 6 + j] = M1[i, j] + M2[i, j]
            F[i, 9 + j] = -C[i, j]
            F[3 + i, 12 + j] = C[i, j]
            a = 0.0
            b = 0.0
            for k in range(3):
                a += sv[i, k] * Mav[k, j]
                b += sv[i, k] * M12[k, j]
            F[3 + i, 3 + j] += a
            F[3 + i, 6 + j] = b + Mg[i, j]
    F[6, 4] = 1.0 / Rm
    F[6, 8] = -vN / (Rm * Rm)
    F[7, 3] = 1.0 / (Rn * cl)
    F[7, 6] = vE * tl / (Rn * cl)
    F[7, 8] = -vE / (Rn * Rn * cl)
    F[8, 5] = 1.0
    if math.isfinite(tau_g):
        for i in range(3):
            F[9 + i, 9 + i] = -1.0 / tau_g
    if math.isfinite(tau_a):
        for i in range(3):
            F[12 + i, 12 + i] = -1.0 / tau_a


def G_matrix(att, n_states=N15):
    """Noise input matrix G (n_states x 12 or 17 x 14), inputs ordered as NOISE_*."""
    C = _as_dcm(att)
    nw = NW15 if n_states == N15 else NW17
    G = np.zeros((n_states, nw))
    G[ATT, NOISE_GYRO] = -C
    G[VEL, NOISE_ACCEL] = C
    G[BG, NOISE_BG] = np.eye(3)
    G[BA, NOISE_BA] = np.eye(3)
    if n_states == N17:
        G[CLK, NOISE_CLK] = 1.0
        G[DRIFT, NOISE_DRIFT] = 1.0
    return G


def noise_psd(errors, n_states=N15, clock_psd=(0.0, 0.0)):
    """Diagonal noise PSD Qc (vector) for :class:`ultratight.ins.imu.ImuErrors`.

    Gauss-Markov bias with steady-state sigma and tau: driving PSD 2 sigma^2 / tau.
    ``clock_psd`` = (S_b m^2/s, S_d m^2/s^3) for the 17-state model.
    """
    nw = NW15 if n_states == N15 else NW17
    q = np.zeros(nw)
    q[NOISE_GYRO] = np.asarray(errors.gyro_arw, float) ** 2
    q[NOISE_ACCEL] = np.asarray(errors.accel_vrw, float) ** 2
    if math.isfinite(errors.gyro_gm_tau):
        q[NOISE_BG] = 2.0 * np.asarray(errors.gyro_gm_sigma, float) ** 2 / errors.gyro_gm_tau
    if math.isfinite(errors.accel_gm_tau):
        q[NOISE_BA] = 2.0 * np.asarray(errors.accel_gm_sigma, float) ** 2 / errors.accel_gm_tau
    if n_states == N17:
        q[NOISE_CLK], q[NOISE_DRIFT] = clock_psd
    return q


def discretize(F, G, Qc, dt):
    """Van Loan discretisation: Phi = exp(F dt), Qd = int Phi G Qc G^T Phi^T (exact for constant F)."""
    n = F.shape[0]
    Qc = np.asarray(Qc, float)
    GQG = G @ (np.diag(Qc) if Qc.ndim == 1 else Qc) @ G.T
    A = np.zeros((2 * n, 2 * n))
    A[:n, :n] = -F
    A[:n, n:] = GQG
    A[n:, n:] = F.T
    B = expm(A * dt)
    Phi = B[n:, n:].T
    Qd = Phi @ B[:n, n:]
    return Phi, 0.5 * (Qd + Qd.T)


def taylor_phi(F, dt):
    """Φ = I + F dt + (F dt)²/2, the transition matrix of :func:`discretize_taylor` alone."""
    Fd = F * dt
    return np.eye(F.shape[0]) + Fd + 0.5 * Fd @ Fd


def discretize_taylor(F, G, Qc, dt):
    """Second-order Taylor discretisation (fast; for small F dt)."""
    Phi = taylor_phi(F, dt)
    Qc = np.asarray(Qc, float)
    GQG = G @ (np.diag(Qc) if Qc.ndim == 1 else Qc) @ G.T
    Qd = 0.5 * (Phi @ GQG + GQG @ Phi.T) * dt
    return Phi, 0.5 * (Qd + Qd.T)


def apply_feedback(x_sins, dx):
    """Correct a SINS state (ultratight.ins.sins layout) in place with the estimated error state.

    Attitude: C_lb <- (I + [phi x]) C_lb (exactly: q_lb <- q(phi) * q_lb); velocity and
    position: subtract.  The bias / clock entries are not touched here: accumulate them into
    the bias estimates used to compensate the increments (:func:`compensate_increments`).
    Returns nothing; the caller zeroes the corresponding error-state entries (closed loop).
    """
    q = x_sins[0:4]
    qn = quat_normalize(quat_mult(rotvec_to_quat(np.ascontiguousarray(dx[ATT], dtype=float)), q))
    x_sins[0:4] = qn
    x_sins[4:7] -= dx[VEL]
    x_sins[7:10] -= dx[POS]


def feedback_and_reset(x_sins, dx, bias_est):
    """Closed-loop reset: apply ATT/VEL/POS to the SINS state, add BG/BA to ``bias_est``
    (array [bg (3), ba (3)], rad/s and m/s^2, in place) and zero those 15 error states in ``dx``
    (in place).  Clock states (17-state model) are left in ``dx``."""
    apply_feedback(x_sins, dx)
    bias_est[0:3] += dx[BG]
    bias_est[3:6] += dx[BA]
    dx[0:N15] = 0.0


def compensate_increments(dtheta, dv, bg, ba, dt):
    """Remove estimated biases (rad/s, m/s^2) from increments: returns (dtheta - bg dt, dv - ba dt)."""
    return dtheta - np.asarray(bg) * dt, dv - np.asarray(ba) * dt


def true_error_state(q_est, vel_est, llh_est, q_true, vel_true, llh_true):
    """Error state (ATT, VEL, POS parts; 9,) of an estimate against truth, same convention as F."""
    C_e = quat_to_dcm(np.asarray(q_est, float))
    C_t = quat_to_dcm(np.asarray(q_true, float))
    dx = np.zeros(9)
    dx[0:3] = dcm_to_rotvec(C_t @ C_e.T)
    dx[3:6] = np.asarray(vel_est) - np.asarray(vel_true)
    dx[6:9] = np.asarray(llh_est) - np.asarray(llh_true)
    return dx
