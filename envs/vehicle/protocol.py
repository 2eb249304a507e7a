"""Vehicle side of the MAVLink mission protocol: mission, fence and rally lists.

Upload (MISSION_COUNT, then MISSION_REQUEST_INT for each item, MISSION_ACK): items
are checked as they arrive (:mod:`envs.vehicle.mission`) and kept in a staging list;
only a complete, valid list replaces the held one (``on_commit``), so an upload that
is refused, cancelled or abandoned half way leaves the previous list in force and
is never flown. The vehicle re-requests an unanswered item every ``retry_s`` and
drops a transfer that makes no progress for ``timeout_s`` (wall clock; PX4: 250 ms
and 5 s). A resent last item after the final ACK is acknowledged again (the ACK was
lost), a resent earlier item is answered with a request for the one expected (unless
the last request is younger than ``retry_s``: over a slow link the copies answering our
own re-requests would multiply the requests), an
item beyond it ends the transfer with MAV_MISSION_INVALID_SEQUENCE, an item of another
list answering the pending request ends it with MAV_MISSION_ERROR
(:meth:`MissionServer._wrong_type`). One upload per
list at a time: a second ground station gets MAV_MISSION_DENIED while one runs. A ground
station is its MAVLink identity (system and component), as PX4 keeps it: the same one
starting again on another link (it reconnected, its old TCP connection half-open)
restarts its own upload; an upload whose link is gone (a TCP client that hung up) is
dropped at once (:meth:`MissionServer.forget_link`).
Items are asked for in the form the ground station speaks, as PX4 does: MISSION_REQUEST_INT,
or the legacy MISSION_REQUEST to one that last sent a float MISSION_ITEM or asked with
MISSION_REQUEST, or started the upload in MAVLink 1 framing (a MAVLink 1-era ground
station may know no other); a MISSION_ACK MAV_MISSION_UNSUPPORTED from the uploader
switches to the other form, as PX4 negotiates it.

Download (MISSION_REQUEST_LIST, MISSION_COUNT, MISSION_REQUEST_INT -> MISSION_ITEM_INT)
is stateless: any request for a held item is answered (legacy MISSION_REQUEST with a
float MISSION_ITEM, as PX4 does, an unset x or y as NaN); the mission's current item
carries ``current=1``.
MISSION_CLEAR_ALL (255: all lists) empties lists at once (MAV_MISSION_DENIED while
another ground station uploads one of them, as PX4 refuses a clear during a transfer).
A count of 0 clears too.
Partial lists (MISSION_WRITE_PARTIAL_LIST, MISSION_REQUEST_PARTIAL_LIST) are refused
with MAV_MISSION_UNSUPPORTED.
"""

from __future__ import annotations

import collections
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from pymavlink.dialects.v20.common import (
    MAV_MISSION_ACCEPTED,
    MAV_MISSION_DENIED,
    MAV_MISSION_ERROR,
    MAV_MISSION_INVALID_SEQUENCE,
    MAV_MISSION_NO_SPACE,
    MAV_MISSION_OPERATION_CANCELLED,
    MAV_MISSION_TYPE_ALL,
    MAV_MISSION_UNSUPPORTED,
)

from envs.vehicle.mission import CAPACITY, UNSET_E7, check_item, check_list
from planner.mavlink_wire import WireItem
from planner.mission import MAV_MISSION_TYPE_MISSION, deg_to_e7

REFUSALS_KEPT = 1000  # the last refusals remembered (MissionServer.refused)
Peer = tuple[int, int, int]  # (link id: envs.vehicle.links, system id, component id)
Send = Callable[[Peer, str, tuple], None]  # peer, pymavlink message name, args after target


@dataclass
class _Upload:
    peer: Peer
    mission_type: int
    count: int
    items: list[WireItem]
    activity_s: float
    requested_s: float
    float_form: bool = False  # ask with the legacy MISSION_REQUEST
    legacy_guess: bool = False  # float form from what the peer did before
    last_asked: int = 0  # requests sent for the last item


@dataclass
class _Commit:
    peer: Peer
    count: int
    asked: int = 0  # requests sent for the last item: as many copies of it answer them
    copies: int = 1  # copies of the last item received


class MissionServer:
    """See the module docstring. ``send(peer, name, args)`` sends
    ``<name>_send(target_system, target_component, *args)`` to ``peer``;
    ``on_commit(mission_type, items, current_seq)`` receives each accepted list;
    ``current()`` is the mission's current item (for downloads)."""

    def __init__(self, send: Send, on_commit: Callable[[int, list[WireItem], int], None],
                 current: Callable[[], int], *, retry_s: float = 0.25, timeout_s: float = 5.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.send = send
        self.on_commit = on_commit
        self.current = current
        self.retry_s = retry_s
        self.timeout_s = timeout_s
        self.clock = clock
        self.held: dict[int, list[WireItem]] = {t: [] for t in CAPACITY}
        self._rx: dict[int, _Upload] = {}
        self._last: dict[int, _Commit] = {}
        # (mission_type, MAV_MISSION_RESULT) of the last refusals
        self.refused: collections.deque[tuple[int, int]] = collections.deque(
            maxlen=REFUSALS_KEPT)
        self.commits: dict[int, int] = {t: 0 for t in CAPACITY}  # accepted lists per type
        self._float_peers: set[Peer] = set()  # last spoke the float forms

    # ------------------------------------------------------------------ helpers
    def _ack(self, peer: Peer, result: int, mission_type: int) -> None:
        self.send(peer, "mission_ack", (result, mission_type))

    def _refuse(self, peer: Peer, result: int, mission_type: int) -> None:
        self._rx.pop(mission_type, None)
        self.refused.append((mission_type, result))
        self._ack(peer, result, mission_type)

    def _request(self, rx: _Upload) -> None:
        rx.requested_s = self.clock()
        rx.last_asked += len(rx.items) == rx.count - 1
        name = "mission_request" if rx.float_form else "mission_request_int"
        self.send(rx.peer, name, (len(rx.items), rx.mission_type))

    def _speaks(self, peer: Peer, float_form: bool) -> None:
        """``peer`` was heard in the float (legacy) or the INT form."""
        if float_form:
            if len(self._float_peers) >= 1024:
                self._float_peers.clear()
            self._float_peers.add(peer)
        else:
            self._float_peers.discard(peer)

    def _commit(self, peer: Peer, mission_type: int, items: list[WireItem],
                asked: int = 0) -> None:
        current = 0
        if mission_type == MAV_MISSION_TYPE_MISSION:
            flagged = [w.seq for w in items if w.current]
            current = flagged[0] if flagged else 0
        self.held[mission_type] = items
        self.commits[mission_type] += 1
        self._last[mission_type] = _Commit(peer, len(items), asked)
        self.on_commit(mission_type, list(items), current)

    @property
    def uploading(self) -> bool:
        return bool(self._rx)

    # ------------------------------------------------------------------ upload
    def on_count(self, peer: Peer, count: int, mission_type: int, *,
                 mavlink1: bool = False) -> None:
        """MISSION_COUNT (``mavlink1``: it came in MAVLink 1 framing)."""
        now = self.clock()
        if mission_type not in CAPACITY:
            self._ack(peer, MAV_MISSION_UNSUPPORTED, mission_type)
            return
        rx = self._rx.get(mission_type)
        if rx is not None and rx.peer[1:] != peer[1:] and now - rx.activity_s < self.timeout_s:
            self._ack(peer, MAV_MISSION_DENIED, mission_type)  # another ground station's upload
            return
        if count > CAPACITY[mission_type]:
            self._refuse(peer, MAV_MISSION_NO_SPACE, mission_type)
            return
        if count <= 0:
            self._rx.pop(mission_type, None)
            self._commit(peer, mission_type, [])
            self._ack(peer, MAV_MISSION_ACCEPTED, mission_type)
            return
        if rx is not None and rx.peer == peer and rx.count == count and not rx.items:
            self._request(rx)  # the count again: our request was lost
            return
        guess = peer in self._float_peers and not mavlink1
        rx = _Upload(peer, mission_type, count, [], now, now,
                     float_form=mavlink1 or guess, legacy_guess=guess)
        self._rx[mission_type] = rx
        self._request(rx)

    def on_item(self, peer: Peer, w: WireItem, *, float_form: bool = False) -> None:
        """One uploaded item (``float_form``: it came as a legacy MISSION_ITEM)."""
        self._speaks(peer, float_form)
        rx = self._rx.get(w.mission_type)
        if rx is not None and rx.peer == peer:
            rx.float_form = float_form
        if rx is None or rx.peer != peer:
            if self._wrong_type(peer, w):
                return
            last = self._last.get(w.mission_type)
            if last is not None and last.peer == peer and w.seq == last.count - 1:
                # a copy beyond those answering our own re-requests: our ACK was lost
                # (one ACK per upload else: MAVSDK takes a second for its next upload's)
                last.copies += 1
                if last.copies > last.asked:
                    self._ack(peer, MAV_MISSION_ACCEPTED, w.mission_type)
            return  # else a late duplicate: ignored
        n = len(rx.items)
        if w.seq < n:
            # a resend of an item we hold: ask for the next one, unless we just did (a
            # slow link's answers to our own re-requests would multiply the requests)
            if self.clock() - rx.requested_s > self.retry_s:
                self._request(rx)
            return
        if w.seq > n:
            self._refuse(peer, MAV_MISSION_INVALID_SEQUENCE, rx.mission_type)
            return
        result = check_item(w, rx.count)
        if result != MAV_MISSION_ACCEPTED:
            self._refuse(peer, result, rx.mission_type)
            return
        rx.items.append(w)
        rx.activity_s = self.clock()
        if len(rx.items) < rx.count:
            self._request(rx)
            return
        result = check_list(rx.items, rx.mission_type)
        if result != MAV_MISSION_ACCEPTED:
            self._refuse(peer, result, rx.mission_type)
            return
        del self._rx[rx.mission_type]
        self._commit(peer, rx.mission_type, rx.items, rx.last_asked)
        self._ack(peer, MAV_MISSION_ACCEPTED, rx.mission_type)

    def _wrong_type(self, peer: Peer, w: WireItem) -> bool:
        """Whether ``w``, an item for a list this ground station is not uploading,
        answers its pending request of another list (its sequence; a script that left
        ``mission_type`` at 0 in a fence upload): then that transfer ends with
        MAV_MISSION_ERROR at once, as PX4 answers an item of another type than the
        transfer's, instead of re-requests until the timeout; so too while another
        ground station uploads the item's list, and before a resent last item of an
        earlier upload is acknowledged again. The held lists stay."""
        hit = False
        for t, rx in list(self._rx.items()):
            if rx.peer == peer and t != w.mission_type and w.seq == len(rx.items):
                self._refuse(peer, MAV_MISSION_ERROR, t)
                hit = True
        return hit

    def on_item_int(self, peer: Peer, msg: Any) -> None:
        self.on_item(peer, WireItem.from_msg(msg))

    def on_item_float(self, peer: Peer, msg: Any) -> None:
        """Legacy MISSION_ITEM (lat/lon in float degrees), stored in the INT form."""
        x, y = float(msg.x), float(msg.y)
        w = WireItem(seq=int(msg.seq), frame=int(msg.frame), command=int(msg.command),
                     current=int(msg.current), autocontinue=int(msg.autocontinue),
                     param1=float(msg.param1), param2=float(msg.param2),
                     param3=float(msg.param3), param4=float(msg.param4),
                     x=deg_to_e7(x) if math.isfinite(x) else UNSET_E7,
                     y=deg_to_e7(y) if math.isfinite(y) else UNSET_E7, z=float(msg.z),
                     mission_type=int(getattr(msg, "mission_type", 0)))
        self.on_item(peer, w, float_form=True)

    def refuse_partial(self, peer: Peer, mission_type: int) -> None:
        """MISSION_WRITE_PARTIAL_LIST / MISSION_REQUEST_PARTIAL_LIST (ArduPilot's; PX4
        leaves them unanswered, a ground station would wait): MAV_MISSION_UNSUPPORTED at
        once; nothing held changes."""
        self.refused.append((mission_type, MAV_MISSION_UNSUPPORTED))
        self._ack(peer, MAV_MISSION_UNSUPPORTED, mission_type)

    def on_ack(self, peer: Peer, result: int, mission_type: int) -> None:
        """A ground station's MISSION_ACK during its upload: MAV_MISSION_UNSUPPORTED says
        it does not speak the form it was asked in (MAVSDK answers a MISSION_REQUEST so):
        ask again in the other form, as PX4 does; any other non-zero one cancels."""
        rx = self._rx.get(mission_type)
        if rx is None or rx.peer != peer or result == MAV_MISSION_ACCEPTED:
            return
        if result == MAV_MISSION_UNSUPPORTED:
            rx.float_form = not rx.float_form
            rx.legacy_guess = False  # it told: no more guessing
            self._speaks(peer, rx.float_form)
            self._request(rx)
            return
        del self._rx[mission_type]

    def forget_link(self, link: int) -> None:
        """The link ``link`` is gone: its uploads end (no one to tell)."""
        for t, rx in list(self._rx.items()):
            if rx.peer[0] == link:
                del self._rx[t]
        self._float_peers = {p for p in self._float_peers if p[0] != link}

    def tick(self) -> None:
        """Re-request unanswered items; drop stalled uploads."""
        now = self.clock()
        for t, rx in list(self._rx.items()):
            if now - rx.activity_s > self.timeout_s:
                self._refuse(rx.peer, MAV_MISSION_OPERATION_CANCELLED, t)
            elif now - rx.requested_s > self.retry_s:
                if rx.legacy_guess and not rx.items:
                    # asked in the float form on memory alone and not answered: this
                    # ground station may have moved on to the INT form; alternate
                    rx.float_form = not rx.float_form
                self._request(rx)

    # ------------------------------------------------------------------ download
    def on_request_list(self, peer: Peer, mission_type: int) -> None:
        if mission_type not in self.held:
            self._ack(peer, MAV_MISSION_UNSUPPORTED, mission_type)
            return
        self.send(peer, "mission_count", (len(self.held[mission_type]), mission_type))

    def _item_args(self, w: WireItem, float_form: bool) -> tuple:
        cur = int(w.mission_type == MAV_MISSION_TYPE_MISSION and w.seq == self.current())
        x, y = w.x, w.y
        if float_form:  # "not set" (INT32_MAX) is the float form's NaN
            x, y = (math.nan if v == UNSET_E7 else v / 1e7 for v in (w.x, w.y))
        return (w.seq, w.frame, w.command, cur, w.autocontinue, w.param1, w.param2, w.param3,
                w.param4, x, y, w.z, w.mission_type)

    def on_request(self, peer: Peer, seq: int, mission_type: int, *,
                   float_form: bool = False) -> None:
        self._speaks(peer, float_form)
        items = self.held.get(mission_type)
        if items is None:
            self._ack(peer, MAV_MISSION_UNSUPPORTED, mission_type)
            return
        if not 0 <= seq < len(items):
            self._ack(peer, MAV_MISSION_INVALID_SEQUENCE, mission_type)
            return
        name = "mission_item" if float_form else "mission_item_int"
        self.send(peer, name, self._item_args(items[seq], float_form))

    # ------------------------------------------------------------------ clear
    def on_clear_all(self, peer: Peer, mission_type: int) -> None:
        types: Sequence[int] = tuple(self.held) if mission_type == MAV_MISSION_TYPE_ALL \
            else (mission_type,)
        if any(t not in self.held for t in types):
            self._ack(peer, MAV_MISSION_UNSUPPORTED, mission_type)
            return
        now = self.clock()
        if any(rx.peer[1:] != peer[1:] and now - rx.activity_s < self.timeout_s
               for t, rx in self._rx.items() if t in types):
            # another ground station's upload of one of these lists runs (PX4: busy)
            self._ack(peer, MAV_MISSION_DENIED, mission_type)
            return
        for t in types:
            self._rx.pop(t, None)
            self._commit(peer, t, [])
        self._ack(peer, MAV_MISSION_ACCEPTED, mission_type)
