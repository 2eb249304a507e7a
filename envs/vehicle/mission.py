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

from pymavlink.dialects.v20.common import (
    MAV_CMD_CONDITION_YAW,
    MAV_CMD_DO_CONTROL_VIDEO,
    MAV_CMD_DO_DIGICAM_CONTROL,
    MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE,
    MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW,
    MAV_CMD_DO_GRIPPER,
    MAV_CMD_DO_LAND_START,
    MAV_CMD_DO_MOUNT_CONFIGURE,
    MAV_CMD_DO_MOUNT_CONTROL,
    MAV_CMD_DO_SET_ACTUATOR,
    MAV_CMD_DO_SET_CAM_TRIGG_DIST,
    MAV_CMD_DO_SET_CAM_TRIGG_INTERVAL,
    MAV_CMD_DO_SET_ROI,
    MAV_CMD_DO_SET_ROI_LOCATION,
    MAV_CMD_DO_SET_ROI_NONE,
    MAV_CMD_DO_SET_ROI_WPNEXT_OFFSET,
    MAV_CMD_DO_SET_SERVO,
    MAV_CMD_DO_TRIGGER_CONTROL,
    MAV_CMD_DO_WINCH,
    MAV_CMD_IMAGE_START_CAPTURE,
    MAV_CMD_IMAGE_STOP_CAPTURE,
    MAV_CMD_NAV_DELAY,
    MAV_CMD_NAV_LOITER_TIME,
    MAV_CMD_NAV_LOITER_TURNS,
    MAV_CMD_NAV_LOITER_UNLIM,
    MAV_CMD_NAV_ROI,
    MAV_CMD_OBLIQUE_SURVEY,
    MAV_CMD_SET_CAMERA_FOCUS,
    MAV_CMD_SET_CAMERA_MODE,
    MAV_CMD_SET_CAMERA_ZOOM,
    MAV_CMD_VIDEO_START_CAPTURE,
    MAV_CMD_VIDEO_STOP_CAPTURE,
    MAV_MISSION_ACCEPTED,
    MAV_MISSION_ERROR,
    MAV_MISSION_INVALID_PARAM1,
    MAV_MISSION_INVALID_PARAM2,
    MAV_MISSION_INVALID_PARAM5_X,
    MAV_MISSION_INVALID_PARAM6_Y,
    MAV_MISSION_INVALID_PARAM7,
    MAV_MISSION_UNSUPPORTED,
    MAV_MISSION_UNSUPPORTED_FRAME,
)

from planner.mavlink_wire import WireItem
from planner.mission import (
    MAV_CMD_DO_CHANGE_SPEED,
    MAV_CMD_DO_JUMP,
    MAV_CMD_NAV_FENCE_CIRCLE_EXCLUSION,
    MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION,
    MAV_CMD_NAV_FENCE_POLYGON_VERTEX_EXCLUSION,
    MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION,
    MAV_CMD_NAV_LAND,
    MAV_CMD_NAV_RALLY_POINT,
    MAV_CMD_NAV_RETURN_TO_LAUNCH,
    MAV_CMD_NAV_TAKEOFF,
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
)

NAV_COMMANDS = frozenset({MAV_CMD_NAV_WAYPOINT, MAV_CMD_NAV_LOITER_UNLIM, MAV_CMD_NAV_LOITER_TURNS,
                          MAV_CMD_NAV_LOITER_TIME, MAV_CMD_NAV_RETURN_TO_LAUNCH,
                          MAV_CMD_NAV_LAND, MAV_CMD_NAV_TAKEOFF})
# flown without a position of their own
TIMED_COMMANDS = frozenset({MAV_CMD_NAV_DELAY})
# DO_ commands that change the flight
DO_COMMANDS = frozenset({MAV_CMD_DO_JUMP, MAV_CMD_DO_CHANGE_SPEED})
# payload commands stored and passed over without effect (camera, gimbal, servo, ROI,
# winch, gripper; the landing marker DO_LAND_START): every such command PX4's mission
# takes (mavlink_mission.cpp), so a QGroundControl plan with them is not refused
IGNORED_COMMANDS = frozenset({
    MAV_CMD_CONDITION_YAW, MAV_CMD_DO_SET_SERVO, MAV_CMD_DO_SET_ROI_LOCATION,
    MAV_CMD_DO_SET_ROI_NONE, MAV_CMD_DO_SET_ROI, MAV_CMD_DO_DIGICAM_CONTROL,
    MAV_CMD_DO_MOUNT_CONTROL, MAV_CMD_DO_SET_CAM_TRIGG_DIST, MAV_CMD_DO_SET_CAM_TRIGG_INTERVAL,
    MAV_CMD_SET_CAMERA_MODE, MAV_CMD_SET_CAMERA_ZOOM, MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW,
    MAV_CMD_IMAGE_START_CAPTURE, MAV_CMD_IMAGE_STOP_CAPTURE, MAV_CMD_VIDEO_START_CAPTURE,
    MAV_CMD_VIDEO_STOP_CAPTURE, MAV_CMD_NAV_ROI, MAV_CMD_DO_SET_ROI_WPNEXT_OFFSET,
    MAV_CMD_DO_MOUNT_CONFIGURE, MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE, MAV_CMD_SET_CAMERA_FOCUS,
    MAV_CMD_DO_CONTROL_VIDEO, MAV_CMD_DO_TRIGGER_CONTROL, MAV_CMD_OBLIQUE_SURVEY,
    MAV_CMD_DO_WINCH, MAV_CMD_DO_GRIPPER, MAV_CMD_DO_SET_ACTUATOR, MAV_CMD_DO_LAND_START})
MISSION_COMMANDS = NAV_COMMANDS | TIMED_COMMANDS | DO_COMMANDS | IGNORED_COMMANDS
# frames of a positioned item: global absolute (0, 5), relative to home (3, 6), above
# terrain (10, 11); position-less items (DO_, NAV_DELAY, RTL) take any frame, as PX4
ABSOLUTE_FRAMES = frozenset({MAV_FRAME_GLOBAL, MAV_FRAME_GLOBAL_INT})
RELATIVE_FRAMES = frozenset({MAV_FRAME_GLOBAL_RELATIVE_ALT, MAV_FRAME_GLOBAL_RELATIVE_ALT_INT})
TERRAIN_FRAMES = frozenset({MAV_FRAME_GLOBAL_TERRAIN_ALT, MAV_FRAME_GLOBAL_TERRAIN_ALT_INT})
GLOBAL_FRAMES = ABSOLUTE_FRAMES | RELATIVE_FRAMES | TERRAIN_FRAMES
POSITIONLESS = frozenset({MAV_CMD_NAV_RETURN_TO_LAUNCH}) | TIMED_COMMANDS | DO_COMMANDS \
    | IGNORED_COMMANDS

FENCE_VERTEX = (MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION,
                MAV_CMD_NAV_FENCE_POLYGON_VERTEX_EXCLUSION)
FENCE_CIRCLE = (MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION, MAV_CMD_NAV_FENCE_CIRCLE_EXCLUSION)

MAX_ALTITUDE_M = 10_000.0  # |altitude| of a positioned item or command, at most
# x or y INT32_MAX: "not set" (MAVLink: INT32_MAX in an integer param is the NaN of a
# float one; a float MISSION_ITEM's NaN is stored so); x = y = 0 too (older senders)
UNSET_E7 = 2**31 - 1
INT32_MIN = -(2**31)


def has_position(w: WireItem) -> bool:
    """Whether an item carries a latitude and longitude (else: where the vehicle is)."""
    return not ((w.x == 0 and w.y == 0) or w.x == UNSET_E7 or w.y == UNSET_E7)

# storage sizes (PX4's dataman on a Pixhawk 6: 2000 items, 64 fence vertices... raised a
# little for fences: a keep-in polygon and some keep-out circles)
CAPACITY = {MAV_MISSION_TYPE_MISSION: 2000, MAV_MISSION_TYPE_FENCE: 256,
            MAV_MISSION_TYPE_RALLY: 16}


def _check_position(w: WireItem, *, unset_ok: bool = False) -> int:
    """``unset_ok``: x = y = INT32_MAX ("not set": where the vehicle is) is taken; only a
    mission item can mean that (a fence vertex, a fence circle's centre or a rally
    point without a position has none: INVALID_PARAM5_X, as any latitude beyond 90)."""
    if w.frame not in GLOBAL_FRAMES:
        return MAV_MISSION_UNSUPPORTED_FRAME
    unset = unset_ok and w.x == UNSET_E7 and w.y == UNSET_E7  # no position: here
    if not unset and not -900_000_000 <= w.x <= 900_000_000:
        return MAV_MISSION_INVALID_PARAM5_X
    if not unset and not -1_800_000_000 <= w.y <= 1_800_000_000:
        return MAV_MISSION_INVALID_PARAM6_Y
    if not math.isfinite(w.z) or abs(w.z) > MAX_ALTITUDE_M:
        return MAV_MISSION_INVALID_PARAM7
    return MAV_MISSION_ACCEPTED


def check_item(w: WireItem, count: int) -> int:
    """MAV_MISSION_RESULT of one uploaded item of a list of ``count`` (0 = accepted)."""
    # storage is MISSION_ITEM_INT's: a float MISSION_ITEM's x or y beyond int32 degE7
    # (214.7 degrees), whatever the command, could never be sent back
    if not INT32_MIN <= w.x <= UNSET_E7:
        return MAV_MISSION_INVALID_PARAM5_X
    if not INT32_MIN <= w.y <= UNSET_E7:
        return MAV_MISSION_INVALID_PARAM6_Y
    if w.mission_type == MAV_MISSION_TYPE_MISSION:
        if w.command not in MISSION_COMMANDS:
            return MAV_MISSION_UNSUPPORTED
        if w.command == MAV_CMD_DO_JUMP:
            target = w.param1
            if not math.isfinite(target) or target != int(target) or not 0 <= target < count \
                    or int(target) == w.seq:
                return MAV_MISSION_INVALID_PARAM1
            if not math.isfinite(w.param2) or w.param2 != int(w.param2):
                return MAV_MISSION_INVALID_PARAM2
            return MAV_MISSION_ACCEPTED
        if w.command in (MAV_CMD_NAV_LOITER_TIME, MAV_CMD_NAV_DELAY, MAV_CMD_NAV_LOITER_TURNS) \
                and (not math.isfinite(w.param1) or w.param1 < 0):
            return MAV_MISSION_INVALID_PARAM1
        if w.command == MAV_CMD_NAV_WAYPOINT and (not math.isfinite(w.param1) or w.param1 < 0):
            return MAV_MISSION_INVALID_PARAM1
        if w.command in POSITIONLESS:
            return MAV_MISSION_ACCEPTED
        return _check_position(w, unset_ok=True)
    if w.mission_type == MAV_MISSION_TYPE_FENCE:
        if w.command in FENCE_VERTEX:
            n = w.param1
            if not math.isfinite(n) or n != int(n) or n < 3:
                return MAV_MISSION_INVALID_PARAM1
        elif w.command in FENCE_CIRCLE:
            if not math.isfinite(w.param1) or w.param1 <= 0:
                return MAV_MISSION_INVALID_PARAM1
        else:
            return MAV_MISSION_UNSUPPORTED
        return _check_position(w) if w.frame in GLOBAL_FRAMES else MAV_MISSION_UNSUPPORTED_FRAME
    if w.mission_type == MAV_MISSION_TYPE_RALLY:
        if w.command != MAV_CMD_NAV_RALLY_POINT:
            return MAV_MISSION_UNSUPPORTED
        return _check_position(w)  # (above the terrain too: it can be flown)
    return MAV_MISSION_ERROR


def check_list(items: Sequence[WireItem], mission_type: int) -> int:
    """MAV_MISSION_RESULT of a complete list (fence polygons must be whole)."""
    if mission_type != MAV_MISSION_TYPE_FENCE:
        return MAV_MISSION_ACCEPTED
    k = 0
    while k < len(items):
        w = items[k]
        if w.command in FENCE_VERTEX:
            n = int(w.param1)
            group = items[k:k + n]
            if len(group) != n or any(v.command != w.command or int(v.param1) != n
                                      for v in group):
                return MAV_MISSION_INVALID_PARAM1
            k += n
        else:
            k += 1
    return MAV_MISSION_ACCEPTED
