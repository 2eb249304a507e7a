"""ROS 2 bags, read with rosbags: ``sensor_msgs/msg/NavSatFix`` messages.

A bag is its directory (with ``metadata.yaml``), or one storage file, ``.db3``
(sqlite3) or ``.mcap``, with or without the ``metadata.yaml`` beside it (a directory
without it is read through the storage files it holds; so is one whose metadata.yaml
no longer matches its storage for the topic, as after an edit of its QoS). Messages
are deserialised with the definitions the bag carries, else with the ROS 2 Humble type
store. The topic is the bag's only NavSatFix topic, or ``--topic``.

Used: ``header.stamp`` (UTC), ``latitude``, ``longitude``, ``altitude`` (above the
WGS84 ellipsoid, as the message defines it), ``status.status`` (-1 no fix and -2
unknown are skipped as ``no_fix``; 1 SBAS and 2 GBAS are ``dgps``; 0 leaves the fix
type unknown) and ``position_covariance``: with a covariance type other than 0
(unknown), acc_m is the square root of the larger horizontal variance (east or north)
and vacc_m that of the vertical one (a NaN variance: unknown). A message with a zero
stamp is skipped (``no_utc``), one that cannot be deserialised counted as
``corrupt_message``. When the storage itself fails midway (a damaged MCAP record or
SQLite page), the fixes read before are kept and the rest of the topic's messages
counted as ``corrupt_data``. A ``.db3`` with a write-ahead log beside it
(``bag.db3-wal``: a recording in SQLite's WAL mode that was not closed) is read from a
temporary copy with the log merged in; an ``.mcap`` cut off without its footer, from a
copy of its whole records closed with one.
"""

from __future__ import annotations

import contextlib
import math
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

from estimator.importers.common import (
    NS_PER_S,
    GnssOptions,
    Skip,
    Source,
    SourceError,
    Stamped,
    Tally,
    brief,
    make_fix,
)

FORMAT = "rosbag2"
KIND = "gnss"
NAVSATFIX = "sensor_msgs/msg/NavSatFix"
SQLITE_MAGIC = b"SQLite format 3\x00"
MCAP_MAGIC = b"\x89MCAP"
STORAGE_SUFFIXES = (".db3", ".mcap")
STATUS = {0: None, 1: "dgps", 2: "dgps"}


def sniff(head: bytes) -> bool:
    return head.startswith((SQLITE_MAGIC, MCAP_MAGIC))


def is_bag_directory(path: Path) -> bool:
    return path.is_dir() and ((path / "metadata.yaml").is_file() or any(
        p.suffix in STORAGE_SUFFIXES for p in path.iterdir()))


def _storage_files(path: Path) -> list[Path]:
    """The storage files of a bag directory, read without its metadata.yaml."""
    files = sorted(p for p in path.iterdir() if p.suffix in STORAGE_SUFFIXES)
    if not files:
        raise SourceError(f"{path}: a directory with no metadata.yaml, .db3 or .mcap")
    return files


def _storage_paths(path: Path) -> list[Path]:
    """What rosbags opens: the bag directory when it has its metadata.yaml, else the
    storage files themselves."""
    if path.is_dir():
        if (path / "metadata.yaml").is_file():
            return [path]
        return _storage_files(path)
    if path.suffix not in STORAGE_SUFFIXES:
        raise SourceError(f"{path}: a bag file must be named .db3 (sqlite3) or .mcap")
    return [path]


def _write_ahead_log(db: Path) -> Path | None:
    """The SQLite write-ahead log beside a ``.db3``, when it holds anything."""
    wal = db.with_name(db.name + "-wal")
    return wal if db.suffix == ".db3" and wal.is_file() and wal.stat().st_size > 0 else None


def _merged_copy(db: Path, wal: Path, folder: Path) -> Path:
    """A copy of ``db`` in ``folder`` with the messages of its write-ahead log merged in
    (SQLite checkpoints the copied log into the copy); the input files are not touched."""
    import sqlite3

    out = folder / db.name
    shutil.copyfile(db, out)
    shutil.copyfile(wal, folder / wal.name)
    with contextlib.closing(sqlite3.connect(out)) as con:
        con.execute("PRAGMA wal_checkpoint(TRUNCATE)")
        con.execute("PRAGMA journal_mode=DELETE")
    return out


MCAP_END = b"\x89MCAP0\r\n"  # the magic that starts and ends an MCAP file
MCAP_FOOTER_BYTES = 37  # Footer record (opcode, length, 20 bytes) and the magic


def _mcap_cut_end(path: Path) -> int | None:
    """The end of the last whole record of an MCAP file that stops before its footer (a
    recording cut off), or ``None`` when the file ends with its magic."""
    with open(path, "rb") as fh:
        size = fh.seek(0, 2)
        if size >= 8 + MCAP_FOOTER_BYTES:
            fh.seek(size - 8)
            if fh.read(8) == MCAP_END:
                return None
        off = 8  # after the leading magic: records of opcode, u64 length, content
        while off + 9 <= size:
            fh.seek(off + 1)
            end = off + 9 + int.from_bytes(fh.read(8), "little")
            if end > size:
                break
            off = end
        return off


def _closed_copy(mcap: Path, end: int, folder: Path) -> Path:
    """A copy of a cut-off MCAP file in ``folder``: its whole records (``end`` bytes),
    then a DataEnd record and a footer without a summary (readers then scan it)."""
    out = folder / mcap.name
    with open(mcap, "rb") as src, open(out, "wb") as dst:
        left = end
        while left > 0:
            block = src.read(min(left, 1 << 20))
            if not block:
                break
            dst.write(block)
            left -= len(block)
        dst.write(b"\x0f" + (4).to_bytes(8, "little") + bytes(4))  # DataEnd, crc 0
        dst.write(b"\x02" + (20).to_bytes(8, "little") + bytes(20))  # Footer: no summary
        dst.write(MCAP_END)
    return out


def _unpaired(reader, topic: str) -> bool:
    """Whether the bag's metadata counts messages on ``topic`` that rosbags yields none
    of: it pairs the metadata's connections with the storage's by topic, type and QoS,
    and an edited metadata.yaml pairs none."""
    conns = [c for c in reader.connections if c.topic == topic]
    if not sum(c.msgcount for c in conns):
        return False
    try:
        return next(iter(reader.messages(connections=conns)), None) is None
    except Exception:  # a damaged storage: records() counts it
        return False


class Reader:
    """The NavSatFix fixes of one ROS 2 bag (see the module docstring)."""

    def __init__(self, path: Path, options: GnssOptions) -> None:
        self.options = options
        self.paths = _storage_paths(path)
        self.source = Source(path=path, format=FORMAT, kind=KIND, utc_uncertainty_ns=1)
        self._copies: Path | None = None  # a folder of merged copies, removed by close()
        try:
            self._repair(path)
            self._choose_topic(path, options)
        except BaseException:
            self.close()
            raise

    def _repair(self, path: Path) -> None:
        """A recording that was not closed (``ros2 bag record`` killed by a crash) has no
        metadata.yaml, and rosbags misses or refuses what it left:

        - SQLite in WAL mode (the ``resilient`` preset) keeps the last messages in
          ``bag.db3-wal``; rosbags opens the database as immutable and does not see
          them: a copy with the log merged in is read;
        - an MCAP file stops without its summary and footer; rosbags refuses it: a copy
          of its whole records closed with a footer is read (rosbags scans it).

        The storage files are then read without metadata.yaml, such ones as their copies
        (in a temporary folder that :meth:`close` removes); the inputs are not changed."""
        import sqlite3

        files = sorted(p for p in path.iterdir() if p.suffix in STORAGE_SUFFIXES) if (
            path.is_dir()) else [path]
        copies: dict[Path, Path] = {}
        for p in files:
            try:
                wal = _write_ahead_log(p)
                end = _mcap_cut_end(p) if p.suffix == ".mcap" else None
                if wal is None and end is None:
                    continue
                if self._copies is None:
                    self._copies = Path(tempfile.mkdtemp(prefix="osa-bag-"))
                if wal is not None:
                    copies[p] = _merged_copy(p, wal, self._copies)
                    self.source.warn(
                        f"{wal.name}: the recording was not closed (a crash?); the messages "
                        f"of this write-ahead log ({wal.stat().st_size // 1024} kB) are read "
                        "from a copy of the database with it merged")
                else:
                    copies[p] = _closed_copy(p, end, self._copies)
                    self.source.warn(
                        f"{p.name}: the recording was cut off (no MCAP footer: a crash?); "
                        f"its whole records ({end} bytes) are read, the last "
                        f"{p.stat().st_size - end} bytes (a record cut short) are not")
            except (OSError, sqlite3.Error) as exc:
                self.source.warn(f"{p.name}: a recording that was not closed, and no copy "
                                 f"of it could be made to read all of it ({brief(exc)})")
        if copies:
            self.paths = [copies.get(p, p) for p in files]

    def _choose_topic(self, path: Path, options: GnssOptions) -> None:
        with self._open() as reader:
            topics = sorted({c.topic for c in reader.connections if c.msgtype == NAVSATFIX})
            if options.topic is not None:
                if options.topic not in topics:
                    raise SourceError(f"{path}: no NavSatFix topic {options.topic!r} "
                                      f"(NavSatFix topics: {', '.join(topics) or 'none'})")
                self.topic = options.topic
            elif len(topics) == 1:
                self.topic = topics[0]
            elif not topics:
                raise SourceError(f"{path}: no {NAVSATFIX} topic")
            else:
                raise SourceError(f"{path}: several NavSatFix topics ({', '.join(topics)}): "
                                  "name one with --topic")
            unpaired = path.is_dir() and self.paths == [path] and _unpaired(reader, self.topic)
        if unpaired:
            self.paths = _storage_files(path)
            self.source.warn(f"metadata.yaml does not describe {self.topic} as its storage "
                             "does (its QoS or type edited?), so none of its messages pair "
                             "with it: the storage files are read without it")
        self.source.label = f"NavSatFix on {self.topic}"

    def _open(self):
        from rosbags.highlevel import AnyReader, AnyReaderError
        from rosbags.typesys import Stores, get_typestore

        try:
            reader = AnyReader(self.paths, default_typestore=get_typestore(Stores.ROS2_HUMBLE))
            reader.open()
        except (AnyReaderError, OSError, ValueError, KeyError) as exc:
            raise SourceError(f"{self.source.path}: not a readable ROS 2 bag "
                              f"({brief(exc)})") from None
        except Exception as exc:  # storage plugins raise their own (sqlite3, mcap) errors
            raise SourceError(f"{self.source.path}: not a readable ROS 2 bag "
                              f"({type(exc).__name__}: {brief(exc)})") from None
        return contextlib.closing(reader)

    def records(self, tally: Tally) -> Iterator[Stamped]:
        with self._open() as reader:
            conns = [c for c in reader.connections if c.topic == self.topic]
            for conn in reader.connections:
                if conn.topic != self.topic:
                    tally.counts.unknown_types[conn.topic] += conn.msgcount
            messages = reader.messages(connections=conns)
            n = 0
            while True:
                try:
                    conn, _, raw = next(messages)
                except StopIteration:
                    break
                except Exception as exc:  # the storage is damaged from here on
                    self._damaged(tally, n, sum(c.msgcount for c in conns), exc)
                    break
                n += 1
                tally.counts.lines += 1
                try:
                    try:
                        msg = reader.deserialize(raw, conn.msgtype)
                    except Exception:  # any failure of one message
                        raise Skip("corrupt_message") from None
                    yield self._fix(msg, tally)
                except Skip as s:
                    tally.skip(s.reason)

    def _damaged(self, tally: Tally, n: int, expected: int, exc: Exception) -> None:
        """The storage raised after ``n`` messages of the topic (a damaged record or
        page): those are kept, the rest of the ``expected`` (the bag's count, at least
        one) are counted as ``corrupt_data``."""
        lost = max(1, expected - n)
        tally.counts.lines += lost
        tally.counts.rejected["corrupt_data"] += lost
        self.source.warn(f"damaged after message {n} of {self.topic} ({brief(exc)}): the "
                         f"rest ({lost}) is counted as corrupt_data")

    def _fix(self, msg, tally: Tally) -> Stamped:
        stamp = msg.header.stamp
        utc_ns = int(stamp.sec) * NS_PER_S + int(stamp.nanosec)
        if utc_ns <= 0:
            raise Skip("no_utc")
        status = int(msg.status.status)
        if status not in STATUS:
            raise Skip("no_fix")
        acc = vacc = None
        if int(msg.position_covariance_type) != 0:
            c = [float(x) for x in msg.position_covariance]
            east, north, up = c[0], c[4], c[8]
            if min(east, north, up) < 0:
                raise Skip("bad_value")
            # a NaN (or infinite) variance is an unknown accuracy: nmea_navsat_driver
            # squares an empty HDOP into NaN
            if math.isfinite(east) and math.isfinite(north):
                acc = math.sqrt(max(east, north))
            if math.isfinite(up):
                vacc = math.sqrt(up)
        fix = make_fix(lat_deg=float(msg.latitude), lon_deg=float(msg.longitude),
                       alt_m=float(msg.altitude), acc_m=acc, vacc_m=vacc, fix=STATUS[status],
                       default_acc_m=self.options.default_acc_m)
        tally.heights["ellipsoid"] += 1
        return Stamped(fix, utc_ns=utc_ns)

    def close(self) -> None:
        if self._copies is not None:
            shutil.rmtree(self._copies, ignore_errors=True)
            self._copies = None
