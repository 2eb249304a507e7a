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


def test_a_refused_rerun_file_leaves_no_search_folder(tmp_path, capsys):
    """`osa search -o DIR --rerun RRD` with RRD existing is refused before the flight,
    and leaves nothing behind: not even DIR (docs/cli.md, "Checks come first")."""
    rrd = tmp_path / "old.rrd"
    rrd.write_bytes(b"mine")
    out = tmp_path / "new" / "search"
    status = status_of(["search", "search-random-los", "-o", str(out), "--rerun", str(rrd),
                        "--no-figures", "--no-progress"])
    assert status == 2
    assert one_line(capsys) == f"osa search: {rrd} exists (use --force to replace it)"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["old.rrd"]
    assert rrd.read_bytes() == b"mine"


def test_replay_figures_of_a_refused_log_leave_no_folder(tmp_path, capsys):
    """A log that is not a flight log is refused (exit 2, one line naming it) and the
    --figures folder the command had prepared for it is not left behind."""
    log = tmp_path / "notes.jsonl"
    log.write_text("hello\n")
    figs = tmp_path / "figs"
    assert status_of(["replay", str(log), "--figures", str(figs)]) == 2
    assert one_line(capsys) == (f"osa replay: {log}: not a flight log (no valid record; "
                                "1 line: 1 not_json)")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.jsonl"]


def test_replay_figures_of_a_missing_log_say_no_such_file(tmp_path, capsys):
    """With --figures a missing log is 'no such file', as without: not 'not a regular
    file (save it to a file first)', which is for pipes."""
    missing = tmp_path / "flight.jsonl"
    for extra in ([], ["--figures", str(tmp_path / "figs")]):
        assert status_of(["replay", str(missing), *extra]) == 2
        assert one_line(capsys) == f"osa replay: {missing}: no such file"
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    "argv",
    [
        ["plan", "lawnmower", "--center", "36.7,-4.4", "-o", "{tmp}/new/a.plan",
         "--geojson", "{tmp}/old.txt"],  # an existing --geojson
        ["plan", "lawnmower", "--center", "36.7,-4.4", "-o", "{tmp}/new/a.plan",
         "--radius", "100000"],  # a mission too long
        ["import", "--gnss", "{tmp}/gnss.txt", "--ranges", "{tmp}/rtt.csv",
         "-o", "{tmp}/new/deeper/x.jsonl"],  # missing inputs
        ["vehicle", "paper-apab", "-c", "udpin:127.0.0.1:99999",
         "--log", "{tmp}/new/v.jsonl"],  # a bad URL
        ["evaluate", "search-random-los", "--policies", "lawnmower", "--seeds", "1",
         "-o", "{tmp}/new/rows.csv", "--summary-json", "{tmp}/new/rows.csv"],
        ["search", "search-random-los", "-o", "{tmp}/new/search", "--policy", "ppo:{tmp}/m"],
    ],
    ids=["plan-geojson", "plan-too-long", "import-missing", "vehicle-url",
         "evaluate-same-file", "search-policy"],
)
def test_a_refused_command_leaves_no_output_folder(argv, tmp_path, capsys):
    """Exit status 2 is a request refused before any work: the output folders the
    command had made for it are gone again, other files are untouched."""
    (tmp_path / "old.txt").write_text("mine")
    assert status_of([a.format(tmp=tmp_path) for a in argv]) == 2
    assert one_line(capsys).startswith(f"osa {argv[0]}: ")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["old.txt"]
    assert (tmp_path / "old.txt").read_text() == "mine"


def test_a_refusal_keeps_an_existing_output_folder_and_its_files(tmp_path, capsys):
    """Undoing a refused command's claims never removes what was there before: an
    existing empty folder stays, a reused folder keeps its files and marker."""
    empty = tmp_path / "empty"
    empty.mkdir()
    rrd = tmp_path / "x.rrd"
    rrd.write_text("mine")
    args = ["search", "search-random-los", "--rerun", str(rrd), "--no-figures"]
    assert status_of([*args, "-o", str(empty)]) == 2
    assert list(empty.iterdir()) == []
    reused = tmp_path / "reused"
    reused.mkdir()
    (reused / ".osa-output").write_text("search\n")
    (reused / "report.json").write_text("{}")
    assert status_of([*args, "-o", str(reused)]) == 2
    capsys.readouterr()
    assert sorted(p.name for p in reused.iterdir()) == [".osa-output", "report.json"]
    assert rrd.read_text() == "mine"


def test_simulate_list_separates_every_name_from_its_description(capsys):
    """`osa simulate --list`: one preset a line, `name  description` (two spaces at
    least), the descriptions in one column whatever the length of the names."""
    from sim.scenario import list_scenarios, load_scenario

    assert status_of(["simulate", "--list"]) == 0
    lines = capsys.readouterr().out.splitlines()
    names = list_scenarios()
    assert [line.split("  ", 1)[0] for line in lines] == names
    width = max(map(len, names)) + 2
    assert any(len(n) >= 16 for n in names)  # the names this was wrong for
    assert [line[:width].rstrip() for line in lines] == names
    assert all(line[width - 2:width] == "  " and line[width] != " " for line in lines)
    for name, line in zip(names, lines, strict=True):
        if not name.startswith("site-"):  # a DEM's world takes seconds to build
            assert line[width:] == load_scenario(name).description


def test_search_reusing_its_folder_leaves_no_file_of_the_previous_search(tmp_path, capsys):
    """A folder osa search wrote before is reused with its files replaced: a second
    agent's log of the previous (two-UAV) search and figures not drawn this time
    (--no-figures) are removed, not left for `osa replay out/flight*.jsonl` to fuse
    with this flight; only the files its marker lists as the previous search's go."""
    sc = tmp_path / "short.toml"
    sc.write_text('extends = "search-random-los-rtk"\n[search]\nbudget_s = 10.0\n')
    out = tmp_path / "out"
    out.mkdir()  # as a two-UAV search left it, and a file of the user's own
    (out / ".osa-output").write_text("search\nflight.jsonl\nflight-uav-2.jsonl\nreport.json"
                                     "\ntrajectory.png\nerrors.png\n")
    for name in ("flight.jsonl", "flight-uav-2.jsonl", "report.json", "trajectory.png",
                 "errors.png", "flight-uav-3.jsonl"):
        (out / name).write_text("previous")
    argv = ["search", str(sc), "--policy", "lawnmower", "-o", str(out), "--no-figures",
            "--no-progress", "--json"]
    assert status_of(argv) == 0
    assert capsys.readouterr().err == f"osa search: replacing the files in {out}\n"
    assert sorted(p.name for p in out.iterdir()) == [
        ".osa-output", "flight-uav-3.jsonl", "flight.jsonl", "report.json"]
    assert (out / "flight-uav-3.jsonl").read_text() == "previous"  # not listed: not ours
    assert (out / ".osa-output").read_text() == "search\nflight.jsonl\nreport.json\n"
    # a refused search removes nothing; with --force into another command's folder
    # nothing of that command's is removed
    (out / "flight-uav-2.jsonl").write_text("previous")
    (out / ".osa-output").write_text("search\nflight-uav-2.jsonl\n")
    rrd = tmp_path / "x.rrd"
    rrd.write_text("mine")
    assert status_of([*argv, "--rerun", str(rrd)]) == 2
    assert (out / "flight-uav-2.jsonl").read_text() == "previous"
    (out / ".osa-output").write_text("run\nflight-uav-2.jsonl\n")
    assert status_of([*argv, "--force"]) == 0
    assert (out / "flight-uav-2.jsonl").read_text() == "previous"


@pytest.mark.parametrize("where", ["log", "figure", "rerun"])
def test_an_interrupted_run_leaves_the_previous_files_whole(where, tmp_path, capsys,
                                                            monkeypatch):
    """`osa run` into its own folder, interrupted while it writes the flight log, a
    figure or the rerun recording: the previous file stays as it was (docs/cli.md: files
    are written to a temporary name, then renamed), no temporary file is left."""
    from estimator.logio import LogWriter

    out = tmp_path / "out"
    out.mkdir()
    (out / ".osa-output").write_text("run\n")
    for name in ("flight.jsonl", "report.json", "trajectory.png", "convergence.png"):
        (out / name).write_text("previous")
    if where == "log":
        real_write = LogWriter.write

        def write(self, rec):
            if self.n_lines == 100:
                raise KeyboardInterrupt
            real_write(self, rec)

        monkeypatch.setattr(LogWriter, "write", write)
    elif where == "rerun":
        import envs.viz

        def record_replay(report, logs, path):
            with open(path, "wb") as fh:
                fh.write(b"RRF2 half")
            raise KeyboardInterrupt

        monkeypatch.setattr(envs.viz, "record_replay", record_replay)
        (tmp_path / "r.rrd").write_text("previous")
    else:
        import matplotlib.figure

        def savefig(self, fname, **kwargs):
            with open(fname, "wb") as fh:
                fh.write(b"\x89PNG half")
            raise KeyboardInterrupt

        monkeypatch.setattr(matplotlib.figure.Figure, "savefig", savefig)
    rerun = ["--rerun", str(tmp_path / "r.rrd"), "--force"] if where == "rerun" else []
    status = status_of(["run", "paper-apab", "-o", str(out), "--no-progress", "--mode",
                        "baseline", *rerun])
    assert status == 130
    assert capsys.readouterr().err.splitlines()[-1] == "osa run: interrupted"
    names = sorted(p.name for p in out.iterdir())
    assert names == [".osa-output", "convergence.png", "flight.jsonl", "report.json",
                     "trajectory.png"]
    if where == "log":
        assert (out / "flight.jsonl").read_text() == "previous"
    elif where == "rerun":  # the log, report and figures were complete: replaced
        assert (out / "trajectory.png").read_bytes().startswith(b"\x89PNG")
        assert sorted(p.name for p in tmp_path.iterdir()) == ["out", "r.rrd"]
        assert (tmp_path / "r.rrd").read_text() == "previous"
    else:  # the log and the report were complete: replaced; the figure was not
        assert (out / "flight.jsonl").read_text().count("\n") > 300
        assert (out / "trajectory.png").read_text() == "previous"


@pytest.mark.parametrize("signame", ["SIGTERM", "SIGINT"])
def test_a_vehicle_stopped_while_it_starts_closes_its_log_and_exits_0(signame, tmp_path,
                                                                     capsys, monkeypatch):
    """`osa vehicle ... & kill $!` on a busy machine: the signal comes while the
    vehicle is still loading. It runs until SIGINT or SIGTERM, then closes the log and
    exits 0 (docs/cli.md) whenever the signal comes: here at once, with a whole log."""
    import json
    import os
    import signal

    import envs.vehicle
    from tests.envs.vehicle.helpers import SEARCH_SCENARIO
    from tests.net import free_udp_port

    real_init = envs.vehicle.VirtualVehicle.__init__

    def init(self, *args, **kwargs):  # the signal arrives while the vehicle is built
        os.kill(os.getpid(), getattr(signal, signame))
        real_init(self, *args, **kwargs)

    monkeypatch.setattr(envs.vehicle.VirtualVehicle, "__init__", init)
    log = tmp_path / "phone.jsonl"
    before = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    status = status_of(["vehicle", SEARCH_SCENARIO, "--connection",
                        f"udpin:127.0.0.1:{free_udp_port()}", "--log", str(log)])
    out, err = capsys.readouterr()
    assert (status, err) == (0, "")
    assert out.splitlines()[-1].startswith("osa vehicle: stopped at 0.0 s simulated")
    assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == before
    records = [json.loads(x) for x in log.read_text().splitlines()]
    assert records[0]["type"] == "header" and log.read_text().endswith("\n")


def test_run_reuses_an_output_folder_named_after_its_preset(tmp_path, capsys, monkeypatch):
    """`osa run paper-apab -o paper-apab`, a second time: the folder osa run wrote is
    reused (docs/cli.md), not taken for the preset's scenario file ('holds an input')."""
    monkeypatch.chdir(tmp_path)
    out = tmp_path / "paper-apab"
    out.mkdir()
    (out / ".osa-output").write_text("run\n")  # as the first run left it
    (out / "report.json").write_text("{}")
    status = status_of(["run", "paper-apab", "-o", "paper-apab", "--mode", "baseline",
                        "--no-progress"])
    captured = capsys.readouterr()
    assert status == 0, captured.err
    assert captured.err == "osa run: replacing the files in paper-apab\n"
    assert captured.out.splitlines()[-1] == (
        "wrote paper-apab/flight.jsonl, paper-apab/report.json, paper-apab/trajectory.png, "
        "paper-apab/convergence.png")


def test_a_file_named_like_a_preset_is_said_to_hide_it(tmp_path, capsys, monkeypatch):
    """`osa simulate paper-apab -o paper-apab` (no ending) writes a log named like the
    preset; every later `osa ... paper-apab` in that folder reads the log as the
    scenario. The one line says so, not only 'invalid TOML'."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "paper-apab").write_text('{"type": "header", "format": "osa-log"}\n')
    assert status_of(["simulate", "paper-apab", "-o", "x.jsonl"]) == 2
    assert one_line(capsys) == (
        "osa simulate: paper-apab: invalid TOML: Invalid statement (at line 1, column 1); "
        "the file paper-apab in this folder hides the preset paper-apab (rename the file, "
        "or run osa from another folder)")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["paper-apab"]


@pytest.mark.parametrize("name", ["new/", "old.jsonl/"])
def test_an_output_file_named_with_a_trailing_slash_is_refused(name, tmp_path, capsys):
    """`-o DIR/` names a folder (POSIX: `echo > x/` is an error): osa simulate wrote a
    log file called DIR, or replaced the file old.jsonl with --force."""
    (tmp_path / "old.jsonl").write_text("previous")
    out = f"{tmp_path}/{name}"
    assert status_of(["simulate", "paper-apab", "-o", out, "--force"]) == 2
    assert one_line(capsys) == (f"osa simulate: cannot write {out}: the name ends with '/', "
                                "a folder's (give a file name)")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["old.jsonl"]
    assert (tmp_path / "old.jsonl").read_text() == "previous"


@pytest.mark.parametrize("command", ["simulate", "import", "plan"])
def test_output_is_also_spelled_out_as_osa_run_spells_it(command):
    """`--out` worked as a prefix of `--output`; with prefixes refused it stays, as the
    spelling `osa run`, `osa search`, `osa evaluate` and `osa train` use."""
    from envs.cli import build_parser, subcommand_parsers

    parser = subcommand_parsers(build_parser())[command]
    outs = [a for a in parser._actions if "--output" in a.option_strings]
    assert [a.option_strings for a in outs] == [["-o", "--output", "--out"]]
