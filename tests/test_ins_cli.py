"""``ultratight ins``: scenario run with JSON output, IMU files, one-line user errors."""

import json

import numpy as np

from ultratight.receiver.cli import main


def test_ins_scenario_error_free_json(capsys):
    rc = main(["ins", "paper-highdyn", "--errors", "ideal", "--duration", "30", "--json"])
    assert rc == 0
    out = json.loads(capsys.readouterr().out)
    for key in ("final_pos_err_m", "final_vel_err_mps", "final_att_err_deg", "max_pos_err_m", "imu_rate_hz"):
        assert key in out
    assert out["imu_rate_hz"] == 100.0 and out["n_steps"] == 3000
    assert out["max_pos_err_m"] < 0.05 and out["final_vel_err_mps"] < 5e-3 and out["final_att_err_deg"] < 1e-4


def test_ins_imu_file_round_trip(tmp_path, capsys):
    p = tmp_path / "run.imu.h5"
    assert main(["ins", "static-open-sky", "--duration", "20", "--errors", "paper", "--seed", "4",
                 "--save-imu", str(p), "--json"]) == 0
    first = json.loads(capsys.readouterr().out)
    assert main(["ins", str(p), "--json"]) == 0
    second = json.loads(capsys.readouterr().out)
    assert second["final_pos_err_m"] == first["final_pos_err_m"]
    assert first["final_pos_err_m"] > 0.0        # paper biases make it drift


def test_ins_bad_csv_is_one_line_error(tmp_path, capsys):
    p = tmp_path / "bad.csv"
    p.write_text("t_s,dthx_rad,dthy_rad,dthz_rad,dvx_mps,dvy_mps,dvz_mps\n"
                 "0.01,0,0,0,0,0,0.098\n0.02,0,0,0,0,0,0.098\n0.015,0,0,0,0,0,0.098\n")
    rc = main(["ins", str(p), "--init-llh", "30", "100", "0"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "line 4" in err[0] and "out-of-order" in err[0]


def test_ins_csv_without_truth_needs_initial_state(tmp_path, capsys):
    p = tmp_path / "ok.csv"
    rows = "".join(f"{0.01 * (k + 1):.2f},0,0,0,0,0,{9.79 * 0.01}\n" for k in range(100))
    p.write_text("t_s,dthx_rad,dthy_rad,dthz_rad,dvx_mps,dvy_mps,dvz_mps\n" + rows)
    assert main(["ins", str(p)]) == 2
    assert "--init-llh" in capsys.readouterr().err
    assert main(["ins", str(p), "--init-llh", "30", "100", "0", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["n_steps"] == 100 and np.isclose(out["final_llh_deg_m"][0], 30.0, atol=1e-6)
