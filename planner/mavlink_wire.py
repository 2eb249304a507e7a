"""The MAVLink mission wire format: items as MISSION_ITEM_INT carries them.

Items go on the wire as MISSION_ITEM_INT (:class:`WireItem`): frame as given
(default 6, GLOBAL_RELATIVE_ALT_INT), x/y = :func:`planner.mission.deg_to_e7`,
contiguous seq, exactly one ``current`` item (seq 0) for the mission. Fence
polygons go as ``NAV_FENCE_POLYGON_VERTEX_*`` (param1 = vertex count), circles as
``NAV_FENCE_CIRCLE_*`` (param1 = radius), rally points as ``NAV_RALLY_POINT``.

Mission numbering follows the autopilot: PX4 (and any other autopilot) takes mission
item ``k`` as seq ``k``; ArduPilot keeps its home in seq 0 and overwrites it, so, as
QGroundControl does, a home item (NAV_WAYPOINT, frame 0 = AMSL, the mission's planned
home, current=1) goes first and item ``k`` is seq ``k + 1`` (DO_JUMP targets shifted
with it). :func:`compare_wire` says how a read-back differs from what was sent; the
errors of a transfer (:class:`UploadError` and its kinds) are defined here too, with
the wire's own (:class:`ProtocolError` for items that do not make a fence). The links
that carry the items are in :mod:`planner.mavlink`.
"""

from __future__ import annotations

import dataclasses
import math
import struct
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from pymavlink.dialects.v20.common import (
    MAV_CMD_CONDITION_DELAY,
    MAV_CMD_CONDITION_LAST,
    MAV_CMD_DO_SET_MODE,
    MAV_CMD_OVERRIDE_GOTO,
)

from planner.mission import (
    MAV_CMD_DO_JUMP,
    MAV_CMD_NAV_FENCE_CIRCLE_EXCLUSION,
    MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION,
    MAV_CMD_NAV_FENCE_POLYGON_VERTEX_EXCLUSION,
    MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION,
    MAV_CMD_NAV_RALLY_POINT,
    MAV_CMD_NAV_RETURN_TO_LAUNCH,
    MAV_CMD_NAV_WAYPOINT,
    MAV_FRAME_GLOBAL,
    MAV_FRAME_GLOBAL_INT,
    MAV_FRAME_GLOBAL_RELATIVE_ALT,
    MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
    MAV_FRAME_GLOBAL_TERRAIN_ALT,
    MAV_FRAME_GLOBAL_TERRAIN_ALT_INT,
    MAV_MISSION_TYPE_FENCE,
    MAV_MISSION_TYPE_MISSION,
    MAV_MISSION_TYPE_RALLY,
    FenceCircle,
    FencePolygon,
    Mission,
    MissionItem,
    deg_to_e7,
    e7_to_deg,
)

MISSION_TYPE_NAMES = {
    MAV_MISSION_TYPE_MISSION: "mission",
    MAV_MISSION_TYPE_FENCE: "fence",
    MAV_MISSION_TYPE_RALLY: "rally",
}
# TransferConfig.autopilot: "auto" = from the vehicle's HEARTBEAT; the others force
# the mission numbering ("px4": item k is seq k; "ardupilot": home in seq 0, item k
# is seq k + 1)
AUTOPILOT_CHOICES = ("auto", "px4", "ardupilot")
NUMBERINGS = ("px4", "ardupilot")
ALT_TOLERANCE_M = 1e-3
FLOAT32_MAX = 3.4028234663852886e38


# ---------------------------------------------------------------- errors


class UploadError(Exception):
    """A mission transfer that did not leave the vehicle holding the mission."""


class InvalidConnectionError(UploadError, ValueError):
    """A connection URL that neither pymavlink nor MAVSDK can open."""


class NoVehicleError(UploadError):
    """No vehicle heartbeat within the connection timeout."""


class UploadTimeoutError(UploadError):
    """The vehicle stopped answering in the middle of a transfer."""


class ProtocolError(UploadError):
    """The vehicle broke the mission protocol (early ACK, bad seq, float items)."""


class MissionRejectedError(UploadError):
    """The vehicle answered with a MISSION_ACK error (a MAV_MISSION_RESULT NACK).

    ``result_name`` is the MAV_MISSION_RESULT name on the pymavlink path (e.g.
    ``MAV_MISSION_NO_SPACE``) and the ``MissionRawResult`` name on the MAVSDK path
    (e.g. ``TOO_MANY_MISSION_ITEMS``), which folds some results together.
    """

    def __init__(self, result_name: str, *, mission_type: int = MAV_MISSION_TYPE_MISSION,
                 result_code: int | None = None, detail: str = "") -> None:
        self.result_name = result_name
        self.result_code = result_code
        self.mission_type = mission_type
        kind = MISSION_TYPE_NAMES.get(mission_type, str(mission_type))
        super().__init__(f"vehicle rejected the {kind} upload: {result_name}"
                         + (f" ({detail})" if detail else ""))


class VerifyMismatchError(UploadError):
    """The items read back from the vehicle differ from the items sent."""

    def __init__(self, differences: Sequence[str], *,
                 mission_type: int = MAV_MISSION_TYPE_MISSION, hint: str = "") -> None:
        self.differences = list(differences)
        self.mission_type = mission_type
        self.hint = hint
        kind = MISSION_TYPE_NAMES.get(mission_type, str(mission_type))
        more = f" (+{len(self.differences) - 1} more)" if len(self.differences) > 1 else ""
        super().__init__(f"{kind} read back differs: {self.differences[0]}{more}"
                         + (f"; {hint}" if hint else ""))


# ---------------------------------------------------------------- wire items


@dataclass(frozen=True, kw_only=True)
class WireItem:
    """One MISSION_ITEM_INT as sent or received (x/y int degE7, z metres)."""

    seq: int
    frame: int
    command: int
    current: int
    autocontinue: int
    param1: float
    param2: float
    param3: float
    param4: float
    x: int
    y: int
    z: float
    mission_type: int = MAV_MISSION_TYPE_MISSION

    @classmethod
    def from_msg(cls, msg: Any) -> WireItem:
        """From a pymavlink MISSION_ITEM_INT or a MAVSDK MissionRaw item."""
        return cls(seq=int(msg.seq), frame=int(msg.frame), command=int(msg.command),
                   current=int(msg.current), autocontinue=int(msg.autocontinue),
                   param1=float(msg.param1), param2=float(msg.param2),
                   param3=float(msg.param3), param4=float(msg.param4),
                   x=int(msg.x), y=int(msg.y), z=float(msg.z),
                   mission_type=int(getattr(msg, "mission_type", 0)))


def to_float32(x: float) -> float:
    """The float32 the wire holds (NaN stays NaN)."""
    if math.isnan(x):
        return x
    if abs(x) > FLOAT32_MAX:
        raise ValueError(f"{x!r} does not fit a float32 mission param")
    return struct.unpack("<f", struct.pack("<f", x))[0]


def _item_to_wire(it: MissionItem, seq: int, current: bool) -> WireItem:
    return WireItem(seq=seq, frame=it.frame, command=it.command, current=int(current),
                    autocontinue=int(bool(it.autocontinue)),
                    param1=to_float32(it.param1), param2=to_float32(it.param2),
                    param3=to_float32(it.param3), param4=to_float32(it.param4),
                    x=deg_to_e7(it.lat_deg), y=deg_to_e7(it.lon_deg), z=to_float32(it.alt_m),
                    mission_type=MAV_MISSION_TYPE_MISSION)


def check_numbering(autopilot: str) -> None:
    if autopilot not in NUMBERINGS:
        raise ValueError(f"mission numbering must be one of {NUMBERINGS}, got {autopilot!r} "
                         "(resolve 'auto' with resolve_autopilot first)")


def home_to_wire(home: tuple[float, float, float]) -> WireItem:
    """ArduPilot's seq 0: the planned home as QGroundControl sends it (NAV_WAYPOINT,
    frame 0 = MAV_FRAME_GLOBAL with AMSL altitude, params 0, autocontinue 1,
    current 1: the one current item of the upload). The vehicle overwrites it."""
    lat, lon, alt = home
    return WireItem(seq=0, frame=MAV_FRAME_GLOBAL, command=MAV_CMD_NAV_WAYPOINT, current=1,
                    autocontinue=1, param1=0.0, param2=0.0, param3=0.0, param4=0.0,
                    x=deg_to_e7(lat), y=deg_to_e7(lon), z=to_float32(alt),
                    mission_type=MAV_MISSION_TYPE_MISSION)


def mission_to_wire(mission: Mission, *, autopilot: str = "px4") -> list[WireItem]:
    """The mission list as sent, with exactly one current item (seq 0).

    ``autopilot="px4"``: item ``k`` is seq ``k``. ``autopilot="ardupilot"``: seq 0 is
    :func:`home_to_wire` (the mission's planned home), item ``k`` is seq ``k + 1``
    and a DO_JUMP's target (param1) moves up by one with it."""
    check_numbering(autopilot)
    if autopilot == "px4":
        return [_item_to_wire(it, i, i == 0) for i, it in enumerate(mission.items)]
    out = [home_to_wire(mission.home)]
    for i, it in enumerate(mission.items):
        w = _item_to_wire(it, i + 1, False)
        if w.command == MAV_CMD_DO_JUMP:
            w = dataclasses.replace(w, param1=to_float32(it.param1 + 1))
        out.append(w)
    return out


def fence_to_wire(mission: Mission) -> list[WireItem]:
    """Fence items: each polygon's vertices (param1 = vertex count), then the circles."""
    out: list[WireItem] = []

    def add(command: int, p1: float, lat: float, lon: float) -> None:
        out.append(WireItem(seq=len(out), frame=MAV_FRAME_GLOBAL, command=command, current=0,
                            autocontinue=0, param1=to_float32(p1), param2=0.0, param3=0.0,
                            param4=0.0, x=deg_to_e7(lat), y=deg_to_e7(lon), z=0.0,
                            mission_type=MAV_MISSION_TYPE_FENCE))

    for poly in mission.polygons:
        cmd = (MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION if poly.inclusion
               else MAV_CMD_NAV_FENCE_POLYGON_VERTEX_EXCLUSION)
        for lat, lon in poly.vertices_deg:
            add(cmd, float(len(poly.vertices_deg)), lat, lon)
    for circle in mission.circles:
        cmd = (MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION if circle.inclusion
               else MAV_CMD_NAV_FENCE_CIRCLE_EXCLUSION)
        add(cmd, circle.radius_m, circle.lat_deg, circle.lon_deg)
    return out


def rally_to_wire(mission: Mission) -> list[WireItem]:
    """Rally points as NAV_RALLY_POINT, altitude relative to home (frame 6)."""
    return [WireItem(seq=i, frame=MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
                     command=MAV_CMD_NAV_RALLY_POINT, current=0, autocontinue=0,
                     param1=0.0, param2=0.0, param3=0.0, param4=0.0,
                     x=deg_to_e7(lat), y=deg_to_e7(lon), z=to_float32(alt),
                     mission_type=MAV_MISSION_TYPE_RALLY)
            for i, (lat, lon, alt) in enumerate(mission.rally_deg)]


def wire_to_mission(items: Sequence[WireItem], *, home: tuple[float, float, float],
                    fence: Sequence[WireItem] = (), rally: Sequence[WireItem] = (),
                    autopilot: str = "px4") -> Mission:
    """A Mission from downloaded items (``home`` is not taken from the items).

    ``autopilot="ardupilot"``: seq 0 (the vehicle's home) is dropped and DO_JUMP
    targets move down by one, the inverse of :func:`mission_to_wire`."""
    check_numbering(autopilot)
    skip = 1 if autopilot == "ardupilot" else 0
    mission_items = tuple(
        MissionItem(command=w.command, frame=w.frame, lat_deg=e7_to_deg(w.x),
                    lon_deg=e7_to_deg(w.y), alt_m=w.z,
                    param1=w.param1 - skip if w.command == MAV_CMD_DO_JUMP else w.param1,
                    param2=w.param2, param3=w.param3, param4=w.param4,
                    autocontinue=bool(w.autocontinue))
        for w in items[skip:])
    polygons, circles = wire_to_fence(fence)
    return Mission(items=mission_items, home=home, polygons=polygons, circles=circles,
                   rally_deg=tuple((e7_to_deg(w.x), e7_to_deg(w.y), w.z) for w in rally))


def wire_to_fence(fence: Sequence[WireItem]
                  ) -> tuple[tuple[FencePolygon, ...], tuple[FenceCircle, ...]]:
    """The polygons and circles of fence items (a polygon: ``param1`` vertex items in a
    row); :class:`ProtocolError` for items that do not make a fence."""
    polygons: list[FencePolygon] = []
    circles: list[FenceCircle] = []
    k = 0
    while k < len(fence):
        w = fence[k]
        if w.command in (MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION,
                         MAV_CMD_NAV_FENCE_POLYGON_VERTEX_EXCLUSION):
            n = int(w.param1)
            if n < 3 or k + n > len(fence):
                raise ProtocolError(f"fence item {k}: polygon of {n} vertices does not fit")
            verts = tuple((e7_to_deg(v.x), e7_to_deg(v.y)) for v in fence[k:k + n])
            polygons.append(FencePolygon(
                vertices_deg=verts,
                inclusion=w.command == MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION))
            k += n
        elif w.command in (MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION, MAV_CMD_NAV_FENCE_CIRCLE_EXCLUSION):
            circles.append(FenceCircle(lat_deg=e7_to_deg(w.x), lon_deg=e7_to_deg(w.y),
                                       radius_m=w.param1,
                                       inclusion=w.command == MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION))
            k += 1
        else:
            raise ProtocolError(f"fence item {k}: unexpected command {w.command}")
    return tuple(polygons), tuple(circles)


def _sameto_float32(a: float, b: float) -> bool:
    if math.isnan(a) or math.isnan(b):
        return math.isnan(a) and math.isnan(b)
    return to_float32(a) == to_float32(b)


# INT and float frames name the same reference (MAVLink common): a vehicle may answer a
# MISSION_REQUEST_INT with the float frame number (ArduPilot's AP_Mission does)
_SAME_FRAME = {MAV_FRAME_GLOBAL_INT: MAV_FRAME_GLOBAL,
               MAV_FRAME_GLOBAL_RELATIVE_ALT_INT: MAV_FRAME_GLOBAL_RELATIVE_ALT,
               MAV_FRAME_GLOBAL_TERRAIN_ALT_INT: MAV_FRAME_GLOBAL_TERRAIN_ALT}
# commands that carry no position: a vehicle may store them with frame 0 and x = y = z = 0
# (return to launch, the CONDITION_ commands, the DO_ commands up to OVERRIDE_GOTO)
_POSITIONLESS = frozenset({MAV_CMD_NAV_RETURN_TO_LAUNCH,
                           *range(MAV_CMD_CONDITION_DELAY, MAV_CMD_CONDITION_LAST + 1),
                           *range(MAV_CMD_DO_SET_MODE, MAV_CMD_OVERRIDE_GOTO + 1)})
ARDUPILOT_ALT_TOLERANCE_M = 0.01  # ArduPilot stores altitudes in whole centimetres


def _frame_class(frame: int) -> int:
    return _SAME_FRAME.get(frame, frame)


def ardupilot_stored(item: WireItem) -> WireItem:
    """``item`` as ArduPilot's AP_Mission gives it back on download
    (``mission_cmd_to_mavlink_int``): the float frame twin of an INT frame, the
    altitude in whole centimetres, commands without a position (RTL, CONDITION_*,
    DO_*) with frame 0 and x = y = z = 0. :func:`compare_wire` accepts exactly
    these changes; seq 0 (home) is the vehicle's own and not derived from the item."""
    if item.command in _POSITIONLESS:
        return dataclasses.replace(item, frame=MAV_FRAME_GLOBAL, x=0, y=0, z=0.0)
    return dataclasses.replace(item, frame=_frame_class(item.frame),
                               z=round(item.z * 100.0) / 100.0)


def compare_wire(sent: Sequence[WireItem], held: Sequence[WireItem], *,
                 skip_seq0: bool = False) -> list[str]:
    """Differences between items sent and items read back (empty = identical).

    Compares seq, frame, command, autocontinue, int x/y, params (as float32, NaN
    equal to NaN), mission_type and z within 1e-3 m. ``current`` is not compared:
    the vehicle moves its current item. ``skip_seq0`` leaves out item 0 (ArduPilot's
    home, which the vehicle rewrites) but still counts it. "item i" is seq i.

    What a vehicle may change without changing the mission is accepted: an INT frame
    read back as its float twin (6 as 3, 5 as 0, 11 as 10), and for commands without
    a position (RTL, CONDITION_*, DO_*) the frame and x/y/z. With ArduPilot numbering
    (``skip_seq0``) altitudes match within its centimetre storage.
    """
    diffs: list[str] = []
    alt_tol = max(ALT_TOLERANCE_M, ARDUPILOT_ALT_TOLERANCE_M) if skip_seq0 else ALT_TOLERANCE_M
    if len(sent) != len(held):
        diffs.append(f"vehicle holds {len(held)} items, {len(sent)} were sent")
    for i, (a, b) in enumerate(zip(sent, held, strict=False)):
        if skip_seq0 and i == 0:
            continue
        positionless = a.command in _POSITIONLESS and b.command == a.command
        for name in ("seq", "command", "autocontinue", "mission_type"):
            va, vb = getattr(a, name), getattr(b, name)
            if va != vb:
                diffs.append(f"item {i}: {name} {vb} != sent {va}")
        if positionless:
            if (b.x, b.y) not in ((a.x, a.y), (0, 0)):
                diffs.append(f"item {i}: x/y {b.x}/{b.y} != sent {a.x}/{a.y}")
        else:
            if _frame_class(a.frame) != _frame_class(b.frame):
                diffs.append(f"item {i}: frame {b.frame} != sent {a.frame}")
            for name in ("x", "y"):
                va, vb = getattr(a, name), getattr(b, name)
                if va != vb:
                    diffs.append(f"item {i}: {name} {vb} != sent {va}")
            if not (abs(a.z - b.z) <= alt_tol):
                diffs.append(f"item {i}: z {b.z!r} != sent {a.z!r}")
        for name in ("param1", "param2", "param3", "param4"):
            va, vb = getattr(a, name), getattr(b, name)
            if not _sameto_float32(va, vb):
                diffs.append(f"item {i}: {name} {vb!r} != sent {va!r}")
    return diffs
