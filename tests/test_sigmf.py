"""SigMF input (through the sigmf package) and ``generate --sigmf``."""

import json
import subprocess
import sys

import numpy as np
import pytest

from ultratight.constants import F_L1
from ultratight.errors import FormatError
from ultratight.receiver.dsp.acquisition import acquire
from ultratight.signals.recording.iffile import open_if

pytest.importorskip("sigmf", reason="sigmf package not installed")

# real recordings (shared/data/README.md): file, SigMF datatype, fs, core:frequency, iq_conj, search
REAL = {
    "pocketsdr-iq": ("pocketsdr/L1_20211202_084700_4MHz_IQ.bin", "ci8", 4.0e6, F_L1, True, (1, 10, 10e3)),
    "pocketsdr-real24": ("pocketsdr/L1_20211201_054600_24MHz_I.bin", "ri8", 24.0e6, 1569.42e6, False, (1, 10, 10e3)),
    "cttc": ("gnss-sdr/GSoC_CTTC_capture_2012_07_26_4Msps_4ms.dat", "cf32_le", 4.0e6, F_L1, False, (1, 4, 10e3)),
    "synthetic": ("gnss-sdr/GPS_L1_CA_ID_1_Fs_4Msps_2ms.dat", "cf32_le", 4.0e6, F_L1, False, (2, 1, 10e3)),
}
SIDE_FMT = {"ci8": "ci8", "ri8": "i8", "cf32_le": "cf32"}


def _sigmf_meta(path, data, datatype, fs, freq, iq_conj, ncd=True):
    g = {"core:datatype": datatype, "core:sample_rate": fs, "core:version": "1.2.0"}
    if ncd:
        g["core:dataset"] = str(data)
    if iq_conj:
        g["core:extensions"] = [{"name": "ultratight", "version": "0.1.0", "optional": True}]
        g["ultratight:iq_conj"] = True
    path.write_text(json.dumps({"global": g, "captures": [{"core:sample_start": 0, "core:frequency": freq}],
                                "annotations": []}))
    return path


@pytest.mark.parametrize("case", list(REAL))
def test_real_recordings_as_sigmf_acquire_like_the_sidecar(shared_data, tmp_path, case):
    rel, dt, fs, freq, conj, (coh, nc, rng) = REAL[case]
    data = shared_data / "real-if" / rel
    if not data.is_file():
        pytest.skip(f"real IF file not found: {data}")
    side = tmp_path / "side.json"
    side.write_text(json.dumps({"format": SIDE_FMT[dt], "fs_hz": fs, "if_hz": F_L1 - freq, "iq_conj": conj}))
    meta = _sigmf_meta(tmp_path / "rec.sigmf-meta", data, dt, fs, freq, conj)
    a = open_if(data, meta=side)
    b = open_if(meta)
    assert (b.fmt, b.fs_hz, b.if_hz, b.n_samples, b._conj) == (a.fmt, a.fs_hz, a.if_hz, a.n_samples, a._conj)
    ra = acquire(a, coherent_ms=coh, noncoherent=nc, doppler_range_hz=rng, pfa=1e-3)
    rb = acquire(b, coherent_ms=coh, noncoherent=nc, doppler_range_hz=rng, pfa=1e-3)
    det = [(r.prn, r.doppler_hz, r.code_phase_chips, r.metric) for r in ra if r.detected]
    assert det and det == [(r.prn, r.doppler_hz, r.code_phase_chips, r.metric) for r in rb if r.detected]


def test_compliant_dataset_name_and_errors(tmp_path):
    x = (np.arange(8000) % 7 - 3).astype(np.int8)
    (tmp_path / "r.sigmf-data").write_bytes(x.tobytes())
    _sigmf_meta(tmp_path / "r.sigmf-meta", None, "ri8", 2.0e6, F_L1 - 4.0e5, False, ncd=False)
    s = open_if(tmp_path / "r.sigmf-data")          # either file of the pair opens the recording
    assert s.fmt == "i8" and s.if_hz == pytest.approx(4.0e5) and s.n_samples == 8000
    assert np.array_equal(s.read(0, 8000), x.astype(np.float32))
    # a high-side LO on real samples: mirrored spectrum, read with the (-1)^n shift
    _sigmf_meta(tmp_path / "r.sigmf-meta", None, "ri8", 2.0e6, F_L1 + 4.0e5, False, ncd=False)
    s = open_if(tmp_path / "r.sigmf-meta")
    assert s.if_hz == pytest.approx(1.0e6 - 4.0e5)
    _sigmf_meta(tmp_path / "r.sigmf-meta", None, "cu8", 2.0e6, F_L1, False, ncd=False)
    with pytest.raises(FormatError, match="core:datatype"):
        open_if(tmp_path / "r.sigmf-meta")
    (tmp_path / "r.sigmf-meta").write_text(json.dumps({"global": {"core:datatype": "ri8", "core:sample_rate": 2e6,
                                                                  "core:version": "1.2.0"},
                                                       "captures": [{"core:sample_start": 0}], "annotations": []}))
    with pytest.raises(FormatError, match="core:frequency"):
        open_if(tmp_path / "r.sigmf-meta")


@pytest.mark.parametrize("fmt", ["ci16", "i8"])
def test_generate_sigmf_reads_back_like_the_sidecar(tmp_path, fmt):
    extra = ["--if", "1.0e6"] if fmt == "i8" else []
    r = subprocess.run([sys.executable, "-m", "ultratight.receiver.cli", "generate", "static-open-sky", "--duration",
                        "0.05", "--fs", "4e6", "--format", fmt, "--sigmf", "--out", str(tmp_path / "g"),
                        "--no-progress", "--json"] + extra, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    files = json.loads(r.stdout)["files"]
    from sigmf import sigmffile
    rec = sigmffile.fromfile(files["sigmf"])
    rec.validate()                                          # the sigmf package's schema check
    a, b = open_if(files["if"]), open_if(files["sigmf"])
    assert (a.fmt, a.fs_hz, a.if_hz, a.n_samples, a.start_week, a.start_tow_s) == \
        (b.fmt, b.fs_hz, b.if_hz, b.n_samples, b.start_week, b.start_tow_s)
    assert np.array_equal(a.read(0, 5000), b.read(0, 5000))


def test_generate_sigmf_refuses_packed_formats(tmp_path):
    r = subprocess.run([sys.executable, "-m", "ultratight.receiver.cli", "generate", "static-open-sky", "--duration",
                        "0.01", "--format", "i2packed", "--if", "1e6", "--sigmf", "--out", str(tmp_path / "g"),
                        "--no-progress"], capture_output=True, text=True, timeout=600)
    assert r.returncode != 0 and "SigMF has no datatype" in r.stderr and not list(tmp_path.glob("g*"))
