"""docs/cli.md taken literally, as a script or an external checker reads it: option
names, exit statuses and what a refused command leaves behind."""

from __future__ import annotations

import pytest

from tests.cli import one_line, status_of


@pytest.mark.parametrize(
    ("argv", "unknown"),
    [
        # `osa search --seed N` habit: was read as --seeds N (N worlds 0..N-1, not seed N;
        # seed 0 makes the old reading fail at once instead of flying)
        (["evaluate", "search-random-los", "--policies", "lawnmower", "--seeds", "30",
          "--seed", "0", "-o", "{tmp}/rows.csv", "--no-figures"], "--seed 0"),
        # a typo of a destructive option
        (["simulate", "paper-apab", "-o", "{tmp}/x.jsonl", "--forc"], "--forc"),
        (["replay", "{tmp}/x.jsonl", "--js"], "--js"),
    ],
)
def test_a_prefix_of_an_option_is_an_unknown_option(argv, unknown, tmp_path, capsys):
    """Options are spelled out in full: a prefix is not silently taken for the option
    it begins (a later added option would change its meaning)."""
    status = status_of([a.format(tmp=tmp_path) for a in argv])
    assert status == 2
    assert one_line(capsys) == f"osa: error: unrecognized arguments: {unknown}"
    assert list(tmp_path.iterdir()) == []
