"""The scenario's first run after an install: the IF written while the kernels compile.

A warm run of several methods reads one generated IF from a shared-memory ring, the generator
running beside the engines (:mod:`ultratight.signals.synth.ifring`). On the first run after an
install numba's cache is empty: one worker compiles the kernels for about a minute
(:func:`ultratight.receiver.cli.workers.warm_up`) while this process only generates the truth and
IMU, and a core waits. Then the IF of the run is written into the run's cache entry during the
compilation instead (the ``--cache`` path: the samples of the ring bit for bit, so the results are
the same), the methods read the file with no generator beside them, and the file is removed from
the entry afterwards (the truth and IMU stay for the next run): 152 s → 131–145 s for the first
``ultratight scenario paper-highdyn`` on the 2-core reference machine; with the engine's epoch chain
compiled ahead in a second worker (:func:`first_compilation`,
:mod:`ultratight.receiver.deep.compile_ahead`) 104–107 s (README).

"First run" is decided from the work, not from the clock or the load: the compiled engine's epoch
runner has no entry in numba's cache for its current source (:func:`engine_kernels_cached`).
The IF is written ahead only for one run of several methods in worker processes, and only when the
output folder has room for the file (twice its size free). One run of one method (default workers, no
``--cache``) on two or more allowed cores writes its IF ahead once the engine is compiled: the method then
reads it with every core, where a generator beside it would hold one of them for the whole run
(docs/ultratight.md "One method, one run"); on a first run the compilation needs the cores instead
(35.8 s streamed against 42.7 s written ahead for ``ultratight scenario paper-highdyn --methods
dlb-rackf``). The epoch chain is compiled ahead on
every first run of the engine: by the scenario's second worker, and for ``process --mode
ultratight`` by a helper process (:func:`compiling_ahead`).
"""

import json
from contextlib import contextmanager
from pathlib import Path

from ultratight.cores import allowed_cores
from ultratight.io_guard import free_disk, write_text_atomic

DISK_MARGIN = 2.0          # free space needed, in IF file sizes


def engine_kernels_cached():
    """True when numba's cache holds the engine's compiled epoch runner for its current source (or
    when that cannot be told: the usual path is then taken)."""
    try:
        from ultratight.receiver.deep.epochs import run_epochs
        return bool(run_epochs._cache._cache_file._load_index())
    except Exception:            # noqa: BLE001 - numba's cache layout is not public: assume warm
        return True


def write_if_ahead(runs, n_workers, shared, if_bytes, out_dir, single=False):
    """Whether this run writes its IF into the cache entry before its methods read it (module
    docstring): one run of one method (``single``: the default workers, no ``--cache``) on two or more
    allowed cores once the engine is compiled, or one run of several methods sharing their IF (``shared``)
    in two or more workers on a first run after an install; either only with room for the file."""
    if runs != 1:
        return False
    if single:
        wanted = allowed_cores() >= 2 and engine_kernels_cached()
    else:
        wanted = shared and n_workers >= 2 and not engine_kernels_cached()
    if not wanted:
        return False
    try:
        return free_disk(out_dir) >= DISK_MARGIN * float(if_bytes)
    except OSError:
        return False


def first_compilation():
    """Whether the engine's kernels are still to be compiled (numba's cache lacks its epoch runner): a
    second worker then compiles the epoch chain's late part while the first compiles from the start
    (:mod:`ultratight.receiver.deep.compile_ahead`), with one job too."""
    return not engine_kernels_cached()


@contextmanager
def compiling_ahead():
    """On a first run (:func:`first_compilation`) a helper process compiles the engine's epoch chain
    (:func:`ultratight.receiver.deep.compile_ahead.compile_ahead`) while the body runs, which then loads
    it from numba's cache; waited for at the end, stopped on an error or an interruption. Otherwise
    nothing is started."""
    if not first_compilation():
        yield
        return
    from ultratight.receiver.cli.workers import WorkerPool
    from ultratight.receiver.deep.compile_ahead import compile_ahead
    with WorkerPool(1, processes=True) as pool:
        pool.start(compile_ahead)
        yield


def drop_if_file(paths, lock, version):
    """Remove the IF file and its sidecar from the run's cache entry (``paths`` of ``prepare_data``),
    under the entry's ``lock``, when this run wrote them (``paths["if_written"]``; an IF file a
    ``--cache`` run put there before stays): ``done.json`` is rewritten without them first, so an
    interruption leaves a valid entry (at worst with a file it no longer lists)."""
    if "if" not in paths or not paths.get("if_written"):
        return
    d = Path(paths["if"]).parent
    done = d / "done.json"
    with lock(d):
        try:
            entry = json.loads(done.read_text(encoding="utf-8"))
            files = dict(entry["files"])
        except (OSError, ValueError, KeyError, TypeError):
            return
        gone = [files.pop(k) for k in ("if", "meta") if k in files]
        write_text_atomic(done, json.dumps({"version": version, "files": files}))
        for rec in gone:
            try:
                (d / rec["name"]).unlink()
            except OSError:
                pass


# ------------------------------------------------------------------------------------------
# a warm cache known to hold a run's kernels: no warm-up
# ------------------------------------------------------------------------------------------
WARM_MARKER = "ultratight-warm-runs.json"
WARM_MARKER_KEYS = 64          # run kinds remembered


def _sources_stamp(root=None):
    """numba's cache is valid for a kernel while its source file keeps its modification time and size:
    those of every module of the package (or under ``root``), with numba's and Python's versions."""
    import sys

    import numba

    root = Path(__file__).resolve().parents[2] if root is None else Path(root)
    files = sorted(root.rglob("*.py"))
    parts = [numba.__version__, sys.version]
    for p in files:
        try:
            st = p.stat()
        except OSError:
            continue
        parts.append(f"{p.relative_to(root)}:{st.st_mtime_ns}:{st.st_size}")
    return parts


def warm_key(*what, root=None):
    """The key of a kind of run (``what``: anything JSON can hold that decides which kernels and
    argument types it compiles, e.g. the methods, the generator's front end and the engine's options)
    at the package's current sources (``root``: another source tree's)."""
    import hashlib

    blob = json.dumps([_sources_stamp(root), what], sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:24]


def _marker_path():
    try:
        from ultratight.receiver.deep.epochs import run_epochs
        return Path(run_epochs._cache._cache_path) / WARM_MARKER
    except Exception:            # noqa: BLE001 - numba's cache layout is not public: no marker
        return None


def warm_cache_known(key):
    """Whether a run of kind ``key`` (:func:`warm_key`) completed since the sources last changed: its
    kernels are then in numba's cache (it compiled them, or loaded them), and the run's warm-up
    (:func:`ultratight.receiver.cli.workers.warm_up`) would only load them once more. The marker
    lives beside numba's cache files, so removing the cache removes it too."""
    path = _marker_path()
    if path is None or not path.is_file():
        return False
    try:
        return key in json.loads(path.read_text(encoding="utf-8")).get("keys", [])
    except (OSError, ValueError, AttributeError):
        return False


def note_warm_cache(key):
    """Record that a run of kind ``key`` completed (:func:`warm_cache_known`); quietly nothing where the
    cache folder cannot be written (numba does not cache there either)."""
    path = _marker_path()
    if path is None or not path.parent.is_dir():
        return
    keys = []
    try:
        keys = list(json.loads(path.read_text(encoding="utf-8")).get("keys", []))
    except (OSError, ValueError, AttributeError):
        pass
    if key in keys:
        return
    keys = (keys + [key])[-WARM_MARKER_KEYS:]
    try:
        write_text_atomic(path, json.dumps({"keys": keys}))
    except OSError:
        pass
