"""A MAVLink autopilot as the closed loop's vehicle: telemetry in, missions out, the
phone's records from a record stream.

:class:`MavlinkVehicle` implements :class:`envs.vehicles.Vehicle` for ``osa vehicle``
or a drone with a PX4 autopilot, so :class:`envs.loop.ClosedLoop` flies it with the
same policies, estimator and bookkeeping as the in-process simulator:

- **state from telemetry**: GLOBAL_POSITION_INT (the autopilot's estimate) and its
  velocity; flight time is the vehicle's ``time_boot_ms`` since the start (arming);
- **records from the phone**: a :class:`envs.phone.RecordSource`: by default the
  records ``osa vehicle`` relays on the same link (TUNNEL, :class:`envs.phone.
  TunnelRecords`), or JSON-line datagrams of a phone app (``--phone``), or a log file
  being written (``--vehicle-log``); put in replay order and released by a
  :class:`envs.phone.PhoneFeed`, and copied to the loop's own log, so ``osa replay``
  of it gives the report's estimates;
- **plans as missions**: each new segment becomes NAV_WAYPOINT items (the
  Douglas-Peucker decimation of ``osa plan``, heights above the terrain converted to
  altitudes above the vehicle's home, a DO_CHANGE_SPEED for the segment's speed, no
  take-off item), uploaded with read-back (:func:`planner.mavlink.upload_on_link`) and
  flown at once: a vehicle in AUTO.MISSION switches to a new mission from where it is,
  without stopping; otherwise MAV_CMD_MISSION_START. ``hold`` is AUTO.LOITER;
- **pacing**: after each decision the vehicle gets an acknowledgement of the time the
  loop has processed (TUNNEL :data:`envs.phone.PAYLOAD_PACE`): an ``osa vehicle
  --lockstep S`` then never runs more than S seconds ahead, and a run is reproducible
  whatever the machine's load.

While the loop decides (a plan, a trained policy) it does not read the link: a daemon
thread (:meth:`MavlinkVehicle._keep_alive`) goes on sending the ground station's
HEARTBEAT at 1 Hz, so a long decision never looks like a lost ground station to the
autopilot (PX4's COM_DL_LOSS_T, ArduPilot's FS_GCS_TIMEOUT); every send goes through
one lock.

Every wait is bounded: uploads are retried ``upload_attempts`` times, commands
``command_attempts`` times, and no telemetry for ``telemetry_timeout_s`` ends the run
with :class:`VehicleLinkError` (one line). At the end the vehicle is sent home (RTL).
"""

from __future__ import annotations

import contextlib
import math
import os
import socket
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from envs.phone import (
    PAYLOAD_PACE,
    PAYLOAD_RECORDS,
    PAYLOAD_RESEND,
    FileRecords,
    PhoneBatch,
    PhoneFeed,
    RecordSource,
    TunnelRecords,
    UdpRecords,
    pace_payload,
    resend_payload,
)
from envs.vehicle.px4 import Mode
from envs.vehicle.telemetry import VEHICLE_TAG, world_fingerprint
from envs.vehicles import VehicleState
from estimator.logio import LogWriter
from estimator.records import LogHeader, Trajectory, TruthRecord
from planner.convert import trajectory_to_mission
from planner.mavlink import PymavlinkLink, TransferConfig, mavutil, upload_on_link
from planner.mavlink_wire import MissionRejectedError, UploadError
from planner.mission import Mission, MissionItem
from sim.realisation import Realisation
from sim.scenario import Scenario

mavlink = mavutil.mavlink
END_DELIVERY_S = 0.5  # records delivered this long after the end still belong to it
CLOCK_TOLERANCE_S = 0.002  # time_boot_ms is truncated to the millisecond
ACK_AGAIN_S = 0.5  # the vehicle's clock still for this long (wall): acknowledge again
RESEND_WAIT_S = 1.0  # records missing at a mark are asked again for this long (wall)
RESEND_EVERY_S = 0.25
QUIET_S = 0.3  # at the start: a source without marks quiet this long holds no backlog
DRAIN_MAX_S = 2.0
KEEPALIVE_POLL_S = 0.2  # the keep-alive thread looks this often whether one is due
RCVBUF_BYTES = 4 << 20  # a lockstep vehicle sends a decision period's records at once


def _runs(seqs: list[int]) -> list[tuple[int, int]]:
    """Consecutive runs of sorted sequence numbers as (first, count)."""
    out: list[tuple[int, int]] = []
    for s in seqs:
        if out and s == out[-1][0] + out[-1][1] and out[-1][1] < 0xFFFF:
            out[-1] = (out[-1][0], out[-1][1] + 1)
        else:
            out.append((s, 1))
    return out


class VehicleLinkError(RuntimeError):
    """The loop lost or could not use the vehicle (one line, for ``osa search``)."""


@dataclass(frozen=True, kw_only=True)
class LinkConfig:
    """Bounds and choices of the loop over MAVLink (wall-clock seconds)."""

    connect_timeout_s: float = 10.0  # the vehicle's heartbeat, position and home
    telemetry_timeout_s: float = 5.0  # no message from the vehicle this long: lost
    command_timeout_s: float = 1.0  # per COMMAND_LONG attempt
    command_attempts: int = 3
    upload_attempts: int = 3  # a whole mission transfer (each message is retried too)
    message_timeout_s: float = 0.5
    retries: int = 5
    release_lag_s: float = 2.0  # a source without marks: records fed this far behind
    return_at_end: bool = True  # RTL when the search is over
    tolerance_m: float = 1.0  # decimation of a segment into waypoints

    @property
    def transfer(self) -> TransferConfig:
        return TransferConfig(connect_timeout_s=self.connect_timeout_s,
                              message_timeout_s=self.message_timeout_s, retries=self.retries,
                              autopilot="auto")


def pymavlink_url(url: str) -> str:
    """The loop talks pymavlink: MAVSDK's ``udpin://H:P`` forms are translated."""
    for scheme, py in (("udpin://", "udpin:"), ("udpout://", "udpout:"), ("udp://", "udpin:"),
                       ("tcpin://", "tcpin:"), ("tcp://", "tcp:"), ("tcpout://", "tcp:")):
        if url.startswith(scheme):
            return py + url[len(scheme):]
    return url


def result_name(code: int) -> str:
    """MAV_RESULT's name for a COMMAND_ACK result (pymavlink's enum)."""
    e = mavlink.enums["MAV_RESULT"].get(int(code))
    return e.name.removeprefix("MAV_RESULT_") if e is not None else str(code)


class MavlinkVehicle:
    """One vehicle behind a MAVLink autopilot (see the module docstring).

    ``realisation`` is the world of the loop's scenario and seed: its frame and terrain
    place telemetry and missions, its fingerprint is checked against ``osa vehicle``'s.
    ``phone``: where the phone's records come from (None: the vehicle's relay).
    ``log_path`` receives them (with the header and the world's truth records).
    """

    n_agents = 1

    def __init__(self, scenario: Scenario, realisation: Realisation, url: str, *,
                 phone: RecordSource | None = None, link: LinkConfig = LinkConfig(),
                 log_path: str | os.PathLike | None = None, seed: object = None) -> None:
        if len(scenario.agents) != 1:
            raise ValueError(f"scenario {scenario.name} has {len(scenario.agents)} agents: "
                             "the loop over MAVLink flies one vehicle")
        if scenario.search is None:
            raise ValueError(f"scenario {scenario.name} has no [search] table")
        self.scenario = scenario
        self.realisation = realisation
        self.seed_label = seed if seed is not None else realisation.seed.entropy
        self.world = realisation.world
        self.link_config = link
        # the vehicle's TUNNEL payloads: its pacing, and its relay of the phone's
        # records unless they come another way
        self.tunnel = TunnelRecords(keep_records=phone is None)
        self.feed = PhoneFeed(phone if phone is not None else self.tunnel,
                              lag_s=link.release_lag_s)
        self.log_paths = [Path(log_path)] if log_path is not None else []
        self._writer: LogWriter | None = None
        self._header: LogHeader | None = None
        try:
            self.link = PymavlinkLink(pymavlink_url(url), link.transfer)
        except BaseException:
            self.feed.close()
            raise
        self.conn = self.link.connection
        self.vehicle = self.link.vehicle
        # one sender at a time: the loop's thread and the keep-alive thread
        self._send_lock = threading.RLock()
        raw_send = self.conn.mav.send

        def send(*args: Any, **kwargs: Any) -> Any:
            with self._send_lock:
                return raw_send(*args, **kwargs)

        self.conn.mav.send = send
        self.conn.message_hooks.append(self._on_message)  # every message, also in uploads
        sock = getattr(self.conn, "port", None)
        if isinstance(sock, socket.socket):  # room for a decision period's records
            with contextlib.suppress(OSError):
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RCVBUF_BYTES)
        self.t_s = 0.0
        self._boot0_s: float | None = None
        self._boot_s: float | None = None
        self._last_rx = self._last_look = time.monotonic()
        self._acked_ms = -1
        self.position: tuple[float, float, float] | None = None
        self.velocity = (0.0, 0.0, 0.0)
        self.custom_mode = 0
        self.armed = False
        self.autopilot_version: Any = None
        self.home: tuple[float, float, float] | None = None
        self._plan_items = 0
        self._plan_upload_boot_s = -math.inf
        self._segment_done = True
        self._path_m = 0.0
        self._track: list[tuple[float, float, float]] = []
        self.uploads = 0
        self.upload_retries = 0
        self.asked_again = 0  # relayed records asked for again
        self.command_tries = 0
        self.started = False
        self.finished = False
        self.closed = False
        self.keepalive_heartbeats = 0  # sent by the keep-alive thread
        self._stop_keepalive = threading.Event()
        self._keepalive = threading.Thread(target=self._keep_alive, daemon=True,
                                           name="osa-gcs-heartbeat")
        self._keepalive.start()

    # ------------------------------------------------------------------ setup
    def header(self, agent: int = 0) -> LogHeader:
        assert self._header is not None, "start() first"
        return self._header

    def start(self) -> None:
        """Check the vehicle's world, wait for telemetry and home, arm; flight time
        starts now."""
        if self.started:
            return
        deadline = time.monotonic() + self.link_config.connect_timeout_s
        self._pace(0)  # ask for the phone's records (and hold a lockstep vehicle)
        ours = self._check_fingerprint(deadline)
        asked = -math.inf
        while not self._ready(ours):
            if time.monotonic() > deadline:
                raise VehicleLinkError("no position or home from the vehicle within "
                                       f"{self.link_config.connect_timeout_s:g} s")
            if time.monotonic() - asked > 0.5:
                asked = time.monotonic()
                if self.home is None:
                    self._send_command(mavlink.MAV_CMD_GET_HOME_POSITION)
                # a lockstep vehicle waiting tells its position on request
                self._send_command(mavlink.MAV_CMD_REQUEST_MESSAGE,
                                   mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT)
                if ours:  # its pacing again: a vehicle says once that it waits, and
                    self._pace(0, again=True)  # a lost datagram is never repeated
            self._pump(0.1)
        self._pump(0.0)
        self.tunnel.settle(count=False)  # the records of before the search: not fed
        self._drain_before()
        self.feed.skip_before()
        self._check_world(self.feed.truth)
        h = self.feed.header
        if h is None:  # not heard (yet): the scenario's phone
            s = self.scenario
            h = LogHeader(agent=s.agents[0].name, start_utc=s.log.start_utc,
                          agl_m=s.search.height_m, range_offset_m=s.log.range_offset_m)
        self._header = replace(h, agl_m=round(float(self.scenario.search.height_m), 3))
        if self.log_paths:
            self._writer = LogWriter(self.log_paths[0], self._header)
            self._writer.write_all(self.realisation.truth_records())
        self._boot0_s = self._boot_s
        p = self.tunnel.pacing
        if ours and p is not None and p.lockstep:  # where it waits, to the millisecond
            self._boot0_s = p.now_ms / 1000.0  # (its telemetry's clock may be 1 ms short)
        self._arm()
        self.started = True

    def _arm(self) -> None:
        """Arm (a vehicle already armed stays as it is), and wait for its home (arming
        sets it where the vehicle stands): plans are flown relative to that one."""
        self._command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0, what="arm")
        self.home = None
        deadline = time.monotonic() + self.link_config.connect_timeout_s
        asked = -math.inf
        while self.home is None:
            if time.monotonic() > deadline:
                raise VehicleLinkError("no home position from the vehicle after arming")
            if time.monotonic() - asked > 0.5:
                asked = time.monotonic()
                self._send_command(mavlink.MAV_CMD_GET_HOME_POSITION)
            self._pump(0.05)
        self.armed = True

    def _drain_before(self) -> None:
        """A source without marks (a file, a phone app) may still hold records of before
        the search: take them until it has been quiet for QUIET_S (at most
        DRAIN_MAX_S; a phone streaming in real time is never quiet, and has no
        backlog either)."""
        if self.feed.source.mark() is not None:
            return
        now = time.monotonic()
        deadline, quiet_since, seen = now + DRAIN_MAX_S, now, -1
        while now < deadline and now - quiet_since < QUIET_S:
            self._pump(0.02)
            self.feed.pull()
            now = time.monotonic()
            if self.feed.stats.received != seen:
                seen, quiet_since = self.feed.stats.received, now

    def _ready(self, ours: bool) -> bool:
        """Position, home and clock known; an ``osa vehicle`` has told its pacing, and
        in lockstep it waits at its limit and the position is of that instant (the
        search then starts at the same simulated time whatever the wall clock did)."""
        if self.position is None or self.home is None or self._boot_s is None:
            return False
        if not ours:
            return True
        p = self.tunnel.pacing
        if p is None:
            return False
        return not p.lockstep or (p.waiting and self._boot_s * 1000.0 >= p.now_ms - 2)

    def _check_fingerprint(self, deadline: float) -> bool:
        """``osa vehicle`` puts its world's fingerprint in AUTOPILOT_VERSION.uid: it
        must be this loop's scenario and seed (another autopilot is not checked).
        True for an ``osa vehicle``."""
        asked = -math.inf
        while time.monotonic() < deadline:
            if time.monotonic() - asked > 0.5:
                asked = time.monotonic()
                self._send_command(mavlink.MAV_CMD_REQUEST_MESSAGE,
                                   mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION)
            self._pump(0.1)
            m = self.autopilot_version
            if m is None:
                continue
            if bytes(m.flight_custom_version).rstrip(b"\0") != VEHICLE_TAG:
                return False
            if int(m.uid) != world_fingerprint(self.realisation):
                raise VehicleLinkError(
                    f"the vehicle flies another world than {self.scenario.name} seed "
                    f"{self._seed_text()} (run osa vehicle on the same scenario and --seed)")
            return True
        raise VehicleLinkError("no AUTOPILOT_VERSION from the vehicle")

    def _check_world(self, truth: Sequence[TruthRecord]) -> None:
        """Truth records in the phone's stream (a vehicle's log file) must be ours."""
        if not truth:
            return

        def key(ts) -> list:
            return sorted((t.bssid, round(t.lat_deg, 7), round(t.lon_deg, 7)) for t in ts)

        if key(self.realisation.truth_records()) != key(truth):
            raise VehicleLinkError(
                f"the vehicle's log is not the world of {self.scenario.name} seed "
                f"{self._seed_text()} (run osa vehicle on the same scenario and --seed)")

    def _seed_text(self) -> str:
        return str(self.seed_label)

    # ------------------------------------------------------------------ MAVLink in
    def _heartbeat(self) -> bool:
        """The link's ground-station HEARTBEAT if one is due (True if sent); under the
        send lock, so the loop's thread and the keep-alive thread send one, not two."""
        with self._send_lock:
            return self.link.heartbeat()

    def _keep_alive(self) -> None:
        """The keep-alive thread: a HEARTBEAT whenever one is due, until :meth:`close`
        (the loop's own reads send them too; this one covers its decisions)."""
        while not self._stop_keepalive.wait(KEEPALIVE_POLL_S):
            if self._heartbeat():
                self.keepalive_heartbeats += 1

    def _pump(self, timeout_s: float) -> int:
        """Read what the vehicle sent (waiting up to ``timeout_s`` for the first); the
        hook :meth:`_on_message` takes each message. Silence is counted while the loop
        listens: after the loop was busy longer than the telemetry timeout (a long plan,
        which may also starve the vehicle's process of the CPU), it counts from now."""
        now = time.monotonic()
        if now - self._last_look > self.link_config.telemetry_timeout_s:
            self._last_rx = max(self._last_rx, now)
        self._heartbeat()
        n = 0
        msg = self.conn.recv_match(blocking=timeout_s > 0, timeout=max(timeout_s, 0.0))
        while msg is not None:
            n += 1
            msg = self.conn.recv_match(blocking=False)
        self._last_look = time.monotonic()
        if n:
            self._last_rx = self._last_look
        elif self._last_look - self._last_rx > self.link_config.telemetry_timeout_s:
            raise VehicleLinkError(f"no telemetry from the vehicle for "
                                   f"{self.link_config.telemetry_timeout_s:g} s")
        return n

    def _on_message(self, conn: Any, m: Any) -> None:
        if (m.get_srcSystem(), m.get_srcComponent()) != tuple(self.vehicle):
            return
        self._last_rx = time.monotonic()
        kind = m.get_type()
        if kind == "TUNNEL":
            if m.payload_type == PAYLOAD_RECORDS:
                self.tunnel.take(bytes(m.payload[: m.payload_length]))
        elif kind == "GLOBAL_POSITION_INT":
            e, n, u = self.world.frame.to_enu(m.lat / 1e7, m.lon / 1e7, m.alt / 1e3)
            self.position = (float(e), float(n), float(u))
            self.velocity = (m.vy / 100.0, m.vx / 100.0, -m.vz / 100.0)
            self._boot_s = max(self._boot_s or 0.0, m.time_boot_ms / 1000.0)
        elif kind == "HEARTBEAT":
            self.custom_mode = int(m.custom_mode)
            self.armed = bool(m.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
        elif kind == "MISSION_CURRENT":
            state = int(getattr(m, "mission_state", 0))
            if (self._boot_s is not None and self._boot_s > self._plan_upload_boot_s
                    and m.total == self._plan_items
                    and state == mavlink.MISSION_STATE_COMPLETE):
                self._segment_done = True
        elif kind == "MISSION_ITEM_REACHED":
            if self._plan_items and m.seq == self._plan_items - 1 \
                    and self._boot_s is not None and self._boot_s > self._plan_upload_boot_s:
                self._segment_done = True
        elif kind == "HOME_POSITION":
            self.home = (m.latitude / 1e7, m.longitude / 1e7, m.altitude / 1e3)
        elif kind == "AUTOPILOT_VERSION":
            self.autopilot_version = m

    def _send_command(self, command: int, *params: float, confirmation: int = 0) -> None:
        p = [float(x) for x in params] + [0.0] * (7 - len(params))
        with contextlib.suppress(OSError):
            self.conn.mav.command_long_send(*self.vehicle, command, confirmation, *p)

    def _command(self, command: int, *params: float, what: str) -> None:
        """COMMAND_LONG until acknowledged (``command_attempts`` tries). A try answered
        late means the vehicle gets the command twice: the answers to every try are
        awaited (a while), so that a lockstep vehicle, still waiting, has executed them
        all before it runs on (a late repeat of MISSION_START would restart a mission
        in flight)."""
        cfg = self.link_config
        acks: list[Any] = []

        def hook(conn: Any, m: Any) -> None:
            if m.get_type() == "COMMAND_ACK" and m.command == command:
                acks.append(m)

        self.conn.message_hooks.append(hook)
        sent = 0
        try:
            while not acks and sent < cfg.command_attempts:
                self._send_command(command, *params, confirmation=sent)
                sent += 1
                self.command_tries += 1
                deadline = time.monotonic() + cfg.command_timeout_s
                while time.monotonic() < deadline and not acks:
                    self._pump(0.05)
            deadline = time.monotonic() + cfg.command_timeout_s
            while acks and len(acks) < sent and time.monotonic() < deadline:
                self._pump(0.05)
        finally:
            self.conn.message_hooks.remove(hook)
        if not acks:
            raise VehicleLinkError(f"no answer to {what} after {cfg.command_attempts} attempts")
        if acks[0].result != mavlink.MAV_RESULT_ACCEPTED:
            raise VehicleLinkError(f"the vehicle refused to {what}: "
                                   f"{result_name(acks[0].result)}")

    def _pace(self, time_boot_ms: int, again: bool = False) -> None:
        """Acknowledge the vehicle's time up to ``time_boot_ms`` (and ask for records)."""
        if time_boot_ms < self._acked_ms or (time_boot_ms == self._acked_ms and not again):
            return
        self._acked_ms = time_boot_ms
        p = pace_payload(time_boot_ms)
        with contextlib.suppress(OSError):
            self.conn.mav.tunnel_send(*self.vehicle, PAYLOAD_PACE, len(p), p.ljust(128, b"\0"))

    # ------------------------------------------------------------------ vehicle
    def state(self, agent: int = 0) -> VehicleState:
        assert self.position is not None
        return VehicleState(self.position, self.velocity)

    def segment_done(self, agent: int = 0) -> bool:
        return self._segment_done

    def mission_for(self, traj: Trajectory) -> Mission:
        """The segment as mission items (no take-off, no RTL, a DO_CHANGE_SPEED first)."""
        assert self.home is not None
        m = trajectory_to_mission(traj, tolerance_m=self.link_config.tolerance_m,
                                  takeoff_alt_m=0.0, rtl=False, terrain=self.world.terrain,
                                  home=self.home, name=traj.name)
        items = list(m.items[1:])  # the vehicle is in the air, or takes off by itself
        xy, dt = np.diff(traj.enu_m[:, :2], axis=0), np.diff(traj.t_s)
        ok = dt > 1e-9
        speed = float(np.median(np.hypot(xy[ok, 0], xy[ok, 1]) / dt[ok])) if ok.any() \
            else self.scenario.search.speed_mps
        if math.isfinite(speed) and speed > 0.5:
            items.insert(0, MissionItem(command=mavlink.MAV_CMD_DO_CHANGE_SPEED,
                                        frame=mavlink.MAV_FRAME_MISSION, param1=1.0,
                                        param2=float(speed), param3=-1.0, param4=0.0))
        return replace(m, items=tuple(items))

    def _upload(self, mission: Mission) -> None:
        last: Exception | None = None
        for attempt in range(self.link_config.upload_attempts):
            try:
                upload_on_link(self.link, mission, fence=False)
                self.uploads += 1
                self.upload_retries += attempt
                return
            except MissionRejectedError as exc:
                raise VehicleLinkError(f"the vehicle refused a plan: {exc}") from None
            except UploadError as exc:
                last = exc
        raise VehicleLinkError(f"mission upload failed {self.link_config.upload_attempts} "
                               f"times: {last}")

    def fly(self, agent: int, traj: Trajectory) -> None:
        """Upload ``traj`` as a mission and fly it from where the vehicle is. Before a
        mission is started (the vehicle not flying one) it is armed (idempotent): one that
        disarmed itself on the ground while the loop planned (COM_DISARM_PRFLT runs on the
        wall clock, also while a lockstep vehicle waits) is armed again, and the mission
        made relative to the home that sets."""
        self._pump(0.0)
        if not (self.armed and self.custom_mode == Mode.MISSION.custom_mode):
            self._arm()
        mission = self.mission_for(traj)
        self._upload(mission)
        self._plan_items = len(mission.items)
        self._plan_upload_boot_s = self._boot_s or 0.0
        self._segment_done = False
        if not (self.armed and self.custom_mode == Mode.MISSION.custom_mode):
            self._command(mavlink.MAV_CMD_MISSION_START, 0.0, 0.0, what="start the mission")

    def hold(self, agent: int = 0) -> None:
        main, sub = Mode.LOITER.value
        self._command(mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
                      main, sub, what="hold")
        self._segment_done = True

    def _flight_s(self) -> float:
        assert self._boot_s is not None and self._boot0_s is not None
        return self._boot_s - self._boot0_s

    def advance_to(self, t_s: float) -> list[PhoneBatch]:
        """Let flight time pass to ``t_s`` (the vehicle's clock): acknowledge the time
        processed, read telemetry and records until the vehicle is there (a lockstep
        vehicle: waiting there), then the records complete up to its latest mark."""
        assert self._boot0_s is not None, "start() first"
        target = t_s
        self._pace(self._boot_ms(self.t_s))
        moved = asked = time.monotonic()
        while True:
            self._pump(0.05)
            now = time.monotonic()
            t = self._flight_s()
            there = t >= target - CLOCK_TOLERANCE_S
            p = self.tunnel.pacing
            if p is not None and p.lockstep:
                held_s = p.now_ms / 1000.0 - self._boot0_s
                if p.waiting and held_s < target - CLOCK_TOLERANCE_S \
                        and p.now_ms > self._acked_ms:
                    self._pace(p.now_ms)  # it waits short of the target: go on
                if there and p.waiting and held_s >= target - CLOCK_TOLERANCE_S:
                    break
            elif there:
                break
            t = min(t, target)
            if t > self.t_s:
                self.t_s, moved = t, now
            if now - max(moved, asked) > ACK_AGAIN_S:
                asked = now  # lost on the way? the same again (answered with the pacing)
                self._pace(self._acked_ms, again=True)
                if p is not None and p.waiting and not there:  # where it waits
                    self._send_command(mavlink.MAV_CMD_REQUEST_MESSAGE,
                                       mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT)
            if now - moved > self.link_config.telemetry_timeout_s:
                raise VehicleLinkError("the vehicle's clock stopped (no newer telemetry for "
                                       f"{self.link_config.telemetry_timeout_s:g} s)")
        self.t_s = target
        self._complete_records()
        batch = self.feed.take(self.t_s, self._boot0_s)
        self._write(batch)
        if self.position is not None:
            if self._track:
                self._path_m += math.dist(self.position, self._track[-1])
            self._track.append(self.position)
        return [batch]

    def _complete_records(self) -> None:
        """Ask again for the relayed records missing below the latest mark (a lost
        datagram) for up to RESEND_WAIT_S; those still missing are counted lost."""
        if not self.tunnel.keep_records:
            return
        deadline = time.monotonic() + RESEND_WAIT_S
        asked = -math.inf
        while (missing := self.tunnel.missing()) and time.monotonic() < deadline:
            if time.monotonic() - asked > RESEND_EVERY_S:
                asked = time.monotonic()
                for first, count in _runs(missing):
                    p = resend_payload(first, count)
                    with contextlib.suppress(OSError):
                        self.conn.mav.tunnel_send(*self.vehicle, PAYLOAD_RESEND, len(p),
                                                  p.ljust(128, b"\0"))
                    self.asked_again += count
            self._pump(0.02)
        self.tunnel.settle()

    def _boot_ms(self, flight_s: float) -> int:
        assert self._boot0_s is not None
        return round((self._boot0_s + flight_s) * 1000.0)

    def _write(self, batch: PhoneBatch) -> None:
        if self._writer is not None and batch.records:
            self._writer.write_all(batch.records)
            self._writer.flush()

    def finish(self) -> list[PhoneBatch]:
        """Records up to the end of the flight (plus what was on its way then), logs
        closed; the vehicle is sent home."""
        if self.finished or not self.started:
            self.close()
            return [PhoneBatch(())]
        self.finished = True
        lost = False
        batch = PhoneBatch(())
        try:
            offset = self.feed.clock_offset_s(self._boot0_s)
            end_ns = None if offset is None else (self.t_s + END_DELIVERY_S + offset) * 1e9
            if end_ns is not None:
                # a lockstep vehicle runs on to deliver them
                self._pace(self._boot_ms(self.t_s))
                deadline = time.monotonic() + self.link_config.telemetry_timeout_s
                asked = time.monotonic()
                try:
                    while (now := time.monotonic()) < deadline:
                        self.feed.pull()
                        got = self.feed.wanted_through_ns()
                        if got is not None and got >= end_ns:
                            break
                        self._pump(0.05)
                        p = self.tunnel.pacing
                        if p is not None and p.waiting and p.now_ms > self._acked_ms:
                            self._pace(p.now_ms)
                            asked = now
                        elif now - asked > ACK_AGAIN_S:  # a lost pacing or acknowledgement
                            asked = now
                            self._pace(self._acked_ms, again=True)
                except VehicleLinkError:
                    lost = True
                self._complete_records()
                batch = self.feed.final(end_ns, self._boot0_s)
                self._write(batch)
            if self.link_config.return_at_end and self.armed and not lost:
                self._command(mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH, what="return")
        finally:
            self.close()
        return [batch]

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        self._stop_keepalive.set()
        if self._keepalive is not threading.current_thread():
            self._keepalive.join()
        if self._writer is not None:
            self._writer.close()
            self._writer = None
        self.feed.close()
        with contextlib.suppress(ValueError):
            self.conn.message_hooks.remove(self._on_message)
        self.link.close()

    def phone_stats(self) -> dict:
        """The record path's counts (the report's ``phone`` entry)."""
        d = self.feed.stats.to_json()
        d["source"] = {TunnelRecords: "relay", FileRecords: "vehicle-log",
                       UdpRecords: "phone"}.get(type(self.feed.source), "other")
        if self.feed.source is self.tunnel:
            d["asked_again"] = self.asked_again
        return d

    # ------------------------------------------------------------------ evaluation
    @property
    def path_length_m(self) -> float:
        """The reported (navigation) track's length: the truth is not seen."""
        return self._path_m

    def true_tracks(self) -> list[np.ndarray]:
        """Over MAVLink the truth of the path is not seen: the reported track stands in."""
        return [np.array(self._track) if self._track else np.zeros((0, 3))]
