"""Hostile inputs against every command (docs/reliability.md).

Each case runs the CLI in a fresh folder holding the inputs and checks: the exit status, a
fragment of the message, exactly one line on stderr, no traceback, no temporary or partial file
left behind, and every input file byte-identical afterwards.
"""

import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from conftest import SHARED_DATA

REAL_IQ = SHARED_DATA / "real-if" / "pocketsdr" / "L1_20211202_084700_4MHz_IQ.bin"
ROOT_USER = hasattr(os, "geteuid") and os.geteuid() == 0


def cli(args, cwd, timeout=300, **kw):
    return subprocess.run([sys.executable, "-m", "ultratight.receiver.cli", *args], cwd=cwd, capture_output=True,
                          text=True, timeout=timeout, **kw)


def snapshot(d):
    out = {}
    for p in sorted(Path(d).rglob("*")):
        if p.is_file() and not p.is_symlink():
            out[str(p.relative_to(d))] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def leftovers(d):
    """Temporary / partial files (hidden .tmp / .part names) under d."""
    return [str(p) for p in Path(d).rglob(".*") if ".tmp" in p.name or ".part" in p.name]


def assert_clean_failure(res, rc, fragment, before, d):
    err = res.stderr
    assert "Traceback" not in err, err
    assert res.returncode == rc, (res.returncode, err)
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert fragment.lower() in lines[0].lower(), lines[0]
    after = snapshot(d)
    for name, h in before.items():
        assert after.get(name) == h, f"input {name} changed or vanished"
    assert not leftovers(d), leftovers(d)


# ------------------------------------------------------------------------------------------
# inputs
# ------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def base(tmp_path_factory):
    """A folder with a short generated recording + IMU (vehicle-turns, 1 s at 2.046 MHz) and the
    crafted hostile files the cases use."""
    d = tmp_path_factory.mktemp("hostile")
    res = cli(["generate", "vehicle-turns", "--duration", "1", "--fs", "2.046e6", "--out", "v", "--no-progress"], d)
    assert res.returncode == 0, res.stderr
    # a real recording (the data-loss reproduction), when the shared data are present
    if REAL_IQ.is_file():
        shutil.copyfile(REAL_IQ, d / "c.bin")
    else:
        (d / "c.bin").write_bytes(np.random.default_rng(0).integers(-8, 8, 400000, dtype=np.int8).tobytes())
    # sidecars
    for name, text in {"fs_str": '{"format": "ci8", "fs_hz": "4MHz"}', "array": '[1, 2, 3]',
                       "ifnan": '{"format": "ci8", "fs_hz": 4e6, "if_hz": NaN}',
                       "negn": '{"format": "ci8", "fs_hz": 4e6, "n_samples": -5}'}.items():
        shutil.copyfile(d / "c.bin", d / f"{name}.bin")
        (d / f"{name}.bin.json").write_text(text)
    shutil.copyfile(d / "c.bin", d / "latin.bin")
    (d / "latin.bin.json").write_bytes(b'{"format": "ci8", "fs_hz": 4e6, "note": "\xe9\xff"}')
    # ION metadata
    ion = """<?xml version="1.0"?><metadata><system id="s"><freqbase format="Hz">4000000</freqbase></system>
<file><url>c.bin</url><lane><block><chunk><endian>little</endian><lump><stream>
<ratefactor>{rf}</ratefactor><quantization>{q}</quantization><packedbits>16</packedbits>
<encoding>TC</encoding><format>IQ</format><band><translatedfreq format="Hz">0</translatedfreq></band>
</stream></lump></chunk></block></lane></file></metadata>"""
    (d / "rf.xml").write_text(ion.format(rf="x", q=8))
    (d / "quant.xml").write_text(ion.format(rf=1, q="thirtytwo"))
    # IMU files
    with h5py.File(d / "v.imu.h5", "r") as f:
        t = f["t"][()]
    n = min(t.size, 100)
    def imu_h5(name, rate=100.0, meta="{}", dth=None, t_shift=0.0, drop_rate=False):
        with h5py.File(d / name, "w") as f:
            f.attrs["format"] = "ultratight-imu"
            f.attrs["version"] = 1
            if not drop_rate:
                f.attrs["rate_hz"] = rate
            f.attrs["meta_json"] = meta
            f["t"] = t[:n] + t_shift
            f["dtheta_b"] = np.zeros((n, 3)) if dth is None else dth
            f["dv_b"] = np.zeros((n, 3))
    bad = np.zeros((n, 3))
    bad[5, 1] = np.nan
    imu_h5("nan.imu.h5", dth=bad)
    imu_h5("rate0.imu.h5", rate=0.0)
    imu_h5("norate.imu.h5", drop_rate=True)
    imu_h5("ratestr.imu.h5", rate="fast")
    imu_h5("meta.imu.h5", meta="{broken")
    # the generated IMU cut to its first half (every per-sample dataset)
    def cut_half(src, dst, n_all):
        for k, v in src.attrs.items():
            dst.attrs[k] = v
        for k, item in src.items():
            if isinstance(item, h5py.Group):
                cut_half(item, dst.create_group(k), n_all)
                continue
            x = item[()]
            dst[k] = x[: n_all // 2] if getattr(x, "ndim", 0) >= 1 and x.shape[0] == n_all else x
            for a, v in item.attrs.items():
                dst[k].attrs[a] = v
    with h5py.File(d / "v.imu.h5", "r") as src, h5py.File(d / "short.imu.h5", "w") as dst:
        cut_half(src, dst, src["t"].shape[0])
    # the generated IMU with every stamp shifted by +10 s (t0 attribute left at 0)

    shutil.copyfile(d / "v.imu.h5", d / "shift.imu.h5")
    with h5py.File(d / "shift.imu.h5", "r+") as f:
        f["t"][...] = f["t"][()] + 10.0
    (d / "binary.csv").write_bytes(bytes(range(256)) * 4)
    (d / "b.csv").write_text("prn,week,tow_s,bit\n1,2000,0.00,1\n")
    # the recording with a sidecar that lists no PRNs (the start-up must find them)
    shutil.copyfile(d / "v.ci8", d / "noprn.ci8")
    (d / "noprn.ci8.json").write_text(json.dumps({k: v for k, v in json.loads((d / "v.ci8.json").read_text()).items()
                                                  if k != "prn"}))
    shutil.copyfile(d / "v.imu.h5", d / "d.imu.h5")          # an IMU with a declaration sidecar
    (d / "d.imu.h5.json").write_text('{"axes": "FLU"}')
    rows = ["t_s,dthx_rad,dthy_rad,dthz_rad,dvx_mps,dvy_mps,dvz_mps"] + \
        [f"{0.01 * (k + 1):.2f},0,0,0,0,0,0.0980665" for k in range(50)]
    (d / "bom.csv").write_bytes(b"\xef\xbb\xbf" + ("\n".join(rows) + "\n").encode())
    # scenario TOMLs
    src = (Path(__file__).resolve().parents[1] / "ultratight" / "data" / "scenarios" / "vehicle-turns.toml").read_text()
    (d / "typo_table.toml").write_text(src.replace("[imu]", "[imu_]"))
    (d / "typo_key.toml").write_text(src.replace("duration_s = 60.0", "durration_s = 1.0"))
    (d / "huge.toml").write_text(src.replace("duration_s = 60.0", "duration_s = 1e12"))
    (d / "noisy.toml").write_text(src + "\n[[noise_events]]\nt0_s = 0.1\nt1_s = 0.2\nnoise_factor = 1e30\n")
    # a truncated recording: the sidecar states more samples than the file holds
    shutil.copyfile(d / "v.ci8", d / "trunc.ci8")
    shutil.copyfile(d / "v.ci8.json", d / "trunc.ci8.json")
    with open(d / "trunc.ci8", "r+b") as f:
        f.truncate(os.path.getsize(d / "v.ci8") // 2)
    os.mkdir(d / "adir")
    (d / "camp" / "runs").mkdir(parents=True)      # another scenario's campaign
    (d / "camp" / "campaign.json").write_text('{"scenario": "paper-afm-noise", "runs": 1}')
    (d / "camp" / "runs" / "run-00000.h5").write_bytes(b"run of paper-afm-noise")
    (d / "bench").mkdir()
    (d / "bench" / "bench_noop.py").write_text(
        "import json, sys\njson.dump({'ok': 1}, open(sys.argv[sys.argv.index('--json') + 1], 'w'))\n")
    return d


@pytest.fixture
def work(base, tmp_path):
    """A private copy of the inputs (symlinks to the big read-only ones would hide overwrites)."""
    d = tmp_path / "w"
    shutil.copytree(base, d, symlinks=True)
    if hasattr(os, "mkfifo"):
        os.mkfifo(d / "fifo")
    return d


def _address_space(nbytes):
    import resource

    def pre():
        resource.setrlimit(resource.RLIMIT_AS, (nbytes, nbytes))
    return pre


LONG = "x" * 300 + ".h5"
P = ["process"]
CI8 = ["--fs", "4e6", "--format", "ci8"]

# (id, argv, exit status, message fragment)
CASES = [
    # 1. data loss: an output naming an input
    ("out-is-recording", P + ["c.bin", "--fs", "4e6", "--if", "0", "--format", "ci8", "--iq-conj", "--out", "c.bin"],
     2, "refusing to overwrite an input"),
    ("out-is-imu", P + ["v.ci8", "--mode", "ultratight", "--imu", "v.imu.h5", "--out", "v.imu.h5"], 2,
     "refusing to overwrite an input"),
    ("out-equals-csv", P + ["c.bin", *CI8, "--out", "x", "--csv", "x"], 2, "name the same file"),
    ("out-is-sidecar", P + ["v.ci8", "--out", "v.ci8.json"], 2, "refusing to overwrite an input"),
    ("kml-is-recording", P + ["c.bin", *CI8, "--kml", "c.bin"], 2, "refusing to overwrite"),
    ("save-imu-is-source", ["ins", "v.imu.h5", "--save-imu", "v.imu.h5"], 2, "refusing to overwrite"),
    ("csv-is-bit-file", P + ["v.ci8", "--mode", "ultratight", "--imu", "v.imu.h5", "--bits", "b.csv", "--csv", "b.csv"],
     2, "refusing to overwrite an input"),
    ("rinex-obs-is-bit-file", P + ["v.ci8", "--mode", "ultratight", "--imu", "v.imu.h5", "--bits", "b.csv",
                                   "--rinex-obs", "b.csv"], 2, "refusing to overwrite an input"),
    ("csv-is-absent-imu-sidecar", P + ["v.ci8", "--mode", "ultratight", "--imu", "v.imu.h5", "--csv",
                                       "v.imu.h5.json"], 2, "refusing to write an output there"),
    ("nmea-is-imu-sidecar", P + ["v.ci8", "--mode", "ultratight", "--imu", "d.imu.h5", "--nmea", "d.imu.h5.json"],
     2, "refusing to overwrite an input"),
    # 2. outputs found bad only after the run
    ("ut-out-missing-dir", P + ["v.ci8", "--mode", "ultratight", "--imu", "v.imu.h5", "--out", "nodir/u.h5"], 2,
     "does not exist"),
    ("ut-out-is-dir", P + ["v.ci8", "--mode", "ultratight", "--imu", "v.imu.h5", "--out", "adir"], 2,
     "is a directory"),
    ("out-too-long", P + ["c.bin", *CI8, "--out", LONG], 2, "too long"),
    ("bench-json-missing-dir", ["bench", "--dir", "bench", "--json", "nodir/b.json"], 2, "does not exist"),
    ("scenario-out-is-file", ["scenario", "vehicle-turns", "--out", "c.bin", "--duration", "1"], 2,
     "not a directory"),
    # 6. limits
    ("ins-rate-huge", ["ins", "paper-highdyn", "--rate", "1e7"], 2, "rate cap"),
    ("ins-duration-huge", ["ins", "paper-highdyn", "--duration", "1e7"], 2, "in memory"),
    ("generate-duration-huge", ["generate", "static-open-sky", "--duration", "1e9", "--out", "g/"], 2, "needs about"),
    ("toml-duration-huge", ["generate", "huge.toml", "--out", "g/"], 2, "needs about"),
    # 7. silent acceptance of bad numbers
    ("imu-nan", ["ins", "nan.imu.h5", "--json", "--init-llh", "41", "2", "50"], 2, "not a finite number"),
    ("sidecar-without-prns", P + ["noprn.ci8", "--mode", "ultratight", "--imu", "v.imu.h5"], 2,
     "the scalar pass over 1 s from t = 0 s gave 0 fixes"),
    ("imu-stamps-shifted", P + ["v.ci8", "--mode", "ultratight", "--imu", "shift.imu.h5"], 2, "time offset"),
    ("ut-iono-flag", P + ["v.ci8", "--mode", "ultratight", "--imu", "v.imu.h5", "--iono", "klobucher"], 2,
     "invalid choice: 'klobucher'"),
    ("ut-packing-flag", P + ["v.ci8", "--mode", "ultratight", "--imu", "v.imu.h5", "--packing", "lsb-first"], 2,
     "--packing not supported with --mode ultratight"),
    ("init-llh-nan", ["ins", "v.imu.h5", "--init-llh", "nan", "0", "0"], 2, "must be finite"),
    ("toml-typo-table", ["generate", "typo_table.toml", "--out", "g/"], 2, "did you mean 'imu'"),
    ("toml-typo-key", ["generate", "typo_key.toml", "--out", "g/"], 2, "did you mean 'duration_s'"),
    ("noise-factor-huge", ["generate", "noisy.toml", "--out", "g/", "--duration", "1"], 2, "noise_factor"),
    ("generate-fs-too-low", ["generate", "static-open-sky", "--fs", "1e3", "--out", "g/", "--duration", "1"], 2,
     "fs_hz"),
    # 8. tracebacks
    ("sidecar-fs-string", P + ["fs_str.bin"], 2, "must be a number"),
    ("sidecar-array", P + ["array.bin"], 2, "must be an object"),
    ("sidecar-not-utf8", P + ["latin.bin"], 2, "not utf-8"),
    ("meta-is-hdf5", P + ["c.bin", "--meta", "v.truth.h5"], 2, "not utf-8"),
    ("ion-ratefactor", P + ["c.bin", "--meta", "rf.xml"], 2, "malformed ion metadata"),
    ("ion-quantization", P + ["c.bin", "--meta", "quant.xml"], 2, "malformed ion metadata"),
    ("prn-abc", P + ["c.bin", *CI8, "--prn", "abc"], 2, "--prn"),
    ("prn-1e1", P + ["c.bin", *CI8, "--prn", "1e1"], 2, "--prn"),
    ("prn-hex", P + ["c.bin", *CI8, "--prn", "0x1f"], 2, "--prn"),
    ("prn-negative", P + ["c.bin", *CI8, "--prn=-1"], 2, "--prn"),
    ("start-nan", P + ["c.bin", *CI8, "--start", "nan"], 2, "--start"),
    ("duration-inf", P + ["c.bin", *CI8, "--duration", "inf"], 2, "--duration"),
    ("imu-rate-zero", ["ins", "rate0.imu.h5", "--init-llh", "41", "2", "50"], 2, "rate_hz"),
    ("imu-rate-missing", ["ins", "norate.imu.h5", "--init-llh", "41", "2", "50"], 2, "rate_hz"),
    ("imu-rate-string", ["ins", "ratestr.imu.h5", "--init-llh", "41", "2", "50"], 2, "rate_hz"),
    ("imu-meta-broken", ["ins", "meta.imu.h5", "--init-llh", "41", "2", "50"], 2, "meta_json"),
    ("imu-csv-binary", ["ins", "binary.csv", "--init-llh", "41", "2", "50"], 2, "not a text csv"),
    ("bits-binary", P + ["v.ci8", "--mode", "ultratight", "--imu", "v.imu.h5", "--bits", "binary.csv"], 2,
     "not a bit file"),
    ("bits-is-hdf5", P + ["v.ci8", "--mode", "ultratight", "--imu", "v.imu.h5", "--bits", "v.truth.h5"], 2,
     "not a bit file"),
    ("generate-seed-negative", ["generate", "static-open-sky", "--seed", "-3", "--out", "g/"], 2, "seed"),
    ("ins-seed-negative", ["ins", "static-open-sky", "--seed", "-3", "--duration", "1"], 2, "seed"),
    # 9. wrong or vague messages
    ("if-is-directory", P + ["adir", *CI8], 2, "is a directory"),
    ("if-is-fifo", P + ["fifo", *CI8], 2, "not a regular file"),
    ("prn-empty-range", P + ["c.bin", *CI8, "--prn", "5-3"], 2, "empty"),
    ("if-nan", P + ["c.bin", *CI8, "--if", "nan"], 2, "--if"),
    ("sidecar-if-nan", P + ["ifnan.bin"], 2, "if_hz"),
    ("sidecar-negative-n", P + ["negn.bin"], 2, "n_samples"),
    ("fs-beside-sidecar", P + ["v.ci8", "--fs", "4e6"], 2,
     "--fs 4e+06 Hz conflicts with the sidecar v.ci8.json, which states fs_hz = 2.046e+06 Hz"),
    ("if-beside-sidecar", P + ["v.ci8", "--if", "1e9"], 2,
     "--if 1e+09 Hz conflicts with the sidecar v.ci8.json, which states if_hz = 0 Hz"),
    # 11. out-of-range numbers accepted, clamped or cut short
    ("mask-above-90", P + ["v.ci8", "--mask", "95"], 2, "--mask must be an elevation in [0, 90) deg, got 95"),
    ("mask-negative", P + ["v.ci8", "--mask=-10"], 2, "--mask must be an elevation in [0, 90) deg, got -10"),
    # the limit at fs = 2.046 MHz: 0.45 fs = 920.7 kHz
    ("doppler-range-huge", P + ["v.ci8", "--doppler-range", "1e9"], 2, "--doppler-range must be in (0, 920700] Hz"),
    ("afm-duration-before-jump", ["scenario", "paper-afm-jump", "--duration", "20", "--out", "g/"], 2,
     "ends before the attitude-jump at fault.t_s = 30 s"),
    # campaign: another scenario's campaign under --resume; malformed and unreachable schedulers
    ("campaign-resume-other-scenario", ["campaign", "static-open-sky", "--runs", "1", "--resume", "--out", "camp"],
     2, "camp holds the campaign of scenario 'paper-afm-noise', not 'static-open-sky'"),
    ("campaign-scheduler-malformed", ["campaign", "static-open-sky", "--runs", "1", "--scheduler", "foo://bar:x",
                                      "--out", "g/"], 2, "unknown protocol 'foo'"),
    ("campaign-scheduler-unreachable", ["campaign", "static-open-sky", "--runs", "1", "--scheduler",
                                        "tcp://127.0.0.1:1", "--connect-timeout", "1", "--out", "g/"], 2,
     "cannot connect within 1 s"),
]


@pytest.mark.parametrize("case", CASES, ids=[c[0] for c in CASES])
def test_hostile_input(work, case):
    name, argv, rc, fragment = case
    if name == "if-is-fifo" and not hasattr(os, "mkfifo"):
        pytest.skip("no FIFOs on this platform")
    before = snapshot(work)
    kw = {}
    if name.endswith("-huge") and hasattr(os, "fork"):
        # keep a run that ignores its estimate from taking the machine's memory (12 GB address space)
        kw["preexec_fn"] = _address_space(12 * 2**30)
    res = cli(argv, work, **kw)
    assert_clean_failure(res, rc, fragment, before, work)
    assert not (work / "g").exists() or not any((work / "g").iterdir())


@pytest.mark.skipif(ROOT_USER, reason="permission checks do not apply to root")
def test_unreadable_and_read_only(work):
    os.chmod(work / "c.bin", 0)
    os.mkdir(work / "ro")
    os.chmod(work / "ro", 0o555)
    try:
        before = snapshot(work)
        res = cli(P + ["c.bin", *CI8], work)
        assert_clean_failure(res, 2, "permission denied", before, work)
        os.chmod(work / "c.bin", 0o644)
        res = cli(P + ["c.bin", *CI8, "--out", "ro/x.h5"], work)
        assert_clean_failure(res, 2, "not writable", before, work)
    finally:
        os.chmod(work / "c.bin", 0o644)
        os.chmod(work / "ro", 0o755)


def _strict_json(text):
    def bad(name):
        raise ValueError(f"non-standard JSON constant {name}")
    return json.loads(text, parse_constant=bad)


def test_truncated_recording_is_processed_with_a_warning(work):
    """10. the sidecar states more samples than the file holds: process what is there, warn once."""
    before = snapshot(work)
    res = cli(P + ["trunc.ci8", "--prn", "11,14,10,28", "--duration", "0.3", "--json", "--no-progress"], work)
    assert "Traceback" not in res.stderr
    assert res.returncode in (0, 2), res.stderr          # 2 only if no satellite is found in 0.3 s
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "truncated recording" in lines[0], res.stderr
    assert snapshot(work) == before
    if res.returncode == 0:
        _strict_json(res.stdout)


# the generated file's named (assisted) start: the recording is too short for the scalar receiver's own fix
ASSISTED = ["--startup", "truth-perturbed", "--bits", "assisted"]


def test_imu_shorter_than_the_recording_is_a_warning(work):
    """12. an IMU that ends half-way through the IF file: the span both cover is processed and one
    warning line says where the IMU ends; status 0, inputs untouched."""
    before = snapshot(work)
    res = cli(P + ["v.ci8", "--mode", "ultratight", "--imu", "short.imu.h5", "--json", *ASSISTED], work)
    assert "Traceback" not in res.stderr
    assert res.returncode == 0, res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "IMU data end at" in lines[0] and "only the first" in lines[0], res.stderr
    summ = _strict_json(res.stdout)
    with h5py.File(work / "short.imu.h5", "r") as f:
        t_end = float(f["t"][-1])
    assert summ["duration_s"] <= t_end + 1e-9 and summ["duration_s"] > 0.5 * t_end, (summ["duration_s"], t_end)
    assert summ["warnings"] == [lines[0].split("warning: ", 1)[1]]
    assert snapshot(work) == before


def test_unhealthy_satellite_is_skipped_with_a_warning(work):
    """13. a navigation file that marks one of the sidecar's PRNs unhealthy (SV health 63): that
    satellite is skipped with one warning line naming its health, the others are tracked."""
    import dataclasses

    from ultratight.receiver.io.rinex_out import write_rinex_nav
    from ultratight.signals.constellation import nominal_ephemerides
    side = json.loads((work / "v.ci8.json").read_text())
    ephs = nominal_ephemerides(side["start_week"], side["start_tow_s"])
    sick = int(side["prn"][0])
    write_rinex_nav(work / "sick.rnx", [dataclasses.replace(e, sv_health=63) if p == sick else e
                                        for p, e in ephs.items()])
    before = snapshot(work)
    res = cli(P + ["v.ci8", "--mode", "ultratight", "--imu", "v.imu.h5", "--ephemeris", "sick.rnx", "--json",
                   *ASSISTED], work)
    assert "Traceback" not in res.stderr
    assert res.returncode == 0, res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and f"PRN {sick} (SV health 63)" in lines[0], res.stderr
    summ = _strict_json(res.stdout)
    assert sick not in summ["prns"] and sorted(summ["prns"]) == sorted(int(p) for p in side["prn"][1:])
    assert snapshot(work) == before


def test_rinex_obs_without_observation_epochs_is_a_warning(work):
    """11. --rinex-obs with no observation epoch (1 s of signal): no file, one warning line, status 0
    (the other outputs are complete; docs/process.md)."""
    before = snapshot(work)
    res = cli(P + ["v.ci8", "--prn", "11,14", "--rinex-obs", "o.obs", "--out", "o.h5", "--no-progress"], work)
    assert_clean_failure(res, 0, "warning: --rinex-obs o.obs not written", before, work)
    assert not (work / "o.obs").exists()
    with h5py.File(work / "o.h5", "r") as f:
        assert f.attrs["complete"]


def test_generated_sidecar_is_strict_json(work):
    """11. paper-highdyn's [engine] noise_tau_s = inf: the generator's sidecar is strict JSON (null)."""
    res = cli(["generate", "paper-highdyn", "--duration", "0.1", "--out", "g/hd", "--no-progress"], work)
    assert res.returncode == 0, res.stderr
    side = _strict_json((work / "g" / "hd.ci16.json").read_text())
    assert side["generator"]["engine"]["noise_tau_s"] is None
    assert side["fs_hz"] == 4e6 and side["format"] == "ci16"


def test_campaign_workers_capped_at_runs_and_cores(work):
    """11. --workers far above the runs and the allowed cores: capped, said in one line."""
    res = cli(["campaign", "static-open-sky", "--methods", "scalar", "--duration", "1", "--runs", "1",
               "--workers", "64", "--out", "cw", "--quiet", "--json"], work)
    assert res.returncode == 0, res.stderr
    assert res.stderr.strip().splitlines() == [
        f"campaign: --workers 64 capped at 1 (1 run(s) to compute, {len(os.sched_getaffinity(0))} allowed core(s))"]
    js = _strict_json(res.stdout)
    assert js["timing"]["where"] == "LocalCluster of 1 worker(s) x 1 thread" and js["runs"] == 1


def test_imu_csv_with_bom_is_read(work):
    res = cli(["ins", "bom.csv", "--init-llh", "41", "2", "50", "--json"], work)
    assert res.returncode == 0, res.stderr
    _strict_json(res.stdout)


# ------------------------------------------------------------------------------------------
# scenario: shipped scenario without [imu], corrupt cache entries, --channel, concurrent runs
# ------------------------------------------------------------------------------------------
def test_scenario_without_imu_runs_and_cache_entries_are_verified(tmp_path):
    out = tmp_path / "out"
    args = ["scenario", "static-open-sky", "--duration", "0.5", "--fs-hz", "2.046e6", "--methods", "scalar",
            "--no-plots", "--quiet", "--out", str(out)]
    res = cli(args, tmp_path)
    assert res.returncode == 0, res.stderr
    done = list(out.glob("cache/*/done.json"))
    assert len(done) == 1
    done[0].write_text("{not json")                       # a corrupt entry is regenerated, not reused
    res = cli(args, tmp_path)
    assert res.returncode == 0, res.stderr
    assert json.loads(done[0].read_text())["version"] >= 2
    res = cli(args + ["--channel", "99"], tmp_path)
    assert res.returncode == 2 and "--channel 99" in res.stderr and len(res.stderr.strip().splitlines()) == 1
    assert not leftovers(out)


def test_concurrent_scenario_runs_do_not_collide(tmp_path):
    out = tmp_path / "out"
    args = [sys.executable, "-m", "ultratight.receiver.cli", "scenario", "vehicle-turns", "--duration", "0.3",
            "--fs-hz", "2.046e6", "--methods", "scalar", "--no-plots", "--quiet", "--out", str(out)]
    procs = [subprocess.Popen(args, cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for _ in range(3)]
    for p in procs:
        _, err = p.communicate(timeout=300)
        assert p.returncode == 0, err
        assert "Traceback" not in err
    assert not leftovers(out)
    json.loads((out / "metrics.json").read_text())
    with h5py.File(out / "results.h5", "r") as f:
        assert "run000" in f


# ------------------------------------------------------------------------------------------
# signals: SIGTERM / SIGHUP mid-run
# ------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def long_rec(tmp_path_factory):
    """20 s of vehicle-turns at 2.046 MHz (IF, IMU, truth) for runs that are stopped mid-way."""
    d = tmp_path_factory.mktemp("long")
    res = cli(["generate", "vehicle-turns", "--duration", "20", "--fs", "2.046e6", "--out", "v", "--no-progress"], d)
    assert res.returncode == 0, res.stderr
    return d


def _run_and_signal(argv, cwd, sig, ready, max_wait=120.0):
    """Start the CLI, wait until ``ready(pid)`` (work under way), send ``sig``; returns (rc, stderr)."""
    def default_sighup():
        # a test run started under nohup passes SIGHUP on as ignored, and the CLI then keeps ignoring
        # it (as it should): the child gets a terminal's default disposition
        if hasattr(signal, "SIGHUP"):
            signal.signal(signal.SIGHUP, signal.SIG_DFL)
    p = subprocess.Popen([sys.executable, "-m", "ultratight.receiver.cli", *argv], cwd=cwd,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         preexec_fn=default_sighup if hasattr(os, "fork") else None)
    t0 = time.monotonic()
    while p.poll() is None and not ready(p.pid) and time.monotonic() - t0 < max_wait:
        time.sleep(0.05)
    if p.poll() is None:
        p.send_signal(sig)
    _, err = p.communicate(timeout=120)
    return p.returncode, err


def _tmp_appears(d, pattern):
    return lambda pid: any(Path(d).rglob(pattern))


def _maps_file(name, settle_s=1.0):
    """Ready once the process has memory-mapped ``name`` (the engine is reading the IF), plus settle_s."""
    seen = []

    def ready(pid):
        if not seen:
            try:
                if name in Path(f"/proc/{pid}/maps").read_text():
                    seen.append(time.monotonic())
            except OSError:
                return False
            return False
        return time.monotonic() - seen[0] > settle_s
    return ready


def test_sigterm_during_generate(tmp_path):
    rc, err = _run_and_signal(["generate", "vehicle-turns", "--duration", "30", "--out", "g/ph", "--no-progress"],
                              tmp_path, signal.SIGTERM, _tmp_appears(tmp_path, ".ph.ci8.tmp-*"))
    assert rc == 128 + signal.SIGTERM, err
    assert err.strip().splitlines() == ["ultratight generate: interrupted by SIGTERM; no output written"]
    assert not leftovers(tmp_path)
    assert not (tmp_path / "g").exists()


def test_sigterm_during_scalar_process_leaves_a_marked_partial_output(long_rec, tmp_path):
    for f in ("v.ci8", "v.ci8.json"):
        os.symlink(long_rec / f, tmp_path / f)
    before = snapshot(long_rec)
    rc, err = _run_and_signal(["process", "v.ci8", "--out", "p.h5", "--no-progress"], tmp_path, signal.SIGTERM,
                              _tmp_appears(tmp_path, ".p.h5.tmp-*"))
    assert rc == 128 + signal.SIGTERM, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "interrupted by SIGTERM" in lines[0], err
    if "partial output" in lines[0]:
        with h5py.File(tmp_path / "p.h5", "r") as f:
            assert not f.attrs["complete"]
    else:
        assert "no output written" in lines[0] and not (tmp_path / "p.h5").exists()
    assert not leftovers(tmp_path)
    assert snapshot(long_rec) == before


@pytest.mark.parametrize("where", ["opening the RINEX writer", "before the run loop"])
def test_interruption_while_the_outputs_open_leaves_no_temporary_file(work, monkeypatch, where):
    """An interruption that lands after the HDF5 stream's temporary file exists but before the run
    loop's cleanup takes over (the window a SIGTERM hit once): the temporary files go."""
    from ultratight.receiver.scalar import receiver as rx_mod
    from ultratight.receiver.scalar import recording

    def interrupt(*a, **k):
        raise KeyboardInterrupt
    if where == "opening the RINEX writer":
        monkeypatch.setattr(recording, "RinexObsWriter", interrupt)
    else:
        monkeypatch.setattr(rx_mod, "_progress_bar", interrupt)
    before = snapshot(work)
    with pytest.raises(KeyboardInterrupt):
        rx_mod.process(str(work / "v.ci8"), out_path=work / "p.h5", rinex_obs_path=work / "p.obs", progress=True)
    assert not leftovers(work), leftovers(work)
    assert not (work / "p.h5").exists() and not (work / "p.obs").exists()
    assert snapshot(work) == before


def _companion(long_rec, d, kind):
    """A companion file of the 20 s recording that does not belong to it (docs/reliability.md)."""
    from ultratight.ins.imu_data import read_imu_h5, write_imu_csv
    from ultratight.ins.imu_decl import ImuDeclaration

    for f in ("v.ci8", "v.ci8.json"):
        os.symlink(long_rec / f, d / f)
    if kind == "parked":
        # a parked vehicle's IMU (level, still) beside a recording that drives
        shutil.copyfile(long_rec / "v.imu.h5", d / "x.imu.h5")
        with h5py.File(d / "x.imu.h5", "r+") as f:
            n, dt = f["t"].shape[0], 1.0 / float(f.attrs["rate_hz"])
            f["dtheta_b"][...] = np.zeros((n, 3))
            f["dv_b"][...] = np.tile([0.0, 0.0, 9.80 * dt], (n, 1))
            del f["truth"]
        return ["--imu", "x.imu.h5"]
    # the recording's own IMU written in FLU and declared RFU (x and y swapped): gravity stays on z,
    # the stationary check cannot tell
    imu = read_imu_h5(long_rec / "v.imu.h5")
    imu.truth = None
    side = write_imu_csv(d / "x.csv", imu, ImuDeclaration(axes="FLU"))
    side.write_text(side.read_text().replace('"FLU"', '"RFU"'))
    return ["--imu", "x.csv"]


@pytest.mark.parametrize("kind", ["parked", "axes-swapped"])
def test_a_companion_that_does_not_belong_ends_lost_or_recovers(long_rec, tmp_path, kind):
    """Issue of the hostile probe: an IMU of another vehicle, or the right IMU mis-declared in a way the
    stationary check cannot see, with --mode ultratight defaults. The integrity monitor sees the
    solution leave the measurements: the run ends lost (status 3, the last stderr line says so) or it
    re-initialised from a new scalar fix and the summary says integrity was lost on the way; never a
    silent exit 0 with an "ok" verdict."""
    flags = _companion(long_rec, tmp_path, kind)
    res = cli(P + ["v.ci8", "--mode", "ultratight", *flags, "--json"], tmp_path)
    assert "Traceback" not in res.stderr
    assert res.returncode in (0, 3), res.stderr
    summ = _strict_json(res.stdout)
    lines = res.stderr.strip().splitlines()
    assert summ["integrity"]["worst"] == "lost", summ["integrity"]
    if res.returncode == 3:
        assert summ["integrity"]["state"] == "lost" and "integrity lost at t =" in lines[-1]
        assert all(ln.startswith("ultratight process: warning: ") for ln in lines[:-1]), res.stderr
    else:
        assert summ["integrity"]["n_reinit"] >= 1 and summ["integrity"]["state"] != "lost"
    assert not leftovers(tmp_path)


def test_prns_the_recording_does_not_hold(long_rec, tmp_path):
    """``--prn`` naming satellites that are not in the recording: the start-up's scalar pass finds no
    fix and says so in one line (it used to claim lock on them)."""
    for f in ("v.ci8", "v.ci8.json", "v.imu.h5"):
        os.symlink(long_rec / f, tmp_path / f)
    res = cli(P + ["v.ci8", "--mode", "ultratight", "--imu", "v.imu.h5", "--prn", "1,8"], tmp_path)
    assert_clean_failure(res, 2, "found no fix", snapshot(tmp_path), tmp_path)


@pytest.mark.skipif(not Path("/proc/self/maps").exists(), reason="needs /proc/PID/maps")
def test_sighup_and_sigterm_during_ultratight_process(long_rec, tmp_path):
    for f in ("v.ci8", "v.ci8.json", "v.imu.h5"):
        os.symlink(long_rec / f, tmp_path / f)
    for sig in (signal.SIGTERM, signal.SIGHUP):
        # the engine runs 20 s of this recording in about 2 s: signal it soon after it maps the IF
        rc, err = _run_and_signal(["process", "v.ci8", "--mode", "ultratight", "--imu", "v.imu.h5", "--out", "u.h5"],
                                  tmp_path, sig, _maps_file("v.ci8", settle_s=0.2))
        assert rc == 128 + sig, err
        assert err.strip().splitlines() == [f"ultratight process: interrupted by {sig.name}; no output written"]
        assert not (tmp_path / "u.h5").exists()
        assert not leftovers(tmp_path)


def test_sigterm_during_scenario(tmp_path):
    out = tmp_path / "out"
    # --cache: the run is stopped while the IF file is being written into the data cache
    rc, err = _run_and_signal(["scenario", "vehicle-turns", "--duration", "20", "--methods", "scalar", "--quiet",
                               "--cache", "--out", str(out)], tmp_path, signal.SIGTERM,
                              _tmp_appears(out, ".data.ci8.tmp-*"))
    assert rc == 128 + signal.SIGTERM, err
    assert len(err.strip().splitlines()) == 1 and "interrupted by SIGTERM" in err, err
    assert not leftovers(tmp_path)
    assert not list(out.glob("cache/*/done.json"))


def _worker_running(pid):
    """Ready once the command has a worker process (not the resource tracker) that has used a second of
    CPU (it is running a method); kills it with SIGKILL from here, as the kernel's out-of-memory killer
    would, and returns True."""
    for child in Path(f"/proc/{pid}/task/{pid}/children").read_text().split():
        try:
            cmd = Path(f"/proc/{child}/cmdline").read_bytes()
            ticks = [int(x) for x in Path(f"/proc/{child}/stat").read_text().rsplit(")", 1)[1].split()[11:13]]
        except OSError:
            continue
        if b"resource_tracker" not in cmd and sum(ticks) / os.sysconf("SC_CLK_TCK") > 1.0:
            os.kill(int(child), signal.SIGKILL)
            return True
    return False


@pytest.mark.skipif(not Path("/proc/self/task").exists(), reason="needs /proc/PID/task/PID/children")
def test_a_worker_killed_mid_run_ends_the_scenario_in_one_line(tmp_path):
    """A method's worker process killed from outside (SIGKILL, as by the out-of-memory killer) while the
    scenario runs: one line naming it, status 2, no outputs, no process and no shared memory left."""
    out = tmp_path / "out"
    shm_before = set(os.listdir("/dev/shm")) if Path("/dev/shm").is_dir() else set()
    p = subprocess.Popen([sys.executable, "-m", "ultratight.receiver.cli", "scenario", "paper-highdyn",
                          "--duration", "8", "--fs-hz", "2.046e6", "--methods", "dlb-rackf,dlb-ckf", "--no-plots",
                          "--quiet", "--out", str(out)], cwd=tmp_path, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True)
    t0 = time.monotonic()
    killed = False
    while p.poll() is None and not killed and time.monotonic() - t0 < 300:
        killed = _worker_running(p.pid)
        time.sleep(0.05)
    _, err = p.communicate(timeout=120)
    assert killed, "no worker to kill: " + err
    assert p.returncode == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "a worker process ended abruptly" in lines[0], err
    assert not (out / "metrics.json").exists() and not (out / "results.h5").exists()
    assert not [d for d in out.glob("cache/*") if d.is_dir() and not (d / "done.json").exists()]
    time.sleep(1.0)                     # (forked workers carry the command's arguments, --out included)
    alive = []
    for d in Path("/proc").iterdir():
        try:
            if d.name.isdigit() and str(out).encode() in (d / "cmdline").read_bytes():
                alive.append(d.name)
        except OSError:
            pass
    assert not alive, alive
    if Path("/dev/shm").is_dir():
        assert not [n for n in set(os.listdir("/dev/shm")) - shm_before if n.startswith("ut-if-")]


# ------------------------------------------------------------------------------------------
# disk full (file-size limit) for every writer
# ------------------------------------------------------------------------------------------
def _limit(nbytes):
    import resource

    def pre():
        resource.setrlimit(resource.RLIMIT_FSIZE, (nbytes, nbytes))
    return pre


DISK_FULL = [
    ("generate", ["generate", "vehicle-turns", "--duration", "1", "--out", "g/x", "--no-progress"], 1_000_000),
    ("process-scalar", ["process", "v.ci8", "--prn", "11,14,10,28", "--out", "o.h5", "--no-progress"], 100_000),
    ("process-csv", ["process", "v.ci8", "--prn", "11,14,10,28", "--csv", "o.csv", "--no-progress"], 10),
    ("process-ultratight", ["process", "v.ci8", "--mode", "ultratight", "--imu", "v.imu.h5", "--out", "u.h5",
                            *ASSISTED],
     50_000),
    ("ins-save-imu", ["ins", "vehicle-turns", "--duration", "5", "--save-imu", "i.h5"], 20_000),
    ("scenario", ["scenario", "vehicle-turns", "--duration", "0.5", "--methods", "scalar", "--no-plots", "--quiet",
                  "--out", "s"], 500_000),
    ("bench", ["bench", "--dir", "bench", "--json", "b.json"], 10),
]


@pytest.mark.skipif(not hasattr(os, "fork"), reason="needs POSIX resource limits")
@pytest.mark.parametrize("case", DISK_FULL, ids=[c[0] for c in DISK_FULL])
def test_disk_full(work, case):
    name, argv, limit = case
    before = snapshot(work)
    res = cli(argv, work, preexec_fn=_limit(limit))
    err = res.stderr
    assert "Traceback" not in err, err
    if name == "process-csv" and res.returncode == 0:
        pytest.fail("the CSV writer ignored the file-size limit")
    assert res.returncode == 2, err
    lines = err.strip().splitlines()
    if name == "bench":      # bench reports each benchmark's progress on stderr; one error line
        lines = [ln for ln in lines if "error" in ln]
    assert len(lines) == 1 and "file too large" in lines[0], err
    after = snapshot(work)
    for k, h in before.items():
        assert after.get(k) == h
    assert not leftovers(work), leftovers(work)
    for out in ("o.h5", "o.csv", "u.h5", "i.h5", "b.json", "s/metrics.json", "s/results.h5", "g/x.ci8"):
        assert not (work / out).exists(), out


def test_sigint_during_scenario_plotting_is_not_swallowed(tmp_path):
    out = tmp_path / "out"
    rc, err = _run_and_signal(["scenario", "vehicle-turns", "--duration", "0.5", "--fs-hz", "2.046e6", "--methods",
                               "dlb-rackf,pb-kf-utc", "--quiet", "--out", str(out)], tmp_path, signal.SIGINT,
                              lambda pid: any(out.glob(".fig*.tmp-*")) or any(out.glob("fig*.png")))
    assert rc == 130, err
    lines = err.strip().splitlines()
    # the signal is sent once a figure is being drawn; when it lands after the last one the run has
    # already said what it wrote (one "wrote ..." line) — either way the interruption is reported last
    assert "interrupted by SIGINT" in lines[-1] and "complete outputs kept" in lines[-1], err
    assert all(ln.startswith("wrote ") for ln in lines[:-1]) and len(lines) <= 2, err
    assert not leftovers(tmp_path)


# ------------------------------------------------------------------------------------------
# campaign: a signal while the LocalCluster starts or the runs are going
# ------------------------------------------------------------------------------------------
CAMPAIGN = ["campaign", "static-open-sky", "--methods", "scalar", "--duration", "1", "--quiet"]


def _campaign_dirt(tmp_path):
    """What a campaign's LocalCluster could leave under ``tmp_path`` (the working directory, ``--out`` and
    the system temporary directory the test gives it): Dask scratch space, worker directories, dirlocks."""
    return [str(p) for pat in ("dask-scratch-space", "worker-*", "*.dirlock", "ultratight-campaign-*")
            for p in Path(tmp_path).rglob(pat)]


def _session_gone(pgid, wait_s=30.0):
    """True once no process of the session ``pgid`` is left (the driver's workers included)."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < wait_s:
        try:
            os.killpg(pgid, 0)
        except ProcessLookupError:
            return True
        time.sleep(0.1)
    return False


def test_sigterm_during_a_campaign_keeps_its_run_files_and_leaves_no_scratch(tmp_path, monkeypatch):
    """Issue 27: a campaign stopped by SIGTERM while its runs are going ends in one line (status 143),
    keeps exactly the run files it names, complete, and leaves no Dask scratch space, worker directory,
    dirlock or temporary file behind (it used to leave them under the system temporary directory)."""
    from ultratight.receiver.cli.campaign import read_run

    monkeypatch.setenv("TMPDIR", str(tmp_path / "tmp"))
    (tmp_path / "tmp").mkdir()
    out = tmp_path / "c"
    rc, err = _run_and_signal(CAMPAIGN + ["--runs", "8", "--workers", "1", "--out", str(out)], tmp_path,
                              signal.SIGTERM, lambda pid: any(out.glob("runs/run-*.h5")))
    assert rc == 128 + signal.SIGTERM, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    head = "ultratight campaign: interrupted by SIGTERM; no partial output written; complete outputs kept: "
    assert lines[0].startswith(head), lines[0]
    kept = sorted(lines[0][len(head):].split(", "))
    assert kept == sorted(str(p) for p in out.glob("runs/*")) and 1 <= len(kept) < 8, (kept, err)
    for p in kept:
        got = read_run(p)
        assert got is not None and bool(got[1]["complete"]) and p.endswith(f"run-{int(got[1]['index']):05d}.h5")
    assert not (out / "campaign.json").exists()
    assert not _campaign_dirt(tmp_path), _campaign_dirt(tmp_path)
    assert not list((tmp_path / "tmp").iterdir())
    assert not leftovers(tmp_path), leftovers(tmp_path)


@pytest.mark.skipif(not hasattr(os, "killpg"), reason="needs process groups")
@pytest.mark.parametrize("sig", [signal.SIGINT, getattr(signal, "SIGHUP", signal.SIGINT)], ids=["INT", "HUP"])
def test_signal_to_the_process_group_while_the_campaign_cluster_starts(tmp_path, monkeypatch, sig):
    """Ctrl-C (SIGINT) or a closed terminal (SIGHUP) reaches the whole process group, the cluster's worker
    processes too, here while they start: one line (128 + N) from the driver and no traceback from a
    worker or multiprocessing's resource tracker; no process of the run is left; the ``--out`` directory
    the command created is removed again (no run file kept) and no scratch space is left."""
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    monkeypatch.setenv("TMPDIR", str(tmp))
    out = tmp_path / "c"
    p = subprocess.Popen([sys.executable, "-m", "ultratight.receiver.cli", *CAMPAIGN, "--runs", "2", "--workers",
                          "2", "--out", str(out)], cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         text=True, start_new_session=True)
    t0 = time.monotonic()
    while p.poll() is None and not any(tmp.rglob("worker-*")) and time.monotonic() - t0 < 120:
        time.sleep(0.05)
    assert p.poll() is None, p.communicate()
    os.killpg(p.pid, sig)
    _, err = p.communicate(timeout=120)
    assert p.returncode == 128 + sig, err
    assert err.strip().splitlines() == [f"ultratight campaign: interrupted by {sig.name}; no output written"], err
    assert _session_gone(p.pid), "processes of the campaign left running"
    assert not out.exists()
    assert not _campaign_dirt(tmp_path), _campaign_dirt(tmp_path)
    assert not list(tmp.iterdir())
    assert not leftovers(tmp_path)


def test_campaign_removes_the_temporaries_of_a_stopped_worker_only(tmp_path):
    """A worker stopped mid-write (killed after distributed's grace period) leaves its
    ``.NAME.tmp-PID-RANDOM`` file in the data cache; once the cluster is down the campaign removes the
    temporaries whose writer has ended, and the directories that leaves empty, and nothing else."""
    from ultratight.io_guard import tmp_name
    from ultratight.receiver.cli.campaign import remove_orphaned_temporaries

    cache = tmp_path / "cache"
    (cache / "k1").mkdir(parents=True)                 # an entry whose only file is the dead writer's temporary
    (cache / "k2").mkdir()
    (cache / "k2" / "done.json").write_text("{}")      # a complete entry and a live writer's temporary
    (cache / "k1.lock").write_text("")
    res = subprocess.run([sys.executable, "-c", "import sys; from ultratight.io_guard import tmp_name; "
                          "p = tmp_name(sys.argv[1]); open(p, 'w').write('x'); print(p)",
                          str(cache / "k1" / "data.truth.h5")], capture_output=True, text=True, check=True)
    dead = Path(res.stdout.strip())
    live = tmp_name(cache / "k2" / "data.imu.h5")
    live.write_text("x")
    assert dead.is_file() and f".tmp-{os.getpid()}-" not in dead.name
    remove_orphaned_temporaries(cache)
    assert not dead.exists() and not (cache / "k1").exists()
    assert live.is_file() and (cache / "k2" / "done.json").is_file() and (cache / "k1.lock").is_file()
    remove_orphaned_temporaries(tmp_path / "absent")   # no cache (a scenario without IF data): nothing to do
