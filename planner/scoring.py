"""Geometry scoring of a flight path against a prior AP position.

The measurement model is the paper's range model, eq. (2): d_i = |p - u_i| + b + n_i,
n_i ~ N(0, sigma_i^2), with p the AP position, u_i the initiator (drone) position and
b the residual FTM bias. Per sample of the path the scorer predicts:

- the slant range d_i = |p - u_i|;
- the response probability P(d_i) and the mean RSSI from the link model
  (:class:`planner.models.LinkModel`: the simulator's ``sim.FtmLink`` when ``osa``
  plans for a known world, else the generic :class:`planner.models.LogisticLink`);
  with a terrain in the configuration (``ScoringConfig.terrain``), P of the link from
  u_i to p with the terrain's obstruction of it (``response_probability_between``: a
  ridge between them lowers it), so a path in view of the AP's likely area scores
  higher;
- the range variance sigma_i^2 from Empirical-R, eq. (23), with that RSSI and the MAD
  gate's floor sigma_floor as sigma_gate (the outer max of eq. 23 then never binds);
- the expected number of measurements n_i = rate x dwell_i x P(d_i).

The Fisher information of theta = (x, y, z, b) is J = sum_i n_i h_i h_i^T / sigma_i^2
with h_i = ((p - u_i)/|p - u_i|, 1) (the Jacobian row of eq. 14; both from the
estimator's one measurement model, :mod:`estimator.measurement`, whose near-zero rule
gives an anchor on the AP no direction information). The IEKF estimates b
(sec. Sequential Bayesian Filtering), so the headline CRLB treats the bias as a
*nuisance* parameter (the position block of J^-1); the known-bias CRLB (the inverse of
the 3 x 3 position block of J) is reported beside it. An orbit at one altitude centred
on the AP cannot tell the AP's height from the bias: every sample sees the AP at the
same elevation angle, so a height change shifts every range alike, as the bias does,
and the vertical CRLB is infinite. That holds exactly only for the centred orbit: off
centre (or on any one-altitude path whose elevation angles differ) the bound is finite,
but large while the angles stay bunched: a 60 m orbit at 45 m, 10 m off centre, gives
a vertical bound of ~300 m and a horizontal one of ~24 m (0.9 m when centred, where the
height-bias direction decouples); 1 m off centre the information in that direction is
below ``rcond`` and the bound is reported infinite. Flying several altitudes spreads the
elevation angles, which is the paper's point on altitude variation (sec. Conclusions). No prior
information enters the CRLB: it says what the flight itself delivers.

The range noise sigma(d) is the estimator's Empirical-R, eq. (23), i.e. the R the filter
uses. The simulator draws its true noise as 0.3 x eq. (23) (``noise_scale`` in
sim/ftm.py, because eq. 23 is a deliberately inflated R) at its own link's RSSI, about
0.27 x the sigma here (0.78 m against 2.87 m at 57.5 m), so against simulated truth the
CRLBs are conservative by about that factor.

CRLBs follow the paper's sigma_H / sigma_Z, eq. (19): crlb_h = sqrt([J^-1]_xx +
[J^-1]_yy), crlb_v = sqrt([J^-1]_zz). A parameter that the geometry cannot estimate
(its unit vector not in the range of J) gets an infinite bound.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from estimator.geometry import horizontal_condition_number
from estimator.measurement import geometric_range_m, range_jacobian
from estimator.noise import EmpiricalRConfig
from estimator.records import Trajectory
from planner.models import LinkModel, LogisticLink, TerrainModel


@dataclass(frozen=True, kw_only=True)
class ScoringConfig:
    """What the scorer assumes about the ranging link (:class:`planner.models.LinkModel`).

    ``link`` gives the response probability and the mean RSSI against slant range;
    ``osa`` passes the simulator's calibrated link (``sim.FtmLink``), the default is the
    generic :class:`planner.models.LogisticLink`. ``noise`` is the estimator's R
    (Empirical-R, eq. 23), the variance the filter will assign. ``terrain`` is what
    obstructs the link (None: nothing); a candidate AP position less than
    ``responder_height_m`` above it is lifted there for the link (the height is the
    least known coordinate of an estimate, and a responder lies on the ground).
    """

    link: LinkModel = field(default_factory=LogisticLink)
    concealment: str = "open"  # the class the responder is assumed to be in
    terrain: TerrainModel | None = None  # obstructs the link; None: nothing does
    responder_height_m: float = 0.5  # a responder's antenna is at least this high
    noise: EmpiricalRConfig = field(default_factory=EmpiricalRConfig)  # eq. (23)
    sigma_gate_m: float = 0.12  # sigma_floor of eq. (4): the smallest MAD-gate scale
    rcond: float = 1e-10  # eigenvalues below rcond x the largest count as zero

    @property
    def ranging_rate_hz(self) -> float:
        return float(self.link.ranging_rate_hz)

    def response_probability(self, slant_m) -> np.ndarray:
        return self.link.response_probability(slant_m, self.concealment)

    def link_point(self, ap_enu_m: Sequence[float] | np.ndarray) -> np.ndarray:
        """The AP as the link sees it: its height floored at ``responder_height_m``
        above the terrain."""
        p = np.array(ap_enu_m, dtype=float).reshape(3)
        if self.terrain is not None:
            ground = float(np.asarray(self.terrain.height_m(p[0], p[1]), dtype=float))
            p[2] = max(p[2], ground + self.responder_height_m)
        return p

    def response_probability_between(self, anchors_enu_m: np.ndarray,
                                     ap_enu_m: Sequence[float] | np.ndarray) -> np.ndarray:
        """P of each anchor's link to the AP, the terrain's obstruction included."""
        return np.asarray(self.link.response_probability_between(
            anchors_enu_m, self.link_point(ap_enu_m), self.terrain, self.concealment))


@dataclass(frozen=True, kw_only=True, eq=False)
class GeometryScore:
    """Predicted information of a path about one AP (see the module docstring).

    ``log_det_fim`` is log det of the position information with the bias marginalised
    (the Schur complement of the bias in J, 1/m^6); -inf when singular. Scores averaged
    over prior draws hold the mean of every field over the draws (``n_prior_draws`` > 1).
    """

    n_samples: int
    duration_s: float
    expected_measurements: float
    crlb_h_m: float
    crlb_v_m: float
    crlb_bias_m: float
    crlb_h_known_bias_m: float
    crlb_v_known_bias_m: float
    log_det_fim: float
    log_det_fim_known_bias: float
    gdop: float
    hdop: float
    condition_number: float
    min_slant_m: float
    min_horizontal_m: float
    fim: np.ndarray  # 4 x 4 over (x, y, z, b), units 1/m^2
    n_prior_draws: int = 1


def range_variance_m2(
    slant_m: np.ndarray | float, cfg: ScoringConfig = ScoringConfig()
) -> np.ndarray:
    """Eq. (23) with the eq. (21) RSSI at each slant range and sigma_gate = sigma_floor.

    Vectorised twin of :func:`estimator.noise.empirical_r_m2` (a test keeps them equal).
    """
    d = np.asarray(slant_m, dtype=float)
    n = cfg.noise
    q = np.maximum(0.0, -np.asarray(cfg.link.mean_rssi_dbm(d, cfg.concealment)) - n.r_ref_db)
    model = n.sigma0_m**2 + n.alpha * d * d + n.beta_m2_per_db2 * q * q
    return np.maximum(cfg.sigma_gate_m**2, model)


def dwell_times_s(t_s: np.ndarray, ranging_rate_hz: float) -> np.ndarray:
    """Time each sample stands for: the step to the next sample (the last repeats the
    previous step); a single sample stands for one ranging period."""
    t = np.asarray(t_s, dtype=float)
    if len(t) == 0:
        return np.zeros(0)
    if len(t) == 1:
        return np.array([1.0 / ranging_rate_hz])
    dt = np.diff(t)
    return np.append(dt, dt[-1])


def fisher_information(
    anchors_enu_m: np.ndarray,
    dwell_s: np.ndarray,
    ap_enu_m: Sequence[float] | np.ndarray,
    cfg: ScoringConfig = ScoringConfig(),
) -> tuple[np.ndarray, np.ndarray]:
    """J (4 x 4 over x, y, z, b) and the expected measurement count of each anchor."""
    u = np.asarray(anchors_enu_m, dtype=float).reshape(-1, 3)
    p = np.asarray(ap_enu_m, dtype=float).reshape(3)
    d, h = range_jacobian(p, u, bias=True)  # slant ranges and rows (g_i, 1), eq. (14)
    prob = (cfg.response_probability(d) if cfg.terrain is None
            else cfg.response_probability_between(u, p))
    counts = cfg.ranging_rate_hz * np.asarray(dwell_s, dtype=float) * prob
    w = counts / range_variance_m2(d, cfg)
    return (h * w[:, None]).T @ h, counts


def _bound_from_info(info: np.ndarray, rcond: float) -> np.ndarray:
    """Diagonal of the CRLB (pseudo-inverse), inf where a parameter is not estimable."""
    n = info.shape[0]
    vals, vecs = np.linalg.eigh(0.5 * (info + info.T))
    top = float(vals.max()) if n else 0.0
    if not math.isfinite(top) or top <= 0.0:
        return np.full(n, math.inf)
    keep = vals > rcond * top
    inv_diag = (vecs[:, keep] ** 2 / vals[keep]).sum(axis=1)
    null_part = (vecs[:, ~keep] ** 2).sum(axis=1)  # |projection of e_j on the null space|^2
    return np.where(null_part > 1e-9, math.inf, inv_diag)


def _log_det(info: np.ndarray, rcond: float) -> float:
    vals = np.linalg.eigvalsh(0.5 * (info + info.T))
    if vals.max() <= 0.0 or vals.min() <= rcond * vals.max():
        return -math.inf
    return float(np.log(vals).sum())


def _dop(
    anchors: np.ndarray, ap: np.ndarray, weights: np.ndarray, rcond: float
) -> tuple[float, float]:
    """GDOP and HDOP of one unit-sigma range with bias: sqrt(tr (G^T W G)^-1), sum W = 1."""
    if weights.sum() <= 0.0:
        return math.inf, math.inf
    _, G = range_jacobian(ap, anchors, bias=True)
    w = weights / weights.sum()
    diag = _bound_from_info((G * w[:, None]).T @ G, rcond)
    return float(math.sqrt(diag.sum())), float(math.sqrt(diag[0] + diag[1]))


def score_anchors(
    anchors_enu_m: np.ndarray,
    dwell_s: np.ndarray,
    ap_enu_m: Sequence[float] | np.ndarray,
    cfg: ScoringConfig = ScoringConfig(),
) -> GeometryScore:
    """Score a set of absolute ENU anchor positions, each flown for ``dwell_s``."""
    u = np.asarray(anchors_enu_m, dtype=float).reshape(-1, 3)
    dwell = np.asarray(dwell_s, dtype=float).reshape(-1)
    if len(dwell) != len(u):
        raise ValueError("one dwell time per anchor")
    p = np.asarray(ap_enu_m, dtype=float).reshape(3)
    if not np.all(np.isfinite(p)):
        raise ValueError("non-finite AP position")
    fim, counts = fisher_information(u, dwell, p, cfg)
    full = _bound_from_info(fim, cfg.rcond)
    known = _bound_from_info(fim[:3, :3], cfg.rcond)
    if fim[3, 3] > 0.0:
        schur = fim[:3, :3] - np.outer(fim[:3, 3], fim[:3, 3]) / fim[3, 3]
        log_det = _log_det(schur, cfg.rcond) if math.isfinite(full[:3].sum()) else -math.inf
    else:
        log_det = -math.inf
    gdop, hdop = _dop(u, p, counts, cfg.rcond)
    horizontal = np.linalg.norm(u[:, :2] - p[None, :2], axis=1)
    slant = geometric_range_m(p, u)
    return GeometryScore(
        n_samples=len(u),
        duration_s=float(dwell.sum()),
        expected_measurements=float(counts.sum()),
        crlb_h_m=float(math.sqrt(full[0] + full[1])),
        crlb_v_m=float(math.sqrt(full[2])),
        crlb_bias_m=float(math.sqrt(full[3])),
        crlb_h_known_bias_m=float(math.sqrt(known[0] + known[1])),
        crlb_v_known_bias_m=float(math.sqrt(known[2])),
        log_det_fim=log_det,
        log_det_fim_known_bias=_log_det(fim[:3, :3], cfg.rcond),
        gdop=gdop,
        hdop=hdop,
        condition_number=horizontal_condition_number(u, counts),
        min_slant_m=float(slant.min()) if len(u) else math.inf,
        min_horizontal_m=float(horizontal.min()) if len(u) else math.inf,
        fim=fim,
    )


def absolute_enu_m(traj: Trajectory, terrain: TerrainModel | None = None) -> np.ndarray:
    """Positions with z above the frame origin (resolves ``height_ref="terrain"``)."""
    p = traj.enu_m.copy()
    if traj.height_ref == "terrain":
        if terrain is None:
            raise ValueError("a terrain-referenced trajectory needs a terrain model to score")
        p[:, 2] += np.asarray(terrain.height_m(p[:, 0], p[:, 1]), dtype=float)
    return p


def score_trajectory(
    traj: Trajectory,
    ap_enu_m: Sequence[float] | np.ndarray,
    cfg: ScoringConfig = ScoringConfig(),
    terrain: TerrainModel | None = None,
) -> GeometryScore:
    """Score a trajectory against one AP position (ENU of the trajectory's origin)."""
    return score_anchors(
        absolute_enu_m(traj, terrain), dwell_times_s(traj.t_s, cfg.ranging_rate_hz), ap_enu_m, cfg
    )


def prior_points(
    mean_enu_m: Sequence[float] | np.ndarray,
    cov_m2: np.ndarray,
    n_points: int = 6,
    rng: np.random.Generator | None = None,
) -> np.ndarray:
    """Points representing the prior N(mean, cov), shape (n_points, 3).

    Without ``rng``: the deterministic spherical-radial cubature points mean +/- sqrt(3)
    sqrt(lambda_j) e_j over the principal axes (exact for the mean and covariance of the
    prior), largest axis first and cycled to ``n_points``: 6 is the full rule, 4 keeps
    the two largest axes (the horizontal ones for an AP on the ground), 1 is the mean.
    With ``rng``: ``n_points`` random draws.
    """
    mean = np.asarray(mean_enu_m, dtype=float).reshape(3)
    cov = np.asarray(cov_m2, dtype=float).reshape(3, 3)
    if n_points < 1:
        raise ValueError("n_points must be >= 1")
    vals, vecs = np.linalg.eigh(0.5 * (cov + cov.T))
    if vals.min() < -1e-9 * max(1.0, vals.max()):
        raise ValueError("prior covariance is not positive semi-definite")
    L = vecs * np.sqrt(np.clip(vals, 0.0, None))[None, :]
    if rng is not None:
        return mean[None, :] + rng.standard_normal((n_points, 3)) @ L.T
    if n_points == 1:
        return mean[None, :]
    cols = math.sqrt(3.0) * L.T[::-1]  # rows: sqrt(3 lambda_j) e_j, largest first
    rule = np.vstack([mean + cols, mean - cols])[[0, 3, 1, 4, 2, 5]]
    return rule[np.arange(n_points) % 6]


def score_over_prior(
    traj: Trajectory,
    prior_mean_enu_m: Sequence[float] | np.ndarray,
    prior_cov_m2: np.ndarray,
    rng: np.random.Generator,
    n_draws: int = 32,
    cfg: ScoringConfig = ScoringConfig(),
    terrain: TerrainModel | None = None,
) -> GeometryScore:
    """Mean of :func:`score_trajectory` over ``n_draws`` AP positions drawn from the prior."""
    if n_draws < 1:
        raise ValueError("n_draws must be >= 1")
    anchors = absolute_enu_m(traj, terrain)
    dwell = dwell_times_s(traj.t_s, cfg.ranging_rate_hz)
    draws = prior_points(prior_mean_enu_m, prior_cov_m2, n_draws, rng)
    scores = [score_anchors(anchors, dwell, ap, cfg) for ap in draws]
    names = (
        "duration_s", "expected_measurements", "crlb_h_m", "crlb_v_m", "crlb_bias_m",
        "crlb_h_known_bias_m", "crlb_v_known_bias_m", "log_det_fim", "log_det_fim_known_bias",
        "gdop", "hdop", "condition_number", "min_slant_m", "min_horizontal_m",
    )  # fmt: skip
    means = {n: float(np.mean([getattr(s, n) for s in scores])) for n in names}
    return GeometryScore(
        n_samples=len(anchors),
        fim=np.mean([s.fim for s in scores], axis=0),
        n_prior_draws=n_draws,
        **means,
    )
