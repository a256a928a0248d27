"""The ``uavsim`` command line: one entry point, one subcommand per job (DESIGN.md §3).

Each subcommand lives in the package that owns the work and exposes ``register(subparsers)``;
this module only wires them together, configures logging once, and turns expected errors
(bad input) into a one-line message and a non-zero exit. Heavy imports happen inside the
subcommands, so ``uavsim --help`` and the in-flight commands stay light.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

#: Modules that add subcommands, in help order. Each has ``register(subparsers)``.
COMMAND_MODULES = [
    "agent.demo",  # the main job
    "sim.cli",  # sim render
    "sim.flight",  # sim-flight
    "telemetry.cli",  # poses, tlog
    "telemetry.sfm_cli",  # import-photos, sfm-photos
    "fields.cli",  # fit, render
    "fields.synth_flight",  # synth
    "export.cli",  # detector train|export|eval, detect
    "agent.replay",  # replay
    "agent.daemon",  # agent
    "agent.bench_cli",  # bench
]

log = logging.getLogger("uavsim")

#: Exceptions that mean "bad input": one line, exit code 2. Anything else is a bug: traceback.
USER_ERRORS = (ValueError, OSError, LookupError)


def configure_logging(verbosity: int) -> None:
    """Plain ``logging`` to stderr: journald-friendly, no colour."""
    level = logging.WARNING - 10 * verbosity
    logging.basicConfig(level=max(level, logging.DEBUG), stream=sys.stderr,
                        format="%(levelname)s %(name)s: %(message)s")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="uavsim", description=__doc__.splitlines()[0])
    parser.add_argument("-v", "--verbose", action="count", default=1,
                        help="more log output (repeatable)")
    parser.add_argument("-q", "--quiet", action="store_true", help="warnings and errors only")
    parser.add_argument("--debug", action="store_true", help="show tracebacks for errors")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    subparsers.required = True
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    configure_logging(0 if args.quiet else args.verbose)
    try:
        result = args.func(args)
    except KeyboardInterrupt:
        print("uavsim: interrupted", file=sys.stderr)
        return 130
    except USER_ERRORS as exc:
        if args.debug:
            raise
        print(f"uavsim: error: {exc}", file=sys.stderr)
        return 2
    return int(result or 0)


if __name__ == "__main__":
    sys.exit(main())
