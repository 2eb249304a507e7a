"""ArduPilot numbering: home in seq 0, the mission from seq 1.

Against :class:`ArduPilotLikeVehicle` (heartbeat autopilot 3, overwrites seq 0 with
its own home) and, for the PX4-style side, ``osa vehicle``'s autopilot (heartbeat
autopilot 12) and MAVSDK's MissionRawServer (heartbeat autopilot 0), all on 127.0.0.1
with free ports."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterator
from pathlib import Path

import pytest

from envs.cli import main as osa_main
from planner.files import write_plan
from planner.mavlink import (
    MAV_AUTOPILOT_ARDUPILOTMEGA,
    TransferConfig,
    connected,
    resolve_autopilot,
    upload_mission,
    upload_on_link,
)
from planner.mavlink_wire import (
    UploadTimeoutError,
    VerifyMismatchError,
    WireItem,
    compare_wire,
    fence_to_wire,
    home_to_wire,
    mission_to_wire,
    rally_to_wire,
    wire_to_mission,
)
from planner.mission import (
    MAV_CMD_NAV_TAKEOFF,
    MAV_CMD_NAV_WAYPOINT,
    MAV_FRAME_GLOBAL,
    MAV_MISSION_TYPE_FENCE,
    MAV_MISSION_TYPE_MISSION,
    MAV_MISSION_TYPE_RALLY,
    Mission,
    MissionItem,
    deg_to_e7,
)
from tests.planner.conftest import (
    ANSWERING,
    CLI_ANSWERING,
    SILENT,
    sample_mission,
    write_mission_file,
)
from tests.planner.peers import ArduPilotLikeVehicle, MavsdkVehiclePeer, VehicleScript
from tests.vehicles import RunningVehicle

BACKENDS = ["pymavlink", "mavsdk"]
VEHICLE_HOME = (36.7201234, -4.4702345, 121.5)  # the vehicle's own home: not the plan's
MAV_CMD_DO_JUMP = 177


def url_of(peer, backend: str) -> str:
    return peer.pymavlink_url if backend == "pymavlink" else peer.mavsdk_url


@pytest.fixture
def ardupilot() -> Iterator[ArduPilotLikeVehicle]:
    with ArduPilotLikeVehicle(home=VEHICLE_HOME) as v:
        yield v


def assert_ardupilot_holds(held: list[WireItem], mission: Mission) -> None:
    """Vehicle home in seq 0, the mission's items in seq 1..n as AP_Mission stores them:
    float frame numbers (6 -> 3), centimetre altitudes, RTL without a position."""
    n = len(mission.items)
    assert [w.seq for w in held] == list(range(n + 1))
    home = held[0]
    assert (home.frame, home.command) == (MAV_FRAME_GLOBAL, MAV_CMD_NAV_WAYPOINT)
    assert (home.x, home.y, home.z) == (367201234, -44702345, 121.5)  # the vehicle's, not ours
    twin = {5: 0, 6: 3, 11: 10}
    for w, it in zip(held[1:], mission.items, strict=True):
        assert w.command == it.command
        assert math.isnan(w.param4) == math.isnan(it.param4)
        if it.command == 20 or 112 <= it.command < 160 or 176 <= it.command < 253:
            # RTL, CONDITION_*, DO_* (e.g. DO_CHANGE_SPEED): stored without a position
            assert (w.frame, w.x, w.y, w.z) == (0, 0, 0, 0.0)
            continue
        assert (w.x, w.y) == (it.x_e7, it.y_e7)
        assert w.frame == twin.get(it.frame, it.frame)
        assert abs(w.z - it.alt_m) <= 0.005 + 1e-9
    assert held[1].command == MAV_CMD_NAV_TAKEOFF


# ---------------------------------------------------------------- wire form


def test_ardupilot_wire_form() -> None:
    m = sample_mission(5)  # 9 items, home (36.7149123, -4.4781234, 108.25)
    px4 = mission_to_wire(m)
    ap = mission_to_wire(m, autopilot="ardupilot")
    assert len(px4) == 9 and len(ap) == 10
    assert [w.seq for w in ap] == list(range(10))
    assert [w.current for w in ap] == [1] + [0] * 9  # one current item: the home (as QGC)
    assert ap[0] == home_to_wire(m.home)
    assert (ap[0].frame, ap[0].command, ap[0].autocontinue) == (0, 16, 1)
    assert (ap[0].x, ap[0].y, ap[0].z) == (367149123, -44781234, 108.25)
    assert (ap[0].param1, ap[0].param2, ap[0].param3, ap[0].param4) == (0.0, 0.0, 0.0, 0.0)
    assert ap[1].command == MAV_CMD_NAV_TAKEOFF and ap[1].x == 367149123
    # the items themselves are unchanged, one seq later
    assert compare_wire([w.__class__(**{**w.__dict__, "seq": w.seq + 1}) for w in px4],
                        ap[1:]) == []
    # read-back: seq 0 counted but not compared
    other_home = WireItem(**{**ap[0].__dict__, "x": 1, "y": 2, "z": 3.0, "current": 0})
    assert compare_wire(ap, [other_home, *ap[1:]], skip_seq0=True) == []
    assert compare_wire(ap, [other_home, *ap[1:]]) == ["item 0: x 1 != sent 367149123",
                                                      "item 0: y 2 != sent -44781234",
                                                      "item 0: z 3.0 != sent 108.25"]
    assert compare_wire(ap, ap[:-1], skip_seq0=True) == ["vehicle holds 9 items, 10 were sent"]
    back = wire_to_mission([other_home, *ap[1:]], home=m.home, autopilot="ardupilot")
    assert compare_wire(mission_to_wire(back), px4) == []
    # fence and rally never get a home item
    assert fence_to_wire(m)[0].seq == 0 and rally_to_wire(m)[0].seq == 0


def test_do_jump_target_follows_the_shift() -> None:
    items = (MissionItem(command=MAV_CMD_NAV_TAKEOFF, lat_deg=36.7, lon_deg=-4.4, alt_m=30.0),
             MissionItem(lat_deg=36.701, lon_deg=-4.4, alt_m=30.0),
             MissionItem(lat_deg=36.702, lon_deg=-4.4, alt_m=30.0),
             MissionItem(command=MAV_CMD_DO_JUMP, frame=2, param1=1.0, param2=3.0))
    m = Mission(items=items, home=(36.7, -4.4, 100.0))
    assert mission_to_wire(m)[3].param1 == 1.0  # PX4: jump to seq 1 = item 1
    ap = mission_to_wire(m, autopilot="ardupilot")
    assert (ap[4].command, ap[4].param1, ap[4].param2) == (MAV_CMD_DO_JUMP, 2.0, 3.0)
    assert ap[2].x == deg_to_e7(36.701)  # seq 2 is still item 1
    assert wire_to_mission(ap, home=m.home, autopilot="ardupilot").items == items


def test_autopilot_choice() -> None:
    class Link:
        autopilot: int | None = None

    link = Link()
    for detected, numbering in ((3, "ardupilot"), (12, "px4"), (0, "px4"), (None, "px4")):
        link.autopilot = detected
        assert resolve_autopilot("auto", link) == numbering
        assert resolve_autopilot("px4", link) == "px4"
        assert resolve_autopilot("ardupilot", link) == "ardupilot"
    with pytest.raises(ValueError, match="autopilot must be one of"):
        TransferConfig(autopilot="apm")
    with pytest.raises(ValueError, match="mission numbering"):
        mission_to_wire(sample_mission(1), autopilot="auto")
    assert TransferConfig().autopilot == "auto"


# ---------------------------------------------------------------- to the ArduPilot-like vehicle


@pytest.mark.parametrize("backend", BACKENDS)
def test_upload_to_ardupilot_auto(ardupilot: ArduPilotLikeVehicle, backend: str) -> None:
    m = sample_mission(20)  # 24 items
    with connected(url_of(ardupilot, backend), ANSWERING) as link:
        assert link.autopilot == MAV_AUTOPILOT_ARDUPILOTMEGA  # from the heartbeat
    report = upload_mission(m, url_of(ardupilot, backend), config=ANSWERING)
    assert (report.items, report.fence_items, report.rally_items) == (24, 9, 2)
    assert report.autopilot == "ardupilot" and report.vehicle == (1, 1)
    held = ardupilot.held()
    assert len(held) == 25
    assert_ardupilot_holds(held, m)
    # what arrived in seq 0 before the vehicle replaced it: our home, as QGC sends it
    sent_home = ardupilot.received[MAV_MISSION_TYPE_MISSION][0]
    assert (sent_home.frame, sent_home.command, sent_home.current) == (0, 16, 1)
    assert (sent_home.x, sent_home.y, sent_home.z) == (367149123, -44781234, 108.25)
    assert [w.current for w in ardupilot.received[MAV_MISSION_TYPE_MISSION]] == [1] + [0] * 24
    # fence and rally: numbered from 0, no home item
    assert compare_wire(fence_to_wire(m), ardupilot.held(MAV_MISSION_TYPE_FENCE)) == []
    assert compare_wire(rally_to_wire(m), ardupilot.held(MAV_MISSION_TYPE_RALLY)) == []
    assert len(ardupilot.held(MAV_MISSION_TYPE_FENCE)) == 9


def test_empty_mission_to_ardupilot(ardupilot: ArduPilotLikeVehicle) -> None:
    """An empty mission is the home item alone (count 1); the report counts 0 items."""
    with connected(ardupilot.pymavlink_url, ANSWERING) as link:
        assert upload_on_link(link, sample_mission(3)) == (7, 9, 2)
        assert len(ardupilot.held()) == 8
        before = ardupilot.upload_count()
        assert upload_on_link(link, Mission(items=(), home=(36.7, -4.4, 100.0))) == (0, 0, 0)
    assert ardupilot.upload_count() == before + 1
    assert len(ardupilot.received[MAV_MISSION_TYPE_MISSION]) == 1
    assert [(w.seq, w.x) for w in ardupilot.held()] == [(0, 367201234)]


def test_ardupilot_mismatch_after_home(scripted_vehicle) -> None:
    """Only seq 0 is left out of the comparison: a changed seq 3 still fails."""
    with ArduPilotLikeVehicle(VehicleScript(download_x_offset_e7=5, download_x_offset_seq=3),
                              home=VEHICLE_HOME) as v:
        m = sample_mission(4)
        with pytest.raises(VerifyMismatchError) as info:
            upload_mission(m, v.pymavlink_url, config=ANSWERING, fence=False)
        x = m.items[2].x_e7
        assert info.value.differences == [f"item 3: x {x + 5} != sent {x}"]
        assert "rewrote item 0" not in str(info.value)


def test_ardupilot_silent_mid_upload_is_not_uploaded() -> None:
    with ArduPilotLikeVehicle(VehicleScript(silent_after_items=6), home=VEHICLE_HOME) as v:
        result = None
        # counted on the wire: home + 5 of the 25 mission items
        with pytest.raises(UploadTimeoutError, match="after 6 of 26 items"):
            result = upload_mission(sample_mission(21), v.pymavlink_url, config=SILENT,
                                    fence=False)
        assert result is None and v.upload_count() == 0
        assert [w.x for w in v.held()] == [367201234]  # still its home alone


@pytest.mark.parametrize(("backend", "suffix"), [("pymavlink", ".plan"),
                                                  ("mavsdk", ".waypoints")])
def test_osa_upload_to_ardupilot(tmp_path: Path, ardupilot: ArduPilotLikeVehicle, capsys,
                                 backend: str, suffix: str) -> None:
    m, path = write_mission_file(sample_mission(12), tmp_path, suffix)  # 16 items
    status = osa_main(["upload", str(path), "--connection", url_of(ardupilot, backend),
                       *CLI_ANSWERING])
    out, err = capsys.readouterr()
    assert (status, err) == (0, "")
    assert "mission items 16," in out and "ArduPilot numbering" in out and backend in out
    assert_ardupilot_holds(ardupilot.held(), m)


@pytest.mark.parametrize("backend", BACKENDS)
def test_forced_px4_on_ardupilot_fails_verify(tmp_path: Path, ardupilot: ArduPilotLikeVehicle,
                                              capsys, backend: str) -> None:
    """PX4 numbering to an ArduPilot: the takeoff goes to seq 0 and is replaced by the
    vehicle's home; the read-back catches it, exit 1, one line on stderr."""
    m = sample_mission(6)  # 10 items
    path = tmp_path / "m.plan"
    write_plan(m, path)
    status = osa_main(["upload", str(path), "--connection", url_of(ardupilot, backend),
                       *CLI_ANSWERING, "--no-fence", "--autopilot", "px4"])
    out, err = capsys.readouterr()
    assert status == 1 and out == ""
    assert err.count("\n") == 1
    assert err.startswith("osa upload: VerifyMismatchError: mission read back differs: item 0: ")
    assert "rewrote item 0" in err and "heartbeat says ArduPilot" in err
    held = ardupilot.held()
    assert len(held) == 10 and held[0].x == 367201234  # the takeoff is gone
    assert [(w.x, w.command) for w in held[1:]] == [(it.x_e7, it.command) for it in m.items[1:]]


def test_cli_autopilot_choices(tmp_path: Path) -> None:
    path = tmp_path / "m.plan"
    write_plan(sample_mission(1), path)
    with pytest.raises(SystemExit) as info:
        osa_main(["upload", str(path), "--connection", "udpout:x:1", "--autopilot", "apm"])
    assert info.value.code == 2


# ---------------------------------------------------------------- PX4-style vehicles


@pytest.fixture(scope="module")
def px4_peer() -> Iterator[MavsdkVehiclePeer]:
    with MavsdkVehiclePeer() as peer:
        yield peer


@pytest.mark.parametrize("backend", BACKENDS)
def test_px4_vehicle_is_not_ardupilot(px4_vehicle: RunningVehicle, backend: str) -> None:
    """``osa vehicle`` says autopilot 12 (PX4): "auto" keeps the mission from seq 0."""
    m = sample_mission(3)
    with connected(url_of(px4_vehicle, backend), ANSWERING) as link:
        assert link.autopilot == 12
        assert resolve_autopilot("auto", link) == "px4"
        assert upload_on_link(link, m, fence=False) == (7, 0, 0)
    held = px4_vehicle.held()
    assert len(held) == 7 and held[0].command == MAV_CMD_NAV_TAKEOFF


@pytest.mark.parametrize("backend", BACKENDS)
def test_mavsdk_server_is_not_ardupilot(px4_peer: MavsdkVehiclePeer, backend: str) -> None:
    """MAVSDK's server says autopilot 0 (generic): "auto" keeps the mission from seq 0
    too (any autopilot but ArduPilot numbers from seq 0)."""
    m = sample_mission(3)
    before = px4_peer.upload_count()
    with connected(url_of(px4_peer, backend), ANSWERING) as link:
        assert link.autopilot == 0
        assert resolve_autopilot("auto", link) == "px4"
        assert upload_on_link(link, m, fence=False) == (7, 0, 0)
    # MAVSDK's server hands the mission over in a callback after its ACK: wait for it
    held = px4_peer.wait_for_upload(after=before, timeout_s=5.0)
    assert len(held) == 7 and held[0].command == MAV_CMD_NAV_TAKEOFF


def test_forced_ardupilot_on_px4_sends_home_item(px4_vehicle: RunningVehicle) -> None:
    """Forcing ArduPilot numbering on a PX4 vehicle stores the home item as seq 0:
    a real waypoint there (documented; the verify cannot tell)."""
    m = sample_mission(3)
    report = upload_mission(m, px4_vehicle.pymavlink_url, config=ANSWERING, fence=False,
                            autopilot="ardupilot")
    assert report.autopilot == "ardupilot" and report.items == 7
    held = px4_vehicle.held()
    assert len(held) == 8
    assert (held[0].frame, held[0].command, held[0].x) == (0, 16, 367149123)
    assert held[1].command == MAV_CMD_NAV_TAKEOFF


def test_link_config_autopilot_is_used(ardupilot: ArduPilotLikeVehicle) -> None:
    """``upload_on_link`` without ``autopilot`` takes the link's TransferConfig."""
    cfg = dataclasses.replace(ANSWERING, autopilot="px4")
    with connected(ardupilot.pymavlink_url, cfg) as link:
        with pytest.raises(VerifyMismatchError, match="rewrote item 0"):
            upload_on_link(link, sample_mission(2), fence=False)
        assert upload_on_link(link, sample_mission(2), fence=False, autopilot="auto") == (6, 0, 0)


def test_compare_wire_accepts_storage_forms_only():
    from dataclasses import replace

    from planner.mavlink_wire import compare_wire

    wp = WireItem(seq=1, frame=6, command=16, current=0, autocontinue=1, param1=0.0,
                  param2=0.0, param3=0.0, param4=float("nan"), x=367150000, y=-44780000,
                  z=45.004, mission_type=0)
    rtl = replace(wp, seq=2, command=20, x=367150000, y=-44780000, z=0.0)
    home = replace(wp, seq=0, frame=0)
    sent = [home, wp, rtl]
    # ArduPilot: float frame twin, centimetre altitude, RTL without position: identical
    held = [home, replace(wp, frame=3, z=45.0), replace(rtl, frame=0, x=0, y=0)]
    assert compare_wire(sent, held, skip_seq0=True) == []
    # PX4 numbering keeps the 1 mm altitude tolerance
    assert any("z" in d for d in compare_wire(sent, held, skip_seq0=False))
    # a different reference is a different mission
    assert compare_wire(sent, [home, replace(wp, frame=11), rtl], skip_seq0=True) == [
        "item 1: frame 11 != sent 6"]
    assert compare_wire(sent, [home, replace(wp, x=wp.x + 1), rtl], skip_seq0=True) == [
        f"item 1: x {wp.x + 1} != sent {wp.x}"]
