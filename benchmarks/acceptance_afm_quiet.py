"""The sigma-point filters of docs/paper_afm.md against the EKF on quiet 300 s runs (no fault).

    python benchmarks/acceptance_afm_quiet.py [--quick] [--seeds 1,2,3] [--json OUT.json]

For each data set — the swinging base with the default IMU errors (1 mg accelerometer bias the
13-state model lacks), the static base with them, the swinging base without the accelerometer bias
— and each seed, the four filters (EKF, UKF, AFF, AFM) run on identical data
(``paper_afm.simulate``, ``filter_setup``, ``run_filter``) and the script prints, per filter, the
largest |attitude difference to the EKF| / the filter's own σ after 5 s (the figure of
docs/paper_afm.md "Acceptance figures"), and for AFF and AFM the number of GPS epochs with a fade
factor > 1 (the chi-square test's false alarms: 1 % per component on 6 components, ≈ 17 of 300
expected).  ``--quick``: 60 s, seed 1, the swinging base only.
"""

import argparse
import sys

import numpy as np

from _common import add_common_args, finish

DATA = {
    "swing": {"trajectory": {"kind": "swing", "att0_deg": [0.0, 0.0, 30.0]}},
    "static": {"trajectory": {"kind": "static", "att0_deg": [0.0, 0.0, 30.0]}},
    "swing-no-accel-bias": {"trajectory": {"kind": "swing", "att0_deg": [0.0, 0.0, 30.0]},
                            "imu": {"accel_bias_ug": 0.0}},
}


def one(name, seed, duration):
    from ultratight.fusion.experiments import paper_afm

    raw = {"experiment": "paper-afm", "paper_experiment": "4.2", "duration_s": duration, "name": name,
           "fault": {"kind": "none"}, **DATA[name]}
    cfg = paper_afm.load(name, raw, {})
    sim = paper_afm.simulate(cfg, seed)
    nom0, P0, Q, R = paper_afm.filter_setup(cfg, sim)
    runs = {m: paper_afm.run_filter(m, cfg, sim, nom0, P0, Q, R) for m in ("ekf", "ukf", "aff", "afm")}
    late = runs["ekf"]["t"] >= 5.0
    out = {}
    for m in ("ukf", "aff", "afm"):
        d = np.abs(runs[m]["att_err"] - runs["ekf"]["att_err"])[late] / runs[m]["att_sigma"][late]
        out[m] = {"max_diff_over_sigma": float(d.max())}
        if m in ("aff", "afm"):
            out[m]["faded_epochs"] = int(np.sum(runs[m]["fade_max"] > 1.0))
            out[m]["gps_epochs"] = int(runs[m]["fade_max"].size)
    return out


def main(argv=None):
    ap = add_common_args(argparse.ArgumentParser(description=__doc__.splitlines()[0]))
    ap.add_argument("--seeds", default="1,2,3")
    a = ap.parse_args(argv)
    seeds = [1] if a.quick else [int(s) for s in a.seeds.split(",")]
    duration = 60.0 if a.quick else 300.0
    names = ["swing"] if a.quick else list(DATA)
    res = {}
    for name in names:
        for seed in seeds:
            r = res.setdefault(name, {})[seed] = one(name, seed, duration)
            print(f"{name:20s} seed {seed}: max |att - EKF| / sigma after 5 s: "
                  + ", ".join(f"{m.upper()} {v['max_diff_over_sigma']:.3f}" for m, v in r.items())
                  + f"; fades > 1: AFF {r['aff']['faded_epochs']} / AFM {r['afm']['faded_epochs']} "
                  f"of {r['aff']['gps_epochs']} GPS epochs", flush=True)
    for name, per_seed in res.items():
        for m in ("ukf", "aff", "afm"):
            v = [r[m]["max_diff_over_sigma"] for r in per_seed.values()]
            print(f"{name:20s} {m.upper():4s} max |att - EKF| / sigma over seeds {seeds}: {min(v):.3f}..{max(v):.3f}")
    finish(a, {"duration_s": duration, "seeds": seeds, "runs": res})
    return 0


if __name__ == "__main__":
    sys.exit(main())
