"""RINEX navigation-message reader (GPS, RINEX 2.10/2.11 and 3.0x).

``read_rinex_nav(path) -> NavData``.  Supports the Fortran ``D`` exponent, blank optional fields
(spares, fit interval), multi-system RINEX 3 files (non-GPS records are skipped) and the optional
header records (ionosphere alpha/beta, GPS–UTC parameters, leap seconds).  Any corrupt record —
a number that does not parse, a missing mandatory field, a record truncated by end of file —
raises :class:`ultratight.errors.NavDataError` naming the file, the line number (1-based) and
the field.
"""

from dataclasses import dataclass, field
from pathlib import Path

from ultratight.errors import InputFileError, NavDataError
from ultratight.signals.ephemeris import Ephemeris, in_fit_interval
from ultratight.signals.gpstime import datetime_to_gps, to_seconds

# Broadcast-orbit field names (RINEX 2.11 Table A4 / RINEX 3 Table A6), 4 per line, 7 lines.
ORBIT_FIELDS = (
    ("iode", "crs", "delta_n", "m0"),
    ("cuc", "e", "cus", "sqrt_a"),
    ("toe", "cic", "omega0", "cis"),
    ("i0", "crc", "omega", "omega_dot"),
    ("idot", "code_on_l2", "week", "l2p_flag"),
    ("sv_accuracy_m", "sv_health", "tgd", "iodc"),
    ("tx_tow", "fit_interval_h", "spare1", "spare2"),
)
OPTIONAL_FIELDS = {"fit_interval_h", "spare1", "spare2", "l2p_flag", "code_on_l2"}
# URA index thresholds (IS-GPS-200 §20.3.3.3.1.3), metres
URA_EDGES_M = (2.4, 3.4, 4.85, 6.85, 9.65, 13.65, 24.0, 48.0, 96.0, 192.0, 384.0, 768.0,
               1536.0, 3072.0, 6144.0)
# lines per record (including the epoch line) for the RINEX 3 systems we skip
RINEX3_RECORD_LINES = {"G": 8, "E": 8, "J": 8, "C": 8, "I": 8, "R": 4, "S": 4}


def ura_index_from_m(acc_m):
    for i, edge in enumerate(URA_EDGES_M):
        if acc_m <= edge:
            return i
    return 15


@dataclass
class NavData:
    """Contents of a navigation file: ephemerides per PRN (sorted by toe) and header data."""

    path: str
    version: float
    ephemerides: dict = field(default_factory=dict)   # prn -> list[Ephemeris] sorted by toe
    ion_alpha: tuple = None
    ion_beta: tuple = None
    utc: dict = None          # {"a0", "a1", "tot", "wnt"}
    leap_seconds: int = None

    @property
    def prns(self):
        return sorted(self.ephemerides)

    def select(self, prn, week, tow_s, healthy_only=True):
        """Ephemeris of ``prn`` with toe nearest to (week, tow_s), healthy and within its fit
        interval; ``None`` when there is none."""
        best, best_dt = None, None
        t = to_seconds(week, tow_s)
        for eph in self.ephemerides.get(int(prn), []):
            if healthy_only and not eph.healthy:
                continue
            if not in_fit_interval(eph, week, tow_s):
                continue
            dt = abs(float(t - to_seconds(eph.week, eph.toe)))
            if best is None or dt < best_dt:
                best, best_dt = eph, dt
        return best

    def select_all(self, week, tow_s, healthy_only=True):
        """dict prn -> selected Ephemeris for all PRNs that have one at (week, tow_s)."""
        out = {}
        for prn in self.prns:
            e = self.select(prn, week, tow_s, healthy_only)
            if e is not None:
                out[prn] = e
        return out


def _num(text, path, lineno, name, optional=False):
    s = text.strip()
    if not s:
        if optional:
            return 0.0
        raise NavDataError(f"{path}: line {lineno}: field '{name}' is empty (expected a number)")
    try:
        return float(s.replace("D", "E").replace("d", "e"))
    except ValueError:
        raise NavDataError(
            f"{path}: line {lineno}: field '{name}' = {s!r} is not a number") from None


def _fields4(line, start, width=19):
    return [line[start + k * width: start + (k + 1) * width] for k in range(4)]


def _parse_header(lines, path):
    info = {"ion_alpha": None, "ion_beta": None, "utc": None, "leap_seconds": None}
    if not lines or "RINEX VERSION" not in lines[0][60:]:
        raise NavDataError(f"{path}: line 1: missing 'RINEX VERSION / TYPE' header record")
    try:
        version = float(lines[0][:9])
    except ValueError:
        raise NavDataError(f"{path}: line 1: field 'version' = {lines[0][:9]!r} is not a number") from None
    ftype = lines[0][20:21]
    if ftype != "N":            # RINEX 2 'G' = GLONASS navigation, 'O' = observations, ...
        raise NavDataError(f"{path}: line 1: field 'file type' = {ftype!r}, expected 'N' (GPS navigation)")
    if version >= 3:
        sys_ = lines[0][40:41]
        if sys_ not in ("G", "M", " "):
            raise NavDataError(f"{path}: line 1: field 'satellite system' = {sys_!r}, expected G or M")
    for i, line in enumerate(lines):
        label = line[60:].strip()
        ln = i + 1
        if label == "END OF HEADER":
            return version, info, i + 1
        if label == "ION ALPHA":
            info["ion_alpha"] = tuple(_num(f, path, ln, "ion alpha") for f in
                                      [line[2 + 12 * k: 14 + 12 * k] for k in range(4)])
        elif label == "ION BETA":
            info["ion_beta"] = tuple(_num(f, path, ln, "ion beta") for f in
                                     [line[2 + 12 * k: 14 + 12 * k] for k in range(4)])
        elif label == "IONOSPHERIC CORR":
            key = line[:4].strip()
            vals = tuple(_num(line[5 + 12 * k: 17 + 12 * k], path, ln, f"{key} parameter") for k in range(4))
            if key == "GPSA":
                info["ion_alpha"] = vals
            elif key == "GPSB":
                info["ion_beta"] = vals
        elif label.startswith("DELTA-UTC"):
            info["utc"] = {"a0": _num(line[3:22], path, ln, "A0"), "a1": _num(line[22:41], path, ln, "A1"),
                           "tot": _num(line[41:50], path, ln, "T"), "wnt": _num(line[50:59], path, ln, "W")}
        elif label == "TIME SYSTEM CORR" and line[:4] == "GPUT":
            info["utc"] = {"a0": _num(line[5:22], path, ln, "A0"), "a1": _num(line[22:38], path, ln, "A1"),
                           "tot": _num(line[38:45], path, ln, "T"), "wnt": _num(line[45:50], path, ln, "W")}
        elif label == "LEAP SECONDS":
            info["leap_seconds"] = int(_num(line[:6], path, ln, "leap seconds"))
    raise NavDataError(f"{path}: line {len(lines)}: no 'END OF HEADER' record")


def _epoch(parts, path, lineno, version):
    names = ("year", "month", "day", "hour", "minute", "second")
    vals = []
    for name, txt in zip(names, parts):
        vals.append(_num(txt, path, lineno, f"epoch {name}"))
    y = int(vals[0])
    if version < 3:
        y += 1900 if y >= 80 else 2000
    if not (1 <= vals[1] <= 12 and 1 <= vals[2] <= 31 and 0 <= vals[3] < 24 and 0 <= vals[4] < 60
            and 0 <= vals[5] < 61):
        raise NavDataError(f"{path}: line {lineno}: field 'epoch' out of range: {parts}")
    return datetime_to_gps(y, int(vals[1]), int(vals[2]), int(vals[3]), int(vals[4]), vals[5])


def _record(lines, i, path, version):
    """Parse one GPS record starting at index i; returns Ephemeris."""
    l0 = lines[i]
    ln0 = i + 1
    if version >= 3:
        prn_txt = l0[1:3]
        ep = [l0[4:8], l0[9:11], l0[12:14], l0[15:17], l0[18:20], l0[21:23]]
        clk = _fields4(l0, 23)[:3]
        orbit_start = 4
    else:
        prn_txt = l0[0:2]
        ep = [l0[2:5], l0[5:8], l0[8:11], l0[11:14], l0[14:17], l0[17:22]]
        clk = _fields4(l0, 22)[:3]
        orbit_start = 3
    prn = _num(prn_txt, path, ln0, "PRN")
    if prn != int(prn) or not 1 <= prn <= 63:
        raise NavDataError(f"{path}: line {ln0}: field 'PRN' = {prn_txt!r} out of range 1..63")
    week_toc, toc = _epoch(ep, path, ln0, version)
    vals = {"af0": _num(clk[0], path, ln0, "af0"), "af1": _num(clk[1], path, ln0, "af1"),
            "af2": _num(clk[2], path, ln0, "af2")}
    for k, names in enumerate(ORBIT_FIELDS):
        j = i + 1 + k
        if j >= len(lines):
            raise NavDataError(f"{path}: line {j + 1}: record of PRN {int(prn)} (line {ln0}) truncated: "
                               f"missing broadcast orbit {k + 1} (fields {', '.join(names)})")
        line = lines[j]
        for name, txt in zip(names, _fields4(line, orbit_start)):
            if name == "fit_interval_h" or name.startswith("spare"):
                vals[name] = _num(txt, path, j + 1, name, optional=True)
            else:
                vals[name] = _num(txt, path, j + 1, name, optional=name in OPTIONAL_FIELDS)
    fit = vals["fit_interval_h"]
    if version < 3 and fit == 0.0:
        fit = 4.0
    if fit == 0.0:       # RINEX 3 gives hours too; 0 in some files means the 4 h default
        fit = 4.0
    week = int(vals["week"])
    return Ephemeris(
        prn=int(prn), week=week, toe=vals["toe"], toc=toc + (week_toc - week) * 604800.0,
        sqrt_a=vals["sqrt_a"], e=vals["e"], i0=vals["i0"], omega0=vals["omega0"],
        omega=vals["omega"], m0=vals["m0"], delta_n=vals["delta_n"], idot=vals["idot"],
        omega_dot=vals["omega_dot"], cuc=vals["cuc"], cus=vals["cus"], crc=vals["crc"],
        crs=vals["crs"], cic=vals["cic"], cis=vals["cis"], af0=vals["af0"], af1=vals["af1"],
        af2=vals["af2"], tgd=vals["tgd"], iodc=int(vals["iodc"]), iode=int(vals["iode"]),
        sv_health=int(vals["sv_health"]), ura_index=ura_index_from_m(vals["sv_accuracy_m"]),
        fit_interval_h=fit, code_on_l2=int(vals["code_on_l2"]), l2p_flag=int(vals["l2p_flag"]),
        tx_tow=vals["tx_tow"]), 8


def read_rinex_nav(path):
    """Read a RINEX 2.x / 3.x navigation file; returns :class:`NavData` (GPS records only).

    Values no field check anticipated (non-finite numbers, out-of-range dates) raise NavDataError too."""
    try:
        return _read_rinex_nav(path)
    except (ValueError, OverflowError, IndexError, TypeError) as exc:
        if isinstance(exc, NavDataError):
            raise
        raise NavDataError(f"{path}: malformed navigation record ({' '.join(str(exc).split())[:200]})") from None


def _read_rinex_nav(path):
    path = Path(path)
    try:
        text = path.read_text(encoding="ascii", errors="replace")
    except OSError as exc:
        raise InputFileError(f"{path}: cannot read RINEX navigation file: {exc.strerror or exc}") from None
    lines = [ln.rstrip("\r\n").ljust(80) for ln in text.splitlines()]
    version, info, i = _parse_header(lines, path)
    if version < 2 or version >= 4:
        raise NavDataError(f"{path}: line 1: field 'version' = {version}, expected 2.x or 3.x")
    ephs = {}
    seen = set()
    while i < len(lines):
        line = lines[i]
        if not line.strip():
            i += 1
            continue
        if version >= 3:
            sys_ = line[0]
            if sys_ != "G":
                if sys_ not in RINEX3_RECORD_LINES:
                    raise NavDataError(f"{path}: line {i + 1}: field 'satellite system' = {sys_!r} "
                                       f"is not a known RINEX 3 system letter")
                i += RINEX3_RECORD_LINES[sys_]
                continue
        eph, n_lines = _record(lines, i, path, version)
        key = (eph.prn, eph.week, eph.toe, eph.iode, eph.iodc)
        if key not in seen:
            seen.add(key)
            ephs.setdefault(eph.prn, []).append(eph)
        i += n_lines
    for prn in ephs:
        ephs[prn].sort(key=lambda e: (e.week, e.toe, e.tx_tow))
    return NavData(path=str(path), version=version, ephemerides=ephs, ion_alpha=info["ion_alpha"],
                   ion_beta=info["ion_beta"], utc=info["utc"], leap_seconds=info["leap_seconds"])
