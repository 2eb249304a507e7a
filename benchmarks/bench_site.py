"""Searching a real site: what the hills cost (issue 17, item 7).

``osa search`` in process (:func:`envs.loop.run_search`) with ``adaptive``, ``lawnmower``
and ``expanding-square`` on the hilly site (``site-valley``: a DEM of a valley whose spur
hides part of the area from the take-off point, a power line as keep-outs), with
standalone and RTK GNSS, and on its open twin: the same area, keep-outs, responders
and seeds, the ground flat at the take-off point's height and the radio's terrain
occlusion off. The twin separates what the terrain costs from what the policy costs.

Per site, GNSS and policy, over the responders of all seeds (two per seed): the share
heard, the share within 5 m of the truth at the end ("success"), the median flight
time until the horizontal error is within 1 m and within 5 m and stays so to the end
of the search (a responder that never gets there counts as the budget: censored), and
the median time the responder was first heard. On the hilly site the same split into
responders hidden from the take-off point (the terrain blocks the line from a drone at
the search height above take-off: knife-edge nu > 0) and those in view.

    python benchmarks/bench_site.py --seeds 30 --plot docs/figures/site-bench.png
    python benchmarks/bench_site.py --seeds 3 --policies adaptive       # a quick look
    python benchmarks/bench_site.py --load runs.json --plot fig.png      # re-print, re-plot

CPU time (``time.process_time``) is printed per run group; 30 seeds (360 searches)
took 3.3 CPU minutes on the 2-core development machine (19 min of wall time while other
jobs ran).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

SITE = "site-valley"
POLICIES = ("adaptive", "lawnmower", "expanding-square")
GNSS = {"standalone": SITE, "rtk": f"{SITE}-rtk"}


def open_twin(scenario):
    """The same scenario over flat ground at the take-off point's height (the area,
    keep-outs, responders' horizontal places and the seeds' draws unchanged), with the
    radio's terrain occlusion off."""
    from sim import HillsTerrain

    ground = float(np.asarray(scenario.world.terrain.height_m(0.0, 0.0)))
    flat = HillsTerrain(base_m=ground, slope_e=0.0, slope_n=0.0, hills=(),
                        ripple_amplitude_m=0.0)
    return dataclasses.replace(
        scenario, name=f"{scenario.name}-open",
        world=dataclasses.replace(scenario.world, terrain=flat),
        ftm=dataclasses.replace(scenario.ftm, occlusion=False))


def hidden_from_takeoff(scenario, seed: int) -> dict[str, bool]:
    """Per responder of the seed's world: does the terrain block the straight line from
    a drone at the search height above the take-off point to its antenna (nu > 0)?"""
    from sim.realisation import realise

    world = realise(scenario, seed).world
    t = world.terrain
    s = scenario.search
    drone = np.array([[s.start_e_m, s.start_n_m,
                       float(np.asarray(t.height_m(s.start_e_m, s.start_n_m))) + s.height_m]])
    out = {}
    for r in world.responders:
        ant = np.array([[r.e_m, r.n_m,
                         float(np.asarray(t.height_m(r.e_m, r.n_m))) + r.antenna_height_m]])
        ob = scenario.ftm.obstruction(ant, drone, t)
        out[r.bssid] = bool(ob.nu[0] > 0.0)
    return out


def run_one(scenario, policy_name: str, seed: int, mode: str) -> dict:
    """One search; per responder: heard, final error, times to 1 m and 5 m."""
    from envs.loop import LoopConfig, run_search
    from envs.metrics import time_within_s
    from envs.policies import load_policy

    policy = load_policy(policy_name)
    c0 = time.process_time()
    res = run_search(scenario, policy, seed, config=LoopConfig(mode=mode))
    cpu = time.process_time() - c0
    resp = []
    for r in res.responders:
        series = res.series.get(r["bssid"], [])
        resp.append(dict(bssid=r["bssid"], concealment=r.get("concealment"),
                         heard_s=r.get("detected_at_s"), err_h_m=r.get("err_h_m"),
                         t1_s=time_within_s(series, 1.0), t5_s=time_within_s(series, 5.0)))
    return dict(policy=policy_name, seed=seed, ended=res.ended,
                flight_time_s=res.flight_time_s, cpu_s=cpu, refused=res.refused_plans,
                responders=resp)


def _median(v) -> float:
    return float(np.median(v)) if len(v) else math.nan


def summarise(rows: list[dict], budget_s: float, hidden: dict | None = None) -> dict:
    """Shares and medians over the responders of ``rows`` (censored at the budget);
    ``hidden`` = {(seed, bssid): bool} keeps only those hidden (True) or in view."""
    rs = [r for row in rows for r in row["responders"]
          if hidden is None or hidden[0].get((row["seed"], r["bssid"])) == hidden[1]]
    n = len(rs)
    if n == 0:
        return dict(n=0)

    def cens(key):
        return [r[key] if r[key] is not None else budget_s for r in rs]

    return dict(
        n=n,
        heard=sum(r["heard_s"] is not None for r in rs) / n,
        success=sum(r["err_h_m"] is not None and r["err_h_m"] <= 5.0 for r in rs) / n,
        within1=sum(r["t1_s"] is not None for r in rs) / n,
        t1_s=_median(cens("t1_s")), t5_s=_median(cens("t5_s")),
        heard_s=_median([r["heard_s"] for r in rs if r["heard_s"] is not None]),
    )


def _fmt_t(t: float, budget_s: float) -> str:
    if math.isnan(t):
        return "-"
    return f">{budget_s / 60:.0f} min" if t >= budget_s - 1e-9 else f"{t / 60:.1f} min"


def print_table(results: dict, budget_s: float, hidden_map: dict) -> None:
    print(f"\n{'site':<7}{'GNSS':<12}{'policy':<18}{'resp':>5}{'heard':>7}{'<=5 m':>7}"
          f"{'<=1 m':>7}{'t to 5 m':>10}{'t to 1 m':>10}{'heard at':>10}")
    for (site, gnss, policy), rows in results.items():
        s = summarise(rows, budget_s)
        print(f"{site:<7}{gnss:<12}{policy:<18}{s['n']:>5}{s['heard']:>7.0%}{s['success']:>7.0%}"
              f"{s['within1']:>7.0%}{_fmt_t(s['t5_s'], budget_s):>10}"
              f"{_fmt_t(s['t1_s'], budget_s):>10}{_fmt_t(s['heard_s'], budget_s):>10}")
    print("\nsplit by the responder's view from take-off on the hilly site (hidden: nu > 0;"
          " on the open twin the same responders)")
    for (site, gnss, policy), rows in results.items():
        for flag, name in ((True, "hidden"), (False, "in view")):
            s = summarise(rows, budget_s, (hidden_map, flag))
            if not s["n"]:
                continue
            print(f"{site:<7}{name[:7]:<8}{gnss[:4]:<5}{policy:<17}{s['n']:>5}{s['heard']:>7.0%}"
                  f"{s['success']:>7.0%}{s['within1']:>7.0%}"
                  f"{_fmt_t(s['t5_s'], budget_s):>10}{_fmt_t(s['t1_s'], budget_s):>10}"
                  f"{_fmt_t(s['heard_s'], budget_s):>10}")


def plot(results: dict, budget_s: float, path: Path, n_seeds: int) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    gnss_list = sorted({k[1] for k in results}, key=lambda g: g != "rtk")
    fig, axes = plt.subplots(len(gnss_list), 2, figsize=(10.5, 3.3 * len(gnss_list)),
                             dpi=110, squeeze=False)
    colours = {"adaptive": "C0", "lawnmower": "C1", "expanding-square": "C2"}
    for i, gnss in enumerate(gnss_list):
        for j, (key, label) in enumerate((("t1_s", "1 m"), ("t5_s", "5 m"))):
            ax = axes[i][j]
            for (site, g, policy), rows in results.items():
                if g != gnss:
                    continue
                t = np.sort([r[key] if r[key] is not None else np.inf
                             for row in rows for r in row["responders"]])
                y = np.arange(1, len(t) + 1) / len(t)
                ok = np.isfinite(t)
                x = np.concatenate([[0.0], t[ok], [budget_s]])
                yy = np.concatenate([[0.0], y[ok], [y[ok][-1] if ok.any() else 0.0]])
                ax.step(x, yy, where="post", color=colours.get(policy, "k"),
                        ls="-" if site == "hilly" else "--", lw=1.4,
                        label=f"{policy}, {site}")
            ax.set_xlim(0, budget_s)
            ax.set_ylim(0, 1)
            ax.grid(alpha=0.3)
            ax.set_xlabel(f"flight time until within {label} for good (s)")
            ax.set_ylabel("share of responders")
            ax.set_title(f"{gnss} GNSS: within {label}", fontsize=10)
    axes[0][1].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    fig.suptitle(f"{SITE}: hilly (solid) against its open twin (dashed), {n_seeds} seeds, "
                 "2 responders each", fontsize=10)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def _replay(a) -> int:
    """``--load``: the table and the figure of an earlier run's JSON."""
    try:
        d = json.loads(Path(a.load).read_text())
        results = {tuple(k.split(" ")): v for k, v in d["runs"].items()}
        hidden_map = {(int(k.split(" ")[0]), k.split(" ")[1]): h for k, h in d["hidden"].items()}
        budget, seeds = float(d["budget_s"]), d["seeds"]
    except (OSError, ValueError, KeyError, TypeError, IndexError) as exc:
        print(f"bench_site: cannot use {a.load}: {str(exc).splitlines()[0]}", file=sys.stderr)
        return 2
    print(f"{SITE}: {d.get('hidden_share', 0):.0%} of the {len(hidden_map)} responders of "
          f"seeds {seeds[0]}-{seeds[-1]} are hidden from the take-off point (from {a.load})")
    print_table(results, budget, hidden_map)
    if a.plot:
        plot(results, budget, Path(a.plot), len(seeds))
        print(f"\nwrote {a.plot}")
    return 0


def main(argv: list[str] | None = None) -> int:
    from tqdm import tqdm

    import sim
    from envs.commands._outputs import OutputRefusedError, claim_output_file
    from envs.loop import DEFAULT_MODE

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=30)
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--policies", default=",".join(POLICIES))
    ap.add_argument("--gnss", default="standalone,rtk", help="standalone, rtk or both")
    ap.add_argument("--sites", default="hilly,open", help="hilly, open or both")
    ap.add_argument("--mode", default=DEFAULT_MODE)
    ap.add_argument("--plot", default=None, help="write the CDF figure here (PNG)")
    ap.add_argument("--json", default=None, help="write every run's figures here")
    ap.add_argument("--force", action="store_true", help="replace existing outputs")
    ap.add_argument("--load", default=None, metavar="JSON",
                    help="print and plot the runs of an earlier --json instead of flying")
    a = ap.parse_args(argv)
    policies = [p for p in a.policies.split(",") if p]
    gnss_list = [g for g in a.gnss.split(",") if g]
    sites = [s for s in a.sites.split(",") if s]
    bad = [g for g in gnss_list if g not in GNSS] + [s for s in sites
                                                     if s not in ("hilly", "open")]
    if bad or a.seeds < 1:
        print(f"bench_site: unknown {bad[0] if bad else 'seed count'}", file=sys.stderr)
        return 2
    try:
        for p in (a.plot, a.json):
            if p:
                claim_output_file(p, force=a.force, inputs=[a.load] if a.load else [])
    except OutputRefusedError as exc:
        print(f"bench_site: {exc}", file=sys.stderr)
        return 2
    if a.load:
        return _replay(a)
    seeds = list(range(a.first_seed, a.first_seed + a.seeds))
    scenarios = {}
    for g in gnss_list:
        hilly = sim.load_scenario(GNSS[g])
        for site in sites:
            scenarios[site, g] = hilly if site == "hilly" else open_twin(hilly)
    base = sim.load_scenario(SITE)
    budget = base.search.budget_s
    hidden_map = {}
    for s in seeds:
        for b, h in hidden_from_takeoff(base, s).items():
            hidden_map[s, b] = h
    share = sum(hidden_map.values()) / len(hidden_map)
    print(f"{SITE}: {share:.0%} of the {len(hidden_map)} responders of seeds "
          f"{seeds[0]}-{seeds[-1]} are hidden from the take-off point at the search height "
          f"(the terrain blocks the line: nu > 0)")

    results: dict[tuple[str, str, str], list[dict]] = {}
    jobs = [(site, g, p, s) for (site, g) in scenarios for p in policies for s in seeds]
    c_all = time.process_time()
    for site, g, p, s in tqdm(jobs, desc="bench_site", unit="search"):
        row = run_one(scenarios[site, g], p, s, a.mode)
        results.setdefault((site, g, p), []).append(row)
    cpu_all = time.process_time() - c_all
    print(f"\n{len(jobs)} searches, {cpu_all / 60:.1f} CPU minutes "
          f"(estimator mode {a.mode}, budget {budget / 60:.0f} min)")
    for key, rows in results.items():
        cpu = [r["cpu_s"] for r in rows]
        refused = sum(r["refused"] for r in rows)
        print(f"  {' '.join(key):<36} median {np.median(cpu):.2f} CPU s per search, "
              f"max {max(cpu):.1f} s, refused plans {refused}")
    print_table(results, budget, hidden_map)
    if a.json:
        Path(a.json).write_text(json.dumps(
            dict(seeds=seeds, budget_s=budget, hidden_share=share,
                 hidden={f"{s} {b}": h for (s, b), h in hidden_map.items()},
                 runs={" ".join(k): v for k, v in results.items()}), indent=1))
    if a.plot:
        plot(results, budget, Path(a.plot), len(seeds))
        print(f"\nwrote {a.plot}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
