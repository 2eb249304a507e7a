"""A user and a hostile file against every command (issue 19, items 1-4): no traceback
from any input, never lost or clobbered work, suspicious data named.

Every case the issue lists has its own test here (the reader's bounds, pipes and
spill files are in tests/estimator/test_reader_bounds.py); property-based tests then
feed random and mutated logs, scenarios, ``.plan`` files and URLs to the commands in
process (``envs.cli.main``) and require exit status 0 or 2 (1 where a vehicle is
asked for and none answers), no traceback, and one line for an error.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import resource
import shutil
import socket
import struct
import threading
import time
import tomllib
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import envs.evaluate
from envs.cli import EXIT_SOFTWARE
from envs.commands._outputs import json_text
from planner.files import write_plan
from planner.mavlink import mavutil  # MAVLink 2 set up before pymavlink is used
from planner.mission import Mission, MissionItem
from tests.cli import one_line, status_of

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "examples" / "example_flight.jsonl"
PRESET = ROOT / "sim" / "scenarios" / "paper-apab.toml"
CENTER = "36.7149,-4.4781"
ESC = "\x1b"
FAST = settings(max_examples=25, deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.function_scoped_fixture,
                                       HealthCheck.too_slow])


def no_traceback(err: str) -> None:
    assert "Traceback" not in err and ESC not in err, err
    assert all(line.startswith("osa") for line in err.splitlines()), err


@pytest.fixture(autouse=True)
def _crash_reports_in_tmp(tmp_path, monkeypatch):
    """Crash reports of these tests go to a temporary cache, not the user's."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))


def _edit_lines(src: Path, dst: Path, edit) -> Path:
    out = []
    for line in src.read_text().splitlines():
        obj = json.loads(line)
        out.append(json.dumps(edit(obj) or obj))
    dst.write_text("\n".join(out) + "\n")
    return dst


@pytest.fixture
def unwritable(tmp_path) -> tuple[Path, list[str]]:
    """An existing folder nobody can write into, and the options that get past the
    'not empty' rule to the write check (root writes through permissions: sysfs)."""
    if os.geteuid() != 0:
        ro = tmp_path / "ro"
        ro.mkdir()
        ro.chmod(0o500)
        yield ro, []
        ro.chmod(0o700)
        return
    probe = Path("/sys/kernel")
    try:
        (probe / ".osa-probe").touch()
    except OSError:
        yield probe, ["--force"]
        return
    pytest.skip("no unwritable folder for root here")


# ============================================================ tracebacks (7 cases)


def test_a_range_of_1e308_is_a_counted_skip(tmp_path, capsys) -> None:
    first_ok = []

    def edit(o):
        if o["type"] == "rtt" and o.get("status") == "ok" and not first_ok:
            first_ok.append(o["t_ns"])
            o["range_m"] = 1e308

    log = _edit_lines(EXAMPLE, tmp_path / "big.jsonl", edit)
    assert status_of(["replay", str(log), "--json"]) == 0
    out, err = capsys.readouterr()
    assert err == ""
    report = json.loads(out)
    assert report["rejected_lines"] == {"bad_range": 1}
    assert report["estimates"][0]["n_meas"] == 959  # the other ranges, estimated
    assert "lat" in report["estimates"][0]


def test_a_huge_truth_altitude_with_json(tmp_path, capsys) -> None:
    def edit(o):
        if o["type"] == "truth":
            o["alt_m"] = 1e300

    log = _edit_lines(EXAMPLE, tmp_path / "truth.jsonl", edit)
    assert status_of(["replay", str(log), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["rejected_lines"] == {"bad_altitude": 1}
    assert "err_h_m" not in report["estimates"][0]  # no truth left to score against


def test_json_output_never_fails_on_a_non_finite_number() -> None:
    obj = {"a": [1.0, float("inf"), {"b": float("nan")}], "c": (1e308, -float("inf"))}
    assert json.loads(json_text(obj)) == {"a": [1.0, None, {"b": None}], "c": [1e308, None]}
    assert json_text({"x": 2.5}, indent=1) == json.dumps({"x": 2.5}, indent=1)


def test_a_scenario_with_a_tiny_spacing_is_refused_before_allocating(tmp_path,
                                                                     capsys) -> None:
    toml = tmp_path / "tiny.toml"
    toml.write_text(PRESET.read_text().replace("speed_mps = 1.3",
                                               "speed_mps = 1.3\npoint_spacing_m = 1e-9"))
    t0 = time.monotonic()
    assert status_of(["simulate", str(toml), "-o", str(tmp_path / "x.jsonl")]) == 2
    line = one_line(capsys)
    assert "would need more than 2000000 path points" in line and "tiny.toml" in line
    assert time.monotonic() - t0 < 60  # refused, not allocated (201 GiB on main)
    assert not (tmp_path / "x.jsonl").exists()
    vehicle = tmp_path / "dt.toml"
    vehicle.write_text('extends = "paper-apab"\n[vehicle]\nsample_dt_s = 1e-7\n')
    assert status_of(["simulate", str(vehicle), "-o", str(tmp_path / "x.jsonl")]) == 2
    assert one_line(capsys).endswith("vehicle: sample_dt_s 1e-07 is below 0.001")
    vehicle.write_text('extends = "paper-ap1f"\n[vehicle]\npath_step_m = 0.001\n')
    assert status_of(["simulate", str(vehicle), "-o", str(tmp_path / "x.jsonl")]) == 2
    assert "vehicle.path_step_m 0.001 m would need" in one_line(capsys)


@pytest.mark.parametrize("args", [["lawnmower", "--spacing", "1e-9"],
                                  ["expanding-square", "--spacing", "1e-6"],
                                  ["lawnmower", "--radius", "1e9"],
                                  ["lawnmower", "--overlap", "0.999999999"]])
def test_a_pattern_that_would_need_absurd_memory_is_refused(tmp_path, capsys, args) -> None:
    assert status_of(["plan", *args, "--center", CENTER, "-o", str(tmp_path / "m.plan")]) == 2
    assert "tracks (more than 100000): widen --spacing or reduce --radius" in one_line(capsys)
    assert not (tmp_path / "m.plan").exists()


@pytest.fixture
def plan_file(tmp_path) -> Path:
    path = tmp_path / "m.plan"
    item = MissionItem(lat_deg=36.7149, lon_deg=-4.4781, alt_m=45.0)
    write_plan(Mission(items=(item,) * 4, home=(36.7149, -4.4781, 0.0)), path)
    return path


@pytest.mark.parametrize("url", ["udpout:127.0.0.1:99999", "udpin:0.0.0.0:99999",
                                 "tcp:127.0.0.1:99999", "udpout://127.0.0.1:99999",
                                 "127.0.0.1:99999", "tcp:127.0.0.1:0", "udpout:a b:14550"])
def test_a_url_with_a_bad_port_or_host(plan_file, capsys, url) -> None:
    assert status_of(["upload", str(plan_file), "-c", url, "--timeout", "0.2"]) == 2
    line = one_line(capsys)
    assert "not a number in 1..65535" in line or "is not a host name" in line


@pytest.mark.parametrize("text", ["[" * 100_000 + "]" * 100_000,
                                  '{"a":' * 50_000 + "1" + "}" * 50_000])
def test_a_plan_of_deeply_nested_brackets(tmp_path, capsys, text) -> None:
    path = tmp_path / "deep.plan"
    path.write_text(text)
    assert status_of(["upload", str(path), "-c", "udpout:127.0.0.1:14550"]) == 2
    assert one_line(capsys) == f"osa upload: {path}: JSON nested too deeply: not a mission file"


class DyingTcpVehicle:
    """A TCP vehicle (pymavlink's encoder on a raw socket) that answers the mission
    protocol and dies after receiving ``die_after`` items: a reset (RST) or a close."""

    def __init__(self, die_after: int, *, reset: bool) -> None:
        self.die_after, self.reset = die_after, reset
        self.listen = socket.create_server(("127.0.0.1", 0))
        self.port = self.listen.getsockname()[1]
        self.items = 0
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        with contextlib.suppress(OSError):
            while self._serve():  # the first connection is the client's reachability probe
                pass

    def _serve(self) -> bool:
        sock, _ = self.listen.accept()
        sock.settimeout(0.05)
        mav = mavutil.mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
        next_hb = 0.0
        while True:
            if time.monotonic() >= next_hb:
                next_hb = time.monotonic() + 0.1
                sock.sendall(mav.heartbeat_encode(2, 12, 0, 0, 3).pack(mav))
            try:
                data = sock.recv(4096)
            except TimeoutError:
                continue
            except OSError:
                return True
            if not data:
                return True
            for m in mav.parse_buffer(data) or []:
                if m.get_type() == "MISSION_COUNT":
                    sock.sendall(mav.mission_request_int_encode(
                        255, 190, 0, m.mission_type).pack(mav))
                elif m.get_type() == "MISSION_ITEM_INT":
                    self.items += 1
                    if self.items >= self.die_after:
                        if self.reset:
                            sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER,
                                            struct.pack("ii", 1, 0))
                        sock.close()
                        self.listen.close()
                        return False
                    sock.sendall(mav.mission_request_int_encode(
                        255, 190, m.seq + 1, m.mission_type).pack(mav))


@pytest.mark.parametrize("reset", [True, False], ids=["reset", "closed"])
def test_a_tcp_vehicle_dying_mid_upload(plan_file, capsys, reset: bool) -> None:
    v = DyingTcpVehicle(2, reset=reset)
    status = status_of(["upload", str(plan_file), "-c", f"tcp:127.0.0.1:{v.port}",
                        "--no-fence"])
    out, err = capsys.readouterr()
    assert (status, out) == (1, "")  # pymavlink's "EOF on TCP socket" is not on stdout
    assert err.count("\n") == 1 and "Traceback" not in err
    assert err.startswith(f"osa upload: NoVehicleError: lost the vehicle on "
                          f"tcp:127.0.0.1:{v.port}: ")
    assert v.items == 2


@pytest.mark.parametrize(("command", "scenario"), [("run", "paper-apab"),
                                                   ("search", "search-random-los")])
def test_an_unwritable_output_folder(unwritable, capsys, command, scenario) -> None:
    folder, extra = unwritable
    before = sorted(p.name for p in folder.iterdir())
    assert status_of([command, scenario, "-o", str(folder), "--no-progress", *extra]) == 2
    line = one_line(capsys)  # refused before any flight: no PermissionError at the end
    assert line.startswith(f"osa {command}: cannot write {folder}: ")
    assert sorted(p.name for p in folder.iterdir()) == before


# ============================================================ lost or clobbered work


def test_simulate_never_writes_over_its_scenario(tmp_path, capsys) -> None:
    toml = tmp_path / "s.toml"
    shutil.copy(PRESET, toml)
    text = toml.read_text()
    for extra in ([], ["--force"]):
        assert status_of(["simulate", str(toml), "-o", str(toml), *extra]) == 2
        assert one_line(capsys) == f"osa simulate: {toml} is also an input: refusing to " \
                                   "write over it"
    os.chdir(tmp_path)
    try:
        assert status_of(["simulate", "s.toml", "-o", "./s.toml", "--force"]) == 2
        capsys.readouterr()
    finally:
        os.chdir(ROOT)
    assert toml.read_text() == text


def test_simulate_refuses_an_existing_log_unless_forced(tmp_path, capsys) -> None:
    log = tmp_path / "ab.jsonl.gz"
    log.write_bytes(b"precious")
    assert status_of(["simulate", "paper-apab", "-o", str(log)]) == 2
    assert one_line(capsys) == f"osa simulate: {log} exists (use --force to replace it)"
    assert log.read_bytes() == b"precious"
    assert status_of(["simulate", "paper-apab", "-o", str(log), "--force"]) == 0
    capsys.readouterr()
    fresh = tmp_path / "fresh.jsonl.gz"
    assert status_of(["simulate", "paper-apab", "-o", str(fresh)]) == 0
    assert log.read_bytes() == fresh.read_bytes()  # written whole, byte-identical
    assert not list(tmp_path.glob(".osa-tmp-*"))


def test_plan_refuses_existing_outputs_unless_forced(tmp_path, capsys) -> None:
    plan, geo = tmp_path / "m.plan", tmp_path / "m.geojson"
    base = ["plan", "orbit", "--center", CENTER, "-o", str(plan), "--geojson", str(geo)]
    geo.write_text("precious")
    assert status_of(base) == 2
    assert one_line(capsys) == f"osa plan: {geo} exists (use --force to replace it)"
    assert not plan.exists() and geo.read_text() == "precious"
    assert status_of([*base, "--force"]) == 0
    assert json.loads(geo.read_text())["type"] == "FeatureCollection"
    capsys.readouterr()
    same = ["plan", "orbit", "--center", CENTER, "-o", str(plan), "--geojson", str(plan)]
    assert status_of([*same, "--force"]) == 2
    assert "is the mission file -o" in one_line(capsys)


@pytest.fixture(scope="module")
def short_search(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("search") / "short.toml"
    path.write_text('name = "short"\nextends = "search-random-los-rtk"\n\n'
                    "[search]\nbudget_s = 60\n")
    return path


def _evaluate(scenario: Path, out: Path, *extra: str) -> list[str]:
    return ["evaluate", str(scenario), "--policies", "lawnmower,adaptive", "--seeds", "2",
            "--workers", "1", "--no-progress", "-o", str(out), *extra]


def test_evaluate_refuses_an_unwritable_output_before_any_episode(
        short_search, unwritable, capsys, monkeypatch) -> None:
    folder, extra = unwritable
    flown = []
    monkeypatch.setattr(envs.evaluate, "run_episode", lambda *a, **k: flown.append(a))
    assert status_of(_evaluate(short_search, folder / "rows.csv", *extra)) == 2
    assert one_line(capsys).startswith(f"osa evaluate: cannot write {folder / 'rows.csv'}")
    assert flown == []


def test_evaluate_refuses_existing_rows_and_figures(short_search, tmp_path, capsys) -> None:
    (tmp_path / "rows.csv").write_text("precious")
    assert status_of(_evaluate(short_search, tmp_path / "rows.csv")) == 2
    assert "rows.csv exists (use --force" in one_line(capsys)
    (tmp_path / "rows.csv").unlink()
    (tmp_path / "trajectories.png").write_text("precious")
    assert status_of(_evaluate(short_search, tmp_path / "rows.csv")) == 2
    assert "trajectories.png exists (use --force" in one_line(capsys)


def test_evaluate_interrupted_then_resumed_gives_the_uninterrupted_rows(
        short_search, tmp_path, capsys, monkeypatch) -> None:
    """Ctrl-C after k = 2 of 4 episodes keeps them in the journal; --resume flies the
    other two only; the rows (and the CSV bytes) equal an uninterrupted run's."""
    whole = tmp_path / "whole" / "rows.csv"
    assert status_of(_evaluate(short_search, whole, "--no-figures")) == 0
    capsys.readouterr()

    real = envs.evaluate.run_episode
    calls = []

    def interrupting(scenario, policy, seed, *a, **k):
        calls.append((policy, seed))
        if len(calls) == 3:
            raise KeyboardInterrupt
        return real(scenario, policy, seed, *a, **k)

    out = tmp_path / "cut" / "rows.csv"
    monkeypatch.setattr(envs.evaluate, "run_episode", interrupting)
    assert status_of(_evaluate(short_search, out, "--no-figures")) == 130
    journal = out.with_name("rows.csv.partial.jsonl")
    assert one_line(capsys) == (f"osa evaluate: interrupted: 2 of 4 episodes kept in {journal}; "
                                "run the same command with --resume to finish")
    assert not out.exists() and len(journal.read_text().splitlines()) == 3
    # with the progress on (off a terminal: a line per 10 % of the episodes), the last
    # line is still the one that says what happened, and the progress adds no second
    calls.clear()
    on = [a for a in _evaluate(short_search, tmp_path / "on" / "rows.csv", "--no-figures")
          if a != "--no-progress"]
    assert status_of(on) == 130
    err = capsys.readouterr().err.splitlines()
    assert err[-1].startswith("osa evaluate: interrupted: 2 of 4 episodes kept in ")
    assert all(line.startswith("osa evaluate: ") and "episodes" in line for line in err), err
    # a new run over the journal must say what it does with it
    assert status_of(_evaluate(short_search, out, "--no-figures")) == 2
    assert "continue it with --resume, or start again with --force" in one_line(capsys)
    assert status_of(_evaluate(short_search, out, "--no-figures", "--seeds", "3",
                               "--resume")) == 2
    assert "belongs to another run" in one_line(capsys)

    monkeypatch.setattr(envs.evaluate, "run_episode", real)
    flown = []
    monkeypatch.setattr(envs.evaluate, "run_episode",
                        lambda sc, p, s, *a, **k: flown.append((p, s)) or real(sc, p, s, *a, **k))
    assert status_of(_evaluate(short_search, out, "--no-figures", "--resume")) == 0
    assert flown == [("lawnmower", 1), ("adaptive", 1)]  # only the missing episodes
    assert out.read_bytes() == whole.read_bytes()
    assert envs.evaluate.read_rows(out) == envs.evaluate.read_rows(whole)
    assert not journal.exists()


def test_evaluate_resume_reads_a_journal_cut_mid_line(short_search, tmp_path, capsys,
                                                      monkeypatch) -> None:
    out = tmp_path / "rows.csv"
    real = envs.evaluate.run_episode

    def stop_after_one(scenario, policy, seed, *a, **k):
        if (policy, seed) != ("lawnmower", 0):
            raise KeyboardInterrupt
        return real(scenario, policy, seed, *a, **k)

    monkeypatch.setattr(envs.evaluate, "run_episode", stop_after_one)
    assert status_of(_evaluate(short_search, out, "--no-figures")) == 130
    journal = out.with_name("rows.csv.partial.jsonl")
    with journal.open("a") as fh:
        fh.write('{"policy": "adaptive", "seed": 0, "rows": [')  # killed while writing
    monkeypatch.setattr(envs.evaluate, "run_episode", real)
    capsys.readouterr()
    assert status_of(_evaluate(short_search, out, "--no-figures", "--resume")) == 0
    rows = envs.evaluate.read_rows(out)
    assert [(r["policy"], r["seed"]) for r in rows][:1] == [("lawnmower", 0)]
    assert len({(r["policy"], r["seed"]) for r in rows}) == 4


def test_evaluate_on_a_full_disk_keeps_the_episodes_and_says_so_in_one_line(
        short_search, tmp_path, capsys, monkeypatch) -> None:
    """The disk fills up after two of four episodes (the third's line half written),
    then again when the rows are written at the end: each time one line (an internal
    error before) that counts the episodes really kept; --resume then flies only the
    missing ones, and the rows equal an uninterrupted run's."""
    whole = tmp_path / "whole" / "rows.csv"
    assert status_of(_evaluate(short_search, whole, "--no-figures")) == 0
    capsys.readouterr()
    out = tmp_path / "rows.csv"
    journal = out.with_name("rows.csv.partial.jsonl")
    real_write = envs.evaluate.EpisodeJournal._write
    written = []

    def full(self, obj):
        if len(written) == 3:  # the header and two episodes fit, a part of the third
            self._fh.write(json.dumps(obj)[:100])
            self._fh.flush()
            raise OSError(errno.ENOSPC, "No space left on device")
        written.append(obj)
        real_write(self, obj)

    monkeypatch.setattr(envs.evaluate.EpisodeJournal, "_write", full)
    assert status_of(_evaluate(short_search, out, "--no-figures")) == 1
    kept = "run the same command with --resume to finish"
    assert one_line(capsys) == (f"osa evaluate: cannot write {journal}: No space left on "
                                f"device (2 of 4 episodes kept in {journal}; {kept})")
    assert not out.exists()
    monkeypatch.setattr(envs.evaluate.EpisodeJournal, "_write", real_write)

    real_rows = envs.evaluate.write_rows

    def no_space(rows, path):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(envs.evaluate, "write_rows", no_space)
    assert status_of(_evaluate(short_search, out, "--no-figures", "--resume")) == 1
    assert one_line(capsys) == (f"osa evaluate: cannot write {out}: No space left on device "
                                f"(all 4 episodes kept in {journal}; run the same command "
                                "with --resume to write them)")
    # the header, four episodes and the cut line (ended, then skipped when read)
    assert not out.exists() and len(journal.read_text().splitlines()) == 6
    monkeypatch.setattr(envs.evaluate, "write_rows", real_rows)

    flown = []
    real_episode = envs.evaluate.run_episode
    monkeypatch.setattr(envs.evaluate, "run_episode",
                        lambda sc, p, s, *a, **k: flown.append((p, s)) or real_episode(sc, p, s,
                                                                                     *a, **k))
    assert status_of(_evaluate(short_search, out, "--no-figures", "--resume")) == 0
    assert flown == []  # the two missing episodes were flown by the run before
    assert out.read_bytes() == whole.read_bytes() and not journal.exists()


def test_train_refuses_a_folder_it_did_not_write(tmp_path, capsys) -> None:
    pytest.importorskip("stable_baselines3")  # the 'rl' extra
    model = tmp_path / "model"
    model.mkdir()
    (model / "notes.txt").write_text("precious")
    assert status_of(["train", "-o", str(model), "--steps", "1"]) == 2
    assert "is not empty and was written by something else" in one_line(capsys)


@pytest.mark.timeout(120)
def test_train_interrupted_mid_step_stops_its_workers_and_keeps_a_marked_model(
        short_search, tmp_path, capsys, monkeypatch) -> None:
    """A signal that lands while the two env workers' replies are read (SIGTERM hung
    there for good: SB3's close waited for the reply already taken; Ctrl-C ended in an
    internal error) stops the workers, exits 130 with one line, and leaves the model
    so far, loadable and marked, never the reused folder's previous model."""
    pytest.importorskip("stable_baselines3")
    import multiprocessing

    from stable_baselines3.common.vec_env import SubprocVecEnv

    from envs.gym.trained import TrainedPolicy

    real = SubprocVecEnv.step_wait
    calls = []

    def cut(self):
        calls.append(1)
        if len(calls) == 20:
            self.remotes[0].recv()  # one worker's reply read, then the signal arrives
            raise KeyboardInterrupt
        return real(self)

    monkeypatch.setattr(SubprocVecEnv, "step_wait", cut)
    model = tmp_path / "model"
    model.mkdir()
    (model / ".osa-output").write_text("train\n")  # a previous training's folder
    (model / "osa-model.json").write_text('{"kind": "search", "steps": 99999}')
    (model / "model.zip").write_text("the previous training's")
    argv = ["train", "--scenario", str(short_search), "--steps", "2000", "--envs", "2",
            "--eval-every", "0", "--checkpoint-every", "0", "--no-progress", "-o", str(model)]
    assert status_of(argv) == 130
    steps = 2 * 19  # 19 whole steps of 2 envs
    # nothing else on stderr: no worker's traceback, no gymnasium note in escapes
    assert capsys.readouterr().err.splitlines() == [
        f"osa train: replacing the files in {model}",
        f"osa train: interrupted: the model after {steps} of 2000 steps is in {model}, "
        "marked \"interrupted\": true in its osa-model.json"]
    assert not [p for p in multiprocessing.active_children() if p.is_alive()]
    meta = json.loads((model / "osa-model.json").read_text())
    assert (meta["interrupted"], meta["steps"], meta["steps_asked"]) == (True, steps, 2000)
    assert TrainedPolicy.load(model).model.num_timesteps == steps


# ============================================================ silently wrong


def test_plan_warns_when_latitude_and_longitude_look_swapped(tmp_path, capsys) -> None:
    out = tmp_path / "m.plan"
    assert status_of(["plan", "orbit", "--center", "-4.4781,36.7149", "--home",
                      "36.7149,-4.4781", "-o", str(out)]) == 2  # 6000 km away: refused
    err = capsys.readouterr().err
    assert err.splitlines()[0] == (
        "osa plan: warning: --home 36.7149,-4.4781 is 6251 km from --center -4.4781,36.7149: "
        "more than one flight (50 km); a latitude and longitude look swapped (did you mean "
        "--home -4.4781,36.7149 or --center 36.7149,-4.4781?)")
    assert status_of(["plan", "orbit", "--center", "151.21,-33.86", "-o", str(out)]) == 2
    assert one_line(capsys).endswith("latitude 151.21 outside [-90, 90] (latitude and "
                                     "longitude swapped? -33.86,151.21)")
    assert status_of(["plan", "orbit", "--center", CENTER, "--home", "36.7155,-4.4770",
                      "-o", str(out)]) == 0
    assert capsys.readouterr().err == ""  # a home 100 m away: no warning


def test_plan_warns_when_the_estimator_will_refuse_the_geometry(tmp_path, capsys) -> None:
    out = tmp_path / "m.plan"
    assert status_of(["plan", "close-pass", "--center", CENTER, "--offset", "2",
                      "--radius", "20", "-o", str(out)]) == 0
    stdout, err = capsys.readouterr()
    kappa = float(stdout.split("condition number ")[1].split(",")[0])
    assert kappa >= 10
    assert err == ("osa plan: warning: the predicted condition number of this flight's "
                   f"geometry is {kappa:.1f}, at or above the estimator's limit 10: it will "
                   "refuse a first position (status weak_geometry); fly around the point "
                   "(circles, orbit, helix) or widen the pass (--offset)\n")
    assert status_of(["plan", "circles", "--center", CENTER, "-o", str(out), "--force"]) == 0
    assert capsys.readouterr().err == ""


def test_terminal_escapes_in_a_log_are_never_printed_raw(tmp_path, capsys) -> None:
    def edit(o):
        if o["type"] == "header":
            o["agent"] = "uav\x1b[2J\x1b]0;owned\x07"
        if o["type"] == "truth":
            o["concealment"] = "open\x1b[31m"

    log = _edit_lines(EXAMPLE, tmp_path / "esc.jsonl", edit)
    (tmp_path / "copy.jsonl").write_bytes(log.read_bytes())
    for extra in ([], ["--json"]):
        assert status_of(["replay", str(log), str(tmp_path / "copy.jsonl"), *extra]) == 0
        out, err = capsys.readouterr()
        assert ESC not in out and "\x07" not in out and ESC not in err
        assert "uav\\x1b[2J" in err  # the same-agent warning names it, escaped
    assert json.loads(out)["estimates"][0]["concealment"] == "open\\x1b[31m"


# ============================================================ the last resort


def test_an_unexpected_error_is_one_line_and_a_crash_report(tmp_path, capsys,
                                                            monkeypatch) -> None:
    import estimator.replay

    def broken(*a, **k):
        raise OverflowError("(34, 'Numerical result out of range')")

    monkeypatch.setattr(estimator.replay, "replay_logs", broken)
    assert status_of(["replay", str(EXAMPLE)]) == EXIT_SOFTWARE
    line = one_line(capsys)
    assert line.startswith("osa replay: internal error: OverflowError: (34, 'Numerical "
                           "result out of range'); crash report ")
    report = Path(line.split("crash report ")[1].split(" (please")[0])
    assert report.parent == tmp_path / "cache" / "osa-testbed"
    text = report.read_text()
    assert f"command   osa replay {EXAMPLE}" in text
    assert "numpy " in text and "Traceback (most recent call last)" in text
    assert "OverflowError" in text

    def no_memory(*a, **k):
        raise MemoryError

    monkeypatch.setattr(estimator.replay, "replay_logs", no_memory)
    assert status_of(["replay", str(EXAMPLE)]) == EXIT_SOFTWARE
    assert one_line(capsys).startswith("osa replay: out of memory; crash report ")


# ============================================================ properties

_LINES = EXAMPLE.read_text().splitlines()
_junk = st.one_of(
    st.sampled_from(["NaN", "1e308", "-1e999", "1" + "0" * 40, "null", "true", '"x"', "[]",
                     "{}", '"\\u001b[2J"', "-0.0", "5e-324", "2e30", "-1"]),
    st.floats(allow_nan=False, allow_infinity=False).map(repr),
    st.integers(-(2**70), 2**70).map(str))


@st.composite
def mutated_logs(draw) -> bytes:
    """The example flight cut, with lines mutated: a value replaced by junk, bytes
    overwritten, lines duplicated, shuffled or dropped."""
    n = draw(st.integers(1, 120))
    start = draw(st.integers(0, len(_LINES) - n))
    lines = list(_LINES[:2]) + list(_LINES[start:start + n])  # header and truth first
    for _ in range(draw(st.integers(0, 6))):
        i = draw(st.integers(0, len(lines) - 1))
        kind = draw(st.sampled_from(["value", "bytes", "dup", "swap", "drop", "garbage"]))
        if kind == "value":
            obj = json.loads(lines[i]) if lines[i].startswith("{") else {}
            if obj:
                key = draw(st.sampled_from(sorted(obj)))
                text = json.dumps(obj)
                lines[i] = text.replace(json.dumps(key) + ": " + json.dumps(obj[key]),
                                        json.dumps(key) + ": " + draw(_junk), 1)
        elif kind == "bytes":
            raw = bytearray(lines[i].encode())
            k = draw(st.integers(0, max(0, len(raw) - 1)))
            raw[k:k + 4] = draw(st.binary(max_size=4))
            lines[i] = raw.decode("utf-8", "surrogateescape")
        elif kind == "dup":
            lines.insert(i, lines[i])
        elif kind == "swap" and len(lines) > 1:
            j = draw(st.integers(0, len(lines) - 1))
            lines[i], lines[j] = lines[j], lines[i]
        elif kind == "drop" and len(lines) > 1:
            del lines[i]
        else:
            lines.insert(i, draw(st.text(max_size=30)))
    return "\n".join(lines).encode("utf-8", "surrogateescape") + b"\n"


@FAST
@given(data=mutated_logs(), json_out=st.booleans())
def test_property_mutated_logs_replay_without_traceback(tmp_path_factory, capsys, data,
                                                         json_out) -> None:
    path = tmp_path_factory.mktemp("logs") / "log.jsonl"
    path.write_bytes(data)
    status = status_of(["replay", str(path), "--mode", "baseline,refined",
                        *(["--json"] if json_out else [])])
    out, err = capsys.readouterr()
    assert status in (0, 2), err
    no_traceback(err)
    if status == 2:
        assert err.count("\n") == 1
    elif json_out:
        json.loads(out)  # valid JSON, whatever the values


_PRESET_TABLE = tomllib.loads(PRESET.read_text())
_NUMERIC_KEYS = sorted(
    (table, key) for table in ("flight", "vehicle", "gnss", "ftm", "clock", "log")
    for key, value in _PRESET_TABLE.get(table, {}).items()
    if isinstance(value, int | float) and not isinstance(value, bool)
) + [("world.origin", k) for k in ("lat_deg", "lon_deg", "h_m")] + [
    ("vehicle", k) for k in ("sample_dt_s", "path_step_m", "crawl_speed_mps", "max_speed_mps")
] + [("flight", "point_spacing_m"), ("ftm", "request_rate_max_hz"), ("gnss", "rate_hz")]
_values = st.one_of(st.sampled_from([0, -1, 1e-9, 1e-300, 1e9, 1e300, -1e300, 10**30]),
                    st.floats(allow_nan=False, allow_infinity=False, width=32))


def _toml_value(v: float) -> str:
    return repr(float(v)) if isinstance(v, float) else str(v)


@pytest.fixture
def memory_cap():
    """At most 2 GiB more address space while a test runs in this process: a runaway
    allocation is a MemoryError (a failure) instead of the machine's memory."""
    with open("/proc/self/status") as fh:
        size = next(int(x.split()[1]) * 1024 for x in fh if x.startswith("VmSize:"))
    soft, hard = resource.getrlimit(resource.RLIMIT_AS)
    cap = size + (2 << 30)
    resource.setrlimit(resource.RLIMIT_AS, (cap if hard < 0 else min(cap, hard), hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_AS, (soft, hard))


@settings(FAST, max_examples=12)
@given(edits=st.lists(st.tuples(st.sampled_from(_NUMERIC_KEYS), _values), min_size=1,
                      max_size=3))
def test_property_mutated_scenarios_simulate_without_traceback(tmp_path_factory, capsys,
                                                                memory_cap, edits) -> None:
    tables: dict[str, dict[str, float]] = {}
    for (table, key), value in edits:
        tables.setdefault(table, {})[key] = value
    text = 'name = "fuzz"\nextends = "paper-apab"\n' + "".join(
        f"[{t}]\n" + "".join(f"{k} = {_toml_value(v)}\n" for k, v in kv.items())
        for t, kv in tables.items())
    folder = tmp_path_factory.mktemp("scen")
    (folder / "s.toml").write_text(text)
    status = status_of(["simulate", str(folder / "s.toml"), "-o", str(folder / "s.jsonl")])
    err = capsys.readouterr().err
    assert status in (0, 2), (text, err)
    no_traceback(err)
    assert status == 0 or err.count("\n") == 1


@st.composite
def mutated_plans(draw) -> str:
    item = {"type": "SimpleItem", "command": 16, "frame": 3, "autoContinue": True,
            "params": [0, 0, 0, None, 36.7149, -4.4781, 45]}
    plan = {"fileType": "Plan", "version": 1, "groundStation": "x",
            "mission": {"version": 2, "plannedHomePosition": [36.7149, -4.4781, 0],
                        "items": [dict(item) for _ in range(draw(st.integers(0, 3)))]},
            "geoFence": {"version": 2, "polygons": [], "circles": []},
            "rallyPoints": {"version": 2, "points": []}}
    text = json.dumps(plan)
    for _ in range(draw(st.integers(1, 4))):
        how = draw(st.sampled_from(["junk", "cut", "nest", "bytes"]))
        if how == "junk":
            tokens = [t for t in ("36.7149", "-4.4781", "45", "16", "true", "null", "2", "[]")
                      if t in text]
            if tokens:
                text = text.replace(draw(st.sampled_from(tokens)), draw(_junk), 1)
        elif how == "cut":
            text = text[:draw(st.integers(0, len(text)))]
        elif how == "nest":
            depth = draw(st.sampled_from([10, 1000, 30_000]))
            text = text.replace("[]", "[" * depth + "]" * depth, 1)
        else:
            k = draw(st.integers(0, max(0, len(text) - 1)))
            text = text[:k] + draw(st.text(max_size=4)) + text[k + 4:]
    return text


@FAST
@given(text=mutated_plans(), suffix=st.sampled_from([".plan", ".waypoints"]))
def test_property_mutated_mission_files_upload_without_traceback(tmp_path_factory, capsys,
                                                                  text, suffix) -> None:
    path = tmp_path_factory.mktemp("plans") / f"m{suffix}"
    path.write_text(text, errors="surrogateescape")
    # a device that is not there: every mission that reads is then refused at the URL
    status = status_of(["upload", str(path), "-c", "serial:///dev/osa-no-such-tty:57600"])
    err = capsys.readouterr().err
    assert status == 2, err
    assert err.count("\n") == 1
    no_traceback(err)


_urls = st.builds(
    lambda scheme, host, port: f"{scheme}{host}{port}",
    st.sampled_from(["udpout:", "udpin:", "tcp:", "tcpin:", "udp:", "udpout://", "udpin://",
                     "tcp://", "udp://", "serial://", "http://", "", "mcast:"]),
    st.one_of(st.sampled_from(["127.0.0.1", "127.0.0.9", "0.0.0.0", "", "a b", "ex$mple",
                               "[::1]", "localhost:1", "\x1b[2J", "-h"]),
              st.text(max_size=6)),
    st.one_of(st.sampled_from([":0", ":1", ":65535", ":65536", ":99999", ":-1", ":abc", "",
                               ":1e3", ": 80", ":١٢"]),
              st.integers(-5, 70_000).map(lambda p: f":{p}")))


@settings(FAST, max_examples=20)
@given(url=_urls)
def test_property_urls_upload_without_traceback(plan_file, capsys, url) -> None:
    """No vehicle listens anywhere: a URL is refused (2) or finds no vehicle (1)."""
    status = status_of(["upload", str(plan_file), "-c", url, "--timeout", "0.2",
                        "--message-timeout", "0.05", "--retries", "0"])
    out, err = capsys.readouterr()
    assert status in (1, 2), err
    assert out == "" and err.count("\n") == 1
    no_traceback(err)
