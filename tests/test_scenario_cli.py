"""``ultratight scenario`` end to end: a 20 s cut of paper-highdyn (2.046 MHz to keep the test
short) through dlb-rackf and dlb-ckf, metrics vs the generator truth, JSON/HDF5 outputs, the
data cache, and user errors."""

import json

import pytest

from ultratight.receiver.cli import main


@pytest.fixture(scope="module")
def scenario_20s(tmp_path_factory):
    out = tmp_path_factory.mktemp("sc")
    return out


def _run(capsys, *argv):
    rc = main(list(argv))
    cap = capsys.readouterr()
    return rc, cap.out, cap.err


def test_paper_highdyn_20s_rackf_keeps_lock_and_beats_ckf(scenario_20s, capsys):
    rc, out, err = _run(capsys, "scenario", "paper-highdyn", "--duration", "20", "--fs-hz", "2.046e6",
                        "--methods", "dlb-rackf,dlb-ckf", "--seed", "3", "--json", "--no-plots",
                        "--out", str(scenario_20s))
    assert rc == 0, err
    js = json.loads(out)
    assert js["scenario"] == "paper-highdyn" and js["seed"] == 3 and js["runs"] == 1
    r, c = js["methods"]["dlb-rackf"], js["methods"]["dlb-ckf"]
    assert r["lock_lost_channels"] == 0 and not r["diverged"]
    assert r["doppler_rms_hz"][0] < c["doppler_rms_hz"][0]
    assert r["doppler_rms_hz"][0] < 0.2 and r["code_rms_chips"][0] < 0.02
    assert r["doppler_rms_hz"][1] is None          # 20-40 s not in a 20 s cut
    assert r["runtime_s"] > 0 and r["realtime_factor"] > 0
    assert (scenario_20s / "metrics.json").is_file() and (scenario_20s / "results.h5").is_file()
    import h5py
    with h5py.File(scenario_20s / "results.h5") as f:
        g = f["run000/dlb-rackf"]
        assert g["doppler_err_hz"].shape[1] == 13 and g["mode"].shape == g["doppler_err_hz"].shape


def test_cache_reused_and_human_output(scenario_20s, capsys):
    rc, out, err = _run(capsys, "scenario", "paper-highdyn", "--duration", "20", "--fs-hz", "2.046e6",
                        "--methods", "dlb-ckf", "--seed", "3", "--no-plots", "--out", str(scenario_20s))
    assert rc == 0, err
    assert "data reused" in out and "paper Table 3" in out and "dlb-ckf" in out


@pytest.mark.parametrize("argv, what", [
    (["scenario", "paper-highdyn", "--methods", "dlb-pf"], "unknown method"),
    (["scenario", "no-such-scenario"], "unknown scenario"),
    (["scenario", "paper-highdyn", "--runs", "0"], "--runs"),
    (["scenario", "paper-highdyn", "--duration", "-1"], "--duration"),
])
def test_user_errors_exit_2(argv, what, tmp_path, capsys):
    rc, out, err = _run(capsys, *argv, "--out", str(tmp_path))
    assert rc == 2
    assert what in err and "Traceback" not in err
