"""Two-stage Gauss-Newton bootstrap (sec. Gauss-Newton Bootstrap, eqs. 5-11).

Stage 1 solves the linearised 2-D system (eq. 6) by weighted least squares (eq. 7) with
the AGL correction rho^2 = d^2 - H_AGL^2 (eq. 5, falling back to d^2 when not
positive), and z0 = median(z_d - H_AGL) (eq. 8). Stage 2 runs 3-D Gauss-Newton (eqs.
9-11) until |dp| < 1e-4 m or 10 iterations; a solution farther than 2x the maximum
range from the drone centroid is rejected as divergent.

Added, as the paper recommends (sec. Discussion): a geometry check refusing kappa_H >=
10 (estimator.geometry) before solving, status ``weak_geometry``.

:class:`RobustBootstrap` is our improvement for weak, NLoS data (the paper's own
offline fix for AP_AB): damped trust-region least squares with a Cauchy loss and the
ground-height prior as a residual, started from stage 1 and from the drone centroid,
accepted on its residuals and geometry, never on the solver's success flag.

A mode holds a component, :class:`GaussNewton` or :class:`Robust`, that builds its
bootstrap from the pipeline's configuration.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, NamedTuple, Protocol

import numpy as np

from estimator.geometry import KAPPA_LIMIT, bbox_diagonal_m, horizontal_condition_number
from estimator.measurement import geometric_range_m, range_jacobian

if TYPE_CHECKING:
    from estimator.pipeline import PipelineConfig


@dataclass(frozen=True, kw_only=True)
class BootstrapConfig:
    min_samples: int = 8  # ">= 8 gated samples"
    min_spread_m: float = 15.0  # horizontal bounding-box diagonal
    gn_tol_m: float = 1e-4  # |dp| < 1e-4 m
    gn_max_iter: int = 10
    divergence_factor: float = 2.0  # reject |p - centroid| > 2 max(d)
    max_condition: float | None = KAPPA_LIMIT  # None disables the geometry check
    max_samples: int = 400  # most recent samples kept for (re)trials


@dataclass(frozen=True, slots=True)
class BootstrapSample:
    anchor_enu_m: tuple[float, float, float]
    range_m: float
    sigma_m: float
    agl_m: float


@dataclass(frozen=True)
class BootstrapResult:
    """Outcome: ``status`` is ``ok``, ``waiting``, ``weak_geometry`` or ``diverged``."""

    status: str
    position_enu_m: tuple[float, float, float] | None = None
    kappa: float = math.inf
    spread_m: float = 0.0
    iterations: int = 0
    n_samples: int = 0
    rms_m: float = math.nan

    @property
    def ok(self) -> bool:
        return self.status == "ok"


class _Prepared(NamedTuple):
    u: np.ndarray
    d: np.ndarray
    w: np.ndarray
    agl: np.ndarray
    kappa: float
    spread: float
    n: int


def _arrays(samples: Sequence[BootstrapSample]) -> tuple[np.ndarray, ...]:
    u = np.array([s.anchor_enu_m for s in samples], dtype=float)
    d = np.array([s.range_m for s in samples], dtype=float)
    w = 1.0 / np.array([max(s.sigma_m, 1e-6) ** 2 for s in samples], dtype=float)
    agl = np.array([s.agl_m for s in samples], dtype=float)
    return u, d, w, agl


def stage1_linear_xy(u: np.ndarray, d: np.ndarray, w: np.ndarray, agl: np.ndarray) -> np.ndarray:
    """Eqs. (5)-(7): WLS of the first-sample-differenced system; raises if singular."""
    rho2 = d * d - agl * agl
    rho2 = np.where(rho2 > 0.0, rho2, d * d)  # eq. (5) fallback
    x, y = u[:, 0], u[:, 1]
    A = np.column_stack((2.0 * (x[1:] - x[0]), 2.0 * (y[1:] - y[0])))
    c = rho2[0] - rho2[1:] + x[1:] ** 2 - x[0] ** 2 + y[1:] ** 2 - y[0] ** 2
    W = w[1:]
    AtWA = A.T @ (W[:, None] * A)
    AtWc = A.T @ (W * c)
    if not np.all(np.isfinite(AtWA)) or abs(np.linalg.det(AtWA)) < 1e-12 * max(
        1.0, float(np.trace(AtWA)) ** 2
    ):
        raise np.linalg.LinAlgError("stage-1 system is singular")
    return np.linalg.solve(AtWA, AtWc)


def gauss_newton_3d(
    p0: np.ndarray,
    u: np.ndarray,
    d: np.ndarray,
    w: np.ndarray,
    tol_m: float = 1e-4,
    max_iter: int = 10,
) -> tuple[np.ndarray, int]:
    """Eqs. (9)-(11): weighted Gauss-Newton on e_i = |p - u_i| - d_i."""
    p = np.array(p0, dtype=float)
    it = 0
    for it in range(1, max_iter + 1):  # noqa: B007 - iteration count is returned
        r, J = range_jacobian(p, u)  # J_ij = (p_j - u_ij) / |p - u_i|
        e = r - d
        JtWJ = J.T @ (w[:, None] * J)
        JtWe = J.T @ (w * e)
        dp = -np.linalg.solve(JtWJ, JtWe)
        p = p + dp
        if not np.all(np.isfinite(p)):
            raise np.linalg.LinAlgError("Gauss-Newton produced a non-finite estimate")
        if float(np.linalg.norm(dp)) < tol_m:
            break
    return p, it


class GaussNewtonBootstrap:
    """The paper's two-stage bootstrap with the added geometry check."""

    def __init__(self, cfg: BootstrapConfig = BootstrapConfig()) -> None:
        self.cfg = cfg

    def ready(self, samples: Sequence[BootstrapSample]) -> tuple[bool, float]:
        """Enough samples and horizontal spread to try (returns the spread too)."""
        if len(samples) < self.cfg.min_samples:
            return False, 0.0
        spread = bbox_diagonal_m([s.anchor_enu_m for s in samples])
        return spread >= self.cfg.min_spread_m, spread

    def _screen(self, samples: Sequence[BootstrapSample]) -> BootstrapResult | _Prepared:
        """The checks before any solving: samples, spread, then the geometry (kappa_H)."""
        n = len(samples)
        ready, spread = self.ready(samples)
        if not ready:
            return BootstrapResult("waiting", n_samples=n, spread_m=spread)
        u, d, w, agl = _arrays(samples)
        kappa = horizontal_condition_number(u, w)
        limit = self.cfg.max_condition
        if limit is not None and not kappa < limit:
            return BootstrapResult("weak_geometry", kappa=kappa, spread_m=spread, n_samples=n)
        return _Prepared(u, d, w, agl, kappa, spread, n)

    def solve(self, samples: Sequence[BootstrapSample]) -> BootstrapResult:
        cfg = self.cfg
        prep = self._screen(samples)
        if isinstance(prep, BootstrapResult):
            return prep
        u, d, w, agl, kappa, spread, n = prep
        try:
            pxy = stage1_linear_xy(u, d, w, agl)
            z0 = float(np.median(u[:, 2] - agl))  # eq. (8)
            p, it = gauss_newton_3d(
                np.array([pxy[0], pxy[1], z0]), u, d, w, cfg.gn_tol_m, cfg.gn_max_iter
            )
        except np.linalg.LinAlgError:
            return BootstrapResult("diverged", kappa=kappa, spread_m=spread, n_samples=n)
        return self._check(p, u, d, kappa, spread, it, n)

    def _check(
        self,
        p: np.ndarray,
        u: np.ndarray,
        d: np.ndarray,
        kappa: float,
        spread: float,
        it: int,
        n: int,
    ) -> BootstrapResult:
        centroid = u.mean(axis=0)
        rms = float(np.sqrt(np.mean((geometric_range_m(p, u) - d) ** 2)))
        far = float(np.linalg.norm(p - centroid)) > self.cfg.divergence_factor * float(d.max())
        if far or not np.all(np.isfinite(p)):
            return BootstrapResult(
                "diverged", kappa=kappa, spread_m=spread, iterations=it, n_samples=n, rms_m=rms
            )
        return BootstrapResult(
            "ok",
            position_enu_m=(float(p[0]), float(p[1]), float(p[2])),
            kappa=kappa,
            spread_m=spread,
            iterations=it,
            n_samples=n,
            rms_m=rms,
        )


@dataclass(frozen=True, kw_only=True)
class RobustBootstrapConfig(BootstrapConfig):
    """Damped robust bootstrap (our extension; sec. Conclusions' recommendation)."""

    loss: str = "cauchy"  # scipy.optimize.least_squares loss, as the paper's offline fix
    loss_scale_m: float = 2.0  # residual scale where the Cauchy loss starts to flatten
    ground_sigma_m: float = 5.0  # ground-height prior, same R_z as eq. (18)
    max_rms_m: float = 6.0  # accept only if the inlier residual RMS is plausible
    inlier_m: float = 8.0  # |residual| below this counts as inlier
    min_inlier_fraction: float = 0.6


class RobustBootstrap(GaussNewtonBootstrap):
    """Trust-region least squares with Cauchy loss + ground prior, multi-start."""

    def __init__(self, cfg: RobustBootstrapConfig = RobustBootstrapConfig()) -> None:
        super().__init__(cfg)
        self.rcfg = cfg

    def solve(self, samples: Sequence[BootstrapSample]) -> BootstrapResult:
        from scipy.optimize import least_squares

        cfg = self.rcfg
        prep = self._screen(samples)
        if isinstance(prep, BootstrapResult):
            return prep
        u, d, w, agl, kappa, spread, n = prep
        z_ground = float(np.median(u[:, 2] - agl))
        sw = np.sqrt(w)

        def resid(p: np.ndarray) -> np.ndarray:
            r = geometric_range_m(p, u) - d
            return np.concatenate((sw * r, [(p[2] - z_ground) / cfg.ground_sigma_m]))

        starts = [np.array([*u[:, :2].mean(axis=0), z_ground])]
        try:
            pxy = stage1_linear_xy(u, d, w, agl)
            starts.insert(0, np.array([pxy[0], pxy[1], z_ground]))
        except np.linalg.LinAlgError:
            pass
        best = None
        for p0 in starts:
            if not np.all(np.isfinite(p0)):
                continue
            sol = least_squares(
                resid,
                p0,
                loss=cfg.loss,
                f_scale=cfg.loss_scale_m * float(np.sqrt(np.median(w))),
                method="trf",
                max_nfev=200,
            )
            if best is None or sol.cost < best.cost:
                best = sol
        if best is None:
            return BootstrapResult("diverged", kappa=kappa, spread_m=spread, n_samples=n)
        p = best.x
        res = geometric_range_m(p, u) - d
        inl = np.abs(res) < cfg.inlier_m
        rms = float(np.sqrt(np.mean(res[inl] ** 2))) if inl.any() else math.inf
        out = self._check(p, u, d, kappa, spread, int(best.nfev), n)
        if out.ok and (inl.mean() < cfg.min_inlier_fraction or rms > cfg.max_rms_m):
            return BootstrapResult(
                "diverged", kappa=kappa, spread_m=spread, n_samples=n, rms_m=rms
            )
        return out


# --------------------------------------------------------------------------- components


class Bootstrapper(Protocol):
    """What a filter run needs of a bootstrap (GaussNewtonBootstrap, RobustBootstrap)."""

    def ready(self, samples: Sequence[BootstrapSample]) -> tuple[bool, float]: ...

    def solve(self, samples: Sequence[BootstrapSample]) -> BootstrapResult: ...


class BootstrapComponent(Protocol):
    """A mode's bootstrap: builds one from the pipeline's config."""

    def make(self, cfg: PipelineConfig) -> Bootstrapper: ...


@dataclass(frozen=True)
class GaussNewton:
    """The paper's bootstrap (``cfg.bootstrap``): :class:`GaussNewtonBootstrap`."""

    def make(self, cfg: PipelineConfig) -> GaussNewtonBootstrap:
        return GaussNewtonBootstrap(cfg.bootstrap)


@dataclass(frozen=True)
class Robust:
    """Our damped robust bootstrap (``cfg.robust_bootstrap``): :class:`RobustBootstrap`."""

    def make(self, cfg: PipelineConfig) -> RobustBootstrap:
        return RobustBootstrap(cfg.robust_bootstrap)
