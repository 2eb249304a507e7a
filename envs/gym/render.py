"""Rendering of the environments: a map image (``rgb_array``) and rerun (``human``).

Both show what the agent knows (the autopilot's track, the estimates and their 95 %
circles, the coverage map); the map adds the true responders as gold stars, marked as
the truth (evaluation), since a person watching wants to see how far off the estimates
are.
"""

from __future__ import annotations

import math

import numpy as np

from envs.gym.interface import Pilot
from envs.loop import ClosedLoop


def map_image(loop: ClosedLoop, pilot: Pilot, size_px: int = 480) -> np.ndarray:
    """(H, W, 3) uint8: area, coverage, track, estimates (95 % circles) and truth."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    dpi = 96
    fig = Figure(figsize=(size_px / dpi, size_px / dpi), dpi=dpi)
    FigureCanvasAgg(fig)
    ax = fig.add_axes((0.08, 0.06, 0.9, 0.88))
    enc = pilot.encoder
    area = np.asarray(loop.scenario.search.area_enu_m, dtype=float)
    lo, hi = area.min(axis=0), area.max(axis=0)
    g = enc.cfg.coverage_cells
    cov = (1.0 - np.exp(enc.log_miss)).reshape(g, g)
    ax.imshow(cov, origin="lower", extent=(lo[0], hi[0], lo[1], hi[1]), cmap="Greens",
              vmin=0.0, vmax=1.0, alpha=0.5)
    ax.add_patch(_polygon(area))
    for k, trk in enumerate(loop.nav_track):
        if trk:
            t = np.asarray(trk)
            ax.plot(t[:, 1], t[:, 2], lw=1.2, color=f"C{k}")
            ax.plot(t[-1, 1], t[-1, 2], "o", color=f"C{k}", ms=5)
    for b, tr in loop.truth.items():
        p = loop.world.frame.to_enu(tr.lat_deg, tr.lon_deg, tr.alt_m)
        ax.plot(p[0], p[1], "*", color="gold", mec="k", ms=12, label="truth (evaluation)")
        e = loop.estimate(b)
        if e.lat_deg is not None:
            q = loop.world.frame.to_enu(e.lat_deg, e.lon_deg, e.alt_m)
            ax.plot(q[0], q[1], "x", color="tab:red", ms=8)
            r95 = e.r95_h_m if e.r95_h_m is not None and math.isfinite(e.r95_h_m) else None
            if r95:
                th = np.linspace(0, 2 * math.pi, 60)
                ax.plot(q[0] + r95 * np.cos(th), q[1] + r95 * np.sin(th), color="tab:red",
                        lw=0.8)
    ax.set_xlim(lo[0] - 20, hi[0] + 20)
    ax.set_ylim(lo[1] - 20, hi[1] + 20)
    ax.set_aspect("equal")
    ax.set_title(f"{loop.scenario.name}  t = {loop.t_s:.0f} s  localised "
                 f"{len(pilot.localised)}", fontsize=9)
    ax.tick_params(labelsize=7)
    fig.canvas.draw()
    img = np.asarray(fig.canvas.buffer_rgba())[:, :, :3]
    return np.ascontiguousarray(img)


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
