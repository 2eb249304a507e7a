"""``osa vehicle``'s autopilot (:class:`envs.vehicle.VirtualVehicle`) as a test peer.

:func:`running_vehicle` starts one in a background thread on a free loopback port
(``udpin``) and gives the URLs a ground station uses to reach it.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

from envs.vehicle import ConnectionURLError, VirtualVehicle
from planner.mavlink_wire import WireItem
from planner.mission import MAV_MISSION_TYPE_MISSION
from sim import load_scenario
from tests.net import LOOPBACK, free_udp_port


@dataclass
class RunningVehicle:
    vehicle: VirtualVehicle
    port: int

    @property
    def pymavlink_url(self) -> str:
        return f"udpout:{LOOPBACK}:{self.port}"

    @property
    def mavsdk_url(self) -> str:
        return f"udpout://{LOOPBACK}:{self.port}"

    @property
    def autopilot(self) -> Any:
        return self.vehicle.autopilot

    def held(self, mission_type: int = MAV_MISSION_TYPE_MISSION) -> list[WireItem]:
        return list(self.vehicle.protocol.held[mission_type])

    def upload_count(self, mission_type: int = MAV_MISSION_TYPE_MISSION) -> int:
        return self.vehicle.protocol.commits[mission_type]


@contextlib.contextmanager
def running_vehicle(scenario: str = "three-aps", *, speedup: float = 1.0, seed: int = 0,
                    log_path: Any = None, params: dict[str, float] | None = None,
                    attempts: int = 5, **options: Any) -> Iterator[RunningVehicle]:
    """A started vehicle on ``udpin:127.0.0.1:<free port>``, stopped afterwards."""
    sc = load_scenario(scenario) if isinstance(scenario, str) else scenario
    last: Exception | None = None
    for _ in range(attempts):
        port = free_udp_port()
        try:
            v = VirtualVehicle(sc, [f"udpin:{LOOPBACK}:{port}"], speedup=speedup, seed=seed,
                               log_path=log_path, params=params, **options)
        except ConnectionURLError as exc:  # the port was taken meanwhile
            last = exc
            continue
        v.start()
        try:
            yield RunningVehicle(v, port)
        finally:
            v.stop()
        return
    raise OSError(f"no free port for a vehicle: {last}")
