"""RINEX observation reader (ultratight.signals.rinex_obs): the GEONET station 0759 file read value for
value as georinex reads it; small RINEX 2 and RINEX 3 files written here (event records, cycle-slip
records, long satellite lists, continued observation lines, other systems, blank fields) read back to
the values written; corrupt records refused with one line naming file, line and field."""

import math
import warnings
from pathlib import Path

import numpy as np
import pytest

from ultratight.errors import InputFileError
from ultratight.signals.gpstime import datetime_to_gps
from ultratight.signals.observations import gps_seconds
from ultratight.signals.rinex_obs import read_rinex_obs

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
GEONET_OBS = DATA / "rinex-geonet" / "07590920.05o"
# the station coordinate the survey authority set (data README; the header's APPROX POSITION XYZ)
STATION_0759 = (-3976219.5082, 3382372.5671, 3652512.9849)


def _need(path):
    if not path.exists():
        pytest.skip(f"shared data not found: {path}")


def _georinex():
    return pytest.importorskip("georinex", reason="georinex (test dependency) not installed")


def _t(y, mo, d, h, mi, s):
    return float(gps_seconds(*datetime_to_gps(y, mo, d, h, mi, s)))


# ----------------------------------------------------------------------------- the 0759 station
def test_geonet_every_value_as_georinex_reads_it():
    _need(GEONET_OBS)
    gr = _georinex()
    raw = read_rinex_obs(GEONET_OBS)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ref = gr.load(GEONET_OBS)
    t_ref = (ref.time.values - np.datetime64("1980-01-06T00:00:00", "ns")).astype(np.int64) / 1e9
    assert raw.n_epochs == ref.time.size == 120
    # same epochs; the receiver's clock steps appear in the epoch lines (e.g. '30.0020000' s), which
    # georinex reads to the millisecond below (30.001 s): at most 1 ms apart, and ours are the text's
    assert np.abs(raw.t - t_ref).max() <= 1.0e-3 + 1e-6
    lines = GEONET_OBS.read_text().splitlines()
    secs = [float(ln[15:26]) for ln in lines if ln[:9] == " 05  4  2" and ln[26:29] == "  0"]
    assert len(secs) == raw.n_epochs and np.allclose(raw.t % 60.0, secs, atol=1e-6, rtol=0)
    svs = [str(s) for s in ref.sv.values]
    n_values = 0
    for k in range(raw.n_epochs):
        sl = raw.epoch(k)
        prns = raw.prn[sl]
        # the satellites of the epoch are the ones georinex holds any value for
        held = {int(s[1:]) for s in svs if np.isfinite(ref["C1"].values[k, svs.index(s)])
                or np.isfinite(ref["L1"].values[k, svs.index(s)])}
        assert set(prns.tolist()) == held
        for j, prn in enumerate(prns):
            col = svs.index(f"G{prn:02d}")
            for ours, name in ((raw.pr_m[sl][j], "C1"), (raw.phase_cyc[sl][j], "L1")):
                theirs = ref[name].values[k, col]
                assert (math.isnan(ours) and math.isnan(theirs)) or ours == theirs, (k, prn, name)
                n_values += 1
    # the file has no S1 and no D1: every C/N0 and Doppler is NaN
    assert "S1" not in ref and "D1" not in ref
    assert np.all(np.isnan(raw.cn0_dbhz)) and np.all(np.isnan(raw.doppler_hz))
    assert n_values == 2 * raw.prn.size and raw.prn.size == 948


def test_geonet_header_meta():
    _need(GEONET_OBS)
    raw = read_rinex_obs(GEONET_OBS)
    assert raw.meta["approx_position_xyz"] == list(STATION_0759)
    assert raw.meta["interval_s"] == 30.0 and raw.meta["marker"] == "0759"
    assert raw.meta["obs_types"] == ["L1", "C1", "L2", "P2"]
    assert raw.meta["signals"] == ["C1", "L1", None, None]
    assert raw.t[0] == _t(2005, 4, 2, 0, 0, 0.0)
    # 30 s epochs as the receiver stamped them (its clock steps by whole milliseconds)
    assert np.all(np.abs(np.diff(raw.t) - 30.0) <= 5e-3)


def test_geonet_p1_not_in_file_is_one_line():
    _need(GEONET_OBS)
    with pytest.raises(InputFileError, match=r"no P1 observations .*\(L1 C1 L2 P2\)"):
        read_rinex_obs(GEONET_OBS, code="P1")


# ---------------------------------------------------------------------------- RINEX 2 written here
def _hdr(label_text, label):
    return f"{label_text:<60}{label}"


def _f(v):
    """One RINEX observation field (F14.3 + LLI + SSI); None: blank."""
    return " " * 16 if v is None else f"{v:14.3f}  "


TYPES2 = ["C1", "L1", "D1", "S1", "P2", "L2", "C2"]          # seven: every record takes two lines


def _rinex2_epoch(y, mo, d, h, mi, s, flag, sats):
    head = f" {y % 100:02d} {mo:2d} {d:2d} {h:2d} {mi:2d}{s:11.7f}  {flag}{len(sats):3d}"
    lines = [head + "".join(sats[:12])]
    for k in range(12, len(sats), 12):
        lines.append(" " * 32 + "".join(sats[k:k + 12]))
    return lines


def _obs2(vals):
    """Observation lines of one satellite: five fields a line."""
    fields = [_f(v) for v in vals]
    return ["".join(fields[k:k + 5]).rstrip() for k in range(0, len(fields), 5)]


def _sat_values(prn, k):
    """Values of satellite ``prn`` at epoch ``k``: C1, L1, D1, S1, P2, L2, C2 (distinct per sat/epoch)."""
    return [2.0e7 + 1000.0 * prn + k, 1.0e8 + 10.0 * prn + 0.125 * k, -1000.0 + prn + 0.5 * k, 40.0 + prn % 10,
            2.0e7 + 1000.0 * prn + k + 3.0, 7.8e7 + prn, 2.0e7 + 1000.0 * prn + k + 2.0]


def _write_rinex2(path):
    """A RINEX 2.11 mixed file: epoch 0 with 14 satellites (two-line list, four GLONASS), an event
    record (flag 5, no records), header information (flag 4, two records), epoch 1 (flag 1) with a
    blank D1 and a blank C1, cycle-slip records (flag 6) and epoch 2."""
    lines = [_hdr("     2.11           OBSERVATION DATA    M (MIXED)", "RINEX VERSION / TYPE"),
             _hdr("TEST", "MARKER NAME"),
             _hdr(" -3976219.5082  3382372.5671  3652512.9849", "APPROX POSITION XYZ"),
             _hdr(f"{len(TYPES2):6d}" + "".join(f"{t:>6}" for t in TYPES2), "# / TYPES OF OBSERV"),
             _hdr("     1.000", "INTERVAL"),
             _hdr("  2020     1     5     0     0    0.0000000     GPS", "TIME OF FIRST OBS"),
             _hdr("", "END OF HEADER")]
    gps0 = [1, 3, 5, 7, 9, 11, 13, 15, 17, 19]
    sats0 = [f"G{p:2d}" for p in gps0[:6]] + ["R 1", "R 2"] + [f"G{p:2d}" for p in gps0[6:]] + ["R 3", "R24"]
    expect = {}
    lines += _rinex2_epoch(2020, 1, 5, 0, 0, 0.0, 0, sats0)
    for s in sats0:
        prn = int(s[1:])
        vals = _sat_values(prn, 0) if s[0] == "G" else [1.9e7] * 7
        lines += _obs2(vals)
        if s[0] == "G":
            expect[(0, prn)] = vals[:4]
    lines.append(" 20  1  5  0  0  0.5000000  5  0")
    lines.append(" " * 28 + "4  2")
    lines += [_hdr("A COMMENT INSIDE THE DATA", "COMMENT"), _hdr("   1.0000   0.0000   0.0000", "ANTENNA: DELTA H/E/N")]
    gps1 = [2, 4, 6, 8]
    lines += _rinex2_epoch(2020, 1, 5, 0, 0, 1.0, 1, [f"G{p:2d}" for p in gps1])
    for p in gps1:
        vals = _sat_values(p, 1)
        if p == 4:
            vals[2] = None                       # blank D1
        if p == 6:
            vals[0] = None                       # blank C1
        lines += _obs2(vals)
        expect[(1, p)] = [math.nan if v is None else v for v in vals[:4]]
    lines += _rinex2_epoch(2020, 1, 5, 0, 0, 1.0, 6, ["G 2"])
    lines += _obs2([1.0, None, None, None, None, None, None])
    lines += _rinex2_epoch(2020, 1, 5, 0, 0, 2.0, 0, ["G 2", "G 4"])
    for p in (2, 4):
        lines += _obs2(_sat_values(p, 2))
        expect[(2, p)] = _sat_values(p, 2)[:4]
    path.write_text("\n".join(lines) + "\n")
    return expect, [_t(2020, 1, 5, 0, 0, s) for s in (0.0, 1.0, 2.0)]


def _check_expect(raw, expect, times):
    assert raw.n_epochs == len(times) and np.array_equal(raw.t, times)
    got = {}
    for k in range(raw.n_epochs):
        sl = raw.epoch(k)
        for j, p in enumerate(raw.prn[sl]):
            got[(k, int(p))] = [raw.pr_m[sl][j], raw.phase_cyc[sl][j], raw.doppler_hz[sl][j], raw.cn0_dbhz[sl][j]]
    assert set(got) == set(expect)
    for key, vals in expect.items():
        np.testing.assert_array_equal(np.array(got[key]), np.array(vals, dtype=float), err_msg=str(key))


def test_rinex2_long_lists_continued_records_events_and_other_systems(tmp_path):
    path = tmp_path / "t.20o"
    expect, times = _write_rinex2(path)
    raw = read_rinex_obs(path)
    _check_expect(raw, expect, times)
    assert raw.meta["epoch_flags"].tolist() == [0, 1, 0]
    assert raw.meta["approx_position_xyz"] == [-3976219.5082, 3382372.5671, 3652512.9849]
    assert raw.meta["interval_s"] == 1.0
    assert [int(p) for p in raw.prn[raw.epoch(0)]] == [1, 3, 5, 7, 9, 11, 13, 15, 17, 19]


def test_rinex2_written_here_as_georinex_reads_it(tmp_path):
    """georinex on the same file (without the event and cycle-slip records, which it handles in its
    own way): the same C1 / L1 / D1 / S1 values."""
    gr = _georinex()
    path = tmp_path / "t.20o"
    _write_rinex2(path)
    lines = path.read_text().splitlines()
    # drop the records of flags 4/5/6 (lines of 'A COMMENT', the flag lines and the slip record)
    i5 = next(i for i, ln in enumerate(lines) if ln[26:29] == "  5")
    del lines[i5:i5 + 4]
    i6 = next(i for i, ln in enumerate(lines) if ln[26:29] == "  6")
    del lines[i6:i6 + 3]
    plain = tmp_path / "plain.20o"
    plain.write_text("\n".join(lines) + "\n")
    raw = read_rinex_obs(plain)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ref = gr.load(plain, use="G")
    svs = [str(s) for s in ref.sv.values]
    for k in range(raw.n_epochs):
        sl = raw.epoch(k)
        for j, p in enumerate(raw.prn[sl]):
            col = svs.index(f"G{p:02d}")
            for ours, name in ((raw.pr_m, "C1"), (raw.phase_cyc, "L1"), (raw.doppler_hz, "D1"), (raw.cn0_dbhz, "S1")):
                a, b = ours[sl][j], ref[name].values[k, col]
                assert (math.isnan(a) and math.isnan(b)) or a == b, (k, p, name, a, b)


# ---------------------------------------------------------------------------- RINEX 3 written here
TYPES3_G = ["C1C", "L1C", "D1C", "S1C", "C2W", "L2W", "C5Q", "L5Q", "D5Q", "S5Q", "C2L", "L2L", "D2L", "S2L"]


def _write_rinex3(path):
    """RINEX 3.04 mixed: 14 GPS types (the type list continues), Galileo satellites skipped, a flag-4
    header record, a flag-6 slip record, blank fields."""
    types_line1 = "G" + f"{len(TYPES3_G):5d}" + "".join(f" {t}" for t in TYPES3_G[:13])
    types_line2 = " " * 6 + "".join(f" {t}" for t in TYPES3_G[13:])
    lines = [_hdr("     3.04           OBSERVATION DATA    M", "RINEX VERSION / TYPE"),
             _hdr("R3TEST", "MARKER NAME"),
             _hdr("  1113194.9079 -4842853.7011  3985496.2542", "APPROX POSITION XYZ"),
             _hdr(types_line1, "SYS / # / OBS TYPES"), _hdr(types_line2, "SYS / # / OBS TYPES"),
             _hdr("E    2 C1C L1C", "SYS / # / OBS TYPES"),
             _hdr("     0.250", "INTERVAL"),
             _hdr("  2023    11    26    23    59   59.7500000     GPS", "TIME OF FIRST OBS"),
             _hdr("", "END OF HEADER")]
    expect = {}
    epochs = [(59.75, [("G", 5), ("E", 11), ("G", 12), ("G", 30)]), (0.0, [("G", 5), ("G", 30)])]
    for k, (sec, sats) in enumerate(epochs):
        mi, hh, day = (59, 23, 26) if k == 0 else (0, 0, 27)
        lines.append(f"> 2023 11 {day:02d} {hh:02d} {mi:02d}{sec:11.7f}  0{len(sats):3d}")
        for sys_, p in sats:
            if sys_ == "E":
                lines.append(f"E{p:02d}" + _f(2.3e7) + _f(1.2e8))
                continue
            vals = _sat_values(p, k) + [None] * (len(TYPES3_G) - 7)
            if (k, p) == (0, 12):
                vals[3] = None                   # blank S1C
            lines.append((f"G{p:02d}" + "".join(_f(v) for v in vals)).rstrip())
            expect[(k, p)] = [math.nan if v is None else v for v in vals[:4]]
        if k == 0:
            lines.append(">" + " " * 30 + "4  1")
            lines.append(_hdr("EVENT COMMENT", "COMMENT"))
            lines.append("> 2023 11 26 23 59 59.7500000  6  1")
            lines.append("G05" + _f(1.0))
    path.write_text("\n".join(lines) + "\n")
    return expect, [_t(2023, 11, 26, 23, 59, 59.75), _t(2023, 11, 27, 0, 0, 0.0)]


def test_rinex3_written_here_read_back(tmp_path):
    path = tmp_path / "t.23o"
    expect, times = _write_rinex3(path)
    raw = read_rinex_obs(path)
    _check_expect(raw, expect, times)
    assert raw.meta["obs_types"] == TYPES3_G and raw.meta["signals"] == ["C1C", "L1C", "D1C", "S1C"]
    assert raw.meta["interval_s"] == 0.25 and raw.meta["version"] == 3.04
    assert raw.t[1] - raw.t[0] == pytest.approx(0.25, abs=1e-9)        # across the day boundary


def test_rinex3_written_here_as_georinex_reads_it(tmp_path):
    gr = _georinex()
    path = tmp_path / "t.23o"
    _write_rinex3(path)
    lines = path.read_text().splitlines()
    i4 = next(i for i, ln in enumerate(lines) if ln.startswith(">" + " " * 30 + "4"))
    del lines[i4:i4 + 4]                      # the flag-4 and flag-6 records
    plain = tmp_path / "plain.23o"
    plain.write_text("\n".join(lines) + "\n")
    raw = read_rinex_obs(plain)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ref = gr.load(plain, use="G")
    svs = [str(s) for s in ref.sv.values]
    for k in range(raw.n_epochs):
        sl = raw.epoch(k)
        for j, p in enumerate(raw.prn[sl]):
            col = svs.index(f"G{p:02d}")
            for ours, name in ((raw.pr_m, "C1C"), (raw.phase_cyc, "L1C"), (raw.doppler_hz, "D1C"),
                               (raw.cn0_dbhz, "S1C")):
                a, b = ours[sl][j], ref[name].values[k, col]
                assert (math.isnan(a) and math.isnan(b)) or a == b, (k, p, name, a, b)


# ----------------------------------------------------------------------------------- corruption
def _corrupt(tmp_path, writer, old, new, count=1):
    path = tmp_path / "c.obs"
    writer(path)
    text = path.read_text()
    assert old in text
    path.write_text(text.replace(old, new, count))
    lineno = text[:text.index(old)].count("\n") + 1
    return path, lineno


@pytest.mark.parametrize("writer", [_write_rinex2, _write_rinex3])
def test_corrupt_observation_value_is_one_line_naming_line_and_field(tmp_path, writer):
    path, lineno = _corrupt(tmp_path, writer, "20005000.000", "2000x000.000")
    with pytest.raises(InputFileError) as ei:
        read_rinex_obs(path)
    msg = str(ei.value)
    assert "\n" not in msg and str(path) in msg and f"line {lineno}:" in msg
    assert "field 'observation 1 of G05'" in msg and "'2000x000.000' is not a number" in msg


def test_corrupt_epoch_and_truncation(tmp_path):
    path, lineno = _corrupt(tmp_path, _write_rinex2, " 20  1  5  0  0  2.0000000", " 20 13  5  0  0  2.0000000")
    with pytest.raises(InputFileError, match=rf"line {lineno}: field 'epoch' out of range"):
        read_rinex_obs(path)
    path = tmp_path / "t.20o"
    _write_rinex2(path)
    path.write_text("\n".join(path.read_text().splitlines()[:-2]) + "\n")      # last record cut
    with pytest.raises(InputFileError, match=r"truncated: observations of 2 satellites"):
        read_rinex_obs(path)


def test_not_an_observation_file(tmp_path):
    nav = DATA / "rinex-geonet" / "07590920.05n"
    _need(nav)
    with pytest.raises(InputFileError, match=r"line 1: field 'file type' = 'N', expected 'O'"):
        read_rinex_obs(nav)
    p = tmp_path / "x.obs"
    p.write_text("hello\n")
    with pytest.raises(InputFileError, match=r"line 1: missing 'RINEX VERSION / TYPE'"):
        read_rinex_obs(p)


def test_rinex2_type_list_over_nine_continues(tmp_path):
    """Ten observation types: the '# / TYPES OF OBSERV' record continues on a second line and every
    satellite record takes two lines; C1 is the tenth type here."""
    types = ["L1", "D1", "S1", "P1", "P2", "L2", "C2", "S2", "D2", "C1"]
    lines = [_hdr("     2.10           OBSERVATION DATA    G (GPS)", "RINEX VERSION / TYPE"),
             _hdr(f"{len(types):6d}" + "".join(f"{t:>6}" for t in types[:9]), "# / TYPES OF OBSERV"),
             _hdr(" " * 6 + "".join(f"{t:>6}" for t in types[9:]), "# / TYPES OF OBSERV"),
             _hdr("", "END OF HEADER")]
    lines += _rinex2_epoch(2010, 6, 30, 12, 0, 0.0, 0, ["G 9", "G31"])
    vals = {9: [1.1e8, -123.5, 45.0, 2.1e7, 2.1e7, 8.6e7, 2.1e7, 40.0, -96.25, 20987654.321],
            31: [1.2e8, 2000.25, 38.0, 2.2e7, 2.2e7, 9.1e7, 2.2e7, 33.0, 1559.0, 22345678.901]}
    for p in (9, 31):
        lines += _obs2(vals[p])
    path = tmp_path / "ten.10o"
    path.write_text("\n".join(lines) + "\n")
    raw = read_rinex_obs(path)
    assert raw.meta["obs_types"] == types and raw.n_epochs == 1
    assert raw.prn.tolist() == [9, 31]
    for j, p in enumerate((9, 31)):
        v = vals[p]
        assert [raw.pr_m[j], raw.phase_cyc[j], raw.doppler_hz[j], raw.cn0_dbhz[j]] == [v[9], v[0], v[1], v[2]]


def test_rinex3_of_the_process_writer_read_back(tmp_path):
    """The RINEX 3.04 file ``ultratight process --rinex-obs`` writes (receiver/io/rinex_out) read back:
    every value to the file's three decimals, the phase blank where the writer had no lock."""
    from ultratight.receiver.io.rinex_out import RinexObsWriter
    rng = np.random.default_rng(11)
    path = tmp_path / "p.obs"
    w = RinexObsWriter(path, 0.1)
    written = []
    for k in range(5):
        sats = []
        for prn in (4, 9, 17, 28):
            s = {"prn": prn, "pr_m": 2.0e7 + rng.uniform(0, 5e6), "phase_cycles": rng.uniform(-1e8, 1e8),
                 "doppler_hz": rng.uniform(-4000, 4000), "cn0_dbhz": rng.uniform(30, 50),
                 "lock": not (k == 2 and prn == 9), "continuous": True}
            sats.append(s)
        w.add_epoch(2300, 345600.0 + 0.1 * k, sats)
        written.append(sats)
    assert w.finish((-2694685.473, -4293642.366, 3857878.924))
    raw = read_rinex_obs(path)
    assert raw.n_epochs == 5 and raw.meta["interval_s"] == 0.1
    assert np.allclose(raw.meta["approx_position_xyz"], (-2694685.473, -4293642.366, 3857878.924), atol=1e-4)
    assert np.allclose(raw.t - gps_seconds(2300, 345600.0), 0.1 * np.arange(5), atol=1e-7)
    for k, sats in enumerate(written):
        sl = raw.epoch(k)
        assert raw.prn[sl].tolist() == [4, 9, 17, 28]
        for j, s in enumerate(sats):
            assert abs(raw.pr_m[sl][j] - s["pr_m"]) <= 5e-4 and abs(raw.doppler_hz[sl][j] - s["doppler_hz"]) <= 5e-4
            assert abs(raw.cn0_dbhz[sl][j] - s["cn0_dbhz"]) <= 5e-4
            if s["lock"]:
                assert abs(raw.phase_cyc[sl][j] - s["phase_cycles"]) <= 5e-4
            else:
                assert math.isnan(raw.phase_cyc[sl][j])
