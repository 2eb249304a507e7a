"""The uploaded geofence in the vehicle's ENU frame, checked horizontally (PX4 rules).

Allowed = inside at least one inclusion zone (polygon or circle; no inclusion zone:
anywhere) and inside no exclusion zone. Altitude is not fenced.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from planner.mavlink import WireItem
from planner.mission import (
    MAV_CMD_NAV_FENCE_CIRCLE_EXCLUSION,
    MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION,
    MAV_CMD_NAV_FENCE_POLYGON_VERTEX_EXCLUSION,
    MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION,
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
    inc_p: list[tuple[tuple[float, float], ...]] = []
    exc_p: list[tuple[tuple[float, float], ...]] = []
    inc_c: list[tuple[float, float, float]] = []
    exc_c: list[tuple[float, float, float]] = []
    k = 0
    while k < len(items):
        w = items[k]
        if w.command in (MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION,
                         MAV_CMD_NAV_FENCE_POLYGON_VERTEX_EXCLUSION):
            m = int(w.param1)
            poly = tuple(to_en(v.x / 1e7, v.y / 1e7) for v in items[k:k + m])
            (inc_p if w.command == MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION
             else exc_p).append(poly)
            k += m
            continue
        e, n = to_en(w.x / 1e7, w.y / 1e7)
        (inc_c if w.command == MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION else exc_c).append(
            (e, n, float(w.param1)))
        k += 1
    return Fence(tuple(inc_p), tuple(exc_p), tuple(inc_c), tuple(exc_c))


FENCE_COMMANDS = (MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION,
                  MAV_CMD_NAV_FENCE_POLYGON_VERTEX_EXCLUSION,
                  MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION, MAV_CMD_NAV_FENCE_CIRCLE_EXCLUSION)
