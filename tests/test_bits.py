"""Navigation-data bits the receiver cannot know: the generator's ``nav.data`` switch, and the ultra-tight
engine's bit strategies (``assisted``, ``decoded``, ``blind``, a bit file) against the generator's record
of the bits it sent."""

import json

import h5py
import numpy as np
import pytest

from ultratight.errors import ConfigError, InputFileError
from ultratight.receiver.cli import metrics as M
from ultratight.receiver.deep.bitsources import check_strategy, known_words, read_bits_csv, write_bits_csv
from ultratight.receiver.cli import main
from ultratight.receiver.deep.options import EngineOptions
from ultratight.receiver.cli.scenario_config import load_scenario
from ultratight.receiver.cli.scenario_runner import errors_vs_truth, run_method
from ultratight.receiver.deep.startup import BitWipeoff
from ultratight.receiver.dsp.wipeoff import BIT_ASSISTED, BIT_BLIND, BIT_DECODED, BIT_FILE
from ultratight.signals.constellation import nominal_ephemerides
from ultratight.signals.synth.generator import generate
from ultratight.signals.lnav import decode_bits, nav_bits, nav_bits_mode
from ultratight.signals.lnav_message import quantise

WEEK = 2190
TOW0 = 518400.0               # a subframe 1 starts here
FS_HZ = 2.046e6


def _sf_of(bit_index):
    """Subframe ID (1..5) of absolute bit indices (20 ms bits of the week)."""
    return (np.asarray(bit_index) // 300) % 5 + 1


# ------------------------------------------------------------------------ the message itself
@pytest.fixture(scope="module")
def eph():
    return nominal_ephemerides(WEEK, TOW0)[20]


def test_random_sf45_keeps_subframes_1_to_3_decodable(eph):
    n = 300 * 10
    lnav = nav_bits(eph, WEEK, TOW0, n)
    rnd = nav_bits_mode(eph, WEEK, TOW0, n, "lnav-random-sf45", seed=5)
    assert np.array_equal(rnd, nav_bits_mode(eph, WEEK, TOW0, n, "lnav-random-sf45", seed=5))   # seeded
    assert not np.array_equal(rnd, nav_bits_mode(eph, WEEK, TOW0, n, "lnav-random-sf45", seed=6))
    # a stretch alone gives the same bits as the whole stream
    assert np.array_equal(nav_bits_mode(eph, WEEK, TOW0 + 7.02, 400, "lnav-random-sf45", seed=5), rnd[351:751])
    dec = decode_bits(rnd, prn=20, ref_week=WEEK)
    assert len(dec.subframes) >= 9 and dec.bad_words == []          # every word keeps valid parity
    assert dec.ephemeris == quantise(eph)
    k = int(TOW0 / 0.02) + np.arange(n)
    sf = _sf_of(k)
    wrong = lnav != rnd
    # subframes 4-5: about half the bits differ from what the ephemeris re-encodes
    assert 0.4 < wrong[(sf == 4) | (sf == 5)].mean() < 0.6
    # subframes 2-3: only the TLM word (message, integrity/reserved bit) and what its parity drags along
    w = (k % 300) // 30
    assert not wrong[((sf == 2) | (sf == 3)) & (w >= 2)].any()
    assert wrong[(sf == 1) & ((w >= 3) & (w <= 6))].mean() > 0.3     # subframe 1 reserved words


def test_random_mode_has_no_lnav_structure(eph):
    rnd = nav_bits_mode(eph, WEEK, TOW0, 3000, "random", seed=1)
    assert 0.45 < np.mean(rnd == 1) < 0.55
    assert decode_bits(rnd).subframes == []
    with pytest.raises(Exception, match="navigation data mode"):
        nav_bits_mode(eph, WEEK, TOW0, 10, "lnav-sf45")


def test_known_words_against_sent_bits(eph):
    """Parity-checked words of a noisy, inverted soft stream are exactly the sent bits; a corrupted word
    stays unknown."""
    rng = np.random.default_rng(3)
    k0 = int((TOW0 - 2.0) / 0.02)                   # 100 bits before subframe 1; subframes 1-4 follow
    sent = nav_bits_mode(eph, WEEK, TOW0 - 2.0, 300 * 4 + 100, "lnav-random-sf45", seed=2).astype(float)
    soft = -sent * 3.0 + rng.normal(0.0, 0.5, sent.size)            # inverted stream, no bit error
    bad = 100 + 300 + 4 * 30 + 5                                    # one wrong bit in word 5 of subframe 2
    soft[bad] = -soft[bad]
    k, v = known_words(soft, TOW0, prn=20, bit_index0=k0)
    j = k - k0
    assert np.array_equal(v, sent[j].astype(np.int8))
    words = sorted(set(((j - 100) // 30).tolist()))
    assert words == [w for w in range(40) if w != 14]               # every word of subframes 1-4 but that one
    # a timing that disagrees with the HOW gives nothing
    k2, _ = known_words(soft, TOW0, prn=20, bit_index0=k0 + 1)
    assert k2.size == 0


# ------------------------------------------------------------------------ the generator switch
def _cfg(**ov):
    base = {"satellites.max_count": 3, "satellites.cn0_dbhz": 35.0, "frontend.fs_hz": FS_HZ, "noise_events": []}
    base.update(ov)
    return load_scenario("paper-highdyn", base)


def test_generator_records_sent_bits_and_assisted_is_wrong_in_sf45(tmp_path):
    cfg = _cfg(**{"duration_s": 4.0, "time.tow_s": TOW0 + 16.0, "nav.data": "lnav-random-sf45"})
    res = generate(cfg, tmp_path, "g", progress=False)
    with h5py.File(res["truth"]) as f:
        sent = f["nav_bits"][()]
        b0 = int(f.attrs["nav_bit0"])
        assert f.attrs["nav_data"] == "lnav-random-sf45"
        prns = [int(p) for p in f.attrs["prn"]]
        # the per-row bit is the recorded bit of the row's transmit time
        ttx = f["t_tx_tow_s"][()]
        rows = f["nav_bit"][()]
    for c in range(len(prns)):
        k = np.floor(ttx[:, c] / 0.02 + 1e-7).astype(np.int64) - b0
        ok = np.abs(ttx[:, c] / 0.02 - np.round(ttx[:, c] / 0.02)) > 1e-3   # not on a bit edge
        assert np.array_equal(rows[ok, c], sent[c, k[ok]])
    ephs = nominal_ephemerides(WEEK, TOW0)
    aw = BitWipeoff(ephs, prns, WEEK, TOW0 + 16.0, 4.0)
    kb = int(aw.t0_ms[0]) // 20 + np.arange(aw.bits.shape[1])
    sel = (kb - b0 >= 0) & (kb - b0 < sent.shape[1])
    sf = _sf_of(kb[sel])
    wrong = aw.bits[:, sel] != sent[:, kb[sel] - b0]
    assert 0.35 < wrong[:, sf == 4].mean() < 0.65          # assisted wipe: half the bits of subframe 4 wrong
    assert not wrong[:, sf == 3].any()                     # subframe 3 (words 8-10): right
    # the default (lnav) data are exactly what the assisted wipe re-encodes
    cfg2 = _cfg(**{"duration_s": 1.0, "time.tow_s": TOW0 + 16.0})
    res2 = generate(cfg2, tmp_path, "h", progress=False)
    with h5py.File(res2["truth"]) as f:
        sent2, b02 = f["nav_bits"][()], int(f.attrs["nav_bit0"])
        assert f.attrs["nav_data"] == "lnav"
    aw2 = BitWipeoff(ephs, prns, WEEK, TOW0 + 16.0, 1.0)
    kb2 = int(aw2.t0_ms[0]) // 20 + np.arange(aw2.bits.shape[1])
    sel2 = (kb2 - b02 >= 0) & (kb2 - b02 < sent2.shape[1])
    assert np.array_equal(aw2.bits[:, sel2], sent2[:, kb2[sel2] - b02])


def test_scenario_rejects_unknown_nav_data():
    with pytest.raises(ConfigError, match="nav.data must be one of"):
        load_scenario("paper-highdyn", {"nav.data": "lnav-sf45"})


# ------------------------------------------------------------------------ the engine's strategies
@pytest.fixture(scope="module")
def unknown(tmp_path_factory):
    """20 s of paper-highdyn (3 satellites, 35 dB-Hz, no noise burst) with random subframes 4-5 and
    reserved fields: subframes 1, 2, 3 complete at 6, 12, 18 s."""
    d = tmp_path_factory.mktemp("bits")
    cfg = _cfg(**{"duration_s": 20.0, "nav.data": "lnav-random-sf45"})
    res = generate(cfg, d, "u", progress=False)
    paths = {"if": res["if"], "imu": res["imu"], "truth": res["truth"]}
    with h5py.File(res["truth"]) as f:
        sent, b0 = f["nav_bits"][()], int(f.attrs["nav_bit0"])
    return cfg, paths, sent, b0


def _run(unknown, bits):
    cfg, paths, _, _ = unknown
    res, truth = run_method(paths, cfg, "dlb-rackf", 1, options=EngineOptions(bits=bits, threads=1))
    d_err, c_err = errors_vs_truth(res, truth)
    t = res.t_start
    late = t[:, 0] > 1.0
    assert np.isfinite(d_err[late]).mean() > 0.99
    return res, float(np.sqrt(np.nanmean(d_err[late] ** 2))), M.summarize(t, d_err, c_err)["lock_lost_channels"]


def test_blind_keeps_lock_and_decides_the_bits(unknown):
    res, rms, lost = _run(unknown, "blind")
    assert lost == 0
    assert rms < 0.1
    assert np.all(res.bit_source == BIT_BLIND)
    info = res.info["bits"]
    assert info["strategy"] == "blind" and info["channel_strategy"] == ["blind"] * 3


def test_decoded_recovers_subframes_1_to_3_exactly(unknown):
    _, _, sent, b0 = unknown
    res, rms, lost = _run(unknown, "decoded")
    assert lost == 0 and rms < 0.1
    info = res.info["bits"]
    assert info["strategy"] == "decoded"
    # the known bits of the decoded source, by absolute bit index, against what was sent
    src = info["source"]
    assert src["decoded_words"] == [30, 30, 30]            # subframes 1-3: every word of every channel
    b = res.bit_source
    assert set(np.unique(b)) == {BIT_DECODED, BIT_BLIND}
    frac = np.mean(b == BIT_DECODED, axis=0)
    assert np.all((frac > 0.85) & (frac < 0.92))           # 18 s of 20 s


def test_decoded_bits_equal_sent_bits(unknown):
    from ultratight.receiver.deep.bitsources import decoded_from_pass
    from ultratight.receiver.deep.engine import UltratightEngine
    from ultratight.receiver.cli.scenario_runner import load_truth, truth_initial_state
    from ultratight.signals.constellation import ephemerides_for
    from ultratight.receiver.deep.startup import StartupErrors, perturb_state
    from ultratight.ins.imu_data import read_imu_h5
    from ultratight.signals.recording.iffile import open_if
    cfg, paths, sent, b0 = unknown
    tr = load_truth(paths["truth"])
    rng = np.random.default_rng(np.random.SeedSequence([1, 7]))
    init = perturb_state(truth_initial_state(cfg), StartupErrors(), rng)
    eng = UltratightEngine(open_if(paths["if"]), read_imu_h5(paths["imu"]), ephemerides_for(cfg), tr["prn"],
                           tr["week"], tr["tow0_s"], options=EngineOptions(bits="blind", threads=1), init_state=init)
    eng.run()
    w = eng.wipe
    rows = decoded_from_pass(w, tr["prn"], tr["tow0_s"], eng.duration_s + 1.0)
    for c in range(3):
        k = np.flatnonzero(rows.bits[c])
        kabs = rows.bit0 + k
        assert np.array_equal(rows.bits[c, k], sent[c, kabs - b0])                 # exactly the sent bits
        assert set(_sf_of(kabs)) == {1, 2, 3} and k.size == 900
        # blind decisions (up to the channel's 180 degree ambiguity) against the sent bits
        s = w.soft[c]
        nz = np.flatnonzero(s)[1:-1]
        agree = np.mean(np.sign(s[nz]) == sent[c, rows.bit0 + nz - b0])
        assert agree > 0.999 or agree < 0.001


def test_bit_file_strategy(unknown, tmp_path):
    cfg, paths, sent, b0 = unknown
    with h5py.File(paths["truth"]) as f:
        prns = [int(p) for p in f.attrs["prn"]]
    part = sent.copy()
    part[:, 500:] = 0                                       # unknown from bit 500 on
    p = tmp_path / "bits.csv"
    write_bits_csv(p, prns[:2], WEEK, b0, part[:2])          # the third PRN is not in the file
    back = read_bits_csv(p)
    assert sorted(back) == sorted(prns[:2])
    wk, tow, bit = back[prns[0]]
    assert np.all(wk == WEEK) and tow[0] == pytest.approx(b0 * 0.02) and np.array_equal(bit, part[0])
    res, rms, lost = _run(unknown, str(p))
    assert lost == 0 and rms < 0.1
    b = res.bit_source
    assert np.all(b[:, 2] == BIT_BLIND)
    assert np.all(b[:9000, :2] == BIT_FILE) and np.all(b[-1000:, :2] == BIT_BLIND)
    assert res.info["bits"]["channel_strategy"] == ["file", "file", "file"]


def test_assisted_unchanged_and_recorded(unknown):
    res, _, _ = _run(unknown, "assisted")
    assert np.all(res.bit_source == BIT_ASSISTED)
    assert "re-encoded from the ephemeris" in res.info["bits"]["source"]["note"]


def test_bit_file_errors(tmp_path):
    p = tmp_path / "b.csv"
    p.write_text("prn,week,tow\n1,2190,0.0\n")
    with pytest.raises(InputFileError, match="header must be prn,week,tow_s,bit"):
        read_bits_csv(p)
    p.write_text("prn,week,tow_s,bit\n1,2190,0.01,1\n")
    with pytest.raises(InputFileError, match="row 2: tow_s 0.01 is not a bit edge"):
        read_bits_csv(p)
    p.write_text("# c\nprn,week,tow_s,bit\n1,2190,0.02,2\n")
    with pytest.raises(InputFileError, match="row 2"):
        read_bits_csv(p)
    with pytest.raises(InputFileError, match="row 2"):      # refused before any processing
        check_strategy(str(p))
    with pytest.raises(ConfigError, match="neither assisted, decoded, blind nor an existing bit file"):
        check_strategy(str(tmp_path / "missing.csv"))
    assert check_strategy("decoded") == ("decoded", None)


def test_cli_bits_flag_errors(tmp_path, capsys):
    f = tmp_path / "x.ci8"
    f.write_bytes(b"\0" * 64)
    assert main(["process", str(f), "--fs", "2e6", "--format", "ci8", "--bits", "blind"]) == 2
    assert "--bits is only used with --mode ultratight" in capsys.readouterr().err


def test_cli_process_ultratight_blind(unknown, tmp_path, capsys):
    _, paths, _, _ = unknown
    out = tmp_path / "r.h5"
    assert main(["process", str(paths["if"]), "--mode", "ultratight", "--imu", str(paths["imu"]), "--bits", "blind",
                 "--duration", "3", "--json", "--out", str(out), "--startup", "truth-perturbed"]) == 0
    summ = json.loads(capsys.readouterr().out)
    assert summ["bit_strategy"] == "blind" and summ["bits"] == {str(p): "blind" for p in summ["prns"]}
    assert summ["blind_fraction"] == [1.0, 1.0, 1.0]
    with h5py.File(out) as f:
        b = f["bit_source"][()]
        assert b.shape == f["doppler_hz"].shape and np.all(b == BIT_BLIND)
        assert json.loads(f.attrs["info_json"])["bits"]["strategy"] == "blind"
    assert main(["process", str(paths["if"]), "--mode", "ultratight", "--imu", str(paths["imu"]), "--bits",
                 str(tmp_path / "nope.csv")]) == 2
    assert "neither assisted, decoded, blind nor an existing bit file" in capsys.readouterr().err


def test_decoded_scalar_pass_on_a_static_receiver(tmp_path):
    """``decoded-scalar``: the scalar receiver, started on predictions, decodes the words of a static
    receiver's signal; every known bit is a sent bit."""
    from ultratight.receiver.deep.bitsources import decoded_source
    from ultratight.receiver.cli.scenario_runner import load_truth
    from ultratight.signals.constellation import ephemerides_for
    from ultratight.receiver.deep.startup import predict_channels
    from ultratight.signals.recording.iffile import open_if
    # TOW 518400 (a frame start; the shipped scenario starts 374 s earlier, 16 s into a frame): subframe 1
    # is sent in the 13 s
    cfg = load_scenario("static-open-sky", {"duration_s": 13.0, "satellites.max_count": 2, "frontend.fs_hz": FS_HZ,
                                            "nav.data": "lnav-random-sf45", "time.tow_s": 518400.0})
    res = generate(cfg, tmp_path, "s", progress=False)
    tr = load_truth(res["truth"])
    with h5py.File(res["truth"]) as f:
        sent, b0 = f["nav_bits"][()], int(f.attrs["nav_bit0"])
        pos, vel = f["pos_e"][0], f["vel_e"][0]
    ephs = ephemerides_for(cfg)
    pred = predict_channels(ephs, tr["prn"], tr["week"], tr["tow0_s"], pos, vel, 0.0, 0.0)
    rows = decoded_source(open_if(res["if"]), tr["prn"], ephs, tr["week"], tr["tow0_s"], 13.0, pred)
    assert rows.strategy == "decoded-scalar"
    for c in range(2):
        k = np.flatnonzero(rows.bits[c])
        assert k.size >= 300                                     # subframe 1 at least, whole
        assert np.array_equal(rows.bits[c, k], sent[c, rows.bit0 + k - b0])
        assert 1 in set(_sf_of(rows.bit0 + k))
