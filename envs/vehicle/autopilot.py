"""The autopilot: PX4 multicopter modes, arming, commands and the mission executor.

:class:`Autopilot` is the guidance of the simulated vehicle (it implements the
``command(px, py, pz, dt) -> (vx, vy, vz)`` protocol of :mod:`sim.vehicle`): every
20 Hz tick it runs the active flight task (:mod:`envs.vehicle.flight`) on the
navigation position, checks the geofence, the terrain clearance and the land
detector, advances the mission, and records events (item reached, current item,
mode, home, status texts) that the MAVLink side publishes. Commands arrive between
steps (:meth:`arm`, :meth:`takeoff`, :meth:`set_mode`, :meth:`mission_start`, ...)
and answer a MAV_RESULT.

PX4 semantics followed (docs/vehicle.md has the table and the deviations):

- boot landed and disarmed in AUTO.LOITER (Hold), home at the start point; home is
  reset at arming; disarm is refused in the air; auto-disarm COM_DISARM_LAND after
  touchdown and COM_DISARM_PRFLT after arming without taking off;
- NAV_WAYPOINT: straight lines at the cruise speed (MPC_XY_CRUISE, DO_CHANGE_SPEED),
  reached within param2 (else NAV_ACC_RAD) horizontally and NAV_MC_ALT_RAD
  vertically, braking for corners and stops, hold param1 seconds, then
  MISSION_ITEM_REACHED; autocontinue 0 pauses at the item;
- NAV_TAKEOFF on the ground: vertical climb at MPC_TKO_SPEED, then to its position
  if it has one; in the air it is a waypoint; a mission started on the ground without
  one climbs to MIS_TAKEOFF_ALT first;
- NAV_LAND: fly to its position (none: here), descend, touch down, disarm;
- NAV_RETURN_TO_LAUNCH: reached, then AUTO.RTL (climb to RTL_RETURN_ALT, fly to the
  closest of home and the rally points, descend to RTL_DESCEND_ALT, wait
  RTL_LAND_DELAY, land);
- NAV_LOITER_TIME (hover param1 s), NAV_LOITER_TURNS (param1 turns of radius
  |param3|, clockwise for param3 > 0), NAV_LOITER_UNLIM (hover, never reached),
  NAV_DELAY (hover param1 s); DO_JUMP (param1 target, param2 repeats, negative:
  forever; never the current item), DO_CHANGE_SPEED (param2 m/s; -2 the default);
- the end of the mission in the air switches to AUTO.LOITER;
- geofence breach (GF_ACTION, GF_PREDICT on the stopping point): hold at the last
  stopping point that was inside, return, or land; arming outside is denied.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from envs.vehicle.flight import (
    Hold,
    Idle,
    Land,
    Limits,
    Line,
    Orbit,
    Task,
    Vec3,
    corner_speed,
    stopping_point,
)
from envs.vehicle.geofence import Fence, fence_from_items
from envs.vehicle.mission import (
    ABSOLUTE_FRAMES,
    IGNORED_COMMANDS,
    MAV_CMD_DO_JUMP,
    MAV_CMD_NAV_DELAY,
    MAV_CMD_NAV_LOITER_TIME,
    MAV_CMD_NAV_LOITER_TURNS,
    MAV_CMD_NAV_LOITER_UNLIM,
    TERRAIN_FRAMES,
)
from envs.vehicle.params import Params
from envs.vehicle.px4 import (
    LANDED_IN_AIR,
    LANDED_LANDING,
    LANDED_ON_GROUND,
    LANDED_TAKEOFF,
    MAV_RESULT_ACCEPTED,
    MAV_RESULT_DENIED,
    MAV_RESULT_TEMPORARILY_REJECTED,
    MISSION_STATE_ACTIVE,
    MISSION_STATE_COMPLETE,
    MISSION_STATE_NO_MISSION,
    MISSION_STATE_NOT_STARTED,
    MISSION_STATE_PAUSED,
    SEVERITY_CRITICAL,
    SEVERITY_INFO,
    SEVERITY_NOTICE,
    SEVERITY_WARNING,
    Mode,
)
from planner.mavlink_wire import WireItem
from planner.mission import (
    MAV_CMD_DO_CHANGE_SPEED,
    MAV_CMD_NAV_LAND,
    MAV_CMD_NAV_RETURN_TO_LAUNCH,
    MAV_CMD_NAV_TAKEOFF,
    MAV_CMD_NAV_WAYPOINT,
)
from sim.stepper import Emitted, Stepper

FORCE_DISARM_MAGIC = 21196  # MAV_CMD_COMPONENT_ARM_DISARM param2: force
TERRAIN_CLEARANCE_M = 2.0  # the vehicle never flies lower above the ground (not PX4)
FENCE_MARGIN_M = 1.0  # a breach is predicted this far beyond the stopping point


@dataclass
class Home:
    """Home position: ENU (navigation frame) and geodetic (ellipsoidal height)."""

    enu: Vec3
    lat_deg: float
    lon_deg: float
    alt_m: float


@dataclass
class MissionProgress:
    """The mission the vehicle holds and where it is in it."""

    items: list[WireItem] = field(default_factory=list)
    seq: int = 0
    jumps: dict[int, int] = field(default_factory=dict)  # DO_JUMP seq -> jumps done
    complete: bool = False
    started: bool = False
    paused: bool = False

    @property
    def state(self) -> int:
        if not self.items:
            return MISSION_STATE_NO_MISSION
        if self.complete:
            return MISSION_STATE_COMPLETE
        if self.paused:
            return MISSION_STATE_PAUSED
        return MISSION_STATE_ACTIVE if self.started else MISSION_STATE_NOT_STARTED


@dataclass
class _Item:
    """The mission item being flown: its phase and task."""

    seq: int
    item: WireItem
    phase: str
    target: Vec3 | None = None
    until_s: float = math.inf
    radius_m: float = 0.0


@dataclass
class _Rtl:
    dest: tuple[float, float]
    return_z: float
    descend_z: float
    phase: str = "climb"
    until_s: float = math.inf


class Autopilot:
    """See the module docstring. ``wall_clock`` gives the wall time of the operator
    timeouts (tests pass their own)."""

    name = "autopilot"
    done = False

    def __init__(self, stepper: Stepper, params: Params | None = None, *,
                 wall_clock: Callable[[], float] = time.monotonic) -> None:
        self.stepper = stepper
        self.agent = stepper.agents[0]
        self.vehicle = self.agent.vehicle
        self.world = stepper.world
        self.frame = self.world.frame
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
        self.mode = Mode.LOITER
        self.armed = False
        self.landed = True
        self.landed_state = LANDED_ON_GROUND
        self.crashed = False
        self.mission = MissionProgress()
        self.fence = Fence()
        self.fence_items: list[WireItem] = []
        self.rally_items: list[WireItem] = []
        self.rally_enu: list[Vec3] = []
        self.task: Task = Idle()
        self.events: list[tuple] = []
        self.reached_log: list[tuple[int, float, Vec3]] = []  # (seq, t_s, position)
        self.mission_set_at: list[float] = []  # simulated times of mission changes
        self.speed_override_mps: float | None = None
        self._limits_key: tuple | None = None
        self._limits: Limits | None = None
        self._item: _Item | None = None
        self._rtl: _Rtl | None = None
        self._takeoff_then: str | None = None  # after a take-off: "hold" | "mission"
        self._touchdown_s: float | None = None
        self._armed_wall: float | None = None
        self._flew_since_arming = False
        self._fence_ok = True
        self._safe_stop: Vec3 | None = None
        self._floor_warned = False
        self._bias = (0.0, 0.0, 0.0)
        self._bias_t = -math.inf
        self._ground = (math.inf, math.inf, 0.0)  # (e, n, height) of the last lookup
        self._sync()
        self._prev_pos = self._pos
        self.accel = (0.0, 0.0, 0.0)
        self.flight_time_s = 0.0
        self.home = self._home_here()
        stepper.command(0, self)

    # ------------------------------------------------------------------ state
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

    def _home_here(self) -> Home:
        lat, lon, alt = self.geodetic(self._pos)
        return Home(self._pos, lat, lon, alt)

    def emit(self, *event: object) -> None:
        self.events.append(event)

    def _emit_current(self) -> None:
        self.emit("current", *self.mission_current())

    def text(self, severity: int, message: str) -> None:
        self.emit("text", severity, message)

    def drain_events(self) -> list[tuple]:
        out, self.events = self.events, []
        return out

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
        if self.armed:
            if not self.landed:
                self.flight_time_s += dt
                self._fence_check(p, v)
            self._run_mode(p)
        cmd = self.task.setpoint(self, p, dt)
        if self.armed and self.landed_state == LANDED_IN_AIR \
                and not isinstance(self.task, Land | Idle):
            cmd = self._terrain_floor(p, cmd)
        self._land_detector(p)
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
                self.text(SEVERITY_WARNING, f"terrain: keeping {limit:g} m above the ground")
                self._floor_warned = True
            return cmd[0], cmd[1], vz_min
        return cmd

    def _land_detector(self, p: Vec3) -> None:
        t = self.t_s
        if isinstance(self.task, Land) and self.task.done and not self.landed:
            self.landed = True
            self.landed_state = LANDED_ON_GROUND
            self._touchdown_s = t
            self.task = Idle()
            self.text(SEVERITY_INFO, "landing detected")
            self.emit("landed")
            if self._item is not None and self._item.item.command == MAV_CMD_NAV_LAND:
                self._reached(self._item.seq)
                self._item = None
                self._mission_complete(landed=True)
            self._rtl = None
        if self.armed and self.landed and self._touchdown_s is not None:
            delay = self.params["COM_DISARM_LAND"]
            if delay >= 0 and t - self._touchdown_s >= delay:
                self._disarm("auto-disarmed after landing")

    # ------------------------------------------------------------------ modes
    def _set_mode(self, mode: Mode) -> None:
        if mode is not self.mode:
            self.mode = mode
            self.emit("mode")
            self.text(SEVERITY_INFO, f"mode {mode.label}")

    def _hold_here(self, point: Vec3 | None = None) -> None:
        """Brake along the current velocity to its stopping point (or ``point``) and
        hold there: a line with a braking profile, so the stop does not overshoot."""
        self.task = Line(self._pos, point or stopping_point(self._pos, self._vel, self.limits))

    def _enter_mode(self, mode: Mode) -> None:
        """Switch to ``mode`` (already judged possible) and start flying it."""
        self._set_mode(mode)
        self._item = None
        self._rtl = None
        if self._takeoff_then is not None:
            self._takeoff_then = None
            if not self.landed:
                self.landed_state = LANDED_IN_AIR
                self.emit("landed")
        if mode is not Mode.MISSION:
            self._pause_mission()
        if not self.armed:
            return
        if self.landed:
            if mode is Mode.TAKEOFF:
                self._takeoff(self.params["MIS_TAKEOFF_ALT"], then="hold")
            elif mode is Mode.MISSION:
                self._mission_begin()
            return
        if mode in (Mode.LOITER, Mode.POSCTL, Mode.TAKEOFF):
            self._hold_here()
        elif mode is Mode.MISSION:
            self._mission_begin()
        elif mode is Mode.RTL:
            self._rtl_begin()
        elif mode is Mode.LAND:
            s = stopping_point(self._pos, self._vel, self.limits)
            self._land_at(s[0], s[1])

    def _pause_mission(self) -> None:
        m = self.mission
        if m.started and not m.complete and not m.paused:
            m.paused = True
            self._emit_current()

    def _run_mode(self, p: Vec3) -> None:
        if self._takeoff_then is not None:
            self._takeoff_tick(p)
        elif self.mode is Mode.MISSION and self._item is not None:
            self._mission_tick(p)
        elif self.mode is Mode.RTL and self._rtl is not None:
            self._rtl_tick(p)

    # ------------------------------------------------------------------ commands
    def arm(self) -> tuple[int, str]:
        """MAV_CMD_COMPONENT_ARM_DISARM param1 = 1."""
        if self.armed:
            return MAV_RESULT_ACCEPTED, ""
        if self.crashed:
            return MAV_RESULT_DENIED, "arming denied: the vehicle crashed"
        if not self.fence.empty and not self.fence.allows(self._pos[0], self._pos[1]):
            return MAV_RESULT_DENIED, "arming denied: outside the geofence"
        if self.mode in (Mode.RTL, Mode.LAND):
            return MAV_RESULT_DENIED, f"arming denied in {self.mode.label}"
        if self.mode is Mode.MISSION and not self.mission.items:
            return MAV_RESULT_DENIED, "arming denied: no mission"
        self.armed = True
        self._armed_wall = self.wall_clock()
        self._flew_since_arming = False
        self._touchdown_s = None
        self.home = self._home_here()
        self.emit("armed")
        self.emit("home")
        self.text(SEVERITY_INFO, "armed")
        if self.mode is Mode.MISSION:
            self._mission_begin()
        elif self.mode is Mode.TAKEOFF:
            self._takeoff(self.params["MIS_TAKEOFF_ALT"], then="hold")
        return MAV_RESULT_ACCEPTED, ""

    def disarm(self, force: bool = False) -> tuple[int, str]:
        if not self.armed:
            return MAV_RESULT_ACCEPTED, ""
        if not self.landed:
            return MAV_RESULT_DENIED, "disarming denied: in the air"
        self._disarm("disarmed")
        return MAV_RESULT_ACCEPTED, ""

    def _disarm(self, why: str) -> None:
        self.armed = False
        self._armed_wall = None
        self.task = Idle()
        self._item = None
        self._takeoff_then = None
        self.emit("armed")
        self.text(SEVERITY_INFO, why)
        if self.mission.complete:  # PX4: a flown mission starts over after landing
            self._restart_mission()

    def takeoff(self, alt_amsl_m: float = math.nan) -> tuple[int, str]:
        """MAV_CMD_NAV_TAKEOFF: climb to ``alt_amsl_m`` (NaN: MIS_TAKEOFF_ALT above home)."""
        if not self.armed:
            return MAV_RESULT_TEMPORARILY_REJECTED, "takeoff denied: disarmed"
        if not self.landed:
            return MAV_RESULT_TEMPORARILY_REJECTED, "takeoff denied: already flying"
        if math.isfinite(alt_amsl_m):
            rel = alt_amsl_m - self.home.alt_m
        else:
            rel = self.params["MIS_TAKEOFF_ALT"]
        if not 1.0 <= rel <= 1000.0:
            return MAV_RESULT_DENIED, f"takeoff denied: altitude {rel:.1f} m above home"
        self._set_mode(Mode.TAKEOFF)
        self._item = None
        self._takeoff(rel, then="hold")
        return MAV_RESULT_ACCEPTED, ""

    def _takeoff(self, rel_alt_m: float, then: str) -> None:
        self._climb_to(self.home.enu[2] + max(rel_alt_m, 1.0), then)

    def _climb_to(self, z: float, then: str) -> None:
        p = self._pos
        self.task = Line(p, (p[0], p[1], z), vertical_mps=self.params["MPC_TKO_SPEED"])
        self._takeoff_then = then
        self.landed = False
        self._flew_since_arming = True
        self._touchdown_s = None
        self.landed_state = LANDED_TAKEOFF
        self.emit("landed")

    def _takeoff_tick(self, p: Vec3) -> None:
        task = self.task
        assert isinstance(task, Line)
        if abs(task.target[2] - p[2]) > self.params["NAV_MC_ALT_RAD"]:
            return
        then, self._takeoff_then = self._takeoff_then, None
        self.landed_state = LANDED_IN_AIR
        self.emit("landed")
        it = self._item
        if then == "item" and it is not None and self.mode is Mode.MISSION:
            t = it.target or p
            w = it.item
            if (w.x or w.y) and math.hypot(t[0] - p[0], t[1] - p[1]) > it.radius_m:
                it.phase = "fly"
                self.task = Line(p, t)
            else:
                self._item_done(it, p)
        elif then in ("mission", "item") and self.mode is Mode.MISSION:
            self._enter_item(self.mission.seq, p)
        else:
            self.task = Hold(task.target)
            if self.mode is Mode.TAKEOFF:
                self._set_mode(Mode.LOITER)

    def set_mode(self, mode: Mode) -> tuple[int, str]:
        """A PX4 mode change (DO_SET_MODE, SET_MODE)."""
        if mode is Mode.MISSION and not self.mission.items:
            return MAV_RESULT_TEMPORARILY_REJECTED, "mission mode denied: no mission"
        if mode in (Mode.RTL, Mode.LAND) and self.landed:
            return MAV_RESULT_TEMPORARILY_REJECTED, f"{mode.label} denied: landed"
        if mode is Mode.TAKEOFF and not self.landed:
            return MAV_RESULT_TEMPORARILY_REJECTED, "takeoff mode denied: already flying"
        if mode is self.mode and (mode is not Mode.MISSION or self._item is not None
                                  or not self.armed):
            return MAV_RESULT_ACCEPTED, ""
        self._enter_mode(mode)
        return MAV_RESULT_ACCEPTED, ""

    def mission_start(self, first: float = 0.0, last: float = 0.0) -> tuple[int, str]:
        """MAV_CMD_MISSION_START (param1 first item; 0 = from the current item)."""
        m = self.mission
        n = len(m.items)
        if not n:
            return MAV_RESULT_DENIED, "mission start denied: no mission"
        if not (math.isfinite(first) and 0 <= int(first) < n):
            return MAV_RESULT_DENIED, f"mission start denied: no item {first:g}"
        m.seq = int(first)
        m.complete = m.paused = m.started = False
        m.jumps.clear()
        self._item = None
        self._emit_current()
        if self.mode is Mode.MISSION:
            self._enter_mode(Mode.MISSION)
            return MAV_RESULT_ACCEPTED, ""
        return self.set_mode(Mode.MISSION)

    def _restart_mission(self) -> None:
        m = self.mission
        m.complete = m.started = m.paused = False
        m.seq = 0
        m.jumps.clear()
        self._emit_current()

    def set_current(self, seq: int, reset_jumps: bool = False) -> tuple[int, str]:
        """MISSION_SET_CURRENT / MAV_CMD_DO_SET_MISSION_CURRENT."""
        m = self.mission
        if not 0 <= seq < len(m.items):
            return MAV_RESULT_DENIED, f"set current denied: no item {seq}"
        m.seq = seq
        m.complete = False
        m.paused = False
        if reset_jumps:
            m.jumps.clear()
        self._emit_current()
        if self.mode is Mode.MISSION and self.armed and not self.landed \
                and self._takeoff_then is None:
            self._enter_item(seq, self._pos)
        return MAV_RESULT_ACCEPTED, ""

    def pause_continue(self, resume: bool) -> tuple[int, str]:
        """MAV_CMD_DO_PAUSE_CONTINUE: 0 holds, 1 resumes the mission."""
        if not resume:
            return self.set_mode(Mode.LOITER)
        m = self.mission
        if m.paused and self._item is not None:  # autocontinue 0: go on to the next item
            m.paused = False
            seq = self._item.seq
            tgt = self._item.target or self._pos
            self._enter_item(seq + 1, tgt)
            return MAV_RESULT_ACCEPTED, ""
        return self.set_mode(Mode.MISSION)

    def change_speed(self, speed_mps: float) -> tuple[int, str]:
        """MAV_CMD_DO_CHANGE_SPEED (param2): -2 (or -1 with nothing set) the default."""
        if speed_mps == -2.0:
            self.speed_override_mps = None
            return MAV_RESULT_ACCEPTED, ""
        if speed_mps == -1.0:
            return MAV_RESULT_ACCEPTED, ""
        vmax = self.params["MPC_XY_VEL_MAX"]
        if not math.isfinite(speed_mps) or speed_mps <= 0:
            return MAV_RESULT_DENIED, f"speed {speed_mps:g} m/s refused"
        self.speed_override_mps = min(speed_mps, vmax)
        return MAV_RESULT_ACCEPTED, ""

    def reposition(self, target: Vec3) -> tuple[int, str]:
        """MAV_CMD_DO_REPOSITION: fly there and hold (AUTO.LOITER)."""
        if not self.armed or self.landed:
            return MAV_RESULT_TEMPORARILY_REJECTED, "reposition denied: not flying"
        self._enter_mode(Mode.LOITER)
        self.task = Line(self._pos, target)
        return MAV_RESULT_ACCEPTED, ""

    def set_home(self, geodetic: tuple[float, float, float] | None) -> tuple[int, str]:
        """MAV_CMD_DO_SET_HOME: here (None) or at (lat, lon, alt)."""
        if geodetic is None:
            self.home = self._home_here()
        else:
            lat, lon, alt = geodetic
            e, n, u = self.frame.to_enu(lat, lon, alt)
            self.home = Home((float(e), float(n), float(u)), lat, lon, alt)
        self.emit("home")
        return MAV_RESULT_ACCEPTED, ""

    def return_to_launch(self) -> tuple[int, str]:
        return self.set_mode(Mode.RTL)

    def land(self) -> tuple[int, str]:
        return self.set_mode(Mode.LAND)

    def hold(self) -> tuple[int, str]:
        return self.set_mode(Mode.LOITER)

    # ------------------------------------------------------------------ storage
    def set_mission(self, items: Sequence[WireItem], current: int = 0) -> None:
        """A complete, validated mission upload: it replaces the held one at once; a
        mission being flown switches to it from where the vehicle is."""
        n = len(items)
        self.mission_set_at.append(self.t_s)
        flying = self.mode is Mode.MISSION and self.armed and not self.landed \
            and self._takeoff_then is None
        self.mission = MissionProgress(items=list(items), seq=current if 0 <= current < n else 0)
        self._item = None
        self._emit_current()
        if not n:
            if flying:
                self._set_mode(Mode.LOITER)
                self._hold_here()
            return
        if flying:
            self.mission.started = True
            self._enter_item(self.mission.seq, self._pos)

    def clear_mission(self) -> None:
        self.set_mission([])

    def set_fence(self, items: Sequence[WireItem]) -> None:
        self.fence_items = list(items)

        def to_en(lat: float, lon: float) -> tuple[float, float]:
            e, n, _ = self.frame.to_enu(lat, lon, self.home.alt_m)
            return float(e), float(n)

        self.fence = fence_from_items(items, to_en)
        self._fence_ok = True
        self._safe_stop = None

    def set_rally(self, items: Sequence[WireItem]) -> None:
        self.rally_items = list(items)
        self.rally_enu = [self._item_position(w) for w in items]

    # ------------------------------------------------------------------ geometry
    def _item_position(self, w: WireItem, here: Vec3 | None = None) -> Vec3:
        """An item's ENU target; lat = lon = 0 means the current position."""
        here = here or self._pos
        if w.x == 0 and w.y == 0:
            e, n = here[0], here[1]
            lat, lon = self.geodetic(here)[:2]
        else:
            lat, lon = w.x / 1e7, w.y / 1e7
            e = n = math.nan
        if w.frame in ABSOLUTE_FRAMES:
            alt = w.z
        elif w.frame in TERRAIN_FRAMES:
            if math.isnan(e):
                ee, nn, _ = self.frame.to_enu(lat, lon, self.home.alt_m)
                e, n = float(ee), float(nn)
            return e, n, float(self.world.ground_m(e, n)) + float(w.z)
        else:
            alt = self.home.alt_m + w.z
        ee, nn, uu = self.frame.to_enu(lat, lon, alt)
        if math.isnan(e):
            e, n = float(ee), float(nn)
        return e, n, float(uu)

    def _acceptance_m(self, w: WireItem) -> float:
        return w.param2 if w.command == MAV_CMD_NAV_WAYPOINT and w.param2 > 0 \
            else self.params["NAV_ACC_RAD"]

    # ------------------------------------------------------------------ mission
    def _mission_begin(self) -> None:
        m = self.mission
        if m.complete:
            if self.landed:
                self._restart_mission()
            else:
                self._set_mode(Mode.LOITER)
                self._hold_here()
                return
        m.started = True
        m.paused = False
        self._emit_current()
        self._set_mode(Mode.MISSION)
        if self.landed:
            first = self._resolve(m.seq, count=False)
            w = m.items[first] if first is not None else None
            if w is not None and w.command == MAV_CMD_NAV_TAKEOFF:
                self._enter_item(m.seq, self._pos)
            else:
                self._takeoff(self.params["MIS_TAKEOFF_ALT"], then="mission")
            return
        self._enter_item(m.seq, self._pos)

    def _resolve(self, seq: int, *, count: bool) -> int | None:
        """The first item to fly from ``seq`` following DO_JUMPs (counting them when
        ``count``); None past the end."""
        items = self.mission.items
        jumps = self.mission.jumps if count else dict(self.mission.jumps)
        for _ in range(4 * len(items) + 8):
            if seq >= len(items):
                return None
            w = items[seq]
            if w.command != MAV_CMD_DO_JUMP:
                return seq
            done = jumps.get(seq, 0)
            repeat = int(w.param2)
            if repeat < 0 or done < repeat:
                jumps[seq] = done + 1
                seq = int(w.param1)
            else:
                seq += 1
        return None  # a loop of jumps without a flown item

    def _set_current(self, seq: int) -> None:
        if self.mission.seq != seq:
            self.mission.seq = seq
        self._emit_current()

    def _reached(self, seq: int) -> None:
        self.reached_log.append((seq, self.t_s, self._pos))
        self.emit("reached", seq)

    def _enter_item(self, seq: int, leg_start: Vec3) -> None:
        """Start flying the mission from item ``seq`` (instant items are done here)."""
        m = self.mission
        items = m.items
        for _ in range(4 * len(items) + 8):
            k = self._resolve(seq, count=True)
            if k is None:
                self._mission_complete(landed=False)
                return
            w = items[k]
            self._set_current(k)
            if w.command == MAV_CMD_DO_CHANGE_SPEED:
                if w.param1 in (0.0, 1.0) or not math.isfinite(w.param1):
                    self.change_speed(float(w.param2))
                self._reached(k)
                seq = k + 1
                continue
            if w.command in IGNORED_COMMANDS:
                self._reached(k)
                seq = k + 1
                continue
            break
        else:
            self._mission_complete(landed=False)
            return
        self._start_item(k, w, leg_start)

    def _start_item(self, seq: int, w: WireItem, leg_start: Vec3) -> None:
        p = self._pos
        cmd = w.command
        it = _Item(seq, w, "fly")
        self._item = it
        if cmd == MAV_CMD_NAV_RETURN_TO_LAUNCH:
            self._reached(seq)
            self._item = None
            self._mission_complete(landed=False, then_rtl=True)
            return
        if cmd == MAV_CMD_NAV_DELAY:
            it.phase = "hold"
            it.target = p
            it.until_s = self.t_s + max(w.param1, 0.0)
            self.task = Hold(p)
            return
        target = self._item_position(w)
        it.target = target
        it.radius_m = self._acceptance_m(w)
        if cmd == MAV_CMD_NAV_TAKEOFF and self.landed:
            it.phase = "climb"
            self._climb_to(max(target[2], self.home.enu[2] + 1.0), then="item")
            return
        if cmd == MAV_CMD_NAV_LAND:
            it.target = (target[0], target[1], p[2])
            if math.hypot(target[0] - p[0], target[1] - p[1]) <= it.radius_m:
                it.phase = "land"
                self._land_at(target[0], target[1])
                return
            self.task = Line((leg_start[0], leg_start[1], p[2]), it.target)
            return
        if cmd == MAV_CMD_NAV_LOITER_TURNS:
            radius = abs(w.param3) if math.isfinite(w.param3) else 0.0
            if radius > 0:
                dx, dy = p[0] - target[0], p[1] - target[1]
                d = math.hypot(dx, dy)
                ux, uy = (dx / d, dy / d) if d > 1e-3 else (1.0, 0.0)
                it.target = (target[0] + radius * ux, target[1] + radius * uy, target[2])
        end = 0.0
        if cmd == MAV_CMD_NAV_WAYPOINT and w.param1 <= 0 and w.autocontinue:
            end = self._corner_after(seq, leg_start, it.target, it.radius_m)
        self.task = Line(leg_start, it.target, end_speed_mps=end, end_at_m=it.radius_m)

    def _corner_after(self, seq: int, start: Vec3, target: Vec3, radius: float) -> float:
        nxt = self._resolve(seq + 1, count=False)
        items = self.mission.items
        while nxt is not None and (items[nxt].command == MAV_CMD_DO_CHANGE_SPEED
                                   or items[nxt].command in IGNORED_COMMANDS):
            nxt = self._resolve(nxt + 1, count=False)
        if nxt is None:
            return 0.0
        w = items[nxt]
        if w.command != MAV_CMD_NAV_WAYPOINT or w.param1 > 0:
            return 0.0
        t2 = self._item_position(w, here=target)
        a = (target[0] - start[0], target[1] - start[1])
        b = (t2[0] - target[0], t2[1] - target[1])
        la, lb = math.hypot(*a), math.hypot(*b)
        if la < 1e-3 or lb < 1e-3:
            return 0.0
        lim = self.limits
        v = corner_speed((a[0] / la, a[1] / la), (b[0] / lb, b[1] / lb), radius, lim,
                         lim.cruise_mps)
        # the next leg must be long enough to brake to a stop at its own end
        return min(v, math.sqrt(2.0 * lim.brake_mps2 * lb))

    def _mission_tick(self, p: Vec3) -> None:
        it = self._item
        assert it is not None
        w = it.item
        alt_rad = self.params["NAV_MC_ALT_RAD"]
        if it.phase == "climb":  # the take-off item's climb is done by _takeoff_tick
            return
        if it.phase == "fly":
            t = it.target
            assert t is not None
            h = math.hypot(t[0] - p[0], t[1] - p[1])
            if h > it.radius_m:
                return
            if abs(t[2] - p[2]) > alt_rad and not (
                    t[2] < p[2] and self.true_agl_m(p) <= TERRAIN_CLEARANCE_M + alt_rad):
                return  # (a target below the terrain clearance counts as reached above it)
            cmd = w.command
            if cmd == MAV_CMD_NAV_LAND:
                it.phase = "land"
                self._land_at(t[0], t[1])
                return
            if cmd == MAV_CMD_NAV_LOITER_UNLIM:
                it.phase = "loiter"
                self.task = Hold(t)
                return
            if cmd == MAV_CMD_NAV_LOITER_TURNS:
                radius = abs(w.param3) if math.isfinite(w.param3) else 0.0
                if radius > 0 and w.param1 > 0:
                    c = self._item_position(w)
                    it.phase = "orbit"
                    self.task = Orbit((c[0], c[1]), radius, t[2],
                                      -1 if w.param3 > 0 else 1, w.param1)
                    return
            hold_s = w.param1 if cmd in (MAV_CMD_NAV_WAYPOINT, MAV_CMD_NAV_LOITER_TIME) else 0.0
            if hold_s > 0:
                it.phase = "hold"
                it.until_s = self.t_s + hold_s
                self.task = Hold(t)
                return
            self._item_done(it, t)
            return
        if it.phase == "hold" and self.t_s >= it.until_s:
            self._item_done(it, it.target or p)
        elif it.phase == "orbit" and self.task.done:
            self._item_done(it, p)

    def _item_done(self, it: _Item, leg_end: Vec3) -> None:
        self._reached(it.seq)
        if not it.item.autocontinue:
            self.mission.paused = True
            it.phase = "paused"
            self.task = Hold(leg_end)
            self._emit_current()
            return
        self._enter_item(it.seq + 1, leg_end)

    def _mission_complete(self, *, landed: bool, then_rtl: bool = False) -> None:
        m = self.mission
        m.complete = True
        m.started = False
        self._item = None
        self._emit_current()
        self.text(SEVERITY_INFO, "mission finished")
        if then_rtl:
            self._enter_mode(Mode.RTL)
        elif not landed and not self.landed:
            self._set_mode(Mode.LOITER)
            self._hold_here()

    # ------------------------------------------------------------------ RTL / land
    def _land_at(self, x: float, y: float) -> None:
        self.task = Land(x, y)
        self.landed_state = LANDED_LANDING
        self.emit("landed")

    def _rtl_begin(self) -> None:
        p = self._pos
        dest = (self.home.enu[0], self.home.enu[1])
        descend = self.home.enu[2] + self.params["RTL_DESCEND_ALT"]
        best = math.hypot(dest[0] - p[0], dest[1] - p[1])
        for r in self.rally_enu:
            d = math.hypot(r[0] - p[0], r[1] - p[1])
            if d < best:
                best, dest, descend = d, (r[0], r[1]), r[2]
        ret = max(p[2], self.home.enu[2] + self.params["RTL_RETURN_ALT"])
        self._rtl = _Rtl(dest, ret, min(descend, ret))
        self.text(SEVERITY_NOTICE, f"returning: {best:.0f} m to go")
        self.task = Line(p, (p[0], p[1], ret))

    def _rtl_tick(self, p: Vec3) -> None:
        r = self._rtl
        assert r is not None
        alt_rad = self.params["NAV_MC_ALT_RAD"]
        task = self.task
        if r.phase == "climb" and isinstance(task, Line):
            if abs(task.target[2] - p[2]) <= alt_rad:
                r.phase = "return"
                self.task = Line(p, (r.dest[0], r.dest[1], r.return_z))
        elif r.phase == "return" and isinstance(task, Line):
            if task.distances(p)[0] <= self.params["NAV_ACC_RAD"] \
                    and task.distances(p)[1] <= alt_rad:
                r.phase = "descend"
                self.task = Line(p, (r.dest[0], r.dest[1], r.descend_z))
        elif r.phase == "descend" and isinstance(task, Line):
            if task.distances(p)[1] <= alt_rad:
                delay = self.params["RTL_LAND_DELAY"]
                r.phase = "loiter"
                r.until_s = math.inf if delay < 0 else self.t_s + delay
                self.task = Hold((r.dest[0], r.dest[1], r.descend_z))
        elif r.phase == "loiter" and self.t_s >= r.until_s:
            r.phase = "land"
            self._land_at(r.dest[0], r.dest[1])

    # ------------------------------------------------------------------ failsafes
    def _fence_check(self, p: Vec3, v: Vec3) -> bool:
        """Edge-triggered geofence action (True when it fired)."""
        if self.fence.empty or self.mode in (Mode.RTL, Mode.LAND):
            return False
        lim = self.limits
        point = stopping_point(p, v, lim) if self.params["GF_PREDICT"] else p
        sh = math.hypot(v[0], v[1])
        m = FENCE_MARGIN_M / sh if sh > 0.1 else 0.0  # look a margin beyond the stop
        ok = self.fence.allows(point[0] + v[0] * m, point[1] + v[1] * m)
        if ok:
            self._fence_ok = True
            self._safe_stop = point
            return False
        if not self._fence_ok:
            return False
        self._fence_ok = False
        action = int(self.params["GF_ACTION"])
        self.text(SEVERITY_CRITICAL, "geofence breached" + (" (predicted)" if point != p else ""))
        if action == 2:
            self._enter_mode(Mode.LOITER)
            self._hold_here(self._safe_stop or p)
        elif action == 3:
            self._enter_mode(Mode.RTL)
        elif action == 5:
            self._enter_mode(Mode.LAND)
        return action >= 2

    def on_link_lost(self) -> None:
        """The ground station is gone (COM_DL_LOSS_T): NAV_DLL_ACT unless exempt."""
        if not self.armed or self.landed:
            return
        action = int(self.params["NAV_DLL_ACT"])
        exempt = int(self.params["COM_DLL_EXCEPT"])
        if self.mode is Mode.MISSION and exempt & 1:
            self.text(SEVERITY_WARNING, "ground station lost: mission continues")
            return
        if self.mode in (Mode.LOITER, Mode.POSCTL) and exempt & 2:
            self.text(SEVERITY_WARNING, "ground station lost: holding")
            return
        self.text(SEVERITY_CRITICAL, "ground station lost: failsafe")
        if action == 1:
            self._enter_mode(Mode.LOITER)
        elif action == 2 and self.mode is not Mode.RTL:
            self._enter_mode(Mode.RTL)
        elif action == 3 and self.mode is not Mode.LAND:
            self._enter_mode(Mode.LAND)

    def on_wall_clock(self, now: float) -> None:
        """Operator timeouts: disarm when armed on the ground without taking off."""
        delay = self.params["COM_DISARM_PRFLT"]
        if (self.armed and self.landed and not self._flew_since_arming and delay >= 0
                and self._armed_wall is not None and now - self._armed_wall >= delay):
            self._disarm("auto-disarmed: no take-off")

    # ------------------------------------------------------------------ reports
    def mission_current(self) -> tuple[int, int, int]:
        """(seq, total, MISSION_STATE) for MISSION_CURRENT."""
        m = self.mission
        return m.seq, len(m.items), m.state

    def in_air(self) -> bool:
        return not self.landed
