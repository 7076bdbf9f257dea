"""The filters of Sun et al. 2012 on the quaternion SINS/GPS model: cost per 100 Hz step and per 300 s run.

    python benchmarks/bench_afm.py [--quick] [--json OUT.json]

The acceptance of the paper-afm scenarios asks for <= 10 s per filter for a 300 s run at 100 Hz
(30 000 time updates of 2L+1 = 55 sigma points, L = n + q + m = 12 + 9 + 6, and 300 GPS updates).
Measured here on the ``paper-afm-noise`` data (swinging base, noise jump at 30 s), one seed, each
filter (UKF, AFF-AUKF, AFM-AUKF, and the EKF for reference) timed over the whole run, plus the
per-call cost of one ``QuatAUKF.predict`` from Python.  ``--quick``: a 60 s run.  The machine may be
shared: the 1-minute load average is recorded with the figures.
"""

import argparse
import time


from _common import add_common_args, finish


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_common_args(ap)
    args = ap.parse_args()
    from ultratight.receiver.cli import experiments
    from ultratight.fusion.experiments import paper_afm
    duration = 60.0 if args.quick else 300.0
    path, raw, _ = experiments.resolve("paper-afm-noise")
    cfg = paper_afm.load(path, raw, {"duration_s": duration})
    t0 = time.perf_counter()
    sim = paper_afm.simulate(cfg, 1)
    sim_s = time.perf_counter() - t0
    nom0, P0, Q, R = paper_afm.filter_setup(cfg, sim)
    # warm-up (numba compile / cache load) on a short slice, not timed
    short = dict(sim, dtheta=sim["dtheta"][:200], dv=sim["dv"][:200])
    for m in ("ukf", "afm", "ekf"):
        paper_afm.run_filter(m, cfg, short, nom0, P0, Q, R)
    res = {"duration_s": duration, "imu_rate_hz": cfg["imu"]["rate_hz"], "simulation_s": sim_s}
    for m in ("ukf", "aff", "afm", "ekf"):
        r = paper_afm.run_filter(m, cfg, sim, nom0, P0, Q, R)
        res[f"{m}_run_s"] = r["runtime_s"]
    f = paper_afm.QuatAUKF(sim["model"], nom0, P0, Q, R)
    n = 3000
    t0 = time.perf_counter()
    for k in range(n):
        f.predict(sim["dtheta"][k], sim["dv"][k])
    res["aukf_predict_us"] = (time.perf_counter() - t0) / n * 1e6
    res["sigma_points"] = int(f.scheme.xi.shape[0])
    for k, v in res.items():
        print(f"{k:28s} {v:12.4g}")
    finish(args, res)


if __name__ == "__main__":
    main()
