"""IMU declaration (ultratight.ins.imu_decl): the same IMU in three axis conventions and both kinds
navigates identically when declared correctly; wrong declarations are refused by the stationary
sanity check with a one-line reason; sidecar/flag plumbing; time reference and offset."""

import json
import subprocess
import sys

import numpy as np
import pytest

from ultratight.errors import ConfigError, InputFileError
from ultratight.ins import imu_decl
from ultratight.ins.imu import imu_errors_from_config, synthesize_imu
from ultratight.ins.imu_data import read_imu_csv, write_imu_csv
from ultratight.ins.imu_decl import ImuDeclaration, axes_matrix, resolve_declaration
from ultratight.ins.trajectory import build_trajectory
from ultratight.receiver.cli import main

LEVER = np.array([0.5, -0.2, 1.0])
CONVENTIONS = [(axes, kind, gu, au) for axes in ("FLU", "FRD", "RFU")
               for kind, gu, au in (("rates", "deg/s", "g"), ("increments", "rad", "m/s"))]


@pytest.fixture(scope="module")
def imu():
    """Tactical IMU: 2 s standing still, then accelerating and turning (FLU, increments)."""
    tr = build_trajectory({"kind": "segments", "segments": [
        {"t0": 0.0}, {"t0": 2.0, "acc_enu": [1.0, 0.5, 0.2], "jerk_enu": [0.0, 0.3, 0.0]}]},
        {"lat_deg": 41.0, "lon_deg": 2.0, "h_m": 50.0}, 20.0)
    d = synthesize_imu(tr, 100.0, imu_errors_from_config({"preset": "tactical"}), np.random.default_rng(3))
    d.lever_arm_b = LEVER.copy()
    return d


@pytest.fixture(scope="module")
def files(imu, tmp_path_factory):
    d = tmp_path_factory.mktemp("decl")
    out = {}
    for axes, kind, gu, au in CONVENTIONS:
        p = d / f"imu_{axes}_{kind}.csv"
        write_imu_csv(p, imu, ImuDeclaration(kind=kind, axes=axes, gyro_unit=gu, accel_unit=au))
        out[axes, kind] = p
    return out


def _ins_json(capsys, *args):
    assert main(["ins", *args, "--json"]) == 0
    return json.loads(capsys.readouterr().out)


def test_three_axes_two_kinds_navigate_identically(imu, files, capsys):
    init = ["--init-llh", "41", "2", "50", "--init-att", "0", "0", "0"]
    runs = {key: _ins_json(capsys, str(p), *init) for key, p in files.items()}
    ref = runs["FLU", "increments"]
    # the file really is in its declared convention: FRD flips y and z, RFU swaps x and y
    first = {key: np.array(p.read_text().splitlines()[2].split(","), float) for key, p in files.items()}
    assert first["FRD", "increments"][2:4] == pytest.approx(-first["FLU", "increments"][2:4])
    assert first["RFU", "increments"][1] == pytest.approx(-first["FLU", "increments"][2])
    assert first["FLU", "rates"][6] == pytest.approx(first["FLU", "increments"][6] / 0.01 / 9.80665)
    for key, out in runs.items():
        assert out["sanity_check"]["checked"] and out["sanity_check"]["window"] == [0, 100], key
        llh = np.radians(out["final_llh_deg_m"][:2]) * 6.4e6
        assert np.max(np.abs(llh - np.radians(ref["final_llh_deg_m"][:2]) * 6.4e6)) < 1e-9, key
        assert abs(out["final_llh_deg_m"][2] - ref["final_llh_deg_m"][2]) < 1e-9, key
        assert np.max(np.abs(np.subtract(out["final_vel_enu_mps"], ref["final_vel_enu_mps"]))) < 1e-9, key
    # and as the internal HDF5 convention would: the increments read back equal the originals
    for key, p in files.items():
        d = read_imu_csv(p)
        assert np.max(np.abs(d.dtheta_b - imu.dtheta_b)) < 1e-15 and np.max(np.abs(d.dv_b - imu.dv_b)) < 1e-14
        assert d.lever_arm_b == pytest.approx(LEVER, abs=1e-15), key
    assert np.linalg.norm(ref["final_vel_enu_mps"]) > 10.0        # it did move


@pytest.mark.parametrize("file_key, flags, needle", [
    (("FRD", "rates"), ["--imu-axes", "FLU"], "axes look FRD, declared FLU"),
    (("FLU", "rates"), ["--imu-axes", "FRD"], "axes look FLU, declared FRD"),
    (("FRD", "rates"), ["--imu-accel-unit", "m/s^2"], "accelerometer units look g, declared m/s^2"),
    (("FLU", "rates"), ["--imu-gyro-unit", "rad/s"], "gyro units look deg/s, declared rad/s"),
    (("RFU", "increments"), ["--imu-gyro-unit", "deg"], "gyro units look rad, declared deg"),
    (("FLU", "rates"), ["--imu-rate", "200"], "declared rate 200 Hz"),
    (("FLU", "rates"), ["--imu-kind", "increments"], "gyro_unit 'deg/s' is a unit of rates, but kind = 'incr"),
    (("FLU", "rates"), ["--imu-kind", "increments", "--imu-gyro-unit", "rad", "--imu-accel-unit", "m/s"],
     "declared kind 'increments'"),
    (("FLU", "rates"), ["--imu-axes", "FLD"], "not a right-handed set"),
])
def test_wrong_declarations_are_one_line_errors(files, file_key, flags, needle):
    r = subprocess.run([sys.executable, "-m", "ultratight.receiver.cli", "ins", str(files[file_key]),
                        "--init-llh", "41", "2", "50", *flags], capture_output=True, text=True)
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 2 and len(lines) == 1, r.stderr
    assert needle in lines[0]


def test_increments_under_rate_names_are_recognised(files, tmp_path):
    src = files["FLU", "increments"].read_text().replace("dthx,dthy,dthz,dvx,dvy,dvz", "gx,gy,gz,ax,ay,az")
    p = tmp_path / "inc_named_rates.csv"
    p.write_text(src)
    with pytest.raises(InputFileError, match="values look like increments, declared rates"):
        read_imu_csv(p, resolve_declaration(None, {"gyro_unit": "rad/s", "accel_unit": "m/s^2"}))
    # the check can be switched off (for records whose still part is not gravity-like)
    d = read_imu_csv(p, resolve_declaration(None, {"gyro_unit": "rad/s", "accel_unit": "m/s^2", "check": False}))
    assert d.meta["sanity_check"]["checked"] is False


def test_steady_motion_is_accepted_and_a_swinging_record_is_not_checked(imu, tmp_path):
    # the accelerating, turning part only: steady enough to pass for still, and correctly declared,
    # so it must not be refused (the turn rate is ~1000 Earth rates: no gyro verdict)
    p = tmp_path / "moving.csv"
    moving = type(imu)(t=imu.t[300:] - imu.t[299], dtheta_b=imu.dtheta_b[300:], dv_b=imu.dv_b[300:],
                       rate_hz=imu.rate_hz, t0=0.0, meta={})
    write_imu_csv(p, moving, ImuDeclaration(kind="rates", axes="FRD", gyro_unit="rad/s", accel_unit="m/s^2"))
    rep = read_imu_csv(p).meta["sanity_check"]
    assert rep["checked"] is True and rep["gyro_in_range"] is False
    # a swinging base (+-10 deg roll, +-8 deg pitch) never stands still: the check is skipped
    tr = build_trajectory({"kind": "swing"}, {"lat_deg": 41.0, "lon_deg": 2.0, "h_m": 50.0}, 10.0)
    sw = synthesize_imu(tr, 100.0)
    p2 = tmp_path / "swing.csv"
    write_imu_csv(p2, sw, ImuDeclaration(kind="increments", axes="FRD", gyro_unit="deg", accel_unit="m/s"))
    rep = read_imu_csv(p2).meta["sanity_check"]
    assert rep["checked"] is False and "never stands still" in rep["reason"]


def test_axes_matrix_and_lever_arm():
    assert np.array_equal(axes_matrix("FRD"), np.diag([1.0, -1.0, -1.0]))
    assert np.array_equal(axes_matrix("RFU") @ [1.0, 0.0, 0.0], [0.0, -1.0, 0.0])    # file x = right
    m = axes_matrix([[0, 1, 0], [-1, 0, 0], [0, 0, 1]])
    assert np.allclose(m, axes_matrix("RFU"))
    with pytest.raises(ConfigError, match="proper rotation"):
        axes_matrix([[1, 0, 0], [0, 1, 0], [0, 0, -1]])
    dec = resolve_declaration(None, {"axes": "FRD", "lever_arm_m": [1.0, 2.0, 3.0]})
    assert np.array_equal(dec.lever_arm_b(), [1.0, -2.0, -3.0])


def test_sidecar_keys_units_and_conflicts(files, tmp_path):
    p = files["FRD", "rates"]
    side = json.loads(imu_decl.sidecar_path(p).read_text())
    assert side["axes"] == "FRD" and side["gyro_unit"] == "deg/s" and side["accel_unit"] == "g"
    assert side["lever_arm_m"] == pytest.approx([0.5, 0.2, -1.0])     # FLU lever in FRD axes
    bad = tmp_path / "x.csv"
    bad.write_text(p.read_text())
    imu_decl.sidecar_path(bad).write_text(json.dumps(dict(side, axis="FRD")))
    with pytest.raises(InputFileError, match="unknown IMU sidecar key 'axis' \\(did you mean 'axes'\\?\\)"):
        read_imu_csv(bad)
    # a unit suffix in the header that contradicts the declaration
    hdr = tmp_path / "h.csv"
    hdr.write_text(p.read_text().replace("t_s,gx,gy,gz,ax,ay,az", "t_s,gx_radps,gy_radps,gz_radps,ax,ay,az"))
    imu_decl.sidecar_path(hdr).write_text(json.dumps(side))
    with pytest.raises(InputFileError, match="gyro unit 'rad/s' in the header but 'deg/s' declared"):
        read_imu_csv(hdr)
    with pytest.raises(ConfigError, match="gyro_unit 'rad' is a unit of increments, but kind = 'rates'"):
        resolve_declaration(None, {"kind": "rates", "gyro_unit": "rad"})


def test_gps_time_reference_offset_and_alignment(imu, tmp_path):
    p = tmp_path / "gps.csv"
    src = type(imu)(t=imu.t, dtheta_b=imu.dtheta_b, dv_b=imu.dv_b, rate_hz=100.0, t0=0.0,
                    meta={"start_tow_s": 518399.5})
    # the IMU clock runs 0.25 s behind GPS: stamps written as GPS time - 0.25 s, offset declared
    write_imu_csv(p, src, ImuDeclaration(kind="increments", axes="FLU", time_ref="gps_tow", gps_week=2190,
                                         time_offset_s=0.25))
    assert float(p.read_text().splitlines()[2].split(",")[0]) == pytest.approx(518399.5 + 0.01 - 0.25)
    d = read_imu_csv(p)
    assert d.meta["start_tow_s"] == pytest.approx(518399.5) and d.meta["start_week"] == 2190
    assert d.t[0] == pytest.approx(0.01) and d.t0 == 0.0
    # the IF starts 0.5 s later: 50 samples are dropped, the time axis starts at the IF start
    a = imu_decl.align_to_gps_start(d, 2190, 518400.0, p)
    assert a.meta["trimmed_samples"] == 50 and a.t[0] == pytest.approx(0.01)
    assert np.array_equal(a.dv_b, imu.dv_b[50:])
    with pytest.raises(InputFileError, match="not on the IMU's 0.01 s sample grid"):
        imu_decl.align_to_gps_start(read_imu_csv(p), 2190, 518400.0043, p)


def test_hdf5_takes_only_a_lever_arm(imu, tmp_path):
    from ultratight.ins.imu_data import write_imu_h5
    p = tmp_path / "x.imu.h5"
    write_imu_h5(p, imu)
    assert np.array_equal(imu_decl.read_imu_file(p).lever_arm_b, LEVER)
    assert np.array_equal(imu_decl.read_imu_file(p, {"lever_arm_m": [0, 0, 2]}).lever_arm_b, [0, 0, 2])
    with pytest.raises(ConfigError, match="axes can only be declared for a CSV file"):
        imu_decl.read_imu_file(p, {"axes": "FRD"})


def test_ten_g_from_the_first_sample_is_not_mistaken_for_rates_in_g(tmp_path):
    """paper-highdyn accelerates at 100 m/s^2 from t = 0: its 100 Hz velocity increments (1.005 m/s)
    read as rates in g are 9.86 m/s^2 — gravity. The gyro (the Earth rate as increments, 1/100 of it
    as rates) says the declaration is right: the check steps aside instead of refusing it."""
    tr = build_trajectory({"kind": "segments", "segments": [{"t0": 0.0, "acc_enu": [100.0, 4.0, 0.0]}]},
                          {"lat_deg": 28.246, "lon_deg": 102.0266, "h_m": 50000.0}, 3.0)
    d = synthesize_imu(tr, 100.0)
    p = tmp_path / "tenG.csv"
    write_imu_csv(p, d, ImuDeclaration(kind="increments", axes="FLU", gyro_unit="rad", accel_unit="m/s"))
    rep = read_imu_csv(p).meta["sanity_check"]
    assert rep["checked"] is False and "not at rest" in rep["reason"]


def test_a_body_standing_on_end_passes_and_an_upside_down_declaration_does_not():
    """A rocket on its pad: gravity on the file's x axis, declared FRD (x forward, pointing up) is a
    body standing on end — accepted and reported; declared with x as the up axis (ULB) it is a level
    body; declared with x as a down axis (DRB) the body would be upside down: the sign of a mix-up."""
    from ultratight.ins.imu_decl import stationary_check

    dt = 0.01
    n = 200
    f = np.tile([9.80665, 0.0, 0.0], (n, 1))                     # m/s^2, x up
    w = np.tile([7.292115e-5, 0.0, 0.0], (n, 1))                  # rad/s: the Earth rate (at the pole, on x)
    rep = stationary_check(f, w, dt, resolve_declaration(None, {"axes": "FRD"}), "m/s^2", "rad/s", "rates", "p.csv")
    assert rep["checked"] and rep["stands_on_end"]
    rep = stationary_check(f, w, dt, resolve_declaration(None, {"axes": "ULB"}), "m/s^2", "rad/s", "rates", "p.csv")
    assert rep["checked"] and not rep["stands_on_end"]
    with pytest.raises(InputFileError, match="declared DRB"):
        stationary_check(f, w, dt, resolve_declaration(None, {"axes": "DRB"}), "m/s^2", "rad/s", "rates", "p.csv")
