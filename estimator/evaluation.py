"""Scoring estimates against truth: evaluation, never estimation.

Nothing here feeds back into a track. A :class:`TruthScorer` is attached to tracks as
an observer (:class:`estimator.pipeline.TrackObserver`) and accumulates, per track,
the time-weighted mean 2-D error (Table "Filter comparison on AP_1F", column TWM)
online, so a replay needs no estimate history to report it. :func:`errors_m` gives the
final horizontal and 3-D errors of one position.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

from estimator.geodesy import EnuFrame
from estimator.pipeline import Published, Track
from estimator.records import TruthRecord


def errors_m(
    position_enu_m: Sequence[float], truth_enu_m: Sequence[float]
) -> tuple[float, float]:
    """(horizontal, 3-D) distance between an estimate and the truth (metres)."""
    dx = position_enu_m[0] - truth_enu_m[0]
    dy = position_enu_m[1] - truth_enu_m[1]
    dz = position_enu_m[2] - truth_enu_m[2]
    return math.hypot(dx, dy), math.sqrt(dx * dx + dy * dy + dz * dz)


class TwmAccumulator:
    """Online time-weighted mean of the 2-D error of a track's published estimates.

    Each estimate's error is weighted by the time until the next one:
    TWM = sum_k e_k (t_{k+1} - t_k) / (t_n - t_1); a single estimate gives its error.
    Kept over the stable estimates and, as a fallback, over all published ones.
    """

    def __init__(self, truth_enu_m: Sequence[float]) -> None:
        self.truth = tuple(truth_enu_m)
        self._stable = [0.0, None, None, 0.0, 0]  # acc, t_first, (t_last, e_last), sum, n
        self._all = [0.0, None, None, 0.0, 0]

    @staticmethod
    def _add(st: list, t_s: float, e: float) -> None:
        if st[1] is None:
            st[1] = t_s
        else:
            t_prev, e_prev = st[2]
            st[0] += e_prev * (t_s - t_prev)
        st[2] = (t_s, e)
        st[3] += e
        st[4] += 1

    def add(self, pub: Published) -> None:
        tr = self.truth
        e = math.hypot(pub.enu_m[0] - tr[0], pub.enu_m[1] - tr[1])
        self._add(self._all, pub.t_s, e)
        if pub.stable:
            self._add(self._stable, pub.t_s, e)

    @staticmethod
    def _value(st: list) -> float | None:
        if st[4] == 0:
            return None
        span = st[2][0] - st[1]
        return st[3] / st[4] if st[4] == 1 or span <= 0 else st[0] / span

    @property
    def twm_h_m(self) -> float | None:
        v = self._value(self._stable)
        return v if v is not None else self._value(self._all)


def twm_of_history(history: Sequence[Published], truth_enu_m: Sequence[float]) -> float | None:
    """The TWM of a stored history, computed in one batch (the definition
    :class:`TwmAccumulator` keeps online): over the stable estimates, else all."""
    pts = [p for p in history if p.stable] or list(history)
    if not pts:
        return None
    errs = [math.hypot(p.enu_m[0] - truth_enu_m[0], p.enu_m[1] - truth_enu_m[1]) for p in pts]
    span = pts[-1].t_s - pts[0].t_s
    if len(pts) == 1 or span <= 0:
        return sum(errs) / len(errs)
    acc = sum(errs[k] * (pts[k + 1].t_s - pts[k].t_s) for k in range(len(pts) - 1))
    return acc / span


class TruthScorer:
    """Observer of tracks that knows where some responders truly are.

    ``truth`` maps bssid to a :class:`estimator.records.TruthRecord` (WGS84) or to an
    ENU position; WGS84 truth is placed in the tracks' frame, which ``frame()`` gives
    once the estimator has fixed it. Restarts reset the accumulator, as the track's
    published history restarts.
    """

    def __init__(
        self,
        truth: dict[str, TruthRecord | Sequence[float]] | None = None,
        frame: Callable[[], EnuFrame | None] | None = None,
    ) -> None:
        self.truth = dict(truth or {})
        self.frame = frame
        self._twm: dict[int, TwmAccumulator] = {}

    def truth_enu_m(self, bssid: str) -> tuple[float, float, float] | None:
        t = self.truth.get(bssid)
        if t is None:
            return None
        if isinstance(t, TruthRecord):
            frame = self.frame() if self.frame is not None else None
            if frame is None:
                return None
            return tuple(float(v) for v in frame.to_enu(t.lat_deg, t.lon_deg, t.alt_m))
        return tuple(float(v) for v in t)

    def published(self, track: Track, pub: Published) -> None:
        acc = self._twm.get(id(track))
        if acc is None:
            tr = self.truth_enu_m(track.bssid)
            if tr is None:
                return
            acc = self._twm[id(track)] = TwmAccumulator(tr)
        acc.add(pub)

    def restarted(self, track: Track) -> None:
        self._twm.pop(id(track), None)

    def twm_h_m(self, track: Track) -> float | None:
        acc = self._twm.get(id(track))
        return acc.twm_h_m if acc is not None else None
