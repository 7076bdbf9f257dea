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
from pathlib import Path


def machine():
    """The machine description of ``ultratight bench`` (CPU model, cores, platform, Python) plus the
    1-minute load average at the time of the call (the machine may be shared)."""
    from ultratight.receiver.commands.bench import machine_info

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
