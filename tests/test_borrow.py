"""ultratight.receiver.deep.borrow: borrowed arrays share the data and layout of their arrays, carry no
memory record (numba's reference counts skip them) and leave the originals' counts as they were."""

import sys
from collections import namedtuple

import numpy as np
from numba import njit, types
from numba.extending import intrinsic

from ultratight.receiver.deep.borrow import borrowed

Rec = namedtuple("Rec", "a b scale n")


@intrinsic
def _meminfo_is_null(typingctx, arr):
    if not isinstance(arr, types.Array):
        return None

    def codegen(context, builder, sig, args):
        ary = context.make_array(sig.args[0])(context, builder, args[0])
        return builder.icmp_unsigned("==", builder.ptrtoint(ary.meminfo, context.get_value_type(types.intp)),
                                     context.get_constant(types.intp, 0))
    return types.boolean(arr), codegen


@njit
def _write_through(rec, k):
    r = borrowed(rec)
    r.a[k] = r.b[k] * r.scale + r.n
    return _meminfo_is_null(r.a), _meminfo_is_null(r.b), _meminfo_is_null(rec.a), r.a.shape[0], r.b.strides[0]


@njit
def _row_view_sum(x):
    b = borrowed(x)
    s = 0.0
    for i in range(b.shape[0]):
        row = b[i]                   # a view of a borrowed array is borrowed as well
        for j in range(row.shape[0]):
            s += row[j]
    return s, _meminfo_is_null(b[0])


def test_borrowed_record_shares_data_and_layout_without_memory_record():
    a = np.zeros(5)
    b = np.arange(10.0)[::2]          # strided
    rec = Rec(a, b, 3.0, 2)
    nulls_a, nulls_b, orig_null, n, stride = _write_through(rec, 3)
    assert a[3] == 6.0 * 3.0 + 2.0    # written through the borrowed array into the caller's
    assert (nulls_a, nulls_b, orig_null) == (True, True, False)
    assert (n, stride) == (5, b.strides[0])


def test_borrowed_views_and_the_originals_reference_counts():
    x = np.arange(12.0).reshape(3, 4)[:, ::2]
    before = sys.getrefcount(x)
    for _ in range(1000):
        s, null = _row_view_sum(x)
    assert s == x.sum() and null
    assert sys.getrefcount(x) == before
