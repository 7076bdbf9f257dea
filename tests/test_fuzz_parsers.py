"""Property-based fuzzing of every input parser (docs/reliability.md).

Each parser either parses or raises the project's error for its input
(:class:`InputFileError` -- including :class:`FormatError` -- or :class:`ConfigError`; the RINEX
reader's documented error is :class:`NavDataError`). Any other exception is a bug.

Default suite: 100 examples per parser; ``-m slow``: 2000.
"""

import json
import math
import tempfile
from pathlib import Path

import h5py
import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from conftest import SHARED_DATA
from ultratight.errors import ConfigError, InputFileError, NavDataError

ROOT = Path(__file__).resolve().parents[1]
SCENARIOS = ROOT / "ultratight" / "data" / "scenarios"
RINEX = SHARED_DATA / "rinex" / "brdc0010.22n"

# the default suite explores the same examples on every run (CI passes or fails on the code, not by
# chance); the slow suite draws fresh ones, and every counterexample it finds is pinned with @example
FAST = settings(max_examples=100, deadline=None, suppress_health_check=list(HealthCheck), database=None,
                derandomize=True)
SLOW = settings(max_examples=2000, deadline=None, suppress_health_check=list(HealthCheck), database=None)

scalars = st.one_of(
    st.none(), st.booleans(), st.integers(-10**12, 10**12), st.integers(),
    st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=12),
    st.sampled_from(["ci8", "i8", "ci16", "cf32", "i2packed", "ci2packed", "f32", "i16", "<i2", ">f4", "u1"]),
)
json_values = st.recursive(scalars, lambda c: st.one_of(st.lists(c, max_size=4),
                                                         st.dictionaries(st.text(max_size=8), c, max_size=4)),
                           max_leaves=8)
SIDECAR_KEYS = ["format", "fs_hz", "if_hz", "is_complex", "iq_conj", "inversion", "n_samples", "start_week",
                "start_tow_s", "bits", "dtype", "iq_swap", "prn", "generator"]


def _tmpdir():
    return tempfile.TemporaryDirectory(prefix="ut-fuzz-")


def _both(fn, examples=(), **strategies):
    """The property as a default-suite test (100 examples) and a slow one (2000); ``examples``:
    explicit cases (dicts of arguments) run first in both."""
    def build(prof):
        t = given(**strategies)(fn)
        for ex in examples:
            t = example(**ex)(t)
        return prof(t)
    return build(FAST), pytest.mark.slow(build(SLOW))


# ------------------------------------------------------------------------------------------ sidecar JSON
sidecar_docs = st.one_of(
    st.binary(max_size=200),
    st.dictionaries(st.sampled_from(SIDECAR_KEYS), json_values, max_size=10).map(
        lambda d: json.dumps(d).encode()),
    st.fixed_dictionaries({"format": st.sampled_from(["ci8", "i8", "ci16", "i2packed"]),
                           "fs_hz": st.one_of(st.floats(), st.integers(), st.text(max_size=5))},
                          optional={k: json_values for k in SIDECAR_KEYS[2:]}).map(lambda d: json.dumps(d).encode()),
    json_values.map(lambda v: json.dumps(v).encode()),
)


def _sidecar(doc, size):
    from ultratight.signals.recording.iffile import open_if
    with _tmpdir() as d:
        p = Path(d) / "x.bin"
        p.write_bytes(bytes(size))
        Path(str(p) + ".json").write_bytes(doc)
        try:
            src = open_if(p)
        except (InputFileError, ConfigError):
            return
        src.read(0, 16)
        src.close()


# found by the property: an optional field given as null (it means "not given")
NULL_SIDECARS = [{"doc": json.dumps(d).encode(), "size": 64} for d in (
    {"format": "i8", "fs_hz": 10, "if_hz": None},
    {"format": "ci8", "fs_hz": 4e6, **{k: None for k in SIDECAR_KEYS[2:]}},
    {"format": None, "fs_hz": None})]
test_fuzz_sidecar_json, test_fuzz_sidecar_json_slow = _both(_sidecar, NULL_SIDECARS, doc=sidecar_docs,
                                                            size=st.integers(0, 5000))


# ------------------------------------------------------------------------------------------ ION XML
ION = """<?xml version="1.0"?>
<metadata><system id="s"><freqbase format="{unit}">{fb}</freqbase></system>
<file><url>{url}</url><lane><block><chunk><endian>{endian}</endian><lump><stream>
<ratefactor>{rf}</ratefactor><quantization>{q}</quantization><packedbits>{pb}</packedbits>
<encoding>{enc}</encoding><format>{fmt}</format><band><translatedfreq format="{unit2}">{tf}</translatedfreq>
<inverted>{inv}</inverted></band></stream></lump></chunk></block></lane></file></metadata>"""
xml_text = st.one_of(st.text(alphabet=st.characters(blacklist_categories=("Cs",), blacklist_characters="<&\x00"),
                             max_size=8),
                     st.sampled_from(["1", "2", "8", "16", "32", "4000000", "-1", "0", "nan", "inf", "1e400", "x",
                                      "thirtytwo", "TC", "SM", "FP", "IQ", "IF", "QIn", "Hz", "MHz", "big", "little",
                                      "true", ""]))
ion_docs = st.one_of(
    st.builds(lambda **kw: ION.format(**kw).encode("utf-8"),
              unit=xml_text, fb=xml_text, url=xml_text, endian=xml_text, rf=xml_text, q=xml_text, pb=xml_text,
              enc=xml_text, fmt=xml_text, unit2=xml_text, tf=xml_text, inv=xml_text),
    st.binary(max_size=300),
)


def _ion(doc):
    from ultratight.signals.recording.iffile import parse_ion_metadata
    with _tmpdir() as d:
        p = Path(d) / "m.xml"
        p.write_bytes(doc)
        try:
            parse_ion_metadata(p)
        except (InputFileError, ConfigError):
            pass


test_fuzz_ion_xml, test_fuzz_ion_xml_slow = _both(_ion, doc=ion_docs)


# ------------------------------------------------------------------------------------------ RINEX nav
def _rinex_base():
    if not RINEX.is_file():
        pytest.skip(f"RINEX file not found at {RINEX}")
    lines = RINEX.read_text(errors="replace").splitlines()
    end = next(i for i, ln in enumerate(lines) if "END OF HEADER" in ln)
    return lines[:end + 1 + 8 * 3]        # header and three records


mutation = st.tuples(st.sampled_from(["replace", "delete", "insert", "dup"]), st.integers(0, 10**6),
                     st.integers(0, 79), st.one_of(xml_text, st.sampled_from(
                         [" nan", "inf", "-1.0D+99", "1e400", "99", "  ", "G", "E", "R01", "9999999999999"])))


def _mutate(lines, muts):
    lines = list(lines)
    for kind, i, col, text in muts:
        if not lines:
            lines = [text]
            continue
        i %= len(lines)
        if kind == "replace":
            ln = lines[i].ljust(80)
            lines[i] = ln[:col] + text + ln[col + len(text):]
        elif kind == "delete":
            del lines[i]
        elif kind == "insert":
            lines.insert(i, text)
        else:
            lines.insert(i, lines[i])
    return lines


def _rinex(muts):
    from ultratight.signals.rinex import read_rinex_nav
    lines = _mutate(_rinex_base(), muts)
    with _tmpdir() as d:
        p = Path(d) / "n.22n"
        p.write_text("\n".join(lines) + "\n", errors="replace")
        try:
            read_rinex_nav(p)
        except (InputFileError, ConfigError, NavDataError):
            pass


test_fuzz_rinex_nav, test_fuzz_rinex_nav_slow = _both(_rinex, muts=st.lists(mutation, min_size=1, max_size=4))


# ------------------------------------------------------------------------------------------ IMU CSV
csv_headers = st.one_of(
    st.sampled_from(["t_s,dthx_rad,dthy_rad,dthz_rad,dvx_mps,dvy_mps,dvz_mps",
                     "t_s,gx_dps,gy_dps,gz_dps,ax_g,ay_g,az_g",
                     "\ufefft_s,gx_radps,gy_radps,gz_radps,ax_mps2,ay_mps2,az_mps2",
                     "t_s,gx_foo,gy_dps,gz_dps,ax_g,ay_g,az_g", "t_s", ""]),
    st.text(max_size=40))
csv_token = st.one_of(st.floats(allow_nan=True, allow_infinity=True).map(repr), st.integers(-5, 5).map(str),
                      st.sampled_from(["", "nan", "inf", "x", '"', "1e400", "0x10", " "]), st.text(max_size=4))
csv_rows = st.lists(st.lists(csv_token, min_size=0, max_size=8).map(",".join), max_size=12)
csv_docs = st.one_of(
    st.builds(lambda h, rows: ("\n".join([h] + rows) + "\n").encode("utf-8", "surrogatepass"), csv_headers, csv_rows),
    st.builds(lambda rows: ("t_s,dthx_rad,dthy_rad,dthz_rad,dvx_mps,dvy_mps,dvz_mps\n" + "\n".join(
        f"{0.01 * (k + 1) + dt},{a},0,0,0,0,{b}" for k, (dt, a, b) in enumerate(rows))).encode(),
        st.lists(st.tuples(st.floats(-0.02, 0.02), st.floats(allow_nan=True), st.floats(allow_infinity=True)),
                 max_size=20)),
    st.binary(max_size=300),
)


def _imu_csv(doc):
    from ultratight.ins.imu_data import read_imu_csv
    with _tmpdir() as d:
        p = Path(d) / "imu.csv"
        p.write_bytes(doc)
        try:
            imu = read_imu_csv(p)
        except (InputFileError, ConfigError):
            return
        assert np.all(np.isfinite(imu.dtheta_b)) and np.all(np.isfinite(imu.dv_b))


test_fuzz_imu_csv, test_fuzz_imu_csv_slow = _both(_imu_csv, doc=csv_docs)


# ------------------------------------------------------------------------------------------ IMU HDF5
h5_text = st.text(alphabet=st.characters(blacklist_categories=("Cs",), blacklist_characters="\x00"), max_size=10)
attr_values = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(-10**6, 10**6), h5_text,
                        st.just("ultratight-imu"), st.lists(st.floats(), max_size=3))
arrays = st.one_of(
    st.builds(lambda n, cols, fill: np.full((n, cols) if cols else (n,), fill), st.integers(0, 6), st.integers(0, 4),
              st.floats(allow_nan=True, allow_infinity=True)),
    st.builds(lambda n: np.arange(1, n + 1) * 0.01, st.integers(0, 8)),
    st.builds(lambda n: np.zeros((n, 3)), st.integers(0, 8)),
    st.just(np.array([b"a", b"b"])),
)


def _imu_h5(fmt, rate, t0, meta, t, dth, dv, truth):
    from ultratight.ins.imu_data import read_imu_h5
    with _tmpdir() as d:
        p = Path(d) / "imu.h5"
        with h5py.File(p, "w") as f:
            f.attrs["format"] = fmt
            for k, v in (("rate_hz", rate), ("t0_s", t0), ("meta_json", meta)):
                if v is not None:
                    f.attrs[k] = v
            for k, v in (("t", t), ("dtheta_b", dth), ("dv_b", dv)):
                if v is not None:
                    f[k] = v
            if truth is not None:
                g = f.create_group("truth")
                for k, v in truth.items():
                    g[k] = v
        try:
            imu = read_imu_h5(p)
        except (InputFileError, ConfigError):
            return
        assert imu.rate_hz > 0 and np.all(np.isfinite(imu.dtheta_b)) and np.all(np.isfinite(imu.t))


test_fuzz_imu_h5, test_fuzz_imu_h5_slow = _both(
    _imu_h5, fmt=st.one_of(st.just("ultratight-imu"), attr_values), rate=st.one_of(st.none(), attr_values),
    t0=st.one_of(st.none(), attr_values), meta=st.one_of(st.none(), h5_text, st.just("{}")),
    t=st.one_of(st.none(), arrays), dth=st.one_of(st.none(), arrays), dv=st.one_of(st.none(), arrays),
    truth=st.one_of(st.none(), st.dictionaries(st.sampled_from(["t", "llh", "vel_l", "q_lb"]), arrays, max_size=4)))


# ------------------------------------------------------------------------------------------ scenario TOML
toml_values = st.one_of(
    st.sampled_from(["nan", "inf", "-inf", "-1", "0", "1e30", "1e-30", '"x"', "[1, 2]", "[]", "true", "{}",
                     '"ci8"', '"complex"', '"rinex"', "33", "2.5", '"static"', '"turns"', "[[1]]", "{ t0 = 1 }"]),
    st.integers().map(str), st.floats(allow_nan=False, allow_infinity=False).map(repr),
    st.text(alphabet="abc_=[]\"'.0123456789 \n", max_size=12))


def _toml_lines(name):
    return (SCENARIOS / f"{name}.toml").read_text().splitlines()


toml_mutation = st.tuples(st.sampled_from(["value", "key", "delete", "append", "raw"]), st.integers(0, 10**6),
                          toml_values, st.text(alphabet="abcdefghijklmnopqrstuvwxyz_", min_size=1, max_size=6))


def _scenario_toml(base, muts):
    from ultratight.receiver.cli.scenario_config import load_scenario
    lines = _toml_lines(base)
    for kind, i, val, name in muts:
        i %= len(lines)
        ln = lines[i]
        if kind == "value" and "=" in ln and not ln.lstrip().startswith("{"):
            lines[i] = ln.split("=", 1)[0] + "= " + val
        elif kind == "key" and "=" in ln:
            lines[i] = name + " =" + ln.split("=", 1)[1]
        elif kind == "key" and ln.startswith("["):
            lines[i] = f"[{name}]"
        elif kind == "delete":
            del lines[i]
        elif kind == "append":
            lines.append(f"{name} = {val}")
        elif kind == "raw":
            lines.insert(i, val)
        if not lines:
            lines = [""]
    with _tmpdir() as d:
        p = Path(d) / "s.toml"
        p.write_text("\n".join(lines) + "\n")
        try:
            cfg = load_scenario(p)
        except (ConfigError, InputFileError):
            return
        assert math.isfinite(cfg["duration_s"]) and cfg["duration_s"] > 0


_SEED_LINE = next(i for i, ln in enumerate(_toml_lines("static-open-sky")) if ln.startswith("seed"))
_TOML_EXAMPLES = [  # integer fields given non-finite values (found by the slow run)
    {"base": "static-open-sky", "muts": [("value", _SEED_LINE, v, "a")]} for v in ("nan", "inf", "-inf")]

test_fuzz_scenario_toml, test_fuzz_scenario_toml_slow = _both(
    _scenario_toml, examples=_TOML_EXAMPLES,
    base=st.sampled_from(["static-open-sky", "vehicle-turns", "paper-highdyn"]),
    muts=st.lists(toml_mutation, min_size=1, max_size=3))


def test_every_parser_is_fuzzed():
    names = {n for n in globals() if n.startswith("test_fuzz_")}
    for parser in ("sidecar_json", "ion_xml", "rinex_nav", "imu_csv", "imu_h5", "scenario_toml"):
        assert f"test_fuzz_{parser}" in names and f"test_fuzz_{parser}_slow" in names
    assert FAST.max_examples >= 100 and SLOW.max_examples >= 2000
