"""Terrain height fields in the world's ENU frame.

A terrain maps horizontal ENU coordinates (metres) to the ground's height ``u`` in the
same frame (metres above the frame origin's tangent plane). Every terrain implements
the planner's terrain protocol (:class:`planner.models.TerrainModel`): ``height_m``
evaluates NumPy arrays and CasADi symbols alike (so the CasADi planner plans over the
simulator's own hills), and ``sag_curvature`` bounds the curvature along any
horizontal line (how far a straight leg can sag towards the ground). Two kinds:

- :class:`HillsTerrain`: an analytic, smooth hilly default (a sum of Gaussian hills and
  a gentle sinusoidal ripple), standing in for the paper's "unstructured, mountainous
  terrain" (sec. Experimental Setup).
- :class:`GridTerrain`: a user-supplied regular grid with bilinear interpolation;
  outside the grid the edge value is held.

A real place's ground comes from a DEM file: :class:`sim.dem.DemTerrain` (GeoTIFF in
any CRS, SRTM ``.hgt``), the same protocol.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike

from sim._config import check_finite, check_positive

MAX_EXTENT_M = 20_000.0  # a search area, not a country: farther points are input errors
# the ground of the Earth spans some -11 km (ocean trenches) to 9 km: no height of a
# terrain above or below the origin's is larger (a larger one is an input error)
MAX_RELIEF_M = 20_000.0
MIN_HILL_SIGMA_M = 0.1  # a narrower Gaussian hill is a typo, not terrain


def check_relief(name: str, value: float) -> None:
    """Raise ``ValueError`` unless ``value`` is a finite height within
    +-:data:`MAX_RELIEF_M` of the origin's."""
    check_finite(name, value)
    if abs(value) > MAX_RELIEF_M:
        raise ValueError(f"{name} {value:g} m is beyond {MAX_RELIEF_M:.0f} m of the origin's "
                         "height (no ground on Earth)")


class Terrain(Protocol):
    def height_m(self, e_m: ArrayLike, n_m: ArrayLike) -> np.ndarray: ...

    def sag_curvature(self) -> tuple[float, float]: ...


def _is_symbolic(x: object) -> bool:
    import casadi as ca

    return isinstance(x, ca.SX | ca.MX | ca.DM)


def bilinear(
    values: np.ndarray,
    x0: float,
    y0: float,
    dx: float,
    dy: float,
    x: ArrayLike,
    y: ArrayLike,
) -> np.ndarray:
    """Bilinear interpolation of ``values[iy, ix]`` sampled at (x0 + ix dx, y0 + iy dy).

    Points outside the grid take the nearest edge value.
    """
    ny, nx = values.shape
    fx = np.clip((np.asarray(x, dtype=float) - x0) / dx, 0.0, nx - 1.0)
    fy = np.clip((np.asarray(y, dtype=float) - y0) / dy, 0.0, ny - 1.0)
    ix = np.minimum(fx.astype(np.intp), max(nx - 2, 0))
    iy = np.minimum(fy.astype(np.intp), max(ny - 2, 0))
    tx = fx - ix
    ty = fy - iy
    ix1 = np.minimum(ix + 1, nx - 1)
    iy1 = np.minimum(iy + 1, ny - 1)
    v00 = values[iy, ix]
    v01 = values[iy, ix1]
    v10 = values[iy1, ix]
    v11 = values[iy1, ix1]
    return (v00 * (1 - tx) + v01 * tx) * (1 - ty) + (v10 * (1 - tx) + v11 * tx) * ty


@dataclass(frozen=True, kw_only=True)
class Hill:
    """One Gaussian hill (negative ``height_m``: a valley)."""

    e_m: float
    n_m: float
    height_m: float
    sigma_m: float

    def __post_init__(self) -> None:
        check_finite("hill e_m", self.e_m)
        check_finite("hill n_m", self.n_m)
        check_relief("hill height_m", self.height_m)
        check_positive("hill sigma_m", self.sigma_m)
        if self.sigma_m < MIN_HILL_SIGMA_M:  # sigma^2 underflowed to 0 (a division by it)
            raise ValueError(f"hill sigma_m {self.sigma_m:g} m is below {MIN_HILL_SIGMA_M:g} m")


# A hillside some 40 m of relief across ~600 m, like the UMA campus slopes
# (sec. Experimental Setup: "unstructured, mountainous terrain").
DEFAULT_HILLS: tuple[Hill, ...] = (
    Hill(e_m=-260.0, n_m=260.0, height_m=28.0, sigma_m=170.0),
    Hill(e_m=260.0, n_m=320.0, height_m=18.0, sigma_m=140.0),
    Hill(e_m=120.0, n_m=-220.0, height_m=-14.0, sigma_m=130.0),
    Hill(e_m=-80.0, n_m=-60.0, height_m=6.0, sigma_m=70.0),
)


@dataclass(frozen=True, kw_only=True)
class HillsTerrain:
    """Analytic smooth terrain: base + slope + Gaussian hills + a sinusoidal ripple."""

    base_m: float = 0.0
    slope_e: float = 0.02  # dimensionless gradient (m per m) towards east
    slope_n: float = 0.04  # ... towards north
    hills: tuple[Hill, ...] = DEFAULT_HILLS
    ripple_amplitude_m: float = 2.5
    ripple_wavelength_m: float = 180.0
    ripple_direction_deg: float = 35.0  # direction of the ripple's wave vector, from east

    def __post_init__(self) -> None:
        for name in ("base_m", "slope_e", "slope_n", "ripple_direction_deg"):
            check_finite(name, getattr(self, name))
        check_relief("base_m", self.base_m)
        check_positive("ripple_amplitude_m", self.ripple_amplitude_m, allow_zero=True)
        check_relief("ripple_amplitude_m", self.ripple_amplitude_m)
        check_positive("ripple_wavelength_m", self.ripple_wavelength_m)
        if abs(self.slope_e) > 1.0 or abs(self.slope_n) > 1.0:
            raise ValueError("terrain slopes steeper than 45 degrees are not flyable terrain")

    def height_m(self, e_m, n_m):
        """Ground height at (e, n): NumPy arrays in, array out; CasADi symbols in, symbol out."""
        if isinstance(e_m, float | int) and isinstance(n_m, float | int):
            return self._height_scalar(float(e_m), float(n_m))
        a = math.radians(self.ripple_direction_deg)
        k = 2.0 * math.pi / self.ripple_wavelength_m
        if _is_symbolic(e_m) or _is_symbolic(n_m):
            import casadi as ca

            h = self.base_m + self.slope_e * e_m + self.slope_n * n_m
            for hill in self.hills:
                r2 = (e_m - hill.e_m) ** 2 + (n_m - hill.n_m) ** 2
                h = h + hill.height_m * ca.exp(-0.5 * r2 / (hill.sigma_m * hill.sigma_m))
            if self.ripple_amplitude_m > 0:
                h = h + self.ripple_amplitude_m * ca.sin(
                    k * (math.cos(a) * e_m + math.sin(a) * n_m))
            return h
        e, n = np.broadcast_arrays(np.asarray(e_m, dtype=float), np.asarray(n_m, dtype=float))
        if e.ndim == 0:
            return self._height_scalar(float(e), float(n))
        # the arithmetic compiled (sim._kernels), NumPy's own exp and sin, point by point
        from sim import _kernels

        shape = e.shape
        e, n = np.ascontiguousarray(e.ravel()), np.ascontiguousarray(n.ravel())
        hc = self._hill_columns()
        h, phase = _kernels.hills_terrain(e, n, self.base_m, self.slope_e, self.slope_n, hc,
                                          np.exp(_kernels.hill_exponents(e, n, hc)),
                                          math.cos(a), math.sin(a), k)
        if self.ripple_amplitude_m > 0:
            h = h + self.ripple_amplitude_m * np.sin(phase)
        return h.reshape(shape)

    def _hill_columns(self) -> np.ndarray:
        """(4, K): the hills' centres e and n, heights and sigma^2."""
        hc = self.__dict__.get("_hc")
        if hc is None:
            hc = np.array([[g.e_m, g.n_m, g.height_m, g.sigma_m * g.sigma_m]
                           for g in self.hills]).reshape(-1, 4).T.copy()
            object.__setattr__(self, "_hc", hc)
        return hc

    def _height_scalar(self, e: float, n: float) -> np.float64:
        """:meth:`height_m` at one point: the same operations in the same order on Python
        floats (the hills' exponentials in one NumPy call, so every value is bit for bit
        the array path's), some 10 x faster than NumPy on 0-d arrays."""
        h = self.base_m + self.slope_e * e + self.slope_n * n
        if self.hills:
            x = []
            for g in self.hills:  # NumPy squares by multiplying (not C pow)
                de, dn = e - g.e_m, n - g.n_m
                x.append(-0.5 * (de * de + dn * dn) / (g.sigma_m * g.sigma_m))
            for g, ex in zip(self.hills, np.exp(x).tolist(), strict=True):
                h = h + g.height_m * ex
        if self.ripple_amplitude_m > 0:
            a = math.radians(self.ripple_direction_deg)
            k = 2.0 * math.pi / self.ripple_wavelength_m
            h = h + self.ripple_amplitude_m * math.sin(k * (math.cos(a) * e + math.sin(a) * n))
        return np.float64(h)

    def max_height_m(self, e_min: float, e_max: float, n_min: float, n_max: float) -> float:
        """An upper bound of the height over the box [e_min, e_max] x [n_min, n_max]:
        the plane at its highest corner, each hill at the box's point nearest its
        centre (a valley at the farthest), the ripple's largest sine over the box's
        phase interval (tight on small boxes: the FTM occlusion tables use them)."""
        h = (self.base_m + max(self.slope_e * e_min, self.slope_e * e_max)
             + max(self.slope_n * n_min, self.slope_n * n_max))
        for g in self.hills:
            if g.height_m > 0:
                de = max(e_min - g.e_m, 0.0, g.e_m - e_max)
                dn = max(n_min - g.n_m, 0.0, g.n_m - n_max)
            else:
                de = max(abs(e_min - g.e_m), abs(e_max - g.e_m))
                dn = max(abs(n_min - g.n_m), abs(n_max - g.n_m))
            h += g.height_m * math.exp(-0.5 * (de * de + dn * dn) / (g.sigma_m * g.sigma_m))
        if self.ripple_amplitude_m > 0:
            a = math.radians(self.ripple_direction_deg)
            k = 2.0 * math.pi / self.ripple_wavelength_m
            ce, sn = k * math.cos(a), k * math.sin(a)
            lo = min(ce * e_min, ce * e_max) + min(sn * n_min, sn * n_max)
            hi = max(ce * e_min, ce * e_max) + max(sn * n_min, sn * n_max)
            crest = 0.5 * math.pi + 2.0 * math.pi * math.ceil((lo - 0.5 * math.pi) / (2 * math.pi))
            top = 1.0 if crest <= hi else max(math.sin(lo), math.sin(hi))
            # + 1e-12: the phase's rounding in height_m (k (cos a e + sin a n))
            h += self.ripple_amplitude_m * min(1.0, top + 1e-12 * (1.0 + abs(lo) + abs(hi)))
        return h

    def sag_curvature(self) -> tuple[float, float]:
        """Bounds (concave, convex) on -T'' and +T'' along any horizontal line (1/m).

        Along a line at offset a from a hill's centre, h exp(-(a^2 + s^2) / 2 sigma^2)
        has a second derivative of at most |h| / sigma^2 on the side of the hill's top
        and 2 e^-1.5 |h| / sigma^2 on the side of its foot; the ripple adds A k^2 either
        way; the plane adds nothing. The bounds add (conservative where the hills do
        not overlap).
        """
        foot = 2.0 * math.exp(-1.5)
        k = 2.0 * math.pi / self.ripple_wavelength_m
        ripple = self.ripple_amplitude_m * k * k
        concave = convex = ripple
        for hill in self.hills:
            c = abs(hill.height_m) / (hill.sigma_m * hill.sigma_m)
            concave += c if hill.height_m > 0 else foot * c
            convex += foot * c if hill.height_m > 0 else c
        return concave, convex


BSPLINE_MIN_NODES = 4  # CasADi's cubic B-spline interpolant: nodes per axis at least


@dataclass(frozen=True, eq=False)
class GridTerrain:
    """Heights on a regular grid, ``heights_m[i_n, i_e]`` at (e0 + i_e s, n0 + i_n s).

    Bilinear in between; outside the grid the nearest edge value is held.
    """

    heights_m: np.ndarray
    e0_m: float
    n0_m: float
    spacing_m: float

    def __post_init__(self) -> None:
        h = np.array(self.heights_m, dtype=float)
        if h.ndim != 2 or h.shape[0] < 2 or h.shape[1] < 2:
            raise ValueError(f"terrain grid must be 2-D with at least 2x2 cells, got {h.shape}")
        if not np.all(np.isfinite(h)):
            raise ValueError("terrain grid holds non-finite heights")
        if np.max(np.abs(h)) > MAX_RELIEF_M:
            raise ValueError(f"terrain grid holds a height beyond {MAX_RELIEF_M:.0f} m of the "
                             f"origin's ({np.max(np.abs(h)):g} m: no ground on Earth)")
        for name in ("e0_m", "n0_m"):
            check_finite(name, getattr(self, name))
            if abs(getattr(self, name)) > MAX_EXTENT_M:
                raise ValueError(f"{name} {getattr(self, name):g} m is beyond "
                                 f"{MAX_EXTENT_M:.0f} m of the origin")
        check_positive("spacing_m", self.spacing_m)
        if self.spacing_m > MAX_EXTENT_M:
            raise ValueError(f"spacing_m {self.spacing_m:g} m is beyond {MAX_EXTENT_M:.0f} m")
        h.setflags(write=False)
        object.__setattr__(self, "heights_m", h)

    @classmethod
    def from_file(cls, path: str | Path, *, e0_m: float, n0_m: float, spacing_m: float):
        """Load a grid from ``.npy`` or a whitespace/comma separated text file (rows: north)."""
        p = Path(path)
        try:
            if p.suffix == ".npy":
                heights = np.load(p, allow_pickle=False)
            else:
                delimiter = "," if p.suffix == ".csv" else None
                heights = np.loadtxt(p, delimiter=delimiter, ndmin=2)
        except OSError as exc:
            raise ValueError(f"cannot read terrain grid {p}: {exc.strerror or exc}") from exc
        except ValueError as exc:
            raise ValueError(f"terrain grid {p} is not a numeric table: {exc}") from exc
        return cls(np.asarray(heights, dtype=float), e0_m, n0_m, spacing_m)

    def height_m(self, e_m, n_m):
        """Bilinear on NumPy arrays; a cubic B-spline through the same grid for CasADi
        symbols (a smooth function Ipopt can differentiate; the planner re-checks its
        paths against this bilinear surface)."""
        if _is_symbolic(e_m) or _is_symbolic(n_m):
            return self._casadi_interpolant()(e_m, n_m)
        s = self.spacing_m
        return bilinear(self.heights_m, self.e0_m, self.n0_m, s, s, e_m, n_m)

    def _casadi_interpolant(self):
        f = self.__dict__.get("_ca_interp")
        if f is None:
            import casadi as ca

            h = self.heights_m
            ny, nx = h.shape
            ge = self.e0_m + self.spacing_m * np.arange(nx)
            gn = self.n0_m + self.spacing_m * np.arange(ny)
            if min(nx, ny) < BSPLINE_MIN_NODES:  # CasADi's cubic B-spline needs 4 nodes an
                # axis: a smaller grid's cells are split (its nodes kept), the new nodes
                # on its own bilinear surface
                def split(g: np.ndarray) -> np.ndarray:
                    k = math.ceil((BSPLINE_MIN_NODES - 1) / (len(g) - 1))
                    return np.linspace(g[0], g[-1], (len(g) - 1) * k + 1)

                ge, gn = split(ge), split(gn)
                E, N = np.meshgrid(ge, gn)
                h = self.height_m(E, N)
            lut = ca.interpolant("terrain", "bspline", [ge.tolist(), gn.tolist()],
                                 np.asarray(h).T.ravel(order="F").tolist())
            e, n = ca.MX.sym("e"), ca.MX.sym("n")
            f = ca.Function("terrain_height", [e, n], [lut(ca.vertcat(e, n))])
            object.__setattr__(self, "_ca_interp", f)
        return lambda e, n: map_elementwise(f, e, n)

    def max_height_m(self, e_min: float, e_max: float, n_min: float, n_max: float) -> float:
        """An upper bound of the height over the box [e_min, e_max] x [n_min, n_max]: the
        highest grid node of the cells it touches (bilinear never exceeds its corners)."""
        ny, nx = self.heights_m.shape
        s = self.spacing_m

        def span(lo: float, hi: float, x0: float, count: int) -> slice:
            i0 = min(max(math.floor((lo - x0) / s), 0), count - 1)
            i1 = min(max(math.ceil((hi - x0) / s), 0), count - 1)
            return slice(i0, i1 + 1)

        cells = self.heights_m[span(n_min, n_max, self.n0_m, ny), span(e_min, e_max, self.e0_m, nx)]
        return float(cells.max())

    def sag_curvature(self) -> tuple[float, float]:
        """Curvature bounds along a line from the grid's second differences (1/m): the
        largest of the row, column and both diagonal second differences, x 1.5 for the
        B-spline's overshoot between nodes."""
        h = self.heights_m
        s = self.spacing_m
        d2 = [np.diff(h, 2, axis=1) / s**2, np.diff(h, 2, axis=0) / s**2]
        if min(h.shape) >= 3:
            diag = (h[2:, 2:] - 2 * h[1:-1, 1:-1] + h[:-2, :-2]) / (2 * s * s)
            anti = (h[2:, :-2] - 2 * h[1:-1, 1:-1] + h[:-2, 2:]) / (2 * s * s)
            d2 += [diag, anti]
        concave = max(float(np.max(-d, initial=0.0)) for d in d2)
        convex = max(float(np.max(d, initial=0.0)) for d in d2)
        return 1.5 * concave, 1.5 * convex


def map_elementwise(f, e, n):
    """Evaluate a scalar CasADi function elementwise over matching row/column vectors."""
    import casadi as ca

    if isinstance(e, ca.SX | ca.MX | ca.DM) and e.numel() > 1:
        shape = e.shape
        m = f.map(e.numel())
        out = m(ca.reshape(e, 1, e.numel()), ca.reshape(n, 1, n.numel()))
        return ca.reshape(out, shape[0], shape[1])
    return f(e, n)
