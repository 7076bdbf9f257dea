"""The experiment of Cai et al. 2020 (§4, "paper-robust-flight"): loose SINS/GNSS of a 500-s aircraft
flight with gross errors every 10 s; plain KF, χ² + Newton robust KF (both readings of V) and
INS only, the paper's quoted error ranges and the abstract's 75 % / 80 % beside ours.

Simulation (this project's choices): an aircraft at 3 km, 200 m/s east at the start, with two climbs /
descents and horizontal manoeuvres (``[trajectory]`` segments of constant ENU acceleration, body
x along the velocity); IMU at 100 Hz with gyro constant 0.2 °/h and random walk 0.01 °/√h,
accelerometer constant 0.01 g and random walk 0.01 g/√Hz (constants drawn per axis and run from
N(0, σ²), ``[imu] bias_reading = "sigma"``, the reading the documented figures were measured with;
``"stated"``: the paper's value as the magnitude with a random sign per axis and run; the filters
know the figures, the drawn values are truth); GNSS fixes at 1 Hz = truth + white noise of σ 0.00015° (latitude, longitude), 5 m
(height), 1 km/h (each velocity axis) — ``[gnss] mode = "truth"``, the paper's description; or
``mode = "lsq"``: least-squares fixes of simulated pseudoranges/rates of the nominal constellation.
Gross errors: at t = 10, 20, …, 500 s the noise of all six components becomes V + m·σ·sign V
(``[gross] mode = "add"``, m = ``factor`` = 50 by default: of the factors 5–50 and both readings
the one whose plain-KF error magnitudes come closest to the paper's Figs. 4/6,
:func:`kf_range_distance`) or m·V (``mode = "scale"``, this project's ×20).  R from the GNSS σ, Q
from the IMU specs, P0 matching the drawn initial errors.  ``[filter] weight_replacements`` (on): a
Newton-replaced innovation of the implementable reading enters the update with the variance of
its extrapolation (:class:`ultratight.fusion.estimators.robust.ChiSquareNewton`).

Each seed runs every method on the gross-error data and, for ``kf`` and the χ² cores, on the same
noise without gross errors ("clean": the cost of false alarms and the false-alarm rate), plus the
``[gross] sweep`` factors (kf and chi2-newton only).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from ultratight.errors import ConfigError
from ultratight.fusion.coupling import integration as I
from ultratight.ins import error_model as em
from ultratight.ins.earth import llh_increment_scale, radii
from ultratight.ins.trajectory import build_trajectory
from ultratight.fusion.experiments import sins_gnss as C
from ultratight.fusion.experiments.paper_static_iakf import ephemerides
from ultratight.signals.synth.obssim import GrossErrors, fix_noise_scale, gnss_fixes, simulate_observables

DEFAULT_METHODS = ("kf", "chi2-newton", "chi2-newton-lit", "ins-only")
METHODS = DEFAULT_METHODS
CLEAN_METHODS = ("kf", "chi2-newton", "chi2-newton-lit")
SWEEP_METHODS = ("kf", "chi2-newton")

# Cai et al. 2020, §4.2, ranges read from Figs. 4/6 (plain KF) and the robust filter, full 500 s:
# (min, max) per axis; position E, N, U (m), velocity E, N, U (m/s)
PAPER_RANGES = {
    "kf": {"pos_enu_m": [[-2000, 0], [0, 1000], [0, 200]], "vel_enu_mps": [[0, 2], [-5, 0], [-2, 2]]},
    "chi2-newton": {"pos_enu_m": [[-13, 25], [-10, 26], [-18, 19]],
                    "vel_enu_mps": [[-0.4, 0.6], [-0.8, 1.5], [-1.0, 1.2]]},
}
PAPER_REDUCTION = {"pos": 0.75, "vel": 0.80}

SEGMENTS = [
    {"t0": 0.0, "acc_enu": [0.0, 0.0, 0.0]},
    {"t0": 40.0, "acc_enu": [0.0, 0.0, 2.0]},        # pull up
    {"t0": 50.0, "acc_enu": [0.0, 0.0, 0.0]},        # climb at 20 m/s
    {"t0": 100.0, "acc_enu": [0.0, 0.0, -2.0]},      # level off
    {"t0": 110.0, "acc_enu": [-2.0, 5.0, 0.0]},      # turn to the north-east
    {"t0": 150.0, "acc_enu": [0.0, 0.0, 0.0]},
    {"t0": 200.0, "acc_enu": [3.0, -6.0, 0.0]},      # turn back east, accelerate
    {"t0": 230.0, "acc_enu": [0.0, 0.0, 0.0]},
    {"t0": 280.0, "acc_enu": [0.0, 0.0, -2.0]},      # push over
    {"t0": 290.0, "acc_enu": [0.0, 0.0, 0.0]},       # descend at 20 m/s
    {"t0": 330.0, "acc_enu": [0.0, 0.0, 2.0]},       # level off
    {"t0": 340.0, "acc_enu": [-3.0, -4.0, 0.0]},     # turn to the south-east, slow down
    {"t0": 380.0, "acc_enu": [0.0, 0.0, 0.0]},
    {"t0": 420.0, "acc_enu": [1.0, 4.0, 0.0]},       # turn back
    {"t0": 460.0, "acc_enu": [0.0, 0.0, 0.0]},
]

SCHEMA = {
    "": {"experiment": "paper-robust-flight", "name": "paper-robust-flight", "description": "",
         "duration_s": 500.0, "seed": 1},
    "time": {"week": 2190, "tow_s": 518400.0},
    "receiver": {"lat_deg": 34.25, "lon_deg": 108.95, "h_m": 3000.0},
    "trajectory": {"vel0_enu_mps": [200.0, 0.0, 0.0], "segments": SEGMENTS},
    "imu": {"rate_hz": 100.0, "gyro_bias_dph": 0.2, "gyro_arw_dprh": 0.01, "accel_bias_g": 0.01,
            "accel_vrw_g_rhz": 0.01, "bias_reading": "sigma"},
    "gnss": {"rate_hz": 1.0, "mode": "truth", "sigma_lat_deg": 0.00015, "sigma_lon_deg": 0.00015,
             "sigma_h_m": 5.0, "sigma_vel_mps": 1.0 / 3.6, "sigma_pr_m": 3.0, "sigma_prr_mps": 0.1,
             "mask_deg": 5.0},
    "gross": {"factor": 50.0, "period_s": 10.0, "mode": "add", "components": [0, 1, 2, 3, 4, 5],
              "sweep": [5.0, 10.0, 20.0, 50.0]},
    "initial_errors": {"att_deg": [0.05, 0.05, 0.2], "vel_mps": 0.3, "pos_m": 10.0},
    "filter": {"alpha": 0.01, "delta": 4.0, "newton_guard": True, "release_after": 3,
               "weight_replacements": True},
}


def load(path, raw, overrides):
    cfg = C.tables(raw, SCHEMA, overrides)
    cfg["name"] = raw.get("name", getattr(path, "stem", "paper-robust-flight"))
    cfg["source_file"] = str(path)
    C.num(cfg, "duration_s", "", lo=10.0, hi=C.MAX_DURATION_S)
    C.num(cfg["receiver"], "lat_deg", "receiver", lo=-85.0, hi=85.0)
    C.num(cfg["receiver"], "h_m", "receiver", lo=-1000.0, hi=1e5)
    C.num(cfg["gnss"], "rate_hz", "gnss", lo=0.0, lo_open=True, hi=100.0)
    C.num(cfg["imu"], "rate_hz", "imu", lo=1.0)
    C.bias_reading(cfg["imu"])
    ratio = cfg["imu"]["rate_hz"] / cfg["gnss"]["rate_hz"]
    if abs(ratio - round(ratio)) > 1e-9:
        raise ConfigError("imu.rate_hz must be an integer multiple of gnss.rate_hz")
    for k in ("gyro_bias_dph", "gyro_arw_dprh", "accel_bias_g", "accel_vrw_g_rhz"):
        C.num(cfg["imu"], k, "imu", lo=0.0)
    for k in ("sigma_lat_deg", "sigma_lon_deg", "sigma_h_m", "sigma_vel_mps", "sigma_pr_m", "sigma_prr_mps"):
        C.num(cfg["gnss"], k, "gnss", lo=0.0, lo_open=True)
    if cfg["gnss"]["mode"] not in ("truth", "lsq"):
        raise ConfigError(f"gnss.mode must be 'truth' or 'lsq', got {cfg['gnss']['mode']!r}")
    g = cfg["gross"]
    C.num(g, "factor", "gross", lo=0.0)
    C.num(g, "period_s", "gross", lo=0.0, lo_open=True)
    comps = g["components"]
    if not isinstance(comps, list) or not all(isinstance(c, int) and 0 <= c < 6 for c in comps):
        raise ConfigError(f"gross.components must be a list of indices 0..5 (lat, lon, h, vE, vN, vU), got {comps!r}")
    if not isinstance(g["sweep"], list) or not all(isinstance(v, (int, float)) and v >= 0 for v in g["sweep"]):
        raise ConfigError(f"gross.sweep must be a list of factors >= 0, got {g['sweep']!r}")
    GrossErrors(float(g["factor"]), float(g["period_s"]), tuple(comps), g["mode"])     # validates mode
    C.num(cfg["filter"], "alpha", "filter", lo=0.0, lo_open=True, hi=0.5)
    C.num(cfg["filter"], "delta", "filter", lo=0.0, lo_open=True)
    C.num(cfg["filter"], "release_after", "filter", lo=0, integer=True)
    for k in ("newton_guard", "weight_replacements"):
        if not isinstance(cfg["filter"][k], bool):
            raise ConfigError(f"filter.{k} must be true or false, got {cfg['filter'][k]!r}")
    return cfg


def _gross(cfg, factor=None):
    g = cfg["gross"]
    return GrossErrors(float(g["factor"] if factor is None else factor), float(g["period_s"]),
                       tuple(g["components"]), g["mode"])


def simulate(cfg, seed):
    """Truth, IMU, clean fix noise (σ units) and initial errors of one seed."""
    rng = np.random.default_rng(seed)
    dur = float(cfg["duration_s"])
    tr = cfg["trajectory"]
    traj = build_trajectory({"kind": "segments", "attitude": "velocity", "vel0_enu_mps": tr["vel0_enu_mps"],
                             "segments": tr["segments"]}, cfg["receiver"], dur)
    im = cfg["imu"]
    rate = float(im["rate_hz"])
    imu, bias_true = C.draw_imu(traj, rate, im["gyro_bias_dph"] * C.DPH, math.radians(im["gyro_arw_dprh"]) / 60.0,
                                im["accel_bias_g"] * C.G0, im["accel_vrw_g_rhz"] * C.G0, rng,
                                im["bias_reading"])
    g = cfg["gnss"]
    dt = 1.0 / float(g["rate_hz"])
    t_gnss = np.arange(1, int(math.floor(dur / dt + 1e-9)) + 1) * dt
    k = traj.kinematics(t_gnss)
    sig_llh = (math.radians(g["sigma_lat_deg"]), math.radians(g["sigma_lon_deg"]), g["sigma_h_m"])
    sig_vel = np.full(3, g["sigma_vel_mps"])
    data = {"t": t_gnss, "llh": k["llh"], "vel": k["vel_l"], "sig_llh": sig_llh, "sig_vel": sig_vel}
    if g["mode"] == "truth":
        data["unit_noise"] = rng.standard_normal((t_gnss.size, 6))      # in σ units; gross errors applied per run
    else:
        data["obs_rng_state"] = rng.bit_generator.state
        data["ephs"] = ephemerides({"satellites": {"source": "nominal"}, "time": cfg["time"]})
        data["pos_e"], data["vel_e"] = k["pos_e"], k["vel_e"]
        data["obs_seed"] = int(rng.integers(2**31))
    ie = cfg["initial_errors"]
    k0 = traj.kinematics(np.zeros(1))
    att = rng.standard_normal(3) * np.radians(np.broadcast_to(np.asarray(ie["att_deg"], float), (3,)))
    vel = rng.standard_normal(3) * ie["vel_mps"]
    pos = rng.standard_normal(3) * ie["pos_m"]
    x0 = I.initial_state(k0["q_lb"][0], k0["vel_l"][0], k0["llh"][0], att, vel, pos)
    inp = I.RunInput(t_imu=np.concatenate([[0.0], imu.t]), dtheta=imu.dtheta_b, dv=imu.dv_b, t_gnss=t_gnss,
                     truth_llh=k["llh"], truth_vel=k["vel_l"], truth_q=k["q_lb"], bias_true=bias_true, x0_est=x0)
    return inp, data


def fixes(cfg, data, factor):
    """GNSS fixes (llh, vel, noise) with gross errors of ``factor`` (0 or 1 → none: 'clean')."""
    n = data["t"].size
    gross = None if factor in (None, 1.0) else _gross(cfg, factor)
    if cfg["gnss"]["mode"] == "truth":
        u = data["unit_noise"] if gross is None else gross.apply(data["t"], data["unit_noise"], np.ones(6))
        noise = u * fix_noise_scale(n, data["sig_llh"], data["sig_vel"])
        return data["llh"] + noise[:, :3], data["vel"] + noise[:, 3:], noise
    g = cfg["gnss"]
    rng = np.random.default_rng(data["obs_seed"])
    og = None if gross is None else replace(gross, components=(0, 1))
    obs = simulate_observables(data["ephs"], int(cfg["time"]["week"]), float(cfg["time"]["tow_s"]), data["t"],
                               data["pos_e"], data["vel_e"], 0.0, 0.0, rng, g["sigma_pr_m"], g["sigma_prr_mps"],
                               g["mask_deg"], og)
    obs.info["pos0_e"] = data["pos_e"][0]
    return gnss_fixes("lsq", rng, data["llh"], data["vel"], None, None, obs=obs)


def noise_model(cfg, llh0):
    """(q_psd, R (6x6, metres N/E/U and m/s), P0) of the filters: R from the GNSS σ, Q from the IMU
    specs, P0 from the initial-error σ (this project's choices)."""
    im, g, ie = cfg["imu"], cfg["gnss"], cfg["initial_errors"]
    q = I.imu_psd(math.radians(im["gyro_arw_dprh"]) / 60.0, im["accel_vrw_g_rhz"] * C.G0, n_states=em.N15)
    rm, rn = radii(float(llh0[0]))
    h = float(llh0[2])
    s_n, s_e, _ = llh_increment_scale(float(llh0[0]), h, rm, rn)
    sn = math.radians(g["sigma_lat_deg"]) * s_n
    se = math.radians(g["sigma_lon_deg"]) * s_e
    R = np.diag([sn ** 2, se ** 2, g["sigma_h_m"] ** 2] + [g["sigma_vel_mps"] ** 2] * 3)
    P0 = C.initial_P(em.N15, np.radians(np.broadcast_to(np.asarray(ie["att_deg"], float), (3,))), ie["vel_mps"],
                     ie["pos_m"], im["gyro_bias_dph"] * C.DPH, im["accel_bias_g"] * C.G0)
    return q, R, P0


def run_method(cfg, method, inp, fx):
    q, R, P0 = noise_model(cfg, inp.truth_llh[0])
    f = cfg["filter"]
    core = I.make_core(method, P0, None, R, alpha=float(f["alpha"]), delta=float(f["delta"]),
                       newton_guard=bool(f["newton_guard"]), release_after=int(f["release_after"]) or None,
                       weight_replacements=bool(f["weight_replacements"]))
    meas = I.loose_measurement_fn(fx[0], fx[1], fx[2], R)
    return I.run_integration("loose", core, inp, meas, q)


def _series(res):
    return {"t": res["t"], "err": res["err"], "sigma": res["sigma"], "nees": res["nees"], "n_faulty": res["n_faulty"]}


def run_one(cfg, methods, seed, progress=False):
    inp, data = simulate(cfg, seed)
    out = {"seed": int(seed), "methods": {}, "series": {}, "clean": {}, "sweep": {}}
    fx_g = fixes(cfg, data, float(cfg["gross"]["factor"]))
    fx_c = fixes(cfg, data, None)
    for m in methods:
        res = run_method(cfg, m, inp, fx_g)
        out["methods"][m] = C.run_metrics(res, em.N15)
        out["series"][m] = _series(res)
        if m in CLEAN_METHODS:
            rc = run_method(cfg, m, inp, fx_c)
            out["clean"][m] = C.run_metrics(rc, em.N15)
        if progress:
            mm = out["methods"][m]
            print(f"  seed {seed} {m:16s} pos rms {np.round(mm['pos_rms_m'], 2)}  vel rms {np.round(mm['vel_rms_mps'], 3)}"
                  f"  {mm['runtime_s']:.2f} s", flush=True)
    for fac in cfg["gross"]["sweep"]:
        fx = fixes(cfg, data, float(fac))
        for m in SWEEP_METHODS:
            if m in methods:
                out["sweep"][f"{float(fac):g}/{m}"] = C.run_metrics(run_method(cfg, m, inp, fx), em.N15)
    return out


def kf_range_distance(pos_max_neu, vel_max_enu):
    """How far the plain KF's error magnitudes are from the paper's Figs. 4/6: mean over the six axes
    of |ln(ours / paper)|, ours the max |error| per axis (position N, E, U; velocity E, N, U), the
    paper's the extent of its quoted KF ranges (``PAPER_RANGES["kf"]``).  The criterion that fixes
    the gross-error factor and reading (docs/integration-experiments.md); 0 = the same magnitudes.
    Returns (all six, position three, velocity three)."""
    pe = [max(abs(a), abs(b)) for a, b in PAPER_RANGES["kf"]["pos_enu_m"]]
    pv = [max(abs(a), abs(b)) for a, b in PAPER_RANGES["kf"]["vel_enu_mps"]]
    dp = np.abs(np.log(np.asarray(pos_max_neu, float) / np.array([pe[1], pe[0], pe[2]])))
    dv = np.abs(np.log(np.asarray(vel_max_enu, float) / np.array(pv)))
    return float(np.mean(np.concatenate([dp, dv]))), float(dp.mean()), float(dv.mean())


def _reduction(a_kf, a_rob):
    """1 − RMS(robust)/RMS(kf) of the 3-D position and velocity RMS (the abstract's stand-in)."""
    def norm(v):
        return float(np.sqrt(np.sum(np.asarray(v) ** 2)))
    return {"pos": 1.0 - norm(a_rob["pos_rms_m"]) / norm(a_kf["pos_rms_m"]),
            "vel": 1.0 - norm(a_rob["vel_rms_mps"]) / norm(a_kf["vel_rms_mps"]),
            "pos_per_axis": (1.0 - np.asarray(a_rob["pos_rms_m"]) / np.asarray(a_kf["pos_rms_m"])).tolist(),
            "vel_per_axis": (1.0 - np.asarray(a_rob["vel_rms_mps"]) / np.asarray(a_kf["vel_rms_mps"])).tolist()}


def summarize(cfg, runs):
    methods = list(runs[0]["methods"])
    agg = C.aggregate(runs, methods)
    L = _range_table(cfg, runs, agg, methods)
    L += _rms_table(agg, methods)
    red = _reductions(L, agg, runs)
    clean = _clean_summary(L, cfg, runs)
    sweep = _sweep_summary(L, runs)
    js = {"scenario": cfg["name"], "seed": int(runs[0]["seed"]), "runs": len(runs),
          "axis_order": {"vel_rms_mps": "E, N, U", "pos_rms_m": "N, E, U", "pos_max_m": "N, E, U (max |error|)",
                         "vel_max_mps": "E, N, U (max |error|)"},
          "gross": {k: cfg["gross"][k] for k in ("factor", "period_s", "mode", "components")},
          "methods": C.json_methods(agg), "rms_reduction_vs_kf": red, "paper_reduction": PAPER_REDUCTION,
          "clean": clean, "sweep": sweep, "paper_ranges_enu": PAPER_RANGES,
          "ranges_min_max": {m: {"pos_neu_m": [agg[m]["pos_min_signed_m"].tolist(), agg[m]["pos_max_signed_m"].tolist()],
                                 "vel_enu_mps": [agg[m]["vel_min_signed_mps"].tolist(), agg[m]["vel_max_signed_mps"].tolist()]}
                             for m in methods}}
    return {"text": "\n".join(L), "json": C.json_clean(js)}


def _range_table(cfg, runs, agg, methods):
    """Text lines: min..max of the signed position / velocity errors per method (and the paper's)."""
    fac = cfg["gross"]["factor"]
    L = [f"paper-robust-flight (Cai et al. 2020): {len(runs)} run(s), seeds {runs[0]['seed']}..{runs[-1]['seed']}; "
         f"gross errors x{fac:g} ({cfg['gross']['mode']}) every {cfg['gross']['period_s']:g} s; GNSS {cfg['gnss']['mode']}",
         "position N, E, U (m), velocity E, N, U (m/s); min..max over all seeds and epochs",
         f"{'method':16s} {'pos N':>15s} {'pos E':>15s} {'pos U':>15s} {'vel E':>13s} {'vel N':>13s} {'vel U':>13s}"]
    for m in methods:
        a = agg[m]
        cells = [f"{lo:7.1f}..{hi:<6.1f}" for lo, hi in zip(a["pos_min_signed_m"], a["pos_max_signed_m"])]
        cells += [f"{lo:6.2f}..{hi:<5.2f}" for lo, hi in zip(a["vel_min_signed_mps"], a["vel_max_signed_mps"])]
        L.append(f"{m:16s} " + " ".join(cells))
        if m in PAPER_RANGES:
            p = PAPER_RANGES[m]
            pe = p["pos_enu_m"]
            ve = p["vel_enu_mps"]
            cells = [f"{pe[i][0]:7.0f}..{pe[i][1]:<6.0f}" for i in (1, 0, 2)]   # paper E, N, U -> our N, E, U
            cells += [f"{ve[i][0]:6.1f}..{ve[i][1]:<5.1f}" for i in range(3)]
            L.append(f"{'  paper':16s} " + " ".join(cells))
    return L


def _rms_table(agg, methods):
    """Text lines: RMS errors, NEES band fraction, false-alarm rate and run time per method."""
    L = []
    L.append("")
    L.append(f"{'RMS':16s} {'pos N':>8s}{'pos E':>8s}{'pos U':>8s}{'vel E':>8s}{'vel N':>8s}{'vel U':>8s}"
             f"{'NEES95':>8s}{'FA rate':>9s}{'time s':>8s}")
    for m in methods:
        a = agg[m]
        fa = a.get("false_alarm_rate", np.nan)
        L.append(f"{m:16s} " + "".join(f"{v:8.2f}" for v in a["pos_rms_m"]) + "".join(f"{v:8.3f}" for v in a["vel_rms_mps"])
                 + f"{a['nees_in_band_fraction']:8.3f}{fa:9.4f}{a['runtime_s']:8.2f}")
        L.append(f"{'  seed min':16s} " + "".join(f"{v:8.2f}" for v in a["pos_rms_m_seed_min"])
                 + "".join(f"{v:8.3f}" for v in a["vel_rms_mps_seed_min"]))
        L.append(f"{'  seed max':16s} " + "".join(f"{v:8.2f}" for v in a["pos_rms_m_seed_max"])
                 + "".join(f"{v:8.3f}" for v in a["vel_rms_mps_seed_max"]))
    return L


def _reductions(L, agg, runs):
    """RMS reduction of the robust filters against the KF (appends text lines to ``L``)."""
    red = {}
    for m in ("chi2-newton", "chi2-newton-lit"):
        if m in agg and "kf" in agg:
            red[m] = _reduction(agg["kf"], agg[m])
            per_seed = [_reduction(r["methods"]["kf"], r["methods"][m]) for r in runs]
            red[m]["seed_range_pos"] = [min(p["pos"] for p in per_seed), max(p["pos"] for p in per_seed)]
            red[m]["seed_range_vel"] = [min(p["vel"] for p in per_seed), max(p["vel"] for p in per_seed)]
            L.append(f"RMS reduction {m} vs kf: position {100 * red[m]['pos']:.1f} % (seeds "
                     f"{100 * red[m]['seed_range_pos'][0]:.1f}..{100 * red[m]['seed_range_pos'][1]:.1f}), velocity "
                     f"{100 * red[m]['vel']:.1f} % (seeds {100 * red[m]['seed_range_vel'][0]:.1f}.."
                     f"{100 * red[m]['seed_range_vel'][1]:.1f}); abstract: 75 % / 80 %")
    return red


def _clean_summary(L, cfg, runs):
    """The runs without gross errors (appends text lines to ``L``)."""
    clean = {}
    cms = [m for m in CLEAN_METHODS if all(m in r["clean"] for r in runs)]
    if cms:
        cagg = C.aggregate([{"methods": r["clean"]} for r in runs], cms)
        L.append("clean data (no gross errors):")
        for m in cms:
            a = cagg[m]
            clean[m] = {"pos_rms_m": a["pos_rms_m"].tolist(), "vel_rms_mps": a["vel_rms_mps"].tolist(),
                        "nees_in_band_fraction": float(a["nees_in_band_fraction"]),
                        "nees_in_band_fraction_seed_range": [float(a["nees_in_band_fraction_seed_min"]),
                                                             float(a["nees_in_band_fraction_seed_max"])],
                        "rms_seed_range": {"pos_rms_m": [a["pos_rms_m_seed_min"].tolist(), a["pos_rms_m_seed_max"].tolist()],
                                           "vel_rms_mps": [a["vel_rms_mps_seed_min"].tolist(),
                                                           a["vel_rms_mps_seed_max"].tolist()]},
                        "false_alarm_rate": float(a.get("false_alarm_rate", np.nan)),
                        "false_alarm_rate_seed_range": [float(a.get("false_alarm_rate_seed_min", np.nan)),
                                                        float(a.get("false_alarm_rate_seed_max", np.nan))]}
            L.append(f"  {m:16s} pos rms {np.round(a['pos_rms_m'], 2)} vel rms {np.round(a['vel_rms_mps'], 3)} "
                     f"NEES95 {a['nees_in_band_fraction']:.3f} (seeds {a['nees_in_band_fraction_seed_min']:.3f}.."
                     f"{a['nees_in_band_fraction_seed_max']:.3f}) FA/dim {a.get('false_alarm_rate', np.nan):.4f} "
                     f"(seeds {a.get('false_alarm_rate_seed_min', np.nan):.4f}..{a.get('false_alarm_rate_seed_max', np.nan):.4f}; "
                     f"alpha {cfg['filter']['alpha']})")
        if "kf" in cagg:
            per_seed = {m: [np.linalg.norm(r["clean"][m]["pos_rms_m"]) / np.linalg.norm(r["clean"]["kf"]["pos_rms_m"])
                            for r in runs] for m in cms}
            for m in cms:
                if m != "kf":
                    clean[m]["rms_vs_kf"] = {
                        "pos": float(np.linalg.norm(cagg[m]["pos_rms_m"]) / np.linalg.norm(cagg["kf"]["pos_rms_m"])),
                        "vel": float(np.linalg.norm(cagg[m]["vel_rms_mps"]) / np.linalg.norm(cagg["kf"]["vel_rms_mps"]))}
                    clean[m]["rms_vs_kf"]["pos_seed_range"] = [float(min(per_seed[m])), float(max(per_seed[m]))]
                    L.append(f"  {m} / kf on clean data: position RMS x{clean[m]['rms_vs_kf']['pos']:.3f} (seeds "
                             f"x{min(per_seed[m]):.3f}..x{max(per_seed[m]):.3f}), "
                             f"velocity RMS x{clean[m]['rms_vs_kf']['vel']:.3f}")
    return clean


def _sweep_summary(L, runs):
    """The gross-error factor sweep (appends text lines to ``L``)."""
    sweep = {}
    keys = sorted({k.split("/")[0] for r in runs for k in r["sweep"]}, key=float)
    if keys:
        L.append("gross-error factor sweep (RMS reduction of chi2-newton vs kf, position / velocity):")
        for fk in keys:
            ka, kb = f"{fk}/kf", f"{fk}/chi2-newton"
            if all(ka in r["sweep"] and kb in r["sweep"] for r in runs):
                sa = C.aggregate([{"methods": {"kf": r["sweep"][ka], "rob": r["sweep"][kb]}} for r in runs], ["kf", "rob"])
                rd = _reduction(sa["kf"], sa["rob"])
                pmax = np.mean([r["sweep"][ka]["pos_max_m"] for r in runs], axis=0)
                vmax = np.mean([r["sweep"][ka]["vel_max_mps"] for r in runs], axis=0)
                dist = kf_range_distance(pmax, vmax)
                sweep[fk] = {"reduction_pos": rd["pos"], "reduction_vel": rd["vel"],
                             "kf_pos_max_m": pmax.tolist(), "kf_vel_max_mps": vmax.tolist(),
                             "kf_range_distance": {"all": dist[0], "pos": dist[1], "vel": dist[2]},
                             "kf_pos_rms_m": sa["kf"]["pos_rms_m"].tolist(), "kf_vel_rms_mps": sa["kf"]["vel_rms_mps"].tolist(),
                             "chi2_pos_rms_m": sa["rob"]["pos_rms_m"].tolist(),
                             "chi2_vel_rms_mps": sa["rob"]["vel_rms_mps"].tolist()}
                L.append(f"  m = {fk:>4s}: {100 * rd['pos']:5.1f} % / {100 * rd['vel']:5.1f} %   "
                         f"(kf pos {np.linalg.norm(sa['kf']['pos_rms_m']):.1f} m, vel {np.linalg.norm(sa['kf']['vel_rms_mps']):.3f} m/s; "
                         f"kf max |err| vs the paper's Figs. 4/6, mean |ln| {dist[0]:.2f} (pos {dist[1]:.2f}, vel {dist[2]:.2f}))")
    return sweep


def _figures(out, run):
    s = run["series"]
    ms = [m for m in ("kf", "chi2-newton", "chi2-newton-lit") if m in s]
    figs = [C.error_figure(out / "fig4_position_error.png", s, ms, em.POS, C.AXES["pos"], "(m)",
                           f"position error, seed {run['seed']} (Cai et al. 2020, Figs. 4/6)"),
            C.error_figure(out / "fig6_velocity_error.png", s, ms, em.VEL, C.AXES["vel"], "(m/s)",
                           f"velocity error, seed {run['seed']} (Cai et al. 2020, Figs. 4/6)"),
            C.error_figure(out / "fig5_position_error_100s.png", s, ms, em.POS, C.AXES["pos"], "(m)",
                           "position error, first 100 s (Cai et al. 2020, Figs. 5/7)", t_max=100.0)]
    ms2 = [m for m in ("chi2-newton", "ins-only") if m in s]
    if len(ms2) == 2:
        figs.append(C.error_figure(out / "fig8_robust_vs_ins.png", s, ms2, em.POS, C.AXES["pos"], "(m)",
                                   "position error, robust filter vs INS only (Cai et al. 2020, Figs. 8/9)"))
    return figs


def write_outputs(cfg, runs, summary, out_dir, plots):
    return C.write_common(cfg, runs, summary, out_dir, plots, _figures)
