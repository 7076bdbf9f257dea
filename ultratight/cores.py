"""How many cores a command uses — one policy for the scenario runner, the campaign runner and both
receivers: worker processes and threads per worker from the size of the work and the cores this
process may run on (its CPU affinity), never from the machine's momentary load. ``--workers`` and
``--threads`` override it.

The load is left out on purpose: a decision that follows the load average (or ``/proc/stat``)
changes from one run to the next with whatever else runs, so the same command took different code
paths (threaded or not, in worker processes or not) and gave different run times on the same
machine. Waiting numba threads sleep instead of spinning (``OMP_WAIT_POLICY=PASSIVE``, set in
:mod:`ultratight`), so a thread per allowed core costs little when another process takes a core.
"""

import os
from dataclasses import dataclass

from ultratight.errors import ConfigError

MAX_WORKERS = 1024             # --workers: beyond this a typo, not a cluster


def allowed_cores():
    """Cores this process may run on: its CPU affinity (``os.sched_getaffinity(0)``, which also
    reflects ``taskset`` and container CPU sets), else ``os.cpu_count()``; at least 1."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):          # no affinity call on this platform
        return max(1, os.cpu_count() or 1)


@dataclass(frozen=True)
class CorePlan:
    """Worker processes for a command's independent jobs, and threads of the compiled stages per
    worker (or in this process when ``workers`` is 1)."""
    workers: int
    threads: int


def plan(n_jobs=1, n_items=None, workers=None, threads=None, reserved=0):
    """The policy: ``n_jobs`` independent jobs (runs, methods) each spreading ``n_items`` items
    (channels; None: no limit) over threads, on :func:`allowed_cores` cores, ``reserved`` of them
    kept for a producer that runs beside the jobs all the time (the scenario's IF generator).

    * workers: ``workers`` when given (an integer >= 1, ``--workers``), else one per allowed core;
      never more than the jobs;
    * threads per worker: ``threads`` when given and > 0 (``--threads``), else the allowed cores
      less the reserved ones shared between the workers (at least 1); never more than the items.

    Reserving matters for threads: a job's threads meet at every batch of epochs, so a thread that
    loses its core to the producer stalls the others — two engine threads beside a generator thread
    on two cores ran slower than one engine thread beside it.
    """
    n_jobs = max(1, int(n_jobs))
    cores = allowed_cores()
    w = cores if workers is None else int(workers)
    w = max(1, min(w, n_jobs))
    free = max(1, cores - max(0, int(reserved)))
    t = int(threads) if threads is not None and int(threads) > 0 else max(1, free // w)
    if n_items is not None:
        t = min(t, max(1, int(n_items)))
    return CorePlan(workers=w, threads=max(1, t))


def check_workers(workers, flag="--workers"):
    """``workers`` from the command line: None (automatic) or an integer in 1..MAX_WORKERS."""
    if workers is None:
        return None
    if isinstance(workers, bool) or not isinstance(workers, int) or not 1 <= workers <= MAX_WORKERS:
        raise ConfigError(f"{flag} must be an integer in 1..{MAX_WORKERS}, got {workers!r}")
    return workers


def stage_threads(requested, n_items=None):
    """Threads for the compiled stages of this process that spread ``n_items`` channels over numba's
    thread pool: :func:`plan` for one job (``requested`` when > 0, else every allowed core), capped by
    the pool (``NUMBA_NUM_THREADS``, fixed when numba loads: one thread in a worker process started
    for one thread)."""
    import numba      # lazy: the command line imports this module before it needs numba

    pool = numba.config.NUMBA_NUM_THREADS
    return max(1, min(plan(1, n_items, threads=requested).threads, pool))
