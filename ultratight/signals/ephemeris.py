"""GPS broadcast ephemeris (IS-GPS-200D §20.3.3.4, Table 20-IV) and satellite clock model.

:class:`Ephemeris` holds the LNAV clock and ephemeris parameters with IS-GPS-200 names in
snake_case, in SI units and **radians** (the message itself carries semicircles; the
conversion uses the IS-GPS-200 value of pi, ``GPS_PI``).

:func:`sat_state` evaluates satellite ECEF position, velocity (analytic time derivative of the
Table 20-IV equations), clock bias and clock drift for an array of GPS times (seconds of week),
vectorised with numpy.  ``tk = t - toe`` and ``t - toc`` are wrapped into ±302400 s so the
evaluation works across a week rollover.

The clock bias is the L1 C/A user's ``Δt_sv`` (IS-GPS-200 §20.3.3.3.3.1 and .3.2):
``af0 + af1·(t−toc) + af2·(t−toc)² + Δt_r − T_GD`` with the relativistic term
``Δt_r = F·e·sqrtA·sin E``; the drift is its time derivative (s/s).  The satellite-clock time
is ``t_sv = t + Δt_sv`` (equivalently ``t = t_sv − Δt_sv``).
"""

import math
from dataclasses import dataclass, fields, replace

import numpy as np
from numba import njit

from ultratight.constants import F_REL, GM, OMEGA_E

GPS_PI = 3.1415926535898          # IS-GPS-200 value of pi (semicircle conversions)
KEPLER_ITER = 10                  # max Newton iterations for Kepler's equation
KEPLER_TOL = 1e-13                # rad; Newton is quadratic, so the returned E is exact to ~1e-16


@dataclass
class Ephemeris:
    """One LNAV ephemeris set (angles in rad, rates in rad/s, times in s of GPS week)."""

    prn: int
    week: int                 # full GPS week of toe
    toe: float                # ephemeris reference time, s of week
    toc: float                # clock reference time, s of week
    sqrt_a: float             # sqrt(m)
    e: float
    i0: float                 # rad
    omega0: float             # longitude of ascending node at weekly epoch, rad
    omega: float              # argument of perigee, rad
    m0: float                 # mean anomaly at toe, rad
    delta_n: float = 0.0      # rad/s
    idot: float = 0.0         # rad/s
    omega_dot: float = 0.0    # rad/s
    cuc: float = 0.0          # rad
    cus: float = 0.0          # rad
    crc: float = 0.0          # m
    crs: float = 0.0          # m
    cic: float = 0.0          # rad
    cis: float = 0.0          # rad
    af0: float = 0.0          # s
    af1: float = 0.0          # s/s
    af2: float = 0.0          # s/s^2
    tgd: float = 0.0          # s
    iodc: int = 0
    iode: int = 0
    sv_health: int = 0        # 6-bit LNAV health (0 = all signals OK)
    ura_index: int = 0
    fit_interval_h: float = 4.0
    code_on_l2: int = 1
    l2p_flag: int = 0
    aodo: int = 0             # s (multiple of 900)
    tx_tow: float = float("nan")   # transmission time of message (RINEX), s of week; nan if unknown

    @property
    def a(self):
        return self.sqrt_a * self.sqrt_a

    @property
    def healthy(self):
        return self.sv_health == 0

    def copy(self, **changes):
        return replace(self, **changes)

    def as_dict(self):
        return {f.name: getattr(self, f.name) for f in fields(self)}


# Layout of the float64 parameter vector used by the numba kernels.
P_TOE, P_TOC, P_SQRTA, P_E, P_I0, P_OMEGA0, P_OMEGA, P_M0, P_DN, P_IDOT, P_OMEGADOT, P_CUC, P_CUS, \
    P_CRC, P_CRS, P_CIC, P_CIS, P_AF0, P_AF1, P_AF2, P_TGD = range(21)
N_PARAMS = 21
_PARAM_NAMES = ("toe", "toc", "sqrt_a", "e", "i0", "omega0", "omega", "m0", "delta_n", "idot",
                "omega_dot", "cuc", "cus", "crc", "crs", "cic", "cis", "af0", "af1", "af2", "tgd")


def eph_params(eph):
    """float64 parameter vector of an Ephemeris for the numba kernels (layout P_*)."""
    return np.array([float(getattr(eph, n)) for n in _PARAM_NAMES], dtype=np.float64)


@njit(cache=True)
def _wrap_half_week(dt):
    if dt > 302400.0:
        dt -= 604800.0 * math.floor((dt + 302400.0) / 604800.0)
    elif dt < -302400.0:
        dt += 604800.0 * math.floor((302400.0 - dt) / 604800.0)
    return dt


@njit(cache=True)
def state_scalar(p, t, out):
    """Table 20-IV at one GPS time t (s of week): out[0:3] pos, out[3:6] vel, out[6] clock bias,
    out[7] clock drift (see :func:`sat_state`)."""
    e = p[P_E]
    a = p[P_SQRTA] * p[P_SQRTA]
    n = math.sqrt(GM / (a * a * a)) + p[P_DN]
    tk = _wrap_half_week(t - p[P_TOE])
    mk = p[P_M0] + n * tk
    ek = mk + e * math.sin(mk)
    for _ in range(KEPLER_ITER):
        sin_e = math.sin(ek)
        cos_e = math.cos(ek)
        dek = (ek - e * sin_e - mk) / (1.0 - e * cos_e)
        ek -= dek
        if abs(dek) < KEPLER_TOL:
            break
    sin_e = math.sin(ek)
    cos_e = math.cos(ek)
    one_m_ecos = 1.0 - e * cos_e
    sq = math.sqrt(1.0 - e * e)
    phi = math.atan2(sq * sin_e, cos_e - e) + p[P_OMEGA]
    s2 = math.sin(2.0 * phi)
    c2 = math.cos(2.0 * phi)
    u = phi + p[P_CUS] * s2 + p[P_CUC] * c2
    r = a * one_m_ecos + p[P_CRS] * s2 + p[P_CRC] * c2
    inc = p[P_I0] + p[P_CIS] * s2 + p[P_CIC] * c2 + p[P_IDOT] * tk
    cu = math.cos(u)
    su = math.sin(u)
    xp = r * cu
    yp = r * su
    om_dot = p[P_OMEGADOT] - OMEGA_E
    om = p[P_OMEGA0] + om_dot * tk - OMEGA_E * p[P_TOE]
    so = math.sin(om)
    co = math.cos(om)
    si = math.sin(inc)
    ci = math.cos(inc)
    x = xp * co - yp * ci * so
    y = xp * so + yp * ci * co
    out[0] = x
    out[1] = y
    out[2] = yp * si
    e_dot = n / one_m_ecos
    phi_dot = sq * e_dot / one_m_ecos          # dv/dt
    u_dot = phi_dot * (1.0 + 2.0 * (p[P_CUS] * c2 - p[P_CUC] * s2))
    r_dot = a * e * sin_e * e_dot + 2.0 * phi_dot * (p[P_CRS] * c2 - p[P_CRC] * s2)
    i_dot = p[P_IDOT] + 2.0 * phi_dot * (p[P_CIS] * c2 - p[P_CIC] * s2)
    xp_dot = r_dot * cu - yp * u_dot
    yp_dot = r_dot * su + xp * u_dot
    out[3] = xp_dot * co - yp_dot * ci * so + yp * si * so * i_dot - y * om_dot
    out[4] = xp_dot * so + yp_dot * ci * co - yp * si * co * i_dot + x * om_dot
    out[5] = yp_dot * si + yp * ci * i_dot
    dt = _wrap_half_week(t - p[P_TOC])
    rel = F_REL * e * p[P_SQRTA]
    out[6] = p[P_AF0] + dt * (p[P_AF1] + dt * p[P_AF2]) + rel * sin_e - p[P_TGD]
    out[7] = p[P_AF1] + 2.0 * p[P_AF2] * dt + rel * cos_e * e_dot


@njit(cache=True)
def _state_many(p, t, pos, vel, clk, drift):
    buf = np.empty(8)
    for k in range(t.shape[0]):
        state_scalar(p, t[k], buf)
        pos[k, 0] = buf[0]
        pos[k, 1] = buf[1]
        pos[k, 2] = buf[2]
        vel[k, 0] = buf[3]
        vel[k, 1] = buf[4]
        vel[k, 2] = buf[5]
        clk[k] = buf[6]
        drift[k] = buf[7]


def sat_state(eph, t_week_s):
    """Satellite state at GPS time(s) ``t_week_s`` (s of week, scalar or (n,) array).

    Returns ``(pos_e (n,3) m, vel_e (n,3) m/s, clk_bias_s (n,), clk_drift (n,) s/s)``; ECEF at the
    epoch t (IS-GPS-200 Table 20-IV; velocity is the exact time derivative of those equations,
    including the harmonic corrections and IDOT).  A scalar time gives n = 1.  ``eph`` may also be
    a parameter vector from :func:`eph_params`.
    """
    t = np.ascontiguousarray(np.atleast_1d(np.asarray(t_week_s, dtype=np.float64)))
    p = eph if isinstance(eph, np.ndarray) else eph_params(eph)
    n = t.shape[0]
    pos = np.empty((n, 3))
    vel = np.empty((n, 3))
    clk = np.empty(n)
    drift = np.empty(n)
    _state_many(p, t, pos, vel, clk, drift)
    return pos, vel, clk, drift


def sat_clock(eph, t_week_s):
    """Satellite clock bias Δt_sv (s) and drift (s/s) at GPS time(s) ``t_week_s`` (s of week).

    Includes the relativistic correction and −T_GD (L1 C/A user)."""
    _, _, clk, drift = sat_state(eph, t_week_s)
    return clk, drift


def sat_pos(eph, t_week_s):
    """Position only (n,3) — convenience wrapper of :func:`sat_state`."""
    return sat_state(eph, t_week_s)[0]


def in_fit_interval(eph, week, tow_s):
    """True when (week, tow) lies within the ephemeris fit interval centred on toe."""
    dt = (int(week) - int(eph.week)) * 604800.0 + (float(tow_s) - eph.toe)
    half = 0.5 * (eph.fit_interval_h if eph.fit_interval_h > 0 else 4.0) * 3600.0
    return abs(dt) <= half
