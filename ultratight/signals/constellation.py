"""Nominal GPS constellation as synthetic broadcast ephemerides.

Slot table source: the baseline 24-slot constellation of the GPS Standard Positioning Service
Performance Standard (SPS PS, 4th ed. 2008 Table 3.2-1; same values as the 2001 edition,
Table 3-1): six planes A–F, RAAN (FK5/J2000) and argument of latitude per slot at the defined
epoch 0000Z 1 July 1993, Greenwich hour angle 18h 36m 14.4s; inclination 55°, semi-major axis
26 559.7 km, eccentricity 0 (the PS allows 0.00–0.02).

Propagation model (deterministic, project-defined):

* Slot geographic longitude of the ascending node at the epoch = RAAN − Greenwich hour angle.
  The epoch is taken as GPS time 1993-07-01 00:00:00 (the 9 s GPS−UTC offset of 1993 is
  ignored — irrelevant for a nominal constellation).
* Mean motion n = sqrt(GM/a³) from a = 26 559.7 km; the node regression is chosen so that the
  ground track repeats every two orbits (the property the GPS constellation is maintained for):
  ``omega_dot = Ω_E − n/2`` (≈ −8.6e-9 rad/s, close to the real J2 regression).  Hence the
  geometry seen from the Earth repeats every 2·2π/n ≈ 86154 s.
* PRN p = 1..24 occupies slot ``SLOTS[p-1]`` (A1, A2, …, F4).  PRNs 25–32 occupy project-defined
  extra slots, one per plane in the order A, B, C, D, E, F, A, B, each at the midpoint of the
  largest argument-of-latitude gap of its plane (recomputed after each insertion).
* ``nominal_ephemerides(week, tow_s)`` builds Ephemeris objects with toe = TOW rounded to the
  nearest hour (a multiple of 16 s as LNAV requires), toc = toe, zero clock terms, harmonic
  corrections and TGD, IODE = IODC = (hour of week) mod 256, healthy.
"""

import math

from ultratight.constants import GM, OMEGA_E
from ultratight.signals.ephemeris import Ephemeris
from ultratight.signals.gpstime import datetime_to_gps, normalize, to_seconds

SEMI_MAJOR_AXIS_M = 26559.7e3
INCLINATION_RAD = math.radians(55.0)
EPOCH_GPS = datetime_to_gps(1993, 7, 1)                    # (week, tow) of the slot-table epoch
GHA_EPOCH_RAD = math.radians((18 + 36 / 60.0 + 14.4 / 3600.0) * 15.0)
TOE_STEP_S = 3600.0

# (slot, RAAN deg, argument of latitude deg) — SPS PS baseline 24-slot table
SLOTS = (
    ("A1", 272.847, 268.126), ("A2", 272.847, 161.786), ("A3", 272.847, 11.676), ("A4", 272.847, 41.806),
    ("B1", 332.847, 80.956), ("B2", 332.847, 173.336), ("B3", 332.847, 309.976), ("B4", 332.847, 204.376),
    ("C1", 32.847, 111.876), ("C2", 32.847, 11.796), ("C3", 32.847, 339.666), ("C4", 32.847, 241.556),
    ("D1", 92.847, 135.226), ("D2", 92.847, 265.446), ("D3", 92.847, 35.156), ("D4", 92.847, 167.356),
    ("E1", 152.847, 197.046), ("E2", 152.847, 302.596), ("E3", 152.847, 66.066), ("E4", 152.847, 333.686),
    ("F1", 212.847, 238.886), ("F2", 212.847, 345.226), ("F3", 212.847, 105.206), ("F4", 212.847, 135.346),
)
EXTRA_PLANES = "ABCDEFAB"          # planes of the project-defined slots of PRNs 25..32


def _extra_slots():
    planes = {}
    for name, raan, u in SLOTS:
        planes.setdefault(name[0], (raan, []))[1].append(u)
    out = []
    for k, plane in enumerate(EXTRA_PLANES):
        raan, us = planes[plane]
        s = sorted(us)
        gaps = [((s[(j + 1) % len(s)] - s[j]) % 360.0, s[j]) for j in range(len(s))]
        gap, start = max(gaps)
        u_new = round((start + gap / 2.0) % 360.0, 3)
        us.append(u_new)
        out.append((f"{plane}X{k // 6 + 1}", raan, u_new))
    return tuple(out)


ALL_SLOTS = SLOTS + _extra_slots()       # index prn-1


def slot_of_prn(prn):
    """Slot tuple (name, RAAN deg, argument of latitude deg at the epoch) of PRN 1..32."""
    if not 1 <= int(prn) <= len(ALL_SLOTS):
        raise ValueError(f"nominal constellation has PRNs 1..{len(ALL_SLOTS)}, got {prn}")
    return ALL_SLOTS[int(prn) - 1]


def _wrap(x):
    return (x + math.pi) % (2.0 * math.pi) - math.pi


def nominal_ephemeris(prn, week, tow_s):
    """Synthetic Ephemeris of nominal-constellation PRN ``prn`` valid around (week, tow_s)."""
    _name, raan_deg, u_deg = slot_of_prn(prn)
    a = SEMI_MAJOR_AXIS_M
    n = math.sqrt(GM / a ** 3)
    omega_dot = OMEGA_E - n / 2.0
    toe_week, toe = normalize(week, round(tow_s / TOE_STEP_S) * TOE_STEP_S)
    dt = float(to_seconds(toe_week, toe) - to_seconds(*EPOCH_GPS))
    node_lon = math.radians(raan_deg) - GHA_EPOCH_RAD + (omega_dot - OMEGA_E) * dt
    u = math.radians(u_deg) + n * dt
    iod = int(round(toe / TOE_STEP_S)) % 256
    return Ephemeris(
        prn=int(prn), week=toe_week, toe=toe, toc=toe, sqrt_a=math.sqrt(a), e=0.0,
        i0=INCLINATION_RAD, omega0=_wrap(node_lon + OMEGA_E * toe), omega=0.0, m0=_wrap(u),
        omega_dot=omega_dot, iodc=iod, iode=iod, sv_health=0, fit_interval_h=4.0)


def nominal_ephemerides(week, tow_s, prns=None):
    """dict prn -> Ephemeris for the nominal constellation (PRNs 1..32 unless ``prns`` given)."""
    prns = range(1, len(ALL_SLOTS) + 1) if prns is None else prns
    return {int(p): nominal_ephemeris(p, week, tow_s) for p in prns}


def repeat_period_s():
    """Period after which the nominal constellation geometry in ECEF repeats (two orbits)."""
    return 2.0 * 2.0 * math.pi / math.sqrt(GM / SEMI_MAJOR_AXIS_M ** 3)


def ephemerides_for(cfg):
    """The ephemerides a scenario's signals come from (dict prn -> Ephemeris) at its start time:
    the nominal constellation (``[satellites] source = "nominal"``) or the healthy ephemerides of
    its RINEX navigation file valid then (:meth:`ultratight.signals.rinex.NavData.select_all`)."""
    from ultratight.signals.rinex import read_rinex_nav

    sat = cfg.get("satellites", {})
    week, tow = int(cfg["time"]["week"]), float(cfg["time"]["tow_s"])
    if sat.get("source", "nominal") == "nominal":
        return nominal_ephemerides(week, tow)
    return read_rinex_nav(sat.get("rinex_path", sat.get("rinex"))).select_all(week, tow)
