"""The geofence: the zones in the vehicle's ENU frame and the keep-in logic (PX4 rules).

:class:`Fence` holds the zones: allowed = inside at least one inclusion zone (polygon
or circle; no inclusion zone: anywhere) and inside no exclusion zone. Altitude is not
fenced. :class:`FenceGuard` acts on it every tick: a breach is predicted on the
stopping point (GF_PREDICT) :data:`FENCE_MARGIN_M` beyond it and acted upon once per
breach (GF_ACTION: 1 a warning, 2 hold at the last stopping point that was inside, 3
return, 5 land; not in AUTO.RTL and AUTO.LAND).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

from pymavlink.dialects.v20.common import (
    MAV_SEVERITY_CRITICAL,
)

from envs.vehicle.flight import Vec3, stopping_point
from envs.vehicle.px4 import Mode
from planner.mavlink_wire import WireItem, wire_to_fence
from planner.mission import (
    MAV_CMD_NAV_FENCE_CIRCLE_EXCLUSION,
    MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION,
    MAV_CMD_NAV_FENCE_POLYGON_VERTEX_EXCLUSION,
    MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION,
    FenceCircle,
    FencePolygon,
)

if TYPE_CHECKING:
    from envs.vehicle.autopilot import Autopilot

FENCE_MARGIN_M = 1.0  # a breach is predicted this far beyond the stopping point


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


class FenceGuard:
    """The autopilot's keep-in logic (see the module docstring); ``ap`` the autopilot."""

    def __init__(self, ap: Autopilot) -> None:
        self.ap = ap
        self.fence = Fence()
        self.items: list[WireItem] = []
        self._ok = True
        self._safe_stop: Vec3 | None = None

    def set_items(self, items: Sequence[WireItem]) -> None:
        """A complete, validated fence upload (horizontal zones at home's height)."""
        ap = self.ap
        self.items = list(items)

        def to_en(lat: float, lon: float) -> tuple[float, float]:
            e, n, _ = ap.frame.to_enu(lat, lon, ap.home.alt_m)
            return float(e), float(n)

        self.fence = fence_from_items(items, to_en)
        self._ok = True
        self._safe_stop = None

    def allows(self, p: Vec3) -> bool:
        """May the vehicle be at ``p`` (arming)?"""
        return self.fence.empty or self.fence.allows(p[0], p[1])

    def check(self, p: Vec3, v: Vec3) -> bool:
        """Edge-triggered geofence action (True when it fired)."""
        ap = self.ap
        if self.fence.empty or ap.mode in (Mode.RTL, Mode.LAND):
            return False
        lim = ap.limits
        point = stopping_point(p, v, lim) if ap.params["GF_PREDICT"] else p
        sh = math.hypot(v[0], v[1])
        m = FENCE_MARGIN_M / sh if sh > 0.1 else 0.0  # look a margin beyond the stop
        ok = self.fence.allows(point[0] + v[0] * m, point[1] + v[1] * m)
        if ok:
            self._ok = True
            self._safe_stop = point
            return False
        if not self._ok:
            return False
        self._ok = False
        action = int(ap.params["GF_ACTION"])
        ap.text(MAV_SEVERITY_CRITICAL, "geofence breached" + (" (predicted)" if point != p else ""))
        if action == 2:
            ap.modes.enter(Mode.LOITER)
            ap.hold_here(self._safe_stop or p)
        elif action == 3:
            ap.modes.enter(Mode.RTL)
        elif action == 5:
            ap.modes.enter(Mode.LAND)
        return action >= 2
