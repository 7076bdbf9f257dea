"""IMU logs in their own layouts (ultratight.ins.imu_logs): the RTKLIB time tag and the raw log of
the walk recording, the sf and KF-GINS layouts, the project's CSV in GPS time, the mount and lever-arm
conventions, the noise declaration, and hostile files (one InputFileError / ConfigError line)."""

import csv
import json
import math
import struct
from datetime import datetime
from pathlib import Path

import numpy as np
import pytest

from ultratight.errors import ConfigError, InputFileError
from ultratight.ins import imu_decl
from ultratight.ins.imu_logs import (
    detect_format,
    lever_arm_frd_to_flu,
    mount_matrix,
    mount_matrix_frd,
    read_imu_log,
    read_tag,
)

WALK = Path(__file__).resolve().parents[2] / "shared" / "data" / "real-imu-gnss" / "walk_0827"
needs_walk = pytest.mark.skipif(not (WALK / "imu_1730.csv").is_file(),
                                reason="shared data real-imu-gnss/walk_0827 not present")
G0 = 9.80665
D2R = math.pi / 180.0
GPS_EPOCH = datetime(1980, 1, 6)
T = np.diag([1.0, -1.0, -1.0])


def _gps_s(dt):
    return (dt - GPS_EPOCH).total_seconds()


# ------------------------------------------------------------------ the walk recording
@needs_walk
def test_tag_header_and_start_against_the_solution_file():
    tag = read_tag(WALK / "imu_1730.csv.tag")
    assert tag.header == "TIMETAG RTKLIB EX"
    # the uint32 after the header text is the host's millisecond tick at open (RTKLIB tick_f), not a
    # frequency: 705026197 ms; the entries' ticks count from the open (first 113 ms, last 134271 ms)
    assert tag.tick_open_ms == 705026197
    assert tag.tick_ms[0] == 113 and tag.tick_ms[-1] == 134271 and tag.tick_ms.size == 9560
    assert tag.start_unix_gpst == 1756402240 and tag.start_frac_s == pytest.approx(0.961, abs=1e-9)
    # 1756402240.961 s since 1970 (GPST) = 2025-08-28 17:30:40.961 GPST; the .pos starts 17:30:39.749
    assert tag.t_start_gps == pytest.approx(_gps_s(datetime(2025, 8, 28, 17, 30, 40, 961000)), abs=1e-6)
    first_pos = _gps_s(datetime(2025, 8, 28, 17, 30, 39, 749000))
    assert 0.0 < tag.t_start_gps - first_pos < 2.0       # measured 1.212 s


def _raw_lines():
    text = (WALK / "imu_1730.csv").read_bytes().decode()
    lines = text.split("\n")
    return [list(map(float, r)) for r in csv.reader(lines[1:-1])]      # first and last are cut


@needs_walk
def test_raw_log_rates_and_stamps_reproduce_the_file():
    imu = read_imu_log(WALK / "imu_1730.csv")                # axes FLU = identity: file axes kept
    rows = np.array(_raw_lines())
    assert imu.meta["format"] == "rtklib-raw" and imu.meta["time_scale"] == "gps"
    assert imu.meta["skipped_lines"] == [1, 20457] and imu.n == rows.shape[0] == 20455
    # increments = rate x interval, the intervals the IMU's tick differences at the fitted clock rate
    # (within 100 ppm of the tag's clock), the first the median one
    ppm = imu.meta["tag"]["clock_rate_ppm"]
    assert abs(ppm) < 100.0
    dt = np.diff(rows[:, 6]) / 1000.0 * (1.0 + ppm * 1e-6)
    dt = np.concatenate([[np.median(dt)], dt])
    np.testing.assert_allclose(imu.dtheta_b, rows[:, 3:6] * D2R * dt[:, None], rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(imu.dv_b, rows[:, 0:3] * G0 * dt[:, None], rtol=1e-9, atol=1e-15)
    # and so are the stamps (to the 0.24 us steps of a float of 1.4e9 s)
    np.testing.assert_allclose(imu.t - imu.t[0], np.concatenate([[0.0], np.cumsum(dt[1:])]), rtol=0, atol=1e-6)
    # no sample is stamped after the tag says its line had been written (line ends counted with CR LF:
    # the log was recorded with CR LF ends and is stored with LF ends), and the earliest line is on time
    tag = read_tag(WALK / "imu_1730.csv.tag")
    raw = (WALK / "imu_1730.csv").read_bytes().split(b"\n")
    end_crlf = np.cumsum([len(s) + 2 for s in raw[:-1]])[1:]
    arrival = tag.t_start_gps + tag.tick_ms[np.searchsorted(tag.file_pos, end_crlf)] / 1000.0
    late = arrival - imu.t
    assert late.min() >= -1e-6 and late.min() < 1e-3
    assert np.median(late) < 0.02                            # measured 9.7 ms
    # the converter's sf copy spreads the same samples evenly over the tag: within 20 ms of ours
    sf = np.loadtxt(WALK / "imu_1730_sf.csv", delimiter=",", usecols=0) - 315964800.0
    assert sf.size == imu.n and np.max(np.abs(sf - imu.t)) < 0.02        # measured 11.5 ms


@needs_walk
def test_sf_layout_reads_its_columns():
    imu = read_imu_log(WALK / "imu_1730_sf.csv")
    assert detect_format(WALK / "imu_1730_sf.csv") == "sf"
    a = np.loadtxt(WALK / "imu_1730_sf.csv", delimiter=",", max_rows=50)
    t = a[:, 0] - 315964800.0
    np.testing.assert_allclose(imu.t[:50], t, rtol=0, atol=1e-6)
    # intervals from the text (7 decimals) without the float rounding of 1.7e9 s
    txt = [ln.split(",")[0] for ln in (WALK / "imu_1730_sf.csv").read_text().splitlines()[:50]]
    dt = np.diff([(int(x.split(".")[0]) - 1756402240) + float("0." + x.split(".")[1]) for x in txt])
    np.testing.assert_allclose(imu.dtheta_b[1:50], a[1:, 4:7] * dt[:, None], rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(imu.dv_b[1:50], a[1:, 1:4] * G0 * dt[:, None], rtol=1e-9, atol=1e-15)


@needs_walk
def test_walk_mount_puts_gravity_down_in_body_frd():
    """Declared FRD + mount (180, 0, -90) (the recording authors' figures): held roughly level at
    the start, the specific force in body FRD is close to (0, 0, -g)."""
    imu = read_imu_log(WALK / "imu_1730.csv", declaration_overrides={"axes": "FRD"}, mount_deg=(180, 0, -90))
    f = np.array(imu.meta["f_start_body_frd_mps2"])
    # measured (0.068, 0.168, -9.920) m/s^2: 1.0 deg of tilt, |f| 1.2 % above g (accelerometer scale)
    assert np.hypot(f[0], f[1]) < G0 * math.sin(5 * D2R)       # "roughly level": within 5 deg
    assert abs(-f[2] / G0 - 1.0) < 0.02
    # same thing from the file's columns: f_body_FRD = (-ay, -ax, -az) under this mount
    rows = np.array(_raw_lines())
    n = int(np.searchsorted(imu.t, imu.t0 + 1.0))
    dt = np.diff(np.concatenate([[imu.t0], imu.t[:n]]))
    f_file = (rows[:n, 0:3] * G0 * dt[:, None]).sum(0) / dt.sum()
    # (intervals from the stamps: floats of 1.4e9 s hold 0.24 us steps, 4e-5 of a 6 ms interval)
    np.testing.assert_allclose(f, [-f_file[1], -f_file[0], -f_file[2]], rtol=1e-4)


# ------------------------------------------------------------------ mount and lever arm
def test_mount_matrix_closed_forms():
    z = np.array([0.0, 0.0, 1.0])
    np.testing.assert_allclose(mount_matrix_frd(180, 0, 0) @ z, -z, atol=1e-15)
    np.testing.assert_allclose(mount_matrix_frd(180, 0, 0) @ [0, 1.0, 0], [0, -1.0, 0], atol=1e-15)
    # C_n^b of a body yawed 90 deg (facing east): north lies on the body's left (-y in FRD)
    np.testing.assert_allclose(mount_matrix_frd(0, 0, 90) @ [1.0, 0, 0], [0, -1.0, 0], atol=1e-15)
    # pitch 90 deg (nose up): the reference down axis lies along the body's forward axis
    np.testing.assert_allclose(mount_matrix_frd(0, 90, 0) @ z, [-1.0, 0, 0], atol=1e-15)
    # composition order R1 R2 R3 against an explicit product of elementary rotations
    r, p, y = 0.3, -0.2, 1.1
    c, s = math.cos, math.sin
    R1 = np.array([[1, 0, 0], [0, c(r), s(r)], [0, -s(r), c(r)]])
    R2 = np.array([[c(p), 0, -s(p)], [0, 1, 0], [s(p), 0, c(p)]])
    R3 = np.array([[c(y), s(y), 0], [-s(y), c(y), 0], [0, 0, 1]])
    C = mount_matrix_frd(r / D2R, p / D2R, y / D2R)
    np.testing.assert_allclose(C, R1 @ R2 @ R3, atol=1e-14)
    # the FLU form acts on FLU vectors as C acts on FRD ones
    v = np.array([0.4, -1.2, 2.5])
    np.testing.assert_allclose(mount_matrix(r / D2R, p / D2R, y / D2R) @ (T @ v), T @ (C @ v), atol=1e-14)
    # the authors' walk mount: f_body = (-f_y, -f_x, -f_z) of the sensor's FRD vector
    np.testing.assert_allclose(mount_matrix_frd(180, 0, -90) @ v, [-v[1], -v[0], -v[2]], atol=1e-14)
    with pytest.raises(ConfigError, match="roll"):
        mount_matrix(float("nan"), 0, 0)


def test_lever_arm_frd_to_flu():
    np.testing.assert_allclose(lever_arm_frd_to_flu([0.1, 0.05, -0.3]), [0.1, -0.05, 0.3])
    with pytest.raises(ConfigError, match="lever arm"):
        lever_arm_frd_to_flu([0.0, 1.0])


# ------------------------------------------------------------------ KF-GINS, project CSV
def _kf_file(path, tow, dth_frd, dv_frd, nan_row=None):
    with open(path, "w") as fh:
        for k in range(tow.size):
            vals = [tow[k], *dth_frd[k], *dv_frd[k]]
            if k == nan_row:
                vals[2] = float("nan")
            fh.write(" ".join(f"{x:.12f}" if k != nan_row or j != 2 else "nan" for j, x in enumerate(vals)) + "\n")


def test_kf_gins_layout_round_trip(tmp_path):
    rng = np.random.default_rng(7)
    tow = 456789.0 + 0.005 * np.arange(200)
    dth = rng.normal(0, 1e-3, (200, 3))
    dv = rng.normal(0, 5e-2, (200, 3))
    p = tmp_path / "imu.txt"
    _kf_file(p, tow, dth, dv)
    assert detect_format(p) == "kf-gins"
    imu = read_imu_log(p, gps_week=2190)
    np.testing.assert_allclose(imu.t, 2190 * 604800.0 + tow, rtol=0, atol=1e-6)
    assert imu.t0 == pytest.approx(imu.t[0] - 0.005, abs=1e-6)
    np.testing.assert_allclose(imu.dtheta_b, dth @ T, atol=1e-12)          # FRD -> FLU
    np.testing.assert_allclose(imu.dv_b, dv @ T, atol=1e-12)
    # continuous GPS seconds (~1.3e9 s) hold 0.24 us steps: a 5 ms interval to 5e-5 relative
    assert imu.rate_hz == pytest.approx(200.0, rel=1e-4)
    with pytest.raises(ConfigError, match="GPS week"):
        read_imu_log(p)
    off = read_imu_log(p, gps_week=2190, time_offset_s=0.25)
    np.testing.assert_allclose(off.t - imu.t, 0.25, atol=1e-6)


def test_project_csv_in_gps_seconds_of_week(tmp_path):
    p = tmp_path / "imu.csv"
    tow = 100.0 + 0.01 * np.arange(1, 301)
    with open(p, "w") as fh:
        fh.write("t_s,gx_radps,gy_radps,gz_radps,ax_mps2,ay_mps2,az_mps2\n")
        for t in tow:
            fh.write(f"{t:.3f},1e-5,2e-5,3e-5,0.1,0.2,9.80665\n")
    imu_decl.write_sidecar(p, imu_decl.ImuDeclaration(time_ref="gps_tow", gps_week=2190))
    imu = read_imu_log(p)
    np.testing.assert_allclose(imu.t, 2190 * 604800.0 + tow, rtol=0, atol=1e-6)
    assert imu.meta["time_scale"] == "gps"
    np.testing.assert_allclose(imu.dtheta_b[5], [1e-7, 2e-7, 3e-7], rtol=1e-6)
    (tmp_path / "run.csv").write_text(p.read_text())
    with pytest.raises(ConfigError, match="GPS time"):
        read_imu_log(tmp_path / "run.csv")


# ------------------------------------------------------------------ synthetic raw logs and tags
def _tag_bytes(start=1756402240, frac=0.5, pairs=(), header=b"TIMETAG RTKLIB EX"):
    b = header.ljust(60, b"\0") + struct.pack("<IId", 12345, start, frac)
    return b + b"".join(struct.pack("<II", t, p) for t, p in pairs)


def _raw_log(tmp_path, n=400, bad_line=None):
    """A raw log at 5 ms with a tag that sees each line 3 ms after its tick (+ up to 4 ms)."""
    rng = np.random.default_rng(3)
    lines = ["3,1.000,0.1,0.2,0.3,100"]                      # a cut first line
    for k in range(n):
        v = ["0.010", "-0.020", "1.000", "0.500", "-0.250", "0.125", str(1000 + 5 * k)]
        if k == bad_line:
            v[2] = "nan"
        lines.append(",".join(v))
    text = "\n".join(lines) + "\n0.01,0.02"                  # a cut last line
    p = tmp_path / "raw.csv"
    p.write_text(text)
    ends = np.cumsum([len(s) + 1 for s in lines])
    pairs = [(int(5 * k + 3 + rng.integers(0, 5)), int(ends[k + 1])) for k in range(n)]
    pairs.append((pairs[-1][0] + 2, len(text)))
    (tmp_path / "raw.csv.tag").write_bytes(_tag_bytes(pairs=pairs))
    return p


def test_synthetic_raw_log_with_tag(tmp_path):
    p = _raw_log(tmp_path)
    imu = read_imu_log(p, fmt="rtklib-raw")
    # the line of tick 1000 ms arrived 3 ms after the tag's tick 0: stamps = tag start - 1 s + tick
    t_start = 1756402240.5 - 315964800.0
    np.testing.assert_allclose(imu.t, t_start + 0.003 - 1.0 + (1000 + 5 * np.arange(400)) / 1000.0, atol=1e-6)
    np.testing.assert_allclose(imu.dtheta_b[1], np.array([0.5, -0.25, 0.125]) * D2R * 0.005, rtol=1e-6)
    assert imu.meta["tag"]["byte_count"] == "direct"


def test_raw_log_nan_row_names_the_line(tmp_path):
    p = _raw_log(tmp_path, bad_line=10)
    with pytest.raises(InputFileError, match=r"line 12: az is nan"):
        read_imu_log(p)


@needs_walk
def test_tag_not_matching_its_log_is_refused(tmp_path):
    log = WALK / "imu_1730.csv"
    # the receiver log's tag: file positions far past the IMU log's size
    with pytest.raises(InputFileError, match="not the log's"):
        read_imu_log(log, tag=WALK / "gnss_1730.ubx.tag")
    # a wrong header
    good = (WALK / "imu_1730.csv.tag").read_bytes()
    (tmp_path / "h.tag").write_bytes(b"TIMETAG XXXXXX" + good[14:])
    with pytest.raises(InputFileError, match="not an RTKLIB time-tag file"):
        read_imu_log(log, tag=tmp_path / "h.tag")
    # ticks that run twice as fast as the IMU's: the arrivals leave the IMU ticks behind
    pairs = np.frombuffer(good[76:], dtype="<u4").reshape(-1, 2).copy()
    pairs[:, 0] //= 2
    (tmp_path / "fast.tag").write_bytes(good[:76] + pairs.astype("<u4").tobytes())
    with pytest.raises(InputFileError, match="does not match"):
        read_imu_log(log, tag=tmp_path / "fast.tag")
    # a truncated entry
    (tmp_path / "cut.tag").write_bytes(good[:-3])
    with pytest.raises(InputFileError, match="truncated"):
        read_imu_log(log, tag=tmp_path / "cut.tag")


def test_hostile_layouts(tmp_path):
    rng = np.random.default_rng(1)
    p = tmp_path / "k.txt"
    _kf_file(p, 1000.0 + 0.01 * np.arange(50), rng.normal(size=(50, 3)), rng.normal(size=(50, 3)), nan_row=7)
    with pytest.raises(InputFileError, match="line 8: dthy"):
        read_imu_log(p, gps_week=2000)
    sf = tmp_path / "s.csv"
    sf.write_text("".join(f"{1756402240 + 0.01 * k:.3f},0,0,1,0,0,0,0,0,0,0\n" for k in range(20)))
    with pytest.raises(InputFileError, match="not the KF-GINS layout"):
        read_imu_log(sf, fmt="kf-gins", gps_week=2000)
    raw = _raw_log(tmp_path)
    with pytest.raises(InputFileError, match="not the sf layout"):
        read_imu_log(raw, fmt="sf")
    with pytest.raises(ConfigError, match="deg/s"):
        read_imu_log(raw, declaration_overrides={"gyro_unit": "rad/s"})
    other = tmp_path / "x.dat"
    other.write_text("hello\nworld\n")
    with pytest.raises(ConfigError, match="--imu-format"):
        read_imu_log(other)
    (tmp_path / "nt.csv").write_text(raw.read_text())
    with pytest.raises(ConfigError, match="time-tag"):
        read_imu_log(tmp_path / "nt.csv", fmt="rtklib-raw")


# ------------------------------------------------------------------ noise declaration
def test_noise_flags_over_sidecar_over_grade(tmp_path):
    p = tmp_path / "imu.csv"
    p.write_text("x\n")
    (tmp_path / "imu.csv.json").write_text(json.dumps(
        {"noise": {"grade": "consumer", "gyro_noise_dps_rthz": 0.0038, "accel_noise_ug_rthz": 70.0}}))
    dec = imu_decl.resolve_declaration(p)
    n = imu_decl.resolve_noise(dec, grade="mems", accel_noise_ug_rthz=80.0)
    assert n.gyro_arw == pytest.approx(0.0038 * D2R)                  # sidecar
    assert n.accel_vrw == pytest.approx(80e-6 * G0)                   # flag over sidecar
    assert n.gyro_bias_sigma == pytest.approx(200.0 / 3600.0 * D2R)   # the flag's grade (mems)
    n2 = imu_decl.resolve_noise(dec)
    assert n2.gyro_bias_sigma == pytest.approx(0.5 * D2R)             # the sidecar's grade (consumer)
    assert dec.to_dict()["noise"]["grade"] == "consumer"
    with pytest.raises(ConfigError, match="declare"):
        imu_decl.resolve_noise(None, gyro_noise_dps_rthz=0.0038)
    (tmp_path / "imu.csv.json").write_text(json.dumps({"noise": {"gyro_noise": 1.0}}))
    with pytest.raises(ConfigError, match="unknown key 'gyro_noise'"):
        imu_decl.resolve_declaration(p)
    (tmp_path / "imu.csv.json").write_text(json.dumps({"noise": {"accel_bias_mps2": -1}}))
    with pytest.raises(ConfigError, match="positive"):
        imu_decl.resolve_declaration(p)


def test_noise_cli_flags():
    import argparse

    from ultratight.receiver.cli.commands import imu_flags
    ap = argparse.ArgumentParser()
    imu_flags.add_arguments(ap)
    imu_flags.add_noise_arguments(ap)
    a = ap.parse_args(["--imu-gyro-noise", "0.0038", "--imu-accel-noise", "70", "--imu-gyro-bias-rw", "3.8e-5",
                       "--imu-accel-bias-rw", "7", "--imu-gyro-bias", "0.2", "--imu-accel-bias", "0.2",
                       "--lever-arm", "0", "0.05", "0"])
    n = imu_flags.resolve_noise(a)
    assert (n.gyro_arw, n.accel_vrw, n.gyro_bias_rw, n.accel_bias_rw, n.gyro_bias_sigma, n.accel_bias_sigma) == \
        pytest.approx((0.0038 * D2R, 70e-6 * G0, 3.8e-5 * D2R, 7e-6 * G0, 0.2 * D2R, 0.2))
    np.testing.assert_allclose(imu_flags.lever_arm_flu(a), [0.0, -0.05, 0.0])
    assert "lever_arm_m" not in imu_flags.overrides(a, lever_arm=False)
    assert imu_flags.overrides(a)["lever_arm_m"] == [0.0, 0.05, 0.0]


def test_project_h5_in_gps_time_with_a_declared_offset(tmp_path):
    from ultratight.ins.imu_data import ImuData, write_imu_h5
    t = 0.01 * np.arange(1, 101)
    imu = ImuData(t=t, dtheta_b=np.full((100, 3), 1e-6), dv_b=np.full((100, 3), 0.098), rate_hz=100.0, t0=0.0,
                  meta={"start_tow_s": 5000.0, "start_week": 2190})
    write_imu_h5(tmp_path / "a.h5", imu)
    got = read_imu_log(tmp_path / "a.h5", declaration_overrides={"time_offset_s": 0.02}, mount_deg=(180, 0, 0))
    np.testing.assert_allclose(got.t, 2190 * 604800.0 + 5000.0 + t + 0.02, rtol=0, atol=1e-6)
    np.testing.assert_allclose(got.dv_b[0], [0.098, -0.098, -0.098])       # roll 180 about x (FLU too)
    write_imu_h5(tmp_path / "run.h5", ImuData(t=t, dtheta_b=imu.dtheta_b, dv_b=imu.dv_b, rate_hz=100.0))
    with pytest.raises(ConfigError, match="GPS time"):
        read_imu_log(tmp_path / "run.h5")
