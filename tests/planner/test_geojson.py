"""GeoJSON export: structure and the RFC 7946 rules (lon/lat order, closed CCW rings)."""

from __future__ import annotations

import itertools
import json
import math

import numpy as np
import pytest

from estimator.geodesy import ExactENU
from planner.convert import trajectory_to_mission
from planner.geojson import plan_geojson, validate_geojson, write_geojson
from planner.mission import MAV_CMD_NAV_TAKEOFF, MAV_CMD_NAV_WAYPOINT
from planner.patterns import FlightConfig, Geofence, KeepOut, helix

HOME = (36.715, -4.478, 120.0)


@pytest.fixture
def plan():
    traj = helix((60.0, 40.0), 40.0, alt_start_m=40.0, alt_end_m=60.0, turns=2.0,
                 flight=FlightConfig(origin=HOME), start_enu_m=(0.0, 0.0, 40.0))  # fmt: skip
    fence = Geofence(
        vertices_m=((-100.0, -100.0), (-100.0, 200.0), (200.0, 200.0), (200.0, -100.0))
    )
    mission = trajectory_to_mission(
        traj, fence=fence, keep_outs=[KeepOut(east_m=150.0, north_m=150.0, radius_m=20.0)]
    )
    lat, lon, _ = ExactENU(*HOME).to_geodetic(60.0, 40.0, 0.0)
    return traj, mission, (lat, lon)


def test_feature_collection_structure(plan) -> None:
    traj, mission, prior = plan
    fc = plan_geojson(mission, traj, prior_latlon=prior, prior_sigma_m=10.0, name="helix")
    assert validate_geojson(fc) == []
    kinds = [f["properties"]["kind"] for f in fc["features"]]
    assert kinds.count("path") == 1 and kinds.count("prior") == 1 and kinds.count("home") == 1
    assert kinds.count("geofence") == 1 and kinds.count("keep_out") == 1
    positioned = [it for it in mission.items if not (it.lat_deg == 0 and it.lon_deg == 0)]
    assert kinds.count("waypoint") == len(positioned) == len(mission.items) - 1  # RTL has none
    path = next(f for f in fc["features"] if f["properties"]["kind"] == "path")
    coords = np.array(path["geometry"]["coordinates"])
    assert coords.shape == (len(traj.t_s), 3)
    # [lon, lat, h]: the first sample is home (0, 0) at 40 m above it
    assert coords[0, 0] == pytest.approx(HOME[1]) and coords[0, 1] == pytest.approx(HOME[0])
    assert coords[0, 2] == pytest.approx(HOME[2] + 40.0, abs=1e-3)
    wps = [f for f in fc["features"] if f["properties"]["kind"] == "waypoint"]
    assert wps[0]["properties"]["command"] == MAV_CMD_NAV_TAKEOFF
    w1 = wps[1]
    assert w1["properties"]["command"] == MAV_CMD_NAV_WAYPOINT
    it = mission.items[w1["properties"]["seq"]]
    assert w1["geometry"]["coordinates"] == pytest.approx(
        [it.lon_deg, it.lat_deg, HOME[2] + it.alt_m], abs=1e-7
    )
    prior_f = next(f for f in fc["features"] if f["properties"]["kind"] == "prior")
    assert prior_f["geometry"]["coordinates"] == pytest.approx([prior[1], prior[0]], abs=1e-7)
    assert prior_f["properties"]["sigma_m"] == 10.0


def test_rings_are_closed_and_counter_clockwise(plan) -> None:
    traj, mission, _ = plan
    fc = plan_geojson(mission, traj)
    for f in fc["features"]:
        if f["geometry"]["type"] != "Polygon":
            continue
        ring = f["geometry"]["coordinates"][0]
        assert ring[0] == ring[-1] and len(ring) >= 4
        area2 = sum(a[0] * b[1] - b[0] * a[1] for a, b in itertools.pairwise(ring))
        assert area2 > 0
    fence = next(f for f in fc["features"] if f["properties"]["kind"] == "geofence")
    assert len(fence["geometry"]["coordinates"][0]) == 5  # 4 vertices + closing
    ko = next(f for f in fc["features"] if f["properties"]["kind"] == "keep_out")
    ring = np.array(ko["geometry"]["coordinates"][0])
    clon, clat = ko["properties"]["center"]
    e, n, _ = ExactENU(clat, clon, 0.0).to_enu(ring[:, 1], ring[:, 0], np.zeros(len(ring)))
    assert np.allclose(np.hypot(e, n), 20.0, atol=0.05)


def test_validator_catches_rfc_violations() -> None:
    good = {
        "type": "Feature",
        "properties": {},
        "geometry": {"type": "Point", "coordinates": [-4.5, 36.7]},
    }
    assert validate_geojson({"type": "FeatureCollection", "features": [good]}) == []
    swapped = {**good, "geometry": {"type": "Point", "coordinates": [36.7, -120.0]}}
    open_ring = {
        **good,
        "geometry": {"type": "Polygon", "coordinates": [[[0, 0], [1, 0], [1, 1], [0, 1]]]},
    }
    clockwise = {
        **good,
        "geometry": {"type": "Polygon", "coordinates": [[[0, 0], [0, 1], [1, 1], [0, 0]]]},
    }
    short = {**good, "geometry": {"type": "LineString", "coordinates": [[0, 0]]}}
    for bad in (swapped, open_ring, clockwise, short):
        assert validate_geojson({"type": "FeatureCollection", "features": [bad]}) != []
    assert validate_geojson({"type": "Feature"}) == ["not a FeatureCollection"]


def test_write_refuses_nan_and_writes_json(plan, tmp_path) -> None:
    traj, mission, prior = plan
    path = tmp_path / "plan.geojson"
    write_geojson(plan_geojson(mission, traj, prior_latlon=prior), path)
    back = json.loads(path.read_text())
    assert back["type"] == "FeatureCollection" and validate_geojson(back) == []
    with pytest.raises(ValueError):
        write_geojson(plan_geojson(prior_latlon=(math.nan, 0.0)), tmp_path / "nan.geojson")
