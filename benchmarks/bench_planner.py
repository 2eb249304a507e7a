"""Planner speed: CasADi re-solves without rebuild, pattern generation and scoring.

Run: ``python benchmarks/bench_planner.py [--resolves N] [--prior-points K]``.

The optimal planner is built once (timed), solved cold once, then re-solved N times
with changed parameters in two scenarios:

- ``prior``: the prior mean drifts (2 m horizontal, 0.5 m vertical per step, seeded)
  and its covariance shrinks 5 % per step; same start pose;
- ``receding``: the same, and the start pose advances one waypoint along the previous
  plan with its velocity (receding horizon, shifted warm start).

Every re-solve is checked (``PlanResult.feasible``, no fallback). Target: median
re-solve <= 50 ms for N = 40 waypoints. Wall-clock medians are reported beside CPU
time: on a shared machine the wall clock includes other processes' time.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from planner.convert import trajectory_to_mission
from planner.optimal import OptimalConfig, OptimalPlanner
from planner.patterns import (
    Geofence,
    KeepOut,
    close_pass,
    concentric_circles,
    expanding_square,
    helix,
    lawnmower,
    orbit,
)
from planner.scoring import score_over_prior, score_trajectory

TARGET_MS = 50.0
COV = np.diag([100.0, 100.0, 4.0])
FENCE = Geofence.square((0.0, 0.0), 200.0)
TOWERS = [KeepOut(east_m=40.0, north_m=30.0, radius_m=15.0)]
START = np.array([-150.0, -100.0, 45.0])


def _resolves(planner: OptimalPlanner, n: int, receding: bool, seed: int) -> dict:
    rng = np.random.default_rng(seed)
    planner.reset_warm_start()
    r = planner.plan((0.0, 0.0, 0.0), COV, START, fence=FENCE, keep_outs=TOWERS)
    wall, cpu, iters, bad = [], [], [], 0
    mean = np.zeros(3)
    start, vel = START, np.zeros(3)
    for i in range(n):
        mean = mean + rng.normal(size=3) * (2.0, 2.0, 0.5)
        if receding:
            W = r.waypoints_enu_m
            start, vel = W[1], (W[2] - W[1]) / r.dt_s
        c0 = time.process_time()
        r = planner.plan(mean, COV * 0.95**i, start, vel, fence=FENCE, keep_outs=TOWERS)
        cpu.append(time.process_time() - c0)
        wall.append(r.solve_time_s)
        iters.append(r.iterations)
        bad += (not r.feasible) or (r.fallback is not None)
    return {
        "median_ms": 1e3 * statistics.median(wall),
        "p90_ms": 1e3 * float(np.percentile(wall, 90)),
        "min_ms": 1e3 * min(wall),
        "cpu_median_ms": 1e3 * statistics.median(cpu),
        "iters": statistics.median(iters),
        "infeasible_or_fallback": bad,
    }


def _timed(fn, reps: int) -> tuple[float, object]:
    out = None
    ts = []
    for _ in range(reps):
        t0 = time.perf_counter()
        out = fn()
        ts.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(ts), out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--resolves", type=int, default=20)
    ap.add_argument("--prior-points", type=int, default=OptimalConfig().n_prior_points)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    cfg = OptimalConfig(n_prior_points=args.prior_points)
    t0 = time.perf_counter()
    planner = OptimalPlanner(cfg)
    build_ms = 1e3 * (time.perf_counter() - t0)
    planner.reset_warm_start()
    cold = planner.plan((0.0, 0.0, 0.0), COV, START, fence=FENCE, keep_outs=TOWERS)
    print(f"optimal planner: N={cfg.n_waypoints} waypoints, K={cfg.n_prior_points} prior points,"
          f" {cfg.max_fence_edges} fence edges, {cfg.max_keep_outs} keep-outs")  # fmt: skip
    print(f"  build (once)          {build_ms:8.1f} ms")
    cold_ms = 1e3 * cold.solve_time_s
    print(f"  cold solve            {cold_ms:8.1f} ms, {cold.iterations} iterations,"
          f" feasible={cold.feasible}")  # fmt: skip
    ok = True
    for name, receding in (("prior", False), ("receding", True)):
        s = _resolves(planner, args.resolves, receding, args.seed)
        verdict = (
            "PASS" if s["median_ms"] <= TARGET_MS and not s["infeasible_or_fallback"] else "FAIL"
        )
        ok &= verdict == "PASS"
        print(f"  re-solve [{name:8s}]  median {s['median_ms']:6.1f} ms (p90 {s['p90_ms']:.1f},"
              f" min {s['min_ms']:.1f}, cpu {s['cpu_median_ms']:.1f}), {s['iters']:g} iterations,"
              f" {s['infeasible_or_fallback']}/{args.resolves} infeasible  [{verdict}"
              f" <= {TARGET_MS:g} ms]")  # fmt: skip

    print("patterns (median of 20): generate / score / score over 32 prior draws / to mission")
    rng = np.random.default_rng(args.seed)
    makers = {
        "lawnmower": lambda: lawnmower((0.0, 0.0), 200.0, spacing_m=60.0),
        "expanding-square": lambda: expanding_square((0.0, 0.0), 150.0, spacing_m=40.0),
        "helix": lambda: helix((0.0, 0.0), 50.0, alt_start_m=40.0, alt_end_m=70.0),
        "circles": lambda: concentric_circles((0.0, 0.0), [20.0, 40.0, 60.0]),
        "close-pass": lambda: close_pass((0.0, 0.0), 10.0),
        "orbit": lambda: orbit((0.0, 0.0), 50.0, turns=2.0),
    }
    for name, make in makers.items():
        gen_ms, traj = _timed(make, 20)
        score_ms, _ = _timed(lambda t=traj: score_trajectory(t, (0.0, 0.0, 0.0)), 20)
        prior_ms, _ = _timed(lambda t=traj: score_over_prior(t, (0, 0, 0), COV, rng, 32), 5)
        mission_ms, m = _timed(lambda t=traj: trajectory_to_mission(t), 20)
        print(f"  {name:17s} {len(traj.t_s):5d} samples  {gen_ms:6.2f} / {score_ms:6.2f} /"
              f" {prior_ms:7.2f} / {mission_ms:6.2f} ms  ({len(m.items)} items)")  # fmt: skip
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
