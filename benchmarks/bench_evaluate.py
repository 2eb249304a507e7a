"""Evaluation benchmark (issue 10, items 5 and 7): ``osa evaluate``'s throughput and
the policy comparison on the test seeds.

1. Throughput: episodes per wall second of the same workload (every policy on
   ``--throughput-seeds`` test seeds) serially in this process (1 worker), on 2
   local processes (pool start-up included: spawn and one planner build per process)
   and on a Dask ``LocalCluster`` of 2 single-threaded worker processes on 127.0.0.1
   (cluster start-up excluded: ``--scheduler`` meets an existing cluster); the
   median of ``--repeat`` interleaved runs. The rows of every run must be identical
   (checked).
2. Comparison: ``lawnmower``, ``expanding-square`` and ``adaptive`` (and ``ppo:PATH``
   with ``--ppo PATH``) on ``--seeds`` seeds of the test split: success rate, median
   and p90 time to localise (censored at the budget), median and p90 final error,
   and the time from which the error stays within 1 m (truth); the figures go to
   ``--figures``.

    python benchmarks/bench_evaluate.py --seeds 30 --figures bench-evaluate
"""

from __future__ import annotations

import argparse
import logging
import os
import time

from envs.commands._progress import QuantityProgress
from envs.evaluate import evaluate, format_summary, summarise, write_rows
from envs.evaluate_plots import plot_evaluation
from envs.metrics import median
from envs.seeds import split_seeds
from sim.scenario import load_scenario

FIXED = ("lawnmower", "expanding-square", "adaptive")


def _timed(desc: str, n: int, **kw):
    bar = QuantityProgress(desc, n, "episodes", every=max(1.0, n / 4))
    t0 = time.perf_counter()
    ev = evaluate(progress=lambda k, note: bar.update(k, note), **kw)
    wall = time.perf_counter() - t0
    bar.close()
    return ev, wall


def throughput(scenario, policies, seeds, repeat: int) -> None:
    from distributed import Client, LocalCluster

    n = len(policies) * len(seeds)
    common = dict(scenario=scenario, policies=policies, seeds=seeds)
    walls: dict[str, list[float]] = {"serial": [], "local": [], "dask": []}
    rows: dict[str, list] = {}
    loads = []
    t0 = time.perf_counter()
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address=None, silence_logs=logging.ERROR) as cluster, \
            Client(cluster, timeout=60, set_as_default=False) as client:
        client.wait_for_workers(2, timeout=120)
        start = time.perf_counter() - t0
        for r in range(repeat):  # interleaved, so a busy spell of the machine hits all three
            for key, kw in (("serial", {"workers": 1}), ("local", {"workers": 2}),
                            ("dask", {"client": client})):
                ev, w = _timed(f"{key} {r + 1}/{repeat}", n, **kw, **common)
                walls[key].append(w)
                rows.setdefault(key, ev.rows)
                if ev.rows != rows["serial"]:
                    raise SystemExit(f"{key}: the rows differ from the serial run's")
            loads.append(os.getloadavg()[0])
    w1 = median(walls["serial"])
    print(f"\nthroughput: {len(policies)} policies x {len(seeds)} test seeds = {n} episodes "
          f"of {scenario.name} (budget {scenario.search.budget_s / 60:.0f} min), median of "
          f"{repeat} interleaved runs; load average {median(loads):.2f} on "
          f"{os.cpu_count()} CPUs (other users' work included)")
    print(f"{'where':<40}{'wall (s)':>10}{'episodes/s':>12}{'x serial':>10}")
    names = {"serial": "1 worker (this process)",
             "local": "2 local processes (spawn, start-up in)",
             "dask": f"Dask LocalCluster 2x1 (+{start:.1f} s start)"}
    for key, name in names.items():
        w = median(walls[key])
        print(f"{name:<40}{w:>10.1f}{n / w:>12.2f}{w1 / w:>10.2f}")
    print("rows identical serial / 2 processes / Dask: True")


def comparison(scenario, policies, seeds, workers: int, figures: str | None,
               rows_out: str | None) -> None:
    n = len(policies) * len(seeds)
    ev, wall = _timed("comparison", n, scenario=scenario, policies=policies, seeds=seeds,
                      workers=workers, example_seeds=seeds[:3])
    print(f"\ncomparison on {len(seeds)} test seeds ({seeds[0]}..{seeds[-1]}) of "
          f"{scenario.name}, {n} episodes in {wall:.0f} s on {workers} workers ({n / wall:.2f}"
          " episodes/s); times in min (>= : censored at the budget), errors in m")
    summaries = summarise(ev.rows, policies, ev.budget_s)
    print(format_summary(summaries))
    best = min((s for s in summaries if s.policy in FIXED[:2]),
               key=lambda s: s.localised_at_s_median)
    for s in summaries:
        if s.policy != best.policy:
            r = s.localised_at_s_median / best.localised_at_s_median
            print(f"{s.policy}: median time to localise {r:.2f}x the best fixed pattern's "
                  f"({best.policy})")
    t1 = {p: median([r["time_within_1m_s"] if r["time_within_1m_s"] is not None
                     else ev.budget_s for r in ev.rows if r["policy"] == p]) for p in policies}
    print("median time to within 1 m for good (truth, censored): "
          + ", ".join(f"{p} {v / 60:.1f} min" for p, v in t1.items()))
    if rows_out:
        write_rows(ev.rows, rows_out)
        print(f"wrote {rows_out}")
    if figures:
        from sim import realise

        terrain = realise(scenario, seeds[0]).world.terrain  # the ground of the examples
        print("wrote " + ", ".join(str(p) for p in plot_evaluation(ev, figures,
                                                                   terrain=terrain)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="search-random-los-rtk")
    ap.add_argument("--seeds", type=int, default=30, help="test seeds of the comparison")
    ap.add_argument("--throughput-seeds", type=int, default=8)
    ap.add_argument("--repeat", type=int, default=3, help="throughput runs per configuration")
    ap.add_argument("--workers", type=int, default=2, help="workers of the comparison")
    ap.add_argument("--ppo", default=None, metavar="PATH", help="also compare ppo:PATH")
    ap.add_argument("--figures", default="bench-evaluate", metavar="DIR")
    ap.add_argument("--rows", default=None, metavar="FILE", help="write the comparison rows")
    ap.add_argument("--skip-throughput", action="store_true")
    ap.add_argument("--skip-comparison", action="store_true")
    a = ap.parse_args()
    scenario = load_scenario(a.scenario)
    policies = [*FIXED, *([f"ppo:{a.ppo}"] if a.ppo else [])]
    if not a.skip_throughput:
        throughput(scenario, list(FIXED), split_seeds("test", a.throughput_seeds), a.repeat)
    if not a.skip_comparison:
        comparison(scenario, policies, split_seeds("test", a.seeds), a.workers, a.figures,
                   a.rows)


if __name__ == "__main__":
    main()
