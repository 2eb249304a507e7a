"""The autopilot's parameters: PX4 names, PX4 defaults unless a comment says otherwise.

They are served over the MAVLink parameter protocol (PARAM_REQUEST_LIST,
PARAM_REQUEST_READ, PARAM_SET; integers bytewise-encoded, as PX4 does), so
QGroundControl and MAVSDK (``Action.set_takeoff_altitude`` sets MIS_TAKEOFF_ALT,
``get_return_to_launch_altitude`` reads RTL_RETURN_ALT) read and change them. Speeds
and limits follow the scenario's vehicle (``[vehicle]``) and search speed.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass

from pymavlink.dialects.v20.common import (
    MAV_PARAM_TYPE_INT8,
    MAV_PARAM_TYPE_INT16,
    MAV_PARAM_TYPE_INT32,
    MAV_PARAM_TYPE_REAL32,
    MAV_PARAM_TYPE_UINT8,
    MAV_PARAM_TYPE_UINT16,
    MAV_PARAM_TYPE_UINT32,
)

_INT32_OR_NARROWER = (MAV_PARAM_TYPE_UINT8, MAV_PARAM_TYPE_INT8, MAV_PARAM_TYPE_UINT16,
                      MAV_PARAM_TYPE_INT16, MAV_PARAM_TYPE_UINT32, MAV_PARAM_TYPE_INT32)


@dataclass(frozen=True)
class ParamSpec:
    name: str
    default: float
    kind: int  # MAV_PARAM_TYPE_INT32 | MAV_PARAM_TYPE_REAL32
    lo: float
    hi: float
    doc: str


def _specs(cruise_mps: float, max_speed_mps: float, max_up_mps: float) -> tuple[ParamSpec, ...]:
    r, i = MAV_PARAM_TYPE_REAL32, MAV_PARAM_TYPE_INT32
    return (
        # PX4's NAV_ACC_RAD default is 10 m; 2 m keeps a decimated plan's geometry
        ParamSpec("NAV_ACC_RAD", 2.0, r, 0.05, 200.0, "waypoint acceptance radius (m) "
                  "when the item's param2 is 0"),
        ParamSpec("NAV_MC_ALT_RAD", 0.8, r, 0.05, 10.0, "altitude acceptance (m)"),
        ParamSpec("MIS_TAKEOFF_ALT", 2.5, r, 0.0, 500.0, "take-off altitude above home (m) "
                  "of MAV_CMD_NAV_TAKEOFF without an altitude and of a mission started on "
                  "the ground without a take-off item"),
        # PX4: 5 m/s; here the scenario's [search] speed_mps when it has one
        ParamSpec("MPC_XY_CRUISE", cruise_mps, r, 0.5, max_speed_mps, "cruise speed (m/s)"),
        ParamSpec("MPC_XY_VEL_MAX", max_speed_mps, r, 0.5, max_speed_mps,
                  "largest speed DO_CHANGE_SPEED may set (m/s)"),
        ParamSpec("MPC_Z_VEL_MAX_UP", max_up_mps, r, 0.5, max_up_mps, "climb speed (m/s)"),
        ParamSpec("MPC_Z_V_AUTO_DN", min(1.5, max_up_mps), r, 0.3, max_up_mps,
                  "descent speed in auto modes (m/s)"),
        ParamSpec("MPC_TKO_SPEED", min(1.5, max_up_mps), r, 0.3, max_up_mps,
                  "take-off climb speed (m/s)"),
        ParamSpec("MPC_LAND_SPEED", 0.7, r, 0.2, 3.0, "landing speed below MPC_LAND_ALT2 (m/s)"),
        ParamSpec("MPC_LAND_ALT1", 10.0, r, 0.0, 122.0, "height above ground where the "
                  "descent starts slowing down (m)"),
        ParamSpec("MPC_LAND_ALT2", 5.0, r, 0.0, 122.0, "height above ground below which "
                  "the landing speed applies (m)"),
        ParamSpec("RTL_RETURN_ALT", 60.0, r, 0.0, 1000.0, "return altitude above home (m)"),
        ParamSpec("RTL_DESCEND_ALT", 30.0, r, 2.0, 500.0, "altitude above the landing point "
                  "at which the return descends before landing (m)"),
        ParamSpec("RTL_LAND_DELAY", 0.0, r, -1.0, 300.0, "hover at RTL_DESCEND_ALT before "
                  "landing (s); -1: hover until told otherwise"),
        ParamSpec("COM_DISARM_LAND", 2.0, r, -1.0, 20.0, "disarm this long after landing "
                  "(s, simulated time); -1: never"),
        ParamSpec("COM_DISARM_PRFLT", 10.0, r, -1.0, 600.0, "disarm when armed on the "
                  "ground without taking off for this long (s, wall clock); -1: never"),
        ParamSpec("COM_DL_LOSS_T", 10.0, r, 0.5, 300.0, "ground-station link lost after "
                  "this long without a message (s, wall clock)"),
        # PX4's default is 0 (disabled); here: return, with the mission exception set
        ParamSpec("NAV_DLL_ACT", 2.0, i, 0.0, 3.0, "link-loss action: 0 none, 1 hold, "
                  "2 return, 3 land"),
        ParamSpec("COM_DLL_EXCEPT", 1.0, i, 0.0, 7.0, "modes exempt from the link-loss "
                  "action, bits: 1 mission, 2 hold"),
        ParamSpec("GF_ACTION", 2.0, i, 0.0, 5.0, "geofence breach action: 0 none, 1 warning, "
                  "2 hold, 3 return, 5 land"),
        ParamSpec("GF_PREDICT", 1.0, i, 0.0, 1.0, "1: act on the stopping point (predicted "
                  "breach), 0: on the position"),
    )


class Params:
    """Named parameter values (an ordered table, indexable as PARAM_VALUE needs)."""

    def __init__(self, cruise_mps: float = 5.0, max_speed_mps: float = 15.0,
                 max_up_mps: float = 3.0) -> None:
        self.specs = _specs(cruise_mps, max_speed_mps, max_up_mps)
        self._index = {s.name: k for k, s in enumerate(self.specs)}
        self.values = {s.name: float(s.default) for s in self.specs}
        self.version = 0  # bumped on every change (the autopilot caches what it derives)

    def __getitem__(self, name: str) -> float:
        return self.values[name]

    def __len__(self) -> int:
        return len(self.specs)

    def index(self, name: str) -> int | None:
        return self._index.get(name)

    def set(self, name: str, value: float) -> str | None:
        """Set ``name``; None on success, else the reason it was refused."""
        k = self._index.get(name)
        if k is None:
            return f"unknown parameter {name}"
        s = self.specs[k]
        if not math.isfinite(value) or not s.lo <= value <= s.hi:
            return f"{name} = {value:g} outside [{s.lo:g}, {s.hi:g}]"
        if s.kind == MAV_PARAM_TYPE_INT32:
            value = float(round(value))
        self.values[name] = float(value)
        self.version += 1
        return None

    def wire_value(self, name: str) -> tuple[float, int]:
        """(param_value, param_type) as PX4 sends them: INT32 bytewise in the float."""
        s = self.specs[self._index[name]]
        v = self.values[name]
        if s.kind == MAV_PARAM_TYPE_INT32:
            return struct.unpack("<f", struct.pack("<i", int(v)))[0], s.kind
        return v, s.kind

    @staticmethod
    def from_wire(value: float, kind: int) -> float:
        """A PARAM_SET value: INT32 bytewise-encoded (PX4), REAL32 as is."""
        if kind in _INT32_OR_NARROWER:
            return float(struct.unpack("<i", struct.pack("<f", value))[0])
        return float(value)
