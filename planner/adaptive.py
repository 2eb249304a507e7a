"""The adaptive search policy: search until a responder is heard, then localise it by
planning around the estimate.

:class:`AdaptivePolicy` ``adaptive``: the lawnmower sweep (:class:`planner.coverage.Sweep`)
until a responder is heard, then a probe orbit until the estimator bootstraps,
receding-horizon CasADi plans around the estimate and its covariance
(:class:`planner.optimal.OptimalPlanner`, re-solved as the estimate moves, over an
altitude band: height and range bias are not separable at one altitude), then a close
helix; responders one after another; it stays inside the area and the budget.
:class:`Manoeuvres` are the path segments it flies about a responder (also the discrete
actions of ``osa/Search-v0``); :func:`coarse_fit` places a responder from the heard
ranges before the estimator can.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from estimator.measurement import geometric_range_m
from estimator.records import Trajectory
from planner.coverage import Sweep, polyline_trajectory, search_spacing_m
from planner.observation import (
    XY,
    AgentView,
    Decision,
    LocalisedRule,
    LocalisedTracker,
    Observation,
    ResponderView,
    SearchMission,
)
from planner.patterns import KeepOut, KeepOutPolygon


def band_floor_m(mission: SearchMission, below_m: float) -> float:
    """The bottom of an altitude band reaching ``below_m`` (negative: down) from the
    search height: never below 10 m, nor below the area's ``min_height_m`` (a keep-out
    flown over: never below the search height, docs/search.md)."""
    return max(10.0, mission.height_m + below_m, mission.area.min_height_m or 0.0)


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
    responder_height_m: float = 0.5  # a responder's antenna above the ground (the link's)
    view_radii: tuple[float, ...] = (1.0, 0.8, 0.6, 0.45)  # probe radii tried when hidden



class Manoeuvres:
    """The path segments flown about a responder (the adaptive policy's, and the
    discrete actions of ``osa/Search-v0``), each kept inside the area with the leg to it.

    Circles are moved and shrunk until they fit inside the area (with its margin); a
    segment starts with a leg from where the vehicle is, routed inside concave areas.
    """

    def __init__(self, mission: SearchMission, cfg: AdaptiveConfig = AdaptiveConfig()) -> None:
        self.mission = mission
        self.cfg = cfg

    def inside_center(self, xy: Sequence[float], radius: float) -> tuple[XY, float]:
        """The centre moved (and the radius shrunk) so the circle stays in the area."""
        area = self.mission.area
        cx, cy = float(xy[0]), float(xy[1])
        if not area.contains(np.array([[cx, cy]]), area.margin_m)[0]:
            cx, cy = area.pull_inside(np.array([cx, cy]))
        th = np.linspace(0.0, 2.0 * math.pi, 73)
        r0 = radius
        for _ in range(40):
            ring = np.column_stack([cx + radius * np.cos(th), cy + radius * np.sin(th)])
            if area.path_inside(ring, area.margin_m):
                break
            radius *= 0.85
        if area.blocking and not area.path_inside(
                np.column_stack([cx + max(radius, 8.0) * np.cos(th),
                                 cy + max(radius, 8.0) * np.sin(th)]), area.margin_m):
            return self._clear_center((cx, cy), r0)
        return (cx, cy), max(radius, 8.0)

    def _clear_center(self, xy: Sequence[float], radius: float) -> tuple[XY, float]:
        """A circle near ``xy`` clear of the area's edges and blocking keep-outs: the
        nearest centre (rings of candidates 10 m apart, out to 300 m) where the largest
        radius of radius, 0.85 radius, ... down to 8 m fits."""
        area = self.mission.area
        th = np.linspace(0.0, 2.0 * math.pi, 73)
        radii = [radius * 0.85**k for k in range(40) if radius * 0.85**k >= 8.0] or [8.0]
        for dist in np.arange(0.0, 301.0, 10.0):
            n = 1 if dist == 0 else max(8, math.ceil(2 * math.pi * dist / 10.0))
            for a in 2 * math.pi * np.arange(n) / n:
                c = (float(xy[0] + dist * math.cos(a)), float(xy[1] + dist * math.sin(a)))
                if not area.contains(np.array([c]), area.margin_m)[0]:
                    continue
                for r in radii:
                    ring = np.column_stack([c[0] + r * np.cos(th), c[1] + r * np.sin(th)])
                    if area.path_inside(ring, area.margin_m):
                        return c, r
        return (float(xy[0]), float(xy[1])), 8.0  # nothing fits: the loop refuses it

    def helix(self, center: XY, radius: float, z0: float, z1: float, turns: float,
              a: AgentView, name: str) -> Trajectory:
        """A helix about ``center`` from height ``z0`` to ``z1`` above the terrain, at the
        cruise speed or slower (lateral acceleration), with the leg to it kept inside."""
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

    def heard_center(self, r: ResponderView) -> tuple[XY, float]:
        """Where the responder was heard (the drone positions weighted by 1/range^2) and
        the median horizontal range it was heard at (clipped to the probe radii)."""
        m, c = self.mission, self.cfg
        heard = np.asarray(r.heard_enu_m, dtype=float).reshape(-1, 3)
        rng_m = np.asarray(r.heard_range_m, dtype=float)
        w = 1.0 / np.maximum(rng_m, 5.0) ** 2
        center = tuple((heard[:, :2] * w[:, None]).sum(axis=0) / w.sum())
        horiz = np.sqrt(np.maximum(rng_m**2 - m.height_m**2, 0.0))
        return center, float(np.clip(np.median(horiz), *c.probe_radius_m))

    def probe(self, r: ResponderView, a: AgentView) -> Trajectory:
        """Orbit where the heard ranges put the responder (a coarse grid fit), climbing;
        both mirror candidates when the estimator reports them; the range ring when too
        few ranges place it."""
        m, c = self.mission, self.cfg
        if r.candidates:
            cand = np.asarray(r.candidates)[:, :2]
            center = tuple(np.mean(cand, axis=0))
            radius = max(c.probe_radius_m[0], 0.5 * float(np.ptp(cand, axis=0).max()) + 15.0)
        else:
            fit = coarse_fit(r, m)
            if fit is None or fit[1] > 2.0 * c.probe_radius_m[1]:
                return self.ring(r, a)
            center, spread = fit
            radius = float(np.clip(spread + 15.0, *c.probe_radius_m))
        (cx, cy), radius = self.in_view(center, radius)
        return self.helix((cx, cy), radius, m.height_m, m.height_m + c.probe_climb_m, 1.25, a,
                          "probe")

    def orbit_view(self, center: Sequence[float], radius: float,
                   height_m: float) -> tuple[float, bool]:
        """The mean response probability of a level orbit ``height_m`` above the
        terrain to a responder on the ground at ``center`` (the link model's, the
        terrain's obstruction included), and whether the terrain hides it from any
        point of the orbit."""
        m, c = self.mission, self.cfg
        th = np.linspace(0.0, 2.0 * math.pi, 36, endpoint=False)
        e = float(center[0]) + radius * np.cos(th)
        n = float(center[1]) + radius * np.sin(th)
        pts = np.column_stack([e, n, np.asarray(m.terrain.height_m(e, n), dtype=float)
                               + height_m])
        ground = float(np.asarray(m.terrain.height_m(float(center[0]), float(center[1]))))
        target = np.array([float(center[0]), float(center[1]), ground + c.responder_height_m])
        p = np.asarray(m.link.response_probability_between(pts, target, m.terrain), dtype=float)
        free = np.asarray(m.link.response_probability(np.linalg.norm(pts - target, axis=1)),
                          dtype=float)
        return float(p.mean()), bool(np.any(p < free * (1.0 - 1e-9)))

    def in_view(self, center: Sequence[float], radius: float) -> tuple[XY, float]:
        """:meth:`inside_center`, and when the terrain hides the centre (the likely
        area) from part of that orbit (at the probe's mid height), the radius of
        ``view_radii`` x radius (at least the smallest probe radius) whose orbit has the
        highest mean response probability: closer orbits look down over a ridge."""
        m, c = self.mission, self.cfg
        (cx, cy), r0 = self.inside_center(center, radius)
        mid = m.height_m + 0.5 * c.probe_climb_m
        p0, hidden = self.orbit_view((cx, cy), r0, mid)
        if not hidden:
            return (cx, cy), r0
        best = (p0, r0, (cx, cy))
        for f in c.view_radii[1:]:
            r = max(radius * f, c.probe_radius_m[0])
            (x, y), r = self.inside_center(center, r)
            p, _ = self.orbit_view((x, y), r, mid)
            if p > best[0]:
                best = (p, r, (x, y))
        return best[2], best[1]

    def ring(self, r: ResponderView, a: AgentView) -> Trajectory:
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
        ring = [m.area.pull_inside(np.array([c[0] + rho * math.cos(t), c[1] + rho * math.sin(t)]))
                for t in th]
        pts = m.area.join([a.position_enu_m[:2], *ring])
        return polyline_trajectory(pts, m.height_m, m.speed_mps, m.origin, "probe ring")

    def close_helix(self, r: ResponderView, a: AgentView) -> Trajectory:
        """A close helix about the estimate, through an altitude band (height and range
        bias cannot be told apart at one altitude)."""
        m, c = self.mission, self.cfg
        assert r.mean_enu_m is not None
        (cx, cy), radius = self.inside_center(r.mean_enu_m[:2], c.close_radius_m)
        return self.helix((cx, cy), radius, band_floor_m(m, c.close_climb_m[0]),
                          m.height_m + c.close_climb_m[1], c.close_turns, a, "close")

    def orbit(self, center: Sequence[float], radius: float, a: AgentView,
              turns: float = 1.0) -> Trajectory:
        """A level orbit at the search height about ``center`` (moved to fit inside)."""
        m = self.mission
        (cx, cy), radius = self.inside_center(center, radius)
        return self.helix((cx, cy), radius, m.height_m, m.height_m, turns, a, "orbit")

    def close_pass(self, center: Sequence[float], cov_m2, a: AgentView,
                   half_length_m: float = 60.0) -> Trajectory:
        """A straight pass over ``center`` along the major axis of the horizontal
        covariance (the direction the estimate knows least), nearer end first, clipped
        into the area."""
        m = self.mission
        c = np.asarray(center, dtype=float)[:2]
        if cov_m2 is not None:
            w, v = np.linalg.eigh(np.asarray(cov_m2, dtype=float)[:2, :2])
            axis = v[:, int(np.argmax(w))]
        else:
            axis = np.array([1.0, 0.0])
        ends = [c - half_length_m * axis, c + half_length_m * axis]
        here = np.asarray(a.position_enu_m[:2], dtype=float)
        if np.linalg.norm(ends[1] - here) < np.linalg.norm(ends[0] - here):
            ends.reverse()
        pts = [self.mission.area.pull_inside(p) for p in (ends[0], c, ends[1])]
        return polyline_trajectory(m.area.join([here, *pts]), m.height_m, m.speed_mps,
                                   m.origin, "close-pass")

    def goto(self, xy: Sequence[float], a: AgentView, name: str = "goto") -> Trajectory:
        """Fly to ``xy`` (pulled inside the area) at the search height, routed inside."""
        m = self.mission
        dest = m.area.pull_inside(np.asarray(xy, dtype=float)[:2])
        return polyline_trajectory(m.area.route(a.position_enu_m[:2], dest), m.height_m,
                                   m.speed_mps, m.origin, name)


class ResponderPlanner:
    """The receding-horizon plan about a responder's estimate that ``adaptive`` flies
    (:class:`planner.optimal.OptimalPlanner` over the altitude band, inside the area's
    local fence and clear of the blocking keep-outs near the vehicle), falling back to
    the probe orbit when the planner refuses the start or its plan leaves the area; also
    the ``planned`` action of ``osa/Search-v2`` (:mod:`envs.gym.plan_actions`).

    The built planner is shared per configuration per process
    (:meth:`planner_for`). ``own_warm_start``: keep this user's warm start
    apart from the other users of the shared planner (worlds stepped in lockstep would
    otherwise warm-start each other); else the planner's own, reset by :meth:`reset`.
    """

    MAX_PLANNER_CIRCLES = 6  # keep-out cylinders the CasADi problem holds at most
    MAX_PLANNER_POLYGONS = 2  # keep-out polygons (convex hulls) it holds at most
    # one built OptimalPlanner per configuration per process, shared by its
    # users (building takes ~1 s; re-solving a built one takes milliseconds)
    _planners: ClassVar[dict[tuple, object]] = {}

    @classmethod
    def planner_for(cls, cfg, key: tuple):
        """The built planner of configuration ``cfg`` (``key`` identifies it)."""
        from planner.optimal import OptimalPlanner

        p = cls._planners.get(key)
        if p is None:
            p = cls._planners[key] = OptimalPlanner(cfg)
        return p

    def __init__(self, config: AdaptiveConfig = AdaptiveConfig(), *,
                 own_warm_start: bool = False) -> None:
        self.cfg = config
        self.own_warm_start = own_warm_start
        self.planner = None
        self.key: tuple | None = None

    def __getstate__(self) -> dict:  # pickles without the built planner (CasADi) ...
        return {k: v for k, v in self.__dict__.items() if k != "planner"}

    def __setstate__(self, state: dict) -> None:  # ... which is this process's again
        self.__dict__.update(state)
        self.planner = (ResponderPlanner.planner_for(self.ocfg, self.key)
                        if self.key is not None else None)

    def reset(self, mission: SearchMission, manoeuvres: Manoeuvres) -> None:
        """The planner of ``mission``'s configuration, its warm start reset."""
        from planner.optimal import OptimalConfig
        from planner.scoring import ScoringConfig

        self.mission, self.manoeuvres = mission, manoeuvres
        m, c = mission, self.cfg
        lo = band_floor_m(m, c.agl_band_m[0])
        hi = m.height_m + c.agl_band_m[1]
        keep: dict = {}
        if m.area.blocking:  # room for the keep-outs near the responder, and their margin
            n_poly = sum(isinstance(k, KeepOutPolygon) for k in m.area.blocking)
            keep = dict(max_keep_outs=min(max(len(m.area.blocking) - n_poly, 1),
                                          self.MAX_PLANNER_CIRCLES),
                        max_keep_out_polygons=min(n_poly, self.MAX_PLANNER_POLYGONS),
                        keep_out_margin_m=0.5 * m.area.margin_m)
        ocfg = OptimalConfig(
            n_waypoints=c.n_waypoints, horizon_s=c.horizon_s, n_prior_points=c.n_prior_points,
            max_iter=c.max_iter,
            max_fence_edges=8, max_keep_outs=1, max_speed_m_s=m.speed_mps,
            agl_min_m=lo, agl_max_m=hi, terrain=m.terrain,
            scoring=ScoringConfig(link=m.link, terrain=m.terrain,
                                  responder_height_m=c.responder_height_m),
        )
        if keep:
            ocfg = dataclasses.replace(ocfg, **keep)
        # terrain and link hash by value (frozen dataclasses; a grid by identity)
        key = (m.terrain, m.link, repr(ocfg))
        if self.planner is None or self.key != key:
            self.planner = ResponderPlanner.planner_for(ocfg, key)
            self.key = key
        self.ocfg = ocfg
        if not self.own_warm_start:  # the others' warm starts are theirs
            self.planner.reset_warm_start()
        self._warm = None
        self.solve_time_s = 0.0  # wall time spent in optimiser solves (benchmarks)

    def plan(self, r: ResponderView, a: AgentView) -> tuple[Trajectory, int]:
        """The plan about ``r``'s estimate from where the vehicle is, or the probe
        orbit; and the number of solves (0 or 1)."""
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
        kw: dict = {}
        if m.area.blocking:  # the blocking keep-outs the horizon can reach
            reach = self.ocfg.horizon_s * self.ocfg.max_speed_m_s + m.area.margin_m
            near = [k for k in m.area.blocking
                    if float(k.signed_distance_m(start[None, :2])[0]) <= reach]
            kw = dict(keep_outs=[k for k in near if isinstance(k, KeepOut)],
                      keep_out_polygons=[k for k in near if isinstance(k, KeepOutPolygon)])
        if self.own_warm_start:
            self.planner.warm_state = self._warm
        try:
            res = self.planner.plan(r.mean_enu_m, cov, start, vel, fence=fence,
                                    agl_band_m=band, origin=m.origin, **kw)
        except ValueError:  # outside the fence, in a keep-out, more keep-outs than it holds
            return self.manoeuvres.probe(r, a), 0
        finally:
            if self.own_warm_start:
                self._warm = self.planner.warm_state
        self.solve_time_s += res.solve_time_s
        traj = res.trajectory
        if not res.feasible or not m.area.path_inside(traj.enu_m, 0.0):
            return self.manoeuvres.probe(r, a), 1
        return traj, 1


class AdaptivePolicy:
    """Search until a responder is heard, then localise it by planning around the
    estimate (see the module docstring)."""

    name = "adaptive"

    def __init__(self, config: AdaptiveConfig = AdaptiveConfig(), *,
                 rule: LocalisedRule = LocalisedRule(), heading_deg: float = 0.0) -> None:
        self.cfg = config
        self.rule = rule
        self.heading_deg = heading_deg
        self.optimal = ResponderPlanner(config)

    # ------------------------------------------------------------------ setup
    def reset(self, mission: SearchMission, rng: np.random.Generator) -> None:
        self.mission = mission
        self.rng = rng
        self.tracker = LocalisedTracker(self.rule)
        self.sweep = Sweep(mission, search_spacing_m(mission, self.cfg.detect_probability),
                           self.heading_deg)
        self.manoeuvres = Manoeuvres(mission, self.cfg)
        self.target: str | None = None
        self.phase = "search"
        self.phase_since = 0.0
        self.target_since = 0.0
        self.abandoned: set[str] = set()
        self.last_plan_t = -math.inf
        self._started = False
        self.optimal.reset(mission, self.manoeuvres)

    @property
    def solve_time_s(self) -> float:
        """Wall time spent in optimiser solves this search (benchmarks)."""
        return self.optimal.solve_time_s

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
            self.sweep.advance(here)
            return Decision(localised=loc)
        self._resume = False
        if self._started:
            # mark what was flown first: a segment flown to its end has passed its last
            # waypoint, and resuming at a waypoint the vehicle stands on would be an
            # empty segment, done at once, forever (a hover that nobody asked for)
            self.sweep.advance(here)
            if self.sweep.at_end:
                heard = {r.bssid for r in obs.responders}
                if a.segment_done and m.expected_responders is None and heard and \
                        heard <= set(loc):
                    self.sweep.passes += 1
                    return Decision(localised=loc, done=True, note="covered, all localised")
                self.sweep.reverse()
        self._started = True
        return Decision(plans={0: self.sweep.resume(here)}, localised=loc, note="search")

    def _localise(self, obs: Observation, r: ResponderView, loc: frozenset[str],
                  a: AgentView) -> Decision:
        c = self.cfg
        t = obs.t_s
        if r.tracked:
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
                traj, solves = self.optimal.plan(r, a)
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
    def _probe(self, r: ResponderView, a: AgentView) -> Trajectory:
        return self.manoeuvres.probe(r, a)

    def _close_helix(self, r: ResponderView, a: AgentView) -> Trajectory:
        return self.manoeuvres.close_helix(r, a)


def coarse_fit(r: ResponderView, mission: SearchMission, cell_m: float = 10.0,
               noise_m: float = 3.0) -> tuple[XY, float] | None:
    """Where the heard ranges put a responder before the estimator can: the best points
    of a grid over the area (the map's terrain under each), scored by the robust sum of
    (range - h)^2 over the heard (position, range) pairs, h the estimator's range model
    without bias (:mod:`estimator.measurement`). Returns the centre of
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
    d = geometric_range_m(np.column_stack([g, gz])[:, None, :], heard[None, :, :])
    res = (rng[None, :] - d) / noise_m
    cost = np.minimum(res * res, 9.0).sum(axis=1)  # robust: a far outlier costs at most 9
    best = float(cost.min())
    near = cost <= best + 2.0 * max(1.0, 0.1 * len(rng))
    pts = g[near]
    centre = pts.mean(axis=0)
    spread = float(np.max(np.linalg.norm(pts - centre, axis=1)))
    return (float(centre[0]), float(centre[1])), spread
