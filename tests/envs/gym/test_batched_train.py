"""Batched worlds under Stable-Baselines3: the ``VecEnv`` adapter presents the worlds as
SB3's ``DummyVecEnv`` presents N single envs (observations, dones, terminal
observations, infos), and ``osa train --vec batched`` trains through it (with
``VecNormalize``) and writes a model that ``ppo:PATH`` loads and flies."""

from __future__ import annotations

import json

import gymnasium
import numpy as np
import pytest

pytest.importorskip("stable_baselines3")

from stable_baselines3.common.vec_env import DummyVecEnv

from envs.gym.sb3 import SB3VecEnv
from envs.rl import make_env
from tests.envs.gym.test_envs import short

N = 3
SCENARIO = ('extends = "search-random-los"\nname = "los-90s"\n'
            '[search]\nbudget_s = 90.0\n')


def test_sb3_adapter_equals_dummy_vec_env():
    kw = {"scenario": short(budget_s=60.0)}
    vec = gymnasium.make_vec("osa/Waypoint-v0", num_envs=N,
                             vectorization_mode="vector_entry_point",
                             autoreset_mode="same_step", **kw)
    ours = SB3VecEnv(vec)
    ref = DummyVecEnv([lambda: make_env("osa/Waypoint-v0", kw)] * N)
    ours.seed(21)
    ref.seed(21)
    a, b = ours.reset(), ref.reset()
    for k in a:
        np.testing.assert_array_equal(a[k], b[k])
    assert [i["world_seed"] for i in ours.reset_infos] == [i["world_seed"] for i in ref.reset_infos]
    rng = np.random.default_rng(0)
    dones = 0
    for step in range(30):
        act = rng.uniform(-1, 1, (N, 3)).astype(np.float32)
        ours.step_async(act)
        ref.step_async(act)
        (oa, ra, da, ia), (ob, rb, db, ib) = ours.step_wait(), ref.step_wait()
        for k in oa:
            np.testing.assert_array_equal(oa[k], ob[k], err_msg=f"step {step} {k}")
        np.testing.assert_array_equal(ra.astype(np.float32), rb)  # DummyVecEnv: float32
        np.testing.assert_array_equal(da, db)
        for x, y in zip(ia, ib, strict=True):
            assert x.keys() == y.keys()
            for key in ("flight_time_s", "world_seed", "localised", "TimeLimit.truncated"):
                assert x[key] == y[key], (step, key)
            assert x["reward_terms"] == pytest.approx(y["reward_terms"], rel=0, abs=0)
            if "terminal_observation" in y:
                for k in y["terminal_observation"]:
                    np.testing.assert_array_equal(x["terminal_observation"][k],
                                                  y["terminal_observation"][k])
        dones += int(da.sum())
    assert dones >= N  # every world ended at least once
    assert ours.get_attr("world_seed") == ref.get_attr("world_seed")
    assert ours.env_method("render") == [None] * N
    assert ours.env_is_wrapped(gymnasium.Wrapper) == [False] * N
    ours.close()
    ref.close()


def test_the_adapter_wants_same_step_autoreset():
    vec = gymnasium.make_vec("osa/Search-v0", num_envs=2, vectorization_mode="vector_entry_point")
    with pytest.raises(ValueError, match="same_step"):
        SB3VecEnv(vec)


def test_osa_train_with_batched_worlds_writes_a_ppo_policy(tmp_path):
    import sim
    from envs.cli import main
    from envs.gym.trained import TrainedPolicy
    from envs.loop import run_search
    from envs.policies import load_policy

    toml = tmp_path / "los-90s.toml"
    toml.write_text(SCENARIO)
    out = tmp_path / "model"
    status = main(["train", "--env", "osa/Search-v0", "--scenario", str(toml),
                   "--steps", "256", "--envs", "2", "--vec", "batched", "--eval-every", "256",
                   "--eval-worlds", "1", "--checkpoint-every", "0", "--no-progress",
                   "-o", str(out)])
    assert status == 0
    meta = json.loads((out / "osa-model.json").read_text())
    assert meta["steps"] >= 256 and meta["kind"] == "search"
    policy = load_policy(f"ppo:{out}")
    assert isinstance(policy, TrainedPolicy)
    assert policy.model.num_timesteps >= 256 and policy.model.n_envs == 2
    assert policy.stats.obs_rms["agent"].count > 256  # VecNormalize saw the worlds' steps
    res = run_search(sim.load_scenario(toml), policy, 5)
    assert res.flight_time_s > 0 and res.ended in ("localised", "budget")
