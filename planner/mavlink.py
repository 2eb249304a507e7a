"""Upload, download and verify missions over MAVLink (pymavlink or MAVSDK).

Two transports with one interface (:class:`MissionLink`):

- :class:`PymavlinkLink` for pymavlink URLs (``udpout:127.0.0.1:14550``,
  ``udpin:0.0.0.0:14550``, ``tcp:host:port``, ``/dev/ttyACM0``): the MAVLink
  mission protocol written out here (MISSION_COUNT, MISSION_REQUEST_INT, and the
  legacy MISSION_REQUEST answered with MISSION_ITEM_INT too, MISSION_ACK), with
  a per-message timeout and a bounded number of resends.
- :class:`MavsdkLink` for MAVSDK URLs (``udpin://``, ``udpout://``, ``tcp://``,
  ``serial://``): ``mavsdk.plugins.mission_raw.MissionRaw``; each call is started
  with the library's callback API and waited for with a deadline, then cancelled.

Items go on the wire as MISSION_ITEM_INT (:mod:`planner.mavlink_wire`: the items, their
numbering, the comparison of a read-back and the transfer errors).

Mission numbering follows the autopilot (``TransferConfig.autopilot``; "auto" reads
the HEARTBEAT's ``autopilot`` field, MAV_AUTOPILOT_ARDUPILOTMEGA = 3): PX4 (and any
other autopilot) takes mission item ``k`` as seq ``k``; ArduPilot keeps its home in
seq 0 and overwrites it, so, as QGroundControl does, a home item (NAV_WAYPOINT,
frame 0 = AMSL, the mission's planned home, current=1) goes first and item ``k`` is
seq ``k + 1`` (DO_JUMP targets shifted with it); the read-back counts seq 0 but does
not compare it. Fence and rally lists are numbered from 0 for every autopilot.

:func:`upload_mission` uploads fence, rally points and mission, downloads them
back and compares item by item; it returns an :class:`UploadReport` only when the
vehicle holds exactly what was sent, and raises an :class:`UploadError` otherwise.
MAVLINK20=1 is set before pymavlink is imported (docs/mavlink.md).
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import math
import os
import re
import socket
import stat
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

os.environ["MAVLINK20"] = "1"  # before pymavlink: else mission_type is dropped

from pymavlink import mavutil
from pymavlink.dialects.v20.common import (
    MAV_AUTOPILOT_ARDUPILOTMEGA,
    MAV_AUTOPILOT_GENERIC,
    MAV_AUTOPILOT_INVALID,
    MAV_AUTOPILOT_PX4,
    MAV_COMP_ID_MISSIONPLANNER,
    MAV_MISSION_ACCEPTED,
    MAV_MISSION_OPERATION_CANCELLED,
    MAV_TYPE_GCS,
)

from planner.mavlink_wire import (
    AUTOPILOT_CHOICES,
    MISSION_TYPE_NAMES,
    InvalidConnectionError,
    MissionRejectedError,
    NoVehicleError,
    ProtocolError,
    UploadError,
    UploadTimeoutError,
    VerifyMismatchError,
    WireItem,
    compare_wire,
    fence_to_wire,
    mission_to_wire,
    rally_to_wire,
)
from planner.mission import (
    MAV_CMD_NAV_WAYPOINT,
    MAV_FRAME_GLOBAL,
    MAV_MISSION_TYPE_FENCE,
    MAV_MISSION_TYPE_MISSION,
    MAV_MISSION_TYPE_RALLY,
    Mission,
)

if mavutil.mavlink.WIRE_PROTOCOL_VERSION != "2.0":  # pymavlink was imported before us
    mavutil.set_dialect(mavutil.current_dialect)

__all__ = [
    "MavsdkLink",
    "MissionLink",
    "PymavlinkLink",
    "TransferConfig",
    "UploadReport",
    "check_connection_url",
    "connected",
    "detected_autopilot",
    "download_wire",
    "is_mavsdk_url",
    "open_link",
    "quiet_mavsdk_logs",
    "resolve_autopilot",
    "upload_mission",
    "upload_on_link",
]

GCS_SYSTEM_ID = 255  # QGroundControl's system id
GCS_COMPONENT_ID = MAV_COMP_ID_MISSIONPLANNER
HEARTBEAT_PERIOD_S = 1.0


# ---------------------------------------------------------------- configuration


@dataclass(frozen=True, kw_only=True)
class TransferConfig:
    """Time bounds of a transfer.

    Every wait for a vehicle message lasts at most ``message_timeout_s``; the
    pymavlink path resends the last message at most ``retries`` times before
    :class:`UploadTimeoutError`. A transfer of ``n`` items is also bounded as a
    whole by ``(n + 3) * (retries + 1) * message_timeout_s`` (a vehicle that keeps
    re-requesting). The MAVSDK path uses ``message_timeout_s`` as MAVSDK's own
    timeout (its resend count is fixed by the library) under the same bound.
    """

    connect_timeout_s: float = 5.0  # wait for the vehicle's heartbeat
    message_timeout_s: float = 0.5  # MAVLink mission protocol: MAVSDK's default
    retries: int = 5
    # mission numbering: "auto" (from the HEARTBEAT), "px4" or "ardupilot" (forced)
    autopilot: str = "auto"

    def __post_init__(self) -> None:
        if self.autopilot not in AUTOPILOT_CHOICES:
            raise ValueError(f"autopilot must be one of {AUTOPILOT_CHOICES}, "
                             f"got {self.autopilot!r}")

    def transfer_bound_s(self, n_items: int) -> float:
        return (n_items + 3) * (self.retries + 1) * self.message_timeout_s


@dataclass(frozen=True)
class UploadReport:
    """What :func:`upload_mission` verified on the vehicle."""

    items: int
    fence_items: int
    rally_items: int
    elapsed_s: float
    backend: str
    vehicle: tuple[int, int] = (0, 0)  # system id, component id
    # mission numbering used: "ardupilot" = home item in seq 0, not counted in items
    autopilot: str = "px4"


# ---------------------------------------------------------------- links


class MissionLink(Protocol):
    """A connection to one vehicle that can move mission items both ways."""

    backend: str
    vehicle: tuple[int, int]
    autopilot: int | None  # MAV_AUTOPILOT of the vehicle's HEARTBEAT (None: unknown)

    def upload(self, items: Sequence[WireItem], mission_type: int) -> None: ...

    def clear(self, mission_type: int) -> None: ...

    def download(self, mission_type: int, expected_items: int = ...) -> list[WireItem]: ...

    def close(self) -> None: ...


MAVSDK_SCHEMES = ("udpin://", "udpout://", "udp://", "tcp://", "tcpin://", "tcpout://",
                  "serial://")


def is_mavsdk_url(url: str) -> bool:
    """True for MAVSDK's ``scheme://`` URLs, False for pymavlink's ``scheme:`` forms."""
    return "://" in url


# pymavlink's network and socket forms (mavutil.mavlink_connection); anything else
# without a colon is a serial device path, optionally with ",BAUD"
PYMAVLINK_PREFIXES = ("tcp:", "tcpin:", "udpin:", "udpout:", "udpbcast:", "udp:", "mcast:",
                      "ws:", "wss:", "wsserver:", "uds:", "unix:")
URL_EXAMPLES = ("udpout:127.0.0.1:14550, udpin:0.0.0.0:14550, tcp:HOST:PORT, a serial device "
                "such as /dev/ttyUSB0 or /dev/ttyUSB0,57600, or a MAVSDK URL such as "
                "udpin://0.0.0.0:14540 or serial:///dev/ttyUSB0:57600")


def _check_serial_device(device: str, url: str) -> None:
    if os.name == "nt":  # COM ports are not paths
        return
    if not os.path.exists(device):
        if "/" not in device:
            raise InvalidConnectionError(
                f"{url!r} is not a connection URL nor a serial device; use {URL_EXAMPLES}")
        raise InvalidConnectionError(
            f"no serial device {device} (is the telemetry radio plugged in?)")
    if not stat.S_ISCHR(os.stat(device).st_mode):
        raise InvalidConnectionError(
            f"{url!r} is not a serial device nor a connection URL; use {URL_EXAMPLES}")


# a host name (RFC 1123 labels) or an IPv4 address; pymavlink splits on ':' (no IPv6)
_HOST_RE = re.compile(r"^(?=.{1,253}$)[A-Za-z0-9](?:[A-Za-z0-9-]{0,61}[A-Za-z0-9])?"
                      r"(?:\.[A-Za-z0-9](?:[A-Za-z0-9-]{0,61}[A-Za-z0-9])?)*$")
# schemes that listen: the host may be empty (every interface), as MAVSDK's udpin://:14540
_LISTEN = ("udpin:", "tcpin:", "udpin://", "udp://", "tcpin://")
_NO_HOST_PORT = ("ws:", "wss:", "wsserver:", "uds:", "unix:")  # URLs, paths: not checked


def _check_host_port(url: str, scheme: str, rest: str) -> None:
    """HOST:PORT of a network URL: a port 1..65535, a host name or an IPv4 address."""
    host, sep, port = rest.rpartition(":")
    if not sep:
        raise InvalidConnectionError(f"{url!r} has no port: use {scheme}HOST:PORT")
    if not (port.isascii() and port.isdigit() and 1 <= int(port) <= 65535):
        raise InvalidConnectionError(f"port {port!r} of {url!r} is not a number in 1..65535")
    if not host and scheme in _LISTEN:
        return
    if not _HOST_RE.match(host):
        raise InvalidConnectionError(f"host {host!r} of {url!r} is not a host name or an "
                                     "IPv4 address")


def check_connection_url(url: str) -> None:
    """Refuse, before any I/O, a URL that cannot reach a vehicle: empty, an unknown
    scheme, a port outside 1..65535, a malformed host, an absent serial device or a
    plain file (pymavlink would replay a log file or even execute it). Raises
    :class:`InvalidConnectionError` with one line."""
    if not url.strip():
        raise InvalidConnectionError(f"empty connection URL; use {URL_EXAMPLES}")
    if is_mavsdk_url(url):
        scheme = url.split("://", 1)[0] + "://"
        if scheme not in MAVSDK_SCHEMES:
            raise InvalidConnectionError(
                f"unknown connection scheme {scheme!r} in {url!r}; use {URL_EXAMPLES}")
        if scheme == "serial://":
            device, _, baud = url[len(scheme):].rpartition(":")
            _check_serial_device(device if baud.isdigit() else url[len(scheme):], url)
        else:
            _check_host_port(url, scheme, url[len(scheme):])
        return
    if url.startswith(_NO_HOST_PORT):
        return
    if url.startswith(PYMAVLINK_PREFIXES):
        scheme = url[: url.index(":") + 1]
        _check_host_port(url, scheme, url[len(scheme):])
        return
    if ":" in url:  # pymavlink's legacy UDP form HOST:PORT
        _check_host_port(url, "", url)
        return
    device = url
    if "," in url and not os.path.exists(url):
        device, _, baud = url.rpartition(",")
        if not baud.isdigit() or int(baud) <= 0:
            raise InvalidConnectionError(f"bad baud rate {baud!r} in {url!r}")
    _check_serial_device(device, url)
    try:
        import serial  # noqa: F401 - pymavlink imports it inside its serial class
    except ModuleNotFoundError:
        raise InvalidConnectionError(
            f"{device}: serial connections need pyserial (pip install pyserial)") from None


def open_link(url: str, config: TransferConfig | None = None) -> MavsdkLink | PymavlinkLink:
    """Connect to the vehicle at ``url`` and wait for it (:class:`NoVehicleError`)."""
    check_connection_url(url)
    config = config or TransferConfig()
    if is_mavsdk_url(url):
        return MavsdkLink(url, config)
    return PymavlinkLink(url, config)


def detected_autopilot(link: Any) -> int | None:
    """The MAV_AUTOPILOT the link saw in the vehicle's HEARTBEAT (None: unknown)."""
    return getattr(link, "autopilot", None)


def resolve_autopilot(choice: str, link: Any = None) -> str:
    """The mission numbering for ``choice`` ("auto", "px4" or "ardupilot") on ``link``:
    "ardupilot" when forced or when "auto" and the vehicle's HEARTBEAT says
    MAV_AUTOPILOT_ARDUPILOTMEGA (3), else "px4" (PX4, generic, unknown)."""
    if choice not in AUTOPILOT_CHOICES:
        raise ValueError(f"autopilot must be one of {AUTOPILOT_CHOICES}, got {choice!r}")
    if choice != "auto":
        return choice
    return "ardupilot" if detected_autopilot(link) == MAV_AUTOPILOT_ARDUPILOTMEGA else "px4"


def _result_name(code: int) -> str:
    entry = mavutil.mavlink.enums["MAV_MISSION_RESULT"].get(code)
    return entry.name if entry is not None else f"MAV_MISSION_RESULT_{code}"


def _vehicle_closed() -> None:
    raise ConnectionAbortedError("the vehicle closed the connection")


def _vehicle_reset() -> None:
    raise ConnectionResetError("the connection was reset (the vehicle is gone)")


def _lost_is_no_vehicle(method: Callable) -> Callable:
    """A link that dies mid-transfer (a TCP vehicle reset or closed the connection, a
    serial device unplugged) is a lost vehicle: :class:`NoVehicleError`, one line."""
    @functools.wraps(method)
    def wrapper(self: PymavlinkLink, *args: Any, **kwargs: Any) -> Any:
        try:
            return method(self, *args, **kwargs)
        except OSError as exc:
            raise NoVehicleError(f"lost the vehicle on {self.url}: "
                                 f"{exc.strerror or exc}") from None
    return wrapper


class PymavlinkLink:
    """The mission protocol over a pymavlink connection."""

    backend = "pymavlink"

    def __init__(self, url: str, config: TransferConfig | None = None, *,
                 source_system: int = GCS_SYSTEM_ID,
                 source_component: int = GCS_COMPONENT_ID) -> None:
        self.config = config or TransferConfig()
        self.url = url
        self._src = (source_system, source_component)
        self._last_heartbeat_s = -math.inf
        self.autopilot: int | None = None  # MAV_AUTOPILOT of the vehicle's HEARTBEAT
        self._conn = self._open(url)
        try:
            self.vehicle = self._wait_vehicle(self.config.connect_timeout_s)
        except BaseException:
            self._conn.close()
            raise

    def _open(self, url: str) -> Any:
        if url.startswith("tcp:"):  # fail fast and bounded instead of pymavlink's retries
            host, _, port = url[4:].rpartition(":")
            try:
                with socket.create_connection((host, int(port)),
                                              timeout=self.config.connect_timeout_s):
                    pass
            except ValueError as exc:
                raise InvalidConnectionError(f"bad TCP URL {url!r}: {exc}") from None
            except OSError as exc:
                raise NoVehicleError(f"no vehicle at {url}: {exc}") from None
        try:
            conn = mavutil.mavlink_connection(
                url, source_system=self._src[0], source_component=self._src[1],
                autoreconnect=False, retries=0, reconnect_delay=0.1)
        except (ValueError, IndexError) as exc:
            raise InvalidConnectionError(f"bad connection URL {url!r}: {exc}") from None
        except OSError as exc:
            raise InvalidConnectionError(f"cannot open {url}: {exc}") from None
        if hasattr(conn, "handle_eof"):
            # pymavlink's TCP link prints "EOF on TCP socket" on stdout at every read of a
            # closed connection and goes on: a closed link is a lost vehicle instead
            conn.handle_eof, conn.handle_disconnect = _vehicle_closed, _vehicle_reset
        return conn

    @property
    def connection(self) -> Any:
        """The pymavlink connection, for a caller that also reads telemetry or sends
        commands on the same link (a vehicle answers one ground-station address)."""
        return self._conn

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self._conn.close()

    def __enter__(self) -> PymavlinkLink:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- low level

    def heartbeat(self, force: bool = False) -> bool:
        """The ground station's HEARTBEAT if one is due (1 Hz) or ``force``; True if sent."""
        now = time.monotonic()
        if not force and now - self._last_heartbeat_s < HEARTBEAT_PERIOD_S:
            return False
        self._last_heartbeat_s = now
        with contextlib.suppress(OSError):
            self._conn.mav.heartbeat_send(MAV_TYPE_GCS, MAV_AUTOPILOT_INVALID, 0, 0, 0)
        return True

    @_lost_is_no_vehicle
    def _wait_vehicle(self, timeout_s: float) -> tuple[int, int]:
        deadline = time.monotonic() + timeout_s
        while (left := deadline - time.monotonic()) > 0:
            self.heartbeat()  # a udpin vehicle learns our address from it
            msg = self._conn.recv_match(type="HEARTBEAT", blocking=True,
                                        timeout=min(left, HEARTBEAT_PERIOD_S / 2))
            if (msg is not None and msg.type != MAV_TYPE_GCS
                    and msg.autopilot != MAV_AUTOPILOT_INVALID):
                self.autopilot = int(msg.autopilot)
                return msg.get_srcSystem(), msg.get_srcComponent()
        raise NoVehicleError(f"no vehicle heartbeat on {self.url} within {timeout_s:g} s")

    def _recv(self, types: Sequence[str], deadline: float) -> Any | None:
        """The next message of ``types`` from the vehicle to us, or None at ``deadline``."""
        sysid, compid = self.vehicle
        while (left := deadline - time.monotonic()) > 0:
            self.heartbeat()
            msg = self._conn.recv_match(type=list(types), blocking=True,
                                        timeout=min(left, HEARTBEAT_PERIOD_S))
            if msg is None:
                continue
            if msg.get_srcSystem() != sysid or msg.get_srcComponent() != compid:
                continue
            if getattr(msg, "target_system", self._src[0]) not in (0, self._src[0]):
                continue
            return msg
        return None

    def _target(self) -> tuple[int, int]:
        return self.vehicle

    def _send_item(self, w: WireItem) -> None:
        self._conn.mav.mission_item_int_send(
            *self._target(), w.seq, w.frame, w.command, w.current, w.autocontinue,
            w.param1, w.param2, w.param3, w.param4, w.x, w.y, w.z, w.mission_type)

    def _cancel(self, mission_type: int) -> None:
        with contextlib.suppress(OSError):
            self._conn.mav.mission_ack_send(*self._target(), MAV_MISSION_OPERATION_CANCELLED,
                                            mission_type)

    # -- transfers

    @_lost_is_no_vehicle
    def upload(self, items: Sequence[WireItem], mission_type: int) -> None:
        """Send ``items`` (seq 0..n-1 of ``mission_type``); return once ACCEPTED."""
        _check_wire(items, mission_type)
        if not items:
            self.clear(mission_type)
            return
        n = len(items)
        cfg = self.config
        kind = MISSION_TYPE_NAMES.get(mission_type, str(mission_type))
        self._drain()
        end = time.monotonic() + cfg.transfer_bound_s(n)

        def send_count() -> None:
            self._conn.mav.mission_count_send(*self._target(), n, mission_type)

        resend: Callable[[], None] = send_count
        send_count()
        deadline = time.monotonic() + cfg.message_timeout_s
        tries = 0
        sent = [False] * n
        while True:
            msg = self._recv(("MISSION_REQUEST_INT", "MISSION_REQUEST", "MISSION_ACK"),
                             min(end, deadline))
            if msg is not None and getattr(msg, "mission_type", 0) != mission_type:
                continue  # another transfer's message
            if msg is None:
                if tries >= cfg.retries or time.monotonic() >= end:
                    self._cancel(mission_type)
                    raise UploadTimeoutError(
                        f"{kind} upload timed out: no answer after {sum(sent)} of {n} items "
                        f"({tries} resends, {cfg.message_timeout_s:g} s each); "
                        f"the vehicle does not hold the {kind}")
                tries += 1
                resend()
                deadline = time.monotonic() + cfg.message_timeout_s
                continue
            if msg.get_type() == "MISSION_ACK":
                if msg.type != MAV_MISSION_ACCEPTED:
                    raise MissionRejectedError(_result_name(msg.type), mission_type=mission_type,
                                               result_code=int(msg.type))
                if all(sent):
                    return
                raise ProtocolError(f"{kind} upload: vehicle accepted after {sum(sent)} of "
                                    f"{n} items; the vehicle does not hold the {kind}")
            seq = int(msg.seq)
            if not 0 <= seq < n:
                self._cancel(mission_type)
                raise ProtocolError(f"{kind} upload: vehicle requested item {seq} of {n}")
            item = items[seq]

            def resend_item(item: WireItem = item) -> None:
                self._send_item(item)

            resend = resend_item
            resend()
            sent[seq] = True
            tries = 0
            deadline = time.monotonic() + cfg.message_timeout_s

    @_lost_is_no_vehicle
    def clear(self, mission_type: int) -> None:
        """MISSION_CLEAR_ALL for ``mission_type``; return once ACCEPTED.

        An empty upload is sent this way, never as MISSION_COUNT 0: MAVSDK 4.1's
        MissionRawServer is left corrupted by a count of 0 (the next upload aborts)."""
        cfg = self.config
        kind = MISSION_TYPE_NAMES.get(mission_type, str(mission_type))
        self._drain()
        for _ in range(cfg.retries + 1):
            self._conn.mav.mission_clear_all_send(*self._target(), mission_type)
            deadline = time.monotonic() + cfg.message_timeout_s
            while (msg := self._recv(("MISSION_ACK",), deadline)) is not None:
                if getattr(msg, "mission_type", 0) != mission_type:
                    continue
                if msg.type != MAV_MISSION_ACCEPTED:
                    raise MissionRejectedError(_result_name(msg.type), mission_type=mission_type,
                                               result_code=int(msg.type), detail="clear all")
                return
        raise UploadTimeoutError(f"{kind} clear timed out: no MISSION_ACK after "
                                 f"{cfg.retries} resends")

    def _drain(self, max_messages: int = 1000) -> None:
        """Drop messages already received (late answers of an earlier transfer)."""
        for _ in range(max_messages):
            if self._conn.recv_match(blocking=False) is None:
                return

    @_lost_is_no_vehicle
    def download(self, mission_type: int, expected_items: int = 0) -> list[WireItem]:
        """Read the vehicle's items of ``mission_type`` (MISSION_REQUEST_INT each).

        ``expected_items`` is unused here: the bound follows the vehicle's count."""
        cfg = self.config
        kind = MISSION_TYPE_NAMES.get(mission_type, str(mission_type))

        def ask(send: Callable[[], None], types: Sequence[str],
                accept: Callable[[Any], bool], what: str, end: float) -> Any:
            tries = 0
            send()
            deadline = time.monotonic() + cfg.message_timeout_s
            while True:
                msg = self._recv((*types, "MISSION_ACK"), min(deadline, end))
                if msg is not None and getattr(msg, "mission_type", 0) != mission_type:
                    continue
                if msg is None:
                    if tries >= cfg.retries or time.monotonic() >= end:
                        self._cancel(mission_type)
                        raise UploadTimeoutError(f"{kind} download timed out waiting for {what}")
                    tries += 1
                    send()
                    deadline = time.monotonic() + cfg.message_timeout_s
                    continue
                if msg.get_type() == "MISSION_ACK":
                    if msg.type == MAV_MISSION_ACCEPTED:
                        continue  # a late ACK of an earlier transfer
                    raise MissionRejectedError(_result_name(msg.type), mission_type=mission_type,
                                               result_code=int(msg.type),
                                               detail="during download")
                if msg.get_type() == "MISSION_ITEM":
                    self._cancel(mission_type)
                    raise ProtocolError(f"{kind} download: vehicle sent float MISSION_ITEM")
                if accept(msg):
                    return msg

        target = self._target()
        self._drain()
        count_msg = ask(lambda: self._conn.mav.mission_request_list_send(*target, mission_type),
                        ("MISSION_COUNT",), lambda m: True, "MISSION_COUNT",
                        time.monotonic() + cfg.transfer_bound_s(0))
        n = int(count_msg.count)
        end = time.monotonic() + cfg.transfer_bound_s(n)
        out: list[WireItem] = []
        for seq in range(n):
            msg = ask(lambda seq=seq: self._conn.mav.mission_request_int_send(
                          *target, seq, mission_type),
                      ("MISSION_ITEM_INT", "MISSION_ITEM"), lambda m, seq=seq: m.seq == seq,
                      f"item {seq} of {n}", end)
            out.append(WireItem.from_msg(msg))
        self._conn.mav.mission_ack_send(*target, MAV_MISSION_ACCEPTED, mission_type)
        return out


def _check_wire(items: Sequence[WireItem], mission_type: int) -> None:
    """Refuse what a vehicle would NACK anyway: gaps, mixed types, current != 1 item."""
    for i, w in enumerate(items):
        if w.seq != i:
            raise ValueError(f"item {i} has seq {w.seq}: seq must be contiguous from 0")
        if w.mission_type != mission_type:
            raise ValueError(f"item {i} has mission_type {w.mission_type}, not {mission_type}")
    if mission_type == MAV_MISSION_TYPE_MISSION and items:
        current = [w.seq for w in items if w.current]
        if current != [0]:
            raise ValueError(f"exactly item 0 must be current, got {current}")


# MissionRawResult names that are not a vehicle's NACK; any other failure is one
_MAVSDK_TIMEOUT = {"TIMEOUT"}
_MAVSDK_NO_VEHICLE = {"NO_SYSTEM"}
_MAVSDK_PROTOCOL = {"BUSY", "INT_MESSAGES_NOT_SUPPORTED"}


class MavsdkLink:
    """Mission transfers through MAVSDK's MissionRaw (libcmavsdk, no server binary)."""

    backend = "mavsdk"

    def __init__(self, url: str, config: TransferConfig | None = None) -> None:
        from mavsdk import ComponentType, Configuration, Mavsdk
        from mavsdk.cmavsdk_loader import _cmavsdk_lib
        from mavsdk.connection_result import ConnectionResult
        from mavsdk.plugins.mission_raw import MissionRaw

        quiet_mavsdk_logs()
        self.config = config or TransferConfig()
        self.url = url
        self._mavsdk = Mavsdk(Configuration.create_with_component_type(
            ComponentType.GROUND_STATION))
        try:
            # per-message timeout of MAVSDK's transfers (not wrapped in Python)
            _cmavsdk_lib.mavsdk_set_timeout_s.argtypes = [ctypes.c_void_p, ctypes.c_double]
            _cmavsdk_lib.mavsdk_set_timeout_s.restype = None
            _cmavsdk_lib.mavsdk_set_timeout_s(self._mavsdk._handle,
                                              float(self.config.message_timeout_s))
            result = self._mavsdk.add_any_connection(url)
            if result != ConnectionResult.SUCCESS:
                raise InvalidConnectionError(f"cannot open {url}: {result.name}")
            system = self._mavsdk.first_autopilot(self.config.connect_timeout_s)
            if system is None:
                raise NoVehicleError(
                    f"no vehicle heartbeat on {url} within {self.config.connect_timeout_s:g} s")
            ids = system.component_ids()
            self.vehicle = (system.get_system_id(), 1 if 1 in ids or not ids else ids[0])
            self._system = system
            self.autopilot = self._autopilot_of(system)
            self._plugin = MissionRaw(system)
        except BaseException:
            self._mavsdk.destroy()
            raise

    def _autopilot_of(self, system: Any, wait_s: float = 2 * HEARTBEAT_PERIOD_S) -> int | None:
        """MAV_AUTOPILOT from MAVSDK's ``System.autopilot_type()`` (set from the
        HEARTBEAT: PX4 -> 12, ArduPilot -> 3, anything else -> GENERIC -> 0); UNKNOWN,
        polled for at most ``wait_s``, gives None."""
        from mavsdk.autopilot import Autopilot

        to_mav = {Autopilot.PX4: MAV_AUTOPILOT_PX4,
                  Autopilot.ARDUPILOT: MAV_AUTOPILOT_ARDUPILOTMEGA,
                  Autopilot.GENERIC: MAV_AUTOPILOT_GENERIC}
        deadline = time.monotonic() + min(wait_s, self.config.connect_timeout_s)
        while True:
            kind = system.autopilot_type()
            if kind in to_mav:
                return to_mav[kind]
            if time.monotonic() >= deadline:
                return None
            time.sleep(0.01)

    def close(self) -> None:
        self._mavsdk.destroy()

    def __enter__(self) -> MavsdkLink:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _wait(self, start: Callable[[Callable[..., None]], None], n_items: int,
              what: str, mission_type: int, cancel: Callable[[], Any] | None) -> tuple[Any, Any]:
        """Start a callback-style MAVSDK call and wait for it with a deadline."""
        done = threading.Event()
        box: list[tuple[Any, Any]] = []

        def callback(result: Any, data: Any = None) -> None:
            box.append((result, data))
            done.set()

        start(callback)
        bound_s = self.config.transfer_bound_s(n_items) + 1.0
        if not done.wait(bound_s):
            if cancel is not None:
                with contextlib.suppress(Exception):
                    cancel()
            raise UploadTimeoutError(f"{what} did not finish within {bound_s:g} s")
        result, data = box[0]
        name = result.name
        if name == "SUCCESS":
            return result, data
        kind = MISSION_TYPE_NAMES.get(mission_type, str(mission_type))
        if name in _MAVSDK_TIMEOUT:
            raise UploadTimeoutError(f"{what} timed out (MAVSDK: {name}); "
                                     f"the vehicle does not hold the {kind}")
        if name in _MAVSDK_NO_VEHICLE:
            raise NoVehicleError(f"{what}: vehicle lost (MAVSDK: {name})")
        if name in _MAVSDK_PROTOCOL:
            raise ProtocolError(f"{what} failed: MAVSDK {name}")
        raise MissionRejectedError(name, mission_type=mission_type, result_code=int(result))

    def upload(self, items: Sequence[WireItem], mission_type: int) -> None:
        from mavsdk.plugins.mission_raw import MissionItem as RawItem

        _check_wire(items, mission_type)
        raw = [RawItem(seq=w.seq, frame=w.frame, command=w.command, current=w.current,
                       autocontinue=w.autocontinue, param1=w.param1, param2=w.param2,
                       param3=w.param3, param4=w.param4, x=w.x, y=w.y, z=w.z,
                       mission_type=w.mission_type) for w in items]
        p = self._plugin
        if not items:  # MAVSDK refuses an empty upload (NO_MISSION_AVAILABLE): clear instead
            self.clear(mission_type)
            return
        start, cancel = {
            MAV_MISSION_TYPE_MISSION: (p.upload_mission_async, p.cancel_mission_upload),
            MAV_MISSION_TYPE_FENCE: (p.upload_geofence_async, None),
            MAV_MISSION_TYPE_RALLY: (p.upload_rally_points_async, None),
        }[mission_type]
        kind = MISSION_TYPE_NAMES[mission_type]
        self._wait(lambda cb: start(raw, lambda r, ud: cb(r)), len(items),
                   f"{kind} upload", mission_type, cancel)

    def import_qgc_plan(self, path: str | os.PathLike[str]) -> dict[int, list[WireItem]]:
        """MAVSDK's own reading of a QGroundControl ``.plan``: items per mission type.

        An independent check of :func:`planner.files.write_plan` (no transfer)."""
        from mavsdk.plugins.mission_raw import MissionRawError

        try:
            data = self._plugin.import_qgroundcontrol_mission(os.fspath(path))
        except MissionRawError as exc:
            raise ValueError(f"MAVSDK cannot import {path}: {exc.result.name}") from None
        return {
            MAV_MISSION_TYPE_MISSION: [WireItem.from_msg(m) for m in data.mission_items],
            MAV_MISSION_TYPE_FENCE: [WireItem.from_msg(m) for m in data.geofence_items],
            MAV_MISSION_TYPE_RALLY: [WireItem.from_msg(m) for m in data.rally_items],
        }

    def clear(self, mission_type: int) -> None:
        """Clear the vehicle's mission (MissionRaw) or fence (the Geofence plugin);
        MAVSDK cannot clear rally points: if the vehicle holds some, an
        :class:`UploadError` says so."""
        if mission_type == MAV_MISSION_TYPE_MISSION:
            p = self._plugin
            self._wait(lambda cb: p.clear_mission_async(lambda r, ud: cb(r)), 0,
                       "mission clear", mission_type, None)
        elif mission_type == MAV_MISSION_TYPE_FENCE:
            from mavsdk.plugins.geofence import Geofence

            g = Geofence(self._system)
            self._wait(lambda cb: g.clear_geofence_async(lambda r, ud: cb(r)), 0,
                       "fence clear", mission_type, None)
        else:
            held = len(self.download(mission_type, expected_items=16))
            if held:
                raise UploadError(
                    f"the vehicle holds {held} rally point{'s' * (held != 1)} and the file "
                    "none; MAVSDK cannot clear rally points: upload with a pymavlink URL "
                    "(udpout:HOST:PORT) or clear them from the ground station")

    def download(self, mission_type: int, expected_items: int = 100) -> list[WireItem]:
        """The vehicle's items; ``expected_items`` only sizes the time bound."""
        p = self._plugin
        start = {
            MAV_MISSION_TYPE_MISSION: p.download_mission_async,
            MAV_MISSION_TYPE_FENCE: p.download_geofence_async,
            MAV_MISSION_TYPE_RALLY: p.download_rallypoints_async,
        }[mission_type]
        kind = MISSION_TYPE_NAMES[mission_type]
        # the count is unknown before the download: bound as for a large mission
        _, data = self._wait(lambda cb: start(lambda r, items, ud: cb(r, items)),
                             expected_items, f"{kind} download", mission_type,
                             p.cancel_mission_download)
        return [WireItem.from_msg(m) for m in data or []]


_LOG_LOCK = threading.Lock()
_LOGS_QUIET = False


def quiet_mavsdk_logs() -> None:
    """Route MAVSDK's console log to Python logging (logger ``mavsdk``, silent unless
    the application configures logging), once per process."""
    global _LOGS_QUIET
    with _LOG_LOCK:
        if _LOGS_QUIET:
            return
        import logging

        from mavsdk import LogLevel, log_subscribe

        logger = logging.getLogger("mavsdk")
        logger.addHandler(logging.NullHandler())  # no stderr fallback: errors are raised
        levels = {LogLevel.DEBUG: logging.DEBUG, LogLevel.INFO: logging.DEBUG,
                  LogLevel.WARN: logging.WARNING, LogLevel.ERROR: logging.ERROR}

        def forward(level: Any, message: str, file: str | None, line: int) -> bool:
            logger.log(levels.get(level, logging.INFO), "%s (%s:%s)", message, file, line)
            return True

        log_subscribe(forward)
        _LOGS_QUIET = True


# ---------------------------------------------------------------- high level


@dataclass
class _Plan:
    mission_type: int
    items: list[WireItem] = field(default_factory=list)
    skip_seq0: bool = False  # ArduPilot's home item: sent, counted, not compared


def _plans(mission: Mission, fence: bool, numbering: str = "px4",
           replace_fence: bool = False) -> list[_Plan]:
    """What to send, in order: fence and rally first (a vehicle may check the mission
    against its fence on upload), then the mission (with ArduPilot's home item in seq
    0 for ``numbering="ardupilot"``; fence and rally never have one). An empty fence or
    rally list is sent (a clear) only with ``replace_fence``."""
    plans = []
    if fence:
        fence_items = fence_to_wire(mission)
        if fence_items or replace_fence:
            plans.append(_Plan(MAV_MISSION_TYPE_FENCE, fence_items))
        rally_items = rally_to_wire(mission)
        if rally_items or replace_fence:
            plans.append(_Plan(MAV_MISSION_TYPE_RALLY, rally_items))
    plans.append(_Plan(MAV_MISSION_TYPE_MISSION, mission_to_wire(mission, autopilot=numbering),
                       skip_seq0=numbering == "ardupilot"))
    return plans


def _verify_error(plan: _Plan, held: Sequence[WireItem], diffs: list[str],
                  detected: int | None) -> VerifyMismatchError:
    """The mismatch, with a hint when a PX4-numbered upload came back changed in item 0
    only and the vehicle is (or item 0 looks like) an ArduPilot home."""
    hint = ""
    only_seq0 = (plan.mission_type == MAV_MISSION_TYPE_MISSION and not plan.skip_seq0
                 and len(held) == len(plan.items)
                 and not compare_wire(plan.items, held, skip_seq0=True))
    if only_seq0 and (detected == MAV_AUTOPILOT_ARDUPILOTMEGA
                      or (held[0].command == MAV_CMD_NAV_WAYPOINT
                          and held[0].frame == MAV_FRAME_GLOBAL)):
        said = (" (its heartbeat says ArduPilot)" if detected == MAV_AUTOPILOT_ARDUPILOTMEGA
                else "")
        hint = (f"the vehicle rewrote item 0 with a home position as ArduPilot does{said}; "
                "upload with autopilot 'auto' or 'ardupilot'")
    return VerifyMismatchError(diffs, mission_type=plan.mission_type, hint=hint)


def upload_on_link(link: MissionLink, mission: Mission, *, fence: bool = True,
                   verify: bool = True, autopilot: str | None = None,
                   replace_fence: bool = False) -> tuple[int, int, int]:
    """Upload (and read back) ``mission`` on an open link; item counts on success.

    ``autopilot`` ("auto", "px4", "ardupilot"; None = the link's
    ``config.autopilot``, else "auto") picks the mission numbering (see
    :func:`resolve_autopilot`); the mission count never includes ArduPilot's home.
    ``replace_fence``: the mission's fence and rally points replace the vehicle's also
    when empty (a ``.plan`` always says what they are), else an empty one is not sent."""
    if autopilot is None:
        autopilot = getattr(getattr(link, "config", None), "autopilot", "auto")
    numbering = resolve_autopilot(autopilot, link)
    try:
        plans = _plans(mission, fence, numbering, replace_fence)
    except ValueError as exc:
        raise UploadError(f"mission cannot be sent: {exc}") from None
    for plan in plans:  # an empty mission to ArduPilot is its home item alone (count 1)
        link.upload(plan.items, plan.mission_type)
    if verify:
        for plan in plans:
            held = link.download(plan.mission_type, expected_items=len(plan.items))
            diffs = compare_wire(plan.items, held, skip_seq0=plan.skip_seq0)
            if diffs:
                raise _verify_error(plan, held, diffs, detected_autopilot(link))
    counts = {p.mission_type: len(p.items) - int(p.skip_seq0) for p in plans}
    return (counts.get(MAV_MISSION_TYPE_MISSION, 0), counts.get(MAV_MISSION_TYPE_FENCE, 0),
            counts.get(MAV_MISSION_TYPE_RALLY, 0))


def upload_mission(mission: Mission, url: str, *, config: TransferConfig | None = None,
                   fence: bool = True, verify: bool = True,
                   autopilot: str | None = None, replace_fence: bool = False) -> UploadReport:
    """Upload ``mission`` (+ fence and rally points unless ``fence=False``; empty ones
    clear the vehicle's with ``replace_fence``) to the vehicle at ``url``, read
    everything back and compare.

    ``autopilot`` ("auto", "px4", "ardupilot"; None = ``config.autopilot``, default
    "auto": from the vehicle's HEARTBEAT) picks the mission numbering: ArduPilot gets
    its home item in seq 0 and the items from seq 1 (see the module docstring).
    Returns only when the vehicle holds exactly what was sent; raises
    :class:`UploadError` (one of its subclasses) otherwise.
    """
    config = config or TransferConfig()
    choice = config.autopilot if autopilot is None else autopilot
    resolve_autopilot(choice)  # a bad choice fails before connecting
    t0 = time.perf_counter()
    with contextlib.closing(open_link(url, config)) as link:
        numbering = resolve_autopilot(choice, link)
        n_items, n_fence, n_rally = upload_on_link(link, mission, fence=fence, verify=verify,
                                                   autopilot=numbering,
                                                   replace_fence=replace_fence)
        return UploadReport(items=n_items, fence_items=n_fence, rally_items=n_rally,
                            elapsed_s=time.perf_counter() - t0, backend=link.backend,
                            vehicle=link.vehicle, autopilot=numbering)


def download_wire(url: str, mission_types: Sequence[int] = (MAV_MISSION_TYPE_MISSION,),
                  *, config: TransferConfig | None = None) -> dict[int, list[WireItem]]:
    """Download the vehicle's items of each of ``mission_types``."""
    with contextlib.closing(open_link(url, config)) as link:
        return {t: link.download(t) for t in mission_types}


@contextlib.contextmanager
def connected(url: str, config: TransferConfig | None = None) -> Iterator[MissionLink]:
    """``with connected(url) as link:`` an open :class:`MissionLink`, closed after."""
    link = open_link(url, config)
    try:
        yield link
    finally:
        link.close()
