"""A team of independent copies of a one-UAV policy (``team:NAME``, docs/evaluate.md).

Every UAV of a multi-UAV mission runs its own copy of the policy, on its own view: the
mission as if it flew alone (``n_agents`` 1) and an observation whose only agent is
itself, with the estimates every agent's ranges feed (the loop's one fused estimator,
the paper's Networked OSA). The copies do not coordinate: that is the baseline a team
policy trained to share the work (``ppo:MODEL`` of ``osa train --env osa/Team-v0``)
has to beat. A UAV whose copy is done holds where it is; the team is done when every
copy is.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np

from planner.observation import Decision, Observation, Policy, SearchMission


class IndependentTeam:
    """``make()`` once per UAV (see the module docstring)."""

    def __init__(self, make: Callable[[], Policy], name: str) -> None:
        self.make = make
        self.name = name
        self.members: list[Policy] = []
        self.done: list[bool] = []

    def reset(self, mission: SearchMission, rng: np.random.Generator) -> None:
        n = mission.n_agents
        alone = dataclasses.replace(mission, n_agents=1)
        self.members = [self.make() for _ in range(n)]
        self.done = [False] * n
        self.localised: frozenset[str] = frozenset()
        for member, child in zip(self.members, rng.spawn(n), strict=True):
            member.reset(alone, child)

    def decide(self, obs: Observation) -> Decision:
        plans, replans, notes = {}, 0, []
        for i, member in enumerate(self.members):
            if self.done[i]:
                continue
            d = member.decide(dataclasses.replace(obs, agents=(obs.agents[i],)))
            self.localised |= d.localised
            replans += d.replans
            if d.note:
                notes.append(f"uav {i + 1}: {d.note}")
            if 0 in d.plans:
                plans[i] = d.plans[0]
            self.done[i] = d.done
        return Decision(plans=plans, localised=self.localised, done=all(self.done),
                        replans=replans, note="; ".join(notes))
