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
