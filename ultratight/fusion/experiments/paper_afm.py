"""The experiments of Sun et al. 2012 (§4.1–4.3): UKF / AFF-AUKF / AFM-AUKF on a simulated SINS/GPS run.

Scenarios ``paper-afm-jump`` (4.1: static base; at ``fault.t_s`` the filters' roll and pitch are
moved by ``fault.roll_pitch_deg``), ``paper-afm-noise`` (4.2: swinging base; from ``fault.t_s`` the
gyro and accelerometer white-noise variances of the *data* are multiplied by
``fault.gyro_var_factor`` / ``fault.accel_var_factor``; the filters' Q is unchanged) and
``paper-afm-accel`` (4.3: the same, accelerometer only).  All three share this module
(``experiment = "paper-afm"``).

Per seed: the trajectory (``[trajectory]``, :func:`ultratight.ins.trajectory.build_trajectory`), the
IMU increments (exact, :func:`ultratight.ins.imu.ideal_increments`) with the sensor errors of
``[imu]`` (:func:`ultratight.ins.imu.imu_errors_from_config`), the noise jump, GPS position and
velocity at ``gps.rate_hz`` with white noise, and an initial error drawn from P0.  Each method
(``ukf``, ``aff``, ``afm``, and ``ekf`` on request) runs on identical data.  Attitude error =
estimated − true Euler angle (wrapped), sampled at ``output_rate_hz``; Table 1 reports its mean and
standard deviation per axis over the whole run (the paper's window is not given; also after the
fault), the paper-style reductions ``1 − |x_filter| / |x_UKF|`` averaged over the axes (this project's reading),
and for the jump the time after the fault from which roll and pitch stay within
``recovery_deg`` of the truth.
"""

from __future__ import annotations

import json
import math
import time

import numpy as np

from ultratight import __version__
from ultratight.errors import ConfigError
from ultratight.io_guard import h5_atomic, savefig_atomic, write_text_atomic
from ultratight.fusion.estimators.quat_aukf import (ATT, BG, N_ERR, POS, VEL, NavModel, Nominal, QuatAUKF, QuatEKF,
                                         euler_from_q_nb, process_noise, q_nb_from_euler, C_nb_from_C_lb)
from ultratight.ins.attitude import dcm_to_quat, rotvec_to_quat, quat_mult, quat_normalize
from ultratight.ins.imu import (DPH_TO_RADPS, DPRH_TO_RADPRS, apply_errors, ideal_increments,
                                imu_errors_from_config)
from ultratight.ins.trajectory import build_trajectory
from ultratight.io_guard import json_clean
from ultratight.config import check_known_keys, check_number

METHODS = ("ukf", "aff", "afm", "ekf")
DEFAULT_METHODS = ("ukf", "aff", "afm")
LABELS = {"ukf": "UKF", "aff": "AFF-AUKF", "afm": "AFM-AUKF", "ekf": "EKF"}
AXES = ("roll", "pitch", "yaw")

# Sun et al. 2012, Table 1 (degrees) and the §4 reductions
PAPER_TABLE1 = {
    "4.1": {"mean": {"ukf": [-0.329, -0.176, -0.153], "aff": [-0.168, -0.053, -0.130], "afm": [-0.045, -0.031, 0.029]},
            "std": {"ukf": [1.352, 0.962, 0.690], "aff": [0.994, 0.567, 0.485], "afm": [0.709, 0.399, 0.286]}},
    "4.2": {"mean": {"ukf": [0.070, 0.100, 0.047], "aff": [-0.030, 0.030, -0.030], "afm": [-0.024, 0.019, 0.015]},
            "std": {"ukf": [1.715, 0.474, 2.055], "aff": [0.678, 0.194, 0.841], "afm": [0.112, 0.070, 0.141]}},
    "4.3": {"mean": {"ukf": [0.064, -0.122, 0.067], "aff": [0.061, -0.104, 0.066], "afm": [-0.025, 0.022, -0.025]},
            "std": {"ukf": [1.361, 0.440, 1.552], "aff": [1.319, 0.431, 1.512], "afm": [0.099, 0.070, 0.124]}},
}
PAPER_REDUCTION = {  # percent, (mean, std), AFF and AFM vs UKF
    "4.1": {"aff": (44.6, 32.4), "afm": (83.2, 54.9)},
    "4.2": {"aff": (54.4, 59.6), "afm": (71.6, 90.6)},
    "4.3": {"aff": (7.0, 2.6), "afm": (78.3, 88.1)},
}

_TOP = ("experiment", "name", "description", "paper_experiment", "seed", "duration_s", "output_rate_hz",
        "recovery_deg", "site", "trajectory", "imu", "gps", "fault", "filter")
_SITE = ("lat_deg", "lon_deg", "h_m")
_GPS = ("rate_hz", "pos_sigma_m", "vel_sigma_mps")
_FAULT = ("kind", "t_s", "roll_pitch_deg", "gyro_var_factor", "accel_var_factor")
_FILTER = ("alpha", "beta", "kappa", "chi2_alpha", "gyro_arw_dprh", "accel_vrw_mps_rh", "gyro_bias_rw_dph_rs",
           "init_att_sigma_deg", "init_vel_sigma_mps", "init_pos_sigma_m", "init_gyro_bias_sigma_dph")
FAULT_KINDS = ("attitude-jump", "noise-jump", "none")

DEFAULTS = {
    "seed": 1, "duration_s": 300.0, "output_rate_hz": 10.0, "recovery_deg": 1.0,
    "site": {"lat_deg": 45.75, "lon_deg": 126.63, "h_m": 150.0},
    "trajectory": {"kind": "static"},
    "imu": {"rate_hz": 100.0, "gyro_bias_dph": 10.0, "gyro_arw_dprh": 0.2, "accel_bias_ug": 1000.0,
            "accel_vrw_ugrhz": 0.1 / 60.0 / 9.80665e-6},   # 0.1 m/s/√h
    "gps": {"rate_hz": 1.0, "pos_sigma_m": 3.0, "vel_sigma_mps": 0.1},
    "fault": {"kind": "none", "t_s": 30.0, "roll_pitch_deg": -10.0, "gyro_var_factor": 1.0, "accel_var_factor": 1.0},
    "filter": {"alpha": 1.0, "beta": 2.0, "kappa": 0.0, "chi2_alpha": 0.01, "gyro_arw_dprh": 0.2,
               "accel_vrw_mps_rh": 0.1, "gyro_bias_rw_dph_rs": 0.01, "init_att_sigma_deg": [1.0, 1.0, 2.0],
               "init_vel_sigma_mps": 0.1, "init_pos_sigma_m": 3.0, "init_gyro_bias_sigma_dph": 10.0},
}


# --------------------------------------------------------------------------- configuration


def _num(value, field, lo=None, hi=None, lo_open=False):
    return float(check_number(value, field, lo=lo, hi=hi, lo_open=lo_open))


def _merge(raw, key):
    tab = raw.get(key, {})
    if not isinstance(tab, dict):
        raise ConfigError(f"[{key}] must be a table")
    out = dict(DEFAULTS[key])
    out.update(tab)
    return out


def load(path, raw, overrides):
    """Complete and validate a paper-afm scenario (unknown keys are ConfigError with did-you-mean)."""
    check_known_keys(raw, _TOP, "scenario")
    cfg = {"experiment": "paper-afm", "name": raw.get("name", str(path)),
           "paper_experiment": str(raw.get("paper_experiment", ""))}
    for k in ("seed", "duration_s", "output_rate_hz", "recovery_deg"):
        cfg[k] = raw.get(k, DEFAULTS[k])
    cfg.update({k: v for k, v in (overrides or {}).items()})
    cfg["seed"] = int(_num(cfg["seed"], "seed", lo=0))
    cfg["duration_s"] = _num(cfg["duration_s"], "duration_s", lo=0, lo_open=True)
    cfg["output_rate_hz"] = _num(cfg["output_rate_hz"], "output_rate_hz", lo=0, lo_open=True)
    cfg["recovery_deg"] = _num(cfg["recovery_deg"], "recovery_deg", lo=0, lo_open=True)
    site = _merge(raw, "site")
    check_known_keys(site, _SITE, "site")
    _num(site["lat_deg"], "site.lat_deg", -90, 90)
    _num(site["lon_deg"], "site.lon_deg", -180, 360)
    _num(site["h_m"], "site.h_m", -1e4, 1e5)
    cfg["site"] = site
    cfg["trajectory"] = dict(raw.get("trajectory", DEFAULTS["trajectory"]))
    if cfg["trajectory"].get("kind", "static") not in ("static", "swing"):
        raise ConfigError(f"trajectory.kind must be 'static' or 'swing' for this experiment (a base at one "
                          f"site), got {cfg['trajectory'].get('kind')!r}")
    imu = _merge(raw, "imu")
    given = raw.get("imu", {}) if isinstance(raw.get("imu", {}), dict) else {}
    # a per-sample noise given in the scenario replaces the default random-walk form (ultratight.ins.imu)
    for per_sample, walk in (("gyro_noise_dph", "gyro_arw_dprh"), ("accel_noise_ug", "accel_vrw_ugrhz")):
        if per_sample in given and walk not in given:
            imu.pop(walk, None)
    imu_errors_from_config(imu)                                   # validates the [imu] keys and values
    _num(imu["rate_hz"], "imu.rate_hz", lo=0, lo_open=True)
    cfg["imu"] = imu
    gps = _merge(raw, "gps")
    check_known_keys(gps, _GPS, "gps")
    _num(gps["rate_hz"], "gps.rate_hz", lo=0, lo_open=True)
    if not float(imu["rate_hz"]) / float(gps["rate_hz"]) == round(float(imu["rate_hz"]) / float(gps["rate_hz"])):
        raise ConfigError(f"gps.rate_hz must divide imu.rate_hz ({imu['rate_hz']}), got {gps['rate_hz']}")
    _num(gps["pos_sigma_m"], "gps.pos_sigma_m", lo=0, lo_open=True)
    _num(gps["vel_sigma_mps"], "gps.vel_sigma_mps", lo=0, lo_open=True)
    cfg["gps"] = gps
    fault = _merge(raw, "fault")
    check_known_keys(fault, _FAULT, "fault")
    if fault["kind"] not in FAULT_KINDS:
        raise ConfigError(f"fault.kind must be one of {', '.join(FAULT_KINDS)}, got {fault['kind']!r}")
    _num(fault["t_s"], "fault.t_s", lo=0)
    _num(fault["roll_pitch_deg"], "fault.roll_pitch_deg", -90, 90)
    _num(fault["gyro_var_factor"], "fault.gyro_var_factor", lo=0, lo_open=True)
    _num(fault["accel_var_factor"], "fault.accel_var_factor", lo=0, lo_open=True)
    if fault["kind"] != "none" and not float(fault["t_s"]) < cfg["duration_s"]:
        raise ConfigError(f"duration_s (--duration) {cfg['duration_s']:g} s ends before the {fault['kind']} at "
                          f"fault.t_s = {fault['t_s']:g} s: the metrics after it need a duration > {fault['t_s']:g} s")
    cfg["fault"] = fault
    flt = _merge(raw, "filter")
    check_known_keys(flt, _FILTER, "filter")
    for k in ("alpha", "gyro_arw_dprh", "accel_vrw_mps_rh", "gyro_bias_rw_dph_rs", "init_vel_sigma_mps",
              "init_pos_sigma_m", "init_gyro_bias_sigma_dph"):
        _num(flt[k], f"filter.{k}", lo=0, lo_open=True)
    _num(flt["beta"], "filter.beta")
    _num(flt["kappa"], "filter.kappa")
    _num(flt["chi2_alpha"], "filter.chi2_alpha", lo=0, lo_open=True, hi=0.999)
    att = flt["init_att_sigma_deg"]
    if not (isinstance(att, list) and len(att) == 3):
        raise ConfigError(f"filter.init_att_sigma_deg must be a list of 3 numbers, got {att!r}")
    for i, a in enumerate(att):
        _num(a, f"filter.init_att_sigma_deg[{i}]", lo=0, lo_open=True)
    cfg["filter"] = flt
    build_trajectory(cfg["trajectory"], cfg["site"], cfg["duration_s"])   # validates the trajectory table
    return cfg


# --------------------------------------------------------------------------- simulation


def _enu_to_ned(a):
    a = np.asarray(a, float)
    return np.stack([a[..., 1], a[..., 0], -a[..., 2]], axis=-1)


def simulate(cfg, seed):
    """Truth, IMU (FRD increments) and GPS of one seed; all draws from ``numpy.random.default_rng(seed)``."""
    rng = np.random.default_rng(seed)
    site = cfg["site"]
    traj = build_trajectory(cfg["trajectory"], site, cfg["duration_s"])
    rate = float(cfg["imu"]["rate_hz"])
    dt = 1.0 / rate
    n = int(math.floor(cfg["duration_s"] * rate + 1e-9))
    edges = np.arange(n + 1) * dt
    dth, dv = ideal_increments(traj, edges)
    errors = imu_errors_from_config(cfg["imu"])
    dth, dv = apply_errors(dth, dv, errors, rng, dt)
    fault = cfg["fault"]
    if fault["kind"] == "noise-jump":
        # variance × factor from t_s on: add white noise of variance (factor − 1) σ² (§4.2/4.3)
        k0 = int(math.ceil(fault["t_s"] * rate - 1e-9))
        m = n - k0
        for arr, sig, fac in ((dth, errors.gyro_arw, fault["gyro_var_factor"]),
                              (dv, errors.accel_vrw, fault["accel_var_factor"])):
            extra = math.sqrt(max(fac - 1.0, 0.0))
            if m > 0 and extra > 0:
                arr[k0:] += rng.standard_normal((m, 3)) * (sig * math.sqrt(dt) * extra)
    flip = np.array([1.0, -1.0, -1.0])                 # FLU -> FRD
    k = traj.kinematics(edges)
    truth = {"t": edges, "euler": k["euler"], "pos_n": _enu_to_ned(k["pos_l0"]), "vel_n": _enu_to_ned(k["vel_l"]),
             "C_lb": k["C_lb"]}
    step = int(round(rate / float(cfg["gps"]["rate_hz"])))
    gk = np.arange(step, n + 1, step)
    g = cfg["gps"]
    z = np.hstack([truth["pos_n"][gk] + rng.standard_normal((gk.size, 3)) * g["pos_sigma_m"],
                   truth["vel_n"][gk] + rng.standard_normal((gk.size, 3)) * g["vel_sigma_mps"]])
    return {"traj": traj, "dt": dt, "dtheta": dth * flip, "dv": dv * flip, "truth": truth, "gps_k": gk, "gps_z": z,
            "rng": rng, "model": NavModel.at_site(math.radians(site["lat_deg"]), site["h_m"], dt)}


def filter_setup(cfg, sim):
    """Filter P0, Q, R and the initial nominal state (truth + an error drawn from P0)."""
    f = cfg["filter"]
    dt = sim["dt"]
    p0 = np.concatenate([np.radians(f["init_att_sigma_deg"]), np.full(3, f["init_vel_sigma_mps"]),
                         np.full(3, f["init_pos_sigma_m"]), np.full(3, f["init_gyro_bias_sigma_dph"] * DPH_TO_RADPS)])
    P0 = np.diag(p0 ** 2)
    Q = process_noise(f["gyro_arw_dprh"] * DPRH_TO_RADPRS, f["accel_vrw_mps_rh"] / 60.0,
                      f["gyro_bias_rw_dph_rs"] * DPH_TO_RADPS, dt)
    g = cfg["gps"]
    R = np.diag(np.r_[np.full(3, g["pos_sigma_m"] ** 2), np.full(3, g["vel_sigma_mps"] ** 2)])
    e0 = sim["rng"].standard_normal(N_ERR) * p0
    tr = sim["truth"]
    q_true = dcm_to_quat(C_nb_from_C_lb(tr["C_lb"][0]))
    nom = Nominal(quat_normalize(quat_mult(rotvec_to_quat(e0[ATT].copy()), q_true)),
                  tr["vel_n"][0] + e0[VEL], tr["pos_n"][0] + e0[POS], e0[BG].copy())
    return nom, P0, Q, R


def _wrap(a):
    return (a + np.pi) % (2.0 * np.pi) - np.pi


def run_filter(method, cfg, sim, nom0, P0, Q, R, progress=False):
    """One method over the run: attitude error (rad, (n_out, 3)), its 1σ, times, runtime."""
    model = sim["model"]
    if method == "ekf":
        flt = QuatEKF(model, nom0, P0, Q, R)
    else:
        mode = {"ukf": None, "aff": "aff", "afm": "afm"}[method]
        f = cfg["filter"]
        flt = QuatAUKF(model, nom0, P0, Q, R, mode=mode, chi2_alpha=f["chi2_alpha"], alpha=f["alpha"],
                       beta=f["beta"], kappa=f["kappa"])
    rate = 1.0 / sim["dt"]
    out_step = max(1, int(round(rate / cfg["output_rate_hz"])))
    n = sim["dtheta"].shape[0]
    gps_at = {int(k): i for i, k in enumerate(sim["gps_k"])}
    fault = cfg["fault"]
    k_jump = int(round(fault["t_s"] * rate)) if fault["kind"] == "attitude-jump" else -1
    ks = np.arange(0, n + 1, out_step)
    eul = np.empty((ks.size, 3))
    sig = np.empty((ks.size, 3))
    vel = np.empty((ks.size, 3))
    pos = np.empty((ks.size, 3))
    fades = []
    j = 0
    t0 = time.perf_counter()
    for k in range(n + 1):
        if k > 0:
            flt.predict(sim["dtheta"][k - 1], sim["dv"][k - 1])
            i = gps_at.get(k)
            if i is not None:
                flt.update(sim["gps_z"][i])
                if method in ("aff", "afm"):
                    fd = flt.last["fade"]
                    fades.append(float(np.max(np.diag(fd))) if np.ndim(fd) else float(fd))
        if k == k_jump:
            # 4.1: the filter's roll and pitch jump (this project's choice); P is not told
            e = flt.nom.euler()
            e[0] += math.radians(fault["roll_pitch_deg"])
            e[1] += math.radians(fault["roll_pitch_deg"])
            nn = flt.nom.copy()
            nn.q = q_nb_from_euler(e)
            flt.set_nominal(nn)
        if k % out_step == 0:
            eul[j] = euler_from_q_nb(flt.nom.q)
            sig[j] = np.sqrt(np.diag(flt.P)[ATT])
            vel[j] = flt.nom.v
            pos[j] = flt.nom.p
            j += 1
    runtime = time.perf_counter() - t0
    err = _wrap(eul - sim["truth"]["euler"][ks])
    tr = sim["truth"]
    return {"t": ks * sim["dt"], "att_err": err, "att_sigma": sig, "runtime_s": runtime,
            "vel_err": vel - tr["vel_n"][ks], "pos_err": pos - tr["pos_n"][ks],
            "fade_max": np.asarray(fades), "chart_guard_epochs": int(getattr(flt, "guard_count", 0))}


def recovery_time(t, err, t_fault, tol):
    """Seconds after ``t_fault`` from which |roll| and |pitch| errors stay ≤ tol (nan if never)."""
    bad = (np.abs(err[:, 0]) > tol) | (np.abs(err[:, 1]) > tol)
    after = t >= t_fault
    if not after.any():
        return float("nan")
    idx = np.flatnonzero(bad & after)
    if idx.size == 0:
        return 0.0
    if idx[-1] == t.size - 1:
        return float("nan")
    return float(t[idx[-1] + 1] - t_fault)


def first_within(t, err, t_fault, tol):
    """Seconds after ``t_fault`` to the first sample with |roll| and |pitch| errors ≤ tol (nan if none)."""
    ok = (np.abs(err[:, 0]) <= tol) & (np.abs(err[:, 1]) <= tol) & (t > t_fault)
    idx = np.flatnonzero(ok)
    return float(t[idx[0]] - t_fault) if idx.size else float("nan")


def run_one(cfg, methods, seed, progress=False):
    sim = simulate(cfg, seed)
    nom0, P0, Q, R = filter_setup(cfg, sim)
    out = {"seed": int(seed), "methods": {}}
    t_fault = cfg["fault"]["t_s"]
    tol = math.radians(cfg["recovery_deg"])
    for m in methods:
        r = run_filter(m, cfg, sim, nom0, P0, Q, R, progress)
        t, e = r["t"], r["att_err"]
        post = e[t >= t_fault] if np.any(t >= t_fault) else np.full((1, 3), np.nan)   # nan: no fault in the run
        res = {"att_err_mean_deg": np.degrees(e.mean(axis=0)), "att_err_std_deg": np.degrees(e.std(axis=0)),
               "att_err_mean_after_deg": np.degrees(post.mean(axis=0)),
               "att_err_std_after_deg": np.degrees(post.std(axis=0)),
               "runtime_s": r["runtime_s"], "t": t, "att_err_deg": np.degrees(e),
               "att_sigma_deg": np.degrees(r["att_sigma"]), "fade_max": r["fade_max"],
               "chart_guard_epochs": r["chart_guard_epochs"],
               "vel_err_ned_mps": r["vel_err"], "pos_err_ned_m": r["pos_err"],
               "vel_err_rms_mps": float(np.sqrt(np.mean(np.sum(r["vel_err"] ** 2, axis=1)))),
               "pos_err_rms_m": float(np.sqrt(np.mean(np.sum(r["pos_err"] ** 2, axis=1)))),
               "faded_epochs": int(np.sum(r["fade_max"] > 1.0))}
        if cfg["fault"]["kind"] == "attitude-jump":
            res["recovery_s"] = recovery_time(t, e, t_fault, tol)
            res["first_within_s"] = first_within(t, e, t_fault, tol)
        out["methods"][m] = res
        if progress:
            print(f"  seed {seed} {LABELS[m]}: std {np.round(res['att_err_std_deg'], 3)} deg, "
                  f"{r['runtime_s']:.1f} s", flush=True)
    return out


# --------------------------------------------------------------------------- summary and outputs


def reduction(x_filter, x_ukf):
    """Paper-style reduction (percent): mean over axes of 1 − |x_filter| / |x_UKF| (this project's reading of §4)."""
    a = np.abs(np.asarray(x_filter, float))
    b = np.abs(np.asarray(x_ukf, float))
    return float(100.0 * np.mean(1.0 - a / b))


def summarize(cfg, runs):
    methods = list(runs[0]["methods"])
    exp = cfg.get("paper_experiment", "")
    stats = _method_stats(runs, methods)
    red = _reductions_vs_ukf(runs, methods, stats)
    ordering = _ordering(exp, runs, methods)
    paper = PAPER_TABLE1.get(exp)
    lines = _summary_lines(cfg, exp, runs, methods, stats, red, ordering, paper)
    js = {"scenario": cfg["name"], "seed": runs[0]["seed"], "runs": len(runs),
          "methods": {m: {"att_err_mean_deg": stats[m]["att_err_mean_deg"], "att_err_std_deg": stats[m]["att_err_std_deg"],
                          "runtime_s": stats[m]["runtime_s"]} for m in methods},
          "details": stats, "reduction_vs_ukf": red, "ordering": ordering,
          "paper": {"table1": paper, "reduction": PAPER_REDUCTION.get(exp)},
          "config": cfg, "version": __version__}
    for m in methods:
        if "recovery_s" in stats[m]:
            js["methods"][m]["recovery_s"] = stats[m]["recovery_s_mean"]
    return {"text": "\n".join(lines), "json": json_clean(js)}


def _method_stats(runs, methods):
    """Per method: attitude error mean / std over the runs, run time, velocity / position RMS ..."""
    stats = {}
    for m in methods:
        mean = np.array([r["methods"][m]["att_err_mean_deg"] for r in runs])
        std = np.array([r["methods"][m]["att_err_std_deg"] for r in runs])
        d = {"att_err_mean_deg": mean.mean(axis=0).tolist(), "att_err_std_deg": std.mean(axis=0).tolist(),
             "att_err_std_deg_min": std.min(axis=0).tolist(), "att_err_std_deg_max": std.max(axis=0).tolist(),
             "att_err_mean_after_deg": np.mean([r["methods"][m]["att_err_mean_after_deg"] for r in runs], 0).tolist(),
             "att_err_std_after_deg": np.mean([r["methods"][m]["att_err_std_after_deg"] for r in runs], 0).tolist(),
             "runtime_s": float(np.mean([r["methods"][m]["runtime_s"] for r in runs])),
             "vel_err_rms_mps": float(np.mean([r["methods"][m]["vel_err_rms_mps"] for r in runs])),
             "pos_err_rms_m": float(np.mean([r["methods"][m]["pos_err_rms_m"] for r in runs])),
             "faded_epochs_mean": float(np.mean([r["methods"][m]["faded_epochs"] for r in runs])),
             "chart_guard_epochs_mean": float(np.mean([r["methods"][m]["chart_guard_epochs"] for r in runs])),
             "per_seed_std_deg": {str(r["seed"]): np.asarray(r["methods"][m]["att_err_std_deg"]).tolist() for r in runs}}
        if "recovery_s" in runs[0]["methods"][m]:
            rec = [r["methods"][m]["recovery_s"] for r in runs]
            d["recovery_s"] = rec
            d["recovery_s_mean"] = float(np.mean(rec))
            d["first_within_s"] = [r["methods"][m]["first_within_s"] for r in runs]
        stats[m] = d
    return stats


def _reductions_vs_ukf(runs, methods, stats):
    """Per method: reduction (%) of the attitude error mean / std against the UKF."""
    red = {}
    if "ukf" in methods:
        for m in methods:
            if m == "ukf":
                continue
            rm = [reduction(r["methods"][m]["att_err_mean_deg"], r["methods"]["ukf"]["att_err_mean_deg"]) for r in runs]
            rs = [reduction(r["methods"][m]["att_err_std_deg"], r["methods"]["ukf"]["att_err_std_deg"]) for r in runs]
            red[m] = {"mean_pct": float(np.mean(rm)), "std_pct": float(np.mean(rs)),
                      "std_pct_min": float(np.min(rs)), "std_pct_max": float(np.max(rs)),
                      "of_averaged_table_mean_pct": reduction(stats[m]["att_err_mean_deg"], stats["ukf"]["att_err_mean_deg"]),
                      "of_averaged_table_std_pct": reduction(stats[m]["att_err_std_deg"], stats["ukf"]["att_err_std_deg"])}
    return red


def _summary_lines(cfg, exp, runs, methods, stats, red, ordering, paper):
    """The text tables (Table 1 with the paper's values, reductions, per-seed figures)."""
    lines = [f"{cfg['name']} (Sun et al. 2012 §{exp}): {len(runs)} run(s), "
             f"seeds {runs[0]['seed']}..{runs[-1]['seed']}, "
             f"{cfg['duration_s']:.0f} s at {cfg['imu']['rate_hz']:.0f} Hz, GPS {cfg['gps']['rate_hz']:.0f} Hz",
             f"filter: alpha={cfg['filter']['alpha']} beta={cfg['filter']['beta']} kappa={cfg['filter']['kappa']} "
             f"chi2_alpha={cfg['filter']['chi2_alpha']}; fault: {cfg['fault']}",
             "", "Table 1 — attitude error (deg), mean over runs; paper in brackets",
             f"{'':10s}{'stat':6s}" + "".join(f"{a:>22s}" for a in AXES)]
    for stat in ("mean", "std"):
        for m in methods:
            vals = stats[m][f"att_err_{stat}_deg"]
            cells = []
            for i in range(3):
                pv = paper[stat].get(m) if paper else None
                cells.append(f"{vals[i]:9.3f} [{pv[i]:7.3f}]" if pv else f"{vals[i]:9.3f} [   —   ]")
            lines.append(f"{LABELS[m]:10s}{stat:6s}" + "".join(f"{c:>22s}" for c in cells))
    if red:
        lines += ["", "Reduction vs UKF (%, mean over axes of 1 − |x|/|x_UKF|, averaged over runs); paper in brackets"]
        for m, r in red.items():
            pp = PAPER_REDUCTION.get(exp, {}).get(m)
            lines.append(f"{LABELS[m]:10s} |mean| {r['mean_pct']:7.1f} [{pp[0] if pp else '—'}]   "
                         f"std {r['std_pct']:7.1f} [{pp[1] if pp else '—'}]   (std per seed {r['std_pct_min']:.1f}..{r['std_pct_max']:.1f})")
    lines += ["", "Std per seed (deg, roll/pitch/yaw):"]
    for r in runs:
        lines.append(f"  seed {r['seed']}: " + "  ".join(
            f"{LABELS[m]} " + "/".join(f"{v:.3f}" for v in r["methods"][m]["att_err_std_deg"]) for m in methods))
    if any("recovery_s" in s for s in stats.values()):
        lines += ["", f"Recovery after the jump, s per seed: time from which roll and pitch stay within "
                  f"{cfg['recovery_deg']}° to the end (nan: not within 300 s) / first time within it:"]
        for m in methods:
            lines.append(f"  {LABELS[m]:10s} " + " ".join(f"{v:.1f}" for v in stats[m]["recovery_s"])
                         + f"   mean {stats[m]['recovery_s_mean']:.1f}")
            lines.append(f"  {'':10s} " + " ".join(f"{v:.1f}" for v in stats[m]["first_within_s"]) + "   (first)")
    lines += ["", "Velocity / position error RMS (3D, whole run, mean over runs): " + ", ".join(
        f"{LABELS[m]} {stats[m]['vel_err_rms_mps']:.3f} m/s / {stats[m]['pos_err_rms_m']:.2f} m" for m in methods)]
    lines += ["", "GPS epochs with a fade > 1 / with the chart guard acting (mean per run): " + ", ".join(
        f"{LABELS[m]} {stats[m]['faded_epochs_mean']:.0f} / {stats[m]['chart_guard_epochs_mean']:.0f}" for m in methods)]
    lines += ["", "Runtime per filter (s, mean over runs): " + ", ".join(
        f"{LABELS[m]} {stats[m]['runtime_s']:.1f}" for m in methods)]
    if ordering:
        lines += ["", "Ordering checks (every seed): " + "; ".join(f"{k}: {v}" for k, v in ordering.items())]
    return lines


def _ordering(exp, runs, methods):
    out = {}
    have = set(methods)
    std = {m: np.array([r["methods"][m]["att_err_std_deg"] for r in runs]) for m in methods}
    if exp == "4.2" and {"ukf", "aff", "afm"} <= have:
        out["AFM<AFF<UKF std, every axis"] = bool(np.all((std["afm"] < std["aff"]) & (std["aff"] < std["ukf"])))
    if exp == "4.3" and {"ukf", "aff", "afm"} <= have:
        out["AFM<UKF std, every axis"] = bool(np.all(std["afm"] < std["ukf"]))
        out["AFF within 10% of UKF, every axis"] = bool(np.all(np.abs(std["aff"] / std["ukf"] - 1.0) <= 0.10))
    if exp == "4.1" and {"ukf", "aff", "afm"} <= have:
        rec = {m: np.array([r["methods"][m]["recovery_s"] for r in runs]) for m in ("ukf", "aff", "afm")}
        out["AFM recovers first"] = bool(np.all((rec["afm"] < rec["aff"]) & (rec["afm"] < rec["ukf"])))
    return out


def write_outputs(cfg, runs, summary, out_dir, plots):
    name = str(cfg["name"]).replace("/", "_")
    mpath = out_dir / f"{name}_metrics.json"
    write_text_atomic(mpath, json.dumps(summary["json"], indent=2, allow_nan=False))
    hpath = out_dir / f"{name}_results.h5"
    with h5_atomic(hpath) as f:
        f.attrs["config_json"] = json.dumps(summary["json"]["config"])
        f.attrs["version"] = summary["json"]["version"]
        f.attrs["schema"] = ("per seed group seed_<s>/<method>: t (s), att_err_deg (n,3 roll/pitch/yaw, "
                             "estimate - truth), att_sigma_deg (n,3 filter 1-sigma of the attitude error), "
                             "vel_err_ned_mps, pos_err_ned_m (n,3 estimate - truth, NED), fade_max (per GPS "
                             "epoch: lambda or the largest diagonal of S)")
        for r in runs:
            g = f.create_group(f"seed_{r['seed']}")
            for m, d in r["methods"].items():
                gm = g.create_group(m)
                for key in ("t", "att_err_deg", "att_sigma_deg", "vel_err_ned_mps", "pos_err_ned_m", "fade_max"):
                    gm.create_dataset(key, data=np.asarray(d[key]))
                gm.attrs["runtime_s"] = d["runtime_s"]
    figures = []
    if plots:
        figures = _figures(cfg, runs, out_dir, name)
    return {"metrics_path": str(mpath), "h5_path": str(hpath), "figures": figures}


def _figures(cfg, runs, out_dir, name):
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return []
    r = runs[0]
    figures = []
    panels = (("attitude_error", "att_err_deg", AXES, "error (°)", "attitude error", "Figs. 1, 4, 5"),
              ("velocity_error", "vel_err_ned_mps", ("north", "east", "down"), "error (m/s)", "velocity error", "Fig. 2"),
              ("position_error", "pos_err_ned_m", ("north", "east", "down"), "error (m)", "position error", "Fig. 3"))
    for tag, key, names, unit, title, ref in panels:
        fig, axs = plt.subplots(3, 1, figsize=(8, 7), sharex=True)
        for m, d in r["methods"].items():
            for i in range(3):
                axs[i].plot(d["t"], d[key][:, i], lw=0.8, label=LABELS[m])
        for i, a in enumerate(names):
            axs[i].set_ylabel(f"{a} {unit}")
            axs[i].grid(alpha=0.3)
        axs[0].legend(loc="upper right")
        axs[-1].set_xlabel("t (s)")
        axs[0].set_title(f"{cfg['name']}: {title}, seed {r['seed']} (cf. Sun et al. 2012 {ref})")
        path = out_dir / f"{name}_{tag}.png"
        savefig_atomic(fig, path)
        plt.close(fig)
        figures.append(str(path))
    return figures
