"""The virtual vehicle against a pymavlink ground station on 127.0.0.1.

Identity and requests (heartbeat, AUTOPILOT_VERSION, parameters, message intervals,
command results), then a whole mission flown over MAVLink: every item reached in
order (with a DO_JUMP lap), the reported positions on the planned legs, and the
phone's log replayed to the responder."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
from pymavlink.dialects.v20.common import MAV_PARAM_TYPE_REAL32

from envs.cli import main as osa_main
from envs.vehicle.px4 import Mode
from estimator.replay import ReplayOptions, replay_logs
from planner.mavlink import TransferConfig, upload_mission
from planner.mission import (
    MAV_CMD_DO_JUMP,
    MAV_CMD_NAV_RETURN_TO_LAUNCH,
    MAV_CMD_NAV_TAKEOFF,
    Mission,
    MissionItem,
)
from tests.envs.vehicle.helpers import SEARCH_SCENARIO, Gcs
from tests.vehicles import running_vehicle

FAST = TransferConfig(connect_timeout_s=3.0, message_timeout_s=0.2, retries=5)
RESULT_ACCEPTED, RESULT_DENIED, RESULT_UNSUPPORTED = 0, 2, 3


def test_identity_commands_and_parameters() -> None:
    with running_vehicle(SEARCH_SCENARIO, speedup=2.0) as rv:
        gcs = Gcs(rv.pymavlink_url)
        try:
            hb = gcs.vehicle_heartbeat
            assert (hb.type, hb.autopilot, hb.system_status) == (2, 12, 3)  # quad, PX4, standby
            assert hb.custom_mode == Mode.LOITER.custom_mode == 0x03040000
            assert hb.base_mode & 1 and not hb.base_mode & 128  # custom mode, disarmed
            # AUTOPILOT_VERSION on request (MAVSDK asks for it)
            assert gcs.command(512, 148) == RESULT_ACCEPTED
            av = gcs.wait("AUTOPILOT_VERSION")
            # MISSION_INT, COMMAND_INT, MAVLINK2, fence, rally
            for cap in (4, 8, 8192, 16384, 32768):
                assert av.capabilities & cap
            assert av.flight_sw_version >> 16 == 0x010E  # 1.14
            assert gcs.command(512, 9999) == RESULT_UNSUPPORTED
            assert gcs.command(31000) == RESULT_UNSUPPORTED
            assert gcs.command(176, 1, 1, 0) == RESULT_DENIED  # MANUAL: needs sticks
            assert gcs.command(176, 1, 4, 4) == 1  # AUTO.MISSION without a mission: TEMP_REJ
            # SET_MODE is answered with a DO_SET_MODE ack, the heartbeat follows
            gcs.conn.mav.set_mode_send(1, 1, Mode.POSCTL.custom_mode)
            assert gcs.wait("COMMAND_ACK", where=lambda m: m.command == 176).result == 0
            hb = gcs.wait("HEARTBEAT", where=lambda m: m.get_srcSystem() == 1
                          and m.custom_mode == Mode.POSCTL.custom_mode)
            assert gcs.command(176, 1, 4, 3) == RESULT_ACCEPTED  # back to AUTO.LOITER
            # home at the scenario's [search] start
            assert gcs.command(410) == RESULT_ACCEPTED
            home = gcs.wait("HOME_POSITION")
            ap = rv.autopilot
            e, n = rv.vehicle.scenario.start_enu_m(0)
            assert math.hypot(ap.home.enu[0] - e, ap.home.enu[1] - n) < 10.0  # GNSS bias
            assert home.latitude == round(ap.home.lat_deg * 1e7)
            # parameters: the list, a read, a set
            gcs.conn.mav.param_request_list_send(1, 1)
            names = set()
            for _ in range(len(ap.params)):
                pv = gcs.wait("PARAM_VALUE")
                names.add(pv.param_id)
                assert pv.param_count == len(ap.params)
            assert names == {s.name for s in ap.params.specs}
            gcs.conn.mav.param_set_send(1, 1, b"MIS_TAKEOFF_ALT", 7.0, MAV_PARAM_TYPE_REAL32)
            pv = gcs.wait("PARAM_VALUE", where=lambda m: m.param_id == "MIS_TAKEOFF_ALT")
            assert pv.param_value == 7.0 and ap.params["MIS_TAKEOFF_ALT"] == 7.0
            # every telemetry message arrives
            seen = {m.get_type() for m in gcs.collect(3.0)}
            assert {"GLOBAL_POSITION_INT", "GPS_RAW_INT", "SYS_STATUS", "EXTENDED_SYS_STATE",
                    "ATTITUDE", "MISSION_CURRENT", "HOME_POSITION", "HEARTBEAT",
                    "VFR_HUD", "BATTERY_STATUS"} <= seen
            ess = [m for m in gcs.messages if m.get_type() == "EXTENDED_SYS_STATE"]
            assert ess[-1].landed_state == 1  # on the ground
            gps = [m for m in gcs.messages if m.get_type() == "GPS_RAW_INT"][-1]
            assert gps.fix_type == 3 and gps.satellites_visible > 5
        finally:
            gcs.close()


def test_message_intervals_follow_the_simulated_clock() -> None:
    with running_vehicle(SEARCH_SCENARIO, speedup=10.0) as rv:
        gcs = Gcs(rv.pymavlink_url)
        try:
            assert gcs.command(511, 33, 1e6) == RESULT_ACCEPTED  # 1 Hz of simulated time
            gcs.collect(0.3)
            pos = [m for m in gcs.collect(2.0) if m.get_type() == "GLOBAL_POSITION_INT"]
            span_s = (pos[-1].time_boot_ms - pos[0].time_boot_ms) / 1000.0
            assert span_s > 10.0
            assert len(pos) - 1 == pytest.approx(span_s, abs=1.5)
            assert gcs.command(510, 33) == RESULT_ACCEPTED
            assert gcs.wait("MESSAGE_INTERVAL").interval_us == 1_000_000
            assert gcs.command(511, 33, -1) == RESULT_ACCEPTED  # stop it
            gcs.collect(0.3)
            assert not [m for m in gcs.collect(1.0) if m.get_type() == "GLOBAL_POSITION_INT"]
            assert gcs.command(511, 33, 0) == RESULT_ACCEPTED  # the default: 5 Hz
            gcs.collect(0.3)
            pos = [m for m in gcs.collect(2.0) if m.get_type() == "GLOBAL_POSITION_INT"]
            span_s = (pos[-1].time_boot_ms - pos[0].time_boot_ms) / 1000.0
            assert (len(pos) - 1) / span_s == pytest.approx(5.0, rel=0.2)
            assert gcs.command(511, 9999, 1e6) == RESULT_UNSUPPORTED
        finally:
            gcs.close()


def _orbit_mission(rv, center_enu: tuple[float, float], radius: float, alt: float,
                   corners: int = 12) -> tuple[Mission, list[tuple[float, float]]]:
    frame = rv.autopilot.frame
    home = rv.autopilot.home
    pts = [(center_enu[0] + radius * math.cos(2 * math.pi * k / corners),
            center_enu[1] + radius * math.sin(2 * math.pi * k / corners))
           for k in range(corners)]
    items = [MissionItem(command=MAV_CMD_NAV_TAKEOFF, lat_deg=home.lat_deg,
                         lon_deg=home.lon_deg, alt_m=alt)]
    for e, n in pts:
        lat, lon, _ = frame.to_geodetic(e, n, home.enu[2])
        items.append(MissionItem(lat_deg=float(lat), lon_deg=float(lon), alt_m=alt))
    items.append(MissionItem(command=MAV_CMD_DO_JUMP, frame=2, param1=1.0, param2=1.0))
    items.append(MissionItem(command=MAV_CMD_NAV_RETURN_TO_LAUNCH))
    return Mission(items=tuple(items), home=(home.lat_deg, home.lon_deg, home.alt_m)), pts


def _segment_distance(p, a, b) -> float:
    ax, ay = b[0] - a[0], b[1] - a[1]
    L2 = ax * ax + ay * ay
    f = 0.0 if L2 == 0 else max(0.0, min(1.0, ((p[0] - a[0]) * ax + (p[1] - a[1]) * ay) / L2))
    return math.hypot(p[0] - a[0] - f * ax, p[1] - a[1] - f * ay)


def test_fly_a_mission_over_mavlink_and_replay_the_log(tmp_path: Path) -> None:
    log = tmp_path / "flight.jsonl"
    with running_vehicle(SEARCH_SCENARIO, speedup=40.0, log_path=log) as rv:
        ap = rv.autopilot
        ap1f = rv.vehicle.realisation.world.responder("AP_1F")
        mission, pts = _orbit_mission(rv, (ap1f.e_m, ap1f.n_m), 45.0, 40.0)
        report = upload_mission(mission, rv.pymavlink_url, config=FAST)
        assert report.items == 15 and report.autopilot == "px4"
        gcs = Gcs(rv.pymavlink_url)
        try:
            assert gcs.command(400, 1) == RESULT_ACCEPTED  # arm
            assert gcs.command(300, 0, 0) == RESULT_ACCEPTED  # MAV_CMD_MISSION_START
            msgs = gcs.collect(90.0, until=lambda m: m.get_type() == "HEARTBEAT"
                               and m.get_srcSystem() == 1 and not m.base_mode & 128)
        finally:
            gcs.close()
        frame = ap.frame
        home = ap.home
        x, y, z = ap.vehicle.state.position_m
        agl_end = z - float(ap.world.ground_m(x, y))
    hb = msgs[-1]
    assert hb.get_type() == "HEARTBEAT" and not hb.base_mode & 128, "never disarmed"
    reached = [m.seq for m in msgs if m.get_type() == "MISSION_ITEM_REACHED"]
    lap = list(range(1, 13))
    assert reached == [0, *lap, *lap, 14]  # DO_JUMP (13) once more, never reached itself
    # the reported positions during the laps lie on the legs of the 12-gon
    legs = [(pts[k], pts[(k + 1) % 12]) for k in range(12)]
    i0 = next(k for k, m in enumerate(msgs) if m.get_type() == "MISSION_ITEM_REACHED"
              and m.seq == 1)
    i1 = max(k for k, m in enumerate(msgs) if m.get_type() == "MISSION_ITEM_REACHED"
             and m.seq == 12)
    on_laps = []
    for m in msgs[i0:i1]:
        if m.get_type() != "GLOBAL_POSITION_INT":
            continue
        e, n, _ = frame.to_enu(m.lat / 1e7, m.lon / 1e7, m.alt / 1e3)
        on_laps.append(min(_segment_distance((float(e), float(n)), a, b) for a, b in legs))
        assert m.relative_alt / 1e3 == pytest.approx(40.0, abs=1.5)
    assert len(on_laps) > 50
    # corners are cut inside the acceptance radius (2 m): no report farther off a leg
    assert max(on_laps) < ap.params["NAV_ACC_RAD"]
    # the last report: landed at home
    last = [m for m in msgs if m.get_type() == "GLOBAL_POSITION_INT"][-1]
    e, n, _ = frame.to_enu(last.lat / 1e7, last.lon / 1e7, last.alt / 1e3)
    assert math.hypot(e - home.enu[0], n - home.enu[1]) < 2.0
    assert abs(last.relative_alt) < 5000  # GNSS altitude drift since arming
    assert [m.landed_state for m in msgs if m.get_type() == "EXTENDED_SYS_STATE"][-1] == 1
    assert abs(agl_end) < 0.1  # on the true terrain
    # the phone's log, written as it flew, replays to the responder
    rep = replay_logs([str(log)], ReplayOptions(modes=("baseline",), keep_history=False))
    tr = {t.bssid: t for t in rep.tracks}[ap1f.bssid]
    assert tr.status == "converged"
    assert tr.err_h_m is not None and tr.err_h_m < 3.0


def test_osa_plan_and_upload_to_the_vehicle(tmp_path: Path, capsys) -> None:
    with running_vehicle(SEARCH_SCENARIO) as rv:
        home = rv.autopilot.home
        plan = tmp_path / "helix.plan"
        assert osa_main(["plan", "helix", "--center", f"{home.lat_deg:.6f},{home.lon_deg:.6f}",
                         "--radius", "40", "--alt", "40", "-o", str(plan)]) == 0
        capsys.readouterr()
        status = osa_main(["upload", str(plan), "--connection", rv.pymavlink_url,
                           "--timeout", "3", "--message-timeout", "0.2"])
        out, err = capsys.readouterr()
        assert (status, err) == (0, "")
        assert "uploaded and verified" in out and "mission from seq 0" in out
        n = int(out.split("mission items ")[1].split(",")[0])
        assert len(rv.held()) == n > 10


def test_a_speedup_it_cannot_keep_up_with_is_reported() -> None:
    """Asked for more than the loop can do, the vehicle says so and runs as fast as it
    can (it re-bases its clock instead of trying to catch up). On a simulated wall
    clock (each reading 20 ms after the last: the loop's work takes time), run in this
    thread: the same numbers whatever the machine's load."""
    import itertools

    from envs.vehicle import VirtualVehicle
    from sim import load_scenario
    from tests.net import free_udp_port

    readings = itertools.count()
    said: list[str] = []
    v = VirtualVehicle(load_scenario(SEARCH_SCENARIO), [f"udpin:127.0.0.1:{free_udp_port()}"],
                       speedup=1e6, status=said.append,
                       wall_clock=lambda: next(readings) * 0.02)
    after: list[tuple[float, float]] = []  # (simulated, wall) once it said so

    def should_stop() -> bool:
        if said:
            after.append((v.t_s, v.stats.wall_s))
        return len(after) > 5

    try:
        v.run(should_stop)
    finally:
        v.close()
    assert said and said[0].startswith("cannot keep up with --speedup 1e+06: simulated time ran")
    assert "it runs as fast as it can" in said[0]
    assert v.stats.behind_events > 0
    (t0, w0), (t1, w1) = after[0], after[-1]
    rate = (t1 - t0) / (w1 - w0)
    # as fast as it can: a step of 1 simulated second costs about two readings of the
    # clock, so about 25x, far below the ask; and on, never stalled
    assert 10.0 < rate < 100.0
    assert all(b[0] > a[0] for a, b in itertools.pairwise(after))


def test_a_vehicle_left_running_keeps_no_phone_records(tmp_path: Path) -> None:
    """The phone's records leave the vehicle as they are delivered (the log, the relay)
    and are not kept: a vehicle left running does not grow with them (the stepper kept
    every record and measurement step: about 50 MB per simulated hour)."""
    import json
    import math as m

    from tests.envs.vehicle.helpers import until

    log = tmp_path / "phone.jsonl"
    with running_vehicle(SEARCH_SCENARIO, speedup=m.inf, log_path=log) as rv:
        def kinds() -> list[str]:
            text = log.read_text()
            return [json.loads(x)["type"] for x in text[: text.rfind("\n") + 1].splitlines()]

        assert until(lambda: kinds().count("gnss") > 300 and "rtt" in kinds(), 60.0)
        a = rv.vehicle.stepper.agents[0]
        assert (a.emitted, a.gnss_steps, a.ftm_steps) == ([], [], [])


def test_gps_raw_int_says_accuracy_and_dop_apart() -> None:
    """GPS_RAW_INT carries the phone's fix accuracy in its accuracy fields (h_acc, v_acc,
    mm) and in eph and epv a dilution of precision (x 100), the GNSS model's own:
    sqrt(sats_ref / satellites) horizontally (1.0 at the reference count), x vacc_ratio
    vertically. eph and epv used to carry the accuracy in cm, which ground stations show
    as an HDOP (0.01 with RTK)."""
    with running_vehicle(SEARCH_SCENARIO, speedup=5.0) as rv:
        cfg = rv.vehicle.scenario.agents[0].gnss
        gcs = Gcs(rv.pymavlink_url)
        try:
            for _ in range(3):
                gps = gcs.wait("GPS_RAW_INT", 20.0, where=lambda m: m.fix_type == 3)
                hdop = math.sqrt(cfg.sats_ref / gps.satellites_visible)
                assert gps.eph == round(100 * hdop)
                assert gps.epv == round(100 * hdop * cfg.vacc_ratio)
                assert 0 < gps.h_acc < 20_000 and gps.h_acc < gps.v_acc < 40_000  # mm
        finally:
            gcs.close()


def test_a_plan_without_fence_or_rally_clears_the_vehicles(tmp_path: Path, capsys) -> None:
    """``osa upload`` of a ``.plan`` makes the vehicle hold exactly the file: a plan
    whose geoFence and rallyPoints are empty clears the fence and rally points a
    previous plan left (they used to stay, under a line saying 'fence items 0, rally
    points 0', exit 0: a return flew to the old site's rally point). A ``.waypoints``
    file cannot hold a fence: it leaves the vehicle's as they are. With a MAVSDK URL
    (MissionRaw cannot clear rally points) rally points held are one line, exit 1."""
    import json

    with running_vehicle(SEARCH_SCENARIO) as rv:
        home = rv.autopilot.home
        lat, lon = home.lat_deg, home.lon_deg
        old = tmp_path / "old.plan"
        assert osa_main(["plan", "helix", "--center", f"{lat:.6f},{lon:.6f}", "--radius",
                         "40", "--alt", "40", "-o", str(old),
                         "--keep-out", f"{lat + 0.002:.6f},{lon:.6f},15"]) == 0
        data = json.loads(old.read_text())
        data["rallyPoints"]["points"] = [[lat + 0.001, lon, 30.0]]
        old.write_text(json.dumps(data))
        new = tmp_path / "new.plan"
        data["geoFence"]["circles"], data["rallyPoints"]["points"] = [], []
        new.write_text(json.dumps(data))
        wpl = tmp_path / "new.waypoints"
        assert osa_main(["plan", "helix", "--center", f"{lat:.6f},{lon:.6f}", "--radius",
                         "30", "--alt", "40", "-o", str(wpl)]) == 0
        url = ["--connection", rv.pymavlink_url, "--timeout", "3", "--message-timeout", "0.2"]

        def upload(path: Path, link: list[str] = url) -> tuple[int, str, str]:
            capsys.readouterr()
            status = osa_main(["upload", str(path), *link])
            out, err = capsys.readouterr()
            return status, out, err

        assert upload(old)[0] == 0
        assert (len(rv.held(1)), len(rv.held(2))) == (1, 1)
        status, out, err = upload(new)
        assert (status, err) == (0, "") and "fence items 0, rally points 0" in out
        assert (len(rv.held(1)), len(rv.held(2))) == (0, 0)
        assert upload(old)[0] == 0
        status, out, err = upload(wpl)
        assert (status, err) == (0, "")
        assert (len(rv.held(1)), len(rv.held(2))) == (1, 1)  # WPL: no fence to replace
        mavsdk = ["--connection", rv.mavsdk_url, "--timeout", "10", "--message-timeout", "0.5"]
        status, out, err = upload(new, mavsdk)
        assert status == 1 and err.count("\n") == 1 and "1 rally point" in err, err
        assert len(rv.held(1)) == 0  # the fence cleared (MAVSDK's Geofence plugin)
