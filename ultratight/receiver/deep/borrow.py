"""Borrowed arrays: a compiled function's arrays without their reference count, for the epoch chain.

numba counts a reference up on every array that enters a compiled function (argument, record
field, view) and down when it leaves — an atomic increment or decrement of the array's memory
record, about twenty cycles each — and LLVM removes only the pairs it can prove redundant. The
per-channel epoch chain (:mod:`ultratight.receiver.deep.epochs`) passes a few hundred array
references per channel and epoch through its stages: those counts were about a sixth of an
engine's time (docs/ultratight.md, "Where an engine's time goes").

:func:`borrowed` returns an array, or a record (named tuple) of arrays and scalars, whose arrays
share the data, shape and strides but have no memory record: numba's counting functions return at
once for them. Valid only while the arrays it was made from are alive — the caller's own
references — and never to be stored or returned beyond that: :func:`~ultratight.receiver.deep.epochs.
epoch_channel` borrows its arguments, which its caller holds until it returns.
"""

from numba import types
from numba.core import cgutils
from numba.extending import intrinsic


def _borrow_array(context, builder, aryty, value):
    src = context.make_array(aryty)(context, builder, value)
    dst = context.make_array(aryty)(context, builder)
    for name in ("nitems", "itemsize", "data", "shape", "strides"):
        setattr(dst, name, getattr(src, name))
    dst.meminfo = cgutils.get_null_value(dst.meminfo.type)
    dst.parent = cgutils.get_null_value(dst.parent.type)
    return dst._getvalue()


@intrinsic
def borrowed(typingctx, x):
    """``x`` (an array, or a named tuple or tuple of arrays and other values) with every array
    borrowed (module docstring); other members as they are."""
    if isinstance(x, types.Array):
        def codegen(context, builder, sig, args):
            return _borrow_array(context, builder, sig.args[0], args[0])
        return x(x), codegen
    if isinstance(x, types.BaseTuple):
        def codegen(context, builder, sig, args):
            out = args[0]
            for i, ty in enumerate(sig.args[0].types):
                v = builder.extract_value(args[0], i)
                if isinstance(ty, types.Array):
                    v = _borrow_array(context, builder, ty, v)
                else:               # the result is a new reference: its other members counted as such
                    context.nrt.incref(builder, ty, v)
                out = builder.insert_value(out, v, i)
            return out
        return x(x), codegen
    return None
