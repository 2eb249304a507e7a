"""``osa evaluate`` and envs.evaluate: the same rows serially, on 2 local processes and
on a Dask LocalCluster; the rows' contents against run_search; file round trips; the
summary against a hand computation; the CLI's exit codes and one-line errors.

Searches use a 2-minute budget (a scenario extending search-random-los-rtk) to keep
the module short; every wait on a pool or a cluster is bounded.
"""

from __future__ import annotations

import json
import math
import socket
import sys

import numpy as np
import pytest

from envs.evaluate import (
    COLUMNS,
    SPEC_COLUMNS,
    EpisodeError,
    EvaluationTimeoutError,
    censored_quantile,
    evaluate,
    format_summary,
    read_rows,
    summarise,
    write_rows,
)
from envs.loop import LoopConfig, run_search
from envs.metrics import time_within_s
from envs.policies import load_policy
from sim.scenario import load_scenario
from tests.cli import one_line, status_of

POLICIES = ("lawnmower", "expanding-square", "adaptive")
SEEDS = (0, 1, 2_000_000)  # no answer / heard / heard and converged (adaptive)
SPEC = ("policy", "seed", "bssid", "ended", "flight_time_s", "detected_at_s",
        "localised_at_s", "status", "sigma_h_m", "err_h_m", "err_3d_m")


@pytest.fixture(scope="module")
def short_toml(tmp_path_factory):
    path = tmp_path_factory.mktemp("evaluate") / "short.toml"
    path.write_text('name = "short"\nextends = "search-random-los-rtk"\n\n'
                    "[search]\nbudget_s = 120\n")
    return path


@pytest.fixture(scope="module")
def scenario(short_toml):
    return load_scenario(short_toml)


@pytest.fixture(scope="module")
def serial(scenario):
    return evaluate(scenario, POLICIES, SEEDS, workers=1, example_seeds=SEEDS[:2])


@pytest.fixture(scope="module")
def dask_client():
    distributed = pytest.importorskip("distributed")
    import logging

    cluster = distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                       host="127.0.0.1", dashboard_address=None,
                                       silence_logs=logging.ERROR)
    client = distributed.Client(cluster, timeout=30, set_as_default=False)
    try:
        client.wait_for_workers(2, timeout=60)
        yield client
    finally:
        client.close(timeout=30)
        cluster.close(timeout=30)


def _same_series(a, b) -> bool:
    return [(e.policy, e.seed) for e in a.episodes] == [(e.policy, e.seed) for e in b.episodes] \
        and all(x.series.keys() == y.series.keys()
                and all(np.array_equal(x.series[k], y.series[k], equal_nan=True)
                        for k in x.series)
                for x, y in zip(a.episodes, b.episodes, strict=True))


# ------------------------------------------------------------------ where it ran


@pytest.mark.timeout(180)
def test_two_local_processes_give_the_serial_rows(scenario, serial):
    two = evaluate(scenario, POLICIES, SEEDS, workers=2, task_size=2, task_timeout_s=120,
                   example_seeds=SEEDS[:2])
    assert two.rows == serial.rows
    assert _same_series(two, serial)
    assert [e.track_enu_m is not None for e in two.episodes] == \
        [e.seed in SEEDS[:2] for e in serial.episodes]


@pytest.mark.timeout(180)
def test_a_dask_cluster_gives_the_serial_rows(scenario, serial, dask_client):
    seen = []
    ev = evaluate(scenario, POLICIES, SEEDS, client=dask_client, task_size=4,
                  task_timeout_s=120, progress=lambda k, note: seen.append(k))
    assert ev.rows == serial.rows
    assert _same_series(ev, serial)
    assert seen[-1] == len(POLICIES) * len(SEEDS) and seen == sorted(seen)
    assert len(seen) == 3  # 9 episodes in tasks of 4: three tasks


def test_any_executor_will_do(scenario, serial):
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(2) as pool:
        ev = evaluate(scenario, ["lawnmower"], SEEDS, client=pool, task_size=1,
                      task_timeout_s=60)
    assert ev.rows == [r for r in serial.rows if r["policy"] == "lawnmower"]


def test_rows_are_in_a_fixed_order(serial):
    keys = [(r["policy"], r["seed"]) for r in serial.rows]
    assert keys == [(p, s) for p in POLICIES for s in SEEDS]


# ------------------------------------------------------------------ contents


def test_rows_hold_what_run_search_reports(scenario, serial):
    rows = iter(serial.rows)
    for p in POLICIES:
        for s in SEEDS:
            res = run_search(scenario, load_policy(p, scenario), s, config=LoopConfig())
            for resp in res.responders:
                row = next(rows)
                assert (row["policy"], row["seed"], row["bssid"]) == (p, s, resp["bssid"])
                assert row["ended"] == res.ended
                assert row["flight_time_s"] == round(res.flight_time_s, 3)
                for k in ("detected_at_s", "localised_at_s", "status", "sigma_h_m",
                          "err_h_m", "err_3d_m", "concealment", "r95_h_m"):
                    assert row[k] == resp.get(k), (p, s, k)
                t1 = time_within_s(res.series[resp["bssid"]], 1.0)
                assert row["time_within_1m_s"] == (None if t1 is None else round(t1, 3))
                assert row["scenario"] == "short" and row["mode"] == res.mode
                assert row["replans"] == res.replans and row["budget_s"] == 120.0
    assert next(rows, None) is None
    # the seeds cover the cases the columns must carry: no estimate, and a converged one
    assert any(r["err_h_m"] is None for r in serial.rows)
    assert any(r["status"] == "converged" and r["err_h_m"] is not None for r in serial.rows)


def test_every_policy_meets_the_same_worlds(serial):
    for s in SEEDS:
        worlds = {p: [(r["bssid"], r["concealment"]) for r in serial.rows
                      if r["seed"] == s and r["policy"] == p] for p in POLICIES}
        assert len({tuple(w) for w in worlds.values()}) == 1, s


def test_columns_are_the_spec_s_then_added_ones(serial):
    assert SPEC_COLUMNS == SPEC
    names = [n for n, _ in COLUMNS]
    assert names[:len(SPEC)] == list(SPEC)
    assert not [n for n in names if "wall" in n or "elapsed" in n or "cpu" in n]
    for r in serial.rows:
        assert list(r) == names
        for n, t in COLUMNS:
            assert r[n] is None or type(r[n]) is t, (n, r[n])
    splits = {r["seed"]: r["split"] for r in serial.rows}
    assert splits == {0: "train", 1: "train", 2_000_000: "test"}


def test_several_responders_keep_the_scenario_s_order():
    sc = load_scenario("search-three-mixed")
    import dataclasses

    sc = dataclasses.replace(sc, search=dataclasses.replace(sc.search, budget_s=60.0))
    ev = evaluate(sc, ["lawnmower"], [3], workers=1)
    res = run_search(sc, load_policy("lawnmower", sc), 3)
    assert [r["bssid"] for r in ev.rows] == [r["bssid"] for r in res.responders]
    assert len(ev.rows) == 3


# ------------------------------------------------------------------ files


def test_csv_round_trip(serial, tmp_path):
    path = write_rows(serial.rows, tmp_path / "rows.csv")
    assert read_rows(path) == serial.rows
    header = path.read_text().splitlines()[0].split(",")
    assert header == [n for n, _ in COLUMNS]


def test_parquet_round_trip(serial, tmp_path):
    pq = pytest.importorskip("pyarrow.parquet")
    path = write_rows(serial.rows, tmp_path / "rows.parquet")
    assert read_rows(path) == serial.rows
    schema = pq.read_schema(path)
    assert str(schema.field("seed").type) == "int64"
    assert str(schema.field("err_h_m").type) == "double"


def test_csv_needs_no_pyarrow(serial, tmp_path, monkeypatch, capsys, short_toml):
    for mod in [m for m in sys.modules if m == "pyarrow" or m.startswith("pyarrow.")]:
        monkeypatch.delitem(sys.modules, mod)
    monkeypatch.setitem(sys.modules, "pyarrow", None)  # import pyarrow now fails
    path = write_rows(serial.rows, tmp_path / "rows.csv")
    assert read_rows(path) == serial.rows
    with pytest.raises(ImportError):
        write_rows(serial.rows, tmp_path / "rows.parquet")
    argv = ["evaluate", str(short_toml), "--policies", "lawnmower", "--seeds", "1",
            "--workers", "1", "--no-progress", "-o", str(tmp_path / "r.parquet")]
    assert status_of(argv) == 2
    assert "Parquet needs pyarrow" in one_line(capsys)


def test_unknown_file_type_is_refused(serial, tmp_path):
    with pytest.raises(ValueError, match=r"\.csv or \.parquet"):
        write_rows(serial.rows, tmp_path / "rows.xlsx")


# ------------------------------------------------------------------ summary


def _row(policy, seed, loc, err, t1=None, budget=1000.0):
    return {"policy": policy, "seed": seed, "bssid": "b", "localised_at_s": loc,
            "err_h_m": err, "time_within_1m_s": t1, "budget_s": budget,
            "flight_time_s": budget}


def test_summary_against_a_hand_computation():
    rows = [_row("a", 0, 100.0, 1.0, 50.0), _row("a", 1, 200.0, 2.0),
            _row("a", 2, None, 3.0), _row("a", 3, 400.0, None, 300.0),
            _row("b", 0, None, None), _row("b", 1, None, 0.5)]
    a, b = summarise(rows, ["a", "b"], 1000.0)
    # a: times with the never-localised as the budget: 100, 200, 400, 1000
    assert (a.episodes, a.responders, a.localised) == (4, 4, 3)
    assert a.success_rate == 0.75
    assert a.localised_at_s_median == 300.0 and not a.localised_at_s_median_censored
    assert a.localised_at_s_p90 == pytest.approx(400.0 + 0.7 * 600.0)  # pos 2.7
    assert a.localised_at_s_p90_censored  # it reaches the censored 1000
    assert a.with_estimate == 3
    assert a.err_h_m_median == 2.0 and a.err_h_m_p90 == pytest.approx(2.8)
    assert a.within_1m == 2
    assert a.time_within_1m_s_median == 650.0 and a.time_within_1m_s_median_censored
    assert b.localised == 0 and b.success_rate == 0.0
    assert b.localised_at_s_median == 1000.0 and b.localised_at_s_median_censored
    assert b.err_h_m_median == 0.5 and b.with_estimate == 1
    text = format_summary([a, b])
    assert "3/4  75%" in text and ">=16.7" in text and "5.0" in text and "2.00" in text


def test_summary_of_real_rows_against_numpy(serial):
    for s in summarise(serial.rows, POLICIES, 120.0):
        mine = [r for r in serial.rows if r["policy"] == s.policy]
        loc = [120.0 if r["localised_at_s"] is None else r["localised_at_s"] for r in mine]
        errs = [r["err_h_m"] for r in mine if r["err_h_m"] is not None]
        assert s.success_rate == np.mean([r["localised_at_s"] is not None for r in mine])
        assert s.localised_at_s_median == pytest.approx(np.quantile(loc, 0.5))
        assert s.localised_at_s_p90 == pytest.approx(np.quantile(loc, 0.9))
        if errs:
            assert s.err_h_m_median == pytest.approx(np.median(errs))
            assert s.err_h_m_p90 == pytest.approx(np.quantile(errs, 0.9))
        else:
            assert math.isnan(s.err_h_m_median)


def test_censored_quantile_flags_only_what_reaches_the_budget():
    assert censored_quantile([1.0, 2.0, 3.0], 0.5, 10.0) == (2.0, False)
    assert censored_quantile([1.0, 2.0, None], 0.5, 10.0) == (2.0, False)
    assert censored_quantile([1.0, 2.0, None], 0.75, 10.0) == (6.0, True)
    assert censored_quantile([None], 0.5, 10.0) == (10.0, True)


# ------------------------------------------------------------------ bounded, and failures


@pytest.mark.timeout(120)
def test_a_stalled_pool_stops_within_the_task_timeout(scenario):
    with pytest.raises(EvaluationTimeoutError, match="no task"):
        evaluate(scenario, ["adaptive"], [0, 1], workers=2, task_timeout_s=0.05)


def test_a_failing_episode_names_its_policy_and_seed(scenario, monkeypatch):
    import envs.evaluate as ev

    def boom(*a, **k):
        raise ArithmeticError("bad luck")

    monkeypatch.setattr(ev, "run_search", boom)
    with pytest.raises(EpisodeError, match="policy lawnmower, seed 7: ArithmeticError"):
        evaluate(scenario, ["lawnmower"], [7], workers=1)


def test_bad_arguments_of_the_library(scenario):
    for kw in ({"policies": []}, {"policies": ["a", "a"]}, {"seeds": []}, {"seeds": [-1]},
               {"workers": 0}):
        args = {"policies": ["lawnmower"], "seeds": [0]} | kw
        with pytest.raises(ValueError):
            evaluate(scenario, args.pop("policies"), args.pop("seeds"), **args)


# ------------------------------------------------------------------ figures


def test_figures_are_written(serial, tmp_path):
    import matplotlib.image as mpimg

    from envs.evaluate_plots import FIGURES, plot_evaluation

    paths = plot_evaluation(serial, tmp_path / "figs")
    assert [p.name for p in paths] == list(FIGURES)
    for p in paths:
        img = mpimg.imread(p)
        assert img.shape[0] > 400 and img.shape[1] > 800
        assert img[..., :3].std() > 0.05


def test_censored_ecdf_stops_at_the_share_observed():
    from envs.evaluate_plots import ecdf_censored

    x, y = ecdf_censored([30.0, None, 10.0, None], 100.0)
    assert x.tolist() == [0.0, 10.0, 30.0, 100.0]
    assert y.tolist() == [0.0, 0.25, 0.5, 0.5]


def test_error_bands_hold_the_last_value_and_count_no_estimate_as_infinite(serial):
    from envs.evaluate import EpisodeResult, Evaluation
    from envs.evaluate_plots import error_bands

    nan = math.nan
    s1 = np.array([[5.0, 4.0, 2.0, nan], [10.0, 2.0, 1.0, nan]])  # ended at 10 s
    s2 = np.array([[5.0, nan, nan, nan], [10.0, 8.0, 3.0, nan], [15.0, 6.0, 2.0, nan]])
    eps = [EpisodeResult("p", 0, [], {"b": s1}), EpisodeResult("p", 1, [], {"b": s2})]
    ev = Evaluation("x", ("p",), (0, 1), 20.0, (), eps, decision_period_s=5.0)
    grid, (lo, hi) = error_bands(ev, "p", 1, qs=(0.0, 1.0))
    assert grid.tolist() == [0.0, 5.0, 10.0, 15.0, 20.0]
    assert lo.tolist() == [np.inf, 4.0, 2.0, 2.0, 2.0]
    assert hi.tolist() == [np.inf, np.inf, 8.0, 6.0, 6.0]


# ------------------------------------------------------------------ the CLI


def _argv(short_toml, tmp_path, *extra):
    return ["evaluate", str(short_toml), "--policies", "lawnmower", "--seeds", "2",
            "--workers", "1", "--no-progress", "-o", str(tmp_path / "rows.csv"), *extra]


def test_cli_writes_rows_figures_and_a_summary(short_toml, tmp_path, capsys, serial):
    assert status_of(_argv(short_toml, tmp_path)) == 0
    out = capsys.readouterr().out
    assert "lawnmower" in out and "t_loc med" in out and "wrote " in out
    rows = read_rows(tmp_path / "rows.csv")
    assert rows == [r for r in serial.rows if r["policy"] == "lawnmower" and r["seed"] < 2]
    for name in ("time_to_localise.png", "error_vs_time.png", "trajectories.png"):
        assert (tmp_path / name).stat().st_size > 10_000


def test_cli_json_prints_the_rows(short_toml, tmp_path, capsys, serial):
    argv = _argv(short_toml, tmp_path, "--json", "--no-figures", "--first-seed", "1")
    assert status_of(argv) == 0
    rows = json.loads(capsys.readouterr().out)
    assert [r["seed"] for r in rows] == [1, 2]  # --first-seed 1, two seeds
    assert rows[0] == next(r for r in serial.rows if r["policy"] == "lawnmower"
                           and r["seed"] == 1)
    assert not (tmp_path / "trajectories.png").exists()


def test_cli_split_takes_the_documented_seeds(short_toml, tmp_path, capsys, serial):
    argv = _argv(short_toml, tmp_path, "--json", "--no-figures", "--split", "test")
    argv[argv.index("--seeds") + 1] = "1"
    assert status_of(argv) == 0
    rows = json.loads(capsys.readouterr().out)
    assert rows == [r for r in serial.rows if r["policy"] == "lawnmower" and r["seed"] == 2e6]


@pytest.mark.timeout(120)
def test_cli_on_a_dask_scheduler(short_toml, tmp_path, capsys, serial, dask_client):
    address = dask_client.scheduler_info()["address"]
    argv = ["evaluate", str(short_toml), "--policies", ",".join(POLICIES), "--seeds", "2",
            "--scheduler", address, "--no-progress", "--json", "--no-figures",
            "-o", str(tmp_path / "rows.parquet")]
    assert status_of(argv) == 0
    rows = json.loads(capsys.readouterr().out)
    assert rows == [r for r in serial.rows if r["seed"] < 2]
    assert read_rows(tmp_path / "rows.parquet") == rows


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.parametrize(
    ("change", "needle"),
    [
        ({"scenario": "no-such-scenario"}, "unknown scenario"),
        ({"scenario": "paper-ap1f"}, "not a search scenario"),
        ({"--policies": "lawnmower,zigzag"}, "unknown policy 'zigzag'"),
        ({"--policies": "lawnmower,lawnmower"}, "named twice"),
        ({"--policies": "lawnmower,"}, "empty policy name"),
        ({"--seeds": "0"}, "--seeds: must be >= 1"),
        ({"--seeds": "many"}, "--seeds: not an integer"),
        ({"--first-seed": "-1"}, "argument --first-seed"),
        ({"--split": "test", "--first-seed": "5"}, "not all in the test split"),
        ({"--split": "validation", "--seeds": "1001"}, "not all in the validation split"),
        ({"--split": "holdout"}, "invalid choice"),
        ({"-o": "rows.txt"}, "write .csv or .parquet"),
        ({"-o": "FILE/rows.csv"}, "is not a folder"),
        ({"--mode": "bogus"}, "--mode"),
        ({"--decision-period": "0"}, "--decision-period"),
        ({"--scheduler": "not-an-address"}, "is not an address"),
        ({"--scheduler": "tcp://127.0.0.1:1", "--workers": "2"}, "not allowed with"),
        ({"--workers": "0"}, "--workers: must be >= 1"),
    ],
)
def test_cli_bad_input_is_one_line_and_exit_2(change, needle, short_toml, tmp_path, capsys):
    (tmp_path / "FILE").write_text("x")
    opts = {"scenario": str(short_toml), "--policies": "lawnmower", "--seeds": "1",
            "--no-progress": None, "-o": str(tmp_path / "rows.csv")}
    opts |= change
    if "-o" in change:
        opts["-o"] = str(tmp_path / change["-o"])
    argv = ["evaluate", opts.pop("scenario")]
    for k, v in opts.items():
        argv += [k] if v is None else [k, v]
    assert status_of(argv) == 2
    assert needle in one_line(capsys)
    assert not (tmp_path / "rows.csv").exists()


@pytest.mark.timeout(60)
def test_cli_unreachable_scheduler_fails_within_the_connect_timeout(short_toml, tmp_path,
                                                                   capsys):
    pytest.importorskip("distributed")
    import time

    address = f"tcp://127.0.0.1:{_free_port()}"
    t0 = time.monotonic()
    argv = ["evaluate", str(short_toml), "--policies", "lawnmower", "--seeds", "1",
            "--no-progress", "-o", str(tmp_path / "rows.csv"), "--scheduler", address,
            "--connect-timeout", "2"]
    assert status_of(argv) == 2
    assert time.monotonic() - t0 < 30
    line = one_line(capsys)
    assert f"cannot reach the Dask scheduler at {address} within 2 s" in line


def test_cli_progress_counts_episodes(short_toml, tmp_path, capsys):
    argv = [a for a in _argv(short_toml, tmp_path, "--no-figures") if a != "--no-progress"]
    assert status_of(argv) == 0
    err = capsys.readouterr().err.splitlines()
    assert err == ["osa evaluate: 1/2 episodes lawnmower seed 0",
                   "osa evaluate: 2/2 episodes lawnmower seed 1", "osa evaluate: done"]


def test_cli_notes_a_trained_policy_on_training_seeds(short_toml, tmp_path, capsys,
                                                      monkeypatch):
    import envs.evaluate
    import envs.policies

    real = envs.policies.load_policy

    def fake(spec, scenario=None):  # a stand-in for a trained policy
        return real("lawnmower" if spec == "ppo:model.zip" else spec, scenario)

    monkeypatch.setattr(envs.policies, "load_policy", fake)
    monkeypatch.setattr(envs.evaluate, "load_policy", fake)
    argv = _argv(short_toml, tmp_path, "--no-figures", "--json")
    argv[argv.index("--policies") + 1] = "ppo:model.zip"
    assert status_of(argv) == 0
    assert "training seeds" in one_line(capsys)
    assert status_of([*argv, "--split", "test", "--force"]) == 0  # rows.csv exists now
    assert capsys.readouterr().err == ""


def test_cli_resumes_only_with_the_same_trained_models(short_toml, tmp_path, capsys,
                                                       monkeypatch):
    """A run of ppo:MODEL interrupted, MODEL trained on meanwhile (osa train into the
    same folder): --resume mixed the two models' episodes in one policy's rows; it is
    refused now, and resumes with the model it started with. team:ppo: is noted as a
    trained policy on training seeds too."""
    import envs.evaluate
    import envs.policies

    model = tmp_path / "model"
    model.mkdir()
    for name in ("model.zip", "vecnormalize.pkl", "osa-model.json"):
        (model / name).write_text("first training")
    real = envs.policies.load_policy
    real_episode = envs.evaluate.run_episode

    def fake(spec, scenario=None):  # a stand-in for the trained policy
        return real("lawnmower" if "ppo:" in spec else spec, scenario)

    def stop_at_seed_1(sc, p, s, *a, **k):
        if s == 1:
            raise KeyboardInterrupt
        return real_episode(sc, p, s, *a, **k)

    monkeypatch.setattr(envs.policies, "load_policy", fake)
    monkeypatch.setattr(envs.evaluate, "load_policy", fake)
    monkeypatch.setattr(envs.evaluate, "run_episode", stop_at_seed_1)
    argv = _argv(short_toml, tmp_path, "--no-figures")
    argv[argv.index("--policies") + 1] = f"team:ppo:{model}"
    assert status_of(argv) == 130
    err = capsys.readouterr().err.splitlines()
    assert "training seeds" in err[0] and "interrupted: 1 of 2 episodes" in err[-1]
    monkeypatch.setattr(envs.evaluate, "run_episode", real_episode)
    (model / "vecnormalize.pkl").write_text("trained on")
    assert status_of([*argv, "--resume"]) == 2
    assert "belongs to another run" in capsys.readouterr().err.splitlines()[-1]
    (model / "vecnormalize.pkl").write_text("first training")
    assert status_of([*argv, "--resume"]) == 0
    assert [r["seed"] for r in read_rows(tmp_path / "rows.csv")] == [0, 1]


def test_cli_refuses_a_summary_named_as_the_journal(short_toml, tmp_path, capsys):
    """--summary-json FILE.partial.jsonl was written, said written, then removed with
    the journal at the end (exit 0, the summary lost)."""
    journal = tmp_path / "rows.csv.partial.jsonl"
    assert status_of(_argv(short_toml, tmp_path, "--summary-json", str(journal))) == 2
    assert one_line(capsys) == (f"osa evaluate: --summary-json names the journal of -o "
                                f"({journal}), which is removed at the end")
    assert not journal.exists() and not (tmp_path / "rows.csv").exists()


@pytest.mark.timeout(180)
def test_a_lost_scheduler_is_an_episode_error_that_keeps_the_finished(scenario, dask_client,
                                                                       monkeypatch):
    """The scheduler going away mid-run (its tasks cancelled: what distributed raises,
    FuturesCancelledError, a CancelledError) was an internal error with Dask's
    tracebacks; it is an EpisodeError now (one line, exit 1), the finished kept."""
    import concurrent.futures as cf

    import distributed

    real_wait = distributed.wait
    calls = []

    def lost_after_one(*a, **k):
        calls.append(1)
        if len(calls) > 1:
            raise cf.CancelledError("scheduler-connection-lost")
        return real_wait(*a, **k)

    monkeypatch.setattr(distributed, "wait", lost_after_one)
    kept = []
    with pytest.raises(EpisodeError, match=r"^the Dask scheduler was lost or cancelled the "
                       r"tasks \(CancelledError: scheduler-connection-lost\)$"):
        evaluate(scenario, ("lawnmower",), (0, 1, 2), client=dask_client, task_size=1,
                 on_episode=kept.append)
    assert 1 <= len(kept) <= 3 and len(calls) == 2

