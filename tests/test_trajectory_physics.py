"""Physical trajectories from files (docs/trajectory-files.md): the attitude along the velocity is
held at rest and slewed with bounded rates in and out of a hold, the reader refuses files no vehicle
could have written (NaN, time going backwards, a jump of kilometres), and every synthesised IMU is
checked against the sensor range (ultratight.ins.imu.check_limits)."""

import math
import subprocess
import sys

import numpy as np
import pytest

from ultratight.constants import OMEGA_E
from ultratight.errors import ConfigError, InputFileError
from ultratight.ins.earth import dcm_ecef_from_enu, llh_to_ecef
from ultratight.ins.imu import check_limits, imu_errors_from_config, synthesize_imu
from ultratight.ins.trajectory import build_trajectory
from ultratight.receiver.cli.scenario_config import load_scenario

LAT, LON, H = math.radians(41.275), math.radians(1.987), 50.0
R0 = np.asarray(llh_to_ecef(LAT, LON, H))
C_EL = dcm_ecef_from_enu(LAT, LON)
REST_S, FLIGHT_S = 20.0, 10.0
ELEV, AZ = math.radians(80.0), math.radians(45.0)     # launch direction: 80 deg up, to the north-east
ACC = 30.0                                           # m/s^2 along the path after a 1 s ramp


def launch_enu(t):
    """Closed form: at rest until REST_S, then along a fixed direction with the acceleration ramped
    by (3 x^2 - 2 x^3) over 1 s to ACC; ENU position (n, 3)."""
    tau = np.clip(t - REST_S, 0.0, None)
    x = np.clip(tau, 0.0, 1.0)
    # s(tau) = int int acc: ramp part ACC (x^4/4 - x^5/10), then constant acceleration
    s_ramp = ACC * (x ** 4 / 4.0 - x ** 5 / 10.0)
    s = np.where(tau <= 1.0, s_ramp, ACC * (0.25 - 0.1) + ACC * 0.5 * (tau - 1.0) + ACC * 0.5 * (tau - 1.0) ** 2)
    d = np.array([math.cos(ELEV) * math.sin(AZ), math.cos(ELEV) * math.cos(AZ), math.sin(ELEV)])
    return s[:, None] * d[None, :]


def write_csv(path, t, enu):
    np.savetxt(path, np.column_stack([t, R0 + enu @ C_EL.T]), delimiter=",", fmt="%.4f",
               header="t,x,y,z", comments="")


def _rotation_steps_deg(q):
    """Angle of the rotation between consecutive attitude quaternions (deg)."""
    dots = np.abs(np.sum(q[1:] * q[:-1], axis=1))
    return np.degrees(2.0 * np.arccos(np.clip(dots, 0.0, 1.0)))


def _euler_steps_deg(e):
    d = np.degrees(np.diff(e, axis=0))
    return np.abs((d + 180.0) % 360.0 - 180.0)


@pytest.fixture(scope="module")
def launch_csv(tmp_path_factory):
    p = tmp_path_factory.mktemp("launch") / "launch.csv"
    t = np.round(np.arange(0.0, REST_S + FLIGHT_S + 1e-9, 0.1), 1)
    write_csv(p, t, launch_enu(t))
    return p


def test_ramp_closed_form_is_continuous():
    # the test's own trajectory: position and speed continuous at the end of the ramp
    h = 1e-6
    t = np.array([REST_S + 1.0 - h, REST_S + 1.0 + h])
    p = launch_enu(t)
    assert np.linalg.norm(p[1] - p[0]) < 1e-4


def test_rest_then_launch_holds_the_attitude_of_the_first_motion(launch_csv):
    tr = build_trajectory({"kind": "file", "path": str(launch_csv)}, {}, REST_S + FLIGHT_S)
    imu = synthesize_imu(tr, 100.0)
    w = imu.dtheta_b * imu.rate_hz
    assert np.degrees(np.max(np.linalg.norm(w, axis=1))) < 50.0
    T = imu.truth
    k = tr.kinematics(T["t"])
    rest = T["t"] < REST_S - 1.0
    e = k["euler"]
    # at rest: the direction of the launch (pitch 80, yaw 45 deg), steady, and the gyros read the
    # Earth rate only
    assert np.max(np.abs(np.degrees(e[rest, 1]) - 80.0)) < 0.5
    assert np.max(np.abs(np.degrees(e[rest, 2]) - 45.0)) < 0.5
    assert np.max(_euler_steps_deg(e[rest])) < 1e-3
    w_rest = w[T["t"][1:] < REST_S - 1.0]
    assert np.max(np.abs(np.linalg.norm(w_rest, axis=1) - OMEGA_E)) < 1e-6
    # never a flip: consecutive attitudes differ by a small rotation, and the Euler angles too
    assert np.max(_rotation_steps_deg(T["q_lb"])) < 0.5
    assert np.max(_euler_steps_deg(e)[:, 1:]) < 2.0
    # in flight the body x axis is along the velocity
    fly = T["t"] > REST_S + 3.0
    bx = k["C_lb"][fly][:, :, 0]
    v = k["vel_l"][fly] / np.linalg.norm(k["vel_l"][fly], axis=1)[:, None]
    assert np.max(np.degrees(np.arccos(np.clip(np.sum(bx * v, axis=1), -1, 1)))) < 0.1


def test_rest_then_launch_from_a_level_attitude_slews_within_the_limits(launch_csv):
    # att0_deg given: held level before the launch, then an 80 deg pitch-up at <= slew_rate_dps
    cfg = {"kind": "file", "path": str(launch_csv), "att0_deg": [0.0, 0.0, 45.0], "slew_rate_dps": 20.0,
           "slew_accel_dps2": 40.0}
    tr = build_trajectory(cfg, {}, REST_S + FLIGHT_S)
    imu = synthesize_imu(tr, 100.0)
    w = np.degrees(imu.dtheta_b * imu.rate_hz)
    assert np.max(np.linalg.norm(w, axis=1)) < 25.0             # 20 deg/s of slew plus the pitch-up's own
    alpha = np.abs(np.diff(w, axis=0)) * imu.rate_hz
    assert np.max(alpha) < 60.0                                  # 40 deg/s^2 of slew plus the path's
    k = tr.kinematics(imu.truth["t"])
    rest = imu.truth["t"] < REST_S - 0.5
    assert np.max(np.abs(np.degrees(k["euler"][rest, 1]))) < 1e-6
    # 80 deg at 20 deg/s takes at least 4 s: along the velocity within 0.1 deg by 9 s after the launch
    t_end = imu.truth["t"] > REST_S + 9.0
    assert np.max(np.abs(np.degrees(k["euler"][t_end, 1]) - 80.0)) < 0.1
    mid = np.abs(imu.truth["t"] - (REST_S + 2.0)) < 0.01
    assert np.all(np.degrees(k["euler"][mid, 1]) < 45.0)


def test_parked_vehicle_with_position_jitter_keeps_its_attitude(tmp_path):
    rng = np.random.default_rng(11)
    t = np.round(np.arange(0.0, 60.0 + 1e-9, 0.1), 1)
    p = tmp_path / "parked.csv"
    write_csv(p, t, rng.normal(0.0, 0.02, (t.size, 3)))
    tr = build_trajectory({"kind": "file", "path": str(p), "att0_deg": [1.0, 2.0, 200.0]}, {}, 60.0)
    # the smoothed jitter stays below the hold threshold of 0.5 m/s
    assert np.max(np.linalg.norm(tr.kinematics(np.linspace(0, 60, 6001))["vel_l0"], axis=1)) < 0.5
    imu = synthesize_imu(tr, 100.0)
    w = imu.dtheta_b * imu.rate_hz
    assert np.degrees(np.max(np.linalg.norm(w, axis=1))) < 50.0
    assert np.max(np.abs(np.linalg.norm(w, axis=1) - OMEGA_E)) < 1e-6        # the Earth rate only
    e = np.degrees(tr.kinematics(imu.truth["t"])["euler"])
    assert np.max(np.abs(e - [1.0, 2.0, 200.0])) < 1e-6
    assert np.max(_rotation_steps_deg(imu.truth["q_lb"])) < 1e-4            # arccos's floor near 1


def test_imu_limit_check_refuses_beyond_the_declared_range():
    # a 37.5 deg/s turn at 30 m/s: within the default range, beyond a 30 deg/s gyro
    cfg = {"kind": "turns", "speed0_mps": 30.0, "segments": [{"t0": 0.0}, {"t0": 2.0, "turn_rate_dps": 37.5}]}
    tr = build_trajectory(cfg, {"lat_deg": 41.275, "lon_deg": 1.987, "h_m": 50.0}, 4.0)
    synthesize_imu(tr, 100.0, imu_errors_from_config({"preset": "ideal"}))
    with pytest.raises(ConfigError) as ei:
        synthesize_imu(tr, 100.0, imu_errors_from_config({"preset": "ideal", "gyro_range_dps": 30.0}))
    msg = str(ei.value)
    # first interval after the step: mean body rate -37.5 deg/s on z (FLU, right turn) plus the Earth's
    assert "angular rate -37.49" in msg and "on body axis z at t = 2.01 s" in msg and "imu.gyro_range_dps" in msg
    # the rate step at t = 2 s between two 10 ms intervals: 37.5 * 100 = 3750 deg/s^2
    with pytest.raises(ConfigError, match=r"angular acceleration -3750 deg/s\^2 on body axis z at t = 2 s "):
        synthesize_imu(tr, 100.0, imu_errors_from_config({"preset": "ideal", "angular_accel_max_dps2": 1000.0}))
    # 3 g straight ahead: specific force along body x of 3 g, beyond a 2 g accelerometer
    seg = {"kind": "segments", "segments": [{"t0": 0.0, "acc_enu": [0.0, 3.0 * 9.80665, 0.0]}]}
    tr = build_trajectory(seg, {"lat_deg": 41.275, "lon_deg": 1.987, "h_m": 50.0}, 1.0)
    with pytest.raises(ConfigError, match=r"specific force 3(\.0+\d*)? g on body axis x at t = 0.01 s"):
        synthesize_imu(tr, 100.0, imu_errors_from_config({"preset": "ideal", "accel_range_g": 2.0}))
    # the defaults (2000 deg/s, 50 g, 5e4 deg/s^2) and a range key checked like any other
    with pytest.raises(ConfigError, match="rate 2100 deg/s on body axis x at t = 0.01 s"):
        check_limits(np.array([[math.radians(21.0), 0.0, 0.0]]), np.zeros((1, 3)), 100.0)
    with pytest.raises(ConfigError, match="imu.accel_range_g must be a number > 0"):
        imu_errors_from_config({"accel_range_g": -1.0})


def _cli(args, cwd):
    return subprocess.run([sys.executable, "-m", "ultratight.receiver.cli", *args], cwd=cwd, capture_output=True,
                          text=True, timeout=300)


SCEN = """name = "file-physics"
duration_s = 0.5
[trajectory]
kind = "file"
path = "{path}"
[frontend]
fs_hz = 2.046e6
[imu]
preset = "ideal"
"""


@pytest.mark.parametrize("edit, needle", [
    ("jump", "line 103: speed 100000 m/s from t = 10 s to t = 10.1 s is above 20000 m/s"),
    ("nan", "line 52: column y is nan (NaN/inf not allowed)"),
    ("backwards", "line 82: time 7.5 s does not increase (previous 7.9 s)"),
])
def test_generate_refuses_unphysical_files(tmp_path, edit, needle):
    t = np.round(np.arange(0.0, 20.0 + 1e-9, 0.1), 1)
    enu = np.zeros((t.size, 3))
    rows = [f"{tk:.1f},{x:.4f},{y:.4f},{z:.4f}" for tk, (x, y, z) in zip(t, R0 + enu @ C_EL.T)]
    # row i is t = i / 10 s, on line i + 2 (after the header)
    if edit == "jump":            # 10 km east in 0.1 s at t = 10.1 s
        x, y, z = R0 + np.array([10000.0, 0.0, 0.0]) @ C_EL.T
        rows[101] = f"10.1,{x:.4f},{y:.4f},{z:.4f}"
    elif edit == "nan":
        f = rows[50].split(",")
        rows[50] = ",".join([f[0], f[1], "nan", f[3]])
    else:
        rows[80] = "7.5" + rows[80][rows[80].index(","):]
    (tmp_path / "traj.csv").write_text("t,x,y,z\n" + "\n".join(rows) + "\n")
    (tmp_path / "s.toml").write_text(SCEN.format(path="traj.csv"))
    before = sorted(p.name for p in tmp_path.iterdir())
    res = _cli(["generate", "s.toml", "--out", "out/r"], tmp_path)
    err = res.stderr.strip().splitlines()
    assert res.returncode == 2 and len(err) == 1, res.stderr
    assert "traj.csv" in err[0] and needle in err[0] and "Traceback" not in res.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == before           # nothing written


def test_rocket_launch_scenario_loads_and_holds_on_the_pad():
    cfg = load_scenario("rocket-launch")
    assert cfg["trajectory"]["kind"] == "file" and cfg["atmosphere"]["iono"] == "klobuchar"
    tr = build_trajectory(cfg["trajectory"], cfg["receiver"], cfg["duration_s"])
    t = np.arange(0.0, 100.0 + 1e-9, 0.05)
    k = tr.kinematics(t)
    speed = np.linalg.norm(k["vel_l"], axis=1)
    assert np.max(speed[t < 59.0]) < 0.01 and 1100.0 < speed[-1] < 1250.0
    e = np.degrees(k["euler"])
    # on the pad: held at the rail's 89.5 deg, azimuth east; then a smooth pitch-over
    assert np.max(np.abs(e[t < 59.0, 1] - 89.5)) < 0.05 and np.max(np.abs(e[t < 59.0, 2] - 90.0)) < 0.05
    assert 50.0 < e[-1, 1] < 65.0 and np.max(_euler_steps_deg(np.radians(e))) < 0.5


def test_unsmoothed_jitter_beyond_100_g_is_refused_by_the_reader(tmp_path):
    # 2 cm jitter at 100 Hz through the interpolating spline: hundreds of g, no vehicle's
    rng = np.random.default_rng(5)
    t = np.round(np.arange(0.0, 10.0 + 1e-9, 0.01), 2)
    p = tmp_path / "jitter.csv"
    write_csv(p, t, rng.normal(0.0, 0.02, (t.size, 3)))
    with pytest.raises(InputFileError, match=r"jitter.csv: line \d+: acceleration .* g\) of the smoothed path at "
                                             r"t = .* s is above 100 g"):
        build_trajectory({"kind": "file", "path": str(p), "smoothing_hz": 0.0}, {}, 10.0)
    build_trajectory({"kind": "file", "path": str(p)}, {}, 10.0)          # smoothed at 1 Hz: accepted


def test_ins_refuses_an_imu_beyond_the_declared_gyro_range(tmp_path):
    src = load_scenario("vehicle-turns")["source_file"]
    text = open(src).read().replace('preset = "tactical"', 'preset = "tactical"\ngyro_range_dps = 30.0')
    (tmp_path / "turns.toml").write_text(text)
    res = _cli(["ins", "turns.toml", "--duration", "10"], tmp_path)
    err = res.stderr.strip().splitlines()
    assert res.returncode == 2 and len(err) == 1 and "Traceback" not in res.stderr
    # the right turn of 37.5 deg/s from t = 8 s (body z, FLU)
    assert "IMU angular rate -37.49" in err[0] and "at t = 8.01 s" in err[0] and "imu.gyro_range_dps" in err[0]
