"""Loose/tight SINS/GNSS integration speed (the experiments of Fang 2017 and Cai et al. 2020).

    python benchmarks/bench_integration.py [--quick] [--repeat R] [--json OUT.json]

* observable simulator: satellite-epochs per wall second and per CPU second (the machine is
  shared) of ``simulate_observables`` (nominal constellation,
  32 PRNs, the paper-robust-flight trajectory at 1 Hz, noise and gross errors included);
* per method, the wall time of one 500-s paper-robust-flight run (100 Hz SINS, 1 Hz GNSS, loose
  15-state: kf, chi2-newton, chi2-newton-lit, ins-only) and of one 500-s paper-static-iakf run
  (tight 17-state with the best-4 GDOP selection: akf0, akf, iakf).  Best of --repeat; the run
  data are simulated once (not timed); the first call compiles nothing new (numba cache).
"""

import argparse
import time

import numpy as np

from _common import add_common_args, best, finish


def best_cpu(fn, repeat):
    """Best process CPU time in s of ``repeat`` calls (the wall time of a shared machine includes
    the other processes' share)."""
    return best(fn, repeat, clock=time.process_time)


def main():
    ap = add_common_args(argparse.ArgumentParser(description=__doc__.splitlines()[0]))
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    repeat = 1 if args.quick else max(1, args.repeat)
    from ultratight.receiver.cli import experiments as E
    from ultratight.fusion.experiments import paper_robust_flight as RF
    from ultratight.fusion.experiments import paper_static_iakf as SI
    from ultratight.signals.constellation import nominal_ephemerides
    from ultratight.signals.synth.obssim import GrossErrors, simulate_observables

    res = {}
    path, raw, _ = E.resolve("paper-robust-flight")
    cfg = RF.load(path, raw, {})
    inp, data = RF.simulate(cfg, 1)
    # simulator throughput
    ephs = nominal_ephemerides(2190, 518400.0)
    from ultratight.ins.trajectory import build_trajectory
    tr = cfg["trajectory"]
    traj = build_trajectory({"kind": "segments", "attitude": "velocity", "vel0_enu_mps": tr["vel0_enu_mps"],
                             "segments": tr["segments"]}, cfg["receiver"], 500.0)
    n_ep = 2000 if args.quick else 20000
    t = np.arange(n_ep) * (500.0 / n_ep)
    k = traj.kinematics(t)
    clk = np.linspace(0.0, 50.0, n_ep)
    gross = GrossErrors(20.0, 10.0)

    def sim():
        simulate_observables(ephs, 2190, 518400.0, t, k["pos_e"], k["vel_e"], clk, 0.1, np.random.default_rng(0),
                             3.0, 0.1, 5.0, gross)

    sim()
    ts = best(sim, repeat)
    cpu = best_cpu(sim, repeat)
    res["simulator_sat_epochs_per_s"] = n_ep * len(ephs) / ts
    res["simulator_sat_epochs_per_cpu_s"] = n_ep * len(ephs) / cpu
    print(f"observable simulator: {n_ep} epochs x {len(ephs)} satellites in {ts:.3f} s wall, {cpu:.3f} s CPU = "
          f"{res['simulator_sat_epochs_per_s'] / 1e6:.2f} M satellite-epochs/s wall, "
          f"{res['simulator_sat_epochs_per_cpu_s'] / 1e6:.2f} M per CPU second")
    # loose flight, per method
    fx = RF.fixes(cfg, data, float(cfg["gross"]["factor"]))
    RF.run_method(cfg, "kf", inp, fx)           # warm-up (numba cache load, imports)
    res["flight_500s_s"] = {}
    for m in RF.METHODS:
        tm = best(lambda: RF.run_method(cfg, m, inp, fx), repeat)
        res["flight_500s_s"][m] = tm
        print(f"paper-robust-flight 500 s, {m:16s}: {tm:.3f} s")
    # tight static, 500 s
    path, raw, _ = E.resolve("paper-static-iakf")
    scfg = SI.load(path, raw, {"duration_s": 500.0})
    sinp, obs = SI.simulate(scfg, 1)
    res["static_tight_500s_s"] = {}
    for m in ("akf0", "akf", "iakf"):
        tm = best(lambda: SI.run_method(scfg, m, sinp, obs), repeat)
        res["static_tight_500s_s"][m] = tm
        print(f"paper-static-iakf 500 s, {m:16s}: {tm:.3f} s")
    finish(args, res)


if __name__ == "__main__":
    main()
