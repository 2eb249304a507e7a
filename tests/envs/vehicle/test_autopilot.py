"""The autopilot flies missions as a PX4 multicopter would (no network: stepped directly).

Numbers checked: the order of MISSION_ITEM_REACHED with DO_JUMP repeats, positions at
each reached item within the acceptance radius, cruise and DO_CHANGE_SPEED speeds,
the take-off climb rate, hold and loiter durations, orbit radius and turns, RTL
altitude and landing point, touchdown on the true terrain and auto-disarm, geofence
breach actions, terrain clearance, link-loss rules and command results.
"""

from __future__ import annotations

import math

import pytest
from pymavlink.dialects.v20.common import (
    MAV_CMD_NAV_LOITER_TIME,
    MAV_CMD_NAV_LOITER_TURNS,
    MAV_RESULT_ACCEPTED,
    MAV_RESULT_DENIED,
    MAV_RESULT_FAILED,
    MAV_RESULT_TEMPORARILY_REJECTED,
    MISSION_STATE_COMPLETE,
)
from pymavlink.dialects.v20.common import (
    MAV_LANDED_STATE_IN_AIR as LANDED_IN_AIR,
)
from pymavlink.dialects.v20.common import (
    MAV_LANDED_STATE_ON_GROUND as LANDED_ON_GROUND,
)

from envs.vehicle.autopilot import TERRAIN_CLEARANCE_M
from envs.vehicle.px4 import Mode
from planner.mission import (
    MAV_CMD_DO_CHANGE_SPEED,
    MAV_CMD_DO_JUMP,
    MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION,
    MAV_CMD_NAV_LAND,
    MAV_CMD_NAV_RETURN_TO_LAUNCH,
    MAV_CMD_NAV_TAKEOFF,
    MAV_MISSION_TYPE_FENCE,
)
from tests.envs.vehicle.helpers import fly, item, make_autopilot, numbered, true_agl


def _leg(samples, t0: float, t1: float):
    return [s for s in samples if t0 <= s.t_s <= t1]


def test_mission_jumps_speeds_loiter_and_land() -> None:
    ap = make_autopilot()
    items = numbered([
        item(ap, MAV_CMD_NAV_TAKEOFF, 0, 0, 20.0),                       # 0
        item(ap, e=60, n=0, alt=20.0),                                    # 1
        item(ap, MAV_CMD_DO_CHANGE_SPEED, p1=1.0, p2=3.0, p3=-1.0),       # 2
        item(ap, e=60, n=60, alt=20.0),                                   # 3
        item(ap, e=0, n=60, alt=25.0),                                    # 4
        item(ap, MAV_CMD_DO_JUMP, p1=1.0, p2=1.0),                       # 5: once more
        item(ap, MAV_CMD_NAV_LOITER_TIME, 0, 0, 20.0, p1=6.0),           # 6
        item(ap, MAV_CMD_NAV_LAND, 0, 0, 0.0),                            # 7
    ])
    ap.set_mission(items)
    assert ap.set_mode(Mode.MISSION) == (MAV_RESULT_ACCEPTED, "")
    assert ap.arm() == (MAV_RESULT_ACCEPTED, "")
    s = fly(ap, 900.0, until=lambda a: not a.armed)
    assert not ap.armed and ap.landed_state == LANDED_ON_GROUND
    seqs = [r[0] for r in ap.reached_log]
    assert seqs == [0, 1, 2, 3, 4, 1, 2, 3, 4, 6, 7]  # DO_JUMP is never current nor reached
    assert ap.mission_current()[2] == 0 or ap.mission.seq == 0  # starts over after landing
    home = ap.home.enu
    radius = ap.params["NAV_ACC_RAD"]
    for seq, _t, p in ap.reached_log:
        w = items[seq]
        if w.command in (MAV_CMD_DO_CHANGE_SPEED,):
            continue
        target = ap._item_position(w)
        d = math.hypot(target[0] - p[0], target[1] - p[1])
        assert d <= radius + 1e-6, (seq, d)
        if w.command != MAV_CMD_NAV_LAND:
            assert abs(target[2] - p[2]) <= ap.params["NAV_MC_ALT_RAD"] + 1e-6
    t_reached = {}
    for seq, t, _p in ap.reached_log:
        t_reached.setdefault(seq, []).append(t)
    # take-off: a vertical climb at MPC_TKO_SPEED (1.5 m/s) to 20 m
    climb = _leg(s, 0.0, t_reached[0][0])
    assert max(x.vz for x in climb) <= 1.5 + 0.05
    assert max(x.speed_h for x in climb) < 0.5
    assert t_reached[0][0] >= (20.0 - 0.8) / 1.5 - 0.5  # (0.8: NAV_MC_ALT_RAD)
    # leg 0 -> 1 at the cruise speed (5 m/s: three-aps has no [search] speed), then 3 m/s
    assert max(x.speed_h for x in _leg(s, t_reached[0][0], t_reached[1][0])) == \
        pytest.approx(5.0, abs=0.3)
    after = _leg(s, t_reached[2][0] + 3.0, t_reached[3][0])
    assert max(x.speed_h for x in after) == pytest.approx(3.0, abs=0.2)
    # the second lap also at 3 m/s: DO_CHANGE_SPEED persists
    assert max(x.speed_h for x in _leg(s, t_reached[1][1] + 3.0, t_reached[4][1])) <= 3.2
    # loiter 6 s at the point after reaching it (arrival: within the acceptance radius)
    arrive = [x.t_s for x in s if x.t_s > t_reached[4][1]
              and math.hypot(x.pos[0], x.pos[1]) <= radius]
    assert t_reached[6][0] - arrive[0] == pytest.approx(6.0, abs=0.6)
    # landed on the true terrain at home, disarmed COM_DISARM_LAND (2 s) later
    last = s[-1]
    assert abs(true_agl(ap, last)) < 0.1
    assert math.hypot(ap.position[0] - home[0], ap.position[1] - home[1]) <= radius
    assert s[-1].t_s - t_reached[7][0] == pytest.approx(2.0, abs=0.3)


def test_loiter_turns_orbit() -> None:
    ap = make_autopilot(params={"MPC_XY_CRUISE": 6.0})
    ap.set_mission(numbered([
        item(ap, MAV_CMD_NAV_TAKEOFF, 0, 0, 15.0),
        item(ap, MAV_CMD_NAV_LOITER_TURNS, 80, 0, 15.0, p1=2.0, p3=30.0),  # 2 turns CW
        item(ap, MAV_CMD_NAV_RETURN_TO_LAUNCH),
    ]))
    ap.set_mode(Mode.MISSION)
    ap.arm()
    s = fly(ap, 900.0, until=lambda a: len(a.reached_log) >= 3)
    (_, t0, _), (_, t1, _), _ = ap.reached_log
    assert ap.mode is Mode.RTL  # the RTL item hands over to AUTO.RTL
    orbit = [x for x in _leg(s, t0, t1) if abs(math.hypot(x.pos[0] - 80, x.pos[1]) - 30) < 5]
    entered = orbit[0].t_s
    ring = [math.hypot(x.pos[0] - 80, x.pos[1]) for x in _leg(s, entered + 3, t1)]
    assert max(abs(r - 30.0) for r in ring) < 1.5
    # v = min(cruise 6, sqrt(a_lat R)) = 6 m/s (a_lat 2.4 m/s^2, R 30 m); 2 turns of 188 m
    speed = sorted(x.speed_h for x in _leg(s, entered + 3, t1))
    assert speed[len(speed) // 2] == pytest.approx(6.0, abs=0.3)
    assert t1 - entered == pytest.approx(2 * 2 * math.pi * 30 / 6.0, rel=0.1)
    # clockwise seen from above: the angle about the centre decreases
    a = [math.atan2(x.pos[1], x.pos[0] - 80) for x in _leg(s, entered + 3, entered + 6)]
    assert math.remainder(a[-1] - a[0], 2 * math.pi) < 0


def test_rtl_climbs_returns_and_lands() -> None:
    ap = make_autopilot()
    ap.arm()
    assert ap.takeoff() == (MAV_RESULT_ACCEPTED, "")  # MIS_TAKEOFF_ALT: 2.5 m
    s = fly(ap, 30.0, until=lambda a: a.mode is Mode.LOITER and a.landed_state == LANDED_IN_AIR)
    assert s[-1].pos[2] == pytest.approx(2.5, abs=0.8)
    h = ap.home.enu
    assert ap.reposition((h[0] + 100.0, h[1] + 40.0, h[2] + 20.0))[0] == MAV_RESULT_ACCEPTED
    fly(ap, 60.0)
    assert ap.return_to_launch() == (MAV_RESULT_ACCEPTED, "")
    s = fly(ap, 400.0, until=lambda a: not a.armed)
    assert not ap.armed and ap.mode is Mode.RTL
    # climb to RTL_RETURN_ALT (60 m) before going home, then descend and land at home
    assert max(x.pos[2] for x in s) == pytest.approx(60.0, abs=1.0)
    top = [x for x in s if x.pos[2] > 59.0]
    assert math.hypot(top[0].pos[0] - 100.0, top[0].pos[1] - 40.0) < 3.0
    assert math.hypot(s[-1].pos[0], s[-1].pos[1]) < ap.params["NAV_ACC_RAD"]
    assert abs(true_agl(ap, s[-1])) < 0.1


def test_fence_breach_holds_inside_or_returns() -> None:
    for action, mode in ((2, Mode.LOITER), (3, Mode.RTL)):
        ap = make_autopilot(params={"GF_ACTION": action})
        square = [(-60, -60), (60, -60), (60, 60), (-60, 60)]
        fence = [item(ap, MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION, e, n, p1=4.0,
                      frame=0, mission_type=MAV_MISSION_TYPE_FENCE) for e, n in square]
        ap.set_fence(numbered(fence))
        ap.set_mission(numbered([item(ap, MAV_CMD_NAV_TAKEOFF, 0, 0, 10.0),
                                 item(ap, e=150, n=0, alt=10.0)]))
        ap.set_mode(Mode.MISSION)
        ap.arm()
        s = fly(ap, 300.0, until=lambda a, m=mode: a.mode is m)
        assert ap.mode is mode
        s += fly(ap, 30.0 if mode is Mode.LOITER else 200.0,
                 until=lambda a: not a.armed)
        # braking on the predicted stopping point keeps it inside (nav position)
        assert max(x.pos[0] for x in s) < 60.0
        if mode is Mode.RTL:
            assert not ap.armed and math.hypot(s[-1].pos[0], s[-1].pos[1]) < 2.0
        else:
            assert 50.0 < s[-1].pos[0] < 60.0 and s[-1].speed_h < 0.3
    # arming outside an inclusion fence is denied
    ap = make_autopilot()
    far = [(200, 200), (300, 200), (300, 300)]
    ap.set_fence(numbered([item(ap, MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION, e, n, p1=3.0,
                                frame=0, mission_type=MAV_MISSION_TYPE_FENCE)
                           for e, n in far]))
    assert ap.arm() == (MAV_RESULT_DENIED, "arming denied: outside the geofence")


def test_new_mission_in_flight_is_taken_without_stopping() -> None:
    ap = make_autopilot()
    ap.set_mission(numbered([item(ap, MAV_CMD_NAV_TAKEOFF, 0, 0, 20.0),
                             item(ap, e=300, n=0, alt=20.0)]))
    ap.set_mode(Mode.MISSION)
    ap.arm()
    s = fly(ap, 200.0, until=lambda a: a.position[0] - a.home.enu[0] > 100.0)
    assert s[-1].speed_h == pytest.approx(5.0, abs=0.3)
    t_switch = s[-1].t_s
    e0 = s[-1].pos[0]
    ap.set_mission(numbered([item(ap, e=e0 + 40, n=60, alt=20.0),
                             item(ap, e=e0 + 40, n=120, alt=20.0)]))
    assert ap.mode is Mode.MISSION and ap.mission.seq == 0
    s2 = fly(ap, 200.0, until=lambda a: len(a.reached_log) >= 3)
    assert [r[0] for r in ap.reached_log] == [0, 0, 1]  # the old take-off, then the new list
    # no stop at the switch: the speed stays above 2.5 m/s while it turns onto the new leg
    assert min(x.speed_h for x in _leg(s2, t_switch, t_switch + 10.0)) > 2.5
    assert max(x.pos[0] for x in s2) < 300.0 - 100.0  # the old waypoint is not flown


def test_terrain_clearance_and_mission_end_hold() -> None:
    ap = make_autopilot()
    # 3 m above home while the ground rises towards the north-east (three-aps' slope)
    ap.set_mission(numbered([item(ap, MAV_CMD_NAV_TAKEOFF, 0, 0, 3.0),
                             item(ap, e=150, n=300, alt=3.0)]))
    ap.set_mode(Mode.MISSION)
    ap.arm()
    s = fly(ap, 400.0, until=lambda a: a.mission.state == MISSION_STATE_COMPLETE)
    texts = [e for e in ap.drain_events() if e[0] == "text"]
    assert any("terrain" in e[2] for e in texts)
    flying = [x for x in s if x.landed_state == LANDED_IN_AIR]
    assert min(true_agl(ap, x) for x in flying[20:]) > TERRAIN_CLEARANCE_M - 1.0
    # the end of a mission in the air: AUTO.LOITER, holding
    s = fly(ap, 10.0)
    assert ap.mode is Mode.LOITER and ap.armed and s[-1].speed_h < 0.3


def test_link_loss_rules() -> None:
    ap = make_autopilot()
    ap.set_mission(numbered([item(ap, MAV_CMD_NAV_TAKEOFF, 0, 0, 10.0),
                             item(ap, e=100, n=0, alt=10.0)]))
    ap.set_mode(Mode.MISSION)
    ap.arm()
    fly(ap, 20.0)
    ap.on_link_lost()  # COM_DLL_EXCEPT bit 1: the mission goes on
    assert ap.mode is Mode.MISSION
    fly(ap, 10.0)
    ap.hold()
    ap.on_link_lost()  # holding: NAV_DLL_ACT 2, return
    assert ap.mode is Mode.RTL
    fly(ap, 300.0, until=lambda a: not a.armed)
    assert not ap.armed


def test_command_results() -> None:
    ap = make_autopilot()
    assert ap.takeoff()[0] == MAV_RESULT_TEMPORARILY_REJECTED  # disarmed
    assert ap.set_mode(Mode.MISSION)[0] == MAV_RESULT_TEMPORARILY_REJECTED  # no mission
    assert ap.mission_start()[0] == MAV_RESULT_DENIED  # no mission
    assert ap.return_to_launch()[0] == MAV_RESULT_TEMPORARILY_REJECTED  # landed
    assert ap.disarm() == (MAV_RESULT_ACCEPTED, "")  # already disarmed
    assert ap.arm()[0] == MAV_RESULT_ACCEPTED
    assert ap.arm()[0] == MAV_RESULT_ACCEPTED  # idempotent
    assert ap.takeoff(ap.home.alt_m + 0.5)[0] == MAV_RESULT_DENIED  # below 1 m
    assert ap.takeoff(ap.home.alt_m + 12.0)[0] == MAV_RESULT_ACCEPTED
    fly(ap, 5.0)
    assert ap.disarm()[0] == MAV_RESULT_DENIED  # in the air
    assert ap.disarm(force=True)[0] == MAV_RESULT_DENIED
    # already flying: ACCEPTED and nothing changes (MAVLink's idempotent TAKEOFF)
    assert ap.takeoff(ap.home.alt_m + 30.0) == (MAV_RESULT_ACCEPTED, "takeoff: already flying")
    assert ap.change_speed(-3.0)[0] == MAV_RESULT_DENIED
    assert ap.set_current(5)[0] == MAV_RESULT_FAILED  # no such item (MAVLink)
    s = fly(ap, 20.0)
    assert s[-1].pos[2] == pytest.approx(12.0, abs=0.8) and ap.mode is Mode.LOITER
    assert ap.land()[0] == MAV_RESULT_ACCEPTED
    fly(ap, 60.0, until=lambda a: not a.armed)
    assert not ap.armed and ap.mode is Mode.LAND
    assert ap.arm()[0] == MAV_RESULT_DENIED  # not in AUTO.LAND


def test_preflight_disarm_on_the_wall_clock() -> None:
    ap = make_autopilot()
    now = [100.0]
    ap.wall_clock = lambda: now[0]
    ap.arm()
    ap.on_wall_clock(105.0)
    assert ap.armed
    ap.on_wall_clock(110.5)  # COM_DISARM_PRFLT 10 s without a take-off
    assert not ap.armed


def test_the_items_reached_kept_are_bounded(monkeypatch) -> None:
    """A patrol that loops for ever (DO_JUMP -1) grows no memory: the autopilot keeps the
    last HISTORY items reached and mission changes (both lists used to grow with every
    lap of a vehicle left running)."""
    from envs.vehicle import executor

    monkeypatch.setattr(executor, "HISTORY", 12)
    ap = make_autopilot()
    ap.set_mission(numbered([item(ap, MAV_CMD_NAV_TAKEOFF, 0, 0, 10.0),
                             item(ap, e=8, n=0, alt=10.0), item(ap, e=0, n=8, alt=10.0),
                             item(ap, MAV_CMD_DO_JUMP, p1=1.0, p2=-1.0)]))
    for _ in range(20):  # mission changes: the same mission again
        ap.set_mission(list(ap.mission.items))
    assert ap.set_mode(Mode.MISSION)[0] == MAV_RESULT_ACCEPTED and ap.arm()[0] == 0
    laps = []
    fly(ap, 900.0, until=lambda a: laps.append(a.reached_log[-1][1] if a.reached_log else 0)
        or sum(1 for t in set(laps) if t) > 30)
    assert len(ap.reached_log) == 12 and len(ap.mission_set_at) == 12
    assert [r[0] for r in ap.reached_log][-4:] in ([1, 2, 1, 2], [2, 1, 2, 1])
    assert ap.reached_log[-1][1] == max(laps)  # the newest kept
