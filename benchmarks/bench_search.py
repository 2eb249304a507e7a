"""Closed-loop search benchmark (issue: closed loop in simulated time).

1. Speed: simulated seconds per wall second of the closed loop for each policy (the
   target is >= 500x real time including every CasADi re-plan), with the share of the
   wall time spent in optimiser solves, and the one-off planner build.
2. Time to localise: on N seeds of ``search-random-los-rtk``, the flight time until
   the estimate is within 1 m of the truth and stays there (to the end of the
   search), for ``adaptive`` against ``lawnmower`` (targets: adaptive <= 5 min median
   and <= 0.5x the lawnmower's). A search that never gets within 1 m counts as the
   budget (censored; the share that got there is printed).
3. With standalone GNSS (``search-random-los``): the error after 10 minutes.

    python benchmarks/bench_search.py --seeds 30
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import sim
from envs.loop import DEFAULT_MODE, LoopConfig, run_search
from envs.metrics import error_at_s, median, quantile, time_within_s
from envs.policies import load_policy


def _run(scenario, policy_name: str, seed: int, config: LoopConfig):
    policy = load_policy(policy_name)
    t0 = time.perf_counter()
    res = run_search(scenario, policy, seed, config=config)
    wall = time.perf_counter() - t0
    solve = getattr(policy, "solve_time_s", 0.0)
    return res, wall, solve


def main() -> None:
    from tqdm import tqdm

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=30)
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--mode", default=DEFAULT_MODE)
    ap.add_argument("--policies", default="adaptive,lawnmower,expanding-square")
    a = ap.parse_args()
    config = LoopConfig(mode=a.mode)
    policies = a.policies.split(",")
    seeds = range(a.first_seed, a.first_seed + a.seeds)

    # the planner's one-off build (cached per process afterwards)
    t0 = time.perf_counter()
    load_policy("adaptive").reset(
        __import__("envs.loop", fromlist=["mission_of"]).mission_of(
            sim.load_scenario("search-random-los-rtk")), None)
    build = time.perf_counter() - t0

    rtk = sim.load_scenario("search-random-los-rtk")
    standalone = sim.load_scenario("search-random-los")
    ten = dataclasses.replace(standalone, search=dataclasses.replace(standalone.search,
                                                                     budget_s=600.0))
    rows = {p: [] for p in policies}
    rows10 = {p: [] for p in policies}
    jobs = [(p, s) for s in seeds for p in policies]
    for p, s in tqdm(jobs, desc="bench_search", unit="search"):
        res, wall, solve = _run(rtk, p, s, config)
        (series,) = res.series.values()
        rows[p].append((res.flight_time_s, wall, solve, time_within_s(series, 1.0),
                        res.responders[0].get("err_h_m"), res.ended, res.replans))
        res10, _, _ = _run(ten, p, s, config)
        (series10,) = res10.series.values()
        rows10[p].append(error_at_s(series10, 600.0))

    print(f"\nplanner build (once per process): {build:.2f} s; estimator mode {a.mode}; "
          f"{len(seeds)} seeds from {a.first_seed}")
    print(f"\n{'policy':<18}{'sim/wall':>10}{'solve share':>13}{'replans':>9}"
          f"{'within 1 m':>12}{'median t1m':>12}{'p90 t1m':>9}{'median err':>12}"
          f"{'err@10min':>11}")
    medians = {}
    for p in policies:
        r = rows[p]
        sim_s = sum(x[0] for x in r)
        wall = sum(x[1] for x in r)
        solve = sum(x[2] for x in r)
        budget = rtk.search.budget_s
        t1 = [x[3] if x[3] is not None else budget for x in r]
        got = sum(x[3] is not None for x in r)
        errs = [x[4] for x in r if x[4] is not None]
        e10 = [e for e in rows10[p] if e is not None]
        medians[p] = median(t1)
        print(f"{p:<18}{sim_s / wall:>9.0f}x{solve / wall:>12.1%}"
              f"{median([x[6] for x in r]):>9.0f}{got:>7d}/{len(r):<4d}"
              f"{medians[p] / 60:>9.1f} min{quantile(t1, 0.9) / 60:>5.1f} min"
              f"{median(errs):>10.2f} m{median(e10):>9.2f} m")
    if "adaptive" in medians and "lawnmower" in medians:
        ratio = medians["adaptive"] / medians["lawnmower"]
        print(f"\nadaptive median time to 1 m: {medians['adaptive'] / 60:.1f} min (target "
              f"<= 5 min); ratio to lawnmower {ratio:.2f} (target <= 0.5; a lawnmower that "
              "never gets there counts as its budget)")


if __name__ == "__main__":
    main()
