"""Search policies: observe what the estimator knows and where the vehicle is, return what
to fly next.

One small interface serves the fixed patterns, the adaptive CasADi policy and trained
networks alike (``envs`` runs them in the closed loop, over MAVLink, in Gymnasium)::

    policy.reset(mission, rng)          # a new search (the mission is what the operator knows)
    decision = policy.decide(obs)       # every few seconds: Observation -> Decision

An :class:`Observation` holds only what a real system has: the autopilot's position and
velocity estimate, the flight time and budget, and per responder heard so far what
the estimator says (status, position, covariance, counts) and where the drone was
when it heard it. Never the truth. A :class:`Decision` may carry a new path segment
(a :class:`Trajectory` in the mission's ENU frame; the vehicle flies it from where it
is), the set of responders the policy judges localised, and whether the search is
over.

Policies:

- :class:`PatternPolicy` ``lawnmower``: the boustrophedon over the area that an
  operator flies today with a QGroundControl survey (our baseline), repeated until the
  budget is spent or every expected responder is localised;
- :class:`PatternPolicy` ``expanding-square``: the IAMSAR expanding square from the
  area's centroid, clipped to the area;
- :class:`AdaptivePolicy` ``adaptive``: the lawnmower until a responder is heard, then
  a probe orbit until the estimator bootstraps, receding-horizon CasADi plans around
  the estimate and its covariance (:class:`planner.optimal.OptimalPlanner`, re-solved
  as the estimate moves, over an altitude band: height and range bias are not
  separable at one altitude), then a close helix; responders one after another; it
  stays inside the area and the budget.

"Localised" (:class:`LocalisedRule`) is judged from the estimator alone: status
``converged``, enough accepted ranges, and sigma_H below the target, or below an
acceptable bound once it has stopped shrinking (the information limit of the
geometry flown).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from estimator.records import Trajectory
from planner.area import SearchArea, pass_detection_range_m
from planner.models import LinkModel, TerrainModel

XY = tuple[float, float]


# ----------------------------------------------------------------------------- data


@dataclass(frozen=True, kw_only=True)
class SearchMission:
    """What the operator knows before take-off (the ``[search]`` table and the map)."""

    area: SearchArea
    start_enu_m: XY
    budget_s: float
    height_m: float  # search height above the terrain
    speed_mps: float
    terrain: TerrainModel
    link: LinkModel
    origin: tuple[float, float, float]  # WGS84 (lat, lon, h) of the mission's ENU frame
    expected_responders: int | None = None  # None: unknown
    n_agents: int = 1


@dataclass(frozen=True, kw_only=True)
class AgentView:
    """One vehicle as the autopilot reports it (navigation estimate, not the truth)."""

    position_enu_m: tuple[float, float, float]
    velocity_enu_mps: tuple[float, float, float]
    segment_done: bool  # the last path segment has been flown to its end


@dataclass(frozen=True, kw_only=True)
class ResponderView:
    """What is known of one responder heard so far (estimator output, mission frame)."""

    bssid: str
    status: str
    detected_at_s: float
    n_heard: int  # ok ranges logged
    heard_enu_m: tuple[tuple[float, float, float], ...]  # drone positions when heard (recent)
    heard_range_m: tuple[float, ...]
    mean_enu_m: tuple[float, float, float] | None = None
    cov_m2: tuple[tuple[float, float, float], ...] | None = None  # 3 x 3 (rows)
    sigma_h_m: float | None = None
    r95_h_m: float | None = None
    n_acc: int = 0
    kappa: float | None = None
    candidates: tuple[tuple[float, float, float], ...] = ()  # ambiguous: mirror positions

    @property
    def has_estimate(self) -> bool:
        return self.mean_enu_m is not None


@dataclass(frozen=True, kw_only=True)
class Observation:
    t_s: float  # flight time since take-off
    budget_s: float
    agents: tuple[AgentView, ...]
    responders: tuple[ResponderView, ...]

    @property
    def agent(self) -> AgentView:
        return self.agents[0]

    @property
    def time_left_s(self) -> float:
        return self.budget_s - self.t_s


@dataclass(frozen=True, kw_only=True)
class Decision:
    """What to fly next: new segments per agent index (absent: keep flying), the
    responders judged localised (all of them so far), and whether the search is over."""

    plans: dict[int, Trajectory] = field(default_factory=dict)
    localised: frozenset[str] = frozenset()
    done: bool = False
    replans: int = 0  # optimiser solves behind this decision
    note: str = ""


class Policy(Protocol):
    """A search policy (see the module docstring)."""

    name: str

    def reset(self, mission: SearchMission, rng: np.random.Generator) -> None: ...

    def decide(self, obs: Observation) -> Decision: ...


# ----------------------------------------------------------------------------- helpers


@dataclass(frozen=True, kw_only=True)
class LocalisedRule:
    """The estimator-only judgement that a responder is localised.

    ``converged`` with at least ``min_n_acc`` accepted ranges and sigma_H <=
    ``target_sigma_h_m``; or sigma_H <= ``accept_sigma_h_m`` once it has shrunk by
    less than ``plateau_fraction`` over the last ``plateau_s`` (the geometry flown
    gives no more: typically the GNSS bias floor of a standalone receiver). With an
    honest sigma_H (mode ``refined``), 0.5 m puts the truth within 1 m with ~98 %
    probability (isotropic: 1 - exp(-1 / (2 (0.5 / sqrt 2)^2))).
    """

    target_sigma_h_m: float = 0.5
    accept_sigma_h_m: float = 3.0
    min_n_acc: int = 30
    plateau_s: float = 90.0
    plateau_fraction: float = 0.05

    def judge(self, r: ResponderView, history: list[tuple[float, float]], t_s: float) -> bool:
        if r.status != "converged" or r.sigma_h_m is None or r.n_acc < self.min_n_acc:
            return False
        if r.sigma_h_m <= self.target_sigma_h_m:
            return True
        if r.sigma_h_m > self.accept_sigma_h_m:
            return False
        old = [s for t, s in history if t <= t_s - self.plateau_s]
        return bool(old) and r.sigma_h_m >= (1.0 - self.plateau_fraction) * old[-1]


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


class _Tracker:
    """Per-responder bookkeeping shared by the policies: localised set, sigma history."""

    def __init__(self, rule: LocalisedRule) -> None:
        self.rule = rule
        self.localised: dict[str, float] = {}
        self.sigma: dict[str, list[tuple[float, float]]] = {}

    def update(self, obs: Observation) -> None:
        for r in obs.responders:
            if r.sigma_h_m is not None:
                self.sigma.setdefault(r.bssid, []).append((obs.t_s, r.sigma_h_m))
            if r.bssid not in self.localised and self.rule.judge(
                r, self.sigma.get(r.bssid, []), obs.t_s
            ):
                self.localised[r.bssid] = obs.t_s

    def all_expected_localised(self, mission: SearchMission, obs: Observation) -> bool:
        n = mission.expected_responders
        return n is not None and len(self.localised) >= n

    def frozen(self) -> frozenset[str]:
        return frozenset(self.localised)


# ----------------------------------------------------------------------------- patterns


class PatternPolicy:
    """Fly a fixed coverage pattern over the area (``lawnmower`` or ``expanding-square``),
    start to end and again in reverse, until every expected responder is localised
    (estimator judgement) or the budget is spent; with an unknown number of responders
    it stops after a full coverage once every responder it heard is localised."""

    def __init__(self, kind: str = "lawnmower", *, heading_deg: float = 0.0,
                 spacing_m: float | None = None, rule: LocalisedRule = LocalisedRule()) -> None:
        if kind not in ("lawnmower", "expanding-square"):
            raise ValueError(f"unknown pattern {kind!r}")
        self.name = kind
        self.kind = kind
        self.heading_deg = heading_deg
        self.spacing_m = spacing_m
        self.rule = rule

    def reset(self, mission: SearchMission, rng: np.random.Generator) -> None:
        self.mission = mission
        self.tracker = _Tracker(self.rule)
        spacing = self.spacing_m or search_spacing_m(mission)
        if self.kind == "lawnmower":
            wps = mission.area.sweep(spacing, self.heading_deg, start=mission.start_enu_m)
        else:
            wps = mission.area.expanding_square(mission.area.centroid_m, spacing,
                                                self.heading_deg)
        self.waypoints = wps
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


# ----------------------------------------------------------------------------- adaptive


@dataclass(frozen=True, kw_only=True)
class AdaptiveConfig:
    """Parameters of the adaptive policy (our choices; documented in the README)."""

    detect_probability: float = 0.95  # search track spacing: see search_spacing_m
    probe_radius_m: tuple[float, float] = (25.0, 60.0)  # orbit before the bootstrap
    probe_climb_m: float = 20.0  # probe helix climbs this much above the search height
    horizon_s: float = 90.0  # CasADi horizon
    n_waypoints: int = 16  # 6 s apart: re-solves in tens of milliseconds
    n_prior_points: int = 4  # the two horizontal axes of the estimate's covariance
    max_iter: int = 80  # Ipopt iterations (deterministic cap; the result is checked)
    replan_s: float = 20.0  # re-solve after flying this much of a plan
    agl_band_m: tuple[float, float] = (-20.0, 25.0)  # about the search height
    prior_inflation_m2: float = 4.0  # added to the estimate's covariance for planning
    close_sigma_h_m: float = 3.0  # below this, finish with a close helix
    close_radius_m: float = 18.0
    close_climb_m: tuple[float, float] = (-15.0, 20.0)  # helix heights about the search height
    close_turns: float = 2.0
    max_localise_s: float = 420.0  # give up on one responder after this long
    reserve_s: float = 20.0  # stop planning new work this close to the budget


class AdaptivePolicy:
    """Search until a responder is heard, then localise it by planning around the
    estimate (see the module docstring)."""

    name = "adaptive"

    def __init__(self, config: AdaptiveConfig = AdaptiveConfig(), *,
                 rule: LocalisedRule = LocalisedRule(), heading_deg: float = 0.0) -> None:
        self.cfg = config
        self.rule = rule
        self.heading_deg = heading_deg
        self._planner = None
        self._planner_key: tuple | None = None

    # ------------------------------------------------------------------ setup
    def reset(self, mission: SearchMission, rng: np.random.Generator) -> None:
        self.mission = mission
        self.rng = rng
        self.tracker = _Tracker(self.rule)
        spacing = search_spacing_m(mission, self.cfg.detect_probability)
        self.sweep = mission.area.sweep(spacing, self.heading_deg, start=mission.start_enu_m)
        self.sweep_next = 0  # next sweep waypoint to fly to
        self.sweeps_done = 0
        self.target: str | None = None
        self.phase = "search"
        self.phase_since = 0.0
        self.target_since = 0.0
        self.abandoned: set[str] = set()
        self.last_plan_t = -math.inf
        self._started = False
        self.solve_time_s = 0.0  # wall time spent in optimiser solves (benchmarks)
        self._ensure_planner()

    def _ensure_planner(self):
        from planner.optimal import OptimalConfig
        from planner.scoring import ScoringConfig

        m, c = self.mission, self.cfg
        lo = max(10.0, m.height_m + c.agl_band_m[0])
        hi = m.height_m + c.agl_band_m[1]
        ocfg = OptimalConfig(
            n_waypoints=c.n_waypoints, horizon_s=c.horizon_s, n_prior_points=c.n_prior_points,
            max_iter=c.max_iter,
            max_fence_edges=8, max_keep_outs=1, max_speed_m_s=m.speed_mps,
            agl_min_m=lo, agl_max_m=hi, terrain=m.terrain,
            scoring=ScoringConfig(link=m.link),
        )
        # terrain and link hash by value (frozen dataclasses; a grid by identity)
        key = (m.terrain, m.link, repr(ocfg))
        if self._planner is None or self._planner_key != key:
            self._planner = _cached_planner(ocfg, key)
            self._planner_key = key
        self.ocfg = ocfg
        self._planner.reset_warm_start()

    # ------------------------------------------------------------------ decide
    def decide(self, obs: Observation) -> Decision:
        m, c = self.mission, self.cfg
        self.tracker.update(obs)
        loc = self.tracker.frozen()
        if self.tracker.all_expected_localised(m, obs):
            return Decision(localised=loc, done=True, note="every expected responder localised")
        if obs.time_left_s < c.reserve_s:
            return Decision(localised=loc, note="budget nearly spent")
        a = obs.agent
        views = {r.bssid: r for r in obs.responders}
        # finish or drop the current target
        if self.target is not None:
            if self.target in loc:
                self._back_to_search(obs.t_s)
            elif obs.t_s - self.target_since > c.max_localise_s:
                self.abandoned.add(self.target)
                self._back_to_search(obs.t_s)
        if self.target is None:
            pending = [r for r in obs.responders
                       if r.bssid not in loc and r.bssid not in self.abandoned]
            if pending:  # the most recently heard first
                self.target = max(pending, key=lambda r: (r.n_heard > 0, r.detected_at_s)).bssid
                self.target_since = obs.t_s
                self.phase = "acquire"  # nothing flown for it yet
                self.phase_since = obs.t_s
                self.last_plan_t = -math.inf
        if self.target is None:
            return self._search(obs, loc)
        return self._localise(obs, views[self.target], loc, a)

    def _back_to_search(self, t_s: float) -> None:
        self.target = None
        self.phase = "search"
        self.phase_since = t_s
        self._resume = True

    def _search(self, obs: Observation, loc: frozenset[str]) -> Decision:
        m = self.mission
        a = obs.agent
        here = a.position_enu_m[:2]
        if self._started and not a.segment_done and not getattr(self, "_resume", False):
            self._advance_sweep(here)
            return Decision(localised=loc)
        self._resume = False
        if self._started and a.segment_done and self.sweep_next >= len(self.sweep):
            self.sweeps_done += 1
            heard = {r.bssid for r in obs.responders}
            if m.expected_responders is None and heard and heard <= set(loc):
                return Decision(localised=loc, done=True, note="covered, all localised")
            self.sweep = self.sweep[::-1]
            self.sweep_next = 0
        self._started = True
        if self.sweep_next >= len(self.sweep):
            self.sweep_next = 0
        # resume the sweep at the waypoint that continues it best from here
        rest = self.sweep[self.sweep_next:]
        pts = m.area.join([here, *rest])
        traj = polyline_trajectory(pts, m.height_m, m.speed_mps, m.origin, "search")
        self._sweep_traj_pts = rest
        return Decision(plans={0: traj}, localised=loc, note="search")

    def _advance_sweep(self, here: Sequence[float]) -> None:
        """Mark sweep waypoints as flown once the vehicle has passed within 15 m."""
        while self.sweep_next < len(self.sweep) and math.dist(
            here, self.sweep[self.sweep_next]
        ) < 15.0:
            self.sweep_next += 1

    def _localise(self, obs: Observation, r: ResponderView, loc: frozenset[str],
                  a: AgentView) -> Decision:
        c = self.cfg
        t = obs.t_s
        if r.has_estimate and r.status in ("converged", "tracking"):
            if r.sigma_h_m is not None and r.sigma_h_m <= c.close_sigma_h_m and (
                self.phase != "close"
            ):
                self.phase = "close"
                self.phase_since = t
                return Decision(plans={0: self._close_helix(r, a)}, localised=loc,
                                note=f"close helix {r.bssid}")
            if self.phase == "close":
                if a.segment_done:  # another turn, re-centred on the estimate
                    return Decision(plans={0: self._close_helix(r, a)}, localised=loc,
                                    note=f"close helix {r.bssid}")
                return Decision(localised=loc)
            if self.phase != "plan" or t - self.last_plan_t >= c.replan_s or a.segment_done:
                self.phase = "plan"
                traj, solves = self._optimal(r, a)
                self.last_plan_t = t
                return Decision(plans={0: traj}, localised=loc, replans=solves,
                                note=f"plan around {r.bssid}")
            return Decision(localised=loc)
        # no usable estimate yet (bootstrapping, weak geometry, ambiguous): probe orbit
        if self.phase != "probe" or a.segment_done or t - self.phase_since > 150.0:
            self.phase = "probe"
            self.phase_since = t
            return Decision(plans={0: self._probe(r, a)}, localised=loc,
                            note=f"probe {r.bssid}")
        return Decision(localised=loc)

    # ------------------------------------------------------------------ manoeuvres
    def _inside_center(self, xy: Sequence[float], radius: float) -> tuple[XY, float]:
        """The centre moved (and the radius shrunk) so the circle stays in the area."""
        area = self.mission.area
        cx, cy = float(xy[0]), float(xy[1])
        if not area.contains(np.array([[cx, cy]]), area.margin_m)[0]:
            cx, cy = area._pull_inside(np.array([cx, cy]))
        for _ in range(40):
            th = np.linspace(0.0, 2.0 * math.pi, 73)
            ring = np.column_stack([cx + radius * np.cos(th), cy + radius * np.sin(th)])
            if area.path_inside(ring, area.margin_m):
                break
            radius *= 0.85
        return (cx, cy), max(radius, 8.0)

    def _helix(self, center: XY, radius: float, z0: float, z1: float, turns: float,
               a: AgentView, name: str) -> Trajectory:
        from planner.patterns import FlightConfig, helix

        m = self.mission
        flight = FlightConfig(speed_m_s=min(m.speed_mps, 0.9 * math.sqrt(2.5 * radius)),
                              alt_m=z0, height_ref="terrain", origin=m.origin)
        traj = helix(center, radius, alt_start_m=z0, alt_end_m=z1, turns=turns, flight=flight)
        # the vehicle flies a leg to the helix from where it is: keep that leg inside too
        p0 = traj.enu_m[0]
        leg = self.mission.area.route(a.position_enu_m[:2], p0[:2])
        if len(leg) > 2:
            prefix = polyline_trajectory(leg[:-1], z0, m.speed_mps, m.origin, name)
            t = np.concatenate([prefix.t_s, prefix.t_s[-1] + 1e-3 +
                                traj.t_s + math.dist(leg[-2], p0[:2]) / m.speed_mps])
            enu = np.vstack([prefix.enu_m, traj.enu_m])
            return Trajectory(t, enu, m.origin, "terrain", name)
        return Trajectory(traj.t_s, traj.enu_m, m.origin, "terrain", name)

    def _probe(self, r: ResponderView, a: AgentView) -> Trajectory:
        """Orbit where the heard ranges put the responder (a coarse grid fit), climbing."""
        m, c = self.mission, self.cfg
        if r.candidates:
            cand = np.asarray(r.candidates)[:, :2]
            center = tuple(np.mean(cand, axis=0))
            radius = max(c.probe_radius_m[0], 0.5 * float(np.ptp(cand, axis=0).max()) + 15.0)
        else:
            fit = coarse_fit(r, m)
            if fit is None or fit[1] > 2.0 * c.probe_radius_m[1]:
                return self._ring(r, a)
            center, spread = fit
            radius = float(np.clip(spread + 15.0, *c.probe_radius_m))
        (cx, cy), radius = self._inside_center(center, radius)
        return self._helix((cx, cy), radius, m.height_m, m.height_m + c.probe_climb_m, 1.25, a,
                           "probe")

    def _ring(self, r: ResponderView, a: AgentView) -> Trajectory:
        """Too few ranges to place it: the responder lies about the horizontal range
        sqrt(d^2 - h^2) from where the nearest range was heard; fly that ring (its part
        inside the area, the rest pulled onto the area's margin), starting nearest."""
        m = self.mission
        heard = np.asarray(r.heard_enu_m, dtype=float).reshape(-1, 3)
        rng = np.asarray(r.heard_range_m, dtype=float)
        k = int(np.argmin(rng))
        c = heard[k, :2]
        ground = float(np.asarray(m.terrain.height_m(c[0], c[1])))
        rho = math.sqrt(max(rng[k] ** 2 - (heard[k, 2] - ground) ** 2, 0.0))
        rho = max(rho, self.cfg.probe_radius_m[0])
        th0 = math.atan2(a.position_enu_m[1] - c[1], a.position_enu_m[0] - c[0])
        n = max(12, math.ceil(2.0 * math.pi * rho / 15.0))
        th = th0 + 2.0 * math.pi * np.arange(n + 1) / n
        ring = [m.area._pull_inside(np.array([c[0] + rho * math.cos(t), c[1] + rho * math.sin(t)]))
                for t in th]
        pts = m.area.join([a.position_enu_m[:2], *ring])
        return polyline_trajectory(pts, m.height_m, m.speed_mps, m.origin, "probe ring")

    def _close_helix(self, r: ResponderView, a: AgentView) -> Trajectory:
        m, c = self.mission, self.cfg
        assert r.mean_enu_m is not None
        (cx, cy), radius = self._inside_center(r.mean_enu_m[:2], c.close_radius_m)
        lo = max(10.0, m.height_m + c.close_climb_m[0])
        return self._helix((cx, cy), radius, lo, m.height_m + c.close_climb_m[1],
                           c.close_turns, a, "close")

    def _optimal(self, r: ResponderView, a: AgentView) -> tuple[Trajectory, int]:
        m, c = self.mission, self.cfg
        assert r.mean_enu_m is not None and r.cov_m2 is not None
        cov = np.asarray(r.cov_m2, dtype=float) + c.prior_inflation_m2 * np.eye(3)
        start = np.asarray(a.position_enu_m, dtype=float)
        vel = np.asarray(a.velocity_enu_mps, dtype=float)
        try:
            fence = m.area.local_fence(r.mean_enu_m[:2] if m.area.contains(
                np.array([r.mean_enu_m[:2]]))[0] else start[:2])
        except ValueError:
            fence = None
        agl0 = float(start[2] - float(np.asarray(m.terrain.height_m(start[0], start[1]))))
        band = (min(self.ocfg.agl_min_m, agl0), max(self.ocfg.agl_max_m, agl0))
        try:
            res = self._planner.plan(r.mean_enu_m, cov, start, vel, fence=fence,
                                     agl_band_m=band, origin=m.origin)
        except ValueError:
            return self._probe(r, a), 0
        self.solve_time_s += res.solve_time_s
        traj = res.trajectory
        if not res.feasible or not m.area.path_inside(traj.enu_m, 0.0):
            return self._probe(r, a), 1
        return traj, 1


def coarse_fit(r: ResponderView, mission: SearchMission, cell_m: float = 10.0,
               noise_m: float = 3.0) -> tuple[XY, float] | None:
    """Where the heard ranges put a responder before the estimator can: the best points
    of a grid over the area (the map's terrain under each), scored by the robust sum of
    (range - distance)^2 over the heard (position, range) pairs. Returns the centre of
    the near-best cells and their spread (two mirror minima of a straight track give a
    wide spread), or None with fewer than 3 ranges."""
    heard = np.asarray(r.heard_enu_m, dtype=float).reshape(-1, 3)
    rng = np.asarray(r.heard_range_m, dtype=float)
    if len(rng) < 3:
        return None
    v = mission.area.vertices
    lo, hi = v.min(axis=0), v.max(axis=0)
    xs = np.arange(lo[0], hi[0] + cell_m, cell_m)
    ys = np.arange(lo[1], hi[1] + cell_m, cell_m)
    gx, gy = np.meshgrid(xs, ys)
    g = np.column_stack([gx.ravel(), gy.ravel()])
    gz = np.asarray(mission.terrain.height_m(g[:, 0], g[:, 1]), dtype=float)
    d = np.sqrt((g[:, None, 0] - heard[None, :, 0]) ** 2 + (g[:, None, 1] - heard[None, :, 1]) ** 2
                + (gz[:, None] - heard[None, :, 2]) ** 2)
    res = (rng[None, :] - d) / noise_m
    cost = np.minimum(res * res, 9.0).sum(axis=1)  # robust: a far outlier costs at most 9
    best = float(cost.min())
    near = cost <= best + 2.0 * max(1.0, 0.1 * len(rng))
    pts = g[near]
    centre = pts.mean(axis=0)
    spread = float(np.max(np.linalg.norm(pts - centre, axis=1)))
    return (float(centre[0]), float(centre[1])), spread


_PLANNERS: dict[tuple, object] = {}


def _cached_planner(cfg, key: tuple):
    """One built OptimalPlanner per configuration per process (building takes ~1 s;
    re-solving a built one takes milliseconds)."""
    from planner.optimal import OptimalPlanner

    p = _PLANNERS.get(key)
    if p is None:
        p = _PLANNERS[key] = OptimalPlanner(cfg)
    return p


def make_policy(name: str, **kw) -> Policy:
    """A policy by name (the CLI's strings): lawnmower, expanding-square, adaptive."""
    if name in ("lawnmower", "expanding-square"):
        return PatternPolicy(name, **kw)
    if name == "adaptive":
        return AdaptivePolicy(**kw)
    raise ValueError(f"unknown policy {name!r} (lawnmower, expanding-square, adaptive)")


POLICIES = ("lawnmower", "expanding-square", "adaptive")
