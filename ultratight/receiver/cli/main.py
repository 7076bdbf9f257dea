"""Command-line entry point: ``ultratight SUBCOMMAND ...``.

Each subcommand lives in ``ultratight.receiver.cli.commands.<name>`` and exposes

* ``HELP``: a one-line description,
* ``add_arguments(parser)``: declare its flags (cheap: no heavy imports),
* ``run(args) -> int``: do the work (import numba-heavy modules here).

User errors (:class:`ultratight.errors.UltratightError`, also output errors such as a full
disk, and memory exhaustion) are printed as one line on stderr with exit status 2. SIGINT,
SIGTERM and SIGHUP stop the run with one line saying whether a partial output (``complete=false``)
was written, exit status 128 + signal number (130, 143, 129). See docs/reliability.md.
"""

import argparse
import gc
import importlib
import sys
import warnings
from concurrent.futures import BrokenExecutor

from ultratight import __version__
from ultratight.errors import UltratightError

SUBCOMMANDS = ("generate", "process", "ins", "integrate", "spp", "scenario", "campaign", "bench")


def _load(name):
    try:
        return importlib.import_module(f"ultratight.receiver.cli.commands.{name}")
    except ModuleNotFoundError as exc:
        if exc.name == f"ultratight.receiver.cli.commands.{name}":
            return None
        raise


class _Parser(argparse.ArgumentParser):
    """argparse with one-line usage errors (``ultratight process: error: ... (see --help)``), exit 2."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {' '.join(message.split())} (see {self.prog} --help)\n")


def build_parser():
    parser = _Parser(
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


# numba's thread pool takes a cross-process lock in /dev/shm when it starts; where it cannot (no
# /dev/shm, or a file-size limit of a few bytes) it warns and goes on without it, which is safe here
# (each process starts its own pool once): the command's own error, if any, is the one line to show
warnings.filterwarnings("ignore", message="Could not obtain multiprocessing lock")


# the receivers allocate many small containers per epoch (records, observables, fixes) and keep few
# cycles: a young generation of 700 objects (CPython's default) had the cyclic collector run
# thousands of times per minute of signal (about 7 % of a ``process`` run, perf); collections still
# happen, less often
GC_THRESHOLD = (50000, 20, 20)


def main(argv=None):
    from ultratight import io_guard

    gc.set_threshold(*GC_THRESHOLD)

    previous = io_guard.install_signal_handlers()
    try:
        return _main(argv, io_guard)
    finally:
        io_guard.restore_signal_handlers(previous)


def console_main(argv=None):
    """The ``ultratight`` executable (and ``python -m ultratight.receiver.cli``): :func:`main`, then
    every object still alive moves to the collector's permanent generation, so the interpreter's
    last cyclic collection at exit does not walk them all again (half a second after a minute of
    signal). Outputs are closed by then; the objects are freed as the interpreter ends, as before."""
    rc = main(argv)
    gc.freeze()
    return rc


def _main(argv, io_guard):
    io_guard.reset_partial()
    try:
        parser = build_parser()
        args = parser.parse_args(argv)
    except KeyboardInterrupt as exc:
        print("ultratight: interrupted", file=sys.stderr)
        return getattr(exc, "exit_code", 130)
    name = f"ultratight {args.command}"
    try:
        rc = int(args._run(args) or 0)
        io_guard.check_interrupted()      # a signal whose exception a finaliser swallowed
        return rc
    except UltratightError as exc:
        if io_guard.interrupted_signal() is not None:
            return _interrupted(name, io_guard)
        print(f"{name}: error: {_one_line(exc)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:
        sig = getattr(exc, "name", "SIGINT")
        print(f"{name}: interrupted by {sig}; {io_guard.interruption_note()}", file=sys.stderr)
        return getattr(exc, "exit_code", 130)
    except MemoryError:
        print(f"{name}: error: out of memory (shorten the run: --duration, a lower rate)", file=sys.stderr)
        return 2
    except BrokenExecutor:
        if io_guard.interrupted_signal() is not None:
            return _interrupted(name, io_guard)
        # a worker process killed from outside (a signal, the kernel's out-of-memory killer): the pool
        # stopped the others; the run's outputs were not written
        print(f"{name}: error: a worker process ended abruptly (killed by a signal, or by the system for "
              f"lack of memory); the run was stopped and its outputs not written", file=sys.stderr)
        return 2
    except OSError as exc:
        if io_guard.interrupted_signal() is not None:
            return _interrupted(name, io_guard)
        # an OS-level failure no stage turned into a user error: report it in one line
        path = getattr(exc, "filename", None)
        where = f" {path}" if path else ""
        print(f"{name}: error:{where} {io_guard.describe_os_error(exc)}", file=sys.stderr)
        return 2
    except Exception:
        # a signal arrived and the code it interrupted then failed in another way (a library
        # object left half-built, a file closed mid-write): the run was still interrupted
        if io_guard.interrupted_signal() is not None:
            return _interrupted(name, io_guard)
        raise


def _interrupted(name, io_guard):
    exc = io_guard.Interrupted(io_guard.interrupted_signal())
    print(f"{name}: interrupted by {exc.name}; {io_guard.interruption_note()}", file=sys.stderr)
    return exc.exit_code


def _one_line(exc):
    text = " ".join(str(exc).split())
    return text if len(text) <= 2000 else text[:2000] + "..."


if __name__ == "__main__":
    sys.exit(main())
