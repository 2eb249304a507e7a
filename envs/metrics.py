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


# ------------------------------------------------------------------ timed challenges
CHALLENGE_TIMES_S = (180.0, 600.0)  # the error at 3 and at 10 minutes of flight
SUCCESS_RADII_M = (2.0, 5.0)  # success: the final estimate within 2 m, within 5 m
ERROR_CAP_M = 50.0  # per-episode error: an estimate farther off, or none, counts as this


def error_at_flight_s(series: Sequence[SeriesPoint], t_s: float, flight_time_s: float,
                      final_err_h_m: float | None) -> float | None:
    """The horizontal error of the estimate held at ``t_s`` of flight: the last sample
    at or before ``t_s`` while the search flew, the final estimate's once it had ended
    (``t_s`` >= ``flight_time_s``: a finished search keeps its estimate); None when
    there was no estimate then."""
    if t_s >= flight_time_s - 1e-9:
        return final_err_h_m
    return error_at_s(series, t_s)


def within(err_h_m: float | None, radius_m: float) -> int:
    """1 if an estimate exists and is within ``radius_m`` horizontally, else 0."""
    return int(err_h_m is not None and err_h_m <= radius_m)


def all_localised_at_s(localised_at_s: Sequence[float | None]) -> float | None:
    """When the last of an episode's responders was judged localised (None: not all
    were, censored at the budget)."""
    if not localised_at_s or any(t is None for t in localised_at_s):
        return None
    return max(float(t) for t in localised_at_s)  # type: ignore[arg-type]


def episode_error_m(errors_h_m: Sequence[float | None], cap_m: float = ERROR_CAP_M) -> float:
    """An episode's final error: the mean over its responders of the horizontal error
    capped at ``cap_m`` (a responder without an estimate counts as ``cap_m``)."""
    if not errors_h_m:
        return math.nan
    return sum(cap_m if e is None else min(float(e), cap_m) for e in errors_h_m) / len(errors_h_m)
