"""Air-data fusion of Duan et al. 2024: the 9-state total-state filter in the ESD frame.

State ``X = [λ, L, h, V_x, V_y, V_z, θ, ψ, φ]`` (longitude, latitude rad; altitude m; ESD velocity
m/s; pitch, yaw, roll rad), process ``Ẋ = f(X, u) + w`` (eq. 1) with u the IMU increments between
two filter epochs, observation the first six states (eqs. 2–3, linear).

**Total state vs the project's error-state filters.** The loose/tight integrations of
:mod:`ultratight.fusion.coupling.tight` estimate an *error* state of a SINS that runs in local-level ENU
with quaternion attitude and IMU bias states, and feed the estimate back. The paper's filter
instead carries the navigation solution itself (positions, velocities, Euler angles) as the state,
no sensor biases, and the mechanization is the process model: every cubature point is pushed
through the strapdown equations (:func:`propagate`), and the EKF (eqs. 7–8) propagates the mean
through the same equations with a finite-difference Jacobian F. The cubature machinery
(:func:`ultratight.fusion.estimators.filters.ckf_predict` / ``ckf_update``, Zhao et al. 2014 eqs. 4–17) and the
EKF functions of :mod:`ultratight.fusion.estimators.filters` are used unchanged; Euler angles are averaged
as numbers (fine away from ψ = ±π and θ = ±π/2, true of this flight).

Mechanization (this project's choice, the paper prints none: Titterton & Weston ch. 3, ESD): per IMU interval dt,
``C_bn ← (I − [ζ×]) C_bn R(Δθ)`` with ζ = (ω_ie + ω_en) dt (Euler rates from body rates, done on
the DCM), ``V ← V + (C̄_bn Δv/dt + g − (2ω_ie + ω_en) × V) dt``, ``λ̇ = V_x/((R_N+h) cos L)``,
``L̇ = −V_y/(R_M+h)``, ``ḣ = −V_z`` (trapezoidal); WGS-84 radii and normal gravity of
:mod:`ultratight.ins.earth`.

FADS/GNSS pre-fusion: eq. 4 (:func:`blend`) for altitude and velocity, the vertical-speed
adaptive altitude noise of eqs. 9–10 (:func:`adaptive_altitude_variance`).
"""

import math

import numpy as np
from numba import njit

from ultratight.airdata.frames import euler_to_dcm
from ultratight.constants import OMEGA_E
from ultratight.fusion.estimators.filters import ckf_predict, ckf_update, ekf_predict, ekf_update
from ultratight.ins.earth import gravity_nu, radii

# state layout (Duan et al. 2024, §1.1)
I_LON, I_LAT, I_H = 0, 1, 2
POS = slice(0, 3)
VEL = slice(3, 6)
I_VZ = 5
ATT = slice(6, 9)
I_PITCH, I_YAW, I_ROLL = 6, 7, 8
N_STATE = 9
N_OBS = 6
H_OBS = np.hstack([np.eye(N_OBS), np.zeros((N_OBS, N_STATE - N_OBS))])   # eq. 3: the first six states
# finite-difference steps of the EKF Jacobian (rad, rad, m, m/s x3, rad x3)
_JAC_STEP = np.array([1e-7, 1e-7, 0.5, 0.01, 0.01, 0.01, 1e-5, 1e-5, 1e-5])


@njit(cache=True)
def _propagate_one(x, dtheta, dv, dt, out):
    lon, lat, h = x[0], x[1], x[2]
    v0, v1, v2 = x[3], x[4], x[5]
    th, ps, ph = x[6], x[7], x[8]
    st, ct, sp, cp, sf, cf = math.sin(th), math.cos(th), math.sin(ps), math.cos(ps), math.sin(ph), math.cos(ph)
    C = np.empty((3, 3))
    C[0, 0] = ct * cp
    C[0, 1] = sf * st * cp - cf * sp
    C[0, 2] = cf * st * cp + sf * sp
    C[1, 0] = ct * sp
    C[1, 1] = sf * st * sp + cf * cp
    C[1, 2] = cf * st * sp - sf * cp
    C[2, 0] = -st
    C[2, 1] = sf * ct
    C[2, 2] = cf * ct
    R = np.empty((3, 3))
    Cn = np.empty((3, 3))
    Cb = np.empty((3, 3))
    for k in range(dtheta.shape[0]):
        rm, rn = radii(lat)
        wie0, wie1, wie2 = 0.0, -OMEGA_E * math.cos(lat), -OMEGA_E * math.sin(lat)
        wen0 = v1 / (rm + h)
        wen1 = -v0 / (rn + h)
        wen2 = -v0 * math.tan(lat) / (rn + h)
        z0, z1, z2 = (wie0 + wen0) * dt, (wie1 + wen1) * dt, (wie2 + wen2) * dt
        # body rotation R(Δθ) (Rodrigues)
        a0, a1, a2 = dtheta[k, 0], dtheta[k, 1], dtheta[k, 2]
        ang2 = a0 * a0 + a1 * a1 + a2 * a2
        if ang2 < 1e-12:
            s1 = 1.0 - ang2 / 6.0
            s2 = 0.5 - ang2 / 24.0
        else:
            ang = math.sqrt(ang2)
            s1 = math.sin(ang) / ang
            s2 = (1.0 - math.cos(ang)) / ang2
        R[0, 0] = 1.0 - s2 * (a1 * a1 + a2 * a2)
        R[0, 1] = -s1 * a2 + s2 * a0 * a1
        R[0, 2] = s1 * a1 + s2 * a0 * a2
        R[1, 0] = s1 * a2 + s2 * a0 * a1
        R[1, 1] = 1.0 - s2 * (a0 * a0 + a2 * a2)
        R[1, 2] = -s1 * a0 + s2 * a1 * a2
        R[2, 0] = -s1 * a1 + s2 * a0 * a2
        R[2, 1] = s1 * a0 + s2 * a1 * a2
        R[2, 2] = 1.0 - s2 * (a0 * a0 + a1 * a1)
        for i in range(3):
            for j in range(3):
                Cb[i, j] = C[i, 0] * R[0, j] + C[i, 1] * R[1, j] + C[i, 2] * R[2, j]
        # nav-frame rotation (I - [ζ×]) C
        for j in range(3):
            c0, c1, c2 = Cb[0, j], Cb[1, j], Cb[2, j]
            Cn[0, j] = c0 + z2 * c1 - z1 * c2
            Cn[1, j] = c1 - z2 * c0 + z0 * c2
            Cn[2, j] = c2 + z1 * c0 - z0 * c1
        # specific-force increment with the mean attitude over the interval
        d0 = 0.5 * ((C[0, 0] + Cn[0, 0]) * dv[k, 0] + (C[0, 1] + Cn[0, 1]) * dv[k, 1] + (C[0, 2] + Cn[0, 2]) * dv[k, 2])
        d1 = 0.5 * ((C[1, 0] + Cn[1, 0]) * dv[k, 0] + (C[1, 1] + Cn[1, 1]) * dv[k, 1] + (C[1, 2] + Cn[1, 2]) * dv[k, 2])
        d2 = 0.5 * ((C[2, 0] + Cn[2, 0]) * dv[k, 0] + (C[2, 1] + Cn[2, 1]) * dv[k, 1] + (C[2, 2] + Cn[2, 2]) * dv[k, 2])
        gn, gu = gravity_nu(lat, h)
        w0, w1, w2 = 2.0 * wie0 + wen0, 2.0 * wie1 + wen1, 2.0 * wie2 + wen2
        c0 = w1 * v2 - w2 * v1
        c1 = w2 * v0 - w0 * v2
        c2 = w0 * v1 - w1 * v0
        n0 = v0 + d0 - c0 * dt
        n1 = v1 + d1 + (-gn - c1) * dt
        n2 = v2 + d2 + (-gu - c2) * dt
        m0, m1, m2 = 0.5 * (v0 + n0), 0.5 * (v1 + n1), 0.5 * (v2 + n2)
        lon += m0 / ((rn + h) * math.cos(lat)) * dt
        lat -= m1 / (rm + h) * dt
        h -= m2 * dt
        v0, v1, v2 = n0, n1, n2
        for i in range(3):
            for j in range(3):
                C[i, j] = Cn[i, j]
    out[0], out[1], out[2] = lon, lat, h
    out[3], out[4], out[5] = v0, v1, v2
    s = C[2, 0]
    if s > 1.0:
        s = 1.0
    elif s < -1.0:
        s = -1.0
    out[6] = -math.asin(s)
    yaw = math.atan2(C[1, 0], C[0, 0])
    dyaw = yaw - ps
    dyaw = (dyaw + math.pi) % (2.0 * math.pi) - math.pi     # keep yaw continuous with the input
    out[7] = ps + dyaw
    out[8] = math.atan2(C[2, 1], C[2, 2])


@njit(cache=True)
def propagate(X, dtheta, dv, dt):
    """Mechanization f(X, u) of eq. 1 for rows X (N, 9) over IMU increments (K, 3) of dt each."""
    out = np.empty_like(X)
    for i in range(X.shape[0]):
        _propagate_one(X[i], dtheta, dv, dt, out[i])
    return out


def jacobian(x, dtheta, dv, dt):
    """F = ∂f/∂X by central differences through :func:`propagate` (one batched call); returns (f(x), F)."""
    E = np.diag(_JAC_STEP)
    X = np.vstack([x[None, :], x + E, x - E])
    Y = propagate(X, dtheta, dv, dt)
    F = ((Y[1:1 + N_STATE] - Y[1 + N_STATE:]) / (2.0 * _JAC_STEP)[:, None]).T
    return Y[0], F


# ------------------------------------------------------------------ pre-fusion (eq. 4) and eqs. 9–10

def blend_weight(h_gnss_m):
    """Eq. 4 interpolation weight of m_2: 0 below 1 km, (h_G − 1)/9 (km) to 10 km, 1 above."""
    return np.clip((np.asarray(h_gnss_m, float) / 1000.0 - 1.0) / 9.0, 0.0, 1.0)


def blend(h_gnss_m, z_gnss, z_fads, R_g, R_f1, R_f2):
    """Eq. 4: ``m_j = (R_G z_F + R_Fj z_G)/(R_G + R_Fj)`` blended by GNSS altitude (numpy broadcasting:
    pass ``h[:, None]`` for per-axis arrays)."""
    m1 = (R_g * z_fads + R_f1 * z_gnss) / (R_g + R_f1)
    m2 = (R_g * z_fads + R_f2 * z_gnss) / (R_g + R_f2)
    return m1 + (m2 - m1) * blend_weight(h_gnss_m)


def fads_weight(h_gnss_m, R_g, R_f1, R_f2):
    """Weight c_F of the FADS value in eq. 4: h_GF = (1 − c_F) z_G + c_F z_F (the blend is linear in both)."""
    w = blend_weight(h_gnss_m)
    return (1.0 - w) * R_g / (R_g + R_f1) + w * R_g / (R_g + R_f2)


def fused_variance(h_gnss_m, R_g, R_f1, R_f2):
    """R_G R_F(h) / (R_G + R_F(h)) with R_F interpolated as in eq. 4 (this project's choice for R_kmin)."""
    R_f1, R_f2 = np.asarray(R_f1, float), np.asarray(R_f2, float)
    R_f = R_f1 + (R_f2 - R_f1) * blend_weight(h_gnss_m)
    return R_g * R_f / (R_g + R_f)


def adaptive_altitude_variance(vz, R_min, R_max, v_min=1.0):
    """Eqs. 9–10: R_k = R_kmin for |V_z| < V_min, else [R_kmin + (|V_z| − V_min) R_kmax]/(|V_z| − V_min + 1)."""
    a = np.abs(np.asarray(vz, float)) - v_min
    out = np.where(a < 0.0, R_min, (R_min + np.maximum(a, 0.0) * R_max) / (np.maximum(a, 0.0) + 1.0))
    return float(out) if np.ndim(out) == 0 else out


# ------------------------------------------------------------------ the filter loop

def fads_velocity_h(C_pred, c_f, wind_n=None):
    """Measurement function (rows X (N, 9) → (N, 6)) of the pre-fused observation ``[λ_G, L_G, h_GF, V_GF]``.

    V_GF = (1 − c_F) V_G + c_F V_F with ``V_F = C_pred v_b,F``: the FADS air velocity (body axes) turned
    to ESD with the INS attitude C_pred of the epoch (this project's FADS model). Its expectation given a state X is
    ``(1 − c_F) V + c_F C_pred C_nb(X) V``: the FADS part depends on the state's attitude (it equals V
    only at X's attitude = C_pred). Eq. 3 as printed (h linear) ignores this, and the filter then
    trusts a velocity that carries its own attitude error (|V| δψ ≈ 4 m/s at Mach 8 per 0.1°): it
    diverges (AoA errors of tens of degrees in this scenario). With a known constant wind W the FADS
    ground velocity is ``C_pred v_b,F + W`` and its expectation ``C_pred C_nb(X) (V − W) + W``."""
    c_f = np.asarray(c_f, float)
    w = np.zeros(3) if wind_n is None else np.asarray(wind_n, float)

    def h(X):
        X = np.atleast_2d(X)
        C = euler_to_dcm(X[:, I_PITCH], X[:, I_YAW], X[:, I_ROLL])
        v_b = np.einsum("nji,nj->ni", C, X[:, VEL] - w)             # C_nb(X) (V - W)
        out = np.empty((X.shape[0], N_OBS))
        out[:, :3] = X[:, POS]
        out[:, 3:6] = (1.0 - c_f) * X[:, VEL] + c_f * (v_b @ C_pred.T + w)
        return out
    return h


def inverse_variance(z1, R1, z2, R2):
    """Minimum-variance combination of two independent estimates of one scalar: ``(z, R)``."""
    return (R2 * z1 + R1 * z2) / (R1 + R2), R1 * R2 / (R1 + R2)


def separate_h(wind_n=None):
    """Measurement function (rows X (N, 9) → (N, 9)) of the separate-observation FADS/GNSS/INS filter:
    ``[λ_G, L_G, h, V_G, v_b,F]`` — position (altitude: GNSS and FADS combined per epoch), the GNSS
    velocity (ESD) and the FADS air velocity in body axes, whose expectation is ``C_nb(X) (V − W)``.

    Unlike eq. 4's pre-fused velocity (a fixed combination of the GNSS velocity and the FADS velocity
    turned to ESD with the INS attitude), the two velocities stay apart: the pre-fusion compresses
    six observations into three and mixes the FADS velocity's attitude dependence into the
    velocity, which the filter can then no longer tell apart — measured, it makes the filter's
    vertical velocity and altitude worse than GNSS/INS alone (docs/airdata.md)."""
    w = np.zeros(3) if wind_n is None else np.asarray(wind_n, float)

    def h(X):
        X = np.atleast_2d(X)
        C = euler_to_dcm(X[:, I_PITCH], X[:, I_YAW], X[:, I_ROLL])
        out = np.empty((X.shape[0], N_OBS + 3))
        out[:, :N_OBS] = X[:, :N_OBS]
        out[:, N_OBS:] = np.einsum("nji,nj->ni", C, X[:, VEL] - w)            # C_nb(X) (V - W)
        return out
    return h


def numerical_jacobian(h, x, steps=_JAC_STEP):
    """∂h/∂X (m, 9) by central differences of a row-vectorised h (one batched call)."""
    E = np.diag(steps)
    Y = h(np.vstack([x + E, x - E]))
    n = x.shape[0]
    return ((Y[:n] - Y[n:]) / (2.0 * steps)[:, None]).T


def run(kind, x0, P0, Q, dtheta, dv, imu_dt, per_epoch, measure):
    """Run the 9-state filter over epochs; ``kind`` 'ckf' (cubature, Zhao et al. 2014 §2.2) or 'ekf' (eqs. 7–8).

    ``dtheta``, ``dv``: IMU increments (n_epochs · per_epoch, 3). ``measure(k, x_pred, P_pred)``
    returns (z (m,), R (m, m)) or (z, R, h) with a row-vectorised measurement function h (default:
    the first six states, eq. 3, m = 6) for epoch k (after the prediction), or None to skip the update.
    Returns (x (n_epochs, 9), P diagonal (n_epochs, 9), NIS (n_epochs,)).
    """
    n_ep = dtheta.shape[0] // per_epoch
    xs = np.empty((n_ep, N_STATE))
    ps = np.empty((n_ep, N_STATE))
    nis = np.full(n_ep, np.nan)
    x, P = np.asarray(x0, float).copy(), np.asarray(P0, float).copy()

    def h_rows(X):
        return X[:, :N_OBS]

    for k in range(n_ep):
        th = dtheta[k * per_epoch:(k + 1) * per_epoch]
        dvk = dv[k * per_epoch:(k + 1) * per_epoch]
        if kind == "ckf":
            x, P = ckf_predict(x, P, lambda X: propagate(X, th, dvk, imu_dt), Q, vectorized=True)  # eqs. 4-8
        else:
            fx, F = jacobian(x, th, dvk, imu_dt)
            x, P = ekf_predict(x, P, lambda _x: fx, F, Q)                                     # eqs. 7-8
        meas = measure(k, x, P)
        if meas is not None:
            z, R = meas[0], meas[1]
            h = meas[2] if len(meas) > 2 else None
            if kind == "ckf":
                res = ckf_update(x, P, z, h or h_rows, R, vectorized=True)                      # eqs. 9-17
            elif h is None:
                res = ekf_update(x, P, z, lambda _x: H_OBS @ _x, H_OBS, R)
            else:
                res = ekf_update(x, P, z, lambda _x: h(_x)[0], numerical_jacobian(h, x), R)
            x, P = res.x, res.P
            nis[k] = res.nis
        xs[k] = x
        ps[k] = np.diag(P)
    return xs, ps, nis
