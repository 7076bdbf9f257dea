"""The SINS/GPS model of Sun et al. 2012 and its augmented UKF family (UKF / AFF-AUKF / AFM-AUKF) plus an EKF.

Model (Sun et al. 2012 §4, "see ref. [11]" = van der Merwe & Wan 2004; NED navigation frame, FRD body
frame, local NED metres at one site; see docs/references.md)
-------------------------------------------------------------------------------------------------
Nominal state (13 parameters): attitude quaternion ``q_nb`` (scalar first), velocity ``v_n``,
position ``p_n`` and gyro bias ``b_g``.  Process noise ``w = [n_g, n_a, n_b]`` (q = 9) enters
non-additively, measurement ``z = [p_n; v_n] + v`` (m = 6).  Per IMU interval Δt with increments
(Δθ̃, Δṽ) (body FRD)::

    θ      = Δθ̃ − (b_g + n_g) Δt                         (rotation vector of the body)
    Δv_b   = Δṽ − n_a Δt;   Δv_b += ½ θ × Δv_b           (first-order rotation compensation)
    q_nb⁺  = q(−ω_ie Δt) ⊗ q_nb ⊗ q(θ)                   (renormalised)
    v_n⁺   = v_n + C_nb Δv_b + (g_n − 2 ω_ie × v_n) Δt
    p_n⁺   = p_n + ½ (v_n + v_n⁺) Δt
    b_g⁺   = b_g + n_b Δt

The paper prints no model equations; this is the flat-Earth model of van der Merwe & Wan 2004
(q ⊗ q(θ), v += (C f + g)Δt, p += vΔt, b += n_b Δt), a choice of this project, with three additions
that cost nothing and remove model errors the simulated sensors would otherwise show: the site's
Earth rate (the gyros sense 15 °/h, the size of the 10 °/h bias, and a flat-Earth model turns it
into a yaw drift), the rotation compensation of Δṽ (the swinging base turns 0.08° per 10 ms
interval) and the trapezoidal position update.  The noise variances are per-sample:
``var(n_g) = ARW²/Δt``, ``var(n_a) = VRW²/Δt``, ``var(n_b) = σ_bw²/Δt`` (σ_bw: bias random walk).

Quaternion handling: error-state attitude, the quaternion outside the sigma set
-------------------------------------------------------------------------------
The covariance is carried on the 12-dimensional tangent space ``δx = [φ, δv, δp, δb]``
(``ATT, VEL, POS, BG``), with the nav-frame attitude error ``C_nb = exp([φ×]) Ĉ_nb``.  A sigma point
is ``q_i = q(φ_i) ⊗ q̂``; after propagation the points are mapped back relative to the propagated
centre point (``φ_i = rotvec(q_i ⊗ q_ref⁻¹)``), averaged, and the mean is folded into the nominal
quaternion (the USQUE construction of Crassidis & Markley 2003).  Why: with the 4-parameter
quaternion of the paper the covariance is singular along the unit-norm constraint (rank 12 of 13
after normalisation), so its Cholesky factor — needed for every sigma draw, and the P⁻¹ of eq. 11 —
exists only with jitter, and a normalised mean of quaternion points is biased.  The price is
L = n + q + m = 12 + 9 + 6 = 27 instead of the paper's 28 (L′ = n + m = 18 instead of 19); the
sigma-point structure, the weights and the fading equations are unchanged.

Filters (Sun et al. 2012 §3)
----------------------------
* :class:`QuatAUKF` ``mode=None`` — the "UKF" of Table 1: augmented UKF, ``x^a = [δx; w; v]``,
  ``P^a = diag(P, Q, R)``, L = n + q + m, 2L+1 points, every IMU interval (steps 1–3); at a GPS epoch
  the measurement points ζ_i = h(χ_i^x, χ_i^v) are the propagated points of the last interval
  (step 4) and the update is ``K = P_xz P_zz⁻¹`` (step 8 without fading).
* ``mode="aff"`` / ``"afm"`` — at a GPS epoch the fading factor λ (eq. 1) or fading matrix S
  (eqs. 5–10) from the sigma-point equivalents (eqs. 11–12, ``A = H P′ Hᵀ``), the faded
  prediction ``P^l = ½(S P′ + P′ Sᵀ) + (P − P′)`` (eq. 13 with S P′ symmetrised, a choice of this
  project: S P′ itself is not symmetric), then the redraw
  ``x^b = [δx; v]``, ``P^b = diag(P^l, R)``, L′ = n + m (steps 5–8).  The functions are those of
  :mod:`ultratight.fusion.estimators.adaptive` (``fading_terms``, ``fading_factor``, ``fading_matrix``,
  ``apply_fading``); the zero-column set of H is the model's (H has non-zero columns only on
  position and velocity; a choice of this project, the paper does not say).
* Multi-rate reading of P′ (the paper filters at one rate): P′ is the covariance of the posterior
  sigma points (n-dimensional set, 2n+1 points) propagated through the noise-free model over all the
  IMU intervals up to the next GPS epoch, without redraws, so ``P − P′`` is the process noise
  accumulated over that interval (the paper's ``Q = P − P′``).
* :class:`QuatEKF` — the same model linearised (error-state EKF), for the cross-check.

Hot path: the point propagation is a numba kernel over all points (:func:`propagate_points`);
one 100 Hz step of the L = 27 set costs tens of microseconds (``benchmarks/bench_afm.py``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from ultratight.chi2 import chdtri
from ultratight.constants import OMEGA_E
from ultratight.errors import FilterError
from ultratight.fusion.estimators.adaptive import apply_fading, fading_factor, fading_matrix, fading_terms
from ultratight.fusion.estimators.filters import aukf_measure, gain_update, kf_update, unscented_scheme
from ultratight.fusion.estimators.guards import check_covariance, cholesky_lower, symmetrize
from ultratight.ins.attitude import (dcm_to_euler, dcm_to_quat, euler_to_dcm, quat_mult, quat_mult_tuple,
                                     quat_normalize, quat_normalize_tuple, quat_to_dcm, rotvec_to_quat,
                                     rotvec_to_quat_tuple, skew)
from ultratight.ins.earth import gravity_l

__all__ = ["ATT", "VEL", "POS", "BG", "N_ERR", "NG", "NA", "NB", "Q_DIM", "M_DIM", "MEAS_COLS",
           "NavModel", "Nominal", "propagate_points", "QuatAUKF", "QuatEKF", "euler_from_q_nb",
           "q_nb_from_euler", "C_lb_from_C_nb", "C_nb_from_C_lb", "process_noise"]

# error-state (covariance) slices
ATT = slice(0, 3)   # nav-frame attitude error φ, rad
VEL = slice(3, 6)   # δv_n, m/s
POS = slice(6, 9)   # δp_n, m
BG = slice(9, 12)   # δb_g, rad/s
N_ERR = 12
# process-noise slices (w)
NG = slice(0, 3)    # gyro white noise, rad/s per sample
NA = slice(3, 6)    # accelerometer white noise, m/s² per sample
NB = slice(6, 9)    # gyro-bias driving noise, rad/s² per sample
Q_DIM = 9
M_DIM = 6           # z = [p_n; v_n]
MEAS_COLS = np.r_[6:9, 3:6]   # error-state columns of z (position rows first, then velocity)

# ENU <-> NED and FLU <-> FRD (both involutions)
_T_NE = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
_T_FB = np.diag([1.0, -1.0, -1.0])


def C_lb_from_C_nb(C_nb):
    """Project attitude C_lb (FLU body → ENU) of a NED/FRD attitude C_nb (works on (..., 3, 3))."""
    return _T_NE @ C_nb @ _T_FB


def C_nb_from_C_lb(C_lb):
    return _T_NE @ C_lb @ _T_FB


def euler_from_q_nb(q_nb):
    """[roll, pitch, yaw] (rad) of q_nb in the project's convention (ultratight.ins.attitude), which
    is the usual NED yaw-pitch-roll sequence: roll right wing down, pitch nose up, yaw from north."""
    return dcm_to_euler(C_lb_from_C_nb(quat_to_dcm(np.asarray(q_nb, float))))


def q_nb_from_euler(euler):
    """q_nb of [roll, pitch, yaw] (rad), inverse of :func:`euler_from_q_nb`."""
    e = np.asarray(euler, float)
    return dcm_to_quat(C_nb_from_C_lb(euler_to_dcm(e[0], e[1], e[2])))


@dataclass(frozen=True)
class NavModel:
    """Site constants of the flat-Earth model: gravity g_n, Earth rate ω_ie^n (NED), IMU interval."""

    g_n: np.ndarray
    w_ie_n: np.ndarray
    dt: float

    @classmethod
    def at_site(cls, lat_rad: float, h_m: float, dt: float) -> "NavModel":
        g_enu = gravity_l(float(lat_rad), float(h_m))
        g_n = np.array([g_enu[1], g_enu[0], -g_enu[2]])
        w = np.array([OMEGA_E * math.cos(lat_rad), 0.0, -OMEGA_E * math.sin(lat_rad)])
        if not dt > 0:
            raise FilterError(f"dt must be > 0 s, got {dt}")
        return cls(g_n, w, float(dt))


@dataclass
class Nominal:
    """The 13-parameter nominal state: q_nb (4), v_n, p_n, b_g."""

    q: np.ndarray
    v: np.ndarray
    p: np.ndarray
    b: np.ndarray

    def copy(self) -> "Nominal":
        return Nominal(self.q.copy(), self.v.copy(), self.p.copy(), self.b.copy())

    def euler(self):
        return euler_from_q_nb(self.q)


def process_noise(gyro_arw, accel_vrw, gyro_bias_rw, dt):
    """Per-sample Q = diag(var n_g, var n_a, var n_b) from ARW (rad/√s), VRW (m/s/√s), bias RW (rad/s/√s)."""
    d = np.concatenate([np.broadcast_to(np.asarray(gyro_arw, float), 3) ** 2,
                        np.broadcast_to(np.asarray(accel_vrw, float), 3) ** 2,
                        np.broadcast_to(np.asarray(gyro_bias_rw, float), 3) ** 2]) / dt
    return np.diag(d)


# --------------------------------------------------------------------------- numba kernels


@njit(cache=True)
def propagate_points(Qs, Vs, Ps, Bs, W, dtheta, dv, dt, g_n, w_ie):
    """The model's f over a set of full-state points, in place: Qs (N,4), Vs, Ps, Bs (N,3);
    W (N,9) process noise [n_g, n_a, n_b] per point (zeros for the noise-free P′ points)."""
    # nav-frame rotation over Δt
    e0, e1, e2, e3 = rotvec_to_quat_tuple(-w_ie[0] * dt, -w_ie[1] * dt, -w_ie[2] * dt)
    for i in range(Qs.shape[0]):
        t0 = dtheta[0] - (Bs[i, 0] + W[i, 0]) * dt
        t1 = dtheta[1] - (Bs[i, 1] + W[i, 1]) * dt
        t2 = dtheta[2] - (Bs[i, 2] + W[i, 2]) * dt
        u0 = dv[0] - W[i, 3] * dt
        u1 = dv[1] - W[i, 4] * dt
        u2 = dv[2] - W[i, 5] * dt
        # rotation compensation Δv_b += ½ θ × Δv_b
        c0 = u0 + 0.5 * (t1 * u2 - t2 * u1)
        c1 = u1 + 0.5 * (t2 * u0 - t0 * u2)
        c2 = u2 + 0.5 * (t0 * u1 - t1 * u0)
        w, x, y, z = Qs[i, 0], Qs[i, 1], Qs[i, 2], Qs[i, 3]
        # C_nb Δv_b (unit quaternion)
        d0 = (1 - 2 * (y * y + z * z)) * c0 + 2 * (x * y - w * z) * c1 + 2 * (x * z + w * y) * c2
        d1 = 2 * (x * y + w * z) * c0 + (1 - 2 * (x * x + z * z)) * c1 + 2 * (y * z - w * x) * c2
        d2 = 2 * (x * z - w * y) * c0 + 2 * (y * z + w * x) * c1 + (1 - 2 * (x * x + y * y)) * c2
        v0, v1, v2 = Vs[i, 0], Vs[i, 1], Vs[i, 2]
        k0 = 2.0 * (w_ie[1] * v2 - w_ie[2] * v1)
        k1 = 2.0 * (w_ie[2] * v0 - w_ie[0] * v2)
        k2 = 2.0 * (w_ie[0] * v1 - w_ie[1] * v0)
        Vs[i, 0] = v0 + d0 + (g_n[0] - k0) * dt
        Vs[i, 1] = v1 + d1 + (g_n[1] - k1) * dt
        Vs[i, 2] = v2 + d2 + (g_n[2] - k2) * dt
        Ps[i, 0] += 0.5 * (v0 + Vs[i, 0]) * dt
        Ps[i, 1] += 0.5 * (v1 + Vs[i, 1]) * dt
        Ps[i, 2] += 0.5 * (v2 + Vs[i, 2]) * dt
        Bs[i, 0] += W[i, 6] * dt
        Bs[i, 1] += W[i, 7] * dt
        Bs[i, 2] += W[i, 8] * dt
        r0, r1, r2, r3 = rotvec_to_quat_tuple(t0, t1, t2)
        a0, a1, a2, a3 = quat_mult_tuple(e0, e1, e2, e3, w, x, y, z)
        a0, a1, a2, a3 = quat_mult_tuple(a0, a1, a2, a3, r0, r1, r2, r3)
        Qs[i, 0], Qs[i, 1], Qs[i, 2], Qs[i, 3] = quat_normalize_tuple(a0, a1, a2, a3)


@njit(cache=True)
def points_from_chart(q, v, p, b, D):
    """Full-state points of chart offsets D (N, 12) around the nominal (q(φ) ⊗ q̂, v̂ + δv, ...)."""
    n = D.shape[0]
    Qs = np.empty((n, 4))
    Vs = np.empty((n, 3))
    Ps = np.empty((n, 3))
    Bs = np.empty((n, 3))
    for i in range(n):
        r0, r1, r2, r3 = rotvec_to_quat_tuple(D[i, 0], D[i, 1], D[i, 2])
        a0, a1, a2, a3 = quat_mult_tuple(r0, r1, r2, r3, q[0], q[1], q[2], q[3])
        Qs[i, 0], Qs[i, 1], Qs[i, 2], Qs[i, 3] = quat_normalize_tuple(a0, a1, a2, a3)
        for k in range(3):
            Vs[i, k] = v[k] + D[i, 3 + k]
            Ps[i, k] = p[k] + D[i, 6 + k]
            Bs[i, k] = b[k] + D[i, 9 + k]
    return Qs, Vs, Ps, Bs


@njit(cache=True)
def chart_of_points(Qs, Vs, Ps, Bs, q_ref):
    """Chart coordinates (N, 12) of full-state points: φ = rotvec(q_i ⊗ q_ref⁻¹), v, p, b as they are."""
    n = Qs.shape[0]
    out = np.empty((n, 12))
    for i in range(n):
        a0, a1, a2, a3 = quat_mult_tuple(Qs[i, 0], Qs[i, 1], Qs[i, 2], Qs[i, 3],
                                         q_ref[0], -q_ref[1], -q_ref[2], -q_ref[3])
        a0, a1, a2, a3 = quat_normalize_tuple(a0, a1, a2, a3)
        vn = math.sqrt(a1 * a1 + a2 * a2 + a3 * a3)
        if vn < 1e-8:
            k = 2.0 / a0 * (1.0 - vn * vn / (3.0 * a0 * a0))
        else:
            k = 2.0 * math.atan2(vn, a0) / vn
        out[i, 0] = a1 * k
        out[i, 1] = a2 * k
        out[i, 2] = a3 * k
        for j in range(3):
            out[i, 3 + j] = Vs[i, j]
            out[i, 6 + j] = Ps[i, j]
            out[i, 9 + j] = Bs[i, j]
    return out


@njit(cache=True)
def _aukf_predict_kernel(q, v, p, b, Lp, Lq, Lr, xi, wm, wc, dtheta, dv, dt, g_n, w_ie, Qn, Vn, Pn, Bn):
    """One augmented time update (Sun et al. 2012 steps 1–3) fused for speed; also moves the P′ points.

    Points: chart offsets ``xi @ blkdiag(Lp, Lq, Lr)ᵀ`` (step 1, rows of ``xi`` the unit set with the
    √(L+λ) factor); full states through :func:`propagate_points` (step 3); back to the chart
    relative to the propagated centre point; weighted mean folded into the nominal, covariance
    Σ W_c D Dᵀ.  Returns (q, v, p, b, P, D, V): D the centred chart deviations, V the
    measurement-noise parts χ^v of the points (for step 4).
    """
    n_x = Lp.shape[0]
    n_w = Lq.shape[0]
    N = xi.shape[0]
    X = np.ascontiguousarray(xi[:, :n_x]) @ np.ascontiguousarray(Lp.T)
    W = np.ascontiguousarray(xi[:, n_x:n_x + n_w]) @ np.ascontiguousarray(Lq.T)
    V = np.ascontiguousarray(xi[:, n_x + n_w:]) @ np.ascontiguousarray(Lr.T)
    Qs, Vs, Ps, Bs = points_from_chart(q, v, p, b, X)
    propagate_points(Qs, Vs, Ps, Bs, W, dtheta, dv, dt, g_n, w_ie)
    q_ref = Qs[0].copy()
    chart = chart_of_points(Qs, Vs, Ps, Bs, q_ref)
    mean = np.zeros(n_x)
    for i in range(N):
        mean += wm[i] * chart[i]
    D = chart - mean
    P = np.zeros((n_x, n_x))
    for r in range(n_x):
        for c in range(r + 1):
            acc = 0.0
            for i in range(N):
                acc += wc[i] * D[i, r] * D[i, c]
            P[r, c] = acc
            P[c, r] = acc
    qn = quat_normalize(quat_mult(rotvec_to_quat(mean[0:3].copy()), q_ref))
    propagate_points(Qn, Vn, Pn, Bn, np.zeros((Qn.shape[0], 9)), dtheta, dv, dt, g_n, w_ie)
    return qn, mean[3:6].copy(), mean[6:9].copy(), mean[9:12].copy(), P, D, V


# --------------------------------------------------------------------------- filters


def _lam(scheme):
    """λ of an unscented scheme (params n, α, β, κ): λ = α²(n + κ) − n."""
    n, a, _, k = scheme.params
    return a * a * (n + k) - n


def _sigma_stats(chart, wm, wc, q_ref):
    """Mean (folded into a Nominal) and covariance of chart points; also the centred deviations."""
    mean = wm @ chart
    D = chart - mean
    P = symmetrize((D.T * wc) @ D)
    q = quat_normalize(quat_mult(rotvec_to_quat(mean[ATT].copy()), q_ref))
    return Nominal(q, mean[VEL].copy(), mean[POS].copy(), mean[BG].copy()), P, D


class QuatAUKF:
    """Augmented UKF on the SINS/GPS model of Sun et al. 2012; ``mode`` None ("UKF"), "aff" or "afm".

    ``QuatAUKF(model, nominal0, P0 (12×12), Q (9×9 per sample), R (6×6), mode, chi2_alpha=0.01,
    alpha=1, beta=2, kappa=0)``.  ``predict(dtheta_b, dv_b)`` once per IMU interval (FRD body
    increments); ``update(z)`` at a GPS epoch with ``z = [p_n; v_n]`` (after at least one predict).
    ``Q`` may be changed between steps (it is the filter's model, not the truth).  ``last`` holds the
    fade (λ or S diagonal) and innovation of the last update.
    """

    MODES = (None, "aff", "afm")

    def __init__(self, model: NavModel, nominal: Nominal, P0, Q, R, mode=None, chi2_alpha=0.01,
                 alpha=1.0, beta=2.0, kappa=0.0):
        if mode not in self.MODES:
            raise FilterError(f"mode: expected None, 'aff' or 'afm', got {mode!r}")
        if not 0.0 < chi2_alpha < 1.0:
            raise FilterError(f"chi2_alpha must be in (0, 1), got {chi2_alpha}")
        self.model = model
        self.nom = nominal.copy()
        self.P = check_covariance("P0", P0, N_ERR)
        self.Q = check_covariance("Q", Q, Q_DIM)
        self.R = check_covariance("R", R, M_DIM)
        self.mode = mode
        self.threshold = float(chdtri(1, chi2_alpha))       # ε_i of eqs. 1 and 6 (Sun et al. 2012)
        self.ut = (float(alpha), float(beta), float(kappa))
        L = N_ERR + Q_DIM + M_DIM                              # step 1: L = n + q + m
        self.scheme = unscented_scheme(L, *self.ut)           # step 2 weights
        self.scheme0 = unscented_scheme(N_ERR, *self.ut)      # noise-free set for P′
        self.last = {}
        self.guard_count = 0                                  # epochs where the chart guard acted
        self._meas = None
        self._Lq = cholesky_lower(self.Q, "Q")
        self._Lr = cholesky_lower(self.R, "R")
        self._draw_noiseless()

    def set_Q(self, Q):
        self.Q = check_covariance("Q", Q, Q_DIM)
        self._Lq = cholesky_lower(self.Q, "Q")

    def set_nominal(self, nominal: Nominal):
        """Replace the nominal state (e.g. an injected fault); P is left as it is (the filter is not told)."""
        self.nom = nominal.copy()
        self._meas = None
        self._draw_noiseless()

    def _draw_noiseless(self):
        Lp = cholesky_lower(self.P, "P")
        D = self.scheme0.xi @ Lp.T
        self._nl = list(points_from_chart(self.nom.q, self.nom.v, self.nom.p, self.nom.b, D))

    def predict(self, dtheta_b, dv_b):
        """Steps 1–3 over one IMU interval: 2L+1 augmented points through f(x, u, w)."""
        m = self.model
        sch = self.scheme
        Lp = cholesky_lower(self.P, "P")
        Qn, Vn, Pn, Bn = self._nl
        q, v, p, b, P, D, V = _aukf_predict_kernel(
            self.nom.q, self.nom.v, self.nom.p, self.nom.b, Lp, self._Lq, self._Lr, sch.xi, sch.wm, sch.wc,
            np.asarray(dtheta_b, float), np.asarray(dv_b, float), m.dt, m.g_n, m.w_ie_n, Qn, Vn, Pn, Bn)
        self.nom = Nominal(q, v, p, b)
        self.P = P
        self._meas = (D, V)                                   # χ^x deviations and χ^v for step 4
        return self.nom, self.P

    def _noiseless_cov(self):
        Qn, Vn, Pn, Bn = self._nl
        chart = chart_of_points(Qn, Vn, Pn, Bn, Qn[0])
        _, Pnl, _ = _sigma_stats(chart, self.scheme0.wm, self.scheme0.wc, Qn[0])
        return Pnl

    def _chart_guard(self, P):
        """Keep the attitude sigma points inside the chart: σ_φ ≤ (π/2)/√(L+λ) per axis.

        A rotation-vector chart is single-valued only for |φ| < π; a faded covariance whose attitude
        sigma points reach beyond it (a fading factor of a few hundred on the unobservable yaw of a
        static base does) wraps them round and the unscented mean and covariance become meaningless,
        which feeds the next inconsistent innovation and the next fade.  The guard scales the attitude
        rows and columns (a congruence, so P stays positive definite); it never acts on the
        unfaded filters, whose attitude σ stays far below the bound.
        """
        c = math.sqrt(self.scheme.xi.shape[1] + _lam(self.scheme))
        cap = 0.5 * math.pi / c
        sd = np.sqrt(np.diag(P)[ATT])
        if np.all(sd <= cap):
            return P
        d = np.ones(N_ERR)
        d[ATT] = np.minimum(1.0, cap / sd)
        self.guard_count += 1
        return P * np.outer(d, d)

    def _h_chart(self, dx, v):
        return np.concatenate([self.nom.p + dx[POS], self.nom.v + dx[VEL]]) + v

    def update(self, z):
        """Steps 4–8 at a GPS epoch; returns the filter's UpdateResult (chart correction in ``x``)."""
        z = np.asarray(z, float).reshape(-1)
        if z.shape != (M_DIM,) or not np.all(np.isfinite(z)):
            raise FilterError(f"z: expected 6 finite numbers [p_n; v_n], got shape {z.shape}")
        if self._meas is None:
            raise FilterError("update: needs a predict since the last update (propagated sigma points)")
        sch = self.scheme
        D, V = self._meas
        zc = np.concatenate([self.nom.p, self.nom.v])
        Z = zc + D[:, MEAS_COLS] + V                          # step 4: ζ_i = h(χ_i^x, χ_i^v)
        zhat = sch.wm @ Z
        DZ = Z - zhat
        Pzz = symmetrize((DZ.T * sch.wc) @ DZ)
        Pxz = (D.T * sch.wc) @ DZ
        zero = np.zeros(N_ERR)
        fade = 1.0
        if self.mode is None:
            res = gain_update(zero, self.P, z, zhat, Pzz, Pxz, np.zeros((M_DIM, M_DIM)))   # step 8
        else:
            y = z - zhat
            Pnl = self._noiseless_cov()                       # P′ (step 3, noise parts zero)
            H, A, B = fading_terms(Pxz, self.P, Pnl, Pzz)     # eqs. 11–12, A = H P′ Hᵀ
            if self.mode == "aff":
                fade = fading_factor(y, A, B, self.threshold)                          # eq. 1
            else:
                fade = fading_matrix(y, A, B, H, self.threshold, nonzero_cols=MEAS_COLS)  # eqs. 5–10
            Pl = self._chart_guard(apply_fading(self.P, Pnl, fade))   # eq. 13, then the chart guard
            zhat, Pzz, Pxz = aukf_measure(zero, Pl, self._h_chart, self.R, *self.ut, m=M_DIM)  # steps 5–7
            res = gain_update(zero, Pl, z, zhat, Pzz, Pxz, np.zeros((M_DIM, M_DIM)))           # step 8
        self._apply_correction(res.x)
        self.P = res.P
        self._meas = None
        self._draw_noiseless()
        self.last = {"fade": fade, "innovation": res.innovation, "nis": res.nis}
        return res

    def _apply_correction(self, dx):
        n = self.nom
        n.q = quat_normalize(quat_mult(rotvec_to_quat(dx[ATT].copy()), n.q))
        n.v = n.v + dx[VEL]
        n.p = n.p + dx[POS]
        n.b = n.b + dx[BG]


class QuatEKF:
    """Error-state EKF on the same model (for the cross-check of the sigma-point filters).

    Linearised error dynamics (C_nb = exp([φ×]) Ĉ_nb, δb = b − b̂):
    φ̇ = −ω_ie × φ − Ĉ (δb + n_g);  δv̇ = −[f_n ×] φ − 2 ω_ie × δv − Ĉ n_a;  δṗ = δv;  δḃ = n_b,
    discretised with Φ = I + F Δt, Q_d = G Q Gᵀ (G Δt-scaled as the per-sample noise of the model).
    """

    def __init__(self, model: NavModel, nominal: Nominal, P0, Q, R):
        self.model = model
        self.nom = nominal.copy()
        self.P = check_covariance("P0", P0, N_ERR)
        self.Q = check_covariance("Q", Q, Q_DIM)
        self.R = check_covariance("R", R, M_DIM)
        self.H = np.zeros((M_DIM, N_ERR))
        self.H[:, MEAS_COLS] = np.eye(M_DIM)

    def set_Q(self, Q):
        self.Q = check_covariance("Q", Q, Q_DIM)

    def set_nominal(self, nominal: Nominal):
        self.nom = nominal.copy()

    def predict(self, dtheta_b, dv_b):
        m = self.model
        dt = m.dt
        C = quat_to_dcm(self.nom.q)
        f_n = C @ (np.asarray(dv_b, float) / dt)
        F = np.zeros((N_ERR, N_ERR))
        F[ATT, ATT] = -skew(m.w_ie_n)
        F[ATT, BG] = -C
        F[VEL, ATT] = -skew(f_n)
        F[VEL, VEL] = -2.0 * skew(m.w_ie_n)
        F[POS, VEL] = np.eye(3)
        Phi = np.eye(N_ERR) + F * dt
        G = np.zeros((N_ERR, Q_DIM))
        G[ATT, NG] = -C * dt
        G[VEL, NA] = -C * dt
        G[BG, NB] = np.eye(3) * dt
        self.P = symmetrize(Phi @ self.P @ Phi.T + G @ self.Q @ G.T)
        Qs, Vs, Ps, Bs = (a[None].copy() for a in (self.nom.q, self.nom.v, self.nom.p, self.nom.b))
        propagate_points(Qs, Vs, Ps, Bs, np.zeros((1, Q_DIM)), np.asarray(dtheta_b, float),
                         np.asarray(dv_b, float), dt, m.g_n, m.w_ie_n)
        self.nom = Nominal(Qs[0], Vs[0], Ps[0], Bs[0])
        return self.nom, self.P

    def update(self, z):
        z = np.asarray(z, float).reshape(-1)
        zero = np.zeros(N_ERR)
        r = z - np.concatenate([self.nom.p, self.nom.v])
        res = kf_update(zero, self.P, r, self.H, self.R)
        n = self.nom
        n.q = quat_normalize(quat_mult(rotvec_to_quat(res.x[ATT].copy()), n.q))
        n.v, n.p, n.b = n.v + res.x[VEL], n.p + res.x[POS], n.b + res.x[BG]
        self.P = res.P
        return res
