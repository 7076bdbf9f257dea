"""LNAV encoder/decoder: parity (independent implementation + hand-computed word), encode→decode
round trip of random ephemerides, single-bit-error detection, polarity, timing of nav_bits."""

import math

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from ultratight.signals.ephemeris import Ephemeris
from ultratight.signals.lnav import (LnavDecoder, check_word, decode_bits, encode_subframe, encode_word,
                                     nav_bits, nav_bits_at, parity_bits)
from ultratight.signals.lnav_message import quantise

PI = 3.1415926535898
WEEK = 2190
TOW0 = 518400.0

# Table 20-XIV: source-bit indices of D25..D30 and whether D29* (0) or D30* (1) enters.
SPEC = [(0, (1, 2, 3, 5, 6, 10, 11, 12, 13, 14, 17, 18, 20, 23)),
        (1, (2, 3, 4, 6, 7, 11, 12, 13, 14, 15, 18, 19, 21, 24)),
        (0, (1, 3, 4, 5, 7, 8, 12, 13, 14, 15, 16, 19, 20, 22)),
        (1, (2, 4, 5, 6, 8, 9, 13, 14, 15, 16, 17, 20, 21, 23)),
        (1, (1, 3, 5, 6, 7, 9, 10, 14, 15, 16, 17, 18, 21, 22, 24)),
        (0, (3, 5, 6, 8, 9, 10, 11, 13, 15, 19, 22, 23, 24))]
# the same as a 6 x 26 parity-check matrix over (D29*, D30*, d1..d24)
H = np.zeros((6, 26), dtype=int)
for r, (star, idx) in enumerate(SPEC):
    H[r, star] = 1
    H[r, [1 + k for k in idx]] = 1


def ref_parity(d_bits, d29s, d30s):
    v = np.array([d29s, d30s] + list(d_bits), dtype=int)
    return [int(x) for x in (H @ v) % 2]


def int_bits(x, n):
    return [(x >> (n - 1 - k)) & 1 for k in range(n)]


def test_known_tlm_word():
    # TLM with preamble 10001011 and all other data bits 0, D29* = D30* = 0.  By hand from
    # Table 20-XIV (data ones at d1, d5, d7, d8): D25..D30 = 0 1 0 0 1 0.
    assert parity_bits(0x8B0000, 0, 0) == 0b010010
    assert encode_word(0x8B0000, 0, 0) == (0x8B0000 << 6) | 0b010010 == 0x22C00012
    # with D30* = 1 the data bits go out complemented and D26, D28, D29 flip
    w = encode_word(0x8B0000, 0, 1)
    assert w >> 6 == 0x8B0000 ^ 0xFFFFFF


def test_parity_matches_independent_implementation():
    rng = np.random.default_rng(3)
    for _ in range(500):
        d = int(rng.integers(0, 1 << 24))
        d29s, d30s = (int(x) for x in rng.integers(0, 2, 2))
        p = parity_bits(d, d29s, d30s)
        assert int_bits(p, 6) == ref_parity(int_bits(d, 24), d29s, d30s)
        ok, dec = check_word(encode_word(d, d29s, d30s), d29s, d30s)
        assert ok and dec == d


def semicircle_angle(lo, hi):
    return st.floats(lo, hi, allow_nan=False, allow_infinity=False)


eph_strategy = st.builds(
    Ephemeris,
    prn=st.integers(1, 32), week=st.just(WEEK),
    toe=st.integers(0, 37799).map(lambda k: 16.0 * k),
    toc=st.integers(0, 37799).map(lambda k: 16.0 * k),
    sqrt_a=st.floats(5000.0, 5400.0), e=st.floats(0.0, 0.03),
    i0=st.floats(0.85, 1.05), omega0=semicircle_angle(-math.pi, math.pi),
    omega=semicircle_angle(-math.pi, math.pi), m0=semicircle_angle(-math.pi, math.pi),
    delta_n=st.floats(-1.1e-8, 1.1e-8), idot=st.floats(-9e-10, 9e-10),
    omega_dot=st.floats(-9e-9, 0.0), cuc=st.floats(-6e-5, 6e-5), cus=st.floats(-6e-5, 6e-5),
    crc=st.floats(-1000.0, 1000.0), crs=st.floats(-1000.0, 1000.0),
    cic=st.floats(-6e-5, 6e-5), cis=st.floats(-6e-5, 6e-5),
    af0=st.floats(-9.7e-4, 9.7e-4), af1=st.floats(-3.7e-9, 3.7e-9),
    af2=st.floats(-3.5e-15, 3.5e-15), tgd=st.floats(-5.9e-8, 5.9e-8),
    iodc=st.integers(0, 1023), iode=st.integers(0, 255), sv_health=st.integers(0, 63),
    ura_index=st.integers(0, 15), fit_interval_h=st.sampled_from([4.0, 6.0]),
    code_on_l2=st.integers(0, 3), l2p_flag=st.integers(0, 1),
    aodo=st.integers(0, 31).map(lambda k: 900 * k),
)

# (field, LSB, semicircles?) from IS-GPS-200 Tables 20-I and 20-III
SCALES = [("tgd", 2 ** -31, False), ("toc", 16, False), ("af2", 2 ** -55, False),
          ("af1", 2 ** -43, False), ("af0", 2 ** -31, False), ("crs", 2 ** -5, False),
          ("delta_n", 2 ** -43, True), ("m0", 2 ** -31, True), ("cuc", 2 ** -29, False),
          ("e", 2 ** -33, False), ("cus", 2 ** -29, False), ("sqrt_a", 2 ** -19, False),
          ("toe", 16, False), ("cic", 2 ** -29, False), ("omega0", 2 ** -31, True),
          ("cis", 2 ** -29, False), ("i0", 2 ** -31, True), ("crc", 2 ** -5, False),
          ("omega", 2 ** -31, True), ("omega_dot", 2 ** -43, True), ("idot", 2 ** -43, True)]


def _subframes(eph, tows, week=WEEK):
    return np.concatenate([encode_subframe(int(t // 6) % 5 + 1, eph, t, week=week) for t in tows])


@settings(max_examples=40, deadline=None)
@given(eph=eph_strategy, inverted=st.booleans(), pm1=st.booleans())
def test_roundtrip_random_ephemeris(eph, inverted, pm1):
    eph = eph.copy(iodc=(eph.iodc & ~0xFF) | eph.iode)       # IODC 8 LSBs = IODE (valid set)
    bits = _subframes(eph, TOW0 + 6.0 * np.arange(6))        # subframes 1..5, 1
    if pm1:
        bits = 1 - 2 * bits.astype(np.int8)
    if inverted:
        bits = (-bits) if pm1 else 1 - bits
    dec = decode_bits(bits, prn=eph.prn, ref_week=WEEK + 100)
    assert dec.inverted == inverted
    assert [s.sf_id for s in dec.subframes] == [1, 2, 3, 4, 5, 1]
    assert [s.tow_s for s in dec.subframes] == list(TOW0 + 6.0 * np.arange(6))
    assert dec.bad_words == []
    assert dec.week == WEEK
    got = dec.ephemeris
    # toe more than half a week from the transmission time belongs to the neighbouring week
    dt = eph.toe - TOW0
    toe_week = WEEK + (1 if dt < -302400 else (-1 if dt > 302400 else 0))
    q = quantise(eph).copy(week=toe_week)
    assert got == q                                          # bit-exact in the quantised values
    for name, lsb, semi in SCALES:                           # and within half an LSB of the input
        scale = lsb * PI if semi else lsb
        diff = getattr(got, name) - getattr(eph, name)
        if name in ("m0", "omega0", "omega"):
            diff = (diff + math.pi) % (2 * math.pi) - math.pi
        assert abs(diff) <= 0.5 * scale * (1 + 1e-9), name
    for name in ("iodc", "iode", "sv_health", "ura_index", "code_on_l2", "l2p_flag", "aodo",
                 "fit_interval_h"):
        assert getattr(got, name) == getattr(eph, name), name


@pytest.fixture(scope="module")
def eph():
    return Ephemeris(prn=7, week=WEEK, toe=518400.0, toc=518400.0, sqrt_a=5153.6, e=0.012,
                     i0=0.96, omega0=-1.2, omega=0.8, m0=2.9, delta_n=4.5e-9, idot=-3e-10,
                     omega_dot=-8e-9, cuc=-7e-6, cus=4.5e-6, crc=300.0, crs=-140.0,
                     cic=-3e-8, cis=2e-7, af0=4.7e-4, af1=-1e-11, tgd=5e-9, iodc=39, iode=39)


def test_every_single_bit_flip_is_detected(eph):
    tows = TOW0 + 6.0 * np.arange(5)
    clean = _subframes(eph, tows)
    detected = 0
    total = 0
    for sf in (1, 2, 3):                   # flip every bit of subframes 2, 3, 4 of the stream
        for j in range(300):
            bits = clean.copy()
            pos = 300 * sf + j
            bits[pos] ^= 1
            dec = decode_bits(bits)
            hit = [s for s in dec.subframes if s.start_bit == 300 * sf]
            total += 1
            if hit and (j // 30 + 1) in hit[0].bad_words:
                detected += 1
    assert total == 900
    assert detected == total


def test_structure_tbits_and_parity_chain(eph):
    for k in range(5):
        tow = TOW0 + 6.0 * k
        bits = encode_subframe(k + 1, eph, tow)
        assert list(bits[:8]) == [1, 0, 0, 0, 1, 0, 1, 1]
        assert bits[58] == 0 and bits[59] == 0               # word 2 ends in 00
        assert bits[298] == 0 and bits[299] == 0             # word 10 ends in 00
        how = int("".join(str(b) for b in bits[30:54]), 2)   # D30* of word 1 is 0 by design?
        d30_tlm = bits[29]
        if d30_tlm:
            how ^= 0xFFFFFF
        assert how >> 7 == int(tow / 6) + 1                  # TOW count of the next subframe
        assert (how >> 2) & 7 == k + 1
        # independent parity check of every word
        prev = (0, 0)
        for w in range(10):
            D = [int(x) for x in bits[30 * w: 30 * w + 30]]
            d = [x ^ prev[1] for x in D[:24]]
            assert D[24:] == ref_parity(d, *prev)
            prev = (D[28], D[29])


def test_nav_bits_alignment_and_decoding(eph):
    n = 300 * 6
    b = nav_bits(eph, WEEK, TOW0, n)
    assert b.dtype == np.int8 and set(np.unique(b)) <= {-1, 1}
    assert list(b[:8]) == [-1, 1, 1, 1, -1, 1, -1, -1]      # preamble, logic 1 -> -1
    # bit k covers [t0 + 0.02k, ...): a start inside bit 1 gives the same bits from bit 1 on
    b2 = nav_bits(eph, WEEK, TOW0 + 0.03, n - 1)
    assert np.array_equal(b2, b[1:])
    b3 = nav_bits(eph, WEEK, TOW0 + 0.04 - 1e-12, n - 2)      # float noise at a bit edge
    assert np.array_equal(b3, b[2:])
    # a stream starting mid-subframe decodes with TOW = GPS time of each subframe's first bit
    t0 = TOW0 + 3.3
    s = nav_bits(eph, WEEK, t0, 2000)
    dec = LnavDecoder(prn=7, ref_week=WEEK)
    out = dec.feed(s[:700]) + dec.feed(s[700:])
    assert len(out) >= 5
    for sf in out:
        assert sf.tow_s == pytest.approx(t0 + 0.02 * sf.start_bit, abs=1e-9)
        assert sf.tow_s % 6.0 == 0.0
    assert dec.ephemeris == quantise(eph)
    # nav_bits_at with absolute bit indices
    k0 = int(round(TOW0 / 0.02))
    assert np.array_equal(nav_bits_at(eph, WEEK, k0 + np.arange(n)), b)


def test_week_rollover_in_stream(eph):
    e = eph.copy(toe=604800.0 - 7216.0, toc=604800.0 - 7216.0)
    t0 = 604800.0 - 12.0
    s = nav_bits(e, WEEK, t0, 300 * 6)
    dec = decode_bits(s, prn=7, ref_week=WEEK)
    assert [sf.tow_s for sf in dec.subframes][:5] == [604788.0, 604794.0, 0.0, 6.0, 12.0]
    assert [sf.sf_id for sf in dec.subframes][:5] == [4, 5, 1, 2, 3]
    assert dec.bad_words == []
    assert dec.week == WEEK + 1                      # subframe 1 sent in the new week
    assert dec.ephemeris == quantise(e)              # toe still belongs to the old week
    assert dec.ephemeris.week == WEEK
    # the same stream through nav_bits with a negative TOW in the following week
    assert np.array_equal(nav_bits(e, WEEK + 1, -12.0, 300 * 6), s)


def test_polarity_flip_midstream_is_followed(eph):
    s = nav_bits(eph, WEEK, TOW0, 300 * 7)
    r = np.concatenate((s[:900], -s[900:]))                  # half-cycle slip at a subframe edge
    dec = decode_bits(r.astype(float) * 0.7, prn=7, ref_week=WEEK)     # soft symbols
    assert [sf.inverted for sf in dec.subframes][:6] == [False] * 3 + [True] * 3
    assert [sf.tow_s for sf in dec.subframes][:6] == list(TOW0 + 6.0 * np.arange(6))
    assert dec.polarity_flips == 1
    assert dec.ephemeris == quantise(eph)


def test_almanac_page_structure(eph):
    from ultratight.signals.lnav_message import _get
    alm = {3: eph.copy(prn=3)}
    def frame_start(page):                       # first frame start after TOW0 showing `page`
        k = int(TOW0 // 30)
        return 30.0 * (k + (page - 1 - k) % 25)
    tow = frame_start(3) + 24.0                  # subframe 5 of the frame showing page 3
    bits = encode_subframe(5, eph, tow, almanac=alm)
    dec = decode_bits(np.concatenate([bits, encode_subframe(1, eph, tow + 6.0)]))
    sf = dec.subframes[0]
    assert sf.ok and sf.sf_id == 5 and sf.page == 3
    v = 0
    for w in sf.words[2:]:
        v = (v << 24) | w
    assert _get(v, 192, 0, 2) == 1 and _get(v, 192, 2, 6) == 3          # data ID 01, SV ID 3
    assert abs(_get(v, 192, 8, 16) * 2 ** -21 - eph.e) <= 2 ** -22
    assert abs(_get(v, 192, 72, 24) * 2 ** -11 - eph.sqrt_a) <= 2 ** -12
    assert abs((_get(v, 192, 32, 16, True) * 2 ** -19 + 0.30) * PI - eph.i0) <= 2 ** -20 * PI
    # subframe 4 page 18 carries SV ID 56 (Table 20-V) with the ionospheric/UTC parameters; without
    # them the generator sends it as a reserved page (SV ID 57) so that no receiver reads filler as alpha/beta
    from ultratight.signals.lnav_message import IonoUtc
    t18 = frame_start(18) + 18.0
    io = IonoUtc(alpha=(1e-8, 0.0, -6e-8, 1e-7), beta=(1e5, 0.0, -2e5, 1e5))
    for iono, sv_id in ((io, 56), (None, 57)):
        b4 = encode_subframe(4, eph, t18, iono=iono)
        d4 = decode_bits(np.concatenate([b4, encode_subframe(5, eph, t18 + 6.0)]))
        assert d4.subframes[0].ok and d4.subframes[0].page == 18
        assert (d4.subframes[0].words[2] >> 16) & 0x3F == sv_id
        assert (d4.iono is not None) == (iono is not None)


def test_random_bit_errors_are_flagged_exactly(eph):
    rng = np.random.default_rng(11)
    n_sf = 40
    clean = nav_bits(eph, WEEK, TOW0, 300 * n_sf)
    flips = rng.random(clean.size) < 3e-3
    flips[:600] = False                           # clean start so the decoder locks at bit 0
    noisy = np.where(flips, -clean, clean)
    dec = decode_bits(noisy, prn=7, ref_week=WEEK)
    ref = decode_bits(clean, prn=7, ref_week=WEEK)
    assert [s.start_bit for s in dec.subframes] == [300 * k for k in range(n_sf)]
    n_err_words = 0
    for sf, rs in zip(dec.subframes, ref.subframes):
        for w in range(10):
            lo = sf.start_bit + 30 * w
            errs = int(flips[lo:lo + 30].sum())
            prev_errs = int(flips[lo - 2:lo].sum()) if lo >= 2 else 0
            if 0 < errs < 4 and not prev_errs:
                n_err_words += 1
                assert (w + 1) in sf.bad_words
            if errs == 0 and prev_errs == 0:
                assert (w + 1) not in sf.bad_words
                assert sf.words[w] == rs.words[w]
    assert n_err_words > 20
