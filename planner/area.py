"""Search areas: keep-in polygons (convex or not) in a local ENU frame.

:class:`SearchArea` covers what the search policies need of the ``[search]`` area:

- containment with a margin (:meth:`SearchArea.contains`, checked densely along legs
  by :meth:`SearchArea.path_inside`);
- a boustrophedon over the polygon (:meth:`SearchArea.sweep`): sweep lines
  ``spacing_m`` apart along a heading, clipped to the polygon and shortened by the
  margin; consecutive waypoints are joined straight when the leg stays inside, else
  along the shortest path through the polygon's inset corners (a visibility graph,
  so a concave area is covered without leaving it);
- the expanding square of IAMSAR from a datum, clipped to the polygon the same way;
- a convex keep-in for the CasADi planner (:meth:`SearchArea.local_fence`): the area
  itself when convex with few edges, else the largest square around a point that lies
  inside it.

Keep-outs. An area may hold keep-outs (:class:`planner.patterns.KeepOut` cylinders and
:class:`planner.patterns.KeepOutPolygon` polygons, each with an optional top above the
ground): holes in the keep-in. ``floor_m`` is the lowest height above the ground the
paths checked against the area fly at; a keep-out whose top is ``clearance_m`` or more
below it is flown over and ignored by every test here, every other one (no top, or a
top above that) *blocks*: :meth:`SearchArea.contains` keeps points ``margin_m`` out of
it, :meth:`SearchArea.path_inside` checks legs against it, :meth:`SearchArea.route` goes
around it (its corners, and a circle's circumscribed polygon, moved out by the margin
join the visibility graph), :meth:`SearchArea.sweep` interrupts its tracks at it and
:meth:`SearchArea.pull_inside` never pulls into it. Without blocking keep-outs every
result is what it was without keep-outs.

The track spacing of a search comes from detection while passing
(:func:`pass_detection_range_m`): the horizontal offset at which a straight pass at
the search height and speed still hears a responder with probability ``p`` (at least
one ``ok`` among the attempts made along the pass), which is much wider than the 50 %
reach of a single attempt.
"""

from __future__ import annotations

import heapq
import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from estimator.geometry import (
    crossing_text,
    point_in_polygon,
    polygon_area_m2,
    polygon_crossing,
    polygon_edge_within_m,
    polygon_is_convex,
    signed_distance_to_polygon_m,
)
from planner.models import LinkModel
from planner.patterns import AnyKeepOut, Geofence

XY = tuple[float, float]
SIMPLIFY_ABOVE = 100  # vertices: a ring with more gives its simplified corners as nodes
NODE_TOLERANCE_M = 2.0  # the boundary detail routes around corners ignore (or half the margin)


def simplify_ring(ring_m: np.ndarray, tolerance_m: float) -> np.ndarray:
    """A closed ring's vertices that keep it within ``tolerance_m`` of itself (the
    Douglas-Peucker algorithm on the two halves between vertex 0 and the vertex farthest
    from it), in their order; the ring itself when it has 4 vertices or fewer."""
    v = np.asarray(ring_m, dtype=float).reshape(-1, 2)
    n = len(v)
    if n <= 4:
        return v
    far = int(np.argmax(np.linalg.norm(v - v[0], axis=1)))
    keep = np.zeros(n + 1, dtype=bool)
    keep[[0, far, n]] = True
    closed = np.vstack([v, v[:1]])
    stack = [(0, far), (far, n)]
    while stack:
        i, j = stack.pop()
        if j - i < 2:
            continue
        a, b = closed[i], closed[j]
        d = b - a
        L = float(np.hypot(*d))
        seg = closed[i + 1:j] - a
        if L < 1e-12:
            dist = np.linalg.norm(seg, axis=1)
        else:
            dist = np.abs(seg[:, 0] * d[1] - seg[:, 1] * d[0]) / L
        k = int(np.argmax(dist))
        if dist[k] > tolerance_m:
            m = i + 1 + k
            keep[m] = True
            stack += [(i, m), (m, j)]
    return v[keep[:n]]


def pass_detection_range_m(
    link: LinkModel,
    height_m: float,
    speed_mps: float,
    probability: float = 0.9,
    concealment: str = "open",
    pass_length_m: float = 500.0,
    max_m: float = 2000.0,
) -> float:
    """Horizontal offset at which one straight pass hears a responder with ``probability``.

    Expected ``ok`` count of a pass ``pass_length_m`` long at offset x, abeam its middle:
    rate / v * integral of P(sqrt(x^2 + s^2 + h^2)) ds over the pass (attempts at the
    link's rate); P(heard) = 1 - exp(-count).
    """
    if not 0.0 < probability < 1.0:
        raise ValueError("probability must be in (0, 1)")
    need = -math.log(1.0 - probability)
    s = np.linspace(-0.5 * pass_length_m, 0.5 * pass_length_m, 2001)
    ds = s[1] - s[0]

    def count(x: float) -> float:
        d = np.sqrt(x * x + s * s + height_m * height_m)
        p = np.asarray(link.response_probability(d, concealment), dtype=float)
        return float(link.ranging_rate_hz / speed_mps * p.sum() * ds)

    if count(0.0) < need:
        return 0.0
    lo, hi = 0.0, max_m
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if count(mid) >= need else (lo, mid)
    return lo


@dataclass(frozen=True, eq=False)
class SearchArea:
    """A keep-in polygon (ENU metres), the margin kept from its edges, and its keep-outs
    (see the module docstring: those below ``floor_m`` - ``clearance_m`` are flown over)."""

    polygon_m: tuple[XY, ...]
    margin_m: float = 10.0
    keep_outs: tuple[AnyKeepOut, ...] = ()
    floor_m: float | None = None  # lowest height above ground flown (None: unknown)
    clearance_m: float = 10.0  # vertical clearance over a keep-out's top
    _ccw: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        p = np.asarray(self.polygon_m, dtype=float).reshape(-1, 2)
        if len(p) < 3 or not np.all(np.isfinite(p)):
            raise ValueError("a search area needs >= 3 finite vertices")
        crossing = polygon_crossing(p)
        if crossing is not None:
            raise ValueError(f"the search area: {crossing_text(crossing)}")
        if abs(polygon_area_m2(p)) < 1.0:
            raise ValueError("the search area encloses no area")
        if polygon_area_m2(p) < 0:
            p = p[::-1]
        object.__setattr__(self, "_ccw", p)
        object.__setattr__(self, "_inset_cache", {})
        object.__setattr__(self, "_visible", {})
        object.__setattr__(self, "keep_outs", tuple(self.keep_outs))
        if self.floor_m is not None and not math.isfinite(self.floor_m):
            raise ValueError("floor_m must be finite")
        object.__setattr__(self, "_blocking", tuple(
            k for k in self.keep_outs if k.blocks(self.floor_m, self.clearance_m)))
        convex = polygon_is_convex(p)
        object.__setattr__(self, "_convex", convex)
        if convex:  # inward unit normals and offsets: inside iff n . q - c >= 0 on each edge
            e = np.roll(p, -1, axis=0) - p
            length = np.linalg.norm(e, axis=1)
            keep = length > 1e-9  # a repeated vertex has no edge
            nrm = np.column_stack([-e[keep, 1], e[keep, 0]]) / length[keep, None]
            object.__setattr__(self, "_halfplanes", (nrm, (nrm * p[keep]).sum(axis=1)))

    @property
    def blocking(self) -> tuple[AnyKeepOut, ...]:
        """The keep-outs that obstruct the area's paths (not flown over)."""
        return self._blocking

    @property
    def min_height_m(self) -> float | None:
        """The height above ground paths must keep because a keep-out is flown over
        (``floor_m``), or None when nothing is flown over."""
        return self.floor_m if len(self._blocking) < len(self.keep_outs) else None

    @property
    def vertices(self) -> np.ndarray:
        """Counter-clockwise vertices (N, 2)."""
        return self._ccw

    @property
    def convex(self) -> bool:
        return self._convex

    @property
    def halfplanes(self) -> tuple[np.ndarray, np.ndarray] | None:
        """A convex area's edges as half-planes: inward unit normals (E, 2) and offsets
        (E,), a point q inside iff ``normals @ q - offsets >= 0`` on every edge (each the
        distance to that edge's line); None for a concave area."""
        return self._halfplanes if self._convex else None

    @property
    def centroid_m(self) -> XY:
        p = self._ccw
        x, y = p[:, 0], p[:, 1]
        x1, y1 = np.roll(x, -1), np.roll(y, -1)
        c = x * y1 - x1 * y
        a = 0.5 * c.sum()
        return float(((x + x1) * c).sum() / (6 * a)), float(((y + y1) * c).sum() / (6 * a))

    def signed_distance_m(self, xy: np.ndarray) -> np.ndarray:
        """Distance to the boundary, negative inside (even-odd rule), positive outside."""
        q = np.asarray(xy, dtype=float).reshape(-1, 2)
        if self._convex:  # inside a convex polygon: the distance to the nearest edge's line
            nrm, c = self._halfplanes
            g = (q @ nrm.T - c).min(axis=1)
            if np.all(g > 0.0):
                return -g
        return signed_distance_to_polygon_m(self._ccw, q)

    def contains(self, xy: np.ndarray, margin_m: float | None = None, *,
                 keep_outs: bool = True) -> np.ndarray:
        """Points at least ``margin_m`` (default: none) inside the polygon and, unless
        ``keep_outs`` is False, at least as far outside every blocking keep-out."""
        m = 0.0 if margin_m is None else margin_m
        if self._convex:  # inside a convex polygon the nearest edge is the nearest line
            nrm, c = self._halfplanes
            q = np.asarray(xy, dtype=float).reshape(-1, 2)
            ok = (q @ nrm.T - c).min(axis=1) >= m - 1e-9
        else:  # signed distance <= -m + 1e-9, the distance computed only near the edge
            q = np.asarray(xy, dtype=float).reshape(-1, 2)
            limit = -m + 1e-9
            inside = point_in_polygon(self._ccw, q)
            if limit < 0.0:  # inside, and not within -limit of the edge
                ok = inside & ~polygon_edge_within_m(self._ccw, q, np.nextafter(-limit, -1.0))
            else:  # inside, or outside by at most limit
                ok = inside | polygon_edge_within_m(self._ccw, q, limit)
        if keep_outs and self._blocking:
            q = np.asarray(xy, dtype=float).reshape(-1, 2)
            for k in self._blocking:
                ok &= k.signed_distance_m(q) >= m - 1e-9
        return ok

    def path_inside(self, points_m: np.ndarray, margin_m: float = 0.0, step_m: float = 1.0,
                    *, keep_outs: bool = True) -> bool:
        """Does the polyline (straight between points) stay ``margin_m`` inside (and out
        of the blocking keep-outs, unless ``keep_outs`` is False)?"""
        p = np.asarray(points_m, dtype=float)[:, :2]
        if len(p) == 1:
            return bool(self.contains(p, margin_m, keep_outs=keep_outs)[0])
        seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
        pts = [p[:1]]
        for a, b, L in zip(p[:-1], p[1:], seg, strict=True):
            n = max(1, math.ceil(L / step_m))
            f = (np.arange(1, n + 1) / n)[:, None]
            pts.append(a + f * (b - a))
        return bool(np.all(self.contains(np.vstack(pts), margin_m, keep_outs=keep_outs)))

    # ------------------------------------------------------------------ paths inside
    def _corners(self, margin_m: float) -> list[XY]:
        """Polygon corners moved inwards along their bisectors, and points round the
        blocking keep-outs (the visibility graph's nodes). Beyond :data:`SIMPLIFY_ABOVE`
        vertices, the corners are those of the ring simplified to the larger of
        :data:`NODE_TOLERANCE_M` and half the margin (:func:`simplify_ring`), moved in
        by that much more: a finely drawn boundary
        (thousands of vertices, metre-scale wiggles) would otherwise make a graph of
        millions of edges, each checked along its length; the legs between nodes are
        still checked against the true polygon."""
        v = self._ccw
        tol = 0.0
        if len(v) > SIMPLIFY_ABOVE:
            tol = max(NODE_TOLERANCE_M, 0.5 * margin_m)
            v = simplify_ring(v, tol)
        out = []
        n = len(v)
        for i in range(n):
            a, b, c = v[i - 1], v[i], v[(i + 1) % n]
            e1, e2 = b - a, c - b
            n1 = np.array([-e1[1], e1[0]]) / max(np.linalg.norm(e1), 1e-12)  # inward (CCW)
            n2 = np.array([-e2[1], e2[0]]) / max(np.linalg.norm(e2), 1e-12)
            bis = n1 + n2
            nb = np.linalg.norm(bis)
            if nb < 1e-9:
                continue
            bis /= nb
            cos_half = max(float(bis @ n1), 0.2)
            q = b + bis * (1.5 * margin_m + 1.0 + tol) / cos_half
            if self.contains(q[None, :], margin_m)[0]:
                out.append((float(q[0]), float(q[1])))
        for k in self._blocking:  # around each blocking keep-out, outside its margin
            ring = k.outline_m(1.5 * margin_m + 1.0)
            for q in ring[self.contains(ring, margin_m)]:
                out.append((float(q[0]), float(q[1])))
        return out

    def _corner_cache(self, margin_m: float) -> list[XY]:
        cache = self.__dict__.setdefault("_corner_nodes", {})
        c = cache.get(margin_m)
        if c is None:
            c = cache[margin_m] = self._corners(margin_m)
        return c

    def route(self, a: Sequence[float], b: Sequence[float], margin_m: float | None = None
              ) -> list[XY]:
        """Shortest path from a to b that stays inside (a, b included); straight if it can."""
        path = self._route(a, b, margin_m)
        return path if path is not None else [(float(a[0]), float(a[1])),
                                              (float(b[0]), float(b[1]))]

    def _route(self, a: Sequence[float], b: Sequence[float], margin_m: float | None = None
               ) -> list[XY] | None:
        """:meth:`route`, or None when no inside route was found (a or b outside, or b
        cut off from a by keep-outs)."""
        m = self.margin_m if margin_m is None else margin_m
        pa = (float(a[0]), float(a[1]))
        pb = (float(b[0]), float(b[1]))
        # the ends may sit on the margin: check the legs with a little slack
        slack = 0.5 * m
        if self.path_inside(np.array([pa, pb]), slack):
            return [pa, pb]
        corners = self._corner_cache(m)
        nodes = [pa, pb, *corners]
        k = len(nodes)
        visible = self._visible.setdefault(m, {})  # between fixed nodes: once per area
        best = {0: 0.0}
        prev: dict[int, int] = {}
        heap = [(0.0, 0)]
        seen: set[int] = set()
        while heap:
            d, i = heapq.heappop(heap)
            if i in seen:
                continue
            seen.add(i)
            if i == 1:
                break
            for j in range(k):
                if j in seen or j == i:
                    continue
                if i >= 2 and j >= 2:
                    key = (min(i, j), max(i, j))
                    ok = visible.get(key)
                    if ok is None:
                        ok = visible[key] = self.path_inside(
                            np.array([nodes[i], nodes[j]]), slack, step_m=2.0)
                else:
                    ok = self.path_inside(np.array([nodes[i], nodes[j]]), slack, step_m=2.0)
                if not ok:
                    continue
                nd = d + math.dist(nodes[i], nodes[j])
                if nd < best.get(j, math.inf):
                    best[j] = nd
                    prev[j] = i
                    heapq.heappush(heap, (nd, j))
        if 1 not in prev:
            return None  # no inside route (a or b outside, or b cut off): the caller checks
        path = [1]
        while path[-1] != 0:
            path.append(prev[path[-1]])
        return [nodes[i] for i in reversed(path)]

    def join(self, waypoints: Sequence[Sequence[float]]) -> list[XY]:
        """Waypoints joined pairwise by :meth:`route` (duplicates dropped). A waypoint
        that cannot be reached from an inside point (cut off by keep-outs: no inside
        route, and the straight leg leaves the area) is dropped: a path through it would
        be refused whole, and the search would stand still."""
        out: list[XY] = []
        for w in waypoints:
            w2 = (float(w[0]), float(w[1]))
            if not out:
                out.append(w2)
                continue
            leg = self._route(out[-1], w2)
            if leg is None:
                straight = np.array([out[-1], w2])
                if (self.contains(straight[:1], 0.0)[0]
                        and not self.path_inside(straight, 0.0)):
                    continue
                leg = [out[-1], w2]
            out.extend(leg[1:])
        return out

    # ------------------------------------------------------------------ patterns
    def sweep(self, spacing_m: float, heading_deg: float = 0.0,
              start: Sequence[float] | None = None) -> list[XY]:
        """Boustrophedon waypoints: tracks along ``heading_deg`` (compass) ``spacing_m``
        apart, the outer ones half a spacing in from the edges, clipped to the polygon
        and its margin; begun at the end nearest ``start``."""
        if not spacing_m > 0:
            raise ValueError("spacing_m must be > 0")
        h = math.radians(heading_deg)
        along = np.array([math.sin(h), math.cos(h)])  # compass heading -> ENU
        across = np.array([along[1], -along[0]])
        v = self._ccw
        a = v @ along
        c = v @ across
        width = c.max() - c.min()
        n = max(1, math.ceil(width / spacing_m - 1e-9))
        offsets = c.min() + (np.arange(n) + 0.5) * (width / n)
        lines: list[list[tuple[float, float]]] = []
        for off in offsets:
            ivs = _clip_line(v, along, across, float(off), a.min() - 1.0, a.max() + 1.0)
            ivs = [(lo + self.margin_m, hi - self.margin_m) for lo, hi in ivs
                   if hi - lo > 2 * self.margin_m]
            if self._blocking:
                ivs = self._clear_of_keep_outs(ivs, float(off), along, across)
            if ivs:
                lines.append([(float(off), lo, hi) for lo, hi in ivs])  # type: ignore[misc]
        if not lines:
            return [self.centroid_m]

        def pt(off: float, s: float) -> XY:
            p = off * across + s * along
            return float(p[0]), float(p[1])

        def order(lines_in, flip_first: bool) -> list[XY]:
            wps: list[XY] = []
            forward = not flip_first
            for line in lines_in:
                segs = line if forward else [(o, hi, lo) for o, lo, hi in reversed(line)]
                for off, s0, s1 in segs:
                    wps += [pt(off, s0), pt(off, s1)]
                forward = not forward
            return wps

        candidates = [order(lines, False), order(lines, True),
                      order(lines[::-1], False), order(lines[::-1], True)]
        if start is not None:
            s0 = (float(start[0]), float(start[1]))
            candidates.sort(key=lambda w: math.dist(s0, w[0]))
        return self.join(candidates[0])

    def _clear_of_keep_outs(self, ivs: list[tuple[float, float]], off: float,
                            along: np.ndarray, across: np.ndarray,
                            step_m: float = 0.5) -> list[tuple[float, float]]:
        """The parts of a sweep line's intervals at least the margin out of every
        blocking keep-out (sampled every ``step_m``; parts shorter than it dropped)."""
        out: list[tuple[float, float]] = []
        for lo, hi in ivs:
            n = max(1, math.ceil((hi - lo) / step_m))
            s = lo + (hi - lo) * np.arange(n + 1) / n
            pts = off * across[None, :] + s[:, None] * along[None, :]
            ok = np.ones(len(s), dtype=bool)
            for k in self._blocking:
                ok &= k.signed_distance_m(pts) >= self.margin_m
            # runs of clear samples
            edges = np.flatnonzero(np.diff(np.concatenate([[0], ok.astype(int), [0]])))
            for r0, r1 in zip(edges[::2], edges[1::2], strict=True):
                if s[r1 - 1] - s[r0] > step_m:
                    out.append((float(s[r0]), float(s[r1 - 1])))
        return out

    def reachable_center(self, start: Sequence[float], cells: int = 48) -> XY:
        """The datum of a pattern flown from ``start``: the area's centroid when a route
        from ``start`` reaches it (always, without blocking keep-outs), else the centre
        of the part of the area ``start`` can reach (keep-outs across the area cut it
        off): the point of that part nearest its mean, found on a grid of ``cells`` x
        ``cells`` points over the area's box (the points ``margin_m`` inside, joined to
        their neighbours by straight legs that stay inside)."""
        c = self.centroid_m
        if not self._blocking or self._route(start, c) is not None:
            return c
        lo, hi = self._ccw.min(axis=0), self._ccw.max(axis=0)
        xs, ys = np.linspace(lo[0], hi[0], cells), np.linspace(lo[1], hi[1], cells)
        gx, gy = np.meshgrid(xs, ys)  # [row = y, col = x]
        pts = np.column_stack([gx.ravel(), gy.ravel()])
        ok = self.contains(pts, self.margin_m).reshape(cells, cells)
        step = float(min(xs[1] - xs[0], ys[1] - ys[0]))
        f = np.linspace(0.0, 1.0, max(2, math.ceil(step / 1.0) + 1))[:, None, None]

        def legs_inside(a: np.ndarray, b: np.ndarray) -> np.ndarray:
            q = a[None] + f * (b - a)[None]  # (k, n, 2): points along every leg at once
            return self.contains(q.reshape(-1, 2), 0.0).reshape(len(f), -1).all(axis=0)

        g = pts.reshape(cells, cells, 2)
        right = ok[:, :-1] & ok[:, 1:]
        right[right] = legs_inside(g[:, :-1][right], g[:, 1:][right])
        up = ok[:-1, :] & ok[1:, :]
        up[up] = legs_inside(g[:-1, :][up], g[1:, :][up])
        d = ((pts - np.asarray(start, dtype=float)[:2]) ** 2).sum(axis=1)
        d[~ok.ravel()] = np.inf
        if not np.isfinite(d.min()):
            return c
        first = divmod(int(np.argmin(d)), cells)
        seen = np.zeros_like(ok)
        seen[first] = True
        todo = [first]
        while todo:  # the grid points joined to the one nearest the start
            r, k = todo.pop()
            for r2, k2, joined in ((r, k + 1, k + 1 < cells and right[r, k]),
                                   (r, k - 1, k > 0 and right[r, k - 1]),
                                   (r + 1, k, r + 1 < cells and up[r, k]),
                                   (r - 1, k, r > 0 and up[r - 1, k])):
                if joined and not seen[r2, k2]:
                    seen[r2, k2] = True
                    todo.append((r2, k2))
        part = pts[seen.ravel()]
        q = part[int(np.argmin(((part - part.mean(axis=0)) ** 2).sum(axis=1)))]
        return float(q[0]), float(q[1])

    def expanding_square(self, datum: Sequence[float], spacing_m: float,
                         heading_deg: float = 0.0) -> list[XY]:
        """The IAMSAR expanding square from ``datum`` (legs S, S, 2S, 2S, ...), its
        corners clipped into the area (a corner outside is moved to the nearest point
        inside), until the squares cover the area."""
        if not spacing_m > 0:
            raise ValueError("spacing_m must be > 0")
        h = math.radians(heading_deg)
        dirs = [np.array([math.sin(h + k * math.pi / 2), math.cos(h + k * math.pi / 2)])
                for k in range(4)]
        p = np.array([float(datum[0]), float(datum[1])])
        reach = float(np.max(np.linalg.norm(self._ccw - p, axis=1)))
        wps = [p.copy()]
        k = 0
        while True:
            length = spacing_m * (k // 2 + 1)
            p = p + length * dirs[k % 4]
            wps.append(p.copy())
            k += 1
            if length > 2.0 * reach + spacing_m:
                break
        inside: list[XY] = []
        for w in wps:
            q = self.pull_inside(w)
            if not inside or math.dist(inside[-1], q) > 1.0:
                inside.append(q)
        return self.join(inside)

    def _inset_points(self, margin_m: float) -> np.ndarray:
        """Points every ~2 m along the edges moved half a metre past the margin inwards,
        those that are inside (cached per margin)."""
        pts = self._inset_cache.get(margin_m)
        if pts is None:
            v = self._ccw
            parts = []
            for i in range(len(v)):
                a, b = v[i], v[(i + 1) % len(v)]
                e = b - a
                L = float(np.linalg.norm(e))
                inward = np.array([-e[1], e[0]]) / max(L, 1e-12)
                f = np.linspace(0.0, 1.0, max(2, int(L / 2.0)))[:, None]
                parts.append(a + f * e + inward * (margin_m + 0.5))
            for k in self._blocking:  # just outside each blocking keep-out's margin
                ring = k.outline_m(margin_m + 0.5)
                ring = np.vstack([ring, ring[:1]])
                for a, b in itertools.pairwise(ring):
                    L = float(np.linalg.norm(b - a))
                    f = np.linspace(0.0, 1.0, max(2, int(L / 2.0)))[:, None]
                    parts.append(a + f * (b - a))
            pts = np.vstack(parts)
            pts = pts[self.contains(pts, margin_m)]
            self._inset_cache[margin_m] = pts
        return pts

    def pull_inside(self, p: np.ndarray, margin_m: float | None = None) -> XY:
        """``p`` if it lies ``margin_m`` (default: the area's) inside, else the nearest
        point of the boundary inset by that much (the centroid if there is none)."""
        m = self.margin_m if margin_m is None else margin_m
        p = np.asarray(p, dtype=float).reshape(2)
        if self.contains(p[None, :], m)[0]:
            return float(p[0]), float(p[1])
        pts = self._inset_points(m)
        if len(pts) == 0:
            return self.centroid_m
        q = pts[int(np.argmin(((pts - p) ** 2).sum(axis=1)))]
        return float(q[0]), float(q[1])

    # ------------------------------------------------------------------ planner fence
    def local_fence(self, center: Sequence[float], max_edges: int = 8,
                    max_half_width_m: float = 400.0) -> Geofence:
        """A convex keep-in for the CasADi planner around ``center``: the area itself
        when convex with at most ``max_edges`` edges, else the largest square (up to
        ``max_half_width_m``) centred at ``center`` that lies inside the area."""
        if self.convex and len(self._ccw) <= max_edges:
            return Geofence(vertices_m=tuple(map(tuple, self._ccw.tolist())))
        cx, cy = float(center[0]), float(center[1])
        lo, hi = 1.0, max_half_width_m
        if not self._square_inside(cx, cy, lo):
            raise ValueError("the point is not inside the search area")
        for _ in range(30):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if self._square_inside(cx, cy, mid) else (lo, mid)
        return Geofence.square((cx, cy), lo)

    def _square_inside(self, cx: float, cy: float, h: float) -> bool:
        sq = np.array([(cx - h, cy - h), (cx + h, cy - h), (cx + h, cy + h), (cx - h, cy + h),
                       (cx - h, cy - h)])
        # inside when its boundary is, and no corner of the area pokes into it
        return self.path_inside(sq, 0.0, step_m=max(1.0, h / 50.0), keep_outs=False) and not bool(
            np.any(point_in_polygon(sq[:4], self._ccw))
        )


def _clip_line(poly: np.ndarray, along: np.ndarray, across: np.ndarray, off: float,
               s_min: float, s_max: float) -> list[tuple[float, float]]:
    """Intervals (in the along coordinate) of the line {across = off} inside the polygon."""
    ss = []
    n = len(poly)
    for i in range(n):
        a, b = poly[i], poly[(i + 1) % n]
        ca, cb = float(a @ across), float(b @ across)
        if (ca > off) != (cb > off):
            t = (off - ca) / (cb - ca)
            ss.append(float((a + t * (b - a)) @ along))
    ss.sort()
    return [(ss[i], ss[i + 1]) for i in range(0, len(ss) - 1, 2)]
