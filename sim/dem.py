"""Terrain from a digital elevation model: a GeoTIFF in any CRS, or an SRTM ``.hgt`` tile.

:class:`DemTerrain` implements the planner's terrain protocol
(:class:`planner.models.TerrainModel`) over a DEM file, in the world's exact WGS84 ENU
frame, so the simulator, the planner (NumPy and CasADi), the vehicle and the figures
all use one surface.

Reading. Only the window the scenario needs is read (a rasterio ``Window`` around the
scenario's box plus a margin; :data:`MAX_WINDOW_CELLS` bounds it), however large the
file. Cell values are heights in metres above the datum of the world origin's height
(docs/scenarios.md), plus ``datum_offset_m``. GDAL places every value at its pixel's
centre in the file's affine transform: a GeoTIFF's cell centre (PixelIsArea) and an
SRTM post or a PixelIsPoint GeoTIFF's post alike (GDAL shifts their transform by half
a pixel), so heights are bilinear between pixel centres, "index coordinates" (i, j)
below: column and row of a pixel centre.

Frames. A ground point (e, n) of the world frame lies at geodetic (lat, lon) where the
vertical through it meets the DEM surface; its ENU up is ``u`` exactly, curvature
included: a point at DEM height h and horizontal distance d from the origin lies
u = h - h0 - c below the tangent plane, c = d^2 / 2R (0.08 m at 1 km, 7.8 m at
10 km). The map ENU (e, n, u) -> index coordinates (i, j) and the drop c(e, n, u) are
smooth: each is fitted once, by least squares to the exact conversion (the WGS84
geodesy of :class:`estimator.geodesy.ExactENU`, then pyproj into the file's CRS with
``always_xy=True``, then the inverse affine), as a cubic polynomial in (e, n) plus u
times a quadratic; :attr:`DemTerrain.map_error_px` is the fit's largest residual on a
finer check grid (below 1e-4 pixel for windows of a few km). ``height_m`` (NumPy)
evaluates the map at the window's median ground height, samples the DEM, and repeats
once at the height found (the vertical through a point tilts by d / R from the frame's
up: 100 m of relief moves the sample 3 cm at 2 km; after the repeat the error is below
a millimetre).

CasADi. For symbols, ``height_m`` composes the same polynomial map (at the median
ground height, no repeat) with ``casadi.interpolant(..., "bspline")`` through the
window's values on the index grid: a smooth function Ipopt can differentiate, through
the same nodes as the bilinear surface (the planner re-checks its paths against the
NumPy surface, as for :class:`sim.terrain.GridTerrain`). A window of more than
:data:`CASADI_MAX_CELLS` cells gives the B-spline every k-th cell in each direction
(a 1 m LiDAR model of a 2 km area: every 5th).

Values. Band 1 is read as GDAL declares it: raw x scale + offset (an int16 file of
decimetres), in its vertical unit (metres, or feet converted; another unit is refused).
Nodata cells are the file's declared nodata, NaN and heights beyond the Earth's
(:data:`LOWEST_M`, :data:`HIGHEST_M`); in a file that declares no nodata, the usual void
markers too (:data:`VOID_MARKERS`, SRTM's -32768).

Refusals (:class:`DemError`, one line naming the file): unreadable file, no CRS or one
pyproj cannot reach from WGS84 (a local grid), a picture's band (red, palette...)
rather than heights, a window beyond :data:`MAX_WINDOW_CELLS`, and through
:meth:`DemTerrain.require_points` / :meth:`DemTerrain.require_polygon`, a point or
area that leaves the file's extent (the message gives it in degrees) or whose bilinear
support touches a nodata cell. The extent of a GeoTIFF of cells (PixelIsArea) is its
bounds, the outer edges of its edge cells: a DEM clipped to the area's bounding box, or
downloaded for it, holds the area; in the outer half of an edge cell the edge value is
held across the edge (bilinear along it). The extent of posts (SRTM, PixelIsPoint) is
its outermost posts.
"""

from __future__ import annotations

import itertools
import math
import re
import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from estimator.geodesy import ExactENU
from sim.terrain import MAX_RELIEF_M, bilinear, map_elementwise

MAX_WINDOW_CELLS = 16_000_000  # 128 MB of float64: far beyond a search area at 1 m
CASADI_MAX_CELLS = 250_000  # the CasADi B-spline takes every k-th cell beyond this
DEFAULT_MARGIN_M = 300.0  # read this far around the scenario's box (overshoot, figures)
# a file that declares no nodata: these raw values are voids (SRTM's -32768, ...), and so
# is any height beyond the Earth's (below the deepest trench, above the highest summit)
VOID_MARKERS = (-32768.0, -32767.0, -9999.0)
LOWEST_M, HIGHEST_M = -11_000.0, 9_000.0
_U_SPAN_M = 1000.0  # the map is fitted over u_ref +- this (metres of ENU up)


class DemError(ValueError):
    """A DEM that cannot be read or does not cover what it must (one line, names the file)."""


def _terms(x, y, u):
    """The fitted model's columns: cubic in (x, y) and u times a quadratic in (x, y)."""
    return [x * 0 + 1, x, y, x * x, x * y, y * y, x * x * x, x * x * y, x * y * y, y * y * y,
            u, u * x, u * y, u * x * x, u * x * y, u * y * y]


class DemTerrain:
    """Heights of a DEM file in a world's ENU frame (see the module docstring).

    ``box_enu_m`` = (e_min, e_max, n_min, n_max) is what the scenario covers; the
    window read adds ``margin_m`` around it (clipped to the file). Outside the window
    the edge value is held, as :class:`sim.terrain.GridTerrain` does.
    """

    def __init__(
        self,
        path: str | Path,
        origin: tuple[float, float, float],
        box_enu_m: tuple[float, float, float, float],
        *,
        datum_offset_m: float = 0.0,
        margin_m: float = DEFAULT_MARGIN_M,
        name: str | None = None,
    ) -> None:
        import rasterio
        from pyproj import Transformer
        from rasterio.windows import Window

        self.path = Path(path)
        self.name = name or str(path)
        if not math.isfinite(datum_offset_m):
            raise DemError(f"{self.name}: datum_offset_m must be finite")
        if abs(datum_offset_m) > MAX_RELIEF_M:  # 1e300 made every height NaN downstream
            raise DemError(f"{self.name}: datum_offset_m {datum_offset_m:g} m is beyond "
                           f"{MAX_RELIEF_M:.0f} m")
        self.datum_offset_m = float(datum_offset_m)
        self.origin = tuple(float(v) for v in origin)
        self._frame = ExactENU(*self.origin)
        e0, e1, n0, n1 = (float(v) for v in box_enu_m)
        if not (all(map(math.isfinite, (e0, e1, n0, n1))) and e0 <= e1 and n0 <= n1):
            raise DemError(f"{self.name}: the scenario's box {box_enu_m!r} is not finite")
        with warnings.catch_warnings():  # a picture's "no geotransform": refused below
            warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
            try:
                src = rasterio.open(self.path)
            except (OSError, rasterio.errors.RasterioError) as exc:
                raise DemError(f"{self.name}: cannot read the DEM: "
                               f"{_hgt_problem(self.path) or _first_line(exc)}") from None
        with src:
            if src.count < 1:
                raise DemError(f"{self.name}: the file holds no raster band")
            if src.crs is None:
                raise DemError(f"{self.name}: the file declares no coordinate reference system")
            if src.colorinterp[0].name in _PICTURE_BANDS:
                raise DemError(f"{self.name}: band 1 is the {src.colorinterp[0].name} of a "
                               "picture, not heights (a hillshade or map image?)")
            self.scale, self.offset_m, self.unit_m = _band_scaling(src, self.name)
            self.declares_nodata = src.nodata is not None
            self.crs = src.crs.to_string()
            self.file_shape = (src.height, src.width)
            aff = src.transform
            self._inv = ~aff
            try:
                self._to_crs = Transformer.from_crs("EPSG:4326", src.crs, always_xy=True)
            except Exception as exc:  # pyproj's ProjError, CRSError: any is a refusal
                raise DemError(f"{self.name}: its coordinate reference system ({self.crs}) "
                               f"cannot be reached from WGS84 latitude and longitude "
                               f"({_first_line(exc)})") from None
            self.pixel_is_point = src.tags().get("AREA_OR_POINT", "Area").lower() == "point"
            # how far beyond the outermost pixel centres the file holds heights (index
            # units): a cell's value is its whole cell's (PixelIsArea), to the file's
            # bounds; a post's is its point only (SRTM, PixelIsPoint)
            self._pad = 0.0 if self.pixel_is_point else 0.5
            self.extent_text = _extent_text(src, self._pad)
            # the window: the box plus the margin, through the exact map (u = 0)
            m = max(float(margin_m), 0.0)
            wi, wj = self._exact_index(*_box_ring(e0 - m, e1 + m, n0 - m, n1 + m),
                                       np.zeros(4 * 64))
            if not (np.all(np.isfinite(wi)) and np.all(np.isfinite(wj))):
                raise DemError(f"{self.name}: the scenario's area does not map into the "
                               f"file's CRS ({self.crs})")
            H, W = self.file_shape
            c0 = max(math.floor(wi.min()) - 1, 0)
            c1 = min(math.ceil(wi.max()) + 1, W - 1)
            r0 = max(math.floor(wj.min()) - 1, 0)
            r1 = min(math.ceil(wj.max()) + 1, H - 1)
            if c1 - c0 < 1 or r1 - r0 < 1:
                raise DemError(f"{self.name}: the scenario's area lies outside the DEM's "
                               f"extent ({self.extent_text})")
            cells = (c1 - c0 + 1) * (r1 - r0 + 1)
            if cells > MAX_WINDOW_CELLS:
                raise DemError(
                    f"{self.name}: the scenario needs {cells:,} cells of the DEM (limit "
                    f"{MAX_WINDOW_CELLS:,}): use a coarser DEM or a smaller area")
            self.window = Window(c0, r0, c1 - c0 + 1, r1 - r0 + 1)
            try:
                band = src.read(1, window=self.window, masked=True, out_dtype="float64")
            except (OSError, rasterio.errors.RasterioError) as exc:
                raise DemError(f"{self.name}: cannot read the DEM: {_first_line(exc)}") from None
        vals = np.ma.getdata(band).astype(float)
        bad = np.ma.getmaskarray(band) | ~np.isfinite(vals)
        if not self.declares_nodata:  # the usual void markers of a file that declares none
            bad |= np.isin(vals, VOID_MARKERS)
        # the band's declared meaning: value = raw x scale + offset, in its vertical unit
        vals = (vals * self.scale + self.offset_m) * self.unit_m
        bad |= (vals < LOWEST_M) | (vals > HIGHEST_M)  # no height on Earth: a void
        if bad.all():
            raise DemError(f"{self.name}: no valid height in the scenario's window")
        self._c0, self._r0 = c0, r0
        self._bad = bad
        # cells (between four pixel centres) that bilinear cannot use: any corner bad
        self._bad_cell = bad[:-1, :-1] | bad[1:, :-1] | bad[:-1, 1:] | bad[1:, 1:]
        if bad.any():  # outside what the scenario needs: the nearest valid height
            from scipy.ndimage import distance_transform_edt

            idx = distance_transform_edt(bad, return_distances=False, return_indices=True)
            vals = vals[tuple(idx)]
        vals = vals + self.datum_offset_m
        vals.setflags(write=False)
        self.values_m = vals  # heights in the origin's datum at the window's pixel centres
        self._fit_maps((e0 - m, e1 + m, n0 - m, n1 + m))

    # ------------------------------------------------------------------ exact map
    def _exact_index(self, e, n, u):
        """Index coordinates (i, j) in the FILE of ENU points (exact geodesy and CRS)."""
        lat, lon, _ = self._frame.to_geodetic(np.asarray(e, dtype=float),
                                              np.asarray(n, dtype=float),
                                              np.asarray(u, dtype=float))
        x, y = self._to_crs.transform(np.asarray(lon), np.asarray(lat))
        col, row = self._inv @ (np.asarray(x), np.asarray(y))
        return np.asarray(col) - 0.5, np.asarray(row) - 0.5

    def _exact_drop(self, e, n, u):
        """c = h(e, n, u) - h0 - u: how far the ellipsoid height exceeds the ENU up."""
        _, _, h = self._frame.to_geodetic(np.asarray(e, dtype=float),
                                          np.asarray(n, dtype=float), np.asarray(u, dtype=float))
        return np.asarray(h) - self.origin[2] - np.asarray(u, dtype=float)

    def _fit_maps(self, box: tuple[float, float, float, float]) -> None:
        e0, e1, n0, n1 = box
        self._ec, self._nc = 0.5 * (e0 + e1), 0.5 * (n0 + n1)
        self._L = max(0.5 * (e1 - e0), 0.5 * (n1 - n0), 1.0)
        # the window's median ground height (first through the u = 0 map)
        g = np.linspace(-1.0, 1.0, 12)
        gx, gy = np.meshgrid(g, g)
        ee, nn = self._ec + self._L * gx.ravel(), self._nc + self._L * gy.ravel()
        i, j = self._exact_index(ee, nn, np.zeros(ee.size))
        hh = bilinear(self.values_m, 0.0, 0.0, 1.0, 1.0, i - self._c0, j - self._r0)
        self.u_ref_m = float(np.median(hh - self.origin[2]))
        self._uc = self.u_ref_m
        coef = []
        samples = []
        for du in (-_U_SPAN_M, 0.0, _U_SPAN_M):
            u = np.full(ee.size, self.u_ref_m + du)
            i, j = self._exact_index(ee, nn, u)
            samples.append((gx.ravel(), gy.ravel(), np.full(ee.size, du / _U_SPAN_M), i - self._c0,
                            j - self._r0, self._exact_drop(ee, nn, u)))
        x, y, s, i, j, c = (np.concatenate(v) for v in zip(*samples, strict=True))
        A = np.column_stack(_terms(x, y, s))
        for target in (i, j, c):
            coef.append(np.linalg.lstsq(A, target, rcond=None)[0])
        self._coef = np.array(coef)  # (3, 16): window index i, j and the drop c
        self._coef_lists = tuple(c.tolist() for c in self._coef)
        # the fit's residual on a finer grid between the fitting nodes
        g2 = np.linspace(-0.97, 0.97, 17)
        hx, hy = np.meshgrid(g2, g2)
        ee2, nn2 = self._ec + self._L * hx.ravel(), self._nc + self._L * hy.ravel()
        err_px = 0.0
        err_c = 0.0
        for du in (-_U_SPAN_M, 0.0, _U_SPAN_M):
            u = np.full(ee2.size, self.u_ref_m + du)
            i, j = self._exact_index(ee2, nn2, u)
            pi, pj, pc = self._map(ee2, nn2, u)
            err_px = max(err_px, float(np.max(np.hypot(pi - (i - self._c0), pj - (j - self._r0)))))
            err_c = max(err_c, float(np.max(np.abs(pc - self._exact_drop(ee2, nn2, u)))))
        self.map_error_px = err_px
        self.drop_error_m = err_c
        # pixel sizes on the ground (m): the Jacobian of (e, n) -> (i, j), inverted
        d = 1.0
        i0, j0, _ = self._map(self._ec, self._nc, self.u_ref_m)
        ie, je, _ = self._map(self._ec + d, self._nc, self.u_ref_m)
        in_, jn, _ = self._map(self._ec, self._nc + d, self.u_ref_m)
        J = np.array([[ie - i0, in_ - i0], [je - j0, jn - j0]], dtype=float).reshape(2, 2)
        Jinv = np.linalg.inv(J)  # (i, j) steps -> (e, n) metres
        self.pixel_m = (float(np.linalg.norm(Jinv[:, 0])), float(np.linalg.norm(Jinv[:, 1])))

    def _xy(self, e, n):
        return ((np.asarray(e, dtype=float) - self._ec) / self._L,
                (np.asarray(n, dtype=float) - self._nc) / self._L)

    def _map(self, e, n, u):
        """Fitted (window index i, window index j, drop c) of ENU points (NumPy)."""
        x, y = self._xy(e, n)
        s = (np.asarray(u, dtype=float) - self._uc) / _U_SPAN_M
        t = _terms(x, y, s)
        out = []
        for k in range(3):
            c = self._coef[k]
            acc = c[0] * t[0]
            for q in range(1, len(t)):
                acc = acc + c[q] * t[q]
            out.append(acc)
        return out[0], out[1], out[2]

    def _up(self, h, e, n):
        """u of the ground point at DEM height h (origin's datum) above (e, n): u = h - h0
        - c(u), with the fitted drop c = a(e, n) + b(e, n) (u - u_ref) solved for u."""
        x, y = self._xy(e, n)
        k = self._coef[2]
        t = _terms(x, y, 1.0)
        a = k[0] * t[0]
        for q in range(1, 10):
            a = a + k[q] * t[q]
        b = k[10] * t[10]
        for q in range(11, 16):
            b = b + k[q] * t[q]
        b = b / _U_SPAN_M
        return (h - self.origin[2] - a + b * self._uc) / (1.0 + b)

    # ------------------------------------------------------------------ protocol
    def height_m(self, e_m, n_m):
        """Ground height (ENU up, m) at (e, n): NumPy in, NumPy out; CasADi symbols in,
        a smooth symbol out (see the module docstring)."""
        import casadi as ca

        if isinstance(e_m, ca.SX | ca.MX | ca.DM) or isinstance(n_m, ca.SX | ca.MX | ca.DM):
            return self._height_casadi(e_m, n_m)
        if isinstance(e_m, float | int) and isinstance(n_m, float | int):
            return np.float64(self._height_scalar(float(e_m), float(n_m)))
        e, n = np.broadcast_arrays(np.asarray(e_m, dtype=float), np.asarray(n_m, dtype=float))
        if e.ndim == 0:
            return np.float64(self._height_scalar(float(e), float(n)))
        u = np.full(e.shape, self.u_ref_m)
        for _ in range(2):  # at the median ground height, then at the height found
            i, j, _ = self._map(e, n, u)
            u = self._up(bilinear(self.values_m, 0.0, 0.0, 1.0, 1.0, i, j), e, n)
        return u if u.ndim else np.float64(u)

    def _height_scalar(self, e: float, n: float) -> float:
        """:meth:`height_m` at one point on Python floats (the same arithmetic, some 20 x
        faster than NumPy on 0-d arrays)."""
        ci, cj, cc = self._coef_lists
        x, y = (e - self._ec) / self._L, (n - self._nc) / self._L
        base = (1.0, x, y, x * x, x * y, y * y, x * x * x, x * x * y, x * y * y, y * y * y)
        quad = base[:6]
        a = sum(k * t for k, t in zip(cc[:10], base, strict=True))
        b = sum(k * t for k, t in zip(cc[10:], quad, strict=True)) / _U_SPAN_M
        i_lin = [sum(k * t for k, t in zip(c[:10], base, strict=True)) for c in (ci, cj)]
        i_u = [sum(k * t for k, t in zip(c[10:], quad, strict=True)) for c in (ci, cj)]
        vals = self.values_m
        ny, nx = vals.shape
        u = self.u_ref_m
        for _ in range(2):
            s = (u - self._uc) / _U_SPAN_M
            fi = min(max(i_lin[0] + s * i_u[0], 0.0), nx - 1.0)
            fj = min(max(i_lin[1] + s * i_u[1], 0.0), ny - 1.0)
            i0 = min(int(fi), nx - 2)
            j0 = min(int(fj), ny - 2)
            ti, tj = fi - i0, fj - j0
            h = ((vals[j0, i0] * (1 - ti) + vals[j0, i0 + 1] * ti) * (1 - tj)
                 + (vals[j0 + 1, i0] * (1 - ti) + vals[j0 + 1, i0 + 1] * ti) * tj)
            u = (float(h) - self.origin[2] - a + b * self._uc) / (1.0 + b)
        return u

    def elevation_m(self, e_m: ArrayLike, n_m: ArrayLike) -> np.ndarray:
        """The DEM's height (plus ``datum_offset_m``: the origin's datum) under ENU points:
        the ground's geodetic height, what a terrain database reports."""
        e, n = np.broadcast_arrays(np.asarray(e_m, dtype=float), np.asarray(n_m, dtype=float))
        u = np.asarray(self.height_m(e, n), dtype=float)
        return u + self.origin[2] + self._map(e, n, u)[2]

    def sag_curvature(self) -> tuple[float, float]:
        """Curvature bounds along a line (1/m), as :meth:`GridTerrain.sag_curvature`: the
        largest row, column and diagonal second differences of the window's heights over
        the pixel's ground size, x 1.5 (the B-spline's overshoot); the Earth's curvature
        (the drop c, 1/R) adds to the concave bound."""
        cached = self.__dict__.get("_sag")
        if cached is not None:
            return cached
        h = self.values_m
        di, dj = self.pixel_m
        d2 = [np.diff(h, 2, axis=1) / di**2, np.diff(h, 2, axis=0) / dj**2]
        if min(h.shape) >= 3:
            dd = di * di + dj * dj
            d2 += [(h[2:, 2:] - 2 * h[1:-1, 1:-1] + h[:-2, :-2]) / dd,
                   (h[2:, :-2] - 2 * h[1:-1, 1:-1] + h[:-2, 2:]) / dd]
        concave = max(float(np.max(-d, initial=0.0)) for d in d2)
        convex = max(float(np.max(d, initial=0.0)) for d in d2)
        out = (1.5 * concave + 1.0 / 6.3e6, 1.5 * convex)
        self._sag = out
        return out

    def max_height_m(self, e_min: float, e_max: float, n_min: float, n_max: float) -> float:
        """An upper bound of the height over the box: the highest pixel of the cells the
        box touches (bilinear never exceeds its corners), less no drop (c >= 0)."""
        e = np.array([e_min, e_max, e_min, e_max, 0.5 * (e_min + e_max)])
        n = np.array([n_min, n_min, n_max, n_max, 0.5 * (n_min + n_max)])
        i, j, _ = self._map(e, n, np.full(5, self.u_ref_m))
        ny, nx = self.values_m.shape
        pad = 1.0 + 0.01 * max(e_max - e_min, n_max - n_min) / min(self.pixel_m)
        ci0 = int(min(max(math.floor(i.min() - pad), 0), nx - 1))
        ci1 = int(min(max(math.ceil(i.max() + pad), 0), nx - 1))
        cj0 = int(min(max(math.floor(j.min() - pad), 0), ny - 1))
        cj1 = int(min(max(math.ceil(j.max() + pad), 0), ny - 1))
        top = float(self.values_m[cj0:cj1 + 1, ci0:ci1 + 1].max())
        return top - self.origin[2] + 1e-3

    # ------------------------------------------------------------------ CasADi
    def _height_casadi(self, e, n):
        import casadi as ca

        f = self.__dict__.get("_ca_fn")
        if f is None:
            ny, nx = self.values_m.shape
            # every cell, or every k-th in each direction beyond CASADI_MAX_CELLS
            k = max(1, math.ceil(math.sqrt(nx * ny / CASADI_MAX_CELLS)))
            gi = np.unique(np.append(np.arange(0, nx, k), nx - 1))
            gj = np.unique(np.append(np.arange(0, ny, k), ny - 1))
            h = self.values_m[np.ix_(gj, gi)]
            lut = ca.interpolant("dem", "bspline", [gi.astype(float).tolist(),
                                                    gj.astype(float).tolist()],
                                 h.T.ravel(order="F").tolist())
            es, ns = ca.MX.sym("e"), ca.MX.sym("n")
            x, y = (es - self._ec) / self._L, (ns - self._nc) / self._L
            t = _terms(x, y, 1.0)
            i, j, a, b = (sum(float(self._coef[k][q]) * t[q] for q in qs)
                          for k, qs in ((0, range(10)), (1, range(10)), (2, range(10)),
                                        (2, range(10, 16))))
            b = b / _U_SPAN_M
            h = lut(ca.vertcat(i, j))
            f = ca.Function("dem_height", [es, ns],
                            [(h - self.origin[2] - a + b * self._uc) / (1.0 + b)])
            self._ca_fn = f
        return map_elementwise(f, e, n)

    # ------------------------------------------------------------------ coverage
    def _file_index(self, e, n, u):
        i, j, _ = self._map(e, n, u)
        return i + self._c0, j + self._r0

    def require_points(self, points_en: ArrayLike, what: str) -> None:
        """Refuse (:class:`DemError`) points that leave the file's extent (a cell file's
        bounds, a post file's outermost posts) or whose bilinear support touches a nodata
        cell."""
        p = np.asarray(points_en, dtype=float).reshape(-1, 2)
        if len(p) == 0:
            return
        u = np.asarray(self.height_m(p[:, 0], p[:, 1]), dtype=float)
        i, j, _ = self._map(p[:, 0], p[:, 1], u)
        self._check_cells(i, j, p, what)

    def _check_cells(self, i, j, p, what: str) -> None:
        ny, nx = self.values_m.shape
        H, W = self.file_shape
        fi, fj = i + self._c0, j + self._r0
        # the fitted map's residual (~1e-6 pixel) must not refuse a vertex on the bounds
        eps, pad = 1e-3, self._pad
        out = ((fi < -pad - eps) | (fj < -pad - eps) | (fi > W - 1 + pad + eps)
               | (fj > H - 1 + pad + eps))
        # the window's own edges, and the file's half cell where the window reaches it
        lo_i, lo_j = (-pad if self._c0 == 0 else 0.0), (-pad if self._r0 == 0 else 0.0)
        hi_i = nx - 1 + (pad if self._c0 + nx == W else 0.0)
        hi_j = ny - 1 + (pad if self._r0 + ny == H else 0.0)
        win_out = (i < lo_i - eps) | (j < lo_j - eps) | (i > hi_i + eps) | (j > hi_j + eps)
        if np.any(out):
            k = int(np.argmax(out))
            lat, lon, _ = self._frame.to_geodetic(p[k, 0], p[k, 1], 0.0)
            raise DemError(f"{self.name}: {what} leaves the DEM's extent at "
                           f"({p[k, 0]:.1f}, {p[k, 1]:.1f}) m, {_latlon_text(lat, lon)} "
                           f"({self.extent_text})")
        if np.any(win_out):
            k = int(np.argmax(win_out))
            raise DemError(f"{self.name}: {what} reaches ({p[k, 0]:.1f}, {p[k, 1]:.1f}) m, "
                           "beyond the part of the DEM read for the scenario")
        ci = np.clip(np.floor(i).astype(int), 0, nx - 2)
        cj = np.clip(np.floor(j).astype(int), 0, ny - 2)
        bad = self._bad_cell[cj, ci]
        if np.any(bad):
            k = int(np.argmax(bad))
            raise DemError(f"{self.name}: {what} touches nodata cells at "
                           f"({p[k, 0]:.1f}, {p[k, 1]:.1f}) m")

    def require_polygon(self, polygon_en: ArrayLike, what: str) -> None:
        """Refuse a polygon (its boundary and every cell inside) that leaves the file's
        extent or touches nodata."""
        from matplotlib.path import Path as MplPath

        poly = np.asarray(polygon_en, dtype=float).reshape(-1, 2)
        step = 0.25 * min(self.pixel_m)
        ring = np.vstack([poly, poly[:1]])
        pts = []  # the ring once round, in order (each edge from its first vertex)
        for a, b in itertools.pairwise(ring):
            k = max(1, math.ceil(float(np.linalg.norm(b - a)) / step))
            f = (np.arange(k) / k)[:, None]
            pts.append(a + f * (b - a))
        boundary = np.vstack(pts)
        self.require_points(boundary, what)
        # every cell whose centre lies inside the polygon (in window index coordinates)
        bu = np.full(len(boundary), self.u_ref_m)
        bi, bj, _ = self._map(boundary[:, 0], boundary[:, 1], bu)
        ny, nx = self.values_m.shape
        i0, i1 = max(math.floor(bi.min()), 0), min(math.ceil(bi.max()), nx - 2)
        j0, j1 = max(math.floor(bj.min()), 0), min(math.ceil(bj.max()), ny - 2)
        if i1 < i0 or j1 < j0:
            return
        gi, gj = np.meshgrid(np.arange(i0, i1 + 1) + 0.5, np.arange(j0, j1 + 1) + 0.5)
        inside = MplPath(np.column_stack([bi, bj])).contains_points(
            np.column_stack([gi.ravel(), gj.ravel()])).reshape(gi.shape)
        bad = self._bad_cell[j0:j1 + 1, i0:i1 + 1] & inside
        if np.any(bad):
            jj, ii = np.argwhere(bad)[0]
            ci, cj = i0 + ii + 0.5, j0 + jj + 0.5
            # back to ENU for the message: Newton on the fitted map
            e, n = self._index_to_enu(ci, cj)
            raise DemError(f"{self.name}: {what} touches nodata cells at ({round(e, 1) + 0.0:.1f}, "
                           f"{round(n, 1) + 0.0:.1f}) m")

    def _index_to_enu(self, i: float, j: float) -> tuple[float, float]:
        e, n = self._ec, self._nc
        for _ in range(8):
            pi, pj, _ = self._map(e, n, self.u_ref_m)
            d = 1.0
            ie, je, _ = self._map(e + d, n, self.u_ref_m)
            in_, jn, _ = self._map(e, n + d, self.u_ref_m)
            J = np.array([[ie - pi, in_ - pi], [je - pj, jn - pj]], dtype=float).reshape(2, 2)
            step = np.linalg.solve(J, np.array([i - pi, j - pj], dtype=float).ravel())
            e, n = e + float(step[0]), n + float(step[1])
        return float(e), float(n)

    def __repr__(self) -> str:
        w = self.window
        return (f"DemTerrain({self.name!r}, crs={self.crs}, window=({w.col_off}, {w.row_off},"
                f" {w.width}x{w.height}), datum_offset_m={self.datum_offset_m:g})")

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state.pop("_ca_fn", None)  # a CasADi function: rebuilt on use
        state.pop("_to_crs", None)  # a pyproj transformer: rebuilt on load
        state["_crs_wkt"] = self.crs
        return state

    def __setstate__(self, state: dict) -> None:
        from pyproj import Transformer

        self.__dict__.update(state)
        self._to_crs = Transformer.from_crs("EPSG:4326", state["_crs_wkt"], always_xy=True)


_PICTURE_BANDS = ("red", "green", "blue", "alpha", "palette", "hue", "saturation",
                  "lightness", "cyan", "magenta", "yellow", "black")
# vertical units a DEM band may declare (GDAL's unit type), in metres; none means metres
_UNITS_M = {"": 1.0, "m": 1.0, "metre": 1.0, "meter": 1.0, "metres": 1.0, "meters": 1.0,
            "ft": 0.3048, "foot": 0.3048, "feet": 0.3048, "international foot": 0.3048,
            "us-ft": 1200.0 / 3937.0, "ftus": 1200.0 / 3937.0, "us survey foot": 1200.0 / 3937.0,
            "foot_us": 1200.0 / 3937.0, "us_survey_foot": 1200.0 / 3937.0}


def _band_scaling(src, name: str) -> tuple[float, float, float]:
    """(scale, offset, metres per unit) of band 1: GDAL's scale and offset (value = raw x
    scale + offset, e.g. decimetres in int16) and its declared vertical unit (metres or
    feet; another unit is refused)."""
    scale = float(src.scales[0]) if src.scales and src.scales[0] is not None else 1.0
    offset = float(src.offsets[0]) if src.offsets and src.offsets[0] is not None else 0.0
    if not (math.isfinite(scale) and math.isfinite(offset)) or scale == 0.0:
        raise DemError(f"{name}: band 1 declares scale {scale:g} and offset {offset:g}")
    unit = (src.units[0] if src.units else None) or ""
    key = unit.strip().lower()
    if key not in _UNITS_M:
        raise DemError(f"{name}: band 1's heights are in {unit!r}: use metres or feet")
    return scale, offset, _UNITS_M[key]


def _box_ring(e0: float, e1: float, n0: float, n1: float, k: int = 64):
    """Points along the four sides of a box (k per side)."""
    f = np.linspace(0.0, 1.0, k, endpoint=False)
    e = np.concatenate([e0 + f * (e1 - e0), np.full(k, e1), e1 - f * (e1 - e0), np.full(k, e0)])
    n = np.concatenate([np.full(k, n0), n0 + f * (n1 - n0), np.full(k, n1), n1 - f * (n1 - n0)])
    return e, n


def _latlon_text(lat: float, lon: float) -> str:
    return (f"{abs(float(lat)):.5f} {'N' if lat >= 0 else 'S'} "
            f"{abs(float(lon)):.5f} {'E' if lon >= 0 else 'W'}")


def _extent_text(src, pad: float) -> str:
    """What a file covers, for messages: 'the DEM covers latitude 36.70000..36.72000,
    longitude -4.50000..-4.47000' in WGS84: its pixel centres' hull widened by ``pad``
    pixels (its bounds for cells, its outermost posts for posts)."""
    from rasterio.warp import transform_bounds

    lo, hi_c, hi_r = 0.5 - pad, src.width - 0.5 + pad, src.height - 0.5 + pad
    xs, ys = zip(*(src.transform @ (c, r) for c in (lo, hi_c) for r in (lo, hi_r)),
                 strict=True)
    try:
        w, s, e, n = transform_bounds(src.crs, "EPSG:4326", min(xs), min(ys), max(xs),
                                      max(ys), densify_pts=21)
    except Exception:  # a message's detail only
        return "its extent cannot be given in WGS84"
    return f"the DEM covers latitude {s:.5f}..{n:.5f}, longitude {w:.5f}..{e:.5f}"


def _first_line(exc: BaseException) -> str:
    """An exception's first line; rasterio's "See previous exception" gives GDAL's own."""
    text = str(exc).strip() or type(exc).__name__
    if "previous exception" in text and exc.__cause__ is not None:
        return _first_line(exc.__cause__)
    return text.splitlines()[0]


_HGT_NAME = re.compile(r"^[NS]\d{2}[EW]\d{3}$", re.IGNORECASE)
_HGT_POSTS = (1201, 3601)  # 3 and 1 arc-second tiles


def _hgt_problem(path: Path) -> str:
    """Why GDAL refused an ``.hgt`` file, when it is SRTM's: the tile's name (which
    places it) or its size (a truncated download); empty for other files."""
    if path.suffix.lower() != ".hgt" or not path.is_file():
        return ""
    if not _HGT_NAME.match(path.stem):
        return (f"'{path.name}' is not an SRTM tile's name (an SRTM .hgt tile must keep "
                "its tile's name, such as N36W005.hgt: the name places it)")
    size = path.stat().st_size
    sizes = [2 * n * n for n in _HGT_POSTS]
    if size not in sizes:
        posts = " or ".join(f"{n} x {n}" for n in _HGT_POSTS)
        return (f"{size:,} bytes: an SRTM tile holds {posts} two-byte posts "
                f"({' or '.join(f'{b:,}' for b in sizes)} bytes): a truncated download?")
    return ""


def box_of(points_en: Sequence[ArrayLike]) -> tuple[float, float, float, float]:
    """(e_min, e_max, n_min, n_max) of several (M, 2) point sets."""
    p = np.vstack([np.asarray(q, dtype=float).reshape(-1, 2) for q in points_en])
    return float(p[:, 0].min()), float(p[:, 0].max()), float(p[:, 1].min()), float(p[:, 1].max())
