"""Trajectory -> Mission: decimation in the mission's own frame, home != origin."""

from __future__ import annotations

import numpy as np
import pymap3d
import pytest

from estimator.geodesy import ExactENU
from planner.convert import (
    douglas_peucker,
    mission_frame_points,
    mission_waypoints_enu_m,
    polyline_distance_m,
    trajectory_to_mission,
)
from planner.mission import (
    MAV_CMD_NAV_TAKEOFF,
    MAV_CMD_NAV_WAYPOINT,
    MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
    MAV_FRAME_GLOBAL_TERRAIN_ALT_INT,
)
from planner.patterns import FlightConfig, Line, densify, orbit, segments_to_trajectory
from tests.planner.conftest import gaussian_hills

ORIGIN = (36.715, -4.478, 95.0)
HILL = gaussian_hills((0.0, 0.0, 30.0, 40.0))  # 30 m high, sigma 40 m


def _agl_pass(origin=ORIGIN):
    """300 m straight pass at a constant 45 m above terrain, over the hill's top."""
    f = FlightConfig(alt_m=45.0, height_ref="terrain", origin=origin)
    return segments_to_trajectory([Line((-150.0, 0.0, 45.0), (150.0, 0.0, 45.0))], f, "pass")


def test_terrain_pass_exported_relative_to_home_follows_the_hill() -> None:
    """Decimating z above terrain kept 2 waypoints and the legs cut 30 m into the
    intended path (15 m AGL over the top); in frame 6 the hill's shape is kept."""
    traj = _agl_pass()
    m = trajectory_to_mission(traj, tolerance_m=1.0, terrain=HILL)
    wps = [it for it in m.items if it.command == MAV_CMD_NAV_WAYPOINT]
    assert all(it.frame == MAV_FRAME_GLOBAL_RELATIVE_ALT_INT for it in wps)
    assert 8 <= len(wps) <= 16  # 11 with these numbers (was 2)
    alts = np.array([it.alt_m for it in wps])
    assert alts.max() == pytest.approx(75.0, abs=1.0)  # 45 m above the 30 m top
    assert alts[0] == pytest.approx(45.0 + float(HILL.height_m(-150.0, 0.0)), abs=0.01)
    # the intended absolute path against the legs flown between the waypoints (degE7)
    back = mission_waypoints_enu_m(m)
    intended = traj.enu_m.copy()
    intended[:, 2] += HILL.height_m(intended[:, 0], intended[:, 1])
    assert polyline_distance_m(intended, back).max() <= 1.0 + 0.02  # was 30.0
    legs = densify(back, 0.5)
    agl = legs[:, 2] - HILL.height_m(legs[:, 0], legs[:, 1])
    assert agl.min() >= 45.0 - 1.0 - 0.02  # was 15.0
    # and in the mission frame itself: every sample within tolerance of the kept vertices
    _, _, _, alt_all = mission_frame_points(traj, terrain=HILL)
    pts = np.column_stack([traj.enu_m[:, :2], alt_all])
    kept = m.meta["kept_indices"]
    assert np.array_equal(kept, douglas_peucker(pts, 1.0))
    assert polyline_distance_m(pts, pts[kept]).max() <= 1.0


def test_terrain_pass_without_a_model_stays_above_terrain() -> None:
    """Frame 11: the autopilot holds the height above terrain, so a constant-AGL pass
    is correctly two waypoints at 45 m."""
    m = trajectory_to_mission(_agl_pass(), tolerance_m=1.0)
    wps = [it for it in m.items if it.command == MAV_CMD_NAV_WAYPOINT]
    assert all(it.frame == MAV_FRAME_GLOBAL_TERRAIN_ALT_INT for it in m.items[:-1])
    assert [it.alt_m for it in wps] == [45.0, 45.0]


def test_relative_altitude_is_exact_geodetic_height_above_home() -> None:
    traj = orbit((0.0, 0.0), 300.0, flight=FlightConfig(origin=ORIGIN, alt_m=45.0))
    frame, lat, lon, alt = mission_frame_points(traj)
    assert frame == MAV_FRAME_GLOBAL_RELATIVE_ALT_INT
    e, n, z = traj.enu_m.T
    la, lo, h = pymap3d.enu2geodetic(e, n, z, *ORIGIN)
    assert np.allclose(alt, h - ORIGIN[2], atol=1e-9)
    # the tangent plane rises d^2 / 2R above the ellipsoid: 7 mm at 300 m
    assert np.allclose(alt - 45.0, 300.0**2 / (2 * 6.38e6), atol=5e-4)
    assert np.allclose(lat, la) and np.allclose(lon, lo)
    # read back into the home ENU frame: the trajectory itself
    m = trajectory_to_mission(traj, tolerance_m=1.0)
    back = mission_waypoints_enu_m(m)
    assert np.allclose(back, traj.enu_m[m.meta["kept_indices"]], atol=0.01)  # degE7: 1 cm


def test_home_away_from_the_trajectory_origin() -> None:
    """Origin on a 100 m (ellipsoidal) hill top, takeoff 300 m south-west at 90 m: the
    relative altitudes are h(point) - 90, not z."""
    origin = (36.715, -4.478, 100.0)
    home_lat, home_lon, _ = ExactENU(*origin).to_geodetic(-212.0, -212.0, 0.0)
    home = (home_lat, home_lon, 90.0)
    f = FlightConfig(origin=origin, alt_m=45.0)
    traj = segments_to_trajectory([Line((0.0, 0.0, 45.0), (100.0, 0.0, 45.0))], f, "leg")
    m = trajectory_to_mission(traj, home=home, rally_enu_m=[(0.0, 0.0, 30.0)])
    assert m.home == home
    take = m.items[0]
    assert take.command == MAV_CMD_NAV_TAKEOFF
    assert (take.lat_deg, take.lon_deg) == (home_lat, home_lon)
    wps = [it for it in m.items if it.command == MAV_CMD_NAV_WAYPOINT]
    assert len(wps) == 2
    # altitudes are written to the millimetre (planner.convert: "Precision")
    assert wps[0].alt_m == pytest.approx(145.0 - 90.0, abs=5e-4)  # (0, 0, 45): h = 145
    _, _, h_end = pymap3d.enu2geodetic(100.0, 0.0, 45.0, *origin)
    assert wps[1].alt_m == pytest.approx(h_end - 90.0, abs=5e-4)
    assert take.alt_m == pytest.approx(55.0, abs=5e-4)
    assert m.rally_deg[0][2] == pytest.approx(40.0, abs=5e-4)
    # the waypoints in the home-centred frame: the same points, seen from home
    back = mission_waypoints_enu_m(m)
    e, n, u = ExactENU(*home).to_enu(*pymap3d.enu2geodetic(100.0, 0.0, 45.0, *origin))
    assert np.allclose(back[1], (e, n, u), atol=0.01)
    assert back[1][2] == pytest.approx(55.0, abs=0.02)
    with pytest.raises(ValueError, match="home"):
        trajectory_to_mission(traj, home=(36.7, -4.4))
    with pytest.raises(ValueError, match="home"):
        trajectory_to_mission(traj, home=(95.0, 0.0, 0.0))
