"""Vehicle kinematics and terrain: limits, heights, trajectories from other frames, wind."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from estimator.geodesy import ExactENU
from estimator.records import Trajectory
from sim import GridTerrain, HillsTerrain, Origin, VehicleConfig, WaypointsFlight, World, fly
from sim.terrain import bilinear

from .util import circles_flight

WORLD = World(Origin(), HillsTerrain(), ())
QUIET = VehicleConfig(tracking_sigma_m=0.0)


def _fly(traj, cfg=QUIET, seed=0):
    return fly(traj, WORLD, cfg, np.random.default_rng(seed))


def test_limits_are_respected_on_a_waypoint_mission():
    cfg = dataclasses.replace(
        QUIET, max_speed_mps=8.0, max_yaw_rate_dps=45.0, max_vertical_speed_mps=2.0
    )
    wp = WaypointsFlight(
        waypoints_m=((0, 0, 40), (150, 0, 40), (150, 120, 70), (0, 0, 40)),
        speed_mps=12.0,
        height_ref="home",
    )
    track = _fly(wp.build(WORLD), cfg)
    dt = track.t_s[1] - track.t_s[0]
    speed_h = np.hypot(track.vel_enu_mps[:, 0], track.vel_enu_mps[:, 1])
    assert speed_h.max() <= 8.0 + 1e-6
    assert np.abs(np.diff(track.yaw_rad)).max() / dt <= math.radians(45.0) + 1e-9
    assert np.abs(track.vel_enu_mps[:, 2]).max() <= 2.0 * 1.05
    acc = np.linalg.norm(np.gradient(track.vel_enu_mps, dt, axis=0), axis=1)
    assert np.quantile(acc, 0.99) <= 1.2 * math.hypot(2.0, 3.0)
    # starts and ends at rest at the first and last waypoints
    assert speed_h[0] < 0.1 and speed_h[-1] < 0.1
    home = WORLD.ground_m(0.0, 0.0)
    np.testing.assert_allclose(track.enu_m[0], [0, 0, home + 40], atol=1e-6)
    np.testing.assert_allclose(track.enu_m[-1], [0, 0, home + 40], atol=0.011)


def test_hover_at_waypoints_adds_time():
    base = dict(waypoints_m=((0, 0, 40), (100, 0, 40), (100, 100, 40)), speed_mps=5.0)
    t0 = _fly(WaypointsFlight(**base).build(WORLD)).duration_s
    t1 = _fly(WaypointsFlight(**base, hover_s=10.0).build(WORLD)).duration_s
    assert abs((t1 - t0) - 10.0) < 1.0


def test_terrain_following_holds_height_above_ground():
    flight = circles_flight(radii_m=(80.0, 150.0), laps=1.0, height_m=42.0)
    traj = flight.build(WORLD)
    assert traj.height_ref == "terrain"
    track = _fly(traj)
    assert np.ptp(WORLD.ground_m(track.enu_m[:, 0], track.enu_m[:, 1])) > 5.0  # hilly
    assert np.all(np.abs(track.agl_m - 42.0) < 0.3)
    # the flight follows the reference circles
    r = np.hypot(track.enu_m[:, 0], track.enu_m[:, 1])
    assert np.quantile(np.minimum(abs(r - 80.0), abs(r - 150.0)), 0.9) < 1.0
    assert track.duration_s >= traj.duration_s


def test_follows_a_trajectory_given_in_another_frame():
    other = ExactENU(36.716, -4.479, 150.0)  # ~140 m away, 10 m higher
    e = np.linspace(0.0, 200.0, 41)
    p = np.column_stack([e, np.full_like(e, 20.0), np.full_like(e, 60.0)])
    traj = Trajectory(e / 5.0, p, (other.lat0_deg, other.lon0_deg, other.h0_m), "origin")
    track = _fly(traj)
    lat, lon, alt = other.to_geodetic(p[:, 0], p[:, 1], p[:, 2])
    want = np.column_stack(WORLD.frame.to_enu(lat, lon, alt))
    np.testing.assert_allclose(track.enu_m[0], want[0], atol=1e-3)
    np.testing.assert_allclose(track.enu_m[-1], want[-1], atol=0.011)
    assert 0.0 < track.duration_s - traj.duration_s < 8.0  # accelerating from, braking to rest


def test_wind_drifts_downwind_and_slows_headwind_legs():
    wp = WaypointsFlight(waypoints_m=((0, 0, 40), (0, 300, 40)), speed_mps=14.0)
    calm = _fly(wp.build(WORLD), dataclasses.replace(QUIET, max_speed_mps=14.0))
    windy_cfg = dataclasses.replace(QUIET, max_speed_mps=14.0, wind_enu_mps=(5.0, -6.0))
    windy = _fly(wp.build(WORLD), windy_cfg)
    mid = len(windy.t_s) // 2
    assert abs(windy.enu_m[mid, 0] - windy_cfg.wind_drift_s * 5.0) < 0.05  # cross-track
    assert abs(calm.enu_m[mid, 0]) < 1e-6
    assert windy.duration_s > calm.duration_s + 5.0  # 6 m/s head wind on a 14 m/s airframe


def test_lever_arm_follows_yaw():
    wp = WaypointsFlight(waypoints_m=((0, 0, 40), (100, 0, 40)), speed_mps=5.0)
    cfg = dataclasses.replace(QUIET, lever_arm_m=(0.3, 0.0, -0.1))
    track = _fly(wp.build(WORLD), cfg)
    t = track.t_s[len(track.t_s) // 2]
    offset = track.antenna_at([t])[0] - track.position_at([t])[0]
    np.testing.assert_allclose(offset, [0.3, 0.0, -0.1], atol=1e-6)  # flying east, nose east


def test_tracking_wander_has_configured_size():
    flight = circles_flight(radii_m=(100.0,), laps=3.0)
    quiet = _fly(flight.build(WORLD))
    noisy = _fly(flight.build(WORLD), VehicleConfig(tracking_sigma_m=0.5, tracking_tau_s=3.0))
    d = noisy.enu_m - quiet.enu_m
    np.testing.assert_allclose(d.std(axis=0), 0.5, rtol=0.3)


def test_grid_terrain_is_bilinear_and_holds_edges():
    e0, n0, s = -100.0, -50.0, 10.0
    ee, nn = np.meshgrid(e0 + s * np.arange(21), n0 + s * np.arange(11))
    plane = 0.1 * ee - 0.05 * nn + 3.0
    grid = GridTerrain(plane, e0, n0, s)
    e = np.array([-95.0, 0.0, 37.3, 99.9])
    n = np.array([-50.0, 1.0, 22.2, 49.0])
    np.testing.assert_allclose(grid.height_m(e, n), 0.1 * e - 0.05 * n + 3.0, atol=1e-9)
    # outside: the edge value
    np.testing.assert_allclose(grid.height_m(500.0, 0.0), 0.1 * 100 + 3.0, atol=1e-9)
    np.testing.assert_allclose(
        bilinear(np.array([[0.0, 1.0], [2.0, 3.0]]), 0, 0, 1, 1, 0.5, 0.5), 1.5
    )
    with pytest.raises(ValueError, match="non-finite"):
        GridTerrain(np.array([[0.0, np.nan], [1.0, 2.0]]), 0.0, 0.0, 1.0)
    with pytest.raises(ValueError, match="2-D"):
        GridTerrain(np.zeros(5), 0.0, 0.0, 1.0)


def test_bad_vehicle_config_is_refused():
    with pytest.raises(ValueError, match="finite"):
        VehicleConfig(max_speed_mps=float("nan"))
    with pytest.raises(ValueError, match="headway"):
        VehicleConfig(max_speed_mps=5.0, wind_enu_mps=(6.0, 0.0))
    with pytest.raises(ValueError, match="> 0"):
        VehicleConfig(max_accel_mps2=0.0)


def _plain_passes(v2: list[float], step: list[float], start_v2: float) -> list[float]:
    """The speed profile's braking and acceleration passes, element by element."""
    v2 = list(v2)
    for i in range(len(v2) - 2, -1, -1):
        v2[i] = min(v2[i], v2[i + 1] + step[i])
    v2[0] = min(v2[0], start_v2)
    for i in range(1, len(v2)):
        v2[i] = min(v2[i], v2[i - 1] + step[i - 1])
    return v2


def test_compiled_speed_passes_equal_the_plain_loops_bit_for_bit() -> None:
    from sim._kernels import limit_passes as _limit_passes

    rng = np.random.default_rng(7)
    for _ in range(3000):
        m = int(rng.integers(2, 80))
        v = rng.uniform(0.0, 10.0, m)
        v[rng.random(m) < 0.3] = 0.0  # stops
        v[rng.random(m) < 0.3] = 8.0  # cruise
        step = rng.uniform(0.0, 1.5, m - 1) * float(rng.uniform(0.5, 6.0))
        start = float(rng.uniform(0.0, 80.0))
        got = _limit_passes(v * v, step, start)
        assert got.tolist() == _plain_passes((v * v).tolist(), step.tolist(), start)


@pytest.mark.parametrize("kw", [{}, {"hills": (), "ripple_amplitude_m": 0.0}])
def test_scalar_terrain_height_equals_the_array_path_bit_for_bit(kw) -> None:
    from sim.terrain import HillsTerrain

    t = HillsTerrain(**kw)
    rng = np.random.default_rng(3)
    e, n = rng.uniform(-700, 700, 40000), rng.uniform(-700, 700, 40000)
    arr = t.height_m(e, n)
    one = [t.height_m(float(a), float(b)) for a, b in zip(e, n, strict=True)]
    zero_d = [t.height_m(np.float64(a), np.float64(b)) for a, b in zip(e, n, strict=True)]
    assert np.array_equal(arr, one) and np.array_equal(arr, zero_d)


@pytest.mark.parametrize("kind", ["hills", "grid"])
def test_terrain_height_bound_holds_over_every_box(kind: str) -> None:
    """max_height_m (the vehicle skips its below-ground check under it) bounds every
    height in its box, and is close: within the ripple and the box's relief."""
    from sim.terrain import GridTerrain, HillsTerrain

    rng = np.random.default_rng(8)
    if kind == "hills":
        terrain = HillsTerrain()
    else:
        terrain = GridTerrain(rng.normal(0.0, 8.0, (30, 40)), e0_m=-300.0, n0_m=-200.0,
                              spacing_m=17.0)
    slack = []
    for _ in range(400):
        e0, n0 = rng.uniform(-900.0, 900.0, 2)
        w, h = rng.uniform(0.0, 60.0, 2)
        e = rng.uniform(e0, e0 + w, 300)
        n = rng.uniform(n0, n0 + h, 300)
        top = terrain.max_height_m(e0, e0 + w, n0, n0 + h)
        heights = terrain.height_m(e, n)
        assert heights.max() <= top
        slack.append(top - heights.max())
    assert np.median(slack) < (8.0 if kind == "hills" else 15.0)
