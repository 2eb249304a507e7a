"""Two recorder files in, one flight log out: formats, one time axis, the overlap.

:func:`import_flight` recognises the GNSS file and the ranging file (from their
content, or as named), reads each twice with its reader (streaming; pass 1 learns the
clocks, pass 2 writes), puts every record on one time axis and writes the time span
both cover as a flight log (docs/log-format.md) with :class:`estimator.logio.LogWriter`.

The time axis (docs/import.md, "Time"):

- **phone**: both files carry the phone's ``elapsedRealtimeNanos`` and, where they
  also carry UTC, their UTC - elapsed offsets agree within 1 s (the same boot): the
  log's ``t_ns`` is that clock, exactly as recorded.
- **utc**: otherwise both are joined on UTC. ``t_ns`` is still the phone's clock where
  one file has it (the ranging file's first): the other file's UTC times are moved
  onto it with the median UTC - elapsed offset of that file. Without any phone clock,
  ``t_ns`` is UTC itself (Unix nanoseconds).

Only the span both files cover is written, plus the GNSS fix just before and the one
just after it (the association interpolates a range between the fixes around it).
Records outside are counted, not written. Memory stays bounded: the files are
streamed, and the clock offsets are medians of a bounded sample.
"""

from __future__ import annotations

import contextlib
import heapq
import importlib
import os
import statistics
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

from estimator.importers.common import (
    NS_PER_S,
    GnssOptions,
    RangesOptions,
    Source,
    SourceError,
    Stamped,
    Tally,
    utc_text,
)
from estimator.logio import LogWriter, RejectCounts
from estimator.records import GnssFix, LogHeader, RangeSample

GNSS_FORMATS = ("gnsslogger", "ulog", "dataflash", "rosbag2", "nmea")
RANGES_FORMATS = ("android-csv", "sensorreadout")
FORMATS = GNSS_FORMATS + RANGES_FORMATS
_MODULES = {f: f.replace("-", "_") for f in FORMATS}
# recognised from content in this order: binary magic first, then the text forms
_SNIFF_ORDER = ("ulog", "dataflash", "rosbag2", "nmea", "gnsslogger", "android-csv",
                "sensorreadout")
SAME_BOOT_NS = NS_PER_S  # two files' UTC - elapsed offsets within 1 s: the same boot
HEAD_BYTES = 65_536
_SAMPLE = 4096
# a file of at most this many records is kept from pass 1 for pass 2 (about 30 MB);
# a longer one is read again: memory stays bounded whatever the file
CACHE_RECORDS = 50_000


class ImportRefused(Exception):  # noqa: N818 - a refusal with a one-line reason
    """The import cannot be done (one line naming the file): unreadable or
    unrecognised file, no usable record, no common clock, no overlap in time."""


@dataclass(frozen=True, kw_only=True)
class ImportOptions:
    """The ``osa import`` options (docs/cli.md) as one object."""

    gnss_format: str | None = None
    ranges_format: str | None = None
    topic: str | None = None
    geoid_offset_m: float | None = None
    gnss_acc_m: float | None = None
    ranges_start_utc_ns: int | None = None
    agent: str = "unknown"
    agl_m: float | None = None
    range_offset_m: float | None = None


def _module(fmt: str):
    return importlib.import_module(f"estimator.importers.{_MODULES[fmt]}")


def detect_format(path: Path) -> str:
    """The recorder format of ``path`` from its content (a bag directory, magic bytes,
    the shape of the first lines); :class:`ImportRefused` when none fits."""
    if path.is_dir():
        if _module("rosbag2").is_bag_directory(path):
            return "rosbag2"
        raise ImportRefused(f"{path}: a directory that is not a ROS 2 bag")
    try:
        with open(path, "rb") as fh:
            head = fh.read(HEAD_BYTES)
    except FileNotFoundError:
        raise ImportRefused(f"{path}: no such file") from None
    except OSError as exc:
        raise ImportRefused(f"{path}: cannot read ({exc.strerror})") from None
    for fmt in _SNIFF_ORDER:
        if _module(fmt).sniff(head):
            return fmt
    raise ImportRefused(f"{path}: not a recognised recorder file (formats: "
                        f"{', '.join(FORMATS)}; name one with --gnss-format / --ranges-format)")


def open_reader(path: Path, kind: str, fmt: str | None, options: ImportOptions):
    """The reader of ``path`` as a ``kind`` (``gnss`` or ``ranges``) file."""
    allowed = GNSS_FORMATS if kind == "gnss" else RANGES_FORMATS
    if fmt is None:
        fmt = detect_format(path)
        if fmt not in allowed:
            other = "ranging" if kind == "gnss" else "GNSS"
            raise ImportRefused(f"{path}: a {fmt} file ({other} data), not "
                                f"{'GNSS' if kind == 'gnss' else 'ranging'} data")
    elif fmt not in allowed:
        raise ImportRefused(f"{fmt!r} is not a {kind} format (choose from {', '.join(allowed)})")
    mod = _module(fmt)
    opts = (GnssOptions(topic=options.topic, geoid_offset_m=options.geoid_offset_m,
                        default_acc_m=options.gnss_acc_m) if kind == "gnss"
            else RangesOptions(start_utc_ns=options.ranges_start_utc_ns))
    try:
        return mod.Reader(path, opts)
    except SourceError as exc:
        raise ImportRefused(str(exc)) from None


# ------------------------------------------------------------------- clock statistics


class _Sample:
    """A bounded, deterministic sample of a stream of integers (every k-th value, k
    doubling whenever the sample is full) with the exact min and max."""

    def __init__(self, size: int = _SAMPLE) -> None:
        self.size, self.step, self.seen = size, 1, 0
        self.values: list[int] = []
        self.lo: int | None = None
        self.hi: int | None = None

    def add(self, v: int) -> None:
        if self.seen % self.step == 0:
            self.values.append(v)
            if len(self.values) >= self.size:
                self.values = self.values[::2]
                self.step *= 2
        self.seen += 1
        self.lo = v if self.lo is None or v < self.lo else self.lo
        self.hi = v if self.hi is None or v > self.hi else self.hi

    @property
    def median(self) -> int | None:
        return int(statistics.median_low(self.values)) if self.values else None

    @property
    def half_spread(self) -> int:
        return (self.hi - self.lo) // 2 if self.values else 0


@dataclass
class _Span:
    lo: int | None = None
    hi: int | None = None
    ordered: bool = True
    _last: int | None = None

    def add(self, v: int) -> None:
        if self._last is not None and v < self._last:
            self.ordered = False
        self._last = v
        self.lo = v if self.lo is None or v < self.lo else self.lo
        self.hi = v if self.hi is None or v > self.hi else self.hi


@dataclass
class ClockStats:
    """What pass 1 learnt of one file's clocks."""

    n: int = 0
    elapsed: _Span = field(default_factory=_Span)  # records with the phone clock
    utc: _Span = field(default_factory=_Span)  # records with UTC
    utc_only: _Span = field(default_factory=_Span)  # UTC without the phone clock
    offsets: _Sample = field(default_factory=_Sample)  # UTC - elapsed, where both

    def add(self, s: Stamped) -> None:
        self.n += 1
        if s.elapsed_ns is not None:
            self.elapsed.add(s.elapsed_ns)
        if s.utc_ns is not None:
            self.utc.add(s.utc_ns)
            if s.elapsed_ns is None:
                self.utc_only.add(s.utc_ns)
            else:
                self.offsets.add(s.utc_ns - s.elapsed_ns)

    @property
    def has_elapsed(self) -> bool:
        return self.elapsed.lo is not None

    @property
    def has_utc(self) -> bool:
        return self.utc.lo is not None


@dataclass(frozen=True)
class Mapping:
    """How one file's records get their ``t_ns``: the phone clock when ``elapsed`` and
    the record has it, else UTC - ``offset_ns``."""

    elapsed: bool
    offset_ns: int | None  # None: UTC cannot be put on the axis

    def t_ns(self, s: Stamped) -> int | None:
        if self.elapsed and s.elapsed_ns is not None:
            return s.elapsed_ns
        if s.utc_ns is not None and self.offset_ns is not None:
            return s.utc_ns - self.offset_ns
        return None

    def span(self, st: ClockStats) -> tuple[int | None, int | None]:
        parts = []
        if self.elapsed and st.has_elapsed:
            parts.append((st.elapsed.lo, st.elapsed.hi))
            if st.utc_only.lo is not None and self.offset_ns is not None:
                parts.append((st.utc_only.lo - self.offset_ns, st.utc_only.hi - self.offset_ns))
        elif st.has_utc and self.offset_ns is not None:
            parts.append((st.utc.lo - self.offset_ns, st.utc.hi - self.offset_ns))
        if not parts:
            return None, None
        return min(p[0] for p in parts), max(p[1] for p in parts)

    def ordered(self, st: ClockStats) -> bool:
        if self.elapsed and st.has_elapsed:
            return st.elapsed.ordered and st.utc_only.lo is None
        return st.utc.ordered


@dataclass(frozen=True)
class TimeAxis:
    """The chosen axis: ``clock`` (``phone`` or ``utc``), the mapping of each file, the
    offset UTC - t_ns (``None`` when unknown) and its uncertainty, the uncertainty of
    the alignment of the two files, and what decided it (``reason``)."""

    clock: str
    gnss: Mapping
    ranges: Mapping
    offset_ns: int | None
    offset_uncertainty_ns: int
    alignment_uncertainty_ns: int
    reason: str
    utc_offsets_s: dict[str, float] = field(default_factory=dict)


def choose_axis(g: ClockStats, r: ClockStats, gs: Source, rs: Source) -> TimeAxis:
    """The time axis of two files (module docstring); :class:`ImportRefused` when they
    share no clock."""
    off_g, off_r = g.offsets.median, r.offsets.median
    offsets = {k: v / NS_PER_S for k, v in (("gnss", off_g), ("ranges", off_r))
               if v is not None}
    if g.has_elapsed and r.has_elapsed:
        if off_g is not None and off_r is not None:
            if abs(off_g - off_r) <= SAME_BOOT_NS:
                pooled = _Sample()
                for v in g.offsets.values + r.offsets.values:
                    pooled.add(v)
                pooled.lo = min(g.offsets.lo, r.offsets.lo)
                pooled.hi = max(g.offsets.hi, r.offsets.hi)
                off = pooled.median
                unc = pooled.half_spread + max(gs.utc_uncertainty_ns, rs.utc_uncertainty_ns)
                return TimeAxis("phone", Mapping(True, off), Mapping(True, off), off, unc, 0,
                                "both files carry the phone's elapsedRealtimeNanos of one "
                                f"boot (their UTC offsets differ by "
                                f"{abs(off_g - off_r) / 1e6:.1f} ms)", offsets)
            reason = ("joined on UTC: the phone clocks of the two files are of different "
                      f"boots, their UTC offsets differ by {abs(off_g - off_r) / NS_PER_S:.1f}"
                      " s (the phone restarted between them)")
            return _utc_axis(g, r, gs, rs, reason, offsets)
        off = off_g if off_g is not None else off_r
        unc = 0
        if off is not None:
            sample, src = (g.offsets, gs) if off_g is not None else (r.offsets, rs)
            unc = sample.half_spread + src.utc_uncertainty_ns
        for st, src in ((g, gs), (r, rs)):
            if st.offsets.median is None:
                src.warn("carries the phone's clock but no UTC beside it: taken to be of "
                         "the same boot as the other file's (not checked)")
        return TimeAxis("phone", Mapping(True, off), Mapping(True, off), off, unc, 0,
                        "both files carry the phone's elapsedRealtimeNanos (the same boot "
                        "is assumed: not both have UTC to check it)", offsets)
    reason = "joined on UTC: " + ("neither file carries the phone's clock" if not (
        g.has_elapsed or r.has_elapsed) else "only one file carries the phone's clock")
    return _utc_axis(g, r, gs, rs, reason, offsets)


def _utc_axis(g: ClockStats, r: ClockStats, gs: Source, rs: Source, reason: str,
              offsets: dict[str, float]) -> TimeAxis:
    for st, src in ((g, gs), (r, rs)):
        if not st.has_utc:
            other = rs if src is gs else gs
            raise ImportRefused(f"{src.path}: no UTC time and no phone clock shared with "
                                f"{other.path}: the two files cannot be put on one time axis")
    if r.offsets.median is not None:  # t_ns: the ranging phone's clock
        off = r.offsets.median
        unc = r.offsets.half_spread + rs.utc_uncertainty_ns
        return TimeAxis("utc", Mapping(False, off), Mapping(True, off), off, unc,
                        unc + gs.utc_uncertainty_ns,
                        reason + "; t_ns is the ranging phone's clock", offsets)
    if g.offsets.median is not None:  # t_ns: the GNSS phone's clock (GnssLogger)
        off = g.offsets.median
        unc = g.offsets.half_spread + gs.utc_uncertainty_ns
        return TimeAxis("utc", Mapping(True, off), Mapping(False, off), off, unc,
                        unc + rs.utc_uncertainty_ns,
                        reason + "; t_ns is the GNSS phone's clock", offsets)
    return TimeAxis("utc", Mapping(False, 0), Mapping(False, 0), 0, 0,
                    gs.utc_uncertainty_ns + rs.utc_uncertainty_ns,
                    reason + "; t_ns is UTC (Unix nanoseconds)", offsets)


# --------------------------------------------------------------------------- report


@dataclass
class SourceReport:
    """One file: what was read, skipped (by reason), written, left outside the overlap."""

    source: Source
    tally: Tally
    read: int = 0  # records the reader produced (after its own skips)
    written: int = 0
    outside: int = 0  # records outside the overlap, not written
    no_clock: int = 0  # records without the clock the axis needs
    ok: int = 0  # ranges: ``ok`` results written

    def to_json(self) -> dict:
        c: RejectCounts = self.tally.counts
        d = {
            "file": str(self.source.path),
            "format": self.source.format,
            "stream": self.source.label,
            "records_read": self.read,
            "written": self.written,
            "skipped": dict(sorted(c.rejected.items())),
            "outside_overlap": self.outside,
            "other_records": dict(sorted(c.unknown_types.items())),
        }
        if self.no_clock:
            d["skipped"] = dict(sorted({**d["skipped"], "no_common_clock": self.no_clock}
                                       .items()))
        if self.source.kind == "gnss":
            d["heights"] = dict(sorted(self.tally.heights.items()))
        else:
            d["ok"] = self.ok
            d["failed"] = self.written - self.ok
        return d


@dataclass
class ImportReport:
    """What ``osa import`` read and wrote (``to_json``: the ``--json`` object)."""

    output: Path
    gnss: SourceReport
    ranges: SourceReport
    axis: TimeAxis
    overlap_ns: tuple[int, int]
    start_utc: str | None
    lines: int
    warnings: list[str]

    def _utc(self, t_ns: int) -> str | None:
        return None if self.axis.offset_ns is None else utc_text(t_ns + self.axis.offset_ns)

    def to_json(self) -> dict:
        a = self.axis
        lo, hi = self.overlap_ns
        time = {
            "clock": a.clock,
            "reason": a.reason,
            "offset_s": None if a.offset_ns is None else a.offset_ns / NS_PER_S,
            "offset_uncertainty_s": a.offset_uncertainty_ns / NS_PER_S,
            "alignment_uncertainty_s": a.alignment_uncertainty_ns / NS_PER_S,
            "utc_offsets_s": a.utc_offsets_s,
            "overlap_start_utc": self._utc(lo),
            "overlap_end_utc": self._utc(hi),
            "overlap_s": (hi - lo) / NS_PER_S,
        }
        return {
            "output": str(self.output),
            "records": {"gnss": self.gnss.written, "rtt": self.ranges.written,
                        "rtt_ok": self.ranges.ok},
            "lines": self.lines,
            "start_utc": self.start_utc,
            "gnss": self.gnss.to_json(),
            "ranges": self.ranges.to_json(),
            "time": time,
            "warnings": list(self.warnings),
        }


# --------------------------------------------------------------------------- import


class _Records:
    """A reader's records for the passes after the first: kept from pass 1 when there
    are at most :data:`CACHE_RECORDS` of them, else read from the file again."""

    def __init__(self, reader) -> None:
        self.reader = reader
        self.kept: list[Stamped] | None = []

    def keep(self, s: Stamped) -> None:
        if self.kept is not None:
            if len(self.kept) < CACHE_RECORDS:
                self.kept.append(s)
            else:
                self.kept = None

    def __iter__(self) -> Iterator[Stamped]:
        if self.kept is not None:
            return iter(self.kept)
        return self.reader.records(Tally())


def _pass1(reader, step: Callable[[str], None]) -> tuple[Tally, ClockStats, _Records]:
    src: Source = reader.source
    step(f"reading {src.path.name} ({src.format})")
    tally, stats, again = Tally(), ClockStats(), _Records(reader)
    for s in reader.records(tally):
        stats.add(s)
        again.keep(s)
    if stats.n == 0:
        c = tally.counts
        why = ", ".join(f"{k}={v}" for k, v in sorted(c.rejected.items()))
        other = ", ".join(f"{k}={v}" for k, v in sorted(c.unknown_types.items())[:6])
        detail = "; ".join(x for x in (f"skipped: {why}" if why else "",
                                       f"other records: {other}" if other else "") if x)
        what = "fix" if src.kind == "gnss" else "ranging result"
        hint = ""
        if src.kind == "gnss" and c.rejected.get("no_accuracy", 0) == max(
                c.rejected.values(), default=0) > 0:
            hint = ": the file gives no accuracy; give one with --gnss-acc M"
        providers = sorted(k[4:] for k in c.unknown_types if k.startswith("Fix ")
                           and k != "Fix (no provider)")
        if src.format == "gnsslogger" and providers:
            hint = f": fixes of {', '.join(providers)} are there; name one with --topic"
        raise ImportRefused(f"{src.path}: no usable {what} ({src.label}"
                            + (f"; {detail}" if detail else "") + ")" + hint)
    return tally, stats, again


def _describe_span(lo: int | None, hi: int | None, axis: TimeAxis) -> str:
    if lo is None or hi is None:
        return "nothing"
    if axis.offset_ns is None:
        return f"{lo / NS_PER_S:.3f}-{hi / NS_PER_S:.3f} s of the phone clock"
    return f"{utc_text(lo + axis.offset_ns)} to {utc_text(hi + axis.offset_ns)}"


def _fix_before(records: _Records, mapping: Mapping, start: int, end: int,
                ordered: bool) -> tuple[int | None, int | None, int | None]:
    """(index and t_ns of the last fix before ``start``, index of the first fix after
    ``end`` when the stream is not in time order)."""
    best_i = best_t = after_i = after_t = None
    for i, s in enumerate(records):
        t = mapping.t_ns(s)
        if t is None or t < 0:
            continue
        if t < start and (best_t is None or t > best_t):
            best_i, best_t = i, t
        elif t >= start and ordered:
            break
        if not ordered and t > end and (after_t is None or t < after_t):
            after_i, after_t = i, t
    return best_i, best_t, after_i


def import_flight(gnss_path: str | os.PathLike, ranges_path: str | os.PathLike,
                  output: str | os.PathLike, options: ImportOptions = ImportOptions(),
                  *, step: Callable[[str], None] | None = None) -> ImportReport:
    """Import one flight (module docstring); raises :class:`ImportRefused` (one line
    naming the file) when it cannot. ``output`` is written through a temporary file
    beside it and replaced at the end, so a failed import leaves no partial log.
    The caller checks that ``output`` may be written (``osa import`` does)."""
    say = step or (lambda _text: None)
    gr = open_reader(Path(gnss_path), "gnss", options.gnss_format, options)
    try:
        rr = open_reader(Path(ranges_path), "ranges", options.ranges_format, options)
    except BaseException:
        gr.close()
        raise
    try:
        return _import(gr, rr, Path(output), options, say)
    finally:
        gr.close()
        rr.close()


def _import(gr, rr, out: Path, options: ImportOptions,
            say: Callable[[str], None]) -> ImportReport:
    gtally, gstats, gagain = _pass1(gr, say)
    rtally, rstats, ragain = _pass1(rr, say)
    gsrc, rsrc = gr.source, rr.source
    if options.geoid_offset_m is not None and not gtally.heights["geoid_offset"]:
        gsrc.warn("--geoid-offset not used: the file gives heights above the ellipsoid "
                  "(or its own undulation)")
    axis = choose_axis(gstats, rstats, gsrc, rsrc)
    g_lo, g_hi = axis.gnss.span(gstats)
    r_lo, r_hi = axis.ranges.span(rstats)
    if None in (g_lo, g_hi, r_lo, r_hi) or max(g_lo, r_lo) > min(g_hi, r_hi):
        raise ImportRefused(
            f"{rsrc.path} and {gsrc.path} do not overlap in time: the ranges cover "
            f"{_describe_span(r_lo, r_hi, axis)}, the GNSS {_describe_span(g_lo, g_hi, axis)}"
            f"; time axis: {axis.reason}")
    start, end = max(g_lo, r_lo), min(g_hi, r_hi)
    g_ordered = axis.gnss.ordered(gstats)
    before_i = before_t = after_i = None
    if g_lo < start or not g_ordered:
        say("finding the fixes around the overlap")
        before_i, before_t, after_i = _fix_before(gagain, axis.gnss, start, end, g_ordered)
    first_t = before_t if before_t is not None else start
    start_utc = None if axis.offset_ns is None else utc_text(first_t + axis.offset_ns)
    header = LogHeader(agent=options.agent, start_utc=start_utc, agl_m=options.agl_m,
                       range_offset_m=options.range_offset_m)
    grep = SourceReport(gsrc, gtally, read=gstats.n)
    rrep = SourceReport(rsrc, rtally, read=rstats.n)

    def gnss_out() -> Iterator[GnssFix]:
        after_done = False
        for i, s in enumerate(gagain):
            t = axis.gnss.t_ns(s)
            if t is None:
                grep.no_clock += 1
                continue
            keep = i == before_i or start <= t <= end
            if not keep and t > end:
                keep = (i == after_i) if not g_ordered else not after_done
                after_done = after_done or keep
            if keep and t >= 0:
                grep.written += 1
                yield _with_t_ns(s.record, t)
            else:
                grep.outside += 1

    def ranges_out() -> Iterator[RangeSample]:
        for s in ragain:
            t = axis.ranges.t_ns(s)
            if t is None:
                rrep.no_clock += 1
                continue
            if start <= t <= end and t >= 0:
                rrep.written += 1
                rrep.ok += s.record.status == "ok"
                yield _with_t_ns(s.record, t)
            else:
                rrep.outside += 1

    say(f"writing {out.name}")
    tmp = out.with_name(f".{out.name}.partial{out.suffix}")
    try:
        with LogWriter(tmp, header) as w:
            for rec in heapq.merge(gnss_out(), ranges_out(), key=_t_ns):
                w.write(rec)
            lines = w.n_lines
        os.replace(tmp, out)
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
    warnings = gsrc.warnings + rsrc.warnings
    return ImportReport(out, grep, rrep, axis, (start, end), start_utc, lines, warnings)


def _t_ns(rec: GnssFix | RangeSample) -> int:
    return rec.t_ns


def _with_t_ns(rec, t_ns: int):
    """A copy of a checked record with its time set (the frozen record built without
    its ``__init__``, as :func:`estimator.records.records_from_columns` builds them)."""
    new = object.__new__(type(rec))
    new.__dict__.update(rec.__dict__)
    new.__dict__["t_ns"] = t_ns
    return new

