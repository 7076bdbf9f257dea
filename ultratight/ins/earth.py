"""WGS-84 Earth model (NIMA TR8350.2; see docs/references.md) and the package's one home of frame
conversions: geodetic <-> ECEF, the local ENU basis (``C_el``), elevation and azimuth of a line of
sight, and the scaling between metres and latitude/longitude/height increments by the radii of
curvature; Earth rate, transport rate and normal gravity.

SI units and radians; ``llh`` is ``[lat_rad, lon_rad, h_m]``.  Local frame of the project: ENU
(east, north, up); ``C_el`` rotates a local ENU vector into ECEF (``v_e = C_el @ v_l``), so its
columns are the east, north and up unit vectors in ECEF.  The scalar functions are numba
``@njit``; the ``_batch`` / ``_vec`` forms and :func:`elev_azim` work on arrays and share the
scalar forms' arithmetic (see each).
"""

import math

import numpy as np
from numba import njit

from ultratight.constants import WGS84_A, WGS84_E2, WGS84_F, OMEGA_E  # noqa: F401  (re-exported)


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
def _ecef_to_llh_xyz(x, y, z):
    """(lat_rad, lon_rad, h_m) of the ECEF point (x, y, z): at most 8 fixed-point iterations on the
    latitude, stopped early once an iteration returns its input exactly (every further one would
    repeat it, so the result is that of all 8)."""
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
        lat_next = math.atan2(z, p * (1.0 - WGS84_E2 * rn / (rn + h)))
        if lat_next == lat:
            break
        lat = lat_next
    return lat, lon, h


@njit(cache=True)
def ecef_to_llh(pos_e):
    """ECEF (m) -> [lat_rad, lon_rad, h_m] (iterative; sub-micrometre at any height)."""
    out = np.empty(3)
    out[0], out[1], out[2] = _ecef_to_llh_xyz(pos_e[0], pos_e[1], pos_e[2])
    return out


def _fill_dcm_ecef_from_enu(c, lat, lon):
    """Write C_el at (lat, lon) into ``c`` (..., 3, 3): the one definition of the ENU basis, run
    compiled for one position (:func:`dcm_ecef_from_enu`) and by numpy for arrays
    (:func:`dcm_ecef_from_enu_vec`)."""
    sl, cl = np.sin(lat), np.cos(lat)
    so, co = np.sin(lon), np.cos(lon)
    c[..., 0, 0] = -so
    c[..., 0, 1] = -sl * co
    c[..., 0, 2] = cl * co
    c[..., 1, 0] = co
    c[..., 1, 1] = -sl * so
    c[..., 1, 2] = cl * so
    c[..., 2, 0] = 0.0
    c[..., 2, 1] = cl
    c[..., 2, 2] = sl


_fill_dcm_ecef_from_enu_njit = njit(cache=True)(_fill_dcm_ecef_from_enu)


@njit(cache=True)
def dcm_ecef_from_enu(lat, lon):
    """C_el: rotation taking a local ENU vector at (lat, lon) into ECEF (columns: east, north, up)."""
    c = np.empty((3, 3))
    _fill_dcm_ecef_from_enu_njit(c, lat, lon)
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
    c = np.empty(lat.shape + (3, 3))
    _fill_dcm_ecef_from_enu(c, lat, lon)
    return c


# ------------------------------------------------------------------ elevation and azimuth

@njit(cache=True)
def _enu_frames_rows(rx, out):
    """out[i] = C_el at the geodetic latitude and longitude of the ECEF point rx[i]."""
    for i in range(rx.shape[0]):
        lat, lon, _ = _ecef_to_llh_xyz(rx[i, 0], rx[i, 1], rx[i, 2])
        _fill_dcm_ecef_from_enu_njit(out[i], lat, lon)


def enu_frames(rx_pos_e):
    """C_el (n, 3, 3) at each of the ECEF points (n, 3) — or (1, 3, 3) for one point: the receiver
    frames :func:`elev_azim` needs, computed once when several satellites share the receivers."""
    rx = np.ascontiguousarray(np.asarray(rx_pos_e, dtype=np.float64).reshape(-1, 3))
    out = np.empty((rx.shape[0], 3, 3))
    _enu_frames_rows(rx, out)
    return out


@njit(cache=True)
def _elev_azim_rows(frames, rx, sat, out):
    """out[i] = (elevation, azimuth) of sat[i] seen from rx[i] in the frame frames[i] (row 0 of rx
    and frames when they have one row)."""
    one_rx = rx.shape[0] == 1
    for i in range(sat.shape[0]):
        r = 0 if one_rx else i
        c = frames[r]
        dx = sat[i, 0] - rx[r, 0]
        dy = sat[i, 1] - rx[r, 1]
        dz = sat[i, 2] - rx[r, 2]
        # ENU components of the line of sight: C_el^T d
        de = c[0, 0] * dx + c[1, 0] * dy + c[2, 0] * dz
        dn = c[0, 1] * dx + c[1, 1] * dy + c[2, 1] * dz
        du = c[0, 2] * dx + c[1, 2] * dy + c[2, 2] * dz
        out[i, 0] = math.atan2(du, math.sqrt(de * de + dn * dn))
        az = math.atan2(de, dn)
        out[i, 1] = az + 2.0 * math.pi if az < 0.0 else az


def elev_azim_rows(frames, rx_rows, sat_rows):
    """:func:`elev_azim` without its broadcasting: elevation and azimuth arrays (n,) of ``sat_rows``
    (n, 3) seen from ``rx_rows`` (n, 3, or 1, 3) in their ``frames`` (:func:`enu_frames` of
    ``rx_rows``), all float64 and C-contiguous — for callers that evaluate many satellites at
    the same receivers."""
    out = np.empty((sat_rows.shape[0], 2))
    _elev_azim_rows(frames, rx_rows, sat_rows, out)
    return out[:, 0], out[:, 1]


def elev_azim(rx_pos_e, sat_pos_e, frames=None):
    """Elevation and azimuth (rad) of satellite(s) seen from receiver(s): ECEF positions, broadcasting
    over (..., 3); a scalar pair for one receiver and one satellite.

    Elevation is measured from the local geodetic horizon (the plane perpendicular to the
    ellipsoid normal at the receiver's :func:`ecef_to_llh` latitude; negative below it); azimuth is
    clockwise from north in [0, 2π).  ``frames``: the receivers' :func:`enu_frames`, when the caller
    already has them (one row per receiver row); computed here otherwise."""
    rx = np.asarray(rx_pos_e, dtype=np.float64)
    sat = np.asarray(sat_pos_e, dtype=np.float64)
    shape = np.broadcast_shapes(rx.shape, sat.shape)[:-1]
    rx_rows = rx.reshape(1, 3) if rx.ndim == 1 else np.broadcast_to(rx, shape + (3,)).reshape(-1, 3)
    rx_rows = np.ascontiguousarray(rx_rows)
    sat_rows = np.broadcast_to(sat, shape + (3,)).reshape(-1, 3)
    if frames is None:
        frames = enu_frames(rx_rows)
    elif frames.shape[0] != rx_rows.shape[0]:
        raise ValueError(f"elev_azim: {frames.shape[0]} frames for {rx_rows.shape[0]} receiver rows")
    out = np.empty((sat_rows.shape[0], 2))
    _elev_azim_rows(np.ascontiguousarray(frames), rx_rows, np.ascontiguousarray(sat_rows), out)
    return out[:, 0].reshape(shape)[()], out[:, 1].reshape(shape)[()]


# ------------------------------------------------------------------ radii, rates, normal gravity

# WGS-84 geocentric gravitational constant including the atmosphere (EGM / normal-gravity value,
# NIMA TR8350.2 Table 3.1).  Note: ultratight.constants.GM is the *GPS ICD* value (3.986005e14)
# used for orbits; the normal gravity field of the WGS-84 ellipsoid is defined with this one.
WGS84_GM_EARTH = 3.986004418e14
_E_LIN = WGS84_A * math.sqrt(WGS84_E2)            # linear eccentricity E = sqrt(a^2 - b^2), m
_B = WGS84_A * math.sqrt(1.0 - WGS84_E2)          # semi-minor axis, m


@njit(cache=True)
def radii(lat):
    """Meridian (M) and prime-vertical (N) radii of curvature (m) at geodetic latitude ``lat``."""
    s = math.sin(lat)
    w2 = 1.0 - WGS84_E2 * s * s
    rn = WGS84_A / math.sqrt(w2)
    rm = WGS84_A * (1.0 - WGS84_E2) / (w2 * math.sqrt(w2))
    return rm, rn


def llh_increment_scale(lat, h, rm, rn):
    """Metres per unit increment of latitude (rad), longitude (rad) and height (m) at geodetic
    latitude ``lat`` and height ``h``, in north, east, up order: ``[M + h, (N + h) cos lat, 1]``
    with ``(rm, rn) = radii(lat)`` (M, N).  A position difference ``(dlat, dlon, dh)`` times this
    is its north, east, up extent in metres; metres divided by it are increments."""
    return np.array([rm + h, (rn + h) * np.cos(lat), 1.0])


def llh_increment_to_enu(lat, h, rm, rn):
    """M (3, 3) with ``[east, north, up] metres = M @ [dlat, dlon, dh]``: the scaling of
    :func:`llh_increment_scale` with the rows in east, north, up order."""
    s_n, s_e, s_u = llh_increment_scale(lat, h, rm, rn)
    return np.array([[0.0, s_e, 0.0],
                     [s_n, 0.0, 0.0],
                     [0.0, 0.0, s_u]])


@njit(cache=True)
def earth_rate_l(lat):
    """Earth rotation rate expressed in local ENU: omega_ie_l (rad/s)."""
    out = np.empty(3)
    out[0] = 0.0
    out[1] = OMEGA_E * math.cos(lat)
    out[2] = OMEGA_E * math.sin(lat)
    return out


@njit(cache=True)
def transport_rate_l(lat, h, vel_l):
    """Transport rate omega_el_l (rad/s) of the ENU frame for ENU velocity ``vel_l``."""
    rm, rn = radii(lat)
    out = np.empty(3)
    out[0] = -vel_l[1] / (rm + h)
    out[1] = vel_l[0] / (rn + h)
    out[2] = vel_l[0] * math.tan(lat) / (rn + h)
    return out


@njit(cache=True)
def _q_fn(x):
    """q = 1/2 [(1 + 3/x^2) atan(x) - 3/x] with x = E/u (TR8350.2 eq. 4-7).

    For x < 0.3 the exact power series sum_{m>=1} (-1)^m/2 [1/(2m+1) - 3/(2m+3)] x^(2m+1)
    is used (the closed form cancels ~5 digits at the Earth's surface)."""
    if x < 0.3:
        x2 = x * x
        xp = x2 * x
        acc = 0.0
        sign = -1.0
        for m in range(1, 40):
            term = 0.5 * sign * (1.0 / (2 * m + 1) - 3.0 / (2 * m + 3)) * xp
            acc += term
            if abs(term) < 1e-18 * abs(acc):
                break
            xp *= x2
            sign = -sign
        return acc
    return 0.5 * ((1.0 + 3.0 / (x * x)) * math.atan(x) - 3.0 / x)


@njit(cache=True)
def _qp_fn(x):
    """q' = 3 (1 + 1/x^2) (1 - atan(x)/x) - 1 with x = E/u (TR8350.2 eq. 4-8); series for x < 0.3:
    q' = sum_{m>=1} (-1)^(m+1) 3 [1/(2m+1) - 1/(2m+3)] x^(2m) - ... (exact expansion)."""
    if x < 0.3:
        # 1 - atan(x)/x = sum_{k>=1} (-1)^(k+1) x^(2k)/(2k+1)
        # q' = 3 sum_k (-1)^(k+1) x^(2k)/(2k+1) + 3 sum_k (-1)^(k+1) x^(2k-2)/(2k+1) - 1
        #    = sum_{m>=1} 3 (-1)^(m+1) [1/(2m+1) - 1/(2m+3)] x^(2m)      (the x^0 term is 3/3 - 1 = 0)
        x2 = x * x
        xp = x2
        acc = 0.0
        sign = 1.0
        for m in range(1, 40):
            term = 3.0 * sign * (1.0 / (2 * m + 1) - 1.0 / (2 * m + 3)) * xp
            acc += term
            if abs(term) < 1e-18 * abs(acc):
                break
            xp *= x2
            sign = -sign
        return acc
    return 3.0 * (1.0 + 1.0 / (x * x)) * (1.0 - math.atan(x) / x) - 1.0


_Q0 = 0.5 * ((1.0 + 3.0 * _B * _B / (_E_LIN * _E_LIN)) * math.atan(_E_LIN / _B) - 3.0 * _B / _E_LIN)


@njit(cache=True)
def gravity_nu(lat, h):
    """Normal gravity (m/s^2) north and up components (g_N, g_U) at geodetic (lat, h).

    Tuple-returning (allocation-free) core of :func:`gravity_l`.

    Closed-form normal gravity field of the WGS-84 level ellipsoid in ellipsoidal
    coordinates (NIMA TR8350.2 eqs. 4-5..4-8; Heiskanen & Moritz 2-124..2-126),
    which is exact for the normal field at any height outside the ellipsoid (valid
    to 100 km and beyond; the only approximation is floating point, < 1e-9 m/s^2).
    It includes the centrifugal term and the small northward component of normal
    gravity above the ellipsoid (plumb-line curvature: -3.4e-4 m/s^2 at 50 km, 28.2 deg N).
    """
    slat = math.sin(lat)
    clat = math.cos(lat)
    rn = WGS84_A / math.sqrt(1.0 - WGS84_E2 * slat * slat)
    rho = (rn + h) * clat
    z = (rn * (1.0 - WGS84_E2) + h) * slat
    E = _E_LIN
    E2 = E * E
    r2 = rho * rho + z * z
    d = r2 - E2
    u2 = 0.5 * d * (1.0 + math.sqrt(1.0 + 4.0 * E2 * z * z / (d * d)))
    u = math.sqrt(u2)
    sue = math.sqrt(u2 + E2)
    beta = math.atan2(z * sue, u * rho)
    sb, cb = math.sin(beta), math.cos(beta)
    w = math.sqrt((u2 + E2 * sb * sb) / (u2 + E2))
    q0 = _Q0
    q = _q_fn(E / u)
    qp = _qp_fn(E / u)
    om2 = OMEGA_E * OMEGA_E
    a2 = WGS84_A * WGS84_A
    g_u = -(WGS84_GM_EARTH / (u2 + E2) + om2 * a2 * E / (u2 + E2) * (qp / q0) * (0.5 * sb * sb - 1.0 / 6.0)
            - om2 * u * cb * cb) / w
    # component along increasing beta (TR8350.2 states it along the opposite sense; checked
    # against a J2..J12 spherical-harmonic gradient in tests/test_ins_earth.py)
    g_b = (om2 * a2 / sue * (q / q0) * sb * cb - om2 * sue * sb * cb) / w
    # unit vectors of the u and beta coordinate lines in the meridian plane (rho, z)
    eu_r = u * cb / (sue * w)
    eu_z = sb / w
    eb_r = -sb / w
    eb_z = u * cb / (sue * w)
    g_rho = g_u * eu_r + g_b * eb_r
    g_z = g_u * eu_z + g_b * eb_z
    return -slat * g_rho + clat * g_z, clat * g_rho + slat * g_z


@njit(cache=True)
def gravity_l(lat, h):
    """Normal gravity vector (m/s^2) in local ENU at geodetic (lat, h): [0, g_N, g_U]
    (see :func:`gravity_nu` for the model and its accuracy)."""
    gn, gu = gravity_nu(lat, h)
    out = np.empty(3)
    out[0] = 0.0
    out[1] = gn
    out[2] = gu
    return out


@njit(cache=True)
def normal_gravity(lat, h):
    """Magnitude of WGS-84 normal gravity (m/s^2) at geodetic latitude ``lat`` and height ``h``."""
    g = gravity_l(lat, h)
    return math.sqrt(g[1] * g[1] + g[2] * g[2])


@njit(cache=True)
def gravity_free_air(lat, h):
    """Somigliana surface gravity with the common second-order free-air height series
    (Groves 2013 eq. 2.140 form); provided for comparison only (error ~1e-4 m/s^2 at 50 km)."""
    s2 = math.sin(lat) ** 2
    g0 = 9.7803253359 * (1.0 + 0.00193185265241 * s2) / math.sqrt(1.0 - WGS84_E2 * s2)
    m = OMEGA_E * OMEGA_E * WGS84_A * WGS84_A * _B / WGS84_GM_EARTH
    return g0 * (1.0 - 2.0 / WGS84_A * (1.0 + WGS84_F + m - 2.0 * WGS84_F * s2) * h
                 + 3.0 * h * h / (WGS84_A * WGS84_A))
