"""SensorReadout logs (the FHWS SensorReadout Android app): their WiFi RTT events.

Each line is ``timestamp;eventId;arguments...`` separated by ``;``. The timestamp is
in nanoseconds since the recording started (the app subtracts its start
``elapsedRealtimeNanos``), so it is not the phone's boot clock; the wall-clock start
is the ``-2`` (file metadata) line's date, Java's ``Date.toString()``
(``Wed Apr 08 15:35:20 GMT+02:00 2020``): one-second resolution, hence a +-1 s
uncertainty of every UTC time of the file (``--ranges-start-utc`` gives the start
when it is known better or is missing). Ranging events are ``17``:
``success;mac;distInMM;distInStdDevMM;rssi;numAttempted;numSuccessful`` (``mac`` with
or without colons). Other events are counted by id and not used.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from datetime import datetime, timedelta, timezone
from pathlib import Path

from estimator.importers.common import (
    NS_PER_S,
    RangesOptions,
    Skip,
    Source,
    SourceError,
    Stamped,
    Tally,
    integer,
    make_range,
    number,
    open_file,
    text_lines,
)

FORMAT = "sensorreadout"
KIND = "ranges"
RTT_EVENT = 17
METADATA_EVENT = -2
_LINE = re.compile(rb"^-?\d+;-?\d+(;|$)")
# unambiguous zone abbreviations Java's Date.toString() prints (hours east of UTC)
ZONES = {
    "UTC": 0, "GMT": 0, "WET": 0, "WEST": 1, "CET": 1, "CEST": 2, "EET": 2, "EEST": 3,
    "BST": 1, "EST": -5, "EDT": -4, "CDT": -5, "MST": -7, "MDT": -6, "PST": -8, "PDT": -7,
    "AKST": -9, "AKDT": -8, "HST": -10, "JST": 9, "KST": 9, "AEST": 10, "AEDT": 11,
    "ACST": 9.5, "AWST": 8, "NZST": 12, "NZDT": 13,
}
_OFFSET = re.compile(r"^(?:GMT|UTC)([+-])(\d{1,2}):?(\d{2})?$")


def sniff(head: bytes) -> bool:
    """Whether most of the first lines look like ``timestamp;eventId;...``."""
    lines = [ln for ln in head.splitlines()[:50] if ln.strip()]
    return bool(lines) and sum(bool(_LINE.match(ln)) for ln in lines) >= 0.8 * len(lines)


def java_date_utc_ns(text: str) -> int:
    """UTC nanoseconds of a Java ``Date.toString()`` (``EEE MMM dd HH:mm:ss zzz yyyy``).

    Raises ``ValueError`` for another form or a zone that is not an unambiguous
    abbreviation (``ZONES``) or ``GMT+hh:mm``.
    """
    parts = text.split()
    if len(parts) != 6:
        raise ValueError(f"not a Java date: {text!r}")
    _, month, day, clock, zone, year = parts
    naive = datetime.strptime(f"{month} {day} {clock} {year}", "%b %d %H:%M:%S %Y")
    m = _OFFSET.match(zone)
    if m:
        sign = -1 if m.group(1) == "-" else 1
        hours = sign * (int(m.group(2)) + int(m.group(3) or 0) / 60.0)
    elif zone in ZONES:
        hours = ZONES[zone]
    else:
        raise ValueError(f"unknown time zone {zone!r}")
    dt = naive.replace(tzinfo=timezone(timedelta(hours=hours)))
    return int(dt.timestamp()) * NS_PER_S


class Reader:
    """The ranging results of one SensorReadout file (see the module docstring)."""

    def __init__(self, path: Path, options: RangesOptions) -> None:
        self.source = Source(path=path, format=FORMAT, kind=KIND,
                             label=f"event {RTT_EVENT} (WiFi RTT) lines")
        if options.start_utc_ns is not None:
            self.start_utc_ns = options.start_utc_ns
            self.source.utc_uncertainty_ns = 1_000_000  # as given
            self.source.label += ", start from --ranges-start-utc"
        else:
            self.start_utc_ns = self._metadata_start()
            self.source.utc_uncertainty_ns = NS_PER_S  # Date.toString(): whole seconds
            self.source.label += ", start from the metadata line (+-1 s)"

    def _metadata_start(self) -> int:
        with open_file(self.source.path) as fh:
            for _, line in text_lines(fh, Tally().counts):
                parts = line.split(";")
                if len(parts) >= 3 and parts[1].strip() == str(METADATA_EVENT):
                    try:
                        return java_date_utc_ns(parts[2].strip())
                    except ValueError as exc:
                        raise SourceError(f"{self.source.path}: cannot read the recording "
                                          f"start ({exc}): give it with --ranges-start-utc"
                                          ) from None
        raise SourceError(f"{self.source.path}: no recording start (no {METADATA_EVENT} "
                          "metadata line): give it with --ranges-start-utc")

    def records(self, tally: Tally) -> Iterator[Stamped]:
        with open_file(self.source.path) as fh:
            for _, line in text_lines(fh, tally.counts):
                parts = line.split(";")
                try:
                    event = int(parts[1]) if len(parts) > 1 else None
                except ValueError:
                    event = None
                if event is None:
                    tally.counts.lines += 1
                    tally.skip("bad_line")
                    continue
                if event == METADATA_EVENT:  # read for the start time
                    continue
                if event != RTT_EVENT:
                    tally.counts.unknown_types[f"event {event}"] += 1
                    continue
                tally.counts.lines += 1
                try:
                    yield self._result(parts)
                except Skip as s:
                    tally.skip(s.reason)

    def _result(self, parts: list[str]) -> Stamped:
        if len(parts) != 9:
            raise Skip("wrong_column_count")
        t_rel = integer(parts[0])
        if t_rel is None:
            raise Skip("missing_field")
        if t_rel < 0:
            raise Skip("negative_time")
        ok = parts[2].strip().lower()
        if ok not in ("1", "0", "true", "false"):
            raise Skip("bad_value")
        rec = make_range(
            bssid=parts[3],
            status="ok" if ok in ("1", "true") else "fail",
            distance_mm=number(parts[4]),
            std_dev_mm=number(parts[5]),
            rssi_dbm=number(parts[6]),
            attempted=integer(parts[7]),
            successful=integer(parts[8]),
        )
        return Stamped(rec, utc_ns=self.start_utc_ns + t_rel)

    def close(self) -> None:
        pass
