"""The scenario's data cache filled while the methods run (scenario_data.shared_run_data): the entry equals
the one prepare_data generates before them (every truth dataset and attribute but the elapsed time, the
IMU and trajectory files), is reused by the next run, and leaves nothing behind when the run fails."""

import json

import h5py
import numpy as np
import pytest

from ultratight.receiver.cli import scenario_data as SD
from ultratight.receiver.cli.scenario_config import load_scenario
from ultratight.signals.synth.ifring import RingIf

OVERRIDES = {"duration_s": 1.0, "frontend.fs_hz": 2.046e6, "satellites.max_count": 3}


def _cfg():
    return load_scenario("paper-highdyn", OVERRIDES)


def _read_all(ring, cfg, seed):
    """Consume the ring as its one method would (every block, in order)."""
    src = RingIf(SD._generator_cfg(cfg), seed, ring.name, 0)
    try:
        n = 0
        while n < src.n_samples:
            n += src.read(n, min(100_000, src.n_samples - n)).shape[0]
    finally:
        src.close()
    return n


def _h5_items(path):
    out = {}
    with h5py.File(path, "r") as f:
        def visit(name, obj):
            if isinstance(obj, h5py.Dataset):
                out[name] = obj[()]
            out.update({f"{name}@{k}": v for k, v in obj.attrs.items()})
        f.visititems(visit)
        out.update({f"@{k}": v for k, v in f.attrs.items() if k != "elapsed_s"})
    return out


def test_entry_written_by_the_ring_equals_the_one_made_before(tmp_path):
    cfg, seed = _cfg(), 5
    before, cached = SD.prepare_data(cfg, seed, tmp_path / "before", cache_if=False)
    assert not cached
    with SD.shared_run_data(cfg, seed, tmp_path / "ring", 1) as data:
        assert not data.reused
        # the methods' view before the truth exists: the IMU is there, the satellites and time base given
        assert data.paths["imu"].is_file() and not data.paths["truth"].exists()
        with h5py.File(before["truth"], "r") as f:
            assert data.paths["truth_head"] == {"prn": [int(p) for p in f.attrs["prn"]],
                                                "week": int(f.attrs["week"]), "tow0_s": float(f.attrs["tow0_s"])}
        data.ring.start()
        assert _read_all(data.ring, cfg, seed) == 2046000
        paths = data.complete()
    for kind in ("truth", "imu", "trajectory"):
        a, b = _h5_items(before[kind]), _h5_items(paths[kind])
        assert a.keys() == b.keys(), kind
        for k in a:
            assert np.array_equal(np.asarray(a[k]), np.asarray(b[k])), (kind, k)
    listed = json.loads((paths["truth"].parent / "done.json").read_text())["files"]
    assert set(listed) == {"truth", "imu", "trajectory"}
    # the next run reuses the entry
    with SD.shared_run_data(cfg, seed, tmp_path / "ring", 1) as again:
        assert again.reused and again.paths["truth"] == paths["truth"]
        again.ring.start()
        _read_all(again.ring, cfg, seed)


def test_a_failed_run_leaves_no_entry(tmp_path):
    cfg, seed = _cfg(), 6
    with pytest.raises(RuntimeError, match="a method failed"):
        with SD.shared_run_data(cfg, seed, tmp_path, 1) as data:
            data.ring.start()
            raise RuntimeError("a method failed")
    cache = tmp_path / "cache"
    assert not [p for p in cache.iterdir() if p.is_dir()]         # the entry's folder removed with its files
    # and the next run generates the entry afresh
    with SD.shared_run_data(cfg, seed, tmp_path, 1) as data:
        assert not data.reused
        data.ring.start()
        _read_all(data.ring, cfg, seed)
    assert any((d / "done.json").is_file() for d in cache.iterdir() if d.is_dir())


def test_without_shared_memory_nothing_is_written(tmp_path, monkeypatch):
    class NoShm:
        def __init__(self, *a, **k):
            raise OSError(28, "No space left on device")

    monkeypatch.setattr(SD, "IfRing", NoShm)
    with pytest.raises(SD.NoSharedMemory, match="No space left on device"):
        with SD.shared_run_data(_cfg(), 7, tmp_path, 2):
            pass
    assert not [p for p in (tmp_path / "cache").iterdir() if p.is_dir()]


def test_a_truth_write_failure_reaches_the_run_and_leaves_no_entry(tmp_path, monkeypatch):
    """The ring's producer cannot write the truth (a full disk on its third block): the methods stop
    with the ring, the run ends with that OSError (errno kept, the CLI's one line), the entry is gone."""
    import errno

    from ultratight.errors import ConfigError
    calls = {"n": 0}
    append = SD.GenerationFiles.append

    def failing(self, rows):
        calls["n"] += 1
        if calls["n"] == 3:
            raise OSError(errno.ENOSPC, "No space left on device", str(self.paths["truth"]))
        append(self, rows)

    monkeypatch.setattr(SD.GenerationFiles, "append", failing)
    cfg, seed = _cfg(), 8
    with pytest.raises(OSError) as err:
        with SD.shared_run_data(cfg, seed, tmp_path, 1) as data:
            data.ring.start()
            _read_all(data.ring, cfg, seed)
    assert err.value.errno == errno.ENOSPC
    assert isinstance(err.value.__context__, ConfigError)          # what the method met: the ring stopped
    assert "IF ring stopped" in str(err.value.__context__)
    assert not [p for p in (tmp_path / "cache").iterdir() if p.is_dir()]


def test_a_second_run_on_the_same_entry_waits_and_reuses_it(tmp_path):
    """While one run's ring writes the entry, another run of the same data is told (``waiting``), waits
    for the lock and then reuses the complete entry."""
    import threading

    cfg, seed = _cfg(), 9
    holding, release = threading.Event(), threading.Event()
    failures = []

    def first():
        try:
            with SD.shared_run_data(cfg, seed, tmp_path, 1) as data:
                holding.set()
                release.wait(60)
                data.ring.start()
                _read_all(data.ring, cfg, seed)
        except BaseException as exc:          # handed to the test
            failures.append(exc)
            holding.set()

    t = threading.Thread(target=first)
    t.start()
    assert holding.wait(60)
    told = []

    def waiting(lock_path):
        told.append(lock_path)
        release.set()

    with SD.shared_run_data(cfg, seed, tmp_path, 1, waiting=waiting) as data:
        assert data.reused
        data.ring.start()
        _read_all(data.ring, cfg, seed)
    t.join(60)
    assert not failures and len(told) == 1 and told[0].name.endswith(".lock")


def test_an_entry_without_its_if_gets_the_if_file_alone(tmp_path):
    """A streamed run's entry (truth, IMU, no IF) asked for its IF file: only the IF and its sidecar are
    written (the truth and IMU files untouched), with the bytes of a fresh entry's IF file."""
    cfg, seed = _cfg(), 7
    made = set()
    streamed, cached = SD.prepare_data(cfg, seed, tmp_path / "a", cache_if=False, made=made)
    assert not cached and made == {"truth", "imu", "trajectory"}
    stamps = {k: (streamed[k].stat().st_ino, streamed[k].stat().st_mtime_ns) for k in ("truth", "imu", "trajectory")}
    made = set()
    added, cached = SD.prepare_data(cfg, seed, tmp_path / "a", cache_if=True, made=made)
    assert cached and made == {"if", "meta"}
    assert {k: (added[k].stat().st_ino, added[k].stat().st_mtime_ns) for k in stamps} == stamps
    listed = json.loads((added["truth"].parent / "done.json").read_text())["files"]
    assert set(listed) == {"truth", "imu", "trajectory", "if", "meta"}
    fresh, cached = SD.prepare_data(cfg, seed, tmp_path / "b", cache_if=True)
    assert not cached
    assert added["if"].read_bytes() == fresh["if"].read_bytes()
    a, b = (json.loads(p.read_text()) for p in (added["meta"], fresh["meta"]))
    assert a == b
    made = set()
    again, cached = SD.prepare_data(cfg, seed, tmp_path / "a", cache_if=True, made=made)
    assert cached and not made and again["if"] == added["if"]
