"""The synthetic world: an exact WGS84 ENU frame, terrain and FTM responders."""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numpy as np

from estimator.geodesy import ExactENU
from estimator.records import CONCEALMENT_CLASSES, TruthRecord
from sim._config import check_finite, check_positive
from sim.terrain import MAX_EXTENT_M, HillsTerrain, Terrain

_BSSID_RE = re.compile(r"^[0-9a-f]{2}(:[0-9a-f]{2}){5}$")
# the tallest structures stand some 830 m: an antenna (or an obstacle's top) higher above
# the ground is an input error
MAX_STRUCTURE_M = 1000.0


@dataclass(frozen=True, kw_only=True)
class Origin:
    """WGS84 origin of the ENU frame (``h_m``: ellipsoidal height of the ground there)."""

    lat_deg: float = 36.715  # UMA campus, Malaga (sec. Experimental Setup)
    lon_deg: float = -4.478
    h_m: float = 140.0  # ~90 m above sea level + ~50 m geoid undulation

    def __post_init__(self) -> None:
        for name in ("lat_deg", "lon_deg", "h_m"):
            check_finite(f"origin {name}", getattr(self, name))
        if not -89.0 <= self.lat_deg <= 89.0:
            raise ValueError(f"origin latitude {self.lat_deg} outside [-89, 89] degrees")
        if not -180.0 <= self.lon_deg <= 180.0:
            raise ValueError(f"origin longitude {self.lon_deg} outside [-180, 180] degrees")
        if not -500.0 <= self.h_m <= 9000.0:
            raise ValueError(f"origin height {self.h_m} m is not on the Earth's surface")

    def frame(self) -> ExactENU:
        return ExactENU(self.lat_deg, self.lon_deg, self.h_m)


@dataclass(frozen=True, kw_only=True)
class Responder:
    """An FTM responder (the person's phone or AP) lying on the ground.

    ``e_m``, ``n_m`` place it in the world frame; its antenna is ``antenna_height_m``
    above the terrain. ``range_offset_m`` fixes its hardware range offset; ``None``
    draws one per run (see :class:`sim.ftm.FtmConfig`).
    """

    name: str
    bssid: str
    e_m: float
    n_m: float
    concealment: str = "open"
    antenna_height_m: float = 0.5  # router on the ground (sec. Experimental Setup)
    range_offset_m: float | None = None

    def __post_init__(self) -> None:
        if not self.name:
            raise ValueError("responder name must not be empty")
        bssid = self.bssid.lower()
        if not _BSSID_RE.match(bssid):
            raise ValueError(f"responder {self.name}: bssid {self.bssid!r} is not six hex pairs")
        object.__setattr__(self, "bssid", bssid)
        check_finite(f"responder {self.name} e_m", self.e_m)
        check_finite(f"responder {self.name} n_m", self.n_m)
        if math.hypot(self.e_m, self.n_m) > MAX_EXTENT_M:
            raise ValueError(
                f"responder {self.name} lies {math.hypot(self.e_m, self.n_m):.0f} m from the "
                f"origin (limit {MAX_EXTENT_M:.0f} m)"
            )
        if self.concealment not in CONCEALMENT_CLASSES:
            raise ValueError(
                f"responder {self.name}: concealment {self.concealment!r} is not one of "
                f"{', '.join(CONCEALMENT_CLASSES)}"
            )
        check_positive(
            f"responder {self.name} antenna_height_m", self.antenna_height_m, allow_zero=True
        )
        if self.antenna_height_m > MAX_STRUCTURE_M:
            raise ValueError(f"responder {self.name} antenna_height_m "
                             f"{self.antenna_height_m:g} m is beyond {MAX_STRUCTURE_M:g} m")
        if self.range_offset_m is not None:
            check_finite(f"responder {self.name} range_offset_m", self.range_offset_m)
            if abs(self.range_offset_m) > MAX_EXTENT_M:
                raise ValueError(f"responder {self.name} range_offset_m "
                                 f"{self.range_offset_m:g} m is beyond {MAX_EXTENT_M:.0f} m")


@dataclass(frozen=True, eq=False)
class World:
    """ENU frame at a WGS84 origin, a terrain and the responders on it."""

    origin: Origin
    terrain: Terrain
    responders: tuple[Responder, ...]

    def __post_init__(self) -> None:
        seen: set[str] = set()
        names: set[str] = set()
        for r in self.responders:
            if r.bssid in seen:
                raise ValueError(f"duplicate responder bssid {r.bssid}")
            if r.name in names:
                raise ValueError(f"duplicate responder name {r.name}")
            seen.add(r.bssid)
            names.add(r.name)

    @property
    def frame(self) -> ExactENU:
        return self.origin.frame()

    def ground_m(self, e_m, n_m) -> np.ndarray:
        """Terrain height (ENU up, metres) under horizontal ENU points."""
        return self.terrain.height_m(e_m, n_m)

    def responder_enu_m(self) -> np.ndarray:
        """(K, 3) responder antenna positions: on the terrain plus the antenna height."""
        if not self.responders:
            return np.zeros((0, 3))
        e = np.array([r.e_m for r in self.responders])
        n = np.array([r.n_m for r in self.responders])
        h = np.array([r.antenna_height_m for r in self.responders])
        return np.column_stack([e, n, self.ground_m(e, n) + h])

    def responder(self, key: str) -> Responder:
        """The responder named ``key`` (name or bssid)."""
        for r in self.responders:
            if key in (r.name, r.bssid):
                return r
        raise KeyError(f"no responder named {key!r}")

    def truth_records(self) -> tuple[TruthRecord, ...]:
        """``truth`` log records (lat/lon to 1e-9 degrees, ellipsoidal height to mm)."""
        p = self.responder_enu_m()
        out = []
        for r, (e, n, u) in zip(self.responders, p, strict=True):
            lat, lon, alt = self.frame.to_geodetic(float(e), float(n), float(u))
            out.append(
                TruthRecord(
                    bssid=r.bssid,
                    lat_deg=round(lat, 9),
                    lon_deg=round(lon, 9),
                    alt_m=round(alt, 3),
                    concealment=r.concealment,
                )
            )
        return tuple(out)


def default_world() -> World:
    """The default hilly world with no responders."""
    return World(Origin(), HillsTerrain(), ())
