"""IMU increment data (:class:`ImuData`) and its files: the project's HDF5 layout
(:func:`write_imu_h5` / :func:`read_imu_h5`) and user CSV files (:func:`read_imu_csv` /
:func:`write_imu_csv`, read and written in the convention of an
:class:`ultratight.ins.imu_decl.ImuDeclaration`); layouts in docs/ins.md.

IMU data are *increments*: sample k covers the interval (t[k] - dt, t[k]] and holds
``dtheta_b[k]`` (rad) and ``dv_b[k]`` (m/s) integrated in the body frame FLU (x forward, y left,
z up); synthesis and sensor errors are in :mod:`ultratight.ins.imu`.  The readers refuse what
they cannot read faithfully with an InputFileError naming the file and the line, dataset or
attribute: non-finite values, duplicate or out-of-order stamps, gaps (an interval longer than
:data:`GAP_FACTOR` times the median), malformed layouts.
"""

import csv
import io
import json
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ultratight.errors import InputFileError
from ultratight.ins import imu_decl
from ultratight.io_guard import atomic_path, read_text_input, write_h5_atomic


@dataclass
class ImuData:
    """Increment IMU data.  ``t[k]`` is the END of interval k; the run starts at ``t0``."""
    t: np.ndarray
    dtheta_b: np.ndarray
    dv_b: np.ndarray
    rate_hz: float
    t0: float = 0.0
    truth: dict | None = None        # optional: t, llh, vel_l, q_lb at t0 and every t[k]
    meta: dict = field(default_factory=dict)
    lever_arm_b: np.ndarray = field(default_factory=lambda: np.zeros(3))   # IMU -> antenna, FLU, m
    # a synthesised run's drawn sensor errors (ultratight.ins.imu.realise_errors, ImuErrors.to_dict form):
    # truth, never written into the IMU file (its meta holds the declaration)
    errors_realised: dict | None = None

    @property
    def n(self):
        return self.t.shape[0]

    @property
    def dt(self):
        return 1.0 / self.rate_hz


# ------------------------------------------------------------------ HDF5 I/O
IMU_H5_FORMAT = "ultratight-imu"
IMU_H5_VERSION = 1


def write_imu_h5(path, imu, meta=None):
    """Write :class:`ImuData` to HDF5 (layout in docs/ins.md); built in memory, written under a
    unique temporary name, then renamed (disk errors raise OutputError)."""
    allmeta = dict(imu.meta or {})
    allmeta.update(meta or {})

    def build(f):
        f.attrs["format"] = IMU_H5_FORMAT
        f.attrs["version"] = IMU_H5_VERSION
        f.attrs["rate_hz"] = float(imu.rate_hz)
        f.attrs["t0_s"] = float(imu.t0)
        f.attrs["body_frame"] = "FLU (x forward, y left, z up)"
        f.attrs["meta_json"] = json.dumps(allmeta, default=str)
        if np.any(imu.lever_arm_b):
            f.attrs["lever_arm_b_m"] = np.asarray(imu.lever_arm_b, float)
        f.create_dataset("t", data=np.asarray(imu.t, float))
        f["t"].attrs["units"] = "s (end of each increment interval)"
        f.create_dataset("dtheta_b", data=np.asarray(imu.dtheta_b, float))
        f["dtheta_b"].attrs["units"] = "rad"
        f.create_dataset("dv_b", data=np.asarray(imu.dv_b, float))
        f["dv_b"].attrs["units"] = "m/s"
        if imu.truth is not None:
            g = f.create_group("truth")
            g.attrs["description"] = "true state at t0 and at every t: llh (rad, rad, m), vel_l ENU m/s, " \
                                     "q_lb scalar-first body->ENU"
            for key in ("t", "llh", "vel_l", "q_lb", "llh_antenna", "vel_l_antenna"):
                if key in imu.truth:
                    g.create_dataset(key, data=np.asarray(imu.truth[key], float))

    write_h5_atomic(path, build)


def _float_array(f, key, path):
    ds = f[key]
    if not hasattr(ds, "dtype") or ds.dtype.kind not in "iuf":
        raise InputFileError(f"{path}: dataset /{key} must hold numbers, not {getattr(ds, 'dtype', type(ds))}")
    return np.asarray(ds[()], dtype=float)


def _attr_number(f, key, path, default=None):
    if key not in f.attrs:
        if default is not None:
            return default
        raise InputFileError(f"{path}: missing attribute {key!r}")
    v = f.attrs[key]
    try:
        v = float(np.asarray(v).reshape(-1)[0]) if np.asarray(v).size == 1 else None
    except (TypeError, ValueError):
        v = None
    if v is None or not math.isfinite(v):
        raise InputFileError(f"{path}: attribute {key!r} must be a finite number, got {f.attrs[key]!r}")
    return v


def read_imu_h5(path):
    """Read an IMU HDF5 file written by :func:`write_imu_h5` (InputFileError on problems: missing
    or malformed datasets/attributes, non-finite increments or stamps)."""
    import h5py        # here: a CSV or log reader does not pay its import (about 0.08 s)

    path = Path(path)
    if not path.is_file():
        raise InputFileError(f"{path}: IMU file not found")
    try:
        with h5py.File(path, "r") as f:
            fmt = f.attrs.get("format")
            if isinstance(fmt, bytes):
                fmt = fmt.decode("utf-8", "replace")
            if fmt != IMU_H5_FORMAT:
                raise InputFileError(f"{path}: not an ultratight IMU HDF5 file (attribute format = "
                                     f"{fmt!r}, expected {IMU_H5_FORMAT!r})")
            for key in ("t", "dtheta_b", "dv_b"):
                if key not in f or not isinstance(f[key], h5py.Dataset):
                    raise InputFileError(f"{path}: missing dataset /{key}")
            t = _float_array(f, "t", path)
            dth = _float_array(f, "dtheta_b", path)
            dv = _float_array(f, "dv_b", path)
            rate = _attr_number(f, "rate_hz", path)
            if not rate > 0:
                raise InputFileError(f"{path}: attribute rate_hz must be > 0 Hz, got {rate}")
            t0 = _attr_number(f, "t0_s", path, default=float(t.reshape(-1)[0] - 1.0 / rate) if t.size else 0.0)
            raw_meta = f.attrs.get("meta_json", "{}")
            if isinstance(raw_meta, bytes):
                raw_meta = raw_meta.decode("utf-8", "replace")
            try:
                meta = json.loads(raw_meta) if isinstance(raw_meta, str) else None
            except ValueError:
                meta = None
            if not isinstance(meta, dict):
                raise InputFileError(f"{path}: attribute meta_json is not a JSON object")
            lever = np.zeros(3)
            if "lever_arm_b_m" in f.attrs:
                lever = np.asarray(f.attrs["lever_arm_b_m"], dtype=float).reshape(-1)
                if lever.shape != (3,) or not np.all(np.isfinite(lever)):
                    raise InputFileError(f"{path}: attribute lever_arm_b_m must be 3 finite numbers (m)")
            truth = None
            if "truth" in f:
                if not isinstance(f["truth"], h5py.Group):
                    raise InputFileError(f"{path}: /truth must be a group")
                truth = {k: _float_array(f["truth"], k, path) for k in f["truth"].keys()}
    except InputFileError:
        raise
    except (OSError, KeyError, ValueError, TypeError) as exc:
        raise InputFileError(f"{path}: cannot read HDF5 ({' '.join(str(exc).split())[:200]})") from None
    if t.ndim != 1:
        raise InputFileError(f"{path}: /t must be one-dimensional, got shape {t.shape}")
    if dth.shape != (t.size, 3) or dv.shape != (t.size, 3):
        raise InputFileError(f"{path}: dtheta_b {dth.shape} / dv_b {dv.shape} do not match t ({t.size},)")
    for name, arr in (("dtheta_b", dth), ("dv_b", dv)):
        bad = np.argwhere(~np.isfinite(arr))
        if bad.size:
            raise InputFileError(f"{path}: sample {int(bad[0][0])}: {name} is not a finite number (NaN/inf)")
    _check_stamps(t, path, first_row=0, what="sample")
    if truth is not None:
        need = {"t": (t.size + 1,), "llh": (t.size + 1, 3), "vel_l": (t.size + 1, 3), "q_lb": (t.size + 1, 4)}
        for k, shp in need.items():
            if k in truth and (truth[k].shape[1:] != shp[1:] or not np.all(np.isfinite(truth[k]))):
                raise InputFileError(f"{path}: /truth/{k} has shape {truth[k].shape} or non-finite values")
        if not all(k in truth for k in ("llh", "vel_l", "q_lb")) or min(truth[k].shape[0] for k in
                                                                          ("llh", "vel_l", "q_lb")) < 1:
            raise InputFileError(f"{path}: /truth needs llh, vel_l and q_lb with at least one row")
    return ImuData(t=t, dtheta_b=dth, dv_b=dv, rate_hz=rate, t0=t0, truth=truth, meta=meta, lever_arm_b=lever)


# ------------------------------------------------------------------ CSV files
# accepted columns: time, then either rates or increments, with a unit suffix or (units declared in
# the IMU sidecar / flags, ultratight.ins.imu_decl) without one
_RATE_UNITS = {"radps": "rad/s", "dps": "deg/s"}
_ACC_UNITS = {"mps2": "m/s^2", "g": "g"}
_DTH_UNITS = {"rad": "rad", "deg": "deg"}
_DV_UNITS = {"mps": "m/s"}
GAP_FACTOR = 1.5        # an interval longer than 1.5 x the median is a gap


def _check_stamps(t, path, first_row, what="row"):
    """Median interval of the time stamps ``t`` (None for one sample) of either reader; refuses no
    samples, non-finite, duplicate or out-of-order stamps and gaps, naming ``what`` number
    ``first_row + i``."""
    if t.size == 0:
        raise InputFileError(f"{path}: no IMU samples")
    bad = np.nonzero(~np.isfinite(t))[0]
    if bad.size:
        raise InputFileError(f"{path}: {what} {first_row + int(bad[0])}: time stamp is not a finite number")
    if t.size < 2:
        return None
    d = np.diff(t)
    nonpos = np.nonzero(d <= 0.0)[0]
    if nonpos.size:
        i = int(nonpos[0]) + 1
        kind = "duplicate" if d[i - 1] == 0.0 else "out-of-order"
        raise InputFileError(f"{path}: {what} {first_row + i}: {kind} time stamp t = {float(t[i]):.9g} s "
                             f"(previous {float(t[i - 1]):.9g} s); stamps must increase strictly")
    med = float(np.median(d))
    gaps = np.nonzero(d > GAP_FACTOR * med)[0]
    if gaps.size:
        i = int(gaps[0]) + 1
        raise InputFileError(f"{path}: {what} {first_row + i}: gap of {d[i - 1]:.6g} s before t = {float(t[i]):.9g} s "
                             f"(nominal interval {med:.6g} s); split the file or fill the gap")
    return med


def read_imu_csv(path, declaration=None):
    """Read a user IMU CSV file (layout in docs/ins.md, docs/imu-declaration.md) -> :class:`ImuData`.

    First non-comment line: header ``t_s`` plus either rates ``gx_<u>, gy_<u>, gz_<u>`` (u: radps,
    dps) and ``ax_<u>, ay_<u>, az_<u>`` (u: mps2, g) -- averages over the interval ending at t -- or
    increments ``dthx_<u>, dthy_<u>, dthz_<u>`` (u: rad, deg) and ``dvx_mps, dvy_mps, dvz_mps``;
    without the ``_<u>`` suffix the units come from ``declaration``.  Lines starting with ``#`` are
    comments.  ``declaration`` (:class:`ultratight.ins.imu_decl.ImuDeclaration`; default: the
    sidecar ``PATH.json`` when present, else the internal convention) gives axes, units, rate,
    time reference, lever arm; it is applied here and checked by the stationary sanity check.
    Problems raise InputFileError naming the line or the likely mistake.
    """
    path = Path(path)
    if not path.is_file():
        raise InputFileError(f"{path}: IMU CSV file not found")
    if declaration is None:
        declaration = imu_decl.resolve_declaration(path)
    lines = _csv_lines(path)
    hdr_line, cols = _csv_header(path, *lines[0])
    mode, gcols, acols = _csv_sensor_columns(path, hdr_line, cols)
    gyro_unit, accel_unit, kind = imu_decl.units_for(declaration, mode, gcols[1][0], acols[1][0], path)
    gsc = np.array([imu_decl.GYRO_UNITS[u or gyro_unit][0] for u in gcols[1]])
    asc = np.array([imu_decl.ACCEL_UNITS[u or accel_unit][0] for u in acols[1]])
    rows = lines[1:]
    if len(rows) < 2:
        raise InputFileError(f"{path}: need at least 2 data lines, got {len(rows)}")
    idx = {c: i for i, c in enumerate(cols)}
    data, line_no = _csv_values(path, rows, cols, [idx["t_s"]] + gcols[0] + acols[0])
    t = data[:, 0] + declaration.time_offset_s
    med = _csv_stamp_interval(t, path, line_no)
    if declaration.rate_hz is not None and abs(declaration.rate_hz * med - 1.0) > 0.01:
        raise InputFileError(f"{path}: declared rate {declaration.rate_hz:g} Hz ({declaration.source}) but the "
                             f"stamps are {1.0 / med:.6g} Hz apart")
    report = {"checked": False, "reason": "check disabled in the declaration"}
    if declaration.check:
        report = imu_decl.stationary_check(data[:, 4:7], data[:, 1:4], med, declaration, accel_unit, gyro_unit,
                                           kind, path)
    vals = data[:, 1:] * np.concatenate([gsc, asc])
    dts = np.diff(t, prepend=t[0] - med)
    if mode == "rates":
        vals = vals * dts[:, None]
    M = declaration.M
    meta = {"source": str(path), "csv_mode": "rate" if mode == "rates" else "increment",
            "declaration": declaration.to_dict(), "declaration_source": declaration.source,
            "sanity_check": report}
    t0 = float(t[0] - med)
    if declaration.time_ref == "gps_tow":
        meta["start_tow_s"] = t0
        if declaration.gps_week is not None:
            meta["start_week"] = int(declaration.gps_week)
        t = t - t0
        t0 = 0.0
    return ImuData(t=t.copy(), dtheta_b=vals[:, :3] @ M.T, dv_b=vals[:, 3:] @ M.T, rate_hz=1.0 / med,
                   t0=t0, truth=None, meta=meta, lever_arm_b=declaration.lever_arm_b())


def _csv_lines(path):
    """(line number, text) of the lines of an IMU CSV file that are neither blank nor comments."""
    text = read_text_input(path, "IMU CSV", "text CSV file")
    lines = [(i + 1, ln) for i, ln in enumerate(text.splitlines())]
    lines = [(i, ln) for i, ln in lines if ln.strip() and not ln.lstrip().startswith("#")]
    if not lines:
        raise InputFileError(f"{path}: empty IMU CSV file")
    return lines


def _csv_header(path, hdr_line, hdr):
    """(line number, lower-case column names) of the header line ``hdr``; it must name ``t_s``."""
    try:
        cols = [c.strip().lower() for c in next(csv.reader([hdr]))]
    except (csv.Error, StopIteration) as exc:
        raise InputFileError(f"{path}: line {hdr_line}: unreadable CSV header ({exc})") from None
    if "t_s" not in cols:
        raise InputFileError(f"{path}: line {hdr_line}: header needs a 't_s' column (seconds); got {cols}")
    return hdr_line, cols


def _axis_columns(path, hdr_line, cols, prefixes, units, kind):
    """(column indices, unit names or None per axis) of the three columns ``prefixes`` (bare or with
    a unit suffix of ``units``), or None when one is missing."""
    idx = {c: i for i, c in enumerate(cols)}
    out_i, out_u = [], []
    for p in prefixes:
        hits = [c for c in cols if c == p or c.startswith(p + "_")]
        if not hits:
            return None
        c = hits[0]
        u = c[len(p) + 1:] if c != p else None
        if u is not None and u not in units:
            raise InputFileError(f"{path}: line {hdr_line}: column {c!r} has unknown unit {u!r} for "
                                 f"{kind}; allowed: {', '.join(p + '_' + k for k in units)} (or {p!r} with "
                                 f"the unit declared in the IMU sidecar)")
        out_i.append(idx[c])
        out_u.append(units[u] if u is not None else None)
    return out_i, out_u


def _csv_sensor_columns(path, hdr_line, cols):
    """(mode "rates" | "increments", gyro columns, accelerometer columns) of a header; the columns as
    :func:`_axis_columns` gives them."""
    g = _axis_columns(path, hdr_line, cols, ("gx", "gy", "gz"), _RATE_UNITS, "angular rate")
    a = _axis_columns(path, hdr_line, cols, ("ax", "ay", "az"), _ACC_UNITS, "specific force")
    dth = _axis_columns(path, hdr_line, cols, ("dthx", "dthy", "dthz"), _DTH_UNITS, "angle increment")
    dvv = _axis_columns(path, hdr_line, cols, ("dvx", "dvy", "dvz"), _DV_UNITS, "velocity increment")
    if g and a:
        mode, gcols, acols = "rates", g, a
    elif dth and dvv:
        mode, gcols, acols = "increments", dth, dvv
    else:
        raise InputFileError(f"{path}: line {hdr_line}: header must have t_s and either gx_/gy_/gz_ + "
                             f"ax_/ay_/az_ rate columns or dthx_/dthy_/dthz_ + dvx_/dvy_/dvz_ increment "
                             f"columns (with unit suffixes, or without and the units declared); got {cols}")
    for what, (_, us) in (("gyro", gcols), ("accelerometer", acols)):
        if len(set(us)) > 1 and None in us:
            raise InputFileError(f"{path}: line {hdr_line}: {what} columns mix unit suffixes and bare names")
    return mode, gcols, acols


def _csv_values(path, rows, cols, want):
    """(n, len(want)) values of the columns ``want`` of the data ``rows`` ((line number, text)) and the
    line number of every row; a field that is not a finite number raises InputFileError.  Plain files
    (no quoting, every line with the header's field count, all values finite) are parsed by numpy in
    one call; anything else goes through the line-by-line reader, which names the offending line."""
    fast = _csv_values_fast(rows, cols, want)
    if fast is not None:
        return fast
    n = len(rows)
    data = np.empty((n, 7))
    line_no = np.empty(n, dtype=int)
    for r, (ln, text) in enumerate(rows):
        try:
            fields = next(csv.reader([text]))
        except (csv.Error, StopIteration) as exc:
            raise InputFileError(f"{path}: line {ln}: unreadable CSV line ({exc})") from None
        line_no[r] = ln
        if len(fields) != len(cols):
            raise InputFileError(f"{path}: line {ln}: {len(fields)} fields, header has {len(cols)}")
        for j, c in enumerate(want):
            try:
                v = float(fields[c])
            except ValueError:
                raise InputFileError(f"{path}: line {ln}: column {cols[c]!r}: {fields[c]!r} is not a number") \
                    from None
            if not math.isfinite(v):
                raise InputFileError(f"{path}: line {ln}: column {cols[c]!r} is {fields[c].strip()} "
                                     f"(NaN/inf not allowed)")
            data[r, j] = v
    return data, line_no


def _csv_values_fast(rows, cols, want):
    texts = [text for _, text in rows]
    commas = len(cols) - 1
    if any('"' in t or t.count(",") != commas for t in texts):
        return None
    try:
        data = np.loadtxt(io.StringIO("\n".join(texts)), delimiter=",", usecols=want, dtype=float, ndmin=2)
    except ValueError:
        return None
    if data.shape != (len(rows), len(want)) or not np.all(np.isfinite(data)):
        return None
    return data, np.array([ln for ln, _ in rows], dtype=int)


def _csv_stamp_interval(t, path, line_no):
    """Median interval of the stamps ``t`` (:func:`_check_stamps`), its errors naming the file line."""
    try:
        return _check_stamps(t, path, 0, what="row")
    except InputFileError as exc:
        # translate the row index into the file line number
        msg = str(exc)
        m = re.search(r"row (\d+):", msg)
        if m:
            msg = msg.replace(f"row {m.group(1)}:", f"line {line_no[int(m.group(1))]}:")
        raise InputFileError(msg) from None


def write_imu_csv(path, imu, declaration=None):
    """Write increments as CSV (t_s, dthx_rad, ..., dvz_mps) -- the format read_imu_csv reads.

    With ``declaration`` (:class:`ultratight.ins.imu_decl.ImuDeclaration`: kind, axes, units, time
    reference and offset) the data are written in that convention under bare column names, the
    lever arm of ``imu`` in the declared axes, and the declaration as the sidecar ``PATH.json``."""
    if declaration is None:
        with atomic_path(path) as tmp:
            with open(tmp, "w") as fh:
                fh.write("# ultratight IMU increments, body frame FLU; t_s = end of interval\n")
                fh.write("t_s,dthx_rad,dthy_rad,dthz_rad,dvx_mps,dvy_mps,dvz_mps\n")
                for k in range(imu.n):
                    fh.write(f"{imu.t[k]:.9f}," + ",".join(f"{x:.17g}" for x in imu.dtheta_b[k]) + "," +
                             ",".join(f"{x:.17g}" for x in imu.dv_b[k]) + "\n")
        return None
    dec = declaration
    kind = dec.kind or "increments"
    gu = dec.gyro_unit or ("rad/s" if kind == "rates" else "rad")
    au = dec.accel_unit or ("m/s^2" if kind == "rates" else "m/s")
    M = dec.M
    dth = imu.dtheta_b @ M / imu_decl.GYRO_UNITS[gu][0]       # v_file = M^T v_FLU
    dv = imu.dv_b @ M / imu_decl.ACCEL_UNITS[au][0]
    t = np.asarray(imu.t, float)
    if kind == "rates":
        dts = np.diff(t, prepend=float(imu.t0))
        dth, dv = dth / dts[:, None], dv / dts[:, None]
    if dec.time_ref == "gps_tow":
        t = t + float(imu.meta.get("start_tow_s", 0.0))
    t = t - dec.time_offset_s
    names = ("gx,gy,gz,ax,ay,az" if kind == "rates" else "dthx,dthy,dthz,dvx,dvy,dvz")
    with atomic_path(path) as tmp:
        with open(tmp, "w") as fh:
            fh.write(f"# ultratight IMU {kind}, axes {dec.axes if isinstance(dec.axes, str) else 'matrix'}, "
                     f"units in the sidecar {imu_decl.sidecar_path(path).name}\n")
            fh.write("t_s," + names + "\n")
            for k in range(t.shape[0]):
                fh.write(f"{t[k]:.9f}," + ",".join(f"{x:.17g}" for x in dth[k]) + "," +
                         ",".join(f"{x:.17g}" for x in dv[k]) + "\n")
    out = imu_decl.ImuDeclaration(kind=kind, axes=dec.axes, gyro_unit=gu, accel_unit=au,
                                  rate_hz=float(imu.rate_hz), time_ref=dec.time_ref, gps_week=dec.gps_week,
                                  time_offset_s=dec.time_offset_s, lever_arm_m=M.T @ np.asarray(imu.lever_arm_b),
                                  check=dec.check)
    return imu_decl.write_sidecar(path, out)

