"""Jobs in worker processes (receiver.workers): same results, in order, as in this process; a
failing job's error reaches the caller; the worker count check."""

import math

import pytest

from _procs import running_since
from ultratight.errors import ConfigError
from ultratight.receiver.cli import workers
def test_jobs_in_processes_equal_jobs_here():
    jobs = [(n,) for n in (5, 10, 3, 20)]
    seen = []
    here = workers.run_jobs(math.factorial, jobs, workers=1)
    there = workers.run_jobs(math.factorial, jobs, workers=2, on_done=lambda i, r: seen.append(i))
    assert there == here == [120, 3628800, 6, 2432902008176640000]
    assert sorted(seen) == [0, 1, 2, 3]


def test_a_failing_job_raises_in_the_caller():
    with pytest.raises(ValueError):
        workers.run_jobs(math.sqrt, [(4.0,), (-1.0,), (9.0,)], workers=2)


def test_worker_count():
    assert workers.check_workers(None) is None and workers.check_workers(3) == 3
    for bad in (0, -1, 1.5, True):
        with pytest.raises(ConfigError, match="--workers"):
            workers.check_workers(bad)


def test_a_failure_here_does_not_wait_for_the_queued_jobs():
    """An error (or an interruption) in this process while the workers run: the jobs still queued or
    running are stopped, not waited for (each would sleep 30 s)."""
    import signal
    import time
    t0 = time.perf_counter()
    with pytest.raises(RuntimeError, match="stop"):
        with workers.WorkerPool(2, processes=True) as pool:
            futs = [pool.start(time.sleep, 30.0) for _ in range(4)]
            time.sleep(1.0)
            raise RuntimeError("stop")
    assert time.perf_counter() - t0 < 20.0
    # none ran to its end: each was cancelled, or stopped with its worker
    assert not any(f.done() and not f.cancelled() and f.exception() is None for f in futs)
    # a worker's SIGINT: a running job stops with KeyboardInterrupt, an idle worker exits quietly
    assert workers._BUSY is False
    with pytest.raises(SystemExit) as ex:
        workers._on_sigint(signal.SIGINT, None)
    assert ex.value.code == 128 + signal.SIGINT
    with pytest.raises(KeyboardInterrupt):
        workers._run_job(workers._on_sigint, (signal.SIGINT, None))
    assert workers._BUSY is False


def _pid_and_exit_later():
    import os
    return os.getpid()


@pytest.mark.parametrize("join", [True, False])
def test_workers_end_with_status_zero_whether_joined_or_not(join):
    """The workers end through :func:`workers._exit_now` (no interpreter teardown) with status 0; with
    ``join_on_exit=False`` leaving the block does not wait for them, and they still end."""
    import time
    with workers.WorkerPool(2, processes=True, join_on_exit=join) as pool:
        pool.map(_pid_and_exit_later, [(), ()])
        procs = list(pool._pool._processes.values())
    t0 = time.perf_counter()        # the executor's thread reaps them: their status is polled
    while any(p.exitcode is None for p in procs) and time.perf_counter() - t0 < 30.0:
        time.sleep(0.05)
    assert [p.exitcode for p in procs] == [0, 0]


def test_a_worker_ended_by_a_signal_keeps_its_status():
    """An idle worker's SIGINT ends it with 128 + SIGINT, also through the fast exit."""
    import multiprocessing
    import os
    import signal
    import time
    ctx = multiprocessing.get_context("spawn")
    p = ctx.Process(target=_idle_worker)
    p.start()
    time.sleep(3.0)                 # the worker imports and waits
    assert p.exitcode is None
    os.kill(p.pid, signal.SIGINT)
    p.join(timeout=30)
    assert p.exitcode == 128 + signal.SIGINT


def _idle_worker():
    import time
    workers._init_worker(())
    while True:
        time.sleep(0.1)


def _touch_and_sleep(path):
    import time
    open(path, "w").close()
    time.sleep(60.0)


@pytest.mark.parametrize("how", ["ignored", "blocked"])
def test_workers_stop_on_an_error_even_when_the_parent_ignores_sigterm(tmp_path, how):
    """A run ignores further signals once interrupted (and a campaign blocks them while its cluster
    starts); workers started meanwhile still take SIGTERM, so an error stops a running job at once
    (WorkerPool.__exit__; SIGKILL only after 10 s)."""
    import multiprocessing
    import signal
    import time
    before = set(multiprocessing.active_children())
    old = signal.getsignal(signal.SIGTERM)
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, [])
    if how == "ignored":
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
    else:
        signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGTERM})
    started = tmp_path / "started"
    try:
        with pytest.raises(RuntimeError, match="stop"):
            with workers.WorkerPool(1, processes=True) as pool:
                pool.start(_touch_and_sleep, str(started))
                t_wait = time.perf_counter()
                while not started.exists() and time.perf_counter() - t_wait < 60.0:
                    time.sleep(0.05)
                assert started.exists()
                t0 = time.perf_counter()
                raise RuntimeError("stop")
        assert time.perf_counter() - t0 < 9.0
    finally:
        signal.signal(signal.SIGTERM, old)
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)
    assert not running_since(before)


FORKED_POOL = r"""
import json, signal, sys, threading
from multiprocessing import shared_memory
from ultratight import io_guard
from ultratight.receiver.cli import workers

def state(name):
    import signal
    from multiprocessing import shared_memory
    seg = shared_memory.SharedMemory(name=name)      # attached as a ring consumer does
    first = bytes(seg.buf[:4])
    seg.close()
    return {"hup": str(signal.getsignal(signal.SIGHUP)), "term": str(signal.getsignal(signal.SIGTERM)),
            "int": getattr(signal.getsignal(signal.SIGINT), "__name__", "?"), "first": first.hex(),
            "module": "ultratight.receiver.cli.scenario_runner" in sys.modules}

if __name__ == "__main__":
    io_guard.install_signal_handlers()
    import ultratight.receiver.cli.scenario_runner            # imported here: a forked worker has it
    out = {"safe": workers.fork_is_safe()}
    seg = None
    try:
        with workers.WorkerPool(2, processes=True, fork=sys.argv[1] == "fork") as pool:
            out["method"] = pool.start_method
            # made after the workers started, as a run's IF ring is
            seg = shared_memory.SharedMemory(create=True, size=4096)
            seg.buf[:4] = b"ring"
            out["jobs"] = pool.map(state, [(seg.name,), (seg.name,)])
        # the workers have ended: the segment is still there (no tracker of their own removed it)
        again = shared_memory.SharedMemory(name=seg.name)
        out["after"] = bytes(again.buf[:4]).hex()
        again.close()
        import h5py
        import tempfile
        with tempfile.TemporaryDirectory() as d:
            with h5py.File(d + "/open.h5", "w"):
                out["safe_with_an_open_hdf5_file"] = workers.fork_is_safe()
        out["safe_again"] = workers.fork_is_safe()
        t = threading.Thread(target=threading.Event().wait, args=(5.0,), daemon=True)
        t.start()
        out["safe_with_a_thread"] = workers.fork_is_safe()
    finally:
        if seg is not None:
            seg.close()
            seg.unlink()
    print(json.dumps(out))
"""


@pytest.mark.skipif(not hasattr(__import__("os"), "fork"), reason="no fork on this system")
@pytest.mark.parametrize("how", ["fork", "spawn"])
def test_forked_workers_start_like_spawned_ones(tmp_path, how):
    """``WorkerPool(fork=True)`` forks when nothing else runs in the process: the workers have the
    parent's modules, the CLI's signal handlers are back to the defaults a spawned worker has (SIGHUP
    ends it; SIGINT is the worker's own), and they share the parent's resource tracker, so shared memory
    they attached outlives them (a ring consumer must not remove the ring). Not with another thread
    running or an HDF5 file open; ``fork=False`` spawns."""
    import json
    import subprocess
    import sys
    script = tmp_path / "pool.py"
    script.write_text(FORKED_POOL)
    r = subprocess.run([sys.executable, str(script), how], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "leaked" not in r.stderr and "resource_tracker" not in r.stderr, r.stderr
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert out["safe"] is True and out["safe_again"] is True
    assert out["safe_with_a_thread"] is False and out["safe_with_an_open_hdf5_file"] is False
    assert out["method"] == how
    for job in out["jobs"]:
        assert job["hup"] == str(signal_default()) and job["term"] == str(signal_default())
        assert job["int"] == "_on_sigint"
        assert job["first"] == b"ring".hex()
        assert job["module"] is (how == "fork")
    assert out["after"] == b"ring".hex()


def signal_default():
    import signal
    return signal.SIG_DFL
