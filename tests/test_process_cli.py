"""End-to-end: ``ultratight process`` on the real IF files, on generated files (against the
generator's truth) and on bad input."""

import json
import subprocess
import sys
import xml.etree.ElementTree as ET

import h5py
import numpy as np
import pytest

from ultratight.constants import C, CA_LEN
from ultratight.receiver.cli import main

REAL = {
    # file, flags, PRNs listed in shared/data/README.md
    "pocket_iq": ("pocketsdr/L1_20211202_084700_4MHz_IQ.bin", ["--fs", "4e6", "--format", "ci8", "--iq-conj"],
                  {31, 26, 29, 16, 32}),
    "pocket_real": ("pocketsdr/L1_20211201_054600_24MHz_I.bin", ["--fs", "24e6", "--if", "6e6", "--format", "i8"],
                    {32, 25, 12, 10, 31, 29, 23, 24}),
    "cttc": ("gnss-sdr/GSoC_CTTC_capture_2012_07_26_4Msps_4ms.dat", ["--fs", "4e6", "--format", "cf32"],
             {29, 25, 12, 2}),
    "synthetic_prn1": ("gnss-sdr/GPS_L1_CA_ID_1_Fs_4Msps_2ms.dat", ["--fs", "4e6", "--format", "cf32"], {1}),
}


def run_cli(argv, capsys):
    code = main(["process", *argv])
    out, err = capsys.readouterr()
    return code, out, err


@pytest.mark.parametrize("key", sorted(REAL))
def test_real_files_exact_prns(key, shared_data, capsys):
    path, flags, prns = REAL[key]
    f = shared_data / "real-if" / path
    if not f.is_file():
        pytest.skip(f"{f} missing")
    code, out, err = run_cli([str(f), *flags, "--json", "--channels", "12"], capsys)
    assert code == 0, err
    d = json.loads(out)
    assert {a["prn"] for a in d["acquired"]} == prns
    if key == "pocket_iq":
        # 0.5 s: every listed satellite reaches phase lock; the right convention raises no warning
        assert set(d["tracked"]) == prns and d["warnings"] == []
    if key == "synthetic_prn1":
        a = d["acquired"][0]
        # the file's notes: generated with Doppler argument +1680 Hz, reported as -1680 by its
        # authors' receiver (their sign conventions disagree); we see +1679.5 Hz. Code delay 524 samples.
        assert abs(abs(a["doppler_hz"]) - 1680) < 50
        assert abs(((1023 - a["code_phase_chips"]) * 4e6 / 1.023e6) % 4000 - 524) < 2


def test_pocket_iq_mirror_warning(shared_data, capsys):
    # read as I + jQ (against the front end's convention): acquisition still works on the mirrored
    # spectrum, but code and carrier Dopplers disagree -> warning with the --iq-conj hint
    f = shared_data / "real-if" / REAL["pocket_iq"][0]
    code, out, err = run_cli([str(f), "--fs", "4e6", "--format", "ci8", "--json", "--prn", "16,26,29,31,32"],
                             capsys)
    d = json.loads(out)
    assert code == 0 and d["warnings"] and "--iq-conj" in d["warnings"][0]
    assert "inverted" in err


# ------------------------------------------------------------------------------ generated files
def shipped_scenario_text(name):
    from importlib import resources
    return (resources.files("ultratight") / "data" / "scenarios" / f"{name}.toml").read_text()


def at_frame_start(text):
    """Scenario TOML text with the start at TOW 518400, a frame start (the shipped static scenarios
    start 16 s into a frame so that subframe 4 page 18 comes 2 s into the run, and decode the time
    of week at ~9.5 s): the subframe that starts 6 s into the run gives the time of week at ~7.3 s,
    so a 9 s file has fixes."""
    import re
    return re.sub(r"(?m)^tow_s = .*$", "tow_s = 518400.0", text)


def without_atmosphere(text):
    """Scenario TOML text without its ``[atmosphere]`` table: a signal with neither ionosphere nor
    troposphere (the receiver is then told ``--iono off --tropo off``)."""
    head, sep, rest = text.partition("\n[atmosphere]\n")
    assert sep, "no [atmosphere] table"
    nxt = rest.find("\n[")
    return head + ("\n" + rest[nxt + 1:] if nxt >= 0 else "\n")


@pytest.fixture(scope="module")
def gen9(tmp_path_factory):
    """9 s of static-open-sky at 2.6 MHz without its atmosphere, from TOW 518400 (TOW decodable from
    ~7.3 s)."""
    import tomllib
    d = tmp_path_factory.mktemp("gen9")
    text = at_frame_start(without_atmosphere(shipped_scenario_text("static-open-sky")))
    cfg = tomllib.loads(text)
    assert "atmosphere" not in cfg and cfg["time"]["tow_s"] == 518400.0
    (d / "static-open-sky.toml").write_text(text)
    r = subprocess.run([sys.executable, "-m", "ultratight.receiver.cli", "generate", str(d / "static-open-sky.toml"),
                        "--duration", "9", "--fs", "2.6e6", "--out", str(d / "s9"), "--no-progress", "--json"],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    files = json.loads(r.stdout)["files"]
    return files


def test_generated_with_ephemeris_against_truth(gen9, tmp_path):
    from ultratight.receiver.scalar.receiver import ProcessConfig, process
    from ultratight.signals.constellation import nominal_ephemerides
    from ultratight.signals.recording.iffile import open_if

    truth = h5py.File(gen9["truth"], "r")
    week, tow0 = int(truth.attrs["week"]), float(truth.attrs["tow0_s"])
    out = tmp_path / "o.h5"
    t_prn = [int(p) for p in truth.attrs["prn"]]
    # the generated signal has no atmosphere ([atmosphere] absent): no corrections
    cfg = ProcessConfig(n_channels=9, record_epochs=True, prns=t_prn + [1, 2, 3], iono="off", tropo="off")
    res = process(open_if(gen9["if"]), cfg, ephemerides=nominal_ephemerides(week, tow0), out_path=out,
                  csv_path=tmp_path / "o.csv", kml_path=tmp_path / "o.kml")
    assert {a.prn for a in res.acquisition if a.detected} == set(t_prn)
    assert all(c["tracked"] and c["losses"] == 0 for c in res.channels)
    # TOW from the first subframe (bits before bit sync are used): HOW confirmed ~7.3 s
    assert len(res.fixes) >= 10 and res.first_fix_s < 8.0
    pos_true, vel_true = truth["pos_e"][0], truth["vel_e"][0]
    P = np.array([f["pos_e"] for f in res.fixes])
    V = np.array([f["vel_e"] for f in res.fixes])
    assert np.sqrt(np.mean(np.sum((P - pos_true) ** 2, axis=1))) < 5.0
    assert np.sqrt(np.mean(np.sum((V - vel_true) ** 2, axis=1))) < 0.1
    # fix time: GPS time of the sample
    f0 = res.fixes[0]
    assert f0["gps_tow_s"] == pytest.approx(tow0 + f0["sample_index"] / truth.attrs["fs_hz"], abs=1e-6)
    # per-epoch estimates (what the scenario runner compares) against the truth rows
    tsi = truth["sample_index"][:]
    for prn, e in res.epochs.items():
        k = t_prn.index(prn)
        late = e["sample_index"] > 2.6e6        # after pull-in
        s = e["sample_index"][late]
        d_true = np.interp(s, tsi, truth["doppler_hz"][:, k])
        assert np.sqrt(np.mean((e["doppler_hz"][late] - d_true) ** 2)) < 3.0
        # code phase: propagate the truth row before each sample at the code rate of its Doppler
        j = np.searchsorted(tsi, s, side="right") - 1
        rate = 1.023e6 * (1.0 + truth["doppler_hz"][j, k] / 1575.42e6)
        cp_t = (truth["code_phase_chips"][j, k] + (s - tsi[j]) * rate / truth.attrs["fs_hz"]) % CA_LEN
        err = (e["code_phase_chips"][late] - cp_t + CA_LEN / 2) % CA_LEN - CA_LEN / 2
        assert np.sqrt(np.mean(err ** 2)) < 0.03
    # transmit times (pseudorange + receiver time) against truth, per channel
    with h5py.File(out, "r") as f:
        assert f.attrs["complete"]
        s_obs = f["observables/sample_index"][:]
        ttx = f["observables/t_rx_tow_s"][:][:, None] - f["observables/pseudorange_m"][:] / C
        summ = json.loads(f.attrs["summary"])
        for j, c in enumerate(summ["channels"]):
            k = t_prn.index(c["prn"])
            t_true = np.interp(s_obs, tsi, truth["t_tx_tow_s"][:, k])
            e = (ttx[:, j] - t_true) * C
            e = e[np.isfinite(e)]
            assert e.size > 10 and np.sqrt(np.mean(e ** 2)) < 4.0
        assert f["pvt/pos_e"].shape == (len(res.fixes), 3)
        assert f["pvt/cov_pos_clk"].shape == (len(res.fixes), 4, 4)
        assert f["acquisition/prn"].shape[0] == len(t_prn) + 3
        tr = f[f"tracking/prn{t_prn[0]:02d}"]
        assert tr.shape[0] > 8000 and "doppler_hz" in tr.dtype.names
    lines = (tmp_path / "o.csv").read_text().splitlines()
    assert len(lines) == len(res.fixes) + 1 and lines[0].startswith("t_s,")
    root = ET.parse(tmp_path / "o.kml").getroot()
    assert root.tag.endswith("kml")


def test_cli_json_generated_short(gen9, capsys):
    truth = h5py.File(gen9["truth"], "r")
    prns = ",".join(str(int(p)) for p in truth.attrs["prn"]) + ",1,2"
    code, out, err = run_cli([gen9["if"], "--json", "--channels", "9", "--duration", "2", "--prn", prns], capsys)
    assert code == 0, err
    d = json.loads(out)
    assert {a["prn"] for a in d["acquired"]} == {int(p) for p in truth.attrs["prn"]}
    assert set(d["tracked"]) == {int(p) for p in truth.attrs["prn"]}
    assert d["fixes"] == 0 and d["first_fix_s"] is None
    assert 0 < d["realtime_factor"] and d["signal_s"] == pytest.approx(2.0, abs=0.01)


def test_threads_give_the_one_thread_result(gen9, tmp_path, capsys):
    # the channels spread over two threads (the default on an idle machine) track exactly as on one
    outs = {}
    for k in ("1", "2"):
        out = tmp_path / f"t{k}.h5"
        code, _, err = run_cli([gen9["if"], "--channels", "6", "--duration", "3", "--threads", k, "--out", str(out),
                                "--no-progress"], capsys)
        assert code == 0, err
        data = {}
        with h5py.File(out, "r") as f:
            f.visititems(lambda name, o: data.__setitem__(name, o[...]) if isinstance(o, h5py.Dataset) else None)
        outs[k] = data
    assert outs["1"].keys() == outs["2"].keys() and any(n.startswith("tracking/prn") for n in outs["1"])
    for name, a in outs["1"].items():
        np.testing.assert_array_equal(a, outs["2"][name], err_msg=name)


def test_all_in_view_threads_give_the_one_thread_result(gen9, tmp_path):
    # all in view with fixes: the periodic search after some blocks (their records go in before the
    # next block is tracked), the records of the others while it is tracked — the one-thread order
    from ultratight.receiver.scalar.receiver import ProcessConfig, process
    from ultratight.signals.constellation import nominal_ephemerides
    from ultratight.signals.recording.iffile import open_if

    truth = h5py.File(gen9["truth"], "r")
    eph = nominal_ephemerides(int(truth.attrs["week"]), float(truth.attrs["tow0_s"]))
    outs, runs = {}, {}
    for k in (1, 2):
        cfg = ProcessConfig(threads=k, search_every_s=1.0, iono="off", tropo="off")
        runs[k] = process(open_if(gen9["if"]), cfg, ephemerides=eph, out_path=tmp_path / f"a{k}.h5")
        with h5py.File(tmp_path / f"a{k}.h5", "r") as f:
            data = {}
            f.visititems(lambda name, o: data.__setitem__(name, o[...]) if isinstance(o, h5py.Dataset) else None)
        outs[k] = data
    srch = runs[2].search
    assert srch["runs"] >= 2 and len(runs[2].fixes) >= 10, srch
    assert outs[1].keys() == outs[2].keys() and sum(n.startswith("tracking/prn") for n in outs[1]) >= 6
    for name, a in outs[1].items():
        np.testing.assert_array_equal(a, outs[2][name], err_msg=name)


def test_cli_with_rinex_ephemeris(tmp_path, rinex_path, capsys):
    """Satellites from the real broadcast ephemeris, with the scenario's atmosphere; the receiver
    gets the same RINEX via --ephemeris, whose header carries the broadcast alpha/beta the generator
    applied, and corrects with its defaults (Klobuchar, Saastamoinen)."""
    import tomllib
    text = at_frame_start(shipped_scenario_text("static-open-sky")).replace('source = "nominal"', 'source = "rinex"')
    cfg = tomllib.loads(text)
    assert cfg["satellites"]["source"] == "rinex" and cfg["atmosphere"]["broadcast"]
    scen = tmp_path / "rinex-sky.toml"
    scen.write_text(text)
    r = subprocess.run([sys.executable, "-m", "ultratight.receiver.cli", "generate", str(scen), "--duration", "9",
                        "--fs", "2.6e6", "--out", str(tmp_path / "r9"), "--no-progress", "--json"],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    files = json.loads(r.stdout)["files"]
    truth = h5py.File(files["truth"], "r")
    prns = ",".join(str(int(p)) for p in truth.attrs["prn"])
    code, out, err = run_cli([files["if"], "--ephemeris", str(rinex_path), "--json", "--channels", "12",
                              "--prn", prns], capsys)
    assert code == 0, err
    d = json.loads(out)
    assert d["fixes"] >= 10
    assert d["corrections"]["iono"] == "klobuchar" and d["corrections"]["iono_source"] == "rinex"
    err_m = np.linalg.norm(np.array(d["position_ecef_m"]) - truth["pos_e"][0])
    assert err_m < 5.0
    lat, lon, h = d["position_llh"]
    assert abs(lat - 41.275) < 1e-4 and abs(lon - 1.987) < 1e-4 and abs(h - 50.0) < 10.0


def test_interrupt_leaves_valid_partial_output(gen9, tmp_path, capsys, monkeypatch):
    from ultratight.receiver.dsp import tracking
    calls = {"n": 0}
    orig = tracking.ScalarTracker.run

    def run(self, *a, **k):
        calls["n"] += 1
        if calls["n"] == 8:
            raise KeyboardInterrupt
        return orig(self, *a, **k)

    monkeypatch.setattr(tracking.ScalarTracker, "run", run)
    out = tmp_path / "p.h5"
    truth = h5py.File(gen9["truth"], "r")
    prns = ",".join(str(int(p)) for p in truth.attrs["prn"][:4])
    code, o, err = run_cli([gen9["if"], "--out", str(out), "--no-progress", "--prn", prns], capsys)
    assert code == 130 and "interrupted" in err and "partial" in err
    with h5py.File(out, "r") as f:
        assert not f.attrs["complete"] and f.attrs["interrupted"]
        assert f["tracking"][list(f["tracking"])[0]].shape[0] > 500
    assert not list(tmp_path.glob(".*part*"))


# ------------------------------------------------------------------------------ bad input
def test_wrong_iq_convention_nonzero_if(tmp_path, capsys):
    r = subprocess.run([sys.executable, "-m", "ultratight.receiver.cli", "generate", "static-open-sky",
                        "--duration", "0.05", "--fs", "2.6e6", "--if", "0.6e6", "--out", str(tmp_path / "c"),
                        "--no-progress", "--json"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    f = json.loads(r.stdout)["files"]["if"]
    prns = ",".join(str(p) for p in json.loads(r.stdout)["prns"])
    code, out, err = run_cli([f, "--json", "--iq-conj", "--prn", prns], capsys)
    assert code == 2
    assert "no satellites acquired" in err and "iq_conj=True" in err and "--iq-conj" in err
    assert json.loads(out)["acquired"] == []
    code, out, err = run_cli([f, "--json", "--prn", prns], capsys)
    assert code == 0 and len(json.loads(out)["acquired"]) >= 4


@pytest.mark.parametrize("argv,needle", [
    (["{missing}", "--fs", "4e6", "--format", "ci8"], "not found"),
    (["{odd}", "--fs", "4e6", "--format", "ci8"], "whole number"),
    (["{empty}", "--fs", "4e6", "--format", "ci8"], "no samples"),
    (["{short}", "--fs", "4e6", "--format", "ci8"], "1 ms"),
    (["{short}"], "sidecar"),
    (["{short}", "--fs=-4e6", "--format", "ci8"], "--fs"),
    (["{short}", "--fs", "4e6", "--format", "ci8", "--if", "5e6"], "--if"),
    (["{long}", "--fs", "4e6", "--format", "ci8", "--channels", "0"], "--channels"),
    (["{long}", "--fs", "4e6", "--format", "ci8", "--threads", "0"], "--threads"),
    (["{long}", "--fs", "4e6", "--format", "ci8", "--coh-ms", "3"], "coh_ms"),
    (["{long}", "--fs", "4e6", "--format", "zz"], "zz"),
    (["{long}", "--fs", "4e6", "--format", "ci8", "--prn", "40"], "PRN"),
])
def test_bad_input_one_line_error(argv, needle, tmp_path, capsys):
    files = {"missing": tmp_path / "nope.bin", "odd": tmp_path / "odd.bin", "empty": tmp_path / "empty.bin",
             "short": tmp_path / "short.bin", "long": tmp_path / "long.bin"}
    files["odd"].write_bytes(b"\x01\x02\x03")
    files["empty"].write_bytes(b"")
    files["short"].write_bytes(np.zeros(2 * 1000, np.int8).tobytes())
    rng = np.random.default_rng(0)
    files["long"].write_bytes(rng.integers(-3, 4, 2 * 40000, dtype=np.int8).tobytes())
    argv = [a.format(**files) for a in argv]
    code, out, err = run_cli(argv, capsys)
    assert code == 2
    assert err.count("\n") == 1 and needle in err and "Traceback" not in err


def test_noise_only_file_reports_no_satellites(tmp_path, capsys):
    rng = np.random.default_rng(1)
    f = tmp_path / "noise.bin"
    f.write_bytes(rng.integers(-3, 4, 2 * 60000, dtype=np.int8).tobytes())
    out = tmp_path / "x.h5"
    code, o, err = run_cli([str(f), "--fs", "4e6", "--format", "ci8", "--out", str(out), "--prn", "1-3"], capsys)
    assert code == 2 and "no satellites acquired" in err and "fs 4e+06 Hz" in err
    assert not out.exists()


def test_loss_of_lock_and_reacquisition(tmp_path):
    """A signal that vanishes for 1.5 s: the channel is declared lost, then re-acquired and tracked."""
    import math
    from ultratight.receiver.scalar.receiver import ProcessConfig, process
    from ultratight.signals.recording.iffile import open_if, write_if
    from ultratight.signals.ca_code import ca_code
    fs, dur = 2.6e6, 5.0
    rng = np.random.default_rng(3)
    n = int(fs * dur)
    t = np.arange(n) / fs
    theta = 0.1 + 1200.0 * t
    p = 50.0 + 1.023e6 * t + (1.023e6 / 1575.42e6) * (theta - 0.1)
    amp = np.full(n, math.sqrt(2 * 10 ** 4.5 / fs), dtype=np.float32)
    amp[int(1.0 * fs):int(2.5 * fs)] = 0.0
    x = amp * ca_code(5).astype(np.float32)[np.floor(p).astype(np.int64) % CA_LEN] * np.exp(2j * np.pi * theta)
    x = x + rng.normal(size=n) + 1j * rng.normal(size=n)
    f = tmp_path / "gap.cf32"
    write_if(f, (x * 8).astype(np.complex64), "cf32", fs)
    res = process(open_if(f), ProcessConfig(prns=[5, 6], record_epochs=True))
    c = res.channels[0]
    assert c["prn"] == 5 and c["losses"] >= 1 and c["reacquisitions"] >= 1
    e = res.epochs[5]
    last = e["sample_index"] > 4.0 * fs          # re-acquired on the 1 s retry after 2.5 s, then pull-in
    assert last.sum() > 900 and np.all(e["mode"][last] == 2)
    truth = (p[e["sample_index"][last]] % CA_LEN)
    err = (e["code_phase_chips"][last] - truth + CA_LEN / 2) % CA_LEN - CA_LEN / 2
    assert np.sqrt(np.mean(err ** 2)) < 0.03


# ------------------------------------------------------------------------------ acceptance (slow)
def _generate(tmp, scenario, *flags):
    r = subprocess.run([sys.executable, "-m", "ultratight.receiver.cli", "generate", scenario, "--out",
                        str(tmp / "g"), "--no-progress", "--json", *flags], capture_output=True, text=True,
                       timeout=1800)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout)["files"]


def earliest_ephemeris_time(truth, n_channels=4):
    """Receive time (s) at which subframes 1, 2 and 3 - each a whole 6 s occurrence transmitted
    after the file start - have all arrived on ``n_channels`` satellites (from the truth's
    per-satellite transmit times: subframe k of a 30 s frame starts at TOW = 30 j + 6 (k - 1))."""
    t, ttx = truth["t_s"][:], truth["t_tx_tow_s"][:]
    done = []
    for k in range(ttx.shape[1]):
        ends = []
        for sf in (1, 2, 3):
            s0 = np.ceil(ttx[0, k] / 6.0) * 6.0
            while int(round(s0 / 6.0)) % 5 != sf - 1:
                s0 += 6.0
            ends.append(s0 + 6.0)
        te = max(ends)
        done.append(float(np.interp(te, ttx[:, k], t)) if te <= ttx[-1, k] else np.inf)
    return sorted(done)[n_channels - 1]


def _fix_errors(res, truth):
    tsi = truth["sample_index"][:]
    s = np.array([f["sample_index"] for f in res.fixes])
    P = np.array([f["pos_e"] for f in res.fixes])
    V = np.array([f["vel_e"] for f in res.fixes])
    Pt = np.stack([np.interp(s, tsi, truth["pos_e"][:, i]) for i in range(3)], axis=1)
    Vt = np.stack([np.interp(s, tsi, truth["vel_e"][:, i]) for i in range(3)], axis=1)
    return (np.sqrt(np.mean(np.sum((P - Pt) ** 2, axis=1))), np.sqrt(np.mean(np.sum((V - Vt) ** 2, axis=1))))


@pytest.mark.slow
@pytest.mark.ci
def test_acceptance_static_60s_everything_from_the_signal(tmp_path):
    from ultratight.receiver.scalar.receiver import ProcessConfig, process
    from ultratight.signals.recording.iffile import open_if
    files = _generate(tmp_path, "static-open-sky")
    truth = h5py.File(files["truth"], "r")
    # a real sky (broadcast Klobuchar, Saastamoinen): the receiver's default corrections, the
    # coefficients decoded from subframe 4 page 18 (2-8 s into the run, before the first fix)
    res = process(open_if(files["if"]), ProcessConfig())
    assert res.corrections["iono_source"] == "lnav" and {f["iono"] for f in res.fixes} == {"klobuchar"}
    t_eph = earliest_ephemeris_time(truth)
    pos_rms, vel_rms = _fix_errors(res, truth)
    print(f"\nstatic 60 s: earliest subframes 1-3 on 4 channels {t_eph:.3f} s, first fix {res.first_fix_s} s, "
          f"{len(res.fixes)} fixes, position RMS {pos_rms:.3f} m, velocity RMS {vel_rms:.4f} m/s, "
          f"real-time factor {res.realtime_factor:.3f}")
    assert res.first_fix_s <= t_eph + 2.0
    # docs/process.md "Measured" table, row "static 60 s (4 MHz), nothing but the signal": with the
    # real sky (subframes 1-3 on 4 channels at 32.074 s by the truth, first fix 32.1 s, 279 fixes)
    # 3D position RMS 0.256 m, velocity RMS 0.0223 m/s (this run, seed 1, 2026-11-28, with the code-noise
    # weights; 0.261 m before them; on the earlier vacuum scenario from TOW 518400, 420 fixes from 18.0 s:
    # 0.162 m / 0.0230 m/s, other seeds 0.16-0.56 m, slowly varying code errors with few independent
    # samples in the run). Bounds = documented x 1.5 (0.384 m, 0.0335 m/s): a doubling breaks them
    assert pos_rms <= 1.5 * 0.256, pos_rms
    assert vel_rms <= 1.5 * 0.0223, vel_rms


@pytest.mark.slow
@pytest.mark.ci
def test_acceptance_vehicle_turns(tmp_path):
    from ultratight.receiver.scalar.receiver import ProcessConfig, process
    from ultratight.receiver.dsp.tracking_layout import FL_PLL_LOCK
    from ultratight.signals.recording.iffile import open_if
    files = _generate(tmp_path, "vehicle-turns")
    truth = h5py.File(files["truth"], "r")
    # a real sky: the receiver's default corrections (coefficients from page 18, before the first fix)
    res = process(open_if(files["if"]), ProcessConfig(n_channels=12, record_epochs=True))
    assert res.corrections["iono_source"] == "lnav" and {f["iono"] for f in res.fixes} == {"klobuchar"}
    pos_rms, vel_rms = _fix_errors(res, truth)
    fs = truth.attrs["fs_hz"]
    worst = min(np.mean(e["flags"][e["sample_index"] > fs] & FL_PLL_LOCK > 0) for e in res.epochs.values())
    print(f"\nvehicle-turns: {len(res.channels)} channels, losses {sum(c['losses'] for c in res.channels)}, "
          f"worst phase-lock fraction after 1 s {worst:.4f}, position RMS {pos_rms:.3f} m, "
          f"velocity RMS {vel_rms:.4f} m/s")
    assert len(res.channels) == len(truth.attrs["prn"])
    assert all(c["losses"] == 0 and c["reacquisitions"] == 0 for c in res.channels)
    assert worst == 1.0
    # docs/process.md "Measured" table, row "vehicle-turns": with the real sky, position RMS 0.164 m
    # with the code-noise weights (0.20 m before them), velocity RMS 0.049 m/s (this run, seed 2, the
    # scenario's, 2026-11-28: 0.164 m, 0.0491 m/s, 279 fixes from 32.1 s; on the earlier vacuum scenario
    # from TOW 518400: 0.295 m, 0.0487 m/s, seeds 1-3 0.30-0.60 m). Bounds = documented x 1.5 (0.246 m,
    # 0.074 m/s): a doubling of either breaks them (the position's seed spread reached 2x, so another
    # seed's file may need its own figure)
    assert pos_rms <= 1.5 * 0.164, pos_rms
    assert vel_rms <= 1.5 * 0.049, vel_rms


@pytest.mark.parametrize("cn0", [28.0])
@pytest.mark.slow
def test_acceptance_sensitivity_static(tmp_path, cn0):
    """Tracking sensitivity: warm start from the truth (Doppler +10 Hz, code +0.25 chip), 60 s."""
    from ultratight.receiver.scalar.receiver import ProcessConfig, process
    from ultratight.receiver.dsp.tracking_layout import FL_PLL_LOCK
    from ultratight.signals.constellation import nominal_ephemerides
    from ultratight.signals.recording.iffile import open_if
    files = _generate(tmp_path, "static-open-sky", "--cn0", str(cn0), "--fs", "2.6e6")
    T = h5py.File(files["truth"], "r")
    prns = [int(p) for p in T.attrs["prn"]]
    tsi = T["sample_index"][:]
    assist = [dict(prn=p, doppler_hz=float(T["doppler_hz"][0, k]) + 10.0,
                   code_phase_chips=float(T["code_phase_chips"][0, k]) + 0.25, sample_index=int(tsi[0]),
                   cn0_dbhz=cn0) for k, p in enumerate(prns)]
    res = process(open_if(files["if"]), ProcessConfig(n_channels=len(prns), record_epochs=True),
                  ephemerides=nominal_ephemerides(int(T.attrs["week"]), float(T.attrs["tow0_s"])), assist=assist)
    fs = T.attrs["fs_hz"]
    # in memory: two C/A epochs can start inside one 1 ms truth row (code rate above nominal), and an
    # HDF5 dataset takes no repeated indices
    dop_t, cp_t = T["doppler_hz"][:], T["code_phase_chips"][:]
    for c in res.channels:
        e = res.epochs[c["prn"]]
        k = prns.index(c["prn"])
        late = e["sample_index"] > 5 * fs
        s = e["sample_index"][late]
        j = np.searchsorted(tsi, s, side="right") - 1
        rate = 1.023e6 * (1 + dop_t[j, k] / 1575.42e6)
        cp = (cp_t[j, k] + (s - tsi[j]) * rate / fs) % CA_LEN
        err = (e["code_phase_chips"][late] - cp + CA_LEN / 2) % CA_LEN - CA_LEN / 2
        lock = np.mean(e["flags"][late] & FL_PLL_LOCK > 0)
        print(f"\n{cn0} dB-Hz PRN {c['prn']}: losses {c['losses']}, lock {lock:.3f}, code RMS "
              f"{np.sqrt(np.mean(err ** 2)):.3f} chip, C/N0 est {c['cn0_dbhz']}, bit sync {c['bit_sync_s']}")
        assert c["losses"] == 0 and e["sample_index"][-1] > 59.9 * fs
        assert lock > 0.95 and np.sqrt(np.mean(err ** 2)) < 0.05
