"""Figures of a closed-loop search (``osa search``): where it flew, and how the error and
the uncertainty evolved.

* :func:`search_trajectory_figure`: a map of the area over the ground (any terrain of
  the planner's protocol; flat ground is not drawn), the path flown, every responder
  (the truth: an open star, by concealment class, drawn under the estimates) and the
  final estimates with their unfilled 95 % circles; beside it one zoom panel per
  responder with an estimate, where the circle and the truth are metres apart.
* :func:`search_error_figure`: per responder, (a) the horizontal error against the
  truth and (b) the estimator's sigma_H and 95 % radius, against flight time, with
  the times it was first heard and judged localised.

The 95 % circle is the estimator's ``r95_h_m``, else 2.45 sigma_H
(:func:`envs.plots.r95_radius_m`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from envs.loop import SearchResult
from envs.plots import (
    LABEL_GID,
    RESPONDER_GID,
    draw_ground,
    framed_extent,
    ground_colorbar,
    ground_grid,
    place_labels,
    plain_log_ticks,
    pyplot,
    r95_radius_m,
    save_figure,
    set_extent,
    short_id,
    zoom_extent,
)
from planner.models import TerrainModel

CONCEALMENT_COLOURS = {
    "open": "tab:green",
    "vegetation": "tab:olive",
    "vegetation_debris": "tab:brown",
}
RESPONDER_COLOURS = ("tab:blue", "tab:orange", "tab:purple", "tab:red", "tab:cyan",
                     "tab:pink", "tab:gray")
R95_GID = "r95"  # gid prefix of the 95 % circles (``r95:<bssid>``)
TRUTH_Z, CIRCLE_Z, ESTIMATE_Z = 6.0, 7.0, 8.0  # the estimate and its circle over the truth
MAX_ZOOMS = 4


def _colour(k: int) -> str:
    return RESPONDER_COLOURS[k % len(RESPONDER_COLOURS)]


def _truth_style(concealment: str) -> dict:
    return dict(marker="*", ms=15, mfc="none", mew=1.6, ls="none", zorder=TRUTH_Z,
                mec=CONCEALMENT_COLOURS.get(concealment, "black"))


def _estimate(ax, est, r95: float | None, colour: str, bssid: str) -> None:
    """The estimate (a dot with a white rim) and its unfilled 95 % circle, over the truth."""
    ax.plot(est[0], est[1], marker="o", ms=5, mfc=colour, mec="white", mew=0.6, ls="none",
            zorder=ESTIMATE_Z)
    if r95 is not None:
        ax.add_patch(pyplot().Circle(est[:2], r95, fill=False, color=colour, lw=1.3,
                                     zorder=CIRCLE_Z, gid=f"{R95_GID}:{bssid}"))


def search_extent(area_enu_m, points=()) -> tuple[float, float, float, float]:
    """The search area plus a 5 % margin, widened only for a point outside it."""
    area = np.asarray(area_enu_m, dtype=float).reshape(-1, 2)
    pts = np.vstack([area, np.asarray(list(points), dtype=float).reshape(-1, 2)])
    ext = framed_extent(area, margin=0.05)
    out = framed_extent(pts, margin=0.05)
    return (min(ext[0], out[0]), max(ext[1], out[1]), min(ext[2], out[2]),
            max(ext[3], out[3]))


def search_trajectory_figure(result: SearchResult, title: str = "", *,
                             terrain: TerrainModel | None = None):
    """Map of the search over the ground and a zoom on each responder with an estimate.

    ``terrain`` is the world's (its ENU frame is the figure's): ``osa search`` passes
    ``sim.realise(scenario, seed).world.terrain``."""
    from matplotlib.lines import Line2D

    plt = pyplot()
    resp = list(result.responders)
    colours = {r["bssid"]: _colour(k) for k, r in enumerate(resp)}
    zoomed = [r for r in resp if r["bssid"] in result.estimates_enu_m
              and r["bssid"] in result.truth_enu_m][:MAX_ZOOMS]
    fig = plt.figure(figsize=(11.8 if zoomed else 9.4, 7.4), layout="constrained")
    if zoomed:
        gs = fig.add_gridspec(1, 2, width_ratios=[2.4, 1.0])
        ax = fig.add_subplot(gs[0, 0])
        right = gs[0, 1].subgridspec(len(zoomed), 1)
    else:
        ax = fig.add_subplot()
    area = np.asarray((*result.area_enu_m, result.area_enu_m[0]), dtype=float)
    extent = search_extent(result.area_enu_m, [*(v[:2] for v in result.truth_enu_m.values()),
                                               *(v[:2] for v in result.estimates_enu_m.values())])
    set_extent(ax, extent)
    grid = ground_grid(terrain, extent)
    if grid is not None:
        ground_colorbar(fig, draw_ground(ax, grid), ax)
    ax.plot(area[:, 0], area[:, 1], color="black", lw=1.2, label="search area", zorder=3)
    for k, trk in enumerate(result.nav_track):
        if trk:
            p = np.asarray(trk)
            ax.plot(p[:, 1], p[:, 2], color="0.25", lw=0.9, zorder=4,
                    label="flight path" if k == 0 else None)
            ax.plot(p[0, 1], p[0, 2], marker="^", color="black", ms=8, ls="none", zorder=5,
                    label="take-off" if k == 0 else None)
    labels = []
    seen_classes: list[str] = []
    estimates: list[str] = []
    for r in resp:
        b = r["bssid"]
        tr = result.truth_enu_m.get(b)
        conc = r.get("concealment", "open")
        if tr is not None:
            ax.plot(tr[0], tr[1], gid=f"{RESPONDER_GID}:{b}", **_truth_style(conc))
            if conc not in seen_classes:
                seen_classes.append(conc)
        est = result.estimates_enu_m.get(b)
        if est is not None:
            _estimate(ax, est, r95_radius_m(r.get("r95_h_m"), r.get("sigma_h_m")), colours[b],
                      b)
            estimates.append(b)
        if tr is not None:
            err = r.get("err_h_m")
            txt = f"{short_id(b)}: " + (f"{err:.1f} m off" if err is not None else r["status"])
            labels.append((tr[0], tr[1], txt))
    handles, names = ax.get_legend_handles_labels()
    for b in estimates:  # a dot in its circle
        handles.append((Line2D([], [], ls="none", marker="o", ms=5, mfc=colours[b],
                               mec="white", mew=0.6),
                        Line2D([], [], ls="none", marker="o", ms=13, mfc="none",
                               mec=colours[b], mew=1.3)))
        names.append(f"estimate {short_id(b)}, 95 % circle")
    for conc in seen_classes:
        handles.append(Line2D([], [], **{**_truth_style(conc), "ms": 12}))
        names.append(f"responder, truth ({conc})")
    ax.set_xlabel("east (m)")
    ax.set_ylabel("north (m)")
    ax.set_title(title or f"{result.scenario}: {result.policy}, seed {result.seed}, "
                 f"ended {result.ended} at {result.flight_time_s / 60:.1f} min", fontsize=10)
    ax.grid(alpha=0.3)
    for k, r in enumerate(zoomed):
        _zoom(fig.add_subplot(right[k, 0]), result, r, colours[r["bssid"]])
    fig.legend(handles, names, loc="outside lower center", ncol=min(4, len(handles)),
               fontsize=8, frameon=False)
    fig.canvas.draw()
    place_labels(ax, labels)
    return fig


def _zoom(ax, result: SearchResult, r: dict, colour: str) -> None:
    """One responder up close: the truth, the estimate and its 95 % circle."""
    b = r["bssid"]
    tr, est = result.truth_enu_m[b], result.estimates_enu_m[b]
    r95 = r95_radius_m(r.get("r95_h_m"), r.get("sigma_h_m"))
    ax.plot(tr[0], tr[1], gid=f"{RESPONDER_GID}:{b}", **_truth_style(r.get("concealment", "")))
    _estimate(ax, est, r95, colour, b)
    set_extent(ax, zoom_extent(tr[:2], [(est[0], est[1], r95 or 0.0)]))
    ax.grid(alpha=0.3)
    ax.tick_params(labelsize=7)
    err = r.get("err_h_m")
    ax.set_title(f"{short_id(b)} ({r.get('concealment', '?')})"
                 + (f": {err:.1f} m off" if err is not None else "")
                 + (f", 95 % radius {r95:.1f} m" if r95 is not None else ""), fontsize=8)


def search_error_figure(result: SearchResult, title: str = ""):
    plt = pyplot()
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(9.6, 6.4), sharex=True)
    any_est = False
    for k, r in enumerate(result.responders):
        b = r["bssid"]
        pts = result.series.get(b, [])
        c = _colour(k)
        t = np.array([p.t_s for p in pts]) / 60.0
        err = np.array([np.nan if p.err_h_m is None else p.err_h_m for p in pts])
        sig = np.array([np.nan if p.sigma_h_m is None else p.sigma_h_m for p in pts])
        r95 = np.array([np.nan if p.r95_h_m is None else p.r95_h_m for p in pts])
        name = f"{short_id(b)} ({r.get('concealment', '?')})"
        if not np.isfinite(err).any():  # listed all the same: every responder shows
            ax1.plot([], [], color=c, lw=1.4, ls=":",
                     label=f"{name}: {'no estimate' if 'detected_at_s' in r else 'never heard'}")
        else:
            any_est = True
            ax1.plot(t, err, color=c, lw=1.4, label=name)
            ax2.plot(t, sig, color=c, lw=1.4, label=f"{b[-5:]} sigma_H")
            if np.isfinite(r95).any():
                ax2.plot(t, r95, color=c, lw=1.0, ls="--", label=f"{b[-5:]} 95 % radius")
        for ax in (ax1, ax2):
            if "detected_at_s" in r:
                ax.axvline(r["detected_at_s"] / 60.0, color=c, lw=0.8, ls=":")
            if "localised_at_s" in r:
                ax.axvline(r["localised_at_s"] / 60.0, color=c, lw=1.2, ls="-.")
    if any_est:
        for ax in (ax1, ax2):
            ax.set_yscale("log")
            plain_log_ticks(ax)
            ax.grid(alpha=0.3, which="both")
        ax1.axhline(1.0, color="black", lw=0.8, ls=":")
        ax1.set_ylabel("horizontal error (m)")
        ax2.set_ylabel("uncertainty (m)")
        ax1.legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=8, frameon=False)
        ax2.legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=8, frameon=False)
    else:
        for ax in (ax1, ax2):
            ax.text(0.5, 0.5, "no estimates", transform=ax.transAxes, ha="center",
                    va="center", gid=LABEL_GID)
            ax.set_yticks([])
    ax2.set_xlabel("flight time (min)")
    ax1.set_title("(a) horizontal error against the truth", fontsize=9, loc="left")
    ax2.set_title("(b) the estimator's sigma_H (solid) and 95 % radius (dashed)", fontsize=9,
                  loc="left")
    fig.suptitle(title or (f"{result.scenario}: {result.policy}, seed {result.seed}; "
                           "dotted: first heard, dash-dot: judged localised"), fontsize=10)
    fig.tight_layout(rect=(0.0, 0.0, 0.7, 1.0))
    return fig


def plot_search(result: SearchResult, out_dir: str | Path, *,
                terrain: TerrainModel | None = None) -> tuple[Path, Path]:
    """Write ``trajectory.png`` (over ``terrain``, the world's) and ``errors.png`` into
    ``out_dir``."""
    out = Path(out_dir)
    p1 = save_figure(search_trajectory_figure(result, terrain=terrain), out / "trajectory.png")
    p2 = save_figure(search_error_figure(result), out / "errors.png")
    return p1, p2
