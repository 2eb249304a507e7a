"""Ground stations the vehicle was not written against: what each one expects of a
PX4/ArduPilot autopilot, with real peers on 127.0.0.1 (docs/vehicle.md). Each test
failed before its fix.

- A MAVLink 1-only ground station (pymavlink's v1.0 dialect on a bare UDP socket: it
  cannot read a MAVLink 2 frame) sees the vehicle, uploads a mission the legacy way
  (MISSION_COUNT, MISSION_REQUEST, float MISSION_ITEM), reads it back, arms and reads a
  parameter, all in MAVLink 1 framing; the PROTOCOL_VERSION it asks for comes in
  MAVLink 2 framing all the same (as PX4 sends it).
- A legacy upload loop over MAVLink 2 (it sends float MISSION_ITEMs and waits for
  MISSION_REQUEST only, as scripts built on pymavlink's ``mavwp`` do) is asked in
  that form once it has sent one, and gets through; the same ground station moving on
  to MISSION_ITEM_INT gets MISSION_REQUEST_INT again. MAVSDK under an identity that
  spoke the float form refuses a MISSION_REQUEST (MISSION_ACK UNSUPPORTED) and is asked
  again in the INT form, as PX4 negotiates it.
- The MAVLink version handshake (MAV_CMD_REQUEST_PROTOCOL_VERSION, REQUEST_MESSAGE 300)
  is acknowledged and answered, as the specification asks of every node.
- MAVSDK's Telemetry.altitude, position_velocity_ned and get_gps_global_origin (PX4's
  ALTITUDE and LOCAL_POSITION_NED streams, GPS_GLOBAL_ORIGIN on request).
- A TCP ground station that reconnects mid-upload, or hangs up, locks no one out; two
  ground stations on one ``udpin`` port each get their own answers only; one heard in
  MAVLink 2 that restarts in MAVLink 1 (QGroundControl) keeps hearing MAVLink 2; a
  MAVLink 1 and a MAVLink 2 one with the same ids on two links each get their own.
- MAVSDK as a companion computer (the vehicle's own system id) is answered.
- LOG_REQUEST_LIST, PING, partial mission lists, standard (base-only) mode changes, a
  fence item sent with the mission's type, are answered at once, never left waiting.
- PX4's payload mission items are taken; INT32_MAX is an unset latitude/longitude; a
  take-off sent again (its ACK lost) is ACCEPTED; ATTITUDE_QUATERNION on request.
- A legacy float item's NaN position reads back as NaN; one whose x or y no
  MISSION_ITEM_INT can carry is refused instead of stopping the vehicle.
- MISSION_CURRENT's ``total`` is UINT16_MAX without a mission (0 means "not supported");
  DO_SET_MISSION_CURRENT to no item is FAILED, as MAVLink and PX4 answer it.
- The mission protocol addressed to component 190 (older ground stations) is answered.
- MAVLink FTP requests get a NAK (UnknownCommand) at once: MAVSDK's Ftp says UNSUPPORTED.
- Garbage and odd frames on the port (random bytes, cut frames, MAVLink 1, non-UTF-8
  names, extreme values) stop nothing.
"""

from __future__ import annotations

import math
import socket
import struct
import time

import numpy as np
import pytest
from pymavlink.dialects.v10 import common as mavlink1
from pymavlink.dialects.v20.common import (
    MAV_CMD_COMPONENT_ARM_DISARM,
    MAV_CMD_NAV_WAYPOINT,
    MAV_CMD_REQUEST_MESSAGE,
    MAV_CMD_REQUEST_PROTOCOL_VERSION,
    MAV_FRAME_GLOBAL_RELATIVE_ALT,
    MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
    MAV_MISSION_ACCEPTED,
    MAV_RESULT_ACCEPTED,
)

from envs.vehicle import VirtualVehicle
from envs.vehicle.px4 import Mode
from sim import load_scenario
from tests.envs.vehicle.helpers import SEARCH_SCENARIO, Gcs, free_tcp_port, until
from tests.net import LOOPBACK
from tests.vehicles import running_vehicle

PROTOCOL_VERSION_ID = 300


def _waypoints(rv, n: int) -> list[tuple[float, float, float]]:
    """``n`` points (lat, lon in degrees, 20 m above home) 30 m apart north of home."""
    ap = rv.autopilot
    h = ap.home.enu
    out = []
    for k in range(n):
        lat, lon, _ = ap.frame.to_geodetic(h[0], h[1] + 30.0 * (k + 1), h[2])
        out.append((float(lat), float(lon), 20.0))
    return out


def _f32(x: float) -> float:
    """``x`` as a MAVLink float field carries it."""
    return float(np.float32(x))


class Mavlink1Gcs:
    """A ground station that speaks and reads MAVLink 1 only (system 250)."""

    def __init__(self, port: int, source_system: int = 250, local_port: int = 0) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.settimeout(0.2)
        if local_port:  # the address of a ground station that was there before
            self.sock.bind((LOOPBACK, local_port))
        self.addr = (LOOPBACK, port)
        gcs = self

        class _Out:
            def write(self, buf: bytes) -> None:
                gcs.sock.sendto(buf, gcs.addr)

        self.mav = mavlink1.MAVLink(_Out(), srcSystem=source_system, srcComponent=190)
        self.mav.robust_parsing = True
        self.datagrams: list[bytes] = []
        self._hb = -math.inf

    def recv(self) -> list:
        now = time.monotonic()
        if now - self._hb > 0.3:  # a ground station's heartbeat keeps the link
            self._hb = now
            self.mav.heartbeat_send(6, 8, 0, 0, 0)
        try:
            data = self.sock.recv(65536)
        except TimeoutError:
            return []
        self.datagrams.append(data)
        return [m for m in self.mav.parse_buffer(data) or [] if m.get_type() != "BAD_DATA"]

    def wait(self, kind: str, timeout_s: float = 10.0, where=None):
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            for m in self.recv():
                if m.get_type() == kind and (where is None or where(m)):
                    return m
        raise TimeoutError(f"no {kind} within {timeout_s:g} s")

    def close(self) -> None:
        self.sock.close()


def _protocol_version_frames(datagrams: list[bytes]) -> list[tuple[int, int, int]]:
    """(version, min, max) of every MAVLink 2 PROTOCOL_VERSION frame in the datagrams."""
    out = []
    for d in datagrams:
        k = d.find(b"\xfd")
        while 0 <= k and k + 10 <= len(d):
            length = d[k + 1]
            msg_id = d[k + 7] | d[k + 8] << 8 | d[k + 9] << 16
            if msg_id == PROTOCOL_VERSION_ID:
                payload = d[k + 10:k + 10 + length] + bytes(22)
                out.append(struct.unpack_from("<HHH", payload))
            k = d.find(b"\xfd", k + 1)
    return out


def test_a_mavlink1_ground_station_uploads_reads_back_and_arms() -> None:
    with running_vehicle(SEARCH_SCENARIO, speedup=2.0) as rv:
        gcs = Mavlink1Gcs(rv.port)
        try:
            hb = gcs.wait("HEARTBEAT", where=lambda m: m.get_srcSystem() == 1)
            assert (hb.type, hb.autopilot) == (2, 12)  # a PX4 quadrotor
            gcs.wait("GLOBAL_POSITION_INT")  # the streams in MAVLink 1 too
            points = _waypoints(rv, 3)
            # legacy upload: asked with MISSION_REQUEST (the MAVLink 1 count says so)
            gcs.mav.mission_count_send(1, 1, len(points))
            for k in range(len(points)):
                req = gcs.wait("MISSION_REQUEST", where=lambda m, k=k: m.seq == k)
                lat, lon, alt = points[req.seq]
                gcs.mav.mission_item_send(1, 1, req.seq, MAV_FRAME_GLOBAL_RELATIVE_ALT,
                                          MAV_CMD_NAV_WAYPOINT, int(k == 0), 1,
                                          0, 0, 0, math.nan, lat, lon, alt)
            assert gcs.wait("MISSION_ACK").type == MAV_MISSION_ACCEPTED
            held = rv.held()
            assert [w.command for w in held] == [MAV_CMD_NAV_WAYPOINT] * 3
            for w, (lat, lon, _) in zip(held, points, strict=True):  # float32 on the wire
                assert abs(w.x / 1e7 - _f32(lat)) < 1e-7 and abs(w.y / 1e7 - _f32(lon)) < 1e-7
            # download: MISSION_REQUEST_LIST, MISSION_REQUEST -> float MISSION_ITEM
            gcs.mav.mission_request_list_send(1, 1)
            assert gcs.wait("MISSION_COUNT").count == 3
            for k, (lat, lon, alt) in enumerate(points):
                gcs.mav.mission_request_send(1, 1, k)
                it = gcs.wait("MISSION_ITEM", where=lambda m, k=k: m.seq == k)
                assert abs(it.x - _f32(lat)) < 1e-7 and abs(it.y - _f32(lon)) < 1e-7
                assert it.z == alt
            # a parameter and a command
            gcs.mav.param_request_read_send(1, 1, b"NAV_ACC_RAD", -1)
            assert gcs.wait("PARAM_VALUE").param_value == rv.autopilot.params["NAV_ACC_RAD"]
            gcs.mav.command_long_send(1, 1, MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0,
                                      0, 0)
            ack = gcs.wait("COMMAND_ACK", where=lambda m: m.command == 400)
            assert ack.result == MAV_RESULT_ACCEPTED
            gcs.wait("HEARTBEAT", where=lambda m: m.get_srcSystem() == 1
                     and m.base_mode & 128)  # armed
            # the version handshake: acknowledged, its answer in MAVLink 2 framing
            gcs.mav.command_long_send(1, 1, MAV_CMD_REQUEST_PROTOCOL_VERSION, 0, 1, 0, 0, 0,
                                      0, 0, 0)
            ack = gcs.wait("COMMAND_ACK", where=lambda m: m.command == 519)
            assert ack.result == MAV_RESULT_ACCEPTED
            deadline = time.monotonic() + 10.0
            while not _protocol_version_frames(gcs.datagrams) \
                    and time.monotonic() < deadline:
                gcs.recv()
            assert _protocol_version_frames(gcs.datagrams) == [(200, 100, 200)]
        finally:
            gcs.close()


def test_a_mavlink2_ground_station_restarting_in_mavlink1_keeps_hearing_mavlink2() -> None:
    """QGroundControl starts in MAVLink 1 and switches on the first MAVLink 2 frame it
    hears: the same ground station (255/190, from the same UDP port) heard in MAVLink 2
    before and now writing MAVLink 1 for longer than the grace keeps getting MAVLink 2,
    or it would never switch back (and lose mission_type: no fence, no rally)."""
    with running_vehicle(SEARCH_SCENARIO, speedup=2.0) as rv:
        first = Gcs(rv.pymavlink_url)  # MAVLink 2, 255/190
        local_port = first.conn.port.getsockname()[1]
        first.close()
        again = Mavlink1Gcs(rv.port, source_system=255, local_port=local_port)
        try:
            t0 = time.monotonic()
            while time.monotonic() - t0 < 3.0:  # past the 2 s grace, writing MAVLink 1
                again.recv()
            again.datagrams.clear()
            deadline = time.monotonic() + 10.0
            while len(again.datagrams) < 5 and time.monotonic() < deadline:
                again.recv()
            assert len(again.datagrams) >= 5
            assert all(d[0] == 0xFD for d in again.datagrams)  # MAVLink 2 frames
        finally:
            again.close()


def test_the_same_ids_on_two_links_each_get_their_own_mavlink_version() -> None:
    """A MAVLink 2 ground station and a MAVLink 1-only one with the same ids (255/190)
    on two links (two addresses on the vehicle's udpin port): the MAVLink 1 one gets
    MAVLink 1 frames once its grace is over, the other keeps MAVLink 2. The version
    used to be remembered by ids across links: the MAVLink 1 one heard MAVLink 2 frames
    it cannot read for ever."""
    with running_vehicle(SEARCH_SCENARIO, speedup=2.0) as rv:
        two = Gcs(rv.pymavlink_url)  # MAVLink 2, 255/190
        one = Mavlink1Gcs(rv.port, source_system=255)
        try:
            assert two.wait("GLOBAL_POSITION_INT").get_msgbuf()[0] == 0xFD
            # in MAVLink 1 framing once its grace is over (generous: a loaded machine)
            one.wait("GLOBAL_POSITION_INT", 30.0, where=lambda m: m.get_msgbuf()[0] == 0xFE)
            two.messages.clear()
            two.wait("GLOBAL_POSITION_INT")
            assert two.messages and all(m.get_msgbuf()[0] == 0xFD for m in two.messages)
            assert len(rv.vehicle.links.links) == 2
        finally:
            one.close()
            two.close()


def test_a_legacy_upload_loop_is_asked_with_mission_request() -> None:
    with running_vehicle(SEARCH_SCENARIO, speedup=2.0) as rv:
        gcs = Gcs(rv.pymavlink_url)
        try:
            points = _waypoints(rv, 3)
            gcs.conn.mav.mission_count_send(1, 1, len(points))
            first = gcs.wait(["MISSION_REQUEST", "MISSION_REQUEST_INT"])
            assert first.seq == 0
            lat, lon, alt = points[0]
            gcs.conn.mav.mission_item_send(1, 1, 0, MAV_FRAME_GLOBAL_RELATIVE_ALT,
                                           MAV_CMD_NAV_WAYPOINT, 1, 1, 0, 0, 0, math.nan,
                                           lat, lon, alt)
            # from now on, as mavwp-style loops wait for it: MISSION_REQUEST only
            for k in (1, 2):
                req = gcs.wait(["MISSION_REQUEST", "MISSION_REQUEST_INT", "MISSION_ACK"],
                               where=lambda m, k=k: m.get_type() == "MISSION_ACK"
                               or m.seq == k)
                assert req.get_type() == "MISSION_REQUEST", req
                lat, lon, alt = points[k]
                gcs.conn.mav.mission_item_send(1, 1, k, MAV_FRAME_GLOBAL_RELATIVE_ALT,
                                               MAV_CMD_NAV_WAYPOINT, 0, 1, 0, 0, 0,
                                               math.nan, lat, lon, alt)
            assert gcs.wait("MISSION_ACK").type == MAV_MISSION_ACCEPTED
            assert rv.upload_count() == 1 and len(rv.held()) == 3
            # the same ground station moves on to the INT form: a request it
            # understands comes (alternating while it does not answer), then only INT
            gcs.conn.mav.mission_count_send(1, 1, 2)
            req = gcs.wait("MISSION_REQUEST_INT", where=lambda m: m.seq == 0)
            for k in range(2):
                lat, lon, alt = points[k]
                gcs.conn.mav.mission_item_int_send(1, 1, k, MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
                                                   MAV_CMD_NAV_WAYPOINT, 0, 1, 0, 0, 0,
                                                   math.nan, round(lat * 1e7),
                                                   round(lon * 1e7), alt)
                if k == 0:
                    req = gcs.wait(["MISSION_REQUEST", "MISSION_REQUEST_INT"],
                                   where=lambda m: m.seq == 1)
                    assert req.get_type() == "MISSION_REQUEST_INT"
            assert gcs.wait("MISSION_ACK").type == MAV_MISSION_ACCEPTED
            assert rv.upload_count() == 2 and len(rv.held()) == 2
        finally:
            gcs.close()


def test_the_protocol_version_handshake_is_answered() -> None:
    with running_vehicle(SEARCH_SCENARIO, speedup=2.0) as rv:
        gcs = Gcs(rv.pymavlink_url)
        try:
            for cmd, params in ((MAV_CMD_REQUEST_PROTOCOL_VERSION, (1,)),
                                (MAV_CMD_REQUEST_MESSAGE, (PROTOCOL_VERSION_ID,))):
                assert gcs.command(cmd, *params) == MAV_RESULT_ACCEPTED
                # pymavlink's dialect lacks message 300: it arrives as its raw frame
                m = gcs.wait("UNKNOWN_300")
                assert _protocol_version_frames([bytes(m.data)]) == [(200, 100, 200)]
        finally:
            gcs.close()


def test_mavsdk_altitude_local_position_and_origin() -> None:
    """MAVSDK's Telemetry.altitude, position_velocity_ned and get_gps_global_origin (PX4
    streams ALTITUDE and LOCAL_POSITION_NED; the origin is the local frame's)."""
    from mavsdk.plugins.telemetry import Telemetry

    from tests.envs.vehicle.test_mavsdk import _until, mavsdk_gcs

    with running_vehicle(SEARCH_SCENARIO, speedup=2.0) as rv, \
            mavsdk_gcs(rv.mavsdk_url) as system:
        t = Telemetry(system)
        # each stream arrives on its own: wait for all three (under load one comes late)
        assert _until(lambda: math.isfinite(t.altitude().altitude_amsl_m)
                      and math.isfinite(t.position().absolute_altitude_m)
                      and math.isfinite(t.position_velocity_ned().position.down_m), 30.0)
        origin = t.get_gps_global_origin()
        f = rv.autopilot.frame
        assert (origin.latitude_deg, origin.longitude_deg) == pytest.approx(
            (f.lat0_deg, f.lon0_deg), abs=1e-7)
        assert origin.altitude_m == pytest.approx(f.h0_m, abs=1e-3)
        # on the ground: every form of the altitude agrees with the position's
        alt, pos, ned = t.altitude(), t.position(), t.position_velocity_ned().position
        assert alt.altitude_amsl_m == pytest.approx(pos.absolute_altitude_m, abs=1.0)
        assert alt.altitude_relative_m == pytest.approx(pos.relative_altitude_m, abs=1.0)
        ground = rv.autopilot.terrain.height_m(pos.latitude_deg, pos.longitude_deg)
        assert alt.altitude_terrain_m == pytest.approx(pos.absolute_altitude_m - ground,
                                                       abs=1.0)
        lat, lon, h = f.to_geodetic(ned.east_m, ned.north_m, -ned.down_m)
        assert float(h) == pytest.approx(pos.absolute_altitude_m, abs=1.0)
        north_m = math.radians(float(lat) - pos.latitude_deg) * 6.371e6
        east_m = math.radians(float(lon) - pos.longitude_deg) * 6.371e6 \
            * math.cos(math.radians(pos.latitude_deg))
        assert math.hypot(north_m, east_m) < 1.0


def _upload_int(gcs: Gcs, points: list[tuple[float, float, float]]) -> int:
    """A MISSION_ITEM_INT upload answering every request; the MISSION_ACK's result."""
    gcs.conn.mav.mission_count_send(1, 1, len(points))
    while True:
        m = gcs.wait(["MISSION_REQUEST_INT", "MISSION_ACK"])
        if m.get_type() == "MISSION_ACK":
            return int(m.type)
        lat, lon, alt = points[m.seq]
        gcs.conn.mav.mission_item_int_send(1, 1, m.seq, MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
                                           MAV_CMD_NAV_WAYPOINT, 0, 1, 0, 0, 0, math.nan,
                                           round(lat * 1e7), round(lon * 1e7), alt)


def test_a_ground_station_that_reconnects_mid_upload_is_not_locked_out() -> None:
    """Over TCP: an upload left half way by a ground station whose old connection is
    half-open (it started again on a new one) or gone (it hung up) locks no one out
    (they used to get MAV_MISSION_DENIED until the 5 s transfer timeout)."""
    port = free_tcp_port()
    sc = load_scenario(SEARCH_SCENARIO)
    v = VirtualVehicle(sc, [f"tcpin:{LOOPBACK}:{port}"], speedup=2.0).start()
    opened: list[Gcs] = []
    try:
        url = f"tcp:{LOOPBACK}:{port}"
        first = Gcs(url)
        opened.append(first)
        first.conn.mav.mission_count_send(1, 1, 3)
        assert first.wait("MISSION_REQUEST_INT").seq == 0
        # the same ground station (255/190) on a new connection, the old one left open
        again = Gcs(url)
        opened.append(again)
        points = _waypoints(_Rv(v), 3)
        assert _upload_int(again, points) == MAV_MISSION_ACCEPTED
        assert v.protocol.commits[0] == 1
        # it starts another upload and hangs up: another ground station is served
        again.conn.mav.mission_count_send(1, 1, 2)
        assert again.wait("MISSION_REQUEST_INT").seq == 0
        again.close()
        opened.remove(again)
        other = Gcs(url, source_system=254)
        opened.append(other)
        assert _upload_int(other, points[:2]) == MAV_MISSION_ACCEPTED
        assert v.protocol.commits[0] == 2 and len(v.protocol.held[0]) == 2
    finally:
        for g in opened:
            g.close()
        v.stop()


class _Rv:
    """What :func:`_waypoints` needs of a running vehicle."""

    def __init__(self, v: VirtualVehicle) -> None:
        self.autopilot = v.autopilot


def test_a_companion_computer_on_the_vehicles_system_is_answered() -> None:
    """MAVSDK as a companion computer (system 1, as the vehicle's own onboard computer
    or phone app would be): its parameter read and mission download are answered (the
    vehicle used to drop everything from its own system id); it is no ground station,
    so it does not keep the ground-station link alive."""
    from mavsdk import ComponentType, Configuration, Mavsdk
    from mavsdk.plugins.mission_raw import MissionRaw
    from mavsdk.plugins.param import Param

    from planner.mavlink import quiet_mavsdk_logs

    quiet_mavsdk_logs()
    with running_vehicle(SEARCH_SCENARIO, speedup=2.0) as rv:
        m = Mavsdk(Configuration.create_with_component_type(ComponentType.COMPANION_COMPUTER))
        try:
            assert m.add_any_connection(rv.mavsdk_url).name == "SUCCESS"
            system = m.first_autopilot(30.0)
            assert system is not None
            assert Param(system).get_param_float("NAV_ACC_RAD") \
                == rv.autopilot.params["NAV_ACC_RAD"]
            assert MissionRaw(system).download_mission() == []
            peers = {p[1] for p in rv.vehicle._link.peers}
            assert peers == {1}  # only the companion talked
            assert not rv.vehicle._link.seen  # no ground station yet
        finally:
            m.destroy()


def test_the_log_list_is_answered_empty() -> None:
    """LOG_REQUEST_LIST (QGroundControl's log download, MAVSDK's LogFiles) gets the empty
    list's one LOG_ENTRY (the autopilot keeps no logs): MAVSDK says NO_LOGFILES (it used to
time out)."""
    from mavsdk.plugins.log_files import LogFiles, LogFilesError, LogFilesResult

    from tests.envs.vehicle.test_mavsdk import mavsdk_gcs

    with running_vehicle(SEARCH_SCENARIO, speedup=2.0) as rv:
        gcs = Gcs(rv.pymavlink_url)
        try:
            gcs.conn.mav.log_request_list_send(1, 1, 0, 0xFFFF)
            entry = gcs.wait("LOG_ENTRY")
            assert (entry.id, entry.num_logs, entry.last_log_num, entry.size) == (0, 0, 0, 0)
        finally:
            gcs.close()
        with mavsdk_gcs(rv.mavsdk_url) as system:
            with pytest.raises(LogFilesError) as err:  # MAVSDK's word for an empty list
                LogFiles(system).get_entries()
            assert err.value.result == LogFilesResult.NO_LOGFILES


def test_a_mode_change_by_the_base_mode_alone() -> None:
    """DO_SET_MODE / SET_MODE with MAVLink's standard modes (no custom mode: what
    pymavlink's ``set_mode(MAV_MODE_...)`` and generic ground stations send) are read as
    PX4 reads them; they used to be DENIED."""
    from pymavlink.dialects.v20.common import (
        MAV_MODE_AUTO_DISARMED,
        MAV_MODE_GUIDED_DISARMED,
        MAV_MODE_MANUAL_DISARMED,
        MAV_RESULT_DENIED,
    )

    with running_vehicle(SEARCH_SCENARIO, speedup=2.0) as rv:
        gcs = Gcs(rv.pymavlink_url)
        try:
            assert _upload_int(gcs, _waypoints(rv, 2)) == MAV_MISSION_ACCEPTED
            conn = gcs.conn
            conn.target_system, conn.target_component = 1, 1
            for base, result, mode in ((MAV_MODE_AUTO_DISARMED, MAV_RESULT_ACCEPTED,
                                        Mode.MISSION),
                                       (MAV_MODE_GUIDED_DISARMED, MAV_RESULT_ACCEPTED,
                                        Mode.POSCTL),
                                       (MAV_MODE_MANUAL_DISARMED, MAV_RESULT_DENIED,
                                        Mode.POSCTL)):
                conn.set_mode(base)  # pymavlink: DO_SET_MODE, base mode only, to PX4
                ack = gcs.wait("COMMAND_ACK", where=lambda m: m.command == 176)
                assert ack.result == result
                assert rv.autopilot.mode is mode
            conn.mav.set_mode_send(1, MAV_MODE_AUTO_DISARMED, 0)  # the SET_MODE message
            assert gcs.wait("COMMAND_ACK", where=lambda m: m.command == 176).result \
                == MAV_RESULT_ACCEPTED
            gcs.wait("HEARTBEAT", where=lambda m: m.get_srcSystem() == 1
                     and m.custom_mode == Mode.MISSION.custom_mode)
        finally:
            gcs.close()


def test_partial_lists_are_refused_at_once() -> None:
    """MISSION_WRITE_PARTIAL_LIST / MISSION_REQUEST_PARTIAL_LIST (MAVProxy's ``wp move``,
    ArduPilot ground stations) get MAV_MISSION_UNSUPPORTED (they used to go unanswered);
    the held mission is unchanged."""
    from pymavlink.dialects.v20.common import MAV_MISSION_UNSUPPORTED

    with running_vehicle(SEARCH_SCENARIO, speedup=2.0) as rv:
        gcs = Gcs(rv.pymavlink_url)
        try:
            points = _waypoints(rv, 3)
            assert _upload_int(gcs, points) == MAV_MISSION_ACCEPTED
            before = rv.held()
            gcs.conn.mav.mission_write_partial_list_send(1, 1, 1, 1, 0)
            assert gcs.wait("MISSION_ACK").type == MAV_MISSION_UNSUPPORTED
            gcs.conn.mav.mission_request_partial_list_send(1, 1, 0, 2, 0)
            assert gcs.wait("MISSION_ACK").type == MAV_MISSION_UNSUPPORTED
            assert rv.held() == before and rv.upload_count() == 1
        finally:
            gcs.close()


def test_an_uploader_that_refuses_the_float_form_is_asked_in_the_int_form() -> None:
    """The request form is negotiated as PX4 does: a ground station known to speak the
    float form (it asked with MISSION_REQUEST) is asked with MISSION_REQUEST; MAVSDK
    under the same identity answers MISSION_ACK MAV_MISSION_UNSUPPORTED (it speaks INT
    only), and the vehicle asks again with MISSION_REQUEST_INT: the upload succeeds
    (it used to cancel the transfer and MAVSDK timed out)."""
    from mavsdk.plugins.mission_raw import MissionItem, MissionRaw

    from tests.envs.vehicle.test_mavsdk import mavsdk_gcs

    with running_vehicle(SEARCH_SCENARIO, speedup=2.0) as rv:
        legacy = Gcs(rv.pymavlink_url, source_system=245)  # MAVSDK's identity, 245/190
        try:
            legacy.conn.mav.mission_request_send(1, 1, 0)  # a float-form download
            legacy.wait("MISSION_ACK")  # (nothing held: INVALID_SEQUENCE)
        finally:
            legacy.close()
        with mavsdk_gcs(rv.mavsdk_url) as system:
            (lat, lon, alt), = _waypoints(rv, 1)
            item = MissionItem(0, MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, MAV_CMD_NAV_WAYPOINT, 1,
                               1, 0.0, 0.0, 0.0, math.nan, round(lat * 1e7),
                               round(lon * 1e7), alt, 0)
            MissionRaw(system).upload_mission([item])
        assert rv.upload_count() == 1
        assert (rv.held()[0].x, rv.held()[0].y) == (round(lat * 1e7), round(lon * 1e7))


def test_a_plan_with_px4s_payload_items_is_taken_and_flown_through() -> None:
    """Camera, gimbal, ROI, winch, gripper, actuator items and the DO_LAND_START marker
    (every payload item PX4's mission takes; QGroundControl's camera and ROI sections
    emit some) are stored as sent and passed over on the way; they used to make the
    whole upload fail with MAV_MISSION_UNSUPPORTED."""
    from pymavlink.dialects.v20 import common as mav

    from tests.envs.vehicle.helpers import fly, item, make_autopilot, numbered

    payload = [mav.MAV_CMD_NAV_ROI, mav.MAV_CMD_DO_SET_ROI_WPNEXT_OFFSET,
               mav.MAV_CMD_DO_MOUNT_CONFIGURE, mav.MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE,
               mav.MAV_CMD_SET_CAMERA_FOCUS, mav.MAV_CMD_DO_CONTROL_VIDEO,
               mav.MAV_CMD_DO_TRIGGER_CONTROL, mav.MAV_CMD_OBLIQUE_SURVEY,
               mav.MAV_CMD_DO_WINCH, mav.MAV_CMD_DO_GRIPPER, mav.MAV_CMD_DO_SET_ACTUATOR,
               mav.MAV_CMD_DO_LAND_START]
    ap = make_autopilot(SEARCH_SCENARIO)
    items = numbered([item(ap, mav.MAV_CMD_NAV_TAKEOFF, 0, 0, 10.0),
                      *(item(ap, c, frame=mav.MAV_FRAME_MISSION, p1=1.0) for c in payload),
                      item(ap, e=30, n=0, alt=10.0),
                      item(ap, mav.MAV_CMD_NAV_LAND, 30, 0, 0.0)])
    with running_vehicle(SEARCH_SCENARIO, speedup=2.0) as rv:
        gcs = Gcs(rv.pymavlink_url)
        try:
            gcs.conn.mav.mission_count_send(1, 1, len(items))
            while True:
                m = gcs.wait(["MISSION_REQUEST_INT", "MISSION_ACK"])
                if m.get_type() == "MISSION_ACK":
                    break
                w = items[m.seq]
                gcs.conn.mav.mission_item_int_send(
                    1, 1, w.seq, w.frame, w.command, w.current, w.autocontinue, w.param1,
                    w.param2, w.param3, w.param4, w.x, w.y, w.z)
            assert m.type == MAV_MISSION_ACCEPTED
            assert [w.command for w in rv.held()] == [w.command for w in items]
        finally:
            gcs.close()
    # flown in process: the payload items are reached at once, in order, on the way
    ap.set_mission(items)
    assert ap.set_mode(Mode.MISSION)[0] == MAV_RESULT_ACCEPTED
    assert ap.arm()[0] == MAV_RESULT_ACCEPTED
    fly(ap, 300.0, until=lambda a: not a.armed)
    assert not ap.armed
    assert [r[0] for r in ap.reached_log] == list(range(len(items)))
    t = {seq: t_s for seq, t_s, _ in ap.reached_log}
    assert all(t[k] == t[1] for k in range(1, len(payload) + 1))  # at once, after take-off


def test_int32_max_is_an_unset_latitude_and_longitude() -> None:
    """INT32_MAX in COMMAND_INT's or MISSION_ITEM_INT's x and y is "not set" (MAVLink:
    the NaN of an integer param): DO_REPOSITION with only an altitude (QGroundControl's
    change of altitude) climbs where the vehicle is, and a take-off item without a
    position is taken; both used to be refused (a latitude of 214.7 degrees)."""
    from pymavlink.dialects.v20.common import (
        MAV_CMD_DO_REPOSITION,
        MAV_CMD_NAV_TAKEOFF,
        MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
    )

    UNSET_E7 = 2**31 - 1  # INT32_MAX

    with running_vehicle(SEARCH_SCENARIO, speedup=10.0) as rv:
        gcs = Gcs(rv.pymavlink_url)
        try:
            # a mission whose take-off has no position, then one waypoint
            (lat, lon, _), = _waypoints(rv, 1)
            items = [(MAV_CMD_NAV_TAKEOFF, UNSET_E7, UNSET_E7, 6.0),
                     (MAV_CMD_NAV_WAYPOINT, round(lat * 1e7), round(lon * 1e7), 6.0)]
            gcs.conn.mav.mission_count_send(1, 1, 2)
            for _ in range(2):
                req = gcs.wait("MISSION_REQUEST_INT")
                cmd, x, y, z = items[req.seq]
                gcs.conn.mav.mission_item_int_send(1, 1, req.seq,
                                                   MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, cmd, 0,
                                                   1, 0, 0, 0, math.nan, x, y, z)
            assert gcs.wait("MISSION_ACK").type == MAV_MISSION_ACCEPTED
            assert (rv.held()[0].x, rv.held()[0].y) == (UNSET_E7, UNSET_E7)
            # arm, take off (MIS_TAKEOFF_ALT), then only a new altitude by COMMAND_INT
            assert gcs.command(MAV_CMD_COMPONENT_ARM_DISARM, 1) == MAV_RESULT_ACCEPTED
            assert gcs.command(MAV_CMD_NAV_TAKEOFF, 0, 0, 0, math.nan, math.nan, math.nan,
                               math.nan) == MAV_RESULT_ACCEPTED
            ap = rv.autopilot
            gcs.wait("EXTENDED_SYS_STATE", 30.0, where=lambda m: m.landed_state == 2)
            e0, n0 = ap.position[0], ap.position[1]
            gcs.conn.mav.command_int_send(1, 1, MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
                                          MAV_CMD_DO_REPOSITION, 0, 0, -1, 0, 0, math.nan,
                                          UNSET_E7, UNSET_E7, 12.0)
            ack = gcs.wait("COMMAND_ACK", where=lambda m: m.command == MAV_CMD_DO_REPOSITION)
            assert ack.result == MAV_RESULT_ACCEPTED
            gpi = gcs.wait("GLOBAL_POSITION_INT", 60.0,
                           where=lambda m: abs(m.relative_alt / 1000.0 - 12.0) < 0.5)
            assert gpi is not None
            assert math.hypot(ap.position[0] - e0, ap.position[1] - n0) < 1.5
        finally:
            gcs.close()


def test_a_ping_is_answered() -> None:
    """The ping microservice (MAVProxy's link latency): a PING to all (targets 0) comes
    back to its sender with its time and sequence; it used to go unanswered."""
    with running_vehicle(SEARCH_SCENARIO, speedup=2.0) as rv:
        gcs = Gcs(rv.pymavlink_url)
        try:
            gcs.conn.mav.ping_send(123_456_789, 42, 0, 0)
            pong = gcs.wait("PING", where=lambda m: m.get_srcSystem() == 1)
            assert (pong.time_usec, pong.seq, pong.target_system, pong.target_component) \
                == (123_456_789, 42, 255, 190)
        finally:
            gcs.close()


def test_two_ground_stations_on_one_udpin_port() -> None:
    """Two ground stations (systems 255 and 254) writing to the same ``udpin`` port,
    as QGroundControl and a MAVSDK script on one PX4 SITL port: each address is a link of
    its own, like a TCP client: both get the telemetry, each gets its own answers and
    not the other's (pymavlink's ``udpin`` sends every message to every address that
    wrote: the quiet one received the talker's MISSION_REQUEST_INTs and COMMAND_ACKs)."""
    with running_vehicle(SEARCH_SCENARIO, speedup=2.0) as rv:
        quiet = Gcs(rv.pymavlink_url, source_system=254)
        talker = Gcs(rv.pymavlink_url)
        try:
            assert _upload_int(talker, _waypoints(rv, 3)) == MAV_MISSION_ACCEPTED
            assert talker.command(MAV_CMD_REQUEST_MESSAGE, 148) == MAV_RESULT_ACCEPTED
            heard = []  # what reaches the quiet one while the talker talks
            deadline = time.monotonic() + 20.0
            while not {"GLOBAL_POSITION_INT", "HEARTBEAT"} <= {m.get_type() for m in heard} \
                    and time.monotonic() < deadline:
                talker.recv(0.02)  # (its HEARTBEATs)
                m = quiet.conn.recv_match(blocking=True, timeout=0.02)
                if m is not None:
                    heard.append(m)
            while (m := quiet.conn.recv_match(blocking=False)) is not None:
                heard.append(m)
            kinds = {m.get_type() for m in heard}
            assert {"GLOBAL_POSITION_INT", "HEARTBEAT"} <= kinds  # the telemetry
            assert [m for m in heard if getattr(m, "target_system", 0) == 255] == []
            # its own command is answered to it
            assert quiet.command(MAV_CMD_REQUEST_MESSAGE, 148) == MAV_RESULT_ACCEPTED
            quiet.conn.mav.mission_request_list_send(1, 1)
            assert quiet.wait("MISSION_COUNT").count == 3  # what the talker uploaded
            assert [m for m in talker.collect(0.5) if getattr(m, "target_system", 0) == 254] \
                == []
        finally:
            quiet.close()
            talker.close()


def test_a_takeoff_sent_again_is_accepted() -> None:
    """A ground station whose take-off ACK was lost sends it again (MAVSDK and QGroundControl
    retry with ``confirmation`` + 1): MAVLink asks ARM and TAKEOFF to be idempotent, so
    the retry is ACCEPTED and changes nothing (it used to be TEMPORARILY_REJECTED:
    the ground station reported a failed take-off while the vehicle climbed)."""
    from pymavlink.dialects.v20.common import MAV_CMD_NAV_TAKEOFF

    with running_vehicle(SEARCH_SCENARIO, speedup=5.0) as rv:
        gcs = Gcs(rv.pymavlink_url)
        try:
            nan = math.nan
            assert gcs.command(MAV_CMD_COMPONENT_ARM_DISARM, 1) == MAV_RESULT_ACCEPTED
            assert gcs.command(MAV_CMD_NAV_TAKEOFF, 0, 0, 0, nan, nan, nan, nan) \
                == MAV_RESULT_ACCEPTED
            for confirmation in (1, 2):  # the retries of a lost ACK
                gcs.conn.mav.command_long_send(1, 1, MAV_CMD_NAV_TAKEOFF, confirmation, 0, 0,
                                               0, nan, nan, nan, nan)
                ack = gcs.wait("COMMAND_ACK", where=lambda m: m.command == MAV_CMD_NAV_TAKEOFF)
                assert ack.result == MAV_RESULT_ACCEPTED
            ess = gcs.wait("EXTENDED_SYS_STATE", 30.0, where=lambda m: m.landed_state == 2)
            assert ess is not None  # in the air, the one take-off done
            target = rv.autopilot.home.alt_m + rv.autopilot.params["MIS_TAKEOFF_ALT"]
            gpi = gcs.wait("GLOBAL_POSITION_INT")
            assert gpi.alt / 1000.0 == pytest.approx(target, abs=1.5)  # one take-off, not two
        finally:
            gcs.close()


def test_attitude_quaternion_on_request() -> None:
    """MAVSDK's Telemetry.set_rate_attitude_quaternion turns ATTITUDE_QUATERNION on (off
    by default, as in PX4's normal mode; it used to be UNSUPPORTED), and the quaternion
    is the one of the ATTITUDE angles."""
    from mavsdk.plugins.telemetry import Telemetry

    from tests.envs.vehicle.test_mavsdk import _until, mavsdk_gcs

    with running_vehicle(SEARCH_SCENARIO, speedup=2.0) as rv, \
            mavsdk_gcs(rv.mavsdk_url) as system:
        t = Telemetry(system)
        t.set_rate_attitude_quaternion(5.0)
        assert _until(lambda: math.isfinite(t.attitude_quaternion().w), 20.0)
        q = t.attitude_quaternion()
        assert q.w ** 2 + q.x ** 2 + q.y ** 2 + q.z ** 2 == pytest.approx(1.0, abs=1e-5)
        yaw = math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y ** 2 + q.z ** 2))
        _, _, attitude_yaw = rv.vehicle.telemetry._attitude()  # ATTITUDE's yaw
        assert yaw == pytest.approx(attitude_yaw, abs=1e-3)  # landed: the nose stays
        # on MAVSDK's link (the only one)
        assert [st.interval_us(31) for st in rv.vehicle.telemetry.streams.values()] == \
            [200_000]


def test_a_fence_item_sent_as_a_mission_item_ends_the_upload_at_once() -> None:
    """A fence upload whose items come with ``mission_type`` 0 (pymavlink's
    ``mission_item_int_send`` without its last argument) ends at once with
    MAV_MISSION_ERROR for the fence (as PX4 answers an item of the wrong list; it used
    to be asked again until the 5 s timeout: OPERATION_CANCELLED); the fence held stays."""
    from pymavlink.dialects.v20.common import (
        MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION,
        MAV_FRAME_GLOBAL_INT,
        MAV_MISSION_ERROR,
        MAV_MISSION_TYPE_FENCE,
    )

    with running_vehicle(SEARCH_SCENARIO, speedup=2.0) as rv:
        gcs = Gcs(rv.pymavlink_url)
        try:
            (lat, lon, _), = _waypoints(rv, 1)
            gcs.conn.mav.mission_count_send(1, 1, 1, MAV_MISSION_TYPE_FENCE)
            req = gcs.wait("MISSION_REQUEST_INT", where=lambda m: m.mission_type == 1)
            gcs.conn.mav.mission_item_int_send(1, 1, req.seq, MAV_FRAME_GLOBAL_INT,
                                               MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION, 0, 1,
                                               500.0, 0, 0, 0, round(lat * 1e7),
                                               round(lon * 1e7), 0.0)  # mission_type 0
            ack = gcs.wait("MISSION_ACK", 10.0)
            assert (ack.type, ack.mission_type) == (MAV_MISSION_ERROR, MAV_MISSION_TYPE_FENCE)
            assert rv.held(MAV_MISSION_TYPE_FENCE) == [] and not rv.vehicle.protocol.uploading
        finally:
            gcs.close()


def test_mavsdks_listen_everywhere_url() -> None:
    """``--connection udp://:14540`` (MAVSDK's and PX4's documentation form: no host,
    every interface) listens on 0.0.0.0; it used to be refused ("expected HOST:PORT")."""
    from tests.net import free_udp_port

    port = free_udp_port()
    v = VirtualVehicle(load_scenario(SEARCH_SCENARIO), [f"udp://:{port}"], speedup=2.0).start()
    try:
        gcs = Gcs(f"udpout:{LOOPBACK}:{port}")
        try:
            assert gcs.command(MAV_CMD_REQUEST_MESSAGE, 148) == MAV_RESULT_ACCEPTED
        finally:
            gcs.close()
    finally:
        v.stop()


def _upload_float(gcs: Gcs, items: list[tuple[int, int, float, float, float, float]]) -> int:
    """A legacy upload (float MISSION_ITEMs: command, frame, param2, x, y, z) answering
    every request; the MISSION_ACK's result."""
    gcs.conn.mav.mission_count_send(1, 1, len(items))
    while True:
        m = gcs.wait(["MISSION_REQUEST", "MISSION_REQUEST_INT", "MISSION_ACK"])
        if m.get_type() == "MISSION_ACK":
            return int(m.type)
        cmd, frame, p2, x, y, z = items[m.seq]
        gcs.conn.mav.mission_item_send(1, 1, m.seq, frame, cmd, int(m.seq == 0), 1, 0, p2,
                                       0, math.nan, x, y, z)


def test_float_items_read_back_nan_and_never_stop_the_vehicle() -> None:
    """A float MISSION_ITEM's NaN latitude and longitude ("not set", stored as INT32_MAX)
    read back as NaN in the float form (it read back as 214.748 degrees, INT32_MAX / 1e7),
    and as INT32_MAX in the INT form. A float item whose x or y no MISSION_ITEM_INT can
    carry (1e30 in a DO_CHANGE_SPEED's param5/6: beyond int32 degE7) is refused with
    INVALID_PARAM5_X / 6_Y and the held mission stays (it used to be stored, and the next
    MISSION_REQUEST_INT for it stopped the vehicle: struct.error in the loop)."""
    from pymavlink.dialects.v20.common import (
        MAV_CMD_DO_CHANGE_SPEED,
        MAV_CMD_NAV_TAKEOFF,
        MAV_FRAME_MISSION,
        MAV_MISSION_INVALID_PARAM5_X,
        MAV_MISSION_INVALID_PARAM6_Y,
    )

    nan, rel = math.nan, MAV_FRAME_GLOBAL_RELATIVE_ALT
    with running_vehicle(SEARCH_SCENARIO, speedup=2.0) as rv:
        gcs = Gcs(rv.pymavlink_url)
        try:
            (lat, lon, alt), = _waypoints(rv, 1)
            held = [(MAV_CMD_NAV_TAKEOFF, rel, 0.0, nan, nan, 10.0),
                    (MAV_CMD_NAV_WAYPOINT, rel, 0.0, lat, lon, alt)]
            assert _upload_float(gcs, held) == MAV_MISSION_ACCEPTED
            for k, form in ((0, "MISSION_ITEM"), (1, "MISSION_ITEM"), (0, "MISSION_ITEM_INT")):
                if form == "MISSION_ITEM":
                    gcs.conn.mav.mission_request_send(1, 1, k)
                else:
                    gcs.conn.mav.mission_request_int_send(1, 1, k)
                got = gcs.wait(form, where=lambda m, k=k: m.seq == k)
                if form == "MISSION_ITEM_INT":
                    assert (got.x, got.y) == (2**31 - 1, 2**31 - 1)
                elif k == 0:
                    assert math.isnan(got.x) and math.isnan(got.y), (got.x, got.y)
                else:
                    assert (got.x, got.y) == (_f32(lat), _f32(lon))
            for x, y, result in ((1e30, 0.0, MAV_MISSION_INVALID_PARAM5_X),
                                 (0.0, -1e30, MAV_MISSION_INVALID_PARAM6_Y)):
                items = [(MAV_CMD_NAV_WAYPOINT, rel, 0.0, lat, lon, alt),
                         (MAV_CMD_DO_CHANGE_SPEED, MAV_FRAME_MISSION, 5.0, x, y, 0.0)]
                assert _upload_float(gcs, items) == result
            assert rv.upload_count() == 1 and [w.command for w in rv.held()] == \
                [MAV_CMD_NAV_TAKEOFF, MAV_CMD_NAV_WAYPOINT]
            for k in range(2):  # every held item is read back in the INT form
                gcs.conn.mav.mission_request_int_send(1, 1, k)
                assert gcs.wait("MISSION_ITEM_INT", where=lambda m, k=k: m.seq == k).seq == k
            assert rv.vehicle.error is None and rv.vehicle._thread.is_alive()
        finally:
            gcs.close()


def test_mission_current_says_no_mission_with_uint16_max() -> None:
    """MISSION_CURRENT's ``total`` is the number of items held, and UINT16_MAX when there
    is no mission (MAVLink: 0 means "not supported"; it used to be 0), before an upload,
    after one and after MISSION_CLEAR_ALL, in the stream and in the answer to
    MISSION_SET_CURRENT alike."""
    from pymavlink.dialects.v20.common import (
        MISSION_STATE_NO_MISSION,
        MISSION_STATE_NOT_STARTED,
    )

    with running_vehicle(SEARCH_SCENARIO, speedup=2.0) as rv:
        gcs = Gcs(rv.pymavlink_url)
        try:
            def current():
                gcs.collect(0.1)
                gcs.messages.clear()
                return gcs.wait("MISSION_CURRENT")

            m = current()
            assert (m.seq, m.total, m.mission_state) == (0, 65535, MISSION_STATE_NO_MISSION)
            assert _upload_int(gcs, _waypoints(rv, 3)) == MAV_MISSION_ACCEPTED
            m = current()
            assert (m.seq, m.total, m.mission_state) == (0, 3, MISSION_STATE_NOT_STARTED)
            gcs.conn.mav.mission_set_current_send(1, 1, 2)
            m = gcs.wait("MISSION_CURRENT", where=lambda m: m.seq == 2)
            assert m.total == 3
            gcs.conn.mav.mission_clear_all_send(1, 1)
            assert gcs.wait("MISSION_ACK").type == MAV_MISSION_ACCEPTED
            m = gcs.wait("MISSION_CURRENT", where=lambda m: m.mission_state
                         == MISSION_STATE_NO_MISSION)
            assert m.total == 65535
            gcs.conn.mav.mission_set_current_send(1, 1, 0)
            assert gcs.wait("MISSION_CURRENT").total == 65535
        finally:
            gcs.close()


def test_set_mission_current_results_follow_mavlink() -> None:
    """MAV_CMD_DO_SET_MISSION_CURRENT as the MAVLink definition and PX4 answer it: a
    sequence number out of range, also with no mission, is FAILED (it was DENIED);
    param1 -1 keeps the current item (to reset the jump counters only); a malformed one
    (param1 NaN or below -1, param2 neither 0 nor 1) is DENIED; each ACCEPTED one is
    followed by MISSION_CURRENT."""
    from pymavlink.dialects.v20.common import (
        MAV_CMD_DO_SET_MISSION_CURRENT,
        MAV_RESULT_DENIED,
        MAV_RESULT_FAILED,
    )

    cmd = MAV_CMD_DO_SET_MISSION_CURRENT
    with running_vehicle(SEARCH_SCENARIO, speedup=2.0) as rv:
        gcs = Gcs(rv.pymavlink_url)
        try:
            assert gcs.command(cmd, 0, 0) == MAV_RESULT_FAILED  # no mission
            assert gcs.command(cmd, -1, 1) == MAV_RESULT_FAILED
            assert _upload_int(gcs, _waypoints(rv, 3)) == MAV_MISSION_ACCEPTED
            assert gcs.command(cmd, 3, 0) == MAV_RESULT_FAILED  # seq 0..2 only
            assert gcs.command(cmd, 2, 0) == MAV_RESULT_ACCEPTED
            assert gcs.wait("MISSION_CURRENT").seq == 2
            assert gcs.command(cmd, -1, 1) == MAV_RESULT_ACCEPTED  # counters only
            assert gcs.wait("MISSION_CURRENT").seq == 2
            for params in ((math.nan, 0), (-2, 0), (1, 2), (1, math.nan)):
                assert gcs.command(cmd, *params) == MAV_RESULT_DENIED, params
            assert rv.autopilot.mission.seq == 2
        finally:
            gcs.close()


def test_garbage_and_odd_frames_on_the_port_stop_nothing() -> None:
    """Whatever arrives on the vehicle's port (random bytes, frames cut after their
    magic byte, MAVLink 1 frames, names that are not UTF-8, NaN and extreme values,
    lists and commands nobody has) leaves it running and answering: a ground station
    that comes afterwards is greeted, its command acknowledged, nothing changed."""
    from pymavlink.dialects.v20 import common as mavlink2

    rng = np.random.default_rng(11)
    with running_vehicle(SEARCH_SCENARIO, speedup=2.0) as rv:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        addr = (LOOPBACK, rv.port)

        class _Out:
            def write(self, buf: bytes) -> None:
                sock.sendto(buf, addr)

        try:
            for k in range(200):
                junk = rng.integers(0, 256, int(rng.integers(1, 300)), dtype=np.uint8)
                sock.sendto((b"\xfd\xfe"[k % 2:k % 2 + 1] if k % 3 else b"") + junk.tobytes(),
                            addr)
            v2 = mavlink2.MAVLink(_Out(), srcSystem=200, srcComponent=190)
            v1 = mavlink1.MAVLink(_Out(), srcSystem=201, srcComponent=190)
            nan, big = math.nan, 2**31 - 1
            v2.param_set_send(1, 1, b"\xff\xfe\x80abc", 1.0, 9)
            v2.param_request_read_send(1, 1, b"\xff\xfe\x80abc", -1)
            v2.param_request_read_send(1, 1, b"", 5000)
            v2.mission_count_send(1, 1, 65535, 0)
            v2.mission_count_send(1, 1, 3, 77)
            v2.mission_request_list_send(1, 1, 77)
            v2.mission_clear_all_send(1, 1, 77)
            v2.mission_item_int_send(1, 1, 5, 6, 16, 0, 1, 0, 0, 0, 0, big, -big - 1, nan, 0)
            v2.mission_set_current_send(1, 1, 65535)
            v2.command_long_send(1, 1, 65535, 255, math.inf, -math.inf, nan, 1e38, -1e38, 0, 0)
            v2.command_int_send(1, 1, 255, 65535, 0, 0, nan, 0, 0, 0, -big - 1, big, nan)
            v2.terrain_check_send(-big - 1, big)
            v2.terrain_request_send(900_000_000, 1_800_000_000, 65535, 2**56 - 1)
            v2.set_mode_send(1, 255, 2**32 - 1)
            v2.timesync_send(0, -2**63)
            v2.tunnel_send(0, 0, 32770, 7, b"\x01\xff\xff\xff\xff\xff\xff" + bytes(121))
            v2.file_transfer_protocol_send(0, 1, 1, bytes(251))
            v2.request_data_stream_send(1, 1, 0, 65535, 1)
            v1.mission_count_send(1, 1, 2)
            v1.mission_item_send(1, 1, 1, 6, 16, 0, 1, 0, 0, 0, 0, nan, math.inf, 1e30)
            v1.command_long_send(1, 1, 400, 0, 5, 0, 0, 0, 0, 0, 0)
            assert until(lambda: rv.vehicle.stats.received >= 20, 20.0)
            gcs = Gcs(rv.pymavlink_url)
            try:
                assert gcs.command(MAV_CMD_REQUEST_MESSAGE, 148) == MAV_RESULT_ACCEPTED
                assert gcs.wait("AUTOPILOT_VERSION").uid == rv.vehicle.telemetry.fingerprint
            finally:
                gcs.close()
        finally:
            sock.close()
        v = rv.vehicle
        assert v.error is None and v._thread.is_alive() and v._bad_kinds == set()
        assert not rv.autopilot.armed and rv.held() == [] and rv.upload_count() == 0


def test_mavlink_ftp_is_refused_at_once() -> None:
    """MAVLink FTP (FILE_TRANSFER_PROTOCOL; the vehicle has no files and does not claim
    the capability): every request gets a NAK with the error UnknownCommand (7), its
    opcode echoed and the sequence number plus one, as the FTP protocol answers what a
    server does not support, so MAVSDK's Ftp says UNSUPPORTED at once. It went
    unanswered: MAVSDK waited 32 s per call for its TIMEOUT (docs/vehicle.md said FTP
    was answered UNSUPPORTED)."""
    from tests.envs.vehicle.test_mavsdk import mavsdk_gcs

    with running_vehicle(SEARCH_SCENARIO, speedup=2.0) as rv:
        gcs = Gcs(rv.pymavlink_url)
        try:
            for seq, opcode in ((7, 3), (0xFFFF, 8)):  # ListDirectory, RemoveFile
                req = struct.pack("<HBBBBBBI", seq, 2, opcode, 1, 0, 0, 0, 0) + b"/"
                gcs.conn.mav.file_transfer_protocol_send(0, 1, 1, list(req.ljust(251, b"\0")))
                m = gcs.wait("FILE_TRANSFER_PROTOCOL", 3.0, where=lambda m: m.get_srcSystem() == 1)
                got = bytes(m.payload)
                assert struct.unpack_from("<HBBBB", got) == ((seq + 1) & 0xFFFF, 2, 129, 1,
                                                             opcode)
                assert got[12] == 7 and (m.target_system, m.target_component) == (255, 190)
        finally:
            gcs.close()
        from mavsdk.plugins.ftp import Ftp, FtpError, FtpResult

        with mavsdk_gcs(rv.mavsdk_url) as system:
            with pytest.raises(FtpError) as err:
                Ftp(system).list_directory("/")
            assert err.value.result == FtpResult.UNSUPPORTED


def test_the_mission_protocol_addressed_to_the_mission_planner_component() -> None:
    """Older ground stations (QGroundControl 2.x's waypoint manager, scripts after it)
    address the mission protocol to component 190 (MAV_COMP_ID_MISSIONPLANNER); PX4
    takes it as its own. A download and an upload so addressed are answered (they
    went unanswered: the ground station waited for its timeout); other messages to
    component 190 are still not the autopilot's."""
    with running_vehicle(SEARCH_SCENARIO, speedup=2.0) as rv:
        gcs = Gcs(rv.pymavlink_url)
        mav = gcs.conn.mav
        try:
            lat, lon = rv.autopilot.home.lat_deg, rv.autopilot.home.lon_deg
            mav.mission_count_send(1, 190, 1, 0)
            req = gcs.wait("MISSION_REQUEST_INT", 3.0)
            assert req.seq == 0
            mav.mission_item_int_send(1, 190, 0, MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
                                      MAV_CMD_NAV_WAYPOINT, 1, 1, 0, 0, 0, math.nan,
                                      int(lat * 1e7), int(lon * 1e7), 20.0, 0)
            ack = gcs.wait("MISSION_ACK", 3.0)
            assert ack.type == MAV_MISSION_ACCEPTED and len(rv.held()) == 1
            mav.mission_request_list_send(1, 190, 0)
            assert gcs.wait("MISSION_COUNT", 3.0).count == 1
            mav.command_long_send(1, 190, MAV_CMD_REQUEST_MESSAGE, 0, 148, 0, 0, 0, 0, 0, 0)
            with pytest.raises(TimeoutError):
                gcs.wait("COMMAND_ACK", 1.0)
        finally:
            gcs.close()


def test_the_phone_records_go_to_the_ground_station_that_asked() -> None:
    """The phone's records (TUNNEL, several a second: more than a 57600-baud telemetry
    radio carries) and the pacing go to the links of the ground stations that asked for
    them (a TUNNEL acknowledgement, as ``osa search --connection`` sends), not to a
    QGroundControl listening on another address of the port: it used to get them all."""
    from envs.phone import PAYLOAD_PACE, pace_payload

    with running_vehicle(SEARCH_SCENARIO, speedup=20.0) as rv:
        qgc = Gcs(rv.pymavlink_url, source_system=254)
        loop = Gcs(rv.pymavlink_url)
        try:
            p = pace_payload(0)
            loop.conn.mav.tunnel_send(1, 1, PAYLOAD_PACE, len(p), p.ljust(128, b"\0"))
            got = []
            deadline = time.monotonic() + 30.0
            while sum(m.get_type() == "TUNNEL" for m in got) < 20 \
                    and time.monotonic() < deadline:
                m = loop.recv(0.05)
                if m is not None:
                    got.append(m)
            assert sum(m.get_type() == "TUNNEL" for m in got) >= 20  # the loop gets them
            kinds = set()  # what reached the other one meanwhile: telemetry only
            while (m := qgc.conn.recv_match(blocking=False)) is not None:
                kinds.add(m.get_type())
            assert "GLOBAL_POSITION_INT" in kinds and "TUNNEL" not in kinds, kinds
        finally:
            qgc.close()
            loop.close()
