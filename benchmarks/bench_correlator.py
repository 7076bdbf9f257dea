"""Correlator-bank throughput against a minimal numba early/prompt/late kernel (same run, same data).

    python benchmarks/bench_correlator.py [--quick] [--json OUT.json] [--seconds 1.0] [--channels 1 8] [--repeat 5]

Reports M samples/s per channel (channel-samples per second) for the bank (complex and real input)
and for the minimal kernel, and their ratio.  The minimal kernel is the reference of
the design goal of a plain numba kernel of this kind (~300 M samples/s per core):
one channel, complex input, E/P/L in one loop into a 4096-entry cos/sin table, no normalisation or
NCO bookkeeping, in two flavours (float64 phases with floor, and integer phase accumulators); the
ratio is taken to the faster of the two.  Timings are best-of-``--repeat`` (the machine is shared).
``--quick``: 0.25 s of samples, best of 2.
"""

import argparse
import time

import numpy as np
from numba import njit

from ultratight.constants import CA_LEN
from ultratight.receiver.dsp.correlator import CorrelatorBank
from ultratight.signals.ca_code import ca_code

from _common import add_common_args, finish

LUT = 4096


@njit(cache=True)
def minimal_epl(x, n, code_ext, cp0, dcp, ph0, dph, cos_t, sin_t, half, out):
    """x: float32 interleaved I,Q; code_ext: code padded by 2 chips on both sides."""
    ip = np.float32(0.0); ie = np.float32(0.0); il = np.float32(0.0)
    qp = np.float32(0.0); qe = np.float32(0.0); ql = np.float32(0.0)
    for k in range(n):
        p = cp0 + k * dcp + 2.0
        ph = ph0 + k * dph
        li = int((ph - np.floor(ph)) * LUT) & (LUT - 1)
        c = cos_t[li]
        s = sin_t[li]
        xr = x[2 * k]
        xi = x[2 * k + 1]
        bi = xr * c + xi * s
        bq = xi * c - xr * s
        cp = code_ext[int(p)]
        ce = code_ext[int(p + half)]
        cl = code_ext[int(p - half)]
        ip += bi * cp; ie += bi * ce; il += bi * cl
        qp += bq * cp; qe += bq * ce; ql += bq * cl
    out[0] = ip; out[1] = ie; out[2] = il; out[3] = qp; out[4] = qe; out[5] = ql


@njit(cache=True)
def minimal_epl_int(x, n, code_ext, cp0, dcp, ph0, dph, cos_t, sin_t, half, out):
    """Same with integer accumulators: code phase in 32.32 fixed point, carrier phase 32-bit."""
    ip = np.float32(0.0); ie = np.float32(0.0); il = np.float32(0.0)
    qp = np.float32(0.0); qe = np.float32(0.0); ql = np.float32(0.0)
    cp = cp0
    ph = ph0
    for k in range(n):
        li = (ph >> 20) & (LUT - 1)
        c = cos_t[li]
        s = sin_t[li]
        xr = x[2 * k]
        xi = x[2 * k + 1]
        bi = xr * c + xi * s
        bq = xi * c - xr * s
        c_p = code_ext[cp >> 32]
        c_e = code_ext[(cp + half) >> 32]
        c_l = code_ext[(cp - half) >> 32]
        ip += bi * c_p; ie += bi * c_e; il += bi * c_l
        qp += bq * c_p; qe += bq * c_e; ql += bq * c_l
        cp += dcp
        ph += dph
    out[0] = ip; out[1] = ie; out[2] = il; out[3] = qp; out[4] = qe; out[5] = ql


@njit(cache=True)
def minimal_epochs_float(x, n_ep, n, code_ext, dcp, dph, cos_t, sin_t, out):
    """All epochs in one call (no Python dispatch per epoch), as the bank's run_epochs."""
    for e in range(n_ep):
        minimal_epl(x[2 * e * n:], n, code_ext, 0.0, dcp, 0.1, dph, cos_t, sin_t, 0.5, out)


@njit(cache=True)
def minimal_epochs_int(x, n_ep, n, code_ext, cp0, dcp, ph0, dph, cos_t, sin_t, half, out):
    for e in range(n_ep):
        minimal_epl_int(x[2 * e * n:], n, code_ext, cp0, dcp, ph0, dph, cos_t, sin_t, half, out)


def minimal_runner(x, fs):
    """Closures timing the two minimal kernels over all whole periods of x (one channel)."""
    xf = x.view(np.float32)
    code = ca_code(1).astype(np.float32)
    code_ext = code[(np.arange(CA_LEN + 4) - 2) % CA_LEN]
    ang = 2 * np.pi * (np.arange(LUT) + 0.5) / LUT
    cos_t, sin_t = np.cos(ang).astype(np.float32), np.sin(ang).astype(np.float32)
    out = np.zeros(6, np.float32)
    n_per = int(fs * 1e-3)
    n_ep = x.shape[0] // n_per
    dcp = 1.023e6 / fs * 0.999999
    one = float(1 << 32)
    iargs = (code_ext, np.int64(2 * one), np.int64(dcp * one), np.int64(0), np.int64(1234.0 / fs * one),
             cos_t, sin_t, np.int64(0.5 * one), out)

    def run_float():
        minimal_epochs_float(xf, n_ep, n_per, code_ext, dcp, 1234.0 / fs, cos_t, sin_t, out)
        return n_ep * n_per

    def run_int():
        minimal_epochs_int(xf, n_ep, n_per, *iargs)
        return n_ep * n_per

    return run_float, run_int


def bank_runners(x, fs, is_complex, n_ch):
    """Closures timing the bank with run_epochs (one numba call) and with a step() loop."""
    if_hz = 0.0 if is_complex else 1.0e6
    bank = CorrelatorBank(list(range(1, n_ch + 1)), fs, if_hz, is_complex)

    def init():
        for ch in range(n_ch):
            bank.init_channel(ch, ch + 1, 37.0 * ch, 500.0 * ch - 2000.0, 0)

    def run_epochs():
        init()
        _, _, ns, _ = bank.run_epochs(x, 0, 1.0)
        return int(ns.sum())

    def run_step():
        init()
        n = 0
        while True:
            _, _, ns = bank.step(x, 0, 1.0)
            if not np.any(ns > 0):
                return n
            n += int(ns.sum())

    return run_epochs, run_step


def best_rates(runners, repeat):
    """Best-of-repeat rate (M samples/s) of each closure, interleaved so they share the same load."""
    for r in runners.values():
        r()                                   # compile / warm up
    best = {k: np.inf for k in runners}
    count = {}
    for _ in range(repeat):
        for k, r in runners.items():
            t0 = time.perf_counter()
            count[k] = r()
            best[k] = min(best[k], time.perf_counter() - t0)
    return {k: count[k] / best[k] / 1e6 for k in runners}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_common_args(ap)
    ap.add_argument("--seconds", type=float, default=None, help="seconds of samples (default 1; 0.25 with --quick)")
    ap.add_argument("--fs", type=float, default=4.0e6)
    ap.add_argument("--channels", type=int, nargs="+", default=[1, 8])
    ap.add_argument("--repeat", type=int, default=None, help="best of N (default 5; 2 with --quick)")
    a = ap.parse_args()
    seconds = a.seconds or (0.25 if a.quick else 1.0)
    repeat = a.repeat or (2 if a.quick else 5)
    rng = np.random.default_rng(0)
    n = int(a.fs * seconds)
    xc = (rng.standard_normal(n) + 1j * rng.standard_normal(n)).astype(np.complex64)
    xr = rng.standard_normal(n).astype(np.float32)
    print(f"numba single thread; fs = {a.fs / 1e6:.3f} MHz, {seconds} s of samples, best of {repeat}")
    runners = {}
    runners["min_float"], runners["min_int"] = minimal_runner(xc, a.fs)
    for n_ch in a.channels:
        for cplx, x in ((True, xc), (False, xr)):
            key = f"{n_ch:2d} ch {'complex' if cplx else 'real   '}"
            runners[key + " run_epochs"], runners[key + " step loop "] = bank_runners(x, a.fs, cplx, n_ch)
    rates = best_rates(runners, repeat)
    ref = max(rates["min_float"], rates["min_int"])
    print(f"minimal numba E/P/L kernel (complex), float phases -> LUT:   {rates['min_float']:8.1f} M samples/s")
    print(f"minimal numba E/P/L kernel (complex), integer accumulators: {rates['min_int']:8.1f} M samples/s")
    print("(ratios are to the faster minimal kernel; bank rates are channel-samples/s per core)")
    bank = {}
    for k, v in rates.items():
        if k.startswith("min_"):
            continue
        print(f"CorrelatorBank {k}: {v:8.1f} M samples/s   ratio {v / ref:5.2f}")
        bank[" ".join(k.split())] = {"msamples_per_s": v, "ratio_to_minimal": v / ref}
    finish(a, {"fs_hz": a.fs, "seconds": seconds, "repeat": repeat, "channels": a.channels,
               "minimal_float_msamples_per_s": rates["min_float"], "minimal_int_msamples_per_s": rates["min_int"],
               "reference_msamples_per_s": ref, "bank": bank})


if __name__ == "__main__":
    main()
