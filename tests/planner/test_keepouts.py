"""Keep-outs in the planner: the search area's holes (contains, path_inside, route,
sweep, pull_inside), their tops, the CasADi planner's keep-out polygons, terrain
following."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from planner.area import SearchArea
from planner.models import FlatTerrain
from planner.optimal import OptimalConfig, OptimalPlanner
from planner.patterns import (
    Geofence,
    KeepOut,
    KeepOutPolygon,
    airspace_violations,
    convex_hull,
    densify,
)
from planner.terrain_follow import agl_along, follow_terrain

SQUARE = ((-300.0, -300.0), (300.0, -300.0), (300.0, 300.0), (-300.0, 300.0))
TOWER = KeepOut(east_m=0.0, north_m=0.0, radius_m=25.0, top_m=40.0)
WALL = KeepOutPolygon(vertices_m=((-150.0, 100.0), (150.0, 100.0), (150.0, 130.0),
                                  (-150.0, 130.0)))  # no top: never flown over
WIRES = KeepOutPolygon(vertices_m=((-300.0, -120.0), (300.0, -120.0), (300.0, -100.0),
                                   (-300.0, -100.0)), top_m=25.0)


def _clearance(points: np.ndarray, keep_outs) -> float:
    d = densify(np.column_stack([np.asarray(points)[:, :2], np.zeros(len(points))]), 0.5)
    return min(float(k.signed_distance_m(d[:, :2]).min()) for k in keep_outs)


def test_keep_outs_are_holes_unless_flown_over():
    area = SearchArea(SQUARE, 10.0, keep_outs=(TOWER, WALL, WIRES), floor_m=45.0)
    # the wires' top + 10 m clearance is below 45 m: flown over; the tower's is not
    assert area.blocking == (TOWER, WALL) and area.min_height_m == 45.0
    pts = np.array([[0.0, 0.0], [0.0, 30.0], [0.0, 36.0], [0.0, 115.0], [0.0, -110.0]])
    assert area.contains(pts, 10.0).tolist() == [False, False, True, False, True]
    assert area.contains(pts, 10.0, keep_outs=False).all()
    # with no floor known (or a low one), every keep-out blocks
    for floor in (None, 20.0):
        a2 = SearchArea(SQUARE, 10.0, keep_outs=(TOWER, WALL, WIRES), floor_m=floor)
        assert len(a2.blocking) == 3 and a2.min_height_m is None
    plain = SearchArea(SQUARE, 10.0)
    assert plain.blocking == () and plain.min_height_m is None


def test_routes_sweeps_and_pulls_stay_out_of_blocking_keep_outs():
    area = SearchArea(SQUARE, 10.0, keep_outs=(TOWER, WALL, WIRES), floor_m=45.0)
    # a route across the tower and the wall goes around them
    leg = area.route((0.0, -200.0), (0.0, 250.0))
    assert len(leg) > 2 and area.path_inside(np.array(leg), 0.0)
    assert _clearance(np.array(leg), area.blocking) >= 5.0 - 1e-6
    # around the wall's end (x = 150 + 16) and back: about 550 m
    assert 540.0 < sum(math.dist(a, b) for a, b in itertools.pairwise(leg)) < 1.4 * 450
    # the lawnmower: tracks interrupted at the keep-outs, joined around them
    for heading in (0.0, 90.0, 30.0):
        wps = area.sweep(50.0, heading, start=(0.0, -290.0))
        path = np.array(wps)
        assert _clearance(path, area.blocking) >= 5.0 - 1e-6
        assert area.path_inside(path, 0.0)
        # the tracks still cover the area: every clear point is within a spacing of them
        g = np.stack(np.meshgrid(np.arange(-280, 281, 20.0), np.arange(-280, 281, 20.0)),
                     -1).reshape(-1, 2)
        g = g[area.contains(g, 10.0)]
        d = densify(np.column_stack([path, np.zeros(len(path))]), 5.0)[:, :2]
        near = np.min(np.linalg.norm(g[:, None, :] - d[None, :, :], axis=2), axis=1)
        assert near.max() <= 50.0
    # the wires (flown over) do not interrupt a track that crosses them
    wps = area.sweep(50.0, 0.0)
    crossing = [(a, b) for a, b in itertools.pairwise(wps)
                if a[0] == b[0] and min(a[1], b[1]) < -120 and max(a[1], b[1]) > -100]
    assert crossing
    # pulled inside: never into a keep-out
    for p in ([0.0, 5.0], [20.0, 115.0], [-400.0, 0.0]):
        q = area.pull_inside(np.array(p))
        assert area.contains(np.array([q]), 10.0 - 1e-6)[0]
    sq = area.expanding_square((5.0, -40.0), 40.0)
    assert _clearance(np.array(sq), area.blocking) >= 5.0 - 1e-6


def test_without_keep_outs_nothing_changes():
    a = SearchArea(SQUARE[::-1], 10.0)
    b = SearchArea(SQUARE[::-1], 10.0, keep_outs=(WIRES,), floor_m=45.0)  # flown over
    assert a.sweep(40.0, 20.0, start=(0, 0)) == b.sweep(40.0, 20.0, start=(0, 0))
    assert a.route((-250, -250), (250, 250)) == b.route((-250, -250), (250, 250))


def test_keep_out_shapes_and_checks():
    assert convex_hull(np.array([[0, 0], [2, 0], [1, 1], [2, 2], [0, 2]])).tolist() == [
        [0.0, 0.0], [2.0, 0.0], [2.0, 2.0], [0.0, 2.0]]
    hp = WALL.hull_half_planes()
    q = np.array([[0.0, 200.0], [0.0, 115.0], [200.0, 115.0]])
    out = (q @ hp[:, :2].T - hp[:, 2]).max(axis=1)
    assert out.tolist() == pytest.approx([70.0, -15.0, 50.0])
    ring = TOWER.outline_m(10.0, sides=12)
    assert np.allclose(np.hypot(*ring.T), 35.0 / math.cos(math.pi / 12))
    grown = WALL.outline_m(5.0)
    assert np.allclose(grown.min(axis=0), (-155.0, 95.0)) and np.allclose(grown.max(axis=0),
                                                                           (155.0, 135.0))
    path = np.array([[0.0, -200.0, 50.0], [0.0, 200.0, 50.0]])
    msgs = airspace_violations(path, None, [TOWER, WALL, WIRES])
    assert len(msgs) == 3 and "keep-out 1 (a polygon) 15.00 m deep" in msgs[1]
    # with heights above ground: the wires (top 25) are cleared at 45 m, the tower is not
    msgs = airspace_violations(path - [0, 0, 5], None, [TOWER, WIRES], agl_m=lambda d: d[:, 2],
                               clearance_m=10.0)
    assert len(msgs) == 1 and "keep-out 0" in msgs[0]
    with pytest.raises(ValueError, match="top_m"):
        KeepOut(east_m=0, north_m=0, radius_m=1, top_m=-1)


def test_casadi_planner_keeps_out_of_polygons():
    poly = KeepOutPolygon(vertices_m=((-90.0, -300.0), (-70.0, -300.0), (-70.0, 300.0),
                                      (-90.0, 300.0)))
    cfg = OptimalConfig(max_keep_out_polygons=1, n_waypoints=16, horizon_s=90.0)
    p = OptimalPlanner(cfg)
    fence = Geofence.square((0.0, 0.0), 300.0)
    for start in ((0.0, -100.0, 45.0), (50.0, 50.0, 45.0)):
        r = p.plan((0.0, 0.0, 0.0), np.diag([100.0, 100.0, 4.0]), start, fence=fence,
                   keep_out_polygons=[poly], warm_start=False)
        assert r.feasible and r.fallback is None, r.violations
        d = densify(r.trajectory.enu_m, 0.5)
        # the hull's margin (2 m) holds along every leg, not only at the waypoints
        assert poly.signed_distance_m(d[:, :2]).min() >= cfg.keep_out_margin_m - 0.01
        assert not p.check(r.waypoints_enu_m, start, (0, 0, 0), r.dt_s, fence=fence,
                           keep_out_polygons=[poly])
    # the check sees a path through the polygon
    W = np.array([[0.0, -100.0, 45.0], [-80.0, -100.0, 45.0], [-160.0, -100.0, 45.0]])
    assert any("polygon" in v for v in p.check(W, W[0], (0, 0, 0), 10.0,
                                               keep_out_polygons=[poly]))
    with pytest.raises(ValueError, match="2 keep-out polygons; the planner holds 1"):
        p.plan((0, 0, 0), np.eye(3) * 100, (0.0, -100.0, 45.0),
               keep_out_polygons=[poly, WALL])
    with pytest.raises(ValueError, match="inside a keep-out polygon"):
        p.plan((0, 0, 0), np.eye(3) * 100, (-80.0, 0.0, 45.0), keep_out_polygons=[poly])


class _Ridges:
    """Rough ground: ridges and a step-like slope (protocol: height_m, sag_curvature)."""

    def height_m(self, e, n):
        e, n = np.asarray(e, dtype=float), np.asarray(n, dtype=float)
        return (40.0 * np.sin(e / 37.0) * np.cos(n / 53.0) + 0.3 * e
                + 15.0 * np.tanh((n - 100.0) / 8.0))

    def sag_curvature(self):
        return 0.1, 0.1


def test_terrain_following_keeps_every_leg_in_the_band():
    t = _Ridges()
    path = np.array([[-400.0, -300.0], [400.0, -300.0], [400.0, -250.0], [-400.0, 250.0]])
    v = follow_terrain(path, 45.0, t)
    agl = agl_along(v, t, 0.1)
    assert agl.min() >= 43.0 and agl.max() <= 70.0
    # the corners are vertices; the first is at the wanted height above the ground
    for c in path:
        assert np.min(np.hypot(*(v[:, :2] - c).T)) < 1e-9
    assert v[0, 2] - float(t.height_m(*path[0])) == pytest.approx(45.0)
    # vertices only where the ground needs them: a narrower band needs more
    tight = follow_terrain(path, 45.0, t, above_m=5.0)
    assert len(tight) > len(v) > len(path)
    a2 = agl_along(tight, t, 0.1)
    assert a2.min() >= 43.0 and a2.max() <= 50.0
    # flat ground: the corners only
    flat = follow_terrain(path, 45.0, FlatTerrain(10.0))
    assert len(flat) == len(path) and np.allclose(flat[:, 2], 55.0)
    # a height per point (a climbing pattern)
    climb = follow_terrain(path, [45.0, 45.0, 60.0, 75.0], t)
    a3 = agl_along(climb[-2:], t, 0.1)
    assert a3.min() >= 58.0 - 0.01


def test_terrain_following_over_cliffs_of_a_one_metre_dem():
    """A 1 m LiDAR grid with a 25 m cliff (one cell wide, across the path and diagonal to
    it) and a 60 m quarry wall: bilinear ground rising 25-60 m within a metre, the path
    off the grid's nodes. Every point of every leg stays in [M - 2, M + 25], checked
    every 2 cm (the legs were sampled every metre with a fixed 0.5 m margin: they dipped
    to 29.6 m above the ground, into the cliffs' edges, and rose to 64.8)."""
    from sim.terrain import GridTerrain

    n = np.arange(-200, 201, dtype=float)
    E, N = np.meshgrid(n, n)
    h = 25.0 * (E > 40.5) + 25.0 * (E + N > 100.5) + 60.0 * (N < -80.5)
    h += 30.0 * np.exp(-((E + 60.0) / 20.0) ** 2)  # and a ridge
    t = GridTerrain(h, -200.0, -200.0, 1.0)
    path = np.array([[-150.0, -120.0], [150.0, -120.0], [150.0, -40.0], [-150.0, -40.0],
                     [-150.0, 60.0], [150.0, 60.0], [0.0, 150.0], [0.0, -150.0]]) + 0.37
    v = follow_terrain(path, 40.0, t)
    agl = agl_along(v, t, 0.02)
    assert agl.min() >= 38.0 and agl.max() <= 65.0
    # an absolute band: a pattern climbing beyond it (a helix's 40 to 75 m) is held in it
    climb = follow_terrain(path, np.linspace(40.0, 75.0, len(path)), t, band_m=(38.0, 65.0))
    a2 = agl_along(climb, t, 0.02)
    assert a2.min() >= 38.0 and a2.max() <= 65.0 and a2[-100:].min() > 60.0
