"""Coverage search policies: fixed patterns flown over the search area.

:class:`PatternPolicy` flies a coverage pattern object over the area, repeated until
the budget is spent or every expected responder is localised:

- :class:`Lawnmower` (policy ``lawnmower``): the boustrophedon over the area that an
  operator flies today with a QGroundControl survey (our baseline);
- :class:`ExpandingSquare` (policy ``expanding-square``): the IAMSAR expanding square
  from the area's centroid, clipped to the area.

:class:`Sweep` is the lawnmower's waypoints as a resumable search sweep (the adaptive
policy searches with it until a responder is heard). The names map to patterns in
:mod:`planner.policy` only.

:func:`polyline_trajectory` and :func:`search_spacing_m` are the path helpers every
policy shares.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import ClassVar, Protocol

import numpy as np

from estimator.records import Trajectory
from planner.area import pass_detection_range_m
from planner.observation import (
    XY,
    Decision,
    LocalisedRule,
    LocalisedTracker,
    Observation,
    SearchMission,
)


def polyline_trajectory(
    points_xy: Sequence[Sequence[float]],
    height_m: float,
    speed_mps: float,
    origin: tuple[float, float, float],
    name: str,
) -> Trajectory:
    """Straight legs through (e, n) points at ``height_m`` above the terrain."""
    p = np.asarray(points_xy, dtype=float).reshape(-1, 2)
    if len(p) == 1:
        p = np.vstack([p, p])
    seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
    t = np.concatenate([[0.0], np.cumsum(seg / speed_mps)])
    keep = np.concatenate([[True], seg > 1e-6])
    enu = np.column_stack([p, np.full(len(p), height_m)])
    return Trajectory(t[keep], enu[keep], origin, "terrain", name)


def search_spacing_m(mission: SearchMission, probability: float = 0.95) -> float:
    """Track spacing: twice the offset at which one pass hears an open responder with
    ``probability`` (:func:`planner.area.pass_detection_range_m`)."""
    v = mission.area.vertices
    extent = float(np.max(np.ptp(v, axis=0)))
    r = pass_detection_range_m(mission.link, mission.height_m, mission.speed_mps,
                               probability, pass_length_m=extent)
    return max(2.0 * r, 20.0)


class CoveragePattern(Protocol):
    """A coverage pattern: its waypoints over a mission's area (tracks ``spacing_m``
    apart, first track at ``heading_deg`` clockwise from north)."""

    name: str

    def waypoints(self, mission: SearchMission, spacing_m: float, heading_deg: float
                  ) -> list[XY]: ...


@dataclass(frozen=True)
class Lawnmower:
    """The boustrophedon over the area, starting at the end nearest the mission's start."""

    name: ClassVar[str] = "lawnmower"

    def waypoints(self, mission: SearchMission, spacing_m: float, heading_deg: float
                  ) -> list[XY]:
        return mission.area.sweep(spacing_m, heading_deg, start=mission.start_enu_m)


@dataclass(frozen=True)
class ExpandingSquare:
    """The IAMSAR expanding square from the area's centroid, clipped to the area; from
    the centre of the part the start can reach when keep-outs cut the centroid off
    (:meth:`planner.area.SearchArea.reachable_center`)."""

    name: ClassVar[str] = "expanding-square"

    def waypoints(self, mission: SearchMission, spacing_m: float, heading_deg: float
                  ) -> list[XY]:
        datum = mission.area.reachable_center(mission.start_enu_m)
        return mission.area.expanding_square(datum, spacing_m, heading_deg)


class PatternPolicy:
    """Fly a coverage pattern (:class:`Lawnmower`, :class:`ExpandingSquare`) over the
    area, start to end and again in reverse, until every expected responder is
    localised (estimator judgement) or the budget is spent; with an unknown number of
    responders it stops after a full coverage once every responder it heard is
    localised. A pattern whose waypoints the start cannot reach (cut off by keep-outs:
    :meth:`planner.area.SearchArea.join` drops them) leaving less than one track
    spacing to fly is replaced by the lawnmower over the part it can reach, so the
    vehicle searches instead of hovering. The policy is named after its pattern."""

    def __init__(self, pattern: CoveragePattern, *, heading_deg: float = 0.0,
                 spacing_m: float | None = None, rule: LocalisedRule = LocalisedRule()) -> None:
        self.pattern = pattern
        self.name = pattern.name
        self.heading_deg = heading_deg
        self.spacing_m = spacing_m
        self.rule = rule

    def reset(self, mission: SearchMission, rng: np.random.Generator) -> None:
        self.mission = mission
        self.tracker = LocalisedTracker(self.rule)
        spacing = self.spacing_m or search_spacing_m(mission)
        self.waypoints = self.pattern.waypoints(mission, spacing, self.heading_deg)
        reach = np.asarray(mission.area.join([mission.start_enu_m, *self.waypoints]))
        if np.linalg.norm(np.diff(reach, axis=0), axis=1).sum() < spacing:
            self.waypoints = Lawnmower().waypoints(mission, spacing, self.heading_deg)
        self.passes = 0
        self._started = False

    def _pattern(self, start: XY, forward: bool) -> Trajectory:
        m = self.mission
        wps = self.waypoints if forward else self.waypoints[::-1]
        pts = m.area.join([start, *wps])
        return polyline_trajectory(pts, m.height_m, m.speed_mps, m.origin, self.name)

    def decide(self, obs: Observation) -> Decision:
        self.tracker.update(obs)
        loc = self.tracker.frozen()
        if self.tracker.all_expected_localised(self.mission, obs):
            return Decision(localised=loc, done=True, note="every expected responder localised")
        a = obs.agent
        if not self._started or a.segment_done:
            if self._started:
                self.passes += 1
                heard = {r.bssid for r in obs.responders}
                if (self.mission.expected_responders is None and heard
                        and heard <= set(loc)):
                    return Decision(localised=loc, done=True, note="covered, all localised")
            self._started = True
            traj = self._pattern(a.position_enu_m[:2], forward=self.passes % 2 == 0)
            return Decision(plans={0: traj}, localised=loc, note=f"{self.name} pass {self.passes}")
        return Decision(localised=loc)


class Sweep:
    """The search sweep of a policy: the lawnmower's waypoints, which of them have been
    flown, and the segment that resumes it from anywhere (reversed at each end)."""

    PASSED_M = 15.0  # a waypoint counts as flown once the vehicle passed within this

    def __init__(self, mission: SearchMission, spacing_m: float, heading_deg: float = 0.0
                 ) -> None:
        self.mission = mission
        self.waypoints = Lawnmower().waypoints(mission, spacing_m, heading_deg)
        self.next = 0  # next waypoint to fly to
        self.passes = 0  # sweeps flown to their end

    @classmethod
    def through(cls, mission: SearchMission, waypoints: Sequence[XY]) -> Sweep:
        """A resumable sweep through given ``waypoints`` (e.g. a sector's lawnmower or an
        expanding square) instead of the lawnmower over the whole area."""
        sweep = cls.__new__(cls)
        sweep.mission = mission
        sweep.waypoints = [(float(x), float(y)) for x, y in waypoints]
        sweep.next = 0
        sweep.passes = 0
        return sweep

    @property
    def at_end(self) -> bool:
        return self.next >= len(self.waypoints)

    @property
    def progress(self) -> float:
        """The share of this pass's waypoints flown (0 to 1)."""
        return self.next / max(len(self.waypoints), 1)

    def advance(self, here: Sequence[float]) -> None:
        """Mark waypoints as flown once the vehicle has passed within ``PASSED_M``."""
        wps = self.waypoints
        while self.next < len(wps) and math.dist(here, wps[self.next]) < self.PASSED_M:
            self.next += 1

    def reverse(self) -> None:
        """The pass is over: fly it again the other way."""
        self.passes += 1
        self.waypoints = self.waypoints[::-1]
        self.next = 0

    def resume(self, here: Sequence[float]) -> Trajectory:
        """The segment from ``here`` through the waypoints not flown yet (those within
        :attr:`PASSED_M` of ``here`` count as flown; past the end, the pass reversed)."""
        m = self.mission
        self.advance(here)
        if self.at_end:
            self.reverse()
            self.advance(here)
        pts = m.area.join([here, *self.waypoints[self.next:]])
        return polyline_trajectory(pts, m.height_m, m.speed_mps, m.origin, "search")


