"""Random processes shared by the sensor and vehicle models (all from an explicit Generator)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike
from scipy.signal import lfilter


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


Seed = int | np.integer | np.random.SeedSequence | np.random.Generator


def as_seed_sequence(seed: Seed) -> np.random.SeedSequence:
    """A seed as a SeedSequence: an int (>= 0), a SeedSequence (as is), or a Generator
    (entropy drawn from it, so the same generator state gives the same sequence)."""
    if isinstance(seed, np.random.SeedSequence):
        return seed
    if isinstance(seed, np.random.Generator):
        return np.random.SeedSequence(seed.integers(0, 2**63, size=4).tolist())
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer):
        kind = type(seed).__name__
        raise TypeError(f"seed must be an int, SeedSequence or Generator, got {kind}")
    if seed < 0:
        raise ValueError(f"seed must be >= 0, got {seed}")
    return np.random.SeedSequence(int(seed))


def child_seed(seq: np.random.SeedSequence, *key: int) -> np.random.SeedSequence:
    """The child of ``seq`` named by ``key`` (a path of ints): the same key always gives
    the same stream, whatever else was drawn (unlike ``spawn``, which counts)."""
    return np.random.SeedSequence(seq.entropy, spawn_key=(*seq.spawn_key, *key))


def child_rng(seq: np.random.SeedSequence, *key: int) -> np.random.Generator:
    return np.random.default_rng(child_seed(seq, *key))


class BlockedGaussMarkov:
    """A stationary Gauss-Markov process on the grid t_k = k dt, as a function of k.

    Values are generated in blocks of ``block`` samples, block b from the stream
    ``child_seed(seq, b)`` and chained to block b - 1 through the recursion state, so
    the value at k does not depend on which values were asked for before: the process
    is a function of time, the same whatever is flown. ``order = 1``: first order
    (autocorrelation exp(-lag/tau) exactly, started in steady state); ``order = 2``:
    two first-order stages in series (a smooth wander), scaled to standard deviation
    ``sigma`` and started after a burn-in of 6 tau.
    """

    def __init__(
        self,
        seq: np.random.SeedSequence,
        dt_s: float,
        sigma: ArrayLike,
        tau_s: float,
        *,
        order: int = 1,
        block: int = 1024,
    ) -> None:
        self.seq = seq
        self.dt_s = dt_s
        self.sigma = np.atleast_1d(np.asarray(sigma, dtype=float))
        self.tau_s = tau_s
        self.order = order
        self.block = block
        self.phi = math.exp(-dt_s / tau_s)
        self._blocks: list[np.ndarray] = []
        self._first = 0  # the block index of _blocks[0] (those before: forgotten)
        self._state: np.ndarray | None = None  # recursion state after the last block

    @property
    def cols(self) -> int:
        return len(self.sigma)

    def _make_block(self) -> np.ndarray:
        b = self._first + len(self._blocks)
        rng = child_rng(self.seq, b)
        n, phi = self.block, self.phi
        w = rng.standard_normal((n, self.cols))
        if self.order == 1:
            scale = math.sqrt(max(0.0, 1.0 - phi * phi))
            x = np.empty_like(w)
            # the first sample of the process is N(0, 1) (steady state); later blocks
            # continue the recursion x[k] = phi x[k-1] + sqrt(1 - phi^2) w[k]
            x[0] = w[0] if self._state is None else phi * self._state + scale * w[0]
            if n > 1:
                x[1:] = lfilter([scale], [1.0, -phi], w[1:], axis=0, zi=(phi * x[0])[None, :])[0]
            self._state = x[-1].copy()
            self._blocks.append(x)
            return x
        gain = math.sqrt((1.0 - phi * phi) ** 3 / (1.0 + phi * phi))
        if self._state is None:  # burn-in from zero state
            burn = math.ceil(6.0 * self.tau_s / self.dt_s)
            wb = np.random.default_rng(child_seed(self.seq, 1 << 30)).standard_normal(
                (burn, self.cols)
            )
            _, zi = lfilter([gain], [1.0, -2.0 * phi, phi * phi], wb, axis=0,
                            zi=np.zeros((2, self.cols)))
        else:
            zi = self._state
        x, zf = lfilter([gain], [1.0, -2.0 * phi, phi * phi], w, axis=0, zi=zi)
        self._state = zf
        self._blocks.append(x)
        return x

    def values(self, k0: int, k1: int) -> np.ndarray:
        """(k1 - k0, cols) unit-variance samples times sigma, grid indices k0 <= k < k1."""
        if k1 <= k0:
            return np.zeros((0, self.cols))
        if k0 < 0:
            raise ValueError("negative grid index")
        last = (k1 - 1) // self.block
        while self._first + len(self._blocks) <= last:
            self._make_block()
        b0 = k0 // self.block
        if b0 < self._first:
            raise ValueError(f"grid index {k0} was forgotten (forget_before)")
        parts = self._blocks[b0 - self._first : last - self._first + 1]
        x = parts[0] if len(parts) == 1 else np.concatenate(parts)
        off = b0 * self.block
        return x[k0 - off : k1 - off] * self.sigma

    def forget_before(self, k: int) -> None:
        """Forget the blocks wholly before grid index ``k`` (the last one made stays):
        a process that runs for hours keeps its recent values only."""
        drop = min(k // self.block - self._first, len(self._blocks) - 1)
        if drop > 0:
            del self._blocks[:drop]
            self._first += drop

    def at(self, t_s: ArrayLike) -> np.ndarray:
        """Linear interpolation of the grid values at times ``t_s`` (>= 0), (M, cols)."""
        from sim import _kernels

        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        if len(t) == 0:
            return np.zeros((0, self.cols))
        f = t / self.dt_s
        k0 = math.floor(f.min())
        return _kernels.lerp_after(self.values(k0, math.floor(f.max()) + 2), f, k0)


@dataclass(frozen=True, eq=False)
class RandomFourierField:
    """A stationary Gaussian random field over the whole plane (random Fourier features).

    f(x) = sigma sqrt(2 / M) sum_m cos(w_m . x + phi_m), w_m ~ N(0, I / L^2),
    phi_m ~ U(0, 2 pi): covariance sigma^2 exp(-r^2 / (2 L^2)) for correlation length L
    (Rahimi and Recht 2007), marginally Gaussian to a good approximation for M ~ 100.
    Defined everywhere, no grid and no bounding box: a world's shadowing does not depend
    on where anyone flies.
    """

    w: np.ndarray  # (M, 2) rad/m
    phase: np.ndarray  # (M,)
    amplitude: float  # sigma sqrt(2 / M)

    @classmethod
    def draw(
        cls, rng: np.random.Generator, sigma: float, corr_length_m: float, n_features: int = 96
    ) -> RandomFourierField:
        w = rng.standard_normal((n_features, 2)) / corr_length_m
        phase = rng.uniform(0.0, 2.0 * math.pi, n_features)
        return cls(w, phase, sigma * math.sqrt(2.0 / n_features))

    def __call__(self, x_m: ArrayLike, y_m: ArrayLike) -> np.ndarray:
        x = np.asarray(x_m, dtype=float)
        y = np.asarray(y_m, dtype=float)
        if self.amplitude == 0.0:
            return np.zeros(np.broadcast(x, y).shape)
        arg = np.multiply.outer(x, self.w[:, 0]) + np.multiply.outer(y, self.w[:, 1]) + self.phase
        return self.amplitude * np.cos(arg).sum(axis=-1)
