"""The stepper and the world realisation: common random numbers, stepping in pieces,
several agents in one world, seeds of every kind, the [search] table."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

import sim
from estimator.records import Trajectory
from sim import realise
from sim.scenario import ScenarioError, scenario_from_table
from sim.stepper import Stepper

from .util import responder, scenario

ORIGIN = (36.715, -4.478, 140.0)


def _line(points, speed=6.0, height_ref="terrain") -> Trajectory:
    p = np.asarray(points, dtype=float)
    seg = np.linalg.norm(np.diff(p[:, :2], axis=0), axis=1)
    t = np.concatenate([[0.0], np.cumsum(seg / speed)])
    return Trajectory(t, p, ORIGIN, height_ref)


def _world_scenario():
    return scenario([responder(e_m=60.0, n_m=40.0),
                     responder("B", "a4:77:33:0f:1e:03", e_m=-80.0, n_m=10.0)])


def _fly(stepper: Stepper, traj: Trajectory, stops) -> list:
    stepper.follow(0, traj)
    out = []
    for t in stops:
        out.extend(stepper.step_to(t)[0])
    return out


def test_two_plans_on_one_seed_meet_one_world():
    """Common random numbers: two plans sharing a first leg see the same GNSS errors,
    shadowing and ranging noise there, and the same world elsewhere."""
    sc = _world_scenario()
    a = _line([(0, -100, 45), (0, 150, 45), (200, 150, 45)])
    b = _line([(0, -100, 45), (0, 150, 45), (-200, 300, 45)])
    ra, rb = realise(sc, 7), realise(sc, 7)
    sa, sb = Stepper(ra), Stepper(rb)
    ea = _fly(sa, a, [30.0, 90.0])
    eb = _fly(sb, b, [30.0, 90.0])
    # the world: responders, offsets and the shadowing field everywhere
    assert np.array_equal(ra.offsets_m, rb.offsets_m)
    pts = np.random.default_rng(0).uniform(-3000, 3000, (500, 2))
    for fa, fb in zip(ra.shadowing, rb.shadowing, strict=True):
        assert np.array_equal(fa(pts[:, 0], pts[:, 1]), fb(pts[:, 0], pts[:, 1]))
    # the GNSS error process is a function of time, whatever is flown
    t = np.linspace(0.0, 90.0, 901)
    ba = sa.agents[0].gnss.process.bias_at(t)
    assert np.array_equal(ba, sb.agents[0].gnss.process.bias_at(t))
    assert np.abs(ba).max() > 0.1  # standalone: a metre-level bias
    # on the common first leg (the first 25 s), the logs are identical
    early_a = [e.record for e in ea if e.record.t_ns < sa.agents[0].clock.to_ns(25.0)]
    early_b = [e.record for e in eb if e.record.t_ns < sb.agents[0].clock.to_ns(25.0)]
    assert len(early_a) > 200 and early_a == early_b
    ga, gb = sa.gnss_track(0), sb.gnss_track(0)
    k = ga.t_s < 25.0
    assert np.array_equal(ga.error_enu_m[k], gb.error_enu_m[k])
    # after the plans part, the paths differ but the receiver's bias does not
    late = ga.t_s > 80.0
    assert np.abs(ga.true_enu_m[late] - gb.true_enu_m[late]).max() > 50.0
    assert np.array_equal(ga.bias_enu_m[late], gb.bias_enu_m[late])


def test_stepping_in_pieces_equals_one_long_step():
    sc = _world_scenario()
    traj = _line([(0, -100, 45), (0, 150, 45), (200, 150, 55), (150, -50, 40)])
    one = Stepper(realise(sc, 3))
    whole = _fly(one, traj, [140.0])
    many = Stepper(realise(sc, 3))
    pieces = _fly(many, traj, [0.37, 0.4, 13.21, 50.0, 77.77, 77.78, 140.0])
    assert len(whole) > 1000
    assert whole == pieces  # records, delivery and write times alike
    np.testing.assert_array_equal(one.vehicle_track(0).enu_m, many.vehicle_track(0).enu_m)
    # records leave in delivery (t_ns) order
    t_ns = [e.t_ns for e in pieces]
    assert t_ns == sorted(t_ns)
    # and the file is written in write order, slightly out of t_ns order
    file_t = [r.t_ns for r in many.file_records(0)]
    assert file_t != sorted(file_t) and sorted(file_t) == sorted(t_ns)


def test_a_new_command_starts_from_the_current_state():
    """Re-planning mid-flight: the vehicle keeps its speed (no restart from rest)."""
    sc = _world_scenario()
    st = Stepper(realise(sc, 1))
    st.follow(0, _line([(0, -100, 45), (0, 300, 45)]))
    st.step_to(40.0)
    v0 = st.state(0).velocity_mps
    assert math.hypot(v0[0], v0[1]) > 5.0
    st.follow(0, _line([(st.state(0).position_m[0], st.state(0).position_m[1], 45),
                        (150, 300, 45)]))
    st.step_to(40.5)
    v1 = st.state(0).velocity_mps
    assert math.hypot(v1[0], v1[1]) > 4.0  # turning, not stopped
    dv = math.hypot(v1[0] - v0[0], v1[1] - v0[1]) / 0.5
    assert dv <= math.hypot(2.0, 3.0) + 1e-6  # within the acceleration limits


@pytest.mark.parametrize("seed", [5, np.random.SeedSequence(5), "generator"])
def test_seeds_of_every_kind(seed):
    sc = _world_scenario()
    if isinstance(seed, str):
        r1 = realise(sc, np.random.default_rng(11))
        r2 = realise(sc, np.random.default_rng(11))
        r3 = realise(sc, np.random.default_rng(12))
        assert np.array_equal(r1.offsets_m, r2.offsets_m)
        assert not np.array_equal(r1.offsets_m, r3.offsets_m)
        return
    r = realise(sc, seed)
    assert np.array_equal(r.offsets_m, realise(sc, 5).offsets_m)
    assert not np.array_equal(r.offsets_m, realise(sc, 6).offsets_m)


def test_seed_errors_are_clear():
    sc = _world_scenario()
    with pytest.raises(ValueError, match=">= 0"):
        realise(sc, -1)
    with pytest.raises(TypeError, match="SeedSequence or Generator"):
        realise(sc, "seven")


SEARCH = """
name = "s"
[world.origin]
lat_deg = 36.715
lon_deg = -4.478
h_m = 140.0
[search]
area_enu_m = [[-250.0, -250.0], [250.0, -250.0], [250.0, 250.0], [0.0, 50.0], [-250.0, 250.0]]
start_e_m = 0.0
start_n_m = -240.0
budget_s = 600.0
random_responders = 20
random_concealment = ["open", "vegetation"]
[[agents]]
name = "uav-1"
[[agents]]
name = "uav-2"
start_e_m = 100.0
start_n_m = -200.0
[agents.gnss]
preset = "rtk"
[[agents]]
name = "walker"
kind = "ground"
"""


def test_search_scenario_random_responders_and_agents():
    import tomllib

    from estimator.geometry import point_in_polygon

    sc = scenario_from_table(tomllib.loads(SEARCH))
    assert sc.flight is None and sc.search is not None and sc.search.budget_s == 600.0
    assert [a.name for a in sc.agents] == ["uav-1", "uav-2", "walker"]
    assert sc.agents[1].gnss.fix == "rtk_fixed" and sc.agents[2].kind == "ground"
    r = realise(sc, 4)
    resp = r.world.responders
    assert len(resp) == 20 and len({x.bssid for x in resp}) == 20
    xy = np.array([[x.e_m, x.n_m] for x in resp])
    assert point_in_polygon(sc.search.area_enu_m, xy).all()  # inside the concave area
    assert {x.concealment for x in resp} <= {"open", "vegetation"}
    assert [x.bssid for x in realise(sc, 4).world.responders] == [x.bssid for x in resp]
    assert [x.bssid for x in realise(sc, 5).world.responders] != [x.bssid for x in resp]
    # three agents fly in one world, each with its own log and receiver
    st = Stepper(r)
    assert [a.header.agent for a in st.agents] == ["uav-1", "uav-2", "walker"]
    st.command(0, sim.HoldGuidance((0.0, -240.0, 50.0), sc.agents[0].vehicle))
    st.follow(2, _line([(0, -240, 1.5), (30, -240, 1.5)], speed=1.4))
    out = st.step_to(30.0)
    assert all(len(o) > 100 for o in out)
    walker = st.vehicle_track(2)
    assert np.abs(walker.agl_m - 1.5).max() < 1e-9  # walks on the hills
    v = st.agents[2].vehicle.state_log.view[:, 4:6]  # the walker's own velocity
    assert np.hypot(v[:, 0], v[:, 1]).max() <= 1.4 + 1e-9
    g0, g1 = st.gnss_track(0), st.gnss_track(1)
    assert np.median(g0.error_h_m) > 10 * np.median(g1.error_h_m)  # standalone vs RTK
    assert not np.array_equal(g0.bias_enu_m[:50], st.gnss_track(2).bias_enu_m[:50])


@pytest.mark.parametrize(
    "change, match",
    [
        ("start_e_m = 400.0", "outside area_enu_m"),
        ("budget_s = 0.0", "budget_s"),
        ('random_concealment = ["rubble"]', "random_concealment"),
        ("area_enu_m = [[0.0, 0.0], [1.0, 0.0]]", "at least 3"),
        ("speed_mps = 80.0", "speed_mps"),
    ],
)
def test_bad_search_table_is_a_clear_error(tmp_path, change, match):
    text = SEARCH.split("[[agents]]")[0]
    key = change.split(" = ")[0]
    lines = [ln for ln in text.splitlines() if not ln.startswith(key + " ")]
    idx = lines.index("[search]")
    lines.insert(idx + 1, change)
    p = tmp_path / "bad.toml"
    p.write_text("\n".join(lines))
    with pytest.raises(ScenarioError, match=match):
        sim.load_scenario(p)


def test_whole_flight_is_a_loop_over_the_stepper():
    """osa simulate's flight, stepped: same records as the result it returns, and a
    valid log (everything read back, nothing rejected)."""
    sc = dataclasses.replace(_world_scenario(), name="w")
    res = sim.run_scenario(sc, 2)
    assert res.summary().startswith("w seed 2:")
    recs = res.records()
    assert len(recs) == res.n_gnss + res.n_rtt
    fixes = [r for r in recs if isinstance(r, sim.stepper.GnssFix)]
    assert len(fixes) == res.n_gnss


def test_a_commanded_segment_is_done_soon_after_its_end():
    """The autopilot flies on its drifting GNSS estimate (standalone: centimetres per
    tick): a segment is done within the acceptance radius of its end, seconds after
    the vehicle gets there, not when the drift happens to pass within a centimetre."""
    sc = _world_scenario()
    st = Stepper(realise(sc, 8))
    g = st.follow(0, _line([(0, -100, 45), (0, 20, 45)], speed=6.0))
    st.step_to(20.0)
    flown_by = None
    for k in range(1, 120):
        st.step_to(20.0 + 0.5 * k)
        if g.done:
            flown_by = st.t_s
            break
    # climb from the ground to 45 m (~15 s at 3 m/s) then 120 m at 6 m/s, then brake
    assert flown_by is not None and flown_by < 50.0
    end = np.array(st.navigation_position_m(0)) - np.array([0.0, 20.0, 0.0])
    assert np.hypot(end[0], end[1]) < Stepper.ARRIVE_M


def test_a_vehicle_holding_on_the_ground_stays_on_it_whatever_its_navigation_error():
    """Holding at take-off used to steer the believed height (truth + a drifting
    navigation error) into the ground: 1.2 m below it after 20 s on seed 3 of
    search-random-los (a FlightError). A landed vehicle stays landed."""
    sc = sim.load_scenario("search-random-los")
    for seed in range(8):
        for command_hold in (True, False):
            st = Stepper(realise(sc, seed))
            if command_hold:
                st.hold(0)
            st.step_to(60.0)
            v = st.agents[0].vehicle
            agl = v._p[2] - float(st.world.ground_m(v._p[0], v._p[1]))
            assert abs(agl) < 1e-9, (seed, command_hold, agl)
    # in the air a hold is still a hold of the believed position
    st = Stepper(realise(sc, 3))
    o = st.world.origin
    e, n, _ = st.agents[0].vehicle.position_m
    st.follow(0, Trajectory(np.array([0.0, 20.0]), np.array([[e, n, 45.0], [e + 40.0, n, 45.0]]),
                            (o.lat_deg, o.lon_deg, o.h_m), "terrain"))
    st.step_to(25.0)
    g = st.hold(0)
    assert g.name == "hold" and g.point == pytest.approx(st.navigation_position_m(0))


def test_a_stepper_that_keeps_no_records_delivers_the_same(monkeypatch):
    """``keep_records=False`` (a vehicle that runs for hours and passes its phone's
    records on as they come) delivers exactly the records of a stepper that keeps them,
    and keeps none of them, nor the measurement steps; of the vehicle's trace, the
    wander's and the GNSS receiver's draws it keeps the recent past only (here the last
    30 to 60 s), so it does not grow with the flight."""
    monkeypatch.setattr(Stepper, "TRACE_KEPT_S", 30.0)
    sc = _world_scenario()
    square = [(0, -100, 45), (0, 150, 45), (200, 150, 45), (200, -100, 45)]
    traj = _line(square * 2 + square[:1])  # twice round: 330 s
    keep, drop = Stepper(realise(sc, 3)), Stepper(realise(sc, 3), keep_records=False)
    stops = [7.5 * k + 0.3 for k in range(1, 46)]
    got = _fly(drop, traj, stops)
    assert got == _fly(keep, traj, stops) and len(got) > 2000
    assert keep.agents[0].emitted and keep.agents[0].gnss_steps
    a = drop.agents[0]
    assert (a.emitted, a.gnss_steps, a.ftm_steps) == ([], [], [])
    # the trace kept: its last 30 to 60 s, the same as the whole one's end
    whole, recent = keep.vehicle_track(0), drop.vehicle_track(0)
    assert 30.0 <= recent.t_s[-1] - recent.t_s[0] <= 60.0 + 1e-9
    np.testing.assert_array_equal(whole.enu_m[-len(recent.t_s):], recent.enu_m)
    # the draws kept: the last blocks only (1024 epochs, 1024 ticks each)
    assert len(a.gnss.process._epochs) <= 2 < len(keep.agents[0].gnss.process._epochs)
    assert len(a.vehicle.wander._blocks) <= 2 < len(keep.agents[0].vehicle.wander._blocks)
