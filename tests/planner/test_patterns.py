"""Patterns: measured spacing, radius, altitude, climb, timing; airspace checks."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from estimator.geodesy import ExactENU
from planner.convert import douglas_peucker
from planner.models import LogisticLink, slant_at
from planner.patterns import (
    FlightConfig,
    Geofence,
    KeepOut,
    airspace_violations,
    close_pass,
    concentric_circles,
    detection_range_m,
    expanding_square,
    helix,
    lawnmower,
    lawnmower_spacing_m,
    orbit,
    to_geodetic,
)

FLIGHT = FlightConfig(speed_m_s=5.0, alt_m=40.0, dt_s=0.5)


def _vertices(traj):
    """Corners of a straight-leg path (exact for polylines)."""
    return traj.enu_m[douglas_peucker(traj.enu_m, 1e-6)]


def _track_offsets(traj, axis: int) -> np.ndarray:
    """Sorted distinct coordinates along ``axis`` of the legs parallel to the other axis."""
    v = _vertices(traj)
    legs = [(a, b) for a, b in itertools.pairwise(v) if abs(a[axis] - b[axis]) < 1e-6]
    return np.unique(np.round([a[axis] for a, _ in legs], 6))


def test_sampling_is_uniform_at_the_commanded_speed() -> None:
    t = lawnmower((0.0, 0.0), 100.0, spacing_m=40.0, flight=FLIGHT)
    dt = np.diff(t.t_s)
    assert np.allclose(dt[:-1], 0.5) and 0 < dt[-1] <= 0.5 + 1e-12
    step = np.linalg.norm(np.diff(t.enu_m, axis=0), axis=1)
    assert np.all(step <= 5.0 * dt + 1e-9)  # chords across corners are shorter
    assert t.length_m == pytest.approx(t.duration_s * 5.0, rel=2e-3)


def test_lawnmower_has_the_requested_spacing_extent_and_altitude() -> None:
    t = lawnmower((10.0, -20.0), 100.0, spacing_m=40.0, flight=FLIGHT)
    xs = _track_offsets(t, axis=0)  # heading 0: north-south tracks stepping east
    assert len(xs) == 5
    assert np.allclose(np.diff(xs), 40.0)
    assert np.mean(xs) == pytest.approx(10.0)
    assert t.enu_m[:, 1].min() == pytest.approx(-120.0) and t.enu_m[:, 1].max() == pytest.approx(
        80.0
    )
    assert np.allclose(t.enu_m[:, 2], 40.0)
    assert t.height_ref == "origin" and t.name == "lawnmower"


def test_lawnmower_heading_rotates_the_tracks() -> None:
    t = lawnmower((0.0, 0.0), 60.0, spacing_m=30.0, heading_deg=90.0, flight=FLIGHT)
    ys = _track_offsets(t, axis=1)  # east-west tracks stepping south
    assert np.allclose(np.diff(ys), 30.0) and len(ys) == 4


def test_lawnmower_default_spacing_comes_from_the_detection_range() -> None:
    resp = LogisticLink()
    r_det = math.sqrt(resp.reach_m**2 - 40.0**2)  # P = 0.5 at the logistic midpoint
    assert detection_range_m(40.0, resp) == pytest.approx(r_det)
    assert lawnmower_spacing_m(r_det, 0.5) == pytest.approx(r_det)
    assert lawnmower_spacing_m(100.0, 0.25) == pytest.approx(150.0)
    t = lawnmower((0.0, 0.0), 300.0, overlap=0.5, flight=FLIGHT)
    assert np.allclose(np.diff(_track_offsets(t, axis=0)), r_det)
    p90 = slant_at(resp, 0.9)
    assert resp.response_probability(p90) == pytest.approx(0.9)
    with pytest.raises(ValueError):
        detection_range_m(500.0, resp)


def test_expanding_square_legs_grow_by_the_spacing() -> None:
    S = 25.0
    t = expanding_square((5.0, 5.0), 60.0, spacing_m=S, flight=FLIGHT)
    v = _vertices(t)
    assert np.allclose(v[0], (5.0, 5.0, 40.0))
    legs = np.linalg.norm(np.diff(v, axis=0), axis=1)
    m = math.ceil(2 * 60.0 / S)
    assert np.allclose(legs, [S * (k // 2 + 1) for k in range(2 * m)] + [S * m])
    d = np.diff(v, axis=0)[:, :2]
    # first leg north, then right turns (clockwise): north, east, south, west, ...
    assert np.allclose(d[0] / legs[0], (0.0, 1.0)) and np.allclose(d[1] / legs[1], (1.0, 0.0))
    # parallel neighbouring legs (same side, one turn apart) are S apart
    ns = [a[0] for a, b in itertools.pairwise(v) if abs(a[0] - b[0]) < 1e-9]
    assert len(ns) >= 4
    assert np.allclose(np.abs(np.diff(ns[::2])), S) and np.allclose(np.abs(np.diff(ns[1::2])), S)


def test_orbit_radius_altitude_and_length() -> None:
    t = orbit((30.0, -10.0), 50.0, turns=2.0, flight=FLIGHT)
    r = np.hypot(t.enu_m[:, 0] - 30.0, t.enu_m[:, 1] + 10.0)
    assert np.allclose(r, 50.0, atol=1e-9)
    assert np.allclose(t.enu_m[:, 2], 40.0)
    assert t.duration_s * 5.0 == pytest.approx(2 * 2 * math.pi * 50.0)  # arc length
    assert t.length_m == pytest.approx(2 * 2 * math.pi * 50.0, rel=2e-4)  # chords
    assert np.allclose(t.enu_m[0], t.enu_m[-1], atol=1e-9)


def test_helix_climbs_by_the_requested_amount() -> None:
    t = helix((0.0, 0.0), 40.0, alt_start_m=30.0, alt_end_m=70.0, turns=3.0, flight=FLIGHT)
    assert t.enu_m[0, 2] == pytest.approx(30.0) and t.enu_m[-1, 2] == pytest.approx(70.0)
    assert np.all(np.diff(t.enu_m[:, 2]) > 0)
    assert np.allclose(np.hypot(t.enu_m[:, 0], t.enu_m[:, 1]), 40.0, atol=1e-9)
    assert t.duration_s * 5.0 == pytest.approx(math.hypot(3 * 2 * math.pi * 40.0, 40.0))
    down = helix((0.0, 0.0), 40.0, alt_start_m=70.0, alt_end_m=50.0, turns=1.0, flight=FLIGHT)
    assert down.enu_m[-1, 2] == pytest.approx(50.0) and np.all(np.diff(down.enu_m[:, 2]) < 0)
    # climb rate = speed x sin(path angle)
    climb = np.diff(t.enu_m[:, 2])[:-1] / 0.5
    assert np.allclose(climb, 5.0 * 40.0 / (t.duration_s * 5.0), rtol=1e-9)


def test_concentric_circles_rings_and_altitude_steps() -> None:
    t = concentric_circles((0.0, 0.0), [20.0, 40.0, 60.0], alt_step_m=10.0, flight=FLIGHT)
    r = np.hypot(t.enu_m[:, 0], t.enu_m[:, 1])
    for radius, alt in ((20.0, 40.0), (40.0, 50.0), (60.0, 60.0)):
        on_ring = np.isclose(r, radius, atol=1e-6) & np.isclose(t.enu_m[:, 2], alt)
        assert on_ring.sum() >= int(2 * math.pi * radius / 2.5) - 1
    assert set(np.round(t.enu_m[np.isclose(r, 60.0), 2], 6)) == {60.0}


def test_close_pass_offset_heading_and_altitude() -> None:
    prior = (12.0, 7.0, 0.0)
    t = close_pass(prior, 11.0, leg_length_m=120.0, heading_deg=45.0, flight=FLIGHT)
    horiz = np.hypot(t.enu_m[:, 0] - 12.0, t.enu_m[:, 1] - 7.0)
    assert horiz.min() == pytest.approx(11.0, abs=1.3)  # samples every 2.5 m
    v = _vertices(t)
    assert len(v) == 2
    d = (v[1] - v[0])[:2] / np.linalg.norm(v[1] - v[0])
    assert np.allclose(d, (math.sqrt(0.5), math.sqrt(0.5)))
    # the exact closest approach of the leg, and the AP on its right
    a, b = v[0][:2], v[1][:2]
    u = (b - a) / np.linalg.norm(b - a)
    rel = np.array(prior[:2]) - a
    assert abs(u[0] * rel[1] - u[1] * rel[0]) == pytest.approx(11.0)
    assert u[0] * rel[1] - u[1] * rel[0] < 0  # cross < 0: AP to the right
    assert np.allclose(t.enu_m[:, 2], 40.0)


def test_start_pose_transit_and_terrain_reference() -> None:
    f = FlightConfig(alt_m=35.0, height_ref="terrain")
    t = orbit((100.0, 0.0), 30.0, flight=f, start_enu_m=(0.0, 0.0, 10.0))
    assert np.allclose(t.enu_m[0], (0.0, 0.0, 10.0))
    assert np.allclose(t.enu_m[np.argmax(t.enu_m[:, 2] >= 35.0 - 1e-9)][:2], (70.0, 0.0), atol=3.0)
    assert t.height_ref == "terrain"


def test_to_geodetic_round_trips_through_the_exact_frame() -> None:
    t = orbit((200.0, -150.0), 80.0, flight=FlightConfig(origin=(36.715, -4.478, 110.0)))
    lat, lon, h = to_geodetic(t)
    e, n, u = ExactENU(36.715, -4.478, 110.0).to_enu(lat, lon, h)
    assert np.allclose(np.column_stack([e, n, u]), t.enu_m, atol=1e-6)
    # the tangent plane leaves the ellipsoid by d^2 / 2R: 8 mm at 320 m
    assert np.allclose(h, 110.0 + t.enu_m[:, 2], atol=0.01)


@pytest.mark.parametrize(
    "make",
    [
        lambda: lawnmower((0.0, 0.0), -1.0),
        lambda: lawnmower((0.0, 0.0), 10.0, spacing_m=0.0),
        lambda: orbit((math.nan, 0.0), 10.0),
        lambda: helix((0.0, 0.0), 10.0, alt_start_m=30.0, alt_end_m=math.inf),
        lambda: FlightConfig(speed_m_s=0.0),
        lambda: FlightConfig(origin=(95.0, 0.0, 0.0)),
        lambda: concentric_circles((0.0, 0.0), [10.0, 20.0], alts_m=[30.0]),
    ],
)
def test_bad_pattern_input_is_refused(make) -> None:
    with pytest.raises(ValueError):
        make()


def test_geofence_and_keep_out_checks() -> None:
    fence = Geofence(vertices_m=((0.0, 0.0), (0.0, 100.0), (100.0, 100.0), (100.0, 0.0)))  # CW in
    assert fence.signed_distance_m(np.array([[50.0, 50.0]]))[0] == pytest.approx(-50.0)
    assert fence.signed_distance_m(np.array([[110.0, 50.0]]))[0] == pytest.approx(10.0)
    ko = [KeepOut(east_m=50.0, north_m=50.0, radius_m=10.0)]
    inside = np.array([[5.0, 5.0, 40.0], [95.0, 5.0, 40.0]])
    assert airspace_violations(inside, fence, ko) == []
    crossing = np.array([[5.0, 50.0, 40.0], [95.0, 50.0, 40.0]])  # endpoints clear, leg not
    assert any("keep-out" in p for p in airspace_violations(crossing, fence, ko))
    outside = np.array([[5.0, 5.0, 40.0], [105.0, 5.0, 40.0]])
    assert any("geofence" in p for p in airspace_violations(outside, fence, ko))
    with pytest.raises(ValueError, match="convex"):
        Geofence(vertices_m=((0, 0), (10, 0), (5, 2), (10, 10), (0, 10)))


def test_default_lawnmower_spacing_uses_the_simulators_reach() -> None:
    """50 % response at 57.5 m slant (sim/ftm.py): from 45 m up, R_det = 35.86 m."""
    r_det = detection_range_m(45.0)
    assert r_det == pytest.approx(math.sqrt(57.544**2 - 45.0**2), abs=0.01)
    assert r_det == pytest.approx(35.86, abs=0.01)
    t = lawnmower((0.0, 0.0), 150.0, flight=FlightConfig(alt_m=45.0))
    xs = _track_offsets(t, axis=0)
    assert len(xs) == 9 and np.allclose(np.diff(xs), r_det)  # ceil(300 / 35.86)
    with pytest.raises(ValueError, match="no detection"):
        detection_range_m(60.0)  # above the 50 % reach


@pytest.mark.parametrize(
    ("half_width", "spacing", "n_tracks", "inset"),
    [(100.0, 40.0, 5, 20.0), (100.0, 45.0, 5, 10.0), (100.0, 70.0, 3, 30.0), (10.0, 40.0, 1, 10.0)],
)
def test_lawnmower_outer_tracks_sit_at_most_half_a_spacing_in(
    half_width, spacing, n_tracks, inset
) -> None:
    t = lawnmower((0.0, 0.0), half_width, spacing_m=spacing, flight=FLIGHT)
    xs = _track_offsets(t, axis=0) if n_tracks > 1 else np.unique(np.round(t.enu_m[:, 0], 6))
    assert len(xs) == n_tracks
    assert half_width - xs.max() == pytest.approx(inset) and xs.min() + half_width == pytest.approx(
        inset
    )
    assert 0.0 < inset <= spacing / 2


@pytest.mark.parametrize("polygon", [
    ((0.0, 0.0), (500.0, 0.0), (500.0, 500.0), (0.0, 500.0)),
    ((0.0, 0.0), (400.0, -50.0), (520.0, 300.0), (200.0, 480.0), (-60.0, 260.0)),
])
def test_convex_area_half_plane_tests_equal_the_general_polygon_tests(polygon) -> None:
    """A convex area answers inside / distance from its edges' lines: the same answers as
    the general (segment distance, crossing count) path."""
    from planner.area import SearchArea

    fast = SearchArea(polygon, 10.0)
    general = SearchArea(polygon, 10.0)
    object.__setattr__(general, "_convex", False)
    q = np.random.default_rng(5).uniform(-80, 600, (4000, 2))
    for margin in (0.0, 10.0, 35.0):
        assert np.array_equal(fast.contains(q, margin), general.contains(q, margin))
    np.testing.assert_allclose(fast.signed_distance_m(q), general.signed_distance_m(q),
                               rtol=0, atol=1e-9)
    assert (fast.signed_distance_m(q) < 0).sum() > 1000  # many points inside
