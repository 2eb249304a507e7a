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
        lat, lon, h = pymap3d.enu2geodetic(
            e_m, n_m, u_m, self.lat0_deg, self.lon0_deg, self.h0_m
        )
        if np.ndim(lat) == 0:
            return float(lat), float(lon), float(h)
        return lat, lon, h


PROJECTIONS = {"tangent": TangentPlaneENU, "wgs84": ExactENU}


def make_frame(kind: str, lat0_deg: float, lon0_deg: float, h0_m: float) -> EnuFrame:
    """Build the ENU frame named ``kind`` (``tangent``: eq. (1); ``wgs84``: exact)."""
    try:
        cls = PROJECTIONS[kind]
    except KeyError as exc:
        raise ValueError(f"unknown projection {kind!r}; choose from {sorted(PROJECTIONS)}") from exc
    return cls(lat0_deg, lon0_deg, h0_m)
