"""Writing the flight log: contract, determinism, read-back, and the ``osa simulate`` CLI."""

from __future__ import annotations

import gzip
import json

import numpy as np
import pytest

import sim
from envs.cli import main as osa
from estimator.geodesy import ExactENU
from estimator.logio import read_log
from tests.cli import status_of


@pytest.fixture(scope="module")
def apab_log(tmp_path_factory):
    path = tmp_path_factory.mktemp("logs") / "apab.jsonl"
    return sim.simulate("paper-apab", 4, path), path


def test_same_seed_same_bytes_different_seed_different(tmp_path):
    for suffix in (".jsonl", ".jsonl.gz"):
        a, b, c = (tmp_path / f"{n}{suffix}" for n in "abc")
        sim.simulate("paper-apab", 7, a)
        sim.simulate("paper-apab", 7, b)
        sim.simulate("paper-apab", 8, c)
        assert a.read_bytes() == b.read_bytes()
        assert a.read_bytes() != c.read_bytes()
    plain = (tmp_path / "a.jsonl").read_bytes()
    assert gzip.decompress((tmp_path / "a.jsonl.gz").read_bytes()) == plain


def test_log_reads_back_with_nothing_rejected(apab_log):
    result, path = apab_log
    log = read_log(path)
    assert log.counts.n_rejected == 0
    assert not log.counts.unknown_types and log.counts.unknown_fields == 0
    assert len(log.gnss) == result.n_gnss
    assert len(log.rtt) == result.n_rtt
    assert sum(r.ok for r in log.rtt) == result.ok_counts()["AP_AB"]
    assert log.header.agent == "uav-1" and log.header.agl_m == result.scenario.header_agl_m
    assert log.header.range_offset_m == 0.0 and log.header.start_utc.endswith("Z")
    (truth,) = log.truth
    assert truth.bssid == "a4:77:33:0f:2b:a4" and truth.concealment == "vegetation"


def test_log_lines_follow_the_spec(apab_log):
    _result, path = apab_log
    lines = [json.loads(s) for s in path.read_text().splitlines()]
    assert lines[0]["type"] == "header" and lines[0]["format"] == "osa-log"
    assert lines[0]["config"] == {"agl_m": 45.0, "range_offset_m": 0.0}
    assert sum(ln["type"] == "header" for ln in lines) == 1
    gnss = [ln for ln in lines if ln["type"] == "gnss"]
    rtt = [ln for ln in lines if ln["type"] == "rtt"]
    for g in gnss:
        assert isinstance(g["t_ns"], int) and g["t_ns"] > 0
        assert set(g) == {"type", "t_ns", "lat", "lon", "alt_m", "acc_m", "vacc_m", "fix", "sats"}
        assert round(g["lat"], 9) == g["lat"] and round(g["alt_m"], 3) == g["alt_m"]
    for r in rtt:
        assert r["attempted"] == 8
        if r["status"] == "ok":
            assert isinstance(r["rssi_dbm"], int)
            assert round(r["range_m"], 3) == r["range_m"]
            assert 1 <= r["successful"] <= 8
        else:
            assert r["status"] in ("fail", "no_response")
            assert "range_m" not in r and r["successful"] == 0
    # written in delivery order: sorted by t_ns apart from small writer jitter
    t = np.array([ln["t_ns"] for ln in lines if "t_ns" in ln])
    back = np.diff(t) < 0
    assert back.mean() < 0.05
    assert np.all(np.diff(t)[back] > -20_000_000)  # never more than 20 ms back


def test_gnss_lines_match_the_simulated_positions(apab_log):
    result, path = apab_log
    log = read_log(path)
    frame = ExactENU(
        *[getattr(result.scenario.world.origin, k) for k in ("lat_deg", "lon_deg", "h_m")]
    )
    fixes = sorted(log.gnss, key=lambda g: g.t_ns)
    e, n, u = frame.to_enu(
        np.array([g.lat_deg for g in fixes]),
        np.array([g.lon_deg for g in fixes]),
        np.array([g.alt_m for g in fixes]),
    )
    np.testing.assert_allclose(np.column_stack([e, n, u]), result.gnss.enu_m, atol=2e-3)
    t_ns = np.array([g.t_ns for g in fixes])
    np.testing.assert_array_equal(t_ns, result.gnss_t_ns())
    # truth: the responder on the ground, 0.5 m antenna height
    tr = log.truth[0]
    te, tn, tu = frame.to_enu(tr.lat_deg, tr.lon_deg, tr.alt_m)
    r = result.scenario.world.responders[0]
    ground = float(result.scenario.world.ground_m(r.e_m, r.n_m))
    np.testing.assert_allclose([te, tn, tu], [r.e_m, r.n_m, ground + 0.5], atol=2e-3)


def test_gzip_log_reads_back(tmp_path):
    result = sim.simulate("paper-apaa", 1, tmp_path / "aa.jsonl.gz")
    log = read_log(tmp_path / "aa.jsonl.gz")
    assert log.counts.n_rejected == 0
    assert len(log.rtt) == result.n_rtt > 0 and not any(r.ok for r in log.rtt)


def test_seed_is_checked():
    with pytest.raises(ValueError, match="seed"):
        sim.simulate("paper-apab", -1)
    with pytest.raises(TypeError, match="seed"):
        sim.simulate("paper-apab", 1.5)


def test_cli_writes_a_log_and_summarises(tmp_path, capsys):
    out = tmp_path / "ab.jsonl"
    assert osa(["simulate", "paper-apab", "-o", str(out), "--seed", "4"]) == 0
    line = capsys.readouterr().out.strip()
    assert "\n" not in line
    assert line.startswith("paper-apab seed 4: 0.4 min") and "AP_AB" in line and "ok" in line
    assert out.read_bytes() == sim.simulate("paper-apab", 4, tmp_path / "x.jsonl").path.read_bytes()


def test_cli_says_which_of_several_agents_flies(tmp_path, capsys):
    """A fixed flight with three [[agents]]: one log, the first agent's (before: the
    others were dropped without a word)."""
    sc = tmp_path / "team.toml"
    sc.write_text('extends = "paper-apab"\nname = "team"\n[[agents]]\nname = "uav-a"\n'
                  '[[agents]]\nname = "uav-b"\n[[agents]]\nname = "w"\nkind = "ground"\n')
    out = tmp_path / "t.jsonl"
    assert osa(["simulate", str(sc), "-o", str(out)]) == 0
    err = capsys.readouterr().err
    assert err == "osa simulate: team has 3 agents; the first, uav-a, flies the flight (one log)\n"
    assert json.loads(out.read_text().splitlines()[0])["agent"] == "uav-a"


def test_cli_list(capsys):
    assert osa(["simulate", "--list"]) == 0
    out = capsys.readouterr().out
    for name in ("paper-ap1f", "paper-apab", "paper-apaa", "three-aps", "paper-ap1f-rtk"):
        assert name in out


@pytest.mark.parametrize(
    "argv, match",
    [
        (["simulate", "nope", "-o", "{tmp}/x.jsonl"], "unknown scenario 'nope'"),
        (["simulate", "paper-apab", "-o", "{tmp}/a-file/x.jsonl"], "cannot write"),
        (["simulate", "paper-apab"], "-o LOG is required"),
        (["simulate"], "SCENARIO is required"),
        (["simulate", "paper-apab", "-o", "{tmp}/x.jsonl", "--seed", "-3"],
         "argument --seed: a seed is an integer from 0 to 2^63 - 1"),  # as every command's
    ],
)
def test_cli_errors_are_one_line_exit_2(tmp_path, capsys, argv, match):
    (tmp_path / "a-file").write_text("in the way of a folder")  # missing folders are created
    argv = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    assert status_of(argv) == 2
    err = capsys.readouterr().err
    prefix = "osa: error: " if "--seed" in argv else "osa simulate: "  # argparse's: a seed
    assert err.count("\n") == 1 and match in err and err.startswith(prefix)
