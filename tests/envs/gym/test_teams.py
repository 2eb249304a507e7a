"""Teams (docs/rl.md, "Teams"): parameter-shared PPO in ``osa/Team-v0`` learns, a
trained team flies ``osa evaluate`` as its env episode flew, ``team:NAME`` flies every
UAV, team evaluations are deterministic per seed, and a training sweep on a Dask
cluster gives what the same tasks give here.

The learning statistics are those of ``test_learning.py``: the trained team (PPO's
stochastic policy, its draws seeded, every UAV running the one network on its own
observation) and a uniformly random team (seeded) fly the same 30 validation worlds;
a world is a win when the team's return (the mean of its UAVs' returns) is higher;
the one-sided exact sign test must give p < 0.01 (at least 22 wins of 30) with a
positive median paired difference.
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

pytest.importorskip("stable_baselines3")
pytest.importorskip("supersuit")

import sim
from envs.gym.multi import with_agents
from envs.gym.team import TEAM_ENV_ID, make_team_env, team_rollout
from envs.gym.trained import TrainedPolicy, TrainedTeamPolicy
from envs.policies import load_policy
from envs.rl import TrainSettings, model_actor, train
from envs.seeds import split_seeds
from tests.envs.gym.test_learning import sign_test_p

# one worker runs this file (pytest-xdist --dist loadgroup): its trained model is
# built once
pytestmark = pytest.mark.xdist_group("teams")

STEPS = 8192  # agent decisions (4096 team steps of 2 UAVs): ~25 s of CPU
WORLDS = 30
SCENARIO = ('extends = "search-random-los-rtk"\nname = "rtk-5min"\n'
            '[search]\nbudget_s = 300.0\n')
LEARN = dict(n_steps=256, batch_size=128, learning_rate=3e-4, gamma=0.99, ent_coef=0.0)


@pytest.fixture(scope="module")
def team(tmp_path_factory):
    d = tmp_path_factory.mktemp("team")
    toml = d / "rtk-5min.toml"
    toml.write_text(SCENARIO)
    kwargs = {"scenario": str(toml), "uavs": 2}
    settings = TrainSettings(env_id=TEAM_ENV_ID, env_kwargs=kwargs, steps=STEPS, seed=0,
                             n_envs=1, eval_every=STEPS, eval_worlds=2, checkpoint_every=0,
                             progress=False, algo_kwargs=LEARN)
    summary = train(settings, d / "model")
    return d / "model", summary, kwargs


def test_a_trained_team_beats_a_random_team_on_held_out_worlds(team):
    model, summary, kwargs = team
    assert summary.steps >= STEPS
    policy = TrainedPolicy.load(model)
    assert isinstance(policy, TrainedTeamPolicy)
    env = make_team_env({**kwargs, "seed_split": "validation"})
    worlds = split_seeds("validation", WORLDS)
    policy.model.set_random_seed(7)

    def sample(obs):
        return policy.model.predict(policy.stats.normalize_obs(obs), deterministic=False)[0]

    ours = [team_rollout(env, sample, w) for w in worlds]
    rng = np.random.default_rng(12345)
    rand = [team_rollout(env, lambda _o: rng.uniform(-1.0, 1.0, 3).astype(np.float32), w)
            for w in worlds]
    diff = np.array([a.ret - b.ret for a, b in zip(ours, rand, strict=True)])
    wins = int(np.sum(diff > 0))
    p = sign_test_p(wins, len(diff))
    print(f"trained team wins {wins} of {len(diff)}, p = {p:.2g}, median paired difference "
          f"{np.median(diff):+.2f}")  # the figure in docs/rl.md (pytest -rP)
    assert p < 0.01 and np.median(diff) > 0, (wins, p, diff.round(2).tolist())


def test_the_trained_team_flies_the_loop_as_its_env_episode(team):
    """``ppo:MODEL`` of a team model: every UAV its own waypoints from the one network,
    the same flight as the env's deterministic episode on the same world."""
    from envs.loop import run_search

    model, _summary, kwargs = team
    meta = json.loads((model / "osa-model.json").read_text())
    assert meta["env_id"] == TEAM_ENV_ID and meta["kind"] == "team"
    assert [a["name"] for a in meta["agents"]] == ["uav-1", "uav-2"]
    policy = load_policy(f"ppo:{model}")
    assert isinstance(policy, TrainedTeamPolicy)
    env = make_team_env({**kwargs, "seed_split": "validation"})
    world = split_seeds("validation", 1)[0]
    ep = team_rollout(env, model_actor(policy.model, policy.stats), world)
    scenario = with_agents(sim.load_scenario(kwargs["scenario"]), 2)
    res = run_search(scenario, policy, world)
    assert res.flight_time_s == pytest.approx(ep.flight_time_s)
    assert (res.ended == "localised") == ep.localised
    moved = [np.ptp(np.asarray(t)[:, 1:3], axis=0).max() for t in res.nav_track]
    assert len(moved) == 2 and min(moved) > 20.0, moved
    with pytest.raises(ValueError, match="flies a team of 2; scenario rtk-5min has 1 agents"):
        load_policy(f"ppo:{model}", sim.load_scenario(kwargs["scenario"]))
    with pytest.raises(ValueError, match="is a team policy, not a one-UAV policy"):
        load_policy(f"team:ppo:{model}")
    with pytest.raises(ValueError, match="team of 2"):
        policy.reset(dataclasses.replace(ep_mission(scenario), n_agents=3),
                     np.random.default_rng(0))


def ep_mission(scenario):
    from envs.loop import mission_of

    return mission_of(scenario)


def test_team_evaluation_rows_are_deterministic_per_seed(team):
    """A short 2-UAV evaluation on three responders: the trained team and two
    independent adaptive UAVs; the same rows again, and with the seeds in another
    order; every UAV of ``team:adaptive`` flies."""
    from envs.evaluate import evaluate, summarise

    model, _summary, _kwargs = team
    base = sim.load_scenario("search-three-mixed")
    scenario = with_agents(dataclasses.replace(
        base, search=dataclasses.replace(base.search, budget_s=240.0)), 2)
    policies = [f"ppo:{model}", "team:adaptive"]
    first = evaluate(scenario, policies, [2_000_000, 2_000_001], example_seeds=[2_000_000])
    again = evaluate(scenario, policies, [2_000_001, 2_000_000])
    key = lambda r: (r["policy"], r["seed"], r["bssid"])  # noqa: E731
    assert sorted(first.rows, key=key) == sorted(again.rows, key=key)
    assert len(first.rows) == 2 * 2 * 3
    by = {(e.policy, e.seed): e for e in first.episodes}
    for p in policies:
        tracks = by[(p, 2_000_000)].track_enu_m
        assert len(tracks) == 2
        assert min(np.ptp(t, axis=0).max() for t in tracks) > 20.0, p
    summaries = summarise(first.rows, policies)
    assert [s.responders for s in summaries] == [6, 6]
    assert sum(r["detected_at_s"] is not None for r in first.rows) > 0


def test_team_policy_names():
    p = load_policy("team:lawnmower")
    assert p.name == "team:lawnmower"
    with pytest.raises(ValueError, match="unknown policy"):
        load_policy("team:nope")
    with pytest.raises(ValueError, match="team of teams"):
        load_policy("team:team:adaptive")


# ---------------------------------------------------------------------- sweeps
SWEEP = """
env = "osa/Team-v0"
steps = 256
eval_worlds = 1
[ppo]
n_steps = 64
batch_size = 64
n_epochs = 2
[[task]]
name = "a"
seed = 0
[[task]]
name = "b"
seed = 1
[task.ppo]
learning_rate = 1e-3
[[task]]
name = "recipe"
env = "osa/Search-v3"
uavs = 1
steps = 128
seed = 2
envs = 2
vec = "batched"
imitate = 1
dagger = 1
imitation_coef = 1.0
critic_warmup = 1
reward_preset = "metric"
curriculum = [0.5, 1.0]
[task.reward]
time_cost_per_s = 0.05
"""


def _parameters(folder) -> dict:
    from stable_baselines3 import PPO

    return {k: v.numpy() for k, v in
            PPO.load(str(folder / "model.zip"), device="cpu").policy.state_dict().items()}


def test_a_sweep_on_a_dask_cluster_equals_the_same_tasks_run_here(tmp_path):
    distributed = pytest.importorskip(
        "distributed", reason="Dask distributed is not installed (not in the README's .[test])")
    from envs.sweep import read_sweep, run_sweep, settings_of

    f = tmp_path / "sweep.toml"
    f.write_text(SWEEP)
    short = tmp_path / "rtk-5min.toml"  # validation: 60 decisions a world
    short.write_text(SCENARIO)
    tasks = read_sweep(f, {"scenario": str(short), "uavs": 2})
    assert [t["name"] for t in tasks] == ["a", "b", "recipe"]
    assert tasks[1]["ppo"] == {"n_steps": 64, "batch_size": 64, "n_epochs": 2,
                               "learning_rate": 1e-3}
    # the recipe of issue 20's item 4 as a sweep task, read as its command line is
    s = settings_of(tasks[2])
    assert (s.env_id, s.imitate_episodes, s.imitate_rounds, s.imitation_coef,
            s.critic_warmup, s.curriculum, s.vec, s.n_envs) == \
        ("osa/Search-v3", 1, 1, 1.0, 1, (0.5, 1.0), "batched", 2)
    assert s.env_kwargs["time_cost_per_s"] == 0.05 and s.env_kwargs["information_weight"] == 0
    assert s.algo_kwargs["n_steps"] == 64 and s.algo_kwargs["gamma"] == 0.995
    here = tmp_path / "here"
    there = tmp_path / "there"
    here.mkdir()
    there.mkdir()
    run_sweep(tasks, here)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False,
                                  dashboard_address=None) as cluster, \
            distributed.Client(cluster, set_as_default=False) as client:
        run_sweep(tasks, there, client)
    assert (here / "sweep.csv").read_text() == (there / "sweep.csv").read_text()
    rows = (here / "sweep.csv").read_text().splitlines()
    assert len(rows) == 4 and rows[1].startswith(f"a,osa/Team-v0,{short},2,0,256")
    assert rows[3].startswith(f"recipe,osa/Search-v3,{short},,2,128,PPO,")
    assert rows[3].endswith('"{""critic_warmup"": 1, ""curriculum"": [0.5, 1.0], ""dagger"": 1, '
                            '""imitate"": 1, ""imitation_coef"": 1.0, ""reward"": '
                            '{""time_cost_per_s"": 0.05}, ""reward_preset"": ""metric""}"')
    imitated = json.loads((here / "recipe" / "imitation.json").read_text())
    assert imitated == json.loads((there / "recipe" / "imitation.json").read_text())
    assert len(imitated["rounds"]) == 2 and imitated["agreement"] > 0.5
    for name in ("a", "b", "recipe"):
        a, b = _parameters(here / name), _parameters(there / name)
        assert a.keys() == b.keys()
        for k in a:
            np.testing.assert_array_equal(a[k], b[k], err_msg=f"{name}: {k}")
        assert ((here / name / "vecnormalize.pkl").read_bytes()
                == (there / name / "vecnormalize.pkl").read_bytes())
    pa, pb = _parameters(here / "a"), _parameters(here / "b")
    assert any(not np.array_equal(pa[k], pb[k]) for k in pa)  # the seeds matter


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("steps = 10\n", "no \\[\\[task\\]\\] entries"),
        ("[[task]]\nlr = 1\n", "unknown key 'lr'"),
        ("[[task]]\nsteps = -1\n", "steps must be an integer >= 1"),
        ("[[task]]\n[task.ppo]\nlearning_rat = 1\n", "unknown PPO setting"),
        ("[[task]]\nname = 'x'\n[[task]]\nname = 'x'\n", "repeated"),
        ("[[task]\n", "not valid TOML"),
        ("[[task]]\nenv = 'osa/Nope-v0'\n", "task task-1: env: unknown env"),
        ("[[task]]\nenv = 'osa/Waypoint-v0'\nuavs = 2\n", "uavs: only for osa/Team-v0"),
        ("[[task]]\nenv = 'osa/Team-v0'\nvec = 'batched'\n", "vec batched: not for osa/Team"),
        ("[[task]]\nvec = 'gpu'\n", "vec must be 'subproc' or 'batched'"),
        ("[[task]]\nimitate = 2\n", "task task-1: imitate: osa/Search-v0 has nothing to imitate"),
        ("[[task]]\nenv = 'osa/Search-v3'\ndagger = 1\n", "dagger: needs --imitate"),
        ("[[task]]\nimitate = -1\n", "imitate must be an integer >= 0"),
        ("[[task]]\ncurriculum = 3\n", "curriculum must be"),
        ("[[task]]\nenv = 'osa/Search-v3'\ncurriculum = '0:2'\n", r"in \[0, 1\]"),
        ("[[task]]\n[task.reward]\nspeed = 1\n", "unknown weight 'speed'"),
        ("[[task]]\nreward_preset = 'fast'\n", "unknown preset 'fast'"),
        ("[[task]]\n[task.ppo]\ngamma = 0\n", r"gamma: expected a number in \(0, 1\]"),
        ("[[task]]\n[task.ppo]\nn_steps = 0.5\n", "n-steps: expected an integer >= 1"),
        ("[[task]]\nalgo = 'A2C'\n[task.ppo]\nn_steps = 64\n", "n-steps: PPO only"),
        ("[[task]]\ninit = 'no-such-model'\n", "init: .*no-such-model"),
        # its folder took sweep.csv's name: an internal error after every training
        ("[[task]]\nname = 'sweep.csv'\nsteps = 1\nenvs = 1\neval_every = 0\n",
         "task 1: name 'sweep.csv' is a file of the sweep's output folder"),
    ],
)
def test_osa_train_sweep_refuses_bad_files_in_one_line(tmp_path, capsys, text, match):
    from envs.cli import main

    f = tmp_path / "s.toml"
    f.write_text(text)
    assert main(["train", "--sweep", str(f), "-o", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    import re

    assert re.search(match, err), err
    assert not (tmp_path / "out").exists()


def test_the_command_lines_recipe_options_are_every_sweep_tasks_defaults(tmp_path):
    """``osa train --sweep FILE --imitate 2 --reward X=Y ...``: the command line's options
    are every task's defaults (a task's own value wins; tables merge key by key), read
    as one training's command line is."""
    from envs.cli import build_parser
    from envs.commands.train import task_of_args
    from envs.sweep import read_sweep, settings_of

    f = tmp_path / "s.toml"
    f.write_text('env = "osa/Search-v3"\n[[task]]\nname = "a"\n[[task]]\nname = "b"\n'
                 'imitate = 1\nimitation_coef = 0.5\n[task.reward]\nlocalised_bonus = 2\n'
                 '[task.ppo]\ngamma = 0.99\n')
    args = build_parser().parse_args(
        ["train", "--sweep", str(f), "-o", "x", "--imitate", "2", "--dagger", "1",
         "--reward", "time_cost_per_s=0.05", "--ent-coef", "0", "--curriculum", "0.2:1"])
    a, b = (settings_of(t) for t in read_sweep(
        f, {k: v for k, v in task_of_args(args).items() if v is not None}))
    assert (a.imitate_episodes, a.imitate_rounds, a.imitation_coef, a.curriculum) == \
        (2, 1, 0.0, (0.2, 1.0))
    assert (b.imitate_episodes, b.imitate_rounds, b.imitation_coef) == (1, 1, 0.5)
    assert a.env_kwargs == {"time_cost_per_s": 0.05}
    assert b.env_kwargs == {"time_cost_per_s": 0.05, "localised_bonus": 2.0}
    assert (a.algo_kwargs["ent_coef"], a.algo_kwargs["gamma"]) == (0.0, 0.995)
    assert (b.algo_kwargs["ent_coef"], b.algo_kwargs["gamma"]) == (0.0, 0.99)


def test_osa_train_scheduler_needs_a_sweep(tmp_path, capsys):
    from envs.cli import main

    assert main(["train", "--scheduler", "tcp://127.0.0.1:1", "-o", str(tmp_path / "o")]) == 2
    assert "--scheduler runs the tasks of a --sweep FILE" in capsys.readouterr().err


def test_a_team_of_one_flies_as_the_policy_itself():
    """``team:adaptive`` on a one-UAV scenario: the same rows as ``adaptive`` (the
    member's view of a one-agent observation is the observation)."""
    from envs.evaluate import run_episode

    base = sim.load_scenario("search-three-mixed")
    scenario = dataclasses.replace(base, search=dataclasses.replace(base.search,
                                                                    budget_s=400.0))
    plain = run_episode(scenario, "adaptive", 2_000_000).rows
    team = run_episode(scenario, "team:adaptive", 2_000_000).rows
    assert [r["policy"] for r in team] == ["team:adaptive"] * 3
    assert [{**r, "policy": ""} for r in plain] == [{**r, "policy": ""} for r in team]
    assert any(r["localised_at_s"] is not None for r in team)
