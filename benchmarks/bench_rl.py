"""The training recipe against the fixed patterns, on held-out (test split) worlds.

1. Trains the recipe of docs/rl.md (``osa train --env osa/Search-v0 --steps 80000
   --seed 0 --eval-every 10000 --eval-worlds 20``, timed), unless ``--model`` names a
   trained one.
2. Flies ``osa search`` (``envs.loop.run_search``) on the first ``--seeds`` worlds of
   the test split with the trained policy (``ppo:MODEL``), ``lawnmower``,
   ``expanding-square``, ``adaptive`` and ``random`` (a uniformly random choice of
   manoeuvre, the env's actions, seeded: ``envs.policies.RandomPolicy``): the same
   worlds for every policy.
3. Prints per policy the share localised within the budget, the median and 90th
   percentile of the time to localise (``localised_at_s``; a world never localised
   counts as the budget: censored), the median horizontal error; and draws the
   distribution of the time to localise (``--figure``).

    python benchmarks/bench_rl.py --seeds 30 --figure docs/figures/rl-recipe.png
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

import sim
from envs.loop import run_search
from envs.policies import load_policy
from envs.seeds import split_seeds


def fly(scenario, policy_name: str, seed: int, model: str) -> dict:
    policy = load_policy(f"ppo:{model}" if policy_name == "ppo" else policy_name)
    res = run_search(scenario, policy, seed)
    r = res.responders[0]
    t = r.get("localised_at_s")
    return {"policy": policy_name, "seed": seed, "ended": res.ended,
            "localised_at_s": t, "err_h_m": r.get("err_h_m"),
            "flight_time_s": res.flight_time_s}


def main() -> None:
    from tqdm import tqdm

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="search-random-los")
    ap.add_argument("--seeds", type=int, default=30)
    ap.add_argument("--model", default=None, help="a trained model (default: train one)")
    ap.add_argument("--steps", type=int, default=80_000)
    ap.add_argument("--out", default="osa-rl-recipe", help="where the recipe's model goes")
    ap.add_argument("--policies", default="ppo,lawnmower,expanding-square,adaptive,random")
    ap.add_argument("--figure", default=None)
    ap.add_argument("--json", default=None, help="write the rows here")
    a = ap.parse_args()
    sc = sim.load_scenario(a.scenario)
    budget = sc.search.budget_s
    model = a.model
    if model is None:
        model = a.out
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-m", "envs.cli", "train", "--env", "osa/Search-v0",
                        "--steps", str(a.steps), "--seed", "0", "--eval-every", "10000",
                        "--eval-worlds", "20", "-o", model], check=True)
        print(f"recipe trained in {(time.perf_counter() - t0) / 60:.1f} min (wall)")
    seeds = split_seeds("test", a.seeds)
    pols = a.policies.split(",")
    rows = []
    for p in pols:
        for s in tqdm(seeds, desc=p, unit="world"):
            rows.append(fly(sc, p, s, model))
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1))
    print(f"\n{a.scenario}, test worlds {seeds[0]}..{seeds[-1]} ({len(seeds)}), budget "
          f"{budget:.0f} s; time to localise censored at the budget\n")
    print(f"{'policy':<18}{'localised':>10}{'median t':>10}{'p90 t':>8}{'median err':>12}")
    times = {}
    for p in pols:
        rs = [r for r in rows if r["policy"] == p]
        t = np.array([r["localised_at_s"] if r["localised_at_s"] is not None else budget
                      for r in rs])
        times[p] = t
        loc = np.mean([r["localised_at_s"] is not None for r in rs])
        errs = [r["err_h_m"] for r in rs if r["err_h_m"] is not None]
        med_err = f"{np.median(errs):.2f} m" if errs else "-"
        print(f"{p:<18}{100 * loc:>9.0f}%{np.median(t):>9.0f}s{np.quantile(t, 0.9):>7.0f}s"
              f"{med_err:>12}")
    if a.figure:
        plot(times, budget, a.scenario, len(seeds), a.figure)
        print(f"\nwrote {a.figure}")


def plot(times: dict, budget: float, scenario: str, n: int, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8.2, 3.6), dpi=110)
    for p, t in times.items():
        x = np.sort(t)
        y = np.arange(1, len(x) + 1) / len(x)
        x = np.concatenate([[0.0], x])
        y = np.concatenate([[0.0], y])
        y[1:][x[1:] >= budget - 1e-9] = np.nan  # censored: never localised
        ax.step(x, y, where="post", label=f"{p} (median {np.median(t):.0f} s)")
    ax.axvline(budget, color="gray", lw=0.8, ls=":")
    ax.set_xlim(0, budget * 1.02)
    ax.set_ylim(0, 1)
    ax.set_xlabel("flight time to localise (s)")
    ax.set_ylabel("share of worlds localised")
    ax.set_title(f"{scenario}: {n} held-out test worlds", fontsize=10)
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))  # outside the data
    ax.grid(alpha=0.3)
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)


if __name__ == "__main__":
    main()
