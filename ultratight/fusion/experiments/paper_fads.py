"""The experiment of Duan et al. 2024, ``paper-fads``: air data (α, β, Mach) from FADS/GNSS/INS.

Per run (one seed): the analytic flight of :mod:`ultratight.airdata.flight` (the same in every run),
Table 1 noise drawn from ``numpy.random.SeedSequence(seed).spawn(4)`` streams (IMU, GNSS, FADS,
initial error), then three methods on the same data and the same initial state:

* ``gnss-ins``: the 9-state total-state CKF with the GNSS position/velocity (eqs. 2–3, fixed R);
* ``fads-ekf`` / ``fads-ckf``: FADS/GNSS/INS — altitude and velocity pre-fused by eq. 4 (GNSS
  latitude/longitude unchanged), the eq. 10 adaptive altitude noise, EKF (eqs. 7–8, linearized) or
  CKF; same Q, R, P0 and data.

Air data from each filter output (Fig. 1): ``v_b = C_nb V̂``, α, β, ``Ma = |V̂|/a(ĥ)``; altitude row
ĥ for GNSS/INS and h_GF for the FADS variants (the paper's reading: altitude is not part of the main
filter); the FADS filters' own ĥ is reported too. Table 3 reading: Max = max |error| over all runs,
Std = std of the pooled errors and, the other reading, the mean of per-run stds.

FADS velocity variances at 1 and 10 km for eq. 4 (not given): the mean first-order covariance of the
FADS air velocity (true attitude) over the epochs within 100 m of 1 km and 10 km altitude of the
run's flight (the covariance is checked against the inversion's actual errors in
``tests/test_airdata.py``). FADS altitude: "direct" (σ_F log-linear 1 → 100 m) by default, or
"pressure" (from the inverted p_∞).

Readings where the paper is silent or ambiguous, each with its alternative, selectable in the
scenario TOML (:data:`CHOICES`; defaults = this project's choices): ``imu.error_model`` ("white" noise
per sample, or a per-run constant "bias", or "bias+white"; Q of the bias from
``filter.bias_horizon_s``, :func:`process_noise`), ``fads.altitude_shape`` ("log-linear" or
"linear" 1 → 100 m curve), ``fads.altitude_curve`` (the curve as 1σ, or as a 3σ "envelope"),
``filter.altitude_row`` ("prefused" h_GF, or the FADS filters' own ĥ) and ``filter.fusion`` ("eq4":
the paper's pre-fusion; "separate": GNSS velocity and FADS body air velocity as separate
observations, altitudes combined per epoch by their variances — :func:`_separate_measurements`,
the built-in scenario ``paper-fads-separate``).
"""

import json
import math
import os
import time
from concurrent.futures import ProcessPoolExecutor
from functools import lru_cache
from pathlib import Path

import numpy as np

from ultratight import __version__
from ultratight.airdata import atmosphere, fads
from ultratight.airdata.flight import Flight
from ultratight.airdata.frames import euler_to_dcm
from ultratight.errors import ConfigError
from ultratight.fusion.coupling import airdata as AF
from ultratight.ins.earth import radii
from ultratight.ins.imu import ImuErrors, apply_errors
from ultratight.io_guard import h5_atomic, savefig_atomic, write_text_atomic
from ultratight.io_guard import json_clean
from ultratight.config import (apply_overrides, deep_merge, check_known_keys, check_number,
                                                 locate_scenario, read_toml)

METHODS = ("gnss-ins", "fads-ekf", "fads-ckf")
DEFAULT_METHODS = METHODS
ROWS = ("aoa_deg", "sideslip_deg", "mach", "altitude_m")
ROW_LABEL = {"aoa_deg": "AoA (deg)", "sideslip_deg": "sideslip (deg)", "mach": "Mach", "altitude_m": "altitude (m)"}
# Duan et al. 2024, Tables 2 and 3: (max, std)
PAPER_TABLE2 = {"gnss-ins": {"aoa_deg": (0.2617, 0.0473), "sideslip_deg": (0.1835, 0.0278), "mach": (0.0117, 0.0045),
                             "altitude_m": (69.54, 16.84)},
                "fads-ckf": {"aoa_deg": (0.1222, 0.0201), "sideslip_deg": (0.1116, 0.0183), "mach": (0.0070, 0.0025),
                             "altitude_m": (69.54, 9.397)}}
PAPER_TABLE3 = {"gnss-ins": {"aoa_deg": (0.3704, 0.0420), "sideslip_deg": (0.2629, 0.0275), "mach": (0.0137, 0.0047),
                             "altitude_m": (96.64, 17.00)},
                "fads-ekf": {"aoa_deg": (0.2882, 0.0240), "sideslip_deg": (0.2503, 0.0286), "mach": (0.0110, 0.0016),
                             "altitude_m": (88.54, 9.559)},
                "fads-ckf": {"aoa_deg": (0.2281, 0.0206), "sideslip_deg": (0.2210, 0.0175), "mach": (0.0090, 0.0025),
                             "altitude_m": (88.54, 9.559)}}
LABEL = {"gnss-ins": "GNSS/INS", "fads-ekf": "FADS/GNSS/INS EKF", "fads-ckf": "FADS/GNSS/INS CKF"}

SCHEMA = {
    "top": ("name", "experiment", "description", "duration_s", "profile_duration_s", "seed", "flight", "imu", "gnss", "fads",
            "atmosphere", "filter"),
    "flight": ("lat_deg", "lon_deg", "t_climb_s", "t_descent_s", "h0_m", "h_cruise_m", "h_end_m", "mach0",
               "mach_cruise", "mach_end", "aoa0_deg", "aoa_amp_deg", "aoa_period_s", "sideslip_amp_deg",
               "sideslip_period_s"),
    "imu": ("rate_hz", "accel_sigma_mps2", "gyro_sigma_dps", "error_model"),
    "gnss": ("pos_sigma_m", "alt_sigma_m", "vel_sigma_mps"),
    "fads": ("noise_pa", "cone_deg", "clock_deg", "epsilon", "altitude_mode", "altitude_curve", "altitude_shape",
             "sigma_h_0km_m", "sigma_h_20km_m"),
    "atmosphere": ("wind_esd_mps",),
    "filter": ("rate_hz", "p0_pos_m", "p0_alt_m", "p0_vel_mps", "p0_att_deg", "q_scale", "bias_horizon_s", "v_min_mps",
               "altitude_row", "fusion"),
}
# the string options and their values (the first is the scenario default; docs/airdata.md has the figures of each)
CHOICES = {("imu", "error_model"): ("white", "bias", "bias+white"),
           ("fads", "altitude_mode"): ("direct", "pressure"),
           ("fads", "altitude_curve"): ("sigma", "envelope"),
           ("fads", "altitude_shape"): ("log-linear", "linear"),
           ("filter", "altitude_row"): ("prefused", "filter"),
           ("filter", "fusion"): ("eq4", "separate")}
POSITIVE = {"imu": ("rate_hz", "accel_sigma_mps2", "gyro_sigma_dps"), "gnss": ("pos_sigma_m", "alt_sigma_m", "vel_sigma_mps"),
            "fads": ("noise_pa", "sigma_h_0km_m", "sigma_h_20km_m"),
            "filter": ("rate_hz", "p0_pos_m", "p0_alt_m", "p0_vel_mps", "p0_att_deg", "q_scale", "bias_horizon_s")}


# ------------------------------------------------------------------ configuration

def _number(table, key, where, positive=False):
    name = key if where is None else f"{where}.{key}"
    return float(check_number(table[key], name, lo=0 if positive else None, lo_open=True))


def load(path, raw, overrides):
    """Complete and check a paper-fads scenario (unknown tables/keys refused with a did-you-mean)."""
    defaults = deep_merge({}, _default_raw())
    cfg = deep_merge(defaults, raw)
    cfg = apply_overrides(cfg, overrides or {})
    check_known_keys(cfg, SCHEMA["top"], "top level")
    for name, keys in SCHEMA.items():
        if name == "top":
            continue
        if not isinstance(cfg[name], dict):
            raise ConfigError(f"[{name}] must be a table")
        check_known_keys(cfg[name], keys, f"[{name}]")
        for k in keys:
            if k in ("cone_deg", "clock_deg", "wind_esd_mps") or (name, k) in CHOICES:
                continue
            cfg[name][k] = _number(cfg[name], k, name, k in POSITIVE.get(name, ()))
    cfg["duration_s"] = _number(cfg, "duration_s", None, True)
    if isinstance(cfg["seed"], bool) or not isinstance(cfg["seed"], int) or cfg["seed"] < 0:
        raise ConfigError(f"seed must be an integer >= 0, got {cfg['seed']!r}")
    for (table, key), values in CHOICES.items():
        if cfg[table][key] not in values:
            raise ConfigError(f"{table}.{key} must be one of " + ", ".join(repr(v) for v in values)
                              + f"; got {cfg[table][key]!r}")
    fads.ports_from_config(cfg["fads"]["cone_deg"], cfg["fads"]["clock_deg"])
    cfg["atmosphere"]["wind_esd_mps"] = [float(x) for x in atmosphere.wind_esd(cfg["atmosphere"]["wind_esd_mps"])]
    per = cfg["imu"]["rate_hz"] / cfg["filter"]["rate_hz"]
    if abs(per - round(per)) > 1e-9 or round(per) < 1:
        raise ConfigError("imu.rate_hz must be an integer multiple of filter.rate_hz")
    # the flight profile is defined over the scenario's duration; --duration cuts the run short
    cfg["profile_duration_s"] = float(cfg.get("profile_duration_s", raw.get("duration_s", 1000.0)))
    if not 0.0 < cfg["duration_s"] <= cfg["profile_duration_s"]:
        raise ConfigError(f"duration_s must be in (0, {cfg['profile_duration_s']:g}] s (the flight's length), "
                          f"got {cfg['duration_s']:g}")
    if abs(cfg["duration_s"] * cfg["filter"]["rate_hz"] - round(cfg["duration_s"] * cfg["filter"]["rate_hz"])) > 1e-6:
        raise ConfigError("duration_s must be a whole number of filter epochs")
    _flight(_flight_key(cfg))          # validates the profile
    cfg["name"] = str(cfg.get("name") or Path(path).stem)
    cfg["scenario_path"] = str(path)
    return cfg


def _default_raw():
    raw = read_toml(locate_scenario("paper-fads"))
    return {k: v for k, v in raw.items() if k not in ("name", "description")}


def _flight_key(cfg):
    fl = dict(cfg["flight"])
    fl["duration_s"] = cfg["profile_duration_s"]
    return tuple(sorted(fl.items()))


@lru_cache(maxsize=2)
def _flight(key):
    return Flight(dict(key))


@lru_cache(maxsize=2)
def _truth(key, imu_rate, filter_rate, duration_s):
    """Truth shared by all runs of a flight: epochs' truth and ideal IMU increments (cached per process)."""
    fl = _flight(key)
    n_ep = int(round(duration_s * filter_rate))
    t = np.arange(n_ep + 1) / filter_rate
    tr = fl.truth(t)
    dth, dv = fl.imu_increments(imu_rate, duration_s)
    return tr, dth, dv


# ------------------------------------------------------------------ one run

def _state(tr, i):
    return np.array([tr["lon"][i], tr["lat"][i], tr["h"][i], *tr["vel"][i], tr["pitch"][i], tr["yaw"][i],
                     tr["roll"][i]])


def _separate_measurements(cfg, sim, wind):
    """``filter.fusion = "separate"``: the observation ``[λ_G, L_G, h_GF, V_G, v_b,F]`` of each epoch
    (:func:`ultratight.fusion.coupling.airdata.separate_h`) and the per-epoch altitude h_GF. h_GF combines the GNSS
    and FADS altitudes by their variances of the epoch (the FADS one from the curve at the GNSS
    altitude, or the inversion's own in "pressure" mode) with R = the combination's variance (no
    eq. 10); the FADS air velocity enters in body axes with the inversion's covariance."""
    zg, sg = sim["z_gnss"], sim["sig_gnss"]
    R_g = cfg["gnss"]["alt_sigma_m"] ** 2
    if cfg["fads"]["altitude_mode"] == "direct":
        R_f = direct_altitude_sigma(cfg, np.maximum(zg[:, 2], 0.0)) ** 2
    else:
        R_f = sim["fads"]["var_h"]
    h_gf, R_h = AF.inverse_variance(zg[:, 2], R_g, sim["h_fads"], R_f)
    R_v = np.eye(3) * cfg["gnss"]["vel_sigma_mps"] ** 2
    v_b, cov_b = sim["fads"]["vel_b"], sim["fads"]["cov_vel_b"]
    h = AF.separate_h(wind)

    def measure(k, x, P):
        z = np.concatenate([zg[k, :2], [h_gf[k]], zg[k, 3:6], v_b[k]])
        R = np.zeros((9, 9))
        R[0, 0], R[1, 1], R[2, 2] = sg[k, 0] ** 2, sg[k, 1] ** 2, R_h[k]
        R[3:6, 3:6] = R_v
        R[6:, 6:] = cov_b[k]
        return z, R, h
    return measure, h_gf


def simulate(cfg, seed):
    """Truth and sensor data of one run (dict of arrays; see module doc)."""
    imu_rate, f_rate = cfg["imu"]["rate_hz"], cfg["filter"]["rate_hz"]
    tr, dth0, dv0 = _truth(_flight_key(cfg), imu_rate, f_rate, cfg["duration_s"])
    ss_imu, ss_gnss, ss_fads, ss_p0 = np.random.SeedSequence(int(seed)).spawn(4)
    dt = 1.0 / imu_rate
    dth, dv, imu_bias = imu_data(cfg, dth0, dv0, np.random.default_rng(ss_imu))
    ep = slice(1, None)                                  # measurement epochs t_k, k = 1..n
    lat, h, vel = tr["lat"][ep], tr["h"][ep], tr["vel"][ep]
    rm, rn = np.vectorize(radii)(lat)
    g = cfg["gnss"]
    sig_g = np.stack([g["pos_sigma_m"] / ((rn + h) * np.cos(lat)), g["pos_sigma_m"] / (rm + h),
                      np.full(h.shape, g["alt_sigma_m"]), *(np.full((3,) + h.shape, g["vel_sigma_mps"]))], axis=1)
    truth_z = np.column_stack([tr["lon"][ep], lat, h, vel])
    rng_g = np.random.default_rng(ss_gnss)
    z_gnss = truth_z + rng_g.standard_normal(truth_z.shape) * sig_g
    # FADS: port pressures of the true air data (+ constant wind), 100 Pa noise, per-epoch inversion
    f = cfg["fads"]
    cone, clock = fads.ports_from_config(f["cone_deg"], f["clock_deg"])
    wind = np.asarray(cfg["atmosphere"]["wind_esd_mps"])
    v_air_n = vel - wind
    v_air_b = np.einsum("nji,nj->ni", tr["C_bn"][ep], v_air_n)
    tas = np.linalg.norm(v_air_b, axis=1)
    alpha = np.arctan2(v_air_b[:, 2], v_air_b[:, 0])
    beta = np.arcsin(v_air_b[:, 1] / tas)
    atm = atmosphere.state(h)
    mach = tas / atm["a"]
    qc = atm["p"] * fads.impact_ratio(mach)
    rng_f = np.random.default_rng(ss_fads)
    p = fads.port_pressures(alpha, beta, qc, atm["p"], cone, clock, f["epsilon"])
    p_meas = p + rng_f.standard_normal(p.shape) * f["noise_pa"]
    y, cov = fads.invert(p_meas, cone, clock, f["noise_pa"], f["epsilon"])
    d = fads.derived(y, cov, tr["C_bn"][ep])
    if f["altitude_mode"] == "direct":
        sig_h = direct_altitude_sigma(cfg, h)
        h_f = h + rng_f.standard_normal(h.shape) * sig_h
        R_f1, R_f2 = direct_altitude_sigma(cfg, 1000.0) ** 2, direct_altitude_sigma(cfg, 10000.0) ** 2
    else:
        h_f = d["h_m"]
        R_f1, R_f2 = _calibrate(h, d["var_h"][:, None])
        R_f1, R_f2 = float(R_f1[0]), float(R_f2[0])
    Rv1, Rv2 = _calibrate(h, np.diagonal(d["cov_vel_n"], axis1=1, axis2=2))
    # initial error from P0
    fc = cfg["filter"]
    x_true0 = _state(tr, 0)
    rm0, rn0 = radii(x_true0[1])
    sd0 = np.array([fc["p0_pos_m"] / ((rn0 + x_true0[2]) * math.cos(x_true0[1])), fc["p0_pos_m"] / (rm0 + x_true0[2]),
                    fc["p0_alt_m"], *([fc["p0_vel_mps"]] * 3), *([math.radians(fc["p0_att_deg"])] * 3)])
    x0 = x_true0 + np.random.default_rng(ss_p0).standard_normal(9) * sd0
    return {"truth": tr, "dtheta": dth, "dv": dv, "z_gnss": z_gnss, "sig_gnss": sig_g, "h_fads": h_f,
            "R_f": (R_f1, R_f2), "R_vf": (Rv1, Rv2), "fads": d, "fads_y": y, "alpha": alpha, "beta": beta,
            "mach": mach, "x0": x0, "sd0": sd0, "per_epoch": int(round(imu_rate / f_rate)), "dt": dt,
            "imu_bias": imu_bias}


def imu_data(cfg, dth0, dv0, rng):
    """Ideal increments corrupted by Table 1's IMU figures read as ``imu.error_model`` says.

    "white" (this project's default): 1σ white noise per sample (increments get σ·dt); "bias": a constant
    bias per axis drawn once per run, N(0, σ²); "bias+white": both. Returns (dθ, dv, biases
    {"gyro_rps", "accel_mps2"})."""
    dt = 1.0 / cfg["imu"]["rate_hz"]
    sg, sa = math.radians(cfg["imu"]["gyro_sigma_dps"]), cfg["imu"]["accel_sigma_mps2"]
    model = cfg["imu"]["error_model"]
    bg = ba = np.zeros(3)
    if model != "white":
        bg, ba = rng.standard_normal(3) * sg, rng.standard_normal(3) * sa
    white = model != "bias"
    err = ImuErrors(gyro_bias=bg, accel_bias=ba,
                    gyro_arw=np.full(3, sg * math.sqrt(dt) if white else 0.0),
                    accel_vrw=np.full(3, sa * math.sqrt(dt) if white else 0.0))
    dth, dv = apply_errors(dth0, dv0, err, rng, dt)
    return dth, dv, {"gyro_rps": bg, "accel_mps2": ba}


def direct_altitude_sigma(cfg, h_m):
    """σ_F(h) of the "direct" FADS altitude: the paper's 1 → 100 m curve (``fads.sigma_h_*``) with
    ``fads.altitude_shape``, read as the 1σ ("sigma") or as a ±3σ envelope ("envelope": σ = curve/3)."""
    f = cfg["fads"]
    s = fads.direct_altitude_sigma(h_m, f["sigma_h_0km_m"], f["sigma_h_20km_m"], shape=f["altitude_shape"])
    return s / 3.0 if f["altitude_curve"] == "envelope" else s


def _calibrate(h, var, band_m=100.0):
    """Mean of per-epoch variances (n, k) over the epochs within ``band_m`` of 1 km and of 10 km."""
    out = []
    for ref in (1000.0, 10000.0):
        sel = np.abs(h - ref) <= band_m
        if not np.any(sel):
            sel = np.argsort(np.abs(h - ref))[:10]
        out.append(np.mean(var[sel], axis=0))
    return out


def process_noise(cfg, sd0):
    """Q per filter step from Table 1 (× q_scale), for the reading ``imu.error_model``.

    White noise: the sum over the IMU samples of a step, ``per·(σ dt)²``. Constant bias: the 9-state
    filter has no bias states, so a bias b is an unmodelled error that grows like b·t; it is given
    the white noise whose variance over ``filter.bias_horizon_s`` = τ equals the bias's own drift
    over τ, (σ τ)², i.e. a PSD of σ² τ and ``σ² τ T`` per step of T (τ = T gives (σ T)²). Both
    terms for "bias+white"."""
    per = cfg["imu"]["rate_hz"] / cfg["filter"]["rate_hz"]
    dt = 1.0 / cfg["imu"]["rate_hz"]
    step = per * dt
    sa, sg = cfg["imu"]["accel_sigma_mps2"], math.radians(cfg["imu"]["gyro_sigma_dps"])
    model = cfg["imu"]["error_model"]
    var_v = var_a = 0.0
    if model != "bias":
        var_v += per * (sa * dt) ** 2
        var_a += per * (sg * dt) ** 2
    if model != "white":
        tau = cfg["filter"]["bias_horizon_s"]
        var_v += sa ** 2 * tau * step
        var_a += sg ** 2 * tau * step
    var_p = max(var_v * step ** 2 / 3.0, 1e-6)                 # m^2 (floor keeps P well conditioned)
    to_rad = sd0[:2] / cfg["filter"]["p0_pos_m"]               # rad per metre (lon, lat)
    q = np.array([var_p * to_rad[0] ** 2, var_p * to_rad[1] ** 2, var_p, var_v, var_v, var_v, var_a, var_a, var_a])
    return np.diag(q * cfg["filter"]["q_scale"])


def _air_errors(xs, tr, h_row, wind):
    C = euler_to_dcm(xs[:, 6], xs[:, 7], xs[:, 8])
    ad = fads.air_data(xs[:, 3:6], C, np.clip(xs[:, 2], -4000.0, 80000.0), wind)
    ep = slice(1, None)
    v_true = tr["vel"][ep] - wind
    vb = np.einsum("nji,nj->ni", tr["C_bn"][ep], v_true)
    m_true = np.linalg.norm(vb, axis=1) / atmosphere.speed_of_sound(tr["h"][ep])
    return {"aoa_deg": np.degrees(ad["alpha"] - np.arctan2(vb[:, 2], vb[:, 0])),
            "sideslip_deg": np.degrees(ad["beta"] - np.arcsin(vb[:, 1] / np.linalg.norm(vb, axis=1))),
            "mach": ad["mach"] - m_true, "altitude_m": h_row - tr["h"][ep]}


SETTLE_S = 20.0      # the "after the initial transient" maxima skip this much of the flight


def _stats(e, settle_epochs=0):
    return {"max": float(np.max(np.abs(e))), "std": float(np.std(e)), "sum": float(np.sum(e)),
            "sumsq": float(np.sum(e * e)), "n": int(e.size),
            "max_settled": float(np.max(np.abs(e[settle_epochs:]))) if e.size > settle_epochs else float("nan")}


def run_method(cfg, sim, method):
    """One filter over one run's data → (errors dict of arrays, extras)."""
    tr = sim["truth"]
    Q = process_noise(cfg, sim["sd0"])
    P0 = np.diag(sim["sd0"] ** 2)
    zg, sg = sim["z_gnss"], sim["sig_gnss"]
    wind = np.asarray(cfg["atmosphere"]["wind_esd_mps"])
    if method == "gnss-ins":
        def measure(k, x, P):
            return zg[k], np.diag(sg[k] ** 2)
        h_gf = None
    elif cfg["filter"]["fusion"] == "separate":
        measure, h_gf = _separate_measurements(cfg, sim, wind)
    else:
        R_g = cfg["gnss"]["alt_sigma_m"] ** 2
        R_f1, R_f2 = sim["R_f"]
        h_gf = AF.blend(zg[:, 2], zg[:, 2], sim["h_fads"], R_g, R_f1, R_f2)          # eq. 4
        R_kmin = AF.fused_variance(zg[:, 2], R_g, R_f1, R_f2)                          # this project's choice
        Rv_g = cfg["gnss"]["vel_sigma_mps"] ** 2
        Rv1, Rv2 = sim["R_vf"]
        R_vel = AF.fused_variance(zg[:, 2:3], Rv_g, Rv1, Rv2)                            # (n, 3)
        v_b = sim["fads"]["vel_b"]
        v_min = cfg["filter"]["v_min_mps"]
        c_f = AF.fads_weight(zg[:, 2:3], Rv_g, Rv1, Rv2)                              # (n, 3)

        def measure(k, x, P):
            C = euler_to_dcm(x[AF.I_PITCH], x[AF.I_YAW], x[AF.I_ROLL])               # INS attitude
            v_f = C @ v_b[k] + wind                                                     # FADS V_F (+ known wind)
            v_gf = AF.blend(zg[k, 2], zg[k, 3:6], v_f, Rv_g, Rv1, Rv2)                 # eq. 4, velocities
            z = np.concatenate([zg[k, :2], [h_gf[k]], v_gf])
            R = np.diag(np.concatenate([sg[k, :2] ** 2,
                                        [AF.adaptive_altitude_variance(x[AF.I_VZ], R_kmin[k], R_g, v_min)],  # eq. 10
                                        R_vel[k]]))
            return z, R, AF.fads_velocity_h(C, c_f[k], wind)
    kind = "ekf" if method == "fads-ekf" else "ckf"
    t0, c0 = time.perf_counter(), time.process_time()
    xs, pdiag, nis = AF.run(kind, sim["x0"], P0, Q, sim["dtheta"], sim["dv"], sim["dt"], sim["per_epoch"], measure)
    runtime, cpu = time.perf_counter() - t0, time.process_time() - c0
    # altitude row: GNSS/INS reports its ĥ; the FADS variants the pre-fused h_GF (the paper: "altitude is
    # not part of the main filter") or, with filter.altitude_row = "filter", their own ĥ
    h_row = xs[:, 2] if h_gf is None or cfg["filter"]["altitude_row"] == "filter" else h_gf
    errs = _air_errors(xs, tr, h_row, wind)
    x_true = np.column_stack([tr["lon"][1:], tr["lat"][1:], tr["h"][1:], tr["vel"][1:], tr["pitch"][1:],
                              tr["yaw"][1:], tr["roll"][1:]])
    extras = {"filter_altitude_m": xs[:, 2] - tr["h"][1:], "nis_mean": float(np.nanmean(nis)), "runtime_s": runtime,
              "cpu_s": cpu, "nees_mean": float(np.mean((xs - x_true) ** 2 / pdiag))}
    if h_gf is not None:
        extras["prefused_altitude_m"] = h_gf - tr["h"][1:]
    return errs, extras


def run_one(cfg, methods, seed, progress=False):
    """One Monte-Carlo run: {"seed", "methods": {m: {row: stats, ..., "runtime_s"}}, "series": ...}."""
    t0 = time.perf_counter()
    sim = simulate(cfg, seed)
    t_sim = time.perf_counter() - t0
    out = {"seed": int(seed), "methods": {}, "simulate_s": t_sim}
    series = {}
    settle = int(round(SETTLE_S * cfg["filter"]["rate_hz"]))
    for m in methods:
        errs, extras = run_method(cfg, sim, m)
        res = {row: _stats(errs[row], settle) for row in ROWS}
        res["filter_altitude_m"] = _stats(extras["filter_altitude_m"], settle)
        if "prefused_altitude_m" in extras:
            res["prefused_altitude_m"] = _stats(extras["prefused_altitude_m"], settle)
        res["nis_mean"] = extras["nis_mean"]
        res["nees_mean"] = extras["nees_mean"]
        res["runtime_s"] = extras["runtime_s"]
        res["cpu_s"] = extras["cpu_s"]
        out["methods"][m] = res
        series[m] = np.stack([errs[row][9::10] for row in ROWS], axis=1)       # 1 Hz for the HDF5 file
    out["series_1hz"] = series
    return out


def run_many(cfg, methods, seeds, progress=False):
    """``run_one`` for each seed in worker processes (all cores); results in seed order, identical to sequential."""
    workers = min(len(seeds), os.cpu_count() or 1)
    if workers <= 1:
        return [run_one(cfg, methods, s, progress) for s in seeds]
    out = []
    with ProcessPoolExecutor(max_workers=workers) as ex:
        for i, res in enumerate(ex.map(run_one, [cfg] * len(seeds), [methods] * len(seeds), seeds,
                                       [False] * len(seeds))):
            out.append(res)
            if progress:
                print(f"run {i + 1}/{len(seeds)} seed {seeds[i]} done", flush=True)
    return out


# ------------------------------------------------------------------ summary

def _pool(runs, m, row):
    st = [r["methods"][m][row] for r in runs]
    n = sum(s["n"] for s in st)
    mean = sum(s["sum"] for s in st) / n
    pooled = math.sqrt(max(sum(s["sumsq"] for s in st) / n - mean * mean, 0.0))
    return {"max": max(s["max"] for s in st), "std": pooled, "std_run_mean": float(np.mean([s["std"] for s in st])),
            "max_settled": max(s["max_settled"] for s in st), "max_per_run": [s["max"] for s in st]}


def summarize(cfg, runs):
    methods = list(runs[0]["methods"])
    table = {m: {row: _pool(runs, m, row) for row in ROWS} for m in methods}
    for m in methods:
        table[m]["filter_altitude_m"] = _pool(runs, m, "filter_altitude_m")
        if "prefused_altitude_m" in runs[0]["methods"][m]:
            table[m]["prefused_altitude_m"] = _pool(runs, m, "prefused_altitude_m")
        table[m]["nees_mean"] = float(np.mean([r["methods"][m]["nees_mean"] for r in runs]))
        table[m]["runtime_s"] = float(np.mean([r["methods"][m]["runtime_s"] for r in runs]))
        table[m]["cpu_s"] = float(np.mean([r["methods"][m]["cpu_s"] for r in runs]))
    nd = {"aoa_deg": 4, "sideslip_deg": 4, "mach": 5, "altitude_m": 2}
    lines = [f"paper-fads: {len(runs)} run(s), seeds {runs[0]['seed']}..{runs[-1]['seed']} "
             f"(IMU '{cfg['imu']['error_model']}', FADS altitude '{cfg['fads']['altitude_mode']}' "
             f"{cfg['fads']['altitude_shape']} {cfg['fads']['altitude_curve']}, FADS altitude row "
             f"'{cfg['filter']['altitude_row']}')", "",
             "Table 3 (Max = max |error| over all runs (after the first 20 s); Std = pooled std [mean of per-run stds])"
             " — ours | paper"]
    for row in ROWS:
        lines.append(f"  {ROW_LABEL[row]}")
        for m in methods:
            t = table[m][row]
            p = PAPER_TABLE3[m][row]
            lines.append(f"    {LABEL[m]:<19} max {t['max']:10.{nd[row]}f} ({t['max_settled']:.{nd[row]}f}) "
                         f"std {t['std']:9.{nd[row]}f} "
                         f"[{t['std_run_mean']:.{nd[row]}f}]  | paper max {p[0]:.{nd[row]}f} std {p[1]:.{nd[row]}f}")
    lines.append("  FADS filters' altitudes, main-filter ĥ: " + ", ".join(
        f"{LABEL[m]} max {table[m]['filter_altitude_m']['max']:.2f} std {table[m]['filter_altitude_m']['std']:.2f}"
        for m in methods if m != "gnss-ins"))
    how = "eq. 4" if cfg["filter"]["fusion"] == "eq4" else "per-epoch inverse-variance combination"
    lines.append(f"  FADS filters' altitudes, pre-fused h_GF ({how}): " + ", ".join(
        f"{LABEL[m]} max {table[m]['prefused_altitude_m']['max']:.2f} std {table[m]['prefused_altitude_m']['std']:.2f}"
        for m in methods if "prefused_altitude_m" in table[m]))
    lines.append("  mean NEES per state (e²/P, 1 = consistent): " + ", ".join(
        f"{LABEL[m]} {table[m]['nees_mean']:.2f}" for m in methods))
    r0 = runs[0]
    lines += ["", f"Table 2 (one run, seed {r0['seed']}) — ours | paper"]
    for row in ROWS:
        for m in methods:
            s = r0["methods"][m][row]
            p = PAPER_TABLE2.get(m, {}).get(row)
            ptxt = f"| paper max {p[0]:.{nd[row]}f} std {p[1]:.{nd[row]}f}" if p else ""
            lines.append(f"  {ROW_LABEL[row]:<15} {LABEL[m]:<19} max {s['max']:10.{nd[row]}f} std {s['std']:9.{nd[row]}f} {ptxt}")
    checks = acceptance(table)
    lines += ["", "checks: " + ", ".join(f"{k} {'yes' if v else 'NO'}" for k, v in checks.items() if isinstance(v, bool))]
    if "ckf_beats_gnss_ins_rows" in checks:
        lines.append("  FADS CKF < GNSS/INS: " + "; ".join(
            f"{r} max {'yes' if v['max'] else 'no'} std {'yes' if v['std'] else 'no'}"
            for r, v in checks["ckf_beats_gnss_ins_rows"].items()))
    if "ckf_vs_ekf" in checks:
        lines.append("  CKF vs EKF (smaller figure): " + "; ".join(
            f"{r} max {v['max']} std {v['std']}" for r, v in checks["ckf_vs_ekf"].items()))
    lines.append("runtime per run, wall [CPU] (s): " + ", ".join(
        f"{m} {table[m]['runtime_s']:.2f} [{table[m]['cpu_s']:.2f}]" for m in methods))
    js = {"scenario": cfg["name"], "seed": runs[0]["seed"], "runs": len(runs), "version": __version__,
          "methods": {m: {**{row: {"max": table[m][row]["max"], "std": table[m][row]["std"],
                                   "std_run_mean": table[m][row]["std_run_mean"],
                                   "max_settled": table[m][row]["max_settled"]}
                             for row in ROWS + ("filter_altitude_m", "prefused_altitude_m") if row in table[m]},
                          "nees_mean": table[m]["nees_mean"], "runtime_s": table[m]["runtime_s"],
                          "cpu_s": table[m]["cpu_s"]} for m in methods},
          "checks": checks}
    return {"text": "\n".join(lines), "json": json_clean(js), "table": table}


def acceptance(table):
    """Issue checks, per row and overall: the FADS CKF beats GNSS/INS (max and std); every figure is
    ≤ 2 × the paper's; and which of CKF / EKF has the smaller figure (ties within 0.5 % are "tie")."""
    out = {}
    stats = ("max", "std")
    if "fads-ckf" in table and "gnss-ins" in table:
        rows = {r: {k: bool(table["fads-ckf"][r][k] < table["gnss-ins"][r][k]) for k in stats} for r in ROWS}
        out["ckf_beats_gnss_ins_rows"] = rows
        out["ckf_beats_gnss_ins"] = all(v for d in rows.values() for v in d.values())
    within = {m: {r: {k: bool(table[m][r][k] <= 2.0 * PAPER_TABLE3[m][r][i]) for i, k in enumerate(stats)}
                  for r in ROWS} for m in table}
    out["within_2x_of_paper_rows"] = within
    out["within_2x_of_paper"] = all(v for d in within.values() for e in d.values() for v in e.values())
    if "fads-ckf" in table and "fads-ekf" in table:
        def winner(r, k):
            c, e = table["fads-ckf"][r][k], table["fads-ekf"][r][k]
            return "tie" if abs(c - e) <= 0.005 * max(c, e) else ("ckf" if c < e else "ekf")
        out["ckf_vs_ekf"] = {r: {k: winner(r, k) for k in stats} for r in ROWS}
    return out


# ------------------------------------------------------------------ outputs

def write_outputs(cfg, runs, summary, out_dir, plots):
    out_dir = Path(out_dir)
    table = summary["table"]
    js = dict(summary["json"])
    js["config"] = cfg
    js["paper_table3"] = PAPER_TABLE3
    js["paper_table2"] = PAPER_TABLE2
    js["per_run"] = [{"seed": r["seed"], "methods": {m: {row: {"max": v[row]["max"], "std": v[row]["std"]}
                                                          for row in ROWS} | {"runtime_s": v["runtime_s"],
                                                                               "nis_mean": v["nis_mean"]}
                                                      for m, v in r["methods"].items()}} for r in runs]
    mpath = out_dir / "metrics.json"
    write_text_atomic(mpath, json.dumps(json_clean(js), indent=2))
    hpath = out_dir / "results.h5"
    with h5_atomic(hpath) as f:
        f.attrs["version"] = __version__
        f.attrs["config_json"] = json.dumps(cfg)
        f.attrs["rows"] = ",".join(ROWS)
        f.attrs["seeds"] = np.array([r["seed"] for r in runs])
        for m in table:
            g = f.create_group(m)
            for row in ROWS:
                g.create_dataset(f"max_per_run/{row}", data=np.array(table[m][row]["max_per_run"]))
            g.create_dataset("errors_1hz_first_run", data=runs[0]["series_1hz"][m])
            g["errors_1hz_first_run"].attrs["columns"] = ",".join(ROWS)
    figs = _figures(table, out_dir) if plots else []
    return {"metrics_path": str(mpath), "h5_path": str(hpath), "figures": figs}


def _figures(table, out_dir):
    """Histograms of per-run maxima like the paper's Figs. 6–8 (skipped without matplotlib)."""
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return []
    figs = []
    for row, fig_no in (("aoa_deg", 6), ("sideslip_deg", 7), ("mach", 8)):
        fig, ax = plt.subplots(figsize=(6, 4))
        data = [np.array(table[m][row]["max_per_run"]) for m in table]
        bins = np.linspace(0.0, max(d.max() for d in data) * 1.05, 25)
        for m, d in zip(table, data):
            ax.hist(d, bins=bins, alpha=0.5, label=LABEL[m])
        ax.set_xlabel(f"per-run max |error| {ROW_LABEL[row]}")
        ax.set_ylabel("runs")
        ax.set_title(f"paper-fads (cf. paper Fig. {fig_no})")
        ax.legend()
        p = out_dir / f"fig{fig_no}_max_{row}.png"
        try:
            savefig_atomic(fig, p, dpi=100)
        finally:
            plt.close(fig)
        figs.append(str(p))
    return figs
