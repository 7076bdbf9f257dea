"""``ultratight bench``: run every benchmark script and write one JSON report.

The benchmark scripts live in ``benchmarks/bench_*.py`` of the source tree
(they need the checkout; ``ultratight bench`` finds them next to the installed
package in an editable install, or via ``--dir``).  Each script is run in its
own Python process (so peak-memory figures are per benchmark) as

    python benchmarks/bench_NAME.py [--quick] --json OUT.json

and must write its figures as a JSON object to OUT.json.  The report gathers
them with the machine description and the total wall time.
"""

HELP = "run all benchmarks (correlator, generator, acquisition, prefilters, SINS, end-to-end) and write a JSON report"


def add_arguments(p):
    p.add_argument("--quick", action="store_true", help="shorter runs (smoke-level figures)")
    p.add_argument("--json", metavar="PATH", default="bench.json", help="report path (default: bench.json)")
    p.add_argument("--only", metavar="LIST", default=None,
                   help="comma-separated benchmark names (e.g. correlator,prefilter)")
    p.add_argument("--dir", metavar="DIR", default=None, help="benchmarks folder (default: the checkout's benchmarks/)")


def _bench_dir(arg):
    from pathlib import Path

    from ultratight.errors import InputFileError

    if arg is not None:
        d = Path(arg)
    else:
        import ultratight

        d = Path(ultratight.__file__).resolve().parents[1] / "benchmarks"
    if not d.is_dir():
        raise InputFileError(f"benchmarks folder not found at {d}; run from a source checkout or pass --dir")
    return d


def machine_info():
    """Platform, CPU model and core count, for naming the machine in reports."""
    import os
    import platform

    cpu = platform.processor() or ""
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "platform": platform.platform(),
        "python": platform.python_version(),
    }


def run(args):
    import json
    import os
    import subprocess
    import sys
    import tempfile
    import time

    from ultratight import __version__
    from ultratight.errors import ConfigError

    from ultratight import io_guard
    io_guard.check_io([], [("--json", args.json)])
    d = _bench_dir(args.dir)
    scripts = sorted(d.glob("bench_*.py"))
    names = [s.stem[len("bench_"):] for s in scripts]
    if args.only:
        wanted = [w.strip() for w in args.only.split(",") if w.strip()]
        unknown = sorted(set(wanted) - set(names))
        if unknown:
            raise ConfigError(f"unknown benchmark(s) {', '.join(unknown)}; known: {', '.join(names)}")
        scripts = [s for s, n in zip(scripts, names) if n in wanted]
    report = {"version": __version__, "machine": machine_info(), "quick": bool(args.quick), "benchmarks": {}}
    t_all = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        for script in scripts:
            name = script.stem[len("bench_"):]
            out = os.path.join(tmp, f"{name}.json")
            cmd = [sys.executable, str(script), "--json", out] + (["--quick"] if args.quick else [])
            print(f"[bench] {name} ...", file=sys.stderr, flush=True)
            t0 = time.perf_counter()
            proc = subprocess.run(cmd, capture_output=True, text=True)
            entry = {"wall_s": round(time.perf_counter() - t0, 3), "returncode": proc.returncode}
            if proc.returncode == 0 and os.path.exists(out):
                try:
                    with open(out) as fh:
                        entry["results"] = json.load(fh)
                except (OSError, ValueError) as exc:
                    entry["error"] = f"unreadable report ({exc})"
            else:
                entry["error"] = (proc.stderr.strip().splitlines() or ["(no output)"])[-1]
            report["benchmarks"][name] = entry
            status = "ok" if "results" in entry else f"FAILED: {entry['error']}"
            print(f"[bench] {name}: {status} ({entry['wall_s']:.1f} s)", file=sys.stderr, flush=True)
    report["total_wall_s"] = round(time.perf_counter() - t_all, 3)
    io_guard.write_text_atomic(args.json, io_guard.json_dumps(report, indent=2))
    print(io_guard.json_dumps({k: v for k, v in report.items() if k != "benchmarks"}))
    print(f"report written to {args.json}")
    failed = [n for n, e in report["benchmarks"].items() if "results" not in e]
    return 1 if failed else 0
