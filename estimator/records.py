"""Record types of the flight log (docs/log-format.md) and of the estimator.

Records are small frozen dataclasses with SI units in their names. They never hold
models or callbacks. Log times are integer nanoseconds of the logging device's
monotonic clock; inside the estimator time is float seconds (``t_s``).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field, fields
from typing import TYPE_CHECKING, Literal

if TYPE_CHECKING:
    import numpy as np

Concealment = Literal["open", "vegetation", "vegetation_debris"]
CONCEALMENT_CLASSES: tuple[str, ...] = ("open", "vegetation", "vegetation_debris")
GNSS_FIX_TYPES: tuple[str, ...] = ("none", "2d", "3d", "dgps", "rtk_float", "rtk_fixed")

LOG_FORMAT = "osa-log"
LOG_VERSION = 1


@dataclass(frozen=True, kw_only=True)
class LogHeader:
    """``header`` record: who recorded the log and its pre-flight configuration."""

    format: str = LOG_FORMAT
    version: int = LOG_VERSION
    agent: str = "unknown"
    start_utc: str | None = None
    agl_m: float | None = None  # configured H_AGL (sec. Gauss-Newton Bootstrap, eq. 5)
    range_offset_m: float | None = None  # pre-flight calibration offset b0 (sec. Range Model)
    extra: dict = field(default_factory=dict, compare=False, hash=False)


def records_from_columns(cls: type, columns: dict[str, list]) -> list:
    """``cls(**row)`` for each row of the equal-length ``columns``, which name every
    field of the record class ``cls``: the same frozen, equal-comparing objects, built
    without the dataclass ``__init__`` (a fifth of its cost) for producers of checked
    values by the thousand (the simulator's phone)."""
    names = tuple(columns)
    if set(names) != _field_names(cls):
        raise ValueError(f"columns {sorted(names)} are not the fields of {cls.__name__}")
    new = object.__new__
    out = []
    for row in zip(*columns.values(), strict=True):
        rec = new(cls)
        rec.__dict__.update(zip(names, row))  # noqa: B905 (rows have one value per name)
        out.append(rec)
    return out


@functools.cache
def _field_names(cls: type) -> frozenset[str]:
    return frozenset(f.name for f in fields(cls))


@dataclass(frozen=True, kw_only=True)
class GnssFix:
    """``gnss`` record: one fix of the initiator's antenna (WGS84, ellipsoidal height)."""

    t_ns: int
    lat_deg: float
    lon_deg: float
    alt_m: float
    acc_m: float
    vacc_m: float | None = None
    fix: str | None = None
    sats: int | None = None

    @property
    def t_s(self) -> float:
        return self.t_ns * 1e-9


@dataclass(frozen=True, kw_only=True)
class RangeSample:
    """``rtt`` record: one IEEE 802.11mc FTM ranging result to one responder."""

    t_ns: int
    bssid: str
    status: str
    range_m: float | None = None
    range_std_m: float | None = None
    rssi_dbm: float | None = None
    attempted: int | None = None
    successful: int | None = None

    @property
    def t_s(self) -> float:
        return self.t_ns * 1e-9

    @property
    def ok(self) -> bool:
        return self.status == "ok" and self.range_m is not None


@dataclass(frozen=True, kw_only=True)
class TruthRecord:
    """``truth`` record (simulator only): surveyed responder position."""

    bssid: str
    lat_deg: float
    lon_deg: float
    alt_m: float
    concealment: str = "open"


@dataclass(frozen=True, kw_only=True)
class AssociatedRange:
    """A corrected FTM range with its GNSS-interpolated anchor: the estimator's unit of work.

    ``range_m`` is the corrected range d = max(0, d_raw - b0) (sec. Range Measurement
    Model); ``anchor_enu_m`` the initiator position u_i in the replay's ENU frame.
    """

    t_s: float
    bssid: str
    range_m: float
    rssi_dbm: float | None
    anchor_enu_m: tuple[float, float, float]
    anchor_acc_m: float
    anchor_vacc_m: float | None = None
    agl_m: float | None = None  # H_AGL of the agent that measured it (None: pipeline default)
    agent: str = ""
    anchor_fix: str | None = None  # GNSS fix type of the anchor (GNSS_FIX_TYPES), if logged


EstimateStatus = Literal[
    "converged", "tracking", "bootstrapping", "weak_geometry", "diverged", "no_data", "ambiguous"
]
STATUSES: tuple[str, ...] = (
    "converged",
    "tracking",
    "bootstrapping",
    "weak_geometry",
    "diverged",
    "no_data",
    "ambiguous",
)


@dataclass(frozen=True, kw_only=True)
class Candidate:
    """One of several positions the data cannot tell apart (status ``ambiguous``)."""

    mean_enu_m: tuple[float, float, float]
    lat_deg: float
    lon_deg: float
    alt_m: float
    sigma_h_m: float
    weight: float  # relative likelihood; the candidates' weights sum to 1


@dataclass(frozen=True, kw_only=True)
class Estimate:
    """What the estimator says of one responder in one mode at time ``t_s``.

    Position fields (``mean_enu_m``, ``cov_m2``, ``lat_deg``...) are ``None`` when there
    is no estimate yet (``bootstrapping``, ``weak_geometry``, ``no_data``...). ENU is the
    estimator's frame (:attr:`estimator.online.OnlineEstimator.frame`); ``cov_m2`` is the
    3 x 3 position covariance. ``t_s`` is the estimator's timeline (the phone clock of
    the first agent, shifted by the agents' start times when several are fused).
    """

    t_s: float
    bssid: str
    mode: str
    status: str
    mean_enu_m: tuple[float, float, float] | None = None
    cov_m2: tuple[tuple[float, float, float], ...] | None = None
    lat_deg: float | None = None
    lon_deg: float | None = None
    alt_m: float | None = None
    bias_m: float | None = None
    sigma_h_m: float | None = None
    sigma_z_m: float | None = None
    r95_h_m: float | None = None
    stable: bool = False
    n_meas: int = 0
    n_bootstrap: int = 0
    n_acc: int = 0
    n_gate: int = 0
    kappa: float | None = None
    candidates: tuple[Candidate, ...] = ()

    @property
    def has_position(self) -> bool:
        return self.mean_enu_m is not None

    @property
    def converged(self) -> bool:
        return self.status == "converged"


@dataclass(frozen=True, eq=False)
class Trajectory:
    """A timed flight path in a local ENU frame: the planner's output, flown by ``sim``.

    ``enu_m`` is (N, 3). ``height_ref`` says what z means: ``"origin"`` (metres above
    the frame origin, i.e. above home for a mission) or ``"terrain"`` (metres above the
    ground under each point; the vehicle resolves it with its terrain model).
    ``origin`` is the WGS84 (lat_deg, lon_deg, h_m) of the ENU frame.
    """

    t_s: np.ndarray
    enu_m: np.ndarray
    origin: tuple[float, float, float]
    height_ref: Literal["origin", "terrain"] = "origin"
    name: str = ""

    def __post_init__(self) -> None:
        import numpy as np

        t = np.asarray(self.t_s, dtype=float)
        p = np.asarray(self.enu_m, dtype=float)
        if p.ndim != 2 or p.shape[1] != 3 or t.shape != (p.shape[0],):
            raise ValueError("Trajectory needs t_s (N,) and enu_m (N, 3)")
        if not (np.isfinite(t).all() and np.isfinite(p).all()):
            raise ValueError("Trajectory holds non-finite values")
        if len(t) > 1 and (t[1:] < t[:-1]).any():
            raise ValueError("Trajectory times must be non-decreasing")
        object.__setattr__(self, "t_s", t)
        object.__setattr__(self, "enu_m", p)

    @property
    def duration_s(self) -> float:
        return float(self.t_s[-1] - self.t_s[0]) if len(self.t_s) else 0.0

    @property
    def length_m(self) -> float:
        import numpy as np

        if len(self.t_s) < 2:
            return 0.0
        return float(np.linalg.norm(np.diff(self.enu_m, axis=0), axis=1).sum())
