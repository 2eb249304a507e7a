"""The planner scores and plans with the estimator's one range model
(estimator.measurement): the same ranges and Jacobian rows, and its near-zero rule."""

from __future__ import annotations

import numpy as np

from estimator import measurement as mm
from planner.adaptive import coarse_fit
from planner.optimal import OptimalConfig, _info_entries, _weights
from planner.scoring import ScoringConfig, fisher_information


def test_an_anchor_on_the_ap_adds_bias_information_only():
    rng = np.random.default_rng(7)
    u = rng.uniform(-60, 60, (30, 3)) + np.array([0.0, 0.0, 45.0])
    p = np.array([4.0, -2.0, 0.0])
    cfg = ScoringConfig()
    with_ap, _ = fisher_information(np.vstack([u, p]), np.ones(31), p, cfg)
    without, _ = fisher_information(u, np.ones(30), p, cfg)
    delta = with_ap - without
    assert np.all(np.isfinite(with_ap)) and delta[3, 3] > 0
    delta[3, 3] = 0.0
    assert np.array_equal(delta, np.zeros((4, 4)))


def test_optimal_planner_information_is_the_models():
    """The entries of sum w h h^T equal those built from the model's Jacobian rows
    (no epsilon of the planner's own), in the NumPy form (the CasADi form equals it:
    tests/planner/test_optimal.py, tests/estimator/test_measurement.py)."""
    cfg = OptimalConfig()
    rng = np.random.default_rng(8)
    W = rng.uniform(-100, 100, (40, 3)) + np.array([0.0, 0.0, 60.0])
    s = np.array([3.0, -4.0, 0.5])
    r, H = mm.range_jacobian(s, W, bias=True)
    w = _weights(r, cfg, 2.5)
    full = (H * w[:, None]).T @ H
    iu = [(0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2), (0, 3), (1, 3), (2, 3), (3, 3)]
    np.testing.assert_allclose(_info_entries(W, s, cfg, 2.5), [full[i, j] for i, j in iu],
                               rtol=1e-13)


def test_coarse_fit_scores_the_model_ranges():
    """Ranges the model predicts from a grid cell's centre put the fit on that cell."""
    from planner.area import SearchArea
    from planner.models import FlatTerrain, LogisticLink
    from planner.observation import ResponderView, SearchMission

    area = SearchArea(((-100.0, -100.0), (100.0, -100.0), (100.0, 100.0), (-100.0, 100.0)))
    ap = np.array([40.0, -30.0, 0.0])
    t = np.linspace(0, 2 * np.pi, 12, endpoint=False)
    heard = np.column_stack([60 * np.cos(t), 60 * np.sin(t), np.full(12, 45.0)])
    view = ResponderView(bssid="b", status="bootstrapping", detected_at_s=0.0, n_heard=12,
                         heard_enu_m=tuple(map(tuple, heard)),
                         heard_range_m=tuple(mm.geometric_range_m(ap, heard)))
    mission = SearchMission(area=area, start_enu_m=(0.0, 0.0), budget_s=600.0, height_m=45.0,
                            speed_mps=5.0, terrain=FlatTerrain(), link=LogisticLink(),
                            origin=(36.7, -4.5, 0.0))
    (cx, cy), spread = coarse_fit(view, mission)
    assert abs(cx - 40.0) <= 5.0 and abs(cy + 30.0) <= 5.0 and spread <= 15.0
