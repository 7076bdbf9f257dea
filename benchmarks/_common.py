"""Shared helpers of the benchmark scripts (``benchmarks/bench_*.py``).

Convention: every script runs as ``python benchmarks/bench_NAME.py [--quick] [--json OUT.json]``,
prints a human-readable summary that names the machine, and with ``--json`` writes one JSON
object with its figures (absolute numbers, the reference measured in the same run, ratios) and a
``machine`` entry.  ``ultratight bench`` runs them all this way and merges the JSON.

Scripts import this module as ``from _common import ...`` (Python puts the script's folder first
on ``sys.path``).
"""

import json
import os
import tempfile
from pathlib import Path


def machine():
    """The machine description of ``ultratight bench`` (CPU model, cores, platform, Python) plus the
    1-minute load average at the time of the call (the machine may be shared)."""
    from ultratight.receiver.cli.commands.bench import machine_info

    info = machine_info()
    try:
        info["load_avg_1m"] = round(os.getloadavg()[0], 2)
    except OSError:
        info["load_avg_1m"] = None
    return info


def machine_line(info=None):
    """One line naming the machine, for the human-readable summaries."""
    m = info or machine()
    load = m.get("load_avg_1m")
    return (f"machine: {m['cpu'] or 'unknown CPU'} x {m['cores']} cores, {m['platform']}, Python {m['python']}"
            + (f", load average {load:.2f}" if load is not None else ""))


def best(fn, repeat, clock=None):
    """Best (minimum) time in s of ``repeat`` calls of ``fn()`` (the machine may be shared); wall
    time by default, ``clock=time.process_time`` for the process's CPU time."""
    import time

    clock = clock or time.perf_counter
    ts = []
    for _ in range(repeat):
        t0 = clock()
        fn()
        ts.append(clock() - t0)
    return min(ts)


# The receiver as it was before it was rebuilt from stages (engine, scalar receiver and scenario
# runner as single functions, one core): the reference of the speed figures of docs/ultratight.md,
# "Performance". ``--baseline none`` leaves it out.
BASELINE = "ac85ff1"


def add_baseline_arg(ap):
    """Add ``--baseline REV`` (default :data:`BASELINE`; ``none``: no baseline run)."""
    ap.add_argument("--baseline", metavar="REV", default=BASELINE,
                    help=f"also time this commit of the repository in the same run (default {BASELINE}; 'none': skip)")
    return ap


def baseline_root(tmp):
    """Where baseline exports live: ``$ULTRATIGHT_BENCH_BASELINES``, else ``~/.cache/ultratight/baselines``
    (kept between runs: an export of a commit never changes, and its numba cache then survives, so a
    baseline compiles once, not at every benchmark run), else ``tmp`` when neither can be created."""
    root = os.environ.get("ULTRATIGHT_BENCH_BASELINES") or str(Path.home() / ".cache" / "ultratight" / "baselines")
    try:
        Path(root).mkdir(parents=True, exist_ok=True)
        return Path(root)
    except OSError:
        return Path(tmp)


def baseline_env(rev, tmp, folders=("ultratight",)):
    """Environment that runs ``python -m ultratight...`` from commit ``rev`` of this repository: the
    commit's ``folders`` are exported (``git archive``) into a folder of :func:`baseline_root` (each
    folder extracted beside it and renamed into place, so an interrupted export is never used) and the
    package put first on ``PYTHONPATH``. Returns ``(env, description)`` — the export's folder is
    ``env["ULTRATIGHT_BASELINE_DIR"]`` — or ``(None, reason)`` when there is no git checkout or no such
    commit."""
    import shutil
    import subprocess
    import tarfile

    root = Path(__file__).resolve().parents[1]
    try:
        full = subprocess.run(["git", "-C", str(root), "rev-parse", "--verify", f"{rev}^{{commit}}"],
                              capture_output=True, text=True, check=True).stdout.strip()
        dest = baseline_root(tmp) / f"baseline-{full[:12]}"
        dest.mkdir(parents=True, exist_ok=True)
        for folder in folders:
            if (dest / folder).is_dir():
                continue
            stage = Path(tempfile.mkdtemp(prefix=f".{folder}-", dir=dest))
            arch = stage / "export.tar"
            subprocess.run(["git", "-C", str(root), "archive", "--format=tar", "-o", str(arch), full, folder],
                           capture_output=True, check=True)
            with tarfile.open(arch) as tf:
                tf.extractall(stage, filter="data")
            os.replace(stage / folder, dest / folder)
            shutil.rmtree(stage, ignore_errors=True)
    except (OSError, subprocess.CalledProcessError) as exc:
        return None, f"baseline {rev} not available ({exc.__class__.__name__})"
    env = dict(os.environ)
    env["PYTHONPATH"] = str(dest) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    env["ULTRATIGHT_BASELINE_DIR"] = str(dest)
    return env, f"commit {full[:12]}"


def add_common_args(ap):
    """Add the convention's ``--quick`` and ``--json OUT.json`` options to an argparse parser."""
    ap.add_argument("--quick", action="store_true", help="short run (smoke-level figures, <~30 s)")
    ap.add_argument("--json", metavar="OUT.json", default=None, help="write the figures as one JSON object")
    return ap


def _default(o):
    import numpy as np

    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.floating):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def write_json(path, obj):
    """Write ``obj`` as JSON to ``path`` (temporary name, then rename)."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    # NaN / inf -> null (strict JSON), numpy scalars and arrays -> Python
    plain = json.loads(json.dumps(obj, default=_default), parse_constant=lambda _c: None)
    text = json.dumps(plain, indent=1)
    tmp.write_text(text)
    os.replace(tmp, path)


def finish(args, results, info=None):
    """Add ``machine`` (and ``quick``) to ``results``, print the machine line and write ``--json``."""
    results = dict(results)
    results.setdefault("machine", info or machine())
    results.setdefault("quick", bool(getattr(args, "quick", False)))
    print(machine_line(results["machine"]))
    if getattr(args, "json", None):
        write_json(args.json, results)
        print(f"figures written to {args.json}")
    return results
