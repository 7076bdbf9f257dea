"""Command-line entry point: ``ultratight SUBCOMMAND ...``.

Each subcommand lives in ``ultratight.receiver.commands.<name>`` and exposes

* ``HELP``: a one-line description,
* ``add_arguments(parser)``: declare its flags (cheap: no heavy imports),
* ``run(args) -> int``: do the work (import numba-heavy modules here).

User errors (:class:`ultratight.errors.UltratightError`) are printed as one
line on stderr with exit status 2; Ctrl-C exits with status 130.
"""

import argparse
import importlib
import sys

from ultratight import __version__
from ultratight.errors import UltratightError

SUBCOMMANDS = ("generate", "process", "ins", "scenario", "bench")


def _load(name):
    try:
        return importlib.import_module(f"ultratight.receiver.commands.{name}")
    except ModuleNotFoundError as exc:
        if exc.name == f"ultratight.receiver.commands.{name}":
            return None
        raise


def build_parser():
    parser = argparse.ArgumentParser(
        prog="ultratight",
        description="Software GPS L1 C/A receiver with ultra-tight SINS coupling.",
    )
    parser.add_argument("--version", action="version", version=f"ultratight {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name in SUBCOMMANDS:
        mod = _load(name)
        if mod is None:
            continue
        p = sub.add_parser(name, help=mod.HELP, description=mod.HELP)
        mod.add_arguments(p)
        p.set_defaults(_run=mod.run)
    return parser


def main(argv=None):
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args._run(args) or 0)
    except UltratightError as exc:
        print(f"ultratight {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"ultratight {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
