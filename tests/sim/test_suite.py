"""The benchmark suite's presets: a name resolves to the counts, concealment, GNSS and
UAVs it says, wherever a preset name is accepted; the concealed share is exact where
it can be and right in expectation where it cannot."""

from __future__ import annotations

import numpy as np
import pytest

from sim.gnss import GNSS_PRESETS
from sim.realisation import random_responders, realise
from sim.scenario import ScenarioError, load_scenario, search_scenario
from sim.suite import BUDGET_S, concealed_count, parse_suite_name, suite_names


@pytest.mark.parametrize("name, r, share, gnss, u", [
    ("suite/r10-c30-rtk-u4", 10, 0.3, "rtk", 4),
    ("suite/r5-c50-sa-u2", 5, 0.5, "standalone", 2),
    ("suite/r1-c0-sa-u1", 1, 0.0, "standalone", 1),
])
def test_a_name_resolves_to_what_it_says(name, r, share, gnss, u):
    sc = search_scenario(name)
    assert sc.name == name
    s = sc.search
    assert s.random_responders == r and s.expected_responders == r
    assert s.concealed_share == pytest.approx(share)
    assert s.random_concealment == ("vegetation",)
    assert s.budget_s == BUDGET_S == 900.0
    assert s.area_enu_m[0] == (-250.0, -250.0) and s.area_enu_m[2] == (250.0, 250.0)
    assert len(sc.agents) == u
    assert all(a.kind == "uav" and a.gnss == GNSS_PRESETS[gnss] for a in sc.agents)
    starts = [sc.start_enu_m(i) for i in range(u)]
    assert starts == [(30.0 * i, -240.0) for i in range(u)]
    assert all(s.contains(*p) for p in starts)


def test_every_name_loads_and_bad_names_are_one_line():
    names = suite_names()
    assert len(names) == 54 == len(set(names))
    for n in names[::7]:
        assert load_scenario(n).name == n
    for bad in ("suite/r3-c30-sa-u1", "suite/r5-c30-gps-u1", "suite/r5-c20-sa-u1",
                "suite/r5-c30-sa-u3", "suite/whatever"):
        with pytest.raises(ScenarioError) as e:
            load_scenario(bad)
        assert "\n" not in str(e.value) and "suite/r{1,5,10}" in str(e.value)
    assert parse_suite_name("suite/r5-c30-sa-u1").name == "suite/r5-c30-sa-u1"


def test_concealed_count_rounds_at_random_to_the_share():
    assert concealed_count(0.3, 10, 0.999) == 3 and concealed_count(0.5, 10, 0.0) == 5
    assert concealed_count(0.3, 5, 0.49) == 2 and concealed_count(0.3, 5, 0.5) == 1
    assert concealed_count(0.5, 1, 0.49) == 1 and concealed_count(0.5, 1, 0.5) == 0
    assert concealed_count(0.0, 5, 0.0) == 0 and concealed_count(1.0, 5, 0.99) == 5


def test_worlds_hold_the_concealed_share():
    sc10 = load_scenario("suite/r10-c30-sa-u1")
    sc5 = load_scenario("suite/r5-c30-sa-u1")
    hidden5 = []
    for seed in range(300):
        w10 = random_responders(sc10, np.random.default_rng(seed))
        assert sum(r.concealment == "vegetation" for r in w10) == 3
        assert {r.concealment for r in w10} == {"open", "vegetation"}
        w5 = random_responders(sc5, np.random.default_rng(seed))
        hidden5.append(sum(r.concealment == "vegetation" for r in w5))
    assert set(hidden5) == {1, 2}
    assert np.mean(hidden5) / 5 == pytest.approx(0.3, abs=0.03)  # 1.5 of 5 expected
    # the places do not depend on the share: c0 and c50 put responders in one place
    a = realise(load_scenario("suite/r5-c0-sa-u1"), 7).world.responders
    b = realise(load_scenario("suite/r5-c50-sa-u1"), 7).world.responders
    assert [(r.e_m, r.n_m, r.bssid) for r in a] == [(r.e_m, r.n_m, r.bssid) for r in b]
    assert {r.concealment for r in a} == {"open"}
    assert sum(r.concealment == "vegetation" for r in b) in (2, 3)


def test_suite_extends_and_the_envs_accept_the_names(tmp_path):
    p = tmp_path / "short.toml"
    p.write_text('name = "short"\nextends = "suite/r5-c30-rtk-u1"\n[search]\nbudget_s = 300\n')
    sc = load_scenario(p)
    assert sc.search.budget_s == 300 and sc.search.random_responders == 5
    assert sc.search.concealed_share == pytest.approx(0.3)
    import gymnasium

    import envs  # noqa: F401  (registers the ids)

    env = gymnasium.make("osa/Search-v0", scenario="suite/r5-c30-rtk-u1", max_responders=5)
    try:
        env.reset(seed=3)
        assert len(env.unwrapped.loop.truth) == 5
    finally:
        env.close()


def test_concealed_share_is_checked():
    base = ('name = "x"\n[world.origin]\nlat_deg = 36.7\nlon_deg = -4.5\nh_m = 140.0\n'
            '[search]\narea_enu_m = [[-50.0, -50.0], [50.0, -50.0], [50.0, 50.0]]\n'
            'start_e_m = 10.0\nstart_n_m = -40.0\nrandom_responders = 2\n')
    import tomllib

    from sim.scenario import scenario_from_table

    for extra, msg in (('concealed_share = 1.5\nrandom_concealment = ["vegetation"]\n',
                        r"1\.5 is not in \[0, 1\]"),
                       ('concealed_share = 0.5\nrandom_concealment = ["open", "vegetation"]\n',
                        "concealed kinds only")):
        with pytest.raises(ScenarioError, match=msg):
            scenario_from_table(tomllib.loads(base + extra))
