"""IF block stream: aligned blocks in a sliding buffer equal the file's samples, each block's noise
estimate is the correlator's, demand reads estimate from their head, and the estimator is one."""

import math

import numpy as np
import pytest

from ultratight.errors import ConfigError
from ultratight.receiver.dsp.blockstream import BlockStream, NoiseFloor, block_sigma_arm
from ultratight.receiver.dsp.correlator import estimate_sigma_arm
from ultratight.signals.recording.iffile import open_if, write_if


@pytest.fixture(params=["ci8", "i16", "cf32"])
def src(request, tmp_path):
    rng = np.random.default_rng(4)
    n = 10_000
    gain = np.repeat([20.0, 5.0, 40.0, 10.0, 30.0], n // 5)        # a different noise level per 2000 samples
    if request.param.startswith("c"):
        x = (rng.normal(size=n) + 1j * rng.normal(size=n)) * gain + 3.0
    else:
        x = rng.normal(size=n) * gain + 3.0
    p = write_if(tmp_path / "x.dat", x, request.param, 1e6, 0.0 if request.param.startswith("c") else 2.5e5)
    with open_if(p) as s:
        yield s


def test_aligned_blocks_and_their_noise(src):
    st = BlockStream(src, 2000)
    assert st.ensure(4500, keep_from=0)
    assert st.buf_start == 0 and st.buf_end == 6000
    np.testing.assert_array_equal(st.buf, src.read(0, 6000))
    for k in range(3):
        ref = estimate_sigma_arm(src.read(2000 * k, 2000), src.is_complex)
        assert st.sigma_at(2000 * k + 1999) == pytest.approx(ref, rel=1e-12)
    assert st.sigma_at(4100) > 3 * st.sigma_at(2100)                  # x40 vs x5 gain
    # sliding: samples before keep_from are dropped, a later view reads them back from the file
    assert st.ensure(9000, keep_from=5000)
    assert st.buf_start == 5000 and st.buf_end == 10_000
    v, lo = st.view(5500)
    np.testing.assert_array_equal(v, src.read(5500, 4500))
    v, lo = st.view(100)
    np.testing.assert_array_equal(v, src.read(100, 9900))
    assert not st.ensure(10_001, keep_from=9000)                      # past the end of the file
    np.testing.assert_allclose(st.sigma_at(np.array([0, 9999])), st.sigma_at([1, 8000]))


def test_noise_floor_and_sigma_stop(src):
    held = BlockStream(src, 2000, floor=NoiseFloor(float("inf"), 2e-3))
    held.ensure(10_000, 0)
    assert np.all(held.sigma_at(np.arange(0, 10_000, 2000)) == held.sigma_at(0))
    cut = BlockStream(src, 2000, sigma_stop=5000)
    cut.ensure(6000, 0)
    assert cut.sigma_at(4000) == pytest.approx(block_sigma_arm(src.read(4000, 1000), src.is_complex), rel=1e-12)


def test_demand_reads_estimate_from_their_head(src):
    st = BlockStream(src, 2000, on_zero=1.0)
    x, sg = st.read_at(1500, 3000, head=400)
    np.testing.assert_array_equal(x, src.read(1500, 3000))
    assert sg == pytest.approx(block_sigma_arm(x[:400], src.is_complex), rel=1e-12)


def test_estimator_closed_forms_and_zero_power():
    x = np.array([1 + 1j, -1 - 1j, 1 - 1j, -1 + 1j], np.complex64) + (5 - 2j)
    assert block_sigma_arm(x, True) == pytest.approx(1.0)
    assert block_sigma_arm(x, True, fast=True) == pytest.approx(1.0)
    r = np.array([2.0, -2.0, 2.0, -2.0], np.float32) + 7
    assert block_sigma_arm(r, False) == pytest.approx(2.0 / math.sqrt(2.0))
    assert block_sigma_arm(np.ones(8, np.complex64), True) == 0.0
    assert block_sigma_arm(np.zeros(0, np.float32), False) == 0.0

    class Flat:
        is_complex, n_samples = True, 100

        def read(self, start, count):
            return np.ones(max(0, min(count, 100 - start)), np.complex64)
    with pytest.raises(ConfigError, match="zero noise power"):
        BlockStream(Flat(), 50).ensure(60, 0)
    assert BlockStream(Flat(), 50, on_zero=1.0).read_at(0, 50, 10)[1] == 1.0


def test_release_keeps_samples_readable(src):
    st = BlockStream(src, 2000)
    st.release(8000)
    x, _ = BlockStream(src, 2000, on_zero=1.0).read_at(0, 100, 100)
    np.testing.assert_array_equal(st.read_at(0, 100, 100)[0], x)

    class NoRelease:
        is_complex, n_samples = False, 10

        def read(self, start, count):
            return np.arange(10, dtype=np.float32)[start:start + count]
    assert BlockStream(NoRelease(), 5).release(5) == 0


def test_reading_on_releases_the_pages_behind_the_kept_samples(src, monkeypatch):
    """A long file read through its mapping: the stream hands the pages behind the samples it keeps
    back every RELEASE_BLOCKS blocks (the data stay readable), so the resident set does not grow to
    the file's size."""
    from ultratight.receiver.dsp import blockstream
    monkeypatch.setattr(blockstream, "RELEASE_BLOCKS", 2)
    calls = []
    real = src.release
    monkeypatch.setattr(src, "release", lambda upto: calls.append(upto) or real(upto))
    want = src.read(500, 9500).copy()
    st = BlockStream(src, 1000)
    for hi in range(1000, 10_001, 1000):
        st.ensure(hi, keep_from=hi - 1000)
    assert calls == [2000, 4000, 6000, 8000]
    np.testing.assert_array_equal(st.view(500)[0], want)         # released samples read back from the file


def test_block_noise_estimate_is_exact_and_independent_of_where_the_block_lies():
    """The fast kernel against an exactly rounded two-pass reference (``math.fsum``), and the same
    value for the same block at every alignment in memory (the reassociated sums keep one order)."""
    from ultratight.receiver.dsp.blockstream import input_sigma

    rng = np.random.default_rng(11)
    z = (rng.normal(size=4001) + 1j * rng.normal(size=4001)) * 37.0 + (2.0 - 1.0j)
    for x in (z.astype(np.complex64), np.round(z).astype(np.complex64)):      # any values; integer levels
        x64 = x.astype(np.complex128)
        m = complex(math.fsum(x64.real), math.fsum(x64.imag)) / x.size
        ref = math.sqrt(math.fsum(np.abs(x64 - m) ** 2) / x.size / 2.0)
        values = set()
        for off in range(8):                      # 0-7 samples of 8 bytes: every alignment in a 64-byte line
            buf = np.empty(x.size + 8, np.complex64)
            y = buf[off:off + x.size]
            y[:] = x
            values.add(input_sigma(y, True, fast=True))
        assert len(values) == 1
        assert values.pop() == pytest.approx(ref, rel=1e-13)
