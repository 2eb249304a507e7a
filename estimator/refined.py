"""Mode ``refined`` (alias ``best``): a sequential front with a robust batch back end (ours).

Real time: every range passes a MAD gate of its own agent (eqs. 3-4; the track's
shared window would mix the agents' ranges, which differ by their geometry) and goes
to a static IEKF front (Q = 0, R from the agent's
calibrated Empirical-R shape, no per-update ground prior, :class:`RefinedConfig`) whose
estimate is published after each accepted update. Periodically (whenever the gated
ranges have grown by 30 %) and at the end, :func:`estimator.batch.solve` refines over
every gated range of the responder with per-agent range and GNSS biases and the ground
prior used once; the front is then re-seeded with the refined state and its range-only
covariance, and later ranges are corrected by the refined per-agent offsets and GNSS
biases before they reach it (so several agents feed one consistent front).

Uncertainty: the reported covariance is the refinement's posterior, in which every
agent's GNSS bias is a Gauss-Markov nuisance parameter (:class:`estimator.batch.
GnssErrorModel`); between refinements, the front's covariance plus the GNSS part of the
last refinement. ``r95_h_m`` is the radius of its 95 % horizontal circle.

Verdict (``status``): ``converged`` only when the geometry (kappa_H), the residuals
(per-agent scale and inlier fraction) and a multi-start check for other minima support
it (:class:`RefinedConfig`); ``ambiguous`` when several minima keep a relative weight
>= 1 % (e.g. both sides of a straight pass): the reported position is then their
mixture mean and covariance, and :attr:`RefinedTrack.candidates` lists them.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from estimator.batch import (
    Minimum,
    RangeBuffer,
    Solution,
    make_layout,
    pass_starts,
    r_circle_m,
    search_minima,
    solve,
)
from estimator.filters import IEKF3D
from estimator.gate import MadGate
from estimator.geometry import horizontal_condition_number
from estimator.noise import CalibratedR, GatedRange, empirical_model_m2
from estimator.pipeline import (
    ACC,
    FilterRun,
    ModeSpec,
    PipelineConfig,
    Published,
    SharedFront,
    Track,
    TrackObserver,
)
from estimator.records import AssociatedRange
from estimator.smoothing import Unsmoothed

CandidateEnu = tuple[tuple[float, float, float], float, float]  # mean ENU, sigma_h, weight


@dataclass(frozen=True)
class RefinedFront:
    """Mode ``refined``'s filter: :class:`IEKF3D` with ``cfg.refined.front`` (Q = 0)."""

    has_bias = True

    def make(self, position_enu_m: Sequence[float], cfg: PipelineConfig) -> IEKF3D:
        return IEKF3D(position_enu_m, cfg.refined.front)


@dataclass(frozen=True)
class CalibratedNoise:
    """Mode ``refined``'s noise: :class:`CalibratedR` with the track's calibrated
    per-agent scales (``scales``, which :class:`RefinedTrack` passes; 1 without)."""

    def make(self, cfg: PipelineConfig, scales: dict[str, float] | None = None
             ) -> CalibratedR:
        return CalibratedR(cfg.empirical, {} if scales is None else scales)


def _tuple3(M: np.ndarray) -> tuple[tuple[float, float, float], ...]:
    return tuple((float(r[0]), float(r[1]), float(r[2])) for r in M)


class _AgentGates:
    """The front a :class:`FilterRun` asks for, for a track that gates each agent in its
    own MAD window: the measurement index, the gated range (with its sigma_gate)."""

    def __init__(self, cfg: PipelineConfig) -> None:
        self.cfg = cfg
        self.index = -1
        self._gates: dict[str, MadGate] = {}
        self._gm: GatedRange | None = None

    def front(self, m: AssociatedRange):
        gate = self._gates.get(m.agent)
        if gate is None:
            gate = self._gates[m.agent] = MadGate(self.cfg.gate)
        g = gate.check(m.t_s, m.range_m)
        self.index += 1
        self._gm = GatedRange(m, g.sigma_gate_m)
        return g

    def gated(self) -> GatedRange:
        assert self._gm is not None
        return self._gm


class RefinedTrack(Track):
    """One responder in mode ``refined``: front, buffer of gated ranges, refinements."""

    def __init__(
        self,
        bssid: str,
        mode: ModeSpec | None = None,
        cfg: PipelineConfig = PipelineConfig(),
        *,
        keep_history: bool = True,
        front: SharedFront | None = None,
        observers: Sequence[TrackObserver] = (),
    ) -> None:
        self.rcfg = cfg.refined
        self.scales: dict[str, float] = {}  # agent -> calibrated noise scale s_a
        self.buffer = RangeBuffer()
        self.solution: Solution | None = None
        self.minima: list[Minimum] = []
        self.verdict: str | None = None
        self.candidates: tuple[CandidateEnu, ...] = ()
        self.n_refinements = 0
        self._next_n = self.rcfg.min_n  # no refinement on fewer ranges than a verdict needs
        self._n_refined = 0
        self._n_checked = 0  # ranges at the last check for other minima
        self._corr: dict[str, tuple] = {}  # agent -> (offset, knot times, knots) or const
        self._gnss_cov: tuple[tuple[float, ...], ...] = ((0.0,) * 3,) * 3
        self._refined_pub: Published | None = None
        self._agent_gates = _AgentGates(cfg)
        super().__init__(bssid, REFINED if mode is None else mode, cfg,
                         keep_history=keep_history, front=front, observers=observers)

    def _make_run(self) -> FilterRun:
        cfg = self.cfg
        noise = self.spec.noise
        return FilterRun(
            self.spec,
            cfg,
            self._agent_gates,  # type: ignore[arg-type]  # index and gated() only
            # a partial, not a lambda (a track must pickle); the scales dict is updated
            # in place: the partial sees every calibration
            noise_factory=functools.partial(noise.make, cfg, self.scales),
            shared_bootstrap=False,
        )

    # ------------------------------------------------------------------ processing
    def process(self, m: AssociatedRange) -> Published | None:
        agl = m.agl_m if m.agl_m is not None else self.cfg.agl_m
        g = self._agent_gates.front(m)
        if g.accepted:
            self.buffer.append(
                m.t_s, m.anchor_enu_m, m.range_m,
                empirical_model_m2(m.range_m, m.rssi_dbm, self.cfg.empirical), agl,
                m.agent, m.anchor_acc_m, m.anchor_vacc_m, m.anchor_fix,
            )
        run = self.run
        out = run.step(self._corrected(m), g, agl)
        if run.generation != self._generation:  # the front restarted; the buffer stays
            self._generation = run.generation
            self.last = self._refined_pub
            for obs in self.observers:
                obs.restarted(self)
        pub = self._publish_front(m.t_s) if out == ACC else None
        if self._due():
            pub = self.refine(m.t_s) or pub
        return pub

    def _corrected(self, m: AssociatedRange) -> AssociatedRange:
        """``m`` with the refined agent offset (b_a - b_1) and GNSS bias removed."""
        c = self._corr.get(m.agent)
        if c is None:
            return m
        off, kt, B = c
        if len(kt) == 1 or m.t_s <= kt[0]:
            bx, by, bz = B[0]
        elif m.t_s >= kt[-1]:
            bx, by, bz = B[-1]
        else:
            j = int(np.searchsorted(kt, m.t_s, side="right") - 1)
            f = (m.t_s - kt[j]) / (kt[j + 1] - kt[j])
            bx, by, bz = ((1.0 - f) * a + f * b for a, b in zip(B[j], B[j + 1], strict=True))
        u = m.anchor_enu_m
        return AssociatedRange(
            t_s=m.t_s, bssid=m.bssid, range_m=m.range_m - off, rssi_dbm=m.rssi_dbm,
            anchor_enu_m=(u[0] - bx, u[1] - by, u[2] - bz), anchor_acc_m=m.anchor_acc_m,
            anchor_vacc_m=m.anchor_vacc_m, agl_m=m.agl_m, agent=m.agent,
            anchor_fix=m.anchor_fix,
        )

    def _due(self) -> bool:
        if self.buffer.n < max(self._next_n, 4):
            return False
        run = self.run
        if run.filter is not None:
            return True
        lb = run.last_bootstrap
        return lb is not None and lb.status != "waiting"

    def _publish_front(self, t_s: float) -> Published:
        f = self.run.filter
        assert f is not None
        (p00, p01, p02, _), (_, p11, p12, _), (_, _, p22, _), _ = f.P
        (g00, g01, g02), (_, g11, g12), (_, _, g22) = self._gnss_cov
        c01, c02, c12 = p01 + g01, p02 + g02, p12 + g12
        C = ((p00 + g00, c01, c02), (c01, p11 + g11, c12), (c02, c12, p22 + g22))
        pub = Published(
            t_s, f.position_enu_m, math.sqrt(p00 + g00 + p11 + g11), math.sqrt(p22 + g22),
            f.bias_m, self.verdict == "converged", self.run.counts.n_acc, C,
        )
        return self._emit(pub)

    def _emit(self, pub: Published) -> Published:
        self.last = pub
        if pub.stable:
            self.last_stable = pub
        if self.keep_history:
            self.history.append(pub)
        for obs in self.observers:
            obs.published(self, pub)
        return pub

    # ------------------------------------------------------------------ refinement
    def refine(self, t_s: float | None = None, *, final: bool = False) -> Published | None:
        """Refine over every gated range now; returns the refined estimate (published).

        ``final`` (the end of the data) always checks for other minima.
        """
        data = self.buffer.view()
        if data.n < 4:
            return None
        rc = self.rcfg
        bcfg = rc.batch
        lay = make_layout(data, bcfg)
        scales0 = [self.scales.get(a, 1.0) for a in data.agents]
        f = self.run.filter
        prev = self.solution
        extra: list[np.ndarray] = []
        # periodic refinements refit after a scale change of > 20 %, the final one of > 5 %
        tol = 0.05 if final else 0.2
        if prev is not None and prev.layout.dim == lay.dim:
            main = solve(data, prev.theta[:4], bcfg, scales=scales0, theta0=prev.theta,
                         layout=lay, recalibrate_tol=tol)
        elif f is not None:
            main = solve(data, (*f.position_enu_m, f.bias_m), bcfg, scales=scales0,
                         layout=lay, recalibrate_tol=tol)
        else:
            starts = pass_starts(data, lay)
            main = solve(data, starts[0], bcfg, scales=scales0, layout=lay)
            extra = starts[1:]
        kappa = horizontal_condition_number(data.u, 1.0 / data.var_e)
        check = (final or f is None or self._n_checked == 0 or len(self.minima) > 1
                 or data.n >= 2 * self._n_checked)
        if check:
            minima = search_minima(data, main, bcfg, extra_starts=extra,
                                   min_weight=rc.min_weight,
                                   straight_pass=not kappa < rc.max_kappa)
            self._n_checked = data.n
        else:
            minima = [Minimum(main, 1.0)]
        best = minima[0].solution
        self.solution, self.minima = best, minima
        self.n_refinements += 1
        self._n_refined = data.n
        self._next_n = max(data.n + rc.min_new, math.ceil(rc.growth * data.n))
        for a, s in zip(data.agents, best.scales, strict=True):
            self.scales[a] = float(s)
        A = len(data.agents)
        b0 = best.theta[3]
        Bk = best.theta[3 + A:].reshape(-1, 3)
        self._corr = {}
        for a, name in enumerate(data.agents):
            r0 = lay.knot_row[a]
            kt = lay.knots_t[a]
            knots = [tuple(float(v) for v in Bk[r0 + k]) for k in range(kt.size)]
            off = float(best.theta[3 + a] - b0)
            if abs(off) > 1e-9 or max(abs(v) for k in knots for v in k) > 1e-6:
                self._corr[name] = (off, [float(t) for t in kt], knots)
        self._gnss_cov = _tuple3(best.cov[:3, :3] - best.cov_cond[:3, :3])
        t_pub = t_s if t_s is not None else float(data.t[-1])
        pub = self._refined_publication(data, t_pub, kappa)
        x = [float(best.theta[0]), float(best.theta[1]), float(best.theta[2]), float(b0)]
        P = best.cov_cond[:4, :4].tolist()
        if f is not None:  # re-seed the front with the refined state, range-only covariance
            f.x = x
            f.P = P
        elif self.verdict in ("converged", "tracking"):  # the refinement bootstraps it
            self.run.seed(x, P, t_pub)
        self._refined_pub = pub
        return self._emit(pub)

    def _refined_publication(self, data, t_s: float, kappa: float) -> Published:
        rc = self.rcfg
        minima = self.minima
        if len(minima) == 1:
            sol = minima[0].solution
            mean = sol.theta[:3]
            C = sol.cov_p
            self.candidates = ()
        else:  # mixture moments: covers every candidate, picks none
            w = np.array([m.weight for m in minima])
            mus = np.array([m.solution.theta[:3] for m in minima])
            mean = w @ mus
            C = sum(wk * (m.solution.cov_p + np.outer(mu - mean, mu - mean))
                    for wk, m, mu in zip(w, minima, mus, strict=True))
            self.candidates = tuple(
                ((float(mu[0]), float(mu[1]), float(mu[2])),
                 math.sqrt(float(m.solution.cov_p[0, 0] + m.solution.cov_p[1, 1])), float(wk))
                for wk, m, mu in zip(w, minima, mus, strict=True)
            )
        # the 95 % circle lies inside the isotropic one of the major sigma
        r95_max = math.sqrt(float(np.linalg.eigvalsh(C[:2, :2])[-1]) * -2.0 * math.log(0.05))
        best = minima[0].solution
        n_by_agent = np.bincount(data.agent, minlength=len(data.agents))
        counted = [s for s, n in zip(best.scales, n_by_agent, strict=True) if n >= 10]
        if len(minima) > 1:
            verdict = "ambiguous"
        elif not kappa < rc.max_kappa:
            verdict = "weak_geometry"
        elif (data.n >= rc.min_n and (not counted or max(counted) <= rc.max_scale)
              and best.inlier_fraction >= rc.min_inlier_fraction
              and (r95_max <= rc.max_r95_m or r_circle_m(C[:2, :2]) <= rc.max_r95_m)):
            verdict = "converged"
        else:
            verdict = "tracking"
        self.verdict = verdict
        return Published(
            t_s, (float(mean[0]), float(mean[1]), float(mean[2])),
            math.sqrt(float(C[0, 0] + C[1, 1])), math.sqrt(float(C[2, 2])), float(best.theta[3]),
            verdict == "converged", self.run.counts.n_acc, _tuple3(C),
        )

    def finalize(self) -> Published | None:
        """The final refinement over everything gated since the last one (end of data)."""
        if self.buffer.n > self._n_refined and self.buffer.n >= 4 and (
            self.run.filter is not None
            or (self.run.last_bootstrap is not None
                and self.run.last_bootstrap.status != "waiting")
        ):
            return self.refine(final=True)
        return None

    # ------------------------------------------------------------------ outcome
    @property
    def status(self) -> str:
        if self.run.counts.n_meas == 0:
            return "no_data"
        if self.verdict is not None:
            return self.verdict
        return super().status

    @property
    def reports_bias(self) -> bool:
        return self.last is not None

    def reported(self) -> Published | None:
        """The latest estimate (front or refinement) with its 95 % circle; while the
        verdict is ``ambiguous``, the refinement's mixture (the front follows one side)."""
        amb = self.verdict == "ambiguous"
        pub = self._refined_pub if amb else self.last
        if pub is None:
            return None
        if pub.r95_h_m is None and pub.cov_m2 is not None:
            C = np.array(pub.cov_m2)
            pub = pub._replace(r95_h_m=r_circle_m(C[:2, :2], 0.95))
            if amb:
                self._refined_pub = pub
            else:
                self.last = pub
        return pub


REFINED = ModeSpec(
    "refined",
    filter=RefinedFront(),
    noise=CalibratedNoise(),
    smoother=Unsmoothed(),
    ground_prior=False,
    paper=False,
    track=RefinedTrack,
)
"""Mode ``refined`` (issue 8): a static IEKF front with calibrated R and no per-update
ground prior, refined periodically and at the end by a robust batch over every gated
range with per-agent range and GNSS biases (:mod:`estimator.batch`)."""
