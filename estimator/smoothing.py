"""Output smoothers (sec. Measurement-Noise Configurations, last paragraph).

All modes but EMA publish a sliding-window median of the filter output (W_xy = 7 for
x and y, W_z = 9 for z); the EMA mode replaces it with s = a x + (1 - a) s_prev,
a = 0.3. Smoothers see the filter output after every accepted update. A mode holds a
component (:class:`Median`, :class:`Ema`, :class:`Unsmoothed`) that builds a fresh
smoother from the pipeline's configuration.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

if TYPE_CHECKING:
    from estimator.pipeline import PipelineConfig


class Smoother(Protocol):
    def push(self, p: tuple[float, float, float]) -> tuple[float, float, float]: ...


@dataclass(frozen=True, kw_only=True)
class MedianSmootherConfig:
    window_xy: int = 7  # W_xy
    window_z: int = 9  # W_z


class MedianSmoother:
    def __init__(self, cfg: MedianSmootherConfig = MedianSmootherConfig()) -> None:
        self._x: deque[float] = deque(maxlen=cfg.window_xy)
        self._y: deque[float] = deque(maxlen=cfg.window_xy)
        self._z: deque[float] = deque(maxlen=cfg.window_z)

    def push(self, p: tuple[float, float, float]) -> tuple[float, float, float]:
        self._x.append(p[0])
        self._y.append(p[1])
        self._z.append(p[2])
        out = []
        for d in (self._x, self._y, self._z):
            v = sorted(d)
            h = len(v) >> 1
            out.append(v[h] if len(v) & 1 else 0.5 * (v[h - 1] + v[h]))
        return out[0], out[1], out[2]


@dataclass(frozen=True, kw_only=True)
class EmaSmootherConfig:
    alpha: float = 0.3  # alpha_EMA


class EmaSmoother:
    def __init__(self, cfg: EmaSmootherConfig = EmaSmootherConfig()) -> None:
        self.alpha = cfg.alpha
        self._s: tuple[float, float, float] | None = None

    def push(self, p: tuple[float, float, float]) -> tuple[float, float, float]:
        if self._s is None:
            self._s = (p[0], p[1], p[2])
        else:
            a = self.alpha
            b = 1.0 - a
            s = self._s
            self._s = (a * p[0] + b * s[0], a * p[1] + b * s[1], a * p[2] + b * s[2])
        return self._s


class PassThrough:
    """No smoothing: publishes the filter output as it is."""

    def push(self, p: tuple[float, float, float]) -> tuple[float, float, float]:
        return p[0], p[1], p[2]


# --------------------------------------------------------------------------- components


class SmootherComponent(Protocol):
    """A mode's output smoother: builds a fresh one from the pipeline's config."""

    def make(self, cfg: PipelineConfig) -> Smoother: ...


@dataclass(frozen=True)
class Median:
    """The sliding-window median of every mode but EMA (``cfg.median``)."""

    def make(self, cfg: PipelineConfig) -> MedianSmoother:
        return MedianSmoother(cfg.median)


@dataclass(frozen=True)
class Ema:
    """The EMA mode's exponential moving average (``cfg.ema``)."""

    def make(self, cfg: PipelineConfig) -> EmaSmoother:
        return EmaSmoother(cfg.ema)


@dataclass(frozen=True)
class Unsmoothed:
    """No output smoothing (mode ``refined`` publishes its front and refinements)."""

    def make(self, cfg: PipelineConfig) -> PassThrough:
        return PassThrough()
