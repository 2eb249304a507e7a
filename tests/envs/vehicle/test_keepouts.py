"""Keep-outs preloaded into the vehicle's geofence (polygons and circles in world ENU
metres, with an optional top above the ground): a mission that would cross one is
stopped before it (GF_ACTION 2, hold) or returns (3) and the return is guarded too, so
the true path never enters a keep-out below its top; one with a top is flown over above
it. RTK GNSS here: the fence acts on the navigation estimate (centimetres off)."""

from __future__ import annotations

import dataclasses
import math

import pytest
from pymavlink.dialects.v20.common import (
    MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION,
    MAV_CMD_NAV_RETURN_TO_LAUNCH,
    MAV_CMD_NAV_TAKEOFF,
    MAV_FRAME_GLOBAL_TERRAIN_ALT_INT,
    MAV_MISSION_TYPE_FENCE,
    MAV_RESULT_ACCEPTED,
    MAV_RESULT_DENIED,
)

from envs.vehicle import VirtualVehicle
from envs.vehicle.autopilot import Autopilot
from envs.vehicle.px4 import Mode
from sim import KeepOutZone, Stepper, load_scenario, realise
from tests.envs.vehicle.helpers import SEARCH_SCENARIO, fly, item, numbered

RTK_SCENARIO = SEARCH_SCENARIO.replace("search-ap1f.toml", "search-ap1f-rtk.toml")
T11 = MAV_FRAME_GLOBAL_TERRAIN_ALT_INT


def _autopilot(zones_home: list, params: dict | None = None, seed: int = 0) -> Autopilot:
    """An autopilot with keep-outs given relative to its home (moved to world ENU)."""
    sc = load_scenario(RTK_SCENARIO)
    stepper = Stepper(realise(sc, seed), agents=sc.agents[:1])
    e0, n0 = sc.start_enu_m(0)
    zones = []
    for z in zones_home:
        if z.center_enu_m is not None:
            ce, cn = z.center_enu_m
            zones.append(dataclasses.replace(z, center_enu_m=(ce + e0, cn + n0)))
        else:
            zones.append(dataclasses.replace(
                z, polygon_enu_m=tuple((e + e0, n + n0) for e, n in z.polygon_enu_m)))
    ap = Autopilot(stepper, wall_clock=lambda: 0.0, keepouts=zones)
    for k, v in (params or {}).items():
        assert ap.params.set(k, v) is None
    return ap


def _texts(ap: Autopilot) -> list[str]:
    return [e[2] for e in ap.drain_events() if e[0] == "text"]


def _inside_below_top(ap: Autopilot, samples) -> list:
    """Samples whose TRUE position is in a keep-out below its top."""
    out = []
    for s in samples:
        e, n, z = s.truth
        for k in ap.fence.keepouts:
            agl = z - float(ap.world.ground_m(e, n))
            if k.contains(e, n) and (k.top_m is None or agl < k.top_m):
                out.append((s.t_s, k))
    return out


def circle(e: float, n: float, r: float, top_m: float | None = None) -> KeepOutZone:
    return KeepOutZone(name="circle", center_enu_m=(e, n), radius_m=r, top_m=top_m)


def polygon(vertices, top_m: float | None = None) -> KeepOutZone:
    return KeepOutZone(name="polygon", polygon_enu_m=tuple(vertices), top_m=top_m)


CIRCLE = circle(100.0, 0.0, 20.0)
SQUARE = polygon([(85.0, -30.0), (115.0, -30.0), (115.0, 30.0), (85.0, 30.0)])


@pytest.mark.parametrize("zone", [CIRCLE, SQUARE], ids=["circle", "polygon"])
def test_a_mission_across_a_keepout_holds_before_it(zone: KeepOutZone) -> None:
    ap = _autopilot([zone])  # GF_ACTION 2: hold
    ap.set_mission(numbered([item(ap, MAV_CMD_NAV_TAKEOFF, 0, 0, 20.0),
                             item(ap, e=200, n=0, alt=20.0)]))
    assert ap.set_mode(Mode.MISSION)[0] == MAV_RESULT_ACCEPTED
    assert ap.arm()[0] == MAV_RESULT_ACCEPTED
    s = fly(ap, 300.0, until=lambda a: a.mode is Mode.LOITER)
    s += fly(ap, 20.0)
    assert ap.mode is Mode.LOITER and ap.armed
    assert "keep-out ahead (predicted)" in _texts(ap)
    assert _inside_below_top(ap, s) == []
    assert [r[0] for r in ap.reached_log] == [0]  # the waypoint beyond is never reached
    last = s[-1]
    assert last.speed_h < 0.3 and 70.0 < last.pos[0] < 85.0  # stopped a few metres before


def test_a_keepout_with_a_top_is_flown_over_above_it() -> None:
    square = polygon([(60.0, -40.0), (140.0, -40.0), (140.0, 40.0), (60.0, 40.0)], top_m=20.0)
    # 35 m above the ground (frame 11): over it
    ap = _autopilot([square])
    ap.set_mission(numbered([item(ap, MAV_CMD_NAV_TAKEOFF, 0, 0, 35.0, frame=T11),
                             item(ap, e=220, n=0, alt=35.0, frame=T11)]))
    ap.set_mode(Mode.MISSION)
    ap.arm()
    s = fly(ap, 300.0, until=lambda a: len(a.reached_log) == 2)
    assert [r[0] for r in ap.reached_log] == [0, 1]
    over = [x for x in s if ap.fence.keepouts[0].contains(x.truth[0], x.truth[1])]
    assert len(over) > 20 and _inside_below_top(ap, s) == []
    assert "keep-out ahead (predicted)" not in _texts(ap)
    # 12 m above the ground: below its top, so it holds before it
    ap = _autopilot([square])
    ap.set_mission(numbered([item(ap, MAV_CMD_NAV_TAKEOFF, 0, 0, 12.0, frame=T11),
                             item(ap, e=220, n=0, alt=12.0, frame=T11)]))
    ap.set_mode(Mode.MISSION)
    ap.arm()
    s = fly(ap, 300.0, until=lambda a: a.mode is Mode.LOITER)
    s += fly(ap, 15.0)
    assert ap.mode is Mode.LOITER and [r[0] for r in ap.reached_log] == [0]
    assert _inside_below_top(ap, s) == []
    assert s[-1].speed_h < 0.3 and s[-1].pos[0] < 60.0


def test_return_and_landing_are_guarded_too() -> None:
    """GF_ACTION 3: the breach returns; a return whose way home crosses a keep-out (no
    top: the return altitude does not clear it) holds before it instead."""
    zone = circle(75.0, 75.0, 25.0)
    ap = _autopilot([zone], params={"GF_ACTION": 3})
    ap.set_mission(numbered([item(ap, MAV_CMD_NAV_TAKEOFF, 0, 0, 20.0),
                             item(ap, e=150, n=0, alt=20.0),
                             item(ap, e=150, n=150, alt=20.0),
                             item(ap, MAV_CMD_NAV_RETURN_TO_LAUNCH)]))
    ap.set_mode(Mode.MISSION)
    ap.arm()
    s = fly(ap, 400.0, until=lambda a: a.mode is Mode.RTL)
    assert [r[0] for r in ap.reached_log] == [0, 1, 2, 3]
    s += fly(ap, 200.0, until=lambda a: a.mode is Mode.LOITER)
    s += fly(ap, 15.0)
    assert ap.mode is Mode.LOITER and ap.armed  # held on the way home
    assert "keep-out ahead (predicted)" in _texts(ap)
    assert _inside_below_top(ap, s) == []
    # the mission's own crossing returns (GF_ACTION 3), and home is reached
    ap = _autopilot([circle(150.0, 75.0, 20.0)], params={"GF_ACTION": 3})
    ap.set_mission(numbered([item(ap, MAV_CMD_NAV_TAKEOFF, 0, 0, 20.0),
                             item(ap, e=150, n=0, alt=20.0),
                             item(ap, e=150, n=150, alt=20.0)]))
    ap.set_mode(Mode.MISSION)
    ap.arm()
    s = fly(ap, 600.0, until=lambda a: not a.armed)
    assert not ap.armed and math.hypot(s[-1].pos[0], s[-1].pos[1]) < 2.0
    assert [r[0] for r in ap.reached_log] == [0, 1]
    assert _inside_below_top(ap, s) == []


def test_keepouts_deny_arming_inside_and_stay_after_a_fence_upload() -> None:
    ap = _autopilot([circle(0.0, 0.0, 10.0, top_m=5.0)])
    assert ap.arm() == (MAV_RESULT_DENIED, "arming denied: outside the geofence")
    ap = _autopilot([CIRCLE])
    square = [(-300, -300), (300, -300), (300, 300), (-300, 300)]
    ap.set_fence(numbered([item(ap, MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION, e, n, p1=4.0,
                                frame=0, mission_type=MAV_MISSION_TYPE_FENCE)
                           for e, n in square]))
    assert len(ap.fence.inclusion_polygons) == 1 and len(ap.fence.keepouts) == 1
    assert ap.fence.with_keepouts([SQUARE]).keepouts[-1] == SQUARE


def test_the_virtual_vehicle_takes_the_scenarios_keepouts() -> None:
    """By default the scenario's [[search.keepout]] (site-valley: a power line's towers
    and corridor with their tops); or the ones given."""
    sc = load_scenario("site-valley-rtk")
    v = VirtualVehicle(sc, ["udpout:127.0.0.1:9"])
    try:
        assert v.autopilot.fence.keepouts == sc.keepouts and len(sc.keepouts) > 1
        assert all(k.top_m is not None for k in sc.keepouts)
        sys_status = v.telemetry.build(1)
        assert sys_status.onboard_control_sensors_enabled & 1 << 20  # GEOFENCE
    finally:
        v.close()
    zone = circle(0.0, 200.0, 30.0, top_m=25.0)
    v = VirtualVehicle(load_scenario(RTK_SCENARIO), ["udpout:127.0.0.1:9"], keepouts=[zone])
    try:
        assert v.autopilot.fence.keepouts == (zone,)
    finally:
        v.close()
