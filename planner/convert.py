"""Trajectory -> MAVLink mission (:class:`planner.mission.Mission`).

Every path, curves included, becomes plain MAV_CMD_NAV_WAYPOINT items: a takeoff item
first, the decimated path, and optionally RETURN_TO_LAUNCH last. Decimation is 3-D
Douglas-Peucker with ``tolerance_m`` (default 1 m): every sample of the trajectory lies
within ``tolerance_m`` of the straight legs between the kept waypoints, so an orbit of
radius r keeps a vertex every 2 sqrt(2 r tol) metres or so (about 20 m for r = 50 m)
and still flies as a circle. The mission's home is the trajectory's origin (the ENU
frame is centred on home), waypoint coordinates go through the exact WGS84 ENU frame.

Heights: a trajectory with ``height_ref="origin"`` gives frame 6
(MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, altitude above home) with alt = z. A
``"terrain"`` trajectory gives frame 6 with alt = z + terrain(x, y) when a terrain
model (ground height above home) is passed, else frame 11 (MAV_FRAME_GLOBAL_TERRAIN_ALT_INT,
altitude above terrain, resolved by the autopilot) with alt = z.

The keep-in fence becomes an inclusion polygon, keep-out cylinders exclusion circles
(mission_type FENCE); rally points are optional.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Sequence

import numpy as np

from estimator.geodesy import ExactENU
from estimator.records import Trajectory
from planner.mission import (
    MAV_CMD_NAV_RETURN_TO_LAUNCH,
    MAV_CMD_NAV_TAKEOFF,
    MAV_CMD_NAV_WAYPOINT,
    MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
    MAV_FRAME_GLOBAL_TERRAIN_ALT_INT,
    FenceCircle,
    FencePolygon,
    Mission,
    MissionItem,
)
from planner.patterns import Geofence, KeepOut

DEFAULT_TOLERANCE_M = 1.0


def douglas_peucker(points: np.ndarray, tolerance_m: float) -> np.ndarray:
    """Indices of the points kept by Douglas-Peucker in 3-D (first and last always).

    Every dropped point lies within ``tolerance_m`` of the segment between the kept
    points around it. Iterative (no recursion limit on long paths).
    """
    p = np.asarray(points, dtype=float).reshape(-1, 3)
    n = len(p)
    if n <= 2:
        return np.arange(n)
    if not (math.isfinite(tolerance_m) and tolerance_m >= 0):
        raise ValueError("tolerance_m must be >= 0")
    keep = np.zeros(n, dtype=bool)
    keep[0] = keep[-1] = True
    stack = [(0, n - 1)]
    while stack:
        i, j = stack.pop()
        if j <= i + 1:
            continue
        d = point_segment_distance_m(p[i + 1 : j], p[i], p[j])
        k = int(np.argmax(d))
        if d[k] > tolerance_m:
            m = i + 1 + k
            keep[m] = True
            stack += [(i, m), (m, j)]
    return np.flatnonzero(keep)


def point_segment_distance_m(q: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distances from points ``q`` (M x 3) to the segment a-b."""
    q = np.atleast_2d(q)
    ab = b - a
    L2 = float(ab @ ab)
    if L2 == 0.0:
        return np.linalg.norm(q - a, axis=1)
    t = np.clip((q - a) @ ab / L2, 0.0, 1.0)
    return np.linalg.norm(q - (a + t[:, None] * ab), axis=1)


def polyline_distance_m(q: np.ndarray, vertices: np.ndarray) -> np.ndarray:
    """Distance from each point ``q`` (M x 3) to the polyline through ``vertices``."""
    v = np.asarray(vertices, dtype=float).reshape(-1, 3)
    q = np.atleast_2d(np.asarray(q, dtype=float))
    if len(v) == 1:
        return np.linalg.norm(q - v[0], axis=1)
    return np.min([point_segment_distance_m(q, a, b) for a, b in itertools.pairwise(v)], axis=0)


def _median_speed_m_s(traj: Trajectory) -> float | None:
    if len(traj.t_s) < 2:
        return None
    dt = np.diff(traj.t_s)
    ok = dt > 0
    if not np.any(ok):
        return None
    v = np.linalg.norm(np.diff(traj.enu_m, axis=0), axis=1)[ok] / dt[ok]
    return float(np.median(v))


def trajectory_to_mission(
    traj: Trajectory,
    *,
    tolerance_m: float = DEFAULT_TOLERANCE_M,
    takeoff_alt_m: float | None = None,
    rtl: bool = True,
    fence: Geofence | None = None,
    keep_outs: Sequence[KeepOut] = (),
    rally_enu_m: Sequence[Sequence[float]] = (),
    terrain: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
    cruise_speed_m_s: float | None = None,
    name: str | None = None,
) -> Mission:
    """Mission flying ``traj``: takeoff, decimated waypoints, optional RTL; home = origin.

    ``takeoff_alt_m`` defaults to the first waypoint's altitude; ``cruise_speed_m_s``
    to the trajectory's median speed.
    """
    if len(traj.t_s) == 0:
        raise ValueError("empty trajectory")
    frame_enu = ExactENU(*traj.origin)
    pts = traj.enu_m
    keep = douglas_peucker(pts, tolerance_m)
    kept = pts[keep]
    if traj.height_ref == "terrain" and terrain is None:
        frame = MAV_FRAME_GLOBAL_TERRAIN_ALT_INT
        alts = kept[:, 2]
    else:
        frame = MAV_FRAME_GLOBAL_RELATIVE_ALT_INT
        alts = kept[:, 2].copy()
        if traj.height_ref == "terrain":
            alts += np.asarray(terrain(kept[:, 0], kept[:, 1]), dtype=float)  # type: ignore[misc]
    h0 = traj.origin[2]
    lat, lon, _ = frame_enu.to_geodetic(kept[:, 0], kept[:, 1], np.zeros(len(kept)))
    lat, lon = np.atleast_1d(lat), np.atleast_1d(lon)
    home_lat, home_lon = traj.origin[0], traj.origin[1]
    t_alt = float(alts[0]) if takeoff_alt_m is None else float(takeoff_alt_m)
    if not math.isfinite(t_alt):
        raise ValueError("takeoff altitude must be finite")
    items = [
        MissionItem(
            command=MAV_CMD_NAV_TAKEOFF,
            frame=frame,
            lat_deg=home_lat,
            lon_deg=home_lon,
            alt_m=t_alt,
        )
    ]
    items += [
        MissionItem(
            command=MAV_CMD_NAV_WAYPOINT,
            frame=frame,
            lat_deg=float(la),
            lon_deg=float(lo),
            alt_m=float(al),
        )
        for la, lo, al in zip(lat, lon, alts, strict=True)
    ]
    if rtl:
        items.append(
            MissionItem(
                command=MAV_CMD_NAV_RETURN_TO_LAUNCH,
                frame=MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
                lat_deg=0.0,
                lon_deg=0.0,
                alt_m=0.0,
            )
        )
    polygons: tuple[FencePolygon, ...] = ()
    if fence is not None:
        v = np.asarray(fence.vertices_m, dtype=float)
        flat, flon, _ = frame_enu.to_geodetic(v[:, 0], v[:, 1], np.zeros(len(v)))
        polygons = (
            FencePolygon(
                vertices_deg=tuple(
                    (float(a), float(b))
                    for a, b in zip(np.atleast_1d(flat), np.atleast_1d(flon), strict=True)
                ),
                inclusion=True,
            ),
        )
    circles = []
    for ko in keep_outs:
        clat, clon, _ = frame_enu.to_geodetic(ko.east_m, ko.north_m, 0.0)
        circles.append(
            FenceCircle(
                lat_deg=float(clat), lon_deg=float(clon), radius_m=ko.radius_m, inclusion=False
            )
        )
    rally = []
    for r in rally_enu_m:
        rlat, rlon, _ = frame_enu.to_geodetic(float(r[0]), float(r[1]), 0.0)
        rally.append((float(rlat), float(rlon), float(r[2])))
    speed = cruise_speed_m_s if cruise_speed_m_s is not None else _median_speed_m_s(traj)
    extra = (
        {}
        if speed is None or not math.isfinite(speed) or speed <= 0
        else {"cruise_speed_m_s": speed}
    )
    return Mission(
        items=tuple(items),
        home=(home_lat, home_lon, h0),
        polygons=polygons,
        circles=tuple(circles),
        rally_deg=tuple(rally),
        name=name if name is not None else traj.name,
        meta={
            "source": traj.name,
            "tolerance_m": tolerance_m,
            "height_ref": traj.height_ref,
            "length_m": traj.length_m,
            "duration_s": traj.duration_s,
            "kept_indices": keep,
        },
        **extra,
    )


def mission_waypoints_enu_m(mission: Mission) -> np.ndarray:
    """ENU (home-centred) positions of the NAV_WAYPOINT items, z = the item altitude."""
    frame = ExactENU(*mission.home)
    wps = [it for it in mission.items if it.command == MAV_CMD_NAV_WAYPOINT]
    if not wps:
        return np.zeros((0, 3))
    lat = np.array([it.lat_deg for it in wps])
    lon = np.array([it.lon_deg for it in wps])
    e, n, _ = frame.to_enu(lat, lon, np.full(len(wps), mission.home[2]))
    return np.column_stack([np.atleast_1d(e), np.atleast_1d(n), [it.alt_m for it in wps]])
