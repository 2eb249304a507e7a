"""Helpers for the vehicle tests: an autopilot on a seeded world, missions in ENU."""

from __future__ import annotations

import math
from dataclasses import dataclass

from envs.vehicle.autopilot import Autopilot
from envs.vehicle.params import Params
from envs.vehicle.px4 import Mode
from planner.mavlink_wire import WireItem
from planner.mission import (
    MAV_CMD_NAV_WAYPOINT,
    MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
    MAV_MISSION_TYPE_MISSION,
    deg_to_e7,
)
from sim import Stepper, load_scenario, realise


def make_autopilot(scenario: str = "three-aps", seed: int = 0,
                   params: dict[str, float] | None = None) -> Autopilot:
    sc = load_scenario(scenario)
    ap = Autopilot(Stepper(realise(sc, seed), agents=sc.agents[:1]), wall_clock=lambda: 0.0)
    for k, v in (params or {}).items():
        assert ap.params.set(k, v) is None
    return ap


def item(ap: Autopilot, command: int = MAV_CMD_NAV_WAYPOINT, e: float | None = None,
         n: float | None = None, alt: float = 0.0, *,
         frame: int = MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, p1: float = 0.0, p2: float = 0.0,
         p3: float = 0.0, p4: float = math.nan,
         autocontinue: int = 1, mission_type: int = MAV_MISSION_TYPE_MISSION) -> WireItem:
    """An item at (e, n) metres east/north of home (None: no position), ``alt`` in
    ``frame``; seq is set by :func:`numbered`."""
    x = y = 0
    if e is not None and n is not None:
        h = ap.home
        lat, lon, _ = ap.frame.to_geodetic(h.enu[0] + e, h.enu[1] + n, h.enu[2])
        x, y = deg_to_e7(float(lat)), deg_to_e7(float(lon))
    return WireItem(seq=0, frame=frame, command=command, current=0, autocontinue=autocontinue,
                    param1=p1, param2=p2, param3=p3, param4=p4, x=x, y=y, z=alt,
                    mission_type=mission_type)


def numbered(items: list[WireItem]) -> list[WireItem]:
    from dataclasses import replace

    return [replace(w, seq=k, current=int(k == 0)) for k, w in enumerate(items)]


@dataclass
class Sample:
    t_s: float
    pos: tuple[float, float, float]  # navigation position, ENU relative to home
    truth: tuple[float, float, float]  # controller state (true position), world ENU
    speed_h: float
    vz: float
    mode: Mode
    armed: bool
    landed_state: int


def fly(ap: Autopilot, seconds: float, dt: float = 0.25, until=None) -> list[Sample]:
    """Step ``ap`` for up to ``seconds`` (stop early when ``until(ap)``)."""
    out: list[Sample] = []
    t_end = ap.vehicle.t_s + seconds
    h = ap.home.enu
    while ap.vehicle.t_s < t_end - 1e-9:
        ap.step_to(ap.vehicle.t_s + dt)
        p = ap.position
        st = ap.vehicle.state
        v = st.velocity_mps
        out.append(Sample(ap.vehicle.t_s, (p[0] - h[0], p[1] - h[1], p[2] - h[2]),
                          st.position_m, math.hypot(v[0], v[1]), v[2], ap.mode, ap.armed,
                          ap.landed_state))
        if until is not None and until(ap):
            break
    return out


def true_agl(ap: Autopilot, s: Sample) -> float:
    x, y, z = s.truth
    return z - float(ap.world.ground_m(x, y))


__all__ = ["Params", "Sample", "fly", "item", "make_autopilot", "numbered", "true_agl"]


# ---------------------------------------------------------------- MAVLink ground station

SEARCH_SCENARIO = str(__import__("pathlib").Path(__file__).parent / "data" / "search-ap1f.toml")


class Gcs:
    """A pymavlink ground station (system 255/190 unless told) with bounded waits."""

    def __init__(self, url: str, timeout_s: float = 5.0, source_system: int = 255) -> None:
        import time

        from planner.mavlink import mavutil

        self.mavlink = mavutil.mavlink
        self.conn = mavutil.mavlink_connection(url, source_system=source_system,
                                               source_component=190)
        self._hb = 0.0
        self.messages: list = []
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            self.heartbeat(force=True)
            m = self.conn.recv_match(type="HEARTBEAT", blocking=True, timeout=0.3)
            if m is not None and m.get_srcSystem() == 1:
                self.vehicle_heartbeat = m
                return
        raise TimeoutError(f"no vehicle heartbeat on {url}")

    def heartbeat(self, force: bool = False) -> None:
        import time

        now = time.monotonic()
        if force or now - self._hb > 0.5:
            self._hb = now
            self.conn.mav.heartbeat_send(6, 8, 0, 0, 0)

    def recv(self, timeout_s: float = 0.2):
        self.heartbeat()
        m = self.conn.recv_match(blocking=True, timeout=timeout_s)
        if m is not None and m.get_type() != "BAD_DATA":
            self.messages.append(m)
            return m
        return None

    def wait(self, types, timeout_s: float = 5.0, where=None):
        """The next message of ``types`` (matching ``where``) within ``timeout_s``."""
        import time

        types = {types} if isinstance(types, str) else set(types)
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            m = self.recv(min(0.2, max(deadline - time.monotonic(), 0.01)))
            if m is not None and m.get_type() in types and (where is None or where(m)):
                return m
        raise TimeoutError(f"no {sorted(types)} within {timeout_s:g} s")

    def command(self, cmd: int, *params: float, timeout_s: float = 3.0) -> int:
        p = [float(x) for x in params] + [0.0] * (7 - len(params))
        self.conn.mav.command_long_send(1, 1, cmd, 0, *p)
        ack = self.wait("COMMAND_ACK", timeout_s, where=lambda m: m.command == cmd)
        return int(ack.result)

    def collect(self, seconds: float, until=None) -> list:
        """All messages for ``seconds`` of wall time (or until ``until(msg)``)."""
        import time

        out = []
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            m = self.recv(0.1)
            if m is None:
                continue
            out.append(m)
            if until is not None and until(m):
                break
        return out

    def close(self) -> None:
        self.conn.close()


def free_tcp_port(host: str = "127.0.0.1") -> int:
    """A TCP port that was free a moment ago (the OS picks it)."""
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def until(pred, timeout_s: float, step_s: float = 0.05) -> bool:
    """Wait (bounded) until ``pred()``; its last value."""
    import time

    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(step_s)
    return bool(pred())
