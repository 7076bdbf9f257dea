"""GNSS solution files (ultratight.receiver.io.solution_files): the walk recording's RTKLIB .pos and
u-blox NAV-PVT, .pos write/read round trip (ours and RTKLIB's readsol), the xyz-ECEF form, NMEA
GGA/RMC/GST reading of generated sentences, KML, and files refused in one line."""

import math
import xml.etree.ElementTree as ET
from datetime import datetime, timedelta
from pathlib import Path

import numpy as np
import pytest

from ultratight.errors import ConfigError, InputFileError
from ultratight.ins.earth import dcm_ecef_from_enu, llh_to_ecef
from ultratight.receiver.io.solution_files import (
    read_gnss,
    read_nmea,
    read_pos,
    sniff_format,
    write_kml,
    write_nmea,
    write_pos,
)
from ultratight.signals.observations import GnssFixes

WALK = Path(__file__).resolve().parents[2] / "shared" / "data" / "real-imu-gnss" / "walk_0827"
needs_walk = pytest.mark.skipif(not (WALK / "gnss_1730_sf.pos").is_file(),
                                reason="shared data real-imu-gnss/walk_0827 not present")
GPS_EPOCH = datetime(1980, 1, 6)
D2R = math.pi / 180.0


def _gps_s(dt):
    return (dt - GPS_EPOCH).total_seconds()


@needs_walk
def test_walk_pos_file():
    f = read_gnss(WALK / "gnss_1730_sf.pos")
    assert f.meta["format"] == "pos" and f.meta["form"] == "llh"
    assert f.n == 536 and int((f.quality == 1).sum()) == 349 and int((f.quality == 2).sum()) == 187
    assert f.t[0] == pytest.approx(_gps_s(datetime(2025, 8, 28, 17, 30, 39, 749000)), abs=1e-6)
    assert np.median(np.diff(f.t)) == pytest.approx(0.25, abs=1e-6)
    # first row: 40.0966916 -105.1471665 1601.435 ... sdn sde sdu 0.0098995 0.0098995 0.0100000,
    # vn ve vu 0.001 -0.002 0.027, sdvn sdve sdvu 0.0494975 x 3
    np.testing.assert_allclose(f.llh[0], [40.0966916 * D2R, -105.1471665 * D2R, 1601.435], rtol=0, atol=1e-9)
    np.testing.assert_allclose(f.sigma_pos_enu[0], [0.0098995, 0.0098995, 0.01], atol=1e-12)
    np.testing.assert_allclose(f.vel_enu[0], [-0.002, 0.001, 0.027], atol=1e-12)
    np.testing.assert_allclose(f.sigma_vel_enu[0], [0.0494975] * 3, atol=1e-12)
    assert np.all(f.n_sat == 25) or f.n_sat.min() > 3


@needs_walk
def test_walk_nav_pvt_against_the_pos_file():
    u = read_gnss(WALK / "gnss_1730.ubx")
    p = read_gnss(WALK / "gnss_1730_sf.pos")
    assert u.meta["message"] == "NAV-PVT" and u.n == 536 and u.meta["skipped"] == 0
    # the .pos file is these NAV-PVT solutions: same quality, position, horizontal sigma (hAcc/sqrt 2)
    np.testing.assert_array_equal(u.quality, p.quality)
    np.testing.assert_allclose(u.llh[:, :2], p.llh[:, :2], rtol=0, atol=1e-7 * D2R)
    np.testing.assert_allclose(u.sigma_pos_enu, p.sigma_pos_enu, rtol=0, atol=1e-7)
    np.testing.assert_allclose(u.vel_enu, p.vel_enu, rtol=0, atol=1e-9)
    # stamps: iTOW (ms) against the .pos's truncated UTC + nano: 1 ms apart
    np.testing.assert_allclose(u.t - p.t, 0.001, atol=1e-6)
    # heights: NAV-PVT height is above the ellipsoid; the .pos column equals the receiver's hMSL,
    # 21.387-21.388 m above it (the geoid undulation there, both heights in whole mm) on every epoch
    dh = p.llh[:, 2] - u.llh[:, 2]
    assert np.all(np.abs(dh - 21.3875) <= 0.0005 + 1e-9)


def _fixes(n=40, seed=5, vel=True):
    rng = np.random.default_rng(seed)
    t = _gps_s(datetime(2024, 3, 1, 23, 59, 50)) + 0.1 * np.arange(n)
    llh = np.column_stack([(35.0 + 1e-5 * np.cumsum(rng.normal(size=n))) * D2R,
                           (139.0 + 1e-5 * np.cumsum(rng.normal(size=n))) * D2R, 40.0 + rng.normal(size=n)])
    v = rng.normal(0, 2, (n, 3)) if vel else np.full((n, 3), np.nan)
    sp = rng.uniform(0.01, 3, (n, 3))
    sv = rng.uniform(0.01, 0.3, (n, 3)) if vel else np.full((n, 3), np.nan)
    q = rng.choice([1, 2, 4, 5], n)
    return GnssFixes(t=t, llh=llh, vel_enu=v, sigma_pos_enu=sp, sigma_vel_enu=sv, quality=q,
                     n_sat=rng.integers(4, 30, n))


def test_pos_round_trip_ours_and_rtklib(tmp_path):
    f = _fixes()
    out = write_pos(tmp_path / "a.pos", f)
    g = read_pos(out)
    assert g.n == f.n and sniff_format(out) == "pos"
    np.testing.assert_allclose(g.t, f.t, rtol=0, atol=1e-6)
    np.testing.assert_allclose(g.llh[:, :2], f.llh[:, :2], rtol=0, atol=0.51e-9 * D2R)     # 9 decimals of deg
    np.testing.assert_allclose(g.llh[:, 2], f.llh[:, 2], atol=0.51e-4)
    np.testing.assert_allclose(g.sigma_pos_enu, f.sigma_pos_enu, atol=0.51e-4)            # RTKLIB's %8.4f
    np.testing.assert_allclose(g.vel_enu, f.vel_enu, atol=0.51e-5)
    np.testing.assert_allclose(g.sigma_vel_enu, f.sigma_vel_enu, atol=0.51e-5)
    np.testing.assert_array_equal(g.quality, f.quality)
    np.testing.assert_array_equal(g.n_sat, f.n_sat)
    # RTKLIB's own reader
    pyrtklib = pytest.importorskip("pyrtklib")
    sb = pyrtklib.solbuf_t()
    assert pyrtklib.readsol([str(out)], 1, sb) == 1 and sb.n == f.n
    for k in (0, 17, f.n - 1):
        s = sb.data[k]                          # (pyrtklib's getsol hands back a pointer it then frees)
        assert s.time.time + s.time.sec - 315964800.0 == pytest.approx(f.t[k], abs=1e-6)
        assert s.stat == f.quality[k] and s.ns == f.n_sat[k]
        r_e = llh_to_ecef(*f.llh[k])
        np.testing.assert_allclose(list(s.rr)[:3], r_e, atol=2e-3)
        C = dcm_ecef_from_enu(f.llh[k, 0], f.llh[k, 1])
        np.testing.assert_allclose(C.T @ np.array(list(s.rr)[3:6]), f.vel_enu[k], atol=1e-4)
        qr = list(s.qr)                        # ECEF covariance: its trace is the sum of the ENU variances
        assert qr[0] + qr[1] + qr[2] == pytest.approx(float(np.sum(f.sigma_pos_enu[k] ** 2)), rel=1e-2)


def test_pos_without_velocity_and_nan_sigma(tmp_path):
    f = _fixes(vel=False)
    f.sigma_pos_enu[3] = np.nan
    g = read_pos(write_pos(tmp_path / "b.pos", f))
    assert np.all(np.isnan(g.vel_enu)) and np.all(np.isnan(g.sigma_vel_enu))
    assert np.all(np.isnan(g.sigma_pos_enu[3])) and np.all(np.isfinite(g.sigma_pos_enu[4]))


def test_pos_xyz_form(tmp_path):
    lat, lon, h = 40.0966916 * D2R, -105.1471665 * D2R, 1580.05
    r = llh_to_ecef(lat, lon, h)
    C = dcm_ecef_from_enu(lat, lon)
    v_enu = np.array([1.0, -0.5, 0.2])
    v = C @ v_enu
    P = C @ np.diag([0.02, 0.03, 0.05]) ** 2 @ C.T          # ENU sigma 0.02, 0.03, 0.05 m
    sd = np.sqrt(np.diag(P))
    off = [np.sign(P[i, j]) * math.sqrt(abs(P[i, j])) for i, j in ((0, 1), (1, 2), (2, 0))]
    text = ("%  GPST          x-ecef(m)      y-ecef(m)      z-ecef(m)   Q  ns   sdx(m)   sdy(m)   sdz(m)  sdxy(m)"
            "  sdyz(m)  sdzx(m) age(s)  ratio  vx(m/s) vy(m/s) vz(m/s)\n"
            f"2300 86400.000 {r[0]:.4f} {r[1]:.4f} {r[2]:.4f} 5 9 {sd[0]:.7f} {sd[1]:.7f} {sd[2]:.7f} "
            f"{off[0]:.7f} {off[1]:.7f} {off[2]:.7f} 0.0 0.0 {v[0]:.6f} {v[1]:.6f} {v[2]:.6f}\n")
    (tmp_path / "x.pos").write_text(text)
    f = read_gnss(tmp_path / "x.pos")
    assert f.meta["form"] == "xyz" and f.quality[0] == 5
    assert f.t[0] == pytest.approx(2300 * 604800.0 + 86400.0)
    np.testing.assert_allclose(f.llh[0, :2], [lat, lon], atol=1e-10)
    assert f.llh[0, 2] == pytest.approx(h, abs=1e-3)
    np.testing.assert_allclose(f.vel_enu[0], v_enu, atol=1e-5)
    np.testing.assert_allclose(f.sigma_pos_enu[0], [0.02, 0.03, 0.05], atol=1e-5)


def _nmea(body):
    c = 0
    for ch in body.encode():
        c ^= ch
    return f"${body}*{c:02X}\r\n"


def test_nmea_generated_gga_rmc_gst(tmp_path):
    # two epochs across midnight UTC; RMC carries the date of the first only (the second rolls over)
    lines = [
        _nmea("GNGGA,235959.50,4005.80150,N,10508.82999,W,4,12,0.8,1601.435,M,-21.387,M,1.0,0000"),
        _nmea("GNRMC,235959.50,A,4005.80150,N,10508.82999,W,1.944,90.0,280825,,,R"),
        _nmea("GNGST,235959.50,0.02,0.03,0.01,45.0,0.011,0.012,0.020"),
        _nmea("GNGGA,000000.00,4005.80160,N,10508.82900,W,5,11,0.9,1601.000,M,-21.387,M,1.0,0000"),
        "$GNGGA,000000.50,garbage*00\r\n",                  # wrong checksum: skipped
    ]
    (tmp_path / "a.nmea").write_text("".join(lines))
    f = read_gnss(tmp_path / "a.nmea")
    assert f.n == 2 and f.meta["bad_checksum"] == 1
    t0 = _gps_s(datetime(2025, 8, 28, 23, 59, 59, 500000)) + 18
    np.testing.assert_allclose(f.t, [t0, t0 + 0.5], atol=1e-6)
    np.testing.assert_allclose(f.llh[0, :2], [(40 + 5.80150 / 60) * D2R, -(105 + 8.82999 / 60) * D2R], atol=1e-12)
    assert f.llh[0, 2] == pytest.approx(1601.435 - 21.387)
    np.testing.assert_array_equal(f.quality, [1, 2])
    np.testing.assert_array_equal(f.n_sat, [12, 11])
    np.testing.assert_allclose(f.vel_enu[0, :2], [1.944 * 1852 / 3600, 0.0], atol=1e-9)     # course 90: east
    np.testing.assert_allclose(f.sigma_pos_enu[0], [0.012, 0.011, 0.020])
    assert np.all(np.isnan(f.vel_enu[1])) and np.all(np.isnan(f.sigma_pos_enu[1]))
    # GGA alone: the date from the caller; leap seconds as given
    (tmp_path / "g.nmea").write_text(lines[0])
    with pytest.raises(ConfigError, match="--date"):
        read_nmea(tmp_path / "g.nmea")
    g = read_nmea(tmp_path / "g.nmea", date="2025-08-28", leap_s=17)
    assert g.t[0] == pytest.approx(t0 - 1.0)


def test_nmea_write_read_round_trip(tmp_path):
    f = _fixes(n=30)
    f.t = np.round(f.t * 100.0) / 100.0
    out = write_nmea(tmp_path / "o.nmea", f)
    g = read_nmea(out)
    assert g.n == f.n
    np.testing.assert_allclose(g.t, f.t, atol=1e-6)                   # across midnight UTC, date from RMC
    np.testing.assert_allclose(g.llh[:, :2], f.llh[:, :2], atol=1e-7 / 60 * D2R)     # 5 decimals of minutes
    np.testing.assert_allclose(g.llh[:, 2], f.llh[:, 2], atol=0.51e-3)
    np.testing.assert_allclose(g.vel_enu[:, :2], f.vel_enu[:, :2], atol=1e-3)
    np.testing.assert_allclose(g.sigma_pos_enu, f.sigma_pos_enu, atol=0.51e-4)
    np.testing.assert_array_equal(g.quality, np.where(f.quality == 4, 4, f.quality))


def test_kml_track(tmp_path):
    f = _fixes(n=12)
    out = write_kml(tmp_path / "t.kml", f, name="walk & run")
    root = ET.parse(out).getroot()
    ns = {"k": "http://www.opengis.net/kml/2.2"}
    coords = root.find(".//k:LineString/k:coordinates", ns).text.split()
    assert len(coords) == f.n
    lon, lat, h = map(float, coords[5].split(","))
    assert (lat, lon) == pytest.approx((f.llh[5, 0] / D2R, f.llh[5, 1] / D2R), abs=1e-9)
    assert h == pytest.approx(f.llh[5, 2], abs=1e-3)


def test_files_refused_in_one_line(tmp_path):
    nm = tmp_path / "a.nmea"
    nm.write_text(_nmea("GPGGA,120000.00,4005.80150,N,10508.82999,W,1,08,0.8,100.0,M,0.0,M,,"))
    with pytest.raises(InputFileError, match="declared pos but the content looks like nmea"):
        read_gnss(nm, fmt="pos")
    with pytest.raises(InputFileError, match="declared ubx but the content looks like nmea"):
        read_gnss(nm, fmt="ubx")
    f = _fixes(n=5)
    p = write_pos(tmp_path / "n.pos", f)
    lines = p.read_text().splitlines()
    lines[6] = lines[6].replace(lines[6].split()[2], "nan", 1)
    p.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputFileError, match="line 7: latitude 'nan'"):
        read_gnss(p)
    other = tmp_path / "x.txt"
    other.write_text("hello\n")
    with pytest.raises(InputFileError, match="not a GNSS solution log"):
        read_gnss(other)
    with pytest.raises(ConfigError, match="format must be one of"):
        read_gnss(nm, fmt="rinex")
    back = tmp_path / "b.pos"
    rows = write_pos(tmp_path / "c.pos", f).read_text().splitlines()
    back.write_text("\n".join(rows[:5] + [rows[4]]) + "\n")
    with pytest.raises(InputFileError, match="line 6: time repeats"):
        read_gnss(back)


def test_writer_leaves_no_temporary_file_and_keeps_existing_on_error(tmp_path):
    f = _fixes(n=5)
    write_pos(tmp_path / "a.pos", f)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.pos"]
    bad = _fixes(n=5)
    bad.quality = None                                        # a bug in the caller: nothing is written
    (tmp_path / "keep.pos").write_text("old\n")
    with pytest.raises(TypeError):
        write_pos(tmp_path / "keep.pos", bad)
    assert (tmp_path / "keep.pos").read_text() == "old\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.pos", "keep.pos"]


def test_date_rollover_from_first_rmc_backwards(tmp_path):
    # a GGA before the first RMC of the next day takes the previous date
    lines = [_nmea("GPGGA,235959.00,4005.80150,N,10508.82999,W,1,08,0.8,100.0,M,0.0,M,,"),
             _nmea("GPGGA,000001.00,4005.80150,N,10508.82999,W,1,08,0.8,100.0,M,0.0,M,,"),
             _nmea("GPRMC,000001.00,A,4005.80150,N,10508.82999,W,0.0,0.0,010124,,,A")]
    (tmp_path / "r.nmea").write_text("".join(lines))
    f = read_nmea(tmp_path / "r.nmea")
    d0 = datetime(2023, 12, 31, 23, 59, 59)
    np.testing.assert_allclose(f.t, [_gps_s(d0) + 18, _gps_s(d0 + timedelta(seconds=2)) + 18], atol=1e-6)


@needs_walk
def test_nav_pvt_frames_in_a_cut_and_corrupted_log(tmp_path):
    """Only whole NAV-PVT frames with a right checksum are read: a log cut inside a frame and with a
    flipped byte in one NAV-PVT frame gives what pyubx2's own stream reader gives."""
    from pyubx2 import UBX_PROTOCOL, UBXReader
    raw = bytearray((WALK / "gnss_1730.ubx").read_bytes()[:150001])
    k = raw.find(b"\xb5\x62\x01\x07", 40000)
    raw[k + 20] ^= 0xFF
    p = tmp_path / "cut.ubx"
    p.write_bytes(b"$GPTXT,garbage\r\n" + bytes(raw))
    ref = []
    with open(p, "rb") as fh:
        for _r, m in UBXReader(fh, protfilter=UBX_PROTOCOL, quitonerror=0):
            if m is not None and m.identity == "NAV-PVT":
                ref.append(m.iTOW / 1000.0)
    f = read_gnss(p)
    assert 0 < f.n == len(ref)
    np.testing.assert_allclose(f.t % 604800.0, ref, atol=1e-9)
