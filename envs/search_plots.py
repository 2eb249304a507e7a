"""Figures of a closed-loop search (``osa search``): where it flew, and how the error and
the uncertainty evolved.

* :func:`search_trajectory_figure`: the area, the path flown, every responder (truth,
  by concealment class), the final estimates with their 95 % circles.
* :func:`search_error_figure`: per responder, (a) the horizontal error against the
  truth and (b) the estimator's sigma_H and 95 % radius, against flight time, with
  the times it was first heard and judged localised.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from envs.loop import SearchResult
from envs.plots import LABEL_GID, RESPONDER_GID, _place_labels, _plt, _save

CONCEALMENT_STYLE = {
    "open": dict(marker="*", color="tab:green"),
    "vegetation": dict(marker="*", color="tab:olive"),
    "vegetation_debris": dict(marker="*", color="tab:brown"),
}
RESPONDER_COLOURS = ("tab:blue", "tab:orange", "tab:purple", "tab:red", "tab:cyan",
                     "tab:pink", "tab:gray")


def _colour(k: int) -> str:
    return RESPONDER_COLOURS[k % len(RESPONDER_COLOURS)]


def search_trajectory_figure(result: SearchResult, title: str = ""):
    plt = _plt()
    fig, ax = plt.subplots(figsize=(8.6, 6.4))
    area = np.asarray((*result.area_enu_m, result.area_enu_m[0]), dtype=float)
    ax.plot(area[:, 0], area[:, 1], color="black", lw=1.2, label="search area")
    for k, trk in enumerate(result.nav_track):
        if trk:
            p = np.asarray(trk)
            ax.plot(p[:, 1], p[:, 2], color="0.35", lw=0.9,
                    label="flight path" if k == 0 else None)
            ax.plot(p[0, 1], p[0, 2], marker="^", color="black", ms=8, ls="none",
                    label="take-off" if k == 0 else None)
    labels = []
    seen_classes = set()
    for k, r in enumerate(result.responders):
        b = r["bssid"]
        tr = result.truth_enu_m.get(b)
        conc = r.get("concealment", "open")
        style = CONCEALMENT_STYLE.get(conc, CONCEALMENT_STYLE["open"])
        if tr is not None:
            first = conc not in seen_classes
            ax.plot(tr[0], tr[1], ls="none", ms=15, mec="black", mew=0.8, zorder=5,
                    gid=f"{RESPONDER_GID}:{b}", label=f"responder ({conc})" if first else None,
                    **style)
            seen_classes.add(conc)
        est = result.estimates_enu_m.get(b)
        if est is not None:
            c = _colour(k)
            ax.plot(est[0], est[1], marker="+", ms=12, mew=2, color=c, ls="none", zorder=6,
                    label=f"estimate {b[-5:]}")
            r95 = r.get("r95_h_m") or (2.45 * r["sigma_h_m"] / math.sqrt(2.0))
            ax.add_patch(plt.Circle(est[:2], r95, fill=False, color=c, lw=1.0, ls="--"))
        if tr is not None:
            err = r.get("err_h_m")
            txt = f"{b[-5:]}: " + (f"{err:.1f} m off" if err is not None else r["status"])
            labels.append((tr[0], tr[1], txt))
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("east (m)")
    ax.set_ylabel("north (m)")
    ax.set_title(title or f"{result.scenario}: {result.policy}, seed {result.seed}, "
                 f"ended {result.ended} at {result.flight_time_s / 60:.1f} min")
    ax.grid(alpha=0.3)
    fig.tight_layout(rect=(0.0, 0.0, 0.74, 1.0))
    ax.legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=8, frameon=False)
    _place_labels(ax, labels)
    return fig


def search_error_figure(result: SearchResult, title: str = ""):
    plt = _plt()
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(8.6, 6.4), sharex=True)
    any_est = False
    for k, r in enumerate(result.responders):
        b = r["bssid"]
        pts = result.series.get(b, [])
        c = _colour(k)
        t = np.array([p.t_s for p in pts]) / 60.0
        err = np.array([np.nan if p.err_h_m is None else p.err_h_m for p in pts])
        sig = np.array([np.nan if p.sigma_h_m is None else p.sigma_h_m for p in pts])
        r95 = np.array([np.nan if p.r95_h_m is None else p.r95_h_m for p in pts])
        if np.isfinite(err).any():
            any_est = True
            ax1.plot(t, err, color=c, lw=1.4, label=f"{b[-5:]} ({r.get('concealment', '?')})")
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
    fig.tight_layout(rect=(0.0, 0.0, 0.76, 1.0))
    return fig


def plot_search(result: SearchResult, out_dir: str | Path) -> tuple[Path, Path]:
    """Write ``trajectory.png`` and ``errors.png`` into ``out_dir``."""
    out = Path(out_dir)
    p1 = _save(search_trajectory_figure(result), out / "trajectory.png")
    p2 = _save(search_error_figure(result), out / "errors.png")
    return p1, p2
