"""Helpers for tests of the ``osa`` command line: its exit status and its one-line errors."""

from __future__ import annotations

from envs.cli import main


def status_of(argv: list[str]) -> int:
    """``osa argv``'s exit status, whether it returns or argparse exits."""
    try:
        return main(argv)
    except SystemExit as exc:
        return int(exc.code)


def one_line(capsys) -> str:
    """What the command wrote on stderr, asserted to be exactly one line, no traceback."""
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.endswith("\n"), err
    assert "Traceback" not in err
    return err.strip()
