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
import statistics
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from estimator.geodesy import ExactENU
from estimator.records import Trajectory
from sim._config import check_finite, check_positive
from sim._random import BlockedGaussMarkov
from sim.world import World


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
        check_positive("wind_drift_s", self.wind_drift_s, allow_zero=True)
        check_positive("tracking_sigma_m", self.tracking_sigma_m, allow_zero=True)
        for i, w in enumerate(self.wind_enu_mps):
            check_finite(f"wind_enu_mps[{i}]", w)
        for i, a in enumerate(self.lever_arm_m):
            check_finite(f"lever_arm_m[{i}]", a)
        if self.ground_height_m is not None:
            check_positive("ground_height_m", self.ground_height_m, allow_zero=True)
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


def _densify(
    t: np.ndarray, en: np.ndarray, z: np.ndarray, step_m: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Split segments into pieces of at most ``step_m`` (horizontally and vertically)."""
    d_en = en[1:] - en[:-1]
    seg = np.maximum(np.hypot(d_en[:, 0], d_en[:, 1]), np.abs(z[1:] - z[:-1]))
    pieces = np.maximum(1, np.ceil(seg / step_m)).astype(np.intp)
    idx = np.repeat(np.arange(len(seg)), pieces)
    first = np.repeat(np.cumsum(pieces) - pieces, pieces)
    frac = (np.arange(len(idx)) - first) / np.repeat(pieces, pieces)

    def lerp(a: np.ndarray) -> np.ndarray:
        da = a[1:] - a[:-1]
        f = frac if a.ndim == 1 else frac[:, None]
        return np.concatenate([a[idx] + f * da[idx], a[-1:]])

    return lerp(t), lerp(en), lerp(z)


def _unwrap(p: np.ndarray) -> np.ndarray:
    """``numpy.unwrap`` of a 1-D angle series (period 2 pi), without its generality."""
    if len(p) < 2:
        return p.copy()
    dd = p[1:] - p[:-1]
    ddmod = np.mod(dd + math.pi, 2.0 * math.pi) - math.pi
    ddmod[(ddmod == -math.pi) & (dd > 0)] = math.pi
    correct = ddmod - dd
    correct[np.abs(dd) < math.pi] = 0.0
    out = p.copy()
    out[1:] += np.cumsum(correct)
    return out


def _forward_fill(values: np.ndarray, valid: np.ndarray, default: float) -> np.ndarray:
    if not valid.any():
        return np.full(len(values), default)
    idx = np.where(valid, np.arange(len(values)), -1)
    idx = np.maximum.accumulate(idx)
    idx[idx < 0] = int(np.argmax(valid))  # before the first valid value: take it
    return values[idx]


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
        t_d, en_d, z_d = _densify(t_ref, p[:, :2], p[:, 2] if hov is None else hov, ds)
        if hov is not None and terrain_height is not None:
            z_d = z_d + np.asarray(terrain_height(en_d[:, 0], en_d[:, 1]), dtype=float)
        pd = np.column_stack([en_d, z_d])
        dpd = pd[1:] - pd[:-1]
        seg = np.sqrt((dpd * dpd).sum(axis=1))
        dt_d = t_d[1:] - t_d[:-1]
        moving = seg > 1e-9
        # nodes: drop zero-length steps, remembering the hovers they hold
        keep = np.concatenate([[True], moving])
        s_all = np.concatenate([[0.0], np.cumsum(seg)])
        idx_keep = np.flatnonzero(keep)
        node_of = np.cumsum(keep) - 1  # dense index -> node index
        dwell: dict[int, float] = {}
        for i in np.flatnonzero(~moving & (dt_d > 0)).tolist():
            n = int(node_of[i])
            dwell[n] = dwell.get(n, 0.0) + float(dt_d[i])
        pts = pd[idx_keep]
        s = s_all[idx_keep]
        self.total_m = float(s[-1])
        m = len(pts)
        if m >= 2:
            d = pts[1:] - pts[:-1]
            cell = np.maximum(np.sqrt((d * d).sum(axis=1)), 1e-12)
            tangent = d / cell[:, None]
            tangent = np.vstack([tangent, tangent[-1:]])
            t_acc = np.concatenate([[0.0], np.cumsum(np.where(moving, dt_d, 0.0))])[keep]
            t_cell = t_acc[1:] - t_acc[:-1]
            with np.errstate(divide="ignore"):
                v_ref = np.where(t_cell > 0, cell / t_cell, np.inf)
                v_climb = cfg.max_vertical_speed_mps * cell / np.maximum(np.abs(d[:, 2]), 1e-12)
            v_cell = np.minimum(np.minimum(v_ref, v_climb), cfg.max_speed_mps)
            h = d[:, :2]
            h_len = np.hypot(h[:, 0], h[:, 1])
            psi = _unwrap(_forward_fill(np.arctan2(h[:, 1], h[:, 0]), h_len > 1e-6 * ds, 0.0))
            turn = np.abs(psi[1:] - psi[:-1])
            arc = 0.5 * (h_len[:-1] + h_len[1:])
            with np.errstate(divide="ignore", invalid="ignore"):
                curv = np.where(turn > 0, turn / np.maximum(arc, 1e-9), 0.0)
                v_turn = np.minimum(
                    np.where(curv > 0, math.radians(cfg.max_yaw_rate_dps) / curv, np.inf),
                    np.where(curv > 0, np.sqrt(cfg.max_lateral_accel_mps2 / curv), np.inf),
                )
            v_node = np.empty(m)
            v_node[0] = v_cell[0]
            v_node[1:-1] = np.minimum(np.minimum(v_cell[:-1], v_cell[1:]), v_turn)
            v_node[-1] = v_cell[-1]
            v_node[1:-1][turn > math.radians(cfg.sharp_turn_deg)] = 0.0
            v_node = np.maximum(v_node, cfg.crawl_speed_mps)
            stops = np.zeros(m, dtype=bool)
            stops[-1] = True
            for n in dwell:
                stops[n] = True
            v_node[stops] = 0.0
            # braking: backward pass on v^2 (deceleration max_accel over each cell), then
            # acceleration from the current speed: forward pass
            a2 = 2.0 * cfg.max_accel_mps2
            v2 = _limit_passes(v_node * v_node, a2 * cell, max(start_speed_mps, 0.0) ** 2)
            v_prof = np.sqrt(v2)
            # the reference never stands still between stops
            floor = np.where(stops, 0.0, cfg.crawl_speed_mps)
            v_prof = np.maximum(v_prof, floor)
        else:
            tangent = np.array([[1.0, 0.0, 0.0]])
            v_prof = np.zeros(1)
        self.s = s.tolist()
        self.x = pts[:, 0].tolist()
        self.y = pts[:, 1].tolist()
        self.z = pts[:, 2].tolist()
        self.tx = tangent[:, 0].tolist()
        self.ty = tangent[:, 1].tolist()
        self.tz = tangent[:, 2].tolist()
        self.v = v_prof.tolist()
        self.dwell = dwell
        self.end_m = (self.x[-1], self.y[-1], self.z[-1])
        self._i = 0
        self._s_ref = 0.0
        self._dwell_left = dwell.get(0, 0.0)
        self._next_stop = self._stop_after(0)
        self.done = False

    @property
    def start_m(self) -> tuple[float, float, float]:
        return self.x[0], self.y[0], self.z[0]

    @property
    def progress_m(self) -> float:
        return self._s_ref

    def _stop_after(self, i: int) -> int:
        later = [n for n in self.dwell if n > i]
        return min(later) if later else len(self.s) - 1

    def command(self, px: float, py: float, pz: float, dt: float) -> tuple[float, float, float]:
        """Velocity command at the navigation position (px, py, pz) for one tick."""
        cfg = self.cfg
        s, xs, ys, zs = self.s, self.x, self.y, self.z
        i = self._i
        last = len(s) - 1
        s_ref = self._s_ref
        if i < last:  # the reference point and its profile speed
            f = (s_ref - s[i]) / (s[i + 1] - s[i])
            rx = xs[i] + f * (xs[i + 1] - xs[i])
            ry = ys[i] + f * (ys[i + 1] - ys[i])
            rz = zs[i] + f * (zs[i + 1] - zs[i])
            vr = self.v[i] + f * (self.v[i + 1] - self.v[i])
        else:
            rx, ry, rz, vr = xs[last], ys[last], zs[last], 0.0
        ex, ey, ez = rx - px, ry - py, rz - pz
        lag = math.sqrt(ex * ex + ey * ey + ez * ez)
        if self._dwell_left > 0.0:  # hovering at a stop
            vr = 0.0
            if lag < 0.5:
                self._dwell_left -= dt
        elif i < last and lag < cfg.lag_limit_m:
            # advance along the profile (at least at crawl speed: the profile is 0 at a
            # stop), never past the next stop
            stop = self._next_stop
            s_new = s_ref + max(vr, cfg.crawl_speed_mps) * dt
            if s_new >= s[stop]:
                s_new = s[stop]
                if stop < last:
                    self._dwell_left = self.dwell.get(stop, 0.0)
                    self._next_stop = self._stop_after(stop)
            self._s_ref = s_new
            while i < last and s[i + 1] <= s_new:
                i += 1
            self._i = i
        if i >= last:
            vr = 0.0
            if lag < self.arrive_m:
                self.done = True
        k = cfg.position_gain_per_s
        return (
            vr * self.tx[i] + k * ex,
            vr * self.ty[i] + k * ey,
            vr * self.tz[i] + k * ez,
        )


def _limit_passes(v2: np.ndarray, step: np.ndarray, start_v2: float) -> np.ndarray:
    """The speed profile's two passes on v^2: backward, ``v2[i] <= v2[i+1] + step[i]``
    (braking), then forward from ``v2[0] <= start_v2``, ``v2[i] <= v2[i-1] + step[i-1]``
    (acceleration). Element by element in Python floats, but only where a limit binds:
    a run of changes starts where the limit binds on the unchanged profile (found with
    NumPy) and ends at the first element it leaves alone, so the result is that of the
    plain element-wise loops, bit for bit, at the cost of the changed elements only."""
    m = len(v2)
    out = v2.tolist()
    st = step.tolist()
    lowest = m
    for c in np.flatnonzero(v2[:-1] > v2[1:] + step)[::-1].tolist():
        if c >= lowest:
            continue
        i = c
        while i >= 0:
            lim = out[i + 1] + st[i]
            if out[i] <= lim:
                break
            out[i] = lim
            i -= 1
        lowest = i
    out[0] = min(out[0], start_v2)
    b = np.asarray(out)
    highest = -1
    seeds = np.flatnonzero(b[1:] > b[:-1] + step) + 1
    for c in seeds.tolist():  # (index 1 after the start limit is among them)
        if c <= highest:
            continue
        i = c
        while i < m:
            lim = out[i - 1] + st[i - 1]
            if out[i] <= lim:
                break
            out[i] = lim
            i += 1
        highest = i
    return np.asarray(out)


class HoldGuidance:
    """Brake and hold a point (PX4 HOLD / LOITER for a multirotor)."""

    def __init__(self, point_m: tuple[float, float, float], cfg: VehicleConfig) -> None:
        self.point = tuple(float(v) for v in point_m)
        self.cfg = cfg
        self.done = False
        self.name = "hold"

    def command(self, px: float, py: float, pz: float, dt: float) -> tuple[float, float, float]:
        k = self.cfg.position_gain_per_s
        x, y, z = self.point
        return k * (x - px), k * (y - py), k * (z - pz)


Guidance = PathGuidance | HoldGuidance


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
    ok = dt > 0
    return float(statistics.median((dd[ok] / dt[ok]).tolist())) if ok.any() else 5.0


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
        self._p = [x, y, z]
        self._v = [float(v) for v in start.velocity_mps]
        self._yaw = float(start.yaw_rad)
        self.state_log = _Columns(8)  # t, x, y, z, vx, vy, vz, yaw (controller state)
        self.out_log = _Columns(3)  # output position: + drift + wander
        self._record(np.array([[self.t_s, x, y, z, *self._v, self._yaw]]))

    @property
    def t_s(self) -> float:
        return self.k * self.dt

    @property
    def state(self) -> VehicleState:
        return VehicleState(self.t_s, tuple(self._p), tuple(self._v), self._yaw)

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
        if self.wander is not None and cfg.tracking_sigma_m > 0:
            k = np.rint(rows[:, 0] / self.dt).astype(np.int64)
            wv = self.wander.values(int(k[0]), int(k[-1]) + 1)[k - k[0]]
            if cfg.ground_height_m is not None:
                wv[:, 2] = 0.0
            out += wv
        if cfg.ground_height_m is not None:
            out[:, 2] = self.world.ground_m(out[:, 0], out[:, 1]) + cfg.ground_height_m
        self.state_log.extend(rows)
        self.out_log.extend(out)

    def advance(self, t_end_s: float, *, until_done: bool = False) -> None:
        """Integrate ticks up to the last grid time at or before ``t_end_s`` (or, with
        ``until_done``, up to the tick where the guidance is done)."""
        k_end = math.floor(t_end_s / self.dt + 1e-9)
        n = k_end - self.k
        if n <= 0:
            return
        cfg = self.cfg
        dt = self.dt
        t_ticks = (self.k + 1 + np.arange(n)) * dt
        nav = self.nav_error(t_ticks - dt) if self.nav_error is not None else None
        a_long = cfg.max_accel_mps2 * dt
        a_lat = cfg.max_lateral_accel_mps2 * dt
        a_z = cfg.max_vertical_accel_mps2 * dt
        vmax = cfg.max_speed_mps
        vz_max = cfg.max_vertical_speed_mps
        yaw_step = math.radians(cfg.max_yaw_rate_dps) * dt
        we, wn = cfg.wind_enu_mps
        walker = cfg.ground_height_m is not None
        ground = self.world.ground_m
        x, y, z = self._p
        vx, vy, vz = self._v
        yaw = self._yaw
        g = self.guidance
        command = g.command
        rows: list[tuple[float, ...]] = []
        row = rows.append
        t_l = t_ticks.tolist()
        nav_l = nav.tolist() if nav is not None else None
        hypot, atan2, pi, two_pi = math.hypot, math.atan2, math.pi, 2.0 * math.pi
        for j in range(n):
            if nav_l is not None:
                bx, by, bz = nav_l[j]
                cx, cy, cz = command(x + bx, y + by, z + bz, dt)
            else:
                cx, cy, cz = command(x, y, z, dt)
            if we or wn:  # air speed: shorten the ground velocity along its own direction
                ax_, ay_ = cx - we, cy - wn
                if ax_ * ax_ + ay_ * ay_ > vmax * vmax:
                    cw = cx * we + cy * wn
                    c2 = cx * cx + cy * cy
                    lam = (cw + math.sqrt(cw * cw - c2 * (we * we + wn * wn - vmax * vmax))) / c2
                    cx *= lam
                    cy *= lam
            elif cx * cx + cy * cy > vmax * vmax:
                sc = vmax / hypot(cx, cy)
                cx *= sc
                cy *= sc
            # horizontal: along-track and lateral acceleration limits
            dvx, dvy = cx - vx, cy - vy
            sp = hypot(vx, vy)
            if sp > 0.1:
                ux, uy = vx / sp, vy / sp
            else:
                dn = hypot(dvx, dvy)
                ux, uy = (dvx / dn, dvy / dn) if dn > 0 else (1.0, 0.0)
            along = dvx * ux + dvy * uy
            latx, laty = dvx - along * ux, dvy - along * uy
            if along > a_long:
                along = a_long
            elif along < -a_long:
                along = -a_long
            lat = hypot(latx, laty)
            if lat > a_lat:
                latx *= a_lat / lat
                laty *= a_lat / lat
            nvx = vx + along * ux + latx
            nvy = vy + along * uy + laty
            # air speed
            ax_, ay_ = nvx - we, nvy - wn
            air = hypot(ax_, ay_)
            if air > vmax:
                nvx = we + ax_ * vmax / air
                nvy = wn + ay_ * vmax / air
            dvz = cz - vz
            if dvz > a_z:
                dvz = a_z
            elif dvz < -a_z:
                dvz = -a_z
            nvz = vz + dvz
            if nvz > vz_max:
                nvz = vz_max
            elif nvz < -vz_max:
                nvz = -vz_max
            x += 0.5 * (vx + nvx) * dt
            y += 0.5 * (vy + nvy) * dt
            if walker:
                nz = float(ground(x, y)) + cfg.ground_height_m
                nvz = (nz - z) / dt
                z = nz
            else:
                z += 0.5 * (vz + nvz) * dt
            vx, vy, vz = nvx, nvy, nvz
            # the nose follows the course, within the yaw-rate limit
            sp = hypot(vx, vy)
            if sp > 0.5:
                d = atan2(vy, vx) - yaw
                d = (d + pi) % two_pi - pi
                yaw += yaw_step if d > yaw_step else -yaw_step if d < -yaw_step else d
            row((t_l[j], x, y, z, vx, vy, vz, yaw))
            if until_done and g.done:
                n = j + 1
                k_end = self.k + n
                break
        self._p = [x, y, z]
        self._v = [vx, vy, vz]
        self._yaw = yaw
        self.k = k_end
        self._record(np.array(rows, dtype=float).reshape(-1, 8))
        agl = self.out_log.view[-n:, 2] - ground(self.out_log.view[-n:, 0],
                                                  self.out_log.view[-n:, 1])
        i = int(np.argmin(agl))
        if agl[i] < -UNDERGROUND_TOLERANCE_M and not walker:
            raise FlightError(
                f"{self.name or 'the vehicle'} flies {-agl[i]:.1f} m below the terrain at "
                f"t = {t_ticks[i]:.1f} s ({g.name or 'its guidance'}): check the path's "
                "height reference and origin height"
            )

    # ------------------------------------------------------------------ trace
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
    t = np.atleast_1d(np.asarray(t_s, dtype=float))
    f = np.clip((t - t0) / dt, 0.0, len(values) - 1.0)
    i = np.minimum(f.astype(np.intp), max(len(values) - 2, 0))
    w = (f - i)[:, None]
    j = np.minimum(i + 1, len(values) - 1)
    return values[i] * (1.0 - w) + values[j] * w


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
