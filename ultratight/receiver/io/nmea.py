"""NMEA 0183 output of ``ultratight process``: GGA, RMC, GSA and GSV sentences per fix.

NMEA 0183 v4.10 sentence layouts; every sentence is ``$<talker><type>,...*hh`` with ``hh`` the
XOR of the characters between ``$`` and ``*`` (two upper-case hex digits) and CR LF line ends.
Talker ``GP`` (GPS only).  Times are UTC = GPS time - leap seconds (the UTC parameters decoded from
subframe 4 page 18, else the RINEX header, else 18 s, the value since 2017-01-01).  Heights: the
receiver computes ellipsoidal heights and knows no geoid, so GGA reports the ellipsoidal height as
altitude with a geoid separation of 0.0 (documented in docs/process.md).  The file starts with a
proprietary sentence ``$PUTGT,<version>,<option>=<value>,...`` naming the package version and the
correction options used.
"""

import math
from datetime import timedelta
from pathlib import Path

from ultratight import __version__
from ultratight.errors import InputFileError
from ultratight.io_guard import write_text_atomic
from ultratight.receiver.io.rinex_out import gps_to_datetime

DEFAULT_LEAP_S = 18
MPS_TO_KNOTS = 3600.0 / 1852.0


def checksum(body):
    """NMEA checksum (XOR of the characters) of the text between '$' and '*'."""
    c = 0
    for ch in body.encode("ascii"):
        c ^= ch
    return f"{c:02X}"


def sentence(body):
    return f"${body}*{checksum(body)}\r\n"


def _lat(lat_deg):
    a = abs(lat_deg)
    d = int(a)
    return f"{d:02d}{(a - d) * 60.0:08.5f}", "N" if lat_deg >= 0 else "S"


def _lon(lon_deg):
    lon_deg = (lon_deg + 180.0) % 360.0 - 180.0
    a = abs(lon_deg)
    d = int(a)
    return f"{d:03d}{(a - d) * 60.0:08.5f}", "E" if lon_deg >= 0 else "W"


def _utc(fix, leap_s):
    t = gps_to_datetime(fix["gps_week"], fix["gps_tow_s"] - leap_s)
    hms = f"{t.hour:02d}{t.minute:02d}{t.second + t.microsecond * 1e-6:05.2f}"
    if hms.endswith("60.00"):        # rounding up to the next minute: format from the rounded time
        t = t + timedelta(seconds=0.005)
        hms = f"{t.hour:02d}{t.minute:02d}{int(t.second):02d}.00"
    return t, hms


def fix_sentences(fix, leap_s=DEFAULT_LEAP_S):
    """GGA, RMC, GSA and GSV sentences (list of str) of one fix dict of the receiver."""
    import numpy as np

    from ultratight.ins.earth import dcm_ecef_from_enu, ecef_to_llh

    t, hms = _utc(fix, leap_s)
    lat, lon, h = fix["llh_deg"]
    la, ns = _lat(lat)
    lo, ew = _lon(lon)
    n_used = int(fix["n_used"])
    out = [sentence(f"GPGGA,{hms},{la},{ns},{lo},{ew},1,{n_used:02d},{fix['hdop']:.2f},{h:.3f},M,0.0,M,,")]
    llh = ecef_to_llh(np.asarray(fix["pos_e"], dtype=float))
    C_el = dcm_ecef_from_enu(llh[0], llh[1])         # columns: east, north, up
    v = np.asarray(fix["vel_e"], dtype=float)
    ve, vn = float(v @ C_el[:, 0]), float(v @ C_el[:, 1])
    speed_kn = math.hypot(ve, vn) * MPS_TO_KNOTS
    course = math.degrees(math.atan2(ve, vn)) % 360.0
    date = f"{t.day:02d}{t.month:02d}{t.year % 100:02d}"
    out.append(sentence(f"GPRMC,{hms},A,{la},{ns},{lo},{ew},{speed_kn:.3f},{course:.2f},{date},,,A,V"))
    used = [int(p) for p in fix["used_prn"]][:12]
    prn_fields = ",".join([f"{p:02d}" for p in used] + [""] * (12 - len(used)))
    out.append(sentence(f"GPGSA,A,3,{prn_fields},{fix['pdop']:.2f},{fix['hdop']:.2f},{fix['vdop']:.2f},1"))
    sv = sorted(fix.get("sv", []), key=lambda s: s["prn"])
    n_msg = max(1, math.ceil(len(sv) / 4))
    for k in range(n_msg):
        fields = []
        for s in sv[4 * k:4 * k + 4]:
            el = "" if not math.isfinite(s["elev_deg"]) else f"{int(round(s['elev_deg'])):02d}"
            az = "" if not math.isfinite(s["azim_deg"]) else f"{int(round(s['azim_deg'])) % 360:03d}"
            snr = "" if not math.isfinite(s["cn0_dbhz"]) else f"{int(round(min(99.0, s['cn0_dbhz']))):02d}"
            fields.append(f"{s['prn']:02d},{el},{az},{snr}")
        out.append(sentence(f"GPGSV,{n_msg},{k + 1},{len(sv):02d}" + "".join("," + f for f in fields) + ",1"))
    return out


def write_nmea(path, fixes, leap_s=DEFAULT_LEAP_S, options=None):
    """All fixes as NMEA sentences (temporary name, then rename)."""
    path = Path(path)
    if not path.parent.is_dir():
        raise InputFileError(f"output directory does not exist: {path.parent}")
    head = ",".join([__version__] + [f"{k}={v}" for k, v in (options or {}).items()])
    lines = [sentence(f"PUTGT,{head}")]
    for f in fixes:
        if f.get("gps_week") is None:
            continue
        lines += fix_sentences(f, leap_s)
    write_text_atomic(path, "".join(lines))
    return len(lines)
