"""``ultratight scenario``: generate (or reuse) a scenario's IF + IMU + truth, run the
ultra-tight methods on it and report the paper's metrics (seed 000 Tables 3 and 4)."""

HELP = "run a scenario end to end (generate IF/IMU/truth, track with each method, paper metrics)"

DEFAULT_METHODS = "pb-kf-utc,dlb-ukf,dlb-ckf,dlb-rackf"


def add_arguments(parser):
    parser.add_argument("scenario", help="scenario name (e.g. paper-highdyn) or path to a TOML file")
    parser.add_argument("--methods", default=DEFAULT_METHODS,
                        help=f"comma-separated methods (default {DEFAULT_METHODS}; also 'scalar')")
    parser.add_argument("--runs", type=int, default=1, help="Monte-Carlo runs (seeds seed..seed+runs-1)")
    parser.add_argument("--seed", type=int, default=None, help="base seed (default: the scenario's)")
    parser.add_argument("--out", default="scenario_out", help="output directory (also holds the data cache)")
    parser.add_argument("--duration", type=float, default=None, help="cut the scenario to this many seconds")
    parser.add_argument("--fs-hz", type=float, default=None, help="override the front-end sampling rate")
    parser.add_argument("--channel", type=int, default=0, help="channel index for the one-channel table")
    parser.add_argument("--monitor", default="off",
                        help="engine-level signal monitor: off (default, the paper's double loop: the "
                             "prefilters ride through fades), gate (keep fading channels out of the tight "
                             "filter only), coast (also coast fading channels on the outer loop and restart)")
    parser.add_argument("--json", action="store_true", help="print the summary as JSON")
    parser.add_argument("--no-plots", action="store_true", help="do not write PNG figures")
    parser.add_argument("--quiet", action="store_true", help="no progress output")


def run(args):
    import json
    import sys

    from ultratight.errors import ConfigError
    from ultratight.receiver.engine import EngineOptions, monitor_options
    from ultratight.receiver.scenario_runner import run_scenario
    try:
        mon = monitor_options(args.monitor)
    except ConfigError as exc:
        raise ConfigError(f"--monitor: {exc}") from None
    summary = run_scenario(
        args.scenario,
        methods=[m.strip() for m in args.methods.split(",") if m.strip()],
        runs=args.runs, seed=args.seed, out_dir=args.out, duration_s=args.duration,
        fs_hz=args.fs_hz, channel=args.channel, plots=not args.no_plots,
        progress=not (args.quiet or args.json), options=EngineOptions(**mon),
    )
    if args.json:
        print(json.dumps(summary["json"], indent=2))
    else:
        print(summary["text"])
        print(f"\nwrote {summary['metrics_path']} and {summary['h5_path']}", file=sys.stderr)
    return 0
