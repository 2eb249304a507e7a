"""Idle hovers: a sweep of seeded searches, every policy, looking for a vehicle that
stands still while the policy keeps flying (issue: the hover stall).

For each policy and seed of the test split: the longest time the autopilot's position
stayed within 3 m (from the track of positions at each decision: a hover the policy
asked for, e.g. the env's ``return``, counts too), the longest such time while a
segment was pending (the loop's own measure: ``ClosedLoop.longest_still_s``), the
stalls the loop detected, and how the search ended. Policies: ``lawnmower``,
``expanding-square``, ``adaptive`` (``osa search``), and in ``osa/Search-v0``
uniformly random manoeuvres and always ``helix``, in ``osa/Waypoint-v0`` uniformly
random waypoints.

    python benchmarks/bench_stalls.py --seeds 30
"""

from __future__ import annotations

import argparse

import sim
from envs.loop import HOVER_RADIUS_M, ClosedLoop, fly, longest_hover_s
from envs.policies import load_policy
from envs.seeds import split_seeds

STILL_M = HOVER_RADIUS_M
HOVER_S = 60.0  # "stands still": this long within STILL_M
longest_still_s = longest_hover_s  # the longest time a track stayed within STILL_M


def search_run(scenario, policy: str, seed: int) -> tuple[float, float, int, str]:
    loop = ClosedLoop(scenario, seed)
    res = fly(loop, load_policy(policy))
    return (longest_still_s(res.nav_track[0]), loop.longest_still_s(0), len(loop.stalls),
            res.ended)


def env_run(scenario_name: str, env_id: str, how: str, seed: int
            ) -> tuple[float, float, int, str]:
    import gymnasium as gym

    import envs  # noqa: F401 - registers the environments

    env = gym.make(env_id, scenario=scenario_name).unwrapped
    env.reset(seed=0, options={"world_seed": seed})
    env.action_space.seed(seed)
    while True:
        a = 3 if how == "helix" else env.action_space.sample()
        _, _, term, trunc, _ = env.step(a)
        if term or trunc:
            break
    loop = env.loop
    ended = "localised" if term else "budget"
    return (longest_still_s(loop.nav_track[0]), loop.longest_still_s(0), len(loop.stalls),
            ended)


def main() -> None:
    from tqdm import tqdm

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=30)
    ap.add_argument("--scenarios", default="search-random-los,search-three-mixed")
    a = ap.parse_args()
    seeds = split_seeds("test", a.seeds)
    policies = [("lawnmower", None), ("expanding-square", None), ("adaptive", None),
                ("random manoeuvres", ("osa/Search-v0", "random")),
                ("always helix", ("osa/Search-v0", "helix")),
                ("random waypoints", ("osa/Waypoint-v0", "random"))]
    rows = []
    jobs = [(s, p, k) for s in a.scenarios.split(",") for p in policies for k in seeds]
    for name, (policy, env), seed in tqdm(jobs, desc="bench_stalls", unit="search"):
        if env is None:
            r = search_run(sim.load_scenario(name), policy, seed)
        else:
            r = env_run(name, env[0], env[1], seed)
        rows.append((name, policy, seed, *r))
    print(f"\n{len(seeds)} seeds of the test split from {seeds[0]}; still: within {STILL_M:g} m")
    print(f"{'scenario':<20}{'policy':<19}{'runs':>5}{f'still>{HOVER_S:.0f}s':>11}"
          f"{'max still':>11}{'max pending':>13}{'stalls':>8}{'localised':>11}")
    for name in a.scenarios.split(","):
        for policy, _ in policies:
            r = [x for x in rows if x[0] == name and x[1] == policy]
            hover = [x for x in r if x[3] >= HOVER_S]
            print(f"{name:<20}{policy:<19}{len(r):>5}{len(hover):>11}"
                  f"{max(x[3] for x in r):>9.0f} s{max(x[4] for x in r):>11.0f} s"
                  f"{sum(x[5] for x in r):>8}{sum(x[6] == 'localised' for x in r):>11}")
            for x in hover:
                print(f"    seed {x[2]}: still {x[3]:.0f} s, pending {x[4]:.0f} s, "
                      f"{x[5]} stalls, {x[6]}")


if __name__ == "__main__":
    main()
