"""Independent jobs of one command (the methods of a scenario run, the runs of ``--runs N``) in
separate processes, as many as :func:`ultratight.cores.plan` gives for the jobs and the allowed cores.

Each job runs in a worker process started with ``spawn`` (no state shared with the parent: numba's
thread pool, open files and signal handlers start fresh) with the plan's threads per worker (one when
there are as many workers as cores), so the workers use the cores without competing for them. A pool
asked to (``WorkerPool(fork=True)``: the scenario's method workers) forks its workers instead when
that is safe (:func:`fork_is_safe`: a POSIX system, no other thread in this process, numba's thread
pool not started, no HDF5 file open), so that they begin with the modules this process has imported
(about 0.6 s of CPU per worker, which on two cores otherwise competes with the IF generator); their
signal handlers are reset to what a spawned worker would have (:func:`_init_worker`). The results
come back in the order of the jobs; the first failure cancels the jobs not yet started and is raised
in the parent.

A worker's numba pool is sized by ``NUMBA_NUM_THREADS`` before numba loads there
(:func:`limit_numba_threads`). The variable is never changed once numba is loaded: numba reads its
environment again at every compilation and refuses a new ``NUMBA_NUM_THREADS`` once its threads run
("Cannot set NUMBA_NUM_THREADS to a different value once the threads have been launched") — which is
what happened when the worker's main module had imported numba before the worker set the variable.
"""

import atexit
import ctypes
import importlib
import multiprocessing
import os
import signal
import sys
import time
from contextlib import contextmanager
from concurrent.futures import FIRST_EXCEPTION, Future, ProcessPoolExecutor, wait
from concurrent.futures import process as _cf_process

from ultratight.cores import check_workers, plan  # noqa: F401 (check_workers: used by the runners)


M_MMAP_THRESHOLD = -3          # glibc mallopt parameters
M_TRIM_THRESHOLD = -1
MMAP_THRESHOLD = 1 << 20       # bytes: larger blocks are mapped on their own and unmapped when freed
# a worker that streams IF keeps its block buffers (about 3.5 MB at 4 MHz) on the heap for reuse
STREAM_MMAP_THRESHOLD = 4 << 20
STREAM_TRIM_THRESHOLD = 16 << 20   # bytes of free heap top kept before they are returned
TRIM_THRESHOLD = 128 << 10         # glibc's default M_TRIM_THRESHOLD


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


@contextmanager
def streaming_heap():
    """The streaming thresholds of :func:`fix_mmap_threshold` inside the block, the fixed threshold (and
    glibc's default heap top) after it, and the heap released: for the process that generates the IF
    ring of a run (3.2 MB blocks every 100 ms at 4 MHz: mapping them fresh made about 0.6 of the main job's
    1.7 million page faults) while the per-epoch results it collects afterwards are unmapped when
    freed."""
    fix_mmap_threshold(streaming=True)
    try:
        yield
    finally:
        lib = _libc()
        if lib:
            lib.mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD)
        fix_mmap_threshold()
        release_heap()


def release_heap():
    """Hand the C heap's free pages back to the operating system (glibc ``malloc_trim``; nothing
    elsewhere). Between the stages of a long run (data preparation, one method after another) the
    many small arrays of a finished stage leave the heap fragmented, and its free pages would
    otherwise stay in the resident set for the rest of the run. True when memory was returned."""
    lib = _libc()
    return bool(lib.malloc_trim(0)) if lib else False


def process_age_s():
    """Seconds since this process started (Linux: its start time in ``/proc/self/stat`` against
    ``/proc/uptime``, to the kernel's clock tick), or None where that cannot be read."""
    try:
        with open("/proc/self/stat", encoding="ascii") as f:
            start_ticks = int(f.read().rsplit(")", 1)[1].split()[19])       # field 22, starttime
        with open("/proc/uptime", encoding="ascii") as f:
            uptime = float(f.read().split()[0])
        return max(0.0, uptime - start_ticks / os.sysconf("SC_CLK_TCK"))
    except (OSError, ValueError, IndexError):
        return None


def limit_numba_threads(threads):
    """At most ``threads`` numba threads in this process. Before numba loads: its pool is sized so
    (``NUMBA_NUM_THREADS``). Once loaded, the variable is left as it is (changed, numba's next
    compilation raises once the pool runs) and this thread uses at most ``threads`` of the pool
    (``numba.set_num_threads``). Returns the threads this thread may use."""
    threads = max(1, int(threads))
    if "numba" not in sys.modules:
        os.environ["NUMBA_NUM_THREADS"] = str(threads)
        return threads
    import numba
    threads = min(threads, numba.config.NUMBA_NUM_THREADS)
    numba.set_num_threads(threads)
    return threads


_BUSY = False           # a worker process is running a job (signals: :func:`_on_sigint`)
_EXIT_STATUS = 0        # a worker's exit status (:func:`_exit_now`): 128 + signal when a signal ended it


def _on_sigint(signum, frame):
    """SIGINT in a worker process (a terminal's Ctrl-C reaches the whole process group): a running job
    stops with KeyboardInterrupt, handed to the parent like any job's error; a worker waiting for its
    next job leaves quietly instead of printing the interrupted queue read's traceback (the parent
    reports the interruption in one line)."""
    global _EXIT_STATUS
    if _BUSY:
        raise KeyboardInterrupt
    _EXIT_STATUS = 128 + signum
    raise SystemExit(_EXIT_STATUS)


def _run_job(fn, args):
    global _BUSY
    _BUSY = True
    try:
        return fn(*args)
    finally:
        _BUSY = False


def _exit_now():
    """The worker's last exit handler (registered first, so it runs after the others): its output
    flushed, the process ends without tearing down its interpreter (the modules, numba's dispatchers
    and the engine's heap: about 0.2 s of CPU per worker), as nothing in it is left for another process
    (the results went back through the pipe; the numba cache is written when a kernel compiles)."""
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError, AttributeError):
            pass
    os._exit(_EXIT_STATUS)


def fork_is_safe():
    """Whether a worker forked from this process starts as cleanly as a spawned one: a POSIX system
    with ``fork``, no thread but this one (a fork copies other threads' locks held, not the threads),
    numba's thread pool not started (its layers do not survive a fork) and no HDF5 file open (the
    library would hand a worker opening the same file this process's copied state of it)."""
    import threading
    if os.name != "posix" or "fork" not in multiprocessing.get_all_start_methods():
        return False
    if threading.active_count() != 1:
        return False
    parallel = sys.modules.get("numba.np.ufunc.parallel")
    if parallel is not None and getattr(parallel, "_is_initialized", False):
        return False
    h5py = sys.modules.get("h5py")
    if h5py is not None:
        try:
            return h5py.h5f.get_obj_count(h5py.h5f.OBJ_ALL, h5py.h5f.OBJ_FILE) == 0
        except Exception:       # an h5py without the call: not known, so not safe
            return False
    return True


def _default_handlers():
    """In a forked worker: the signals whose handlers are this process's Python functions (the CLI's,
    :func:`ultratight.io_guard.install_signal_handlers`) back to the default a spawned worker starts
    with; ignored ones stay ignored, as across ``exec``."""
    for s in signal.valid_signals():
        try:
            if callable(signal.getsignal(s)):
                signal.signal(s, signal.SIG_DFL)
        except (OSError, ValueError, TypeError):
            pass
    sys.unraisablehook = sys.__unraisablehook__


def _init_worker(preload, threads=1, forked=False):
    if forked:
        _default_handlers()
    atexit.register(_exit_now)
    signal.signal(signal.SIGINT, _on_sigint)
    # the parent stops a worker with SIGTERM (WorkerPool.__exit__): never ignored nor blocked here, whatever
    # the parent's state when it started the worker (a run ignores further signals once interrupted)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    if hasattr(signal, "pthread_sigmask"):
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGTERM})
    limit_numba_threads(threads)
    fix_mmap_threshold(streaming=True)
    for name in preload:              # import the job's modules now, while the parent still works
        importlib.import_module(name)


def _stop_processes(procs):
    """SIGTERM to each live process of ``procs``, then SIGKILL to one not ended 10 s later."""
    procs = list(procs)
    for p in procs:
        if p.is_alive():
            p.terminate()
    for p in procs:
        p.join(timeout=10)
        if p.is_alive():         # a process that could not take SIGTERM
            p.kill()
            p.join(timeout=10)


def _ready():
    return os.getpid()


class WorkerPool:
    """``workers`` spawned worker processes of ``threads`` numba threads each (none when ``workers``
    <= 1: jobs then run in this process; ``processes=True`` spawns one then too). Started on entering
    the ``with`` block, with the modules of ``preload`` imported by every worker at once — so their
    start-up overlaps what the parent does before :meth:`map`. ``join_on_exit=False``: leaving the block
    without an error does not wait for the idle workers to end. ``fork=True``: the workers are forked
    when :func:`fork_is_safe` (module docstring), spawned otherwise; ``start_method`` tells which."""

    def __init__(self, workers, preload=(), processes=None, threads=1, join_on_exit=True, fork=False):
        self.workers = max(1, int(workers))
        self.fork = bool(fork)
        self.start_method = None
        self.join_on_exit = bool(join_on_exit)
        self.threads = max(1, int(threads))
        self.preload = tuple(preload)
        self.processes = self.workers > 1 if processes is None else bool(processes)
        self._pool = None

    def __enter__(self):
        if self.processes:
            self.start_method = "fork" if self.fork and fork_is_safe() else "spawn"
            if self.start_method == "fork":
                # the workers share this process's resource tracker, as spawned ones do (they register the
                # IF ring's shared memory there; a tracker of their own would remove it when they end)
                from multiprocessing import resource_tracker
                resource_tracker.ensure_running()
            ctx = multiprocessing.get_context(self.start_method)
            self._pool = ProcessPoolExecutor(max_workers=self.workers, mp_context=ctx, initializer=_init_worker,
                                             initargs=(self.preload, self.threads, self.start_method == "fork"))
            self._children_before = set(multiprocessing.active_children())
            self._warm = [self._pool.submit(_ready) for _ in range(self.workers)]   # spawns them all now
        return self

    def __exit__(self, exc_type, *exc):
        pool, self._pool = self._pool, None
        if pool is None:
            return False
        if exc_type is None:
            # without join_on_exit the workers end on their own while this process goes on (the
            # executor's exit handler joins them before this process ends)
            pool.shutdown(wait=self.join_on_exit, cancel_futures=True)
            return False
        # a failure or an interruption: the jobs still queued or running are not waited for (a
        # graceful shutdown waited for the queued jobs to run, and could hang once a worker had
        # been interrupted in the middle of one)
        procs = list((getattr(pool, "_processes", None) or {}).values())
        pool.shutdown(wait=False, cancel_futures=True)
        _stop_processes(procs)
        # and any process the executor started that its table no longer lists: none outlives the error
        _stop_processes(set(multiprocessing.active_children()) - self._children_before - set(procs))
        # the executor's thread ends with its workers; joined here, so that the interpreter's exit does
        # not wake it through the pipe it closed (Python 3.11 printed "Bad file descriptor" then)
        manager = getattr(pool, "_executor_manager_thread", None)
        if manager is not None:
            manager.join(timeout=10)
            if not manager.is_alive():
                getattr(_cf_process, "_threads_wakeups", {}).pop(manager, None)
        return False

    def call(self, fn, *args):
        """``fn(*args)`` in one worker (here without worker processes), waited for; its result."""
        if self._pool is None:
            return fn(*args)
        return self._pool.submit(_run_job, fn, args).result()

    def start(self, fn, *args):
        """``fn(*args)`` in one worker, not waited for: a future (``.result()`` waits and returns it or
        raises); here, without worker processes, run at once."""
        fut = Future()
        if self._pool is not None:
            return self._pool.submit(_run_job, fn, args)
        try:
            fut.set_result(fn(*args))
        except Exception as exc:        # handed on like a worker's: raised by .result()
            fut.set_exception(exc)
        return fut

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
        futs = {self._pool.submit(_run_job, fn, tuple(job)): i for i, job in enumerate(jobs)}
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


def warm_up(fn, jobs, progress=False):
    """Compile once: ``fn(*job)`` for each of ``jobs`` (short representative calls) in this process, one
    after the other, before the other workers get their jobs (:meth:`WorkerPool.call`). What numba
    compiles for them goes into its cache (``cache=True`` kernels), from which every worker then loads
    the kernels at their first call instead of compiling the same ones at the same time — with an empty
    cache (a fresh install) the four method workers of the main job each compiled every shared kernel.
    The first job always runs; when numba compiled nothing for it (the cache is warm) the others are
    skipped. A job's error is not raised here (the job proper meets it again and reports it).
    ``progress``: a line when the first compilation starts (why the run waits) and one with the count
    and time at the end. Returns the kernels compiled (numba's ``numba:compile`` events, cache loads
    not counted)."""
    from numba.core import event

    class CompileCounter(event.Listener):
        compiled = 0

        def on_start(self, ev):
            self.compiled += 1
            if self.compiled == 1 and progress:
                print("numba: compiling the kernels once, before the workers start (the first run after an "
                      "install; later runs load them from the cache)", flush=True)

        def on_end(self, ev):
            pass

    t0 = time.perf_counter()
    counter = CompileCounter()
    event.register("numba:compile", counter)
    try:
        for i, job in enumerate(jobs):
            try:
                fn(*job)
            except Exception:       # a short cut may not suit every setting: the job itself says what fails
                pass
            if i == 0 and counter.compiled == 0:
                break
    finally:
        event.unregister("numba:compile", counter)
    if progress and counter.compiled:
        print(f"numba: {counter.compiled} kernel(s) compiled in {time.perf_counter() - t0:.1f} s", flush=True)
    return counter.compiled


def run_jobs(fn, jobs, workers=None, on_done=None):
    """``[fn(*job) for job in jobs]``, in worker processes when ``workers`` (default: the plan's,
    :func:`ultratight.cores.plan`) is above 1 (:class:`WorkerPool`, the plan's threads each)."""
    jobs = list(jobs)
    p = plan(len(jobs), workers=workers)
    with WorkerPool(p.workers, threads=p.threads) as pool:
        return pool.map(fn, jobs, on_done)
