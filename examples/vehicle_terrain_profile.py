"""Fly one tour over paper-ap1f's hills with ``osa vehicle``'s autopilot, twice: items above
the terrain (MAVLink frame 11) and the same items relative to home (frame 6), and plot
the height above the ground along the way.

    python examples/vehicle_terrain_profile.py -o docs/figures/vehicle-terrain-profile.png

The autopilot is stepped in process (no network: the same code ``osa vehicle`` runs).
Frame 11 holds the items' height above the ground along the legs too (its own estimate
within centimetres with RTK GNSS, the truth within the GNSS error); frame 6 flies
straight lines at a constant altitude, so its height above the ground follows the hills.
"""

from __future__ import annotations

import argparse
import math
from dataclasses import replace

import numpy as np

from envs.vehicle.autopilot import Autopilot
from envs.vehicle.px4 import Mode
from planner.mavlink_wire import WireItem
from planner.mission import (
    MAV_CMD_NAV_LAND,
    MAV_CMD_NAV_TAKEOFF,
    MAV_CMD_NAV_WAYPOINT,
    MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
    MAV_FRAME_GLOBAL_TERRAIN_ALT_INT,
    MAV_MISSION_TYPE_MISSION,
    deg_to_e7,
)
from sim import Stepper, load_scenario, realise

TOUR_ENU = [(-260.0, 100.0), (-260.0, 300.0), (0.0, 330.0), (260.0, 320.0), (200.0, -200.0)]


def _items(ap: Autopilot, frame: int, height_m: float) -> list[WireItem]:
    def wp(command: int, e: float | None, n: float | None, alt: float) -> WireItem:
        x = y = 0
        if e is not None and n is not None:
            lat, lon, _ = ap.frame.to_geodetic(e, n, 0.0)
            x, y = deg_to_e7(lat), deg_to_e7(lon)
        return WireItem(seq=0, frame=frame, command=command, current=0, autocontinue=1,
                        param1=0.0, param2=0.0, param3=0.0, param4=math.nan, x=x, y=y, z=alt,
                        mission_type=MAV_MISSION_TYPE_MISSION)

    items = [wp(MAV_CMD_NAV_TAKEOFF, None, None, height_m)]
    items += [wp(MAV_CMD_NAV_WAYPOINT, e, n, height_m) for e, n in TOUR_ENU]
    items.append(wp(MAV_CMD_NAV_LAND, None, None, 0.0))
    return [replace(w, seq=k, current=int(k == 0)) for k, w in enumerate(items)]


def fly_tour(scenario: str, frame: int, height_m: float, seed: int) -> dict[str, np.ndarray]:
    """Distance flown, ground, true and estimated height above the ground (1 Hz), from
    the first tour item to the last."""
    sc = load_scenario(scenario)
    ap = Autopilot(Stepper(realise(sc, seed), agents=sc.agents[:1]), wall_clock=lambda: 0.0)
    ap.set_mission(_items(ap, frame, height_m))
    ap.set_mode(Mode.MISSION)
    ap.arm()
    rows = []
    while ap.armed and ap.vehicle.t_s < 1500.0:
        ap.step_to(ap.vehicle.t_s + 1.0)
        x, y, z = ap.vehicle.state.position_m
        p = ap.position
        rows.append((ap.vehicle.t_s, x, y, z, float(ap.world.ground_m(x, y)), ap.agl_m(p)))
    a = np.array(rows)
    t0, t1 = ap.reached_log[1][1], ap.reached_log[len(TOUR_ENU)][1]
    a = a[(a[:, 0] >= t0) & (a[:, 0] <= t1)]
    dist = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(a[:, 1]), np.diff(a[:, 2])))])
    return {"dist": dist, "ground": a[:, 4], "true": a[:, 3] - a[:, 4], "own": a[:, 5],
            "alt": a[:, 3]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("-o", "--output", default="vehicle-terrain-profile.png")
    parser.add_argument("--scenario", default="paper-ap1f-rtk")
    parser.add_argument("--height", type=float, default=60.0, help="items' height (m)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    terrain = fly_tour(args.scenario, MAV_FRAME_GLOBAL_TERRAIN_ALT_INT, args.height, args.seed)
    relative = fly_tour(args.scenario, MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, args.height,
                        args.seed)
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    top.fill_between(terrain["dist"], terrain["ground"].min() - 5, terrain["ground"],
                     color="0.8", label="ground")
    top.plot(terrain["dist"], terrain["alt"], label="frame 11 (above the terrain)")
    top.plot(relative["dist"], relative["alt"], label="frame 6 (relative to home)")
    top.set_ylabel("height, ENU up (m)")
    top.legend(loc="lower right", fontsize=8)
    bottom.axhline(args.height, color="k", lw=0.8, ls=":")
    bottom.plot(terrain["dist"], terrain["true"], label="frame 11, true")
    bottom.plot(terrain["dist"], terrain["own"], lw=0.8, label="frame 11, autopilot's estimate")
    bottom.plot(relative["dist"], relative["true"], label="frame 6, true")
    bottom.set_xlabel("distance flown from the first tour item (m)")
    bottom.set_ylabel("height above ground (m)")
    bottom.legend(loc="center", fontsize=8)
    fig.suptitle(f"{args.scenario}, seed {args.seed}: items {args.height:g} m up")
    fig.tight_layout()
    fig.savefig(args.output, dpi=110)
    for name, r in (("frame 11", terrain), ("frame 6", relative)):
        print(f"{name}: height above ground {r['true'].min():.1f}..{r['true'].max():.1f} m "
              f"true, {r['own'].min():.1f}..{r['own'].max():.1f} m estimated; ground "
              f"{r['ground'].min():.1f}..{r['ground'].max():.1f} m")
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()
