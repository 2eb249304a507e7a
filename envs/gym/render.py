"""Rendering of the environments: a map image (``rgb_array``) and rerun (``human``).

Both show what the agent knows (the autopilot's track, the estimates and their 95 %
circles, the coverage map); the map adds the true responders as stars, marked as the
truth (evaluation), filled once heard, since a person watching wants to see how far
off the estimates are. The map has its axes in metres (the world's ENU frame), a
legend of everything drawn and the flight time.
"""

from __future__ import annotations

import math

import numpy as np

from envs.gym.interface import Pilot
from envs.loop import ClosedLoop
from envs.plots import r95_radius_m

LEGEND_GID = "legend"  # gid of the map's legend (tests look for it)


def map_image(loop: ClosedLoop, pilot: Pilot, size_px: int = 480) -> np.ndarray:
    """(size_px, 1.5 size_px, 3) uint8: :func:`map_figure` rendered."""
    fig = map_figure(loop, pilot, size_px)
    fig.canvas.draw()
    img = np.asarray(fig.canvas.buffer_rgba())[:, :, :3]
    return np.ascontiguousarray(img)


def map_figure(loop: ClosedLoop, pilot: Pilot, size_px: int = 480):
    """The map (area, coverage, track, estimates with their 95 % circles, the truth)
    on the left, its legend and the flight time on the right (a matplotlib Figure on
    its own Agg canvas: no pyplot state)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    dpi = 96
    fig = Figure(figsize=(1.5 * size_px / dpi, size_px / dpi), dpi=dpi)
    FigureCanvasAgg(fig)
    ax = fig.add_axes((0.085, 0.1, 0.6, 0.8))
    enc = pilot.encoder
    area = np.asarray(loop.scenario.search.area_enu_m, dtype=float)
    lo, hi = area.min(axis=0), area.max(axis=0)
    g = enc.cfg.coverage_cells
    cov = (1.0 - np.exp(enc.log_miss)).reshape(g, g)
    ax.imshow(cov, origin="lower", extent=(lo[0], hi[0], lo[1], hi[1]), cmap="Greens",
              vmin=0.0, vmax=1.25, alpha=0.4)  # fully searched: Greens(0.8)
    ax.add_patch(_polygon(area))
    import matplotlib as mpl

    handles = [Line2D([], [], color="k", lw=1.0, label="search area"),
               Patch(fc=mpl.colormaps["Greens"](0.8), alpha=0.4,
                     label="searched (darker: surer)")]
    for k, trk in enumerate(loop.nav_track):
        if trk:
            t = np.asarray(trk)
            ax.plot(t[:, 1], t[:, 2], lw=1.2, color=f"C{k}")
            ax.plot(t[-1, 1], t[-1, 2], "o", color=f"C{k}", ms=5)
            name = "path, drone now" if len(loop.nav_track) == 1 else f"path {k + 1}, drone now"
            handles.append(Line2D([], [], lw=1.2, color=f"C{k}", marker="o", ms=5, label=name))
    heard = not_heard = with_estimate = False
    for b, tr in loop.truth.items():
        p = loop.world.frame.to_enu(tr.lat_deg, tr.lon_deg, tr.alt_m)
        was_heard = loop.detected_at(b) is not None
        heard, not_heard = heard or was_heard, not_heard or not was_heard
        ax.plot(p[0], p[1], "*", mfc="gold" if was_heard else "none", mec="k", ms=12,
                zorder=5)
        e = loop.estimate(b)
        if e.lat_deg is not None:
            with_estimate = True
            q = loop.world.frame.to_enu(e.lat_deg, e.lon_deg, e.alt_m)
            ax.plot(q[0], q[1], "x", color="tab:red", ms=8, mew=1.5, zorder=7)
            r95 = r95_radius_m(e.r95_h_m, e.sigma_h_m)
            if r95:
                th = np.linspace(0, 2 * math.pi, 60)
                ax.plot(q[0] + r95 * np.cos(th), q[1] + r95 * np.sin(th), color="tab:red",
                        lw=0.9, zorder=6)
    if with_estimate:
        handles += [Line2D([], [], ls="none", marker="x", color="tab:red", ms=8, mew=1.5,
                           label="estimate"),
                    Line2D([], [], ls="none", marker="o", ms=11, mfc="none", mec="tab:red",
                           label="95 % circle")]
    if heard:
        handles.append(Line2D([], [], ls="none", marker="*", mfc="gold", mec="k", ms=12,
                              label="responder heard (truth)"))
    if not_heard:
        handles.append(Line2D([], [], ls="none", marker="*", mfc="none", mec="k", ms=12,
                              label="not heard yet (truth)"))
    ax.set_xlim(lo[0] - 20, hi[0] + 20)
    ax.set_ylim(lo[1] - 20, hi[1] + 20)
    ax.set_aspect("equal")
    ax.set_xlabel("east (m)", fontsize=8)
    ax.set_ylabel("north (m)", fontsize=8)
    ax.tick_params(labelsize=7)
    ax.set_title(loop.scenario.name, fontsize=9)
    fig.legend(handles=handles, loc="upper left", bbox_to_anchor=(0.71, 0.9), fontsize=8,
               frameon=False).set_gid(LEGEND_GID)
    fig.text(0.72, 0.1, f"flight time {loop.t_s / 60:.1f} min ({loop.t_s:.0f} s)\n"
             f"localised {len(pilot.localised)} of {len(loop.truth)}", fontsize=8.5,
             va="bottom")
    return fig


def _polygon(area: np.ndarray):
    from matplotlib.patches import Polygon

    return Polygon(area, closed=True, fill=False, ec="k", lw=1.0)


def log_rerun(rec, loop: ClosedLoop, pilot: Pilot) -> None:
    """Log the current state to a rerun recording (entity paths as envs.viz)."""
    import rerun as rr

    rec.set_time("flight_time", duration=loop.t_s)
    for k, trk in enumerate(loop.nav_track):
        if trk:
            t = np.asarray(trk)[:, 1:4]
            rec.log(f"world/drone_{k}/track", rr.LineStrips3D([t], colors=[(31, 119, 180)]))
    for b in loop.truth:
        e = loop.estimate(b)
        if e.lat_deg is not None:
            q = loop.world.frame.to_enu(e.lat_deg, e.lon_deg, e.alt_m)
            s = (e.sigma_h_m or 1.0) / math.sqrt(2.0)
            rec.log(f"world/ap/{b.replace(':', '')}/estimate",
                    rr.Ellipsoids3D(centers=[q], half_sizes=[[s, s, e.sigma_z_m or s]]))
            rec.log(f"plots/{b.replace(':', '')}/sigma_h_m", rr.Scalars([e.sigma_h_m]))
