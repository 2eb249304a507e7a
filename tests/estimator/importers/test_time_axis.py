"""The clocks: GPS time to UTC, Java dates, NMEA's dates, the choice of the time axis."""

from __future__ import annotations

from datetime import UTC, datetime
from pathlib import Path

import pytest

from estimator.importers import ImportOptions, ImportRefused, import_flight
from estimator.importers.common import Source, Stamped
from estimator.importers.dataflash import gps_to_utc_ns
from estimator.importers.joiner import ClockStats, choose_axis
from estimator.importers.nmea import Reader as NmeaReader
from estimator.importers.sensorreadout import java_date_utc_ns
from estimator.records import RangeSample
from tests.estimator.importers.writers import (
    NS,
    Flight,
    gps_week_ms,
    write_android_csv,
    write_gnsslogger,
)


def _unix_ns(text: str) -> int:
    return int(datetime.fromisoformat(text).replace(tzinfo=UTC).timestamp()) * NS


def test_gps_week_and_milliseconds_to_utc_by_hand():
    # 2025-06-12T10:12:00Z = Unix 1749723120 s; GPS seconds = 1749723120 - 315964800 + 18
    # = 1433758338 = week 2370 (1433376000 s) + 382338 s
    assert gps_to_utc_ns(2370, 382_338_000) == 1_749_723_120 * NS
    # 2016-06-01T00:00:00Z (17 leap seconds then): Unix 1464739200
    gps_s = 1_464_739_200 - 315_964_800 + 17
    assert gps_to_utc_ns(gps_s // 604_800, gps_s % 604_800 * 1000) == 1_464_739_200 * NS
    # the first second of 2017 (18 s from then on) and the last of 2016 (17 s)
    jan1 = _unix_ns("2017-01-01T00:00:00")
    g = (jan1 // NS) - 315_964_800 + 18
    assert gps_to_utc_ns(g // 604_800, g % 604_800 * 1000) == jan1
    g = (jan1 // NS - 1) - 315_964_800 + 17
    assert gps_to_utc_ns(g // 604_800, g % 604_800 * 1000) == jan1 - NS
    # the tests' DataFlash writer agrees with the reader
    assert gps_to_utc_ns(*gps_week_ms(jan1 + 123_000_000)) == jan1 + 123_000_000


def test_java_dates():
    want = _unix_ns("2020-04-08T13:35:20")
    assert java_date_utc_ns("Wed Apr 08 15:35:20 GMT+02:00 2020") == want
    assert java_date_utc_ns("Wed Apr 08 15:35:20 CEST 2020") == want
    assert java_date_utc_ns("Wed Apr 08 13:35:20 UTC 2020") == want
    assert java_date_utc_ns("Wed Apr 08 09:35:20 EDT 2020") == want
    assert java_date_utc_ns("Wed Apr 08 08:05:20 GMT-05:30 2020") == want
    with pytest.raises(ValueError, match="time zone"):
        java_date_utc_ns("Wed Apr 08 15:35:20 CST 2020")  # China or US Central: ambiguous
    with pytest.raises(ValueError):
        java_date_utc_ns("2020-04-08 15:35:20")


def _nmea_line(body: str) -> str:
    cs = 0
    for ch in body.encode():
        cs ^= ch
    return f"${body}*{cs:02X}"


def test_nmea_fixes_after_midnight_take_the_next_day(tmp_path):
    lines = [
        _nmea_line("GPRMC,235959.50,A,3642.9000,N,00428.6800,W,1.0,90.0,311224,,,A"),
        _nmea_line("GPGGA,235959.90,3642.9000,N,00428.6800,W,1,12,0.60,100.0,M,50.0,M,,"),
        _nmea_line("GPGGA,000000.10,3642.9001,N,00428.6800,W,1,12,0.60,100.0,M,50.0,M,,"),
        _nmea_line("GPRMC,000000.50,A,3642.9001,N,00428.6800,W,1.0,90.0,010125,,,A"),
        _nmea_line("GPGGA,000000.90,3642.9002,N,00428.6800,W,4,12,0.60,100.0,M,50.0,M,,"),
    ]
    p = tmp_path / "midnight.nmea"
    p.write_text("\n".join(lines) + "\n")
    from estimator.importers.common import GnssOptions, Tally

    tally = Tally()
    got = list(NmeaReader(p, GnssOptions()).records(tally))
    assert [s.utc_ns for s in got] == [
        _unix_ns("2024-12-31T23:59:59") + 900_000_000,
        _unix_ns("2025-01-01T00:00:00") + 100_000_000,
        _unix_ns("2025-01-01T00:00:00") + 900_000_000,
    ]
    first = got[0].record
    assert first.lat_deg == pytest.approx(36 + 42.9 / 60, abs=1e-12)
    assert first.lon_deg == pytest.approx(-(4 + 28.68 / 60), abs=1e-12)
    assert first.alt_m == pytest.approx(150.0)  # MSL 100 + N 50
    assert first.acc_m == pytest.approx(0.9)  # 1.5 m x HDOP 0.6
    assert first.fix is None and got[2].record.fix == "rtk_fixed"


def _stats(stamps) -> ClockStats:
    st = ClockStats()
    for s in stamps:
        st.add(s)
    return st


def _range(utc_ns=None, elapsed_ns=None) -> Stamped:
    return Stamped(RangeSample(t_ns=0, bssid="a4:77:33:0f:1e:02", status="fail"),
                   utc_ns=utc_ns, elapsed_ns=elapsed_ns)


def _sources(tmp_path):
    return (Source(path=tmp_path / "g", format="gnsslogger", kind="gnss"),
            Source(path=tmp_path / "r", format="android-csv", kind="ranges"))


def test_the_axis_is_the_phone_clock_of_one_boot(tmp_path):
    boot = 1_749_000_000 * NS  # UTC at the phone's boot
    g = _stats(_range(boot + t, t) for t in range(10 * NS, 20 * NS, NS // 10))
    # the ranging file's UTC is 0.4 s off (another app's clock): still the same boot
    r = _stats(_range(boot + t + 400_000_000, t) for t in range(12 * NS, 18 * NS, NS // 5))
    axis = choose_axis(g, r, *_sources(tmp_path))
    assert axis.clock == "phone" and axis.alignment_uncertainty_ns == 0
    assert axis.gnss.t_ns(_range(boot + 15 * NS, 15 * NS)) == 15 * NS
    # offset: the median of both files' pairs; its uncertainty covers their spread
    assert boot <= axis.offset_ns <= boot + 400_000_000
    assert axis.offset_uncertainty_ns >= 200_000_000


def test_two_boots_are_joined_on_utc_onto_the_ranging_phones_clock(tmp_path):
    boot_a, boot_b = 1_749_000_000 * NS, 1_749_007_000 * NS  # restarted ~2 h later
    g = _stats(_range(boot_b + 5 * NS + t, boot_b + 5 * NS - boot_a + t)
               for t in range(0, 10 * NS, NS))
    r = _stats(_range(boot_b + 5 * NS + t, 5 * NS + t) for t in range(0, 10 * NS, NS))
    axis = choose_axis(g, r, *_sources(tmp_path))
    assert axis.clock == "utc" and "restarted" in axis.reason
    assert axis.ranges.t_ns(_range(boot_b + 7 * NS, 7 * NS)) == 7 * NS
    assert axis.gnss.t_ns(_range(boot_b + 7 * NS, boot_b + 7 * NS - boot_a)) == 7 * NS


def test_a_phone_clock_without_utc_is_taken_as_the_same_boot(tmp_path):
    boot = 1_749_000_000 * NS
    g = _stats(_range(boot + t, t) for t in range(10 * NS, 20 * NS, NS))
    r = _stats(_range(elapsed_ns=t) for t in range(12 * NS, 18 * NS, NS))  # no utc_ms
    gs, rs = _sources(tmp_path)
    axis = choose_axis(g, r, gs, rs)
    assert axis.clock == "phone" and axis.offset_ns == boot
    assert axis.ranges.t_ns(_range(elapsed_ns=13 * NS)) == 13 * NS
    assert rs.warnings and "not checked" in rs.warnings[0] and not gs.warnings


def test_without_a_common_clock_the_import_is_refused(tmp_path):
    g = _stats(_range(utc_ns=t) for t in range(NS, 5 * NS, NS))
    r = _stats(_range(elapsed_ns=t) for t in range(NS, 5 * NS, NS))  # phone clock only
    with pytest.raises(ImportRefused, match="cannot be put on one time axis"):
        choose_axis(g, r, *_sources(tmp_path))


def test_files_that_do_not_overlap_are_refused_in_one_line(flight, tmp_path):
    gnss = write_gnsslogger(tmp_path / "gnss_log.txt", flight)
    later = Flight(flight.header, flight.gnss, flight.rtt, flight.t0_ns,
                   flight.utc0_ns + 3600 * NS)  # the ranges of a flight an hour later
    rtt = write_android_csv(tmp_path / "rtt.csv", later, elapsed=False)
    out = tmp_path / "out.jsonl"
    with pytest.raises(ImportRefused) as err:
        import_flight(gnss, rtt, out, ImportOptions())
    text = str(err.value)
    assert "\n" not in text and "do not overlap" in text
    assert "ranges cover 2025-06-12T11:12:07" in text and "GNSS 2025-06-12T10:1" in text
    assert not out.exists() and list(Path(tmp_path).glob(".out*")) == []
