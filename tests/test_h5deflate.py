"""ultratight.h5deflate against HDF5's own filter pipeline: what it writes reads back through HDF5 as the
array (every shape, with edge chunks, and dtype), and a chunk HDF5 itself compressed decompresses, by
the module's layout of the shuffle, to the array's chunk."""

import io
import zlib
from concurrent.futures import ThreadPoolExecutor

import h5py
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from ultratight.h5deflate import CHUNK_BYTES, Deflated, chunk_shape

DTYPES = [np.float64, np.float32, np.int64, np.int8, np.uint16, np.complex64, np.bool_]


def _array(rng, shape, dtype):
    if dtype is np.bool_:
        return rng.random(shape) > 0.5
    if np.issubdtype(dtype, np.complexfloating):
        return (rng.normal(size=shape) + 1j * rng.normal(size=shape)).astype(dtype)
    if np.issubdtype(dtype, np.integer):
        info = np.iinfo(dtype)
        return rng.integers(info.min, info.max, size=shape, dtype=dtype, endpoint=True)
    return rng.normal(size=shape).cumsum(axis=0).astype(dtype)


@settings(max_examples=40, deadline=None)
@given(shape=st.lists(st.integers(0, 9000), min_size=0, max_size=3).filter(
           lambda s: int(np.prod(s, dtype=np.int64)) <= 200_000),
       dtype=st.sampled_from(DTYPES), shuffle=st.booleans(), threads=st.sampled_from([0, 2]),
       seed=st.integers(0, 2**31 - 1))
def test_written_chunks_read_back_through_hdf5(shape, dtype, shuffle, threads, seed):
    a = _array(np.random.default_rng(seed), tuple(shape), dtype)
    if a.ndim == 0:
        a = np.asarray(a)
    bio = io.BytesIO()
    with ThreadPoolExecutor(threads) if threads else _no_pool() as pool, h5py.File(bio, "w") as f:
        ds = Deflated(a, pool, shuffle=shuffle).write(f, "x")
        if a.ndim and a.size:
            assert ds.chunks == chunk_shape(a.shape, a.dtype.itemsize)
            assert ds.compression == "gzip" and ds.compression_opts == 1 and ds.shuffle == shuffle
    with h5py.File(bio, "r") as f:
        back = f["x"][()]
    assert back.dtype == a.dtype and back.shape == a.shape
    assert np.array_equal(back, a)


class _no_pool:
    def __enter__(self):
        return None

    def __exit__(self, *exc):
        return False


def test_a_chunk_compressed_by_hdf5_unpacks_by_this_layout():
    """HDF5 compresses a dataset with the same filters; its stored chunks, inflated and unshuffled the
    way this module shuffles (byte k of every element together), are the array's chunks."""
    rng = np.random.default_rng(7)
    a = rng.normal(size=(10_000, 3)).cumsum(axis=0)
    chunks = chunk_shape(a.shape, a.dtype.itemsize)
    assert chunks == (CHUNK_BYTES // 8, 1)
    bio = io.BytesIO()
    with h5py.File(bio, "w") as f:
        ds = f.create_dataset("x", data=a, chunks=chunks, compression="gzip", compression_opts=1, shuffle=True)
        n = 0
        for i0 in range(0, a.shape[0], chunks[0]):
            for j in range(a.shape[1]):
                mask, stored = ds.id.read_direct_chunk((i0, j))
                assert mask == 0
                raw = np.frombuffer(zlib.decompress(stored), np.uint8).reshape(8, -1).T.copy()
                got = raw.view(np.float64).ravel()
                want = a[i0:i0 + chunks[0], j]
                assert np.array_equal(got[:want.size], want)
                assert not np.any(got[want.size:])          # the edge chunk's padding
                n += 1
    assert n == 3 * -(-a.shape[0] // chunks[0])
