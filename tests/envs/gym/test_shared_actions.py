"""Envs made with one ``PlanActions`` object (docs/rl.md: ``gymnasium.make("osa/Search-v1",
actions=PlanActions(...))``) each fly their own copy of it.

Given once to ``make_vec`` (every batched world gets the same keywords) or to two
``gymnasium.make`` calls, the one object (its target, sweeps, what is flown, the
sectors' coverage) was every env's: world 1's decisions moved world 0's sweeps, and
world 0's first observation of ``sectors`` was world 1's (0.0 where it was 0.33).
"""

from __future__ import annotations

import gymnasium
import numpy as np
from gymnasium.vector import SyncVectorEnv

import envs  # noqa: F401  (registers the envs)
from envs.gym.interface import EnvConfig
from envs.gym.plan_actions import PlanActions
from tests.envs.gym.test_actions import short
from tests.envs.gym.test_batched import assert_same


def test_envs_given_one_actions_object_fly_their_own_copies():
    cfg = EnvConfig(max_responders=5, coverage_cells=6)
    given = PlanActions(cfg, sectors=2)
    vec = gymnasium.make_vec("osa/Search-v1", num_envs=2,
                             vectorization_mode="vector_entry_point", scenario=short(120),
                             actions=given)
    ref = SyncVectorEnv([lambda: gymnasium.make("osa/Search-v1", scenario=short(120),
                                                actions=PlanActions(cfg, sectors=2))] * 2)
    a, b = (gymnasium.make("osa/Search-v1", scenario=short(120), actions=given).unwrapped
            for _ in range(2))
    owners = [w.pilot.actions for w in vec.unwrapped.worlds] + [a.pilot.actions,
                                                                 b.pilot.actions]
    assert len({id(x) for x in owners}) == 4 and given not in owners
    assert all(x.sectors == 2 and x.space.n == 12 for x in owners)
    assert_same(vec.reset(seed=3), ref.reset(seed=3), "reset")
    for k in range(12):
        act = np.array([k % 4, (k + 2) % 4])
        assert_same(vec.step(act), ref.step(act), f"step {k}")


def test_actions_for_other_responder_slots_are_refused_when_made():
    """``PlanActions(EnvConfig())`` (3 responder slots) given to v1 (5 by default): the
    env observed ``set_aside`` for 3 slots beside ``responders`` of 5, silently."""
    import pytest

    with pytest.raises(ValueError, match=r"^actions observe 3 responder slots, the env 5 "
                                         r"\(max_responders\)"):
        gymnasium.make("osa/Search-v1", scenario=short(), actions=PlanActions(EnvConfig()))
    env = gymnasium.make("osa/Search-v1", scenario=short(), max_responders=3,
                         actions=PlanActions(EnvConfig()))
    obs, _ = env.reset(seed=0)
    assert obs["set_aside"].shape == obs["responder_mask"].shape == (3,)
