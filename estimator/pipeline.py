"""One responder track: gate -> bootstrap -> filter -> ground prior -> smoother -> rules.

The paper's six modes (sec. Measurement-Noise Configurations) are compositions, not six
pipelines: a :class:`ModeSpec` holds its filter, noise model, smoother and bootstrap as
component objects (``filters.Iekf()``, ``noise.Nlos()``, ``smoothing.Ema()``,
``bootstrap.GaussNewton()``...), each building its part from the :class:`PipelineConfig`.
Names are resolved to specs in one place, the registry :data:`estimator.modes.MODES`
(``resolve_mode``), at the command line's and the options' edge. Further modes (ours)
are compositions too and carry their own names; the paper's six never change.

Counting (Table "Filter comparison on AP_1F"): ``n_meas`` associated measurements enter
the track; those up to and including the successful bootstrap are ``n_bootstrap``;
after it every measurement is either rejected (``n_gate`` = MAD ``n_mad`` + NIS
``n_nis``) or accepted (``n_acc``), so n_meas = n_bootstrap + n_gate + n_acc. When the
filter state becomes invalid the track restarts: the measurements of the discarded
filter (and the one that broke it) join ``n_bootstrap``, the post-bootstrap counts
restart at zero (``n_restarts`` counts restarts), so the identity holds and ``n_acc``
(which the convergence rules read) counts the running filter's updates only.
"""

from __future__ import annotations

import functools
import math
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import NamedTuple, Protocol

from estimator.batch import BatchConfig
from estimator.bootstrap import (
    BootstrapComponent,
    BootstrapConfig,
    BootstrapResult,
    BootstrapSample,
    GaussNewton,
    RobustBootstrapConfig,
)
from estimator.convergence import ConvergenceConfig, ConvergenceMonitor
from estimator.filters import (
    FilterComponent,
    FilterError,
    Iekf,
    IekfConfig,
    SequentialFilter,
    UkfConfig,
)
from estimator.gate import MadGate, MadGateConfig, median
from estimator.geometry import KAPPA_LIMIT
from estimator.noise import (
    AdaptiveRConfig,
    Constant,
    EmpiricalRConfig,
    GatedRange,
    GnssCovarianceConfig,
    NlosConfig,
    NoiseComponent,
    NoiseModel,
)
from estimator.records import AssociatedRange
from estimator.smoothing import (
    EmaSmootherConfig,
    Median,
    MedianSmootherConfig,
    Smoother,
    SmootherComponent,
)

DEFAULT_AGL_M = 45.0  # docs/cli.md: header config.agl_m, else 45 m


@dataclass(frozen=True, kw_only=True)
class GroundPriorConfig:
    """Ground-height pseudo-measurement after each accepted update (eq. 18)."""

    enabled: bool = True
    window: int = 25  # W_z of the ground prior: last 25 drone altitudes
    r_z_m2: float = 25.0  # R_z = (5 m)^2


@dataclass(frozen=True, kw_only=True)
class RefinedConfig:
    """Mode ``refined``: front, refinement schedule and the verdict (issue 8).

    The front is the IEKF with Q = 0 (a static responder: no artificial random walk)
    and R = s_a^2 sigma_E^2 (the Empirical-R shape, eq. 23, scaled by the agent's
    calibrated scale), without the per-update ground prior. The refinement runs once
    the front bootstraps (or its bootstrap gives up), then whenever the gated ranges
    have grown by ``growth`` (at least ``min_new`` more), and at the end; the check for
    other minima runs at the first and the last, whenever the ranges have doubled since
    the previous check, and while no front runs or the previous check was ambiguous.
    ``converged`` needs: >= ``min_n`` ranges, kappa_H < ``max_kappa``, every agent's
    scale <= ``max_scale`` (residuals at most 1.5 x the paper's Empirical-R sigma), an
    inlier fraction (|e| < 3) >= ``min_inlier_fraction``, no other minimum with weight
    >= ``min_weight`` and a 95 % circle <= ``max_r95_m``.
    """

    batch: BatchConfig = field(default_factory=BatchConfig)
    front: IekfConfig = field(
        default_factory=lambda: IekfConfig(q_diag=(0.0, 0.0, 0.0, 0.0))
    )
    growth: float = 2.0
    min_new: int = 8
    min_n: int = 15
    max_kappa: float = KAPPA_LIMIT
    max_scale: float = 1.5
    min_inlier_fraction: float = 0.8
    min_weight: float = 0.01
    max_r95_m: float = 10.0


@dataclass(frozen=True, kw_only=True)
class PipelineConfig:
    """Every parameter of the pipeline; defaults are the paper's values."""

    agl_m: float = DEFAULT_AGL_M  # H_AGL when a measurement carries none
    gate: MadGateConfig = field(default_factory=MadGateConfig)
    bootstrap: BootstrapConfig = field(default_factory=BootstrapConfig)
    robust_bootstrap: RobustBootstrapConfig = field(default_factory=RobustBootstrapConfig)
    iekf: IekfConfig = field(default_factory=IekfConfig)
    ukf: UkfConfig = field(default_factory=UkfConfig)
    ground: GroundPriorConfig = field(default_factory=GroundPriorConfig)
    nlos: NlosConfig = field(default_factory=NlosConfig)
    empirical: EmpiricalRConfig = field(default_factory=EmpiricalRConfig)
    adaptive: AdaptiveRConfig = field(default_factory=AdaptiveRConfig)
    gnss_cov: GnssCovarianceConfig = field(default_factory=GnssCovarianceConfig)
    median: MedianSmootherConfig = field(default_factory=MedianSmootherConfig)
    ema: EmaSmootherConfig = field(default_factory=EmaSmootherConfig)
    convergence: ConvergenceConfig = field(default_factory=ConvergenceConfig)
    refined: RefinedConfig = field(default_factory=RefinedConfig)


class Published(NamedTuple):
    """One published (smoothed) estimate in the track's history.

    ``cov_m2`` is the filter's 3 x 3 position covariance at publication (row-major
    tuples); ``sigma_h_m`` = sqrt(P_xx + P_yy) and ``sigma_z_m`` = sqrt(P_zz) (eq. 19).
    ``r95_h_m`` (modes beyond the paper's) is the radius of the 95 % horizontal circle.
    """

    t_s: float
    enu_m: tuple[float, float, float]
    sigma_h_m: float
    sigma_z_m: float
    bias_m: float
    stable: bool
    accepted_index: int
    cov_m2: tuple[tuple[float, float, float], ...] | None = None
    r95_h_m: float | None = None


def position_cov(P) -> tuple[tuple[float, float, float], ...]:
    """The 3 x 3 position block of a filter covariance, as tuples."""
    return (
        (P[0][0], P[0][1], P[0][2]),
        (P[1][0], P[1][1], P[1][2]),
        (P[2][0], P[2][1], P[2][2]),
    )


class TrackObserver(Protocol):
    """Told of what a track publishes (evaluation hooks in here: the track never sees truth)."""

    def published(self, track: Track, pub: Published) -> None: ...

    def restarted(self, track: Track) -> None: ...


@dataclass
class TrackCounts:
    n_meas: int = 0
    n_bootstrap: int = 0
    n_gate: int = 0
    n_mad: int = 0
    n_nis: int = 0
    n_acc: int = 0
    n_bootstrap_attempts: int = 0
    n_restarts: int = 0


class SharedFront:
    """Mode-independent front end of one responder: MAD gate, ground window, filter runs.

    Every mode sees the same gate decisions and ground-height window, so tracks of several
    modes on one responder share one front end and each measurement is gated once. Modes
    whose filter, noise model and bootstrap agree (``baseline`` and ``ema`` differ only
    in the smoother) also share one :class:`FilterRun`. A standalone :class:`Track` makes
    its own front end. Results are cached for the latest measurement only (by identity).
    """

    def __init__(self, cfg: PipelineConfig = PipelineConfig()) -> None:
        self.cfg = cfg
        self.gate = MadGate(cfg.gate)
        self.ground: deque[float] = deque(maxlen=cfg.ground.window)
        self._m: AssociatedRange | None = None
        self._g = None
        self._gm: GatedRange | None = None
        self._ground_med: float | None = None
        self.index = -1
        self._runs: dict[tuple, FilterRun] = {}
        self._boot_cache: dict[str, tuple[int, BootstrapResult]] = {}

    def front(self, m: AssociatedRange, agl_m: float):
        """Gate result of ``m`` (computed once however many tracks ask)."""
        if m is not self._m:
            self._m = m
            self.index += 1
            self.ground.append(m.anchor_enu_m[2] - agl_m)
            self._ground_med = None
            self._g = self.gate.check(m.t_s, m.range_m)
        return self._g

    def gated(self) -> GatedRange:
        """The current measurement with its sigma_gate (one object for every mode)."""
        gm = self._gm
        if gm is None or gm.meas is not self._m:
            gm = self._gm = GatedRange(self._m, self._g.sigma_gate_m)
        return gm

    def ground_median(self) -> float:
        """z_prior = median of the last W (z_d - H_AGL), eq. (18)."""
        if self._ground_med is None:
            self._ground_med = median(self.ground)
        return self._ground_med

    def bootstrap(self, kind: BootstrapComponent, solver, samples) -> BootstrapResult:
        """One bootstrap attempt per kind and measurement: runs that have not restarted
        hold the same samples, so they share the result."""
        hit = self._boot_cache.get(kind)
        if hit is not None and hit[0] == self.index:
            return hit[1]
        res = solver.solve(list(samples))
        self._boot_cache[kind] = (self.index, res)
        return res

    def filter_run(self, spec: ModeSpec) -> FilterRun:
        """The run of ``spec``'s filter, noise model, bootstrap and ground prior (one per
        distinct combination: components compare by value)."""
        key = (spec.filter, spec.noise, spec.bootstrap, spec.ground_prior)
        run = self._runs.get(key)
        if run is None:
            run = self._runs[key] = FilterRun(spec, self.cfg, self)
        return run


# step outcomes of a FilterRun
BOOT, MAD, NIS, ACC, RESTART = range(5)


class FilterRun:
    """Bootstrap, filter and noise model of one responder (shared by modes that agree).

    The filter, noise model, bootstrap and the per-update ground pseudo-measurement are
    the spec's components. The keywords serve modes beyond the paper's (their defaults
    are the paper's pipeline): ``noise_factory`` builds the noise model (at start and at
    every restart) instead of ``spec.noise``, ``shared_bootstrap`` lets the first
    bootstrap attempt at a measurement be shared with the other runs of the front.
    """

    def __init__(
        self,
        spec: ModeSpec,
        cfg: PipelineConfig,
        front: SharedFront,
        *,
        noise_factory: Callable[[], NoiseModel] | None = None,
        shared_bootstrap: bool = True,
    ) -> None:
        self.spec = spec
        self.cfg = cfg
        self.front = front
        # a partial, not a lambda: a track (and every env holding one) must pickle
        self._noise_factory = noise_factory or functools.partial(spec.noise.make, cfg)
        self.ground_prior = spec.ground_prior and cfg.ground.enabled
        self.shared_bootstrap = shared_bootstrap
        self.counts = TrackCounts()
        self.bootstrapper = spec.bootstrap.make(cfg)
        self._boot: deque[BootstrapSample] = deque(maxlen=cfg.bootstrap.max_samples)
        self.last_bootstrap: BootstrapResult | None = None
        self.bootstrap_result: BootstrapResult | None = None
        self.bootstrap_t_s: float | None = None
        self.filter: SequentialFilter | None = None
        self.noise: NoiseModel = self._noise_factory()
        self._innovation_noise = self.noise.innovation_based
        self.generation = 0  # bumped at every restart
        self.diverged = False
        self._index = -2
        self._out = BOOT

    def step(self, m: AssociatedRange, g, agl_m: float) -> int:
        """Process ``m`` once (cached for the front end's current measurement)."""
        index = self.front.index
        if self._index == index:
            return self._out
        self._index = index
        self._out = out = self._step(m, g, agl_m)
        return out

    def _step(self, m: AssociatedRange, g, agl_m: float) -> int:
        c = self.counts
        c.n_meas += 1
        u = m.anchor_enu_m
        if self.filter is None:
            c.n_bootstrap += 1
            if g.accepted:
                self._boot.append(BootstrapSample(u, m.range_m, g.sigma_gate_m, agl_m))
                self._try_bootstrap(m.t_s)
            return BOOT
        if not g.accepted:
            c.n_gate += 1
            c.n_mad += 1
            return MAD
        f = self.filter
        gm = self.front.gated()
        noise = self.noise
        try:
            f.predict()
            if self._innovation_noise:
                res = f.update(u, m.range_m, lambda nu, hph: noise.variance(gm, nu, hph))
            else:
                res = f.update(u, m.range_m, noise.variance(gm, 0.0, 0.0))
            if not res.accepted:
                c.n_gate += 1
                c.n_nis += 1
                return NIS
            if self.ground_prior:
                f.update_height(self.front.ground_median(), self.cfg.ground.r_z_m2)
            c.n_acc += 1
        except FilterError:
            self._restart()
            return RESTART
        return ACC

    def _try_bootstrap(self, t_s: float) -> None:
        ready, _ = self.bootstrapper.ready(self._boot)
        if not ready:
            return
        self.counts.n_bootstrap_attempts += 1
        if self.generation == 0 and self.shared_bootstrap:
            res = self.front.bootstrap(self.spec.bootstrap, self.bootstrapper, self._boot)
        else:
            res = self.bootstrapper.solve(list(self._boot))
        self.last_bootstrap = res
        if not res.ok:
            return
        assert res.position_enu_m is not None
        self.bootstrap_result = res
        self.bootstrap_t_s = t_s
        self.filter = self.spec.filter.make(res.position_enu_m, self.cfg)
        self.diverged = False

    def seed(self, x: Sequence[float], P: Sequence[Sequence[float]], t_s: float) -> None:
        """Start the filter at a given state and covariance (a refinement's, in place
        of a bootstrap); later measurements count as post-bootstrap."""
        f = self.spec.filter.make(x[:3], self.cfg)
        f.x = [float(v) for v in x]
        f.P = [[float(v) for v in row] for row in P]
        self.filter = f
        self.bootstrap_t_s = t_s
        self.diverged = False

    def _restart(self) -> None:
        """Filter blew up: mark diverged and bootstrap again from new samples.

        The current measurement (already in ``n_meas``) and everything the discarded
        filter counted join ``n_bootstrap``; the post-bootstrap counts restart at zero.
        """
        c = self.counts
        c.n_bootstrap += c.n_gate + c.n_acc + 1
        c.n_gate = c.n_mad = c.n_nis = c.n_acc = 0
        c.n_restarts += 1
        self.diverged = True
        self.generation += 1
        self.filter = None
        self._boot.clear()
        self.noise = self._noise_factory()


class Track:
    """The real-time pipeline for one BSSID in one mode (sec. System Architecture).

    A track is a :class:`FilterRun` (possibly shared with other modes) plus its own
    smoother, convergence monitor and published history. A mode whose ``track`` is
    another class (``refined``: :class:`estimator.refined.RefinedTrack`) is built by
    :func:`make_track`.
    """

    candidates: tuple = ()  # (mean_enu_m, sigma_h_m, weight) of an ambiguous estimate

    def __init__(
        self,
        bssid: str,
        mode: ModeSpec,
        cfg: PipelineConfig = PipelineConfig(),
        *,
        keep_history: bool = True,
        front: SharedFront | None = None,
        observers: Sequence[TrackObserver] = (),
    ) -> None:
        if not isinstance(mode, ModeSpec):
            raise TypeError(f"a track takes a ModeSpec, not {mode!r} "
                            "(names: estimator.modes.resolve_mode)")
        if not isinstance(self, mode.track):
            raise ValueError(f"mode {mode.name!r} is a {mode.track.__name__} (make_track)")
        self.bssid = bssid
        self.observers = tuple(observers)
        self.spec = mode
        self.cfg = cfg
        self.front = front if front is not None else SharedFront(cfg)
        self.run = self._make_run()
        self.keep_history = keep_history
        self.smoother = self._make_smoother()
        self.monitor = ConvergenceMonitor(cfg.convergence)
        self.history: list[Published] = []
        self.last: Published | None = None
        self.last_stable: Published | None = None
        self._generation = 0

    def _make_run(self) -> FilterRun:
        return self.front.filter_run(self.spec)

    def _make_smoother(self) -> Smoother:
        return self.spec.smoother.make(self.cfg)

    # ------------------------------------------------------------------ processing
    def process(self, m: AssociatedRange) -> Published | None:
        """Feed one associated range (time-ordered); return the estimate it published."""
        agl = m.agl_m if m.agl_m is not None else self.cfg.agl_m
        g = self.front.front(m, agl)
        run = self.run
        out = run.step(m, g, agl)
        if run.generation != self._generation:  # the shared filter restarted
            self._generation = run.generation
            self.smoother = self._make_smoother()
            self.monitor = ConvergenceMonitor(self.cfg.convergence)
            self.last = None
            self.last_stable = None
            for obs in self.observers:
                obs.restarted(self)
        if out == ACC:
            self.monitor.on_accepted()
            return self._publish(m.t_s)
        if out in (MAD, NIS):
            self.monitor.on_rejected()
        return None

    def _publish(self, t_s: float) -> Published:
        f = self.run.filter
        assert f is not None
        P = f.P
        sigma_h = math.sqrt(P[0][0] + P[1][1])  # eq. (19)
        sigma_z = math.sqrt(P[2][2])
        pos = self.smoother.push(f.position_enu_m)
        n_acc = self.run.counts.n_acc
        stable = self.monitor.on_published(pos, sigma_h, sigma_z, n_acc)
        pub = Published(t_s, pos, sigma_h, sigma_z, f.bias_m, stable, n_acc, position_cov(P))
        self.last = pub
        if stable:
            self.last_stable = pub
        if self.keep_history:
            self.history.append(pub)
        for obs in self.observers:
            obs.published(self, pub)
        return pub

    # ------------------------------------------------------------------ outcome
    @property
    def counts(self) -> TrackCounts:
        return self.run.counts

    @property
    def reports_bias(self) -> bool:
        """Whether the reported estimate carries a range bias (the UKF has none)."""
        return self.run.filter is not None and self.run.filter.has_bias

    @property
    def filter(self) -> SequentialFilter | None:
        return self.run.filter

    @property
    def bootstrap_result(self) -> BootstrapResult | None:
        return self.run.bootstrap_result

    @property
    def last_bootstrap(self) -> BootstrapResult | None:
        return self.run.last_bootstrap

    @property
    def bootstrap_t_s(self) -> float | None:
        return self.run.bootstrap_t_s

    @property
    def status(self) -> str:
        """converged | tracking | bootstrapping | weak_geometry | diverged | no_data."""
        run = self.run
        if run.counts.n_meas == 0:
            return "no_data"
        if run.filter is not None:
            return "converged" if self.last_stable is not None else "tracking"
        if run.diverged:
            return "diverged"
        lb = run.last_bootstrap
        if lb is None or lb.status == "waiting":
            return "bootstrapping"
        return "weak_geometry" if lb.status == "weak_geometry" else "diverged"

    def reported(self) -> Published | None:
        """The estimate to report: the last stable one, else the latest filter output."""
        f = self.run.filter
        if f is None:
            return None
        if self.last_stable is not None:
            return self.last_stable
        if self.last is not None:
            return self.last
        P = f.P
        return Published(
            self.run.bootstrap_t_s or 0.0,
            f.position_enu_m,
            math.sqrt(P[0][0] + P[1][1]),
            math.sqrt(P[2][2]),
            f.bias_m,
            False,
            0,
            position_cov(P),
        )


@dataclass(frozen=True)
class ModeSpec:
    """A mode: a composition of component objects (sec. Measurement-Noise Configurations).

    ``filter`` builds the sequential filter (:class:`estimator.filters.Iekf`, ``Ukf``),
    ``noise`` the measurement-noise model (:mod:`estimator.noise`: ``Constant``,
    ``Nlos``, ``Empirical``, ``Adaptive``...), ``smoother`` the output smoother
    (:mod:`estimator.smoothing`: ``Median``, ``Ema``), ``bootstrap`` the initialisation
    (:mod:`estimator.bootstrap`: ``GaussNewton``, ``Robust``), each from its section of
    the :class:`PipelineConfig`. ``ground_prior``: the ground-height pseudo-measurement
    after each accepted update (eq. 18). ``track`` is the track class that runs the mode
    (:class:`Track`; mode ``refined`` has its own). ``paper``: one of the paper's six.
    Components compare by value, so modes that agree on filter, noise, bootstrap and
    ground prior (``baseline`` and ``ema``) share one filter run. Names map to specs in
    :data:`estimator.modes.MODES` only.
    """

    name: str
    filter: FilterComponent = field(default_factory=Iekf)
    noise: NoiseComponent = field(default_factory=Constant)
    smoother: SmootherComponent = field(default_factory=Median)
    bootstrap: BootstrapComponent = field(default_factory=GaussNewton)
    ground_prior: bool = True
    paper: bool = True
    track: type[Track] = Track


def make_track(bssid: str, mode: ModeSpec, cfg: PipelineConfig = PipelineConfig(), **kw
               ) -> Track:
    """The track that runs ``mode`` (its ``track`` class) for one responder."""
    return mode.track(bssid, mode, cfg, **kw)
