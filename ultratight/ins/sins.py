"""Strapdown inertial navigation (SINS) mechanisation, local-level ENU frame (numba).

Navigation frame: local ENU at the current position ("l").  State: attitude
quaternion ``q_lb`` (body FLU -> ENU, scalar first), Earth-relative velocity
``vel_l`` (ENU, m/s), geodetic position ``[lat, lon, h]`` (rad, rad, m).

One step over an IMU interval dt with increments (dtheta, dv) -- two-sample
(previous + current interval) coning and sculling:

* rotation vector   phi   = dth_k + dth_{k-1} x dth_k / 12
* velocity increment dv_sf = dv_k + dth_k x dv_k / 2 + (dth_{k-1} x dv_k + dv_{k-1} x dth_k) / 12
  (rotation compensation + sculling)
* nav-frame rotation zeta = (omega_ie_l + omega_el_l) dt at mid interval
* v_k = v_{k-1} + (I - [zeta x]/2) C_lb,{k-1} dv_sf + (g_l - (2 omega_ie + omega_el) x v) dt
  with mid-interval gravity (WGS-84 normal gravity with height, ultratight.ins.earth.gravity_l),
  Earth rate and transport rate; the mid-interval velocity comes from a predictor-corrector pass.
* trapezoidal position update in lat/lon/h using mid-interval radii of curvature
* q_lb,k = q(-zeta) * q_lb,{k-1} * q(phi)

The state is one float64 array (length :data:`SINS_STATE_LEN`) with named slices, so the
same step function serves the batch run (:func:`sins_run`) and the 100 Hz ultra-tight loop
(:func:`sins_step`, with error-state feedback via :mod:`ultratight.ins.error_model`).
"""

import math

import numpy as np
from numba import njit

from ultratight.constants import OMEGA_E
from ultratight.ins.attitude import quat_mult, quat_normalize, quat_to_dcm, rotvec_to_quat
from ultratight.ins.earth import gravity_l, radii

# state layout
Q = slice(0, 4)          # q_lb (scalar first)
VEL = slice(4, 7)        # vel_l ENU, m/s
LLH = slice(7, 10)       # lat, lon (rad), h (m)
DTH_PREV = slice(10, 13)  # previous interval's dtheta (coning)
DV_PREV = slice(13, 16)   # previous interval's dv (sculling)
HAS_PREV = 16             # 1.0 when DTH_PREV/DV_PREV are valid
SINS_STATE_LEN = 17
I_LAT, I_LON, I_H = 7, 8, 9


def make_state(q_lb, vel_l, llh):
    """SINS state array from attitude quaternion, ENU velocity and [lat, lon, h]."""
    x = np.zeros(SINS_STATE_LEN)
    x[Q] = np.asarray(q_lb, float) / np.linalg.norm(q_lb)
    x[VEL] = vel_l
    x[LLH] = llh
    return x


@njit(cache=True)
def _cross(a, b):
    out = np.empty(3)
    out[0] = a[1] * b[2] - a[2] * b[1]
    out[1] = a[2] * b[0] - a[0] * b[2]
    out[2] = a[0] * b[1] - a[1] * b[0]
    return out


@njit(cache=True)
def sins_step(x, dtheta, dv, dt):
    """Advance the SINS state ``x`` (in place) by one IMU interval of length dt."""
    q = x[0:4]
    v0 = x[4:7].copy()
    lat0, lon0, h0 = x[7], x[8], x[9]
    if x[HAS_PREV] > 0.5:
        dth_p = x[10:13]
        dv_p = x[13:16]
    else:
        dth_p = np.zeros(3)
        dv_p = np.zeros(3)
    c_th = _cross(dth_p, dtheta)
    phi = np.empty(3)
    for i in range(3):
        phi[i] = dtheta[i] + c_th[i] / 12.0
    r1 = _cross(dtheta, dv)
    r2 = _cross(dth_p, dv)
    r3 = _cross(dv_p, dtheta)
    dvs = np.empty(3)
    for i in range(3):
        dvs[i] = dv[i] + 0.5 * r1[i] + (r2[i] + r3[i]) / 12.0
    C = quat_to_dcm(q)
    dvl = C @ dvs

    # mid-interval position predicted with v0 (gravity, Earth rate, radii)
    rm, rn = radii(lat0)
    h_m = h0 + 0.5 * dt * v0[2]
    lat_m = lat0 + 0.5 * dt * v0[1] / (rm + h_m)
    rm, rn = radii(lat_m)
    g = gravity_l(lat_m, h_m)
    slat, clat = math.sin(lat_m), math.cos(lat_m)
    wie_n = OMEGA_E * clat
    wie_u = OMEGA_E * slat
    tlat = slat / clat
    v_m = v0.copy()
    v1 = np.empty(3)
    zeta = np.empty(3)
    for it in range(2):
        wen_e = -v_m[1] / (rm + h_m)
        wen_n = v_m[0] / (rn + h_m)
        wen_u = v_m[0] * tlat / (rn + h_m)
        zeta[0] = wen_e * dt
        zeta[1] = (wie_n + wen_n) * dt
        zeta[2] = (wie_u + wen_u) * dt
        cz = _cross(zeta, dvl)
        # Coriolis + transport: (2 w_ie + w_en) x v_m
        w2 = np.empty(3)
        w2[0] = wen_e
        w2[1] = 2.0 * wie_n + wen_n
        w2[2] = 2.0 * wie_u + wen_u
        cor = _cross(w2, v_m)
        for i in range(3):
            v1[i] = v0[i] + dvl[i] - 0.5 * cz[i] + (g[i] - cor[i]) * dt
        for i in range(3):
            v_m[i] = 0.5 * (v0[i] + v1[i])
        h_m = h0 + 0.5 * dt * (0.75 * v0[2] + 0.25 * v1[2])
    # position (trapezoid)
    h1 = h0 + dt * v_m[2]
    lat1 = lat0 + dt * v_m[1] / (rm + h_m)
    lon1 = lon0 + dt * v_m[0] / ((rn + h_m) * clat)
    # attitude
    q_bb = rotvec_to_quat(phi)
    mz = np.empty(3)
    for i in range(3):
        mz[i] = -zeta[i]
    q_ll = rotvec_to_quat(mz)
    qn = quat_normalize(quat_mult(quat_mult(q_ll, q), q_bb))
    for i in range(4):
        x[i] = qn[i]
    for i in range(3):
        x[4 + i] = v1[i]
        x[10 + i] = dtheta[i]
        x[13 + i] = dv[i]
    x[7] = lat1
    x[8] = lon1
    x[9] = h1
    x[HAS_PREV] = 1.0


@njit(cache=True)
def sins_run(x0, dtheta, dv, dt):
    """Run the mechanisation over a whole IMU array.

    ``x0``: initial state (not modified); ``dtheta``, ``dv``: (n, 3).  Returns
    ``(q_lb (n+1, 4), vel_l (n+1, 3), llh (n+1, 3))`` at t0 and after every interval.
    """
    n = dtheta.shape[0]
    x = x0.copy()
    q = np.empty((n + 1, 4))
    v = np.empty((n + 1, 3))
    p = np.empty((n + 1, 3))
    q[0] = x[0:4]
    v[0] = x[4:7]
    p[0] = x[7:10]
    for k in range(n):
        sins_step(x, dtheta[k], dv[k], dt)
        q[k + 1] = x[0:4]
        v[k + 1] = x[4:7]
        p[k + 1] = x[7:10]
    return q, v, p


@njit(cache=True)
def sins_run_final(x0, dtheta, dv, dt):
    """Like :func:`sins_run` but returns only the final state (benchmarks, long runs)."""
    x = x0.copy()
    for k in range(dtheta.shape[0]):
        sins_step(x, dtheta[k], dv[k], dt)
    return x


# ------------------------------------------------------------------ error metrics vs truth
def nav_errors(q_lb, vel_l, llh, truth_q, truth_vel, truth_llh):
    """Position error (m, ENU), velocity error (m/s) and attitude error (rad, rotation vector
    of C_true C_est^T) of a SINS solution against truth; arrays (n, 3)."""
    from ultratight.ins.attitude import dcm_to_quat_vec, quat_to_dcm_vec
    from ultratight.ins.earth import dcm_ecef_from_enu_vec, llh_to_ecef_batch
    pe = llh_to_ecef_batch(np.ascontiguousarray(llh))
    pt = llh_to_ecef_batch(np.ascontiguousarray(truth_llh))
    C_el = dcm_ecef_from_enu_vec(truth_llh[:, 0], truth_llh[:, 1])
    dpos = np.einsum("nji,nj->ni", C_el, pe - pt)
    dvel = vel_l - truth_vel
    Ce = quat_to_dcm_vec(q_lb)
    Ct = quat_to_dcm_vec(truth_q)
    dq = dcm_to_quat_vec(Ct @ np.transpose(Ce, (0, 2, 1)))
    s = np.linalg.norm(dq[:, 1:], axis=1)
    ang = 2.0 * np.arctan2(s, dq[:, 0])
    with np.errstate(invalid="ignore", divide="ignore"):
        k = np.where(s > 1e-15, ang / np.where(s > 1e-15, s, 1.0), 2.0)
    datt = dq[:, 1:] * k[:, None]
    return dpos, dvel, datt
