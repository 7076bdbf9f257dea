"""WGS-84 Earth model: geodetic <-> ECEF conversions and local-frame rotations.

All functions are numba-compatible (plain math on floats / small arrays) and
use SI units and radians.  ``llh`` is ``[lat_rad, lon_rad, h_m]``.
Local frame of the project: ENU (east, north, up); ``C_el`` rotates a local
ENU vector into ECEF (``v_e = C_el @ v_l``).
"""

import math

import numpy as np
from numba import njit

from ultratight.constants import WGS84_A, WGS84_E2, OMEGA_E  # noqa: F401  (re-exported)


@njit(cache=True)
def llh_to_ecef(lat, lon, h):
    """Geodetic latitude/longitude (rad) and ellipsoidal height (m) -> ECEF (m)."""
    slat = math.sin(lat)
    clat = math.cos(lat)
    rn = WGS84_A / math.sqrt(1.0 - WGS84_E2 * slat * slat)
    out = np.empty(3)
    out[0] = (rn + h) * clat * math.cos(lon)
    out[1] = (rn + h) * clat * math.sin(lon)
    out[2] = (rn * (1.0 - WGS84_E2) + h) * slat
    return out


@njit(cache=True)
def ecef_to_llh(pos_e):
    """ECEF (m) -> [lat_rad, lon_rad, h_m] (iterative; sub-micrometre at any height)."""
    x, y, z = pos_e[0], pos_e[1], pos_e[2]
    p = math.sqrt(x * x + y * y)
    lon = math.atan2(y, x)
    lat = math.atan2(z, p * (1.0 - WGS84_E2))
    h = 0.0
    for _ in range(8):
        slat = math.sin(lat)
        rn = WGS84_A / math.sqrt(1.0 - WGS84_E2 * slat * slat)
        clat = math.cos(lat)
        if abs(clat) > 1e-9:
            h = p / clat - rn
        else:
            h = abs(z) - rn * (1.0 - WGS84_E2)
        lat = math.atan2(z, p * (1.0 - WGS84_E2 * rn / (rn + h)))
    out = np.empty(3)
    out[0] = lat
    out[1] = lon
    out[2] = h
    return out


@njit(cache=True)
def dcm_ecef_from_enu(lat, lon):
    """C_el: rotation taking a local ENU vector at (lat, lon) into ECEF."""
    sl, cl = math.sin(lat), math.cos(lat)
    so, co = math.sin(lon), math.cos(lon)
    c = np.empty((3, 3))
    c[0, 0] = -so
    c[0, 1] = -sl * co
    c[0, 2] = cl * co
    c[1, 0] = co
    c[1, 1] = -sl * so
    c[1, 2] = cl * so
    c[2, 0] = 0.0
    c[2, 1] = cl
    c[2, 2] = sl
    return c


@njit(cache=True)
def ecef_to_llh_batch(pos_e):
    """Vectorised :func:`ecef_to_llh`: (n, 3) -> (n, 3) [lat_rad, lon_rad, h_m]."""
    n = pos_e.shape[0]
    out = np.empty((n, 3))
    for i in range(n):
        out[i] = ecef_to_llh(pos_e[i])
    return out


@njit(cache=True)
def llh_to_ecef_batch(llh):
    """Vectorised :func:`llh_to_ecef`: (n, 3) -> (n, 3)."""
    n = llh.shape[0]
    out = np.empty((n, 3))
    for i in range(n):
        out[i] = llh_to_ecef(llh[i, 0], llh[i, 1], llh[i, 2])
    return out


def dcm_ecef_from_enu_vec(lat, lon):
    """Vectorised :func:`dcm_ecef_from_enu`: arrays (n,) -> (n, 3, 3)."""
    lat = np.asarray(lat, float)
    lon = np.asarray(lon, float)
    sl, cl = np.sin(lat), np.cos(lat)
    so, co = np.sin(lon), np.cos(lon)
    c = np.zeros(lat.shape + (3, 3))
    c[..., 0, 0] = -so
    c[..., 0, 1] = -sl * co
    c[..., 0, 2] = cl * co
    c[..., 1, 0] = co
    c[..., 1, 1] = -sl * so
    c[..., 1, 2] = cl * so
    c[..., 2, 1] = cl
    c[..., 2, 2] = sl
    return c
