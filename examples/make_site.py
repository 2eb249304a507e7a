"""Write the site of the ``site-valley`` presets: a DEM of a hilly valley, a search area
and a power line, as an operator would have them (GeoTIFF, KML). Deterministic.

The valley runs south-west to north-east near the paper's site (36.71 N, 4.48 W), in
UTM zone 30N (EPSG:32630), 10 m cells, heights above mean sea level (the presets add
the geoid's ~51 m with ``datum_offset_m``). A spur of the north-west slope reaches into
the valley and hides the north-east part of the search area from the take-off point.
A power line crosses the valley: six towers (circles of 15 m, 40 m high) and the
corridor of its wires (40 m wide, 25 m high). Run::

    python examples/make_site.py                 # writes sim/scenarios/site/
    python examples/make_site.py -o DIR          # anywhere else

The files are small (the DEM ~150 kB) and committed; the presets and tests read them.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np

from estimator.geodesy import ExactENU

ORIGIN_LAT, ORIGIN_LON = 36.7105, -4.4905  # the take-off point (ENU origin of the presets)
GEOID_M = 51.0  # ellipsoid minus mean sea level near Malaga (EGM2008, ~51 m)
CRS = "EPSG:32630"  # UTM zone 30N
CELL_M = 10.0
CELLS = 260  # 2.6 km x 2.6 km
VALLEY_DEG = 40.0  # the valley's axis, degrees from east (south-west to north-east)
LINE_A_M = 150.0  # the power line crosses the valley (and the area) here (along-valley)
TOWERS_C_M = (-625.0, -375.0, -125.0, 125.0, 375.0, 625.0)  # across-valley places of its towers
TOWER_RADIUS_M, TOWER_TOP_M = 15.0, 40.0
CORRIDOR_HALF_M, CORRIDOR_TOP_M = 20.0, 25.0
# the search area in (along, across) metres about the take-off point
AREA_AC_M = ((-120.0, -260.0), (760.0, -260.0), (840.0, 40.0), (640.0, 260.0),
             (20.0, 260.0), (-120.0, 120.0))


def axes() -> tuple[np.ndarray, np.ndarray]:
    """Unit vectors along and across the valley (east, north)."""
    t = math.radians(VALLEY_DEG)
    return np.array([math.cos(t), math.sin(t)]), np.array([-math.sin(t), math.cos(t)])


def to_en(a_m, c_m) -> np.ndarray:
    """(along, across) -> (east, north) about the take-off point."""
    along, across = axes()
    a, c = np.asarray(a_m, dtype=float), np.asarray(c_m, dtype=float)
    return a[..., None] * along + c[..., None] * across


def height_amsl_m(e_m: np.ndarray, n_m: np.ndarray) -> np.ndarray:
    """The valley's ground, metres above mean sea level, at ENU (e, n) of the take-off
    point (deterministic: a few smooth shapes and sinusoids)."""
    along, across = axes()
    a = e_m * along[0] + n_m * along[1]
    c = e_m * across[0] + n_m * across[1]
    floor = 95.0 + 0.025 * a  # the valley floor rises gently to the north-east
    walls = 170.0 * (1.0 - np.exp(-((c + 60.0) / 480.0) ** 2))
    # the spur: a ridge from the north-west slope into the valley, ~50 m above its floor
    spur = 52.0 * np.exp(-((a - 330.0) / 120.0) ** 2) / (1.0 + np.exp(-(c - 60.0) / 70.0))
    texture = (3.0 * np.sin(e_m / 97.0 + 0.3) * np.cos(n_m / 131.0 - 1.1)
               + 2.0 * np.sin((e_m + 2.0 * n_m) / 173.0 + 2.0))
    return floor + walls + spur + texture


def write_dem(path: Path) -> tuple[float, float]:
    """The GeoTIFF (float32, DEFLATE, UTM 30N); returns the take-off point's UTM x, y."""
    import rasterio
    from pyproj import Transformer
    from rasterio.transform import from_origin

    to_utm = Transformer.from_crs("EPSG:4326", CRS, always_xy=True)
    x0, y0 = to_utm.transform(ORIGIN_LON, ORIGIN_LAT)
    west = math.floor(x0 / CELL_M) * CELL_M - CELLS * CELL_M / 2
    north = math.floor(y0 / CELL_M) * CELL_M + CELLS * CELL_M / 2
    # cell centres -> WGS84 -> ENU of the take-off point -> the valley's height
    xs = west + CELL_M * (np.arange(CELLS) + 0.5)
    ys = north - CELL_M * (np.arange(CELLS) + 0.5)
    X, Y = np.meshgrid(xs, ys)
    lon, lat = Transformer.from_crs(CRS, "EPSG:4326", always_xy=True).transform(X, Y)
    e, n, _ = ExactENU(ORIGIN_LAT, ORIGIN_LON, 0.0).to_enu(lat, lon, np.zeros_like(lat))
    h = np.round(height_amsl_m(np.asarray(e), np.asarray(n)), 1).astype("float32")
    profile = dict(driver="GTiff", width=CELLS, height=CELLS, count=1, dtype="float32",
                   crs=CRS, transform=from_origin(west, north, CELL_M, CELL_M),
                   compress="deflate", predictor=3, nodata=-9999.0)
    with rasterio.open(path, "w", **profile) as dst:
        dst.write(h, 1)
        dst.update_tags(AREA_OR_POINT="Area")
    return x0, y0


def _kml_coords(en: np.ndarray) -> str:
    lat, lon, _ = ExactENU(ORIGIN_LAT, ORIGIN_LON, 0.0).to_geodetic(
        en[:, 0], en[:, 1], np.zeros(len(en)))
    ring = [f"{lo:.7f},{la:.7f},0" for la, lo in zip(np.atleast_1d(lat), np.atleast_1d(lon),
                                                     strict=True)]
    return " ".join([*ring, ring[0]]) if len(ring) > 1 else ring[0]


def _kml(name: str, placemarks: list[str]) -> str:
    body = "\n".join(placemarks)
    return ('<?xml version="1.0" encoding="UTF-8"?>\n'
            '<kml xmlns="http://www.opengis.net/kml/2.2">\n<Document>\n'
            f"<name>{name}</name>\n{body}\n</Document>\n</kml>\n")


def _polygon(name: str, en: np.ndarray, top_m: float | None = None) -> str:
    ext = (f'<ExtendedData><Data name="top_m"><value>{top_m:g}</value></Data></ExtendedData>'
           if top_m is not None else "")
    return (f"<Placemark><name>{name}</name>{ext}<Polygon><outerBoundaryIs><LinearRing>"
            f"<coordinates>{_kml_coords(en)}</coordinates></LinearRing></outerBoundaryIs>"
            "</Polygon></Placemark>")


def _tower(name: str, en: np.ndarray) -> str:
    return (f"<Placemark><name>{name}</name><ExtendedData>"
            f'<Data name="radius_m"><value>{TOWER_RADIUS_M:g}</value></Data>'
            f'<Data name="top_m"><value>{TOWER_TOP_M:g}</value></Data></ExtendedData>'
            f"<Point><coordinates>{_kml_coords(en[None, :])}</coordinates></Point>"
            "</Placemark>")


def write_site(folder: Path) -> list[Path]:
    folder.mkdir(parents=True, exist_ok=True)
    dem = folder / "valley-dem.tif"
    write_dem(dem)
    area = folder / "valley-area.kml"
    en = to_en([p[0] for p in AREA_AC_M], [p[1] for p in AREA_AC_M])
    area.write_text(_kml("site-valley search area", [_polygon("search area", en)]),
                    encoding="utf-8")
    line = folder / "valley-powerline.kml"
    towers = [_tower(f"tower {k + 1}", to_en(LINE_A_M, c)) for k, c in enumerate(TOWERS_C_M)]
    c0, c1 = TOWERS_C_M[0] - 150.0, TOWERS_C_M[-1] + 150.0
    corridor = to_en([LINE_A_M - CORRIDOR_HALF_M, LINE_A_M + CORRIDOR_HALF_M,
                      LINE_A_M + CORRIDOR_HALF_M, LINE_A_M - CORRIDOR_HALF_M],
                     [c0, c0, c1, c1])
    line.write_text(_kml("site-valley power line",
                         [*towers, _polygon("wires", corridor, CORRIDOR_TOP_M)]),
                    encoding="utf-8")
    return [dem, area, line]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("-o", "--output", default=str(Path(__file__).resolve().parents[1]
                                                   / "sim" / "scenarios" / "site"),
                    help="folder for the files (default: sim/scenarios/site)")
    args = ap.parse_args()
    for p in write_site(Path(args.output)):
        print(f"{p} ({p.stat().st_size / 1000:.0f} kB)")
    h0 = float(height_amsl_m(np.array([0.0]), np.array([0.0]))[0])
    print(f"take-off point {ORIGIN_LAT}, {ORIGIN_LON}: ground {h0:.1f} m AMSL, "
          f"{h0 + GEOID_M:.1f} m above the ellipsoid")


if __name__ == "__main__":
    main()
