"""Closed-loop searches on a real site (the site-valley preset: a DEM, the area from a KML,
a power line as keep-outs): whatever policy flies, the drone's TRUE path never enters a
keep-out below its top."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import sim
from envs.loop import ClosedLoop, drive, mission_of
from estimator.geometry import signed_distance_to_polygon_m
from planner.policy import make_policy


def _site(budget_s: float):
    sc = sim.load_scenario("site-valley")
    return dataclasses.replace(sc, search=dataclasses.replace(sc.search, budget_s=budget_s))


def _true_track(scenario, policy: str, seed: int) -> tuple[np.ndarray, ClosedLoop]:
    loop = ClosedLoop(scenario, seed)
    drive(loop, make_policy(policy))  # the loop holds its LoopConfig
    loop.finish()
    return loop.stepper.vehicle_track(0).enu_m, loop  # every vehicle tick (0.05 s)


def test_the_mission_holds_the_keep_outs():
    sc = sim.load_scenario("site-valley")
    m = mission_of(sc)
    # the towers (top 40 m + 10 m above the 45 m search height) are holes; the wires
    # (top 25 m) are flown over, so the policies keep to the search height at least
    assert len(m.area.keep_outs) == 7 and len(m.area.blocking) == 6
    assert m.area.min_height_m == sc.search.height_m


@pytest.mark.parametrize(("policy", "seed", "budget_s"), [
    ("lawnmower", 0, 600.0),
    ("expanding-square", 1, 500.0),
    ("adaptive", 0, 1500.0),
    ("adaptive", 3, 1500.0),
])
def test_the_true_track_never_enters_a_keep_out_below_its_top(policy, seed, budget_s):
    sc = _site(budget_s)
    track, loop = _true_track(sc, policy, seed)
    ground = np.asarray(sc.world.terrain.height_m(track[:, 0], track[:, 1]))
    agl = track[:, 2] - ground
    near = 0
    for k in sc.keepouts:
        if k.is_circle:
            d = np.hypot(track[:, 0] - k.center_enu_m[0], track[:, 1] - k.center_enu_m[1])
            d = d - k.radius_m
        else:
            d = signed_distance_to_polygon_m(k.polygon_enu_m, track[:, :2])
        inside = d < 0.0
        if k.top_m is None or k.top_m + 10.0 > sc.search.height_m:
            assert not inside.any(), f"{policy} seed {seed} enters {k.name}"
        else:  # flown over: above its top wherever the drone is over it
            assert np.all(agl[inside] > k.top_m), f"{policy} seed {seed} under {k.name}"
            near += int(inside.any())
        near += int(d.min() < 60.0)
    assert near >= 2  # the flight came close to the power line (the test is not vacuous)
    assert loop.refused_plans == 0  # every plan the policy made stayed clear (2-D check)
