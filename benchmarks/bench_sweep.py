"""Sweep of scenarios x seeds x policies: no traceback, no stall, no NaN, no excursion,
no difference between two identical runs.

Each search is flown in process (``envs.loop``, the loop of ``osa search``) with its
budget cut to ``--budget-s`` (0: the scenario's own), and checked for:

- an exception (the traceback's last frame is printed),
- a number in the report that is not finite,
- the true path leaving the area or entering a keep-out below its top (worst excursion,
  metres, ``ClosedLoop.excursion_m``; ``--tolerance-m`` allowed for the controller's
  wander),
- stalls the loop detected and the longest time still while a segment was pending,
- a hover: the vehicle within 3 m of one point for ``--hover-s`` or longer, whatever
  the policy asked (``envs.loop.longest_hover_s``; the env's ``return`` holds too),
- with ``--repeat``: a second identical run whose report or log differs.

The last line counts the searches and those with a problem, and names the farthest
excursion (tolerated or not) with its policy, scenario and seed.

    python benchmarks/bench_sweep.py --budget-s 240 --seeds 0,1,2147483647,4294967301
    python benchmarks/bench_sweep.py --scenarios suite/r5-h30-sa-u2 --policies team:adaptive
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import math
import signal
import tempfile
import time
import traceback
from pathlib import Path

from bench_stalls import longest_still_s

from envs.loop import ClosedLoop, fly
from envs.policies import load_policy
from sim.scenario import load_scenario

SCENARIOS = ("search-random-los", "search-random-los-rtk", "search-three-mixed",
             "search-five-mixed", "site-valley", "site-valley-rtk", "suite/r5-h30-sa-u1",
             "suite/r10-c50-rtk-u1", "suite/r1-c0-sa-u2")
POLICIES = ("adaptive", "lawnmower", "expanding-square", "random", "random:waypoint")


class WallTimeoutError(Exception):
    pass


def _alarm(signum, frame):
    raise WallTimeoutError("wall-clock limit")


def non_finite(obj, path: str = "") -> list[str]:
    """The dotted paths of the report's numbers that are not finite."""
    if isinstance(obj, dict):
        return [p for k, v in obj.items() for p in non_finite(v, f"{path}.{k}")]
    if isinstance(obj, list | tuple):
        return [p for i, v in enumerate(obj) for p in non_finite(v, f"{path}[{i}]")]
    if isinstance(obj, float) and not math.isfinite(obj):
        return [path]
    return []


def one_run(scenario, policy: str, seed: int, log: Path | None) -> dict:
    logs = None if log is None else [log.with_suffix(f".{i}.jsonl")
                                      for i in range(len(scenario.agents))]
    loop = ClosedLoop(scenario, seed, log_paths=logs)
    res = fly(loop, load_policy(policy, scenario))
    report = res.to_json()
    report.pop("log", None)
    report.pop("logs", None)  # the file names differ between the two runs
    out = {
        "ended": res.ended, "flight_time_s": res.flight_time_s,
        "nonfinite": non_finite(report), "excursion_m": loop.excursion_m(),
        "stalls": len(loop.stalls),
        "still_pending_s": max(loop.longest_still_s(i) for i in range(len(loop.nav_track))),
        # the UAVs the policy flies: one-UAV policies leave the others at take-off
        "still_s": max(longest_still_s(t) for t in (
            loop.nav_track if policy.startswith(("team:", "random")) else loop.nav_track[:1])),
        "refused": res.refused_plans,
        "localised": sum("localised_at_s" in r for r in res.responders),
        "responders": len(res.responders),
        "digest": hashlib.sha256(json.dumps(report, sort_keys=True).encode()).hexdigest(),
    }
    for p in logs or ():
        out["digest"] += hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def run_job(name: str, policy: str, seed: int, budget_s: float, repeat: bool,
            wall_s: float) -> dict:
    row: dict = {"scenario": name, "policy": policy, "seed": seed}
    t0 = time.process_time()
    signal.signal(signal.SIGALRM, _alarm)
    signal.alarm(int(wall_s))
    try:
        sc = load_scenario(name)
        if budget_s > 0:
            sc = dataclasses.replace(sc, search=dataclasses.replace(
                sc.search, budget_s=min(budget_s, sc.search.budget_s)))
        with tempfile.TemporaryDirectory() as tmp:
            row.update(one_run(sc, policy, seed, Path(tmp) / "a.jsonl" if repeat else None))
            if repeat:
                again = one_run(sc, policy, seed, Path(tmp) / "b.jsonl")
                row["same"] = again["digest"] == row["digest"]
    except Exception as exc:  # the sweep reports every failure
        tb = traceback.extract_tb(exc.__traceback__)[-1]
        row["error"] = f"{type(exc).__name__}: {exc} ({Path(tb.filename).name}:{tb.lineno})"
    finally:
        signal.alarm(0)
    row["cpu_s"] = time.process_time() - t0
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenarios", default=",".join(SCENARIOS))
    ap.add_argument("--policies", default=",".join(POLICIES))
    ap.add_argument("--seeds", default="0,1,2147483647,4294967301")
    ap.add_argument("--budget-s", type=float, default=240.0,
                    help="cut every budget to this (0: the scenario's own)")
    ap.add_argument("--repeat", action="store_true", help="fly each twice and compare")
    ap.add_argument("--tolerance-m", type=float, default=3.0)
    ap.add_argument("--hover-s", type=float, default=120.0)
    ap.add_argument("--wall-s", type=float, default=600.0, help="per search (a hang)")
    ap.add_argument("--json", default=None, help="write the rows here")
    a = ap.parse_args()
    rows = []
    jobs = []
    for s in a.scenarios.split(","):
        team = len(load_scenario(s).agents) > 1  # several UAVs: every one its own adaptive
        for p in [*a.policies.split(","), *(["team:adaptive"] if team else [])]:
            jobs += [(s, p, int(k)) for k in a.seeds.split(",")]
    for i, (s, p, k) in enumerate(jobs):
        r = run_job(s, p, k, a.budget_s, a.repeat, a.wall_s)
        rows.append(r)
        bad = []
        if "error" in r:
            bad.append(r["error"])
        else:
            if r["nonfinite"]:
                bad.append(f"non-finite {r['nonfinite'][:3]}")
            if r["excursion_m"] > a.tolerance_m:
                bad.append(f"excursion {r['excursion_m']:.1f} m")
            if r["stalls"]:
                bad.append(f"{r['stalls']} stalls (still {r['still_pending_s']:.0f} s)")
            if r.get("same") is False:
                bad.append("two runs differ")
            if r["still_s"] >= a.hover_s:
                bad.append(f"hover {r['still_s']:.0f} s")
        flag = "FAIL " + "; ".join(bad) if bad else "ok"
        print(f"[{i + 1}/{len(jobs)}] {s} {p} seed {k}: {r.get('ended', '-')} "
              f"{r.get('localised', 0)}/{r.get('responders', 0)} localised, "
              f"{r['cpu_s']:.1f} CPU s: {flag}", flush=True)
    n_bad = sum(1 for r in rows if "error" in r or r.get("nonfinite") or r.get("stalls")
                or r.get("excursion_m", 0) > a.tolerance_m or r.get("same") is False
                or r.get("still_s", 0) >= a.hover_s)
    far = max(rows, key=lambda r: r.get("excursion_m", 0.0))
    where = (f" ({far['policy']} on {far['scenario']}, seed {far['seed']})"
             if far.get("excursion_m", 0.0) > 0 else "")
    print(f"{len(rows)} searches, {n_bad} with a problem, farthest outside "
          f"{far.get('excursion_m', 0.0):.1f} m{where}, "
          f"{sum(r['cpu_s'] for r in rows) / 60:.1f} CPU min")
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
