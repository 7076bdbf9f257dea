"""Benchmark the batched I/Q prefilters (CKF, UKF, RACKF) and the PB-KF-UTC baseline.

    python benchmarks/bench_prefilter.py [--quick] [--json OUT.json] [--n-ch 12]

Figures (per filter kind, 12 channels, 20 dB-Hz measurements from the correlator-level
simulator with the NCO on the truth; the code/phase estimates are zeroed after each epoch as a
cheap stand-in for the feedback, so the filters stay in their working regime):
* ``kernel_us_per_epoch``: the numba kernel alone (one call = one epoch, all channels),
  median over repetitions of ``--epochs`` calls;
* ``step_us_per_epoch``: ``PrefilterBank.step`` (input checks + kernel);
* ``us_per_channel_epoch`` = kernel / n_ch;
* ``rackf_over_ukf``: RACKF/UKF kernel-time ratio (paper Table 4: about 0.5);
* ``innerloop_us_per_epoch``: the NCO feedback law for all channels;
* ``compile_s``: first-call time (numba compile or cache load).
Times are CPU time of the benchmarking thread (``time.thread_time``), so that other
processes sharing the cores do not inflate them; ``kernel_us_per_epoch_wall`` is the wall
clock figure for comparison.
"""

import argparse
import time

import numpy as np

from _common import add_common_args, finish

from ultratight.fusion.channel import prefilter as pf
from ultratight.fusion.channel.innerloop import InnerLoop
from ultratight.fusion.channel.pbkf import PbKfBank
from ultratight.fusion.channel.prefilter import PrefilterBank
from ultratight.fusion.channel.prefilter_kernels import bank_step
from ultratight.fusion.channel.prefilter_model import IPRM_DO_CORRECTION
from ultratight.signals.synth.corrsim import CorrSim, SimNco, SimScenario

# CPU time of this thread: robust to other processes competing for the 2 cores (wall time
# is reported separately as *_wall).
_clock = time.thread_time
_wall = time.perf_counter


def _measurements(n_ch, n_ep, seed=1):
    """z at 20 dB-Hz from the correlator-level simulator, NCO on the (static) truth."""
    sc = SimScenario(duration_s=n_ep * 1e-3, n_ch=n_ch, cn0_dbhz=20.0, segments=[(0.0, 0.0, 0.0)])
    sim = CorrSim(sc, np.random.default_rng(seed))
    sim.init_nco()
    out = np.empty((n_ep, n_ch, 6))
    for k in range(n_ep):
        out[k] = sim.outputs()
        if k + 1 < n_ep:
            sim.advance()
    return out, sim.truth.bits


def bench_kind(kind, Z, bits, reps):
    n_ep, n_ch, _ = Z.shape
    bank = pf.PrefilterBank(n_ch, kind=kind, cn0_dbhz_init=20.0)
    bank.reset(np.arange(n_ch))
    t0 = _clock()
    bank.step(Z[0], bits[0])
    compile_s = _clock() - t0
    kern = []
    step = []
    wall = []
    for _ in range(reps):
        bank.reset(np.arange(n_ch))
        bank.epoch = 0
        t0 = _clock()
        for k in range(n_ep):
            bank.step(Z[k], bits[k])
            bank.x[:, 1:3] = 0.0          # cheap stand-in for the feedback (keeps errors small)
        step.append((_clock() - t0) / n_ep)
        # kernel alone
        bank.reset(np.arange(n_ch))
        bank.epoch = 0
        kc, fbuf, ibuf = bank.packed
        iprm = bank._iprm
        rscale = np.ones(n_ch)          # no filter-R noise event
        t0 = _clock()
        w0 = _wall()
        for k in range(n_ep):
            iprm[IPRM_DO_CORRECTION] = 1 if k % bank.correction_period == 0 else 0
            bank_step(kc, fbuf, ibuf, Z[k], bits[k], rscale)
            bank.x[:, 1:3] = 0.0
        kern.append((_clock() - t0) / n_ep)
        wall.append(_wall() - w0)
    return {"kernel_us_per_epoch": 1e6 * float(np.median(kern)),
            "step_us_per_epoch": 1e6 * float(np.median(step)),
            "us_per_channel_epoch": 1e6 * float(np.median(kern)) / n_ch,
            "kernel_us_per_epoch_wall": 1e6 * float(np.median(wall)) / n_ep,
            "compile_s": compile_s, "resets": int(bank.n_resets.sum())}


def bench_pbkf(Z, bits, reps):
    n_ep, n_ch, _ = Z.shape
    bank = PbKfBank(n_ch, cn0_dbhz_init=20.0)
    bank.reset(np.arange(n_ch))
    t0 = _clock()
    bank.step(Z[0], bits[0])
    compile_s = _clock() - t0
    step = []
    for _ in range(reps):
        bank.reset(np.arange(n_ch))
        t0 = _clock()
        for k in range(n_ep):
            bank.step(Z[k], bits[k])
        step.append((_clock() - t0) / n_ep)
    return {"step_us_per_epoch": 1e6 * float(np.median(step)), "compile_s": compile_s}


def bench_innerloop(n_ch, reps, n_ep=2000):
    bank = PrefilterBank(n_ch)
    bank.reset(np.arange(n_ch))
    nco = SimNco(n_ch)
    law = InnerLoop(n_ch)
    aid = np.zeros(n_ch)
    law.apply(bank, nco, aid)
    ts = []
    for _ in range(reps):
        t0 = _clock()
        for _k in range(n_ep):
            law.apply(bank, nco, aid)
        ts.append((_clock() - t0) / n_ep)
    return 1e6 * float(np.median(ts))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_common_args(ap)
    ap.add_argument("--n-ch", type=int, default=12)
    ap.add_argument("--epochs", type=int, default=None)
    args = ap.parse_args()
    n_ep = args.epochs or (1000 if args.quick else 5000)
    reps = 3 if args.quick else 5
    Z, bits = _measurements(args.n_ch, n_ep)
    res = {"n_ch": args.n_ch, "epochs": n_ep}
    for kind in ("ckf", "ukf", "rackf"):
        res[kind] = bench_kind(kind, Z, bits, reps)
    res["rackf_over_ukf"] = res["rackf"]["kernel_us_per_epoch"] / res["ukf"]["kernel_us_per_epoch"]
    res["rackf_over_ckf"] = res["rackf"]["kernel_us_per_epoch"] / res["ckf"]["kernel_us_per_epoch"]
    try:
        res["pbkf"] = bench_pbkf(Z, bits, reps)
    except ImportError:
        pass
    res["innerloop_us_per_epoch"] = bench_innerloop(args.n_ch, reps)
    for kind in ("ckf", "ukf", "rackf"):
        r = res[kind]
        print(f"{kind:6s} kernel {r['kernel_us_per_epoch']:7.2f} us/epoch ({r['us_per_channel_epoch']:.2f} us per "
              f"channel-epoch), step() {r['step_us_per_epoch']:7.2f} us, first call {r['compile_s']:.2f} s")
    if "pbkf" in res:
        print(f"pbkf   step() {res['pbkf']['step_us_per_epoch']:7.2f} us/epoch")
    print(f"RACKF/UKF = {res['rackf_over_ukf']:.2f}, RACKF/CKF = {res['rackf_over_ckf']:.2f}; "
          f"inner loop {res['innerloop_us_per_epoch']:.2f} us/epoch ({args.n_ch} channels)")
    finish(args, res)

if __name__ == "__main__":
    main()
