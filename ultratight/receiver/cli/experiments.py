"""Paper experiments behind ``ultratight scenario`` (and any campaign runner).

A scenario TOML names the experiment that runs it with a top-level key
``experiment = "NAME"``; without it the scenario is Zhao et al. 2014's IF-level
double-loop experiment (``if-double-loop``: IF generator → correlators →
prefilters → tight filter, ``receiver.cli.scenario_runner``).

Each experiment is a module named in :data:`EXPERIMENTS`: the IF-level double loop lives with
its runner (``ultratight.receiver.cli.if_double_loop``), the integration-filter experiments beside
the filters they exercise (``ultratight.fusion.experiments.<NAME with - as _>``). Each exposes

* ``DEFAULT_METHODS`` / ``METHODS``: tuples of method names (the ones run by
  default / all it accepts);
* ``load(path, raw, overrides) -> cfg``: complete and validate the scenario
  (its own schema; unknown tables or keys are :class:`ConfigError` — use
  :func:`ultratight.config.check_known_keys`);
* ``run_one(cfg, methods, seed, progress=False) -> dict``: one Monte-Carlo run,
  ``{"seed": s, "methods": {name: {metric: value, ..., "runtime_s": t}}, ...}``
  (plain numbers and numpy arrays only, so a distributed runner can ship it);
* ``summarize(cfg, runs) -> {"text": str, "json": dict}``: the tables beside
  the paper's, over a list of ``run_one`` results;
* ``write_outputs(cfg, runs, summary, out_dir, plots) -> {"metrics_path",
  "h5_path", "figures"}``: ``metrics.json``, ``results.h5`` (atomic writes) and
  figures when matplotlib is installed.

:func:`run_experiment` is the driver ``ultratight scenario`` uses: seeds ``seed, seed+1, ...``,
one ``run_one`` each, sequentially — or, when the module has the optional hook
``run_many(cfg, methods, seeds, progress) -> [run_one results in seed order]``, through it (e.g. in
worker processes on all cores). ``run_many`` must return exactly what the sequential loop would:
each run's randomness depends only on its seed. The IF-level experiment keeps
its own driver (``scenario_runner.run_scenario``: it manages an on-disk data
cache), reached through the same :func:`run_experiment`; for campaigns it also has ``load`` /
``run_one`` / ``summarize``. :mod:`ultratight.receiver.cli.campaign` (``ultratight campaign``) runs
``run_one`` of any experiment on dask.distributed with seeds from ``SeedSequence(seed).spawn(N)``.
"""

import importlib
import time
from pathlib import Path

from ultratight.errors import ConfigError
from ultratight.config import locate_scenario, read_toml

DEFAULT_EXPERIMENT = "if-double-loop"


EXPERIMENTS = {
    "if-double-loop": "ultratight.receiver.cli.if_double_loop",
    "paper-afm": "ultratight.fusion.experiments.paper_afm",
    "paper-fads": "ultratight.fusion.experiments.paper_fads",
    "paper-robust-flight": "ultratight.fusion.experiments.paper_robust_flight",
    "paper-static-iakf": "ultratight.fusion.experiments.paper_static_iakf",
}


def module_name(name):
    """The module of experiment ``name`` (``-`` or ``_`` spelling); None when unknown."""
    return EXPERIMENTS.get(str(name).replace("_", "-"))


def list_experiments():
    """Names of the experiments shipped in this package (``-`` spelling)."""
    return sorted(EXPERIMENTS)


def get(name):
    """The experiment module for ``name``; ConfigError naming the known ones when absent."""
    if not isinstance(name, str) or not name or not all(c.isalnum() or c in "-_" for c in name):
        raise ConfigError(f"experiment must be a name, got {name!r}")
    module = module_name(name)
    if module is None:
        raise ConfigError(f"unknown experiment {name!r}; known: {', '.join(list_experiments())}")
    return importlib.import_module(module)


def resolve(scenario):
    """(path, raw TOML dict, experiment module) of a scenario name or TOML path."""
    path = locate_scenario(scenario)
    raw = read_toml(path)
    return path, raw, get(raw.get("experiment", DEFAULT_EXPERIMENT))


def check_methods(module, methods):
    """Methods of a run: the experiment's defaults when ``methods`` is empty/None; unknown names refused."""
    methods = list(methods or module.DEFAULT_METHODS)
    unknown = [m for m in methods if m not in module.METHODS]
    if unknown:
        raise ConfigError(f"unknown method(s) {', '.join(unknown)} for this scenario; "
                          f"expected some of {', '.join(module.METHODS)}")
    if len(set(methods)) != len(methods):
        raise ConfigError(f"--methods lists a method twice: {','.join(methods)}")
    return methods


def run_experiment(module, path, raw, *, methods=None, runs=1, seed=None, out_dir="scenario_out",
                   overrides=None, plots=True, progress=True):
    """Run ``runs`` seeds of an experiment sequentially; returns the summary with output paths."""
    methods = check_methods(module, methods)
    if isinstance(runs, bool) or int(runs) != runs or int(runs) < 1:
        raise ConfigError(f"--runs must be an integer >= 1, got {runs}")
    if Path(out_dir).exists() and not Path(out_dir).is_dir():
        raise ConfigError(f"--out {out_dir}: exists and is not a directory")
    cfg = module.load(path, raw, overrides or {})
    base_seed = int(cfg.get("seed", 0) if seed is None else seed)
    if base_seed < 0:
        raise ConfigError(f"--seed must be >= 0, got {base_seed}")
    if Path(out_dir).exists() and not Path(out_dir).is_dir():
        raise ConfigError(f"--out {out_dir}: exists and is not a directory")
    results = []
    seeds = [base_seed + r for r in range(int(runs))]
    if hasattr(module, "run_many") and int(runs) > 1:
        results = module.run_many(cfg, methods, seeds, progress=progress)
    for r in range(0 if results else int(runs)):
        t0 = time.perf_counter()
        res = module.run_one(cfg, methods, base_seed + r, progress=progress)
        results.append(res)
        if progress:
            print(f"run {r + 1}/{runs} seed {base_seed + r}: {time.perf_counter() - t0:.1f} s", flush=True)
    summary = module.summarize(cfg, results)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    summary.update(module.write_outputs(cfg, results, summary, out, plots))
    return summary
