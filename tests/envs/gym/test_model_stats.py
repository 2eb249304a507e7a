"""A model folder whose ``vecnormalize.pkl`` normalises another observation is refused
when it is loaded, in one line.

The statistics of another env or another version of its observation (here: the
coverage map 6 x 6 instead of the 8 x 8 the network takes), copied into a model
folder: ``TrainedPolicy.load`` took it, and ``osa search --policy ppo:MODEL`` ended in
"internal error: ValueError: operands could not be broadcast together with shapes
(36,) (64,)" (exit 70) at the first decision.
"""

from __future__ import annotations

import pickle
import re
import shutil

import gymnasium
import pytest

pytest.importorskip("stable_baselines3")

import envs  # noqa: F401  (registers the envs)
from envs.gym.trained import TrainedPolicy
from envs.rl import TrainSettings, train


def test_statistics_of_another_observation_are_refused_when_loaded(tmp_path, capsys):
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    from tests.cli import one_line, status_of

    settings = TrainSettings(env_id="osa/Search-v0", steps=64, seed=0, n_envs=1,
                             eval_every=0, checkpoint_every=0, progress=False,
                             algo_kwargs=dict(n_steps=64, batch_size=32, n_epochs=1))
    train(settings, tmp_path / "good")
    TrainedPolicy.load(tmp_path / "good")  # its own statistics load
    bad = tmp_path / "bad"
    shutil.copytree(tmp_path / "good", bad)
    other = VecNormalize(DummyVecEnv([lambda: gymnasium.make("osa/Search-v0",
                                                             coverage_cells=6)]))
    other.save(str(bad / "vecnormalize.pkl"))
    with open(bad / "vecnormalize.pkl", "rb") as f:
        assert pickle.load(f).observation_space["coverage"].shape == (36,)
    needle = (f"{bad / 'vecnormalize.pkl'}: statistics of another observation than "
              "model.zip's (osa/Search-v0)")
    with pytest.raises(ValueError, match=re.escape(needle)):
        TrainedPolicy.load(bad)
    argv = ["search", "search-random-los", "--policy", f"ppo:{bad}", "--seed", "1",
            "--no-figures", "--no-progress", "-o", str(tmp_path / "out")]
    assert status_of(argv) == 2
    assert needle in one_line(capsys)
    argv = ["train", "--env", "osa/Search-v0", "--init", str(bad), "--steps", "1",
            "--envs", "1", "--no-progress", "-o", str(tmp_path / "m")]
    assert status_of(argv) == 2
    assert one_line(capsys).startswith(f"osa train: --init: {needle}")
    assert not (tmp_path / "m").exists()
