"""NMEA 0183 text: ``GGA`` sentences for the fixes, ``RMC`` for the date.

``$xxGGA,hhmmss.ss,ddmm.mmmm,N,dddmm.mmmm,E,q,nn,hdop,alt,M,N,M,...*cs`` (any talker
``xx``: ``GP``, ``GN``, ``GL``...). Used: the UTC time of day (dated by the nearest
``RMC`` sentence's ``ddmmyy``, across midnight too), latitude, longitude, the fix
quality ``q`` (0 invalid, 6 dead reckoning, 7 manual and 8 simulated are skipped as
``no_fix``; 2 is ``dgps``, 4 ``rtk_fixed``, 5 ``rtk_float``, 1 and 3 leave the fix
type unknown), the satellites ``nn``, HDOP (``acc_m`` = 1.5 m x HDOP: a typical
standalone user equivalent range error; it is a proxy, as the log format says) and
the height: ``alt`` above mean sea level plus the geoid separation ``N`` of the same
sentence (ellipsoidal = MSL + N), ``--geoid-offset`` when the sentence has none.
A sentence whose ``*hh`` checksum does not match is skipped (``bad_checksum``); one
behind binary bytes on its line (a u-center log's UBX messages) is read from its ``$``.
A GGA without a fix and a void RMC (status ``V``) without a date, as a receiver writes
them before it has a fix and the time (their time or date empty), are ``no_fix``.
"""

from __future__ import annotations

import functools
import operator
import re
from collections.abc import Iterator
from datetime import UTC, date, datetime, timedelta
from pathlib import Path
from typing import IO

from estimator.importers.common import (
    NS_PER_S,
    GnssOptions,
    Skip,
    Source,
    Stamped,
    Tally,
    ellipsoidal_m,
    integer,
    make_fix,
    number,
    open_file,
    text_lines,
)
from estimator.logio import RejectCounts

FORMAT = "nmea"
KIND = "gnss"
HDOP_TO_ACC_M = 1.5  # acc_m = 1.5 m x HDOP (documented in docs/import.md)
QUALITY = {1: None, 2: "dgps", 3: None, 4: "rtk_fixed", 5: "rtk_float"}
_SENTENCE = re.compile(rb"^\$[A-Z]{2}(GGA|RMC),")
_HHMMSS = re.compile(r"(\d{2})(\d{2})(\d{2}(?:\.\d+)?)")
_DDMMYY = re.compile(r"\d{6}")
_START = re.compile(r"\$[A-Z]{5},")  # where a sentence starts, after other bytes too


def sniff(head: bytes) -> bool:
    """Whether the file has GGA or RMC sentences near its start."""
    return any(_SENTENCE.match(ln.strip()) for ln in head.splitlines()[:200])


def _checked(line: str) -> list[str]:
    """The fields of one sentence (after ``$xxTTT``), its checksum verified if present."""
    body = line.strip()
    if not body.startswith("$"):
        raise Skip("bad_line")
    body = body[1:]
    if "*" in body:
        body, cs = body.rsplit("*", 1)
        want = functools.reduce(operator.xor, body.encode("ascii", "replace"), 0)
        try:
            if int(cs[:2], 16) != want:
                raise Skip("bad_checksum")
        except ValueError:
            raise Skip("bad_checksum") from None
    return body.split(",")


def _time_of_day_ns(text: str) -> int:
    m = _HHMMSS.fullmatch(text.strip())
    if not m:
        raise Skip("bad_time")
    h, mi = int(m.group(1)), int(m.group(2))
    sec_text = m.group(3)
    whole, _, frac = sec_text.partition(".")
    s = int(whole)
    if h > 23 or mi > 59 or s > 60:
        raise Skip("bad_time")
    frac_ns = int((frac + "000000000")[:9]) if frac else 0
    return ((h * 60 + mi) * 60 + s) * NS_PER_S + frac_ns


def _angle(value: str, hemi: str, degree_digits: int, positive: str, negative: str) -> float:
    v = value.strip()
    if not v:
        raise Skip("missing_field")
    deg_text, minutes_text = v[:degree_digits], v[degree_digits:]
    deg = integer(deg_text)
    minutes = number(minutes_text)
    if deg is None or minutes is None:
        raise Skip("bad_type")
    if minutes >= 60.0:
        raise Skip("bad_value")
    a = deg + minutes / 60.0
    h = hemi.strip().upper()
    if h == negative:
        return -a
    if h != positive:
        raise Skip("bad_value")
    return a


def _rmc_date(fields: list[str]) -> date | None:
    if len(fields) < 10:
        return None
    d = fields[9].strip()
    if not _DDMMYY.fullmatch(d):
        return None
    try:
        return date(2000 + int(d[4:6]), int(d[2:4]), int(d[0:2]))
    except ValueError:
        return None


def _void_undated(fields: list[str]) -> bool:
    """Whether an RMC is a receiver's "void" sentence (status ``V``: no fix) without a
    date yet, as receivers write them before they have the time."""
    return (len(fields) > 2 and fields[2].strip().upper() == "V"
            and (len(fields) < 10 or not fields[9].strip()))


def _sentences(fh: IO[bytes], counts: RejectCounts) -> Iterator[str]:
    """The lines of an NMEA file, each from where its sentence starts: a receiver's log
    (u-center's) holds binary messages between the sentences, with no line break after
    them, so a sentence can follow other bytes on its line (read as Latin-1: NMEA is
    ASCII). A line without a sentence start is given whole."""
    for _, line in text_lines(fh, counts, eight_bit=True):
        if not _START.match(line):
            starts = [m.start() for m in _START.finditer(line)]
            if starts:
                line = line[starts[-1]:]
        yield line


class Reader:
    """The GGA fixes of one NMEA file (see the module docstring)."""

    def __init__(self, path: Path, options: GnssOptions) -> None:
        self.options = options
        self.source = Source(path=path, format=FORMAT, kind=KIND, label="GGA sentences",
                             utc_uncertainty_ns=5_000_000)  # hhmmss.ss: 10 ms steps

    def _first_date(self) -> tuple[date, int] | None:
        with open_file(self.source.path) as fh:
            for line in _sentences(fh, Tally().counts):
                if line[3:6] == "RMC":
                    try:
                        f = _checked(line)
                        d = _rmc_date(f)
                        if d is not None:
                            return d, _time_of_day_ns(f[1])
                    except Skip:
                        continue
        return None

    def records(self, tally: Tally) -> Iterator[Stamped]:
        dated = self._first_date()  # GGAs before the first RMC take its date
        if dated is None:
            self.source.warn("no RMC sentence with a date: the fixes cannot be dated")
        with open_file(self.source.path) as fh:
            for line in _sentences(fh, tally.counts):
                kind = line[3:6] if line.startswith("$") else ""
                if kind not in ("GGA", "RMC"):
                    tally.counts.unknown_types[line[1:6] if line.startswith("$") else
                                               "(not a sentence)"] += 1
                    continue
                tally.counts.lines += 1
                try:
                    fields = _checked(line)
                    if kind == "RMC":
                        d = _rmc_date(fields)
                        if d is None:
                            raise Skip("no_fix" if _void_undated(fields) else "bad_date")
                        dated = (d, _time_of_day_ns(fields[1]))
                        continue
                    if dated is None:
                        raise Skip("no_date")
                    yield self._fix(fields, dated, tally)
                except Skip as s:
                    tally.skip(s.reason)

    def _fix(self, f: list[str], dated: tuple[date, int], tally: Tally) -> Stamped:
        if len(f) < 12:
            raise Skip("missing_field")
        quality = integer(f[6])  # first: a receiver without a fix leaves the time empty
        if quality is None:
            raise Skip("missing_field")
        if quality not in QUALITY:
            raise Skip("no_fix")
        tod = _time_of_day_ns(f[1])
        day, rmc_tod = dated
        if tod < rmc_tod - 43_200 * NS_PER_S:  # the GGA is past midnight after the RMC
            day = day + timedelta(days=1)
        elif tod > rmc_tod + 43_200 * NS_PER_S:
            day = day - timedelta(days=1)
        midnight = int(datetime(day.year, day.month, day.day, tzinfo=UTC).timestamp())
        utc_ns = midnight * NS_PER_S + tod
        lat = _angle(f[2], f[3], 2, "N", "S")
        lon = _angle(f[4], f[5], 3, "E", "W")
        hdop = number(f[8])
        alt, how = ellipsoidal_m(self.source, number(f[9]), number(f[11]),
                                 self.options.geoid_offset_m)
        fix = make_fix(
            lat_deg=lat,
            lon_deg=lon,
            alt_m=alt,
            acc_m=None if hdop is None else HDOP_TO_ACC_M * hdop,
            fix=QUALITY[quality],
            sats=integer(f[7]),
            default_acc_m=self.options.default_acc_m,
        )
        tally.heights[how] += 1
        return Stamped(fix, utc_ns=utc_ns)

    def close(self) -> None:
        pass
