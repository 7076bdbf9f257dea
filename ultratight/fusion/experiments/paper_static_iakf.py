"""The experiment of Fang 2017 (§4, "paper-static-iakf"): tight SINS/GPS of a static receiver with
AKF0 (true noise), AKF and IAKF (the paper's wrong noise settings), Table 1 beside ours.

Simulation (the recorded GPS data of the paper are not available): a static receiver
at the test point (36.8103° N, 117.9996° E, 76.6825 m), satellites from a real broadcast
ephemeris (``[satellites] rinex``; the nominal constellation with ``source = "nominal"``) above the
elevation mask, pseudoranges/rates from :func:`ultratight.signals.synth.obssim.simulate_observables`
(σ 2 m, 2 m/s), a receiver clock starting at 25 m / 0.01 m/s driven by the TCXO h-parameters; a
level static IMU at 100 Hz with constant bias and white noise 0.02 °/h (gyro) and 1e-4 g
(accelerometer) each (the constant drawn per axis and run from N(0, σ²), ``[imu] bias_reading =
"sigma"``, the reading the documented figures were measured with; ``"stated"``: the paper's value
as each axis's bias magnitude with a random sign per axis and run; the white noise as the 1σ of
each IMU sample).  Initial SINS errors (identical for all filters of a run) are drawn from
N(0, σ²) with σ = 0.6° (attitude), 0.2 m/s (velocity), 15 m (position); the initial receiver
clock estimate is 0 (error 25 m / 0.01 m/s).

Filters (tight 17-state, :mod:`ultratight.fusion.coupling.integration`, best-4 GDOP satellites every
epoch for all cores so that the adaptive windows have a fixed dimension m = 8):

* ``akf0`` — Q from the IMU simulation parameters and the clock model, R = (2 m)², (2 m/s)²;
  fixed by default (``[filter] akf0_adaptive = false``, the alternative reading of the paper),
  eq. 15 still adapting with ``true``;
* ``akf`` — AKF (eqs. 6–15, window N) started from the wrong settings;
* ``iakf`` — IAKF (eqs. 16–26) started from the wrong settings; the numerator of eq. 24 from the
  least-squares reading of eqs. 21–22 (``[filter] iakf_r_source = "lsq"``, default) or from
  P_ΔX̂ = K P̂_ε Kᵀ (eq. 13, ``"correction"``, which collapses R̂ as K shrinks: measured 2–3x worse
  velocity RMS on this scenario, docs/integration-experiments.md);
  ``[filter] iakf_start``: "growing" (default: R̂ and Q̂ from the first epoch over the terms
  available, then the sliding window N) or "full-window" (the given settings until N terms exist);
  ``[filter] iakf_q_structure``: eq. 26's Q̂ projected onto the eq. 3 noise structure
  ("model-diag", default; "model") or as printed ("full");
  ``[filter] iakf_q_ceiling = true`` (default): the projected noise variances may fall below the
  given (wrong) ones but not exceed them;
  ``[filter] iakf_adapt_q = false`` keeps the given Q (R adaptation only: a diagnostic);
* ``kf`` — fixed-gain KF with the wrong settings (no adaptation: what the settings alone do);
* ``kf-true-noise`` — diagnostic bound: fixed-gain KF with the *true* Q, R but the wrong settings'
  initial covariance of the biases and the clock (what perfect Q/R estimation could reach from the
  wrong start; the attitude/velocity/position P0 is the same for every method);
* ``ins-only`` — free inertial.

Wrong settings (this project's reading of the paper's list): gyro (0.1 °/h)², accelerometer
(1e-2 g)² (white noise per sample and bias P0), clock bias (35 m)², drift (0.3 m/s)² (per-epoch Q
and P0), pseudorange (50 m)², rate (0.6 m/s)² (R).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ultratight.errors import ConfigError, InputFileError
from ultratight.fusion.coupling import integration as I
from ultratight.fusion.estimators.adaptive import IAKF_STARTS, Q_STRUCTURES
from ultratight.ins import error_model as em
from ultratight.ins.trajectory import build_trajectory
from ultratight.fusion.experiments import sins_gnss as C
from ultratight.config import shared_data_dir
from ultratight.signals.constellation import ephemerides_for
from ultratight.signals.synth.obssim import clock_q, simulate_clock, simulate_observables

DEFAULT_METHODS = ("akf0", "akf", "iakf")
METHODS = ("akf0", "akf", "iakf", "kf", "kf-true-noise", "ins-only")
TRUE_NOISE = ("akf0", "kf-true-noise")

# Fang 2017, Table 1 (RMS): velocity E, N, U (m/s); latitude, longitude, height (m)
PAPER_TABLE1 = {
    "akf0": {"vel_rms_mps": [0.0311, 0.0279, 0.0233], "pos_rms_m": [3.7023, 3.0533, 3.5617]},
    "akf": {"vel_rms_mps": [0.7512, 0.8526, 0.8936], "pos_rms_m": [8.1662, 7.1589, 12.4737]},
    "iakf": {"vel_rms_mps": [0.0491, 0.0433, 0.0655], "pos_rms_m": [3.8616, 3.2693, 3.7522]},
}

SCHEMA = {
    "": {"experiment": "paper-static-iakf", "name": "paper-static-iakf", "description": "",
         "duration_s": 1000.0, "seed": 1},
    "time": {"week": 2190, "tow_s": 518400.0},
    "receiver": {"lat_deg": 36.8103, "lon_deg": 117.9996, "h_m": 76.6825, "heading_deg": 0.0},
    "satellites": {"source": "rinex", "rinex": "rinex/brdc0010.22n", "mask_deg": 10.0},
    "gnss": {"rate_hz": 1.0, "sigma_pr_m": 2.0, "sigma_prr_mps": 2.0, "clock_bias0_m": 25.0,
             "clock_drift0_mps": 0.01, "h0": 2e-19, "h_m2": 2e-20},
    "imu": {"rate_hz": 100.0, "gyro_bias_dph": 0.02, "gyro_noise_dph": 0.02, "accel_bias_g": 1e-4,
            "accel_noise_g": 1e-4, "bias_reading": "sigma"},
    "initial_errors": {"att_deg": 0.6, "vel_mps": 0.2, "pos_m": 15.0},
    "wrong": {"gyro_dph": 0.1, "accel_g": 1e-2, "clock_bias_m": 35.0, "clock_drift_mps": 0.3,
              "sigma_pr_m": 50.0, "sigma_prr_mps": 0.6},
    "filter": {"window": 20, "akf0_adaptive": False, "iakf_r_source": "lsq", "iakf_adapt_q": True,
               "iakf_start": "growing", "iakf_q_structure": "model-diag", "iakf_q_ceiling": True, "best4": True},
}


def load(path, raw, overrides):
    cfg = C.tables(raw, SCHEMA, overrides)
    cfg["name"] = raw.get("name", path.stem if hasattr(path, "stem") else "paper-static-iakf")
    cfg["source_file"] = str(path)
    C.num(cfg, "duration_s", "", lo=10.0, hi=C.MAX_DURATION_S)
    for k in ("lat_deg",):
        C.num(cfg["receiver"], k, "receiver", lo=-89.0, hi=89.0)
    C.num(cfg["receiver"], "lon_deg", "receiver", lo=-180.0, hi=360.0)
    C.num(cfg["receiver"], "h_m", "receiver", lo=-1000.0, hi=1e5)
    C.num(cfg["gnss"], "rate_hz", "gnss", lo=0.0, lo_open=True, hi=100.0)
    for k in ("sigma_pr_m", "sigma_prr_mps", "h0", "h_m2"):
        C.num(cfg["gnss"], k, "gnss", lo=0.0, lo_open=True)
    C.num(cfg["imu"], "rate_hz", "imu", lo=1.0)
    C.bias_reading(cfg["imu"])
    if abs(cfg["imu"]["rate_hz"] / cfg["gnss"]["rate_hz"] - round(cfg["imu"]["rate_hz"] / cfg["gnss"]["rate_hz"])) > 1e-9:
        raise ConfigError("imu.rate_hz must be an integer multiple of gnss.rate_hz")
    for k in ("gyro_bias_dph", "gyro_noise_dph", "accel_bias_g", "accel_noise_g"):
        C.num(cfg["imu"], k, "imu", lo=0.0)
    for k in cfg["initial_errors"]:
        C.num(cfg["initial_errors"], k, "initial_errors", lo=0.0, lo_open=True)
    for k in cfg["wrong"]:
        C.num(cfg["wrong"], k, "wrong", lo=0.0, lo_open=True)
    C.num(cfg["filter"], "window", "filter", lo=2, hi=10000, integer=True)
    C.num(cfg["satellites"], "mask_deg", "satellites", lo=-5.0, hi=60.0)
    if cfg["satellites"]["source"] not in ("rinex", "nominal"):
        raise ConfigError(f"satellites.source must be 'rinex' or 'nominal', got {cfg['satellites']['source']!r}")
    for k in ("akf0_adaptive", "iakf_adapt_q", "iakf_q_ceiling", "best4"):
        if not isinstance(cfg["filter"][k], bool):
            raise ConfigError(f"filter.{k} must be true or false, got {cfg['filter'][k]!r}")
    if cfg["filter"]["iakf_q_structure"] not in Q_STRUCTURES:
        raise ConfigError(f"filter.iakf_q_structure must be one of {', '.join(Q_STRUCTURES)}, "
                          f"got {cfg['filter']['iakf_q_structure']!r}")
    if cfg["filter"]["iakf_start"] not in IAKF_STARTS:
        raise ConfigError(f"filter.iakf_start must be one of {', '.join(IAKF_STARTS)}, "
                          f"got {cfg['filter']['iakf_start']!r}")
    if cfg["filter"]["iakf_q_ceiling"] and cfg["filter"]["iakf_q_structure"] == "full":
        raise ConfigError("filter.iakf_q_ceiling = true needs iakf_q_structure 'model' or 'model-diag' "
                          "(the ceiling acts on the projected noise variances)")
    if cfg["filter"]["iakf_r_source"] not in ("correction", "lsq"):
        raise ConfigError("filter.iakf_r_source must be 'correction' (eq. 13) or 'lsq' (eqs. 21–22)")
    return cfg


def ephemerides(cfg):
    sat = dict(cfg["satellites"])
    if sat["source"] == "rinex":
        p = Path(sat["rinex"])
        if not p.is_absolute() and not p.is_file():
            p = shared_data_dir() / p
        if not p.is_file():
            raise InputFileError(f"satellites.rinex: navigation file not found: {p}")
        sat["rinex_path"] = str(p)
    return ephemerides_for({"satellites": sat, "time": cfg["time"]})


def simulate(cfg, seed):
    """Shared data of one seed: trajectory truth, IMU, observables, initial errors."""
    rng = np.random.default_rng(seed)
    dur = float(cfg["duration_s"])
    rcv = cfg["receiver"]
    traj = build_trajectory({"kind": "static", "attitude": "fixed", "att0_deg": [0.0, 0.0, rcv["heading_deg"]]},
                            rcv, dur)
    imu_c = cfg["imu"]
    rate = float(imu_c["rate_hz"])
    imu, bias_true = C.draw_imu(traj, rate, imu_c["gyro_bias_dph"] * C.DPH, imu_c["gyro_noise_dph"] * C.DPH / math.sqrt(rate),
                                imu_c["accel_bias_g"] * C.G0, imu_c["accel_noise_g"] * C.G0 / math.sqrt(rate), rng,
                                imu_c["bias_reading"])
    g = cfg["gnss"]
    dt = 1.0 / float(g["rate_hz"])
    t_gnss = np.arange(1, int(math.floor(dur / dt + 1e-9)) + 1) * dt
    k = traj.kinematics(t_gnss)
    cb, cd = simulate_clock(t_gnss.size + 1, dt, g["clock_bias0_m"], g["clock_drift0_mps"], rng, g["h0"], g["h_m2"])
    cb, cd = cb[1:], cd[1:]
    obs = simulate_observables(ephemerides(cfg), int(cfg["time"]["week"]), float(cfg["time"]["tow_s"]), t_gnss,
                               k["pos_e"], k["vel_e"], cb, cd, rng, g["sigma_pr_m"], g["sigma_prr_mps"],
                               cfg["satellites"]["mask_deg"])
    ie = cfg["initial_errors"]
    k0 = traj.kinematics(np.zeros(1))
    att_e = rng.standard_normal(3) * math.radians(ie["att_deg"])
    vel_e = rng.standard_normal(3) * ie["vel_mps"]
    pos_e = rng.standard_normal(3) * ie["pos_m"]
    x0 = I.initial_state(k0["q_lb"][0], k0["vel_l"][0], k0["llh"][0], att_e, vel_e, pos_e)
    inp = I.RunInput(t_imu=np.concatenate([[0.0], imu.t]), dtheta=imu.dtheta_b, dv=imu.dv_b, t_gnss=t_gnss,
                     truth_llh=k["llh"], truth_vel=k["vel_l"], truth_q=k["q_lb"], bias_true=bias_true, x0_est=x0,
                     clk_true=np.stack([cb, cd], axis=1), clk0_est=np.zeros(2))
    return inp, obs


def noise_settings(cfg, true, p0_true=None):
    """(q_psd, clock Q_d, R variances (pr, prr), P0) a core is given: the true or the wrong ones;
    ``p0_true`` (default ``true``) selects the initial covariance of the biases and the clock."""
    imu_c, g, ie = cfg["imu"], cfg["gnss"], cfg["initial_errors"]
    rate = float(imu_c["rate_hz"])
    dt = 1.0 / float(g["rate_hz"])
    if true:
        gyro, accel = imu_c["gyro_noise_dph"] * C.DPH, imu_c["accel_noise_g"] * C.G0
        bg, ba = imu_c["gyro_bias_dph"] * C.DPH, imu_c["accel_bias_g"] * C.G0
        cq = clock_q(dt, g["h0"], g["h_m2"])
        clk0 = (g["clock_bias0_m"], g["clock_drift0_mps"])
        r = (g["sigma_pr_m"] ** 2, g["sigma_prr_mps"] ** 2)
    else:
        w = cfg["wrong"]
        gyro, accel = w["gyro_dph"] * C.DPH, w["accel_g"] * C.G0
        bg, ba = gyro, accel
        cq = np.diag([w["clock_bias_m"] ** 2, w["clock_drift_mps"] ** 2])
        clk0 = (w["clock_bias_m"], w["clock_drift_mps"])
        r = (w["sigma_pr_m"] ** 2, w["sigma_prr_mps"] ** 2)
    # white noise given as the 1σ of each IMU sample (this project's choice): PSD σ²/rate
    q = I.imu_psd(gyro / math.sqrt(rate), accel / math.sqrt(rate), n_states=em.N17)
    if p0_true is not None and p0_true != true:
        _, _, _, P0 = noise_settings(cfg, p0_true)
        return q, cq, r, P0
    P0 = C.initial_P(em.N17, math.radians(ie["att_deg"]), ie["vel_mps"], ie["pos_m"], bg, ba, clk0)
    return q, cq, r, P0


def run_method(cfg, method, inp, obs):
    true = method in TRUE_NOISE
    q, cq, r, P0 = noise_settings(cfg, true, p0_true=method == "akf0")
    f = cfg["filter"]
    R0 = np.diag([r[0]] * 4 + [r[1]] * 4)
    Q0 = np.diag(np.full(em.N17, 1e-12))
    core = I.make_core("kf" if method == "kf-true-noise" else method, P0, Q0, R0, window=int(f["window"]), m_sat=4,
                       akf0_adaptive=f["akf0_adaptive"], iakf_r_source=f["iakf_r_source"],
                       iakf_adapt_q=f["iakf_adapt_q"], iakf_q_structure=f["iakf_q_structure"],
                       iakf_start=f["iakf_start"], iakf_q_ceiling=f["iakf_q_ceiling"])
    meas = I.tight_measurement_fn(obs, r[0], r[1], select_best4=bool(f["best4"]) or method == "iakf")
    return I.run_integration("tight", core, inp, meas, q, cq)


def run_one(cfg, methods, seed, progress=False):
    inp, obs = simulate(cfg, seed)
    out = {"seed": int(seed), "methods": {}, "series": {},
           "n_visible_mean": float(obs.visible.sum(axis=1).mean())}
    for m in methods:
        res = run_method(cfg, m, inp, obs)
        out["methods"][m] = C.run_metrics(res, em.N17)
        out["series"][m] = {"t": res["t"], "err": res["err"], "sigma": res["sigma"], "nees": res["nees"]}
        if progress:
            mm = out["methods"][m]
            print(f"  seed {seed} {m:9s} vel rms {np.round(mm['vel_rms_mps'], 4)}  pos rms {np.round(mm['pos_rms_m'], 3)}"
                  f"  {mm['runtime_s']:.2f} s", flush=True)
    return out


def summarize(cfg, runs):
    methods = list(runs[0]["methods"])
    agg = C.aggregate(runs, methods)
    cols = ["vE", "vN", "vU", "lat", "lon", "h"]
    lines = [f"paper-static-iakf (Fang 2017 Table 1): {len(runs)} run(s), seeds {runs[0]['seed']}..{runs[-1]['seed']}; "
             "RMS over the whole run; velocity m/s (E, N, U), position m (lat = N, lon = E, h = U)",
             f"{'method':10s} {'':6s}" + "".join(f"{c:>9s}" for c in cols) + f"{'NEES in 95%':>13s}{'runtime s':>11s}"]
    for m in methods:
        a = agg[m]
        row = np.concatenate([a["vel_rms_mps"], a["pos_rms_m"]])
        lines.append(f"{m:10s} {'ours':6s}" + "".join(f"{v:9.4f}" for v in row)
                     + f"{a['nees_in_band_fraction']:13.3f}{a['runtime_s']:11.2f}")
        lo = np.concatenate([a["vel_rms_mps_seed_min"], a["pos_rms_m_seed_min"]])
        hi = np.concatenate([a["vel_rms_mps_seed_max"], a["pos_rms_m_seed_max"]])
        lines.append(f"{'':10s} {'min':6s}" + "".join(f"{v:9.4f}" for v in lo))
        lines.append(f"{'':10s} {'max':6s}" + "".join(f"{v:9.4f}" for v in hi))
        if m in PAPER_TABLE1:
            p = PAPER_TABLE1[m]
            lines.append(f"{'':10s} {'paper':6s}" + "".join(f"{v:9.4f}" for v in p["vel_rms_mps"] + p["pos_rms_m"]))
    ratios = {}

    def _row(m):
        return np.concatenate([agg[m]["vel_rms_mps"], agg[m]["pos_rms_m"]])

    def _prow(m):
        return np.array(PAPER_TABLE1[m]["vel_rms_mps"] + PAPER_TABLE1[m]["pos_rms_m"])

    for num_, den in (("iakf", "akf0"), ("akf", "iakf")):
        if num_ in agg and den in agg:
            ours = _row(num_) / _row(den)
            paper = _prow(num_) / _prow(den)
            ratios[f"{num_}/{den}"] = {"ours": ours.tolist(), "paper": paper.tolist()}
            lines.append(f"ratio {num_}/{den:5s}ours " + "".join(f"{v:9.3f}" for v in ours))
            lines.append(f"{'':16s}paper" + "".join(f"{v:9.3f}" for v in paper))
    js = {"scenario": cfg["name"], "seed": int(runs[0]["seed"]), "runs": len(runs),
          "axis_order": {"vel_rms_mps": "E, N, U", "pos_rms_m": "N (lat), E (lon), U (h)",
                         "pos_max_m": "N, E, U (max |error|)", "vel_max_mps": "E, N, U (max |error|)"},
          "methods": C.json_methods(agg), "ratios": ratios, "paper_table1": PAPER_TABLE1}
    return {"text": "\n".join(lines), "json": C.json_clean(js),
            "details": {"n_visible_mean": [r["n_visible_mean"] for r in runs]}}


def _figures(out, run):
    s = run["series"]
    ms = list(s)
    return [C.error_figure(out / "fig1_velocity_error.png", s, ms, em.VEL, C.AXES["vel"], "(m/s)",
                           f"velocity error, seed {run['seed']} (Fang 2017, Fig. 1)"),
            C.error_figure(out / "fig2_position_error.png", s, ms, em.POS, C.AXES["pos"], "(m)",
                           f"position error, seed {run['seed']} (Fang 2017, Fig. 2)")]


def write_outputs(cfg, runs, summary, out_dir, plots):
    return C.write_common(cfg, runs, summary, out_dir, plots, _figures)
