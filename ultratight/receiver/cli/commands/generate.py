"""``ultratight generate SCENARIO``: write a sampled-IF file, its sidecar and the truth.

``--out`` is either a directory (an existing one, or any path ending in ``/``; files are
named after the scenario: ``DIR/<scenario>.<format>``, ``DIR/<scenario>.truth.h5`` ...) or a
path stem ``DIR/STEM`` (``DIR/STEM.<format>``, ``DIR/STEM.truth.h5``; a trailing
``.<format>`` extension on STEM is dropped). Missing directories are created (and removed
again if the generation fails before writing anything). Default: the current directory.
Flags override the scenario's fields; ``--format`` also sets the sampling (real/complex)
and a matching quantiser width (2-bit formats: 2, float formats: none, 16-bit: 16).
"""

HELP = "generate a GPS L1 C/A IF file (+ JSON sidecar, truth HDF5, IMU) from a scenario"


def add_arguments(p):
    p.add_argument("scenario", metavar="SCENARIO", help="built-in scenario name or path to a .toml file")
    p.add_argument("--duration", type=float, metavar="S", help="duration in seconds")
    p.add_argument("--out", metavar="PATH", default=".", help="output directory or path stem (default: .)")
    p.add_argument("--seed", type=int, metavar="N", help="random seed")
    p.add_argument("--fs", type=float, metavar="HZ", help="sampling rate, Hz")
    p.add_argument("--if", dest="if_hz", type=float, metavar="HZ", help="intermediate frequency, Hz (0: complex baseband)")
    p.add_argument("--format", metavar="FMT", help="sample format: i8 i16 f32 ci8 ci16 cf32 i2packed ci2packed")
    p.add_argument("--cn0", type=float, metavar="DBHZ", help="C/N0 of every satellite, dB-Hz")
    p.add_argument("--sigmf", action="store_true",
                   help="also write SigMF metadata (<stem>.sigmf-meta naming the IF file as its dataset)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")


def _out_location(out, name, fmt_names):
    """``(directory, stem)`` for ``--out`` (see the module doc); the directory may not exist yet."""
    import os
    from pathlib import Path

    p = Path(out)
    if p.is_dir() or str(out).endswith((os.sep, "/")):
        return p, name
    stem = p.name
    for f in fmt_names:
        if stem.endswith("." + f):
            stem = stem[: -len(f) - 1]
            break
    return p.parent, stem


def _make_dirs(d):
    """Create directory ``d`` and missing parents; returns the ones created (deepest last)."""
    from pathlib import Path

    from ultratight.errors import ConfigError

    d = Path(d)
    missing = []
    q = d
    while not q.exists():
        missing.append(q)
        if q.parent == q:
            break
        q = q.parent
    if q.exists() and not q.is_dir():
        raise ConfigError(f"--out: {q} is not a directory")
    try:
        d.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(f"--out: cannot create directory {d} ({exc.strerror or exc})") from None
    return missing[::-1]


def _remove_empty_dirs(dirs):
    for d in reversed(dirs):
        try:
            d.rmdir()
        except OSError:
            break


def check_outputs(cfg, out_dir, stem):
    """Refuse before any work: output names invalid or naming the scenario file, not enough free
    disk or memory for the estimate (:func:`ultratight.signals.synth.generator.generation_estimate`)."""
    from ultratight import io_guard
    from ultratight.signals.synth.generator import generation_estimate, output_paths
    paths = output_paths(out_dir, stem, cfg["frontend"]["format"])
    io_guard.check_io([("SCENARIO", cfg.get("source_file"))],
                      [(f"--out ({k})", str(v)) for k, v in paths.items()], create_parents=True)
    est = generation_estimate(cfg)
    total = est["if_bytes"] + est["truth_bytes"] + 2 * est["imu_bytes"]
    io_guard.check_disk(out_dir, total, f"generating {cfg['duration_s']:g} s at {cfg['frontend']['fs_hz']:g} Hz "
                                        f"({cfg['frontend']['format']})")
    io_guard.check_memory(est["memory_bytes"], f"generating {cfg['duration_s']:g} s")


def format_overrides(fmt):
    """Front-end overrides implied by choosing sample format ``fmt``."""
    from ultratight.signals.recording.iffile import get_format

    spec = get_format(fmt)
    return {"frontend.format": spec.name, "frontend.sampling": "complex" if spec.is_complex else "real",
            "frontend.bits": spec.quantiser_bits}


def run(args):
    import sys

    from ultratight.errors import ConfigError
    from ultratight.receiver.cli.scenario_config import load_scenario
    from ultratight.signals.recording.iffile import FORMATS

    overrides = {"duration_s": args.duration, "seed": args.seed, "frontend.fs_hz": args.fs,
                 "frontend.if_hz": args.if_hz, "satellites.cn0_dbhz": args.cn0}
    if args.format is not None:
        if args.format not in FORMATS:
            raise ConfigError(f"--format: unknown IF sample format {args.format!r}; expected one of "
                              f"{', '.join(FORMATS)}")
        overrides.update(format_overrides(args.format))
    cfg = load_scenario(args.scenario, overrides)
    if getattr(args, "sigmf", False):
        from ultratight.signals.recording.sigmf_io import FORMAT_TO_DATATYPE
        if cfg["frontend"]["format"] not in FORMAT_TO_DATATYPE:
            raise ConfigError(f"--sigmf: SigMF has no datatype for the {cfg['frontend']['format']!r} format "
                              f"(use one of {', '.join(FORMAT_TO_DATATYPE)})")
    out_dir, stem = _out_location(args.out, cfg["name"], list(FORMATS))
    check_outputs(cfg, out_dir, stem)

    from ultratight.signals.synth.generator import generate

    created = _make_dirs(out_dir)
    try:
        res = generate(cfg, out_dir, stem, seed=cfg["seed"], progress=not args.no_progress)
    except BaseException as exc:
        _remove_empty_dirs(created)     # only directories this run created, and only when empty
        from ultratight.errors import UltratightError
        if isinstance(exc, OSError) and not isinstance(exc, UltratightError):
            from ultratight.io_guard import output_error
            raise output_error(f"{out_dir}/{stem}.*", exc) from None
        raise
    summ = res["summary"]
    if getattr(args, "sigmf", False):
        from ultratight.signals.recording.sigmf_io import write_sigmf_meta
        fe = cfg.get("frontend", {})
        res["sigmf"] = write_sigmf_meta(res["if"], summ["format"], summ["fs_hz"], summ["if_hz"],
                                        inversion=bool(fe.get("inversion", False)),
                                        start_week=cfg["time"]["week"], start_tow_s=cfg["time"]["tow_s"],
                                        description=f"ultratight generate {cfg['name']} (seed {summ['seed']})")
    files = {k: str(v) for k, v in res.items() if k != "summary"}
    if args.json:
        from ultratight.io_guard import json_dumps
        print(json_dumps({"files": files, **summ}, indent=1))
        return 0
    fs = summ["fs_hz"]
    print(f"scenario {cfg['name']}: {summ['duration_s']:.3f} s at {fs / 1e6:g} MHz, IF {summ['if_hz'] / 1e6:g} MHz, "
          f"format {summ['format']}, seed {summ['seed']} ({summ['elapsed_s']:.1f} s)")
    sats = ", ".join(f"{p} ({c:g} dB-Hz)" for p, c in zip(summ["prns"], summ["cn0_dbhz"]))
    print(f"satellites ({len(summ['prns'])}): {sats}")
    for k, v in files.items():
        print(f"  {k:10s} {v}")
    sys.stdout.flush()
    return 0
