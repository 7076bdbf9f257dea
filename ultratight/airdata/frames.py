"""The paper's frames (Duan et al. 2024, §1.1): East–South–Down navigation frame "n" and the body
frame x nose, y right wing, z down; Euler angles pitch θ, yaw ψ, roll φ of the 3-2-1 sequence
(ψ = 0 points East, positive toward South; θ positive nose up; φ positive right wing down), so
``C_bn = Rz(ψ) Ry(θ) Rx(φ)`` maps body vectors to ESD (``v_n = C_bn @ v_b``).

The project's INS (:mod:`ultratight.ins`) works in local-level ENU with an FLU body; the maps
between the two are :data:`C_ESD_ENU` (``v_esd = C_ESD_ENU @ v_enu``) and ``diag(1, -1, -1)``
(FLU ↔ FRD body).
"""

import numpy as np

C_ESD_ENU = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])


def euler_to_dcm(pitch, yaw, roll):
    """C_bn (..., 3, 3) from pitch θ, yaw ψ, roll φ (rad, arrays broadcast)."""
    th, ps, ph = np.broadcast_arrays(np.asarray(pitch, float), np.asarray(yaw, float), np.asarray(roll, float))
    st, ct = np.sin(th), np.cos(th)
    sp, cp = np.sin(ps), np.cos(ps)
    sf, cf = np.sin(ph), np.cos(ph)
    c = np.empty(th.shape + (3, 3))
    c[..., 0, 0] = ct * cp
    c[..., 0, 1] = sf * st * cp - cf * sp
    c[..., 0, 2] = cf * st * cp + sf * sp
    c[..., 1, 0] = ct * sp
    c[..., 1, 1] = sf * st * sp + cf * cp
    c[..., 1, 2] = cf * st * sp - sf * cp
    c[..., 2, 0] = -st
    c[..., 2, 1] = sf * ct
    c[..., 2, 2] = cf * ct
    return c


def dcm_to_euler(c):
    """(pitch, yaw, roll) arrays from C_bn (..., 3, 3); yaw in (-π, π]."""
    c = np.asarray(c, float)
    pitch = -np.arcsin(np.clip(c[..., 2, 0], -1.0, 1.0))
    yaw = np.arctan2(c[..., 1, 0], c[..., 0, 0])
    roll = np.arctan2(c[..., 2, 1], c[..., 2, 2])
    return pitch, yaw, roll


def wind_axes_dcm(alpha, beta):
    """C_bw (..., 3, 3): body → wind axes; its first row is the body direction of the airflow
    velocity ``[cos α cos β, sin β, sin α cos β]`` (zero bank about the velocity)."""
    a, b = np.broadcast_arrays(np.asarray(alpha, float), np.asarray(beta, float))
    sa, ca, sb, cb = np.sin(a), np.cos(a), np.sin(b), np.cos(b)
    c = np.empty(a.shape + (3, 3))
    c[..., 0, :] = np.stack([ca * cb, sb, sa * cb], axis=-1)
    c[..., 1, :] = np.stack([-ca * sb, cb, -sa * sb], axis=-1)
    c[..., 2, :] = np.stack([-sa, np.zeros_like(a), ca], axis=-1)
    return c
