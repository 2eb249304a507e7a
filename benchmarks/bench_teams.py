"""Teams benchmark (docs/rl.md, Teams): a 2-UAV team trained in ``osa/Team-v0`` against
two independent ``adaptive`` UAVs on the 5-responder world ``benchmarks/team-r5.toml``,
on held-out test seeds.

    python benchmarks/bench_teams.py --steps 60000 --seeds 20 --out bench-teams

Runs, in this process (one core; CPU time is measured):

    osa train --env osa/Team-v0 --scenario benchmarks/team-r5.toml --steps N --seed 0 \\
        --envs 1 --eval-every N/3 --eval-worlds 5 -o OUT/team-ppo
    osa evaluate benchmarks/team-r5.toml --policies ppo:OUT/team-ppo,team:adaptive \\
        --split test --seeds K --workers 1 -o OUT/rows.csv

(``--scenario`` another 2-UAV scenario, e.g. ``suite/r5-c30-sa-u2``; ``--model`` an
existing team model instead of training), then pairs the policies per world on the
time until every responder is localised (a responder never localised: the budget,
censored), and prints a Markdown table:
responders localised, median and 90th percentile of that time, median final error,
and the paired sign test (two-sided, exact; ties dropped).
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCENARIO = ROOT / "benchmarks" / "team-r5.toml"


def sign_test_two_sided(wins: int, losses: int) -> float:
    n = wins + losses
    if n == 0:
        return 1.0
    k = min(wins, losses)
    tail = sum(math.comb(n, i) for i in range(k + 1)) / 2**n
    return min(1.0, 2 * tail)


def all_localised_s(rows: list[dict], budget_s: float) -> dict[int, float]:
    """Per seed: when the last responder was localised (the budget if one never was)."""
    out: dict[int, float] = {}
    for r in rows:
        t = r["localised_at_s"]
        t = budget_s if t is None else float(t)
        out[r["seed"]] = max(out.get(r["seed"], 0.0), t)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=60000)
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--out", default="bench-teams")
    ap.add_argument("--model", default=None, help="a trained team model (skip training)")
    ap.add_argument("--scenario", default=str(SCENARIO),
                    help="the 2-UAV scenario to train and evaluate on (default team-r5.toml)")
    a = ap.parse_args(argv)
    from envs.cli import main as osa
    from envs.evaluate import read_rows

    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    model = Path(a.model) if a.model else out / "team-ppo"
    cpu0 = time.process_time()
    if a.model is None:
        status = osa(["train", "--env", "osa/Team-v0", "--scenario", a.scenario,
                      "--steps", str(a.steps), "--seed", "0", "--envs", "1",
                      "--eval-every", str(max(a.steps // 3, 1)), "--eval-worlds", "5",
                      "--no-progress", "--force", "-o", str(model)])
        if status:
            return status
    cpu_train = time.process_time() - cpu0
    policies = [f"ppo:{model}", "team:adaptive"]
    rows_path = out / "rows.csv"
    status = osa(["evaluate", a.scenario, "--policies", ",".join(policies), "--split", "test",
                  "--seeds", str(a.seeds), "--workers", "1", "--no-progress", "--no-figures",
                  "--force", "-o", str(rows_path)])
    if status:
        return status
    cpu_eval = time.process_time() - cpu0 - cpu_train
    rows = read_rows(rows_path)
    budget = float(rows[0]["budget_s"])
    times = {p: all_localised_s([r for r in rows if r["policy"] == p], budget) for p in policies}
    print(f"\n{a.seeds} test worlds of {rows[0]['scenario']}, budget {budget:.0f} s; "
          f"CPU: training {cpu_train / 60:.1f} min, evaluation {cpu_eval / 60:.1f} min\n")
    print("| policy | responders localised | all localised (median) | 90th pct | "
          "median error |")
    print("| --- | --- | --- | --- | --- |")
    for p in policies:
        mine = [r for r in rows if r["policy"] == p]
        loc = sum(r["localised_at_s"] is not None for r in mine)
        errs = [r["err_h_m"] for r in mine if r["err_h_m"] is not None]
        ts = sorted(times[p].values())
        p90 = ts[min(len(ts) - 1, math.ceil(0.9 * len(ts)) - 1)]
        cens = lambda v: (">= " if v >= budget else "") + f"{v:.0f} s"  # noqa: E731
        print(f"| {p} | {loc}/{len(mine)} | {cens(statistics.median(ts))} | {cens(p90)} | "
              f"{statistics.median(errs) if errs else float('nan'):.2f} m |")
    a_t, b_t = times[policies[0]], times[policies[1]]
    wins = sum(a_t[s] < b_t[s] for s in a_t)
    losses = sum(a_t[s] > b_t[s] for s in a_t)
    ties = len(a_t) - wins - losses
    print(f"\npaired on all-localised time, trained team vs team:adaptive: {wins} faster, "
          f"{losses} slower, {ties} ties; two-sided sign test p = "
          f"{sign_test_two_sided(wins, losses):.3g}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
