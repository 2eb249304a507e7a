"""PX4's identity on MAVLink: custom flight modes and the heartbeat's mode fields.

PX4 packs its flight mode into HEARTBEAT ``custom_mode`` as
``(sub_mode << 24) | (main_mode << 16)`` (px4_custom_mode.h); ``base_mode`` carries
MAV_MODE_FLAG_CUSTOM_MODE_ENABLED plus the armed and auto/guided flags. Only the
modes this vehicle flies are named in :data:`SUPPORTED_MODES`; the others decode
(for messages and refusals) but are refused.
"""

from __future__ import annotations

from enum import Enum

from pymavlink.dialects.v20.common import (
    MAV_MODE_FLAG_AUTO_ENABLED,
    MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
    MAV_MODE_FLAG_GUIDED_ENABLED,
    MAV_MODE_FLAG_MANUAL_INPUT_ENABLED,
    MAV_MODE_FLAG_SAFETY_ARMED,
    MAV_MODE_FLAG_STABILIZE_ENABLED,
)

# MAVLink's numbers are pymavlink's (the common dialect); PX4's custom modes have no
# MAVLink enum and are defined here
FORCE_DISARM_MAGIC = 21196  # MAV_CMD_COMPONENT_ARM_DISARM param2: force (MAVLink spec)

# PX4 main modes (px4_custom_mode.h)
MAIN_MANUAL, MAIN_ALTCTL, MAIN_POSCTL, MAIN_AUTO, MAIN_ACRO, MAIN_OFFBOARD = 1, 2, 3, 4, 5, 6
MAIN_STABILIZED, MAIN_RATTITUDE = 7, 8
# PX4 AUTO sub modes
SUB_AUTO_READY, SUB_AUTO_TAKEOFF, SUB_AUTO_LOITER, SUB_AUTO_MISSION = 1, 2, 3, 4
SUB_AUTO_RTL, SUB_AUTO_LAND = 5, 6
SUB_AUTO_FOLLOW_TARGET, SUB_AUTO_PRECLAND = 8, 9


class Mode(Enum):
    """The flight modes this vehicle flies (value: (main mode, sub mode))."""

    POSCTL = (MAIN_POSCTL, 0)  # no sticks: holds position
    TAKEOFF = (MAIN_AUTO, SUB_AUTO_TAKEOFF)
    LOITER = (MAIN_AUTO, SUB_AUTO_LOITER)  # QGroundControl's and MAVSDK's "Hold"
    MISSION = (MAIN_AUTO, SUB_AUTO_MISSION)
    RTL = (MAIN_AUTO, SUB_AUTO_RTL)
    LAND = (MAIN_AUTO, SUB_AUTO_LAND)

    @property
    def custom_mode(self) -> int:
        main, sub = self.value
        return (sub << 24) | (main << 16)

    @property
    def label(self) -> str:
        return "POSCTL" if self is Mode.POSCTL else f"AUTO.{self.name}"

    @property
    def is_auto(self) -> bool:
        return self.value[0] == MAIN_AUTO


SUPPORTED_MODES = {m.value: m for m in Mode}
_MAIN_NAMES = {1: "MANUAL", 2: "ALTCTL", 3: "POSCTL", 4: "AUTO", 5: "ACRO", 6: "OFFBOARD",
               7: "STABILIZED", 8: "RATTITUDE"}
_AUTO_NAMES = {1: "READY", 2: "TAKEOFF", 3: "LOITER", 4: "MISSION", 5: "RTL", 6: "LAND",
               8: "FOLLOW_TARGET", 9: "PRECLAND"}


def decode_custom_mode(custom_mode: int) -> tuple[int, int]:
    """(main mode, sub mode) of a PX4 ``custom_mode``."""
    return (int(custom_mode) >> 16) & 0xFF, (int(custom_mode) >> 24) & 0xFF


def mode_from_main_sub(main: int, sub: int) -> Mode | None:
    """The supported mode for PX4 (main, sub); POSCTL ignores its sub mode (ORBIT = 1
    is refused); None for anything else."""
    if main == MAIN_POSCTL:
        return Mode.POSCTL if sub == 0 else None
    return SUPPORTED_MODES.get((main, sub))


def mode_name(main: int, sub: int) -> str:
    """A readable PX4 mode name, also for modes we refuse."""
    name = _MAIN_NAMES.get(main, f"main mode {main}")
    if main == MAIN_AUTO:
        return f"AUTO.{_AUTO_NAMES.get(sub, sub)}"
    return name


def base_mode(mode: Mode, armed: bool) -> int:
    """HEARTBEAT ``base_mode`` as PX4 fills it for ``mode``."""
    flags = MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | MAV_MODE_FLAG_STABILIZE_ENABLED
    if mode.is_auto:
        flags |= MAV_MODE_FLAG_AUTO_ENABLED | MAV_MODE_FLAG_GUIDED_ENABLED
    else:
        flags |= MAV_MODE_FLAG_MANUAL_INPUT_ENABLED | MAV_MODE_FLAG_GUIDED_ENABLED
    if armed:
        flags |= MAV_MODE_FLAG_SAFETY_ARMED
    return flags
