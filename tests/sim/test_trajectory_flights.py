"""Flying an external Trajectory: heights checked, header H_AGL from the flight flown."""

from __future__ import annotations

import numpy as np
import pytest

import sim
from estimator.logio import read_log
from estimator.records import Trajectory


def orbit(origin, z_m, height_ref="origin", radius=40.0, n=240):
    t = np.linspace(0.0, 120.0, n)
    a = 2 * np.pi * t / 60.0
    p = np.column_stack((40 + radius * np.cos(a), -30 + radius * np.sin(a), np.full(n, z_m)))
    return Trajectory(t, p, origin, height_ref=height_ref, name="orbit")


def test_underground_trajectory_is_refused():
    sc = sim.load_scenario("paper-ap1f")
    o = sc.world.origin
    # heights relative to an origin at ellipsoid height 0: 45 m is ~95 m underground here
    bad = orbit((o.lat_deg, o.lon_deg, 0.0), 45.0)
    with pytest.raises(ValueError, match="below the terrain"):
        sim.simulate(sc.with_trajectory(bad), 0)


def test_header_agl_is_the_height_flown(tmp_path):
    sc = sim.load_scenario("paper-ap1f")
    o = sc.world.origin
    traj = orbit((o.lat_deg, o.lon_deg, o.h_m), 25.0, height_ref="terrain")
    res = sim.simulate(sc.with_trajectory(traj), 1, tmp_path / "o.jsonl")
    hdr = read_log(tmp_path / "o.jsonl").header
    assert hdr.agl_m == pytest.approx(float(np.median(res.vehicle.agl_m)), abs=1e-3)
    assert hdr.agl_m == pytest.approx(25.0, abs=1.0)  # not the preset's 45 m
    # the preset itself keeps its configured height
    assert sim.simulate(sc, 1).header.agl_m == pytest.approx(45.0)
