"""``osa replay`` against docs/cli.md: JSON shape, table, fusion, exit statuses."""

from __future__ import annotations

import gzip
import json
import shutil
import subprocess
import sys

import pytest

from envs.cli import main
from tests.estimator.synth import BSSID, write_flight


@pytest.fixture(scope="module")
def log(tmp_path_factory):
    return write_flight(tmp_path_factory.mktemp("cli") / "f.jsonl", seed=5)


def run_json(capsys, *argv):
    rc = main(["replay", *map(str, argv), "--json"])
    out = capsys.readouterr().out
    return rc, json.loads(out)


def test_json_all_modes(capsys, log):
    rc, js = run_json(capsys, log, "--mode", "all")
    assert rc == 0
    assert [e["mode"] for e in js["estimates"]] == [
        "baseline", "nlos", "empirical-r", "ukf", "ema", "adaptive-r"]
    assert js["logs"] == 1 and js["rejected_lines"] == {}
    for e in js["estimates"]:
        assert e["bssid"] == BSSID and e["status"] == "converged" and e["converged"] is True
        assert e["err_h_m"] < 3.0
        assert e["n_meas"] == e["n_bootstrap"] + e["n_acc"] + e["n_gate"]


def test_json_counts_rejected_lines_and_fuses_logs(capsys, log, tmp_path):
    bad = tmp_path / "bad.jsonl.gz"
    with open(log, "rb") as src, gzip.open(bad, "wb") as dst:
        shutil.copyfileobj(src, dst)
        dst.write(b"{not json\n")
        dst.write(b'{"type":"gnss","t_ns":1}\n')
        dst.write(b'{"type":"gnss","t_ns":-5,"lat":1,"lon":1,"alt_m":1,"acc_m":1}\n')
    rc, js = run_json(capsys, log, bad)
    assert rc == 0
    assert js["logs"] == 2
    assert js["rejected_lines"] == {"not_json": 1, "missing_field": 1, "negative_t_ns": 1}
    assert js["estimates"][0]["n_meas"] == 2 * 720


def test_agl_and_range_offset_options(capsys, log):
    _, a = run_json(capsys, log)
    _, b = run_json(capsys, log, "--range-offset", "0.3")
    # the synthetic ranges carry +0.3 m: removing it moves the bias estimate by ~-0.3 m
    assert b["estimates"][0]["bias_m"] == pytest.approx(a["estimates"][0]["bias_m"] - 0.3,
                                                         abs=0.15)


def test_human_table(capsys, log):
    assert main(["replay", str(log), "--mode", "all"]) == 0
    out = capsys.readouterr().out
    for word in ("Mode", "n_gate", "n_acc", "sigma_H", "err_2D", "TWM", "empirical-r"):
        assert word in out


@pytest.mark.parametrize(
    "argv",
    [["replay", "/no/such/file.jsonl"], ["replay", "LOG", "--mode", "kalman"],
     ["replay", "LOG", "--agl", "nan"], ["replay"]],
)
def test_usage_errors_exit_2(argv, log, capsys):
    argv = [str(log) if a == "LOG" else a for a in argv]
    try:
        rc = main(argv)
    except SystemExit as e:  # argparse usage errors
        rc = e.code
    assert rc == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("osa")


def test_newer_major_version_refused(tmp_path, capsys):
    p = tmp_path / "v2.jsonl"
    p.write_text('{"type":"header","format":"osa-log","version":2}\n')
    assert main(["replay", str(p)]) == 2
    assert "version" in capsys.readouterr().err


def test_console_script_runs(log):
    r = subprocess.run([sys.executable, "-m", "envs.cli", "replay", str(log), "--json"],
                       capture_output=True, text=True, timeout=120, check=False)
    assert r.returncode == 0
    assert json.loads(r.stdout)["estimates"][0]["status"] == "converged"


def test_a_start_utc_without_a_zone_is_utc_whatever_the_machine(capsys, tmp_path) -> None:
    """Two drones flying together: a header's start_utc without a zone ("...T10:12:00",
    as some apps write it) is UTC, as its name says; it was read in the machine's
    local zone, so on a machine at UTC+9 the second drone's ranges were placed 9 h
    before the first's and the fused estimates differed from the same logs with "Z"."""
    import os
    import time

    a = write_flight(tmp_path / "a.jsonl", seed=3, agent="uav-1")
    z = write_flight(tmp_path / "z.jsonl", seed=4, agent="uav-2",
                     start_utc="2026-05-08T10:12:30Z")
    naive = tmp_path / "naive.jsonl"
    naive.write_text(z.read_text().replace('"2026-05-08T10:12:30Z"', '"2026-05-08T10:12:30"'))
    old = os.environ.get("TZ")
    os.environ["TZ"] = "JST-9"  # a POSIX zone string: no tz database needed
    time.tzset()
    try:
        _, want = run_json(capsys, a, z)
        _, got = run_json(capsys, a, naive)
    finally:
        if old is None:
            del os.environ["TZ"]
        else:
            os.environ["TZ"] = old
        time.tzset()
    assert got["estimates"] == want["estimates"]
    assert [e["status"] for e in got["estimates"]] == ["converged"]


def test_an_unreadable_start_utc_is_named_in_the_warning(capsys, log, tmp_path) -> None:
    """A start_utc that is not a time is not 'no start_utc': the warning quotes it."""
    other = tmp_path / "other.jsonl"
    other.write_text(log.read_text().replace('"agent":"uav-1"', '"agent":"uav-2"')
                     .replace('"2026-05-08T10:12:00Z"', '"yesterday"'))
    assert main(["replay", str(log), str(other), "--json"]) == 0
    err = capsys.readouterr().err
    assert "agent uav-2#1: start_utc 'yesterday' is not an ISO 8601 time; assumed to " \
           "start with the earliest agent" in err
    assert "no start_utc" not in err
