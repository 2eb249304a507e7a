"""``osa import`` and ``osa replay --figures`` at the command line (docs/cli.md)."""

from __future__ import annotations

import json

import pytest

from envs.cli import main
from envs.commands._outputs import MARKER
from tests.estimator.importers.writers import (
    NS,
    Flight,
    write_android_csv,
    write_dataflash,
    write_gnsslogger,
)


@pytest.fixture
def files(flight, tmp_path):
    return (write_dataflash(tmp_path / "00000007.BIN", flight),
            write_android_csv(tmp_path / "rtt.csv", flight))


def _import(capsys, gnss, rtt, out, *extra):
    code = main(["import", "--gnss", str(gnss), "--ranges", str(rtt), "-o", str(out),
                 "--no-progress", *extra])
    cap = capsys.readouterr()
    return code, cap.out, cap.err


def test_import_then_replay_with_figures(files, tmp_path, capsys):
    gnss, rtt = files
    out = tmp_path / "flight.jsonl.gz"
    code, text, err = _import(capsys, gnss, rtt, out, "--agl", "45", "--agent", "uav-7")
    assert code == 0 and err == ""
    lines = text.splitlines()
    assert lines[0].startswith(f"gnss: {gnss} (dataflash, GPS[0] with GPA): 3520 fixes read")
    assert any(ln.startswith("  heights: undulation=3520") for ln in lines)
    assert any("1247 results read, 1247 written (299 ok, 948 failed)" in ln for ln in lines)
    assert any(ln.startswith("  overlap: 2025-06-12T10:12:07") for ln in lines)
    assert lines[-1].startswith(f"wrote {out}:")
    # an imported flight is a normal log: replay it, with the figures of osa run
    figs = tmp_path / "figs"
    code = main(["replay", str(out), "--mode", "baseline,refined", "--json",
                 "--figures", str(figs)])
    report = json.loads(capsys.readouterr().out)
    assert code == 0
    refined = [e for e in report["estimates"] if e["mode"] == "refined"]
    assert {e["status"] for e in refined} == {"converged"} and all(
        0 < e["r95_h_m"] < 10 for e in refined)
    pngs = sorted(p.name for p in figs.iterdir())
    assert pngs == [MARKER, "convergence.png", "trajectory.png"]
    assert all((figs / p).stat().st_size > 20_000 for p in pngs if p.endswith(".png"))
    # a folder with other files is not written into (checked before the replay)
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("keep me")
    assert main(["replay", str(out), "--figures", str(tmp_path / "mine")]) == 2
    assert "not empty" in capsys.readouterr().err
    assert (tmp_path / "mine" / "notes.txt").read_text() == "keep me"


def test_json_is_one_object(files, tmp_path, capsys):
    gnss, rtt = files
    code, text, _ = _import(capsys, gnss, rtt, tmp_path / "f.jsonl", "--json")
    assert code == 0
    j = json.loads(text)
    assert text.count("\n") == 1
    assert j["records"] == {"gnss": j["gnss"]["written"], "rtt": 1247, "rtt_ok": 299}
    assert j["time"]["clock"] == "utc" and j["gnss"]["skipped"] == {}
    assert set(j) == {"output", "records", "lines", "start_utc", "gnss", "ranges", "time",
                      "warnings"}


def test_outputs_are_never_overwritten_without_force(files, tmp_path, capsys):
    gnss, rtt = files
    out = tmp_path / "f.jsonl"
    out.write_text("precious\n")
    code, _, err = _import(capsys, gnss, rtt, out)
    assert code == 2 and err.count("\n") == 1 and "use --force" in err
    assert out.read_text() == "precious\n"
    code, _, err = _import(capsys, gnss, rtt, rtt, "--force")  # an input, even with --force
    assert code == 2 and "is also an input" in err
    code, _, err = _import(capsys, gnss, rtt, tmp_path / "f.csv")
    assert code == 2 and ".jsonl or .jsonl.gz" in err
    assert _import(capsys, gnss, rtt, out, "--force")[0] == 0
    assert out.read_text() != "precious\n"


def test_refusals_are_one_line_with_status_2(flight, files, tmp_path, capsys):
    gnss, rtt = files
    later = Flight(flight.header, flight.gnss, flight.rtt, flight.t0_ns,
                   flight.utc0_ns + 7200 * NS)
    rtt_later = write_android_csv(tmp_path / "later.csv", later, elapsed=False)
    out = tmp_path / "f.jsonl"
    for args, want in [
        ((gnss, rtt_later), "do not overlap in time"),
        ((rtt, rtt), "not GNSS data"),
        ((tmp_path / "nothing.bin", rtt), "no such file"),
        ((gnss, rtt, "--gnss-format", "nmea"), "no usable fix"),
        ((gnss, rtt, "--topic", "GPS[x]"), "GPS or GPS[N]"),
    ]:
        code, text, err = _import(capsys, *args[:2], out, *args[2:])
        assert code == 2 and text == "" and err.count("\n") == 1, (args, err)
        assert err.startswith("osa import: ") and want in err, err
        assert not out.exists()
    with pytest.raises(SystemExit) as exit_:
        main(["import", "--gnss", str(gnss), "--ranges", str(rtt), "-o", str(out),
              "--gnss-format", "bogus"])
    assert exit_.value.code == 2 and "invalid choice" in capsys.readouterr().err


def test_warnings_go_to_stderr(flight, tmp_path, capsys):
    gnss = write_dataflash(tmp_path / "old.bin", flight, with_und=False)
    rtt = write_android_csv(tmp_path / "rtt.csv", flight)
    code, text, err = _import(capsys, gnss, rtt, tmp_path / "f.jsonl")
    assert code == 0 and "heights: msl_as_ellipsoid=3520" in text
    assert err.startswith("osa import: warning: ") and "--geoid-offset" in err


def test_the_restarted_phone_is_reported(flight, tmp_path, capsys):
    gnss = write_gnsslogger(tmp_path / "gnss_log.txt", flight)
    rtt = write_android_csv(tmp_path / "rtt.csv", flight, elapsed_shift_ns=-5000 * NS)
    code, text, _ = _import(capsys, gnss, rtt, tmp_path / "f.jsonl")
    assert code == 0
    assert "time: utc clock: joined on UTC: the phone clocks of the two files are of " \
           "different boots" in text and "restarted" in text


def test_the_figures_of_a_flight_without_truth_zoom_on_its_estimates(files, tmp_path,
                                                                     capsys):
    from envs.plots import pyplot, trajectory_figure
    from estimator.replay import ReplayOptions, replay_logs

    gnss, rtt = files
    out = tmp_path / "flight.jsonl"
    assert _import(capsys, gnss, rtt, out, "--agl", "45")[0] == 0
    report = replay_logs([str(out)], ReplayOptions(modes=("refined",)))
    assert not report.truth
    fig = trajectory_figure(report, [out])
    titles = sorted(a.get_title() for a in fig.axes if "(no survey)" in a.get_title())
    assert titles == ["1e:02 (no survey)", "2b:a4 (no survey)"]
    # each zoom panel holds its estimate
    for a in fig.axes:
        if "(no survey)" in a.get_title():
            t = next(t for t in report.tracks if t.bssid.endswith(a.get_title()[:5]))
            x0, x1 = a.get_xlim()
            y0, y1 = a.get_ylim()
            assert x0 < t.estimate.enu_m[0] < x1 and y0 < t.estimate.enu_m[1] < y1
    pyplot().close(fig)


def test_a_refused_log_name_creates_no_folder(files, tmp_path, capsys):
    """``-o new/dir/f.csv`` was refused for its name only after the folders new/dir had
    been created: a refused command left them behind."""
    gnss, rtt = files
    code, text, err = _import(capsys, gnss, rtt, tmp_path / "new" / "dir" / "f.csv")
    assert code == 2 and text == "" and ".jsonl or .jsonl.gz" in err
    assert not (tmp_path / "new").exists()
