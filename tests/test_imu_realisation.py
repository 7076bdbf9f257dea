"""The simulated IMU is a sensor drawn per run from its declaration (ultratight.ins.imu, docs/ins.md):
turn-on biases, scale factors and misalignments are random per seed with the declared 1-sigma (a
paper's stated bias: that magnitude, random sign), the IMU file declares the datasheet figures only,
the drawn sensor is in the truth file, and the ultra-tight engine's initial bias covariance is the
declared sigma squared."""

import json
import math

import h5py
import numpy as np
import pytest
from scipy.stats import chi2

from ultratight.errors import ConfigError
from ultratight.fusion.coupling import tight as tightmod
from ultratight.ins import imu as imu_mod
from ultratight.ins.imu import imu_errors_from_config, realise_errors, synthesize_imu
from ultratight.ins.imu_data import read_imu_h5
from ultratight.ins.trajectory import build_trajectory

TACTICAL = imu_errors_from_config({"preset": "tactical"})


def _static(duration=1.0):
    return build_trajectory({"kind": "static", "attitude": "fixed", "att0_deg": [1.0, -2.0, 30.0]},
                            {"lat_deg": 30.0, "lon_deg": 100.0, "h_m": 500.0}, duration)


def test_seeds_draw_different_sensors_and_a_seed_always_the_same():
    tr = _static()
    a = synthesize_imu(tr, 100.0, TACTICAL, np.random.default_rng(11))
    b = synthesize_imu(tr, 100.0, TACTICAL, np.random.default_rng(12))
    a2 = synthesize_imu(tr, 100.0, TACTICAL, np.random.default_rng(11))
    for k in ("gyro_bias", "accel_bias", "gyro_sf", "accel_sf", "gyro_misalign", "accel_misalign"):
        assert np.array_equal(a.errors_realised[k], a2.errors_realised[k]), k
        assert not np.allclose(a.errors_realised[k], b.errors_realised[k]), k
    assert np.array_equal(a.dtheta_b, a2.dtheta_b) and np.array_equal(a.dv_b, a2.dv_b)
    # the declaration is the same in every run: the preset's figures, not a draw
    assert a.meta["errors"] == b.meta["errors"] == TACTICAL.to_dict()


def test_drawn_errors_have_the_declared_sigma():
    """2000 sensors of the tactical grade: per axis (and per off-diagonal misalignment element) the sum
    of squares over sigma^2 is chi^2 with 2000 degrees of freedom (zero mean known); each lies in its
    two-sided 99.9 % interval, the mean within 4 standard errors of 0, the diagonal of M stays 0."""
    rng = np.random.default_rng(20261127)
    n = 2000
    draws = [realise_errors(TACTICAL, rng) for _ in range(n)]
    lo, hi = chi2.ppf(0.0005, n), chi2.ppf(0.9995, n)
    off = ~np.eye(3, dtype=bool)
    for k in ("gyro_bias", "accel_bias", "gyro_sf", "accel_sf", "gyro_misalign", "accel_misalign"):
        x = np.array([getattr(d, k) for d in draws])
        sig = np.asarray(getattr(TACTICAL, k))
        if x.ndim == 3:
            assert np.all(x[:, ~off] == 0.0), k
            x, sig = x[:, off], sig[off]
        q = np.sum((x / sig) ** 2, axis=0)
        assert np.all((q > lo) & (q < hi)), (k, q, lo, hi)
        assert np.all(np.abs(x.mean(axis=0)) < 4.0 * sig / math.sqrt(n)), k
    # the noise processes are declared ones: copied, not drawn
    assert np.array_equal(draws[0].gyro_arw, TACTICAL.gyro_arw)
    assert draws[0].accel_gm_tau == TACTICAL.accel_gm_tau


def test_paper_bias_is_the_stated_magnitude_with_random_signs():
    """Zhao et al. 2014, §3 state the bias (0.01 deg/h, 30 ug): every run has exactly that magnitude on
    every axis; the sign is random per axis and run (200 runs x 3 axes: each sign appears, and the
    count of + lies in the binomial(600, 1/2) 99.9 % interval)."""
    spec = imu_errors_from_config({"preset": "paper"})
    assert spec.bias_reading == "stated"
    rng = np.random.default_rng(4)
    g = np.array([realise_errors(spec, rng).gyro_bias for _ in range(200)])
    rng = np.random.default_rng(5)
    a = np.array([realise_errors(spec, rng).accel_bias for _ in range(200)])
    assert np.allclose(np.abs(g), 0.01 * imu_mod.DPH_TO_RADPS, rtol=1e-15, atol=0)
    assert np.allclose(np.abs(a), 30.0 * imu_mod.UG_TO_MPS2, rtol=1e-15, atol=0)
    for x in (g, a):
        assert np.all((x > 0).any(axis=0)) and np.all((x < 0).any(axis=0))
        n_pos = int((x > 0).sum())
        assert 300 - 3.29 * math.sqrt(150) < n_pos < 300 + 3.29 * math.sqrt(150), n_pos
    # the grades read their figure as a 1-sigma; a table may ask for the other reading
    assert TACTICAL.bias_reading == "sigma"
    assert imu_errors_from_config({"preset": "paper", "bias_reading": "sigma"}).bias_reading == "sigma"
    with pytest.raises(ConfigError, match="bias_reading"):
        imu_errors_from_config({"preset": "paper", "bias_reading": "fixed"})


def _generated(tmp_path, imu_table, seed=3):
    from ultratight.receiver.cli.scenario_config import load_scenario
    from ultratight.receiver.cli.scenario_runner import prepare_data
    ov = {"duration_s": 1.0, "frontend.fs_hz": 2.046e6, "satellites.max_count": 2}
    ov.update({f"imu.{k}": v for k, v in imu_table.items()})
    cfg = load_scenario("paper-highdyn", ov)
    paths, _ = prepare_data(cfg, seed, tmp_path, cache_if=False)
    return cfg, paths


def test_imu_file_declares_the_spec_and_the_truth_file_holds_the_drawn_sensor(tmp_path):
    """A generated paper-highdyn cut with a noise-free sensor of declared biases 100 deg/h and 5000 ug
    (1 sigma): its IMU file's metadata holds the declaration; the increments minus the exact ones over
    dt are the truth file's drawn biases (so those are what the sensor applied), which differ from the
    declared figures and appear nowhere in the IMU file."""
    from ultratight.ins.imu import ideal_increments
    from ultratight.signals.synth.generator import read_imu_errors_truth
    table = {"preset": "ideal", "gyro_bias_dph": 100.0, "accel_bias_ug": 5000.0}
    cfg, paths = _generated(tmp_path, table)
    imu = read_imu_h5(paths["imu"])
    decl = imu.meta["errors"]
    assert decl["bias_reading"] == "sigma"
    assert np.allclose(decl["gyro_bias"], 100.0 * imu_mod.DPH_TO_RADPS, rtol=1e-15, atol=0)
    assert np.allclose(decl["accel_bias"], 5000.0 * imu_mod.UG_TO_MPS2, rtol=1e-15, atol=0)
    real = read_imu_errors_truth(paths["truth"])
    # the sensor's bias from the data: increments minus the exact increments of the scenario trajectory
    from ultratight.ins.trajectory import build_trajectory as bt
    traj = bt(cfg["trajectory"], cfg["receiver"], float(cfg["duration_s"]))
    edges = np.concatenate([[imu.t0], imu.t])
    dth0, dv0 = ideal_increments(traj, edges)
    bg = np.mean(imu.dtheta_b - dth0, axis=0) * imu.rate_hz
    ba = np.mean(imu.dv_b - dv0, axis=0) * imu.rate_hz
    assert np.allclose(bg, real["gyro_bias"], rtol=1e-6, atol=1e-12)
    assert np.allclose(ba, real["accel_bias"], rtol=1e-6, atol=1e-9)
    assert not np.allclose(np.abs(real["gyro_bias"]), decl["gyro_bias"], rtol=1e-3)
    # the receiver reads the IMU file: no drawn value anywhere in it (metadata, attributes, datasets)
    drawn = np.concatenate([real["gyro_bias"], real["accel_bias"]])
    with h5py.File(paths["imu"], "r") as f:
        found = _numbers(json.loads(f.attrs["meta_json"]))
        found += [float(x) for k in f.attrs if k != "meta_json" and np.asarray(f.attrs[k]).dtype.kind in "iuf"
                  for x in np.ravel(np.asarray(f.attrs[k], float))]
        f.visititems(lambda name, obj: found.extend(np.ravel(obj[()]).tolist()) if isinstance(obj, h5py.Dataset)
                     and obj.size < 10 else None)
    assert len(found) > 10
    for v in drawn:
        assert not any(math.isclose(v, x, rel_tol=1e-9) for x in found), v


def _numbers(obj):
    """Every number in a JSON value, strings holding JSON (the scenario's config_json) included."""
    if isinstance(obj, dict):
        return [x for v in obj.values() for x in _numbers(v)]
    if isinstance(obj, list):
        return [x for v in obj for x in _numbers(v)]
    if isinstance(obj, str):
        try:
            inner = json.loads(obj)
        except ValueError:
            return []
        return _numbers(inner) if isinstance(inner, (dict, list)) else []
    if isinstance(obj, (int, float)) and not isinstance(obj, bool):
        return [float(obj)]
    return []


def test_engine_initial_bias_covariance_is_the_declared_sigma(tmp_path, monkeypatch):
    """The tight filter of the engine starts from P0 whose gyro / accelerometer bias blocks are the
    declared tactical 1-sigma squared (1 deg/h, 1000 ug), not the squares of the run's drawn biases."""
    from ultratight.receiver.cli.scenario_runner import run_method
    from ultratight.signals.synth.generator import read_imu_errors_truth
    cfg, paths = _generated(tmp_path, {"preset": "tactical"}, seed=5)
    real = read_imu_errors_truth(paths["truth"])
    sg, sa = 1.0 * imu_mod.DPH_TO_RADPS, 1000.0 * imu_mod.UG_TO_MPS2
    assert np.all(np.abs(np.abs(real["gyro_bias"]) / sg - 1.0) > 0.02)     # the draw is not the figure

    class Captured(Exception):
        pass

    seen = {}

    def capture(P0, **kw):
        seen["P0"] = np.array(P0)
        raise Captured

    monkeypatch.setattr(tightmod, "TightFilter", capture)
    with pytest.raises(Captured):
        run_method(paths, cfg, "dlb-rackf", 5, duration_s=0.5)
    P0 = seen["P0"]
    assert np.allclose(np.diag(P0[tightmod.BG, tightmod.BG]), sg ** 2, rtol=1e-12, atol=0)
    assert np.allclose(np.diag(P0[tightmod.BA, tightmod.BA]), sa ** 2, rtol=1e-12, atol=0)
    assert not np.allclose(np.diag(P0[tightmod.BG, tightmod.BG]), real["gyro_bias"] ** 2, rtol=1e-2, atol=0)


def test_scenario_tables_name_the_start_up_and_the_imu_declaration():
    """``ultratight scenario`` records how its runs start (truth at t = 0 plus the hot-start errors of
    StartupErrors: assisted) and that the IMU is a sensor drawn from the declaration, in the text below
    the tables, metrics.json and results.h5 (run_settings)."""
    from ultratight.receiver.cli.scenario_config import load_scenario
    from ultratight.receiver.cli.scenario_runner import run_settings, run_settings_text
    from ultratight.receiver.deep.startup import StartupErrors
    s = run_settings(load_scenario("paper-highdyn"))
    assert s["startup"] == {"kind": "truth-perturbed (assisted)", "sigmas": StartupErrors().as_dict()}
    assert s["imu"]["preset"] == "paper" and s["imu"]["bias_reading"] == "stated"
    text = run_settings_text(s)
    assert text.startswith("start-up: truth-perturbed (assisted): truth at t = 0 plus 1-sigma errors position 0.5 m")
    assert "IMU: preset paper (stated bias magnitudes, random signs)" in text
    t2 = run_settings_text(run_settings(load_scenario("vehicle-turns"), StartupErrors(pos_m=3.0)))
    assert "position 3 m" in t2 and "IMU: preset tactical (1-sigma figures)" in t2
    assert json.loads(json.dumps(s)) == s              # what results.h5 stores as run_settings_json


def test_experiments_draw_their_sensor_from_the_paper_figures():
    """sins_gnss.draw_imu (paper-static-iakf, paper-robust-flight): "stated" gives each axis the paper's
    constant with a random sign, "sigma" N(0, sigma^2) draws -- the latter the same numbers as drawing
    the biases first and applying them with the white noise of the same generator (an independent
    implementation here); the filters' figures are the declared ones (the returned biases are truth)."""
    from ultratight.fusion.experiments import paper_robust_flight as RF
    from ultratight.fusion.experiments import paper_static_iakf as SI
    from ultratight.fusion.experiments import sins_gnss as C
    from ultratight.ins.imu import ImuErrors, apply_errors
    # the documented 10-seed figures of both experiments were measured with the N(0, sigma^2) reading
    assert SI.SCHEMA["imu"]["bias_reading"] == RF.SCHEMA["imu"]["bias_reading"] == "sigma"
    tr = _static(2.0)
    bg, ba = 0.2 * C.DPH, 0.01 * C.G0
    _, b = C.draw_imu(tr, 100.0, bg, 1e-6, ba, 1e-4, np.random.default_rng(8), "stated")
    assert np.allclose(np.abs(b), [bg] * 3 + [ba] * 3, rtol=1e-15, atol=0)
    imu, b = C.draw_imu(tr, 100.0, bg, 1e-6, ba, 1e-4, np.random.default_rng(8), "sigma")
    rng = np.random.default_rng(8)
    want = np.concatenate([rng.standard_normal(3) * bg, rng.standard_normal(3) * ba])
    assert np.array_equal(b, want)
    e = ImuErrors(gyro_bias=want[:3], accel_bias=want[3:], gyro_arw=np.full(3, 1e-6), accel_vrw=np.full(3, 1e-4))
    ideal = synthesize_imu(tr, 100.0)
    dth, dv = apply_errors(ideal.dtheta_b, ideal.dv_b, e, rng, 0.01)
    assert np.array_equal(dth, imu.dtheta_b) and np.array_equal(dv, imu.dv_b)
    with pytest.raises(ConfigError, match="bias_reading"):
        C.bias_reading({"bias_reading": "both"})
