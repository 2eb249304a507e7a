"""Figures of an evaluation (``osa evaluate``): how the policies compare over seeds.

* :func:`time_to_localise_figure`: per policy, the empirical CDF over (seed,
  responder) of (a) the time the policy judged a responder localised and (b) the time
  from which the error stays within 1 m (truth). Never localised by the budget is
  censored: the curve stops below 1 at the budget, and the legend gives the share.
* :func:`error_vs_time_figure`: per policy, the median over seeds of (a) the
  horizontal error and (b) the estimator's sigma_H against flight time, with the
  25-75 % band. A seed whose search ended keeps its final estimate; a seed without an
  estimate yet counts as an infinite error (a median that is infinite is not drawn).
* :func:`trajectories_figure`: a few example worlds, one panel each framed on the
  search area, over the ground (flat ground is not drawn), every policy's path on the
  same world (common random numbers) in its own colour, line style and marker, the
  responders (open stars, the truth) and each policy's final estimates (its marker)
  with their unfilled 95 % circles.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from envs.evaluate import Evaluation
from envs.plots import (
    draw_ground,
    ground_colorbar,
    ground_grid,
    ground_norm,
    plain_log_ticks,
    pyplot,
    r95_radius_m,
    save_figure,
    set_extent,
)
from envs.search_plots import search_extent
from planner.models import TerrainModel

POLICY_COLOURS = {"lawnmower": "tab:blue", "expanding-square": "tab:orange",
                  "adaptive": "tab:green"}
OTHER_COLOURS = ("tab:red", "tab:purple", "tab:brown", "tab:pink", "tab:olive", "tab:cyan")
POLICY_STYLES = ("-", "--", "-.", ":")
POLICY_MARKERS = {"lawnmower": "s", "expanding-square": "D", "adaptive": "o"}
OTHER_MARKERS = ("^", "v", "P", "X", "h", "<", ">", "p")
FIGURES = ("time_to_localise.png", "error_vs_time.png", "trajectories.png")


def policy_colour(policies: Sequence[str], policy: str) -> str:
    if policy in POLICY_COLOURS:
        return POLICY_COLOURS[policy]
    others = [p for p in policies if p not in POLICY_COLOURS]
    return OTHER_COLOURS[others.index(policy) % len(OTHER_COLOURS)]


def policy_marker(policies: Sequence[str], policy: str) -> str:
    """The policy's marker: its own for the built-in policies, else one of
    :data:`OTHER_MARKERS` in the order the others were given."""
    if policy in POLICY_MARKERS:
        return POLICY_MARKERS[policy]
    others = [p for p in policies if p not in POLICY_MARKERS]
    return OTHER_MARKERS[others.index(policy) % len(OTHER_MARKERS)]


def _style(ev: Evaluation, policy: str) -> dict:
    k = ev.policies.index(policy)
    return dict(color=policy_colour(ev.policies, policy), ls=POLICY_STYLES[k % 4])


def ecdf_censored(times: Sequence[float | None], budget_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Step ECDF points (x, y) of ``times`` with None censored at the budget: y ends
    at the share observed, drawn flat to the budget."""
    n = len(times)
    obs = np.sort(np.array([t for t in times if t is not None], dtype=float))
    x = np.concatenate([[0.0], obs, [budget_s]])
    y = np.concatenate([[0.0], np.arange(1, len(obs) + 1) / max(n, 1),
                        [len(obs) / max(n, 1)]])
    return x, y


def time_to_localise_figure(ev: Evaluation):
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(11.5, 4.8), sharey=True)
    budget_min = ev.budget_s / 60.0
    keys = (("localised_at_s", "(a) judged localised by the policy"),
            ("time_within_1m_s", "(b) error within 1 m and staying there (truth)"))
    for ax, (key, title) in zip(axes, keys, strict=True):
        for p in ev.policies:
            vals = [r[key] for r in ev.rows if r["policy"] == p]
            x, y = ecdf_censored(vals, ev.budget_s)
            n_ok = sum(v is not None for v in vals)
            ax.step(x / 60.0, y, where="post", lw=1.8,
                    label=f"{p}: {n_ok}/{len(vals)} by the budget", **_style(ev, p))
        ax.axvline(budget_min, color="black", lw=0.8, ls=":")
        ax.text(budget_min, 1.02, "budget", ha="right", va="bottom", fontsize=8,
                transform=ax.get_xaxis_transform())
        ax.set_xlim(0.0, budget_min * 1.02)
        ax.set_ylim(0.0, 1.0)
        ax.set_xlabel("flight time (min)")
        ax.set_title(title, fontsize=9, loc="left")
        ax.grid(alpha=0.3)
        ax.legend(loc="upper left", fontsize=8, frameon=True, framealpha=0.9)
    axes[0].set_ylabel("share of responders")
    n = len(ev.seeds)
    fig.suptitle(f"{ev.scenario}: time to localise over {n} seed{'s' * (n != 1)}; "
                 "a curve below 1 at the budget is the share never localised (censored)",
                 fontsize=10)
    fig.tight_layout()
    return fig


def _held(series: np.ndarray, column: int, grid: np.ndarray) -> np.ndarray:
    """Values of one series column on ``grid``: the last sample at or before each time,
    the last one after the end, inf before the first sample or where there is none."""
    out = np.full(grid.shape, np.inf)
    if series.size == 0:
        return out
    t = series[:, 0]
    idx = np.searchsorted(t, grid + 1e-9, side="right") - 1
    ok = idx >= 0
    vals = series[idx[ok], column]
    out[ok] = np.where(np.isfinite(vals), vals, np.inf)
    return out


def error_bands(ev: Evaluation, policy: str, column: int, dt_s: float | None = None,
                qs: Sequence[float] = (0.25, 0.5, 0.75)) -> tuple[np.ndarray, np.ndarray]:
    """(grid, quantiles[len(qs), len(grid)]) of a series column over (seed, responder);
    inf where the quantile is infinite (no estimate)."""
    dt_s = dt_s if dt_s is not None else ev.decision_period_s
    grid = np.arange(0.0, ev.budget_s + 0.5 * dt_s, dt_s)
    stack = [_held(s, column, grid) for e in ev.episodes if e.policy == policy
             for s in e.series.values()]
    if not stack:
        return grid, np.full((len(qs), len(grid)), np.inf)
    a = np.vstack(stack)
    return grid, np.quantile(a, qs, axis=0, method="inverted_cdf")


def error_vs_time_figure(ev: Evaluation):
    plt = pyplot()
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(9.6, 7.4), sharex=True)
    drawn = False
    for ax, column in ((ax1, 1), (ax2, 2)):
        for p in ev.policies:
            grid, (lo, mid, hi) = error_bands(ev, p, column)
            t = grid / 60.0
            st = _style(ev, p)
            m = np.where(np.isfinite(mid), mid, np.nan)
            drawn = drawn or bool(np.isfinite(m).any())
            ax.plot(t, m, lw=1.8, label=f"{p}: median", **st)
            ok = np.isfinite(lo) & np.isfinite(hi)
            ax.fill_between(t, np.where(ok, lo, np.nan), np.where(ok, hi, np.nan), where=ok,
                            alpha=0.18, color=st["color"], lw=0, label=f"{p}: 25-75 %")
    if drawn:
        for ax in (ax1, ax2):
            ax.set_yscale("log")
            plain_log_ticks(ax)
            ax.grid(alpha=0.3, which="both")
    else:
        for ax in (ax1, ax2):
            ax.text(0.5, 0.5, "no estimates", transform=ax.transAxes, ha="center",
                    va="center")
    ax1.axhline(1.0, color="black", lw=0.8, ls=":")
    ax1.set_ylabel("horizontal error (m)")
    ax2.set_ylabel("sigma_H (m)")
    ax2.set_xlabel("flight time (min)")
    ax2.set_xlim(0.0, ev.budget_s / 60.0)
    ax1.set_title("(a) horizontal error against the truth", fontsize=9, loc="left")
    ax2.set_title("(b) the estimator's own uncertainty sigma_H", fontsize=9, loc="left")
    handles, labels = ax1.get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=len(ev.policies), fontsize=8,
               frameon=False)
    n = len(ev.seeds)
    fig.suptitle(f"{ev.scenario}: median and 25-75 % band over {n} seed{'s' * (n != 1)}\n"
                 "a search that ended keeps its final estimate; no estimate yet counts as "
                 "an infinite error (not drawn)", fontsize=9)
    fig.tight_layout(rect=(0.0, 0.09, 1.0, 1.0))
    return fig


def trajectories_figure(ev: Evaluation, *, terrain: TerrainModel | None = None):
    """The example worlds; ``terrain`` (the scenario world's) draws the ground."""
    from matplotlib.lines import Line2D

    plt = pyplot()
    seeds = ev.example_seeds
    n = max(1, len(seeds))
    fig, axes = plt.subplots(1, n, figsize=(4.9 * n + 1.6, 6.3), squeeze=False,
                             layout="constrained")
    axes = axes[0]
    area = np.asarray((*ev.area_enu_m, ev.area_enu_m[0]), dtype=float)
    by = {(e.policy, e.seed): e for e in ev.episodes}
    panels = []
    for ax, seed in zip(axes, seeds, strict=False):
        eps = [by[(p, seed)] for p in ev.policies if (p, seed) in by]
        pts = [v[:2] for e in eps for v in (*e.truth_enu_m.values(), *e.estimates_enu_m.values())]
        extent = search_extent(ev.area_enu_m, pts)
        set_extent(ax, extent)
        panels.append((ax, ground_grid(terrain, extent)))
    grids = [g for _, g in panels if g is not None]
    if grids:
        norm = ground_norm(grids)
        mappable = None
        for ax, g in panels:
            if g is not None:
                mappable = draw_ground(ax, g, norm)
        ground_colorbar(fig, mappable, list(axes), shrink=0.7)
    for ax, seed in zip(axes, seeds, strict=False):
        ax.plot(area[:, 0], area[:, 1], color="black", lw=1.0, zorder=3)
        truth: dict = {}
        handles = []
        for k_pol, p in enumerate(ev.policies):
            e = by.get((p, seed))
            if e is None or e.track_enu_m is None:
                continue
            st = _style(ev, p)
            mk = policy_marker(ev.policies, p)
            row = {r["bssid"]: r for r in e.rows}
            first = next(iter(row.values()), {})
            end = f"{first.get('ended', '?')} {first.get('flight_time_s', math.nan) / 60:.1f} min"
            for trk in e.track_enu_m:
                if len(trk):
                    ax.plot(trk[:, 0], trk[:, 1], lw=max(0.9, 2.2 - 0.5 * k_pol), alpha=0.9,
                            marker=mk, ms=4.5, markevery=0.25, mfc="white",
                            zorder=4 + 0.1 * k_pol, **st)
            handles.append(Line2D([], [], lw=1.6, marker=mk, ms=6, mfc="white",
                                  label=f"{p} ({end})", **st))
            for b, est in e.estimates_enu_m.items():
                r = row.get(b, {})
                r95 = r95_radius_m(r.get("r95_h_m"), r.get("sigma_h_m"))
                # later policies smaller and on top: estimates at one place all show
                ax.plot(est[0], est[1], marker=mk, ms=max(4.0, 11.0 - 2.5 * k_pol), mec="white",
                        mew=0.7, ls="none", color=st["color"], zorder=8 + 0.1 * k_pol,
                        gid=f"estimate:{p}")
                if r95 is not None:
                    ax.add_patch(plt.Circle(est[:2], r95, fill=False, color=st["color"],
                                            lw=1.1, zorder=7))
            truth.update(e.truth_enu_m)
            if e.track_enu_m and len(e.track_enu_m[0]):
                ax.plot(*e.track_enu_m[0][0], marker="^", color="black", ms=7, ls="none",
                        zorder=9)
        for tr in truth.values():
            ax.plot(tr[0], tr[1], marker="*", ms=15, mfc="none", mec="black", mew=1.3,
                    ls="none", zorder=6)
        ax.set_title(f"seed {seed}", fontsize=9)
        ax.set_xlabel("east (m)")
        ax.grid(alpha=0.3)
        ax.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, -0.11),
                  fontsize=7.5, frameon=False)
    if not seeds:
        axes[0].text(0.5, 0.5, "no example seeds", transform=axes[0].transAxes,
                     ha="center", va="center")
    axes[0].set_ylabel("north (m)")
    common = [Line2D([], [], color="black", lw=1.0, label="search area"),
              Line2D([], [], ls="none", marker="^", color="black", ms=7, label="take-off"),
              Line2D([], [], ls="none", marker="*", ms=12, mfc="none", mec="black",
                     label="responder (truth)"),
              Line2D([], [], ls="none", marker="o", ms=12, mfc="none", mec="0.3",
                     label="final estimate (the policy's marker), 95 % circle")]
    fig.legend(handles=common, loc="outside lower center", ncol=4, fontsize=8, frameon=False)
    fig.suptitle(f"{ev.scenario}: example worlds, every policy on the same world", fontsize=10)
    return fig


def plot_evaluation(ev: Evaluation, out_dir: str | Path, *,
                    terrain: TerrainModel | None = None) -> list[Path]:
    """Write :data:`FIGURES` into ``out_dir`` (created if needed); ``terrain`` (the
    scenario world's) is drawn under the example worlds."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    return [
        save_figure(time_to_localise_figure(ev), out / FIGURES[0]),
        save_figure(error_vs_time_figure(ev), out / FIGURES[1]),
        save_figure(trajectories_figure(ev, terrain=terrain), out / FIGURES[2]),
    ]
