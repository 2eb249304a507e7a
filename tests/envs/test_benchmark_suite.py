"""The benchmark suite's evaluation: the timed-challenge metrics against hand-made
series, the paired tests against a hand computation, the ``random`` policy (seeded,
deterministic, uniform over the env's actions), and random below adaptive on a tiny
suite run."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from gymnasium import spaces

from envs.evaluate import (
    compare_pairs,
    format_challenge,
    format_paired,
    paired_tests,
    rows_of,
    summarise,
    summary_json,
)
from envs.loop import SearchResult, SeriesPoint, run_search
from envs.metrics import all_localised_at_s, episode_error_m, error_at_flight_s, within
from envs.policies import RandomPolicy, load_policy, uniform_action
from sim.scenario import load_scenario


def _pt(t, err):
    return SeriesPoint(t_s=t, status="tracking", sigma_h_m=1.0, r95_h_m=2.0, err_h_m=err)


# ------------------------------------------------------------------ metrics
def test_error_at_a_flight_time_from_a_hand_made_series():
    series = [_pt(5.0, None), _pt(170.0, 9.0), _pt(180.0, 4.0), _pt(185.0, 3.0),
              _pt(590.0, 2.5), _pt(600.0, 1.5), _pt(605.0, 1.0)]
    assert error_at_flight_s(series, 180.0, 700.0, 0.8) == 4.0  # the sample at 3 min
    assert error_at_flight_s(series, 600.0, 700.0, 0.8) == 1.5
    assert error_at_flight_s(series, 100.0, 700.0, 0.8) is None  # no estimate yet
    assert error_at_flight_s(series, 4.0, 700.0, 0.8) is None  # before any sample
    # a search that ended (at 400 s) keeps its final estimate at 10 min
    assert error_at_flight_s(series[:4], 600.0, 400.0, 2.2) == 2.2
    assert error_at_flight_s([], 600.0, 400.0, None) is None
    assert [within(e, 2.0) for e in (None, 1.99, 2.0, 2.01)] == [0, 1, 1, 0]
    assert all_localised_at_s([100.0, 340.5, 20.0]) == 340.5
    assert all_localised_at_s([100.0, None]) is None and all_localised_at_s([]) is None
    assert episode_error_m([1.0, None, 80.0, 3.0]) == pytest.approx((1 + 50 + 50 + 3) / 4)


def _result(responders, series, flight_time_s=700.0):
    return SearchResult(policy="p", mode="refined", seed=3, ended="budget",
                        flight_time_s=flight_time_s, path_length_m=1000.0, replans=0,
                        responders=responders, log=None, logs=[], refused_plans=0,
                        series=series, scenario="s")


def test_rows_carry_the_timed_challenge():
    resp = [
        {"bssid": "a", "status": "converged", "localised_at_s": 300.0, "err_h_m": 1.5},
        {"bssid": "b", "status": "converged", "localised_at_s": 650.0, "err_h_m": 4.0},
        {"bssid": "c", "status": "tracking", "localised_at_s": None, "err_h_m": 7.0},
    ]
    series = {"a": [_pt(175.0, 6.0), _pt(180.0, 5.0), _pt(600.0, 1.4)],
              "b": [_pt(400.0, 9.0), _pt(600.0, 4.5)],
              "c": [_pt(180.0, 30.0), _pt(600.0, 7.5)]}
    rows = rows_of(_result(resp, series), "p", 3, 1200.0)
    got = [(r["err_h_3min_m"], r["err_h_10min_m"], r["within_2m"], r["within_5m"],
            r["all_localised_at_s"]) for r in rows]
    assert got == [(5.0, 1.4, 1, 1, None), (None, 4.5, 0, 1, None), (30.0, 7.5, 0, 0, None)]
    resp[2]["localised_at_s"] = 690.0
    rows = rows_of(_result(resp, series), "p", 3, 1200.0)
    assert {r["all_localised_at_s"] for r in rows} == {690.0}


def _rows(policy, per_seed, budget=1200.0):
    """Rows of one policy: per seed a list of (localised_at_s, err_h_m)."""
    out = []
    for seed, resp in per_seed.items():
        t_all = all_localised_at_s([t for t, _ in resp])
        for i, (t, e) in enumerate(resp):
            out.append({"policy": policy, "seed": seed, "bssid": f"b{i}", "localised_at_s": t,
                        "err_h_m": e, "flight_time_s": budget, "budget_s": budget,
                        "time_within_1m_s": None, "err_h_3min_m": e, "err_h_10min_m": e,
                        "within_2m": within(e, 2.0), "within_5m": within(e, 5.0),
                        "all_localised_at_s": t_all})
    return out


# ------------------------------------------------------------------ paired tests
def test_paired_tests_against_a_hand_computation():
    # differences a - b = -3, +1, -2, -5: a wins 3, loses 1. Sign test, two-sided:
    # P(X <= 1) + P(X >= 3) for X ~ B(4, 1/2) = (1 + 4 + 4 + 1) / 16. Wilcoxon: ranks of
    # |d| = 3, 1, 2, 4; W+ (a's losses) = 1; exact two-sided p = #{W+ <= 1 or W+ >= 9}
    # over the 16 sign patterns = 4 / 16.
    w, lo, t, sp, wp = paired_tests([10.0, 11.0, 10.0, 5.0, 7.0], [13.0, 10.0, 12.0, 10.0, 7.0])
    assert (w, lo, t) == (3, 1, 1)
    assert sp == pytest.approx(10 / 16, abs=1e-12)
    assert wp == pytest.approx(4 / 16, abs=1e-12)
    # eight wins, no loss: sign p = 2 / 2^8, Wilcoxon exact 2 / 2^8
    w, lo, t, sp, wp = paired_tests(np.arange(8.0), np.arange(8.0) + np.arange(1, 9))
    assert (w, lo, t) == (8, 0, 0)
    assert sp == pytest.approx(2 / 256) and wp == pytest.approx(2 / 256)
    w, lo, t, sp, wp = paired_tests([1.0, 2.0], [1.0, 2.0])
    assert (w, lo, t) == (0, 0, 2) and math.isnan(sp) and math.isnan(wp)


def test_compare_pairs_censors_at_the_budget():
    fast = _rows("fast", {1: [(100.0, 1.0), (200.0, 1.0)], 2: [(150.0, 0.5), (160.0, 2.5)],
                          3: [(300.0, 1.0), (None, None)]})
    slow = _rows("slow", {1: [(400.0, 3.0), (500.0, 1.0)], 2: [(None, 4.0), (100.0, 2.5)],
                          3: [(None, None), (None, None)], 4: [(10.0, 0.1)]})
    comps = compare_pairs(fast + slow, ["fast", "slow"], 1200.0)
    t, e = comps
    assert (t.a, t.b, t.metric, t.seeds) == ("fast", "slow", "all_localised_at_s", 3)
    # seed 1: 200 vs 500; seed 2: 160 vs censored 1200; seed 3: both censored (tie)
    assert (t.wins, t.losses, t.ties) == (2, 0, 1)
    assert (t.median_a, t.median_b) == (200.0, 1200.0)
    assert t.sign_p == pytest.approx(0.5)
    # errors: seed 1: 1 vs 2; seed 2: 1.5 vs 3.25; seed 3: 25.5 vs 50 (none = 50 m)
    assert (e.metric, e.wins, e.losses, e.ties) == ("error_m", 3, 0, 0)
    assert e.median_a == pytest.approx(1.5) and e.median_b == pytest.approx(3.25)
    assert e.sign_p == pytest.approx(0.25) and e.wilcoxon_p == pytest.approx(0.25)
    s_fast, s_slow = summarise(fast + slow, ["fast", "slow"], 1200.0)
    assert (s_fast.all_localised, s_slow.all_localised) == (2, 2)
    assert s_fast.all_localised_at_s_median == 200.0  # 160, 200, censored 1200
    assert s_slow.all_localised_at_s_median_censored  # 10, 500, 1200, 1200
    assert (s_fast.within_2m, s_fast.within_5m, s_slow.within_2m) == (4, 5, 2)
    text = format_challenge([s_fast, s_slow]) + format_paired(comps)
    assert "fast vs slow" in text and "2/3" in text
    js = json.loads(json.dumps(summary_json(fast + slow, ["fast", "slow"], 1200.0)))
    assert js["paired"][0]["wins"] == 2 and js["policies"][1]["policy"] == "slow"


# ------------------------------------------------------------------ random
def test_uniform_action_draws_from_the_space_with_the_generator():
    rng, ref = np.random.default_rng(4), np.random.default_rng(4)
    d = [uniform_action(spaces.Discrete(7), rng) for _ in range(400)]
    assert d[:20] == [int(ref.integers(7)) for _ in range(20)]  # the Generator's own draws
    assert set(d) == set(range(7)) and abs(np.mean(d) - 3.0) < 0.3
    box = spaces.Box(-1.0, 1.0, (3,), np.float32)
    b = np.array([uniform_action(box, rng) for _ in range(400)])
    assert b.dtype == np.float32 and b.min() >= -1 and b.max() <= 1
    assert np.all(np.abs(b.mean(axis=0)) < 0.15)
    md = uniform_action(spaces.Dict({"k": spaces.MultiDiscrete([2, 5]), "x": box}), rng)
    assert md["k"].shape == (2,) and md["k"][1] < 5 and md["x"].shape == (3,)
    with pytest.raises(ValueError):
        uniform_action(spaces.Box(-np.inf, np.inf, (1,)), rng)


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    p = tmp_path_factory.mktemp("suite") / "tiny.toml"
    p.write_text('name = "tiny"\nextends = "suite/r5-c0-rtk-u1"\n[search]\nbudget_s = 600\n')
    return load_scenario(p)


def test_random_is_seeded_and_deterministic(tiny):
    import dataclasses

    short = dataclasses.replace(tiny, search=dataclasses.replace(tiny.search, budget_s=150.0))

    def flight(seed, rng_seed=None):
        rng = None if rng_seed is None else np.random.default_rng(rng_seed)
        res = run_search(short, load_policy("random"), seed, policy_rng=rng)
        return res.notes, [(r["bssid"], r.get("err_h_m")) for r in res.responders]

    a = flight(2_000_000)
    assert a == flight(2_000_000)  # the same seed, the same search
    assert flight(2_000_000, 1) != flight(2_000_000, 2)  # its draws come from its Generator
    assert isinstance(load_policy("random"), RandomPolicy)
    assert load_policy("random:waypoint").name == "random:waypoint"
    with pytest.raises(ValueError, match="random:waypoint"):
        load_policy("random:bogus")


def test_random_flies_every_uav_of_a_team():
    sc = load_scenario("suite/r1-c0-rtk-u2")
    import dataclasses

    sc = dataclasses.replace(sc, search=dataclasses.replace(sc.search, budget_s=60.0))
    res = run_search(sc, load_policy("random"), 5)
    moved = [np.hypot(*(np.asarray(t[-1][1:3]) - np.asarray(t[0][1:3]))) for t in res.nav_track]
    assert len(moved) == 2 and min(moved) > 50.0


def test_random_is_below_adaptive_on_a_tiny_suite_run(tiny):
    """5 open responders, RTK, 10 minutes of battery, 4 test worlds: adaptive judges
    more responders localised than random (measured 19 of 20 against 13), more
    episodes all localised (3 against 0), and ends more episodes with the smaller
    capped error (4 of 4)."""
    seeds = tuple(range(2_000_000, 2_000_004))
    pols = ("random", "adaptive")
    rows = []
    for p in pols:
        for s in seeds:
            rows += rows_of(run_search(tiny, load_policy(p), s), p, s, 600.0)
    r, a = summarise(rows, pols, 600.0)
    assert a.localised >= r.localised + 3
    assert a.all_localised > r.all_localised
    _, err = compare_pairs(rows, pols, 600.0)
    assert err.losses > err.wins  # adaptive's error is the smaller in most worlds


# ------------------------------------------------------------------ the CLI
def test_osa_evaluate_prints_and_writes_the_challenge_and_the_pairs(tmp_path, capsys):
    from envs.cli import main

    toml = tmp_path / "s.toml"
    toml.write_text('name = "s"\nextends = "suite/r1-c0-rtk-u1"\n[search]\nbudget_s = 60\n')
    out, js = tmp_path / "rows.csv", tmp_path / "summary.json"
    args = ["evaluate", str(toml), "--policies", "random,lawnmower", "--seeds", "2",
            "--workers", "1", "--no-figures", "--no-progress", "-o", str(out)]
    assert main([*args, "--summary-json", str(out)]) == 2  # one file for both: refused
    assert "same file" in capsys.readouterr().err
    assert main([*args, "--summary-json", str(js)]) == 0
    text = capsys.readouterr().out
    assert "Timed search challenge" in text and "random vs lawnmower" in text
    summary = json.loads(js.read_text())
    assert [p["policy"] for p in summary["policies"]] == ["random", "lawnmower"]
    assert [(c["a"], c["b"], c["metric"], c["seeds"]) for c in summary["paired"]] == [
        ("random", "lawnmower", "all_localised_at_s", 2), ("random", "lawnmower", "error_m", 2)]
    out.unlink()  # only the summary exists now: the output rule refuses it
    assert main([*args, "--summary-json", str(js)]) == 2
    err = capsys.readouterr().err
    assert "summary.json exists" in err and "--force" in err
    assert not out.exists()
    assert main(["evaluate", "suite/r2-c0-sa-u1", "--policies", "random", "--seeds", "1",
                 "-o", str(tmp_path / "x.csv")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "suite/r{1,5,10}" in err
