"""Where the walk_0827 reference track sits against the broadcast orbits, from Galileo alone.

The tight solution on the walk's GPS pseudoranges and the project's own single-point solutions sit
6-7 m from the RTK track (tests/test_integrate_tight_walk.py, docs/gins-tight.md).  This test puts the
same question to another constellation, decoded here in the test and nowhere in the package (the package
positions with GPS only): Galileo E1-B I/NAV pages of the log's RXM-SFRBX (even and odd half-pages, CRC-24Q
over their 196 bits; word types 1-5 after the Galileo OS SIS ICD, Issue 2.0, §4.3.5: ephemeris, clock,
BGD), the E1-C / E5a-Q ionosphere-free pseudoranges with the I/NAV clock moved to the E1/E5a pair by the
two broadcast group delays (ICD §5.1.5: Δt(E1,E5a) = Δt(E1,E5b) − BGD(E1,E5b) + BGD(E1,E5a)), and one
weighted least-squares fix per fixed reference epoch (the σ of ultratight.fusion.gins.tight_meas with
the E1/E5a noise factor; orbits through ultratight.signals.ephemeris with the mean
motion moved from GPS's GM to Galileo's, 3.986004418e14 m³/s²; GST seconds of week equal GPS's).

Measured (2026-11-27): six or seven satellites per fix, post-fit RMS 0.4-1.0 m on four of them (5-6 m on
the three weak ones, which the C/N0 weighting discounts), and a mean offset of the fixes from the RTK
track of (E, N, U) = (+4.86, +4.45, −2.21) m: 6.6 m horizontally,
as GPS's L1/L2C combination gives (+6.3, +2.1, −1.7 m).  Two constellations with their own orbits, clocks
and group delays agree that the RTK track (the receiver's own fixed solution, relative to its base) is
offset by 6-7 m from the broadcast frame: no GNSS-only absolute solution of this log comes closer to it."""

import math
from pathlib import Path

import numpy as np
import pytest

from ultratight.constants import C
from ultratight.signals.cnav import crc24q, field_value
from ultratight.signals.ephemeris import Ephemeris
from ultratight.signals.observations import F_L5_HZ, RawEpochs, iono_free_combination
from ultratight.signals.rinex import NavData

WALK = Path(__file__).resolve().parents[2] / "shared" / "data" / "real-imu-gnss" / "walk_0827"
PI = 3.1415926535898
GM_GAL, GM_GPS = 3.986004418e14, 3.986005e14
GAL, E1C, E1B, E5AQ = 2, 0, 1, 4
WEEK = 2381


def _scan(path):
    """(page words by satellite and word type, rows of (t, sv, sig, pr, C/N0)) of the log's Galileo messages."""
    from pyubx2 import UBXReader
    words, rows = {}, []
    with open(path, "rb") as fh:
        for _, m in UBXReader(fh, protfilter=2):
            if m.identity == "RXM-SFRBX" and m.gnssId == GAL and m.sigId == E1B and m.numWords == 8:
                bits = np.array([(getattr(m, f"dwrd_{k:02d}") >> (31 - j)) & 1 for k in range(1, 9)
                                 for j in range(32)], dtype=np.uint8)
                even, odd = bits[:120], bits[128:248]
                if even[0] != 0 or odd[0] != 1 or even[1] != 0:
                    continue                                 # not a nominal even/odd page pair
                if crc24q(np.concatenate([even[:114], odd[:82]])) != field_value(odd, 83, 24):
                    continue
                word = np.concatenate([even[2:114], odd[2:18]])
                words.setdefault(int(m.svId), {})[field_value(word, 1, 6)] = word
            elif m.identity == "RXM-RAWX":
                t = m.week * 604800.0 + m.rcvTow
                for i in range(1, m.numMeas + 1):
                    s = f"_{i:02d}"
                    if getattr(m, "gnssId" + s) == GAL and getattr(m, "prValid" + s):
                        rows.append((t, getattr(m, "svId" + s), getattr(m, "sigId" + s), getattr(m, "prMes" + s),
                                     getattr(m, "cno" + s)))
    return words, rows


def _ephemeris(sv, w):
    """Ephemeris (GPS form, Galileo GM folded into Δn, T_GD 0) and (BGD E1/E5a, BGD E1/E5b) of word types 1-5."""
    def s(word, first, n, scale):
        return field_value(word, first, n, True) * scale

    def u(word, first, n, scale=1.0):
        return field_value(word, first, n) * scale
    w1, w2, w3, w4, w5 = (w[k] for k in (1, 2, 3, 4, 5))
    assert len({u(x, 7, 10) for x in (w1, w2, w3, w4)}) == 1          # one IODnav
    sqrt_a = u(w1, 95, 32, 2.0 ** -19)
    a = sqrt_a ** 2
    eph = Ephemeris(prn=sv, week=WEEK, toe=u(w1, 17, 14, 60.0), toc=u(w4, 55, 14, 60.0), sqrt_a=sqrt_a,
                    e=u(w1, 63, 32, 2.0 ** -33), m0=s(w1, 31, 32, 2.0 ** -31 * PI),
                    omega0=s(w2, 17, 32, 2.0 ** -31 * PI), i0=s(w2, 49, 32, 2.0 ** -31 * PI),
                    omega=s(w2, 81, 32, 2.0 ** -31 * PI), idot=s(w2, 113, 14, 2.0 ** -43 * PI),
                    omega_dot=s(w3, 17, 24, 2.0 ** -43 * PI),
                    delta_n=s(w3, 41, 16, 2.0 ** -43 * PI) + math.sqrt(GM_GAL / a ** 3) - math.sqrt(GM_GPS / a ** 3),
                    cuc=s(w3, 57, 16, 2.0 ** -29), cus=s(w3, 73, 16, 2.0 ** -29), crc=s(w3, 89, 16, 2.0 ** -5),
                    crs=s(w3, 105, 16, 2.0 ** -5), cic=s(w4, 23, 16, 2.0 ** -29), cis=s(w4, 39, 16, 2.0 ** -29),
                    af0=s(w4, 69, 31, 2.0 ** -34), af1=s(w4, 100, 21, 2.0 ** -46), af2=s(w4, 121, 6, 2.0 ** -59),
                    tgd=0.0, iode=int(u(w1, 7, 10)), fit_interval_h=4.0)
    assert u(w4, 17, 6) == sv and u(w5, 74, 12) == WEEK - 1024              # SVID, GST week
    return eph, (s(w5, 48, 10, 2.0 ** -32), s(w5, 58, 10, 2.0 ** -32))


@pytest.fixture(scope="module")
def galileo():
    if not (WALK / "gnss_1730.ubx").is_file():
        pytest.skip(f"walk_0827 data not found in {WALK}")
    pytest.importorskip("pyubx2", reason="pyubx2 not installed")
    words, rows = _scan(WALK / "gnss_1730.ubx")
    ephs, bgd = {}, {}
    for sv, w in words.items():
        if all(k in w for k in (1, 2, 3, 4, 5)):
            eph, bgd[sv] = _ephemeris(sv, w)
            ephs[sv] = [eph]
    by_epoch = {}
    for t, sv, sig, pr, cn0 in rows:
        by_epoch.setdefault(round(t, 4), {}).setdefault(sv, {})[sig] = (pr, cn0)
    t_, start, prn, pr_if, cn0_e1 = [], [0], [], [], []
    for t in sorted(by_epoch):
        for sv, p in sorted(by_epoch[t].items()):
            if sv in ephs and E1C in p and E5AQ in p:
                prn.append(sv)
                pr_if.append(float(iono_free_combination(p[E1C][0], p[E5AQ][0], F_L5_HZ))
                             - C * (bgd[sv][1] - bgd[sv][0]))
                cn0_e1.append(float(p[E1C][1]))
        t_.append(t)
        start.append(len(prn))
    raw = RawEpochs(t=np.array(t_), start=np.array(start), prn=np.array(prn), pr_m=np.array(pr_if),
                    doppler_hz=np.full(len(prn), np.nan), cn0_dbhz=np.array(cn0_e1),
                    iono_free_f2_hz=np.full(len(prn), F_L5_HZ))
    return raw, NavData(path="galileo", version=3.0, ephemerides=ephs), bgd


def test_galileo_alone_sees_the_rtk_track_offset(galileo):
    from ultratight.fusion.gins.tight_meas import TightMeasurements
    from ultratight.ins.earth import dcm_ecef_from_enu, llh_to_ecef
    from ultratight.receiver.io.solution_files import read_pos
    raw, nav, bgd = galileo
    assert sorted(nav.ephemerides) == [7, 8, 13, 14, 26, 29, 33]
    assert all(abs(b) < 10e-9 for pair in bgd.values() for b in pair)       # ns-level group delays
    ref = read_pos(WALK / "gnss_1730_sf.pos")
    meas = TightMeasurements(raw, nav, iono="off")
    err, post = [], {}
    for k in range(raw.n_epochs):
        j = np.flatnonzero((np.abs(ref.t - raw.t[k]) < 0.01) & (ref.quality == 1))
        if j.size == 0:
            continue
        lat, lon, h = ref.llh[j[0]]
        x = np.asarray(llh_to_ecef(lat, lon, h - 21.39))
        fix = meas.spp(k, x)
        assert fix.ok
        err.append(dcm_ecef_from_enu(lat, lon).T @ (fix.pos_e - x))
        r = meas.rows(k, fix.pos_e, np.zeros(3), fix.clk_m, 0.0)
        for p, v in zip(r.prn, r.dz_pr):
            post.setdefault(int(p), []).append(v)
    err = np.array(err)
    mean = err.mean(axis=0)
    print(f"\nGalileo E1/E5a fixes at {len(err)} fixed epochs: mean offset from the RTK track E {mean[0]:+.2f} "
          f"N {mean[1]:+.2f} U {mean[2]:+.2f} m; post-fit RMS per satellite "
          + ", ".join(f"E{p:02d} {np.sqrt(np.mean(np.square(v))):.2f}" for p, v in sorted(post.items())))
    assert len(err) == 349
    assert sorted(np.sqrt(np.mean(np.square(v))) for v in post.values())[3] < 1.0
    assert 5.5 < math.hypot(mean[0], mean[1]) < 8.0
    assert abs(mean[0] - 4.86) < 1.0 and abs(mean[1] - 4.45) < 1.0
