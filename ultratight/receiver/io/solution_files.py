"""GNSS solution files read into :class:`ultratight.signals.observations.GnssFixes` and written
from it (docs/integrate-inputs.md).

Readers: RTKLIB ``.pos`` (:func:`read_pos`: latitude/longitude/height or x/y/z-ECEF form, GPST or
UTC, date-time or week/seconds stamps, σ columns and, when present, velocity and its σ), NMEA
GGA + RMC + GST (:func:`read_nmea`), u-blox NAV-PVT (:func:`read_ubx_pvt`, through ``pyubx2``), and
:func:`read_gnss`, which recognises the format (:func:`sniff_format`) and refuses a file whose
content is not the declared one.  Writers: RTKLIB ``.pos`` (:func:`write_pos`, read back by RTKLIB's
``readsol`` and by :func:`read_pos`), KML (:func:`write_kml`, a LineString) and NMEA GGA + RMC + GST
(:func:`write_nmea`); all through :mod:`ultratight.io_guard` (temporary file, then rename).

Conventions: time is continuous GPS seconds; UTC sources (NMEA, a UTC ``.pos``) become GPST with
``leap_s`` seconds (GPS − UTC), 18 by default (its value since 2017-01-01; give the right one for
older logs).  σ values of 0 in a ``.pos`` file (RTKLIB's "not given") are read as NaN; NaN σ are
written as 0.  Heights are taken as the file gives them: RTKLIB writes ellipsoidal heights unless
it was told to write geodetic (MSL) ones (its ``height : geodetic`` header line, kept in
``meta["height"]``).
"""

from __future__ import annotations

import math
import re
from datetime import datetime, timedelta
from pathlib import Path

import numpy as np

from ultratight.errors import ConfigError, InputFileError
from ultratight.ins.earth import dcm_ecef_from_enu, ecef_to_llh
from ultratight.io_guard import read_text_input, write_text_atomic
from ultratight.signals.observations import (
    Q_DGPS,
    Q_FIX,
    Q_FLOAT,
    Q_PPP,
    Q_SBAS,
    Q_SINGLE,
    GnssFixes,
)

GPS_EPOCH = datetime(1980, 1, 6)
DEFAULT_LEAP_S = 18
FORMATS = ("pos", "nmea", "ubx")
KNOT_MPS = 1852.0 / 3600.0
DEG = math.pi / 180.0


def _gps_seconds_of(dt):
    return (dt - GPS_EPOCH).total_seconds()


def _datetime_of(t_gps):
    return GPS_EPOCH + timedelta(seconds=float(t_gps))


def _empty(n):
    return np.full((n, 3), np.nan)


def _bad_number(path, ln, what, text):
    return InputFileError(f"{path}: line {ln}: {what} {text!r} is not a finite number")


# ------------------------------------------------------------------ RTKLIB .pos
_POS_TIME = re.compile(r"^\d{4}/\d{1,2}/\d{1,2}$")


def _pos_header(lines, path):
    """(column names after the time, time system, height note) from the ``%`` lines."""
    cols, tsys, height = None, "GPST", None
    for _ln, s in lines:
        if not s.startswith("%"):
            break
        body = s[1:].strip()
        if body.lower().startswith("height") and ":" in body:
            height = body.split(":", 1)[1].strip()
        toks = body.split()
        if toks and toks[0] in ("GPST", "UTC", "JST") and len(toks) > 3:
            tsys, cols = toks[0], [t.split("(")[0].lower() for t in toks[1:]]
    if cols is None:
        raise InputFileError(f"{path}: no RTKLIB column header ('%  GPST  latitude(deg) ...'): not a .pos file")
    if tsys == "JST":
        raise InputFileError(f"{path}: times in JST are not read; write the solution in GPST or UTC")
    return cols, tsys, height


def _pos_time(path, ln, f, tsys, leap_s):
    """(GPS seconds, number of fields used) of the stamp that starts ``f``."""
    try:
        if _POS_TIME.match(f[0]):
            dt = datetime.strptime(f[0], "%Y/%m/%d") + timedelta(seconds=_hms_seconds(f[1]))
            t = _gps_seconds_of(dt)
        else:
            t = float(f[0]) * 604800.0 + float(f[1])
    except (ValueError, IndexError):
        raise InputFileError(f"{path}: line {ln}: time {' '.join(f[:2])!r} is neither 'YYYY/MM/DD hh:mm:ss.s' "
                             "nor 'week seconds'") from None
    if not math.isfinite(t):
        raise _bad_number(path, ln, "time", " ".join(f[:2]))
    return t + (leap_s if tsys == "UTC" else 0.0)


def _hms_seconds(s):
    h, m, sec = s.split(":")
    return int(h) * 3600.0 + int(m) * 60.0 + float(sec)


def _cov_from_signed_sqrt(sd, sdxy):
    """Covariance (n, 3, 3) of RTKLIB's σ (sdx, sdy, sdz) and signed square roots (sdxy, sdyz, sdzx)."""
    P = np.zeros((sd.shape[0], 3, 3))
    for i in range(3):
        P[:, i, i] = sd[:, i] ** 2
    for (i, j), c in zip(((0, 1), (1, 2), (2, 0)), sdxy.T):
        P[:, i, j] = P[:, j, i] = np.sign(c) * c ** 2
    return P


def read_pos(path, leap_s=DEFAULT_LEAP_S):
    """An RTKLIB solution file -> :class:`GnssFixes` (module doc).  Latitude/longitude in degrees
    (the d m s form is refused) or x/y/z-ECEF; ``Q`` and ``ns`` columns required; σ and velocity
    columns used when present.  One InputFileError line naming the line on a malformed row."""
    path = Path(path)
    text = read_text_input(path, "RTKLIB solution", "text .pos file")
    lines = [(i + 1, s.strip()) for i, s in enumerate(text.splitlines()) if s.strip()]
    cols, tsys, height = _pos_header(lines, path)
    if cols[:3] == ["latitude", "longitude", "height"]:
        form = "llh"
    elif cols[:3] == ["x-ecef", "y-ecef", "z-ecef"]:
        form = "xyz"
    else:
        raise InputFileError(f"{path}: position columns {cols[:3]} are not latitude(deg)/longitude(deg)/height "
                             "or x/y/z-ecef(m)")
    if "q" not in cols or "ns" not in cols:
        raise InputFileError(f"{path}: the column header names no Q / ns column: not an RTKLIB solution")
    rows, tt, lnos = [], [], []
    for ln, s in lines:
        if s.startswith("%"):
            continue
        f = s.split()
        t = _pos_time(path, ln, f, tsys, leap_s)
        vals = f[2:]
        if len(vals) < len(cols):
            raise InputFileError(f"{path}: line {ln}: {len(vals)} values after the time, the header names "
                                 f"{len(cols)}")
        row = []
        for name, v in zip(cols, vals):
            try:
                x = float(v)
            except ValueError:
                raise _bad_number(path, ln, name, v) from None
            if not math.isfinite(x):
                raise _bad_number(path, ln, name, v)
            row.append(x)
        rows.append(row)
        tt.append(t)
        lnos.append(ln)
    if not rows:
        raise InputFileError(f"{path}: no solution rows")
    a = np.array(rows)
    t = np.array(tt)
    _check_times(path, t, lnos)
    c = {name: a[:, i] for i, name in enumerate(cols)}
    q = c["q"].astype(int)
    bad = np.nonzero((q < 1) | (q > 7) | (c["q"] != q))[0]
    if bad.size:
        raise InputFileError(f"{path}: line {lnos[bad[0]]}: Q = {c['q'][bad[0]]:g} is not a solution quality 1..7")
    fx = _pos_llh(c) if form == "llh" else _pos_xyz(c)
    return GnssFixes(t=t, llh=fx[0], vel_enu=fx[1], sigma_pos_enu=fx[2], sigma_vel_enu=fx[3], quality=q,
                     n_sat=c["ns"].astype(int), source=str(path),
                     meta={"format": "pos", "form": form, "time_system": tsys,
                           "height": height or "as written (RTKLIB default: ellipsoidal)",
                           "leap_s": leap_s if tsys == "UTC" else None})


def _zero_nan(x):
    x = np.array(x, dtype=float)
    x[x == 0.0] = np.nan
    return x


def _pos_llh(c):
    n = c["q"].size
    llh = np.column_stack([c["latitude"] * DEG, c["longitude"] * DEG, c["height"]])
    sp = np.column_stack([c[k] for k in ("sde", "sdn", "sdu")]) if "sdn" in c else _empty(n)
    vel = np.column_stack([c["ve"], c["vn"], c["vu"]]) if "vn" in c else _empty(n)
    sv = np.column_stack([c[k] for k in ("sdve", "sdvn", "sdvu")]) if "sdvn" in c else _empty(n)
    return llh, vel, _zero_nan(sp), _zero_nan(sv)


def _enu_rotations(llh):
    return np.array([dcm_ecef_from_enu(la, lo) for la, lo in llh[:, :2]])      # columns E, N, U


def _pos_xyz(c):
    n = c["q"].size
    r = np.column_stack([c["x-ecef"], c["y-ecef"], c["z-ecef"]])
    llh = np.array([ecef_to_llh(x) for x in r])
    C = _enu_rotations(llh)
    sp, vel, sv = _empty(n), _empty(n), _empty(n)
    if "sdx" in c:
        P = _cov_from_signed_sqrt(np.column_stack([c["sdx"], c["sdy"], c["sdz"]]),
                                  np.column_stack([c["sdxy"], c["sdyz"], c["sdzx"]]))
        sp = np.sqrt(np.einsum("nji,njk,nki->ni", C, P, C))
    if "vx" in c:
        vel = np.einsum("nji,nj->ni", C, np.column_stack([c["vx"], c["vy"], c["vz"]]))
    if "sdvx" in c:
        P = _cov_from_signed_sqrt(np.column_stack([c["sdvx"], c["sdvy"], c["sdvz"]]),
                                  np.column_stack([c["sdvxy"], c["sdvyz"], c["sdvzx"]]))
        sv = np.sqrt(np.einsum("nji,njk,nki->ni", C, P, C))
    return llh, vel, _zero_nan(sp), _zero_nan(sv)


def _check_times(path, t, lnos):
    d = np.diff(t)
    bad = np.nonzero(d <= 0)[0]
    if bad.size:
        i = int(bad[0]) + 1
        raise InputFileError(f"{path}: line {lnos[i]}: time {'repeats' if d[i - 1] == 0 else 'goes back'} "
                             f"({t[i] - t[i - 1]:+.3f} s); solution epochs must increase")


def _pos_rows(fx):
    """The text rows of :func:`write_pos` (llh form, GPST)."""
    vel_ok = bool(np.all(np.isfinite(fx.vel_enu)))
    sp = np.nan_to_num(fx.sigma_pos_enu, nan=0.0)
    sv = np.nan_to_num(fx.sigma_vel_enu, nan=0.0)
    ns = fx.n_sat if fx.n_sat is not None else np.zeros(fx.n, int)
    out = []
    for k in range(fx.n):
        ms = int(round(float(fx.t[k]) * 1000.0))
        dt = GPS_EPOCH + timedelta(milliseconds=ms)
        row = (f"{dt:%Y/%m/%d %H:%M:%S}.{ms % 1000:03d} {fx.llh[k, 0] / DEG:14.9f} {fx.llh[k, 1] / DEG:14.9f} "
               f"{fx.llh[k, 2]:10.4f} {int(fx.quality[k]):3d} {int(ns[k]):3d} {sp[k, 1]:8.4f} {sp[k, 0]:8.4f} "
               f"{sp[k, 2]:8.4f} {0.0:8.4f} {0.0:8.4f} {0.0:8.4f} {0.0:6.2f} {0.0:6.1f}")
        if vel_ok:
            v = fx.vel_enu[k]
            row += (f" {v[1]:10.5f} {v[0]:10.5f} {v[2]:10.5f} {sv[k, 1]:9.5f} {sv[k, 0]:9.5f} {sv[k, 2]:9.5f}"
                    f" {0.0:9.5f} {0.0:9.5f} {0.0:9.5f}")
        out.append(row)
    return vel_ok, out


def write_pos(path, fixes, program="ultratight"):
    """Write an RTKLIB ``.pos`` (llh form, GPST, ms stamps): position, Q, ns, σ N/E/U (covariances
    0), age and ratio 0, and velocity N/E/U with its σ when every epoch has a velocity."""
    vel_ok, rows = _pos_rows(fixes)
    hdr = ["% program   : " + program, "% pos mode  : " + str(fixes.meta.get("mode", "integrate")),
           "% (lat/lon/height=WGS84/ellipsoidal,Q=1:fix,2:float,3:sbas,4:dgps,5:single,6:ppp,ns=# of satellites)",
           "%  GPST                  latitude(deg) longitude(deg)  height(m)   Q  ns   sdn(m)   sde(m)   sdu(m)"
           "  sdne(m)  sdeu(m)  sdun(m) age(s)  ratio"
           + ("    vn(m/s)    ve(m/s)    vu(m/s)      sdvn      sdve      sdvu     sdvne     sdveu     sdvun"
              if vel_ok else "")]
    write_text_atomic(path, "\n".join(hdr + rows) + "\n")
    return Path(path)


# ------------------------------------------------------------------ KML
def write_kml(path, fixes, name="ultratight track"):
    """A KML document with the track as one LineString (absolute altitudes, the heights given)."""
    coords = " ".join(f"{lo / DEG:.9f},{la / DEG:.9f},{h:.3f}" for la, lo, h in fixes.llh)
    text = ('<?xml version="1.0" encoding="UTF-8"?>\n<kml xmlns="http://www.opengis.net/kml/2.2">\n<Document>\n'
            f"<name>{_xml(name)}</name>\n<Style id=\"track\"><LineStyle><color>ff0000ff</color><width>3</width>"
            "</LineStyle></Style>\n<Placemark>\n"
            f"<name>{_xml(name)}</name><styleUrl>#track</styleUrl>\n<LineString>\n<altitudeMode>absolute"
            f"</altitudeMode>\n<coordinates>{coords}</coordinates>\n</LineString>\n</Placemark>\n</Document>\n</kml>\n")
    write_text_atomic(path, text)
    return Path(path)


def _xml(s):
    return str(s).replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")


# ------------------------------------------------------------------ NMEA
GGA_TO_Q = {1: Q_SINGLE, 2: Q_DGPS, 3: Q_SINGLE, 4: Q_FIX, 5: Q_FLOAT, 9: Q_SBAS}
Q_TO_GGA = {Q_FIX: 4, Q_FLOAT: 5, Q_SBAS: 2, Q_DGPS: 2, Q_SINGLE: 1, Q_PPP: 1}
_SENTENCE = re.compile(r"^\$([A-Z]{2})([A-Z]{3}),(.*?)(?:\*([0-9A-Fa-f]{2}))?\s*$")


def _nmea_checksum(body):
    c = 0
    for ch in body.encode("ascii", "replace"):
        c ^= ch
    return c


def _nmea_angle(v, hemi, deg_digits):
    if not v:
        return math.nan
    a = float(v[:deg_digits]) + float(v[deg_digits:]) / 60.0
    return -a if hemi in ("S", "W") else a


def _nmea_sentences(path):
    """(line, type, fields) of the sentences with a good checksum; the count of bad ones."""
    text = read_text_input(path, "NMEA log", "text NMEA file")
    out, bad = [], 0
    for i, s in enumerate(text.splitlines()):
        m = _SENTENCE.match(s.strip())
        if not m:
            continue
        body = s.strip()[1:].split("*")[0]
        if m.group(4) is not None and _nmea_checksum(body) != int(m.group(4), 16):
            bad += 1
            continue
        out.append((i + 1, m.group(2), m.group(3).split(",")))
    return out, bad


def _nmea_epochs(path, sentences):
    """dict UTC hhmmss.ss text -> {"GGA": fields, "RMC": fields, "GST": fields, "line": n} in file order."""
    ep = {}
    for ln, typ, f in sentences:
        if typ in ("GGA", "RMC", "GST") and f and f[0]:
            e = ep.setdefault(f[0], {"line": ln})
            e.setdefault(typ, f)
    return ep


def _nmea_dates(path, keys, ep, date):
    """UTC datetime of every epoch key: the RMC date of the epoch, else carried from the previous
    epoch (a day added when the clock wraps past midnight), else ``date``."""
    d0 = None
    if date is not None:
        try:
            d0 = date if isinstance(date, datetime) else datetime.strptime(str(date), "%Y-%m-%d")
        except ValueError:
            raise ConfigError(f"--date must be YYYY-MM-DD, got {date!r}") from None
    first_rmc = next((k for k in keys if "RMC" in ep[k] and ep[k]["RMC"][8:9] and ep[k]["RMC"][8]), None)
    out, day, prev = [], None, None
    for k in keys:
        sod = _hms_seconds(f"{k[0:2]}:{k[2:4]}:{k[4:]}")
        rmc = ep[k].get("RMC")
        if rmc is not None and len(rmc) > 8 and rmc[8]:
            day = datetime.strptime(rmc[8], "%d%m%y")
        elif day is None:
            if first_rmc is not None:
                day = datetime.strptime(ep[first_rmc]["RMC"][8], "%d%m%y")
                if _hms_seconds(f"{first_rmc[0:2]}:{first_rmc[2:4]}:{first_rmc[4:]}") < sod:
                    day -= timedelta(days=1)
            elif d0 is not None:
                day = d0
            else:
                raise ConfigError(f"{path}: NMEA without RMC sentences has no date: give --date YYYY-MM-DD")
        elif prev is not None and sod < prev - 43200.0:
            day += timedelta(days=1)
        prev = sod
        out.append(day + timedelta(seconds=sod))
    return out


def read_nmea(path, date=None, leap_s=DEFAULT_LEAP_S):
    """NMEA GGA (+ RMC for velocity and date, + GST for σ) -> :class:`GnssFixes`.  Epochs are the
    GGA sentences with a fix (quality 0 and 6, dead reckoning, are left out); GGA quality 4 -> Q 1
    (fixed), 5 -> 2 (float), 2 -> 4 (DGPS), 9 -> 3 (SBAS), 1 and 3 -> 5 (single).  Height =
    altitude + geoid separation (ellipsoidal).  RMC speed/course give the horizontal velocity
    (vertical NaN); GST's latitude/longitude/altitude σ give the σ.  UTC -> GPST with ``leap_s``.
    Sentences with a wrong checksum are skipped (counted in ``meta["bad_checksum"]``)."""
    path = Path(path)
    sents, bad = _nmea_sentences(path)
    ep = _nmea_epochs(path, sents)
    keys = [k for k in ep if "GGA" in ep[k]]
    if not keys:
        raise InputFileError(f"{path}: no GGA sentence with a time: not an NMEA solution log")
    when = _nmea_dates(path, keys, ep, date)
    rows = []
    for k, dt in zip(keys, when):
        g = ep[k]["GGA"]
        ln = ep[k]["line"]
        try:
            qual = int(g[5]) if len(g) > 5 and g[5] else 0
            if qual not in GGA_TO_Q:
                continue
            lat, lon = _nmea_angle(g[1], g[2], 2), _nmea_angle(g[3], g[4], 3)
            h = float(g[8]) + (float(g[10]) if len(g) > 10 and g[10] else 0.0)
            ns = int(g[6]) if g[6] else 0
            vel = sig = (math.nan,) * 3
            r = ep[k].get("RMC")
            if r is not None and len(r) > 7 and r[1] == "A" and r[6] and r[7]:
                sog, cog = float(r[6]) * KNOT_MPS, float(r[7]) * DEG
                vel = (sog * math.sin(cog), sog * math.cos(cog), math.nan)
            s = ep[k].get("GST")
            if s is not None and len(s) > 7 and all(s[5:8]):
                sig = (float(s[6]), float(s[5]), float(s[7]))
        except (ValueError, IndexError):
            raise InputFileError(f"{path}: line {ln}: malformed GGA/RMC/GST fields at UTC {k}") from None
        if not all(math.isfinite(x) for x in (lat, lon, h)):
            raise InputFileError(f"{path}: line {ln}: GGA position is not a finite number")
        rows.append((_gps_seconds_of(dt) + leap_s, lat * DEG, lon * DEG, h, *vel, *sig, GGA_TO_Q[qual], ns))
    if not rows:
        raise InputFileError(f"{path}: no GGA sentence with a fix (quality 1-5 or 9)")
    a = np.array(rows)
    _check_times(path, a[:, 0], [ep[k]["line"] for k in keys])
    return GnssFixes(t=a[:, 0], llh=a[:, 1:4], vel_enu=a[:, 4:7], sigma_pos_enu=a[:, 7:10],
                     sigma_vel_enu=_empty(a.shape[0]), quality=a[:, 10].astype(int), n_sat=a[:, 11].astype(int),
                     source=str(path), meta={"format": "nmea", "leap_s": leap_s, "bad_checksum": bad})


def write_nmea(path, fixes, leap_s=DEFAULT_LEAP_S):
    """NMEA GGA + RMC (+ GST where σ are given) per epoch, talker GP, UTC = GPST − ``leap_s``;
    the ellipsoidal height is written as altitude with a geoid separation of 0 (as ``process``
    does).  SBAS (Q 3) and DGPS (Q 4) both become GGA quality 2."""
    from ultratight.receiver.io.nmea import _lat, _lon, sentence

    out = []
    for k in range(fixes.n):
        dt = _datetime_of(round((float(fixes.t[k]) - leap_s) * 100.0) / 100.0)      # NMEA: centiseconds
        hms = f"{dt:%H%M%S}.{dt.microsecond // 10000:02d}"
        la, ns_ = _lat(fixes.llh[k, 0] / DEG)
        lo, ew = _lon(fixes.llh[k, 1] / DEG)
        nsat = int(fixes.n_sat[k]) if fixes.n_sat is not None else 0
        q = Q_TO_GGA.get(int(fixes.quality[k]), 1)
        out.append(sentence(f"GPGGA,{hms},{la},{ns_},{lo},{ew},{q},{nsat:02d},,{fixes.llh[k, 2]:.3f},M,0.0,M,,"))
        v = fixes.vel_enu[k]
        if np.all(np.isfinite(v[:2])):
            sog = math.hypot(v[0], v[1]) / KNOT_MPS
            cog = math.degrees(math.atan2(v[0], v[1])) % 360.0
            spd = f"{sog:.4f},{cog:.3f}"
        else:
            spd = ","
        out.append(sentence(f"GPRMC,{hms},A,{la},{ns_},{lo},{ew},{spd},{dt:%d%m%y},,,A"))
        s = fixes.sigma_pos_enu[k]
        if np.all(np.isfinite(s)):
            out.append(sentence(f"GPGST,{hms},,,,,{s[1]:.4f},{s[0]:.4f},{s[2]:.4f}"))
    write_text_atomic(path, "".join(out))
    return Path(path)


# ------------------------------------------------------------------ u-blox NAV-PVT
def _pvt_quality(m):
    """RTKLIB Q of a NAV-PVT (None: no usable fix): carrSoln 2 -> fixed, 1 -> float, else DGPS when
    diffSoln, else single; fixType 2 (2D), 3 (3D) and 4 (GNSS + dead reckoning) with gnssFixOk."""
    if int(m.fixType) not in (2, 3, 4) or not int(m.gnssFixOk):
        return None
    cs = int(getattr(m, "carrSoln", 0))
    if cs == 2:
        return Q_FIX
    if cs == 1:
        return Q_FLOAT
    return Q_DGPS if int(getattr(m, "diffSoln", 0)) else Q_SINGLE


def _ubx_frames(raw, cls, mid):
    """The whole UBX frames (sync to checksum) of class ``cls`` and id ``mid`` in ``raw`` with a right
    Fletcher checksum; other bytes (other messages, NMEA text, a cut frame) are passed over.  Only
    these frames are handed to pyubx2, which keeps a log of raw measurements quick to read."""
    i, n = 0, len(raw)
    while True:
        i = raw.find(b"\xb5\x62", i)
        if i < 0 or i + 8 > n:
            return
        end = i + 8 + (raw[i + 4] | (raw[i + 5] << 8))
        if end <= n and _ubx_checksum_ok(raw, i, end):
            if raw[i + 2] == cls and raw[i + 3] == mid:
                yield raw[i:end]
            i = end                 # a whole frame: its payload is not searched for sync bytes
            continue
        i += 2


def _ubx_checksum_ok(raw, i, end):
    a = b = 0
    for x in raw[i + 2:end - 2]:
        a = (a + x) & 0xFF
        b = (b + a) & 0xFF
    return raw[end - 2] == a and raw[end - 1] == b


def read_ubx_pvt(path, gps_week=None):
    """u-blox UBX-NAV-PVT messages of a binary log (pyubx2) -> :class:`GnssFixes`.

    Time: iTOW (GPS ms of week) in the GPS week of the message's UTC date (or ``gps_week``).
    Position: lat, lon, ``height`` (above the ellipsoid).  Velocity: (velE, velN, −velD).  σ: hAcc
    is a horizontal accuracy, split as hAcc/√2 on east and north; vAcc on up; sAcc (speed, 3-D)
    as sAcc/√3 per axis.  Q from fixType / gnssFixOk / carrSoln / diffSoln (:func:`_pvt_quality`);
    messages without a usable fix are left out (``meta["skipped"]``)."""
    from pyubx2 import UBXReader

    path = Path(path)
    rows, skipped = [], 0
    try:
        raw = path.read_bytes()
        for frame in _ubx_frames(raw, 0x01, 0x07):
            m = UBXReader.parse(frame)
            q = _pvt_quality(m)
            if q is None:
                skipped += 1
                continue
            tow = int(m.iTOW) / 1000.0
            week = gps_week
            if week is None:
                if not int(m.validDate):
                    raise ConfigError(f"{path}: NAV-PVT at iTOW {tow:.3f} s has no valid date: give the GPS week")
                utc = _gps_seconds_of(datetime(int(m.year), int(m.month), int(m.day), int(m.hour),
                                               int(m.min), min(int(m.second), 59)))
                week = int(round((utc + DEFAULT_LEAP_S - tow) / 604800.0))
            hs = int(m.hAcc) / 1000.0 / math.sqrt(2.0)
            ss = int(m.sAcc) / 1000.0 / math.sqrt(3.0)
            rows.append((week * 604800.0 + tow, float(m.lat) * DEG, float(m.lon) * DEG, int(m.height) / 1000.0,
                         int(m.velE) / 1000.0, int(m.velN) / 1000.0, -int(m.velD) / 1000.0,
                         hs, hs, int(m.vAcc) / 1000.0, ss, ss, ss, q, int(m.numSV)))
    except OSError as exc:
        raise InputFileError(f"{path}: cannot read u-blox log ({exc.strerror or exc})") from None
    except (ValueError, TypeError, AttributeError) as exc:
        raise InputFileError(f"{path}: malformed UBX data ({' '.join(str(exc).split())[:160]})") from None
    if not rows:
        raise InputFileError(f"{path}: no UBX-NAV-PVT message with a fix ({skipped} without one)")
    a = np.array(rows)
    _check_times(path, a[:, 0], list(range(1, a.shape[0] + 1)))
    return GnssFixes(t=a[:, 0], llh=a[:, 1:4], vel_enu=a[:, 4:7], sigma_pos_enu=a[:, 7:10], sigma_vel_enu=a[:, 10:13],
                     quality=a[:, 13].astype(int), n_sat=a[:, 14].astype(int), source=str(path),
                     meta={"format": "ubx", "message": "NAV-PVT", "skipped": skipped})


# ------------------------------------------------------------------ recognising the format
def sniff_format(path):
    """``pos``, ``nmea`` or ``ubx`` from the first 64 KiB (the UBX sync bytes 0xB5 0x62 followed by a
    plausible class; NMEA ``$..GGA/RMC`` sentences; an RTKLIB ``%`` header or ``YYYY/MM/DD`` rows),
    None when nothing fits."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(65536)
    except OSError as exc:
        raise InputFileError(f"{path}: cannot read GNSS log ({exc.strerror or exc})") from None
    i = head.find(b"\xb5\x62")
    if i >= 0 and i + 3 < len(head) and head[i + 2] in (0x01, 0x02, 0x05, 0x06, 0x0A, 0x0D, 0x10, 0x13, 0x27, 0x28):
        return "ubx"
    txt = head.decode("ascii", "replace")
    if re.search(r"^\$[A-Z]{2}(GGA|RMC),", txt, re.MULTILINE):
        return "nmea"
    if re.search(r"^%\s+(GPST|UTC)\s", txt, re.MULTILINE) or re.search(r"^\d{4}/\d\d/\d\d \d\d:\d\d:\d", txt, re.MULTILINE):
        return "pos"
    return None


def read_gnss(path, fmt=None, leap_s=DEFAULT_LEAP_S, date=None, gps_week=None):
    """A GNSS solution log -> :class:`GnssFixes`; ``fmt`` one of :data:`FORMATS` or None / "auto"
    (recognised by :func:`sniff_format`).  A declared format the content contradicts is refused
    with one line."""
    path = Path(path)
    if not path.is_file():
        raise InputFileError(f"{path}: GNSS log not found")
    seen = sniff_format(path)
    if fmt in (None, "auto"):
        if seen is None:
            raise InputFileError(f"{path}: not a GNSS solution log this reader knows (RTKLIB .pos, NMEA "
                                 "GGA/RMC, u-blox NAV-PVT)")
        fmt = seen
    if fmt not in FORMATS:
        raise ConfigError(f"GNSS solution format must be one of {', '.join(FORMATS)}, got {fmt!r}")
    if seen != fmt:
        raise InputFileError(f"{path}: declared {fmt} but the content "
                             + (f"looks like {seen}" if seen else f"is not {fmt}"))
    if fmt == "pos":
        return read_pos(path, leap_s=leap_s)
    if fmt == "nmea":
        return read_nmea(path, date=date, leap_s=leap_s)
    return read_ubx_pvt(path, gps_week=gps_week)
