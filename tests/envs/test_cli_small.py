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


# ------------------------------------------------------------------ progress


class _Tty(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_progress_is_plain_lines_when_stderr_is_a_file(tmp_path, capsys):
    assert main(["run", "paper-apaa", "--mode", "baseline", "-o", str(tmp_path / "r")]) == 0
    err = capsys.readouterr().err
    assert "\r" not in err
    assert err.splitlines() == [
        "osa run: 1/3 simulating paper-apaa (seed 0)",
        "osa run: 2/3 replaying 1 modes",
        "osa run: 3/3 drawing figures",
        "osa run: done",
    ]


def test_progress_bar_on_a_terminal_ends_clean():
    tty = _Tty()
    bar = StepProgress("osa run", 3, stream=tty)
    for step in ("simulating", "replaying", "drawing figures"):
        bar.step(step)
    bar.close()
    last = tty.getvalue().split("\r")[-1].rstrip()
    assert last == "osa run: 3/3, done"
    assert " , " not in tty.getvalue()


def test_no_progress_prints_nothing():
    stream = io.StringIO()
    bar = StepProgress("osa run", 2, enabled=False, stream=stream)
    bar.step("a")
    bar.close()
    assert stream.getvalue() == ""


# ------------------------------------------------------------------ --mode all+robust


@pytest.mark.parametrize("text", ["all+robust", "all,robust", "robust+all", "all+baseline"])
def test_replay_takes_the_same_modes_as_run(text, log, capsys):
    from estimator.pipeline import PAPER_MODES

    assert main(["replay", str(log), "--mode", text, "--json"]) == 0
    modes = [e["mode"] for e in json.loads(capsys.readouterr().out)["estimates"]]
    want = {"all+robust": [*PAPER_MODES, "robust"], "all,robust": [*PAPER_MODES, "robust"],
            "robust+all": ["robust", *PAPER_MODES], "all+baseline": list(PAPER_MODES)}[text]
    assert modes == want


def test_one_mode_parser_for_run_and_replay(tmp_path, log, capsys):
    from estimator.pipeline import PAPER_MODES
    from estimator.replay import parse_modes

    assert parse_modes("all+robust") == (*PAPER_MODES, "robust")
    assert parse_modes(" ukf , ema ") == ("ukf", "ema")
    for argv in (["run", "paper-apaa", "-o", str(tmp_path / "r")], ["replay", str(log)]):
        assert status_of([*argv, "--mode", "all+kalman"]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "unknown mode 'all+kalman'" in err
    assert not (tmp_path / "r").exists()


# ------------------------------------------------------------------ UKF has no bias


def test_ukf_rows_have_no_bias(log, capsys):
    assert main(["replay", str(log), "--mode", "baseline,ukf", "--json"]) == 0
    est = {e["mode"]: e for e in json.loads(capsys.readouterr().out)["estimates"]}
    assert "bias_m" in est["baseline"] and "bias_m" not in est["ukf"]
    assert est["ukf"]["sigma_h_m"] > 0  # the rest of the estimate is there
    assert main(["replay", str(log), "--mode", "baseline,ukf"]) == 0
    rows = {ln.split()[0]: ln.split() for ln in capsys.readouterr().out.splitlines()
            if ln.strip().startswith(("baseline", "ukf"))}
    assert rows["ukf"][-1] == "-"
    assert re.fullmatch(r"-?\d+\.\d\d", rows["baseline"][-1])
