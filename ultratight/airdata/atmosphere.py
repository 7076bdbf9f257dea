"""ICAO standard atmosphere (= U.S. Standard Atmosphere 1976 below 32 km, this project's choice) via ``ambiance``.

All functions take the geometric altitude ``h_m`` (m, scalar or array) and return SI values
(Pa, K, kg/m³, m/s). The valid range is the library's, -5 km to 81 km; outside it a
:class:`ConfigError`/ValueError names the altitude. :func:`altitude_from_pressure` is the
inverse of :func:`pressure` (the FADS "pressure altitude" h_F of Duan et al. 2024).

Constants: γ = 1.4, R = 287.053 J/(kg·K), g₀ = 9.80665 m/s²; the speed of sound is
a = sqrt(γ R T).
"""

import numpy as np
from ambiance import Atmosphere

from ultratight.errors import ConfigError

GAMMA = 1.4                 # ratio of specific heats of air
R_AIR = 287.05287           # specific gas constant of dry air, J/(kg K) (ICAO; 287.053 rounded)
G0 = 9.80665                # standard gravity, m/s^2
H_MIN_M = -5000.0
H_MAX_M = 81020.0


def _h(h_m):
    h = np.asarray(h_m, dtype=float)
    if not np.all(np.isfinite(h)) or np.any(h < H_MIN_M) or np.any(h > H_MAX_M):
        bad = h[~(np.isfinite(h) & (h >= H_MIN_M) & (h <= H_MAX_M))].reshape(-1)[0]
        raise ConfigError(f"altitude {bad!r} m is outside the standard atmosphere's range "
                          f"[{H_MIN_M:g}, {H_MAX_M:g}] m")
    return h


def _out(x, like):
    x = np.asarray(x, dtype=float).reshape(np.shape(like))
    return float(x) if x.ndim == 0 else x


def state(h_m):
    """dict of ``p`` (Pa), ``T`` (K), ``rho`` (kg/m³), ``a`` (m/s) at geometric altitude(s) h_m."""
    h = _h(h_m)
    atm = Atmosphere(h.reshape(-1))
    return {"p": _out(atm.pressure, h), "T": _out(atm.temperature, h), "rho": _out(atm.density, h),
            "a": _out(atm.speed_of_sound, h)}


def _property(h_m, name):
    h = _h(h_m)
    return _out(getattr(Atmosphere(h.reshape(-1)), name), h)


def pressure(h_m):
    """Static pressure (Pa)."""
    return _property(h_m, "pressure")


def temperature(h_m):
    """Temperature (K)."""
    return _property(h_m, "temperature")


def density(h_m):
    """Density (kg/m³)."""
    return _property(h_m, "density")


def speed_of_sound(h_m):
    """Speed of sound a = sqrt(γ R T) (m/s)."""
    return _property(h_m, "speed_of_sound")


def altitude_from_pressure(p_pa):
    """Geometric altitude (m) of static pressure ``p_pa`` in the standard atmosphere."""
    p = np.asarray(p_pa, dtype=float)
    lo, hi = pressure(H_MAX_M), pressure(H_MIN_M)
    if not np.all(np.isfinite(p)) or np.any(p <= lo) or np.any(p >= hi):
        raise ConfigError(f"static pressure outside the standard atmosphere's range ({lo:.4g}, {hi:.6g}) Pa")
    return _out(Atmosphere.from_pressure(p.reshape(-1)).h, p)


def dpressure_dh(h_m):
    """dp/dh = -ρ g (Pa/m), hydrostatic, with the library's gravity at altitude."""
    h = _h(h_m)
    atm = Atmosphere(h.reshape(-1))
    return _out(-atm.density * atm.grav_accel, h)


def wind_esd(cfg_wind, field="atmosphere.wind_esd_mps"):
    """Constant wind vector (m/s, ESD: East, South, Down) from a config list; zero by default."""
    try:
        w = np.zeros(3) if cfg_wind is None else np.asarray(cfg_wind, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        w = np.zeros(0)
    if w.shape != (3,) or not np.all(np.isfinite(w)):
        raise ConfigError(f"{field} must be 3 finite numbers (East, South, Down), got {cfg_wind!r}")
    return w
