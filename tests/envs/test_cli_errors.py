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

from envs.cli import EXIT_BROKEN_PIPE
from planner.files import read_mission, write_plan
from planner.mission import Mission, MissionItem
from tests.cli import one_line, status_of
from tests.estimator.synth import write_flight

ROOT = Path(__file__).resolve().parents[2]
CENTER = "36.7149,-4.4781"


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


# ------------------------------------------------------------------ osa run


def test_run_negative_seed_leaves_no_folder(tmp_path, capsys):
    out = tmp_path / "out"
    assert status_of(["run", "paper-apaa", "--seed", "-1", "-o", str(out)]) == 2
    assert "--seed" in one_line(capsys) and not out.exists()


def test_run_checks_the_rerun_path_before_the_job(tmp_path, capsys):
    out = tmp_path / "out"
    assert status_of(["run", "paper-apaa", "-o", str(out), "--rerun",
                      "/nonexistent/dir/x.rrd"]) == 2
    err = one_line(capsys)
    assert err == "osa run: cannot write /nonexistent/dir/x.rrd: no such directory /nonexistent/dir"
    assert not out.exists()  # nothing simulated, no empty folder
    assert status_of(["run", "paper-apaa", "-o", str(out), "--rerun", str(tmp_path)]) == 2
    assert "is a directory" in one_line(capsys) and not out.exists()


def _closed_pipe_run(argv: list[str]) -> subprocess.CompletedProcess:
    """``osa argv`` writing into a pipe whose reader is already gone (``| head``)."""
    r, w = os.pipe()
    os.close(r)
    try:
        return subprocess.run([sys.executable, "-m", "envs.cli", *argv], stdout=w,
                              stderr=subprocess.PIPE, text=True, timeout=120, cwd=ROOT,
                              check=False)
    finally:
        os.close(w)


def test_simulate_list_into_a_closed_pipe():
    proc = _closed_pipe_run(["simulate", "--list"])
    assert proc.stderr == ""
    assert proc.returncode == EXIT_BROKEN_PIPE


def test_run_into_a_closed_pipe(tmp_path):
    proc = _closed_pipe_run(["run", "paper-apaa", "--mode", "baseline", "--no-progress",
                             "-o", str(tmp_path / "out")])
    assert proc.stderr == ""
    assert proc.returncode == EXIT_BROKEN_PIPE
    assert (tmp_path / "out" / "report.json").exists()  # the job itself ran


def test_head_reads_the_first_line_quietly(tmp_path):
    proc = subprocess.run(f"{sys.executable} -m envs.cli simulate --list | head -1",
                          shell=True, capture_output=True, text=True, timeout=120, cwd=ROOT,
                          check=False)
    assert proc.stderr == "" and proc.returncode == 0
    assert proc.stdout.startswith("paper-ap1f ") and proc.stdout.count("\n") == 1


# ------------------------------------------------------------------ osa plan: mission size


@pytest.mark.timeout(60)
@pytest.mark.parametrize(("radius", "hours"), [(1000, "7.2 h"), (10000, "691.6 h"),
                                               (100000, "68826.8 h")])
def test_plan_refuses_a_mission_beyond_one_flight(radius, hours, tmp_path, capsys):
    out = tmp_path / "big.plan"
    status = status_of(["plan", "lawnmower", "--center", CENTER, "--radius", str(radius),
                        "-o", str(out)])
    err = one_line(capsys)
    assert status == 2 and not out.exists()
    assert err.startswith(f"osa plan: lawnmower --radius {radius} is {hours} of flight (")
    assert "beyond the 2 h limit" in err and "km at 5 m/s" in err and "items" in err


def test_plan_warns_above_the_flight_time_and_writes(tmp_path, capsys):
    out = tmp_path / "lm.plan"
    argv = ["plan", "lawnmower", "--center", CENTER, "--radius", "300", "-o", str(out)]
    assert status_of(argv) == 0
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert err.startswith("osa plan: warning: lawnmower --radius 300 is 43 min of flight")
    assert "longer than --warn-flight-time 30 min" in err
    assert len(read_mission(out).items) > 10
    assert status_of([*argv, "--warn-flight-time", "45", "--force"]) == 0  # lm.plan exists
    assert capsys.readouterr().err == ""


def test_plan_refuses_more_items_than_a_vehicle_holds(tmp_path, capsys):
    argv = ["plan", "helix", "--center", CENTER, "--turns", "40", "-o", str(tmp_path / "h.plan")]
    assert status_of(argv) == 2
    err = one_line(capsys)
    assert "at least 631 items" in err and "more than the 500 items a vehicle holds" in err
    assert status_of([*argv, "--max-items", "2000"]) == 0  # an ArduPilot with an SD card


def test_plan_refuses_a_long_optimal_horizon(tmp_path, capsys):
    argv = ["plan", "optimal", "--center", CENTER, "--time-budget", "9000",
            "-o", str(tmp_path / "o.plan")]
    assert status_of(argv) == 2
    assert "reduce --time-budget" in one_line(capsys)


# ------------------------------------------------------------------ osa replay: not a log


@pytest.mark.parametrize(
    ("content", "detail"),
    [
        (b"", "empty"),
        (bytes(range(256)) * 8, "not_utf8"),
        (json.dumps({"type": "FeatureCollection", "features": []}).encode(),
         "1 line: 1 of unknown type 'FeatureCollection'"),
        (b"{not json\n\n[1, 2]\n", "2 lines: 1 not_json, 1 not_object"),
    ],
    ids=["empty", "random-bytes", "geojson", "garbage-json"],
)
def test_replay_of_a_file_that_is_not_a_log(content, detail, tmp_path, capsys):
    path = tmp_path / "f.jsonl"
    path.write_bytes(content)
    assert status_of(["replay", str(path), "--json"]) == 2
    err = one_line(capsys)
    assert err.startswith(f"osa replay: {path}: not a flight log (no valid record; ")
    assert detail in err


def test_replay_header_errors_name_the_file(tmp_path, capsys):
    v3 = tmp_path / "v3.jsonl"
    v3.write_text('{"type":"header","format":"osa-log","version":3}\n')
    assert status_of(["replay", str(v3)]) == 2
    assert one_line(capsys) == (f"osa replay: {v3}: log format version 3 is newer than this "
                                "reader (version 1)")
    other = tmp_path / "other.jsonl"
    other.write_text('{"type":"header","format":"ulog"}\n')
    assert status_of(["replay", str(other)]) == 2
    assert one_line(capsys) == f"osa replay: {other}: not an osa-log file (header format 'ulog')"


def test_replay_of_the_same_log_twice_is_refused(tmp_path, capsys):
    log = write_flight(tmp_path / "f.jsonl", seed=3, duration_s=30.0)
    alias = tmp_path / "sub" / ".." / "f.jsonl"
    (tmp_path / "sub").mkdir()
    assert status_of(["replay", str(log), str(alias), "--json"]) == 2
    assert one_line(capsys) == (f"osa replay: {alias}: given twice (a log fused with itself "
                                "counts every range twice)")


def test_replay_of_two_logs_of_one_agent_warns(tmp_path, capsys):
    a = write_flight(tmp_path / "a.jsonl", seed=3, duration_s=30.0)
    b = tmp_path / "b.jsonl"
    b.write_bytes(a.read_bytes())  # a copy: same header, same agent
    assert status_of(["replay", str(a), str(b), "--json"]) == 0
    out, err = capsys.readouterr()
    assert json.loads(out)["logs"] == 2
    assert err == (f"osa replay: warning: {b} and {a} name the same agent 'uav-1': fused as "
                   "two logs (if one is a copy of the other, every range counts twice)\n")
