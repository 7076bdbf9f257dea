"""Noise events inside the receiver (receiver.burst): the correlator-output noise has the thermal
noise's E/P/L structure and scale, the filter-R scale is applied where and only where an event is,
and at the correlator outputs a burst degrades tracking as the same burst at the IF does."""

import math

import numpy as np
import pytest

from ultratight.errors import ConfigError
from ultratight.receiver.dsp.burst import burst_one, if_events, make_burst
from ultratight.signals import corr_model
from ultratight.signals.synth.generator import noise_factor

T = 1e-3


def test_correlator_noise_has_the_thermal_covariance():
    ev = [{"t0_s": 0.0, "t1_s": 40.0, "noise_factor": 3.0, "place": "correlator"}]
    b = make_burst(ev, 2, corr_model.tap_offsets(1.0), T, seed=5)
    assert b.unit.shape[0] == 2 and b.unit.shape[1] >= 40000
    for c in range(2):
        cov = np.cov(b.unit[c].T)
        np.testing.assert_allclose(cov, corr_model.epl_noise_covariance(1.0), atol=0.03)
    # seeded: the same noise for every method of a run, other noise for another run
    np.testing.assert_array_equal(make_burst(ev, 2, corr_model.tap_offsets(1.0), T, seed=5).unit, b.unit)
    assert not np.allclose(make_burst(ev, 2, corr_model.tap_offsets(1.0), T, seed=6).unit[0, :100], b.unit[0, :100])


def test_burst_one_acts_inside_the_events_only():
    ev = [{"t0_s": 1.0, "t1_s": 2.0, "noise_factor": 3.0, "place": "correlator"},
          {"t0_s": 1.5, "t1_s": 2.5, "noise_factor": 2.0, "place": "correlator"},
          {"t0_s": 0.5, "t1_s": 1.0, "noise_factor": 5.0, "place": "filter-r"},
          {"t0_s": 0.0, "t1_s": 9.0, "noise_factor": 7.0, "place": "if"}]
    b = make_burst(ev, 3, corr_model.tap_offsets(1.0), T, seed=1)
    out = np.zeros((3, 6))
    for k, t, f, rs in ((400, 0.4003, 1.0, 1.0), (700, 0.7004, 1.0, 25.0), (1200, 1.2002, 3.0, 1.0),
                        (1700, 1.7001, 6.0, 1.0), (2200, 2.2004, 2.0, 1.0), (3000, 3.0003, 1.0, 1.0)):
        out[:] = 0.0
        burst_one(1, k, t, b, out)
        expect = math.sqrt(f * f - 1.0) * b.unit[1, k - b.k0] if f > 1 else np.zeros(6)
        np.testing.assert_allclose(out[1], expect, rtol=1e-12, atol=0)
        assert not out[0].any() and not out[2].any()
        assert b.rscale[1] == rs
    assert [e["place"] for e in if_events(ev)] == ["if"]
    # the generator applies the IF events only
    np.testing.assert_allclose(noise_factor(ev, np.array([0.7, 1.7])), [7.0, 7.0])


@pytest.mark.parametrize("ev,msg", [
    ({"place": "prefilter"}, "place must be one of"),
    ({"place": "correlator", "noise_factor": 0.5}, "can only be added"),
])
def test_bad_places_are_refused(ev, msg):
    from ultratight.receiver.cli.scenario_config import load_scenario
    e = {"t0_s": 1.0, "t1_s": 2.0, "noise_factor": 2.0}
    e.update(ev)
    with pytest.raises(ConfigError, match=msg):
        load_scenario("paper-highdyn", {"noise_events": [e]})


@pytest.fixture(scope="module")
def burst_runs(tmp_path_factory):
    """4 s of paper-highdyn (2.046 MHz, dlb-ckf) with noise std x4.47 over 1.5-3 s: at the IF, at the
    correlator outputs, in the filter's R only, and without the event."""
    from ultratight.receiver.cli import metrics as M
    from ultratight.receiver.cli.scenario_config import load_scenario
    from ultratight.receiver.cli.scenario_runner import errors_vs_truth, prepare_data, run_method
    out = tmp_path_factory.mktemp("burst")
    rms = {}
    for place in ("none", "if", "correlator", "filter-r"):
        cfg = load_scenario("paper-highdyn", {"duration_s": 4.0, "frontend.fs_hz": 2.046e6})
        cfg["noise_events"] = [] if place == "none" else [
            {"t0_s": 1.5, "t1_s": 3.0, "noise_factor": 4.47, "place": place}]
        paths, _ = prepare_data(cfg, 11, out, progress=False)
        res, truth = run_method(paths, cfg, "dlb-ckf", 11)
        de, _ = errors_vs_truth(res, truth)
        rms[place] = M.segment_rms(res.t_start, de, ((0.5, 1.5), (1.5, 3.0)))
    return rms


def test_a_burst_at_the_correlators_equals_one_at_the_if(burst_runs):
    r = burst_runs
    for place in ("correlator", "filter-r"):
        assert r[place][0] == r["none"][0]                      # identical before the event
    # (at the IF the fixed-gain front end's headroom for the burst quantises the whole record anew)
    assert r["if"][0] == pytest.approx(r["none"][0], rel=0.01)
    assert r["if"][1] > 3.0 * r["none"][1] and r["correlator"][1] > 3.0 * r["none"][1]
    assert 0.5 < r["correlator"][1] / r["if"][1] < 2.0          # the same C/N0 loss, made in two places
    # R x 20 with the signal unchanged: the filter trusts its measurements less, no noise is added
    assert r["filter-r"][1] != r["none"][1] and r["filter-r"][1] < 2.0 * r["none"][1]


def test_inside_events_share_the_data_and_engine_switches_are_checked():
    from ultratight.receiver.cli.scenario_config import load_scenario
    from ultratight.receiver.cli.scenario_runner import _cfg_key
    base = load_scenario("paper-highdyn", {"noise_events": []})
    ev = {"t0_s": 5.0, "t1_s": 10.0, "noise_factor": 20.0}
    for place, same in (("correlator", True), ("filter-r", True), ("if", False)):
        c = load_scenario("paper-highdyn", {"noise_events": [dict(ev, place=place)]})
        assert (_cfg_key(c) == _cfg_key(base)) is same
    c = load_scenario("paper-highdyn", {"engine.lock_monitor": True, "engine.monitor_gates_tight": True})
    assert c["engine"]["lock_monitor"] is True
    with pytest.raises(ConfigError, match="engine.lock_monitor must be true or false"):
        load_scenario("paper-highdyn", {"engine.lock_monitor": "yes"})
