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
from tests.cli import status_of
from tests.estimator.synth import write_flight

ROOT = Path(__file__).resolve().parents[2]


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
    from estimator.modes import PAPER_MODES

    assert main(["replay", str(log), "--mode", text, "--json"]) == 0
    modes = [e["mode"] for e in json.loads(capsys.readouterr().out)["estimates"]]
    want = {"all+robust": [*PAPER_MODES, "robust"], "all,robust": [*PAPER_MODES, "robust"],
            "robust+all": ["robust", *PAPER_MODES], "all+baseline": list(PAPER_MODES)}[text]
    assert modes == want


def test_one_mode_parser_for_run_and_replay(tmp_path, log, capsys):
    from estimator.modes import PAPER_MODES
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


# ------------------------------------------------------------------ osa plan


def test_plan_takes_southern_and_western_coordinates(tmp_path, capsys):
    out = tmp_path / "syd.plan"
    rc = main(["plan", "orbit", "--center", "-33.86,151.21", "--home", "-33.8605,151.2095,3",
               "--keep-out", "-33.8598,151.2104,5", "--heading", "-30", "-o", str(out)])
    assert rc == 0, capsys.readouterr().err
    m = read_mission(out)
    assert m.home == pytest.approx((-33.8605, 151.2095, 3.0))
    assert m.circles[0].lat_deg == pytest.approx(-33.8598)
    wps = [it for it in m.items if it.command == MAV_CMD_NAV_WAYPOINT]
    assert all(abs(it.lat_deg + 33.86) < 0.001 for it in wps)
    west = tmp_path / "w.plan"
    assert main(["plan", "helix", "--center=-12.5,-45.25", "-o", str(west)]) == 0
    assert read_mission(west).home[:2] == pytest.approx((-12.5, -45.25))


def test_plan_help_describes_radius_per_pattern(capsys):
    with pytest.raises(SystemExit):
        main(["plan", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "module doc" not in text
    for words in ("half-width of the search square (lawnmower, expanding-square",
                  "orbit radius (helix, orbit", "outer ring radius (circles",
                  "half the pass length (close-pass", "keep-in square (optimal",
                  "--warn-flight-time", "--max-items"):
        assert words in text, words


def test_mission_files_carry_no_float_noise(tmp_path, capsys):
    for name in ("o.plan", "o.waypoints"):
        out = tmp_path / name
        assert main(["plan", "orbit", "--center", "36.7149,-4.4781", "-o", str(out),
                     "--keep-out", "36.7152,-4.4772,10"]) == 0
        text = out.read_text()
        assert not re.search(r"\d\.\d{8,}", text), re.search(r"\d\.\d{8,}", text)
        m = read_mission(out)
        for it in m.items:
            assert round(it.lat_deg * 1e7) == pytest.approx(it.lat_deg * 1e7, abs=1e-6)
            assert round(it.alt_m, 3) == it.alt_m
    assert "44.99999" not in text and "\t45.0\t" in text
    capsys.readouterr()


# ------------------------------------------------------------------ examples, .gitignore


def test_make_example_log_help_writes_nothing(tmp_path):
    proc = subprocess.run([sys.executable, str(ROOT / "examples" / "make_example_log.py"),
                           "--help"], capture_output=True, text=True, timeout=60,
                          cwd=tmp_path, check=False)
    assert proc.returncode == 0 and proc.stdout.startswith("usage: make_example_log.py")
    assert list(tmp_path.iterdir()) == []


def test_make_example_log_is_reproducible(tmp_path):
    proc = subprocess.run([sys.executable, str(ROOT / "examples" / "make_example_log.py"),
                           str(tmp_path / "ex.jsonl")], capture_output=True, text=True,
                          timeout=120, cwd=ROOT, check=False)
    assert proc.returncode == 0, proc.stderr
    shipped = ROOT / "examples" / "example_flight.jsonl"
    assert (tmp_path / "ex.jsonl").read_bytes() == shipped.read_bytes()


def test_output_folders_are_ignored():
    lines = (ROOT / ".gitignore").read_text().splitlines()
    assert "osa-run/" in lines and "osa-search/" in lines
