"""``osa/Search-v1`` on held-out test worlds: a trained policy, the hand-written policy
in v1's actions, a uniformly random v1 policy and ``adaptive`` (docs/rl.md); and the
hand-written policy in ``osa/Search-v2``'s and ``osa/Search-v3``'s actions
(``heuristic-v2``, ``heuristic-v3``).

Every policy flies ``osa search`` (``envs.loop.run_search``) on the same first
``--seeds`` test worlds (common random numbers). Per world: the time until every
expected responder is localised (the estimator's judgement; censored at the budget),
the number localised, the mean horizontal error of the final estimates (the
truth, for evaluation only), and whether the flight ended at take-off (within
``HOME_M`` horizontally of where it started) with a responder heard but not
localised (``home_unlocalised``: issue 20 asks that a trained policy never does).
Paired two-sided exact sign tests (ties dropped) and Wilcoxon signed-rank tests (zero
differences dropped) compare each policy with ``adaptive`` on the time. ``--model``
(repeatable) adds ``ppo:PATH`` policies; ``--skip N`` flies test worlds N, N + 1, ...
(rows of more worlds join with ``--table A.json B.json``). ``--curve MODEL`` draws the
learning curve of an ``osa train`` folder (``progress.csv`` and ``validation.json``).

    python benchmarks/bench_rl_v1.py --model MODEL --seeds 20 --json rows.json
    python benchmarks/bench_rl_v1.py --table rows.json [more.json ...]
    python benchmarks/bench_rl_v1.py --curve MODEL --figure curve.png
"""

from __future__ import annotations

import argparse
import csv
import json
import math
from pathlib import Path

import numpy as np

import sim
from envs.gym.interface import PLAN_KINDS, EnvConfig, Pilot
from envs.gym.plan_actions import PlanActions, plan_heuristic
from envs.gym.trained import META_FILE
from envs.loop import run_search
from envs.policies import load_policy
from envs.seeds import split_seeds
from planner.observation import Decision

PLAN_POLICIES = ("heuristic", "random", "heuristic-v2", "heuristic-v3")


class PlanPolicy:
    """A policy in ``osa/Search-v1``'s actions flying ``osa search``: ``heuristic``
    (:func:`plan_heuristic`) or ``random`` (uniform actions from the loop's generator);
    ``heuristic-v2`` / ``heuristic-v3``: :func:`plan_heuristic` in ``osa/Search-v2``'s /
    ``osa/Search-v3``'s actions."""

    def __init__(self, name: str, config: EnvConfig = EnvConfig(max_responders=5,
                                                                 coverage_cells=6)) -> None:
        self.name = name
        self.config = config

    def reset(self, mission, rng) -> None:
        self.rng = rng
        kind = {"heuristic-v2": "plan-v2", "heuristic-v3": "plan-v3"}.get(self.name, "plan")
        actions = PlanActions(self.config, **PLAN_KINDS[kind])
        self.pilot = Pilot(kind, self.config, actions=actions)
        self.pilot.reset(mission)
        n = self.pilot.action_space.n
        self.act = (plan_heuristic(self.pilot.actions) if self.name != "random"
                    else (lambda enc: int(self.rng.integers(n))))

    def decide(self, obs) -> Decision:
        enc, _ = self.pilot.observe(obs)
        if self.pilot.done(obs):
            return Decision(localised=self.pilot.localised, done=True)
        return self.pilot.act(self.act(enc), obs)


HOME_M = 10.0  # "at take-off": the end of the true track this close to its start


def fly(scenario, name: str, seed: int) -> dict:
    """One ``osa search`` of policy ``name`` (one of :data:`PLAN_POLICIES`, a named
    policy or ``ppo:PATH``) on world ``seed``."""
    policy = PlanPolicy(name) if name in PLAN_POLICIES else load_policy(name)
    res = run_search(scenario, policy, seed)
    budget = scenario.search.budget_s
    times = [r.get("localised_at_s") for r in res.responders]
    n_loc = sum(t is not None for t in times)
    want = scenario.search.expected_responders or len(times)
    t_all = max(t for t in times if t is not None) if times and n_loc >= want else budget
    errs = [r["err_h_m"] for r in res.responders if r.get("err_h_m") is not None]
    track = res.true_track[0]
    home = bool(len(track)) and float(np.hypot(*(track[-1][:2] - track[0][:2]))) < HOME_M
    unloc = sum("detected_at_s" in r and r.get("localised_at_s") is None
                for r in res.responders)
    return {"policy": name, "seed": seed, "t_all_s": float(t_all), "localised": n_loc,
            "responders": len(times), "err_h_m": float(np.mean(errs)) if errs else None,
            "flight_time_s": res.flight_time_s, "ended": res.ended,
            "home_unlocalised": bool(home and unloc > 0)}


def sign_test_two_sided(wins: int, losses: int) -> float:
    n = wins + losses
    if n == 0:
        return 1.0
    k = min(wins, losses)
    return min(1.0, 2 * sum(math.comb(n, i) for i in range(k + 1)) / 2**n)


def wilcoxon_two_sided(x: np.ndarray, y: np.ndarray) -> float:
    """The two-sided Wilcoxon signed-rank p of paired ``x`` and ``y`` (zero differences
    dropped; 1 when every pair ties)."""
    from scipy.stats import wilcoxon

    d = np.asarray(x, dtype=float) - np.asarray(y, dtype=float)
    if not np.any(d != 0):
        return 1.0
    return float(wilcoxon(d, zero_method="wilcox", alternative="two-sided").pvalue)


def table(rows: list[dict], budget: float) -> str:
    pols = list(dict.fromkeys(r["policy"] for r in rows))
    by = {p: sorted((r for r in rows if r["policy"] == p), key=lambda r: r["seed"])
          for p in pols}
    w0 = max(11, *(len(p) + 1 for p in pols))
    out = [f"{'policy':<{w0}}{'all localised':>14}{'responders':>11}{'median t_all':>13}"
           f"{'median err':>11}{'home+heard':>11}{'vs adaptive (faster/slower/tie, p)':>37}"
           f"{'Wilcoxon p':>11}"]
    for p in pols:
        rs = by[p]
        t = np.array([r["t_all_s"] for r in rs])
        done = np.mean([r["t_all_s"] < budget for r in rs])
        loc = sum(r["localised"] for r in rs) / max(sum(r["responders"] for r in rs), 1)
        errs = [r["err_h_m"] for r in rs if r["err_h_m"] is not None]
        hov = [r["home_unlocalised"] for r in rs if "home_unlocalised" in r]
        home = f"{sum(hov)}/{len(hov)}" if hov else "-"
        cmp, wil = "", ""
        if "adaptive" in by and p != "adaptive":
            if [r["seed"] for r in by["adaptive"]] != [r["seed"] for r in rs]:
                raise ValueError(f"{p} and adaptive flew different worlds")
            a = np.array([r["t_all_s"] for r in by["adaptive"]])
            w, lo, ti = int((t < a).sum()), int((t > a).sum()), int((t == a).sum())
            cmp = f"{w}/{lo}/{ti}, p = {sign_test_two_sided(w, lo):.2g}"
            wil = f"{wilcoxon_two_sided(t, a):.2g}"
        out.append(f"{p:<{w0}}{100 * done:>13.0f}%{100 * loc:>10.0f}%{np.median(t):>12.0f}s"
                   f"{(f'{np.median(errs):.2f} m' if errs else '-'):>11}{home:>11}{cmp:>37}"
                   f"{wil:>11}")
    return "\n".join(out)


def curve(model: str, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    d = Path(model)
    with open(d / "progress.csv") as f:
        rows = [r for r in csv.DictReader(f) if r.get("rollout/ep_rew_mean")]
    steps = [float(r["time/total_timesteps"]) for r in rows]
    ret = [float(r["rollout/ep_rew_mean"]) for r in rows]
    val = json.loads((d / "validation.json").read_text())
    fig, ax = plt.subplots(1, 2, figsize=(10, 3.6))
    ax[0].plot(steps, ret, color="C2")
    warm = [float(r["time/total_timesteps"]) for r in rows if r.get("train/critic_warmup") == "1"]
    if warm:  # --critic-warmup: the rollouts whose update fitted only the value head
        ax[0].axvspan(0, max(warm), color="0.85",
                      label="critic warm-up: the clone flies, unchanged")
        ax[0].legend(loc="upper right", fontsize=8)
    ax[0].set_xlabel("training steps (decisions)")
    ax[0].set_ylabel("mean return, last 100 training episodes")
    ax[0].set_title("training (stochastic policy)", fontsize=10)
    ax[0].grid(alpha=0.3)
    vs = [v["steps"] for v in val]
    # two y-axes: each axis, its ticks and its line in one colour, and one legend for both
    h1 = ax[1].plot(vs, [v["median_time_s"] for v in val], "o-", color="C0",
                    label="median time to localise all (s, left axis)")
    ax[1].set_xlabel("training steps (decisions)")
    ax[1].set_ylabel("median time to localise all (s)", color="C0")
    ax[1].tick_params(axis="y", colors="C0")
    ax[1].set_ylim(0, 1.05 * max(v["median_time_s"] for v in val))
    ax[1].set_title(f"validation ({val[0]['worlds']} worlds, deterministic policy)",
                    fontsize=10)
    ax2 = ax[1].twinx()
    h2 = ax2.plot(vs, [100 * v["localised"] for v in val], "s--", color="C1",
                  label="worlds all localised (%, right axis)")
    ax2.set_ylabel("worlds all localised (%)", color="C1")
    ax2.tick_params(axis="y", colors="C1")
    ax2.set_ylim(0, 100)
    ax[1].legend(handles=[*h1, *h2], loc="lower left", fontsize=8)
    ax[1].grid(alpha=0.3)
    from matplotlib.ticker import MaxNLocator

    for a in ax:
        a.xaxis.set_major_locator(MaxNLocator(5))
    meta = d / META_FILE
    env_id = json.loads(meta.read_text()).get("env_id") if meta.is_file() else "osa/Search-v1"
    fig.suptitle(f"osa train {env_id}: {d.name}")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    print(f"wrote {path}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="search-five-mixed")
    ap.add_argument("--seeds", type=int, default=20, help="test worlds to fly")
    ap.add_argument("--skip", type=int, default=0, help="skip the first N test worlds")
    ap.add_argument("--model", action="append", default=[],
                    help="an osa train folder, flown as ppo:PATH (repeat for several)")
    ap.add_argument("--policies", default="adaptive,heuristic,random")
    ap.add_argument("--json", default=None, help="write the rows here")
    ap.add_argument("--curve", default=None, metavar="MODEL", help="draw MODEL's curve")
    ap.add_argument("--figure", default=None)
    ap.add_argument("--table", nargs="+", default=None, metavar="JSON",
                    help="print the table of the rows of these files (one table)")
    a = ap.parse_args()
    if a.table:
        rows = [r for f in a.table for r in json.loads(Path(f).read_text())]
        print(table(rows, sim.load_scenario(a.scenario).search.budget_s))
        return
    if a.curve:
        curve(a.curve, a.figure or "curve.png")
        return
    sc = sim.load_scenario(a.scenario)
    pols = [p for p in a.policies.split(",") if p] + [f"ppo:{m}" for m in a.model]
    rows = [fly(sc, p, s) for p in pols for s in split_seeds("test", a.skip + a.seeds)[a.skip:]]
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1))
    print(f"{a.scenario}: {a.seeds} test worlds, budget {sc.search.budget_s:.0f} s "
          "(t_all: every expected responder localised, censored at the budget)")
    print(table(rows, sc.search.budget_s))


if __name__ == "__main__":
    main()
