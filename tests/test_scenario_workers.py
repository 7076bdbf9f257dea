"""`ultratight scenario` with its methods in worker processes gives the tables of the same run in
one process (receiver.workers + scenario_runner), and so does the default: the run's IF generated
once and read by all its methods at the same time (ultratight.signals.synth.ifring)."""

import json
import re

from ultratight.receiver.cli.scenario_runner import run_scenario

CUT = {"frontend.fs_hz": 2.046e6, "satellites.max_count": 3}
TIMING = ("runtime_s", "realtime_factor", "timing_s")


def _strip(o):
    """The summary without wall-clock figures (they differ between any two runs)."""
    if isinstance(o, dict):
        return {k: _strip(v) for k, v in o.items() if k not in TIMING}
    if isinstance(o, list):
        return [_strip(v) for v in o]
    return o


def test_methods_in_workers_equal_methods_here(tmp_path):
    kw = dict(methods=("dlb-rackf", "pb-kf-utc", "dlb-ckf"), runs=2, seed=3, duration_s=1.0, plots=False,
              progress=False, overrides=CUT)
    run_scenario("paper-highdyn", out_dir=tmp_path / "one", workers=1, **kw)
    run_scenario("paper-highdyn", out_dir=tmp_path / "two", workers=2, **kw)
    a = _strip(json.loads((tmp_path / "one" / "metrics.json").read_text()))
    b = _strip(json.loads((tmp_path / "two" / "metrics.json").read_text()))
    assert a["methods"].keys() == b["methods"].keys() == {"dlb-rackf", "pb-kf-utc", "dlb-ckf"}
    assert a == b


def test_shared_if_ring_equals_one_stream_per_method(tmp_path, capsys):
    kw = dict(methods=("dlb-rackf", "pb-kf-utc", "scalar"), runs=2, seed=4, duration_s=1.0, plots=False,
              overrides=CUT)
    run_scenario("paper-highdyn", out_dir=tmp_path / "one", workers=1, progress=False, **kw)
    run_scenario("paper-highdyn", out_dir=tmp_path / "ring", progress=True, **kw)     # the default workers
    out = capsys.readouterr().out
    assert re.search(r"in 3 worker process\(es\) of \d+ thread\(s\), the IF generated once per run and shared", out), out
    a = _strip(json.loads((tmp_path / "one" / "metrics.json").read_text()))
    b = _strip(json.loads((tmp_path / "ring" / "metrics.json").read_text()))
    assert a == b


def test_without_shared_memory_each_method_streams_its_own_if(tmp_path, capsys, monkeypatch):
    from ultratight.receiver.cli import scenario_runner
    class NoShm:
        def __init__(self, *a, **k):
            raise OSError(28, "No space left on device")

    monkeypatch.setattr(scenario_runner, "IfRing", NoShm)
    kw = dict(methods=("dlb-rackf", "pb-kf-utc"), runs=1, seed=4, duration_s=1.0, plots=False, overrides=CUT)
    run_scenario("paper-highdyn", out_dir=tmp_path / "one", workers=1, progress=False, **kw)
    run_scenario("paper-highdyn", out_dir=tmp_path / "fallback", progress=False, **kw)
    err = capsys.readouterr().err
    assert "no shared memory for the IF (No space left on device); each method generates its own copy" in err
    a = _strip(json.loads((tmp_path / "one" / "metrics.json").read_text()))
    b = _strip(json.loads((tmp_path / "fallback" / "metrics.json").read_text()))
    assert a == b
