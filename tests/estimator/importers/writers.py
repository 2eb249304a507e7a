"""Writers of the recorders' formats, for the import tests and the benchmark.

Each writes one real file of its format from a simulated flight (:class:`Flight`: the
gnss and rtt records of a simulated log with the UTC time of each ``t_ns``):

- ULog (PX4): the file header, the flag-bits message, format (``F``), info (``I``)
  and parameter (``P``) messages, then the data section with add-logged (``A``) and
  data (``D``) messages, a logged string (``L``), a sync (``S``) and a dropout
  (``O``): as the ULog file format specification lays them out. Two GNSS layouts:
  ``v1.13`` (``vehicle_gps_position``: 1e-7 degree integers, millimetre heights) and
  ``v1.14`` (``sensor_gps``: degrees and metres as doubles).
- DataFlash (ArduPilot): ``FMT`` messages (the first describing ``FMT`` itself), then
  ``PARM``, ``MSG``, ``IMU`` and the ``GPS`` + ``GPA`` pairs, each message
  ``0xA3 0x95 type`` and its little-endian fields.
- ROS 2 bags with rosbags' own ``Writer`` (sqlite3 or MCAP), NavSatFix from the ROS 2
  Humble type store.
- Text: GnssLogger, NMEA (GGA + RMC with checksums), the Android ``RangingResult`` CSV,
  SensorReadout.
No library is asked to write ULog or DataFlash: these writers follow the formats.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Iterable
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta, timezone
from pathlib import Path

import numpy as np

from estimator.logio import read_log
from estimator.records import GnssFix, LogHeader, RangeSample

NS = 1_000_000_000
GPS_EPOCH_S = 315_964_800
LEAP_S = 18  # GPS - UTC since 2017-01-01


@dataclass
class Flight:
    """A simulated flight's records with their wall-clock time."""

    header: LogHeader
    gnss: list[GnssFix]
    rtt: list[RangeSample]
    t0_ns: int  # the first record's phone time
    utc0_ns: int  # its UTC (the header's start_utc)

    def utc_ns(self, t_ns: int) -> int:
        return self.utc0_ns + (t_ns - self.t0_ns)


def flight_from_log(path: str | Path) -> Flight:
    log = read_log(path)
    t0 = min(log.gnss[0].t_ns, log.rtt[0].t_ns)
    start = datetime.fromisoformat(log.header.start_utc.replace("Z", "+00:00"))
    return Flight(log.header, log.gnss, log.rtt, t0, int(start.timestamp()) * NS)


def utc_ms(utc_ns: int) -> int:
    return (utc_ns + 500_000) // 1_000_000


# ------------------------------------------------------------------------------ text


GNSSLOGGER_FIX = ("Fix,Provider,LatitudeDegrees,LongitudeDegrees,AltitudeMeters,SpeedMps,"
                  "AccuracyMeters,BearingDegrees,UnixTimeMillis,SpeedAccuracyMps,"
                  "BearingAccuracyDegrees,elapsedRealtimeNanos,VerticalAccuracyMeters,"
                  "MockLocation,NumberOfUsedSignals,VerticalSpeedAccuracyMps,SolutionType")


def write_gnsslogger(path: Path, flight: Flight, *, elapsed_shift_ns: int = 0,
                     with_elapsed: bool = True, bad_lines: Iterable[str] = ()) -> Path:
    """A GnssLogger v3 file: header comments, ``Raw``/``Status`` lines and the ``Fix``
    lines of provider GPS (plus one FLP fix a second, to be ignored)."""
    with open(path, "w", encoding="utf-8", newline="\n") as fh:
        fh.write("#\n# Header Description:\n#\n# Version: v3.0.6.0 Platform: 14 "
                 "Manufacturer: Google Model: Pixel 8\n#\n")
        fh.write("# Raw,utcTimeMillis,TimeNanos,LeapSecond,Svid\n")
        fh.write("# Status,UnixTimeMillis,SignalCount,SignalIndex,ConstellationType,Svid\n")
        fh.write(f"# {GNSSLOGGER_FIX}\n#\n")
        for k, g in enumerate(flight.gnss):
            utc = flight.utc_ns(g.t_ns)
            el = str(g.t_ns + elapsed_shift_ns) if with_elapsed else ""
            vacc = "" if g.vacc_m is None else repr(g.vacc_m)
            line = (f"Fix,GPS,{g.lat_deg!r},{g.lon_deg!r},{g.alt_m!r},6.5,{g.acc_m!r},90.0,"
                    f"{utc_ms(utc)},0.5,10.0,{el},{vacc},0,{g.sats or ''},0.3,")
            fh.write(line + "\n")
            if k % 10 == 0:
                fh.write(f"Raw,{utc_ms(utc)},{g.t_ns},18,{k % 32}\n")
                fh.write(f"Status,{utc_ms(utc)},20,0,1,{k % 32}\n")
                fh.write(f"Fix,FLP,{g.lat_deg + 1e-5!r},{g.lon_deg!r},{g.alt_m!r},6.5,3.9,90.0,"
                         f"{utc_ms(utc)},0.5,10.0,{el},5.0,0,,0.3,\n")
        for line in bad_lines:
            fh.write(line + "\n")
    return path


ANDROID_COLUMNS = ("utc_ms", "bssid", "channel_mhz", "status", "distance_mm",
                   "distance_std_dev_mm", "rssi", "num_attempted", "num_successful",
                   "elapsed_ns")


def write_android_csv(path: Path, flight: Flight, *, utc: bool = True, elapsed: bool = True,
                      elapsed_shift_ns: int = 0, numeric_status: bool = False,
                      upper_bssid: bool = False, bad_lines: Iterable[str] = ()) -> Path:
    """The ranging results as a CSV of Android ``RangingResult`` fields (a column order
    of its own and an extra column, as a real app's export has)."""
    cols = [c for c in ANDROID_COLUMNS if (utc or c != "utc_ms") and (elapsed or
                                                                      c != "elapsed_ns")]
    codes = {"ok": "0", "fail": "1"}
    with open(path, "w", encoding="utf-8", newline="\n") as fh:
        fh.write(",".join(cols) + "\n")
        for r in flight.rtt:
            status = codes.get(r.status, r.status) if numeric_status else (
                "0" if r.ok else r.status)
            row = {
                "utc_ms": str(utc_ms(flight.utc_ns(r.t_ns))),
                "elapsed_ns": str(r.t_ns + elapsed_shift_ns),
                "bssid": r.bssid.upper() if upper_bssid else r.bssid,
                "channel_mhz": "5180",
                "status": status,
                "distance_mm": "" if r.range_m is None else str(round(r.range_m * 1000)),
                "distance_std_dev_mm": "" if r.range_std_m is None else str(
                    round(r.range_std_m * 1000)),
                "rssi": "" if r.rssi_dbm is None else str(int(r.rssi_dbm)),
                "num_attempted": "" if r.attempted is None else str(r.attempted),
                "num_successful": "" if r.successful is None else str(r.successful),
            }
            fh.write(",".join(row[c] for c in cols) + "\n")
        for line in bad_lines:
            fh.write(line + "\n")
    return path


def java_date(utc_ns: int, hours_east: int = 2) -> str:
    """``Date.toString()`` of a UTC time in the zone ``GMT+hh:00``."""
    tz = timezone(timedelta(hours=hours_east))
    dt = datetime.fromtimestamp(utc_ns // NS, tz=tz)
    sign = "+" if hours_east >= 0 else "-"
    return dt.strftime("%a %b %d %H:%M:%S ") + f"GMT{sign}{abs(hours_east):02d}:00" + \
        dt.strftime(" %Y")


def write_sensorreadout(path: Path, flight: Flight, start_utc_ns: int) -> Path:
    """A SensorReadout recording started at ``start_utc_ns`` (a whole second): the
    metadata line, accelerometer events and the RTT events (``17``) at millisecond
    steps since the start, MACs without colons, failed results with success 0."""
    start_t = flight.t0_ns - (flight.utc_ns(flight.t0_ns) - start_utc_ns)
    events: list[tuple[int, str]] = []
    for r in flight.rtt:
        rel = (r.t_ns - start_t) // 1_000_000 * 1_000_000
        if r.ok:
            args = (f"1;{r.bssid.replace(':', '')};{round(r.range_m * 1000)};"
                    f"{round((r.range_std_m or 0) * 1000)};{int(r.rssi_dbm)};"
                    f"{r.attempted or 0};{r.successful or 0}")
        else:
            args = f"0;{r.bssid.replace(':', '')};0;0;0;{r.attempted or 0};0"
        events.append((rel, f"{rel};17;{args}"))
    for k in range(0, len(flight.gnss), 5):
        rel = flight.gnss[k].t_ns - start_t
        events.append((rel, f"{rel};0;0.12;-0.05;9.81"))
    events.sort(key=lambda e: e[0])
    with open(path, "w", encoding="utf-8", newline="\n") as fh:
        fh.write(f"0;-2;{java_date(start_utc_ns)};tester;osa import test\n")
        for _, line in events:
            fh.write(line + "\n")
    return path


def _nmea(body: str) -> str:
    cs = 0
    for ch in body.encode("ascii"):
        cs ^= ch
    return f"${body}*{cs:02X}"


def _ddmm(value: float, deg_digits: int) -> str:
    a = abs(value)
    d = int(a)
    minutes = (a - d) * 60.0
    return f"{d:0{deg_digits}d}{minutes:010.7f}"


def write_nmea(path: Path, flight: Flight, *, undulation_m: float | None = 50.125,
               bad_lines: Iterable[str] = ()) -> Path:
    """GGA + RMC sentences per fix: time hhmmss.sss, 1e-7-minute positions, MSL height
    and the geoid separation (left empty when ``undulation_m`` is None), HDOP = acc/1.5
    with four decimals."""
    n = undulation_m or 0.0
    with open(path, "w", encoding="ascii", newline="\n") as fh:
        for g in flight.gnss:
            dt = datetime.fromtimestamp(0, tz=UTC) + timedelta(
                microseconds=flight.utc_ns(g.t_ns) // 1000)
            hms = dt.strftime("%H%M%S") + f".{dt.microsecond // 1000:03d}"
            lat = _ddmm(g.lat_deg, 2) + ("," + ("N" if g.lat_deg >= 0 else "S"))
            lon = _ddmm(g.lon_deg, 3) + ("," + ("E" if g.lon_deg >= 0 else "W"))
            sep = "" if undulation_m is None else f"{n:.3f}"
            gga = (f"GNGGA,{hms},{lat},{lon},1,{g.sats or 12:02d},{g.acc_m / 1.5:.4f},"
                   f"{g.alt_m - n:.3f},M,{sep},M,,")
            rmc = f"GNRMC,{hms},A,{lat},{lon},12.6,90.0,{dt.strftime('%d%m%y')},,,A"
            fh.write(_nmea(gga) + "\r\n" + _nmea(rmc) + "\r\n")
            fh.write(_nmea(f"GNGSA,A,3,01,02,03,,,,,,,,,,1.2,{g.acc_m / 1.5:.2f},1.0") + "\r\n")
        for line in bad_lines:
            fh.write(line + "\r\n")
    return path


# ------------------------------------------------------------------------------ ULog

ULOG_MAGIC = b"ULog\x01\x12\x35"
_ULOG_TYPES = {"uint64_t": "Q", "int64_t": "q", "uint32_t": "I", "int32_t": "i",
               "uint16_t": "H", "int16_t": "h", "uint8_t": "B", "int8_t": "b",
               "float": "f", "double": "d", "bool": "?", "char": "c"}

# (type, name) of the GNSS topics as PX4 logs them (a faithful subset, in PX4's order)
VEHICLE_GPS_POSITION_V113 = (
    ("uint64_t", "timestamp"), ("uint64_t", "time_utc_usec"), ("int32_t", "lat"),
    ("int32_t", "lon"), ("int32_t", "alt"), ("int32_t", "alt_ellipsoid"),
    ("float", "s_variance_m_s"), ("float", "c_variance_rad"), ("float", "eph"),
    ("float", "epv"), ("float", "hdop"), ("float", "vdop"), ("int32_t", "noise_per_ms"),
    ("int32_t", "jamming_indicator"), ("float", "vel_m_s"), ("float", "vel_n_m_s"),
    ("float", "vel_e_m_s"), ("float", "vel_d_m_s"), ("float", "cog_rad"),
    ("int32_t", "timestamp_time_relative"), ("float", "heading"),
    ("float", "heading_offset"), ("uint8_t", "fix_type"), ("uint8_t", "jamming_state"),
    ("bool", "vel_ned_valid"), ("uint8_t", "satellites_used"), ("uint8_t[4]", "_padding0"),
)
SENSOR_GPS_V114 = (
    ("uint64_t", "timestamp"), ("uint64_t", "timestamp_sample"),
    ("uint64_t", "time_utc_usec"), ("double", "latitude_deg"), ("double", "longitude_deg"),
    ("double", "altitude_msl_m"), ("double", "altitude_ellipsoid_m"),
    ("uint32_t", "device_id"), ("float", "s_variance_m_s"), ("float", "c_variance_rad"),
    ("float", "eph"), ("float", "epv"), ("float", "hdop"), ("float", "vdop"),
    ("int32_t", "noise_per_ms"), ("int32_t", "jamming_indicator"), ("float", "vel_m_s"),
    ("float", "vel_n_m_s"), ("float", "vel_e_m_s"), ("float", "vel_d_m_s"),
    ("float", "cog_rad"), ("int32_t", "timestamp_time_relative"), ("float", "heading"),
    ("float", "heading_offset"), ("float", "heading_accuracy"),
    ("uint16_t", "automatic_gain_control"), ("uint8_t", "fix_type"),
    ("uint8_t", "jamming_state"), ("bool", "vel_ned_valid"),
    ("uint8_t", "satellites_used"), ("uint8_t[2]", "_padding0"),
)
SENSOR_ACCEL = (("uint64_t", "timestamp"), ("uint64_t", "timestamp_sample"),
                ("uint32_t", "device_id"), ("float", "x"), ("float", "y"), ("float", "z"),
                ("float", "temperature"), ("uint32_t", "error_count"),
                ("uint8_t[3]", "clip_counter"), ("uint8_t", "samples"),
                ("uint8_t[4]", "_padding0"))


def _ulog_dtype(fields) -> np.dtype:
    """The packed little-endian record of a ULog format (arrays as sub-arrays)."""
    out = []
    for typ, name in fields:
        base, _, n = typ.partition("[")
        code = np.dtype("<" + _ULOG_TYPES[base].replace("?", "b1").replace("c", "S1"))
        out.append((name, code, (int(n.rstrip("]")),)) if n else (name, code))
    return np.dtype(out)


def logged_dtype(fields) -> np.dtype:
    """The record a format's data messages carry: without the trailing padding fields,
    which PX4's logger leaves out (and readers expect absent)."""
    logged = list(fields)
    while logged and logged[-1][1].startswith("_padding"):
        logged.pop()
    return _ulog_dtype(logged)


def _pack(dtype: np.dtype, values: dict) -> bytes:
    """One message's payload: the named values, zeros for the rest."""
    rec = np.zeros(1, dtype=dtype)
    for k, v in values.items():
        if k in dtype.names:
            rec[k] = v
    return rec.tobytes()


class ULogWriter:
    """A ULog file, version 1, written message by message (see the module docstring)."""

    def __init__(self, path: Path, start_us: int = 10_000_000) -> None:
        self.fh = open(path, "wb")  # noqa: SIM115 - closed in close()
        self.fh.write(ULOG_MAGIC + bytes([1]) + struct.pack("<Q", start_us))
        # flag bits: no compat/incompat flags, no appended data
        self._msg(b"B", bytes(8) + bytes(8) + struct.pack("<3Q", 0, 0, 0))
        self.ids: dict[tuple[str, int], int] = {}

    def _msg(self, kind: bytes, payload: bytes) -> None:
        self.fh.write(struct.pack("<HB", len(payload), kind[0]) + payload)

    def format(self, name: str, fields) -> np.dtype:
        """Define a format; returns the record its data messages carry."""
        text = name + ":" + "".join(f"{t} {n};" for t, n in fields)
        self._msg(b"F", text.encode("ascii"))
        return logged_dtype(fields)

    def info(self, key_type: str, key: str, value: bytes) -> None:
        k = f"{key_type} {key}".encode("ascii")
        self._msg(b"I", bytes([len(k)]) + k + value)

    def param(self, key: str, value: float) -> None:
        k = f"float {key}".encode("ascii")
        self._msg(b"P", bytes([len(k)]) + k + struct.pack("<f", value))

    def add_logged(self, name: str, multi_id: int = 0) -> int:
        msg_id = len(self.ids)
        self.ids[(name, multi_id)] = msg_id
        self._msg(b"A", struct.pack("<BH", multi_id, msg_id) + name.encode("ascii"))
        return msg_id

    def data(self, msg_id: int, payload: bytes) -> None:
        self._msg(b"D", struct.pack("<H", msg_id) + payload)

    def logged_string(self, level: int, t_us: int, text: str) -> None:
        self._msg(b"L", struct.pack("<BQ", level, t_us) + text.encode("utf-8"))

    def sync(self) -> None:
        self._msg(b"S", b"\x2f\x73\x13\x20\x25\x0c\xbb\x12")

    def dropout(self, ms: int) -> None:
        self._msg(b"O", struct.pack("<H", ms))

    def raw(self, data: bytes) -> None:
        self.fh.write(data)

    def close(self) -> None:
        self.fh.close()


def _gnss_values(g: GnssFix, t_us: int, utc_us: int, undulation_m: float) -> dict:
    """Both layouts' fields of one fix (each writer takes the names its format has)."""
    msl = g.alt_m - undulation_m
    return {
        "timestamp": t_us, "timestamp_sample": t_us - 40_000, "time_utc_usec": utc_us,
        "lat": round(g.lat_deg * 1e7), "lon": round(g.lon_deg * 1e7),
        "alt": round(msl * 1000), "alt_ellipsoid": round(g.alt_m * 1000),
        "latitude_deg": g.lat_deg, "longitude_deg": g.lon_deg, "altitude_msl_m": msl,
        "altitude_ellipsoid_m": g.alt_m, "device_id": 11_796_489,
        "s_variance_m_s": 0.3, "c_variance_rad": 0.01, "eph": g.acc_m,
        "epv": g.vacc_m or 0.0, "hdop": 0.7, "vdop": 1.1, "noise_per_ms": 100,
        "jamming_indicator": 5, "vel_m_s": 6.5, "vel_n_m_s": 4.0, "vel_e_m_s": 5.0,
        "vel_d_m_s": -0.1, "cog_rad": 1.0, "heading": float("nan"),
        "automatic_gain_control": 1000, "fix_type": 3, "vel_ned_valid": True,
        "satellites_used": g.sats or 12,
    }


def write_ulog(path: Path, flight: Flight, *, variant: str = "v1.13",
               msl_only: bool = False, undulation_m: float = 50.125,
               no_utc_first: int = 0, second_instance: bool = True,
               garbage_after: int | None = None) -> Path:
    """A PX4 flight log with the GNSS topic (``variant``), a second GNSS instance
    (``multi_id`` 1, a worse receiver), a battery topic, a logged string, syncs and a
    dropout. ``msl_only`` drops the ellipsoidal height (as some drivers' logs lack it);
    the first ``no_utc_first`` fixes have no UTC yet (``time_utc_usec`` 0);
    ``garbage_after`` writes junk bytes after that many fixes."""
    name, fields = (("vehicle_gps_position", VEHICLE_GPS_POSITION_V113) if variant == "v1.13"
                    else ("sensor_gps", SENSOR_GPS_V114))
    if msl_only:
        fields = tuple(f for f in fields if f[1] not in ("alt_ellipsoid",
                                                         "altitude_ellipsoid_m"))
    battery = (("uint64_t", "timestamp"), ("float", "voltage_v"), ("float", "current_a"),
               ("float", "remaining"), ("uint8_t", "cell_count"), ("uint8_t[3]", "_padding0"))
    boot_t0_us = 30_000_000
    w = ULogWriter(path, start_us=boot_t0_us - 5_000_000)
    gdt = w.format(name, fields)
    bdt = w.format("battery_status", battery)
    w.info("char[3]", "sys_name", b"PX4")
    w.info("char[7]", "ver_hw", b"PX4_FMU")
    # PX4's release number: major, minor, patch, type (255: release) in a uint32
    w.info("uint32_t", "ver_sw_release", struct.pack("<I", (1 << 24) | (13 << 16) | (3 << 8)
                                                     | 255))
    w.param("MPC_XY_VEL_MAX", 12.0)
    gid = w.add_logged(name, 0)
    gid2 = w.add_logged(name, 1) if second_instance else None
    bid = w.add_logged("battery_status", 0)
    w.logged_string(ord("6"), boot_t0_us - 1_000_000, "[commander] Takeoff detected")
    for k, g in enumerate(flight.gnss):
        t_us = boot_t0_us + (g.t_ns - flight.t0_ns) // 1000
        utc_us = 0 if k < no_utc_first else flight.utc_ns(g.t_ns) // 1000
        w.data(gid, _pack(gdt, _gnss_values(g, t_us, utc_us, undulation_m)))
        if gid2 is not None and k % 2 == 0:
            worse = GnssFix(t_ns=g.t_ns, lat_deg=g.lat_deg + 2e-5, lon_deg=g.lon_deg,
                            alt_m=g.alt_m + 3.0, acc_m=4.0, vacc_m=6.0, fix="3d", sats=8)
            w.data(gid2, _pack(gdt, _gnss_values(worse, t_us, utc_us, undulation_m)))
        if k % 10 == 0:
            w.data(bid, _pack(bdt, {"timestamp": t_us, "voltage_v": 16.2, "current_a": 12.5,
                                    "remaining": 0.8, "cell_count": 4}))
        if k % 500 == 0:
            w.sync()
        if k == len(flight.gnss) // 2:
            w.dropout(40)
        if garbage_after is not None and k == garbage_after:
            w.raw(b"\x00\x00\x00" + bytes(range(7, 40)))
    w.close()
    return path


def write_day_ulog(path: Path, hours: float = 24.0, gnss_hz: float = 5.0,
                   accel_hz: float = 100.0, utc0_ns: int = 1_749_723_120 * NS) -> dict:
    """A long PX4 log made in bulk, minute by minute: ``vehicle_gps_position`` at
    ``gnss_hz`` circling a point and ``sensor_accel`` at ``accel_hz`` (the bulk of
    the file, as IMU topics are in real logs). Returns its sizes."""
    w = ULogWriter(path, start_us=1_000_000)
    gdt = w.format("vehicle_gps_position", VEHICLE_GPS_POSITION_V113)
    adt = w.format("sensor_accel", SENSOR_ACCEL)
    w.info("char[3]", "sys_name", b"PX4")
    gid = w.add_logged("vehicle_gps_position", 0)
    aid = w.add_logged("sensor_accel", 0)

    def framed(payload_dtype: np.dtype, msg_id: int, n: int) -> np.ndarray:
        dt = np.dtype([("size", "<u2"), ("type", "u1"), ("id", "<u2"), ("p", payload_dtype)])
        m = np.zeros(n, dtype=dt)
        m["size"], m["type"], m["id"] = payload_dtype.itemsize + 2, ord("D"), msg_id
        return m

    seconds = round(hours * 3600)
    chunk_s = 60
    per_g, per_a = round(chunk_s * gnss_hz), round(chunk_s * accel_hz)
    n_g = n_a = 0
    for c0 in range(0, seconds, chunk_s):
        tg = c0 + np.arange(per_g) / gnss_hz
        ta = c0 + np.arange(per_a) / accel_hz
        g = framed(gdt, gid, per_g)
        p = g["p"]
        p["timestamp"] = (2_000_000 + tg * 1e6).astype(np.uint64)
        p["time_utc_usec"] = (utc0_ns // 1000 + tg * 1e6).astype(np.uint64)
        ang = tg * 2 * math.pi / 120.0
        p["lat"] = np.round((36.715 + 0.0007 * np.sin(ang)) * 1e7).astype(np.int32)
        p["lon"] = np.round((-4.478 + 0.0009 * np.cos(ang)) * 1e7).astype(np.int32)
        p["alt"], p["alt_ellipsoid"] = 140_000, 190_125
        p["eph"], p["epv"], p["fix_type"], p["satellites_used"] = 0.9, 1.4, 3, 18
        g["p"] = p
        a = framed(adt, aid, per_a)
        q = a["p"]
        q["timestamp"] = (2_000_000 + ta * 1e6).astype(np.uint64)
        q["z"] = 9.81
        a["p"] = q
        w.raw(g.tobytes())
        w.raw(a.tobytes())
        n_g += per_g
        n_a += per_a
    w.close()
    return {"gnss": n_g, "accel": n_a, "bytes": path.stat().st_size, "seconds": seconds}


# ------------------------------------------------------------------------- DataFlash

DF_HEAD = b"\xa3\x95"
_DF_TYPES = {"a": "64s", "b": "b", "B": "B", "h": "h", "H": "H", "i": "i", "I": "I",
             "f": "f", "d": "d", "n": "4s", "N": "16s", "Z": "64s", "c": "h", "C": "H",
             "e": "i", "E": "I", "L": "i", "M": "B", "q": "q", "Q": "Q"}
DF_GPS = ("GPS", "QBBIHBcLLeffffB", "TimeUS,I,Status,GMS,GWk,NSats,HDop,Lat,Lng,Alt,Spd,"
          "GCrs,VZ,Yaw,U")
DF_GPA = ("GPA", "QBCCCCfBIHfHH", "TimeUS,I,VDop,HAcc,VAcc,SAcc,YAcc,VV,SMS,Delta,Und,"
          "RTCMFU,RTCMFD")
DF_GPA_OLD = ("GPA", "QBCCCCfBIH", "TimeUS,I,VDop,HAcc,VAcc,SAcc,YAcc,VV,SMS,Delta")
DF_PARM = ("PARM", "QNf", "TimeUS,Name,Value")
DF_MSG = ("MSG", "QZ", "TimeUS,Message")
DF_IMU = ("IMU", "QBffffffIIfBBHH", "TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ,EG,EA,T,GH,AH,"
          "GHz,AHz")


class DataFlashWriter:
    """An ArduPilot DataFlash log: ``FMT`` messages first, then messages."""

    def __init__(self, path: Path) -> None:
        self.fh = open(path, "wb")  # noqa: SIM115 - closed in close()
        self.structs: dict[str, tuple[int, struct.Struct]] = {}
        self._define(128, "FMT", "BBnNZ", "Type,Length,Name,Format,Columns")

    def _define(self, type_id: int, name: str, fmt: str, columns: str) -> None:
        st = struct.Struct("<" + "".join(_DF_TYPES[c] for c in fmt))
        self.structs[name] = (type_id, st)
        body = struct.pack("<BB4s16s64s", type_id, 3 + st.size, name.encode(),
                           fmt.encode(), columns.encode())
        self.fh.write(DF_HEAD + bytes([128]) + body)

    def define(self, type_id: int, spec: tuple[str, str, str]) -> None:
        self._define(type_id, *spec)

    def write(self, name: str, *values) -> None:
        type_id, st = self.structs[name]
        self.fh.write(DF_HEAD + bytes([type_id]) + st.pack(*values))

    def raw(self, data: bytes) -> None:
        self.fh.write(data)

    def close(self) -> None:
        self.fh.close()


def gps_week_ms(utc_ns: int) -> tuple[int, int]:
    gps_ms = (utc_ns + LEAP_S * NS) // 1_000_000 - GPS_EPOCH_S * 1000
    return int(gps_ms // 604_800_000), int(gps_ms % 604_800_000)


def write_dataflash(path: Path, flight: Flight, *, with_und: bool = True,
                    undulation_m: float = 50.125, no_time_first: int = 0,
                    corrupt_after: int | None = None) -> Path:
    """An ArduCopter log: FMTs, PARM and MSG, IMU at 2x the GNSS rate, a second GPS
    instance (``I`` 1) and the GPS + GPA pairs of instance 0 (GPA with ``Und`` when
    ``with_und``: ArduPilot's undulation, mean sea level above the ellipsoid, so
    ``-undulation_m`` for a geoid ``undulation_m`` above it). The first
    ``no_time_first`` fixes have no GPS time yet (``GWk`` 0);
    ``corrupt_after`` inserts garbage bytes after that many fixes."""
    w = DataFlashWriter(path)
    w.define(129, DF_PARM)
    w.define(130, DF_MSG)
    w.define(131, DF_GPS)
    w.define(132, DF_GPA if with_und else DF_GPA_OLD)
    w.define(133, DF_IMU)
    w.write("MSG", 1_000_000, b"ArduCopter V4.5.7 (2a3dc4b7)")
    w.write("PARM", 1_100_000, b"GPS_TYPE", 1.0)
    boot0_us = 60_000_000
    for k, g in enumerate(flight.gnss):
        t_us = boot0_us + (g.t_ns - flight.t0_ns) // 1000
        week, ms = (0, 0) if k < no_time_first else gps_week_ms(flight.utc_ns(g.t_ns))
        msl_cm = round((g.alt_m - undulation_m) * 100)
        for j in range(2):
            w.write("IMU", t_us - 50_000 * j, 0, 0.01, 0.0, 0.0, 0.1, 0.0, -9.8, 0, 0, 35.0,
                    1, 1, 1000, 1000)
        if k % 3 == 0:  # a second receiver, worse, at a third of the rate
            w.write("GPS", t_us + 5, 1, 3, ms, week, 9, 180, round(g.lat_deg * 1e7) + 200,
                    round(g.lon_deg * 1e7), msl_cm + 300, 6.5, 90.0, -0.1, 0.0, 1)
        w.write("GPS", t_us, 0, 3 if k >= no_time_first else 1, ms, week, g.sats or 12,
                round(g.acc_m / 1.5 * 100), round(g.lat_deg * 1e7), round(g.lon_deg * 1e7),
                msl_cm, 6.5, 90.0, -0.1, 0.0, 1)
        hacc, vacc = round(g.acc_m * 100), round((g.vacc_m or 0.0) * 100)
        gpa = [t_us, 0, 110, hacc, vacc, 40, 0.0, 1, t_us // 1000, 100]
        if with_und:
            gpa += [-undulation_m, 0, 0]
        w.write("GPA", *gpa)
        if corrupt_after is not None and k == corrupt_after:
            w.raw(b"\xa3\x95\xfe garbage \x00\x13\x37" * 3)
    w.close()
    return path


# --------------------------------------------------------------------------- rosbag2


def write_rosbag(path: Path, flight: Flight, *, storage: str = "sqlite3",
                 topic: str = "/fix", covariance: bool = True,
                 extra_topic: bool = True, second_fix_topic: str | None = None,
                 image_bytes: int = 0, nan_every: int = 0) -> Path:
    """A ROS 2 bag directory (rosbags' ``Writer``, version 9) with NavSatFix on
    ``topic`` stamped with the fix's UTC, a diagonal covariance (acc^2, acc^2,
    vacc^2), recorded 30 ms after the stamp; plus a ``/battery`` topic of another type
    and, if asked, a second NavSatFix topic (a worse receiver, every tenth fix) and a
    ``/camera`` topic of ``image_bytes`` images every tenth fix (a bag's bulk: MCAP
    then holds several chunks). With ``nan_every``, every such fix has NaN horizontal
    variances and every other one a NaN vertical one (nmea_navsat_driver's covariance
    from an empty HDOP)."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    NavSatFix = ts.types["sensor_msgs/msg/NavSatFix"]
    NavSatStatus = ts.types["sensor_msgs/msg/NavSatStatus"]
    Header = ts.types["std_msgs/msg/Header"]
    Time = ts.types["builtin_interfaces/msg/Time"]
    Float32 = ts.types["std_msgs/msg/Float32"]
    Image = ts.types["sensor_msgs/msg/Image"]
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with Writer(path, version=9, storage_plugin=plugin) as w:
        conn = w.add_connection(topic, NavSatFix.__msgtype__, typestore=ts)
        bconn = w.add_connection("/battery", Float32.__msgtype__, typestore=ts) \
            if extra_topic else None
        conn2 = w.add_connection(second_fix_topic, NavSatFix.__msgtype__, typestore=ts) \
            if second_fix_topic else None
        iconn = w.add_connection("/camera", Image.__msgtype__, typestore=ts) \
            if image_bytes else None
        for k, g in enumerate(flight.gnss):
            utc = flight.utc_ns(g.t_ns)
            vacc = g.vacc_m if g.vacc_m is not None else 0.0
            cov = (np.array([g.acc_m ** 2, 0, 0, 0, g.acc_m ** 2, 0, 0, 0, vacc ** 2])
                   if covariance else np.zeros(9))
            if nan_every and k % nan_every == 0:
                cov[0] = cov[4] = np.nan
            elif nan_every and k % nan_every == 1:
                cov[8] = np.nan
            msg = NavSatFix(
                header=Header(stamp=Time(sec=utc // NS, nanosec=utc % NS), frame_id="gnss"),
                status=NavSatStatus(status=0, service=1),
                latitude=g.lat_deg, longitude=g.lon_deg, altitude=g.alt_m,
                position_covariance=cov.astype(np.float64),
                position_covariance_type=2 if covariance else 0,
            )
            w.write(conn, utc + 30_000_000, ts.serialize_cdr(msg, NavSatFix.__msgtype__))
            if conn2 is not None and k % 10 == 0:
                msg.latitude += 3e-5
                msg.position_covariance = np.array([16.0, 0, 0, 0, 16.0, 0, 0, 0, 36.0])
                w.write(conn2, utc + 35_000_000, ts.serialize_cdr(msg, NavSatFix.__msgtype__))
            if bconn is not None and k % 10 == 0:
                w.write(bconn, utc + 31_000_000,
                        ts.serialize_cdr(Float32(data=15.9), Float32.__msgtype__))
            if iconn is not None and k % 10 == 0:
                img = Image(header=msg.header, height=1, width=image_bytes, encoding="mono8",
                            is_bigendian=0, step=image_bytes,
                            data=np.full(image_bytes, k % 256, dtype=np.uint8))
                w.write(iconn, utc + 32_000_000, ts.serialize_cdr(img, Image.__msgtype__))
    return path


def storage_file(bag_dir: Path) -> Path:
    """The one storage file of a bag directory (``.db3`` or ``.mcap``)."""
    (f,) = [p for p in bag_dir.iterdir() if p.suffix in (".db3", ".mcap")]
    return f


def mcap_messages(data: bytes) -> list[tuple[int, int, int, int]]:
    """(chunk number, offset, length, end of the chunk) of each Message record (opcode
    0x05) in the uncompressed chunks of an MCAP file (records: opcode, u64 length,
    content, as the MCAP specification lays them out); to damage or cut a bag where
    its messages are."""
    out, off, chunk = [], 8, 0  # after the magic
    while off + 9 <= len(data):
        op, n = data[off], struct.unpack_from("<Q", data, off + 1)[0]
        if op == 0x06:  # Chunk: start, end, size (u64 x3), crc (u32), compression, records
            c = off + 9 + 28
            comp_len = struct.unpack_from("<I", data, c)[0]
            assert data[c + 4:c + 4 + comp_len] == b"", "a compressed chunk"
            q, end = c + 4 + comp_len + 8, off + 9 + n
            while q < end:
                size = struct.unpack_from("<Q", data, q + 1)[0]
                if data[q] == 0x05:
                    out.append((chunk, q, size, end))
                q += 9 + size
            chunk += 1
        if op == 0x0F:  # DataEnd
            break
        off += 9 + n
    return out
