"""The vehicle's side of the MAVLink terrain protocol and items above the terrain.

Against a pymavlink ground station on 127.0.0.1: TERRAIN_CHECK at several points is
answered with the ground's height there (against the terrain evaluated independently:
ENU points put on the ground with ``height_m`` and converted with the world frame) and
the vehicle's height above it, nothing pending; a point beyond the database is
unavailable (spacing 0); TERRAIN_REPORT for its own position comes about once a
simulated second; TERRAIN_REQUEST is answered with the blocks of its mask; TERRAIN_DATA
changes nothing. A frame-11 mission over the hills is flown at its height above the
ground, along the legs too: within 1 m of it with RTK GNSS (measured within 0.3 m), and
the autopilot's own height above the ground (from its estimate) within 1 m with
standalone GNSS, whose vertical error the true height then carries. On a DEM site the
reports are the GeoTIFF's own heights, computed by hand with rasterio and pyproj, and
where the DEM gives none the answer is "no data" (spacing 0)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pymavlink.dialects.v20.common import (
    MAV_CMD_COMPONENT_ARM_DISARM,
    MAV_CMD_DO_REPOSITION,
    MAV_CMD_MISSION_START,
    MAV_CMD_NAV_LAND,
    MAV_CMD_NAV_LOITER_TURNS,
    MAV_CMD_NAV_RALLY_POINT,
    MAV_CMD_NAV_TAKEOFF,
    MAV_FRAME_GLOBAL_TERRAIN_ALT,
    MAV_FRAME_GLOBAL_TERRAIN_ALT_INT,
    MAV_MISSION_ACCEPTED,
    MAV_MISSION_TYPE_RALLY,
    MAV_PROTOCOL_CAPABILITY_TERRAIN,
    MAV_RESULT_ACCEPTED,
)

from envs.vehicle.mission import check_item
from envs.vehicle.px4 import Mode
from planner.mavlink import TransferConfig, upload_mission
from planner.mission import Mission, MissionItem, deg_to_e7
from tests.envs.vehicle.helpers import (
    SEARCH_SCENARIO,
    Gcs,
    fly,
    item,
    make_autopilot,
    numbered,
    true_agl,
    until,
)
from tests.vehicles import running_vehicle

RTK_SCENARIO = SEARCH_SCENARIO.replace("search-ap1f.toml", "search-ap1f-rtk.toml")
FAST = TransferConfig(connect_timeout_s=3.0, message_timeout_s=0.2, retries=5)
# a tour over three-aps' hills (world ENU metres): up the 28 m hill, across, down the slope
TOUR_ENU = [(-260.0, 100.0), (-260.0, 300.0), (0.0, 330.0), (260.0, 320.0), (200.0, -200.0)]
AGL_M = 15.0


def _ground_geodetic(world, e: float, n: float) -> tuple[float, float, float]:
    """(lat, lon, height) of the ground at ENU (e, n), evaluated independently."""
    lat, lon, h = world.frame.to_geodetic(e, n, float(world.terrain.height_m(e, n)))
    return float(lat), float(lon), float(h)


def test_terrain_check_report_request_and_data() -> None:
    with running_vehicle(SEARCH_SCENARIO, speedup=10.0) as rv:
        world = rv.vehicle.realisation.world
        gcs = Gcs(rv.pymavlink_url)
        try:
            pos = gcs.wait("GLOBAL_POSITION_INT")
            for e, n in ((0.0, 0.0), (-260.0, 260.0), (120.0, -220.0), (850.0, -40.0),
                         (-3000.0, 4000.0)):
                lat, lon, h = _ground_geodetic(world, e, n)
                gcs.conn.mav.terrain_check_send(deg_to_e7(lat), deg_to_e7(lon))
                where = (deg_to_e7(lat), deg_to_e7(lon))
                r = gcs.wait("TERRAIN_REPORT", where=lambda m, w=where: (m.lat, m.lon) == w)
                assert r.terrain_height == pytest.approx(h, abs=0.01)  # (1e-7 deg: 1 cm)
                assert (r.spacing, r.pending) == (100, 0) and r.loaded > 0
                # its own height above that ground: its altitude minus the ground's
                pos = [m for m in gcs.messages if m.get_type() == "GLOBAL_POSITION_INT"][-1]
                assert r.current_height == pytest.approx(pos.alt / 1e3 - h, abs=0.5)
            # beyond the database (30 km from the origin): unavailable
            lat, lon, _ = world.frame.to_geodetic(30_000.0, 0.0, 0.0)
            gcs.conn.mav.terrain_check_send(deg_to_e7(lat), deg_to_e7(lon))
            r = gcs.wait("TERRAIN_REPORT", where=lambda m: m.lat == deg_to_e7(lat))
            assert r.spacing == 0
            # its own position about once a simulated second, the ground under it
            gcs.collect(0.2)
            gcs.messages.clear()
            first = gcs.wait("GLOBAL_POSITION_INT").time_boot_ms
            gcs.collect(60.0, until=lambda m: m.get_type() == "GLOBAL_POSITION_INT"
                        and m.time_boot_ms - first >= 12_000)  # 12 simulated seconds
            own = [m for m in gcs.messages if m.get_type() == "TERRAIN_REPORT"]
            pos = [m for m in gcs.messages if m.get_type() == "GLOBAL_POSITION_INT"]
            span_s = (pos[-1].time_boot_ms - pos[0].time_boot_ms) / 1e3
            assert span_s >= 12.0
            assert len(own) == pytest.approx(span_s, abs=2.0)
            for r in own[-3:]:
                assert abs(r.lat - pos[-1].lat) < 100 and abs(r.lon - pos[-1].lon) < 100
                e, n, _ = world.frame.to_enu(r.lat / 1e7, r.lon / 1e7, pos[-1].alt / 1e3)
                assert r.terrain_height == pytest.approx(_ground_geodetic(world, e, n)[2],
                                                         abs=0.05)
                # landed: its estimate's height above the ground is the GNSS error (m)
                assert abs(r.current_height) < 10.0
            # TERRAIN_REQUEST: the blocks of its mask, 4 x 4 heights from the SW corner
            lat0, lon0, _ = _ground_geodetic(world, -100.0, -100.0)
            e0, n0, _ = world.frame.to_enu(lat0, lon0, 0.0)
            spacing, bits = 30, (0, 9, 55)
            gcs.conn.mav.terrain_request_send(deg_to_e7(lat0), deg_to_e7(lon0), spacing,
                                              sum(1 << b for b in bits))
            blocks = {}
            while len(blocks) < len(bits):
                m = gcs.wait("TERRAIN_DATA")
                blocks[m.gridbit] = m
            assert sorted(blocks) == list(bits)
            for b, m in blocks.items():
                assert (m.lat, m.lon, m.grid_spacing) == (deg_to_e7(lat0), deg_to_e7(lon0),
                                                          spacing)
                for i, got in enumerate(m.data):
                    e = e0 + 4 * spacing * (b % 8) + spacing * (i % 4)
                    n = n0 + 4 * spacing * (b // 8) + spacing * (i // 4)
                    assert abs(got - _ground_geodetic(world, e, n)[2]) <= 0.55
            # TERRAIN_DATA: accepted, no effect
            lat, lon, h = _ground_geodetic(world, 0.0, 0.0)
            gcs.conn.mav.terrain_data_send(deg_to_e7(lat), deg_to_e7(lon), 30, 0, [999] * 16)
            assert until(lambda: rv.vehicle.terrain_data_ignored == 1, 10.0)
            gcs.conn.mav.terrain_check_send(deg_to_e7(lat), deg_to_e7(lon))
            r = gcs.wait("TERRAIN_REPORT", where=lambda m: m.lat == deg_to_e7(lat)
                         and m.lon == deg_to_e7(lon))
            assert r.terrain_height == pytest.approx(h, abs=0.01)
            # AUTOPILOT_VERSION says it speaks the terrain protocol
            assert gcs.command(512, 148) == MAV_RESULT_ACCEPTED
            assert gcs.wait("AUTOPILOT_VERSION").capabilities & MAV_PROTOCOL_CAPABILITY_TERRAIN
        finally:
            gcs.close()


def _tour(ap, frame: int = MAV_FRAME_GLOBAL_TERRAIN_ALT_INT) -> list:
    h = ap.home.enu
    return numbered([item(ap, MAV_CMD_NAV_TAKEOFF, 0, 0, AGL_M, frame=frame)]
                    + [item(ap, e=e - h[0], n=n - h[1], alt=AGL_M, frame=frame)
                       for e, n in TOUR_ENU]
                    + [item(ap, MAV_CMD_NAV_LAND, 0, 0, 0.0)])


@pytest.mark.parametrize(("scenario", "frame"), [(RTK_SCENARIO, MAV_FRAME_GLOBAL_TERRAIN_ALT_INT),
                                                 (SEARCH_SCENARIO, MAV_FRAME_GLOBAL_TERRAIN_ALT)])
def test_terrain_items_are_flown_above_the_ground_along_the_legs(scenario: str,
                                                                  frame: int) -> None:
    ap = make_autopilot(scenario, seed=1)
    ap.set_mission(_tour(ap, frame))
    ap.set_mode(Mode.MISSION)
    ap.arm()
    s = fly(ap, 1500.0, until=lambda a: not a.armed)
    assert [r[0] for r in ap.reached_log] == list(range(len(TOUR_ENU) + 2))
    assert not ap.armed and abs(true_agl(ap, s[-1])) < 0.1
    t0, t1 = ap.reached_log[1][1], ap.reached_log[len(TOUR_ENU)][1]
    legs = [x for x in s if t0 <= x.t_s <= t1]
    h = ap.home.enu
    ground = [ap.ground_m(x.pos[0] + h[0], x.pos[1] + h[1]) for x in legs]
    assert max(ground) - min(ground) > 40.0  # the hills it crossed
    own = [x.pos[2] + h[2] - g - AGL_M for x, g in zip(legs, ground, strict=True)]
    assert max(abs(d) for d in own) < 1.0  # the autopilot's height above the ground
    if scenario == RTK_SCENARIO:  # (standalone: the true height carries the GNSS error)
        assert max(abs(true_agl(ap, x) - AGL_M) for x in legs) < 1.0


def test_terrain_loiter_rally_and_reposition() -> None:
    ap = make_autopilot(RTK_SCENARIO)
    h = ap.home.enu
    # a rally point above the terrain is accepted (it can be flown)
    rally = item(ap, MAV_CMD_NAV_RALLY_POINT, 50, 50, 20.0, frame=MAV_FRAME_GLOBAL_TERRAIN_ALT_INT,
                 mission_type=MAV_MISSION_TYPE_RALLY)
    assert check_item(rally, 1) == MAV_MISSION_ACCEPTED
    ap.set_rally([rally])
    r = ap.rally_enu[0]
    assert r[2] - ap.ground_m(r[0], r[1]) == pytest.approx(20.0, abs=1e-6)
    # loiter turns about the 28 m hill's flank: the circle follows the ground
    c = (-260.0 - h[0], 150.0 - h[1])
    ap.set_mission(numbered([
        item(ap, MAV_CMD_NAV_TAKEOFF, 0, 0, AGL_M, frame=MAV_FRAME_GLOBAL_TERRAIN_ALT_INT),
        item(ap, MAV_CMD_NAV_LOITER_TURNS, *c, AGL_M, frame=MAV_FRAME_GLOBAL_TERRAIN_ALT_INT,
             p1=1.0, p3=60.0)]))
    ap.set_mode(Mode.MISSION)
    ap.arm()
    s = fly(ap, 900.0, until=lambda a: len(a.reached_log) >= 2)
    assert [r[0] for r in ap.reached_log] == [0, 1]
    t_orbit = [x for x in s if abs(math.hypot(x.pos[0] - c[0], x.pos[1] - c[1]) - 60.0) < 1.5]
    ring = [x for x in t_orbit if x.t_s > t_orbit[0].t_s + 5.0]
    ground = [ap.ground_m(x.pos[0] + h[0], x.pos[1] + h[1]) for x in ring]
    assert max(ground) - min(ground) > 10.0
    assert max(abs(x.pos[2] + h[2] - g - AGL_M) for x, g in zip(ring, ground, strict=True)) < 1.0


def test_frame11_mission_over_mavlink_holds_the_height_above_ground() -> None:
    """Uploaded with pymavlink (osa upload's link), flown, watched: the vehicle's
    TERRAIN_REPORTs say it held its height above the ground, the true track agrees."""
    with running_vehicle(RTK_SCENARIO, speedup=40.0, seed=2) as rv:
        ap = rv.autopilot
        world = rv.vehicle.realisation.world
        h = ap.home
        items = [MissionItem(command=MAV_CMD_NAV_TAKEOFF, frame=MAV_FRAME_GLOBAL_TERRAIN_ALT_INT,
                             lat_deg=h.lat_deg, lon_deg=h.lon_deg, alt_m=AGL_M)]
        for e, n in TOUR_ENU:
            lat, lon, _ = world.frame.to_geodetic(e, n, 0.0)
            items.append(MissionItem(frame=MAV_FRAME_GLOBAL_TERRAIN_ALT_INT, lat_deg=float(lat),
                                     lon_deg=float(lon), alt_m=AGL_M))
        items.append(MissionItem(command=MAV_CMD_NAV_LAND, lat_deg=h.lat_deg,
                                 lon_deg=h.lon_deg))
        report = upload_mission(Mission(items=tuple(items), home=(h.lat_deg, h.lon_deg,
                                                                  h.alt_m)),
                                rv.pymavlink_url, config=FAST)
        assert report.items == len(items)
        gcs = Gcs(rv.pymavlink_url)
        try:
            assert gcs.command(MAV_CMD_COMPONENT_ARM_DISARM, 1) == MAV_RESULT_ACCEPTED
            assert gcs.command(MAV_CMD_MISSION_START, 0, 0) == MAV_RESULT_ACCEPTED
            msgs = gcs.collect(180.0, until=lambda m: m.get_type() == "HEARTBEAT"
                               and m.get_srcSystem() == 1 and not m.base_mode & 128)
        finally:
            gcs.close()
        assert not ap.armed, "never disarmed"
        reached = [r[0] for r in ap.reached_log]
        t0, t1 = ap.reached_log[1][1], ap.reached_log[len(TOUR_ENU)][1]
    assert reached == list(range(len(items)))
    # its own reports between the first and the last tour item
    i0 = next(k for k, m in enumerate(msgs) if m.get_type() == "MISSION_ITEM_REACHED"
              and m.seq == 1)
    i1 = next(k for k, m in enumerate(msgs) if m.get_type() == "MISSION_ITEM_REACHED"
              and m.seq == len(TOUR_ENU))
    own = [m.current_height for m in msgs[i0:i1] if m.get_type() == "TERRAIN_REPORT"]
    assert len(own) > 30
    assert max(abs(x - AGL_M) for x in own) < 1.0
    # the true track (the simulator's, for evaluation)
    track = rv.vehicle.stepper.vehicle_track(0)
    on = (track.t_s >= t0) & (track.t_s <= t1)
    agl = track.enu_m[on, 2] - track.lever_arm_m[2] - track.ground_m[on]
    assert np.ptp(track.ground_m[on]) > 40.0
    assert np.max(np.abs(agl - AGL_M)) < 1.0


def test_terrain_frame_commands() -> None:
    """COMMAND_INT DO_REPOSITION in frame 11: to that height above the ground there."""
    with running_vehicle(RTK_SCENARIO, speedup=20.0) as rv:
        ap = rv.autopilot
        world = rv.vehicle.realisation.world
        gcs = Gcs(rv.pymavlink_url)
        try:
            assert gcs.command(MAV_CMD_COMPONENT_ARM_DISARM, 1) == MAV_RESULT_ACCEPTED
            assert gcs.command(22, 0, 0, 0, math.nan, math.nan, math.nan, math.nan) == 0
            assert until(lambda: ap.mode is Mode.LOITER and not ap.landed, 20.0)
            lat, lon, _ = world.frame.to_geodetic(-200.0, 200.0, 0.0)
            gcs.conn.mav.command_int_send(1, 1, MAV_FRAME_GLOBAL_TERRAIN_ALT_INT,
                                          MAV_CMD_DO_REPOSITION, 0, 0, -1, 0, 0, math.nan,
                                          deg_to_e7(lat), deg_to_e7(lon), 25.0)
            ack = gcs.wait("COMMAND_ACK", where=lambda m: m.command == MAV_CMD_DO_REPOSITION)
            assert ack.result == MAV_RESULT_ACCEPTED
            target = ap.task.target
            assert target[2] - ap.ground_m(target[0], target[1]) == pytest.approx(25.0, abs=0.05)
            assert math.hypot(target[0] + 200.0, target[1] - 200.0) < 0.05
        finally:
            gcs.close()


def test_the_database_of_a_grid_terrain() -> None:
    """A grid terrain (the planner's terrain protocol, any kind): its cell size is the
    database's spacing, heights are the grid's, in the world's datum; ``loaded`` counts the
    blocks of the grid's 2 km square, and beyond the grid (its edge value held) there is
    no data: spacing 0."""
    from envs.vehicle.terrain import TerrainDatabase
    from sim.terrain import GridTerrain
    from sim.world import Origin, World

    rng = np.random.default_rng(3)
    grid = GridTerrain(rng.uniform(-20.0, 60.0, size=(41, 41)), -1000.0, -1000.0, 50.0)
    world = World(Origin(lat_deg=47.3, lon_deg=8.5, h_m=400.0), grid, ())
    db = TerrainDatabase(world)
    assert db.spacing == 50 and db.loaded == (2000 // 200) ** 2
    for e, n in ((0.0, 0.0), (-975.0, 630.0), (412.5, -333.3), (999.0, 999.0)):
        u = float(grid.height_m(e, n))
        lat, lon, h = world.frame.to_geodetic(e, n, u)
        r = db.report(deg_to_e7(lat), deg_to_e7(lon), h + 25.0)
        assert r.terrain_height_m == pytest.approx(h, abs=0.02)  # (1e-7 deg, 80 m/km grade)
        assert r.current_height_m == pytest.approx(25.0, abs=0.02)
        assert (r.spacing, r.pending) == (50, 0)
        assert db.above_ground(lat, lon, 12.0)[2] - u == pytest.approx(12.0, abs=0.02)
    for e, n in ((1010.0, 0.0), (0.0, -1500.0)):
        lat, lon, _ = world.frame.to_geodetic(e, n, 0.0)
        assert db.report(deg_to_e7(lat), deg_to_e7(lon), 500.0).spacing == 0


def test_a_dem_site_database_and_a_terrain_following_tour() -> None:
    """site-valley (a GeoTIFF DEM in UTM, datum_offset_m 51): the database's heights are
    the DEM's own (``elevation_m``: the cells plus the offset), its spacing the DEM's
    pixel; a frame-11 tour across the valley holds its height above that ground."""
    from envs.vehicle.terrain import TerrainDatabase

    ap = make_autopilot("site-valley-rtk", seed=1)
    world = ap.world
    dem = world.terrain
    db = TerrainDatabase(world)
    assert db.spacing == round(min(dem.pixel_m)) == 10
    for e, n in ((0.0, 0.0), (300.0, 100.0), (520.0, 350.0), (-120.0, 180.0)):
        lat, lon, _ = _ground_geodetic(world, e, n)
        assert db.height_m(lat, lon) == pytest.approx(float(dem.elevation_m(e, n)), abs=0.01)
    h = ap.home.enu
    tour = [(300.0, 100.0), (520.0, 350.0), (350.0, 520.0), (0.0, 150.0)]
    ap.set_mission(numbered(
        [item(ap, MAV_CMD_NAV_TAKEOFF, 0, 0, 45.0, frame=MAV_FRAME_GLOBAL_TERRAIN_ALT_INT)]
        + [item(ap, e=e - h[0], n=n - h[1], alt=45.0, frame=MAV_FRAME_GLOBAL_TERRAIN_ALT_INT)
           for e, n in tour]))
    ap.set_mode(Mode.MISSION)
    ap.arm()
    s = fly(ap, 900.0, until=lambda a: len(a.reached_log) == len(tour) + 1)
    assert [r[0] for r in ap.reached_log] == list(range(len(tour) + 1))
    legs = [x for x in s if ap.reached_log[1][1] <= x.t_s <= ap.reached_log[-1][1]]
    ground = [float(dem.height_m(x.truth[0], x.truth[1])) for x in legs]
    assert max(ground) - min(ground) > 20.0
    assert max(abs(x.truth[2] - g - 45.0) for x, g in zip(legs, ground, strict=True)) < 1.0


def _dem_file_height(path, lat: float, lon: float, offset_m: float) -> float:
    """The DEM file's height at (lat, lon), by hand: the GeoTIFF's band with rasterio, WGS84
    to its CRS with pyproj, its affine transform inverted, bilinear between the pixel
    centres (PixelIsArea), plus the scenario's ``datum_offset_m``."""
    import pyproj
    import rasterio

    with rasterio.open(path) as ds:
        z = ds.read(1).astype(float)
        to_px = ~ds.transform
        x, y = pyproj.Transformer.from_crs("EPSG:4326", ds.crs, always_xy=True).transform(
            lon, lat)
    col, row = to_px @ (x, y)
    c, r = col - 0.5, row - 0.5  # from the pixel's corner to its centre
    c0, r0 = math.floor(c), math.floor(r)
    fc, fr = c - c0, r - r0
    cell = z[r0:r0 + 2, c0:c0 + 2]
    return float(cell[0, 0] * (1 - fc) * (1 - fr) + cell[0, 1] * fc * (1 - fr)
                 + cell[1, 0] * (1 - fc) * fr + cell[1, 1] * fc * fr) + offset_m


def test_terrain_check_on_a_dem_site_against_the_file() -> None:
    """site-valley (a UTM GeoTIFF, datum_offset_m 51), over MAVLink: TERRAIN_CHECK answers
    the file's own height, computed by hand from the GeoTIFF (to 1 cm), with the DEM's
    pixel as spacing, nothing pending, and ``loaded`` the blocks of the DEM it holds (not
    of 20 km about the origin); where the DEM gives no height (beyond the part read for
    the scenario, here 3 km east, outside the file) ``spacing`` is 0 and a TERRAIN_REQUEST
    there gets no TERRAIN_DATA. It used to answer the DEM's edge value held out there, as
    if it were the file's (spacing 10), and 65535 blocks loaded."""
    from pathlib import Path

    import sim

    # the preset's DEM and its datum_offset_m (sim/scenarios/site-valley.toml)
    path, offset = Path(sim.__file__).parent / "scenarios" / "site" / "valley-dem.tif", 51.0
    with running_vehicle("site-valley", speedup=5.0) as rv:
        world = rv.vehicle.realisation.world
        gcs = Gcs(rv.pymavlink_url, timeout_s=30.0)
        try:
            pos = gcs.wait("GLOBAL_POSITION_INT")
            for e, n in ((0.0, 0.0), (310.0, 120.0), (-250.0, -330.0), (480.0, 400.0)):
                lat, lon, _ = world.frame.to_geodetic(e, n, 150.0)
                where = (deg_to_e7(float(lat)), deg_to_e7(float(lon)))
                gcs.conn.mav.terrain_check_send(*where)
                r = gcs.wait("TERRAIN_REPORT", where=lambda m, w=where: (m.lat, m.lon) == w)
                h = _dem_file_height(path, where[0] / 1e7, where[1] / 1e7, offset)
                assert r.terrain_height == pytest.approx(h, abs=0.01)
                assert (r.spacing, r.pending) == (10, 0)
                assert r.current_height == pytest.approx(pos.alt / 1e3 - h, abs=1.0)
                # the DEM held: more than the scenario's 1 km square, less than the
                # file's 2.6 km square (260 x 260 pixels of 10 m), in 40 m blocks
                assert 25 * 25 <= r.loaded <= 65 * 65
            lat, lon, _ = world.frame.to_geodetic(3000.0, 0.0, 150.0)
            where = (deg_to_e7(float(lat)), deg_to_e7(float(lon)))
            gcs.conn.mav.terrain_check_send(*where)
            r = gcs.wait("TERRAIN_REPORT", where=lambda m: (m.lat, m.lon) == where)
            assert (r.spacing, r.pending) == (0, 0)
            gcs.conn.mav.terrain_request_send(*where, 10, 0b111)
            gcs.conn.mav.terrain_check_send(*where)  # answered after any TERRAIN_DATA
            gcs.wait("TERRAIN_REPORT", where=lambda m: (m.lat, m.lon) == where)
            assert [m for m in gcs.messages if m.get_type() == "TERRAIN_DATA"] == []
        finally:
            gcs.close()
