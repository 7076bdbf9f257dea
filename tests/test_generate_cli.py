"""`ultratight generate` and scenario loading: outputs, overrides, one-line errors, no partial files."""

import json
import subprocess
import sys

import h5py
import numpy as np
import pytest

from ultratight.errors import ConfigError
from ultratight.receiver.cli import main
from ultratight.receiver.cli.scenario_config import list_scenarios, load_scenario
from ultratight.signals.recording.iffile import open_if


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "ultratight.receiver.cli", *args], capture_output=True,
                          text=True)


def test_list_and_unknown_scenario():
    names = list_scenarios()
    assert {"static-open-sky", "paper-highdyn"} <= set(names)
    with pytest.raises(ConfigError, match=r"unknown scenario 'nope'.*paper-highdyn.*static-open-sky"):
        load_scenario("nope")


def test_paper_highdyn_matches_spec():
    cfg = load_scenario("paper-highdyn")
    assert (cfg["receiver"]["lat_deg"], cfg["receiver"]["lon_deg"], cfg["receiver"]["h_m"]) == \
        (28.2460, 102.0266, 50000.0)
    segs = cfg["trajectory"]["segments"]
    assert [s["t0"] for s in segs] == [0.0, 20.0, 21.0, 40.0, 41.0]
    assert [s["acc_enu"][0] for s in segs] == [100.0, 100.0, 200.0, 200.0, -200.0]
    assert [s["jerk_enu"][0] for s in segs] == [0.0, 100.0, 0.0, -400.0, 0.0]
    assert all(s["acc_enu"][1] == 4.0 for s in segs)
    assert cfg["satellites"]["cn0_dbhz"] == 20.0 and cfg["duration_s"] == 60.0
    assert cfg["noise_events"] == [{"t0_s": 5.0, "t1_s": 10.0, "noise_factor": 20.0}]
    assert cfg["imu"]["preset"] == "paper" and cfg["imu"]["rate_hz"] == 100.0
    # 13 satellites in view at the start point with the nominal constellation
    from ultratight.ins.trajectory import build_trajectory
    from ultratight.signals.synth.generator import _ephemerides

    traj = build_trajectory(cfg["trajectory"], cfg["receiver"], cfg["duration_s"])
    ephs, cn0 = _ephemerides(cfg, traj.pos_vel_e(np.zeros(1))[0][0])
    assert len(ephs) == 13 and np.all(cn0 == 20.0)


def test_static_open_sky_has_8_or_more():
    cfg = load_scenario("static-open-sky")
    from ultratight.ins.trajectory import build_trajectory
    from ultratight.signals.synth.generator import _ephemerides

    traj = build_trajectory(cfg["trajectory"], cfg["receiver"], 1.0)
    ephs, cn0 = _ephemerides(cfg, traj.pos_vel_e(np.zeros(1))[0][0])
    assert len(ephs) >= 8 and np.all(cn0 == 45.0)


def test_overrides_dotted_and_nested():
    cfg = load_scenario("static-open-sky", {"duration_s": 2.0, "frontend.fs_hz": 2.046e6, "seed": None,
                                            "satellites": {"cn0_dbhz": 38.0}})
    assert cfg["duration_s"] == 2.0 and cfg["frontend"]["fs_hz"] == 2.046e6
    assert cfg["satellites"]["cn0_dbhz"] == 38.0 and cfg["satellites"]["mask_deg"] == 5.0
    assert cfg["seed"] == 1


@pytest.mark.parametrize("text,field", [
    ("[receiver]\nlon_deg = 1.0\n", "receiver.lat_deg"),
    ("[receiver]\nlat_deg = 95.0\nlon_deg = 1.0\n", "receiver.lat_deg"),
    ("duration_s = -1\n[receiver]\nlat_deg = 1.0\nlon_deg = 1.0\n", "duration_s"),
    ("[receiver]\nlat_deg = 1.0\nlon_deg = 1.0\n[frontend]\nformat = 'xx'\n", "frontend.format"),
    ("[receiver]\nlat_deg = 1.0\nlon_deg = 1.0\n[frontend]\nfs_hz = 0.0\n", "frontend.fs_hz"),
    ("[receiver]\nlat_deg = 1.0\nlon_deg = 1.0\n[satellites]\nprns = [0, 40]\n", "satellites.prns"),
    ("[receiver]\nlat_deg = 1.0\nlon_deg = 1.0\n[satellites]\nsource = 'almanac'\n", "satellites.source"),
    ("[receiver]\nlat_deg = 1.0\nlon_deg = 1.0\n[[noise_events]]\nt0_s = 3.0\nt1_s = 1.0\nnoise_factor = 2.0\n",
     "noise_events"),
    ("[receiver]\nlat_deg = 1.0\nlon_deg = 1.0\n[nav]\ndata_bits = 'yes'\n", "nav.data_bits"),
    ("[receiver]\nlat_deg = 1.0\nlon_deg = 1.0\n[frontend]\nformat = 'ci2packed'\nbits = 8\n", "frontend.bits"),
    ("[receiver\n", "invalid TOML"),
])
def test_validation_names_field(tmp_path, text, field):
    p = tmp_path / "s.toml"
    p.write_text(text)
    with pytest.raises(ConfigError, match=field.replace(".", r"\.").replace("[", r"\[")):
        load_scenario(p)


def test_generate_cli_outputs(tmp_path, capsys):
    rc = main(["generate", "static-open-sky", "--duration", "0.05", "--out", str(tmp_path / "run1.ci8"),
               "--seed", "3", "--cn0", "40", "--no-progress"])
    assert rc == 0
    out = capsys.readouterr().out
    assert "satellites (" in out and "(40 dB-Hz)" in out and "run1.ci8" in out
    with open_if(tmp_path / "run1.ci8") as src:
        assert src.n_samples == 200_000 and src.fs_hz == 4e6
        assert src.meta["generator"]["seed"] == 3
    with h5py.File(tmp_path / "run1.truth.h5") as f:
        assert np.all(f["cn0_dbhz"][()] == 40.0)
        assert json.loads(f.attrs["config_json"])["duration_s"] == 0.05
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run1.ci8", "run1.ci8.json", "run1.truth.h5"]


def test_generate_cli_directory_format_and_json(tmp_path, capsys):
    rc = main(["generate", "static-open-sky", "--duration", "0.02", "--out", str(tmp_path), "--format",
               "i2packed", "--fs", "8e6", "--if", "2e6", "--json", "--no-progress"])
    assert rc == 0
    summ = json.loads(capsys.readouterr().out)
    assert summ["format"] == "i2packed" and summ["files"]["if"].endswith("static-open-sky.i2packed")
    with open_if(summ["files"]["if"]) as src:
        assert not src.is_complex and src.if_hz == 2e6
        assert set(np.unique(src.read(0, 5000))) <= {-3.0, -1.0, 1.0, 3.0}


@pytest.mark.parametrize("args,needle", [
    (["nope"], "unknown scenario 'nope'"),
    (["static-open-sky", "--format", "cs16"], "unknown IF sample format 'cs16'"),
    (["static-open-sky", "--format", "i8"], "fs/2"),          # real sampling needs an IF
    (["static-open-sky", "--fs", "-1"], "fs_hz"),
    (["static-open-sky", "--duration", "0"], "duration_s"),
])
def test_generate_cli_errors_one_line_no_files(tmp_path, args, needle):
    r = _cli("generate", *args, "--out", str(tmp_path), "--duration" if "--duration" not in args else "--seed",
             "0.01" if "--duration" not in args else "1", "--no-progress")
    assert r.returncode == 2
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and needle in lines[0], r.stderr
    assert list(tmp_path.iterdir()) == []


def test_interrupted_generate_leaves_no_files(tmp_path, monkeypatch):
    import ultratight.signals.synth.generator as g

    def boom(*a):
        raise KeyboardInterrupt

    monkeypatch.setattr(g, "_synth_complex", boom)
    rc = main(["generate", "paper-highdyn", "--duration", "0.3", "--out", str(tmp_path / "x"), "--no-progress"])
    assert rc == 130
    assert list(tmp_path.iterdir()) == []


def test_paper_highdyn_writes_imu_and_trajectory(tmp_path):
    rc = main(["generate", "paper-highdyn", "--duration", "0.2", "--out", str(tmp_path / "ph"), "--no-progress"])
    assert rc == 0
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == ["ph.ci16", "ph.ci16.json", "ph.imu.h5", "ph.traj.h5", "ph.truth.h5"]
    with h5py.File(tmp_path / "ph.truth.h5") as f:
        assert f["code_phase_chips"].shape == (200, 13)
        assert np.all(f["cn0_dbhz"][()] == 20.0)      # the x20 noise event starts at 5 s


def test_generate_creates_missing_out_directories(tmp_path):
    stem = tmp_path / "new" / "deeper" / "run.ci8"
    rc = main(["generate", "static-open-sky", "--duration", "0.01", "--out", str(stem), "--no-progress"])
    assert rc == 0
    assert sorted(p.name for p in stem.parent.iterdir()) == ["run.ci8", "run.ci8.json", "run.truth.h5"]
    with open_if(stem) as src:
        assert src.n_samples == 40_000
    # a path ending in "/" names a directory: files named after the scenario inside it
    d = tmp_path / "dir_only"
    rc = main(["generate", "static-open-sky", "--duration", "0.01", "--out", str(d) + "/", "--no-progress"])
    assert rc == 0
    assert (d / "static-open-sky.ci8").is_file() and (d / "static-open-sky.truth.h5").is_file()


def test_generate_failure_removes_directories_it_created(tmp_path, monkeypatch):
    import ultratight.signals.synth.generator as g

    def boom(*a):
        raise KeyboardInterrupt

    monkeypatch.setattr(g, "_synth_complex", boom)
    rc = main(["generate", "static-open-sky", "--duration", "0.01", "--out", str(tmp_path / "a" / "b" / "x"),
               "--no-progress"])
    assert rc == 130
    assert list(tmp_path.iterdir()) == []


def test_generate_out_parent_is_a_file(tmp_path):
    (tmp_path / "f").write_text("x")
    r = _cli("generate", "static-open-sky", "--duration", "0.01", "--out", str(tmp_path / "f" / "run"),
             "--no-progress")
    assert r.returncode == 2
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "is not a directory" in lines[0], r.stderr


def test_generate_rewrites_existing_stem(tmp_path):
    out = tmp_path / "r.ci8"
    for seed in ("1", "2"):
        assert main(["generate", "static-open-sky", "--duration", "0.01", "--out", str(out), "--seed", seed,
                     "--no-progress"]) == 0
    with open_if(out) as src:
        assert src.meta["generator"]["seed"] == 2
