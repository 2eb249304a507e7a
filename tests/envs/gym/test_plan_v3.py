"""``osa/Search-v3``: ``osa/Search-v2`` with each responder's recent sigma_H shrink in
the observation, and the hand-written policy that sets a target aside once its close
helix gains nothing (issue 20, item 4: the teacher of the recipe that beats
``adaptive``, docs/rl.md)."""

from __future__ import annotations

import warnings

import gymnasium
import numpy as np
import pytest

import envs  # noqa: F401  (registers the envs)
import sim
from envs.gym.plan import EffortEnv, PlannedEnv
from envs.gym.plan_actions import SHRINK_WINDOW_S, plan_heuristic, sigma_shrink
from envs.loop import run_search
from envs.policies import load_policy
from tests.envs.gym.test_envs import assert_checkers_pass
from tests.envs.gym.test_plan import equal, rollout, small
from tests.envs.gym.test_plan_v2 import recording

ID = "osa/Search-v3"


def test_v3_passes_the_checkers_and_is_v2_with_one_more_key():
    assert_checkers_pass(ID, scenario=small())
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the newest version: no note
        v3 = gymnasium.make(ID).unwrapped
    v2 = PlannedEnv()
    assert isinstance(v3, EffortEnv) and v3.kind == "plan-v3" and v2.kind == "plan-v2"
    assert v3.pilot.actions.names == v2.pilot.actions.names and v3.action_space.n == 18
    s2, s3 = v2.observation_space.spaces, v3.observation_space.spaces
    assert set(s3) - set(s2) == {"sigma_shrink"} and all(s2[k] == s3[k] for k in s2)
    assert s3["sigma_shrink"].shape == (5,)  # one per responder slot


def test_sigma_shrink_against_a_hand_computation():
    h = [(0.0, 4.0), (5.0, 3.0), (10.0, 2.5), (25.0, 2.4)]
    # at 25 s the latest sigma_H at least 20 s old is 3.0 (t = 5 s): 1 - 2.4 / 3.0
    assert sigma_shrink(h, 25.0) == pytest.approx(0.2)
    assert sigma_shrink(h, 30.0) == pytest.approx(1.0 - 2.4 / 2.5)  # then t = 10 s
    assert sigma_shrink(h[:3], 20.0) == pytest.approx(1.0 - 2.5 / 4.0)  # t = 0 s
    assert sigma_shrink(h[:3], 19.0) == 1.0  # nothing 20 s old at 19 s: not settled
    assert sigma_shrink([], 100.0) == 1.0
    assert sigma_shrink([(0.0, 2.0), (30.0, 2.5)], 30.0) == 0.0  # grew: clipped
    assert SHRINK_WINDOW_S == 20.0


def test_the_observed_shrink_is_that_of_the_estimates_seen():
    env = gymnasium.make(ID, scenario=small(900.0, 1)).unwrapped
    teacher = plan_heuristic(env.pilot.actions)
    seen = [step[0]["sigma_shrink"].copy() for step in rollout(env, teacher, world_seed=7)]
    enc = env.pilot.encoder
    # at the end, by hand from the tracker's history of the one responder
    (b,) = enc.slots
    hist = enc.tracker.sigma[b]
    t = env.loop.t_s
    old = [s for tt, s in hist if tt <= t - 20.0][-1]
    assert seen[-1][0] == pytest.approx(max(0.0, 1.0 - hist[-1][1] / old), abs=1e-6)
    assert seen[0][0] == 0.0  # no responder in the slot yet
    assert max(s[0] for s in seen) == 1.0 and min(s[0] for s in seen[1:]) < 0.03


@pytest.fixture(scope="module")
def five():
    return sim.load_scenario("search-five-mixed")


@pytest.mark.parametrize("world", [2_000_000, 2_000_002, 2_000_006])
def test_the_v3_teacher_leaves_settled_targets_and_is_faster_than_adaptive(five, world):
    """Three held-out test worlds of five responders: the teacher sets each target aside
    once its close helix gains < 3 % in 20 s, the estimator's plateau judgement localises
    it while the drone flies on, and every responder is localised well before
    ``adaptive`` (which circles each until it is judged localised)."""
    env = gymnasium.make(ID, scenario=five, max_responders=5, coverage_cells=6).unwrapped
    acts = env.pilot.actions
    teacher = plan_heuristic(acts)
    done = acts.index("done")
    decisions = recording(env)
    states = []
    obs, _ = env.reset(options={"world_seed": world})
    while True:
        a = teacher(obs)
        states.append((a, obs, acts.enc.target, acts.enc.tracker.frozen()))
        obs, _, te, tr, info = env.step(a)
        if te or tr:
            break
    assert te and info["localised"] == 5
    left = [(o, t) for a, o, t, loc in states if a == done and t not in loc]
    assert len(left) >= 3  # most responders are left before they are judged localised
    for o, t in left:
        i = acts.enc.slots.index(t)
        assert o["sigma_shrink"][i] < 0.03  # ... when their sigma_H stopped shrinking
    ours = env.loop.t_s
    theirs = run_search(five, load_policy("adaptive"), world)
    t_adaptive = max(r["localised_at_s"] for r in theirs.responders)
    assert ours < t_adaptive - 100.0, (ours, t_adaptive)
    errs = [e["err_h_m"] for e in info["eval"].values()]
    assert np.median(errs) < 3.0, errs
    assert len(decisions) == len(states)


def test_v3_pickles_at_every_decision_of_a_search():
    """Pickled and restored at every decision (after detections, plans, set-asides and
    localisations): the same search as without."""
    sc = small(600.0, 2)
    env = gymnasium.make(ID, scenario=sc).unwrapped
    act = plan_heuristic(env.pilot.actions)  # reads only the observation
    straight = rollout(env, act, world_seed=1)
    twin = rollout(gymnasium.make(ID, scenario=sc).unwrapped, act, world_seed=1, pickled=True)
    assert len(straight) > 40 and equal(straight, twin)
    names = [env.pilot.actions.names[act(step[0])] for step in straight[:-1]]
    assert {"lawnmower", "helix", "planned", "done"} <= set(names)  # every kind of state
    assert straight[-1][2] and straight[-1][4]["localised"] == 2
