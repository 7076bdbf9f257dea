"""RTKLIB's single-point solutions of the walk_0827 log against its RTK track (the broadcast-frame offset).

The project's single-point solutions of this log (GPS L1 C/A + L2C ionosphere-free, seven satellites;
Galileo E1/E5a in tests/test_walk_reference.py) sit 6.6 m horizontally from the RTK track.  Here the same
question goes to another implementation, RTKLIB 2.4.3 b34 through pyrtklib: its own u-blox decoder
(``input_ubxf``: RXM-RAWX observations, RXM-SFRBX ephemerides), its broadcast orbits and clocks, its
Saastamoinen troposphere and its ``pntpos`` least squares, one fix per RAWX epoch, 10° elevation mask.

What RTKLIB can take from this log: four GPS LNAV ephemerides (PRNs 10, 23, 27, 32; the other satellites'
subframe 1 is not in the 134 s, and RTKLIB does not decode CNAV); GPS L1 C/A and L2C, Galileo E1 (E5a,
E6 and this receiver's BeiDou signals have no RTKLIB b34 signal code); no Klobuchar coefficients (no
subframe 4 page 18).  The decoder takes an 8-word Galileo RXM-SFRBX page for an E5b I/NAV page and skips
it, and this receiver sends E1-B I/NAV pages as 8 words: each E1-B page is handed over with a zero ninth
word (its even/odd halves, CRC-24Q and word types are then RTKLIB's to check), which gives five Galileo
ephemerides (E07, E13, E26, E29, E33; E08 and E14, which the project's decoder completes, are not
completed by RTKLIB's within the 134 s).

The reference: the .pos file is the receiver's NAV-PVT (same latitude, longitude, hMSL; time iTOW − 1
ms); all 536 NAV-PVT epochs are carrier solutions (349 fixed, 187 float, none without carrier), so the
receiver's own non-RTK position cannot be compared.  Its heights are above mean sea level: NAV-PVT's
height − hMSL = −21.387 m, so ellipsoidal = .pos height − 21.387 m.  Fixes are compared with the fixed
track linearly interpolated to the fix's GPS time.

Measured (2026-11-27), mean ENU of RTKLIB minus the RTK track over 347 fixed epochs, (scatter):
  * GPS L1 C/A + L2C ionosphere-free (IONOOPT_IFLC, 4 satellites, no redundancy): (+7.37, +0.26, −2.82) m,
    7.38 m horizontally (σ 1.57, 2.13, 7.34 m);
  * GPS + Galileo L1 C/A + E1, no ionosphere model (9 satellites): (+5.67, +5.65, +7.75) m, 8.00 m
    horizontally (σ 1.24, 0.78, 4.24 m); the unmodelled ionosphere lifts the height by 8-10 m and
    moves the fix 1.0-1.6 m north (RTKLIB with no ionosphere model, GPS L1 C/A of the four satellites:
    (+7.18, +4.06, +5.39) m, Galileo E1 alone: (+4.68, +5.48, +8.18) m; ionosphere-free, (+6.49, +2.46,
    −3.11) m below and the project's Galileo E1/E5a (+4.86, +4.45, −2.21) m).
RTKLIB's ionosphere-free row is the P(Y) combination: it takes no CNAV inter-signal corrections and
no T_GD, which the project applies (IS-GPS-200 §30.3.3.3.1.1).  Folded into RTKLIB's pseudoranges,
those four satellites' corrections (−1.10, −0.25, −0.61, +0.38 m) move its mean by (−0.88, +2.20,
−0.29) m to (+6.49, +2.46, −3.11) m, and RTKLIB's fixes then equal the project's single-point fixes of
the same four satellites to 0.3 mm at every epoch.  So an independent implementation sees the RTK
track 6.5-8 m from where the broadcast orbits put the antenna, east to north-east, as the project does."""

import datetime
import math
import struct

import numpy as np
import pytest
from conftest import SHARED_DATA

WALK = SHARED_DATA / "real-imu-gnss" / "walk_0827"
GPS_LNAV_PRNS = [10, 23, 27, 32]
GAL_INAV_PRNS = [7, 13, 26, 29, 33]
GPS_EPOCH = datetime.datetime(1980, 1, 6)
C = 299792458.0
GAMMA_L1_L2 = (1575.42 / 1227.60) ** 2
PROJECT_GPS_ENU = (6.3, 2.1)          # docs/gins-tight.md: L1/L2C single point minus RTK track, E and N (m)
PROJECT_GAL_ENU = (4.86, 4.45)        # tests/test_walk_reference.py: Galileo E1/E5a, E and N (m)


def _frames(data):
    """(start, class-id bytes, payload) of each UBX frame with a valid checksum."""
    i = 0
    while i + 8 <= len(data):
        if data[i] != 0xB5 or data[i + 1] != 0x62:
            i += 1
            continue
        n = struct.unpack_from("<H", data, i + 4)[0]
        end = i + 6 + n
        if end + 2 > len(data):
            return
        if _checksum(data[i + 2:end]) == data[end:end + 2]:
            yield i, data[i + 2:i + 4], data[i + 6:end]
            i = end + 2
        else:
            i += 1


def _checksum(body):
    a = b = 0
    for x in body:
        a = (a + x) & 0xFF
        b = (b + a) & 0xFF
    return bytes((a, b))


def _pad_galileo_e1b(data):
    """The log with every Galileo E1-B RXM-SFRBX page (gnssId 2, sigId 1, 8 words) given a zero ninth
    word, the layout RTKLIB b34's decoder reads as E1-B I/NAV; (bytes, pages padded)."""
    out, last, n = bytearray(), 0, 0
    for start, ident, pay in _frames(data):
        if ident == b"\x02\x13" and pay[0] == 2 and pay[2] == 1 and pay[4] == 8:
            body = bytearray(b"\x02\x13" + struct.pack("<H", len(pay) + 4) + pay + bytes(4))
            body[8] = 9                                          # numWords
            out += data[last:start] + b"\xb5\x62" + body + _checksum(body)
            last = start + 8 + len(pay)
            n += 1
    out += data[last:]
    return bytes(out), n


def _nav_pvt(data):
    """NAV-PVT rows (iTOW s, carrSoln, lat deg, lon deg, height m, hMSL m)."""
    rows = []
    for _, ident, p in _frames(data):
        if ident == b"\x01\x07" and len(p) >= 40:
            lon, lat, h, hmsl = struct.unpack_from("<iiii", p, 24)
            rows.append((struct.unpack_from("<I", p, 0)[0] * 1e-3, p[21] >> 6, lat * 1e-7, lon * 1e-7,
                         h * 1e-3, hmsl * 1e-3))
    return np.array(rows)


def _read_pos(path):
    """(t GPS s, lat deg, lon deg, height m, Q) rows of an RTKLIB .pos file with GPST date and time."""
    rows = []
    for line in path.read_text().splitlines():
        if line.startswith("%") or not line.strip():
            continue
        f = line.split()
        t = datetime.datetime.strptime(f[0] + " " + f[1], "%Y/%m/%d %H:%M:%S.%f")
        rows.append([(t - GPS_EPOCH).total_seconds()] + [float(x) for x in f[2:6]])
    return np.array(rows)


def _ecef(lat, lon, h):
    a, f = 6378137.0, 1.0 / 298.257223563
    e2 = f * (2.0 - f)
    la, lo = math.radians(lat), math.radians(lon)
    n = a / math.sqrt(1.0 - e2 * math.sin(la) ** 2)
    return np.array([(n + h) * math.cos(la) * math.cos(lo), (n + h) * math.cos(la) * math.sin(lo),
                     (n * (1.0 - e2) + h) * math.sin(la)])


def _enu_rows(lat, lon):
    la, lo = math.radians(lat), math.radians(lon)
    return np.array([[-math.sin(lo), math.cos(lo), 0.0],
                     [-math.sin(la) * math.cos(lo), -math.sin(la) * math.sin(lo), math.cos(la)],
                     [math.cos(la) * math.cos(lo), math.cos(la) * math.sin(lo), math.sin(la)]])


@pytest.fixture(scope="module")
def walk(tmp_path_factory):
    """pyrtklib, the padded log's path, RTKLIB's navigation data (the decoder that holds it), its
    decoder counts, the .pos rows, the NAV-PVT rows and the number of padded pages."""
    if not (WALK / "gnss_1730.ubx").is_file() or not (WALK / "gnss_1730_sf.pos").is_file():
        pytest.skip(f"walk_0827 data not found in {WALK}")
    p = pytest.importorskip("pyrtklib", reason="pyrtklib (RTKLIB binding, test dependency) not installed")
    data = (WALK / "gnss_1730.ubx").read_bytes()
    padded, n_pad = _pad_galileo_e1b(data)
    path = tmp_path_factory.mktemp("rtklib") / "gnss_1730_e1b9.ubx"
    path.write_bytes(padded)
    raw = p.raw_t()
    assert p.init_raw(raw, p.STRFMT_UBX) == 1
    fw = p.FileWrapper(str(path), "rb")
    counts = {}
    while (s := p.input_ubxf(raw, fw)) != -2:
        counts[s] = counts.get(s, 0) + 1
    return p, path, raw, counts, _read_pos(WALK / "gnss_1730_sf.pos"), _nav_pvt(data), n_pad


def _fixes(walk, navsys, ionoopt, shift_m=None):
    """RTKLIB pntpos fix of every RAWX epoch: rows (GPS s, x, y, z, satellites).  ``shift_m``: metres
    added to both GPS pseudoranges of a satellite (by PRN) before the fix."""
    p, path, raw_nav = walk[0], walk[1], walk[2]
    opt = p.prcopt_t()
    opt.mode, opt.navsys, opt.elmin = p.PMODE_SINGLE, navsys, math.radians(10.0)
    opt.ionoopt, opt.tropopt, opt.sateph = ionoopt, p.TROPOPT_SAAS, p.EPHOPT_BRDC
    opt.nf, opt.maxgdop, opt.niter = 2, 30.0, 1
    for k, v in enumerate((100.0, 0.003, 0.003, 0.0, 1.0)):          # RTKLIB's default code error model
        opt.err[k] = v
    for k, v in enumerate((100.0, 100.0, 0.0)):
        opt.eratio[k] = v
    raw = p.raw_t()
    assert p.init_raw(raw, p.STRFMT_UBX) == 1
    fw = p.FileWrapper(str(path), "rb")
    sol, ssat, msg, week = p.sol_t(), p.Arr1Dssat_t(p.MAXSAT), p.Arr1Dchar(128), p.Arr1Dint(1)
    out = []
    while (s := p.input_ubxf(raw, fw)) != -2:
        if s != 1:
            continue
        n = raw.obs.n
        if shift_m:
            for i in range(n):
                o = raw.obs.data[i]
                d = shift_m.get(int(o.sat))                            # RTKLIB numbers GPS PRN n as n
                for j in (0, 1):
                    if d is not None and o.P[j] != 0.0:
                        o.P[j] = o.P[j] + d
        if p.pntpos(raw.obs.data.ptr, n, raw_nav.nav, opt, sol, p.Arr1Ddouble(2 * n), ssat.ptr, msg):
            tow = p.time2gpst(sol.time, week)
            out.append((week[0] * 604800.0 + tow, sol.rr[0], sol.rr[1], sol.rr[2], sol.ns))
    p.free_raw(raw)
    return np.array(out)


def _offsets(fixes, ref, sep_m):
    """ENU of each fix minus the fixed RTK track interpolated to its time (both neighbours fixed, ≤ 0.3 s
    apart), the track's heights made ellipsoidal with ``sep_m``."""
    err = []
    for t, x, y, z, _ in fixes:
        j = int(np.searchsorted(ref[:, 0], t))
        if j == 0 or j >= len(ref) or ref[j - 1, 4] != 1 or ref[j, 4] != 1 or ref[j, 0] - ref[j - 1, 0] > 0.3:
            continue
        w = (t - ref[j - 1, 0]) / (ref[j, 0] - ref[j - 1, 0])
        lat, lon, h = (1.0 - w) * ref[j - 1, 1:4] + w * ref[j, 1:4]
        err.append(_enu_rows(lat, lon) @ (np.array([x, y, z]) - _ecef(lat, lon, h + sep_m)))
    return np.array(err)


def _separation(walk):
    pvt = walk[5]
    return float(np.mean(pvt[:, 4] - pvt[:, 5]))


def test_reference_is_the_receivers_carrier_solution_above_msl(walk):
    """The .pos track is NAV-PVT: same position and hMSL, time iTOW − 1 ms, Q 1/2 = carrSoln 2/1; no
    NAV-PVT epoch without carrier (so no receiver standalone fix to compare); height − hMSL = −21.387 m."""
    ref, pvt = walk[4], walk[5]
    assert len(ref) == len(pvt) == 536
    assert np.allclose((ref[:, 0] % 604800.0) - pvt[:, 0], -0.001, atol=2e-6)
    assert np.max(np.abs(ref[:, 1:3] - pvt[:, 2:4])) < 1e-9 and np.max(np.abs(ref[:, 3] - pvt[:, 5])) < 1e-6
    assert np.array_equal(np.where(pvt[:, 1] == 2, 1, 2), ref[:, 4])
    assert int(np.sum(pvt[:, 1] == 2)) == 349 and int(np.sum(pvt[:, 1] == 1)) == 187
    assert not np.any(pvt[:, 1] == 0)
    sep = pvt[:, 4] - pvt[:, 5]
    assert -21.3885 < sep.min() <= sep.max() < -21.3865


def test_rtklib_decodes_the_logs_ephemerides(walk):
    """RTKLIB's decoder on the log: 536 observation epochs, the four GPS LNAV and (with the E1-B pages in
    nine words) five Galileo I/NAV ephemerides, no Klobuchar coefficients."""
    p, _, raw, counts, _, _, n_pad = walk
    sats = sorted(int(raw.nav.eph[i].sat) for i in range(raw.nav.n) if raw.nav.eph[i].sat)
    gps = [s for s in sats if s <= 32]
    gal = [s - p.satno(p.SYS_GAL, 1) + 1 for s in sats if p.satsys(s, p.Arr1Dint(1)) == p.SYS_GAL]
    assert counts[1] == 536 and n_pad == 396
    assert gps == GPS_LNAV_PRNS and gal == GAL_INAV_PRNS
    assert all(v == 0.0 for v in list(raw.nav.ion_gps)[:8])


def test_rtklib_gps_iono_free_sees_the_offset(walk):
    """GPS L1 C/A + L2C ionosphere-free: measured (+7.37, +0.26, −2.82) m, 7.38 m horizontally.  Bounds:
    ±1 m on the horizontal offset and its east part, north within ±1.3 m; against the project's L1/L2C
    offset (+6.3, +2.1) the measured difference is 2.13 m (the inter-signal corrections, next test):
    bound 2.6 m."""
    p = walk[0]
    fixes = _fixes(walk, p.SYS_GPS, p.IONOOPT_IFLC)
    err = _offsets(fixes, walk[4], _separation(walk))
    m, sd = err.mean(axis=0), err.std(axis=0)
    print(f"\nRTKLIB GPS L1/L2C IF: {len(fixes)} fixes, {len(err)} on fixed epochs, median "
          f"{np.median(fixes[:, 4]):.0f} satellites; mean ENU {np.round(m, 2)} m "
          f"({math.hypot(m[0], m[1]):.2f} m), σ {np.round(sd, 2)} m")
    assert len(fixes) >= 520 and len(err) >= 340 and np.all(fixes[:, 4] == 4)
    assert 6.4 < math.hypot(m[0], m[1]) < 8.4 and 6.4 < m[0] < 8.4 and abs(m[1]) < 1.3
    assert math.hypot(m[0] - PROJECT_GPS_ENU[0], m[1] - PROJECT_GPS_ENU[1]) < 2.6


def test_rtklib_gps_galileo_single_frequency_sees_the_offset(walk):
    """GPS + Galileo L1 C/A + E1, no ionosphere model: measured (+5.67, +5.65, +7.75) m, 8.00 m
    horizontally, the height lifted by the unmodelled ionosphere.  Bounds: ±1 m on the horizontal offset,
    height above +5 m, within 2 m of the project's Galileo E1/E5a offset (measured 1.45 m)."""
    p = walk[0]
    fixes = _fixes(walk, p.SYS_GPS | p.SYS_GAL, p.IONOOPT_OFF)
    err = _offsets(fixes, walk[4], _separation(walk))
    m, sd = err.mean(axis=0), err.std(axis=0)
    print(f"\nRTKLIB GPS+Galileo L1/E1: {len(fixes)} fixes, {len(err)} on fixed epochs, median "
          f"{np.median(fixes[:, 4]):.0f} satellites; mean ENU {np.round(m, 2)} m "
          f"({math.hypot(m[0], m[1]):.2f} m), σ {np.round(sd, 2)} m")
    assert len(fixes) == 536 and len(err) >= 340 and np.median(fixes[:, 4]) >= 8
    assert 7.0 < math.hypot(m[0], m[1]) < 9.0 and m[0] > 4.5 and m[1] > 4.5 and m[2] > 5.0
    assert math.hypot(m[0] - PROJECT_GAL_ENU[0], m[1] - PROJECT_GAL_ENU[1]) < 2.0


def test_inter_signal_corrections_bring_rtklib_onto_the_project(walk):
    """The CNAV inter-signal corrections and T_GD (IS-GPS-200 §30.3.3.3.1.1) folded into RTKLIB's L1 C/A
    and L2C pseudoranges: RTKLIB's fixes then equal the project's single-point fixes of the same four
    satellites (ultratight.fusion.gins.tight_meas from the Earth's centre, L1/L2C rows of
    ultratight.signals.ubx) to within 1 cm at every epoch (measured: below 0.3 mm), and the correction
    moves RTKLIB's mean offset by (−0.88, +2.20, −0.29) m, onto the project's seven-satellite figure within
    1 m (measured 0.41 m)."""
    pytest.importorskip("pyubx2", reason="pyubx2 not installed")
    from ultratight.fusion.gins.tight_meas import TightMeasurements
    from ultratight.signals.ubx import read_ubx
    p = walk[0]
    log = read_ubx(WALK / "gnss_1730.ubx")
    gd = log.group_delays
    shift = {prn: C * ((gd[prn]["isc_l2c"] - GAMMA_L1_L2 * gd[prn]["isc_l1ca"]) / (1.0 - GAMMA_L1_L2)
                       - gd[prn]["tgd"]) for prn in GPS_LNAV_PRNS}
    plain = _fixes(walk, p.SYS_GPS, p.IONOOPT_IFLC)
    fixes = _fixes(walk, p.SYS_GPS, p.IONOOPT_IFLC, shift)
    meas = TightMeasurements(log.raw, log.nav, iono="off", sats=GPS_LNAV_PRNS)
    lat, lon = walk[4][0, 1:3]
    rot = _enu_rows(lat, lon)
    diff = []
    for k in range(0, log.raw.n_epochs, 4):
        j = int(np.argmin(np.abs(fixes[:, 0] - log.raw.t[k])))
        fix = meas.spp(k)
        if fix.ok and abs(fixes[j, 0] - log.raw.t[k]) < 0.05:
            diff.append(rot @ (fix.pos_e - fixes[j, 1:4]))
    diff = np.array(diff)
    sep = _separation(walk)
    moved = _offsets(fixes, walk[4], sep).mean(axis=0) - _offsets(plain, walk[4], sep).mean(axis=0)
    m = _offsets(fixes, walk[4], sep).mean(axis=0)
    print(f"\nshift per PRN {({k: round(v, 3) for k, v in shift.items()})} m; RTKLIB mean moved "
          f"{np.round(moved, 3)} m to {np.round(m, 2)} m; project − RTKLIB over {len(diff)} epochs: max |ENU| "
          f"{np.round(np.abs(diff).max(axis=0), 5)} m")
    assert len(diff) >= 130
    assert np.max(np.abs(diff)) < 0.01
    assert np.allclose(moved, (-0.88, 2.20, -0.29), atol=0.05)
    assert math.hypot(m[0] - PROJECT_GPS_ENU[0], m[1] - PROJECT_GPS_ENU[1]) < 1.0
