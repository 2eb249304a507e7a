"""Evaluation metrics of closed-loop searches (they read the truth: evaluation only)."""

from __future__ import annotations

import math
from collections.abc import Sequence

from envs.loop import SeriesPoint


def time_within_s(series: Sequence[SeriesPoint], threshold_m: float) -> float | None:
    """Flight time from which the horizontal error stays <= ``threshold_m`` to the end
    of the series (None if it never does, or is not within it at the end)."""
    t_in = None
    for p in series:
        ok = p.err_h_m is not None and p.err_h_m <= threshold_m
        if ok and t_in is None:
            t_in = p.t_s
        elif not ok:
            t_in = None
    return t_in


def error_at_s(series: Sequence[SeriesPoint], t_s: float) -> float | None:
    """The horizontal error of the last sample at or before ``t_s`` (None if none)."""
    best = None
    for p in series:
        if p.t_s <= t_s + 1e-9:
            best = p.err_h_m
    return best


def median(values: Sequence[float]) -> float:
    v = sorted(values)
    if not v:
        return math.nan
    h = len(v) // 2
    return v[h] if len(v) % 2 else 0.5 * (v[h - 1] + v[h])


def quantile(values: Sequence[float], q: float) -> float:
    v = sorted(values)
    if not v:
        return math.nan
    pos = q * (len(v) - 1)
    lo = math.floor(pos)
    hi = min(lo + 1, len(v) - 1)
    return v[lo] + (pos - lo) * (v[hi] - v[lo])
