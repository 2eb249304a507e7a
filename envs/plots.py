"""Figures of a replay: the paper's trajectory figure and its convergence figure, and
what every figure of the project shares (labels that avoid each other, the ground).

* :func:`trajectory_figure` / :func:`plot_trajectory`: a map of the drone's GNSS track
  in the replay's ENU frame over the ground, every surveyed responder (also those that
  never answered) and the estimates, framed on the flight; beside it one zoom panel
  per responder with estimates: every mode's estimate and sigma_H circle, the truth.
* :func:`convergence_figure` / :func:`plot_convergence`: one column per responder:
  (a) sigma_H against time since bootstrap for every mode with the 2.5 m threshold,
  (b) 2-D error against the truth over the same time, the reported (final) errors
  labelled at the right, each joined to the time its estimate was published.
* The ground: :func:`ground_grid` evaluates any terrain of the planner's protocol
  (:class:`planner.models.TerrainModel`, ``height_m(e, n)``: hills, grids, DEMs) on a
  figure's extent, :func:`draw_ground` draws it light (hillshade and contours) under
  the tracks, :func:`ground_colorbar` gives its heights in metres. Ground with less
  than :data:`FLAT_RELIEF_M` of relief over the extent is not drawn.

Readability rules, checked by tests/envs/test_figures.py: legends sit outside the
data axes, labels never overlap one another, every mode has its own colour, line
style and marker (EMA smooths Baseline's filter, so their curves nearly coincide),
every responder is drawn inside the axes, and a figure without estimates says so
instead of drawing an empty 0-1 axis.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from estimator.geodesy import EnuFrame
from estimator.replay import ReplayReport, TrackResult
from planner.models import TerrainModel

MODE_COLOURS = {
    "baseline": "tab:blue",
    "nlos": "tab:orange",
    "empirical-r": "tab:green",
    "ukf": "tab:red",
    "ema": "tab:purple",
    "adaptive-r": "tab:brown",
    "robust": "black",
    "refined": "tab:pink",
}
# (line style, line width, marker): Baseline is drawn wide and first, EMA dashed on it
MODE_STYLES: dict[str, tuple[Any, float, str]] = {
    "baseline": ("-", 2.6, "o"),
    "nlos": (":", 1.6, "v"),
    "empirical-r": ("-", 1.1, "s"),
    "ukf": ("-.", 1.2, "^"),
    "ema": ("--", 1.2, "x"),
    "adaptive-r": ((0, (6, 1.5, 1, 1.5, 1, 1.5)), 1.2, "D"),
    "robust": ("-", 0.9, "*"),
    "refined": ("-", 1.4, "P"),
}
RESPONDER_GID = "responder"  # gid of each surveyed responder's marker (tests count them)
LABEL_GID = "label"  # gid of the texts that must not overlap


def pyplot():
    """matplotlib.pyplot on the Agg backend (files, no display)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plain_log_ticks(ax) -> None:
    """A log y axis labelled 1, 2, 5, 10, 20 ... instead of 2 x 10^0."""
    from matplotlib.ticker import FuncFormatter, LogLocator

    ax.yaxis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
    ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    ax.yaxis.set_minor_formatter(FuncFormatter(lambda v, _: ""))


def mode_style(mode: str) -> dict[str, Any]:
    """Line keyword arguments of a mode (colour, style, width, marker)."""
    ls, lw, marker = MODE_STYLES.get(mode, ("-", 1.0, "."))
    return {"color": MODE_COLOURS.get(mode, "gray"), "ls": ls, "lw": lw, "marker": marker}


def with_plot_frame(report: ReplayReport, log_paths: Sequence[str | Path]) -> ReplayReport:
    """The report with an ENU frame even when no range was associated (then eq. (1) at
    the first GNSS fix) and every surveyed responder placed in it, so a flight without a
    single usable range, or a responder that never answered, still shows."""
    frame = report.frame
    if frame is None:
        from estimator.geodesy import TangentPlaneENU
        from estimator.logio import iter_log
        from estimator.records import GnssFix

        first = None
        for p in log_paths:
            for r in iter_log(p):
                if isinstance(r, GnssFix) and (first is None or r.t_ns < first.t_ns):
                    first = r
        if first is None:
            return report
        frame = TangentPlaneENU(first.lat_deg, first.lon_deg, first.alt_m)
    tracks = []
    for t in report.tracks:
        tru = report.truth.get(t.bssid)
        if tru is not None and t.truth_enu_m is None:
            t = dataclasses.replace(
                t, truth_enu_m=tuple(frame.to_enu(tru.lat_deg, tru.lon_deg, tru.alt_m))
            )
        tracks.append(t)
    return dataclasses.replace(report, tracks=tracks, frame=frame)


def gnss_track_enu(report: ReplayReport, log_paths: Sequence[str | Path]) -> list[np.ndarray]:
    """The logged GNSS fixes of each log in the report's ENU frame (N x 3 each)."""
    from estimator.logio import iter_log
    from estimator.records import GnssFix

    out = []
    if report.frame is None:
        return out
    for p in log_paths:
        fixes = [r for r in iter_log(p) if isinstance(r, GnssFix)]
        fixes.sort(key=lambda r: r.t_ns)
        if not fixes:
            continue
        lat = np.array([f.lat_deg for f in fixes])
        lon = np.array([f.lon_deg for f in fixes])
        alt = np.array([f.alt_m for f in fixes])
        e, n, u = report.frame.to_enu(lat, lon, alt)
        out.append(np.column_stack((e, n, u)))
    return out


@dataclasses.dataclass(frozen=True)
class PlacedResponder:
    """A surveyed responder placed in a replay's frame, with its best status; or, for a
    log without ``truth`` (a real flight), an estimated one placed at its best-observed
    estimate (``surveyed`` False)."""

    bssid: str
    enu_m: tuple[float, float, float]
    concealment: str
    status: str  # the best status over the modes
    has_estimate: bool
    surveyed: bool = True


_STATUS_RANK = ("converged", "tracking", "weak_geometry", "bootstrapping", "diverged", "no_data")


def responders(report: ReplayReport) -> list[PlacedResponder]:
    """Every surveyed responder of the report (truth known and placed), in report order,
    then surveyed responders the log never mentioned in an ``rtt`` record."""
    by: dict[str, list[TrackResult]] = {}
    for t in report.tracks:
        by.setdefault(t.bssid, []).append(t)
    out = []
    for bssid, rows in by.items():
        placed = [r for r in rows if r.truth_enu_m is not None]
        if not placed:
            continue
        ranks = [_STATUS_RANK.index(r.status) if r.status in _STATUS_RANK else 9 for r in rows]
        best = rows[int(np.argmin(ranks))].status
        conc = rows[0].concealment or report.truth[bssid].concealment
        out.append(PlacedResponder(bssid, placed[0].truth_enu_m, conc, best,
                              any(r.estimate is not None for r in rows)))
    if report.frame is not None:
        for bssid, tru in report.truth.items():
            if bssid not in by:  # surveyed, never ranged
                enu = tuple(report.frame.to_enu(tru.lat_deg, tru.lon_deg, tru.alt_m))
                out.append(PlacedResponder(bssid, enu, tru.concealment, "not ranged", False))
    return out


def unsurveyed_estimates(report: ReplayReport) -> list[PlacedResponder]:
    """The responders with estimates but no ``truth`` record, each placed at the
    estimate of its mode with the most accepted ranges (what the zoom panels centre on
    for a real flight)."""
    by: dict[str, list[TrackResult]] = {}
    for t in report.tracks:
        if t.estimate is not None and t.truth_enu_m is None and t.bssid not in report.truth:
            by.setdefault(t.bssid, []).append(t)
    out = []
    for bssid, rows in by.items():
        best = max(rows, key=lambda t: t.counts["n_acc"])
        ranks = [_STATUS_RANK.index(r.status) if r.status in _STATUS_RANK else 9 for r in rows]
        out.append(PlacedResponder(bssid, tuple(best.estimate.enu_m), "no survey",
                                   rows[int(np.argmin(ranks))].status, True, surveyed=False))
    return out


def short_id(bssid: str) -> str:
    """The last two octets of a BSSID: how the figures name a responder."""
    return bssid[-5:]


# --------------------------------------------------------------------------- labels
def _overlaps(a, b) -> bool:
    return not (a.x1 <= b.x0 or b.x1 <= a.x0 or a.y1 <= b.y0 or b.y1 <= a.y0)


def place_labels(ax, points: Sequence[tuple[float, float, str]],
                 fontsize: float = 7.5) -> list:
    """Annotate each (x, y, text) at the first of a few offsets where the label overlaps
    no label placed before and stays inside the axes; when none does, it is stacked
    above the others on a leader line."""
    fig = ax.figure
    renderer = fig.canvas.get_renderer()
    offsets = [(7, 7, "left", "bottom"), (7, -7, "left", "top"), (-7, 7, "right", "bottom"),
               (-7, -7, "right", "top"), (0, 14, "center", "bottom"),
               (0, -14, "center", "top"), (7, 24, "left", "bottom"), (-7, -24, "right", "top"),
               (14, 0, "left", "center"), (-14, 0, "right", "center")]
    placed: list = []
    texts = []
    ax_box = ax.get_window_extent(renderer)
    box_style = {"boxstyle": "round,pad=0.15", "fc": "white", "ec": "none", "alpha": 0.8}
    for x, y, text in points:
        chosen = None
        for dx, dy, ha, va in offsets:
            t = ax.annotate(text, (x, y), xytext=(dx, dy), textcoords="offset points",
                            ha=ha, va=va, fontsize=fontsize, gid=LABEL_GID, zorder=9,
                            bbox=box_style)
            box = t.get_window_extent(renderer)
            inside = (box.x0 >= ax_box.x0 and box.x1 <= ax_box.x1 and box.y0 >= ax_box.y0
                      and box.y1 <= ax_box.y1)
            if inside and not any(_overlaps(box, b) for b in placed):
                chosen = (t, box)
                break
            t.remove()
        if chosen is None:  # crowded: above everything placed so far, on a leader line
            top = max((b.y1 for b in placed), default=ax_box.y0)
            py = ax.transData.transform((x, y))[1]
            dy = max(7.0, (top - py) * 72.0 / fig.dpi + 4.0)
            t = ax.annotate(text, (x, y), xytext=(7, dy), textcoords="offset points",
                            ha="left", va="bottom", fontsize=fontsize, gid=LABEL_GID,
                            zorder=9, bbox=box_style, annotation_clip=False,
                            arrowprops={"arrowstyle": "-", "lw": 0.5, "color": "0.4",
                                        "relpos": (0.0, 0.0)})
            chosen = (t, t.get_window_extent(renderer))
        placed.append(chosen[1])
        texts.append(chosen[0])
    return texts


# --------------------------------------------------------------------------- ground
GROUND_GID = "ground"  # gid of the ground's image and contours (tests look for them)
FLAT_RELIEF_M = 0.5  # less relief than this over the plotted extent: no ground drawn
GROUND_CELLS = 220  # grid points along the longer side of the plotted extent


@dataclasses.dataclass(frozen=True)
class GroundGrid:
    """Ground heights on a regular grid of a figure's extent, in the figure's frame.

    ``height_m[i, j]`` at (``e_m[j]``, ``n_m[i]``); NaN where the terrain gives none.
    """

    e_m: np.ndarray
    n_m: np.ndarray
    height_m: np.ndarray

    @property
    def relief_m(self) -> float:
        h = self.height_m[np.isfinite(self.height_m)]
        return float(h.max() - h.min()) if h.size else 0.0


def ground_grid(terrain: TerrainModel | None, extent: Sequence[float], *,
                terrain_frame: EnuFrame | None = None, plot_frame: EnuFrame | None = None,
                cells: int = GROUND_CELLS) -> GroundGrid | None:
    """The heights of ``terrain`` (the planner's protocol: ``height_m(e, n)`` on NumPy
    arrays) over ``extent`` = (e_min, e_max, n_min, n_max) of a figure, or None where
    there is nothing to show: no terrain, or less than :data:`FLAT_RELIEF_M` of relief.

    The figure's coordinates are in ``plot_frame`` and the terrain's in
    ``terrain_frame`` (a replay's frame is set at its first GNSS fix, the world's at its
    origin); when both are given each grid point goes through WGS84 from one to the
    other. Without them the two are the same frame.
    """
    if terrain is None:
        return None
    e0, e1, n0, n1 = (float(v) for v in extent)
    span = max(e1 - e0, n1 - n0)
    if not (math.isfinite(span) and span > 0):
        return None
    step = span / max(cells - 1, 1)
    e = np.linspace(e0, e1, max(2, round((e1 - e0) / step) + 1))
    n = np.linspace(n0, n1, max(2, round((n1 - n0) / step) + 1))
    ee, nn = np.meshgrid(e, n)
    qe, qn = ee.ravel(), nn.ravel()
    if terrain_frame is not None and plot_frame is not None and terrain_frame != plot_frame:
        lat, lon, alt = plot_frame.to_geodetic(qe, qn, np.zeros_like(qe))
        qe, qn, _ = terrain_frame.to_enu(lat, lon, alt)
        qe, qn = np.asarray(qe, dtype=float), np.asarray(qn, dtype=float)
    h = np.asarray(terrain.height_m(qe, qn), dtype=float).reshape(ee.shape)
    grid = GroundGrid(e, n, np.where(np.isfinite(h), h, np.nan))
    return grid if grid.relief_m >= FLAT_RELIEF_M else None


def _ground_colours():
    """A light terrain colour map (low green to high sand), half-way to white."""
    import matplotlib as mpl
    from matplotlib.colors import ListedColormap

    base = mpl.colormaps["gist_earth"](np.linspace(0.38, 0.86, 256))[:, :3]
    return ListedColormap(np.column_stack((1.0 - 0.5 * (1.0 - base), np.ones(256))),
                          name="osa-ground")


def ground_norm(grids: Sequence[GroundGrid]):
    """One colour scale (metres) for every grid of a figure."""
    from matplotlib.colors import Normalize

    lo = min(float(np.nanmin(g.height_m)) for g in grids)
    hi = max(float(np.nanmax(g.height_m)) for g in grids)
    return Normalize(lo, hi)


def draw_ground(ax, grid: GroundGrid, norm=None):
    """Hillshaded heights under everything else of ``ax`` (light colours, the sun in
    the north-west) and thin contours; returns the mappable for a colour bar."""
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import LightSource
    from matplotlib.ticker import MaxNLocator

    cmap = _ground_colours()
    norm = norm if norm is not None else ground_norm([grid])
    h = grid.height_m
    valid = np.isfinite(h)
    filled = np.where(valid, h, np.nanmin(h))
    de = float(grid.e_m[1] - grid.e_m[0])
    dn = float(grid.n_m[1] - grid.n_m[0])
    # rows from north to south, as LightSource and an upper-origin image take them
    rgba = LightSource(azdeg=315, altdeg=45).shade(
        filled[::-1], cmap=cmap, norm=norm, blend_mode="soft", vert_exag=2.0, dx=de, dy=dn)
    rgba = 1.0 - 0.75 * (1.0 - rgba)  # shading kept soft: the tracks stay readable
    rgba[..., 3] = valid[::-1]
    ext = (grid.e_m[0] - de / 2, grid.e_m[-1] + de / 2, grid.n_m[0] - dn / 2,
           grid.n_m[-1] + dn / 2)
    xlim, ylim = ax.get_xlim(), ax.get_ylim()
    auto = ax.get_autoscale_on()
    ax.imshow(rgba, extent=ext, origin="upper", interpolation="bilinear", zorder=0,
              gid=GROUND_GID, aspect="auto")
    levels = MaxNLocator(nbins=8, steps=[1, 2, 2.5, 5, 10]).tick_values(norm.vmin, norm.vmax)
    ax.contour(grid.e_m, grid.n_m, np.ma.masked_invalid(h), levels=levels, colors="0.45",
               linewidths=0.45, alpha=0.55, zorder=0.2,
               negative_linestyles="solid").set_gid(GROUND_GID)
    if not auto:
        ax.set_xlim(xlim)
        ax.set_ylim(ylim)
    ax.set_autoscale_on(auto)
    ax.set_axisbelow(True)
    return ScalarMappable(norm=norm, cmap=cmap)


def ground_colorbar(fig, mappable, axes, **kw):
    """The ground's colour bar beside ``axes``, in metres."""
    cb = fig.colorbar(mappable, ax=axes, shrink=kw.pop("shrink", 0.75),
                      pad=kw.pop("pad", 0.02), aspect=kw.pop("aspect", 30), **kw)
    cb.set_label("ground height (m)", fontsize=8)
    cb.ax.tick_params(labelsize=7)
    cb.ax.set_gid(GROUND_GID)
    return cb


def framed_extent(points: np.ndarray, margin: float = 0.06,
                  least_m: float = 20.0) -> tuple[float, float, float, float]:
    """(e_min, e_max, n_min, n_max) holding ``points`` (N x 2) with ``margin`` of the
    larger span on every side (at least ``least_m`` wide)."""
    p = np.asarray(points, dtype=float).reshape(-1, 2)
    p = p[np.all(np.isfinite(p), axis=1)]
    if not len(p):
        return (-least_m, least_m, -least_m, least_m)
    lo, hi = p.min(axis=0), p.max(axis=0)
    span = max(float(np.max(hi - lo)), least_m)
    pad = margin * span
    mid = 0.5 * (lo + hi)
    half = np.maximum(0.5 * (hi - lo), 0.5 * least_m) + pad
    return (float(mid[0] - half[0]), float(mid[0] + half[0]),
            float(mid[1] - half[1]), float(mid[1] + half[1]))


def r95_radius_m(r95_h_m: float | None, sigma_h_m: float | None) -> float | None:
    """The radius of an estimate's 95 % horizontal circle: the estimator's ``r95_h_m``,
    else 2.45 sigma_H, an upper bound whatever the covariance's shape (its larger
    per-axis sigma is at most sigma_H = sqrt(P_xx + P_yy), eq. 19), else None."""
    if r95_h_m is not None and math.isfinite(r95_h_m):
        return float(r95_h_m)
    if sigma_h_m is not None and math.isfinite(sigma_h_m):
        return 2.45 * float(sigma_h_m)
    return None


def set_extent(ax, extent: Sequence[float]) -> None:
    """Fixed limits, equal scales (the axes box takes the data's shape)."""
    ax.set_xlim(extent[0], extent[1])
    ax.set_ylim(extent[2], extent[3])
    ax.set_aspect("equal", adjustable="box")
    ax.set_autoscale_on(False)


def zoom_extent(centre: Sequence[float], circles: Sequence[tuple[float, float, float]],
                least_half_m: float = 6.0) -> tuple[float, float, float, float]:
    """A square window on ``centre`` holding every (x, y, radius) circle."""
    half = least_half_m
    for x, y, r in circles:
        d = math.hypot(x - centre[0], y - centre[1]) + (r if math.isfinite(r) else 0.0)
        half = max(half, 1.2 * d)
    return (centre[0] - half, centre[0] + half, centre[1] - half, centre[1] + half)


# ----------------------------------------------------------------------- trajectory
MAX_ZOOMS = 6  # zoom panels of the trajectory figure (responders with estimates)


def trajectory_figure(report: ReplayReport, log_paths: Sequence[str | Path], title: str = "",
                      *, terrain: TerrainModel | None = None,
                      terrain_frame: EnuFrame | None = None):
    """The paper's trajectory figure: a map of the flight (GNSS track), every surveyed
    responder and the estimates over the ground, and one zoom panel per responder with
    estimates (every mode's estimate and its sigma_H circle around the truth).

    ``terrain`` (the planner's protocol) in ``terrain_frame`` (the world's ENU frame;
    the replay's frame differs) draws the ground under the map; flat ground is not drawn.
    """
    from matplotlib.lines import Line2D

    report = with_plot_frame(report, log_paths)
    plt = pyplot()
    resp = responders(report)
    estimated = unsurveyed_estimates(report)  # a real flight's: no truth to place them
    candidates = [r for r in resp if r.has_estimate] + estimated
    zoomed = candidates[:MAX_ZOOMS]
    n_rows = min(3, max(1, len(zoomed)))
    n_cols = max(1, math.ceil(len(zoomed) / 3))
    fig = plt.figure(figsize=(7.8 + 3.1 * n_cols, 7.2), layout="constrained")
    gs = fig.add_gridspec(1, 2, width_ratios=[2.3, 1.0 * n_cols])
    ax = fig.add_subplot(gs[0, 0])
    tracks = gnss_track_enu(report, log_paths)
    handles: list = []
    for k, trk in enumerate(tracks):
        ax.plot(trk[:, 0], trk[:, 1], lw=0.7, color="0.3", zorder=2)
        if k == 0:
            handles.append(Line2D([], [], lw=0.8, color="0.3", label="drone (GNSS)"))
    # the view: the flight and every responder, and the estimates near them (one far
    # off would shrink the map to nothing: its zoom panel shows it)
    core = [trk[:, :2] for trk in tracks] + [np.array([r.enu_m[:2] for r in resp])]
    core_pts = np.vstack([c.reshape(-1, 2) for c in core]) if resp or tracks else np.zeros((0, 2))
    ext0 = framed_extent(core_pts, margin=0.0)
    reach = max(100.0, 0.5 * max(ext0[1] - ext0[0], ext0[3] - ext0[2]))
    near = [t.estimate.enu_m[:2] for t in report.tracks if t.estimate is not None
            and ext0[0] - reach <= t.estimate.enu_m[0] <= ext0[1] + reach
            and ext0[2] - reach <= t.estimate.enu_m[1] <= ext0[3] + reach]
    extent = framed_extent(np.vstack([core_pts, np.array(near).reshape(-1, 2)]), margin=0.07)
    set_extent(ax, extent)
    placed = terrain_frame is None or report.frame is not None  # else: nowhere to put it
    grid = ground_grid(terrain if placed else None, extent, terrain_frame=terrain_frame,
                       plot_frame=report.frame)
    if grid is not None:
        ground_colorbar(fig, draw_ground(ax, grid), ax)
    modes = _draw_estimates(ax, report, circles=False)
    for r in resp:
        _responder_marker(ax, r)
    if any(r.has_estimate for r in resp):
        handles.append(_responder_handle(True))
    if any(not r.has_estimate for r in resp):
        handles.append(_responder_handle(False))
    for m in modes:
        st = mode_style(m)
        handles.append(Line2D([], [], ls="--", lw=0.8, marker="o", ms=5, color=st["color"],
                              label=f"{m}: estimate, sigma_H circle"))
    if resp:
        handles.append(Line2D([], [], ls="none", marker="*", ms=11, mfc="none", mec="k",
                              label="truth (zoom panels)"))
    ax.set_xlabel("East [m]")
    ax.set_ylabel("North [m]")
    ax.grid(alpha=0.3)
    ax.set_title(title or "Trajectory, surveyed and estimated responders")
    fig.canvas.draw()
    place_labels(ax, [(r.enu_m[0], r.enu_m[1],
                       f"{short_id(r.bssid)} ({r.concealment}): {r.status}")
                      for r in resp + estimated])
    right = gs[0, 1].subgridspec(n_rows, n_cols)
    if not zoomed:
        ins = fig.add_subplot(right[0, 0])
        ins.set_axis_off()
        lines = [f"{r.bssid} ({r.concealment}): {r.status}" for r in resp]
        ins.text(0.5, 0.5, "no estimates to zoom on\n\n" + "\n".join(lines[:12]),
                 ha="center", va="center", fontsize=9, transform=ins.transAxes)
    for k, r in enumerate(zoomed):
        ins = fig.add_subplot(right[k % 3, k // 3])
        _zoom_panel(ins, report, r)
        if k % 3 == n_rows - 1 or k == len(zoomed) - 1:
            ins.set_xlabel("East [m]", fontsize=8)
        if k < 3:
            ins.set_ylabel("North [m]", fontsize=8)
    more = len(candidates) - len(zoomed)
    if more > 0:
        fig.text(0.99, 0.01, f"{more} more responders with estimates: not zoomed",
                 ha="right", fontsize=7)
    fig.legend(handles=handles, loc="outside lower center", ncol=min(4, len(handles)),
               fontsize=8, frameon=False)
    return fig


def _zoom_panel(ax, report: ReplayReport, r: PlacedResponder) -> None:
    """Every mode's estimate of ``r`` and its sigma_H circle, the truth on top (when
    surveyed)."""
    rows = [t for t in report.tracks if t.bssid == r.bssid and t.estimate is not None]
    _draw_estimates(ax, report, only=r.bssid)
    t = r.enu_m
    if r.surveyed:
        ax.plot(t[0], t[1], marker="*", ms=14, mfc="none", mec="k", mew=1.2, ls="none",
                zorder=8, gid=f"{RESPONDER_GID}:{r.bssid}")
    set_extent(ax, zoom_extent(t[:2], [(x.estimate.enu_m[0], x.estimate.enu_m[1],
                                        x.estimate.sigma_h_m) for x in rows]))
    ax.grid(alpha=0.3)
    ax.tick_params(labelsize=7)
    errs = [x.err_h_m for x in rows if x.err_h_m is not None]
    span = (f", 2-D error {min(errs):.1f}-{max(errs):.1f} m" if len(errs) > 1 and
            f"{min(errs):.1f}" != f"{max(errs):.1f}" else
            f", 2-D error {errs[0]:.1f} m" if errs else "")
    ax.set_title(f"{short_id(r.bssid)} ({r.concealment}){span}", fontsize=8)


def plot_trajectory(
    report: ReplayReport, log_paths: Sequence[str | Path], path: str | Path, title: str = "",
    *, terrain: TerrainModel | None = None, terrain_frame: EnuFrame | None = None,
) -> Path:
    """Write :func:`trajectory_figure` as PNG."""
    fig = trajectory_figure(report, log_paths, title, terrain=terrain,
                            terrain_frame=terrain_frame)
    return save_figure(fig, path)


def save_figure(fig, path: str | Path) -> Path:
    """Write ``fig`` as PNG (130 dpi) and close it."""
    from envs.commands._outputs import written_whole

    out = Path(path)
    try:  # a temporary name, then renamed: an interrupted drawing keeps the previous file
        with written_whole(out) as tmp:
            fig.savefig(tmp, dpi=130)  # the format from the ending, kept by tmp
    finally:
        pyplot().close(fig)
    return out


def _responder_marker(ax, r: PlacedResponder, *, ms: float = 15, zorder: float = 5) -> None:
    x, y = r.enu_m[0], r.enu_m[1]
    face = "gold" if r.has_estimate else "white"
    ax.plot(x, y, marker="*", ms=ms, mfc=face, mec="k", mew=1.0, ls="none", zorder=zorder,
            gid=f"{RESPONDER_GID}:{r.bssid}")


def _responder_handle(has_estimate: bool):
    from matplotlib.lines import Line2D

    return Line2D([], [], ls="none", marker="*", ms=12, mec="k",
                  mfc="gold" if has_estimate else "white",
                  label="surveyed responder" if has_estimate
                  else "surveyed responder, no estimate")


def _draw_estimates(ax, report: ReplayReport, only: str | None = None,
                    circles: bool = True) -> list[str]:
    """Estimates (dot, and a dashed sigma_H circle) per mode; returns the modes drawn."""
    from matplotlib.patches import Circle

    modes: list[str] = []
    for t in report.tracks:
        if (only is not None and t.bssid != only) or t.estimate is None:
            continue
        e = t.estimate
        c = MODE_COLOURS.get(t.mode, "gray")
        ax.plot(e.enu_m[0], e.enu_m[1], "o", ms=4 if circles else 3, color=c, zorder=6,
                mec="white" if circles else c, mew=0.4)
        if circles:
            ax.add_patch(Circle((e.enu_m[0], e.enu_m[1]), e.sigma_h_m, fill=False, lw=0.9,
                                ls="--", color=c, zorder=5))
        if t.mode not in modes:
            modes.append(t.mode)
    return modes


# ---------------------------------------------------------------------- convergence
def spread_positions(y: Sequence[float], gap: float, lo: float = 0.0,
                     hi: float = 1.0) -> list[float]:
    """Positions as close to ``y`` as possible, at least ``gap`` apart, in [lo, hi]
    (order kept): the label positions of the convergence figure's end labels."""
    order = sorted(range(len(y)), key=lambda i: y[i])
    pos = [min(max(y[i], lo), hi) for i in order]
    for k in range(1, len(pos)):
        pos[k] = max(pos[k], pos[k - 1] + gap)
    if pos and pos[-1] > hi:
        pos[-1] = hi
        for k in range(len(pos) - 2, -1, -1):
            pos[k] = min(pos[k], pos[k + 1] - gap)
    out = [0.0] * len(y)
    for k, i in enumerate(order):
        out[i] = pos[k]
    return out


def convergence_figure(report: ReplayReport, bssid: str | None = None):
    """The paper's convergence figure for every responder (or only ``bssid``): one
    column each, (a) sigma_H and (b) the 2-D error against the truth, against time
    since bootstrap, one line per mode, the reported errors labelled at the right.
    A responder without estimates keeps a narrow column saying so."""
    plt = pyplot()
    by: dict[str, list[TrackResult]] = {}
    for t in report.tracks:
        if bssid is None or t.bssid == bssid:
            by.setdefault(t.bssid, []).append(t)
    with_data = [b for b, rows in by.items() if any(t.history for t in rows)]
    if not with_data:
        fig, (a1, a2) = plt.subplots(2, 1, figsize=(9, 7.5), layout="constrained")
        statuses = sorted({f"{t.bssid}: {t.status}" for t in report.tracks})
        for a, what in ((a1, "sigma_H"), (a2, "2-D error")):
            a.set_xticks([])
            a.set_yticks([])
            a.text(0.5, 0.5, f"no estimates: no {what} to show\n" + "\n".join(statuses[:8]),
                   ha="center", va="center", fontsize=9, transform=a.transAxes)
        a1.set_title("(a) horizontal uncertainty: no estimates")
        a2.set_title("(b) ground-truth 2-D error: no estimates")
        return fig
    widths = [1.0 if b in with_data else 0.32 for b in by]
    fig = plt.figure(figsize=(max(9.0, 1.2 + sum(4.9 * w for w in widths)), 7.6),
                     layout="constrained")
    fig.get_layout_engine().set(w_pad=0.12)  # the end labels' text keeps off the edge
    gs = fig.add_gridspec(2, len(by), width_ratios=widths)
    handles: dict[str, Any] = {}
    ends_by_axis: list[tuple[Any, list]] = []
    for col, (b, rows) in enumerate(by.items()):
        conc = rows[0].concealment or (report.truth[b].concealment if b in report.truth
                                       else "")
        name = f"{short_id(b)}" + (f" ({conc})" if conc else "")
        if b not in with_data:
            ax = fig.add_subplot(gs[:, col])
            ax.set_axis_off()
            status = ", ".join(sorted({t.status for t in rows}))
            ax.text(0.5, 0.5, f"{name}\n\nno estimates\n({status})", ha="center", va="center",
                    fontsize=9, transform=ax.transAxes, wrap=True)
            continue
        a1 = fig.add_subplot(gs[0, col])
        a2 = fig.add_subplot(gs[1, col], sharex=a1)
        ends = _convergence_column(a1, a2, rows, handles)
        a1.set_title(f"(a) sigma_H, {name}", fontsize=9)
        a2.set_title(f"(b) 2-D error, {name}" if ends else
                     f"(b) 2-D error, {name}: no truth in the log", fontsize=9)
        if col == 0:
            a1.set_ylabel("sigma_H [m] (internal)")
            a2.set_ylabel("2-D error [m] (vs truth)")
        a2.set_xlabel("time since bootstrap [s]")
        if ends:
            ends_by_axis.append((a2, ends))
    order = [m for m in MODE_STYLES if m in handles] + [m for m in handles
                                                         if m not in MODE_STYLES]
    hl = [handles[m] for m in order]
    fig.legend(hl, [h.get_label() for h in hl], loc="outside lower center",
               ncol=min(8, len(hl)), fontsize=8, frameon=False)
    _end_labels(fig, ends_by_axis)
    return fig


def _convergence_column(a1, a2, rows: list[TrackResult], handles: dict) -> list:
    """One responder's curves; returns its end labels (t, err, text, colour) at the
    reported estimate of each mode."""
    from matplotlib.lines import Line2D

    ends: list[tuple[float, float, str, str]] = []
    t_end = 0.0
    for t in rows:
        if not t.history:
            continue
        t0 = t.bootstrap_t_s if t.bootstrap_t_s is not None else t.history[0].t_s
        ts = np.array([p.t_s - t0 for p in t.history])
        t_end = max(t_end, float(ts[-1]))
        st = mode_style(t.mode)
        step = max(1, len(ts) // 8)
        k = list(MODE_STYLES).index(t.mode) if t.mode in MODE_STYLES else 0
        kw = {**st, "ms": 5, "mfc": "none", "markevery": (k * step // 7 % step, step),
              "label": t.mode}
        line = a1.plot(ts, [p.sigma_h_m for p in t.history], **kw)[0]
        handles.setdefault(t.mode, line)
        if t.truth_enu_m is not None:
            tr = t.truth_enu_m
            err = [math.hypot(p.enu_m[0] - tr[0], p.enu_m[1] - tr[1]) for p in t.history]
            a2.plot(ts, err, **kw)
            if t.err_h_m is not None and t.estimate is not None:
                # the reported estimate is the last stable one, not always the last
                ends.append((float(t.estimate.t_s - t0), float(t.err_h_m),
                             f"{t.mode} {t.err_h_m:.1f} m", st["color"]))
    a1.axhline(2.5, ls="--", color="k", lw=0.8)
    handles.setdefault("_threshold", Line2D([], [], ls="--", color="k", lw=0.8,
                                            label="sigma_H = 2.5 m"))
    for a in (a1, a2):
        a.grid(alpha=0.3)
        a.set_ylim(bottom=0)
        a.tick_params(labelsize=8)
    a1.set_xlim(right=t_end * 1.02 + 1e-9)
    return ends


def _end_labels(fig, ends_by_axis: list[tuple[Any, list]], fontsize: float = 7.5) -> None:
    """Final errors at the right of each error axis, spread so that none overlaps
    another, each joined to its curve's end by a thin line from the label's left edge.

    The layout is made with the labels in it, then frozen, and the labels are spread
    again on the final axes heights: a later draw (saving) moves nothing."""
    placed = []
    for ax, ends in ends_by_axis:
        texts = [ax.annotate(text, (x, y), xycoords="data", xytext=(1.03, 0.5),
                             textcoords="axes fraction", va="center", ha="left",
                             fontsize=fontsize, color=colour, gid=LABEL_GID,
                             annotation_clip=False,
                             arrowprops={"arrowstyle": "-", "lw": 0.6, "color": colour,
                                         "shrinkA": 1, "shrinkB": 2, "relpos": (0.0, 0.5)})
                 for x, y, text, colour in ends]
        placed.append((ax, ends, texts))
    fig.canvas.draw()  # the layout, with room for the labels
    fig.set_layout_engine("none")
    renderer = fig.canvas.get_renderer()
    for ax, ends, texts in placed:
        height_px = ax.get_window_extent(renderer).height
        gap = 1.45 * fontsize * fig.dpi / 72.0 / height_px
        to_axes = ax.transData + ax.transAxes.inverted()
        ys = [float(to_axes.transform((x, y))[1]) for x, y, _, _ in ends]
        for t, yp in zip(texts, spread_positions(ys, gap), strict=True):
            t.set_position((1.03, yp))


def plot_convergence(report: ReplayReport, path: str | Path, bssid: str | None = None) -> Path:
    """Write :func:`convergence_figure` as PNG."""
    return save_figure(convergence_figure(report, bssid), path)
