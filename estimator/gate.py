"""Sliding-window MAD outlier gate, eqs. (3)-(4) (sec. MAD Outlier Gating).

The window holds the track's ranges of the last 1500 ms, the current one included
(every sample enters the window, accepted or not: the median is robust to the rejected
ones, and a genuine level change is accepted once it dominates the window). With at
least N_min = 8 entries the gate rejects |d - median| > k 1.4826 MAD. Every accepted
sample gets sigma_gate = max(1.4826 MAD, sigma_floor) computed over the current window
whatever its size (a lone sample gets the floor).

At the paper's 3-5 Hz the gate does not fire: the window holds >= 8 samples only when
8 successive responses arrive within 1.5 s (a sustained >= 4.7 Hz without one failed
exchange), which periodic FTM ranging at 3-5 Hz with its failed exchanges does not
deliver, so n_mad = 0 (the paper's table; every single-agent flight of our accuracy
benchmark) and the gate only supplies sigma_gate. It fires on bursty ranging and when
several agents' ranges to one responder share the window (a fused track at 10+ Hz):
the window then mixes ranges from different positions; mode ``refined`` gates each
agent in its own window.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import NamedTuple

MAD_TO_SIGMA = 1.4826  # 1 / Phi^-1(3/4), eq. (3)


@dataclass(frozen=True, kw_only=True)
class MadGateConfig:
    window_s: float = 1.5  # 1500 ms window
    min_samples: int = 8  # N_min warm-up
    k: float = 3.5  # Iglewicz and Hoaglin
    sigma_floor_m: float = 0.12  # eq. (4)


def _median(sorted_vals: list[float]) -> float:
    n = len(sorted_vals)
    h = n // 2
    return sorted_vals[h] if n % 2 else 0.5 * (sorted_vals[h - 1] + sorted_vals[h])


def median(values: list[float] | deque[float]) -> float:
    """Median of a short sequence (sorts a copy)."""
    return _median(sorted(values))


class GateResult(NamedTuple):
    accepted: bool
    sigma_gate_m: float
    median_m: float
    mad_m: float
    n_window: int


class MadGate:
    """Per-track MAD gate; ``check(t_s, range_m)`` returns the decision and sigma_gate."""

    def __init__(self, cfg: MadGateConfig = MadGateConfig()) -> None:
        self.cfg = cfg
        self._t: deque[float] = deque()
        self._d: deque[float] = deque()
        self.n_rejected = 0

    def check(self, t_s: float, range_m: float) -> GateResult:
        cfg = self.cfg
        self._t.append(t_s)
        self._d.append(range_m)
        horizon = t_s - cfg.window_s
        while self._t and self._t[0] < horizon:
            self._t.popleft()
            self._d.popleft()
        vals = sorted(self._d)
        med = _median(vals)
        mad = _median(sorted(abs(v - med) for v in vals))
        scale = MAD_TO_SIGMA * mad
        n = len(vals)
        accepted = not (n >= cfg.min_samples and abs(range_m - med) > cfg.k * scale)
        if not accepted:
            self.n_rejected += 1
        return GateResult(
            accepted=accepted,
            sigma_gate_m=max(scale, cfg.sigma_floor_m),
            median_m=med,
            mad_m=mad,
            n_window=n,
        )
