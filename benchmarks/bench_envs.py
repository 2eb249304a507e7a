"""Environment throughput: decisions per second of the search envs against CartPole-v1,
measured in the same run (issue 10, item 3: >= 1000 decisions/s per core for
``osa/Waypoint-v0`` with 5-second decisions).

For each env: one env stepped in this process (decisions per CPU-second of this process:
"per core"; and per wall second), and vectorised with ``gymnasium.make_vec`` (``sync``,
4 copies in this process; ``async``, one worker process per core, per wall second).
Random actions; episodes reset as they end (the reset is counted in the time). Each
figure is the median of ``--repeats`` runs of ``--steps`` decisions; the envs take turns
within each repeat, and the ratio to CartPole is the median of the per-repeat ratios
(this machine's speed drifts by 10-20 % over minutes). One BLAS thread.

    python benchmarks/bench_envs.py --steps 2000 --repeats 5
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

# one BLAS thread: per-core figures (a BLAS pool spinning on another core would count in
# this process's CPU time); an env per core is how vectorised training runs them
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import gymnasium  # (numpy loads here, after the BLAS setting)

import envs  # noqa: F401  (registers the envs)

ENVS = ("CartPole-v1", "osa/Waypoint-v0", "osa/Search-v0")


def single(env_id: str, steps: int, seed: int) -> tuple[float, float]:
    """(decisions per CPU second, per wall second) of one env in this process."""
    env = gymnasium.make(env_id)
    env.reset(seed=seed)
    env.action_space.seed(seed)
    c0, w0 = time.process_time(), time.perf_counter()
    for _ in range(steps):
        _, _, te, tr, _ = env.step(env.action_space.sample())
        if te or tr:
            env.reset()
    c1, w1 = time.process_time(), time.perf_counter()
    env.close()
    return steps / (c1 - c0), steps / (w1 - w0)


def vector(env_id: str, steps: int, seed: int, mode: str, n: int) -> float:
    """Decisions (summed over the copies) per wall second of a vector env."""
    vec = gymnasium.make_vec(env_id, num_envs=n, vectorization_mode=mode)
    vec.reset(seed=[seed + i for i in range(n)])
    vec.action_space.seed(seed)
    rounds = max(steps // n, 1)
    w0 = time.perf_counter()
    for _ in range(rounds):
        vec.step(vec.action_space.sample())  # autoreset: ended copies reset themselves
    w1 = time.perf_counter()
    vec.close()
    return rounds * n / (w1 - w0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=2000)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--envs", default=",".join(ENVS))
    a = ap.parse_args()
    cores = os.cpu_count() or 1
    ids = a.envs.split(",")
    runs: dict[str, list[tuple[float, float, float, float]]] = {e: [] for e in ids}
    for r in range(a.repeats):  # the envs take turns, so each repeat sees one machine state
        for env_id in ids:
            steps = a.steps * (20 if env_id == "CartPole-v1" else 1)
            c, w = single(env_id, steps, r)
            runs[env_id].append((c, w, vector(env_id, steps, r, "sync", 4),
                                 vector(env_id, steps, r, "async", cores)))
        print(f"repeat {r + 1}/{a.repeats} done", flush=True)
    load = os.getloadavg()[0]
    print(f"\n{a.repeats} runs of {a.steps} decisions (CartPole 20x more), medians; "
          f"{cores} cores, load average {load:.1f} at the end\n")
    print(f"{'env':<18}{'per CPU-s':>12}{'per wall-s':>12}{'sync x4':>12}"
          f"{'async x' + str(cores):>12}{'vs CartPole':>13}")
    base = runs.get("CartPole-v1")
    for env_id, rs in runs.items():
        c, w, s, y = (statistics.median(x) for x in zip(*rs, strict=True))
        # the ratio per repeat (same machine state), then its median
        ratio = (f"{statistics.median(q[0] / b[0] for q, b in zip(rs, base, strict=True)):.5f}"
                 if base else "-")
        print(f"{env_id:<18}{c:>12.0f}{w:>12.0f}{s:>12.0f}{y:>12.0f}{ratio:>13}")
        if env_id == "osa/Waypoint-v0":
            last = (f"\nosa/Waypoint-v0 (5 s decisions): {c:.0f} decisions per CPU-second "
                    f"(target 1000): {1e3 / c:.2f} ms of CPU per decision")
    if "osa/Waypoint-v0" in runs:
        print(last)


if __name__ == "__main__":
    main()
