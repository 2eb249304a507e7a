"""Test-only loopback peers for the upload tests (the vehicle itself is envs.vehicle).

- :class:`MavsdkVehiclePeer`: MAVSDK as an autopilot (libcmavsdk,
  ``ComponentType.AUTOPILOT``) listening on ``udpin://127.0.0.1:PORT`` with a
  ``MissionRawServer``: an independent implementation of the vehicle side, kept for
  the checks that are about MAVSDK's server (its heartbeat, its count-0 trap).
- :class:`ScriptedMavlinkVehicle`: a tiny pymavlink vehicle for the error paths no
  well-behaved vehicle produces on demand: a chosen MISSION_ACK NACK (on
  MISSION_COUNT or on an item), silence after N items, legacy MISSION_REQUEST, a
  corrupted read-back.
- :class:`ArduPilotLikeVehicle`: the scripted vehicle with ArduPilot's heartbeat
  (autopilot 3, quadrotor) and ArduPilot's mission storage: seq 0 is always the
  vehicle's own home (whatever was uploaded there), the mission from seq 1, items as
  :func:`planner.mavlink.ardupilot_stored` gives them back.

All pick a free port at start and stop within a bounded time.

Trap: a MISSION_COUNT of 0 leaves MAVSDK 4.1's MissionRawServer corrupted (the next
upload aborts the process in ``process_mission_item_int``); clear with
MISSION_CLEAR_ALL instead, as :mod:`planner.mavlink` does.
"""

from __future__ import annotations

import contextlib
import ctypes
import socket
import threading
import time
from dataclasses import dataclass
from typing import Any

from planner.mavlink import (
    MAV_AUTOPILOT_ARDUPILOTMEGA,
    MAV_AUTOPILOT_GENERIC,
    MAV_MISSION_ACCEPTED,
    mavutil,
    quiet_mavsdk_logs,
)
from planner.mavlink_wire import WireItem, ardupilot_stored
from planner.mission import (
    MAV_CMD_NAV_WAYPOINT,
    MAV_FRAME_GLOBAL,
    MAV_MISSION_TYPE_MISSION,
    deg_to_e7,
)
from tests.net import LOOPBACK, free_udp_port

__all__ = [
    "ArduPilotLikeVehicle",
    "MavsdkVehiclePeer",
    "ScriptedMavlinkVehicle",
    "VehicleScript",
    "free_udp_port",
]

MAV_TYPE_QUADROTOR = 2
MAV_MODE_FLAG_CUSTOM_MODE_ENABLED = 1
MAV_STATE_STANDBY = 3


class _Holdings:
    """What a vehicle holds per mission type, with a condition to wait on uploads."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._held: dict[int, list[WireItem]] = {}
        self._uploads: dict[int, int] = {}

    def store(self, mission_type: int, items: list[WireItem]) -> None:
        with self._cond:
            self._held[mission_type] = list(items)
            self._uploads[mission_type] = self._uploads.get(mission_type, 0) + 1
            self._cond.notify_all()

    def clear(self, mission_type: int) -> None:
        with self._cond:
            self._held[mission_type] = []
            self._cond.notify_all()

    def held(self, mission_type: int) -> list[WireItem]:
        with self._cond:
            return list(self._held.get(mission_type, []))

    def upload_count(self, mission_type: int) -> int:
        with self._cond:
            return self._uploads.get(mission_type, 0)

    def wait_for_upload(self, mission_type: int, after: int, timeout_s: float) -> list[WireItem]:
        with self._cond:
            ok = self._cond.wait_for(lambda: self._uploads.get(mission_type, 0) > after,
                                     timeout=timeout_s)
            if not ok:
                raise TimeoutError(f"no upload of mission type {mission_type} "
                                   f"within {timeout_s:g} s")
            return list(self._held.get(mission_type, []))


class MavsdkVehiclePeer:
    """MAVSDK's autopilot-side MissionRawServer on loopback.

    Ground stations reach it at :attr:`pymavlink_url` or :attr:`mavsdk_url`.
    ``with MavsdkVehiclePeer() as peer: ...`` starts and stops it.
    """

    def __init__(self, *, host: str = LOOPBACK, port: int | None = None,
                 mav_type: int = MAV_TYPE_QUADROTOR) -> None:
        self.host = host
        self.port = port
        self.mav_type = mav_type
        self.mavsdk: Any = None
        self.server_component: Any = None
        self.mission_server: Any = None
        self._holdings = _Holdings()

    @property
    def pymavlink_url(self) -> str:
        return f"udpout:{self.host}:{self.port}"

    @property
    def mavsdk_url(self) -> str:
        return f"udpout://{self.host}:{self.port}"

    def start(self, attempts: int = 5) -> MavsdkVehiclePeer:
        """Listen on a free port (or ``port``); retries a port taken meanwhile."""
        from mavsdk import ComponentType, Configuration, Mavsdk
        from mavsdk.cmavsdk_loader import _cmavsdk_lib
        from mavsdk.connection_result import ConnectionResult
        from mavsdk.plugins.mission_raw_server import MissionRawServer

        if self.mavsdk is not None:
            return self
        quiet_mavsdk_logs()
        fixed = self.port is not None
        last = None
        for _ in range(1 if fixed else attempts):
            port = self.port if fixed else free_udp_port(self.host)
            cfg = Configuration.create_with_component_type(ComponentType.AUTOPILOT)
            # heartbeat MAV_TYPE: MAVSDK's Python package does not wrap it, so call the C API
            _cmavsdk_lib.mavsdk_configuration_set_mav_type.argtypes = [ctypes.c_void_p,
                                                                       ctypes.c_uint8]
            _cmavsdk_lib.mavsdk_configuration_set_mav_type.restype = None
            _cmavsdk_lib.mavsdk_configuration_set_mav_type(cfg._handle, self.mav_type)
            mavsdk = Mavsdk(cfg)
            last = mavsdk.add_any_connection(f"udpin://{self.host}:{port}")
            if last == ConnectionResult.SUCCESS:
                self.port = port
                self.mavsdk = mavsdk
                break
            mavsdk.destroy()
        else:
            raise OSError(f"MAVSDK peer cannot listen on {self.host}: {last}")
        self.server_component = self.mavsdk.server_component()
        self.mission_server = MissionRawServer(self.server_component)
        self.mission_server.subscribe_incoming_mission(self._on_incoming)
        self.mission_server.subscribe_clear_all(self._on_clear_all)
        return self

    def _on_incoming(self, result: Any, plan: Any, _user_data: Any) -> None:
        if result.name != "SUCCESS":
            return
        items = [WireItem.from_msg(m) for m in plan.mission_items]
        mission_type = items[0].mission_type if items else MAV_MISSION_TYPE_MISSION
        self._holdings.store(mission_type, items)

    def _on_clear_all(self, mission_type: Any, _user_data: Any) -> None:
        self._holdings.clear(int(mission_type))

    def held(self, mission_type: int = MAV_MISSION_TYPE_MISSION) -> list[WireItem]:
        """The items of the last accepted upload of ``mission_type``."""
        return self._holdings.held(mission_type)

    def upload_count(self, mission_type: int = MAV_MISSION_TYPE_MISSION) -> int:
        return self._holdings.upload_count(mission_type)

    def wait_for_upload(self, mission_type: int = MAV_MISSION_TYPE_MISSION, *, after: int = 0,
                        timeout_s: float = 2.0) -> list[WireItem]:
        """Wait until more than ``after`` uploads of ``mission_type`` were accepted.

        An empty upload (count 0) is not reported by MAVSDK's server."""
        return self._holdings.wait_for_upload(mission_type, after, timeout_s)

    def stop(self) -> None:
        if self.mavsdk is not None:
            self.mavsdk.destroy()
            self.mavsdk = self.server_component = self.mission_server = None

    def __enter__(self) -> MavsdkVehiclePeer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


@dataclass(frozen=True, kw_only=True)
class VehicleScript:
    """How a :class:`ScriptedMavlinkVehicle` misbehaves (defaults: it behaves)."""

    nack_on_count: int | None = None  # MAV_MISSION_RESULT answered to MISSION_COUNT
    nack_at_seq: int | None = None  # answer this item with nack_result instead
    nack_result: int = 1  # MAV_MISSION_RESULT, 1 = MAV_MISSION_ERROR
    silent_after_items: int | None = None  # stop answering transfers after N items
    legacy_requests: bool = False  # request items with MISSION_REQUEST, not _INT
    download_x_offset_e7: int = 0  # report item download_x_offset_seq's x off by this much
    download_x_offset_seq: int = 0
    heartbeat_period_s: float = 0.1


class ScriptedMavlinkVehicle:
    """A minimal pymavlink vehicle (sys 1, comp 1) on ``udpin:127.0.0.1:PORT``.

    Its HEARTBEAT says quadrotor, MAV_AUTOPILOT_GENERIC (0): PX4-style numbering."""

    mav_type = MAV_TYPE_QUADROTOR
    autopilot = MAV_AUTOPILOT_GENERIC
    base_mode = 0
    custom_mode = 0
    system_status = 0

    def __init__(self, script: VehicleScript | None = None, *, host: str = LOOPBACK) -> None:
        self.script = script or VehicleScript()
        self.host = host
        self.port = 0
        self._holdings = _Holdings()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._conn: Any = None
        self.items_received = 0
        self.silent = False
        self._rx: dict[str, Any] | None = None  # the upload in progress
        self._gcs = (255, 190)  # the ground station we answer

    @property
    def pymavlink_url(self) -> str:
        return f"udpout:{self.host}:{self.port}"

    @property
    def mavsdk_url(self) -> str:
        return f"udpout://{self.host}:{self.port}"

    def start(self) -> ScriptedMavlinkVehicle:
        # port 0: the OS picks the port at the bind itself (no window in which another
        # socket takes it); pymavlink binds with SO_REUSEADDR, which would let a ground
        # station's own socket, bound later to an ephemeral port, share this one and
        # receive its datagrams (MAVSDK then heard no vehicle): cleared after the bind
        self._conn = mavutil.mavlink_connection(f"udpin:{self.host}:0",
                                                source_system=1, source_component=1)
        sock = self._conn.port
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 0)
        self.port = int(sock.getsockname()[1])
        self._thread = threading.Thread(target=self._run, name="scripted-vehicle", daemon=True)
        self._thread.start()
        return self

    def stop(self, timeout_s: float = 2.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout_s)
            self._thread = None
        if self._conn is not None:
            with contextlib.suppress(OSError):
                self._conn.close()
            self._conn = None

    def __enter__(self) -> ScriptedMavlinkVehicle:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def held(self, mission_type: int = MAV_MISSION_TYPE_MISSION) -> list[WireItem]:
        return self._holdings.held(mission_type)

    def upload_count(self, mission_type: int = MAV_MISSION_TYPE_MISSION) -> int:
        return self._holdings.upload_count(mission_type)

    # -- vehicle side of the mission protocol

    def _run(self) -> None:
        conn = self._conn
        next_hb = 0.0
        while not self._stop.is_set():
            now = time.monotonic()
            if now >= next_hb:
                next_hb = now + self.script.heartbeat_period_s
                conn.mav.heartbeat_send(self.mav_type, self.autopilot, self.base_mode,
                                        self.custom_mode, self.system_status)
            try:
                msg = conn.recv_match(blocking=True, timeout=0.02)
            except OSError:
                return
            if msg is None or self.silent:
                continue
            if getattr(msg, "target_system", 1) not in (0, 1):
                continue
            handler = getattr(self, f"_on_{msg.get_type().lower()}", None)
            if handler is not None:
                self._gcs = (msg.get_srcSystem(), msg.get_srcComponent())  # reply to sender
                handler(msg)

    def _ack(self, result: int, mission_type: int) -> None:
        self._conn.mav.mission_ack_send(*self._gcs, result, mission_type)

    def _request(self, seq: int, mission_type: int) -> None:
        if self.script.legacy_requests:
            self._conn.mav.mission_request_send(*self._gcs, seq, mission_type)
        else:
            self._conn.mav.mission_request_int_send(*self._gcs, seq, mission_type)

    def _on_mission_count(self, msg: Any) -> None:
        mission_type = int(msg.mission_type)
        if self.script.nack_on_count is not None:
            self._ack(self.script.nack_on_count, mission_type)
            return
        if msg.count == 0:
            self._store(mission_type, [])
            self._ack(MAV_MISSION_ACCEPTED, mission_type)
            return
        self._rx = {"type": mission_type, "count": int(msg.count), "items": []}
        self._request(0, mission_type)

    def _on_mission_item_int(self, msg: Any) -> None:
        rx = self._rx
        if rx is None or msg.mission_type != rx["type"]:
            return
        seq = int(msg.seq)
        if seq != len(rx["items"]):  # a resend of an item we have: ask for the next again
            if seq < len(rx["items"]):
                self._request(len(rx["items"]), rx["type"])
            return
        self.items_received += 1
        s = self.script
        if s.silent_after_items is not None and self.items_received >= s.silent_after_items:
            self.silent = True
            return
        if s.nack_at_seq is not None and seq == s.nack_at_seq:
            self._rx = None
            self._ack(s.nack_result, rx["type"])
            return
        rx["items"].append(WireItem.from_msg(msg))
        if len(rx["items"]) == rx["count"]:
            self._rx = None
            self._store(rx["type"], rx["items"])
            self._ack(MAV_MISSION_ACCEPTED, rx["type"])
        else:
            self._request(len(rx["items"]), rx["type"])

    def _store(self, mission_type: int, items: list[WireItem]) -> None:
        """Keep a completed upload (a subclass may rewrite it, as an autopilot does)."""
        self._holdings.store(mission_type, items)

    def _on_mission_request_list(self, msg: Any) -> None:
        mission_type = int(msg.mission_type)
        self._conn.mav.mission_count_send(*self._gcs, len(self.held(mission_type)), mission_type)

    def _on_mission_request_int(self, msg: Any) -> None:
        mission_type = int(msg.mission_type)
        held = self.held(mission_type)
        seq = int(msg.seq)
        if not 0 <= seq < len(held):
            self._ack(mavutil.mavlink.MAV_MISSION_INVALID_SEQUENCE, mission_type)
            return
        w = held[seq]
        x = w.x + (self.script.download_x_offset_e7
                   if seq == self.script.download_x_offset_seq else 0)
        self._conn.mav.mission_item_int_send(
            *self._gcs, w.seq, w.frame, w.command, w.current, w.autocontinue,
            w.param1, w.param2, w.param3, w.param4, x, w.y, w.z, mission_type)

    _on_mission_request = _on_mission_request_int

    def _on_mission_clear_all(self, msg: Any) -> None:
        self._holdings.clear(int(msg.mission_type))
        self._ack(MAV_MISSION_ACCEPTED, int(msg.mission_type))


class ArduPilotLikeVehicle(ScriptedMavlinkVehicle):
    """A pymavlink vehicle that numbers its mission as ArduPilot does.

    HEARTBEAT: MAV_TYPE_QUADROTOR (2), MAV_AUTOPILOT_ARDUPILOTMEGA (3), custom mode
    enabled, STANDBY. Mission list (fence and rally are kept as sent): seq 0 is the
    vehicle's home, NAV_WAYPOINT in frame 0 (AMSL) at :attr:`home` — an uploaded seq
    0 is stored and then overwritten by it, never flown — and the uploaded items
    follow from seq 1. With nothing uploaded (or after MISSION_CLEAR_ALL) it holds
    its home alone (count 1). ``script`` misbehaviours work as in the base class.
    """

    autopilot = MAV_AUTOPILOT_ARDUPILOTMEGA
    base_mode = MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    custom_mode = 0  # Copter STABILIZE
    system_status = MAV_STATE_STANDBY

    # somewhere else than any planned home of the tests: the vehicle's own GPS home
    DEFAULT_HOME = (36.7201234, -4.4702345, 121.5)

    def __init__(self, script: VehicleScript | None = None, *, host: str = LOOPBACK,
                 home: tuple[float, float, float] = DEFAULT_HOME) -> None:
        super().__init__(script, host=host)
        self.home = home
        self.received: dict[int, list[WireItem]] = {}  # last uploads as they arrived

    def home_item(self) -> WireItem:
        lat, lon, alt = self.home
        return WireItem(seq=0, frame=MAV_FRAME_GLOBAL, command=MAV_CMD_NAV_WAYPOINT,
                        current=0, autocontinue=1, param1=0.0, param2=0.0, param3=0.0,
                        param4=0.0, x=deg_to_e7(lat), y=deg_to_e7(lon), z=float(alt),
                        mission_type=MAV_MISSION_TYPE_MISSION)

    def _store(self, mission_type: int, items: list[WireItem]) -> None:
        self.received[mission_type] = list(items)
        if mission_type == MAV_MISSION_TYPE_MISSION:
            # seq 0 is home, whatever was sent; the rest as AP_Mission stores them
            items = [self.home_item(), *(ardupilot_stored(it) for it in items[1:])]
        self._holdings.store(mission_type, items)

    def held(self, mission_type: int = MAV_MISSION_TYPE_MISSION) -> list[WireItem]:
        items = self._holdings.held(mission_type)
        if mission_type == MAV_MISSION_TYPE_MISSION and not items:
            return [self.home_item()]  # never empty: home stays in seq 0
        return items
