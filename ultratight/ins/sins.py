"""Strapdown inertial navigation (SINS) mechanisation, local-level ENU frame (numba).

Navigation frame: local ENU at the current position ("l").  State: attitude
quaternion ``q_lb`` (body FLU -> ENU, scalar first), Earth-relative velocity
``vel_l`` (ENU, m/s), geodetic position ``[lat, lon, h]`` (rad, rad, m).

One step over an IMU interval dt with increments (dtheta, dv) -- two-sample
(previous + current interval) coning and sculling (Savage 1998; Groves 2013; see docs/references.md):

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
from ultratight.ins.attitude import (dcm_to_quat_vec, quat_mult_tuple, quat_normalize_tuple, quat_to_dcm_vec,
                                     rotvec_to_quat_tuple)
from ultratight.ins.earth import (dcm_ecef_from_enu, dcm_ecef_from_enu_vec, gravity_nu, llh_to_ecef, llh_to_ecef_batch,
                                  radii)

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
def sins_step(x, dtheta, dv, dt):
    """Advance the SINS state ``x`` (in place) by one IMU interval of length dt.

    Allocation-free (scalar arithmetic only) so that it runs at > 1 M steps/s."""
    tx, ty, tz = dtheta[0], dtheta[1], dtheta[2]
    ux, uy, uz = dv[0], dv[1], dv[2]
    if x[HAS_PREV] > 0.5:
        px, py, pz = x[10], x[11], x[12]
        wx, wy, wz = x[13], x[14], x[15]
    else:
        px = py = pz = 0.0
        wx = wy = wz = 0.0
    # coning: phi = dth + dth_prev x dth / 12
    fx = tx + (py * tz - pz * ty) / 12.0
    fy = ty + (pz * tx - px * tz) / 12.0
    fz = tz + (px * ty - py * tx) / 12.0
    # rotation compensation + sculling
    sx = ux + 0.5 * (ty * uz - tz * uy) + ((py * uz - pz * uy) + (wy * tz - wz * ty)) / 12.0
    sy = uy + 0.5 * (tz * ux - tx * uz) + ((pz * ux - px * uz) + (wz * tx - wx * tz)) / 12.0
    sz = uz + 0.5 * (tx * uy - ty * ux) + ((px * uy - py * ux) + (wx * ty - wy * tx)) / 12.0
    q0, q1, q2, q3 = x[0], x[1], x[2], x[3]
    # C_lb from q, applied to the body increment
    c00 = 1.0 - 2.0 * (q2 * q2 + q3 * q3)
    c01 = 2.0 * (q1 * q2 - q0 * q3)
    c02 = 2.0 * (q1 * q3 + q0 * q2)
    c10 = 2.0 * (q1 * q2 + q0 * q3)
    c11 = 1.0 - 2.0 * (q1 * q1 + q3 * q3)
    c12 = 2.0 * (q2 * q3 - q0 * q1)
    c20 = 2.0 * (q1 * q3 - q0 * q2)
    c21 = 2.0 * (q2 * q3 + q0 * q1)
    c22 = 1.0 - 2.0 * (q1 * q1 + q2 * q2)
    lx = c00 * sx + c01 * sy + c02 * sz
    ly = c10 * sx + c11 * sy + c12 * sz
    lz = c20 * sx + c21 * sy + c22 * sz
    vE0, vN0, vU0 = x[4], x[5], x[6]
    lat0, lon0, h0 = x[7], x[8], x[9]

    # mid-interval position predicted with v0 (gravity, Earth rate, radii)
    rm, rn = radii(lat0)
    h_m = h0 + 0.5 * dt * vU0
    lat_m = lat0 + 0.5 * dt * vN0 / (rm + h_m)
    rm, rn = radii(lat_m)
    gN, gU = gravity_nu(lat_m, h_m)
    slat, clat = math.sin(lat_m), math.cos(lat_m)
    wie_n = OMEGA_E * clat
    wie_u = OMEGA_E * slat
    tlat = slat / clat
    vEm, vNm, vUm = vE0, vN0, vU0
    vE1, vN1, vU1 = vE0, vN0, vU0
    zx = zy = zz = 0.0
    for _ in range(2):
        wen_e = -vNm / (rm + h_m)
        wen_n = vEm / (rn + h_m)
        wen_u = vEm * tlat / (rn + h_m)
        zx = wen_e * dt
        zy = (wie_n + wen_n) * dt
        zz = (wie_u + wen_u) * dt
        # (I - [zeta x]/2) dv_l
        czx = zy * lz - zz * ly
        czy = zz * lx - zx * lz
        czz = zx * ly - zy * lx
        # (2 w_ie + w_en) x v_m
        ax_, ay_, az_ = wen_e, 2.0 * wie_n + wen_n, 2.0 * wie_u + wen_u
        corx = ay_ * vUm - az_ * vNm
        cory = az_ * vEm - ax_ * vUm
        corz = ax_ * vNm - ay_ * vEm
        vE1 = vE0 + lx - 0.5 * czx - corx * dt
        vN1 = vN0 + ly - 0.5 * czy + (gN - cory) * dt
        vU1 = vU0 + lz - 0.5 * czz + (gU - corz) * dt
        vEm = 0.5 * (vE0 + vE1)
        vNm = 0.5 * (vN0 + vN1)
        vUm = 0.5 * (vU0 + vU1)
        h_m = h0 + 0.5 * dt * (0.75 * vU0 + 0.25 * vU1)
    # position (trapezoid)
    x[9] = h0 + dt * vUm
    x[7] = lat0 + dt * vNm / (rm + h_m)
    x[8] = lon0 + dt * vEm / ((rn + h_m) * clat)
    x[4], x[5], x[6] = vE1, vN1, vU1
    # attitude: q <- q(-zeta) * q * q(phi)
    b0, b1, b2, b3 = rotvec_to_quat_tuple(fx, fy, fz)
    l0, l1, l2, l3 = rotvec_to_quat_tuple(-zx, -zy, -zz)
    r0, r1, r2, r3 = quat_mult_tuple(q0, q1, q2, q3, b0, b1, b2, b3)
    r0, r1, r2, r3 = quat_mult_tuple(l0, l1, l2, l3, r0, r1, r2, r3)
    x[0], x[1], x[2], x[3] = quat_normalize_tuple(r0, r1, r2, r3)
    x[10], x[11], x[12] = tx, ty, tz
    x[13], x[14], x[15] = ux, uy, uz
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


@njit(cache=True)
def state_pos_vel_e(x):
    """ECEF position and velocity (m, m/s) of a SINS state (for the outer loop / NCO aiding)."""
    pos = llh_to_ecef(x[7], x[8], x[9])
    C = dcm_ecef_from_enu(x[7], x[8])
    return pos, C @ x[4:7].copy()


def state_from_trajectory(traj, t=0.0):
    """SINS state equal to the trajectory truth at time t (s since start)."""
    k = traj.kinematics(np.array([float(t)]))
    return make_state(k["q_lb"][0], k["vel_l"][0], k["llh"][0])


# ------------------------------------------------------------------ error metrics vs truth
def nav_errors(q_lb, vel_l, llh, truth_q, truth_vel, truth_llh):
    """Position error (m, ENU), velocity error (m/s) and attitude error (rad, rotation vector
    of C_true C_est^T) of a SINS solution against truth; arrays (n, 3)."""
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
