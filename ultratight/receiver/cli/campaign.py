"""Monte-Carlo campaigns on ``dask.distributed`` (``ultratight campaign``, docs/campaign.md).

A campaign runs ``N`` seeds of one scenario's experiment (:mod:`ultratight.receiver.cli.experiments`,
any module with ``run_one``/``summarize``) as independent tasks on a Dask cluster: a
``LocalCluster`` of single-threaded worker processes (one numba thread each) or an existing
scheduler given by its address.

Seeds. Run ``i`` of a campaign with base seed ``S`` uses the child sequence
``numpy.random.SeedSequence(S).spawn(N)[i]``; ``run_one`` is seed-driven, so it receives the
integer :func:`run_seed` ``= int(child.generate_state(1, dtype=numpy.uint32)[0])`` (a value in
``[0, 2**32)``), recorded with the run. Child ``i`` does not depend on ``N``: a campaign of 8 runs
starts with the 4 runs of the same campaign with ``--runs 4``.

Outputs in ``OUT``:

* ``runs/run-IIIII.h5``: one file per run, the whole ``run_one`` result (nested groups; see
  :func:`write_run` / :func:`read_run`, lossless for numbers and arrays), written atomically by the
  driver as the run comes back, with attributes ``complete``, ``seed``, ``index`` and ``key``
  (hash of the resolved scenario, the methods and the run seed). ``--resume`` keeps a file whose
  ``key`` matches and which reads back whole, and runs only the others.
* ``campaign.json``: the aggregated metrics (:func:`aggregate`: every numeric metric of
  ``run_one`` with at most :data:`MAX_METRIC_SIZE` elements, per element: mean, 95 % Student-t
  confidence interval of the mean, std, min, max over the runs), the experiment's own
  ``summarize`` tables, the seeds and the timing.

The aggregation always reads the run files back (also for runs computed just now), so a
resumed campaign and an uninterrupted one sum the same numbers in the same order.
"""

import hashlib
import json
import logging
import os
import re
import shutil
import signal
import sys
import tempfile
import threading
import time
import weakref
from contextlib import contextmanager
from multiprocessing import resource_tracker
from pathlib import Path

import dask
import h5py
import numba
import numpy as np
from distributed import Client, LocalCluster, as_completed
from scipy.stats import t as student_t
from tqdm import tqdm

from ultratight import __version__, io_guard
from ultratight.cores import allowed_cores, check_workers, plan
from ultratight.errors import ConfigError
from ultratight.io_guard import json_clean, json_dumps, note_complete, write_h5_atomic, write_text_atomic
from ultratight.receiver.cli import experiments
SCHEMA = "ultratight campaign run v1 (docs/campaign.md)"
MAX_METRIC_SIZE = 64          # a numeric leaf with more elements is a series, not a metric
SCHEDULER_TIMEOUT_S = 10.0    # --scheduler: give up connecting after this long
TIMING_KEYS = ("runtime_s", "realtime_factor", "cpu_s", "simulate_s")   # timings: not reproducible


# ------------------------------------------------------------------------------------------
# seeds
# ------------------------------------------------------------------------------------------
def run_seeds(seed, runs):
    """The integer seeds of a campaign's runs (module doc)."""
    return [run_seed(c) for c in np.random.SeedSequence(int(seed)).spawn(int(runs))]


def run_seed(child):
    """Integer seed of a run from its child ``SeedSequence``: its first 32-bit state word."""
    return int(child.generate_state(1, dtype=np.uint32)[0])


# ------------------------------------------------------------------------------------------
# run files: a run_one result as nested HDF5 groups
# ------------------------------------------------------------------------------------------
_PLAIN = (bool, int, float)


def _put(parent, name, value):
    """Store ``value`` under ``parent[name]`` with attribute ``kind`` saying how to read it back."""
    if isinstance(value, dict):
        g = parent.create_group(name)
        g.attrs["kind"] = "dict"
        for i, (k, v) in enumerate(value.items()):
            if not isinstance(k, (str, int)) or isinstance(k, bool):
                raise TypeError(f"run result key {k!r}: only str or int keys can be stored")
            _put(g, f"k{i:05d}", v)
            g[f"k{i:05d}"].attrs["key"] = json.dumps(k)
        return
    if isinstance(value, (list, tuple)):
        kind = "list" if isinstance(value, list) else "tuple"
        types = {type(v) for v in value}
        if value and len(types) == 1 and types.pop() in _PLAIN:
            ds = parent.create_dataset(name, data=np.asarray(value))
            ds.attrs["kind"] = kind
            return
        g = parent.create_group(name)
        g.attrs["kind"] = kind
        for i, v in enumerate(value):
            _put(g, f"i{i:05d}", v)
        return
    if value is None:
        ds = parent.create_dataset(name, data=np.zeros(0))
        ds.attrs["kind"] = "none"
        return
    if isinstance(value, str):
        ds = parent.create_dataset(name, data=np.zeros(0))
        ds.attrs["kind"] = "str"
        ds.attrs["value"] = value
        return
    if isinstance(value, np.generic):          # before the plain types: numpy.float64 is a float
        ds = parent.create_dataset(name, data=value)
        ds.attrs["kind"] = "npscalar"
        return
    if type(value) in _PLAIN:
        ds = parent.create_dataset(name, data=value)
        ds.attrs["kind"] = type(value).__name__
        return
    if isinstance(value, np.ndarray):
        if value.dtype.kind not in "biufc":
            raise TypeError(f"run result array of dtype {value.dtype}: only numeric arrays can be stored")
        big = value.size > 4096
        ds = parent.create_dataset(name, data=value, **({"compression": "gzip", "compression_opts": 1}
                                                         if big else {}))
        ds.attrs["kind"] = "ndarray"
        return
    raise TypeError(f"run result value of type {type(value).__name__} cannot be stored")


def _get(node):
    kind = node.attrs["kind"]
    if isinstance(kind, bytes):
        kind = kind.decode()
    if kind == "dict":
        return {json.loads(node[n].attrs["key"]): _get(node[n]) for n in sorted(node)}
    if kind in ("list", "tuple"):
        if isinstance(node, h5py.Dataset):
            v = node[()].tolist()
        else:
            v = [_get(node[n]) for n in sorted(node)]
        return v if kind == "list" else tuple(v)
    if kind == "none":
        return None
    if kind == "str":
        v = node.attrs["value"]
        return v.decode() if isinstance(v, bytes) else str(v)
    if kind in ("bool", "int", "float"):
        return {"bool": bool, "int": int, "float": float}[kind](node[()])
    if kind == "npscalar":
        return node[()]
    if kind == "ndarray":
        return np.asarray(node[()])
    raise ValueError(f"unknown stored kind {kind!r}")


def run_key(cfg, methods, seed):
    """Identity of a run file: the resolved scenario, the methods and the run seed."""
    blob = json.dumps({"cfg": json_clean(cfg), "methods": list(methods), "seed": int(seed)}, sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:24]


def write_run(path, result, *, index, seed, key, elapsed_s):
    """One run's ``run_one`` result, atomically (``io_guard.write_h5_atomic``)."""

    def build(f):
        f.attrs["schema"] = SCHEMA
        f.attrs["version"] = __version__
        f.attrs["index"] = int(index)
        f.attrs["seed"] = int(seed)
        f.attrs["key"] = key
        f.attrs["elapsed_s"] = float(elapsed_s)
        _put(f, "result", result)
        f.attrs["complete"] = True

    write_h5_atomic(path, build)


def read_run(path, key=None):
    """(result, attrs) of a run file; ``None`` when it is missing, unreadable, incomplete or (with
    ``key``) from another configuration."""
    try:
        with h5py.File(path, "r") as f:
            attrs = {k: f.attrs[k] for k in f.attrs}
            if not bool(attrs.get("complete", False)) or attrs.get("schema") != SCHEMA:
                return None
            if key is not None and attrs.get("key") != key:
                return None
            return _get(f["result"]), attrs
    except (OSError, KeyError, ValueError, TypeError):
        return None


def run_path(out_dir, index):
    return Path(out_dir) / "runs" / f"run-{int(index):05d}.h5"


# ------------------------------------------------------------------------------------------
# aggregation
# ------------------------------------------------------------------------------------------
def _leaves(obj, prefix=""):
    """(path, array) of every numeric leaf of a run result with at most MAX_METRIC_SIZE elements."""
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from _leaves(v, f"{prefix}/{k}" if prefix else str(k))
        return
    if isinstance(obj, (str, bytes)) or obj is None:
        return
    if isinstance(obj, (list, tuple)) and any(isinstance(v, (dict, list, tuple, str)) or v is None for v in obj):
        return
    try:
        a = np.asarray(obj)
    except (TypeError, ValueError):
        return
    if a.dtype.kind in "biuf" and 0 < a.size <= MAX_METRIC_SIZE:
        yield prefix, a.astype(float)


def t_quantile_975(dof):
    """Two-sided 95 % quantile of Student's t with ``dof`` degrees of freedom."""
    return float(student_t.ppf(0.975, dof))


def aggregate(runs):
    """Per numeric metric (path ``section/method/name``, seed excluded) and element: ``n`` finite
    values, ``mean``, ``ci95`` = mean -+ t(0.975, n-1)·std/sqrt(n), ``std`` (ddof 1), ``min``, ``max``.
    Non-finite values (a metric undefined in a run) are left out of that element's statistics."""
    paths = {}
    for r in runs:
        for p, a in _leaves({k: v for k, v in r.items() if k != "seed"}):
            paths.setdefault(p, []).append(a)
    out = {}
    for p, arrs in paths.items():
        shapes = {a.shape for a in arrs}
        if len(shapes) != 1 or len(arrs) != len(runs):
            continue                       # not present in every run, or shape varies: not a metric
        v = np.stack(arrs)                 # (runs, ...)
        fin = np.isfinite(v)
        n = fin.sum(axis=0)
        with np.errstate(invalid="ignore", divide="ignore"):
            vz = np.where(fin, v, 0.0)
            mean = np.where(n > 0, vz.sum(axis=0) / np.maximum(n, 1), np.nan)
            dev = np.where(fin, v - mean, 0.0)
            std = np.where(n > 1, np.sqrt((dev ** 2).sum(axis=0) / np.maximum(n - 1, 1)), np.nan)
            tq = np.vectorize(lambda k: t_quantile_975(k - 1) if k > 1 else np.nan, otypes=[float])(n)
            half = tq * std / np.sqrt(np.maximum(n, 1))
            vmin = np.where(n > 0, np.where(fin, v, np.inf).min(axis=0), np.nan)
            vmax = np.where(n > 0, np.where(fin, v, -np.inf).max(axis=0), np.nan)
        scalar = arrs[0].ndim == 0
        conv = (lambda x: float(x)) if scalar else (lambda x: np.asarray(x).tolist())
        out[p] = {"n": int(n) if scalar else n.tolist(), "mean": conv(mean),
                  "ci95": [conv(mean - half), conv(mean + half)], "std": conv(std),
                  "min": conv(vmin), "max": conv(vmax)}
    return out


def reproducible(agg):
    """The aggregated metrics without the wall-clock ones (:data:`TIMING_KEYS`)."""
    return {p: v for p, v in agg.items() if p.rsplit("/", 1)[-1] not in TIMING_KEYS}


# ------------------------------------------------------------------------------------------
# cluster
# ------------------------------------------------------------------------------------------
WORKER_ENV = {"NUMBA_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1",
              "MKL_NUM_THREADS": "1"}


def local_workers(workers, n_runs, log=None):
    """LocalCluster worker processes for ``n_runs`` runs: ``workers`` (``--workers``) or one per allowed
    core (:func:`ultratight.cores.plan`), never more than the runs nor the allowed cores (one line
    through ``log`` when ``--workers`` is capped)."""
    n_runs = max(1, int(n_runs))
    cores = allowed_cores()
    k = plan(n_runs).workers if workers is None else int(workers)
    cap = min(n_runs, cores)
    if k > cap:
        if log is not None:
            log(f"campaign: --workers {k} capped at {cap} ({n_runs} run(s) to compute, {cores} allowed core(s))")
        k = cap
    return k


# the scratch directory of each LocalCluster started here (start_client), removed by stop_client
_SCRATCH = weakref.WeakKeyDictionary()


def start_client(workers=None, scheduler=None, timeout_s=SCHEDULER_TIMEOUT_S, n_runs=None, log=None):
    """(client, cluster or None, description): a LocalCluster of single-threaded worker processes
    (:func:`local_workers` for ``n_runs`` runs; default: one per allowed core), or a connection to
    ``scheduler``. Close both with :func:`stop_client`.

    The LocalCluster keeps Dask's scratch space (``dask-scratch-space``: the worker directories and
    their ``*.dirlock`` files) in a temporary directory of its own (``ultratight-campaign-*`` under
    the system's temporary directory), removed by :func:`stop_client` or, at the latest, when the
    cluster object is collected or the interpreter exits. It starts with SIGINT, SIGTERM and SIGHUP
    deferred (:func:`_signals_deferred`): its worker processes never receive them (a Ctrl-C reaches
    the terminal's whole process group) and are stopped by the driver instead; a signal that arrives
    meanwhile ends the run once the cluster is up, which is then closed again."""
    if scheduler is not None:
        try:
            client = Client(scheduler, timeout=timeout_s)
        except (OSError, TimeoutError, ValueError) as exc:
            raise ConfigError(f"--scheduler {scheduler}: cannot connect within {timeout_s:g} s "
                              f"({' '.join(str(exc).split()) or type(exc).__name__})") from None
        return client, None, f"scheduler {scheduler}"
    k = local_workers(workers, allowed_cores() if n_runs is None else n_runs, log)
    client = cluster = scratch = None
    try:
        scratch = tempfile.mkdtemp(prefix="ultratight-campaign-")
        with dask.config.set({"temporary-directory": scratch}), _signals_deferred():
            cluster = LocalCluster(n_workers=k, threads_per_worker=1, processes=True, dashboard_address=":0",
                                   silence_logs=logging.CRITICAL, env=dict(WORKER_ENV), local_directory=scratch)
            _SCRATCH[cluster] = weakref.finalize(cluster, shutil.rmtree, scratch, ignore_errors=True)
            client = Client(cluster)
    except BaseException:
        stop_client(client, cluster)
        if scratch is not None:
            shutil.rmtree(scratch, ignore_errors=True)
        raise
    return client, cluster, f"LocalCluster of {k} worker(s) x 1 thread"


def stop_client(client, cluster=None):
    """Close ``client`` and ``cluster`` (either may be None) without distributed's shutdown messages (a
    worker's heartbeat that finds the scheduler gone, a comm closed mid-message), then remove the
    cluster's scratch directory (:func:`start_client`)."""
    quiet = logging.getLogger("distributed")
    level = quiet.level
    quiet.setLevel(logging.CRITICAL + 1)
    try:
        for part in (client, cluster):
            if part is not None:
                try:
                    part.close()
                except Exception:      # already closed, or the scheduler gone: nothing left to stop
                    pass
    finally:
        quiet.setLevel(level)
        remove = _SCRATCH.pop(cluster, None) if cluster is not None else None
        if remove is not None:
            remove()


@contextmanager
def _signals_deferred():
    """Block SIGINT, SIGTERM and SIGHUP in this thread while a LocalCluster starts. The threads it
    starts (its event loop) inherit the mask, and so do the worker processes they spawn: a signal sent
    to the process group (Ctrl-C, a closed terminal, ``timeout``) reaches only the driver, whose
    cleanup closes the cluster, instead of ending each worker with its own traceback. A blocked signal
    is pending, not lost: it is handled as soon as the mask is restored."""
    if not hasattr(signal, "pthread_sigmask") or threading.current_thread() is not threading.main_thread():
        yield
        return
    sigs = set(io_guard.HANDLED_SIGNALS)
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, sigs)
    try:
        # multiprocessing's resource tracker (a process started with the first worker) ignores SIGINT and
        # SIGTERM but would die of a SIGHUP, and starting it unblocks SIGINT and SIGTERM in the thread that
        # starts it: start it here, with SIGHUP blocked, then block all three again
        resource_tracker.ensure_running()
        signal.pthread_sigmask(signal.SIG_BLOCK, sigs)
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)


def _task(experiment, cfg, methods, seed):
    """Worker side of one run: ``run_one`` with one numba thread; returns (result, seconds)."""
    try:
        numba.set_num_threads(1)
    except ValueError:    # pragma: no cover
        pass
    module = experiments.get(experiment)
    t0 = time.perf_counter()
    res = module.run_one(cfg, list(methods), int(seed), progress=False)
    return res, time.perf_counter() - t0


# ------------------------------------------------------------------------------------------
# driver
# ------------------------------------------------------------------------------------------
def run_campaign(scenario, *, runs, methods=None, seed=None, workers=None, scheduler=None, out_dir="campaign_out",
                 resume=False, overrides=None, progress=True, client=None, log=None,
                 connect_timeout_s=SCHEDULER_TIMEOUT_S, cache=False):
    """Run a campaign (module doc); returns ``{"json", "text", "campaign_path", "runs_dir", ...}``.

    ``client``: an existing ``distributed.Client`` to use (then ``workers``/``scheduler`` are ignored).
    ``cache``: IF-level experiments write each run's IF file into ``OUT/cache`` (else it is generated in
    memory for each method; same results)."""
    log = log or (lambda msg: print(msg, file=sys.stderr, flush=True))
    if isinstance(runs, bool) or int(runs) != runs or int(runs) < 1:
        raise ConfigError(f"--runs must be an integer >= 1, got {runs}")
    runs = int(runs)
    workers = check_workers(workers)
    if not connect_timeout_s > 0:
        raise ConfigError(f"--connect-timeout must be > 0 s, got {connect_timeout_s}")
    if workers is not None and scheduler is not None:
        raise ConfigError("--workers and --scheduler exclude each other (the scheduler's workers run the campaign)")
    module, name, cfg, methods, base_seed = _resolve(scenario, methods, seed, overrides)
    if cache and not getattr(module, "USES_DATA_DIR", False):
        raise ConfigError(f"--cache: only for IF-level scenarios (this one runs experiment {name!r})")
    out = Path(out_dir)
    _check_out(out)
    if resume:
        _check_resume_scenario(out, cfg.get("name", name))
    if scheduler is not None and client is None:
        check_scheduler_address(scheduler)
    seeds = run_seeds(base_seed, runs)
    keys = [run_key(cfg, methods, s) for s in seeds]
    if getattr(module, "USES_DATA_DIR", False):
        # where the runs keep generated data, and whether the IF files too (not part of a run's key)
        cfg = module.with_data_dir(cfg, out, cache=bool(cache))
    created = [d for d in (out, out / "runs") if not d.exists()]
    try:
        (out / "runs").mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise io_guard.output_error(out / "runs", exc, "cannot create output directory") from None

    todo = list(range(runs))
    if resume:
        todo = [i for i in todo if read_run(run_path(out, i), keys[i]) is None]
        if progress:
            log(f"resume: {runs - len(todo)} of {runs} run(s) already complete in {out / 'runs'}")

    t0 = time.perf_counter()
    elapsed = {}
    where = "no runs left"
    if todo:
        local = client is None and scheduler is None
        try:
            where = _compute_on(client, (workers, scheduler, connect_timeout_s, log), name, cfg, methods, seeds,
                                keys, todo, runs, out, elapsed, progress, log)
        except BaseException:
            if local:                   # the cluster's workers are gone: so are the writers of any temporaries
                remove_orphaned_temporaries(out / "cache")
                if out in created and not any((out / "runs").glob("*")):
                    shutil.rmtree(out / "cache", ignore_errors=True)   # OUT is this call's, no run kept: its data go
            for d in reversed(created):     # no run file kept: leave no empty OUT/runs (or OUT) behind
                _remove_empty_dir(d)
            raise
    wall = time.perf_counter() - t0

    results = []
    for i in range(runs):
        got = read_run(run_path(out, i), keys[i])
        if got is None:
            raise ConfigError(f"{run_path(out, i)}: run file missing or invalid after the campaign")
        results.append(got[0])
        elapsed.setdefault(i, float(got[1].get("elapsed_s", float("nan"))))
    return finish(module, cfg, results, out, name=name, base_seed=base_seed, seeds=seeds, methods=methods,
                  wall_s=wall, computed=len(todo), elapsed=[elapsed[i] for i in range(runs)], where=where)


def _resolve(scenario, methods, seed, overrides):
    """``(experiment module, experiment name, resolved configuration, methods, base seed)``."""
    path, raw, module = experiments.resolve(scenario)
    name = raw.get("experiment", experiments.DEFAULT_EXPERIMENT)
    if not hasattr(module, "run_one"):
        raise ConfigError(f"experiment {name!r} has no run_one; a campaign cannot run it")
    methods = experiments.check_methods(module, methods)
    cfg = module.load(path, raw, dict(overrides or {}))
    base_seed = int(cfg.get("seed", 0) if seed is None else seed)
    if base_seed < 0:
        raise ConfigError(f"--seed must be >= 0, got {base_seed}")
    return module, name, cfg, methods, base_seed


def _remove_empty_dir(d):
    try:
        d.rmdir()
    except OSError:          # not empty (or gone): kept
        pass


def check_scheduler_address(address):
    """``--scheduler``: a Dask address ``[PROTOCOL://]HOST:PORT`` with a protocol this installation
    knows and, for tcp/tls/ws/wss, a host and a port in 1..65535 (ConfigError otherwise)."""
    from distributed.comm.addressing import parse_address, parse_host_port
    from distributed.comm.registry import backends
    try:
        scheme, loc = parse_address(str(address), strict=False)
    except (ValueError, TypeError):
        raise ConfigError(f"--scheduler {address}: not an address (expected e.g. tcp://127.0.0.1:8786)") from None
    if scheme not in backends:
        raise ConfigError(f"--scheduler {address}: unknown protocol {scheme!r} (known: {', '.join(sorted(backends))})")
    if scheme in ("tcp", "tls", "ws", "wss"):
        try:
            host, port = parse_host_port(loc)
            ok = bool(host) and isinstance(port, int) and 1 <= port <= 65535
        except (ValueError, TypeError):
            ok = False
        if not ok:
            raise ConfigError(f"--scheduler {address}: expected {scheme}://HOST:PORT with a port in 1..65535")


def _check_resume_scenario(out, scenario):
    """``--resume`` into an OUT whose campaign.json belongs to another scenario: refused."""
    cpath = out / "campaign.json"
    try:
        other = json.loads(cpath.read_text(encoding="utf-8")).get("scenario")
    except (OSError, ValueError, AttributeError):
        return                      # no readable campaign.json: the run files' keys decide what is kept
    if other is not None and other != scenario:
        raise ConfigError(f"--resume: {out} holds the campaign of scenario {other!r}, not {scenario!r}; give "
                          f"another --out for {scenario!r}")


def _check_out(out):
    io_guard.check_path_length(out, "--out")
    if out.exists() and not out.is_dir():
        raise ConfigError(f"--out {out} exists and is not a directory")
    io_guard.check_output_path(out / "runs" / "run-00000.h5", "--out", create_parent=True)


def _compute_on(client, start, name, cfg, methods, seeds, keys, todo, *rest):
    """:func:`_compute` on ``client``, or on a client started from ``start`` = (workers, scheduler,
    connect timeout, log) and stopped again on every exit path (:func:`stop_client`); returns where the
    runs executed."""
    job = (name, cfg, methods, seeds, keys, todo, *rest)
    if client is not None:
        _compute(client, "given client", *job)
        return "given client"
    workers, scheduler, timeout_s, log = start
    client, cluster, where = start_client(workers, scheduler, timeout_s, len(todo), log)
    try:
        _compute(client, where, *job)
    finally:
        stop_client(client, cluster)
    return where


_TEMPORARY = re.compile(r"^\..+\.tmp-(\d+)-[0-9a-f]+$")     # io_guard.tmp_name: .NAME.tmp-PID-RANDOM


def remove_orphaned_temporaries(d):
    """Remove the temporary files (``io_guard.tmp_name``) under ``d`` whose writing process has ended
    (a worker stopped mid-write), then the directories below ``d`` that this leaves empty. A temporary
    file is renamed only by the process that wrote it, so once that process is gone it is garbage."""
    d = Path(d)
    if not d.is_dir():
        return
    emptied = set()
    for p in d.rglob(".*.tmp-*"):
        m = _TEMPORARY.match(p.name)
        if m and p.is_file() and not _pid_alive(int(m.group(1))):
            try:
                p.unlink()
            except OSError:
                continue
            emptied.update(q for q in p.parents if q != d and d in q.parents)
    for sub in sorted(emptied, key=lambda q: len(q.parts), reverse=True):
        _remove_empty_dir(sub)


def _pid_alive(pid):
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:                  # e.g. another user's process: alive
        return True
    return True


def _compute(client, where, name, cfg, methods, seeds, keys, todo, runs, out, elapsed, progress, log):
    """Submit the runs ``todo`` to ``client`` and write each run file as it completes (``elapsed``: index
    -> seconds of the run)."""
    n_workers = len(client.scheduler_info().get("workers", {}))
    if progress:
        log(f"campaign: {where}, {n_workers} worker(s); dashboard {client.dashboard_link}")
    futs = {client.submit(_task, name, cfg, methods, seeds[i], pure=False, key=f"run-{i:05d}-{keys[i]}"): i
            for i in todo}
    bar = tqdm(total=runs, initial=runs - len(todo), unit="run", desc=str(cfg.get("name", name)),
               disable=not progress, file=sys.stderr)
    try:
        for fut in as_completed(list(futs)):
            i = futs[fut]
            res, dt = fut.result()
            write_run(run_path(out, i), res, index=i, seed=seeds[i], key=keys[i], elapsed_s=dt)
            io_guard.note_complete(run_path(out, i))
            elapsed[i] = dt
            fut.release()
            bar.update(1)
    finally:
        bar.close()
        for fut in futs:
            fut.cancel()


def finish(module, cfg, results, out, *, name, base_seed, seeds, methods, wall_s, computed, elapsed, where):
    """Aggregate, summarize and write ``campaign.json``."""
    agg = aggregate(results)
    summary = module.summarize(cfg, results)
    runs = len(results)
    throughput = computed / wall_s if computed and wall_s > 0 else None
    js = {"scenario": cfg.get("name", name), "experiment": name, "version": __version__, "seed": base_seed,
          "runs": runs, "run_seeds": seeds, "methods": list(methods),
          "seed_rule": "run i: int(SeedSequence(seed).spawn(runs)[i].generate_state(1, uint32)[0])",
          "metrics": agg, "summary": summary.get("json", {}),
          "timing": {"where": where, "computed_runs": computed, "wall_s": wall_s,
                     "runs_per_hour": None if throughput is None else 3600.0 * throughput,
                     "run_elapsed_s": elapsed}}
    cpath = Path(out) / "campaign.json"
    write_text_atomic(cpath, json_dumps(js, indent=2))
    note_complete(cpath)
    text = [summary.get("text", ""), "", f"campaign: {runs} run(s) of {js['scenario']}, base seed {base_seed} "
            f"({computed} computed now, {wall_s:.1f} s wall; {where})",
            "aggregated metrics (mean [95 % CI] (min..max), scalars only; all in campaign.json):"]
    for p, v in agg.items():
        if isinstance(v["mean"], float):
            text.append(f"  {p:48s} {_g(v['mean'])} [{_g(v['ci95'][0])}, {_g(v['ci95'][1])}] "
                        f"({_g(v['min'])}..{_g(v['max'])})")
    return {"json": json_clean(js), "text": "\n".join(text), "campaign_path": str(cpath),
            "runs_dir": str(Path(out) / "runs"), "results": results}


def _g(x):
    return "-" if x is None or not np.isfinite(x) else f"{x:.6g}"
