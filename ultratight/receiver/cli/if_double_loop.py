"""The experiment of Zhao et al. 2014: IF samples → correlators → prefilters → tight filter (the double loop).

The scenario schema, data cache and metrics are those of :mod:`ultratight.receiver.cli.scenario_runner`
and :mod:`ultratight.receiver.cli.scenario_config` (docs/ultratight.md); this module is the
:mod:`ultratight.receiver.cli.experiments` entry for them. ``ultratight scenario`` calls its driver
``run_scenario`` whole (it manages the on-disk cache of generated data). ``load`` / ``run_one`` /
``summarize`` are the same steps one run at a time, for a campaign (:mod:`ultratight.receiver.cli.campaign`):
``run_one`` generates (or reuses) the run's data with ``prepare_data`` (the cache under the
directory :func:`with_data_dir` names, guarded by its per-key lock; truth and IMU only, the IF
streamed from the generator into each method, unless :func:`with_data_dir` was asked to cache the
IF files), runs each method with ``run_method`` and returns the per-run metrics of
``metrics.summarize`` plus the tracking-error series; ``summarize`` combines them with ``scenario_runner.aggregate`` / ``event_rms`` exactly as
``run_scenario`` does (RMS over all channels and runs, Tables 3 and 4), on channel 0 and with the
default engine options plus the scenario's ``[engine]`` table.
"""

from pathlib import Path
from types import SimpleNamespace

from ultratight.errors import ConfigError
from ultratight.io_guard import json_clean
from ultratight.receiver.cli import metrics as M
from ultratight.receiver.cli import scenario_runner
from ultratight.receiver.deep.methods import METHODS  # noqa: F401  (the accepted method names)
from ultratight.receiver.cli.scenario_config import IMU_DEFAULTS, load_scenario
from ultratight.receiver.cli.scenario_runner import (METHOD_METRICS, aggregate_methods, errors_vs_truth,
                                                     noise_event_text, prepare_data, run_method, run_settings,
                                                     run_settings_text)

DEFAULT_METHODS = ("pb-kf-utc", "dlb-ukf", "dlb-ckf", "dlb-rackf")

# run_one finds the data cache's parent directory under this key of cfg (set by with_data_dir)
USES_DATA_DIR = True
DATA_DIR_KEY = "_data_dir"
CACHE_KEY = "_if_cache"          # True: the runs write their IF files into the cache (else streamed)


def run_scenario(scenario, **kwargs):
    return scenario_runner.run_scenario(scenario, **kwargs)


def load(path, raw, overrides):
    """The resolved scenario (``scenario_config.load_scenario``)."""
    ov = dict(overrides or {})
    if "duration_s" in ov and not float(ov["duration_s"]) > 0:
        raise ConfigError(f"--duration must be > 0 s, got {ov['duration_s']}")
    return load_scenario(path, ov)


def with_data_dir(cfg, out_dir, cache=False):
    """``cfg`` whose runs keep their generated data under ``OUT/cache/<key>/`` (absolute path), the IF
    files too when ``cache`` (else each method reads the IF from the generator in memory)."""
    c = dict(cfg)
    c[DATA_DIR_KEY] = str(Path(out_dir).resolve())
    c[CACHE_KEY] = bool(cache)
    return c


def run_one(cfg, methods, seed, progress=False):
    """One run: data of ``seed`` (generated or reused), every method on it, metrics vs truth."""
    c = dict(cfg)
    data_dir = c.pop(DATA_DIR_KEY, "scenario_out")
    cache = bool(c.pop(CACHE_KEY, False))
    if any(m != "scalar" for m in methods) and "imu" not in c:
        # the ultra-tight methods run on an IMU: the default one, as run_scenario adds it
        c["imu"] = dict(IMU_DEFAULTS)
    paths, _cached = prepare_data(c, int(seed), data_dir, progress=progress, cache_if=cache)
    out = {"seed": int(seed), "methods": {}, "series": {}}
    for m in methods:
        res, truth = run_method(paths, c, m, int(seed))
        d_err, c_err = errors_vs_truth(res, truth)
        summ = M.summarize(res.t_start, d_err, c_err, M.SEGMENTS_S, channel=0)
        summ["runtime_s"] = float(res.runtime_s)
        summ["realtime_factor"] = res.runtime_s / res.duration_s if res.duration_s > 0 else float("nan")
        out["methods"][m] = summ
        out["series"][m] = {"t_start_s": res.t_start, "doppler_err_hz": d_err, "code_err_chips": c_err,
                            "prn": [int(p) for p in res.prns]}
    return out


def summarize(cfg, runs):
    """Tables 3 and 4 over the runs, as ``run_scenario`` prints them (channel 0)."""
    segs = M.SEGMENTS_S
    methods = list(runs[0]["methods"])
    per = {m: [dict(r["methods"][m], seed=r["seed"]) for r in runs] for m in methods}
    raw = {(i, m): (SimpleNamespace(t_start=r["series"][m]["t_start_s"]), r["series"][m]["doppler_err_hz"],
                    r["series"][m]["code_err_chips"]) for i, r in enumerate(runs) for m in methods}
    agg = aggregate_methods(cfg, per, raw, methods, 0)
    dur = float(cfg["duration_s"])
    seeds = [int(r["seed"]) for r in runs]
    settings = run_settings(cfg)
    text = M.format_tables(agg, segs) + "\n" + (
        f"\n{len(runs)} run(s), seeds {', '.join(map(str, seeds))}; RMS over all channels and runs; "
        "'\\' = lock lost (diverged) in that segment.\n") + run_settings_text(settings) + noise_event_text(agg, methods)
    js = {"scenario": cfg.get("name"), "runs": len(runs), "seeds": seeds, "duration_s": dur,
          "segments_s": [list(x) for x in segs], "channel": 0, "startup": settings["startup"], "imu": settings["imu"],
          "methods": {m: {k: agg[m][k] for k in METHOD_METRICS} for m in methods},
          "paper_table3": M.PAPER_TABLE3, "paper_table4_s": M.PAPER_TABLE4_S}
    return {"text": text, "json": json_clean(js)}
