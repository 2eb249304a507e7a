"""GeoJSON (RFC 7946) export of a plan: path, waypoints, geofence, keep-outs, prior AP.

One FeatureCollection; every feature has a ``kind`` property: ``path`` (LineString of
the trajectory), ``waypoint`` (Point per positioned mission item), ``geofence``
(Polygon), ``keep_out`` (Polygon approximating the circle, 64 vertices) and ``prior``
(Point). Positions are [longitude, latitude, height] (RFC 7946 sec. 3.1.1), heights in
metres: the home altitude plus the relative altitude (frame 6), the origin height plus
z for the path. Polygon rings are closed and their exterior runs counter-clockwise
(sec. 3.1.6). Coordinates keep 7 decimals (about 1 cm), the MAVLink degE7 resolution.
"""

from __future__ import annotations

import itertools
import json
import math
import os
from collections.abc import Sequence
from typing import Any

import numpy as np

from estimator.geodesy import ExactENU
from estimator.records import Trajectory
from planner.mission import (
    MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
    MAV_FRAME_GLOBAL_TERRAIN_ALT_INT,
    Mission,
)
from planner.patterns import to_geodetic

_DIGITS = 7
_CIRCLE_VERTICES = 64


def _pos(lon: float, lat: float, h: float | None = None) -> list[float]:
    out = [round(float(lon), _DIGITS), round(float(lat), _DIGITS)]
    if h is not None:
        out.append(round(float(h), 3))
    return out


def _ccw_ring(lonlat: Sequence[Sequence[float]]) -> list[list[float]]:
    """Closed ring, counter-clockwise in (lon, lat)."""
    ring = [_pos(lo, la) for lo, la in lonlat]
    if ring[0] != ring[-1]:
        ring.append(list(ring[0]))
    area2 = sum(a[0] * b[1] - b[0] * a[1] for a, b in itertools.pairwise(ring))
    return ring if area2 > 0 else ring[::-1]


def circle_ring(lat: float, lon: float, radius_m: float) -> list[list[float]]:
    """A circle as a polygon ring through the exact WGS84 ENU frame at its centre."""
    th = np.linspace(0.0, 2.0 * math.pi, _CIRCLE_VERTICES, endpoint=False)
    rlat, rlon, _ = ExactENU(lat, lon, 0.0).to_geodetic(
        radius_m * np.cos(th), radius_m * np.sin(th), np.zeros_like(th)
    )
    return _ccw_ring(list(zip(rlon, rlat, strict=True)))


def _feature(geometry: dict, **properties: Any) -> dict:
    return {"type": "Feature", "geometry": geometry, "properties": properties}


def plan_geojson(
    mission: Mission | None = None,
    trajectory: Trajectory | None = None,
    *,
    prior_latlon: tuple[float, float] | None = None,
    prior_sigma_m: float | None = None,
    name: str = "",
) -> dict:
    """Build the FeatureCollection of a plan (any argument may be left out)."""
    features: list[dict] = []
    if trajectory is not None and len(trajectory.t_s) >= 2:
        lat, lon, h = to_geodetic(trajectory)
        features.append(
            _feature(
                {
                    "type": "LineString",
                    "coordinates": [_pos(a, b, c) for a, b, c in zip(lon, lat, h, strict=True)],
                },
                kind="path",
                name=trajectory.name,
                height_ref=trajectory.height_ref,
                length_m=round(trajectory.length_m, 3),
                duration_s=round(trajectory.duration_s, 3),
            )
        )
    if mission is not None:
        h0 = mission.home[2]
        for seq, it in enumerate(mission.items):
            if it.lat_deg == 0.0 and it.lon_deg == 0.0:
                continue  # RTL and other unpositioned items
            if it.frame == MAV_FRAME_GLOBAL_RELATIVE_ALT_INT:
                h = h0 + it.alt_m
            elif it.frame == MAV_FRAME_GLOBAL_TERRAIN_ALT_INT:
                h = None  # above terrain: no ellipsoidal height known here
            else:
                h = it.alt_m
            features.append(
                _feature(
                    {"type": "Point", "coordinates": _pos(it.lon_deg, it.lat_deg, h)},
                    kind="waypoint",
                    seq=seq,
                    command=it.command,
                    frame=it.frame,
                    alt_m=it.alt_m,
                )
            )
        for k, poly in enumerate(mission.polygons):
            ring = _ccw_ring([(lo, la) for la, lo in poly.vertices_deg])
            features.append(
                _feature(
                    {"type": "Polygon", "coordinates": [ring]},
                    kind="geofence",
                    index=k,
                    inclusion=poly.inclusion,
                )
            )
        for k, c in enumerate(mission.circles):
            features.append(
                _feature(
                    {
                        "type": "Polygon",
                        "coordinates": [circle_ring(c.lat_deg, c.lon_deg, c.radius_m)],
                    },
                    kind="keep_out" if not c.inclusion else "geofence_circle",
                    index=k,
                    inclusion=c.inclusion,
                    center=_pos(c.lon_deg, c.lat_deg),
                    radius_m=c.radius_m,
                )
            )
        features.append(
            _feature(
                {"type": "Point", "coordinates": _pos(mission.home[1], mission.home[0], h0)},
                kind="home",
            )
        )
    if prior_latlon is not None:
        props: dict[str, Any] = {"kind": "prior"}
        if prior_sigma_m is not None:
            props["sigma_m"] = prior_sigma_m
        features.append(
            _feature(
                {"type": "Point", "coordinates": _pos(prior_latlon[1], prior_latlon[0])}, **props
            )
        )
    out: dict[str, Any] = {"type": "FeatureCollection", "features": features}
    if name:
        out["name"] = name
    return out


def write_geojson(collection: dict, path: str | os.PathLike[str]) -> None:
    """Write the collection as UTF-8 JSON (``allow_nan=False``: NaN is not JSON)."""
    problems = validate_geojson(collection)
    if problems:
        raise ValueError("invalid GeoJSON: " + "; ".join(problems))
    with open(path, "w", encoding="utf-8") as fh:
        json.dump(collection, fh, allow_nan=False, separators=(",", ":"))
        fh.write("\n")


def _check_position(p: Any, where: str, out: list[str]) -> None:
    if not (
        isinstance(p, list) and 2 <= len(p) <= 3 and all(isinstance(v, int | float) for v in p)
    ):
        out.append(f"{where}: a position is 2 or 3 numbers")
        return
    if not all(math.isfinite(v) for v in p):
        out.append(f"{where}: non-finite coordinate")
    elif not (-180.0 <= p[0] <= 180.0 and -90.0 <= p[1] <= 90.0):
        out.append(f"{where}: [lon, lat] out of range: {p[:2]}")


def validate_geojson(obj: Any) -> list[str]:
    """RFC 7946 checks used here: structure, [lon, lat] ranges, LineStrings of >= 2
    positions, closed rings of >= 4 positions with a counter-clockwise exterior.
    Returns the problems found (empty when valid)."""
    out: list[str] = []
    if not isinstance(obj, dict) or obj.get("type") != "FeatureCollection":
        return ["not a FeatureCollection"]
    feats = obj.get("features")
    if not isinstance(feats, list):
        return ["features must be a list"]
    for i, f in enumerate(feats):
        where = f"feature {i}"
        if not isinstance(f, dict) or f.get("type") != "Feature" or "properties" not in f:
            out.append(f"{where}: not a Feature with properties")
            continue
        g = f.get("geometry")
        if not isinstance(g, dict):
            out.append(f"{where}: missing geometry")
            continue
        kind, coords = g.get("type"), g.get("coordinates")
        if kind == "Point":
            _check_position(coords, where, out)
        elif kind == "LineString":
            if not isinstance(coords, list) or len(coords) < 2:
                out.append(f"{where}: a LineString needs >= 2 positions")
            else:
                for p in coords:
                    _check_position(p, where, out)
        elif kind == "Polygon":
            if not isinstance(coords, list) or not coords:
                out.append(f"{where}: a Polygon needs rings")
                continue
            for r, ring in enumerate(coords):
                if not isinstance(ring, list) or len(ring) < 4 or ring[0] != ring[-1]:
                    out.append(f"{where}: ring {r} must be closed with >= 4 positions")
                    continue
                for p in ring:
                    _check_position(p, where, out)
                area2 = sum(a[0] * b[1] - b[0] * a[1] for a, b in itertools.pairwise(ring))
                if (area2 > 0) != (r == 0):
                    out.append(f"{where}: ring {r} has the wrong winding")
        else:
            out.append(f"{where}: unsupported geometry {kind!r}")
    return out
