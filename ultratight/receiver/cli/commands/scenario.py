"""``ultratight scenario``: run a scenario's experiment and report the paper's metrics.

The scenario's ``experiment`` key picks the experiment (:mod:`ultratight.receiver.cli.experiments`);
without it, the IF-level double loop of Zhao et al. 2014: generate (or reuse) IF + IMU + truth, run the
ultra-tight methods on it, report Tables 3 and 4."""

HELP = "run a scenario end to end (simulate, run each method, print the paper's tables)"

DEFAULT_METHODS = "pb-kf-utc,dlb-ukf,dlb-ckf,dlb-rackf"


def add_arguments(parser):
    parser.add_argument("scenario", help="scenario name (e.g. paper-highdyn) or path to a TOML file")
    parser.add_argument("--methods", default=None,
                        help=f"comma-separated methods (default: the experiment's; paper-highdyn: {DEFAULT_METHODS}, "
                             "also 'scalar')")
    parser.add_argument("--runs", type=int, default=1, help="Monte-Carlo runs (seeds seed..seed+runs-1)")
    parser.add_argument("--seed", type=int, default=None, help="base seed (default: the scenario's)")
    parser.add_argument("--out", default="scenario_out", help="output directory (also holds the data cache)")
    parser.add_argument("--cache", action="store_true",
                        help="IF-level scenarios: write the generated IF files into OUT/cache and read them from "
                             "disk (default: each method reads the IF from the generator in memory; same results)")
    parser.add_argument("--duration", type=float, default=None, help="cut the scenario to this many seconds")
    parser.add_argument("--fs-hz", type=float, default=None, help="override the front-end sampling rate")
    parser.add_argument("--channel", type=int, default=None, help="channel index for the one-channel table (default 0)")
    parser.add_argument("--monitor", default=None,
                        help="engine-level signal monitor: off (default, the paper's double loop: the "
                             "prefilters ride through fades), gate (keep fading channels out of the tight "
                             "filter only), coast (also coast fading channels on the outer loop and restart)")
    parser.add_argument("--noise-tau", type=float, default=None, metavar="S",
                        help="engine noise-floor estimator time constant in s (default: the scenario's [engine] "
                             "noise_tau_s, else 0 = per 10 ms IF block; inf = calibrated at start-up and held)")
    parser.add_argument("--frontend-gain", choices=("agc", "fixed"), default=None,
                        help="generator front-end gain: agc (follows noise events) or fixed (nominal noise, "
                             "headroom for the loudest noise event); default: the scenario's")
    parser.add_argument("--format", default=None,
                        help="override the generated IF format (e.g. ci16; sets the matching quantiser bits)")
    parser.add_argument("--outer-freq-update", action="store_true",
                        help="double loop: channels whose rows are out of the tight filter (faded) take the "
                             "outer loop's Doppler as a frequency pseudo-measurement (not in the paper; off "
                             "by default, see docs/ultratight.md)")
    parser.add_argument("--bits", default=None, metavar="STRATEGY",
                        help="navigation-data bits of the ultra-tight methods: assisted, decoded, decoded-scalar, "
                             "blind or a bit file (default: the scenario's [engine] bits, else assisted)")
    parser.add_argument("--workers", type=int, default=None, metavar="K",
                        help="worker processes for the methods and runs (default: one per core this process may "
                             "use, at most one per job; 1: all in this process)")
    parser.add_argument("--threads", type=int, default=None, metavar="K",
                        help="threads of one run's channel stages (default: the allowed cores shared between the "
                             "workers)")
    parser.add_argument("--json", action="store_true", help="print the summary as JSON")
    parser.add_argument("--no-plots", action="store_true", help="do not write PNG figures")
    parser.add_argument("--quiet", action="store_true", help="no progress output")


def format_overrides(fmt):
    """Scenario overrides for an IF format: the format, its sampling and a matching quantiser width."""
    from ultratight.errors import ConfigError
    from ultratight.signals.recording.iffile import FORMATS
    if fmt not in FORMATS:
        raise ConfigError(f"--format: unknown IF sample format {fmt!r}; expected one of {', '.join(FORMATS)}")
    spec = FORMATS[fmt]
    return {"frontend.format": fmt, "frontend.sampling": "complex" if spec.is_complex else "real",
            "frontend.bits": spec.quantiser_bits}


def _methods(args):
    return None if args.methods is None else [m.strip() for m in args.methods.split(",") if m.strip()]


def _print_summary(args, summary):
    import sys
    if args.json:
        from ultratight.io_guard import json_dumps
        print(json_dumps(summary["json"], indent=2))
    else:
        print(summary["text"])
        print(f"\nwrote {summary['metrics_path']} and {summary['h5_path']}", file=sys.stderr)


def run(args):
    from ultratight.errors import ConfigError
    from ultratight.receiver.cli import experiments
    path, raw, module = experiments.resolve(args.scenario)
    if not hasattr(module, "run_scenario"):
        used = [f"--{k.replace('_', '-')}" for k in IF_ONLY if getattr(args, k) not in (None, False)]
        if used:
            raise ConfigError(f"{', '.join(used)}: only for IF-level scenarios (this one runs experiment "
                              f"{raw.get('experiment')!r})")
        overrides = {} if args.duration is None else {"duration_s": args.duration}
        summary = experiments.run_experiment(
            module, path, raw, methods=_methods(args), runs=args.runs, seed=args.seed, out_dir=args.out,
            overrides=overrides, plots=not args.no_plots, progress=not (args.quiet or args.json))
        _print_summary(args, summary)
        return 0
    return _run_if(args, path, module)


# flags only the IF-level experiment understands (argparse dest names)
IF_ONLY = ("fs_hz", "channel", "monitor", "noise_tau", "frontend_gain", "format", "outer_freq_update", "workers",
           "threads", "bits", "cache")


def _run_if(args, path, module):
    from ultratight.errors import ConfigError
    from ultratight.receiver.cli import experiments
    from ultratight.receiver.deep.options import EngineOptions, monitor_options
    try:
        mon = monitor_options(args.monitor or "off")
    except ConfigError as exc:
        raise ConfigError(f"--monitor: {exc}") from None
    if args.outer_freq_update:
        mon["outer_freq_update"] = True
    if args.threads is not None:
        if args.threads < 1:
            raise ConfigError(f"--threads must be an integer >= 1, got {args.threads}")
        mon["threads"] = args.threads
    overrides = {}
    if args.noise_tau is not None:
        if not args.noise_tau >= 0:
            raise ConfigError(f"--noise-tau must be >= 0 s (or inf), got {args.noise_tau}")
        overrides["engine.noise_tau_s"] = float(args.noise_tau)
    if args.frontend_gain is not None:
        overrides["frontend.gain"] = args.frontend_gain
    if args.bits is not None:
        from ultratight.receiver.deep.bitsources import check_strategy
        check_strategy(args.bits)
        overrides["engine.bits"] = args.bits
    if args.format is not None:
        overrides.update(format_overrides(args.format))
    summary = module.run_scenario(
        path, methods=experiments.check_methods(module, _methods(args)),
        runs=args.runs, seed=args.seed, out_dir=args.out, duration_s=args.duration,
        fs_hz=args.fs_hz, channel=0 if args.channel is None else args.channel, plots=not args.no_plots,
        progress=not (args.quiet or args.json), options=EngineOptions(**mon), overrides=overrides,
        workers=args.workers, cache=args.cache,
    )
    _print_summary(args, summary)
    return 0
