"""What a search policy sees and returns, and the one interface every policy implements.

One small interface serves the fixed patterns (:mod:`planner.coverage`), the adaptive
CasADi policy (:mod:`planner.adaptive`) and trained networks alike (``envs`` runs them
in the closed loop, over MAVLink, in Gymnasium)::

    policy.reset(mission, rng)          # a new search (the mission is what the operator knows)
    decision = policy.decide(obs)       # every few seconds: Observation -> Decision

An :class:`Observation` holds only what a real system has: the autopilot's position and
velocity estimate, the flight time and budget, and per responder heard so far what
the estimator says (status, position, covariance, counts) and where the drone was
when it heard it. Never the truth. A :class:`Decision` may carry a new path segment
(a :class:`Trajectory` in the mission's ENU frame; the vehicle flies it from where it
is), the set of responders the policy judges localised, and whether the search is
over.

"Localised" (:class:`LocalisedRule`) is judged from the estimator alone: status
``converged``, enough accepted ranges, and sigma_H below the target, or below an
acceptable bound once it has stopped shrinking (the information limit of the
geometry flown); :class:`LocalisedTracker` keeps that judgement per responder.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from estimator.records import Trajectory
from planner.area import SearchArea
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
    # the vehicle's along-track acceleration limit (the scenario's [vehicle], as PX4's
    # MPC_ACC_HOR): what braking before a reversal needs
    max_accel_mps2: float = 2.0


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

    @property
    def tracked(self) -> bool:
        """An estimate the estimator tracks (converged or tracking): one to plan about."""
        return self.mean_enu_m is not None and self.status in ("converged", "tracking")


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



# ----------------------------------------------------------------------------- localised


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



class LocalisedTracker:
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

