"""``osa plan`` on a site: an area and keep-outs from files, heights over a rough DEM,
the altitude frames, KML; every leg checked as an autopilot flies it (straight between
the items), the DEM sampled independently (rasterio, pyproj)."""

from __future__ import annotations

import itertools
import json
import math
import xml.etree.ElementTree as ET

import numpy as np
import pytest
import rasterio
from pyproj import Transformer
from rasterio.transform import from_origin

from envs.cli import main
from estimator.geodesy import ExactENU
from planner.files import read_mission
from planner.mission import (
    MAV_CMD_NAV_TAKEOFF,
    MAV_CMD_NAV_WAYPOINT,
    MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
    MAV_FRAME_GLOBAL_TERRAIN_ALT_INT,
)
from sim.sitefiles import read_area, read_keepouts

LAT0, LON0 = 36.7105, -4.4905
UTM = "EPSG:32630"
AGL = 40.0
TOWER_EN, TOWER_R = (120.0, 60.0), 20.0


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    d = tmp_path_factory.mktemp("site")
    to_utm = Transformer.from_crs("EPSG:4326", UTM, always_xy=True)
    x0, y0 = to_utm.transform(LON0, LAT0)
    res, n = 10.0, 200
    west, north = x0 - n / 2 * res, y0 + n / 2 * res
    X, Y = np.meshgrid(west + res * (np.arange(n) + 0.5), north - res * (np.arange(n) + 0.5))
    rng = np.random.default_rng(7)
    rough = (300.0 + 45.0 * np.sin((X - x0) / 70.0) * np.cos((Y - y0) / 95.0)
             + 0.25 * (X - x0) + 30.0 * np.tanh((Y - y0 - 80.0) / 15.0)
             + rng.normal(0.0, 2.5, X.shape))
    dem = d / "rough.tif"
    with rasterio.open(dem, "w", driver="GTiff", width=n, height=n, count=1, dtype="float32",
                       crs=UTM, transform=from_origin(west, north, res, res)) as dst:
        dst.write(rough.astype("float32"), 1)
    frame = ExactENU(LAT0, LON0, 0.0)

    def deg(en):
        lat, lon, _ = frame.to_geodetic(np.array([p[0] for p in en], dtype=float),
                                        np.array([p[1] for p in en], dtype=float),
                                        np.zeros(len(en)))
        return list(zip(np.atleast_1d(lat).tolist(), np.atleast_1d(lon).tolist(), strict=True))

    area_en = [(-250.0, -200.0), (300.0, -200.0), (300.0, 220.0), (0.0, 250.0), (-250.0, 100.0)]
    ring = " ".join(f"{lo!r},{la!r},0" for la, lo in [*deg(area_en), deg(area_en)[0]])
    area = d / "area.kml"
    area.write_text('<?xml version="1.0"?><kml xmlns="http://www.opengis.net/kml/2.2">'
                    "<Document><Placemark><name>area</name><Polygon><outerBoundaryIs>"
                    f"<LinearRing><coordinates>{ring}</coordinates></LinearRing>"
                    "</outerBoundaryIs></Polygon></Placemark></Document></kml>",
                    encoding="utf-8")
    (tlat, tlon), = deg([TOWER_EN])
    wires = deg([(-300.0, -60.0), (350.0, -60.0), (350.0, -40.0), (-300.0, -40.0)])
    keep = d / "keep.geojson"
    keep.write_text(json.dumps({"type": "FeatureCollection", "features": [
        {"type": "Feature", "properties": {"name": "tower", "radius_m": TOWER_R, "top_m": 60},
         "geometry": {"type": "Point", "coordinates": [tlon, tlat]}},
        {"type": "Feature", "properties": {"name": "wires", "top_m": 15},
         "geometry": {"type": "Polygon",
                      "coordinates": [[[lo, la] for la, lo in [*wires, wires[0]]]]}},
    ]}), encoding="utf-8")
    return {"dir": d, "dem": str(dem), "area": str(area), "keep": str(keep),
            "ground": _ground_of(dem), "area_en": area_en, "frame": frame}


def _ground_of(dem):
    """The DEM's height at (lat, lon) arrays: bilinear between cell centres, by hand."""
    with rasterio.open(dem) as src:
        heights, inv = src.read(1).astype(float), ~src.transform
        to_crs = Transformer.from_crs("EPSG:4326", src.crs, always_xy=True)

    def ground(lat, lon):
        x, y = to_crs.transform(np.asarray(lon), np.asarray(lat))
        c, r = inv @ (np.asarray(x), np.asarray(y))
        ci, cj = np.asarray(c) - 0.5, np.asarray(r) - 0.5
        i0, j0 = np.floor(ci).astype(int), np.floor(cj).astype(int)
        ti, tj = ci - i0, cj - j0
        h = heights
        return ((h[j0, i0] * (1 - ti) + h[j0, i0 + 1] * ti) * (1 - tj)
                + (h[j0 + 1, i0] * (1 - ti) + h[j0 + 1, i0 + 1] * ti) * tj)

    return ground


def _legs(mission, home_h, step_m=0.5):
    """(lat, lon, absolute height) every ~``step_m`` along the straight legs between the
    positioned items (takeoff at home, then the waypoints), as an autopilot flies them."""
    items = [it for it in mission.items if it.command in (MAV_CMD_NAV_TAKEOFF,
                                                          MAV_CMD_NAV_WAYPOINT)]

    def absolute(it):
        return home_h + it.alt_m if it.frame == MAV_FRAME_GLOBAL_RELATIVE_ALT_INT else it.alt_m

    out = []
    for a, b in itertools.pairwise(items):
        d = math.hypot((b.lat_deg - a.lat_deg) * 111_000.0, (b.lon_deg - a.lon_deg) * 89_000.0)
        f = np.linspace(0.0, 1.0, max(2, int(d / step_m) + 2))
        out.append(np.column_stack([a.lat_deg + f * (b.lat_deg - a.lat_deg),
                                    a.lon_deg + f * (b.lon_deg - a.lon_deg),
                                    absolute(a) + f * (absolute(b) - absolute(a))]))
    return np.vstack(out)


def test_lawnmower_over_a_rough_dem_covers_the_polygon_and_keeps_its_height(site, capsys):
    out = site["dir"] / "mower.plan"
    rc = main(["plan", "lawnmower", "--area", site["area"], "--keepout", site["keep"],
               "--dem", site["dem"], "--agl", str(AGL), "--spacing", "60", "--speed", "8",
               "-o", str(out)])
    text = capsys.readouterr().out
    assert rc == 0, text
    m = read_mission(out)
    home_h = m.home[2]
    assert home_h == pytest.approx(float(site["ground"](m.home[0], m.home[1])), abs=0.01)
    pts = _legs(m, home_h)
    agl = pts[:, 2] - site["ground"](pts[:, 0], pts[:, 1])
    assert agl.min() >= AGL - 2.0 - 0.02 and agl.max() <= AGL + 25.0 + 0.02
    # items were added where the ground changes: inside straight tracks, not at corners
    wps = [it for it in m.items if it.command == MAV_CMD_NAV_WAYPOINT]
    assert all(it.frame == MAV_FRAME_GLOBAL_RELATIVE_ALT_INT for it in wps)
    ll = np.array([[w.lat_deg, w.lon_deg * math.cos(math.radians(LAT0))] for w in wps])
    d1, d2 = ll[1:-1] - ll[:-2], ll[2:] - ll[1:-1]
    cross = np.abs(d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0])
    straight = cross < 1e-3 * np.linalg.norm(d1, axis=1) * np.linalg.norm(d2, axis=1)
    assert straight.sum() >= 10
    # the polygon, not its bounding square: every waypoint inside the area
    frame = site["frame"]
    e, n, _ = frame.to_enu(np.array([w.lat_deg for w in wps]),
                           np.array([w.lon_deg for w in wps]), np.zeros(len(wps)))
    from estimator.geometry import signed_distance_to_polygon_m

    assert signed_distance_to_polygon_m(site["area_en"], np.column_stack([e, n])).max() < 0
    # the tower (top 60 m) is avoided; the wires (top 15 m + 10 m < 38 m) flown over
    le, ln, _ = frame.to_enu(pts[:, 0], pts[:, 1], np.zeros(len(pts)))
    assert np.hypot(le - TOWER_EN[0], ln - TOWER_EN[1]).min() > TOWER_R
    over = (ln > -60.0) & (ln < -40.0)
    assert over.any() and agl[over].min() > 15.0
    # the summary: the heights above the DEM along the legs and the flight time
    lo, hi = (float(v) for v in text.split("  ground    ")[1].split(" m above")[0].split(" to "))
    assert lo == pytest.approx(agl.min(), abs=0.1) and hi == pytest.approx(agl.max(), abs=0.1)
    assert "1 avoided, 1 flown over" in text and "min home to home" in text
    # the fence: the area (inclusion), the tower (exclusion circle); the wires are not fenced
    assert [p.inclusion for p in m.polygons] == [True] and len(m.circles) == 1


@pytest.mark.parametrize("pattern", ["lawnmower", "helix"])
def test_cliffs_of_a_one_metre_lidar_dem(tmp_path, pattern, capsys):
    """A 1 m GeoTIFF with cliffs (25 m, one across the tracks and one diagonal to them)
    and a 60 m quarry wall: every leg within [M - 2, M + 25] of the DEM, sampled every
    5 cm by hand (a lawnmower's legs dipped to 26.3 m above it, cut into a cliff's
    edge; a helix climbing its default 30 m rose beyond M + 25). The helix's climb
    beyond the band is held in it, with a warning."""
    to_utm = Transformer.from_crs("EPSG:4326", UTM, always_xy=True)
    x0, y0 = to_utm.transform(LON0, LAT0)
    n = 600
    X, Y = np.meshgrid(np.arange(n) + 0.5 - n / 2, n / 2 - np.arange(n) - 0.5)
    z = (400.0 + 25.0 * (X > 60.3) + 25.0 * (X + Y > 140.7) + 60.0 * (Y < -150.2)
         + 30.0 * np.exp(-((X + 80.0) / 20.0) ** 2))
    dem = tmp_path / "lidar.tif"
    with rasterio.open(dem, "w", driver="GTiff", width=n, height=n, count=1, dtype="float32",
                       crs=UTM, transform=from_origin(x0 - n / 2, y0 + n / 2, 1.0, 1.0),
                       tiled=True, blockxsize=256, blockysize=256, compress="deflate") as dst:
        dst.write(z.astype("float32"), 1)
    frame = ExactENU(LAT0, LON0, 0.0)
    ring = [frame.to_geodetic(e, n_, 0.0)[:2] for e, n_ in
            [(-200.0, -200.0), (200.0, -200.0), (200.0, 200.0), (-200.0, 200.0)]]
    area = tmp_path / "area.geojson"
    area.write_text(json.dumps({"type": "Polygon", "coordinates": [
        [[float(lo), float(la)] for la, lo in [*ring, ring[0]]]]}), encoding="utf-8")
    out = tmp_path / f"{pattern}.plan"
    extra = (["--spacing", "45"] if pattern == "lawnmower"
             else ["--center", f"{LAT0},{LON0 + 0.0007}", "--radius", "60"])
    rc = main(["plan", pattern, "--area", str(area), "--dem", str(dem), "--agl", str(AGL),
               *extra, "-o", str(out)])
    err = capsys.readouterr().err
    assert rc == 0, err
    assert ("held within 38 to 65 m above the DEM" in err) == (pattern == "helix")
    m = read_mission(out)
    pts = _legs(m, m.home[2], step_m=0.05)
    agl = pts[:, 2] - _ground_of(dem)(pts[:, 0], pts[:, 1])
    assert agl.min() >= AGL - 2.0 and agl.max() <= AGL + 25.0


def test_legs_outside_the_band_are_refused_not_written(site, monkeypatch, capsys):
    """The last check: legs that leave [M - 2, M + 25] above the DEM (here a follower
    that flies the pattern flat at M above home) are refused, status 1, no file."""
    import planner.terrain_follow

    def flat(path, targets, terrain, **kw):
        return np.column_stack([path, targets])

    monkeypatch.setattr(planner.terrain_follow, "follow_terrain", flat)
    out = site["dir"] / "flat.plan"
    rc = main(["plan", "lawnmower", "--area", site["area"], "--dem", site["dem"],
               "--agl", str(AGL), "--spacing", "80", "-o", str(out)])
    err = capsys.readouterr().err
    assert rc == 1 and err.count("\n") == 1, err
    assert "m above the DEM, outside 38 to 65: not flyable as planned" in err
    assert not out.exists()


def test_an_area_across_the_antimeridian(tmp_path, capsys):
    """A 440 x 330 m area in Fiji across 180 degrees of longitude (vertices at 179.998 E
    and 179.998 W): planned there, not about the mean of its longitudes (0, on the far
    side of the Earth, where the mission was written)."""
    lat0 = -16.5
    ring = [[179.998, lat0 - 0.0015], [-179.998, lat0 - 0.0015], [-179.998, lat0 + 0.0015],
            [179.998, lat0 + 0.0015], [179.998, lat0 - 0.0015]]
    area = tmp_path / "fiji.geojson"
    area.write_text(json.dumps({"type": "Polygon", "coordinates": [ring]}), encoding="utf-8")
    out = tmp_path / "fiji.plan"
    rc = main(["plan", "lawnmower", "--area", str(area), "--spacing", "60", "-o", str(out)])
    assert rc == 0, capsys.readouterr().err
    m = read_mission(out)
    wps = [it for it in m.items if it.command == MAV_CMD_NAV_WAYPOINT]
    lat = np.array([m.home[0], *(w.lat_deg for w in wps)])
    lon = np.array([m.home[1], *(w.lon_deg for w in wps)])
    assert np.all(np.abs(lat - lat0) < 0.0015) and np.all(np.abs(lon) > 179.998)
    assert (lon > 0).any() and (lon < 0).any()  # both sides of the line are swept


@pytest.mark.parametrize("frame", ["amsl", "terrain"])
def test_altitude_frames(site, frame, capsys):
    out = site["dir"] / f"x-{frame}.plan"
    rc = main(["plan", "expanding-square", "--area", site["area"], "--dem", site["dem"],
               "--agl", str(AGL), "--alt-frame", frame, "--spacing", "80",
               "--home", f"{LAT0},{LON0}", "-o", str(out)])
    assert rc == 0, capsys.readouterr().err
    m = read_mission(out)
    wps = [it for it in m.items if it.command == MAV_CMD_NAV_WAYPOINT]
    g = site["ground"](np.array([w.lat_deg for w in wps]), np.array([w.lon_deg for w in wps]))
    alt = np.array([w.alt_m for w in wps])
    if frame == "amsl":  # frame 0: the DEM's datum
        assert {w.frame for w in wps} == {0}
        agl = alt - g
        pts = _legs(m, 0.0)
        a = pts[:, 2] - site["ground"](pts[:, 0], pts[:, 1])
        assert a.min() >= AGL - 2.02 and a.max() <= AGL + 25.02
    else:  # frame 11: above the terrain at the item
        assert {w.frame for w in wps} == {MAV_FRAME_GLOBAL_TERRAIN_ALT_INT}
        agl = alt
    assert np.all(agl >= AGL - 2.02) and np.all(agl <= AGL + 25.02)
    # the first item is home, at the wanted height above its ground
    assert (wps[0].lat_deg, wps[0].lon_deg) == pytest.approx((LAT0, LON0), abs=1e-7)
    assert agl[0] == pytest.approx(AGL, abs=0.01)


@pytest.mark.parametrize("frame", ["relative", "terrain", "amsl"])
def test_kml_output_for_google_earth(site, frame, capsys):
    """Absolute altitudes whatever the mission's frame when the DEM is known (frame 11
    items were drawn relativeToGround: each vertex at M over the ground)."""
    out = site["dir"] / f"mission-{frame}.kml"
    rc = main(["plan", "lawnmower", "--area", site["area"], "--keepout", site["keep"],
               "--dem", site["dem"], "--agl", str(AGL), "--spacing", "80",
               "--alt-frame", frame, "-o", str(out)])
    assert rc == 0, capsys.readouterr().err
    root = ET.parse(out).getroot()
    ns = {"k": "http://www.opengis.net/kml/2.2"}
    line = root.find(".//k:LineString", ns)
    assert line.find("k:altitudeMode", ns).text == "absolute"
    coords = [tuple(map(float, c.split(","))) for c in line.find("k:coordinates", ns).text.split()]
    lon, lat, alt = np.array(coords).T
    agl = alt - site["ground"](lat, lon)
    assert agl[1:].min() >= AGL - 2.02 and agl.max() <= AGL + 25.02
    names = [p.find("k:name", ns).text for p in root.iter(f"{{{ns['k']}}}Placemark")]
    assert names[:3] == ["mission", "home", "search area"] and {"tower", "wires"} <= set(names)
    # the KML reads back as a site file: as --area its search area, as --keepout its
    # keep-outs with their tops, never the search area (which read as a keep-out made a
    # re-plan from the file fail: "lawnmower path enters keep-out 0 (a polygon)")
    shapes = read_keepouts(out)
    tops = sorted(s.top_m for s in shapes if s.top_m is not None)
    assert tops == [15.0, 60.0]
    assert [s.name for s in shapes] == names[3:]
    area = read_area(site["area"])
    assert len(area) == 5
    assert np.max(np.abs(np.array(read_area(out)) - np.array(area))) < 1e-7
    if frame == "relative":  # and plans again from itself alone
        again = site["dir"] / "again.kml"
        rc = main(["plan", "lawnmower", "--area", str(out), "--keepout", str(out), "--dem",
                   site["dem"], "--agl", str(AGL), "--spacing", "80", "-o", str(again)])
        assert rc == 0, capsys.readouterr().err
        assert read_keepouts(again) == read_keepouts(out)


@pytest.mark.parametrize(("extra", "needle"), [
    (["--area", "nowhere.kml"], "nowhere.kml: cannot read"),
    (["--area", "AREA", "--keepout", "nowhere.geojson"], "nowhere.geojson: cannot read"),
    (["--area", "AREA", "--dem", "nowhere.tif"], "nowhere.tif: cannot read the DEM"),
    (["--area", "AREA", "--agl", "40"], "--agl needs --dem"),
    (["--area", "AREA", "--alt-frame", "amsl"], "--alt-frame amsl needs --dem"),
    (["--dem", "DEM"], "give --center LAT,LON or --area FILE"),
    (["--area", "BIG", "--dem", "DEM"], "the area leaves the DEM's extent"),
])
def test_site_refusals_are_one_line_and_status_2(site, extra, needle, capsys, tmp_path):
    big = tmp_path / "big.geojson"
    big.write_text(json.dumps({"type": "Feature", "properties": {}, "geometry": {
        "type": "Polygon", "coordinates": [[[-4.50, 36.70], [-4.47, 36.70], [-4.47, 36.72],
                                            [-4.50, 36.70]]]}}), encoding="utf-8")
    repl = {"AREA": site["area"], "DEM": site["dem"], "BIG": str(big)}
    argv = ["plan", "lawnmower", "-o", str(tmp_path / "x.plan"),
            *[repl.get(a, a) for a in extra]]
    rc = main(argv)
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1 and needle in err, err
    assert not (tmp_path / "x.plan").exists()


@pytest.mark.parametrize("pattern", ["optimal", "helix"])
def test_home_beyond_the_dem_is_refused_for_every_pattern(site, pattern, capsys, tmp_path):
    """--home 1.3 km east of the origin, beyond the 2 km DEM: exit 2 naming the file (the
    optimal pattern planned from the DEM's edge height held there instead: "no feasible
    plan: ... height above terrain -510.27..54.71 m", exit 1)."""
    rc = main(["plan", pattern, "--dem", site["dem"], "--agl", str(AGL),
               "--center", f"{LAT0},{LON0 + 0.008}", "--radius", "700",
               "--home", f"{LAT0},{LON0 + 0.0145}", "-o", str(tmp_path / "x.plan")])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1, err
    assert "rough.tif: --home leaves the DEM's extent at (0.0, 0.0) m" in err


@pytest.mark.parametrize("home", [None, f"{LAT0},{LON0},612.5"])
def test_kml_without_a_dem(site, home, capsys, tmp_path):
    """No DEM: the path is absolute, as site.md fixes (ALT + the relative altitude;
    without --home's ALT, home's height is unknown and taken as 0 m)."""
    out = tmp_path / "m.kml"
    rc = main(["plan", "lawnmower", "--area", site["area"], "--spacing", "80",
               *(["--home", home] if home else []), "-o", str(out)])
    assert rc == 0, capsys.readouterr().err
    ns = {"k": "http://www.opengis.net/kml/2.2"}
    line = ET.parse(out).getroot().find(".//k:LineString", ns)
    alt = np.array([float(c.split(",")[2]) for c in line.find("k:coordinates", ns).text.split()])
    mode = line.find("k:altitudeMode", ns).text
    assert mode == "absolute"
    if home is None:
        assert alt[0] == 0.0 and np.allclose(alt[1:], 45.0, atol=0.01)
    else:
        assert alt[0] == 612.5
        assert np.allclose(alt[1:], 612.5 + 45.0, atol=0.01)


@pytest.mark.parametrize("case", ["edge", "void"])
def test_a_path_beyond_the_dem_or_over_a_void_is_refused(site, case, capsys, tmp_path):
    """A helix of 50 m about a --center 25 m inside the DEM's east edge, or about the
    origin over a void (nodata 40-60 m east): exit 2 naming the file (it was planned
    over the edge's heights held beyond it, or over the void filled from around it)."""
    dem = site["dem"]
    lon = LON0 + 975.0 / 89_230.0
    if case == "void":
        with rasterio.open(dem) as src:
            profile, z = src.profile, src.read(1)
        z[98:102, 104:106] = -9999.0  # rows about the origin, columns 40-60 m east
        profile.update(nodata=-9999.0)
        dem = tmp_path / "void.tif"
        with rasterio.open(dem, "w", **profile) as dst:
            dst.write(z, 1)
        lon = LON0
    rc = main(["plan", "helix", "--dem", str(dem), "--agl", str(AGL), "--center",
               f"{LAT0},{lon}", "--radius", "50", "-o", str(tmp_path / "x.plan")])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1, err
    want = ("rough.tif: the path leaves the DEM's extent at" if case == "edge"
            else "void.tif: the path touches nodata cells at")
    assert want in err, err
    assert not (tmp_path / "x.plan").exists()
