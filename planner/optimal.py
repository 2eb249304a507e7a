"""Information-optimal waypoint planning with CasADi (``casadi.Opti`` + Ipopt).

Decision variables: N waypoints p_0..p_{N-1} (ENU, metres above the frame origin), one
every ``dt`` seconds, so the horizon (the flight time budget) is (N - 1) dt.

Objective: maximise the mean over K prior points s_k of log det of the AP position
information with the FTM bias marginalised (:mod:`planner.scoring`), i.e.

    J_k = sum_i rate dt P(d_ik) / sigma^2(d_ik) h_ik h_ik^T + P0^-1,
    h_ik = ((s_k - p_i) / d_ik, 1),  d_ik = |s_k - p_i|,
    maximise (1/K) sum_k log det( J_k[pp] - J_k[pb] J_k[pb]^T / J_k[bb] ),

with P(d) the link's response probability (lowered, with a terrain in the scoring
configuration, by the terrain's loss on each waypoint's link to the prior's centre:
a second, warm-started solve when the first plan is partly hidden, see
:meth:`OptimalPlanner._occluded_stage`) and sigma^2(d) Empirical-R, eq. (23), at
the eq. (21) RSSI, where the kink of q = max(0, -RSSI - r_ref) is smoothed
((q + sqrt(q^2 + 1 dB^2)) / 2) so Ipopt sees a smooth problem. P0^-1 is the IEKF's initial
information, P0 = diag(25, 25, 100, 4) (sec. IEKF3D): it keeps log det finite for any
path, as the filter's own prior does. The K prior points are the deterministic
cubature points of N(mean, cov) (:func:`planner.scoring.prior_points`), so a small
change of the prior moves them a little and the warm start stays good. A small
penalty on the second differences keeps the path smooth. The ten distinct entries of
each J_k are lifted into extra variables (equality constraints), which keeps the
Hessian of the Lagrangian block-sparse: this is what makes re-solves fast.

Constraints (on waypoints, and the altitude band on leg midpoints too; straight flight
between waypoints):
- start: p_0 = the current position; (p_1 - p_0)/dt - v_0 bounded like the accel;
- speed |p_{i+1} - p_i| <= v_max dt, climb |z_{i+1} - z_i| <= v_z dt;
- acceleration |p_{i+1} - 2 p_i + p_{i-1}| <= a_max dt^2;
- altitude band: agl_min <= z - terrain(x, y) <= agl_max at the waypoints i >= 1 and
  at the midpoints of the legs, with the terrain a smooth function CasADi can evaluate
  (:class:`planner.models.TerrainModel`: the simulator's own ``sim.HillsTerrain`` or
  ``sim.GridTerrain``, or a flat ground). A straight leg over a hill top sags
  towards the ground between its ends (its height above terrain is convex where the
  terrain is concave), so over curved terrain both sets of points keep a sag margin
  m = kappa (v_max dt / 2)^2 / 8 inside the band (kappa the terrain's curvature bound,
  ``TerrainModel.sag_curvature``): every half-leg then stays inside the band
  (flat terrain: no midpoints, no margin). The first leg starts where the drone is, so
  its midpoint keeps the band widened to the start's own height above terrain;
- keep-in geofence: a convex polygon as half-planes a_j . (x, y) <= b_j - margin,
  joined per waypoint by a log-sum-exp smooth max (above the true max, so
  conservative; convexity keeps whole legs inside when their ends are);
- keep-out cylinders: (x - c_x)^2 + (y - c_y)^2 >= R^2 with R^2 = (r + margin)^2 +
  (v_max dt / 2)^2 at the waypoints, which keeps every straight leg (length <= v_max
  dt) out of r + margin; several cylinders are joined by a smooth min (conservative);
- keep-out polygons (``max_keep_out_polygons``, a power line's corridor): each by its
  convex hull (a superset), as half-planes a_j . (x, y) <= b_j with unit outward
  normals; a point is out by at least max_j (a_j . q - b_j), which a log-mean-exp
  tau log (1/E sum_j exp((a_j . q - b_j) / tau)) bounds from below (by at most
  tau log E), so requiring it >= margin + v_max dt / (2 q) at the centres of q equal
  pieces of every leg (``keep_out_leg_points``; every point of a leg lies within
  v_max dt / 2q of one) keeps whole legs out of the hull by the margin.

The problem is built once; the prior points, start pose, dt, limits, altitude band,
fence and keep-outs are ``opti.parameter``s, so :meth:`OptimalPlanner.plan` only
re-solves, warm-started (primal and dual) from the previous solution. Unused fence
edges and keep-outs are padded with rows that always hold.

The solver's own status is never trusted: :meth:`OptimalPlanner.check` re-checks every
constraint numerically (legs densely, every 1 m, for the altitude band, the fence and
the keep-outs, without margins); if the optimiser's path fails, the planner falls back
to the best feasible orbit about the prior mean flown by an acceleration-limited
guidance law from the current pose. If CasADi raises, there is no optimiser path: the
initial guess is returned if it passes the check, labelled as a fallback, and is not
kept as a warm start.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from estimator.measurement import jacobian_rows, range_casadi, range_of_difference
from estimator.records import Trajectory
from planner.models import FlatTerrain, TerrainModel
from planner.patterns import (
    PAPER_SITE,
    Geofence,
    KeepOut,
    KeepOutPolygon,
    airspace_violations,
    densify,
)
from planner.scoring import ScoringConfig, prior_points

_FAR_M = 1e5  # padding: an unused fence edge or keep-out this far away never binds

# --------------------------------------------------------------------------- terrain


def _is_symbolic(x: object) -> bool:
    return isinstance(x, ca.SX | ca.MX | ca.DM)


def sag_margins_m(terrain: TerrainModel, leg_m: float) -> tuple[float, float]:
    """How far the height above ``terrain`` can dip below (first) or rise above (second)
    the straight interpolation of its values at the ends of a horizontal leg ``leg_m``
    long: kappa leg^2 / 8, kappa the terrain's curvature bound along a line."""
    concave, convex = terrain.sag_curvature()
    return concave * leg_m * leg_m / 8.0, convex * leg_m * leg_m / 8.0


# --------------------------------------------------------------------------- config


@dataclass(frozen=True, kw_only=True)
class OptimalConfig:
    """Structure (fixed at build) and default limits of the optimal planner."""

    n_waypoints: int = 40
    n_prior_points: int = 6  # the full 3-D cubature rule (2 x 3 points)
    max_fence_edges: int = 8
    max_keep_outs: int = 4
    horizon_s: float = 120.0  # flight time budget (N - 1) dt
    max_speed_m_s: float = 8.0  # our choice: 2 m between 4 Hz ranges
    max_accel_m_s2: float = 2.0  # our choice: gentle for a 6-9 kg multirotor
    max_climb_m_s: float = 3.0  # PX4 MPC_Z_VEL_MAX_UP default
    agl_min_m: float = 30.0  # below the paper's 35-55 m AGL (sec. Experimental Setup)
    agl_max_m: float = 80.0
    fence_margin_m: float = 2.0
    fence_smoothing_m: float = 1.0  # log-sum-exp scale of the keep-in edges
    keep_out_smoothing: float = 0.05  # soft-min scale of (d / R)^2 - 1 over keep-outs
    keep_out_margin_m: float = 2.0
    max_keep_out_polygons: int = 0  # keep-out polygons the problem holds (convex hulls)
    max_keep_out_edges: int = 8  # hull edges per keep-out polygon
    keep_out_leg_points: int = 4  # polygon clearance checked at this many points per leg
    keep_out_polygon_smoothing_m: float = 1.0  # log-mean-exp scale of the hull's edges
    terrain: TerrainModel = field(default_factory=FlatTerrain)
    scoring: ScoringConfig = field(default_factory=ScoringConfig)
    prior_information: tuple[float, float, float, float] = (1 / 25, 1 / 25, 1 / 100, 1 / 4)
    smoothing_db: float = 1.0  # smoothing scale of q = max(0, -RSSI - r_ref)
    smoothness_weight: float = 1e-3
    position_scale_m: float = 100.0  # variable scaling for Ipopt
    information_scale: float = 100.0
    output_dt_s: float = 0.5  # sample period of the returned trajectory
    max_iter: int = 150
    tol: float = 1e-3
    barrier_target: float = 1e-4  # stop on the central path at mu = 1e-4: a slightly
    # interior, fully feasible point; going to mu -> 0 buys < 0.01 of log det per 5 iterations
    acceptable_tol: float = 1e-2
    acceptable_iter: int = 2
    check_tolerance_m: float = 0.01  # slack of the numerical constraint check
    fallback_radii_m: tuple[float, ...] = (25.0, 40.0, 60.0, 90.0)
    ipopt_options: dict = field(default_factory=dict)  # overrides of the options below


@dataclass(frozen=True, kw_only=True, eq=False)
class PlanResult:
    """Output of :meth:`OptimalPlanner.plan`.

    ``violations`` lists what the optimiser's own path broke (empty when it passed the
    check; when CasADi raised, first "no solver path ..." and then what the initial
    guess broke); ``fallback`` names what is returned instead of an optimiser path (None
    only when the optimiser's path is returned): ``"orbit r=.. m"`` or, after a solver
    error, ``"initial guess: ..."``; ``feasible`` says whether the returned path passes
    the check.
    """

    trajectory: Trajectory
    waypoints_enu_m: np.ndarray
    dt_s: float
    objective: float  # mean over the prior points of log det (position, bias marginalised)
    status: str
    solver_success: bool
    iterations: int
    solve_time_s: float
    violations: tuple[str, ...]
    feasible: bool
    fallback: str | None = None
    occlusion: str = ""  # with a terrain in the scoring: "in view", "replanned in view", ...


# --------------------------------------------------------------------------- model


def _smooth_relu(z, k: float):
    """(z + sqrt(z^2 + k^2)) / 2: a smooth max(0, z), above it by at most k / 2."""
    sqrt = ca.sqrt if _is_symbolic(z) else np.sqrt
    return 0.5 * (z + sqrt(z * z + k * k))


def _smooth_max(rows, tau):
    """Column-wise tau log sum_j exp(row_j / tau) (>= the max, by at most tau log n)."""
    top = rows[0, :]
    for j in range(1, rows.shape[0]):
        top = ca.fmax(top, rows[j, :])
    total = 0
    for j in range(rows.shape[0]):
        total = total + ca.exp((rows[j, :] - top) / tau)
    return top + tau * ca.log(total)


def _smooth_mean(rows, tau):
    """Column-wise tau log (1/n sum_j exp(row_j / tau)): <= the max, by at most
    tau log n (a lower bound of the max, for constraints that it be large)."""
    top = rows[0, :]
    for j in range(1, rows.shape[0]):
        top = ca.fmax(top, rows[j, :])
    total = 0
    for j in range(rows.shape[0]):
        total = total + ca.exp((rows[j, :] - top) / tau)
    return top + tau * ca.log(total / rows.shape[0])


def _weights(d, cfg: OptimalConfig, dwell, loss_db=None):
    """Expected measurements per unit variance rate dt P(d) / sigma^2(d) (smooth), P
    with the terrain's loss ``loss_db`` on each waypoint's link when given."""
    sc = cfg.scoring
    link = sc.link
    q = _smooth_relu(-link.mean_rssi_dbm(d, sc.concealment) - sc.noise.r_ref_db, cfg.smoothing_db)
    n = sc.noise
    var = n.sigma0_m**2 + n.alpha * d * d + n.beta_m2_per_db2 * q * q
    if loss_db is None:
        prob = link.response_probability(d, sc.concealment)
    else:
        prob = link.response_probability(d, sc.concealment, loss_db)
    return sc.ranging_rate_hz * dwell * prob / var


def link_loss_db(P, prior_points, cfg: OptimalConfig):
    """The terrain's loss (dB) on the link of each waypoint to the likely area's centre
    (the prior points' mean, lifted to ``responder_height_m`` above the ground as
    :meth:`planner.scoring.ScoringConfig.link_point` does), shared by the prior points;
    None without a terrain in ``cfg.scoring``. ``P`` and ``prior_points`` 3 x N and
    3 x K CasADi (the link's smooth approximation) or N x 3 and K x 3 NumPy (its exact
    profile)."""
    sc = cfg.scoring
    if sc.terrain is None:
        return None
    if _is_symbolic(P):
        c = ca.sum2(prior_points) / prior_points.shape[1]
        ground = sc.terrain.height_m(c[0], c[1])
        a = ca.vertcat(c[0], c[1], ca.fmax(c[2], ground + sc.responder_height_m))
        return sc.link.obstruction_loss_db(P, a, sc.terrain)
    a = sc.link_point(np.mean(np.asarray(prior_points, dtype=float).reshape(-1, 3), axis=0))
    return np.asarray(sc.link.obstruction_loss_db(P, a, sc.terrain), dtype=float)


def _info_entries(P, s, cfg: OptimalConfig, dwell, loss_db=None):
    """(xx, yy, zz, xy, xz, yz, xb, yb, zb, bb) of sum_i w_i h_i h_i^T for one AP s.

    ``P`` is 3 x N (CasADi) or N x 3 (NumPy); h_i = ((s - p_i) / d_i, 1) and d_i from
    the estimator's measurement model (:mod:`estimator.measurement`, its near-zero rule
    in both forms); ``loss_db`` the terrain's loss on each waypoint's link
    (:func:`link_loss_db`)."""
    if _is_symbolic(P):
        D = ca.repmat(s, 1, P.shape[1]) - P
        d2, d = range_casadi(D)
        w = _weights(d, cfg, dwell, loss_db)
        u = w / d2  # w g g^T = u D D^T, w g = v D
        v = w / d
        dx, dy, dz = D[0, :], D[1, :], D[2, :]
        ux, uy = u * dx, u * dy
        tot = ca.sum2
        return ca.vertcat(
            tot(ux * dx), tot(uy * dy), tot(u * dz * dz),
            tot(ux * dy), tot(ux * dz), tot(uy * dz),
            tot(v * dx), tot(v * dy), tot(v * dz), tot(w),
        )  # fmt: skip
    D = np.asarray(s, dtype=float)[None, :] - P
    d = range_of_difference(D)
    g = jacobian_rows(D, d)
    w = _weights(d, cfg, dwell, loss_db)
    gx, gy, gz = g[:, 0], g[:, 1], g[:, 2]
    return np.array(
        [
            (w * gx * gx).sum(), (w * gy * gy).sum(), (w * gz * gz).sum(),
            (w * gx * gy).sum(), (w * gx * gz).sum(), (w * gy * gz).sum(),
            (w * gx).sum(), (w * gy).sum(), (w * gz).sum(), w.sum(),
        ]
    )  # fmt: skip


def _log_det_marginal(f, prior_info):
    """log det of the position information with the bias marginalised (entries ``f``)."""
    ix, iy, iz, ib = prior_info
    xx, yy, zz = f[0] + ix, f[1] + iy, f[2] + iz
    xy, xz, yz = f[3], f[4], f[5]
    bx, by, bz, bb = f[6], f[7], f[8], f[9] + ib
    a = xx - bx * bx / bb
    b = yy - by * by / bb
    c = zz - bz * bz / bb
    e = xy - bx * by / bb
    g = xz - bx * bz / bb
    h = yz - by * bz / bb
    det = a * (b * c - h * h) - e * (e * c - h * g) + g * (e * h - b * g)
    return ca.log(det) if _is_symbolic(det) else math.log(det) if det > 0 else -math.inf


def planning_objective(
    waypoints_enu_m: np.ndarray,
    prior_points_enu_m: np.ndarray,
    dt_s: float,
    cfg: OptimalConfig = OptimalConfig(),
) -> float:
    """The optimiser's objective (without the smoothness term) in NumPy: mean over the
    prior points of log det of the bias-marginalised position information, P0 included."""
    P = np.asarray(waypoints_enu_m, dtype=float).reshape(-1, 3)
    pts = np.asarray(prior_points_enu_m, dtype=float).reshape(-1, 3)
    loss = link_loss_db(P, pts, cfg)
    vals = [_log_det_marginal(_info_entries(P, s, cfg, dt_s, loss), cfg.prior_information)
            for s in pts]
    return float(np.mean(vals))


# --------------------------------------------------------------------------- fallback


def guidance_orbit(
    start_enu_m: Sequence[float],
    start_vel_m_s: Sequence[float],
    center_enu_m: Sequence[float],
    radius_m: float,
    alt_m: float,
    n_waypoints: int,
    dt_s: float,
    max_speed_m_s: float,
    max_accel_m_s2: float,
    max_climb_m_s: float,
) -> np.ndarray:
    """Waypoints (N x 3) converging on a counter-clockwise orbit by the Lyapunov vector
    field of Lawrence, Frew and Pisano (2008), flown with the velocity change per step
    limited to a_max dt, the speed to v_max and the climb rate to v_z: it meets the
    speed, climb and acceleration constraints by construction."""
    p = np.asarray(start_enu_m, dtype=float).copy()
    v = np.asarray(start_vel_m_s, dtype=float).copy()
    c = np.asarray(center_enu_m, dtype=float)[:2]
    speed = min(max_speed_m_s, 0.9 * math.sqrt(max_accel_m_s2 * radius_m))
    out = [p.copy()]
    for _ in range(n_waypoints - 1):
        rel = p[:2] - c
        rho2 = float(rel @ rel)
        k = -speed / (radius_m * (rho2 + radius_m**2)) if rho2 > 0 else 0.0
        rho = math.sqrt(rho2)
        vdes_xy = k * np.array(
            [
                rel[0] * (rho2 - radius_m**2) + rel[1] * 2.0 * rho * radius_m,
                rel[1] * (rho2 - radius_m**2) - rel[0] * 2.0 * rho * radius_m,
            ]
        )
        if rho2 == 0.0:
            vdes_xy = np.array([speed, 0.0])
        vz = float(np.clip((alt_m - p[2]) / max(dt_s, 1e-9), -max_climb_m_s, max_climb_m_s))
        dv = np.array([vdes_xy[0], vdes_xy[1], vz]) - v
        n_dv = float(np.linalg.norm(dv))
        if n_dv > max_accel_m_s2 * dt_s:
            dv *= max_accel_m_s2 * dt_s / n_dv
        v = v + dv
        n_v = float(np.linalg.norm(v))
        if n_v > max_speed_m_s:
            v *= max_speed_m_s / n_v
        v[2] = float(np.clip(v[2], -max_climb_m_s, max_climb_m_s))
        p = p + v * dt_s
        out.append(p.copy())
    return np.array(out)


def waypoints_to_trajectory(
    waypoints_enu_m: np.ndarray,
    dt_s: float,
    out_dt_s: float,
    origin: tuple[float, float, float],
    name: str,
) -> Trajectory:
    """Straight legs between waypoints ``dt_s`` apart, sampled every ``out_dt_s`` and at
    every waypoint (so the corners are in the samples)."""
    W = np.asarray(waypoints_enu_m, dtype=float)
    t_w = np.arange(len(W)) * dt_s
    t = np.union1d(np.arange(0.0, t_w[-1] + 1e-9, out_dt_s), t_w)  # corners kept exactly
    t = t[np.append(True, np.diff(t) > 1e-9)]
    enu = np.column_stack([np.interp(t, t_w, W[:, j]) for j in range(3)])
    return Trajectory(t_s=t, enu_m=enu, origin=origin, height_ref="origin", name=name)


# --------------------------------------------------------------------------- planner


class OptimalPlanner:
    """Build the Opti problem once; :meth:`plan` re-solves it with new parameters."""

    def __init__(self, cfg: OptimalConfig = OptimalConfig()) -> None:
        if cfg.n_waypoints < 3 or cfg.n_prior_points < 1:
            raise ValueError("need n_waypoints >= 3 and n_prior_points >= 1")
        self.cfg = cfg
        t0 = time.perf_counter()
        self._build()
        self.build_time_s = time.perf_counter() - t0
        self._warm: tuple[np.ndarray, np.ndarray] | None = None

    # ---------------------------------------------------------------- build
    def _build(self) -> None:
        """The problem without the terrain's loss (``_solve_cold``, ``_solve_warm``) and,
        with a terrain in ``cfg.scoring``, the same problem with it (``_solve_occluded``,
        a warm start: same variables and constraints, the weights lowered by the
        loss)."""
        self._solve_occluded = self._loss_fn = None
        if self.cfg.scoring.terrain is not None:
            self._build_problem(occlusion=True)
            self._solve_occluded = self._solve_warm
        self._build_problem(occlusion=False)

    def _build_problem(self, occlusion: bool) -> None:
        cfg = self.cfg
        N, K, E, M = cfg.n_waypoints, cfg.n_prior_points, cfg.max_fence_edges, cfg.max_keep_outs
        S = cfg.position_scale_m
        opti = ca.Opti()
        X = opti.variable(3, N)  # waypoints / S
        Fv = opti.variable(10, K)  # lifted information entries / information_scale
        p_prior = opti.parameter(3, K)  # metres
        p_start = opti.parameter(3)
        p_vel = opti.parameter(3)
        p_dt = opti.parameter()
        p_lim = opti.parameter(3)  # v_max, a_max, v_z
        p_band = opti.parameter(4)  # agl min, max; the first leg's min, max
        p_fence = opti.parameter(E, 3)  # a_x, a_y, b (m, margin applied)
        p_keep = opti.parameter(M, 3)  # c_x, c_y (m), effective radius^2 (m^2)
        P = S * X

        blocks: list[tuple[int, int]] = []  # (first row, rows) of per-leg constraint rows

        def per_leg(constraint) -> None:
            first_row = opti.ng
            opti.subject_to(constraint)
            blocks.append((first_row, opti.ng - first_row))

        # the terrain's loss on each waypoint's link to the likely area
        loss = link_loss_db(P, p_prior, cfg) if occlusion else None
        if loss is not None:
            self._loss_fn = ca.Function("link_loss", [X, p_prior], [loss])

        objective = 0
        for k in range(K):
            entries = _info_entries(P, p_prior[:, k], cfg, p_dt, loss)
            opti.subject_to(cfg.information_scale * Fv[:, k] == entries)
            objective += _log_det_marginal(cfg.information_scale * Fv[:, k], cfg.prior_information)
        acc = X[:, 2:] - 2 * X[:, 1:-1] + X[:, :-2]
        amax_dt2 = p_lim[1] * p_dt * p_dt / S
        smooth = ca.sum2(ca.sum1(acc * acc)) / ((N - 2) * amax_dt2 * amax_dt2)
        opti.minimize(-objective / K + cfg.smoothness_weight * smooth)

        opti.subject_to(X[:, 0] == p_start / S)
        step = X[:, 1:] - X[:, :-1]
        per_leg(ca.sum1(step * step) <= (p_lim[0] * p_dt / S) ** 2)
        per_leg(opti.bounded(-p_lim[2] * p_dt / S, step[2, :], p_lim[2] * p_dt / S))
        per_leg(ca.sum1(acc * acc) <= amax_dt2**2)
        first = X[:, 1] - X[:, 0] - p_vel * p_dt / S
        opti.subject_to(ca.sumsqr(first) <= amax_dt2**2)
        agl = X[2, 1:] - cfg.terrain.height_m(P[0, 1:], P[1, 1:]) / S
        concave, convex = sag_margins_m(cfg.terrain, 1.0)  # kappa / 8 per m^2 of leg
        if concave > 0.0 or convex > 0.0:
            # sag margins of a half-leg, m = kappa (v_max dt / 2)^2 / 8, in scaled units
            half2 = (p_lim[0] * p_dt / 2) ** 2
            m_lo, m_hi = concave * half2 / S, convex * half2 / S
            per_leg(opti.bounded(p_band[0] / S + m_lo, agl, p_band[1] / S - m_hi))
            mid = 0.5 * (P[:, 1:] + P[:, :-1])
            ground_mid = cfg.terrain.height_m(mid[0, :], mid[1, :])
            agl_mid = 0.5 * (X[2, 1:] + X[2, :-1]) - ground_mid / S
            lo_mid = ca.horzcat(p_band[2], ca.repmat(p_band[0], 1, N - 2)) / S + m_lo
            hi_mid = ca.horzcat(p_band[3], ca.repmat(p_band[1], 1, N - 2)) / S - m_hi
            per_leg(opti.bounded(lo_mid, agl_mid, hi_mid))
        else:  # flat: the height above terrain is linear along a leg, the ends suffice
            per_leg(opti.bounded(p_band[0] / S, agl, p_band[1] / S))
        # keep-in: smooth max over the edges (log-sum-exp >= max, so conservative by at
        # most fence_smoothing_m log E), one row per waypoint whatever E
        edge = ca.vertcat(
            *[
                p_fence[j, 0] * X[0, 1:] + p_fence[j, 1] * X[1, 1:] - p_fence[j, 2] / S
                for j in range(E)
            ]
        )
        per_leg(_smooth_max(edge, cfg.fence_smoothing_m / S) <= 0)
        # keep-outs: smooth min over the cylinders of |xy - c|^2 / R^2 - 1 >= 0
        clear = ca.vertcat(
            *[
                ((X[0, 1:] - p_keep[j, 0] / S) ** 2 + (X[1, 1:] - p_keep[j, 1] / S) ** 2)
                * (S * S / p_keep[j, 2])
                - 1.0
                for j in range(M)
            ]
        )
        per_leg(_smooth_max(-clear, cfg.keep_out_smoothing) <= 0)
        # keep-out polygons: their hulls' half-planes, a log-mean-exp (<= the max, so
        # conservative) at q points per leg, each clear by the margin + half a piece
        Pn, Q, q = cfg.max_keep_out_polygons, cfg.max_keep_out_edges, cfg.keep_out_leg_points
        p_poly = opti.parameter(Pn * Q, 3) if Pn else None  # a_x, a_y, b (m)
        if p_poly is not None:
            tau = cfg.keep_out_polygon_smoothing_m / S
            need = (cfg.keep_out_margin_m + p_lim[0] * p_dt / (2 * q)) / S
            for k in range(q):
                f = (k + 0.5) / q
                pts = X[:2, :-1] + f * (X[:2, 1:] - X[:2, :-1])
                for j in range(Pn):
                    rows = ca.vertcat(*[
                        p_poly[j * Q + r, 0] * pts[0, :] + p_poly[j * Q + r, 1] * pts[1, :]
                        - p_poly[j * Q + r, 2] / S for r in range(Q)])
                    per_leg(_smooth_mean(rows, tau) >= need)
        self._leg_blocks = tuple(blocks)

        common = {
            "print_level": 0,
            "sb": "yes",
            "max_iter": cfg.max_iter,
            "tol": cfg.tol,
            "acceptable_tol": cfg.acceptable_tol,
            "acceptable_iter": cfg.acceptable_iter,
            "acceptable_constr_viol_tol": 1e-5,
            "constr_viol_tol": 1e-6,  # scaled units: 0.1 mm of height, 0.2 mm of leg length
            "mu_target": cfg.barrier_target,
            "mumps_scaling": 0,
            "mumps_permuting_scaling": 0,
        }
        warm = {
            "mu_init": 1e-4,
            "warm_start_init_point": "yes",
            "warm_start_bound_push": 1e-6,
            "warm_start_mult_bound_push": 1e-6,
            "warm_start_slack_bound_push": 1e-6,
        }
        args = [p_prior, p_start, p_vel, p_dt, p_lim, p_band, p_fence, p_keep,
                *([p_poly] if p_poly is not None else []), X, Fv, opti.lam_g]
        outs = [X, Fv, opti.lam_g, opti.f]
        plugin = {"expand": True, "print_time": False, "show_eval_warnings": False}
        # the same problem, two Ipopt set-ups: a cold start from the default barrier and
        # a primal-dual warm start with a small one
        if not occlusion:  # the problem with the loss is only ever solved warm
            opti.solver("ipopt", plugin, common | cfg.ipopt_options)
            self._solve_cold = opti.to_function("optimal_plan_cold", args, outs)
        opti.solver("ipopt", plugin, common | warm | cfg.ipopt_options)
        self._solve_warm = opti.to_function("optimal_plan_warm", args, outs)
        self._opti = opti
        self._n_g = opti.ng

    # ---------------------------------------------------------------- parameters
    def _fence_rows(self, fence: Geofence | None) -> np.ndarray:
        E = self.cfg.max_fence_edges
        rows = np.tile([0.0, 0.0, _FAR_M], (E, 1))
        if fence is not None:
            hp = fence.half_planes
            if len(hp) > E:
                raise ValueError(f"geofence has {len(hp)} edges; the planner holds {E}")
            rows[: len(hp)] = hp
            rows[: len(hp), 2] -= self.cfg.fence_margin_m
        return rows

    def _keep_rows(self, keep_outs: Sequence[KeepOut], leg_m: float) -> np.ndarray:
        M = self.cfg.max_keep_outs
        if len(keep_outs) > M:
            raise ValueError(f"{len(keep_outs)} keep-outs; the planner holds {M}")
        rows = np.tile([_FAR_M, _FAR_M, 1.0], (M, 1))
        for j, ko in enumerate(keep_outs):
            r = ko.radius_m + self.cfg.keep_out_margin_m
            rows[j] = (ko.east_m, ko.north_m, r * r + 0.25 * leg_m * leg_m)
        return rows

    def _poly_rows(self, polygons: Sequence[KeepOutPolygon]) -> np.ndarray:
        Pn, Q = self.cfg.max_keep_out_polygons, self.cfg.max_keep_out_edges
        if len(polygons) > Pn:
            raise ValueError(f"{len(polygons)} keep-out polygons; the planner holds {Pn}")
        rows = np.tile([0.0, 0.0, -_FAR_M], (Pn * Q, 1))
        for j, poly in enumerate(polygons):
            hp = poly.hull_half_planes()
            if len(hp) > Q:
                raise ValueError(f"a keep-out polygon's hull has {len(hp)} edges; the planner "
                                 f"holds {Q}")
            rows[j * Q:(j + 1) * Q] = hp[0]  # unused edges repeat one (the max is unchanged)
            rows[j * Q:j * Q + len(hp)] = hp
        return rows

    # ---------------------------------------------------------------- check
    def check(
        self,
        waypoints_enu_m: np.ndarray,
        start_enu_m: Sequence[float],
        start_vel_m_s: Sequence[float],
        dt_s: float,
        *,
        fence: Geofence | None = None,
        keep_outs: Sequence[KeepOut] = (),
        agl_band_m: tuple[float, float] | None = None,
        limits: tuple[float, float, float] | None = None,
        keep_out_polygons: Sequence[KeepOutPolygon] = (),
    ) -> list[str]:
        """Every constraint of the problem, checked numerically; empty when all hold.

        The altitude band is checked every 1 m along the straight legs; the first leg,
        which starts where the drone already is, against :meth:`first_leg_band`."""
        cfg = self.cfg
        W = np.asarray(waypoints_enu_m, dtype=float)
        tol = cfg.check_tolerance_m
        vmax, amax, vz = limits or (cfg.max_speed_m_s, cfg.max_accel_m_s2, cfg.max_climb_m_s)
        lo, hi = agl_band_m or (cfg.agl_min_m, cfg.agl_max_m)
        out: list[str] = []
        if not np.all(np.isfinite(W)):
            return ["non-finite waypoints"]
        if np.linalg.norm(W[0] - np.asarray(start_enu_m, dtype=float)) > tol:
            out.append("does not start at the current pose")
        step = np.diff(W, axis=0)
        speed = np.linalg.norm(step, axis=1) / dt_s
        if speed.max() > vmax + tol / dt_s:
            out.append(f"speed {speed.max():.2f} m/s > {vmax:g}")
        climb = np.abs(step[:, 2]) / dt_s
        if climb.max() > vz + tol / dt_s:
            out.append(f"climb rate {climb.max():.2f} m/s > {vz:g}")
        vel = np.vstack([np.asarray(start_vel_m_s, dtype=float), step / dt_s])
        accel = np.linalg.norm(np.diff(vel, axis=0), axis=1) / dt_s
        if accel.max() > amax + tol / dt_s**2:
            out.append(f"acceleration {accel.max():.2f} m/s^2 > {amax:g}")
        # the altitude band along the legs (every 1 m), not only at the waypoints: a
        # straight leg over a hill top sags towards the ground between its ends
        lo1, hi1 = self.first_leg_band(W[0], (lo, hi), vmax, dt_s)
        for name, pts, (b_lo, b_hi) in (
            ("", densify(W[1:], 1.0), (lo, hi)),
            ("first leg: ", densify(W[:2], 1.0)[1:], (lo1, hi1)),
        ):
            agl = pts[:, 2] - np.asarray(cfg.terrain.height_m(pts[:, 0], pts[:, 1]), dtype=float)
            if agl.min() < b_lo - tol or agl.max() > b_hi + tol:
                out.append(
                    f"{name}height above terrain {agl.min():.2f}..{agl.max():.2f} m"
                    f" outside {b_lo:g}..{b_hi:g}"
                )
        out += airspace_violations(W, fence, [*keep_outs, *keep_out_polygons], tolerance_m=tol)
        return out

    def first_leg_band(
        self, start_enu_m: Sequence[float], band: tuple[float, float], v_max: float, dt_s: float
    ) -> tuple[float, float]:
        """The band on the first leg: widened to the start's own height above terrain,
        less (more) the sag margin of half a leg, which is what the NLP can guarantee
        from a start it cannot move."""
        p = np.asarray(start_enu_m, dtype=float).reshape(3)
        agl0 = float(p[2] - np.asarray(self.cfg.terrain.height_m(p[0], p[1]), dtype=float))
        m_lo, m_hi = sag_margins_m(self.cfg.terrain, v_max * dt_s / 2.0)
        return min(band[0], agl0 - m_lo), max(band[1], agl0 + m_hi)

    # ---------------------------------------------------------------- plan
    def reset_warm_start(self) -> None:
        self._warm = None

    @property
    def warm_state(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The last checked solution (primal, dual) the next solve starts from, or None:
        users sharing one planner keep theirs apart by swapping it."""
        return self._warm

    @warm_state.setter
    def warm_state(self, value: tuple[np.ndarray, np.ndarray] | None) -> None:
        self._warm = value

    def plan(
        self,
        prior_mean_enu_m: Sequence[float],
        prior_cov_m2: np.ndarray,
        start_enu_m: Sequence[float],
        start_vel_m_s: Sequence[float] = (0.0, 0.0, 0.0),
        *,
        horizon_s: float | None = None,
        fence: Geofence | None = None,
        keep_outs: Sequence[KeepOut] = (),
        agl_band_m: tuple[float, float] | None = None,
        limits: tuple[float, float, float] | None = None,
        origin: tuple[float, float, float] = PAPER_SITE,
        prior_points_enu_m: np.ndarray | None = None,
        warm_start: bool = True,
        keep_out_polygons: Sequence[KeepOutPolygon] = (),
    ) -> PlanResult:
        """Plan the next horizon from the current pose against the prior N(mean, cov).

        ``limits`` = (v_max, a_max, v_z); ``agl_band_m`` = (min, max) height above terrain;
        ``prior_points_enu_m`` (K x 3) replaces the cubature points when given.
        """
        cfg = self.cfg
        N, K = cfg.n_waypoints, cfg.n_prior_points
        horizon = cfg.horizon_s if horizon_s is None else float(horizon_s)
        if not (math.isfinite(horizon) and horizon > 0):
            raise ValueError("horizon_s must be positive")
        dt = horizon / (N - 1)
        lim = tuple(
            float(v) for v in (limits or (cfg.max_speed_m_s, cfg.max_accel_m_s2, cfg.max_climb_m_s))
        )
        band = tuple(float(v) for v in (agl_band_m or (cfg.agl_min_m, cfg.agl_max_m)))
        if not (all(math.isfinite(v) and v > 0 for v in lim) and band[0] < band[1]):
            raise ValueError("limits must be positive and the altitude band non-empty")
        start = np.asarray(start_enu_m, dtype=float).reshape(3)
        vel = np.asarray(start_vel_m_s, dtype=float).reshape(3)
        mean = np.asarray(prior_mean_enu_m, dtype=float).reshape(3)
        if not (
            np.all(np.isfinite(start)) and np.all(np.isfinite(vel)) and np.all(np.isfinite(mean))
        ):
            raise ValueError("non-finite start pose or prior")
        if prior_points_enu_m is None:
            pts = prior_points(mean, prior_cov_m2, K)
        else:
            pts = np.asarray(prior_points_enu_m, dtype=float).reshape(K, 3)
        if not np.all(np.isfinite(pts)):
            raise ValueError("non-finite prior points")
        if fence is not None and fence.signed_distance_m(start[None, :2])[0] > 0:
            raise ValueError("the start pose is outside the geofence")
        for ko in keep_outs:
            if math.hypot(start[0] - ko.east_m, start[1] - ko.north_m) < ko.radius_m:
                raise ValueError("the start pose is inside a keep-out cylinder")
        for poly in keep_out_polygons:
            if poly.signed_distance_m(start[None, :2])[0] < 0:
                raise ValueError("the start pose is inside a keep-out polygon")
        fence_rows = self._fence_rows(fence)
        keep_rows = self._keep_rows(keep_outs, lim[0] * dt)
        poly = self._poly_rows(keep_out_polygons)  # refuses more than the problem holds
        poly_rows = [poly] if cfg.max_keep_out_polygons else []

        agl0 = float(start[2] - np.asarray(cfg.terrain.height_m(start[0], start[1]), dtype=float))
        band4 = (*band, min(band[0], agl0), max(band[1], agl0))

        S = cfg.position_scale_m
        if warm_start and self._warm is not None:
            solve = self._solve_warm
            x0, lam0 = self._shift(*self._warm, start / S)
            guess = "previous plan, shifted"
        else:
            solve = self._solve_cold
            r0, W0 = self._initial_guess(start, vel, mean, pts, dt, lim, band)
            if keep_out_polygons:
                W0 = self._stop_before(W0, keep_out_polygons, lim[0] * dt)
            x0 = W0.T / S
            lam0 = np.zeros(self._n_g)
            guess = f"orbit r={r0:g} m"
        f0 = np.column_stack([_info_entries(x0.T * S, s, cfg, dt) for s in pts])
        f0 /= cfg.information_scale
        params = (pts.T, start, vel, dt, lim, band4, fence_rows, keep_rows, *poly_rows)
        t0 = time.perf_counter()
        error = None
        m_lo, m_hi = sag_margins_m(cfg.terrain, lim[0] * dt / 2.0)
        if band[0] + m_lo > band[1] - m_hi or band4[2] + m_lo > band4[3] - m_hi:
            # the legs' sag margins over the terrain's sharpest curvature (a cliff in a
            # DEM) leave no height: ill-posed bounds, which CasADi would refuse (printing
            # every input on stderr)
            error = (f"not solved: the terrain's curvature shuts the height band "
                     f"{band[0]:g}..{band[1]:g} m (legs may sag {m_lo:.1f} m and bulge "
                     f"{m_hi:.1f} m; shorten the horizon)")
            x, lam, stats = x0, lam0, {"return_status": error}
        else:
            try:
                x, _fv, lam, _ = solve(*params, x0, f0, lam0)
                stats = solve.stats()
            except RuntimeError as exc:  # CasADi evaluation errors: no optimiser path
                error = f"error: {exc}".splitlines()[0]
                x, lam, stats = x0, lam0, {"return_status": error}
        solve_time = time.perf_counter() - t0
        status = str(stats.get("return_status", "unknown"))
        W = np.asarray(x).T * S
        violations = self.check(
            W, start, vel, dt, fence=fence, keep_outs=keep_outs, agl_band_m=band, limits=lim,
            keep_out_polygons=keep_out_polygons,
        )
        occlusion = ""
        if self._solve_occluded is not None and error is None and not violations:
            occlusion = "in view"
            if np.any(link_loss_db(W, pts, cfg) > 0.0):  # the terrain hides part of it
                occlusion, x, lam, W, stats, dt_solve = self._occluded_stage(
                    params, x, lam, W, stats, pts, dt, start, vel, band, lim, fence,
                    [*keep_outs, *keep_out_polygons])
                solve_time += dt_solve
                status = str(stats.get("return_status", "unknown"))
        # only an optimiser path that passed the check warm-starts the next solve
        self._warm = None if violations or error else (np.asarray(x), np.asarray(lam).ravel())
        fallback = None
        feasible = not violations
        if error is not None:
            # the solver raised: what we hold is the initial guess, never an optimiser result
            what = error if error.startswith("not solved") else f"CasADi {error}"
            violations = [f"no solver path ({what})", *violations]
            if feasible:
                fallback = f"initial guess: {guess}"
        if not feasible:
            ok, r, W = self._fallback(start, vel, mean, pts, dt, lim, band, fence,
                                      [*keep_outs, *keep_out_polygons])
            fallback = f"orbit r={r:g} m"
            feasible = ok
        return PlanResult(
            trajectory=waypoints_to_trajectory(W, dt, cfg.output_dt_s, origin, "optimal"),
            waypoints_enu_m=W,
            dt_s=dt,
            objective=planning_objective(W, pts, dt, cfg),
            status=status,
            solver_success=bool(stats.get("success", False)),
            iterations=int(stats.get("iter_count", -1)),
            solve_time_s=solve_time,
            violations=tuple(violations),
            feasible=feasible,
            fallback=fallback,
            occlusion=occlusion,
        )

    def _occluded_stage(self, params, x, lam, W, stats, pts, dt, start, vel, band, lim, fence,
                        keep_outs):
        """The second solve, when the terrain hides part of the first plan from the likely
        area: the problem with the terrain's loss, warm-started from the first plan; its
        path is kept when it passes the check and scores higher on the objective with
        the loss (:func:`planning_objective`). Without the loss every objective is at
        least as high, so a first plan in full view needs no second solve."""
        cfg, S = self.cfg, self.cfg.position_scale_m
        loss0 = np.asarray(self._loss_fn(x, pts.T), dtype=float).reshape(-1)
        f0 = np.column_stack([_info_entries(W, s, cfg, dt, loss0) for s in pts])
        f0 /= cfg.information_scale
        t0 = time.perf_counter()
        try:
            x2, _fv, lam2, _ = self._solve_occluded(*params, x, f0, lam)
            stats2 = self._solve_occluded.stats()
        except RuntimeError:
            return "hidden in part, the second solve failed", x, lam, W, stats, (
                time.perf_counter() - t0)
        elapsed = time.perf_counter() - t0
        stats2 = {**stats2, "iter_count": int(stats.get("iter_count", 0))
                  + int(stats2.get("iter_count", 0))}
        W2 = np.asarray(x2).T * S
        ok = not self.check(
            W2, start, vel, dt, fence=fence, agl_band_m=band, limits=lim,
            keep_outs=[k for k in keep_outs if isinstance(k, KeepOut)],
            keep_out_polygons=[k for k in keep_outs if isinstance(k, KeepOutPolygon)],
        )
        if ok and planning_objective(W2, pts, dt, cfg) > planning_objective(W, pts, dt, cfg):
            return "replanned in view", np.asarray(x2), np.asarray(lam2), W2, stats2, elapsed
        return "hidden in part, kept", x, lam, W, {**stats, "iter_count":
                                                    stats2["iter_count"]}, elapsed

    def _orbits(self, start, vel, mean, pts, dt, lim, band):
        """Guidance orbits about the prior mean at the start's height above terrain."""
        cfg = self.cfg
        agl0 = start[2] - float(np.asarray(cfg.terrain.height_m(start[0], start[1])))
        ground = float(np.asarray(cfg.terrain.height_m(mean[0], mean[1])))
        alt = ground + float(np.clip(agl0, *band))
        for r in cfg.fallback_radii_m:
            W = guidance_orbit(start, vel, mean, r, alt, cfg.n_waypoints, dt, *lim)
            yield r, W, planning_objective(W, pts, dt, cfg)

    def _stop_before(self, W: np.ndarray, polygons: Sequence[KeepOutPolygon],
                     leg_m: float) -> np.ndarray:
        """The guess waits at its last waypoint whose leg stays clear of the polygons'
        hulls (the NLP cannot carry a path across a keep-out: it would be infeasible on
        both sides; Ipopt moves the waiting points along the clear side)."""
        need = self.cfg.keep_out_margin_m + leg_m / (2 * self.cfg.keep_out_leg_points)
        hps = [poly.hull_half_planes() for poly in polygons]
        W = W.copy()
        for i in range(1, len(W)):
            seg = densify(W[i - 1:i + 1], 1.0)[:, :2]
            if any(((seg @ hp[:, :2].T - hp[:, 2]).max(axis=1) < need).any() for hp in hps):
                W[i:] = W[i - 1]
                break
        return W

    def _initial_guess(self, start, vel, mean, pts, dt, lim, band):
        """Cold start: the guidance orbit with the best objective."""
        r, W, _ = max(self._orbits(start, vel, mean, pts, dt, lim, band), key=lambda c: c[2])
        return r, W

    def _fallback(self, start, vel, mean, pts, dt, lim, band, fence, keep_outs):
        """Best feasible guidance orbit (feasible first, then by objective)."""
        best = None
        for r, W, obj in self._orbits(start, vel, mean, pts, dt, lim, band):
            ok = not self.check(
                W, start, vel, dt, fence=fence, agl_band_m=band, limits=lim,
                keep_outs=[k for k in keep_outs if isinstance(k, KeepOut)],
                keep_out_polygons=[k for k in keep_outs if isinstance(k, KeepOutPolygon)],
            )
            if best is None or (ok, obj) > (best[0], best[3]):
                best = (ok, r, W, obj)
        assert best is not None
        return best[:3]

    def _shift(
        self, x_prev: np.ndarray, lam_prev: np.ndarray, start_scaled: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Warm start for a receding horizon: drop the waypoints already flown (the new
        start is nearest to waypoint j of the previous plan), extrapolate the tail, and
        shift the multipliers of the per-leg constraints alike."""
        x = np.asarray(x_prev, dtype=float).copy()
        lam = np.asarray(lam_prev, dtype=float).copy()
        j = int(np.argmin(np.linalg.norm(x - start_scaled[:, None], axis=0)))
        if j > 0:
            tail = x[:, -1:] + (x[:, -1:] - x[:, -2:-1]) * np.arange(1, j + 1)[None, :]
            x = np.hstack([x[:, j:], tail])
            for first_row, rows in self._leg_blocks:
                block = lam[first_row : first_row + rows]
                k = min(j, rows - 1)
                lam[first_row : first_row + rows] = np.append(block[k:], np.repeat(block[-1], k))
        x[:, 0] = start_scaled
        return x, lam
