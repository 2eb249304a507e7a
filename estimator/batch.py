"""Robust batch refinement over a whole track: the information-limit back end (ours).

The paper's filters are sequential and carry its known weaknesses (sec. Discussion):
a ground-height pseudo-measurement applied after every update as if independent
(eq. 18), a random walk for a static responder (eq. 12), and a covariance that ignores
the GNSS anchor error, which is correlated over minutes and does not average out like
range noise (sec. Filter Overconfidence). :func:`solve` is the maximum a-posteriori
fit of every gated range of one responder, with

* state [x, y, z, b_1..b_A, beta]: the responder, one range bias b_a per agent (eq. 2's
  b, per initiator: each phone has its own offset), and each agent's GNSS bias beta_a(t),
  3 axes, linear between knots ``knot_spacing_s`` apart (one constant knot for a
  shorter track);
* range model d_i = |p - (u_i - beta_a(t_i))| + b_a + n_i (the anchor u_i is the
  logged GNSS position, truth + beta), n_i ~ N(0, s_a^2 sigma_E^2(d_i, RSSI_i)) with
  the Empirical-R shape sigma_E^2 = sigma_0^2 + alpha d^2 + beta q^2 (eq. 23) and a
  per-agent scale s_a calibrated from the agent's own residuals (robust MAD, shrunk
  towards 1 with ``scale_prior_n`` pseudo-samples);
* priors used once: beta_a ~ Gauss-Markov N(0, sigma_gnss^2 exp(-|dt| / tau)) per axis
  (:class:`GnssErrorModel`, from the fix accuracy and type), b_a ~ N(0, (2 m)^2) (the
  paper's P0 for the bias), and the ground height p_z ~ N(median(z_d - H_AGL), 5 m^2)
  (eq. 18's value and R_z, once per agent with its variance times the agent count, so
  the prior counts once overall);
* a Cauchy loss on the range residuals (iteratively reweighted Gauss-Newton with
  Levenberg damping), as the paper's offline fix of AP_AB.

Its posterior covariance is honest about the GNSS error: with one agent the bias is a
pure translation, so the horizontal covariance is the range-only one plus the GNSS
bias covariance; with several agents each agent's bias is shrunk by the others, which
weights each agent by its own GNSS quality and measured noise (multi-agent fusion).

:func:`search_minima` checks for other minima (multi-start from the mirror images about
the anchors' principal axes, and both sides of a straight pass) and weighs them by
their Laplace-approximated evidence; :func:`r_circle_m` gives the radius of a
probability circle of a 2 x 2 covariance (``r95_h_m``).
"""

from __future__ import annotations

import math
from array import array
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from estimator.measurement import jacobian_rows, range_of_difference
from estimator.noise import EmpiricalRConfig

RTK_FIXES = ("rtk_fixed",)
FLOAT_FIXES = ("rtk_float", "dgps")


@dataclass(frozen=True, kw_only=True)
class GnssErrorModel:
    """Per-axis GNSS bias sigma of an agent from its logged accuracy and fix type.

    Standalone: ``acc_m`` is an HDOP-derived proxy, not a covariance; the paper logged
    0.77-1.02 while the horizontal error was 1.5-3 m (sec. Experimental Setup), i.e. a
    per-axis sigma of about 1.75 x the proxy (2-D RMS / sqrt 2 over the proxy, both at
    mid-range). RTK fixed: the receiver's accuracy is a covariance, taken x 1.5 with a
    2 cm floor. Vertical: ``vacc_m`` with the same factor, else ``vertical_ratio`` x
    horizontal. The error is a first-order Gauss-Markov process with correlation time
    ``tau_s`` (20 min, typical of standalone multi-band receivers: ionosphere and
    orbit/clock errors change over tens of minutes).
    """

    standalone_scale: float = 1.75
    standalone_floor_m: float = 0.5
    float_scale: float = 1.75  # dgps, rtk_float
    float_floor_m: float = 0.1
    rtk_scale: float = 1.5
    rtk_floor_m: float = 0.02
    vertical_ratio: float = 1.7
    tau_s: float = 1200.0
    knot_spacing_s: float = 300.0

    def sigmas_m(self, acc_m: float, vacc_m: float | None, fix: str | None
                 ) -> tuple[float, float]:
        """(horizontal per-axis, vertical) bias sigma for fixes of this accuracy and type."""
        if fix in RTK_FIXES:
            k, floor = self.rtk_scale, self.rtk_floor_m
        elif fix in FLOAT_FIXES:
            k, floor = self.float_scale, self.float_floor_m
        else:
            k, floor = self.standalone_scale, self.standalone_floor_m
        sh = max(floor, k * acc_m)
        sv = max(floor, k * vacc_m) if vacc_m is not None else self.vertical_ratio * sh
        return sh, sv


@dataclass(frozen=True, kw_only=True)
class BatchConfig:
    """Robust MAP refinement (module docstring); defaults are documented choices."""

    noise: EmpiricalRConfig = field(default_factory=EmpiricalRConfig)  # sigma_E shape
    gnss: GnssErrorModel = field(default_factory=GnssErrorModel)
    cauchy_c: float = 2.385  # Cauchy constant in calibrated sigmas (95 % efficiency)
    ground_sigma_m: float = 5.0  # eq. (18)'s R_z = (5 m)^2, used once
    bias_sigma_m: float = 2.0  # the paper's P0 for b: (2 m)^2
    scale_prior_n: float = 10.0  # pseudo-samples at s = 1 (the paper's Empirical-R)
    max_iter: int = 30
    tol_m: float = 1e-3  # position step at which the fit has converged
    min_scale: float = 0.05


class RangeBuffer:
    """Every gated range of one responder (columns grow as packed C arrays, 88 bytes a
    range: a log of hours holds ~1e6; numpy arrays on demand)."""

    def __init__(self) -> None:
        self.n = 0
        self._t = array("d")
        self._u = array("d")  # x, y, z of each anchor
        self._d = array("d")
        self._var_e = array("d")  # sigma_E^2 (eq. 23)
        self._ground = array("d")  # z_d - H_AGL
        self._agent = array("q")
        self._acc = array("d")
        self._vacc = array("d")  # nan if not logged
        self.agents: list[str] = []
        self._index: dict[str, int] = {}
        self._fixes: list[dict] = []  # per agent: fix type -> count
        self._view: RangeData | None = None

    def append(self, t_s: float, anchor: Sequence[float], range_m: float, var_e_m2: float,
               agl_m: float, agent: str, acc_m: float, vacc_m: float | None,
               fix: str | None) -> None:
        k = self._index.get(agent)
        if k is None:
            k = self._index[agent] = len(self.agents)
            self.agents.append(agent)
            self._fixes.append({})
        self._t.append(t_s)
        self._u.extend(anchor[:3])
        self._d.append(range_m)
        self._var_e.append(var_e_m2)
        self._ground.append(anchor[2] - agl_m)
        self._agent.append(k)
        self._acc.append(acc_m)
        self._vacc.append(math.nan if vacc_m is None else vacc_m)
        f = self._fixes[k]
        f[fix] = f.get(fix, 0) + 1
        self.n += 1

    def view(self) -> RangeData:
        v = self._view
        if v is None or v.n != self.n:
            v = self._view = RangeData(
                np.array(self._t), np.array(self._u, float).reshape(-1, 3), np.array(self._d),
                np.array(self._var_e), np.array(self._ground), np.array(self._agent, np.int64),
                np.array(self._acc), np.array(self._vacc), tuple(self.agents),
                tuple(max(f, key=f.get) for f in self._fixes))
        return v


@dataclass(frozen=True)
class RangeData:
    t: np.ndarray
    u: np.ndarray
    d: np.ndarray
    var_e: np.ndarray
    ground: np.ndarray
    agent: np.ndarray
    acc: np.ndarray
    vacc: np.ndarray
    agents: tuple[str, ...]
    fix: tuple[str | None, ...]  # each agent's most frequent fix type

    @property
    def n(self) -> int:
        return int(self.d.size)


@dataclass(frozen=True)
class Layout:
    """Where each agent's parameters sit in the state [p, b_1..b_A, beta], and priors.

    beta is a (K x 3) matrix of knots, all agents' knots stacked (agent-major), flattened
    row-major into the state after the A biases.
    """

    n_agents: int
    knots_t: tuple[np.ndarray, ...]  # per agent, knot times
    knot_row: tuple[int, ...]  # per agent, its first knot's row in the K x 3 matrix
    n_knots: int
    dim: int
    j0: np.ndarray  # per measurement: knot rows before / after it and their weights
    j1: np.ndarray
    w0: np.ndarray
    w1: np.ndarray
    cols0: np.ndarray  # (n, 3) state columns of beta at j0 and j1
    cols1: np.ndarray
    single_knot: bool
    prior_jac: np.ndarray  # linear priors: r_prior = prior_jac @ theta - prior_y
    prior_y: np.ndarray
    sigma_gnss: tuple[tuple[float, float], ...]  # per agent (horizontal, vertical)
    ground_m: tuple[float, ...]  # per agent median(z_d - H_AGL), eq. (18)


def make_layout(data: RangeData, cfg: BatchConfig = BatchConfig()) -> Layout:
    """Knots, GNSS priors (Gauss-Markov, per agent and axis) and ground priors of ``data``."""
    gm = cfg.gnss
    A = len(data.agents)
    n = data.n
    knots, rows, sig, grounds = [], [], [], []
    j0 = np.zeros(n, dtype=np.int64)
    j1 = np.zeros(n, dtype=np.int64)
    w0 = np.ones(n)
    w1 = np.zeros(n)
    omega = []  # per agent, mean interpolation weight of each knot
    K = 0
    for a in range(A):
        sel = data.agent == a
        ta = data.t[sel]
        t0, t1 = float(ta.min()), float(ta.max())
        span = t1 - t0
        if span <= gm.knot_spacing_s:
            kt = np.array([0.5 * (t0 + t1)])
        else:
            kt = np.linspace(t0, t1, math.ceil(span / gm.knot_spacing_s) + 1)
        knots.append(kt)
        rows.append(K)
        Ka = kt.size
        if Ka == 1:
            j0[sel] = K
            j1[sel] = K
            omega.append(np.ones(1))
        else:
            j = np.clip(np.searchsorted(kt, ta, side="right") - 1, 0, Ka - 2)
            f = (ta - kt[j]) / (kt[j + 1] - kt[j])
            j0[sel] = K + j
            j1[sel] = K + j + 1
            w0[sel] = 1.0 - f
            w1[sel] = f
            om = np.bincount(j, 1.0 - f, Ka) + np.bincount(j + 1, f, Ka)
            omega.append(om / ta.size)
        vacc = data.vacc[sel]
        vv = float(np.median(vacc)) if np.all(np.isfinite(vacc)) else None
        sig.append(gm.sigmas_m(float(np.median(data.acc[sel])), vv, data.fix[a]))
        grounds.append(float(np.median(data.ground[sel])))
        K += Ka
    dim = 3 + A + 3 * K
    ax = np.arange(3)
    cols0 = 3 + A + 3 * j0[:, None] + ax
    cols1 = 3 + A + 3 * j1[:, None] + ax
    # linear priors: GNSS bias (whitened Gauss-Markov), range bias, ground height
    npri = 3 * K + A + A
    Jp = np.zeros((npri, dim))
    yp = np.zeros(npri)
    for a in range(A):
        kt = knots[a]
        corr = np.exp(-np.abs(kt[:, None] - kt[None, :]) / gm.tau_s)
        Ui = np.linalg.cholesky(np.linalg.inv(corr)).T  # Ui^T Ui = corr^-1
        for axis, s in enumerate((sig[a][0], sig[a][0], sig[a][1])):
            idx = 3 + A + 3 * (rows[a] + np.arange(kt.size)) + axis
            prow = 3 * rows[a] + axis + 3 * np.arange(kt.size)
            Jp[np.ix_(prow, idx)] = Ui / s
    for a in range(A):
        Jp[3 * K + a, 3 + a] = 1.0 / cfg.bias_sigma_m
    gs = cfg.ground_sigma_m * math.sqrt(A)  # once overall, shared by the agents
    for a in range(A):
        r = 3 * K + A + a
        Jp[r, 2] = 1.0 / gs
        Jp[r, 3 + A + 3 * (rows[a] + np.arange(knots[a].size)) + 2] = omega[a] / gs
        yp[r] = grounds[a] / gs
    return Layout(A, tuple(knots), tuple(rows), K, dim, j0, j1, w0, w1, cols0, cols1,
                  all(k.size == 1 for k in knots), Jp, yp, tuple(sig), tuple(grounds))


@dataclass
class Solution:
    """One minimum of the refinement: state, covariances and diagnostics."""

    theta: np.ndarray
    cov: np.ndarray  # full posterior covariance (GNSS biases marginalised: honest)
    cov_cond: np.ndarray  # covariance of [p, b_1..b_A] with the GNSS biases held fixed
    cost: float  # robust negative log-posterior (Cauchy ranges + priors)
    scales: np.ndarray  # per agent s_a
    e: np.ndarray  # normalised range residuals at the solution
    layout: Layout
    iterations: int

    @property
    def position_enu_m(self) -> tuple[float, float, float]:
        return float(self.theta[0]), float(self.theta[1]), float(self.theta[2])

    @property
    def cov_p(self) -> np.ndarray:
        return self.cov[:3, :3]

    @property
    def n(self) -> int:
        return int(self.e.size)

    @property
    def inlier_fraction(self) -> float:
        return float(np.mean(np.abs(self.e) < 3.0)) if self.e.size else 0.0

    @property
    def log_evidence(self) -> float:
        """Laplace approximation: -cost + log det(cov) / 2 (same state for all minima)."""
        sign, logdet = np.linalg.slogdet(self.cov)
        return -self.cost + 0.5 * logdet if sign > 0 else -math.inf

    def bias_m(self, agent: int = 0) -> float:
        return float(self.theta[3 + agent])

    def gnss_bias_m(self, agent: int, t_s: float) -> np.ndarray:
        """beta_a(t) (3,), held at the end knots outside the agent's span."""
        lay = self.layout
        kt = lay.knots_t[agent]
        B = self.theta[3 + lay.n_agents:].reshape(-1, 3)
        r0 = lay.knot_row[agent]
        if kt.size == 1 or t_s <= kt[0]:
            return B[r0].copy()
        if t_s >= kt[-1]:
            return B[r0 + kt.size - 1].copy()
        j = int(np.searchsorted(kt, t_s, side="right") - 1)
        f = (t_s - kt[j]) / (kt[j + 1] - kt[j])
        return (1.0 - f) * B[r0 + j] + f * B[r0 + j + 1]


# the normal equations' Jacobian is built in row blocks of at most this many bytes: a
# log of hours holds ~1e6 ranges and ~100 GNSS-bias knots (dense: 3 GB)
NORMAL_BLOCK_BYTES = 32 << 20


class _Problem:
    """Residuals and Jacobians of one data set under fixed per-agent scales."""

    def __init__(self, data: RangeData, lay: Layout, scales: np.ndarray, cfg: BatchConfig):
        self.data, self.lay, self.cfg = data, lay, cfg
        s = np.maximum(np.asarray(scales, float), cfg.min_scale)
        self.inv_sig = 1.0 / (s[data.agent] * np.sqrt(data.var_e))
        self.rows = np.arange(data.n)
        self.bcol = 3 + data.agent
        self.c = cfg.cauchy_c

    def residuals(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        lay, d = self.lay, self.data
        B = theta[3 + lay.n_agents:].reshape(-1, 3)
        beta = B[lay.j0] if lay.single_knot else (
            B[lay.j0] * lay.w0[:, None] + B[lay.j1] * lay.w1[:, None])
        diff = theta[:3] - d.u + beta  # p - (u - beta_a(t)): the anchor corrected
        r = range_of_difference(diff)
        e = (r + theta[self.bcol] - d.d) * self.inv_sig
        return e, diff, r

    def jacobian(self, diff: np.ndarray, r: np.ndarray, rows: slice = slice(None)
                 ) -> np.ndarray:
        """The whitened Jacobian's ``rows`` (default: all), dense."""
        lay = self.lay
        inv = self.inv_sig[rows]
        Hs = jacobian_rows(diff[rows], r[rows], scale=inv)  # eq. (14)'s rows, whitened
        idx = self.rows[: Hs.shape[0]]
        J = np.zeros((Hs.shape[0], lay.dim))
        J[:, :3] = Hs
        J[idx, self.bcol[rows]] = inv
        ii = idx[:, None]
        if lay.single_knot:
            J[ii, lay.cols0[rows]] = Hs
        else:
            J[ii, lay.cols0[rows]] = Hs * lay.w0[rows, None]
            J[ii, lay.cols1[rows]] += Hs * lay.w1[rows, None]
        return J

    def objective(self, theta: np.ndarray, e: np.ndarray) -> float:
        c = self.c
        rp = self.lay.prior_jac @ theta - self.lay.prior_y
        return 0.5 * c * c * float(np.log1p((e / c) ** 2).sum()) + 0.5 * float(rp @ rp)

    def normal(self, theta, e, diff, r):
        """The IRLS normal equations (N, g), the Jacobian built in row blocks of at most
        NORMAL_BLOCK_BYTES (a log of ordinary length is one block)."""
        w = 1.0 / (1.0 + (e / self.c) ** 2)
        Jp = self.lay.prior_jac
        rp = Jp @ theta - self.lay.prior_y
        n, dim = self.data.n, self.lay.dim
        step = max(1, NORMAL_BLOCK_BYTES // (16 * dim))  # J and J * w
        N, g = np.zeros((dim, dim)), np.zeros(dim)
        for i in range(0, max(n, 1), step):
            rows = slice(i, i + step)
            J = self.jacobian(diff, r, rows)
            Jw = J * w[rows, None]
            if i == 0:
                N, g = Jw.T @ J, Jw.T @ e[rows]
            else:
                N += Jw.T @ J
                g += Jw.T @ e[rows]
        return N + Jp.T @ Jp, g + Jp.T @ rp

    def minimise(self, theta: np.ndarray, max_iter: int, *,
                 stop_near: tuple[np.ndarray, float] | None = None,
                 hold_xy: bool = False) -> tuple[np.ndarray, int]:
        """Iteratively reweighted Gauss-Newton with Levenberg damping (cost never rises).

        ``stop_near`` = (xy, radius): stop once the horizontal position comes within
        ``radius`` of ``xy`` (a multi-start that falls back into a known basin).
        ``hold_xy``: the horizontal position stays put (a profile over the rest).
        """
        e, diff, r = self.residuals(theta)
        f = self.objective(theta, e)
        mu = 1e-6
        it = 0
        free = slice(2, None) if hold_xy else slice(None)
        for it in range(1, max_iter + 1):
            N, g = self.normal(theta, e, diff, r)
            N, g = N[free, free], g[free]
            dN = np.diag(N)
            while True:
                try:
                    step = np.zeros_like(theta)
                    step[free] = -np.linalg.solve(N + mu * np.diag(dN), g)
                except np.linalg.LinAlgError:
                    step = None
                if step is not None:
                    cand = theta + step
                    e2, diff2, r2 = self.residuals(cand)
                    f2 = self.objective(cand, e2)
                    if f2 <= f + 1e-12 * abs(f):
                        break
                mu *= 10.0
                if mu > 1e6:
                    return theta, it
            theta, e, diff, r, f = cand, e2, diff2, r2, f2
            mu = max(mu * 0.1, 1e-9)
            if float(np.abs(step[:4]).max()) < self.cfg.tol_m:
                break
            if stop_near is not None and math.dist(theta[:2], stop_near[0]) < stop_near[1]:
                break
        return theta, it

    def solution(self, theta: np.ndarray, scales: np.ndarray, iterations: int) -> Solution:
        e, diff, r = self.residuals(theta)
        N, _ = self.normal(theta, e, diff, r)
        cov = _inv_spd(N)
        m = 3 + self.lay.n_agents
        cov_cond = _inv_spd(N[:m, :m])
        return Solution(theta, cov, cov_cond, self.objective(theta, e),
                        np.asarray(scales, float), e, self.lay, iterations)


def solve(data: RangeData, x0: Sequence[float], cfg: BatchConfig = BatchConfig(), *,
          scales: Sequence[float] | None = None, calibrate: bool = True,
          theta0: np.ndarray | None = None, layout: Layout | None = None,
          recalibrate_tol: float = 0.05) -> Solution:
    """MAP fit from ``x0`` = (x, y, z[, b]) or a whole state ``theta0`` of the same layout.

    With ``calibrate`` the per-agent scales are re-estimated from the residuals and the
    fit repeated while they move by more than ``recalibrate_tol`` (three rounds at
    most); the scales returned are always the latest estimate.
    """
    lay = layout or make_layout(data, cfg)
    A = lay.n_agents
    s = np.ones(A) if scales is None else np.asarray(scales, float).copy()
    if theta0 is not None and theta0.size == lay.dim:
        theta = np.array(theta0, float)
    else:
        theta = np.zeros(lay.dim)
        theta[:3] = x0[:3]
        if len(x0) > 3:
            theta[3:3 + A] = x0[3]
    its = 0
    for rnd in range(3 if calibrate else 1):
        prob = _Problem(data, lay, s, cfg)
        theta, it = prob.minimise(theta, cfg.max_iter)
        its += it
        if not calibrate or rnd == 2:
            break
        e, _, _ = prob.residuals(theta)
        raw = e / (prob.inv_sig * np.sqrt(data.var_e))  # r / sigma_E
        new = calibrate_scales(raw, data.agent, A, cfg.scale_prior_n)
        moved = np.abs(new / s - 1.0).max()
        s = new
        if moved < recalibrate_tol:
            break
    prob = _Problem(data, lay, s, cfg)
    return prob.solution(theta, s, its)


def calibrate_scales(raw: np.ndarray, agent: np.ndarray, n_agents: int, prior_n: float
                     ) -> np.ndarray:
    """Per-agent scale s_a of r / sigma_E: 1.4826 MAD, shrunk towards 1 with ``prior_n``.

    s_a^2 = (n s_MAD^2 + n0) / (n + n0): with few samples an agent keeps the paper's
    Empirical-R noise; with many its own measured noise.
    """
    out = np.ones(n_agents)
    for a in range(n_agents):
        ua = raw[agent == a]
        n = ua.size
        if n < 3:
            continue
        smad = 1.4826 * float(np.median(np.abs(ua - np.median(ua))))
        out[a] = math.sqrt((n * smad * smad + prior_n) / (n + prior_n))
    return out


def _inv_spd(M: np.ndarray) -> np.ndarray:
    try:
        Li = np.linalg.inv(np.linalg.cholesky(M))
        return Li.T @ Li
    except np.linalg.LinAlgError:
        return np.linalg.pinv(M)


# ----------------------------------------------------------------------------- other minima


def principal_axes(data: RangeData) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Weighted centroid and major / minor unit axes of the anchors' horizontal spread."""
    w = 1.0 / data.var_e
    xy = data.u[:, :2]
    c = (w[:, None] * xy).sum(axis=0) / w.sum()
    dxy = xy - c
    S = (w[:, None] * dxy).T @ dxy
    _, vecs = np.linalg.eigh(S)
    return c, vecs[:, 1], vecs[:, 0]


def mirror_xy(p: Sequence[float], centre: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """Reflection of p's horizontal position about the line through ``centre`` along ``axis``."""
    v = np.asarray(p[:2], float) - centre
    return centre + 2.0 * (v @ axis) * axis - v


def pass_starts(data: RangeData, lay: Layout, min_offset_m: float = 10.0) -> list[np.ndarray]:
    """Both sides of a (nearly straight) pass: the closest approach +- its horizontal
    range (at least ``min_offset_m``), on the ground prior, no bias."""
    _, _, minor = principal_axes(data)
    i = int(np.argmin(data.d))
    a = int(data.agent[i])
    zg = lay.ground_m[a]
    rho = max(min_offset_m, math.sqrt(max(data.d[i] ** 2 - (data.u[i, 2] - zg) ** 2, 0.0)))
    base = data.u[i, :2]
    return [np.array([*(base + s * rho * minor), zg, 0.0]) for s in (1.0, -1.0)]


@dataclass(frozen=True)
class Minimum:
    """A distinct minimum with its relative likelihood weight (weights sum to 1)."""

    solution: Solution
    weight: float


def _merge_radius_m(sol: Solution, min_separation_m: float = 1.0) -> float:
    """Converged points closer than this (max(1 m, a tenth of the largest range-only
    horizontal sigma)) are one minimum; farther, two: one basin has one minimum."""
    sig = math.sqrt(float(np.linalg.eigvalsh(sol.cov_cond[:2, :2])[-1]))
    return max(min_separation_m, 0.1 * sig)


def distinct_minima(sols: Sequence[Solution], *, min_weight: float = 0.01,
                    min_separation_m: float = 1.0) -> list[Minimum]:
    """Merge minima closer than :func:`_merge_radius_m` and weigh the rest by their
    Laplace evidence; drop those below ``min_weight``. Best first, weights sum to 1."""
    order = sorted(sols, key=lambda s: s.cost)
    kept: list[Solution] = []
    for s in order:
        same = False
        for k in kept:
            if math.dist(s.theta[:2], k.theta[:2]) < _merge_radius_m(k, min_separation_m):
                same = True
                break
        if not same:
            kept.append(s)
    ev = np.array([k.log_evidence for k in kept])
    w = np.exp(ev - ev.max())
    w /= w.sum()
    out = [Minimum(k, float(x)) for k, x in zip(kept, w, strict=True) if x >= min_weight]
    tot = sum(m.weight for m in out)
    return sorted((Minimum(m.solution, m.weight / tot) for m in out), key=lambda m: -m.weight)


def search_minima(data: RangeData, main: Solution, cfg: BatchConfig = BatchConfig(), *,
                  extra_starts: Sequence[np.ndarray] = (), max_iter: int = 25,
                  min_weight: float = 0.01, straight_pass: bool = False) -> list[Minimum]:
    """Multi-start check around ``main``: its mirror images about the anchors' major and
    minor axes (and ``extra_starts``), solved with ``main``'s scales and layout.

    ``straight_pass`` (kappa_H over the limit): the two sides of the pass are two
    hypotheses whatever the solver finds; when no minimum on the other side survives,
    the mirror image of the best one about the major axis is kept as a candidate at
    its profile optimum (x, y held, the rest fitted), weighed like the others.
    """
    c, major, minor = principal_axes(data)
    lim = _merge_radius_m(main)
    sols = [main]
    starts = []
    for ax in (major, minor):
        m = mirror_xy(main.theta, c, ax)
        if math.dist(m, main.theta[:2]) > lim:
            th = main.theta.copy()
            th[:2] = m
            starts.append(th)
    for s in extra_starts:
        th = main.theta.copy()
        th[:len(s)] = s
        starts.append(th)
    prob = _Problem(data, main.layout, main.scales, cfg)
    for th in starts:
        t, it = prob.minimise(th, max_iter, stop_near=(main.theta[:2], lim))
        if math.dist(t[:2], main.theta[:2]) >= lim:
            sols.append(prob.solution(t, main.scales, it))
    minima = distinct_minima(sols, min_weight=0.0)
    if straight_pass:
        best = minima[0].solution
        side = np.sign((best.theta[:2] - c) @ minor)
        other = [m for m in minima if np.sign((m.solution.theta[:2] - c) @ minor) != side]
        if not other:
            th = best.theta.copy()
            th[:2] = mirror_xy(best.theta, c, major)
            t, it = prob.minimise(th, max_iter, hold_xy=True)
            sols.append(prob.solution(t, main.scales, it))
    return distinct_minima(sols, min_weight=min_weight)


# ----------------------------------------------------------------------------- circles

_GL_X, _GL_W = np.polynomial.legendre.leggauss(48)
_THETA = 0.25 * np.pi * (_GL_X + 1.0)  # nodes on [0, pi/2]
_THETA_W = 0.25 * np.pi * _GL_W


def circle_probability(cov2: np.ndarray, r_m: float) -> float:
    """P(|x| <= r) for x ~ N(0, cov2), 2-D (exact up to quadrature, not isotropic).

    With sigma_1 >= sigma_2 the principal sigmas, z_1 = (r / sigma_1) sin(theta):
    P = 2 int_0^{pi/2} phi(z_1) erf(r cos(theta) / (sigma_2 sqrt 2)) (r / sigma_1)
    cos(theta) dtheta, a smooth integrand (48-point Gauss-Legendre).
    """
    l2, l1 = np.linalg.eigvalsh(np.asarray(cov2, float))
    return _circle_p(math.sqrt(max(l1, 0.0)), math.sqrt(max(l2, 0.0)), r_m)


def _circle_p(s1: float, s2: float, r_m: float) -> float:
    from scipy.special import erf

    if r_m <= 0.0:
        return 0.0
    if not s1 > 0.0:
        return 1.0
    ct = _COS_T
    z1 = (r_m / s1) * _SIN_T
    inner = erf(r_m * ct / (s2 * math.sqrt(2.0))) if s2 > s1 * 1e-12 else 1.0
    f = np.exp(-0.5 * z1 * z1) * inner * ct
    return float(2.0 * (r_m / s1) / math.sqrt(2.0 * math.pi) * (_THETA_W @ f))


_COS_T = np.cos(_THETA)
_SIN_T = np.sin(_THETA)


def r_circle_m(cov2: np.ndarray, p: float = 0.95) -> float:
    """Radius of the circle centred on the estimate holding probability ``p`` (2 x 2 cov).

    Regula falsi (Illinois) between the 1-D bound (major axis alone) and the isotropic
    bound (both axes at the major sigma), which bracket it.
    """
    from scipy.special import ndtri

    l2, l1 = np.linalg.eigvalsh(np.asarray(cov2, float))
    if not l1 > 0.0:
        return 0.0
    s1, s2 = math.sqrt(l1), math.sqrt(max(l2, 0.0))
    lo = s1 * float(ndtri(0.5 + 0.5 * p))
    hi = s1 * math.sqrt(-2.0 * math.log(1.0 - p))
    f_lo = _circle_p(s1, s2, lo) - p
    f_hi = _circle_p(s1, s2, hi) - p
    if f_lo >= 0.0:
        return lo
    if f_hi <= 0.0:
        return hi
    # Illinois regula falsi on the bracket (P is increasing in r)
    side = 0
    for _ in range(100):
        r = (lo * f_hi - hi * f_lo) / (f_hi - f_lo)
        f = _circle_p(s1, s2, r) - p
        if abs(f) < 1e-14 or hi - lo < 1e-13 * s1:
            return r
        if f < 0.0:
            lo, f_lo = r, f
            if side == -1:
                f_hi *= 0.5
            side = -1
        else:
            hi, f_hi = r, f
            if side == 1:
                f_lo *= 0.5
            side = 1
    return r
