"""Independent jobs of one command (the methods of a scenario run, the runs of ``--runs N``) in
separate processes when more than one core is free.

Each job runs in a worker process started with ``spawn`` (no state shared with the parent: numba's
thread pool, open files and signal handlers start fresh), one numba thread per worker, so two
workers use two cores without competing for them. The results come back in the order of the jobs;
the first failure cancels the jobs not yet started and is raised in the parent.
"""

import ctypes
import importlib
import math
import multiprocessing
import os
import time
from concurrent.futures import FIRST_EXCEPTION, ProcessPoolExecutor, wait

import numba

from ultratight.errors import ConfigError


def _cpu_times():
    """(available, total) jiffies of all CPUs from /proc/stat — available: idle, waiting for I/O or
    running niced work (which yields to ours) — or None where there is none."""
    try:
        with open("/proc/stat") as f:
            v = [int(x) for x in f.readline().split()[1:]]
    except (OSError, ValueError):
        return None
    return v[1] + v[3] + (v[4] if len(v) > 4 else 0), sum(v[:8])


_FREE = {"t": -1e9, "v": 0.0}     # last measurement (reused for a few seconds: many short runs)


def free_cores(window_s=0.2, max_age_s=5.0):
    """Available cores now: the share of all CPUs idle or running niced work over ``window_s``
    (``/proc/stat``) times the core count; where that is not available, the cores not busy by the 1-minute load average. (The load
    average alone lags by a minute: right after a heavy job it still counts that job.)"""
    n = os.cpu_count() or 1
    now = time.monotonic()
    if now - _FREE["t"] < max_age_s:
        return _FREE["v"]
    a = _cpu_times()
    if a is not None:
        time.sleep(window_s)
        b = _cpu_times()
        if b is not None and b[1] > a[1]:
            _FREE.update(t=time.monotonic(), v=n * (b[0] - a[0]) / (b[1] - a[1]))
            return _FREE["v"]
    try:
        load = os.getloadavg()[0]
    except OSError:
        load = 0.0
    return max(0.0, n - load)


def default_workers(n_jobs):
    """Worker processes for ``n_jobs`` jobs: one per available core (a core counts when at least a
    quarter of it is available), at most one per job; 1 (run in this process) when fewer than about
    1.25 cores are available."""
    k = int(math.floor(free_cores() + 0.75))
    return max(1, min(int(n_jobs), k))


def check_workers(workers):
    """``workers`` from the command line: None (automatic) or an integer >= 1."""
    if workers is None:
        return None
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ConfigError(f"--workers must be an integer >= 1, got {workers!r}")
    return workers


def stage_threads(requested):
    """Threads for the compiled stages that spread channels over numba's thread pool: ``requested``
    when > 0 (capped by the pool), else every thread of the pool when at least 1.25 cores are
    available (:func:`free_cores`), and one otherwise — on a busy machine the threads wait for each
    other at every synchronisation and lose more than they gain."""
    pool = numba.config.NUMBA_NUM_THREADS
    if requested and requested > 0:
        return max(1, min(int(requested), pool))
    return pool if pool > 1 and free_cores() >= 1.25 else 1


M_MMAP_THRESHOLD = -3          # glibc mallopt parameters
M_TRIM_THRESHOLD = -1
MMAP_THRESHOLD = 1 << 20       # bytes: larger blocks are mapped on their own and unmapped when freed
# a worker that streams IF keeps its block buffers (about 3.5 MB at 4 MHz) on the heap for reuse
STREAM_MMAP_THRESHOLD = 4 << 20
STREAM_TRIM_THRESHOLD = 16 << 20   # bytes of free heap top kept before they are returned


def _libc():
    global _LIBC
    if _LIBC is None:
        try:
            lib = ctypes.CDLL(None)
            _LIBC = lib if hasattr(lib, "malloc_trim") and hasattr(lib, "mallopt") else False
        except OSError:
            _LIBC = False
    return _LIBC


_LIBC = None


def fix_mmap_threshold(streaming=False):
    """Keep glibc's mmap threshold at :data:`MMAP_THRESHOLD` (``mallopt``; nothing elsewhere). By default
    glibc raises the threshold to the size of every mapped block freed (up to 32 MB), after which
    the per-epoch result arrays of a run (6 MB each) come from the heap and, once freed, stay in the
    resident set; with a fixed threshold they are unmapped when freed. True when set.

    ``streaming`` (a worker that reads a streamed IF): :data:`STREAM_MMAP_THRESHOLD` and a heap top of
    :data:`STREAM_TRIM_THRESHOLD` kept, so that the IF blocks decoded every 100 ms reuse the freed
    memory of the last ones instead of mapping fresh pages: the main job's page faults fell from
    4.5 to 1.9 million and its system time from 6.8 to 4.3 s."""
    lib = _libc()
    if not lib:
        return False
    if not streaming:
        return bool(lib.mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD))
    return bool(lib.mallopt(M_MMAP_THRESHOLD, STREAM_MMAP_THRESHOLD)
                and lib.mallopt(M_TRIM_THRESHOLD, STREAM_TRIM_THRESHOLD))


def release_heap():
    """Hand the C heap's free pages back to the operating system (glibc ``malloc_trim``; nothing
    elsewhere). Between the stages of a long run (data preparation, one method after another) the
    many small arrays of a finished stage leave the heap fragmented, and its free pages would
    otherwise stay in the resident set for the rest of the run. True when memory was returned."""
    lib = _libc()
    return bool(lib.malloc_trim(0)) if lib else False


def _init_worker(preload):
    os.environ["NUMBA_NUM_THREADS"] = "1"
    fix_mmap_threshold(streaming=True)
    for name in preload:              # import the job's modules now, while the parent still works
        importlib.import_module(name)


def _ready():
    return os.getpid()


class WorkerPool:
    """``workers`` spawned worker processes (none when ``workers`` <= 1: jobs then run in this
    process; ``processes=True`` spawns one then too). Started on entering the ``with`` block, with the
    modules of ``preload`` imported by every worker at once — so their start-up overlaps what the
    parent does before :meth:`map`."""

    def __init__(self, workers, preload=(), processes=None):
        self.workers = max(1, int(workers))
        self.preload = tuple(preload)
        self.processes = self.workers > 1 if processes is None else bool(processes)
        self._pool = None

    def __enter__(self):
        if self.processes:
            ctx = multiprocessing.get_context("spawn")
            self._pool = ProcessPoolExecutor(max_workers=self.workers, mp_context=ctx, initializer=_init_worker,
                                             initargs=(self.preload,))
            self._warm = [self._pool.submit(_ready) for _ in range(self.workers)]   # spawns them all now
        return self

    def __exit__(self, *exc):
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
        return False

    def map(self, fn, jobs, on_done=None):
        """``[fn(*job) for job in jobs]`` in the workers (module-level ``fn``, picklable arguments and
        results); ``on_done(i, result)`` in this process as each job finishes; the first failure
        cancels the jobs not yet started and is raised here."""
        jobs = list(jobs)
        if self._pool is None:
            out = []
            for i, job in enumerate(jobs):
                out.append(fn(*job))
                if on_done is not None:
                    on_done(i, out[-1])
            return out
        results = [None] * len(jobs)
        futs = {self._pool.submit(fn, *job): i for i, job in enumerate(jobs)}
        pending = set(futs)
        try:
            while pending:
                done, pending = wait(pending, return_when=FIRST_EXCEPTION)
                for f in done:
                    i = futs[f]
                    results[i] = f.result()          # raises the job's exception
                    if on_done is not None:
                        on_done(i, results[i])
        except BaseException:
            for f in pending:
                f.cancel()
            raise
        return results


def run_jobs(fn, jobs, workers=None, on_done=None):
    """``[fn(*job) for job in jobs]``, in worker processes when ``workers`` (default
    :func:`default_workers`) is above 1 (:class:`WorkerPool`)."""
    jobs = list(jobs)
    workers = default_workers(len(jobs)) if workers is None else min(int(workers), max(1, len(jobs)))
    with WorkerPool(workers if len(jobs) > 1 else 1) as pool:
        return pool.map(fn, jobs, on_done)
