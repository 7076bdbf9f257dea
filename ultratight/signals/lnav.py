"""GPS LNAV (L1 C/A legacy navigation message) bit stream, IS-GPS-200D §20.3 (see
docs/references.md): parity, encoding of subframes into transmitted bits, the bits by GPS time
(with the data modes a receiver cannot re-encode) and the streaming decoder.  What the words carry
(fields, scale factors, pages) is in :mod:`ultratight.signals.lnav_message`.

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

The decoder keeps the latest subframe 4 page 18 (ionospheric / UTC parameters) it reads with good
parity in ``LnavDecoder.iono``.
"""

from dataclasses import dataclass

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from ultratight.constants import SECONDS_PER_WEEK
from ultratight.errors import NavDataError
from ultratight.signals.gpstime import full_week, normalize
from ultratight.signals.lnav_message import (BIT_S, BITS_PER_WEEK, PREAMBLE, SUBFRAME_BITS, SUBFRAME_S,
                                             SUBFRAME_WORDS, WORD_BITS, ints_to_eph, parse_iono_page,
                                             parse_sf123, subframe_words)

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


# ------------------------------------------------------------------------------- encoding
def encode_subframe(sf_id, eph, tow_s, week=None, almanac=None, alert=0, anti_spoof=0,
                    tlm_message=0, iono=None):
    """300 transmitted bits (uint8 0/1) of the subframe that starts at GPS TOW ``tow_s``.

    ``tow_s`` must be a multiple of 6 s; ``week`` is the transmission week (default eph.week; only
    its 10 LSBs are sent).  Raises NavDataError when a parameter does not fit its field."""
    if abs(tow_s / SUBFRAME_S - round(tow_s / SUBFRAME_S)) > 1e-9:
        raise NavDataError(f"LNAV subframe start tow_s = {tow_s} is not a multiple of 6 s")
    if week is None:
        week = eph.week
    words = subframe_words(int(sf_id), eph, tow_s, int(week), almanac, alert, anti_spoof, tlm_message, iono)
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
            words = subframe_words(sf_id, eph, tow, w, almanac, iono=iono)
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
        n_start = n - 2 * WORD_BITS + 1
        if n_start <= 0:
            return None, None, False
        # the starts whose 8 bits are the preamble, upright or inverted, in order
        win = sliding_window_view(b[:n_start + 7], 8)
        upright = (win == pre).all(axis=1)
        inverted = (win == 1 - pre).all(axis=1)
        for i in np.flatnonzero(upright | inverted).tolist():
            inv = 0 if upright[i] else 1
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
            self.iono = parse_iono_page(words)
        return sf

    def _try_ephemeris(self):
        if not all(k in self._sf for k in (1, 2, 3)):
            return
        s1, s2, s3 = (self._sf[k].words for k in (1, 2, 3))
        ints, wn = parse_sf123(s1, s2, s3)
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


def decode_bits(bits, prn=0, ref_week=None):
    """Decode a whole bit stream at once; returns the :class:`LnavDecoder` after feeding it."""
    dec = LnavDecoder(prn=prn, ref_week=ref_week)
    dec.feed(bits)
    return dec
