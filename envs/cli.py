"""The ``osa`` command line (docs/cli.md).

Each subcommand lives in ``envs/commands/<name>.py`` with ``add_parser(subparsers)``
and ``run(args) -> int``; modules import their heavy dependencies inside ``run`` so
``osa --help`` stays fast. Exit status 2 means a usage error or an unreadable input,
with one clear line on stderr.
"""

from __future__ import annotations

import argparse
import importlib
import os
import re
import sys
from collections.abc import Sequence

COMMANDS = ("run", "replay", "simulate", "import", "plan", "upload", "search", "evaluate",
            "train", "vehicle")
EXIT_BROKEN_PIPE = 141  # 128 + SIGPIPE: what a shell reports for `yes | head`

# a value that argparse would take for an option: -33.86,151.21 or -.5
_NEGATIVE_VALUE = re.compile(r"^-\.?\d")


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # one clear line, exit status 2
        self.exit(2, f"osa: error: {message}\n")


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("osa-testbed")
    except PackageNotFoundError:  # run from a source tree that was never installed
        return "unknown (not installed)"


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="osa", description="osa-testbed: find people by their WiFi (FTM).")
    parser.add_argument("--version", action="version", version=f"osa {_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sub.required = True
    for name in COMMANDS:
        try:
            mod = importlib.import_module(f"envs.commands.{name}")
        except ModuleNotFoundError as exc:
            if exc.name == f"envs.commands.{name}":
                continue
            raise
        mod.add_parser(sub)
    return parser


def subcommand_parsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    """The registered subcommands' parsers by name (for help, tests and docs checks)."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def _value_options(parser: argparse.ArgumentParser) -> set[str]:
    """Long options (of every subcommand) that take exactly one value."""
    opts: set[str] = set()
    for p in (parser, *subcommand_parsers(parser).values()):
        for a in p._actions:
            if a.option_strings and a.nargs is None and not isinstance(
                a, argparse._StoreConstAction | argparse._HelpAction | argparse._VersionAction
            ):
                opts |= {s for s in a.option_strings if s.startswith("--")}
    return opts


def join_negative_values(parser: argparse.ArgumentParser, argv: Sequence[str]) -> list[str]:
    """``--center -33.86,151.21`` -> ``--center=-33.86,151.21``: argparse reads a value
    that starts with '-' and is not a plain number as an option and refuses it."""
    takes_value = _value_options(parser)
    out: list[str] = []
    it = iter(range(len(argv)))
    for i in it:
        tok = argv[i]
        if tok == "--":
            out.extend(argv[i:])
            break
        if tok in takes_value and i + 1 < len(argv) and _NEGATIVE_VALUE.match(argv[i + 1]):
            out.append(f"{tok}={argv[i + 1]}")
            next(it, None)
        else:
            out.append(tok)
    return out


def _main(argv: Sequence[str] | None) -> int:
    parser = build_parser()
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv:  # `osa` alone: the usage and the commands, not a bare error
        parser.print_help(sys.stderr)
        return 2
    args = parser.parse_args(join_negative_values(parser, argv))
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print("osa: interrupted", file=sys.stderr)
        return 130


def main(argv: Sequence[str] | None = None) -> int:
    try:
        status = _main(argv)
        sys.stdout.flush()  # a closed pipe shows up here when the output was buffered
    except BrokenPipeError:
        # the reader went away (`osa run | head`): stop quietly, as a killed `cat` would;
        # stdout goes to devnull so the interpreter's final flush cannot raise again
        try:
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
        except (OSError, ValueError):  # stdout without a file descriptor (captured)
            pass
        return EXIT_BROKEN_PIPE
    return status


if __name__ == "__main__":
    sys.exit(main())
