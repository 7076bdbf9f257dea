"""RINEX observation reader (RINEX 2.10/2.11 and 3.0x) for GPS L1 C/A → :class:`RawEpochs`.

``read_rinex_obs(path, code="C1") -> RawEpochs`` keeps, per epoch and GPS satellite, the L1 C/A
pseudorange, carrier phase, Doppler and signal strength:

* RINEX 2: ``C1`` (or ``P1`` with ``code="P1"``), ``L1``, ``D1``, ``S1`` from ``# / TYPES OF OBSERV``;
* RINEX 3: ``C1C``, ``L1C``, ``D1C``, ``S1C`` from ``SYS / # / OBS TYPES`` (``C1W``... with ``code="P1"``).

Epoch flags 0 (OK) and 1 (power failure since the previous epoch) are observation epochs and are
kept; flags 2–5 (antenna moving, new site, header information, external event) are followed by as
many special records as the satellite-count field says, which are skipped; flag 6 (cycle-slip
records) is followed by satellite records in the observation layout, which are skipped too.
Satellite lists longer than 12 (RINEX 2) continue on the next lines, observation records with more
than five values (RINEX 2) continue every five; satellites of other systems are skipped; a blank
field is NaN.  The header's ``APPROX POSITION XYZ`` (m), ``INTERVAL`` (s), ``MARKER NAME`` and the
observation types go to ``meta``.  Times are GPS time (the header's time system must be GPS).

Any malformed record raises :class:`ultratight.errors.InputFileError` naming the file, the line
(1-based) and the field.

The reader is written here rather than taken from a library: the part of the format needed (one
signal of one system) is small, and the package keeps no heavy dependency for it; the tests check it
against an independent reader (georinex) on a real station file.
"""

import math
from pathlib import Path

import numpy as np

from ultratight.errors import InputFileError
from ultratight.signals.gpstime import datetime_to_gps
from ultratight.signals.observations import RawEpochs, gps_seconds

OBS_WIDTH = 16                    # F14.3 + LLI + SSI
RINEX2_PER_LINE = 5
RINEX2_SATS_PER_LINE = 12
# observation types of GPS L1 per (RINEX major version, code): pseudorange, phase, Doppler, strength
L1_TYPES = {
    (2, "C1"): ("C1", "L1", "D1", "S1"),
    (2, "P1"): ("P1", "L1", "D1", "S1"),
    (3, "C1"): ("C1C", "L1C", "D1C", "S1C"),
    (3, "P1"): ("C1W", "L1W", "D1W", "S1W"),
}
CODES = ("C1", "P1")
OBS_FLAGS = (0, 1)
SPECIAL_FLAGS = (2, 3, 4, 5)
CYCLE_SLIP_FLAG = 6


def _err(path, lineno, msg):
    return InputFileError(f"{path}: line {lineno}: {msg}")


def _num(text, path, lineno, name, blank=math.nan):
    s = text.strip()
    if not s:
        return blank
    try:
        v = float(s.replace("D", "E").replace("d", "e"))
    except ValueError:
        raise _err(path, lineno, f"field '{name}' = {s!r} is not a number") from None
    if not math.isfinite(v):
        raise _err(path, lineno, f"field '{name}' = {s!r} is not a finite number")
    return v


def _int(text, path, lineno, name):
    v = _num(text, path, lineno, name, blank=None)
    if v is None:
        raise _err(path, lineno, f"field '{name}' is empty (expected an integer)")
    if v != int(v):
        raise _err(path, lineno, f"field '{name}' = {text.strip()!r} is not an integer")
    return int(v)


def _header(lines, path):
    """(version, info dict, index of the first data line)."""
    if not lines or "RINEX VERSION" not in lines[0][60:]:
        raise _err(path, 1, "missing 'RINEX VERSION / TYPE' header record (not a RINEX file)")
    version = _num(lines[0][:9], path, 1, "version")
    if not 2.0 <= version < 4.0:
        raise _err(path, 1, f"field 'version' = {lines[0][:9].strip()!r}, expected 2.x or 3.x")
    if lines[0][20:21] != "O":
        raise _err(path, 1, f"field 'file type' = {lines[0][20:21]!r}, expected 'O' (observation data)")
    info = {"version": version, "types": {}, "approx_position_xyz": None, "interval_s": None,
            "marker": "", "time_system": "GPS"}
    pending = None                 # (system, count, list) of a type list continued on the next line
    for i, line in enumerate(lines):
        label, ln = line[60:].strip(), i + 1
        if label == "END OF HEADER":
            if pending is not None and len(pending[2]) < pending[1]:
                raise _err(path, ln, f"observation type list of system {pending[0]} has "
                                     f"{len(pending[2])} of {pending[1]} types")
            return version, info, i + 1
        if label == "# / TYPES OF OBSERV":
            pending = _types2(line, ln, path, pending, info)
        elif label == "SYS / # / OBS TYPES":
            pending = _types3(line, ln, path, pending, info)
        elif label == "APPROX POSITION XYZ":
            xyz = [_num(line[14 * k:14 * (k + 1)], path, ln, f"approx position {'XYZ'[k]}") for k in range(3)]
            info["approx_position_xyz"] = xyz if all(math.isfinite(v) for v in xyz) else None
        elif label == "INTERVAL":
            v = _num(line[:10], path, ln, "interval")
            info["interval_s"] = v if math.isfinite(v) else None
        elif label == "MARKER NAME":
            info["marker"] = line[:60].strip()
        elif label == "TIME OF FIRST OBS":
            ts = line[48:51].strip()
            if ts and ts not in ("GPS", "GAL"):
                raise _err(path, ln, f"field 'time system' = {ts!r}: only GPS time is supported")
            info["time_system"] = ts or "GPS"
    raise _err(path, len(lines), "no 'END OF HEADER' record")


def _types2(line, ln, path, pending, info):
    if pending is None or len(pending[2]) >= pending[1]:
        n = _int(line[:6], path, ln, "# / types of observ")
        pending = ("G", n, [])
        info["types"]["G"] = pending[2]
    pending[2].extend(line[6 + 6 * k:12 + 6 * k].strip() for k in range(9)
                      if line[6 + 6 * k:12 + 6 * k].strip())
    return pending


def _types3(line, ln, path, pending, info):
    if line[0] != " ":
        n = _int(line[3:6], path, ln, "number of observation types")
        pending = (line[0], n, [])
        info["types"][line[0]] = pending[2]
    elif pending is None:
        raise _err(path, ln, "'SYS / # / OBS TYPES' continuation line without a system")
    pending[2].extend(line[7 + 4 * k:10 + 4 * k].strip() for k in range(13)
                      if line[7 + 4 * k:10 + 4 * k].strip())
    return pending


def _column_indices(types, wanted, path, code):
    """Indices of (pseudorange, phase, Doppler, strength) in ``types`` (None where absent)."""
    idx = [types.index(t) if t in types else None for t in wanted]
    if idx[0] is None:
        raise InputFileError(f"{path}: no {wanted[0]} observations in the header's GPS observation types "
                             f"({' '.join(types) or 'none'}); code={code!r}")
    return idx


def _epoch_time(parts, path, ln, version):
    names = ("year", "month", "day", "hour", "minute", "second")
    vals = [_num(p, path, ln, f"epoch {n}", blank=None) for p, n in zip(parts, names)]
    for v, n in zip(vals, names):
        if v is None:
            raise _err(path, ln, f"field 'epoch {n}' is empty")
    y, mo, d, h, mi, s = vals
    y = int(y)
    if version < 3:
        y += 1900 if y >= 80 else 2000
    if not (1 <= mo <= 12 and 1 <= d <= 31 and 0 <= h < 24 and 0 <= mi < 60 and 0 <= s < 61):
        raise _err(path, ln, f"field 'epoch' out of range: {' '.join(p.strip() for p in parts)}")
    week, tow = datetime_to_gps(y, int(mo), int(d), int(h), int(mi), float(s))
    return float(gps_seconds(week, tow))


def _sat_id(text, path, ln):
    s = text.strip()
    if not s:
        raise _err(path, ln, "field 'satellite' is empty")
    sys_ = text[0] if text[0] != " " else "G"
    num = text[1:3].strip()
    if not num.isdigit():
        raise _err(path, ln, f"field 'satellite' = {text!r} is not a satellite number")
    return sys_, int(num)


class _Collector:
    """Rows of the epochs read so far (flat lists)."""

    def __init__(self):
        self.t, self.start, self.flag = [], [0], []
        self.prn, self.pr, self.ph, self.dop, self.snr = [], [], [], [], []

    def row(self, prn, vals):
        self.prn.append(prn)
        self.pr.append(vals[0])
        self.ph.append(vals[1])
        self.dop.append(vals[2])
        self.snr.append(vals[3])

    def close_epoch(self, t, flag):
        self.t.append(t)
        self.flag.append(flag)
        self.start.append(len(self.prn))


def _values(chunks, idx):
    """The four wanted values from the observation fields (list of 16-character strings)."""
    return [chunks[j] if j is not None and j < len(chunks) else math.nan for j in idx]


def _field(line, k, path, ln, name):
    return _num(line[OBS_WIDTH * k: OBS_WIDTH * k + 14], path, ln, name)


def _epoch2(lines, i, path, version, idx, ntypes, out):
    """One RINEX 2 epoch at line index i; returns the index after it."""
    line, ln = lines[i], i + 1
    flag = _int(line[26:29], path, ln, "epoch flag")
    nsat = _int(line[29:32], path, ln, "number of satellites")
    if flag in SPECIAL_FLAGS:
        return i + 1 + nsat
    if flag not in OBS_FLAGS + (CYCLE_SLIP_FLAG,):
        raise _err(path, ln, f"field 'epoch flag' = {flag}, expected 0..6")
    t = _epoch_time([line[0:3], line[3:6], line[6:9], line[9:12], line[12:15], line[15:26]], path, ln, version)
    sats, j = [], i
    while len(sats) < nsat:
        if j >= len(lines):
            raise _err(path, j, f"epoch of line {ln} truncated: satellite list of {nsat} ends early")
        src = lines[j]
        for k in range(min(RINEX2_SATS_PER_LINE, nsat - len(sats))):
            sats.append(_sat_id(src[32 + 3 * k:35 + 3 * k], path, j + 1))
        j += 1
    per_sat = max(1, -(-ntypes // RINEX2_PER_LINE))
    if j + per_sat * nsat > len(lines):
        raise _err(path, len(lines), f"epoch of line {ln} truncated: observations of {nsat} satellites "
                                     f"({per_sat} line(s) each) end early")
    if flag == CYCLE_SLIP_FLAG:
        return j + per_sat * nsat
    for sys_, num in sats:
        if sys_ == "G":
            chunks = []
            for r in range(per_sat):
                src, lr = lines[j + r], j + r + 1
                for k in range(min(RINEX2_PER_LINE, ntypes - RINEX2_PER_LINE * r)):
                    chunks.append(_field(src, k, path, lr, f"observation {RINEX2_PER_LINE * r + k + 1} of G{num:02d}"))
            out.row(num, _values(chunks, idx))
        j += per_sat
    out.close_epoch(t, flag)
    return j


def _epoch3(lines, i, path, version, idx, ntypes, out):
    """One RINEX 3 epoch at line index i; returns the index after it."""
    line, ln = lines[i], i + 1
    if line[0] != ">":
        raise _err(path, ln, f"expected an epoch record starting with '>', got {line[:20].rstrip()!r}")
    flag = _int(line[29:32], path, ln, "epoch flag")
    nsat = _int(line[32:35], path, ln, "number of satellites")
    if flag in SPECIAL_FLAGS:
        return i + 1 + nsat
    if flag not in OBS_FLAGS + (CYCLE_SLIP_FLAG,):
        raise _err(path, ln, f"field 'epoch flag' = {flag}, expected 0..6")
    t = _epoch_time([line[2:6], line[7:9], line[10:12], line[13:15], line[16:18], line[18:29]], path, ln, version)
    if i + 1 + nsat > len(lines):
        raise _err(path, len(lines), f"epoch of line {ln} truncated: {nsat} satellite records expected")
    if flag == CYCLE_SLIP_FLAG:
        return i + 1 + nsat
    for r in range(nsat):
        src, lr = lines[i + 1 + r], i + 2 + r
        sys_, num = _sat_id(src[0:3], path, lr)
        if sys_ != "G":
            continue
        chunks = [_num(src[3 + OBS_WIDTH * k: 3 + OBS_WIDTH * k + 14], path, lr,
                       f"observation {k + 1} of G{num:02d}") for k in range(ntypes)]
        out.row(num, _values(chunks, idx))
    out.close_epoch(t, flag)
    return i + 1 + nsat


def read_rinex_obs(path, code="C1"):
    """GPS L1 observations of a RINEX 2.x / 3.x observation file as :class:`RawEpochs`
    (module doc); ``code``: ``"C1"`` (C/A code, default) or ``"P1"``."""
    if code not in CODES:
        raise InputFileError(f"RINEX observation code must be one of {', '.join(CODES)}, got {code!r}")
    path = Path(path)
    try:
        text = path.read_text(encoding="ascii", errors="replace")
    except OSError as exc:
        raise InputFileError(f"{path}: cannot read RINEX observation file: {exc.strerror or exc}") from None
    lines = [ln.rstrip("\r\n").ljust(80) for ln in text.splitlines()]
    version, info, i = _header(lines, path)
    major = int(version)
    types = info["types"].get("G")
    if types is None:
        raise InputFileError(f"{path}: the header lists no GPS observation types")
    wanted = L1_TYPES[(major, code)]
    idx = _column_indices(types, wanted, path, code)
    reader = _epoch3 if major >= 3 else _epoch2
    out = _Collector()
    while i < len(lines):
        if not lines[i].strip():
            i += 1
            continue
        i = reader(lines, i, path, version, idx, len(types), out)
    meta = {"version": version, "marker": info["marker"], "approx_position_xyz": info["approx_position_xyz"],
            "interval_s": info["interval_s"], "obs_types": list(types),
            "signals": [w if j is not None else None for w, j in zip(wanted, idx)],
            "epoch_flags": np.asarray(out.flag, dtype=np.int8), "time_system": info["time_system"]}
    return RawEpochs(t=np.asarray(out.t, dtype=float), start=np.asarray(out.start, dtype=np.int64),
                     prn=np.asarray(out.prn, dtype=np.int64), pr_m=np.asarray(out.pr, dtype=float),
                     doppler_hz=np.asarray(out.dop, dtype=float), cn0_dbhz=np.asarray(out.snr, dtype=float),
                     phase_cyc=np.asarray(out.ph, dtype=float), source=str(path), meta=meta)
