"""GPS CNAV messages (ultratight.signals.cnav) and the dual-frequency pseudoranges of a u-blox log
(ultratight.signals.ubx, ultratight.signals.observations).

Messages are built in the test from the field tables of IS-GPS-200 (Figures 30-1 to 30-3, Tables 30-I,
30-III, 30-IV, 20-X) with a CRC-24Q computed here by polynomial division (§30.3.5.1), decoded and compared;
the orbit of Table 30-II is checked against the LNAV orbit of Table 20-IV (ultratight.signals.ephemeris)
for a set whose CNAV-only rate terms are zero; the ionosphere-free pseudorange and the inter-signal
corrections of §30.3.3.3.1.1 against their closed forms.  On the walk_0827 log (shared data; skipped
without it): every CNAV message passes its CRC, the CNAV orbit and clock of the four satellites that also
have an LNAV ephemeris agree with it, and the type 30 group delays give the same ionosphere on every
satellite while the opposite sign convention does not."""

import math
from pathlib import Path

import numpy as np
import pytest

from ultratight.constants import C
from ultratight.signals import cnav
from ultratight.signals.ephemeris import Ephemeris, eph_params, sat_state
from ultratight.signals.observations import (
    F_L1_HZ,
    F_L2_HZ,
    F_L5_HZ,
    RawEpochs,
    iono_free_combination,
    iono_free_noise_factor,
)

PI = 3.1415926535898
WALK_UBX = Path(__file__).resolve().parents[2] / "shared" / "data" / "real-imu-gnss" / "walk_0827" / "gnss_1730.ubx"
G12 = (77.0 / 60.0) ** 2


# ------------------------------------------------------------------ a message built from the tables
def crc24q_test(bits):
    """CRC-24Q by long division of m(X)·X^24 by g(X) (coefficients i = 0,1,3,4,5,6,7,10,11,14,17,18,23,24)."""
    g = [0] * 25
    for i in (0, 1, 3, 4, 5, 6, 7, 10, 11, 14, 17, 18, 23, 24):
        g[24 - i] = 1                              # g[0] is the X^24 coefficient
    reg = [int(b) for b in bits] + [0] * 24
    for i in range(len(bits)):
        if reg[i]:
            for j in range(25):
                reg[i + j] ^= g[j]
    return reg[-24:]


def put(bits, first, length, value):
    v = int(value) & ((1 << length) - 1)            # two's complement for negative values
    for j in range(length):
        bits[first - 1 + j] = (v >> (length - 1 - j)) & 1


def build(prn, mt, tow_count, fields):
    """300 bits: preamble, PRN, type, TOW count, the (first bit, length, integer) fields, CRC."""
    bits = [0] * 300
    put(bits, 1, 8, 0b10001011)
    put(bits, 9, 6, prn)
    put(bits, 15, 6, mt)
    put(bits, 21, 17, tow_count)
    for first, length, value in fields:
        put(bits, first, length, value)
    bits[276:300] = crc24q_test(bits[:276])
    return np.array(bits, dtype=np.uint8)


# integers as broadcast (LSB units of Tables 30-I / 30-III / 30-IV / 20-X)
MT10 = {"wn": (39, 13, 2381 % 8192), "health": (52, 3, 0b001), "top": (55, 11, 1361), "ura_oe": (66, 5, -3),
        "toe": (71, 11, 1362), "delta_a": (82, 26, -3_456_789), "a_dot": (108, 25, 1234),
        "delta_n0": (133, 17, 21_000), "delta_n0_dot": (150, 23, -300), "m0": (173, 33, -2_000_000_000),
        "e": (206, 33, 85_000_000), "omega": (239, 33, 1_500_000_000)}
MT11 = {"toe": (39, 11, 1362), "omega0": (50, 33, -3_000_000_000), "i0": (83, 33, 1_300_000_000),
        "delta_omega_dot": (116, 17, -4321), "idot": (133, 15, 777), "cis": (148, 16, -55), "cic": (164, 16, 66),
        "crs": (180, 24, -4000), "crc": (204, 24, 60_000), "cus": (228, 21, 2800), "cuc": (249, 21, -3100)}
MT30 = {"top": (39, 11, 1361), "ura_oc": (50, 5, -2), "ura_oc1": (55, 3, 1), "ura_oc2": (58, 3, 2),
        "toc": (61, 11, 1362), "af0": (72, 26, -11_000_000), "af1": (98, 20, -123), "af2": (118, 10, 3),
        "tgd": (128, 13, 160), "isc_l1ca": (141, 13, -36), "isc_l2c": (154, 13, -4096), "isc_l5i5": (167, 13, 364),
        "isc_l5q5": (180, 13, 379)}
SCALE = {"wn": 1, "health": 1, "top": 300, "ura_oe": 1, "toe": 300, "delta_a": 2 ** -9, "a_dot": 2 ** -21,
         "delta_n0": 2 ** -44 * PI, "delta_n0_dot": 2 ** -57 * PI, "m0": 2 ** -32 * PI, "e": 2 ** -34,
         "omega": 2 ** -32 * PI, "omega0": 2 ** -32 * PI, "i0": 2 ** -32 * PI, "delta_omega_dot": 2 ** -44 * PI,
         "idot": 2 ** -44 * PI, "cis": 2 ** -30, "cic": 2 ** -30, "crs": 2 ** -8, "crc": 2 ** -8, "cus": 2 ** -30,
         "cuc": 2 ** -30, "ura_oc": 1, "ura_oc1": 1, "ura_oc2": 1, "toc": 300, "af0": 2 ** -35, "af1": 2 ** -48,
         "af2": 2 ** -60, "tgd": 2 ** -35, "isc_l1ca": 2 ** -35, "isc_l2c": 2 ** -35, "isc_l5i5": 2 ** -35,
         "isc_l5q5": 2 ** -35}
ALPHA = (12, -3, -60, 5)            # α0..α3 in units 2^-30, 2^-27, 2^-24, 2^-24
BETA = (70, -2, -64, 9)             # β0..β3 in units 2^11, 2^14, 2^16, 2^16


def _messages(prn=5, tow_count=68_100):
    f30 = list(MT30.values()) + [(193 + 8 * j, 8, a) for j, a in enumerate(ALPHA)] + \
        [(225 + 8 * j, 8, b) for j, b in enumerate(BETA)]
    return (build(prn, 10, tow_count, MT10.values()), build(prn, 11, tow_count + 2, MT11.values()),
            build(prn, 30, tow_count + 4, f30))


def test_crc24q_of_the_catalogue_check_string():
    """CRC-24Q (the generator of §30.3.5.1, seed 0) of ASCII "123456789" is 0xCDE703 (the polynomial's
    published check value), by the module and by the test's division."""
    bits = [(c >> (7 - j)) & 1 for c in b"123456789" for j in range(8)]
    assert cnav.crc24q(bits) == 0xCDE703
    assert int("".join(map(str, crc24q_test(bits))), 2) == 0xCDE703


def test_messages_built_from_the_tables_decode_to_their_values():
    m10, m11, m30 = (cnav.parse_message(b) for b in _messages())
    assert (m10.prn, m10.msg_type, m10.tow_s, m10.alert) == (5, 10, 68_100 * 6.0, 0)
    for table, msg in ((MT10, m10), (MT11, m11), (MT30, m30)):
        for name, (_, _, value) in table.items():
            if name == "isc_l2c":
                continue
            assert msg.fields[name] == pytest.approx(value * SCALE[name], rel=1e-15, abs=0), name
    assert m30.fields["isc_l2c"] is None                    # 1000000000000: not available
    assert m30.fields["alpha"] == pytest.approx([a * 2.0 ** e for a, e in zip(ALPHA, (-30, -27, -24, -24))])
    assert m30.fields["beta"] == pytest.approx([b * 2.0 ** e for b, e in zip(BETA, (11, 14, 16, 16))])


def test_a_damaged_message_is_refused():
    good = _messages()[0]
    for i in (0, 100, 299):                                  # preamble, a field, a CRC bit
        bad = good.copy()
        bad[i] ^= 1
        with pytest.raises(cnav.CnavError):
            cnav.parse_message(bad)
    with pytest.raises(cnav.CnavError, match="300 bits"):
        cnav.parse_message(good[:299])
    dec = cnav.CnavDecoder(5)
    bad = good.copy()
    bad[150] ^= 1
    assert dec.feed(bad) is None and dec.rejected == 1 and not dec.mt10


def test_decoder_pairs_types_10_11_and_the_clock_into_an_ephemeris():
    dec = cnav.CnavDecoder(5, ref_week=2381)
    m10, m11, m30 = _messages()
    assert dec.feed(m10) and dec.feed(m11) and not dec.ephemerides        # no clock yet
    assert dec.feed(m30)
    (e,) = dec.ephemerides
    assert (e.week, e.toe, e.toc) == (2381, 1362 * 300.0, 1362 * 300.0)
    assert e.tgd == pytest.approx(160 * 2.0 ** -35) and "isc_l2c" not in e.isc
    assert e.signal_ok("L1") and e.signal_ok("L2") and not e.signal_ok("L5") and e.healthy
    assert dec.iono[0][0] == pytest.approx(12 * 2.0 ** -30)
    assert cnav.CnavDecoder(6).feed(m10) is None                           # another satellite's message


def test_cnav_orbit_equals_the_lnav_orbit_when_its_rate_terms_are_zero():
    """Table 30-II with Ȧ = Δṅ₀ = 0 and Ω̇ = Ω̇_REF + ΔΩ̇ is Table 20-IV with A = A_REF + ΔA: the module's
    CNAV evaluation against the LNAV kernel of ultratight.signals.ephemeris (independent code), positions
    to 1 mm, velocities (central differences) to 1 mm/s, clocks to 1e-12 s."""
    kw = {"m0": 0.7, "e": 0.012, "omega": -1.1, "omega0": 2.2, "i0": 0.95, "idot": 1e-10, "cis": 1e-7, "cic": -2e-7,
          "crs": 40.0, "crc": 250.0, "cus": 5e-6, "cuc": -4e-6, "af0": 1e-4, "af1": -3e-12, "af2": 0.0}
    toe = 410400.0
    c = cnav.CnavEphemeris(prn=3, week=2381, toe=toe, toc=toe, delta_a=1234.5, a_dot=0.0, delta_n0=4e-9,
                           delta_n0_dot=0.0, delta_omega_dot=-3e-10, tgd=-5e-9, **kw)
    lnav = Ephemeris(prn=3, week=2381, toe=toe, toc=toe, sqrt_a=math.sqrt(cnav.A_REF_M + 1234.5), delta_n=4e-9,
                     omega_dot=-2.6e-9 * PI - 3e-10, tgd=-5e-9, **kw)
    t = toe + np.linspace(-5400.0, 5400.0, 13)
    p1, v1, c1, d1 = c.state(t)
    p2, v2, c2, d2 = sat_state(eph_params(lnav), t)
    assert np.max(np.abs(p1 - p2)) < 1e-3
    assert np.max(np.abs(v1 - v2)) < 1e-3
    assert np.max(np.abs(c1 - c2)) < 1e-12 and np.max(np.abs(d1 - d2)) < 1e-15
    # the rate terms act as Table 30-II says: A_k = A0 + Ȧ t_k moves the radius by Ȧ t_k (circular orbit)
    grow = cnav.CnavEphemeris(**{**c.__dict__, "a_dot": 0.01, "e": 0.0, "crs": 0.0, "crc": 0.0})
    flat = cnav.CnavEphemeris(**{**c.__dict__, "e": 0.0, "crs": 0.0, "crc": 0.0})
    dr = np.linalg.norm(grow.state(t)[0], axis=1) - np.linalg.norm(flat.state(t)[0], axis=1)
    assert np.allclose(dr, 0.01 * (t - toe), atol=1e-6)


# ------------------------------------------------------------------ combinations
def test_iono_free_combination_closed_form():
    """P1 = ρ + I and P2 = ρ + γI give ρ; the σ of the combination of two independent, equally noisy
    pseudoranges is √(γ²+1)/(γ−1) of theirs (≈ 2.98 L1/L2, 2.59 L1/L5), also by simulation (fixed seed)."""
    rho, iono = 2.2e7 + 123.456, np.array([0.0, 3.0, 17.5])
    for f2 in (F_L2_HZ, F_L5_HZ):
        g = (F_L1_HZ / f2) ** 2
        assert np.allclose(iono_free_combination(rho + iono, rho + g * iono, f2), rho, atol=1e-6)
    assert iono_free_noise_factor(F_L2_HZ) == pytest.approx(2.978, abs=1e-3)
    assert iono_free_noise_factor(F_L5_HZ) == pytest.approx(2.588, abs=1e-3)
    assert iono_free_noise_factor(0.0) == 1.0 and iono_free_noise_factor(float("nan")) == 1.0
    rng = np.random.default_rng(7)
    n1, n2 = rng.normal(0.0, 1.0, (2, 200_000))
    assert np.std(iono_free_combination(n1, n2, F_L2_HZ)) == pytest.approx(2.978, rel=0.01)


def test_inter_signal_corrections_follow_is_gps_200():
    """Pseudoranges with the group delays of §30.3.3.3.1.1.1 (the L1 C/A signal leaves ISC_L1C/A before
    L1 P(Y), L1 P(Y) T_GD after the clock's reference, L2C ISC_L2C before L1 P(Y)) and an ionosphere:
    after ubx.iono_free_rows the pseudorange is the range minus the L1 C/A user's clock c(Δt − T_GD),
    as obs_geometry predicts it (the combination of §30.3.3.3.1.1.2 plus c·T_GD)."""
    from ultratight.signals.ubx import iono_free_rows
    rho, dt_sv, tgd, isc1, isc2, iono = 2.1e7, 1.2e-4, -8.4e-9, -0.2e-9, 5.6e-9, 6.3
    p1 = rho - C * dt_sv + C * (tgd - isc1) + iono
    p2 = rho - C * dt_sv + C * (tgd - isc2) + G12 * iono
    raw = RawEpochs(t=np.array([1.0e9]), start=np.array([0, 2]), prn=np.array([23, 10]), pr_m=np.array([p1, p1]),
                    doppler_hz=np.zeros(2), cn0_dbhz=np.full(2, 45.0), phase_cyc=np.full(2, np.nan))
    out = iono_free_rows(raw, {"L2C": np.array([p2, np.nan]), "L5": np.full(2, np.nan)},
                         {23: {"tgd": tgd, "isc_l1ca": isc1, "isc_l2c": isc2}}, {})
    assert out.prn.tolist() == [23] and out.start.tolist() == [0, 1]           # no L2C: the row is dropped
    assert out.pr_m[0] == pytest.approx(rho - C * (dt_sv - tgd), abs=1e-6)
    assert out.iono_free_f2_hz[0] == F_L2_HZ and out.pr_l1_m[0] == p1
    # a satellite whose CNAV type 10 marks L2 bad keeps no combined row
    bad = iono_free_rows(raw, {"L2C": np.array([p2, p2]), "L5": np.full(2, np.nan)}, {}, {23: 0b010})
    assert bad.prn.tolist() == [10]


# ------------------------------------------------------------------ the real log
@pytest.fixture(scope="module")
def walk():
    if not WALK_UBX.exists():
        pytest.skip(f"shared data not found: {WALK_UBX}")
    pytest.importorskip("pyubx2", reason="pyubx2 not installed")
    from ultratight.signals.ubx import read_ubx
    return read_ubx(WALK_UBX, signals="l1")


def test_every_cnav_message_of_the_log_passes_its_crc(walk):
    """148 L2 CM / L5 I messages; types 10, 11, 30, 32, 33 of seven satellites; each satellite's types
    10 + 11 + 30 arrive within the 134 s."""
    nav = walk.raw.meta["navigation"]
    assert nav["cnav_messages"] == 148 and nav["cnav_rejected"] == 0
    assert sorted(walk.cnav) == [8, 10, 18, 23, 24, 27, 32]
    for dec in walk.cnav.values():
        assert set(dec.types) <= {10, 11, 30, 32, 33} and len(dec.ephemerides) == 1
    assert nav["lnav_ephemeris_prns"] == [10, 23, 27, 32] and nav["cnav_ephemeris_prns"] == [8, 18, 24]
    assert nav["klobuchar"] == "CNAV type 30"


def test_cnav_orbits_of_the_log_agree_with_its_lnav_orbits(walk):
    """PRN 10, 23, 27, 32: CNAV (toe 408600 s) and LNAV (toe 410400 s) sets of the same satellites over the
    log's 134 s.  Measured: positions 0.05–0.82 m apart, clocks 1–6 cm, velocities 0.2 mm/s; bound: the
    broadcast's accuracy (URA index of the sets: 2.4–3.4 m), 1.5 m and 0.3 m for the clock."""
    t = 408640.0 + np.arange(0.0, 140.0, 10.0)
    for prn in (10, 23, 27, 32):
        (lnav,), (cn,) = walk.nav.ephemerides[prn], walk.cnav[prn].ephemerides
        pl, vl, cl, _ = sat_state(eph_params(lnav), t)
        pc, vc, cc, _ = cn.state(t)
        assert np.max(np.linalg.norm(pl - pc, axis=1)) < 1.5, prn
        assert np.max(np.abs(C * (cl - cc))) < 0.3, prn
        assert np.max(np.linalg.norm(vl - vc, axis=1)) < 1e-3, prn
        assert cn.tgd == pytest.approx(lnav.tgd, abs=2.0 ** -35)       # T_GD: LNAV 2^-31 s, CNAV 2^-35 s LSB


def test_group_delays_of_the_log_give_one_ionosphere(walk):
    """The ionosphere from L2C − L1 C/A with the type 30 group delays (the test's closed form:
    P2 − P1 = (γ−1) I + c(ISC_L1C/A − ISC_L2C)) is the same vertical delay on every satellite above 30°
    (the Klobuchar obliquity 1 + 16(0.53 − E)³ removes the elevation): measured spread (max − min) 1.6 m;
    with the ISCs' sign reversed 6.5 m (the receiver's own L1/L2 bias is common to all satellites)."""
    from ultratight.fusion.gins.tight_meas import TightMeasurements
    raw, p2 = walk.raw, _l2c(walk)
    m = TightMeasurements(raw, walk.nav, iono="off", mask_deg=30.0)
    r = m.rows(0, np.array([-1276965.25, -4717231.73, 4087230.15]), np.zeros(3), 0.0, 0.0)
    vert = {+1: [], -1: []}
    for prn, el in zip(r.prn, r.elev_rad):
        g = walk.group_delays[int(prn)]
        sel = (raw.prn == prn) & np.isfinite(p2)
        d = np.median(p2[sel] - raw.pr_m[sel])
        f = 1.0 + 16.0 * (0.53 - el / math.pi) ** 3
        for s in (+1, -1):
            vert[s].append((d - s * C * (g["isc_l1ca"] - g["isc_l2c"])) / (G12 - 1.0) / f)
    assert len(vert[1]) == 6
    assert np.ptp(vert[1]) < 2.0 and np.ptp(vert[-1]) > 2.0 * np.ptp(vert[1])


def _l2c(log):
    """L2C pseudoranges beside the L1 C/A rows (the reader keeps them; NaN without L2C)."""
    return log.pr2["L2C"]
