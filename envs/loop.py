"""The closed loop in simulated time: simulator -> estimator -> policy -> vehicle.

:class:`ClosedLoop` joins the three step-by-step pieces: a realised world and its
stepper (:mod:`sim.stepper`), the online estimator (:mod:`estimator.online`) fed with
every record the phones log, in the order a replay of their logs gives, and the
phones' logs written as they fly. It offers ``observe()`` (what a policy may see:
the autopilots' estimates and the estimator's output, never the truth), ``apply(
decision)`` (new segments to fly) and ``advance(dt)``; :func:`run_search` drives it
with a :class:`planner.observation.Policy` until the policy says it is done or the budget
is spent, and returns a :class:`SearchResult` (the ``osa search`` JSON report, plus
time series for figures). The Gymnasium environments use the same object.

Frames: the mission (area, plans, observations) is in the world's ENU frame (exact
WGS84 ENU at ``[world.origin]``, what an operator's map gives); the estimator keeps its
own frame (eq. 1 at its first anchor) and reports WGS84, which the loop converts.

Evaluation: errors against the truth are computed by the loop for the report and the
figures only (the ``evaluation`` fields); they never reach the policy. The errors are
measured in the estimator's frame, as ``osa replay`` measures them, so a replay of the
written log reports the same numbers.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from estimator.evaluation import errors_m
from estimator.online import EstimatorOptions, OnlineEstimator
from estimator.records import Estimate, RangeSample, Trajectory
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
from sim.stepper import REPLAY_ORDER, Emitted, LogSink, Stepper

DEFAULT_MODE = "best"  # the recommended estimator mode (its real name: refined)


@dataclass(frozen=True, kw_only=True)
class LoopConfig:
    """How the loop runs (our choices, documented in the README)."""

    decision_period_s: float = 5.0  # the policy is asked every this many seconds
    mode: str = DEFAULT_MODE  # estimator mode (a name parse_modes accepts: "best" too)
    area_margin_m: float = 10.0  # patterns keep this far inside the area's edges
    heard_kept: int = 60  # drone positions kept per responder heard (most recent)

    def __post_init__(self) -> None:
        if not (math.isfinite(self.decision_period_s) and self.decision_period_s > 0):
            raise ValueError("decision_period_s must be > 0")
        modes = parse_modes(self.mode)
        if len(modes) != 1:
            raise ValueError(f"the loop runs one estimator mode, not {self.mode!r}")


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
    )


@dataclass
class _Heard:
    first_t_s: float
    n: int = 0
    pos: list[tuple[float, float, float]] = field(default_factory=list)
    rng: list[float] = field(default_factory=list)


@dataclass
class SeriesPoint:
    """One evaluation sample of one responder (truth used: figures and reports only)."""

    t_s: float
    status: str
    sigma_h_m: float | None
    r95_h_m: float | None
    err_h_m: float | None


class SearchLoopBase:
    """What every closed loop shares (in process here, over MAVLink in
    :mod:`envs.mavlink_loop`): the estimator fed with the phones' records, the
    responders heard and where, the observations of them a policy gets (no truth), the
    evaluation series and the report's entries (the truth, for evaluation only).

    A subclass flies the vehicle: it calls :meth:`_init_search`, feeds records to
    ``self.estimator`` and heard ranges to :meth:`_hear`, and provides ``observe``,
    ``apply``, ``advance``, ``finish``, ``t_s``, ``path_length_m``, ``log_paths``,
    ``nav_track`` and :meth:`true_tracks`.
    """

    def _init_search(self, scenario: Scenario, seed, realisation: Realisation | None,
                     config: LoopConfig, headers: Sequence) -> None:
        if scenario.search is None:
            raise ValueError(f"scenario {scenario.name} has no [search] table")
        self.scenario = scenario
        self.seed = seed
        self.config = config
        self.realisation = realisation if realisation is not None else realise(scenario, seed)
        self.world = self.realisation.world
        self.mission = mission_of(scenario, self.realisation, config.area_margin_m)
        self.mode = parse_modes(config.mode)[0]
        self.estimator = OnlineEstimator(EstimatorOptions(modes=(self.mode,)))
        for h in headers:
            self.estimator.add_agent(h.agent, header=h)
        self.truth = {t.bssid: t for t in self.realisation.truth_records()}
        self._heard: dict[str, _Heard] = {}
        self.replans = 0
        self.refused_plans = 0
        self.localised_at: dict[str, float] = {}
        self.series: dict[str, list[SeriesPoint]] = {b: [] for b in self.truth}
        self.notes: list[tuple[float, str]] = []
        self.finished = False

    # ------------------------------------------------------------------ knowledge
    def _hear(self, bssid: str, t_s: float, position_enu_m: Sequence[float],
              range_m: float) -> None:
        """An ``ok`` range to ``bssid`` heard at flight time ``t_s`` from the position the
        autopilot reported (mission ENU)."""
        h = self._heard.get(bssid)
        if h is None:
            h = self._heard[bssid] = _Heard(first_t_s=t_s)
        h.n += 1
        h.pos.append((float(position_enu_m[0]), float(position_enu_m[1]),
                      float(position_enu_m[2])))
        h.rng.append(float(range_m))
        if len(h.pos) > self.config.heard_kept:
            del h.pos[0], h.rng[0]

    def _world_enu(self, e: Estimate) -> tuple[float, float, float] | None:
        if e.lat_deg is None:
            return None
        x, y, z = self.world.frame.to_enu(e.lat_deg, e.lon_deg, e.alt_m)
        return float(x), float(y), float(z)

    def _to_world(self, p_est: Sequence[float]) -> tuple[float, float, float]:
        lat, lon, alt = self.estimator.frame.to_geodetic(*p_est)
        x, y, z = self.world.frame.to_enu(lat, lon, alt)
        return float(x), float(y), float(z)

    def estimate(self, bssid: str) -> Estimate:
        return self.estimator.estimate(bssid, self.mode)

    def responder_views(self) -> tuple[ResponderView, ...]:
        """What the estimator says of every responder heard so far (no truth)."""
        views = []
        for b, h in self._heard.items():
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

    def _note(self, decision: Decision) -> None:
        """Bookkeeping of a decision: localised set, solves, what the policy does."""
        for b in decision.localised:
            self.localised_at.setdefault(b, self.t_s)
        self.replans += decision.replans
        if decision.note:
            self.notes.append((self.t_s, decision.note))

    def _sample_series(self) -> None:
        """Evaluation (truth): error and uncertainty of every responder now."""
        frame = self.estimator.frame
        for b, tr in self.truth.items():
            e = self.estimate(b)
            err = None
            if e.mean_enu_m is not None and frame is not None:
                err = errors_m(e.mean_enu_m, frame.to_enu(tr.lat_deg, tr.lon_deg, tr.alt_m))[0]
            self.series[b].append(SeriesPoint(self.t_s, e.status, e.sigma_h_m, e.r95_h_m, err))

    # ------------------------------------------------------------------ outcome
    def detected_at(self, bssid: str) -> float | None:
        h = self._heard.get(bssid)
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


class ClosedLoop(SearchLoopBase):
    """One search in closed loop (see the module docstring)."""

    def __init__(
        self,
        scenario: Scenario,
        seed=0,
        *,
        config: LoopConfig = LoopConfig(),
        log_paths: Sequence[str | Path] | None = None,
        flush_lines: bool = False,
        realisation: Realisation | None = None,
    ) -> None:
        if scenario.search is None:
            raise ValueError(f"scenario {scenario.name} has no [search] table")
        real = realisation if realisation is not None else realise(scenario, seed)
        self.stepper = Stepper(real, header_agl_m=scenario.search.height_m)
        self._init_search(scenario, seed, real, config, [a.header for a in self.stepper.agents])
        self._convex = self.mission.area.convex
        truth = self.realisation.truth_records()
        self.sinks: list[LogSink] = []
        if log_paths is not None:
            if len(log_paths) != len(self.stepper.agents):
                raise ValueError("one log path per agent")
            for a, p in zip(self.stepper.agents, log_paths, strict=True):
                self.sinks.append(LogSink(p, a.header, truth, flush_lines=flush_lines))
        self.log_paths = [Path(p) for p in log_paths] if log_paths is not None else []
        self.t_s = 0.0
        self._segment: dict[int, object] = {}
        self._refused: set[int] = set()
        self._path_m = [0.0] * len(self.stepper.agents)
        self._last_pos = [self.stepper.state(i).position_m for i in range(len(self.stepper.agents))]
        self.nav_track: list[list[tuple[float, float, float, float]]] = [
            [] for _ in self.stepper.agents
        ]
        self._estimates: dict[str, Estimate] = {}  # until the estimator is fed again

    def estimate(self, bssid: str) -> Estimate:
        """The estimator's estimate of ``bssid`` (kept until the next records reach it)."""
        e = self._estimates.get(bssid)
        if e is None:
            e = self._estimates[bssid] = super().estimate(bssid)
        return e

    # ------------------------------------------------------------------ observe
    def observe(self) -> Observation:
        """What a policy may see now (no truth)."""
        agents = []
        for i, a in enumerate(self.stepper.agents):
            nav = self.stepper.navigation_position_m(i)
            v = a.vehicle.state.velocity_mps
            g = self._segment.get(i)
            done = g is None or i in self._refused or bool(getattr(g, "done", False))
            agents.append(AgentView(position_enu_m=nav, velocity_enu_mps=tuple(v),
                                    segment_done=done))
        return Observation(t_s=self.t_s, budget_s=self.mission.budget_s, agents=tuple(agents),
                           responders=self.responder_views())

    # ------------------------------------------------------------------ act
    def apply(self, decision: Decision) -> None:
        """Fly the decision's new segments (a segment leaving the area is refused: the
        vehicle holds instead) and note what it judged localised."""
        self._note(decision)
        for i, traj in decision.plans.items():
            if not self.plan_inside(traj, i):
                self.refused_plans += 1
                self._refused.add(i)
                self._segment[i] = self.stepper.hold(i)
                continue
            self._refused.discard(i)
            self._segment[i] = self.stepper.follow(i, traj)

    def plan_inside(self, traj: Trajectory, agent: int = 0) -> bool:
        """Does a segment, and the leg to it from where the autopilot is, stay inside?
        (From outside, e.g. after a turn swung wide, the segment from its first point
        inside on: what comes before brings the vehicle back in.)"""
        if tuple(traj.origin) != tuple(self.mission.origin):
            return False
        here = np.asarray(self.stepper.navigation_position_m(agent)[:2])[None, :]
        pts = np.concatenate((here, traj.enu_m[:, :2]))
        inside = self.mission.area.contains(pts, 0.0)  # point by point: one call for all
        if not inside[0]:  # outside: the segment from its first point inside on (the rest
            if not inside.any():  # comes back)
                return False
            first = int(np.argmax(inside))
            pts, inside = pts[first:], inside[first:]
        if self._convex:  # straight legs between inside points stay inside a convex area
            return bool(inside.all())
        return self.mission.area.path_inside(pts, 0.0)

    # ------------------------------------------------------------------ advance
    def advance(self, dt_s: float) -> list[list[Emitted]]:
        """Fly ``dt_s`` more (never past the budget); feed the estimator and the logs."""
        t_next = min(self.t_s + dt_s, self.mission.budget_s)
        out = self.stepper.step_to(t_next)
        self.t_s = self.stepper.t_s
        self._ingest(out)
        for i, a in enumerate(self.stepper.agents):
            p = tuple(a.vehicle._p)  # the true position (evaluation: path flown)
            self._path_m[i] += math.dist(p, self._last_pos[i])
            self._last_pos[i] = p
            self.nav_track[i].append((self.t_s, *self.stepper.navigation_position_m(i)))
        self._sample_series()
        return out

    def _ingest(self, out: list[list[Emitted]]) -> None:
        est = self.estimator
        self._estimates.clear()
        for i, (a, emitted) in enumerate(zip(self.stepper.agents, out, strict=True)):
            ordered = sorted(emitted, key=REPLAY_ORDER)
            est.push_many([e.record for e in ordered], i)
            # what the policy hears (the estimator does not read it): each ok range with
            # where the autopilot believed it was then
            ok = [e.record for e in ordered if isinstance(e.record, RangeSample) and e.record.ok]
            if ok:
                v = a.vehicle
                t = a.clock.to_s(np.array([r.t_ns for r in ok]))
                pos = v.position_at(t)
                if v.nav_error is not None:
                    pos = pos + v.nav_error(t)
                for r, t_s, p in zip(ok, t.tolist(), pos.tolist(), strict=True):
                    self._hear(r.bssid, t_s, p, r.range_m)
            if emitted:
                est.mark_time(i, emitted[-1].t_ns)
            if self.sinks:
                self.sinks[i].add(emitted, a.t_s)

    def finish(self) -> None:
        """End of the flight: deliver what is still on its way, close the logs."""
        if self.finished:
            return
        out = self.stepper.finish()
        self._ingest(out)
        self.estimator.finish()
        self._estimates.clear()
        for s in self.sinks:
            s.close()
        self._sample_series()
        self.finished = True

    # ------------------------------------------------------------------ outcome
    @property
    def path_length_m(self) -> float:
        return float(sum(self._path_m))

    def true_tracks(self) -> list[np.ndarray]:
        """The vehicles' true paths (evaluation: figures), every half second."""
        return [self.stepper.vehicle_track(i).enu_m[::10]
                for i in range(len(self.stepper.agents))]


@dataclass
class SearchResult:
    """The outcome of one search (the ``osa search`` report) and its evaluation series."""

    policy: str
    mode: str
    seed: object
    ended: str  # "localised" | "budget"
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
        return d


def drive(loop, policy: Policy, config: LoopConfig,
          progress: Callable[[float, str], None] | None = None,
          policy_rng: np.random.Generator | None = None) -> str:
    """Run ``policy`` on a started loop until it is done or the budget is spent; returns
    how it ended (``localised`` or ``budget``). The loop is not finished here."""
    rng = policy_rng if policy_rng is not None else np.random.default_rng(
        np.random.SeedSequence(loop.realisation.seed.entropy, spawn_key=(9,))
    )
    policy.reset(loop.mission, rng)
    budget = loop.mission.budget_s
    while loop.t_s < budget - 1e-9:
        d = policy.decide(loop.observe())
        loop.apply(d)
        if d.done:
            return "localised"
        loop.advance(config.decision_period_s)
        if progress is not None:
            progress(loop.t_s, loop.notes[-1][1] if loop.notes else "")
    d = policy.decide(loop.observe())  # the policy's last judgement at the budget
    for b in d.localised:
        loop.localised_at.setdefault(b, loop.t_s)
    return "budget"


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
    """Fly ``scenario`` with ``policy`` until it is done or the budget is spent."""
    loop = ClosedLoop(scenario, seed, config=config, log_paths=log_paths)
    ended = drive(loop, policy, config, progress, policy_rng)
    loop.finish()
    return result_of(loop, policy.name, ended)


def result_of(loop: SearchLoopBase, policy_name: str, ended: str) -> SearchResult:
    """The report of a finished search (the loop gives its own true tracks)."""
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
    )
