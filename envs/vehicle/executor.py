"""The mission executor: which item is flown, how, and when it is reached (PX4 rules).

:class:`MissionExecutor` holds the mission the vehicle flies (:class:`MissionProgress`)
and the item being flown, and turns items into flight tasks on the autopilot:

- NAV_WAYPOINT: a straight line at the cruise speed, reached within param2 (else
  NAV_ACC_RAD) horizontally and NAV_MC_ALT_RAD vertically, braking for corners and
  stops (:func:`envs.vehicle.flight.corner_speed`), hold param1 seconds, then
  MISSION_ITEM_REACHED; autocontinue 0 pauses at the item;
- NAV_TAKEOFF on the ground: the mode machine's vertical climb, then to its position
  if it has one; in the air a waypoint;
- NAV_LAND: fly to its position (none: here), descend, touch down, disarm;
- NAV_RETURN_TO_LAUNCH: reached, then AUTO.RTL;
- NAV_LOITER_TIME (hover param1 s), NAV_LOITER_TURNS (param1 turns of radius |param3|,
  clockwise for param3 > 0), NAV_LOITER_UNLIM (hover, never reached), NAV_DELAY
  (hover param1 s); DO_JUMP (param1 target, param2 repeats, negative: forever; never
  the current item), DO_CHANGE_SPEED (param2 m/s; -2 the default); payload commands
  are reached at once;
- items above the terrain (MAV_FRAME_GLOBAL_TERRAIN_ALT(_INT)) are flown at their
  height above the terrain database's ground, also along the leg into them: the height
  above the ground goes linearly from the leg's start to the item's
  (:class:`envs.vehicle.flight.TerrainLine`; a loiter circle follows the ground too, a
  landing's approach keeps its height above it);
- the end of the mission in the air switches to AUTO.LOITER; after landing a
  finished mission starts over from item 0.

The executor records the last :data:`HISTORY` items reached (``reached_log``) and
emits the ``current`` and ``reached`` events the MAVLink side publishes. Mode changes go through the
autopilot's mode machine (:mod:`envs.vehicle.modes`).
"""

from __future__ import annotations

import collections
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from pymavlink.dialects.v20.common import (
    MAV_CMD_DO_JUMP,
    MAV_CMD_NAV_DELAY,
    MAV_CMD_NAV_LOITER_TIME,
    MAV_CMD_NAV_LOITER_TURNS,
    MAV_CMD_NAV_LOITER_UNLIM,
    MAV_SEVERITY_INFO,
    MISSION_STATE_ACTIVE,
    MISSION_STATE_COMPLETE,
    MISSION_STATE_NO_MISSION,
    MISSION_STATE_NOT_STARTED,
    MISSION_STATE_PAUSED,
)

from envs.vehicle.flight import (
    TERRAIN_CLEARANCE_M,
    Hold,
    Line,
    Orbit,
    TerrainLine,
    Vec3,
    corner_speed,
)
from envs.vehicle.mission import IGNORED_COMMANDS, TERRAIN_FRAMES
from envs.vehicle.px4 import Mode
from planner.mavlink_wire import WireItem
from planner.mission import (
    MAV_CMD_DO_CHANGE_SPEED,
    MAV_CMD_NAV_LAND,
    MAV_CMD_NAV_RETURN_TO_LAUNCH,
    MAV_CMD_NAV_TAKEOFF,
    MAV_CMD_NAV_WAYPOINT,
)

if TYPE_CHECKING:
    from envs.vehicle.autopilot import Autopilot

HISTORY = 10_000  # items reached and mission changes remembered (the last ones)


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
class FlownItem:
    """The mission item being flown: its phase (``fly``, ``climb``, ``hold``,
    ``loiter``, ``orbit``, ``land``, ``paused``) and target."""

    seq: int
    item: WireItem
    phase: str
    target: Vec3 | None = None
    until_s: float = math.inf
    radius_m: float = 0.0


class MissionExecutor:
    """See the module docstring; ``ap`` is the autopilot it flies."""

    def __init__(self, ap: Autopilot) -> None:
        self.ap = ap
        self.progress = MissionProgress()
        self.item: FlownItem | None = None
        # (seq, t_s, position) of the last HISTORY items reached; the simulated times
        # of the last HISTORY mission changes (a patrol looping for ever grows nothing)
        self.reached_log: collections.deque[tuple[int, float, Vec3]] = collections.deque(
            maxlen=HISTORY)
        self.mission_set_at: collections.deque[float] = collections.deque(maxlen=HISTORY)

    # ------------------------------------------------------------------ reports
    def mission_current(self) -> tuple[int, int, int]:
        """(seq, total, MISSION_STATE) for MISSION_CURRENT."""
        m = self.progress
        return m.seq, len(m.items), m.state

    def emit_current(self) -> None:
        self.ap.emit("current", *self.mission_current())

    def reached(self, seq: int) -> None:
        ap = self.ap
        self.reached_log.append((seq, ap.t_s, ap.position))
        ap.emit("reached", seq)

    def acceptance_m(self, w: WireItem) -> float:
        return w.param2 if w.command == MAV_CMD_NAV_WAYPOINT and w.param2 > 0 \
            else self.ap.params["NAV_ACC_RAD"]

    def flying(self) -> bool:
        """In AUTO.MISSION, armed, in the air and past any take-off climb."""
        ap = self.ap
        return ap.mode is Mode.MISSION and ap.armed and not ap.landed \
            and ap.modes.takeoff_then is None

    # ------------------------------------------------------------------ storage
    def set_mission(self, items: Sequence[WireItem], current: int = 0) -> None:
        """A complete, validated mission upload: it replaces the held one at once; a
        mission being flown switches to it from where the vehicle is."""
        ap = self.ap
        n = len(items)
        self.mission_set_at.append(ap.t_s)
        flying = self.flying()
        self.progress = MissionProgress(items=list(items),
                                        seq=current if 0 <= current < n else 0)
        self.item = None
        self.emit_current()
        if not n:
            if flying:
                ap.modes.switch(Mode.LOITER)
                ap.hold_here()
            return
        if flying:
            self.progress.started = True
            self.enter_item(self.progress.seq, ap.position)

    def restart(self) -> None:
        """Back to item 0, not started (a flown mission after landing; PX4)."""
        m = self.progress
        m.complete = m.started = m.paused = False
        m.seq = 0
        m.jumps.clear()
        self.emit_current()

    def rewind(self, seq: int) -> None:
        """MISSION_START: from item ``seq``, DO_JUMP counters reset."""
        m = self.progress
        m.seq = seq
        m.complete = m.paused = m.started = False
        m.jumps.clear()
        self.item = None
        self.emit_current()

    def select(self, seq: int, reset_jumps: bool) -> None:
        """MISSION_SET_CURRENT: ``seq`` is current (flown at once when flying)."""
        m = self.progress
        m.seq = seq
        m.complete = False
        m.paused = False
        if reset_jumps:
            m.jumps.clear()
        self.emit_current()
        if self.flying():
            self.enter_item(seq, self.ap.position)

    def pause(self) -> None:
        m = self.progress
        if m.started and not m.complete and not m.paused:
            m.paused = True
            self.emit_current()

    def resume_after_pause(self) -> bool:
        """DO_PAUSE_CONTINUE 1 after an item with autocontinue 0: the next item."""
        m = self.progress
        if m.paused and self.item is not None:
            m.paused = False
            seq = self.item.seq
            tgt = self.item.target or self.ap.position
            self.enter_item(seq + 1, tgt)
            return True
        return False

    # ------------------------------------------------------------------ flying
    def begin(self) -> None:
        """Fly the mission from its current item (AUTO.MISSION entered)."""
        ap = self.ap
        m = self.progress
        if m.complete:
            if ap.landed:
                self.restart()
            else:
                ap.modes.switch(Mode.LOITER)
                ap.hold_here()
                return
        m.started = True
        m.paused = False
        self.emit_current()
        ap.modes.switch(Mode.MISSION)
        if ap.landed:
            first = self.resolve(m.seq, count=False)
            w = m.items[first] if first is not None else None
            if w is not None and w.command == MAV_CMD_NAV_TAKEOFF:
                self.enter_item(m.seq, ap.position)
            else:
                ap.modes.takeoff_climb(ap.params["MIS_TAKEOFF_ALT"], then="mission")
            return
        self.enter_item(m.seq, ap.position)

    def resolve(self, seq: int, *, count: bool) -> int | None:
        """The first item to fly from ``seq`` following DO_JUMPs (counting them when
        ``count``); None past the end."""
        items = self.progress.items
        jumps = self.progress.jumps if count else dict(self.progress.jumps)
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

    def _set_seq(self, seq: int) -> None:
        if self.progress.seq != seq:
            self.progress.seq = seq
        self.emit_current()

    def enter_item(self, seq: int, leg_start: Vec3) -> None:
        """Start flying the mission from item ``seq`` (instant items are done here)."""
        items = self.progress.items
        for _ in range(4 * len(items) + 8):
            k = self.resolve(seq, count=True)
            if k is None:
                self.complete(landed=False)
                return
            w = items[k]
            self._set_seq(k)
            if w.command == MAV_CMD_DO_CHANGE_SPEED:
                if w.param1 in (0.0, 1.0) or not math.isfinite(w.param1):
                    self.ap.change_speed(float(w.param2))
                self.reached(k)
                seq = k + 1
                continue
            if w.command in IGNORED_COMMANDS:
                self.reached(k)
                seq = k + 1
                continue
            break
        else:
            self.complete(landed=False)
            return
        self._start_item(k, w, leg_start)

    def _start_item(self, seq: int, w: WireItem, leg_start: Vec3) -> None:
        ap = self.ap
        p = ap.position
        cmd = w.command
        it = FlownItem(seq, w, "fly")
        self.item = it
        if cmd == MAV_CMD_NAV_RETURN_TO_LAUNCH:
            self.reached(seq)
            self.item = None
            self.complete(landed=False, then_rtl=True)
            return
        if cmd == MAV_CMD_NAV_DELAY:
            it.phase = "hold"
            it.target = p
            it.until_s = ap.t_s + max(w.param1, 0.0)
            ap.task = Hold(p)
            return
        target = ap.item_position(w)
        it.target = target
        it.radius_m = self.acceptance_m(w)
        if cmd == MAV_CMD_NAV_TAKEOFF and ap.landed:
            it.phase = "climb"
            ap.modes.climb_to(max(target[2], ap.home.enu[2] + 1.0), then="item")
            return
        terrain = w.frame in TERRAIN_FRAMES
        if cmd == MAV_CMD_NAV_LAND:
            if math.hypot(target[0] - p[0], target[1] - p[1]) <= it.radius_m:
                it.target = (target[0], target[1], p[2])
                it.phase = "land"
                ap.land_at(target[0], target[1])
                return
            if terrain:  # the approach keeps its height above the ground
                agl = ap.agl_m(p)
                it.target = (target[0], target[1], ap.ground_m(target[0], target[1]) + agl)
                ap.task = TerrainLine((leg_start[0], leg_start[1], p[2]), it.target, agl, agl)
                return
            it.target = (target[0], target[1], p[2])
            ap.task = Line((leg_start[0], leg_start[1], p[2]), it.target)
            return
        if cmd == MAV_CMD_NAV_LOITER_TURNS:
            radius = abs(w.param3) if math.isfinite(w.param3) else 0.0
            if radius > 0:
                dx, dy = p[0] - target[0], p[1] - target[1]
                d = math.hypot(dx, dy)
                ux, uy = (dx / d, dy / d) if d > 1e-3 else (1.0, 0.0)
                e, n = target[0] + radius * ux, target[1] + radius * uy
                it.target = (e, n, ap.ground_m(e, n) + w.z if terrain else target[2])
        end = 0.0
        if cmd == MAV_CMD_NAV_WAYPOINT and w.param1 <= 0 and w.autocontinue:
            end = self._corner_after(seq, leg_start, it.target, it.radius_m)
        if terrain:
            ap.task = TerrainLine(leg_start, it.target, ap.agl_m(leg_start), float(w.z),
                                  end_speed_mps=end, end_at_m=it.radius_m)
            return
        ap.task = Line(leg_start, it.target, end_speed_mps=end, end_at_m=it.radius_m)

    def _corner_after(self, seq: int, start: Vec3, target: Vec3, radius: float) -> float:
        nxt = self.resolve(seq + 1, count=False)
        items = self.progress.items
        while nxt is not None and (items[nxt].command == MAV_CMD_DO_CHANGE_SPEED
                                   or items[nxt].command in IGNORED_COMMANDS):
            nxt = self.resolve(nxt + 1, count=False)
        if nxt is None:
            return 0.0
        w = items[nxt]
        if w.command != MAV_CMD_NAV_WAYPOINT or w.param1 > 0:
            return 0.0
        t2 = self.ap.item_position(w, here=target)
        a = (target[0] - start[0], target[1] - start[1])
        b = (t2[0] - target[0], t2[1] - target[1])
        la, lb = math.hypot(*a), math.hypot(*b)
        if la < 1e-3 or lb < 1e-3:
            return 0.0
        lim = self.ap.limits
        v = corner_speed((a[0] / la, a[1] / la), (b[0] / lb, b[1] / lb), radius, lim,
                         lim.cruise_mps)
        # the next leg must be long enough to brake to a stop at its own end
        return min(v, math.sqrt(2.0 * lim.brake_mps2 * lb))

    def tick(self, p: Vec3) -> None:
        """One 20 Hz tick in AUTO.MISSION: judge the item being flown."""
        ap = self.ap
        it = self.item
        assert it is not None
        w = it.item
        alt_rad = ap.params["NAV_MC_ALT_RAD"]
        if it.phase == "climb":  # the take-off item's climb is the mode machine's
            return
        if it.phase == "fly":
            t = it.target
            assert t is not None
            h = math.hypot(t[0] - p[0], t[1] - p[1])
            if h > it.radius_m:
                return
            if abs(t[2] - p[2]) > alt_rad and not (
                    t[2] < p[2] and ap.true_agl_m(p) <= TERRAIN_CLEARANCE_M + alt_rad):
                return  # (a target below the terrain clearance counts as reached above it)
            cmd = w.command
            if cmd == MAV_CMD_NAV_LAND:
                it.phase = "land"
                ap.land_at(t[0], t[1])
                return
            if cmd == MAV_CMD_NAV_LOITER_UNLIM:
                it.phase = "loiter"
                ap.task = Hold(t)
                return
            if cmd == MAV_CMD_NAV_LOITER_TURNS:
                radius = abs(w.param3) if math.isfinite(w.param3) else 0.0
                if radius > 0 and w.param1 > 0:
                    c = ap.item_position(w)
                    it.phase = "orbit"
                    ap.task = Orbit((c[0], c[1]), radius, t[2],
                                    -1 if w.param3 > 0 else 1, w.param1,
                                    agl_m=float(w.z) if w.frame in TERRAIN_FRAMES else None)
                    return
            hold_s = w.param1 if cmd in (MAV_CMD_NAV_WAYPOINT, MAV_CMD_NAV_LOITER_TIME) else 0.0
            if hold_s > 0:
                it.phase = "hold"
                it.until_s = ap.t_s + hold_s
                ap.task = Hold(t)
                return
            self.item_done(it, t)
            return
        if it.phase == "hold" and ap.t_s >= it.until_s:
            self.item_done(it, it.target or p)
        elif it.phase == "orbit" and ap.task.done:
            self.item_done(it, p)

    def item_done(self, it: FlownItem, leg_end: Vec3) -> None:
        self.reached(it.seq)
        if not it.item.autocontinue:
            self.progress.paused = True
            it.phase = "paused"
            self.ap.task = Hold(leg_end)
            self.emit_current()
            return
        self.enter_item(it.seq + 1, leg_end)

    def climbed(self, p: Vec3) -> None:
        """The take-off item's climb is over at ``p``: on to its position, or done."""
        it = self.item
        assert it is not None
        t = it.target or p
        w = it.item
        if (w.x or w.y) and math.hypot(t[0] - p[0], t[1] - p[1]) > it.radius_m:
            it.phase = "fly"
            if w.frame in TERRAIN_FRAMES:
                self.ap.task = TerrainLine(p, t, self.ap.agl_m(p), float(w.z))
            else:
                self.ap.task = Line(p, t)
        else:
            self.item_done(it, p)

    def on_touchdown(self) -> None:
        """The land detector felt the ground: a NAV_LAND item is reached."""
        if self.item is not None and self.item.item.command == MAV_CMD_NAV_LAND:
            self.reached(self.item.seq)
            self.item = None
            self.complete(landed=True)

    def complete(self, *, landed: bool, then_rtl: bool = False) -> None:
        ap = self.ap
        m = self.progress
        m.complete = True
        m.started = False
        self.item = None
        self.emit_current()
        ap.text(MAV_SEVERITY_INFO, "mission finished")
        if then_rtl:
            ap.modes.enter(Mode.RTL)
        elif not landed and not ap.landed:
            ap.modes.switch(Mode.LOITER)
            ap.hold_here()
