"""Batched worlds: decisions per CPU-second of one env against the batched env
(``gymnasium.make_vec(ID, num_envs=N, vectorization_mode="vector_entry_point")``) at
N = 1, 8, 64, with CartPole-v1 (one env) in the same run (issue 20, item 3).

Both fly the same work (:func:`work`): N worlds, ``--steps`` / N decisions each, the
same random actions, episodes reset as they end (same-step autoreset for the batched
env, so every world decides in every call); one env flies the worlds one after the
other. So the ratio is what batching gains, not a difference in the part of the
episodes flown (a decision costs more once responders are heard). Each figure is the
median of ``--repeats`` runs; the configurations take turns within each repeat and each
ratio is the median of the per-repeat ratios (this machine's speed drifts over minutes).
One BLAS thread; CPU time of this process (``time.process_time``). ``--profile N``
instead prints where the time of the batched env at N worlds goes (cProfile);
``--no-gc`` measures with Python's garbage collector off; ``--train STEPS`` measures
``osa train`` itself (PPO, in this process) with one env against ``--vec batched``.

    python benchmarks/bench_batch.py --steps 1280 --repeats 3
"""

from __future__ import annotations

import argparse
import gc
import os
import statistics
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import gymnasium  # (numpy loads here, after the BLAS setting)

import envs  # noqa: F401  (registers the envs)

IDS = ("osa/Waypoint-v0", "osa/Search-v0")
SIZES = (1, 8, 64)


def cartpole(steps: int, seed: int) -> float:
    """Steps per CPU-second of one CartPole-v1 (the yardstick of bench_envs.py)."""
    env = gymnasium.make("CartPole-v1")
    env.reset(seed=seed)
    env.action_space.seed(seed)
    c0 = time.process_time()
    for _ in range(steps):
        _, _, te, tr, _ = env.step(env.action_space.sample())
        if te or tr:
            env.reset()
    return steps / (time.process_time() - c0)


def work(env_id: str, steps: int, seed: int, n: int) -> tuple[float, float]:
    """(one env, batched env) decisions per CPU-second on the same work: worlds
    ``seed .. seed + n - 1``, ``steps // n`` decisions each with the same random actions
    (episodes that end are reset and go on). The one env flies the worlds one after the
    other; the batched env flies them in lockstep. Resets to the first world untimed."""
    vec = gymnasium.make_vec(env_id, num_envs=n, vectorization_mode="vector_entry_point",
                             autoreset_mode="same_step")
    vec.action_space.seed(seed)
    rounds = max(steps // n, 2)
    acts = [vec.action_space.sample() for _ in range(rounds)]
    env = gymnasium.make(env_id)
    cpu = 0.0
    for i in range(n):
        env.reset(seed=seed + i)
        c0 = time.process_time()
        for k in range(rounds):
            _, _, te, tr, _ = env.step(acts[k][i])
            if te or tr:
                env.reset()
        cpu += time.process_time() - c0
    env.close()
    vec.reset(seed=seed)
    c0 = time.process_time()
    for k in range(rounds):
        vec.step(acts[k])
    c1 = time.process_time()
    vec.close()
    return rounds * n / cpu, rounds * n / (c1 - c0)


PARTS = (  # (label, file suffix, function): cumulative time per part of a decision
    ("simulator: vehicle (100 ticks)", "sim/vehicle.py", "advance"),
    ("simulator: GNSS receiver", "sim/gnss.py", "measure_until"),
    ("simulator: FTM radio", "sim/ftm.py", "range_until"),
    ("simulator: phone records", "sim/stepper.py", "_queue"),
    ("estimator: records in, estimates", "envs/loop.py", "_ingest"),
    ("plan: guidance of a new segment", "envs/loop.py", "apply"),
    ("action mapping", "envs/gym/interface.py", "act"),
    ("observation, coverage, reward", "envs/gym/interface.py", "observe"),
    ("loop: observe (estimates to views)", "envs/loop.py", "observe"),
    ("loop: evaluation series (truth)", "envs/loop.py", "_sample_series"),
    ("env info (eval from the truth)", "envs/gym/base.py", "_info"),
)


def profile(env_id: str, n: int, steps: int) -> None:
    """Where the batched env's time goes (cProfile: it inflates call-heavy parts)."""
    import cProfile
    import pstats

    vec = gymnasium.make_vec(env_id, num_envs=n, vectorization_mode="vector_entry_point",
                             autoreset_mode="same_step")
    vec.reset(seed=0)
    vec.action_space.seed(0)
    for _ in range(3):
        vec.step(vec.action_space.sample())
    pr = cProfile.Profile()
    pr.enable()
    for _ in range(max(steps // n, 2)):
        vec.step(vec.action_space.sample())
    pr.disable()
    st = pstats.Stats(pr)
    total = next(v[3] for k, v in st.stats.items()
                 if k[0].endswith("envs/gym/batched.py") and k[2] == "step")
    print(f"\n{env_id}, {n} worlds: share of the batched step's time (cumulative)")
    for label, file, func in PARTS:
        ct = sum(v[3] for k, v in st.stats.items() if k[0].endswith(file) and k[2] == func)
        print(f"  {label:<38}{100 * ct / total:>6.1f} %")


def train_cost(env_id: str, steps: int, vec: str, n: int, out: str
               ) -> tuple[int, float, float]:
    """(decisions flown, CPU seconds of this process, wall seconds) of ``osa train``'s
    :func:`envs.rl.train` asked for ``steps`` decisions (PPO, no evaluation or
    checkpoints; PPO completes its rollout of 256 decisions per env, so with many envs
    it flies more than asked)."""
    import resource

    from envs.commands.train import PPO_DEFAULTS
    from envs.rl import TrainSettings, train

    def cpu() -> float:
        r = resource.getrusage(resource.RUSAGE_SELF)
        return r.ru_utime + r.ru_stime

    settings = TrainSettings(env_id=env_id, steps=steps, seed=0, n_envs=n, vec=vec,
                             eval_every=0, checkpoint_every=0, progress=False,
                             algo_kwargs=PPO_DEFAULTS)
    c0, w0 = cpu(), time.perf_counter()
    summary = train(settings, __import__("pathlib").Path(out))
    return summary.steps, cpu() - c0, time.perf_counter() - w0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=1280, help="decisions per measurement")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--envs", default=",".join(IDS))
    ap.add_argument("--sizes", default=",".join(map(str, SIZES)))
    ap.add_argument("--no-gc", action="store_true",
                    help="with Python's cyclic garbage collector off (what it costs)")
    ap.add_argument("--train", type=int, default=0, metavar="STEPS",
                    help="instead: CPU and wall seconds of osa train for STEPS decisions, "
                    "one env (--envs 1) against --vec batched (each of --sizes)")
    ap.add_argument("--profile", type=int, default=0, metavar="N",
                    help="profile the batched env at N worlds instead")
    a = ap.parse_args()
    ids = a.envs.split(",")
    if a.no_gc:
        gc.disable()
    if a.train:
        import tempfile

        with tempfile.TemporaryDirectory() as tmp:
            for env_id in ids:
                # --envs 1 is a DummyVecEnv in this process: its CPU time is all here
                # (subprocesses of the forkserver are not this process's children)
                runs = [("subproc", 1)] + [("batched", int(n)) for n in a.sizes.split(",")]
                for vec, n in runs:
                    k, c, w = train_cost(env_id, a.train, vec, n, f"{tmp}/{vec}{n}")
                    print(f"{env_id:<18}--vec {vec:<8} --envs {n:<3} {k:>6} steps: "
                          f"{c:7.1f} CPU-s ({k / c:5.0f} steps per CPU-s), "
                          f"{w:7.1f} wall-s", flush=True)
        return
    if a.profile:
        for env_id in ids:
            profile(env_id, a.profile, a.steps)
        return
    sizes = [int(s) for s in a.sizes.split(",")]
    cart: list[float] = []
    runs: dict[tuple[str, int], list[tuple[float, float]]] = {}
    for r in range(a.repeats):
        cart.append(cartpole(20 * a.steps, r))
        for env_id in ids:
            for n in sizes:
                runs.setdefault((env_id, n), []).append(work(env_id, a.steps, 1000 * r, n))
        print(f"repeat {r + 1}/{a.repeats} done", flush=True)
    load = os.getloadavg()[0]
    c = statistics.median(cart)
    print(f"\n{a.repeats} runs of about {a.steps} decisions per configuration (CartPole "
          f"20x more), medians; load average {load:.1f} at the end\n")
    print(f"CartPole-v1: {c:.0f} steps per CPU-second\n")
    print(f"{'env':<18}{'N':>4}{'one env /CPU-s':>16}{'batched /CPU-s':>16}{'batched/one':>13}"
          f"{'batched/CartPole':>18}")
    for (env_id, n), rs in runs.items():
        one = statistics.median(x[0] for x in rs)
        bat = statistics.median(x[1] for x in rs)
        ratio = statistics.median(x[1] / x[0] for x in rs)
        vs_cart = statistics.median(x[1] / q for x, q in zip(rs, cart, strict=True))
        print(f"{env_id:<18}{n:>4}{one:>16.0f}{bat:>16.0f}{ratio:>13.2f}{vs_cart:>18.5f}")


if __name__ == "__main__":
    main()
