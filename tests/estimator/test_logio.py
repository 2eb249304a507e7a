"""Flight-log reader/writer against docs/log-format.md (version 1)."""

from __future__ import annotations

import gzip
import json
import math
import random
import tempfile
import tracemalloc
import warnings
from collections import Counter
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from estimator.logio import (
    ACC_MAX_M,
    ALT_MAX_M,
    ALT_MIN_M,
    COUNT_MAX,
    RANGE_MAX_M,
    RSSI_MAX_DBM,
    RSSI_MIN_DBM,
    T_NS_MAX,
    LogError,
    LogStream,
    LogVersionError,
    LogWarning,
    LogWriter,
    RejectCounts,
    dumps_record,
    iter_log,
    iter_log_sorted,
    parse_line,
    read_log,
)
from estimator.records import GNSS_FIX_TYPES, GnssFix, LogHeader, RangeSample, TruthRecord

HEADER = (
    '{"type":"header","format":"osa-log","version":1,"agent":"uav-1",'
    '"start_utc":"2026-05-08T10:12:00Z","config":{"agl_m":45.0,"range_offset_m":0.25}}'
)
GOOD_GNSS = (
    '{"type":"gnss","t_ns":1000,"lat":36.715123,"lon":-4.478321,"alt_m":152.31,'
    '"acc_m":0.92,"vacc_m":1.6,"fix":"3d","sats":21}'
)
GOOD_RTT = (
    '{"type":"rtt","t_ns":3000,"bssid":"a4:77:33:0f:1e:02","status":"ok","range_m":74.312,'
    '"range_std_m":0.41,"rssi_dbm":-71,"attempted":8,"successful":7}'
)
GNSS_REC = GnssFix(
    t_ns=1000,
    lat_deg=36.715123,
    lon_deg=-4.478321,
    alt_m=152.31,
    acc_m=0.92,
    vacc_m=1.6,
    fix="3d",
    sats=21,
)
RTT_REC = RangeSample(
    t_ns=3000,
    bssid="a4:77:33:0f:1e:02",
    status="ok",
    range_m=74.312,
    range_std_m=0.41,
    rssi_dbm=-71.0,
    attempted=8,
    successful=7,
)
TRUTH_LINE = (
    '{"type":"truth","bssid":"a4:77:33:0f:1e:02","lat":36.7149,"lon":-4.4781,'
    '"alt_m":108.2,"concealment":"open"}'
)
TRUTH_REC = TruthRecord(
    bssid="a4:77:33:0f:1e:02", lat_deg=36.7149, lon_deg=-4.4781, alt_m=108.2, concealment="open"
)


def _write(path: Path, lines: list[str | bytes]) -> Path:
    data = b"".join((ln if isinstance(ln, bytes) else ln.encode("utf-8")) + b"\n" for ln in lines)
    path.write_bytes(data)
    return path


def _gnss(t: int, **kw: object) -> str:
    obj = {"type": "gnss", "t_ns": t, "lat": 36.715, "lon": -4.478, "alt_m": 100.0, "acc_m": 1.0}
    obj.update(kw)
    return json.dumps(obj)


def _rtt(t: int, **kw: object) -> str:
    obj = {
        "type": "rtt",
        "t_ns": t,
        "bssid": "a4:77:33:0f:1e:02",
        "status": "ok",
        "range_m": 50.0,
        "rssi_dbm": -70,
    }
    obj.update(kw)
    return json.dumps(obj)


def _without(line: str, key: str) -> str:
    obj = json.loads(line)
    del obj[key]
    return json.dumps(obj)


def _replace(line: str, key: str, raw: str) -> str:
    """``line`` with ``key``'s value replaced by the raw JSON text ``raw`` (even invalid JSON)."""
    obj = json.loads(line)
    obj[key] = "@@PLACEHOLDER@@"
    return json.dumps(obj).replace('"@@PLACEHOLDER@@"', raw)


# ------------------------------------------------------------------------ bad input

BAD_LINES: list[tuple[str, str | bytes, str]] = [
    # (id, bad line, reason)
    ("truncated-json", '{"type":"gnss","t_ns":2000,"lat":36.7', "not_json"),
    ("plain-text", "hello world", "not_json"),
    ("trailing-garbage", GOOD_GNSS + " x", "not_json"),
    ("two-objects", GOOD_GNSS + GOOD_GNSS, "not_json"),
    ("deep-nesting", "[" * 100_000 + "]" * 100_000, "not_json"),
    ("json-array", '[1, 2, {"type": "gnss"}]', "not_object"),
    ("json-number", "42", "not_object"),
    ("json-string", '"gnss"', "not_object"),
    ("json-null", "null", "not_object"),
    ("no-type", _without(GOOD_GNSS, "type"), "missing_field"),
    ("gnss-no-t_ns", _without(GOOD_GNSS, "t_ns"), "missing_field"),
    ("gnss-no-lat", _without(GOOD_GNSS, "lat"), "missing_field"),
    ("gnss-no-lon", _without(GOOD_GNSS, "lon"), "missing_field"),
    ("gnss-no-alt", _without(GOOD_GNSS, "alt_m"), "missing_field"),
    ("gnss-no-acc", _without(GOOD_GNSS, "acc_m"), "missing_field"),
    ("gnss-null-lat", _replace(GOOD_GNSS, "lat", "null"), "missing_field"),
    ("rtt-no-t_ns", _without(GOOD_RTT, "t_ns"), "missing_field"),
    ("rtt-no-bssid", _without(GOOD_RTT, "bssid"), "missing_field"),
    ("rtt-no-status", _without(GOOD_RTT, "status"), "missing_field"),
    ("rtt-ok-no-range", _without(GOOD_RTT, "range_m"), "missing_field"),
    ("truth-no-bssid", _without(TRUTH_LINE, "bssid"), "missing_field"),
    ("truth-no-lat", _without(TRUTH_LINE, "lat"), "missing_field"),
    ("truth-no-alt", _without(TRUTH_LINE, "alt_m"), "missing_field"),
    ("nan-lat", _replace(GOOD_GNSS, "lat", "NaN"), "non_finite"),
    ("inf-alt", _replace(GOOD_GNSS, "alt_m", "Infinity"), "non_finite"),
    ("-inf-range", _replace(GOOD_RTT, "range_m", "-Infinity"), "non_finite"),
    ("nan-t_ns", _replace(GOOD_RTT, "t_ns", "NaN"), "non_finite"),
    ("nan-optional", _replace(GOOD_RTT, "range_std_m", "NaN"), "non_finite"),
    ("nan-truth", _replace(TRUTH_LINE, "alt_m", "NaN"), "non_finite"),
    ("overflow-float", _replace(GOOD_GNSS, "acc_m", "1e999"), "non_finite"),
    ("huge-int-t_ns", _replace(GOOD_GNSS, "t_ns", "1" + "0" * 400), "non_finite"),
    ("huge-int-lat", _replace(GOOD_GNSS, "lat", "1" + "0" * 400), "non_finite"),
    ("lat-above-90", _replace(GOOD_GNSS, "lat", "90.000001"), "bad_latitude"),
    ("lat-below-90", _replace(GOOD_GNSS, "lat", "-91"), "bad_latitude"),
    ("truth-lat", _replace(TRUTH_LINE, "lat", "123.4"), "bad_latitude"),
    ("lon-above-180", _replace(GOOD_GNSS, "lon", "180.5"), "bad_longitude"),
    ("lon-below-180", _replace(GOOD_GNSS, "lon", "-180.000001"), "bad_longitude"),
    ("truth-lon", _replace(TRUTH_LINE, "lon", "-200"), "bad_longitude"),
    ("negative-t_ns-gnss", _replace(GOOD_GNSS, "t_ns", "-1"), "negative_t_ns"),
    ("negative-t_ns-rtt", _replace(GOOD_RTT, "t_ns", "-81234601234567"), "negative_t_ns"),
    ("bssid-five-pairs", _replace(GOOD_RTT, "bssid", '"a4:77:33:0f:1e"'), "bad_bssid"),
    ("bssid-seven-pairs", _replace(GOOD_RTT, "bssid", '"a4:77:33:0f:1e:02:03"'), "bad_bssid"),
    ("bssid-dashes", _replace(GOOD_RTT, "bssid", '"a4-77-33-0f-1e-02"'), "bad_bssid"),
    ("bssid-not-hex", _replace(GOOD_RTT, "bssid", '"g4:77:33:0f:1e:02"'), "bad_bssid"),
    ("bssid-no-colons", _replace(GOOD_RTT, "bssid", '"a477330f1e02"'), "bad_bssid"),
    ("bssid-empty", _replace(GOOD_RTT, "bssid", '""'), "bad_bssid"),
    ("bssid-newline", _replace(GOOD_RTT, "bssid", '"a4:77:33:0f:1e:02\\n"'), "bad_bssid"),
    ("bssid-space", _replace(GOOD_RTT, "bssid", '" a4:77:33:0f:1e:02"'), "bad_bssid"),
    ("truth-bssid", _replace(TRUTH_LINE, "bssid", '"a4:77:33"'), "bad_bssid"),
    ("lat-string", _replace(GOOD_GNSS, "lat", '"36.715"'), "bad_type"),
    ("t_ns-fraction", _replace(GOOD_GNSS, "t_ns", "1000.5"), "bad_type"),
    ("t_ns-bool", _replace(GOOD_GNSS, "t_ns", "true"), "bad_type"),
    ("t_ns-string", _replace(GOOD_RTT, "t_ns", '"3000"'), "bad_type"),
    ("bssid-number", _replace(GOOD_RTT, "bssid", "12"), "bad_type"),
    ("status-number", _replace(GOOD_RTT, "status", "0"), "bad_type"),
    ("range-list", _replace(GOOD_RTT, "range_m", "[74.3]"), "bad_type"),
    ("sats-fraction", _replace(GOOD_GNSS, "sats", "2.5"), "bad_type"),
    ("fix-number", _replace(GOOD_GNSS, "fix", "3"), "bad_type"),
    ("type-number", _replace(GOOD_GNSS, "type", "7"), "bad_type"),
    ("acc-negative", _replace(GOOD_GNSS, "acc_m", "-0.5"), "bad_value"),
    # physical limits (logio.BOUNDS, docs/log-format.md "Limits")
    ("t_ns-beyond-2^62", _replace(GOOD_GNSS, "t_ns", str(2**62 + 1)), "bad_t_ns"),
    ("alt-1e30", _replace(GOOD_GNSS, "alt_m", "1e30"), "bad_altitude"),
    ("alt-below-500", _replace(GOOD_GNSS, "alt_m", "-500.5"), "bad_altitude"),
    ("truth-alt-1e300", _replace(TRUTH_LINE, "alt_m", "1e300"), "bad_altitude"),
    ("range-1e30", _replace(GOOD_RTT, "range_m", "1e30"), "bad_range"),
    ("range-1e308", _replace(GOOD_RTT, "range_m", "1e308"), "bad_range"),
    ("range-minus-20km", _replace(GOOD_RTT, "range_m", "-20000"), "bad_range"),
    ("acc-1e300", _replace(GOOD_GNSS, "acc_m", "1e300"), "bad_value"),
    ("vacc-1e300", _replace(GOOD_GNSS, "vacc_m", "1e300"), "bad_value"),
    ("std-1e300", _replace(GOOD_RTT, "range_std_m", "1e300"), "bad_value"),
    ("rssi-1e30", _replace(GOOD_RTT, "rssi_dbm", "1e30"), "bad_value"),
    ("sats-negative", _replace(GOOD_GNSS, "sats", "-1"), "bad_value"),
    ("attempted-huge", _replace(GOOD_RTT, "attempted", "100000"), "bad_value"),
    ("not-utf8", b'{"type":"gnss","t_ns":2000,"lat":36.7,"lon":-4.4,"acc_m":\xff}', "not_utf8"),
    ("latin1", '{"type":"truth","bssid":"a4:77:33:0f:1e:02","lat":1,"lon":2,"alt_m":3,'
     '"concealment":"caf\u00e9"}'.encode("latin-1"), "not_utf8"),
    ("duplicate-header", HEADER, "duplicate_header"),
]  # fmt: skip


@pytest.mark.parametrize(
    ("bad", "reason"), [(b, r) for _, b, r in BAD_LINES], ids=[i for i, _, _ in BAD_LINES]
)
def test_bad_line_is_skipped_and_counted(tmp_path: Path, bad: str | bytes, reason: str) -> None:
    path = _write(tmp_path / "log.jsonl", [HEADER, GOOD_GNSS, bad, GOOD_RTT, TRUTH_LINE])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a bad data line is counted, not warned about
        log = read_log(path)
    assert log.gnss == [GNSS_REC]
    assert log.rtt == [RTT_REC]
    assert log.truth == [TRUTH_REC]
    assert log.header == LogHeader(
        agent="uav-1", start_utc="2026-05-08T10:12:00Z", agl_m=45.0, range_offset_m=0.25
    )
    assert log.counts.rejected == Counter({reason: 1})
    assert log.counts.n_rejected == 1
    assert log.counts.unknown_types == Counter()
    assert log.counts.unknown_fields == 0


def test_bad_line_before_the_only_good_line(tmp_path: Path) -> None:
    """A good line right after a bad one (no separator) is still read."""
    path = _write(tmp_path / "log.jsonl", [HEADER, '{"type":"gnss",', GOOD_GNSS])
    log = read_log(path)
    assert log.gnss == [GNSS_REC]
    assert log.counts.rejected == Counter({"not_json": 1})


def test_all_bad_lines_in_one_file(tmp_path: Path) -> None:
    """Every bad kind interleaved with good lines: each good line read, each bad counted."""
    lines: list[str | bytes] = [HEADER]
    expected_gnss = []
    for i, (_, bad, _) in enumerate(BAD_LINES):
        lines.append(bad)
        lines.append(_gnss(10_000 + i, lat=10.0 + i * 0.01))
        expected_gnss.append(
            GnssFix(
                t_ns=10_000 + i, lat_deg=10.0 + i * 0.01, lon_deg=-4.478, alt_m=100.0, acc_m=1.0
            )
        )
    log = read_log(_write(tmp_path / "log.jsonl", lines))
    assert log.gnss == expected_gnss
    assert log.rtt == []
    assert log.counts.rejected == Counter(r for _, _, r in BAD_LINES)
    assert log.counts.n_rejected == len(BAD_LINES)


def test_blank_lines_and_crlf_are_harmless(tmp_path: Path) -> None:
    data = (HEADER + "\r\n\r\n   \n" + GOOD_GNSS + "\r\n\n" + GOOD_RTT).encode()  # no final \n
    path = tmp_path / "log.jsonl"
    path.write_bytes(data)
    log = read_log(path)
    assert log.gnss == [GNSS_REC]
    assert log.rtt == [RTT_REC]
    assert log.counts.n_rejected == 0


@pytest.mark.parametrize("gz", [False, True])
def test_a_byte_order_mark_keeps_the_header(tmp_path: Path, gz: bool) -> None:
    """A log saved by a Windows editor starts with a UTF-8 byte-order mark: the header
    behind it is read (its range offset used), nothing is rejected, no warning. A BOM
    at the start of a later line (files joined with cat) is skipped too."""
    data = ("\ufeff" + HEADER + "\r\n" + GOOD_GNSS + "\r\n" + "\ufeff" + GOOD_RTT + "\r\n")
    path = tmp_path / ("log.jsonl.gz" if gz else "log.jsonl")
    raw = data.encode("utf-8")
    path.write_bytes(gzip.compress(raw, mtime=0) if gz else raw)
    with warnings.catch_warnings():
        warnings.simplefilter("error", LogWarning)
        log = read_log(path)
    assert log.header.agent == "uav-1" and log.header.range_offset_m == 0.25
    assert (log.gnss, log.rtt) == ([GNSS_REC], [RTT_REC])
    assert log.counts.n_rejected == 0 and log.counts.lines == 3


def test_unknown_types_and_fields_are_counted(tmp_path: Path) -> None:
    lines = [
        HEADER[:-1] + ',"firmware":"1.2"}',
        '{"type":"imu","t_ns":1500,"ax":0.1}',
        '{"type":"imu","t_ns":1600,"ax":0.2}',
        '{"type":"baro","t_ns":1700,"p":1013.2}',
        GOOD_GNSS[:-1] + ',"speed_mps":3.2,"bearing_deg":90}',
        GOOD_RTT[:-1] + ',"channel":149}',
        TRUTH_LINE,
    ]
    log = read_log(_write(tmp_path / "log.jsonl", lines))
    assert log.gnss == [GNSS_REC]
    assert log.rtt == [RTT_REC]
    assert log.truth == [TRUTH_REC]
    assert log.header.agent == "uav-1"
    assert log.counts.unknown_types == Counter({"imu": 2, "baro": 1})
    assert log.counts.unknown_fields == 3  # header, gnss, rtt (one per line, not per field)
    assert log.counts.n_rejected == 0


def test_upper_case_bssid_is_normalised(tmp_path: Path) -> None:
    lines = [
        HEADER,
        _rtt(10, bssid="A4:77:33:0F:1E:02"),
        _rtt(20, bssid="a4:77:33:0F:1e:02"),
        TRUTH_LINE.replace("a4:77:33:0f:1e:02", "A4:77:33:0F:1E:02"),
    ]
    log = read_log(_write(tmp_path / "log.jsonl", lines))
    assert [r.bssid for r in log.rtt] == ["a4:77:33:0f:1e:02"] * 2
    assert log.truth == [TRUTH_REC]


@pytest.mark.parametrize("status", ["fail", "no_response", "busy"])
def test_rtt_failure_without_range_is_valid(tmp_path: Path, status: str) -> None:
    line = json.dumps({"type": "rtt", "t_ns": 5, "bssid": "a4:77:33:0f:1e:02", "status": status})
    log = read_log(_write(tmp_path / "log.jsonl", [HEADER, line]))
    assert log.rtt == [RangeSample(t_ns=5, bssid="a4:77:33:0f:1e:02", status=status)]
    assert not log.rtt[0].ok
    assert log.counts.n_rejected == 0


def test_no_header_reads_with_warning(tmp_path: Path) -> None:
    path = _write(tmp_path / "log.jsonl", [GOOD_GNSS, GOOD_RTT])
    with pytest.warns(LogWarning, match="no header"):
        log = read_log(path)
    assert log.header == LogHeader()
    assert log.header.version == 1
    assert log.gnss == [GNSS_REC]
    assert log.rtt == [RTT_REC]


def test_header_not_first_warns_but_is_used(tmp_path: Path) -> None:
    path = _write(tmp_path / "log.jsonl", [GOOD_GNSS, HEADER, GOOD_RTT])
    with pytest.warns(LogWarning, match="not the first line"):
        log = read_log(path)
    assert log.header.agent == "uav-1"
    assert log.gnss == [GNSS_REC]
    assert log.rtt == [RTT_REC]


@pytest.mark.parametrize("version", ["2", "2.0", '"2.1"', "17"])
def test_newer_major_version_is_refused(tmp_path: Path, version: str) -> None:
    header = HEADER.replace('"version":1', f'"version":{version}')
    path = _write(tmp_path / "log.jsonl", [header, GOOD_GNSS])
    with pytest.raises(LogVersionError, match="newer than this reader"):
        read_log(path)
    assert issubclass(LogVersionError, LogError)


def test_newer_minor_version_is_read(tmp_path: Path) -> None:
    header = HEADER.replace('"version":1', '"version":"1.3"')
    log = read_log(_write(tmp_path / "log.jsonl", [header, GOOD_GNSS]))
    assert log.header.version == 1
    assert log.gnss == [GNSS_REC]


def test_missing_file_raises_log_error(tmp_path: Path) -> None:
    with pytest.raises(LogError, match="no such file"):
        read_log(tmp_path / "nope.jsonl")
    with pytest.raises(LogError):
        next(iter_log(tmp_path / "nope.jsonl"))
    with pytest.raises(LogError):
        next(iter_log_sorted(tmp_path / "nope.jsonl.gz"))
    with pytest.raises(LogError):
        read_log(tmp_path)  # a directory


@pytest.mark.parametrize("gz", [False, True])
def test_empty_file_reads_as_zero_records_with_warning(tmp_path: Path, gz: bool) -> None:
    path = tmp_path / ("empty.jsonl.gz" if gz else "empty.jsonl")
    path.write_bytes(gzip.compress(b"", mtime=0) if gz else b"")
    with pytest.warns(LogWarning, match="no header"):
        log = read_log(path)
    assert (log.gnss, log.rtt, log.truth) == ([], [], [])
    assert log.counts.n_rejected == 0
    assert log.counts.lines == 0


def _big_gz_log(tmp_path: Path, n: int = 3000) -> tuple[Path, bytes]:
    rng = random.Random(5)
    lines = [HEADER] + [_gnss(i, lat=36.0 + rng.random()) for i in range(n)]
    data = ("\n".join(lines) + "\n").encode()
    path = tmp_path / "log.jsonl.gz"
    path.write_bytes(gzip.compress(data, mtime=0))
    return path, path.read_bytes()


def test_a_truncated_gzip_keeps_the_records_before_the_cut(tmp_path: Path) -> None:
    """A recorder cut off while writing (a flat battery) leaves a truncated gzip: the
    records before the cut are read, with a warning saying so (it used to refuse the
    whole flight); cut inside the gzip header, nothing is readable: refused."""
    path, blob = _big_gz_log(tmp_path)
    whole = read_log(path)
    assert len(whole.gnss) == 3000
    for cut in (len(blob) // 2, len(blob) - 4):
        path.write_bytes(blob[:cut])
        with pytest.warns(LogWarning, match="compressed file ends early") as said:
            log = read_log(path)
        n = len(log.gnss)
        assert (1000 < n < 2000) if cut == len(blob) // 2 else n == 3000
        assert log.gnss == whole.gnss[:n]  # the records before the cut, exactly
        assert f"the {n + 1} records" in str(said[0].message)  # the header and the fixes
        assert log.counts.n_rejected <= 1  # at most the line cut in two
    path.write_bytes(blob[:12])
    with pytest.raises(LogError, match="corrupt or truncated"):
        read_log(path)


def test_a_corrupt_gzip_is_read_to_the_damage_or_refused(tmp_path: Path) -> None:
    """Damaged compressed data: a stream that breaks before any record is refused in
    one line; a checksum that fails at the end (every line was read) is a warning and
    the lines are checked one by one as always."""
    path, blob = _big_gz_log(tmp_path)
    whole = read_log(path)
    flipped = blob[:100] + bytes(b ^ 0x55 for b in blob[100:200]) + blob[200:]
    path.write_bytes(flipped)
    with pytest.raises(LogError, match="corrupt or truncated"):
        read_log(path)
    path.write_bytes(blob[:-8] + b"\0" * 8)  # CRC and size trailer zeroed
    with pytest.warns(LogWarning, match="fails its checksum"):
        log = read_log(path)
    assert log.gnss == whole.gnss


def _mixed_log_lines() -> list[str]:
    return [
        HEADER,
        _gnss(3000, lat=36.3),
        _rtt(2000, range_m=20.0),
        TRUTH_LINE,
        _gnss(1000, lat=36.1),
        _rtt(4000, range_m=40.0, bssid="A4:77:33:0F:1E:03"),
        '{"type":"imu","t_ns":1}',
        "not json",
    ]


def test_gzip_reads_equal_plain(tmp_path: Path) -> None:
    lines = _mixed_log_lines()
    plain = _write(tmp_path / "log.jsonl", lines)
    gz = tmp_path / "log.jsonl.gz"
    gz.write_bytes(gzip.compress(plain.read_bytes()))
    misnamed = tmp_path / "really_gzip.jsonl"  # detected by magic bytes, not by name
    misnamed.write_bytes(gz.read_bytes())
    a, b, c = read_log(plain), read_log(gz), read_log(misnamed)
    assert len(a.gnss) == 2 and len(a.rtt) == 2 and len(a.truth) == 1
    for other in (b, c):
        assert other.gnss == a.gnss
        assert other.rtt == a.rtt
        assert other.truth == a.truth
        assert other.header == a.header
        assert other.counts == a.counts
    assert a.counts.rejected == Counter({"not_json": 1})
    assert a.counts.unknown_types == Counter({"imu": 1})


def test_plain_file_named_gz_is_read(tmp_path: Path) -> None:
    path = _write(tmp_path / "plain.jsonl.gz", [HEADER, GOOD_GNSS])
    assert read_log(path).gnss == [GNSS_REC]


# ------------------------------------------------------------------------ ordering


def test_out_of_order_lines_are_sorted_by_t_ns(tmp_path: Path) -> None:
    log = read_log(_write(tmp_path / "log.jsonl", _mixed_log_lines()))
    assert [g.t_ns for g in log.gnss] == [1000, 3000]
    assert [g.lat_deg for g in log.gnss] == [36.1, 36.3]
    assert [r.t_ns for r in log.rtt] == [2000, 4000]
    merged = list(iter_log_sorted(tmp_path / "log.jsonl"))
    assert [r.t_ns for r in merged] == [1000, 2000, 3000, 4000]
    assert [type(r).__name__ for r in merged] == [
        "GnssFix",
        "RangeSample",
        "GnssFix",
        "RangeSample",
    ]
    in_file_order = [r.t_ns for r in iter_log(tmp_path / "log.jsonl")]
    assert in_file_order == [3000, 2000, 1000, 4000]


def test_equal_t_ns_keeps_file_order(tmp_path: Path) -> None:
    # records that differ only in their position in the file (range_m marks the position)
    lines = [HEADER, _rtt(500, range_m=0.0)]
    lines += [_rtt(100, range_m=float(i)) for i in range(1, 6)]
    lines += [
        _gnss(100, lat=1.0),
        _rtt(50, range_m=6.0),
        _rtt(100, range_m=7.0),
        _gnss(100, lat=2.0),
    ]
    out = list(iter_log_sorted(_write(tmp_path / "log.jsonl", lines)))
    assert [(r.t_ns, getattr(r, "range_m", None), getattr(r, "lat_deg", None)) for r in out] == [
        (50, 6.0, None),
        (100, 1.0, None),
        (100, 2.0, None),
        (100, 3.0, None),
        (100, 4.0, None),
        (100, 5.0, None),
        (100, None, 1.0),
        (100, 7.0, None),
        (100, None, 2.0),
        (500, 0.0, None),
    ]


def _shuffled_log(tmp_path: Path, n: int, seed: int) -> tuple[Path, list[GnssFix | RangeSample]]:
    """``n`` records, shuffled, with many equal t_ns; the i-th line carries i in a value."""
    rng = random.Random(seed)
    recs: list[GnssFix | RangeSample] = []
    for i in range(n):
        t = rng.randrange(n // 10)  # ~10 records per t_ns
        if rng.random() < 0.3:
            recs.append(GnssFix(t_ns=t, lat_deg=i * 1e-4, lon_deg=0.5, alt_m=float(i), acc_m=1.0))
        else:
            recs.append(RangeSample(t_ns=t, bssid="a4:77:33:0f:1e:02", status="ok",
                                    range_m=float(i), rssi_dbm=-60.0))  # fmt: skip
    path = tmp_path / "shuffled.jsonl"
    with LogWriter(path, LogHeader(agent="shuffle")) as w:
        w.write_all(recs)
    return path, recs


def test_external_sort_equals_in_memory_stable_sort(tmp_path: Path, monkeypatch) -> None:
    path, recs = _shuffled_log(tmp_path, 5000, seed=11)
    expected = sorted(recs, key=lambda r: r.t_ns)  # Python's sort is stable
    spill = tmp_path / "spill"
    spill.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(spill))
    st = LogStream(path=str(path))
    out = list(iter_log_sorted(path, st, chunk_records=100))
    assert out == expected
    assert st.n_gnss + st.n_rtt == 5000
    assert st.header is not None and st.header.agent == "shuffle"
    assert list(spill.iterdir()) == []  # the 50 spilled runs were removed
    # the in-memory path (one chunk) gives the same
    assert list(iter_log_sorted(path, chunk_records=10_000)) == expected
    # chunk boundaries at every size give the same, including a partial last chunk
    for chunk in (64, 4999, 5000):
        assert list(iter_log_sorted(path, chunk_records=chunk)) == expected


def test_external_sort_cleans_up_when_abandoned(tmp_path: Path, monkeypatch) -> None:
    path, _ = _shuffled_log(tmp_path, 1000, seed=3)
    spill = tmp_path / "spill"
    spill.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(spill))
    it = iter_log_sorted(path, chunk_records=100)
    first = next(it)
    assert first.t_ns == 0
    assert len(list(spill.iterdir())) == 1  # the run directory
    it.close()
    assert list(spill.iterdir()) == []


# ------------------------------------------------------------------------ writer


def _sample_records() -> tuple[LogHeader, list]:
    header = LogHeader(
        agent="uav-2",
        start_utc="2026-05-08T10:12:00Z",
        agl_m=45.0,
        range_offset_m=-0.3,
        extra={"note": "calibrated", "wind_mps": 3.5},
    )
    recs = [
        GnssFix(t_ns=81234567890123, lat_deg=36.715123, lon_deg=-4.478321, alt_m=152.31,
                acc_m=0.92, vacc_m=1.6, fix="3d", sats=21),
        GnssFix(t_ns=81234667890123, lat_deg=-0.1, lon_deg=179.999999, alt_m=-20.0, acc_m=0.0),
        RangeSample(t_ns=81234601234567, bssid="a4:77:33:0f:1e:02", status="ok", range_m=-0.25,
                    range_std_m=0.41, rssi_dbm=-71.0, attempted=8, successful=7),
        RangeSample(t_ns=81234601234567, bssid="a4:77:33:0f:1e:03", status="no_response"),
        TruthRecord(bssid="a4:77:33:0f:1e:02", lat_deg=36.7149, lon_deg=-4.4781, alt_m=108.2,
                    concealment="vegetation_debris"),
    ]  # fmt: skip
    return header, recs


@pytest.mark.parametrize("name", ["out.jsonl", "out.jsonl.gz"])
def test_writer_reader_round_trip(tmp_path: Path, name: str) -> None:
    header, recs = _sample_records()
    path = tmp_path / name
    with LogWriter(path, header) as w:
        w.write_all(recs)
        assert w.n_lines == 6
    log = read_log(path)
    assert log.header == header
    assert log.header.extra == {"note": "calibrated", "wind_mps": 3.5}
    assert log.gnss == [recs[0], recs[1]]
    assert log.rtt == [recs[2], recs[3]]
    assert log.truth == [recs[4]]
    assert log.counts == RejectCounts(lines=6)
    with gzip.open(path) if name.endswith(".gz") else open(path, "rb") as fh:
        lines = fh.read().split(b"\n")
    assert len(lines) == 7 and lines[-1] == b""  # 6 lines, each ending in \n
    assert json.loads(lines[0])["type"] == "header"


def test_writer_refuses_nan_and_stays_readable(tmp_path: Path) -> None:
    path = tmp_path / "out.jsonl"
    with LogWriter(path, LogHeader()) as w:
        w.write(GNSS_REC)
        with pytest.raises(ValueError):
            w.write(GnssFix(t_ns=2, lat_deg=math.nan, lon_deg=0.0, alt_m=0.0, acc_m=1.0))
        with pytest.raises(ValueError):
            w.write(RangeSample(t_ns=3, bssid="a4:77:33:0f:1e:02", status="ok",
                                range_m=math.inf, rssi_dbm=-60.0))  # fmt: skip
        w.write(RTT_REC)
    log = read_log(path)
    assert log.gnss == [GNSS_REC]
    assert log.rtt == [RTT_REC]
    assert log.counts.n_rejected == 0
    with pytest.raises(ValueError):
        dumps_record(TruthRecord(bssid="a4:77:33:0f:1e:02", lat_deg=0.0, lon_deg=0.0,
                                 alt_m=-math.inf))  # fmt: skip


def test_gz_output_is_deterministic(tmp_path: Path) -> None:
    header, recs = _sample_records()
    blobs = []
    for sub in ("a", "b"):
        (tmp_path / sub).mkdir()
        path = tmp_path / sub / f"flight_{sub}.jsonl.gz"  # different names, same bytes
        with LogWriter(path, header) as w:
            w.write_all(recs)
        blobs.append(path.read_bytes())
    assert blobs[0] == blobs[1]
    assert blobs[0][:2] == b"\x1f\x8b"
    assert blobs[0][4:8] == b"\0\0\0\0"  # mtime 0
    plain = tmp_path / "plain.jsonl"
    with LogWriter(plain, header) as w:
        w.write_all(recs)
    assert gzip.decompress(blobs[0]) == plain.read_bytes()


# ------------------------------------------------------------------------ bounded memory


def _write_big_log(path: Path, n: int, seed: int = 0) -> None:
    """``n`` lines (1 in 5 gnss, the rest rtt at 4 responders), 10 ms apart, locally shuffled
    in blocks of 16 lines; written as text, block by block."""
    rng = random.Random(seed)
    base = 81_000_000_000_000
    gnss = (
        '{"type":"gnss","t_ns":%d,"lat":%.7f,"lon":%.7f,"alt_m":%.2f,"acc_m":1.5,'
        '"fix":"3d","sats":20}'
    )
    rtt = '{"type":"rtt","t_ns":%d,"bssid":"a4:77:33:0f:1e:%02x","status":"ok","range_m":%.3f,"rssi_dbm":-70}'  # noqa: E501
    with open(path, "w", encoding="utf-8") as fh:
        fh.write(HEADER + "\n")
        for start in range(0, n, 10_000):
            lines = []
            for i in range(start, min(n, start + 10_000)):
                t = base + i * 10_000_000
                if i % 5 == 0:
                    lines.append(gnss % (t, 36.715 + i * 1e-8, -4.478 + i * 1e-8, 100 + i % 100))
                else:
                    lines.append(rtt % (t, i % 4, 50.0 + (i % 1000) * 0.01))
            for j in range(0, len(lines), 16):
                seg = lines[j : j + 16]
                rng.shuffle(seg)
                lines[j : j + 16] = seg
            fh.write("\n".join(lines))
            fh.write("\n")


def _stream_peak(path: Path, chunk: int) -> tuple[int, int, bool, float]:
    """Stream ``path`` sorted: (records, gnss records, ordered?, tracemalloc peak in MB)."""
    n = n_gnss = 0
    last = -1
    ordered = True
    tracemalloc.start()
    try:
        for rec in iter_log_sorted(path, chunk_records=chunk):
            n += 1
            n_gnss += isinstance(rec, GnssFix)
            ordered &= rec.t_ns >= last
            last = rec.t_ns
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    return n, n_gnss, ordered, peak / 1e6


def test_sorted_stream_memory_is_bounded_40k(tmp_path: Path) -> None:
    # measured: peak 1.9 MB with 2k-record chunks (1.85 MB for 20k records: the chunk
    # sets it, not the file); the 40k records held at once take ~14 MB and the file's
    # text alone is 4.5 MB, so 3 MB fails for any whole-file load (the 1M case: slow)
    path = tmp_path / "big.jsonl"
    _write_big_log(path, 40_000)
    n, n_gnss, ordered, peak_mb = _stream_peak(path, 2_000)
    assert (n, n_gnss, ordered) == (40_000, 8_000, True)
    assert path.stat().st_size > 4e6
    assert peak_mb < 3.0, f"peak {peak_mb:.1f} MB"


@pytest.mark.slow
@pytest.mark.timeout(1200)
def test_sorted_stream_memory_is_bounded_1m(tmp_path: Path) -> None:
    # measured: peak 20.6 MB with 50k-record chunks (~200 s under tracemalloc); the 1M
    # records held at once take ~345 MB and the file's text alone is 113 MB
    path = tmp_path / "big.jsonl"
    _write_big_log(path, 1_000_000)
    n, n_gnss, ordered, peak_mb = _stream_peak(path, 50_000)
    assert (n, n_gnss, ordered) == (1_000_000, 200_000, True)
    assert peak_mb < 50.0, f"peak {peak_mb:.1f} MB"


# ------------------------------------------------------------------------ properties

# valid records: every value inside the reader's documented limits (logio.BOUNDS)
_alt = st.floats(min_value=ALT_MIN_M, max_value=ALT_MAX_M)
_range = st.floats(min_value=-RANGE_MAX_M, max_value=RANGE_MAX_M)
_rssi = st.floats(min_value=RSSI_MIN_DBM, max_value=RSSI_MAX_DBM)
_nonneg = st.floats(min_value=0.0, max_value=ACC_MAX_M)
_t_ns = st.integers(min_value=0, max_value=T_NS_MAX)
_bssid = st.lists(st.integers(0, 255), min_size=6, max_size=6).map(
    lambda b: ":".join(f"{x:02x}" for x in b)
)
_lat = st.floats(min_value=-90.0, max_value=90.0, allow_nan=False)
_lon = st.floats(min_value=-180.0, max_value=180.0, allow_nan=False)
_opt_int = st.none() | st.integers(min_value=0, max_value=COUNT_MAX)

_gnss_st = st.builds(
    GnssFix,
    t_ns=_t_ns,
    lat_deg=_lat,
    lon_deg=_lon,
    alt_m=_alt,
    acc_m=_nonneg,
    vacc_m=st.none() | _nonneg,
    fix=st.none() | st.sampled_from(GNSS_FIX_TYPES),
    sats=_opt_int,
)
_rtt_ok_st = st.builds(
    RangeSample,
    t_ns=_t_ns,
    bssid=_bssid,
    status=st.just("ok"),
    range_m=_range,
    range_std_m=st.none() | _nonneg,
    rssi_dbm=_rssi,
    attempted=_opt_int,
    successful=_opt_int,
)
_rtt_fail_st = st.builds(
    RangeSample,
    t_ns=_t_ns,
    bssid=_bssid,
    status=st.sampled_from(["fail", "no_response", "ok?", ""])
    | st.text(max_size=8).filter(str.isprintable),
    range_m=st.none() | _range,
    range_std_m=st.none() | _nonneg,
    rssi_dbm=st.none() | _rssi,
    attempted=_opt_int,
    successful=_opt_int,
).filter(lambda r: r.status != "ok")
_truth_st = st.builds(
    TruthRecord,
    bssid=_bssid,
    lat_deg=_lat,
    lon_deg=_lon,
    alt_m=_alt,
    concealment=st.sampled_from(["open", "vegetation", "vegetation_debris"]),
)


@settings(max_examples=300, deadline=None)
@given(rec=st.one_of(_gnss_st, _rtt_ok_st, _rtt_fail_st, _truth_st))
def test_valid_records_round_trip_exactly(rec) -> None:
    counts = RejectCounts()
    line = dumps_record(rec)
    assert "\n" not in line
    back = parse_line(line, counts)
    assert back == rec
    assert type(back) is type(rec)
    assert counts == RejectCounts(lines=1)
    assert parse_line(line.encode("utf-8"), counts) == rec


def _counter_state(c: RejectCounts) -> tuple[int, int, int]:
    return c.n_rejected, sum(c.unknown_types.values()), c.unknown_fields


def _check_one_outcome(line: str | bytes) -> None:
    counts = RejectCounts()
    rec = parse_line(line, counts)
    rejected, unknown, _ = _counter_state(counts)
    if isinstance(line, bytes):
        try:
            text: str | None = line.decode("utf-8")
        except UnicodeDecodeError:
            text = None
    else:
        text = line
    if rec is not None:
        assert rejected == 0 and unknown == 0
        assert isinstance(rec, GnssFix | RangeSample | TruthRecord | LogHeader)
    elif text is not None and not text.removeprefix("\ufeff").strip():
        assert counts == RejectCounts()  # blank (a leading byte-order mark is not content)
    else:
        assert rejected + unknown == 1, (line, counts)
        assert counts.unknown_fields == 0


@settings(max_examples=300, deadline=None)
@given(line=st.text() | st.binary())
def test_arbitrary_lines_never_raise(line: str | bytes) -> None:
    _check_one_outcome(line)


_json_leaf = (
    st.none()
    | st.booleans()
    | st.integers(min_value=-(2**70), max_value=2**70)
    | st.floats(allow_nan=False, allow_infinity=False)
    | st.text(max_size=20)
    | _bssid
)
_json_value = st.recursive(
    _json_leaf,
    lambda kids: (
        st.lists(kids, max_size=3) | st.dictionaries(st.text(max_size=5), kids, max_size=3)
    ),
    max_leaves=6,
)
_keys = sorted(
    {"t_ns", "lat", "lon", "alt_m", "acc_m", "vacc_m", "fix", "sats", "bssid", "status"}
    | {"range_m", "range_std_m", "rssi_dbm", "attempted", "successful", "concealment", "extra"}
)


@st.composite
def _json_ish_lines(draw) -> str:
    """Record-shaped objects with random values, sometimes with a non-finite token spliced in."""
    obj = {"type": draw(st.sampled_from(["gnss", "rtt", "truth", "imu"]))}
    for k in draw(st.lists(st.sampled_from(_keys), unique=True, max_size=len(_keys))):
        obj[k] = draw(_json_value)
    line = json.dumps(obj)
    keys = [k for k in obj if k != "type"]
    if keys and draw(st.booleans()):
        line = _replace(
            line,
            draw(st.sampled_from(keys)),
            draw(st.sampled_from(["NaN", "Infinity", "-Infinity"])),
        )
    return line


@st.composite
def _mutated_lines(draw) -> bytes:
    rec = draw(st.one_of(_gnss_st, _rtt_ok_st, _rtt_fail_st, _truth_st))
    raw = bytearray(dumps_record(rec).encode())
    start = draw(st.integers(0, len(raw)))
    stop = draw(st.integers(start, min(len(raw), start + 8)))
    raw[start:stop] = draw(st.binary(max_size=8))
    return bytes(raw)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(line=_json_ish_lines() | _mutated_lines())
def test_record_shaped_garbage_never_raises(line: str | bytes) -> None:
    _check_one_outcome(line)


def test_a_gzip_log_closes_its_file_when_abandoned(tmp_path: Path) -> None:
    """Reading part of a .gz log and stopping leaves no file open (no ResourceWarning)."""
    import gc

    from estimator.logio import probe_log

    path, _ = _big_gz_log(tmp_path, n=50)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        stream = probe_log(path)
        it = iter_log(path)
        next(it)
        it.close()
        del it
        gc.collect()
    assert stream.n_records == 2  # the header and the first fix
    assert [w for w in caught if issubclass(w.category, ResourceWarning)] == []


@pytest.mark.parametrize("name", ["log.jsonl.gz", "log.jsonl"])
def test_reading_closes_the_file_under_the_gzip_stream(tmp_path: Path, name: str) -> None:
    """Every replay of a gzip log printed 'unclosed file': the GzipFile did not close the
    file it was given. Reading to the end, or stopping early, must leave nothing open."""
    import gc

    from estimator.replay import replay_logs
    from tests.estimator.synth import write_flight

    path = write_flight(tmp_path / name, seed=1, duration_s=30.0)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        replay_logs([path])
        it = iter_log(path)
        next(it)
        it.close()  # an abandoned reader closes too
        gc.collect()
    assert [w for w in caught if issubclass(w.category, ResourceWarning)] == []


def test_records_from_columns_are_the_dataclass_records() -> None:
    """The simulator's fast construction gives records equal to cls(**row), frozen,
    hashable, and refuses columns that are not the class's fields."""
    import dataclasses

    import pytest

    from estimator.records import GnssFix, RangeSample, records_from_columns

    cols = {"t_ns": [1, 2], "bssid": ["aa:bb:cc:dd:ee:ff"] * 2, "status": ["ok", "fail"],
            "range_m": [12.5, None], "range_std_m": [0.4, None], "rssi_dbm": [-61.0, None],
            "attempted": [8, 8], "successful": [7, 0]}
    got = records_from_columns(RangeSample, cols)
    want = [RangeSample(**dict(zip(cols, row, strict=True)))
            for row in zip(*cols.values(), strict=True)]
    assert got == want and hash(got[0]) == hash(want[0]) and got[0].ok and not got[1].ok
    with pytest.raises(dataclasses.FrozenInstanceError):
        got[0].range_m = 3.0  # type: ignore[misc]
    with pytest.raises(ValueError, match="not the fields of GnssFix"):
        records_from_columns(GnssFix, {"t_ns": [1], "lat_deg": [0.0]})


def test_trajectory_refuses_bad_paths() -> None:
    import numpy as np
    import pytest

    from estimator.records import Trajectory

    o = (36.7, -4.4, 0.0)
    ok = Trajectory([0.0, 1.0, 1.0], np.zeros((3, 3)), o)  # a hover: equal times allowed
    assert ok.t_s.dtype == float and ok.enu_m.shape == (3, 3)
    with pytest.raises(ValueError, match="non-finite"):
        Trajectory([0.0, 1.0], [[0.0, 0.0, 0.0], [np.nan, 0.0, 0.0]], o)
    with pytest.raises(ValueError, match="non-finite"):
        Trajectory([0.0, np.inf], np.zeros((2, 3)), o)
    with pytest.raises(ValueError, match="non-decreasing"):
        Trajectory([0.0, 2.0, 1.0], np.zeros((3, 3)), o)
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        Trajectory([0.0, 1.0], np.zeros((2, 2)), o)
