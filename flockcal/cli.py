"""The `flockcal` command line: parses arguments and hands over to a command module.

Errors a person can act on are raised as a `flockcal.errors.FlockcalError` (each layer derives its
own type) and printed as one line on stderr with a non-zero exit code, never as a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from flockcal import __version__
from flockcal.errors import FlockcalError

# Each module registers its own sub-commands; this is which registers which (tests/test_cli_dispatch.py
# holds it to what the modules register). A command line that names one imports only its module: the
# others' compiling and imports were ~0.02 s of every `flockcal fit`.
COMMANDS = {
    "fit": "flockcal.commands.fit",
    "simulate": "flockcal.commands.simulate",
    "record": "flockcal.commands.record", "replay": "flockcal.commands.record", "convert": "flockcal.commands.record",
    "serve": "flockcal.commands.serve",
    "scale": "flockcal.commands.outputs", "report": "flockcal.commands.outputs",
    "export-bvh": "flockcal.commands.outputs", "export-gltf": "flockcal.commands.outputs",
    "skeleton": "flockcal.commands.outputs",
    "fit-markers": "flockcal.commands.markers",
    "batch": "flockcal.commands.batch",
}
COMMAND_MODULES = list(dict.fromkeys(COMMANDS.values()))


class Parser(argparse.ArgumentParser):
    """Argument errors as one line naming the command and where its options are listed, exit 2 (argparse
    prints its whole usage block first: up to 10 lines before the one that matters)."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message}; `{self.prog} --help` lists the options\n")


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The whole command line's parser; with `command` (a name in COMMANDS), one that knows only the
    commands of that command's module."""
    parser = Parser(
        prog="flockcal",
        description="Live skeleton calibration for 6-DOF magnetic motion trackers.",
    )
    parser.add_argument("--version", action="version", version=f"flockcal {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in [COMMANDS[command]] if command in COMMANDS else COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    parser.commands = sub.choices  # each command's own parser: its errors carry its name
    return parser


def main(argv: list[str] | None = None) -> int:
    # Before the command modules load numpy (some import it at the top): OpenBLAS reads its thread count
    # once, at load. A second BLAS thread spin-waits on a loaded machine: it doubled the service's slip
    # loop CPU time and let `flockcal serve` fall seconds behind the tracker (docs/slippage.md).
    from flockcal.threads import single_threaded_blas

    single_threaded_blas()
    words = sys.argv[1:] if argv is None else argv
    named = next((w for w in words if not w.startswith("-")), None)  # (the top level's options take no value)
    parser = build_parser(named)
    args, unknown = parser.parse_known_args(argv)
    if unknown:  # reported by the command's parser, so the line says which command refused them
        where = parser.commands.get(getattr(args, "command", None) or "", parser)
        where.error(f"unrecognized arguments: {' '.join(unknown)}")
    logging.basicConfig(
        level=logging.DEBUG if args.verbose > 1 else logging.INFO if args.verbose else logging.WARNING,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except FlockcalError as exc:
        print(f"flockcal {args.command}: error: {exc}", file=sys.stderr)
        return int(getattr(exc, "exit_code", 2))
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:
        return 0
