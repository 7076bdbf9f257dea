"""GPS LNAV (L1 C/A legacy navigation message) encoder and decoder, IS-GPS-200D §20.3
(see docs/references.md).

Bit conventions
---------------
* Internally bits are ``uint8`` 0/1 in transmission order (D1 first).  As ±1 symbols
  (``nav_bits``) a logic 0 is +1 and a logic 1 is −1 (BPSK ``x = (−1)^b``).  A Costas loop may
  deliver the whole stream inverted; the decoder resolves that from the preamble.
* A subframe is 10 words × 30 bits = 300 bits = 6 s.  Word 1 (TLM) starts with the preamble
  10001011; word 2 (HOW) carries the 17-bit TOW count of the *next* subframe start (in units of
  6 s), alert and anti-spoof flags and the 3-bit subframe ID.
* Parity: (32,26) Hamming code of Table 20-XIV with the last two bits D29*, D30* of the previous
  word; the 24 source bits are transmitted complemented when D30* = 1.  The two non-information
  bits 23–24 ("t bits") of words 2 and 10 are solved so that D29 = D30 = 0, hence every word 1 and
  word 3 start with D29* = D30* = 0 and every subframe can be encoded independently.
* Timing: subframe boundaries are at GPS TOW multiples of 6 s; subframe ID = (TOW/6 mod 5) + 1,
  page of subframes 4/5 = (TOW/30 mod 25) + 1.  Data bit k of the week spans
  [0.02·k, 0.02·(k+1)) s of satellite time.

Subframes 1–3 carry the clock/ephemeris parameters with the IS-GPS-200 scale factors (Tables
20-I, 20-III).  Subframes 4 and 5 carry structurally valid pages: data ID 01, the SV (page) ID
of Table 20-V and, for subframe 5 pages 1–24, the almanac of PRN = page when ``almanac`` (dict
prn -> Ephemeris) holds it; subframe 4 page 18 (SV ID 56) carries the ionospheric and UTC
parameters (Figure 20-1 sheet 8, Table 20-X scale factors) when ``iono`` (:class:`IonoUtc`) is
given (without it, page 18 is sent as a reserved page, SV ID 57); otherwise the page content is
the alternating 1/0 filler pattern.  The decoder keeps the
latest page 18 it reads with good parity in ``LnavDecoder.iono``.
"""

from dataclasses import dataclass

import numpy as np

from ultratight.constants import BIT_RATE, SECONDS_PER_WEEK
from ultratight.errors import NavDataError
from ultratight.signals.ephemeris import GPS_PI, Ephemeris
from ultratight.signals.gpstime import full_week, normalize

PREAMBLE = (1, 0, 0, 0, 1, 0, 1, 1)
WORD_BITS = 30
DATA_BITS = 24
SUBFRAME_WORDS = 10
SUBFRAME_BITS = WORD_BITS * SUBFRAME_WORDS
SUBFRAME_S = 6.0
BIT_S = 1.0 / BIT_RATE
BITS_PER_WEEK = int(round(SECONDS_PER_WEEK * BIT_RATE))
DEFAULT_WEEK_ERA = 2048          # ref for 10-bit week when no reference week is given (2019-2038)

# Table 20-XIV: source-bit indices (1-based) for D25..D30 and which of D29*/D30* enters.
PARITY_TABLE = (
    (29, (1, 2, 3, 5, 6, 10, 11, 12, 13, 14, 17, 18, 20, 23)),
    (30, (2, 3, 4, 6, 7, 11, 12, 13, 14, 15, 18, 19, 21, 24)),
    (29, (1, 3, 4, 5, 7, 8, 12, 13, 14, 15, 16, 19, 20, 22)),
    (30, (2, 4, 5, 6, 8, 9, 13, 14, 15, 16, 17, 20, 21, 23)),
    (30, (1, 3, 5, 6, 7, 9, 10, 14, 15, 16, 17, 18, 21, 22, 24)),
    (29, (3, 5, 6, 8, 9, 10, 11, 13, 15, 19, 22, 23, 24)),
)
_PARITY_MASKS = tuple((star, sum(1 << (24 - i) for i in idx)) for star, idx in PARITY_TABLE)

# Table 20-V: SV ID of subframe 4 pages 1..25 (57 = reserved pages; 56 = iono/UTC; 63 = A-S/health)
SF4_SV_ID = (57, 25, 26, 27, 28, 57, 29, 30, 31, 32, 57, 62, 52, 53, 54, 57, 55, 56, 58, 59, 57, 60,
             61, 62, 63)
SF5_PAGE25_SV_ID = 51
FILLER_24 = 0xAAAAAA             # alternating 1010... pattern

SC = GPS_PI                      # semicircle -> rad


# ----------------------------------------------------------------------------------- parity
def _popcount_parity(x):
    return bin(x).count("1") & 1


def parity_bits(d24, d29s, d30s):
    """Six parity bits (D25..D30 as an int, D25 the MSB) of 24 *source* bits ``d24`` (int, d1 MSB)."""
    out = 0
    for star, mask in _PARITY_MASKS:
        p = _popcount_parity(d24 & mask) ^ (d29s if star == 29 else d30s)
        out = (out << 1) | p
    return out


def encode_word(d24, d29s, d30s):
    """30 transmitted bits (int, D1 MSB) of a word from its 24 source bits and D29*, D30*."""
    data = d24 ^ (0xFFFFFF if d30s else 0)
    return (data << 6) | parity_bits(d24, d29s, d30s)


def check_word(word30, d29s, d30s):
    """(parity_ok, d24 source bits) of a received 30-bit word (int) given D29*, D30*."""
    d24 = (word30 >> 6) ^ (0xFFFFFF if d30s else 0)
    return parity_bits(d24, d29s, d30s) == (word30 & 0x3F), d24


def _solve_t_bits(d22, d29s, d30s):
    """24 source bits with the two t bits chosen so that D29 = D30 = 0 (given D29*, D30*)."""
    for t in range(4):
        d24 = (d22 << 2) | t
        if encode_word(d24, d29s, d30s) & 0x3 == 0:
            return d24
    raise AssertionError("no t-bit solution")   # cannot happen: D29/D30 depend on d23/d24


# ------------------------------------------------------------------------------ bit fields
class _Packer:
    def __init__(self):
        self.v = 0
        self.n = 0

    def put(self, value, nbits, name="field", signed=False):
        value = int(value)
        lo, hi = (-(1 << (nbits - 1)), (1 << (nbits - 1)) - 1) if signed else (0, (1 << nbits) - 1)
        if not lo <= value <= hi:
            raise NavDataError(f"LNAV field '{name}' = {value} does not fit in {nbits} "
                               f"{'signed' if signed else 'unsigned'} bits")
        self.v = (self.v << nbits) | (value & ((1 << nbits) - 1))
        self.n += nbits
        return self


def _split_words(packer, n_words):
    assert packer.n == 24 * n_words, packer.n
    return [(packer.v >> (24 * (n_words - 1 - k))) & 0xFFFFFF for k in range(n_words)]


def _get(bits_int, total, start, nbits, signed=False):
    """Extract a field of ``nbits`` at 0-based offset ``start`` from a ``total``-bit int."""
    v = (bits_int >> (total - start - nbits)) & ((1 << nbits) - 1)
    if signed and v >= 1 << (nbits - 1):
        v -= 1 << nbits
    return v


def _q(x, scale):
    return int(np.round(x / scale))


def _wrap_pi(x):
    return (x + np.pi) % (2.0 * np.pi) - np.pi


# Integer representation of the ephemeris (field name -> (scale, bits, signed, semicircles))
EPH_FIELDS = {
    "tgd": (2.0 ** -31, 8, True, False),
    "toc": (2.0 ** 4, 16, False, False),
    "af2": (2.0 ** -55, 8, True, False),
    "af1": (2.0 ** -43, 16, True, False),
    "af0": (2.0 ** -31, 22, True, False),
    "crs": (2.0 ** -5, 16, True, False),
    "delta_n": (2.0 ** -43, 16, True, True),
    "m0": (2.0 ** -31, 32, True, True),
    "cuc": (2.0 ** -29, 16, True, False),
    "e": (2.0 ** -33, 32, False, False),
    "cus": (2.0 ** -29, 16, True, False),
    "sqrt_a": (2.0 ** -19, 32, False, False),
    "toe": (2.0 ** 4, 16, False, False),
    "cic": (2.0 ** -29, 16, True, False),
    "omega0": (2.0 ** -31, 32, True, True),
    "cis": (2.0 ** -29, 16, True, False),
    "i0": (2.0 ** -31, 32, True, True),
    "crc": (2.0 ** -5, 16, True, False),
    "omega": (2.0 ** -31, 32, True, True),
    "omega_dot": (2.0 ** -43, 24, True, True),
    "idot": (2.0 ** -43, 14, True, True),
}
WRAPPED_ANGLES = ("m0", "omega0", "omega")


def eph_to_ints(eph):
    """Quantised integer message fields of an Ephemeris (raises NavDataError if out of range)."""
    out = {}
    for name, (scale, nbits, signed, semi) in EPH_FIELDS.items():
        x = float(getattr(eph, name))
        if name in WRAPPED_ANGLES:
            x = float(_wrap_pi(x))
        if semi:
            x = x / SC
        v = _q(x, scale)
        if signed and v == 1 << (nbits - 1) and name in WRAPPED_ANGLES:
            v = -v                          # +pi rounds to the field edge: same angle as -pi
        _Packer().put(v, nbits, name, signed)   # range check
        out[name] = v
    out["iodc"] = int(eph.iodc)
    out["iode"] = int(eph.iode)
    out["sv_health"] = int(eph.sv_health)
    out["ura_index"] = int(eph.ura_index)
    out["code_on_l2"] = int(eph.code_on_l2)
    out["l2p_flag"] = int(eph.l2p_flag)
    out["fit_flag"] = 1 if eph.fit_interval_h > 4.0 else 0
    out["aodo"] = int(round(eph.aodo / 900.0))
    return out


def ints_to_eph(ints, prn, week):
    """Ephemeris from integer message fields (``week`` = full week of toe)."""
    kw = {}
    for name, (scale, _nbits, _signed, semi) in EPH_FIELDS.items():
        v = ints[name] * scale
        kw[name] = v * SC if semi else v
    return Ephemeris(prn=int(prn), week=int(week), iodc=ints["iodc"], iode=ints["iode"],
                     sv_health=ints["sv_health"], ura_index=ints["ura_index"],
                     code_on_l2=ints["code_on_l2"], l2p_flag=ints["l2p_flag"],
                     fit_interval_h=6.0 if ints["fit_flag"] else 4.0, aodo=900 * ints["aodo"], **kw)


def quantise(eph):
    """The Ephemeris exactly as an LNAV receiver decodes it after transmission."""
    return ints_to_eph(eph_to_ints(eph), eph.prn, eph.week)


# ------------------------------------------------------------------------------- encoding
@dataclass(frozen=True)
class IonoUtc:
    """Subframe 4 page 18 content: Klobuchar alpha_0..3 (s, s/semicircle^n), beta_0..3 (s, ...),
    UTC parameters A0 (s), A1 (s/s), t_ot (s), WN_t, delta_t_LS, WN_LSF, DN, delta_t_LSF."""

    alpha: tuple
    beta: tuple
    a0: float = 0.0
    a1: float = 0.0
    tot: float = 0.0
    wnt: int = 0
    dt_ls: int = 18
    wn_lsf: int = 0
    dn: int = 1
    dt_lsf: int = 18


# Table 20-X scale factors (power of two) of alpha_0..3 and beta_0..3 (8-bit two's complement)
ALPHA_SCALE = (-30, -27, -24, -24)
BETA_SCALE = (11, 14, 16, 16)


def quantise_iono(alpha, beta):
    """alpha, beta (tuples) as an LNAV receiver decodes them from subframe 4 page 18."""
    qa = tuple(_q(v, 2.0 ** ALPHA_SCALE[k]) * 2.0 ** ALPHA_SCALE[k] for k, v in enumerate(alpha))
    qb = tuple(_q(v, 2.0 ** BETA_SCALE[k]) * 2.0 ** BETA_SCALE[k] for k, v in enumerate(beta))
    return qa, qb


def _iono_page(p18):
    p = _Packer().put(0b01, 2).put(56, 6, "sv_id")
    for k, v in enumerate(p18.alpha):
        p.put(_q(v, 2.0 ** ALPHA_SCALE[k]), 8, f"alpha{k}", True)
    for k, v in enumerate(p18.beta):
        p.put(_q(v, 2.0 ** BETA_SCALE[k]), 8, f"beta{k}", True)
    p.put(_q(p18.a1, 2.0 ** -50), 24, "A1", True)
    a0 = _q(p18.a0, 2.0 ** -30)
    _Packer().put(a0, 32, "A0", True)
    a0 &= 0xFFFFFFFF
    p.put(a0 >> 8, 24).put(a0 & 0xFF, 8)
    p.put(_q(p18.tot, 2.0 ** 12), 8, "t_ot").put(p18.wnt % 256, 8, "WN_t")
    p.put(p18.dt_ls, 8, "delta_t_LS", True).put(p18.wn_lsf % 256, 8, "WN_LSF").put(p18.dn, 8, "DN")
    p.put(p18.dt_lsf, 8, "delta_t_LSF", True).put(0, 14).put(0, 2)
    return _split_words(p, 8)


def _parse_iono_page(words):
    """IonoUtc from the 24-bit source words 3..10 of a subframe 4 page with SV ID 56."""
    v = 0
    for w in words[2:10]:
        v = (v << 24) | w
    n = 8 * 24
    alpha = tuple(_get(v, n, 8 + 8 * k, 8, True) * 2.0 ** ALPHA_SCALE[k] for k in range(4))
    beta = tuple(_get(v, n, 40 + 8 * k, 8, True) * 2.0 ** BETA_SCALE[k] for k in range(4))
    return IonoUtc(alpha=alpha, beta=beta, a1=_get(v, n, 72, 24, True) * 2.0 ** -50,
                   a0=_get(v, n, 96, 32, True) * 2.0 ** -30, tot=_get(v, n, 128, 8) * 2.0 ** 12,
                   wnt=_get(v, n, 136, 8), dt_ls=_get(v, n, 144, 8, True), wn_lsf=_get(v, n, 152, 8),
                   dn=_get(v, n, 160, 8), dt_lsf=_get(v, n, 168, 8, True))


def _subframe_words(sf_id, eph, tow_s, week, almanac=None, alert=0, anti_spoof=0, tlm_message=0, iono=None):
    """24-bit source words 1..10 (t bits of words 2 and 10 not yet solved: low 2 bits 0)."""
    tow_next = int(round(tow_s / SUBFRAME_S)) + 1
    tow_count = tow_next % (BITS_PER_WEEK // SUBFRAME_BITS)
    tlm = _Packer().put(0b10001011, 8).put(tlm_message, 14, "tlm_message").put(0, 1).put(0, 1)
    how = _Packer().put(tow_count, 17, "tow").put(alert, 1).put(anti_spoof, 1).put(sf_id, 3).put(0, 2)
    words = [tlm.v, how.v]
    if sf_id in (1, 2, 3):
        q = eph_to_ints(eph)
    if sf_id == 1:
        p = _Packer()
        p.put(week % 1024, 10, "week").put(q["code_on_l2"], 2, "code_on_l2")
        p.put(q["ura_index"], 4, "ura_index").put(q["sv_health"], 6, "sv_health")
        p.put(q["iodc"] >> 8, 2, "iodc")
        p.put(q["l2p_flag"], 1, "l2p_flag").put(0, 23)
        p.put(0, 24).put(0, 24).put(0, 16).put(q["tgd"], 8, "tgd", True)
        _Packer().put(q["iodc"], 10, "iodc")
        p.put(q["iodc"] & 0xFF, 8).put(q["toc"], 16, "toc")
        p.put(q["af2"], 8, "af2", True).put(q["af1"], 16, "af1", True)
        p.put(q["af0"], 22, "af0", True).put(0, 2)
        words += _split_words(p, 8)
    elif sf_id == 2:
        p = _Packer()
        p.put(q["iode"], 8, "iode").put(q["crs"], 16, "crs", True)
        p.put(q["delta_n"], 16, "delta_n", True).put(q["m0"] >> 24, 8, "m0", True)
        p.put(q["m0"] & 0xFFFFFF, 24)
        p.put(q["cuc"], 16, "cuc", True).put(q["e"] >> 24, 8)
        p.put(q["e"] & 0xFFFFFF, 24)
        p.put(q["cus"], 16, "cus", True).put(q["sqrt_a"] >> 24, 8)
        p.put(q["sqrt_a"] & 0xFFFFFF, 24)
        p.put(q["toe"], 16, "toe").put(q["fit_flag"], 1).put(q["aodo"], 5, "aodo").put(0, 2)
        words += _split_words(p, 8)
    elif sf_id == 3:
        p = _Packer()
        p.put(q["cic"], 16, "cic", True).put(q["omega0"] >> 24, 8, "omega0", True)
        p.put(q["omega0"] & 0xFFFFFF, 24)
        p.put(q["cis"], 16, "cis", True).put(q["i0"] >> 24, 8, "i0", True)
        p.put(q["i0"] & 0xFFFFFF, 24)
        p.put(q["crc"], 16, "crc", True).put(q["omega"] >> 24, 8, "omega", True)
        p.put(q["omega"] & 0xFFFFFF, 24)
        p.put(q["omega_dot"], 24, "omega_dot", True)
        p.put(q["iode"], 8, "iode").put(q["idot"], 14, "idot", True).put(0, 2)
        words += _split_words(p, 8)
    elif sf_id in (4, 5):
        page = int(round(tow_s / SUBFRAME_S)) // 5 % 25 + 1
        if sf_id == 4 and page == 18 and iono is not None:
            words += _iono_page(iono)
        elif sf_id == 4 and page == 18:
            # no coefficients to send: a reserved page (SV ID 57), so that no receiver reads the
            # filler pattern as ionospheric / UTC parameters
            words += _filler_page(57)
        elif sf_id == 4:
            words += _filler_page(SF4_SV_ID[page - 1])
        elif page == 25:
            words += _filler_page(SF5_PAGE25_SV_ID)
        elif almanac is not None and almanac.get(page) is not None:
            words += _almanac_page(almanac[page], tow_s)
        else:
            words += _filler_page(page)
    else:
        raise NavDataError(f"LNAV subframe ID {sf_id} invalid (expected 1..5)")
    return words


def _filler_page(sv_id):
    p = _Packer().put(0b01, 2).put(sv_id, 6, "sv_id").put(FILLER_24 & 0xFFFF, 16)
    for _ in range(6):
        p.put(FILLER_24, 24)
    p.put(FILLER_24 >> 2, 22).put(0, 2)
    return _split_words(p, 8)


def _almanac_page(eph, tow_s):
    """Subframe 5 almanac page (Table 20-VI scale factors) for ``eph`` with toa = toe."""
    p = _Packer().put(0b01, 2).put(eph.prn, 6, "sv_id")
    p.put(_q(eph.e, 2.0 ** -21), 16, "alm e")
    p.put(_q(eph.toe % SECONDS_PER_WEEK, 2.0 ** 12) & 0xFF, 8, "toa")
    p.put(_q(eph.i0 / SC - 0.30, 2.0 ** -19), 16, "delta_i", True)
    p.put(_q(eph.omega_dot / SC, 2.0 ** -38), 16, "alm omega_dot", True)
    p.put(eph.sv_health & 0xFF, 8, "alm health")
    p.put(_q(eph.sqrt_a, 2.0 ** -11), 24, "alm sqrt_a")
    for name in ("omega0", "omega", "m0"):
        p.put(_q(_wrap_pi(getattr(eph, name)) / SC, 2.0 ** -23), 24, f"alm {name}", True)
    af0 = _q(eph.af0, 2.0 ** -20)
    _Packer().put(af0, 11, "alm af0", True)
    af0 &= 0x7FF
    p.put(af0 >> 3, 8).put(_q(eph.af1, 2.0 ** -38), 11, "alm af1", True).put(af0 & 0x7, 3).put(0, 2)
    return _split_words(p, 8)


def encode_subframe(sf_id, eph, tow_s, week=None, almanac=None, alert=0, anti_spoof=0,
                    tlm_message=0, iono=None):
    """300 transmitted bits (uint8 0/1) of the subframe that starts at GPS TOW ``tow_s``.

    ``tow_s`` must be a multiple of 6 s; ``week`` is the transmission week (default eph.week; only
    its 10 LSBs are sent).  Raises NavDataError when a parameter does not fit its field."""
    if abs(tow_s / SUBFRAME_S - round(tow_s / SUBFRAME_S)) > 1e-9:
        raise NavDataError(f"LNAV subframe start tow_s = {tow_s} is not a multiple of 6 s")
    if week is None:
        week = eph.week
    words = _subframe_words(int(sf_id), eph, tow_s, int(week), almanac, alert, anti_spoof, tlm_message, iono)
    return encode_words(words)


def encode_words(words):
    """300 transmitted bits (uint8 0/1) of a subframe from its ten 24-bit source words (the t bits of
    words 2 and 10, their two low bits, are solved so that D29 = D30 = 0)."""
    bits = np.empty(SUBFRAME_BITS, dtype=np.uint8)
    d29s = d30s = 0
    for k, d24 in enumerate(words):
        if k in (1, 9):
            d24 = _solve_t_bits(d24 >> 2, d29s, d30s)
        w30 = encode_word(d24, d29s, d30s)
        for j in range(WORD_BITS):
            bits[k * WORD_BITS + j] = (w30 >> (WORD_BITS - 1 - j)) & 1
        d29s, d30s = (w30 >> 1) & 1, w30 & 1
    return bits


def subframe_id_at(tow_s):
    """Subframe ID (1..5) of the subframe that starts at TOW ``tow_s`` (multiple of 6)."""
    return int(round(tow_s / SUBFRAME_S)) % 5 + 1


def bit_index(tow_s):
    """Index of the LNAV bit in progress at TOW ``tow_s`` (floor; 1e-7 bit tolerance)."""
    return np.floor(np.asarray(tow_s, dtype=np.float64) / BIT_S + 1e-7).astype(np.int64)


def nav_bits_at(eph, week, bit_indices, almanac=None, iono=None):
    """±1 symbols (int8, logic 0 -> +1) of the LNAV bits with absolute indices ``bit_indices``
    counted from the start of GPS week ``week`` (may be negative or ≥ one week: the week is
    carried).  Subframes are encoded once per call."""
    idx = np.asarray(bit_indices, dtype=np.int64)
    out = np.empty(idx.shape, dtype=np.int8)
    if idx.size == 0:
        return out
    sf_idx = np.floor_divide(idx, SUBFRAME_BITS)
    for s in np.unique(sf_idx):
        w, tow = normalize(week, float(s) * SUBFRAME_S)
        bits = encode_subframe(subframe_id_at(tow), eph, tow, week=w, almanac=almanac, iono=iono)
        sel = sf_idx == s
        out[sel] = 1 - 2 * bits[idx[sel] - s * SUBFRAME_BITS].astype(np.int8)
    return out


def nav_bits(eph, week, tow_start_s, n_bits, almanac=None, iono=None):
    """``n_bits`` ±1 LNAV data bits (int8) aligned to GPS (satellite) time.

    Bit k spans [t0 + 0.02·k, t0 + 0.02·(k+1)) with t0 = the start of the bit in progress at
    ``tow_start_s``, i.e. ``t0 = floor(tow_start_s / 0.02)·0.02`` (to within 1e-7 bit, so a
    ``tow_start_s`` on a bit edge up to float rounding is used as is).  When ``tow_start_s`` is
    not on a bit edge, bit 0 is the partial bit containing it.  Use :func:`bit_index` /
    :func:`nav_bits_at` to look bits up for arbitrary satellite-clock times."""
    k0 = int(bit_index(tow_start_s))
    return nav_bits_at(eph, week, k0 + np.arange(int(n_bits)), almanac, iono)


# ------------------------------------------------------- navigation data a receiver cannot know
NAV_DATA_MODES = ("lnav", "lnav-random-sf45", "random")
"""Content of the broadcast data (:func:`nav_bits_mode`):

* ``lnav``: the LNAV message of this module (subframes 1-3 from the ephemeris, structured
  subframes 4-5), all of it reproducible from the ephemeris;
* ``lnav-random-sf45``: as a real satellite sends it, content a receiver cannot re-encode from the
  ephemeris: subframes 4 and 5 carry random source bits in words 3-10 (22 of word 10), and the
  reserved fields of subframes 1-3 are random (TLM message and the TLM's integrity/reserved bit of
  every subframe; subframe 1: the 23 reserved bits of word 4, words 5-6 and the 16 reserved bits
  of word 7); every word keeps valid parity, so a decoder reads all of it and the ephemeris of
  subframes 1-3 is unchanged;
* ``random``: every bit random (no preamble, no parity).

Random content is a function of ``(seed, prn, subframe)`` only (one ``numpy.random.Generator`` per
subframe from ``SeedSequence([seed, NAV_SEED_TAG, prn, week * 100800 + subframe of week])``), so any
stretch of the stream can be reproduced alone."""
NAV_SEED_TAG = 0x6E6176


def _subframe_rng(seed, prn, week, sf_of_week):
    return np.random.default_rng(np.random.SeedSequence(
        [int(seed), NAV_SEED_TAG, int(prn), int(week) * (BITS_PER_WEEK // SUBFRAME_BITS) + int(sf_of_week)]))


def randomise_words(words, sf_id, rng):
    """Source words of one subframe with the fields of ``lnav-random-sf45`` (:data:`NAV_DATA_MODES`)
    replaced by random bits from ``rng``; returns a new list."""
    w = list(words)
    tlm_msg = int(rng.integers(0, 1 << 14))
    isf = int(rng.integers(0, 2))
    w[0] = (w[0] & 0xFF0000) | (tlm_msg << 2) | (isf << 1)
    if sf_id == 1:
        w[3] = (w[3] & 0x800000) | int(rng.integers(0, 1 << 23))
        w[4] = int(rng.integers(0, 1 << 24))
        w[5] = int(rng.integers(0, 1 << 24))
        w[6] = (int(rng.integers(0, 1 << 16)) << 8) | (w[6] & 0xFF)
    elif sf_id in (4, 5):
        for k in range(2, 9):
            w[k] = int(rng.integers(0, 1 << 24))
        w[9] = int(rng.integers(0, 1 << 22)) << 2
    return w


def nav_bits_mode(eph, week, tow_start_s, n_bits, mode="lnav", seed=0, almanac=None, iono=None):
    """:func:`nav_bits` with the data content ``mode`` (:data:`NAV_DATA_MODES`) and its seed."""
    if mode not in NAV_DATA_MODES:
        raise NavDataError(f"navigation data mode {mode!r} unknown; expected one of {', '.join(NAV_DATA_MODES)}")
    if mode == "lnav":
        return nav_bits(eph, week, tow_start_s, n_bits, almanac, iono)
    k0 = int(bit_index(tow_start_s))
    idx = k0 + np.arange(int(n_bits), dtype=np.int64)
    out = np.empty(idx.shape, dtype=np.int8)
    sf_idx = np.floor_divide(idx, SUBFRAME_BITS)
    for s in np.unique(sf_idx):
        w, tow = normalize(week, float(s) * SUBFRAME_S)
        rng = _subframe_rng(seed, eph.prn, w, int(round(tow / SUBFRAME_S)))
        if mode == "random":
            bits = rng.integers(0, 2, SUBFRAME_BITS).astype(np.uint8)
        else:
            sf_id = subframe_id_at(tow)
            words = _subframe_words(sf_id, eph, tow, w, almanac, iono=iono)
            bits = encode_words(randomise_words(words, sf_id, rng))
        sel = sf_idx == s
        out[sel] = 1 - 2 * bits[idx[sel] - s * SUBFRAME_BITS].astype(np.int8)
    return out


# ------------------------------------------------------------------------------- decoding
@dataclass
class DecodedSubframe:
    start_bit: int            # index in the fed stream of the first bit of the TLM word
    inverted: bool            # stream polarity (True: received bits were complemented)
    sf_id: int
    tow_s: float              # GPS TOW of the start of this subframe (HOW count·6 − 6; predicted
                              # from the previous subframe when the HOW fails parity; None if unknown)
    words: list               # 24-bit source data of words 1..10 (None where parity failed)
    bad_words: list           # 1-based numbers of words failing parity
    page: int = 0             # page number for subframes 4/5 (from the TOW)

    @property
    def ok(self):
        return not self.bad_words


def _to_bits01(bits):
    b = np.asarray(bits)
    if b.dtype == np.bool_:
        return b.astype(np.uint8)
    if np.issubdtype(b.dtype, np.floating) or np.any(b < 0):
        return (b < 0).astype(np.uint8)          # ±1 (or soft) symbols: negative -> logic 1
    return (b != 0).astype(np.uint8)


def _word_int(b, start):
    v = 0
    for j in range(WORD_BITS):
        v = (v << 1) | int(b[start + j])
    return v


class LnavDecoder:
    """Streaming LNAV decoder.

    ``feed(bits)`` accepts ±1 symbols (int or float; negative = logic 1) or 0/1 bits, possibly
    complemented (Costas-loop ambiguity).  It searches the preamble (either polarity) with TLM and
    HOW parity, confirms with the next preamble 300 bits later (or a consistent HOW), then decodes
    subframe by subframe.  Returns the newly decoded :class:`DecodedSubframe` list; attributes:
    ``inverted`` (polarity), ``tow_s`` (start TOW of the latest subframe), ``week`` (full week from
    subframe 1, resolved with ``ref_week``; default the 2048-week era), ``ephemeris`` (latest
    complete subframe 1–3 set with matching IODC/IODE, else None), ``bad_words`` (list of
    (start_bit, word_number) of every word that failed parity), ``subframes`` (all decoded),
    ``polarity_flips`` (times the polarity changed while locked: the expected preamble appeared
    complemented with good TLM/HOW parity, as after a Costas half-cycle slip).
    """

    def __init__(self, prn=0, ref_week=None):
        self.prn = int(prn)
        self.ref_week = ref_week
        self.buf = np.zeros(0, dtype=np.uint8)
        self.buf_offset = 0            # stream index of buf[0]
        self.sync = None               # stream index of the next expected subframe start
        self.inverted = None
        self.tow_s = None
        self.week = None
        self.ephemeris = None
        self.bad_words = []
        self.subframes = []
        self._sf = {}
        self.polarity_flips = 0
        self.iono = None               # IonoUtc of the latest subframe 4 page 18 with good parity
        self.ephemeris_tx_tow = None   # TOW of the subframe 1 of the current ephemeris

    # -- helpers
    def _tlm_how_ok(self, b, i, inv, prev_zero=False):
        """TLM and HOW parity (and preamble, subframe ID, TOW range) at i with polarity inv.
        D29*, D30* of the TLM are read from the stream, or taken as 0 (their design value: word 10
        ends in 00) when ``prev_zero`` or at the stream start."""
        if i + 2 * WORD_BITS > len(b):
            return None
        if i >= 2 and not prev_zero:
            d29s, d30s = int(b[i - 2]) ^ inv, int(b[i - 1]) ^ inv
        else:
            d29s, d30s = 0, 0
        w1 = _word_int(b, i) ^ (0x3FFFFFFF if inv else 0)
        ok1, d1 = check_word(w1, d29s, d30s)
        w2 = _word_int(b, i + WORD_BITS) ^ (0x3FFFFFFF if inv else 0)
        ok2, d2 = check_word(w2, (w1 >> 1) & 1, w1 & 1)
        if not (ok1 and ok2) or (d1 >> 16) != 0b10001011:
            return False
        sf_id = (d2 >> 2) & 0x7
        return 1 <= sf_id <= 5 and (d2 >> 7) < 100800

    @staticmethod
    def _preamble_at(b, i, inv):
        return (_word_int(b, i) ^ (0x3FFFFFFF if inv else 0)) >> 22 == 0b10001011

    def _how_word(self, b, i, inv):
        """Source bits of the HOW at subframe start i if its parity holds, else None."""
        w1 = _word_int(b, i) ^ (0x3FFFFFFF if inv else 0)
        w2 = _word_int(b, i + WORD_BITS) ^ (0x3FFFFFFF if inv else 0)
        ok, d2 = check_word(w2, (w1 >> 1) & 1, w1 & 1)
        return d2 if ok else None

    def _next_how_consistent(self, b, i, inv):
        h1 = self._how_word(b, i, inv)
        h2 = self._how_word(b, i + SUBFRAME_BITS, inv)
        return h1 is not None and h2 is not None and (h2 >> 7) == ((h1 >> 7) + 1) % 100800

    def _search(self, b):
        pre = np.array(PREAMBLE, dtype=np.uint8)
        n = len(b)
        for i in range(0, n - 2 * WORD_BITS + 1):
            seg = b[i:i + 8]
            if np.array_equal(seg, pre):
                inv = 0
            elif np.array_equal(seg, 1 - pre):
                inv = 1
            else:
                continue
            r = self._tlm_how_ok(b, i, inv)
            if r is None:
                return None, None, True           # need more bits
            if not r:
                continue
            j = i + SUBFRAME_BITS
            if j + 2 * WORD_BITS > n:
                return None, None, True           # confirm with the next subframe first
            # confirmation: the next subframe's preamble (same polarity) or its TLM+HOW parity
            # or a HOW there with good parity and the TOW count one higher
            if np.array_equal(b[j:j + 8], pre if inv == 0 else 1 - pre) or \
                    self._tlm_how_ok(b, j, inv) or self._next_how_consistent(b, i, inv):
                return i, inv, False
        return None, None, False

    def feed(self, bits):
        new = _to_bits01(bits).ravel()
        self.buf = np.concatenate((self.buf, new))
        out = []
        while True:
            b = self.buf
            if self.sync is None:
                i, inv, _need = self._search(b)
                if i is None:
                    keep = min(len(b), SUBFRAME_BITS + 2 * WORD_BITS)
                    self.buf_offset += len(b) - keep
                    self.buf = b[len(b) - keep:]
                    return out
                self.sync = self.buf_offset + i
                self.inverted = bool(inv)
            i = self.sync - self.buf_offset
            if i + SUBFRAME_BITS > len(b):
                drop = max(0, i - 2)
                self.buf = b[drop:]
                self.buf_offset += drop
                return out
            inv = int(self.inverted)
            if not self._preamble_at(b, i, inv) and self._preamble_at(b, i, 1 - inv) and \
                    self._tlm_how_ok(b, i, 1 - inv, prev_zero=True):
                self.inverted = not self.inverted     # half-cycle slip of the carrier loop
                self.polarity_flips += 1
            sf = self._decode_at(b, i, int(self.inverted))
            if sf is None:                          # lost lock: search again after this point
                self.sync = None
                self.inverted = None
                drop = i + 1
                self.buf = b[drop:]
                self.buf_offset += drop
                continue
            out.append(sf)
            self.sync += SUBFRAME_BITS

    def _decode_at(self, b, i, inv):
        """Decode the subframe at buffer index i (lock held).  Words failing parity are reported;
        the lock is dropped (None returned) only when the preamble, the TLM and the HOW all fail."""
        d29s, d30s = (int(b[i - 2]) ^ inv, int(b[i - 1]) ^ inv) if i >= 2 else (0, 0)
        words, bad = [], []
        for k in range(SUBFRAME_WORDS):
            w = _word_int(b, i + k * WORD_BITS) ^ (0x3FFFFFFF if inv else 0)
            ok, d24 = check_word(w, d29s, d30s)
            words.append(d24 if ok else None)
            if not ok:
                bad.append(k + 1)
            d29s, d30s = (w >> 1) & 1, w & 1
        pre_ok = (_word_int(b, i) ^ (0x3FFFFFFF if inv else 0)) >> 22 == 0b10001011
        how = words[1]
        how_ok = how is not None and 1 <= (how >> 2) & 0x7 <= 5 and (how >> 7) < 100800
        if not (pre_ok or 1 not in bad or how_ok):
            return None
        for k in bad:
            self.bad_words.append((self.buf_offset + i, k))
        if how_ok:
            tow = ((how >> 7) * SUBFRAME_S - SUBFRAME_S) % SECONDS_PER_WEEK
            sf_id = (how >> 2) & 0x7
        elif self.tow_s is not None:             # predicted from the previous subframe
            tow = (self.tow_s + SUBFRAME_S) % SECONDS_PER_WEEK
            sf_id = subframe_id_at(tow)
        else:
            tow, sf_id = None, 0
        page = int(round(tow / SUBFRAME_S)) // 5 % 25 + 1 if sf_id in (4, 5) and tow is not None else 0
        sf = DecodedSubframe(self.buf_offset + i, bool(inv), sf_id, tow, words, bad, page)
        self.tow_s = tow
        self.subframes.append(sf)
        if sf_id in (1, 2, 3) and not bad:
            self._sf[sf_id] = sf
            self._try_ephemeris()
        elif sf_id == 4 and not bad and (words[2] >> 16) & 0x3F == 56:
            self.iono = _parse_iono_page(words)
        return sf

    def _try_ephemeris(self):
        if not all(k in self._sf for k in (1, 2, 3)):
            return
        s1, s2, s3 = (self._sf[k].words for k in (1, 2, 3))
        ints, wn = _parse_sf123(s1, s2, s3)
        if not (ints["iode"] == ints["iode3"] == (ints["iodc"] & 0xFF)):
            return
        ref = self.ref_week if self.ref_week is not None else DEFAULT_WEEK_ERA
        week = full_week(wn, ref)
        self.week = week
        tx_tow = self._sf[1].tow_s
        dt = ints["toe"] * 2.0 ** 4 - tx_tow
        eph_week = week + (-1 if dt > SECONDS_PER_WEEK / 2 else (1 if dt < -SECONDS_PER_WEEK / 2 else 0))
        self.ephemeris = ints_to_eph(ints, self.prn, eph_week)
        self.ephemeris_tx_tow = float(tx_tow)     # start of its subframe 1 (the RINEX transmission time)


def _parse_sf123(s1, s2, s3):
    """Integer fields from the 24-bit source words of subframes 1, 2, 3; returns (ints, wn10)."""
    def cat(words, k0, k1):            # concatenate words k0..k1 (0-based) into one int
        v = 0
        for k in range(k0, k1 + 1):
            v = (v << 24) | words[k]
        return v, 24 * (k1 - k0 + 1)

    q = {}
    v, n = cat(s1, 2, 9)
    wn = _get(v, n, 0, 10)
    q["code_on_l2"] = _get(v, n, 10, 2)
    q["ura_index"] = _get(v, n, 12, 4)
    q["sv_health"] = _get(v, n, 16, 6)
    iodc_msb = _get(v, n, 22, 2)
    q["l2p_flag"] = _get(v, n, 24, 1)
    q["tgd"] = _get(v, n, 4 * 24 + 16, 8, True)
    q["iodc"] = (iodc_msb << 8) | _get(v, n, 5 * 24, 8)
    q["toc"] = _get(v, n, 5 * 24 + 8, 16)
    q["af2"] = _get(v, n, 6 * 24, 8, True)
    q["af1"] = _get(v, n, 6 * 24 + 8, 16, True)
    q["af0"] = _get(v, n, 7 * 24, 22, True)
    v, n = cat(s2, 2, 9)
    q["iode"] = _get(v, n, 0, 8)
    q["crs"] = _get(v, n, 8, 16, True)
    q["delta_n"] = _get(v, n, 24, 16, True)
    q["m0"] = _get(v, n, 40, 32, True)
    q["cuc"] = _get(v, n, 72, 16, True)
    q["e"] = _get(v, n, 88, 32)
    q["cus"] = _get(v, n, 120, 16, True)
    q["sqrt_a"] = _get(v, n, 136, 32)
    q["toe"] = _get(v, n, 168, 16)
    q["fit_flag"] = _get(v, n, 184, 1)
    q["aodo"] = _get(v, n, 185, 5)
    v, n = cat(s3, 2, 9)
    q["cic"] = _get(v, n, 0, 16, True)
    q["omega0"] = _get(v, n, 16, 32, True)
    q["cis"] = _get(v, n, 48, 16, True)
    q["i0"] = _get(v, n, 64, 32, True)
    q["crc"] = _get(v, n, 96, 16, True)
    q["omega"] = _get(v, n, 112, 32, True)
    q["omega_dot"] = _get(v, n, 144, 24, True)
    q["iode3"] = _get(v, n, 168, 8)
    q["idot"] = _get(v, n, 176, 14, True)
    return q, wn


def decode_bits(bits, prn=0, ref_week=None):
    """Decode a whole bit stream at once; returns the :class:`LnavDecoder` after feeding it."""
    dec = LnavDecoder(prn=prn, ref_week=ref_week)
    dec.feed(bits)
    return dec
