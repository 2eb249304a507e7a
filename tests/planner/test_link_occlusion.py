"""The planner's link model knows the terrain's obstruction (planner.models.LinkModel
``response_probability_between``): the simulator's exact profile in NumPy, a smooth
CasADi approximation, the scorer's expected information, the optimal planner's
objective and the adaptive probe."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from planner.adaptive import AdaptiveConfig, Manoeuvres
from planner.area import SearchArea
from planner.models import FlatTerrain, LinkModel, LogisticLink
from planner.observation import SearchMission
from planner.optimal import OptimalConfig, OptimalPlanner
from planner.scoring import ScoringConfig, fisher_information
from sim import FtmConfig, FtmLink, GridTerrain

LINK = FtmLink(FtmConfig())


def ridge_along_e(crest_n_m: float, height_m: float, half_width_m: float) -> GridTerrain:
    """A smooth east-west ridge (cos^2 profile across it) on flat ground, 5 m grid."""
    x = np.arange(-300.0, 301.0, 5.0)
    d = x - crest_n_m
    prof = np.where(np.abs(d) < half_width_m,
                    height_m * np.cos(np.pi * d / (2 * half_width_m)) ** 2, 0.0)
    return GridTerrain(np.tile(prof[:, None], (1, len(x))), -300.0, -300.0, 5.0)


def ridge_along_n(crest_e_m: float, height_m: float, half_width_m: float) -> GridTerrain:
    g = ridge_along_e(crest_e_m, height_m, half_width_m)
    return GridTerrain(g.heights_m.T.copy(), -300.0, -300.0, 5.0)


def test_links_are_link_models_and_equal_the_slant_model_in_the_clear() -> None:
    assert isinstance(LINK, LinkModel) and isinstance(LogisticLink(), LinkModel)
    rng = np.random.default_rng(0)
    p = np.column_stack([rng.uniform(-150, 150, (200, 2)), rng.uniform(30, 80, 200)])
    ap = np.array([10.0, -5.0, 0.5])
    d = np.linalg.norm(p - ap, axis=1)
    for link in (LINK, LogisticLink()):
        between = link.response_probability_between(p, ap, FlatTerrain())
        np.testing.assert_allclose(between, link.response_probability(d), rtol=1e-12)
        assert np.all(np.asarray(link.obstruction_loss_db(p, ap, FlatTerrain())) == 0.0)
    # a loss of L dB is the slant range where the RSSI is L dB lower
    lg = LogisticLink()
    assert lg.response_probability(50.0, loss_db=10.0 * lg.path_loss_exponent) == \
        pytest.approx(lg.response_probability(500.0), rel=1e-12)
    assert LINK.response_probability(80.0, loss_db=0.0) == LINK.response_probability(80.0)


def test_casadi_approximation_follows_the_exact_profile() -> None:
    """Drones at 10-40 m above an east-west ridge 15 m north of the responder: the
    smooth loss is the exact one (to 0.05 dB) where the exact nu is below -1.2, within
    1.5 dB where the ridge blocks the line (nu > 1), within 3 dB about the edge of the
    Fresnel zone (the soft-max overshoots by up to 0.2 log 6); probabilities within 0.1."""
    g = ridge_along_e(15.0, 20.0, 20.0)
    ap = np.array([0.0, 0.0, float(g.height_m(0.0, 0.0)) + 0.5])
    rng = np.random.default_rng(1)
    e, n = rng.uniform(-80, 80, 400), rng.uniform(-80, 80, 400)
    p = np.column_stack([e, n, g.height_m(e, n) + rng.uniform(10, 40, 400)])
    ob = LINK.cfg.obstruction(ap, p, g)
    smooth = np.asarray(LINK.obstruction_loss_db(ca.DM(p.T), ca.DM(ap), g)).ravel()
    diff = np.abs(smooth - ob.loss_db)
    clear, blocked = ob.nu < -1.2, ob.nu > 1.0
    assert clear.sum() > 200 and blocked.sum() > 20
    assert diff[clear].max() < 0.05 and diff[blocked].max() < 1.5 and diff.max() < 3.0
    pe = LINK.response_probability_between(p, ap, g)
    ps = np.asarray(LINK.response_probability_between(ca.DM(p.T), ca.DM(ap), g)).ravel()
    assert np.abs(pe - ps).max() < 0.1
    # symbolic positions build (what the planner differentiates)
    x = ca.SX.sym("x", 3, 4)
    assert LINK.response_probability_between(x, ca.DM(ap), g).shape == (1, 4)


def test_scoring_counts_fewer_ranges_from_behind_a_ridge() -> None:
    g = ridge_along_e(15.0, 20.0, 20.0)
    ap = np.array([0.0, 0.0, float(g.height_m(0.0, 0.0)) + 0.5])
    north = np.array([[0.0, 45.0, float(g.height_m(0.0, 45.0)) + 15.0]])
    south = np.array([[0.0, -45.0, 15.0]])
    blind, aware = ScoringConfig(link=LINK), ScoringConfig(link=LINK, terrain=g)
    for u in (north, south):
        _, c_blind = fisher_information(u, np.ones(1), ap, blind)
        _, c_aware = fisher_information(u, np.ones(1), ap, aware)
        if u is south:  # in view: the same counts
            assert c_aware[0] == pytest.approx(c_blind[0], rel=1e-12)
        else:  # behind the ridge: far fewer
            assert c_aware[0] < 0.05 * c_blind[0]
    # an AP estimate below the ground is judged on the ground (the link's end)
    assert aware.link_point((0.0, 0.0, -20.0))[2] == pytest.approx(ap[2])


def test_optimal_plan_stays_where_the_estimate_is_in_view() -> None:
    """An east-west ridge 15 m north of the estimate hides it from most of the north at
    10-40 m above the ground. The plan that knows the obstruction spends all its time in
    view (the simulator's profile says so); the plan of the same planner blind to it
    flies 12-13 % of its time where the ridge hides the estimate."""
    g = ridge_along_e(15.0, 20.0, 20.0)
    mean = np.array([0.0, 0.0, float(g.height_m(0.0, 0.0)) + 0.5])
    cov = np.diag([100.0, 100.0, 9.0])
    kw = dict(n_waypoints=24, horizon_s=60.0, n_prior_points=4, terrain=g, agl_min_m=10.0,
              agl_max_m=40.0)
    seen = {}
    for aware in (False, True):
        planner = OptimalPlanner(OptimalConfig(
            **kw, scoring=ScoringConfig(link=LINK, terrain=g if aware else None)))
        for start in ((30.0, -30.0), (-40.0, 0.0)):
            st = np.array([*start, float(g.height_m(*start)) + 25.0])
            planner.reset_warm_start()
            res = planner.plan(mean, cov, st)
            assert res.feasible and res.fallback is None
            w = res.trajectory.enu_m
            in_view = LINK.obstruction_loss_db(w, mean, g) == 0.0
            seen[aware, start] = float(in_view.mean())
            if aware:
                assert res.occlusion == "replanned in view"
    for start in ((30.0, -30.0), (-40.0, 0.0)):
        assert seen[True, start] >= 0.97
        assert seen[False, start] <= 0.9
    assert seen[False, (30.0, -30.0)] < seen[True, (30.0, -30.0)]


def _mission(terrain) -> SearchMission:
    return SearchMission(
        area=SearchArea(((-400.0, -400.0), (400.0, -400.0), (400.0, 400.0), (-400.0, 400.0))),
        start_enu_m=(0.0, -300.0), budget_s=1200.0, height_m=40.0, speed_mps=8.0,
        terrain=terrain, link=LINK, origin=(36.7, -4.5, 100.0),
    )


def test_adaptive_probe_picks_a_radius_in_view() -> None:
    """A north-south ridge 35 m west of the likely area hides it from the west of a
    60 m probe orbit; the probe closes in (a steeper view over the ridge) and its
    orbit's mean response probability rises. On flat ground nothing changes."""
    g = ridge_along_n(-35.0, 40.0, 30.0)
    m = Manoeuvres(_mission(g), AdaptiveConfig())
    p0, hidden = m.orbit_view((0.0, 0.0), 60.0, 50.0)
    assert hidden
    (cx, cy), r = m.in_view((0.0, 0.0), 60.0)
    p1, still = m.orbit_view((cx, cy), r, 50.0)
    assert r < 45.0 and p1 > p0 + 0.05
    flat = Manoeuvres(_mission(FlatTerrain()), AdaptiveConfig())
    assert flat.in_view((0.0, 0.0), 60.0) == flat.inside_center((0.0, 0.0), 60.0)
    assert not flat.orbit_view((0.0, 0.0), 60.0, 50.0)[1]
    del still
