"""Acquisition speed (cold and warm) against a textbook FFT search and, with --real, the detection
table on the real IF files.

    python benchmarks/bench_acquisition.py [--quick] [--json OUT.json] [--repeat 3] [--real] [-v]

Speed: 32 PRNs, +-10 kHz, 1 ms x 10 non-coherent, 4 MHz complex noise.  "Cold" is the first
acquire() call in a fresh process (includes building the code FFTs for this fs and the FFT
plans); the module import time is reported separately.  The reference, timed in the same run,
is a plain parallel code-phase search (scipy.fft, same worker count, same number of Doppler
bins, no decimation / CW excision / refinement / detection statistics): ``warm_over_reference``
is the ratio of the best warm acquire() time to it.  ``--quick`` times one warm call.
The machine is shared by several processes: timings are what this run saw (load average printed).
"""
import argparse
import os
import time

from _common import add_common_args, finish

t_imp0 = time.perf_counter()
import numpy as np  # noqa: E402

from ultratight.receiver.dsp.acquisition import acquire  # noqa: E402
t_import = time.perf_counter() - t_imp0

DATA = os.environ.get("ULTRATIGHT_DATA") or os.path.join(os.path.dirname(__file__), "..", "..", "shared", "data")

FILES = [
    # label, path, loader kind, fs, if, coherent_ms, noncoherent, doppler range, listed PRNs (data README)
    ("pocketsdr 4 MHz IQ (x = I - jQ)", "real-if/pocketsdr/L1_20211202_084700_4MHz_IQ.bin", "iq", 4e6, 0.0, 1, 10,
     10e3, {31, 26, 29, 16, 32}),
    ("pocketsdr 24 MHz real, IF 6 MHz", "real-if/pocketsdr/L1_20211201_054600_24MHz_I.bin", "i8", 24e6, 6e6, 1, 10,
     10e3, {32, 25, 12, 10, 31, 29, 23, 24}),
    ("gnss-sdr CTTC 4 ms (+-10 kHz)", "real-if/gnss-sdr/GSoC_CTTC_capture_2012_07_26_4Msps_4ms.dat", "cf32", 4e6,
     0.0, 1, 4, 10e3, {29, 25, 12, 2}),
    ("gnss-sdr CTTC 4 ms (+-12 kHz)", "real-if/gnss-sdr/GSoC_CTTC_capture_2012_07_26_4Msps_4ms.dat", "cf32", 4e6,
     0.0, 1, 4, 12e3, {29, 25, 12, 2}),
    ("gnss-sdr synthetic PRN 1, 2 ms", "real-if/gnss-sdr/GPS_L1_CA_ID_1_Fs_4Msps_2ms.dat", "cf32", 4e6, 0.0, 2, 1,
     10e3, {1}),
]


def load(path, kind):
    if kind == "iq":
        raw = np.fromfile(path, dtype=np.int8).astype(np.float32)
        return (raw[0::2] - 1j * raw[1::2]).astype(np.complex64), True
    if kind == "i8":
        return np.fromfile(path, dtype=np.int8).astype(np.float32), False
    return np.fromfile(path, dtype=np.complex64), True


def reference_search(x, fs, n_bins, doppler_range_hz=10e3, coherent_ms=1, noncoherent=10):
    """Textbook parallel code-phase search: per Doppler bin, wipe the carrier off all blocks, FFT,
    multiply by the conjugate code spectra of all 32 PRNs, inverse FFT, sum |.|^2 over the blocks."""
    import scipy.fft as sfft

    from ultratight.constants import CA_LEN, F_CA
    from ultratight.signals.ca_code import ca_code

    n = int(round(fs * 1e-3 * coherent_ms))
    blocks = x[:n * noncoherent].reshape(noncoherent, n)
    t = (np.arange(n * noncoherent) / fs).reshape(noncoherent, n)
    idx = (np.arange(n) * F_CA / fs).astype(np.int64) % CA_LEN
    codes = np.stack([ca_code(p)[idx] for p in range(1, 33)]).astype(np.complex64)
    code_f = np.conj(sfft.fft(codes, axis=1, workers=-1))[:, None, :]
    best = np.zeros(32)
    for fd in np.linspace(-doppler_range_hz, doppler_range_hz, n_bins):
        wiped = (blocks * np.exp(-2j * np.pi * fd * t)).astype(np.complex64)
        spec = sfft.fft(wiped, axis=1, workers=-1)[None, :, :]
        corr = sfft.ifft(spec * code_f, axis=2, workers=-1)
        power = np.sum(corr.real ** 2 + corr.imag ** 2, axis=1)
        best = np.maximum(best, power.max(axis=1))
    return best


def speed(args):
    rng = np.random.default_rng(1)
    fs = 4.0e6
    n = int(fs * 0.010)
    x = (rng.standard_normal(n) + 1j * rng.standard_normal(n)).astype(np.complex64)
    t0 = time.perf_counter()
    res = acquire(x, fs, 0.0, True, doppler_range_hz=10e3, coherent_ms=1, noncoherent=10)
    t_cold = time.perf_counter() - t0
    n_bins = res[0].n_doppler_bins
    reference_search(x[: int(fs * 1e-3) * 2], fs, 2, noncoherent=2)     # plan the FFT sizes
    warm, ref = [], []
    for _ in range(args.repeat):                                         # interleaved: same load
        t0 = time.perf_counter()
        acquire(x, fs, 0.0, True, doppler_range_hz=10e3, coherent_ms=1, noncoherent=10)
        warm.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        reference_search(x, fs, n_bins)
        ref.append(time.perf_counter() - t0)
    out = {"import_s": t_import, "cold_s": t_cold, "warm_best_s": min(warm), "warm_median_s": float(np.median(warm)),
           "reference_best_s": min(ref), "warm_over_reference": min(warm) / min(ref),
           "n_doppler_bins": n_bins, "prns": 32, "fs_hz": fs, "coherent_ms": 1, "noncoherent": 10,
           "repeat": args.repeat}
    print(f"import ultratight.receiver.dsp.acquisition: {t_import:.2f} s")
    print(f"32 PRNs, +-10 kHz ({n_bins} Doppler bins), 1 ms x 10 non-coherent, 4 MHz complex:")
    print(f"  cold (first call): {t_cold:.2f} s;  warm: best {min(warm):.2f} s, median {np.median(warm):.2f} s")
    print(f"  reference textbook FFT search (same bins): best {min(ref):.2f} s;  "
          f"warm/reference = {out['warm_over_reference']:.2f}")
    return out


def real(args):
    rows = []
    print(f"\n{'file':34s} {'detected (pfa 1e-3 per PRN)':36s} {'extra vs README':15s} "
          f"{'weakest det. metric/thr':24s} {'strongest rej. metric/thr':24s} time")
    for label, rel, kind, fs, if_hz, coh, nc, rng_hz, listed in FILES:
        path = os.path.join(DATA, rel)
        if not os.path.isfile(path):
            print(f"{label:34s} (missing: {path})")
            rows.append({"file": label, "missing": True})
            continue
        x, cplx = load(path, kind)
        t0 = time.perf_counter()
        res = acquire(x, fs, if_hz, cplx, coherent_ms=coh, noncoherent=nc, doppler_range_hz=rng_hz)
        dt = time.perf_counter() - t0
        det = [r for r in res if r.detected]
        rej = [r for r in res if not r.detected]
        weak = min(det, key=lambda r: r.metric / r.threshold)
        strong = max(rej, key=lambda r: r.metric / r.threshold)
        det_s = ",".join(str(r.prn) for r in sorted(det, key=lambda r: -r.metric))
        extra = sorted({r.prn for r in det} - listed)
        missing = sorted(listed - {r.prn for r in det})
        ex = (f"+{extra}" if extra else "") + (f" -{missing}" if missing else "") or "none"
        print(f"{label:34s} {det_s:36s} {ex:15s} "
              f"PRN {weak.prn:2d} {weak.metric:7.2f}/{weak.threshold:6.2f}   "
              f"PRN {strong.prn:2d} {strong.metric:7.2f}/{strong.threshold:6.2f}   {dt:.2f} s")
        rows.append({"file": label, "detected": sorted(r.prn for r in det), "extra": extra, "missing_prns": missing,
                     "weakest_detected": {"prn": weak.prn, "metric_over_threshold": weak.metric / weak.threshold},
                     "strongest_rejected": {"prn": strong.prn,
                                            "metric_over_threshold": strong.metric / strong.threshold},
                     "time_s": dt})
        if args.verbose:
            for r in sorted(det, key=lambda r: -r.metric):
                print(f"    PRN {r.prn:2d} fd {r.doppler_hz:9.1f} Hz  code {r.code_phase_chips:8.3f} chips  "
                      f"C/N0 {r.cn0_dbhz:5.1f} dB-Hz  metric {r.metric:8.2f}  K_eff {r.k_eff:5.2f}")
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_common_args(ap)
    ap.add_argument("--real", action="store_true", help="also run the real IF files table")
    ap.add_argument("--verbose", "-v", action="store_true")
    ap.add_argument("--repeat", type=int, default=None, help="warm repetitions (default 3; 1 with --quick)")
    args = ap.parse_args()
    if args.repeat is None:
        args.repeat = 1 if args.quick else 3
    out = speed(args)
    if args.real:
        out["real_files"] = real(args)
    finish(args, out)


if __name__ == "__main__":
    main()
