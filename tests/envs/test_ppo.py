"""The recipe's training options (docs/rl.md, "What was tried"): the metric as the reward
(``--reward-preset metric``), PPO kept near the clone (``--imitation-coef``) and the
critic warm-up (``--critic-warmup``), :mod:`envs.ppo`."""

from __future__ import annotations

import dataclasses
import re

import gymnasium
import numpy as np
import pytest

import envs  # noqa: F401  (registers the envs)
import sim
from envs.commands.train import preset_weights
from envs.gym.plan_actions import plan_heuristic

ID = "osa/Search-v1"


def one_responder_file(tmp_path, budget_s: float):
    """``search-five-mixed`` with one responder and a short budget, as a scenario file."""
    toml = tmp_path / "r.toml"
    toml.write_text('extends = "search-five-mixed"\nname = "r"\n[search]\n'
                    f'budget_s = {budget_s}\nrandom_responders = 1\nexpected_responders = 1\n')
    return toml


def assert_train_refuses(main, cases, out, capsys) -> None:
    """Each ``(argv, pattern)`` of ``cases``: ``osa train`` refuses it in one line, exit 2."""
    capsys.readouterr()
    for argv, match in cases:
        assert main(["train", *argv, "-o", str(out)]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "osa train: --" in err and re.search(match, err)


def small(budget_s: float, responders: int):
    sc = sim.load_scenario("search-five-mixed")
    return dataclasses.replace(sc, search=dataclasses.replace(
        sc.search, budget_s=budget_s, random_responders=responders,
        expected_responders=responders))


def test_metric_reward_is_minus_the_time_until_every_expected_responder_is_localised():
    """The hand computation on a scripted episode (the hand-written policy): every
    step's reward is -time_cost_per_s x the seconds flown in it, every other term is 0,
    and the return is -time_cost_per_s x the flight time at the end, which is the
    moment the estimator judges the expected responders localised (or the budget)."""
    weights = preset_weights("metric", ID)
    assert weights == {"information_weight": 0.0, "detection_bonus": 0.0,
                       "coverage_bonus": 0.0, "leave_penalty": 0.0, "localised_bonus": 0.0}
    env = gymnasium.make(ID, scenario=small(900.0, 1), time_cost_per_s=0.02, **weights)
    full = gymnasium.make(ID, scenario=small(900.0, 1))  # the default reward, same world
    act = plan_heuristic(env.unwrapped.pilot.actions)
    ends = {}
    for name, e in (("metric", env), ("full", full)):
        obs, info = e.reset(options={"world_seed": 1_000_000})
        ret, t_prev, n = 0.0, 0.0, 0
        while True:
            obs, r, term, trunc, info = e.step(act(obs))
            n += 1
            dt = info["flight_time_s"] - t_prev
            t_prev = info["flight_time_s"]
            if name == "metric":
                assert r == pytest.approx(-0.02 * dt, abs=1e-12)
                assert all(v == 0.0 for k, v in info["reward_terms"].items() if k != "time")
            ret += r
            if term or trunc:
                break
        ends[name] = (ret, n, info, term)
    ret, n, info, term = ends["metric"]
    assert term and info["localised"] == 1  # ended by the estimator's judgement
    assert ret == pytest.approx(-0.02 * info["flight_time_s"], abs=1e-9)
    assert info["flight_time_s"] == pytest.approx(5.0 * n)  # decisions of 5 s
    # the same flight as under the default reward (the reward does not steer the env)
    assert ends["full"][1] == n and ends["full"][0] > ret + 10  # bonuses paid there


def _setup(coef: float, warmup: int = 0, seed: int = 0):
    """A GuidedPPO on one small world with the hand-written policy's labels of one
    episode as the imitation dataset."""
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    from envs.ppo import GuidedPPO
    from envs.rl import _fly_and_label

    sc = small(150.0, 1)
    venv = DummyVecEnv([lambda: gymnasium.make(ID, scenario=sc)])
    venv.seed(seed)
    venv = VecNormalize(venv, gamma=0.995)
    model = GuidedPPO("MultiInputPolicy", venv, n_steps=64, batch_size=32, n_epochs=4,
                      learning_rate=1e-3, ent_coef=0.0, seed=seed, device="cpu",
                      policy_kwargs={"net_arch": [32, 32]}, imitation_coef=coef,
                      critic_warmup=warmup, imitation_seed=seed)
    teacher = plan_heuristic(gymnasium.make(ID, scenario=sc).unwrapped.pilot.actions)
    raw, labels, _, _ = _fly_and_label(venv, 1, teacher, None, 0.995)
    model.set_imitation_data({k: np.stack([x[k] for x in raw]) for k in raw[0]},
                             np.array(labels), venv.normalize_obs)
    return model


def _ce(model) -> float:
    import torch

    with torch.no_grad():
        return float(model.imitation_ce())


def test_imitation_term_keeps_the_policy_near_the_teacher_s_labels():
    pytest.importorskip("stable_baselines3")
    import torch

    models, start = [], []
    for coef in (0.0, 5.0, 5.0):  # each built then trained (SB3 seeds torch's global RNG)
        m = _setup(coef)
        start.append(_ce(m))
        m.learn(192)  # three updates of 64 decisions
        models.append(m)
    plain, guided, again = models
    ce0 = start[0]
    assert start == pytest.approx([ce0] * 3, abs=1e-12)  # the same start
    # the term lowers the cross-entropy to the labels; plain PPO does not
    ce_plain, ce_guided = _ce(plain), _ce(guided)  # 2.83 -> 2.82 and 2.05 when written
    assert ce_guided < 0.8 * ce0 and ce_plain > 0.95 * ce0 and ce_guided < ce_plain - 0.5
    # deterministic: the same seed trains the same weights
    a, b = guided.policy.state_dict(), again.policy.state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)


def test_critic_warm_up_leaves_the_actor_unchanged_and_fits_the_value_head(tmp_path):
    pytest.importorskip("stable_baselines3")
    import torch
    from stable_baselines3 import PPO

    model = _setup(5.0, warmup=2)
    actor = [x.detach().clone() for x in model.actor_parameters()]
    value = [x.detach().clone() for x in model.policy.value_net.parameters()]
    model.learn(128)  # two updates: the warm-up
    assert model.updates_done == 2
    assert all(torch.equal(a, x) for a, x in zip(actor, model.actor_parameters(), strict=True))
    assert not all(torch.equal(a, x) for a, x in
                   zip(value, model.policy.value_net.parameters(), strict=True))
    model.learn(64, reset_num_timesteps=False)  # after it, the actor moves
    assert not all(torch.equal(a, x)
                   for a, x in zip(actor, model.actor_parameters(), strict=True))
    # it saves and loads as a plain PPO model (ppo:MODEL), without the dataset
    model.save(str(tmp_path / "model.zip"))
    loaded = PPO.load(str(tmp_path / "model.zip"), device="cpu")
    a, b = model.policy.state_dict(), loaded.policy.state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert not hasattr(loaded, "_imitation")


def test_osa_train_recipe_options_and_their_errors(tmp_path, capsys):
    pytest.importorskip("stable_baselines3")
    import json

    from envs.cli import main

    toml = one_responder_file(tmp_path, 100.0)
    out = tmp_path / "m"
    assert main(["train", "--env", ID, "--scenario", str(toml), "--steps", "512", "--envs", "2",
                 "--vec", "batched", "--imitate", "1", "--reward-preset", "metric",
                 "--reward", "time_cost_per_s=0.05", "--imitation-coef", "1",
                 "--critic-warmup", "1", "--eval-every", "0", "--checkpoint-every", "0",
                 "--no-progress", "-o", str(out)]) == 0
    meta = json.loads((out / "osa-model.json").read_text())
    assert meta["imitation_coef"] == 1.0 and meta["critic_warmup"] == 1
    cfg = meta["config"]
    assert (cfg["information_weight"], cfg["detection_bonus"], cfg["coverage_bonus"],
            cfg["leave_penalty"], cfg["time_cost_per_s"]) == (0.0, 0.0, 0.0, 0.0, 0.05)
    assert meta["env_kwargs"]["localised_bonus"] == 0.0
    assert_train_refuses(main, ((["--env", ID, "--imitation-coef", "1"], "needs --imitate"),
                                (["--env", ID, "--imitate", "1", "--imitation-coef", "-1"],
                                 ">= 0"),
                                (["--algo", "A2C", "--critic-warmup", "2"], "PPO only"),
                                (["--env", "osa/Team-v0", "--reward-preset", "metric"],
                                 "not for"),
                                (["--env", ID, "--reward", "information_weight=-1"], ">= 0")),
                         tmp_path / "x", capsys)
