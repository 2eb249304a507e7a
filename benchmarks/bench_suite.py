"""The benchmark suite's table (docs/rl.md, "The benchmark suite"): policies on held-out
test worlds of suite presets, the timed search challenge and paired tests.

Every policy flies the first ``--seeds`` worlds of the test split of each ``--suite``
preset (the same worlds for every policy), serially in this process
(``envs.evaluate.evaluate``, as ``osa evaluate --split test --workers 1``), and the
script prints per preset ``osa evaluate``'s three tables (summary, timed challenge,
paired comparisons) and a Markdown table for docs/rl.md, with the CPU time spent.
A trained policy joins as ``ppo:PATH`` in ``--policies``.

    python benchmarks/bench_suite.py --suite suite/r5-c30-sa-u1,suite/r1-c30-sa-u1 \\
        --seeds 30 --policies random,random:waypoint,lawnmower,expanding-square,adaptive
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

from envs.evaluate import (
    compare_pairs,
    evaluate,
    format_challenge,
    format_paired,
    format_summary,
    summarise,
    summary_json,
)
from envs.seeds import split_seeds
from sim.scenario import search_scenario

DEFAULT_POLICIES = "random,random:waypoint,lawnmower,expanding-square,adaptive"


def _min(v: float, censored: bool) -> str:
    return "-" if not math.isfinite(v) else (">= " if censored else "") + f"{v / 60:.1f}"


def _m(v: float) -> str:
    return "-" if not math.isfinite(v) else f"{v:.2f}"


def _p(v: float) -> str:
    return "-" if not math.isfinite(v) else (f"{v:.1e}" if v < 0.001 else f"{v:.3f}")


def markdown(rows: list[dict], policies: list[str], budget_s: float, best: str) -> str:
    """The docs table: per policy the challenge, and its paired tests against ``best``."""
    summ = summarise(rows, policies, budget_s)
    pairs = {(c.a, c.b, c.metric): c for c in compare_pairs(rows, policies, budget_s)}
    out = ["| policy | responders localised | all localised (episodes) | time until all, "
           "median (min) | error at 3 min, median (m) | at 10 min | final within 2 m | "
           f"within 5 m | vs {best}: time until all, W-L-T (sign p, Wilcoxon p) | "
           f"vs {best}: final error, W-L-T (sign p, Wilcoxon p) |",
           "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for s in summ:
        cells = []
        for metric in ("all_localised_at_s", "error_m"):
            c = pairs.get((s.policy, best, metric))
            flip = False
            if c is None:
                c, flip = pairs.get((best, s.policy, metric)), True
            if c is None:
                cells.append("-")
                continue
            w, lo = (c.losses, c.wins) if flip else (c.wins, c.losses)
            cells.append(f"{w}-{lo}-{c.ties} ({_p(c.sign_p)}, {_p(c.wilcoxon_p)})")
        out.append(
            f"| {s.policy} | {s.localised}/{s.responders} ({s.success_rate:.0%}) | "
            f"{s.all_localised}/{s.episodes} | "
            f"{_min(s.all_localised_at_s_median, s.all_localised_at_s_median_censored)} | "
            f"{_m(s.err_h_3min_m_median)} | {_m(s.err_h_10min_m_median)} | "
            f"{s.within_2m}/{s.responders} | {s.within_5m}/{s.responders} | "
            f"{cells[0]} | {cells[1]} |")
    return "\n".join(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--suite", default="suite/r5-c30-sa-u1",
                    help="comma-separated suite presets (or any search scenarios)")
    ap.add_argument("--seeds", type=int, default=30, help="test worlds per preset")
    ap.add_argument("--policies", default=DEFAULT_POLICIES)
    ap.add_argument("--best", default="adaptive", help="the policy the table pairs against")
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--json", default=None, help="write summaries and paired tests here")
    a = ap.parse_args()
    policies = [p.strip() for p in a.policies.split(",")]
    seeds = split_seeds("test", a.seeds)
    report = {}
    for name in a.suite.split(","):
        sc = search_scenario(name)
        t0, w0 = time.process_time(), time.perf_counter()
        ev = evaluate(sc, policies, seeds, workers=a.workers)
        cpu, wall = time.process_time() - t0, time.perf_counter() - w0
        rows, budget = ev.rows, ev.budget_s
        summ = summarise(rows, policies, budget)
        print(f"\n{name}: {len(policies)} policies x {len(seeds)} test worlds "
              f"({seeds[0]}..{seeds[-1]}), budget {budget / 60:.0f} min; {cpu / 60:.1f} "
              f"CPU-min in this process ({wall / 60:.1f} min wall, {a.workers} worker(s))\n")
        print(format_summary(summ))
        print()
        print(format_challenge(summ))
        print()
        print(format_paired(compare_pairs(rows, policies, budget)))
        print()
        print(markdown(rows, policies, budget, a.best))
        report[name] = summary_json(rows, policies, budget)
    if a.json:
        Path(a.json).write_text(json.dumps(report, indent=1, default=str))


if __name__ == "__main__":
    main()
