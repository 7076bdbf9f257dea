"""Shared parts of the SINS/GNSS integration experiments (Fang 2017, Cai et al. 2020): configuration
checks, IMU synthesis with per-run constant biases, metrics over a run, the summary across
seeds, and the outputs (``metrics.json``, ``results.h5``, error-vs-time figures).

Metric conventions (both experiments; axis order named in every output):
velocity errors E, N, U (m/s); position errors N, E, U in metres (= latitude, longitude, height
of Fang 2017, Table 1); RMS over the whole run (this project's choice) per axis; min/max per axis;
``nees_in_band_fraction``: fraction of epochs whose full-state NEES lies in the two-sided 95 %
χ²(n) band (n = 15 loose, 17 tight).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from ultratight import __version__
from ultratight.errors import ConfigError
from ultratight.io_guard import h5_atomic, savefig_atomic, write_text_atomic
from ultratight.fusion.coupling.integration import nees_band
from ultratight.ins import error_model as em
from ultratight.ins.imu import BIAS_READINGS, ImuErrors, synthesize_imu
from ultratight.io_guard import json_clean
from ultratight.config import apply_overrides, deep_merge, check_known_keys, check_number

AXES = {"vel": ["E", "N", "U"], "pos": ["N (lat)", "E (lon)", "U (h)"]}
G0 = 9.80665
DPH = math.pi / 180.0 / 3600.0


MAX_DURATION_S = 86400.0     # one day of 100 Hz IMU data is ~0.5 GB of increments


def num(table, key, where, lo=None, hi=None, lo_open=False, integer=False):
    """A number of a TOML table (ConfigError naming ``where.key`` when absent or out of range)."""
    name = f"{where}.{key}" if where else key
    return float(check_number(table.get(key), name, lo=lo, hi=hi, lo_open=lo_open, integer=integer))


def tables(raw, schema, overrides):
    """Validate the scenario against ``schema`` {table: {key: default}} (top-level keys under
    ``""``), apply dotted ``overrides`` and return the completed config (a new dict)."""
    top_allowed = set(schema[""]) | {k for k in schema if k}
    check_known_keys(raw, top_allowed, "top level")
    for name in schema:
        if name and name in raw:
            if not isinstance(raw[name], dict):
                raise ConfigError(f"[{name}] must be a table")
            check_known_keys(raw[name], schema[name], f"[{name}]")
    base = dict(schema[""])
    base.update({k: dict(v) for k, v in schema.items() if k})
    cfg = deep_merge(base, raw)
    return apply_overrides(cfg, overrides)


def draw_imu(traj, rate_hz, gyro_bias, gyro_white, accel_bias, accel_white, rng, bias_reading="sigma"):
    """IMU increments along ``traj`` of a sensor drawn from the declared figures (rad/s, m/s²; white
    noise rad/√s, (m/s)/√s): ``bias_reading = "sigma"`` draws each axis's constant bias from
    N(0, figure²), ``"stated"`` takes the figure as the magnitude with a random sign per axis
    (:func:`ultratight.ins.imu.realise_errors`).  Returns (ImuData, bias_true [bg, ba] (6,)): the
    drawn biases are truth; the filters are tuned from the figures."""
    e = ImuErrors(gyro_bias=np.full(3, float(gyro_bias)), accel_bias=np.full(3, float(accel_bias)),
                  gyro_arw=np.full(3, gyro_white), accel_vrw=np.full(3, accel_white), preset="custom",
                  bias_reading=bias_reading)
    imu = synthesize_imu(traj, rate_hz, errors=e, rng=rng)
    real = imu.errors_realised
    return imu, np.concatenate([real["gyro_bias"], real["accel_bias"]])


def bias_reading(imu_table):
    """``[imu] bias_reading``: "stated" (the paper's constant bias is the magnitude, random sign per
    axis and run) or "sigma" (the figure is the 1σ of N(0, σ²)); ConfigError otherwise."""
    v = imu_table.get("bias_reading")
    if v not in BIAS_READINGS:
        raise ConfigError(f"imu.bias_reading must be one of {', '.join(BIAS_READINGS)}, got {v!r}")
    return v


def initial_P(n_states, att_rad, vel_mps, pos_m, bg, ba, clk=None):
    """Diagonal P0 (position block in metres, the integration module's units)."""
    d = np.zeros(n_states)
    d[em.ATT] = np.broadcast_to(np.asarray(att_rad, float) ** 2, (3,))
    d[em.VEL] = np.broadcast_to(np.asarray(vel_mps, float) ** 2, (3,))
    d[em.POS] = np.broadcast_to(np.asarray(pos_m, float) ** 2, (3,))
    d[em.BG] = np.broadcast_to(np.asarray(bg, float) ** 2, (3,))
    d[em.BA] = np.broadcast_to(np.asarray(ba, float) ** 2, (3,))
    if n_states == em.N17:
        d[em.CLK], d[em.DRIFT] = np.asarray(clk, float) ** 2
    return np.diag(d)


def run_metrics(res, n_states, t_from=0.0):
    """Per-method metrics of one run (whole run, or from ``t_from`` s)."""
    sel = res["t"] >= t_from
    e = res["err"][sel]
    vel, pos = e[:, em.VEL], e[:, em.POS]
    lo, hi = nees_band(n_states)
    nees = res["nees"][sel]
    out = {
        "vel_rms_mps": np.sqrt(np.mean(vel ** 2, axis=0)),
        "pos_rms_m": np.sqrt(np.mean(pos ** 2, axis=0)),
        "vel_max_mps": np.max(np.abs(vel), axis=0),
        "pos_max_m": np.max(np.abs(pos), axis=0),
        "vel_min_signed_mps": vel.min(axis=0), "vel_max_signed_mps": vel.max(axis=0),
        "pos_min_signed_m": pos.min(axis=0), "pos_max_signed_m": pos.max(axis=0),
        "nees_in_band_fraction": float(np.mean((nees >= lo) & (nees <= hi))),
        "nees_mean": float(np.nanmean(nees)),
        "runtime_s": float(res["runtime_s"]),
    }
    if res["n_screened"]:
        out["false_alarm_rate"] = res["n_faults"] / res["n_screened"]
    return out


VEC_KEYS = ("vel_rms_mps", "pos_rms_m", "vel_max_mps", "pos_max_m", "vel_min_signed_mps", "vel_max_signed_mps",
            "pos_min_signed_m", "pos_max_signed_m")


def aggregate(runs, methods):
    """Mean over seeds and the per-seed spread (min, max) of every metric, per method."""
    agg = {}
    for m in methods:
        rs = [r["methods"][m] for r in runs if m in r["methods"]]
        a = {}
        for k in rs[0]:
            v = np.array([np.asarray(r[k], float) for r in rs])
            if k in ("vel_min_signed_mps", "pos_min_signed_m"):
                a[k] = v.min(axis=0)
            elif k in ("vel_max_signed_mps", "pos_max_signed_m", "vel_max_mps", "pos_max_m"):
                a[k] = v.max(axis=0)
            else:
                a[k] = v.mean(axis=0)
            a[k + "_seed_min"] = v.min(axis=0)
            a[k + "_seed_max"] = v.max(axis=0)
        agg[m] = a
    return agg


def json_methods(agg):
    """The ``--json`` ``methods`` block (issue schema) plus the per-seed spread."""
    out = {}
    for m, a in agg.items():
        d = {k: np.asarray(a[k]).tolist() for k in ("vel_rms_mps", "pos_rms_m", "pos_max_m", "vel_max_mps")}
        d["nees_in_band_fraction"] = float(a["nees_in_band_fraction"])
        d["runtime_s"] = float(a["runtime_s"])
        if "false_alarm_rate" in a:
            d["false_alarm_rate"] = float(a["false_alarm_rate"])
        d["seed_spread"] = {k: [np.asarray(a[k + "_seed_min"]).tolist(), np.asarray(a[k + "_seed_max"]).tolist()]
                            for k in ("vel_rms_mps", "pos_rms_m", "nees_in_band_fraction")}
        out[m] = d
    return out


def write_common(cfg, runs, summary, out_dir, plots, figure_fn):
    """``metrics.json`` + ``results.h5`` (atomic) and the figures of ``figure_fn(out_dir, run0)``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    mpath = out / "metrics.json"
    doc = {"version": __version__, "config": cfg, **summary["json"], "details": summary.get("details", {})}
    write_text_atomic(mpath, json.dumps(json_clean(doc), indent=2, default=str))
    hpath = out / "results.h5"
    with h5_atomic(hpath) as f:
        f.attrs["schema"] = "ultratight-sins-gnss-results/1"
        f.attrs["version"] = __version__
        f.attrs["config_json"] = json.dumps(json_clean(cfg), default=str)
        f.attrs["state_order"] = "att E,N,U (rad); vel E,N,U (m/s); pos N,E,U (m); bg (rad/s); ba (m/s^2)" \
                                 "[; clock bias (m), drift (m/s)]"
        for r in runs:
            for m, series in r["series"].items():
                g = f.create_group(f"seed{int(r['seed']):06d}/{m}")
                for k, v in series.items():
                    g.create_dataset(k, data=np.asarray(v), compression="gzip", compression_opts=1)
                for k, v in r["methods"][m].items():
                    g.attrs[k] = np.asarray(v, float)
    figs = []
    if plots and runs:
        try:
            import matplotlib
            matplotlib.use("Agg")
        except ImportError:
            matplotlib = None
        if matplotlib is not None:
            figs = figure_fn(out, runs[0])
    return {"metrics_path": str(mpath), "h5_path": str(hpath), "figures": figs}


def error_figure(path, series, methods, block, labels, ylabel, title, t_max=None):
    """One figure: three panels (axes of ``block``) of error vs time, one line per method."""
    import matplotlib.pyplot as plt
    fig, axs = plt.subplots(3, 1, figsize=(8, 7), sharex=True)
    for m in methods:
        if m not in series:
            continue
        t = series[m]["t"]
        e = series[m]["err"][:, block]
        sel = t <= (t_max if t_max is not None else np.inf)
        for i in range(3):
            axs[i].plot(t[sel], e[sel, i], lw=0.8, label=m)
    for i in range(3):
        axs[i].set_ylabel(f"{labels[i]} {ylabel}")
        axs[i].grid(alpha=0.3)
    axs[0].legend(fontsize=8, ncol=3)
    axs[0].set_title(title)
    axs[-1].set_xlabel("time (s)")
    fig.tight_layout()
    try:
        savefig_atomic(fig, path)
    finally:
        plt.close(fig)
    return str(path)
