"""The autopilot: the simulated vehicle's guidance, made of parts with one job each.

:class:`Autopilot` implements the ``command(px, py, pz, dt) -> (vx, vy, vz)`` protocol
of :mod:`sim.vehicle`: every 20 Hz tick it checks the geofence, runs the active mode,
flies the active flight task (:mod:`envs.vehicle.flight`) on the navigation position,
keeps the terrain clearance and runs the land detector. It holds what the parts
share (navigation position and velocity, home, the flight task, landed state, the
parameters and the limits they give, the events the MAVLink side publishes) and
hands the rest to them:

- :class:`envs.vehicle.modes.ModeMachine` (``modes``): flight modes, arming, take-off
  and the commands of a ground station, link loss;
- :class:`envs.vehicle.executor.MissionExecutor` (``executor``): the mission, its
  items, jumps, speed changes and loiters, the items reached and the current one;
- :class:`envs.vehicle.geofence.FenceGuard` (``geofence``): the fence (uploaded zones
  and preloaded keep-outs with their tops) and what a (predicted) breach does;
- :class:`envs.vehicle.rtl.ReturnToLaunch` (``rtl``): AUTO.RTL and the rally points;
- :class:`envs.vehicle.terrain.TerrainDatabase` (``terrain``): the scenario's terrain,
  for the terrain protocol and the items above the terrain.

Landing is the autopilot's own (:meth:`Autopilot.land_at`, the land detector judged
on the true height above the terrain); so are the terrain clearance (never lower than
:data:`TERRAIN_CLEARANCE_M` above the ground, not PX4) and the geometry of items
(:meth:`Autopilot.item_position`). The commands are also methods of the autopilot
(:meth:`arm`, :meth:`takeoff`, :meth:`set_mode`, ...), answering a MAV_RESULT and
why. docs/vehicle.md has the tables and the deviations from PX4.
"""

from __future__ import annotations

import collections
import math
import time
from collections.abc import Callable, Sequence

import numpy as np
from pymavlink.dialects.v20.common import (
    MAV_LANDED_STATE_IN_AIR,
    MAV_LANDED_STATE_LANDING,
    MAV_LANDED_STATE_ON_GROUND,
    MAV_SEVERITY_INFO,
    MAV_SEVERITY_WARNING,
)

from envs.vehicle.executor import MissionExecutor, MissionProgress
from envs.vehicle.flight import (
    TERRAIN_CLEARANCE_M,
    Home,
    Idle,
    Land,
    Limits,
    Line,
    Task,
    Vec3,
    stopping_point,
)
from envs.vehicle.geofence import Fence, FenceGuard
from envs.vehicle.mission import ABSOLUTE_FRAMES, TERRAIN_FRAMES, has_position
from envs.vehicle.modes import ModeMachine, Result
from envs.vehicle.params import Params
from envs.vehicle.px4 import Mode
from envs.vehicle.rtl import ReturnToLaunch
from envs.vehicle.terrain import TerrainDatabase
from planner.mavlink_wire import WireItem
from sim.scenario import KeepOutZone
from sim.stepper import Emitted, Stepper

__all__ = ["TERRAIN_CLEARANCE_M", "Autopilot", "Home", "MissionProgress"]


class Autopilot:
    """See the module docstring. ``wall_clock`` gives the wall time of the operator
    timeouts (tests pass their own); ``keepouts`` are preloaded into the geofence
    (:class:`sim.scenario.KeepOutZone`, world ENU metres: a scenario's keep-outs)."""

    name = "autopilot"
    done = False

    def __init__(self, stepper: Stepper, params: Params | None = None, *,
                 wall_clock: Callable[[], float] = time.monotonic,
                 keepouts: Sequence[KeepOutZone] = ()) -> None:
        self.stepper = stepper
        self.agent = stepper.agents[0]
        self.vehicle = self.agent.vehicle
        self.world = stepper.world
        self.frame = self.world.frame
        self.terrain = TerrainDatabase(self.world)
        self._geo_key: Vec3 | None = None
        self._geo = (0.0, 0.0, 0.0)
        self.cfg = self.agent.spec.vehicle
        search = stepper.realisation.scenario.search
        cruise = min(search.speed_mps if search is not None else 5.0, self.cfg.max_speed_mps)
        self.params = params or Params(cruise, self.cfg.max_speed_mps,
                                       self.cfg.max_vertical_speed_mps)
        self.wall_clock = wall_clock
        self.dt = self.cfg.sample_dt_s
        self.t_s = self.vehicle.t_s
        self.landed = True
        self.landed_state = MAV_LANDED_STATE_ON_GROUND
        self.crashed = False
        self.task: Task = Idle()
        self.events: list[tuple] = []
        self.speed_override_mps: float | None = None
        self.touchdown_s: float | None = None
        self._limits_key: tuple | None = None
        self._limits: Limits | None = None
        self._floor_warned = False
        self._bias = (0.0, 0.0, 0.0)
        self._bias_t = -math.inf
        self._ground = (math.inf, math.inf, 0.0)  # (e, n, height) of the last lookup
        self.modes = ModeMachine(self)
        self.executor = MissionExecutor(self)
        self.geofence = FenceGuard(self, keepouts)
        self.rtl = ReturnToLaunch(self)
        self._sync()
        self._prev_pos = self._pos
        self.accel = (0.0, 0.0, 0.0)
        self.flight_time_s = 0.0
        self.home = self.home_here()
        stepper.command(0, self)

    # ------------------------------------------------------------------ state
    @property
    def mode(self) -> Mode:
        return self.modes.mode

    @property
    def armed(self) -> bool:
        return self.modes.armed

    @property
    def mission(self) -> MissionProgress:
        return self.executor.progress

    @property
    def reached_log(self) -> collections.deque[tuple[int, float, Vec3]]:
        """(seq, t_s, navigation position) of the items reached, in order (the last
        :data:`envs.vehicle.executor.HISTORY`)."""
        return self.executor.reached_log

    @property
    def mission_set_at(self) -> collections.deque[float]:
        """Simulated times of the mission changes (the last HISTORY)."""
        return self.executor.mission_set_at

    @property
    def fence(self) -> Fence:
        return self.geofence.fence

    @property
    def fence_items(self) -> list[WireItem]:
        return self.geofence.items

    @property
    def rally_items(self) -> list[WireItem]:
        return self.rtl.rally_items

    @property
    def rally_enu(self) -> list[Vec3]:
        return self.rtl.rally_enu

    @property
    def limits(self) -> Limits:
        key = (self.params.version, self.speed_override_mps)
        if self._limits_key != key:
            self._limits = self._make_limits()
            self._limits_key = key
        return self._limits

    def _make_limits(self) -> Limits:
        p = self.params
        cfg = self.cfg
        cruise = self.speed_override_mps if self.speed_override_mps is not None \
            else p["MPC_XY_CRUISE"]
        return Limits(
            cruise_mps=min(cruise, cfg.max_speed_mps), climb_mps=p["MPC_Z_VEL_MAX_UP"],
            descent_mps=p["MPC_Z_V_AUTO_DN"], takeoff_mps=p["MPC_TKO_SPEED"],
            land_mps=p["MPC_LAND_SPEED"], land_alt1_m=p["MPC_LAND_ALT1"],
            land_alt2_m=p["MPC_LAND_ALT2"], brake_mps2=0.8 * cfg.max_accel_mps2,
            brake_z_mps2=0.8 * cfg.max_vertical_accel_mps2,
            lateral_mps2=0.8 * cfg.max_lateral_accel_mps2,
            yaw_rate_rps=math.radians(cfg.max_yaw_rate_dps), gain_per_s=cfg.position_gain_per_s)

    def _sync(self) -> None:
        """Position and velocity at a step boundary."""
        self._pos = self.stepper.navigation_position_m(0)
        self._vel = tuple(self.vehicle.state.velocity_mps)

    @property
    def position(self) -> Vec3:
        """Navigation position (ENU m): what the autopilot believes."""
        return self._pos

    @property
    def velocity(self) -> Vec3:
        return self._vel

    def geodetic(self, p: Vec3) -> tuple[float, float, float]:
        """(lat, lon, ellipsoidal height) of an ENU point (the last one is cached)."""
        if self._geo_key != p:
            lat, lon, alt = self.frame.to_geodetic(p[0], p[1], p[2])
            self._geo = (float(lat), float(lon), float(alt))
            self._geo_key = p
        return self._geo

    def home_here(self) -> Home:
        """Home at the navigation position."""
        lat, lon, alt = self.geodetic(self._pos)
        return Home(self._pos, lat, lon, alt)

    def emit(self, *event: object) -> None:
        """An event for the MAVLink side: ("reached", seq), ("current", seq, total,
        state), ("mode",), ("armed",), ("home",), ("landed",), ("text", severity, text)."""
        self.events.append(event)

    def text(self, severity: int, message: str) -> None:
        self.emit("text", severity, message)

    def drain_events(self) -> list[tuple]:
        out, self.events = self.events, []
        return out

    def in_air(self) -> bool:
        return not self.landed

    def mission_current(self) -> tuple[int, int, int]:
        """(seq, total, MISSION_STATE) for MISSION_CURRENT."""
        return self.executor.mission_current()

    # ------------------------------------------------------------------ stepping
    def step_to(self, t_s: float) -> list[Emitted]:
        """Advance the vehicle and the phone to ``t_s``; the phone's new records."""
        self.t_s = self.vehicle.t_s
        out = self.stepper.step_to(t_s)[0]
        self._sync()
        return out

    def finish(self) -> list[Emitted]:
        return self.stepper.finish()[0]

    def command(self, px: float, py: float, pz: float, dt: float) -> Vec3:
        """One tick of guidance (the :mod:`sim.vehicle` protocol)."""
        p = (px, py, pz)
        q = self._prev_pos
        v = ((px - q[0]) / dt, (py - q[1]) / dt, (pz - q[2]) / dt)
        self.accel = ((v[0] - self._vel[0]) / dt, (v[1] - self._vel[1]) / dt,
                      (v[2] - self._vel[2]) / dt)
        self._pos, self._vel, self._prev_pos = p, v, p
        if self.modes.armed:
            if not self.landed:
                self.flight_time_s += dt
                self.geofence.check(p, v)
            self.modes.tick(p)
        cmd = self.task.setpoint(self, p, dt)
        if self.modes.armed and self.landed_state == MAV_LANDED_STATE_IN_AIR \
                and not isinstance(self.task, Land | Idle):
            cmd = self._terrain_floor(p, cmd)
        self._land_detector()
        self.t_s += dt
        return cmd

    # ------------------------------------------------------------------ sensing
    def _bias_now(self, fresh: bool = False) -> tuple[float, float, float]:
        """The navigation error now (cached for a second unless ``fresh``)."""
        if self.vehicle.nav_error is None:
            return 0.0, 0.0, 0.0
        if self.t_s - self._bias_t >= (1e-9 if fresh else 1.0):
            b = self.vehicle.nav_error(np.array([self.t_s]))[0]
            self._bias = (float(b[0]), float(b[1]), float(b[2]))
            self._bias_t = self.t_s
        return self._bias

    def ground_m(self, e_m: float, n_m: float) -> float:
        """The terrain database's ground height (ENU up) at (e, n)."""
        return self.terrain.ground_m(e_m, n_m)

    def agl_m(self, p: Vec3) -> float:
        """Height of ``p`` above the terrain database's ground under it."""
        return p[2] - self.terrain.ground_m(p[0], p[1])

    def true_agl_m(self, p: Vec3) -> float:
        """True height above the terrain of navigation position ``p``."""
        b = self._bias_now()
        e, n, z = p[0] - b[0], p[1] - b[1], p[2] - b[2]
        ge, gn, gh = self._ground
        low = z - gh < 5.0
        if low:  # near the ground: the error of this tick (it drifts by dm per second)
            b = self._bias_now(fresh=True)
            e, n, z = p[0] - b[0], p[1] - b[1], p[2] - b[2]
        tol = 0.25 if low else 2.0
        if abs(e - ge) > tol or abs(n - gn) > tol:
            gh = float(self.world.ground_m(e, n))
            self._ground = (e, n, gh)
        return z - gh

    def _terrain_floor(self, p: Vec3, cmd: Vec3) -> Vec3:
        agl = self.true_agl_m(p)
        limit = TERRAIN_CLEARANCE_M
        lim = self.limits
        if agl > limit + 15.0:
            self._floor_warned = False
            return cmd
        vz = cmd[2]
        vz_min = -math.sqrt(2.0 * lim.brake_z_mps2 * max(agl - 0.5 * limit, 0.0))
        if agl < limit:
            vz_min = max(vz_min, lim.gain_per_s * (limit - agl))
        if vz < vz_min:
            if not self._floor_warned and agl < limit + 0.5:
                self.text(MAV_SEVERITY_WARNING, f"terrain: keeping {limit:g} m above the ground")
                self._floor_warned = True
            return cmd[0], cmd[1], vz_min
        return cmd

    # ------------------------------------------------------------------ landing
    def hold_here(self, point: Vec3 | None = None) -> None:
        """Brake along the current velocity to its stopping point (or ``point``) and
        hold there: a line with a braking profile, so the stop does not overshoot."""
        self.task = Line(self._pos, point or stopping_point(self._pos, self._vel, self.limits))

    def land_at(self, x: float, y: float) -> None:
        """Descend at (x, y) until the land detector feels the ground."""
        self.task = Land(x, y)
        self.landed_state = MAV_LANDED_STATE_LANDING
        self.emit("landed")

    def _land_detector(self) -> None:
        t = self.t_s
        if isinstance(self.task, Land) and self.task.done and not self.landed:
            self.landed = True
            self.landed_state = MAV_LANDED_STATE_ON_GROUND
            self.touchdown_s = t
            self.task = Idle()
            self.text(MAV_SEVERITY_INFO, "landing detected")
            self.emit("landed")
            self.executor.on_touchdown()
            self.rtl.leg = None
        self.modes.after_touchdown(t)

    # ------------------------------------------------------------------ geometry
    def item_position(self, w: WireItem, here: Vec3 | None = None) -> Vec3:
        """An item's ENU target; no latitude and longitude (lat = lon = 0, or INT32_MAX:
        :func:`envs.vehicle.mission.has_position`) means the current position
        (``here``)."""
        here = here or self._pos
        if not has_position(w):
            e, n = here[0], here[1]
            lat, lon = self.geodetic(here)[:2]
        else:
            lat, lon = w.x / 1e7, w.y / 1e7
            e = n = math.nan
        if w.frame in ABSOLUTE_FRAMES:
            alt = w.z
        elif w.frame in TERRAIN_FRAMES:  # above the terrain database's ground
            if math.isnan(e):
                return self.terrain.above_ground(lat, lon, float(w.z))
            return e, n, self.terrain.ground_m(e, n) + float(w.z)
        else:
            alt = self.home.alt_m + w.z
        ee, nn, uu = self.frame.to_enu(lat, lon, alt)
        if math.isnan(e):
            e, n = float(ee), float(nn)
        return e, n, float(uu)

    _item_position = item_position  # the name the tests know

    # ------------------------------------------------------------------ commands
    def arm(self) -> Result:
        return self.modes.arm()

    def disarm(self, force: bool = False) -> Result:
        return self.modes.disarm(force)

    def takeoff(self, alt_amsl_m: float = math.nan) -> Result:
        return self.modes.takeoff(alt_amsl_m)

    def set_mode(self, mode: Mode) -> Result:
        return self.modes.set_mode(mode)

    def mission_start(self, first: float = 0.0, last: float = 0.0) -> Result:
        return self.modes.mission_start(first, last)

    def set_current(self, seq: int, reset_jumps: bool = False) -> Result:
        return self.modes.set_current(seq, reset_jumps)

    def pause_continue(self, resume: bool) -> Result:
        return self.modes.pause_continue(resume)

    def change_speed(self, speed_mps: float) -> Result:
        return self.modes.change_speed(speed_mps)

    def reposition(self, target: Vec3) -> Result:
        return self.modes.reposition(target)

    def set_home(self, geodetic: tuple[float, float, float] | None) -> Result:
        return self.modes.set_home(geodetic)

    def return_to_launch(self) -> Result:
        return self.modes.return_to_launch()

    def land(self) -> Result:
        return self.modes.land()

    def hold(self) -> Result:
        return self.modes.hold()

    def on_link_lost(self) -> None:
        self.modes.on_link_lost()

    def on_wall_clock(self, now: float) -> None:
        self.modes.on_wall_clock(now)

    # ------------------------------------------------------------------ storage
    def set_mission(self, items: Sequence[WireItem], current: int = 0) -> None:
        self.executor.set_mission(items, current)

    def clear_mission(self) -> None:
        self.set_mission([])

    def set_fence(self, items: Sequence[WireItem]) -> None:
        self.geofence.set_items(items)

    def set_rally(self, items: Sequence[WireItem]) -> None:
        self.rtl.set_rally(items)
