"""The ``osa`` command line (shared/spec/cli.md).

Each subcommand lives in ``envs/commands/<name>.py`` with ``add_parser(subparsers)``
and ``run(args) -> int``; modules import their heavy dependencies inside ``run`` so
``osa --help`` stays fast. Exit status 2 means a usage error or an unreadable input,
with one clear line on stderr.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

COMMANDS = ("run", "replay", "simulate", "plan", "upload", "vehicle")


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # one clear line, exit status 2
        self.exit(2, f"osa: error: {message}\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="osa", description="osa-testbed: find people by their WiFi (FTM).")
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


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print("osa: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
