"""GPS LNAV message content, IS-GPS-200D §20.3 (see docs/references.md): the frame structure, the
fields of every subframe with their scale factors, and the 24-bit source words that carry them.

:func:`subframe_words` builds the ten source words of a subframe (the t bits of words 2 and 10 left
0: :func:`ultratight.signals.lnav.encode_words` solves them and adds the parity);
:func:`parse_sf123` and :func:`parse_iono_page` read fields back from decoded source words.

Subframes 1–3 carry the clock/ephemeris parameters with the IS-GPS-200 scale factors (Tables
20-I, 20-III).  Subframes 4 and 5 carry structurally valid pages: data ID 01, the SV (page) ID
of Table 20-V and, for subframe 5 pages 1–24, the almanac of PRN = page when ``almanac`` (dict
prn -> Ephemeris) holds it; subframe 4 page 18 (SV ID 56) carries the ionospheric and UTC
parameters (Figure 20-1 sheet 8, Table 20-X scale factors) when ``iono`` (:class:`IonoUtc`) is
given (without it, page 18 is sent as a reserved page, SV ID 57); otherwise the page content is
the alternating 1/0 filler pattern.  :func:`quantise` and :func:`quantise_iono` give the values
exactly as a receiver decodes them after transmission.
"""

from dataclasses import dataclass

import numpy as np

from ultratight.constants import BIT_RATE, SECONDS_PER_WEEK
from ultratight.errors import NavDataError
from ultratight.signals.ephemeris import GPS_PI, Ephemeris

# frame structure (the bit stream in ultratight.signals.lnav)
PREAMBLE = (1, 0, 0, 0, 1, 0, 1, 1)
WORD_BITS = 30
DATA_BITS = 24
SUBFRAME_WORDS = 10
SUBFRAME_BITS = WORD_BITS * SUBFRAME_WORDS
SUBFRAME_S = 6.0
BIT_S = 1.0 / BIT_RATE
BITS_PER_WEEK = int(round(SECONDS_PER_WEEK * BIT_RATE))

# Table 20-V: SV ID of subframe 4 pages 1..25 (57 = reserved pages; 56 = iono/UTC; 63 = A-S/health)
SF4_SV_ID = (57, 25, 26, 27, 28, 57, 29, 30, 31, 32, 57, 62, 52, 53, 54, 57, 55, 56, 58, 59, 57, 60,
             61, 62, 63)
SF5_PAGE25_SV_ID = 51
FILLER_24 = 0xAAAAAA             # alternating 1010... pattern

SC = GPS_PI                      # semicircle -> rad


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


# ------------------------------------------------------------------ subframe 4 page 18: iono / UTC
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


def parse_iono_page(words):
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


# ------------------------------------------------------------------------ subframe source words
def subframe_words(sf_id, eph, tow_s, week, almanac=None, alert=0, anti_spoof=0, tlm_message=0, iono=None):
    """24-bit source words 1..10 of subframe ``sf_id`` starting at GPS TOW ``tow_s`` of the
    transmission week ``week`` (t bits of words 2 and 10 not yet solved: low 2 bits 0)."""
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


def parse_sf123(s1, s2, s3):
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
