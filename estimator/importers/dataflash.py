"""ArduPilot DataFlash logs (``.bin``, or the text ``.log`` Mission Planner makes of
one), read with pymavlink's ``DFReader``.

``GPS`` messages give the fix: ``GWk`` (GPS week) and ``GMS`` (milliseconds of the
week) for the time, ``Status`` (0-1 no fix, skipped as ``no_fix``; 2 ``2d``, 3
``3d``, 4 ``dgps``, 5 ``rtk_float``, 6 ``rtk_fixed``), ``NSats``, ``HDop``, ``Lat``,
``Lng`` and ``Alt`` (above mean sea level). The ``GPA`` message written with it (same
instance ``I`` and ``TimeUS``) gives ``HAcc`` and ``VAcc`` (``acc_m``, ``vacc_m``) and
the height above the ellipsoid: ``Und`` (ArduPilot 4.6 and the releases before it) is
``AP_GPS::get_undulation``, the height of mean sea level above the ellipsoid, -N (uBlox
``hMSL - height``), so alt_m = Alt - Und; ``AEl`` (later firmware) is the ellipsoidal
height itself (cm; INT32_MIN unknown). A zero ``Und`` is a receiver without a geoid
model. Without either, ``--geoid-offset`` gives N (else a warning); without ``HAcc``,
acc_m = 1.5 m x HDop (as for NMEA). Instance 0 is read (``--topic GPS[1]`` picks the
second receiver; in logs before ArduPilot 4.1, without the ``I`` column, its messages
are ``GPS2`` and ``GPA2``, also named by ``--topic GPS2``). Fixes without GPS time
(``GWk`` 0) are skipped as ``no_utc``.

GPS time runs ahead of UTC by the leap seconds since 1980 (18 s since 2017-01-01):
:data:`LEAP_SECONDS` is the table (IERS Bulletin C; no leap second has been added
since 2017).
"""

from __future__ import annotations

import contextlib
import functools
import io
import math
import os
import re
import struct
import sys
from collections import Counter
from collections.abc import Callable, Iterator
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from estimator.importers.common import (
    NS_PER_S,
    GnssOptions,
    Skip,
    Source,
    SourceError,
    Stamped,
    Tally,
    brief,
    ellipsoidal_m,
    float32_decimal,
    make_fix,
    open_file,
)

FORMAT = "dataflash"
KIND = "gnss"
HEAD = b"\xa3\x95\x80"  # message header bytes, then the FMT message's type (128)
FMT_TYPE = 0x80
CHUNK_MIN, CHUNK_MAX = 1 << 16, 1 << 23  # re-indexing past a corrupt stretch (bytes)
GPS_EPOCH_S = 315_964_800  # 1980-01-06T00:00:00Z in Unix seconds
HDOP_TO_ACC_M = 1.5
AEL_UNKNOWN_M = -(2**31) / 100  # GPA.AEl's INT32_MIN (cm): no ellipsoidal height
STATUS = {2: "2d", 3: "3d", 4: "dgps", 5: "rtk_float", 6: "rtk_fixed"}
# (UTC date from which it holds, GPS - UTC in seconds)
LEAP_SECONDS: tuple[tuple[str, int], ...] = (
    ("2017-01-01", 18), ("2015-07-01", 17), ("2012-07-01", 16), ("2009-01-01", 15),
    ("2006-01-01", 14), ("1999-01-01", 13), ("1997-07-01", 12), ("1996-01-01", 11),
    ("1994-07-01", 10), ("1993-07-01", 9), ("1992-07-01", 8), ("1991-01-01", 7),
    ("1990-01-01", 6), ("1988-01-01", 5), ("1985-07-01", 4), ("1983-07-01", 3),
    ("1982-07-01", 2), ("1981-07-01", 1), ("1980-01-06", 0),
)
_LEAPS_NS = tuple(
    (int(datetime.fromisoformat(d).replace(tzinfo=UTC).timestamp()) * NS_PER_S, s)
    for d, s in LEAP_SECONDS
)


def sniff(head: bytes) -> bool:
    return head.startswith(HEAD) or _is_text(head)


def _is_text(head: bytes) -> bool:
    """A DataFlash log as text (Mission Planner's ``.log``, pymavlink's text form):
    its first line the ``FMT`` message of ``FMT``."""
    return head.removeprefix(b"\xef\xbb\xbf").startswith((b"FMT, 128,", b"FMT,128,"))


def gps_to_utc_ns(week: int, ms: int) -> int:
    """UTC (Unix nanoseconds) of GPS week ``week`` + ``ms`` milliseconds."""
    gps_ns = (GPS_EPOCH_S + week * 604_800) * NS_PER_S + ms * 1_000_000
    for start_ns, leap in _LEAPS_NS:
        if gps_ns - leap * NS_PER_S >= start_ns:
            return gps_ns - leap * NS_PER_S
    return gps_ns


@contextlib.contextmanager
def quiet_output() -> Iterator[None]:
    """Silence what pymavlink prints about bad bytes (from Python and from its compiled
    indexer) so that it cannot mix with osa's own output; the counts say it instead."""
    sys.stdout.flush()
    sys.stderr.flush()
    saved = [os.dup(1), os.dup(2)]
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 1)
            os.dup2(null.fileno(), 2)
            with contextlib.redirect_stdout(io.StringIO()) as a, \
                    contextlib.redirect_stderr(io.StringIO()) as b:
                yield
                a.truncate(0)
                b.truncate(0)
    finally:
        with contextlib.suppress(Exception):
            sys.stdout.flush()
            sys.stderr.flush()
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
        os.close(saved[0])
        os.close(saved[1])


def _topic(text: str | None) -> int:
    if text is None:
        return 0
    t = text.strip().upper()
    if t == "GPS":
        return 0
    if t.startswith("GPS[") and t.endswith("]") and t[4:-1].isdigit():
        return int(t[4:-1])
    if t[3:].isdigit() and t.startswith("GPS") and int(t[3:]) >= 2:  # GPS2: older logs
        return int(t[3:]) - 1
    raise SourceError(f"--topic {text!r}: a DataFlash log takes GPS or GPS[N] (instance N; "
                      "GPS2 is GPS[1])")


def _names(df, instance: int) -> tuple[str, str]:
    """The message names of receiver ``instance``: ``GPS``/``GPA`` with their ``I``
    column (ArduPilot 4.1 on), or, in older logs without it, ``GPS``/``GPA`` for the
    first receiver and ``GPS2``/``GPA2`` for the second."""
    if instance == 0 or "I" in _format(df, "GPS").columns:
        return "GPS", "GPA"
    return f"GPS{instance + 1}", f"GPA{instance + 1}"


def _format(df, name: str):
    """The ``DFFormat`` of message ``name`` (binary readers key formats by type number,
    the text reader by name), or ``None``."""
    if isinstance(df, _text_reader()):
        return df.formats.get(name)
    t = df.name_to_id.get(name)
    return None if t is None else df.formats.get(t)


def _text_reader() -> type:
    from pymavlink import DFReader

    return DFReader.DFReader_text


_NUMPY = {"b": "i1", "B": "u1", "h": "<i2", "H": "<u2", "i": "<i4", "I": "<u4", "q": "<i8",
          "Q": "<u8", "f": "<f4", "d": "<f8", "e": "<f2", "s": "S", "?": "?"}


def message_dtype(msg_struct: str) -> np.dtype:
    """The packed numpy record of a DFReader format's ``struct`` layout."""
    fields = []
    for k, (count, code) in enumerate(re.findall(r"(\d*)([a-zA-Z?])", msg_struct.lstrip("<"))):
        np_code = _NUMPY[code] + (count if code == "s" else "")
        shape = (int(count),) if count and code != "s" else ()
        fields.append((f"f{k}", np.dtype(np_code), shape) if shape else (f"f{k}", np_code))
    return np.dtype(fields)


def _exact_values(fmt) -> dict[str, Callable[[float], float]]:
    """For each column of a format, what makes its value the number the field holds:
    a fixed-point field (``L`` 1e-7 degrees, ``e``/``c``/``C`` hundredths) rounded to
    its step, a single-precision one (``f``) as its shortest decimal (0.9, not
    0.8999999761581421), others as they are."""
    out: dict[str, Callable[[float], float]] = {}
    for col, code, mult in zip(fmt.columns, fmt.format, fmt.msg_mults, strict=False):
        if mult is not None and 0.0 < mult < 1.0:
            out[col] = functools.partial(_rounded, digits=round(-math.log10(mult)))
        elif code == "f":
            out[col] = float32_decimal
        else:
            out[col] = float
    return out


def _rounded(value: float, digits: int) -> float:
    return round(float(value), digits)


def _fast_index() -> bool:
    """Whether pymavlink's compiled indexer is there (it is in its wheels)."""
    from pymavlink import dfindexer

    return bool(dfindexer.available)


def _fmt_fields(df) -> tuple[int, int, int]:
    """(length, offset of ``Type``, offset of ``Length``) of the log's ``FMT`` message."""
    from pymavlink.DFReader import FORMAT_TO_STRUCT

    fmt = df.formats[FMT_TYPE]
    at, where = 3, {}
    for col, code in zip(fmt.columns, fmt.format, strict=True):
        where[col] = at
        at += struct.calcsize("<" + FORMAT_TO_STRUCT[code][0])
    return fmt.len, where["Type"], where["Length"]


def _new_format(df, body: bytes, known: dict):
    """The ``DFFormat`` an ``FMT`` message's body defines, if it is sound: its length is
    its fields' (with the 3 header bytes), one column per field, and its type is new or
    defined alike in ``known`` (type: (name, format, length) of the log's FMTs so far);
    else ``None``."""
    from pymavlink import DFReader

    try:
        t, length, name, fmt, columns = struct.unpack(df.formats[FMT_TYPE].msg_struct, body)
        name, fmt, columns = (DFReader.null_term(x) for x in (name, fmt, columns))
        size = struct.calcsize("<" + "".join(DFReader.FORMAT_TO_STRUCT[c][0] for c in fmt))
        if size + 3 != length or len(columns.split(",")) != len(fmt):
            return None
        if known.get(t, (name, fmt, length)) != (name, fmt, length):
            return None
        return DFReader.DFFormat(t, name, length, fmt, columns)
    except Exception:  # bad bytes: pymavlink raises bare Exceptions
        return None


def _index_past_corruption(df, offset: int) -> int:
    """Index the messages from ``offset`` on into ``df.offsets``, past every corrupt
    stretch; the bytes they cover.

    pymavlink's compiled indexer stops for good at a message header of an undefined
    type (bad bytes that look like a header). It learns message lengths from the
    ``FMT`` messages it meets, so it is run again on the rest of the file, a chunk at
    a time, each chunk led by the log's ``FMT`` messages: from one byte past the bad
    header, from the last whole message at a chunk's end. The chunks grow from 64 KiB
    to 8 MiB while the index runs through them (memory stays bounded; a file with many
    corrupt stretches is not copied many times over)."""
    from pymavlink import DFReader, dfindexer

    fmt_len, type_at, length_at = _fmt_fields(df)
    data, n = df.data_map, df.data_len
    prefix = b"".join(data[o:o + fmt_len] for o in df.offsets[FMT_TYPE] if o + fmt_len <= n)
    # the types the indexed FMT messages define (pymavlink's first look at the
    # messages may have put FMTs from past its index's end in df.formats)
    known = {}
    for o in range(0, len(prefix), fmt_len):
        t, length, name, fmt, _ = struct.unpack(df.formats[FMT_TYPE].msg_struct,
                                                prefix[o + 3:o + fmt_len])
        known[t] = (DFReader.null_term(name), DFReader.null_term(fmt), length)
    covered = 0
    pos, size = offset, CHUNK_MIN
    while pos + 3 <= n:
        chunk = prefix + data[pos:pos + size]
        base = len(prefix)
        offs = dfindexer.build_offsets(memoryview(chunk), FMT_TYPE, fmt_len, type_at,
                                       length_at, HEAD[0], HEAD[1])
        # FMT messages met here define types for the rest of the file; a bad one (a
        # layout that does not add up, or another for a type already defined: ArduPilot
        # defines each type once a log) is bad bytes: the chunk's index ends there
        limit = len(chunk)
        for o in offs[FMT_TYPE]:
            if o < base or o + fmt_len > len(chunk):
                continue
            f = _new_format(df, chunk[o + 3:o + fmt_len], known)
            if f is None:
                limit = o
                break
            if f.type not in known:
                known[f.type] = (f.name, f.format, f.len)
                df.formats[f.type] = f
                df.name_to_id[f.name] = f.type
                df.id_to_name[f.type] = f.name
                prefix += chunk[o:o + fmt_len]
        end = base  # the end of the last whole message of the chunk
        for t, found in enumerate(offs):
            if not found or t not in df.formats:
                continue
            length = df.formats[t].len
            whole = [o for o in found if o >= base and o + length <= limit]
            df.offsets[t].extend(o - base + pos for o in whole)
            covered += len(whole) * length
            if whole:
                end = max(end, whole[-1] + length)
        # where the indexer stopped: the first header after the last whole message; a
        # bad one (of no type, a bad FMT, one the indexer refused) or a message the
        # chunk's end cut
        h = limit if limit < len(chunk) else chunk.find(HEAD[:2], end)
        at_eof = pos + size >= n
        t = chunk[h + 2] if 0 <= h < len(chunk) - 2 else None
        if t is not None and (h == limit or t not in df.formats
                              or h + df.formats[t].len <= len(chunk)):
            nxt, size = pos + (h - base) + 1, CHUNK_MIN  # a bad header: one byte past it
        elif at_eof:
            break  # the rest is a message cut off by the end of the file, or junk
        else:  # a message cut by the chunk's end (or junk up to it): the next chunk
            nxt = pos + ((h if h >= 0 else len(chunk) - 2) - base)
            size = min(2 * size, CHUNK_MAX)
        if nxt <= pos:
            break
        pos = nxt
    df.counts = [len(o) for o in df.offsets]
    return covered


class Reader:
    """The fixes of one DataFlash log (see the module docstring).

    pymavlink's ``DFReader_binary`` indexes the file (every message's offset by type)
    and describes each type from the log's own ``FMT`` messages (layout, columns,
    multipliers); the ``GPS`` and ``GPA`` messages are then unpacked in bulk with that
    description (the same values ``DFReader``'s messages give, tested), once: the
    reader keeps the GNSS columns, as the ULog reader keeps its topic. pymavlink's
    index stops at the first message header of an undefined type (a corrupt stretch);
    the rest of the file is then indexed past it with the same compiled indexer
    (:func:`_index_past_corruption`), or, without it, read message by message with
    ``DFReader.recv_msg``, which skips bad bytes. Bytes no message covers are counted
    (``corrupt_bytes``).
    """

    def __init__(self, path: Path, options: GnssOptions) -> None:
        from pymavlink import DFReader

        self.options = options
        self.instance = _topic(options.topic)
        self.source = Source(path=path, format=FORMAT, kind=KIND,
                             label=f"GPS[{self.instance}] with GPA",
                             utc_uncertainty_ns=500_000)  # GMS: 1 ms steps
        with open_file(path) as fh:
            text = _is_text(fh.read(16))
        try:
            with quiet_output():  # pymavlink prints about bad bytes, from C too
                df = (DFReader.DFReader_text if text else DFReader.DFReader_binary)(
                    str(path), zero_time_base=True)
        except Exception as exc:  # pymavlink raises bare Exceptions on foreign data
            raise SourceError(f"{path}: not a readable DataFlash log ({brief(exc)})") from None
        try:
            if text:
                self._load_text(df, path)
                self.source.label += " (text log)"
            else:
                self._load(df, path)
        except SourceError:
            raise
        except Exception as exc:  # bad bytes pymavlink let through
            raise SourceError(f"{path}: a DataFlash log this reader cannot read "
                              f"({brief(exc)})") from None
        finally:
            with contextlib.suppress(BufferError):  # arrays on its map still referenced
                df.close()

    def _check(self, df, path: Path) -> tuple[str, str]:
        """The GPS and GPA message names of the receiver read, after checking the log
        has them with the columns needed."""
        gps_fmt = _format(df, "GPS")
        if gps_fmt is None:
            raise SourceError(f"{path}: no GPS messages (no FMT for GPS)")
        missing = [c for c in ("GMS", "GWk", "Lat", "Lng", "Alt", "Status")
                   if c not in gps_fmt.columns]
        if missing:
            raise SourceError(f"{path}: GPS messages without {', '.join(missing)} "
                              "(a log older than ArduPilot 3.3?)")
        gps_name, gpa_name = _names(df, self.instance)
        if _format(df, gps_name) is None:
            raise SourceError(f"{path}: no {gps_name} messages (the second receiver of a log "
                              "without instance numbers)")
        if gps_name != "GPS":
            self.source.label = f"{gps_name} with {gpa_name}"
        return gps_name, gpa_name

    def _older(self, df, gps_name: str) -> list[str]:
        """The other receivers' message names in a log without instance numbers."""
        if "I" in _format(df, "GPS").columns:
            return []
        names = df.formats if isinstance(df, _text_reader()) else df.name_to_id
        return [n for n in names if (n == "GPS" or (n[:3] == "GPS" and n[3:].isdigit()))
                and n != gps_name]

    def _load_text(self, df, path: Path) -> None:
        """The GPS and GPA messages of a text log (values as written: already scaled)."""
        gps_name, gpa_name = self._check(df, path)
        rows: dict[str, list] = {gps_name: [], gpa_name: []}
        self.text_skips: Counter = Counter()
        with quiet_output():
            while True:
                try:  # (pymavlink's index has moved past the line whatever happens)
                    m = df.recv_match(type=[gps_name, gpa_name])
                except UnicodeDecodeError:
                    self.text_skips["not_utf8"] += 1
                    continue
                except ValueError:  # a line pymavlink cannot split into its fields
                    self.text_skips["bad_type"] += 1
                    continue
                if m is None:
                    break
                try:
                    values = [getattr(m, c) for c in m.fmt.columns]
                except ValueError:  # text where a number belongs
                    self.text_skips["bad_type"] += 1
                    continue
                rows[m.get_type()].append(values)
        cols = {}
        for name, found in rows.items():
            fmt = _format(df, name)
            cols[name] = {c: np.array([r[k] for r in found]) for k, c in
                          enumerate(fmt.columns)} if found and fmt is not None else {}
        if not cols[gps_name]:
            cols[gps_name] = {c: np.zeros(0) for c in _format(df, gps_name).columns}
        fmts = {n: _format(df, n) for n in (gps_name, gpa_name) if _format(df, n)}
        older = {n: df.counts.get(n, 0) for n in self._older(df, gps_name)}
        self.truncated = self.corrupt_bytes = 0
        self._select(cols[gps_name], cols[gpa_name], fmts, gps_name, gpa_name, older)

    def _load(self, df, path: Path) -> None:
        types = [t for t in df.formats if isinstance(t, int) and t < len(df.offsets)]
        covered = sum(len(df.offsets[t]) * df.formats[t].len for t in types)
        end = max((df.offsets[t][-1] + df.formats[t].len for t in types if df.offsets[t]),
                  default=0)
        if end < df.data_len - 3 and _fast_index():
            # the index stopped at a corrupt stretch: index the rest past it
            with quiet_output():  # the indexer prints about the bad bytes
                covered += _index_past_corruption(df, end)
            end = df.data_len
        # (after the re-indexing: ArduPilot writes the GPS FMT when the receiver is first
        # detected, which may be after a corrupt stretch)
        gps_name, gpa_name = self._check(df, path)
        self.truncated = 0
        gps = self._columns(df, gps_name)
        gpa = self._columns(df, gpa_name) if gpa_name in df.name_to_id else {}
        fmts = {n: df.formats[df.name_to_id[n]] for n in (gps_name, gpa_name)
                if n in df.name_to_id}
        if end < df.data_len - 3:  # the index stopped: read on message by message
            more, n_bytes, more_fmts = self._read_on(df, end, (gps_name, gpa_name))
            fmts.update(more_fmts)
            covered += n_bytes
            for name, cols in ((gps_name, gps), (gpa_name, gpa)):
                rows = more[name]
                if rows:  # (its FMT may be after the index's end: not in name_to_id)
                    for c in rows[0]:
                        extra = np.array([r[c] for r in rows]).astype(
                            cols[c].dtype if c in cols else float)
                        cols[c] = np.concatenate([cols[c], extra]) if c in cols else extra
        self.corrupt_bytes = max(0, df.data_len - covered)
        older = {n: len(df.offsets[df.name_to_id[n]]) for n in self._older(df, gps_name)}
        self._select(gps, gpa, fmts, gps_name, gpa_name, older)

    def _select(self, gps: dict, gpa: dict, fmts: dict, gps_name: str, gpa_name: str,
                older: dict[str, int]) -> None:
        """Keep the receiver's GPS columns and pair each fix with its GPA; count the
        other receivers' (``older``: their message counts in a log without ``I``)."""
        n_all = len(gps["GMS"])
        inst = gps.get("I", np.full(n_all, self.instance, dtype=np.int64))
        self.other_instances = {int(i): int(n) for i, n in zip(
            *np.unique(inst[inst != self.instance], return_counts=True), strict=True)}
        for name, count in older.items():  # the other receivers' messages of an older log
            k = 0 if name == "GPS" else int(name[3:]) - 1
            self.other_instances[k] = count
        mine = inst == self.instance
        self.gps = {k: v[mine] for k, v in gps.items()}
        self.n = int(mine.sum())
        # the GPA written with each GPS: same instance and boot time (TimeUS; logs
        # before ArduPilot 3.3 have no TimeUS, and no GPA)
        self.gpa_index = np.full(self.n, -1, dtype=np.int64)
        key = "TimeUS"
        if gpa and key in gpa and key in self.gps:
            gi = gpa.get("I", np.full(len(gpa[key]), self.instance, dtype=np.int64))
            sel = np.flatnonzero(gi == self.instance)
            t = gpa[key][sel]
            order = np.argsort(t, kind="stable")
            ts = t[order]
            pos = np.searchsorted(ts, self.gps[key])
            ok = pos < len(ts)
            hit = np.zeros(self.n, dtype=bool)
            hit[ok] = ts[pos[ok]] == self.gps[key][ok]
            self.gpa_index[hit] = sel[order[pos[hit]]]
        self.gpa = gpa
        self.exact_gps = _exact_values(fmts[gps_name])
        self.exact_gpa = _exact_values(fmts[gpa_name]) if gpa_name in fmts else {}

    @staticmethod
    def _read_on(df, offset: int, names: tuple[str, str]) -> tuple[dict[str, list[dict]],
                                                                    int, dict]:
        """The ``names`` (GPS and GPA) messages from ``offset`` on, parsed one by one by
        DFReader (which skips bad bytes), the bytes the messages parsed there cover and
        the formats of those names."""
        df.offset, df.remaining = offset, df.data_len - offset
        out: dict[str, list[dict]] = {n: [] for n in names}
        fmts = {}
        n_bytes = 0
        with quiet_output():
            while (m := df.recv_msg()) is not None:
                n_bytes += m.fmt.len
                kind = m.get_type()
                if kind in out:
                    out[kind].append({c: getattr(m, c) for c in m.fmt.columns})
                    fmts[kind] = m.fmt
        return out, n_bytes, fmts

    def _columns(self, df, name: str) -> dict[str, np.ndarray]:
        """Every column of the indexed ``name`` messages, scaled as DFReader scales them."""
        type_id = df.name_to_id[name]
        fmt = df.formats[type_id]
        offs = np.asarray(df.offsets[type_id], dtype=np.int64)
        whole = offs + fmt.len <= df.data_len
        self.truncated += int((~whole).sum())
        offs = offs[whole]
        buf = np.frombuffer(df.data_map, dtype=np.uint8)
        body = buf[offs[:, None] + 3 + np.arange(fmt.len - 3)]
        rec = body.view(message_dtype(fmt.msg_struct)).reshape(len(offs))
        out = {}
        for k, col in enumerate(fmt.columns):
            v = rec[f"f{k}"]
            mult = fmt.msg_mults[k]
            if v.dtype.kind in "iuf":
                v = v.astype(np.float64 if (mult is not None or v.dtype.kind == "f")
                             else np.int64)
                if mult is not None:  # as DFReader: divide by 1/mult for mult < 1
                    v = v / (1.0 / mult) if 0.0 < mult < 1.0 else v * mult
            out[col] = v
        return out

    def records(self, tally: Tally) -> Iterator[Stamped]:
        for reason, n in getattr(self, "text_skips", {}).items():
            tally.counts.lines += n
            tally.counts.rejected[reason] += n
        if self.corrupt_bytes:
            tally.counts.rejected["corrupt_bytes"] += self.corrupt_bytes
        if self.truncated:
            tally.skip("truncated")
        for inst, n in self.other_instances.items():
            tally.counts.unknown_types[f"GPS[{inst}]"] += n
        g, a = self.gps, self.gpa
        has = {c: c in a for c in ("HAcc", "VAcc", "Und", "AEl")}
        for i in range(self.n):
            tally.counts.lines += 1
            j = int(self.gpa_index[i])
            try:
                yield self._fix(g, i, a if j >= 0 else None, j, has, tally)
            except Skip as s:
                tally.skip(s.reason)

    def _fix(self, g: dict, i: int, a: dict | None, j: int, has: dict,
             tally: Tally) -> Stamped:
        status = int(g["Status"][i])
        if status not in STATUS:
            raise Skip("no_fix")
        week, ms = int(g["GWk"][i]), int(g["GMS"][i])
        if week <= 0:
            raise Skip("no_utc")
        eg, ea = self.exact_gps, self.exact_gpa

        def gpa(col: str) -> float | None:
            return ea[col](a[col][j]) if a is not None and has[col] else None

        hacc, vacc = gpa("HAcc"), gpa("VAcc")
        # Und is ArduPilot's undulation: mean sea level above the ellipsoid, -N
        und = gpa("Und")
        if und == 0.0:  # a receiver without an undulation model logs 0
            und = None
        ael = gpa("AEl")
        if ael is not None and ael <= AEL_UNKNOWN_M:
            ael = None
        if not hacc and "HDop" in g:
            hdop = eg["HDop"](g["HDop"][i])
            if hdop:
                hacc = round(HDOP_TO_ACC_M * hdop, 3)  # HDop: 0.01 steps
                self.source.warn("fixes without GPA.HAcc: acc_m = 1.5 m x HDop")
        if ael is not None:
            alt, how = ael, "ellipsoid"
        else:
            alt, how = ellipsoidal_m(self.source, eg["Alt"](g["Alt"][i]),
                                     None if und is None else -und,
                                     self.options.geoid_offset_m)
            alt = round(alt, 6)  # cm + a float32's shortest decimal, without binary noise
        fix = make_fix(
            lat_deg=eg["Lat"](g["Lat"][i]), lon_deg=eg["Lng"](g["Lng"][i]),
            alt_m=alt, acc_m=hacc, vacc_m=vacc, fix=STATUS[status],
            sats=int(g["NSats"][i]) if "NSats" in g else None,
            default_acc_m=self.options.default_acc_m,
        )
        tally.heights[how] += 1
        return Stamped(fix, utc_ns=gps_to_utc_ns(week, ms))

    def close(self) -> None:
        self.gps, self.gpa = {}, {}
