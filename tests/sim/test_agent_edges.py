"""Agents at the edges the seeds sweep found: a walking ground agent given a UAV's
segment walks its ground track (it stood still at take-off, its reference waiting for
it 43 m up); a wide controller wander does not push a UAV into the ground at take-off
(a FlightError, a traceback of ``osa search``, 0.1 s into the flight)."""

from __future__ import annotations

import numpy as np

from estimator.records import Trajectory
from sim.realisation import realise
from sim.scenario import load_scenario
from sim.stepper import Stepper
from sim.vehicle import UNDERGROUND_TOLERANCE_M

SCENARIO = """
[world.origin]
lat_deg = 36.715
lon_deg = -4.478
h_m = 140.0

[search]
area_enu_m = [[-250.0, -250.0], [250.0, -250.0], [250.0, 250.0], [-250.0, 250.0]]
start_e_m = 0.0
start_n_m = -240.0
random_responders = 1

[[agents]]
name = "uav-1"

[[agents]]
name = "walker"
kind = "ground"
"""


def test_a_walker_follows_a_segment_flown_45_m_up_along_its_ground_track(tmp_path):
    p = tmp_path / "walk.toml"
    p.write_text(SCENARIO)
    sc = load_scenario(p)
    real = realise(sc, 3)
    st = Stepper(real)
    o = sc.world.origin
    traj = Trajectory(np.array([0.0, 25.0]), np.array([[0.0, -240.0, 45.0], [0.0, -40.0, 45.0]]),
                      (o.lat_deg, o.lon_deg, o.h_m), "terrain", "leg")
    st.follow(1, traj)
    st.step_to(60.0)
    walker = st.agents[1].vehicle
    e, n, z = walker._p
    # 60 s at its 1.4 m/s along the leg's ground track, its antenna 1.5 m above ground
    assert 60.0 < n + 240.0 <= 1.4 * 60.0 + 1.0 and abs(e) < 5.0
    assert abs(z - float(sc.world.ground_m(e, n)) - 1.5) < 1e-6


def test_a_wide_wander_does_not_push_a_uav_into_the_ground(tmp_path):
    p = tmp_path / "wander.toml"
    p.write_text(SCENARIO.split("[[agents]]")[0] + "\n[vehicle]\ntracking_sigma_m = 5.0\n")
    sc = load_scenario(p)
    st = Stepper(realise(sc, 4294967301))
    o = sc.world.origin
    traj = Trajectory(np.array([0.0, 25.0]), np.array([[0.0, -240.0, 45.0], [0.0, -40.0, 45.0]]),
                      (o.lat_deg, o.lon_deg, o.h_m), "terrain", "leg")
    st.follow(0, traj)
    st.step_to(40.0)  # raised FlightError at 0.1 s before
    out = st.agents[0].vehicle.out_log.view
    agl = out[:, 2] - sc.world.ground_m(out[:, 0], out[:, 1])
    # it wanders, never into the ground (within the check's tolerance: the ground's slope
    # under the wandered position)
    assert agl.min() > -UNDERGROUND_TOLERANCE_M and np.ptp(out[:, 0]) > 5.0
