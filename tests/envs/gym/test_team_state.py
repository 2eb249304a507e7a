"""The team env's ``state()`` (for centralised critics) has its ``state_space``.

``SearchParallelEnv.state()`` was there without ``state_space``: PettingZoo's
``state_test`` and a centralised critic sizing its input from it met an
AttributeError. ``state_space`` is every agent's observation vector in turn
(``agent``, ``responders``, ``responder_mask``, ``coverage``, ``others``), its bounds.
"""

from __future__ import annotations

import numpy as np
import pytest

from tests.envs.gym.test_actions import short

pytest.importorskip("pettingzoo")


def test_the_team_state_has_its_space_and_passes_pettingzoos_state_test():
    from pettingzoo.test import state_test
    from pettingzoo.utils.conversions import parallel_to_aec

    from envs.gym.multi import SearchParallelEnv

    def make():
        return SearchParallelEnv(short(60), uavs=2, ground=1)

    state_test(parallel_to_aec(make()), make(), num_cycles=5)
    env = make()
    with pytest.raises(RuntimeError, match="call reset"):  # before: AttributeError '_obs'
        env.state()
    env.reset(seed=5)
    rng = np.random.default_rng(5)
    # 3 agents x (10 + 3 x 17 + 3 + 64 + 2 x 4)
    assert env.state_space.shape == (3 * 136,) and env.state_space.dtype == np.float32
    while env.agents:
        obs, *_ = env.step({a: rng.uniform(-1, 1, 3).astype(np.float32) for a in env.agents})
        s = env.state()
        assert env.state_space.contains(s)
        # the state is the agents' observations, in the order of possible_agents
        for i, a in enumerate(env.possible_agents if obs else ()):
            np.testing.assert_array_equal(
                s[i * 136:(i + 1) * 136],
                np.concatenate([obs[a][k] for k in ("agent", "responders", "responder_mask",
                                                    "coverage", "others")]))


def test_an_action_for_an_agent_the_team_does_not_have_is_refused():
    """``{"uav1": ...}`` for ``uav-1`` (a typo): before, ignored, every UAV flew on what it
    flew and the step was spent; now a ValueError naming the agents, nothing flown."""
    from envs.gym.multi import SearchParallelEnv

    env = SearchParallelEnv(short(60), uavs=2)
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"^no agent 'uav1' in this team \(uav-1, uav-2\)"):
        env.step({"uav1": np.zeros(3, np.float32), "uav-2": np.zeros(3, np.float32)})
    assert env.loop.t_s == 0.0
    _, rew, *_ = env.step({"uav-1": np.zeros(3, np.float32)})  # a subset is fine
    assert set(rew) == {"uav-1", "uav-2"} and env.loop.t_s == 5.0
