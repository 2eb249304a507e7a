"""Recorder files as phones, spreadsheets and loggers leave them: a UTF-8 byte order mark
(Excel's "CSV UTF-8", Windows Notepad), CRLF line endings, columns reordered and extra
ones, several talkers in one NMEA file. Each imports to the same records as the plain
file the tests write."""

from __future__ import annotations

import contextlib
import dataclasses
import shutil
import tempfile

import numpy as np
import pytest

from estimator.importers import ImportOptions, ImportRefused, import_flight
from estimator.logio import read_log
from tests.estimator.importers.writers import (
    DataFlashWriter,
    gps_week_ms,
    mcap_messages,
    storage_file,
    write_android_csv,
    write_gnsslogger,
    write_nmea,
    write_rosbag,
)

BOM = "\ufeff"


def _import(gnss, rtt, out):
    report = import_flight(gnss, rtt, out, ImportOptions())
    return report.to_json(), read_log(out)


def test_a_byte_order_mark_hides_no_column(flight, tmp_path):
    """With a BOM the first column's name read "\\ufeffutc_ms": the file lost its UTC
    column, was joined on the phone's clock alone and warned that it had no UTC."""
    gnss = write_gnsslogger(tmp_path / "gnss_log.txt", flight)
    plain = write_android_csv(tmp_path / "plain.csv", flight)
    text = plain.read_text(encoding="utf-8")
    lines = text.splitlines()
    cols = lines[0].split(",")
    assert cols[0] == "utc_ms"
    # Excel's export: BOM, CRLF, the columns in another order and one more column
    order = list(reversed(range(len(cols))))
    rows = [",".join([*(cols[i].upper() for i in order), "note"])]
    rows += [",".join([*(r.split(",")[i] for i in order), "x"]) for r in lines[1:]]
    excel = tmp_path / "excel.csv"
    excel.write_bytes((BOM + "\r\n".join(rows) + "\r\n").encode("utf-8"))
    ref_j, ref = _import(gnss, plain, tmp_path / "ref.jsonl")
    got_j, got = _import(gnss, excel, tmp_path / "got.jsonl")
    assert got_j["warnings"] == ref_j["warnings"] == []
    assert got_j["time"]["utc_offsets_s"] == ref_j["time"]["utc_offsets_s"]
    assert "ranges" in got_j["time"]["utc_offsets_s"]
    assert got.rtt == ref.rtt and len(got.rtt) == len(flight.rtt)
    assert got_j["ranges"]["skipped"] == {}


def test_bom_before_the_first_nmea_sentence_and_gnsslogger_header(flight, tmp_path):
    rtt = write_android_csv(tmp_path / "rtt.csv", flight, elapsed=False)
    nmea = write_nmea(tmp_path / "plain.nmea", flight)
    bom_nmea = tmp_path / "bom.nmea"
    bom_nmea.write_bytes(BOM.encode() + nmea.read_bytes())
    ref_j, ref = _import(nmea, rtt, tmp_path / "ref.jsonl")
    got_j, got = _import(bom_nmea, rtt, tmp_path / "got.jsonl")
    assert got_j["gnss"]["records_read"] == ref_j["gnss"]["records_read"] == len(flight.gnss)
    assert got_j["gnss"]["other_records"] == ref_j["gnss"]["other_records"]
    assert got.gnss == ref.gnss
    # GnssLogger whose first line is its Fix column comment (columns in its own order)
    gl = write_gnsslogger(tmp_path / "gl.txt", flight)
    lines = [ln for ln in gl.read_text().splitlines() if ln.startswith(("# Fix", "Fix,GPS"))]
    head = lines[0].removeprefix("# ").split(",")
    swap = list(range(len(head)))
    swap[2], swap[3] = 3, 2  # longitude before latitude
    body = ["# " + ",".join(head[i] for i in swap)]
    body += [",".join(ln.split(",")[i] for i in swap) for ln in lines[1:]]
    bom_gl = tmp_path / "bom_gl.txt"
    bom_gl.write_bytes((BOM + "\n".join(body) + "\n").encode())
    rtt2 = write_android_csv(tmp_path / "rtt2.csv", flight)
    gl_j, gl_log = _import(bom_gl, rtt2, tmp_path / "gl.jsonl")
    _, plain_log = _import(gl, rtt2, tmp_path / "gl_plain.jsonl")
    assert gl_j["gnss"]["records_read"] == len(flight.gnss)
    assert gl_log.gnss == plain_log.gnss  # latitude and longitude from their own columns
    assert 35.0 < gl_log.gnss[0].lat_deg < 38.0 and -5.0 < gl_log.gnss[0].lon_deg < -4.0


# ArduPilot before 4.1: no instance column; the second receiver logs GPS2 and GPA2
OLD_GPS = "QBIHBcLLeffffB", "TimeUS,Status,GMS,GWk,NSats,HDop,Lat,Lng,Alt,Spd,GCrs,VZ,Yaw,U"
OLD_GPA = "QCCCCBCH", "TimeUS,VDop,HAcc,VAcc,SAcc,VV,SMS,Delta"


def _old_dataflash(path, flight):
    w = DataFlashWriter(path)
    for k, name in enumerate(("GPS", "GPS2")):
        w.define(129 + k, (name, *OLD_GPS))
    for k, name in enumerate(("GPA", "GPA2")):
        w.define(131 + k, (name, *OLD_GPA))
    for k, g in enumerate(flight.gnss):
        t_us = 60_000_000 + (g.t_ns - flight.t0_ns) // 1000
        week, ms = gps_week_ms(flight.utc_ns(g.t_ns))
        msl_cm = round((g.alt_m - 50.0) * 100)
        lat, lon = round(g.lat_deg * 1e7), round(g.lon_deg * 1e7)
        w.write("GPS", t_us, 3, ms, week, 12, 70, lat, lon, msl_cm, 6.5, 90.0, -0.1, 0.0, 1)
        w.write("GPA", t_us, 110, round(g.acc_m * 100), 150, 40, 1, 0, 100)
        if k % 2 == 0:  # the second receiver: 2e-5 degrees north, 3 m up, HAcc 4 m
            w.write("GPS2", t_us + 3, 3, ms, week, 8, 180, lat + 200, lon, msl_cm + 300, 6.5,
                    90.0, -0.1, 0.0, 1)
            w.write("GPA2", t_us + 3, 110, 400, 600, 40, 1, 0, 100)
    w.close()
    return path


def test_dataflash_before_instances_second_receiver_is_gps2(flight, tmp_path):
    df = _old_dataflash(tmp_path / "old.bin", flight)
    rtt = write_android_csv(tmp_path / "rtt.csv", flight, elapsed=False)
    first_j, first = _import(df, rtt, tmp_path / "first.jsonl")
    n2 = (len(flight.gnss) + 1) // 2
    assert first_j["gnss"]["records_read"] == len(flight.gnss)
    assert first_j["gnss"]["other_records"] == {"GPS[1]": n2}  # counted, not silent
    for topic in ("GPS[1]", "GPS2"):
        out = tmp_path / f"second-{topic}.jsonl"
        j = import_flight(df, rtt, out, ImportOptions(topic=topic, geoid_offset_m=50.0)
                          ).to_json()
        second = read_log(out)
        assert j["gnss"]["stream"] == "GPS2 with GPA2"
        assert j["gnss"]["records_read"] == n2
        assert j["gnss"]["other_records"] == {"GPS[0]": len(flight.gnss)}
        by_t = {g.t_ns: g for g in first.gnss}
        pairs = [(s, by_t[s.t_ns]) for s in second.gnss if s.t_ns in by_t]
        assert len(pairs) > 0.9 * len(second.gnss)
        for s, f in pairs:
            assert s.lat_deg == pytest.approx(f.lat_deg + 2e-5, abs=1e-9)
            assert s.alt_m == pytest.approx(f.alt_m + 3.0 + 50.0, abs=1e-6)  # MSL + N
            assert (s.acc_m, s.vacc_m) == (4.0, 6.0)
    with pytest.raises(ImportRefused, match=r"old.bin: no GPS3 messages"):
        import_flight(df, rtt, tmp_path / "x.jsonl", ImportOptions(topic="GPS[2]"))


def test_a_bag_without_covariance_says_how_to_give_an_accuracy(flight, tmp_path):
    bag = write_rosbag(tmp_path / "bag", flight, covariance=False, extra_topic=False)
    rtt = write_android_csv(tmp_path / "rtt.csv", flight, elapsed=False)
    with pytest.raises(ImportRefused, match=r"bag: no usable fix .*no_accuracy=\d+\): the "
                                            r"file gives no accuracy; give one with "
                                            r"--gnss-acc M$"):
        import_flight(bag, rtt, tmp_path / "x.jsonl", ImportOptions())
    j = import_flight(bag, rtt, tmp_path / "y.jsonl", ImportOptions(gnss_acc_m=2.5)).to_json()
    assert j["gnss"]["records_read"] == len(flight.gnss)
    assert {g.acc_m for g in read_log(tmp_path / "y.jsonl").gnss} == {2.5}


def test_semicolon_and_tab_separated_exports_read_as_the_comma_file(flight, tmp_path):
    """A spreadsheet where the comma is the decimal mark (Spain, Germany...) saves "CSV"
    with semicolons; a tab-separated export alike. Recognised from content and read to
    the same records; a decimal comma in a number is counted as bad_type."""
    gnss = write_gnsslogger(tmp_path / "gnss_log.txt", flight)
    plain = write_android_csv(tmp_path / "plain.csv", flight)
    _, ref = _import(gnss, plain, tmp_path / "ref.jsonl")
    text = plain.read_text()
    for sep, name in ((";", "semi.csv"), ("\t", "tabs.txt")):
        f = tmp_path / name
        f.write_text(text.replace(",", sep))
        j, got = _import(gnss, f, tmp_path / f"{name}.jsonl")
        assert j["ranges"]["format"] == "android-csv"
        assert got.rtt == ref.rtt and j["ranges"]["skipped"] == {}
    lines = text.splitlines()
    ok_row = next(ln for ln in lines[1:] if ln.split(",")[3] == "0")
    cells = ok_row.split(",")
    cells[4] = cells[4] + ",5"  # distance_mm "12345,5": a decimal comma
    f = tmp_path / "decimal.csv"
    rows = [ln.replace(",", ";") for ln in lines if ln != ok_row] + [";".join(cells)]
    f.write_text("\n".join(rows) + "\n")
    j, got = _import(gnss, f, tmp_path / "d.jsonl")
    assert j["ranges"]["skipped"] == {"bad_type": 1}
    assert len(got.rtt) == len(ref.rtt) - 1


def test_gnsslogger_without_gps_fixes_names_the_providers_it_has(flight, tmp_path):
    """A phone with the GPS provider off logs only fused (FLP) fixes: the refusal says
    so and how to read them."""
    gl = write_gnsslogger(tmp_path / "gl.txt", flight)
    only_flp = tmp_path / "flp.txt"
    only_flp.write_text("\n".join(ln for ln in gl.read_text().splitlines()
                                  if not ln.startswith("Fix,GPS")) + "\n")
    rtt = write_android_csv(tmp_path / "rtt.csv", flight)
    with pytest.raises(ImportRefused, match=r"flp.txt: no usable fix \(Fix lines of provider "
                                            r"GPS; other records: Fix FLP=\d+.*\): fixes of "
                                            r"FLP are there; name one with --topic$"):
        import_flight(only_flp, rtt, tmp_path / "x.jsonl", ImportOptions())
    j = import_flight(only_flp, rtt, tmp_path / "y.jsonl", ImportOptions(topic="FLP")
                      ).to_json()
    assert j["gnss"]["records_read"] == (len(flight.gnss) + 9) // 10


def test_times_a_spreadsheet_rounded_are_skipped_not_misplaced(flight, tmp_path):
    """Excel shows a 13-digit utc_ms as 1.74972E+12 and saves it so: 1749720000000, up to
    hours off. Such a time is skipped (rounded_time); an exponent form with every digit
    is exact and read."""
    gnss = write_gnsslogger(tmp_path / "gnss_log.txt", flight)
    plain = write_android_csv(tmp_path / "plain.csv", flight, elapsed=False)
    lines = plain.read_text().splitlines()
    cols = lines[0].split(",")
    k = cols.index("utc_ms")
    rows = [ln.split(",") for ln in lines[1:]]
    for r in rows[:10]:  # as Excel saves them
        r[k] = f"{int(r[k]):.5E}"
    exact = rows[10][k]
    rows[10][k] = f"{int(exact[0])}.{exact[1:]}E+{len(exact) - 1}"  # every digit kept
    f = tmp_path / "excel.csv"
    f.write_text("\n".join([lines[0], *(",".join(r) for r in rows)]) + "\n")
    _, ref = _import(gnss, plain, tmp_path / "ref.jsonl")
    j, got = _import(gnss, f, tmp_path / "got.jsonl")
    assert j["ranges"]["skipped"] == {"rounded_time": 10}
    assert got.rtt == ref.rtt[10:]  # the exact exponent form read to the same time


def test_gnsslogger_nan_accuracies_mean_unknown(flight, tmp_path):
    """Apps writing the GnssLogger format leave an accuracy they do not have as "NaN":
    an unknown accuracy (as an empty one), never a reason to drop the fix. A NaN
    vertical accuracy is left out; a NaN horizontal one is no_accuracy (kept with
    --gnss-acc)."""
    gl = write_gnsslogger(tmp_path / "gl.txt", flight)
    rtt = write_android_csv(tmp_path / "rtt.csv", flight)
    out, k = [], 0
    for ln in gl.read_text().splitlines():
        if ln.startswith("Fix,GPS"):
            cells = ln.split(",")
            if k % 2 == 0:
                cells[12] = "NaN"  # VerticalAccuracyMeters
            if k == 1001:
                cells[6] = "nan"  # AccuracyMeters
            ln, k = ",".join(cells), k + 1
        out.append(ln)
    nan = tmp_path / "nan.txt"
    nan.write_text("\n".join(out) + "\n")
    j, log = _import(nan, rtt, tmp_path / "nan.jsonl")
    assert j["gnss"]["skipped"] == {"no_accuracy": 1}
    assert j["gnss"]["records_read"] == len(flight.gnss) - 1
    _, ref = _import(gl, rtt, tmp_path / "ref.jsonl")
    by_t = {g.t_ns: g for g in ref.gnss}
    n_unknown = 0
    for g in log.gnss:
        r = by_t[g.t_ns]
        assert (g.lat_deg, g.lon_deg, g.alt_m, g.acc_m) == (r.lat_deg, r.lon_deg, r.alt_m,
                                                          r.acc_m)
        assert g.vacc_m in (None, r.vacc_m)
        n_unknown += g.vacc_m is None
    assert n_unknown == sum(1 for g in ref.gnss if g.t_ns in {f.t_ns for f in flight.gnss[::2]})
    kept = import_flight(nan, rtt, tmp_path / "acc.jsonl", ImportOptions(gnss_acc_m=3.0))
    assert kept.to_json()["gnss"]["records_read"] == len(flight.gnss)
    given = next(g for g in read_log(tmp_path / "acc.jsonl").gnss
                 if g.t_ns == flight.gnss[1001].t_ns)
    assert given.acc_m == 3.0 and given.vacc_m == flight.gnss[1001].vacc_m


QOS_EDIT = """offered_qos_profiles:
      - history: keep_last
        depth: 10
        reliability: best_effort
        durability: volatile
        deadline:
          sec: 9223372036
          nsec: 854775807
        lifespan:
          sec: 9223372036
          nsec: 854775807
        liveliness: automatic
        liveliness_lease_duration:
          sec: 9223372036
          nsec: 854775807
        avoid_ros_namespace_conventions: false"""


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_a_bag_whose_metadata_qos_was_edited_is_read(flight, tmp_path, storage):
    """Editing a topic's offered_qos_profiles in metadata.yaml is a common cure for
    ``ros2 bag play`` QoS mismatches; rosbags then pairs no storage connection with the
    topic and yields none of its messages, and the import said "no usable fix" with
    nothing skipped. The storage files are read without the metadata instead."""
    bag = write_rosbag(tmp_path / "bag", flight, storage=storage)
    meta = bag / "metadata.yaml"
    text = meta.read_text()
    assert text.count("offered_qos_profiles: []") == 2  # /fix first, then /battery
    meta.write_text(text.replace("offered_qos_profiles: []", QOS_EDIT, 1))
    rtt = write_android_csv(tmp_path / "rtt.csv", flight)
    j, log = _import(bag, rtt, tmp_path / "edited.jsonl")
    assert j["gnss"]["records_read"] == len(flight.gnss) and j["gnss"]["skipped"] == {}
    assert j["gnss"]["other_records"] == {"/battery": (len(flight.gnss) + 9) // 10}
    assert any("metadata.yaml" in w and "/fix" in w for w in j["warnings"])
    _, ref = _import(storage_file(bag), rtt, tmp_path / "ref.jsonl")
    assert log.gnss == ref.gnss


def test_a_crashed_bag_write_ahead_log_is_read(flight, tmp_path, monkeypatch):
    """``ros2 bag record --storage-preset-profile resilient`` keeps SQLite in WAL mode:
    when the recorder dies (a drone's power lost), the last messages are still in
    bag.db3-wal and there is no metadata.yaml. rosbags opens the database as immutable
    and never sees them: the import silently lost the end of the flight. They are read
    from a merged copy; the input files are not changed."""
    import sqlite3

    n = 1500
    part = write_rosbag(tmp_path / "part", dataclasses.replace(flight, gnss=flight.gnss[:n]),
                        extra_topic=False)
    full = write_rosbag(tmp_path / "full", flight, extra_topic=False)
    with contextlib.closing(sqlite3.connect(storage_file(full))) as src:
        rest = src.execute("SELECT topic_id, timestamp, data FROM messages "
                           "ORDER BY timestamp").fetchall()[n:]
    db = storage_file(part)
    crash = tmp_path / "crash"
    crash.mkdir()
    with contextlib.closing(sqlite3.connect(db)) as con:  # the recorder, still running
        assert con.execute("PRAGMA journal_mode=WAL").fetchone() == ("wal",)
        con.execute("PRAGMA wal_autocheckpoint=0")
        con.executemany("INSERT INTO messages(topic_id, timestamp, data) VALUES (?, ?, ?)",
                        rest)
        con.commit()
        for f in db.parent.iterdir():  # what the crash left: no metadata.yaml
            if f.name != "metadata.yaml":
                shutil.copy(f, crash / f.name)
    wal = crash / (db.name + "-wal")
    assert wal.stat().st_size > 100_000
    before = {f.name: f.read_bytes() for f in crash.iterdir()}
    rtt = write_android_csv(tmp_path / "rtt.csv", flight)
    _, ref = _import(storage_file(full), rtt, tmp_path / "ref.jsonl")
    temp = tmp_path / "temp"
    temp.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(temp))  # where the merged copy goes
    for bag in (crash, crash / db.name):
        j, log = _import(bag, rtt, tmp_path / "crash.jsonl")
        assert j["gnss"]["records_read"] == len(flight.gnss)
        assert log.gnss == ref.gnss
        assert any(f"{db.name}-wal" in w for w in j["warnings"])
    assert {f.name: f.read_bytes() for f in crash.iterdir()} == before
    assert list(temp.iterdir()) == []  # the copy removed


def test_a_crashed_mcap_recording_is_read_up_to_the_cut(flight, tmp_path, monkeypatch):
    """MCAP is ROS 2's default storage since Iron. A recorder that dies leaves the file
    without its summary and footer (and no metadata.yaml): rosbags refused it whole
    ("File end magic is invalid"), the flight lost. The whole records before the cut
    are read (from a copy closed with a footer), with a warning; the input is not
    changed."""
    bag = write_rosbag(tmp_path / "bag", flight, storage="mcap", extra_topic=False,
                       image_bytes=20_000)
    mcap = storage_file(bag)
    data = mcap.read_bytes()
    fixes = [m for m in mcap_messages(data) if m[2] < 1000]
    assert len(fixes) == len(flight.gnss)
    cut_at = (fixes[len(fixes) // 2][1] + fixes[len(fixes) // 2 + 5][1]) // 2  # mid-chunk
    crash = tmp_path / "crash"
    crash.mkdir()
    cut = crash / mcap.name
    cut.write_bytes(data[:cut_at])
    kept = sum(m[3] <= cut_at for m in fixes)
    assert 0.3 * len(fixes) < kept < len(fixes) // 2
    rtt = write_android_csv(tmp_path / "rtt.csv", flight, elapsed=False)
    _, ref = _import(mcap, rtt, tmp_path / "ref.jsonl")
    temp = tmp_path / "temp"
    temp.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(temp))
    for path in (crash, cut):
        j, log = _import(path, rtt, tmp_path / "cut.jsonl")
        assert j["gnss"]["records_read"] == kept
        assert any(f"{mcap.name}: the recording was cut off" in w for w in j["warnings"])
        assert log.gnss == ref.gnss[:len(log.gnss)] and len(log.gnss) > 0.25 * len(ref.gnss)
    assert cut.read_bytes() == data[:cut_at] and list(temp.iterdir()) == []


def test_a_csv_saved_by_excel_in_a_windows_encoding_is_read(flight, tmp_path):
    """Excel's plain "CSV (Comma delimited)" is saved in the Windows code page: a
    responder name such as "Café Señor" in an extra column is not UTF-8, and every row
    was skipped (not_utf8), the import refused. The fields used are ASCII: the rows
    read as the UTF-8 file's."""
    gnss = write_gnsslogger(tmp_path / "gnss_log.txt", flight)
    plain = write_android_csv(tmp_path / "plain.csv", flight)
    lines = plain.read_text().splitlines()
    rows = [lines[0] + ",ssid"] + [ln + ",Café Señor" for ln in lines[1:]]
    excel = tmp_path / "excel.csv"
    excel.write_bytes(("\r\n".join(rows) + "\r\n").encode("cp1252"))
    _, ref = _import(gnss, plain, tmp_path / "ref.jsonl")
    j, got = _import(gnss, excel, tmp_path / "got.jsonl")
    assert j["ranges"]["skipped"] == {} and got.rtt == ref.rtt
    assert len(got.rtt) == len(flight.rtt)


def test_nmea_logged_with_binary_ubx_messages_between_the_sentences(flight, tmp_path):
    """u-center logs a u-blox receiver's whole output: NMEA sentences with binary UBX
    messages between them (no line break after a UBX message, which holds any bytes).
    Every GGA behind one was lost (not_utf8, or a line not starting with "$"). The
    sentences are found where they start; the binary bytes are other records."""
    plain = write_nmea(tmp_path / "plain.nmea", flight)
    rng = np.random.default_rng(5)
    mixed = bytearray()
    for line in plain.read_bytes().split(b"\r\n"):
        if line.startswith(b"$GNGGA"):  # a UBX-NAV-PVT before it: sync, class, id, size
            mixed += b"\xb5\x62\x01\x07" + (92).to_bytes(2, "little") + rng.bytes(94)
        if line:
            mixed += line + b"\r\n"
    ubx = tmp_path / "COM7_250612_101158.ubx"
    ubx.write_bytes(bytes(mixed))
    rtt = write_android_csv(tmp_path / "rtt.csv", flight, elapsed=False)
    _, ref = _import(plain, rtt, tmp_path / "ref.jsonl")
    j, got = _import(ubx, rtt, tmp_path / "got.jsonl")
    assert j["gnss"]["format"] == "nmea" and j["gnss"]["skipped"] == {}
    assert j["gnss"]["records_read"] == len(flight.gnss) and got.gnss == ref.gnss
    assert j["gnss"]["other_records"]["GNGSA"] == len(flight.gnss)
