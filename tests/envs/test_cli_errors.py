"""A stranger's mistakes: each is one clear line on stderr and exit status 2 (or a
warning and a correct result), never a traceback (issue 11)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from envs.cli import EXIT_BROKEN_PIPE, main
from planner.files import read_mission, write_plan
from planner.mission import Mission, MissionItem
from tests.estimator.synth import write_flight

ROOT = Path(__file__).resolve().parents[2]
CENTER = "36.7149,-4.4781"


def status_of(argv: list[str]) -> int:
    """``osa argv``'s exit status, whether it returns or argparse exits."""
    try:
        return main(argv)
    except SystemExit as exc:
        return int(exc.code)


def one_line(capsys) -> str:
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.endswith("\n"), err
    assert "Traceback" not in err
    return err.strip()


# ------------------------------------------------------------------ osa upload


@pytest.fixture
def mission_file(tmp_path) -> Path:
    path = tmp_path / "x.plan"
    item = MissionItem(lat_deg=36.7149, lon_deg=-4.4781, alt_m=45.0)
    write_plan(Mission(items=(item,), home=(36.7149, -4.4781, 0.0)), path)
    return path


def test_pyserial_is_a_runtime_dependency():
    deps = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]
    assert any(d.startswith("pyserial") for d in deps)
    import serial  # noqa: F401 - installed with the project


@pytest.mark.parametrize(
    ("connection", "needle"),
    [
        ("", "empty connection URL"),
        ("garbage", "'garbage' is not a connection URL nor a serial device"),
        ("{tmp}/ttyUSB9", "no serial device {tmp}/ttyUSB9"),
        ("{tmp}/ttyUSB9,57600", "no serial device {tmp}/ttyUSB9"),
        ("serial://{tmp}/ttyUSB9:57600", "no serial device {tmp}/ttyUSB9"),
        ("{tmp}/x.plan", "is not a serial device nor a connection URL"),
        ("/dev/ttyUSB0,fast", "bad baud rate 'fast'"),
        ("bogus://x", "unknown connection scheme 'bogus://'"),
    ],
)
def test_upload_to_a_bad_connection(connection, needle, mission_file, capsys):
    tmp = str(mission_file.parent)
    status = status_of(["upload", str(mission_file), "--connection",
                        connection.format(tmp=tmp), "--timeout", "0.5"])
    err = one_line(capsys)
    assert status == 2
    assert err.startswith("osa upload: ") and needle.format(tmp=tmp) in err


def test_upload_over_serial_without_pyserial(mission_file, capsys, monkeypatch):
    """An existing character device, pyserial missing: one line saying what to install."""
    if not os.path.exists("/dev/null"):
        pytest.skip("needs a character device")
    monkeypatch.setitem(sys.modules, "serial", None)  # import serial -> ModuleNotFoundError
    assert status_of(["upload", str(mission_file), "--connection", "/dev/null"]) == 2
    assert "need pyserial (pip install pyserial)" in one_line(capsys)
