"""The packages together: a planned pattern, flown by the simulator, replayed by the estimator.

The planner's geometry score must agree with what the estimator then achieves: a helix
around the responder (kappa_H ~ 1) converges to metres, and a straight pass scored with
a large kappa_H is refused by the bootstrap as ``weak_geometry``.
"""

from __future__ import annotations

import numpy as np
import pytest

import sim
from estimator.replay import ReplayOptions, replay_logs
from planner import patterns, scoring


@pytest.fixture(scope="module")
def world():
    sc = sim.load_scenario("paper-ap1f")
    o = sc.world.origin
    ap = sc.world.responders[0]
    return sc, (o.lat_deg, o.lon_deg, o.h_m), ap


def fly_and_replay(sc, traj, tmp_path, seed=3):
    path = tmp_path / f"{traj.name}.jsonl"
    sim.simulate(sc.with_trajectory(traj), seed, path)
    rep = replay_logs([path], ReplayOptions(modes=("baseline", "empirical-r")))
    return [t for t in rep.tracks if t.bssid == sc.world.responders[0].bssid]


def test_helix_flown_and_replayed(world, tmp_path):
    sc, origin, ap = world
    flight = patterns.FlightConfig(speed_m_s=5.0, alt_m=45.0, height_ref="terrain",
                                   origin=origin)
    traj = patterns.helix((ap.e_m + 8.0, ap.n_m - 5.0), 45.0, alt_start_m=40.0,
                          alt_end_m=60.0, turns=3.0, flight=flight)
    ground = sc.world.terrain
    ap_enu = np.array([ap.e_m, ap.n_m, float(ground.height_m(ap.e_m, ap.n_m))])
    score = scoring.score_trajectory(traj, ap_enu, terrain=ground)
    assert score.condition_number < 2.0
    tracks = fly_and_replay(sc, traj, tmp_path)
    assert len(tracks) == 2
    for t in tracks:
        assert t.status == "converged", (t.mode, t.status)
        assert t.err_h_m < 5.0
        assert t.kappa < 10.0  # the bootstrap ran once an arc of the helix was wide enough


def test_straight_pass_refused_like_its_score(world, tmp_path):
    sc, origin, ap = world
    flight = patterns.FlightConfig(speed_m_s=2.0, alt_m=40.0, height_ref="terrain",
                                   origin=origin)
    # a 30 m pass 20 m beside the responder: a line of anchors
    traj = patterns.close_pass((ap.e_m, ap.n_m, 0.0), 20.0, leg_length_m=30.0, flight=flight)
    ground = sc.world.terrain
    ap_enu = np.array([ap.e_m, ap.n_m, float(ground.height_m(ap.e_m, ap.n_m))])
    score = scoring.score_trajectory(traj, ap_enu, terrain=ground)
    assert score.condition_number > 10.0
    for t in fly_and_replay(sc, traj, tmp_path):
        assert t.status in ("weak_geometry", "bootstrapping"), t.status
        assert t.estimate is None
