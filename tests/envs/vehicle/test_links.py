"""Several ground stations at once and a COMMAND_ACK for every command.

Over ``tcpin`` the vehicle accepts any number of pymavlink TCP clients: an idle one
(connected first, never reading or writing) locks no one out, every client gets the
telemetry (at its own link's rates), each one's commands are answered to it alone, a
client whose buffers are full only loses its own (whole) messages, and one that hangs
up is forgotten. Every COMMAND_LONG
and COMMAND_INT is acknowledged, malformed ones too (a table of NaN and out-of-range
parameters with the MAV_RESULT each gets), and none of them changes the vehicle."""

from __future__ import annotations

import math
import socket
import time

import pytest
from pymavlink.dialects.v20.common import (
    MAV_CMD_COMPONENT_ARM_DISARM,
    MAV_CMD_DO_CHANGE_SPEED,
    MAV_CMD_DO_PAUSE_CONTINUE,
    MAV_CMD_DO_REPOSITION,
    MAV_CMD_DO_SET_HOME,
    MAV_CMD_DO_SET_MISSION_CURRENT,
    MAV_CMD_DO_SET_MODE,
    MAV_CMD_GET_MESSAGE_INTERVAL,
    MAV_CMD_MISSION_START,
    MAV_CMD_NAV_TAKEOFF,
    MAV_CMD_REQUEST_MESSAGE,
    MAV_CMD_SET_MESSAGE_INTERVAL,
    MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
    MAV_FRAME_LOCAL_NED,
    MAV_RESULT_ACCEPTED,
    MAV_RESULT_DENIED,
    MAV_RESULT_TEMPORARILY_REJECTED,
    MAV_RESULT_UNSUPPORTED,
    MAVLINK_MSG_ID_AUTOPILOT_VERSION,
    MAVLINK_MSG_ID_GLOBAL_POSITION_INT,
)

from envs.vehicle import VirtualVehicle, links
from envs.vehicle.px4 import Mode
from envs.vehicle.telemetry import Streams
from planner.mavlink import mavutil
from sim import load_scenario
from tests.envs.vehicle.helpers import SEARCH_SCENARIO, Gcs, free_tcp_port, until
from tests.vehicles import running_vehicle

NAN, INF = math.nan, math.inf


def _drain(conn) -> list:
    """Every message waiting on a pymavlink connection (non-blocking)."""
    out = []
    for _ in range(100_000):
        m = conn.recv_match(blocking=False)
        if m is None:
            break
        if m.get_type() != "BAD_DATA":
            out.append(m)
    return out


def test_tcp_ground_stations_one_idle(monkeypatch) -> None:
    # small buffers: a client that never reads fills them within a second
    monkeypatch.setattr(links, "TCP_BUFFER_BYTES", 8192)
    monkeypatch.setattr(links, "TCP_SEND_BUFFER_BYTES", 4096)
    port = free_tcp_port()
    url = f"tcp:127.0.0.1:{port}"
    v = VirtualVehicle(load_scenario(SEARCH_SCENARIO), [f"tcpin:127.0.0.1:{port}"],
                       speedup=20.0)
    with v:
        idle = mavutil.mavlink_connection(url, source_system=254, source_component=190)
        # (pymavlink's tcpin would now serve the idle client only)
        a, b = Gcs(url), Gcs(url)
        # and one that never reads with a small receive buffer
        deaf = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        deaf.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        deaf.connect(("127.0.0.1", port))
        try:
            assert until(lambda: len(v.links.links) == 4, 15.0)
            # each one's commands are answered to it, with what it asked for
            assert a.command(MAV_CMD_REQUEST_MESSAGE, MAVLINK_MSG_ID_AUTOPILOT_VERSION) == \
                MAV_RESULT_ACCEPTED
            assert a.wait("AUTOPILOT_VERSION").flight_custom_version == list(b"osa-veh\0")
            assert b.command(MAV_CMD_SET_MESSAGE_INTERVAL, MAVLINK_MSG_ID_GLOBAL_POSITION_INT,
                             5e5) == MAV_RESULT_ACCEPTED
            assert b.command(MAV_CMD_DO_SET_MODE, 1, 3, 0) == MAV_RESULT_ACCEPTED  # POSCTL
            assert until(lambda: v.autopilot.mode is Mode.POSCTL, 10.0)
            # both get the telemetry, and the mode b set
            for gcs in (a, b):
                gcs.wait("HEARTBEAT", where=lambda m: m.get_srcSystem() == 1
                         and m.custom_mode == Mode.POSCTL.custom_mode)
                gcs.wait("GLOBAL_POSITION_INT")
            a.collect(0.5)
            b.collect(0.5)
            acks_a = {m.command for m in a.messages if m.get_type() == "COMMAND_ACK"}
            acks_b = {m.command for m in b.messages if m.get_type() == "COMMAND_ACK"}
            assert acks_a == {MAV_CMD_REQUEST_MESSAGE}
            assert acks_b == {MAV_CMD_SET_MESSAGE_INTERVAL, MAV_CMD_DO_SET_MODE}
            assert not [m for m in b.messages if m.get_type() == "AUTOPILOT_VERSION"]
            # the deaf client lost its own messages, nobody else's
            deaf_link = next(k for k in list(v.links.links.values())
                             if isinstance(k, links.TcpClient)
                             and k.address[1] == deaf.getsockname()[1])
            assert until(lambda: deaf_link.dropped > 0, 30.0)
            assert a.command(MAV_CMD_DO_SET_MODE, 1, 4, 3) == MAV_RESULT_ACCEPTED  # LOITER
            b.wait("HEARTBEAT", where=lambda m: m.get_srcSystem() == 1
                   and m.custom_mode == Mode.LOITER.custom_mode)
            # the idle one read nothing meanwhile: it holds telemetry, no one's answers
            got = _drain(idle)
            kinds = {m.get_type() for m in got}
            assert {"HEARTBEAT", "GLOBAL_POSITION_INT"} <= kinds
            assert "COMMAND_ACK" not in kinds and "AUTOPILOT_VERSION" not in kinds
            # a client that hangs up is forgotten
            a.close()
            assert until(lambda: len(v.links.links) == 3, 15.0)
            assert b.command(MAV_CMD_REQUEST_MESSAGE, MAVLINK_MSG_ID_AUTOPILOT_VERSION) == \
                MAV_RESULT_ACCEPTED
        finally:
            for c in (a, b):
                c.close()
            idle.close()
            deaf.close()


# (command, params 1..7, MAV_RESULT) on a landed, disarmed vehicle without a mission
MALFORMED_LONG = [
    (MAV_CMD_COMPONENT_ARM_DISARM, (NAN,), MAV_RESULT_DENIED),
    (MAV_CMD_COMPONENT_ARM_DISARM, (2.0,), MAV_RESULT_DENIED),
    (MAV_CMD_COMPONENT_ARM_DISARM, (0.0, NAN), MAV_RESULT_ACCEPTED),  # disarmed already
    (MAV_CMD_NAV_TAKEOFF, (0, 0, 0, 0, 0, 0, INF), MAV_RESULT_DENIED),
    (MAV_CMD_NAV_TAKEOFF, (0, 0, 0, 0, 0, 0, 1e9), MAV_RESULT_DENIED),
    (MAV_CMD_NAV_TAKEOFF, (0, 0, 0, 0, 0, 0, NAN), MAV_RESULT_TEMPORARILY_REJECTED),
    (MAV_CMD_DO_SET_MODE, (NAN, 4, 3), MAV_RESULT_DENIED),
    (MAV_CMD_DO_SET_MODE, (1, NAN, 3), MAV_RESULT_DENIED),
    (MAV_CMD_DO_SET_MODE, (1, 4, 1e12), MAV_RESULT_DENIED),
    (MAV_CMD_DO_SET_MODE, (1, -3, 0), MAV_RESULT_DENIED),
    (MAV_CMD_MISSION_START, (NAN,), MAV_RESULT_DENIED),
    (MAV_CMD_MISSION_START, (1e12,), MAV_RESULT_DENIED),
    (MAV_CMD_DO_PAUSE_CONTINUE, (NAN,), MAV_RESULT_DENIED),
    (MAV_CMD_DO_PAUSE_CONTINUE, (7,), MAV_RESULT_DENIED),
    (MAV_CMD_DO_CHANGE_SPEED, (1, NAN), MAV_RESULT_DENIED),
    (MAV_CMD_DO_CHANGE_SPEED, (1, -7), MAV_RESULT_DENIED),
    (MAV_CMD_DO_REPOSITION, (-1, 0, 0, NAN, 95.0, 10.0, 50), MAV_RESULT_DENIED),
    (MAV_CMD_DO_REPOSITION, (-1, 0, 0, NAN, 36.7, 400.0, 50), MAV_RESULT_DENIED),
    (MAV_CMD_DO_REPOSITION, (-1, 0, 0, NAN, NAN, NAN, INF), MAV_RESULT_DENIED),
    (MAV_CMD_DO_REPOSITION, (-1, 0, 0, NAN, NAN, NAN, NAN), MAV_RESULT_TEMPORARILY_REJECTED),
    (MAV_CMD_DO_SET_HOME, (0, 0, 0, 0, 36.7, -4.4, NAN), MAV_RESULT_DENIED),
    (MAV_CMD_DO_SET_HOME, (NAN, 0, 0, 0, 36.7, -4.4, 100), MAV_RESULT_DENIED),
    (MAV_CMD_DO_SET_HOME, (0, 0, 0, 0, -91.0, -4.4, 100), MAV_RESULT_DENIED),
    (MAV_CMD_DO_SET_MISSION_CURRENT, (NAN,), MAV_RESULT_DENIED),  # param1 NaN: malformed
    (MAV_CMD_SET_MESSAGE_INTERVAL, (NAN, 1e6), MAV_RESULT_DENIED),
    (MAV_CMD_SET_MESSAGE_INTERVAL, (33, NAN), MAV_RESULT_DENIED),
    (MAV_CMD_SET_MESSAGE_INTERVAL, (33, -5), MAV_RESULT_DENIED),
    (MAV_CMD_SET_MESSAGE_INTERVAL, (1e30, 1e6), MAV_RESULT_DENIED),
    (MAV_CMD_SET_MESSAGE_INTERVAL, (9999, 1e6), MAV_RESULT_UNSUPPORTED),
    (MAV_CMD_GET_MESSAGE_INTERVAL, (NAN,), MAV_RESULT_DENIED),
    (MAV_CMD_REQUEST_MESSAGE, (NAN,), MAV_RESULT_DENIED),
    (MAV_CMD_REQUEST_MESSAGE, (33.5,), MAV_RESULT_DENIED),
    (MAV_CMD_REQUEST_MESSAGE, (-1,), MAV_RESULT_DENIED),
    (MAV_CMD_REQUEST_MESSAGE, (9999,), MAV_RESULT_UNSUPPORTED),
    (31000, (NAN,) * 7, MAV_RESULT_UNSUPPORTED),
]
# (command, frame, params 1..4, x, y, z, MAV_RESULT)
MALFORMED_INT = [
    (MAV_CMD_DO_REPOSITION, MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, (-1, 0, 0, NAN),
     2**31 - 1, 0, 30.0, MAV_RESULT_DENIED),
    (MAV_CMD_DO_REPOSITION, MAV_FRAME_LOCAL_NED, (-1, 0, 0, NAN), 367_000_000, -44_000_000,
     30.0, MAV_RESULT_DENIED),
    (MAV_CMD_DO_SET_HOME, MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, (0, 0, 0, 0), 367_000_000,
     -44_000_000, INF, MAV_RESULT_DENIED),
    (MAV_CMD_NAV_TAKEOFF, MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, (0, 0, 0, NAN), 0, 0, NAN,
     MAV_RESULT_TEMPORARILY_REJECTED),
    (MAV_CMD_SET_MESSAGE_INTERVAL, 0, (NAN, 1e6, 0, 0), 0, 0, 0.0, MAV_RESULT_DENIED),
    (31000, 0, (0, 0, 0, 0), 0, 0, 0.0, MAV_RESULT_UNSUPPORTED),
]


def test_every_command_is_acknowledged_malformed_ones_too() -> None:
    with running_vehicle(SEARCH_SCENARIO, speedup=2.0) as rv:
        ap = rv.autopilot
        home = (ap.home.lat_deg, ap.home.lon_deg, ap.home.alt_m)
        intervals = Streams().interval_s  # the defaults
        gcs = Gcs(rv.pymavlink_url)
        try:
            got = []
            for cmd, params, _ in MALFORMED_LONG:
                got.append(gcs.command(cmd, *params))
            for cmd, frame, p, x, y, z, _ in MALFORMED_INT:
                gcs.conn.mav.command_int_send(1, 1, frame, cmd, 0, 0, *p, x, y, z)
                got.append(int(gcs.wait("COMMAND_ACK", 3.0,
                                        where=lambda m, c=cmd: m.command == c).result))
            gcs.collect(0.3)
            acks = [m for m in gcs.messages if m.get_type() == "COMMAND_ACK"]
        finally:
            gcs.close()
        expected = [r for *_, r in MALFORMED_LONG] + [r for *_, r in MALFORMED_INT]
        assert got == expected
        assert len(acks) == len(expected)  # one each, no more
        # nothing changed
        assert (ap.home.lat_deg, ap.home.lon_deg, ap.home.alt_m) == home
        assert not ap.armed and ap.mode is Mode.LOITER and ap.landed
        streams = list(rv.vehicle.telemetry.streams.values())
        assert streams and all(st.interval_s == intervals for st in streams)
        assert rv.vehicle._bad_kinds == set()  # no message it could not handle


def test_message_rates_are_per_link() -> None:
    """SET_MESSAGE_INTERVAL on one link (ATTITUDE at 1 Hz, ATTITUDE_QUATERNION at 10 Hz)
    changes nothing on another (two addresses on the vehicle's udpin port), as PX4 keeps
    rates per MAVLink instance and ArduPilot per serial port; GET_MESSAGE_INTERVAL tells
    each link its own. Messages are counted over 10 s of the vehicle's simulated clock
    (their time_boot_ms). The rates used to be the vehicle's: the other link got 1 Hz
    ATTITUDE and the quaternions too."""
    from pymavlink.dialects.v20.common import (
        MAVLINK_MSG_ID_ATTITUDE,
        MAVLINK_MSG_ID_ATTITUDE_QUATERNION,
    )

    with running_vehicle(SEARCH_SCENARIO, speedup=5.0) as rv:
        a, b = Gcs(rv.pymavlink_url), Gcs(rv.pymavlink_url)
        try:
            assert until(lambda: len(rv.vehicle.links.links) == 2, 15.0)
            for msg_id, interval_us in ((MAVLINK_MSG_ID_ATTITUDE, 1e6),
                                        (MAVLINK_MSG_ID_ATTITUDE_QUATERNION, 1e5)):
                assert a.command(MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, interval_us) == \
                    MAV_RESULT_ACCEPTED
            told = {}
            for name, gcs in (("a", a), ("b", b)):
                assert gcs.command(MAV_CMD_GET_MESSAGE_INTERVAL, MAVLINK_MSG_ID_ATTITUDE) == \
                    MAV_RESULT_ACCEPTED
                told[name] = gcs.wait("MESSAGE_INTERVAL", where=lambda m: m.message_id
                                      == MAVLINK_MSG_ID_ATTITUDE).interval_us
            assert told == {"a": 1_000_000, "b": 100_000}
            t0_ms = (rv.vehicle.t_s + 1.0) * 1000.0  # from a moment after the change
            t1_ms = t0_ms + 10_000.0
            counts = {(g, k): 0 for g in "ab" for k in ("ATTITUDE", "ATTITUDE_QUATERNION")}
            done = {"a": False, "b": False}
            deadline = time.monotonic() + 120.0
            while not all(done.values()) and time.monotonic() < deadline:
                for name, gcs in (("a", a), ("b", b)):
                    m = gcs.recv(0.05)
                    if m is None or not hasattr(m, "time_boot_ms"):
                        continue
                    if m.time_boot_ms >= t1_ms:
                        done[name] = True
                    elif m.time_boot_ms >= t0_ms and (name, m.get_type()) in counts:
                        counts[name, m.get_type()] += 1
            assert all(done.values())
        finally:
            a.close()
            b.close()
    # 10 Hz streams are thinned to the simulation steps (0.2 s of simulated time or less)
    assert 9 <= counts["a", "ATTITUDE"] <= 11
    assert 40 <= counts["a", "ATTITUDE_QUATERNION"] <= 101
    assert 40 <= counts["b", "ATTITUDE"] <= 101
    assert counts["b", "ATTITUDE_QUATERNION"] == 0


def test_tcpin_that_cannot_listen_is_one_line() -> None:
    busy = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    busy.bind(("127.0.0.1", 0))
    busy.listen(1)
    try:
        for url in (f"tcpin:127.0.0.1:{busy.getsockname()[1]}", "tcpin:256.1.1.1:5000"):
            with pytest.raises(links.ConnectionURLError, match=r"^cannot listen on tcpin:") \
                    as info:
                links.Links([url], 1, 1)
            assert "\n" not in str(info.value)
    finally:
        busy.close()


def test_udpin_addresses_are_forgotten_when_silent_or_too_many(monkeypatch) -> None:
    """A ``udpin`` port's per-address links are bounded (wall times given, no waiting on
    the clock): an address silent for UDP_PEER_TIMEOUT_S is forgotten (its id reported
    by ``take_gone``, so its upload is dropped), never the last one that wrote; beyond
    MAX_UDP_PEERS addresses the one silent longest makes room; a forgotten address that
    writes again is a new link."""
    from tests.net import LOOPBACK, free_udp_port

    port = free_udp_port()
    lk = links.Links([f"udpin:{LOOPBACK}:{port}"], 1, 1)
    socks = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(3)]
    try:
        def hb(k: int) -> None:
            m = mavutil.mavlink.MAVLink_heartbeat_message(6, 8, 0, 0, 0, 3)
            socks[k].sendto(m.pack(mavutil.mavlink.MAVLink(None, 250 + k, 190)),
                            (LOOPBACK, port))

        def heard(now: float, n: int) -> dict[int, int]:
            """link id -> system id of the next ``n`` messages (bounded wait)."""
            got: dict[int, int] = {}

            def enough() -> bool:
                got.update({k: m.get_srcSystem() for k, m in lk.poll(now)})
                return len(got) >= n

            until(enough, 5.0)
            return got

        t_out = links.UDP_PEER_TIMEOUT_S
        hb(0)
        hb(1)
        first = heard(0.0, 2)
        a, b = sorted(first, key=first.get)  # systems 250 and 251
        hb(1)
        assert heard(50.0, 1) == {b: 251}
        assert list(lk.poll(t_out + 1.0)) == [] and lk.take_gone() == [a]  # 250: silent
        assert sorted(lk.links) == [b]
        assert list(lk.poll(t_out + 150.0)) == [] and lk.take_gone() == []  # 251: last
        hb(0)  # 250 again: a new link
        (a2, sys_a2), = heard(t_out + 160.0, 1).items()
        assert sys_a2 == 250 and a2 not in (a, b)
        monkeypatch.setattr(links, "MAX_UDP_PEERS", 2)
        hb(2)  # a third address: 251 (silent since 50 s) makes room
        assert list(heard(t_out + 170.0, 1).values()) == [252]
        assert lk.take_gone() == [b] and len(lk.links) == 2
    finally:
        for s in socks:
            s.close()
        lk.close()


def test_a_client_gone_in_the_same_poll_as_anothers_count_locks_no_one_out() -> None:
    """A TCP client that hung up mid-upload and another ground station's MISSION_COUNT
    read in the same poll of the links (the loop stepped by hand, no waiting on the
    clock): the hang-up is handled before the count, so the count starts its upload
    (it was MAV_MISSION_DENIED: the gone link's upload was forgotten only after the
    whole poll; test_ground_stations' reconnect test failed so now and then)."""
    mav = mavutil.mavlink
    port = free_tcp_port()
    v = VirtualVehicle(load_scenario(SEARCH_SCENARIO), [f"tcpin:127.0.0.1:{port}"])
    gone = socket.create_connection(("127.0.0.1", port))
    other = socket.create_connection(("127.0.0.1", port))
    try:
        gone.sendall(mav.MAVLink_mission_count_message(1, 1, 3, 0).pack(
            mav.MAVLink(None, 255, 190)))
        assert until(lambda: v._receive(0.0) or v.protocol.uploading, 5.0)
        # in one poll: the first client hangs up, the other one writes its count
        gone.close()
        other.sendall(mav.MAVLink_mission_count_message(1, 1, 2, 0).pack(
            mav.MAVLink(None, 254, 190)))
        v._receive(0.1)
        other.settimeout(5.0)
        parser = mav.MAVLink(None)
        parser.robust_parsing = True
        answer = None
        while answer is None:
            for m in parser.parse_buffer(other.recv(65536)) or ():
                if m.get_type() in ("MISSION_ACK", "MISSION_REQUEST_INT"):
                    answer = m
        assert answer.get_type() == "MISSION_REQUEST_INT", answer.to_dict()
        assert answer.seq == 0
    finally:
        other.close()
        v.close()
