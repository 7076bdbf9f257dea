"""The generator's IF handed to a receiver block by block, without an IF file.

:class:`GeneratedIf` has the interface of :class:`ultratight.signals.recording.iffile.IfSource` that the
receiver reads through (``read``, ``release``, ``close``, ``blocks``; ``fs_hz``, ``if_hz``,
``is_complex``, ``n_samples``, ``duration_s``, ``start_week``, ``start_tow_s``, ``meta``, ``path``)
and yields the samples :func:`ultratight.signals.synth.generator.generate` writes for the same resolved
configuration and seed, bit for bit: the same blocks (:meth:`Generation.blocks
<ultratight.signals.synth.generator.Generation.blocks>`, one noise generator drawn in block order from the
seed's noise sequence, the front-end filter state carried from block to block), encoded in the
file's sample format by the writer's encoder and decoded as :func:`ultratight.signals.recording.iffile.open_if`
decodes the file (``SampleFormat.decode``, :func:`ultratight.signals.recording.iffile.orient`).

Production: a worker thread runs the generator up to ``ahead`` blocks (of 100 ms) ahead of the
reader, so on a machine with a free core the next block is synthesised while the receiver tracks
the current one (the synthesis kernels release the GIL; the thread uses one numba thread). Where
numba's threading layer is ``workqueue`` (not safe for parallel kernels launched from two threads)
the blocks are produced in the reading thread instead.

Reading: any ``read(start, count)`` is correct. The source holds the encoded samples from
``keep_s`` before the start of the latest read (and what :meth:`release` has not dropped) to the end
of the blocks produced; the receiver's block stream reads forward, so memory stays at a few blocks
whatever the run's length. A read before the held window restarts the generation from its first
block (counted in :attr:`GeneratedIf.restarts`): correct, only slower.
"""

import math
import queue
import threading
from collections import deque

import numba
import numpy as np

from ultratight import __version__
from ultratight.errors import ConfigError
from ultratight.signals.synth.generator import Generation
from ultratight.signals.synth.synthesis import COS_LUT, N_EXT, _synth_real
from ultratight.signals.recording.iffile import iter_blocks, orient

_END = object()


def threads_safe():
    """True when numba's threading layer accepts parallel kernels launched from two threads at once
    (``omp``, ``tbb``); False for ``workqueue``. Starts the layer (an empty generator kernel call)
    when no parallel kernel has run yet."""
    try:
        layer = numba.threading_layer()
    except ValueError:
        _synth_real(np.zeros(0, np.float32), 1, 0, np.zeros((0, N_EXT), np.float32), np.zeros((0, 0, 6)),
                    np.zeros((0, 0), np.float32), np.zeros((0, 0, 3), np.float32), COS_LUT)
        layer = numba.threading_layer()
    return layer != "workqueue"


class GeneratedIf:
    """The IF of ``generate(cfg, ..., seed=seed)`` as a streaming source (module docstring).

    ``ahead``: blocks produced ahead of the reader (worker thread); ``threaded``: False produces in
    the reading thread; ``keep_s``: seconds of samples held before the latest read's start."""

    def __init__(self, cfg, seed=None, ahead=2, threaded=True, keep_s=0.25):
        gen = Generation(cfg, seed)
        self._gen = gen
        fe, spec = gen.fe, gen.spec
        self.spec = spec
        self.fmt = spec.name
        self.fs_hz = float(fe.fs_hz)
        self.is_complex = bool(spec.is_complex)
        # the sidecar generate() writes: iq_conj false, inversion = the front end's
        self._conj = bool(fe.inversion and self.is_complex)
        self._alt_sign = bool(fe.inversion and not self.is_complex)
        self.file_if_hz = float(fe.if_hz)
        self.if_hz = self.fs_hz / 2.0 - self.file_if_hz if self._alt_sign else self.file_if_hz
        self.n_samples = int(gen.n_total)
        self.duration_s = self.n_samples / self.fs_hz
        self.start_week = gen.week
        self.start_tow_s = gen.tow0
        self.packing = spec.layout(None)
        self.prns = [int(p) for p in gen.plan.prns]
        self.meta = {"format": spec.name, "fs_hz": self.fs_hz, "if_hz": self.file_if_hz,
                     "is_complex": self.is_complex, "iq_conj": False, "inversion": bool(fe.inversion),
                     "start_week": gen.week, "start_tow_s": gen.tow0, "bits": fe.bits,
                     "n_samples": self.n_samples, "version": __version__, "streamed": True,
                     **gen.sidecar_extra()}
        self.path = f"<IF of scenario {cfg.get('name', '?')!r} seed {gen.seed}, generated in memory>"
        self.warnings = []
        self.restarts = 0
        self._exact = fe.bits != 0
        self._dtype = np.dtype(spec.dtype)
        if spec.packed:
            # the held window starts on a word boundary of the packed layout
            per = self.packing.per_word
            self._align = per // math.gcd(per, spec.comps)
        else:
            self._align = 1
        self._keep = max(0, int(round(float(keep_s) * self.fs_hz)))
        self._ahead = max(1, int(ahead))
        self._threaded = bool(threaded) and threads_safe()
        self._thread = None
        self._stop = None
        self._q = None
        self._it = None
        self._start()

    # ------------------------------------------------------------------ production
    def _chunks(self, stop=None, rows_to=None):
        """The encoded bytes of the file, block by block (uint8 arrays), then the encoder's tail.
        ``rows_to``: the truth rows of every block are handed to its ``append`` (a
        :class:`ultratight.signals.synth.generator.GenerationFiles`) before the block is yielded."""
        enc = self.spec.encoder()
        blocks = self._gen.blocks(samples=True, truth=rows_to is not None)
        try:
            for _j0, _n, y, rows in blocks:
                if stop is not None and stop.is_set():
                    return
                if rows_to is not None:
                    rows_to.append(rows)
                if self.is_complex:
                    comps = np.ascontiguousarray(y, dtype=np.complex64).view(np.float32)
                else:
                    comps = np.ascontiguousarray(y, dtype=np.float32).reshape(-1)
                yield np.frombuffer(enc.encode(comps, self._exact), dtype=np.uint8)
            tail = enc.flush()
            if tail:
                yield np.frombuffer(tail, dtype=np.uint8)
        finally:
            blocks.close()

    def _worker(self, q, stop):
        try:
            numba.set_num_threads(1)            # the generator takes one core beside the receiver
        except ValueError:                      # pragma: no cover - a pool without threads
            pass
        item = _END
        try:
            for chunk in self._chunks(stop):
                if not self._put(q, stop, chunk):
                    return
        except BaseException as exc:            # handed to the reader, raised there
            item = exc
        self._put(q, stop, item)

    @staticmethod
    def _put(q, stop, item):
        while not stop.is_set():
            try:
                q.put(item, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def _start(self):
        self._held = HeldBytes()                     # encoded samples from sample _s0
        self._s0 = 0
        self._done = False
        if self._threaded:
            self._stop = threading.Event()
            self._q = queue.Queue(maxsize=self._ahead)
            self._thread = threading.Thread(target=self._worker, args=(self._q, self._stop), daemon=True,
                                            name="ultratight-if-generator")
            self._thread.start()
        else:
            self._it = self._chunks()

    def _halt(self):
        if self._thread is not None:
            self._stop.set()
            while True:                     # unblock a worker waiting on a full queue
                try:
                    self._q.get_nowait()
                except queue.Empty:
                    break
            self._thread.join()
            self._thread = None
        if self._it is not None:
            self._it.close()
            self._it = None

    def _next_chunk(self):
        if self._thread is not None:
            item = self._q.get()
            if item is _END:
                self._thread.join()
                self._thread = None
                return None
            if isinstance(item, BaseException):
                self._thread.join()
                self._thread = None
                raise item
            return item
        if self._it is None:
            return None
        try:
            return next(self._it)
        except StopIteration:
            self._it = None
            return None

    def _held_end(self):
        """End (sample index) of the samples decodable from the held bytes."""
        return self._s0 + self.spec.count(self._held.size, self.packing)

    def _produce_to(self, end):
        while not self._done and self._held_end() < end:
            chunk = self._next_chunk()
            if chunk is None:
                self._done = True
                break
            self._held.append(chunk)

    def _drop_before(self, sample):
        """Forget the held samples before ``sample`` (rounded down to the window alignment); bytes dropped."""
        s = min(int(sample), self._held_end())
        s -= s % self._align
        if s <= self._s0:
            return 0
        nb = self.spec.nbytes(s - self._s0, self.packing)
        self._chunks_done(self._held.drop(nb))
        self._s0 = s
        return nb

    def _chunks_done(self, n):
        """``n`` more of the chunks :meth:`_next_chunk` returned are no longer held (a ring consumer tells
        its producer then)."""

    # ------------------------------------------------------------------ the IfSource interface
    def read(self, start, count):
        """Samples ``[start, start+count)`` (clipped to the end) as complex64 / float32."""
        start = int(start)
        if start < 0:
            raise ValueError("start must be >= 0")
        count = max(0, min(int(count), self.n_samples - start))
        if start < self._s0:
            # samples no longer held: generate again from the first block
            self._halt()
            self.restarts += 1
            self._start()
        end = start + count
        self._produce_to(end)
        if self._held_end() < end:
            raise ConfigError(f"{self.path}: the generator ended at sample {self._held_end()}, before {end}")
        # the bytes from the aligned sample at or before ``start`` to the words holding ``end``
        s_a = start - (start - self._s0) % self._align
        b0 = self.spec.nbytes(s_a - self._s0, self.packing)
        n_need = -(-(end - s_a) // self._align) * self._align
        b1 = min(self._held.size, b0 + self.spec.nbytes(n_need, self.packing))
        parts = self._held.parts(b0, b1)
        if len(parts) > 1 and self.packing is None:
            # samples in two chunks (the kept ones and the new block): decoded from both, not joined first
            raw = self.spec.decode_parts([p.view(self._dtype) for p in parts], start - s_a, count)
        else:
            store = (parts[0] if len(parts) == 1 else self._held.span(b0, b1)).view(self._dtype)
            raw = self.spec.decode(store, start - s_a, count, self.packing)
        x = orient(raw, start, self.is_complex, False, self._conj, self._alt_sign)
        self._drop_before(start - self._keep)
        return x

    def blocks(self, block_len, start=0, stop=None):
        """Iterate ``(start_index, samples)`` over consecutive blocks of ``block_len`` samples."""
        return iter_blocks(self, block_len, start, stop)

    def release(self, upto_sample):
        """Forget the samples before ``upto_sample`` (they stay readable: a later read of them generates
        again from the start). Returns the bytes freed."""
        return self._drop_before(upto_sample)

    def held_bytes(self):
        """Bytes of encoded samples held now (memory check)."""
        return int(self._held.size)

    def close(self):
        self._halt()
        self._held = HeldBytes()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def __del__(self):
        try:
            self._halt()
        except Exception:  # noqa: BLE001 - interpreter shutdown
            pass

    def __repr__(self):
        return (f"GeneratedIf({self.path!r}, fmt={self.fmt!r}, fs_hz={self.fs_hz}, if_hz={self.if_hz}, "
                f"n_samples={self.n_samples})")


class HeldBytes:
    """A stream's encoded bytes held as the chunks they arrived in: appending a block and dropping the
    bytes before a point copy nothing (the held window was one array before, concatenated again with
    every 100 ms block and copied on every drop: a tenth of a scenario worker's time went to moving
    those bytes), and a read copies only the bytes it spans when they lie in two chunks."""

    def __init__(self):
        self._chunks = deque()
        self.size = 0

    def append(self, chunk):
        # an empty chunk is held too (and let go with the bytes before it), so that every chunk appended
        # is counted once by drop()
        self._chunks.append(chunk)
        self.size += int(chunk.size)

    def drop(self, nb):
        """Forget the first ``nb`` bytes; returns how many chunks were let go whole."""
        nb = min(int(nb), self.size)
        self.size -= nb
        gone = 0
        while nb:
            first = self._chunks[0]
            if first.size <= nb:
                self._chunks.popleft()
                nb -= first.size
                gone += 1
            else:
                self._chunks[0] = first[nb:]
                nb = 0
        return gone

    def count(self):
        """The chunks held (whole or in part)."""
        return len(self._chunks)

    def own(self):
        """Hold copies of the chunks instead of the arrays appended (views into memory their owner reuses)."""
        self._chunks = deque(c.copy() for c in self._chunks)

    def parts(self, b0, b1):
        """Bytes ``[b0, b1)`` of those held as views into the chunks they lie in (uint8), in order."""
        parts, at = [], 0
        for c in self._chunks:
            lo, hi = max(b0 - at, 0), min(b1 - at, c.size)
            if lo < hi:
                parts.append(c[lo:hi])
            at += c.size
            if at >= b1:
                break
        return parts

    def span(self, b0, b1):
        """Bytes ``[b0, b1)`` of those held (uint8; a view into one chunk, or a copy across chunks)."""
        parts = self.parts(b0, b1)
        if len(parts) == 1:
            return parts[0]
        return np.concatenate(parts) if parts else np.zeros(0, dtype=np.uint8)


__all__ = ["GeneratedIf", "HeldBytes", "threads_safe"]
