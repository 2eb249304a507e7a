"""Finely drawn search areas: the time to sweep and join a lawnmower over a boundary of
N vertices with metre-scale wiggles (a circle of 555 m radius, 0.2 % radial noise, as a
GIS export or a walked boundary has), with the route nodes taken from the simplified
outline (planner/area.py, beyond ``SIMPLIFY_ABOVE`` vertices) and, for comparison,
from every vertex (the behaviour before; quadratic in N and more, so only for small N).

    python benchmarks/bench_area_detail.py --vertices 150 200 1000 5000 --every-up-to 200

Prints per N: route nodes, seconds (median of ``--repeats``), path length, and the
closest the joined path comes to the boundary (m; the margin is 10 m, routes may use
half of it as slack).
"""

from __future__ import annotations

import argparse
import itertools
import statistics
import time

import numpy as np

import planner.area as area_mod
from planner.area import SearchArea


def wiggly(n: int, seed: int = 0) -> tuple[tuple[float, float], ...]:
    rng = np.random.default_rng(seed)
    r = 555.0 * (1 + 0.002 * rng.standard_normal(n))
    t = 2 * np.pi * np.arange(n) / n
    return tuple(map(tuple, np.column_stack([r * np.cos(t), r * np.sin(t)])))


def run(n: int, simplify: bool, repeats: int) -> dict:
    saved = area_mod.SIMPLIFY_ABOVE
    area_mod.SIMPLIFY_ABOVE = 100 if simplify else 10**9
    try:
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            a = SearchArea(wiggly(n), 10.0)
            wps = a.sweep(80.0, 0.0)
            path = np.array(a.join(wps))
            times.append(time.perf_counter() - t0)
        nodes = len(a._corners(10.0))
    finally:
        area_mod.SIMPLIFY_ABOVE = saved
    pts = [path[:1]]
    for p, q in itertools.pairwise(path):
        k = max(1, int(np.linalg.norm(q - p) / 2.0))
        pts.append(p + (np.arange(1, k + 1) / k)[:, None] * (q - p))
    clear = float(-np.max(a.signed_distance_m(np.vstack(pts))))
    return {"n": n, "nodes": nodes, "s": statistics.median(times),
            "length_m": float(np.sum(np.linalg.norm(np.diff(path, axis=0), axis=1))),
            "clearance_m": clear}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--vertices", type=int, nargs="+", default=[150, 200, 1000])
    ap.add_argument("--every-up-to", type=int, default=200,
                    help="also time every-vertex nodes for N up to this")
    ap.add_argument("--repeats", type=int, default=1)
    args = ap.parse_args()
    print("| vertices | nodes | route nodes from | s | path m | closest to the edge m |")
    print("| --- | --- | --- | --- | --- | --- |")
    for n in args.vertices:
        for simplify in (True, False):
            if not simplify and n > args.every_up_to:
                continue
            r = run(n, simplify, args.repeats)
            how = "simplified outline" if simplify else "every vertex"
            print(f"| {n} | {r['nodes']} | {how} | {r['s']:.1f} | {r['length_m']:.0f} | "
                  f"{r['clearance_m']:.2f} |", flush=True)


if __name__ == "__main__":
    main()
