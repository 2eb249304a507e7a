"""``osa/Search-v2``: ``osa/Search-v1`` with ``adaptive``'s receding-horizon plan as the
``planned`` action, and the hand-written policy that flies it (``adaptive`` in v2's
actions). v1 itself is unchanged (tests/envs/gym/test_plan.py)."""

from __future__ import annotations

import pickle

import gymnasium
import numpy as np
import pytest

import envs  # noqa: F401  (registers the envs)
from envs.gym.plan import PlanEnv, PlannedEnv
from envs.gym.plan_actions import plan_heuristic
from tests.envs.gym.test_envs import assert_checkers_pass
from tests.envs.gym.test_plan import rollout, small
from tests.envs.test_ppo import assert_train_refuses, one_responder_file

ID = "osa/Search-v2"


def recording(env):
    """The env's decisions, recorded as its pilot makes them."""
    decisions = []
    act = env.pilot.act

    def record(action, obs):
        decisions.append((int(action), obs.t_s, act(action, obs)))
        return decisions[-1][2]

    env.pilot.act = record
    return decisions


def test_v2_passes_the_checkers_and_v1_is_unchanged():
    assert_checkers_pass(ID, scenario=small())
    with pytest.warns(DeprecationWarning, match="osa/Search-v1 is out of date"):
        v1 = gymnasium.make("osa/Search-v1").unwrapped  # Gymnasium's note: v2 exists
    v2 = gymnasium.make(ID).unwrapped
    assert type(v1) is PlanEnv and isinstance(v2, PlannedEnv)
    assert v1.action_space.n == 17 and v2.action_space.n == 18
    assert v2.pilot.actions.names[:17] == v1.pilot.actions.names
    assert v2.pilot.actions.names[17] == "planned" and "planned" not in v1.pilot.actions.names
    assert v1.kind == "plan" and v2.kind == "plan-v2"
    s1, s2 = v1.observation_space.spaces, v2.observation_space.spaces
    assert s1.keys() == s2.keys() and s1["flying"].shape == (17,)
    assert all(s1[k] == s2[k] for k in s1 if k != "flying")


def test_planned_flies_an_optimal_plan_inside_the_area_and_replans_every_20_s():
    env = gymnasium.make(ID, scenario=small(900.0, 1)).unwrapped
    acts = env.pilot.actions
    planned = acts.index("planned")
    teacher = plan_heuristic(acts)
    decisions = recording(env)
    obs, _ = env.reset(options={"world_seed": 5})
    for _ in range(170):  # the teacher until it chooses the plan
        a = teacher(obs)
        if a == planned:
            break
        obs, *_ = env.step(a)
    assert a == planned
    for _ in range(5):  # 25 s of the planned action
        obs, *_ = env.step(planned)
    flown = [(t, d) for a, t, d in decisions if a == planned]
    solved = [(t, d) for t, d in flown if d.replans]
    # solved at the first choice and again 20 s later, not at the 5 s decisions between
    assert len(flown) == 5 and [t - flown[0][0] for t, _ in solved] == [0.0, 20.0]
    area = env.loop.mission.area
    for _, d in solved:
        traj = d.plans[0]
        assert d.note.startswith("planned") and not d.note.endswith("probe")
        assert traj.name == "optimal"  # the CasADi plan (OptimalPlanner's)
        assert area.path_inside(traj.enu_m, 0.0)
        assert np.ptp(traj.enu_m[:, 2]) > 1.0  # through the altitude band, not level
    # the v2 env pickles (without its built planner) and flies on the same
    del env.pilot.act  # the recording
    twin = pickle.loads(pickle.dumps(env))
    assert twin.pilot.actions.optimal.planner is acts.optimal.planner
    o1, r1, *_ = env.step(planned)
    o2, r2, *_ = twin.step(planned)
    assert r1 == r2 and np.array_equal(o1["agent"], o2["agent"])


def test_the_v2_teacher_localises_one_responder():
    env = gymnasium.make(ID, scenario=small(900.0, 1)).unwrapped
    teacher = plan_heuristic(env.pilot.actions)
    decisions = recording(env)
    run = rollout(env, teacher, world_seed=7)
    *_, terminated, _, info = run[-1]
    assert terminated and info["localised"] == 1
    (err,) = [e["err_h_m"] for e in info["eval"].values()]
    assert err < 3.0, err
    names = [env.pilot.actions.names[a] for a, _, _ in decisions]
    assert "planned" in names and names[0] == "lawnmower"
    assert info["flight_time_s"] < 600.0


@pytest.mark.parametrize("env_id,kind", [(ID, "plan-v2"), ("osa/Search-v3", "plan-v3")])
def test_osa_train_v2_and_v3_imitate_their_teacher_with_its_gamma(env_id, kind, tmp_path, capsys):
    pytest.importorskip("stable_baselines3")
    import json

    from stable_baselines3 import PPO

    from envs.cli import main
    from envs.policies import load_policy

    toml = one_responder_file(tmp_path, 200.0)
    out = tmp_path / "m"
    assert main(["train", "--env", env_id, "--scenario", str(toml), "--steps", "256",
                 "--envs", "1", "--eval-every", "0", "--checkpoint-every", "0",
                 "--imitate", "2", "--gamma", "0.999", "--no-progress", "-o", str(out)]) == 0
    imitated = json.loads((out / "imitation.json").read_text())
    # 2 episodes of at most 200 s / 5 s (one ends when its responder is localised)
    assert imitated["episodes"] == 2 and 40 < imitated["decisions"] < 80
    assert imitated["agreement"] > 0.7
    meta = json.loads((out / "osa-model.json").read_text())
    assert meta["env_id"] == env_id and meta["kind"] == kind
    assert PPO.load(str(out / "model.zip"), device="cpu").gamma == 0.999
    policy = load_policy(f"ppo:{out}")  # flies with v2's (v3's) actions
    policy.reset(sim_mission(toml), None)
    assert policy.pilot.action_space.n == 18 and policy.pilot.actions.planned
    assert policy.pilot.actions.shrink == (kind == "plan-v3")
    assert ("sigma_shrink" in policy.pilot.observation_space.spaces) == (kind == "plan-v3")
    assert_train_refuses(main, ((["--env", env_id, "--gamma", "0"], r"in \(0, 1\]"),
                                (["--env", env_id, "--gamma", "1.5"], r"\(0, 1\]"),
                                (["--env", env_id, "--algo", "A2C", "--gamma", "0.99"],
                                 "PPO only")),
                         tmp_path / "x", capsys)


def sim_mission(toml):
    """The search mission of world 0 of a scenario file."""
    import sim
    from envs.loop import ClosedLoop

    return ClosedLoop(sim.load_scenario(toml), 0).mission
