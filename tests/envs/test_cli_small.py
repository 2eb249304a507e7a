"""The smaller rough edges of the ``osa`` CLI (issue 11), each shown fixed."""

from __future__ import annotations

import io
import json
import re
import subprocess
import sys
from importlib.metadata import version
from pathlib import Path

import pytest

from envs.cli import main
from envs.commands.run import StepProgress
from planner.files import read_mission
from planner.mission import MAV_CMD_NAV_WAYPOINT
from tests.estimator.synth import write_flight

ROOT = Path(__file__).resolve().parents[2]


def status_of(argv: list[str]) -> int:
    try:
        return main(argv)
    except SystemExit as exc:
        return int(exc.code)


@pytest.fixture(scope="module")
def log(tmp_path_factory):
    return write_flight(tmp_path_factory.mktemp("small") / "f.jsonl", seed=5, duration_s=120.0)


# ------------------------------------------------------------------ osa alone, --version


def test_osa_alone_prints_the_usage_and_the_commands(capsys):
    assert status_of([]) == 2
    out, err = capsys.readouterr()
    assert out == "" and err.startswith("usage: osa ")
    for command in ("run", "replay", "simulate", "plan", "upload"):
        assert re.search(rf"^\s+{command}\s+\S", err, re.M), command


def test_osa_version(capsys):
    assert status_of(["--version"]) == 0
    assert capsys.readouterr().out == f"osa {version('osa-testbed')}\n"
