"""Plan a search pattern, fly it in the simulator, and locate the responder from its log.

    python examples/plan_fly_replay.py [--pattern helix|orbit|circles|close-pass] [--seed N]

The three packages together: ``planner`` makes a pattern around a prior guess of
AP_1F's position (20 m off the truth), scores its geometry; ``sim`` flies it over the
paper-ap1f world and writes the flight log a phone would; ``estimator`` replays the log
in three modes and reports the error against the simulator's truth.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

import sim
from estimator.replay import ReplayOptions, format_table, replay_logs
from planner import patterns, scoring


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pattern", default="helix",
                    choices=("helix", "orbit", "circles", "close-pass"))
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()

    scenario = sim.load_scenario("paper-ap1f")
    origin = scenario.world.origin
    ap1f = scenario.world.responders[0]
    terrain = scenario.world.terrain
    truth = np.array([ap1f.e_m, ap1f.n_m, float(terrain.height_m(ap1f.e_m, ap1f.n_m))])
    prior = truth[:2] + np.array([15.0, -13.0])  # a coarse first detection, 20 m off

    flight = patterns.FlightConfig(speed_m_s=5.0, alt_m=45.0, height_ref="terrain",
                                   origin=(origin.lat_deg, origin.lon_deg, origin.h_m))
    if a.pattern == "helix":
        traj = patterns.helix(prior, 45.0, alt_start_m=35.0, alt_end_m=60.0, turns=3,
                              flight=flight)
    elif a.pattern == "orbit":
        traj = patterns.orbit(prior, 45.0, turns=3, flight=flight)
    elif a.pattern == "circles":
        traj = patterns.concentric_circles(prior, (25.0, 50.0, 75.0), flight=flight)
    else:
        traj = patterns.close_pass((*prior, 0.0), 10.0, flight=flight)
    cfg = scoring.ScoringConfig(link=sim.FtmLink(scenario.ftm))  # the world's own link
    score = scoring.score_trajectory(traj, truth, cfg, terrain=terrain)
    print(f"{a.pattern}: {traj.length_m:.0f} m in {traj.duration_s:.0f} s; kappa_H "
          f"{score.condition_number:.2f}, predicted CRLB {score.crlb_h_m:.2f} m horizontal, "
          f"{score.expected_measurements:.0f} expected ranges")

    log = Path(tempfile.mkdtemp(prefix="osa-example-")) / f"{a.pattern}.jsonl"
    result = sim.simulate(scenario.with_trajectory(traj), a.seed, log)
    print(f"flew it: {result.summary()}\n")
    report = replay_logs([log], ReplayOptions(modes=("baseline", "empirical-r", "robust")))
    print(format_table(report))
    print(f"\nlog: {log}")


if __name__ == "__main__":
    main()
