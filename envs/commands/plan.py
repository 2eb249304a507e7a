"""``osa plan PATTERN -o FILE [options]`` (docs/cli.md): write a mission.

The ENU frame is centred on home (``--home``, default: the centre), so the mission's
relative altitudes are the trajectory's z (exactly: the height above home through the
WGS84 geodesy, z + d^2 / 2R, 8 mm at 320 m). The prior AP is at ``--center`` on the
ground at home height (z = 0).

Home height: ``--home LAT,LON,ALT`` takes ALT as the home's height in the same datum
the vehicle reports (default 0). There is no geoid model here, so it is not converted
between AMSL and the WGS84 ellipsoid: the geodesy uses it as the ENU origin's height
(an error of a geoid undulation, < 110 m, changes horizontal positions by < 2e-5 of
their distance from home) and it is written unchanged as the mission's planned home
(``Mission.home``, the .plan plannedHomePosition / the .waypoints home line), which is
therefore in the vehicle's datum, not necessarily AMSL. Every mission item is relative
to home (frame 6, MAV_FRAME_GLOBAL_RELATIVE_ALT_INT), so the items do not depend on
ALT (beyond that 2e-5 scale); only that home record and the GeoJSON heights do.

``--radius`` means, per pattern: the half-width of the search square (lawnmower,
expanding-square), the orbit radius (helix, orbit), the outer ring radius (circles),
half the leg length (close-pass) and the half-width of the keep-in square geofence
(optimal).

Mission size, before anything is sampled: the pattern's segments give the flight
length and time (home -> pattern -> home at ``--speed``) and the waypoint count
(:func:`planner.patterns.estimate_path`). Above ``--warn-flight-time`` (default 30
min, one multirotor battery) a warning goes to stderr and the plan is written; beyond
:data:`MAX_FLIGHT_S` (2 h: no multirotor battery, and a lawnmower of 1 km radius is
6.4 h) or ``--max-items`` (default 500: what PX4 stores on a flight controller,
``NUM_MISSIONS_SUPPORTED``) the plan is refused with the numbers (exit 2).

Exit status: 0 written; 1 the plan is not flyable (a pattern crosses a keep-out, the
optimiser found nothing feasible); 2 bad input, a mission too long or too big, or an
unwritable file, with one line on stderr.
"""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from envs.commands._args import finite_float, positive_float
from envs.commands._outputs import add_force_option

PATTERNS = ("lawnmower", "expanding-square", "helix", "circles", "close-pass", "orbit", "optimal")
MISSION_SUFFIXES = (".plan", ".waypoints", ".txt", ".kml")
MAX_FLIGHT_S = 2 * 3600.0  # hard limit: beyond any multirotor battery
DEFAULT_WARN_FLIGHT_MIN = 30.0  # one battery of a survey multirotor
DEFAULT_MAX_ITEMS = 500  # PX4 on a flight controller (NUM_MISSIONS_SUPPORTED)
MAX_RINGS = 100
RADIUS_HELP = (
    "size in metres, per pattern: half-width of the search square (lawnmower, "
    "expanding-square; default 150), orbit radius (helix, orbit; default 50), outer ring "
    "radius (circles; default 60), half the pass length (close-pass; default 100), "
    "half-width of the keep-in square (optimal; default 200)"
)
DEFAULT_RADIUS_M = {
    "lawnmower": 150.0,
    "expanding-square": 150.0,
    "helix": 50.0,
    "circles": 60.0,
    "close-pass": 100.0,
    "orbit": 50.0,
    "optimal": 200.0,
}


def _latlon(text: str, n: int = 2) -> tuple[float, ...]:
    parts = text.split(",")
    if len(parts) != n:
        want = "LAT,LON" if n == 2 else "LAT,LON,R"
        raise argparse.ArgumentTypeError(f"expected {want}, got {text!r}")
    vals = tuple(finite_float(p.strip()) for p in parts)
    if not -90.0 <= vals[0] <= 90.0:
        from planner.plan_checks import swapped_hint

        raise argparse.ArgumentTypeError(f"latitude {vals[0]:g} outside [-90, 90]"
                                         + swapped_hint(vals[0], vals[1]))
    if not -180.0 <= vals[1] <= 180.0:
        raise argparse.ArgumentTypeError(f"longitude {vals[1]:g} outside [-180, 180]")
    return vals


def _home(text: str) -> tuple[float, ...]:
    parts = text.split(",")
    if len(parts) == 3:
        return (*_latlon(",".join(parts[:2])), finite_float(parts[2]))
    return (*_latlon(text), 0.0)


def _keep_out(text: str) -> tuple[float, ...]:
    vals = _latlon(text, 3)
    if vals[2] <= 0:
        raise argparse.ArgumentTypeError(f"keep-out radius must be > 0: {text!r}")
    return vals


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "plan",
        help="plan a search or localisation flight and write it as a mission",
        description=(
            "Plan a flight pattern (or the CasADi information-optimal path) around a centre "
            "and write it as a QGroundControl .plan or a QGC WPL 110 .waypoints mission. "
            "Southern and western coordinates are negative: --center -33.86,151.21."
        ),
    )
    p.add_argument("pattern", metavar="PATTERN", choices=PATTERNS, help=" | ".join(PATTERNS))
    p.add_argument("-o", "--output", "--out", required=True, metavar="FILE",
                   help=".plan or .waypoints")
    p.add_argument(
        "--center", type=_latlon, metavar="LAT,LON",
        help="centre of the search area / prior AP estimate (degrees); required unless "
             "--area is given",
    )  # fmt: skip
    p.add_argument("--radius", type=positive_float, metavar="M", help=RADIUS_HELP)
    p.add_argument(
        "--alt",
        type=positive_float,
        default=45.0,
        metavar="M",
        help="altitude above home (m, default 45: the paper's 35-55 m AGL)",
    )
    p.add_argument(
        "--home",
        type=_home,
        metavar="LAT,LON[,ALT]",
        help=(
            "home/takeoff point and its height in the datum the vehicle reports (no geoid "
            "conversion; the items are relative to home, so they do not depend on it; "
            "default: the centre, 0 m)"
        ),
    )
    p.add_argument(
        "--speed",
        type=positive_float,
        default=5.0,
        metavar="M/S",
        help="commanded speed; the speed limit for optimal (default 5)",
    )
    p.add_argument(
        "--spacing",
        type=positive_float,
        metavar="M",
        help="track spacing (default 2 R_det (1 - overlap))",
    )
    p.add_argument(
        "--overlap",
        type=finite_float,
        default=0.5,
        metavar="F",
        help="track overlap fraction in [0, 1) (default 0.5)",
    )
    p.add_argument(
        "--heading",
        type=finite_float,
        default=0.0,
        metavar="DEG",
        help="track / first leg / pass heading, clockwise from north (default 0)",
    )
    p.add_argument("--turns", type=positive_float, metavar="N", help="helix 3, orbit 1 by default")
    p.add_argument(
        "--climb",
        type=finite_float,
        default=30.0,
        metavar="M",
        help="helix altitude change (negative descends, default 30)",
    )
    p.add_argument("--rings", type=int, default=3, metavar="N", help="circles: rings (default 3)")
    p.add_argument(
        "--alt-step",
        type=finite_float,
        default=10.0,
        metavar="M",
        help="circles: altitude step between rings (default 10)",
    )
    p.add_argument(
        "--offset",
        type=finite_float,
        default=10.0,
        metavar="M",
        help="close-pass: horizontal offset from the centre (default 10)",
    )
    p.add_argument(
        "--time-budget",
        type=positive_float,
        default=120.0,
        metavar="S",
        help="optimal: flight time of the horizon (default 120)",
    )
    p.add_argument(
        "--prior-sigma",
        type=positive_float,
        default=10.0,
        metavar="M",
        help="optimal: horizontal 1-sigma of the prior AP position (default 10)",
    )
    p.add_argument(
        "--keep-out",
        type=_keep_out,
        action="append",
        default=[],
        metavar="LAT,LON,R",
        help="keep-out cylinder (repeatable)",
    )
    p.add_argument(
        "--tolerance",
        type=positive_float,
        default=1.0,
        metavar="M",
        help="waypoint decimation tolerance (default 1)",
    )
    p.add_argument(
        "--warn-flight-time",
        type=positive_float,
        default=DEFAULT_WARN_FLIGHT_MIN,
        metavar="MIN",
        help=f"warn when the flight (home to home) is longer (default {DEFAULT_WARN_FLIGHT_MIN:g}"
        f" min); beyond {MAX_FLIGHT_S / 3600:g} h the plan is refused",
    )
    p.add_argument(
        "--max-items",
        type=int,
        default=DEFAULT_MAX_ITEMS,
        metavar="N",
        help=f"refuse a mission of more items than the vehicle holds (default "
        f"{DEFAULT_MAX_ITEMS}, PX4 on a flight controller)",
    )
    site = p.add_argument_group("on a site (docs/planner.md)")
    site.add_argument("--area", metavar="FILE",
                      help="search area: a KML (or KMZ) or GeoJSON polygon, or a .plan whose "
                           "geoFence holds one inclusion polygon; lawnmower and expanding-square "
                           "cover it, the other patterns stay inside it")
    site.add_argument("--keepout", action="append", default=[], metavar="FILE",
                      help="keep-outs (KML/GeoJSON polygons or points with radius_m, a "
                           ".plan's exclusion fence; top_m: height above ground); repeatable")
    site.add_argument("--dem", metavar="FILE",
                      help="ground heights (GeoTIFF in any CRS, SRTM .hgt): heights follow "
                           "the ground, every leg within [M - 2, M + 25] m above it")
    site.add_argument("--agl", type=positive_float, metavar="M",
                      help="height above the ground (needs --dem or --alt-frame terrain; "
                           "default: --alt)")
    site.add_argument("--alt-frame", choices=("relative", "terrain", "amsl"), default=None,
                      help="item altitudes: relative to home (frame 6, default), above the "
                           "terrain (frame 11) or above mean sea level (frame 0, needs --dem)")
    site.add_argument("--margin", type=finite_float, default=10.0, metavar="M",
                      help="distance kept from the area's edges and the keep-outs (default 10)")
    p.add_argument("--no-rtl", action="store_true", help="no RETURN_TO_LAUNCH item at the end")
    p.add_argument("--geojson", metavar="PATH", help="also write the plan as GeoJSON")
    add_force_option(p)
    p.set_defaults(func=run)
    return p


class PlanError(Exception):
    """A request that cannot be planned: one line for stderr and the exit status."""

    def __init__(self, message: str, status: int = 2) -> None:
        super().__init__(message)
        self.status = status


@dataclass(frozen=True)
class PlanOutput:
    """What ``osa plan`` computed (before writing files)."""

    trajectory: Any  # estimator.records.Trajectory
    mission: Any  # planner.mission.Mission
    prior_enu_m: Any  # numpy array (3,)
    note: str = ""
    warnings: tuple[str, ...] = ()  # for stderr: the plan is written anyway


def _fail(message: str, status: int = 2) -> int:
    print(f"osa plan: {message}", file=sys.stderr)
    return status


def _fmt(v: float, unit: str = " m") -> str:
    return f"{v:.2f}{unit}" if math.isfinite(v) else "inf"


def pattern_segments(args: argparse.Namespace, pat: Any, radius: float, center, prior,
                      start, flight) -> list:
    """The pattern's exact segments (cheap: nothing sampled yet)."""
    name = args.pattern
    if name in ("lawnmower", "expanding-square"):
        spacing = args.spacing
        if spacing is None:  # the patterns' default: from the detection range at --alt
            r_det = pat.detection_range_m(args.alt, scoring_config().link)
            spacing = pat.lawnmower_spacing_m(r_det, args.overlap)
        if name == "lawnmower":
            return pat.lawnmower_segments(center, radius, spacing, heading_deg=args.heading,
                                          alt_m=args.alt)
        return pat.expanding_square_segments(center, radius, spacing,
                                             heading_deg=args.heading, alt_m=args.alt)
    if name == "helix":
        if args.alt + args.climb <= 0:
            raise PlanError(f"--alt {args.alt:g} with --climb {args.climb:g} goes below home")
        return pat.helix_segments(center, radius, alt_start_m=args.alt,
                                  alt_end_m=args.alt + args.climb, turns=args.turns or 3.0,
                                  start_enu_m=start)
    if name == "circles":
        radii = [radius * (k + 1) / args.rings for k in range(args.rings)]
        alts = [args.alt + k * args.alt_step for k in range(args.rings)]
        if min(alts) <= 0:
            raise PlanError("--alt-step takes a ring below home")
        return pat.concentric_circles_segments(center, radii, alts_m=alts, flight=flight,
                                               start_enu_m=start)
    if name == "close-pass":
        return pat.close_pass_segments(prior, args.offset, leg_length_m=2.0 * radius,
                                       heading_deg=args.heading, flight=flight)
    return pat.helix_segments(center, radius, alt_start_m=args.alt, alt_end_m=args.alt,
                              turns=args.turns or 1.0, start_enu_m=start)


def _fmt_duration(s: float) -> str:
    return f"{s / 3600:.1f} h" if s >= 5400 else f"{s / 60:.0f} min"


def check_mission_size(args: argparse.Namespace, duration_s: float, length_m: float,
                       n_items: int | None, what: str,
                       hint: str = "reduce --radius, widen --spacing or split the area",
                       ) -> list[str]:
    """Refuse (:class:`PlanError`) a mission beyond the hard limits; return the warnings."""
    size = (f"{_fmt_duration(duration_s)} of flight ({length_m / 1000:.1f} km at "
            f"{args.speed:g} m/s, home to home)"
            + (f", at least {n_items} items" if n_items is not None else ""))
    if duration_s > MAX_FLIGHT_S:
        raise PlanError(f"{what} is {size}: beyond the {MAX_FLIGHT_S / 3600:g} h limit of one "
                        f"flight; {hint}")
    if n_items is not None and n_items > args.max_items:
        raise PlanError(f"{what} is {size}: more than the {args.max_items} items a vehicle "
                        "holds (--max-items); raise --tolerance or reduce the pattern")
    if duration_s > args.warn_flight_time * 60.0:
        return [f"{what} is {size}: longer than --warn-flight-time "
                f"{args.warn_flight_time:g} min (more than one battery?)"]
    return []


def _check_suffix(args: argparse.Namespace) -> None:
    if Path(args.output).suffix.lower() not in MISSION_SUFFIXES:
        raise PlanError(f"{args.output}: unknown mission type (use .plan, .waypoints, .txt "
                        "or .kml)")


def claim_outputs(args: argparse.Namespace) -> None:
    """-o and --geojson may be written (envs/commands/_outputs.py: an existing file needs
    --force, an input is never written over), checked before any planning; raises
    :class:`PlanError`."""
    from envs.commands._outputs import OutputRefusedError, claim_output_file

    _check_suffix(args)
    if args.geojson and Path(args.geojson).resolve() == Path(args.output).resolve():
        raise PlanError(f"--geojson {args.geojson} is the mission file -o: name another file")
    inputs = [f for f in (args.area, *args.keepout, args.dem) if f]
    try:
        for path in filter(None, (args.output, args.geojson)):
            claim_output_file(path, force=args.force, inputs=inputs)
    except OutputRefusedError as exc:
        raise PlanError(str(exc)) from None


def build_plan(args: argparse.Namespace) -> PlanOutput:
    """Plan from parsed arguments (no file written); raises :class:`PlanError`."""
    _check_suffix(args)
    if args.center is None:
        raise PlanError("give --center LAT,LON (or --area FILE)")
    if not 0.0 <= args.overlap < 1.0:
        raise PlanError(f"--overlap must be in [0, 1), got {args.overlap:g}")
    if not 1 <= args.rings <= MAX_RINGS:
        raise PlanError(f"--rings must be in 1..{MAX_RINGS}, got {args.rings}")
    if args.max_items < 3:
        raise PlanError(f"--max-items must be >= 3 (takeoff, a waypoint, RTL), got "
                        f"{args.max_items}")

    import numpy as np

    from estimator.geodesy import ExactENU
    from planner import patterns as pat
    from planner.convert import trajectory_to_mission

    name = args.pattern
    radius = args.radius if args.radius is not None else DEFAULT_RADIUS_M[name]
    clat, clon = args.center
    home = tuple(args.home) if args.home is not None else (clat, clon, 0.0)
    frame = ExactENU(*home)
    cx, cy, _ = frame.to_enu(clat, clon, home[2])
    center = (cx, cy)
    prior = np.array([cx, cy, 0.0])
    keep_outs = []
    for lat, lon, r in args.keep_out:
        e, n, _ = frame.to_enu(lat, lon, home[2])
        keep_outs.append(pat.KeepOut(east_m=e, north_m=n, radius_m=r))
    start = (0.0, 0.0, args.alt)  # airborne above home after the takeoff item
    fence = None
    note = ""
    what = f"{name} --radius {radius:g}"
    extra_items = 1 + (0 if args.no_rtl else 1)  # takeoff, RTL
    try:
        if name == "optimal":
            warnings = check_mission_size(args, args.time_budget,
                                          args.time_budget * args.speed, None,
                                          f"optimal --time-budget {args.time_budget:g}",
                                          hint="reduce --time-budget")
            traj, note, fence = _optimal(args, radius, center, prior, start, keep_outs, home)
        else:
            flight = pat.FlightConfig(speed_m_s=args.speed, alt_m=args.alt, origin=home)
            segs = pattern_segments(args, pat, radius, center, prior, start, flight)
            est = pat.estimate_path(segs, flight, start_enu_m=start,
                                    end_enu_m=None if args.no_rtl else start,
                                    tolerance_m=args.tolerance)
            warnings = check_mission_size(args, est.duration_s, est.length_m,
                                          est.n_waypoints + extra_items, what)
            traj = pat.segments_to_trajectory(segs, flight, name, start)
    except ValueError as exc:
        raise PlanError(str(exc)) from None
    if name != "optimal":
        problems = pat.airspace_violations(traj.enu_m, None, keep_outs)
        if problems:
            raise PlanError(f"{name} path {problems[0]}; move the area or plan 'optimal'", 1)
    mission = trajectory_to_mission(
        traj,
        tolerance_m=args.tolerance,
        rtl=not args.no_rtl,
        fence=fence,
        keep_outs=keep_outs,
        home=home,  # the ENU origin: relative altitudes are the trajectory's z
        name=f"osa plan {name}",
    )
    if len(mission.items) > args.max_items:
        raise PlanError(f"{what}: {len(mission.items)} mission items, more than the "
                        f"{args.max_items} a vehicle holds (--max-items); raise --tolerance")
    return PlanOutput(trajectory=traj, mission=mission, prior_enu_m=prior, note=note,
                      warnings=tuple(warnings))


def run(args: argparse.Namespace) -> int:
    from envs.commands.plan_site import run_site, site_requested
    from planner.plan_checks import geometry_warnings, site_warnings

    if args.center is not None:
        points = [("--home", *args.home[:2])] if args.home else []
        points += [("--keep-out", lat, lon) for lat, lon, _ in args.keep_out]
        for w in site_warnings(tuple(args.center), points):
            print(f"osa plan: warning: {w}", file=sys.stderr)
    try:
        claim_outputs(args)
    except PlanError as exc:
        return _fail(str(exc), exc.status)
    if site_requested(args):
        return run_site(args)
    try:
        plan = build_plan(args)
    except PlanError as exc:
        return _fail(str(exc), exc.status)
    for w in plan.warnings:
        print(f"osa plan: warning: {w}", file=sys.stderr)

    import dataclasses

    import numpy as np

    from planner.files import MissionFileError, write_mission
    from planner.mission import MAV_CMD_NAV_WAYPOINT
    from planner.scoring import score_trajectory

    out = Path(args.output)
    traj, mission = plan.trajectory, plan.mission
    fence_note = ""
    if out.suffix.lower() != ".plan" and (mission.polygons or mission.circles):
        mission = dataclasses.replace(mission, polygons=(), circles=())
        fence_note = "not written: a .waypoints file holds no geofence (write a .plan)"
    try:
        write_mission(mission, out)
    except MissionFileError as exc:
        return _fail(str(exc))
    if args.geojson:
        from planner.geojson import plan_geojson, write_geojson

        collection = plan_geojson(
            plan.mission, traj, prior_latlon=tuple(args.center), name=args.pattern
        )
        try:
            write_geojson(collection, args.geojson)
        except (OSError, ValueError) as exc:
            return _fail(f"{args.geojson}: cannot write GeoJSON: {exc}")

    score = score_trajectory(traj, plan.prior_enu_m, scoring_config())
    for w in geometry_warnings(score.condition_number):
        print(f"osa plan: warning: {w}", file=sys.stderr)
    n_wp = sum(1 for it in mission.items if it.command == MAV_CMD_NAV_WAYPOINT)
    dt = float(np.median(np.diff(traj.t_s))) if len(traj.t_s) > 1 else 0.0
    print(f"osa plan {args.pattern} -> {out}")
    print(
        f"  path      {traj.length_m:.1f} m, {traj.duration_s:.1f} s"
        f" ({len(traj.t_s)} samples, {dt:g} s apart)"
    )
    print(
        f"  mission   {len(mission.items)} items (takeoff, {n_wp} waypoints"
        f"{'' if args.no_rtl else ', RTL'}), decimation tolerance {args.tolerance:g} m"
    )
    print(
        f"  geometry  condition number {score.condition_number:.2f},"
        f" GDOP {_fmt(score.gdop, '')}, closest {score.min_slant_m:.1f} m slant,"
        f" {score.expected_measurements:.0f} expected ranges"
    )
    print(
        f"  CRLB      horizontal {_fmt(score.crlb_h_m)}, vertical {_fmt(score.crlb_v_m)}"
        f" (bias estimated); {_fmt(score.crlb_h_known_bias_m)} /"
        f" {_fmt(score.crlb_v_known_bias_m)} (bias known)"
    )
    if fence_note:
        print(f"  fence     {fence_note}")
    if plan.note:
        print(f"  optimal   {plan.note}")
    return 0


def scoring_config():
    """The scorer with the simulator's calibrated link (sim.FtmLink): the planner's
    predictions use the same response model the simulated world has."""
    from planner.scoring import ScoringConfig
    from sim.ftm import FtmLink

    return ScoringConfig(link=FtmLink())


def _optimal(args, radius, center, prior, start, keep_outs, home):
    """Solve the CasADi plan; returns (trajectory, note, fence); raises PlanError."""
    import numpy as np

    from planner.optimal import OptimalConfig, OptimalPlanner
    from planner.patterns import Geofence

    cfg = OptimalConfig(scoring=scoring_config())
    fence = Geofence.square(center, radius)
    if fence.signed_distance_m(np.array([start[:2]]))[0] > -cfg.fence_margin_m:
        raise PlanError(f"home is outside the {radius:g} m keep-in square around --center")
    sigma = args.prior_sigma
    planner = OptimalPlanner(cfg)
    band = (min(cfg.agl_min_m, args.alt), max(cfg.agl_max_m, args.alt))
    res = planner.plan(prior, np.diag([sigma**2, sigma**2, 4.0]), start,
                       horizon_s=args.time_budget, fence=fence, keep_outs=keep_outs,
                       agl_band_m=band, limits=(args.speed, cfg.max_accel_m_s2, cfg.max_climb_m_s),
                       origin=tuple(home))  # fmt: skip
    if not res.feasible:
        raise PlanError("no feasible plan: " + "; ".join(res.violations), 1)
    note = (
        f"ipopt {res.status} in {res.iterations} iterations, {res.solve_time_s * 1e3:.0f} ms;"
        f" objective {res.objective:.3f}"
    )
    if res.fallback:
        note += f"; solver path not used ({'; '.join(res.violations)}), flying {res.fallback}"
    return res.trajectory, note, fence
