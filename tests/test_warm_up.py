"""Compile once (receiver.cli.workers.warm_up, scenario_runner._warm_methods): the kernels of a scenario's
methods are compiled by one worker, one method after the other, on data of its own while the runs' data are
generated, before any job reaches the workers; with a warm cache only the first method runs there."""

import os
from types import SimpleNamespace

import numba
import numpy as np
import pytest

from _procs import running_since
from ultratight.receiver.cli import scenario_runner, workers


def _fresh_kernel_call(x):
    """Compile and call a kernel numba has never seen (a new function object each call)."""
    return numba.njit(lambda v: v * 2 + 1)(x)


def test_warm_up_counts_compilations_and_runs_every_job_when_cold(capsys):
    seen = []

    def job(x):
        seen.append(x)
        assert _fresh_kernel_call(x) == 2 * x + 1
        # the line saying why the run waits comes with the first compilation, once
        out = capsys.readouterr().out
        assert ("numba: compiling the kernels once" in out) == (x == 1)

    assert workers.warm_up(job, [(1,), (2,), (3,)], progress=True) == 3
    assert seen == [1, 2, 3]
    assert capsys.readouterr().out.startswith("numba: 3 kernel(s) compiled in ")


def test_warm_up_skips_the_rest_when_the_first_job_compiled_nothing():
    kernel = numba.njit(lambda v: v - 1)
    kernel(np.int64(5))                     # compiled before: later calls load nothing new
    seen = []

    def job(x):
        seen.append(x)
        assert kernel(np.int64(x)) == x - 1

    assert workers.warm_up(job, [(1,), (2,), (3,)]) == 0
    assert seen == [1]


def test_a_failing_warm_up_job_is_left_to_the_job_proper():
    seen = []

    def job(x):
        seen.append(x)
        _fresh_kernel_call(x)
        if x == 1:
            raise ValueError("too short a cut for this setting")

    assert workers.warm_up(job, [(1,), (2,)]) == 2
    assert seen == [1, 2]


class _Stop(Exception):
    pass


@pytest.fixture
def recorded_run(monkeypatch):
    """``_run_all`` with the data, the engine and the pool replaced by recorders: the events in order
    (("start", workers, threads), ("call", function) for what one worker runs, ("method", name,
    duration_s, threads), ("jobs", names)); the pool stops the run when it is handed the jobs."""
    events = []
    state = {"cold": True}

    class Pool:
        def __init__(self, workers, preload=(), processes=None, threads=1, join_on_exit=True, fork=False):
            events.append(("start", workers, threads))

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return False

        def call(self, fn, *args):
            events.append(("call", fn.__name__))
            return fn(*args)

        def start(self, fn, *args):          # runs at once here; the data are generated after it
            events.append(("call", fn.__name__))
            res = fn(*args)
            return SimpleNamespace(result=lambda: res)

        def map(self, fn, jobs, on_done=None):
            events.append(("jobs", [j[2] for j in jobs]))
            raise _Stop

    def run_method(paths, cfg, method, seed, options=None, startup_errors=None, duration_s=None):
        events.append(("method", method, duration_s, getattr(options, "threads", None)))
        if state["cold"]:
            _fresh_kernel_call(3)                 # an empty cache: the method's kernels compile now

    monkeypatch.setattr(scenario_runner, "WorkerPool", Pool)
    monkeypatch.setattr(scenario_runner, "write_if_ahead", lambda *a, **k: False)    # whatever numba's cache holds
    # whatever runs completed before: no run of this kind known (test_a_known_warm_cache_skips_the_warm_up)
    monkeypatch.setattr(scenario_runner, "warm_cache_known", lambda key: state.get("known", False))
    monkeypatch.setattr(scenario_runner, "note_warm_cache", lambda key: events.append(("noted", key)))
    monkeypatch.setattr(scenario_runner, "run_method", run_method)
    # a first run: the epoch chain's late part compiled ahead in another worker (recorded, not compiled here)
    monkeypatch.setattr(scenario_runner, "first_compilation", lambda: state["cold"])
    def compile_ahead():
        pass

    monkeypatch.setattr(scenario_runner, "compile_ahead", compile_ahead)
    monkeypatch.setattr(scenario_runner, "_prepare_run", lambda cfg, r, *a, **k: {"truth": "t.h5", "if_seed": r})
    # the warm-up's own short data (not the run's)
    monkeypatch.setattr(scenario_runner, "prepare_data",
                        lambda cfg, seed, out, **k: ({"truth": "warm.h5", "if_seed": seed}, False))

    def go(methods, workers=None, cold=True, known=False):
        state["cold"] = cold
        state["known"] = known
        cfg = scenario_runner.scenario_config("paper-highdyn", methods, 1, 2.0)
        shared = workers is None and len(methods) > 1
        if shared:
            def map_shared(pool, cfg, methods, base_seed, out, channel, progress, tail, all_paths, done, ready=None):
                if ready is not None:
                    ready()             # the warm-up, waited for before the jobs are handed out
                pool.map(None, [({}, cfg, m, base_seed) + tail for m in methods])

            monkeypatch.setattr(scenario_runner, "_map_shared", map_shared)
        with pytest.raises(_Stop):
            scenario_runner._run_all(cfg, list(methods), 1, 1, "unused", 0, False, None, workers)
        return events

    return go


@pytest.mark.parametrize("workers", [None, 2])          # the shared IF ring, and one stream per method
def test_methods_warmed_by_one_worker_before_the_workers_get_jobs(recorded_run, workers):
    methods = ["pb-kf-utc", "dlb-ukf", "dlb-ckf", "dlb-rackf"]
    events = recorded_run(methods, workers)
    start, ahead, call, *warm, jobs = events
    assert start[0] == "start" and start[1] >= 2
    threads = start[2]
    # another worker compiles the epoch chain's late part meanwhile (numba's cache is empty here)
    assert ahead == ("call", "compile_ahead")
    # in one worker: every method once, on the workers' threads, WARM_S of signal; then the jobs
    assert call == ("call", "_warm_methods")
    assert warm == [("method", m, scenario_runner.WARM_S, threads) for m in methods]
    assert jobs == ("jobs", methods)


def test_warm_cache_runs_only_the_first_method_here(recorded_run):
    events = recorded_run(["dlb-rackf", "dlb-ckf", "pb-kf-utc"], workers=3, cold=False)
    assert [e[:3] for e in events[1:]] == [("call", "_warm_methods"), ("method", "dlb-rackf", scenario_runner.WARM_S),
                                          ("jobs", ["dlb-rackf", "dlb-ckf", "pb-kf-utc"])]


def test_a_known_warm_cache_skips_the_warm_up(recorded_run):
    """A run of the same kind completed since the sources changed (first_run.warm_cache_known): the
    workers get their jobs at once; on a first run (the engine not in the cache) the warm-up stays."""
    events = recorded_run(["dlb-rackf", "dlb-ckf", "pb-kf-utc"], workers=3, cold=False, known=True)
    assert [e[0] for e in events] == ["start", "jobs"]
    events.clear()
    events = recorded_run(["dlb-rackf", "dlb-ckf"], workers=2, cold=True, known=True)
    assert ("call", "_warm_methods") in events


def test_the_kind_of_run_follows_the_sources(tmp_path, monkeypatch):
    """warm_key changes with a source file's modification time or size and with the run's settings;
    note_warm_cache / warm_cache_known keep the keys in a marker beside numba's cache."""
    from ultratight.receiver.cli import first_run
    src = tmp_path / "src" / "pkg"
    src.mkdir(parents=True)
    (src / "a.py").write_text("x = 1\n")
    (src / "b.py").write_text("y = 2\n")
    monkeypatch.setattr(first_run, "_marker_path", lambda: tmp_path / first_run.WARM_MARKER)

    def key(*what):
        return first_run.warm_key(*what, root=tmp_path / "src")

    a = key(["dlb-rackf"], 1, {"frontend": {"fs_hz": 4e6}})
    assert a == key(["dlb-rackf"], 1, {"frontend": {"fs_hz": 4e6}})
    assert a != key(["dlb-ckf"], 1, {"frontend": {"fs_hz": 4e6}})
    assert a != key(["dlb-rackf"], 1, {"frontend": {"fs_hz": 2e6}})
    assert not first_run.warm_cache_known(a)
    first_run.note_warm_cache(a)
    assert first_run.warm_cache_known(a)
    st = (src / "a.py").stat()
    os.utime(src / "a.py", ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000_000))
    b = key(["dlb-rackf"], 1, {"frontend": {"fs_hz": 4e6}})
    assert b != a and not first_run.warm_cache_known(b)
    os.utime(src / "a.py", ns=(st.st_atime_ns, st.st_mtime_ns))
    assert key(["dlb-rackf"], 1, {"frontend": {"fs_hz": 4e6}}) == a
    (src / "b.py").write_text("y = 22\n")              # another size
    assert key(["dlb-rackf"], 1, {"frontend": {"fs_hz": 4e6}}) != a


@pytest.mark.parametrize("methods,workers,cold", [
    (["dlb-rackf", "dlb-ckf"], 1, True),     # --workers 1: the jobs run here, one after the other
    (["dlb-rackf"], None, False),           # one job, the kernels in numba's cache: one worker, no warm-up
])
def test_no_warm_up_without_several_workers(recorded_run, methods, workers, cold):
    events = recorded_run(methods, workers, cold=cold)
    assert [e[0] for e in events] == ["start", "jobs"] and events[0][1] == 1


def test_one_job_on_a_first_run_compiles_in_two_workers_while_the_data_are_made(recorded_run):
    events = recorded_run(["dlb-rackf"], None, cold=True)
    assert events[0][0] == "start" and events[0][1] == 2
    assert [e[:2] for e in events[1:]] == [("call", "compile_ahead"), ("call", "_warm_methods"),
                                          ("method", "dlb-rackf"), ("jobs", ["dlb-rackf"])]


def test_pool_call_runs_in_one_worker_process():
    with workers.WorkerPool(2, processes=True) as pool:
        pid = pool.call(os.getpid)
    assert pid != os.getpid()
    with workers.WorkerPool(1) as pool:              # no worker processes: here
        assert pool.call(os.getpid) == os.getpid()


@pytest.mark.parametrize("cached", [True, False])
def test_process_compiles_ahead_in_a_helper_only_on_a_first_run(monkeypatch, cached):
    """``process --mode ultratight`` runs inside first_run.compiling_ahead: on a first run a helper
    process compiles the engine's epoch chain beside it (here the kernels are cached, so it loads them)
    and is gone afterwards; otherwise no process is started."""
    import multiprocessing

    from ultratight.receiver.cli import first_run
    monkeypatch.setattr(first_run, "engine_kernels_cached", lambda: cached)
    before = set(multiprocessing.active_children())
    with first_run.compiling_ahead():
        during = set(multiprocessing.active_children()) - before
    assert len(during) == (0 if cached else 1)
    assert not running_since(before)


def test_an_error_in_the_body_stops_the_helper(monkeypatch):
    import multiprocessing

    from ultratight.receiver.cli import first_run
    monkeypatch.setattr(first_run, "engine_kernels_cached", lambda: False)
    before = set(multiprocessing.active_children())
    with pytest.raises(KeyboardInterrupt):
        with first_run.compiling_ahead():
            raise KeyboardInterrupt
    assert not running_since(before)
