"""Random processes shared by the sensor and vehicle models (all from an explicit Generator)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike
from scipy.ndimage import gaussian_filter, gaussian_filter1d
from scipy.signal import lfilter

from sim.terrain import bilinear


def gauss_markov(
    rng: np.random.Generator, n: int, dt_s: float, sigma: ArrayLike, tau_s: float
) -> np.ndarray:
    """First-order Gauss-Markov samples on a uniform grid, started in steady state.

    x[k+1] = phi x[k] + sqrt(1 - phi^2) sigma w[k], phi = exp(-dt/tau), x[0] ~ N(0, sigma^2),
    so the autocorrelation at lag L is exp(-L/tau) exactly. ``sigma`` may be a vector
    (one column per axis); the result is (n, len(sigma)) or (n,) for a scalar sigma.
    """
    s = np.asarray(sigma, dtype=float)
    cols = 1 if s.ndim == 0 else s.shape[0]
    if n <= 0:
        return np.zeros((0,) if s.ndim == 0 else (0, cols))
    phi = math.exp(-dt_s / tau_s)
    w = rng.standard_normal((n, cols))
    w[0] *= s
    w[1:] *= s * math.sqrt(max(0.0, 1.0 - phi * phi))
    x = lfilter([1.0], [1.0, -phi], w, axis=0)
    return x[:, 0] if s.ndim == 0 else x


def smooth_gauss_markov(
    rng: np.random.Generator, n: int, dt_s: float, sigma: ArrayLike, tau_s: float
) -> np.ndarray:
    """A smooth (differentiable) stationary wander: second-order Gauss-Markov.

    Two first-order stages with the same pole phi = exp(-dt/tau) in series, scaled so
    the standard deviation is ``sigma``; a burn-in of 6 tau reaches steady state.
    Shapes as :func:`gauss_markov`.
    """
    s = np.asarray(sigma, dtype=float)
    cols = 1 if s.ndim == 0 else s.shape[0]
    if n <= 0:
        return np.zeros((0,) if s.ndim == 0 else (0, cols))
    phi = math.exp(-dt_s / tau_s)
    burn = math.ceil(6.0 * tau_s / dt_s)
    w = rng.standard_normal((n + burn, cols))
    gain = math.sqrt((1.0 - phi * phi) ** 3 / (1.0 + phi * phi))  # unit steady variance
    x = lfilter([gain], [1.0, -2.0 * phi, phi * phi], w, axis=0)[burn:] * s
    return x[:, 0] if s.ndim == 0 else x


@dataclass(frozen=True, eq=False)
class GaussianField2D:
    """A stationary Gaussian random field on a coarse grid, interpolated bilinearly.

    Covariance ~ sigma^2 exp(-r^2 / (2 L^2)) for correlation length L: white noise on a
    grid of spacing L/2 smoothed by a Gaussian kernel of standard deviation L/sqrt(2)
    and rescaled to unit variance at the grid nodes.
    """

    values: np.ndarray
    x0_m: float
    y0_m: float
    spacing_m: float

    @classmethod
    def draw(
        cls,
        rng: np.random.Generator,
        bounds_m: tuple[float, float, float, float],
        corr_length_m: float,
        sigma: float,
        max_cells: int = 1_000_000,
    ) -> GaussianField2D:
        xmin, xmax, ymin, ymax = bounds_m
        pad = 3.0 * corr_length_m
        spacing = corr_length_m / 2.0
        width = xmax - xmin + 2 * pad
        height = ymax - ymin + 2 * pad
        while (width / spacing + 2) * (height / spacing + 2) > max_cells:
            spacing *= 1.5
        nx = math.ceil(width / spacing) + 2
        ny = math.ceil(height / spacing) + 2
        white = rng.standard_normal((ny, nx))
        if sigma == 0.0:
            return cls(np.zeros((ny, nx)), xmin - pad, ymin - pad, spacing)
        s_cells = corr_length_m / (math.sqrt(2.0) * spacing)
        smooth = gaussian_filter(white, s_cells, mode="wrap")
        delta = np.zeros(8 * math.ceil(s_cells) + 9)
        delta[len(delta) // 2] = 1.0
        kernel = gaussian_filter1d(delta, s_cells, mode="constant")
        scale = sigma / float(np.sum(kernel * kernel))  # 2-D variance = (sum w^2)^2
        return cls(smooth * scale, xmin - pad, ymin - pad, spacing)

    def __call__(self, x_m: ArrayLike, y_m: ArrayLike) -> np.ndarray:
        s = self.spacing_m
        return bilinear(self.values, self.x0_m, self.y0_m, s, s, x_m, y_m)
