"""Recorded IMU logs in their own layouts and time bases, read into :class:`ImuData` in GPS time.

Every reader returns increments ``dtheta_b`` (rad) / ``dv_b`` (m/s) in the body frame FLU with
``t`` (end of each interval) and ``t0`` (start of the first) in **continuous GPS seconds** since
1980-01-06 00:00:00 GPST (``meta["time_scale"] = "gps"``); intervals may be non-uniform and
``rate_hz`` is the median rate.  Layouts (docs/integrate-inputs.md):

* ``rtklib-raw`` — the raw text log of a serial IMU as an RTKLIB stream server saved it: lines
  ``ax,ay,az,gx,gy,gz,tick`` (g, deg/s, the IMU's millisecond counter since power-up) with the
  RTKLIB time-tag file ``LOG.tag`` beside it (:func:`read_tag`, :func:`tag_clock_fit`).  The first
  line is always dropped (a log opened on a running stream starts inside a line, and a cut that
  still leaves seven fields cannot be told from a whole line); the last line is dropped when it has
  no line end.  Blank lines are skipped; any other malformed line is refused with its number.
* ``sf`` — the converted CSV: GPS time as seconds since 1970-01-01 *in the GPS time scale*, specific
  force in g (3 columns), angular rate in rad/s (3 columns), further columns ignored.  (On the walk
  recording its stamps are the raw log's millisecond ticks stretched linearly from the tag's start to
  its last entry: intervals of 6, 7, 8 and 9 ms × 1.00014.)
* ``kf-gins`` — the KF-GINS text layout: GPS seconds of week, dθ x y z (rad), dv x y z (m/s),
  axes FRD, white-space separated; the GPS week comes from ``gps_week`` or the declaration.
* ``csv`` / ``h5`` — the project's files (:mod:`ultratight.ins.imu_data`) with the declaration
  ``time_ref = "gps_tow"`` and ``gps_week``.

Rates are averages over the interval that ends at their stamp: increment = rate × (t[k] − t[k−1]),
the first interval taken as the median one.  Two lines of a raw log with the same tick cannot be
ordered and share a zero interval (their increment would be zero): the later is dropped and counted
in ``meta["repeated_ticks"]``.  The millisecond ticks jitter by their quantisation; they are used as
they come (no smoothing), so the summed intervals equal the logged span and the integrated angle and
velocity keep no bias from it.

Axes: the declaration (``axes``, :mod:`ultratight.ins.imu_decl`) turns the file's axes into FLU;
the mount (:func:`mount_matrix`) then rotates the sensor frame into the body frame.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ultratight.errors import ConfigError, InputFileError
from ultratight.ins import imu_decl
from ultratight.ins.imu_data import GAP_FACTOR, ImuData

G0 = 9.80665
DEG = math.pi / 180.0
SECONDS_PER_WEEK = 604800.0
# 1980-01-06 minus 1970-01-01: 3657 days; "seconds since 1970 in the GPS time scale" minus this
# is continuous GPS time (no leap seconds enter: both count in GPST)
GPS_EPOCH_UNIX_S = 315964800.0
FORMATS = ("csv", "h5", "rtklib-raw", "sf", "kf-gins")
FRD_FLU = np.diag([1.0, -1.0, -1.0])        # v_FLU = FRD_FLU v_FRD (its own inverse)

TAG_HEADER_LEN = 60
TAG_MAGIC = b"TIMETAG RTKLIB"
TAG_FIXED = TAG_HEADER_LEN + 4 + 4 + 8
LATENCY_SPREAD_MAX_S = 1.0      # arrival latency beyond the lower envelope allowed for a matching tag
CLOCK_RATE_MAX = 1e-3           # |IMU clock rate - 1| allowed against the tag (1000 ppm)
ENVELOPE_BIN_S = 10.0
TICK_QUANTUM_S = 1e-3           # millisecond ticks (raw logs and the sf copy made from them): the gap
                                # rule allows 1.5 x the median interval plus one tick


# ------------------------------------------------------------------ time bases
def gps_seconds_of_week(week, tow_s):
    """Continuous GPS seconds of GPS ``week`` and seconds of week ``tow_s``."""
    return np.asarray(week, dtype=float) * SECONDS_PER_WEEK + np.asarray(tow_s, dtype=float)


def week_and_tow(t_gps):
    """(week, seconds of week) of continuous GPS seconds."""
    t = np.asarray(t_gps, dtype=float)
    week = np.floor(t / SECONDS_PER_WEEK)
    return week.astype(int), t - week * SECONDS_PER_WEEK


def gps_seconds_from_unix_gpst(s):
    """Continuous GPS seconds of "seconds since 1970-01-01 in the GPS time scale" (no leap seconds)."""
    return np.asarray(s, dtype=float) - GPS_EPOCH_UNIX_S


def unix_gpst_from_gps_seconds(t):
    """Inverse of :func:`gps_seconds_from_unix_gpst`."""
    return np.asarray(t, dtype=float) + GPS_EPOCH_UNIX_S


# ------------------------------------------------------------------ mount and lever arm
def _r1(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, s], [0.0, -s, c]])


def _r2(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]])


def _r3(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])


def mount_matrix_frd(roll_deg, pitch_deg, yaw_deg):
    """C = R1(roll) R2(pitch) R3(yaw) (frame rotations; the form of C_n^b of a body at that roll,
    pitch and yaw): f_body = C f_sensor, both FRD."""
    return _r1(roll_deg * DEG) @ _r2(pitch_deg * DEG) @ _r3(yaw_deg * DEG)


def mount_matrix(roll_deg, pitch_deg, yaw_deg):
    """FLU -> FLU rotation R with v_body = R v_sensor for the declared (FLU) sensor vectors: the
    mount C of :func:`mount_matrix_frd` written in FLU (R = T C T, T = diag(1, -1, -1))."""
    for name, v in (("roll", roll_deg), ("pitch", pitch_deg), ("yaw", yaw_deg)):
        if isinstance(v, bool) or not isinstance(v, (int, float, np.floating)) or not math.isfinite(v):
            raise ConfigError(f"IMU mount {name} must be a finite number of degrees, got {v!r}")
    return FRD_FLU @ mount_matrix_frd(roll_deg, pitch_deg, yaw_deg) @ FRD_FLU


def lever_arm_frd_to_flu(lever_frd):
    """A lever arm given in body axes FRD (the CLI's ``--lever-arm X Y Z`` of integrate) in FLU (m)."""
    la = np.asarray(lever_frd, dtype=float).reshape(-1)
    if la.shape != (3,) or not np.all(np.isfinite(la)):
        raise ConfigError(f"lever arm must be 3 finite numbers (m), got {lever_frd!r}")
    return FRD_FLU @ la


# ------------------------------------------------------------------ RTKLIB time tag
@dataclass
class TimeTag:
    """An RTKLIB time-tag file.  ``tick_ms[i]`` (ms since the log was opened) is when the log had
    ``file_pos[i]`` bytes; the log was opened at ``start_unix_gpst`` (integer s since 1970 in the GPS
    time scale) + ``start_frac_s``.  ``tick_open_ms`` is the recording host's tick at that moment
    (RTKLIB's ``tick_f``; it is not needed to map the entries)."""
    path: str
    header: str
    tick_open_ms: int
    start_unix_gpst: int
    start_frac_s: float
    tick_ms: np.ndarray
    file_pos: np.ndarray

    @property
    def t_start_gps(self):
        """Continuous GPS seconds at which the log was opened."""
        return float(gps_seconds_from_unix_gpst(self.start_unix_gpst)) + self.start_frac_s

    def gps_time(self, tick_ms):
        """GPS seconds of tag ticks (ms since open)."""
        return self.t_start_gps + np.asarray(tick_ms, dtype=float) / 1000.0


def read_tag(path):
    """Read an RTKLIB ``.tag`` file (little-endian: 60-byte header text, uint32 host tick at open,
    uint32 start time [s since 1970, GPS time scale], float64 fraction of a second, then (uint32
    tick_ms, uint32 file_pos) pairs).  One InputFileError line on a wrong header, size, time or
    non-monotonic entries."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise InputFileError(f"{path}: cannot read RTKLIB time-tag file ({exc.strerror or exc})") from None
    if len(raw) < TAG_FIXED or not raw.startswith(TAG_MAGIC):
        raise InputFileError(f"{path}: not an RTKLIB time-tag file (expected a {TAG_FIXED}-byte header starting "
                             f"{TAG_MAGIC.decode()!r})")
    if (len(raw) - TAG_FIXED) % 8:
        raise InputFileError(f"{path}: size {len(raw)} B is not the header plus whole 8-byte (tick, file "
                             "position) pairs: truncated time-tag file")
    header = raw[:TAG_HEADER_LEN].split(b"\0", 1)[0].decode("ascii", "replace")
    tick_open, start = struct.unpack_from("<II", raw, TAG_HEADER_LEN)
    (frac,) = struct.unpack_from("<d", raw, TAG_HEADER_LEN + 8)
    if not (math.isfinite(frac) and 0.0 <= frac < 1.0) or start < GPS_EPOCH_UNIX_S:
        raise InputFileError(f"{path}: start time {start} s + {frac!r} is not a GPS time after 1980-01-06")
    pairs = np.frombuffer(raw, dtype="<u4", offset=TAG_FIXED).reshape(-1, 2).astype(np.int64)
    if pairs.shape[0] == 0:
        raise InputFileError(f"{path}: time-tag file has no (tick, file position) entries")
    for j, what in ((0, "tick"), (1, "file position")):
        bad = np.nonzero(np.diff(pairs[:, j]) < 0)[0]
        if bad.size:
            raise InputFileError(f"{path}: entry {int(bad[0]) + 1}: {what} decreases ({int(pairs[bad[0], j])} -> "
                                 f"{int(pairs[bad[0] + 1, j])})")
    return TimeTag(str(path), header, int(tick_open), int(start), float(frac), pairs[:, 0].copy(),
                   pairs[:, 1].copy())


def tag_byte_offsets(tag, log_size, n_newlines, has_cr, log_path):
    """How the tag's file positions count the log's bytes: ``"direct"`` when they fit in the file,
    ``"crlf"`` when the log was recorded with CR LF line ends and stored with LF ends since (the
    positions then reach exactly past the stored size by up to one byte per line).  Any other tag
    is refused: it does not belong to this log."""
    top = int(tag.file_pos[-1])
    if top <= log_size:
        return "direct"
    if not has_cr and top <= log_size + n_newlines:
        return "crlf"
    raise InputFileError(f"{tag.path}: file positions reach {top} B, past the size of {log_path} ({log_size} B"
                         f"{'' if has_cr else f', {log_size + n_newlines} B counting CR LF line ends'}): this "
                         "time-tag file is not the log's")


def tag_clock_fit(tag, arrival_tick_ms, imu_tick_ms, log_path):
    """Map the IMU's own millisecond counter to GPS time through the tag.

    ``arrival_tick_ms``: tag tick by which each line had been written; the arrival time minus the
    IMU tick is the offset of the IMU clock plus a transfer latency (>= 0, a few ms; longer when
    the host buffered).  The lower envelope of that difference (its minimum per 10 s of IMU time,
    a straight line through those minima) is taken as the clock offset and rate: t_gps = a +
    tick/1000 + b (tick - tick_0)/1000.  The remaining constant latency below the envelope is not
    observable from the tag; ``--imu-time-offset`` corrects it.  Returns ((base, t_rel), info) with
    the GPS stamps ``base + t_rel`` (t_rel keeps the intervals exact).  Refuses (one line) a tag whose
    arrivals do not follow the IMU ticks: latency spread over 1 s, clock rate beyond 1000 ppm, or
    the IMU's span outside the tag's span."""
    tick_s = np.asarray(imu_tick_ms, dtype=float) / 1000.0
    arr = tag.gps_time(arrival_tick_ms)
    d = arr - tick_s
    rel = tick_s - tick_s[0]
    nb = max(1, int(rel[-1] // ENVELOPE_BIN_S) + 1)
    b_idx = np.minimum((rel // ENVELOPE_BIN_S).astype(int), nb - 1)
    mins = [np.flatnonzero(b_idx == k) for k in range(nb)]
    pick = np.array([m[np.argmin(d[m])] for m in mins if m.size])
    if pick.size >= 2 and rel[pick[-1]] - rel[pick[0]] >= 2 * ENVELOPE_BIN_S:
        b, a = np.polyfit(rel[pick], d[pick], 1)
    else:
        b, a = 0.0, float(np.min(d))
    resid = d - (a + b * rel)
    a += float(min(0.0, resid.min()))
    resid = d - (a + b * rel)
    span_tag = (float(tag.tick_ms[-1]) - float(tag.tick_ms[0])) / 1000.0
    what = f"{tag.path} does not match {log_path}"
    if abs(b) > CLOCK_RATE_MAX:
        raise InputFileError(f"{what}: the IMU ticks run {b * 1e6:+.0f} ppm against the tag's clock")
    if resid.max() > LATENCY_SPREAD_MAX_S:
        raise InputFileError(f"{what}: line arrivals scatter {resid.max():.3f} s around the IMU ticks "
                             f"(more than {LATENCY_SPREAD_MAX_S:g} s)")
    if rel[-1] > span_tag + LATENCY_SPREAD_MAX_S:
        raise InputFileError(f"{what}: the IMU ticks span {rel[-1]:.3f} s, the tag {span_tag:.3f} s")
    base, t_rel = float(a + tick_s[0]), rel * (1.0 + b)     # t_gps = base + t_rel
    info = {"offset_s": float(a), "clock_rate_ppm": float(b * 1e6),
            "latency_s": {"median": float(np.median(resid)), "p99": float(np.percentile(resid, 99)),
                          "max": float(resid.max())},
            "tag_start_gps_s": tag.t_start_gps, "tag_span_s": span_tag, "tag_header": tag.header}
    return (base, t_rel), info


# ------------------------------------------------------------------ text helpers
def _read_bytes(path, what):
    path = Path(path)
    if not path.is_file():
        raise InputFileError(f"{path}: {what} not found")
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise InputFileError(f"{path}: cannot read {what} ({exc.strerror or exc})") from None
    if b"\0" in raw[:65536]:
        raise InputFileError(f"{path}: {what} holds binary data (NUL bytes), not text")
    return raw


def _numbers(path, ln, fields, n_want, names):
    """Floats of the first ``n_want`` ``fields`` of line ``ln``; one InputFileError line when a field
    is missing, not a number or NaN/inf."""
    if len(fields) < n_want:
        raise InputFileError(f"{path}: line {ln}: {len(fields)} fields, expected {n_want} ({', '.join(names)})")
    out = []
    for j in range(n_want):
        try:
            v = float(fields[j])
        except ValueError:
            raise InputFileError(f"{path}: line {ln}: {names[j]} {fields[j].strip()!r} is not a number") from None
        if not math.isfinite(v):
            raise InputFileError(f"{path}: line {ln}: {names[j]} is {fields[j].strip()} (NaN/inf not allowed)")
        out.append(v)
    return out


def _increments_from_rates(t, gyro_radps, acc_mps2):
    """(t0, dtheta, dv, median interval): rates averaged over (t[k-1], t[k]] times the interval."""
    dts = np.diff(t)
    med = float(np.median(dts)) if dts.size else 0.0
    dts = np.concatenate([[med], dts])
    return float(t[0] - med), gyro_radps * dts[:, None], acc_mps2 * dts[:, None], med


RAW_NAMES = ("ax", "ay", "az", "gx", "gy", "gz", "tick")


def parse_raw_log(path):
    """The lines of a raw ``ax,ay,az,gx,gy,gz,tick`` log: dict with ``values`` (n, 6) file units,
    ``tick_ms`` (n,) unwrapped int, ``end_offset`` (n,) byte offset just past each line's end,
    ``line_no`` (n,), ``skipped`` line numbers, ``repeated_ticks``, ``size``, ``n_newlines``,
    ``has_cr`` (rules in the module doc)."""
    raw = _read_bytes(path, "IMU log")
    lines = raw.split(b"\n")
    ends = np.cumsum([len(s) + 1 for s in lines])
    skipped = [1]
    last = len(lines) - 1
    if lines[-1] != b"":
        skipped.append(len(lines))        # no line end: partial
    vals, ticks, end_off, line_no = [], [], [], []
    for i in range(1, last):
        text = lines[i].decode("ascii", "replace").strip()
        if not text:
            continue
        f = text.split(",")
        if len(f) != 7:
            raise InputFileError(f"{path}: line {i + 1}: {len(f)} fields, a raw IMU log line has 7 "
                                 f"({','.join(RAW_NAMES)})")
        v = _numbers(path, i + 1, f, 6, RAW_NAMES)
        try:
            tk = int(f[6])
        except ValueError:
            raise InputFileError(f"{path}: line {i + 1}: tick {f[6].strip()!r} is not a whole number of ms") from None
        vals.append(v)
        ticks.append(tk)
        end_off.append(int(ends[i]))
        line_no.append(i + 1)
    if len(ticks) < 2:
        raise InputFileError(f"{path}: fewer than 2 complete IMU lines")
    tick = np.array(ticks, dtype=np.int64)
    step = np.diff(tick)
    tick[1:] += np.cumsum(np.where(step < -(1 << 31), 1 << 32, 0))      # uint32 ms counter wrap
    d = np.diff(tick)
    back = np.nonzero(d < 0)[0]
    if back.size:
        k = int(back[0]) + 1
        raise InputFileError(f"{path}: line {line_no[k]}: tick {ticks[k]} ms goes back from {ticks[k - 1]} ms")
    keep = np.concatenate([[True], d > 0])
    return {"values": np.array(vals)[keep], "tick_ms": tick[keep], "end_offset": np.array(end_off)[keep],
            "line_no": np.array(line_no)[keep], "skipped": skipped, "repeated_ticks": int((~keep).sum()),
            "size": len(raw), "n_newlines": raw.count(b"\n"), "has_cr": b"\r" in raw}


def read_rtklib_raw(path, tag=None):
    """A raw log with its RTKLIB time tag (default ``LOG.tag``) -> ((base, t_rel) GPS s, gyro rad/s,
    accel m/s^2, meta) in the file's axes, the stamps mapped by :func:`tag_clock_fit`."""
    path = Path(path)
    tag_path = Path(tag) if tag is not None else path.with_name(path.name + ".tag")
    if not tag_path.is_file():
        raise ConfigError(f"{path}: a raw IMU log needs its RTKLIB time-tag file ({tag_path} not found; "
                          "give --imu-tag)")
    tg = read_tag(tag_path)
    p = parse_raw_log(path)
    mode = tag_byte_offsets(tg, p["size"], p["n_newlines"], p["has_cr"], path)
    end = p["end_offset"]
    if mode == "crlf":
        end = end + p["line_no"]          # one CR before every LF up to and including the line's
    k = np.searchsorted(tg.file_pos, end, side="left")
    if k[0] >= tg.file_pos.size or k[-1] >= tg.file_pos.size:
        n_out = int((k >= tg.file_pos.size).sum())
        raise InputFileError(f"{tag_path}: {n_out} lines of {path} lie past the tag's last file position "
                             f"{int(tg.file_pos[-1])} B: this time-tag file is not the log's")
    tb, info = tag_clock_fit(tg, tg.tick_ms[k], p["tick_ms"], path)
    info["byte_count"] = mode
    meta = {"tag": info, "skipped_lines": p["skipped"], "repeated_ticks": p["repeated_ticks"],
            "tag_path": str(tag_path), "line_no": p["line_no"]}
    return tb, p["values"][:, 3:6] * DEG, p["values"][:, 0:3] * G0, meta


def _text_rows(path, what, sep):
    """(line number, fields) of the non-blank, non-comment (``#``, ``%``) lines of a text log."""
    raw = _read_bytes(path, what)
    out = []
    for i, ln in enumerate(raw.decode("ascii", "replace").splitlines()):
        s = ln.strip()
        if s and s[0] not in "#%":
            out.append((i + 1, s.split(sep) if sep else s.split()))
    if len(out) < 2:
        raise InputFileError(f"{path}: fewer than 2 data lines in the {what}")
    return out


def _layout_guard(path, row, time_ok, time_what, layout):
    """Refuse in one line a file whose first data line is not of ``layout``: fewer than 7 fields or a
    first field that is not a time of ``time_what``."""
    ln, f = row
    try:
        ok = len(f) >= 7 and time_ok(float(f[0]))
    except ValueError:
        ok = False
    if not ok:
        raise InputFileError(f"{path}: line {ln}: {len(f)} field(s) starting {f[0].strip()[:24]!r}; expected 7 or "
                             f"more with {time_what} first: not the {layout} layout")


SF_NAMES = ("time (s since 1970, GPST)", "ax (g)", "ay (g)", "az (g)", "gx (rad/s)", "gy (rad/s)", "gz (rad/s)")


def read_sf(path):
    """The ``_sf`` CSV -> ((base, t_rel) GPS s, gyro rad/s, accel m/s^2, meta), the file's axes."""
    rows = _text_rows(path, "IMU CSV (sf layout)", ",")
    _layout_guard(path, rows[0], lambda t: t > GPS_EPOCH_UNIX_S, "seconds since 1970 after the GPS epoch", "sf")
    data = np.array([_numbers(path, ln, f, 7, SF_NAMES) for ln, f in rows])
    i0 = math.floor(data[0, 0])
    t_rel = np.array([_since(f[0], i0) for _ln, f in rows])
    return ((float(gps_seconds_from_unix_gpst(i0)), t_rel), data[:, 4:7], data[:, 1:4] * G0,
            {"line_no": [r[0] for r in rows]})


def _since(text, i0):
    """Seconds of the decimal ``text`` after the whole second ``i0``, without the rounding of a
    float of 1e9 s (0.24 us steps)."""
    ip, _, fp = text.strip().partition(".")
    try:
        return (int(ip) - i0) + (float("0." + fp) if fp else 0.0)
    except ValueError:
        return float(text) - i0


KF_NAMES = ("time (GPS s of week)", "dthx (rad)", "dthy (rad)", "dthz (rad)", "dvx (m/s)", "dvy (m/s)",
            "dvz (m/s)")


def read_kf_gins(path, gps_week):
    """The KF-GINS IMU text file -> ((base, t_rel) GPS s, dtheta rad, dv m/s, meta), axes FRD as in
    the file."""
    if gps_week is None:
        raise ConfigError(f"{path}: the KF-GINS layout is stamped in seconds of week: give the GPS week "
                          "(--gps-week, or gps_week in the sidecar)")
    rows = _text_rows(path, "KF-GINS IMU file", None)
    _layout_guard(path, rows[0], lambda t: 0.0 <= t < SECONDS_PER_WEEK + 1.0, "GPS seconds of week", "KF-GINS")
    data = np.array([_numbers(path, ln, f, 7, KF_NAMES) for ln, f in rows])
    s0 = math.floor(data[0, 0])
    base = float(gps_seconds_of_week(int(gps_week), s0))
    return (base, data[:, 0] - s0), data[:, 1:4], data[:, 4:7], {"line_no": [r[0] for r in rows],
                                                               "gps_week": int(gps_week)}


def detect_format(path):
    """The layout of an IMU log from its name and first lines: ``h5`` for .h5/.hdf5 (or the HDF5
    signature); a header naming ``t_s`` -> ``csv``; 7 comma-separated fields ending in a whole
    number -> ``rtklib-raw``; a first comma-separated field above 3.2e8 (s since 1970) -> ``sf``;
    7 or more white-space separated numbers, the first below 604801 -> ``kf-gins``.  ConfigError
    when none fits."""
    path = Path(path)
    if path.suffix.lower() in (".h5", ".hdf5"):
        return "h5"
    try:
        with open(path, "rb") as fh:
            head = fh.read(4096)
    except OSError as exc:
        raise InputFileError(f"{path}: cannot read IMU log ({exc.strerror or exc})") from None
    if head.startswith(b"\x89HDF"):
        return "h5"
    lines = [ln.strip() for ln in head.decode("ascii", "replace").splitlines()[:-1]]
    lines = [ln for ln in lines if ln and ln[0] not in "#%"]
    if any("t_s" in ln.lower().split(",")[0] for ln in lines[:1]):
        return "csv"
    probe = lines[1] if len(lines) > 1 else (lines[0] if lines else "")
    f = probe.split(",")
    try:
        if len(f) == 7 and f[6].strip().lstrip("-").isdigit():
            [float(x) for x in f[:6]]
            return "rtklib-raw"
        if len(f) >= 7 and float(f[0]) > GPS_EPOCH_UNIX_S:
            return "sf"
        w = probe.split()
        if len(w) >= 7 and 0.0 <= float(w[0]) < SECONDS_PER_WEEK + 1.0:
            [float(x) for x in w[:7]]
            return "kf-gins"
    except ValueError:
        pass
    raise ConfigError(f"{path}: cannot tell the IMU log layout from its first lines; give --imu-format "
                      f"({', '.join(FORMATS)})")


# the fixed kind / units of the text layouts (a declaration may not say otherwise)
FIXED_UNITS = {"rtklib-raw": ("rates", "deg/s", "g"), "sf": ("rates", "rad/s", "g"),
               "kf-gins": ("increments", "rad", "m/s")}


def _check_fixed_units(fmt, dec, path):
    kind, gu, au = FIXED_UNITS[fmt]
    for name, have, want in (("kind", dec.kind, kind), ("gyro_unit", dec.gyro_unit, gu),
                             ("accel_unit", dec.accel_unit, au)):
        if have is not None and have != want:
            raise ConfigError(f"{path}: the {fmt} layout is {kind} in {gu} and {au}; the declaration says "
                              f"{name} = {have!r} ({dec.source})")


def _read_project_file(path, fmt, overrides, gps_week):
    """The project's CSV / HDF5 in GPS time: (ImuData with t, t0 in GPS seconds, declaration)."""
    if fmt == "csv":
        ov = dict(overrides or {})
        if gps_week is not None and ov.get("gps_week") is None:
            ov["gps_week"] = int(gps_week)
        dec = imu_decl.resolve_declaration(path, ov)
        imu = imu_decl.read_imu_file(path, ov)
    else:
        # HDF5 is in the internal convention: a time offset and the GPS week may still be declared
        ov = {k: v for k, v in (overrides or {}).items() if v is not None}
        shift = float(ov.pop("time_offset_s", 0.0))
        week_decl = ov.pop("gps_week", None)
        gps_week = gps_week if gps_week is not None else week_decl
        dec = imu_decl.resolve_declaration(None, {k: v for k, v in ov.items() if k in ("lever_arm_m", "check")})
        imu = imu_decl.read_imu_file(path, ov)
        imu.t, imu.t0 = imu.t + shift, float(imu.t0) + shift
    meta = imu.meta or {}
    if meta.get("time_scale") == "gps":
        return imu, dec
    if "start_tow_s" not in meta:
        raise ConfigError(f"{path}: the IMU stamps are run time; integration needs GPS time: declare "
                          "time_ref = \"gps_tow\" and gps_week (sidecar or --imu-time-ref gps_tow --imu-week)")
    week = meta.get("start_week", gps_week)
    if week is None:
        raise ConfigError(f"{path}: stamps in GPS seconds of week need the GPS week (gps_week in the sidecar, "
                          "--imu-week or --gps-week)")
    start = float(gps_seconds_of_week(int(week), float(meta["start_tow_s"])))
    imu.t = imu.t + start
    imu.t0 = float(imu.t0) + start
    return imu, dec


def _still_specific_force(dv, t, t0, seconds=1.0):
    """Mean specific force (m/s^2, FLU) over the first ``seconds`` of increments."""
    n = max(1, int(np.searchsorted(t, t0 + seconds)))
    return dv[:n].sum(axis=0) / (t[n - 1] - t0)


def read_imu_log(path, fmt=None, declaration_overrides=None, tag=None, gps_week=None, time_offset_s=0.0,
                 mount_deg=None):
    """Read an IMU log in any layout of the module doc -> :class:`ImuData` in GPS time.

    ``fmt``: one of :data:`FORMATS`, or None to recognise it (:func:`detect_format`: the suffix
    .h5/.hdf5 or the HDF5 signature; a ``t_s`` header; a 7-field comma line ending in an integer
    tick; a first field in seconds since 1970; white-space separated seconds of week).
    ``declaration_overrides``: sidecar keys (:mod:`ultratight.ins.imu_decl`) over the log's sidecar
    ``LOG.json``: ``axes`` turns the file's axes into FLU (the text layouts fix kind and units;
    KF-GINS files default to FRD), ``lever_arm_m`` (file axes), ``time_offset_s``, ``gps_week``.
    ``tag``: the RTKLIB time tag of a raw log (default ``LOG.tag``).  ``gps_week``: the week of
    seconds-of-week stamps.  ``time_offset_s``: added to every stamp (on top of a declared one).
    ``mount_deg``: (roll, pitch, yaw) of :func:`mount_matrix`, applied after the axes.
    Problems: one InputFileError / ConfigError line naming the file, line and problem."""
    path = Path(path)
    if not path.is_file():
        raise InputFileError(f"{path}: IMU log not found")
    if fmt is None or fmt == "auto":
        fmt = detect_format(path)
    if fmt not in FORMATS:
        raise ConfigError(f"IMU log format must be one of {', '.join(FORMATS)}, got {fmt!r}")
    if not (isinstance(time_offset_s, (int, float)) and math.isfinite(time_offset_s)):
        raise ConfigError(f"IMU time offset must be a finite number of seconds, got {time_offset_s!r}")
    R = np.eye(3) if mount_deg is None else mount_matrix(*mount_deg)
    if fmt in ("csv", "h5"):
        imu, dec = _read_project_file(path, fmt, declaration_overrides, gps_week)
        meta = dict(imu.meta or {})
        dth, dv, t, t0 = imu.dtheta_b @ R.T, imu.dv_b @ R.T, imu.t + time_offset_s, imu.t0 + time_offset_s
        lever = R @ imu.lever_arm_b
        med = 1.0 / float(imu.rate_hz)
    else:
        ov = dict(declaration_overrides or {})
        if fmt == "kf-gins" and ov.get("axes") is None:
            ov["axes"] = "FRD"
        dec = imu_decl.resolve_declaration(path, ov)
        _check_fixed_units(fmt, dec, path)
        if fmt == "rtklib-raw":
            (base, tr), w, f, meta = read_rtklib_raw(path, tag)
        elif fmt == "sf":
            (base, tr), w, f, meta = read_sf(path)
        else:
            (base, tr), dth_f, dv_f, meta = read_kf_gins(path, gps_week if gps_week is not None else dec.gps_week)
        base = base + dec.time_offset_s + time_offset_s
        line_no = meta.pop("line_no", None)
        _stamps_named(tr, path, line_no, 0.0 if fmt == "kf-gins" else TICK_QUANTUM_S)
        if fmt == "kf-gins":
            med = float(np.median(np.diff(tr)))
            t0r = float(tr[0] - med)
        else:
            t0r, dth_f, dv_f, med = _increments_from_rates(tr, w, f)
        t, t0 = base + tr, base + t0r
        A = R @ dec.M
        dth, dv = dth_f @ A.T, dv_f @ A.T
        lever = R @ dec.lever_arm_b()
    meta.update({"source": str(path), "format": fmt, "time_scale": "gps", "declaration": dec.to_dict(),
                 "declaration_source": dec.source, "time_offset_s": float(time_offset_s),
                 "mount_deg": None if mount_deg is None else [float(x) for x in mount_deg],
                 "f_start_body_frd_mps2": (FRD_FLU @ _still_specific_force(dv, t, t0)).tolist()})
    return ImuData(t=np.asarray(t, float), dtheta_b=dth, dv_b=dv, rate_hz=1.0 / med, t0=float(t0), meta=meta,
                   lever_arm_b=np.asarray(lever, float))


def _stamps_named(t, path, line_no, quantum_s=0.0):
    """Refuse non-finite, repeated or out-of-order GPS stamps and gaps (an interval longer than
    GAP_FACTOR x the median plus the stamp quantum ``quantum_s``), naming the file line."""
    def where(i):
        return f"line {line_no[i]}" if line_no is not None else f"sample {i}"
    bad = np.nonzero(~np.isfinite(t))[0]
    if bad.size:
        raise InputFileError(f"{path}: {where(int(bad[0]))}: time stamp is not a finite number")
    d = np.diff(t)
    nonpos = np.nonzero(d <= 0.0)[0]
    if nonpos.size:
        i = int(nonpos[0]) + 1
        raise InputFileError(f"{path}: {where(i)}: {'repeated' if d[i - 1] == 0 else 'out-of-order'} time stamp "
                             f"{t[i]:.6f} s (previous {t[i - 1]:.6f} s); stamps must increase strictly")
    med = float(np.median(d))
    gaps = np.nonzero(d > GAP_FACTOR * med + quantum_s)[0]
    if gaps.size:
        i = int(gaps[0]) + 1
        raise InputFileError(f"{path}: {where(i)}: gap of {d[i - 1]:.6g} s before it (nominal interval {med:.6g} s); "
                             "split the log or fill the gap")
