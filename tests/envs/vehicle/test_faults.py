"""Faults on the MAVLink link to the virtual vehicle: a lossy link (a seeded proxy
dropping a share of the datagrams both ways), a link that dies half way through an
upload, a NACKed mission, an upload abandoned half way while a mission is flown, a
ground station that disappears. The vehicle never flies a partial list, the ground
side retries within bounds or fails with one line, nothing waits unbounded."""

from __future__ import annotations

import math
import time
from pathlib import Path

import pytest

from envs.cli import main as osa_main
from envs.vehicle.px4 import Mode
from planner.files import write_plan
from planner.mavlink import TransferConfig, download_wire, upload_mission
from planner.mavlink_wire import UploadTimeoutError, compare_wire, mission_to_wire
from planner.mission import (
    MAV_CMD_NAV_RETURN_TO_LAUNCH,
    MAV_CMD_NAV_TAKEOFF,
    Mission,
    MissionItem,
)
from tests.envs.vehicle.helpers import SEARCH_SCENARIO, Gcs
from tests.net import LossyUdpProxy
from tests.planner.conftest import sample_mission
from tests.vehicles import RunningVehicle, running_vehicle

FAST = TransferConfig(connect_timeout_s=3.0, message_timeout_s=0.2, retries=8)
LOSSY = TransferConfig(connect_timeout_s=3.0, message_timeout_s=0.1, retries=12)


def square(rv: RunningVehicle, side: float = 60.0, alt: float = 20.0, laps: int = 1,
           rtl: bool = True) -> Mission:
    ap = rv.autopilot
    h = ap.home
    items = [MissionItem(command=MAV_CMD_NAV_TAKEOFF, lat_deg=h.lat_deg, lon_deg=h.lon_deg,
                         alt_m=alt)]
    for _ in range(laps):
        for e, n in ((side, 0.0), (side, side), (0.0, side), (0.0, 0.0)):
            lat, lon, _ = ap.frame.to_geodetic(h.enu[0] + e, h.enu[1] + n, h.enu[2])
            items.append(MissionItem(lat_deg=float(lat), lon_deg=float(lon), alt_m=alt))
    if rtl:
        items.append(MissionItem(command=MAV_CMD_NAV_RETURN_TO_LAUNCH))
    return Mission(items=tuple(items), home=(h.lat_deg, h.lon_deg, h.alt_m))


def _until(pred, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(0.05)
    return pred()


def test_upload_through_a_lossy_link() -> None:
    """20 % of the datagrams lost each way: pymavlink's resends and the vehicle's
    re-requests get a 14-item mission, its fence and rally points through, verified by
    the read-back."""
    m = sample_mission(10)
    with running_vehicle(SEARCH_SCENARIO) as rv, \
            LossyUdpProxy(rv.port, drop=0.2, seed=7) as proxy:
        report = upload_mission(m, f"udpout:127.0.0.1:{proxy.port}", config=LOSSY)
        assert (report.items, report.fence_items, report.rally_items) == (14, 9, 2)
        assert compare_wire(mission_to_wire(m), rv.held()) == []
        assert proxy.dropped[0] > 3 and proxy.dropped[1] > 3
        drop = [d / (d + p) for d, p in zip(proxy.dropped, proxy.passed, strict=True)]
        assert all(0.1 < f < 0.3 for f in drop)


def test_mavsdk_upload_through_a_lossy_link_succeeds_or_fails_cleanly() -> None:
    """MAVSDK 4.1 does not resend its last item when the final MISSION_ACK is lost (it
    times out): over a lossy link its upload may fail, but within its bound and with
    a typed error, and the vehicle then holds the previous list, never part of one."""
    from planner.mavlink_wire import UploadError

    m = sample_mission(6)
    outcomes = []
    with running_vehicle(SEARCH_SCENARIO) as rv:
        for seed in range(2):
            before = {t: rv.held(t) for t in (0, 1, 2)}
            with LossyUdpProxy(rv.port, drop=0.2, seed=seed) as proxy:
                t0 = time.monotonic()
                try:
                    upload_mission(m, f"udpout://127.0.0.1:{proxy.port}", config=LOSSY)
                    outcomes.append("ok")
                except UploadError as exc:
                    outcomes.append(type(exc).__name__)
                    assert "\n" not in str(exc)
                assert time.monotonic() - t0 < LOSSY.transfer_bound_s(10) * 3 + 3.0
            sent = {0: mission_to_wire(m), 1: None, 2: None}
            for t in (0, 1, 2):
                held = rv.held(t)
                if held != before[t]:  # replaced: then by the whole new list
                    assert sent[t] is None or compare_wire(sent[t], held) == []
                    assert len(held) == {0: 10, 1: 9, 2: 2}[t]
    assert set(outcomes) <= {"ok", "UploadTimeoutError", "MissionRejectedError",
                             "ProtocolError"}


def test_link_dies_half_way_through_osa_upload(tmp_path: Path, capsys) -> None:
    """The link dies after part of the items: osa upload fails within its bound with
    one line; the vehicle keeps the mission it had (and drops the staged items)."""
    with running_vehicle(SEARCH_SCENARIO, transfer_timeout_s=1.0) as rv, \
            LossyUdpProxy(rv.port) as proxy:
        first = square(rv)
        upload_mission(first, rv.pymavlink_url, config=FAST)
        old = rv.held()
        path = tmp_path / "big.plan"
        write_plan(sample_mission(120), path)

        proxy.cut_after_up = 50  # the heartbeat, MISSION_COUNT and some 45 items
        t0 = time.monotonic()
        status = osa_main(["upload", str(path), "--no-fence", "--connection",
                           f"udpout:127.0.0.1:{proxy.port}", "--timeout", "3",
                           "--message-timeout", "0.2", "--retries", "3"])
        elapsed = time.monotonic() - t0
        out, err = capsys.readouterr()
        assert status == 1 and out == ""
        assert err.count("\n") == 1 and err.startswith("osa upload: UploadTimeoutError: ")
        assert "the vehicle does not hold the mission" in err
        assert elapsed < (124 + 3) * 4 * 0.2  # the whole-transfer bound
        assert rv.held() == old
        assert _until(lambda: not rv.vehicle.protocol.uploading, 30.0)  # dropped, not flown
        assert rv.held() == old


def test_nacked_mission_leaves_the_previous_one(tmp_path: Path, capsys) -> None:
    with running_vehicle(SEARCH_SCENARIO) as rv:
        good = square(rv)
        upload_mission(good, rv.pymavlink_url, config=FAST)
        held = rv.held()
        bad = Mission(items=(*good.items[:3], MissionItem(command=31000, frame=2)),
                      home=good.home)
        path = tmp_path / "bad.plan"
        write_plan(bad, path)
        for url, name in ((rv.pymavlink_url, "MAV_MISSION_UNSUPPORTED"),
                          (rv.mavsdk_url, "UNSUPPORTED")):
            status = osa_main(["upload", str(path), "--connection", url, "--timeout", "3"])
            out, err = capsys.readouterr()
            assert status == 1 and out == "" and err.count("\n") == 1
            assert err.startswith("osa upload: MissionRejectedError: vehicle rejected the "
                                  f"mission upload: {name}")
            assert rv.held() == held
        assert list(rv.vehicle.protocol.refused)[-2:] == [(0, 3), (0, 3)]  # MAV_MISSION_UNSUPPORTED


def test_upload_abandoned_while_flying_is_never_flown() -> None:
    """A ground station sends MISSION_COUNT and half the items of a new mission, then
    falls silent: the vehicle flies on the old mission, re-requests, then cancels."""
    with running_vehicle(SEARCH_SCENARIO, speedup=20.0, transfer_timeout_s=1.5) as rv:
        old = square(rv, laps=3)
        upload_mission(old, rv.pymavlink_url, config=FAST)
        gcs = Gcs(rv.pymavlink_url)
        try:
            assert gcs.command(400, 1) == 0
            assert gcs.command(300, 0, 0) == 0
            assert _until(lambda: len(rv.autopilot.reached_log) >= 2, 20.0)
            new = mission_to_wire(square(rv, side=150.0, alt=35.0))
            gcs.conn.mav.mission_count_send(1, 1, len(new), 0)
            sent = 0
            while sent < len(new) // 2:
                req = gcs.wait("MISSION_REQUEST_INT", 2.0)
                w = new[req.seq]
                gcs.conn.mav.mission_item_int_send(
                    1, 1, w.seq, w.frame, w.command, w.current, w.autocontinue, w.param1,
                    w.param2, w.param3, w.param4, w.x, w.y, w.z, 0)
                sent += 1
            # silence: the vehicle asks for the next item again, then gives up
            t0 = time.monotonic()
            asked = []
            ack = None
            while time.monotonic() - t0 < 30.0 and ack is None:  # a bound only
                m = gcs.recv(0.2)
                if m is not None and m.get_type() == "MISSION_REQUEST_INT":
                    asked.append(m.seq)
                elif m is not None and m.get_type() == "MISSION_ACK":
                    ack = m
            assert ack is not None and ack.type == 15  # MAV_MISSION_OPERATION_CANCELLED
            assert set(asked) == {len(new) // 2} and len(asked) >= 3
            assert time.monotonic() - t0 < 1.5 + 10.0  # its 1.5 s, and slack for a busy machine
        finally:
            gcs.close()
        assert compare_wire(mission_to_wire(old), rv.held()) == []
        got = download_wire(rv.pymavlink_url, config=FAST)[0]
        assert compare_wire(mission_to_wire(old), got) == []
        # still flying the old square (60 m), never the half-sent 150 m one
        reached = len(rv.autopilot.reached_log)
        assert _until(lambda: len(rv.autopilot.reached_log) > reached + 1, 20.0)
        ap = rv.autopilot
        h = ap.home.enu
        assert max(abs(p[0] - h[0]) for _, _, p in ap.reached_log) < 65.0
        assert ap.mode is Mode.MISSION


def test_ground_station_disappears() -> None:
    """Mission mode: the mission is flown to its end (COM_DLL_EXCEPT), the vehicle
    returns and lands. Hold: after COM_DL_LOSS_T the link-loss action (return)."""
    params = {"COM_DL_LOSS_T": 0.5}
    with running_vehicle(SEARCH_SCENARIO, speedup=60.0, params=params) as rv:
        mission = square(rv)
        upload_mission(mission, rv.pymavlink_url, config=FAST)
        gcs = Gcs(rv.pymavlink_url)
        assert gcs.command(400, 1) == 0 and gcs.command(300, 0, 0) == 0
        gcs.close()  # gone: no heartbeat, no message
        ap = rv.autopilot
        assert _until(lambda: not ap.armed and ap.landed, 40.0)
        assert [r[0] for r in ap.reached_log] == [0, 1, 2, 3, 4, 5]  # all, then AUTO.RTL
        assert rv.vehicle._link.lost
    with running_vehicle(SEARCH_SCENARIO, speedup=60.0, params=params) as rv:
        gcs = Gcs(rv.pymavlink_url)
        assert gcs.command(400, 1) == 0 and gcs.command(22, 0, 0, 0, math.nan, math.nan,
                                                         math.nan, math.nan) == 0
        ap = rv.autopilot
        assert _until(lambda: ap.mode is Mode.LOITER and not ap.landed, 30.0)
        gcs.close()
        assert _until(lambda: ap.mode is Mode.RTL, 30.0)  # NAV_DLL_ACT 2 after 0.5 s
        assert _until(lambda: not ap.armed, 40.0)
        # a ground station coming back is served again
        gcs = Gcs(rv.pymavlink_url)
        assert gcs.command(512, 148) == 0
        gcs.close()
        assert _until(lambda: not rv.vehicle._link.lost, 30.0)


def test_upload_timeout_is_bounded_when_the_vehicle_is_gone() -> None:
    with running_vehicle(SEARCH_SCENARIO) as rv, LossyUdpProxy(rv.port) as proxy:
        url = f"udpout:127.0.0.1:{proxy.port}"
        cfg = TransferConfig(connect_timeout_s=2.0, message_timeout_s=0.1, retries=2)
        from planner.mavlink import connected

        with connected(url, cfg) as link:
            proxy.cut = True
            t0 = time.monotonic()
            with pytest.raises(UploadTimeoutError, match="the vehicle does not hold"):
                link.upload(mission_to_wire(sample_mission(10)), 0)
            assert time.monotonic() - t0 < (14 + 3) * 3 * 0.1 + 10.0  # slack: a busy machine
