"""Policies by name, for the CLI and the evaluation harness (strings live at the edges).

``lawnmower``, ``expanding-square`` and ``adaptive`` are the planner's policies
(:mod:`planner.policy`); ``random`` (``random:search``) and ``random:waypoint`` are
:class:`RandomPolicy`, uniform actions of ``osa/Search-v0`` and ``osa/Waypoint-v0``
(the floors of a comparison); ``ppo:PATH`` loads a policy trained by ``osa train`` (one
UAV, or a whole team when trained in ``osa/Team-v0``); ``team:NAME`` flies every UAV of
a multi-UAV scenario with its own copy of the one-UAV policy ``NAME``
(:class:`planner.team.IndependentTeam`).
"""

from __future__ import annotations

import functools

import numpy as np
from gymnasium import spaces

from planner.observation import Decision, Observation, SearchMission
from planner.policy import POLICIES, Policy, make_policy
from planner.team import IndependentTeam
from sim.scenario import Scenario

RANDOM = "random"


def uniform_action(space: spaces.Space, rng: np.random.Generator):
    """One action drawn uniformly from ``space`` with ``rng`` (Discrete, MultiDiscrete,
    MultiBinary, bounded Box, and Dict / Tuple of those)."""
    if isinstance(space, spaces.Discrete):
        return int(space.start + rng.integers(int(space.n)))
    if isinstance(space, spaces.MultiDiscrete):
        return (space.start + rng.integers(space.nvec)).astype(space.dtype)
    if isinstance(space, spaces.MultiBinary):
        return rng.integers(0, 2, space.shape).astype(space.dtype)
    if isinstance(space, spaces.Box):
        if not (np.all(np.isfinite(space.low)) and np.all(np.isfinite(space.high))):
            raise ValueError("a uniform action needs a bounded Box")
        return rng.uniform(space.low, space.high).astype(space.dtype)
    if isinstance(space, spaces.Dict):
        return {k: uniform_action(s, rng) for k, s in space.spaces.items()}
    if isinstance(space, spaces.Tuple):
        return tuple(uniform_action(s, rng) for s in space.spaces)
    raise ValueError(f"no uniform draw from a {type(space).__name__} space")


class RandomPolicy:
    """The floor: every decision, every UAV takes a uniformly random action of an env's
    action space through that env's own action mapping (:class:`envs.gym.interface.
    Pilot`; ``kind`` "search": ``osa/Search-v0``, the policy ``random``; "waypoint":
    ``osa/Waypoint-v0``, ``random:waypoint``), drawn from the episode's Generator
    (``reset``'s ``rng``), so the same seed flies the same search. Like a trained policy
    it ends the search when its encoder judges every responder localised."""

    def __init__(self, kind: str = "search") -> None:
        from envs.gym.interface import Pilot

        Pilot(kind)  # an unknown kind is a ValueError now, not at the first flight
        self.kind = kind
        self.name = RANDOM if kind == "search" else f"{RANDOM}:{kind}"

    def reset(self, mission: SearchMission, rng: np.random.Generator) -> None:
        from envs.gym.interface import Pilot

        self.rng = rng
        self.pilots = []
        for i in range(mission.n_agents):
            pilot = Pilot(self.kind)
            pilot.reset(mission, i)
            self.pilots.append(pilot)

    def decide(self, obs: Observation) -> Decision:
        for p in self.pilots:
            p.observe(obs)
        lead = self.pilots[0]
        if lead.done(obs):
            return Decision(localised=lead.localised, done=True,
                            note="every detected responder localised")
        plans: dict = {}
        notes = []
        for p in self.pilots:
            d = p.act(uniform_action(p.action_space, self.rng), obs)
            plans.update(d.plans)
            if d.note:
                notes.append(d.note)
        return Decision(plans=plans, localised=lead.localised, note="; ".join(notes))


def policy_names() -> tuple[str, ...]:
    """The named policies (``ppo:PATH`` besides)."""
    return (*POLICIES, RANDOM)


def load_policy(spec: str, scenario: Scenario | None = None) -> Policy:
    """The policy named ``spec`` (raises ValueError with the choices otherwise)."""
    if spec.startswith("team:"):
        inner = spec[len("team:"):]
        if inner.startswith("team:"):
            raise ValueError(f"{spec}: a team of teams")
        one = load_policy(inner)  # the error now, not in the first episode
        if getattr(one, "team_size", 1) != 1:
            raise ValueError(f"{spec}: {inner} is a team policy, not a one-UAV policy")
        return IndependentTeam(functools.partial(load_policy, inner), spec)
    if spec.startswith("ppo:"):
        from envs.gym.trained import TrainedPolicy  # needs the optional 'rl' extra

        policy = TrainedPolicy.load(spec[len("ppo:"):])
        size = getattr(policy, "team_size", 1)
        if scenario is not None and len(scenario.agents) != size:
            what = f"a team of {size}" if size > 1 else "one UAV (team:ppo:PATH: one each)"
            raise ValueError(f"{spec} flies {what}; scenario {scenario.name} has "
                             f"{len(scenario.agents)} agents")
        return policy
    if spec == RANDOM or spec.startswith(f"{RANDOM}:"):
        kind = spec.partition(":")[2] or "search"
        try:
            return RandomPolicy(kind)
        except ValueError:
            raise ValueError(f"unknown policy {spec!r}: random takes the action kind of an env "
                             "(random = random:search, osa/Search-v0; random:waypoint, "
                             "osa/Waypoint-v0)") from None
    if spec in POLICIES:
        return make_policy(spec)
    raise ValueError(f"unknown policy {spec!r}; choose from {', '.join(policy_names())}, "
                     "ppo:PATH or team:POLICY")
