"""Search and localisation flight patterns as timed ENU trajectories.

Every pattern is a chain of exact segments (straight lines and circular arcs, an arc
optionally climbing: a helix) flown at a constant commanded speed and sampled every
``dt_s`` seconds along the arc length, plus the exact end point. Points on arcs lie on
the circle (no chord error). With ``start_enu_m`` the trajectory begins there and flies
straight to the pattern's first point (climbing or descending on the way).

Heights: ``alt_m`` is z in the trajectory's frame: metres above the frame origin
(``height_ref="origin"``; with origin = home this is a mission's relative altitude) or
above the terrain under the drone (``height_ref="terrain"``). Headings are degrees
clockwise from north, as on a map.

The patterns are those the paper recommends (sec. Discussion, Bootstrap Geometry and
Flight Planning): lawnmower, expanding square, helix, concentric circles with altitude
steps, a close pass (the AP_1F close approach, sec. Results) and an orbit. The lawnmower
track spacing comes from the detection range: spacing = 2 R_det (1 - overlap), with
R_det the horizontal distance at which the response probability falls to ``p_detect``
at the flight height (:func:`detection_range_m`).

Airspace types (a convex keep-in fence, keep-out cylinders and polygons, each with an
optional top above the ground) and their check live here too, shared by the patterns,
the search area, the optimal planner and the mission export.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from estimator.geodesy import ExactENU
from estimator.geometry import (
    crossing_text,
    polygon_area_m2,
    polygon_crossing,
    signed_distance_to_polygon_m,
)
from estimator.records import Trajectory
from planner.models import LinkModel, LogisticLink, slant_at

# University of Malaga campus (sec. Experimental Setup); h = 140 m is the ellipsoidal
# height of the ground there, the same default origin as sim.world.Origin, so a default
# pattern flown in the simulator is above ground, not 140 m under it
PAPER_SITE = (36.715, -4.478, 140.0)
DEFAULT_LINK = LogisticLink()


@dataclass(frozen=True, kw_only=True)
class FlightConfig:
    """How a pattern is flown and sampled."""

    speed_m_s: float = 5.0  # our choice: slow enough for 4 Hz ranging every 1.25 m
    alt_m: float = 45.0  # the paper flew 35-55 m AGL (sec. Experimental Setup)
    dt_s: float = 0.5  # sample period of the output trajectory
    height_ref: Literal["origin", "terrain"] = "origin"
    origin: tuple[float, float, float] = PAPER_SITE  # WGS84 of the ENU frame (home)

    def __post_init__(self) -> None:
        for name in ("speed_m_s", "dt_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be positive and finite, got {v!r}")
        if not math.isfinite(self.alt_m):
            raise ValueError("alt_m must be finite")
        if self.height_ref not in ("origin", "terrain"):
            raise ValueError(f"unknown height_ref {self.height_ref!r}")
        lat, lon, h = self.origin
        if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0 and math.isfinite(h)):
            raise ValueError(f"origin out of range: {self.origin!r}")


# --------------------------------------------------------------------------- segments


@dataclass(frozen=True)
class Line:
    """Straight segment from ``a`` to ``b`` (ENU, metres)."""

    a: tuple[float, float, float]
    b: tuple[float, float, float]

    @property
    def length_m(self) -> float:
        return float(np.linalg.norm(np.subtract(self.b, self.a)))

    def at(self, s_m: np.ndarray) -> np.ndarray:
        L = self.length_m
        f = np.zeros_like(s_m) if L == 0 else s_m / L
        return np.asarray(self.a)[None, :] + f[:, None] * np.subtract(self.b, self.a)[None, :]


@dataclass(frozen=True)
class Arc:
    """Circular arc (a helix when z0 != z1): centre (x, y), radius, start angle and
    signed sweep (rad, counter-clockwise positive), heights at both ends."""

    cx: float
    cy: float
    radius: float
    theta0: float
    sweep: float
    z0: float
    z1: float

    @property
    def length_m(self) -> float:
        return math.hypot(self.radius * self.sweep, self.z1 - self.z0)

    def at(self, s_m: np.ndarray) -> np.ndarray:
        L = self.length_m
        f = np.zeros_like(s_m) if L == 0 else s_m / L
        th = self.theta0 + f * self.sweep
        return np.column_stack(
            [
                self.cx + self.radius * np.cos(th),
                self.cy + self.radius * np.sin(th),
                self.z0 + f * (self.z1 - self.z0),
            ]
        )

    def point(self, f: float) -> tuple[float, float, float]:
        th = self.theta0 + f * self.sweep
        return (
            self.cx + self.radius * math.cos(th),
            self.cy + self.radius * math.sin(th),
            self.z0 + f * (self.z1 - self.z0),
        )


Segment = Line | Arc


def _start_point(seg: Segment) -> tuple[float, float, float]:
    return seg.a if isinstance(seg, Line) else seg.point(0.0)


def segments_to_trajectory(
    segments: Sequence[Segment],
    flight: FlightConfig,
    name: str,
    start_enu_m: Sequence[float] | None = None,
) -> Trajectory:
    """Fly ``segments`` at ``flight.speed_m_s``, sampled every ``flight.dt_s``."""
    segs: list[Segment] = list(segments)
    if not segs:
        raise ValueError("a pattern needs at least one segment")
    if start_enu_m is not None:
        s0 = tuple(float(v) for v in start_enu_m)
        if len(s0) != 3 or not all(math.isfinite(v) for v in s0):
            raise ValueError("start_enu_m must be 3 finite numbers")
        first = _start_point(segs[0])
        if math.dist(s0, first) > 1e-9:
            segs.insert(0, Line(s0, first))  # type: ignore[arg-type]
    lengths = np.array([s.length_m for s in segs])
    ends = np.cumsum(lengths)
    total = float(ends[-1])
    step = flight.speed_m_s * flight.dt_s
    n = math.floor(total / step + 1e-9)
    s = np.arange(n + 1) * step
    if total - s[-1] > 1e-9:
        s = np.append(s, total)
    idx = np.minimum(np.searchsorted(ends, s, side="right"), len(segs) - 1)
    starts = ends - lengths
    pts = np.empty((len(s), 3))
    for k, seg in enumerate(segs):
        sel = idx == k
        if np.any(sel):
            pts[sel] = seg.at(np.clip(s[sel] - starts[k], 0.0, seg.length_m))
    return Trajectory(
        t_s=s / flight.speed_m_s,
        enu_m=pts,
        origin=flight.origin,
        height_ref=flight.height_ref,
        name=name,
    )


# --------------------------------------------------------------------------- helpers


def detection_range_m(
    alt_m: float, link: LinkModel = DEFAULT_LINK, p_detect: float = 0.5,
    concealment: str = "open",
) -> float:
    """Horizontal distance at which P(response) = p_detect for an AP ``alt_m`` below."""
    slant = slant_at(link, p_detect, concealment)
    if slant <= abs(alt_m):
        raise ValueError(
            f"no detection at {alt_m:g} m height (the {p_detect:.0%} response reach is"
            f" {slant:.1f} m slant): fly lower or give the track spacing"
        )
    return math.sqrt(slant * slant - alt_m * alt_m)


def lawnmower_spacing_m(detection_range: float, overlap: float = 0.5) -> float:
    """Track spacing 2 R_det (1 - overlap): overlap 0.5 puts every point within R_det of
    two tracks, i.e. ranged from two sides (bearing diversity for the bootstrap)."""
    if not (detection_range > 0 and 0.0 <= overlap < 1.0):
        raise ValueError("need detection_range > 0 and 0 <= overlap < 1")
    return 2.0 * detection_range * (1.0 - overlap)


def _xy(center: Sequence[float]) -> tuple[float, float]:
    if len(center) < 2 or not all(math.isfinite(float(c)) for c in center[:2]):
        raise ValueError("center must hold finite east, north (m)")
    return float(center[0]), float(center[1])


def _positive(name: str, v: float) -> float:
    if not (math.isfinite(v) and v > 0):
        raise ValueError(f"{name} must be positive and finite, got {v!r}")
    return float(v)


def _heading_axes(heading_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """Unit vector along the heading (clockwise from north) and the one 90 deg right."""
    h = math.radians(heading_deg)
    along = np.array([math.sin(h), math.cos(h)])
    right = np.array([along[1], -along[0]])
    return along, right


def _entry_angle(cx: float, cy: float, start: Sequence[float] | None, default: float) -> float:
    if start is None:
        return default
    dx, dy = float(start[0]) - cx, float(start[1]) - cy
    return math.atan2(dy, dx) if math.hypot(dx, dy) > 1e-9 else default


# --------------------------------------------------------------------------- patterns


def lawnmower(
    center_enu_m: Sequence[float],
    half_width_m: float,
    *,
    spacing_m: float | None = None,
    half_length_m: float | None = None,
    heading_deg: float = 0.0,
    overlap: float = 0.5,
    link: LinkModel = DEFAULT_LINK,
    flight: FlightConfig = FlightConfig(),
    start_enu_m: Sequence[float] | None = None,
) -> Trajectory:
    """Boustrophedon over a rectangle centred on ``center_enu_m``.

    Tracks run along ``heading_deg`` (length 2 x ``half_length_m``, default the width)
    and step right across 2 x ``half_width_m``: n = ceil(2 hw / spacing) tracks exactly
    ``spacing_m`` apart, centred on the rectangle. The outer tracks therefore sit
    (2 hw - (n - 1) spacing) / 2 in from the edges: half a spacing only when 2 hw /
    spacing is an integer, less otherwise (never 0: every point of the rectangle is
    within half a spacing of a track). ``spacing_m`` defaults to
    :func:`lawnmower_spacing_m` of the detection range at ``flight.alt_m``.
    """
    cx, cy = _xy(center_enu_m)
    hw = _positive("half_width_m", half_width_m)
    hl = hw if half_length_m is None else _positive("half_length_m", half_length_m)
    if spacing_m is None:
        spacing_m = lawnmower_spacing_m(detection_range_m(flight.alt_m, link), overlap)

    segs = lawnmower_segments((cx, cy), hw, spacing_m, half_length_m=hl,
                              heading_deg=heading_deg, alt_m=flight.alt_m)
    return segments_to_trajectory(segs, flight, "lawnmower", start_enu_m)


MAX_TRACKS = 100_000  # tracks of one area pattern: far beyond any flight, refused before


def _legs(n: float) -> float:
    """The number of tracks of an area pattern, refused (ValueError) before anything is
    built when absurd (a spacing of 1e-9 m would need 3e11 of them)."""
    if not n <= MAX_TRACKS:
        raise ValueError(f"the area at this spacing needs {n:.3g} tracks (more than "
                         f"{MAX_TRACKS}): widen --spacing or reduce --radius")
    return n


def lawnmower_segments(
    center_enu_m: Sequence[float],
    half_width_m: float,
    spacing_m: float,
    *,
    half_length_m: float | None = None,
    heading_deg: float = 0.0,
    alt_m: float = 45.0,
) -> list[Segment]:
    """The lines of :func:`lawnmower` for a given track spacing (two per track, nothing
    sampled: cheap for any size)."""
    cx, cy = _xy(center_enu_m)
    hw = _positive("half_width_m", half_width_m)
    hl = hw if half_length_m is None else _positive("half_length_m", half_length_m)
    sp = _positive("spacing_m", spacing_m)
    n_tracks = max(1, math.ceil(_legs(2.0 * hw / sp) - 1e-9))
    along, right = _heading_axes(heading_deg)
    c = np.array([cx, cy])
    z = float(alt_m)
    pts: list[tuple[float, float, float]] = []
    for i in range(n_tracks):
        off = (i - (n_tracks - 1) / 2.0) * sp
        sign = 1.0 if i % 2 == 0 else -1.0
        for end in (-sign, sign):
            xy = c + off * right + end * hl * along
            pts.append((float(xy[0]), float(xy[1]), z))
    return [Line(a, b) for a, b in itertools.pairwise(pts)] or [Line(pts[0], pts[0])]


def expanding_square(
    center_enu_m: Sequence[float],
    half_width_m: float,
    *,
    spacing_m: float | None = None,
    heading_deg: float = 0.0,
    clockwise: bool = True,
    overlap: float = 0.5,
    link: LinkModel = DEFAULT_LINK,
    flight: FlightConfig = FlightConfig(),
    start_enu_m: Sequence[float] | None = None,
) -> Trajectory:
    """The IAMSAR expanding square search from the datum ``center_enu_m``.

    Legs of S, S, 2S, 2S, 3S, ... turning 90 deg (right when ``clockwise``), first leg
    along ``heading_deg``; parallel neighbouring legs are S apart. It stops after the
    first pair of legs at least 2 x ``half_width_m`` long plus one closing leg.
    """
    cx, cy = _xy(center_enu_m)
    hw = _positive("half_width_m", half_width_m)
    if spacing_m is None:
        spacing_m = lawnmower_spacing_m(detection_range_m(flight.alt_m, link), overlap)

    segs = expanding_square_segments((cx, cy), hw, spacing_m, heading_deg=heading_deg,
                                     clockwise=clockwise, alt_m=flight.alt_m)
    return segments_to_trajectory(segs, flight, "expanding-square", start_enu_m)


def expanding_square_segments(
    center_enu_m: Sequence[float],
    half_width_m: float,
    spacing_m: float,
    *,
    heading_deg: float = 0.0,
    clockwise: bool = True,
    alt_m: float = 45.0,
) -> list[Segment]:
    """The legs of :func:`expanding_square` for a given spacing (nothing sampled)."""
    cx, cy = _xy(center_enu_m)
    hw = _positive("half_width_m", half_width_m)
    sp = _positive("spacing_m", spacing_m)
    along, right = _heading_axes(heading_deg)
    turn = right if clockwise else -right
    dirs = [along, turn, -along, -turn]
    m_max = max(1, math.ceil(_legs(2.0 * hw / sp) - 1e-9))
    lengths = [sp * (k // 2 + 1) for k in range(2 * m_max)] + [sp * m_max]
    p = np.array([cx, cy])
    z = float(alt_m)
    pts = [(cx, cy, z)]
    for k, L in enumerate(lengths):
        p = p + L * dirs[k % 4]
        pts.append((float(p[0]), float(p[1]), z))
    return [Line(a, b) for a, b in itertools.pairwise(pts)]


def orbit(
    center_enu_m: Sequence[float],
    radius_m: float,
    *,
    turns: float = 1.0,
    clockwise: bool = False,
    start_angle_rad: float | None = None,
    flight: FlightConfig = FlightConfig(),
    start_enu_m: Sequence[float] | None = None,
) -> Trajectory:
    """Circle(s) of ``radius_m`` at ``flight.alt_m``; entry on the side facing the start."""
    return helix(
        center_enu_m,
        radius_m,
        alt_start_m=flight.alt_m,
        alt_end_m=flight.alt_m,
        turns=turns,
        clockwise=clockwise,
        start_angle_rad=start_angle_rad,
        flight=flight,
        start_enu_m=start_enu_m,
        name="orbit",
    )


def helix(
    center_enu_m: Sequence[float],
    radius_m: float,
    *,
    alt_start_m: float,
    alt_end_m: float,
    turns: float = 3.0,
    clockwise: bool = False,
    start_angle_rad: float | None = None,
    flight: FlightConfig = FlightConfig(),
    start_enu_m: Sequence[float] | None = None,
    name: str = "helix",
) -> Trajectory:
    """Climbing (alt_end > alt_start) or descending orbit of ``turns`` turns."""
    segs = helix_segments(center_enu_m, radius_m, alt_start_m=alt_start_m,
                          alt_end_m=alt_end_m, turns=turns, clockwise=clockwise,
                          start_angle_rad=start_angle_rad, start_enu_m=start_enu_m)
    return segments_to_trajectory(segs, flight, name, start_enu_m)


def helix_segments(
    center_enu_m: Sequence[float],
    radius_m: float,
    *,
    alt_start_m: float,
    alt_end_m: float,
    turns: float = 3.0,
    clockwise: bool = False,
    start_angle_rad: float | None = None,
    start_enu_m: Sequence[float] | None = None,
) -> list[Segment]:
    """The one arc of :func:`helix` (entered on the side facing ``start_enu_m``)."""
    cx, cy = _xy(center_enu_m)
    r = _positive("radius_m", radius_m)
    t = _positive("turns", turns)
    if not (math.isfinite(alt_start_m) and math.isfinite(alt_end_m)):
        raise ValueError("altitudes must be finite")
    th0 = start_angle_rad if start_angle_rad is not None else _entry_angle(cx, cy, start_enu_m, 0.0)
    sweep = (-1.0 if clockwise else 1.0) * 2.0 * math.pi * t
    return [Arc(cx, cy, r, th0, sweep, float(alt_start_m), float(alt_end_m))]


def concentric_circles(
    center_enu_m: Sequence[float],
    radii_m: Sequence[float],
    *,
    alts_m: Sequence[float] | None = None,
    alt_step_m: float = 10.0,
    clockwise: bool = False,
    flight: FlightConfig = FlightConfig(),
    start_enu_m: Sequence[float] | None = None,
) -> Trajectory:
    """One full circle per radius (in the order given), each at its own altitude.

    Altitudes default to ``flight.alt_m + k * alt_step_m`` for ring k; the drone moves
    between rings radially, changing altitude on the way.
    """
    segs = concentric_circles_segments(center_enu_m, radii_m, alts_m=alts_m,
                                       alt_step_m=alt_step_m, clockwise=clockwise,
                                       flight=flight, start_enu_m=start_enu_m)
    return segments_to_trajectory(segs, flight, "circles", start_enu_m)


def concentric_circles_segments(
    center_enu_m: Sequence[float],
    radii_m: Sequence[float],
    *,
    alts_m: Sequence[float] | None = None,
    alt_step_m: float = 10.0,
    clockwise: bool = False,
    flight: FlightConfig = FlightConfig(),
    start_enu_m: Sequence[float] | None = None,
) -> list[Segment]:
    """The arcs and radial transitions of :func:`concentric_circles`."""
    cx, cy = _xy(center_enu_m)
    radii = [_positive("radius", float(r)) for r in radii_m]
    if not radii:
        raise ValueError("need at least one radius")
    if alts_m is None:
        alts = [flight.alt_m + k * alt_step_m for k in range(len(radii))]
    else:
        alts = [float(a) for a in alts_m]
        if len(alts) != len(radii) or not all(math.isfinite(a) for a in alts):
            raise ValueError("one finite altitude per radius")
    th0 = _entry_angle(cx, cy, start_enu_m, 0.0)
    sweep = (-1.0 if clockwise else 1.0) * 2.0 * math.pi
    segs: list[Segment] = []
    for k, (r, z) in enumerate(zip(radii, alts, strict=True)):
        arc = Arc(cx, cy, r, th0, sweep, z, z)
        if k:
            segs.append(Line(segs[-1].point(1.0), arc.point(0.0)))  # type: ignore[union-attr]
        segs.append(arc)
    return segs


def close_pass(
    prior_enu_m: Sequence[float],
    offset_m: float,
    *,
    leg_length_m: float = 200.0,
    heading_deg: float = 0.0,
    flight: FlightConfig = FlightConfig(),
    start_enu_m: Sequence[float] | None = None,
) -> Trajectory:
    """A straight fly-by along ``heading_deg`` whose closest approach passes
    ``offset_m`` (horizontal, to the right of the track; negative: left) from the prior
    AP, centred on the closest approach. The paper's AP_1F fix came from such a pass at
    about 11 m (sec. Results)."""
    segs = close_pass_segments(prior_enu_m, offset_m, leg_length_m=leg_length_m,
                               heading_deg=heading_deg, flight=flight)
    return segments_to_trajectory(segs, flight, "close-pass", start_enu_m)


def close_pass_segments(
    prior_enu_m: Sequence[float],
    offset_m: float,
    *,
    leg_length_m: float = 200.0,
    heading_deg: float = 0.0,
    flight: FlightConfig = FlightConfig(),
) -> list[Segment]:
    """The one straight leg of :func:`close_pass`."""
    px, py = _xy(prior_enu_m)
    if not math.isfinite(offset_m):
        raise ValueError("offset_m must be finite")
    L = _positive("leg_length_m", leg_length_m)
    along, right = _heading_axes(heading_deg)
    mid = np.array([px, py]) - offset_m * right  # the AP lies offset_m to the right
    a = mid - 0.5 * L * along
    b = mid + 0.5 * L * along
    z = flight.alt_m
    return [Line((float(a[0]), float(a[1]), z), (float(b[0]), float(b[1]), z))]


@dataclass(frozen=True)
class PathEstimate:
    """What flying some segments costs, known before any sample is computed."""

    length_m: float  # from the start point (if any), through the segments, home (if any)
    duration_s: float  # at the commanded speed (no acceleration or wind)
    n_waypoints: int  # a lower bound of the waypoints kept by decimation


def estimate_path(
    segments: Sequence[Segment],
    flight: FlightConfig,
    *,
    start_enu_m: Sequence[float] | None = None,
    end_enu_m: Sequence[float] | None = None,
    tolerance_m: float = 1.0,
) -> PathEstimate:
    """Length, flight time and waypoint count of flying ``segments`` from
    ``start_enu_m`` and back to ``end_enu_m`` (e.g. home for a return to launch), in
    O(segments): the check a planner runs before sampling a path of any size.

    Waypoints, a lower bound of what Douglas-Peucker keeps: the start, one per line end
    and, per arc of radius r, the chords whose sagitta is ``tolerance_m`` (angle
    2 acos(1 - tol / r) each). Sampling misses exact corners, so a mission often holds
    up to about 1.5 times as many.
    """
    length = sum(s.length_m for s in segments)
    n = 1
    for seg in segments:
        if isinstance(seg, Arc):
            r = max(seg.radius, 1e-9)
            chord = 2.0 * math.acos(max(-1.0, 1.0 - tolerance_m / r)) if tolerance_m > 0 else 0
            n += max(1, math.ceil(abs(seg.sweep) / chord)) if chord > 0 else 10**9
        else:
            n += 1
    if segments and start_enu_m is not None:
        length += math.dist(tuple(float(v) for v in start_enu_m), _start_point(segments[0]))
    if segments and end_enu_m is not None:
        last = segments[-1]
        end = last.b if isinstance(last, Line) else last.point(1.0)
        length += math.dist(end, tuple(float(v) for v in end_enu_m))
    return PathEstimate(length_m=length, duration_s=length / flight.speed_m_s, n_waypoints=n)


def to_geodetic(traj: Trajectory) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(lat_deg, lon_deg, h_m) of the samples through the exact WGS84 ENU frame.

    ``h_m`` is the ellipsoidal height of the ENU point for ``height_ref="origin"``
    (origin h + z plus d^2 / 2R, as the tangent plane rises above the ellipsoid: 8 mm at
    320 m) and the height above terrain (z itself) for ``"terrain"``.
    """
    frame = ExactENU(*traj.origin)
    e, n, u = traj.enu_m[:, 0], traj.enu_m[:, 1], traj.enu_m[:, 2]
    lat, lon, h = frame.to_geodetic(e, n, u if traj.height_ref == "origin" else np.zeros_like(u))
    lat, lon, h = np.atleast_1d(lat), np.atleast_1d(lon), np.atleast_1d(h)
    return lat, lon, (h if traj.height_ref == "origin" else u.copy())


# --------------------------------------------------------------------------- airspace


@dataclass(frozen=True, kw_only=True)
class KeepOut:
    """A keep-out cylinder (a tower, a power line pylon): centre (east, north), radius,
    and the obstacle's height above the ground (``top_m``; None: never fly over it)."""

    east_m: float
    north_m: float
    radius_m: float
    top_m: float | None = None

    def __post_init__(self) -> None:
        if not (math.isfinite(self.east_m) and math.isfinite(self.north_m)):
            raise ValueError("keep-out centre must be finite")
        _positive("radius_m", self.radius_m)
        _check_top(self.top_m)

    def signed_distance_m(self, xy: np.ndarray) -> np.ndarray:
        """Distance to the circle, negative inside (m)."""
        p = np.asarray(xy, dtype=float).reshape(-1, 2)
        return np.hypot(p[:, 0] - self.east_m, p[:, 1] - self.north_m) - self.radius_m

    def outline_m(self, grow_m: float = 0.0, sides: int = 12) -> np.ndarray:
        """A counter-clockwise polygon (sides, 2) around the circle grown by ``grow_m``:
        circumscribed, so its edges are ``radius + grow_m`` from the centre."""
        r = (self.radius_m + grow_m) / math.cos(math.pi / sides)
        th = (np.arange(sides) + 0.5) * 2.0 * math.pi / sides
        return np.column_stack([self.east_m + r * np.cos(th), self.north_m + r * np.sin(th)])

    def blocks(self, floor_m: float | None, clearance_m: float) -> bool:
        """Does it obstruct paths flown at least ``floor_m`` above the ground (None: any
        height)? Only when it has a top and the paths clear it by ``clearance_m`` not."""
        return self.top_m is None or floor_m is None or self.top_m + clearance_m > floor_m


@dataclass(frozen=True, kw_only=True)
class KeepOutPolygon:
    """A keep-out polygon (a power line's corridor, a building) in ENU metres, convex or
    not, and its height above the ground (``top_m``; None: never fly over it)."""

    vertices_m: tuple[tuple[float, float], ...]
    top_m: float | None = None

    def __post_init__(self) -> None:
        v = np.asarray(self.vertices_m, dtype=float)
        if v.ndim != 2 or v.shape[1] != 2 or len(v) < 3 or not np.all(np.isfinite(v)):
            raise ValueError("a keep-out polygon needs >= 3 finite (east, north) vertices")
        crossing = polygon_crossing(v)
        if crossing is not None:
            raise ValueError(f"the keep-out polygon: {crossing_text(crossing)}")
        if abs(polygon_area_m2(v)) < 1.0:
            raise ValueError("the keep-out polygon encloses no area")
        _check_top(self.top_m)

    def signed_distance_m(self, xy: np.ndarray) -> np.ndarray:
        """Distance to the polygon's boundary, negative inside (m)."""
        return signed_distance_to_polygon_m(self.vertices_m, xy)

    def outline_m(self, grow_m: float = 0.0) -> np.ndarray:
        """Counter-clockwise vertices (N, 2), each moved ``grow_m`` outwards along its
        bisector (a convex corner by grow / cos(half its turn), so the edges move out by
        ``grow_m``)."""
        v = np.asarray(self.vertices_m, dtype=float)
        if polygon_area_m2(v) < 0:
            v = v[::-1]
        if grow_m == 0.0:
            return v.copy()
        out = []
        n = len(v)
        for i in range(n):
            a, b, c = v[i - 1], v[i], v[(i + 1) % n]
            e1, e2 = b - a, c - b
            n1 = np.array([e1[1], -e1[0]]) / max(float(np.linalg.norm(e1)), 1e-12)  # outward
            n2 = np.array([e2[1], -e2[0]]) / max(float(np.linalg.norm(e2)), 1e-12)
            bis = n1 + n2
            nb = float(np.linalg.norm(bis))
            bis = n1 if nb < 1e-9 else bis / nb
            out.append(b + bis * grow_m / max(float(bis @ n1), 0.2))
        return np.array(out)

    def hull_half_planes(self) -> np.ndarray:
        """The convex hull (a superset) as half-planes, rows (a_x, a_y, b) with unit outward
        normals: a point q is outside the hull by max_j (a_j . q - b_j) or more."""
        h = convex_hull(np.asarray(self.vertices_m, dtype=float))
        e = np.roll(h, -1, axis=0) - h
        L = np.linalg.norm(e, axis=1)
        keep = L > 1e-9
        nrm = np.column_stack([e[keep, 1], -e[keep, 0]]) / L[keep, None]
        return np.column_stack([nrm, (nrm * h[keep]).sum(axis=1)])

    def blocks(self, floor_m: float | None, clearance_m: float) -> bool:
        """As :meth:`KeepOut.blocks`."""
        return self.top_m is None or floor_m is None or self.top_m + clearance_m > floor_m


AnyKeepOut = KeepOut | KeepOutPolygon


def _check_top(top_m: float | None) -> None:
    if top_m is not None and not (math.isfinite(top_m) and top_m >= 0.0):
        raise ValueError(f"a keep-out's top_m must be finite and >= 0, got {top_m!r}")


def convex_hull(points_m: np.ndarray) -> np.ndarray:
    """Counter-clockwise convex hull of (N, 2) points (Andrew's monotone chain)."""
    pts = sorted({(float(x), float(y)) for x, y in np.asarray(points_m, dtype=float)})
    if len(pts) < 3:
        return np.array(pts)

    def cross(o, a, b) -> float:
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    lower: list = []
    for p in pts:
        while len(lower) >= 2 and cross(lower[-2], lower[-1], p) <= 0:
            lower.pop()
        lower.append(p)
    upper: list = []
    for p in reversed(pts):
        while len(upper) >= 2 and cross(upper[-2], upper[-1], p) <= 0:
            upper.pop()
        upper.append(p)
    return np.array(lower[:-1] + upper[:-1])


@dataclass(frozen=True, kw_only=True)
class Geofence:
    """A convex keep-in polygon in ENU (east, north) metres; vertices in either order."""

    vertices_m: tuple[tuple[float, float], ...]
    half_planes: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        v = np.asarray(self.vertices_m, dtype=float)
        if v.ndim != 2 or v.shape[1] != 2 or len(v) < 3 or not np.all(np.isfinite(v)):
            raise ValueError("a geofence needs >= 3 finite (east, north) vertices")
        area2 = float(np.sum(v[:, 0] * np.roll(v[:, 1], -1) - np.roll(v[:, 0], -1) * v[:, 1]))
        if abs(area2) < 1e-9:
            raise ValueError("degenerate geofence polygon")
        if area2 < 0:
            v = v[::-1]  # counter-clockwise
        edges = np.roll(v, -1, axis=0) - v
        cross = edges[:, 0] * np.roll(edges[:, 1], -1) - edges[:, 1] * np.roll(edges[:, 0], -1)
        if np.any(cross < -1e-9):
            raise ValueError("the geofence polygon must be convex")
        normals = np.column_stack([edges[:, 1], -edges[:, 0]])  # outward for CCW
        norms = np.linalg.norm(normals, axis=1)
        keep = norms > 1e-12
        normals = normals[keep] / norms[keep, None]
        offsets = np.einsum("ij,ij->i", normals, v[keep])
        object.__setattr__(self, "half_planes", np.column_stack([normals, offsets]))

    @classmethod
    def square(cls, center_enu_m: Sequence[float], half_width_m: float) -> Geofence:
        cx, cy = _xy(center_enu_m)
        h = _positive("half_width_m", half_width_m)
        return cls(
            vertices_m=((cx - h, cy - h), (cx + h, cy - h), (cx + h, cy + h), (cx - h, cy + h))
        )

    def signed_distance_m(self, xy: np.ndarray) -> np.ndarray:
        """Max over edges of a . x - b: negative inside, positive outside (m)."""
        p = np.asarray(xy, dtype=float).reshape(-1, 2)
        hp = self.half_planes
        return (p @ hp[:, :2].T - hp[:, 2][None, :]).max(axis=1)


def densify(points_enu_m: np.ndarray, max_step_m: float = 1.0) -> np.ndarray:
    """Insert points on every straight segment so no step exceeds ``max_step_m``."""
    p = np.asarray(points_enu_m, dtype=float).reshape(-1, 3)
    if len(p) < 2:
        return p.copy()
    out = [p[:1]]
    for a, b in itertools.pairwise(p):
        n = max(1, math.ceil(float(np.linalg.norm(b - a)) / max_step_m))
        f = (np.arange(1, n + 1) / n)[:, None]
        out.append(a + f * (b - a))
    return np.vstack(out)


def airspace_violations(
    points_enu_m: np.ndarray,
    fence: Geofence | None = None,
    keep_outs: Sequence[AnyKeepOut] = (),
    tolerance_m: float = 1e-6,
    max_step_m: float = 1.0,
    agl_m: Callable[[np.ndarray], np.ndarray] | None = None,
    clearance_m: float = 0.0,
) -> list[str]:
    """Where a polyline (flown straight between points) leaves the fence or enters a
    keep-out (a cylinder or a polygon), checked every ``max_step_m`` along it. Empty when
    clear. With ``agl_m`` (the dense points' heights above the ground), a keep-out with a
    ``top_m`` is entered only by points below its top + ``clearance_m``; without it,
    every point inside one counts (its top unknown to the path)."""
    dense = densify(points_enu_m, max_step_m)
    out: list[str] = []
    if fence is not None:
        sd = fence.signed_distance_m(dense[:, :2])
        if sd.max() > tolerance_m:
            out.append(f"leaves the geofence by {sd.max():.2f} m")
    agl = None
    for k, ko in enumerate(keep_outs):
        d = ko.signed_distance_m(dense[:, :2])
        inside = d < -tolerance_m
        if ko.top_m is not None and agl_m is not None and np.any(inside):
            if agl is None:
                agl = np.asarray(agl_m(dense), dtype=float)
            inside &= agl < ko.top_m + clearance_m
        if not np.any(inside):
            continue
        if isinstance(ko, KeepOut):
            out.append(f"enters keep-out {k} (r={ko.radius_m:g} m) to "
                       f"{ko.radius_m + d[inside].min():.2f} m from its centre")
        else:
            out.append(f"enters keep-out {k} (a polygon) {-d[inside].min():.2f} m deep")
    return out
