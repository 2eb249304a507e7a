"""The benchmark suite's presets: a name resolves to the counts, concealment, GNSS and
UAVs it says, wherever a preset name is accepted; the concealed share is exact where
it can be and right in expectation where it cannot; the share hidden by terrain (the
``h`` names, ``[search] hidden_share``) is really out of the take-off point's sight."""

from __future__ import annotations

import numpy as np
import pytest

from sim.gnss import GNSS_PRESETS
from sim.occlusion import J_GRAZING_DB
from sim.realisation import (
    HIDDEN_NU,
    HIDE_MAX_CANDIDATES,
    random_responders,
    realise,
    takeoff_nu,
)
from sim.scenario import ScenarioError, load_scenario, search_scenario
from sim.suite import BUDGET_S, RIDGE, concealed_count, parse_suite_name, suite_names
from sim.terrain import DEFAULT_HILLS


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


# ----------------------------------------------------------- hidden by terrain (h names)


def test_the_c_names_worlds_are_those_of_before():
    """Pinned from the suite before the h names existed: same places, kinds, BSSIDs and
    range offsets (the search-three-mixed preset's too), default hills, no hiding."""
    r = realise(load_scenario("suite/r5-c30-sa-u1"), 2)
    assert [(x.e_m, x.n_m, x.concealment, x.bssid) for x in r.world.responders[:2]] == [
        (217.894, -176.673, "open", "b6:6f:3e:99:0e:87"),
        (147.037, -228.587, "vegetation", "8e:d6:8f:ac:5a:de")]
    assert r.offsets_m[0] == 0.948425015744178 and r.offsets_m[4] == 0.936975245307754
    assert r.hiding is None and r.notes == ()
    assert r.scenario.search.hidden_share is None
    assert r.world.terrain.hills == DEFAULT_HILLS
    m = realise(load_scenario("search-three-mixed"), 2)
    assert [(x.e_m, x.n_m, x.bssid) for x in m.world.responders[1:]] == [
        (-228.587, 168.988, "8e:ac:5a:de:e6:d5"), (-245.726, -69.317, "3e:fb:46:1a:91:07")]
    assert m.offsets_m[2] == 0.690218867126664 and m.hiding is None


def test_h_names_resolve_to_a_hidden_share_on_a_ridge():
    sc = search_scenario("suite/r5-h30-rtk-u2")
    s = sc.search
    assert sc.name == "suite/r5-h30-rtk-u2" and len(sc.agents) == 2
    assert s.hidden_share == pytest.approx(0.3) and s.concealed_share == 0.0
    assert sc.world.terrain.hills == (*DEFAULT_HILLS, *RIDGE) and len(RIDGE) == 9
    hidden = suite_names(hidden=True)
    assert len(hidden) == 54 == len(set(hidden)) and not set(hidden) & set(suite_names())
    assert parse_suite_name("suite/r10-h0-sa-u4").hidden_pct == 0
    for bad in ("suite/r5-h20-sa-u1", "suite/r5-x30-sa-u1"):
        with pytest.raises(ScenarioError) as e:
            load_scenario(bad)
        assert "\n" not in str(e.value) and "{c,h}{0,30,50}" in str(e.value)


def _takeoff_links(r):
    """The occlusion model's obstruction of every responder's link to the take-off
    point at the search height (the radio's own sim.ftm.FtmConfig.obstruction)."""
    sc = r.scenario
    s, t = sc.search, r.world.terrain
    b = np.array([s.start_e_m, s.start_n_m,
                  float(t.height_m(np.array([s.start_e_m]), np.array([s.start_n_m]))[0])
                  + s.height_m])
    p = r.world.responder_enu_m()
    return sc.ftm.obstruction(p, np.broadcast_to(b, p.shape), t)


def test_hidden_responders_are_out_of_sight_of_the_take_off_point_exactly():
    sc10 = load_scenario("suite/r10-h30-sa-u1")
    sc5 = load_scenario("suite/r5-h50-sa-u1")
    for seed in range(15):
        r = realise(sc10, seed)
        ob = _takeoff_links(r)
        hidden = ob.nu >= HIDDEN_NU
        assert hidden.sum() == 3 == r.hiding.wanted == len(r.hiding.hidden)
        assert r.hiding.misplaced == 0
        assert [x.name for x, h in zip(r.world.responders, hidden, strict=True) if h] == list(
            r.hiding.hidden)
        # hidden: the ground above the straight line, a knife-edge loss of 13.9 dB and more
        # (beyond vegetation_debris' 12 dB); the others: the line clears the ground
        assert np.all(ob.loss_db[hidden] >= 13.8) and np.all(ob.excess_m[hidden] > 0.0)
        assert np.all(ob.nu[~hidden] <= 0.0) and np.all(ob.loss_db[~hidden] <= J_GRAZING_DB)
        assert {x.concealment for x in r.world.responders} == {"open"}
    counts = [len(realise(sc5, seed).hiding.hidden) for seed in range(60)]
    assert set(counts) == {2, 3} and np.mean(counts) == pytest.approx(2.5, abs=0.25)
    # without the rule, on the suite's own hills, nothing is hidden from the take-off point
    w = realise(load_scenario("suite/r10-c0-sa-u1"), 0)
    assert np.all(_takeoff_links(w).nu < 0.0)


def test_hiding_is_seeded_and_keeps_the_c0_draws():
    sc = load_scenario("suite/r10-h30-sa-u1")
    a, b, c = realise(sc, 4), realise(sc, 4), realise(sc, 5)
    key = [(x.e_m, x.n_m, x.bssid) for x in a.world.responders]
    assert key == [(x.e_m, x.n_m, x.bssid) for x in b.world.responders]
    assert key != [(x.e_m, x.n_m, x.bssid) for x in c.world.responders]
    assert np.array_equal(a.offsets_m, b.offsets_m)
    # the hiding draws come after the c0 draws: the same BSSIDs, and exactly the
    # responders whose c0 place (on the ridge's terrain) lacks their kind move
    c0 = realise(load_scenario("suite/r10-c0-sa-u1"), 4).world.responders
    assert [x.bssid for x in c0] == [x.bssid for x in a.world.responders]
    nu0 = takeoff_nu(sc, np.array([y.e_m for y in c0]), np.array([y.n_m for y in c0]))
    moved = [(x.e_m, x.n_m) != (y.e_m, y.n_m) for x, y in zip(a.world.responders, c0,
                                                                   strict=True)]
    hid = np.array([x.name in a.hiding.hidden for x in a.world.responders])
    has_kind = np.where(hid, nu0 >= HIDDEN_NU, nu0 <= 0.0)
    assert moved == (~has_kind).tolist() and 0 < sum(moved) < 10


def test_flat_ground_hides_nothing_and_says_so(tmp_path):
    p = tmp_path / "flat.toml"
    p.write_text('name = "flat"\nextends = "suite/r5-h50-sa-u1"\n[world.terrain]\n'
                 'hills = []\nslope_e = 0.0\nslope_n = 0.0\nripple_amplitude_m = 0.0\n')
    r = realise(load_scenario(p), 1)  # bounded: returns after HIDE_MAX_CANDIDATES places
    assert r.hiding.wanted in (2, 3) and r.hiding.hidden == ()
    assert r.hiding.misplaced == r.hiding.wanted and r.hiding.candidates == HIDE_MAX_CANDIDATES
    assert "kept a uniform one" in r.notes[0] and "(wanted " in r.notes[0]
    assert np.all(takeoff_nu(r.scenario, np.array([0.0, 200.0]), np.array([0.0, 240.0])) < 0)


def test_hidden_share_is_checked(tmp_path):
    for extra, msg in (("[search]\nhidden_share = -0.1\n", r"-0\.1 is not in \[0, 1\]"),
                       ("[ftm]\nocclusion = false\n", "needs terrain occlusion")):
        p = tmp_path / "bad.toml"
        p.write_text(f'name = "bad"\nextends = "suite/r5-h30-sa-u1"\n{extra}')
        with pytest.raises(ScenarioError, match=msg) as e:
            load_scenario(p)
        assert "\n" not in str(e.value)
