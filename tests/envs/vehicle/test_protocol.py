"""The vehicle side of the mission protocol, message by message (fake link and clock):
what it ACKs, what it refuses with which MAV_MISSION_RESULT, and that only a complete
list ever replaces the held one."""

from __future__ import annotations

from dataclasses import replace

import pytest
from pymavlink.dialects.v20.common import (
    MAV_MISSION_ACCEPTED as MISSION_ACCEPTED,
)
from pymavlink.dialects.v20.common import (
    MAV_MISSION_DENIED as MISSION_DENIED,
)
from pymavlink.dialects.v20.common import (
    MAV_MISSION_ERROR as MISSION_ERROR,
)
from pymavlink.dialects.v20.common import (
    MAV_MISSION_INVALID_PARAM1 as MISSION_INVALID_PARAM1,
)
from pymavlink.dialects.v20.common import (
    MAV_MISSION_INVALID_PARAM5_X as MISSION_INVALID_PARAM5_X,
)
from pymavlink.dialects.v20.common import (
    MAV_MISSION_INVALID_SEQUENCE as MISSION_INVALID_SEQUENCE,
)
from pymavlink.dialects.v20.common import (
    MAV_MISSION_NO_SPACE as MISSION_NO_SPACE,
)
from pymavlink.dialects.v20.common import (
    MAV_MISSION_OPERATION_CANCELLED as MISSION_OPERATION_CANCELLED,
)
from pymavlink.dialects.v20.common import (
    MAV_MISSION_UNSUPPORTED as MISSION_UNSUPPORTED,
)
from pymavlink.dialects.v20.common import (
    MAV_MISSION_UNSUPPORTED_FRAME as MISSION_UNSUPPORTED_FRAME,
)

from envs.vehicle.mission import CAPACITY
from envs.vehicle.protocol import MissionServer
from planner.mavlink_wire import WireItem
from planner.mission import MAV_MISSION_TYPE_FENCE, MAV_MISSION_TYPE_MISSION

GCS = (0, 255, 190)
OTHER = (0, 250, 1)


class Link:
    def __init__(self) -> None:
        self.sent: list[tuple] = []
        self.now = 0.0
        self.commits: list[tuple[int, list[WireItem], int]] = []
        self.server = MissionServer(self.send, lambda t, items, cur: self.commits.append(
            (t, items, cur)), lambda: 0, clock=lambda: self.now)

    def send(self, peer, name, args) -> None:
        self.sent.append((peer, name, args))

    def take(self) -> list[tuple]:
        out, self.sent = self.sent, []
        return out

    def acks(self) -> list[int]:
        return [a[0] for _, n, a in self.sent if n == "mission_ack"]


def wp(seq: int, **kw) -> WireItem:
    base = dict(seq=seq, frame=6, command=16, current=int(seq == 0), autocontinue=1,
                param1=0.0, param2=0.0, param3=0.0, param4=float("nan"),
                x=367150000 + 100 * seq, y=-44780000, z=30.0, mission_type=0)
    base.update(kw)
    return WireItem(**base)


def upload(link: Link, items: list[WireItem], peer=GCS, mission_type: int = 0) -> None:
    link.server.on_count(peer, len(items), mission_type)
    for w in items:
        link.server.on_item(peer, w)


def test_complete_upload_is_committed_and_acked_once() -> None:
    link = Link()
    items = [wp(k) for k in range(5)]
    link.server.on_count(GCS, 5, 0)
    assert link.take() == [(GCS, "mission_request_int", (0, 0))]
    for w in items[:4]:
        link.server.on_item(GCS, w)
    assert [a for _, n, a in link.take()] == [(k, 0) for k in range(1, 5)]
    assert link.commits == []  # nothing flown before the last item
    link.server.on_item(GCS, items[4])
    assert link.take() == [(GCS, "mission_ack", (MISSION_ACCEPTED, 0))]
    assert link.commits == [(0, items, 0)]
    # the ACK was lost: the last item again is acknowledged again, nothing re-committed
    link.server.on_item(GCS, items[4])
    assert link.take() == [(GCS, "mission_ack", (MISSION_ACCEPTED, 0))]
    assert len(link.commits) == 1
    # the current item of the upload becomes the current item
    upload(link, [replace(wp(k), current=int(k == 2)) for k in range(4)])
    assert link.commits[-1][2] == 2


def test_refusals_leave_the_previous_mission() -> None:
    link = Link()
    good = [wp(k) for k in range(3)]
    upload(link, good)
    assert link.server.held[0] == good
    cases = [
        ([wp(0), wp(1, command=31000)], MISSION_UNSUPPORTED),  # unknown command
        ([wp(0), wp(1, frame=1)], MISSION_UNSUPPORTED_FRAME),  # local NED
        ([wp(0), wp(1, x=950_000_000)], MISSION_INVALID_PARAM5_X),  # latitude 95
        ([wp(0), wp(1, command=177, frame=2, param1=7.0, param2=1.0)], MISSION_INVALID_PARAM1),
        ([wp(0), wp(2)], MISSION_INVALID_SEQUENCE),  # a gap
    ]
    for items, result in cases:
        link.take()
        link.server.on_count(GCS, 3, 0)
        for w in items:
            link.server.on_item(GCS, w)
        assert link.acks() == [result], items
        assert link.server.held[0] == good and len(link.commits) == 1
    link.take()
    link.server.on_count(GCS, CAPACITY[0] + 1, 0)
    assert link.acks() == [MISSION_NO_SPACE]
    assert link.server.refused[-1] == (0, MISSION_NO_SPACE)


def test_interrupted_upload_times_out_and_keeps_the_old_list() -> None:
    link = Link()
    old = [wp(k) for k in range(3)]
    upload(link, old)
    link.take()
    new = [wp(k, z=50.0) for k in range(10)]
    link.server.on_count(GCS, 10, 0)
    for w in new[:5]:
        link.server.on_item(GCS, w)
    link.take()
    # silence: the vehicle asks again every retry_s, gives up after timeout_s
    for k in range(1, 20):
        link.now = 0.3 * k
        link.server.tick()
    sent = link.take()
    requests = [a for _, n, a in sent if n == "mission_request_int"]
    assert requests and all(a == (5, 0) for a in requests)
    assert len(requests) <= 5.0 / 0.25 + 1
    assert [a for _, n, a in sent if n == "mission_ack"] == [(MISSION_OPERATION_CANCELLED, 0)]
    assert link.server.held[0] == old and not link.server.uploading
    # a late item of the dropped upload is ignored
    link.server.on_item(GCS, new[5])
    assert link.take() == [] and link.server.held[0] == old
    # the ground station may cancel too
    link.server.on_count(GCS, 10, 0)
    link.server.on_item(GCS, new[0])
    link.server.on_ack(GCS, MISSION_OPERATION_CANCELLED, 0)
    assert not link.server.uploading and link.server.held[0] == old


def test_duplicates_busy_and_other_types() -> None:
    link = Link()
    items = [wp(k) for k in range(4)]
    link.server.on_count(GCS, 4, 0)
    link.server.on_count(GCS, 4, 0)  # our request was lost: asked again
    assert [a for _, n, a in link.take()] == [(0, 0), (0, 0)]
    link.server.on_item(GCS, items[0])
    link.server.on_item(GCS, items[0])  # a copy at once: our request is on its way
    link.now += link.server.retry_s + 0.01
    link.server.on_item(GCS, items[0])  # a resend later: ask for the next one again
    assert [a for _, n, a in link.take()] == [(1, 0), (1, 0)]
    # another ground station while this upload runs
    link.server.on_count(OTHER, 2, 0)
    assert link.take() == [(OTHER, "mission_ack", (MISSION_DENIED, 0))]
    # a fence upload meanwhile is its own transfer; a split polygon is refused
    fence = [WireItem(seq=k, frame=0, command=5001, current=0, autocontinue=0, param1=4.0,
                      param2=0.0, param3=0.0, param4=0.0, x=367150000 + k, y=-44780000, z=0.0,
                      mission_type=MAV_MISSION_TYPE_FENCE) for k in range(3)]
    upload(link, fence, mission_type=MAV_MISSION_TYPE_FENCE)
    assert link.acks()[-1] == MISSION_INVALID_PARAM1 and link.server.held[1] == []
    for w in items[1:]:
        link.server.on_item(GCS, w)
    assert link.acks()[-1] == MISSION_ACCEPTED and link.server.held[0] == items


def test_download_clear_and_count_zero() -> None:
    link = Link()
    items = [wp(k) for k in range(3)]
    upload(link, items)
    link.take()
    link.server.on_request_list(GCS, 0)
    assert link.take() == [(GCS, "mission_count", (3, 0))]
    link.server.on_request(GCS, 1, 0)
    (_, name, args), = link.take()
    assert name == "mission_item_int" and args[0] == 1 and args[3] == 0 and args[9] == items[1].x
    link.server.on_request(GCS, 0, 0)
    assert link.take()[0][2][3] == 1  # the current item carries current=1
    link.server.on_request(GCS, 1, 0, float_form=True)
    (_, name, args), = link.take()
    assert name == "mission_item" and args[9] == pytest.approx(items[1].x / 1e7)
    link.server.on_request(GCS, 3, 0)
    assert link.acks() == [MISSION_INVALID_SEQUENCE]
    link.take()
    link.server.on_clear_all(GCS, 255)
    assert link.acks() == [MISSION_ACCEPTED]
    assert all(v == [] for v in link.server.held.values())
    upload(link, items)
    link.take()
    link.server.on_count(GCS, 0, MAV_MISSION_TYPE_MISSION)  # PX4: a count of 0 clears
    assert link.acks() == [MISSION_ACCEPTED] and link.server.held[0] == []


def _fence_item(seq: int, mission_type: int = MAV_MISSION_TYPE_FENCE) -> WireItem:
    return WireItem(seq=seq, frame=0, command=5003, current=0, autocontinue=0, param1=1.0,
                    param2=0.0, param3=0.0, param4=0.0, x=367150000, y=-44780000, z=0.0,
                    mission_type=mission_type)


@pytest.mark.parametrize("before", ["nothing", "another uploads the mission",
                                    "its own mission uploaded"])
def test_an_item_of_the_wrong_list_answering_a_pending_request_ends_that_upload(
        before: str) -> None:
    """A fence item sent with ``mission_type`` 0 answering this ground station's pending
    fence request ends the fence upload with MAV_MISSION_ERROR at once (as PX4 answers an
    item of another type than the transfer's), whatever else is going on with the
    mission list: nothing; another ground station uploading it (the item used to be
    ignored: re-requests until the 5 s timeout); this ground station's own last mission
    ending at that sequence (it used to be taken for a resent last item: the mission was
    ACCEPTED again). The held lists and the other's upload stay."""
    link = Link()
    if before == "another uploads the mission":
        link.server.on_count(OTHER, 3, MAV_MISSION_TYPE_MISSION)
    elif before == "its own mission uploaded":
        upload(link, [wp(0)])
    held = {t: list(v) for t, v in link.server.held.items()}
    link.take()
    link.server.on_count(GCS, 1, MAV_MISSION_TYPE_FENCE)
    assert link.take() == [(GCS, "mission_request_int", (0, MAV_MISSION_TYPE_FENCE))]
    link.server.on_item(GCS, _fence_item(0, mission_type=MAV_MISSION_TYPE_MISSION))
    assert link.take() == [(GCS, "mission_ack", (MISSION_ERROR, MAV_MISSION_TYPE_FENCE))]
    assert link.server.held == held
    other_uploading = before == "another uploads the mission"
    assert (MAV_MISSION_TYPE_MISSION in link.server._rx) == other_uploading
    assert MAV_MISSION_TYPE_FENCE not in link.server._rx


def test_an_item_of_another_list_not_answering_a_request_is_not_an_error() -> None:
    """Without a pending request at its sequence, an item for a list this ground station
    is not uploading is a late duplicate (ignored), or its last item resent (its ACK was
    lost: ACCEPTED again)."""
    link = Link()
    upload(link, [wp(0), wp(1)])
    link.take()
    link.server.on_count(GCS, 2, MAV_MISSION_TYPE_FENCE)
    link.take()
    link.server.on_item(GCS, wp(1))  # not the pending fence request (seq 0): a resend
    assert link.take() == [(GCS, "mission_ack", (MISSION_ACCEPTED, MAV_MISSION_TYPE_MISSION))]
    link.server.on_item(OTHER, wp(1))  # someone else's late duplicate
    assert link.take() == []
    assert link.server.uploading  # the fence upload goes on


def test_int32_max_is_no_position_only_for_a_mission_item() -> None:
    """INT32_MAX in x and y ("not set": where the vehicle is) is taken for a mission item
    only; a fence vertex, a fence circle or a rally point has no "here" (the fence used
    to be placed at latitude 214.7 degrees, and the vehicle could not arm)."""
    unset = 2**31 - 1
    link = Link()
    upload(link, [wp(0, command=22, x=unset, y=unset), wp(1)])  # take-off: here
    assert link.acks() == [MISSION_ACCEPTED]
    circle = wp(0, command=5003, frame=5, param1=500.0, x=unset, y=unset,
                mission_type=MAV_MISSION_TYPE_FENCE)
    vertices = [wp(k, command=5001, frame=5, param1=3.0, x=unset if k == 1 else 367150000 + k,
                   y=unset if k == 1 else -44780000 - k * k, mission_type=MAV_MISSION_TYPE_FENCE)
                for k in range(3)]
    rally = wp(0, command=5100, x=unset, y=unset, mission_type=2)
    for items, t in (([circle], MAV_MISSION_TYPE_FENCE), (vertices, MAV_MISSION_TYPE_FENCE),
                     ([rally], 2)):
        link.take()
        upload(link, items, mission_type=t)
        assert link.acks() == [MISSION_INVALID_PARAM5_X], items
        assert t not in {c[0] for c in link.commits}


def test_refusals_kept_are_bounded() -> None:
    """A ground station that keeps sending what is refused (partial lists, counts beyond
    the storage) grows no memory: the last REFUSALS_KEPT refusals are kept (the list
    used to grow with every one)."""
    from envs.vehicle.protocol import REFUSALS_KEPT

    link = Link()
    for k in range(3 * REFUSALS_KEPT):
        if k % 2:
            link.server.refuse_partial(GCS, 0)
        else:
            link.server.on_count(GCS, CAPACITY[0] + 1, 0)
    assert len(link.server.refused) == REFUSALS_KEPT
    assert link.server.refused[-1] == (0, MISSION_UNSUPPORTED)
    assert link.server.refused[-2] == (0, MISSION_NO_SPACE)
    assert len(link.acks()) == 3 * REFUSALS_KEPT  # every one answered


@pytest.mark.parametrize("cleared", [MAV_MISSION_TYPE_MISSION, 255])
def test_a_clear_from_another_ground_station_does_not_drop_an_upload(cleared: int) -> None:
    """Two ground stations: while one uploads a mission, the other's MISSION_CLEAR_ALL
    (of the mission, or 255: all lists) is MAV_MISSION_DENIED, as a second upload is,
    and nothing held changes (PX4 refuses a clear while a transfer runs); the upload goes
    on to its ACK. It used to be ACCEPTED and to drop the upload silently: the uploader's
    next items were ignored as late duplicates and it waited for the answer until its
    own timeout."""
    link = Link()
    old = [wp(k) for k in range(2)]
    upload(link, old)
    new = [wp(k, z=40.0) for k in range(3)]
    link.take()
    link.server.on_count(GCS, 3, MAV_MISSION_TYPE_MISSION)
    link.server.on_item(GCS, new[0])
    link.take()
    link.server.on_clear_all(OTHER, cleared)
    assert link.take() == [(OTHER, "mission_ack", (MISSION_DENIED, cleared))]
    assert link.server.held[MAV_MISSION_TYPE_MISSION] == old
    for w in new[1:]:
        link.server.on_item(GCS, w)
    assert link.take() == [(GCS, "mission_request_int", (2, 0)),
                           (GCS, "mission_ack", (MISSION_ACCEPTED, 0))]
    assert link.server.held[MAV_MISSION_TYPE_MISSION] == new
    # a stalled upload (no progress for the timeout) no longer blocks a clear
    link.server.on_count(GCS, 3, MAV_MISSION_TYPE_MISSION)
    link.now += link.server.timeout_s + 0.1
    link.take()
    link.server.on_clear_all(OTHER, cleared)
    assert link.acks() == [MISSION_ACCEPTED] and link.server.held[0] == []


def test_a_ground_station_clearing_during_its_own_upload_ends_it() -> None:
    """The uploader's own MISSION_CLEAR_ALL ends its upload and clears (it changed its
    mind): ACCEPTED."""
    link = Link()
    link.server.on_count(GCS, 3, MAV_MISSION_TYPE_MISSION)
    link.server.on_item(GCS, wp(0))
    link.take()
    link.server.on_clear_all(GCS, MAV_MISSION_TYPE_MISSION)
    assert link.acks() == [MISSION_ACCEPTED] and not link.server.uploading


def test_a_slow_link_does_not_multiply_the_requests() -> None:
    """A ground station answering every request over a link with a 0.3 s round trip
    (a telemetry radio carrying telemetry too; longer than the 0.25 s re-request): the
    vehicle re-requests before each answer arrives, and a copy of an item it holds is
    answered with a new request only if its last one is older than that. 100 items
    take 200 requests, PX4's retry alone (it ignores copies); each copy used to be
    answered with a request, and the copies multiplied: 1680 requests and 1658 items
    on the link for 100."""
    import heapq

    link = Link()
    rtt = 0.3
    items = [wp(k) for k in range(100)]
    events: list[tuple[float, int, str, int]] = []
    n_req = n_items = 0
    acks: list[tuple[float, int]] = []

    def send(peer, name, args) -> None:
        nonlocal n_req
        if name == "mission_request_int":
            n_req += 1
            heapq.heappush(events, (link.now + rtt / 2, len(events) + 7 * n_req, "req",
                                    args[0]))
        elif name == "mission_ack":
            acks.append((link.now, args[0]))

    link.server.send = send
    link.server.on_count(GCS, 100, 0)
    t = 0.0
    while (not acks or t < acks[0][0] + 2 * rtt) and t < 300.0:
        t = round(t + 0.02, 6)
        while events and events[0][0] <= t:
            at, k, kind, seq = heapq.heappop(events)
            if kind == "req":  # the ground station's answer, half a round trip later
                heapq.heappush(events, (at + rtt / 2, k, "item", seq))
            else:
                link.now = at
                n_items += 1
                link.server.on_item(GCS, items[seq])
        link.now = t
        link.server.tick()
    assert acks and acks[0][1] == MISSION_ACCEPTED
    assert acks[0][0] == pytest.approx(100 * rtt, abs=1.0)  # one round trip per item
    assert link.server.held[0] == items
    assert n_req <= 210 and n_items <= 210, (n_req, n_items)
    # the copy of the last item answering the re-request is not ACKed again: MAVSDK
    # takes a second ACK for the end of its next upload (docs/vehicle.md, its traps)
    assert len(acks) == 1, acks
    link.now += link.server.retry_s + 0.01
    link.server.on_item(GCS, items[-1])  # later: the ground station lost our ACK
    assert len(acks) == 2
