"""Built-in flights: reference paths the vehicle flies, as :class:`Trajectory` objects.

- :class:`SweepsFlight`: the paper's manually piloted circular sweeps (circles of varied
  radii and centres joined by straight transitions) ending with a close pass by a
  responder (sec. Experimental Setup and Results: 23 min at 35-55 m AGL, final pass
  ~11 m from AP_1F).
- :class:`PassFlight`: a short, nearly straight pass (AP_AB: 31 results in 21 s over a
  28 m bounding-box diagonal, sec. NLoS Access Points).
- :class:`WaypointsFlight`: a waypoint list flown at a constant speed.
- :class:`TrajectoryFlight`: any given trajectory (e.g. the planner's).

Heights: ``height_ref = "terrain"`` means metres above the ground beneath (the pilot
holds a height above ground), ``"home"`` metres above the ground at the start point,
``"origin"`` metres above the world frame's origin.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from estimator.records import Trajectory
from sim._config import check_finite, check_positive
from sim.world import MAX_EXTENT_M, World

HeightRef = Literal["terrain", "home", "origin"]


def _check_xy(name: str, e_m: float, n_m: float) -> None:
    check_finite(f"{name} e_m", e_m)
    check_finite(f"{name} n_m", n_m)
    if math.hypot(e_m, n_m) > MAX_EXTENT_M:
        raise ValueError(f"{name} lies beyond {MAX_EXTENT_M:.0f} m of the origin")


def _check_height(name: str, h: float | None) -> None:
    if h is not None:
        check_finite(name, h)
        if not -100.0 <= h <= 500.0:
            raise ValueError(f"{name} {h} m is outside [-100, 500] m")


def _check_speed(name: str, v: float | None) -> None:
    if v is not None:
        check_positive(name, v)
        if v > 30.0:
            raise ValueError(f"{name} {v} m/s is beyond a multirotor")


MAX_PATH_VERTICES = 2_000_000  # 4000 km at 2 m spacing; refused before allocating


class _PathBuilder:
    """Accumulates a polyline with a height per vertex and a duration per segment.

    At most :data:`MAX_PATH_VERTICES` vertices: a spacing that would need more is
    refused (``ValueError``) before anything is allocated."""

    def __init__(self, e_m: float, n_m: float, h_m: float, spacing_m: float) -> None:
        self.e = [np.array([e_m])]
        self.n = [np.array([n_m])]
        self.h = [np.array([h_m])]
        self.dt: list[np.ndarray] = []
        self.spacing = spacing_m
        self.n_vertices = 1

    def _vertices(self, length_m: float, minimum: int) -> int:
        """Reserve the vertices of ``length_m`` of path (at least ``minimum``);
        ValueError beyond the budget."""
        count = length_m / self.spacing
        if not self.n_vertices + count <= MAX_PATH_VERTICES:
            raise ValueError(f"the flight would need more than {MAX_PATH_VERTICES} path "
                             f"points at point_spacing_m {self.spacing:g}: widen the spacing "
                             "or shorten the flight")
        k = max(minimum, math.ceil(count))
        self.n_vertices += k
        return k

    @property
    def last(self) -> tuple[float, float, float]:
        return float(self.e[-1][-1]), float(self.n[-1][-1]), float(self.h[-1][-1])

    def add(self, e: np.ndarray, n: np.ndarray, h: np.ndarray, speed: float) -> None:
        """Append vertices flown at ``speed`` (horizontal, or vertical when climbing)."""
        if len(e):
            e0, n0, h0 = self.last
            seg = np.maximum(
                np.hypot(np.diff(e, prepend=e0), np.diff(n, prepend=n0)),
                np.abs(np.diff(h, prepend=h0)),
            )
            self.e.append(e)
            self.n.append(n)
            self.h.append(h)
            self.dt.append(seg / speed)

    def hover(self, duration_s: float) -> None:
        e0, n0, h0 = self.last
        self.e.append(np.array([e0]))
        self.n.append(np.array([n0]))
        self.h.append(np.array([h0]))
        self.dt.append(np.array([duration_s]))

    def line_to(self, e1: float, n1: float, h1: float, speed: float) -> None:
        e0, n0, h0 = self.last
        length = max(math.hypot(e1 - e0, n1 - n0), abs(h1 - h0))
        if length < 1e-9:
            return
        k = self._vertices(length, 1)
        f = np.arange(1, k + 1) / k
        self.add(e0 + f * (e1 - e0), n0 + f * (n1 - n0), h0 + f * (h1 - h0), speed)

    def arc(
        self,
        ce: float,
        cn: float,
        r: float,
        theta0: float,
        sweep_rad: float,
        h: float,
        speed: float,
    ) -> None:
        k = self._vertices(abs(sweep_rad) * r, 2)
        th = theta0 + sweep_rad * np.arange(1, k + 1) / k
        self.add(ce + r * np.cos(th), cn + r * np.sin(th), np.full(k, h), speed)

    def trajectory(self, world: World, height_ref: HeightRef, name: str) -> Trajectory:
        e = np.concatenate(self.e)
        n = np.concatenate(self.n)
        h = np.concatenate(self.h)
        dt = np.concatenate(self.dt) if self.dt else np.zeros(0)
        t = np.concatenate([[0.0], np.cumsum(dt)])
        ref: Literal["origin", "terrain"] = "terrain"
        if height_ref == "home":
            h = h + float(world.ground_m(e[0], n[0]))
            ref = "origin"
        elif height_ref == "origin":
            ref = "origin"
        o = world.origin
        return Trajectory(t, np.column_stack([e, n, h]), (o.lat_deg, o.lon_deg, o.h_m), ref, name)


@dataclass(frozen=True, kw_only=True)
class Circle:
    """``laps`` turns (fractions allowed) of a circle, entered where the path meets it."""

    center_e_m: float
    center_n_m: float
    radius_m: float
    laps: float = 1.0
    clockwise: bool = False
    height_m: float | None = None  # None: the flight's height
    speed_mps: float | None = None  # None: the flight's speed

    def __post_init__(self) -> None:
        _check_xy("circle centre", self.center_e_m, self.center_n_m)
        check_positive("circle radius_m", self.radius_m)
        check_positive("circle laps", self.laps)
        if self.radius_m > 5000.0 or self.laps > 100.0:
            raise ValueError("circle radius_m must be <= 5000 and laps <= 100")
        _check_height("circle height_m", self.height_m)
        _check_speed("circle speed_mps", self.speed_mps)


@dataclass(frozen=True, kw_only=True)
class ClosePass:
    """A straight pass whose closest approach is ``offset_m`` beside a responder."""

    target: str  # responder name or bssid
    offset_m: float = 9.0  # the paper's closest sample was ~11 m horizontally from AP_1F
    course_deg: float = 45.0  # compass course (clockwise from north)
    length_m: float = 160.0
    height_m: float | None = None
    speed_mps: float | None = None

    def __post_init__(self) -> None:
        check_positive("close_pass offset_m", self.offset_m, allow_zero=True)
        check_finite("close_pass course_deg", self.course_deg)
        check_positive("close_pass length_m", self.length_m)
        _check_height("close_pass height_m", self.height_m)
        _check_speed("close_pass speed_mps", self.speed_mps)


@dataclass(frozen=True, kw_only=True)
class SweepsFlight:
    """Circular sweeps from a start point, optionally ending with a close pass."""

    kind: Literal["sweeps"] = "sweeps"
    start_e_m: float = 0.0
    start_n_m: float = 0.0
    height_ref: Literal["terrain", "home"] = "terrain"
    height_m: float = 45.0  # 35-55 m AGL (sec. Experimental Setup)
    speed_mps: float = 7.0
    circles: tuple[Circle, ...] = ()
    close_pass: ClosePass | None = None
    point_spacing_m: float = 2.0

    def __post_init__(self) -> None:
        _check_xy("start", self.start_e_m, self.start_n_m)
        _check_height("height_m", self.height_m)
        _check_speed("speed_mps", self.speed_mps)
        check_positive("point_spacing_m", self.point_spacing_m)
        if not self.circles and self.close_pass is None:
            raise ValueError("a sweeps flight needs circles or a close pass")

    @property
    def nominal_height_m(self) -> float:
        return self.height_m

    def build(self, world: World) -> Trajectory:
        b = _PathBuilder(self.start_e_m, self.start_n_m, self.height_m, self.point_spacing_m)
        for c in self.circles:
            h = self.height_m if c.height_m is None else c.height_m
            v = self.speed_mps if c.speed_mps is None else c.speed_mps
            e0, n0, _ = b.last
            theta0 = math.atan2(n0 - c.center_n_m, e0 - c.center_e_m)
            b.line_to(
                c.center_e_m + c.radius_m * math.cos(theta0),
                c.center_n_m + c.radius_m * math.sin(theta0),
                h,
                self.speed_mps,
            )
            sweep = 2.0 * math.pi * c.laps * (-1.0 if c.clockwise else 1.0)
            b.arc(c.center_e_m, c.center_n_m, c.radius_m, theta0, sweep, h, v)
        if self.close_pass is not None:
            cp = self.close_pass
            target = world.responder(cp.target)
            h = self.height_m if cp.height_m is None else cp.height_m
            v = self.speed_mps if cp.speed_mps is None else cp.speed_mps
            course = math.radians(cp.course_deg)
            d = np.array([math.sin(course), math.cos(course)])  # ENU unit vector of the course
            normal = np.array([d[1], -d[0]])
            e0, n0, _ = b.last
            here = np.array([e0 - target.e_m, n0 - target.n_m])
            if here @ normal < 0:
                normal = -normal
            closest = np.array([target.e_m, target.n_m]) + cp.offset_m * normal
            ends = [closest - 0.5 * cp.length_m * d, closest + 0.5 * cp.length_m * d]
            near = min(range(2), key=lambda i: float(np.hypot(*(ends[i] - [e0, n0]))))
            b.line_to(*ends[near], h, self.speed_mps)
            b.line_to(*ends[1 - near], h, v)
        return b.trajectory(world, self.height_ref, "sweeps")


@dataclass(frozen=True, kw_only=True)
class PassFlight:
    """A nearly straight pass: a line bowed sideways by ``bow_m`` at its middle."""

    kind: Literal["pass"] = "pass"
    start_e_m: float
    start_n_m: float
    course_deg: float  # compass course (clockwise from north)
    length_m: float
    bow_m: float = 0.0  # sideways (to the right of the course) at mid-pass
    height_ref: Literal["terrain", "home"] = "terrain"
    height_m: float = 45.0
    speed_mps: float = 5.0
    point_spacing_m: float = 1.0

    def __post_init__(self) -> None:
        _check_xy("start", self.start_e_m, self.start_n_m)
        check_finite("course_deg", self.course_deg)
        check_positive("length_m", self.length_m)
        check_finite("bow_m", self.bow_m)
        _check_height("height_m", self.height_m)
        _check_speed("speed_mps", self.speed_mps)
        check_positive("point_spacing_m", self.point_spacing_m)

    @property
    def nominal_height_m(self) -> float:
        return self.height_m

    def build(self, world: World) -> Trajectory:
        b = _PathBuilder(self.start_e_m, self.start_n_m, self.height_m, self.point_spacing_m)
        course = math.radians(self.course_deg)
        d = np.array([math.sin(course), math.cos(course)])
        right = np.array([d[1], -d[0]])
        k = b._vertices(self.length_m, 2)
        f = np.arange(1, k + 1) / k
        side = self.bow_m * np.sin(math.pi * f)
        e = self.start_e_m + f * self.length_m * d[0] + side * right[0]
        n = self.start_n_m + f * self.length_m * d[1] + side * right[1]
        b.add(e, n, np.full(k, self.height_m), self.speed_mps)
        return b.trajectory(world, self.height_ref, "pass")


@dataclass(frozen=True, kw_only=True)
class WaypointsFlight:
    """Straight legs through ``(e_m, n_m, height_m)`` waypoints at ``speed_mps``."""

    kind: Literal["waypoints"] = "waypoints"
    waypoints_m: tuple[tuple[float, float, float], ...]
    height_ref: HeightRef = "terrain"
    speed_mps: float = 5.0
    hover_s: float = 0.0  # hover at every interior waypoint
    point_spacing_m: float = 2.0

    def __post_init__(self) -> None:
        if len(self.waypoints_m) < 2:
            raise ValueError("a waypoints flight needs at least two waypoints")
        for i, (e, n, h) in enumerate(self.waypoints_m):
            _check_xy(f"waypoint {i}", e, n)
            _check_height(f"waypoint {i} height", h)
        _check_speed("speed_mps", self.speed_mps)
        check_positive("hover_s", self.hover_s, allow_zero=True)
        check_positive("point_spacing_m", self.point_spacing_m)

    @property
    def nominal_height_m(self) -> float:
        return float(np.median([w[2] for w in self.waypoints_m]))

    def build(self, world: World) -> Trajectory:
        e0, n0, h0 = self.waypoints_m[0]
        b = _PathBuilder(e0, n0, h0, self.point_spacing_m)
        for i, (e, n, h) in enumerate(self.waypoints_m[1:], start=1):
            b.line_to(e, n, h, self.speed_mps)
            if self.hover_s > 0 and i < len(self.waypoints_m) - 1:
                b.hover(self.hover_s)
        return b.trajectory(world, self.height_ref, "waypoints")


@dataclass(frozen=True, eq=False)
class TrajectoryFlight:
    """Fly a given trajectory (e.g. the planner's output)."""

    trajectory: Trajectory
    kind: Literal["trajectory"] = "trajectory"

    @property
    def nominal_height_m(self) -> float:
        return float(np.median(self.trajectory.enu_m[:, 2]))

    def build(self, world: World) -> Trajectory:
        return self.trajectory


Flight = SweepsFlight | PassFlight | WaypointsFlight | TrajectoryFlight
FLIGHT_KINDS: dict[str, type] = {
    "sweeps": SweepsFlight,
    "pass": PassFlight,
    "waypoints": WaypointsFlight,
}
