"""The engine's per-channel epoch chain compiled ahead, in a second process, on a first run.

numba compiles a kernel when it is first called, and a caller's callees with it, one after the
other in one process: the engine's first compilation is one chain of about 80 s — the set-up
kernels its Python side calls, then :func:`~ultratight.receiver.deep.epochs.run_epochs` with the
per-channel epoch (:func:`~ultratight.receiver.deep.epochs.epoch_channel`, the tracking banks' kernels
inside: about 30 s of it), then the post-processing kernels. A compilation looks for the kernel in
numba's on-disk cache first, also when another process wrote it there. So while one worker compiles
the chain from its start (:func:`ultratight.receiver.cli.workers.warm_up`), another compiles the
chain's late, large parts (:func:`kernels`) from their declared signatures; the first then loads them
from the cache when it gets there. The signatures are those the engine calls the kernels with (the
records of :mod:`ultratight.receiver.deep.epochs`, :data:`RECORD_FIELDS`); a test checks them against
a run's. A declared signature the engine no longer uses costs the second process's time only.
"""

import time

import numpy as np
import numba

from ultratight.receiver.deep import epochs as E
from ultratight.receiver.dsp.burst import Burst

# field kinds of the engine's records as the engine fills them: "f8", "i8", "b1" scalars, "f4:2"
# a C-contiguous float32 array of two dimensions (numba.typeof of a record gives its numba type)
RECORD_FIELDS = {
    E.If: "f4:1 b1 i8 i8 i8 i8 f8:1",
    E.Corr: "f4:2 i8 b1:1 i8:1 f8:1 f8:1 f8:1 f8:1 f8 f8:1 i8 b1 f8:2 i8:1 i8:1 f8:1 f8:1 f8:1",
    E.Wipe: "i1:2 i8:1 i8:1 f8:1 i8 i1:1 b1:1 i8:1 f8:1 f8:1 f8:1 f8:1 i8:1 i1:1 i1:2 f8:2 f8",
    E.Bank: "i8 i8 f8:1 i8:1 i8 i8 f8:2 f8:2 f8:3 i8 i8 i8:1 f8:2 f8:3 f8:2 f8:1 f8:1 f8:2 f8:2 f8:2 f8:2 f8:1 i8:1",
    E.Outer: "f8:1 f8:2 f8:2 f8:2 i8:1 i8 f8 f8:2 i8 f8 b1",
    E.Window: "f8 f8:2 f8:3 i8:2",
    E.Rec: "f8:2 f8:2 f8:2 f8:2 i1:2 i1:1 i8",
    E.Law: "f8:1 f8:1 f8:1 i8:1 b1:1 f8:1 f8:2 f8:1",
    E.Sig: "f8 f8 f8",
    Burst: "f8:1 f8:1 f8:1 i8 f8:3 f8:1 f8:1 f8:1 f8:1",
}
_SCALARS = {"f8": 0.0, "i8": 0, "b1": False}
_DTYPES = {"f8": np.float64, "f4": np.float32, "i8": np.int64, "i1": np.int8, "b1": np.bool_}


def _example(kind):
    if ":" not in kind:
        return _SCALARS[kind]
    dt, nd = kind.split(":")
    return np.zeros((1,) * int(nd), dtype=_DTYPES[dt])


def record_type(cls):
    """The numba type of the engine's record ``cls`` (:data:`RECORD_FIELDS`)."""
    kinds = RECORD_FIELDS[cls].split()
    if len(kinds) != len(cls._fields):
        raise ValueError(f"{cls.__name__}: {len(kinds)} field kinds declared for {len(cls._fields)} fields")
    return numba.typeof(cls(*(_example(k) for k in kinds)))


def _records():
    return tuple(record_type(cls) for cls in (E.If, E.Corr, E.Wipe, E.Bank, E.Outer, E.Window, E.Rec, E.Law,
                                              E.Sig, Burst))


def kernels():
    """``(kernel, signature)`` pairs compiled ahead, in the order the engine reaches them."""
    from ultratight.chi2 import gamma_map
    from ultratight.ins.error_model import fill_f_matrix
    i8, f8 = numba.int64, numba.float64
    f1, f2, f3, i1 = (numba.typeof(_example(k)) for k in ("f8:1", "f8:2", "f8:3", "i8:1"))
    rec = _records()
    work = (i1, f2, f3, f1)                       # tap_fix, W1, W2, WA (epochs._work_arrays)
    return [(E.epoch_channel, (i8, i8, i8, i8) + rec + work),
            (E._serial_epoch, (i8, i8) + rec + work + (i1,)),
            (fill_f_matrix, (f2, f2, f1, f8, f8, f1, f8, f8)),
            (gamma_map, (i8, f1, f1))]


def compile_ahead():
    """Compile (or load from numba's cache) :func:`kernels`; returns the seconds it took. Errors are
    left to the engine's own compilation to meet and report."""
    t0 = time.perf_counter()
    try:
        for fn, sig in kernels():
            fn.compile(sig)
    except Exception:           # noqa: BLE001 - the worker compiling from the start meets it too
        pass
    return time.perf_counter() - t0
