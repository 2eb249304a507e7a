"""Uploads to real loopback peers: ``osa vehicle``'s autopilot (happy paths),
MAVSDK's MissionRawServer (its count-0 trap) and a scripted pymavlink vehicle (NACKs,
silence, legacy requests, corrupted read-back)."""

from __future__ import annotations

import math
import time
from pathlib import Path

import pytest

from envs.cli import main as osa_main
from planner.files import write_plan
from planner.mavlink import TransferConfig, connected, download_wire, upload_mission, upload_on_link
from planner.mavlink_wire import (
    InvalidConnectionError,
    MissionRejectedError,
    NoVehicleError,
    UploadTimeoutError,
    VerifyMismatchError,
    WireItem,
    compare_wire,
    fence_to_wire,
    mission_to_wire,
    rally_to_wire,
    wire_to_mission,
)
from planner.mission import (
    MAV_MISSION_TYPE_FENCE,
    MAV_MISSION_TYPE_MISSION,
    MAV_MISSION_TYPE_RALLY,
    Mission,
    deg_to_e7,
)
from tests.net import free_udp_port
from tests.planner.conftest import (
    ANSWERING,
    CLI_ANSWERING,
    SILENT,
    sample_mission,
    write_mission_file,
)
from tests.planner.peers import MavsdkVehiclePeer, VehicleScript
from tests.vehicles import RunningVehicle

BACKENDS = ["pymavlink", "mavsdk"]


def url_of(peer, backend: str) -> str:
    return peer.pymavlink_url if backend == "pymavlink" else peer.mavsdk_url


def assert_holds(held: list[WireItem], mission: Mission) -> None:
    """The vehicle holds exactly the mission: seq order, one current, int lat/lon, frame."""
    assert [w.seq for w in held] == list(range(len(mission.items)))
    assert [w.current for w in held] == [1] + [0] * (len(mission.items) - 1)
    assert [(w.x, w.y) for w in held] == [(it.x_e7, it.y_e7) for it in mission.items]
    assert [(w.frame, w.command) for w in held] == [(it.frame, it.command)
                                                   for it in mission.items]
    assert [math.isnan(w.param4) for w in held] == [math.isnan(it.param4)
                                                    for it in mission.items]
    assert all(abs(w.z - it.alt_m) <= 1e-3 for w, it in zip(held, mission.items, strict=True))
    assert all(w.mission_type == MAV_MISSION_TYPE_MISSION for w in held)


# ---------------------------------------------------------------- wire form


def test_wire_form() -> None:
    m = sample_mission(5)
    wire = mission_to_wire(m)
    assert [w.seq for w in wire] == list(range(len(m.items)))
    assert [w.current for w in wire] == [1] + [0] * (len(wire) - 1)
    assert wire[1].x == deg_to_e7(m.items[1].lat_deg) == 367149123
    fence = fence_to_wire(m)
    assert [w.param1 for w in fence] == [4.0] * 4 + [3.0] * 3 + [12.5, 400.0]
    assert all(w.mission_type == MAV_MISSION_TYPE_FENCE and w.current == 0 for w in fence)
    rally = rally_to_wire(m)
    assert [(w.command, w.z) for w in rally] == [(5100, 30.0), (5100, 35.5)]
    back = wire_to_mission(wire, home=m.home, fence=fence, rally=rally)
    assert [(it.x_e7, it.y_e7) for it in back.items] == [(it.x_e7, it.y_e7) for it in m.items]
    assert back.polygons == m.polygons and back.circles == m.circles
    assert back.rally_deg == m.rally_deg
    assert compare_wire(wire, mission_to_wire(back)) == []
    nudged = [wire[0], WireItem(**{**wire[1].__dict__, "y": wire[1].y + 1}), *wire[2:]]
    assert compare_wire(wire, nudged) == [f"item 1: y {wire[1].y + 1} != sent {wire[1].y}"]
    assert compare_wire(wire, wire[:-1])[0].startswith("vehicle holds")


# ---------------------------------------------------------------- happy paths (osa vehicle)


@pytest.mark.parametrize("backend", BACKENDS)
def test_upload_to_vehicle(px4_vehicle: RunningVehicle, backend: str) -> None:
    m = sample_mission(40)
    before = {t: px4_vehicle.upload_count(t) for t in (0, 1, 2)}
    report = upload_mission(m, url_of(px4_vehicle, backend), config=ANSWERING)
    assert (report.items, report.fence_items, report.rally_items) == (len(m.items), 9, 2)
    assert report.backend == backend and report.vehicle == (1, 1)
    assert report.autopilot == "px4"  # the heartbeat says MAV_AUTOPILOT_PX4
    # one accepted list per type, held before the ACK
    assert {t: px4_vehicle.upload_count(t) - before[t] for t in (0, 1, 2)} == {0: 1, 1: 1, 2: 1}
    held = px4_vehicle.held(MAV_MISSION_TYPE_MISSION)
    assert_holds(held, m)
    assert compare_wire(mission_to_wire(m), held) == []
    assert compare_wire(fence_to_wire(m), px4_vehicle.held(MAV_MISSION_TYPE_FENCE)) == []
    assert compare_wire(rally_to_wire(m), px4_vehicle.held(MAV_MISSION_TYPE_RALLY)) == []
    # the autopilot took them: 2 inclusion zones, 2 exclusion zones, 2 rally points
    fence = px4_vehicle.autopilot.fence
    assert (len(fence.inclusion_polygons), len(fence.exclusion_polygons),
            len(fence.inclusion_circles), len(fence.exclusion_circles)) == (1, 1, 1, 1)
    assert len(px4_vehicle.autopilot.rally_enu) == 2
    # an independent read-back equals what was sent
    got = download_wire(url_of(px4_vehicle, backend), (0, 1, 2), config=ANSWERING)
    assert compare_wire(mission_to_wire(m), got[0]) == []
    assert compare_wire(fence_to_wire(m), got[1]) == []
    assert compare_wire(rally_to_wire(m), got[2]) == []
    back = wire_to_mission(got[0], home=m.home, fence=got[1], rally=got[2])
    assert back.polygons == m.polygons and back.circles == m.circles


@pytest.mark.parametrize("backend", BACKENDS)
def test_link_reuse_and_no_fence(px4_vehicle: RunningVehicle, backend: str) -> None:
    """Several uploads on one link; ``fence=False`` leaves fence and rally untouched."""
    with connected(url_of(px4_vehicle, backend), ANSWERING) as link:
        for n in (1, 7, 100):
            m = sample_mission(n)
            link.upload(mission_to_wire(m), MAV_MISSION_TYPE_MISSION)
            assert compare_wire(mission_to_wire(m), link.download(MAV_MISSION_TYPE_MISSION)) == []
    fence_uploads = px4_vehicle.upload_count(MAV_MISSION_TYPE_FENCE)
    m = sample_mission(3)
    report = upload_mission(m, url_of(px4_vehicle, backend), config=ANSWERING, fence=False)
    assert (report.items, report.fence_items, report.rally_items) == (len(m.items), 0, 0)
    assert px4_vehicle.upload_count(MAV_MISSION_TYPE_FENCE) == fence_uploads
    assert_holds(px4_vehicle.held(), m)


@pytest.mark.parametrize("backend", BACKENDS)
def test_empty_mission_clears(mavsdk_peer: MavsdkVehiclePeer, backend: str) -> None:
    """An empty mission is sent as MISSION_CLEAR_ALL (a MISSION_COUNT of 0 corrupts
    MAVSDK 4.1's MissionRawServer: this is why the check runs against it); the next
    upload still works."""
    url = url_of(mavsdk_peer, backend)
    with connected(url, ANSWERING) as link:
        link.upload(mission_to_wire(sample_mission(2)), MAV_MISSION_TYPE_MISSION)
        assert len(link.download(MAV_MISSION_TYPE_MISSION)) == 6
        report = upload_on_link(link, Mission(items=(), home=(36.7, -4.4, 100.0)))
        assert report == (0, 0, 0)
        assert link.download(MAV_MISSION_TYPE_MISSION) == []
        deadline = time.monotonic() + 1.0
        while mavsdk_peer.held() and time.monotonic() < deadline:
            time.sleep(0.01)
        assert mavsdk_peer.held() == []
        m = sample_mission(4)
        link.upload(fence_to_wire(m), MAV_MISSION_TYPE_FENCE)
        link.upload(mission_to_wire(m), MAV_MISSION_TYPE_MISSION)
        assert compare_wire(mission_to_wire(m), link.download(MAV_MISSION_TYPE_MISSION)) == []


# ---------------------------------------------------------------- errors


@pytest.mark.timeout(60)  # the connect bound holds: no hang (no timed assertion)
@pytest.mark.parametrize("backend", BACKENDS)
def test_no_vehicle(backend: str) -> None:
    port = free_udp_port()
    url = f"udpout:127.0.0.1:{port}" if backend == "pymavlink" else f"udpout://127.0.0.1:{port}"
    cfg = TransferConfig(connect_timeout_s=1.0)
    with pytest.raises(NoVehicleError, match=r"no vehicle heartbeat on .* within 1 s"):
        upload_mission(sample_mission(2), url, config=cfg)


def test_bad_urls() -> None:
    for url in ("udpout:localhost", "bogus://x", "udpin:127.0.0.1:notaport"):
        with pytest.raises(InvalidConnectionError):
            upload_mission(sample_mission(1), url, config=ANSWERING)
    with pytest.raises(NoVehicleError, match="Connection refused"):
        upload_mission(sample_mission(1), f"tcp:127.0.0.1:{free_udp_port()}", config=ANSWERING)


# MAV_MISSION_RESULT -> (name on the pymavlink path, MissionRawResult name MAVSDK reports)
NACKS = {
    1: ("MAV_MISSION_ERROR", "PROTOCOL_ERROR"),
    2: ("MAV_MISSION_UNSUPPORTED_FRAME", "UNSUPPORTED"),
    4: ("MAV_MISSION_NO_SPACE", "TOO_MANY_MISSION_ITEMS"),
    13: ("MAV_MISSION_INVALID_SEQUENCE", "INVALID_SEQUENCE"),
    14: ("MAV_MISSION_DENIED", "DENIED"),
    15: ("MAV_MISSION_OPERATION_CANCELLED", "TRANSFER_CANCELLED"),
}


@pytest.mark.parametrize("result", sorted(NACKS))
@pytest.mark.parametrize("backend", BACKENDS)
def test_nack_on_count(scripted_vehicle, backend: str, result: int) -> None:
    v = scripted_vehicle(VehicleScript(nack_on_count=result))
    with pytest.raises(MissionRejectedError) as info:
        upload_mission(sample_mission(5), url_of(v, backend), config=ANSWERING, fence=False)
    expected = NACKS[result][0 if backend == "pymavlink" else 1]
    assert info.value.result_name == expected
    assert expected in str(info.value)
    assert v.upload_count() == 0


@pytest.mark.parametrize("backend", BACKENDS)
def test_nack_mid_upload(scripted_vehicle, backend: str) -> None:
    v = scripted_vehicle(VehicleScript(nack_at_seq=3, nack_result=6))  # INVALID_PARAM1
    with pytest.raises(MissionRejectedError) as info:
        upload_mission(sample_mission(10), url_of(v, backend), config=ANSWERING, fence=False)
    assert info.value.result_name == ("MAV_MISSION_INVALID_PARAM1" if backend == "pymavlink"
                                      else "INVALID_ARGUMENT")
    assert v.items_received == 4 and v.upload_count() == 0


@pytest.mark.timeout(60)  # the transfer bound holds: no hang (no timed assertion)
@pytest.mark.parametrize("backend", BACKENDS)
def test_vehicle_goes_silent_mid_upload(scripted_vehicle, backend: str) -> None:
    v = scripted_vehicle(VehicleScript(silent_after_items=10))
    m = sample_mission(30)
    result = None
    with pytest.raises(UploadTimeoutError, match="the vehicle does not hold"):
        result = upload_mission(m, url_of(v, backend), config=SILENT, fence=False)
    assert result is None  # nothing reported as uploaded
    assert v.items_received == 10 and v.upload_count() == 0 and v.held() == []


def test_pymavlink_answers_legacy_mission_request(scripted_vehicle) -> None:
    v = scripted_vehicle(VehicleScript(legacy_requests=True))
    m = sample_mission(25)
    report = upload_mission(m, v.pymavlink_url, config=ANSWERING)
    assert report.items == len(m.items) and report.fence_items == 9
    assert_holds(v.held(), m)
    assert compare_wire(fence_to_wire(m), v.held(MAV_MISSION_TYPE_FENCE)) == []


@pytest.mark.parametrize("backend", BACKENDS)
def test_read_back_mismatch(scripted_vehicle, backend: str) -> None:
    v = scripted_vehicle(VehicleScript(download_x_offset_e7=1))
    m = sample_mission(4)
    with pytest.raises(VerifyMismatchError) as info:
        upload_mission(m, url_of(v, backend), config=ANSWERING, fence=False)
    assert info.value.differences == [f"item 0: x {m.items[0].x_e7 + 1} != sent {m.items[0].x_e7}"]


# ---------------------------------------------------------------- osa upload


@pytest.mark.parametrize(("backend", "suffix"), [("pymavlink", ".plan"),
                                                  ("mavsdk", ".waypoints")])
def test_osa_upload_end_to_end(tmp_path: Path, px4_vehicle: RunningVehicle, capsys,
                               backend: str, suffix: str) -> None:
    m, path = write_mission_file(sample_mission(15), tmp_path, suffix)
    status = osa_main(["upload", str(path), "--connection", url_of(px4_vehicle, backend),
                       *CLI_ANSWERING])
    out, err = capsys.readouterr()
    assert (status, err) == (0, "")
    assert f"mission items {len(m.items)}" in out and backend in out
    assert_holds(px4_vehicle.held(), m)


def test_osa_upload_failures(tmp_path: Path, capsys) -> None:
    path = tmp_path / "m.plan"
    write_plan(sample_mission(3), path)
    port = free_udp_port()
    status = osa_main(["upload", str(path), "--connection", f"udpout:127.0.0.1:{port}",
                       "--timeout", "0.5"])
    out, err = capsys.readouterr()
    assert status == 1 and out == ""
    assert err.count("\n") == 1 and err.startswith("osa upload: NoVehicleError: no vehicle")
    (tmp_path / "bad.plan").write_text("{")
    status = osa_main(["upload", str(tmp_path / "bad.plan"), "--connection", "udpout:x:1"])
    err = capsys.readouterr().err
    assert status == 2 and err.count("\n") == 1 and "malformed JSON" in err
    status = osa_main(["upload", str(path), "--connection", "nonsense://"])
    err = capsys.readouterr().err
    assert status == 2 and err.count("\n") == 1
    with pytest.raises(SystemExit) as info:
        osa_main(["upload", str(path), "--connection", "udpout:x:1", "--retries", "-1"])
    assert info.value.code == 2


def test_osa_upload_console_one_line(tmp_path: Path) -> None:
    """A real process: MAVSDK's C++ log must not leak onto stderr."""
    import subprocess
    import sys

    path = tmp_path / "m.plan"
    write_plan(sample_mission(3), path)
    root = Path(__file__).resolve().parents[2]
    proc = subprocess.run(
        [sys.executable, "-m", "envs.cli", "upload", str(path), "--connection",
         f"udpout://127.0.0.1:{free_udp_port()}", "--timeout", "0.5"],
        capture_output=True, text=True, timeout=30, cwd=root)
    assert proc.returncode == 1 and proc.stdout == ""
    assert proc.stderr.count("\n") == 1, proc.stderr
    assert proc.stderr.startswith("osa upload: NoVehicleError: no vehicle heartbeat")
