"""``osa vehicle`` as a process: it serves ``osa upload``, writes the phone's log as it
runs, stops on SIGTERM or SIGINT with status 0 and a complete log; bad input is one
line on stderr and status 2."""

from __future__ import annotations

import json
import signal
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from envs.cli import main as osa_main
from tests.envs.vehicle.helpers import SEARCH_SCENARIO, until
from tests.net import free_udp_port

ROOT = Path(__file__).resolve().parents[3]


def _start(args: list[str]) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "envs.cli", "vehicle", *args], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _first_line(proc: subprocess.Popen) -> str:
    """The vehicle's first line, an event: it comes when the vehicle is up, however
    long loading takes on a busy machine, or the process ended (its stderr said why).
    A vehicle that hangs silently is stopped by the test's timeout (pyproject)."""
    line = proc.stdout.readline()
    if not line:
        proc.wait()
        raise AssertionError(f"osa vehicle ended ({proc.returncode}) before its first line: "
                             f"{proc.stderr.read()}")
    return line


def _kinds(log: Path) -> list[str]:
    """The record types of the complete lines of a log being written."""
    text = log.read_text() if log.exists() else ""
    return [json.loads(x)["type"] for x in text[: text.rfind("\n") + 1].splitlines()]


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_vehicle_process_serves_upload_and_stops_cleanly(tmp_path: Path, capsys,
                                                          sig: int) -> None:
    port = free_udp_port()
    log = tmp_path / "phone.jsonl"
    proc = _start([SEARCH_SCENARIO, "--connection", f"udpin:127.0.0.1:{port}",
                   "--speedup", "20", "--log", str(log), "--seed", "3"])
    try:
        line = _first_line(proc)
        assert line.startswith("osa vehicle: search-ap1f seed 3: PX4 quadrotor")
        assert "landed and disarmed" in line and "speed-up 20x" in line
        if sig == signal.SIGTERM:
            plan = tmp_path / "m.plan"
            assert osa_main(["plan", "orbit", "--center", "36.7145,-4.4776", "--radius",
                             "30", "--alt", "40", "-o", str(plan)]) == 0
            capsys.readouterr()
            status = osa_main(["upload", str(plan), "--connection",
                               f"udpout:127.0.0.1:{port}", "--timeout", "5"])
            out, err = capsys.readouterr()
            assert (status, err) == (0, ""), err
            assert "uploaded and verified" in out
        # the log grows while it runs (flushed): header, truth, then the phone's records;
        # waited for as an event (the bound is for a vehicle that never writes them)
        assert until(lambda: _kinds(log).count("gnss") > 100 and "rtt" in _kinds(log), 60.0)
        assert _kinds(log)[0] == "header"
        proc.send_signal(sig)
        stdout, stderr = proc.communicate()  # it stops (else the test's timeout says so)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate(timeout=5)
    assert proc.returncode == 0, stderr
    # nothing on stderr but, on a loaded machine, the documented "cannot keep up" notice
    assert [x for x in stderr.splitlines() if "cannot keep up with --speedup" not in x] == []
    assert "osa vehicle: stopped at" in stdout
    text = log.read_text()
    assert text.endswith("\n")
    records = [json.loads(x) for x in text.splitlines()]  # every line whole
    kinds = [r["type"] for r in records]
    assert kinds[0] == "header" and kinds[1:4] == ["truth"] * 3
    assert kinds.count("gnss") > 100 and "rtt" in kinds


def test_vehicle_bad_input_is_one_line_and_status_2(capsys) -> None:
    busy = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    busy.bind(("127.0.0.1", 0))
    port = busy.getsockname()[1]
    try:
        cases = [
            ([SEARCH_SCENARIO, "--connection", "serial:/dev/null"], "unsupported connection"),
            ([SEARCH_SCENARIO, "--connection", "udpin:127.0.0.1:abc"], "is not a number"),
            ([SEARCH_SCENARIO, "--connection", "udpin:127.0.0.1:0"],
             "port 0 is not in 1..65535"),  # (it said "expected HOST:PORT")
            ([SEARCH_SCENARIO, "--connection", "tcpin:0.0.0.0:70000"],
             "port 70000 is not in 1..65535"),
            ([SEARCH_SCENARIO, "--connection", f"udpin:127.0.0.1:{port}"], "cannot listen"),
            ([SEARCH_SCENARIO, "--connection", "udpin:127.0.0.1:1", "--param", "NOPE=1"],
             "unknown parameter NOPE"),
            ([SEARCH_SCENARIO, "--connection", "udpin:127.0.0.1:1", "--param",
              "GF_ACTION=9"], "GF_ACTION = 9 outside"),
            ([SEARCH_SCENARIO, "--connection", "udpin:127.0.0.1:1", "--speedup", "-1"],
             "--speedup"),
            ([SEARCH_SCENARIO], "--connection"),
        ]
        for args, text in cases:
            try:
                status = osa_main(["vehicle", *args])
            except SystemExit as exc:  # argparse
                status = exc.code
            err = capsys.readouterr().err
            assert status == 2, (args, err)
            assert err.count("\n") == 1 and text in err, err
    finally:
        busy.close()
    # a real process: one line, no traceback
    proc = subprocess.run([sys.executable, "-m", "envs.cli", "vehicle", "no-such-scenario",
                           "--connection", "udpin:127.0.0.1:1"],
                          cwd=ROOT, capture_output=True, text=True)  # it ends by itself
    assert proc.returncode == 2 and proc.stdout == ""
    assert proc.stderr.count("\n") == 1
    assert proc.stderr.startswith("osa vehicle: unknown scenario 'no-such-scenario'")


def test_vehicle_log_follows_the_output_rule(tmp_path: Path, capsys) -> None:
    """An existing log needs --force; the scenario file is never the log, not even with
    --force; nothing is written over when refused."""
    import shutil

    log = tmp_path / "phone.jsonl"
    log.write_text("keep\n")
    scenario = tmp_path / "search-ap1f.toml"
    shutil.copy(SEARCH_SCENARIO, scenario)
    before = scenario.read_text()
    busy = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    busy.bind(("127.0.0.1", 0))
    port = busy.getsockname()[1]
    try:
        cases = [
            (["--log", str(log)], "exists (use --force to replace it)"),
            (["--log", str(scenario), "--force"], "is also an input"),
            (["--log", str(tmp_path / "." / scenario.name), "--force"], "is also an input"),
            # --force lets the log through; the next check (the busy port) refuses
            (["--log", str(log), "--force"], "cannot listen"),
        ]
        for extra, text in cases:
            status = osa_main(["vehicle", str(scenario), "--connection",
                               f"udpin:127.0.0.1:{port}", *extra])
            err = capsys.readouterr().err
            assert status == 2, (extra, err)
            assert err.count("\n") == 1 and text in err, err
    finally:
        busy.close()
    assert log.read_text() == "keep\n"
    assert scenario.read_text() == before
