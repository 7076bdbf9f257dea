"""Attitude representations and conversions (numba-compatible).

Conventions (project-wide):

* Quaternions are scalar-first ``q = [w, x, y, z]``, unit norm; ``q_ab``
  rotates frame-b vectors into frame a, like the DCM ``C_ab``
  (``v_a = C_ab @ v_b``).
* Body frame: x forward (nose), y left (left wing), z up ("FLU").
  Local navigation frame: ENU.
* Euler angles ``[roll, pitch, yaw]`` (rad): yaw is the heading measured
  clockwise from north (0 = nose north, +pi/2 = nose east), pitch is positive
  nose up, roll is positive right wing down.  With this body frame
  ``C_lb = Rz(pi/2 - yaw) @ Ry(-pitch) @ Rx(roll)`` where ``Rk(a)`` is the
  active right-handed rotation by ``a`` about axis k.
* Rotation vector ``phi``: rotation by ``|phi|`` about ``phi/|phi|``;
  ``C = exp([phi x])``.

All conversions normalise their output (quaternions to unit norm with
``w >= 0``; DCMs are exact rotations when built from quaternions).

The quaternion product, normalisation and rotation-vector conversion are written once, on
components (``quat_mult_tuple``, ``quat_normalize_tuple``, ``rotvec_to_quat_tuple``: floats in,
a tuple out, no allocation, for numba loops such as the SINS step); the array functions call them.
"""

import math

import numpy as np
from numba import njit


@njit(cache=True)
def skew(v):
    """Cross-product matrix [v x]."""
    m = np.zeros((3, 3))
    m[0, 1] = -v[2]
    m[0, 2] = v[1]
    m[1, 0] = v[2]
    m[1, 2] = -v[0]
    m[2, 0] = -v[1]
    m[2, 1] = v[0]
    return m


# ------------------------------------------------ quaternion algebra on components (see module doc)

@njit(cache=True, inline="always")
def quat_normalize_tuple(q0, q1, q2, q3):
    """Unit quaternion with non-negative scalar part, on components (tuple in, tuple out)."""
    s = 1.0 / math.sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3)
    if q0 < 0.0:
        s = -s
    return q0 * s, q1 * s, q2 * s, q3 * s


@njit(cache=True, inline="always")
def quat_mult_tuple(a0, a1, a2, a3, b0, b1, b2, b3):
    """Hamilton product a * b on components (tuple in, tuple out)."""
    return (a0 * b0 - a1 * b1 - a2 * b2 - a3 * b3,
            a0 * b1 + a1 * b0 + a2 * b3 - a3 * b2,
            a0 * b2 - a1 * b3 + a2 * b0 + a3 * b1,
            a0 * b3 + a1 * b2 - a2 * b1 + a3 * b0)


@njit(cache=True, inline="always")
def rotvec_to_quat_tuple(x, y, z):
    """Rotation vector (x, y, z) -> quaternion components (w, x, y, z); series near zero angle
    (sin(a/2)/a and cos(a/2) to O(a^6) below a = 1e-4: relative error < 1e-20)."""
    a2 = x * x + y * y + z * z
    if a2 < 1e-8:
        s = 0.5 - a2 / 48.0 + a2 * a2 / 3840.0
        w = 1.0 - a2 / 8.0 + a2 * a2 / 384.0
    else:
        a = math.sqrt(a2)
        s = math.sin(0.5 * a) / a
        w = math.cos(0.5 * a)
    return w, x * s, y * s, z * s


# ------------------------------------------------ arrays

@njit(cache=True)
def quat_normalize(q):
    """Unit quaternion with non-negative scalar part."""
    out = np.empty(4)
    out[0], out[1], out[2], out[3] = quat_normalize_tuple(q[0], q[1], q[2], q[3])
    return out


@njit(cache=True)
def quat_mult(p, q):
    """Hamilton product p * q (so q_ac = q_ab * q_bc)."""
    out = np.empty(4)
    out[0], out[1], out[2], out[3] = quat_mult_tuple(p[0], p[1], p[2], p[3], q[0], q[1], q[2], q[3])
    return out


@njit(cache=True)
def quat_conj(q):
    out = np.empty(4)
    out[0] = q[0]
    out[1] = -q[1]
    out[2] = -q[2]
    out[3] = -q[3]
    return out


@njit(cache=True)
def quat_to_dcm(q):
    """Unit quaternion q_ab -> DCM C_ab."""
    w, x, y, z = q[0], q[1], q[2], q[3]
    n = w * w + x * x + y * y + z * z
    s = 2.0 / n
    c = np.empty((3, 3))
    c[0, 0] = 1.0 - s * (y * y + z * z)
    c[0, 1] = s * (x * y - w * z)
    c[0, 2] = s * (x * z + w * y)
    c[1, 0] = s * (x * y + w * z)
    c[1, 1] = 1.0 - s * (x * x + z * z)
    c[1, 2] = s * (y * z - w * x)
    c[2, 0] = s * (x * z - w * y)
    c[2, 1] = s * (y * z + w * x)
    c[2, 2] = 1.0 - s * (x * x + y * y)
    return c


@njit(cache=True)
def dcm_to_quat(c):
    """DCM C_ab -> unit quaternion q_ab (Shepperd's method, w >= 0)."""
    tr = c[0, 0] + c[1, 1] + c[2, 2]
    q = np.empty(4)
    if tr >= c[0, 0] and tr >= c[1, 1] and tr >= c[2, 2]:
        s = 2.0 * math.sqrt(1.0 + tr)
        q[0] = 0.25 * s
        q[1] = (c[2, 1] - c[1, 2]) / s
        q[2] = (c[0, 2] - c[2, 0]) / s
        q[3] = (c[1, 0] - c[0, 1]) / s
    elif c[0, 0] >= c[1, 1] and c[0, 0] >= c[2, 2]:
        s = 2.0 * math.sqrt(1.0 + c[0, 0] - c[1, 1] - c[2, 2])
        q[0] = (c[2, 1] - c[1, 2]) / s
        q[1] = 0.25 * s
        q[2] = (c[0, 1] + c[1, 0]) / s
        q[3] = (c[0, 2] + c[2, 0]) / s
    elif c[1, 1] >= c[2, 2]:
        s = 2.0 * math.sqrt(1.0 - c[0, 0] + c[1, 1] - c[2, 2])
        q[0] = (c[0, 2] - c[2, 0]) / s
        q[1] = (c[0, 1] + c[1, 0]) / s
        q[2] = 0.25 * s
        q[3] = (c[1, 2] + c[2, 1]) / s
    else:
        s = 2.0 * math.sqrt(1.0 - c[0, 0] - c[1, 1] + c[2, 2])
        q[0] = (c[1, 0] - c[0, 1]) / s
        q[1] = (c[0, 2] + c[2, 0]) / s
        q[2] = (c[1, 2] + c[2, 1]) / s
        q[3] = 0.25 * s
    return quat_normalize(q)


@njit(cache=True)
def rotvec_to_quat(phi):
    """Rotation vector -> unit quaternion (series near zero angle, :func:`rotvec_to_quat_tuple`)."""
    q = np.empty(4)
    q[0], q[1], q[2], q[3] = rotvec_to_quat_tuple(phi[0], phi[1], phi[2])
    return q


@njit(cache=True)
def quat_to_rotvec(q):
    """Unit quaternion -> rotation vector with angle in [0, pi]."""
    qn = quat_normalize(q)
    v = math.sqrt(qn[1] * qn[1] + qn[2] * qn[2] + qn[3] * qn[3])
    out = np.empty(3)
    if v < 1e-8:
        # angle = 2 atan2(v, w) ~ 2 v / w
        k = 2.0 / qn[0] * (1.0 - v * v / (3.0 * qn[0] * qn[0]))
    else:
        k = 2.0 * math.atan2(v, qn[0]) / v
    out[0] = qn[1] * k
    out[1] = qn[2] * k
    out[2] = qn[3] * k
    return out


@njit(cache=True)
def rotvec_to_dcm(phi):
    """Rotation vector -> DCM (Rodrigues, series near zero)."""
    a2 = phi[0] * phi[0] + phi[1] * phi[1] + phi[2] * phi[2]
    a = math.sqrt(a2)
    if a < 1e-4:
        s1 = 1.0 - a2 / 6.0 + a2 * a2 / 120.0
        s2 = 0.5 - a2 / 24.0 + a2 * a2 / 720.0
    else:
        s1 = math.sin(a) / a
        s2 = (1.0 - math.cos(a)) / a2
    k = skew(phi)
    return np.eye(3) + s1 * k + s2 * (k @ k)


@njit(cache=True)
def dcm_to_rotvec(c):
    return quat_to_rotvec(dcm_to_quat(c))


@njit(cache=True)
def euler_to_dcm(roll, pitch, yaw):
    """[roll, pitch, yaw] (rad) -> C_lb (body FLU -> ENU); see module doc."""
    sr, cr = math.sin(roll), math.cos(roll)
    sp, cp = math.sin(pitch), math.cos(pitch)
    # heading-from-north yaw -> rotation about up by (pi/2 - yaw)
    sa, ca = math.cos(yaw), math.sin(yaw)   # sin/cos of (pi/2 - yaw)
    c = np.empty((3, 3))
    # Rz(a) @ Ry(-p) @ Rx(r), a = pi/2 - yaw
    c[0, 0] = ca * cp
    c[0, 1] = -sa * cr - ca * sp * sr
    c[0, 2] = sa * sr - ca * sp * cr
    c[1, 0] = sa * cp
    c[1, 1] = ca * cr - sa * sp * sr
    c[1, 2] = -ca * sr - sa * sp * cr
    c[2, 0] = sp
    c[2, 1] = cp * sr
    c[2, 2] = cp * cr
    return c


@njit(cache=True)
def dcm_to_euler(c):
    """C_lb -> [roll, pitch, yaw] (rad); yaw in [0, 2 pi), pitch in [-pi/2, pi/2]."""
    out = np.empty(3)
    sp = c[2, 0]
    if sp > 1.0:
        sp = 1.0
    elif sp < -1.0:
        sp = -1.0
    out[1] = math.asin(sp)
    out[0] = math.atan2(c[2, 1], c[2, 2])
    a = math.atan2(c[1, 0], c[0, 0])       # angle from east, counter-clockwise
    yaw = 0.5 * math.pi - a
    yaw = yaw % (2.0 * math.pi)
    out[2] = yaw
    return out


@njit(cache=True)
def euler_to_quat(roll, pitch, yaw):
    return dcm_to_quat(euler_to_dcm(roll, pitch, yaw))


@njit(cache=True)
def quat_to_euler(q):
    return dcm_to_euler(quat_to_dcm(q))


@njit(cache=True)
def dcm_orthonormalize(c):
    """Nearest rotation (via quaternion round trip)."""
    return quat_to_dcm(dcm_to_quat(c))


# ---------------------------------------------------------------- vectorised helpers (numpy)

def euler_to_dcm_vec(roll, pitch, yaw):
    """Vectorised :func:`euler_to_dcm`: arrays (n,) -> (n, 3, 3)."""
    roll, pitch, yaw = np.broadcast_arrays(np.asarray(roll, float), np.asarray(pitch, float),
                                           np.asarray(yaw, float))
    sr, cr = np.sin(roll), np.cos(roll)
    sp, cp = np.sin(pitch), np.cos(pitch)
    sa, ca = np.cos(yaw), np.sin(yaw)
    c = np.empty(roll.shape + (3, 3))
    c[..., 0, 0] = ca * cp
    c[..., 0, 1] = -sa * cr - ca * sp * sr
    c[..., 0, 2] = sa * sr - ca * sp * cr
    c[..., 1, 0] = sa * cp
    c[..., 1, 1] = ca * cr - sa * sp * sr
    c[..., 1, 2] = -ca * sr - sa * sp * cr
    c[..., 2, 0] = sp
    c[..., 2, 1] = cp * sr
    c[..., 2, 2] = cp * cr
    return c


def rotvec_to_dcm_vec(phi):
    """Vectorised Rodrigues: (n, 3) -> (n, 3, 3)."""
    phi = np.asarray(phi, float)
    a2 = np.sum(phi * phi, axis=-1)
    a = np.sqrt(a2)
    small = a < 1e-4
    with np.errstate(invalid="ignore", divide="ignore"):
        s1 = np.where(small, 1.0 - a2 / 6.0 + a2 * a2 / 120.0, np.sin(a) / np.where(small, 1.0, a))
        s2 = np.where(small, 0.5 - a2 / 24.0 + a2 * a2 / 720.0,
                      (1.0 - np.cos(a)) / np.where(small, 1.0, a2))
    k = np.zeros(phi.shape[:-1] + (3, 3))
    k[..., 0, 1] = -phi[..., 2]
    k[..., 0, 2] = phi[..., 1]
    k[..., 1, 0] = phi[..., 2]
    k[..., 1, 2] = -phi[..., 0]
    k[..., 2, 0] = -phi[..., 1]
    k[..., 2, 1] = phi[..., 0]
    return np.eye(3) + s1[..., None, None] * k + s2[..., None, None] * (k @ k)


@njit(cache=True)
def _dcm_to_quat_batch(c):
    out = np.empty((c.shape[0], 4))
    for i in range(c.shape[0]):
        out[i] = dcm_to_quat(c[i])
    return out


def dcm_to_quat_vec(c):
    """Vectorised DCM -> quaternion (..., 3, 3) -> (..., 4), w >= 0."""
    c = np.ascontiguousarray(c, dtype=float)
    return _dcm_to_quat_batch(c.reshape(-1, 3, 3)).reshape(c.shape[:-2] + (4,))


def quat_to_dcm_vec(q):
    q = np.asarray(q, float)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    s = 2.0 / np.sum(q * q, axis=-1)
    c = np.empty(q.shape[:-1] + (3, 3))
    c[..., 0, 0] = 1.0 - s * (y * y + z * z)
    c[..., 0, 1] = s * (x * y - w * z)
    c[..., 0, 2] = s * (x * z + w * y)
    c[..., 1, 0] = s * (x * y + w * z)
    c[..., 1, 1] = 1.0 - s * (x * x + z * z)
    c[..., 1, 2] = s * (y * z - w * x)
    c[..., 2, 0] = s * (x * z - w * y)
    c[..., 2, 1] = s * (y * z + w * x)
    c[..., 2, 2] = 1.0 - s * (x * x + y * y)
    return c
