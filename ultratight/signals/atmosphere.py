"""Signal delays in the atmosphere: Klobuchar ionosphere and Saastamoinen troposphere (L1);
see docs/references.md.

Both the IF generator (:mod:`ultratight.signals.synth.generator`, scenario table ``[atmosphere]``) and
the receiver's PVT (:mod:`ultratight.receiver.scalar.receiver`, ``--iono`` / ``--tropo``) use these
functions; the generator can also apply a model the receiver does not share (a scaled ionosphere,
another tropospheric mapping function) so that tests are not circular.

Ionosphere — the broadcast single-frequency model of IS-GPS-200D §20.3.3.5.2.5 (Klobuchar, 1987,
"Ionospheric time-delay algorithm for single-frequency GPS users", IEEE Trans. AES 23(3)), with
the eight coefficients alpha_0..3 (s, s/semicircle^n), beta_0..3 (s, s/semicircle^n) of subframe 4
page 18 or of a RINEX navigation header.  It returns the L1 group delay in seconds; the code is
delayed by ``c T_iono`` and the carrier phase advanced by the same amount (first-order
ionosphere: phase and group delays have opposite signs).

Troposphere — Saastamoinen (1972, "Atmospheric correction for the troposphere and stratosphere
in radio ranging of satellites", Geophys. Monogr. 15) zenith delays with the hydrostatic part in
the form of Davis et al. (1985, Radio Sci. 20(6)),

    ZHD = 0.0022768 P / (1 - 0.00266 cos 2 phi - 0.00028 h_km)       (m, P in hPa)
    ZWD = 0.002277 (1255 / T + 0.05) e                                (m, T in K, e in hPa)

with the meteorological values of a standard atmosphere at the ellipsoidal height ``h`` (the
closed-form troposphere of the ICAO/ISA model: ``P = 1013.25 (1 - 2.2557e-5 h)^5.2568`` hPa,
``T = 288.16 - 6.5e-3 h`` K, relative humidity 70 %, water-vapour pressure from the
saturation formula ``6.108 exp((17.15 T - 4684) / (T - 38.45))`` hPa).  Above the tropopause
(11 km) the closed form no longer holds; there the pressure follows the ICAO standard atmosphere's
upper layers (the ``ambiance`` library, scaled to meet the closed form at 11 km) up to its top at
81 km, where it is zero.  The delay is therefore continuous in height: a vehicle that climbs
through 10-11 km sees the ~0.5 m of zenith delay above it fade, not switch off (RTKLIB's
``tropmodel`` returns 0 above 10 km, a step of up to 5 m at 5 deg of elevation that a receiver
tracking a climbing vehicle takes as a jump of the carrier).  Mapping functions
(``MAPPINGS``):

* ``"cosz"`` — ``1 / cos z = 1 / sin E`` (Saastamoinen's own thin-layer mapping, the one RTKLIB's
  ``tropmodel`` uses; the receiver default so that RTKLIB positions our RINEX with the same
  corrections);
* ``"black-eisner"`` — ``1.001 / sqrt(0.002001 + sin^2 E)`` (Black & Eisner, 1984, "Correcting
  for tropospheric range effects in satellite positioning", J. Geophys. Res. 89(D2)), which
  stays finite at the horizon; the generator's alternative model.

Everything is vectorised over numpy arrays (angles in radians, heights in metres).
"""

import math

import numpy as np

from ultratight.constants import C
from ultratight.errors import ConfigError

IONO_MODELS = ("klobuchar", "off")
TROPO_MODELS = ("saastamoinen", "off")
MAPPINGS = ("cosz", "black-eisner")
REL_HUMIDITY = 0.7
ISA_T0_K = 288.16              # 15 degC + 273.16 (the Saastamoinen standard-atmosphere constant)
TROPO_H_MIN_M = -100.0
TROPOPAUSE_M = 11000.0         # top of the closed-form troposphere
ISA_TOP_M = 81000.0            # top of the ISA tables (ambiance): no delay above
NIGHT_DELAY_S = 5.0e-9         # the model's constant night-time delay (IS-GPS-200)
MIN_PERIOD_S = 72000.0


def klobuchar_delay_s(alpha, beta, lat_rad, lon_rad, elev_rad, azim_rad, tow_s):
    """L1 ionospheric group delay (s) of the broadcast model, IS-GPS-200 §20.3.3.5.2.5.

    ``alpha``, ``beta``: 4 coefficients each (RINEX / LNAV units); user geodetic latitude,
    longitude, satellite elevation and azimuth in radians; ``tow_s`` GPS time of week.
    Arrays broadcast."""
    a = np.asarray(alpha, dtype=float).reshape(4)
    b = np.asarray(beta, dtype=float).reshape(4)
    el = np.asarray(elev_rad, dtype=float) / math.pi            # semicircles
    az = np.asarray(azim_rad, dtype=float)
    phi_u = np.asarray(lat_rad, dtype=float) / math.pi
    lam_u = np.asarray(lon_rad, dtype=float) / math.pi
    psi = 0.0137 / (el + 0.11) - 0.022                          # earth angle, semicircles
    phi_i = np.clip(phi_u + psi * np.cos(az), -0.416, 0.416)
    lam_i = lam_u + psi * np.sin(az) / np.cos(phi_i * math.pi)
    phi_m = phi_i + 0.064 * np.cos((lam_i - 1.617) * math.pi)  # geomagnetic latitude
    t = np.mod(4.32e4 * lam_i + np.asarray(tow_s, dtype=float), 86400.0)
    f = 1.0 + 16.0 * (0.53 - el) ** 3                           # slant factor
    amp = a[0] + phi_m * (a[1] + phi_m * (a[2] + phi_m * a[3]))
    amp = np.maximum(amp, 0.0)
    per = b[0] + phi_m * (b[1] + phi_m * (b[2] + phi_m * b[3]))
    per = np.maximum(per, MIN_PERIOD_S)
    x = 2.0 * math.pi * (t - 50400.0) / per
    day = NIGHT_DELAY_S + amp * (1.0 - x * x / 2.0 + x ** 4 / 24.0)
    return f * np.where(np.abs(x) < 1.57, day, NIGHT_DELAY_S)


def _closed_form(h):
    return 1013.25 * (1.0 - 2.2557e-5 * h) ** 5.2568, ISA_T0_K - 6.5e-3 * h


def _closed_form(h):
    """(P hPa, T K, e hPa) of the closed-form troposphere (module docstring) at h <= 11 km."""
    p = 1013.25 * (1.0 - 2.2557e-5 * h) ** 5.2568
    t = ISA_T0_K - 6.5e-3 * h
    return p, t, 6.108 * REL_HUMIDITY * np.exp((17.15 * t - 4684.0) / (t - 38.45))


def standard_atmosphere(h_m):
    """(pressure hPa, temperature K, water-vapour pressure hPa) at ellipsoidal height ``h_m``
    (clamped at 0 below the ellipsoid), standard atmosphere with 70 % relative humidity: the closed
    form up to the tropopause (11 km); above it the ICAO layers' pressure and temperature (module
    docstring), the water vapour falling with the pressure from its tropopause value (the
    stratosphere is dry: 70 % humidity at its 270 K would be 0.4 m of slant delay at 50 km), and
    no atmosphere above 81 km."""
    h = np.maximum(np.asarray(h_m, dtype=float), 0.0)
    p, t, e = (np.array(v, dtype=float, ndmin=1) for v in _closed_form(np.minimum(h, TROPOPAUSE_M)))
    hi = np.broadcast_to(h > TROPOPAUSE_M, p.shape)
    if np.any(hi):
        from ambiance import Atmosphere

        hh = np.broadcast_to(h, p.shape)[hi]
        isa = Atmosphere(np.concatenate([[TROPOPAUSE_M], np.minimum(hh, ISA_TOP_M)]))
        p11, t11, e11 = _closed_form(TROPOPAUSE_M)
        ratio = np.where(hh >= ISA_TOP_M, 0.0, isa.pressure[1:] / isa.pressure[0])
        p[hi], e[hi] = p11 * ratio, e11 * ratio
        t[hi] = isa.temperature[1:] + (t11 - isa.temperature[0])
    if not h.ndim:
        return p[0], t[0], e[0]
    return p, t, e


def saastamoinen_zenith_m(lat_rad, h_m, pressure_hpa=None, temperature_k=None, vapour_hpa=None):
    """(hydrostatic, wet) zenith delays in metres; meteorological values default to the
    standard atmosphere at ``h_m``."""
    p0, t0, e0 = standard_atmosphere(h_m)
    p = p0 if pressure_hpa is None else np.asarray(pressure_hpa, dtype=float)
    t = t0 if temperature_k is None else np.asarray(temperature_k, dtype=float)
    e = e0 if vapour_hpa is None else np.asarray(vapour_hpa, dtype=float)
    h_km = np.maximum(np.asarray(h_m, dtype=float), 0.0) / 1e3
    zhd = 0.0022768 * p / (1.0 - 0.00266 * np.cos(2.0 * np.asarray(lat_rad, dtype=float)) - 0.00028 * h_km)
    zwd = 0.002277 * (1255.0 / t + 0.05) * e
    return zhd, zwd


def mapping(elev_rad, name="cosz"):
    """Tropospheric mapping function value (one for both parts) at elevation ``elev_rad``."""
    s = np.sin(np.asarray(elev_rad, dtype=float))
    if name == "cosz":
        return 1.0 / np.maximum(s, 1e-3)
    if name == "black-eisner":
        return 1.001 / np.sqrt(0.002001 + s * s)
    raise ConfigError(f"tropospheric mapping function must be one of {', '.join(MAPPINGS)}, got {name!r}")


def saastamoinen_delay_m(lat_rad, h_m, elev_rad, mapping_name="cosz"):
    """Slant tropospheric delay (m); 0 for elevations <= 0, below -100 m and above the standard
    atmosphere's top (81 km)."""
    zhd, zwd = saastamoinen_zenith_m(lat_rad, h_m)
    el = np.asarray(elev_rad, dtype=float)
    h = np.asarray(h_m, dtype=float)
    d = (zhd + zwd) * mapping(el, mapping_name)
    ok = (el > 0.0) & (h >= TROPO_H_MIN_M) & (h < ISA_TOP_M)
    return np.where(ok, d, 0.0)


class AtmosphereModel:
    """Delays (m, L1) for a receiver position and satellite directions, one object per setting.

    ``iono``: "klobuchar" or "off"; ``alpha``/``beta``: the broadcast coefficients (None: no
    ionosphere even if requested); ``iono_scale``: factor on the Klobuchar delay (1 for the
    receiver; the generator may use another to model an ionosphere the receiver does not know);
    ``tropo``: "saastamoinen" or "off"; ``mapping``: see :data:`MAPPINGS`.
    """

    def __init__(self, iono="off", alpha=None, beta=None, tropo="off", mapping_name="cosz", iono_scale=1.0):
        if iono not in IONO_MODELS:
            raise ConfigError(f"ionosphere model must be one of {', '.join(IONO_MODELS)}, got {iono!r}")
        if tropo not in TROPO_MODELS:
            raise ConfigError(f"troposphere model must be one of {', '.join(TROPO_MODELS)}, got {tropo!r}")
        if mapping_name not in MAPPINGS:
            raise ConfigError(f"tropospheric mapping function must be one of {', '.join(MAPPINGS)}, "
                              f"got {mapping_name!r}")
        self.iono = iono
        self.alpha = None if alpha is None else tuple(float(v) for v in alpha)
        self.beta = None if beta is None else tuple(float(v) for v in beta)
        self.tropo = tropo
        self.mapping = mapping_name
        self.iono_scale = float(iono_scale)

    @property
    def iono_active(self):
        return self.iono == "klobuchar" and self.alpha is not None and self.beta is not None

    @property
    def active(self):
        return self.iono_active or self.tropo != "off"

    def delays_m(self, lat_rad, lon_rad, h_m, elev_rad, azim_rad, tow_s):
        """(iono_m, tropo_m) arrays (broadcast shapes) of the L1 code delays."""
        el = np.asarray(elev_rad, dtype=float)
        shape = np.broadcast(el, np.asarray(azim_rad), np.asarray(tow_s), np.asarray(lat_rad)).shape
        iono = np.zeros(shape)
        tropo = np.zeros(shape)
        if self.iono_active:
            iono = self.iono_scale * C * klobuchar_delay_s(self.alpha, self.beta, lat_rad, lon_rad, el,
                                                           azim_rad, tow_s)
            iono = np.where(el > 0.0, iono, 0.0) * np.ones(shape)
        if self.tropo == "saastamoinen":
            tropo = saastamoinen_delay_m(lat_rad, h_m, el, self.mapping) * np.ones(shape)
        return iono, tropo

    def describe(self):
        return {"iono": self.iono if self.iono == "off" else ("klobuchar" if self.iono_active else
                                                              "klobuchar (no parameters)"),
                "tropo": self.tropo if self.tropo == "off" else f"saastamoinen ({self.mapping})",
                "iono_alpha": list(self.alpha) if self.alpha else None,
                "iono_beta": list(self.beta) if self.beta else None}
