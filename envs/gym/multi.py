"""A PettingZoo ``ParallelEnv``: several agents searching together, one fused estimate.

The paper's Networked OSA (left there as future work): N UAVs, optionally walking
first responders with a phone (ground agents), fly in one world; the online estimator
fuses every agent's ranges into one estimate per responder, so what one agent hears
helps all. Each agent sets its next waypoint as in ``osa/Waypoint-v0``.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import ClassVar

import numpy as np
from gymnasium import spaces
from gymnasium.utils import seeding
from pettingzoo import ParallelEnv

from envs.gym.base import (
    DEFAULT_SCENARIO,
    draw_world_seed,
    env_settings,
    loop_eval,
    outside_area,
    warn_unobserved,
)
from envs.gym.interface import EnvConfig, Pilot
from envs.loop import DEFAULT_MODE, ClosedLoop
from planner.observation import Decision
from sim.scenario import AgentSpec, Scenario, check_randomised_wind, search_scenario
from sim.vehicle import WALKER


def with_agents(scenario: Scenario, uavs: int, ground: int = 0) -> Scenario:
    """The one-agent search ``scenario`` with ``uavs`` UAVs (side by side, 30 m apart
    eastwards from its take-off point) and ``ground`` walking agents (from the take-off
    point), each with the scenario's GNSS receiver."""
    if uavs < 1 or ground < 0:
        raise ValueError("at least one UAV, and no negative number of ground agents")
    s = scenario.search
    assert s is not None
    specs = []
    for i in range(uavs):
        specs.append(AgentSpec(name=f"uav-{i + 1}", vehicle=scenario.vehicle, gnss=scenario.gnss,
                               start_e_m=s.start_e_m + 30.0 * i, start_n_m=s.start_n_m))
    for i in range(ground):
        specs.append(AgentSpec(name=f"walker-{i + 1}", kind="ground", vehicle=WALKER,
                               gnss=scenario.gnss, start_e_m=s.start_e_m,
                               start_n_m=s.start_n_m))
    out = dataclasses.replace(scenario, agents_=tuple(specs))
    check_randomised_wind(out)  # a walker's 1.4 m/s under the scenario's [randomise] wind
    return out


def agent_roles(scenario: Scenario) -> list[dict]:
    """What a pilot needs of each agent (and a trained team model records):
    ``name``, ``ground`` and, for a ground agent, its walking ``speed_mps``."""
    return [{"name": a.name, "ground": a.kind == "ground",
             "speed_mps": a.vehicle.max_speed_mps if a.kind == "ground" else None}
            for a in scenario.agents]


def team_pilots(roles: list[dict], config: EnvConfig) -> list[Pilot]:
    """One waypoint :class:`Pilot` per agent, each seeing the ``others``: the env's and
    a trained team policy's (one definition)."""
    n = len(roles)
    return [Pilot("waypoint", config, n_others=n - 1, speed_mps=r["speed_mps"],
                  ground=r["ground"]) for r in roles]


class SearchParallelEnv(ParallelEnv):
    """N agents (UAVs, optionally ground agents) sharing one fused estimate.

    Per agent: the action of ``osa/Waypoint-v0`` (``Box(-1, 1, (3,))``, the next
    waypoint; a ground agent walks at its own speed and ignores the height), and its
    observation (``agent``, ``responders``, ``responder_mask``, ``coverage``, the
    coverage and the estimates shared by all) plus ``others``: every other agent's
    position relative to it and velocity. Rewards: the team's information gained,
    detection bonus and coverage (one map for all), shared by all agents, minus each
    agent's own time and area terms. Every agent terminates when every detected
    responder is localised (the estimator's judgement); all are truncated at the budget.

    ``scenario`` with one agent gets ``uavs`` UAVs and ``ground`` ground agents
    (:func:`with_agents`); a scenario with ``[[agents]]`` keeps its own. Other
    arguments as ``osa/Waypoint-v0``.
    """

    metadata: ClassVar[dict] = {"render_modes": ["rgb_array"], "name": "osa_search_parallel_v0",
                                "is_parallelizable": True, "render_fps": 4}

    def __init__(
        self,
        scenario: str | Path | Scenario = DEFAULT_SCENARIO,
        *,
        uavs: int = 2,
        ground: int = 0,
        render_mode: str | None = None,
        seed_split: str = "train",
        decision_period_s: float = 5.0,
        max_responders: int = 3,
        coverage_cells: int = 8,
        information_weight: float = 1.0,
        detection_bonus: float = 1.0,
        coverage_bonus: float = 5.0,
        time_cost_per_s: float = 0.01,
        leave_penalty: float = 1.0,
        mode: str = DEFAULT_MODE,
    ) -> None:
        self.config, self.loop_config = env_settings(
            render_mode, self.metadata["render_modes"], seed_split, mode,
            decision_period_s=decision_period_s, max_responders=max_responders,
            coverage_cells=coverage_cells, information_weight=information_weight,
            detection_bonus=detection_bonus,
            coverage_bonus=coverage_bonus, time_cost_per_s=time_cost_per_s,
            leave_penalty=leave_penalty)
        sc = search_scenario(scenario)
        warn_unobserved(sc, max_responders)
        if len(sc.agents) == 1:
            sc = with_agents(sc, uavs, ground)
        self.scenario = sc
        self.render_mode = render_mode
        self.seed_split = seed_split
        self.possible_agents = [a.name for a in sc.agents]
        self.roles = agent_roles(sc)
        self.pilots = dict(zip(self.possible_agents, team_pilots(self.roles, self.config),
                               strict=True))
        self.agents: list[str] = []
        self.loop: ClosedLoop | None = None
        self.world_seed: int | None = None
        self.np_random, _ = seeding.np_random(None)
        # state(): every agent's observation vector in turn (the encoder's order)
        bounds = [p.encoder.bounds for p in self.pilots.values()]
        self.state_space = spaces.Box(np.concatenate([lo for lo, _ in bounds]).astype(np.float32),
                                      np.concatenate([hi for _, hi in bounds]).astype(np.float32),
                                      dtype=np.float32)

    def observation_space(self, agent: str):  # the same object every call
        return self.pilots[agent].observation_space

    def action_space(self, agent: str):
        return self.pilots[agent].action_space

    # ------------------------------------------------------------------ API
    def reset(self, seed: int | None = None, options: dict | None = None):
        if seed is not None or self.loop is None:
            self.np_random, _ = seeding.np_random(seed)
        self.world_seed = draw_world_seed(options, self.np_random, self.seed_split)
        self.loop = ClosedLoop(self.scenario, self.world_seed, config=self.loop_config)
        self.agents = list(self.possible_agents)
        for i, name in enumerate(self.possible_agents):
            self.pilots[name].reset(self.loop.mission, agent=i)
        self._obs = self.loop.observe()
        obs, _ = self._observe_all()
        return obs, {a: self._info() for a in self.agents}

    def _others(self, i: int) -> tuple:
        """Every agent's view but agent ``i``'s (its ``others`` observation)."""
        return tuple(v for j, v in enumerate(self._obs.agents) if j != i)

    def _observe_all(self) -> tuple[dict, dict]:
        obs, changes = {}, {}
        for i, name in enumerate(self.possible_agents):
            obs[name], changes[name] = self.pilots[name].observe(self._obs, self._others(i))
        return obs, changes

    def step(self, actions: dict):
        if self.loop is None:
            raise RuntimeError("call reset() before step()")
        unknown = [a for a in actions if a not in self.possible_agents]
        if unknown:  # a typo would otherwise fly on silently
            raise ValueError(f"no agent {unknown[0]!r} in this team "
                             f"({', '.join(self.possible_agents)})")
        loop = self.loop
        t0 = loop.t_s
        plans = {}
        for name in self.possible_agents:
            if name in actions:
                plans.update(self.pilots[name].act(actions[name], self._obs).plans)
        loop.apply(Decision(plans=plans, localised=self.pilots[self.possible_agents[0]].localised))
        refused = {i for i in plans if loop.refused(i)}  # plans the loop refused (outside)
        loop.advance(self.config.decision_period_s)
        self._obs = loop.observe()
        obs, changes = self._observe_all()
        c = self.config
        first = changes[self.possible_agents[0]]  # the team's: one shared estimate
        team = (c.information_weight * first["information"] + c.detection_bonus * first["detected"]
                + c.coverage_bonus * first["covered"])
        dt = loop.t_s - t0
        rewards = {}
        for i, name in enumerate(self.possible_agents):
            outside = outside_area(loop, self._obs, i)
            own = -c.time_cost_per_s * dt - c.leave_penalty * (
                (i in refused) + outside
                + (self.pilots[name].area_penalty() if name in actions else 0.0))
            rewards[name] = float(team + own)
        done = self.pilots[self.possible_agents[0]].done(self._obs)
        out_of_time = not done and loop.budget_spent
        terms = {a: done for a in self.agents}
        truncs = {a: out_of_time for a in self.agents}
        infos = {a: self._info() for a in self.agents}
        obs = {a: obs[a] for a in self.agents}
        rewards = {a: rewards[a] for a in self.agents}
        if done or out_of_time:
            self.agents = []
        return obs, rewards, terms, truncs, infos

    def _info(self) -> dict:
        loop = self.loop
        assert loop is not None
        return {"flight_time_s": float(loop.t_s), "world_seed": self.world_seed,
                "eval": loop_eval(loop)}

    def state(self) -> np.ndarray:
        """Every agent's observation, concatenated (for centralised critics)."""
        if self.loop is None:
            raise RuntimeError("call reset() before state()")
        return np.concatenate([
            np.concatenate(list(self.pilots[name].encoder.encode(self._obs,
                                                                 self._others(i)).values()))
            for i, name in enumerate(self.possible_agents)])

    def render(self):
        if self.render_mode != "rgb_array" or self.loop is None:
            return None
        from envs.gym.render import map_image

        return map_image(self.loop, self.pilots[self.possible_agents[0]])

    def close(self) -> None:
        pass
