"""Trajectories from files: position logs read, checked and smoothed into a C2 spline.

Formats (``[trajectory] kind = "file"``, docs/trajectory-files.md):

* **CSV**, ``frame = "ecef"``: ``t, x, y, z`` (s, m) -- the user-motion format common GPS
  simulators take, with or without a header line (header names ``t``/``t_s``, ``x``/``x_m``,
  ...); ``frame = "llh"``: ``t, lat, lon, h`` (deg, deg, m ellipsoidal; header names ``lat``/
  ``lat_deg``, ``lon``/``lon_deg``, ``h``/``h_m``).  Optional columns ``roll, pitch, yaw``
  (deg, ``roll_deg`` ...: Euler angles of the FLU body w.r.t. the local ENU frame at the
  current position, yaw clockwise from north, the convention of :mod:`ultratight.ins.attitude`).
  Lines starting with ``#`` are comments.
* **NMEA 0183 GGA** (any talker, ``$GPGGA``/``$GNGGA``...): checksums verified, fixes with
  quality 0 skipped, time of day (UTC) relative to the first fix with a midnight roll-over,
  ellipsoidal height = altitude + geoid separation.  The frame is LLH whatever ``frame`` says.

Checks (one-line :class:`ultratight.errors.InputFileError` naming the file and line): numbers
finite, times strictly increasing, at least 4 points, intervals at most 1 s (>= 1 Hz), positions
plausible (|r| between 6.0e6 and 5.0e7 m, latitude within +-90 deg), physics: no speed between two
positions above :data:`MAX_SPEED_MPS` (20 km/s, the limit of ``ultratight ins --init-vel``) and no
acceleration of the smoothed path above :data:`MAX_ACCEL_MPS2` (100 g).

Attitude along the velocity (``attitude = "velocity"``, :func:`held_velocity_attitude`): the
velocity gives the attitude only above ``hold_speed_mps`` (horizontal speed for the yaw); below it
the attitude is held, and the changes between "held" and "along the velocity" are rate- and
acceleration-limited (``slew_rate_dps``, ``slew_accel_dps2``), so a vehicle at rest, or a parked
one whose positions jitter, keeps a steady attitude and bounded, continuous body rates.

Smoothing: each l0 (ENU at the first point) coordinate, and each given Euler angle (yaw
unwrapped), is fitted by the cubic smoothing spline of :func:`scipy.interpolate.make_smoothing_spline`
(knots at the samples, natural end conditions): position, velocity and acceleration are
continuous (C2), jerk is piecewise constant, so the synthesised IMU is physical.  The penalty
``lam`` (s^4) is set from a cut-off frequency ``smoothing_hz`` (default 1 Hz): for sample spacing
``h`` the spline acts on a sampled signal as the low-pass ``1 / (1 + lam h (2 pi f)^4)``, so
``lam = 1 / (h (2 pi f_c)^4)`` puts the half-power point at ``f_c``.  ``smoothing_hz = 0`` gives
the interpolating natural cubic spline (no smoothing).
"""

import math
from pathlib import Path

import numpy as np
from scipy.interpolate import BSpline, make_interp_spline, make_smoothing_spline

from ultratight.errors import InputFileError
from ultratight.io_guard import read_text_input
from ultratight.ins.earth import dcm_ecef_from_enu, ecef_to_llh_batch, llh_to_ecef, llh_to_ecef_batch

FRAMES = ("ecef", "llh")
DEFAULT_SMOOTHING_HZ = 1.0
MAX_INTERVAL_S = 1.0          # >= 1 Hz
MIN_POINTS = 4
R_MIN_M, R_MAX_M = 6.0e6, 5.0e7
MAX_SPEED_MPS = 20000.0       # no vehicle (nor ultratight ins --init-vel) goes faster
MAX_ACCEL_MPS2 = 100.0 * 9.80665
# attitude along the velocity: the hold threshold and the limits of the slews in and out of a hold
DEFAULT_HOLD_SPEED_MPS = 0.5
DEFAULT_SLEW_RATE_DPS = 20.0
DEFAULT_SLEW_ACCEL_DPS2 = 40.0
ATTITUDE_STEP_S = 0.05        # grid of the attitude profile (the file's knots, subdivided)
_SLEW_BANDWIDTH = 1.0         # rad/s: linear region of the slew servo (critically damped, poles -2)

_HEADER_NAMES = {
    "t": ("t", "t_s", "time", "time_s"),
    "x": ("x", "x_m"), "y": ("y", "y_m"), "z": ("z", "z_m"),
    "lat": ("lat", "lat_deg"), "lon": ("lon", "lon_deg"), "h": ("h", "h_m", "height", "height_m"),
    "roll": ("roll", "roll_deg"), "pitch": ("pitch", "pitch_deg"), "yaw": ("yaw", "yaw_deg", "heading_deg"),
}


class PositionLog:
    """Positions read from a file: ``t`` (s, first = 0), ``pos_e`` (n, 3) ECEF m, ``euler`` (n, 3)
    rad [roll, pitch, yaw] or None, ``t_first`` (the file's own first time stamp), ``lines``."""

    def __init__(self, path, t, pos_e, euler, t_first, lines, fmt):
        self.path, self.t, self.pos_e, self.euler = path, t, pos_e, euler
        self.t_first, self.lines, self.format = t_first, lines, fmt


def _err(path, line, msg):
    return InputFileError(f"{path}: line {line}: {msg}" if line else f"{path}: {msg}")


def _read_text(path):
    if not path.is_file():
        raise InputFileError(f"{path}: trajectory file not found")
    return read_text_input(path, "trajectory file")


def _nmea_checksum_ok(s):
    if "*" not in s:
        return True            # checksum is optional in NMEA 0183
    body, cs = s[1:].split("*", 1)
    c = 0
    for ch in body:
        c ^= ord(ch)
    try:
        return int(cs.strip()[:2], 16) == c
    except ValueError:
        return False


def _parse_gga(path, rows):
    t, llh, lines = [], [], []
    day = 0.0
    prev = None
    for ln, s in rows:
        s = s.strip()
        if not s.startswith("$") or s[3:6] != "GGA":
            continue
        if not _nmea_checksum_ok(s):
            raise _err(path, ln, "NMEA checksum mismatch")
        f = s.split("*", 1)[0].split(",")
        if len(f) < 12:
            raise _err(path, ln, f"GGA sentence has {len(f)} fields, expected at least 12")
        if not f[6].strip() or f[6].strip() == "0":
            continue                       # no fix
        try:
            hms = f[1]
            tod = int(hms[0:2]) * 3600.0 + int(hms[2:4]) * 60.0 + float(hms[4:])
            lat = int(f[2][:2]) + float(f[2][2:]) / 60.0
            lon = int(f[4][:3]) + float(f[4][3:]) / 60.0
            alt = float(f[9])
            sep = float(f[11]) if f[11].strip() else 0.0
        except (ValueError, IndexError):
            raise _err(path, ln, "unreadable GGA time, latitude, longitude or altitude") from None
        if f[3] not in ("N", "S") or f[5] not in ("E", "W"):
            raise _err(path, ln, f"GGA hemisphere must be N/S and E/W, got {f[3]!r} {f[5]!r}")
        lat = -lat if f[3] == "S" else lat
        lon = -lon if f[5] == "W" else lon
        if prev is not None and tod + day < prev - 43200.0:
            day += 86400.0                 # midnight roll-over
        prev = tod + day
        t.append(tod + day)
        llh.append((lat, lon, alt + sep))
        lines.append(ln)
    if not t:
        raise InputFileError(f"{path}: no GGA sentence with a fix")
    return np.array(t), np.array(llh), None, np.array(lines)


def _parse_csv(path, rows, frame):
    first_ln, first = rows[0]
    cells = [c.strip().lower() for c in first.split(",")]

    def is_num(c):
        try:
            float(c)
            return True
        except ValueError:
            return False

    names = ("t", "x", "y", "z") if frame == "ecef" else ("t", "lat", "lon", "h")
    if all(is_num(c) for c in cells):
        idx = {k: i for i, k in enumerate(names)}
        if len(cells) >= 7:
            idx.update(roll=4, pitch=5, yaw=6)
        ncol = len(cells)
        data_rows = rows
    else:
        idx = {}
        for key, alts in _HEADER_NAMES.items():
            hit = [i for i, c in enumerate(cells) if c in alts]
            if hit:
                idx[key] = hit[0]
        miss = [k for k in names if k not in idx]
        if miss:
            raise _err(path, first_ln, f"header for frame = \"{frame}\" needs columns {', '.join(names)}; "
                       f"missing {', '.join(miss)} (got {', '.join(cells)})")
        att = [k for k in ("roll", "pitch", "yaw") if k in idx]
        if att and len(att) != 3:
            raise _err(path, first_ln, "attitude columns must be all three of roll, pitch, yaw (deg)")
        ncol = len(cells)
        data_rows = rows[1:]
    cols = list(names) + ([k for k in ("roll", "pitch", "yaw")] if "roll" in idx else [])
    vals = np.empty((len(data_rows), len(cols)))
    lines = np.empty(len(data_rows), dtype=int)
    for r, (ln, s) in enumerate(data_rows):
        f = s.split(",")
        if len(f) != ncol:
            raise _err(path, ln, f"{len(f)} fields, expected {ncol}")
        for j, k in enumerate(cols):
            c = f[idx[k]].strip()
            try:
                v = float(c)
            except ValueError:
                raise _err(path, ln, f"column {k}: {c!r} is not a number") from None
            if not math.isfinite(v):
                raise _err(path, ln, f"column {k} is {c} (NaN/inf not allowed)")
            vals[r, j] = v
        lines[r] = ln
    t = vals[:, 0]
    pos = vals[:, 1:4]
    euler = np.radians(vals[:, 4:7]) if len(cols) == 7 else None
    return t, pos, euler, lines


def read_position_log(path, frame="ecef"):
    """Read a trajectory file (module doc) -> :class:`PositionLog`.  InputFileError naming the line."""
    path = Path(path)
    if frame not in FRAMES:
        raise InputFileError(f"{path}: trajectory frame must be one of {', '.join(FRAMES)}, got {frame!r}")
    text = _read_text(path)
    rows = [(i + 1, ln) for i, ln in enumerate(text.splitlines())
            if ln.strip() and not ln.lstrip().startswith("#")]
    if not rows:
        raise InputFileError(f"{path}: empty trajectory file")
    if rows[0][1].lstrip().startswith("$"):
        t, coords, euler, lines = _parse_gga(path, rows)
        frame, fmt = "llh", "nmea-gga"
    else:
        t, coords, euler, lines = _parse_csv(path, rows, frame)
        fmt = f"csv-{frame}"
    if t.size < MIN_POINTS:
        raise InputFileError(f"{path}: {t.size} positions; a trajectory file needs at least {MIN_POINTS}")
    d = np.diff(t)
    bad = np.flatnonzero(d <= 0.0)
    if bad.size:
        i = int(bad[0]) + 1
        raise _err(path, lines[i], f"time {t[i]:.9g} s does not increase (previous {t[i - 1]:.9g} s)")
    gap = np.flatnonzero(d > MAX_INTERVAL_S + 1e-9)
    if gap.size:
        i = int(gap[0]) + 1
        raise _err(path, lines[i], f"interval of {d[i - 1]:.6g} s before t = {t[i]:.9g} s; positions must come "
                   f"at least once per {MAX_INTERVAL_S:g} s (>= 1 Hz)")
    if frame == "llh":
        badlat = np.flatnonzero(np.abs(coords[:, 0]) > 90.0)
        if badlat.size:
            i = int(badlat[0])
            raise _err(path, lines[i], f"latitude {coords[i, 0]} deg outside [-90, 90]")
        llh = coords.copy()
        llh[:, :2] = np.radians(llh[:, :2])
        pos_e = llh_to_ecef_batch(llh)
    else:
        pos_e = coords
    r = np.linalg.norm(pos_e, axis=1)
    badr = np.flatnonzero((r < R_MIN_M) | (r > R_MAX_M))
    if badr.size:
        i = int(badr[0])
        raise _err(path, lines[i], f"position {pos_e[i].tolist()} m is {r[i] / 1e3:.1f} km from the Earth's "
                   f"centre (expected {R_MIN_M / 1e3:.0f}..{R_MAX_M / 1e3:.0f} km: wrong frame or units?)")
    pos_e = np.asarray(pos_e, float)
    speed = np.linalg.norm(np.diff(pos_e, axis=0), axis=1) / d
    fast = np.flatnonzero(speed > MAX_SPEED_MPS)
    if fast.size:
        i = int(fast[0]) + 1
        raise _err(path, lines[i], f"speed {speed[i - 1]:.6g} m/s from t = {t[i - 1]:.9g} s to t = {t[i]:.9g} s is "
                   f"above {MAX_SPEED_MPS:g} m/s (no vehicle moves that fast: a jump in the positions?)")
    return PositionLog(path, t - t[0], pos_e, euler, float(t[0]), lines, fmt)


def smoothing_lam(t, smoothing_hz):
    """Penalty of the cubic smoothing spline for the cut-off ``smoothing_hz`` (module doc); 0 -> None
    (interpolating spline)."""
    if smoothing_hz == 0.0:
        return None
    h = float(np.median(np.diff(t)))
    return 1.0 / (h * (2.0 * math.pi * float(smoothing_hz)) ** 4)


def fit_spline(t, y, lam):
    """Cubic C2 spline of the columns of ``y`` against ``t``: smoothing (``lam``) or interpolating."""
    if lam is None:
        return make_interp_spline(t, y, k=3, bc_type="natural")
    # one spline per column (same knots), coefficients stacked into one vector-valued BSpline
    parts = [make_smoothing_spline(t, y[:, j], lam=lam) for j in range(y.shape[1])]
    c = np.stack([p.c for p in parts], axis=1)
    return BSpline(parts[0].t, c, 3, extrapolate=False)


class FileMotion:
    """Smoothed motion of a :class:`PositionLog` in the start tangent frame l0 (ENU at the first
    point): ``motion(t)`` -> p, v, a, j (n, 3) each; ``euler(t)`` -> Euler angles and their rates
    (or None when the file gives no attitude)."""

    def __init__(self, log, smoothing_hz=DEFAULT_SMOOTHING_HZ):
        self.log = log
        self.smoothing_hz = float(smoothing_hz)
        llh0 = ecef_to_llh_batch(log.pos_e[:1])[0]
        self.lat0, self.lon0, self.h0 = (float(v) for v in llh0)
        self.r0_e = np.asarray(llh_to_ecef(self.lat0, self.lon0, self.h0))
        self.C_el0 = dcm_ecef_from_enu(self.lat0, self.lon0)
        p = (log.pos_e - self.r0_e) @ self.C_el0
        self.lam = smoothing_lam(log.t, self.smoothing_hz)
        self.pos = fit_spline(log.t, p, self.lam)
        self.derivs = [self.pos.derivative(k) for k in (1, 2, 3)]
        self.att = None
        if log.euler is not None:
            e = log.euler.copy()
            e[:, 2] = np.unwrap(e[:, 2])
            self.att = fit_spline(log.t, e, self.lam)
            self.att_rate = self.att.derivative(1)
        self.duration_s = float(log.t[-1])
        self.knots = np.asarray(log.t, float)
        self._check_acceleration()

    def _check_acceleration(self):
        """InputFileError when the smoothed path accelerates beyond :data:`MAX_ACCEL_MPS2` (at the
        knots and half-way between them, where a cubic's acceleration peaks are caught)."""
        k = self.knots
        tq = np.sort(np.concatenate([k, 0.5 * (k[1:] + k[:-1])]))
        acc = np.linalg.norm(self.derivs[1](tq), axis=1)
        bad = np.flatnonzero(acc > MAX_ACCEL_MPS2)
        if bad.size:
            i = int(bad[0])
            j = int(np.argmin(np.abs(k - tq[i])))
            raise _err(self.log.path, self.log.lines[j],
                       f"acceleration {acc[i]:.6g} m/s^2 ({acc[i] / 9.80665:.4g} g) of the smoothed path at t = "
                       f"{tq[i]:.6g} s is above {MAX_ACCEL_MPS2 / 9.80665:g} g (no vehicle accelerates so hard)")

    def motion(self, t):
        t = np.clip(np.atleast_1d(np.asarray(t, float)), 0.0, self.duration_s)
        return self.pos(t), self.derivs[0](t), self.derivs[1](t), self.derivs[2](t)

    def euler(self, t):
        t = np.clip(np.atleast_1d(np.asarray(t, float)), 0.0, self.duration_s)
        return self.att(t), self.att_rate(t)


def velocity_euler(v, a):
    """Euler angles [0, pitch, yaw] (rad) of the direction of ``v`` (l0, (n, 3)) and their rates with
    ``a`` = dv/dt, plus the speed and the horizontal speed (n,).  Undefined directions give 0."""
    vh = np.hypot(v[:, 0], v[:, 1])
    speed = np.linalg.norm(v, axis=1)
    vh_s = np.where(vh > 0.0, vh, 1.0)
    sp_s = np.where(speed > 0.0, speed, 1.0)
    e = np.zeros_like(v)
    de = np.zeros_like(v)
    e[:, 1] = np.arctan2(v[:, 2], vh)
    e[:, 2] = np.arctan2(v[:, 0], v[:, 1])
    vh_dot = np.where(vh > 0.0, (v[:, 0] * a[:, 0] + v[:, 1] * a[:, 1]) / vh_s, 0.0)
    de[:, 1] = np.where(speed > 0.0, (vh * a[:, 2] - v[:, 2] * vh_dot) / sp_s ** 2, 0.0)
    de[:, 2] = np.where(vh > 0.0, (v[:, 1] * a[:, 0] - v[:, 0] * a[:, 1]) / vh_s ** 2, 0.0)
    return e, de, speed, vh


def attitude_grid(knots, step=ATTITUDE_STEP_S):
    """The knots with every interval longer than ``step`` cut into equal parts no longer than it."""
    d = np.diff(knots)
    m = np.maximum(1, np.ceil(d / step - 1e-9).astype(int))
    i = np.repeat(np.arange(d.size), m)
    j = np.arange(i.size) - np.repeat(np.cumsum(m) - m, m)
    return np.append(knots[:-1][i] + d[i] * j / m[i], knots[-1])


def _slew(t, tgt, dtgt, moving, hold0, wrap, rate, acc):
    """One Euler angle along ``t``: the target ``tgt`` (rate ``dtgt``) where ``moving``, else the
    held value (``hold0`` before the first motion, then the angle at the last stop).  The angle is
    target + c; c jumps at a switch so that angle and rate stay continuous, then returns to 0 with
    |dc/dt| <= max(rate, its value at the switch) and |d2c/dt2| <= acc.  Returns angle and rate."""
    n = t.size
    E, dE = np.empty(n), np.empty(n)
    k_gain = 4.0 * _SLEW_BANDWIDTH
    mov = bool(moving[0])
    h, off = float(hold0), 0.0
    if mov and wrap:
        off = 2.0 * math.pi * round((h - tgt[0]) / (2.0 * math.pi))
    T, dT = (tgt[0] + off, dtgt[0]) if mov else (h, 0.0)
    c = dc = 0.0
    E[0], dE[0] = T, dT
    for k in range(n - 1):
        if c != 0.0 or dc != 0.0:
            dt = t[k + 1] - t[k]
            want = min(max(-_SLEW_BANDWIDTH * c, -rate), rate)
            dc += min(max(k_gain * (want - dc), -acc), acc) * dt
            c += dc * dt
            if abs(c) < 1e-12 and abs(dc) < 1e-12:
                c = dc = 0.0
        if mov:
            Tn = tgt[k + 1] + off
            if wrap and abs(Tn - T) > math.pi:
                off += 2.0 * math.pi * round((T - Tn) / (2.0 * math.pi))
                Tn = tgt[k + 1] + off
            T, dT = Tn, dtgt[k + 1]
        if bool(moving[k + 1]) != mov:
            En, dEn = T + c, dT + dc
            mov = not mov
            if mov:
                off = 2.0 * math.pi * round((En - tgt[k + 1]) / (2.0 * math.pi)) if wrap else 0.0
                T, dT = tgt[k + 1] + off, dtgt[k + 1]
            else:
                h = En
                T, dT = h, 0.0
            c, dc = En - T, dEn - dT
        E[k + 1], dE[k + 1] = T + c, dT + dc
    return E, dE


def held_velocity_attitude(fm, att0=None, hold_speed=DEFAULT_HOLD_SPEED_MPS, slew_rate_dps=DEFAULT_SLEW_RATE_DPS,
                           slew_accel_dps2=DEFAULT_SLEW_ACCEL_DPS2):
    """Euler angles [roll, pitch, yaw] w.r.t. l0 of a :class:`FileMotion` "along the velocity" with
    holds at rest (module doc), as a C2 cubic spline on :func:`attitude_grid` of the file's knots.

    Pitch and roll follow the velocity above ``hold_speed`` (m/s), yaw above ``hold_speed`` of
    horizontal speed (a vertical climb keeps its yaw); roll is 0 along the velocity.  Before the
    first motion the angles are ``att0`` (rad) when given, else those of the first motion.
    Returns the spline (its ``derivative()`` gives the rates) and the grid."""
    grid = attitude_grid(fm.knots)
    _, v, a, _ = fm.motion(grid)
    tgt, dtgt, speed, vh = velocity_euler(v, a)
    moving = np.stack([speed > hold_speed, speed > hold_speed, vh > hold_speed], axis=1)
    rate, acc = math.radians(slew_rate_dps), math.radians(slew_accel_dps2)
    E, dE = np.empty_like(tgt), np.empty_like(tgt)
    for j in range(3):
        if att0 is not None:
            h0 = float(att0[j])
        else:
            first = np.flatnonzero(moving[:, j])
            h0 = float(tgt[first[0], j]) if first.size else 0.0
        E[:, j], dE[:, j] = _slew(grid, tgt[:, j], dtgt[:, j], moving[:, j], h0, j == 2, rate, acc)
    spline = make_interp_spline(grid, E, k=3, bc_type=([(1, dE[0])], [(1, dE[-1])]))
    return spline, grid
