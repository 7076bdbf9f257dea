"""How many cores a command uses: the cores free now, the worker processes for a number of jobs,
the threads of the compiled stages, and the check of ``--workers`` — one policy for the scenario
runner, the campaign runner and both receivers.
"""

import math
import os
import time

from ultratight.errors import ConfigError

MAX_WORKERS = 1024             # --workers: beyond this a typo, not a cluster


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


def check_workers(workers, flag="--workers"):
    """``workers`` from the command line: None (automatic) or an integer in 1..MAX_WORKERS."""
    if workers is None:
        return None
    if isinstance(workers, bool) or not isinstance(workers, int) or not 1 <= workers <= MAX_WORKERS:
        raise ConfigError(f"{flag} must be an integer in 1..{MAX_WORKERS}, got {workers!r}")
    return workers


def stage_threads(requested):
    """Threads for the compiled stages that spread channels over numba's thread pool: ``requested``
    when > 0 (capped by the pool), else every thread of the pool when at least 1.25 cores are
    available (:func:`free_cores`), and one otherwise — on a busy machine the threads wait for each
    other at every synchronisation and lose more than they gain."""
    import numba      # lazy: the command line imports this module before it needs numba

    pool = numba.config.NUMBA_NUM_THREADS
    if requested and requested > 0:
        return max(1, min(int(requested), pool))
    return pool if pool > 1 and free_cores() >= 1.25 else 1
