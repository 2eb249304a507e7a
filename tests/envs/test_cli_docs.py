"""docs/cli.md documents every registered ``osa`` subcommand and every option of it.

The subcommands are taken from the parser itself (``envs.cli.build_parser``), so a
subcommand or an option added later fails here until docs/cli.md describes it.
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import pytest

from envs.cli import build_parser, subcommand_parsers

DOC = Path(__file__).resolve().parents[2] / "docs" / "cli.md"
PLANNED = ("search", "vehicle", "evaluate", "train")
SUBCOMMANDS = sorted(subcommand_parsers(build_parser()))


def sections() -> dict[str, tuple[str, str]]:
    """``{name: (heading, body)}`` of the ``## `osa NAME ...`` sections."""
    out: dict[str, tuple[str, str]] = {}
    parts = re.split(r"^(## `osa [^\n]*)$", DOC.read_text(encoding="utf-8"), flags=re.M)
    for heading, body in zip(parts[1::2], parts[2::2], strict=True):
        name = re.match(r"## `osa ([\w-]+)", heading).group(1)
        out[name] = (heading, body)
    return out


def _mentioned(token: str, text: str) -> bool:
    """``token`` appears in ``text`` as code: `--seed N`, `--json`, `-o DIR`."""
    return re.search(r"`" + re.escape(token) + r"(?=[\s`=,\]])", text) is not None


def _documentable(action: argparse.Action) -> bool:
    return not isinstance(action, argparse._HelpAction)


def test_the_parser_has_the_built_commands():
    assert {"run", "replay", "simulate", "plan", "upload"} <= set(SUBCOMMANDS)


@pytest.mark.parametrize("name", SUBCOMMANDS)
def test_every_subcommand_has_its_section(name):
    assert name in sections(), f"docs/cli.md has no '## `osa {name} ...`' section"
    heading, _ = sections()[name]
    assert "(planned)" not in heading, f"osa {name} is built: drop '(planned)' in docs/cli.md"


@pytest.mark.parametrize("name", SUBCOMMANDS)
def test_every_option_and_choice_is_documented(name):
    parser = subcommand_parsers(build_parser())[name]
    heading, body = sections()[name]
    text = heading + body
    missing = []
    for action in parser._actions:
        if not _documentable(action):
            continue
        if action.option_strings:
            missing += [s for s in action.option_strings if not _mentioned(s, text)]
        else:  # a positional: by its metavar (or its name in capitals)
            label = action.metavar or action.dest.upper()
            if not _mentioned(label, text):
                missing.append(label)
        for choice in action.choices or ():
            if f"`{choice}`" not in text:
                missing.append(f"{action.dest}={choice}")
    assert not missing, f"osa {name}: not in docs/cli.md: {missing}"


@pytest.mark.parametrize("name", SUBCOMMANDS)
def test_documented_options_exist(name):
    """The first column of the options table names only real options."""
    parser = subcommand_parsers(build_parser())[name]
    known = {s for a in parser._actions for s in a.option_strings}
    _, body = sections()[name]
    rows = [ln.split("|")[1] for ln in body.splitlines() if ln.startswith("| `-")]
    assert rows, f"osa {name}: no options table"
    named = {tok for row in rows for tok in re.findall(r"`(-{1,2}[\w-]+)", row)}
    assert named <= known, f"osa {name}: docs/cli.md lists unknown options {named - known}"


def test_global_options_and_planned_commands():
    text = DOC.read_text(encoding="utf-8")
    parser = build_parser()
    for action in parser._actions:
        for opt in action.option_strings:
            assert _mentioned(opt, text), opt
    secs = sections()
    for name in PLANNED:
        if name not in SUBCOMMANDS:
            heading, body = secs[name]
            assert heading.endswith("(planned)") and "Not built yet" in body


def test_the_checker_sees_a_missing_option():
    """The check can fail: an option that docs/cli.md does not name is caught."""
    assert not _mentioned("--no-such-option", DOC.read_text(encoding="utf-8"))
    assert _mentioned("--seed", "| `--seed N` | random seed |")
    assert not _mentioned("--see", "| `--seed N` | random seed |")
