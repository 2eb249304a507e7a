"""What the vehicle accepts into its mission, fence and rally storage, and why not.

Each uploaded item is checked as it arrives (:func:`check_item`) and each complete
list once more (:func:`check_list`); the first failure is the MAV_MISSION_RESULT of
the MISSION_ACK that ends the transfer, and the previous list stays in force.
Storage is as sent (PX4 keeps the frame of a navigation item; the read-back of
:func:`planner.mavlink.compare_wire` is exact).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from planner.mavlink_wire import WireItem
from planner.mission import (
    MAV_CMD_DO_CHANGE_SPEED,
    MAV_CMD_NAV_FENCE_CIRCLE_EXCLUSION,
    MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION,
    MAV_CMD_NAV_FENCE_POLYGON_VERTEX_EXCLUSION,
    MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION,
    MAV_CMD_NAV_LAND,
    MAV_CMD_NAV_RALLY_POINT,
    MAV_CMD_NAV_RETURN_TO_LAUNCH,
    MAV_CMD_NAV_TAKEOFF,
    MAV_CMD_NAV_WAYPOINT,
    MAV_MISSION_TYPE_FENCE,
    MAV_MISSION_TYPE_MISSION,
    MAV_MISSION_TYPE_RALLY,
)

MAV_CMD_NAV_LOITER_UNLIM = 17
MAV_CMD_NAV_LOITER_TURNS = 18
MAV_CMD_NAV_LOITER_TIME = 19
MAV_CMD_NAV_DELAY = 93
MAV_CMD_DO_JUMP = 177

# MAV_MISSION_RESULT
MISSION_ACCEPTED = 0
MISSION_ERROR = 1
MISSION_UNSUPPORTED_FRAME = 2
MISSION_UNSUPPORTED = 3
MISSION_NO_SPACE = 4
MISSION_INVALID = 5
MISSION_INVALID_PARAM1 = 6
MISSION_INVALID_PARAM2 = 7
MISSION_INVALID_PARAM5_X = 10
MISSION_INVALID_PARAM6_Y = 11
MISSION_INVALID_PARAM7 = 12
MISSION_INVALID_SEQUENCE = 13
MISSION_DENIED = 14
MISSION_OPERATION_CANCELLED = 15

NAV_COMMANDS = frozenset({MAV_CMD_NAV_WAYPOINT, MAV_CMD_NAV_LOITER_UNLIM, MAV_CMD_NAV_LOITER_TURNS,
                          MAV_CMD_NAV_LOITER_TIME, MAV_CMD_NAV_RETURN_TO_LAUNCH,
                          MAV_CMD_NAV_LAND, MAV_CMD_NAV_TAKEOFF})
# flown without a position of their own
TIMED_COMMANDS = frozenset({MAV_CMD_NAV_DELAY})
# DO_ commands that change the flight
DO_COMMANDS = frozenset({MAV_CMD_DO_JUMP, MAV_CMD_DO_CHANGE_SPEED})
# payload commands stored and passed over without effect (camera, gimbal, servo)
IGNORED_COMMANDS = frozenset({115, 183, 195, 197, 201, 203, 205, 206, 214, 530, 531, 1000,
                              2000, 2001, 2500, 2501})
MISSION_COMMANDS = NAV_COMMANDS | TIMED_COMMANDS | DO_COMMANDS | IGNORED_COMMANDS
# frames of a positioned item: global absolute (0, 5), relative to home (3, 6), above
# terrain (10, 11); position-less items (DO_, NAV_DELAY, RTL) take any frame, as PX4
ABSOLUTE_FRAMES = frozenset({0, 5})
RELATIVE_FRAMES = frozenset({3, 6})
TERRAIN_FRAMES = frozenset({10, 11})
GLOBAL_FRAMES = ABSOLUTE_FRAMES | RELATIVE_FRAMES | TERRAIN_FRAMES
POSITIONLESS = frozenset({MAV_CMD_NAV_RETURN_TO_LAUNCH}) | TIMED_COMMANDS | DO_COMMANDS \
    | IGNORED_COMMANDS

FENCE_VERTEX = (MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION,
                MAV_CMD_NAV_FENCE_POLYGON_VERTEX_EXCLUSION)
FENCE_CIRCLE = (MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION, MAV_CMD_NAV_FENCE_CIRCLE_EXCLUSION)

# storage sizes (PX4's dataman on a Pixhawk 6: 2000 items, 64 fence vertices... raised a
# little for fences: a keep-in polygon and some keep-out circles)
CAPACITY = {MAV_MISSION_TYPE_MISSION: 2000, MAV_MISSION_TYPE_FENCE: 256,
            MAV_MISSION_TYPE_RALLY: 16}


def result_name(code: int) -> str:
    names = {0: "ACCEPTED", 1: "ERROR", 2: "UNSUPPORTED_FRAME", 3: "UNSUPPORTED",
             4: "NO_SPACE", 5: "INVALID", 6: "INVALID_PARAM1", 7: "INVALID_PARAM2",
             8: "INVALID_PARAM3", 9: "INVALID_PARAM4", 10: "INVALID_PARAM5_X",
             11: "INVALID_PARAM6_Y", 12: "INVALID_PARAM7", 13: "INVALID_SEQUENCE",
             14: "DENIED", 15: "OPERATION_CANCELLED"}
    return "MAV_MISSION_" + names.get(code, str(code))


def _check_position(w: WireItem) -> int:
    if w.frame not in GLOBAL_FRAMES:
        return MISSION_UNSUPPORTED_FRAME
    if not -900_000_000 <= w.x <= 900_000_000:
        return MISSION_INVALID_PARAM5_X
    if not -1_800_000_000 <= w.y <= 1_800_000_000:
        return MISSION_INVALID_PARAM6_Y
    if not math.isfinite(w.z) or abs(w.z) > 10_000.0:
        return MISSION_INVALID_PARAM7
    return MISSION_ACCEPTED


def check_item(w: WireItem, count: int) -> int:
    """MAV_MISSION_RESULT of one uploaded item of a list of ``count`` (0 = accepted)."""
    if w.mission_type == MAV_MISSION_TYPE_MISSION:
        if w.command not in MISSION_COMMANDS:
            return MISSION_UNSUPPORTED
        if w.command == MAV_CMD_DO_JUMP:
            target = w.param1
            if not math.isfinite(target) or target != int(target) or not 0 <= target < count \
                    or int(target) == w.seq:
                return MISSION_INVALID_PARAM1
            if not math.isfinite(w.param2) or w.param2 != int(w.param2):
                return MISSION_INVALID_PARAM2
            return MISSION_ACCEPTED
        if w.command in (MAV_CMD_NAV_LOITER_TIME, MAV_CMD_NAV_DELAY, MAV_CMD_NAV_LOITER_TURNS) \
                and (not math.isfinite(w.param1) or w.param1 < 0):
            return MISSION_INVALID_PARAM1
        if w.command == MAV_CMD_NAV_WAYPOINT and (not math.isfinite(w.param1) or w.param1 < 0):
            return MISSION_INVALID_PARAM1
        if w.command in POSITIONLESS:
            return MISSION_ACCEPTED
        return _check_position(w)
    if w.mission_type == MAV_MISSION_TYPE_FENCE:
        if w.command in FENCE_VERTEX:
            n = w.param1
            if not math.isfinite(n) or n != int(n) or n < 3:
                return MISSION_INVALID_PARAM1
        elif w.command in FENCE_CIRCLE:
            if not math.isfinite(w.param1) or w.param1 <= 0:
                return MISSION_INVALID_PARAM1
        else:
            return MISSION_UNSUPPORTED
        return _check_position(w) if w.frame in GLOBAL_FRAMES else MISSION_UNSUPPORTED_FRAME
    if w.mission_type == MAV_MISSION_TYPE_RALLY:
        if w.command != MAV_CMD_NAV_RALLY_POINT:
            return MISSION_UNSUPPORTED
        if w.frame in TERRAIN_FRAMES:
            return MISSION_UNSUPPORTED_FRAME
        return _check_position(w)
    return MISSION_ERROR


def check_list(items: Sequence[WireItem], mission_type: int) -> int:
    """MAV_MISSION_RESULT of a complete list (fence polygons must be whole)."""
    if mission_type != MAV_MISSION_TYPE_FENCE:
        return MISSION_ACCEPTED
    k = 0
    while k < len(items):
        w = items[k]
        if w.command in FENCE_VERTEX:
            n = int(w.param1)
            group = items[k:k + n]
            if len(group) != n or any(v.command != w.command or int(v.param1) != n
                                      for v in group):
                return MISSION_INVALID_PARAM1
            k += n
        else:
            k += 1
    return MISSION_ACCEPTED
