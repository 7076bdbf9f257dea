"""Real recorded IF files (../shared/data/real-if, see its README) read through open_if:
a plain FFT acquisition written here finds a listed PRN far above the noise floor, while
absent PRNs stay at the noise level."""

import numpy as np
import pytest

from ultratight.constants import CA_LEN, F_CA
from ultratight.signals.ca_code import ca_code
from ultratight.signals.recording.iffile import open_if

FILES = [
    # path, open_if flags, present PRN, absent PRNs, ms to integrate
    ("pocketsdr/L1_20211202_084700_4MHz_IQ.bin", dict(fmt="ci8", fs_hz=4e6, iq_conj=True), 31, (1, 3), 5),
    ("pocketsdr/L1_20211201_054600_24MHz_I.bin", dict(fmt="i8", fs_hz=24e6, if_hz=6e6), 32, (1, 3), 4),
    ("gnss-sdr/GSoC_CTTC_capture_2012_07_26_4Msps_4ms.dat", dict(fmt="cf32", fs_hz=4e6), 29, (1, 3), 4),
    ("gnss-sdr/GPS_L1_CA_ID_1_Fs_4Msps_2ms.dat", dict(fmt="cf32", fs_hz=4e6), 1, (3, 5), 2),
]


def fft_acquire(x, fs, if_hz, prn, n_ms, dmax=12e3, step=500.0):
    """Parallel code-phase search: non-coherent sum of n_ms 1 ms FFT correlations per Doppler bin.
    Returns (peak / mean of the whole grid, Doppler of the peak, sample offset of the peak)."""
    L = int(round(fs * 1e-3))
    n = np.arange(L)
    code = ca_code(prn).astype(float)[np.floor(n * F_CA / fs).astype(int) % CA_LEN]
    cf = np.conj(np.fft.fft(code))
    dops = np.arange(-dmax, dmax + 1, step)
    t = np.arange(n_ms * L) / fs
    grid = np.empty((len(dops), L))
    for i, f in enumerate(dops):
        y = (x[:n_ms * L] * np.exp(-2j * np.pi * (if_hz + f) * t)).reshape(n_ms, L)
        grid[i] = np.sum(np.abs(np.fft.ifft(np.fft.fft(y, axis=1) * cf, axis=1)) ** 2, axis=0)
    k = np.unravel_index(np.argmax(grid), grid.shape)
    return grid.max() / grid.mean(), dops[k[0]], k[1]


@pytest.mark.parametrize("name,flags,prn,absent,n_ms", FILES, ids=[f[0].split("/")[1][:20] for f in FILES])
def test_acquisition_peak(shared_data, name, flags, prn, absent, n_ms):
    path = shared_data / "real-if" / name
    if not path.is_file():
        pytest.skip(f"{path} not present")
    with open_if(path, **flags) as src:
        assert src.n_samples == path.stat().st_size // {"ci8": 2, "i8": 1, "cf32": 8}[flags["fmt"]]
        x = src.read(0, int(n_ms * 1e-3 * src.fs_hz)).astype(np.complex128)
        ratio, dop, off = fft_acquire(x, src.fs_hz, src.if_hz, prn, n_ms)
        noise = [fft_acquire(x, src.fs_hz, src.if_hz, p, n_ms)[0] for p in absent]
    assert ratio > 10.0, ratio
    assert ratio > 2.5 * max(noise), (ratio, noise)
    if name.startswith("gnss-sdr/GPS_L1_CA_ID_1"):
        # synthetic file: |Doppler| 1680 Hz, code delay 524 samples (its authors' notes)
        assert abs(abs(dop) - 1680.0) <= 250.0
        assert abs(off - 524) <= 2


def test_blocks_equal_whole_read(shared_data):
    path = shared_data / "real-if" / "pocketsdr" / "L1_20211202_084700_4MHz_IQ.bin"
    if not path.is_file():
        pytest.skip(f"{path} not present")
    with open_if(path, fmt="ci8", fs_hz=4e6, iq_conj=True) as src:
        assert src.duration_s == pytest.approx(0.5)
        whole = src.read(1000, 50000)
        parts = np.concatenate([b for _, b in src.blocks(4096, start=1000, stop=51000)])
        np.testing.assert_array_equal(whole, parts)
        raw = np.fromfile(path, dtype=np.int8, count=2 * 51000)[2000:].astype(np.float32)
        np.testing.assert_array_equal(whole.real, raw[0::2])
        np.testing.assert_array_equal(whole.imag, -raw[1::2])     # x = I - jQ
        assert set(np.unique(raw)) <= {-3.0, -1.0, 1.0, 3.0}
