"""Acquisition speed (cold and warm) and, with --real, the detection table on the real IF files.

    python benchmarks/bench_acquisition.py                 # 32 PRNs, +-10 kHz, 1 ms x 10, 4 MHz complex
    python benchmarks/bench_acquisition.py --real          # + per-file detections / weakest / strongest rejected

"Cold" is the first acquire() call in a fresh process (includes building the code FFTs for this fs and
scipy.fft planning); the module import time is reported separately.  The machine is shared by
several processes: timings are what this run saw (load average printed).
"""

import argparse
import os
import time

t_imp0 = time.perf_counter()
import numpy as np  # noqa: E402

from ultratight.receiver.acquisition import acquire  # noqa: E402
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


def speed(args):
    rng = np.random.default_rng(1)
    fs = 4.0e6
    n = int(fs * 0.010)
    x = (rng.standard_normal(n) + 1j * rng.standard_normal(n)).astype(np.complex64)
    t0 = time.perf_counter()
    res = acquire(x, fs, 0.0, True, doppler_range_hz=10e3, coherent_ms=1, noncoherent=10)
    t_cold = time.perf_counter() - t0
    warm = []
    for _ in range(args.repeat):
        t0 = time.perf_counter()
        acquire(x, fs, 0.0, True, doppler_range_hz=10e3, coherent_ms=1, noncoherent=10)
        warm.append(time.perf_counter() - t0)
    print(f"load average: {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores")
    print(f"import ultratight.receiver.acquisition: {t_import:.2f} s")
    print(f"32 PRNs, +-10 kHz ({res[0].n_doppler_bins} Doppler bins), 1 ms x 10 non-coherent, 4 MHz complex:")
    print(f"  cold (first call): {t_cold:.2f} s;  warm: best {min(warm):.2f} s, median {np.median(warm):.2f} s")


def real(args):
    print(f"\n{'file':34s} {'detected (pfa 1e-3 per PRN)':36s} {'extra vs README':15s} "
          f"{'weakest det. metric/thr':24s} {'strongest rej. metric/thr':24s} time")
    for label, rel, kind, fs, if_hz, coh, nc, rng_hz, listed in FILES:
        path = os.path.join(DATA, rel)
        if not os.path.isfile(path):
            print(f"{label:34s} (missing: {path})")
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
        if args.verbose:
            for r in sorted(det, key=lambda r: -r.metric):
                print(f"    PRN {r.prn:2d} fd {r.doppler_hz:9.1f} Hz  code {r.code_phase_chips:8.3f} chips  "
                      f"C/N0 {r.cn0_dbhz:5.1f} dB-Hz  metric {r.metric:8.2f}  K_eff {r.k_eff:5.2f}")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--real", action="store_true", help="also run the real IF files table")
    ap.add_argument("--verbose", "-v", action="store_true")
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    speed(args)
    if args.real:
        real(args)


if __name__ == "__main__":
    main()
