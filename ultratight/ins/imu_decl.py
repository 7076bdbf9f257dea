"""IMU declaration: how a user's IMU CSV is to be read (kind, axes, units, rate, time, lever arm),
applied on read so that the rest of the project sees its one internal convention (increments
``dtheta_b`` rad / ``dv_b`` m/s, body frame FLU, time in seconds since the IF start, lever arm
IMU -> antenna in FLU metres), and a stationary sanity check of the declaration.

The declaration comes from a JSON sidecar beside the IMU file (``IMU.csv`` -> ``IMU.csv.json``,
layout in docs/imu-declaration.md) and/or from CLI flags (``--imu-axes`` ... of ``process --mode
ultratight`` and ``ins``), which override the sidecar key by key::

    {"format": "ultratight-imu-sidecar", "version": 1,
     "kind": "rates",              # "rates" (averages over the interval ending at t) | "increments"
     "axes": "FRD",                # the file's x, y, z axes: three of F/B, L/R, U/D (a right-handed
                                   # set), or a 3x3 matrix M with v_FLU = M v_file (a proper rotation)
     "gyro_unit": "deg/s",         # rates: rad/s | deg/s; increments: rad | deg
     "accel_unit": "m/s^2",        # rates: m/s^2 | g; increments: m/s
     "rate_hz": 100.0,             # checked against the stamps (1 %)
     "time_ref": "run",            # "run": seconds since the first IF sample | "gps_tow": GPS seconds of week
     "gps_week": 2190,             # with "gps_tow" (optional)
     "time_offset_s": 0.0,         # added to every stamp (the IMU clock's offset to the declared reference)
     "lever_arm_m": [0.0, 0.0, 0.0],  # IMU -> antenna, in the file's (declared) axes, m
     "check": true,                # run the stationary sanity check
     "noise": {"grade": "mems",    # the declared noise (optional): a grade of ultratight.ins.imu_noise
               "gyro_noise_dps_rthz": 0.0038}}   # and/or its datasheet keys (they replace the grade's)

The noise declaration (:func:`resolve_noise`) is resolved as CLI flags over the sidecar's ``noise``
table over the grade (the flag's grade over the sidecar's).

Column units in the CSV header (``gx_dps`` ...) still work; a header without unit suffixes
(``gx, gy, gz, ax, ay, az`` or ``dthx ... dvz``) takes the declared units; both given and in
conflict is an error.  Without a sidecar or flags the declaration is the internal convention
(FLU, run time, zero lever arm) with the header's units.

**Stationary sanity check** (:func:`stationary_check`): the first 1-s window in which every
accelerometer axis varies by less than 1 % of the mean specific-force magnitude and that
magnitude is within 5 % of gravity under one of the readings (m/s^2, g, per-sample
increments) counts as still (a steady turn or a steady acceleration can pass for still: the
checks below are built to accept those when the declaration is right).  There:

* the declared reading must give ``|f|`` within 5 % of 9.80665 m/s^2, else "accelerometer
  units look g, declared m/s^2" or "values look like increments, declared rates";
* the specific force at rest points up: when the file axis carrying most of it is declared
  vertical (U or D), its reading must say so (U positive, D negative), else "axes look FLU,
  declared FRD" (the most common right-handed convention with the right vertical letter is
  named) — the declaration would put the body upside down, the sign of a FLU/FRD mix-up.  An
  axis declared horizontal that carries gravity is a body standing on end (a rocket on its pad,
  a handheld unit held upright): accepted, and the report says ``stands_on_end``;
* ``|omega|`` outside [1/20, 40] Earth rates as declared while the other gyro unit puts it
  within [0.2, 5] Earth rates (a tactical or better gyro at rest) gives "gyro units look deg/s,
  declared rad/s".

A record that never stands still is not checked (the report says so).  Limits: a swap of the
two horizontal axes (FLU vs RFU) leaves gravity where it is and is not detected; a gyro whose
bias exceeds ~40 Earth rates is only refused when the other unit fits.
"""

import difflib
import itertools
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ultratight.constants import OMEGA_E
from ultratight.errors import ConfigError, InputFileError
from ultratight.ins.imu_noise import ALL_KEYS, GRADES, OPTIONAL_KEYS, imu_noise

SIDECAR_FORMAT = "ultratight-imu-sidecar"
SIDECAR_VERSION = 1
G0 = 9.80665
KINDS = ("rates", "increments")
TIME_REFS = ("run", "gps_tow")
LETTERS = {"F": (1.0, 0.0, 0.0), "B": (-1.0, 0.0, 0.0), "L": (0.0, 1.0, 0.0), "R": (0.0, -1.0, 0.0),
           "U": (0.0, 0.0, 1.0), "D": (0.0, 0.0, -1.0)}
# unit name -> (factor to SI, kind)
GYRO_UNITS = {"rad/s": (1.0, "rates"), "deg/s": (math.pi / 180.0, "rates"),
              "rad": (1.0, "increments"), "deg": (math.pi / 180.0, "increments")}
ACCEL_UNITS = {"m/s^2": (1.0, "rates"), "g": (G0, "rates"), "m/s": (1.0, "increments")}
_UNIT_ALIASES = {"m/s2": "m/s^2", "m/s²": "m/s^2", "mps2": "m/s^2", "dps": "deg/s", "radps": "rad/s",
                 "mps": "m/s"}
KEYS = ("format", "version", "kind", "axes", "gyro_unit", "accel_unit", "rate_hz", "time_ref", "gps_week",
        "time_offset_s", "lever_arm_m", "check", "noise")
NOISE_KEYS = ("grade",) + tuple(ALL_KEYS)
# preference when naming the likely axes (most common first)
COMMON_AXES = ("FLU", "FRD", "RFU", "LFD", "RBD", "BRU", "LBU", "BLD")
STILL_WINDOW_S = 1.0
STILL_REL_STD = 0.01
G_TOL = 0.05
W_LO, W_HI = 1.0 / 20.0, 40.0      # |omega| at rest accepted, in Earth rates
W_FIT = (0.2, 5.0)                  # the other gyro unit "fits" when it puts |omega| here


@dataclass
class ImuDeclaration:
    """A resolved declaration (see module doc).  ``lever_arm_m`` is in the declared (file) axes."""
    kind: str | None = None
    axes: object = "FLU"
    gyro_unit: str | None = None
    accel_unit: str | None = None
    rate_hz: float | None = None
    time_ref: str = "run"
    gps_week: int | None = None
    time_offset_s: float = 0.0
    lever_arm_m: np.ndarray = field(default_factory=lambda: np.zeros(3))
    check: bool = True
    source: str = "default"
    noise: dict | None = None         # the sidecar's noise table (grade and datasheet keys), as given

    @property
    def M(self):
        """v_FLU = M @ v_file."""
        return axes_matrix(self.axes)

    def lever_arm_b(self):
        """Lever arm IMU -> antenna in the internal body frame FLU (m)."""
        return self.M @ np.asarray(self.lever_arm_m, float)

    def to_dict(self):
        ax = self.axes if isinstance(self.axes, str) else np.asarray(self.axes, float).tolist()
        return {"format": SIDECAR_FORMAT, "version": SIDECAR_VERSION, "kind": self.kind, "axes": ax,
                "gyro_unit": self.gyro_unit, "accel_unit": self.accel_unit, "rate_hz": self.rate_hz,
                "time_ref": self.time_ref, "gps_week": self.gps_week, "time_offset_s": self.time_offset_s,
                "lever_arm_m": np.asarray(self.lever_arm_m, float).tolist(), "check": self.check,
                **({"noise": dict(self.noise)} if self.noise is not None else {})}


def axes_matrix(axes):
    """M (3, 3) with v_FLU = M v_file for ``axes`` = three letters of F/B, L/R, U/D or a 3x3 matrix
    (ConfigError when not a proper rotation)."""
    if isinstance(axes, str):
        a = axes.strip().upper()
        if len(a) != 3 or any(c not in LETTERS for c in a):
            raise ConfigError(f"IMU axes {axes!r}: expected three letters of F/B, L/R, U/D (e.g. FLU, FRD, RFU)")
        M = np.array([LETTERS[c] for c in a]).T
        if abs(np.linalg.det(M) - 1.0) > 1e-9:
            raise ConfigError(f"IMU axes {axes!r}: not a right-handed set (each of F/B, L/R, U/D once, "
                              "right-handed: e.g. FLU, FRD, RFU)")
        return M
    try:
        M = np.asarray(axes, dtype=float)
    except (TypeError, ValueError):
        raise ConfigError(f"IMU axes {axes!r}: expected three letters or a 3x3 matrix") from None
    if M.shape != (3, 3) or not np.all(np.isfinite(M)):
        raise ConfigError(f"IMU axes: a matrix must be 3x3 and finite, got shape {M.shape}")
    if np.max(np.abs(M @ M.T - np.eye(3))) > 1e-6 or np.linalg.det(M) < 0:
        raise ConfigError("IMU axes: the matrix must be a proper rotation (orthonormal, determinant +1)")
    return M


def _norm_unit(u, table, what):
    if u is None:
        return None
    s = str(u).strip()
    s = _UNIT_ALIASES.get(s.lower(), _UNIT_ALIASES.get(s, s))
    if s not in table:
        raise ConfigError(f"IMU {what} unit {u!r}: expected one of {', '.join(table)}")
    return s


def sidecar_path(imu_path):
    """The IMU sidecar of ``imu_path``: the same name plus ``.json``."""
    p = Path(imu_path)
    return p.with_name(p.name + ".json")


def read_sidecar(path):
    """The raw dict of an IMU sidecar (InputFileError on unreadable JSON / unknown keys)."""
    path = Path(path)
    try:
        d = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError) as exc:
        raise InputFileError(f"{path}: cannot read IMU sidecar ({exc})") from None
    except ValueError as exc:
        raise InputFileError(f"{path}: IMU sidecar is not valid JSON ({exc})") from None
    if not isinstance(d, dict):
        raise InputFileError(f"{path}: IMU sidecar must be a JSON object")
    for k in d:
        if k not in KEYS:
            near = difflib.get_close_matches(k, KEYS, n=1)
            hint = f" (did you mean {near[0]!r}?)" if near else f"; known: {', '.join(KEYS)}"
            raise InputFileError(f"{path}: unknown IMU sidecar key {k!r}{hint}")
    if d.get("format", SIDECAR_FORMAT) != SIDECAR_FORMAT:
        raise InputFileError(f"{path}: format {d.get('format')!r}, expected {SIDECAR_FORMAT!r}")
    return d


def resolve_declaration(imu_path=None, overrides=None):
    """The declaration of ``imu_path``: its sidecar (when present) with ``overrides`` (a dict of
    sidecar keys, ``None`` values ignored) on top.  ConfigError naming the key on bad values."""
    raw, srcs = {}, []
    if imu_path is not None:
        sp = sidecar_path(imu_path)
        if sp.is_file():
            raw.update(read_sidecar(sp))
            srcs.append(str(sp))
    ov = {k: v for k, v in (overrides or {}).items() if v is not None}
    for k in ov:
        if k not in KEYS:
            raise ConfigError(f"IMU declaration: unknown key {k!r}")
    if ov:
        srcs.append("flags")
    raw.update(ov)
    where = " + ".join(srcs) or "default"
    try:
        return _declaration_from_dict(raw, where)
    except ConfigError as exc:
        raise ConfigError(f"{where}: {exc}") from None


def _declaration_from_dict(d, where):
    dec = ImuDeclaration(source=where)
    kind = d.get("kind")
    if kind is not None and kind not in KINDS:
        raise ConfigError(f"kind must be one of {', '.join(KINDS)}, got {kind!r}")
    dec.kind = kind
    dec.axes = d.get("axes", "FLU")
    axes_matrix(dec.axes)
    if isinstance(dec.axes, str):
        dec.axes = dec.axes.strip().upper()
    dec.gyro_unit = _norm_unit(d.get("gyro_unit"), GYRO_UNITS, "gyro")
    dec.accel_unit = _norm_unit(d.get("accel_unit"), ACCEL_UNITS, "accelerometer")
    for name, u, table in (("gyro_unit", dec.gyro_unit, GYRO_UNITS), ("accel_unit", dec.accel_unit, ACCEL_UNITS)):
        if u is not None and kind is not None and table[u][1] != kind:
            raise ConfigError(f"{name} {u!r} is a unit of {table[u][1]}, but kind = {kind!r}")
    if dec.gyro_unit and dec.accel_unit and GYRO_UNITS[dec.gyro_unit][1] != ACCEL_UNITS[dec.accel_unit][1]:
        raise ConfigError(f"gyro_unit {dec.gyro_unit!r} and accel_unit {dec.accel_unit!r} are of different kinds")
    if d.get("rate_hz") is not None:
        r = _number(d["rate_hz"], "rate_hz")
        if not r > 0:
            raise ConfigError(f"rate_hz must be > 0, got {r}")
        dec.rate_hz = r
    dec.time_ref = d.get("time_ref", "run")
    if dec.time_ref not in TIME_REFS:
        raise ConfigError(f"time_ref must be one of {', '.join(TIME_REFS)}, got {dec.time_ref!r}")
    if d.get("gps_week") is not None:
        w = d["gps_week"]
        if isinstance(w, bool) or not isinstance(w, int) or w < 0:
            raise ConfigError(f"gps_week must be an integer >= 0, got {w!r}")
        dec.gps_week = w
    dec.time_offset_s = _number(d.get("time_offset_s", 0.0), "time_offset_s")
    la = d.get("lever_arm_m", [0.0, 0.0, 0.0])
    try:
        la = np.asarray(la, dtype=float)
    except (TypeError, ValueError):
        raise ConfigError(f"lever_arm_m must be a list of 3 numbers (m), got {la!r}") from None
    if la.shape != (3,) or not np.all(np.isfinite(la)) or np.max(np.abs(la)) > 1e3:
        raise ConfigError(f"lever_arm_m must be 3 finite numbers of at most 1000 m, got {d.get('lever_arm_m')!r}")
    dec.lever_arm_m = la
    chk = d.get("check", True)
    if not isinstance(chk, bool):
        raise ConfigError(f"check must be true or false, got {chk!r}")
    dec.check = chk
    if d.get("noise") is not None:
        dec.noise = _noise_table(d["noise"])
    return dec


def _noise_table(nz):
    """The sidecar's ``noise`` table checked key by key (ConfigError naming the key)."""
    if not isinstance(nz, dict):
        raise ConfigError(f"noise must be a table of {', '.join(NOISE_KEYS)}, got {nz!r}")
    for k, v in nz.items():
        if k not in NOISE_KEYS:
            near = difflib.get_close_matches(k, NOISE_KEYS, n=1)
            raise ConfigError(f"noise: unknown key {k!r}" + (f" (did you mean {near[0]!r}?)" if near else
                                                             f"; known: {', '.join(NOISE_KEYS)}"))
        if k == "grade":
            if v not in GRADES:
                raise ConfigError(f"noise grade must be one of {', '.join(GRADES)}, got {v!r}")
        elif isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0 or (
                v == 0 and k not in OPTIONAL_KEYS):
            raise ConfigError(f"noise {k} must be a {'non-negative' if k in OPTIONAL_KEYS else 'positive'} number, "
                              f"got {v!r}")
    return dict(nz)


def resolve_noise(declaration=None, grade=None, **flags):
    """The declared :class:`ultratight.ins.imu_noise.ImuNoise`: the datasheet values of ``flags``
    (keys of ``ALL_KEYS``, None = not given) over the ``noise`` table of ``declaration``
    (an :class:`ImuDeclaration` or None) over the grade (``grade``, else the table's).  ConfigError
    when a value is missing and no grade is given."""
    table = dict((declaration.noise or {}) if declaration is not None else {})
    g = grade if grade is not None else table.pop("grade", None)
    table.pop("grade", None)
    table.update({k: v for k, v in flags.items() if v is not None})
    return imu_noise(g, **table)


def _number(v, name):
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise ConfigError(f"{name} must be a finite number, got {v!r}")
    return float(v)


def write_sidecar(path, dec):
    """Write ``dec`` as the sidecar of the IMU file ``path`` (returns the sidecar path)."""
    from ultratight.io_guard import atomic_path
    sp = sidecar_path(path)
    with atomic_path(sp) as tmp:
        Path(tmp).write_text(json.dumps(dec.to_dict(), indent=2) + "\n")
    return sp


# ------------------------------------------------------------------ applying it
def units_for(dec, header_kind, header_gyro, header_accel, path):
    """(gyro factor, accel factor, kind) from the header's unit suffixes and the declaration
    (InputFileError when they conflict or when neither gives a unit)."""
    kind = header_kind
    if dec.kind is not None and dec.kind != kind:
        raise InputFileError(f"{path}: declared kind {dec.kind!r} ({dec.source}) but the columns hold {kind}")
    out = []
    for what, hdr, decl, table in (("gyro", header_gyro, dec.gyro_unit, GYRO_UNITS),
                                   ("accelerometer", header_accel, dec.accel_unit, ACCEL_UNITS)):
        if hdr is not None and decl is not None and hdr != decl:
            raise InputFileError(f"{path}: {what} unit {hdr!r} in the header but {decl!r} declared ({dec.source})")
        u = hdr or decl
        if u is None:
            raise InputFileError(f"{path}: no {what} unit: give a column suffix or declare {what.split()[0][:5]}"
                                 f"_unit in the sidecar / flags")
        if table[u][1] != kind:
            raise InputFileError(f"{path}: {what} unit {u!r} is a unit of {table[u][1]}, the columns hold {kind}")
        out.append(u)
    return out[0], out[1], kind


def _still_window(f_raw, n_win, scales):
    """Index range [a, b) of the first still window of the raw accelerometer columns (module doc):
    every axis varies by less than 1 % of the mean magnitude, which is within 5 % of gravity
    under one of the readings ``scales`` (raw -> m/s^2); None when there is none."""
    n = f_raw.shape[0]
    for s in range(0, n - n_win + 1, max(1, n_win // 2)):
        w = f_raw[s:s + n_win]
        m = float(np.linalg.norm(w.mean(axis=0)))
        if m <= 0.0 or np.max(w.std(axis=0)) > STILL_REL_STD * m:
            continue
        if any(abs(m * sc / G0 - 1.0) < G_TOL for sc in scales):
            return s, s + n_win
    return None


def stationary_check(f_raw, w_raw, dt, dec, accel_unit, gyro_unit, kind, path):
    """The sanity check of the module doc on the raw (file-unit, file-axes) columns.  Returns a
    report dict; raises InputFileError naming the likely mistake."""
    n_win = max(2, int(round(STILL_WINDOW_S / dt)))
    # every reading of the accelerometer column: (kind, unit, factor raw -> specific force m/s^2)
    readings = [("rates", "m/s^2", 1.0), ("rates", "g", G0), ("increments", "m/s", 1.0 / dt)]
    win = _still_window(f_raw, n_win, [r[2] for r in readings]) if f_raw.shape[0] >= n_win else None
    if win is None:
        return {"checked": False, "reason": "the record never stands still for 1 s: sanity check skipped"}
    a, b = win
    fm = f_raw[a:b].mean(axis=0)
    wm = w_raw[a:b].mean(axis=0)
    mraw = float(np.linalg.norm(fm))
    t_txt = f"still at samples {a}..{b - 1}"
    decl = next(r for r in readings if r[0] == kind and r[1] == accel_unit)
    fits = [r for r in readings if abs(mraw * r[2] / G0 - 1.0) < G_TOL]
    if decl not in fits:
        if fits:
            k2, u2, _ = fits[0]
            if k2 != kind and _earth_rate_fits(wm, dt, gyro_unit, kind) and not _earth_rate_fits(wm, dt, gyro_unit, k2):
                # the gyro reads the Earth rate as declared and not as the other kind: this is a steady
                # specific force of a moving vehicle that happens to read 1 g as the other kind
                return {"checked": False, "reason": f"steady specific force |f| = {mraw * decl[2]:.4g} m/s^2 "
                        f"with no rotation ({t_txt}): not at rest, sanity check skipped"}
            if k2 != kind:
                raise InputFileError(f"{path}: values look like {k2}, declared {kind} ({t_txt}: |f| = "
                                     f"{mraw * decl[2]:.4g} m/s^2 as declared, {mraw * fits[0][2]:.4g} as {k2})")
            raise InputFileError(f"{path}: accelerometer units look {u2}, declared {accel_unit} ({t_txt}: |f| = "
                                 f"{mraw * decl[2]:.4g} m/s^2 as declared)")
        raise InputFileError(f"{path}: at rest ({t_txt}) |f| = {mraw * decl[2]:.4g} m/s^2 is not gravity under any "
                             "accelerometer unit; check the columns")
    # axes: specific force at rest points up
    i = int(np.argmax(np.abs(fm)))
    up_letter = "U" if fm[i] > 0 else "D"
    on_end = bool(abs(fm[i]) > 0.7 * mraw and isinstance(dec.axes, str) and dec.axes[i] not in "UD")
    if abs(fm[i]) > 0.7 * mraw and isinstance(dec.axes, str) and dec.axes[i] in "UD" and dec.axes[i] != up_letter:
        cands = [c for c in _proper_axes() if c[i] == up_letter]
        pref = {c: k for k, c in enumerate(COMMON_AXES)}
        cands.sort(key=lambda c: (pref.get(c, 99), -sum(x == y for x, y in zip(c, dec.axes)), c))
        raise InputFileError(f"{path}: axes look {cands[0]}, declared {dec.axes} (at rest the file's "
                             f"{'xyz'[i]} axis reads {fm[i] * decl[2]:+.3g} m/s^2: it points "
                             f"{'up' if up_letter == 'U' else 'down'})")
    if not isinstance(dec.axes, str):
        up = dec.M @ fm
        if up[2] < -0.7 * mraw:
            raise InputFileError(f"{path}: declared axes matrix puts the specific force at rest at "
                                 f"{(up / mraw).round(3).tolist()} (FLU), not up")
        on_end = bool(abs(up[2]) < 0.7 * mraw)
    # gyro: |omega| against the Earth rate, when the other unit fits better
    gfac = GYRO_UNITS[gyro_unit][0] / (dt if kind == "increments" else 1.0)
    w_decl = float(np.linalg.norm(wm)) * gfac
    ratio = w_decl / OMEGA_E
    other = {"rad/s": "deg/s", "deg/s": "rad/s", "rad": "deg", "deg": "rad"}[gyro_unit]
    ofac = GYRO_UNITS[other][0] / (dt if kind == "increments" else 1.0)
    oratio = float(np.linalg.norm(wm)) * ofac / OMEGA_E
    gyro_ok = W_LO <= ratio <= W_HI
    if not gyro_ok and W_FIT[0] <= oratio <= W_FIT[1]:
        raise InputFileError(f"{path}: gyro units look {other}, declared {gyro_unit} ({t_txt}: |omega| = "
                             f"{ratio:.3g} x Earth rate as declared, {oratio:.3g} x as {other})")
    return {"checked": True, "window": [int(a), int(b)], "f_mps2": float(mraw * decl[2]),
            "omega_earth_rates": ratio, "gyro_in_range": bool(gyro_ok), "stands_on_end": on_end}


def _earth_rate_fits(wm, dt, gyro_unit, kind):
    """Whether the mean raw gyro column ``wm`` reads the Earth rate (within [W_LO, W_HI] of it) in
    ``gyro_unit`` as ``kind``."""
    fac = GYRO_UNITS[gyro_unit][0] / (dt if kind == "increments" else 1.0)
    return W_LO <= float(np.linalg.norm(wm)) * fac / OMEGA_E <= W_HI


def _proper_axes():
    out = []
    for a, b, c in itertools.product("FBLRUD", repeat=3):
        s = a + b + c
        try:
            axes_matrix(s)
        except ConfigError:
            continue
        out.append(s)
    return out


# ------------------------------------------------------------------ files
def read_imu_file(path, overrides=None):
    """An IMU file (CSV with its sidecar, or the project's HDF5) with the declaration
    ``overrides`` (sidecar keys, e.g. from CLI flags) applied -> :class:`ultratight.ins.imu_data.ImuData`.

    HDF5 files are in the internal convention already: only ``lever_arm_m`` (FLU) may be declared
    for them."""
    from ultratight.ins.imu_data import read_imu_csv, read_imu_h5

    path = Path(path)
    ov = {k: v for k, v in (overrides or {}).items() if v is not None}
    if path.suffix.lower() == ".csv":
        return read_imu_csv(path, resolve_declaration(path, ov))
    other = sorted(k for k in ov if k not in ("lever_arm_m", "check"))
    if other:
        raise ConfigError(f"{path}: IMU HDF5 files are in the internal convention (FLU, increments, SI, run "
                          f"time); {', '.join(other)} can only be declared for a CSV file")
    imu = read_imu_h5(path)
    if "lever_arm_m" in ov:
        imu.lever_arm_b = resolve_declaration(None, {"lever_arm_m": ov["lever_arm_m"]}).lever_arm_b()
    return imu


def align_to_gps_start(imu, week, tow_s, path="IMU file", tol_s=1e-3):
    """Drop the samples of a GPS-stamped IMU (``meta["start_tow_s"]``, time_ref = "gps_tow") that
    precede the IF start ``(week, tow_s)``, when the IMU's sample grid meets that start within
    ``tol_s``; the IMU's time axis then starts at the IF's first sample.  Other IMUs are returned
    unchanged (the engine's alignment check reports any remaining offset)."""
    meta = imu.meta or {}
    if "start_tow_s" not in meta:
        return imu
    off = float(tow_s) - float(meta["start_tow_s"])
    if meta.get("start_week") is not None and week is not None:
        off += (int(week) - int(meta["start_week"])) * 604800.0
    if off <= tol_s:
        return imu
    k = int(round(off * imu.rate_hz))
    if abs(k / imu.rate_hz - off) > tol_s or k >= imu.n - 1:
        raise InputFileError(f"{path}: IMU starts {off:.6f} s before the IF record, which is not on the IMU's "
                             f"{1.0 / imu.rate_hz:.6g} s sample grid (tolerance {tol_s} s) or leaves no data")
    t_cut = float(imu.t[k - 1])
    imu.t = imu.t[k:] - t_cut
    imu.dtheta_b = imu.dtheta_b[k:]
    imu.dv_b = imu.dv_b[k:]
    imu.t0 = 0.0
    imu.meta = dict(meta, start_tow_s=float(meta["start_tow_s"]) + t_cut, trimmed_samples=k)
    return imu
