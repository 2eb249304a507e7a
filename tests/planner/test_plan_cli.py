"""Trajectory -> Mission conversion and the ``osa plan`` command."""

from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest

from envs.cli import build_parser, main
from envs.commands.plan import PATTERNS, build_plan
from planner.convert import (
    douglas_peucker,
    mission_waypoints_enu_m,
    polyline_distance_m,
    trajectory_to_mission,
)
from planner.files import read_mission
from planner.geojson import validate_geojson
from planner.mission import (
    MAV_CMD_NAV_RETURN_TO_LAUNCH,
    MAV_CMD_NAV_TAKEOFF,
    MAV_CMD_NAV_WAYPOINT,
    MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
    MAV_FRAME_GLOBAL_TERRAIN_ALT_INT,
)
from planner.patterns import (
    FlightConfig,
    Geofence,
    KeepOut,
    close_pass,
    concentric_circles,
    expanding_square,
    helix,
    lawnmower,
    orbit,
)

HOME = (36.715, -4.478, 95.0)
F = FlightConfig(origin=HOME, alt_m=45.0)
CENTER = "36.7152,-4.4778"

TRAJECTORIES = {
    "lawnmower": lambda: lawnmower((0.0, 0.0), 150.0, spacing_m=60.0, flight=F),
    "expanding-square": lambda: expanding_square((0.0, 0.0), 100.0, spacing_m=40.0, flight=F),
    "helix": lambda: helix((20.0, 10.0), 50.0, alt_start_m=40.0, alt_end_m=70.0, flight=F),
    "circles": lambda: concentric_circles((0.0, 0.0), [20.0, 40.0, 60.0], flight=F),
    "close-pass": lambda: close_pass((0.0, 0.0), 10.0, flight=F, start_enu_m=(0, 0, 45)),
    "orbit": lambda: orbit((0.0, 0.0), 35.0, turns=1.5, flight=F, start_enu_m=(80, 0, 45)),
}


# --------------------------------------------------------------------------- conversion


def test_douglas_peucker_keeps_corners_and_drops_collinear_points() -> None:
    line = np.column_stack([np.linspace(0, 100, 51), np.zeros(51), np.full(51, 40.0)])
    assert list(douglas_peucker(line, 0.5)) == [0, 50]
    corner = np.vstack([line, [[100.0, y, 40.0] for y in np.linspace(2, 60, 30)]])
    assert list(douglas_peucker(corner, 0.5)) == [0, 50, 80]
    # a circle of radius r keeps a vertex every ~2 sqrt(2 r tol): curves stay curves
    t = orbit((0.0, 0.0), 50.0, flight=FlightConfig(dt_s=0.1))
    kept = douglas_peucker(t.enu_m, 1.0)
    assert (
        2 * math.pi * 50.0 / (2 * math.sqrt(2 * 50.0)) <= len(kept) - 1 <= 2 * math.pi * 50.0 / 9.0
    )


@pytest.mark.parametrize("name", sorted(TRAJECTORIES))
def test_mission_keeps_every_vertex_within_tolerance(name: str) -> None:
    traj = TRAJECTORIES[name]()
    m = trajectory_to_mission(traj, tolerance_m=1.0)
    assert m.home == HOME
    # relative altitude = h - home_h exactly: z plus the tangent plane's rise d^2 / 2R
    assert m.items[0].command == MAV_CMD_NAV_TAKEOFF and m.items[0].alt_m == pytest.approx(
        traj.enu_m[0, 2], abs=0.01
    )
    assert (m.items[0].lat_deg, m.items[0].lon_deg) == HOME[:2]
    assert m.items[-1].command == MAV_CMD_NAV_RETURN_TO_LAUNCH
    wps = m.items[1:-1]
    assert all(it.command == MAV_CMD_NAV_WAYPOINT for it in wps)
    assert all(it.frame == MAV_FRAME_GLOBAL_RELATIVE_ALT_INT for it in m.items)
    # read the waypoints back from degE7 (what a vehicle holds) into the home ENU frame
    back = mission_waypoints_enu_m(m)
    e7 = np.array([[it.x_e7 / 1e7, it.y_e7 / 1e7] for it in wps])
    assert np.allclose(e7, [[it.lat_deg, it.lon_deg] for it in wps], atol=0.6e-7)
    assert np.allclose(back[0], traj.enu_m[0], atol=0.02) and np.allclose(
        back[-1], traj.enu_m[-1], atol=0.02
    )
    dist = polyline_distance_m(traj.enu_m, back)
    assert dist.max() <= 1.0 + 0.02  # DP tolerance + degE7 rounding
    assert m.cruise_speed_m_s == pytest.approx(F.speed_m_s, rel=0.01)
    assert len(wps) < len(traj.t_s) / 2  # decimated


def test_fence_keep_outs_rally_and_no_rtl() -> None:
    traj = TRAJECTORIES["orbit"]()
    fence = Geofence.square((0.0, 0.0), 150.0)
    m = trajectory_to_mission(traj, rtl=False, fence=fence, takeoff_alt_m=20.0,
                              keep_outs=[KeepOut(east_m=100.0, north_m=0.0, radius_m=12.0)],
                              rally_enu_m=[(-50.0, -50.0, 30.0)])  # fmt: skip
    assert m.items[-1].command == MAV_CMD_NAV_WAYPOINT and m.items[0].alt_m == 20.0
    assert len(m.polygons) == 1 and m.polygons[0].inclusion and len(m.polygons[0].vertices_deg) == 4
    assert len(m.circles) == 1 and not m.circles[0].inclusion and m.circles[0].radius_m == 12.0
    from estimator.geodesy import ExactENU

    e, n, _ = ExactENU(*HOME).to_enu(m.circles[0].lat_deg, m.circles[0].lon_deg, HOME[2])
    assert (e, n) == pytest.approx((100.0, 0.0), abs=0.01)  # on the degE7 grid: < 1 cm
    assert len(m.rally_deg) == 1 and m.rally_deg[0][2] == pytest.approx(30.0, abs=1e-3)


def test_terrain_referenced_paths() -> None:
    f = FlightConfig(origin=HOME, alt_m=40.0, height_ref="terrain")
    traj = orbit((0.0, 0.0), 30.0, flight=f)
    m = trajectory_to_mission(traj)
    assert all(it.frame == MAV_FRAME_GLOBAL_TERRAIN_ALT_INT for it in m.items[:-1])
    from sim.terrain import HillsTerrain

    hill = HillsTerrain(slope_e=0.1, slope_n=0.0, hills=(), ripple_amplitude_m=0.0)  # rising east
    m2 = trajectory_to_mission(traj, terrain=hill)
    wps = [it for it in m2.items if it.command == MAV_CMD_NAV_WAYPOINT]
    back = mission_waypoints_enu_m(m2)
    assert all(it.frame == MAV_FRAME_GLOBAL_RELATIVE_ALT_INT for it in wps)
    assert np.allclose([it.alt_m for it in wps], 40.0 + 0.1 * back[:, 0], atol=0.01)


# --------------------------------------------------------------------------- CLI


def _items_printed(out: str) -> int:
    return int(re.search(r"mission\s+(\d+) items", out).group(1))


@pytest.mark.parametrize("pattern", PATTERNS)
def test_osa_plan_writes_a_readable_mission(pattern: str, tmp_path, capsys) -> None:
    path = tmp_path / f"{pattern}.plan"
    gj = tmp_path / f"{pattern}.geojson"
    rc = main(["plan", pattern, "-o", str(path), "--center", CENTER, "--alt", "40",
               "--home", "36.7148,-4.4783,95", "--geojson", str(gj),
               "--keep-out", "36.7170,-4.4760,10"])  # fmt: skip
    out, err = capsys.readouterr()
    assert rc == 0, err
    for key in ("path", "mission", "condition number", "CRLB", "horizontal", "vertical"):
        assert key in out
    m = read_mission(path)
    assert len(m.items) == _items_printed(out)
    assert m.home == pytest.approx((36.7148, -4.4783, 95.0))
    assert (
        m.items[0].command == MAV_CMD_NAV_TAKEOFF
        and m.items[-1].command == MAV_CMD_NAV_RETURN_TO_LAUNCH
    )
    assert all(it.alt_m == pytest.approx(40.0) for it in m.items[:2])
    assert len(m.circles) == 1 and len(m.polygons) == (1 if pattern == "optimal" else 0)
    assert validate_geojson(json.loads(gj.read_text())) == []


def test_osa_plan_waypoints_file_and_options(tmp_path, capsys) -> None:
    path = tmp_path / "h.waypoints"
    opts = ["--radius", "30", "--turns", "2", "--climb", "-10", "--alt", "50", "--no-rtl"]
    rc = main(["plan", "helix", "-o", str(path), "--center", CENTER, *opts, "--speed", "4"])
    out, err = capsys.readouterr()
    assert rc == 0, err
    assert path.read_text().startswith("QGC WPL 110")
    m = read_mission(path)
    assert len(m.items) == _items_printed(out)
    assert m.items[-1].command == MAV_CMD_NAV_WAYPOINT
    alts = [it.alt_m for it in m.items[1:]]
    assert alts[0] == pytest.approx(50.0) and alts[-1] == pytest.approx(40.0, abs=0.01)
    enu = mission_waypoints_enu_m(m)
    assert np.allclose(enu[0], (0.0, 0.0, 50.0), atol=0.02)  # starts above home = centre
    assert np.allclose(np.hypot(enu[1:, 0], enu[1:, 1]), 30.0, atol=0.05)


@pytest.mark.parametrize(
    ("argv", "needle"),
    [
        (["plan", "spiral", "-o", "x.plan", "--center", CENTER], "invalid choice"),
        (["plan", "helix", "-o", "x.plan"], "--center"),
        (["plan", "helix", "-o", "x.plan", "--center", "91,0"], "latitude"),
        (["plan", "helix", "-o", "x.plan", "--center", "0,181"], "longitude"),
        (["plan", "helix", "-o", "x.plan", "--center", "nan,0"], "finite"),
        (["plan", "helix", "-o", "x.plan", "--center", CENTER, "--radius", "0"], "> 0"),
        (["plan", "helix", "-o", "x.plan", "--center", CENTER, "--radius", "-5"], "--radius"),
        (["plan", "helix", "-o", "x.plan", "--center", CENTER, "--alt", "nan"], "finite"),
        (["plan", "helix", "-o", "x.gpx", "--center", CENTER], "unknown mission type"),
        (["plan", "helix", "-o", "/dev/null/x.plan", "--center", CENTER], "cannot write"),
        (["plan", "lawnmower", "-o", "x.plan", "--center", CENTER, "--overlap", "1"], "overlap"),
        (
            [
                "plan",
                "optimal",
                "-o",
                "x.plan",
                "--center",
                CENTER,
                "--radius",
                "10",
                "--home",
                "36.72,-4.47",
            ],
            "keep-in",
        ),
    ],
)
def test_osa_plan_bad_input_is_one_line_and_status_2(argv, needle, capsys) -> None:
    with pytest.raises(SystemExit) as exc:
        rc = main(argv)
        raise SystemExit(rc)
    err = capsys.readouterr().err
    assert exc.value.code == 2
    assert err.count("\n") == 1 and needle in err


def test_pattern_through_a_keep_out_is_refused(tmp_path, capsys) -> None:
    rc = main(["plan", "orbit", "-o", str(tmp_path / "o.plan"), "--center", "36.715,-4.478",
               "--radius", "50", "--keep-out", "36.715,-4.47744,10"])  # fmt: skip
    err = capsys.readouterr().err
    assert rc == 1 and "keep-out" in err and not (tmp_path / "o.plan").exists()


def test_mavsdk_imports_what_was_planned(tmp_path, mavsdk_peer) -> None:
    """MAVSDK's own QGroundControl importer reads the written .plan as planned."""
    from planner.mavlink import connected
    from planner.mavlink_wire import compare_wire, fence_to_wire, mission_to_wire
    from tests.planner.conftest import ANSWERING

    path = tmp_path / "c.plan"
    argv = ["plan", "circles", "-o", str(path), "--center", CENTER, "--keep-out", "36.716,-4.476,8"]
    assert main(argv) == 0
    planned = build_plan(build_parser().parse_args(argv)).mission
    with connected(mavsdk_peer.mavsdk_url, ANSWERING) as link:
        imported = link.import_qgc_plan(path)
    assert compare_wire(mission_to_wire(planned), imported[0]) == []
    assert [(w.x, w.y) for w in imported[0]] == [(it.x_e7, it.y_e7) for it in planned.items]
    assert [(w.command, w.x, w.y, w.param1) for w in imported[1]] == [
        (w.command, w.x, w.y, w.param1) for w in fence_to_wire(planned)
    ]
