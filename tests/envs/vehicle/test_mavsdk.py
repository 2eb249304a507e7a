"""The virtual vehicle driven by MAVSDK as the ground station (Mission, MissionRaw,
Action, Telemetry, Param) on 127.0.0.1."""

from __future__ import annotations

import contextlib
import math
import threading
import time
from collections.abc import Iterator

import pytest

from planner.mavlink import TransferConfig, quiet_mavsdk_logs, upload_mission
from planner.mavlink_wire import compare_wire, mission_to_wire
from planner.mission import MAV_CMD_NAV_TAKEOFF, Mission, MissionItem
from tests.envs.vehicle.helpers import SEARCH_SCENARIO
from tests.vehicles import RunningVehicle, running_vehicle


@contextlib.contextmanager
def mavsdk_gcs(url: str) -> Iterator[object]:
    from mavsdk import ComponentType, Configuration, Mavsdk

    quiet_mavsdk_logs()
    m = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
    try:
        assert m.add_any_connection(url).name == "SUCCESS"
        system = m.first_autopilot(30.0)  # a bound that only a missing vehicle reaches
        assert system is not None, "no autopilot within 30 s"
        yield system
    finally:
        m.destroy()


def _until(pred, timeout_s: float, step_s: float = 0.05) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(step_s)
    return pred()


def _points(rv: RunningVehicle, offsets: list[tuple[float, float]]) -> list[tuple[float, float]]:
    ap = rv.autopilot
    h = ap.home.enu
    out = []
    for e, n in offsets:
        lat, lon, _ = ap.frame.to_geodetic(h[0] + e, h[1] + n, h[2])
        out.append((float(lat), float(lon)))
    return out


def test_mavsdk_mission_action_and_telemetry() -> None:
    from mavsdk.autopilot import Autopilot as MavsdkAutopilot
    from mavsdk.plugins.action import Action
    from mavsdk.plugins.mission import Mission as MavsdkMission
    from mavsdk.plugins.mission import MissionItem as MavsdkItem
    from mavsdk.plugins.mission import MissionPlan
    from mavsdk.plugins.telemetry import Telemetry

    with running_vehicle(SEARCH_SCENARIO, speedup=30.0) as rv, \
            mavsdk_gcs(rv.mavsdk_url) as system:
        assert system.autopilot_type() == MavsdkAutopilot.PX4
        mission, action, telemetry = MavsdkMission(system), Action(system), Telemetry(system)
        nan = math.nan
        wps = _points(rv, [(0.0, 60.0), (60.0, 60.0), (60.0, 0.0)])
        items = [MavsdkItem(la, lo, 25.0, 6.0, True, nan, nan, MavsdkItem.CameraAction.NONE,
                            nan, nan, 2.0, nan, nan, MavsdkItem.VehicleAction.NONE)
                 for la, lo in wps]
        mission.upload_mission(MissionPlan(items))
        # MAVSDK's Mission adds a DO_CHANGE_SPEED per item: 6 raw items, frame 3 (relative)
        held = rv.held()
        assert [(w.command, w.frame) for w in held] == [(16, 3), (178, 2)] * 3
        assert [w.param2 for w in held if w.command == 178] == [6.0] * 3
        back = mission.download_mission().mission_items
        assert [(round(b.latitude_deg, 7), round(b.longitude_deg, 7)) for b in back] == \
            [(round(la, 7), round(lo, 7)) for la, lo in wps]
        assert [b.relative_altitude_m for b in back] == [25.0] * 3
        progress: list[tuple[int, int]] = []
        positions: list = []
        lock = threading.Lock()

        def on_progress(p, _ud) -> None:
            with lock:
                progress.append((p.current, p.total))

        def on_position(p, _ud) -> None:
            with lock:
                positions.append(p)

        mission.subscribe_mission_progress(on_progress)
        telemetry.subscribe_position(on_position)
        assert action.get_takeoff_altitude() == pytest.approx(2.5)  # MIS_TAKEOFF_ALT
        action.arm()
        assert _until(telemetry.armed, 30.0)
        mission.start_mission()
        assert _until(mission.is_mission_finished, 30.0), progress[-3:]
        # MAVSDK may call the progress callback after it reports the mission finished:
        # wait for the callback (an event), not for a time
        assert _until(lambda: progress[-1:] == [(3, 3)], 30.0), progress[-3:]
        with lock:
            currents = [c for c, _ in progress]
        assert currents == sorted(currents)  # progress only goes forward
        # MAVSDK's position follows the vehicle: it came within the acceptance radius (2 m,
        # plus a telemetry sample's travel) of the last waypoint and holds near it at 25 m
        # (when the mission reports finished it may still be braking past the point)
        with lock:
            seen = list(positions)

        def off_m(q) -> float:
            d_n = (q.latitude_deg - wps[2][0]) * 111_320.0
            d_e = (q.longitude_deg - wps[2][1]) * 111_320.0 * math.cos(math.radians(wps[2][0]))
            return math.hypot(d_e, d_n)

        assert min(off_m(q) for q in seen) < 2.6
        assert off_m(seen[-1]) < 10.0
        assert seen[-1].relative_altitude_m == pytest.approx(25.0, abs=1.5)
        assert telemetry.in_air()
        # Action: hold, then a take-off in the air is accepted and changes nothing
        # (MAVLink: TAKEOFF when flying is idempotent), then return and land
        action.hold()
        assert _until(lambda: telemetry.flight_mode().name == "HOLD", 30.0)
        action.takeoff()
        assert telemetry.flight_mode().name == "HOLD" and rv.autopilot.mode.name == "LOITER"
        action.return_to_launch()
        assert _until(lambda: telemetry.flight_mode().name == "RETURN_TO_LAUNCH", 30.0)
        assert _until(lambda: not telemetry.armed(), 40.0)
        assert telemetry.landed_state().name == "ON_GROUND"


def test_mavsdk_missionraw_and_action_takeoff() -> None:
    from mavsdk.plugins.action import Action
    from mavsdk.plugins.mission_raw import MissionRaw
    from mavsdk.plugins.telemetry import Telemetry

    with running_vehicle(SEARCH_SCENARIO, speedup=30.0) as rv, \
            mavsdk_gcs(rv.mavsdk_url) as system:
        ap = rv.autopilot
        h = ap.home
        pts = _points(rv, [(30.0, 0.0), (30.0, 30.0)])
        m = Mission(items=(MissionItem(command=MAV_CMD_NAV_TAKEOFF, lat_deg=h.lat_deg,
                                       lon_deg=h.lon_deg, alt_m=12.0),
                           *(MissionItem(lat_deg=la, lon_deg=lo, alt_m=12.0) for la, lo in pts)),
                    home=(h.lat_deg, h.lon_deg, h.alt_m))
        # MissionRaw through planner.mavlink's MAVSDK link (upload + read-back)
        # the vehicle answers: bounds a busy machine cannot reach (the upload takes ms),
        # where MAVSDK's 0.5 s default timed out under load with the vehicle flying at 30x
        report = upload_mission(m, rv.mavsdk_url,
                                config=TransferConfig(connect_timeout_s=30.0,
                                                      message_timeout_s=5.0))
        assert report.backend == "mavsdk" and report.items == 3
        raw = MissionRaw(system).download_mission()
        from planner.mavlink_wire import WireItem

        assert compare_wire(mission_to_wire(m), [WireItem.from_msg(r) for r in raw]) == []
        action, telemetry = Action(system), Telemetry(system)
        action.set_takeoff_altitude(8.0)  # PARAM_SET MIS_TAKEOFF_ALT
        assert _until(lambda: ap.params["MIS_TAKEOFF_ALT"] == 8.0, 30.0)
        modes: list[str] = []  # every mode MAVSDK reports (TAKEOFF may last one heartbeat)
        telemetry.subscribe_flight_mode(lambda mode, _ud: modes.append(mode.name))
        action.arm()
        action.takeoff()
        assert _until(lambda: "HOLD" in modes[modes.index("TAKEOFF"):]
                      if "TAKEOFF" in modes else False, 30.0), modes
        assert telemetry.flight_mode().name == "HOLD"
        assert telemetry.position().relative_altitude_m == pytest.approx(8.0, abs=1.0)
        action.land()
        assert _until(lambda: not telemetry.armed(), 20.0)
        assert not telemetry.in_air()
