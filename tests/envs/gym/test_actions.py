"""Actions outside an env's action space are refused in one line, not flown as another.

A ``Discrete(n)`` action of -1 was flown as the last action (Python's negative index:
``return`` in ``osa/Search-v0``, ``done`` in v1), 2.5 and ``"1"`` as 2 and 1, and n
raised an ``IndexError`` ("tuple index out of range"); a NaN waypoint was flown (as a
request outside the area, charged the whole ``leave_penalty``). Each is now a
``ValueError`` naming the action, raised before anything moves, so the env goes on as
if it had not been asked.
"""

from __future__ import annotations

import dataclasses

import gymnasium
import numpy as np
import pytest

import envs  # noqa: F401  (registers the envs)
import sim
from envs.gym.batched import BatchedSearchEnv
from tests.envs.gym.test_batched import assert_same

DISCRETE = {"osa/Search-v0": 7, "osa/Search-v1": 17, "osa/Search-v3": 18}


def short(budget_s: float = 60.0):
    sc = sim.load_scenario("search-three-mixed")
    return dataclasses.replace(sc, search=dataclasses.replace(sc.search, budget_s=budget_s))


def made(env_id: str):
    env = gymnasium.make(env_id, scenario=short()).unwrapped
    env.reset(seed=1)
    return env


@pytest.mark.filterwarnings("ignore::DeprecationWarning")
@pytest.mark.parametrize("env_id", list(DISCRETE))
def test_a_discrete_action_outside_the_space_is_refused(env_id):
    n = DISCRETE[env_id]
    env = made(env_id)
    for bad in (-1, n, 2.5, "1", float("nan"), None, np.array([1, 2])):
        with pytest.raises(ValueError, match=rf"action .* not one of Discrete\({n}\)"):
            env.step(bad)
    # nothing moved: the next valid step is the first step of a fresh env
    ref = made(env_id)
    assert env.loop.t_s == 0.0
    assert_same(env.step(3), ref.step(3), "after the refusals")
    # the integer forms Gymnasium, SB3 and NumPy give are one action
    for same in (np.int64(4), np.array(4), np.array([4]), 4.0):
        a, b = made(env_id), made(env_id)
        assert_same(a.step(same), b.step(4), repr(same))


def test_a_waypoint_that_is_not_three_finite_numbers_is_refused():
    env = made("osa/Waypoint-v0")
    for bad in (np.array([np.nan, 0.0, 0.0], np.float32), [0.1, 0.2], [0.1, 0.2, 0.3, 0.4],
                np.array([0.0, -np.nan, 1.0])):
        with pytest.raises(ValueError, match=r"action .* not a waypoint"):
            env.step(bad)
    ref = made("osa/Waypoint-v0")
    assert env.loop.t_s == 0.0
    # beyond the bounds (infinite too) is clipped to them, as before
    assert_same(env.step(np.array([np.inf, -5.0, 0.5], np.float32)),
                ref.step(np.array([1.0, -1.0, 0.5], np.float32)), "clipped")


def test_the_batched_and_team_envs_refuse_a_nan_waypoint():
    vec = BatchedSearchEnv(2, env_class="envs.gym.waypoint:WaypointEnv", scenario=short())
    vec.reset(seed=0)
    acts = np.zeros((2, 3), np.float32)
    acts[1, 0] = np.nan
    with pytest.raises(ValueError, match="not a waypoint"):
        vec.step(acts)
    pytest.importorskip("pettingzoo")
    from envs.gym.multi import SearchParallelEnv

    team = SearchParallelEnv(short(), uavs=2)
    team.reset(seed=0)
    with pytest.raises(ValueError, match="not a waypoint"):
        team.step({"uav-1": np.zeros(3, np.float32),
                   "uav-2": np.array([0.0, np.nan, 0.0], np.float32)})


WEIGHTS = ("information_weight", "detection_bonus", "coverage_bonus", "time_cost_per_s",
           "leave_penalty")


@pytest.mark.parametrize("env_id", ["osa/Search-v0", "osa/Waypoint-v0"])
def test_a_reward_weight_that_is_not_a_number_at_least_0_is_refused_when_made(env_id):
    """Before: ``time_cost_per_s=nan`` was taken and every reward of the episode was NaN
    (``--reward`` and v1's ``localised_bonus`` refused it already); ``max_responders=2.5``
    was Gymnasium's TypeError about Box shapes."""
    for name in WEIGHTS:
        for bad in (float("nan"), float("inf"), -1.0, "1"):
            with pytest.raises(ValueError, match=rf"^{name} must be a number >= 0"):
                gymnasium.make(env_id, scenario=short(), **{name: bad})
    for name, bad in (("max_responders", 2.5), ("coverage_cells", 4.0),
                      ("max_responders", True)):
        with pytest.raises(ValueError, match=rf"^{name} must be an integer"):
            gymnasium.make(env_id, scenario=short(), **{name: bad})
    env = gymnasium.make(env_id, scenario=short(), information_weight=0, max_responders=np.int64(2))
    env.reset(seed=0)
    assert env.observation_space["responder_mask"].shape == (2,)
    assert np.isfinite(env.step(env.action_space.sample())[1])


def test_the_team_env_takes_the_information_weight_as_the_one_uav_envs():
    """docs/rl.md: the team env's other arguments are ``osa/Waypoint-v0``'s; before,
    ``information_weight`` was a TypeError (an unexpected keyword) and the team reward
    always counted the information at weight 1."""
    pytest.importorskip("pettingzoo")
    from envs.gym.multi import SearchParallelEnv

    def rollout(weight: float) -> np.ndarray:
        env = SearchParallelEnv(short(120), uavs=2, information_weight=weight)
        env.reset(seed=5)  # a world where a responder is heard within the 2 minutes
        rng = np.random.default_rng(5)
        out = []
        while env.agents:
            acts = {a: rng.uniform(-1, 1, 3).astype(np.float32) for a in env.agents}
            out.append(list(env.step(acts)[1].values()))
        return np.array(out)

    one, half, off = rollout(1.0), rollout(0.5), rollout(0.0)
    assert one.shape == half.shape == off.shape == (24, 2)
    information = one - off  # the same flight: only the information term differs
    assert information.sum() > 5.0  # heard and narrowed down within the 2 minutes
    np.testing.assert_allclose(half, off + 0.5 * information, atol=1e-9)
