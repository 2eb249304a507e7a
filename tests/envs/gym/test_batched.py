"""Batched worlds (``make_vec(..., vectorization_mode="vector_entry_point")``) equal N
single envs seed for seed, bit for bit: observations, rewards, terminations,
truncations and infos, across episode ends in both autoreset modes, through pickling,
partial resets and ``max_episode_steps``."""

from __future__ import annotations

import pickle

import gymnasium
import numpy as np
import pytest
from gymnasium.vector import SyncVectorEnv

import envs  # noqa: F401  (registers the envs)
from envs.gym.batched import BatchedSearchEnv, parse_autoreset
from tests.envs.gym.test_envs import short

IDS = ("osa/Search-v0", "osa/Waypoint-v0")
N = 3
STEPS = 30  # 60 s budgets of 5 s decisions: every world ends twice (autoreset)


def kwargs() -> dict:
    return {"scenario": short(budget_s=60.0)}


def batched(env_id: str, mode: str = "next_step", **kw) -> BatchedSearchEnv:
    vec = gymnasium.make_vec(env_id, num_envs=N, vectorization_mode="vector_entry_point",
                             autoreset_mode=mode, **kwargs(), **kw)
    assert isinstance(vec, BatchedSearchEnv)
    return vec


def singles(env_id: str, mode: str = "next_step", **kw) -> SyncVectorEnv:
    """N single ``gymnasium.make`` envs under Gymnasium's reference vectorisation."""
    return SyncVectorEnv([lambda: gymnasium.make(env_id, **kwargs(), **kw)] * N,
                         autoreset_mode=parse_autoreset(mode))


def assert_same(a, b, where: str = "") -> None:
    """Equal bit for bit (NaN equal to NaN), recursing into dicts and object arrays."""
    if isinstance(a, dict):
        assert isinstance(b, dict) and a.keys() == b.keys(), where
        for k in a:
            assert_same(a[k], b[k], f"{where}.{k}")
    elif isinstance(a, tuple | list):
        assert type(a) is type(b) and len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            assert_same(x, y, f"{where}[{i}]")
    elif isinstance(a, np.ndarray) and a.dtype == object:
        assert isinstance(b, np.ndarray) and a.shape == b.shape, where
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            assert_same(x, y, f"{where}[{i}]")
    elif isinstance(a, np.ndarray):
        assert isinstance(b, np.ndarray) and a.dtype == b.dtype, where
        np.testing.assert_array_equal(a, b, err_msg=where, strict=True)
    elif isinstance(a, float) and a != a:
        assert isinstance(b, float) and b != b, where
    else:
        assert type(a) is type(b) and a == b, (where, a, b)


def actions(vec, k: int):
    vec.action_space.seed(k)
    return vec.action_space.sample()


@pytest.mark.parametrize("mode", ["next_step", "same_step"])
@pytest.mark.parametrize("env_id", IDS)
def test_batched_equals_single_envs(env_id, mode):
    vec, ref = batched(env_id, mode), singles(env_id, mode)
    assert vec.metadata["autoreset_mode"] == parse_autoreset(mode)
    assert vec.single_observation_space == ref.single_observation_space
    assert vec.action_space == ref.action_space
    a, b = vec.reset(seed=11), ref.reset(seed=11)
    assert_same(a, b, "reset")
    ends = np.zeros(N, dtype=int)
    for k in range(STEPS):
        act = actions(vec, k)
        got, want = vec.step(act), ref.step(act)
        assert_same(got, want, f"step {k}")
        ends += got[2] | got[3]
        assert got[0]["agent"].shape == (N, 10) and got[0]["agent"].dtype == np.float32
    assert (ends >= 2).all()  # every world ended twice: both autoresets exercised
    if mode == "same_step":
        assert "final_obs" in got[4] or ends.sum() > 0


def test_batched_world_is_the_single_env_of_its_seed():
    """World i of ``reset(seed=s)`` is ``gymnasium.make(ID)`` reset with ``s + i``."""
    env_id = "osa/Waypoint-v0"
    vec = batched(env_id)
    obs, _ = vec.reset(seed=40)
    one = gymnasium.make(env_id, **kwargs())
    o1, i1 = one.reset(seed=42)
    for k in ("agent", "responders", "coverage"):
        np.testing.assert_array_equal(obs[k][2], o1[k])
    for k in range(8):
        act = actions(vec, k)
        obs, r, te, tr, info = vec.step(act)
        o1, r1, te1, tr1, i1 = one.step(act[2])
        assert (r[2], te[2], tr[2]) == (r1, te1, tr1)
        assert info["flight_time_s"][2] == i1["flight_time_s"]
        for key in o1:
            np.testing.assert_array_equal(obs[key][2], o1[key])


@pytest.mark.parametrize("env_id", IDS)
def test_batched_pickles_and_goes_on_identically(env_id):
    vec = batched(env_id)
    vec.reset(seed=3)
    for k in range(14):  # past the first episode ends: an autoreset is pending
        vec.step(actions(vec, k))
    twin = pickle.loads(pickle.dumps(vec))
    for k in range(14, 22):
        act = actions(vec, k)
        assert_same(vec.step(act), twin.step(act), f"step {k}")


def test_partial_reset_and_time_limit_as_single_envs():
    env_id = "osa/Search-v0"
    vec, ref = batched(env_id, max_episode_steps=4), singles(env_id, max_episode_steps=4)
    assert_same(vec.reset(seed=5), ref.reset(seed=5))
    for k in range(6):
        act = actions(vec, k)
        got, want = vec.step(act), ref.step(act)
        assert_same(got, want, f"step {k}")
    assert got[3].any() or want[3].any() or k == 5
    mask = np.array([True, False, True])
    opts = {"world_seed": 1234}
    assert_same(vec.reset(seed=[7, None, 9], options={**opts, "reset_mask": mask}),
                ref.reset(seed=[7, None, 9], options={**opts, "reset_mask": mask.copy()}))
    for k in range(3):
        act = actions(vec, k)
        assert_same(vec.step(act), ref.step(act), f"after reset {k}")


def test_make_vec_prefers_the_batched_worlds():
    """Gymnasium uses a registered ``vector_entry_point`` when no mode is given."""
    vec = gymnasium.make_vec("osa/Waypoint-v0", num_envs=2, scenario=short(budget_s=60.0))
    assert isinstance(vec, BatchedSearchEnv) and vec.num_envs == 2
    assert vec.spec is not None and vec.spec.id == "osa/Waypoint-v0"
    sync = gymnasium.make_vec("osa/Waypoint-v0", num_envs=2, vectorization_mode="sync")
    assert isinstance(sync, SyncVectorEnv)


def test_bad_arguments_are_one_line_errors():
    with pytest.raises(ValueError, match="num_envs"):
        gymnasium.make_vec("osa/Search-v0", num_envs=0, vectorization_mode="vector_entry_point")
    with pytest.raises(ValueError):
        batched("osa/Search-v0", mode="bogus")
    with pytest.raises(ValueError, match="not a search env"):
        BatchedSearchEnv(2, env_class="gymnasium.envs.classic_control:CartPoleEnv")
    vec = batched("osa/Search-v0")
    with pytest.raises(RuntimeError, match="reset"):
        vec.step(np.zeros(N, dtype=np.int64))
