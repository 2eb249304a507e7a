"""Recorder files as phones, spreadsheets and loggers leave them: a UTF-8 byte order mark
(Excel's "CSV UTF-8", Windows Notepad), CRLF line endings, columns reordered and extra
ones, several talkers in one NMEA file. Each imports to the same records as the plain
file the tests write."""

from __future__ import annotations

from estimator.importers import ImportOptions, import_flight
from estimator.logio import read_log
from tests.estimator.importers.writers import (
    write_android_csv,
    write_gnsslogger,
    write_nmea,
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
    plain_j, plain_log = _import(gl, rtt2, tmp_path / "gl_plain.jsonl")
    assert gl_j["gnss"]["records_read"] == len(flight.gnss)
    assert gl_log.gnss == plain_log.gnss  # latitude and longitude from their own columns
    assert 35.0 < gl_log.gnss[0].lat_deg < 38.0 and -5.0 < gl_log.gnss[0].lon_deg < -4.0
