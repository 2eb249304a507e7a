"""The vehicle's terrain database and its side of the MAVLink terrain protocol.

The vehicle holds the scenario's terrain (the world's :class:`planner.models.TerrainModel`:
``height_m(e, n)`` in the world's ENU frame, hills, grids or a DEM) as its terrain
database: nothing is ever pending. Heights are given in the terrain's datum, the datum
of ``[world.origin] h_m`` (the world has no geoid: WGS84 ellipsoidal heights, as every
altitude the vehicle reports): the ground point ``(e, n, height_m(e, n))`` under a
latitude and longitude, converted to geodetic with the world frame. A DEM's
``datum_offset_m`` is already in its surface (site.md: it is added to every cell), so it
is in these heights too.

As ArduPilot speaks the protocol (the vehicle's side):

- TERRAIN_CHECK (lat, lon) is answered with TERRAIN_REPORT: ``terrain_height`` the
  ground's height there, ``current_height`` the vehicle's own height above it (its
  altitude minus ``terrain_height``), ``spacing`` the database's grid spacing (0: no
  terrain data there, :meth:`TerrainDatabase.has_data`: beyond
  :data:`sim.world.MAX_EXTENT_M` of the origin, or beyond a grid or the part of a DEM
  read for the scenario, where the ground flown is its edge value held, which no data
  backs), ``pending`` 0, ``loaded`` the 4x4 blocks of that spacing that cover the
  database's data (at most 65535, the field's limit);
- TERRAIN_REPORT for its own position (the ground below its navigation position) is
  sent about once a second (simulated time);
- TERRAIN_REQUEST (a ground station asking for blocks; normally the vehicle asks) is
  answered with the TERRAIN_DATA blocks of its mask from the database, laid out as
  ground stations lay them out (an 8 x 7 array of 4 x 4 blocks from the south-west
  corner, row-major to the north; heights in whole metres): the vehicle needs no data,
  so it never sends TERRAIN_REQUEST itself;
- TERRAIN_DATA is accepted and has no effect (the database is the scenario's terrain).

Items and commands in MAV_FRAME_GLOBAL_TERRAIN_ALT(_INT) are flown at their height above
the same surface (:meth:`TerrainDatabase.above_ground`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from planner.mission import deg_to_e7
from sim.dem import DemError, DemTerrain
from sim.terrain import GridTerrain
from sim.world import MAX_EXTENT_M, World

NOMINAL_SPACING_M = 100  # an analytic terrain has no grid: ArduPilot's TERRAIN_SPACING
BLOCK_POINTS = 4  # a TERRAIN_DATA block: 4 x 4 heights
REQUEST_BLOCKS_E, REQUEST_BLOCKS_N = 8, 7  # a TERRAIN_REQUEST mask: 8 x 7 blocks (56 bits)
EARTH_RADIUS_M = 6_371_000.0  # (only to guess a height's ENU curvature drop)


@dataclass(frozen=True)
class TerrainReport:
    """The fields of a TERRAIN_REPORT."""

    lat_e7: int
    lon_e7: int
    spacing: int
    terrain_height_m: float
    current_height_m: float
    pending: int
    loaded: int


class TerrainDatabase:
    """The world's terrain as the vehicle's terrain database (see the module docstring)."""

    def __init__(self, world: World) -> None:
        self.world = world
        self.frame = world.frame
        spacing = getattr(world.terrain, "spacing_m", None)  # a grid's cell
        pixel = getattr(world.terrain, "pixel_m", None)  # a DEM's pixel on the ground
        if spacing is None and pixel is not None:
            spacing = min(pixel)
        self.spacing = int(min(max(round(spacing), 1), 65535)) if spacing else \
            NOMINAL_SPACING_M
        self._h0 = float(self.frame.to_geodetic(0.0, 0.0, 0.0)[2])  # the origin's height
        block = BLOCK_POINTS * self.spacing
        width, height = self._data_size_m()
        self.loaded = min(math.ceil(width / block) * math.ceil(height / block), 65535)

    def _data_size_m(self) -> tuple[float, float]:
        """East and north size of the terrain's data (an analytic one: the world's)."""
        t = self.world.terrain
        if isinstance(t, GridTerrain):
            ny, nx = t.heights_m.shape
            return (nx - 1) * t.spacing_m, (ny - 1) * t.spacing_m
        if isinstance(t, DemTerrain):
            ny, nx = t.values_m.shape
            return (nx - 1) * t.pixel_m[0], (ny - 1) * t.pixel_m[1]
        return 2.0 * MAX_EXTENT_M, 2.0 * MAX_EXTENT_M

    def has_data(self, points_en: list[tuple[float, float]]) -> bool:
        """Whether the terrain's own data gives the ground at every ENU (e, n) point: an
        analytic terrain everywhere (within the world's extent), a grid inside it, a DEM
        where its bilinear support lies in the part of the file read for the scenario, off
        nodata cells (:meth:`sim.dem.DemTerrain.require_points`). Elsewhere the ground the
        vehicle flies over is an edge value held, which it does not report as data."""
        if any(math.hypot(e, n) > MAX_EXTENT_M for e, n in points_en):
            return False
        t = self.world.terrain
        if isinstance(t, GridTerrain):
            ny, nx = t.heights_m.shape
            s = t.spacing_m
            return all(0.0 <= e - t.e0_m <= (nx - 1) * s and 0.0 <= n - t.n0_m <= (ny - 1) * s
                       for e, n in points_en)
        if isinstance(t, DemTerrain):
            try:
                t.require_points(points_en, "a terrain check")
            except DemError:
                return False
        return True

    def ground_m(self, e_m: float, n_m: float) -> float:
        """Ground height (ENU up) at ENU (e, n)."""
        return float(self.world.ground_m(e_m, n_m))

    def ground_enu(self, lat_deg: float, lon_deg: float) -> tuple[float, float, float]:
        """The ground point under (lat, lon) in ENU metres: a fixed point, as the ENU
        horizontal position of a geodetic point moves with its height (about 1.6 cm per
        100 m at 1 km from the origin); the height it needs is approximated on a sphere
        (millimetres here)."""
        e = n = u = 0.0
        for _ in range(3):
            h = self._h0 + u + (e * e + n * n) / (2.0 * EARTH_RADIUS_M)
            e, n, _ = self.frame.to_enu(lat_deg, lon_deg, h)
            e, n = float(e), float(n)
            u = self.ground_m(e, n)
        return e, n, u

    def available(self, lat_deg: float, lon_deg: float) -> bool:
        """Does the database cover (lat, lon)? (The world's extent about its origin.)"""
        if not (math.isfinite(lat_deg) and math.isfinite(lon_deg)
                and abs(lat_deg) <= 90.0 and abs(lon_deg) <= 180.0):
            return False
        e, n, _ = self.frame.to_enu(lat_deg, lon_deg, self._h0)
        return math.hypot(float(e), float(n)) <= MAX_EXTENT_M

    def height_m(self, lat_deg: float, lon_deg: float) -> float:
        """The ground's height at (lat, lon) in the terrain's datum (NaN: unavailable)."""
        if not self.available(lat_deg, lon_deg):
            return math.nan
        e, n, u = self.ground_enu(lat_deg, lon_deg)
        return float(self.frame.to_geodetic(e, n, u)[2])

    def above_ground(self, lat_deg: float, lon_deg: float, agl_m: float) -> tuple[float,
                                                                                 float, float]:
        """The ENU point ``agl_m`` above the ground under (lat, lon)."""
        e, n, u = self.ground_enu(lat_deg, lon_deg)
        return e, n, u + agl_m

    def data_height_m(self, lat_deg: float, lon_deg: float) -> float:
        """:meth:`height_m` where the terrain has data (:meth:`has_data`), else NaN: what
        the vehicle reports as the ground (TERRAIN_REPORT, ALTITUDE)."""
        if not self.available(lat_deg, lon_deg):
            return math.nan
        e, n, u = self.ground_enu(lat_deg, lon_deg)
        if not self.has_data([(e, n)]):
            return math.nan
        return float(self.frame.to_geodetic(e, n, u)[2])

    def report(self, lat_e7: int, lon_e7: int, vehicle_alt_m: float) -> TerrainReport:
        """TERRAIN_REPORT for (lat, lon) of a vehicle at ``vehicle_alt_m`` (its
        altitude in the same datum); spacing 0 where there is no data."""
        h = self.data_height_m(lat_e7 / 1e7, lon_e7 / 1e7)
        if not math.isfinite(h):
            return TerrainReport(lat_e7, lon_e7, 0, 0.0, 0.0, 0, self.loaded)
        return TerrainReport(lat_e7, lon_e7, self.spacing, h, vehicle_alt_m - h, 0, self.loaded)

    def report_below(self, p: tuple[float, float, float],
                     geodetic: tuple[float, float, float]) -> TerrainReport:
        """TERRAIN_REPORT for a vehicle at ENU ``p`` = ``geodetic`` (lat, lon, alt), the
        ground straight below it: its height above the ground along ENU up is its height
        above it along the ellipsoid's normal to a millimetre (the two differ by the
        angle from the origin, 0.003 rad at 20 km), so no second conversion is needed."""
        lat, lon, alt = geodetic
        if not self.has_data([(p[0], p[1])]):
            return TerrainReport(deg_to_e7(lat), deg_to_e7(lon), 0, 0.0, 0.0, 0, self.loaded)
        agl = p[2] - self.ground_m(p[0], p[1])
        return TerrainReport(deg_to_e7(lat), deg_to_e7(lon), self.spacing, alt - agl, agl, 0,
                             self.loaded)

    def block(self, lat_e7: int, lon_e7: int, spacing_m: int, gridbit: int) -> list[int] | None:
        """The 16 heights (whole metres, int16) of block ``gridbit`` of a TERRAIN_REQUEST
        from the south-west corner (lat, lon) at ``spacing_m``; None if unavailable."""
        lat, lon = lat_e7 / 1e7, lon_e7 / 1e7
        if not (0 <= gridbit < REQUEST_BLOCKS_E * REQUEST_BLOCKS_N and spacing_m > 0
                and self.available(lat, lon)):
            return None
        e0, n0, _ = self.ground_enu(lat, lon)
        step = BLOCK_POINTS * spacing_m
        be = e0 + step * (gridbit % REQUEST_BLOCKS_E)
        bn = n0 + step * (gridbit // REQUEST_BLOCKS_E)
        points = [(be + spacing_m * (i % BLOCK_POINTS),  # east along a row
                   bn + spacing_m * (i // BLOCK_POINTS))  # rows to the north
                  for i in range(BLOCK_POINTS * BLOCK_POINTS)]
        if not self.has_data(points):
            return None
        out = []
        for e, n in points:
            h = float(self.frame.to_geodetic(e, n, self.ground_m(e, n))[2])
            out.append(max(-32768, min(32767, round(h))))
        return out
