"""The closed loop: the online estimator equals a replay of the loop's own log; the same
seed gives the same bytes; the vehicle stays inside the area; policies see no truth;
the adaptive policy localises a line-of-sight responder."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest

import sim
from envs.cli import main
from envs.loop import ClosedLoop, LoopConfig, fly, run_search
from estimator.replay import ReplayOptions, replay_logs
from planner.adaptive import AdaptivePolicy
from planner.observation import Decision, Observation
from planner.policy import make_policy

RTK = "search-random-los-rtk"


def _short(name: str, budget_s: float, **search):
    sc = sim.load_scenario(name)
    return dataclasses.replace(sc, search=dataclasses.replace(sc.search, budget_s=budget_s,
                                                              **search))


@pytest.fixture(scope="module")
def adaptive_run(tmp_path_factory):
    d = tmp_path_factory.mktemp("adaptive")
    sc = sim.load_scenario(RTK)
    res = run_search(sc, AdaptivePolicy(), 2, log_paths=[d / "flight.jsonl"])
    return sc, res, d / "flight.jsonl"


def test_online_estimates_equal_a_replay_of_the_loops_log(adaptive_run):
    _sc, res, log = adaptive_run
    rep = replay_logs([log], ReplayOptions(modes=(res.mode,)))
    assert len(res.responders) == 1 and rep.tracks[0].bssid == res.responders[0]["bssid"]
    r, t = res.responders[0], rep.tracks[0].to_json()
    for key in ("status", "lat", "lon", "alt_m", "sigma_h_m", "sigma_z_m", "err_h_m",
                "err_3d_m"):
        assert r[key] == t[key], key
    assert rep.rejected.n_rejected == 0


def test_adaptive_localises_the_line_of_sight_responder(adaptive_run):
    """Detected, localised by the estimator's own judgement well within the budget (RTK,
    seed 2): within 0.5 m of the truth, the truth inside the reported 95 % circle."""
    _sc, res, _log = adaptive_run
    r = res.responders[0]
    assert res.mode == "refined"  # the loop's default: the recommended mode (best)
    assert res.ended == "localised" and r["status"] == "converged"
    assert r["detected_at_s"] < r["localised_at_s"] <= res.flight_time_s < 600.0
    assert r["err_h_m"] < 0.5 and r["err_h_m"] < r["r95_h_m"] and r["sigma_h_m"] <= 0.5
    assert res.replans >= 1 and res.refused_plans == 0


def test_adaptive_with_standalone_gnss_stops_at_the_gnss_floor():
    """Standalone GNSS (a metre-level correlated anchor error): sigma_H plateaus above
    the 0.5 m target, and the policy stops on the plateau rule; the truth is inside the
    honest 95 % circle (seed 2)."""
    res = run_search(sim.load_scenario("search-random-los"), AdaptivePolicy(), 2)
    r = res.responders[0]
    assert res.ended == "localised" and r["status"] == "converged"
    assert 0.5 < r["sigma_h_m"] <= 3.0 and r["err_h_m"] < r["r95_h_m"] < 6.0


@pytest.mark.parametrize("policy", ["lawnmower", "adaptive"])
def test_the_vehicle_never_leaves_the_area(policy, adaptive_run):
    from envs.policies import load_policy
    from estimator.geometry import signed_distance_to_polygon_m

    sc = _short(RTK, 400.0)
    res = adaptive_run[1] if policy == "adaptive" else run_search(sc, load_policy(policy), 2)
    area = res.area_enu_m
    for trk in res.true_track:  # the vehicle's true path, every half second
        assert signed_distance_to_polygon_m(area, trk[:, :2]).max() < -1.0
    nav = np.asarray(res.nav_track[0])[:, 1:3]
    assert signed_distance_to_polygon_m(area, nav).max() < 0.0


def test_same_seed_same_log_bytes(tmp_path):
    sc = _short(RTK, 150.0)
    for k in (1, 2):
        run_search(sc, make_policy("lawnmower"), 5, log_paths=[tmp_path / f"{k}.jsonl"])
    a, b = (tmp_path / "1.jsonl").read_bytes(), (tmp_path / "2.jsonl").read_bytes()
    assert a == b and a.count(b"\n") > 1000
    run_search(sc, make_policy("lawnmower"), 6, log_paths=[tmp_path / "3.jsonl"])
    assert (tmp_path / "3.jsonl").read_bytes() != a


class _Recorder:
    """A test's policy: records what it observes and flies a fixed square about a point
    (the test aims it near the responder; the point is not an observation)."""

    name = "recorder"

    def __init__(self, center):
        self.seen: list[Observation] = []
        self.center = center

    def reset(self, mission, rng):
        self.mission = mission

    def decide(self, obs):
        self.seen.append(obs)
        if obs.t_s == 0.0:
            from planner.coverage import polyline_trajectory

            m = self.mission
            cx, cy = self.center
            sq = [(cx - 50, cy - 50), (cx + 50, cy - 50), (cx + 50, cy + 50), (cx - 50, cy + 50)]
            sq = [(min(max(x, -230), 230), min(max(y, -230), 230)) for x, y in sq]
            return Decision(plans={0: polyline_trajectory(
                m.area.join([m.start_enu_m, *sq, sq[0], *sq]), m.height_m, m.speed_mps,
                m.origin, "square")})
        return Decision()


def test_policies_see_no_truth():
    """Everything the loop knows of the truth (realisation, world, truth records) is
    swapped for a world whose responder lies 50 m away, while the stepper keeps
    measuring the original: the observations are identical; only the evaluation moves."""
    sc = _short(RTK, 150.0)
    real = sim.realise(sc, 3)
    r0 = real.world.responders[0]
    moved_world = dataclasses.replace(real.world, responders=(dataclasses.replace(
        r0, e_m=r0.e_m + 50.0),))
    moved = dataclasses.replace(real, world=moved_world)

    def run(swap: bool):
        loop = ClosedLoop(sc, 3, realisation=real)
        if swap:
            loop.realisation, loop.world = moved, moved_world
            loop.truth = {t.bssid: t for t in moved.truth_records()}
        p = _Recorder((r0.e_m, r0.n_m))
        p.reset(loop.mission, np.random.default_rng(0))
        while loop.t_s < 150.0:
            loop.apply(p.decide(loop.observe()))
            loop.advance(5.0)
        return p.seen, loop

    seen_a, loop_a = run(False)
    seen_b, loop_b = run(True)
    assert any(o.responders and o.responders[0].has_estimate for o in seen_a)
    assert seen_a == seen_b
    err_a = loop_a.series[r0.bssid][-1].err_h_m
    err_b = loop_b.series[r0.bssid][-1].err_h_m
    assert err_a is not None and abs(err_b - err_a) > 30.0  # only the evaluation moved


@pytest.mark.parametrize("command", ["simulate", "run"])
def test_fixed_flight_commands_refuse_a_search(command, tmp_path, capsys):
    assert main([command, RTK, "-o", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "fly it with osa search" in err


def test_loop_config_and_scenario_errors():
    with pytest.raises(ValueError, match="one estimator mode"):
        LoopConfig(mode="all")
    with pytest.raises(ValueError, match="no \\[search\\]"):
        ClosedLoop(sim.load_scenario("paper-ap1f"), 0)


def test_osa_search_cli_writes_log_report_and_figures(tmp_path, capsys):
    out = tmp_path / "s"
    sc_path = tmp_path / "short.toml"
    sc_path.write_text('extends = "search-random-los-rtk"\n[search]\nbudget_s = 120.0\n')
    status = main(["search", str(sc_path), "--policy", "lawnmower", "--seed", "1", "-o",
                   str(out), "--json", "--no-progress"])
    assert status == 0
    rep = json.loads(capsys.readouterr().out)
    assert rep["policy"] == "lawnmower" and rep["seed"] == 1 and rep["ended"] == "budget"
    assert rep["flight_time_s"] == pytest.approx(120.0) and rep["log"].endswith("flight.jsonl")
    assert {"bssid", "status"} <= set(rep["responders"][0])
    for f in ("flight.jsonl", "report.json", "trajectory.png", "errors.png"):
        assert (out / f).stat().st_size > 0
    assert json.loads((out / "report.json").read_text()) == rep


@pytest.mark.parametrize(
    ("argv", "match"),
    [
        (["search", "paper-ap1f"], "not a search scenario"),
        (["search", "nope"], "unknown scenario"),
        (["search", RTK, "--policy", "magic"], "--policy: unknown policy"),
        (["search", RTK, "--mode", "all"], "--mode"),
        (["search", RTK, "--seed", "-1"], "--seed"),
        (["search", RTK, "--decision-period", "0"], "--decision-period"),
    ],
)
def test_osa_search_errors_are_one_line(argv, match, capsys, tmp_path):
    with pytest.raises(SystemExit) if "--seed" in argv else _NoRaise():
        status = main([*argv, "-o", str(tmp_path / "o"), "--no-progress"])
        assert status == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and match in err


class _NoRaise:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


def test_a_segment_bringing_a_vehicle_back_inside_is_accepted(monkeypatch):
    """From inside, a segment (with the leg to it) must stay inside; from outside (a wide
    turn), the segment counts from its first point inside on."""
    from planner.coverage import polyline_trajectory

    loop = ClosedLoop(_short(RTK, 60.0), 0)
    m = loop.mission

    def seg(*pts):
        return polyline_trajectory(pts, m.height_m, m.speed_mps, m.origin, "t")

    monkeypatch.setattr(loop.stepper, "navigation_position_m", lambda i=0: (0.0, -255.0, 0.0))
    assert loop.plan_inside(seg((0.0, -255.0), (0.0, -200.0), (50.0, -200.0)))
    assert not loop.plan_inside(seg((0.0, -255.0), (0.0, -260.0)))  # never comes back
    assert not loop.plan_inside(seg((0.0, -255.0), (0.0, -200.0), (0.0, -270.0)))
    monkeypatch.setattr(loop.stepper, "navigation_position_m", lambda i=0: (0.0, -200.0, 0.0))
    assert loop.plan_inside(seg((0.0, -200.0), (100.0, 0.0)))
    assert not loop.plan_inside(seg((0.0, -200.0), (0.0, -260.0), (0.0, -200.0)))


# ----------------------------------------------------------------------------- stalls


def _still_s(track) -> float:
    """The longest time a (t, e, n, u) track stayed within 3 m of one point."""
    t = np.asarray(track, dtype=float)
    best, i = 0.0, 0
    for j in range(1, len(t)):
        while np.linalg.norm(t[j, 1:4] - t[i, 1:4]) > 3.0:
            i += 1
        best = max(best, float(t[j, 0] - t[i, 0]))
    return best


def test_the_reported_hover_stall_flies_on():
    """search-three-mixed, adaptive, seed 2000028 stood still at (124.9, -239.9) from
    325 s to the end of the budget: the sweep resumed at the waypoint the vehicle stood
    on (an empty segment, done at once, re-planned the same, forever). It now turns
    back into its next pass and never stands still."""
    loop = ClosedLoop(_short("search-three-mixed", 450.0), 2000028)
    res = fly(loop, AdaptivePolicy())
    nav = np.asarray(res.nav_track[0])
    after = nav[nav[:, 0] >= 325.0]
    assert np.ptp(after[:, 2]) > 100.0  # it flew on (north) from the corner
    assert _still_s(nav) < 20.0 and loop.stalls == [] and res.to_json()["stalls"] == 0


def test_the_reported_helix_stall_flies_on():
    """osa/Search-v0 always choosing `helix` on search-random-los world 2000002 hovered
    from 85 s to the budget: the new path started while the vehicle flew on at speed,
    it overshot the path's start by more than the guidance's lag limit, and the
    feed-forward along the path balanced the pull back (the reference waited for the
    vehicle, the vehicle for the reference). The reference now advances when the
    vehicle is ahead of it."""
    import gymnasium as gym

    import envs  # noqa: F401

    env = gym.make("osa/Search-v0", scenario="search-random-los").unwrapped
    env.reset(seed=0, options={"world_seed": 2000002})
    for _ in range(40):  # 200 s
        _, _, term, trunc, _ = env.step(3)
        if term or trunc:
            break
    assert _still_s(env.loop.nav_track[0]) < 20.0
    assert env.loop.longest_still_s(0) < 20.0 and env.loop.stalls == []


class _Jammed:
    """A vehicle whose autopilot stops obeying at ``jam_s``: it holds where it is but
    says the segment is still being flown (a stall the loop must see)."""

    def __init__(self, inner, jam_s: float) -> None:
        self.inner, self.jam_s = inner, jam_s
        self.flown = 0

    def __getattr__(self, name):
        return getattr(self.inner, name)

    def fly(self, agent, traj):
        self.flown += 1
        if self.inner.t_s >= self.jam_s:
            self.inner.hold(agent)
        else:
            self.inner.fly(agent, traj)

    def advance_to(self, t_s):
        if self.inner.t_s >= self.jam_s:
            self.inner.hold(0)
        return self.inner.advance_to(t_s)

    def segment_done(self, agent):
        return False if self.inner.t_s >= self.jam_s else self.inner.segment_done(agent)


def test_a_vehicle_that_makes_no_progress_is_a_stall():
    """Jammed from 60 s: the loop counts a stall once the vehicle has stayed within 3 m
    for more than 30 s on a pending segment, notes it, reports the segment done; the
    policy plans again (and the jammed vehicle stalls again)."""
    from envs.vehicles import SimVehicle

    sc = _short(RTK, 200.0)
    real = sim.realise(sc, 0)
    v = _Jammed(SimVehicle(real, header_agl_m=sc.search.height_m), jam_s=60.0)
    loop = ClosedLoop(sc, 0, vehicle=v, realisation=real)
    seen = []

    inner = make_policy("lawnmower")

    class Spy:
        name = "spy"

        def reset(self, mission, rng):
            inner.reset(mission, rng)

        def decide(self, obs):
            seen.append((obs.t_s, obs.agent.segment_done))
            return inner.decide(obs)

    res = fly(loop, Spy())
    assert len(loop.stalls) >= 2
    t0, agent, _p, still = loop.stalls[0]
    assert agent == 0 and 90.0 < t0 <= 100.0 and 30.0 < still <= 35.0
    assert (t0, True) in seen and v.flown >= 2  # reported done, planned again
    j = res.to_json()
    assert j["stalls"] == len(loop.stalls) and j["stall_events"][0]["t_s"] == t0
    assert any("stall: agent 0 made no progress" in n for _, n in res.notes)


def test_a_planned_hover_is_not_a_stall():
    """A plan that hovers 60 s on the way is flown to its end: the loop allows the
    plan's own stops."""
    from estimator.records import Trajectory

    sc = _short(RTK, 200.0)

    class Hover:
        name = "hover"

        def reset(self, mission, rng):
            self.m = mission

        def decide(self, obs):
            if obs.t_s == 0.0:
                p = np.array([[0.0, -200.0, 40.0], [0.0, -150.0, 40.0], [0.0, -150.0, 40.0],
                              [50.0, -150.0, 40.0]])
                t = np.array([0.0, 10.0, 70.0, 80.0])
                return Decision(plans={0: Trajectory(t, p, self.m.origin, "terrain", "h")})
            return Decision(done=obs.agent.segment_done)

    loop = ClosedLoop(sc, 0)
    res = fly(loop, Hover())
    assert res.ended == "localised" and loop.stalls == []
    assert 55.0 < loop.longest_still_s(0) < 90.0  # it hovered as asked


# worlds of the test split where the policies used to stand still early (the full
# sweep: benchmarks/bench_stalls.py)
SWEEP = {"search-random-los": (2000000, 2000002), "search-three-mixed": (2000000, 2000006)}


@pytest.mark.parametrize("scenario", list(SWEEP))
def test_no_idle_hover_in_a_sweep_of_searches(scenario):
    """Every policy on two worlds (400 s each): the patterns and the adaptive policy
    never stay 30 s within 3 m; in osa/Search-v0 uniformly random manoeuvres and always
    `helix` never stay 30 s within 3 m while a segment is pending (a random `return`
    asks for a hover); no stall. These worlds stood still before: `helix` from 65 s on
    search-three-mixed 2000000 and from 85 s on search-random-los 2000002, random
    manoeuvres from about 310 s on search-three-mixed 2000006."""
    import gymnasium as gym

    import envs  # noqa: F401
    from envs.policies import load_policy

    sc = _short(scenario, 400.0)
    for seed in SWEEP[scenario]:
        for name in ("lawnmower", "expanding-square", "adaptive"):
            loop = ClosedLoop(sc, seed)
            res = fly(loop, load_policy(name))
            assert _still_s(res.nav_track[0]) < 30.0, (name, seed)
            assert loop.stalls == [], (name, seed)
        for how in ("random", "helix"):
            env = gym.make("osa/Search-v0", scenario=sc).unwrapped
            env.reset(seed=0, options={"world_seed": seed})
            env.action_space.seed(seed)
            for _ in range(80):
                a = 3 if how == "helix" else env.action_space.sample()
                _, _, term, trunc, _ = env.step(a)
                if term or trunc:
                    break
            assert env.loop.longest_still_s(0) < 30.0, (how, seed)
            assert env.loop.stalls == [], (how, seed)
            if how == "helix":
                assert _still_s(env.loop.nav_track[0]) < 30.0, seed


# ----------------------------------------------------------------------------- osa search


@pytest.mark.parametrize(("signame", "expected_status"), [("SIGINT", 130), ("SIGTERM", 143)])
def test_an_interrupted_search_reports_and_closes_its_log(signame, expected_status, tmp_path,
                                                          capsys, monkeypatch):
    """SIGTERM (as Ctrl-C) during `osa search`: the search ends at its next decision,
    the report says `interrupted`, the log is complete and replays to the report, and
    the progress never says done; the exit status is the signal's (docs/cli.md
    Conventions: 130 Ctrl-C, 143 SIGTERM, as a job scheduler's time limit expects)."""
    import os
    import signal

    from envs.commands import _progress

    sent = []
    real_update = _progress.QuantityProgress.update

    def update(self, value, note=""):
        real_update(self, value, note)
        if value >= 60.0 and not sent:
            sent.append(value)
            os.kill(os.getpid(), getattr(signal, signame))

    monkeypatch.setattr(_progress.QuantityProgress, "update", update)
    out = tmp_path / "s"
    before = signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)
    status = main(["search", RTK, "--policy", "lawnmower", "-o", str(out), "--no-figures"])
    _, err = capsys.readouterr()
    assert (signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)) == before
    assert status == expected_status and "done" not in err and "interrupted" in err
    rep = json.loads((out / "report.json").read_text())
    assert rep["ended"] == "interrupted" and 60.0 <= rep["flight_time_s"] <= 70.0
    lines = (out / "flight.jsonl").read_bytes().split(b"\n")
    assert lines[-1] == b"" and all(json.loads(x) for x in lines[:-1])
    replay = replay_logs([out / "flight.jsonl"], ReplayOptions(modes=(rep["mode"],)))
    got = {t.bssid: t.to_json() for t in replay.tracks}
    for r in rep["responders"]:
        if "lat" in r:
            assert got[r["bssid"]]["lat"] == r["lat"]


def test_osa_search_follows_the_output_rule(tmp_path, capsys):
    """A folder another command (or nothing of ours) wrote is refused before the flight
    unless --force; its own folder is reused (said on stderr); an unwritable folder is
    refused before the flight; the scenario file is never an output."""
    import os

    sc_path = tmp_path / "short.toml"
    sc_path.write_text('extends = "search-random-los-rtk"\n[search]\nbudget_s = 30.0\n')
    args = ["search", str(sc_path), "--policy", "lawnmower", "--no-figures", "--no-progress",
            "--json"]
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("mine")
    assert main([*args, "-o", str(foreign)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "use --force" in err
    assert not (foreign / "flight.jsonl").exists()
    assert main([*args, "-o", str(foreign), "--force"]) == 0
    assert (foreign / "notes.txt").read_text() == "mine" and (foreign / "report.json").exists()
    capsys.readouterr()
    assert main([*args, "-o", str(foreign)]) == 0  # now ours: reused
    assert "replacing the files" in capsys.readouterr().err
    assert main([*args, "-o", str(tmp_path)]) == 2  # holds the scenario: an input
    assert "holds an input" in capsys.readouterr().err
    if os.geteuid() != 0:
        locked = tmp_path / "locked"
        locked.mkdir()
        locked.chmod(0o500)
        try:
            assert main([*args, "-o", str(locked / "out")]) == 2
            assert "cannot" in capsys.readouterr().err
        finally:
            locked.chmod(0o700)


@pytest.mark.parametrize("budget_s, flown_s", [(10.03, 10.0), (0.01, 0.0), (10.0, 10.0)])
def test_a_budget_off_the_vehicles_time_grid_ends(budget_s, flown_s):
    """The vehicle ticks on its 0.05 s grid: a budget of 10.03 s ends at its last tick
    within it, 10.0 s (before: the loop asked for the remaining 0.03 s forever, its
    tracks growing without bound, in osa search, osa evaluate and the envs)."""
    loop = ClosedLoop(_short(RTK, budget_s), 0)
    steps = 0
    while not loop.budget_spent and steps < 10:
        loop.advance(5.0)
        steps += 1
    assert loop.budget_spent and loop.t_s == pytest.approx(flown_s, abs=1e-9)
    assert steps == math.ceil(budget_s / 5.0)  # 3 decisions for 10.03 s, 1 for 0.01 s
