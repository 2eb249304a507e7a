"""Keep-outs that cut the area in two (the seeds sweep): the patterns cover the part the
start can reach instead of proposing a path through the wall that the loop refuses
(the drone then stood on the ground for the whole budget)."""

from __future__ import annotations

import numpy as np

from planner.area import SearchArea
from planner.patterns import KeepOutPolygon

SQUARE = ((-250.0, -250.0), (250.0, -250.0), (250.0, 250.0), (-250.0, 250.0))
# a keep-out across the whole width: the north is out of reach from the south
WALL = KeepOutPolygon(vertices_m=((-260.0, -100.0), (260.0, -100.0), (260.0, -90.0),
                                  (-260.0, -90.0)))


def test_a_waypoint_cut_off_by_keep_outs_is_dropped_from_a_joined_path():
    area = SearchArea(SQUARE, 10.0, keep_outs=(WALL,))
    south, north, south2 = (0.0, -200.0), (0.0, 100.0), (100.0, -200.0)
    assert area.route(south, north) == [south, north]  # no inside route: straight
    joined = area.join([south, north, south2])
    assert joined == [south, south2]
    assert area.path_inside(np.array(joined), 0.0)


def test_the_sweep_from_the_south_stays_on_the_south_side_and_inside():
    area = SearchArea(SQUARE, 10.0, keep_outs=(WALL,))
    wps = np.array(area.sweep(100.0, 0.0, start=(0.0, -240.0)))
    assert len(wps) >= 8 and wps[:, 1].max() < -100.0
    assert area.path_inside(wps, 0.0)


def test_a_leg_from_outside_the_area_is_kept_for_the_loop_to_judge():
    """From outside (a turn swung wide) the straight leg back stays: the loop flies the
    segment from its first point inside on."""
    area = SearchArea(SQUARE, 10.0, keep_outs=(WALL,))
    outside, inside = (0.0, -260.0), (0.0, -200.0)
    assert area.join([outside, inside]) == [outside, inside]


def test_joining_an_area_without_cut_off_parts_is_unchanged():
    area = SearchArea(SQUARE, 10.0)
    pts = [(0.0, -200.0), (0.0, 200.0), (100.0, 200.0)]
    assert area.join(pts) == pts


def test_the_reachable_center_is_the_centre_of_the_part_the_start_can_reach():
    area = SearchArea(SQUARE, 10.0, keep_outs=(WALL,))
    # from the south: the south part is y in [-240, -110] (the margins), x in [-240, 240]
    e, n = area.reachable_center((0.0, -240.0))
    assert abs(e) < 12.0 and abs(n - (-175.0)) < 12.0
    assert area.reachable_center((0.0, 200.0)) == area.centroid_m  # routed to: as before
    assert SearchArea(SQUARE, 10.0).reachable_center((0.0, -240.0)) == (0.0, 0.0)


def test_the_expanding_square_from_the_south_has_legs_to_fly():
    """Before: centred on the centroid (in the north), every waypoint was cut off from
    the south and the path from the start was the start alone."""
    area = SearchArea(SQUARE, 10.0, keep_outs=(WALL,))
    start = (0.0, -240.0)
    wps = area.expanding_square(area.reachable_center(start), 100.0)
    path = np.array(area.join([start, *wps]))
    assert len(path) >= 6 and path[:, 1].max() < -100.0
    assert np.linalg.norm(np.diff(path, axis=0), axis=1).sum() > 1500.0
    assert area.path_inside(path, 0.0)
