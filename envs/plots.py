"""Figures of a replay: the paper's trajectory figure and its convergence figure.

* :func:`trajectory_figure` / :func:`plot_trajectory`: drone GNSS track in the
  replay's ENU frame, every surveyed responder (also those that never answered),
  the estimates with their sigma_H circles, and a zoom on the best-observed responder.
* :func:`convergence_figure` / :func:`plot_convergence`: (a) sigma_H against time
  since bootstrap for every mode with the 2.5 m threshold, (b) 2-D error against the
  truth over the same time, with the final errors labelled at the right.

Readability rules, checked by tests/envs/test_figures.py: legends sit outside the
data axes, labels never overlap one another, every mode has its own colour, line
style and marker (EMA smooths Baseline's filter, so their curves nearly coincide),
and a figure without estimates says so instead of drawing an empty 0-1 axis.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from estimator.replay import ReplayReport, TrackResult

MODE_COLOURS = {
    "baseline": "tab:blue",
    "nlos": "tab:orange",
    "empirical-r": "tab:green",
    "ukf": "tab:red",
    "ema": "tab:purple",
    "adaptive-r": "tab:brown",
    "robust": "black",
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
}
RESPONDER_GID = "responder"  # gid of each surveyed responder's marker (tests count them)
LABEL_GID = "label"  # gid of the texts that must not overlap


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


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
class _Responder:
    bssid: str
    enu_m: tuple[float, float, float]
    concealment: str
    status: str  # the best status over the modes
    has_estimate: bool


_STATUS_RANK = ("converged", "tracking", "weak_geometry", "bootstrapping", "diverged", "no_data")


def responders(report: ReplayReport) -> list[_Responder]:
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
        out.append(_Responder(bssid, placed[0].truth_enu_m, conc, best,
                              any(r.estimate is not None for r in rows)))
    if report.frame is not None:
        for bssid, tru in report.truth.items():
            if bssid not in by:  # surveyed, never ranged
                enu = tuple(report.frame.to_enu(tru.lat_deg, tru.lon_deg, tru.alt_m))
                out.append(_Responder(bssid, enu, tru.concealment, "not ranged", False))
    return out


def _overlaps(a, b) -> bool:
    return not (a.x1 <= b.x0 or b.x1 <= a.x0 or a.y1 <= b.y0 or b.y1 <= a.y0)


def _place_labels(ax, points: list[tuple[float, float, str]], fontsize: float = 7.5) -> list:
    """Annotate each (x, y, text) at the first of a few offsets where the label overlaps
    no label placed before and stays inside the axes (the last offset tried otherwise)."""
    fig = ax.figure
    renderer = fig.canvas.get_renderer()
    offsets = [(7, 7, "left", "bottom"), (7, -7, "left", "top"), (-7, 7, "right", "bottom"),
               (-7, -7, "right", "top"), (0, 14, "center", "bottom"),
               (0, -14, "center", "top"), (7, 24, "left", "bottom"), (-7, -24, "right", "top")]
    placed: list = []
    texts = []
    ax_box = ax.get_window_extent(renderer)
    for x, y, text in points:
        chosen = None
        for dx, dy, ha, va in offsets:
            t = ax.annotate(text, (x, y), xytext=(dx, dy), textcoords="offset points",
                            ha=ha, va=va, fontsize=fontsize, gid=LABEL_GID,
                            bbox={"boxstyle": "round,pad=0.15", "fc": "white", "ec": "none",
                                  "alpha": 0.8})
            box = t.get_window_extent(renderer)
            inside = (box.x0 >= ax_box.x0 and box.x1 <= ax_box.x1 and box.y0 >= ax_box.y0
                      and box.y1 <= ax_box.y1)
            if inside and not any(_overlaps(box, b) for b in placed):
                chosen = (t, box)
                break
            t.remove()
        if chosen is None:  # crowded: the first offset, nudged up past the others
            dy = 7 + 12 * len(placed)
            t = ax.annotate(text, (x, y), xytext=(7, dy), textcoords="offset points",
                            ha="left", va="bottom", fontsize=fontsize, gid=LABEL_GID,
                            arrowprops={"arrowstyle": "-", "lw": 0.5, "color": "0.4"})
            chosen = (t, t.get_window_extent(renderer))
        placed.append(chosen[1])
        texts.append(chosen[0])
    return texts


def trajectory_figure(report: ReplayReport, log_paths: Sequence[str | Path], title: str = ""):
    """The paper's trajectory figure (Fig. "trajectory"): map and zoom panel."""
    from matplotlib.lines import Line2D

    report = with_plot_frame(report, log_paths)
    plt = _plt()
    fig, (ax, ins) = plt.subplots(
        1, 2, figsize=(12, 6.6), gridspec_kw={"width_ratios": [1.6, 1.0]}, layout="constrained"
    )
    handles: list = []
    for k, trk in enumerate(gnss_track_enu(report, log_paths)):
        ax.plot(trk[:, 0], trk[:, 1], lw=0.6, color="0.6")
        if k == 0:
            handles.append(Line2D([], [], lw=0.8, color="0.6", label="drone (GNSS)"))
    resp = responders(report)
    modes = _draw_estimates(ax, report)
    for r in resp:
        _responder_marker(ax, r)
    if any(r.has_estimate for r in resp):
        handles.append(_responder_handle(True))
    if any(not r.has_estimate for r in resp):
        handles.append(_responder_handle(False))
    for m in modes:
        st = mode_style(m)
        handles.append(Line2D([], [], ls="none", marker="o", ms=5, color=st["color"],
                              label=f"{m} estimate, sigma_H circle"))
    ax.set_xlabel("East [m]")
    ax.set_ylabel("North [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(alpha=0.3)
    ax.set_title(title or "Trajectory, surveyed and estimated responders")
    # the responders and their sigma circles inside the view, with room for labels
    pts = [r.enu_m[:2] for r in resp]
    if pts:
        ax.update_datalim(np.array(pts))
        ax.autoscale_view()
        ax.margins(0.08)
    fig.canvas.draw()
    _place_labels(ax, [(r.enu_m[0], r.enu_m[1],
                        f"{r.bssid[-5:]} ({r.concealment}): {r.status}") for r in resp])
    best = _best_observed(report)
    if best is None:
        ins.set_axis_off()
        lines = [f"{r.bssid} ({r.concealment}): {r.status}" for r in resp]
        ins.text(0.5, 0.5, "no estimates to zoom on\n\n" + "\n".join(lines[:12]),
                 ha="center", va="center", fontsize=9, transform=ins.transAxes)
    else:
        _draw_estimates(ins, report, only=best.bssid)
        for r in resp:
            if r.bssid == best.bssid:  # under the estimates: they stay visible
                _responder_marker(ins, r, ms=13, zorder=3)
        # centred on the surveyed position, else (a real flight) on the best estimate
        t = best.truth_enu_m if best.truth_enu_m is not None else best.estimate.enu_m
        half = 12.0
        ests = [x for x in report.tracks if x.bssid == best.bssid and x.estimate is not None]
        if ests:
            half = max(half, *(1.3 * (math.hypot(x.estimate.enu_m[0] - t[0],
                                                 x.estimate.enu_m[1] - t[1])
                                      + x.estimate.sigma_h_m) for x in ests))
        ins.set_xlim(t[0] - half, t[0] + half)
        ins.set_ylim(t[1] - half, t[1] + half)
        ins.set_aspect("equal")
        ins.grid(alpha=0.3)
        ins.set_xlabel("East [m]")
        ins.set_title(f"zoom on {best.bssid}: estimates with sigma_H circles"
                      + ("" if best.truth_enu_m is not None else " (no survey)"), fontsize=9)
    fig.legend(handles=handles, loc="outside lower center", ncol=min(4, len(handles)),
               fontsize=8, frameon=False)
    return fig


def plot_trajectory(
    report: ReplayReport, log_paths: Sequence[str | Path], path: str | Path, title: str = ""
) -> Path:
    """Write :func:`trajectory_figure` as PNG."""
    fig = trajectory_figure(report, log_paths, title)
    return _save(fig, path)


def _save(fig, path: str | Path) -> Path:
    out = Path(path)
    fig.savefig(out, dpi=130)
    _plt().close(fig)
    return out


def _responder_marker(ax, r: _Responder, *, ms: float = 15, zorder: float = 5) -> None:
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


def _best_observed(report: ReplayReport) -> TrackResult | None:
    """The track with the most accepted ranges, among those with a surveyed truth if
    any has one (a real flight without ``truth`` records: among all estimates)."""
    cands = [t for t in report.tracks if t.estimate is not None]
    surveyed = [t for t in cands if t.truth_enu_m is not None]
    return max(surveyed or cands, key=lambda t: t.counts["n_acc"], default=None)


def _draw_estimates(ax, report: ReplayReport, only: str | None = None) -> list[str]:
    """Estimates (dot + dashed sigma_H circle) per mode; returns the modes drawn."""
    from matplotlib.patches import Circle

    modes: list[str] = []
    for t in report.tracks:
        if (only is not None and t.bssid != only) or t.estimate is None:
            continue
        e = t.estimate
        c = MODE_COLOURS.get(t.mode, "gray")
        ax.plot(e.enu_m[0], e.enu_m[1], "o", ms=4, color=c, zorder=4)
        ax.add_patch(Circle((e.enu_m[0], e.enu_m[1]), e.sigma_h_m, fill=False, lw=0.8,
                            ls="--", color=c))
        if t.mode not in modes:
            modes.append(t.mode)
    return modes


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
    """The paper's convergence figure: sigma_H and 2-D error against time since bootstrap."""
    plt = _plt()
    best = _best_observed(report) if bssid is None else None
    target = bssid or (best.bssid if best else None)
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(9, 7.5), sharex=True, layout="constrained")
    rows = [t for t in report.tracks if t.bssid == target and t.history]
    ends: list[tuple[float, float, str, str]] = []  # (t, err, text, colour)
    for t in rows:
        t0 = t.bootstrap_t_s if t.bootstrap_t_s is not None else t.history[0].t_s
        ts = np.array([p.t_s - t0 for p in t.history])
        st = mode_style(t.mode)
        step = max(1, len(ts) // 8)
        k = list(MODE_STYLES).index(t.mode) if t.mode in MODE_STYLES else 0
        kw = {**st, "ms": 5, "mfc": "none", "markevery": (k * step // 7 % step, step),
              "label": t.mode}
        a1.plot(ts, [p.sigma_h_m for p in t.history], **kw)
        if t.truth_enu_m is not None:
            tr = t.truth_enu_m
            err = [math.hypot(p.enu_m[0] - tr[0], p.enu_m[1] - tr[1]) for p in t.history]
            a2.plot(ts, err, **kw)
            if t.err_h_m is not None:
                ends.append((float(ts[-1]), float(err[-1]), f"{t.mode} {t.err_h_m:.1f} m",
                             st["color"]))
    if not rows:
        statuses = sorted({f"{t.bssid}: {t.status}" for t in report.tracks})
        for a, what in ((a1, "sigma_H"), (a2, "2-D error")):
            a.set_xticks([])
            a.set_yticks([])
            a.text(0.5, 0.5, f"no estimates: no {what} to show\n" + "\n".join(statuses[:8]),
                   ha="center", va="center", fontsize=9, transform=a.transAxes)
        a1.set_title("(a) horizontal uncertainty: no estimates")
        a2.set_title("(b) ground-truth 2-D error: no estimates")
        return fig
    a1.axhline(2.5, ls="--", color="k", lw=0.8, label="sigma_H = 2.5 m")
    a1.set_ylabel("sigma_H [m] (internal)")
    a1.set_title(f"(a) horizontal uncertainty, {target}")
    a1.grid(alpha=0.3)
    a1.set_ylim(bottom=0)
    a2.set_ylabel("2-D error [m] (vs truth)")
    a2.set_xlabel("time since bootstrap [s]")
    a2.set_title("(b) ground-truth 2-D error" if ends else
                 "(b) ground-truth 2-D error: no truth in the log")
    a2.grid(alpha=0.3)
    a2.set_ylim(bottom=0)
    handles, labels = a1.get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside right upper", fontsize=8, frameon=False)
    if ends:
        _end_labels(fig, a2, ends)
    return fig


def _end_labels(fig, ax, ends: list[tuple[float, float, str, str]], fontsize: float = 7.5):
    """Final errors at the right of ``ax``, spread so that none overlaps another, each
    joined to its curve's end by a thin line."""
    ax.set_xlim(right=max(e[0] for e in ends) * 1.02 + 1e-9)
    fig.canvas.draw()  # fixes the layout and the data limits
    renderer = fig.canvas.get_renderer()
    height_px = ax.get_window_extent(renderer).height
    gap = 1.7 * fontsize * fig.dpi / 72.0 / height_px
    to_axes = ax.transData + ax.transAxes.inverted()
    ys = [float(to_axes.transform((x, y))[1]) for x, y, _, _ in ends]
    pos = spread_positions(ys, gap)
    for (x, y, text, colour), yp in zip(ends, pos, strict=True):
        ax.annotate(text, (x, y), xycoords="data", xytext=(1.02, yp),
                    textcoords="axes fraction", va="center", ha="left", fontsize=fontsize,
                    color=colour, gid=LABEL_GID, annotation_clip=False,
                    arrowprops={"arrowstyle": "-", "lw": 0.6, "color": colour,
                                "shrinkA": 0, "shrinkB": 2})


def plot_convergence(report: ReplayReport, path: str | Path, bssid: str | None = None) -> Path:
    """Write :func:`convergence_figure` as PNG."""
    return _save(convergence_figure(report, bssid), path)
