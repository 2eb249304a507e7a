"""DEM terrain (sim/dem.py): heights in the world's ENU frame from GeoTIFFs in a
geographic and a projected CRS and from an SRTM .hgt tile, against analytic surfaces
and an independent conversion (pyproj, rasterio's transform, the exact geodesy)."""

from __future__ import annotations

import math
import pickle

import numpy as np
import pytest
import rasterio
from pyproj import Transformer
from rasterio.transform import from_origin

from estimator.geodesy import ExactENU
from sim.dem import DemError, DemTerrain

LAT0, LON0, H0 = 36.7105, -4.4905, 150.0
UTM = "EPSG:32630"


def _write(path, values, crs, transform, nodata=None, **kw):
    h, w = values.shape
    with rasterio.open(path, "w", driver="GTiff", width=w, height=h, count=1,
                       dtype=values.dtype, crs=crs, transform=transform, nodata=nodata,
                       **kw) as dst:
        dst.write(values, 1)
    return path


def _geo_grid(res_deg=1 / 1200, n=240):
    """A geographic grid (cell centres) of n x n cells around the origin."""
    west = LON0 - n / 2 * res_deg
    north = LAT0 + n / 2 * res_deg
    lon = west + res_deg * (np.arange(n) + 0.5)
    lat = north - res_deg * (np.arange(n) + 0.5)
    return from_origin(west, north, res_deg, res_deg), *np.meshgrid(lon, lat)


def _utm_grid(res=20.0, n=200):
    x0, y0 = Transformer.from_crs("EPSG:4326", UTM, always_xy=True).transform(LON0, LAT0)
    west, north = x0 - n / 2 * res, y0 + n / 2 * res
    xs = west + res * (np.arange(n) + 0.5)
    ys = north - res * (np.arange(n) + 0.5)
    return from_origin(west, north, res, res), *np.meshgrid(xs, ys), (x0, y0)


def _ground_points(dem, rng, half=600.0, k=400):
    e = rng.uniform(-half, half, k)
    n = rng.uniform(-half, half, k)
    u = np.asarray(dem.height_m(e, n))
    lat, lon, h = ExactENU(*dem.origin).to_geodetic(e, n, u)
    return e, n, u, np.asarray(lat), np.asarray(lon), np.asarray(h)


def test_plane_in_wgs84_geotiff(tmp_path):
    tr, lon, lat = _geo_grid()
    plane = lambda la, lo: 120.0 + 9000.0 * (lo - LON0) - 7000.0 * (la - LAT0)  # noqa: E731
    f = _write(tmp_path / "plane4326.tif", plane(lat, lon).astype("float64"), "EPSG:4326", tr)
    dem = DemTerrain(f, (LAT0, LON0, H0), (-500, 500, -500, 500))
    assert dem.crs == "EPSG:4326"
    assert dem.map_error_px < 1e-3
    _, _, _, la, lo, h = _ground_points(dem, np.random.default_rng(1))
    # the ground point's ellipsoidal height is the plane's value where it lies
    assert np.max(np.abs(h - plane(la, lo))) < 1e-3


def test_quadratic_in_wgs84_geotiff_is_bilinear_between_cell_centres(tmp_path):
    tr, lon, lat = _geo_grid()
    q = lambda la, lo: 200.0 + 4e6 * (lo - LON0) ** 2 - 3e6 * (lo - LON0) * (la - LAT0)  # noqa: E731
    f = _write(tmp_path / "quad4326.tif", q(lat, lon), "EPSG:4326", tr)
    dem = DemTerrain(f, (LAT0, LON0, H0), (-500, 500, -500, 500))
    _, _, _, la, lo, h = _ground_points(dem, np.random.default_rng(6))
    col, row = ~tr @ (lo, la)
    ci, cj = np.asarray(col) - 0.5, np.asarray(row) - 0.5
    i0, j0 = np.floor(ci), np.floor(cj)
    ti, tj = ci - i0, cj - j0

    def at(i, j):
        x, y = tr @ (i + 0.5, j + 0.5)
        return q(np.asarray(y), np.asarray(x))

    hand = ((at(i0, j0) * (1 - ti) + at(i0 + 1, j0) * ti) * (1 - tj)
            + (at(i0, j0 + 1) * (1 - ti) + at(i0 + 1, j0 + 1) * ti) * tj)
    assert np.max(np.abs(h - hand)) < 1e-4
    assert np.max(np.abs(h - q(la, lo))) > 1e-3  # not the quadratic itself: bilinear


def test_plane_in_an_hgt_tile(tmp_path):
    n = 1201
    j, i = np.mgrid[0:n, 0:n]
    (100 + i + 2 * j).astype(">i2").tofile(tmp_path / "N36W005.hgt")
    dem = DemTerrain(tmp_path / "N36W005.hgt", (36.5, -4.5, 150.0), (-800, 800, -800, 800))
    _, _, _, la, lo, h = _ground_points(dem, np.random.default_rng(8), half=700.0)
    # posts every 3 arc-seconds from the tile's corner (37 N, 5 W): column, row of a post
    col, row = (lo + 5.0) * 1200.0, (37.0 - la) * 1200.0
    assert np.max(np.abs(h - (100 + col + 2 * row))) < 1e-4


def test_plane_and_quadratic_in_utm_geotiff(tmp_path):
    tr, X, Y, (x0, y0) = _utm_grid()
    plane = 95.0 + 0.04 * (X - x0) - 0.03 * (Y - y0)
    f = _write(tmp_path / "plane.tif", plane, UTM, tr)
    dem = DemTerrain(f, (LAT0, LON0, H0), (-600, 600, -600, 600))
    _, _, _, la, lo, h = _ground_points(dem, np.random.default_rng(2))
    x, y = Transformer.from_crs("EPSG:4326", UTM, always_xy=True).transform(lo, la)
    assert np.max(np.abs(h - (95.0 + 0.04 * (x - x0) - 0.03 * (y - y0)))) < 1e-3
    # a quadratic: bilinear between cell centres, exactly; within res^2 q'' / 8 of it
    q = lambda x, y: 100.0 + 2e-4 * (x - x0) ** 2 + 1e-4 * (x - x0) * (y - y0)  # noqa: E731
    f2 = _write(tmp_path / "quad.tif", q(X, Y), UTM, tr)
    dem2 = DemTerrain(f2, (LAT0, LON0, H0), (-600, 600, -600, 600))
    _, _, _, la, lo, h = _ground_points(dem2, np.random.default_rng(3))
    x, y = Transformer.from_crs("EPSG:4326", UTM, always_xy=True).transform(lo, la)
    col, row = ~tr @ (x, y)
    ci, cj = np.asarray(col) - 0.5, np.asarray(row) - 0.5  # cell-centre index coordinates
    i0, j0 = np.floor(ci), np.floor(cj)
    ti, tj = ci - i0, cj - j0

    def at(i, j):  # the cell centres' analytic values
        cx, cy = tr @ (i + 0.5, j + 0.5)
        return q(np.asarray(cx), np.asarray(cy))

    hand = ((at(i0, j0) * (1 - ti) + at(i0 + 1, j0) * ti) * (1 - tj)
            + (at(i0, j0 + 1) * (1 - ti) + at(i0 + 1, j0 + 1) * ti) * tj)
    assert np.max(np.abs(h - hand)) < 1e-4
    # bilinear error bound of x^2 over a 20 m cell: 20^2 * 2 * 2e-4 / 8 = 0.02 m
    assert 1e-3 < np.max(np.abs(h - q(x, y))) <= 0.02 + 1e-6


def test_srtm_hgt_posts_and_cell_centres(tmp_path):
    """An .hgt value sits at its post (PixelIsPoint); the same array in a GeoTIFF whose
    cells start at the tile's corner (PixelIsArea) puts it half a cell away."""
    n = 1201
    j, i = np.mgrid[0:n, 0:n]
    vals = (100 + (i * 7 + j * 3) % 50 + (i * j) % 11).astype(">i2")
    hgt = tmp_path / "N36W005.hgt"
    vals.tofile(hgt)
    lat_p, lon_p = 36.5, -4.5  # the post at row 600, column 600
    dem = DemTerrain(hgt, (lat_p, lon_p, 150.0), (-200, 200, -200, 200))
    assert dem.pixel_is_point
    # at the origin the ground lies on the origin's vertical: u = value - h0 exactly
    assert float(dem.height_m(0.0, 0.0)) == pytest.approx(vals[600, 600] - 150.0, abs=1e-6)
    # the same values as cells whose corner is the tile's corner (PixelIsArea)
    tif = _write(tmp_path / "area.tif", vals.astype("int16"), "EPSG:4326",
                 from_origin(-5.0, 37.0, 1 / 1200, 1 / 1200))
    area = DemTerrain(tif, (lat_p, lon_p, 150.0), (-200, 200, -200, 200))
    assert not area.pixel_is_point
    # the post is the corner of four cells: their mean
    assert float(area.height_m(0.0, 0.0)) == pytest.approx(
        vals[599:601, 599:601].astype(float).mean() - 150.0, abs=1e-6)
    # between posts: bilinear of the four posts around (independently through rasterio)
    e, n_, u = 37.0, -21.0, float(dem.height_m(37.0, -21.0))
    lat, lon, h = ExactENU(lat_p, lon_p, 150.0).to_geodetic(e, n_, u)
    with rasterio.open(hgt) as src:
        col, row = ~src.transform @ (lon, lat)
    ci, cj = col - 0.5, row - 0.5
    i0, j0 = math.floor(ci), math.floor(cj)
    ti, tj = ci - i0, cj - j0
    v = vals.astype(float)
    hand = ((v[j0, i0] * (1 - ti) + v[j0, i0 + 1] * ti) * (1 - tj)
            + (v[j0 + 1, i0] * (1 - ti) + v[j0 + 1, i0 + 1] * ti) * tj)
    assert h == pytest.approx(hand, abs=1e-4)


def test_datum_offset_and_the_earths_curvature(tmp_path):
    tr, X, _Y, _ = _utm_grid(res=50.0, n=200)
    flat = np.full(X.shape, H0)  # the ground at the origin's own height everywhere
    f = _write(tmp_path / "flat.tif", flat, UTM, tr)
    dem = DemTerrain(f, (LAT0, LON0, H0), (-3000, 3000, -3000, 3000))
    assert float(dem.height_m(0.0, 0.0)) == pytest.approx(0.0, abs=1e-6)
    frame = ExactENU(LAT0, LON0, H0)
    for d in (1000.0, 3000.0):
        for e, n in ((d, 0.0), (0.0, d), (0.7 * d, -0.7 * d)):
            u = float(dem.height_m(e, n))
            # below the tangent plane by ~d^2 / 2R, and exactly on the ellipsoid height H0
            r = math.hypot(e, n)
            assert u == pytest.approx(-r * r / (2 * 6.37e6), rel=0.01)
            assert frame.to_geodetic(e, n, u)[2] == pytest.approx(H0, abs=1e-4)
    off = DemTerrain(f, (LAT0, LON0, H0), (-3000, 3000, -3000, 3000), datum_offset_m=12.5)
    e = np.linspace(-2500, 2500, 11)
    assert np.allclose(np.asarray(off.height_m(e, e)) - np.asarray(dem.height_m(e, e)), 12.5,
                       atol=1e-5)
    assert off.elevation_m(100.0, -40.0) == pytest.approx(H0 + 12.5, abs=1e-6)


def test_casadi_form_numpy_forms_and_bounds(tmp_path):
    import casadi as ca

    tr, X, Y, (x0, y0) = _utm_grid(res=20.0, n=120)
    z = 100 + 30 * np.sin((X - x0) / 150.0) * np.cos((Y - y0) / 210.0)
    f = _write(tmp_path / "hills.tif", z.astype("float32"), UTM, tr)
    dem = DemTerrain(f, (LAT0, LON0, H0), (-400, 400, -400, 400))
    rng = np.random.default_rng(4)
    e, n = rng.uniform(-450, 450, (2, 200))
    arr = np.asarray(dem.height_m(e, n))
    one = np.array([dem.height_m(float(a), float(b)) for a, b in zip(e, n, strict=True)])
    assert np.max(np.abs(arr - one)) < 1e-9
    es, ns = ca.MX.sym("e"), ca.MX.sym("n")
    fn = ca.Function("h", [es, ns], [dem.height_m(es, ns)])
    sym = np.array([float(fn(a, b)) for a, b in zip(e, n, strict=True)])
    # a B-spline through the same nodes: close to the bilinear surface
    assert np.max(np.abs(sym - arr)) < 1.0
    vec = np.asarray(dem.height_m(ca.DM(e).T, ca.DM(n).T)).ravel()
    assert np.allclose(vec, sym)
    # the box bound and the sag bound hold
    E, N = np.meshgrid(np.linspace(-200, 100, 60), np.linspace(-50, 250, 60))
    assert float(np.max(dem.height_m(E, N))) <= dem.max_height_m(-200, 100, -50, 250)
    concave, convex = dem.sag_curvature()
    s = np.linspace(-300, 300, 3001)
    h = np.asarray(dem.height_m(s, 0.3 * s + 20))
    d2 = np.diff(h, 2) / ((s[1] - s[0]) ** 2 * (1 + 0.09))
    # bilinear kinks aside (slope steps at cell edges), the curvature along a line
    # averaged over two cells is bounded
    k = np.convolve(d2, np.ones(200) / 200, mode="valid")
    assert k.max() <= convex * 1.05 and -k.min() <= concave * 1.05
    back = pickle.loads(pickle.dumps(dem))
    assert np.array_equal(np.asarray(back.height_m(e, n)), arr)


def test_casadi_form_of_a_large_window_takes_every_kth_cell(tmp_path, monkeypatch):
    import casadi as ca

    import sim.dem

    tr, X, Y, (x0, y0) = _utm_grid(res=20.0, n=120)
    z = 100 + 30 * np.sin((X - x0) / 150.0) * np.cos((Y - y0) / 210.0)
    f = _write(tmp_path / "hills.tif", z, UTM, tr)
    monkeypatch.setattr(sim.dem, "CASADI_MAX_CELLS", 1000)  # the window: ~2500 cells
    dem = DemTerrain(f, (LAT0, LON0, H0), (-400, 400, -400, 400))
    es, ns = ca.MX.sym("e"), ca.MX.sym("n")
    fn = ca.Function("h", [es, ns], [dem.height_m(es, ns)])
    e, n = np.random.default_rng(5).uniform(-400, 400, (2, 100))
    sym = np.array([float(fn(a, b)) for a, b in zip(e, n, strict=True)])
    # a smooth 30 m surface through every 2nd cell (40 m): within a metre of the bilinear
    assert np.max(np.abs(sym - np.asarray(dem.height_m(e, n)))) < 1.0


def test_only_the_window_is_read_from_a_huge_file(tmp_path):
    """A 100 000 x 100 000 GeoTIFF (40 GB as float32, sparse: only the scenario's blocks
    are written) is read through a small window."""
    res = 1.0
    x0, y0 = Transformer.from_crs("EPSG:4326", UTM, always_xy=True).transform(LON0, LAT0)
    west, north = x0 - 50_000.0, y0 + 50_000.0
    path = tmp_path / "huge.tif"
    with rasterio.open(path, "w", driver="GTiff", width=100_000, height=100_000, count=1,
                       dtype="float32", crs=UTM, transform=from_origin(west, north, res, res),
                       tiled=True, blockxsize=256, blockysize=256, compress="deflate",
                       sparse_ok=True, nodata=-9999.0, BIGTIFF="YES") as dst:
        from rasterio.windows import Window

        win = Window(50_000 - 256, 50_000 - 256, 512, 512)  # data: +-256 m about the origin
        cols, rows = np.meshgrid(np.arange(512) + win.col_off, np.arange(512) + win.row_off)
        vals = 100.0 + 0.01 * (cols - 50_000) + 0.02 * (rows - 50_000)
        dst.write(vals.astype("float32"), 1, window=win)
    assert path.stat().st_size < 50_000_000
    dem = DemTerrain(path, (LAT0, LON0, H0), (-200, 200, -200, 200), margin_m=200.0)
    assert dem.file_shape == (100_000, 100_000)
    assert dem.values_m.shape[0] * dem.values_m.shape[1] < 1000 * 1000
    u = float(dem.height_m(0.0, 0.0))
    col, row = ~from_origin(west, north, res, res) @ (x0, y0)
    expect = 100.0 + 0.01 * (col - 0.5 - 50_000) + 0.02 * (row - 0.5 - 50_000)
    assert u + H0 == pytest.approx(expect, abs=1e-3)
    # a scenario box beyond the written blocks touches nodata: refused, naming the file
    with pytest.raises(DemError, match=r"huge.tif: the area touches nodata"):
        dem.require_polygon([(-100, -100), (350, -100), (350, 100)], "the area")
    # beyond the window limit: refused before anything is read
    with pytest.raises(DemError, match=r"huge.tif: the scenario needs .* cells"):
        DemTerrain(path, (LAT0, LON0, H0), (-5000, 5000, -5000, 5000))


def test_refusals_name_the_file(tmp_path):
    tr, X, _Y, _ = _utm_grid(res=20.0, n=60)  # 1.2 km square
    z = np.full(X.shape, 100.0, dtype="float32")
    z[:10, :10] = -9999.0
    f = _write(tmp_path / "small.tif", z, UTM, tr, nodata=-9999.0)
    dem = DemTerrain(f, (LAT0, LON0, H0), (-300, 300, -300, 300))
    dem.require_points([(0.0, 0.0), (200.0, -200.0)], "the start")
    with pytest.raises(DemError, match=r"small.tif: the flight leaves the DEM's extent"):
        dem.require_points([(0.0, 0.0), (900.0, 0.0)], "the flight")
    with pytest.raises(DemError, match=r"small.tif: the search area touches nodata"):
        dem.require_polygon([(-560, 560), (-300, 560), (-300, 300)], "the search area")
    with pytest.raises(DemError, match=r"small.tif: the scenario's area lies outside"):
        DemTerrain(f, (LAT0, LON0, H0), (5000, 6000, 5000, 6000))
    bad = tmp_path / "bad.tif"
    bad.write_bytes(b"not a tiff")
    with pytest.raises(DemError, match=r"bad.tif: cannot read the DEM"):
        DemTerrain(bad, (LAT0, LON0, H0), (0, 1, 0, 1))
    nocrs = _write(tmp_path / "nocrs.tif", z, None, tr)
    with pytest.raises(DemError, match=r"nocrs.tif: the file declares no coordinate"):
        DemTerrain(nocrs, (LAT0, LON0, H0), (0, 1, 0, 1))
