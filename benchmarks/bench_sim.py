"""Simulator speed: the 23-minute paper-ap1f flight, simulated and written as a log.

Run ``python benchmarks/bench_sim.py [--runs N] [--scenario NAME] [--gz]``. Prints the
median wall time over the runs, the real-time factor, and the split between building
the flight (vehicle, GNSS, FTM arrays, geodesy) and writing the log. The target is a
median under 0.55 s (>= 2500x real time) for paper-ap1f with 10 Hz GNSS.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

TARGET_S = 0.55


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=7)
    ap.add_argument("--scenario", default="paper-ap1f")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--gz", action="store_true", help="write .jsonl.gz instead of .jsonl")
    args = ap.parse_args(argv)

    from sim import load_scenario, run_scenario, write_log

    scenario = load_scenario(args.scenario)
    suffix = ".jsonl.gz" if args.gz else ".jsonl"
    build_s: list[float] = []
    write_s: list[float] = []
    total_s: list[float] = []
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / f"bench{suffix}"
        run_scenario(scenario, args.seed)  # warm-up: imports, caches
        for i in range(args.runs):
            t0 = time.perf_counter()
            result = run_scenario(scenario, args.seed + i)
            t1 = time.perf_counter()
            write_log(result, path)
            t2 = time.perf_counter()
            build_s.append(t1 - t0)
            write_s.append(t2 - t1)
            total_s.append(t2 - t0)
        size = path.stat().st_size
    med = statistics.median(total_s)
    flight_s = result.duration_s
    print(
        f"scenario {args.scenario}: {flight_s / 60:.1f} min flight, {result.n_gnss} gnss, "
        f"{result.n_rtt} rtt lines ({sum(result.ok_counts().values())} ok), "
        f"{size / 1e6:.2f} MB {suffix}"
    )
    print(
        f"median over {args.runs} runs: {med:.3f} s "
        f"(build {statistics.median(build_s):.3f} s, write {statistics.median(write_s):.3f} s; "
        f"min {min(total_s):.3f} s, max {max(total_s):.3f} s)"
    )
    print(f"real-time factor: {flight_s / med:.0f}x")
    ok = med < TARGET_S
    print(f"target < {TARGET_S} s: {'met' if ok else 'NOT met'}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
