"""Geometry conditioning of a set of virtual anchors.

The paper (sec. Discussion, Bootstrap Geometry) reports a condition number of 2.2 for
AP_1F and 28.5 for AP_AB and suggests refusing kappa >= 10, without defining the
matrix. Our definition, used by the bootstrap and by the planner alike:

    kappa_H = sqrt(lambda_max / lambda_min) of the weighted horizontal scatter matrix
    C = sum_i w_i (u_i - u_bar)(u_i - u_bar)^T / sum_i w_i, u_i = (x_i, y_i),

i.e. the singular-value ratio of the weighted, centred stage-1 design matrix (eq. 6
with the mean anchor as reference). It depends on the flight alone: a straight pass
(which leaves a mirror ambiguity about its line whatever the ranges) has kappa equal to
its length over its width times a constant (a 28 m pass 0.3 m wide: ~27), a circle has
kappa = 1, and any orbit or sweep covering both horizontal directions stays small.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike

KAPPA_LIMIT = 10.0  # sec. Discussion: "kappa < 10 would have rejected AP_AB, accepted AP_1F"


def horizontal_condition_number(
    anchors_xy_m: Sequence[Sequence[float]] | np.ndarray,
    weights: Sequence[float] | np.ndarray | None = None,
) -> float:
    """kappa_H of horizontal anchor positions (N x 2 or N x 3, metres); inf if degenerate."""
    a = np.asarray(anchors_xy_m, dtype=float)
    if a.ndim != 2 or a.shape[0] < 2:
        return math.inf
    xy = a[:, :2]
    w = np.ones(len(xy)) if weights is None else np.asarray(weights, dtype=float)
    if not np.all(np.isfinite(w)) or w.sum() <= 0:
        return math.inf
    mean = (w[:, None] * xy).sum(axis=0) / w.sum()
    d = xy - mean
    sxx = float((w * d[:, 0] ** 2).sum())
    syy = float((w * d[:, 1] ** 2).sum())
    sxy = float((w * d[:, 0] * d[:, 1]).sum())
    return condition_from_scatter(sxx, syy, sxy)


def condition_from_scatter(sxx: float, syy: float, sxy: float) -> float:
    """sqrt(lambda_max / lambda_min) of [[sxx, sxy], [sxy, syy]] (closed form, 2 x 2)."""
    tr = sxx + syy
    disc = math.sqrt(max(0.0, 0.25 * (sxx - syy) ** 2 + sxy * sxy))
    lmax = 0.5 * tr + disc
    lmin = 0.5 * tr - disc
    if not math.isfinite(lmax) or lmax <= 0.0 or lmin <= lmax * 1e-18:
        return math.inf
    return math.sqrt(lmax / lmin)


def bbox_diagonal_m(anchors_xy_m: Sequence[Sequence[float]] | np.ndarray) -> float:
    """Horizontal bounding-box diagonal of the anchors (sec. Gauss-Newton Bootstrap)."""
    a = np.asarray(anchors_xy_m, dtype=float)
    if a.ndim != 2 or a.shape[0] == 0:
        return 0.0
    span = a[:, :2].max(axis=0) - a[:, :2].min(axis=0)
    return float(math.hypot(span[0], span[1]))


# ----------------------------------------------------------------------------- polygons
# Search areas are polygons in a local ENU frame (convex or not); these small helpers
# are shared by the simulator (random responders in the area), the planner (keep-in
# checks) and the closed loop.


def _next_vertex(poly: np.ndarray) -> np.ndarray:
    """The vertices shifted by one (each edge's end): ``np.roll(poly, -1, axis=0)``."""
    return np.concatenate([poly[1:], poly[:1]])


def point_in_polygon(polygon_m: ArrayLike, points_m: ArrayLike) -> np.ndarray:
    """Even-odd rule: which of the (M, 2) points lie inside the (N, 2) polygon."""
    poly = np.asarray(polygon_m, dtype=float).reshape(-1, 2)
    p = np.asarray(points_m, dtype=float).reshape(-1, 2)
    if _indexed(poly, p):
        return _edge_index(poly).inside(p)
    every = np.arange(len(poly))[None, :]
    return np.concatenate([np.count_nonzero(_crossings(poly, every, q[:, None, :]), axis=1) % 2
                           == 1 for q in _chunks(p, len(poly))])


def polygon_edge_distance_m(polygon_m: ArrayLike, points_m: ArrayLike) -> np.ndarray:
    """Distance from each of the (M, 2) points to the polygon's boundary."""
    poly = np.asarray(polygon_m, dtype=float).reshape(-1, 2)
    p = np.asarray(points_m, dtype=float).reshape(-1, 2)
    if _indexed(poly, p):
        return _edge_index(poly).distance(p)
    every = np.arange(len(poly))[None, :]
    return np.concatenate([_edge_distances(poly, every, q[:, None, :]).min(axis=1)
                           for q in _chunks(p, len(poly))])


def polygon_edge_within_m(polygon_m: ArrayLike, points_m: ArrayLike,
                          radius_m: float) -> np.ndarray:
    """Which of the (M, 2) points lie within ``radius_m`` of the polygon's boundary:
    :func:`polygon_edge_distance_m` <= ``radius_m``, the same booleans, without the
    distance of the points farther (of many vertices: only the edges near each point)."""
    poly = np.asarray(polygon_m, dtype=float).reshape(-1, 2)
    p = np.asarray(points_m, dtype=float).reshape(-1, 2)
    if _indexed(poly, p) and radius_m >= 0:
        return _edge_index(poly).within(p, float(radius_m))
    return polygon_edge_distance_m(poly, p) <= radius_m


def signed_distance_to_polygon_m(polygon_m: ArrayLike, points_m: ArrayLike) -> np.ndarray:
    """Distance to the boundary, negative inside and positive outside."""
    d = polygon_edge_distance_m(polygon_m, points_m)
    return np.where(point_in_polygon(polygon_m, points_m), -d, d)


# Polygons of many vertices (a boundary traced from a map or a GPS track: thousands) are
# queried through an index of their edges; the answers are the same numbers, edge for
# edge, as comparing every point with every edge (which took minutes for a 20 000-vertex
# area, and M x N x 16 bytes of memory). Few vertices: every edge, points in chunks.
INDEX_ABOVE = 64  # vertices
_PAIRS = 1 << 21  # point-edge pairs evaluated at once (memory bound)
_INDEX_CACHE: dict[bytes, _EdgeIndex] = {}


def _indexed(poly: np.ndarray, p: np.ndarray) -> bool:
    """Query through the edge index: many vertices, some points, all finite."""
    return bool(len(poly) > INDEX_ABOVE and len(p) and np.all(np.isfinite(poly))
                and np.all(np.isfinite(p)))


def _chunks(p: np.ndarray, n_edges: int):
    step = max(1, _PAIRS // max(n_edges, 1))
    if len(p) == 0:
        yield p
    for k in range(0, len(p), step):
        yield p[k:k + step]


def _edge_index(poly: np.ndarray) -> _EdgeIndex:
    key = poly.tobytes()
    idx = _INDEX_CACHE.get(key)
    if idx is None:
        if len(_INDEX_CACHE) >= 8:
            _INDEX_CACHE.pop(next(iter(_INDEX_CACHE)))
        idx = _INDEX_CACHE[key] = _EdgeIndex(poly)
    return idx


class _EdgeIndex:
    """A polygon's edges in horizontal bands of y (for the crossings of +x rays) and, cut
    into pieces of bounded length, in a k-d tree (for the nearest edge)."""

    def __init__(self, poly: np.ndarray) -> None:
        from scipy.spatial import cKDTree

        self.poly = poly
        nxt = _next_vertex(poly)
        n = len(poly)
        # bands: each edge listed in the bands its y range meets; as many bands as keep
        # the lists about 2 n long (tall edges: fewer, wider bands)
        lo, hi = np.minimum(poly[:, 1], nxt[:, 1]), np.maximum(poly[:, 1], nxt[:, 1])
        self.y0 = float(lo.min())
        span = max(float(hi.max()) - self.y0, 1e-9)
        tall = float(np.sum(hi - lo)) / span
        self.n_bands = int(max(1, min(n, n / max(tall, 1e-9))))
        self.width = span / self.n_bands
        b0, b1 = self._band(lo), self._band(hi)
        counts = b1 - b0 + 1
        edge = np.repeat(np.arange(n), counts)
        first = np.repeat(np.cumsum(counts) - counts, counts)
        band = np.repeat(b0, counts) + (np.arange(len(edge)) - first)
        order = np.argsort(band, kind="stable")
        self.band_edges = edge[order]
        self.band_start = np.searchsorted(band[order], np.arange(self.n_bands + 1))
        # pieces: every edge cut into pieces no longer than twice the mean edge
        seg = np.linalg.norm(nxt - poly, axis=1)
        piece = 2.0 * max(float(seg.mean()), 1e-9)
        k = np.maximum(1, np.ceil(seg / piece)).astype(int)
        self.piece_edge = np.repeat(np.arange(n), k)
        j = np.arange(len(self.piece_edge)) - np.repeat(np.cumsum(k) - k, k)
        f = ((j + 0.5) / np.repeat(k, k))[:, None]
        e = self.piece_edge
        mid = poly[e] + f * (nxt[e] - poly[e])
        self.half = 0.5 * float(np.max(seg / k)) * (1.0 + 1e-9) + 1e-9
        self.tree = cKDTree(mid)

    def _band(self, y: np.ndarray) -> np.ndarray:
        b = np.floor((y - self.y0) / self.width)
        return np.clip(b, 0, self.n_bands - 1).astype(int)

    def inside(self, p: np.ndarray) -> np.ndarray:
        out = np.zeros(len(p), dtype=bool)
        b = self._band(p[:, 1])
        n_c = self.band_start[b + 1] - self.band_start[b]
        for rows in _groups(n_c):
            q = p[rows]
            starts, counts = self.band_start[b[rows]], n_c[rows]
            pt = np.repeat(np.arange(len(rows)), counts)
            cand = self.band_edges[np.repeat(starts, counts) + (
                np.arange(len(pt)) - np.repeat(np.cumsum(counts) - counts, counts))]
            hit = _crossings(self.poly, cand, q[pt])
            out[rows] = (np.bincount(pt[hit], minlength=len(rows)) % 2) == 1
        return out

    def distance(self, p: np.ndarray) -> np.ndarray:
        # the nearest edge has a piece whose midpoint lies within (its distance + half a
        # piece) <= (the nearest midpoint's distance + half a piece)
        r0, _ = self.tree.query(p)
        return self._nearest(p, r0 + self.half)

    def within(self, p: np.ndarray, radius: float) -> np.ndarray:
        # an edge within the radius has a piece whose midpoint lies within radius + half
        return self._nearest(p, np.full(len(p), radius + self.half)) <= radius

    def _nearest(self, p: np.ndarray, reach: np.ndarray) -> np.ndarray:
        """The distance to the nearest edge among those with a piece's midpoint within
        ``reach`` of each point (inf where none)."""
        near = self.tree.query_ball_point(p, reach, return_sorted=False)
        counts = np.fromiter((len(c) for c in near), dtype=int, count=len(p))
        out = np.full(len(p), np.inf)
        if not counts.any():
            return out
        flat = np.concatenate([np.asarray(c, dtype=int) for c in near if c])
        offsets = np.cumsum(counts) - counts
        for rows in _groups(counts):
            c = counts[rows]
            pt = np.repeat(np.arange(len(rows)), c)
            idx = flat[np.repeat(offsets[rows], c) + (np.arange(len(pt)) - np.repeat(
                np.cumsum(c) - c, c))]
            d = _edge_distances(self.poly, self.piece_edge[idx], p[rows][pt])
            best = np.full(len(rows), np.inf)
            np.minimum.at(best, pt, d)
            out[rows] = best
        return out


def _groups(counts: np.ndarray):
    """Consecutive row ranges whose counts sum to at most about :data:`_PAIRS`."""
    total = np.cumsum(counts)
    k = 0
    while k < len(counts):
        base = total[k] - counts[k]
        end = max(int(np.searchsorted(total, base + _PAIRS, side="right")), k + 1)
        yield np.arange(k, end)
        k = end


def _crossings(poly: np.ndarray, edges: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Does the +x ray from q cross the edge (``edges`` and the points ``q[..., :]``
    broadcast: pairwise, or (M, 1) points against (1, N) edges)?"""
    nxt = _next_vertex(poly)
    x, y = q[..., 0], q[..., 1]
    x0, y0 = poly[edges, 0], poly[edges, 1]
    x1, y1 = nxt[edges, 0], nxt[edges, 1]
    crosses = (y0 > y) != (y1 > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        x_at = x0 + (y - y0) * (x1 - x0) / (y1 - y0)
    return crosses & (x < x_at)


def _edge_distances(poly: np.ndarray, edges: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Distance from q to the edge (broadcast as :func:`_crossings`)."""
    a = poly[edges]
    ab = _next_vertex(poly)[edges] - a
    ap = q - a
    t = np.clip((ap * ab).sum(axis=-1) / np.maximum((ab * ab).sum(axis=-1), 1e-300), 0.0, 1.0)
    return np.linalg.norm(ap - t[..., None] * ab, axis=-1)


def polygon_area_m2(polygon_m: ArrayLike) -> float:
    """Signed area (shoelace formula; positive for counter-clockwise vertices)."""
    p = np.asarray(polygon_m, dtype=float).reshape(-1, 2)
    x, y = p[:, 0], p[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def polygon_is_convex(polygon_m: ArrayLike) -> bool:
    """True when every turn along the boundary has the same sense (collinear allowed)."""
    p = np.asarray(polygon_m, dtype=float).reshape(-1, 2)
    d1 = np.roll(p, -1, axis=0) - p
    d2 = np.roll(d1, -1, axis=0)
    cross = d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]
    scale = 1e-9 * float(np.max(np.abs(cross), initial=1.0))
    return bool(np.all(cross >= -scale) or np.all(cross <= scale))


def polygon_crossing(polygon_m: ArrayLike, block: int = 256
                     ) -> tuple[int, int, float, float] | None:
    """The first two edges of a polygon's ring that cross each other (edge k runs from
    vertex k to vertex k + 1): (k, m, x, y) with the crossing point, or None for a simple
    polygon. Only proper crossings count (edges that touch at a vertex or overlap along a
    line do not). Edges sorted by their x extent are tested a block at a time against
    those whose extent can meet it: near-linear for a boundary, at worst quadratic."""
    a = np.asarray(polygon_m, dtype=float).reshape(-1, 2)
    n = len(a)
    if n < 4:
        return None
    b = _next_vertex(a)
    lo, hi = np.minimum(a[:, 0], b[:, 0]), np.maximum(a[:, 0], b[:, 0])
    order = np.argsort(lo, kind="stable")
    lo_sorted = lo[order]

    def orient(p, q, r):
        return ((q[..., 0] - p[..., 0]) * (r[..., 1] - p[..., 1])
                - (q[..., 1] - p[..., 1]) * (r[..., 0] - p[..., 0]))

    best: tuple[int, int, float, float] | None = None
    for s in range(0, n, block):
        i = order[s:s + block]
        end = int(np.searchsorted(lo_sorted, hi[i].max(), side="right"))
        j = order[s:end]
        ai, bi = a[i][:, None, :], b[i][:, None, :]
        aj, bj = a[j][None, :, :], b[j][None, :, :]
        o1, o2 = orient(ai, bi, aj), orient(ai, bi, bj)
        o3, o4 = orient(aj, bj, ai), orient(aj, bj, bi)
        hit = (o1 * o2 < 0) & (o3 * o4 < 0) & (hi[i][:, None] >= lo[j][None, :])
        if not hit.any():
            continue
        for r, c in zip(*np.nonzero(hit), strict=True):
            k, m = sorted((int(i[r]), int(j[c])))
            if best is None or (k, m) < best[:2]:
                t = o1[r, c] / (o1[r, c] - o2[r, c])
                x, y = a[j[c]] + t * (b[j[c]] - a[j[c]])
                best = (k, m, float(x), float(y))
    return best


def crossing_text(crossing: tuple[int, int, float, float]) -> str:
    """A refusal's words for :func:`polygon_crossing`'s result (edges numbered from 1)."""
    k, m, x, y = crossing
    return (f"its edges {k + 1} and {m + 1} cross at ({x:.1f}, {y:.1f}) m: its vertices are "
            "not in order round its boundary")
