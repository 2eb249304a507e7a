"""The geofence: the zones in the vehicle's ENU frame and the keep-in logic (PX4 rules).

:class:`Fence` holds the zones: allowed = inside at least one inclusion zone (polygon
or circle; no inclusion zone: anywhere) and inside no exclusion zone. The uploaded zones
(MAVLink fence items) are horizontal: altitude is not fenced. Keep-outs preloaded at
start (the scenario's :class:`sim.scenario.KeepOutZone`: a polygon or a circle in world
ENU metres, with an optional top, its height above the ground: a keep-out may be flown
over above its top, one without a top never) are exclusion zones too, kept across fence
uploads (:meth:`Fence.with_keepouts`; ``Autopilot(..., keepouts=...)``).

:class:`FenceGuard` acts on the fence every tick: a breach is predicted on the stopping
point (GF_PREDICT) :data:`FENCE_MARGIN_M` beyond it (and, for a keep-out's top, that
much below it) and acted upon once per breach (GF_ACTION: 0 nothing, 1 a warning, 2
hold at the last stopping point that was allowed, 3 return, 5 land). The uploaded zones
are not enforced in AUTO.RTL and AUTO.LAND (PX4); the keep-outs are: a return or a
landing that would enter one holds at its last allowed stopping point instead (GF_ACTION
2, 3 and 5), so with an action the vehicle never enters a keep-out below its top, as
far as its navigation estimate knows (draw keep-outs with the navigation error as a
margin).
"""

from __future__ import annotations

import dataclasses
import functools
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
from sim.scenario import KeepOutZone

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
    """Zones in ENU metres: polygons as vertex tuples, circles as (e, n, radius), and
    the preloaded keep-outs."""

    inclusion_polygons: tuple[tuple[tuple[float, float], ...], ...] = ()
    exclusion_polygons: tuple[tuple[tuple[float, float], ...], ...] = ()
    inclusion_circles: tuple[tuple[float, float, float], ...] = ()
    exclusion_circles: tuple[tuple[float, float, float], ...] = ()
    keepouts: tuple[KeepOutZone, ...] = ()

    @property
    def empty(self) -> bool:
        return not (self.inclusion_polygons or self.exclusion_polygons
                    or self.inclusion_circles or self.exclusion_circles or self.keepouts)

    def with_keepouts(self, zones: Sequence[KeepOutZone]) -> Fence:
        """This fence and the keep-outs ``zones`` too."""
        return dataclasses.replace(self, keepouts=(*self.keepouts, *zones))

    def keepout_at(self, e: float, n: float, ground_m: Callable[[float, float], float],
                   z: float, margin_m: float = 0.0) -> KeepOutZone | None:
        """The keep-out that a point at ENU height ``z`` over (e, n) is in (below its top
        plus ``margin_m``; ``ground_m(e, n)`` the ground), or None."""
        for k, (e0, e1, n0, n1) in zip(self.keepouts, self._keepout_boxes, strict=True):
            if e0 <= e <= e1 and n0 <= n <= n1 and k.contains(e, n) \
                    and (k.top_m is None or z - ground_m(e, n) < k.top_m + margin_m):
                return k
        return None

    @functools.cached_property
    def _keepout_boxes(self) -> tuple[tuple[float, float, float, float], ...]:
        """(e_min, e_max, n_min, n_max) of each keep-out: most points are far from all."""
        out = []
        for k in self.keepouts:
            if k.center_enu_m is not None:
                (ce, cn), r = k.center_enu_m, float(k.radius_m or 0.0)
                out.append((ce - r, ce + r, cn - r, cn + r))
            else:
                es, ns = zip(*k.polygon_enu_m, strict=True)
                out.append((min(es), max(es), min(ns), max(ns)))
        return tuple(out)

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
    """The autopilot's keep-in logic (see the module docstring); ``ap`` the autopilot,
    ``keepouts`` preloaded for good (fence uploads add to them)."""

    def __init__(self, ap: Autopilot, keepouts: Sequence[KeepOutZone] = ()) -> None:
        self.ap = ap
        self.keepouts = tuple(keepouts)
        self.fence = Fence(keepouts=self.keepouts)
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

        self.fence = fence_from_items(items, to_en).with_keepouts(self.keepouts)
        self._ok = True
        self._safe_stop = None

    def allows(self, p: Vec3) -> bool:
        """May the vehicle be at ``p`` (arming)?"""
        f = self.fence
        return f.empty or (f.allows(p[0], p[1])
                           and f.keepout_at(p[0], p[1], self.ap.ground_m, p[2]) is None)

    def check(self, p: Vec3, v: Vec3) -> bool:
        """Edge-triggered geofence action (True when it fired)."""
        ap = self.ap
        f = self.fence
        zones = ap.mode not in (Mode.RTL, Mode.LAND)  # the uploaded zones: not there (PX4)
        if f.empty or not (zones or f.keepouts):
            return False
        lim = ap.limits
        point = stopping_point(p, v, lim) if ap.params["GF_PREDICT"] else p
        sh = math.hypot(v[0], v[1])
        m = FENCE_MARGIN_M / sh if sh > 0.1 else 0.0  # look a margin beyond the stop
        qe, qn = point[0] + v[0] * m, point[1] + v[1] * m
        ok = not zones or f.allows(qe, qn)
        keepout = ok and bool(f.keepouts) \
            and f.keepout_at(qe, qn, ap.ground_m, point[2], FENCE_MARGIN_M) is not None
        if ok and not keepout:
            self._ok = True
            self._safe_stop = point
            return False
        if not self._ok:
            return False
        self._ok = False
        action = int(ap.params["GF_ACTION"])
        what = "keep-out ahead" if keepout else "geofence breached"
        ap.text(MAV_SEVERITY_CRITICAL, what + (" (predicted)" if point != p else ""))
        if action == 2 or (not zones and action >= 2):  # a return or landing: hold
            ap.modes.enter(Mode.LOITER)
            ap.hold_here(self._safe_stop or p)
        elif action == 3:
            ap.modes.enter(Mode.RTL)
        elif action == 5:
            ap.modes.enter(Mode.LAND)
        return action >= 2
