"""``osa plan`` on a site: ``--area FILE``, ``--keepout FILE``, ``--dem FILE``, ``--agl M``,
``--alt-frame``, ``-o FILE.kml`` (docs/cli.md, docs/planner.md "On a site").

The site's files are read here, at the edge, and converted once to one ENU frame (its
origin at ``--home``, else the area's or the centre's middle, at the DEM's height
there); the planner gets objects only.

- The area (KML, GeoJSON or a ``.plan``'s inclusion polygon) becomes a
  :class:`planner.area.SearchArea` with the keep-outs (``--keepout`` files, and the
  ``--keep-out`` circles): ``lawnmower`` and ``expanding-square`` cover its polygon,
  the other patterns fly about ``--center`` and must stay inside it; every path goes
  around the keep-outs that block it.
- With ``--dem`` the heights follow the ground (:func:`planner.terrain_follow.
  follow_terrain`): every point of every straight leg between items is within
  [M - 2, M + 25] m of the DEM (M = ``--agl``), vertices added where the ground
  changes (a pattern's own heights beyond that band, a helix's climb, held in it with a
  warning; legs still outside it: refused, exit 1); a keep-out whose ``top_m`` + 10 m
  is at most M - 2 is then flown over, the others are avoided. Without a DEM every
  keep-out is avoided.
- ``--alt-frame``: items in frame 6 (relative to home; home's height from the DEM at
  home), 11 (above the terrain) or 0 (above mean sea level: the DEM's datum).
- The summary gives the lowest and highest height above the DEM along the legs (as an
  autopilot flies them) and the flight time. A leg beyond the DEM or over its nodata
  is refused (exit 2, naming the file), as are the area, ``--center`` and ``--home``.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np

from envs.commands.plan import (
    MAX_FLIGHT_S,
    PlanError,
    check_mission_size,
    pattern_segments,
    scoring_config,
)

ABOVE_M = 25.0  # a leg may rise this far above the wanted height above ground
BELOW_M = 2.0  # ... and dip this far below it
CLEARANCE_M = 10.0  # over a keep-out's top
ALT_FRAMES = ("relative", "terrain", "amsl")


def site_requested(args: argparse.Namespace) -> bool:
    """Does the command line ask for the site flow (an option of this module, or KML)?"""
    return bool(args.area or args.keepout or args.dem or args.agl is not None
                or args.alt_frame is not None or Path(args.output).suffix.lower() == ".kml")


@dataclasses.dataclass(frozen=True)
class SitePlan:
    """What the site flow computed (before writing files)."""

    trajectory: Any  # the vertices flown straight, origin heights (Trajectory)
    mission: Any  # planner.mission.Mission, in the requested frame
    frame_name: str  # relative | terrain | amsl
    prior_enu_m: Any | None  # the --center on the ground (scoring), or None
    agl_range_m: tuple[float, float] | None  # lowest, highest above the DEM along the legs
    flight_s: float  # home to home at --speed (the RTL leg straight)
    kml: str  # the KML document (written for -o FILE.kml)
    n_avoided: int
    n_flown_over: int
    note: str = ""
    warnings: tuple[str, ...] = ()


def _read_site(args) -> tuple[Any, list]:
    from sim.sitefiles import GeoShape, SiteFileError, read_area, read_keepouts

    try:
        area = read_area(args.area) if args.area else None
        shapes = [s for f in args.keepout for s in read_keepouts(f)]
    except SiteFileError as exc:
        raise PlanError(str(exc)) from None
    for lat, lon, r in args.keep_out:
        shapes.append(GeoShape(center_deg=(lat, lon), radius_m=r, name="keep-out"))
    return area, shapes


def build_site_plan(args: argparse.Namespace) -> SitePlan:
    """Plan on a site from parsed arguments; raises :class:`PlanError`."""
    from estimator.geodesy import ExactENU
    from estimator.records import Trajectory
    from planner import patterns as pat
    from planner.area import SearchArea
    from planner.convert import trajectory_to_mission
    from planner.kml import KmlShape, mission_kml
    from planner.terrain_follow import agl_along, follow_terrain

    frame_name = args.alt_frame or "relative"
    if args.agl is not None and args.dem is None and frame_name != "terrain":
        raise PlanError("--agl needs --dem (or --alt-frame terrain: the autopilot's terrain "
                        "database holds the ground)")
    if frame_name == "amsl" and args.dem is None:
        raise PlanError("--alt-frame amsl needs --dem (the ground's height above sea level)")
    if args.center is None and args.area is None:
        raise PlanError("give --center LAT,LON or --area FILE")
    if args.pattern not in ("lawnmower", "expanding-square") and args.center is None:
        raise PlanError(f"{args.pattern} flies about --center LAT,LON: give it")
    if not (math.isfinite(args.margin) and args.margin >= 0):
        raise PlanError(f"--margin must be >= 0, got {args.margin:g}")
    height = args.agl if args.agl is not None else args.alt
    area_deg, shapes = _read_site(args)

    # the frame: at --home, else the middle of the area or the centre
    if args.home is not None:
        o_lat, o_lon = args.home[0], args.home[1]
    elif area_deg is not None:
        o_lat, o_lon = _middle(area_deg)
    else:
        o_lat, o_lon = args.center
    home_alt = args.home[2] if args.home is not None and len(args.home) > 2 else 0.0
    frame = ExactENU(o_lat, o_lon, float(home_alt))

    def en(lat: float, lon: float) -> tuple[float, float]:
        """(e, n) in the frame of a point at the frame origin's height."""
        e, n, _ = frame.to_enu(lat, lon, frame.h0_m)
        return float(e), float(n)

    radius = args.radius if args.radius is not None else _default_radius(args.pattern)
    center_en = en(*args.center) if args.center is not None else None
    area_en = [en(*v) for v in area_deg] if area_deg is not None else None

    dem = None
    if args.dem is not None:
        from sim.dem import DemError, DemTerrain, box_of

        pts = [np.zeros((1, 2))]
        if area_en is not None:
            pts.append(np.array(area_en))
        if center_en is not None:
            c = np.array(center_en)
            reach = radius + args.offset + 50.0
            pts.append(np.array([c - reach, c + reach]))
        try:
            dem = DemTerrain(args.dem, (o_lat, o_lon, 0.0), box_of(pts))
            h_origin = float(dem.elevation_m(0.0, 0.0))
            dem = DemTerrain(args.dem, (o_lat, o_lon, h_origin), box_of(pts))
            frame = ExactENU(o_lat, o_lon, h_origin)  # again, at the ground's height
            center_en = en(*args.center) if args.center is not None else None
            area_en = [en(*v) for v in area_deg] if area_deg is not None else None
            if area_en is not None:
                dem.require_polygon(np.array(area_en), "the area")
            if center_en is not None:
                dem.require_points(np.array([center_en]), "--center")
            if args.home is not None:  # the frame's origin
                dem.require_points(np.zeros((1, 2)), "--home")
        except DemError as exc:
            raise PlanError(str(exc)) from None
    origin = (frame.lat0_deg, frame.lon0_deg, frame.h0_m)

    # keep-outs in the frame; those the path flies over (DEM: it keeps >= M - 2)
    floor = height - BELOW_M if dem is not None else None
    keep_outs: list = []
    for s in shapes:
        if s.is_circle:
            e, n = en(*s.center_deg)
            keep_outs.append(pat.KeepOut(east_m=e, north_m=n, radius_m=s.radius_m, top_m=s.top_m))
        else:
            try:
                keep_outs.append(pat.KeepOutPolygon(
                    vertices_m=tuple(en(*v) for v in s.vertices_deg), top_m=s.top_m))
            except ValueError as exc:
                raise PlanError(f"--keepout: {s.name or 'a polygon'}: {exc}") from None
    blocking = [k for k in keep_outs if k.blocks(floor, CLEARANCE_M)]
    area = None
    if area_en is not None:
        try:
            area = SearchArea(tuple(area_en), args.margin, keep_outs=tuple(keep_outs),
                              floor_m=floor, clearance_m=CLEARANCE_M)
        except ValueError as exc:
            raise PlanError(f"{args.area}: {exc}") from None
    home_en = en(args.home[0], args.home[1]) if args.home is not None else None

    # the horizontal path and the wanted height above ground (or home) along it
    link = scoring_config().link
    fence = None
    note = ""
    warnings: list[str] = []
    targets: np.ndarray | None = None
    vertices = None
    args_h = argparse.Namespace(**{**vars(args), "alt": height})
    try:
        if args.pattern in ("lawnmower", "expanding-square") and area is not None:
            spacing = args.spacing or pat.lawnmower_spacing_m(
                pat.detection_range_m(height, link), args.overlap)
            a2 = abs(_area_m2(area_en))
            est_m = a2 / spacing + 4.0 * math.sqrt(a2)
            warnings += check_mission_size(args, est_m / args.speed, est_m, None,
                                           f"{args.pattern} over {args.area}",
                                           hint="widen --spacing or split the area")
            if args.pattern == "lawnmower":
                wps = area.sweep(spacing, args.heading, start=home_en)
            else:
                datum = center_en if center_en is not None else area.centroid_m
                wps = area.expanding_square(datum, spacing, args.heading)
            if home_en is None:
                path2 = area.join(wps)
            elif area.contains(np.array([home_en]), 0.0)[0]:
                path2 = area.join([home_en, *wps])
            else:  # take-off outside the area: straight to the pattern (checked below)
                path2 = [home_en, *area.join(wps)]
            path2 = np.asarray(path2, dtype=float)
            targets = np.full(len(path2), height)
        elif args.pattern == "optimal":
            vertices, note, fence = _optimal(args, radius, center_en, home_en, area, blocking,
                                             dem, height, origin)
        else:
            vertices = None
            flight = pat.FlightConfig(speed_m_s=args.speed, alt_m=height, origin=origin)
            c = center_en if center_en is not None else (0.0, 0.0)
            prior = np.array([c[0], c[1], 0.0])
            start = (*home_en, height) if home_en is not None else None
            segs = pattern_segments(args_h, pat, radius, c, prior, start, flight)
            est = pat.estimate_path(segs, flight, start_enu_m=start, tolerance_m=args.tolerance)
            warnings += check_mission_size(args, est.duration_s, est.length_m,
                                           est.n_waypoints + 2, f"{args.pattern} --radius "
                                           f"{radius:g}")
            traj = pat.segments_to_trajectory(segs, flight, args.pattern, start)
            from planner.convert import douglas_peucker

            keep = douglas_peucker(traj.enu_m, args.tolerance)
            path2 = traj.enu_m[keep, :2]
            targets = traj.enu_m[keep, 2]
    except ValueError as exc:
        raise PlanError(str(exc)) from None

    if vertices is None:
        assert targets is not None
        # the path must stay in the area and out of what blocks it
        if area is not None and args.pattern not in ("lawnmower", "expanding-square") and (
                not area.path_inside(path2, 0.0, step_m=1.0, keep_outs=False)):
            raise PlanError(f"{args.pattern} leaves the area {args.area}; move --center or "
                            "reduce --radius", 1)
        problems = pat.airspace_violations(np.column_stack([path2, targets]), None, blocking)
        if problems:
            raise PlanError(f"{args.pattern} path {problems[0]}; move the area, --center or "
                            "--home", 1)
        if dem is not None:
            band = (height - BELOW_M, height + ABOVE_M)
            if targets.min() < band[0] or targets.max() > band[1]:
                warnings.append(f"{args.pattern} flies {targets.min():.0f} to "
                                f"{targets.max():.0f} m: held within {band[0]:g} to "
                                f"{band[1]:g} m above the DEM (--agl {height:g})")
            vertices = follow_terrain(path2, targets, dem, band_m=band)
        else:
            vertices = np.column_stack([path2, targets])
    if home_en is None:
        home_en = (float(vertices[0, 0]), float(vertices[0, 1]))
    # home (lat, lon, height in the DEM's datum or as given)
    h_lat, h_lon, _ = frame.to_geodetic(home_en[0], home_en[1], 0.0)
    if args.home is not None:
        h_lat, h_lon = args.home[0], args.home[1]
    home_h = (float(dem.elevation_m(home_en[0], home_en[1])) if dem is not None
              else float(home_alt))
    home = (float(h_lat), float(h_lon), home_h)

    # the mission: vertices straight, no decimation (each was placed for the ground)
    seg = np.linalg.norm(np.diff(vertices, axis=0), axis=1)
    t = np.concatenate([[0.0], np.cumsum(seg / args.speed)])
    keep = np.concatenate([[True], seg > 1e-6])
    ref = "terrain" if (dem is None and frame_name == "terrain") else "origin"
    traj = Trajectory(t[keep], vertices[keep], origin, ref, args.pattern)
    if len(traj.t_s) < 2:
        raise PlanError(f"{args.pattern}: the path has a single point")
    fence_keep = [k for k in blocking if isinstance(k, pat.KeepOut)]
    try:
        mission = trajectory_to_mission(traj, tolerance_m=0.0, rtl=not args.no_rtl,
                                        fence=fence, keep_outs=fence_keep, home=home,
                                        name=f"osa plan {args.pattern}")
    except ValueError as exc:
        raise PlanError(str(exc)) from None
    mission = _site_fence(mission, frame, area_en, blocking)
    drawn = mission  # the KML's path: absolute heights (home's + relative) with a DEM
    if frame_name != "relative" and dem is not None:
        mission = _reframe(mission, frame_name, traj, dem, home_h)
    if len(mission.items) > args.max_items:
        raise PlanError(f"{args.pattern}: {len(mission.items)} mission items, more than the "
                        f"{args.max_items} a vehicle holds (--max-items); raise --spacing or "
                        "split the area")

    # heights above the DEM along the legs as an autopilot flies them (straight)
    agl_range = None
    if dem is not None:
        from planner.patterns import densify
        from sim.dem import DemError

        flown = np.vstack([[home_en[0], home_en[1], float(dem.height_m(*home_en)) + height],
                           vertices])
        try:  # the ground under every leg is the file's (not beyond it, not a void)
            dem.require_points(densify(flown, 0.25 * min(dem.pixel_m))[:, :2], "the path")
        except DemError as exc:
            raise PlanError(str(exc)) from None
        a = agl_along(flown, dem, 0.25)
        agl_range = (float(a.min()), float(a.max()))
        if agl_range[0] < height - BELOW_M - 0.01 or agl_range[1] > height + ABOVE_M + 0.01:
            raise PlanError(f"{args.pattern}: the legs fly {agl_range[0]:.1f} to "
                            f"{agl_range[1]:.1f} m above the DEM, outside {height - BELOW_M:g} "
                            f"to {height + ABOVE_M:g}: not flyable as planned", 1)
    length = float(np.sum(seg)) + math.dist(vertices[-1][:2], home_en)
    flight_s = length / args.speed
    if flight_s > MAX_FLIGHT_S:
        raise PlanError(f"{args.pattern}: {flight_s / 3600:.1f} h of flight: beyond the "
                        f"{MAX_FLIGHT_S / 3600:g} h limit of one flight; split the area")

    # the KML: the path through the items, absolute heights where known
    kml_shapes = []
    for k, (s, ko) in enumerate(zip(shapes, keep_outs, strict=True)):
        kml_shapes.append(KmlShape(name=s.name or f"keep-out {k + 1}", vertices_deg=s.vertices_deg,
                                   center_deg=s.center_deg, radius_m=s.radius_m, top_m=s.top_m,
                                   flown_over=not any(ko is b for b in blocking)))
    path_deg, above_ground = _kml_path(drawn, home)
    kml = mission_kml(path_deg, home=(home[0], home[1], home[2] if not above_ground else 0.0),
                      above_ground=above_ground, area_deg=area_deg, keep_outs=kml_shapes,
                      name=f"osa plan {args.pattern}",
                      description=f"{len(mission.items)} items, {frame_name} altitudes")
    prior = np.array([center_en[0], center_en[1], 0.0]) if center_en is not None else None
    if prior is not None and dem is not None:
        prior[2] = float(dem.height_m(*center_en))
    return SitePlan(trajectory=traj, mission=mission, frame_name=frame_name, prior_enu_m=prior,
                    agl_range_m=agl_range, flight_s=flight_s, kml=kml,
                    n_avoided=len(blocking), n_flown_over=len(keep_outs) - len(blocking),
                    note=note, warnings=tuple(warnings))


def _middle(vertices_deg) -> tuple[float, float]:
    """The mean (lat, lon) of vertices, longitudes taken about the first one (an area
    across 180 degrees has its middle there, not at their plain mean, 0)."""
    lat = np.array([v[0] for v in vertices_deg], dtype=float)
    lon = np.array([v[1] for v in vertices_deg], dtype=float)
    lon = lon[0] + (lon - lon[0] + 180.0) % 360.0 - 180.0
    mid = (float(np.mean(lon)) + 180.0) % 360.0 - 180.0
    return float(np.mean(lat)), mid


def _default_radius(pattern: str) -> float:
    from envs.commands.plan import DEFAULT_RADIUS_M

    return DEFAULT_RADIUS_M[pattern]


def _area_m2(poly) -> float:
    from estimator.geometry import polygon_area_m2

    return polygon_area_m2(poly)


def _site_fence(mission, frame, area_en, blocking):
    """The area as an inclusion polygon and the blocking keep-out polygons as exclusion
    polygons (an autopilot's fence has no top: what is flown over is not fenced)."""
    from planner.convert import on_e7_grid
    from planner.mission import FencePolygon
    from planner.patterns import KeepOutPolygon

    def deg(poly) -> tuple:
        v = np.asarray(poly, dtype=float)
        lat, lon, _ = frame.to_geodetic(v[:, 0], v[:, 1], np.zeros(len(v)))
        return tuple((on_e7_grid(a), on_e7_grid(b)) for a, b in
                     zip(np.atleast_1d(lat), np.atleast_1d(lon), strict=True))

    polys = list(mission.polygons)
    if area_en is not None:
        polys.append(FencePolygon(vertices_deg=deg(area_en), inclusion=True))
    for k in blocking:
        if isinstance(k, KeepOutPolygon):
            polys.append(FencePolygon(vertices_deg=deg(k.vertices_m), inclusion=False))
    return dataclasses.replace(mission, polygons=tuple(polys))


def _reframe(mission, frame_name: str, traj, dem, home_h: float):
    """Frame-6 items to frame 11 (height above the DEM at the item) or frame 0 (the
    DEM's datum: home's height + the relative altitude)."""
    from planner.convert import on_mm
    from planner.mission import (
        MAV_CMD_NAV_TAKEOFF,
        MAV_CMD_NAV_WAYPOINT,
        MAV_FRAME_GLOBAL,
        MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
        MAV_FRAME_GLOBAL_TERRAIN_ALT_INT,
    )

    keep = mission.meta["kept_indices"]
    wp = traj.enu_m[keep]
    agl = wp[:, 2] - np.asarray(dem.height_m(wp[:, 0], wp[:, 1]), dtype=float)
    items = []
    k = 0
    for it in mission.items:
        if it.command == MAV_CMD_NAV_WAYPOINT and it.frame == MAV_FRAME_GLOBAL_RELATIVE_ALT_INT:
            alt = agl[k] if frame_name == "terrain" else home_h + it.alt_m
            k += 1
        elif it.command == MAV_CMD_NAV_TAKEOFF:
            alt = agl[0] if frame_name == "terrain" else home_h + it.alt_m
        else:
            items.append(it)
            continue
        items.append(dataclasses.replace(
            it, alt_m=on_mm(alt),
            frame=MAV_FRAME_GLOBAL_TERRAIN_ALT_INT if frame_name == "terrain"
            else MAV_FRAME_GLOBAL))
    return dataclasses.replace(mission, items=tuple(items))


def _kml_path(mission, home) -> tuple[list[tuple[float, float, float]], bool]:
    """Home and the positioned items as (lat, lon, absolute alt), or above the ground
    for frame-11 items."""
    from planner.mission import (
        MAV_CMD_NAV_WAYPOINT,
        MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
        MAV_FRAME_GLOBAL_TERRAIN_ALT_INT,
    )

    wps = [it for it in mission.items if it.command == MAV_CMD_NAV_WAYPOINT]
    above = bool(wps) and wps[0].frame == MAV_FRAME_GLOBAL_TERRAIN_ALT_INT
    out = [(home[0], home[1], 0.0 if above else home[2])]
    for it in wps:
        alt = home[2] + it.alt_m if it.frame == MAV_FRAME_GLOBAL_RELATIVE_ALT_INT else it.alt_m
        out.append((it.lat_deg, it.lon_deg, alt))
    return out, above


def _optimal(args, radius, center_en, home_en, area, blocking, dem, height, origin):
    """The CasADi plan from home about --center, inside the area's local fence (or the
    --radius square) and out of the blocking keep-outs; over the DEM its band is
    [M - 2, M + 25] m above it. Returns (vertices, note, fence)."""
    from planner import patterns as pat
    from planner.optimal import OptimalConfig, OptimalPlanner

    n_poly = sum(isinstance(k, pat.KeepOutPolygon) for k in blocking)
    cfg = OptimalConfig(scoring=scoring_config(), max_keep_outs=max(1, len(blocking) - n_poly),
                        max_keep_out_polygons=n_poly,
                        **({"terrain": dem} if dem is not None else {}))
    if area is not None:
        fence = area.local_fence(center_en)
    else:
        fence = pat.Geofence.square(center_en, radius)
    start_en = home_en if home_en is not None else center_en
    ground = float(dem.height_m(*start_en)) if dem is not None else 0.0
    start = np.array([start_en[0], start_en[1], ground + height])
    prior_z = float(dem.height_m(*center_en)) if dem is not None else 0.0
    band = ((height - BELOW_M, height + ABOVE_M) if dem is not None
            else (min(cfg.agl_min_m, height), max(cfg.agl_max_m, height)))
    sigma = args.prior_sigma
    res = OptimalPlanner(cfg).plan(
        (center_en[0], center_en[1], prior_z), np.diag([sigma**2, sigma**2, 4.0]), start,
        horizon_s=args.time_budget, fence=fence,
        keep_outs=[k for k in blocking if isinstance(k, pat.KeepOut)],
        keep_out_polygons=[k for k in blocking if isinstance(k, pat.KeepOutPolygon)],
        agl_band_m=band, limits=(args.speed, cfg.max_accel_m_s2, cfg.max_climb_m_s),
        origin=origin)
    if not res.feasible:
        raise PlanError("no feasible plan: " + "; ".join(res.violations), 1)
    note = (f"ipopt {res.status} in {res.iterations} iterations, "
            f"{res.solve_time_s * 1e3:.0f} ms; objective {res.objective:.3f}")
    if res.fallback:
        note += f"; solver path not used, flying {res.fallback}"
    return res.waypoints_enu_m, note, fence


def print_site_summary(args, plan: SitePlan, out: Path, fence_note: str) -> None:
    from planner.mission import MAV_CMD_NAV_WAYPOINT

    traj, mission = plan.trajectory, plan.mission
    frames = {"relative": "relative to home (frame 6)", "terrain": "above the terrain (frame "
              "11)", "amsl": "above mean sea level, the DEM's datum (frame 0)"}
    n_wp = sum(1 for it in mission.items if it.command == MAV_CMD_NAV_WAYPOINT)
    print(f"osa plan {args.pattern} -> {out}")
    print(f"  path      {traj.length_m:.1f} m, {traj.duration_s:.1f} s at {args.speed:g} m/s "
          f"(home to the last waypoint)")
    print(f"  mission   {len(mission.items)} items (takeoff, {n_wp} waypoints"
          f"{'' if args.no_rtl else ', RTL'}), altitudes {frames[plan.frame_name]}")
    if plan.agl_range_m is not None:
        lo, hi = plan.agl_range_m
        h = args.agl if args.agl is not None else args.alt
        print(f"  ground    {lo:.1f} to {hi:.1f} m above the DEM along the legs (wanted "
              f"{h:g} m, allowed {h - BELOW_M:g} to {h + ABOVE_M:g})")
    if plan.n_avoided or plan.n_flown_over:
        print(f"  keep-outs {plan.n_avoided} avoided, {plan.n_flown_over} flown over (their "
              f"top + {CLEARANCE_M:g} m below the path)")
    print(f"  flight    {plan.flight_s / 60:.1f} min home to home at {args.speed:g} m/s")
    if plan.prior_enu_m is not None:
        from planner.scoring import score_trajectory

        s = score_trajectory(traj, plan.prior_enu_m, scoring_config())
        print(f"  geometry  condition number {s.condition_number:.2f}, closest "
              f"{s.min_slant_m:.1f} m slant, {s.expected_measurements:.0f} expected ranges")
        from planner.plan_checks import geometry_warnings

        for w in geometry_warnings(s.condition_number):
            print(f"osa plan: warning: {w}", file=sys.stderr)
    if fence_note:
        print(f"  fence     {fence_note}")
    if plan.note:
        print(f"  optimal   {plan.note}")


def run_site(args: argparse.Namespace) -> int:
    """Plan on a site, write the mission (or KML), print the summary."""
    from planner.files import MissionFileError, write_mission
    from planner.kml import write_kml

    try:
        plan = build_site_plan(args)
    except PlanError as exc:
        print(f"osa plan: {exc}", file=sys.stderr)
        return exc.status
    for w in plan.warnings:
        print(f"osa plan: warning: {w}", file=sys.stderr)
    out = Path(args.output)
    mission = plan.mission
    fence_note = ""
    try:
        if out.suffix.lower() == ".kml":
            write_kml(plan.kml, out)
        else:
            if out.suffix.lower() != ".plan" and (mission.polygons or mission.circles):
                mission = dataclasses.replace(mission, polygons=(), circles=())
                fence_note = "not written: a .waypoints file holds no geofence (write a .plan)"
            write_mission(mission, out)
    except (MissionFileError, OSError) as exc:
        print(f"osa plan: {out}: cannot write: {exc}", file=sys.stderr)
        return 2
    if args.geojson:
        from planner.geojson import plan_geojson, write_geojson

        try:
            write_geojson(plan_geojson(plan.mission, plan.trajectory, name=args.pattern,
                                       prior_latlon=tuple(args.center) if args.center else None),
                          args.geojson)
        except (OSError, ValueError) as exc:
            print(f"osa plan: {args.geojson}: cannot write GeoJSON: {exc}", file=sys.stderr)
            return 2
    print_site_summary(args, plan, out, fence_note)
    return 0
