"""The error covariance of the filter as built, with the sensor errors its model leaves out.

The filter's own covariance P (the design model: white noise, bias random walks) sets its gains.
A consumer MEMS part also has constant scale-factor and cross-axis errors (ImuNoise ``gyro_sf``,
``gyro_cross``, ``accel_sf``, ``accel_cross``, 1σ, from its datasheet or grade) that the design
model does not carry.  Estimating them as states was tried and made the walk_0827 drift several
times worse (docs/integrate.md); carrying them as Schmidt consider parameters (Schmidt 1966) changes
the gains too, and on the same log let the GNSS and NHC innovations, whose errors are correlated in
time, into the attitude: the forward drift went from 2.2 m to 5–12 m.  What is kept is the
consider *covariance analysis* of
the suboptimal filter (Gelb 1974, *Applied Optimal Estimation*, §7.2; Maybeck 1979, §6.8): the
gains stay the design filter's K, and the covariance of its actual error is propagated with the
left-out parameters s (covariance P_ss fixed, never updated) beside it::

    e⁻ = Φ e⁺ + Γ s + w          P_t⁻ = Φ P_t Φᵀ + Φ P_ts Γᵀ + Γ P_st Φᵀ + Γ P_ss Γᵀ + Q,
                                 P_ts⁻ = Φ P_ts + Γ P_ss
    e⁺ = (I − K H) e⁻ + K v      P_t⁺ = (I − K H) P_t⁻ (I − K H)ᵀ + K R Kᵀ,  P_ts⁺ = (I − K H) P_ts⁻

with Γ the step's sensitivity to s (:func:`consider_sensitivity`).  The σ the filter reports is
that of P_t; with every consider σ zero P_t equals P.  The estimate is the design filter's, so the
drift does not change; the χ² gate tests innovations against P_t (the innovation covariance of the
filter as built: H P_t Hᵀ + R).
"""

from __future__ import annotations

import numpy as np

from ultratight.ins import error_model as em

# off-diagonal (i, j) entries of the cross-axis matrix, in the order of the parameters
CROSS_PAIRS = ((0, 1), (0, 2), (1, 0), (1, 2), (2, 0), (2, 1))
# per parameter of one sensor: the axis whose reading is wrong (i) and the axis it senses (j)
_SEL_READ = np.eye(3)[:, [0, 1, 2] + [i for i, _ in CROSS_PAIRS]]          # (3, 9): C @ it = C's column i
_SEL_SENSED = np.eye(3)[[0, 1, 2] + [j for _, j in CROSS_PAIRS]]           # (9, 3): it @ inc = inc[j]


def consider_sensitivity(C, dth, dv, n_states):
    """Γ (n_states × 18): the error state's change over one step per unit consider parameter.

    Parameters (measured = (I + S + M) true; S diagonal scale factors, M the off-diagonal
    cross-axis terms): gyro scale factors x, y, z; gyro cross-axis (i, j), i ≠ j, in the order of
    :data:`CROSS_PAIRS`; then the same for the accelerometer.  The rate error δω_i = s_i ω_i +
    m_ij ω_j drives the attitude error as a gyro bias does (φ̇ = −C δω), the specific-force error
    the velocity error as an accelerometer bias does (δv̇ = C δf); over a step the body increments
    ``dth``, ``dv`` (rad, m/s: the step's sums) replace ω dt and f dt.  ``C``: C_lb (body FLU to ENU)."""
    G = np.zeros((n_states, 18))
    Cr = C @ _SEL_READ
    G[em.ATT, 0:9] = -Cr * (_SEL_SENSED @ dth)
    G[em.VEL, 9:18] = Cr * (_SEL_SENSED @ dv)
    return G


def consider_sigmas(noise):
    """(18,) 1σ of the parameters of :func:`consider_sensitivity` from an ImuNoise."""
    return np.concatenate([np.full(3, noise.gyro_sf), np.full(6, noise.gyro_cross),
                           np.full(3, noise.accel_sf), np.full(6, noise.accel_cross)])


class ConsiderCovariance:
    """P_t and P_ts of the module docstring beside the design filter's P.

    The considered parameters: the sensors' 18 (those with a σ above zero) and, with ``nhc_sigma``,
    two constant offsets of the NHC rows (body lateral and vertical velocity, σ ``nhc_sigma`` each):
    the design filter takes the constraint's error as white, σ ``nhc_sigma`` at every row; a body
    whose forward axis is held a few degrees off its path (a handheld unit, a mount's residual
    misalignment) violates it by the same amount row after row.  Their Γ is zero; they enter the
    NHC rows (:meth:`update` ``nhc=True``), where the innovation is H e + b + v:
    e⁺ = (I − K H) e⁻ − K b − K v."""

    def __init__(self, noise, P0, nhc_sigma=None):
        sd = consider_sigmas(noise)
        self.keep = sd > 0.0
        self.n_sensor = int(self.keep.sum())
        extra = [] if nhc_sigma is None else [float(nhc_sigma)] * 2
        self.pss = np.concatenate([sd[self.keep] ** 2, np.square(extra)])
        self.on = bool(self.pss.size)
        self.Pt = np.array(P0, float)
        self.Pts = np.zeros((self.Pt.shape[0], self.pss.size))

    track = False       # keep each node's composite update (L, J, N) and its step's Γ, Q: the smoother's

    def predict(self, Phi, Qd, C, dth, dv):
        """One covariance step (Φ, Q_d of the design model; C_lb and the step's body increments)."""
        if not self.on:
            return
        n = Phi.shape[0]
        G6 = np.zeros((6, self.pss.size))            # Γ has rows in the attitude and velocity blocks only
        G = consider_sensitivity(C, dth, dv, 6)
        G6[:, :self.n_sensor] = G if self.n_sensor == 18 else G[:, self.keep]
        A = Phi @ self.Pts
        AG = A @ G6.T
        Pt = Phi @ self.Pt @ Phi.T + Qd
        Pt[:, :6] += AG
        Pt[:6, :] += AG.T
        Pt[:6, :6] += (G6 * self.pss) @ G6.T
        self.Pt = 0.5 * (Pt + Pt.T)
        A[:6] += G6 * self.pss
        self.Pts = A
        if self.track:                                # the node's composite update e⁺ = L e⁻ − J s + η
            self.G = np.zeros((n, self.pss.size))
            self.G[:6] = G6
            self.Q = Qd
            self.L, self.J, self.N = np.eye(n), np.zeros((n, self.pss.size)), np.zeros((n, n))

    def update(self, P_design, H, R, nhc=False):
        """An update of the design filter with prior ``P_design`` and rows (H, R): its gain applied
        to P_t and P_ts; ``nhc``: the rows are the NHC's (lateral, vertical), which carry the two
        constant offsets."""
        if not self.on:
            return
        PHt = P_design @ H.T
        K = np.linalg.solve(H @ PHt + R, PHt.T).T
        A = np.eye(K.shape[0]) - K @ H
        KRK = K @ R @ K.T
        Pt = A @ self.Pt @ A.T + KRK
        Pts = A @ self.Pts
        J = A @ self.J if self.track else None
        if nhc and self.pss.size > self.n_sensor:
            b = slice(self.n_sensor, self.n_sensor + 2)
            KB = K @ self.Pts[:, b].T @ A.T
            Pt = Pt + K @ np.diag(self.pss[b]) @ K.T - KB - KB.T
            Pts[:, b] -= K * self.pss[b]
            if self.track:
                J[:, b] += K
        self.Pt = 0.5 * (Pt + Pt.T)
        self.Pts = Pts
        if self.track:
            self.L, self.J, self.N = A @ self.L, J, A @ self.N @ A.T + KRK

    def covariance(self, P_design):
        """The covariance of the filter's actual error (P_t; the design P when nothing is considered)."""
        return self.Pt if self.on else P_design


def consider_smoother(Phi, P_prior, P_post, st):
    """(K, n, n) covariance of the RTS-smoothed solution's actual error.

    The smoother's gains C_k = P⁺_k Φ_{k+1}ᵀ (P⁻_{k+1})⁻¹ are the design filter's (``Phi``,
    ``P_prior``, ``P_post`` as :func:`ultratight.fusion.gins.smoother.rts_backward` takes them).
    With e⁻_{k+1} = Φ e⁺_k + Γ s + w and each node's composite update e⁺ = L e⁻ − J s + η
    (``st``: per node ``Pt``, ``Pts`` after the updates, ``L``, ``J``, ``N`` = Cov η, ``G`` = Γ and
    ``Q`` of the step into it, ``pss``), the smoothed error e^s_k = (I − C Φ) e⁺_k + C e^s_{k+1}
    − C Γ s − C w is written e^s_k = T_k e⁺_k + U_k s + f_k, f_k independent of e⁺_k and s::

        T_k = I − C Φ + C T_{k+1} L_{k+1} Φ,   U_k = C (T_{k+1} (L_{k+1} Γ − J_{k+1}) + U_{k+1} − Γ)
        F_k = C ((T_{k+1} L_{k+1} − I) Q (…)ᵀ + T_{k+1} N_{k+1} T_{k+1}ᵀ + F_{k+1}) Cᵀ
        Ps_k = T P_t Tᵀ + U P_ss Uᵀ + T P_ts Uᵀ + U P_st Tᵀ + F_k

    from T_K = I, U_K = 0, F_K = 0 (the last node's smoothed error is its filtered one)."""
    K, n = P_post.shape[0], P_post.shape[1]
    I = np.eye(n)
    Pss = np.diag(st.pss)
    Ps = np.empty((K, n, n))
    Ps[-1] = st.Pt[-1]
    T, U, F = I, np.zeros((n, st.pss.size)), np.zeros((n, n))
    for k in range(K - 2, -1, -1):
        Pp = P_prior[k + 1]
        Ph = Phi[k + 1]
        try:
            C = np.linalg.solve(Pp, Ph @ P_post[k]).T
        except np.linalg.LinAlgError:
            C = P_post[k] @ Ph.T @ np.linalg.pinv(Pp)
        TL = T @ st.L[k + 1]
        G = st.G[k + 1]
        B = TL - I
        F = C @ (B @ st.Q[k + 1] @ B.T + T @ st.N[k + 1] @ T.T + F) @ C.T
        U = C @ (TL @ G - T @ st.J[k + 1] + U - G)
        T = I - C @ Ph + C @ TL @ Ph
        X = T @ st.Pts[k] @ U.T
        P = T @ st.Pt[k] @ T.T + U @ Pss @ U.T + X + X.T + F
        Ps[k] = 0.5 * (P + P.T)
    return Ps
