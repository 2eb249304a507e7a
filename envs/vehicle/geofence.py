"""The uploaded geofence in the vehicle's ENU frame, checked horizontally (PX4 rules).

Allowed = inside at least one inclusion zone (polygon or circle; no inclusion zone:
anywhere) and inside no exclusion zone. Altitude is not fenced.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from planner.mavlink_wire import WireItem, wire_to_fence
from planner.mission import (
    MAV_CMD_NAV_FENCE_CIRCLE_EXCLUSION,
    MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION,
    MAV_CMD_NAV_FENCE_POLYGON_VERTEX_EXCLUSION,
    MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION,
    FenceCircle,
    FencePolygon,
)


def _inside_polygon(x: float, y: float, poly: Sequence[tuple[float, float]]) -> bool:
    inside = False
    n = len(poly)
    xj, yj = poly[-1]
    for k in range(n):
        xi, yi = poly[k]
        if (yi > y) != (yj > y) and x < (xj - xi) * (y - yi) / (yj - yi) + xi:
            inside = not inside
        xj, yj = xi, yi
    return inside


@dataclass(frozen=True)
class Fence:
    """Zones in ENU metres: polygons as vertex tuples, circles as (e, n, radius)."""

    inclusion_polygons: tuple[tuple[tuple[float, float], ...], ...] = ()
    exclusion_polygons: tuple[tuple[tuple[float, float], ...], ...] = ()
    inclusion_circles: tuple[tuple[float, float, float], ...] = ()
    exclusion_circles: tuple[tuple[float, float, float], ...] = ()

    @property
    def empty(self) -> bool:
        return not (self.inclusion_polygons or self.exclusion_polygons
                    or self.inclusion_circles or self.exclusion_circles)

    def allows(self, e: float, n: float) -> bool:
        """Is (e, n) inside the fence?"""
        if self.inclusion_polygons or self.inclusion_circles:
            ok = any(_inside_polygon(e, n, p) for p in self.inclusion_polygons) or any(
                math.hypot(e - ce, n - cn) <= r for ce, cn, r in self.inclusion_circles)
            if not ok:
                return False
        if any(_inside_polygon(e, n, p) for p in self.exclusion_polygons):
            return False
        return not any(math.hypot(e - ce, n - cn) < r for ce, cn, r in self.exclusion_circles)


def fence_from_items(items: Sequence[WireItem],
                     to_en: Callable[[float, float], tuple[float, float]]) -> Fence:
    """A :class:`Fence` from validated fence items (``to_en(lat, lon)`` -> (e, n))."""
    polygons, circles = wire_to_fence(items)

    def poly(p: FencePolygon) -> tuple[tuple[float, float], ...]:
        return tuple(to_en(lat, lon) for lat, lon in p.vertices_deg)

    def circle(c: FenceCircle) -> tuple[float, float, float]:
        return (*to_en(c.lat_deg, c.lon_deg), float(c.radius_m))

    return Fence(tuple(poly(p) for p in polygons if p.inclusion),
                 tuple(poly(p) for p in polygons if not p.inclusion),
                 tuple(circle(c) for c in circles if c.inclusion),
                 tuple(circle(c) for c in circles if not c.inclusion))


FENCE_COMMANDS = (MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION,
                  MAV_CMD_NAV_FENCE_POLYGON_VERTEX_EXCLUSION,
                  MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION, MAV_CMD_NAV_FENCE_CIRCLE_EXCLUSION)
