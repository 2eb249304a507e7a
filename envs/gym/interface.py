"""What the environments observe, how their actions become flights, and their reward.

One object per episode, shared by the Gymnasium envs and :class:`envs.gym.trained.
TrainedPolicy`, so a network trained in an env meets exactly the same observation and
action mapping when it flies ``osa search``: everything here is computed from a
:class:`planner.observation.Observation` (what the autopilot and the estimator say, never
the truth) and the :class:`planner.observation.SearchMission` (what the operator knows).

- :class:`Encoder`: the observation (a flat ``Dict`` of normalised float32 vectors:
  the vehicle, responder slots with a mask, a coarse coverage map), the estimator-only
  "localised" bookkeeping (:class:`planner.observation.LocalisedRule`) and the information
  potential behind the reward.
- :class:`ManoeuvreActions` (``osa/Search-v0``) and :class:`WaypointActions`
  (``osa/Waypoint-v0``): action -> :class:`planner.observation.Decision`;
  ``osa/Search-v1``'s :class:`envs.gym.plan_actions.PlanActions` (kind ``plan``) also
  adds observation keys of its own.

Reward of one decision (all terms from the estimator, the vehicle and the link model):
``information_weight * information + detection_bonus * newly detected + coverage_bonus *
newly covered share - time_cost_per_s * dt - leave_penalty * (leaving the area)``, where
information is the increase of
``sum_b 0.5 (log det P0 - log det P_b)`` over the detected responders b (P_b the
estimate's 3 x 3 position covariance, P0 the prior before any estimate): the reduction of
1/2 log det of the covariance, the D-optimal objective the CasADi planner maximises,
and the covered share is the mean of the coverage map over the area: what the search
has learnt before anything is heard (where the responder is not).
"""

from __future__ import annotations

import itertools
import math
import numbers
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TypeVar

import numpy as np
from gymnasium import spaces

from estimator.records import Trajectory
from planner.adaptive import AdaptiveConfig, Manoeuvres, band_floor_m
from planner.coverage import Sweep, search_spacing_m
from planner.observation import (
    AgentView,
    Decision,
    LocalisedRule,
    LocalisedTracker,
    Observation,
    ResponderView,
    SearchMission,
)

SLOT_FEATURES = (
    "present_estimate", "d_east", "d_north", "d_up", "log_sigma_h", "log_sigma_z",
    "status_none", "status_tracking", "status_converged", "status_diverged",
    "log_heard", "log_accepted", "localised", "heard_d_east", "heard_d_north",
    "age", "target",
)  # fmt: skip
AGENT_FEATURES = (
    "east", "north", "height", "v_east", "v_north", "v_up", "time", "time_left",
    "edge", "segment_done",
)  # fmt: skip
_TRACKING = ("tracking",)
_NONE = ("bootstrapping", "weak_geometry", "ambiguous", "no_data")
T = TypeVar("T")
_THIRDS = np.array([1 / 6, 1 / 2, 5 / 6])[:, None, None]  # three points along a step


# the reward weights of every env (osa train --reward, besides v1's localised_bonus)
REWARD_WEIGHTS = ("information_weight", "detection_bonus", "coverage_bonus",
                  "time_cost_per_s", "leave_penalty")


@dataclass(frozen=True, kw_only=True)
class EnvConfig:
    """The environments' settings (documented in docs/rl.md, Arguments)."""

    decision_period_s: float = 5.0  # flight between two actions
    max_responders: int = 3  # responder slots in the observation
    coverage_cells: int = 8  # the coverage map is cells x cells over the area's box
    information_weight: float = 1.0  # times the information gained (0: the term off)
    detection_bonus: float = 1.0  # per responder heard for the first time
    coverage_bonus: float = 5.0  # for covering the whole area once (the search map)
    time_cost_per_s: float = 0.01  # per second of flight
    leave_penalty: float = 1.0  # a segment refused / a waypoint outside the area
    prior_sigma_h_m: float = 100.0  # P0: the covariance "before any estimate"
    prior_sigma_z_m: float = 30.0
    cov_floor_m2: float = 0.01  # added to P before log det (keeps it finite)
    rule: LocalisedRule = field(default_factory=LocalisedRule)
    adaptive: AdaptiveConfig = field(default_factory=AdaptiveConfig)

    def __post_init__(self) -> None:
        if not (math.isfinite(self.decision_period_s) and 0.5 <= self.decision_period_s <= 600):
            raise ValueError("decision_period_s must be in [0.5, 600] s")
        for name, lo in (("max_responders", 1), ("coverage_cells", 2)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, numbers.Integral):
                raise ValueError(f"{name} must be an integer, not {v!r}")
            if not lo <= v <= 32:
                raise ValueError(f"{name} must be in [{lo}, 32]")
            object.__setattr__(self, name, int(v))
        # as osa train's --reward: a NaN weight made every reward NaN
        for name in REWARD_WEIGHTS:
            v = getattr(self, name)
            if (isinstance(v, bool) or not isinstance(v, numbers.Real)
                    or not (math.isfinite(v) and v >= 0)):
                raise ValueError(f"{name} must be a number >= 0, not {v!r}")

    def to_json(self) -> dict:
        """The settings a trained model needs to meet the same observation and actions."""
        return {k: getattr(self, k) for k in (
            "decision_period_s", "max_responders", "coverage_cells", "information_weight",
            "detection_bonus", "coverage_bonus",
            "time_cost_per_s", "leave_penalty", "prior_sigma_h_m", "prior_sigma_z_m",
            "cov_floor_m2")}


def half_logdet(cov: np.ndarray, floor_m2: float) -> float:
    """0.5 log det (P + floor I) of a 3 x 3 covariance."""
    sign, ld = np.linalg.slogdet(np.asarray(cov, dtype=float) + floor_m2 * np.eye(3))
    return 0.5 * float(ld) if sign > 0 else math.inf


def _heard_center(r: ResponderView) -> tuple[float, float]:
    """Where a responder was heard: the drone positions weighted by 1 / range^2."""
    h = np.asarray(r.heard_enu_m, dtype=float)
    w = 1.0 / np.maximum(np.asarray(r.heard_range_m, dtype=float), 5.0) ** 2
    cx, cy = (h[:, :2] * w[:, None]).sum(axis=0) / w.sum()
    return float(cx), float(cy)


class Encoder:
    """Observation vectors, coverage, localised bookkeeping and the information potential
    of one agent's episode (see the module docstring)."""

    def __init__(self, config: EnvConfig, n_others: int = 0) -> None:
        self.cfg = config
        self.n_others = n_others
        k, g = config.max_responders, config.coverage_cells
        f32 = np.float32
        sp = {
            "agent": spaces.Box(-4.0, 4.0, (len(AGENT_FEATURES),), f32),
            "responders": spaces.Box(-4.0, 4.0, (k * len(SLOT_FEATURES),), f32),
            "responder_mask": spaces.Box(0.0, 1.0, (k,), f32),
            "coverage": spaces.Box(0.0, 1.0, (g * g,), f32),
        }
        if n_others:
            sp["others"] = spaces.Box(-4.0, 4.0, (4 * n_others,), f32)
        self.space = spaces.Dict(sp)
        self._parts: list[tuple[str, int, int]] = []  # (key, start, end) in one vector
        for key, box in sp.items():
            start = self._parts[-1][2] if self._parts else 0
            self._parts.append((key, start, start + box.shape[0]))
        self._low = np.concatenate([b.low for b in sp.values()]).astype(float)
        self._high = np.concatenate([b.high for b in sp.values()]).astype(float)
        p0 = np.diag([config.prior_sigma_h_m**2, config.prior_sigma_h_m**2,
                      config.prior_sigma_z_m**2])
        self.prior_half_logdet = half_logdet(p0, config.cov_floor_m2)

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """The low and high of the observation as one vector (the keys in turn)."""
        return self._low, self._high

    # ------------------------------------------------------------------ episode
    def reset(self, mission: SearchMission, agent: int = 0) -> None:
        self.mission = mission
        self.agent = agent
        self.tracker = LocalisedTracker(self.cfg.rule)
        v = mission.area.vertices
        lo, hi = v.min(axis=0), v.max(axis=0)
        self.center = tuple((0.5 * (lo + hi)).tolist())
        self.half = max(float(np.max(hi - lo)) / 2.0, 1.0)
        g = self.cfg.coverage_cells
        edges_e = np.linspace(lo[0], hi[0], g + 1)
        edges_n = np.linspace(lo[1], hi[1], g + 1)
        ce, cn = np.meshgrid(0.5 * (edges_e[:-1] + edges_e[1:]),
                             0.5 * (edges_n[:-1] + edges_n[1:]))  # row = north index
        self.cells = np.column_stack([ce.ravel(), cn.ravel()])
        self.cell_ground = np.asarray(mission.terrain.height_m(self.cells[:, 0],
                                                               self.cells[:, 1]), dtype=float)
        self.cell_inside = mission.area.contains(self.cells)
        self._cell_e, self._cell_n = self.cells[:, 0][None], self.cells[:, 1][None]
        self._n_inside = int(self.cell_inside.sum())
        self._cell_outside = ~self.cell_inside
        self.log_miss = np.zeros(len(self.cells))  # log P(not heard | responder in cell)
        self.coverage = 1.0 - np.exp(self.log_miss)  # kept with log_miss: P(heard | cell)
        self._ground_at: tuple[object, float] | None = None  # (position, terrain height)
        self._memo: dict[tuple[str, str], tuple[object, object]] = {}  # see _kept
        self.rate_hz = float(getattr(mission.link, "ranging_rate_hz", 4.0))
        self.last_pos: np.ndarray | None = None
        self.last_t = 0.0
        self.detected: set[str] = set()
        self.information = 0.0
        self.covered_share = 0.0
        self.slots: list[str] = []  # bssids in order of detection
        self.target: str | None = None

    # ------------------------------------------------------------------ update
    def update(self, obs: Observation) -> dict:
        """Take a new observation: bookkeeping, coverage, information; returns the
        changes the reward needs (``information``: increase of the potential,
        ``detected``: responders heard for the first time)."""
        self.tracker.update(obs)
        self._cover([np.asarray(a.position_enu_m, dtype=float) for a in obs.agents], obs.t_s)
        new = [r.bssid for r in obs.responders if r.bssid not in self.detected]
        self.detected.update(new)
        for r in obs.responders:
            if r.bssid not in self.slots:
                self.slots.append(r.bssid)
        info = self.potential(obs)
        gain = info - self.information
        self.information = info
        covered = self.covered()
        more = covered - self.covered_share
        self.covered_share = covered
        return {"information": gain, "detected": len(new), "covered": more}

    def covered(self) -> float:
        """The share of the area where a responder would have been heard by now (the
        mean coverage of the cells inside the area)."""
        if not self._n_inside:
            return 0.0
        return float(self.coverage[self.cell_inside].sum()) / self._n_inside  # np.mean's

    def potential(self, obs: Observation) -> float:
        """sum over detected responders of 0.5 (log det P0 - log det P)."""
        total = 0.0
        for r in obs.responders:
            if r.cov_m2 is not None:
                h = self._kept("logdet", r.bssid, r.cov_m2,
                               lambda r=r: half_logdet(r.cov_m2, self.cfg.cov_floor_m2))
                if math.isfinite(h):  # a covariance that is not positive definite: no gain
                    total += self.prior_half_logdet - h
        return total

    def _cover(self, positions: list[np.ndarray], t_s: float) -> None:
        """Coverage: the chance that a responder in each cell would have been heard (by
        any agent: they share one estimator)."""
        pos = np.asarray(positions, dtype=float)  # (agents, 3)
        if self.last_pos is None:
            self.last_pos, self.last_t = pos, t_s
            return
        dt = t_s - self.last_t
        if dt > 0:
            p = (self.last_pos[None] + _THIRDS * (pos - self.last_pos)[None]).reshape(-1, 3)
            d = np.sqrt((self._cell_e - p[:, 0:1]) ** 2 + (self._cell_n - p[:, 1:2]) ** 2
                        + (p[:, 2:3] - self.cell_ground) ** 2)
            q = np.clip(np.asarray(self.mission.link.response_probability(d), dtype=float),
                        0.0, 0.999)
            self.log_miss += self.rate_hz * dt / 3.0 * np.log1p(-q).sum(axis=0)
            self.coverage = 1.0 - np.exp(self.log_miss)
        self.last_pos, self.last_t = pos, t_s

    # ------------------------------------------------------------------ encode
    def done(self, obs: Observation) -> bool:
        """Every detected responder localised (estimator judgement), at least one, and as
        many as the mission expects when it says."""
        loc = self.tracker.localised
        heard = {r.bssid for r in obs.responders}
        if not heard or not heard <= set(loc):
            return False
        n = self.mission.expected_responders
        return n is None or len(loc) >= n

    def _kept(self, kind: str, bssid: str, inputs: object, value: Callable[[], T]) -> T:
        """``value()`` of a responder, kept while its ``inputs`` stay equal (a responder's
        estimate and heard positions change only when new ranges arrive)."""
        got = self._memo.get((kind, bssid))
        if got is None or got[0] != inputs:
            got = self._memo[(kind, bssid)] = (inputs, value())
        return got[1]

    def ground_m(self, position: tuple[float, float, float]) -> float:
        """Terrain height under an agent's reported ``position_enu_m`` (kept for the same
        position object: the encoder and the actions ask it of one observation)."""
        if self._ground_at is None or self._ground_at[0] is not position:
            h = self.mission.terrain.height_m(float(position[0]), float(position[1]))
            self._ground_at = (position, float(np.asarray(h)))
        return self._ground_at[1]

    def encode(self, obs: Observation, others: tuple[AgentView, ...] = ()) -> dict:
        """The observation: one clipped float32 vector, a view of it per space key."""
        m, c = self.mission, self.cfg
        a = obs.agents[self.agent]
        pos = np.asarray(a.position_enu_m, dtype=float)
        e, n, z = pos.tolist()
        ce, cn = self.center
        half, speed = self.half, m.speed_mps
        sd = float(m.area.signed_distance_m(pos[None, :2])[0])
        ve, vn, vu = (float(v) / speed for v in a.velocity_enu_mps)
        buf = np.zeros(self._high.shape[0])
        (_, _, na), (_, _, nr), (_, _, nm), (_, _, ng), *_ = self._parts
        agl = z - self.ground_m(a.position_enu_m)
        buf[:na] = [(e - ce) / half, (n - cn) / half, agl / m.height_m - 1.0, ve, vn, vu,
                    obs.t_s / obs.budget_s, obs.time_left_s / obs.budget_s, -sd / half,
                    float(a.segment_done)]
        views = {r.bssid: r for r in obs.responders}
        slots = buf[na:nr].reshape(c.max_responders, len(SLOT_FEATURES))
        for i, b in enumerate(self.slots[: c.max_responders]):
            buf[nr + i] = 1.0
            self._slot(slots[i], views[b], pos, obs)
        cov = buf[nm:ng]
        cov[:] = self.coverage
        cov[self._cell_outside] = 1.0
        if self.n_others:
            rows = buf[ng:].reshape(self.n_others, 4)
            for j, o in enumerate(others[: self.n_others]):
                rows[j] = [(o.position_enu_m[0] - pos[0]) / half,
                           (o.position_enu_m[1] - pos[1]) / half,
                           o.velocity_enu_mps[0] / speed, o.velocity_enu_mps[1] / speed]
        out = np.clip(buf, self._low, self._high, out=buf).astype(np.float32)
        return {key: out[lo:hi] for key, lo, hi in self._parts}

    def _slot(self, s: np.ndarray, r: ResponderView, pos: np.ndarray, obs: Observation
              ) -> None:
        """Fill one responder slot ``s`` (zeros, :data:`SLOT_FEATURES`)."""
        m = self.mission
        if r.mean_enu_m is not None and r.cov_m2 is not None:
            s[0] = 1.0
            s[1] = (r.mean_enu_m[0] - pos[0]) / self.half
            s[2] = (r.mean_enu_m[1] - pos[1]) / self.half
            s[3] = (r.mean_enu_m[2] - pos[2]) / m.height_m
            s[4] = math.log10(max(r.sigma_h_m or 1e-2, 1e-2)) / 2.0
            cz = float(r.cov_m2[2][2])
            s[5] = math.log10(max(math.sqrt(max(cz, 0.0)), 1e-2)) / 2.0
        else:
            s[4] = s[5] = 2.0  # no estimate: as if sigma were 10 km
        st = r.status
        s[6 + (1 if st in _TRACKING else 2 if st == "converged" else 0 if st in _NONE else 3)] = 1
        s[10] = math.log1p(r.n_heard) / math.log(1000.0)
        s[11] = math.log1p(r.n_acc) / math.log(1000.0)
        s[12] = float(r.bssid in self.tracker.localised)
        if r.heard_enu_m:
            cx, cy = self._kept("heard", r.bssid, (r.heard_enu_m, r.heard_range_m),
                                lambda: _heard_center(r))
            s[13] = (cx - pos[0]) / self.half
            s[14] = (cy - pos[1]) / self.half
        s[15] = (obs.t_s - r.detected_at_s) / obs.budget_s
        s[16] = float(r.bssid == self.target)


# ----------------------------------------------------------------------------- actions


MANOEUVRES = ("sweep", "orbit-near", "orbit-far", "helix", "close-pass", "next-responder",
              "return")


def responder_manoeuvre(man, adaptive, name: str, target: str, obs: Observation,
                        a: AgentView, goto_note: str):
    """The path segment of a manoeuvre about responder ``target`` (the adaptive policy's
    own building blocks, ``man``: :class:`planner.adaptive.Manoeuvres`): about its
    estimate once the estimator tracks it, else about where it was heard. ``name`` is
    ``orbit-near``, ``orbit-far``, ``helix``, ``close-pass``; anything else flies to it
    (noted ``goto_note``)."""
    r = next(v for v in obs.responders if v.bssid == target)
    est = r.tracked
    center = r.mean_enu_m[:2] if est else man.heard_center(r)[0]
    if name == "orbit-near":
        return man.orbit(center, adaptive.probe_radius_m[0], a)
    if name == "orbit-far":
        return man.orbit(center, adaptive.probe_radius_m[1], a)
    if name == "helix":
        return man.close_helix(r, a) if est else man.probe(r, a)
    if name == "close-pass":
        return man.close_pass(center, r.cov_m2 if est else None, a)
    return man.goto(center, a, goto_note)


def discrete_action(action, n: int) -> int:
    """The index of a ``Discrete(n)`` action (an integer, NumPy's integer or a one-value
    array of one); anything else, e.g. -1, ``n``, 2.5, ``"1"`` or NaN, is a
    ``ValueError`` (not another action flown)."""
    a = np.asarray(action) if not isinstance(action, str) else None
    if a is not None and a.size == 1 and a.dtype.kind in "biuf":
        v = a.item()
        if math.isfinite(v) and float(v).is_integer() and 0 <= v < n:
            return int(v)
    raise ValueError(f"action {action!r} is not one of Discrete({n})'s: an integer "
                     f"from 0 to {n - 1}")


def waypoint_action(action) -> tuple[float, float, float]:
    """A ``Box(-1, 1, (3,))`` waypoint action clipped to the bounds (inf too); not three
    numbers, or a NaN among them, is a ``ValueError`` (not a waypoint flown)."""
    try:
        a = np.asarray(action, dtype=float)
    except (TypeError, ValueError):
        a = None
    if a is None or a.size != 3 or np.isnan(a).any():
        raise ValueError(f"action {action!r} is not a waypoint: three numbers (east, "
                         "north, up) in [-1, 1], none NaN")
    ax, ay, az = (min(max(v, -1.0), 1.0) for v in a.reshape(3).tolist())
    return ax, ay, az


class ManoeuvreActions:
    """``osa/Search-v0``: a choice of manoeuvre per decision (:data:`MANOEUVRES`).

    - ``sweep``: continue the search sweep (the lawnmower, resumed where it was left);
    - ``orbit-near`` / ``orbit-far``: a level orbit of the target's estimate at the
      probe radii (25 / 60 m), or of where it was heard while there is no estimate;
    - ``helix``: the close helix about the estimate (18 m, through the altitude band),
      or the climbing probe helix while there is no estimate;
    - ``close-pass``: a straight pass over the estimate along its least known axis;
    - ``next-responder``: make the next detected responder not yet localised the
      target and fly to it;
    - ``return``: fly back to the take-off point and hold there.

    The target is the responder the manoeuvres are about: the most recently detected one
    not yet localised, until ``next-responder`` changes it. Without a target (nothing
    heard, or everything heard localised) every action continues the sweep. Choosing the
    manoeuvre being flown again keeps flying it until its segment is done, then starts
    it anew about the current estimate.
    """

    def __init__(self, config: EnvConfig) -> None:
        self.cfg = config
        self.space = spaces.Discrete(len(MANOEUVRES))

    def reset(self, mission: SearchMission, encoder: Encoder) -> None:
        self.mission = mission
        self.enc = encoder
        self.man = Manoeuvres(mission, self.cfg.adaptive)
        self.sweep = Sweep(mission, search_spacing_m(mission, self.cfg.adaptive.detect_probability))
        self.current: tuple[str, str | None] | None = None  # (manoeuvre, target)
        self.refused = 0

    def _pick_target(self, obs: Observation) -> None:
        loc = self.enc.tracker.localised
        views = {r.bssid: r for r in obs.responders}
        t = self.enc.target
        if t is not None and t not in loc and t in views:
            return
        pending = [r for r in obs.responders if r.bssid not in loc]
        self.enc.target = max(pending, key=lambda r: r.detected_at_s).bssid if pending else None

    def decide(self, action, obs: Observation) -> Decision:
        name = MANOEUVRES[discrete_action(action, len(MANOEUVRES))]
        loc = self.enc.tracker.frozen()
        a = obs.agents[self.enc.agent]
        self._pick_target(obs)
        if name == "next-responder":
            loc_set = self.enc.tracker.localised
            pending = [r.bssid for r in obs.responders if r.bssid not in loc_set]
            if pending:
                i = pending.index(self.enc.target) if self.enc.target in pending else -1
                self.enc.target = pending[(i + 1) % len(pending)]
        target = self.enc.target
        if target is None:  # nothing to manoeuvre about (and nothing to return with)
            name = "sweep"
        key = (name, target if name != "sweep" else None)
        if name == "sweep":
            if self.current == key and not a.segment_done:
                self.sweep.advance(a.position_enu_m[:2])
                return Decision(localised=loc)
            if self.current == key:  # the segment is flown: mark its end, reverse if over
                self.sweep.advance(a.position_enu_m[:2])
                if self.sweep.at_end:
                    self.sweep.reverse()
            self.current = key
            return Decision(plans={self.enc.agent: self.sweep.resume(a.position_enu_m[:2])},
                            localised=loc, note="sweep")
        if self.current == key and not a.segment_done:
            return Decision(localised=loc)
        self.current = key
        traj = self._build(name, target, obs, a)
        return Decision(plans={self.enc.agent: traj}, localised=loc, note=f"{name} {target}")

    def _build(self, name: str, target: str | None, obs: Observation, a: AgentView):
        if name == "return":
            return self.man.goto(self.mission.start_enu_m, a, "return")
        return responder_manoeuvre(self.man, self.cfg.adaptive, name, target, obs, a,
                                   "next-responder")


class WaypointActions:
    """``osa/Waypoint-v0``: ``Box(-1, 1, (3,))``, the next waypoint relative to the
    vehicle: east and north times the reach of one decision (speed x period), height
    above the terrain changed by up to ``climb_m`` within the altitude band (the
    adaptive policy's: 20 m below to 25 m above the search height, at least 10 m, and
    not below the search height when a keep-out is flown over).
    A waypoint beyond the *inset* (the area's margin plus the braking distance at cruise
    speed, ``speed^2 / (2 max_accel_mps2)`` of the mission's vehicle: 26 m at 8 m/s and
    2 m/s^2; at most half the depth of the area's deepest point, at least the margin) is
    moved to the nearest point inside it (so the vehicle slides along the edge instead of
    stopping there); such a request costs ``leave_penalty`` times the share of the reach
    it lies outside. The vehicle flies to it at cruise speed and on along the same line
    (so it does not brake at each waypoint), routed inside a concave area. A request
    shorter than 1 m holds. The braking room is what a reversal at the inset needs: the
    autopilot turns back on a U-turn of either hand, and with the margin alone (and a
    standalone GNSS's bias) the true path went up to 2.5 m outside the area.
    """

    climb_m = 10.0

    def __init__(self, config: EnvConfig, speed_mps: float | None = None,
                 ground: bool = False) -> None:
        self.cfg = config
        self.space = spaces.Box(-1.0, 1.0, (3,), np.float32)
        self.speed_override = speed_mps
        self.ground = ground

    def reset(self, mission: SearchMission, encoder: Encoder) -> None:
        self.mission = mission
        self.enc = encoder
        self.speed = self.speed_override or mission.speed_mps
        band = self.cfg.adaptive.agl_band_m
        self.band = (band_floor_m(mission, band[0]), mission.height_m + band[1])
        self.penalty = 0.0  # of the last decision: share of the reach outside the inset
        area = mission.area
        # waypoints keep the braking distance at cruise speed inside the margin
        lo, hi = area.vertices.min(axis=0), area.vertices.max(axis=0)
        grid = np.stack(np.meshgrid(*np.linspace(lo, hi, 17).T), -1).reshape(-1, 2)
        depth = -float(area.signed_distance_m(grid).min())  # about the deepest point's
        self.inset_m = max(area.margin_m, min(
            area.margin_m + self.speed**2 / (2.0 * mission.max_accel_mps2), 0.5 * depth))
        hp = area.halfplanes  # inside the inset: n . q - c >= inset on every edge
        self.halfplanes = None if hp is None else (hp[0], hp[1] + self.inset_m)

    def _inside(self, p: np.ndarray) -> np.ndarray:
        """The point of the area inset by ``inset_m`` nearest to ``p`` (a convex area:
        projections onto the violated edges; exact for a box, close otherwise)."""
        nrm, c = self.halfplanes
        q = np.asarray(p, dtype=float).copy()
        for _ in range(2 * len(c)):
            g = nrm @ q - c
            i = int(np.argmin(g))
            if g[i] >= -1e-9:
                break
            q = q - g[i] * nrm[i]
        return q

    def decide(self, action, obs: Observation) -> Decision:
        ax, ay, az = waypoint_action(action)
        m = self.mission
        area = m.area
        loc = self.enc.tracker.frozen()
        a = obs.agents[self.enc.agent]
        here = np.asarray(a.position_enu_m, dtype=float)
        he, hn, hz = here.tolist()
        here = here[:2]
        reach = self.speed * self.cfg.decision_period_s
        want = np.array([he + reach * ax, hn + reach * ay])
        if self.halfplanes is not None:  # convex: the nearest point inside the inset
            wp = self._inside(want)
        else:
            wp = np.asarray(area.pull_inside(want, self.inset_m), dtype=float)
        self.penalty = min(1.0, _norm(want - wp) / reach)
        if self.ground:
            agl = 0.0
        else:
            lo, hi = self.band
            agl = min(max(hz - self.enc.ground_m(a.position_enu_m) + self.climb_m * az, lo), hi)
        i = self.enc.agent
        if _norm(wp - here) < 1.0:
            pts = [(he, hn)]
        elif self.halfplanes is not None:  # on along the same line, up to the inset
            on = self._inside(2.0 * wp - here)
            pts = [(he, hn), tuple(wp.tolist())]
            if _norm(on - wp) > 1.0:
                pts.append(tuple(on.tolist()))
        else:
            pts = area.route(here, wp)
            on = wp + (wp - np.asarray(pts[-2], dtype=float))
            if area.path_inside(np.array([wp, on]), self.inset_m, step_m=5.0):
                pts = [*pts, (float(on[0]), float(on[1]))]
        if len(pts) == 1:
            t, kept = [0.0, self.cfg.decision_period_s], pts * 2
        else:  # the legs' lengths and times as NumPy's norm and cumsum give them
            t, kept, elapsed = [0.0], [pts[0]], 0.0
            for (x0, y0), (x1, y1) in itertools.pairwise(pts):
                dx, dy = x1 - x0, y1 - y0
                seg = math.sqrt(dx * dx + dy * dy)
                elapsed += seg / self.speed
                if seg > 1e-6:
                    t.append(elapsed)
                    kept.append((x1, y1))
        enu = np.array([(x, y, agl) for x, y in kept], dtype=float)
        traj = Trajectory(np.array(t), enu, m.origin, "terrain", "waypoint")
        return Decision(plans={i: traj}, localised=loc)


# the action kinds of osa/Search-v1, v2 and v3: PlanActions' options of each
PLAN_KINDS: dict[str, dict[str, bool]] = {
    "plan": {}, "plan-v2": {"planned": True}, "plan-v3": {"planned": True, "shrink": True},
}


def _norm(v: np.ndarray) -> float:
    """``np.linalg.norm`` of a vector (its square root of ``v . v``), without its checks."""
    return math.sqrt(v.dot(v))


class Pilot:
    """One agent's observation and action mapping (``kind`` "search" or "waypoint"): what
    an env wraps around the closed loop and a trained policy around its network."""

    def __init__(self, kind: str, config: EnvConfig = EnvConfig(), *, n_others: int = 0,
                 speed_mps: float | None = None, ground: bool = False,
                 actions: object | None = None) -> None:
        if kind not in ("search", "waypoint", *PLAN_KINDS):
            raise ValueError(f"unknown action kind {kind!r} (search, waypoint, "
                             f"{', '.join(PLAN_KINDS)})")
        self.kind = kind
        self.cfg = config
        self.encoder = Encoder(config, n_others)
        if actions is not None:  # an action mapping object (e.g. PlanActions(sectors=4))
            self.actions = actions
        elif kind in PLAN_KINDS:  # osa/Search-v1, v2, v3
            from envs.gym.plan_actions import PlanActions

            self.actions = PlanActions(config, **PLAN_KINDS[kind])
        else:
            self.actions = (ManoeuvreActions(config) if kind == "search"
                            else WaypointActions(config, speed_mps, ground))
        # an action mapping may add observation keys of its own (PlanActions.obs_space)
        self._extra = getattr(self.actions, "obs_space", None)
        self.observation_space = (spaces.Dict({**self.encoder.space.spaces, **self._extra})
                                  if self._extra else self.encoder.space)
        self.action_space = self.actions.space

    def reset(self, mission: SearchMission, agent: int = 0) -> None:
        self.encoder.reset(mission, agent)
        self.actions.reset(mission, self.encoder)

    def observe(self, obs: Observation, others: tuple[AgentView, ...] = ()
                ) -> tuple[dict, dict]:
        """(encoded observation, reward changes) of a new observation; call once each."""
        changes = self.encoder.update(obs)
        enc = self.encoder.encode(obs, others)
        if self._extra:
            enc.update(self.actions.observe(obs))
        return enc, changes

    def act(self, action, obs: Observation) -> Decision:
        return self.actions.decide(action, obs)

    def done(self, obs: Observation) -> bool:
        return self.encoder.done(obs)

    @property
    def localised(self) -> frozenset[str]:
        return self.encoder.tracker.frozen()

    def area_penalty(self) -> float:
        """Share of the last waypoint request outside the inset (waypoint actions)."""
        return float(getattr(self.actions, "penalty", 0.0))
