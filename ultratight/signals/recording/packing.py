"""Packed 2-bit and 4-bit IF samples in the layouts front ends use.

A layout (:class:`PackedLayout`) is: sample width ``bits`` (2 or 4), the order of the samples
inside a word (``"msb-first"``: the first sample in the most significant bits;
``"lsb-first"``: in the least significant bits), the word size in bytes (1, 2, 4 or 8) and its
byte order (``"little"`` / ``"big"``), and the encoding of a sample code ``c`` (the names of the ION
GNSS SDR Metadata Standard; the levels are odd integers, symmetric about zero):

==================  ==========  =================================================================
``sign-magnitude``  SM          top bit = sign (1 = negative), the rest = magnitude m: ``±(2m + 1)``
``twos-complement`` TC          ``c`` as a signed integer v: ``2v + 1``
``offset-binary``   OB          ``v = c - 2^(bits-1)``: ``2v + 1``
``sign``            SIGN        the top bit only (sign-only data in a wider field): ``+1`` / ``-1``
==================  ==========  =================================================================

The project's own ``i2packed`` / ``ci2packed`` files are ``PackedLayout(2)`` (MSB first, 1-byte
words, sign-magnitude: codes 0, 1, 2, 3 = +1, +3, -1, -3); complex samples interleave I then Q.
"""

from dataclasses import asdict, dataclass

import numpy as np

from ultratight.errors import ConfigError

ORDERS = ("msb-first", "lsb-first")
ENCODINGS = ("sign-magnitude", "twos-complement", "offset-binary", "sign")
ION_ENCODINGS = {"SM": "sign-magnitude", "SIGNMAG": "sign-magnitude", "TC": "twos-complement",
                 "OB": "offset-binary", "SIGN": "sign"}
WORD_BYTES = (1, 2, 4, 8)


@dataclass(frozen=True)
class PackedLayout:
    bits: int = 2
    order: str = "msb-first"
    word_bytes: int = 1
    endian: str = "little"
    encoding: str = "sign-magnitude"

    def __post_init__(self):
        if self.bits not in (2, 4):
            raise ConfigError(f"packed sample width must be 2 or 4 bits, got {self.bits}")
        if self.order not in ORDERS:
            raise ConfigError(f"--packing must be one of {', '.join(ORDERS)}, got {self.order!r}")
        if self.word_bytes not in WORD_BYTES:
            raise ConfigError(f"--word-size must be one of {', '.join(map(str, WORD_BYTES))} bytes, "
                              f"got {self.word_bytes}")
        if self.endian not in ("little", "big"):
            raise ConfigError(f"--endian must be little or big, got {self.endian!r}")
        if self.encoding not in ENCODINGS:
            raise ConfigError(f"--encoding must be one of {', '.join(ENCODINGS)}, got {self.encoding!r}")

    @property
    def per_word(self):
        return 8 * self.word_bytes // self.bits

    def as_dict(self):
        return asdict(self)

    def levels(self):
        """float32 level of every code 0 .. 2^bits - 1."""
        b = self.bits
        c = np.arange(1 << b)
        top = c >> (b - 1)
        if self.encoding == "sign-magnitude":
            m = c & ((1 << (b - 1)) - 1)
            v = np.where(top == 1, -(2 * m + 1), 2 * m + 1)
        elif self.encoding == "twos-complement":
            v = 2 * np.where(top == 1, c - (1 << b), c) + 1
        elif self.encoding == "offset-binary":
            v = 2 * (c - (1 << (b - 1))) + 1
        else:
            v = np.where(top == 1, -1, 1)
        return v.astype(np.float32)

    def shifts(self):
        wb = 8 * self.word_bytes
        k = np.arange(self.per_word)
        return (wb - self.bits * (k + 1)) if self.order == "msb-first" else self.bits * k

    def unpack(self, raw_bytes):
        """Levels (float32, one per packed component, in stream order) of whole words."""
        raw = np.asarray(raw_bytes, dtype=np.uint8)
        lv = self.levels()
        mask = (1 << self.bits) - 1
        if self.word_bytes == 1:
            lut = lv[(np.arange(256)[:, None] >> self.shifts()[None, :]) & mask].astype(np.float32)
            return lut[raw].reshape(-1)
        dt = np.dtype(("<" if self.endian == "little" else ">") + f"u{self.word_bytes}")
        words = raw[: raw.size // self.word_bytes * self.word_bytes].view(dt).astype(np.uint64)
        codes = (words[:, None] >> self.shifts().astype(np.uint64)[None, :]) & np.uint64(mask)
        return lv[codes.reshape(-1).astype(np.int64)]

    def pack(self, codes):
        """Bytes of the codes (ints 0 .. 2^bits - 1, stream order; padded with code 0 to whole words)."""
        c = np.asarray(codes, dtype=np.uint64)
        n = -(-c.size // self.per_word) * self.per_word
        c = np.concatenate([c, np.zeros(n - c.size, np.uint64)]).reshape(-1, self.per_word)
        words = np.bitwise_or.reduce(c << self.shifts().astype(np.uint64)[None, :], axis=1)
        dt = np.dtype(("<" if self.endian == "little" else ">") + f"u{self.word_bytes}")
        return words.astype(dt).tobytes()

    def codes_of_levels(self, levels):
        """Codes of the given levels (each must be one of :meth:`levels`; for ``sign`` the sign)."""
        lv = self.levels()
        x = np.asarray(levels, dtype=np.float32)
        if self.encoding == "sign":
            return np.where(x < 0, 1 << (self.bits - 1), 0).astype(np.uint64)
        idx = np.abs(x[:, None] - lv[None, :]).argmin(axis=1)
        return idx.astype(np.uint64)


DEFAULT_2BIT = PackedLayout(2)
