"""Finely drawn search areas (planner/area.py): a boundary exported from a GIS or walked
with a GNSS receiver has thousands of vertices and metre-scale wiggles. The routes
around corners take the simplified ring's corners as nodes (a graph of a few dozen
nodes, not thousands) and every leg still stays inside the true polygon."""

from __future__ import annotations

import math

import numpy as np

from planner.area import SIMPLIFY_ABOVE, SearchArea, simplify_ring


def _signed_ring_distance_m(ring, pts):
    """Largest distance (m) from points to the closed ring's edges (brute force)."""
    a = np.asarray(ring, dtype=float)
    b = np.roll(a, -1, axis=0)
    d = b - a
    out = 0.0
    for p in np.asarray(pts, dtype=float):
        t = np.clip(((p - a) * d).sum(axis=1) / np.maximum((d * d).sum(axis=1), 1e-12), 0, 1)
        out = max(out, float(np.min(np.linalg.norm(a + t[:, None] * d - p, axis=1))))
    return out


def test_simplify_ring_keeps_corners_and_stays_within_tolerance():
    # a 400 m square drawn with 2000 points, 0.3 m of wiggle on every side
    rng = np.random.default_rng(11)
    s = np.linspace(0.0, 4.0, 2000, endpoint=False)
    side, f = np.floor(s).astype(int), s % 1.0
    corners = np.array([(0, 0), (400, 0), (400, 400), (0, 400), (0, 0)], dtype=float)
    ring = corners[side] + f[:, None] * (corners[side + 1] - corners[side])
    ring += rng.uniform(-0.3, 0.3, ring.shape)
    v = simplify_ring(ring, 1.0)
    assert 4 <= len(v) <= 8
    # the four corners are kept (within the wiggle) and every point is within 1 m
    for c in corners[:4]:
        assert np.min(np.linalg.norm(v - c, axis=1)) < 0.9
    assert _signed_ring_distance_m(v, ring) <= 1.0 + 1e-9
    # a ring of 4 vertices or fewer is itself; order is kept
    assert np.array_equal(simplify_ring(corners[:4], 50.0), corners[:4])
    idx = [int(np.argmin(np.linalg.norm(ring - p, axis=1))) for p in v]
    assert idx == sorted(idx)


def test_a_wiggly_boundary_has_few_route_nodes_and_its_legs_stay_inside():
    """150 vertices with 1.1 m wiggles on a 555 m circle: 32 route nodes instead of 150
    (benchmarks/bench_area_detail.py: the same path, in a twelfth of the time)."""
    n = 150
    rng = np.random.default_rng(0)
    r = 555.0 * (1 + 0.002 * rng.standard_normal(n))
    t = 2 * np.pi * np.arange(n) / n
    poly = tuple(map(tuple, np.column_stack([r * np.cos(t), r * np.sin(t)])))
    area = SearchArea(poly, 10.0)
    assert n > SIMPLIFY_ABOVE
    assert len(area._corners(10.0)) <= 40
    wps = area.sweep(80.0, 0.0)
    path = np.array(area.join(wps))
    # every leg inside the true polygon (the turns along the wiggles come within 3.5 m
    # of it: the route's slack is half the margin, the wiggles take the rest)
    assert area.path_inside(path, 3.0, step_m=2.0)
    # and no detour: the sweep's lines plus about one spacing per turn
    lines = sum(math.dist(wps[k], wps[k + 1]) for k in range(0, len(wps) - 1, 2))
    assert np.sum(np.linalg.norm(np.diff(path, axis=0), axis=1)) < lines + len(wps) * 80.0


def test_small_polygons_route_exactly_as_before():
    """Below SIMPLIFY_ABOVE vertices nothing is simplified: an L-shape routes round its
    one reflex corner, moved in by 1.5 x margin + 1 along the bisector."""
    L = ((0, 0), (100, 0), (100, 50), (50, 50), (50, 100), (0, 100))
    assert len(L) < SIMPLIFY_ABOVE
    area = SearchArea(L, 5.0)
    c = 50.0 - 8.5 / math.sqrt(2) * math.sqrt(2)
    route = area.route((90.0, 10.0), (10.0, 90.0))
    assert len(route) == 3
    assert route[1] == (c, c)


def test_crossing_edges_are_found_and_refused_in_one_line(tmp_path):
    """A ring whose vertices are out of order (two swapped: a bow tie) crosses itself;
    it used to be planned over as if it were an area."""
    import pytest

    from estimator.geometry import polygon_crossing
    from planner.patterns import KeepOutPolygon

    bow = [(0.0, 0.0), (100.0, 100.0), (100.0, 0.0), (0.0, 90.0)]
    k, m, x, y = polygon_crossing(bow)
    assert (k, m) == (0, 2)  # edges 1 and 3
    # edge 1 is y = x, edge 3 runs from (100, 0) to (0, 90): they meet at x = 900/19
    assert (x, y) == pytest.approx((900 / 19, 900 / 19))
    assert polygon_crossing([(0, 0), (100, 0), (100, 50), (50, 50), (50, 100), (0, 100)]) \
        is None
    # a 20 000-vertex wiggly circle is simple; one swapped pair of vertices is found
    n = 20_000
    t = 2 * np.pi * np.arange(n) / n
    r = 555.0 * (1 + 0.002 * np.random.default_rng(1).standard_normal(n))
    ring = np.column_stack([r * np.cos(t), r * np.sin(t)])
    assert polygon_crossing(ring) is None
    ring[[5000, 15000]] = ring[[15000, 5000]]
    found = polygon_crossing(ring)
    assert found is not None and found[0] in (4999, 5000)
    with pytest.raises(ValueError, match=r"^the search area: its edges 1 and 3 cross at "
                                         r"\(47\.4, 47\.4\) m: its vertices are not in order"):
        SearchArea(tuple(bow), 5.0)
    with pytest.raises(ValueError, match=r"^the keep-out polygon: its edges 1 and 3 cross"):
        KeepOutPolygon(vertices_m=tuple(bow))


def test_many_vertex_polygons_answer_as_every_edge_does(monkeypatch):
    """Inside and distance for polygons of 65 to 1500 vertices (stars, combs of tall
    teeth, integer vertices with horizontal edges; points anywhere, on vertices and on
    edges): the edge index gives the same numbers, bit for bit, as every edge."""
    import estimator.geometry as geo

    rng = np.random.default_rng(5)
    for trial in range(8):
        n = int(rng.integers(65, 1500))
        if trial % 3:
            a = np.sort(rng.uniform(0.0, 2 * math.pi, n))
            r = rng.uniform(50.0, 300.0, n)
            poly = np.column_stack([r * np.cos(a), r * np.sin(a)])
        else:  # a comb: tall teeth, every band crossed by every tooth
            poly = np.array([(x + dx, y) for x in range(0, n, 2)
                             for dx, y in ((0, 0), (0, 100), (1, 100), (1, 0))], dtype=float)
        if trial % 4 == 0:
            poly = np.round(poly)
        pts = np.vstack([rng.uniform(poly.min(0) - 20, poly.max(0) + 20, (800, 2)),
                         poly[:40], 0.5 * (poly[:40] + np.roll(poly, -1, axis=0)[:40])])
        got = geo.point_in_polygon(poly, pts), geo.polygon_edge_distance_m(poly, pts)
        monkeypatch.setattr(geo, "INDEX_ABOVE", 10**9)
        want = geo.point_in_polygon(poly, pts), geo.polygon_edge_distance_m(poly, pts)
        monkeypatch.undo()
        assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1]), trial
    assert 0 < got[0].sum() < len(pts)


def test_a_twenty_thousand_vertex_boundary_is_queried_through_few_edges(monkeypatch):
    """A 500 m area traced with 20 000 vertices: each point meets a few edges, not all
    of them (osa plan lawnmower compared every path sample with every edge: stopped
    after 5 min), with the same answers; and the test of a margin meets fewer still."""
    import estimator.geometry as geo

    t = np.linspace(0.0, 2 * math.pi, 20_000, endpoint=False)
    poly = np.column_stack([250 * np.cos(t) * (1 + 0.1 * np.sin(20 * t)), 250 * np.sin(t)])
    pts = np.random.default_rng(2).uniform(-300.0, 300.0, (2000, 2))
    pairs = []
    for name in ("_crossings", "_edge_distances"):
        real = getattr(geo, name)

        def counted(poly_, edges, q, real=real):
            pairs.append(len(edges))
            return real(poly_, edges, q)

        monkeypatch.setattr(geo, name, counted)
    d = geo.signed_distance_to_polygon_m(poly, pts)
    assert sum(pairs) < 100 * len(pts)  # 62 per point; every edge: 2 x 20 000
    monkeypatch.undo()
    monkeypatch.setattr(geo, "INDEX_ABOVE", 10**9)
    assert np.array_equal(d[:200], geo.signed_distance_to_polygon_m(poly, pts[:200]))
    monkeypatch.undo()
    monkeypatch.setattr(geo, "_edge_distances", counted)
    pairs.clear()
    near = geo.polygon_edge_within_m(poly, pts, 10.0)
    assert np.array_equal(near, np.abs(d) <= 10.0) and 0 < near.sum() < len(pts)
    assert sum(pairs) < 25 * len(pts)  # 17 per point
