"""RINEX 3.04 output of ``ultratight process``: GPS observations (C1C, L1C, D1C, S1C) and the
decoded navigation data (RINEX 3.04 GPS navigation with the ionospheric header records).

Format: RINEX 3.04 (IGS/RTCM RINEX WG, 2018), sections 5.1 (observation header and epoch
records, Tables A2/A3) and 5.2 (GPS navigation, Tables A5/A6).

Observations at each receiver epoch (receiver-clock time, GPS time system):

* ``C1C`` — the code pseudorange the PVT uses (m; carrier smoothed when ``--smoothing`` > 0, the
  header says so in a COMMENT), ``L1C`` — accumulated carrier phase (cycles, RINEX sign: grows
  with the range; a half cycle is added when the LNAV preamble shows the inverted polarity),
  ``D1C`` — Doppler (Hz, positive for an approaching satellite), ``S1C`` — C/N0 (dB-Hz).
* loss-of-lock indicator on L1C: bit 0 when the phase was not continuously locked since the
  previous epoch of that satellite (first epoch, re-acquisition, lost PLL lock), bit 1 while the
  half-cycle ambiguity is unresolved (no LNAV preamble yet).
* signal-strength indicator on every observation: ``clip(floor(C/N0 / 6), 1, 9)`` (RINEX 3
  Table 7 mapping of dB-Hz to 1..9).

The body is streamed to a temporary file; :meth:`RinexObsWriter.finish` writes the header (time
of first observation, approximate position from the receiver's median fix) followed by the body
and renames the result onto the target, so a failed run never leaves a partial file.
"""

import math
from datetime import datetime, timedelta
from pathlib import Path

import numpy as np

from ultratight import __version__
from ultratight.errors import InputFileError
from ultratight.io_guard import atomic_path, tmp_name, write_text_atomic

GPS_EPOCH = datetime(1980, 1, 6)
OBS_TYPES = ("C1C", "L1C", "D1C", "S1C")


def gps_to_datetime(week, tow_s):
    """datetime (GPS time scale, naive) of a GPS week and time of week."""
    return GPS_EPOCH + timedelta(weeks=int(week), seconds=float(tow_s))


def _hline(text, label):
    return f"{text:<60.60s}{label:<20s}\n"


def ssi(cn0_dbhz):
    """RINEX signal-strength indicator 1..9 from C/N0 (dB-Hz); 0 (blank) when unknown."""
    if not np.isfinite(cn0_dbhz):
        return 0
    return int(min(9, max(1, math.floor(cn0_dbhz / 6.0))))


def _obs_field(value, lli=0, s=0):
    if value is None or not np.isfinite(value) or abs(value) >= 1e10:
        return " " * 16
    return f"{value:14.3f}{(str(lli) if lli else ' ')}{(str(s) if s else ' ')}"


def _program_lines(run_by="ultratight"):
    now = datetime.utcnow().strftime("%Y%m%d %H%M%S UTC")
    return _hline(f"{'ultratight ' + __version__:<20s}{run_by:<20s}{now:<20s}", "PGM / RUN BY / DATE")


class RinexObsWriter:
    """Streaming RINEX 3.04 GPS observation writer (see the module doc)."""

    def __init__(self, path, interval_s, comments=(), marker="ULTRATIGHT"):
        self.path = Path(path)
        if not self.path.parent.is_dir():
            raise InputFileError(f"output directory does not exist: {self.path.parent}")
        self.interval_s = float(interval_s)
        self.comments = list(comments)
        self.marker = marker
        self.first = None
        self.last = None
        self.n_epochs = 0
        self.locked = {}          # prn -> phase continuously locked up to the previous epoch
        self.body = tmp_name(self.path.with_name(self.path.name + ".body"))   # the epochs, before the header
        self.f = open(self.body, "w")          # last: nothing after it can leave the file behind

    def add_epoch(self, week, tow_s, sats):
        """One epoch: ``sats`` = list of dicts prn, pr_m, phase_cycles, doppler_hz, cn0_dbhz,
        lock (bool, phase locked now), continuous (bool, no restart since the previous epoch),
        half_cycle (bool, ambiguity unresolved)."""
        rows = [s for s in sats if np.isfinite(s["pr_m"])]
        if not rows:
            return
        t = gps_to_datetime(week, tow_s)
        sec = t.second + t.microsecond * 1e-6
        if self.first is None:
            self.first = t
        self.last = t
        self.f.write(f"> {t.year:4d} {t.month:02d} {t.day:02d} {t.hour:02d} {t.minute:02d}{sec:11.7f}  0"
                     f"{len(rows):3d}\n")
        now_locked = {}
        for s in sorted(rows, key=lambda r: r["prn"]):
            prn = int(s["prn"])
            lock = bool(s["lock"]) and np.isfinite(s["phase_cycles"])
            lli = 0
            if lock:
                if not (self.locked.get(prn, False) and s.get("continuous", True)):
                    lli |= 1
                if s.get("half_cycle", False):
                    lli |= 2
            now_locked[prn] = lock
            k = ssi(s["cn0_dbhz"])
            self.f.write(f"G{prn:02d}" + _obs_field(s["pr_m"], 0, k)
                         + _obs_field(s["phase_cycles"] if lock else None, lli, k)
                         + _obs_field(s["doppler_hz"], 0, k)
                         + _obs_field(s["cn0_dbhz"], 0, 0) + "\n")
        self.locked = now_locked
        self.n_epochs += 1

    def header(self, approx_pos_e):
        h = [_hline(f"{'3.04':>9s}{'':11s}{'OBSERVATION DATA':<20s}{'G (GPS)':<20s}", "RINEX VERSION / TYPE"),
             _program_lines()]
        for c in self.comments:
            for k in range(0, len(c), 60):
                h.append(_hline(c[k:k + 60], "COMMENT"))
        pos = approx_pos_e if approx_pos_e is not None else (0.0, 0.0, 0.0)
        h += [_hline(self.marker, "MARKER NAME"),
              _hline("NON_GEODETIC", "MARKER TYPE"),
              _hline(f"{'unknown':<20s}{'ultratight':<40s}", "OBSERVER / AGENCY"),
              _hline(f"{'0':<20s}{'ULTRATIGHT SDR':<20s}{__version__:<20s}", "REC # / TYPE / VERS"),
              _hline(f"{'0':<20s}{'UNKNOWN':<20s}", "ANT # / TYPE"),
              _hline("".join(f"{v:14.4f}" for v in pos), "APPROX POSITION XYZ"),
              _hline("".join(f"{0.0:14.4f}" for _ in range(3)), "ANTENNA: DELTA H/E/N"),
              _hline(f"G{len(OBS_TYPES):5d}" + "".join(f" {o}" for o in OBS_TYPES), "SYS / # / OBS TYPES"),
              _hline("DBHZ", "SIGNAL STRENGTH UNIT"),
              _hline(f"{self.interval_s:10.3f}", "INTERVAL")]
        for label, t in (("TIME OF FIRST OBS", self.first), ("TIME OF LAST OBS", self.last)):
            sec = t.second + t.microsecond * 1e-6
            h.append(_hline(f"{t.year:6d}{t.month:6d}{t.day:6d}{t.hour:6d}{t.minute:6d}{sec:13.7f}     GPS",
                            label))
        h += [_hline("G L1C", "SYS / PHASE SHIFT"), _hline("", "END OF HEADER")]
        return "".join(h)

    def finish(self, approx_pos_e):
        """Write header + body to the target (atomic); nothing is written without an epoch."""
        self.f.close()
        try:
            if self.first is None:
                return False
            with atomic_path(self.path) as tmp, open(tmp, "w") as out, open(self.body) as body:
                out.write(self.header(approx_pos_e))
                for line in body:
                    out.write(line)
            return True
        finally:
            self.body.unlink(missing_ok=True)

    def abort(self):
        try:
            self.f.close()
        finally:
            self.body.unlink(missing_ok=True)


def _d19(x):
    """RINEX 3 navigation number: 19 characters, 12 decimals, 'E' exponent."""
    return f"{x:19.12E}"


def write_rinex_nav(path, ephemerides, iono=None, leap_seconds=None, comments=()):
    """GPS navigation file (RINEX 3.04) of ``ephemerides`` (iterable of Ephemeris; duplicates of
    (prn, week, toe, iode) written once), with GPSA/GPSB ionospheric records when ``iono`` =
    (alpha, beta) is given.  Written to a temporary name, then renamed."""
    from ultratight.signals.rinex import URA_EDGES_M

    path = Path(path)
    if not path.parent.is_dir():
        raise InputFileError(f"output directory does not exist: {path.parent}")
    h = [_hline(f"{'3.04':>9s}{'':11s}{'N: GNSS NAV DATA':<20s}{'G: GPS':<20s}", "RINEX VERSION / TYPE"),
         _program_lines()]
    for c in comments:
        for k in range(0, len(c), 60):
            h.append(_hline(c[k:k + 60], "COMMENT"))
    if iono is not None:
        alpha, beta = iono
        h.append(_hline("GPSA " + "".join(f"{v:12.4E}" for v in alpha), "IONOSPHERIC CORR"))
        h.append(_hline("GPSB " + "".join(f"{v:12.4E}" for v in beta), "IONOSPHERIC CORR"))
    if leap_seconds is not None:
        h.append(_hline(f"{int(leap_seconds):6d}", "LEAP SECONDS"))
    h.append(_hline("", "END OF HEADER"))
    seen, recs = set(), []
    for e in sorted(ephemerides, key=lambda e: (e.prn, e.week, e.toe)):
        key = (e.prn, e.week, e.toe, e.iode)
        if key in seen:
            continue
        seen.add(key)
        wk_toc, toc_s = int(e.week), float(e.toc)
        if toc_s - e.toe > 302400.0:
            wk_toc -= 1
        elif toc_s - e.toe < -302400.0:
            wk_toc += 1
        t = gps_to_datetime(wk_toc, toc_s)
        ura_m = URA_EDGES_M[e.ura_index] if e.ura_index < len(URA_EDGES_M) else 6144.0
        tx = e.tx_tow if np.isfinite(e.tx_tow) else e.toe
        lines = [f"G{e.prn:02d} {t.year:4d} {t.month:02d} {t.day:02d} {t.hour:02d} {t.minute:02d} {t.second:02d}"
                 + _d19(e.af0) + _d19(e.af1) + _d19(e.af2)]
        orbit = ((e.iode, e.crs, e.delta_n, e.m0), (e.cuc, e.e, e.cus, e.sqrt_a),
                 (e.toe, e.cic, e.omega0, e.cis), (e.i0, e.crc, e.omega, e.omega_dot),
                 (e.idot, e.code_on_l2, e.week, e.l2p_flag), (ura_m, e.sv_health, e.tgd, e.iodc),
                 (tx, e.fit_interval_h))
        for row in orbit:
            lines.append("    " + "".join(_d19(float(v)) for v in row))
        recs.append("\n".join(lines) + "\n")
    write_text_atomic(path, "".join(h) + "".join(recs))
    return len(recs)
