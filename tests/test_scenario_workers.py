"""`ultratight scenario` with its methods in worker processes gives the tables of the same run in
one process (receiver.workers + scenario_runner), and so does the default: the run's IF generated
once and read by all its methods at the same time (ultratight.signals.synth.ifring)."""

import json
import re

from ultratight.receiver.cli.scenario_runner import run_scenario

CUT = {"frontend.fs_hz": 2.046e6, "satellites.max_count": 3}
TIMING = ("runtime_s", "realtime_factor", "timing_s", "command_timing_s")


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
    from ultratight.receiver.cli import scenario_data, scenario_runner

    class NoShm:
        def __init__(self, *a, **k):
            raise OSError(28, "No space left on device")

    monkeypatch.setattr(scenario_data, "IfRing", NoShm)
    monkeypatch.setattr(scenario_runner, "write_if_ahead", lambda *a, **k: False)    # whatever numba's cache holds
    kw = dict(methods=("dlb-rackf", "pb-kf-utc"), runs=1, seed=4, duration_s=1.0, plots=False, overrides=CUT)
    run_scenario("paper-highdyn", out_dir=tmp_path / "one", workers=1, progress=False, **kw)
    run_scenario("paper-highdyn", out_dir=tmp_path / "fallback", progress=False, **kw)
    err = capsys.readouterr().err
    assert "no shared memory for the IF (No space left on device); each method generates its own copy" in err
    a = _strip(json.loads((tmp_path / "one" / "metrics.json").read_text()))
    b = _strip(json.loads((tmp_path / "fallback" / "metrics.json").read_text()))
    assert a == b


def test_first_run_writes_the_if_while_compiling_then_removes_it(tmp_path, capsys, monkeypatch):
    """numba's cache without the engine (the first run after an install): the IF goes into the cache
    entry while the kernels compile, the methods read it (the same tables), and it is removed after."""
    from ultratight.receiver.cli import first_run
    monkeypatch.setattr(first_run, "engine_kernels_cached", lambda: False)
    kw = dict(methods=("dlb-rackf", "pb-kf-utc"), runs=1, seed=4, duration_s=1.0, plots=False, overrides=CUT)
    run_scenario("paper-highdyn", out_dir=tmp_path / "one", workers=1, progress=False, **kw)
    run_scenario("paper-highdyn", out_dir=tmp_path / "first", progress=True, **kw)
    out = capsys.readouterr().out
    assert "the IF is written into the cache while the kernels compile" in out
    assert re.search(r"in 2 worker process\(es\) of \d+ thread\(s\), the IF read from the cache", out), out
    a = _strip(json.loads((tmp_path / "one" / "metrics.json").read_text()))
    b = _strip(json.loads((tmp_path / "first" / "metrics.json").read_text()))
    assert a == b
    # the entry keeps the truth and IMU, lists no IF, and holds no IF file
    entries = [d for d in (tmp_path / "first" / "cache").iterdir() if (d / "done.json").is_file()]
    run_entry = [d for d in entries if "if" not in json.loads((d / "done.json").read_text())["files"]]
    assert len(run_entry) == len(entries) >= 1
    for d in entries:
        listed = {f["name"] for f in json.loads((d / "done.json").read_text())["files"].values()}
        assert {p.name for p in d.iterdir()} - {"done.json"} <= listed
    # a later run reuses the entry (no regeneration) and streams again
    monkeypatch.setattr(first_run, "engine_kernels_cached", lambda: True)
    run_scenario("paper-highdyn", out_dir=tmp_path / "first", progress=True, **kw)
    out = capsys.readouterr().out
    assert "data reused" in out and "the IF generated once per run and shared" in out
    assert _strip(json.loads((tmp_path / "first" / "metrics.json").read_text())) == a

    # an IF file a --cache run wrote stays where it is
    run_scenario("paper-highdyn", out_dir=tmp_path / "kept", progress=False, cache=True, **kw)
    monkeypatch.setattr(first_run, "engine_kernels_cached", lambda: False)
    run_scenario("paper-highdyn", out_dir=tmp_path / "kept", progress=True, **kw)
    out = capsys.readouterr().out
    assert "the IF read from the cache" in out and "data reused" in out
    assert _strip(json.loads((tmp_path / "kept" / "metrics.json").read_text())) == a
    assert any("if" in json.loads((d / "done.json").read_text())["files"]
               for d in (tmp_path / "kept" / "cache").iterdir() if (d / "done.json").is_file())


def test_one_method_reads_its_if_written_ahead_on_two_cores_and_streams_on_one(tmp_path, capsys, monkeypatch):
    """One run of one method with the default workers: on two or more allowed cores the IF is written into
    the cache entry first and the method reads it with every core (the same tables, the file removed after,
    the command's split in metrics.json); on one core, without room for the file or on a first run after an
    install (the compilation needs the cores), it streams."""
    import time
    from ultratight.receiver.cli import first_run
    kw = dict(methods=("dlb-rackf",), runs=1, seed=5, duration_s=1.0, plots=False, overrides=CUT)
    run_scenario("paper-highdyn", out_dir=tmp_path / "one", workers=1, progress=False, **kw)
    a = _strip(json.loads((tmp_path / "one" / "metrics.json").read_text()))
    cases = {"two": (2, 1e15, True, True), "single": (1, 1e15, True, False), "full": (2, 1.0, True, False),
             "first": (2, 1e15, False, False)}
    for name, (cores, free, compiled, ahead) in cases.items():
        monkeypatch.setattr(first_run, "allowed_cores", lambda c=cores: c)
        monkeypatch.setattr(first_run, "free_disk", lambda _d, f=free: f)
        monkeypatch.setattr(first_run, "engine_kernels_cached", lambda c=compiled: c)
        t0 = time.perf_counter()
        run_scenario("paper-highdyn", out_dir=tmp_path / name, progress=True, **kw)
        wall = time.perf_counter() - t0
        out = capsys.readouterr().out
        assert ("one method: the IF is written into the cache first" in out) == ahead, (name, out)
        assert ("the IF read from the cache" in out) == ahead, (name, out)
        js = json.loads((tmp_path / name / "metrics.json").read_text())
        assert _strip(js) == a, name
        assert not list((tmp_path / name).rglob("*.ci16")), name       # no IF file left behind
        split = js["command_timing_s"]
        assert set(split) == {"start_up_s", "data_s", "methods_s"}
        assert 0 < split["methods_s"] and 0 <= split["data_s"] and split["data_s"] + split["methods_s"] <= wall
        assert split["start_up_s"] is None or split["start_up_s"] >= 0


def test_one_runs_aggregate_is_its_summary_and_several_runs_pool_their_errors():
    """``aggregate`` takes one run's RMS from its summary (the same errors, the same segments) and pools
    the errors of several runs; both against ``segment_rms`` of the errors themselves, and the summary's
    errors against the truth whether or not the truth's unwrapped code phase was kept from a method
    before."""
    from types import SimpleNamespace

    import numpy as np

    from ultratight.receiver.cli import metrics as M
    from ultratight.receiver.cli.scenario_runner import _summarize_method, aggregate

    rng = np.random.default_rng(5)
    n, nch = 60000, 4
    t_truth = np.arange(n + 10) * 1e-3
    truth = {"t_s": t_truth, "doppler_hz": rng.normal(0, 1e3, (n + 10, nch)),
             "code_phase_chips": (np.arange(n + 10)[:, None] * 1023.0 + rng.uniform(0, 1023, nch)) % 1023}

    def result(seed):
        r = np.random.default_rng(seed)
        t = np.arange(n)[:, None] * 1e-3 + np.zeros(nch)
        cp = M.interp_truth(t_truth, M.unwrap_chips(t_truth, truth["code_phase_chips"]), t) + r.normal(0, .01,
                                                                                                       (n, nch))
        dop = M.interp_truth(t_truth, truth["doppler_hz"], t + 0.5e-3) + r.normal(0, 0.1, (n, nch))
        dop[r.integers(0, n, 50), r.integers(0, nch, 50)] = np.nan
        return SimpleNamespace(t_start=t, doppler_hz=dop, code_phase_chips=cp % 1023, runtime_s=1.0, duration_s=60.0,
                               info={})

    fresh = dict(truth)
    summ, raw0 = _summarize_method(result(1), fresh, 1, 1)
    assert "code_phase_unwrapped" in fresh
    again, _ = _summarize_method(result(1), fresh, 1, 1)          # the kept unwrapped code phase
    assert json.dumps(summ, sort_keys=True) == json.dumps(again, sort_keys=True)
    one = aggregate([summ], {(0, "m"): raw0}, "m", M.SEGMENTS_S, 1)
    assert one["doppler_rms_hz"] == M.segment_rms(raw0[0].t_start, raw0[1], M.SEGMENTS_S).tolist()
    assert one["code_rms_chips_channel"] == M.segment_rms(raw0[0].t_start, raw0[2], M.SEGMENTS_S, 1).tolist()
    summ2, raw1 = _summarize_method(result(2), dict(truth), 1, 2)
    two = aggregate([summ, summ2], {(0, "m"): raw0, (1, "m"): raw1}, "m", M.SEGMENTS_S, 1)
    t = np.concatenate([raw0[0].t_start, raw1[0].t_start])
    d = np.concatenate([raw0[1], raw1[1]])
    assert two["doppler_rms_hz"] == M.segment_rms(t, d, M.SEGMENTS_S).tolist()
    assert two["doppler_rms_hz"] != one["doppler_rms_hz"]
