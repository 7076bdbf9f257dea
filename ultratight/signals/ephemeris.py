"""GPS broadcast ephemeris (IS-GPS-200 §20.3.3.4, Table 20-IV) and satellite clock model.

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

from dataclasses import dataclass, fields, replace

import numpy as np

from ultratight.constants import F_REL, GM, OMEGA_E
from ultratight.signals.gpstime import wrap_week_diff

GPS_PI = 3.1415926535898          # IS-GPS-200 value of pi (semicircle conversions)
KEPLER_ITER = 6                   # Newton iterations for Kepler's equation (e < 0.03 → converged)


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


def _kepler(m, e):
    """Eccentric anomaly for mean anomaly array ``m`` (Newton, fixed iteration count)."""
    ea = m + e * np.sin(m)
    for _ in range(KEPLER_ITER):
        ea = ea - (ea - e * np.sin(ea) - m) / (1.0 - e * np.cos(ea))
    return ea


def sat_clock(eph, t_week_s):
    """Satellite clock bias Δt_sv (s) and drift (s/s) at GPS time(s) ``t_week_s`` (s of week).

    Includes the relativistic correction and −T_GD (L1 C/A user)."""
    t = np.asarray(t_week_s, dtype=np.float64)
    tk = wrap_week_diff(t - eph.toe)
    a = eph.sqrt_a * eph.sqrt_a
    n = np.sqrt(GM / (a * a * a)) + eph.delta_n
    ea = _kepler(eph.m0 + n * tk, eph.e)
    sin_e, cos_e = np.sin(ea), np.cos(ea)
    e_dot = n / (1.0 - eph.e * cos_e)
    dt = wrap_week_diff(t - eph.toc)
    bias = eph.af0 + dt * (eph.af1 + dt * eph.af2) + F_REL * eph.e * eph.sqrt_a * sin_e - eph.tgd
    drift = eph.af1 + 2.0 * eph.af2 * dt + F_REL * eph.e * eph.sqrt_a * cos_e * e_dot
    return bias, drift


def sat_state(eph, t_week_s):
    """Satellite state at GPS time(s) ``t_week_s`` (s of week, scalar or (n,) array).

    Returns ``(pos_e (n,3) m, vel_e (n,3) m/s, clk_bias_s (n,), clk_drift (n,) s/s)``; ECEF at the
    epoch t (IS-GPS-200 Table 20-IV; velocity is the exact time derivative of those equations).
    A scalar time gives n = 1.
    """
    t = np.atleast_1d(np.asarray(t_week_s, dtype=np.float64))
    e = eph.e
    a = eph.sqrt_a * eph.sqrt_a
    n0 = np.sqrt(GM / (a * a * a))
    n = n0 + eph.delta_n
    tk = wrap_week_diff(t - eph.toe)
    mk = eph.m0 + n * tk
    ek = _kepler(mk, e)
    sin_e, cos_e = np.sin(ek), np.cos(ek)
    one_m_ecos = 1.0 - e * cos_e
    sq = np.sqrt(1.0 - e * e)
    vk = np.arctan2(sq * sin_e, cos_e - e)
    phi = vk + eph.omega
    s2, c2 = np.sin(2.0 * phi), np.cos(2.0 * phi)
    du = eph.cus * s2 + eph.cuc * c2
    dr = eph.crs * s2 + eph.crc * c2
    di = eph.cis * s2 + eph.cic * c2
    u = phi + du
    r = a * one_m_ecos + dr
    inc = eph.i0 + di + eph.idot * tk
    xp = r * np.cos(u)
    yp = r * np.sin(u)
    om = eph.omega0 + (eph.omega_dot - OMEGA_E) * tk - OMEGA_E * eph.toe
    so, co = np.sin(om), np.cos(om)
    si, ci = np.sin(inc), np.cos(inc)
    x = xp * co - yp * ci * so
    y = xp * so + yp * ci * co
    z = yp * si

    # time derivatives
    e_dot = n / one_m_ecos
    v_dot = sq * e_dot / one_m_ecos          # dv/dt = sqrt(1-e^2)·Edot/(1-e cosE)
    phi_dot = v_dot
    u_dot = phi_dot * (1.0 + 2.0 * (eph.cus * c2 - eph.cuc * s2))
    r_dot = a * e * sin_e * e_dot + 2.0 * phi_dot * (eph.crs * c2 - eph.crc * s2)
    i_dot = eph.idot + 2.0 * phi_dot * (eph.cis * c2 - eph.cic * s2)
    om_dot = eph.omega_dot - OMEGA_E
    cu, su = np.cos(u), np.sin(u)
    xp_dot = r_dot * cu - r * su * u_dot
    yp_dot = r_dot * su + r * cu * u_dot
    vx = xp_dot * co - yp_dot * ci * so + yp * si * so * i_dot - y * om_dot
    vy = xp_dot * so + yp_dot * ci * co - yp * si * co * i_dot + x * om_dot
    vz = yp_dot * si + yp * ci * i_dot

    dt = wrap_week_diff(t - eph.toc)
    rel = F_REL * e * eph.sqrt_a
    bias = eph.af0 + dt * (eph.af1 + dt * eph.af2) + rel * sin_e - eph.tgd
    drift = eph.af1 + 2.0 * eph.af2 * dt + rel * cos_e * e_dot

    pos = np.stack((x, y, z), axis=-1)
    vel = np.stack((vx, vy, vz), axis=-1)
    return pos, vel, np.asarray(bias, dtype=np.float64), np.asarray(drift, dtype=np.float64)


def sat_pos(eph, t_week_s):
    """Position only (n,3) — convenience wrapper of :func:`sat_state`."""
    return sat_state(eph, t_week_s)[0]


def in_fit_interval(eph, week, tow_s):
    """True when (week, tow) lies within the ephemeris fit interval centred on toe."""
    dt = (int(week) - int(eph.week)) * 604800.0 + (float(tow_s) - eph.toe)
    half = 0.5 * (eph.fit_interval_h if eph.fit_interval_h > 0 else 4.0) * 3600.0
    return abs(dt) <= half
