"""The phone's records as a stream: one interface whatever carries them.

A phone on the drone logs GNSS fixes and FTM results (docs/log-format.md). The closed
loop needs them as they are made, and the online estimator does not care how they
travel. Each way is a small :class:`RecordSource` (``poll()`` -> the new records, in
the order they arrived; bad lines counted with the estimator's own reader,
:func:`estimator.logio.parse_line` and :class:`estimator.logio.RejectCounts`):

- :class:`FileRecords`: the lines of a log file that is still being written (``osa
  vehicle --log FILE`` on the same machine);
- :class:`TunnelRecords`: the records ``osa vehicle`` relays to the ground station on
  the MAVLink link itself, in TUNNEL messages of the private payload type
  :data:`PAYLOAD_RECORDS` (the byte layout below and in docs/vehicle.md);
- :class:`UdpRecords`: JSON-line datagrams from a phone app, one record per datagram.

:class:`PhoneFeed` puts a source's records in the order a replay of the log reads them
(by ``t_ns``, ties in arrival order) and releases those the phone can no longer
precede: up to the relay's mark when the source has marks (exact), else up to
``lag_s`` behind the newest record. It also maps the phone's clock to flight time,
and, for a source without marks, goes on through a reboot of the phone (its clock
jumping back: :meth:`PhoneFeed._retimed`).

Relay layout (one record's JSON line, UTF-8, no newline, in one or more TUNNEL
messages; every payload is at most :data:`TUNNEL_PAYLOAD_BYTES` bytes; integers
little-endian)::

    PAYLOAD_RECORDS (vehicle -> ground station), kind 0, a chunk of one record:
      0  u8   version (1)
      1  u8   kind (0)
      2  u32  record sequence number (0, 1, 2, ... one per record the vehicle relays)
      6  u8   chunk index (0 .. count - 1)
      7  u8   chunk count (1 .. 255)
      8  ...  up to 120 bytes of the line
    PAYLOAD_RECORDS, kind 1, a mark (after each step that delivered records):
      0  u8   version (1)
      1  u8   kind (1)
      2  u32  sequence number of the next record (every record before it was sent)
      6  i64  t_ns: every record the phone delivered up to this phone time was sent
     14  i64  clock offset (ns): phone time minus the vehicle's time since boot
    PAYLOAD_RECORDS, kind 2, pacing (the answer to each PAYLOAD_PACE, and once when a
    lockstep vehicle reaches its limit):
      0  u8   version (1)
      1  u8   kind (2)
      2  u32  the vehicle's time_boot_ms now
      6  u32  time_boot_ms it may run to (0xFFFFFFFF: no lockstep); now = limit: it waits
     10  u32  } the latest mark (next sequence number, t_ns, clock offset), as in
     14  i64  } kind 1 (t_ns -1: no record relayed yet)
     22  i64  }
    PAYLOAD_PACE (ground station -> vehicle): the acknowledgement
      0  u8   version (1)
      1  u32  time_boot_ms the ground station has processed (osa vehicle --lockstep)
    PAYLOAD_RESEND (ground station -> vehicle): send records again
      0  u8   version (1)
      1  u32  first sequence number
      5  u16  how many

A record whose chunks do not all arrive is asked for again (the vehicle keeps the
last :data:`RESEND_KEPT` records); one still missing when the loop must go on is
counted lost (the sequence numbers show it). Records are handed on in sequence order,
so a record that came again is fed where it belongs. A record arriving after later
records were released is counted late and dropped (the estimator takes each agent's
records in time order).
"""

from __future__ import annotations

import dataclasses
import heapq
import math
import os
import socket
import struct
import time
from collections import Counter, deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

from estimator.logio import (
    CLOCK_JUMP_BACK_S,
    CLOCK_JUMP_GAP_S,
    LogError,
    RejectCounts,
    dumps_record,
    parse_line,
)
from estimator.records import GnssFix, LogHeader, RangeSample, TruthRecord

PAYLOAD_RECORDS = 32768  # MAVLink TUNNEL payload types >= 32768: "local experiments"
PAYLOAD_PACE = 32769
PAYLOAD_RESEND = 32770
RESEND_KEPT = 8192  # records the vehicle keeps to send again
TUNNEL_PAYLOAD_BYTES = 128
VERSION = 1
KIND_CHUNK, KIND_MARK, KIND_PACING = 0, 1, 2
_PACING = struct.Struct("<BBIIIqq")  # version, kind, now, limit, latest mark
_RESEND = struct.Struct("<BIH")  # version, first seq, count
NO_LIMIT_MS = 0xFFFFFFFF
_CHUNK = struct.Struct("<BBIBB")  # version, kind, seq, index, count
_MARK = struct.Struct("<BBIqq")  # version, kind, next seq, through t_ns, clock offset ns
_PACE = struct.Struct("<BI")  # version, time_boot_ms
CHUNK_DATA_BYTES = TUNNEL_PAYLOAD_BYTES - _CHUNK.size  # 120
MAX_CHUNKS = 255
PENDING_RECORDS = 4096  # records waiting for a missing one, at most (then it is given up)
_RECENT_RECORDS = 4096  # a record that repeats one of these is a copy, not a clock jump
_EARLIEST_RECORDS = 256  # nor one that repeats one of the first records

Record = GnssFix | RangeSample


# ----------------------------------------------------------------------------- wire


def record_chunks(seq: int, rec: LogHeader | Record) -> list[bytes]:
    """The TUNNEL payloads of record number ``seq`` (its log line in chunks); empty
    when the line would need more than :data:`MAX_CHUNKS` chunks."""
    line = dumps_record(rec).encode("utf-8")
    n = max(1, math.ceil(len(line) / CHUNK_DATA_BYTES))
    if n > MAX_CHUNKS:
        return []
    seq &= 0xFFFFFFFF
    return [_CHUNK.pack(VERSION, KIND_CHUNK, seq, k, n)
            + line[k * CHUNK_DATA_BYTES:(k + 1) * CHUNK_DATA_BYTES] for k in range(n)]


def mark_payload(next_seq: int, through_ns: int, clock_offset_ns: int) -> bytes:
    """A mark: records up to ``next_seq`` were sent, the phone's stream is complete up
    to ``through_ns``; ``clock_offset_ns`` = phone time - vehicle time since boot."""
    return _MARK.pack(VERSION, KIND_MARK, next_seq & 0xFFFFFFFF, through_ns, clock_offset_ns)


def pacing_payload(now_ms: int, limit_ms: int | None, mark: Mark | None) -> bytes:
    """The vehicle's pacing: its time now, the time it may run to (None: no lockstep;
    ``now_ms == limit_ms``: it waits for the ground station) and its latest mark."""
    limit = NO_LIMIT_MS if limit_ms is None else min(limit_ms, NO_LIMIT_MS - 1)
    m = mark if mark is not None else Mark(0, -1, 0)
    return _PACING.pack(VERSION, KIND_PACING, now_ms & 0xFFFFFFFF, limit,
                        m.next_seq & 0xFFFFFFFF, m.through_ns, m.clock_offset_ns)


@dataclass(frozen=True)
class Pacing:
    """What a vehicle says of its pacing (see :func:`pacing_payload`)."""

    now_ms: int
    limit_ms: int | None  # None: no lockstep

    @property
    def lockstep(self) -> bool:
        return self.limit_ms is not None

    @property
    def waiting(self) -> bool:
        """At its limit (within the milliseconds' truncation): it waits for us."""
        return self.limit_ms is not None and self.now_ms >= self.limit_ms - 2


def resend_payload(first_seq: int, count: int) -> bytes:
    """The ground station asks for records ``first_seq .. first_seq + count - 1``."""
    return _RESEND.pack(VERSION, first_seq & 0xFFFFFFFF, max(0, min(count, 0xFFFF)))


def read_resend(payload: bytes) -> tuple[int, int] | None:
    """(first sequence number, count) of a :data:`PAYLOAD_RESEND` payload."""
    if len(payload) < _RESEND.size or payload[0] != VERSION:
        return None
    _, first, count = _RESEND.unpack_from(payload)
    return int(first), int(count)


def pace_payload(time_boot_ms: int) -> bytes:
    """The ground station's acknowledgement: it has processed the vehicle's time up to
    ``time_boot_ms`` (``osa vehicle --lockstep``)."""
    return _PACE.pack(VERSION, time_boot_ms & 0xFFFFFFFF)


def read_pace(payload: bytes) -> int | None:
    """The ``time_boot_ms`` of a :data:`PAYLOAD_PACE` payload (None if malformed)."""
    if len(payload) < _PACE.size or payload[0] != VERSION:
        return None
    return int(_PACE.unpack_from(payload)[1])


@dataclass(frozen=True)
class Mark:
    """What a relay's mark says (see the module docstring)."""

    next_seq: int
    through_ns: int
    clock_offset_ns: int


# ----------------------------------------------------------------------------- sources


def parse_record(line: bytes, counts: RejectCounts) -> LogHeader | Record | TruthRecord | None:
    """:func:`estimator.logio.parse_line` for a live stream: a header the log reader would
    refuse (another format, a newer major version) is counted (``refused_header``) and
    skipped; one bad datagram never stops the search."""
    try:
        return parse_line(line, counts)
    except LogError:
        counts.reject("refused_header")
        return None


class RecordSource(Protocol):
    """The phone's records, whatever carries them (see the module docstring)."""

    counts: RejectCounts  # bad lines, by reason

    def poll(self) -> list[LogHeader | Record | TruthRecord]:
        """New records since the last call, in the order they arrived."""
        ...

    def mark(self) -> Mark | None:
        """The latest mark of the stream (None: this source has none)."""
        ...

    @property
    def lost(self) -> int:
        """Records known to be lost on the way."""
        ...

    def close(self) -> None: ...


class FileRecords:
    """The records of a log file that is still being written, line by line (a gzip
    file cannot be read while it is written: refused)."""

    def __init__(self, path: str | os.PathLike, timeout_s: float = 10.0) -> None:
        self.path = Path(path)
        if self.path.suffix == ".gz":
            raise ValueError(f"{self.path}: a gzip log cannot be read while it is written")
        self.counts = RejectCounts()
        deadline = time.monotonic() + timeout_s
        while not self.path.is_file():
            if time.monotonic() > deadline:
                raise FileNotFoundError(f"no log {self.path} (osa vehicle --log FILE)")
            time.sleep(0.05)
        self._fh = open(self.path, "rb")  # noqa: SIM115 - closed in close()
        self._buf = b""

    def poll(self) -> list:
        data = self._fh.read()
        if not data:
            return []
        lines = (self._buf + data).split(b"\n")
        self._buf = lines.pop()
        out = []
        for line in lines:
            rec = parse_record(line, self.counts)
            if rec is not None:
                out.append(rec)
        return out

    def mark(self) -> Mark | None:
        return None

    @property
    def lost(self) -> int:
        return 0

    def close(self) -> None:
        self._fh.close()


def udp_listen_address(url: str) -> tuple[str, int]:
    """(host, port) of ``udpin://HOST:PORT`` or ``udpin:HOST:PORT`` (ValueError else)."""
    u = url.strip()
    for scheme in ("udpin://", "udpin:", "udp://"):
        if u.startswith(scheme):
            rest = u[len(scheme):]
            break
    else:
        raise ValueError(f"unsupported phone URL {url!r}: use udpin://HOST:PORT "
                         "(the loop listens there)")
    host, _, port = rest.rpartition(":")
    try:
        p = int(port)
    except ValueError:
        raise ValueError(f"bad phone URL {url!r}: port {port!r} is not a number") from None
    if not host or not 0 <= p < 65536:  # 0: a port the system picks
        raise ValueError(f"bad phone URL {url!r}: expected udpin://HOST:PORT")
    return host, p


class UdpRecords:
    """JSON-line datagrams from a phone app: one record per datagram (several lines in
    one datagram are taken too); listens on ``udpin://HOST:PORT``. The records are one
    phone's: those of the first address (host) whose datagram held a valid record; the
    datagrams of any other are counted (:attr:`other_sender`) and ignored (a second
    phone's GNSS and clock fed as the drone's would corrupt every estimate)."""

    MAX_DATAGRAM = 65535

    def __init__(self, url: str) -> None:
        host, port = udp_listen_address(url)
        self.counts = RejectCounts()
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self.sock.bind((host, port))
        except OSError as exc:
            self.sock.close()
            raise OSError(f"cannot listen on {url}: {exc.strerror or exc}") from None
        self.sock.setblocking(False)
        self.datagrams = 0
        self.sender: str | None = None  # the phone's host, once it sent a valid record
        self.other_sender = 0  # datagrams from another host: ignored

    @property
    def port(self) -> int:
        return int(self.sock.getsockname()[1])

    def poll(self) -> list:
        out = []
        while True:
            try:
                data, addr = self.sock.recvfrom(self.MAX_DATAGRAM)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:
                break
            self.datagrams += 1
            if self.sender is not None and addr[0] != self.sender:
                self.other_sender += 1
                continue
            n = len(out)
            for line in data.split(b"\n"):
                rec = parse_record(line, self.counts)
                if rec is not None:
                    out.append(rec)
            if self.sender is None and len(out) > n:
                self.sender = addr[0]
        return out

    def mark(self) -> Mark | None:
        return None

    @property
    def lost(self) -> int:
        return 0

    def close(self) -> None:
        self.sock.close()


class TunnelRecords:
    """The records ``osa vehicle`` relays on the MAVLink link (TUNNEL payload type
    :data:`PAYLOAD_RECORDS`): chunks reassembled by sequence number and handed on in
    sequence order, the missing ones known (:meth:`missing`, to ask for them again)
    until :meth:`settle` counts them lost; the latest mark and pacing kept. Feed it
    each payload with :meth:`take`. With ``keep_records=False`` only the pacing and the
    marks are read (the records come another way)."""

    def __init__(self, keep_records: bool = True) -> None:
        self.keep_records = keep_records
        self.counts = RejectCounts()
        self._parts: dict[int, dict[int, bytes]] = {}  # seq -> chunk index -> data
        self._lines: dict[int, bytes] = {}  # complete, not handed on yet
        self._next: int | None = None  # the next seq to hand on
        self._gone: set[int] = set()  # given up (counted lost), not passed yet
        self._lost = 0
        self._mark: Mark | None = None
        self.pacing: Pacing | None = None  # the vehicle's latest pacing message
        self.chunks = 0
        self.duplicates = 0
        self.malformed = 0

    def take(self, payload: bytes | Sequence[int]) -> None:
        """One TUNNEL payload (its ``payload_length`` bytes) of type PAYLOAD_RECORDS."""
        b = bytes(payload)
        if len(b) < 2 or b[0] != VERSION:
            self.malformed += 1
            return
        if b[1] == KIND_PACING and len(b) >= _PACING.size:
            _, _, now, limit, nxt, through, offset = _PACING.unpack_from(b)
            self.pacing = Pacing(int(now), None if limit == NO_LIMIT_MS else int(limit))
            if through >= 0:
                self._take_mark(Mark(int(nxt), int(through), int(offset)))
            return
        if b[1] == KIND_MARK and len(b) >= _MARK.size:
            _, _, nxt, through, offset = _MARK.unpack_from(b)
            self._take_mark(Mark(int(nxt), int(through), int(offset)))
            return
        if not self.keep_records:
            return
        if b[1] != KIND_CHUNK or len(b) < _CHUNK.size:
            self.malformed += 1
            return
        _, _, seq, k, n = _CHUNK.unpack_from(b)
        if n == 0 or k >= n:
            self.malformed += 1
            return
        self.chunks += 1
        if self._next is None:
            self._next = seq  # the first record heard: what came before is not ours
        if seq < self._next or seq in self._lines or seq in self._gone:
            self.duplicates += 1  # (or too late: counted lost already)
            return
        parts = self._parts.setdefault(seq, {})
        if k in parts:
            self.duplicates += 1
            return
        parts[k] = b[_CHUNK.size:]
        if len(parts) == n:
            del self._parts[seq]
            self._lines[seq] = b"".join(parts[i] for i in range(n))
        if len(self._parts) + len(self._lines) > PENDING_RECORDS:  # bounded memory
            self.settle(max(self._lines, default=self._next) + 1)

    def _take_mark(self, m: Mark) -> None:
        if self._mark is None or (m.next_seq, m.through_ns) > (self._mark.next_seq,
                                                               self._mark.through_ns):
            self._mark = m
        if self._next is None and self.keep_records:
            self._next = m.next_seq  # nothing heard yet: from here on

    def missing(self, until_seq: int | None = None) -> list[int]:
        """Sequence numbers below ``until_seq`` (default: the latest mark's next) not
        yet complete nor settled."""
        if self._next is None:
            return []
        if until_seq is None:
            until_seq = self._mark.next_seq if self._mark is not None else self._next
        return [s for s in range(self._next, until_seq)
                if s not in self._lines and s not in self._gone]

    def settle(self, until_seq: int | None = None, *, count: bool = True) -> int:
        """Give up on what is still missing below ``until_seq`` (default: the latest
        mark's next): counted lost (unless ``count`` is False: records of before the
        search). Returns how many."""
        gone = self.missing(until_seq)
        for s in gone:
            self._parts.pop(s, None)
        self._gone.update(gone)
        self._lost += len(gone) if count else 0
        return len(gone)

    def poll(self) -> list:
        """The records complete in sequence order (up to the first missing one)."""
        out = []
        if self._next is None:
            return out
        while True:
            line = self._lines.pop(self._next, None)
            if line is None:
                if self._next in self._gone:  # given up: skip it
                    self._gone.discard(self._next)
                    self._next += 1
                    continue
                break
            self._next += 1
            rec = parse_record(line, self.counts)
            if rec is not None:
                out.append(rec)
        return out

    def mark(self) -> Mark | None:
        return self._mark

    @property
    def lost(self) -> int:
        return self._lost

    def close(self) -> None:
        pass


# ----------------------------------------------------------------------------- feed


@dataclass(frozen=True)
class PhoneBatch:
    """What one agent's phone delivered since the last batch: the records in the order
    a replay of its log reads them, the phone time up to which its stream is complete
    (``through_ns``; None: no news), and its clock (``clock_offset_s``: phone seconds
    minus flight seconds; None: not known yet)."""

    records: Sequence[Record]
    through_ns: int | None = None
    clock_offset_s: float | None = None


@dataclass
class FeedStats:
    """Counts of a network record path (the report's ``phone`` entry)."""

    received: int = 0
    released: int = 0
    late: int = 0  # arrived after later records had been released: dropped
    lost: int = 0
    rejected: dict = field(default_factory=dict)
    skipped: dict = field(default_factory=dict)  # unknown types and fields, counted
    other_sender: int = 0  # datagrams of another phone than the one heard first: ignored
    clock_jumps: int = 0  # the phone clock jumped back (a reboot): the records re-timed

    def to_json(self) -> dict:
        d: dict = {"released": self.released, "lost": self.lost, "late": self.late}
        if self.rejected:
            d["rejected_lines"] = dict(self.rejected)
        if any(self.skipped.values()):
            d["skipped"] = dict(self.skipped)
        if self.other_sender:
            d["other_sender"] = self.other_sender
        if self.clock_jumps:
            d["clock_jumps"] = self.clock_jumps
        return d


class PhoneFeed:
    """A record source put in replay order and released (see the module docstring).

    ``take(flight_s, vehicle_boot_s)`` returns a :class:`PhoneBatch` of what may be fed
    now; ``final(end_ns)`` the rest up to ``end_ns``. Records before the loop started
    (``skip_before()``) are not fed. The clock offset comes from the source's marks,
    else from arrivals: every record taken at flight time ``flight_s`` was stamped
    before it, so the largest phone time minus ``flight_s`` bounds the offset from
    below, and a range's flight time is late by at most the source's latency (never
    early, never after the flight time it was taken at)."""

    def __init__(self, source: RecordSource, *, lag_s: float = 2.0) -> None:
        self.source = source
        self.lag_s = lag_s
        self.header: LogHeader | None = None
        self.truth: list[TruthRecord] = []
        self._heap: list[tuple[int, int, Record]] = []
        self._n = 0
        self._newest: int | None = None
        self._released: int | None = None  # t_ns of the last record released
        self._start_ns: int | None = None
        self._offset_s: float | None = None
        self._shift_ns = 0  # added to the phone's t_ns since its clock jumped back
        self._recent: deque[Record] = deque(maxlen=_RECENT_RECORDS)  # as the phone sent them
        self._recent_n: Counter[Record] = Counter()  # the same, to look a record up at once
        self._earliest: set[Record] = set()  # the first records (a log sent again from its start)
        self._copy_at: int | None = None  # reading copies of earlier records: the latest
        self.stats = FeedStats()

    def _pull(self, flight_s: float | None) -> None:
        for rec in self.source.poll():
            if isinstance(rec, LogHeader):
                if self.header is None:
                    self.header = rec
                continue
            if isinstance(rec, TruthRecord):
                self.truth.append(rec)
                continue
            if not isinstance(rec, GnssFix | RangeSample):
                continue
            self.stats.received += 1
            if self.source.mark() is None:
                retimed = self._retimed(rec, flight_s)
                if retimed is None:
                    self.stats.late += 1
                    continue
                rec = retimed
            if flight_s is not None and self.source.mark() is None:
                off = rec.t_ns * 1e-9 - flight_s
                self._offset_s = off if self._offset_s is None else max(self._offset_s, off)
            if self._start_ns is not None and rec.t_ns < self._start_ns:
                continue  # of before the search
            if self._released is not None and rec.t_ns < self._released:
                self.stats.late += 1
                continue
            heapq.heappush(self._heap, (rec.t_ns, self._n, rec))
            self._n += 1
            self._newest = rec.t_ns if self._newest is None else max(self._newest, rec.t_ns)

    def _retimed(self, rec: Record, flight_s: float | None) -> Record | None:
        """``rec`` on the feed's clock; None for a copy of earlier records (an app that
        sends its records again). A record older than the newest by more than
        CLOCK_JUMP_BACK_S means the phone clock jumped back (a reboot resets it): from
        there on the records are shifted, the first of them to its arrival (the flight
        time it was taken at on the clock before the jump), at least CLOCK_JUMP_GAP_S
        after the newest; unless it repeats one of the recent or the first records: a
        copy, and so are the records after it up to the newest while they go on in time
        (as a replay of the log tells copies from jumps, docs/log-format.md)."""
        back_ns = int(CLOCK_JUMP_BACK_S * 1e9)
        t = rec.t_ns + self._shift_ns
        if self._newest is not None and t < self._newest - back_ns:
            if self._copy_at is not None and t < self._copy_at - back_ns:
                self._copy_at = None  # far before the copy going on: not part of it
            if self._copy_at is None and (rec in self._recent_n or rec in self._earliest):
                self._copy_at = t
            if self._copy_at is not None:
                self._copy_at = max(self._copy_at, t)
                return None
            self.stats.clock_jumps += 1
            at = self._newest + int(CLOCK_JUMP_GAP_S * 1e9)
            if flight_s is not None and self._offset_s is not None:
                at = max(at, round((flight_s + self._offset_s) * 1e9))
            self._shift_ns = at - rec.t_ns
            t = at
        self._copy_at = None
        if len(self._earliest) < _EARLIEST_RECORDS:
            self._earliest.add(rec)
        if len(self._recent) == self._recent.maxlen:
            old = self._recent[0]
            self._recent_n[old] -= 1
            if not self._recent_n[old]:
                del self._recent_n[old]
        self._recent.append(rec)
        self._recent_n[rec] += 1
        return rec if t == rec.t_ns else dataclasses.replace(rec, t_ns=t)

    def pull(self) -> None:
        """Take what the source has now (without releasing anything)."""
        self._pull(None)

    def skip_before(self, flight_s: float | None = None) -> None:
        """Drop what arrived so far (the records of before the search); records stamped
        before the newest of them are not fed either."""
        self._pull(flight_s)
        m = self.source.mark()
        newest = m.through_ns if m is not None else self._newest
        self._heap.clear()
        if newest is not None:
            self._start_ns = newest + 1

    def clock_offset_s(self, boot0_s: float) -> float | None:
        """Phone seconds minus flight seconds (flight time: vehicle time - ``boot0_s``)."""
        m = self.source.mark()
        if m is not None:
            return m.clock_offset_ns * 1e-9 + boot0_s
        return self._offset_s

    def take(self, flight_s: float | None, boot0_s: float) -> PhoneBatch:
        """The records that may be fed now (see the class docstring)."""
        self._pull(flight_s)
        m = self.source.mark()
        if m is not None:
            limit: float | None = m.through_ns
        elif self._newest is not None:
            limit = self._newest - self.lag_s * 1e9
        else:
            limit = None
        return self._release(limit, boot0_s)

    def final(self, end_ns: float, boot0_s: float) -> PhoneBatch:
        """Everything up to ``end_ns`` (phone time), at the end of the flight."""
        self._pull(None)
        batch = self._release(end_ns, boot0_s)
        self._heap.clear()
        return batch

    def wanted_through_ns(self) -> int | None:
        """Phone time up to which the stream is known complete (mark or newest - lag)."""
        m = self.source.mark()
        if m is not None:
            return m.through_ns
        if self._newest is None:
            return None
        return int(self._newest - self.lag_s * 1e9)

    def _release(self, limit: float | None, boot0_s: float) -> PhoneBatch:
        out: list[Record] = []
        heap = self._heap
        if limit is not None:
            while heap and heap[0][0] <= limit:
                out.append(heapq.heappop(heap)[2])
        if out:
            self._released = out[-1].t_ns
            self.stats.released += len(out)
        self.stats.lost = self.source.lost
        self.stats.rejected = dict(self.source.counts.rejected)
        self.stats.skipped = self.source.counts.skipped()
        self.stats.other_sender = getattr(self.source, "other_sender", 0)
        through = None
        if limit is not None and math.isfinite(limit) and (
                self._start_ns is None or limit >= self._start_ns):
            through = int(limit)
            if self._released is not None:
                through = max(through, self._released)
        return PhoneBatch(out, through, self.clock_offset_s(boot0_s))

    def close(self) -> None:
        self.source.close()
