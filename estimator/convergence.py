"""Convergence rules (sec. Measurement-Noise Configurations, last paragraph).

A published estimate is *stable* when all hold: sigma_H < 2.5 m, sigma_Z < 8 m,
n_acc >= 15, the jump from the previous published estimate satisfies
dxy < max(1, 2 sigma_H) and dz < max(2, 2 sigma_Z), and the streak of consecutive
accepted updates is >= 3. Once sigma_H has been non-increasing (within 2 %) for 5
consecutive updates n_acc relaxes to >= 10, after 8 the streak requirement drops to
>= 2.

Every rejection after the bootstrap resets the streak, whether the MAD gate (eq. 3) or
the NIS gate (eq. 16) made it (:meth:`estimator.pipeline.Track.process` calls
:meth:`ConvergenceMonitor.on_rejected` for both); a rejection does not reset the
sigma_H run, which counts published updates only. The relaxation is not latched: the
run restarts at the first published sigma_H more than 2 % above the previous one, and
the relaxed thresholds revert to n_acc >= 15 and a streak >= 3 with it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True, kw_only=True)
class ConvergenceConfig:
    max_sigma_h_m: float = 2.5
    max_sigma_z_m: float = 8.0
    min_n_acc: int = 15
    min_jump_xy_m: float = 1.0  # dxy < max(1, 2 sigma_H)
    min_jump_z_m: float = 2.0  # dz < max(2, 2 sigma_Z)
    jump_sigma_factor: float = 2.0
    min_streak: int = 3
    relax_tolerance: float = 0.02  # sigma_H "non-increasing within 2 %"
    relax_n_acc_after: int = 5
    relaxed_min_n_acc: int = 10
    relax_streak_after: int = 8
    relaxed_min_streak: int = 2


class ConvergenceMonitor:
    """Feed ``on_rejected()`` for every post-bootstrap rejection (MAD or NIS),
    ``on_accepted()`` per accepted update and ``on_published(...)`` per estimate."""

    def __init__(self, cfg: ConvergenceConfig = ConvergenceConfig()) -> None:
        self.cfg = cfg
        self.streak = 0
        self.non_increasing = 0
        self._prev_sigma_h: float | None = None
        self._prev_pos: tuple[float, float, float] | None = None

    def on_rejected(self) -> None:
        self.streak = 0

    def on_accepted(self) -> None:
        self.streak += 1

    def on_published(
        self,
        pos: tuple[float, float, float],
        sigma_h_m: float,
        sigma_z_m: float,
        n_acc: int,
    ) -> bool:
        """Judge one published estimate (after ``on_accepted``); True when stable."""
        cfg = self.cfg
        prev_s = self._prev_sigma_h
        if prev_s is not None and sigma_h_m <= prev_s * (1.0 + cfg.relax_tolerance):
            self.non_increasing += 1
        else:
            self.non_increasing = 0
        self._prev_sigma_h = sigma_h_m
        min_n = (
            cfg.relaxed_min_n_acc
            if self.non_increasing >= cfg.relax_n_acc_after
            else cfg.min_n_acc
        )
        min_streak = (
            cfg.relaxed_min_streak
            if self.non_increasing >= cfg.relax_streak_after
            else cfg.min_streak
        )
        prev = self._prev_pos
        self._prev_pos = pos
        if prev is None:
            return False
        dxy = math.hypot(pos[0] - prev[0], pos[1] - prev[1])
        dz = abs(pos[2] - prev[2])
        return (
            sigma_h_m < cfg.max_sigma_h_m
            and sigma_z_m < cfg.max_sigma_z_m
            and n_acc >= min_n
            and dxy < max(cfg.min_jump_xy_m, cfg.jump_sigma_factor * sigma_h_m)
            and dz < max(cfg.min_jump_z_m, cfg.jump_sigma_factor * sigma_z_m)
            and self.streak >= min_streak
        )
