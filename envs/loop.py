"""The closed loop: vehicle -> phone records -> estimator -> policy -> vehicle.

:class:`ClosedLoop` is the one loop of ``osa search``, the evaluation harness and the
Gymnasium/PettingZoo environments, whatever flies: it runs over a
:class:`envs.vehicles.Vehicle`, the stepped simulator in process
(:class:`envs.vehicles.SimVehicle`, the default) or a MAVLink autopilot
(:class:`envs.mavlink_vehicle.MavlinkVehicle`). It owns

- the online estimator (:mod:`estimator.online`), fed with every record the phones
  deliver, in the order a replay of their logs reads them;
- where each range was heard: the estimator's own association of that range with the
  phone's GNSS (:class:`estimator.online.RangeObserver`), the same for every vehicle;
- what a policy may see (``observe()``: the autopilots' estimates and the estimator's
  output, never the truth), and what it may fly (``apply(decision)``: a segment that
  would leave the area is refused and the vehicle holds, :meth:`ClosedLoop.plan_inside`);
- progress: a vehicle that makes no progress on a pending segment for longer than
  ``LoopConfig.stall_s`` (beyond the stops the plan itself makes) is a *stall*: counted,
  noted, and its segment reported done so that the policy plans anew;
- the evaluation (errors against the truth, for the report and the figures only).

:func:`run_search` drives a :class:`planner.observation.Policy` until it is done or the
budget is spent and returns a :class:`SearchResult` (the ``osa search`` report).

Frames: the mission (area, plans, observations) is in the world's ENU frame (exact
WGS84 ENU at ``[world.origin]``, what an operator's map gives); the estimator keeps its
own frame (eq. 1 at its first anchor) and reports WGS84, which the loop converts. The
errors are measured in the estimator's frame, as ``osa replay`` measures them.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from envs.phone import PhoneBatch
from envs.vehicles import SimVehicle, Vehicle
from estimator.association import GeoRange
from estimator.evaluation import errors_m
from estimator.online import EstimatorOptions, OnlineEstimator
from estimator.records import Estimate, Trajectory
from estimator.replay import parse_modes
from planner.area import SearchArea
from planner.observation import (
    AgentView,
    Decision,
    Observation,
    Policy,
    ResponderView,
    SearchMission,
)
from planner.patterns import KeepOut, KeepOutPolygon
from sim.ftm import FtmLink
from sim.realisation import Realisation, realise
from sim.scenario import Scenario

DEFAULT_MODE = "best"  # the recommended estimator mode (its real name: refined)


@dataclass(frozen=True, kw_only=True)
class LoopConfig:
    """How the loop runs (our choices, documented in docs/search.md)."""

    decision_period_s: float = 5.0  # the policy is asked every this many seconds
    mode: str = DEFAULT_MODE  # estimator mode (a name parse_modes accepts: "best" too)
    area_margin_m: float = 10.0  # patterns keep this far inside the area's edges
    heard_kept: int = 60  # drone positions kept per responder heard (most recent)
    stall_s: float = 30.0  # no progress this long on a pending segment: a stall
    stall_radius_m: float = 3.0  # "no progress": the autopilot's position within this

    def __post_init__(self) -> None:
        if not (math.isfinite(self.decision_period_s) and self.decision_period_s > 0):
            raise ValueError("decision_period_s must be > 0")
        if not (math.isfinite(self.stall_s) and self.stall_s > 0 and self.stall_radius_m > 0):
            raise ValueError("stall_s and stall_radius_m must be > 0")
        modes = parse_modes(self.mode)
        if len(modes) != 1:
            raise ValueError(f"the loop runs one estimator mode, not {self.mode!r}")

    @property
    def estimator_mode(self) -> str:
        """The one estimator mode, resolved (``best`` -> its real name)."""
        return parse_modes(self.mode)[0]


def mission_of(scenario: Scenario, realisation: Realisation | None = None,
               margin_m: float = 10.0) -> SearchMission:
    """The operator's view of a search scenario: area, start, budget, map and link."""
    s = scenario.search
    if s is None:
        raise ValueError(f"scenario {scenario.name} has no [search] table")
    o = scenario.world.origin
    world = realisation.world if realisation is not None else scenario.world
    # the keep-outs: those whose top is well below the search height are flown over (the
    # policies then never fly below it); every other one is a hole in the area
    keep_outs = tuple(
        KeepOut(east_m=k.center_enu_m[0], north_m=k.center_enu_m[1], radius_m=k.radius_m,
                top_m=k.top_m) if k.center_enu_m is not None
        else KeepOutPolygon(vertices_m=k.polygon_enu_m, top_m=k.top_m)
        for k in scenario.keepouts)
    return SearchMission(
        area=SearchArea(tuple(tuple(v) for v in s.area_enu_m), margin_m, keep_outs=keep_outs,
                        floor_m=s.height_m if keep_outs else None),
        start_enu_m=(s.start_e_m, s.start_n_m),
        budget_s=s.budget_s,
        height_m=s.height_m,
        speed_mps=s.speed_mps,
        terrain=world.terrain,
        link=FtmLink(scenario.ftm),
        origin=(o.lat_deg, o.lon_deg, o.h_m),
        expected_responders=s.expected_responders,
        n_agents=len(scenario.agents),
        max_accel_mps2=scenario.vehicle.max_accel_mps2,
    )


@dataclass
class _Heard:
    first_t_s: float
    n: int = 0
    pos: list[tuple[float, float, float]] = field(default_factory=list)
    rng: list[float] = field(default_factory=list)


class HeardRanges:
    """Where each range was heard, as the estimator associated it: told of every
    associated range (an :class:`estimator.online.RangeObserver`), it keeps per
    responder the first time, the count and the most recent ``kept`` drone positions
    (the phone's GNSS anchor, mission ENU) with their corrected ranges."""

    def __init__(self, kept: int) -> None:
        self.kept = kept
        self.by_bssid: dict[str, _Heard] = {}
        self._pending: list[tuple[int, GeoRange]] = []

    def associated(self, agent: int, g: GeoRange) -> None:
        self._pending.append((agent, g))

    def settle(self, frame, clock_offset_s: Sequence[float | None], now_s: float) -> None:
        """Put the ranges associated since the last call in the mission frame; a range's
        flight time is its phone time minus the phone's clock offset."""
        if not self._pending:
            return
        pend, self._pending = self._pending, []
        lat = np.array([g.lat_deg for _, g in pend])
        lon = np.array([g.lon_deg for _, g in pend])
        alt = np.array([g.alt_m for _, g in pend])
        e, n, u = frame.to_enu(lat, lon, alt)
        pos = np.column_stack([e, n, u]).tolist()
        for (agent, g), p in zip(pend, pos, strict=True):
            off = clock_offset_s[agent]
            t = g.t_ns * 1e-9 - off if off is not None else now_s
            h = self.by_bssid.get(g.bssid)
            if h is None:
                h = self.by_bssid[g.bssid] = _Heard(first_t_s=t)
            h.n += 1
            h.pos.append((p[0], p[1], p[2]))
            h.rng.append(float(g.range_m))
            if len(h.pos) > self.kept:
                del h.pos[0], h.rng[0]


@dataclass
class SeriesPoint:
    """One evaluation sample of one responder (truth used: figures and reports only)."""

    t_s: float
    status: str
    sigma_h_m: float | None
    r95_h_m: float | None
    err_h_m: float | None


@dataclass
class _Progress:
    """One agent's progress on its pending segment (stall detection)."""

    since_s: float = 0.0
    anchor: tuple[float, float, float] | None = None
    planned_still_s: float = 0.0  # the longest stop the plan itself makes
    stalled: bool = False
    longest_still_s: float = 0.0  # evaluation: the longest still time while pending


HOVER_RADIUS_M = 3.0  # "still": within this of one point (evaluation, the benchmarks)


def planned_still_s(traj: Trajectory, radius_m: float) -> float:
    """The longest time the plan itself keeps the vehicle within ``radius_m`` of one
    point (its hovers and slow climbs): not a stall."""
    return _longest_within_s(traj.t_s, traj.enu_m, radius_m)


def longest_hover_s(track, radius_m: float = HOVER_RADIUS_M) -> float:
    """Evaluation: the longest time a track of (t, e, n, u) rows (``nav_track``) stayed
    within ``radius_m`` of one point, whatever the policy asked (a hover it asked for
    counts too; :meth:`ClosedLoop.longest_still_s` counts only pending segments)."""
    rows = np.asarray(track, dtype=float).reshape(-1, 4)
    return _longest_within_s(rows[:, 0], rows[:, 1:4], radius_m)


def _longest_within_s(t_s, enu_m, radius_m: float) -> float:
    p = np.asarray(enu_m, dtype=float)
    t = np.asarray(t_s, dtype=float)
    best, i = 0.0, 0
    for j in range(1, len(p)):
        while float(np.linalg.norm(p[j] - p[i])) > radius_m:
            i += 1
        best = max(best, float(t[j] - t[i]))
    return best


class ClosedLoop:
    """One search in closed loop over a vehicle (see the module docstring).

    Without ``vehicle`` the scenario's world (``realisation``, else realised from
    ``seed``) is flown in process by a :class:`SimVehicle` whose phones write
    ``log_paths``. With a vehicle (e.g. over MAVLink), ``realisation`` is still the
    world of the scenario and seed: the truth of the evaluation.
    """

    def __init__(
        self,
        scenario: Scenario,
        seed=0,
        *,
        config: LoopConfig = LoopConfig(),
        vehicle: Vehicle | None = None,
        log_paths: Sequence[str | Path] | None = None,
        flush_lines: bool = False,
        realisation: Realisation | None = None,
    ) -> None:
        if scenario.search is None:
            raise ValueError(f"scenario {scenario.name} has no [search] table")
        self.scenario = scenario
        self.seed = seed
        self.config = config
        self.realisation = realisation if realisation is not None else realise(scenario, seed)
        self.world = self.realisation.world
        self.mission = mission_of(scenario, self.realisation, config.area_margin_m)
        self.mode = config.estimator_mode
        if vehicle is None:
            vehicle = SimVehicle(self.realisation, header_agl_m=scenario.search.height_m,
                                 log_paths=log_paths, flush_lines=flush_lines)
            self.log_paths = [Path(p) for p in log_paths] if log_paths is not None else []
        else:
            self.log_paths = list(getattr(vehicle, "log_paths", []))
        self.vehicle = vehicle
        n = vehicle.n_agents
        self.truth = {t.bssid: t for t in self.realisation.truth_records()}
        self.heard = HeardRanges(config.heard_kept)
        self.estimator: OnlineEstimator | None = None
        self.replans = 0
        self.refused_plans = 0
        self.stalls: list[tuple[float, int, tuple[float, float, float], float]] = []
        self.localised_at: dict[str, float] = {}
        self.series: dict[str, list[SeriesPoint]] = {b: [] for b in self.truth}
        self.notes: list[tuple[float, str]] = []
        self.nav_track: list[list[tuple[float, float, float, float]]] = [[] for _ in range(n)]
        self.started = False
        self.finished = False
        self._advanced_to_budget = False
        self._refused: set[int] = set()
        self._progress = [_Progress() for _ in range(n)]
        self._clock_offset_s: list[float | None] = [None] * n
        self._estimates: dict[str, Estimate] = {}  # until the estimator is fed again
        if isinstance(vehicle, SimVehicle):
            self.start()

    # ------------------------------------------------------------------ start
    def start(self) -> None:
        """Start the vehicle (connect, check, arm) and the estimator; idempotent."""
        if self.started:
            return
        self.vehicle.start()
        height = self.scenario.search.height_m  # the configured H_AGL of a search
        self.estimator = OnlineEstimator(EstimatorOptions(modes=(self.mode,)),
                                         range_observers=(self.heard,))
        for i in range(self.vehicle.n_agents):
            h = replace(self.vehicle.header(i), agl_m=round(float(height), 3))
            self.estimator.add_agent(h.agent, header=h)
        self.started = True

    @property
    def t_s(self) -> float:
        """Flight time (the vehicle's clock, from the start of the search)."""
        return self.vehicle.t_s

    @property
    def budget_spent(self) -> bool:
        """Is the budget flown? The clock reached it, or the loop advanced to it: a
        vehicle on a time grid stops at its last tick within the budget (a budget of
        10.03 s on the 0.05 s grid is 10.0 s of flight; before, the loop asked for the
        remaining 0.03 s forever)."""
        return self._advanced_to_budget or self.t_s >= self.mission.budget_s - 1e-9

    @property
    def stepper(self):
        """The in-process simulator (a :class:`SimVehicle`'s; evaluation and tests)."""
        return self.vehicle.stepper  # type: ignore[attr-defined]

    # ------------------------------------------------------------------ knowledge
    def estimate(self, bssid: str) -> Estimate:
        """The estimator's estimate of ``bssid`` (kept until the next records reach it)."""
        e = self._estimates.get(bssid)
        if e is None:
            e = self._estimates[bssid] = self.estimator.estimate(bssid, self.mode)
        return e

    def _world_enu(self, e: Estimate) -> tuple[float, float, float] | None:
        if e.lat_deg is None:
            return None
        x, y, z = self.world.frame.to_enu(e.lat_deg, e.lon_deg, e.alt_m)
        return float(x), float(y), float(z)

    def _to_world(self, p_est: Sequence[float]) -> tuple[float, float, float]:
        lat, lon, alt = self.estimator.frame.to_geodetic(*p_est)
        x, y, z = self.world.frame.to_enu(lat, lon, alt)
        return float(x), float(y), float(z)

    def responder_views(self) -> tuple[ResponderView, ...]:
        """What the estimator says of every responder heard so far (no truth)."""
        views = []
        for b, h in self.heard.by_bssid.items():
            e = self.estimate(b)
            kw: dict = {}
            mean = self._world_enu(e)
            if mean is not None and e.cov_m2 is not None:
                cov = tuple(tuple(float(v) for v in row) for row in e.cov_m2)
                kw = dict(mean_enu_m=mean, cov_m2=cov, sigma_h_m=e.sigma_h_m,
                          r95_h_m=e.r95_h_m)
            cands = tuple(self._to_world(c.mean_enu_m) for c in e.candidates)
            views.append(ResponderView(
                bssid=b, status=e.status, detected_at_s=h.first_t_s, n_heard=h.n,
                heard_enu_m=tuple(h.pos), heard_range_m=tuple(h.rng), n_acc=e.n_acc,
                kappa=e.kappa, candidates=cands, **kw,
            ))
        return tuple(views)

    def segment_done(self, agent: int) -> bool:
        """The agent's last segment is flown (or refused: it holds; or it stalled)."""
        return (agent in self._refused or self._progress[agent].stalled
                or self.vehicle.segment_done(agent))

    def refused(self, agent: int) -> bool:
        """The agent's last segment was refused (it left the area): the vehicle holds."""
        return agent in self._refused

    # ------------------------------------------------------------------ observe
    def observe(self) -> Observation:
        """What a policy may see now (no truth)."""
        self.start()
        agents = []
        for i in range(self.vehicle.n_agents):
            s = self.vehicle.state(i)
            agents.append(AgentView(position_enu_m=s.position_enu_m,
                                    velocity_enu_mps=s.velocity_enu_mps,
                                    segment_done=self.segment_done(i)))
        return Observation(t_s=self.t_s, budget_s=self.mission.budget_s, agents=tuple(agents),
                           responders=self.responder_views())

    # ------------------------------------------------------------------ act
    def apply(self, decision: Decision) -> None:
        """Fly the decision's new segments (a segment leaving the area is refused: the
        vehicle holds instead) and note what it judged localised."""
        self.start()
        for b in decision.localised:
            self.localised_at.setdefault(b, self.t_s)
        self.replans += decision.replans
        if decision.note:
            self.notes.append((self.t_s, decision.note))
        for i, traj in decision.plans.items():
            pr = self._progress[i]
            pr.stalled, pr.anchor, pr.since_s = False, None, self.t_s
            if not self.plan_inside(traj, i):
                self.refused_plans += 1
                self._refused.add(i)
                self.vehicle.hold(i)
                continue
            self._refused.discard(i)
            pr.planned_still_s = planned_still_s(traj, self.config.stall_radius_m)
            self.vehicle.fly(i, traj)

    def plan_inside(self, traj: Trajectory, agent: int = 0) -> bool:
        """Does a segment, and the leg to it from where the autopilot is, stay inside?
        (From outside, e.g. after a turn swung wide, the segment from its first point
        inside on: what comes before brings the vehicle back in.)"""
        if tuple(traj.origin) != tuple(self.mission.origin):
            return False
        area = self.mission.area
        here = np.asarray(self.vehicle.state(agent).position_enu_m[:2])[None, :]
        pts = np.concatenate((here, traj.enu_m[:, :2]))
        inside = area.contains(pts, 0.0)  # point by point: one call for all
        if not inside[0]:  # outside: the segment from its first point inside on (the rest
            if not inside.any():  # comes back)
                return False
            first = int(np.argmax(inside))
            pts, inside = pts[first:], inside[first:]
        if area.convex and not area.blocking:  # straight legs between inside points stay
            return bool(inside.all())  # inside a convex area without holes
        return area.path_inside(pts, 0.0)

    # ------------------------------------------------------------------ advance
    def advance(self, dt_s: float) -> None:
        """Fly ``dt_s`` more (never past the budget); feed the estimator."""
        self.start()
        t_next = min(self.t_s + dt_s, self.mission.budget_s)
        self._ingest(self.vehicle.advance_to(t_next))
        if t_next >= self.mission.budget_s:
            self._advanced_to_budget = True
        for i in range(self.vehicle.n_agents):
            p = self.vehicle.state(i).position_enu_m
            self.nav_track[i].append((self.t_s, *p))
            self._check_progress(i, p)
        self._sample_series()

    def _ingest(self, batches: Sequence[PhoneBatch]) -> None:
        est = self.estimator
        self._estimates.clear()
        for i, b in enumerate(batches):
            if b.clock_offset_s is not None:
                self._clock_offset_s[i] = b.clock_offset_s
            if b.records:
                est.push_many(b.records, i)
            if b.through_ns is not None:
                est.mark_time(i, b.through_ns)
        self.heard.settle(self.world.frame, self._clock_offset_s, self.t_s)

    def _check_progress(self, i: int, p: tuple[float, float, float]) -> None:
        """A pending segment on which the vehicle stays within ``stall_radius_m`` for
        longer than ``stall_s`` plus the plan's own stops is a stall (see the module
        docstring)."""
        pr, cfg, t = self._progress[i], self.config, self.t_s
        if pr.stalled or i in self._refused or self.vehicle.segment_done(i):
            pr.anchor = None
            return
        if pr.anchor is None or math.dist(p, pr.anchor) > cfg.stall_radius_m:
            pr.anchor, pr.since_s = p, t
            return
        still = t - pr.since_s
        pr.longest_still_s = max(pr.longest_still_s, still)
        if still > cfg.stall_s + pr.planned_still_s:
            pr.stalled = True
            self.stalls.append((t, i, p, still))
            self.notes.append((t, f"stall: agent {i} made no progress for {still:.0f} s at "
                                  f"({p[0]:.1f}, {p[1]:.1f}): its segment is done"))

    def longest_still_s(self, agent: int = 0) -> float:
        """Evaluation: the longest time the agent stayed within ``stall_radius_m`` while
        a segment was pending (its plan's own stops included)."""
        return self._progress[agent].longest_still_s

    def finish(self) -> None:
        """End of the flight: deliver what is still on its way, close the logs."""
        if self.finished:
            return
        self.finished = True
        if not self.started:
            self.vehicle.close()
            return
        self._ingest(self.vehicle.finish())
        self.estimator.finish()
        self._estimates.clear()
        self._sample_series()

    def close(self) -> None:
        """Release the vehicle without finishing (after a failure)."""
        self.finished = True
        self.vehicle.close()

    # ------------------------------------------------------------------ evaluation
    def _sample_series(self) -> None:
        """Evaluation (truth): error and uncertainty of every responder now."""
        frame = self.estimator.frame
        for b, tr in self.truth.items():
            e = self.estimate(b)
            err = None
            if e.mean_enu_m is not None and frame is not None:
                err = errors_m(e.mean_enu_m, frame.to_enu(tr.lat_deg, tr.lon_deg, tr.alt_m))[0]
            self.series[b].append(SeriesPoint(self.t_s, e.status, e.sigma_h_m, e.r95_h_m, err))

    def detected_at(self, bssid: str) -> float | None:
        h = self.heard.by_bssid.get(bssid)
        return h.first_t_s if h is not None else None

    def responder_outcome(self, bssid: str) -> dict:
        """The ``responders`` entry of the report (truth errors for evaluation only)."""
        out: dict = {"bssid": bssid}
        det = self.detected_at(bssid)
        if det is not None:
            out["detected_at_s"] = round(det, 3)
        if bssid in self.localised_at:
            out["localised_at_s"] = round(self.localised_at[bssid], 3)
        e = self.estimate(bssid)
        out["status"] = e.status
        if e.lat_deg is not None:
            out.update(lat=round(e.lat_deg, 8), lon=round(e.lon_deg, 8), alt_m=round(e.alt_m, 3),
                       sigma_h_m=round(e.sigma_h_m, 4), sigma_z_m=round(e.sigma_z_m, 4))
            if e.r95_h_m is not None and math.isfinite(e.r95_h_m):
                out["r95_h_m"] = round(e.r95_h_m, 4)
            tr = self.truth.get(bssid)
            frame = self.estimator.frame
            if tr is not None and frame is not None:
                eh, e3 = errors_m(e.mean_enu_m, frame.to_enu(tr.lat_deg, tr.lon_deg, tr.alt_m))
                out["err_h_m"] = round(eh, 3)
                out["err_3d_m"] = round(e3, 3)
        if e.candidates:
            out["candidates"] = [
                {"lat": round(c.lat_deg, 8), "lon": round(c.lon_deg, 8),
                 "alt_m": round(c.alt_m, 3), "sigma_h_m": round(c.sigma_h_m, 4),
                 "weight": round(c.weight, 6)} for c in e.candidates
            ]
        tr = self.truth.get(bssid)
        if tr is not None:
            out["concealment"] = tr.concealment
        return out

    @property
    def path_length_m(self) -> float:
        return self.vehicle.path_length_m

    def true_tracks(self) -> list[np.ndarray]:
        return self.vehicle.true_tracks()

    def excursion_m(self) -> float:
        """The farthest the true path of any agent went outside the area or into a
        keep-out below its top, in metres (0 when it never did; evaluation only:
        ``benchmarks/bench_sweep.py``'s check)."""
        area = self.mission.area
        terrain = self.world.terrain
        worst = 0.0
        for track in self.true_tracks():
            xyz = np.asarray(track)
            xy = xyz[:, :2]
            worst = max(worst, float(np.max(area.signed_distance_m(xy), initial=0.0)))
            for k in area.keep_outs:
                inside = -k.signed_distance_m(xy)
                if k.top_m is not None:  # flown over: only below its top counts
                    agl = xyz[:, 2] - terrain.height_m(xy[:, 0], xy[:, 1])
                    inside = np.where(agl < k.top_m, inside, 0.0)
                worst = max(worst, float(np.max(inside, initial=0.0)))
        return worst


@dataclass
class SearchResult:
    """The outcome of one search (the ``osa search`` report) and its evaluation series."""

    policy: str
    mode: str
    seed: object
    ended: str  # "localised" | "budget" | "interrupted"
    flight_time_s: float
    path_length_m: float
    replans: int
    responders: list[dict]
    log: str | None
    logs: list[str]
    refused_plans: int
    series: dict[str, list[SeriesPoint]] = field(repr=False, default_factory=dict)
    nav_track: list[list[tuple[float, float, float, float]]] = field(repr=False,
                                                                     default_factory=list)
    true_track: list[np.ndarray] = field(repr=False, default_factory=list)
    truth_enu_m: dict[str, tuple[float, float, float]] = field(repr=False, default_factory=dict)
    estimates_enu_m: dict[str, tuple[float, float, float]] = field(repr=False,
                                                                   default_factory=dict)
    area_enu_m: tuple = ()
    notes: list[tuple[float, str]] = field(repr=False, default_factory=list)
    scenario: str = ""
    stalls: list[dict] = field(default_factory=list)
    phone: dict | None = None  # over a network: the record path's counts

    def to_json(self) -> dict:
        seed = self.seed if isinstance(self.seed, int | np.integer) else str(self.seed)
        d = {
            "policy": self.policy,
            "mode": self.mode,
            "seed": int(seed) if isinstance(seed, int | np.integer) else seed,
            "ended": self.ended,
            "flight_time_s": round(self.flight_time_s, 3),
            "path_length_m": round(self.path_length_m, 2),
            "replans": self.replans,
            "responders": self.responders,
            "log": self.log,
        }
        if len(self.logs) > 1:
            d["logs"] = self.logs
        d["scenario"] = self.scenario
        d["refused_plans"] = self.refused_plans
        d["stalls"] = len(self.stalls)
        if self.stalls:
            d["stall_events"] = self.stalls
        if self.phone is not None:
            d["phone"] = self.phone
        return d


def drive(loop: ClosedLoop, policy: Policy,
          progress: Callable[[float, str], None] | None = None,
          policy_rng: np.random.Generator | None = None,
          should_stop: Callable[[], bool] | None = None) -> str:
    """Run ``policy`` on a loop until it is done, the budget is spent or
    ``should_stop()`` says so (checked before each decision); returns how it ended
    (``localised``, ``budget`` or ``interrupted``). The loop is not finished here."""
    loop.start()
    rng = policy_rng if policy_rng is not None else np.random.default_rng(
        np.random.SeedSequence(loop.realisation.seed.entropy, spawn_key=(9,))
    )
    policy.reset(loop.mission, rng)
    while not loop.budget_spent:
        if should_stop is not None and should_stop():
            return "interrupted"
        d = policy.decide(loop.observe())
        loop.apply(d)
        if d.done:
            return "localised"
        loop.advance(loop.config.decision_period_s)
        if progress is not None:
            progress(loop.t_s, loop.notes[-1][1] if loop.notes else "")
    d = policy.decide(loop.observe())  # the policy's last judgement at the budget
    for b in d.localised:
        loop.localised_at.setdefault(b, loop.t_s)
    return "budget"


def fly(loop: ClosedLoop, policy: Policy, *,
        progress: Callable[[float, str], None] | None = None,
        policy_rng: np.random.Generator | None = None,
        should_stop: Callable[[], bool] | None = None) -> SearchResult:
    """Drive ``policy`` on ``loop`` (:func:`drive`), finish the loop (what is still on
    its way is delivered, the logs are closed) and report. A failure (an exception,
    Ctrl-C) releases the vehicle and propagates."""
    try:
        ended = drive(loop, policy, progress, policy_rng, should_stop)
        loop.finish()
    except BaseException:
        loop.close()
        raise
    return result_of(loop, policy.name, ended)


def run_search(
    scenario: Scenario,
    policy: Policy,
    seed=0,
    *,
    config: LoopConfig = LoopConfig(),
    log_paths: Sequence[str | Path] | None = None,
    progress: Callable[[float, str], None] | None = None,
    policy_rng: np.random.Generator | None = None,
) -> SearchResult:
    """Fly ``scenario`` in process with ``policy`` until it is done or the budget is
    spent."""
    loop = ClosedLoop(scenario, seed, config=config, log_paths=log_paths)
    return fly(loop, policy, progress=progress, policy_rng=policy_rng)


def result_of(loop: ClosedLoop, policy_name: str, ended: str) -> SearchResult:
    """The report of a finished search."""
    frame = loop.world.frame
    bssids = list(loop.truth)
    truth_enu = {b: tuple(float(v) for v in frame.to_enu(t.lat_deg, t.lon_deg, t.alt_m))
                 for b, t in loop.truth.items()}
    est_enu = {}
    for b in bssids:
        e = loop.estimate(b)
        if e.lat_deg is not None:
            est_enu[b] = tuple(float(v) for v in frame.to_enu(e.lat_deg, e.lon_deg, e.alt_m))
    logs = [str(p) for p in loop.log_paths]
    stats = getattr(loop.vehicle, "phone_stats", None)
    return SearchResult(
        policy=policy_name,
        mode=loop.mode,
        seed=loop.seed,
        ended=ended,
        flight_time_s=loop.t_s,
        path_length_m=loop.path_length_m,
        replans=loop.replans,
        responders=[loop.responder_outcome(b) for b in bssids],
        log=logs[0] if logs else None,
        logs=logs,
        refused_plans=loop.refused_plans,
        series=loop.series,
        nav_track=loop.nav_track,
        true_track=loop.true_tracks(),
        truth_enu_m=truth_enu,
        estimates_enu_m=est_enu,
        area_enu_m=tuple(tuple(v) for v in loop.scenario.search.area_enu_m),
        notes=loop.notes,
        scenario=loop.scenario.name,
        stalls=[{"t_s": round(t, 3), "agent": i, "e_m": round(p[0], 2), "n_m": round(p[1], 2),
                 "still_s": round(s, 1)} for t, i, p, s in loop.stalls],
        phone=stats() if callable(stats) else None,
    )
