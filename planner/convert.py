"""Trajectory -> MAVLink mission (:class:`planner.mission.Mission`).

Every path, curves included, becomes plain MAV_CMD_NAV_WAYPOINT items: a takeoff item
at home first, the decimated path, and optionally RETURN_TO_LAUNCH last.

Heights. The mission frame is chosen first and every trajectory sample is expressed in
it before anything is dropped:

- frame 6 (MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, altitude relative to home), for a
  ``height_ref="origin"`` trajectory, and for a ``"terrain"`` one when a terrain model
  (ground height above the trajectory origin) is passed. The sample's absolute position
  is (e, n, z) in the trajectory's exact WGS84 ENU frame, z plus terrain(e, n) for a
  terrain-referenced path; its altitude is alt = h(point) - home_h, with h the height
  from the exact geodesy (:class:`estimator.geodesy.ExactENU`, pymap3d). With home = the
  trajectory origin (the default) alt is z less the tangent plane's drop d^2 / 2R
  (8 mm at 320 m).
- frame 11 (MAV_FRAME_GLOBAL_TERRAIN_ALT_INT, altitude above terrain, resolved by the
  autopilot) for a ``"terrain"`` trajectory without a terrain model: alt = z.

Decimation is 3-D Douglas-Peucker with ``tolerance_m`` (default 1 m) on (east, north,
alt) in that mission frame, so every dropped sample lies within ``tolerance_m`` of the
straight legs the autopilot flies between the kept waypoints (which are straight in
latitude, longitude and the frame's altitude). A constant-height-above-terrain pass
over a hill therefore keeps the vertices that follow the hill in frame 6. An orbit of
radius r keeps a vertex every 2 sqrt(2 r tol) metres or so (about 20 m for r = 50 m)
and still flies as a circle.

Home. ``home=(lat, lon, h)`` defaults to the trajectory origin; a trajectory whose
origin is not the takeoff point gets its relative altitudes from the given home.
``h`` must be in the same vertical datum as the trajectory origin's height: the frames
here treat both as WGS84 ellipsoidal heights. We have no geoid model, so nothing is
converted to AMSL: :attr:`Mission.home` holds exactly the ``home`` given (or the
origin), i.e. whatever datum the caller used (``osa plan --home LAT,LON,ALT`` takes ALT
as the home's height in the datum the vehicle reports). The waypoint items themselves
are relative to home (frame 6) or to the terrain (frame 11), so they do not depend on
that datum; only the planned-home record and heights derived from it (GeoJSON) do.

The keep-in fence becomes an inclusion polygon, keep-out cylinders exclusion circles
(mission_type FENCE); rally points (ENU, z above the trajectory origin) are optional and
get altitudes relative to home like the waypoints.

Precision. Every computed latitude and longitude of the mission (waypoints, fence,
rally points) is put on the int degE7 grid the vehicle stores (MISSION_ITEM_INT,
rounded half away from zero as MAVSDK's QGroundControl importer does), altitudes on
the millimetre, the cruise speed on the cm/s: the files then hold exactly what a
vehicle reads back (``36.7149``, ``45.0``), not the geodesy's float noise
(``44.999999999864144``). The planned home and the takeoff item at home keep the
coordinates given.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence

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
    deg_to_e7,
)
from planner.models import TerrainModel
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


def on_e7_grid(deg: float) -> float:
    """``deg`` on the int degE7 grid a vehicle stores (the value it reads back)."""
    return deg_to_e7(float(deg)) / 1e7


def on_mm(alt_m: float) -> float:
    """An altitude or length rounded to the millimetre (+0.0, never -0.0)."""
    return round(float(alt_m), 3) + 0.0


def _median_speed_m_s(traj: Trajectory) -> float | None:
    if len(traj.t_s) < 2:
        return None
    dt = np.diff(traj.t_s)
    ok = dt > 0
    if not np.any(ok):
        return None
    v = np.linalg.norm(np.diff(traj.enu_m, axis=0), axis=1)[ok] / dt[ok]
    return float(np.median(v))


def _home(traj: Trajectory, home: Sequence[float] | None) -> tuple[float, float, float]:
    if home is None:
        return (float(traj.origin[0]), float(traj.origin[1]), float(traj.origin[2]))
    h = tuple(float(v) for v in home)
    if len(h) != 3 or not all(math.isfinite(v) for v in h):
        raise ValueError("home must be 3 finite numbers (lat_deg, lon_deg, h_m)")
    if not (-90.0 <= h[0] <= 90.0 and -180.0 <= h[1] <= 180.0):
        raise ValueError(f"home out of range: {h!r}")
    return h  # type: ignore[return-value]


def mission_frame_points(
    traj: Trajectory,
    *,
    home: Sequence[float] | None = None,
    terrain: TerrainModel | None = None,
) -> tuple[int, np.ndarray, np.ndarray, np.ndarray]:
    """(frame, lat_deg, lon_deg, alt_m) of every trajectory sample in the mission frame.

    Frame 6: alt = h(point) - home_h through the exact geodesy (the absolute point is z
    above the trajectory origin, plus terrain(e, n) for a terrain-referenced path).
    Frame 11 (terrain-referenced, no terrain model): alt = z above terrain.
    """
    frame_enu = ExactENU(*traj.origin)
    e, n, z = traj.enu_m[:, 0], traj.enu_m[:, 1], traj.enu_m[:, 2]
    if traj.height_ref == "terrain" and terrain is None:
        lat, lon, _ = frame_enu.to_geodetic(e, n, np.zeros(len(e)))
        return (
            MAV_FRAME_GLOBAL_TERRAIN_ALT_INT,
            np.atleast_1d(lat),
            np.atleast_1d(lon),
            np.array(z, dtype=float),
        )
    up = np.array(z, dtype=float)
    if traj.height_ref == "terrain":
        up = up + np.asarray(terrain.height_m(e, n), dtype=float)  # type: ignore[union-attr]
    lat, lon, h = frame_enu.to_geodetic(e, n, up)
    alt = np.atleast_1d(h) - _home(traj, home)[2]
    return MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, np.atleast_1d(lat), np.atleast_1d(lon), alt


def trajectory_to_mission(
    traj: Trajectory,
    *,
    tolerance_m: float = DEFAULT_TOLERANCE_M,
    takeoff_alt_m: float | None = None,
    rtl: bool = True,
    fence: Geofence | None = None,
    keep_outs: Sequence[KeepOut] = (),
    rally_enu_m: Sequence[Sequence[float]] = (),
    terrain: TerrainModel | None = None,
    home: Sequence[float] | None = None,
    cruise_speed_m_s: float | None = None,
    name: str | None = None,
) -> Mission:
    """Mission flying ``traj``: takeoff at home, decimated waypoints, optional RTL.

    ``home`` = (lat_deg, lon_deg, h_m), default the trajectory origin; ``h_m`` in the
    datum of the origin's height (see the module docstring). ``terrain`` (ground height
    above the trajectory origin at (e, n)) turns a terrain-referenced path into frame 6.
    ``takeoff_alt_m`` defaults to the first waypoint's altitude; ``cruise_speed_m_s``
    to the trajectory's median speed.
    """
    if len(traj.t_s) == 0:
        raise ValueError("empty trajectory")
    home_t = _home(traj, home)
    frame_enu = ExactENU(*traj.origin)
    frame, lat_all, lon_all, alt_all = mission_frame_points(traj, home=home_t, terrain=terrain)
    # decimate in the mission's own frame: (east, north, alt as flown)
    pts = np.column_stack([traj.enu_m[:, 0], traj.enu_m[:, 1], alt_all])
    keep = douglas_peucker(pts, tolerance_m)
    lat, lon, alts = lat_all[keep], lon_all[keep], alt_all[keep]
    home_lat, home_lon, home_h = home_t
    t_alt = float(alts[0]) if takeoff_alt_m is None else float(takeoff_alt_m)
    if not math.isfinite(t_alt):
        raise ValueError("takeoff altitude must be finite")
    items = [
        MissionItem(
            command=MAV_CMD_NAV_TAKEOFF,
            frame=frame,
            lat_deg=home_lat,  # at home, exactly as given
            lon_deg=home_lon,
            alt_m=on_mm(t_alt),
        )
    ]
    items += [
        MissionItem(
            command=MAV_CMD_NAV_WAYPOINT,
            frame=frame,
            lat_deg=on_e7_grid(la),
            lon_deg=on_e7_grid(lo),
            alt_m=on_mm(al),
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
                    (on_e7_grid(a), on_e7_grid(b))
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
                lat_deg=on_e7_grid(clat), lon_deg=on_e7_grid(clon), radius_m=ko.radius_m,
                inclusion=False,
            )
        )
    rally = []
    for r in rally_enu_m:
        rlat, rlon, rh = frame_enu.to_geodetic(float(r[0]), float(r[1]), float(r[2]))
        rally.append((on_e7_grid(rlat), on_e7_grid(rlon), on_mm(float(rh) - home_h)))
    speed = cruise_speed_m_s if cruise_speed_m_s is not None else _median_speed_m_s(traj)
    extra = (
        {}
        if speed is None or not math.isfinite(speed) or speed <= 0
        else {"cruise_speed_m_s": round(speed, 2)}
    )
    return Mission(
        items=tuple(items),
        home=home_t,
        polygons=polygons,
        circles=tuple(circles),
        rally_deg=tuple(rally),
        name=name if name is not None else traj.name,
        meta={
            "source": traj.name,
            "tolerance_m": tolerance_m,
            "height_ref": traj.height_ref,
            "frame": frame,
            "length_m": traj.length_m,
            "duration_s": traj.duration_s,
            "kept_indices": keep,
        },
        **extra,
    )


def mission_waypoints_enu_m(mission: Mission) -> np.ndarray:
    """Positions of the NAV_WAYPOINT items in the ENU frame centred on ``mission.home``.

    Frame-6 items are inverted exactly (the point at height home_h + alt): for a mission
    exported with home = the trajectory origin this gives back the trajectory's
    (e, n, z). Items in other frames (11: above terrain) keep z = their altitude.
    """
    frame = ExactENU(*mission.home)
    wps = [it for it in mission.items if it.command == MAV_CMD_NAV_WAYPOINT]
    if not wps:
        return np.zeros((0, 3))
    lat = np.array([it.lat_deg for it in wps])
    lon = np.array([it.lon_deg for it in wps])
    alt = np.array([it.alt_m for it in wps])
    relative = np.array([it.frame == MAV_FRAME_GLOBAL_RELATIVE_ALT_INT for it in wps])
    e, n, u = frame.to_enu(lat, lon, mission.home[2] + np.where(relative, alt, 0.0))
    z = np.where(relative, np.atleast_1d(u), alt)
    return np.column_stack([np.atleast_1d(e), np.atleast_1d(n), z])
