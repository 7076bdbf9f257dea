"""The command line and what it orchestrates: argparse commands, scenario and campaign runners,
worker processes, scenario configuration and the experiment registry."""

from ultratight.receiver.cli.main import build_parser, main

__all__ = ["build_parser", "main"]
