"""One documented ``ultratight scenario`` run (a paper's Monte Carlo table), as an acceptance run of
``ultratight bench``.

    python benchmarks/acceptance_scenario.py SCENARIO [scenario options ...] [--set KEY=VALUE ...]
        [--from-s S] [--json OUT.json]

Without ``--set``: runs ``python -m ultratight.receiver.cli scenario SCENARIO [options] --out TMP
--no-plots`` in a subprocess and prints what it prints (the paper's tables with our figures, per
seed and pooled: docs/paper_afm.md, docs/integration-experiments.md, docs/airdata.md name the
commands).  With ``--set KEY=VALUE`` (a dotted key of the scenario TOML, e.g.
``filter.iakf_start="full-window"``; the value in TOML syntax; repeatable): the same run with the
keys changed, as the documents' "a copy of the TOML with KEY changed" variants (in this process,
through ``experiments.run_experiment``; only ``--runs``, ``--seed``, ``--methods``,
``--duration`` are understood then).  ``--from-s S`` (observable-level runs): also the velocity
error RMS of every method over t ≥ S, mean over the seeds, from the run's ``results.h5``.  With ``--json`` the run's ``metrics.json``
(``NAME_metrics.json``) is copied there.  The exit status is the command's.
"""

import argparse
import shutil
import subprocess
import sys
import tempfile
import tomllib
from pathlib import Path


def parse_set(items):
    """``["a.b=1", 'c="x"']`` -> ``{"a.b": 1, "c": "x"}`` (values in TOML syntax)."""
    out = {}
    for it in items:
        key, sep, val = it.partition("=")
        if not sep or not key.strip():
            raise ValueError(f"--set {it!r}: expected KEY=VALUE")
        try:
            out[key.strip()] = tomllib.loads(f"v = {val.strip()}")["v"]
        except tomllib.TOMLDecodeError as exc:
            raise ValueError(f"--set {it!r}: the value is not TOML ({exc})") from None
    return out


def run_with_overrides(scenario, rest, overrides, out_dir):
    """The scenario with ``overrides`` in this process; prints its tables; returns 0."""
    from ultratight.receiver.cli import experiments

    ap = argparse.ArgumentParser(prog="acceptance_scenario")
    ap.add_argument("--runs", type=int, default=1)
    ap.add_argument("--seed", type=int, default=None)
    ap.add_argument("--methods", default=None)
    ap.add_argument("--duration", type=float, default=None)
    a = ap.parse_args(rest)
    if a.duration is not None:
        overrides = dict(overrides, duration_s=a.duration)
    path, raw, module = experiments.resolve(scenario)
    summary = experiments.run_experiment(module, path, raw, methods=a.methods.split(",") if a.methods else None,
                                         runs=a.runs, seed=a.seed, out_dir=out_dir, overrides=overrides,
                                         plots=False, progress=True)
    print(summary["text"], flush=True)
    return 0


def rms_from(h5_path, t_from):
    """Velocity error RMS (E, N, U) of every method over ``t >= t_from``, mean over the seeds, from
    the per-epoch errors of an observable-level run's ``results.h5`` (``seedNNNNNN/METHOD/err``, the
    error-state order of ``ins.error_model``): ``{method: [E, N, U]}``."""
    import h5py
    import numpy as np

    from ultratight.ins import error_model as em

    per = {}
    with h5py.File(h5_path, "r") as f:
        for seed in f:
            for m in f[seed]:
                g = f[seed][m]
                if "err" not in g or "t" not in g:
                    continue
                sel = g["t"][()] >= t_from
                per.setdefault(m, []).append(np.sqrt(np.mean(g["err"][()][sel][:, em.VEL] ** 2, axis=0)))
    return {m: [float(x) for x in np.mean(v, axis=0)] for m, v in per.items()}


def main(argv=None):
    argv = list(sys.argv[1:] if argv is None else argv)
    ap = argparse.ArgumentParser(add_help=False)
    ap.add_argument("--json", default=None)
    ap.add_argument("--set", action="append", default=[])
    ap.add_argument("--from-s", type=float, default=None)
    known, rest = ap.parse_known_args(argv)
    if not rest or rest[0].startswith("-"):
        print("acceptance_scenario: name a scenario, e.g. paper-afm-jump --runs 10 --seed 1", file=sys.stderr)
        return 2
    try:
        overrides = parse_set(known.set)
    except ValueError as exc:
        print(f"acceptance_scenario: {exc}", file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory() as tmp:
        print("command: ultratight scenario " + " ".join(rest)
              + "".join(f" [{k} = {v!r}]" for k, v in overrides.items()), flush=True)
        if overrides:
            rc = run_with_overrides(rest[0], rest[1:], overrides, tmp)
        else:
            cmd = [sys.executable, "-m", "ultratight.receiver.cli", "scenario", *rest, "--out", tmp, "--no-plots"]
            rc = subprocess.run(cmd).returncode
        if rc == 0 and known.from_s is not None:
            for h5 in sorted(Path(tmp).glob("*results.h5")):
                for m, v in rms_from(h5, known.from_s).items():
                    print(f"from {known.from_s:g} s, mean over seeds: {m:15s} velocity RMS E/N/U "
                          + " / ".join(f"{x:.4f}" for x in v) + " m/s")
        metrics = sorted(Path(tmp).glob("*metrics.json"))       # metrics.json or NAME_metrics.json
        if rc == 0 and known.json is not None:
            if not metrics:
                print("acceptance_scenario: the run wrote no metrics.json", file=sys.stderr)
                return 1
            shutil.copyfile(metrics[0], known.json)
    return rc


if __name__ == "__main__":
    sys.exit(main())
