"""``osa/Search-v1`` (the whole search as the policy's choice), domain randomisation
from ``[randomise]`` and the curriculum level.

The floor: a uniformly random policy and the hand-written policy in the same actions
(:func:`envs.gym.plan_actions.plan_heuristic`) fly the same worlds of a small suite
(common random numbers); per world the better is the one that localised more
responders, then sooner; the hand-written policy must win so many worlds that a
one-sided exact sign test gives p < 0.01 (ties count against it).
"""

from __future__ import annotations

import dataclasses
import math
import pickle
import re

import gymnasium
import numpy as np
import pytest

import envs  # noqa: F401  (registers the envs)
import sim
from envs.gym.interface import EnvConfig
from envs.gym.plan import PlanEnv
from envs.gym.plan_actions import PlanActions, plan_heuristic
from sim.randomise import Randomise
from tests.envs.gym.test_envs import assert_checkers_pass

ID = "osa/Search-v1"


def small(budget_s: float = 900.0, responders: int = 2, **search):
    sc = sim.load_scenario("search-five-mixed")
    return dataclasses.replace(sc, search=dataclasses.replace(
        sc.search, budget_s=budget_s, random_responders=responders,
        expected_responders=responders, **search))


def randomised(**ranges):
    sc = small()
    return dataclasses.replace(sc, randomise=Randomise(**ranges))


def rollout(env, act, *, seed=None, world_seed=None, steps=10_000, pickled=False):
    obs, info = env.reset(seed=seed, options=None if world_seed is None
                          else {"world_seed": world_seed})
    out = [(obs, info)]
    for _ in range(steps):
        if pickled:
            env = pickle.loads(pickle.dumps(env))
        obs, r, te, tr, info = env.step(act(obs))
        out.append((obs, r, te, tr, info))
        if te or tr:
            break
    return out


def equal(a, b) -> bool:
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(equal(a[k], b[k]) for k in a)
    if isinstance(a, tuple | list):
        return len(a) == len(b) and all(equal(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, np.ndarray):
        return a.dtype == b.dtype and np.array_equal(a, b)
    return a == b


def uniform(seed: int, n: int):
    rng = np.random.default_rng(seed)
    return lambda obs: int(rng.integers(n))


# ----------------------------------------------------------------------------- the env


def test_checkers_pass_without_warnings():
    assert_checkers_pass(ID, scenario=small())
    u = gymnasium.make(ID).unwrapped
    assert isinstance(u, PlanEnv) and u.action_space.n == 17
    assert {"sectors", "set_aside", "flying", "coverage", "responders"} <= set(
        u.observation_space.spaces)


def test_the_action_mapping_is_an_object_passed_to_the_env():
    acts = PlanActions(EnvConfig(max_responders=5, coverage_cells=8), sectors=4)
    env = gymnasium.make(ID, scenario=small(), actions=acts, coverage_cells=8)
    u = env.unwrapped
    # its own copy (test_shared_actions.py: one object given to several envs)
    assert u.pilot.actions is not acts and u.pilot.actions.sectors == 4
    assert u.action_space.n == 16 + 8
    obs, _ = env.reset(seed=0)
    assert obs["sectors"].shape == (16,) and obs["flying"].shape == (24,)
    with pytest.raises(ValueError, match="sectors"):
        PlanActions(EnvConfig(), sectors=0)


def test_same_seed_same_rollout_and_every_state_pickles():
    """Pickled and unpickled after EVERY step of a seeded random rollout, the copy
    taking the next step: equal to the straight rollout; the same seed again: equal."""
    sc = small(300.0)
    straight = rollout(gymnasium.make(ID, scenario=sc).unwrapped, uniform(3, 17), seed=4)
    twin = rollout(gymnasium.make(ID, scenario=sc).unwrapped, uniform(3, 17), seed=4,
                   pickled=True)
    again = rollout(gymnasium.make(ID, scenario=sc).unwrapped, uniform(3, 17), seed=4)
    assert len(straight) == 61  # the 300 s budget in 5 s decisions
    assert equal(straight, twin) and equal(straight, again)
    other = rollout(gymnasium.make(ID, scenario=sc).unwrapped, uniform(3, 17), seed=5)
    assert other[0][1]["world_seed"] != straight[0][1]["world_seed"]
    # the random rollout did use the choices: several actions flown, responders heard
    flown = {int(np.argmax(o[0]["flying"])) for o in straight[1:] if o[0]["flying"].any()}
    assert len(flown) >= 6


def test_nothing_is_forced_before_anything_is_heard():
    """Each sector action flies to its own sector (v0 swept whatever was chosen)."""
    env = gymnasium.make(ID, scenario=small()).unwrapped
    ends = []
    for a in (0, 2, 6, 8):  # the four corner sectors of 3 x 3
        env.reset(options={"world_seed": 11})
        for _ in range(12):
            obs, *_ = env.step(a)
        ends.append(obs["agent"][:2].copy())
    e = np.array(ends)  # east, north about the centre / half extent
    assert e[0][0] < 0 and e[0][1] < 0 and e[1][0] > 0 and e[1][1] < 0
    assert e[2][0] < 0 and e[2][1] > 0 and e[3][0] > 0 and e[3][1] > 0


def test_done_sets_the_target_aside_and_next_switches():
    env = gymnasium.make(ID, scenario=small(900.0, 3, random_concealment=("open",))).unwrapped
    acts = env.pilot.actions
    act = plan_heuristic(acts)
    obs, _ = env.reset(options={"world_seed": 21})
    heard = 0
    for _ in range(180):
        obs, *_ = env.step(act(obs))
        heard = int(obs["responder_mask"].sum())
        if heard >= 2 and not obs["set_aside"].any():
            break
    assert heard >= 2
    slots = obs["responders"].reshape(5, -1)
    target = int(np.argmax(slots[:, -1]))
    obs, *_ = env.step(acts.index("done"))
    assert obs["set_aside"][target] == 1.0
    assert obs["responders"].reshape(5, -1)[target, -1] == 0.0  # no longer the target
    before = int(np.argmax(obs["responders"].reshape(5, -1)[:, -1]))
    obs, *_ = env.step(acts.index("next"))
    assert int(np.argmax(obs["responders"].reshape(5, -1)[:, -1])) != target or before == target


def sign_test_p(wins: int, n: int) -> float:
    """One-sided exact sign test: P(X >= wins), X ~ Binomial(n, 1/2)."""
    return sum(math.comb(n, k) for k in range(wins, n + 1)) / 2**n


def score(run) -> tuple[int, float]:
    """(responders localised, -time): higher is better."""
    info = run[-1][-1]
    return info["localised"], -info["flight_time_s"]


def test_random_is_clearly_worse_than_the_hand_written_policy():
    sc = small(600.0, 2)
    env = gymnasium.make(ID, scenario=sc, seed_split="validation").unwrapped
    best = plan_heuristic(env.pilot.actions)
    worlds = range(1_000_000, 1_000_012)
    wins = 0
    for k, w in enumerate(worlds):
        h = score(rollout(env, best, world_seed=w))
        r = score(rollout(env, uniform(k, env.action_space.n), world_seed=w))
        wins += h > r
    assert sign_test_p(wins, len(worlds)) < 0.01, wins


# ----------------------------------------------------------------------------- randomise


RANGES = dict(gnss_bias_scale=(0.5, 3.0), concealed_share=(0.2, 0.9), range_offset_m=(0.0, 2.0),
              gnss_drop_prob=(0.0, 0.05), wind_mps=(0.0, 6.0))


def drawn(real) -> dict:
    s = real.scenario
    return {"bias": s.gnss.bias_sigma_h_m, "offset": s.ftm.offset_min_m,
            "drop": s.gnss.drop_prob, "wind": math.hypot(*s.vehicle.wind_enu_mps),
            "concealed": sum(c != "open" for c in s.search.random_concealment) / 20}


def test_randomise_is_drawn_from_the_world_seed_inside_the_ranges():
    sc = randomised(**RANGES)
    base = small().gnss.bias_sigma_h_m
    a, b = drawn(sim.realise(sc, 7)), drawn(sim.realise(sc, 7))
    assert a == b  # the same world seed, the same draw, wherever it is realised
    seen = [drawn(sim.realise(sc, s)) for s in range(40)]
    for d in seen:
        assert 0.5 * base <= d["bias"] <= 3.0 * base
        assert 0.2 - 0.025 <= d["concealed"] <= 0.9 + 0.025
        assert 0.0 <= d["offset"] <= 2.0 and 0.0 <= d["drop"] <= 0.05 and d["wind"] <= 6.0
    assert len({d["bias"] for d in seen}) == 40  # it does vary from world to world
    # and the realised world follows: every responder concealed at a share of 1, none at 0
    all_in = sim.realise(randomised(concealed_share=(1.0, 1.0)), 3).world.responders
    none_in = sim.realise(randomised(concealed_share=(0.0, 0.0)), 3).world.responders
    assert {r.concealment for r in all_in} == {"vegetation"}
    assert {r.concealment for r in none_in} == {"open"}
    # the offsets the radio uses: every responder the drawn offset
    real = sim.realise(randomised(range_offset_m=(1.5, 1.5)), 3)
    assert np.allclose(real.offsets_m, 1.5)


def test_randomise_has_an_effect_on_what_is_flown_and_heard():
    """The same world seed and flight: wind moves the vehicle (the simulator's truth,
    read here for the test only); concealment in vegetation cuts the ranges heard."""
    out = {}
    for key, ranges in (("calm", dict(wind_mps=(0.0, 0.0), concealed_share=(0.0, 0.0))),
                        ("windy", dict(wind_mps=(9.0, 9.0), concealed_share=(0.0, 0.0))),
                        ("hidden", dict(wind_mps=(0.0, 0.0), concealed_share=(1.0, 1.0)))):
        env = gymnasium.make(ID, scenario=randomised(**ranges)).unwrapped
        obs, _ = env.reset(options={"world_seed": 5})
        for _ in range(40):
            obs, *_ = env.step(env.pilot.actions.index("lawnmower"))
        heard = obs["responders"].reshape(5, -1)[:, 10].sum()  # log counts of ranges heard
        out[key] = (np.array(env.loop.vehicle.stepper.agents[0].vehicle.state.position_m), heard)
    assert np.linalg.norm(out["calm"][0] - out["windy"][0]) > 5.0
    assert np.array_equal(out["calm"][0], out["hidden"][0])  # the same flight
    assert out["hidden"][1] < 0.8 * out["calm"][1]


def test_scenario_table_and_its_errors(tmp_path):
    p = tmp_path / "r.toml"
    p.write_text('extends = "search-five-mixed"\nname = "r"\n[randomise]\n'
                 'gnss_bias_scale = [0.5, 2.0]\nwind_mps = [0.0, 5.0]\n')
    sc = sim.load_scenario(p)
    assert sc.randomise == Randomise(gnss_bias_scale=(0.5, 2.0), wind_mps=(0.0, 5.0))
    for bad, match in (("wind_mps = [5.0, 1.0]", "wind_mps"), ("concealed_share = [0, 2]",
                       "concealed_share"), ("gusts = [0, 1]", "unknown key")):
        p.write_text(f'extends = "search-five-mixed"\nname = "r"\n[randomise]\n{bad}\n')
        with pytest.raises(sim.ScenarioError, match=match):
            sim.load_scenario(p)


# ----------------------------------------------------------------------------- curriculum


def test_curriculum_level_narrows_the_ranges():
    sc = randomised(**RANGES)
    env = gymnasium.make(ID, scenario=sc).unwrapped
    base = small().gnss.bias_sigma_h_m
    got = {}
    for level in (0.0, 0.5, 1.0):
        env.set_level(level)
        _, info = env.reset(options={"world_seed": 9})
        assert info["level"] == level
        got[level] = drawn(env.loop.realisation)
    assert got[0.0]["bias"] == pytest.approx(0.5 * base) and got[0.0]["wind"] == 0.0
    assert got[0.0]["bias"] < got[0.5]["bias"] < got[1.0]["bias"]
    assert got[1.0] == drawn(sim.realise(sc, 9))  # level 1: the world everywhere else
    _, info = env.reset(options={"world_seed": 9, "level": 0.5})
    assert drawn(env.loop.realisation) == got[0.5] and env.level == 0.5
    with pytest.raises(ValueError, match="level"):
        env.set_level(1.5)


def test_curriculum_level_of_the_training_progress():
    from envs.rl import curriculum_level

    assert curriculum_level((0.2, 1.0), 0.0) == 0.2
    assert curriculum_level((0.2, 1.0), 0.5) == 0.6
    assert curriculum_level((0.2, 1.0), 2.0) == 1.0
    assert curriculum_level((1.0, 0.0), 0.25) == 0.75


def test_osa_train_trains_search_v1_with_a_curriculum_and_it_flies_osa_search(tmp_path):
    pytest.importorskip("stable_baselines3")
    import json

    from envs.cli import main
    from envs.loop import run_search
    from envs.policies import load_policy
    from envs.rl import make_env
    from envs.rl import rollout as env_rollout

    toml = tmp_path / "r.toml"
    toml.write_text('extends = "search-five-mixed"\nname = "r"\n[search]\nbudget_s = 200.0\n'
                    'random_responders = 2\nexpected_responders = 2\n'
                    '[randomise]\nwind_mps = [0.0, 4.0]\n')
    out = tmp_path / "m"
    assert main(["train", "--env", "osa/Search-v1", "--scenario", str(toml), "--steps", "256",
                 "--envs", "1", "--eval-every", "0", "--checkpoint-every", "0",
                 "--curriculum", "0:1", "--imitate", "2", "--dagger", "1", "--no-progress",
                 "-o", str(out)]) == 0
    imitated = json.loads((out / "imitation.json").read_text())
    assert imitated["episodes"] == 2 and imitated["decisions"] == 80  # 2 x 200 s / 5 s
    assert imitated["loss"][-1] < 0.7 * imitated["loss"][0] and imitated["agreement"] > 0.7
    teacher, dagger = imitated["rounds"]  # the DAgger round: the clone flew, was labelled
    assert teacher["flown_by"] == "teacher" and dagger["flown_by"] == "clone"
    assert dagger["decisions"] == 80 and 0.0 <= teacher["clone_agreement_flying"] <= 1.0
    meta = json.loads((out / "osa-model.json").read_text())
    assert meta["env_id"] == "osa/Search-v1" and meta["kind"] == "plan"
    assert meta["curriculum"] == [0.0, 1.0]
    with open(out / "progress.csv") as f:
        assert "train/curriculum_level" in f.readline()
    # the model flies osa search as it flew its env (same world, same end)
    policy = load_policy(f"ppo:{out}")
    res = run_search(sim.load_scenario(toml), policy, 2_000_000)
    env = make_env("osa/Search-v1", {"scenario": str(toml)})
    ep = env_rollout(env, lambda o: policy.action(o), 2_000_000)
    assert res.flight_time_s == pytest.approx(ep.flight_time_s, abs=5.0)


def test_osa_train_curriculum_and_imitate_errors(tmp_path, capsys):
    pytest.importorskip("stable_baselines3")
    from envs.cli import main

    for argv, match in ((["--env", "osa/Search-v0", "--curriculum", "0:1"], "no curriculum"),
                        (["--env", "osa/Search-v1", "--curriculum", "0-1"], "FROM:TO"),
                        (["--env", "osa/Search-v1", "--curriculum", "0:2"], r"\[0, 1\]"),
                        (["--env", "osa/Search-v0", "--imitate", "3"], "nothing to imitate"),
                        (["--env", "osa/Search-v1", "--dagger", "2"], "needs --imitate"),
                        (["--env", "osa/Search-v1", "--ent-coef", "nan"], "in \\[0, 1\\]"),
                        (["--algo", "A2C", "--learning-rate", "1e-4"], "PPO only")):
        assert main(["train", *argv, "-o", str(tmp_path / "x")]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "osa train: --" in err and re.search(match, err)


def test_osa_train_init_starts_from_a_model_s_weights_and_statistics(tmp_path, capsys):
    pytest.importorskip("stable_baselines3")
    import json
    import pickle

    import torch
    from stable_baselines3 import PPO

    from envs.cli import main

    toml = tmp_path / "r.toml"
    toml.write_text('extends = "search-five-mixed"\nname = "r"\n[search]\nbudget_s = 100.0\n'
                    'random_responders = 1\nexpected_responders = 1\n')
    common = ["train", "--env", "osa/Search-v1", "--scenario", str(toml), "--steps", "256",
              "--envs", "1", "--checkpoint-every", "0", "--no-progress"]
    a, b = tmp_path / "a", tmp_path / "b"
    assert main([*common, "--eval-every", "0", "-o", str(a)]) == 0
    # from a, with another seed (other fresh weights) at learning rate 0: the weights stay
    # a's, and the first validation (before any rollout) flies a's policy
    # (and other reward weights: the observation and actions are the same)
    assert main([*common, "--init", str(a), "--seed", "1", "--learning-rate", "0",
                 "--reward", "time_cost_per_s=0.1", "--reward", "localised_bonus=0",
                 "--eval-every", "100000", "--eval-worlds", "1", "-o", str(b)]) == 0
    pa, pb = (PPO.load(str(m / "model.zip"), device="cpu").policy.state_dict() for m in (a, b))
    assert all(torch.equal(pa[k], pb[k]) for k in pa)
    meta = json.loads((b / "osa-model.json").read_text())
    assert meta["init"] == str(a.resolve()) and meta["config"]["time_cost_per_s"] == 0.1
    assert meta["env_kwargs"]["localised_bonus"] == 0.0
    with open(a / "vecnormalize.pkl", "rb") as f:
        n_a = pickle.load(f).obs_rms["agent"].count
    with open(b / "vecnormalize.pkl", "rb") as f:
        n_b = pickle.load(f).obs_rms["agent"].count
    assert n_b >= n_a + 256  # a's statistics, updated by b's 256 steps
    capsys.readouterr()
    for argv, match in ((["--init", str(tmp_path / "none")], "not a model"),
                        (["--init", str(a), "--env", "osa/Search-v0"], "not PPO in osa/Search-v0"),
                        (["--init", str(a), "--env", "osa/Search-v1", "--algo", "A2C"],
                         "not A2C in osa/Search-v1"),
                        (["--reward", "speed=1"], "unknown weight"),
                        (["--reward", "time_cost_per_s=-1"], ">= 0"),
                        (["--reward", "localised_bonus=1"], "osa/Search-v1's")):
        assert main(["train", *argv, "-o", str(tmp_path / "x")]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "osa train: --" in err and re.search(match, err)
