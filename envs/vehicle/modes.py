"""The mode machine: PX4 flight modes, arming, take-off and the commands a ground
station sends.

:class:`ModeMachine` holds the flight mode and the armed state and answers the
commands (:meth:`arm`, :meth:`takeoff`, :meth:`set_mode`, :meth:`mission_start`,
...) with a MAV_RESULT and, for a refusal, why. Entering a mode starts flying it:
AUTO.LOITER and POSCTL brake to the stopping point and hold it, AUTO.TAKEOFF climbs,
AUTO.MISSION hands over to the mission executor (:mod:`envs.vehicle.executor`),
AUTO.RTL to the return (:mod:`envs.vehicle.rtl`), AUTO.LAND lands at the stopping
point. PX4 semantics (docs/vehicle.md has the tables):

- boot landed and disarmed in AUTO.LOITER (Hold); home is reset at arming; arming is
  denied outside the geofence, in AUTO.RTL / AUTO.LAND, and in AUTO.MISSION without a
  mission; disarm is refused in the air; auto-disarm COM_DISARM_LAND after touchdown
  and COM_DISARM_PRFLT (wall clock) after arming without taking off;
- take-off: a vertical climb at MPC_TKO_SPEED (to MIS_TAKEOFF_ALT, the command's
  altitude, or a take-off item's), then hold, the mission or the item;
- link loss (COM_DL_LOSS_T): NAV_DLL_ACT unless the mode is exempt (COM_DLL_EXCEPT).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

from pymavlink.dialects.v20.common import (
    MAV_LANDED_STATE_IN_AIR,
    MAV_LANDED_STATE_TAKEOFF,
    MAV_RESULT_ACCEPTED,
    MAV_RESULT_DENIED,
    MAV_RESULT_FAILED,
    MAV_RESULT_TEMPORARILY_REJECTED,
    MAV_SEVERITY_CRITICAL,
    MAV_SEVERITY_INFO,
    MAV_SEVERITY_WARNING,
)

from envs.vehicle.flight import Hold, Home, Idle, Line, Vec3, stopping_point
from envs.vehicle.px4 import Mode

if TYPE_CHECKING:
    from envs.vehicle.autopilot import Autopilot

Result = tuple[int, str]  # (MAV_RESULT, why: empty when accepted)


class ModeMachine:
    """See the module docstring; ``ap`` is the autopilot whose modes these are."""

    def __init__(self, ap: Autopilot) -> None:
        self.ap = ap
        self.mode = Mode.LOITER
        self.armed = False
        self.takeoff_then: str | None = None  # after a take-off: "hold" | "mission" | "item"
        self._armed_wall: float | None = None
        self._flew_since_arming = False

    # ------------------------------------------------------------------ modes
    def switch(self, mode: Mode) -> None:
        """Say the mode is ``mode`` (nothing else changes)."""
        if mode is not self.mode:
            self.mode = mode
            self.ap.emit("mode")
            self.ap.text(MAV_SEVERITY_INFO, f"mode {mode.label}")

    def enter(self, mode: Mode) -> None:
        """Switch to ``mode`` (already judged possible) and start flying it."""
        ap = self.ap
        self.switch(mode)
        ap.executor.item = None
        ap.rtl.leg = None
        if self.takeoff_then is not None:
            self.takeoff_then = None
            if not ap.landed:
                ap.landed_state = MAV_LANDED_STATE_IN_AIR
                ap.emit("landed")
        if mode is not Mode.MISSION:
            ap.executor.pause()
        if not self.armed:
            return
        if ap.landed:
            if mode is Mode.TAKEOFF:
                self.takeoff_climb(ap.params["MIS_TAKEOFF_ALT"], then="hold")
            elif mode is Mode.MISSION:
                ap.executor.begin()
            return
        if mode in (Mode.LOITER, Mode.POSCTL, Mode.TAKEOFF):
            ap.hold_here()
        elif mode is Mode.MISSION:
            ap.executor.begin()
        elif mode is Mode.RTL:
            ap.rtl.begin()
        elif mode is Mode.LAND:
            s = stopping_point(ap.position, ap.velocity, ap.limits)
            ap.land_at(s[0], s[1])

    def tick(self, p: Vec3) -> None:
        """One 20 Hz tick of the active mode (armed)."""
        ap = self.ap
        if self.takeoff_then is not None:
            self._takeoff_tick(p)
        elif self.mode is Mode.MISSION and ap.executor.item is not None:
            ap.executor.tick(p)
        elif self.mode is Mode.RTL and ap.rtl.leg is not None:
            ap.rtl.tick(p)

    # ------------------------------------------------------------------ arming
    def arm(self) -> Result:
        """MAV_CMD_COMPONENT_ARM_DISARM param1 = 1."""
        ap = self.ap
        if self.armed:
            return MAV_RESULT_ACCEPTED, ""
        if ap.crashed:
            return MAV_RESULT_DENIED, "arming denied: the vehicle crashed"
        if not ap.geofence.allows(ap.position):
            return MAV_RESULT_DENIED, "arming denied: outside the geofence"
        if self.mode in (Mode.RTL, Mode.LAND):
            return MAV_RESULT_DENIED, f"arming denied in {self.mode.label}"
        if self.mode is Mode.MISSION and not ap.executor.progress.items:
            return MAV_RESULT_DENIED, "arming denied: no mission"
        self.armed = True
        self._armed_wall = ap.wall_clock()
        self._flew_since_arming = False
        ap.touchdown_s = None
        ap.home = ap.home_here()
        ap.emit("armed")
        ap.emit("home")
        ap.text(MAV_SEVERITY_INFO, "armed")
        if self.mode is Mode.MISSION:
            ap.executor.begin()
        elif self.mode is Mode.TAKEOFF:
            self.takeoff_climb(ap.params["MIS_TAKEOFF_ALT"], then="hold")
        return MAV_RESULT_ACCEPTED, ""

    def disarm(self, force: bool = False) -> Result:
        if not self.armed:
            return MAV_RESULT_ACCEPTED, ""
        if not self.ap.landed:
            return MAV_RESULT_DENIED, "disarming denied: in the air"
        self.disarm_now("disarmed")
        return MAV_RESULT_ACCEPTED, ""

    def disarm_now(self, why: str) -> None:
        ap = self.ap
        self.armed = False
        self._armed_wall = None
        ap.task = Idle()
        ap.executor.item = None
        self.takeoff_then = None
        ap.emit("armed")
        ap.text(MAV_SEVERITY_INFO, why)
        if ap.executor.progress.complete:  # PX4: a flown mission starts over after landing
            ap.executor.restart()

    def after_touchdown(self, t_s: float) -> None:
        """COM_DISARM_LAND after touchdown (simulated time)."""
        ap = self.ap
        if self.armed and ap.landed and ap.touchdown_s is not None:
            delay = ap.params["COM_DISARM_LAND"]
            if delay >= 0 and t_s - ap.touchdown_s >= delay:
                self.disarm_now("auto-disarmed after landing")

    def on_wall_clock(self, now: float) -> None:
        """Operator timeouts: disarm when armed on the ground without taking off."""
        ap = self.ap
        delay = ap.params["COM_DISARM_PRFLT"]
        if (self.armed and ap.landed and not self._flew_since_arming and delay >= 0
                and self._armed_wall is not None and now - self._armed_wall >= delay):
            self.disarm_now("auto-disarmed: no take-off")

    # ------------------------------------------------------------------ take-off
    def takeoff(self, alt_amsl_m: float = math.nan) -> Result:
        """MAV_CMD_NAV_TAKEOFF: climb to ``alt_amsl_m`` (NaN: MIS_TAKEOFF_ALT above home)."""
        ap = self.ap
        if not self.armed:
            return MAV_RESULT_TEMPORARILY_REJECTED, "takeoff denied: disarmed"
        if not ap.landed:
            # idempotent, as MAVLink asks (a take-off sent again because its ACK was lost
            # must not fail): ACCEPTED, nothing changes
            return MAV_RESULT_ACCEPTED, "takeoff: already flying"
        if math.isfinite(alt_amsl_m):
            rel = alt_amsl_m - ap.home.alt_m
        else:
            rel = ap.params["MIS_TAKEOFF_ALT"]
        if not 1.0 <= rel <= 1000.0:
            return MAV_RESULT_DENIED, f"takeoff denied: altitude {rel:.1f} m above home"
        self.switch(Mode.TAKEOFF)
        ap.executor.item = None
        self.takeoff_climb(rel, then="hold")
        return MAV_RESULT_ACCEPTED, ""

    def takeoff_climb(self, rel_alt_m: float, then: str) -> None:
        """Climb to ``rel_alt_m`` above home (at least 1 m), then ``then``."""
        self.climb_to(self.ap.home.enu[2] + max(rel_alt_m, 1.0), then)

    def climb_to(self, z: float, then: str) -> None:
        """Vertical climb from the ground to ENU height ``z``, then ``then`` ("hold":
        AUTO.LOITER; "mission": the mission's current item; "item": the take-off
        item's position)."""
        ap = self.ap
        p = ap.position
        ap.task = Line(p, (p[0], p[1], z), vertical_mps=ap.params["MPC_TKO_SPEED"])
        self.takeoff_then = then
        ap.landed = False
        self._flew_since_arming = True
        ap.touchdown_s = None
        ap.landed_state = MAV_LANDED_STATE_TAKEOFF
        ap.emit("landed")

    def _takeoff_tick(self, p: Vec3) -> None:
        ap = self.ap
        task = ap.task
        assert isinstance(task, Line)
        if abs(task.target[2] - p[2]) > ap.params["NAV_MC_ALT_RAD"]:
            return
        then, self.takeoff_then = self.takeoff_then, None
        ap.landed_state = MAV_LANDED_STATE_IN_AIR
        ap.emit("landed")
        if then == "item" and ap.executor.item is not None and self.mode is Mode.MISSION:
            ap.executor.climbed(p)
        elif then in ("mission", "item") and self.mode is Mode.MISSION:
            ap.executor.enter_item(ap.executor.progress.seq, p)
        else:
            ap.task = Hold(task.target)
            if self.mode is Mode.TAKEOFF:
                self.switch(Mode.LOITER)

    # ------------------------------------------------------------------ commands
    def set_mode(self, mode: Mode) -> Result:
        """A PX4 mode change (DO_SET_MODE, SET_MODE)."""
        ap = self.ap
        if mode is Mode.MISSION and not ap.executor.progress.items:
            return MAV_RESULT_TEMPORARILY_REJECTED, "mission mode denied: no mission"
        if mode in (Mode.RTL, Mode.LAND) and ap.landed:
            return MAV_RESULT_TEMPORARILY_REJECTED, f"{mode.label} denied: landed"
        if mode is Mode.TAKEOFF and not ap.landed:
            return MAV_RESULT_TEMPORARILY_REJECTED, "takeoff mode denied: already flying"
        if mode is self.mode and (mode is not Mode.MISSION or ap.executor.item is not None
                                  or not self.armed):
            return MAV_RESULT_ACCEPTED, ""
        self.enter(mode)
        return MAV_RESULT_ACCEPTED, ""

    def mission_start(self, first: float = 0.0, last: float = 0.0) -> Result:
        """MAV_CMD_MISSION_START (param1 first item; 0 = from the current item)."""
        n = len(self.ap.executor.progress.items)
        if not n:
            return MAV_RESULT_DENIED, "mission start denied: no mission"
        if not (math.isfinite(first) and 0 <= int(first) < n):
            return MAV_RESULT_DENIED, f"mission start denied: no item {first:g}"
        self.ap.executor.rewind(int(first))
        if self.mode is Mode.MISSION:
            self.enter(Mode.MISSION)
            return MAV_RESULT_ACCEPTED, ""
        return self.set_mode(Mode.MISSION)

    def set_current(self, seq: int, reset_jumps: bool = False) -> Result:
        """MISSION_SET_CURRENT / MAV_CMD_DO_SET_MISSION_CURRENT."""
        ex = self.ap.executor
        if not 0 <= seq < len(ex.progress.items):  # FAILED, as MAVLink defines it
            return MAV_RESULT_FAILED, f"set current failed: no item {seq}"
        ex.select(seq, reset_jumps)
        return MAV_RESULT_ACCEPTED, ""

    def pause_continue(self, resume: bool) -> Result:
        """MAV_CMD_DO_PAUSE_CONTINUE: 0 holds, 1 resumes the mission."""
        if not resume:
            return self.set_mode(Mode.LOITER)
        if self.ap.executor.resume_after_pause():  # autocontinue 0: the next item
            return MAV_RESULT_ACCEPTED, ""
        return self.set_mode(Mode.MISSION)

    def change_speed(self, speed_mps: float) -> Result:
        """MAV_CMD_DO_CHANGE_SPEED (param2): -2 (or -1 with nothing set) the default."""
        ap = self.ap
        if speed_mps == -2.0:
            ap.speed_override_mps = None
            return MAV_RESULT_ACCEPTED, ""
        if speed_mps == -1.0:
            return MAV_RESULT_ACCEPTED, ""
        vmax = ap.params["MPC_XY_VEL_MAX"]
        if not math.isfinite(speed_mps) or speed_mps <= 0:
            return MAV_RESULT_DENIED, f"speed {speed_mps:g} m/s refused"
        ap.speed_override_mps = min(speed_mps, vmax)
        return MAV_RESULT_ACCEPTED, ""

    def reposition(self, target: Vec3) -> Result:
        """MAV_CMD_DO_REPOSITION: fly there and hold (AUTO.LOITER)."""
        ap = self.ap
        if not self.armed or ap.landed:
            return MAV_RESULT_TEMPORARILY_REJECTED, "reposition denied: not flying"
        self.enter(Mode.LOITER)
        ap.task = Line(ap.position, target)
        return MAV_RESULT_ACCEPTED, ""

    def set_home(self, geodetic: tuple[float, float, float] | None) -> Result:
        """MAV_CMD_DO_SET_HOME: here (None) or at (lat, lon, alt)."""
        ap = self.ap
        if geodetic is None:
            ap.home = ap.home_here()
        else:
            lat, lon, alt = geodetic
            e, n, u = ap.frame.to_enu(lat, lon, alt)
            ap.home = Home((float(e), float(n), float(u)), lat, lon, alt)
        ap.emit("home")
        return MAV_RESULT_ACCEPTED, ""

    def return_to_launch(self) -> Result:
        return self.set_mode(Mode.RTL)

    def land(self) -> Result:
        return self.set_mode(Mode.LAND)

    def hold(self) -> Result:
        return self.set_mode(Mode.LOITER)

    # ------------------------------------------------------------------ failsafes
    def on_link_lost(self) -> None:
        """The ground station is gone (COM_DL_LOSS_T): NAV_DLL_ACT unless exempt."""
        ap = self.ap
        if not self.armed or ap.landed:
            return
        action = int(ap.params["NAV_DLL_ACT"])
        exempt = int(ap.params["COM_DLL_EXCEPT"])
        if self.mode is Mode.MISSION and exempt & 1:
            ap.text(MAV_SEVERITY_WARNING, "ground station lost: mission continues")
            return
        if self.mode in (Mode.LOITER, Mode.POSCTL) and exempt & 2:
            ap.text(MAV_SEVERITY_WARNING, "ground station lost: holding")
            return
        ap.text(MAV_SEVERITY_CRITICAL, "ground station lost: failsafe")
        if action == 1:
            self.enter(Mode.LOITER)
        elif action == 2 and self.mode is not Mode.RTL:
            self.enter(Mode.RTL)
        elif action == 3 and self.mode is not Mode.LAND:
            self.enter(Mode.LAND)
