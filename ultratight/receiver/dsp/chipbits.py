"""Code chips as sign bits, for the correlator's three-tap kernel (:func:`ultratight.receiver.dsp.correlator._epl_block`).

A +-1 chip table in float32 holds each chip's value in the sign bit of its entry.  The kernel reads
the chips of a stretch of samples from one 64-bit *window* (bit ``c`` = sign of chip ``j0 + c``,
:func:`code_window`) by shifting it, instead of one table look-up per sample and tap: look-ups at
per-lane indices are scalar loads and inserts when LLVM vectorises, shifts are one vector
instruction for eight samples.  The 32-bit helpers below are LLVM intrinsics because numba widens
integer arithmetic to 64 bits, which would halve the vector width of the shifts and compares.
"""

import numpy as np
from llvmlite import ir
from numba import njit
from numba.core import types
from numba.extending import intrinsic

_I32 = ir.IntType(32)
_I64 = ir.IntType(64)
_SIGN = 0x80000000
_ONE_F32 = 0x3F800000          # bit pattern of float32 1.0


def _as_i32(builder, v):
    return builder.trunc(v, _I32) if v.type.width > 32 else v


def _sign_bit_to_chip(builder, v):
    """float32 +1 or -1 with the sign of bit 31 of the i32 ``v``."""
    v = builder.and_(v, ir.Constant(_I32, _SIGN))
    return builder.bitcast(builder.or_(v, ir.Constant(_I32, _ONE_F32)), ir.FloatType())


@intrinsic
def signs8(typingctx, arr, j):
    """Sign bits of the float32 entries ``arr[j .. j+7]`` (C-contiguous, in range) as an int64:
    bit ``i`` set when entry ``j + i`` is negative (a compare and a move-mask on x86)."""
    if not (isinstance(arr, types.Array) and arr.dtype == types.float32 and isinstance(j, types.Integer)):
        return None

    def codegen(context, builder, sig, args):
        a = context.make_array(sig.args[0])(context, builder, args[0])
        vec = ir.VectorType(_I32, 8)
        ptr = builder.bitcast(builder.gep(a.data, [args[1]]), vec.as_pointer())
        neg = builder.icmp_signed("<", builder.load(ptr, align=4), ir.Constant(vec, None))
        return builder.zext(builder.bitcast(neg, ir.IntType(8)), _I64)

    return types.int64(arr, j), codegen


@intrinsic
def chip_at(typingctx, v, s, lo, thr):
    """The chip ``+-1.0`` (float32) whose sign is bit 31 of ``v << (s - (lo > thr))``, all in
    32-bit signed arithmetic (``v``: window bits, ``s``: 31 - the bit wanted, ``lo > thr``: the
    carry of the tap's fractional code phase, see :func:`ultratight.receiver.dsp.correlator._epl_block`)."""
    if not all(isinstance(a, types.Integer) for a in (v, s, lo, thr)):
        return None

    def codegen(context, builder, sig, args):
        v_, s_, lo_, thr_ = (_as_i32(builder, a) for a in args)
        carry = builder.zext(builder.icmp_signed(">", lo_, thr_), _I32)
        return _sign_bit_to_chip(builder, builder.shl(v_, builder.sub(s_, carry)))

    return types.float32(v, s, lo, thr), codegen


@njit(cache=True)
def code_window(code_ext, j0):
    """64-bit window of a +-1 chip table: bit ``c`` is the sign of ``code_ext[j0 + c]`` (``c < 64``;
    chips beyond the table's end read as +1)."""
    if j0 + 64 <= code_ext.shape[0]:
        w = signs8(code_ext, j0)
        for g in range(1, 8):
            w |= signs8(code_ext, j0 + 8 * g) << (8 * g)
        return np.uint64(w)
    w = np.uint64(0)
    for c in range(code_ext.shape[0] - j0):
        w |= np.uint64(code_ext[j0 + c] < 0) << np.uint64(c)
    return w


@njit(cache=True)
def unit_chips(code_ext):
    """True when every entry of the float32 table is exactly +1 or -1 (what the windows assume)."""
    bits = code_ext.view(np.uint32)
    bad = np.uint32(0)
    for j in range(bits.shape[0]):
        bad |= (bits[j] & np.uint32(0x7FFFFFFF)) ^ np.uint32(_ONE_F32)
    return bad == 0
