"""The virtual vehicle's loop: simulated time, MAVLink links, the phone's log.

:class:`VirtualVehicle` realises the scenario's world for a seed
(:func:`sim.realise`), flies its first agent with the :class:`Autopilot` and talks
MAVLink 2 (1 to a ground station that reads only 1) on one or more ports
(:mod:`envs.vehicle.links`: ``udpin:HOST:PORT``: the vehicle listens, each address
that writes is answered on its own; ``udpout:HOST:PORT``: it sends there, as PX4 SITL
to QGroundControl's 14550; ``tcpin:HOST:PORT``: any number of ground stations
connect; ``tcp:HOST:PORT``). Each loop iteration (about 50 per wall second)
it reads every link, advances simulated time to ``speedup`` x the elapsed wall time
in steps of at most ``step_s`` (``speedup=inf``: one step per iteration, as fast as
it can), publishes the autopilot's events and the telemetry streams that are due, and
runs the mission protocol's and the operator timeouts. If the simulation cannot keep
up with the speed-up it says so (``status``) and runs as fast as it can, re-basing its
clock instead of drifting silently. ``--log`` receives the phone's records as they
reach the file (:class:`sim.stepper.LogSink`, flushed): :meth:`VirtualVehicle._on_phone_records`
is the one place the phone's records leave the simulation.

Replies go to the link and system that asked; telemetry to every link, at that link's
rates (MAV_CMD_SET_MESSAGE_INTERVAL sets them for its own link only); a ground
station heard for the first time gets a HEARTBEAT at once (it need not wait a second to
discover the vehicle). Every
COMMAND_LONG and COMMAND_INT is answered with a COMMAND_ACK, malformed ones too (NaN
or out-of-range parameters: DENIED; a command it does not know: UNSUPPORTED; one that
fails: FAILED). Any message from another system keeps the ground-station link alive
(another component of its own system, a companion computer, is answered too but is no
ground station);
after COM_DL_LOSS_T wall seconds of silence the autopilot's link-loss rule applies.
"""

from __future__ import annotations

import collections
import contextlib
import math
import os
import select
import struct
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pymavlink.dialects.v20.common import (
    MAV_CMD_COMPONENT_ARM_DISARM,
    MAV_CMD_DO_CHANGE_SPEED,
    MAV_CMD_DO_PAUSE_CONTINUE,
    MAV_CMD_DO_REPOSITION,
    MAV_CMD_DO_SET_HOME,
    MAV_CMD_DO_SET_MISSION_CURRENT,
    MAV_CMD_DO_SET_MODE,
    MAV_CMD_GET_HOME_POSITION,
    MAV_CMD_GET_MESSAGE_INTERVAL,
    MAV_CMD_MISSION_START,
    MAV_CMD_NAV_LAND,
    MAV_CMD_NAV_RETURN_TO_LAUNCH,
    MAV_CMD_NAV_TAKEOFF,
    MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES,
    MAV_CMD_REQUEST_MESSAGE,
    MAV_CMD_REQUEST_PROTOCOL_VERSION,
    MAV_CMD_SET_MESSAGE_INTERVAL,
    MAV_COMP_ID_MISSIONPLANNER,
    MAV_MODE_FLAG_AUTO_ENABLED,
    MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
    MAV_MODE_FLAG_GUIDED_ENABLED,
    MAV_MODE_FLAG_MANUAL_INPUT_ENABLED,
    MAV_PARAM_TYPE_REAL32,
    MAV_RESULT_ACCEPTED,
    MAV_RESULT_DENIED,
    MAV_RESULT_FAILED,
    MAV_RESULT_UNSUPPORTED,
    MAV_SEVERITY_CRITICAL,
    MAV_SEVERITY_INFO,
    MAV_SEVERITY_WARNING,
    MAVLINK_MSG_ID_AUTOPILOT_VERSION,
    MAVLINK_MSG_ID_EXTENDED_SYS_STATE,
    MAVLINK_MSG_ID_GLOBAL_POSITION_INT,
    MAVLINK_MSG_ID_HOME_POSITION,
    MAVLINK_MSG_ID_MISSION_CURRENT,
)

from envs.phone import PAYLOAD_PACE, PAYLOAD_RESEND
from envs.vehicle.autopilot import Autopilot
from envs.vehicle.links import ConnectionURLError, Links, is_mavlink1
from envs.vehicle.mission import (
    GLOBAL_FRAMES,
    MAX_ALTITUDE_M,
    RELATIVE_FRAMES,
    TERRAIN_FRAMES,
    UNSET_E7,
)
from envs.vehicle.params import Params
from envs.vehicle.protocol import MissionServer, Peer
from envs.vehicle.px4 import (
    FORCE_DISARM_MAGIC,
    Mode,
    decode_custom_mode,
    mode_from_main_sub,
    mode_name,
)
from envs.vehicle.relay import RecordRelay
from envs.vehicle.telemetry import MAVLINK_MSG_ID_PROTOCOL_VERSION, REQUESTABLE, Telemetry
from envs.vehicle.terrain import REQUEST_BLOCKS_E, REQUEST_BLOCKS_N
from estimator.records import GnssFix
from planner.mavlink import mavutil
from planner.mission import MAV_MISSION_TYPE_FENCE, MAV_MISSION_TYPE_MISSION
from sim.realisation import realise
from sim.scenario import KeepOutZone, Scenario
from sim.stepper import Emitted, LogSink, Stepper
from sim.vehicle import FlightError

mavlink = mavutil.mavlink
MAX_PEERS = 1024  # ground stations remembered (to greet a new one with a HEARTBEAT)
# MAVLink FTP (FILE_TRANSFER_PROTOCOL payload): header bytes, response opcodes, the
# error of an operation a server does not support
FTP_HEADER_BYTES, FTP_RSP_ACK, FTP_RSP_NAK, FTP_ERR_UNKNOWN_COMMAND = 12, 128, 129, 7


@dataclass
class Stats:
    """How the loop kept up (wall seconds, simulated seconds)."""

    wall_s: float = 0.0
    sim_s: float = 0.0
    behind_events: int = 0
    steps: int = 0
    received: int = 0
    sent: int = 0

    @property
    def ratio(self) -> float:
        return self.sim_s / self.wall_s if self.wall_s > 0 else 0.0


@dataclass
class _Link:
    last_rx_wall: float = -math.inf
    seen: bool = False
    lost: bool = False
    peers: set[Peer] = field(default_factory=set)  # (link, system, component) heard from


class VirtualVehicle:
    """A simulated PX4 multicopter on MAVLink (see the module docstring).

    ``with VirtualVehicle(scenario, ["udpin:127.0.0.1:14540"], speedup=20) as v:``
    runs it in a background thread (tests, benchmarks); :meth:`run` runs it in the
    calling thread until ``should_stop()`` (the CLI). ``keepouts``
    (:class:`sim.scenario.KeepOutZone`, world ENU metres; None: the scenario's
    ``[[search.keepout]]``) are preloaded into the autopilot's geofence.
    """

    LOOP_PERIOD_S = 0.02
    BEHIND_WALL_S = 1.0  # later than this (wall seconds): cannot keep up
    STEP_WALL_S = 0.1  # wall time one loop iteration may spend stepping

    def __init__(self, scenario: Scenario, connections: Sequence[str], *, seed: int = 0,
                 speedup: float = 1.0, log_path: str | os.PathLike | None = None,
                 params: dict[str, float] | None = None, sysid: int = 1, compid: int = 1,
                 step_s: float | None = None, status: Callable[[str], None] | None = None,
                 transfer_timeout_s: float = 5.0,
                 wall_clock: Callable[[], float] = time.monotonic,
                 keepouts: Sequence[KeepOutZone] | None = None,
                 lockstep_s: float | None = None) -> None:
        if not connections:
            raise ConnectionURLError("a vehicle needs at least one --connection")
        if not speedup > 0:
            raise ValueError(f"speedup must be > 0, got {speedup!r}")
        self.scenario = scenario
        self.speedup = float(speedup)
        # simulated seconds per step: 5 steps per simulated second up to a speed-up of 10
        # (every 5 Hz stream has its own state), growing to 1 s from 50x (one per loop)
        self.step_s = step_s if step_s is not None else \
            max(0.2, min(1.0, self.speedup * self.LOOP_PERIOD_S))
        self.sysid, self.compid = sysid, compid
        self.status = status or (lambda message: None)
        self.clock = wall_clock
        self.realisation = realise(scenario, seed)
        # the configured H_AGL of a search is its height (as in osa search)
        agl = scenario.search.height_m if scenario.search is not None else None
        # the phone's records leave as they are delivered (the log, the relay): not kept
        self.stepper = Stepper(self.realisation, agents=scenario.agents[:1], header_agl_m=agl,
                               keep_records=False)
        self.autopilot = Autopilot(self.stepper, wall_clock=wall_clock,
                                   keepouts=scenario.keepouts if keepouts is None else keepouts)
        for name, value in (params or {}).items():
            why = self.autopilot.params.set(name, value)
            if why is not None:
                raise ValueError(why)
        self.telemetry = Telemetry(self.autopilot)
        # the phone's records to the ground stations that ask (TUNNEL), lockstep pacing
        self._relay_links: set[int] = set()
        self.relay = RecordRelay(self._relay_send, self.stepper.agents[0].header,
                                 lockstep_s=lockstep_s, tick_s=self.autopilot.dt)
        self.protocol = MissionServer(self._send_to, self._on_commit,
                                      lambda: self.autopilot.mission.seq,
                                      timeout_s=transfer_timeout_s, clock=wall_clock)
        self.links = Links(connections, sysid, compid)
        self.log_path = Path(log_path) if log_path is not None else None
        self._sink: LogSink | None = None
        if self.log_path is not None:
            agent = self.stepper.agents[0]
            self._sink = LogSink(self.log_path, agent.header, self.realisation.truth_records(),
                                 flush_lines=True)
        self.stats = Stats()
        self.error: str | None = None
        self._link = _Link()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._last_current: tuple[int, int, int] | None = None
        self._bad_kinds: set[str] = set()
        self.terrain_data_ignored = 0  # TERRAIN_DATA received (the database needs none)
        self._closed = False
        self._lock = threading.Lock()

    # ------------------------------------------------------------------ lifecycle
    @property
    def t_s(self) -> float:
        return self.autopilot.vehicle.t_s

    def start(self) -> VirtualVehicle:
        self._thread = threading.Thread(target=self.run, args=(self._stop.is_set,),
                                        name="osa-vehicle", daemon=True)
        self._thread.start()
        return self

    def stop(self, timeout_s: float = 5.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout_s)
            self._thread = None
        self.close()

    def __enter__(self) -> VirtualVehicle:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def close(self) -> None:
        """Deliver what the phone still has on its way, close the log and the ports."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            with contextlib.suppress(FlightError):
                self._on_phone_records(self.autopilot.finish(), math.inf)
            if self._sink is not None:
                self._sink.close()
            self.links.close()

    # ------------------------------------------------------------------ loop
    def run(self, should_stop: Callable[[], bool]) -> None:
        """Run until ``should_stop()`` (checked every iteration) or a crash."""
        wall0 = self.clock()
        sim0 = self.t_s
        next_hb = wall0
        next_report = -math.inf
        start_wall, start_sim = wall0, sim0
        window: collections.deque[tuple[float, float]] = collections.deque(maxlen=21)
        while not should_stop():
            now = self.clock()
            if not window or now - window[-1][0] >= 0.5:
                window.append((now, self.t_s))
            self._receive(now)
            limit = self.relay.limit_s
            if math.isfinite(self.speedup):
                target = sim0 + (now - wall0) * self.speedup
                if target > limit:  # lockstep: waiting for the ground station is not lag
                    target, sim0, wall0 = limit, self.t_s, now
                if (target - self.t_s) / self.speedup > self.BEHIND_WALL_S:
                    self.stats.behind_events += 1
                    if now >= next_report:
                        w0, s0 = window[0]
                        ratio = (self.t_s - s0) / max(now - w0, 1e-9)
                        self.status(f"cannot keep up with --speedup {self.speedup:g}: "
                                    f"simulated time ran at {ratio:.0f}x real time over the "
                                    f"last {now - w0:.0f} s; it runs as fast as it can")
                        next_report = now + 30.0
                    target = min(self.t_s + self.step_s, limit)
                    sim0, wall0 = target, now
            else:
                target = min(self.t_s + self.step_s, limit)
            try:
                self._advance_to(target)
            except FlightError as exc:
                self.error = f"the vehicle crashed: {exc}"
                self.autopilot.crashed = True
                self.autopilot.text(MAV_SEVERITY_CRITICAL, "crashed")
                self.status(self.error)
                self._publish_events()
                break
            if now >= next_hb:
                self._broadcast(self.telemetry.heartbeat())
                next_hb = max(next_hb + 1.0, now + 0.5)
            self._publish_streams()
            self.protocol.tick()
            self._link_check(now)
            self.autopilot.on_wall_clock(now)
            self._publish_events()
            self.stats.wall_s = self.clock() - start_wall
            self.stats.sim_s = self.t_s - start_sim
            waiting = self.t_s >= limit - 1e-9
            self._wait(self.LOOP_PERIOD_S if math.isfinite(self.speedup) or waiting else 0.0)

    def _advance_to(self, target_s: float) -> None:
        """Step towards ``target_s``, for at most STEP_WALL_S of wall time (the ports
        are read again after that; a target not reached shows as lag)."""
        ap = self.autopilot
        dt = ap.dt
        until = self.clock() + self.STEP_WALL_S
        while math.floor(target_s / dt + 1e-9) > ap.vehicle.k and self.clock() < until:
            t = min(target_s, self.t_s + self.step_s)
            emitted = ap.step_to(t)
            self.stats.steps += 1
            self._on_phone_records(emitted, self.t_s)
            self._publish_events()
            self._publish_streams()
        if self.relay.held(self.t_s):  # lockstep: where it waits, at that instant
            self._broadcast(self.telemetry.build(MAVLINK_MSG_ID_GLOBAL_POSITION_INT))

    def _on_phone_records(self, emitted: list[Emitted], now_s: float) -> None:
        """The phone's new records (delivery order, :class:`sim.stepper.Emitted`) at
        simulated time ``now_s``: the latest GNSS fix for GPS_RAW_INT, the lines for the
        log. The one place the phone's records leave the simulation."""
        for e in emitted:
            if isinstance(e.record, GnssFix):
                self.telemetry.last_fix = e.record
        if self._sink is not None:
            self._sink.add(emitted, now_s)
        self.relay.relay(emitted)  # to the ground stations that asked (TUNNEL)

    def _publish_streams(self) -> None:
        """The streams that are due, each link at its own rates."""
        built: dict[int, Any] = {}
        for link in self.links.ids():
            for msg_id in self.telemetry.streams_of(link).due(self.t_s):
                if msg_id not in built:
                    built[msg_id] = self.telemetry.build(msg_id)
                self.links.send_on(link, built[msg_id])
        self.stats.sent = self.links.sent

    def _wait(self, timeout_s: float) -> None:
        if timeout_s <= 0:
            return
        fds = self.links.fds()
        if fds is None:
            time.sleep(timeout_s)
            return
        with contextlib.suppress(OSError, ValueError):
            select.select(fds, [], [], timeout_s)

    # ------------------------------------------------------------------ sending
    def _broadcast(self, msg: Any) -> None:
        self.links.broadcast(msg)
        self.stats.sent = self.links.sent

    def _send_to(self, peer: Peer, name: str, args: tuple) -> None:
        self.links.send_args(peer, name, args)
        self.stats.sent = self.links.sent

    def _send_msg(self, peer: Peer, msg: Any) -> None:
        # PROTOCOL_VERSION in MAVLink 2 framing on any link (as PX4: the handshake)
        self.links.send(peer, msg, mavlink2=getattr(msg, "id", None)
                        == MAVLINK_MSG_ID_PROTOCOL_VERSION)
        self.stats.sent = self.links.sent

    def _ack(self, peer: Peer, command: int, result: int) -> None:
        self._send_msg(peer, mavlink.MAVLink_command_ack_message(command, result, 0, 0,
                                                                 peer[1], peer[2]))

    def _statustext(self, severity: int, text: str) -> None:
        self._broadcast(mavlink.MAVLink_statustext_message(severity, text[:50].encode(), 0, 0))

    def _publish_events(self) -> None:
        ap = self.autopilot
        for ev in ap.drain_events():
            kind = ev[0]
            if kind == "reached":
                self._broadcast(mavlink.MAVLink_mission_item_reached_message(int(ev[1])))
            elif kind == "current":
                state = ev[1:4]
                if state != self._last_current:
                    self._last_current = state
                    self._broadcast(self.telemetry.mission_current(*state))
            elif kind in ("mode", "armed"):
                self._broadcast(self.telemetry.heartbeat())
            elif kind == "home":
                self._broadcast(self.telemetry.build(MAVLINK_MSG_ID_HOME_POSITION))
            elif kind == "landed":
                self._broadcast(self.telemetry.build(MAVLINK_MSG_ID_EXTENDED_SYS_STATE))
            elif kind == "text":
                self._statustext(int(ev[1]), str(ev[2]))

    # ------------------------------------------------------------------ receiving
    def _receive(self, now: float) -> None:
        for link, msg in self.links.poll(now):
            self._forget_gone()  # before the next message: it may be another's count
            self._dispatch(link, msg, now)
        self._forget_gone()

    def _forget_gone(self) -> None:
        """The uploads of links closed since (a TCP client hung up, a udpin address
        silent too long) end."""
        for link in self.links.take_gone():
            self.protocol.forget_link(link)
            self.telemetry.forget(link)
            self._relay_links.discard(link)

    def _dispatch(self, link: int, msg: Any, now: float) -> None:
        kind = msg.get_type()
        if kind == "BAD_DATA":
            return
        src = (msg.get_srcSystem(), msg.get_srcComponent())
        if src == (self.sysid, self.compid):  # its own messages, looped back
            return
        self.stats.received += 1
        here = (link, *src)
        if here not in self._link.peers:  # a new ground station: it hears from us at once
            if len(self._link.peers) >= MAX_PEERS:
                self._link.peers.clear()
            self._link.peers.add(here)
            self._send_msg(here, self.telemetry.heartbeat())
        # another component of its own system (a companion computer) is served but is
        # no ground station: it does not keep the ground-station link alive
        if src[0] != self.sysid:
            self._link.last_rx_wall = now
            if not self._link.seen or self._link.lost:
                if self._link.lost:
                    self.autopilot.text(MAV_SEVERITY_WARNING, "ground station regained")
                self._link.seen, self._link.lost = True, False
        target = getattr(msg, "target_system", 0)
        if target not in (0, self.sysid):
            return
        tcomp = getattr(msg, "target_component", 0)
        if kind not in ("SET_MODE",) and tcomp not in (0, self.compid) and not (
                tcomp == MAV_COMP_ID_MISSIONPLANNER and kind.startswith("MISSION_")):
            # (the mission protocol addressed to the mission planner component, as
            # older ground stations send it, is the autopilot's: PX4 takes it too)
            return
        peer = (link, src[0], src[1])
        handler = getattr(self, f"_on_{kind.lower()}", None)
        if handler is None:
            return
        try:
            handler(peer, msg)
        except (ValueError, TypeError, OverflowError, KeyError, struct.error) as exc:
            # a message the vehicle cannot use (or an answer that cannot be encoded)
            # never stops it: say so once per kind
            if kind not in self._bad_kinds:
                self._bad_kinds.add(kind)
                self.status(f"ignored a {kind} from {peer[1]}/{peer[2]}: {exc}")

    def _on_tunnel(self, peer: Peer, msg: Any) -> None:
        if msg.payload_type in (PAYLOAD_PACE, PAYLOAD_RESEND):  # it asks for the records
            self._relay_links.add(peer[0])
        self.relay.on_tunnel(msg, self.t_s)

    def _relay_send(self, msg: Any) -> None:
        """The relay's TUNNELs to the links of the ground stations that asked for them
        (several a second: not to a ground station on a telemetry radio that did not)."""
        for link in list(self._relay_links):
            self.links.send_on(link, msg)
        self.stats.sent = self.links.sent

    # mission protocol
    def _on_mission_count(self, peer: Peer, msg: Any) -> None:
        self.protocol.on_count(peer, int(msg.count), int(getattr(msg, "mission_type", 0)),
                               mavlink1=is_mavlink1(msg))

    def _on_mission_item_int(self, peer: Peer, msg: Any) -> None:
        self.protocol.on_item_int(peer, msg)

    def _on_mission_item(self, peer: Peer, msg: Any) -> None:
        self.protocol.on_item_float(peer, msg)

    def _on_mission_request_list(self, peer: Peer, msg: Any) -> None:
        self.protocol.on_request_list(peer, int(getattr(msg, "mission_type", 0)))

    def _on_mission_request_int(self, peer: Peer, msg: Any) -> None:
        self.protocol.on_request(peer, int(msg.seq), int(getattr(msg, "mission_type", 0)))

    def _on_mission_request(self, peer: Peer, msg: Any) -> None:
        self.protocol.on_request(peer, int(msg.seq), int(getattr(msg, "mission_type", 0)),
                                 float_form=True)

    def _on_mission_write_partial_list(self, peer: Peer, msg: Any) -> None:
        """Partial lists (ArduPilot's) are refused at once, never left unanswered."""
        self.protocol.refuse_partial(peer, int(getattr(msg, "mission_type", 0)))

    _on_mission_request_partial_list = _on_mission_write_partial_list

    def _on_mission_clear_all(self, peer: Peer, msg: Any) -> None:
        self.protocol.on_clear_all(peer, int(getattr(msg, "mission_type", 0)))

    def _on_mission_ack(self, peer: Peer, msg: Any) -> None:
        self.protocol.on_ack(peer, int(msg.type), int(getattr(msg, "mission_type", 0)))

    def _on_mission_set_current(self, peer: Peer, msg: Any) -> None:
        result, why = self.autopilot.set_current(int(msg.seq))
        if result != MAV_RESULT_ACCEPTED:
            self.autopilot.text(MAV_SEVERITY_WARNING, why)
        self._send_msg(peer, self.telemetry.build(MAVLINK_MSG_ID_MISSION_CURRENT))

    def _on_commit(self, mission_type: int, items: list, current: int) -> None:
        ap = self.autopilot
        if mission_type == MAV_MISSION_TYPE_MISSION:
            ap.set_mission(items, current)
        elif mission_type == MAV_MISSION_TYPE_FENCE:
            ap.set_fence(items)
        else:
            ap.set_rally(items)

    # parameters
    def _param_value(self, peer: Peer | None, name: str) -> None:
        params = self.autopilot.params
        value, kind = params.wire_value(name)
        k = params.index(name)
        msg = mavlink.MAVLink_param_value_message(name.encode(), value, kind, len(params), k)
        if peer is None:
            self._broadcast(msg)
        else:
            self._send_msg(peer, msg)

    def _on_param_request_list(self, peer: Peer, msg: Any) -> None:
        for spec in self.autopilot.params.specs:
            self._param_value(peer, spec.name)

    def _on_param_request_read(self, peer: Peer, msg: Any) -> None:
        params = self.autopilot.params
        idx = int(msg.param_index)
        if 0 <= idx < len(params):
            self._param_value(peer, params.specs[idx].name)
        elif params.index(msg.param_id) is not None:
            self._param_value(peer, msg.param_id)

    def _on_param_set(self, peer: Peer, msg: Any) -> None:
        params = self.autopilot.params
        name = msg.param_id
        if params.index(name) is None:
            self.autopilot.text(MAV_SEVERITY_WARNING, f"unknown parameter {name}")
            return
        value = Params.from_wire(float(msg.param_value), int(msg.param_type or
                                                                MAV_PARAM_TYPE_REAL32))
        why = params.set(name, value)
        if why is not None:
            self.autopilot.text(MAV_SEVERITY_WARNING, why)
        self._param_value(None, name)

    # terrain protocol (envs/vehicle/terrain.py)
    def _on_terrain_check(self, peer: Peer, msg: Any) -> None:
        self._send_msg(peer, self.telemetry.terrain_report(int(msg.lat), int(msg.lon)))

    def _on_terrain_request(self, peer: Peer, msg: Any) -> None:
        """The blocks of the mask from the database (none: it needs no data)."""
        db = self.autopilot.terrain
        lat, lon, spacing, mask = int(msg.lat), int(msg.lon), int(msg.grid_spacing), \
            int(msg.mask)
        for bit in range(REQUEST_BLOCKS_E * REQUEST_BLOCKS_N):
            if mask >> bit & 1:
                heights = db.block(lat, lon, spacing, bit)
                if heights is not None:
                    self._send_msg(peer, mavlink.MAVLink_terrain_data_message(
                        lat, lon, spacing, bit, heights))

    def _on_terrain_data(self, peer: Peer, msg: Any) -> None:
        """Accepted without effect: the database is the scenario's terrain."""
        self.terrain_data_ignored += 1

    def _on_log_request_list(self, peer: Peer, msg: Any) -> None:
        """The autopilot keeps no logs (the phone's log is ``--log``): one LOG_ENTRY with
        ``num_logs`` 0, as the log protocol answers an empty list."""
        self._send_msg(peer, mavlink.MAVLink_log_entry_message(0, 0, 0, 0, 0))

    def _on_file_transfer_protocol(self, peer: Peer, msg: Any) -> None:
        """MAVLink FTP (no files here; AUTOPILOT_VERSION does not claim it): every request
        is answered with a NAK, error UnknownCommand, as the FTP protocol answers an
        operation a server does not support (MAVSDK's Ftp: UNSUPPORTED at once, not a
        TIMEOUT after 32 s). Responses (opcodes 128, 129) are not answered."""
        req = bytes(msg.payload)
        if len(req) < FTP_HEADER_BYTES or req[3] >= FTP_RSP_ACK:
            return
        seq, session, opcode = struct.unpack_from("<HBB", req)
        nak = struct.pack("<HBBBBBBI", (seq + 1) & 0xFFFF, session, FTP_RSP_NAK, 1, opcode,
                          0, 0, 0) + bytes([FTP_ERR_UNKNOWN_COMMAND])
        self._send_msg(peer, mavlink.MAVLink_file_transfer_protocol_message(
            0, peer[1], peer[2], list(nak.ljust(251, b"\0"))))

    def _on_ping(self, peer: Peer, msg: Any) -> None:
        """A PING request (targets 0) is answered to its sender with its time and
        sequence (the ping microservice; PX4 answers it too)."""
        if msg.target_system == 0 and msg.target_component == 0:
            self._send_msg(peer, mavlink.MAVLink_ping_message(int(msg.time_usec), int(msg.seq),
                                                              peer[1], peer[2]))

    def _on_timesync(self, peer: Peer, msg: Any) -> None:
        if msg.tc1 == 0:
            self._send_msg(peer, mavlink.MAVLink_timesync_message(
                int(self.clock() * 1e9), int(msg.ts1)))

    # commands
    def _on_command_long(self, peer: Peer, msg: Any) -> None:
        p = [msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6,
             msg.param7]
        self._command(peer, int(msg.command), [float(v) for v in p], None)

    def _on_command_int(self, peer: Peer, msg: Any) -> None:
        p = [msg.param1, msg.param2, msg.param3, msg.param4, msg.x / 1e7, msg.y / 1e7, msg.z]
        if msg.x == 0 and msg.y == 0:
            p[4] = p[5] = math.nan
        for k, v in ((4, msg.x), (5, msg.y)):  # INT32_MAX: not set (the NaN of an int)
            if v == UNSET_E7:
                p[k] = math.nan
        self._command(peer, int(msg.command), [float(v) for v in p], int(msg.frame))

    def _on_set_mode(self, peer: Peer, msg: Any) -> None:
        """SET_MODE (deprecated): answered as PX4 does, with a DO_SET_MODE COMMAND_ACK."""
        main, sub = decode_custom_mode(int(msg.custom_mode))
        self._command(peer, MAV_CMD_DO_SET_MODE, [float(msg.base_mode), float(main), float(sub),
                                              0.0, 0.0, 0.0, 0.0], None)

    def _alt_amsl(self, alt: float, frame: int | None, lat_deg: float = math.nan,
                  lon_deg: float = math.nan) -> float:
        """A command's altitude as AMSL (COMMAND_LONG: AMSL; COMMAND_INT: by frame; above
        the terrain: at (lat, lon), NaN: under the vehicle)."""
        ap = self.autopilot
        if frame in RELATIVE_FRAMES and math.isfinite(alt):
            return ap.home.alt_m + alt
        if frame in TERRAIN_FRAMES and math.isfinite(alt):
            if not (math.isfinite(lat_deg) and math.isfinite(lon_deg)):
                lat_deg, lon_deg = ap.geodetic(ap.position)[:2]
            return ap.terrain.height_m(lat_deg, lon_deg) + alt
        return alt

    def _command(self, peer: Peer, cmd: int, p: list[float], frame: int | None) -> None:
        """Answer a COMMAND_LONG / COMMAND_INT: always one COMMAND_ACK to ``peer`` (a
        refusal also a STATUSTEXT saying why), then what was asked for."""
        ap = self.autopilot
        try:
            result, why, after = self._decide(peer, cmd, p, frame)
        except (ArithmeticError, ValueError, TypeError, KeyError) as exc:
            result, why, after = MAV_RESULT_FAILED, f"command {cmd} failed: {exc}", None
        self._ack(peer, cmd, result)
        if why:
            ap.text(MAV_SEVERITY_WARNING if result else MAV_SEVERITY_INFO, why)
        self._send_msg(peer, after)
        self._publish_events()

    def _decide(self, peer: Peer, cmd: int, p: list[float],
                frame: int | None) -> tuple[int, str, Any]:
        """(MAV_RESULT, why, the message to send after the ACK or None) for a command
        from ``peer`` (message intervals: of its link)."""
        ap = self.autopilot
        if cmd == MAV_CMD_COMPONENT_ARM_DISARM:
            if p[0] == 1.0:
                return (*ap.arm(), None)
            if p[0] == 0.0:
                return (*ap.disarm(force=p[1] == FORCE_DISARM_MAGIC), None)
            return MAV_RESULT_DENIED, f"arm/disarm param1 {p[0]:g}", None
        if cmd == MAV_CMD_NAV_TAKEOFF:
            why = _bad_frame(frame) or _bad_altitude(p[6], nan_ok=True)
            if why:
                return MAV_RESULT_DENIED, f"takeoff denied: {why}", None
            return (*ap.takeoff(self._alt_amsl(p[6], frame)), None)
        if cmd == MAV_CMD_DO_SET_MODE:
            return (*self._set_mode(p), None)
        if cmd == MAV_CMD_MISSION_START:
            return (*ap.mission_start(p[0], p[1]), None)
        if cmd == MAV_CMD_NAV_RETURN_TO_LAUNCH:
            return (*ap.return_to_launch(), None)
        if cmd == MAV_CMD_NAV_LAND:
            return (*ap.land(), None)
        if cmd == MAV_CMD_DO_PAUSE_CONTINUE:
            if p[0] not in (0.0, 1.0):
                return MAV_RESULT_DENIED, f"pause/continue param1 {p[0]:g}", None
            return (*ap.pause_continue(p[0] == 1.0), None)
        if cmd == MAV_CMD_DO_CHANGE_SPEED:
            return (*ap.change_speed(p[1]), None)
        if cmd == MAV_CMD_DO_REPOSITION:
            why = _bad_frame(frame) or _bad_position(p[4], p[5]) \
                or _bad_altitude(p[6], nan_ok=True)
            if why:
                return MAV_RESULT_DENIED, f"reposition denied: {why}", None
            return (*self._reposition(p, frame), None)
        if cmd == MAV_CMD_DO_SET_HOME:
            if p[0] == 1.0 or (p[0] == 0.0 and not (math.isfinite(p[4])
                                                    and math.isfinite(p[5]))):
                return (*ap.set_home(None), None)
            why = (f"param1 {p[0]:g}" if p[0] != 0.0 else "") or _bad_frame(frame) \
                or _bad_position(p[4], p[5]) or _bad_altitude(p[6], nan_ok=False)
            if why:
                return MAV_RESULT_DENIED, f"set home denied: {why}", None
            return (*ap.set_home((p[4], p[5], self._alt_amsl(p[6], frame, p[4], p[5]))),
                    None)
        if cmd == MAV_CMD_DO_SET_MISSION_CURRENT:
            # MAVLink: param1 -1 keeps the current item; param2 is a boolean
            if not (math.isfinite(p[0]) and p[0] >= -1.0) or p[1] not in (0.0, 1.0):
                return MAV_RESULT_DENIED, f"set current param1 {p[0]:g}, param2 {p[1]:g}", None
            seq = int(p[0]) if p[0] >= 0 else ap.mission.seq
            result, why = ap.set_current(seq, reset_jumps=p[1] == 1.0)
            return result, why, self.telemetry.build(MAVLINK_MSG_ID_MISSION_CURRENT)
        if cmd in (MAV_CMD_SET_MESSAGE_INTERVAL, MAV_CMD_GET_MESSAGE_INTERVAL,
                   MAV_CMD_REQUEST_MESSAGE):
            if not _is_message_id(p[0]):
                return MAV_RESULT_DENIED, f"no message id {p[0]:g}", None
            msg_id = int(p[0])
            streams = self.telemetry.streams_of(peer[0])
            if cmd == MAV_CMD_GET_MESSAGE_INTERVAL:
                return MAV_RESULT_ACCEPTED, "", mavlink.MAVLink_message_interval_message(
                    msg_id, streams.interval_us(msg_id))
            if cmd == MAV_CMD_SET_MESSAGE_INTERVAL:
                if not (math.isfinite(p[1]) and p[1] >= -1.0):
                    return MAV_RESULT_DENIED, f"message interval {p[1]:g} us", None
                ok = streams.set_interval(msg_id, p[1])
                return (MAV_RESULT_ACCEPTED if ok else MAV_RESULT_UNSUPPORTED), "", None
        if cmd in (MAV_CMD_REQUEST_MESSAGE, MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES,
                   MAV_CMD_GET_HOME_POSITION, MAV_CMD_REQUEST_PROTOCOL_VERSION):
            msg_id = {MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES: MAVLINK_MSG_ID_AUTOPILOT_VERSION,
                      MAV_CMD_GET_HOME_POSITION: MAVLINK_MSG_ID_HOME_POSITION,
                      MAV_CMD_REQUEST_PROTOCOL_VERSION: MAVLINK_MSG_ID_PROTOCOL_VERSION,
                      }.get(cmd, int(p[0]))
            if msg_id in REQUESTABLE:
                return MAV_RESULT_ACCEPTED, "", self.telemetry.build(msg_id)
        return MAV_RESULT_UNSUPPORTED, "", None

    def _set_mode(self, p: list[float]) -> tuple[int, str]:
        base = int(p[0]) if math.isfinite(p[0]) and 0 <= p[0] <= 255 else 0
        if not base & MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            # the base mode alone, as PX4 reads it: AUTO_ENABLED is AUTO.MISSION, manual
            # input with GUIDED is POSCTL, manual input without it needs sticks
            if base & MAV_MODE_FLAG_AUTO_ENABLED:
                return self.autopilot.set_mode(Mode.MISSION)
            if base & MAV_MODE_FLAG_MANUAL_INPUT_ENABLED:
                if base & MAV_MODE_FLAG_GUIDED_ENABLED:
                    return self.autopilot.set_mode(Mode.POSCTL)
                return MAV_RESULT_DENIED, f"base mode {base} (manual) not supported"
            return MAV_RESULT_DENIED, f"mode change to base mode {base}: no mode in it"
        if not all(math.isfinite(x) and 0 <= x <= 255 for x in p[1:3]):
            return MAV_RESULT_DENIED, f"mode change to main mode {p[1]:g}, sub mode {p[2]:g}"
        main, sub = int(p[1]), int(p[2])
        mode = mode_from_main_sub(main, sub)
        if mode is None:
            return MAV_RESULT_DENIED, f"mode {mode_name(main, sub)} not supported"
        return self.autopilot.set_mode(mode)

    def _reposition(self, p: list[float], frame: int | None) -> tuple[int, str]:
        ap = self.autopilot
        here = ap.position
        lat, lon, alt = ap.geodetic(here)
        if math.isfinite(p[4]) and math.isfinite(p[5]):
            lat, lon = p[4], p[5]
        a = self._alt_amsl(p[6], frame, lat, lon)
        if math.isfinite(a):
            alt = a
        e, n, u = ap.frame.to_enu(lat, lon, alt)
        if p[0] > 0:
            ap.change_speed(p[0])
        return ap.reposition((float(e), float(n), float(u)))

    def _link_check(self, now: float) -> None:
        link = self._link
        timeout = self.autopilot.params["COM_DL_LOSS_T"]
        if link.seen and not link.lost and now - link.last_rx_wall > timeout:
            link.lost = True
            self.autopilot.on_link_lost()


def _is_message_id(x: float) -> bool:
    """A MAVLink 2 message id (24 bits) in a float parameter."""
    return math.isfinite(x) and x == int(x) and 0 <= x < (1 << 24)


def _bad_frame(frame: int | None) -> str:
    """Why a COMMAND_INT's frame cannot place a position ('' if it can)."""
    return "" if frame is None or frame in GLOBAL_FRAMES else f"frame {frame} not supported"


def _bad_position(lat_deg: float, lon_deg: float) -> str:
    """Why a command's latitude and longitude are unusable (NaN: none given; '' if fine)."""
    if math.isnan(lat_deg) and math.isnan(lon_deg):
        return ""
    if not (math.isfinite(lat_deg) and -90.0 <= lat_deg <= 90.0):
        return f"latitude {lat_deg:g}"
    if not (math.isfinite(lon_deg) and -180.0 <= lon_deg <= 180.0):
        return f"longitude {lon_deg:g}"
    return ""


def _bad_altitude(alt_m: float, *, nan_ok: bool) -> str:
    """Why a command's altitude is unusable (NaN: unchanged, when ``nan_ok``)."""
    if math.isnan(alt_m) and nan_ok:
        return ""
    if not (math.isfinite(alt_m) and abs(alt_m) <= MAX_ALTITUDE_M):
        return f"altitude {alt_m:g} m"
    return ""
