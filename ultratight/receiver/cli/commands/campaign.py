"""``ultratight campaign``: Monte-Carlo runs of a scenario on dask.distributed (docs/campaign.md)."""

HELP = "Monte-Carlo campaign of a scenario on dask.distributed (local cores or a scheduler)"


def add_arguments(parser):
    parser.add_argument("scenario", help="scenario name (e.g. paper-robust-flight) or path to a TOML file")
    parser.add_argument("--runs", type=int, required=True, help="number of Monte-Carlo runs")
    parser.add_argument("--methods", default=None, help="comma-separated methods (default: the experiment's)")
    parser.add_argument("--seed", type=int, default=None,
                        help="base seed (default: the scenario's); run i uses SeedSequence(seed).spawn(runs)[i]")
    where = parser.add_mutually_exclusive_group()
    where.add_argument("--workers", type=int, default=None,
                       help="LocalCluster worker processes, one thread each (default: one per allowed core; "
                            "at most one per run and per allowed core)")
    where.add_argument("--scheduler", default=None, metavar="ADDRESS",
                       help="run on an existing Dask scheduler (e.g. tcp://127.0.0.1:8786)")
    parser.add_argument("--connect-timeout", type=float, default=10.0, metavar="S",
                        help="--scheduler: give up connecting after S seconds (default 10)")
    parser.add_argument("--out", default="campaign_out", help="output directory (runs/ and campaign.json)")
    parser.add_argument("--resume", action="store_true", help="keep the complete run files of this campaign in "
                                                               "OUT/runs and run only the missing ones")
    parser.add_argument("--duration", type=float, default=None, help="cut the scenario to this many seconds")
    parser.add_argument("--cache", action="store_true",
                        help="IF-level scenarios: write each run's IF file into OUT/cache (default: generated in "
                             "memory for each method; same results)")
    parser.add_argument("--json", action="store_true", help="print the campaign summary as JSON")
    parser.add_argument("--quiet", action="store_true", help="no progress bar or cluster messages")


def run(args):
    import sys

    from ultratight.errors import ConfigError
    from ultratight.io_guard import json_dumps
    from ultratight.receiver.cli.campaign import run_campaign
    methods = None if args.methods is None else [m.strip() for m in args.methods.split(",") if m.strip()]
    overrides = {}
    if args.duration is not None:
        if not args.duration > 0:
            raise ConfigError(f"--duration must be > 0 s, got {args.duration}")
        overrides["duration_s"] = float(args.duration)
    res = run_campaign(args.scenario, runs=args.runs, methods=methods, seed=args.seed, workers=args.workers,
                       scheduler=args.scheduler, out_dir=args.out, resume=args.resume, overrides=overrides,
                       progress=not args.quiet, connect_timeout_s=args.connect_timeout, cache=args.cache)
    if args.json:
        print(json_dumps(res["json"], indent=2))
    else:
        print(res["text"])
        print(f"\nwrote {res['campaign_path']} and {res['runs_dir']}/", file=sys.stderr)
    return 0
