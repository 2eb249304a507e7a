"""Search policies by name: the one place where the CLI's and the scenario's strings
become policy objects.

The interface and what a policy sees are in :mod:`planner.observation`; the policies
in :mod:`planner.coverage` (a :class:`planner.coverage.PatternPolicy` over the coverage
patterns of :data:`PATTERNS`) and :mod:`planner.adaptive` (``adaptive``).
"""

from __future__ import annotations

from planner.adaptive import AdaptivePolicy
from planner.coverage import CoveragePattern, ExpandingSquare, Lawnmower, PatternPolicy
from planner.observation import Policy

PATTERNS: dict[str, CoveragePattern] = {
    "lawnmower": Lawnmower(),
    "expanding-square": ExpandingSquare(),
}
POLICIES = (*PATTERNS, "adaptive")


def make_policy(name: str, **kw) -> Policy:
    """A policy by name (the CLI's strings): lawnmower, expanding-square, adaptive."""
    pattern = PATTERNS.get(name)
    if pattern is not None:
        return PatternPolicy(pattern, **kw)
    if name == "adaptive":
        return AdaptivePolicy(**kw)
    raise ValueError(f"unknown policy {name!r} ({', '.join(POLICIES)})")
