"""DEM files as real users have them (sim/dem.py): holes inside the area, a band's scale,
offset and vertical unit, void markers of files that declare no nodata, pictures
instead of heights, tiled and compressed files, misnamed SRTM tiles. Each checked
against the plane the file was made from, or refused in one line naming the file."""

from __future__ import annotations

import math
import re
import warnings

import numpy as np
import pytest
import rasterio
from pyproj import Transformer
from rasterio.transform import from_origin

from estimator.geodesy import ExactENU
from sim.dem import DemError, DemTerrain

LAT0, LON0, H0 = 36.7105, -4.4905, 150.0
UTM = "EPSG:32630"
RES_M, N = 20.0, 100  # a 2 km square of 20 m cells centred on the origin
SQUARE = np.array([(-300.0, -300.0), (300.0, -300.0), (300.0, 300.0), (-300.0, 300.0)])
X0, Y0 = Transformer.from_crs("EPSG:4326", UTM, always_xy=True).transform(LON0, LAT0)
WEST, NORTH = X0 - N / 2 * RES_M, Y0 + N / 2 * RES_M
TRANSFORM = from_origin(WEST, NORTH, RES_M, RES_M)


def _plane(x, y):
    """Heights (m) of a plane in UTM metres: 300 m at the origin, 5 % east, 2 % north."""
    return 300.0 + 0.05 * (x - X0) + 0.02 * (y - Y0)


def _cells():
    xs = WEST + RES_M * (np.arange(N) + 0.5)
    ys = NORTH - RES_M * (np.arange(N) + 0.5)
    return np.meshgrid(xs, ys)


def _write(path, values, *, nodata=None, scales=None, offsets=None, units=None, count=1,
           **kw):
    with rasterio.open(path, "w", driver="GTiff", width=N, height=N, count=count,
                       dtype=values.dtype, crs=UTM, transform=TRANSFORM, nodata=nodata,
                       **kw) as dst:
        for b in range(1, count + 1):
            dst.write(values, b)
        if scales:
            dst.scales = scales
        if offsets:
            dst.offsets = offsets
        if units:
            dst.units = units
    return path


def _max_error_m(dem) -> float:
    """Largest |DEM height - plane| at 200 ground points of the area (through the exact
    geodesy and pyproj, independently of the DEM's own fitted map)."""
    rng = np.random.default_rng(3)
    e, n = rng.uniform(-450, 450, 200), rng.uniform(-450, 450, 200)
    u = np.asarray(dem.height_m(e, n))
    lat, lon, h = ExactENU(LAT0, LON0, H0).to_geodetic(e, n, u)
    x, y = Transformer.from_crs("EPSG:4326", UTM, always_xy=True).transform(lon, lat)
    return float(np.max(np.abs(np.asarray(h) - _plane(np.asarray(x), np.asarray(y)))))


def _dem(path):
    return DemTerrain(path, (LAT0, LON0, H0), (-450, 450, -450, 450), margin_m=100.0)


@pytest.mark.parametrize("kind", ["decimetres", "offset", "feet", "us-feet", "tiled"])
def test_scale_offset_unit_and_tiling_give_metres(tmp_path, kind):
    """A band's declared scale, offset and unit make its values metres (without them an
    int16 file of decimetres read 10 x too high, feet 3.3 x)."""
    X, Y = _cells()
    z = _plane(X, Y)
    if kind == "decimetres":  # int16 decimetres, LZW with a horizontal predictor
        f = _write(tmp_path / "dm.tif", np.round(z * 10).astype("int16"), scales=[0.1],
                   compress="lzw", predictor=2)
    elif kind == "offset":
        f = _write(tmp_path / "off.tif", np.round((z - 100.0) * 100).astype("int16"),
                   scales=[0.01], offsets=[100.0])
    elif kind == "feet":
        f = _write(tmp_path / "ft.tif", (z / 0.3048).astype("float64"), units=["ft"])
    elif kind == "us-feet":
        f = _write(tmp_path / "usft.tif", (z * 3937.0 / 1200.0).astype("float64"),
                   units=["US survey foot"])
    else:
        f = _write(tmp_path / "tiled.tif", z.astype("float32"), tiled=True, blockxsize=32,
                   blockysize=32, compress="deflate", predictor=3)
    assert _max_error_m(_dem(f)) < 0.01


def test_an_unknown_vertical_unit_and_a_picture_are_refused(tmp_path):
    X, Y = _cells()
    z = _plane(X, Y)
    f = _write(tmp_path / "fathoms.tif", z.astype("float32"), units=["fathom"])
    with pytest.raises(DemError, match=r"^\S*fathoms.tif: band 1's heights are in 'fathom'"):
        _dem(f)
    rgb = _write(tmp_path / "shade.tif", np.zeros((N, N), dtype="uint8"), count=3)
    with pytest.raises(DemError, match=r"^\S*shade.tif: band 1 is the red of a picture"):
        _dem(rgb)
    # a local engineering CRS (a survey's own grid): no way from WGS84 to it
    local = 'LOCAL_CS["site grid",UNIT["metre",1],AXIS["X",EAST],AXIS["Y",NORTH]]'
    with rasterio.open(tmp_path / "local.tif", "w", driver="GTiff", width=N, height=N,
                       count=1, dtype="float32", crs=rasterio.crs.CRS.from_wkt(local),
                       transform=from_origin(0.0, 2000.0, RES_M, RES_M)) as dst:
        dst.write(z.astype("float32"), 1)
    with pytest.raises(DemError, match=r"^\S*local.tif: its coordinate reference system "
                                       r"\(LOCAL_CS.*cannot be reached from WGS84"):
        _dem(tmp_path / "local.tif")


@pytest.mark.parametrize("declared", [True, False])
def test_a_hole_inside_the_area_is_refused(tmp_path, declared):
    """One nodata cell well inside the area, away from its boundary: refused, at the
    hole (its four cells share the pixel at (+10, -10) m). Without a declared nodata,
    SRTM's -32768 is a void all the same."""
    X, Y = _cells()
    z = np.round(_plane(X, Y)).astype("int16")
    z[50, 50] = -9999 if declared else -32768
    f = _write(tmp_path / "holed.tif", z, nodata=-9999 if declared else None)
    dem = _dem(f)
    dem.require_polygon([(-300, -300), (-100, -300), (-100, -100)], "a corner")  # clear
    with pytest.raises(DemError, match=r"holed.tif: the area touches nodata cells at") as exc:
        dem.require_polygon(SQUARE, "the area")
    e, n = (float(v) for v in str(exc.value).rsplit("(", 1)[1].split(")")[0].split(","))
    assert abs(e - 10.0) <= 20.0 and abs(n + 10.0) <= 20.0


def test_nan_holes_and_an_area_across_the_edge(tmp_path):
    X, Y = _cells()
    z = _plane(X, Y).astype("float32")
    z[60, 40] = np.nan
    f = _write(tmp_path / "nan.tif", z)
    dem = _dem(f)
    with pytest.raises(DemError, match=r"nan.tif: the area touches nodata"):
        dem.require_polygon(SQUARE, "the area")
    # an area from the middle to 400 m beyond the east edge (1 km from the origin)
    with pytest.raises(DemError, match=r"nan.tif: the area leaves the DEM's extent at"):
        DemTerrain(f, (LAT0, LON0, H0), (0, 1400, -200, 200)).require_polygon(
            [(0, -200), (1400, -200), (1400, 200), (0, 200)], "the area")


def test_hgt_tiles_one_and_three_arc_seconds_voids_and_names(tmp_path):
    """SRTM 1" (3601 posts) and 3" (1201) tiles: a plane in post indices; a void
    (-32768) inside the area is refused; a tile renamed from its N..W.. name is refused
    with a hint."""
    for n_posts in (3601, 1201):
        j, i = np.mgrid[0:n_posts, 0:n_posts]
        per_deg = n_posts - 1
        scale = 1200.0 / per_deg  # the same metres per degree for both tiles
        vals = (100 + scale * (i + 2 * j)).round().astype(">i2")
        path = tmp_path / f"{n_posts}" / "N36W005.hgt"
        path.parent.mkdir()
        vals.tofile(path)
        dem = DemTerrain(path, (36.5, -4.5, 150.0), (-400, 400, -400, 400))
        rng = np.random.default_rng(5)
        e, n = rng.uniform(-400, 400, 100), rng.uniform(-400, 400, 100)
        u = np.asarray(dem.height_m(e, n))
        lat, lon, h = ExactENU(36.5, -4.5, 150.0).to_geodetic(e, n, u)
        col, row = (np.asarray(lon) + 5.0) * per_deg, (37.0 - np.asarray(lat)) * per_deg
        assert np.max(np.abs(np.asarray(h) - (100 + scale * (col + 2 * row)))) < 0.51
    vals[600, 600] = -32768  # the 3" tile's post at (36.5 N, 4.5 W)
    vals.tofile(path)
    with pytest.raises(DemError, match=r"N36W005.hgt: the area touches nodata"):
        DemTerrain(path, (36.5, -4.5, 150.0), (-400, 400, -400, 400)).require_polygon(
            SQUARE, "the area")
    renamed = tmp_path / "valley.hgt"
    renamed.write_bytes(path.read_bytes())
    with pytest.raises(DemError, match=r"valley.hgt: cannot read the DEM: .*must keep its "
                                       r"tile's name"):
        DemTerrain(renamed, (36.5, -4.5, 150.0), (-400, 400, -400, 400))


def test_site_valley_from_an_int16_decimetre_dem_and_a_kmz_area(tmp_path):
    """The site-valley preset with its DEM saved as tiled LZW int16 decimetres (scale
    0.1, nodata -32768) and its area as a KMZ: the same ground to the rounding (5 cm),
    the same area."""
    import shutil
    import zipfile
    from pathlib import Path

    import sim
    from sim.scenario import load_scenario

    here = Path(sim.__file__).parent / "scenarios"
    with rasterio.open(here / "site" / "valley-dem.tif") as src:
        profile, z = src.profile, src.read(1).astype(float)
    profile.update(dtype="int16", nodata=-32768, tiled=True, blockxsize=64, blockysize=64,
                   compress="lzw")
    (tmp_path / "site").mkdir()
    with rasterio.open(tmp_path / "site" / "dm.tif", "w", **profile) as dst:
        dst.write(np.round(z * 10).astype("int16"), 1)
        dst.scales = [0.1]
    with zipfile.ZipFile(tmp_path / "site" / "area.kmz", "w", zipfile.ZIP_DEFLATED) as kmz:
        kmz.write(here / "site" / "valley-area.kml", "doc.kml")
    shutil.copy(here / "site" / "valley-powerline.kml", tmp_path / "site" / "pl.kml")
    text = (here / "site-valley.toml").read_text()
    text = (text.replace('"site/valley-dem.tif"', '"site/dm.tif"')
            .replace('"site/valley-area.kml"', '"site/area.kmz"')
            .replace('"site/valley-powerline.kml"', '"site/pl.kml"'))
    assert text.count("site/dm.tif") == text.count("site/area.kmz") == 1
    (tmp_path / "valley.toml").write_text(text)
    ref, got = load_scenario("site-valley"), load_scenario(tmp_path / "valley.toml")
    assert got.search.area_enu_m == ref.search.area_enu_m
    e, n = np.meshgrid(np.linspace(-300, 500, 9), np.linspace(-200, 600, 9))
    diff = np.asarray(got.world.terrain.height_m(e, n)) - np.asarray(
        ref.world.terrain.height_m(e, n))
    assert np.max(np.abs(diff)) <= 0.05 + 1e-6


def test_a_picture_a_damaged_file_and_a_short_tile_are_refused_in_one_line(tmp_path, capsys):
    """What a user passes as --dem by mistake, each one line naming the file and what is
    wrong: a PNG screenshot (rasterio's NotGeoreferencedWarning went to stderr too), a
    tiled GeoTIFF cut short by a download (was "Read failed. See previous exception"),
    an SRTM tile rightly named but short (was told to keep its tile's name)."""
    from tests.cli import one_line, status_of

    png = tmp_path / "shot.png"
    with rasterio.open(png, "w", driver="PNG", width=8, height=8, count=1,
                       dtype="uint8") as dst:
        dst.write(np.zeros((8, 8), dtype="uint8"), 1)
    X, Y = _cells()
    full = _write(tmp_path / "full.tif", _plane(X, Y).astype("float32"), tiled=True,
                  blockxsize=16, blockysize=16, compress="deflate")
    cut = tmp_path / "cut.tif"
    cut.write_bytes(full.read_bytes()[:6000])
    tile = tmp_path / "N36W005.hgt"
    tile.write_bytes(b"\0" * 1_000_000)
    cases = [(png, "shot.png: the file declares no coordinate reference system"),
             (cut, r"cut.tif: cannot read the DEM: .*cut.tif, band 1: IReadBlock failed"),
             (tile, r"N36W005.hgt: cannot read the DEM: 1,000,000 bytes: an SRTM tile holds "
                    r"1201 x 1201 or 3601 x 3601 two-byte posts \(2,884,802 or 25,934,402 "
                    r"bytes\): a truncated download\?")]
    for path, message in cases:
        with warnings.catch_warnings(record=True) as caught:  # pytest's capture aside
            warnings.simplefilter("always")
            rc = status_of(["plan", "lawnmower", "--center", f"{LAT0},{LON0}", "--dem",
                            str(path), "-o", str(tmp_path / "m.plan")])
        assert [str(w.message) for w in caught] == []
        line = one_line(capsys)
        assert rc == 2 and re.search(f"^osa plan: \\S*{message}", line), line


def test_a_dem_clipped_to_the_areas_box_holds_the_area(tmp_path):
    """A GeoTIFF clipped to the search area's bounding box (QGIS "Clip raster by
    extent", a DEM downloaded for the area's box): its cells cover the area to their
    outer edges. It was refused: "the area leaves the DEM's extent at (-300.0, ...) m,
    36.70780 N 4.49386 W (the DEM covers latitude 36.70768..36.71331, ...)", a point
    inside the extent it gave, as only the hull of the cell centres was usable. Now in
    the outer half of an edge cell the edge value holds across the edge (bilinear along
    it); beyond the bounds is refused with the bounds; an SRTM tile's extent is its
    outermost posts (GDAL's bounds reach half a post beyond them)."""
    fr = ExactENU(LAT0, LON0, H0)
    lat, lon, _ = fr.to_geodetic(SQUARE[:, 0], SQUARE[:, 1], np.zeros(4))
    x, y = Transformer.from_crs("EPSG:4326", UTM, always_xy=True).transform(
        np.asarray(lon), np.asarray(lat))
    west, north = float(x.min()), float(y.max())
    w, h = (math.ceil((float(x.max()) - west) / RES_M), math.ceil((north - float(y.min()))
                                                                  / RES_M))
    tr = from_origin(west, north, RES_M, RES_M)
    xs, ys = west + RES_M * (np.arange(w) + 0.5), north - RES_M * (np.arange(h) + 0.5)
    z = _plane(*np.meshgrid(xs, ys))
    f = tmp_path / "clipped.tif"
    with rasterio.open(f, "w", driver="GTiff", width=w, height=h, count=1, dtype="float64",
                       crs=UTM, transform=tr) as dst:
        dst.write(z, 1)
    dem = DemTerrain(f, (LAT0, LON0, H0), (-300, 300, -300, 300))
    dem.require_polygon(SQUARE, "the area")  # was refused
    # the west-most and north-most corners lie on the bounds: index -0.5, the edge held
    for k in (int(np.argmin(x)), int(np.argmax(y))):
        e, n = SQUARE[k]
        u = float(dem.height_m(e, n))
        la, lo, hh = fr.to_geodetic(e, n, u)
        px, py = Transformer.from_crs("EPSG:4326", UTM, always_xy=True).transform(lo, la)
        col, row = ~tr @ (px, py)
        ci, cj = col - 0.5, row - 0.5
        assert min(ci, cj) == pytest.approx(-0.5, abs=1e-3)
        ci, cj = min(max(ci, 0.0), w - 1.0), min(max(cj, 0.0), h - 1.0)
        i0, j0 = min(int(ci), w - 2), min(int(cj), h - 2)
        ti, tj = ci - i0, cj - j0
        hand = ((z[j0, i0] * (1 - ti) + z[j0, i0 + 1] * ti) * (1 - tj)
                + (z[j0 + 1, i0] * (1 - ti) + z[j0 + 1, i0 + 1] * ti) * tj)
        assert float(hh) == pytest.approx(hand, abs=1e-4)
    # a cell and a half beyond the west bound: refused, outside the extent it names
    k = int(np.argmin(x))
    with pytest.raises(DemError, match=r"clipped.tif: the flight leaves the DEM's extent") as exc:
        dem.require_points([(SQUARE[k, 0] - 1.5 * RES_M, SQUARE[k, 1])], "the flight")
    west_lon = float(re.search(r"longitude (-?[\d.]+)\.\.", str(exc.value)).group(1))
    at_lon = -float(re.search(r" N ([\d.]+) W", str(exc.value)).group(1))
    assert at_lon < west_lon < float(lon[k])  # the corner held lies inside the extent named
    # an SRTM tile: its posts are its extent, whatever GDAL's half-post bounds say
    tile = tmp_path / "N36W005.hgt"
    np.full((1201, 1201), 300, dtype=">i2").tofile(tile)
    o = (36.5, -4.995, 300.0)
    srtm = DemTerrain(tile, o, (-600, 100, -100, 100))
    e_post = float(ExactENU(*o).to_enu(36.5, -5.0, 300.0)[0])
    srtm.require_points([(e_post + 0.01, 0.0)], "the start")  # on the west posts
    e_half = float(ExactENU(*o).to_enu(36.5, -5.0 - 1 / 2400, 300.0)[0])
    with pytest.raises(DemError, match=r"N36W005.hgt: the start leaves the DEM's extent at .*"
                                       r"\(the DEM covers latitude 36.00000..37.00000, "
                                       r"longitude -5.00000..-4.00000\)$"):
        srtm.require_points([(0.5 * (e_post + e_half), 0.0)], "the start")


def _hand_bilinear(path, lat, lon):
    """Bilinear of band 1 between pixel centres at (lat, lon), through rasterio's affine
    and pyproj alone (no sim.dem code): the reference the DEM's heights must equal."""
    with rasterio.open(path) as src:
        x, y = Transformer.from_crs("EPSG:4326", src.crs, always_xy=True).transform(lon, lat)
        col, row = ~src.transform @ (np.asarray(x), np.asarray(y))
        v = src.read(1).astype(float) * (src.scales[0] or 1.0) + (src.offsets[0] or 0.0)
    ci, cj = np.asarray(col) - 0.5, np.asarray(row) - 0.5
    i0, j0 = np.floor(ci).astype(int), np.floor(cj).astype(int)
    ti, tj = ci - i0, cj - j0
    return ((v[j0, i0] * (1 - ti) + v[j0, i0 + 1] * ti) * (1 - tj)
            + (v[j0 + 1, i0] * (1 - ti) + v[j0 + 1, i0 + 1] * ti) * tj)


@pytest.mark.parametrize("kind", ["utm-south", "web-mercator", "north-down", "rotated",
                                  "pixel-is-point", "geographic-south-west"])
def test_grids_as_tools_write_them_match_a_hand_bilinear(tmp_path, kind):
    """Rough random terrain in grids as GIS tools write them, sampled at 150 ground points
    and compared with a hand bilinear through rasterio's affine and pyproj: a southern UTM
    zone, Web Mercator (cells of 20 m / cos(lat)), a north-down raster (positive y pixel
    size), a geotransform rotated by 30 degrees, a PixelIsPoint int16 GeoTIFF with scale
    0.1 (posts: GDAL shifts its transform half a pixel), EPSG:4326 in the southern and
    western hemispheres."""
    from rasterio.transform import Affine

    rng = np.random.default_rng(11)
    lat0, lon0, crs, n = -22.5, 16.0, "EPSG:32733", 80
    z = 300.0 + np.cumsum(np.cumsum(rng.normal(0, 1, (n, n)), 0), 1) / 10
    tags = {}
    if kind == "geographic-south-west":
        lat0, lon0, crs, res = -33.45, -70.66, "EPSG:4326", 1 / 3600
        tr = from_origin(lon0 - n / 2 * res, lat0 + n / 2 * res, res, res)
    else:
        if kind in ("web-mercator", "pixel-is-point"):
            lat0, lon0, crs = 47.0, 15.0, "EPSG:3857" if kind == "web-mercator" else "EPSG:32633"
        x0, y0 = Transformer.from_crs("EPSG:4326", crs, always_xy=True).transform(lon0, lat0)
        res = 20.0 / math.cos(math.radians(lat0)) if kind == "web-mercator" else 20.0
        tr = from_origin(x0 - n / 2 * res, y0 + n / 2 * res, res, res)
        if kind == "north-down":
            tr = Affine(res, 0.0, x0 - n / 2 * res, 0.0, res, y0 - n / 2 * res)
        elif kind == "rotated":
            a = math.radians(30.0)
            tr = (Affine.translation(x0, y0) @ Affine.rotation(30.0)
                  @ Affine.translation(-n / 2 * res, n / 2 * res) @ Affine.scale(res, -res))
            assert tr.b != 0.0 and abs(tr.a - res * math.cos(a)) < 1e-9
        elif kind == "pixel-is-point":
            tags = {"AREA_OR_POINT": "Point"}
    f = tmp_path / f"{kind}.tif"
    dtype = "int16" if kind == "pixel-is-point" else "float32"
    data = np.round(z * 10).astype("int16") if dtype == "int16" else z.astype("float32")
    with rasterio.open(f, "w", driver="GTiff", width=n, height=n, count=1, dtype=dtype,
                       crs=crs, transform=tr, nodata=-32768 if dtype == "int16" else None,
                       tiled=True, blockxsize=16, blockysize=16, compress="deflate") as dst:
        dst.write(data, 1)
        dst.update_tags(**tags)
        if dtype == "int16":
            dst.scales = [0.1]
    origin = (lat0, lon0, 300.0)
    dem = DemTerrain(f, origin, (-300, 300, -300, 300))
    assert dem.pixel_is_point == (kind == "pixel-is-point")
    e, n_ = rng.uniform(-300, 300, 150), rng.uniform(-300, 300, 150)
    lat, lon, h = ExactENU(*origin).to_geodetic(e, n_, np.asarray(dem.height_m(e, n_)))
    hand = _hand_bilinear(f, np.asarray(lat), np.asarray(lon))
    assert np.max(np.abs(np.asarray(h) - hand)) < 1e-4
    assert np.ptp(hand) > 5.0  # rough enough that a misplaced sample would show
    if kind == "pixel-is-point":  # the file's own tie point: raster (0, 0) is a post
        X, Y = _tiepoint(f)
        assert (X, Y) == pytest.approx((tr.c + res / 2, tr.f - res / 2), abs=1e-6)
        lo, la = Transformer.from_crs(crs, "EPSG:4326", always_xy=True).transform(X, Y)
        fr = ExactENU(*origin)
        pe, pn, _ = fr.to_enu(la, lo, 300.0)
        far = DemTerrain(f, origin, (float(pe) - 5, float(pe) + 5, float(pn) - 5, float(pn) + 5))
        got = fr.to_geodetic(float(pe), float(pn), float(far.height_m(float(pe), float(pn))))
        assert float(got[2]) == pytest.approx(data[0, 0] * 0.1, abs=0.01)


def _tiepoint(path) -> tuple[float, float]:
    """(X, Y) of a classic little-endian GeoTIFF's ModelTiepointTag (raster (0, 0))."""
    import struct

    b = path.read_bytes()
    assert b[:4] == b"II*\0"
    off = struct.unpack("<I", b[4:8])[0]
    for k in range(struct.unpack("<H", b[off:off + 2])[0]):
        tag, _typ, _count, at = struct.unpack("<HHII", b[off + 2 + 12 * k:off + 14 + 12 * k])
        if tag == 33922:
            i, j, _, x, y, _ = struct.unpack("<6d", b[at:at + 48])
            assert (i, j) == (0.0, 0.0)
            return x, y
    raise AssertionError("no ModelTiepointTag")
