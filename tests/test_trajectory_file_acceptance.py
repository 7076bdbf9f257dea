"""Acceptance (issue 13, trajectory from file; slow, ~10 min on 2 cores): a 10 Hz ECEF CSV of a
300 s vehicle circle -> `ultratight generate` (IF + IMU + truth) -> scalar `process`: 3D RMS
<= 1 m against the CSV; -> `process --mode ultratight` with the generator's IMU, from the assisted
truth-perturbed start and from the engine's own scalar start: <= 1 m each and no lock loss.  The
same run by hand: docs/trajectory-files.md."""

import json
import math

import h5py
import numpy as np
import pytest

from ultratight.ins.earth import dcm_ecef_from_enu, llh_to_ecef
from ultratight.receiver.cli import main

pytestmark = pytest.mark.slow

SCEN = """name = "vehicle-circle-file"
description = "300 s vehicle circle (200 m radius, 20 m/s) from a 10 Hz ECEF CSV"
duration_s = 300.0
seed = 3
[time]
week = 2190
tow_s = 518400.0
[trajectory]
kind = "file"
path = "circle.csv"
frame = "ecef"
[satellites]
source = "nominal"
max_count = 12
mask_deg = 5.0
cn0_dbhz = 45.0
[frontend]
fs_hz = 2.046e6
sampling = "complex"
format = "ci8"
bits = 8
[imu]
preset = "tactical"
rate_hz = 100.0
"""


def _rms_against(csv_t, csv_p, t, p):
    ref = np.stack([np.interp(t, csv_t, csv_p[:, i]) for i in range(3)], 1)
    return float(np.sqrt(np.mean(np.sum((p - ref) ** 2, axis=1))))


def test_circle_csv_generate_scalar_and_ultratight(tmp_path, capsys):
    lat, lon = math.radians(41.275), math.radians(1.987)
    t = np.arange(0.0, 300.0 + 1e-9, 0.1)
    enu = np.stack([200.0 - 200.0 * np.cos(0.1 * t), 200.0 * np.sin(0.1 * t), 0 * t], 1)
    p = enu @ dcm_ecef_from_enu(lat, lon).T + np.asarray(llh_to_ecef(lat, lon, 50.0))
    np.savetxt(tmp_path / "circle.csv", np.column_stack([t, p]), delimiter=",", fmt="%.4f")
    csv = np.loadtxt(tmp_path / "circle.csv", delimiter=",")
    (tmp_path / "circle.toml").write_text(SCEN)
    out = tmp_path / "circ"
    assert main(["generate", str(tmp_path / "circle.toml"), "--out", str(out), "--no-progress"]) == 0
    capsys.readouterr()
    # scalar receiver; the generated signal has no atmosphere, so no tropospheric correction
    assert main(["process", str(tmp_path / "circ.ci8"), "--tropo", "off", "--iono", "off",
                 "--csv", str(tmp_path / "scalar.csv"), "--json", "--no-progress"]) == 0
    summ = json.loads(capsys.readouterr().out)
    assert summ["fixes"] > 2500
    fx = np.genfromtxt(tmp_path / "scalar.csv", delimiter=",", names=True)
    rms_scalar = _rms_against(csv[:, 0], csv[:, 1:], fx["t_s"], np.stack([fx["x_m"], fx["y_m"], fx["z_m"]], 1))
    # ultra-tight engine with the generator's IMU (hot start from the IMU file's truth, perturbed)
    assert main(["process", str(tmp_path / "circ.ci8"), "--mode", "ultratight", "--imu",
                 str(tmp_path / "circ.imu.h5"), "--out", str(tmp_path / "ut.h5"), "--json",
                 "--startup", "truth-perturbed", "--bits", "assisted"]) == 0
    ut = json.loads(capsys.readouterr().out)
    with h5py.File(tmp_path / "ut.h5") as f:
        rms_ut = _rms_against(csv[:, 0], csv[:, 1:], f["nav_t_s"][()], f["nav_pos_e"][()])
    print(f"circle from CSV: scalar 3D RMS {rms_scalar:.3f} m over {summ['fixes']} fixes; ultra-tight 3D RMS "
          f"{rms_ut:.3f} m, lock losses {ut['lock_losses']}")
    assert rms_scalar <= 1.0
    assert ut["duration_s"] == pytest.approx(300.0, abs=0.01)
    assert ut["lock_losses"] == 0
    assert rms_ut <= 1.0
    # the command of docs/trajectory-files.md: the engine's own scalar start-up, no atmosphere corrections
    # (the signal carries none; a moving start-up's few fixes cannot test for a troposphere)
    capsys.readouterr()
    assert main(["process", str(tmp_path / "circ.ci8"), "--mode", "ultratight", "--imu", str(tmp_path / "circ.imu.h5"),
                 "--tropo", "off", "--iono", "off", "--out", str(tmp_path / "ut_own.h5"), "--json"]) == 0
    own = json.loads(capsys.readouterr().out)
    with h5py.File(tmp_path / "ut_own.h5") as f:
        rms_own = _rms_against(csv[:, 0], csv[:, 1:], f["nav_t_s"][()], f["nav_pos_e"][()])
    print(f"ultra-tight from its own scalar start ({own['startup']}): 3D RMS {rms_own:.3f} m, lock losses "
          f"{own['lock_losses']}, assisted {own['assisted']}")
    assert own["startup"] == "scalar-fix" and own["assisted"] == [] and own["lock_losses"] == 0
    assert rms_own <= 1.0
