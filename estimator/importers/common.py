"""What every recorder reader shares: the stamped record, the skip reasons, the checks.

A reader turns one foreign file into log records (:class:`estimator.records.GnssFix`,
:class:`estimator.records.RangeSample`) with their clock facts (:class:`Stamped`): the
UTC time of the record and/or the phone's ``elapsedRealtimeNanos``. The record's own
``t_ns`` is 0 until :mod:`estimator.importers.joiner` puts every record on one time
axis. A line or message a reader cannot use raises :class:`Skip` with a reason (the
vocabulary of :class:`estimator.logio.RejectCounts` where one fits) and is counted,
never fatal; a file that cannot be read at all raises :class:`SourceError`.
"""

from __future__ import annotations

import math
import re
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from datetime import UTC, datetime
from decimal import ROUND_HALF_EVEN, Decimal, InvalidOperation
from pathlib import Path
from typing import IO

from estimator.logio import RejectCounts
from estimator.records import GnssFix, RangeSample

NS_PER_S = 1_000_000_000
# Android RangingResult status codes (android.net.wifi.rtt.RangingResult)
ANDROID_RTT_STATUS = {0: "ok", 1: "fail", 2: "not_80211mc"}

_MAC_SEPARATED = re.compile(r"^[0-9a-fA-F]{2}([:-])[0-9a-fA-F]{2}(\1[0-9a-fA-F]{2}){4}$")
_MAC_BARE = re.compile(r"^[0-9a-fA-F]{12}$")


class SourceError(Exception):
    """A recorder file that cannot be read at all (one line naming the file)."""


def brief(exc: BaseException, limit: int = 160) -> str:
    """A library's error message as one short line, to quote in a one-line refusal or
    warning: its whitespace (newlines too) collapsed, cut at ``limit`` characters."""
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if len(text) <= limit else text[:limit - 3] + "..."


class Skip(Exception):  # noqa: N818 - a counted skip, not an error
    """One line or message that is not used, with the reason it is counted under."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


@dataclass(frozen=True, slots=True)
class Stamped:
    """A log record (its ``t_ns`` still 0) with the clocks its source gave it."""

    record: GnssFix | RangeSample
    utc_ns: int | None = None  # Unix time (UTC) of the record, ns
    elapsed_ns: int | None = None  # the phone's elapsedRealtimeNanos, ns since its boot


@dataclass(frozen=True, kw_only=True)
class GnssOptions:
    """What a GNSS reader may be told: which stream, the geoid undulation to use for
    heights above mean sea level, the accuracy of fixes that carry none."""

    topic: str | None = None  # --topic
    geoid_offset_m: float | None = None  # --geoid-offset: N (ellipsoidal = MSL + N)
    default_acc_m: float | None = None  # --gnss-acc: acc_m of fixes without an accuracy


@dataclass(frozen=True, kw_only=True)
class RangesOptions:
    """What a ranging reader may be told: the UTC time of the file's time zero when the
    file's own is missing or wrong (SensorReadout)."""

    start_utc_ns: int | None = None  # --ranges-start-utc


@dataclass
class Source:
    """A reader's description of its file, filled in as it reads.

    ``label`` says which stream was read (a topic, a provider); ``utc_uncertainty_ns``
    bounds the error of its UTC stamps (half their resolution, or more when the file's
    wall clock is coarse).
    """

    path: Path
    format: str
    kind: str  # "gnss" or "ranges"
    label: str = ""
    utc_uncertainty_ns: int = 500_000
    warnings: list[str] = field(default_factory=list)

    def warn(self, text: str) -> None:
        """Remember a warning once (readers run twice over a file)."""
        msg = f"{self.path}: {text}"
        if msg not in self.warnings:
            self.warnings.append(msg)


@dataclass
class Tally:
    """What one reading of a file counted: skipped lines by reason (and other record
    types, ``counts.unknown_types``), and how each fix's ``alt_m`` was obtained
    (``heights``: ``ellipsoid``, the source's own ellipsoidal height; ``undulation``,
    MSL plus the source's N; ``geoid_offset``, MSL plus ``--geoid-offset``;
    ``msl_as_ellipsoid``, MSL with no N at all)."""

    counts: RejectCounts = field(default_factory=RejectCounts)
    heights: Counter = field(default_factory=Counter)

    def skip(self, reason: str) -> None:
        self.counts.reject(reason)


def ellipsoidal_m(source: Source, msl_m: float | None, undulation_m: float | None,
                  geoid_offset_m: float | None) -> tuple[float, str]:
    """Height above the WGS84 ellipsoid from a height above mean sea level, and how it
    was obtained (a :attr:`Tally.heights` key): MSL + N with the source's undulation N
    (``undulation``), else ``--geoid-offset`` (``geoid_offset``), else MSL itself with a
    warning (``msl_as_ellipsoid``)."""
    if msl_m is None:
        raise Skip("missing_field")
    if undulation_m is not None and math.isfinite(undulation_m):
        return msl_m + undulation_m, "undulation"
    if geoid_offset_m is not None:
        return msl_m + geoid_offset_m, "geoid_offset"
    source.warn("heights above mean sea level and no geoid undulation: alt_m is MSL, off "
                "by the local N (give it with --geoid-offset)")
    return msl_m, "msl_as_ellipsoid"


def normalise_bssid(text: str) -> str:
    """A MAC address as the log writes it (lower case, colon separated) from the forms
    recorders use: ``A4:77:33:0F:1E:02``, ``a4-77-33-0f-1e-02``, ``a477330f1e02``."""
    t = text.strip()
    if _MAC_SEPARATED.fullmatch(t):
        return t.replace("-", ":").lower()
    if _MAC_BARE.fullmatch(t):
        t = t.lower()
        return ":".join(t[i:i + 2] for i in range(0, 12, 2))
    raise Skip("bad_bssid")


def number(text: str | None) -> float | None:
    """A decimal number from a text field; ``None`` when empty. Raises :class:`Skip`
    (``bad_type``, ``non_finite``) for anything else."""
    if text is None:
        return None
    t = text.strip()
    if not t:
        return None
    try:
        v = float(t)
    except ValueError:
        raise Skip("bad_type") from None
    if not math.isfinite(v):
        raise Skip("non_finite")
    return v


def integer(text: str | None) -> int | None:
    """An integer from a text field (``12``, ``12.0``); ``None`` when empty."""
    if text is None or not text.strip():
        return None
    t = text.strip()
    try:
        return int(t)
    except ValueError:
        pass
    v = number(t)
    if v is None or not v.is_integer():
        raise Skip("bad_type")
    return int(v)


_EXPONENT = re.compile(r"^[+-]?(?=\.?\d)(\d*)(?:\.(\d*))?[eE]([+-]?\d+)$")  # a digit first


def _not_rounded(text: str) -> str:
    """``text``, unless it is written in exponent form with fewer digits than its size
    (``1.74972E+12``: a spreadsheet's rounding of 1749723127123, off by up to hours):
    :class:`Skip` ``rounded_time``."""
    t = text.strip()
    m = _EXPONENT.fullmatch(t)
    if m and len(m.group(2) or "") < int(m.group(3)) and float(t) != 0.0:
        raise Skip("rounded_time")
    return t


def time_integer(text: str | None) -> int | None:
    """An integer time field (ns, ms): :func:`integer`, but a rounded exponent form is
    skipped as ``rounded_time``, never read as a wrong time."""
    if text is None or not text.strip():
        return None
    t = _not_rounded(text)
    if _EXPONENT.fullmatch(t):
        try:
            d = Decimal(t)
        except InvalidOperation:
            raise Skip("bad_type") from None
        if d != d.to_integral_value():
            raise Skip("bad_type")
        return int(d)
    return integer(t)


def ms_to_ns(text: str | None) -> int | None:
    """Milliseconds (an integer, or a decimal with a fraction) as integer nanoseconds,
    exactly; a rounded exponent form is ``rounded_time`` (:func:`time_integer`)."""
    if text is None or not text.strip():
        return None
    t = _not_rounded(text)
    try:
        return int(t) * 1_000_000
    except ValueError:
        v = number(t)  # bad_type, non_finite
        assert v is not None
        return int((Decimal(t) * 1_000_000).to_integral_value(rounding=ROUND_HALF_EVEN))


def float32_decimal(value: float) -> float:
    """A single-precision value as the shortest decimal that is it (0.902, not the
    0.9020000100135803 its widening to double gives): what the recorder meant."""
    import numpy as np

    return float(np.format_float_positional(np.float32(value), unique=True))


def accuracy_field(text: str | None) -> float | None:
    """An accuracy from a text field: :func:`number`, but ``NaN`` (what apps write for an
    accuracy they do not have) is unknown, ``None``, as an empty field is."""
    if text is not None and text.strip().lower() == "nan":
        return None
    return number(text)


def accuracy_m(value: float | None) -> float | None:
    """A source's accuracy in metres: ``None`` (unknown) when missing, NaN or zero;
    :class:`Skip` ``bad_value`` when negative."""
    if value is None or not math.isfinite(value) or value == 0.0:
        return None
    if value < 0.0:
        raise Skip("bad_value")
    return float(value)


def make_fix(
    *,
    lat_deg: float | None,
    lon_deg: float | None,
    alt_m: float | None,
    acc_m: float | None,
    vacc_m: float | None = None,
    fix: str | None = None,
    sats: int | None = None,
    default_acc_m: float | None = None,
) -> GnssFix:
    """A checked ``gnss`` record (``t_ns`` 0): the log reader's rules (finite values,
    latitude in [-90, 90], longitude in [-180, 180]); an unknown accuracy takes
    ``default_acc_m`` or the fix is skipped (``no_accuracy``)."""
    if lat_deg is None or lon_deg is None or alt_m is None:
        raise Skip("missing_field")
    for v in (lat_deg, lon_deg, alt_m):
        if not math.isfinite(v):
            raise Skip("non_finite")
    if not -90.0 <= lat_deg <= 90.0:
        raise Skip("bad_latitude")
    if not -180.0 <= lon_deg <= 180.0:
        raise Skip("bad_longitude")
    acc = accuracy_m(acc_m)
    if acc is None:
        if default_acc_m is None:
            raise Skip("no_accuracy")
        acc = default_acc_m
    return GnssFix(t_ns=0, lat_deg=float(lat_deg), lon_deg=float(lon_deg), alt_m=float(alt_m),
                   acc_m=acc, vacc_m=accuracy_m(vacc_m), fix=fix, sats=sats)


def make_range(
    *,
    bssid: str,
    status: str,
    distance_mm: float | None,
    std_dev_mm: float | None,
    rssi_dbm: float | None,
    attempted: int | None,
    successful: int | None,
) -> RangeSample:
    """A checked ``rtt`` record (``t_ns`` 0) from Android ``RangingResult`` fields:
    ``range_m`` = distance_mm / 1000, ``range_std_m`` = distance_std_dev_mm / 1000; an
    ``ok`` result needs its distance and RSSI, a failed one keeps only its counts."""
    b = normalise_bssid(bssid)
    if status == "ok":
        if distance_mm is None or rssi_dbm is None:
            raise Skip("missing_field")
        if std_dev_mm is not None and std_dev_mm < 0:
            raise Skip("bad_value")
        return RangeSample(
            t_ns=0, bssid=b, status="ok", range_m=distance_mm / 1000.0,
            range_std_m=None if std_dev_mm is None else std_dev_mm / 1000.0,
            rssi_dbm=rssi_dbm, attempted=attempted, successful=successful,
        )
    return RangeSample(t_ns=0, bssid=b, status=status, attempted=attempted,
                       successful=successful)


def status_word(text: str) -> str:
    """A ranging status as the log writes it: ``0`` or ``success`` is ``ok``; Android's
    codes 1 and 2 are ``fail`` and ``not_80211mc``, other codes ``status_N``; a word is
    kept in lower case."""
    t = text.strip().lower()
    if not t:
        raise Skip("missing_field")
    if t in ("ok", "success"):
        return "ok"
    try:
        code = int(t)
    except ValueError:
        if not re.fullmatch(r"[a-z][a-z0-9_]*", t):
            raise Skip("bad_value") from None
        return t
    return ANDROID_RTT_STATUS.get(code, f"status_{code}")


def text_lines(fh: IO[bytes], counts: RejectCounts, *,
               eight_bit: bool = False) -> Iterator[tuple[int, str]]:
    """(line number, text) of a binary file's lines without their line ending; a line
    that is not UTF-8 is counted (``not_utf8``) and skipped, or, with ``eight_bit``, read
    as Latin-1 (a spreadsheet's export in a Windows code page, for a reader that uses
    only ASCII fields: the other bytes land in columns it ignores or fail its checks);
    blank lines are skipped. A UTF-8 byte order mark (Excel and Windows Notepad write
    one) is not part of the first line: left in, it would hide the first column's
    name."""
    for n, raw in enumerate(fh, start=1):
        if n == 1 and raw.startswith(b"\xef\xbb\xbf"):
            raw = raw[3:]
        try:
            line = raw.decode("utf-8")
        except UnicodeDecodeError:
            if eight_bit:
                line = raw.decode("latin-1")
            else:
                counts.lines += 1
                counts.reject("not_utf8")
                continue
        line = line.rstrip("\r\n")
        if line.strip():
            yield n, line


def open_file(path: Path) -> IO[bytes]:
    """Open a recorder file for reading; :class:`SourceError` (one line) if it cannot."""
    try:
        return open(path, "rb")  # the caller closes it
    except FileNotFoundError:
        raise SourceError(f"{path}: no such file") from None
    except IsADirectoryError:
        raise SourceError(f"{path}: is a directory") from None
    except PermissionError:
        raise SourceError(f"{path}: permission denied") from None
    except OSError as exc:
        raise SourceError(f"{path}: cannot open ({exc.strerror})") from None


def utc_text(utc_ns: int) -> str:
    """ISO 8601 UTC with milliseconds, as the log header's ``start_utc``."""
    dt = datetime.fromtimestamp(utc_ns // NS_PER_S, tz=UTC)
    ms = (utc_ns % NS_PER_S) // 1_000_000
    return dt.strftime("%Y-%m-%dT%H:%M:%S") + f".{ms:03d}Z"
