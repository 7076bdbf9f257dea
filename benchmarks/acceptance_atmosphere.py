"""Atmosphere-correction acceptance on generated IF (static-open-sky-atmosphere, 60 s).

    python benchmarks/acceptance_atmosphere.py [--quick] [--seed 1] [--json OUT.json]

Runs (each one generated file, processed with every receiver setting shown):

* ``same``: the generator's delays are the receiver's models (Klobuchar with the broadcast
  coefficients, Saastamoinen with the 1/cos z mapping) — processed with ``--iono klobuchar
  --tropo saastamoinen`` and with both off (the error the corrections remove);
* ``other``: the generator uses models the receiver does not share — the Klobuchar delay scaled
  by ``iono_scale`` = 1.2 and the Black & Eisner tropospheric mapping — processed with the
  corrections on: the residual of the receiver's models against a different atmosphere.

Figures per run: fixes, first fix (s), satellites used (median, max), 3D RMS, mean and RMS of the
east/north/up errors against the truth position (m), and the wall time.
"""

import argparse
import sys
import tempfile
import time

import numpy as np

from _common import add_common_args, finish


def errors_enu(fixes, truth_pos):
    from ultratight.ins.earth import dcm_ecef_from_enu, ecef_to_llh

    P = np.array([f["pos_e"] for f in fixes])
    d = P - truth_pos[None, :]
    llh = ecef_to_llh(np.asarray(truth_pos, dtype=float))
    enu = d @ dcm_ecef_from_enu(llh[0], llh[1])          # (C_el^T d)^T: east, north, up
    return {"fixes": len(fixes), "first_fix_s": round(float(fixes[0]["t_s"]), 2) if fixes else None,
            "n_used_median": float(np.median([f["n_used"] for f in fixes])) if fixes else None,
            "n_used_max": int(max(f["n_used"] for f in fixes)) if fixes else None,
            "rms_3d_m": float(np.sqrt(np.mean(np.sum(d ** 2, axis=1)))),
            "mean_enu_m": [float(v) for v in enu.mean(axis=0)],
            "rms_enu_m": [float(v) for v in np.sqrt(np.mean(enu ** 2, axis=0))]}


def run_case(tmp, name, overrides, settings, seed):
    import h5py

    from ultratight.receiver.scalar.receiver import ProcessConfig, process
    from ultratight.receiver.cli.scenario_config import load_scenario
    from ultratight.signals.synth.generator import generate

    cfg = load_scenario("static-open-sky-atmosphere", {**overrides, "seed": seed})
    t0 = time.perf_counter()
    paths = generate(cfg, tmp, name, progress=False)
    gen_s = time.perf_counter() - t0
    with h5py.File(paths["truth"], "r") as f:
        truth_pos = f["pos_e"][0]
        n_sat = len(f.attrs["prn"])
        iono = f["iono_m"][0]
        tropo = f["tropo_m"][0]
    out = {"generate_s": round(gen_s, 1), "satellites": n_sat,
           "truth_iono_m_range": [float(iono.min()), float(iono.max())],
           "truth_tropo_m_range": [float(tropo.min()), float(tropo.max())]}
    for iono_opt, tropo_opt in settings:
        t0 = time.perf_counter()
        res = process(paths["if"], ProcessConfig(iono=iono_opt, tropo=tropo_opt))
        key = f"iono={iono_opt},tropo={tropo_opt}"
        first = min((c["acquired_s"] for c in res.channels if c.get("acquired_s") is not None), default=None)
        out[key] = {**errors_enu(res.fixes, truth_pos), "wall_s": round(time.perf_counter() - t0, 1),
                    "corrections": res.corrections, "tracked": len(res.summary()["tracked"]),
                    # all in view (docs/process.md): channels acquired at the cold start, periodic searches
                    "acquired_at_start": sum(1 for c in res.channels if c.get("acquired_s") == first),
                    "used_max": max((len(f["used_prn"]) for f in res.fixes), default=0),
                    "searches": res.searches}
    return out


def main(argv=None):
    ap = add_common_args(argparse.ArgumentParser(description=__doc__.splitlines()[0]))
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args(argv)
    results = {"seed": args.seed}
    with tempfile.TemporaryDirectory() as tmp:
        dur = {"duration_s": 45.0} if args.quick else {}
        results["same"] = run_case(tmp, "same", dur, [("klobuchar", "saastamoinen"), ("off", "off")], args.seed)
        results["other"] = run_case(tmp, "other", {**dur, "atmosphere.iono_scale": 1.2,
                                                   "atmosphere.tropo_mapping": "black-eisner"},
                                    [("klobuchar", "saastamoinen")], args.seed)
    for case in ("same", "other"):
        for k, v in results[case].items():
            if isinstance(v, dict):
                e = v["mean_enu_m"]
                print(f"{case:5s} {k:32s} fixes {v['fixes']:4d} first {v['first_fix_s']} s  used {v['n_used_median']:.0f}"
                      f"  3D RMS {v['rms_3d_m']:.3f} m  mean E/N/U {e[0]:+.3f} {e[1]:+.3f} {e[2]:+.3f} m"
                      f"  acquired at the cold start {v['acquired_at_start']}, searches {v['searches']}")
    finish(args, results)
    return 0


if __name__ == "__main__":
    sys.exit(main())
