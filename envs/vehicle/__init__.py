"""A simulated PX4 multicopter on MAVLink: the scenario's world behind an autopilot.

``osa vehicle`` (envs/commands/vehicle.py) runs :class:`VirtualVehicle`; docs/vehicle.md
describes what it answers and how it flies. Modules: :mod:`.px4` (modes and codes),
:mod:`.params`, :mod:`.flight` (flight tasks), :mod:`.autopilot` (the guidance: shared
state, terrain clearance, landing) with its parts :mod:`.modes` (modes, arming,
commands, link loss), :mod:`.executor` (the mission flown), :mod:`.geofence` (zones,
keep-outs and breach actions), :mod:`.rtl` (return, rally points) and :mod:`.terrain`
(the terrain database and protocol); :mod:`.mission` (what
storage accepts), :mod:`.protocol` (mission protocol server), :mod:`.telemetry`,
:mod:`.links` (the MAVLink ports and the ground stations on them), :mod:`.server`
(the loop).
"""

from envs.vehicle.autopilot import Autopilot
from envs.vehicle.links import ConnectionURLError, vehicle_url
from envs.vehicle.params import Params
from envs.vehicle.px4 import Mode
from envs.vehicle.server import VirtualVehicle

__all__ = ["Autopilot", "ConnectionURLError", "Mode", "Params", "VirtualVehicle", "vehicle_url"]
