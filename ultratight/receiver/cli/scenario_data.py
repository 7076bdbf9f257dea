"""The scenario's data cache (``OUT/cache/<key>/``, docs/ultratight.md "Outputs"): truth, IMU and trajectory
(and with ``--cache`` the IF file) of a resolved scenario and seed, generated once and reused while the
configuration and the package version stay the same.

Two ways to fill an entry: :func:`prepare_data` generates its files before the methods run; a run whose
methods share one generated IF (:func:`shared_run_data`) writes only the IMU and trajectory first and the
truth while the IF ring's producer generates the samples (the truth's rows come with every block:
one pass of the signal geometry instead of two), the entry listed complete (``done.json``) once the
truth is.
"""

import hashlib
import json
from contextlib import contextmanager
from pathlib import Path

import h5py

from ultratight import __version__
from ultratight.errors import ConfigError, InputFileError
from ultratight.io_guard import output_error, write_text_atomic
from ultratight.receiver.dsp.burst import PLACE_IF, event_place
from ultratight.signals.recording.iffile import open_if
from ultratight.signals.synth.generator import GenerationFiles, generate, output_paths
from ultratight.signals.synth.ifring import IfRing

try:
    import fcntl
except ImportError:      # pragma: no cover - no fcntl (not POSIX): cache entries are not locked
    fcntl = None

def _cfg_key(cfg):
    evs = cfg.get("noise_events") or []
    if any(event_place(ev) != PLACE_IF for ev in evs):
        # noise events inside the receiver do not change the data: one cache entry for their readings
        cfg = dict(cfg, noise_events=[ev for ev in evs if event_place(ev) == PLACE_IF])
    blob = json.dumps(cfg, sort_keys=True, default=str) + __version__ + DATA_MODEL
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


# the generated data's model, part of the cache key: entries of an older model are never reused
# ("imu-realised": the IMU sensor drawn per seed from the [imu] declaration, ultratight.ins.imu)
DATA_MODEL = "imu-realised"
CACHE_VERSION = 2       # done.json layout: {"version", "files": {kind: {"name", "size"}}}


def _cache_entry_ok(d, done, need_if=True):
    """Paths of a verified cache entry, or None (missing, unparsable, wrong sizes, bad sidecar; without
    the IF file when ``need_if``)."""
    try:
        entry = json.loads(done.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if not isinstance(entry, dict) or entry.get("version") != CACHE_VERSION or not isinstance(entry.get("files"), dict):
        return None
    paths = {}
    for kind, rec in entry["files"].items():
        if not isinstance(rec, dict) or not isinstance(rec.get("name"), str) or "/" in rec["name"]:
            return None
        p = d / rec["name"]
        try:
            if not p.is_file() or p.stat().st_size != rec.get("size"):
                return None
        except OSError:
            return None
        paths[kind] = p
    if "truth" not in paths or (need_if and "if" not in paths):
        return None
    if "if" in paths:
        try:
            open_if(paths["if"]).close()
        except (OSError, ValueError):
            return None
    return paths


@contextmanager
def _cache_lock(d, waiting=None):
    """Exclusive per-key lock (``fcntl.flock`` on ``OUT/cache/<key>.lock``): concurrent runs of the same
    configuration wait for each other instead of writing the same files. ``waiting(lock_path)`` is
    called when another run holds the lock, before this one waits for it."""
    lock_path = d.with_name(d.name + ".lock")
    fh = open(lock_path, "a+")
    try:
        if fcntl is not None:
            try:
                fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                if waiting is not None:
                    waiting(lock_path)
                fcntl.flock(fh.fileno(), fcntl.LOCK_EX)
        yield
    finally:
        fh.close()               # releases the lock


def prepare_data(cfg, seed, out_dir, progress=False, cache_if=True, made=None):
    """Generate the scenario's files under OUT/cache/<key>/ unless a verified entry is already there;
    returns (paths, whether the truth and IMU were there).

    The entry is guarded by a per-key lock; ``done.json`` records every file's name and size and is
    written last (atomically); an entry that does not verify is regenerated. ``cache_if=False``: the
    entry needs no IF file (one without is generated without it) and the paths returned have no
    ``if``/``meta`` but ``if_seed``, the seed :func:`ultratight.receiver.cli.scenario_runner.run_method`
    streams the IF of. An entry verified but for its IF file gets the IF file alone (the truth and IMU
    kept). ``made`` (a set) gets the kinds of the files this call wrote."""
    c, d = _entry_dir(cfg, seed, out_dir)
    done = d / "done.json"
    made = set() if made is None else made
    with _cache_lock(d):
        paths = _cache_entry_ok(d, done, need_if=cache_if) if done.is_file() else None
        if paths is not None:
            return _data_paths(paths, cache_if, seed), True
        paths = _cache_entry_ok(d, done, need_if=False) if done.is_file() else None
        if paths is not None:            # only the IF file is missing
            try:
                res = generate(c, d, "data", seed=int(seed), progress=progress, write_rest=False)
            except BaseException as exc:
                _failed_entry(d, exc)
                raise
            made.update(("if", "meta"))
            return _list_entry(done, dict(paths, **{k: res[k] for k in ("if", "meta")})), True
        _fresh_entry(d, done)
        try:
            res = generate(c, d, "data", seed=int(seed), progress=progress, write_if=cache_if)
        except BaseException as exc:
            _failed_entry(d, exc)
            raise
        files = {k: v for k, v in res.items() if k != "summary"}
        made.update(files)
        return _data_paths(_list_entry(done, files), cache_if, seed), False


def _remove_if_empty(d):
    try:
        d.rmdir()
    except OSError:
        pass


def _failed_entry(d, exc):
    """After a failed generation into the entry ``d``: its folder removed when empty (the generator
    removed its temporary files); an OSError raised again as one line naming the folder."""
    _remove_if_empty(d)
    if isinstance(exc, OSError) and not isinstance(exc, (ConfigError, InputFileError)):
        raise output_error(d, exc, "cannot write scenario data in") from None


def _data_paths(paths, cache_if, seed):
    """The paths a method reads: with the cached IF file, or (streamed) without it and with ``if_seed``."""
    if cache_if:
        return paths
    out = {k: v for k, v in paths.items() if k not in ("if", "meta")}
    out["if_seed"] = int(seed)
    return out


def _generator_cfg(cfg):
    """The generator's part of a scenario (processing settings left out)."""
    return {k: v for k, v in cfg.items() if k not in ("source_file", "engine")}


def load_truth(path):
    """Truth arrays of the generator (docs/generator.md): t_s (n,), prn (n_ch,), code phase,
    Doppler (n, n_ch)."""
    try:
        with h5py.File(path, "r") as f:
            return {"t_s": f["t_s"][()], "prn": [int(p) for p in f.attrs["prn"]],
                    "code_phase_chips": f["code_phase_chips"][()], "doppler_hz": f["doppler_hz"][()],
                    "config": json.loads(f.attrs["config_json"]), "fs_hz": float(f.attrs["fs_hz"]),
                    "week": int(f.attrs["week"]), "tow0_s": float(f.attrs["tow0_s"])}
    except (OSError, KeyError) as exc:
        raise InputFileError(f"{path}: cannot read generator truth ({exc})") from None


def _entry_dir(cfg, seed, out_dir):
    """The cache entry of ``cfg`` (the generator's part) and ``seed``, its parent created."""
    c = _generator_cfg(cfg)          # processing settings are not part of the generated data
    c["seed"] = int(seed)
    d = Path(out_dir) / "cache" / _cfg_key(c)
    try:
        d.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise output_error(d.parent, exc, "cannot create cache directory") from None
    return c, d


def _fresh_entry(d, done):
    """An entry about to be (re)generated: its ``done.json`` removed, the folder there."""
    try:
        done.unlink()
    except FileNotFoundError:
        pass
    except OSError as exc:
        raise output_error(done, exc, "cannot remove stale cache entry") from None
    try:
        d.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise output_error(d, exc, "cannot create cache directory") from None


def _list_entry(done, files):
    """``done.json`` of an entry holding ``files`` (paths by kind), written last and atomically."""
    listed = {k: {"name": Path(v).name, "size": Path(v).stat().st_size} for k, v in files.items()}
    write_text_atomic(done, json.dumps({"version": CACHE_VERSION, "files": listed}))
    return {k: done.parent / v["name"] for k, v in listed.items()}


def truth_head(generation):
    """What a method reads of the truth before it runs (:func:`load_truth`'s ``prn``, ``week`` and
    ``tow0_s``), from the generation itself."""
    return {"prn": [int(p) for p in generation.plan.prns], "week": int(generation.week),
            "tow0_s": float(generation.tow0)}


class NoSharedMemory(Exception):
    """:func:`shared_run_data` cannot make the IF ring (no shared memory, or too little); nothing written."""


class SharedRunData:
    """The data of one run whose methods read one IF ring (:func:`shared_run_data`): ``ring`` (an
    :class:`ultratight.signals.synth.ifring.IfRing`, not started), ``paths`` (the methods' data paths,
    with ``truth_head`` for a truth still being written), ``reused`` (the entry was complete)."""

    def __init__(self, ring, paths, reused, files, done):
        self.ring, self.paths, self.reused = ring, paths, reused
        self._files, self._done = files, done

    def complete(self):
        """Wait for the ring's producer to finish the truth; then the entry's files are committed and
        listed (``done.json``). Returns the paths by kind. Idempotent."""
        self.ring.wait()
        if self._files is not None:
            files, self._files = self._files, None
            written = files.commit()
            self.paths.update(_list_entry(self._done, written))
        return self.paths


@contextmanager
def shared_run_data(cfg, seed, out_dir, n_consumers, waiting=None):
    """The IF ring of run ``seed`` for ``n_consumers`` methods and the run's data (a
    :class:`SharedRunData`), under the entry's lock until the block ends. A complete entry is reused;
    otherwise the IMU and trajectory are written now and the truth by the ring's producer
    (:meth:`SharedRunData.complete`, which the block must call once the methods are done: an entry
    left incomplete — an error, an interruption — is removed and regenerated by the next run). The
    ring is closed at the end (raising its producer's error, if any). OSError from the shared memory
    (none, or too little) is raised before anything is written. Another run writing the same entry
    holds its lock until its truth is complete: ``waiting(lock_path)`` is called, then this run waits
    and reuses the entry."""
    c, d = _entry_dir(cfg, seed, out_dir)
    done = d / "done.json"
    with _cache_lock(d, waiting):
        paths = _cache_entry_ok(d, done, need_if=False) if done.is_file() else None
        try:
            ring = IfRing(c, int(seed), n_consumers)
        except OSError as exc:
            raise NoSharedMemory(exc.strerror or str(exc)) from None
        files = data = None
        try:
            gen = ring.generation
            if paths is None:
                _fresh_entry(d, done)
                try:
                    files = GenerationFiles(gen, output_paths(d, "data", gen.spec.name))
                    files.commit_imu()           # the methods read the IMU from their start
                except BaseException as exc:
                    if files is not None:
                        files.abort()
                        files = None
                    _failed_entry(d, exc)
                    raise
                ring.write_files(files)
                paths = dict(files.written)
            run_paths = _data_paths(paths, False, seed)
            run_paths["truth_head"] = truth_head(gen)
            data = SharedRunData(ring, run_paths, files is None, files, done)
            yield data
            data.complete()
        except BaseException:
            ring.abort()
            pending = files if data is None else data._files      # not committed: removed
            if pending is not None:
                ring.wait(quiet=True)          # the producer stopped writing first
                pending.abort()
                _remove_if_empty(d)
            raise
        finally:
            ring.close()


__all__ = ["CACHE_VERSION", "DATA_MODEL", "NoSharedMemory", "SharedRunData", "load_truth", "prepare_data",
           "shared_run_data", "truth_head"]
