"""Policies by name, for the CLI and the evaluation harness (strings live at the edges).

``lawnmower``, ``expanding-square`` and ``adaptive`` are the planner's policies
(:mod:`planner.policy`); ``ppo:PATH`` loads a policy trained by ``osa train`` (one UAV,
or a whole team when trained in ``osa/Team-v0``); ``team:NAME`` flies every UAV of a
multi-UAV scenario with its own copy of the one-UAV policy ``NAME``
(:class:`planner.team.IndependentTeam`).
"""

from __future__ import annotations

import functools

from planner.policy import POLICIES, Policy, make_policy
from planner.team import IndependentTeam
from sim.scenario import Scenario


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
    if spec in POLICIES:
        return make_policy(spec)
    raise ValueError(f"unknown policy {spec!r}; choose from {', '.join(POLICIES)}, ppo:PATH "
                     "or team:POLICY")
