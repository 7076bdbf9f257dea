"""The core policy (ultratight.cores.plan): worker processes and threads from the work and the cores
the process may use, the same on a busy and an idle machine (the load is never read); a worker
whose numba loaded before its thread limit keeps compiling after its pool started; the scenario
command on one and two allowed cores, in one and in several workers."""

import json
import os
import subprocess
import sys
import textwrap

import pytest

from ultratight import cores
from ultratight.receiver.cli import main, scenario_runner


@pytest.fixture
def machine(monkeypatch):
    """``machine(n_cores, load)``: the allowed cores and the 1-minute load average the policy would see;
    returns the list of load-average reads (which must stay empty)."""
    reads = []

    def set_machine(n_cores, load):
        def loadavg():
            reads.append(load)
            return (load, load, load)
        monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(n_cores)), raising=False)
        monkeypatch.setattr(os, "getloadavg", loadavg)
        return reads
    return set_machine


BUSY, IDLE = 7.5, 0.0


@pytest.mark.parametrize("load", [BUSY, IDLE])
def test_plan_follows_the_work_and_the_allowed_cores(machine, load):
    reads = machine(1, load)
    assert cores.allowed_cores() == 1
    assert cores.plan(1) == cores.CorePlan(workers=1, threads=1)
    assert cores.plan(6) == cores.CorePlan(workers=1, threads=1)
    reads = machine(2, load)
    assert cores.allowed_cores() == 2
    assert cores.plan(1) == cores.CorePlan(1, 2)           # one job: both cores as threads
    assert cores.plan(2) == cores.CorePlan(2, 1)           # two jobs: a worker per core
    assert cores.plan(5) == cores.CorePlan(2, 1)
    assert cores.plan(1, n_items=1) == cores.CorePlan(1, 1)   # one channel: one thread
    # --workers and --threads override; workers never exceed the jobs
    assert cores.plan(1, threads=1) == cores.CorePlan(1, 1)
    assert cores.plan(4, workers=3, threads=2) == cores.CorePlan(3, 2)
    assert cores.plan(2, workers=8) == cores.CorePlan(2, 1)
    # a producer beside the jobs (the scenario's streamed IF) keeps a core: the job's threads
    # take the rest, at least one; --threads still overrides
    assert cores.plan(1, reserved=1) == cores.CorePlan(1, 1)
    assert cores.plan(4, workers=4, reserved=1) == cores.CorePlan(4, 1)
    assert cores.plan(1, reserved=1, threads=2) == cores.CorePlan(1, 2)
    reads = machine(4, load)
    assert cores.plan(1, reserved=1) == cores.CorePlan(1, 3)
    assert cores.plan(1, reserved=9) == cores.CorePlan(1, 1)
    assert reads == []


def test_allowed_cores_without_affinity_is_the_cpu_count(monkeypatch):
    monkeypatch.delattr(os, "sched_getaffinity", raising=False)
    monkeypatch.setattr(os, "cpu_count", lambda: 3)
    assert cores.allowed_cores() == 3 and cores.plan(7) == cores.CorePlan(3, 1)
    monkeypatch.setattr(os, "cpu_count", lambda: None)
    assert cores.allowed_cores() == 1


def test_stage_threads_capped_by_numba_pool(machine):
    import numba
    machine(64, IDLE)
    assert cores.stage_threads(0) == numba.config.NUMBA_NUM_THREADS
    assert cores.stage_threads(1) == 1
    assert cores.stage_threads(0, n_items=1) == 1


WORKER_SCRIPT = """
import os, sys
import numba          # loaded before the worker's initializer limits its threads
from ultratight.receiver.cli import workers


def job():
    numba.get_num_threads()                  # starts numba's thread pool, as a parallel stage does
    f = numba.njit(lambda x: x + 1)          # a compilation reads numba's environment again
    return numba.get_num_threads(), f(41)


if __name__ == "__main__":
    with workers.WorkerPool(1, processes=True, threads=int(sys.argv[1])) as pool:
        print(pool.map(job, [()]))
"""


@pytest.mark.parametrize("threads", [1, 2])
def test_worker_compiles_after_its_pool_started(tmp_path, threads):
    """The worker's main module (here the script) loaded numba before the worker's initializer ran:
    setting NUMBA_NUM_THREADS then made numba's next compilation raise "Cannot set NUMBA_NUM_THREADS
    to a different value once the threads have been launched"."""
    script = tmp_path / "drive.py"
    script.write_text(textwrap.dedent(WORKER_SCRIPT))
    r = subprocess.run([sys.executable, str(script), str(threads)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    import numba
    assert r.stdout.strip() == f"[({min(threads, numba.config.NUMBA_NUM_THREADS)}, 42)]"


@pytest.mark.parametrize("n_cores,load,runs,flags,expect", [
    (1, BUSY, 1, [], (1, 1)),                    # one core: one worker, one thread
    (2, IDLE, 1, ["--cache"], (1, 2)),           # two cores, one job on a cached IF file: one worker of two threads
    (2, BUSY, 1, [], (1, 2)),                    # the same job by default: its IF written ahead, read the same way
    (2, BUSY, 1, ["--workers", "2"], (1, 1)),    # its IF generated beside it: the generator keeps a core
    (2, BUSY, 2, [], (2, 1)),                    # two cores, two jobs: two workers of one thread
])
def test_scenario_command_on_one_and_two_cores(machine, monkeypatch, tmp_path, capsys, n_cores, load, runs, flags,
                                               expect):
    from ultratight.receiver.cli import first_run
    reads = machine(n_cores, load)
    # numba's cache holds the engine (a first run would add a compiling worker), whatever ran before
    monkeypatch.setattr(first_run, "engine_kernels_cached", lambda: True)
    pools = []

    class Pool(scenario_runner.WorkerPool):
        def __init__(self, workers, preload=(), processes=None, threads=1, **kw):
            pools.append((workers, threads))
            super().__init__(workers, preload, processes, threads, **kw)

    monkeypatch.setattr(scenario_runner, "WorkerPool", Pool)
    out = tmp_path / "X"
    rc = main(["scenario", "static-open-sky", "--duration", "1", "--methods", "scalar", "--out", str(out),
               "--no-plots", "--quiet", "--runs", str(runs)] + flags)
    err = capsys.readouterr().err
    assert rc == 0, err[-2000:]
    assert "Traceback" not in err and "NUMBA_NUM_THREADS" not in err
    assert pools == [expect] and reads == []
    assert (out / "results.h5").is_file()
    m = json.loads((out / "metrics.json").read_text())
    assert m["runs"] == runs and m["duration_s"] == 1.0
    for run in m["per_run"]["scalar"]:
        # the scalar loops track the generator's truth: no lock lost, Hz-level Doppler, hundredth-chip code
        assert run["lock_lost_channels"] == 0
        assert 0 < run["doppler_rms_hz"][0] < 3.0
        assert 0 < run["code_rms_chips"][0] < 0.02
    # the results do not depend on the workers nor the threads: seed 1 gives the same figures everywhere
    first = m["per_run"]["scalar"][0]
    assert first["seed"] == 1
    assert first["doppler_rms_hz"][0] == pytest.approx(SEED1_DOPPLER_RMS_HZ, rel=1e-12)
    assert first["code_rms_chips"][0] == pytest.approx(SEED1_CODE_RMS_CHIPS, rel=1e-12)


# seed 1 of static-open-sky cut to 1 s, scalar method (ultratight scenario ... --workers 1, one thread),
# with the scenario's real sky (its channels start from predictions without the atmosphere, so the
# code RMS includes the pull-in over the few metres of delay: 0.0033 chip on the vacuum scenario);
# written again when the block noise estimate's sums were reassociated (1.047009644918391 Hz and
# 0.007932321323819262 chip before: float64 rounding carried through the tracking loops)
SEED1_DOPPLER_RMS_HZ = 1.0470072263489618
SEED1_CODE_RMS_CHIPS = 0.007932292611776408
