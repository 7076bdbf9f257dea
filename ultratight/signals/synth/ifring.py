"""One generated IF shared by several receivers in other processes: a ring of blocks in shared memory.

Streamed scenario runs (:mod:`ultratight.signals.synth.ifstream`) let every method synthesise its own copy
of the IF — the same samples, generated once per method. :class:`IfRing` generates them once: a
producer thread in the parent process runs the generator (:class:`~ultratight.signals.synth.ifstream.
GeneratedIf`'s encoded blocks, so the bytes are those of the IF file) into ``slots`` shared-memory
slots of one block (100 ms) each, and every consumer — a :class:`RingIf` in a worker process, with
the interface of the file source — reads the blocks in order, in place: a consumer holds the slots of
the blocks it still needs (its kept samples and the read in progress) rather than copies of them, and
copies them out only if it would otherwise hold all but one slot. A slot is written again only when
every consumer has let its block go, so the fastest consumer waits for the slowest one (at most
``slots`` blocks ahead) and memory stays at ``slots`` blocks whatever the run's length. The
consumers must therefore run at the same time (one worker process each).

Control (an int64 array in a second shared-memory segment): ``[produced, total, abort, n_cons,
consumed_0 … consumed_{n-1}, length_0 … length_{slots-1}]``; ``consumed_i``: the blocks consumer
``i`` has let go. ``total`` is the block count once the producer has finished (-1 before); ``abort``
is set by the parent when the run fails (a consumer's exception, a signal) and by a consumer whose
read cannot be served; waiting parties poll it. A consumer that closes (its method done, or failed)
marks itself as having taken every block, so the producer never waits for it.
"""

import threading
import time
import uuid
from multiprocessing import shared_memory

import numpy as np

from ultratight.errors import ConfigError
from ultratight.signals.synth.generator import BLOCK_INTERVALS
from ultratight.signals.synth.ifstream import GeneratedIf, HeldBytes

_PRODUCED, _TOTAL, _ABORT, _NCONS = 0, 1, 2, 3
_DONE = np.iinfo(np.int64).max        # "taken every block": a closed consumer
_POLL_S = 0.0005                      # first wait of a poll; doubled up to _POLL_MAX_S while nothing changes
_POLL_MAX_S = 0.008


def _pause(waited):
    """Sleep once in a poll loop that has slept ``waited`` times; returns ``waited + 1``. The pause
    doubles from :data:`_POLL_S` to :data:`_POLL_MAX_S`: a party that waits for a whole block (tens of
    ms while the engines and the generator share the cores) wakes a few times instead of every 0.5 ms
    (each wake costs CPU the engines need), while a short wait still ends within a millisecond."""
    time.sleep(min(_POLL_MAX_S, _POLL_S * (1 << min(waited, 8))))
    return waited + 1


def _segment_name(tag):
    return f"ut-{tag}-{uuid.uuid4().hex[:12]}"


class IfRing:
    """The producer side (module docstring): ``IfRing(cfg, seed, n_consumers)``, then :meth:`start`;
    :attr:`name` identifies the ring to :class:`RingIf`; :meth:`close` stops the producer and frees the
    shared memory (also after a failure: the consumers then stop with an error)."""

    def __init__(self, cfg, seed, n_consumers, slots=8):
        if int(n_consumers) < 1 or int(slots) < 2:
            raise ConfigError(f"IF ring: need >= 1 consumer and >= 2 slots, got {n_consumers}, {slots}")
        self._src = GeneratedIf(cfg, seed, threaded=False)
        self.generation = self._src._gen
        self.files = None
        self.n_consumers = int(n_consumers)
        self.slots = int(slots)
        L = self._src._gen.plan.L
        self.slot_bytes = int(self._src.spec.nbytes(BLOCK_INTERVALS * L, self._src.packing)) + 64
        self.name = _segment_name("if")
        n_ctl = 4 + self.n_consumers + self.slots
        self._data = shared_memory.SharedMemory(name=self.name + "-d", create=True, size=self.slots * self.slot_bytes)
        try:
            self._ctl_shm = shared_memory.SharedMemory(name=self.name + "-c", create=True, size=8 * n_ctl)
        except BaseException:
            self._data.close()
            self._data.unlink()
            raise
        self._ctl = np.ndarray((n_ctl,), dtype=np.int64, buffer=self._ctl_shm.buf)
        self._ctl[:] = 0
        self._ctl[_TOTAL] = -1
        self._ctl[_NCONS] = self.n_consumers
        self._buf = np.ndarray((self.slots, self.slot_bytes), dtype=np.uint8, buffer=self._data.buf)
        self._thread = None
        self.error = None

    def write_files(self, files):
        """Also write the generation's truth while producing (``files``: a :class:`ultratight.signals.synth.
        generator.GenerationFiles` of :attr:`generation`): every block's rows go to it before the block is
        published, and it is finished (closed, not committed) after the last; :meth:`wait` waits for
        that. Before :meth:`start`."""
        self.files = files
        return self

    def start(self):
        self._thread = threading.Thread(target=self._produce, name="ultratight-if-ring", daemon=True)
        self._thread.start()
        return self

    def _produce(self):
        ctl, n = self._ctl, self.n_consumers
        k = 0
        try:
            for chunk in self._src._chunks(rows_to=self.files):
                if chunk.size > self.slot_bytes:          # pragma: no cover - sized from the format
                    raise ConfigError(f"IF ring: block of {chunk.size} bytes exceeds the slot ({self.slot_bytes})")
                waited = 0
                while k - int(ctl[4:4 + n].min()) >= self.slots:
                    if ctl[_ABORT]:
                        return
                    waited = _pause(waited)
                if ctl[_ABORT]:
                    return
                s = k % self.slots
                self._buf[s, :chunk.size] = chunk
                ctl[4 + n + s] = chunk.size
                k += 1
                ctl[_PRODUCED] = k
            ctl[_TOTAL] = k
            if self.files is not None:
                self.files.finish()
        except BaseException as exc:      # the consumers stop on the abort flag; the parent re-raises
            self.error = exc
            ctl[_ABORT] = 1

    def wait(self, quiet=False):
        """Wait for the producer to end (its blocks all taken into the ring, the truth finished); raises
        its error, if it had one (``quiet``: kept for :meth:`close`)."""
        if self._thread is not None:
            self._thread.join()
        if self.error is not None and not quiet:
            err, self.error = self.error, None
            raise err

    def abort(self):
        """Make every waiting party stop (a consumer's read then raises)."""
        self._ctl[_ABORT] = 1

    def close(self):
        """Stop the producer (abort if it is still running) and free the shared memory. Raises the
        producer's own error, if it had one."""
        if self._thread is not None:
            if self._thread.is_alive():
                self.abort()
            self._thread.join()
            self._thread = None
        self._buf = None
        self._ctl = None
        self._src.close()
        for shm in (self._data, self._ctl_shm):
            try:
                shm.close()
                shm.unlink()
            except FileNotFoundError:       # pragma: no cover - already freed
                pass
        if self.error is not None:
            err, self.error = self.error, None
            raise err

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.close()
        return False


class RingIf(GeneratedIf):
    """The consumer side: the IF of ``cfg``/``seed`` read from the ring ``name`` as consumer
    ``index`` (the interface of :class:`~ultratight.signals.synth.ifstream.GeneratedIf`; reads go forward
    only — a read before the held window raises ConfigError, as the ring has moved on)."""

    def __init__(self, cfg, seed, name, index, keep_s=0.25):
        self._ring_name = str(name)
        self._index = int(index)
        self._data = self._ctl_shm = None
        self._opened = False
        super().__init__(cfg, seed, threaded=False, keep_s=keep_s)
        self.path = f"<IF of scenario {cfg.get('name', '?')!r} seed {self._gen.seed}, shared by the run's methods>"

    # GeneratedIf's production, replaced by the ring
    def _start(self):
        where = f"<IF ring {self._ring_name}>"
        if self._opened:
            raise ConfigError(f"{where}: the shared IF cannot be read again from its start")
        self._opened = True
        self._held = HeldBytes()
        self._s0 = 0
        self._done = False
        self._k = 0
        self._acked = 0      # chunks let go (the count the producer reads)
        self._copied = 0     # held chunks that are copies (already let go)
        try:
            # worker processes spawned by the producer's process share its resource tracker, where
            # the segments are registered once; the producer unlinks them (IfRing.close)
            self._data = shared_memory.SharedMemory(name=self._ring_name + "-d")
            self._ctl_shm = shared_memory.SharedMemory(name=self._ring_name + "-c")
        except FileNotFoundError:
            raise ConfigError(f"{where}: the IF ring is gone (its run stopped)") from None
        n_ctl = self._ctl_shm.size // 8
        ctl = np.ndarray((n_ctl,), dtype=np.int64, buffer=self._ctl_shm.buf)
        self._n = int(ctl[_NCONS])
        if not 0 <= self._index < self._n:
            del ctl
            self._halt()
            raise ConfigError(f"{where}: consumer {self._index} of a ring of {self._n}")
        self._ctl = ctl
        self._slots = n_ctl - 4 - self._n
        self._slot_bytes = self._data.size // self._slots
        self._ring = np.ndarray((self._slots, self._slot_bytes), dtype=np.uint8, buffer=self._data.buf)

    def _next_chunk(self):
        ctl, k = self._ctl, self._k
        # chunks are the slots themselves, not copies: the producer reuses a slot only once this consumer
        # has let its chunk go (_chunks_done); one that would hold all but one slot copies what it holds
        # first, so that the producer always has a slot for the next chunk
        if k - self._acked >= self._slots - 1:
            self._held.own()
            self._copied = self._held.count()     # the oldest held chunks, let go now (copies)
            self._ack(k)
        waited = 0
        while int(ctl[_PRODUCED]) <= k:
            total = int(ctl[_TOTAL])
            if 0 <= total <= k:
                return None
            if ctl[_ABORT]:
                raise ConfigError(f"{self.path}: the IF ring stopped (another method of the run failed, or the "
                                  f"generator did)")
            waited = _pause(waited)
        s = k % self._slots
        chunk = self._ring[s, :int(ctl[4 + self._n + s])]
        self._k = k + 1
        return chunk

    def _chunks_done(self, n):
        copied = min(int(n), self._copied)      # copies: let go when they were made
        self._copied -= copied
        if n - copied:
            self._ack(self._acked + n - copied)

    def _ack(self, k):
        """The blocks before ``k`` let go: the producer may reuse their slots."""
        self._acked = int(k)
        if self._ctl is not None:
            self._ctl[4 + self._index] = self._acked

    def _halt(self):
        ctl = getattr(self, "_ctl", None)
        if ctl is not None:
            ctl[4 + self._index] = _DONE       # never wait for a consumer that stopped reading
            self._ctl = None
            self._ring = None
        self._held = HeldBytes()               # views into the ring's slots: let go before it is closed
        for shm in (self._data, self._ctl_shm):
            if shm is not None:
                try:
                    shm.close()
                except BufferError:            # a view still referenced (an error's traceback): the
                    pass                       # mapping closes when the last one goes
        self._data = self._ctl_shm = None


__all__ = ["IfRing", "RingIf"]
