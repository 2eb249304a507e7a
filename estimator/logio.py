"""Flight-log reader and writer: the format of docs/log-format.md, version 1.

Reading never crashes on a bad line and never drops a good one because of it: every
rejected line is counted by reason (``RejectCounts``). Plain ``.jsonl`` and gzip
(detected by its magic bytes, whatever the file is called) are both accepted.

Streaming: :func:`iter_log` yields records in file order with O(1) memory;
:func:`iter_log_sorted` yields them ordered by ``t_ns`` (stable) with bounded memory,
spilling sorted runs of ``chunk_records`` records to temporary files and merging them
(an external merge sort), so a log of any length is ordered without holding it.

Bounded on any input (docs/log-format.md, "Limits"): every value is checked against
physical bounds (:data:`BOUNDS`), a line longer than :data:`MAX_LINE_BYTES` is skipped
without being held, a gzip stream that expands beyond :data:`GZIP_MAX_RATIO` times its
compressed size is refused, a file whose first :data:`MAX_PREFIX_BYTES` hold no valid
record is not a log, and at most :data:`MAX_BSSIDS` responders are read. A log is
opened once and read in one pass, so a pipe, a fifo or ``-`` (standard input) loses
nothing. Strings from a log never carry terminal control characters (they are
escaped as they are read).
"""

from __future__ import annotations

import contextlib
import dataclasses
import gzip
import heapq
import io
import json
import math
import os
import pickle
import re
import sys
import tempfile
import warnings
import zlib
from collections import Counter, deque
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from estimator.records import (
    LOG_FORMAT,
    LOG_VERSION,
    GnssFix,
    LogHeader,
    RangeSample,
    TruthRecord,
)

Record = LogHeader | GnssFix | RangeSample | TruthRecord
TimedRecord = GnssFix | RangeSample

_BSSID_RE = re.compile(r"^[0-9a-fA-F]{2}(:[0-9a-fA-F]{2}){5}$")
_GZIP_MAGIC = b"\x1f\x8b"
_BOM = "\ufeff"  # a UTF-8 byte-order mark, skipped at the start of a line
STDIN = "-"  # the path that reads standard input

# Limits of the reader (docs/log-format.md, "Limits"): what a phone on a drone can
# report, with a wide margin; a value outside is a counted skip, never a crash later.
T_NS_MAX = 2**62  # 146 years of uptime; keeps every sum of times inside int64
ALT_MIN_M, ALT_MAX_M = -500.0, 10_000.0  # ellipsoidal heights of gnss and truth
RANGE_MAX_M = 10_000.0  # |range_m|: FTM reaches a few hundred metres
ACC_MAX_M = 10_000.0  # acc_m, vacc_m, range_std_m
RSSI_MIN_DBM, RSSI_MAX_DBM = -200.0, 100.0
COUNT_MAX = 65_535  # sats, attempted, successful
AGL_MIN_M, AGL_MAX_M = 0.1, 1_000.0  # header config.agl_m: a height above the ground
RANGE_OFFSET_MAX_M = 100.0  # header config.range_offset_m in [-max, max]
BOUNDS = {
    "t_ns": (0, T_NS_MAX),
    "alt_m": (ALT_MIN_M, ALT_MAX_M),
    "range_m": (-RANGE_MAX_M, RANGE_MAX_M),
    "acc_m": (0.0, ACC_MAX_M),
    "rssi_dbm": (RSSI_MIN_DBM, RSSI_MAX_DBM),
    "agl_m": (AGL_MIN_M, AGL_MAX_M),
    "range_offset_m": (-RANGE_OFFSET_MAX_M, RANGE_OFFSET_MAX_M),
}
MAX_LINE_BYTES = 1 << 20  # a record is ~200 bytes; a longer line is skipped unread
MAX_PREFIX_BYTES = 16 << 20  # no valid record in the first 16 MiB: not a flight log
GZIP_MAX_RATIO = 200  # a flight log compresses ~6x; a decompression bomb ~1000x
GZIP_RATIO_FLOOR_BYTES = 64 << 20  # the ratio is checked beyond this much output
MAX_BSSIDS = 4096  # responders per log (rtt and truth); a search sees a handful
MAX_UNKNOWN_TYPES = 64  # distinct unknown record types counted by name


class LogError(Exception):
    """A log that cannot be read at all (missing file, refused version, not a log)."""


class LogVersionError(LogError):
    """The header declares a major version this reader does not understand."""


class NotALogError(LogError):
    """A readable file without a single valid record: not a flight log."""


class LogWarning(UserWarning):
    """A readable log with a problem worth telling (no header, header not first)."""


@dataclass
class RejectCounts:
    """Lines skipped while reading, counted by reason.

    ``rejected`` holds bad lines (the replay report's ``rejected_lines``);
    ``unknown_types`` and ``unknown_fields`` count forward-compatible content that was
    skipped or ignored as the spec asks.
    """

    rejected: Counter = field(default_factory=Counter)
    unknown_types: Counter = field(default_factory=Counter)
    unknown_fields: int = 0
    lines: int = 0
    # suspicious but used: backward jumps of the phone clock (see iter_log_sorted)
    clock_jumps_back: int = 0

    def reject(self, reason: str) -> None:
        self.rejected[reason] += 1

    def unknown_type(self, kind: str) -> None:
        """Count a record of unknown ``type`` (at most MAX_UNKNOWN_TYPES names)."""
        if kind not in self.unknown_types and len(self.unknown_types) >= MAX_UNKNOWN_TYPES:
            kind = "(others)"
        self.unknown_types[kind] += 1

    def merge(self, other: RejectCounts) -> None:
        self.rejected.update(other.rejected)
        self.unknown_types.update(other.unknown_types)
        self.unknown_fields += other.unknown_fields
        self.lines += other.lines
        self.clock_jumps_back += other.clock_jumps_back

    @property
    def n_rejected(self) -> int:
        return sum(self.rejected.values())

    def skipped(self) -> dict[str, int]:
        """The forward-compatible content counted (a report's ``skipped`` entry)."""
        return {"unknown_types": sum(self.unknown_types.values()),
                "lines_with_unknown_fields": self.unknown_fields}


class _Reject(Exception):  # noqa: N818 - internal control flow, not an error type
    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


_KNOWN_FIELDS: dict[str, frozenset[str]] = {
    "header": frozenset({"type", "format", "version", "agent", "start_utc", "config"}),
    "gnss": frozenset(
        {"type", "t_ns", "lat", "lon", "alt_m", "acc_m", "vacc_m", "fix", "sats"}
    ),
    "rtt": frozenset(
        {
            "type",
            "t_ns",
            "bssid",
            "status",
            "range_m",
            "range_std_m",
            "rssi_dbm",
            "attempted",
            "successful",
        }
    ),
    "truth": frozenset({"type", "bssid", "lat", "lon", "alt_m", "concealment"}),
}


def _reject_constant(name: str) -> float:
    raise _Reject("non_finite")


def printable(text: str) -> str:
    """``text`` with every non-printable character (terminal escapes, other control
    and format characters) written as a Python escape: safe to print on a terminal."""
    if text.isprintable():
        return text
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


def _bounded(v: float, key: str, reason: str) -> float:
    lo, hi = BOUNDS[key]
    if not lo <= v <= hi:
        raise _Reject(reason)
    return v


def _num(obj: dict, key: str, *, required: bool) -> float | None:
    if key not in obj or obj[key] is None:
        if required:
            raise _Reject("missing_field")
        return None
    v = obj[key]
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise _Reject("bad_type")
    try:
        finite = math.isfinite(v)
    except OverflowError:  # an integer beyond the float range
        finite = False
    if not finite:
        raise _Reject("non_finite")
    return float(v)


def _int(obj: dict, key: str, *, required: bool) -> int | None:
    v = _num(obj, key, required=required)
    if v is None:
        return None
    if not float(v).is_integer():
        raise _Reject("bad_type")
    return int(obj[key]) if isinstance(obj[key], int) else int(v)


def _str(obj: dict, key: str, *, required: bool) -> str | None:
    if key not in obj or obj[key] is None:
        if required:
            raise _Reject("missing_field")
        return None
    v = obj[key]
    if not isinstance(v, str):
        raise _Reject("bad_type")
    return printable(v)


def _count(obj: dict, key: str) -> int | None:
    v = _int(obj, key, required=False)
    if v is not None and not 0 <= v <= COUNT_MAX:
        raise _Reject("bad_value")
    return v


def _alt(obj: dict) -> float:
    alt = _num(obj, "alt_m", required=True)
    assert alt is not None
    return _bounded(alt, "alt_m", "bad_altitude")


def _t_ns(obj: dict) -> int:
    t = _int(obj, "t_ns", required=True)
    assert t is not None
    if t < 0:
        raise _Reject("negative_t_ns")
    if t > T_NS_MAX:
        raise _Reject("bad_t_ns")
    return t


def _latlon(obj: dict) -> tuple[float, float]:
    lat = _num(obj, "lat", required=True)
    lon = _num(obj, "lon", required=True)
    assert lat is not None and lon is not None
    if not -90.0 <= lat <= 90.0:
        raise _Reject("bad_latitude")
    if not -180.0 <= lon <= 180.0:
        raise _Reject("bad_longitude")
    return lat, lon


def _bssid(obj: dict) -> str:
    b = _str(obj, "bssid", required=True)
    assert b is not None
    if not _BSSID_RE.fullmatch(b):  # match() let a trailing newline through
        raise _Reject("bad_bssid")
    return b.lower()


def _parse_header(obj: dict) -> tuple[LogHeader, list[str]]:
    """The header, and what in its config was out of range (dropped: defaults apply)."""
    fmt = obj.get("format", LOG_FORMAT)
    if fmt != LOG_FORMAT:
        raise LogError(f"not an {LOG_FORMAT} file (header format {fmt!r})")
    version = obj.get("version", LOG_VERSION)
    if isinstance(version, bool) or not isinstance(version, int | float | str):
        raise LogError(f"header version {version!r} is not a number")
    try:
        major = int(str(version).split(".")[0])
    except ValueError as exc:
        raise LogError(f"header version {version!r} is not a number") from exc
    if major > LOG_VERSION:
        raise LogVersionError(
            f"log format version {version} is newer than this reader (version {LOG_VERSION})"
        )
    config = obj.get("config") or {}
    if not isinstance(config, dict):
        raise _Reject("bad_type")
    agl = _num(config, "agl_m", required=False)
    off = _num(config, "range_offset_m", required=False)
    bad = []  # out-of-range settings: dropped (the defaults apply), the line counted
    if agl is not None and not AGL_MIN_M <= agl <= AGL_MAX_M:
        bad.append(f"config.agl_m {agl:g} outside [{AGL_MIN_M:g}, {AGL_MAX_M:g}] m")
        agl = None
    if off is not None and not abs(off) <= RANGE_OFFSET_MAX_M:
        bad.append(f"config.range_offset_m {off:g} outside [-{RANGE_OFFSET_MAX_M:g}, "
                   f"{RANGE_OFFSET_MAX_M:g}] m")
        off = None
    agent = obj.get("agent")
    start = obj.get("start_utc")
    extra = {k: v for k, v in config.items() if k not in ("agl_m", "range_offset_m")}
    return LogHeader(
        version=major,
        agent=printable(str(agent)) if agent is not None else "unknown",
        start_utc=printable(str(start)) if start is not None else None,
        agl_m=agl,
        range_offset_m=off,
        extra=extra,
    ), bad


def _parse_gnss(obj: dict) -> GnssFix:
    t = _t_ns(obj)
    lat, lon = _latlon(obj)
    alt = _alt(obj)
    acc = _num(obj, "acc_m", required=True)
    vacc = _num(obj, "vacc_m", required=False)
    assert acc is not None
    _bounded(acc, "acc_m", "bad_value")
    if vacc is not None:
        _bounded(vacc, "acc_m", "bad_value")
    fix = _str(obj, "fix", required=False)
    sats = _count(obj, "sats")
    return GnssFix(
        t_ns=t, lat_deg=lat, lon_deg=lon, alt_m=alt, acc_m=acc, vacc_m=vacc, fix=fix, sats=sats
    )


def _parse_rtt(obj: dict) -> RangeSample:
    t = _t_ns(obj)
    bssid = _bssid(obj)
    status = _str(obj, "status", required=True)
    assert status is not None
    ok = status == "ok"
    rng = _num(obj, "range_m", required=ok)
    rssi = _num(obj, "rssi_dbm", required=ok)
    std = _num(obj, "range_std_m", required=False)
    if rng is not None:
        _bounded(rng, "range_m", "bad_range")
    if rssi is not None:
        _bounded(rssi, "rssi_dbm", "bad_value")
    if std is not None:
        _bounded(std, "acc_m", "bad_value")
    att = _count(obj, "attempted")
    suc = _count(obj, "successful")
    return RangeSample(
        t_ns=t,
        bssid=bssid,
        status=status,
        range_m=rng,
        range_std_m=std,
        rssi_dbm=rssi,
        attempted=att,
        successful=suc,
    )


def _parse_truth(obj: dict) -> TruthRecord:
    bssid = _bssid(obj)
    lat, lon = _latlon(obj)
    alt = _alt(obj)
    conc = _str(obj, "concealment", required=False) or "open"
    return TruthRecord(bssid=bssid, lat_deg=lat, lon_deg=lon, alt_m=alt, concealment=conc)


_PARSERS = {"gnss": _parse_gnss, "rtt": _parse_rtt, "truth": _parse_truth}
# one decoder for all lines; NaN / Infinity tokens raise _Reject("non_finite")
_DECODER = json.JSONDecoder(parse_constant=_reject_constant)


def parse_line(line: bytes | str, counts: RejectCounts) -> Record | None:
    """Parse one log line; return its record, or ``None`` after counting why it was skipped."""
    if isinstance(line, bytes):
        try:
            line = line.decode("utf-8")
        except UnicodeDecodeError:
            counts.lines += 1
            counts.reject("not_utf8")
            return None
    if line.startswith(_BOM):  # a byte-order mark (Windows editors write one): not content
        line = line[1:]
    if not line.strip():
        return None
    counts.lines += 1
    try:
        obj = _DECODER.decode(line)
    except _Reject as r:
        counts.reject(r.reason)
        return None
    except (json.JSONDecodeError, RecursionError, ValueError):
        counts.reject("not_json")
        return None
    if not isinstance(obj, dict):
        counts.reject("not_object")
        return None
    kind = obj.get("type")
    if not isinstance(kind, str):
        counts.reject("missing_field" if kind is None else "bad_type")
        return None
    if kind == "header":
        try:
            rec, bad = _parse_header(obj)
        except _Reject as r:
            counts.reject(r.reason)
            return None
        if bad:
            counts.reject("bad_config")
            warnings.warn(f"header {'; '.join(bad)}: ignored (the default applies)",
                          LogWarning, stacklevel=2)
    else:
        parser = _PARSERS.get(kind)
        if parser is None:
            counts.unknown_type(printable(kind[:64]))
            return None
        try:
            rec = parser(obj)
        except _Reject as r:
            counts.reject(r.reason)
            return None
    known = _KNOWN_FIELDS[kind]
    if any(k not in known for k in obj):
        counts.unknown_fields += 1
    return rec


def display_name(path: str | os.PathLike) -> str:
    """How messages name a log: its path, or ``standard input`` for ``-``."""
    return "standard input" if str(path) == STDIN else str(path)


class _Counted:
    """A binary stream that counts the bytes read from it (the gzip budget)."""

    mode = "rb"

    def __init__(self, raw: IO[bytes], *, close: bool = True) -> None:
        self.raw = raw
        self.n = 0
        self._close = close

    def read(self, size: int = -1) -> bytes:
        data = self.raw.read(size)
        self.n += len(data)
        return data

    def readline(self, size: int = -1) -> bytes:
        line = self.raw.readline(size)
        self.n += len(line)
        return line

    def peek(self, size: int = 0) -> bytes:
        return self.raw.peek(size) if hasattr(self.raw, "peek") else b""

    def close(self) -> None:
        if self._close:
            self.raw.close()


def _open_binary(path: str | os.PathLike) -> tuple[IO[bytes], _Counted]:
    """The log's bytes (decompressed when it starts with the gzip magic) and the
    counter of the bytes read from the file. Opened once: a pipe, a fifo or ``-``
    (standard input) is read in one pass."""
    p = Path(path)
    if str(path) == STDIN:
        raw = _Counted(sys.stdin.buffer, close=False)
    else:
        try:
            raw = _Counted(open(p, "rb"))  # noqa: SIM115 - returned to the caller
        except FileNotFoundError as exc:
            raise LogError(f"{p}: no such file") from exc
        except IsADirectoryError as exc:
            raise LogError(f"{p}: is a directory") from exc
        except PermissionError as exc:
            raise LogError(f"{p}: permission denied") from exc
        except OSError as exc:
            raise LogError(f"{p}: cannot open ({exc.strerror})") from exc
    try:
        head = raw.peek(2)[:2]
    except OSError as exc:
        raw.close()
        raise LogError(f"{display_name(path)}: cannot read ({exc.strerror or exc})") from exc
    if head == _GZIP_MAGIC:
        return _GzipReader(raw), raw
    return raw, raw  # type: ignore[return-value]


class _GzipReader(gzip.GzipFile):
    """A gzip stream that owns the file under it: closing it closes both (a GzipFile
    given a ``fileobj`` leaves that file open, and it leaks as a ResourceWarning)."""

    def __init__(self, raw: _Counted) -> None:
        self._raw = raw
        super().__init__(fileobj=raw, mode="rb")  # type: ignore[arg-type]

    def close(self) -> None:
        try:
            super().close()
        finally:
            self._raw.close()


@dataclass
class LogStream:
    """An opened log: its header (once seen), reject counts, and the records read so far."""

    path: str
    counts: RejectCounts = field(default_factory=RejectCounts)
    header: LogHeader | None = None
    truth: list[TruthRecord] = field(default_factory=list)
    n_gnss: int = 0
    n_rtt: int = 0
    n_header: int = 0  # header lines read (0: none yet; a default header is assumed at EOF)
    bssids: set[str] = field(default_factory=set, repr=False)  # responders read (capped)

    @property
    def n_records(self) -> int:
        """Valid records read so far (header, gnss, rtt, truth)."""
        return self.n_header + self.n_gnss + self.n_rtt + len(self.truth)

    def _new_bssid_refused(self, bssid: str) -> bool:
        if bssid in self.bssids:
            return False
        if len(self.bssids) >= MAX_BSSIDS:
            self.counts.reject("too_many_bssids")
            return True
        self.bssids.add(bssid)
        return False


def _lines(fh: IO[bytes], raw: _Counted, st: LogStream) -> Iterator[bytes | None]:
    """The lines of ``fh``, bounded: a line longer than MAX_LINE_BYTES is skipped as
    it is read (``None``, counted ``line_too_long``); a gzip stream expanding beyond
    GZIP_MAX_RATIO and a file without a valid record in its first MAX_PREFIX_BYTES
    are refused (:class:`LogError`, :class:`NotALogError`)."""
    name = display_name(st.path)
    limit = MAX_LINE_BYTES
    total = 0
    gz = fh is not raw

    def check() -> None:
        if gz and total > GZIP_RATIO_FLOOR_BYTES and total > GZIP_MAX_RATIO * raw.n:
            raise LogError(f"{name}: refused: its gzip stream expands more than "
                           f"{GZIP_MAX_RATIO} times ({raw.n} bytes to over {total}); "
                           "a decompression bomb, not a flight log")
        if total > MAX_PREFIX_BYTES and st.n_records == 0:
            raise NotALogError(f"{name}: not a flight log (no valid record in its first "
                               f"{MAX_PREFIX_BYTES >> 20} MiB)")

    try:
        while line := fh.readline(limit + 1):
            total += len(line)
            if len(line) > limit and not line.endswith(b"\n"):
                while (more := fh.readline(limit)) and not more.endswith(b"\n"):
                    total += len(more)
                    check()
                total += len(more)
                st.counts.lines += 1
                st.counts.reject("line_too_long")
                check()
                yield None
                continue
            check()
            yield line
    except (EOFError, gzip.BadGzipFile, zlib.error) as exc:
        if not gz or st.n_records == 0:
            raise LogError(f"{name}: corrupt or truncated compressed file ({exc})") from exc
        # a recorder cut off while writing (a flat battery) leaves a truncated gzip: the
        # records before the damage are the flight's, and kept
        if "CRC" in str(exc) or "length" in str(exc):  # at its end: everything was read
            warnings.warn(f"{name}: the compressed file fails its checksum ({exc}): its "
                          f"{st.n_records} records are read, each line checked as always "
                          "(damaged ones are counted as rejected)", LogWarning, stacklevel=2)
        else:
            what = "ends early" if isinstance(exc, EOFError) else "is corrupt"
            warnings.warn(f"{name}: the compressed file {what} ({exc}): the {st.n_records} "
                          f"records of its first {total} bytes are read, nothing after",
                          LogWarning, stacklevel=2)
    except OSError as exc:
        raise LogError(f"{name}: corrupt or truncated compressed file ({exc})") from exc


def iter_log(path: str | os.PathLike, stream: LogStream | None = None) -> Iterator[TimedRecord]:
    """Yield the ``gnss`` and ``rtt`` records of a log in file order, streaming.

    Header and truth records are stored on ``stream`` (truth records are few: one per
    responder, the first one counts). Raises :class:`LogError` only for a file that
    cannot be read as a log at all.
    """
    st = stream if stream is not None else LogStream(path=str(path))
    name = display_name(path)
    fh, raw = _open_binary(path)
    first = True
    header_seen = False
    truth_of: set[str] = {t.bssid for t in st.truth}
    try:
        for line in _lines(fh, raw, st):
            if line is None:  # too long: counted by _lines
                first = False
                continue
            try:
                rec = parse_line(line, st.counts)
            except LogError as exc:  # a refused header: say which file
                raise type(exc)(f"{name}: {exc}") from None
            if rec is None:
                if line.strip():
                    first = False
                continue
            if isinstance(rec, LogHeader):
                if header_seen:
                    st.counts.reject("duplicate_header")
                else:
                    header_seen = True
                    st.header = rec
                    st.n_header = 1
                    if not first:
                        warnings.warn(
                            f"{name}: header is not the first line", LogWarning, stacklevel=2
                        )
                first = False
                continue
            first = False
            if isinstance(rec, TruthRecord):
                if rec.bssid in truth_of:
                    st.counts.reject("duplicate_truth")
                elif not st._new_bssid_refused(rec.bssid):
                    truth_of.add(rec.bssid)
                    st.truth.append(rec)
            elif isinstance(rec, GnssFix):
                st.n_gnss += 1
                yield rec
            elif not st._new_bssid_refused(rec.bssid):
                st.n_rtt += 1
                yield rec
    finally:
        fh.close()
    if st.header is None:
        warnings.warn(
            f"{name}: no header line; read as version {LOG_VERSION}", LogWarning, stacklevel=2
        )
        st.header = LogHeader()


def not_a_log(stream: LogStream) -> NotALogError | None:
    """The error for a log read without a single valid record (None if it had one)."""
    if stream.n_records:
        return None
    c = stream.counts
    what = [f"{n} {reason}" for reason, n in sorted(c.rejected.items())]
    what += [f"{n} of unknown type {kind!r}" for kind, n in sorted(c.unknown_types.items())]
    lines = f"{c.lines} line{'s' if c.lines != 1 else ''}"
    detail = f"{lines}: " + ", ".join(what) if what else "empty"
    return NotALogError(f"{display_name(stream.path)}: not a flight log (no valid record; "
                        f"{detail})")


def probe_log(path: str | os.PathLike) -> LogStream:
    """Read ``path`` up to its first ``gnss`` or ``rtt`` record (the whole file only when
    it has none) and return the stream: header, counts, :attr:`LogStream.n_records`.

    Raises :class:`NotALogError` for a file without a single valid record (an empty
    file, random bytes, a GeoJSON file...), :class:`LogError` for one that cannot be
    read. Warnings of the reader (no header, ...) are the caller's to show. (It opens
    the file: a pipe read by a probe is gone; :func:`estimator.replay.replay_logs`
    checks the same while it reads.)
    """
    st = LogStream(path=str(path))
    it = iter_log(path, st)
    try:
        next(it, None)
    finally:
        it.close()
    if (err := not_a_log(st)) is not None:
        raise err
    return st


def _key(rec: TimedRecord) -> int:
    return rec.t_ns


# Clock jumps (docs/log-format.md, "Suspicious data"). The contract lets lines come in
# any order (readers order by t_ns), so an old record is a clock jump only when the
# phone's clock, not the writer, explains it: a record more than CLOCK_JUMP_BACK_S older
# than the newest of its own stream (the GNSS fixes, or the ranges to one responder: a
# writer that puts one stream after the other is not a jump), followed in the file by
# records in time order from it (a reboot's new stretch; shuffled or reversed lines are
# not in order and are sorted as they are). The records from there on are shifted so that
# the first of them comes CLOCK_JUMP_GAP_S after the newest one before the jump (the true
# time across a jump is unknown; the gap keeps even a late record of the new stretch after
# the old one), so no range is associated across it; unless they repeat earlier records
# (a log concatenated with itself, overlapping pieces): those keep their times and the
# association drops them as duplicates. A file found out of order in this way has no
# backward jump from there on (its lines are sorted by t_ns, as the contract says).
CLOCK_JUMP_BACK_S = 10.0
CLOCK_JUMP_GAP_S = 2 * CLOCK_JUMP_BACK_S
_RECENT_RECORDS = 4096  # a jump that repeats one of these (or of the first ones) is a copy
_LOOKAHEAD_RECORDS = 50_000  # at most this many records are read ahead to judge a jump
_MIN_AHEAD_RECORDS = 32  # ... and at least this many (or the rest of the file)


def _stream_of(rec: TimedRecord) -> str:
    """The stream a record belongs to: ``"gnss"``, or the BSSID of a range."""
    return "gnss" if isinstance(rec, GnssFix) else rec.bssid


def _goes_on_in_order(first: TimedRecord, ahead: Iterator[TimedRecord],
                      read: list[TimedRecord], back_ns: int) -> bool:
    """Whether the records after ``first`` (read from ``ahead`` into ``read``) go on in
    time order from it (none more than ``back_ns`` older than the newest before it) for
    at least :data:`_MIN_AHEAD_RECORDS` records and ``back_ns`` of time, or to the end
    of the file (at most :data:`_LOOKAHEAD_RECORDS` are read): a new stretch of the
    phone's clock, not shuffled or reversed lines."""
    top = first.t_ns
    for rec in ahead:
        read.append(rec)
        if rec.t_ns < top - back_ns:
            return False
        top = max(top, rec.t_ns)
        if (len(read) >= _MIN_AHEAD_RECORDS and top >= first.t_ns + back_ns) \
                or len(read) >= _LOOKAHEAD_RECORDS:
            return True
    return True


def iter_log_sorted(
    path: str | os.PathLike,
    stream: LogStream | None = None,
    *,
    chunk_records: int = 200_000,
) -> Iterator[TimedRecord]:
    """Yield ``gnss``/``rtt`` records ordered by ``t_ns`` (stable), in bounded memory.

    Runs of at most ``chunk_records`` records are sorted in memory; a log longer than
    that is spilled to temporary files and merged, so memory stays O(chunk_records).
    The spill folder is removed however the iteration ends (closed, an exception,
    SIGTERM turned into one by the ``osa`` command). A backward clock jump is counted
    (``stream.counts.clock_jumps_back``) and the records after it re-timed (see
    :data:`CLOCK_JUMP_BACK_S`).
    """
    st = stream if stream is not None else LogStream(path=str(path))
    it = iter_log(path, st)
    runs: list[str] = []
    tmpdir: tempfile.TemporaryDirectory | None = None
    buf: list[TimedRecord] = []
    in_order = True
    last = -1
    back_ns = int(CLOCK_JUMP_BACK_S * 1e9)
    gap_ns = int(CLOCK_JUMP_GAP_S * 1e9)
    offset = 0  # added to t_ns after a backward jump
    newest = -1  # the newest (re-timed) t_ns read
    copy_until: int | None = None  # reading a repeat of earlier records, up to this time
    newest_of: dict[str, int] = {}  # the newest (re-timed) t_ns of each stream
    unordered = False  # lines found out of order: sorted, no backward jump any more
    earliest: list[TimedRecord] = []
    recent: deque[TimedRecord] = deque(maxlen=_RECENT_RECORDS)
    pending: deque[TimedRecord] = deque()  # read ahead to judge a jump, not yet taken

    def records() -> Iterator[TimedRecord]:
        while True:
            if pending:
                yield pending.popleft()
            else:
                nxt = next(it, None)
                if nxt is None:
                    return
                yield nxt

    try:
        for rec in records():
            t = rec.t_ns + offset
            key = _stream_of(rec)
            if t < newest - back_ns and copy_until is None:
                if rec in recent or rec in earliest:
                    copy_until = newest
                elif not unordered and t < newest_of.get(key, t) - back_ns:
                    ahead: list[TimedRecord] = []
                    reboot = _goes_on_in_order(rec, records(), ahead, back_ns)
                    pending.extend(ahead)
                    if reboot:
                        st.counts.clock_jumps_back += 1
                        offset = newest + gap_ns - rec.t_ns
                        t = rec.t_ns + offset
                    else:
                        unordered = True
            if copy_until is not None and t >= copy_until - back_ns:
                copy_until = None
            if len(earliest) < 256:
                earliest.append(rec)
            recent.append(rec)
            if offset:
                rec = dataclasses.replace(rec, t_ns=t)
            newest = max(newest, t)
            newest_of[key] = max(newest_of.get(key, t), t)
            if t < last:
                in_order = False
            last = t
            buf.append(rec)
            if len(buf) >= chunk_records:
                if tmpdir is None:
                    tmpdir = tempfile.TemporaryDirectory(prefix="osa-sort-")
                buf.sort(key=_key)
                run = os.path.join(tmpdir.name, f"run{len(runs)}.pkl")
                with open(run, "wb") as fo:
                    for r in buf:
                        pickle.dump(r, fo, protocol=pickle.HIGHEST_PROTOCOL)
                runs.append(run)
                buf = []
        if not runs:
            if not in_order:
                buf.sort(key=_key)
            yield from buf
            return
        buf.sort(key=_key)
        # heapq.merge is stable across its inputs in argument order: runs are in file order
        iters = [_read_run(r) for r in runs] + [iter(buf)]
        yield from heapq.merge(*iters, key=_key)
    finally:
        it.close()
        if tmpdir is not None:
            tmpdir.cleanup()


def _read_run(path: str) -> Iterator[TimedRecord]:
    with open(path, "rb") as fh:
        while True:
            try:
                yield pickle.load(fh)
            except EOFError:
                return


@dataclass
class FlightLog:
    """A whole log in memory, ordered by ``t_ns`` (for tools and tests; replay streams)."""

    path: str
    header: LogHeader
    gnss: list[GnssFix]
    rtt: list[RangeSample]
    truth: list[TruthRecord]
    counts: RejectCounts


def read_log(path: str | os.PathLike) -> FlightLog:
    """Read a whole log into memory, ordered by ``t_ns``."""
    st = LogStream(path=str(path))
    gnss: list[GnssFix] = []
    rtt: list[RangeSample] = []
    for rec in iter_log_sorted(path, st):
        (gnss if isinstance(rec, GnssFix) else rtt).append(rec)  # type: ignore[arg-type]
    assert st.header is not None
    return FlightLog(
        path=str(path), header=st.header, gnss=gnss, rtt=rtt, truth=st.truth, counts=st.counts
    )


# ----------------------------------------------------------------------------- writer


def _clean(d: dict[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in d.items() if v is not None}


def header_to_dict(h: LogHeader) -> dict[str, Any]:
    config = dict(h.extra)
    if h.agl_m is not None:
        config["agl_m"] = h.agl_m
    if h.range_offset_m is not None:
        config["range_offset_m"] = h.range_offset_m
    return _clean(
        {
            "type": "header",
            "format": h.format,
            "version": h.version,
            "agent": h.agent,
            "start_utc": h.start_utc,
            "config": config,
        }
    )


def record_to_dict(rec: Record) -> dict[str, Any]:
    """The JSON object of one record, exactly as the spec names its fields."""
    if isinstance(rec, LogHeader):
        return header_to_dict(rec)
    if isinstance(rec, GnssFix):
        return _clean(
            {
                "type": "gnss",
                "t_ns": int(rec.t_ns),
                "lat": rec.lat_deg,
                "lon": rec.lon_deg,
                "alt_m": rec.alt_m,
                "acc_m": rec.acc_m,
                "vacc_m": rec.vacc_m,
                "fix": rec.fix,
                "sats": rec.sats,
            }
        )
    if isinstance(rec, RangeSample):
        return _clean(
            {
                "type": "rtt",
                "t_ns": int(rec.t_ns),
                "bssid": rec.bssid,
                "status": rec.status,
                "range_m": rec.range_m,
                "range_std_m": rec.range_std_m,
                "rssi_dbm": rec.rssi_dbm,
                "attempted": rec.attempted,
                "successful": rec.successful,
            }
        )
    if isinstance(rec, TruthRecord):
        return {
            "type": "truth",
            "bssid": rec.bssid,
            "lat": rec.lat_deg,
            "lon": rec.lon_deg,
            "alt_m": rec.alt_m,
            "concealment": rec.concealment,
        }
    raise TypeError(f"not a log record: {type(rec).__name__}")


def dumps_record(rec: Record) -> str:
    """One log line (without newline). Non-finite numbers are refused (``ValueError``)."""
    return json.dumps(record_to_dict(rec), separators=(",", ":"), allow_nan=False)


class LogWriter:
    """Write a flight log; ``.gz`` paths are gzip-compressed reproducibly (mtime 0).

    Use as a context manager. The header is written first, once.
    """

    def __init__(self, path: str | os.PathLike, header: LogHeader) -> None:
        self.path = Path(path)
        self._raw = open(self.path, "wb")  # noqa: SIM115 - closed in close()
        if self.path.suffix == ".gz":
            self._bin: IO[bytes] = gzip.GzipFile(
                filename="", fileobj=self._raw, mode="wb", mtime=0, compresslevel=6
            )
        else:
            self._bin = self._raw
        self._fh = io.TextIOWrapper(self._bin, encoding="utf-8", newline="\n")
        self.n_lines = 0
        self.write(header)

    def write(self, rec: Record) -> None:
        self._fh.write(dumps_record(rec))
        self._fh.write("\n")
        self.n_lines += 1

    def write_all(self, recs: Iterable[Record]) -> None:
        for r in recs:
            self.write(r)

    def flush(self) -> None:
        """Push the lines written so far to the file (a live log others may read)."""
        self._fh.flush()
        self._bin.flush()
        if self._bin is not self._raw:
            self._raw.flush()

    def close(self) -> None:
        with contextlib.suppress(ValueError):
            self._fh.flush()
        self._fh.close()
        if self._bin is not self._raw:
            self._raw.close()

    def __enter__(self) -> LogWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
