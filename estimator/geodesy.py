"""Local ENU frames.

:class:`TangentPlaneENU` reproduces the paper's eq. (1) (``enu_projection``) exactly as
the phone computes it: a local tangent plane with R = 6378137 m and the mean latitude
in the cosine. :class:`ExactENU` is the exact WGS84 ellipsoid ENU through pymap3d.
Both map WGS84 (degrees, ellipsoidal height) to metres and back, scalars or arrays.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import pymap3d

EARTH_RADIUS_M = 6378137.0  # R_earth in eq. (1)


class EnuFrame(Protocol):
    lat0_deg: float
    lon0_deg: float
    h0_m: float

    def to_enu(self, lat_deg, lon_deg, alt_m):
        ...

    def to_geodetic(self, e_m, n_m, u_m):
        ...


def _wrap180(deg):
    """Longitude (difference) into [-180, 180]: a frame straddling the antimeridian.

    Values already in range are returned unchanged (bit for bit).
    """
    if isinstance(deg, float | int):
        return deg - 360.0 if deg > 180.0 else deg + 360.0 if deg < -180.0 else deg
    return np.where(deg > 180.0, deg - 360.0, np.where(deg < -180.0, deg + 360.0, deg))


@dataclass(frozen=True)
class TangentPlaneENU:
    """Eq. (1): x = R (lon - lon0) cos((lat + lat0)/2), y = R (lat - lat0), z = h - h0."""

    lat0_deg: float
    lon0_deg: float
    h0_m: float
    radius_m: float = EARTH_RADIUS_M

    name = "tangent"

    def to_enu(self, lat_deg, lon_deg, alt_m):
        if isinstance(lat_deg, float | int) and isinstance(lon_deg, float | int):
            lat = math.radians(lat_deg)
            lat0 = math.radians(self.lat0_deg)
            dlon = _wrap180(lon_deg - self.lon0_deg)
            x = self.radius_m * math.radians(dlon) * math.cos(0.5 * (lat + lat0))
            y = self.radius_m * (lat - lat0)
            return x, y, alt_m - self.h0_m
        lat = np.radians(np.asarray(lat_deg, dtype=float))
        lat0 = math.radians(self.lat0_deg)
        dlon = np.radians(_wrap180(np.asarray(lon_deg, dtype=float) - self.lon0_deg))
        x = self.radius_m * dlon * np.cos(0.5 * (lat + lat0))
        y = self.radius_m * (lat - lat0)
        return x, y, np.asarray(alt_m, dtype=float) - self.h0_m

    def to_geodetic(self, e_m, n_m, u_m):
        """Exact inverse of :meth:`to_enu` (latitude from y first, then longitude)."""
        scalar = isinstance(e_m, float | int) and isinstance(n_m, float | int)
        mod = math if scalar else np
        lat0 = math.radians(self.lat0_deg)
        lat = lat0 + n_m / self.radius_m
        lon = math.radians(self.lon0_deg) + e_m / (self.radius_m * mod.cos(0.5 * (lat + lat0)))
        return mod.degrees(lat), _wrap180(mod.degrees(lon)), u_m + self.h0_m


@dataclass(frozen=True)
class ExactENU:
    """Exact WGS84 East-North-Up at (lat0, lon0, h0), through pymap3d."""

    lat0_deg: float
    lon0_deg: float
    h0_m: float

    name = "wgs84"

    def to_enu(self, lat_deg, lon_deg, alt_m):
        e, n, u = pymap3d.geodetic2enu(
            lat_deg, lon_deg, alt_m, self.lat0_deg, self.lon0_deg, self.h0_m
        )
        if np.ndim(e) == 0:
            return float(e), float(n), float(u)
        return e, n, u

    def to_geodetic(self, e_m, n_m, u_m):
        if _float_vectors(e_m, n_m, u_m):
            return _enu2geodetic_wgs84(self._origin_terms(), e_m, n_m, u_m)
        lat, lon, h = pymap3d.enu2geodetic(
            e_m, n_m, u_m, self.lat0_deg, self.lon0_deg, self.h0_m
        )
        if np.ndim(lat) == 0:
            return float(lat), float(lon), float(h)
        return lat, lon, h

    def _origin_terms(self) -> tuple:
        terms = self.__dict__.get("_terms")
        if terms is None:
            terms = _origin_terms_wgs84(self.lat0_deg, self.lon0_deg, self.h0_m)
            object.__setattr__(self, "_terms", terms)
        return terms


# The array path of ExactENU.to_geodetic: pymap3d's enu2geodetic (enu2ecef then You's
# non-iterative ecef2geodetic) operation for operation, the same NumPy ufuncs in the same
# order, so the results are bit for bit pymap3d's (tests/estimator/test_geodesy.py checks
# it), without its per-call costs (the origin's ECEF position and sines recomputed, the
# ellipsoid rebuilt, masked copies when no point is degenerate).
_WGS84_A = 6378137.0
_WGS84_B = 6356752.31424518


def _float_vectors(*xs) -> bool:
    return all(isinstance(x, np.ndarray) and x.ndim == 1 and x.dtype == np.float64
               for x in xs) and len({x.shape for x in xs}) == 1


def _origin_terms_wgs84(lat0_deg: float, lon0_deg: float, h0_m: float) -> tuple:
    a, b = _WGS84_A, _WGS84_B
    lat0, lon0 = np.radians(lat0_deg), np.radians(lon0_deg)
    n0 = a**2 / np.hypot(a * np.cos(lat0), b * np.sin(lat0))
    x0 = (n0 + h0_m) * np.cos(lat0) * np.cos(lon0)
    y0 = (n0 + h0_m) * np.cos(lat0) * np.sin(lon0)
    z0 = (n0 * (b / a) ** 2 + h0_m) * np.sin(lat0)
    return (x0, y0, z0, np.cos(lat0), np.sin(lat0), np.cos(lon0), np.sin(lon0))


def _enu2geodetic_wgs84(terms: tuple, east, north, up):
    x0, y0, z0, clat0, slat0, clon0, slon0 = terms
    a, b = _WGS84_A, _WGS84_B
    t = clat0 * up - slat0 * north
    w = slat0 * up + clat0 * north
    u_ = clon0 * t - slon0 * east
    v = slon0 * t + clon0 * east
    x, y, z = x0 + u_, y0 + v, z0 + w
    x2, y2, z2 = x**2, y**2, z**2  # each subexpression once: the same values
    r = np.sqrt(x2 + y2 + z2)
    E = np.sqrt(a**2 - b**2)
    r2e = r**2 - E**2
    u = np.sqrt(0.5 * r2e + 0.5 * np.hypot(r2e, 2 * E * z))
    hxy = np.hypot(x, y)
    huE = np.hypot(u, E)
    if (np.abs(u) <= 1e-8).any() or (np.abs(hxy) <= 1e-8).any():  # pymap3d's isclose(., 0)
        return pymap3d.ecef2geodetic(x, y, z)
    Beta = np.arctan(huE / u * z / hxy)
    cos0 = np.cos(Beta)
    Beta += ((b * u - a * huE + E**2) * np.sin(Beta)) / (a * huE / cos0 - E**2 * cos0)
    lat = np.arctan(a / b * np.tan(Beta))
    lim_pi2 = math.pi / 2 - np.finfo(Beta.dtype).eps
    lon = np.arctan2(y, x)
    cosBeta = np.cos(Beta)
    top, bottom = Beta >= lim_pi2, Beta <= -lim_pi2
    if top.any() or bottom.any():
        lat = np.where(top, math.pi / 2, np.where(bottom, -math.pi / 2, lat))
        cosBeta = np.where(top | bottom, 0, cosBeta)
    alt = np.hypot(z - b * np.sin(Beta), hxy - a * cosBeta)
    inside = x2 / a**2 + y2 / a**2 + z2 / b**2 < 1
    if inside.any():
        alt[inside] = -alt[inside]
    return np.degrees(lat), np.degrees(lon), alt


PROJECTIONS = {"tangent": TangentPlaneENU, "wgs84": ExactENU}


def make_frame(kind: str, lat0_deg: float, lon0_deg: float, h0_m: float) -> EnuFrame:
    """Build the ENU frame named ``kind`` (``tangent``: eq. (1); ``wgs84``: exact)."""
    try:
        cls = PROJECTIONS[kind]
    except KeyError as exc:
        raise ValueError(f"unknown projection {kind!r}; choose from {sorted(PROJECTIONS)}") from exc
    return cls(lat0_deg, lon0_deg, h0_m)
