"""Mission files: round trips, independent readers (MAVSDK, pymavlink), refusals."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from planner.files import (
    MissionFileError,
    read_mission,
    read_plan,
    read_wpl,
    write_mission,
    write_plan,
    write_wpl,
)
from planner.mavlink import connected
from planner.mavlink_wire import compare_wire, fence_to_wire, mission_to_wire, rally_to_wire
from planner.mission import (
    MAV_CMD_NAV_FENCE_CIRCLE_EXCLUSION,
    MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION,
    MAV_CMD_NAV_FENCE_POLYGON_VERTEX_EXCLUSION,
    MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION,
    MAV_CMD_NAV_RALLY_POINT,
    FenceCircle,
    FencePolygon,
    Mission,
    MissionItem,
    deg_to_e7,
)
from tests.planner.conftest import ANSWERING, sample_mission


def assert_same_mission(a: Mission, b: Mission, *, with_fence: bool = True,
                        with_meta: bool = True) -> None:
    """Equal at int degE7 for lat/lon, 1e-6 m for altitudes, NaN == NaN for params."""
    assert len(a.items) == len(b.items)
    for i, (x, y) in enumerate(zip(a.items, b.items, strict=True)):
        assert (x.command, x.frame, x.autocontinue) == (y.command, y.frame, y.autocontinue), i
        assert (deg_to_e7(x.lat_deg), deg_to_e7(x.lon_deg)) == (
            deg_to_e7(y.lat_deg), deg_to_e7(y.lon_deg)), i
        assert abs(x.alt_m - y.alt_m) <= 1e-6, i
        for p, q in zip((x.param1, x.param2, x.param3, x.param4),
                        (y.param1, y.param2, y.param3, y.param4), strict=True):
            assert (math.isnan(p) and math.isnan(q)) or p == q, i
    assert (deg_to_e7(a.home[0]), deg_to_e7(a.home[1])) == (
        deg_to_e7(b.home[0]), deg_to_e7(b.home[1]))
    assert abs(a.home[2] - b.home[2]) <= 1e-6
    if with_fence:
        assert a.polygons == b.polygons
        assert a.circles == b.circles
        assert a.rally_deg == b.rally_deg
    if with_meta:
        assert (a.cruise_speed_m_s, a.hover_speed_m_s, a.vehicle_type, a.firmware) == (
            b.cruise_speed_m_s, b.hover_speed_m_s, b.vehicle_type, b.firmware)


# ---------------------------------------------------------------- strategies

lat = st.floats(-90.0, 90.0, allow_nan=False)
lon = st.floats(-180.0, 180.0, allow_nan=False)
alt = st.floats(-500.0, 10_000.0, allow_nan=False)
param = st.floats(-1e6, 1e6, allow_nan=False, allow_infinity=False)
items = st.builds(
    MissionItem,
    command=st.sampled_from([16, 17, 19, 20, 21, 22, 178, 183, 206]),
    frame=st.sampled_from([0, 2, 3, 5, 6, 10, 11]),
    lat_deg=lat, lon_deg=lon, alt_m=alt,
    param1=param, param2=param, param3=param,
    param4=st.one_of(st.just(math.nan), param),
    autocontinue=st.booleans(),
)
polygons = st.builds(
    FencePolygon,
    vertices_deg=st.lists(st.tuples(lat, lon), min_size=3, max_size=8).map(tuple),
    inclusion=st.booleans(),
)
circles = st.builds(FenceCircle, lat_deg=lat, lon_deg=lon,
                    radius_m=st.floats(0.1, 1e5, allow_nan=False), inclusion=st.booleans())
missions = st.builds(
    Mission,
    items=st.lists(items, max_size=30).map(tuple),
    home=st.tuples(lat, lon, alt),
    polygons=st.lists(polygons, max_size=3).map(tuple),
    circles=st.lists(circles, max_size=3).map(tuple),
    rally_deg=st.lists(st.tuples(lat, lon, alt), max_size=3).map(tuple),
    cruise_speed_m_s=st.floats(0.5, 50.0),
    hover_speed_m_s=st.floats(0.5, 20.0),
    vehicle_type=st.sampled_from(["multirotor", "fixed_wing", "vtol", "rover", "generic"]),
    firmware=st.sampled_from(["px4", "ardupilot", "generic"]),
)
file_settings = settings(max_examples=60, deadline=None,
                         suppress_health_check=[HealthCheck.function_scoped_fixture])


# ---------------------------------------------------------------- round trips


@file_settings
@given(mission=missions)
def test_plan_round_trip(tmp_path: Path, mission: Mission) -> None:
    path = tmp_path / "m.plan"
    write_plan(mission, path)
    back = read_plan(path)
    assert_same_mission(mission, back)
    assert_same_mission(read_mission(path), back)
    # the file is strict JSON: NaN is null, never a bare token
    text = path.read_text()
    json.loads(text, parse_constant=lambda c: pytest.fail(f"bare {c} in .plan"))


@file_settings
@given(mission=missions)
def test_wpl_round_trip(tmp_path: Path, mission: Mission) -> None:
    path = tmp_path / "m.waypoints"
    write_wpl(mission, path, drop_fence=True)
    back = read_wpl(path)
    assert_same_mission(mission, back, with_fence=False, with_meta=False)
    assert_same_mission(read_mission(path), back)


def test_write_mission_dispatches_by_suffix(tmp_path: Path) -> None:
    m = sample_mission(3)
    bare = Mission(items=m.items, home=m.home)
    write_mission(m, tmp_path / "a.plan")
    write_mission(bare, tmp_path / "b.waypoints")
    write_mission(bare, tmp_path / "c.txt")
    assert json.loads((tmp_path / "a.plan").read_text())["fileType"] == "Plan"
    for name in ("b.waypoints", "c.txt"):
        assert (tmp_path / name).read_text().splitlines()[0] == "QGC WPL 110"
        assert_same_mission(bare, read_mission(tmp_path / name))
    assert_same_mission(m, read_mission(tmp_path / "a.plan"))
    with pytest.raises(MissionFileError, match="unknown mission file type"):
        write_mission(m, tmp_path / "d.json")
    with pytest.raises(MissionFileError, match="unknown mission file type"):
        read_mission(tmp_path / "d.kml")


def test_plan_layout(tmp_path: Path) -> None:
    m = sample_mission(4)
    path = tmp_path / "m.plan"
    write_plan(m, path)
    plan = json.loads(path.read_text())
    assert (plan["fileType"], plan["version"]) == ("Plan", 1)
    mission = plan["mission"]
    assert (mission["version"], mission["firmwareType"], mission["vehicleType"]) == (2, 12, 2)
    assert mission["plannedHomePosition"] == list(m.home)
    assert mission["items"][1]["params"][3] == 90.0  # yaw set
    wp = mission["items"][2]
    assert wp["type"] == "SimpleItem"
    assert wp["params"][3] is None  # NaN yaw
    assert wp["params"][4:] == [m.items[2].lat_deg, m.items[2].lon_deg, m.items[2].alt_m]
    assert wp["AMSLAltAboveTerrain"] is None
    assert (wp["Altitude"], wp["AltitudeMode"], wp["frame"]) == (m.items[2].alt_m, 1, 6)
    assert [it["doJumpId"] for it in mission["items"]] == list(range(1, len(m.items) + 1))
    assert plan["geoFence"]["version"] == 2
    assert plan["geoFence"]["polygons"][0]["polygon"][0] == list(m.polygons[0].vertices_deg[0])
    assert plan["geoFence"]["circles"][0]["circle"] == {"center": [36.7151, -4.4775],
                                                        "radius": 12.5}
    assert plan["rallyPoints"] == {"points": [list(p) for p in m.rally_deg], "version": 2}


def test_wpl_layout_and_home_line(tmp_path: Path) -> None:
    m = sample_mission(2)
    path = tmp_path / "m.waypoints"
    write_wpl(Mission(items=m.items, home=m.home), path)
    lines = path.read_text().splitlines()
    assert lines[0] == "QGC WPL 110"
    home = lines[1].split("\t")
    assert home[:4] == ["0", "1", "0", "16"] and home[-1] == "1"
    assert [float(v) for v in home[8:11]] == list(m.home)
    first = lines[2].split("\t")
    assert len(first) == 12 and first[:4] == ["1", "0", "6", "22"]
    assert all(line.split("\t")[1] == "0" for line in lines[2:])
    assert len(lines) == 2 + len(m.items)


def test_wpl_refuses_fence_unless_dropped(tmp_path: Path) -> None:
    m = sample_mission(2)
    with pytest.raises(MissionFileError, match="cannot hold a geofence"):
        write_wpl(m, tmp_path / "m.waypoints")
    assert not (tmp_path / "m.waypoints").exists()
    write_wpl(m, tmp_path / "m.waypoints", drop_fence=True)
    assert_same_mission(m, read_wpl(tmp_path / "m.waypoints"), with_fence=False,
                        with_meta=False)


# ---------------------------------------------------------------- independent readers


def test_wpl_read_by_pymavlink_mavwploader(tmp_path: Path) -> None:
    from pymavlink import mavwp

    m = sample_mission(12)
    path = tmp_path / "m.waypoints"
    write_wpl(Mission(items=m.items, home=m.home), path)
    loader = mavwp.MAVWPLoader()
    assert loader.load(str(path)) == len(m.items) + 1
    home = loader.wp(0)
    assert (deg_to_e7(home.x), deg_to_e7(home.y), home.z) == (
        deg_to_e7(m.home[0]), deg_to_e7(m.home[1]), m.home[2])
    assert home.current == 1
    for i, it in enumerate(m.items):
        w = loader.wp(i + 1)
        assert w.seq == i + 1 and w.current == 0
        assert (w.command, w.frame, w.autocontinue) == (it.command, it.frame,
                                                        int(it.autocontinue))
        assert (deg_to_e7(w.x), deg_to_e7(w.y)) == (it.x_e7, it.y_e7)
        assert w.z == it.alt_m
        for p, q in ((w.param1, it.param1), (w.param2, it.param2), (w.param3, it.param3),
                     (w.param4, it.param4)):
            assert (math.isnan(p) and math.isnan(q)) or p == q


def test_plan_imported_by_mavsdk(tmp_path: Path, mavsdk_peer) -> None:
    """MAVSDK's own QGroundControl importer reads what was planned, exactly."""
    m = sample_mission(20)
    path = tmp_path / "m.plan"
    write_plan(m, path)
    with connected(mavsdk_peer.mavsdk_url, ANSWERING) as link:
        imported = link.import_qgc_plan(path)
        bad = tmp_path / "bare-nan.plan"
        bad.write_text(path.read_text().replace("null", "NaN"))
        with pytest.raises(ValueError, match="FAILED_TO_PARSE_QGC_PLAN"):
            link.import_qgc_plan(bad)  # why the writer must use allow_nan=False
    got = imported[0]
    assert compare_wire(mission_to_wire(m), got) == []
    assert [w.current for w in got] == [1] + [0] * (len(got) - 1)
    assert [(w.x, w.y) for w in got] == [(it.x_e7, it.y_e7) for it in m.items]
    yaw_nan = [math.isnan(it.param4) for it in m.items]
    assert any(yaw_nan) and [math.isnan(w.param4) for w in got] == yaw_nan
    fence = imported[1]
    ours = fence_to_wire(m)
    assert [(w.command, w.x, w.y, w.param1) for w in fence] == [
        (w.command, w.x, w.y, w.param1) for w in ours]
    assert [w.command for w in ours] == (
        [MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION] * 4
        + [MAV_CMD_NAV_FENCE_POLYGON_VERTEX_EXCLUSION] * 3
        + [MAV_CMD_NAV_FENCE_CIRCLE_EXCLUSION, MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION])
    rally = imported[2]
    assert [(w.command, w.x, w.y, w.z) for w in rally] == [
        (MAV_CMD_NAV_RALLY_POINT, w.x, w.y, w.z) for w in rally_to_wire(m)]


# ---------------------------------------------------------------- refusals


def _plan_text(mutate) -> str:
    plan = json.loads(json.dumps(_base_plan()))
    mutate(plan)
    return json.dumps(plan)


_BASE: dict | None = None


def _base_plan() -> dict:
    global _BASE
    if _BASE is None:
        from planner.files import plan_dict

        _BASE = plan_dict(sample_mission(3))
    return _BASE


def _set(path: tuple, value):
    def mutate(plan: dict) -> None:
        obj = plan
        for key in path[:-1]:
            obj = obj[key]
        obj[path[-1]] = value
    return mutate


BAD_PLANS = {
    "malformed JSON": ('{"fileType": "Plan", ', "malformed JSON"),
    "not an object": ("[1, 2]", "not a JSON object"),
    "bare NaN": (_plan_text(lambda p: None).replace('"Altitude": 45.0', '"Altitude": NaN', 1),
                 "bare NaN"),
    "wrong fileType": (_plan_text(_set(("fileType",), "GeoFence")), "fileType"),
    "plan version": (_plan_text(_set(("version",), 2)), "unsupported version 2"),
    "mission version": (_plan_text(_set(("mission", "version"), 1)),
                        "mission: unsupported version 1"),
    "fence version": (_plan_text(_set(("geoFence", "version"), 1)),
                      "geoFence: unsupported version 1"),
    "rally version": (_plan_text(_set(("rallyPoints", "version"), 3)),
                      "rallyPoints: unsupported version 3"),
    "no items": (_plan_text(lambda p: p["mission"].pop("items")), "missing key 'items'"),
    "complex item": (_plan_text(lambda p: p["mission"]["items"].append(
        {"type": "ComplexItem", "complexItemType": "survey"})), "ComplexItem \\(survey\\)"),
    "unknown type": (_plan_text(_set(("mission", "items", 0, "type"), "FancyItem")),
                     "unknown item type"),
    "lat > 90": (_plan_text(_set(("mission", "items", 1, "params", 4), 90.5)),
                 "latitude 90.5 outside"),
    "lon < -180": (_plan_text(_set(("mission", "items", 1, "params", 5), -180.25)),
                   "longitude -180.25 outside"),
    "null lat": (_plan_text(_set(("mission", "items", 1, "params", 4), None)),
                 "expected a number"),
    "huge alt": (_plan_text(_set(("mission", "items", 1, "params", 6), 12345.678)).replace(
        "12345.678", "1e400"), "non-finite"),
    "six params": (_plan_text(lambda p: p["mission"]["items"][0]["params"].pop()),
                   "6 values, expected 7"),
    "string command": (_plan_text(_set(("mission", "items", 0, "command"), "16")),
                       "command: expected"),
    "bad home": (_plan_text(_set(("mission", "plannedHomePosition"), [95.0, 0.0, 0.0])),
                 "latitude 95.0"),
    "2-vertex polygon": (_plan_text(_set(("geoFence", "polygons", 0, "polygon"),
                                         [[36.7, -4.4], [36.8, -4.4]])), "need >= 3"),
    "zero radius": (_plan_text(_set(("geoFence", "circles", 0, "circle", "radius"), 0)),
                    "radius 0.0 m must be"),
    "rally out of range": (_plan_text(_set(("rallyPoints", "points"), [[0.0, 200.0, 1.0]])),
                           "longitude 200.0"),
}


@pytest.mark.parametrize("case", sorted(BAD_PLANS))
def test_bad_plan_refused(tmp_path: Path, case: str) -> None:
    text, message = BAD_PLANS[case]
    path = tmp_path / "bad.plan"
    path.write_text(text)
    with pytest.raises(MissionFileError, match=message) as info:
        read_plan(path)
    assert str(path) in str(info.value) and "\n" not in str(info.value)


_GOOD_WPL = ("QGC WPL 110\n0\t1\t0\t16\t0\t0\t0\t0\t36.7\t-4.47\t100\t1\n"
             "1\t0\t6\t16\t0\t0\t0\tnan\t36.71\t-4.48\t45\t1\n")
BAD_WPLS = {
    "header": (_GOOD_WPL.replace("QGC WPL 110", "QGC WPL 100"), "expected 'QGC WPL 110'"),
    "empty": ("", "expected 'QGC WPL 110'"),
    "no home": ("QGC WPL 110\n", "no home line"),
    "fields": (_GOOD_WPL.replace("\t1\n", "\n"), "11 fields, expected 12"),
    "index gap": (_GOOD_WPL.replace("\n1\t0", "\n2\t0"), "index 2, expected 1"),
    "not a number": (_GOOD_WPL.replace("36.71", "36,71"), "latitude: not a number"),
    "nan lat": (_GOOD_WPL.replace("36.71", "nan"), "latitude: non-finite"),
    "lat > 90": (_GOOD_WPL.replace("36.71", "91.0"), "latitude 91.0 outside"),
    "lon > 180": (_GOOD_WPL.replace("-4.48", "-181"), "longitude -181.0 outside"),
    "inf param": (_GOOD_WPL.replace("\tnan\t", "\tinf\t"), "param4: non-finite"),
    "bad frame": (_GOOD_WPL.replace("\t0\t6\t", "\t0\t300\t"), "frame: 300 outside"),
}


@pytest.mark.parametrize("case", sorted(BAD_WPLS))
def test_bad_wpl_refused(tmp_path: Path, case: str) -> None:
    text, message = BAD_WPLS[case]
    path = tmp_path / "bad.waypoints"
    path.write_text(text)
    with pytest.raises(MissionFileError, match=message):
        read_wpl(path)


def test_good_wpl_sample_reads(tmp_path: Path) -> None:
    path = tmp_path / "ok.waypoints"
    path.write_text(_GOOD_WPL)
    m = read_wpl(path)
    assert m.home == (36.7, -4.47, 100.0)
    assert len(m.items) == 1 and math.isnan(m.items[0].param4)
    assert (m.items[0].x_e7, m.items[0].y_e7, m.items[0].frame) == (367100000, -44800000, 6)


def test_missing_file_and_unwritable_values(tmp_path: Path) -> None:
    with pytest.raises(MissionFileError, match="cannot read"):
        read_mission(tmp_path / "none.plan")
    m = sample_mission(2)
    bad_items = (MissionItem(lat_deg=math.nan, lon_deg=0.0, alt_m=1.0),)
    for bad in (Mission(items=bad_items, home=m.home),
                Mission(items=(MissionItem(lat_deg=0.0, lon_deg=0.0, alt_m=math.inf),),
                        home=m.home),
                Mission(items=m.items, home=(91.0, 0.0, 0.0))):
        for name in ("x.plan", "x.waypoints"):
            with pytest.raises(MissionFileError):
                write_mission(bad, tmp_path / name)
            assert not (tmp_path / name).exists()
    with pytest.raises(MissionFileError, match="unknown firmware"):
        write_plan(Mission(items=m.items, home=m.home, firmware="betaflight"), tmp_path / "f.plan")


def test_do_jump_target_survives_both_formats(tmp_path):
    """DO_JUMP param1 is the target's item index in a Mission, index + 1 in the files."""
    from planner.files import read_plan, read_wpl, write_plan, write_wpl
    from planner.mission import Mission, MissionItem

    wp = [MissionItem(lat_deg=36.715 + 1e-4 * k, lon_deg=-4.478, alt_m=40.0) for k in range(3)]
    jump = MissionItem(command=177, frame=2, param1=1.0, param2=3.0, param4=0.0)
    m = Mission(items=(*wp, jump), home=(36.715, -4.478, 100.0))
    write_plan(m, tmp_path / "j.plan")
    write_wpl(m, tmp_path / "j.waypoints")
    import json

    raw = json.loads((tmp_path / "j.plan").read_text())["mission"]["items"]
    assert raw[3]["params"][0] == 2.0 and raw[1]["doJumpId"] == 2  # QGC: doJumpId of item 1
    wpl_line = (tmp_path / "j.waypoints").read_text().splitlines()[5].split("\t")
    assert float(wpl_line[4]) == 2.0  # item 1 is line 2 (home is line 0)
    for back in (read_plan(tmp_path / "j.plan"), read_wpl(tmp_path / "j.waypoints")):
        assert back.items[3].command == 177 and back.items[3].param1 == 1.0
