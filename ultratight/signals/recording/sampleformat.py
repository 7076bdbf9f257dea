"""IF sample formats: how each format stores, decodes and encodes its samples, and the registry.

The formats themselves are listed in :mod:`ultratight.signals.recording.iffile` (its module docstring), which
reads and writes files through the objects defined here; :mod:`ultratight.signals.recording.metadata_check`
and :mod:`ultratight.signals.recording.sigmf_io` look formats up here too.
"""

import numpy as np

from ultratight.errors import ConfigError, FormatError
from ultratight.signals.recording.packing import PackedLayout


class SampleFormat:
    """One IF sample format: how its samples are stored, decoded and encoded.

    ``name``; ``dtype``, the numpy dtype of one stored component (packed formats: of one byte);
    ``is_complex``; ``comps`` (1 or 2 stored components per sample). The reader and the writer
    only call the methods below, so a new format is a new subclass (or instance) plus an entry
    in :data:`FORMATS` (or :data:`READ_ONLY_FORMATS`):

    * ``layout(packing, path)``: the per-file packing layout (None for byte-aligned formats);
    * ``count(size_bytes, layout, path)``: samples held by a file of ``size_bytes``;
    * ``nbytes(n, layout)``: bytes holding the first ``n`` samples (whole words);
    * ``decode(store, start, count, layout)``: float32 components of samples
      ``[start, start + count)`` from the memory-mapped store;
    * ``encoder()``: a streaming encoder (``encode(comps, exact) -> bytes``, ``flush() -> bytes``);
    * ``quantiser_bits``: the front-end quantiser width the format stores (0: float);
      ``check_bits(bits, field)``: ConfigError unless a quantiser width can be stored.
    """

    packed_bits = 0
    writable = True

    def __init__(self, name, dtype, is_complex):
        self.name = name
        self.dtype = dtype
        self.is_complex = bool(is_complex)

    def __repr__(self):
        return f"{type(self).__name__}({self.name!r}, {self.dtype!r}, is_complex={self.is_complex})"

    def __eq__(self, other):
        return type(self) is type(other) and (self.name, self.dtype, self.is_complex, self.packed_bits) == (
            other.name, other.dtype, other.is_complex, other.packed_bits)

    def __hash__(self):
        return hash((type(self).__name__, self.name, self.dtype, self.is_complex))

    @property
    def packed(self):
        return self.packed_bits > 0

    @property
    def packed2(self):
        return self.packed_bits == 2

    @property
    def packed4(self):
        return self.packed_bits == 4

    @property
    def comps(self):
        return 2 if self.is_complex else 1

    @property
    def samples_per_byte(self):
        return None

    @property
    def bytes_per_sample(self):
        return np.dtype(self.dtype).itemsize * self.comps

    @property
    def quantiser_bits(self):
        dt = np.dtype(self.dtype)
        return 0 if dt.kind == "f" else 8 * dt.itemsize

    def check_bits(self, bits, field="frontend"):
        q = self.quantiser_bits
        if q == 8 and bits not in (1, 2, 4, 8):
            raise ConfigError(f"{field}.format {self.name!r} stores 8-bit samples; {field}.bits must be 1, 2, 4 "
                              f"or 8 (got {bits})")
        if q == 16 and bits == 0:
            raise ConfigError(f"{field}.format {self.name!r} stores integers; {field}.bits must not be 0 (float)")

    def layout(self, packing=None, path=""):
        return None

    def count(self, size_bytes, layout=None, path=""):
        bps = self.bytes_per_sample
        if size_bytes % bps:
            raise FormatError(f"{path}: size {size_bytes} bytes is not a whole number of {self.name} samples "
                              f"({bps} bytes each)")
        return size_bytes // bps

    def nbytes(self, n, layout=None):
        return n * self.bytes_per_sample

    def decode(self, store, start, count, layout=None):
        c = self.comps
        return np.asarray(store[start * c:(start + count) * c]).astype(np.float32)

    def decode_parts(self, parts, start, count):
        """:meth:`decode` of the concatenation of ``parts`` (arrays of the stored dtype, whole samples
        each), each converted into its place in the result rather than joined first: the same values."""
        c = self.comps
        out = np.empty(count * c, dtype=np.float32)
        lo, hi = start * c, (start + count) * c
        at = o = 0
        for p in parts:
            a, b = max(lo - at, 0), min(hi - at, p.shape[0])
            if a < b:
                out[o:o + b - a] = p[a:b]
                o += b - a
            at += p.shape[0]
        if o != out.shape[0]:
            raise ValueError(f"decode_parts: {o} of {out.shape[0]} components in the parts given")
        return out

    def encoder(self):
        return _PlainEncoder(np.dtype(self.dtype))


class PackedFormat(SampleFormat):
    """2- or 4-bit samples packed into words in a :class:`ultratight.signals.recording.packing.PackedLayout`."""

    def __init__(self, name, is_complex, bits, writable=True):
        super().__init__(name, "u1", is_complex)
        self.packed_bits = int(bits)
        self.writable = bool(writable)

    @property
    def samples_per_byte(self):
        return 8 // self.packed_bits // self.comps

    @property
    def bytes_per_sample(self):
        return None

    @property
    def quantiser_bits(self):
        return self.packed_bits

    def check_bits(self, bits, field="frontend"):
        if not self.writable:
            raise ConfigError(f"{field}.format {self.name!r} is read only (no writer for "
                              f"{self.packed_bits}-bit packed samples)")
        if bits not in (1, self.packed_bits):
            raise ConfigError(f"{field}.format {self.name!r} stores {self.packed_bits}-bit samples; {field}.bits "
                              f"must be 1 or {self.packed_bits} (got {bits})")

    def layout(self, packing=None, path=""):
        lay = packing if isinstance(packing, PackedLayout) else PackedLayout(**{"bits": self.packed_bits,
                                                                                **(packing or {})})
        if lay.bits != self.packed_bits:
            raise FormatError(f"{path}: packing of {lay.bits}-bit samples given for format {self.name}")
        return lay

    def count(self, size_bytes, layout=None, path=""):
        return size_bytes // layout.word_bytes * layout.per_word // self.comps

    def nbytes(self, n, layout=None):
        return n * self.comps // layout.per_word * layout.word_bytes

    def decode(self, store, start, count, layout=None):
        comp_start = start * self.comps
        comp_stop = (start + count) * self.comps
        w0, w1 = comp_start // layout.per_word, -(-comp_stop // layout.per_word)
        vals = layout.unpack(np.asarray(store[w0 * layout.word_bytes:w1 * layout.word_bytes]))
        off = comp_start - layout.per_word * w0
        return np.ascontiguousarray(vals[off: off + count * self.comps], dtype=np.float32)

    def encoder(self):
        if not self.writable:
            raise FormatError(f"format {self.name!r} is read only (no writer for {self.packed_bits}-bit "
                              f"packed samples)")
        return _Packed2Encoder()


class _PlainEncoder:
    """float components -> bytes of ``dtype`` (integers rounded and clipped unless ``exact``)."""

    def __init__(self, dt):
        self.dt = dt

    def encode(self, comps, exact=False):
        dt = self.dt
        if dt.kind == "i" and exact:
            out = comps.astype(dt)
        elif dt.kind == "i":
            info = np.iinfo(dt)
            out = np.clip(np.rint(comps), info.min, info.max).astype(dt)
        else:
            out = comps.astype(dt)
        return out.tobytes()

    def flush(self):
        return b""


class _Packed2Encoder:
    """float components -> 2-bit sign-magnitude codes, four to a byte, the first in the high bits
    (the ``i2packed``/``ci2packed`` layout); components that do not fill a byte are carried to the
    next call, and ``flush`` pads the last byte with level +1 (code 0)."""

    def __init__(self):
        self._carry = np.zeros(0, dtype=np.float32)

    def encode(self, comps, exact=False):
        comps = np.concatenate([self._carry, comps]) if self._carry.size else comps
        n4 = comps.size // 4 * 4
        self._carry = comps[n4:].copy()
        c = _encode2(comps[:n4]).reshape(-1, 4)
        b = (c[:, 0] << 6) | (c[:, 1] << 4) | (c[:, 2] << 2) | c[:, 3]
        return b.astype(np.uint8).tobytes()

    def flush(self):
        if not self._carry.size:
            return b""
        pad = np.zeros(4 - self._carry.size, dtype=np.float32) + 1.0
        c = _encode2(np.concatenate([self._carry, pad]))
        self._carry = np.zeros(0, dtype=np.float32)
        return bytes([int((c[0] << 6) | (c[1] << 4) | (c[2] << 2) | c[3])])


FORMATS = {
    "i8": SampleFormat("i8", "<i1", False),
    "i16": SampleFormat("i16", "<i2", False),
    "f32": SampleFormat("f32", "<f4", False),
    "ci8": SampleFormat("ci8", "<i1", True),
    "ci16": SampleFormat("ci16", "<i2", True),
    "cf32": SampleFormat("cf32", "<f4", True),
    "i2packed": PackedFormat("i2packed", False, 2),
    "ci2packed": PackedFormat("ci2packed", True, 2),
}
# formats the reader accepts but nothing here writes
READ_ONLY_FORMATS = {
    "i4packed": PackedFormat("i4packed", False, 4, writable=False),
    "ci4packed": PackedFormat("ci4packed", True, 4, writable=False),
}

# 2-bit code -> level (sign-magnitude): 0:+1, 1:+3, 2:-1, 3:-3
CODE2_LEVEL = np.array([1.0, 3.0, -1.0, -3.0], dtype=np.float32)


def get_format(name):
    try:
        return FORMATS[name] if name in FORMATS else READ_ONLY_FORMATS[name]
    except (KeyError, TypeError):
        raise FormatError(f"unknown IF sample format {name!r}; expected one of "
                          f"{', '.join(list(FORMATS) + list(READ_ONLY_FORMATS))}") from None


def check_bits_for_format(fmt, bits, field="frontend"):
    """ConfigError unless quantiser width ``bits`` (0 = float) can be stored in format ``fmt``."""
    get_format(fmt).check_bits(bits, field)


def _encode2(levels):
    """Levels (any real) -> 2-bit codes: sign bit 1 if < 0, magnitude bit 1 if |x| > 2."""
    lv = np.asarray(levels, dtype=np.float32)
    return ((lv < 0).astype(np.uint8) << 1) | (np.abs(lv) > 2.0).astype(np.uint8)
