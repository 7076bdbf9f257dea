"""`ultratight process --mode ultratight`: the engine on a generated IF file + IMU file from the CLI."""

import json
import subprocess
import sys
import time

import h5py
import numpy as np
import pytest

from ultratight.receiver.cli import main

FS_HZ = 2.046e6       # 2 samples per chip: the lowest rate the correlators take comfortably
DURATION_S = 3.0


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "ultratight.receiver.cli", *args], capture_output=True,
                          text=True)


def _one_line_error(r):
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 2, r.stderr
    assert len(lines) == 1, r.stderr
    return lines[0]


@pytest.fixture(scope="module")
def cut(tmp_path_factory):
    d = tmp_path_factory.mktemp("ph")
    rc = main(["generate", "paper-highdyn", "--duration", str(DURATION_S), "--fs", str(FS_HZ),
               "--out", str(d / "ph"), "--no-progress"])
    assert rc == 0
    paths = {"if": d / "ph.ci16", "imu": d / "ph.imu.h5", "traj": d / "ph.traj.h5", "truth": d / "ph.truth.h5"}
    for p in paths.values():
        assert p.is_file(), p
    return paths


def test_ultratight_mode_json_and_output_against_truth(cut, tmp_path, capsys):
    out = tmp_path / "res.h5"
    t_wall = time.perf_counter()
    # the named assisted start (truth-perturbed, bits re-encoded): a 3 s cut leaves no time for a scalar fix
    rc = main(["process", str(cut["if"]), "--mode", "ultratight", "--imu", str(cut["imu"]), "--json",
               "--out", str(out), "--startup", "truth-perturbed", "--bits", "assisted",
               "--csv", str(tmp_path / "n.csv"), "--nmea", str(tmp_path / "n.nmea"), "--kml", str(tmp_path / "n.kml"),
               "--rinex-obs", str(tmp_path / "n.obs")])
    t_wall = time.perf_counter() - t_wall
    assert rc == 0
    summ = json.loads(capsys.readouterr().out)
    side = json.loads((cut["if"].parent / "ph.ci16.json").read_text())
    assert summ["mode"] == "ultratight" and summ["method"] == "dlb-rackf"     # the default method
    assert summ["prns"] == side["prn"] and len(summ["prns"]) == 13
    assert summ["duration_s"] == pytest.approx(DURATION_S, abs=2e-3)
    assert summ["n_epochs"] == pytest.approx(1000 * DURATION_S, abs=2)
    # the run time is wall-clock seconds of the run inside this call: the wall time measured here around
    # the call bounds it, and the real-time factor (wall s per signal s) times the signal duration
    assert 0 < summ["runtime_s"] <= t_wall, (summ["runtime_s"], t_wall)
    assert 0 < summ["realtime_factor"] * DURATION_S <= t_wall, (summ["realtime_factor"], t_wall)
    assert summ["lock_losses"] == 0           # 20 dB-Hz, no noise event in the first 3 s
    assert summ["startup"] == "truth-perturbed" and summ["lock_lost_channels"] == []
    assert len(summ["assisted"]) == 3 and "truth-perturbed" in summ["assisted"][0]
    # paper-highdyn puts no troposphere on its signals; the truth-perturbed start-up has no fixes to test
    # the recording on, so the correction follows the generator's configuration, an assisted part
    assert "troposphere correction off" in summ["assisted"][2] and summ["atmosphere"]["tropo"] == "off"
    # every output of an assisted run says so
    for name in ("n.csv", "n.nmea", "n.kml", "n.obs"):
        head = (tmp_path / name).read_text()[:4000]
        assert "ASSISTED" in head and "truth-perturbed" in head and "bits assisted" in head, (name, head[:3000])
    assert summ["n_tight_updates"] >= 20
    assert summ["out"] == str(out)
    # the result file: navigation solution against the generator's trajectory truth
    with h5py.File(out) as f, h5py.File(cut["traj"]) as g, h5py.File(cut["truth"]) as tr:
        assert f.attrs["method"] == "dlb-rackf"
        assert "truth-perturbed" in f.attrs["assisted"] and "--bits assisted" in f.attrs["assisted"]
        assert list(f.attrs["prn"]) == summ["prns"]
        t = f["nav_t_s"][()]
        assert t.size >= summ["n_tight_updates"] and np.allclose(np.diff(t), t[1] - t[0])
        tt = g["t"][()]
        pos = np.stack([np.interp(t, tt, g["pos_e"][:, i]) for i in range(3)], axis=1)
        vel = np.stack([np.interp(t, tt, g["vel_e"][:, i]) for i in range(3)], axis=1)
        # the generated file starts from the truth perturbed by the hot-start errors of docs/ultratight.md
        # "Assisted hot start" (1 sigma per axis 0.5 m, 0.02 m/s); over 3 s the tight filter keeps the
        # solution at that start error.  Bound: the 99.9 % chi-square(3) radius of those sigmas,
        # 0.5 m x 4.03 = 2.0 m and 0.02 m/s x 4.03 = 0.081 m/s.  Measured (seeds 1-4 of the file; the
        # start draw is the engine's own seed): max 0.54-0.57 m and 0.040 m/s
        assert np.max(np.linalg.norm(f["nav_pos_e"][()] - pos, axis=1)) < 2.0
        assert np.max(np.linalg.norm(f["nav_vel_e"][()] - vel, axis=1)) < 0.081
        # per-channel Doppler estimate against the logged truth (1 ms truth grid, epoch mid-points)
        t_mid = f["t_start_s"][()] + 0.5e-3
        d_est = f["doppler_hz"][()]
        d_true = np.stack([np.interp(t_mid[:, c], tr["t_s"][()], tr["doppler_hz"][:, c])
                           for c in range(d_est.shape[1])], axis=1)
        late = t_mid[:, 0] > 1.0
        # docs/ultratight.md acceptance table: dlb-rackf Doppler RMS 0.0866 Hz over 0-5 s (before the
        # burst; 4 MHz, 5 seeds; README 0.0917 Hz over 0-20 s).  At 2.046 MHz the correlators' SNR is
        # the same C/N0 T.  This run (seed 1, 1-3 s): 0.055 Hz; seeds 1-4: 0.055-0.078 Hz.
        # Bound 0.11 Hz = documented x 1.27 (a doubling of this run's figure breaks it)
        assert np.sqrt(np.mean((d_est[late] - d_true[late]) ** 2)) < 0.11


def test_ultratight_human_summary_other_method(cut, capsys):
    rc = main(["process", str(cut["if"]), "--mode", "ultratight", "--imu", str(cut["imu"]), "--method",
               "dlb-ckf", "--duration", "1", "--prn", "31,20,18,28,21,15", "--startup", "truth-perturbed",
               "--bits", "assisted"])
    assert rc == 0
    out = capsys.readouterr().out
    assert out.startswith("ASSISTED run: start-up from the IMU file's truth (truth-perturbed); data bits re-encoded "
                          "from the ephemeris (--bits assisted); troposphere correction off: the generator's "
                          "configuration (sidecar) put none on the signal (the truth-perturbed start-up has no "
                          "fixes to test it on)\nultratight dlb-ckf: PRN 31, 20, 18, 28, 21, 15\n")
    assert "signal 1.00 s in " in out and "lock losses: 0" in out


def test_ultratight_needs_imu(cut):
    msg = _one_line_error(_cli("process", str(cut["if"]), "--mode", "ultratight"))
    assert "--mode ultratight needs --imu IMU.h5" in msg


def test_ultratight_rejects_unknown_method(cut):
    r = _cli("process", str(cut["if"]), "--mode", "ultratight", "--imu", str(cut["imu"]), "--method", "ekf")
    assert r.returncode == 2 and "invalid choice: 'ekf'" in r.stderr


def test_imu_given_without_ultratight_mode(cut):
    msg = _one_line_error(_cli("process", str(cut["if"]), "--imu", str(cut["imu"])))
    assert "--imu is only used with --mode ultratight" in msg


def test_ultratight_out_of_order_imu_stamp(cut, tmp_path):
    from ultratight.ins.imu_data import read_imu_h5, write_imu_h5
    imu = read_imu_h5(cut["imu"])
    k = 57
    imu.t = imu.t.copy()
    imu.t[k], imu.t[k + 1] = imu.t[k + 1], imu.t[k]
    bad = tmp_path / "bad.imu.h5"
    write_imu_h5(bad, imu)
    msg = _one_line_error(_cli("process", str(cut["if"]), "--mode", "ultratight", "--imu", str(bad)))
    assert str(bad) in msg and "out-of-order" in msg
    assert f"sample {k + 1}:" in msg          # the first stamp not after its predecessor


def test_truth_start_keeps_a_troposphere_asked_for(cut, capsys):
    """``--tropo saastamoinen`` given: the truth-perturbed start-up keeps the correction on a signal the
    generator made without a troposphere (the user's choice), and nothing of it is assisted."""
    rc = main(["process", str(cut["if"]), "--mode", "ultratight", "--imu", str(cut["imu"]), "--json",
               "--startup", "truth-perturbed", "--bits", "assisted", "--duration", "1", "--tropo", "saastamoinen"])
    assert rc == 0
    summ = json.loads(capsys.readouterr().out)
    assert summ["atmosphere"]["tropo"] == "saastamoinen (cosz)"
    assert len(summ["assisted"]) == 2 and not any("troposphere" in a for a in summ["assisted"])


def test_truth_start_troposphere_follows_the_generator():
    """The truth-perturbed start-up's troposphere (receiver.deep.recordings.truth_start_troposphere): off
    only when the correction was not asked for and the generator's configuration applied none."""
    from ultratight.receiver.deep.atmosphere_terms import receiver_model
    from ultratight.receiver.deep.handover import HandoverConfig
    from ultratight.receiver.deep.recordings import truth_start_troposphere

    on = receiver_model(iono="off", tropo="saastamoinen")
    vacuum = {"name": "x"}
    sky = {"atmosphere": {"iono": "off", "tropo": "saastamoinen", "broadcast": False}}
    atmo, _, note = truth_start_troposphere(None, (None, vacuum, "off"), on, None)
    assert atmo.tropo == "off" and "generator" in note
    for gen, hcfg in ((sky, None), (vacuum, HandoverConfig(tropo_check=False)), (None, None)):
        atmo, _, note = truth_start_troposphere(hcfg, (None, gen, "off"), on, None)
        assert atmo is on and note is None


def test_parser_does_not_import_the_engine():
    # subcommands' add_arguments must stay cheap: the method choices are resolved lazily
    code = ("import sys; from ultratight.receiver.cli import build_parser; "
            "a = build_parser().parse_args(['process', 'x.bin', '--mode', 'ultratight']); "
            "print(a.method, 'ultratight.receiver.deep.engine' in sys.modules)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert r.stdout.split() == ["None", "False"]


@pytest.mark.parametrize("flags,checked", [((), True), (("--tropo", "saastamoinen"), False), (("--tropo", "off"), False)])
def test_the_troposphere_is_tested_only_when_not_asked_for(cut, monkeypatch, flags, checked):
    """Without --tropo the start-up tests the recording for a troposphere (receiver.deep.tropo_check);
    a --tropo given is the user's choice and is not second-guessed."""
    import ultratight.receiver.deep.recordings as rec

    seen = {}

    class Stop(Exception):
        pass

    def run(*a, **k):
        seen.update(check=k["handover"].tropo_check, tropo=k["tropo"])
        raise Stop

    monkeypatch.setattr(rec, "run_ultratight_on_files", run)
    with pytest.raises(Stop):
        main(["process", str(cut["if"]), "--mode", "ultratight", "--imu", str(cut["imu"]), *flags])
    assert seen == {"check": checked, "tropo": flags[1] if flags else "saastamoinen"}
