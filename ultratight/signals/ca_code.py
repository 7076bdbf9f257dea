"""GPS L1 C/A Gold codes (IS-GPS-200D §3.3.2.3 and Table 3-I; see docs/references.md).

G1 = 1 + x^3 + x^10, G2 = 1 + x^2 + x^3 + x^6 + x^8 + x^9 + x^10, both
started from all ones.  The code of PRN i is G1 XOR (G2 delayed by the PRN's
G2 delay in chips).  Logic 0 maps to +1 and logic 1 to -1 (``ca_code``);
``ca_code_bits`` returns the logic levels.
"""

import functools

import numpy as np

from ultratight.constants import CA_LEN
from ultratight.errors import ConfigError

# IS-GPS-200D Table 3-I, "Code Delay Chips" for G2, PRN 1..32.
G2_DELAY = (
    5, 6, 7, 8, 17, 18, 139, 140, 141, 251, 252, 254, 255, 256, 257, 258,
    469, 470, 471, 472, 473, 474, 509, 512, 513, 514, 515, 516, 859, 860, 861, 862,
)
PRNS = tuple(range(1, 33))


def _lfsr_sequence(taps):
    """1023 output bits of a 10-stage Fibonacci LFSR started from all ones.

    ``taps`` are the polynomial exponents fed back; the output is stage 10.
    """
    reg = [1] * 10
    out = np.empty(CA_LEN, dtype=np.uint8)
    for k in range(CA_LEN):
        out[k] = reg[9]
        fb = 0
        for t in taps:
            fb ^= reg[t - 1]
        reg = [fb] + reg[:9]
    return out


@functools.lru_cache(maxsize=None)
def _g1g2():
    return _lfsr_sequence((3, 10)), _lfsr_sequence((2, 3, 6, 8, 9, 10))


def _check_prn(prn):
    if not (isinstance(prn, (int, np.integer)) and 1 <= prn <= 32):
        raise ConfigError(f"PRN must be an integer in 1..32, got {prn!r}")


@functools.lru_cache(maxsize=None)
def _bits(prn):
    g1, g2 = _g1g2()
    delay = G2_DELAY[prn - 1]
    code = g1 ^ np.roll(g2, delay)
    code.setflags(write=False)
    return code


def ca_code_bits(prn):
    """Logic levels (uint8, 0/1) of the 1023 chips of PRN ``prn`` (read-only)."""
    _check_prn(prn)
    return _bits(int(prn))


def ca_code(prn):
    """Chips of PRN ``prn`` as +1/-1 int8 (logic 0 -> +1, logic 1 -> -1)."""
    return (1 - 2 * ca_code_bits(prn).astype(np.int8)).astype(np.int8)


def ca_code_table(prns=PRNS):
    """Array (len(prns), 1023) of +1/-1 int8 chips, one row per PRN."""
    return np.stack([ca_code(p) for p in prns])


def first_chips_octal(prn, n=10):
    """First ``n`` chips of PRN as an octal string, as tabulated in IS-GPS-200D Table 3-I."""
    value = 0
    for b in ca_code_bits(prn)[:n]:
        value = (value << 1) | int(b)
    return format(value, "o")
