"""Mission data types: what the planner exports and what a MAVLink vehicle holds.

Items are MAVLink mission items in the ``_INT`` form (docs/mavlink.md):
latitude and longitude are kept in degrees here and converted to int degE7 with
:func:`deg_to_e7` (round half away from zero, as MAVSDK does) on the wire and in
comparisons. The default frame is MAV_FRAME_GLOBAL_RELATIVE_ALT_INT (6): altitude
above home.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

# the MAVLink constants the planner uses: pymavlink's common dialect, the one definition
# (importing the dialect module directly is safe whatever MAVLINK20 says: planner/mavlink.py)
from pymavlink.dialects.v20.common import (
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

__all__ = [
    "MAV_CMD_DO_CHANGE_SPEED",
    "MAV_CMD_DO_JUMP",
    "MAV_CMD_NAV_FENCE_CIRCLE_EXCLUSION",
    "MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION",
    "MAV_CMD_NAV_FENCE_POLYGON_VERTEX_EXCLUSION",
    "MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION",
    "MAV_CMD_NAV_LAND",
    "MAV_CMD_NAV_RALLY_POINT",
    "MAV_CMD_NAV_RETURN_TO_LAUNCH",
    "MAV_CMD_NAV_TAKEOFF",
    "MAV_CMD_NAV_WAYPOINT",
    "MAV_FRAME_GLOBAL",
    "MAV_FRAME_GLOBAL_INT",
    "MAV_FRAME_GLOBAL_RELATIVE_ALT",
    "MAV_FRAME_GLOBAL_RELATIVE_ALT_INT",
    "MAV_FRAME_GLOBAL_TERRAIN_ALT",
    "MAV_FRAME_GLOBAL_TERRAIN_ALT_INT",
    "MAV_MISSION_TYPE_FENCE",
    "MAV_MISSION_TYPE_MISSION",
    "MAV_MISSION_TYPE_RALLY",
    "FenceCircle",
    "FencePolygon",
    "Mission",
    "MissionItem",
    "deg_to_e7",
    "e7_to_deg",
]


def deg_to_e7(deg: float) -> int:
    """Degrees to int degE7, rounded half away from zero (MAVSDK's convention)."""
    if not math.isfinite(deg):
        raise ValueError(f"non-finite coordinate {deg!r}")
    v = math.floor(abs(deg) * 1e7 + 0.5)
    return int(math.copysign(v, deg)) if v else 0


def e7_to_deg(v: int) -> float:
    return v / 1e7


@dataclass(frozen=True, kw_only=True)
class MissionItem:
    """One mission item (MISSION_ITEM_INT fields; lat/lon in degrees, alt in metres)."""

    command: int = MAV_CMD_NAV_WAYPOINT
    frame: int = MAV_FRAME_GLOBAL_RELATIVE_ALT_INT
    lat_deg: float = 0.0
    lon_deg: float = 0.0
    alt_m: float = 0.0
    param1: float = 0.0  # NAV_WAYPOINT: hold time (s)
    param2: float = 0.0  # acceptance radius (m)
    param3: float = 0.0  # pass radius (m)
    param4: float = math.nan  # yaw (deg); NaN = unchanged
    autocontinue: bool = True

    @property
    def x_e7(self) -> int:
        return deg_to_e7(self.lat_deg)

    @property
    def y_e7(self) -> int:
        return deg_to_e7(self.lon_deg)


@dataclass(frozen=True, kw_only=True)
class FencePolygon:
    """A geofence polygon: vertices (lat_deg, lon_deg); inclusion (keep-in) or exclusion."""

    vertices_deg: tuple[tuple[float, float], ...]
    inclusion: bool = True


@dataclass(frozen=True, kw_only=True)
class FenceCircle:
    """A geofence circle (centre lat/lon in degrees, radius in metres)."""

    lat_deg: float
    lon_deg: float
    radius_m: float
    inclusion: bool = False


@dataclass(frozen=True, kw_only=True)
class Mission:
    """A mission: items (seq = index), planned home (lat, lon, alt), fence, rally.

    The home altitude is in the datum the vehicle reports (we carry no geoid model:
    ``osa plan --home LAT,LON,ALT`` writes ALT unchanged); items in frame 6 are relative
    to home, so they do not depend on it.

    The current item on upload is item 0 (exactly one ``current=1``).
    """

    items: tuple[MissionItem, ...]
    home: tuple[float, float, float]
    polygons: tuple[FencePolygon, ...] = ()
    circles: tuple[FenceCircle, ...] = ()
    rally_deg: tuple[tuple[float, float, float], ...] = ()
    cruise_speed_m_s: float = 10.0
    hover_speed_m_s: float = 5.0
    vehicle_type: str = "multirotor"
    firmware: str = "px4"
    name: str = ""
    meta: dict = field(default_factory=dict, compare=False, hash=False)
