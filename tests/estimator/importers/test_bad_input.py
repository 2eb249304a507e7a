"""Bad input: every malformed line or message counted by reason, never a traceback,
never a good record lost; files that are not what they should be refused in one line."""

from __future__ import annotations

import dataclasses
import json
import re

import numpy as np
import pytest

from estimator.importers import ImportOptions, ImportRefused, detect_format, import_flight
from estimator.importers.common import GnssOptions, Tally
from estimator.importers.dataflash import Reader as DataFlashReader
from estimator.logio import read_log
from tests.estimator.importers.writers import (
    VEHICLE_GPS_POSITION_V113,
    Flight,
    logged_dtype,
    mcap_messages,
    storage_file,
    write_android_csv,
    write_dataflash,
    write_gnsslogger,
    write_nmea,
    write_rosbag,
    write_sensorreadout,
    write_ulog,
)

GOOD_FIX = ("Fix,GPS,36.7151,-4.4781,185.2,6.5,0.9,90.0,{utc},0.5,10.0,{el},1.4,0,20,0.3,")


def _run(gnss, rtt, tmp_path, **kw):
    out = tmp_path / "out.jsonl"
    report = import_flight(gnss, rtt, out, ImportOptions(**kw))
    return report.to_json(), read_log(out)


def test_gnsslogger_bad_lines_are_counted_and_the_good_ones_kept(flight, tmp_path):
    g = flight.gnss[len(flight.gnss) // 2]
    utc, el = flight.utc_ns(g.t_ns) // 1_000_000, g.t_ns
    bad = [
        GOOD_FIX.format(utc=utc, el=el).replace("36.7151", "abc"),  # bad_type
        GOOD_FIX.format(utc=utc, el=el).replace("36.7151", "95.0"),  # bad_latitude
        GOOD_FIX.format(utc=utc, el=el).replace("-4.4781", "-181.0"),  # bad_longitude
        GOOD_FIX.format(utc=utc, el=el).replace("185.2", "NaN"),  # non_finite
        GOOD_FIX.format(utc=utc, el=el).replace(",0.9,", ",-0.9,"),  # bad_value
        GOOD_FIX.format(utc=utc, el=el).replace(",0.9,", ",,"),  # no_accuracy
        GOOD_FIX.format(utc="", el=""),  # missing_field (no time at all)
        GOOD_FIX.format(utc=-5, el=el),  # negative_time
        "Fix,GPS,36.7",  # missing_field (cut)
        "Nav,1,2,3",  # another record type
    ]
    gnss = write_gnsslogger(tmp_path / "gnss_log.txt", flight, bad_lines=bad)
    with open(gnss, "ab") as fh:
        fh.write(b"Fix,GPS,\xff\xfe36.7,-4.4\n")  # not_utf8
    rtt = write_android_csv(tmp_path / "rtt.csv", flight)
    j, log = _run(gnss, rtt, tmp_path)
    assert j["gnss"]["skipped"] == {
        "bad_latitude": 1, "bad_longitude": 1, "bad_type": 1, "bad_value": 1,
        "missing_field": 2, "negative_time": 1, "no_accuracy": 1, "non_finite": 1,
        "not_utf8": 1}
    assert j["gnss"]["records_read"] == len(flight.gnss)  # every good fix read
    assert j["gnss"]["other_records"]["Nav"] == 1
    assert j["gnss"]["other_records"]["Fix FLP"] == (len(flight.gnss) + 9) // 10
    assert len(log.gnss) == j["gnss"]["written"]
    # --gnss-acc keeps the fix without an accuracy
    j2, _ = _run(gnss, rtt, tmp_path, gnss_acc_m=3.0)
    assert "no_accuracy" not in j2["gnss"]["skipped"]
    assert j2["gnss"]["records_read"] == len(flight.gnss) + 1


def test_csv_bad_rows_are_counted(flight, tmp_path):
    t = flight.utc_ns(flight.rtt[100].t_ns) // 1_000_000
    e = flight.rtt[100].t_ns
    row = "{t},{b},5180,{s},{d},{sd},-70,8,7,{e}"
    bad = [
        row.format(t=t, b="a4:77:33:0f:1e", s="0", d=1000, sd=10, e=e),  # bad_bssid
        row.format(t=t, b="a4:77:33:0f:1e:02", s="", d=1000, sd=10, e=e),  # missing_field
        row.format(t=t, b="a4:77:33:0f:1e:02", s="0", d="", sd=10, e=e),  # missing_field
        row.format(t=t, b="a4:77:33:0f:1e:02", s="0", d="nan", sd=10, e=e),  # non_finite
        row.format(t=t, b="a4:77:33:0f:1e:02", s="0", d=1000, sd=-3, e=e),  # bad_value
        row.format(t=t, b="a4:77:33:0f:1e:02", s="0", d="1km", sd=3, e=e),  # bad_type
        "1,2,3",  # wrong_column_count
        row.format(t=t, b="a4:77:33:0f:1e:02", s="0", d=1000, sd=10, e="") + ",x",
    ]
    rtt = write_android_csv(tmp_path / "rtt.csv", flight, bad_lines=bad, numeric_status=True,
                            upper_bssid=True)
    gnss = write_gnsslogger(tmp_path / "gnss_log.txt", flight)
    j, log = _run(gnss, rtt, tmp_path)
    assert j["ranges"]["skipped"] == {"bad_bssid": 1, "bad_type": 1, "bad_value": 1,
                                      "missing_field": 2, "non_finite": 1,
                                      "wrong_column_count": 2}
    assert j["ranges"]["written"] == len(flight.rtt)
    # numeric Android codes: 0 is ok, 1 is fail; upper-case MACs are written lower case
    assert {r.status for r in log.rtt} == {r.status for r in flight.rtt}
    assert all(r.bssid == r.bssid.lower() for r in log.rtt)
    ok = [r for r in log.rtt if r.ok]
    src = [r for r in flight.rtt if r.ok]
    assert [(r.range_m, r.range_std_m, r.rssi_dbm) for r in ok] == [
        (r.range_m, r.range_std_m, r.rssi_dbm) for r in src]


def test_nmea_bad_sentences(flight, tmp_path):
    bad = ["$GNGGA,101207.000,3642.9000,N,00428.6800,W,1,12,0.60,100.0,M,50.0,M,,*00",
           "$GNGGA,251207.000,3642.9000,N,00428.6800,W,1,12,0.60,100.0,M,50.0,M,,",
           "$GNGGA,101207.000,3642.9000,N,00428.6800,W,0,00,,,M,,M,,",
           "garbage line"]
    gnss = write_nmea(tmp_path / "gps.nmea", flight, bad_lines=bad)
    rtt = write_android_csv(tmp_path / "rtt.csv", flight)
    j, _ = _run(gnss, rtt, tmp_path)
    assert j["gnss"]["skipped"] == {"bad_checksum": 1, "bad_time": 1, "no_fix": 1}
    assert j["gnss"]["other_records"]["(not a sentence)"] == 1
    assert j["gnss"]["records_read"] == len(flight.gnss)


def test_ulog_fixes_before_utc_and_a_corrupt_stretch(flight, tmp_path):
    gnss = write_ulog(tmp_path / "f.ulg", flight, no_utc_first=25, garbage_after=2000)
    rtt = write_android_csv(tmp_path / "rtt.csv", flight)
    j, _ = _run(gnss, rtt, tmp_path)
    sk = j["gnss"]["skipped"]
    assert sk["no_utc"] == 25
    # pyulog resumes at the next sync message (the writer puts one every 500 fixes):
    # what it lost is counted, estimated from the gaps in the topic's timestamps (the
    # simulated receiver's own dropouts make it a little more)
    lost = len(flight.gnss) - 25 - j["gnss"]["records_read"]
    assert 400 <= lost <= 500
    assert lost <= sk["corrupt_data"] <= 1.1 * lost


def test_ulog_topic_choice(flight, tmp_path):
    gnss = write_ulog(tmp_path / "f.ulg", flight)
    rtt = write_android_csv(tmp_path / "rtt.csv", flight)
    j, log = _run(gnss, rtt, tmp_path, topic="vehicle_gps_position[1]")
    assert j["gnss"]["stream"] == "vehicle_gps_position[1]"
    assert {g.acc_m for g in log.gnss} == {4.0}  # the second receiver's
    with pytest.raises(ImportRefused, match=r"no vehicle_gps_position\[3\]"):
        _run(gnss, rtt, tmp_path, topic="vehicle_gps_position[3]")
    with pytest.raises(ImportRefused, match="NAME or NAME"):
        _run(gnss, rtt, tmp_path, topic="a b")


def test_dataflash_fixes_without_time_garbage_and_a_cut_end(flight, tmp_path):
    gnss = write_dataflash(tmp_path / "f.bin", flight, no_time_first=12, corrupt_after=700)
    data = gnss.read_bytes()
    cut = tmp_path / "cut.bin"
    cut.write_bytes(data[:-20])  # the last GPA cut in the middle
    rtt = write_android_csv(tmp_path / "rtt.csv", flight)
    j, _ = _run(cut, rtt, tmp_path)
    sk = j["gnss"]["skipped"]
    assert sk["no_fix"] == 12  # Status 1 before the receiver had time and a fix
    # the junk (3 x 15 bytes; pymavlink's index stops there, the reader reads on) and
    # the 19 bytes left of the cut GPA message (39 bytes long)
    assert sk["corrupt_bytes"] == 3 * 15 + 39 - 20
    assert j["gnss"]["records_read"] == len(flight.gnss) - 12  # nothing good lost
    # the last fix lost its GPA: its accuracy comes from HDop, with a warning
    assert any("HDop" in w for w in j["warnings"])


def test_dataflash_bulk_columns_equal_dfreader_messages(flight, tmp_path):
    """The reader's bulk unpacking gives the values pymavlink's own messages give."""
    from pymavlink import DFReader

    path = write_dataflash(tmp_path / "f.bin", dataclasses.replace(flight,
                                                                   gnss=flight.gnss[:300]))
    reader = DataFlashReader(path, GnssOptions())
    df = DFReader.DFReader_binary(str(path), zero_time_base=True)
    msgs = []
    while (m := df.recv_match(type=["GPS"], strict=True)) is not None:
        if m.I == 0:
            msgs.append(m)
    df.close()
    assert len(msgs) == reader.n == 300
    for col in ("TimeUS", "Status", "GMS", "GWk", "NSats", "HDop", "Lat", "Lng", "Alt"):
        assert np.array_equal(reader.gps[col], [getattr(m, col) for m in msgs]), col
    got = list(reader.records(Tally()))
    assert [s.record.acc_m for s in got] == [round(g.acc_m * 100) / 100
                                             for g in flight.gnss[:300]]


def test_rosbag_fixes_without_stamp_or_covariance(flight, tmp_path):
    bag = write_rosbag(tmp_path / "bag", flight, covariance=False, extra_topic=False)
    rtt = write_android_csv(tmp_path / "rtt.csv", flight)
    with pytest.raises(ImportRefused, match=f"no usable fix.*no_accuracy={len(flight.gnss)}"):
        _run(bag, rtt, tmp_path)
    _, log = _run(bag, rtt, tmp_path, gnss_acc_m=2.5)
    assert {g.acc_m for g in log.gnss} == {2.5} and {g.vacc_m for g in log.gnss} == {None}


def test_files_that_are_not_recorder_files(flight, tmp_path, sim_log):
    rtt = write_android_csv(tmp_path / "rtt.csv", flight)
    gnss = write_gnsslogger(tmp_path / "gnss_log.txt", flight)
    ulg = write_ulog(tmp_path / "f.ulg", flight)
    (tmp_path / "empty.txt").write_bytes(b"")
    (tmp_path / "noise.bin").write_bytes(np.random.default_rng(3).bytes(5000))
    (tmp_path / "folder").mkdir()
    cases = [
        (tmp_path / "empty.txt", rtt, "not a recognised recorder file"),
        (tmp_path / "noise.bin", rtt, "not a recognised recorder file"),
        (tmp_path / "folder", rtt, "not a ROS 2 bag"),
        (sim_log, rtt, "not a recognised recorder file"),  # a flight log is not a recorder's
        (tmp_path / "missing.txt", rtt, "no such file"),
        (rtt, rtt, "android-csv file (ranging data), not GNSS data"),
        (gnss, ulg, "ulog file (GNSS data), not ranging data"),
    ]
    for g, r, msg in cases:
        with pytest.raises(ImportRefused, match=re.escape(msg)) as err:
            _run(g, r, tmp_path)
        assert "\n" not in str(err.value)
    with pytest.raises(ImportRefused, match="'nmea' is not a ranges format"):
        _run(gnss, rtt, tmp_path, ranges_format="nmea")
    # named formats win over recognition, and a wrong name fails in one line
    with pytest.raises(ImportRefused, match="not a readable ULog file"):
        _run(gnss, rtt, tmp_path, gnss_format="ulog")
    assert not (tmp_path / "out.jsonl").exists()


def test_a_gnss_file_with_only_other_providers_says_what_it_holds(flight, tmp_path):
    gnss = write_gnsslogger(tmp_path / "gnss_log.txt", flight)
    text = gnss.read_text().replace("Fix,GPS,", "Fix,NLP,")
    gnss.write_text(text)
    rtt = write_android_csv(tmp_path / "rtt.csv", flight)
    with pytest.raises(ImportRefused, match=r"no usable fix .*Fix NLP=") as err:
        _run(gnss, rtt, tmp_path)
    assert "\n" not in str(err.value)
    j, log = _run(gnss, rtt, tmp_path, topic="NLP")  # the provider asked for
    assert j["gnss"]["stream"] == "Fix lines of provider NLP" and log.gnss


def test_detection_by_content(flight, tmp_path):
    f: Flight = flight
    files = {
        "gnsslogger": write_gnsslogger(tmp_path / "a.txt", f),
        "ulog": write_ulog(tmp_path / "b.dat", f),
        "dataflash": write_dataflash(tmp_path / "c.log", f),
        "nmea": write_nmea(tmp_path / "d.txt", f),
        "android-csv": write_android_csv(tmp_path / "e.txt", f),
        "sensorreadout": write_sensorreadout(tmp_path / "g.csv", f, f.utc0_ns),
        "rosbag2": write_rosbag(tmp_path / "bag", f),
    }
    for fmt, path in files.items():
        assert detect_format(path) == fmt, path
    # the report is JSON-able as it is
    j, _ = _run(files["dataflash"], files["sensorreadout"], tmp_path)
    assert json.loads(json.dumps(j)) == j


def test_sensorreadout_start_from_the_option_when_the_file_lacks_it(flight, tmp_path):
    from tests.estimator.importers.writers import NS

    start = (flight.utc0_ns // NS - 2) * NS
    rtt = write_sensorreadout(tmp_path / "readout.csv", flight, start)
    gnss = write_gnsslogger(tmp_path / "gnss_log.txt", flight)
    lines = rtt.read_text().splitlines()
    rtt.write_text("\n".join(lines[1:]) + "\n")  # no metadata line
    with pytest.raises(ImportRefused, match=r"no recording start.*--ranges-start-utc"):
        _run(gnss, rtt, tmp_path)
    j, _ = _run(gnss, rtt, tmp_path, ranges_start_utc_ns=start)
    # ms stamps on both sides instead of the metadata's whole seconds
    assert j["time"]["alignment_uncertainty_s"] < 0.003
    assert j["ranges"]["written"] == len(flight.rtt)
    rtt.write_text(lines[0].replace("GMT+02:00", "CST") + "\n" + "\n".join(lines[1:]) + "\n")
    with pytest.raises(ImportRefused, match="unknown time zone 'CST'"):
        _run(gnss, rtt, tmp_path)


def test_a_bag_with_two_fix_topics_needs_one_named(flight, tmp_path):
    bag = write_rosbag(tmp_path / "bag", flight, storage="mcap", second_fix_topic="/rtk/fix")
    rtt = write_android_csv(tmp_path / "rtt.csv", flight)
    with pytest.raises(ImportRefused, match=r"several NavSatFix topics \(/fix, /rtk/fix\)"):
        _run(bag, rtt, tmp_path)
    j, log = _run(bag, rtt, tmp_path, topic="/rtk/fix")
    assert j["gnss"]["stream"] == "NavSatFix on /rtk/fix"
    assert {g.acc_m for g in log.gnss} == {4.0} and {g.vacc_m for g in log.gnss} == {6.0}
    with pytest.raises(ImportRefused, match="no NavSatFix topic '/gps'"):
        _run(bag, rtt, tmp_path, topic="/gps")


def test_a_time_with_an_exponent_but_no_digits_before_it_is_a_bad_type():
    """A damaged time cell such as "E749723142525" (its first digit lost) looked like
    an exponent form and crashed the import with a ValueError traceback."""
    from estimator.importers.common import Skip, ms_to_ns, time_integer

    for text in ("E749723142525", "e12", ".E5", "+E3"):
        for parse in (ms_to_ns, time_integer):
            with pytest.raises(Skip) as skip:
                parse(text)
            assert skip.value.reason == "bad_type", (text, parse)
    assert ms_to_ns("1.749723142525E12") == 1_749_723_142_525_000_000  # every digit kept
    assert time_integer("3.9853029979635E13") == 39_853_029_979_635
    assert ms_to_ns(".5E1") == 5_000_000 and time_integer("5.E0") == 5


def test_a_bag_damaged_midway_keeps_the_fixes_before_the_damage(flight, tmp_path):
    """A damaged record in the middle of an MCAP bag made rosbags raise while the
    messages were read: a traceback. The fixes before it are kept; the topic's messages
    from there on are counted as corrupt_data, with a warning."""
    import struct

    short = dataclasses.replace(flight, gnss=flight.gnss[:2000])
    bag = write_rosbag(tmp_path / "bag", short, storage="mcap", extra_topic=False,
                       image_bytes=20_000)
    data = bytearray(storage_file(bag).read_bytes())
    msgs = mcap_messages(bytes(data))
    fixes = [m for m in msgs if m[2] < 1000]  # the NavSatFix records, not the images
    assert len(fixes) == 2000 and msgs[-1][0] >= 3  # several chunks
    chunk, off, _, _ = next(m for m in fixes if m[0] == 2)  # the first fix of chunk 3
    data[off + 1:off + 9] = struct.pack("<Q", 1 << 40)  # its length
    broken = tmp_path / "broken.mcap"
    broken.write_bytes(bytes(data))
    rtt = write_android_csv(tmp_path / "rtt.csv", flight, elapsed=False)
    j, log = _run(broken, rtt, tmp_path)
    kept = sum(m[0] < chunk for m in fixes)
    assert j["gnss"]["records_read"] == kept > 400
    assert j["gnss"]["skipped"] == {"corrupt_data": 2000 - kept}
    assert any(f"broken.mcap: damaged after message {kept} of /fix" in w
               for w in j["warnings"])
    _, ref = _run(storage_file(bag), rtt, tmp_path)
    assert log.gnss == ref.gnss[:len(log.gnss)] and len(log.gnss) > 300


def test_library_errors_are_one_line(flight, tmp_path):
    """A bag whose SQLite schema is damaged: rosbags' error quotes the schema over
    several lines; the refusal stays one line."""
    bag = write_rosbag(tmp_path / "bag", dataclasses.replace(flight, gnss=flight.gnss[:50]),
                       extra_topic=False)
    data = storage_file(bag).read_bytes()
    assert data.count(b"metadata_version INTEGER") == 1
    bad = tmp_path / "bad.db3"
    bad.write_bytes(data.replace(b"metadata_version INTEGER", b"`etadata_version INTEGER"))
    rtt = write_android_csv(tmp_path / "rtt.csv", flight)
    with pytest.raises(ImportRefused, match=r"bad.db3: not a readable ROS 2 bag \(.*"
                                            r"malformed database schema") as err:
        _run(bad, rtt, tmp_path)
    assert "\n" not in str(err.value) and len(str(err.value)) < 300


def test_nmea_sentences_of_a_receiver_without_a_fix_yet_are_no_fix(flight, tmp_path):
    """A u-blox receiver starting up writes GGA and RMC with empty time, position and
    date (``$GPGGA,,,,,,0,00,99.99,,,,,,*48``, ``$GPRMC,,V,,,,,,,,,,N*53``), then with
    the time but no fix: they were counted as bad_time and bad_date (a "wrong" time or
    date), not as what they are: sentences without a fix."""
    from tests.estimator.importers.writers import _nmea

    start = ["$GPGGA,,,,,,0,00,99.99,,,,,,*48", "$GPRMC,,V,,,,,,,,,,N*53",
             _nmea("GPGGA,101159.00,,,,,0,03,25.3,,,,,,"),
             _nmea("GPRMC,101159.00,V,,,,,,,120625,,,N")]
    good = write_nmea(tmp_path / "good.nmea", flight).read_text().splitlines()
    gnss = tmp_path / "ublox.nmea"
    gnss.write_text("\r\n".join(start * 4 + good) + "\r\n")
    rtt = write_android_csv(tmp_path / "rtt.csv", flight)
    j, _ = _run(gnss, rtt, tmp_path)
    assert j["gnss"]["skipped"] == {"no_fix": 12}  # the void RMC with a date dates
    assert j["gnss"]["records_read"] == len(flight.gnss)
    # a damaged time or date with a fix is still what it is
    bad = [_nmea("GPGGA,,3642.9000,N,00428.6800,W,1,12,0.60,100.0,M,50.0,M,,"),
           _nmea("GPRMC,101200.00,A,3642.9000,N,00428.6800,W,1.0,90.0,,,,A")]
    gnss.write_text("\r\n".join(bad + good) + "\r\n")
    j, _ = _run(gnss, rtt, tmp_path)
    assert j["gnss"]["skipped"] == {"bad_time": 1, "bad_date": 1}


def test_a_ulog_cut_off_in_its_last_fix_counts_it(flight, tmp_path):
    """A PX4 log ends where the power went: in the middle of a message. pyulog stops
    there and says nothing; a GNSS message cut off is counted (truncated), as in a
    DataFlash log, and one of another topic is not the GNSS stream's."""
    ulg = write_ulog(tmp_path / "f.ulg", flight)
    data = ulg.read_bytes()
    rtt = write_android_csv(tmp_path / "rtt.csv", flight)
    size = 3 + 2 + logged_dtype(VEHICLE_GPS_POSITION_V113).itemsize  # header, id, fields
    cases = [(data, len(flight.gnss), {}),
             (data[:-7], len(flight.gnss) - 1, {"truncated": 1}),  # in the last fix
             (data[:-size + 5], len(flight.gnss) - 1, {"truncated": 1}),  # its id there
             (data[:-size + 4], len(flight.gnss) - 1, {}),  # half its id: whose?
             (data[:-size + 2], len(flight.gnss) - 1, {}),  # in its header
             (data[:-size], len(flight.gnss) - 1, {})]  # a message boundary
    # the last battery_status message: 23 bytes (its id 2, 21 of fields)
    battery = data.rfind(b"\x17\x00D\x02\x00")
    assert battery > len(data) - 3000
    cases.append((data[:battery + 10], None, {}))  # cut in another topic's message
    for k, (content, n, skipped) in enumerate(cases):
        cut = tmp_path / f"cut{k}.ulg"
        cut.write_bytes(content)
        j, _ = _run(cut, rtt, tmp_path)
        assert j["gnss"]["skipped"] == skipped, k
        if n is not None:
            assert j["gnss"]["records_read"] == n, k


def test_a_navsatfix_variance_of_nan_is_an_unknown_accuracy(flight, tmp_path):
    """nmea_navsat_driver squares an empty HDOP into NaN variances (covariance type
    1): the fix was skipped as non_finite, even with --gnss-acc. A NaN variance is an
    unknown accuracy, as an empty one elsewhere: no_accuracy, kept with --gnss-acc; a
    NaN vertical variance leaves vacc_m out."""
    bag = write_rosbag(tmp_path / "bag", flight, extra_topic=False, nan_every=10)
    rtt = write_android_csv(tmp_path / "rtt.csv", flight)
    j, log = _run(bag, rtt, tmp_path)
    n_nan = (len(flight.gnss) + 9) // 10
    assert j["gnss"]["skipped"] == {"no_accuracy": n_nan}
    src_t = np.array([g.t_ns for g in flight.gnss])
    for g in log.gnss:  # each written fix's source: the nearest in time (1 ms of UTC)
        k = int(np.argmin(np.abs(src_t - g.t_ns)))
        assert abs(src_t[k] - g.t_ns) < 2_000_000 and k % 10 != 0
        assert g.acc_m == pytest.approx(flight.gnss[k].acc_m)
        assert (g.vacc_m is None) == (k % 10 == 1)
    j, log = _run(bag, rtt, tmp_path, gnss_acc_m=2.5)
    assert j["gnss"]["skipped"] == {} and j["gnss"]["records_read"] == len(flight.gnss)
    assert sum(g.acc_m == 2.5 for g in log.gnss) >= 0.9 * len(log.gnss) // 10
