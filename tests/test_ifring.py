"""One generated IF shared by several readers (ultratight.signals.synth.ifring): every reader gets the
samples of its own stream, a reader that stops early holds nobody up, a failure stops everybody
with one clear error, and the shared memory is freed."""

import threading
from pathlib import Path

import numpy as np
import pytest

from ultratight.errors import ConfigError
from ultratight.receiver.cli.scenario_config import load_scenario
from ultratight.signals.synth.ifring import IfRing, RingIf
from ultratight.signals.synth.ifstream import GeneratedIf

STEP = 20000


@pytest.fixture(scope="module")
def cfg():
    c = load_scenario("paper-highdyn", {"duration_s": 1.5, "frontend.fs_hz": 2.046e6, "satellites.max_count": 3})
    return {k: v for k, v in c.items() if k not in ("source_file", "engine")}


def _read_all(src, stop_at=None):
    out, s = [], 0
    end = src.n_samples if stop_at is None else stop_at
    while s < end:
        out.append(src.read(s, min(STEP, end - s)))
        s += STEP
    return np.concatenate(out)


def _segments(ring):
    return [Path("/dev/shm") / (ring.name + sfx) for sfx in ("-d", "-c")]


def test_every_reader_gets_the_streamed_samples(cfg):
    with GeneratedIf(cfg, 7) as g:
        ref = _read_all(g)
    got = {}

    def reader(i, stop_at=None):
        with RingIf(cfg, 7, ring.name, i) as src:
            got[i] = _read_all(src, stop_at)

    with IfRing(cfg, 7, 3, slots=3) as ring:
        segs = _segments(ring)
        assert all(p.exists() for p in segs)
        # reader 2 stops after a quarter of the samples: the others must still get to the end
        ts = [threading.Thread(target=reader, args=(i, ref.size // 4 if i == 2 else None)) for i in range(3)]
        [t.start() for t in ts]
        [t.join(timeout=120) for t in ts]
        assert not any(t.is_alive() for t in ts)
    np.testing.assert_array_equal(got[0], ref)
    np.testing.assert_array_equal(got[1], ref)
    np.testing.assert_array_equal(got[2], ref[:ref.size // 4])
    assert not any(p.exists() for p in segs)             # freed by the producer's close
    with pytest.raises(ConfigError, match="is gone"):
        RingIf(cfg, 7, ring.name, 0)


def test_abort_stops_a_waiting_reader_with_one_clear_error(cfg):
    errors = []
    ring = IfRing(cfg, 3, 2, slots=2)     # not started: reader 0 waits for the first block

    def reader():
        try:
            with RingIf(cfg, 3, ring.name, 0) as src:
                src.read(0, 1000)
        except ConfigError as exc:
            errors.append(str(exc))

    t = threading.Thread(target=reader)
    t.start()
    ring.abort()
    t.join(timeout=30)
    ring.close()
    assert not t.is_alive() and len(errors) == 1
    assert "the IF ring stopped" in errors[0] and "\n" not in errors[0]


def test_a_reader_cannot_rewind_and_consumer_index_is_checked(cfg):
    with IfRing(cfg, 5, 1, slots=2) as ring:
        with pytest.raises(ConfigError, match="consumer 1 of a ring of 1"):
            RingIf(cfg, 5, ring.name, 1)
        with RingIf(cfg, 5, ring.name, 0, keep_s=0.01) as src:
            src.read(0, 1000)
            src.read(src.n_samples // 2, 1000)
            with pytest.raises(ConfigError, match="cannot be read again from its start"):
                src.read(0, 1000)


@pytest.mark.parametrize("slots, keep_s", [(2, 0.5), (3, 0.01), (8, 0.25), (4, 1.2)])
def test_readers_holding_slots_get_the_samples_and_never_block_the_producer(cfg, slots, keep_s):
    """A reader reads the ring's slots in place and lets the producer reuse one only when it no longer
    holds its block; one that keeps more samples than the ring has slots for copies what it holds
    instead of waiting for a block the producer has no slot for. Two readers of different habits (one
    re-reading its kept samples) get the streamed samples to the end."""
    with GeneratedIf(cfg, 11) as g:
        ref = _read_all(g)
    got, errors = {}, []

    def reader(i):
        try:
            with RingIf(cfg, 11, ring.name, i, keep_s=keep_s) as src:
                if i == 0:
                    got[i] = _read_all(src)
                    return
                out, s, back = [], 0, int(keep_s * src.fs_hz * 0.5)
                while s < src.n_samples:            # every read starts inside the kept samples
                    n = min(STEP, src.n_samples - s)
                    x = src.read(max(0, s - back), n + min(back, s))
                    out.append(x[min(back, s):])
                    s += n
                got[i] = np.concatenate(out)
        except Exception as exc:                   # reported below, not lost in the thread
            errors.append(exc)

    with IfRing(cfg, 11, 2, slots=slots) as ring:
        ts = [threading.Thread(target=reader, args=(i,)) for i in range(2)]
        [t.start() for t in ts]
        [t.join(timeout=120) for t in ts]
        assert not any(t.is_alive() for t in ts), "a reader or the producer waits for a slot"
    assert not errors, errors
    np.testing.assert_array_equal(got[0], ref)
    np.testing.assert_array_equal(got[1], ref)
