"""Telemetry: the messages the vehicle publishes, built from the autopilot's state.

Default rates are PX4's "normal" MAVLink mode (GLOBAL_POSITION_INT 5 Hz, ATTITUDE
10 Hz, VFR_HUD 4 Hz, GPS_RAW_INT / SYS_STATUS / EXTENDED_SYS_STATE / MISSION_CURRENT /
ALTITUDE / LOCAL_POSITION_NED 1 Hz, HOME_POSITION and BATTERY_STATUS 0.5 Hz;
TERRAIN_REPORT for its own position 1 Hz, as ArduPilot; GPS_GLOBAL_ORIGIN 0.1 Hz: the
local frame of LOCAL_POSITION_NED and HOME_POSITION is the world's ENU frame, as NED),
on the simulated clock (as PX4 SITL with a speed factor). Each link has its own
:class:`Streams` (as PX4 keeps rates per MAVLink instance, ArduPilot per serial port):
MAV_CMD_SET_MESSAGE_INTERVAL changes them for the link that asked only (also simulated
time; ATTITUDE_QUATERNION is off until asked for, as in PX4's normal mode), a new link
starts at the defaults, and MAV_CMD_REQUEST_MESSAGE sends one now. A stream is sent at most
once per simulation step (0.2 s of simulated time up to a speed-up of 10, then up to
1 s from 50x), so a faster stream is thinned to the step rate. HEARTBEAT goes at 1 Hz
of wall time (it keeps ground stations' links alive whatever the speed-up) and at once
on a change of mode or arming.
"""

from __future__ import annotations

import hashlib
import math
import struct
from dataclasses import dataclass, field
from typing import ClassVar

from pymavlink.dialects.v20.common import (
    MAV_AUTOPILOT_PX4,
    MAV_STATE_ACTIVE,
    MAV_STATE_STANDBY,
    MAV_TYPE_QUADROTOR,
    MAVLINK_MSG_ID_ALTITUDE,
    MAVLINK_MSG_ID_ATTITUDE,
    MAVLINK_MSG_ID_ATTITUDE_QUATERNION,
    MAVLINK_MSG_ID_AUTOPILOT_VERSION,
    MAVLINK_MSG_ID_BATTERY_STATUS,
    MAVLINK_MSG_ID_EXTENDED_SYS_STATE,
    MAVLINK_MSG_ID_GLOBAL_POSITION_INT,
    MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN,
    MAVLINK_MSG_ID_GPS_RAW_INT,
    MAVLINK_MSG_ID_HEARTBEAT,
    MAVLINK_MSG_ID_HOME_POSITION,
    MAVLINK_MSG_ID_LOCAL_POSITION_NED,
    MAVLINK_MSG_ID_MISSION_CURRENT,
    MAVLINK_MSG_ID_SYS_STATUS,
    MAVLINK_MSG_ID_TERRAIN_REPORT,
    MAVLINK_MSG_ID_VFR_HUD,
)

from envs.vehicle.autopilot import Autopilot
from envs.vehicle.px4 import Mode, base_mode
from envs.vehicle.terrain import TerrainReport
from estimator.records import GnssFix
from planner.mavlink import mavutil
from planner.mission import deg_to_e7
from sim.realisation import Realisation

mavlink = mavutil.mavlink

MAVLINK_MSG_ID_PROTOCOL_VERSION = 300  # minimal.xml; not in pymavlink 2.4's dialects


class ProtocolVersionMessage(mavlink.MAVLink_message):
    """PROTOCOL_VERSION (300, MAVLink 2 only; pymavlink's common dialect lacks it): the
    versions spoken, for the handshake of MAV_CMD_REQUEST_PROTOCOL_VERSION / REQUEST_MESSAGE
    (every node should answer it, the MAVLink specification says). Hashes of the
    definitions are zeros (unknown)."""

    id = MAVLINK_MSG_ID_PROTOCOL_VERSION
    msgname = "PROTOCOL_VERSION"
    fieldnames: ClassVar[list[str]] = ["version", "min_version", "max_version",
                                       "spec_version_hash", "library_version_hash"]
    CRC_EXTRA = 217  # of the message definition (minimal.xml)

    def __init__(self, version: int = 200, min_version: int = 100,
                 max_version: int = 200) -> None:
        super().__init__(self.id, self.msgname)
        self._fieldnames = self.fieldnames
        self.version, self.min_version, self.max_version = version, min_version, max_version
        self.spec_version_hash = self.library_version_hash = bytes(8)

    def pack(self, mav: object, force_mavlink1: bool = False) -> bytes:
        payload = struct.pack("<HHH8s8s", self.version, self.min_version, self.max_version,
                              self.spec_version_hash, self.library_version_hash)
        return self._pack(mav, self.CRC_EXTRA, payload, force_mavlink1=force_mavlink1)


# message id -> default rate (Hz of simulated time)
DEFAULT_RATES_HZ = {
    MAVLINK_MSG_ID_GLOBAL_POSITION_INT: 5.0,
    MAVLINK_MSG_ID_ATTITUDE: 10.0,
    MAVLINK_MSG_ID_VFR_HUD: 4.0,
    MAVLINK_MSG_ID_GPS_RAW_INT: 1.0,
    MAVLINK_MSG_ID_SYS_STATUS: 1.0,
    MAVLINK_MSG_ID_EXTENDED_SYS_STATE: 1.0,
    MAVLINK_MSG_ID_MISSION_CURRENT: 1.0,
    MAVLINK_MSG_ID_HOME_POSITION: 0.5,
    MAVLINK_MSG_ID_BATTERY_STATUS: 0.5,
    MAVLINK_MSG_ID_TERRAIN_REPORT: 1.0,
    MAVLINK_MSG_ID_ALTITUDE: 1.0,
    MAVLINK_MSG_ID_LOCAL_POSITION_NED: 1.0,
    MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN: 0.1,
}
# streams a ground station may turn on (SET_MESSAGE_INTERVAL), off by default as in
# PX4's normal mode (MAVSDK's Telemetry.set_rate_attitude_quaternion)
OFF_BY_DEFAULT = frozenset({MAVLINK_MSG_ID_ATTITUDE_QUATERNION})
STREAMABLE = frozenset({*DEFAULT_RATES_HZ, *OFF_BY_DEFAULT})
REQUESTABLE = frozenset({*STREAMABLE, MAVLINK_MSG_ID_HEARTBEAT,
                         MAVLINK_MSG_ID_AUTOPILOT_VERSION, MAVLINK_MSG_ID_PROTOCOL_VERSION})
NO_MISSION_TOTAL = 0xFFFF  # MISSION_CURRENT.total without a mission (MAVLink)
UNKNOWN_TERRAIN_M = -1001.0  # ALTITUDE.altitude_terrain below -1000: unknown

CAPABILITIES = (
    mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_FLOAT
    | mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_INT
    | mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
    | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
    | mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
    | mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_FENCE
    | mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_RALLY
    | mavlink.MAV_PROTOCOL_CAPABILITY_TERRAIN
)
FLIGHT_SW_VERSION = (1 << 24) | (14 << 16) | (0 << 8) | 255  # "PX4 1.14.0, official"
VEHICLE_TAG = b"osa-veh"  # AUTOPILOT_VERSION.flight_custom_version of this vehicle


def world_fingerprint(realisation: Realisation) -> int:
    """A 64-bit fingerprint of a realised world (scenario, seed, responders), sent as
    AUTOPILOT_VERSION.uid, so a loop can check it flies the world it simulates."""
    sc = realisation.scenario
    truth = ";".join(f"{t.bssid},{t.lat_deg:.7f},{t.lon_deg:.7f}"
                     for t in realisation.truth_records())
    seq = realisation.seed
    text = f"{sc.name}|{seq.entropy}|{tuple(seq.spawn_key)}|{truth}"
    return int.from_bytes(hashlib.blake2b(text.encode(), digest_size=8).digest(), "little")
# sensors a PX4 quadrotor reports present, enabled and healthy
_SENSORS = (
    mavlink.MAV_SYS_STATUS_SENSOR_3D_GYRO | mavlink.MAV_SYS_STATUS_SENSOR_3D_ACCEL
    | mavlink.MAV_SYS_STATUS_SENSOR_3D_MAG | mavlink.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE
    | mavlink.MAV_SYS_STATUS_SENSOR_GPS | mavlink.MAV_SYS_STATUS_SENSOR_ANGULAR_RATE_CONTROL
    | mavlink.MAV_SYS_STATUS_SENSOR_ATTITUDE_STABILIZATION
    | mavlink.MAV_SYS_STATUS_SENSOR_YAW_POSITION
    | mavlink.MAV_SYS_STATUS_SENSOR_Z_ALTITUDE_CONTROL
    | mavlink.MAV_SYS_STATUS_SENSOR_XY_POSITION_CONTROL | mavlink.MAV_SYS_STATUS_AHRS
    | mavlink.MAV_SYS_STATUS_SENSOR_BATTERY | mavlink.MAV_SYS_STATUS_PREARM_CHECK
)
_FIX_TYPES = {"none": mavlink.GPS_FIX_TYPE_NO_FIX, "2d": mavlink.GPS_FIX_TYPE_2D_FIX,
              "3d": mavlink.GPS_FIX_TYPE_3D_FIX, "dgps": mavlink.GPS_FIX_TYPE_DGPS,
              "rtk_float": mavlink.GPS_FIX_TYPE_RTK_FLOAT,
              "rtk_fixed": mavlink.GPS_FIX_TYPE_RTK_FIXED}
ENDURANCE_S = 40 * 60.0  # battery: linear drain over 40 min of flight (no failsafe)
GRAVITY = 9.80665


def _quaternion(roll: float, pitch: float, yaw: float) -> tuple[float, float, float, float]:
    """(w, x, y, z) of the body-to-NED rotation of ZYX Euler angles (rad), as
    ATTITUDE_QUATERNION carries it."""
    cr, sr = math.cos(roll / 2.0), math.sin(roll / 2.0)
    cp, sp = math.cos(pitch / 2.0), math.sin(pitch / 2.0)
    cy, sy = math.cos(yaw / 2.0), math.sin(yaw / 2.0)
    return (cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy)


def _wrap_pi(a: float) -> float:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


def _default_interval_s(msg_id: int) -> float:
    """A stream's default interval (simulated seconds; inf: off)."""
    rate = DEFAULT_RATES_HZ.get(msg_id)
    return 1.0 / rate if rate else math.inf


@dataclass
class Streams:
    """Which messages stream at which interval (simulated seconds) and when next, on
    one link."""

    interval_s: dict[int, float] = field(
        default_factory=lambda: {k: _default_interval_s(k)
                                 for k in (*DEFAULT_RATES_HZ, *sorted(OFF_BY_DEFAULT))})
    next_s: dict[int, float] = field(default_factory=dict)

    def set_interval(self, msg_id: int, interval_us: float) -> bool:
        """MAV_CMD_SET_MESSAGE_INTERVAL: -1 stops, 0 restores the default."""
        if msg_id not in STREAMABLE:
            return False
        if interval_us < 0:
            self.interval_s[msg_id] = math.inf
        elif interval_us == 0:
            self.interval_s[msg_id] = _default_interval_s(msg_id)
        else:
            self.interval_s[msg_id] = max(interval_us * 1e-6, 1e-3)
        self.next_s.pop(msg_id, None)
        return True

    def interval_us(self, msg_id: int) -> int:
        v = self.interval_s.get(msg_id)
        if v is None:
            return 0
        return -1 if math.isinf(v) else round(v * 1e6)

    def due(self, t_s: float) -> list[int]:
        out = []
        for msg_id, dt in self.interval_s.items():
            if math.isinf(dt):
                continue
            nxt = self.next_s.get(msg_id, t_s)
            if t_s + 1e-9 >= nxt:
                out.append(msg_id)
                nxt += dt
                self.next_s[msg_id] = nxt if nxt > t_s else t_s + dt
        return out


class Telemetry:
    """Builds telemetry messages (pymavlink message objects) for ``autopilot``."""

    def __init__(self, autopilot: Autopilot) -> None:
        self.ap = autopilot
        self.last_fix: GnssFix | None = None
        self.streams: dict[int, Streams] = {}  # per link id (envs.vehicle.links)
        self.fingerprint = world_fingerprint(autopilot.stepper.realisation)

    def streams_of(self, link: int) -> Streams:
        """The streams of link ``link`` (a new link: the defaults)."""
        st = self.streams.get(link)
        if st is None:
            st = self.streams[link] = Streams()
        return st

    def forget(self, link: int) -> None:
        """Link ``link`` is gone: its rates with it."""
        self.streams.pop(link, None)

    def _time_ms(self) -> int:
        return int(self.ap.t_s * 1000.0) & 0xFFFFFFFF

    def heartbeat(self) -> object:
        ap = self.ap
        status = MAV_STATE_ACTIVE if ap.armed else MAV_STATE_STANDBY
        return mavlink.MAVLink_heartbeat_message(
            MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_PX4, base_mode(ap.mode, ap.armed),
            ap.mode.custom_mode, status, 3)

    def build(self, msg_id: int) -> object | None:
        """The message ``msg_id`` now, or None if there is nothing to say yet."""
        ap = self.ap
        if msg_id == MAVLINK_MSG_ID_HEARTBEAT:
            return self.heartbeat()
        if msg_id == MAVLINK_MSG_ID_GLOBAL_POSITION_INT:
            p, v = ap.position, ap.velocity
            lat, lon, alt = ap.geodetic(p)
            hdg = self._heading_deg()
            return mavlink.MAVLink_global_position_int_message(
                self._time_ms(), deg_to_e7(lat), deg_to_e7(lon), round(alt * 1000.0),
                round((p[2] - ap.home.enu[2]) * 1000.0),
                _cms(v[1]), _cms(v[0]), _cms(-v[2]), round(hdg * 100.0) % 36000)
        if msg_id == MAVLINK_MSG_ID_ATTITUDE_QUATERNION:
            q = _quaternion(*self._attitude())
            return mavlink.MAVLink_attitude_quaternion_message(self._time_ms(), *q, 0.0, 0.0,
                                                               0.0)
        if msg_id == MAVLINK_MSG_ID_ATTITUDE:
            roll, pitch, yaw = self._attitude()
            return mavlink.MAVLink_attitude_message(self._time_ms(), roll, pitch, yaw,
                                                    0.0, 0.0, 0.0)
        if msg_id == MAVLINK_MSG_ID_GPS_RAW_INT:
            return self._gps_raw()
        if msg_id == MAVLINK_MSG_ID_SYS_STATUS:
            enabled = _SENSORS | (mavlink.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS if ap.armed else 0)
            if not ap.fence.empty:
                enabled |= mavlink.MAV_SYS_STATUS_GEOFENCE
            present = _SENSORS | mavlink.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS \
                | mavlink.MAV_SYS_STATUS_GEOFENCE
            volts, amps, left = self._battery()
            return mavlink.MAVLink_sys_status_message(
                present, enabled, enabled, 250, round(volts * 1000), round(amps * 100), left,
                0, 0, 0, 0, 0, 0, 0, 0, 0)
        if msg_id == MAVLINK_MSG_ID_EXTENDED_SYS_STATE:
            return mavlink.MAVLink_extended_sys_state_message(0, ap.landed_state)
        if msg_id == MAVLINK_MSG_ID_HOME_POSITION:
            h = ap.home
            return mavlink.MAVLink_home_position_message(
                deg_to_e7(h.lat_deg), deg_to_e7(h.lon_deg), round(h.alt_m * 1000.0),
                h.enu[1], h.enu[0], -h.enu[2], [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0,
                int(ap.t_s * 1e6))
        if msg_id == MAVLINK_MSG_ID_MISSION_CURRENT:
            return self.mission_current(*ap.mission_current())
        if msg_id == MAVLINK_MSG_ID_VFR_HUD:
            v = ap.velocity
            gs = math.hypot(v[0], v[1])
            lat, lon, alt = ap.geodetic(ap.position)
            throttle = 0 if not ap.armed else 20 if ap.landed else 50
            return mavlink.MAVLink_vfr_hud_message(gs, gs, round(self._heading_deg()) % 360,
                                                   throttle, alt, v[2])
        if msg_id == MAVLINK_MSG_ID_BATTERY_STATUS:
            volts, amps, left = self._battery()
            cells = [round(volts * 250)] * 4 + [65535] * 6
            return mavlink.MAVLink_battery_status_message(
                0, mavlink.MAV_BATTERY_FUNCTION_ALL, mavlink.MAV_BATTERY_TYPE_LION, 32767, cells,
                round(amps * 100), -1, -1, left, 0, 0)
        if msg_id == MAVLINK_MSG_ID_TERRAIN_REPORT:
            p = ap.position
            return _terrain_report(ap.terrain.report_below(p, ap.geodetic(p)))
        if msg_id == MAVLINK_MSG_ID_LOCAL_POSITION_NED:
            # the local frame is the world's ENU frame (origin: GPS_GLOBAL_ORIGIN), NED
            p, v = ap.position, ap.velocity
            return mavlink.MAVLink_local_position_ned_message(
                self._time_ms(), p[1], p[0], -p[2], v[1], v[0], -v[2])
        if msg_id == MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN:
            f = ap.frame
            return mavlink.MAVLink_gps_global_origin_message(
                deg_to_e7(f.lat0_deg), deg_to_e7(f.lon0_deg), round(f.h0_m * 1000.0),
                int(ap.t_s * 1e6))
        if msg_id == MAVLINK_MSG_ID_ALTITUDE:
            p = ap.position
            lat, lon, alt = ap.geodetic(p)
            ground = ap.terrain.data_height_m(lat, lon)
            above = alt - ground if math.isfinite(ground) else UNKNOWN_TERRAIN_M
            return mavlink.MAVLink_altitude_message(
                int(ap.t_s * 1e6), alt, alt, p[2], alt - ap.home.alt_m, above, -1.0)
        if msg_id == MAVLINK_MSG_ID_PROTOCOL_VERSION:
            return ProtocolVersionMessage()  # MAVLink 2 spoken, 1 understood
        if msg_id == MAVLINK_MSG_ID_AUTOPILOT_VERSION:
            return mavlink.MAVLink_autopilot_version_message(
                CAPABILITIES, FLIGHT_SW_VERSION, 0, 0, 0, list(VEHICLE_TAG.ljust(8, b"\0")),
                [0] * 8, [0] * 8, 0, 0, self.fingerprint, [0] * 18)
        return None

    def mission_current(self, seq: int, total: int, state: int) -> object:
        """MISSION_CURRENT for the mission's (seq, items held, MISSION_STATE): ``total``
        UINT16_MAX when none is held (MAVLink: 0 would say "not supported");
        ``mission_mode`` 1 in AUTO.MISSION, else 2 (suspended) with a mission, 0 without."""
        mode = 1 if self.ap.mode is Mode.MISSION else 2 if total else 0
        return mavlink.MAVLink_mission_current_message(seq, total or NO_MISSION_TOTAL, state,
                                                       mode)

    def terrain_report(self, lat_e7: int, lon_e7: int) -> object:
        """TERRAIN_REPORT for (lat, lon): the ground there and the vehicle's height
        above it (envs/vehicle/terrain.py)."""
        ap = self.ap
        return _terrain_report(ap.terrain.report(lat_e7, lon_e7, ap.geodetic(ap.position)[2]))

    def _heading_deg(self) -> float:
        yaw = self.ap.vehicle.state.yaw_rad  # ENU, counter-clockwise from east
        return math.degrees(_wrap_pi(math.pi / 2.0 - yaw)) % 360.0

    def _attitude(self) -> tuple[float, float, float]:
        ap = self.ap
        yaw_enu = ap.vehicle.state.yaw_rad
        ax, ay, _ = ap.accel if ap.armed and not ap.landed else (0.0, 0.0, 0.0)
        c, s = math.cos(yaw_enu), math.sin(yaw_enu)
        fwd, left = ax * c + ay * s, -ax * s + ay * c
        pitch = -math.atan2(fwd, GRAVITY)
        roll = math.atan2(-left, GRAVITY)
        lim = math.radians(35.0)
        return (max(-lim, min(lim, roll)), max(-lim, min(lim, pitch)),
                _wrap_pi(math.pi / 2.0 - yaw_enu))

    def _battery(self) -> tuple[float, float, int]:
        left = max(0.0, 1.0 - self.ap.flight_time_s / ENDURANCE_S)
        amps = 18.0 if self.ap.armed and not self.ap.landed else 0.5
        return 14.0 + 2.8 * left, amps, round(100 * left)

    def _gps_raw(self) -> object:
        f = self.last_fix
        t_us = int(self.ap.t_s * 1e6)
        v = self.ap.velocity
        gs = math.hypot(v[0], v[1])
        cog = round(self._heading_deg() * 100) % 36000 if gs > 0.5 else 65535
        if f is None:
            return mavlink.MAVLink_gps_raw_int_message(
                t_us, mavlink.GPS_FIX_TYPE_NO_GPS, 0, 0, 0, 65535, 65535, 65535, 65535, 0, 0, 0,
                0, 0, 0, 0)
        acc = f.acc_m if f.acc_m is not None else 9.99
        vacc = f.vacc_m if f.vacc_m is not None else 2.0 * acc
        alt_mm = round(f.alt_m * 1000.0)
        eph = epv = 65535  # HDOP, VDOP x 100: unknown without a satellite count
        if f.sats:  # the receiver model's dilution (sim.gnss: it scales the accuracy)
            cfg = self.ap.agent.spec.gnss
            hdop = math.sqrt(cfg.sats_ref / f.sats)
            eph, epv = (min(round(100.0 * d), 65534) for d in (hdop, hdop * cfg.vacc_ratio))
        return mavlink.MAVLink_gps_raw_int_message(
            t_us, _FIX_TYPES.get(f.fix or "3d", mavlink.GPS_FIX_TYPE_3D_FIX), deg_to_e7(f.lat_deg),
            deg_to_e7(f.lon_deg), alt_mm, eph, epv, round(gs * 100), cog,
            f.sats if f.sats is not None else 255, alt_mm, round(acc * 1000),
            round(vacc * 1000), 0, 0, 0)


def _terrain_report(r: TerrainReport) -> object:
    return mavlink.MAVLink_terrain_report_message(
        r.lat_e7, r.lon_e7, r.spacing, r.terrain_height_m, r.current_height_m, r.pending,
        r.loaded)


def _cms(v_mps: float) -> int:
    return max(-32768, min(32767, round(v_mps * 100.0)))
