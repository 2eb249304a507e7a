"""Every state of the environments pickles, and the unpickled twin goes on identically.

Process pools, checkpoints and SubprocVecEnv restarts copy envs by pickling them. A
seeded rollout of each env is flown twice: once straight, once pickled and unpickled
after EVERY step (the unpickled copy takes the next step): observations, rewards,
terminations and infos are equal step for step, through the estimator's refinements,
the localisation and the episode's end.
"""

from __future__ import annotations

import pickle

import gymnasium as gym
import numpy as np
import pytest

import envs  # noqa: F401 - registers the environments


def _rollout(env_id: str, seed: int, steps: int, *, pickled: bool) -> list:
    env = gym.make(env_id).unwrapped
    obs, info = env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    out = [(obs, info)]
    for _ in range(steps):
        if pickled:
            env = pickle.loads(pickle.dumps(env))
        if env_id == "osa/Search-v0":
            a = int(rng.integers(env.action_space.n))
        else:
            a = rng.uniform(-1.0, 1.0, 3).astype(np.float32)
        obs, r, term, trunc, info = env.step(a)
        out.append((obs, r, term, trunc, info))
        if term or trunc:
            break
    return out


def _equal(a, b) -> bool:
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_equal(a[k], b[k]) for k in a)
    if isinstance(a, tuple | list):
        return len(a) == len(b) and all(_equal(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, np.ndarray):
        return a.dtype == b.dtype and np.array_equal(a, b)
    return a == b


@pytest.mark.parametrize(("env_id", "seed", "steps"), [("osa/Search-v0", 3, 240),
                                                         ("osa/Waypoint-v0", 5, 100)])
def test_every_state_pickles_and_goes_on_identically(env_id: str, seed: int,
                                                     steps: int) -> None:
    straight = _rollout(env_id, seed, steps, pickled=False)
    twin = _rollout(env_id, seed, steps, pickled=True)
    assert len(straight) == len(twin)
    for k, (a, b) in enumerate(zip(straight, twin, strict=True)):
        assert _equal(a, b), k
    last = straight[-1]
    if env_id == "osa/Search-v0":  # to the episode's end: localised (terminated)
        assert last[2] and last[4]["localised"] >= 1
    else:  # long enough for the refined estimator's refinements
        assert any(s[4]["eval"] and any("err_h_m" in v for v in s[4]["eval"].values())
                   for s in straight[1:])


def test_a_refined_track_pickles_after_a_refinement() -> None:
    """The issue's case: the refined estimator's filter run held a lambda
    ("Can't pickle local object 'RefinedTrack._make_run.<locals>.<lambda>'")."""
    env = gym.make("osa/Search-v0").unwrapped
    env.reset(seed=3)
    rng = np.random.default_rng(3)
    refined = False
    for _ in range(60):
        env.step(int(rng.integers(7)))
        for tr in env.loop.estimator.tracks.values():
            refined = refined or bool(getattr(tr, "scales", {}))
        copy = pickle.loads(pickle.dumps(env))
        assert copy.loop.t_s == env.loop.t_s
        if refined:
            break
    assert refined
