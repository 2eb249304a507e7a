"""Policies by name, for the CLI and the evaluation harness (strings live at the edges).

``lawnmower``, ``expanding-square`` and ``adaptive`` are the planner's policies
(:mod:`planner.policy`); ``ppo:PATH`` loads a policy trained by ``osa train``.
"""

from __future__ import annotations

from planner.policy import POLICIES, Policy, make_policy
from sim.scenario import Scenario


def load_policy(spec: str, scenario: Scenario | None = None) -> Policy:
    """The policy named ``spec`` (raises ValueError with the choices otherwise)."""
    if spec.startswith("ppo:"):
        from envs.gym.trained import TrainedPolicy  # needs the optional 'rl' extra

        return TrainedPolicy.load(spec[len("ppo:"):])
    if spec in POLICIES:
        return make_policy(spec)
    raise ValueError(f"unknown policy {spec!r}; choose from {', '.join(POLICIES)} or ppo:PATH")
