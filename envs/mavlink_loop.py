"""The closed loop over MAVLink: the same policies, flying a vehicle through its autopilot.

:class:`MavlinkLoop` offers the interface of :class:`envs.loop.ClosedLoop`
(``observe()``, ``apply(decision)``, ``advance(dt)``, ``finish()``) with the vehicle
behind a MAVLink link (``osa vehicle``, or an autopilot) instead of the in-process
stepper. It runs where the phone would run:

- **positions from telemetry**: GLOBAL_POSITION_INT (the autopilot's estimate) and
  its velocity; flight time is the vehicle's ``time_boot_ms`` since the start;
- **ranges from the phone**: the phone's records are read from the flight log the
  vehicle process writes (``osa vehicle --log FILE``, flushed line by line), tailed
  as it grows. The vehicle owns the simulated radio, the log is the contract between
  phone and estimator (docs/log-format.md), and a file needs no second protocol. The
  lines are slightly out of ``t_ns`` order (as a phone writes them): they are held
  ``release_lag_s`` and fed in the order a replay of the log reads them, and copied
  to the loop's own ``flight.jsonl``, so ``osa replay`` of it gives the report's
  estimates. The log's header and truth records must be those of the loop's scenario
  and seed (checked: the same world);
- **plans as missions**: each new segment becomes NAV_WAYPOINT items (the
  Douglas-Peucker decimation of ``osa plan``, heights above the terrain converted to
  altitudes above the vehicle's home, a DO_CHANGE_SPEED for the segment's speed,
  no take-off item), uploaded with read-back (:func:`planner.mavlink.upload_on_link`)
  and flown at once: a vehicle in AUTO.MISSION switches to a new mission from where
  it is, without stopping; otherwise MAV_CMD_MISSION_START. A refused segment (it
  would leave the area) makes the vehicle hold (AUTO.LOITER).

Every wait is bounded: uploads are retried ``upload_attempts`` times, commands
``command_attempts`` times, and no telemetry for ``telemetry_timeout_s`` ends the run
with :class:`VehicleLinkError` (one line). At the end the vehicle is sent home (RTL).
"""

from __future__ import annotations

import heapq
import math
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from envs.loop import LoopConfig, SearchLoopBase, SearchResult, drive, result_of
from envs.vehicle.telemetry import VEHICLE_TAG, world_fingerprint
from estimator.logio import LogWriter, RejectCounts, parse_line
from estimator.records import GnssFix, LogHeader, RangeSample, Trajectory, TruthRecord
from planner.convert import trajectory_to_mission
from planner.mavlink import PymavlinkLink, TransferConfig, upload_on_link
from planner.mavlink_wire import MissionRejectedError, UploadError
from planner.mission import MAV_CMD_DO_CHANGE_SPEED, Mission, MissionItem
from planner.observation import AgentView, Decision, Observation, Policy
from sim.realisation import Realisation
from sim.scenario import Scenario

MAV_CMD_NAV_RETURN_TO_LAUNCH = 20
MAV_CMD_DO_SET_MODE = 176
MAV_CMD_MISSION_START = 300
MAV_CMD_COMPONENT_ARM_DISARM = 400
PX4_LOITER = (4, 3)  # AUTO.LOITER (main, sub)
PX4_MISSION_MODE = 0x04040000
MISSION_STATE_COMPLETE = 5
END_DELIVERY_S = 0.5  # records delivered this long after the end still belong to it
_RESULTS = {0: "ACCEPTED", 1: "TEMPORARILY_REJECTED", 2: "DENIED", 3: "UNSUPPORTED",
            4: "FAILED", 5: "IN_PROGRESS"}


class VehicleLinkError(RuntimeError):
    """The loop lost or could not use the vehicle (one line, for ``osa search``)."""


@dataclass(frozen=True, kw_only=True)
class LinkLoopConfig:
    """Bounds and choices of the loop over MAVLink (wall-clock seconds)."""

    connect_timeout_s: float = 10.0  # the vehicle's heartbeat, the log's header
    telemetry_timeout_s: float = 5.0  # no message from the vehicle this long: lost
    command_timeout_s: float = 1.0  # per COMMAND_LONG attempt
    command_attempts: int = 3
    upload_attempts: int = 3  # a whole mission transfer (each message is retried too)
    message_timeout_s: float = 0.5
    retries: int = 5
    release_lag_s: float = 2.0  # records are fed this far behind the newest one
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


class LogTail:
    """The records of a flight log that is still being written, line by line."""

    def __init__(self, path: str | os.PathLike, timeout_s: float) -> None:
        self.path = Path(path)
        if self.path.suffix == ".gz":
            raise VehicleLinkError(f"{self.path}: a gzip log cannot be read while it is "
                                   "written; give osa vehicle a .jsonl --log")
        self.counts = RejectCounts()
        deadline = time.monotonic() + timeout_s
        while not self.path.is_file():
            if time.monotonic() > deadline:
                raise VehicleLinkError(f"no vehicle log {self.path} (osa vehicle --log FILE)")
            time.sleep(0.05)
        self._fh = open(self.path, "rb")  # noqa: SIM115 - closed in close()
        self._buf = b""
        self.header: LogHeader | None = None
        self.truth: list[TruthRecord] = []
        while self.header is None or not self.truth:
            for rec in self.read():
                if isinstance(rec, LogHeader):
                    self.header = rec
                elif isinstance(rec, TruthRecord):
                    self.truth.append(rec)
            if self.header is not None and self.truth:
                break
            if time.monotonic() > deadline:
                what = "header" if self.header is None else "truth records"
                raise VehicleLinkError(f"{self.path}: no {what} (is it osa vehicle's --log?)")
            time.sleep(0.05)
        self._pending: list[GnssFix | RangeSample] = []

    def read(self) -> list[Any]:
        """New complete lines since the last call, parsed (bad lines are counted)."""
        data = self._fh.read()
        if not data:
            return []
        data = self._buf + data
        lines = data.split(b"\n")
        self._buf = lines.pop()
        out = []
        for line in lines:
            rec = parse_line(line, self.counts)
            if rec is not None:
                out.append(rec)
        return out

    def skip(self) -> int | None:
        """Drop what the log holds now (records of before the search); the newest t_ns."""
        newest = None
        for rec in self.read():
            if isinstance(rec, TruthRecord):
                self.truth.append(rec)
            elif hasattr(rec, "t_ns"):
                newest = rec.t_ns if newest is None else max(newest, rec.t_ns)
        return newest

    def close(self) -> None:
        self._fh.close()


class MavlinkLoop(SearchLoopBase):
    """One search flown over MAVLink (see the module docstring)."""

    def __init__(self, scenario: Scenario, seed: Any, url: str, vehicle_log: str | os.PathLike,
                 *, config: LoopConfig = LoopConfig(), link: LinkLoopConfig = LinkLoopConfig(),
                 log_paths: Sequence[str | os.PathLike] | None = None,
                 realisation: Realisation | None = None) -> None:
        if scenario.search is not None and len(scenario.agents) != 1:
            raise ValueError(f"scenario {scenario.name} has {len(scenario.agents)} agents: "
                             "the loop over MAVLink flies one vehicle")
        self._init_search(scenario, seed, realisation, config, ())
        self.link_config = link
        self.tail = LogTail(vehicle_log, link.connect_timeout_s)
        self._check_world(self.tail.truth)
        header = self.tail.header
        assert header is not None
        header = replace(header, agl_m=scenario.search.height_m)
        self.estimator.add_agent(header.agent, header=header)
        self.log_paths = [Path(p) for p in log_paths] if log_paths else []
        self._writer: LogWriter | None = None
        if self.log_paths:
            self._writer = LogWriter(self.log_paths[0], header)
            self._writer.write_all(self.realisation.truth_records())
        try:
            self.link = PymavlinkLink(pymavlink_url(url), link.transfer)
        except BaseException:
            self._close_files()
            raise
        self.conn = self.link.connection
        self.vehicle = self.link.vehicle
        self.t_s = 0.0
        self._boot0_s: float | None = None
        self._boot_s: float | None = None
        self._last_rx = time.monotonic()
        self._last_hb = 0.0
        self.position: tuple[float, float, float] | None = None
        self.velocity = (0.0, 0.0, 0.0)
        self.custom_mode = 0
        self.armed = False
        self.mission_state: tuple[int, int, int] | None = None
        self.home: tuple[float, float, float] | None = None
        self._plan_items = 0
        self._plan_upload_boot_s = -math.inf
        self._segment_done = True
        self._refused = False
        self._heap: list[tuple[int, int, GnssFix | RangeSample]] = []
        self._n = 0
        self._newest_ns: int | None = None
        self._t_ns0: int | None = None
        self._end_ns = math.inf
        self._fix_enu: tuple[float, float, float] | None = None
        self._path_m = 0.0
        self._last_pos: tuple[float, float, float] | None = None
        self.uploads = 0
        self.upload_retries = 0
        self.nav_track: list[list[tuple[float, float, float, float]]] = [[]]

    # ------------------------------------------------------------------ setup
    def _check_world(self, truth: Sequence[TruthRecord]) -> None:
        def key(ts) -> list:
            return sorted((t.bssid, round(t.lat_deg, 7), round(t.lon_deg, 7)) for t in ts)

        mine, theirs = key(self.truth.values()), key(truth)
        if mine != theirs:
            raise VehicleLinkError(
                f"the vehicle's log {self.tail.path} is not the world of {self.scenario.name} "
                f"seed {self.seed} (run osa vehicle on the same scenario and --seed)")

    def start(self) -> None:
        """Check the vehicle's world, wait for telemetry and home, arm; flight time
        starts now."""
        deadline = time.monotonic() + self.link_config.connect_timeout_s
        self._check_fingerprint(deadline)
        asked = -math.inf
        while self.position is None or self.home is None or self._boot_s is None:
            if time.monotonic() > deadline:
                raise VehicleLinkError("no position or home from the vehicle within "
                                       f"{self.link_config.connect_timeout_s:g} s")
            if self.home is None and time.monotonic() - asked > 0.5:
                asked = time.monotonic()  # MAV_CMD_GET_HOME_POSITION
                self.conn.mav.command_long_send(*self.vehicle, 410, 0, 0, 0, 0, 0, 0, 0, 0)
            self._pump(0.1)
        newest = self.tail.skip()
        self._t_ns0 = newest
        self._boot0_s = self._boot_s
        self._command(MAV_CMD_COMPONENT_ARM_DISARM, 1.0, what="arm")
        self._last_pos = self.position

    def _check_fingerprint(self, deadline: float) -> None:
        """``osa vehicle`` puts its world's fingerprint in AUTOPILOT_VERSION.uid: it
        must be this loop's scenario and seed (another autopilot is not checked)."""
        asked = -math.inf
        while time.monotonic() < deadline:
            if time.monotonic() - asked > 0.5:
                asked = time.monotonic()  # MAV_CMD_REQUEST_MESSAGE AUTOPILOT_VERSION
                self.conn.mav.command_long_send(*self.vehicle, 512, 0, 148, 0, 0, 0, 0, 0, 0)
            for m in self._pump(0.1):
                if m.get_type() != "AUTOPILOT_VERSION":
                    continue
                if bytes(m.flight_custom_version).rstrip(b"\0") != VEHICLE_TAG:
                    return
                if int(m.uid) != world_fingerprint(self.realisation):
                    raise VehicleLinkError(
                        f"the vehicle flies another world than {self.scenario.name} seed "
                        f"{self.seed} (run osa vehicle on the same scenario and --seed)")
                return
        raise VehicleLinkError("no AUTOPILOT_VERSION from the vehicle")

    # ------------------------------------------------------------------ MAVLink in
    def _heartbeat(self) -> None:
        now = time.monotonic()
        if now - self._last_hb >= 1.0:
            self._last_hb = now
            self.conn.mav.heartbeat_send(6, 8, 0, 0, 0)

    def _pump(self, timeout_s: float) -> list[Any]:
        """Read what the vehicle sent (waiting up to ``timeout_s`` for the first)."""
        self._heartbeat()
        out = []
        msg = self.conn.recv_match(blocking=timeout_s > 0, timeout=max(timeout_s, 0.0))
        while msg is not None:
            out.append(msg)
            self._on_message(msg)
            msg = self.conn.recv_match(blocking=False)
        if out:
            self._last_rx = time.monotonic()
        elif time.monotonic() - self._last_rx > self.link_config.telemetry_timeout_s:
            raise VehicleLinkError(f"no telemetry from the vehicle for "
                                   f"{self.link_config.telemetry_timeout_s:g} s")
        return out

    def _on_message(self, m: Any) -> None:
        if (m.get_srcSystem(), m.get_srcComponent()) != tuple(self.vehicle):
            return
        kind = m.get_type()
        if kind == "GLOBAL_POSITION_INT":
            e, n, u = self.world.frame.to_enu(m.lat / 1e7, m.lon / 1e7, m.alt / 1e3)
            self.position = (float(e), float(n), float(u))
            self.velocity = (m.vy / 100.0, m.vx / 100.0, -m.vz / 100.0)
            self._boot_s = m.time_boot_ms / 1000.0
        elif kind == "HEARTBEAT":
            self.custom_mode = int(m.custom_mode)
            self.armed = bool(m.base_mode & 128)
        elif kind == "MISSION_CURRENT":
            self.mission_state = (int(m.seq), int(m.total), int(getattr(m, "mission_state", 0)))
            if (self._boot_s is not None and self._boot_s > self._plan_upload_boot_s
                    and m.total == self._plan_items and self.mission_state[2] ==
                    MISSION_STATE_COMPLETE):
                self._segment_done = True
        elif kind == "MISSION_ITEM_REACHED":
            if self._plan_items and m.seq == self._plan_items - 1 \
                    and self._boot_s is not None and self._boot_s > self._plan_upload_boot_s:
                self._segment_done = True
        elif kind == "HOME_POSITION":
            self.home = (m.latitude / 1e7, m.longitude / 1e7, m.altitude / 1e3)
        elif kind == "ATTITUDE":
            self._boot_s = max(self._boot_s or 0.0, m.time_boot_ms / 1000.0)

    def _command(self, command: int, *params: float, what: str) -> None:
        p = [float(x) for x in params] + [0.0] * (7 - len(params))
        cfg = self.link_config
        for attempt in range(cfg.command_attempts):
            self.conn.mav.command_long_send(*self.vehicle, command, attempt, *p)
            deadline = time.monotonic() + cfg.command_timeout_s
            while time.monotonic() < deadline:
                for m in self._pump(0.05):
                    if m.get_type() == "COMMAND_ACK" and m.command == command:
                        if m.result != 0:
                            raise VehicleLinkError(
                                f"the vehicle refused to {what}: "
                                f"{_RESULTS.get(m.result, m.result)}")
                        return
        raise VehicleLinkError(f"no answer to {what} after {cfg.command_attempts} attempts")

    # ------------------------------------------------------------------ records
    def _ingest(self, final: bool = False) -> None:
        for rec in self.tail.read():
            if isinstance(rec, GnssFix | RangeSample):
                heapq.heappush(self._heap, (rec.t_ns, self._n, rec))
                self._n += 1
                self._newest_ns = rec.t_ns if self._newest_ns is None \
                    else max(self._newest_ns, rec.t_ns)
        if self._newest_ns is None:
            return
        limit = self._end_ns if final else self._newest_ns - self.link_config.release_lag_s * 1e9
        est = self.estimator
        last = None
        while self._heap and self._heap[0][0] <= limit:
            t_ns, _, rec = heapq.heappop(self._heap)
            if self._t_ns0 is None:
                self._t_ns0 = t_ns
            est.push(rec, 0)
            if self._writer is not None:
                self._writer.write(rec)
            last = t_ns
            if isinstance(rec, GnssFix):
                e, n, u = self.world.frame.to_enu(rec.lat_deg, rec.lon_deg, rec.alt_m)
                self._fix_enu = (float(e), float(n), float(u))
            elif rec.ok and self._fix_enu is not None:
                self._hear(rec.bssid, (t_ns - self._t_ns0) / 1e9, self._fix_enu, rec.range_m)
        if last is not None:
            est.mark_time(0, last)
            if self._writer is not None:
                self._writer.flush()

    # ------------------------------------------------------------------ observe
    def observe(self) -> Observation:
        """What a policy may see now: telemetry and the estimator (no truth)."""
        assert self.position is not None
        agent = AgentView(position_enu_m=self.position, velocity_enu_mps=self.velocity,
                          segment_done=self._segment_done or self._refused)
        return Observation(t_s=self.t_s, budget_s=self.mission.budget_s, agents=(agent,),
                           responders=self.responder_views())

    # ------------------------------------------------------------------ act
    def plan_inside(self, traj: Trajectory) -> bool:
        if tuple(traj.origin) != tuple(self.mission.origin):
            return False
        assert self.position is not None
        here = np.asarray(self.position[:2])[None, :]
        return self.mission.area.path_inside(np.vstack([here, traj.enu_m[:, :2]]), 0.0)

    def mission_for(self, traj: Trajectory) -> Mission:
        """The segment as mission items (no take-off, no RTL, a DO_CHANGE_SPEED first)."""
        assert self.home is not None
        m = trajectory_to_mission(traj, tolerance_m=self.link_config.tolerance_m,
                                  takeoff_alt_m=0.0, rtl=False, terrain=self.mission.terrain,
                                  home=self.home, name=traj.name)
        items = list(m.items[1:])  # the vehicle is in the air, or takes off by itself
        xy, dt = np.diff(traj.enu_m[:, :2], axis=0), np.diff(traj.t_s)
        ok = dt > 1e-9
        speed = float(np.median(np.hypot(xy[ok, 0], xy[ok, 1]) / dt[ok])) if ok.any() \
            else self.mission.speed_mps
        if math.isfinite(speed) and speed > 0.5:
            items.insert(0, MissionItem(command=MAV_CMD_DO_CHANGE_SPEED, frame=2,
                                        param1=1.0, param2=float(speed), param3=-1.0,
                                        param4=0.0))
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

    def apply(self, decision: Decision) -> None:
        """Upload the decision's new segment and fly it (or hold if it leaves the area)."""
        self._note(decision)
        traj = decision.plans.get(0)
        if traj is None:
            return
        if not self.plan_inside(traj):
            self.refused_plans += 1
            self._refused = True
            self._command(MAV_CMD_DO_SET_MODE, 1.0, *PX4_LOITER, what="hold")
            return
        self._refused = False
        mission = self.mission_for(traj)
        self._upload(mission)
        self._plan_items = len(mission.items)
        self._plan_upload_boot_s = self._boot_s or 0.0
        self._segment_done = False
        if not (self.armed and self.custom_mode == PX4_MISSION_MODE):
            self._command(MAV_CMD_MISSION_START, 0.0, 0.0, what="start the mission")

    # ------------------------------------------------------------------ advance
    def advance(self, dt_s: float) -> None:
        """Let ``dt_s`` of flight pass (the vehicle's clock), reading telemetry and the log."""
        target = min(self.t_s + dt_s, self.mission.budget_s)
        moved = time.monotonic()
        while self.t_s < target - 1e-9:
            self._pump(0.05)
            self._ingest()
            if self._boot_s is not None and self._boot0_s is not None:
                t = min(self._boot_s - self._boot0_s, target)
                if t > self.t_s:
                    self.t_s, moved = t, time.monotonic()
            if time.monotonic() - moved > self.link_config.telemetry_timeout_s:
                raise VehicleLinkError("the vehicle's clock stopped (no newer telemetry for "
                                       f"{self.link_config.telemetry_timeout_s:g} s)")
        self._ingest()
        if self.position is not None:
            if self._last_pos is not None:
                self._path_m += math.dist(self.position, self._last_pos)
            self._last_pos = self.position
            self.nav_track[0].append((self.t_s, *self.position))
        self._sample_series()

    def finish(self) -> None:
        """Feed what the log still holds, close the logs; send the vehicle home."""
        if self.finished:
            return
        self.finished = True
        lost = False
        try:
            # records up to the end of the flight (plus what was on its way then), not
            # of what the vehicle flies after it: wait until the log holds them all
            t0 = self._t_ns0 if self._t_ns0 is not None else 0
            self._end_ns = t0 + int((self.t_s + END_DELIVERY_S) * 1e9)
            end_wanted = self._end_ns + int(self.link_config.release_lag_s * 1e9)
            deadline = time.monotonic() + self.link_config.telemetry_timeout_s
            try:
                while time.monotonic() < deadline and (self._newest_ns or 0) < end_wanted:
                    self._pump(0.05)
                    self._ingest()
            except VehicleLinkError:
                lost = True
            self._ingest(final=True)
            self._heap.clear()
            self.estimator.finish()
            self._sample_series()
            if self.link_config.return_at_end and self.armed and not lost:
                self._command(MAV_CMD_NAV_RETURN_TO_LAUNCH, what="return")
        finally:
            self._close_files()
            self.link.close()

    def _close_files(self) -> None:
        if self._writer is not None:
            self._writer.close()
            self._writer = None
        self.tail.close()

    # ------------------------------------------------------------------ outcome
    @property
    def path_length_m(self) -> float:
        return self._path_m

    def true_tracks(self) -> list[np.ndarray]:
        """Over MAVLink the truth of the path is not seen: the reported track stands in."""
        trk = self.nav_track[0]
        return [np.array([p[1:] for p in trk]) if trk else np.zeros((0, 3))]


def run_search_mavlink(
    scenario: Scenario,
    policy: Policy,
    url: str,
    vehicle_log: str | os.PathLike,
    seed: Any = 0,
    *,
    config: LoopConfig = LoopConfig(),
    link: LinkLoopConfig = LinkLoopConfig(),
    log_paths: Sequence[str | os.PathLike] | None = None,
    progress: Callable[[float, str], None] | None = None,
    policy_rng: np.random.Generator | None = None,
) -> SearchResult:
    """:func:`envs.loop.run_search` over MAVLink: the same driver, the same report."""
    loop = MavlinkLoop(scenario, seed, url, vehicle_log, config=config, link=link,
                       log_paths=log_paths)
    try:
        loop.start()
        ended = drive(loop, policy, config, progress, policy_rng)
    finally:
        loop.finish()
    return result_of(loop, policy.name, ended)
