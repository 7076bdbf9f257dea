"""``ultratight bench``: run every benchmark script and write one JSON report.

The benchmark scripts live in ``benchmarks/bench_*.py`` of the source tree
(they need the checkout; ``ultratight bench`` finds them next to the installed
package in an editable install, or via ``--dir``).  Each script is run in its
own Python process (so peak-memory figures are per benchmark) as

    python benchmarks/bench_NAME.py [--quick] --json OUT.json

and must write its figures as a JSON object to OUT.json.  The report gathers
them, each script's printed lines, the machine description and the total wall
time.

``--acceptance`` adds the acceptance runs of :data:`ACCEPTANCE`: the scripts
``benchmarks/acceptance_*.py`` and ``benchmarks/study_highdyn.py`` with the
arguments that reproduce the documented acceptance figures, and
``benchmarks/acceptance_reproductions.py``, which runs the test suite's slow
reproductions (``pytest -m slow``) and reports each node's outcome and printed
figures.  They take minutes to hours (the study: hours); ``--only NAME`` runs
one of them without the flag.  Their generated data go to ``--data DIR``
(default: a temporary folder removed at the end; pass a folder to keep the
data and let the study resume).
"""

HELP = "run all benchmarks (correlator, generator, acquisition, prefilters, SINS, end-to-end) and write a JSON report"

# The acceptance runs: name -> (script, arguments of the documented run, arguments under --quick,
# whether the script writes --json).  "{data}" is the run's own folder under --data.  The commands
# are the ones the documents state (README "Results", docs/ultratight.md "Measured",
# docs/prefilter.md, docs/process.md, docs/claims.md "Running the checks").
ACCEPTANCE = {
    "acceptance_ultratight": (
        "acceptance_ultratight.py",
        ["--seeds", "1,2,3,4,5", "--duration", "60", "--monitor", "off", "--frontend-gain", "fixed",
         "--format", "ci16", "--noise-tau", "inf", "--data", "{data}"],
        ["--quick", "--data", "{data}"], True),
    "acceptance_ultratight_agc": (
        "acceptance_ultratight.py",
        ["--seeds", "1,2,3,4,5", "--duration", "60", "--monitor", "off", "--frontend-gain", "agc",
         "--format", "ci8", "--noise-tau", "0", "--data", "{data}"],
        ["--quick", "--frontend-gain", "agc", "--format", "ci8", "--noise-tau", "0", "--data", "{data}"], True),
    "acceptance_prefilter": ("acceptance_prefilter.py", ["--seeds", "5"], ["--seeds", "1"], True),
    "acceptance_bits": ("acceptance_bits.py", ["check", "--data", "{data}"],
                        ["check", "--seeds", "1", "--data", "{data}"], True),
    "acceptance_bits_sweep": ("acceptance_bits.py", ["sweep", "--data", "{data}"],
                              ["sweep", "--cn0-list", "30", "--strategies", "blind", "--data", "{data}"], True),
    "acceptance_bits_sweep_lnav": ("acceptance_bits.py",
                                   ["sweep", "--nav-data", "lnav", "--strategies", "assisted", "--data", "{data}"],
                                   ["sweep", "--nav-data", "lnav", "--strategies", "assisted", "--cn0-list", "30",
                                    "--data", "{data}"], True),
    "acceptance_atmosphere": ("acceptance_atmosphere.py", [], ["--quick"], True),
    "acceptance_all_in_view": ("acceptance_all_in_view.py", [], ["--quick"], True),
    "acceptance_reproductions": ("acceptance_reproductions.py", [], ["--quick"], True),
    "acceptance_campaign": ("acceptance_campaign.py", [], ["--quick"], True),
    "acceptance_afm_quiet": ("acceptance_afm_quiet.py", [], ["--quick"], True),
    # the real recordings' acquisition table (../shared/data; a missing file is reported as such)
    "acceptance_acquisition_real": ("bench_acquisition.py", ["--real", "-v"], ["--real", "-v", "--quick"], True),
    # the scalar receiver at 4 MHz (docs/process.md "speed": the 0.1 real-time goal)
    "acceptance_process_4mhz": ("bench_process.py", ["--fs", "4e6"], ["--fs", "4e6", "--quick"], True),
    # docs/integrate.md: the walk_0827 table of every core (../shared/data) and the tight run
    "acceptance_integrate_walk": ("acceptance_integrate_walk.py", [], ["--quick"], True),
    # docs/ultratight.md "A rocket launch as a user's files": process --mode ultratight with its defaults
    "acceptance_rocket_launch": ("acceptance_rocket_launch.py", ["--cn0-list", "45,30", "--data", "{data}"],
                                 ["--quick", "--data", "{data}"], True),
}
# the papers' Monte Carlo tables, printed by ``ultratight scenario`` (docs/paper_afm.md,
# docs/integration-experiments.md, docs/airdata.md): --quick runs one seed of a shorter cut
for _name, _runs, _extra, _cut in (("paper-afm-jump", 10, [], 60), ("paper-afm-noise", 10, [], 60),
                                   ("paper-afm-accel", 10, [], 60),
                                   ("paper-static-iakf", 10, ["--methods", "akf0,akf,iakf,kf,kf-true-noise",
                                                              "--from-s", "200"], 300),
                                   ("paper-robust-flight", 10, [], 100), ("paper-fads", 100, [], 60),
                                   ("paper-fads-separate", 100, [], 60)):
    ACCEPTANCE["scenario_" + _name.replace("-", "_")] = (
        "acceptance_scenario.py", [_name, "--runs", str(_runs), "--seed", "1"] + _extra,
        [_name, "--runs", "1", "--seed", "1", "--duration", str(_cut)] + _extra, True)
# paper-highdyn with and without the opt-in outer-loop frequency update (docs/ultratight.md, "Why the
# DLB filters peaked ..."): the 20 s, seeds 1-2 comparison and the 5-seed 60 s run
_DLB = ["--methods", "dlb-rackf,dlb-ckf,dlb-ukf"]
_HD_QUICK = ["paper-highdyn", "--runs", "1", "--seed", "1", "--duration", "4", "--fs-hz", "2.046e6",
             "--methods", "dlb-rackf"]
ACCEPTANCE.update({
    "scenario_highdyn_20s": ("acceptance_scenario.py", ["paper-highdyn", "--runs", "2", "--seed", "1", "--duration",
                                                        "20"] + _DLB, _HD_QUICK, True),
    "scenario_highdyn_20s_outer_freq": ("acceptance_scenario.py", ["paper-highdyn", "--runs", "2", "--seed", "1",
                                                                   "--duration", "20"] + _DLB + ["--outer-freq-update"],
                                        _HD_QUICK + ["--outer-freq-update"], True),
    "scenario_highdyn_outer_freq": ("acceptance_scenario.py", ["paper-highdyn", "--runs", "5", "--seed", "1"] + _DLB
                                    + ["--outer-freq-update"], _HD_QUICK + ["--outer-freq-update"], True),
})
# the readings and variants the documents run on "a copy of the TOML with KEY changed"
# (acceptance_scenario.py --set KEY=VALUE): name -> (scenario, runs, extra arguments, --set items)
_NOISIER = ["imu.gyro_arw_dprh=3.0", "imu.accel_vrw_ugrhz=254.9", "filter.gyro_arw_dprh=3.0",
            "filter.accel_vrw_mps_rh=0.15"]
VARIANTS = {
    "static_iakf_model": ("paper-static-iakf", 10, ["--methods", "iakf"], ['filter.iakf_q_structure="model"']),
    "static_iakf_no_ceiling": ("paper-static-iakf", 10, ["--methods", "iakf"], ["filter.iakf_q_ceiling=false"]),
    "static_iakf_keep_q": ("paper-static-iakf", 10, ["--methods", "iakf"], ["filter.iakf_adapt_q=false"]),
    "static_iakf_full_window": ("paper-static-iakf", 10, ["--methods", "iakf"], ['filter.iakf_start="full-window"']),
    "static_iakf_as_printed": ("paper-static-iakf", 10, ["--methods", "iakf"],
                               ['filter.iakf_q_structure="full"', "filter.iakf_q_ceiling=false"]),
    "static_iakf_earlier_default": ("paper-static-iakf", 10, ["--methods", "iakf"],
                                    ['filter.iakf_q_structure="full"', "filter.iakf_q_ceiling=false",
                                     'filter.iakf_start="full-window"']),
    "static_akf0_literal": ("paper-static-iakf", 3, ["--methods", "akf0"], ["filter.akf0_adaptive=true"]),
    "robust_flight_scale20": ("paper-robust-flight", 10, [], ['gross.mode="scale"', "gross.factor=20.0"]),
    "robust_flight_scale20_no_replacements": ("paper-robust-flight", 10, [],
                                              ['gross.mode="scale"', "gross.factor=20.0",
                                               "filter.weight_replacements=false"]),
    "robust_flight_lsq": ("paper-robust-flight", 10, [], ['gnss.mode="lsq"']),
    "robust_flight_lsq_scale20": ("paper-robust-flight", 10, [],
                                  ['gnss.mode="lsq"', 'gross.mode="scale"', "gross.factor=20.0"]),
    "fads_bias": ("paper-fads", 20, [], ['imu.error_model="bias"']),
    # docs/paper_afm.md "A noisier IMU": gyro ARW 3 deg/sqrt(h), VRW 0.15 m/s/sqrt(h), the filters' Q matched
    "afm_jump_noisier": ("paper-afm-jump", 2, [], _NOISIER),
    "afm_noise_noisier": ("paper-afm-noise", 2, [], _NOISIER),
    "afm_accel_noisier": ("paper-afm-accel", 2, [], _NOISIER),
    "afm_noise_arw30": ("paper-afm-noise", 2, [], ["imu.gyro_arw_dprh=30.0", "imu.accel_vrw_ugrhz=254.9",
                                                    "filter.gyro_arw_dprh=30.0", "filter.accel_vrw_mps_rh=0.15"]),
    "fads_linear_envelope": ("paper-fads", 100, [], ['fads.altitude_shape="linear"', 'fads.altitude_curve="envelope"']),
    # docs/airdata.md "The FADS altitude curve": the four readings on 20 runs each
    "fads_curve_loglinear_sigma_20": ("paper-fads", 20, [], ['fads.altitude_shape="log-linear"',
                                                             'fads.altitude_curve="sigma"']),
    "fads_curve_loglinear_envelope_20": ("paper-fads", 20, [], ['fads.altitude_shape="log-linear"',
                                                                'fads.altitude_curve="envelope"']),
    "fads_curve_linear_sigma_20": ("paper-fads", 20, [], ['fads.altitude_shape="linear"', 'fads.altitude_curve="sigma"']),
    "fads_curve_linear_envelope_20": ("paper-fads", 20, [], ['fads.altitude_shape="linear"',
                                                             'fads.altitude_curve="envelope"']),
}
for _name, (_scen, _runs, _extra, _sets) in VARIANTS.items():
    _set_args = [a for item in _sets for a in ("--set", item)]
    ACCEPTANCE["variant_" + _name] = (
        "acceptance_scenario.py", [_scen, "--runs", str(_runs), "--seed", "1"] + _extra + _set_args,
        [_scen, "--runs", "1", "--seed", "1", "--duration", "60"] + _extra + _set_args, True)
del _name, _runs, _extra, _cut, _scen, _sets, _set_args, _DLB, _HD_QUICK, _NOISIER
ACCEPTANCE.update({
    "study_highdyn": (
        "study_highdyn.py",
        ["--runs", "10", "--cache", "--out", "{data}", "--only",
         "if-x20,if-x4.47,corr-x4.47,filter-r-x4.47,if-x10,if-x20-coast,corr-x4.47-coast"],
        ["--runs", "2", "--duration", "12", "--fs-hz", "2.046e6", "--out", "{data}", "--only", "if-x20"], False),
    "study_highdyn_20s": (
        "study_highdyn.py",
        ["--runs", "10", "--cache", "--duration", "20", "--out", "{data}", "--only",
         "corr-x20,corr-x10,filter-r-x20,if-x3,if-x2,corr-x3,corr-x2"],
        ["--runs", "2", "--duration", "12", "--fs-hz", "2.046e6", "--out", "{data}", "--only", "corr-x20"], False),
})


def add_arguments(p):
    p.add_argument("--quick", action="store_true", help="shorter runs (smoke-level figures)")
    p.add_argument("--json", metavar="PATH", default="bench.json", help="report path (default: bench.json)")
    p.add_argument("--only", metavar="LIST", default=None,
                   help="comma-separated benchmark names (e.g. correlator,prefilter, or an acceptance run)")
    p.add_argument("--acceptance", action="store_true",
                   help="also run the acceptance scripts, the study and the slow test reproductions (long)")
    p.add_argument("--data", metavar="DIR", default=None,
                   help="folder for the acceptance runs' generated data (default: a temporary folder)")
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


def select(d, only=None, acceptance=False):
    """The runs to do, in order: a list of ``(name, script path, kind)`` with kind ``"bench"`` or
    ``"acceptance"``.  The default set is every ``bench_*.py`` of ``d``; ``acceptance`` adds the
    entries of :data:`ACCEPTANCE` whose script is in ``d``; ``only`` (names, comma-separated) picks
    from both sets.  An unknown name raises ``ConfigError``."""
    from ultratight.errors import ConfigError

    runs = [(s.stem[len("bench_"):], s, "bench") for s in sorted(d.glob("bench_*.py"))]
    extra = [(n, d / spec[0], "acceptance") for n, spec in ACCEPTANCE.items() if (d / spec[0]).is_file()]
    if only:
        wanted = [w.strip() for w in only.split(",") if w.strip()]
        known = [r[0] for r in runs + extra]
        unknown = sorted(set(wanted) - set(known))
        if unknown:
            raise ConfigError(f"unknown benchmark(s) {', '.join(unknown)}; known: {', '.join(known)}")
        return [r for r in runs + extra if r[0] in wanted]
    return runs + extra if acceptance else runs


def command(name, script, kind, out, quick, data_dir):
    """The command line of one run (``out``: its JSON report; ``data_dir``: the --data folder)."""
    import os
    import sys

    if kind == "bench":
        return [sys.executable, str(script), "--json", out] + (["--quick"] if quick else [])
    _, full, short, writes_json = ACCEPTANCE[name]
    data = os.path.join(data_dir, name)
    args = [a.replace("{data}", data) for a in (short if quick else full)]
    return [sys.executable, str(script)] + args + (["--json", out] if writes_json else [])


def run_one(cmd, out, cwd):
    """Run one script; its report entry (wall time, CPU time, peak memory, status, figures, printed
    lines).  ``cpu_s`` is the user + system time of the script and of every process it waited for
    (a scenario's worker processes included); ``max_rss_mb`` the largest resident set of any one of
    them (``wait4``'s rusage, Linux: kB)."""
    import json
    import os
    import subprocess
    import tempfile
    import time

    t0 = time.perf_counter()
    with tempfile.TemporaryFile("w+") as fo, tempfile.TemporaryFile("w+") as fe:
        proc = subprocess.Popen(cmd, stdout=fo, stderr=fe, text=True, cwd=cwd)
        _, status, usage = os.wait4(proc.pid, 0)
        proc.returncode = os.waitstatus_to_exitcode(status)
        fo.seek(0)
        fe.seek(0)
        stdout, stderr = fo.read(), fe.read()
    entry = {"wall_s": round(time.perf_counter() - t0, 3), "cpu_s": round(usage.ru_utime + usage.ru_stime, 3),
             "max_rss_mb": round(usage.ru_maxrss / 1024.0, 1), "returncode": proc.returncode,
             "command": cmd[1:], "output": stdout.splitlines()}
    if proc.returncode != 0:
        entry["error"] = (stderr.strip().splitlines() or ["(no output)"])[-1]
    elif "--json" not in cmd:
        entry["results"] = {}
    elif os.path.exists(out):
        try:
            with open(out) as fh:
                entry["results"] = json.load(fh)
        except (OSError, ValueError) as exc:
            entry["error"] = f"unreadable report ({exc})"
    else:
        entry["error"] = "no report written"
    return entry


def run(args):
    import os
    import sys
    import tempfile
    import time

    from ultratight import __version__, io_guard

    from ultratight.errors import ConfigError

    io_guard.check_io([], [("--json", args.json)])
    if args.data is not None and os.path.exists(args.data) and not os.path.isdir(args.data):
        raise ConfigError(f"--data {args.data} is a file, not a folder")
    d = _bench_dir(args.dir)
    runs = select(d, args.only, args.acceptance)
    report = {"version": __version__, "machine": machine_info(), "quick": bool(args.quick),
              "acceptance": bool(args.acceptance), "benchmarks": {}}
    t_all = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        data_dir = os.path.abspath(args.data) if args.data else os.path.join(tmp, "data")
        for name, script, kind in runs:
            out = os.path.join(tmp, f"{name}.json")
            cmd = command(name, script, kind, out, args.quick, data_dir)
            print(f"[bench] {name} ...", file=sys.stderr, flush=True)
            entry = run_one(cmd, out, cwd=os.getcwd())
            report["benchmarks"][name] = entry
            if kind == "acceptance":
                for line in entry["output"]:
                    print(f"[{name}] {line}", file=sys.stderr)
            status = "ok" if "results" in entry else f"FAILED: {entry['error']}"
            print(f"[bench] {name}: {status} ({entry['wall_s']:.1f} s, {entry['cpu_s']:.1f} s CPU, "
                  f"{entry['max_rss_mb']:.0f} MB peak RSS)", file=sys.stderr, flush=True)
    report["total_wall_s"] = round(time.perf_counter() - t_all, 3)
    io_guard.write_text_atomic(args.json, io_guard.json_dumps(report, indent=2))
    print(io_guard.json_dumps({k: v for k, v in report.items() if k != "benchmarks"}))
    print(f"report written to {args.json}")
    failed = [n for n, e in report["benchmarks"].items() if "results" not in e]
    return 1 if failed else 0
