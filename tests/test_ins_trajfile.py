"""Trajectories from files (ultratight.ins.trajfile, [trajectory] kind = "file"): readers, the C2
smoothing spline against closed-form motion, attitude from the file, checks naming the line, and
the scenario plumbing (path relative to the TOML)."""

import json
import math

import numpy as np
import pytest

from ultratight.errors import ConfigError, InputFileError
from ultratight.ins.earth import dcm_ecef_from_enu, ecef_to_llh_batch, llh_to_ecef
from ultratight.ins.imu import synthesize_imu
from ultratight.ins.sins import make_state, nav_errors, sins_run
from ultratight.ins.trajectory import build_trajectory
from ultratight.ins.trajfile import read_position_log
from ultratight.receiver.cli import main
from ultratight.receiver.cli.scenario_config import load_scenario

LAT, LON, H = math.radians(41.275), math.radians(1.987), 50.0
R_M, V_MPS = 200.0, 20.0
W = V_MPS / R_M


def circle_enu(t):
    """Closed-form circle (start heading north, turning right): ENU position, velocity, acceleration."""
    p = np.stack([R_M - R_M * np.cos(W * t), R_M * np.sin(W * t), 0 * t], 1)
    v = np.stack([V_MPS * np.sin(W * t), V_MPS * np.cos(W * t), 0 * t], 1)
    a = np.stack([V_MPS * W * np.cos(W * t), -V_MPS * W * np.sin(W * t), 0 * t], 1)
    return p, v, a


def circle_ecef(t):
    r0 = np.asarray(llh_to_ecef(LAT, LON, H))
    return circle_enu(t)[0] @ dcm_ecef_from_enu(LAT, LON).T + r0


def write_ecef_csv(path, duration_s=60.0, rate_hz=10.0, header=False, decimals=4):
    t = np.arange(0.0, duration_s + 1e-9, 1.0 / rate_hz)
    p = circle_ecef(t)
    with open(path, "w") as f:
        if header:
            f.write("# vehicle circle\nt_s,x_m,y_m,z_m\n")
        for k in range(t.size):
            f.write(f"{t[k]:.3f},{p[k, 0]:.{decimals}f},{p[k, 1]:.{decimals}f},{p[k, 2]:.{decimals}f}\n")
    return t, p


def _nmea(body):
    c = 0
    for ch in body:
        c ^= ord(ch)
    return f"${body}*{c:02X}"


def write_gga(path, duration_s=60.0):
    t = np.arange(0.0, duration_s + 1e-9, 1.0)
    llh = ecef_to_llh_batch(circle_ecef(t))
    lines = []
    for k in range(t.size):
        s = 86390.0 + t[k]                 # crosses midnight after 10 s
        s = s % 86400.0
        hms = f"{int(s // 3600):02d}{int(s % 3600 // 60):02d}{s % 60:05.2f}"
        lat, lon = math.degrees(llh[k, 0]), math.degrees(llh[k, 1])
        la = f"{int(lat):02d}{(lat - int(lat)) * 60:010.7f}"
        lo = f"{int(lon):03d}{(lon - int(lon)) * 60:010.7f}"
        # altitude above the geoid + separation 49.5 m = ellipsoidal height
        lines.append(_nmea(f"GPGGA,{hms},{la},N,{lo},E,1,08,0.9,{llh[k, 2] - 49.5:.3f},M,49.5,M,,"))
    lines.insert(3, _nmea("GPGGA,000000.00,,,,,0,00,,,M,,M,,"))       # no fix: skipped
    lines.insert(5, _nmea("GPRMC,000000.00,A,4116.5,N,00159.2,E,0.0,0.0,010122,,,A"))   # not GGA: ignored
    path.write_text("\n".join(lines) + "\n")
    return t, llh


@pytest.fixture(scope="module")
def circle_csv(tmp_path_factory):
    p = tmp_path_factory.mktemp("traj") / "circle.csv"
    write_ecef_csv(p)
    return p


@pytest.fixture(scope="module")
def circle_traj(circle_csv):
    return build_trajectory({"kind": "file", "path": str(circle_csv), "frame": "ecef"}, {}, 60.0)


def test_spline_follows_the_closed_form_circle(circle_traj):
    tr = circle_traj
    assert tr.attitude_mode == "velocity"
    assert math.degrees(tr.lat0) == pytest.approx(41.275, abs=1e-9) and tr.h0 == pytest.approx(H, abs=1e-3)
    t = np.linspace(3.0, 57.0, 1001)           # away from the natural end conditions
    k = tr.kinematics(t)
    p, v, a = circle_enu(t)
    assert np.max(np.abs(k["pos_l0"] - p)) < 2e-3
    assert np.max(np.abs(k["vel_l0"] - v)) < 2e-3
    assert np.max(np.abs(k["acc_l0"] - a)) < 0.02 * V_MPS * W
    # heading from the velocity: yaw = w t (clockwise from north)
    yaw = np.unwrap(k["euler"][:, 2])
    assert np.max(np.abs(yaw - W * t)) < 1e-4
    # ends: the spline stays on the file's positions within a few cm
    k0 = tr.kinematics(np.array([0.0, 60.0]))
    assert np.max(np.abs(k0["pos_l0"] - circle_enu(np.array([0.0, 60.0]))[0])) < 0.05


def test_spline_is_c2_at_the_knots(circle_traj):
    knots = circle_traj.breakpoints()
    # interior samples of a 10 Hz, 60 s file (599), each interval halved by the 0.05 s grid of the
    # attitude along the velocity (docs/trajectory-files.md)
    assert knots.size == 1199 and np.allclose(knots[1::2], np.arange(1, 600) * 0.1, atol=1e-9)
    tk = knots[1::2][100:110]
    lo = circle_traj.local_motion(tk - 1e-7)
    hi = circle_traj.local_motion(tk + 1e-7)
    assert np.max(np.abs(hi[2] - lo[2])) < 1e-5          # acceleration continuous
    assert np.max(np.abs(hi[3] - lo[3])) > 1e-4          # jerk steps (cubic spline)


def test_error_free_sins_follows_the_file_trajectory(circle_traj):
    imu = synthesize_imu(circle_traj, 100.0)
    T = imu.truth
    q, v, p = sins_run(make_state(T["q_lb"][0], T["vel_l"][0], T["llh"][0]), imu.dtheta_b, imu.dv_b, 0.01)
    dp, dv, da = nav_errors(q, v, p, T["q_lb"], T["vel_l"], T["llh"])
    assert np.max(np.linalg.norm(dp, axis=1)) < 5e-3
    assert np.max(np.linalg.norm(dv, axis=1)) < 1e-4


def test_smoothing_cut_off_as_documented(tmp_path):
    # a 2 m vertical wobble at the cut-off frequency is halved, one at a fifth of it passes
    t = np.arange(0.0, 60.0 + 1e-9, 0.1)
    base = circle_ecef(t)
    up = dcm_ecef_from_enu(LAT, LON)[:, 2]
    for f_hz, lo, hi in ((1.0, 0.42, 0.58), (0.2, 0.99, 1.01)):
        p = base + 2.0 * np.sin(2 * np.pi * f_hz * t)[:, None] * up
        path = tmp_path / f"wobble{f_hz}.csv"
        np.savetxt(path, np.column_stack([t, p]), delimiter=",", fmt="%.6f")
        tr = build_trajectory({"kind": "file", "path": str(path), "smoothing_hz": 1.0}, {}, 60.0)
        ts = np.linspace(10.0, 50.0, 4001)
        u = tr.kinematics(ts)["pos_l0"][:, 2] - circle_enu(ts)[0][:, 2]
        gain = np.sqrt(2.0 * np.mean(u ** 2)) / 2.0
        assert lo < gain < hi, (f_hz, gain)


def test_llh_csv_header_csv_and_gga_give_the_same_path(tmp_path, circle_traj):
    t = np.arange(0.0, 60.0 + 1e-9, 0.1)
    llh = ecef_to_llh_batch(circle_ecef(t))
    p_llh = tmp_path / "c_llh.csv"
    with open(p_llh, "w") as f:
        f.write("t,lat_deg,lon_deg,h_m\n")
        for k in range(t.size):
            f.write(f"{t[k]:.1f},{math.degrees(llh[k, 0]):.10f},{math.degrees(llh[k, 1]):.10f},{llh[k, 2]:.4f}\n")
    p_hdr = tmp_path / "c_hdr.csv"
    write_ecef_csv(p_hdr, header=True)
    tq = np.linspace(5.0, 55.0, 201)
    ref = circle_traj.pos_vel_e(tq)[0]
    for p, frame in ((p_llh, "llh"), (p_hdr, "ecef")):
        tr = build_trajectory({"kind": "file", "path": str(p), "frame": frame}, {}, 60.0)
        assert np.max(np.linalg.norm(tr.pos_vel_e(tq)[0] - ref, axis=1)) < 0.01
    p_gga = tmp_path / "c.nmea"
    write_gga(p_gga)
    log = read_position_log(p_gga)
    assert log.format == "nmea-gga" and log.t.size == 61 and log.t[-1] == pytest.approx(60.0)
    tr = build_trajectory({"kind": "file", "path": str(p_gga), "smoothing_hz": 0.0}, {}, 60.0)
    # 1 Hz interpolating spline of a 0.1 rad/s circle: within a few cm between the fixes
    assert np.max(np.linalg.norm(tr.pos_vel_e(tq)[0] - ref, axis=1)) < 0.1


def test_attitude_columns(tmp_path):
    t = np.arange(0.0, 30.0 + 1e-9, 0.1)
    p = circle_ecef(t)
    roll = 5.0 * np.sin(0.3 * t)
    pitch = 2.0 + 0 * t
    yaw = np.degrees(W * t) % 360.0 + 10.0              # wraps at 360: unwrapped on read
    path = tmp_path / "att.csv"
    np.savetxt(path, np.column_stack([t, p, roll, pitch, yaw]), delimiter=",", fmt="%.8f",
               header="t,x,y,z,roll,pitch,yaw", comments="")
    tr = build_trajectory({"kind": "file", "path": str(path)}, {}, 30.0)
    assert tr.attitude_mode == "file"
    tq = np.linspace(5.0, 25.0, 101)
    e = np.degrees(tr.kinematics(tq)["euler"])
    yaw_true = (np.degrees(W * tq) + 10.0) % 360.0
    assert np.max(np.abs(e[:, 0] - 5.0 * np.sin(0.3 * tq))) < 1e-3
    assert np.max(np.abs(e[:, 1] - 2.0)) < 1e-3
    assert np.max(np.abs((e[:, 2] - yaw_true + 180.0) % 360.0 - 180.0)) < 1e-3
    # the IMU synthesised from it is consistent with the attitude truth (exact body rates)
    imu = synthesize_imu(tr, 100.0)
    T = imu.truth
    q, v, pp = sins_run(make_state(T["q_lb"][0], T["vel_l"][0], T["llh"][0]), imu.dtheta_b, imu.dv_b, 0.01)
    dp, dv, da = nav_errors(q, v, pp, T["q_lb"], T["vel_l"], T["llh"])
    assert np.max(np.abs(da)) < 1e-6 and np.max(np.linalg.norm(dp, axis=1)) < 5e-3


@pytest.mark.parametrize("body, frame, needle", [
    ("0,4797650,166447,4185457\n0.1,4797650,166447,4185458\n0.1,4797650,166447,4185459\n"
     "0.3,4797650,166447,4185460\n", "ecef", "line 3: time 0.1 s does not increase"),
    ("0,4797650,166447,4185457\n0.5,4797650,166447,4185458\n2.0,4797650,166447,4185459\n"
     "2.5,4797650,166447,4185460\n", "ecef", "line 3: interval of 1.5 s"),
    ("t,x,y,z\n0,4797650,166447,4185457\n0.1,4797650,abc,4185458\n0.2,4797650,166447,4185459\n"
     "0.3,4797650,166447,4185460\n", "ecef", "line 3: column y: 'abc' is not a number"),
    ("0,4797650,166447,4185457\n0.1,4797650,166447,4185458\n", "ecef", "at least 4"),
    ("0,4797650,166447,4185457\n0.1,4797650,166447,4185458\n0.2,4797650,166447,4185459\n"
     "0.3,4797650,166447,4185460\n", "llh", "line 1: latitude 4797650.0 deg outside"),
    ("0,41.2,1.9,50\n0.1,41.2,1.9,50\n0.2,41.2,1.9,50\n0.3,41.2,1.9,50\n", "ecef",
     "line 1: position [41.2, 1.9, 50.0] m is 0.1 km from the Earth's centre"),
    ("t,x,y\n0,1,2\n", "ecef", "line 1: header for frame = \"ecef\" needs columns t, x, y, z; missing z"),
    ("$GPGGA,000000.00,4116.5,N,00159.2,E,1,08,0.9,50.0,M,0.0,M,,*00\n", "ecef", "line 1: NMEA checksum mismatch"),
])
def test_bad_files_name_file_and_line(tmp_path, body, frame, needle):
    p = tmp_path / "bad.csv"
    p.write_text(body)
    with pytest.raises(InputFileError) as ei:
        read_position_log(p, frame)
    msg = str(ei.value)
    assert str(p) in msg and needle in msg and "\n" not in msg


SCEN = """name = "circle-file"
duration_s = {dur}
[time]
week = 2190
tow_s = 518400.0
[trajectory]
kind = "file"
path = "{path}"
frame = "ecef"
[imu]
preset = "ideal"
rate_hz = 100.0
"""


def test_scenario_resolves_the_path_next_to_the_toml(tmp_path, capsys):
    d = tmp_path / "scen"
    (d / "logs").mkdir(parents=True)
    write_ecef_csv(d / "logs" / "circle.csv")
    toml = d / "circle.toml"
    toml.write_text(SCEN.format(dur=30.0, path="logs/circle.csv"))
    cfg = load_scenario(str(toml))
    assert cfg["trajectory"]["path"] == str((d / "logs" / "circle.csv").resolve())
    assert len(cfg["trajectory"]["file_sha256"]) == 64
    assert cfg["receiver"]["lat_deg"] == pytest.approx(41.275, abs=1e-9)
    # `ultratight ins` on the scenario: the synthetic error-free IMU reproduces the file's path
    assert main(["ins", str(toml), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["max_pos_err_m"] < 5e-3 and out["n_steps"] == 3000
    # duration longer than the file / bad file: one-line errors naming the file
    toml.write_text(SCEN.format(dur=90.0, path="logs/circle.csv"))
    with pytest.raises(ConfigError, match="circle.csv: covers 60 s, shorter than duration_s = 90 s"):
        load_scenario(str(toml))
    with pytest.raises(ConfigError, match="covers 60 s, shorter than duration_s = 90 s"):
        build_trajectory({"kind": "file", "path": str(d / "logs" / "circle.csv")}, {}, 90.0)
    (d / "logs" / "bad.csv").write_text("0,1,2,3\n0,1,2,3\n")
    toml.write_text(SCEN.format(dur=30.0, path="logs/bad.csv"))
    rc = main(["ins", str(toml)])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "bad.csv" in err[0] and "at least 4" in err[0]
    toml.write_text(SCEN.format(dur=30.0, path="logs/missing.csv"))
    with pytest.raises(ConfigError, match="missing.csv: trajectory file not found"):
        load_scenario(str(toml))
