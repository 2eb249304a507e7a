"""The vehicle's side of the phone's record relay, and lockstep pacing.

The phone on the drone produces its records inside the vehicle process (the stepper's
:class:`sim.stepper.Emitted`). :class:`RecordRelay` sends them to the ground stations
on the MAVLink link itself, in TUNNEL messages of the private payload type
:data:`envs.phone.PAYLOAD_RECORDS` (the byte layout is in :mod:`envs.phone` and
docs/vehicle.md): each record's log line in chunks with a sequence number, then a mark
saying up to which phone time the stream is complete. A ground station asks for the
records by sending a TUNNEL of type :data:`envs.phone.PAYLOAD_PACE` (its
acknowledgement of the vehicle time it has processed); from then on every record the
phone delivers is relayed, the log header first. The last
:data:`envs.phone.RESEND_KEPT` records are kept and sent again on request
(:data:`envs.phone.PAYLOAD_RESEND`).

Lockstep (``osa vehicle --lockstep S``): the vehicle never runs more than ``S`` seconds
of simulated time ahead of the ground station's last acknowledgement. It waits there
(saying so once with a ``held`` payload, with its position), so a loop that
acknowledges after each decision meets the vehicle at the same simulated instants
whatever the wall clock does: a run is reproducible under any load.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Sequence
from typing import Any

from envs.phone import (
    PAYLOAD_PACE,
    PAYLOAD_RECORDS,
    PAYLOAD_RESEND,
    RESEND_KEPT,
    Mark,
    mark_payload,
    pacing_payload,
    read_pace,
    read_resend,
    record_chunks,
)
from estimator.records import LogHeader
from planner.mavlink import mavutil
from sim.stepper import REPLAY_ORDER, Emitted

mavlink = mavutil.mavlink


class RecordRelay:
    """Relays the phone's records in TUNNEL messages; paces the vehicle in lockstep."""

    def __init__(self, broadcast: Callable[[Any], None], header: LogHeader, *,
                 lockstep_s: float | None = None, tick_s: float = 0.05) -> None:
        if lockstep_s is not None and not (math.isfinite(lockstep_s) and lockstep_s > 0):
            raise ValueError(f"lockstep must be > 0 s, got {lockstep_s!r}")
        self.broadcast = broadcast
        self.header = header
        self.lockstep_s = lockstep_s
        self.tick_s = tick_s
        self.active = False  # a ground station asked for the records
        self.seq = 0
        self.ack_s = 0.0
        self.sent_chunks = 0
        self.resent = 0  # records sent again on request
        self.skipped = 0  # records whose line is too long for 255 chunks
        self.mark: Mark | None = None  # the latest mark sent
        self._kept: deque[tuple[int, list[bytes]]] = deque(maxlen=RESEND_KEPT)
        self._held_at: float | None = None

    # ------------------------------------------------------------------ ground station
    def on_tunnel(self, msg: Any, t_s: float) -> None:
        """A TUNNEL from a ground station at the vehicle's time ``t_s``: an
        acknowledgement (PAYLOAD_PACE), answered with the vehicle's pacing, or a
        request to send records again (PAYLOAD_RESEND)."""
        payload = bytes(msg.payload[: msg.payload_length])
        if msg.payload_type == PAYLOAD_RESEND:
            asked = read_resend(payload)
            if asked is not None:
                self._resend(*asked)
            return
        ms = read_pace(payload) if msg.payload_type == PAYLOAD_PACE else None
        if ms is None:
            return
        if not self.active:
            self.active = True
            self._send_record(self.header)
        # the vehicle's ticks: the acknowledged time_boot_ms (truncated) names a tick
        ack = round(ms / 1000.0 / self.tick_s) * self.tick_s
        self.ack_s = max(self.ack_s, ack)
        self._pacing(t_s)

    def _pacing(self, t_s: float) -> None:
        limit = None if self.lockstep_s is None else _ms(self.limit_s)
        self._tunnel(pacing_payload(_ms(t_s), limit, self.mark))

    def _resend(self, first: int, count: int) -> None:
        """Records ``first .. first + count - 1`` again, those still kept."""
        if not self._kept:
            return
        lo = self._kept[0][0]
        for k in range(max(first, lo), min(first + count, self.seq)):
            seq, chunks = self._kept[k - lo]
            assert seq == k
            for c in chunks:
                self._tunnel(c)
            self.resent += 1

    # ------------------------------------------------------------------ pacing
    @property
    def limit_s(self) -> float:
        """The simulated time the vehicle may run to (inf without lockstep)."""
        return math.inf if self.lockstep_s is None else self.ack_s + self.lockstep_s

    def held(self, t_s: float) -> bool:
        """True once when the vehicle has just reached its limit at ``t_s`` (it then
        says so with its pacing)."""
        if self.lockstep_s is None or t_s < self.limit_s - 1e-9 or self._held_at == t_s:
            return False
        self._held_at = t_s
        self._pacing(t_s)
        return True

    # ------------------------------------------------------------------ records
    def relay(self, emitted: Sequence[Emitted]) -> None:
        """The records the phone delivered in one step (in the order a replay reads
        them), then a mark: the stream is complete up to the last one."""
        if not self.active or not emitted:
            return
        ordered = sorted(emitted, key=REPLAY_ORDER)
        for e in ordered:
            self._send_record(e.record)
        last = ordered[-1]
        offset = last.t_ns - round(last.delivery_s * 1e9)
        self.mark = Mark(self.seq, last.t_ns, offset)
        self._tunnel(mark_payload(self.seq, last.t_ns, offset))

    def _send_record(self, rec: Any) -> None:
        chunks = record_chunks(self.seq, rec)
        self._kept.append((self.seq, chunks))
        self.seq += 1
        if not chunks:
            self.skipped += 1
            return
        for c in chunks:
            self._tunnel(c)
            self.sent_chunks += 1

    def _tunnel(self, payload: bytes) -> None:
        self.broadcast(mavlink.MAVLink_tunnel_message(
            0, 0, PAYLOAD_RECORDS, len(payload), payload.ljust(128, b"\0")))


def _ms(t_s: float) -> int:
    """time_boot_ms of a simulated time (as the vehicle's telemetry stamps it)."""
    return int(t_s * 1000.0) & 0xFFFFFFFF
