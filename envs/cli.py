"""The ``osa`` command line (docs/cli.md).

Each subcommand lives in ``envs/commands/<name>.py`` with ``add_parser(subparsers)``
and ``run(args) -> int``; modules import their heavy dependencies inside ``run`` so
``osa --help`` stays fast. Exit status 2 means a usage error or an unreadable input,
with one clear line on stderr.

Last resort (docs/cli.md, "Conventions"): whatever goes wrong inside a command ends in
ONE line on stderr and status 70 (EX_SOFTWARE), never a traceback on the terminal;
the traceback, the versions and the command line go to a crash report file (in the
user's cache folder, else the temporary folder) whose path the line gives. SIGTERM
stops a command as Ctrl-C does (its temporary files are removed) with status 143.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import os
import platform
import re
import signal
import sys
import tempfile
import time
import traceback
import warnings
from collections.abc import Sequence
from pathlib import Path

COMMANDS = ("run", "replay", "simulate", "import", "plan", "upload", "search", "evaluate",
            "train", "vehicle")
EXIT_BROKEN_PIPE = 141  # 128 + SIGPIPE: what a shell reports for `yes | head`
EXIT_SOFTWARE = 70  # sysexits.h EX_SOFTWARE: an internal error (a bug), see crash_report
EXIT_INTERRUPTED = 130  # 128 + SIGINT
EXIT_TERMINATED = 143  # 128 + SIGTERM
FLOAT_NOTES = r"(overflow|invalid value|divide by zero|underflow) encountered"
# the libraries whose versions a crash report lists
REPORTED_PACKAGES = ("osa-testbed", "numpy", "scipy", "casadi", "numba", "pymap3d",
                     "pymavlink", "mavsdk", "gymnasium", "matplotlib", "pyarrow")


class Terminated(BaseException):  # a signal, like KeyboardInterrupt
    """SIGTERM arrived: unwind (``finally`` blocks remove temporary files) and stop."""

# a value that argparse would take for an option: -33.86,151.21 or -.5
_NEGATIVE_VALUE = re.compile(r"^-\.?\d")


class _Parser(argparse.ArgumentParser):
    """Options are spelled out in full: argparse's prefix matching would take
    ``osa evaluate --seed 7`` for ``--seeds 7`` and ``--forc`` for ``--force``, and an
    option added later would change what a script's prefix means."""

    def __init__(self, *args, **kwargs) -> None:
        kwargs.setdefault("allow_abbrev", False)
        super().__init__(*args, **kwargs)

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


def _cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "osa-testbed"


def crash_report(exc: BaseException, argv: Sequence[str]) -> Path | None:
    """Write the traceback of ``exc``, the versions and the command line to a new file
    in ``~/.cache/osa-testbed`` (``$XDG_CACHE_HOME``), else the temporary folder;
    return its path (None if nothing could be written)."""
    from importlib.metadata import PackageNotFoundError, version

    versions = []
    for name in REPORTED_PACKAGES:
        try:
            versions.append(f"  {name} {version(name)}")
        except PackageNotFoundError:
            versions.append(f"  {name} (not installed)")
    text = "\n".join([
        "osa crash report: attach this file to a bug report",
        f"time      {time.strftime('%Y-%m-%dT%H:%M:%SZ', time.gmtime())}",
        f"command   osa {' '.join(argv)}",
        f"cwd       {os.getcwd()}",
        f"python    {sys.version.split()[0]} ({sys.executable})",
        f"platform  {platform.platform()}",
        "versions",
        *versions,
        "",
        "".join(traceback.format_exception(exc)),
    ])
    stamp = time.strftime("%Y%m%d-%H%M%S", time.gmtime())
    for folder in (_cache_dir(), Path(tempfile.gettempdir())):
        try:
            folder.mkdir(parents=True, exist_ok=True)
            fd, name = tempfile.mkstemp(prefix=f"osa-crash-{stamp}-", suffix=".txt",
                                        dir=folder)
            with os.fdopen(fd, "w", encoding="utf-8") as fh:
                fh.write(text)
            return Path(name)
        except OSError:
            continue
    return None


def _internal_error(command: str, exc: BaseException, argv: Sequence[str]) -> int:
    """One line for anything a command did not expect, and a crash report beside it."""
    path = crash_report(exc, argv)
    what = ("out of memory" if isinstance(exc, MemoryError)
            else f"internal error: {type(exc).__name__}: {' '.join(str(exc).split())[:200]}")
    where = (f"crash report {path} (please attach it to a bug report)" if path is not None
             else "no crash report could be written")
    print(f"osa{' ' + command if command else ''}: {what}; {where}", file=sys.stderr)
    return EXIT_SOFTWARE


def _main(argv: Sequence[str] | None) -> int:
    from envs.commands._outputs import forget_claims, release_claims

    argv = list(sys.argv[1:] if argv is None else argv)
    command = next((a for a in argv if a in COMMANDS), "")
    try:
        parser = build_parser()
        if not argv:  # `osa` alone: the usage and the commands, not a bare error
            parser.print_help(sys.stderr)
            return 2
        args = parser.parse_args(join_negative_values(parser, argv))
        command = args.command
        with warnings.catch_warnings():
            # NumPy's floating-point notes (an overflow inside a dot product of absurd
            # input) are not for the user: results are checked to be finite where used
            warnings.filterwarnings("ignore", category=RuntimeWarning,
                                    message=FLOAT_NOTES)
            status = int(args.func(args) or 0)
        if status == 2:  # refused before any work: the output folders it made go
            release_claims()
        return status
    except KeyboardInterrupt:
        print(f"osa{' ' + command if command else ''}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except Terminated:
        print(f"osa{' ' + command if command else ''}: terminated", file=sys.stderr)
        return EXIT_TERMINATED
    except BrokenPipeError:
        raise  # main() stops quietly
    except Exception as exc:
        return _internal_error(command or "", exc, argv)
    finally:
        forget_claims()


def _on_sigterm(signum: int, frame: object) -> None:
    raise Terminated


@contextlib.contextmanager
def _sigterm_unwinds():
    """SIGTERM raises :class:`Terminated` in the main thread while a command runs."""
    try:
        previous = signal.signal(signal.SIGTERM, _on_sigterm)
    except ValueError:  # not the main thread (a test runner's worker): leave it
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def main(argv: Sequence[str] | None = None) -> int:
    try:
        with _sigterm_unwinds():
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
    # run the package's module, not this copy named __main__: one Terminated class
    # for the handler and the commands that catch it
    from envs.cli import main as package_main

    sys.exit(package_main())
