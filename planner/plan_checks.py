"""Plausibility checks of a plan request: warnings a pilot should read before flying.

- **Swapped coordinates.** Latitude and longitude given in the wrong order are still a
  valid position when both are within [-90, 90] (36.715,-4.478 is Spain; -4.478,36.715
  is Tanzania), so a lone point cannot be checked. Every point of one plan (the centre,
  home, the keep-outs) must however lie within one flight of each other: a point more
  than :data:`MAX_SITE_SPAN_M` from the centre is named, and when swapping its two
  numbers (or the centre's) brings it within that span, the warning says the pair
  looks swapped and shows the swapped pair. A latitude outside [-90, 90] is refused
  by the command with the swapped pair as a hint (:func:`swapped_hint`).
- **Weak geometry.** The estimator's bootstrap refuses a first position when the
  horizontal condition number of its geometry is at or above
  :data:`estimator.geometry.KAPPA_LIMIT` (10, sec. Discussion): a flight whose
  predicted condition number reaches it would end in ``weak_geometry``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from pyproj import Geod

from estimator.geometry import KAPPA_LIMIT

MAX_SITE_SPAN_M = 50_000.0  # beyond any multirotor flight (2 h at 5 m/s is 36 km)
_GEOD = Geod(ellps="WGS84")


def distance_m(a: tuple[float, float], b: tuple[float, float]) -> float:
    """Geodesic distance between two (lat, lon) points on the WGS84 ellipsoid."""
    return float(_GEOD.inv(a[1], a[0], b[1], b[0])[2])


def _valid(lat: float, lon: float) -> bool:
    return -90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0


def swapped_hint(lat: float, lon: float) -> str:
    """`` (swapped? LON,LAT)`` when the swapped pair is a valid position, else ``""``."""
    return f" (latitude and longitude swapped? {lon:g},{lat:g})" if _valid(lon, lat) else ""


def _km(d_m: float) -> str:
    return f"{d_m / 1000:.0f} km" if d_m >= 10_000 else f"{d_m / 1000:.1f} km"


def site_warnings(center: tuple[float, float],
                  points: Sequence[tuple[str, float, float]]) -> list[str]:
    """Warnings for the ``(name, lat, lon)`` points farther than MAX_SITE_SPAN_M from
    ``center`` (lat, lon), saying when a swapped pair would fit (see the module)."""
    out = []
    for name, lat, lon in points:
        d = distance_m(center, (lat, lon))
        if d <= MAX_SITE_SPAN_M:
            continue
        text = (f"{name} {lat:g},{lon:g} is {_km(d)} from --center {center[0]:g},"
                f"{center[1]:g}: more than one flight ({_km(MAX_SITE_SPAN_M)})")
        guesses = []
        if _valid(lon, lat) and distance_m(center, (lon, lat)) <= MAX_SITE_SPAN_M:
            guesses.append(f"{name} {lon:g},{lat:g}")
        c_lat, c_lon = center[1], center[0]
        if _valid(c_lat, c_lon) and distance_m((c_lat, c_lon), (lat, lon)) <= MAX_SITE_SPAN_M:
            guesses.append(f"--center {c_lat:g},{c_lon:g}")
        if guesses:
            text += ("; a latitude and longitude look swapped (did you mean "
                     + " or ".join(guesses) + "?)")
        out.append(text)
    return out


def geometry_warnings(condition_number: float, limit: float = KAPPA_LIMIT) -> list[str]:
    """A warning when the predicted bootstrap condition number reaches the estimator's
    limit (its first position would be refused as ``weak_geometry``)."""
    if math.isfinite(condition_number) and condition_number < limit:
        return []
    kappa = f"{condition_number:.1f}" if math.isfinite(condition_number) else "infinite"
    return [f"the predicted condition number of this flight's geometry is {kappa}, at or "
            f"above the estimator's limit {limit:g}: it will refuse a first position "
            "(status weak_geometry); fly around the point (circles, orbit, helix) or "
            "widen the pass (--offset)"]
