"""All in view: every satellite acquired is tracked by default, the others are searched again on a
schedule, and a satellite that appears during the run is acquired."""

import math
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest


def test_default_is_all_in_view_and_validates():
    from ultratight.errors import ConfigError
    from ultratight.receiver.scalar.receiver import ProcessConfig
    cfg = ProcessConfig()
    assert cfg.n_channels is None
    with pytest.raises(ConfigError, match="search interval"):
        ProcessConfig(search_every_s=0.0).validate(type("S", (), {"fs_hz": 4e6})())


def test_satellite_appearing_during_the_run_is_acquired(tmp_path):
    """PRN 16 is 3.11 deg high and rising at TOW 567000; with the generator's horizon at 3.14 deg its
    signal starts ~8 s into the run.  The cold start cannot find it; the periodic search (every 5 s
    here) must, within one interval of its appearance plus the search's own block."""
    from ultratight.receiver.scalar.receiver import ProcessConfig, process
    from ultratight.receiver.cli.scenario_config import load_scenario
    from ultratight.signals.synth.generator import generate
    # without the scenario's atmosphere: the receiver's corrections are off
    cfg = load_scenario("static-open-sky", {"time.tow_s": 567000.0, "duration_s": 22.0, "frontend.fs_hz": 2.0e6,
                                            "satellites.mask_deg": 3.0, "satellites.horizon_deg": 3.14,
                                            "atmosphere.iono": "off", "atmosphere.tropo": "off",
                                            "atmosphere.broadcast": False})
    files = generate(cfg, tmp_path, "rise", progress=False)
    with h5py.File(files["truth"], "r") as f:
        prns = [int(p) for p in f.attrs["prn"]]
        k = prns.index(16)
        el, t = f["elev_deg"][:, k], f["t_s"][:]
    t_appear = float(t[np.flatnonzero(el > 3.14)[0]])
    assert 5.0 < t_appear < 12.0
    res = process(files["if"], ProcessConfig(search_every_s=5.0, iono="off", tropo="off"))
    ch = {c["prn"]: c for c in res.channels}
    assert 16 not in {a.prn for a in res.acquisition[:32] if a.detected}      # not at the cold start
    assert all(ch[p]["started"] and ch[p]["acquired_s"] < 0.1 for p in prns if p != 16)
    assert ch[16]["started"] and t_appear <= ch[16]["acquired_s"] <= t_appear + 5.0 + 0.5
    assert ch[16]["tracked"] and res.searches >= 2
    # no satellite that is not in the signal was started
    assert {p for p, c in ch.items() if c["started"]} == set(prns)


@pytest.mark.slow
def test_acceptance_rising_satellite_10min():
    """10-minute run (benchmarks/acceptance_all_in_view.py): PRN 16 crosses the 5 deg mask at ~505 s
    and is acquired within 30 s; every satellite above the mask is used within 30 s of the first fix."""
    import tempfile
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    from acceptance_all_in_view import run
    with tempfile.TemporaryDirectory() as tmp:
        r = run(tmp)
    print("\n", r)
    ff = r["first_fix_s"]
    rising = [p for p, v in r["satellites"].items() if v["above_mask_s"] is not None and v["above_mask_s"] > ff]
    assert rising                                           # the run does contain a rising satellite
    for p, v in r["satellites"].items():
        if v["above_mask_s"] is None:
            continue
        assert v["acquired_s"] is not None and v["acquired_s"] <= v["above_mask_s"] + 30.0, (p, v)
        if p not in rising:
            assert v["first_used_s"] is not None and v["first_used_s"] <= ff + 30.0, (p, v)
