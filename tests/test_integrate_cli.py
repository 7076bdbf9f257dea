"""``ultratight integrate`` end to end on the real walk (../shared/data/real-imu-gnss/walk_0827) and
on hostile inputs.

The walk is declared with what its authors state and nothing else (../shared/data/README.md):
raw IMU log with its RTKLIB time tag, axes taken as the sensor frame (FRD) and mounted at roll, pitch,
yaw = 180°, 0°, −90°, IMU 5 cm from the antenna, the noise figures of their configuration.  GNSS is
removed over the two 15 s windows they test with (17:31:04.75–17:31:19.50 and 17:31:50.00–17:32:04.50
GPST, 2025-08-28 = GPS week 2381, seconds of week 408664.75 and 408710.00); the RTK solution's fixed
epochs are the reference.  Figures and tolerances: docs/integrate.md, docs/claims.md.
"""

import json
import subprocess
import sys

import pytest
from conftest import SHARED_DATA
from test_hostile_inputs import assert_clean_failure, snapshot

WALK = SHARED_DATA / "real-imu-gnss" / "walk_0827"
needs_walk = pytest.mark.skipif(not WALK.is_dir(), reason=f"real walk data not found at {WALK}")
OUTAGES = ("--outage", "408664.75:14.75", "--outage", "408710.00:14.5")
AUTHORS = ("--imu-axes", "FRD", "--mount", "180", "0", "-90", "--lever-arm", "0", "-0.05", "0",
           "--imu-gyro-noise", "0.0038", "--imu-accel-noise", "70", "--imu-accel-bias-rw", "7",
           "--imu-gyro-bias-rw", "3.8e-5", "--imu-gyro-bias", "0.2", "--imu-accel-bias", "0.2")


def cli(args, cwd=None, timeout=600):
    return subprocess.run([sys.executable, "-m", "ultratight.receiver.cli", *args], cwd=cwd, capture_output=True,
                          text=True, timeout=timeout)


def walk_args(*extra, imu=None, gnss=None):
    return ["integrate", "--imu", str(imu or WALK / "imu_1730.csv"), *AUTHORS,
            "--gnss", str(gnss or WALK / "gnss_1730_sf.pos"), *extra]


def _run_json(args, cwd=None):
    res = cli([*args, "--json"], cwd=cwd)
    assert res.returncode == 0, res.stderr
    return json.loads(res.stdout)


# ------------------------------------------------------------------ hostile inputs
@needs_walk
def test_logs_that_do_not_overlap_in_time_are_refused(tmp_path):
    pos = tmp_path / "day_later.pos"
    lines = (WALK / "gnss_1730_sf.pos").read_text().splitlines()
    pos.write_text("\n".join(ln.replace("2025/08/28", "2025/08/29") for ln in lines) + "\n")
    before = snapshot(tmp_path)
    res = cli(walk_args("--out", "sol.pos", gnss=pos), cwd=tmp_path)
    assert_clean_failure(res, 2, "do not overlap", before, tmp_path)
    assert not (tmp_path / "sol.pos").exists()


@needs_walk
def test_a_gnss_file_of_another_format_than_declared_is_refused(tmp_path):
    before = snapshot(tmp_path)
    res = cli(walk_args("--gnss-format", "nmea", "--out", "sol.pos"), cwd=tmp_path)
    assert_clean_failure(res, 2, "nmea", before, tmp_path)
    assert not (tmp_path / "sol.pos").exists()


@needs_walk
def test_a_time_tag_of_another_log_is_refused(tmp_path):
    before = snapshot(tmp_path)
    res = cli(walk_args("--imu-tag", str(WALK / "gnss_1730.ubx.tag"), "--out", "sol.pos"), cwd=tmp_path)
    assert_clean_failure(res, 2, "tag", before, tmp_path)
    assert not (tmp_path / "sol.pos").exists()


@needs_walk
def test_a_nan_row_in_the_imu_log_is_refused_with_its_line(tmp_path):
    lines = (WALK / "imu_1730.csv").read_text().splitlines()
    f = lines[500].split(",")
    f[2] = "nan"
    lines[500] = ",".join(f)
    imu = tmp_path / "imu.csv"
    imu.write_text("\n".join(lines) + "\n")
    (tmp_path / "imu.csv.tag").write_bytes((WALK / "imu_1730.csv.tag").read_bytes())
    before = snapshot(tmp_path)
    res = cli(walk_args("--out", "sol.pos", imu=imu), cwd=tmp_path)
    assert_clean_failure(res, 2, "501", before, tmp_path)
    assert not (tmp_path / "sol.pos").exists()


@needs_walk
def test_an_output_on_an_input_is_refused(tmp_path):
    pos = tmp_path / "gnss.pos"
    pos.write_bytes((WALK / "gnss_1730_sf.pos").read_bytes())
    before = snapshot(tmp_path)
    res = cli(walk_args("--out", str(pos), gnss=pos), cwd=tmp_path)
    assert_clean_failure(res, 2, "refusing to overwrite", before, tmp_path)


def test_impossible_flags_are_refused_before_reading(tmp_path):
    imu, gnss = tmp_path / "imu.csv", tmp_path / "g.pos"
    imu.write_text("t_s,dthx_rad,dthy_rad,dthz_rad,dvx_mps,dvy_mps,dvz_mps\n")
    gnss.write_text("% nothing\n")
    before = snapshot(tmp_path)
    for extra, fragment in ((["--rate", "-1"], "--rate"), (["--outages", "60:60"], "shorter than every"),
                            (["--outage-keep-sats", "3"], "--coupling tight"),
                            (["--outage", "1:2", "--outages", "180:60"], "not both"),
                            (["--plot", "x.png"], "--reference")):
        res = cli(["integrate", "--imu", str(imu), "--gnss", str(gnss), "--imu-grade", "mems", *extra], cwd=tmp_path)
        assert_clean_failure(res, 2, fragment, before, tmp_path)
