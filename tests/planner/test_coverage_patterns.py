"""Coverage patterns are objects a PatternPolicy flies; names map to them in
planner/policy.py only."""

from __future__ import annotations

import numpy as np
import pytest

from planner.area import SearchArea
from planner.coverage import ExpandingSquare, Lawnmower, PatternPolicy, Sweep
from planner.models import FlatTerrain, LogisticLink
from planner.observation import SearchMission
from planner.policy import PATTERNS, POLICIES, make_policy

AREA = SearchArea(((-200.0, -150.0), (250.0, -150.0), (250.0, 200.0), (-200.0, 200.0)))
MISSION = SearchMission(area=AREA, start_enu_m=(-180.0, -140.0), budget_s=900.0, height_m=45.0,
                        speed_mps=6.0, terrain=FlatTerrain(), link=LogisticLink(),
                        origin=(36.7, -4.5, 0.0))


def test_patterns_give_the_areas_sweeps():
    lm = Lawnmower().waypoints(MISSION, 40.0, 30.0)
    assert np.array_equal(lm, AREA.sweep(40.0, 30.0, start=MISSION.start_enu_m))
    es = ExpandingSquare().waypoints(MISSION, 40.0, 0.0)
    assert np.array_equal(es, AREA.expanding_square(AREA.centroid_m, 40.0, 0.0))
    assert not np.array_equal(np.asarray(lm[:3]), np.asarray(es[:3]))


def test_policies_fly_their_pattern_objects():
    assert POLICIES == ("lawnmower", "expanding-square", "adaptive")
    for name, pattern in PATTERNS.items():
        p = make_policy(name, spacing_m=50.0)
        assert isinstance(p, PatternPolicy) and p.pattern == pattern and p.name == name
        p.reset(MISSION, np.random.default_rng(0))
        assert np.array_equal(p.waypoints, pattern.waypoints(MISSION, 50.0, 0.0))
    # a policy over a pattern object needs no name in the registry
    custom = PatternPolicy(ExpandingSquare(), spacing_m=70.0, heading_deg=45.0)
    custom.reset(MISSION, np.random.default_rng(0))
    assert np.array_equal(custom.waypoints, AREA.expanding_square(AREA.centroid_m, 70.0, 45.0))
    # the adaptive policy's sweep is the lawnmower's
    sw = Sweep(MISSION, 50.0, 10.0)
    assert np.array_equal(sw.waypoints, Lawnmower().waypoints(MISSION, 50.0, 10.0))
    with pytest.raises(ValueError, match="unknown policy"):
        make_policy("spiral")
