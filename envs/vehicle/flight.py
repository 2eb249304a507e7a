"""Flight tasks: velocity setpoints for the kinematic multirotor, one task at a time.

A task turns the navigation position (the autopilot's estimate) into a velocity
command each 20 Hz tick, as PX4's multicopter flight tasks feed its position
controller; :class:`sim.vehicle.Multirotor` applies its speed, acceleration and
yaw-rate limits to it. Tasks:

- :class:`Idle`: on the ground, motors off (no command).
- :class:`Hold`: a point, reached with a proportional pull (PX4 Hold / Loiter).
- :class:`Line`: a straight 3-D line from ``start`` to ``target`` at cruise speed,
  braking so that the vehicle is down to ``end_speed`` ``end_at_m`` before ``target``
  (where the caller switches to the next leg; 0 and 0: it stops there), the climb and
  descent limited, and not speeding up while the velocity still points elsewhere
  (a turn onto the line is flown at the speed it started with); a cross-track pull
  keeps it on the line (PX4's line-following auto mode). Reaching is judged by the
  caller (acceptance radius).
- :class:`TerrainLine`: the same line seen from above, at a height above the ground
  (the terrain database's, at the navigation position) that goes linearly from the
  start's to the target's along the leg: the climb follows the ground's grade ahead, and
  the horizontal speed drops where the grade would need more than the climb or descent
  limits (MAVLink's terrain frames, as ArduPilot flies them).
- :class:`Orbit`: a circle at a tangential speed the lateral-acceleration and yaw-rate
  limits allow, for a number of turns (at a height, or a height above the ground).
- :class:`Land`: hold the horizontal position and descend (fast, then
  MPC_LAND_SPEED below MPC_LAND_ALT2), braking to touch down gently; touchdown is
  judged on the true height above the terrain (a land detector feels the ground,
  the estimate does not).

Also the geometry the autopilot's parts share: :data:`Vec3` (ENU metres),
:class:`Home`, :class:`Limits` and :data:`TERRAIN_CLEARANCE_M`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

Vec3 = tuple[float, float, float]
TERRAIN_CLEARANCE_M = 2.0  # the vehicle never flies lower above the ground (not PX4)


@dataclass
class Home:
    """Home position: ENU (navigation frame) and geodetic (ellipsoidal height)."""

    enu: Vec3
    lat_deg: float
    lon_deg: float
    alt_m: float


@dataclass(frozen=True)
class Limits:
    """What the tasks may command (from the parameters and the vehicle's limits)."""

    cruise_mps: float
    climb_mps: float
    descent_mps: float
    takeoff_mps: float
    land_mps: float
    land_alt1_m: float
    land_alt2_m: float
    brake_mps2: float  # deceleration the speed profiles plan with
    brake_z_mps2: float
    lateral_mps2: float
    yaw_rate_rps: float
    gain_per_s: float  # proportional pull towards the line or point


class Context(Protocol):
    """What a task sees of the autopilot."""

    limits: Limits

    @property
    def velocity(self) -> Vec3: ...

    def true_agl_m(self, p: Vec3) -> float: ...

    def ground_m(self, e_m: float, n_m: float) -> float:
        """The terrain database's ground height (ENU up) at (e, n)."""
        ...


class Task:
    """A flight task (see the module docstring)."""

    name = "task"
    done = False

    def setpoint(self, ctx: Context, p: Vec3, dt: float) -> Vec3:
        raise NotImplementedError


class Idle(Task):
    name = "idle"

    def setpoint(self, ctx: Context, p: Vec3, dt: float) -> Vec3:
        return 0.0, 0.0, 0.0


def _cap_vertical(vz: float, lim: Limits) -> float:
    return max(-lim.descent_mps, min(lim.climb_mps, vz))


def _cap_horizontal(vx: float, vy: float, vmax: float) -> tuple[float, float]:
    s = math.hypot(vx, vy)
    if s > vmax > 0:
        return vx * vmax / s, vy * vmax / s
    return vx, vy


def stopping_point(p: Vec3, v: Vec3, lim: Limits) -> Vec3:
    """Where the vehicle comes to rest braking at the planned deceleration."""
    sh = math.hypot(v[0], v[1])
    k = sh / (2.0 * lim.brake_mps2) if sh > 0 else 0.0
    kz = abs(v[2]) / (2.0 * lim.brake_z_mps2)
    return p[0] + v[0] * k, p[1] + v[1] * k, p[2] + v[2] * kz


class Hold(Task):
    name = "hold"

    def __init__(self, point: Vec3) -> None:
        self.point = point

    def setpoint(self, ctx: Context, p: Vec3, dt: float) -> Vec3:
        lim = ctx.limits
        k = lim.gain_per_s
        vx, vy = _cap_horizontal(k * (self.point[0] - p[0]), k * (self.point[1] - p[1]),
                                 lim.cruise_mps)
        return vx, vy, _cap_vertical(k * (self.point[2] - p[2]), lim)


class Line(Task):
    """Straight 3-D line ``start`` -> ``target`` (see the module docstring)."""

    name = "line"

    def __init__(self, start: Vec3, target: Vec3, *, end_speed_mps: float = 0.0,
                 end_at_m: float = 0.0, speed_mps: float | None = None,
                 vertical_mps: float | None = None) -> None:
        self.start = start
        self.target = target
        self.end_speed = max(0.0, end_speed_mps)
        self.end_at = max(0.0, end_at_m) if self.end_speed > 0 else 0.0
        self.speed = speed_mps  # None: the cruise speed of the moment
        self.vertical = vertical_mps  # None: the climb / descent limits
        d = (target[0] - start[0], target[1] - start[1], target[2] - start[2])
        self.length = math.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
        self.u = (d[0] / self.length, d[1] / self.length, d[2] / self.length) \
            if self.length > 1e-6 else (0.0, 0.0, 0.0)

    def setpoint(self, ctx: Context, p: Vec3, dt: float) -> Vec3:
        lim = ctx.limits
        k = lim.gain_per_s
        t = self.target
        speed = lim.cruise_mps if self.speed is None else self.speed
        ux, uy, uz = self.u
        sx, sy, sz = self.start
        along = (p[0] - sx) * ux + (p[1] - sy) * uy + (p[2] - sz) * uz
        if self.length <= 1e-6 or along >= self.length:
            # at or past the end: pull to the target, no faster than the end speed allows
            vx, vy = _cap_horizontal(k * (t[0] - p[0]), k * (t[1] - p[1]),
                                     max(self.end_speed, 1.0))
            return vx, vy, _cap_vertical(k * (t[2] - p[2]), lim)
        a = max(along, 0.0)
        rem = max(self.length - a - self.end_at, 0.0)
        brake = min(lim.brake_mps2, lim.brake_z_mps2) if abs(uz) > 0.7 else lim.brake_mps2
        v = min(speed, math.sqrt(self.end_speed ** 2 + 2.0 * brake * rem))
        vx0, vy0, _ = ctx.velocity
        s0 = math.hypot(vx0, vy0)
        hl = math.hypot(ux, uy)
        if s0 > 0.5 and hl > 0.3 and (vx0 * ux + vy0 * uy) / (s0 * hl) < 0.97:
            v = min(v, s0 + 0.2)  # still turning onto the line: no faster yet
        up = self.vertical if self.vertical is not None else lim.climb_mps
        down = self.vertical if self.vertical is not None else lim.descent_mps
        if uz > 1e-9 and v * uz > up:
            v = up / uz
        elif uz < -1e-9 and -v * uz > down:
            v = down / -uz
        cx, cy, cz = sx + ux * a, sy + uy * a, sz + uz * a
        return (v * ux + k * (cx - p[0]), v * uy + k * (cy - p[1]),
                v * uz + k * (cz - p[2]))

    def distances(self, p: Vec3) -> tuple[float, float]:
        """(horizontal, vertical) distance from ``p`` to the target."""
        t = self.target
        return math.hypot(t[0] - p[0], t[1] - p[1]), abs(t[2] - p[2])


def corner_speed(u_in: tuple[float, float], u_out: tuple[float, float], radius_m: float,
                 lim: Limits, speed_mps: float) -> float:
    """Speed at a waypoint between two legs (horizontal unit vectors): the turn must fit
    an arc that starts at the acceptance radius (radius r / tan(theta / 2)) within the
    lateral-acceleration and yaw-rate limits; 0 for turns beyond 120 degrees."""
    c = max(-1.0, min(1.0, u_in[0] * u_out[0] + u_in[1] * u_out[1]))
    theta = math.acos(c)
    if theta < 1e-3:
        return speed_mps
    if theta > math.radians(120.0):
        return 0.0
    r = radius_m / math.tan(theta / 2.0)
    return min(speed_mps, math.sqrt(lim.lateral_mps2 * r), lim.yaw_rate_rps * r)


class TerrainLine(Task):
    """A horizontal line ``start`` -> ``target`` at a height above the ground going from
    ``agl_start_m`` to ``agl_end_m`` (see the module docstring); ``target`` is where it
    ends (its height the ground's there plus ``agl_end_m``), ``end_speed_mps`` and
    ``end_at_m`` as for :class:`Line`."""

    name = "terrain-line"
    LOOKAHEAD_S = 1.5  # the grade is judged this far ahead (at the speed of the moment)

    def __init__(self, start: Vec3, target: Vec3, agl_start_m: float, agl_end_m: float, *,
                 end_speed_mps: float = 0.0, end_at_m: float = 0.0) -> None:
        self.start = start
        self.target = target
        self.agl_start = agl_start_m
        self.agl_end = agl_end_m
        self.end_speed = max(0.0, end_speed_mps)
        self.end_at = max(0.0, end_at_m) if self.end_speed > 0 else 0.0
        d = (target[0] - start[0], target[1] - start[1])
        self.length = math.hypot(*d)
        self.u = (d[0] / self.length, d[1] / self.length) if self.length > 1e-6 else (0.0, 0.0)

    def agl_at(self, along_m: float) -> float:
        """The height above the ground wanted ``along_m`` into the leg."""
        if self.length <= 1e-6:
            return self.agl_end
        f = min(max(along_m / self.length, 0.0), 1.0)
        return self.agl_start + f * (self.agl_end - self.agl_start)

    def setpoint(self, ctx: Context, p: Vec3, dt: float) -> Vec3:
        lim = ctx.limits
        k = lim.gain_per_s
        t = self.target
        ux, uy = self.u
        sx, sy = self.start[0], self.start[1]
        along = (p[0] - sx) * ux + (p[1] - sy) * uy
        ground = ctx.ground_m(p[0], p[1])
        if self.length <= 1e-6 or along >= self.length:
            vx, vy = _cap_horizontal(k * (t[0] - p[0]), k * (t[1] - p[1]),
                                     max(self.end_speed, 1.0))
            return vx, vy, _cap_vertical(k * (ground + self.agl_end - p[2]), lim)
        a = max(along, 0.0)
        rem = max(self.length - a - self.end_at, 0.0)
        v = min(lim.cruise_mps, math.sqrt(self.end_speed ** 2 + 2.0 * lim.brake_mps2 * rem))
        vx0, vy0, _ = ctx.velocity
        s0 = math.hypot(vx0, vy0)
        if s0 > 0.5 and (vx0 * ux + vy0 * uy) / s0 < 0.97:
            v = min(v, s0 + 0.2)  # still turning onto the line: no faster yet
        # the grade ahead: the ground's and the wanted height's change per metre
        d = min(max(2.0, self.LOOKAHEAD_S * max(v, s0)), self.length - a + 2.0)
        ahead = ctx.ground_m(p[0] + ux * d, p[1] + uy * d)
        grade = (ahead - ground) / d + (self.agl_end - self.agl_start) / self.length
        if grade > 1e-6:
            v = min(v, 0.9 * lim.climb_mps / grade)
        elif grade < -1e-6:
            v = min(v, 0.9 * lim.descent_mps / -grade)
        cx, cy = sx + ux * a, sy + uy * a
        vz = grade * v + k * (ground + self.agl_at(a) - p[2])
        return v * ux + k * (cx - p[0]), v * uy + k * (cy - p[1]), _cap_vertical(vz, lim)

    def distances(self, p: Vec3) -> tuple[float, float]:
        """(horizontal, vertical) distance from ``p`` to the target."""
        t = self.target
        return math.hypot(t[0] - p[0], t[1] - p[1]), abs(t[2] - p[2])


class Orbit(Task):
    """``turns`` circles of ``radius`` about ``center`` at height ``z`` (or, with
    ``agl_m``, that high above the ground); ``direction`` +1 counter-clockwise, -1
    clockwise (seen from above)."""

    name = "orbit"

    def __init__(self, center: tuple[float, float], radius_m: float, z: float,
                 direction: int, turns: float, *, agl_m: float | None = None) -> None:
        self.center = center
        self.radius = max(radius_m, 0.5)
        self.z = z
        self.agl = agl_m
        self.direction = 1 if direction >= 0 else -1
        self.goal_rad = 2.0 * math.pi * max(turns, 0.0)
        self.swept_rad = 0.0
        self._last: float | None = None

    def setpoint(self, ctx: Context, p: Vec3, dt: float) -> Vec3:
        lim = ctx.limits
        k = lim.gain_per_s
        rx, ry = p[0] - self.center[0], p[1] - self.center[1]
        r = math.hypot(rx, ry)
        if r < 1e-3:
            rx, ry, r = 1.0, 0.0, 1.0
        ex, ey = rx / r, ry / r
        ang = math.atan2(ey, ex)
        if self._last is not None:
            d = (ang - self._last + math.pi) % (2.0 * math.pi) - math.pi
            self.swept_rad += d * self.direction
        self._last = ang
        if self.swept_rad >= self.goal_rad:
            self.done = True
        R = self.radius
        vt = min(lim.cruise_mps, math.sqrt(lim.lateral_mps2 * R), 0.9 * lim.yaw_rate_rps * R)
        tx, ty = -ey * self.direction, ex * self.direction
        pull = k * (R - r)
        if self.agl is None:
            vz = k * (self.z - p[2])
        else:  # the ground's grade along the circle, and the pull to the height above it
            ground = ctx.ground_m(p[0], p[1])
            d = max(2.0, vt)
            ahead = ctx.ground_m(p[0] + tx * d, p[1] + ty * d)
            vz = (ahead - ground) / d * vt + k * (ground + self.agl - p[2])
        return vt * tx + pull * ex, vt * ty + pull * ey, _cap_vertical(vz, lim)


class Land(Task):
    """Descend at (x, y) until touchdown (``done``); see the module docstring."""

    name = "land"
    TOUCHDOWN_M = 0.03

    def __init__(self, x: float, y: float) -> None:
        self.x, self.y = x, y

    def setpoint(self, ctx: Context, p: Vec3, dt: float) -> Vec3:
        lim = ctx.limits
        if self.done:
            return 0.0, 0.0, 0.0
        agl = ctx.true_agl_m(p)
        if agl <= self.TOUCHDOWN_M:
            self.done = True
            return 0.0, 0.0, 0.0
        k = lim.gain_per_s
        vx, vy = _cap_horizontal(k * (self.x - p[0]), k * (self.y - p[1]), 2.0)
        if agl >= lim.land_alt1_m:
            vd = lim.descent_mps
        elif agl > lim.land_alt2_m and lim.land_alt1_m > lim.land_alt2_m:
            f = (agl - lim.land_alt2_m) / (lim.land_alt1_m - lim.land_alt2_m)
            vd = lim.land_mps + f * (lim.descent_mps - lim.land_mps)
        else:
            vd = lim.land_mps
        vd = min(vd, max(math.sqrt(2.0 * lim.brake_z_mps2 * max(agl - 0.02, 0.0)), 0.15))
        return vx, vy, -vd
