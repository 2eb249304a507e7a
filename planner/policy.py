"""Search policies by name: the one place where the CLI's and the scenario's strings
become policy objects.

The interface and what a policy sees are in :mod:`planner.observation`; the policies
in :mod:`planner.coverage` (``lawnmower``, ``expanding-square``) and
:mod:`planner.adaptive` (``adaptive``).
"""

from __future__ import annotations

from planner.adaptive import AdaptivePolicy
from planner.coverage import PatternPolicy
from planner.observation import Policy


def make_policy(name: str, **kw) -> Policy:
    """A policy by name (the CLI's strings): lawnmower, expanding-square, adaptive."""
    if name in ("lawnmower", "expanding-square"):
        return PatternPolicy(name, **kw)
    if name == "adaptive":
        return AdaptivePolicy(**kw)
    raise ValueError(f"unknown policy {name!r} (lawnmower, expanding-square, adaptive)")


POLICIES = ("lawnmower", "expanding-square", "adaptive")
