"""Fixtures: real MAVLink peers on 127.0.0.1 (free ports picked at runtime): the
virtual vehicle of ``osa vehicle`` for the happy paths, MAVSDK's MissionRawServer
and scripted pymavlink vehicles where they add something (tests/planner/peers.py)."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator

import pytest

from planner.mavlink import TransferConfig
from planner.mission import (
    MAV_CMD_DO_CHANGE_SPEED,
    MAV_CMD_NAV_LAND,
    MAV_CMD_NAV_TAKEOFF,
    MAV_CMD_NAV_WAYPOINT,
    MAV_FRAME_GLOBAL_RELATIVE_ALT,
    FenceCircle,
    FencePolygon,
    Mission,
    MissionItem,
)
from tests.planner.peers import MavsdkVehiclePeer, ScriptedMavlinkVehicle, VehicleScript
from tests.vehicles import RunningVehicle, running_vehicle


def gaussian_hills(*hills: tuple[float, float, float, float]):
    """The simulator's terrain with only Gaussian hills (east, north, height, sigma):
    the planner plans over ``sim``'s own terrain type (the planner's TerrainModel)."""
    from sim.terrain import Hill, HillsTerrain

    return HillsTerrain(
        slope_e=0.0, slope_n=0.0, ripple_amplitude_m=0.0,
        hills=tuple(Hill(e_m=e, n_m=n, height_m=h, sigma_m=s) for e, n, h, s in hills),
    )


# Peers that answer (the vehicle, MAVSDK's server, a scripted vehicle that NACKs or
# reads back wrong) never make a transfer wait for a timeout: their bounds are long, so
# a busy machine makes an answer late, never lost (these transfers take milliseconds
# whatever the bound). Only a peer that stops answering waits for a timeout: SILENT
# (half a second, after a heartbeat found within the long connect bound).
ANSWERING = TransferConfig(connect_timeout_s=30.0, message_timeout_s=5.0, retries=3)
SILENT = TransferConfig(connect_timeout_s=30.0, message_timeout_s=0.5, retries=3)


@pytest.fixture(scope="module")
def px4_vehicle() -> Iterator[RunningVehicle]:
    """``osa vehicle``'s autopilot (three-aps, landed), listening on udpin 127.0.0.1."""
    with running_vehicle("three-aps") as v:
        yield v


@pytest.fixture(scope="module")
def mavsdk_peer() -> Iterator[MavsdkVehiclePeer]:
    """MAVSDK's autopilot-side MissionRawServer, listening on udpin://127.0.0.1:PORT."""
    with MavsdkVehiclePeer() as peer:
        yield peer


@pytest.fixture
def scripted_vehicle() -> Iterator[Callable[[VehicleScript], ScriptedMavlinkVehicle]]:
    """Factory for misbehaving pymavlink vehicles; all are stopped after the test."""
    started: list[ScriptedMavlinkVehicle] = []

    def make(script: VehicleScript) -> ScriptedMavlinkVehicle:
        v = ScriptedMavlinkVehicle(script).start()
        started.append(v)
        return v

    yield make
    for v in started:
        v.stop()


def sample_mission(n_waypoints: int = 20) -> Mission:
    """Takeoff, waypoints with NaN and set yaw, a speed change, a frame-3 item, land."""
    lat0, lon0 = 36.7149123, -4.4781234
    items = [MissionItem(command=MAV_CMD_NAV_TAKEOFF, lat_deg=lat0, lon_deg=lon0, alt_m=45.0)]
    for i in range(n_waypoints):
        items.append(MissionItem(
            lat_deg=lat0 + 1.234567e-4 * i, lon_deg=lon0 - 0.987654e-4 * i,
            alt_m=45.0 + 0.25 * i, param1=1.5 if i % 5 == 0 else 0.0, param2=2.0,
            param4=math.nan if i % 2 else 90.0 + i))
    items.insert(3, MissionItem(command=MAV_CMD_DO_CHANGE_SPEED, frame=2, lat_deg=0.0,
                                lon_deg=0.0, alt_m=0.0, param1=1.0, param2=7.5, param3=-1.0,
                                param4=0.0))
    items.append(MissionItem(command=MAV_CMD_NAV_WAYPOINT, frame=MAV_FRAME_GLOBAL_RELATIVE_ALT,
                             lat_deg=lat0 - 5e-5, lon_deg=lon0 + 5e-5, alt_m=30.0))
    items.append(MissionItem(command=MAV_CMD_NAV_LAND, lat_deg=lat0, lon_deg=lon0, alt_m=0.0))
    return Mission(
        items=tuple(items), home=(lat0, lon0, 108.25),
        polygons=(FencePolygon(vertices_deg=((36.713, -4.481), (36.718, -4.481),
                                             (36.718, -4.474), (36.713, -4.474))),
                  FencePolygon(vertices_deg=((36.7150, -4.4790), (36.7155, -4.4790),
                                             (36.7152, -4.4785)), inclusion=False)),
        circles=(FenceCircle(lat_deg=36.7151, lon_deg=-4.4775, radius_m=12.5),
                 FenceCircle(lat_deg=36.7149, lon_deg=-4.4781, radius_m=400.0,
                             inclusion=True)),
        rally_deg=((36.7140, -4.4790, 30.0), (36.7160, -4.4770, 35.5)),
        name="sample")


def write_mission_file(m: Mission, directory, suffix: str) -> tuple[Mission, object]:
    """Write ``m`` as ``.plan`` or ``.waypoints`` (WPL holds no fence: dropped there);
    return the mission the file holds and its path."""
    from planner.files import write_plan, write_wpl

    path = directory / f"mission{suffix}"
    if suffix == ".plan":
        write_plan(m, path)
    else:
        m = Mission(items=m.items, home=m.home)
        write_wpl(m, path)
    return m, path


# the bounds of the CLI upload tests against answering peers (see ANSWERING)
CLI_ANSWERING = ("--timeout", "30", "--message-timeout", "5", "--retries", "3")
