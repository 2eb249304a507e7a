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

from estimator._jit import compiled

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
    """pymap3d's enu2geodetic, bit for bit: the arithmetic of each point in compiled
    loops (:func:`_geodetic_prep`, :func:`_geodetic_step`, :func:`_geodetic_finish`:
    the same operations in the same order), NumPy's own arctan, sin, cos, tan and
    arctan2 between them (their SIMD rounding differs from libm's)."""
    x, y, z, u, hxy, huE, beta_arg, inside, degenerate = compiled(_geodetic_prep)(
        east, north, up, *terms, _WGS84_A, _WGS84_B, _E, _E2)
    if degenerate:  # a point at the centre or on the axis: pymap3d's own branches
        return pymap3d.ecef2geodetic(x, y, z)
    beta0 = np.arctan(beta_arg)
    beta = compiled(_geodetic_step)(beta0, np.sin(beta0), np.cos(beta0), u, huE,
                                    _WGS84_A, _WGS84_B, _E2)
    lat = np.arctan(_WGS84_A / _WGS84_B * np.tan(beta))
    return compiled(_geodetic_finish)(beta, lat, np.arctan2(y, x), np.sin(beta), np.cos(beta),
                                      z, hxy, inside, _WGS84_A, _WGS84_B)


_E = float(np.sqrt(_WGS84_A**2 - _WGS84_B**2))  # the ellipsoid's linear eccentricity
_E2 = float(np.float64(_E) ** 2)


def _geodetic_prep(east, north, up, x0, y0, z0, clat0, slat0, clon0, slon0, a, b, E, E2):
    """ENU to ECEF and You's algorithm up to the reduced latitude's argument, per point:
    x, y, z, u, hypot(x, y), hypot(u, E), the argument, inside the ellipsoid (1/0), and
    whether a point is degenerate (u or hypot(x, y) within 1e-8 of 0; the rest is then
    not computed beyond x, y, z)."""
    n = len(east)
    out = np.zeros((8, n))
    a2, b2 = a**2, b**2
    degenerate = False
    for i in range(n):
        t = clat0 * up[i] - slat0 * north[i]
        w = slat0 * up[i] + clat0 * north[i]
        x = x0 + (clon0 * t - slon0 * east[i])
        y = y0 + (slon0 * t + clon0 * east[i])
        z = z0 + w
        x2, y2, z2 = x * x, y * y, z * z
        r = math.sqrt(x2 + y2 + z2)
        r2e = r * r - E2
        u = math.sqrt(0.5 * r2e + 0.5 * np.hypot(r2e, 2 * E * z))
        hxy = np.hypot(x, y)
        out[0, i], out[1, i], out[2, i] = x, y, z
        degenerate = degenerate or abs(u) <= 1e-8 or abs(hxy) <= 1e-8
        if degenerate:
            continue
        huE = np.hypot(u, E)
        out[3, i] = u
        out[4, i], out[5, i], out[6, i] = hxy, huE, huE / u * z / hxy
        out[7, i] = 1.0 if x2 / a2 + y2 / a2 + z2 / b2 < 1 else 0.0
    return out[0], out[1], out[2], out[3], out[4], out[5], out[6], out[7], degenerate


def _geodetic_step(beta, sin_b, cos_b, u, huE, a, b, E2):
    """One Newton step on the reduced latitude (You's eq.)."""
    out = np.empty(len(beta))
    for i in range(len(beta)):
        out[i] = beta[i] + ((b * u[i] - a * huE[i] + E2) * sin_b[i]) / (
            a * huE[i] / cos_b[i] - E2 * cos_b[i])
    return out


def _geodetic_finish(beta, lat, lon, sin_b, cos_b, z, hxy, inside, a, b):
    """Latitude (clamped at the poles), longitude and height, in degrees and metres."""
    lim = math.pi / 2 - 2.220446049250313e-16
    n = len(beta)
    lat_deg, lon_deg, alt = np.empty(n), np.empty(n), np.empty(n)
    for i in range(n):
        la, cb = lat[i], cos_b[i]
        if beta[i] >= lim:
            la, cb = math.pi / 2, 0.0
        elif beta[i] <= -lim:
            la, cb = -math.pi / 2, 0.0
        h = np.hypot(z[i] - b * sin_b[i], hxy[i] - a * cb)
        alt[i] = -h if inside[i] else h
        lat_deg[i] = la * (180.0 / math.pi)
        lon_deg[i] = lon[i] * (180.0 / math.pi)
    return lat_deg, lon_deg, alt


PROJECTIONS = {"tangent": TangentPlaneENU, "wgs84": ExactENU}


def make_frame(kind: str, lat0_deg: float, lon0_deg: float, h0_m: float) -> EnuFrame:
    """Build the ENU frame named ``kind`` (``tangent``: eq. (1); ``wgs84``: exact)."""
    try:
        cls = PROJECTIONS[kind]
    except KeyError as exc:
        raise ValueError(f"unknown projection {kind!r}; choose from {sorted(PROJECTIONS)}") from exc
    return cls(lat0_deg, lon0_deg, h0_m)
