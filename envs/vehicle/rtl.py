"""AUTO.RTL: climb, return to the closest of home and the rally points, descend, land.

PX4's multicopter return: climb to RTL_RETURN_ALT above home (or stay higher), fly to
the closest of home and the rally points (at the rally point's altitude), descend to
RTL_DESCEND_ALT, wait RTL_LAND_DELAY (-1: hover until told otherwise), then land
there (the autopilot's landing: :meth:`envs.vehicle.autopilot.Autopilot.land_at`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

from pymavlink.dialects.v20.common import (
    MAV_SEVERITY_NOTICE,
)

from envs.vehicle.flight import Hold, Line, Vec3
from planner.mavlink_wire import WireItem

if TYPE_CHECKING:
    from envs.vehicle.autopilot import Autopilot


@dataclass
class ReturnLeg:
    """Where a return goes and which phase it is in (climb, return, descend, loiter,
    land)."""

    dest: tuple[float, float]
    return_z: float
    descend_z: float
    phase: str = "climb"
    until_s: float = math.inf


class ReturnToLaunch:
    """The return of AUTO.RTL and the rally points it may go to; ``ap`` the autopilot."""

    def __init__(self, ap: Autopilot) -> None:
        self.ap = ap
        self.leg: ReturnLeg | None = None
        self.rally_items: list[WireItem] = []
        self.rally_enu: list[Vec3] = []

    def set_rally(self, items: Sequence[WireItem]) -> None:
        """A complete, validated rally list (positions resolved now)."""
        self.rally_items = list(items)
        self.rally_enu = [self.ap.item_position(w) for w in items]

    def begin(self) -> None:
        ap = self.ap
        p = ap.position
        home = ap.home.enu
        dest = (home[0], home[1])
        descend = home[2] + ap.params["RTL_DESCEND_ALT"]
        best = math.hypot(dest[0] - p[0], dest[1] - p[1])
        for r in self.rally_enu:
            d = math.hypot(r[0] - p[0], r[1] - p[1])
            if d < best:
                best, dest, descend = d, (r[0], r[1]), r[2]
        ret = max(p[2], home[2] + ap.params["RTL_RETURN_ALT"])
        self.leg = ReturnLeg(dest, ret, min(descend, ret))
        ap.text(MAV_SEVERITY_NOTICE, f"returning: {best:.0f} m to go")
        ap.task = Line(p, (p[0], p[1], ret))

    def tick(self, p: Vec3) -> None:
        ap = self.ap
        r = self.leg
        assert r is not None
        alt_rad = ap.params["NAV_MC_ALT_RAD"]
        task = ap.task
        if r.phase == "climb" and isinstance(task, Line):
            if abs(task.target[2] - p[2]) <= alt_rad:
                r.phase = "return"
                ap.task = Line(p, (r.dest[0], r.dest[1], r.return_z))
        elif r.phase == "return" and isinstance(task, Line):
            if task.distances(p)[0] <= ap.params["NAV_ACC_RAD"] \
                    and task.distances(p)[1] <= alt_rad:
                r.phase = "descend"
                ap.task = Line(p, (r.dest[0], r.dest[1], r.descend_z))
        elif r.phase == "descend" and isinstance(task, Line):
            if task.distances(p)[1] <= alt_rad:
                delay = ap.params["RTL_LAND_DELAY"]
                r.phase = "loiter"
                r.until_s = math.inf if delay < 0 else ap.t_s + delay
                ap.task = Hold((r.dest[0], r.dest[1], r.descend_z))
        elif r.phase == "loiter" and ap.t_s >= r.until_s:
            r.phase = "land"
            ap.land_at(r.dest[0], r.dest[1])
