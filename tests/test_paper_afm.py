"""The experiments of Sun et al. 2012 behind ``ultratight scenario paper-afm-*``."""

import json
import math

import numpy as np
import pytest

from ultratight.errors import ConfigError
from ultratight.ins.imu import ideal_increments
from ultratight.receiver.cli import experiments
from ultratight.receiver.cli import main
from ultratight.fusion.experiments import paper_afm
@pytest.mark.parametrize("name,exp", [("paper-afm-jump", "4.1"), ("paper-afm-noise", "4.2"),
                                      ("paper-afm-accel", "4.3")])
def test_scenarios_resolve_to_the_experiment(name, exp):
    path, raw, module = experiments.resolve(name)
    assert module is paper_afm
    cfg = module.load(path, raw, {})
    assert cfg["paper_experiment"] == exp
    assert experiments.check_methods(module, None) == ["ukf", "aff", "afm"]


def test_unknown_keys_are_refused_with_a_suggestion():
    path, raw, _ = experiments.resolve("paper-afm-noise")
    bad = dict(raw, fault=dict(raw["fault"], accel_var_factr=10.0))
    with pytest.raises(ConfigError, match=r"fault: unknown key 'accel_var_factr' \(did you mean 'accel_var_factor'\?\)"):
        paper_afm.load(path, bad, {})
    with pytest.raises(ConfigError, match="fault.kind"):
        paper_afm.load(path, dict(raw, fault={"kind": "jump"}), {})
    with pytest.raises(ConfigError, match="trajectory.kind"):
        paper_afm.load(path, dict(raw, trajectory={"kind": "turns"}), {})
    with pytest.raises(ConfigError, match="gps.rate_hz must divide"):
        paper_afm.load(path, dict(raw, gps={"rate_hz": 3.0}), {})


def test_noise_jump_multiplies_the_data_noise_variance():
    """4.3: from t_s the accelerometer white noise has 100× the variance, the gyro noise is unchanged."""
    path, raw, _ = experiments.resolve("paper-afm-accel")
    cfg = paper_afm.load(path, raw, {"duration_s": 60.0})
    sim = paper_afm.simulate(cfg, 11)
    dt = sim["dt"]
    edges = np.arange(sim["dtheta"].shape[0] + 1) * dt
    dth0, dv0 = ideal_increments(sim["traj"], edges)
    flip = np.array([1.0, -1.0, -1.0])
    rg = sim["dtheta"] - dth0 * flip
    ra = sim["dv"] - dv0 * flip
    k0 = int(round(30.0 / dt))
    # white-noise part: first differences remove the constant biases
    var = lambda r: np.var(np.diff(r, axis=0), axis=0)
    acc_ratio = var(ra[k0:]) / var(ra[:k0])
    gyr_ratio = var(rg[k0:]) / var(rg[:k0])
    assert np.all((acc_ratio > 80) & (acc_ratio < 125)), acc_ratio     # 3000 samples: ±~5 % per axis
    assert np.all((gyr_ratio > 0.85) & (gyr_ratio < 1.18)), gyr_ratio


def test_cli_json_is_strict_and_carries_table1(tmp_path, capsys):
    rc = main(["scenario", "paper-afm-jump", "--duration", "45", "--json", "--no-plots",
               "--out", str(tmp_path), "--seed", "3"])
    assert rc == 0
    js = json.loads(capsys.readouterr().out, parse_constant=lambda c: pytest.fail(f"non-finite {c}"))
    assert js["scenario"] == "paper-afm-jump" and js["seed"] == 3 and js["runs"] == 1
    assert set(js["methods"]) == {"ukf", "aff", "afm"}
    for m, d in js["methods"].items():
        assert len(d["att_err_mean_deg"]) == 3 and len(d["att_err_std_deg"]) == 3
        assert d["runtime_s"] > 0
    assert js["config"]["fault"]["kind"] == "attitude-jump" and js["version"]
    # the −10° jump is in the record: the roll and pitch errors right after 30 s are ≈ −10°
    import h5py
    with h5py.File(tmp_path / "paper-afm-jump_results.h5") as f:
        g = f["seed_3/ukf"]
        t, e = g["t"][:], g["att_err_deg"][:]
        assert json.loads(f.attrs["config_json"])["duration_s"] == 45.0
    i = np.searchsorted(t, 30.0)
    np.testing.assert_allclose(e[i, :2], -10.0, atol=0.5)
    assert np.all(np.abs(e[i - 1, :2]) < 0.5)
    assert (tmp_path / "paper-afm-jump_metrics.json").is_file()


def test_reduction_and_recovery_times():
    assert paper_afm.reduction([0.5, 0.2, 0.1], [1.0, 0.4, 0.2]) == pytest.approx(50.0)
    t = np.arange(0, 60.0, 0.1)
    e = np.zeros((t.size, 3))
    e[(t >= 30) & (t < 42.0), :2] = math.radians(5.0)
    assert paper_afm.recovery_time(t, e, 30.0, math.radians(1.0)) == pytest.approx(12.0)
    assert paper_afm.first_within(t, e, 30.0, math.radians(1.0)) == pytest.approx(12.0)
    e[-1, 0] = 1.0
    assert math.isnan(paper_afm.recovery_time(t, e, 30.0, math.radians(1.0)))
    e[t > 30.0, 1] = 1.0
    assert math.isnan(paper_afm.first_within(t, e, 30.0, math.radians(1.0)))
