"""DataFlash and ULog files as the autopilots' firmware writes them, every value checked
against a hand computation: ArduPilot's ``FMT``/``UNIT``/``MULT``/``FMTU`` preamble, the
``GPA`` layouts of its releases, PX4's GNSS topics of v1.11 to v1.15."""

from __future__ import annotations

import pytest

from estimator.importers.common import GnssOptions, Tally
from estimator.importers.dataflash import Reader as DataFlashReader
from tests.estimator.importers.writers import (
    DF_GPS,
    VEHICLE_GPS_POSITION_V113,
    DataFlashWriter,
)

# 2025-06-12T10:12:00Z is GPS week 2370 + 382,338,000 ms (GPS time is 18 s ahead)
WEEK, WEEK_MS, UTC_NS = 2370, 382_338_000, 1_749_723_120 * 1_000_000_000
INT32_MIN = -(2**31)

# ArduPilot's GPA layouts: 4.1 on (no height), up to 4.6 (Und: AMSL minus ellipsoid,
# AP_GPS::get_undulation), later (AEl: the ellipsoidal height in cm, INT32_MIN unknown)
GPA_NO_HEIGHT = ("GPA", "QBCCCCfBIH", "TimeUS,I,VDop,HAcc,VAcc,SAcc,YAcc,VV,SMS,Delta")
GPA_UND = ("GPA", "QBCCCCfBIHfHH", "TimeUS,I,VDop,HAcc,VAcc,SAcc,YAcc,VV,SMS,Delta,Und,"
           "RTCMFU,RTCMFD")
GPA_AEL = ("GPA", "QBCCCCfBIHeHH", "TimeUS,I,VDop,HAcc,VAcc,SAcc,YAcc,VV,SMS,Delta,AEl,"
           "RTCMFU,RTCMFD")
UNITS = {"s": "s", "m": "m", "D": "deglatitude", "U": "deglongitude", "S": "satellites",
         "n": "m/s", "h": "degheading", "d": "deg", "#": "instance", "-": ""}
MULTS = {"-": 0.0, "0": 1.0, "B": 1e-2, "C": 1e-3, "F": 1e-6, "G": 1e-7}


def ardupilot_log(path, gpa, rows):
    """A log as ArduPilot 4.x starts it: ``FMT`` of ``FMT``, the ``UNIT`` and ``MULT``
    tables, each type's ``FMT`` then ``FMTU`` before its first message; then ``rows``:
    (GPS values, GPA values) written with one ``TimeUS`` as ``AP_GPS::Write_GPS`` does."""
    w = DataFlashWriter(path)
    w.define(177, ("UNIT", "QbZ", "TimeUS,Id,Label"))
    w.define(178, ("MULT", "Qbd", "TimeUS,Id,Mult"))
    w.define(179, ("FMTU", "QBNN", "TimeUS,FmtType,UnitIds,MultIds"))
    for k, label in UNITS.items():
        w.write("UNIT", 0, ord(k), label.encode())
    for k, mult in MULTS.items():
        w.write("MULT", 0, ord(k), mult)
    w.define(130, DF_GPS)
    w.write("FMTU", 0, 130, b"s#-s-S-DUmnhnh-", b"F--C-0BGGB000--")
    w.define(131, gpa)
    w.write("FMTU", 0, 131, b"s#-mmmnd-ssm--", b"F-BBBB0-CC0B--")
    for gps, gpa_values in rows:
        w.write("GPS", *gps)
        w.write("GPA", *gpa_values)
    w.close()
    return path


def _gps(t_us, inst, alt_cm, status=3, week=WEEK, ms=WEEK_MS):
    # Malaga: 36.7136672 N, 4.4791287 W, 20 satellites, HDop 0.60
    return (t_us, inst, status, ms, week, 20, 60, 367_136_672, -44_791_287, alt_cm, 6.5,
            90.0, -0.1, 0.0, 1)


def _gpa(t_us, inst, height=()):
    return (t_us, inst, 110, 90, 142, 40, 0.0, 1, t_us // 1000, 200, *height)


def _fixes(path, **options):
    reader = DataFlashReader(path, GnssOptions(**options))
    tally = Tally()
    return list(reader.records(tally)), tally, reader.source


@pytest.mark.parametrize(("gpa", "height", "alt_m", "how"), [
    # 131.96 m AMSL where the geoid is 50.125 m above the ellipsoid: ArduPilot logs
    # Und = AMSL - ellipsoid = -50.125 (uBlox hMSL - height); the ellipsoidal height
    # is 131.96 + 50.125 = 182.085 m
    (GPA_UND, (-50.125, 0, 0), 182.085, "undulation"),
    # where the geoid is below the ellipsoid (the US midwest, N = -31.5 m): Und +31.5
    (GPA_UND, (31.5, 0, 0), 100.46, "undulation"),
    # later firmware logs the ellipsoidal height itself: 182.08 m in cm
    (GPA_AEL, (18_208, 0, 0), 182.08, "ellipsoid"),
])
def test_dataflash_heights_as_ardupilot_logs_them(tmp_path, gpa, height, alt_m, how):
    rows = [(_gps(60_000_000, 0, 13_196), _gpa(60_000_000, 0, height))]
    (fix,), tally, source = _fixes(ardupilot_log(tmp_path / "a.bin", gpa, rows))
    assert fix.record.alt_m == alt_m
    assert dict(tally.heights) == {how: 1}
    assert source.warnings == []
    assert (fix.record.lat_deg, fix.record.lon_deg) == (36.7136672, -4.4791287)
    assert (fix.record.acc_m, fix.record.vacc_m, fix.record.sats) == (0.9, 1.42, 20)
    assert fix.utc_ns == UTC_NS


@pytest.mark.parametrize(("gpa", "height"), [
    (GPA_UND, (0.0, 0, 0)),  # a receiver without a geoid model: get_undulation false
    (GPA_AEL, (INT32_MIN, 0, 0)),  # AEl unknown
    (GPA_NO_HEIGHT, ()),
])
def test_dataflash_without_a_height_above_the_ellipsoid(tmp_path, gpa, height):
    rows = [(_gps(60_000_000, 0, 13_196), _gpa(60_000_000, 0, height))]
    path = ardupilot_log(tmp_path / "a.bin", gpa, rows)
    (fix,), tally, source = _fixes(path)
    assert fix.record.alt_m == 131.96
    assert dict(tally.heights) == {"msl_as_ellipsoid": 1}
    assert any("--geoid-offset" in w for w in source.warnings)
    (fix,), tally, _ = _fixes(path, geoid_offset_m=50.125)
    assert fix.record.alt_m == 182.085
    assert dict(tally.heights) == {"geoid_offset": 1}


def test_dataflash_of_arduplane_3_2_without_timeus_and_gpa(tmp_path):
    """ArduPlane 3.2 logs GPS with GMS/GWk and its boot time as ``T`` (ms), no
    ``TimeUS`` and no GPA: the fixes are read, their accuracy from HDop (1.5 m x 1.20)."""
    w = DataFlashWriter(tmp_path / "plane32.bin")
    w.define(130, ("GPS", "BIHBcLLeeEefI", "Status,GMS,GWk,NSats,HDop,Lat,Lng,RelAlt,Alt,Spd,"
                   "GCrs,VZ,T"))
    for k in range(3):
        w.write("GPS", 3, WEEK_MS + 200 * k, WEEK, 10, 120, 367_136_672 + k, -44_791_287,
                1000, 13_196, 650, 9000, -0.1, 60_000 + 200 * k)
    w.close()
    fixes, tally, source = _fixes(tmp_path / "plane32.bin", geoid_offset_m=50.125)
    assert [f.utc_ns for f in fixes] == [UTC_NS + k * 200_000_000 for k in range(3)]
    assert [f.record.lat_deg for f in fixes] == [36.7136672, 36.7136673, 36.7136674]
    assert {(f.record.alt_m, f.record.acc_m, f.record.vacc_m) for f in fixes} == {
        (182.085, 1.8, None)}
    assert dict(tally.counts.rejected) == {}
    assert any("HDop" in w for w in source.warnings)


def test_dataflash_two_receivers_and_the_leap_seconds_of_the_log_date(tmp_path):
    """Two receivers (``I`` 0 and 1, each with its GPA, a few microseconds apart as
    ``Write_GPS`` logs them), in June 2016: GPS time was 17 s ahead of UTC then.
    2016-06-12T10:12:00Z (a Sunday) = GPS 10:12:17 = week 1901 + 36,737,000 ms."""
    week, ms = 1901, 36_737_000
    rows = []
    for k in range(4):
        t = 60_000_000 + 200_000 * k
        rows.append((_gps(t, 0, 13_196, ms=ms + 200 * k, week=week),
                     _gpa(t, 0, (-50.125, 0, 0))))
        second = list(_gps(t + 9, 1, 13_496, ms=ms + 200 * k, week=week))
        second[7] += 200  # 2e-5 degrees north
        rows.append((tuple(second), (t + 9, 1, 180, 300, 450, 60, 0.0, 1, t // 1000, 200,
                                     -50.125, 0, 0)))
    path = ardupilot_log(tmp_path / "2016.bin", GPA_UND, rows)
    utc0 = 1_465_726_320 * 1_000_000_000  # 2016-06-12T10:12:00Z
    first, tally, _ = _fixes(path)
    assert [f.utc_ns for f in first] == [utc0 + k * 200_000_000 for k in range(4)]
    assert {(f.record.lat_deg, f.record.alt_m, f.record.acc_m) for f in first} == {
        (36.7136672, 182.085, 0.9)}
    assert dict(tally.counts.unknown_types) == {"GPS[1]": 4}
    second, tally, _ = _fixes(path, topic="GPS[1]")
    assert [f.utc_ns for f in second] == [utc0 + k * 200_000_000 for k in range(4)]
    assert {(f.record.lat_deg, f.record.alt_m, f.record.acc_m, f.record.vacc_m)
            for f in second} == {(36.7136872, 185.085, 3.0, 4.5)}
    assert dict(tally.counts.unknown_types) == {"GPS[0]": 4}


def _clean_and_corrupt(path, n=400):
    """A log whose GPA is first defined after a corrupt stretch, and the same log with
    corrupt stretches (junk that looks like headers of undefined types, zeros) and a
    cut end; the number of junk bytes."""
    from tests.estimator.importers.writers import DF_IMU

    def write(p, junk):
        w = DataFlashWriter(p)
        w.define(130, DF_GPS)
        w.define(133, DF_IMU)
        n_junk = 0
        for k in range(n):
            t = 60_000_000 + 200_000 * k
            if k == 20:
                w.define(131, GPA_UND)  # ArduPilot writes a type's FMT before its first
            if junk and k in (10, 150, 151, 390):
                bad = b"\xa3\x95\x07 bad \xa3\x95\xfe" + bytes(k % 7)
                w.raw(bad)
                n_junk += len(bad)
            for j in range(3):
                w.write("IMU", t + j, 0, 0.01, 0.0, 0.0, 0.1, 0.0, -9.8, 0, 0, 35.0, 1, 1,
                        1000, 1000)
            w.write("GPS", *_gps(t, 0, 13_196 + k, ms=WEEK_MS + 200 * k))
            if k >= 20:
                w.write("GPA", *_gpa(t, 0, (-50.125, 0, 0)))
        w.close()
        return p, n_junk

    clean, _ = write(path.with_suffix(".clean"), False)
    corrupt, n_junk = write(path, True)
    corrupt.write_bytes(corrupt.read_bytes()[:-7])  # the last GPA cut: 32 of 39 bytes
    return clean, corrupt, n_junk + 32


@pytest.mark.parametrize("chunks", [(1 << 16, 1 << 23), (100, 300), (400, 400)])
def test_dataflash_corrupt_stretches_are_indexed_past(tmp_path, monkeypatch, chunks):
    """pymavlink's index stops at the first corrupt stretch; the rest is indexed past it
    (in chunks of any size) to the same fixes as the clean log's, and the bad bytes are
    counted; the messages are not parsed one by one (a 198 MB log with 23 bad bytes 2 MB
    in took 58 s so, 3 s now)."""
    from pymavlink import DFReader

    import estimator.importers.dataflash as dataflash

    monkeypatch.setattr(dataflash, "CHUNK_MIN", chunks[0])
    monkeypatch.setattr(dataflash, "CHUNK_MAX", chunks[1])
    clean, corrupt, n_bad = _clean_and_corrupt(tmp_path / "c.bin")
    want, _, _ = _fixes(clean)
    parsed = []
    original = DFReader.DFReader_binary._parse_next

    def counting(self):
        parsed.append(self.offset)
        return original(self)

    monkeypatch.setattr(DFReader.DFReader_binary, "_parse_next", counting)
    got, tally, _ = _fixes(corrupt)
    assert len(parsed) < 10  # pymavlink's own look at each type's first message
    assert [f.record for f in got[:-1]] == [f.record for f in want[:-1]]
    assert [f.utc_ns for f in got] == [f.utc_ns for f in want]
    # the last fix lost its GPA to the cut: its accuracy is 1.5 m x HDop 0.60
    assert (got[-1].record.acc_m, got[-1].record.vacc_m) == (0.9, None)
    assert dict(tally.counts.rejected) == {"corrupt_bytes": n_bad}
    assert dict(tally.heights) == {"msl_as_ellipsoid": 21, "undulation": 379}


def test_dataflash_corrupt_stretches_without_the_compiled_indexer(tmp_path, monkeypatch):
    """Where pymavlink has no compiled indexer, the rest is read message by message: the
    same fixes and counts."""
    import estimator.importers.dataflash as dataflash

    _, corrupt, n_bad = _clean_and_corrupt(tmp_path / "c.bin")
    fast, fast_tally, _ = _fixes(corrupt)
    monkeypatch.setattr(dataflash, "_fast_index", lambda: False)
    slow, slow_tally, _ = _fixes(corrupt)
    assert [(f.record, f.utc_ns) for f in slow] == [(f.record, f.utc_ns) for f in fast]
    assert slow_tally.counts.rejected == fast_tally.counts.rejected == {"corrupt_bytes": n_bad}


def test_dataflash_alt_in_metres_keeps_its_millimetres(tmp_path):
    """``Alt`` as ArduPilot logs it is ``e`` (int32 cm); a logger that writes it as
    ``f`` (float32 metres) keeps what it wrote: 131.957 m, not rounded to 131.96."""
    w = DataFlashWriter(tmp_path / "f.bin")
    w.define(130, ("GPS", "QBBIHBcLLffffB", "TimeUS,I,Status,GMS,GWk,NSats,HDop,Lat,Lng,Alt,"
                   "Spd,GCrs,VZ,U"))
    w.define(131, GPA_UND)
    w.write("GPS", 60_000_000, 0, 3, WEEK_MS, WEEK, 20, 60, 367_136_672, -44_791_287,
            131.957, 6.5, 90.0, -0.1, 1)
    w.write("GPA", *_gpa(60_000_000, 0, (-50.125, 0, 0)))
    w.close()
    (fix,), tally, _ = _fixes(tmp_path / "f.bin")
    assert fix.record.alt_m == 182.082  # 131.957 + 50.125
    assert dict(tally.heights) == {"undulation": 1}


# PX4's GNSS message across releases (ULog formats as its logger writes them): v1.11-1.12
# vehicle_gps_position and v1.13 sensor_gps in 1e-7 degree / mm integers; v1.15
# sensor_gps in doubles, fix_type moved up, more fields (v1.14's is in writers.py)
# v1.11-1.12: v1.13's vehicle_gps_position with a `selected` receiver byte
_INT_FIELDS = (*VEHICLE_GPS_POSITION_V113[:-1], ("uint8_t", "selected"),
               ("uint8_t[3]", "_padding0"))
_V113_SENSOR_GPS = (("uint64_t", "timestamp"), ("uint64_t", "timestamp_sample"),
                    ("uint32_t", "device_id"), *_INT_FIELDS[1:])
_V115_SENSOR_GPS = (
    ("uint64_t", "timestamp"), ("uint64_t", "timestamp_sample"), ("uint32_t", "device_id"),
    ("double", "latitude_deg"), ("double", "longitude_deg"), ("double", "altitude_msl_m"),
    ("double", "altitude_ellipsoid_m"), ("float", "s_variance_m_s"),
    ("float", "c_variance_rad"), ("uint8_t", "fix_type"), ("float", "eph"), ("float", "epv"),
    ("float", "hdop"), ("float", "vdop"), ("int32_t", "noise_per_ms"),
    ("uint16_t", "automatic_gain_control"), ("uint8_t", "jamming_state"),
    ("int32_t", "jamming_indicator"), ("uint8_t", "spoofing_state"), ("float", "vel_m_s"),
    ("float", "vel_n_m_s"), ("float", "vel_e_m_s"), ("float", "vel_d_m_s"),
    ("float", "cog_rad"), ("bool", "vel_ned_valid"), ("int32_t", "timestamp_time_relative"),
    ("uint64_t", "time_utc_usec"), ("uint8_t", "satellites_used"), ("float", "heading"),
    ("float", "heading_offset"), ("float", "heading_accuracy"),
    ("float", "rtcm_injection_rate"), ("uint8_t", "selected_rtcm_instance"),
    ("uint8_t[5]", "_padding0"))


@pytest.mark.parametrize(("topic", "fields"), [
    ("vehicle_gps_position", _INT_FIELDS),  # v1.11, v1.12
    ("sensor_gps", _V113_SENSOR_GPS),  # v1.13, sensor_gps only
    ("sensor_gps", _V115_SENSOR_GPS),  # v1.15
])
def test_ulog_gnss_layouts_of_px4_releases(tmp_path, topic, fields):
    """Two receivers (multi_id 0 and 1), the first three fixes before UTC, a logged
    string and a dropout between: each value as the release's fields give it."""
    from estimator.importers.ulog import Reader as ULogReader
    from tests.estimator.importers.writers import ULogWriter, _pack

    w = ULogWriter(tmp_path / "px4.ulg")
    dtype = w.format(topic, fields)
    ids = [w.add_logged(topic, m) for m in (0, 1)]
    w.logged_string(ord("6"), 29_000_000, "[gps] u-blox firmware version: SPG 5.10")
    for k in range(10):
        for m, msg_id in enumerate(ids):
            lat_e7 = 367_136_672 + k + 1000 * m
            w.data(msg_id, _pack(dtype, {
                "timestamp": 30_000_000 + 200_000 * k,
                "time_utc_usec": 0 if k < 3 else UTC_NS // 1000 + 200_000 * k,
                "lat": lat_e7, "lon": -44_791_287, "alt": 131_960, "alt_ellipsoid": 182_085,
                "latitude_deg": lat_e7 / 1e7, "longitude_deg": -4.4791287,
                "altitude_msl_m": 131.96, "altitude_ellipsoid_m": 182.085,
                "eph": 0.9 + 3 * m, "epv": 1.42, "fix_type": 3 if k else 1,
                "satellites_used": 20 - m}))
        if k == 5:
            w.dropout(40)
    w.close()
    for m in (0, 1):
        reader = ULogReader(tmp_path / "px4.ulg", GnssOptions(topic=f"{topic}[{m}]"))
        tally = Tally()
        fixes = list(reader.records(tally))
        assert dict(tally.counts.rejected) == {"no_utc": 3}
        assert [f.utc_ns for f in fixes] == [UTC_NS + 200_000_000 * k for k in range(3, 10)]
        assert [f.record.lat_deg for f in fixes] == [
            round(36.7136672 + (k + 1000 * m) * 1e-7, 7) for k in range(3, 10)]
        assert {(f.record.lon_deg, f.record.alt_m, f.record.acc_m, f.record.vacc_m,
                 f.record.sats, f.record.fix) for f in fixes} == {
            (-4.4791287, 182.085, 0.9 + 3 * m, 1.42, 20 - m, "3d")}
        assert dict(tally.heights) == {"ellipsoid": 7}


def _fmt_message(type_id, length, name, fmt, columns):
    import struct

    return b"\xa3\x95\x80" + struct.pack("<BB4s16s64s", type_id, length, name, fmt, columns)


@pytest.mark.parametrize("bad_fmt", [
    _fmt_message(200, 10, b"XXX", b"zz", b"a,b"),  # format characters that do not exist
    _fmt_message(131, 12, b"GPA", b"QB", b"TimeUS,I"),  # GPA again, another layout
    _fmt_message(201, 2, b"YY", b"", b""),  # shorter than a message header
], ids=["unknown-format-chars", "gpa-redefined", "too-short"])
def test_dataflash_bad_fmt_bytes_in_a_corrupt_stretch(tmp_path, bad_fmt):
    """A corrupt stretch holding what looks like an FMT message: bad bytes like any
    other (ArduPilot defines each type once in a log), counted, and every fix kept."""
    junk = b"\xa3\x95\x07" + bad_fmt
    rows = [(_gps(60_000_000 + 200_000 * k, 0, 13_196, ms=WEEK_MS + 200 * k),
             _gpa(60_000_000 + 200_000 * k, 0, (-50.125, 0, 0))) for k in range(50)]
    path = ardupilot_log(tmp_path / "a.bin", GPA_UND, rows)
    data = path.read_bytes()
    cut = data.index(b"\xa3\x95\x82", len(data) - 40 * 90)  # a GPS message
    path.write_bytes(data[:cut] + junk + data[cut:])
    fixes, tally, _ = _fixes(path)
    assert len(fixes) == 50
    assert {(f.record.alt_m, f.record.acc_m) for f in fixes} == {(182.085, 0.9)}
    assert dict(tally.counts.rejected) == {"corrupt_bytes": len(junk)}


def _as_text_log(binary, text):
    """The log as Mission Planner's text ``.log``: one line a message, its values as
    pymavlink reads them (float32 fields in their shortest form)."""
    import numpy as np
    from pymavlink import DFReader

    df = DFReader.DFReader_binary(str(binary), zero_time_base=True)
    lines = []
    while (m := df.recv_msg()) is not None:
        values = []
        for c, code in zip(m.fmt.columns, m.fmt.format, strict=True):
            v = getattr(m, c)
            values.append(str(np.float32(v)) if code == "f" else str(v))
        lines.append(", ".join([m.get_type(), *values]))
    df.close()
    text.write_text("\r\n".join(lines) + "\r\n")
    return text


def test_dataflash_text_log_reads_as_the_binary_log(tmp_path):
    """Mission Planner converts the ``.bin`` it downloads to a text ``.log`` (and users
    share that): it reads to the same fixes, for either receiver."""
    rows = []
    for k in range(6):
        t = 60_000_000 + 200_000 * k
        rows.append((_gps(t, 0, 13_196 + k, ms=WEEK_MS + 200 * k), _gpa(t, 0, (-50.125, 0, 0))))
        rows.append((_gps(t + 9, 1, 13_496, ms=WEEK_MS + 200 * k),
                     (t + 9, 1, 180, 300, 450, 60, 0.0, 1, t // 1000, 200, -50.125, 0, 0)))
    binary = ardupilot_log(tmp_path / "00000007.BIN", GPA_UND, rows)
    text = _as_text_log(binary, tmp_path / "00000007.log")
    assert text.read_text().startswith("FMT, 128, 89, FMT, BBnNZ, Type,Length,Name,Format")
    for topic in (None, "GPS[1]"):
        want, want_tally, _ = _fixes(binary, topic=topic)
        got, tally, source = _fixes(text, topic=topic)
        assert [(f.record, f.utc_ns) for f in got] == [(f.record, f.utc_ns) for f in want]
        assert len(got) == 6
        assert tally.counts.unknown_types == want_tally.counts.unknown_types
        assert source.label == f"{'GPS[0]' if topic is None else 'GPS[1]'} with GPA (text log)"
    assert got[0].record.alt_m == 185.085 and got[0].record.acc_m == 3.0
    from estimator.importers import detect_format

    assert detect_format(text) == "dataflash"


def test_ulog_with_appended_hardfault_data(tmp_path):
    """PX4 appends a hardfault's text after the end of a log (flag bits: data appended,
    its offset); the fixes before it are all read, nothing is counted as corrupt."""
    import struct

    from estimator.importers.ulog import Reader as ULogReader
    from tests.estimator.importers.writers import SENSOR_GPS_V114, ULogWriter, _pack

    path = tmp_path / "hardfault.ulg"
    w = ULogWriter(path)
    dtype = w.format("sensor_gps", SENSOR_GPS_V114)
    msg_id = w.add_logged("sensor_gps", 0)
    for k in range(30):
        w.data(msg_id, _pack(dtype, {
            "timestamp": 30_000_000 + 200_000 * k, "time_utc_usec": UTC_NS // 1000 + 200_000 * k,
            "latitude_deg": 36.7136672, "longitude_deg": -4.4791287,
            "altitude_ellipsoid_m": 182.085, "eph": 0.9, "epv": 1.42, "fix_type": 3}))
    w.fh.flush()
    appended_at = w.fh.tell()
    for part in range(3):  # info-multiple messages, as hardfault_log writes them
        text = b"[hardfault] R0 0x2001f3c8 R1 0x00000000 " * 8
        key = f"char[{len(text)}] hardfault_plain".encode()
        w._msg(b"M", bytes([part > 0, len(key)]) + key + text)
    w.close()
    data = bytearray(path.read_bytes())
    data[16 + 3 + 8] = 1  # incompat flag 0: data appended
    data[16 + 3 + 16:16 + 3 + 24] = struct.pack("<Q", appended_at)
    path.write_bytes(bytes(data))
    reader = ULogReader(path, GnssOptions())
    tally = Tally()
    fixes = list(reader.records(tally))
    assert len(fixes) == 30 and dict(tally.counts.rejected) == {}
    assert fixes[-1].utc_ns == UTC_NS + 29 * 200_000_000


def test_ulog_other_gnss_streams_are_counted_as_other_records(tmp_path):
    """As a DataFlash log's second receiver is: the GNSS streams not read (the other
    multi_id, the other topic) are other records, so that a refusal names them."""
    from estimator.importers import ImportOptions, ImportRefused, import_flight
    from estimator.importers.ulog import Reader as ULogReader
    from tests.estimator.importers.writers import SENSOR_GPS_V114, ULogWriter, _pack

    path = tmp_path / "px4.ulg"
    w = ULogWriter(path)
    dtypes = {t: w.format(t, SENSOR_GPS_V114) for t in ("sensor_gps", "vehicle_gps_position")}
    ids = {(t, m): w.add_logged(t, m) for t in dtypes for m in (0, 1)}
    for k in range(30):
        v = {"timestamp": 30_000_000 + 200_000 * k, "time_utc_usec": UTC_NS // 1000,
             "latitude_deg": 36.7, "longitude_deg": -4.4, "altitude_ellipsoid_m": 182.0,
             "eph": 0.9, "fix_type": 3}
        for (t, m), msg_id in ids.items():
            if m == 0 or k % 3 == 0:  # the second receivers at a third of the rate
                # the blended vehicle_gps_position has no UTC here
                w.data(msg_id, _pack(dtypes[t], dict(v, time_utc_usec=0) if
                                     t == "vehicle_gps_position" else v))
    w.close()

    def others(topic):
        tally = Tally()
        list(ULogReader(path, GnssOptions(topic=topic)).records(tally))
        return dict(tally.counts.unknown_types)

    assert others(None) == {"vehicle_gps_position[1]": 10, "sensor_gps[0]": 30,
                            "sensor_gps[1]": 10}
    assert others("sensor_gps[1]") == {"sensor_gps[0]": 30}  # only that topic is loaded
    rtt = tmp_path / "rtt.csv"
    rtt.write_text("utc_ms,bssid,status,distance_mm,distance_std_dev_mm,rssi\n"
                   f"{UTC_NS // 1_000_000 + 100},a4:77:33:0f:1e:02,0,50000,1500,-70\n")
    with pytest.raises(ImportRefused, match=r"no usable fix \(vehicle_gps_position\[0\]; "
                       r"skipped: no_utc=30; other records: .*sensor_gps\[0\]=30"):
        import_flight(path, rtt, tmp_path / "c.jsonl", ImportOptions())


def test_dataflash_text_log_bad_lines_are_counted(tmp_path):
    """A text log's line with a byte that is not UTF-8, or text where a number belongs,
    is skipped and counted; the file is read (it was refused whole)."""
    rows = [(_gps(60_000_000 + 200_000 * k, 0, 13_196, ms=WEEK_MS + 200 * k),
             _gpa(60_000_000 + 200_000 * k, 0, (-50.125, 0, 0))) for k in range(6)]
    binary = ardupilot_log(tmp_path / "a.bin", GPA_UND, rows)
    text = _as_text_log(binary, tmp_path / "a.log")
    lines = text.read_bytes().split(b"\r\n")
    gps = [k for k, line in enumerate(lines) if line.startswith(b"GPS, ")]
    lines[gps[1]] = lines[gps[1]].replace(b"36.7136672", b"36.71\xb036672")  # Latin-1 degree
    lines[gps[3]] = lines[gps[3]].replace(b", 20, ", b", n/a, ")  # NSats
    text.write_bytes(b"\r\n".join(lines))
    fixes, tally, _ = _fixes(text)
    assert [f.utc_ns for f in fixes] == [UTC_NS + k * 200_000_000 for k in (0, 2, 4, 5)]
    assert dict(tally.counts.rejected) == {"not_utf8": 1, "bad_type": 1}


def test_dataflash_gps_defined_after_a_corrupt_stretch(tmp_path):
    """ArduPilot writes the GPS FMT when the receiver is first detected, which can be
    after a corrupt stretch near the start of the log: the fixes are read."""
    from tests.estimator.importers.writers import DF_IMU

    w = DataFlashWriter(tmp_path / "late.bin")
    w.define(133, DF_IMU)
    for k in range(5):
        w.write("IMU", 1000 * k, 0, 0.01, 0.0, 0.0, 0.1, 0.0, -9.8, 0, 0, 35.0, 1, 1, 1000, 1000)
    w.raw(b"\xa3\x95\x07 bad")
    w.define(130, DF_GPS)
    w.define(131, GPA_UND)
    for k in range(4):
        w.write("GPS", *_gps(60_000_000 + 200_000 * k, 0, 13_196, ms=WEEK_MS + 200 * k))
        w.write("GPA", *_gpa(60_000_000 + 200_000 * k, 0, (-50.125, 0, 0)))
    w.close()
    fixes, tally, _ = _fixes(tmp_path / "late.bin")
    assert [f.utc_ns for f in fixes] == [UTC_NS + k * 200_000_000 for k in range(4)]
    assert {f.record.alt_m for f in fixes} == {182.085}
    assert dict(tally.counts.rejected) == {"corrupt_bytes": 7}


def test_ulog_ellipsoidal_heights_that_are_msl_heights_are_warned_about(tmp_path):
    """PX4's simulators and HIL_GPS write altitude_ellipsoid_m = altitude_msl_m: the
    heights are read as the file gives them, with a warning that N is missing."""
    from estimator.importers.ulog import Reader as ULogReader
    from tests.estimator.importers.writers import SENSOR_GPS_V114, ULogWriter, _pack

    for name, ellipsoid_m, warned in (("copied", 131.96, True), ("real", 182.085, False)):
        path = tmp_path / f"{name}.ulg"
        w = ULogWriter(path)
        dtype = w.format("sensor_gps", SENSOR_GPS_V114)
        msg_id = w.add_logged("sensor_gps", 0)
        for k in range(5):
            w.data(msg_id, _pack(dtype, {
                "timestamp": 30_000_000 + 200_000 * k, "time_utc_usec": UTC_NS // 1000,
                "latitude_deg": 36.7, "longitude_deg": -4.4, "altitude_msl_m": 131.96,
                "altitude_ellipsoid_m": ellipsoid_m, "eph": 0.9, "fix_type": 3}))
        w.close()
        reader = ULogReader(path, GnssOptions())
        fixes = list(reader.records(Tally()))
        assert {f.record.alt_m for f in fixes} == {ellipsoid_m}
        assert any("equal the MSL heights" in x for x in reader.source.warnings) == warned
