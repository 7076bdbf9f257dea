"""Method registry: every method is a spec naming its tracking bank and loop structure; the engine
runs the scalar method through the scalar pipeline instead of refusing it."""

import numpy as np
import pytest

from ultratight.errors import ConfigError
from ultratight.fusion.channel.pbkf import PbKfBank
from ultratight.fusion.channel.prefilter import KINDS, PrefilterBank
from ultratight.receiver.deep.methods import DEFAULT_METHOD, METHODS, REGISTRY, check_method, method_spec


def test_registry_names_banks_and_loops():
    assert METHODS == ("pb-kf-utc", "dlb-ukf", "dlb-ckf", "dlb-rackf", "dlb-rackf-paper", "scalar")
    assert DEFAULT_METHOD in METHODS
    for name, spec in REGISTRY.items():
        assert spec.name == name
        assert spec.bank in KINDS + ("pbkf", "scalar")
        assert spec.double_loop == (spec.bank in KINDS)
        assert spec.needs_imu != spec.scalar
    assert method_spec("pb-kf-utc").loop == "outer" and method_spec("scalar").scalar
    with pytest.raises(ConfigError, match="unknown method 'dlb-pf'"):
        check_method("dlb-pf")
    with pytest.raises(ConfigError, match="unknown method"):
        method_spec(["dlb-ckf"])


def test_banks_declare_their_covariance_indices():
    pb = PbKfBank(2)
    assert pb.P.shape[1:] == (4, 4) and (pb.P_ITAU, pb.P_IF) == (0, 2)
    pf = PrefilterBank(2, kind="ckf")
    assert pf.P.shape[1:] == (5, 5) and (pf.P_ITAU, pf.P_IF) == (1, 3)
    x = pf.x.copy()
    pf.note_correction(np.ones(2))                 # the inner loop corrected x in place already
    np.testing.assert_array_equal(pf.x, x)


def test_engine_runs_the_scalar_method_through_the_scalar_pipeline(tmp_path):
    from ultratight.ins.imu_data import read_imu_h5
    from ultratight.receiver.deep.engine import UltratightEngine
    from ultratight.receiver.cli.scenario_config import load_scenario
    from ultratight.receiver.cli.scenario_runner import (
        ephemerides_for, load_truth, prepare_data, run_scalar, truth_initial_state)
    from ultratight.signals.recording.iffile import open_if
    cfg = load_scenario("paper-highdyn", {"duration_s": 0.5, "frontend.fs_hz": 2.046e6, "satellites.max_count": 2})
    paths, _ = prepare_data(cfg, 3, tmp_path)
    truth, ephs, init = load_truth(paths["truth"]), ephemerides_for(cfg), truth_initial_state(cfg)
    with open_if(paths["if"]) as src:
        eng = UltratightEngine(src, read_imu_h5(paths["imu"]), ephs, truth["prn"], truth["week"], truth["tow0_s"],
                               method="scalar", init_state=init, duration_s=0.4)
        res = eng.run()
        ref = run_scalar(src, truth["prn"], ephs, truth["week"], truth["tow0_s"], init, 0.4)
    assert res.doppler_hz.shape == ref.doppler_hz.shape and res.doppler_hz.shape[0] > 100
    np.testing.assert_array_equal(res.doppler_hz, ref.doppler_hz)
    np.testing.assert_array_equal(res.code_phase_chips, ref.code_phase_chips)


def test_paper_literal_rackf_gets_algorithm_1_settings():
    from ultratight.receiver.deep.options import EngineOptions
    from ultratight.receiver.deep.tracking_banks import make_tracking_bank
    sig = (np.full(2, 0.05), np.full(2, 0.5))
    from ultratight.signals.signal import GPS_L1CA
    paper = make_tracking_bank(method_spec("dlb-rackf-paper"), 2, EngineOptions(), sig, GPS_L1CA)
    ours = make_tracking_bank(method_spec("dlb-rackf"), 2, EngineOptions(), sig, GPS_L1CA)
    assert (paper.robust_mode, paper.adaptive_stat) == ("period", "epoch")
    assert (ours.robust_mode, ours.adaptive_stat) == ("every", "window")
    assert paper.kind == ours.kind == "rackf"
