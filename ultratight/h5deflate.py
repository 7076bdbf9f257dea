"""HDF5 datasets compressed outside the HDF5 library, on several threads.

HDF5 runs a dataset's filters (h5py's ``compression="gzip", shuffle=True``: the byte shuffle, then
deflate) chunk after chunk on the thread that writes, holding the GIL — about 1.5 s of a scenario's
``results.h5`` (docs/ultratight.md) on one core while the other waits. :class:`Deflated` applies the
same two filters to an array's chunks with zlib on a thread pool (zlib releases the GIL while it
compresses), started as soon as the array exists; :meth:`Deflated.write` then creates the dataset with
those filters declared and stores the finished chunks as they are (``write_direct_chunk``). A reader
meets an ordinary chunked dataset and decompresses it through HDF5's own filter pipeline.

Chunks: the first axis in runs of at most :data:`CHUNK_BYTES`, every other axis one element wide (a
channel's series is one run of chunks, as h5py's own chunk guess gives for these tables); edge chunks
are stored padded to the full chunk with zeros, as HDF5 stores them. Empty and 0-d arrays, and dtypes
the shuffle does not apply to byte-wise (strings, objects), go through h5py's filters unchanged.
"""

import zlib

import numpy as np

CHUNK_BYTES = 32 * 1024          # upper bound of one chunk, uncompressed


def chunk_shape(shape, itemsize):
    """The chunk shape :class:`Deflated` uses for an array of ``shape`` and ``itemsize``: at most
    :data:`CHUNK_BYTES` along the first axis, one element along every other."""
    rows = max(1, min(int(shape[0]), CHUNK_BYTES // max(1, int(itemsize))))
    return (rows,) + (1,) * (len(shape) - 1)


def _chunk_origins(shape, chunks):
    grids = np.meshgrid(*[np.arange(0, n, c) for n, c in zip(shape, chunks)], indexing="ij")
    return [tuple(int(g.flat[i]) for g in grids) for i in range(grids[0].size)]


def deflate_chunk(a, origin, chunks, level=1, shuffle=True):
    """The stored bytes of the chunk of ``a`` at ``origin``: padded to ``chunks`` with zeros, the byte
    shuffle (byte k of every element, then byte k + 1 ...) when ``shuffle``, then deflate at ``level``
    in the zlib format of HDF5's deflate filter."""
    block = a[tuple(slice(o, o + c) for o, c in zip(origin, chunks))]
    if block.shape != tuple(chunks):
        full = np.zeros(chunks, dtype=a.dtype)
        full[tuple(slice(0, n) for n in block.shape)] = block
        block = full
    raw = np.ascontiguousarray(block).view(np.uint8)
    size = a.dtype.itemsize
    if shuffle and size > 1:
        raw = raw.reshape(-1, size).T
    return zlib.compress(np.ascontiguousarray(raw).data, level)


class Deflated:
    """``a`` compressed chunk by chunk on ``pool`` (a ``concurrent.futures`` executor; None: here, now)
    with the filters of ``create_dataset(..., compression="gzip", compression_opts=level,
    shuffle=shuffle)``; :meth:`write` stores it. The array is not copied: it must not change until
    :meth:`write` returns."""

    def __init__(self, a, pool=None, level=1, shuffle=True):
        self.array = np.asarray(a)
        self.level, self.shuffle = int(level), bool(shuffle)
        direct = self.array.ndim > 0 and self.array.size > 0 and self.array.dtype.kind in "biufc"
        self.chunks = chunk_shape(self.array.shape, self.array.dtype.itemsize) if direct else None
        self._parts = []
        if self.chunks is not None:
            for origin in _chunk_origins(self.array.shape, self.chunks):
                args = (self.array, origin, self.chunks, self.level, self.shuffle)
                self._parts.append((origin, pool.submit(deflate_chunk, *args) if pool is not None
                                    else deflate_chunk(*args)))

    def write(self, group, name):
        """The dataset ``name`` in ``group`` (h5py): the chunks compressed so far are waited for and
        written as stored; returns it."""
        a = self.array
        kw = {"compression": "gzip", "compression_opts": self.level}
        if self.shuffle:
            kw["shuffle"] = True
        if self.chunks is None:
            return group.create_dataset(name, data=a, **(kw if a.ndim and a.size else {}))
        ds = group.create_dataset(name, shape=a.shape, dtype=a.dtype, chunks=self.chunks, **kw)
        for origin, part in self._parts:
            ds.id.write_direct_chunk(origin, part.result() if hasattr(part, "result") else part)
        self._parts = []
        return ds


__all__ = ["CHUNK_BYTES", "Deflated", "chunk_shape", "deflate_chunk"]
