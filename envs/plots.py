"""Figures of a replay: the paper's trajectory figure and its convergence figure.

* :func:`plot_trajectory`: drone GNSS track in the replay's ENU frame, surveyed and
  estimated responders, sigma_H circles, and an inset around the best-observed one.
* :func:`plot_convergence`: (a) sigma_H against time since bootstrap for every mode with
  the 2.5 m threshold, (b) 2-D error against the truth over the same time.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from pathlib import Path

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


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def with_plot_frame(report: ReplayReport, log_paths: Sequence[str | Path]) -> ReplayReport:
    """The report, with an ENU frame even when no range was associated (then the frame
    is eq. (1) at the first GNSS fix, and surveyed responders are placed in it), so a
    flight without a single usable range still shows its path and its responders."""
    if report.frame is not None:
        return report
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


def plot_trajectory(
    report: ReplayReport, log_paths: Sequence[str | Path], path: str | Path, title: str = ""
) -> Path:
    """The paper's trajectory figure (Fig. "trajectory") as PNG: map and zoom panel."""
    report = with_plot_frame(report, log_paths)
    plt = _plt()
    fig, (ax, ins) = plt.subplots(
        1, 2, figsize=(12, 6), gridspec_kw={"width_ratios": [1.6, 1.0]}
    )
    for k, trk in enumerate(gnss_track_enu(report, log_paths)):
        lab = "drone (GNSS)" if k == 0 else None
        ax.plot(trk[:, 0], trk[:, 1], lw=0.6, color="0.55", label=lab)
    _draw_aps(ax, report, legend=True)
    ax.set_xlabel("East [m]")
    ax.set_ylabel("North [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(alpha=0.3)
    ax.set_title(title or "Trajectory, surveyed and estimated responders")
    best = _best_observed(report)
    if best is None or best.truth_enu_m is None:
        ins.set_axis_off()
        lines = sorted({f"{t.bssid}: {t.status}" for t in report.tracks})
        ins.text(0.5, 0.5, "no estimate to zoom on\n\n" + "\n".join(lines[:12]),
                 ha="center", va="center", fontsize=9, transform=ins.transAxes)
    else:
        _draw_aps(ins, report, legend=False, only=best.bssid)
        t = best.truth_enu_m
        half = 12.0
        ests = [x for x in report.tracks if x.bssid == best.bssid and x.estimate is not None]
        if ests:
            half = max(half, *(1.3 * math.hypot(x.estimate.enu_m[0] - t[0],
                                                x.estimate.enu_m[1] - t[1]) for x in ests))
        ins.set_xlim(t[0] - half, t[0] + half)
        ins.set_ylim(t[1] - half, t[1] + half)
        ins.set_aspect("equal")
        ins.grid(alpha=0.3)
        ins.set_xlabel("East [m]")
        ins.set_title(f"zoom on {best.bssid}: estimates with sigma_H circles", fontsize=9)
    ax.legend(loc="upper left", fontsize=7)
    fig.tight_layout()
    out = Path(path)
    fig.savefig(out, dpi=130)
    plt.close(fig)
    return out


def _best_observed(report: ReplayReport) -> TrackResult | None:
    cands = [t for t in report.tracks if t.estimate is not None and t.truth_enu_m is not None]
    return max(cands, key=lambda t: t.counts["n_acc"], default=None)


def _draw_aps(ax, report: ReplayReport, *, legend: bool, only: str | None = None) -> None:
    seen_truth: set[str] = set()
    labelled: set[str] = set()
    for t in report.tracks:
        if only is not None and t.bssid != only:
            continue
        if t.truth_enu_m is not None and t.bssid not in seen_truth:
            seen_truth.add(t.bssid)
            x, y = t.truth_enu_m[0], t.truth_enu_m[1]
            ax.plot(x, y, marker="*", ms=14, color="gold", mec="k",
                    label="surveyed AP" if legend and not seen_truth - {t.bssid} else None)
            if only is None:
                ax.annotate(f"{t.bssid[-5:]} ({t.concealment or '?'})", (x, y), fontsize=7,
                            xytext=(5, 5), textcoords="offset points")
        e = t.estimate
        if e is None:
            continue
        c = MODE_COLOURS.get(t.mode, "gray")
        lab = t.mode if legend and t.mode not in labelled else None
        labelled.add(t.mode)
        ax.plot(e.enu_m[0], e.enu_m[1], "o", ms=4, color=c, label=lab)
        ax.add_patch(
            _circle((e.enu_m[0], e.enu_m[1]), e.sigma_h_m, c)
        )


def _circle(xy: tuple[float, float], r: float, colour: str):
    from matplotlib.patches import Circle

    return Circle(xy, r, fill=False, lw=0.8, ls="--", color=colour)


def plot_convergence(report: ReplayReport, path: str | Path, bssid: str | None = None) -> Path:
    """The paper's convergence figure: sigma_H and 2-D error against time since bootstrap."""
    plt = _plt()
    best = _best_observed(report) if bssid is None else None
    target = bssid or (best.bssid if best else None)
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(8, 7), sharex=True)
    for t in report.tracks:
        if t.bssid != target or not t.history:
            continue
        t0 = t.bootstrap_t_s if t.bootstrap_t_s is not None else t.history[0].t_s
        ts = np.array([p.t_s - t0 for p in t.history])
        c = MODE_COLOURS.get(t.mode, "gray")
        a1.plot(ts, [p.sigma_h_m for p in t.history], color=c, lw=1.0, label=t.mode)
        if t.truth_enu_m is not None:
            tr = t.truth_enu_m
            err = [math.hypot(p.enu_m[0] - tr[0], p.enu_m[1] - tr[1]) for p in t.history]
            a2.plot(ts, err, color=c, lw=1.0, label=t.mode)
            if t.err_h_m is not None:
                a2.annotate(f"{t.err_h_m:.1f} m", (ts[-1], err[-1]), fontsize=7, color=c,
                            xytext=(3, 0), textcoords="offset points")
    if not any(t.bssid == target and t.history for t in report.tracks):
        for a in (a1, a2):
            a.text(0.5, 0.5, "no published estimate", ha="center", va="center",
                   transform=a.transAxes)
    a1.axhline(2.5, ls="--", color="k", lw=0.8, label="sigma_H = 2.5 m")
    a1.set_ylabel("sigma_H [m] (internal)")
    a1.set_title(f"(a) horizontal uncertainty, {target}")
    a1.legend(fontsize=7, ncol=2)
    a1.grid(alpha=0.3)
    a1.set_ylim(bottom=0)
    a2.set_ylabel("2-D error [m] (vs truth)")
    a2.set_xlabel("time since bootstrap [s]")
    a2.set_title("(b) ground-truth 2-D error")
    a2.grid(alpha=0.3)
    a2.set_ylim(bottom=0)
    fig.tight_layout()
    out = Path(path)
    fig.savefig(out, dpi=130)
    plt.close(fig)
    return out
