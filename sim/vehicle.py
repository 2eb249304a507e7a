"""Kinematic multirotor, stepped in time: from any state toward a setpoint or along a path.

The vehicle is a point mass whose velocity follows a guidance command within its
limits, integrated on an absolute time grid (``sample_dt_s``, 20 Hz), so a flight
advanced in pieces is the same flight as one advanced at once. Guidance
(:class:`PathGuidance`) flies a reference path at its reference speed wherever the
limits allow and slower where they do not (the reference then waits for the vehicle
and does not catch up):

- a speed profile along the path: reference speed, ``max_speed_mps``, turn limits
  v^2 kappa <= a_lat and v kappa <= r_max (the nose follows the course), climb
  |dz/ds| v <= v_z, then a backward pass so the vehicle can brake before every corner,
  stop and path end; sharp corners are passed at ``crawl_speed_mps``;
- a feed-forward velocity along the path plus a proportional pull towards the
  reference point (``position_gain_per_s``);
- the vehicle's own limits on the command: horizontal air speed (the wind is
  subtracted), along-track and lateral acceleration, vertical speed and acceleration,
  yaw rate.

The controller navigates on what the autopilot believes: the true position plus a
navigation error (the GNSS receiver's correlated bias, when an agent flies with one:
an autopilot tracks its own estimate), so the true path is the commanded one minus
that error. A steady wind pushes the vehicle a little downwind across its track, and
a slow smooth Gauss-Markov wander stands for the position controller's tracking error;
both are added to the output (the controller does not see them). Positions are those
of the GNSS antenna (the initiator's reference point); the WiFi antenna sits at
``lever_arm_m`` in the body frame. A ground agent (``ground_height_m``) walks at that
height above the terrain.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from estimator.geodesy import ExactENU
from estimator.records import Trajectory
from sim._config import check_finite, check_positive
from sim._random import BlockedGaussMarkov
from sim.world import MAX_STRUCTURE_M, World

MIN_POSITIVE = 1e-3  # the smallest speed, step, time... a vehicle setting may take


class FlightError(ValueError):
    """A flight that cannot be flown (into the ground, an empty path...)."""


@dataclass(frozen=True, kw_only=True)
class VehicleConfig:
    """Limits and disturbances of the kinematic multirotor (DJI Matrice 350 RTK class)."""

    max_speed_mps: float = 15.0  # M350 RTK tops at 23 m/s; survey flying is slower
    max_accel_mps2: float = 2.0
    max_lateral_accel_mps2: float = 3.0
    max_yaw_rate_dps: float = 60.0
    max_vertical_speed_mps: float = 3.0
    max_vertical_accel_mps2: float = 2.0
    sharp_turn_deg: float = 20.0  # heading change per path step passed at crawl speed
    crawl_speed_mps: float = 0.3  # slowest reference speed (sharp corners)
    position_gain_per_s: float = 1.0  # P gain of the path tracker
    lag_limit_m: float = 6.0  # the reference waits while the vehicle is farther behind
    wind_enu_mps: tuple[float, float] = (0.0, 0.0)  # steady horizontal wind (towards)
    wind_drift_s: float = 0.1  # cross-track offset per m/s of cross wind
    tracking_sigma_m: float = 0.15  # position-controller wander (per axis)
    tracking_tau_s: float = 4.0
    lever_arm_m: tuple[float, float, float] = (0.0, 0.0, 0.0)  # WiFi antenna: fwd, left, up
    ground_height_m: float | None = None  # a walking ground agent: antenna above terrain
    path_step_m: float = 0.5
    sample_dt_s: float = 0.05

    def __post_init__(self) -> None:
        for name in (
            "max_speed_mps",
            "max_accel_mps2",
            "max_lateral_accel_mps2",
            "max_yaw_rate_dps",
            "max_vertical_speed_mps",
            "max_vertical_accel_mps2",
            "sharp_turn_deg",
            "crawl_speed_mps",
            "position_gain_per_s",
            "lag_limit_m",
            "tracking_tau_s",
            "path_step_m",
            "sample_dt_s",
        ):
            check_positive(name, getattr(self, name))
            if getattr(self, name) < MIN_POSITIVE:  # 1e-300: no vehicle, and no end to it
                raise ValueError(f"{name} {getattr(self, name):g} is below {MIN_POSITIVE:g}")
        check_positive("wind_drift_s", self.wind_drift_s, allow_zero=True)
        check_positive("tracking_sigma_m", self.tracking_sigma_m, allow_zero=True)
        for i, w in enumerate(self.wind_enu_mps):
            check_finite(f"wind_enu_mps[{i}]", w)
        for i, a in enumerate(self.lever_arm_m):
            check_finite(f"lever_arm_m[{i}]", a)
        if self.ground_height_m is not None:
            check_positive("ground_height_m", self.ground_height_m, allow_zero=True)
            if self.ground_height_m > MAX_STRUCTURE_M:
                raise ValueError(f"ground_height_m {self.ground_height_m:g} m is beyond "
                                 f"{MAX_STRUCTURE_M:g} m")
        if self.sample_dt_s > 0.5:
            raise ValueError("sample_dt_s above 0.5 s cannot resolve 10 Hz GNSS")
        if self.crawl_speed_mps >= self.max_speed_mps:
            raise ValueError("crawl_speed_mps must be below max_speed_mps")
        if math.hypot(*self.wind_enu_mps) >= self.max_speed_mps:
            raise ValueError("wind at or above max_speed_mps: the vehicle cannot make headway")


WALKER = VehicleConfig(
    max_speed_mps=1.4,
    max_accel_mps2=0.8,
    max_lateral_accel_mps2=1.0,
    max_yaw_rate_dps=120.0,
    crawl_speed_mps=0.2,
    ground_height_m=1.5,
    tracking_sigma_m=0.3,
    tracking_tau_s=6.0,
)  # a first responder walking with the phone in hand


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


# ----------------------------------------------------------------------------- guidance


@dataclass
class VehicleState:
    """The vehicle's controller state at ``t_s`` (true frame, before wander and drift)."""

    t_s: float
    position_m: tuple[float, float, float]
    velocity_mps: tuple[float, float, float]
    yaw_rad: float = 0.0


class PathGuidance:
    """Follow a reference path (absolute ENU heights) at its speed profile.

    Built from a :class:`Trajectory` already in the world frame with absolute heights
    (:func:`absolute_path`); the path is resampled every ``path_step_m`` of arc length.
    Zero-length steps of the reference with time (hovers) become stops of that length.
    The path is done when the reference has reached its end and the (navigation)
    position is within ``arrive_m`` of it: 1 cm by default (an open-loop flight ends
    on its last point); a closed loop flying on a drifting GNSS estimate uses an
    acceptance radius instead (:meth:`sim.stepper.Stepper.follow`).
    """

    def __init__(
        self,
        t_ref_s: np.ndarray,
        enu_m: np.ndarray,
        cfg: VehicleConfig,
        *,
        start_speed_mps: float = 0.0,
        terrain_height: Callable | None = None,
        height_above_terrain_m: np.ndarray | None = None,
        name: str = "",
        arrive_m: float = 0.01,
    ) -> None:
        self.cfg = cfg
        self.name = name
        self.arrive_m = arrive_m
        t_ref = np.asarray(t_ref_s, dtype=float) - float(t_ref_s[0])
        p = np.asarray(enu_m, dtype=float)
        if len(p) == 0:
            raise FlightError("cannot fly an empty path")
        ds = cfg.path_step_m
        hov = height_above_terrain_m
        if len(p) == 1:
            t_ref, p = np.array([0.0, t_ref[0]]), np.vstack([p, p])
            hov = None if hov is None else np.array([hov[0], hov[0]])
        from sim import _kernels

        z_ref = np.ascontiguousarray(p[:, 2] if hov is None else hov, dtype=float)
        t_d, en_d, z_d = _kernels.densify(t_ref, np.ascontiguousarray(p[:, :2]), z_ref, ds)
        if hov is not None and terrain_height is not None:
            z_d = z_d + np.asarray(terrain_height(en_d[:, 0], en_d[:, 1]), dtype=float)
        pts, s, self._dwell, t_move = _kernels.path_nodes(t_d, np.column_stack([en_d, z_d]))
        self.total_m = float(s[-1])
        m = len(pts)
        if m >= 2:
            d = pts[1:] - pts[:-1]
            lim = np.array([ds, cfg.max_speed_mps, cfg.max_vertical_speed_mps,
                            math.radians(cfg.max_yaw_rate_dps), cfg.max_lateral_accel_mps2,
                            cfg.max_accel_mps2, math.radians(cfg.sharp_turn_deg),
                            cfg.crawl_speed_mps, max(start_speed_mps, 0.0) ** 2])
            self._path, self._stop_after = _kernels.path_profile(
                pts, s, self._dwell, t_move, np.arctan2(d[:, 1], d[:, 0]), lim)
        else:  # a single point: hold it
            self._path = np.array([[0.0], *pts.T, [1.0], [0.0], [0.0], [0.0]])
            self._stop_after = np.zeros(1)
        self._gc = np.array([cfg.position_gain_per_s, cfg.lag_limit_m, cfg.crawl_speed_mps,
                             arrive_m])
        self._gs = np.array([0.0, 0.0, self._dwell[0], self._stop_after[0], 0.0])
        self.end_m = tuple(pts[-1].tolist())

    @property
    def done(self) -> bool:
        return bool(self._gs[4])

    @property
    def start_m(self) -> tuple[float, float, float]:
        return tuple(self._path[1:4, 0].tolist())

    @property
    def progress_m(self) -> float:
        return float(self._gs[1])

    def command(self, px: float, py: float, pz: float, dt: float) -> tuple[float, float, float]:
        """Velocity command at the navigation position (px, py, pz) for one tick
        (:func:`sim._kernels.path_command`)."""
        from sim import _kernels

        return _kernels.path_command(self._path, self._dwell, self._stop_after, self._gs,
                                     self._gc, px, py, pz, dt)


class HoldGuidance:
    """Brake and hold a point (PX4 HOLD / LOITER for a multirotor)."""

    def __init__(self, point_m: tuple[float, float, float], cfg: VehicleConfig) -> None:
        self.point = tuple(float(v) for v in point_m)
        self._point = np.array(self.point)
        self.cfg = cfg
        self.done = False
        self.name = "hold"

    def command(self, px: float, py: float, pz: float, dt: float) -> tuple[float, float, float]:
        """Velocity command at the navigation position (:func:`sim._kernels.hold_command`)."""
        from sim import _kernels

        return _kernels.hold_command(self._point, self.cfg.position_gain_per_s, px, py, pz)


class LandedGuidance:
    """Stay on the ground: a landed multirotor does not steer its believed height into
    the terrain (its navigation error moves the estimate, not the vehicle)."""

    def __init__(self) -> None:
        self.done = False
        self.name = "landed"

    def command(self, px: float, py: float, pz: float, dt: float) -> tuple[float, float, float]:
        return 0.0, 0.0, 0.0


LANDED_AGL_M = 0.5  # at most this high above the ground, a vehicle told to hold stays landed

Guidance = PathGuidance | HoldGuidance | LandedGuidance


def absolute_path(
    traj: Trajectory, world: World
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """(t_s, enu_m with absolute heights or None-terrain, height above terrain or None) of a
    trajectory in ``world``'s frame: terrain-referenced heights stay relative (resolved
    along the dense path by :class:`PathGuidance`)."""
    en, z = _reference_in_world(traj, world)
    if traj.height_ref == "terrain":
        return traj.t_s, np.column_stack([en, z]), z
    return traj.t_s, np.column_stack([en, z]), None


def path_guidance(
    traj: Trajectory, world: World, cfg: VehicleConfig, *, start_speed_mps: float = 0.0,
    from_m: tuple[float, float, float] | None = None, arrive_m: float = 0.01,
) -> PathGuidance:
    """Guidance along ``traj`` (any frame, any height reference) in ``world``.

    With ``from_m`` (where the vehicle is), a straight leg from there to the path's
    first point is prepended when they are more than 1 m apart. ``arrive_m``: see
    :class:`PathGuidance`.
    """
    t, p, hov = absolute_path(traj, world)
    if hov is not None:  # terrain-referenced: prepend in the same reference
        if from_m is not None:
            g0 = float(world.ground_m(p[0, 0], p[0, 1]))
            start_abs = np.array([p[0, 0], p[0, 1], g0 + hov[0]])
            gap = float(np.linalg.norm(np.asarray(from_m) - start_abs))
            if gap > 1.0:
                gh = float(world.ground_m(from_m[0], from_m[1]))
                v = max(_median_speed(t, p), 1.0)
                t = np.concatenate([[t[0] - gap / v], t])
                p = np.vstack([[from_m[0], from_m[1], from_m[2] - gh], p])
                hov = np.concatenate([[from_m[2] - gh], hov])
        return PathGuidance(t, p, cfg, start_speed_mps=start_speed_mps,
                            terrain_height=world.ground_m, height_above_terrain_m=hov,
                            name=traj.name, arrive_m=arrive_m)
    if from_m is not None:
        gap = float(np.linalg.norm(np.asarray(from_m) - p[0]))
        if gap > 1.0:
            v = max(_median_speed(t, p), 1.0)
            t = np.concatenate([[t[0] - gap / v], t])
            p = np.vstack([np.asarray(from_m, dtype=float)[None, :], p])
    return PathGuidance(t, p, cfg, start_speed_mps=start_speed_mps, name=traj.name,
                        arrive_m=arrive_m)


def _median_speed(t: np.ndarray, p: np.ndarray) -> float:
    if len(t) < 2:
        return 5.0
    dt = t[1:] - t[:-1]
    dp = p[1:, :2] - p[:-1, :2]
    dd = np.sqrt((dp * dp).sum(axis=1))
    v = sorted((dd[dt > 0] / dt[dt > 0]).tolist())
    if not v:
        return 5.0
    mid = len(v) // 2  # statistics.median's rule, without its generality
    return v[mid] if len(v) % 2 else (v[mid - 1] + v[mid]) / 2


# ----------------------------------------------------------------------------- vehicle


class _Columns:
    """Growable float columns (amortised appends, contiguous views)."""

    def __init__(self, width: int, capacity: int = 4096) -> None:
        self._a = np.empty((capacity, width))
        self.n = 0

    def extend(self, rows: np.ndarray) -> None:
        k = len(rows)
        if self.n + k > len(self._a):
            grow = np.empty((max(2 * len(self._a), self.n + k), self._a.shape[1]))
            grow[: self.n] = self._a[: self.n]
            self._a = grow
        self._a[self.n : self.n + k] = rows
        self.n += k

    @property
    def view(self) -> np.ndarray:
        return self._a[: self.n]

    def drop_front(self, k: int) -> None:
        """Forget the first ``k`` rows (the others move to the front)."""
        k = min(max(k, 0), self.n)
        if k:
            self._a[: self.n - k] = self._a[k : self.n]
            self.n -= k


_NO_NAV = np.empty((0, 3))  # placeholders of the kernel's unused arguments
_NO_POINT = np.zeros(3)
_NO_PATH = np.zeros((8, 1))
_NO_NODES = np.zeros(1)
_NO_GS = np.zeros(5)

UNDERGROUND_TOLERANCE_M = 1.0  # wander and corner cutting may graze the ground by less


class Multirotor:
    """The kinematic multirotor of one agent, advanced tick by tick on an absolute grid.

    ``nav_error`` (a function of time returning (M, 3)) is the autopilot's navigation
    error (the GNSS bias when the agent flies on GNSS); ``wander`` a process of time
    (:class:`sim._random.BlockedGaussMarkov`, order 2) for the tracking error.
    """

    def __init__(
        self,
        cfg: VehicleConfig,
        world: World,
        start: VehicleState,
        *,
        nav_error: Callable[[np.ndarray], np.ndarray] | None = None,
        wander: BlockedGaussMarkov | None = None,
        name: str = "",
    ) -> None:
        self.cfg = cfg
        self.world = world
        self.name = name
        self.dt = cfg.sample_dt_s
        self.k = round(start.t_s / self.dt)
        if abs(self.k * self.dt - start.t_s) > 1e-9:
            raise ValueError("a vehicle starts on its time grid (a multiple of sample_dt_s)")
        self.nav_error = nav_error
        self.wander = wander
        self.guidance: Guidance = HoldGuidance(start.position_m, cfg)
        x, y, z = (float(v) for v in start.position_m)
        if cfg.ground_height_m is not None:
            z = float(world.ground_m(x, y)) + cfg.ground_height_m
        elif z - float(world.ground_m(x, y)) <= LANDED_AGL_M:  # starts landed: stays so
            self.guidance = LandedGuidance()
        self._p = [x, y, z]
        self._v = [float(v) for v in start.velocity_mps]
        self._yaw = float(start.yaw_rad)
        dt = self.dt  # per-tick limits, in sim._kernels' layout
        self._params = np.array([
            dt, cfg.max_accel_mps2 * dt, cfg.max_lateral_accel_mps2 * dt,
            cfg.max_vertical_accel_mps2 * dt, cfg.max_speed_mps, cfg.max_vertical_speed_mps,
            math.radians(cfg.max_yaw_rate_dps) * dt, *cfg.wind_enu_mps,
        ])
        self.state_log = _Columns(8)  # t, x, y, z, vx, vy, vz, yaw (controller state)
        self.out_log = _Columns(3)  # output position: + drift + wander
        self._record(np.array([[self.t_s, x, y, z, *self._v, self._yaw]]))

    @property
    def t_s(self) -> float:
        return self.k * self.dt

    @property
    def state(self) -> VehicleState:
        return VehicleState(self.t_s, tuple(self._p), tuple(self._v), self._yaw)

    @property
    def position_m(self) -> tuple[float, float, float]:
        """The controller's (true) position now, world ENU metres (read-only)."""
        return (self._p[0], self._p[1], self._p[2])

    @property
    def velocity_mps(self) -> tuple[float, float, float]:
        """The controller's (true) velocity now, ENU m/s (read-only)."""
        return (self._v[0], self._v[1], self._v[2])

    def set_guidance(self, guidance: Guidance) -> None:
        self.guidance = guidance

    def _record(self, rows: np.ndarray) -> None:
        cfg = self.cfg
        out = rows[:, 1:4].copy()
        we, wn = cfg.wind_enu_mps
        if we or wn:
            v = rows[:, 4:6]
            sp = np.hypot(v[:, 0], v[:, 1])
            u = np.where(sp[:, None] > 0.3, v / np.maximum(sp, 1e-9)[:, None], 0.0)
            w = np.array([we, wn])
            w_along = u @ w
            out[:, :2] += cfg.wind_drift_s * (w[None, :] - w_along[:, None] * u)
        if self.wander is not None and cfg.tracking_sigma_m > 0:  # rows: consecutive ticks
            k0 = round(float(rows[0, 0]) / self.dt)
            wv = self.wander.values(k0, k0 + len(rows))
            if cfg.ground_height_m is not None:
                wv[:, 2] = 0.0
            out += wv
            if cfg.ground_height_m is None and 4.0 * cfg.tracking_sigma_m > UNDERGROUND_TOLERANCE_M:
                # a wander this wide would reach the ground from near it (on it at
                # take-off): the controller does not push the vehicle into the ground
                # (a state below it stays, for the check)
                g = self.world.ground_m(out[:, 0], out[:, 1])
                out[:, 2] = np.maximum(out[:, 2], np.minimum(rows[:, 3], g))
        if cfg.ground_height_m is not None:
            out[:, 2] = self.world.ground_m(out[:, 0], out[:, 1]) + cfg.ground_height_m
        self.state_log.extend(rows)
        self.out_log.extend(out)

    def advance(self, t_end_s: float, *, until_done: bool = False) -> None:
        """Integrate ticks up to the last grid time at or before ``t_end_s`` (or, with
        ``until_done``, up to the tick where the guidance is done). Path and hold
        guidance fly compiled (:func:`sim._kernels.fly`); any other guidance object
        (the MAVLink autopilot) and a walking agent, whose height follows the terrain,
        tick by tick with the same dynamics (:func:`sim._kernels.tick`)."""
        from sim import _kernels as kn

        k_end = math.floor(t_end_s / self.dt + 1e-9)
        n = k_end - self.k
        if n <= 0:
            return
        cfg = self.cfg
        dt = self.dt
        t_ticks = (self.k + 1 + np.arange(n)) * dt
        nav = self.nav_error(t_ticks - dt) if self.nav_error is not None else None
        walker = cfg.ground_height_m is not None
        ground = self.world.ground_m
        g = self.guidance
        st = np.array([*self._p, *self._v, self._yaw])
        rows = np.empty((n, 8))
        p = self._params
        if not walker and isinstance(g, PathGuidance | HoldGuidance):
            path = isinstance(g, PathGuidance)
            nav_a = np.ascontiguousarray(nav, dtype=float) if nav is not None else _NO_NAV
            if path:
                mode, point, args = kn.PATH, _NO_POINT, (g._path, g._dwell, g._stop_after,
                                                         g._gs, g._gc)
            else:
                mode, point = kn.HOLD, g._point
                args = (_NO_PATH, _NO_NODES, _NO_NODES, _NO_GS,
                        np.array([g.cfg.position_gain_per_s, 0.0, 0.0, 0.0]))
            done = kn.fly(st, nav_a, p, mode, point, *args, until_done, rows)
        else:
            command = g.command
            nav_l = nav.tolist() if nav is not None else None
            h = cfg.ground_height_m
            done = n
            for j in range(n):
                x, y, z = st[:3].tolist()
                if nav_l is not None:
                    bx, by, bz = nav_l[j]
                    if walker:  # a walker's height is the ground's: no GNSS height error
                        bz = 0.0
                    cx, cy, cz = command(x + bx, y + by, z + bz, dt)
                else:
                    cx, cy, cz = command(x, y, z, dt)
                kn.tick(st, cx, cy, cz, p)
                if walker:  # the height follows the ground beneath
                    nz = float(ground(float(st[0]), float(st[1]))) + h
                    st[2], st[5] = nz, (nz - z) / dt
                rows[j, 1:] = st
                if until_done and g.done:
                    done = j + 1
                    break
        if done < n:
            n = done
            k_end = self.k + n
            rows = rows[:n]
        rows[:, 0] = t_ticks[:n]
        x, y, z, vx, vy, vz, yaw = st.tolist()
        self._p = [x, y, z]
        self._v = [vx, vy, vz]
        self._yaw = yaw
        self.k = k_end
        self._record(rows)
        if not walker:
            self._check_above_ground(g, t_ticks[:n])

    def _check_above_ground(self, g: Guidance, t_s: np.ndarray) -> None:
        """Raise :class:`FlightError` if the last ``len(t_s)`` outputs went below the
        terrain by more than the tolerance (skipped when the terrain's upper bound over
        their box, if it has one, shows they cannot have)."""
        from sim import _kernels

        out = self.out_log.view[-len(t_s):]
        bound = getattr(self.world.terrain, "max_height_m", None)
        if bound is not None:
            e0, e1, n0, n1, z0 = _kernels.extent(out)
            if z0 - bound(e0, e1, n0, n1) > 0.01 - UNDERGROUND_TOLERANCE_M:
                return
        agl = out[:, 2] - self.world.ground_m(out[:, 0], out[:, 1])
        i = int(np.argmin(agl))
        if agl[i] < -UNDERGROUND_TOLERANCE_M:
            raise FlightError(
                f"{self.name or 'the vehicle'} flies {-agl[i]:.1f} m below the terrain at "
                f"t = {t_s[i]:.1f} s ({g.name or 'its guidance'}): check the path's "
                "height reference and origin height"
            )

    # ------------------------------------------------------------------ trace
    @property
    def trace_start_s(self) -> float:
        """The first time of the trace kept (0 unless :meth:`forget_before`)."""
        return float(self.state_log.view[0, 0])

    def forget_before(self, t_s: float) -> None:
        """Forget the trace (and the wander's draws) before ``t_s``: a vehicle that
        flies for hours keeps its recent past only; :meth:`position_at`, :meth:`track`
        and the like then start there."""
        k = min(int((t_s - self.trace_start_s) / self.dt), self.state_log.n - 1)
        if k > 0:
            self.state_log.drop_front(k)
            self.out_log.drop_front(k)
        if self.wander is not None:
            self.wander.forget_before(round(self.trace_start_s / self.dt))

    def position_at(self, t_s: ArrayLike) -> np.ndarray:
        """(M, 3) GNSS-antenna positions (output) at times within the flown span."""
        return _interp_grid(self.out_log.view, self.state_log.view[0, 0], self.dt, t_s)

    def yaw_at(self, t_s: ArrayLike) -> np.ndarray:
        st = self.state_log.view
        return _interp_grid(st[:, 7:8], st[0, 0], self.dt, t_s)[:, 0]

    def antenna_at(self, t_s: ArrayLike) -> np.ndarray:
        p = self.position_at(t_s)
        fwd, left, up = self.cfg.lever_arm_m
        if fwd == 0.0 and left == 0.0 and up == 0.0:
            return p
        yaw = self.yaw_at(t_s)
        c, s = np.cos(yaw), np.sin(yaw)
        p[:, 0] += c * fwd - s * left
        p[:, 1] += s * fwd + c * left
        p[:, 2] += up
        return p

    def track(self) -> VehicleTrack:
        st = self.state_log.view
        out = self.out_log.view
        t = st[:, 0].copy()
        vel = np.gradient(out, self.dt, axis=0) if len(t) > 1 else np.zeros_like(out)
        ground = self.world.ground_m(out[:, 0], out[:, 1])
        return VehicleTrack(t, out.copy(), vel, st[:, 7].copy(), np.asarray(ground),
                            self.cfg.lever_arm_m)


def _interp_grid(values: np.ndarray, t0: float, dt: float, t_s: ArrayLike) -> np.ndarray:
    """Rows of ``values`` (sampled every ``dt`` from ``t0``) linearly interpolated at
    ``t_s``, clamped to the sampled span (:func:`sim._kernels.grid_lerp`)."""
    from sim import _kernels

    t = np.atleast_1d(np.asarray(t_s, dtype=float))
    return _kernels.grid_lerp(values, float(t0), float(dt), t)


def fly(
    traj: Trajectory,
    world: World,
    cfg: VehicleConfig,
    rng: np.random.Generator | None = None,
    *,
    max_duration_s: float | None = None,
) -> VehicleTrack:
    """Fly ``traj`` from rest at its first point until it has been flown; the whole track.

    The wander is drawn from ``rng`` (none without one). Raises :class:`FlightError`
    (a ``ValueError``) for a flight that would go below the terrain: that is almost
    always a trajectory whose heights refer to another origin height or datum, and a
    silent underground flight would still "measure" ranges.
    """
    from sim._random import as_seed_sequence

    if len(traj.t_s) == 0:
        raise FlightError("cannot fly an empty trajectory")
    g = path_guidance(traj, world, cfg)
    wander = None
    if rng is not None and cfg.tracking_sigma_m > 0:
        wander = BlockedGaussMarkov(as_seed_sequence(rng), cfg.sample_dt_s,
                                    np.full(3, cfg.tracking_sigma_m), cfg.tracking_tau_s, order=2)
    v = Multirotor(cfg, world, VehicleState(0.0, g.start_m, (0.0, 0.0, 0.0)), wander=wander)
    v.set_guidance(g)
    try:
        fly_guidance(v, g, max_duration_s or 3.0 * traj.duration_s + 600.0)
    except FlightError as exc:
        raise trajectory_error(exc, traj, world) from None
    return v.track()


def trajectory_error(exc: FlightError, traj: Trajectory, world: World) -> FlightError:
    """The error of a trajectory that cannot be flown, naming its height reference and
    origin height (an underground flight is almost always a datum mix-up)."""
    return FlightError(
        f"trajectory {traj.name or ''!s}: {exc.args[0]} ({traj.height_ref}; origin height "
        f"{traj.origin[2]:g} m, the world's {world.origin.h_m:g} m)"
    )


def fly_guidance(v: Multirotor, g: Guidance, max_duration_s: float, chunk_s: float = 30.0) -> None:
    """Advance ``v`` until ``g`` is done (and its last point reached) or the time is up."""
    t_stop = v.t_s + max_duration_s
    while not g.done and v.t_s < t_stop - 1e-9:
        v.advance(min(v.t_s + chunk_s, t_stop), until_done=True)
