"""Kinematic multirotor flying a timed path, simulated as whole-flight NumPy arrays.

The vehicle flies the geometry of a :class:`estimator.records.Trajectory` at the
reference speed wherever its limits allow and slower where they do not (it then falls
behind the reference clock and does not catch up). Every limit is a speed bound along
the path, so the flight is one vectorised speed profile:

- speed: ``max_speed_mps`` (air speed: a head wind lowers the reachable ground speed);
- turns: lateral acceleration v^2 kappa <= a_lat and yaw rate v kappa <= r_max (the nose
  follows the course); sharper corners than ``sharp_turn_deg`` per path step are flown
  stop-turn-go, turning on the spot at the yaw-rate limit;
- climb: |dz/ds| v <= max vertical speed;
- along-track acceleration <= ``max_accel_mps2`` (forward and backward passes over v^2,
  closed-form with cumulative minima); the flight starts and ends at rest.

A steady wind pushes the vehicle a little downwind across its track, and a slow
Gauss-Markov wander stands for the position controller's tracking error. Positions are
those of the GNSS antenna (the initiator's reference point); the WiFi antenna sits at
``lever_arm_m`` in the body frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from estimator.geodesy import ExactENU
from estimator.records import Trajectory
from sim._config import check_finite, check_positive
from sim._random import smooth_gauss_markov
from sim.world import World


@dataclass(frozen=True, kw_only=True)
class VehicleConfig:
    """Limits and disturbances of the kinematic multirotor (DJI Matrice 350 RTK class)."""

    max_speed_mps: float = 15.0  # M350 RTK tops at 23 m/s; survey flying is slower
    max_accel_mps2: float = 2.0
    max_lateral_accel_mps2: float = 3.0
    max_yaw_rate_dps: float = 60.0
    max_vertical_speed_mps: float = 3.0
    sharp_turn_deg: float = 20.0  # heading change per path step flown stop-turn-go
    wind_enu_mps: tuple[float, float] = (0.0, 0.0)  # steady horizontal wind (towards)
    wind_drift_s: float = 0.1  # cross-track offset per m/s of cross wind
    tracking_sigma_m: float = 0.15  # position-controller wander (per axis)
    tracking_tau_s: float = 4.0
    lever_arm_m: tuple[float, float, float] = (0.0, 0.0, 0.0)  # WiFi antenna: fwd, left, up
    path_step_m: float = 0.5
    sample_dt_s: float = 0.05

    def __post_init__(self) -> None:
        for name in (
            "max_speed_mps",
            "max_accel_mps2",
            "max_lateral_accel_mps2",
            "max_yaw_rate_dps",
            "max_vertical_speed_mps",
            "sharp_turn_deg",
            "tracking_tau_s",
            "path_step_m",
            "sample_dt_s",
        ):
            check_positive(name, getattr(self, name))
        check_positive("wind_drift_s", self.wind_drift_s, allow_zero=True)
        check_positive("tracking_sigma_m", self.tracking_sigma_m, allow_zero=True)
        for i, w in enumerate(self.wind_enu_mps):
            check_finite(f"wind_enu_mps[{i}]", w)
        for i, a in enumerate(self.lever_arm_m):
            check_finite(f"lever_arm_m[{i}]", a)
        if self.sample_dt_s > 0.5:
            raise ValueError("sample_dt_s above 0.5 s cannot resolve 10 Hz GNSS")
        if math.hypot(*self.wind_enu_mps) >= self.max_speed_mps:
            raise ValueError("wind at or above max_speed_mps: the vehicle cannot make headway")


@dataclass(frozen=True, eq=False)
class VehicleTrack:
    """The flown path on a uniform time grid (ENU metres in the world frame).

    ``enu_m`` is the GNSS antenna, ``yaw_rad`` the nose direction (counter-clockwise
    from east, unwrapped: continuous), ``ground_m`` the terrain height beneath.
    """

    t_s: np.ndarray
    enu_m: np.ndarray
    vel_enu_mps: np.ndarray
    yaw_rad: np.ndarray
    ground_m: np.ndarray
    lever_arm_m: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __repr__(self) -> str:
        return f"VehicleTrack({len(self.t_s)} samples, {self.duration_s:.1f} s)"

    @property
    def duration_s(self) -> float:
        return float(self.t_s[-1] - self.t_s[0])

    @property
    def agl_m(self) -> np.ndarray:
        """Height above the ground beneath, per sample."""
        return self.enu_m[:, 2] - self.ground_m

    @property
    def speed_mps(self) -> np.ndarray:
        return np.linalg.norm(self.vel_enu_mps, axis=1)

    def position_at(self, t_s: ArrayLike) -> np.ndarray:
        """(M, 3) GNSS-antenna positions at times ``t_s`` (clamped to the flight)."""
        t = np.asarray(t_s, dtype=float)
        return np.column_stack([np.interp(t, self.t_s, self.enu_m[:, i]) for i in range(3)])

    def antenna_at(self, t_s: ArrayLike) -> np.ndarray:
        """(M, 3) WiFi-antenna positions: GNSS antenna plus the yawed lever arm."""
        p = self.position_at(t_s)
        fwd, left, up = self.lever_arm_m
        if fwd == 0.0 and left == 0.0 and up == 0.0:
            return p
        yaw = np.interp(np.asarray(t_s, dtype=float), self.t_s, self.yaw_rad)
        c, s = np.cos(yaw), np.sin(yaw)
        p[:, 0] += c * fwd - s * left
        p[:, 1] += s * fwd + c * left
        p[:, 2] += up
        return p


def _reference_in_world(traj: Trajectory, world: World) -> tuple[np.ndarray, np.ndarray]:
    """Reference (e, n) and z (meaning per ``height_ref``) in the world's frame."""
    p = traj.enu_m
    lat0, lon0, h0 = traj.origin
    o = world.origin
    if abs(lat0 - o.lat_deg) < 1e-10 and abs(lon0 - o.lon_deg) < 1e-10 and abs(h0 - o.h_m) < 1e-6:
        return p[:, :2].copy(), p[:, 2].copy()
    src = ExactENU(lat0, lon0, h0)
    if traj.height_ref == "terrain":
        lat, lon, alt = src.to_geodetic(p[:, 0], p[:, 1], np.zeros(len(p)))
        e, n, _ = world.frame.to_enu(lat, lon, alt)
        return np.column_stack([e, n]), p[:, 2].copy()
    lat, lon, alt = src.to_geodetic(p[:, 0], p[:, 1], p[:, 2])
    e, n, u = world.frame.to_enu(lat, lon, alt)
    return np.column_stack([e, n]), np.asarray(u, dtype=float)


def _densify(
    t: np.ndarray, en: np.ndarray, z: np.ndarray, step_m: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Split segments into pieces of at most ``step_m`` (horizontally and vertically)."""
    d_en = np.diff(en, axis=0)
    seg = np.maximum(np.hypot(d_en[:, 0], d_en[:, 1]), np.abs(np.diff(z)))
    pieces = np.maximum(1, np.ceil(seg / step_m)).astype(np.intp)
    idx = np.repeat(np.arange(len(seg)), pieces)
    first = np.repeat(np.cumsum(pieces) - pieces, pieces)
    frac = (np.arange(len(idx)) - first) / np.repeat(pieces, pieces)

    def lerp(a: np.ndarray) -> np.ndarray:
        da = np.diff(a, axis=0)
        f = frac if a.ndim == 1 else frac[:, None]
        return np.concatenate([a[idx] + f * da[idx], a[-1:]])

    return lerp(t), lerp(en), lerp(z)


def _forward_fill(values: np.ndarray, valid: np.ndarray, default: float) -> np.ndarray:
    if not valid.any():
        return np.full(len(values), default)
    idx = np.where(valid, np.arange(len(values)), -1)
    idx = np.maximum.accumulate(idx)
    idx[idx < 0] = int(np.argmax(valid))  # before the first valid value: take it
    return values[idx]


def _round_corners(x: np.ndarray) -> np.ndarray:
    """Smooth a uniformly sampled coordinate with a (1 2 3 2 1)/9 kernel, ends fixed."""
    if len(x) < 5:
        return x
    out = x.copy()
    out[2:-2] = (x[:-4] + 2 * x[1:-3] + 3 * x[2:-2] + 2 * x[3:-1] + x[4:]) / 9.0
    return out


def _hover_track(
    t_end: float, p: np.ndarray, world: World, cfg: VehicleConfig, rng: np.random.Generator
) -> VehicleTrack:
    n = math.ceil(t_end / cfg.sample_dt_s) + 1
    t = np.arange(n) * cfg.sample_dt_s
    enu = np.repeat(p[None, :], n, axis=0)
    enu[:, :2] += cfg.wind_drift_s * np.asarray(cfg.wind_enu_mps)
    enu += smooth_gauss_markov(
        rng, n, cfg.sample_dt_s, np.full(3, cfg.tracking_sigma_m), cfg.tracking_tau_s
    )
    vel = np.gradient(enu, cfg.sample_dt_s, axis=0) if n > 1 else np.zeros_like(enu)
    ground = world.ground_m(enu[:, 0], enu[:, 1])
    return VehicleTrack(t, enu, vel, np.zeros(n), ground, cfg.lever_arm_m)


UNDERGROUND_TOLERANCE_M = 1.0  # wander and corner rounding may graze the ground by less


def fly(
    traj: Trajectory,
    world: World,
    cfg: VehicleConfig,
    rng: np.random.Generator,
) -> VehicleTrack:
    """Fly ``traj`` over ``world`` within the limits of ``cfg``; the whole flight at once.

    Raises ``ValueError`` for a flight that would go below the terrain: that is almost
    always a trajectory whose heights refer to another origin height or datum, and a
    silent underground flight would still "measure" ranges.
    """
    track = _fly(traj, world, cfg, rng)
    agl = track.agl_m
    k = int(np.argmin(agl))
    if agl[k] < -UNDERGROUND_TOLERANCE_M:
        h0 = traj.origin[2]
        raise ValueError(
            f"trajectory {traj.name or ''!s} goes {-agl[k]:.1f} m below the terrain at "
            f"t = {track.t_s[k]:.1f} s: check its height reference "
            f"({traj.height_ref}) and origin height ({h0:g} m; the world's is "
            f"{world.origin.h_m:g} m)"
        )
    return track


def _fly(
    traj: Trajectory,
    world: World,
    cfg: VehicleConfig,
    rng: np.random.Generator,
) -> VehicleTrack:
    if len(traj.t_s) == 0:
        raise ValueError("cannot fly an empty trajectory")
    t_ref = traj.t_s - traj.t_s[0]
    en_ref, z_ref = _reference_in_world(traj, world)
    terrain_ref = traj.height_ref == "terrain"
    if len(t_ref) == 1:
        z0 = z_ref[0] + (world.ground_m(*en_ref[0]) if terrain_ref else 0.0)
        return _hover_track(0.0, np.array([*en_ref[0], z0]), world, cfg, rng)

    # 1. dense reference, absolute heights, 3-D arc length; zero-length steps are hovers
    t_d, en_d, zr_d = _densify(t_ref, en_ref, z_ref, cfg.path_step_m)
    z_d = zr_d + world.ground_m(en_d[:, 0], en_d[:, 1]) if terrain_ref else zr_d
    p_d = np.column_stack([en_d, z_d])
    seg = np.linalg.norm(np.diff(p_d, axis=0), axis=1)
    dt_d = np.diff(t_d)
    moving = seg > 1e-9
    s_d = np.concatenate([[0.0], np.cumsum(seg)])
    total = float(s_d[-1])
    if total < cfg.path_step_m:
        return _hover_track(float(t_ref[-1]), p_d[0], world, cfg, rng)
    keep = np.concatenate([[True], moving])
    t_move = np.concatenate([[0.0], np.cumsum(np.where(moving, dt_d, 0.0))])[keep]
    s_keep = s_d[keep]
    hover_s = s_d[:-1][~moving & (dt_d > 0)]
    hover_dt = dt_d[~moving & (dt_d > 0)]

    # 2. uniform resampling in arc length
    m = math.ceil(total / cfg.path_step_m)
    s_u = np.linspace(0.0, total, m + 1)
    ds = total / m
    # corners are rounded over +-2 path steps: a multirotor does not fly a kink
    e_u = _round_corners(np.interp(s_u, s_keep, en_d[keep, 0]))
    n_u = _round_corners(np.interp(s_u, s_keep, en_d[keep, 1]))
    if terrain_ref:
        z_u = np.interp(s_u, s_keep, zr_d[keep]) + world.ground_m(e_u, n_u)
    else:
        z_u = np.interp(s_u, s_keep, z_d[keep])
    t_ref_u = np.interp(s_u, s_keep, t_move)
    dwell = np.zeros(m + 1)
    np.add.at(dwell, np.rint(hover_s / ds).astype(np.intp).clip(0, m), hover_dt)

    # 3. speed limits per cell (between nodes) and per node
    de, dn, dz = np.diff(e_u), np.diff(n_u), np.diff(z_u)
    h_len = np.hypot(de, dn)
    has_heading = h_len > 1e-6 * ds
    psi = np.unwrap(_forward_fill(np.arctan2(dn, de), has_heading, 0.0))
    dt_ref = np.diff(t_ref_u)
    with np.errstate(divide="ignore"):
        v_ref = np.where(dt_ref > 0, ds / dt_ref, np.inf)  # the reference's own speed
        v_climb = cfg.max_vertical_speed_mps * ds / np.abs(dz)
    v_cell = np.minimum(np.minimum(v_ref, v_climb), cfg.max_speed_mps)
    we, wn = cfg.wind_enu_mps
    if we or wn:
        w_along = we * np.cos(psi) + wn * np.sin(psi)
        w_cross2 = np.maximum(we * we + wn * wn - w_along * w_along, 0.0)
        v_cell = np.minimum(v_cell, w_along + np.sqrt(cfg.max_speed_mps**2 - w_cross2))
    v_cell = np.maximum(v_cell, 0.05)

    yaw_rate = math.radians(cfg.max_yaw_rate_dps)
    turn = np.abs(np.diff(psi))  # at interior nodes 1..m-1
    sharp = turn > math.radians(cfg.sharp_turn_deg)
    arc = 0.5 * (h_len[:-1] + h_len[1:])
    with np.errstate(divide="ignore", invalid="ignore"):
        curv = np.where(turn > 0, turn / np.maximum(arc, 1e-9), 0.0)
        v_turn = np.minimum(
            np.where(curv > 0, yaw_rate / curv, np.inf),
            np.where(curv > 0, np.sqrt(cfg.max_lateral_accel_mps2 / curv), np.inf),
        )
    v_node = np.empty(m + 1)
    v_node[1:-1] = np.minimum(np.minimum(v_cell[:-1], v_cell[1:]), v_turn)
    v_node[1:-1][sharp] = 0.0
    v_node[[0, -1]] = 0.0
    v_node[dwell > 0] = 0.0
    dwell[1:-1] += np.where(sharp, turn / yaw_rate, 0.0)

    # 4. acceleration limits: forward and backward passes on v^2 in closed form
    lim2 = v_node * v_node
    c = 2.0 * cfg.max_accel_mps2 * ds
    i_c = np.arange(m + 1) * c
    fwd = i_c + np.minimum.accumulate(lim2 - i_c)
    bwd = np.minimum.accumulate((lim2 + i_c)[::-1])[::-1] - i_c
    v = np.sqrt(np.maximum(np.minimum(fwd, bwd), 0.0))

    # 5. node times (arrival, departure after any dwell) and the uniform time grid
    vsum = v[:-1] + v[1:]
    with np.errstate(divide="ignore"):
        dt_cell = np.where(vsum > 1e-9, 2.0 * ds / vsum, 2.0 * math.sqrt(ds / cfg.max_accel_mps2))
    arrive = np.concatenate([[0.0], np.cumsum(dt_cell + dwell[:-1])])
    depart = arrive + dwell
    has_dwell = dwell > 0
    psi_in = np.concatenate([psi[:1], psi])
    psi_out = np.concatenate([psi, psi[-1:]])
    knots_t = np.column_stack([arrive, depart]).ravel()
    knots_psi = np.column_stack(
        [np.where(has_dwell, psi_in, 0.5 * (psi_in + psi_out)), psi_out]
    ).ravel()
    mask = np.column_stack([np.ones(m + 1, dtype=bool), has_dwell]).ravel()

    dt = cfg.sample_dt_s
    n_t = math.ceil(depart[-1] / dt) + 1
    t = np.arange(n_t) * dt
    # arc length at t: constant acceleration within each cell, still while dwelling
    node = np.clip(np.searchsorted(arrive, t, side="right") - 1, 0, m)
    cell = np.minimum(node, m - 1)
    tau = np.clip(t - depart[cell], 0.0, dt_cell[cell])
    x = tau / dt_cell[cell]
    a_cell = (v[cell + 1] - v[cell]) / dt_cell[cell]
    along = np.where(
        vsum[cell] > 1e-9,
        v[cell] * tau + 0.5 * a_cell * tau * tau,
        ds * x * x * (3.0 - 2.0 * x),  # from rest to rest within one cell
    )
    s_t = np.where((node == m) | (t < depart[node]), s_u[node], s_u[cell] + along)
    yaw = np.interp(t, knots_t[mask], knots_psi[mask])
    enu = np.column_stack(
        [np.interp(s_t, s_u, e_u), np.interp(s_t, s_u, n_u), np.interp(s_t, s_u, z_u)]
    )

    # 6. disturbances: downwind drift across the track, controller wander
    if we or wn:
        vel = np.gradient(enu[:, :2], dt, axis=0)
        sp = np.hypot(vel[:, 0], vel[:, 1])
        u = np.where(sp[:, None] > 0.3, vel / np.maximum(sp, 1e-9)[:, None], 0.0)
        w = np.array([we, wn])
        w_along = u @ w
        enu[:, :2] += cfg.wind_drift_s * (w[None, :] - w_along[:, None] * u)
    if cfg.tracking_sigma_m > 0:
        sigma = np.full(3, cfg.tracking_sigma_m)
        enu += smooth_gauss_markov(rng, n_t, dt, sigma, cfg.tracking_tau_s)
    vel = np.gradient(enu, dt, axis=0)
    ground = world.ground_m(enu[:, 0], enu[:, 1])
    return VehicleTrack(t, enu, vel, yaw, ground, cfg.lever_arm_m)
