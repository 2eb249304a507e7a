"""Geometry scoring against hand-computed Fisher information and CRLBs."""

from __future__ import annotations

import math

import numpy as np
import pytest

from estimator.geometry import horizontal_condition_number
from estimator.noise import EmpiricalRConfig, empirical_r_m2
from estimator.records import Trajectory
from planner.models import LogisticLink
from planner.patterns import FlightConfig, close_pass, helix, orbit
from planner.scoring import (
    ScoringConfig,
    fisher_information,
    prior_points,
    range_variance_m2,
    score_anchors,
    score_over_prior,
    score_trajectory,
)

CFG = ScoringConfig()


def _ring(n: int, radius: float, height: float, phase: float = 0.3) -> np.ndarray:
    th = phase + 2 * math.pi * np.arange(n) / n
    return np.column_stack([radius * np.cos(th), radius * np.sin(th), np.full(n, height)])


def test_range_variance_is_empirical_r_at_the_path_loss_rssi() -> None:
    d = np.array([0.5, 1.0, 1.5, 10.0, 74.0, 130.0, 300.0])
    rssi = CFG.link.mean_rssi_dbm(d)
    assert rssi[1] == pytest.approx(-35.0) and rssi[4] == pytest.approx(-35 - 30 * math.log10(74))
    expect = [
        empirical_r_m2(float(x), float(r), 0.12, EmpiricalRConfig())
        for x, r in zip(d, rssi, strict=True)
    ]
    assert np.allclose(range_variance_m2(d, CFG), expect, rtol=1e-12)


def test_response_probability_is_logistic_in_slant_range() -> None:
    m = LogisticLink(reach_m=130.0, width_m=10.0)
    assert m.response_probability(130.0) == pytest.approx(0.5)
    assert m.response_probability(100.0) == pytest.approx(1 / (1 + math.exp(-3.0)))
    assert m.response_probability(1e6) == 0.0 and m.response_probability(-1e6) == 1.0


def test_symmetric_ring_matches_the_closed_form_crlb() -> None:
    """N anchors evenly on a circle, equal slant range, equal sigma:
    J_h = (N/2) n cos^2(el) / sigma^2 I, so CRLB_h = 2 sigma / (cos(el) sqrt(N n));
    z and the bias are then indistinguishable (CRLB_v infinite) unless the bias is known,
    when J_zz = N n sin^2(el) / sigma^2."""
    n_anchors, radius, height = 12, 60.0, 45.0
    anchors = _ring(n_anchors, radius, height)
    dwell = np.full(n_anchors, 2.0)
    d = math.hypot(radius, height)
    n_per = CFG.ranging_rate_hz * 2.0 * CFG.response_probability(d)
    sigma = math.sqrt(range_variance_m2(d, CFG))
    cos_el, sin_el = radius / d, height / d
    s = score_anchors(anchors, dwell, (0.0, 0.0, 0.0), CFG)
    assert s.expected_measurements == pytest.approx(n_anchors * n_per)
    assert s.crlb_h_m == pytest.approx(
        2 * sigma / (cos_el * math.sqrt(n_anchors * n_per)), rel=1e-9
    )
    assert s.crlb_h_known_bias_m == pytest.approx(s.crlb_h_m, rel=1e-9)
    assert math.isinf(s.crlb_v_m) and math.isinf(s.crlb_bias_m)
    assert s.crlb_v_known_bias_m == pytest.approx(
        sigma / (sin_el * math.sqrt(n_anchors * n_per)), rel=1e-9
    )
    j_h = 0.5 * n_anchors * n_per * cos_el**2 / sigma**2
    assert np.allclose(s.fim[:2, :2], j_h * np.eye(2), rtol=1e-9, atol=1e-12)
    assert s.log_det_fim == -math.inf
    assert s.log_det_fim_known_bias == pytest.approx(
        math.log(j_h**2 * n_anchors * n_per * sin_el**2 / sigma**2), rel=1e-9
    )
    assert s.condition_number == pytest.approx(1.0, abs=1e-9)
    assert s.condition_number == horizontal_condition_number(anchors)
    assert math.isinf(s.gdop)  # single-altitude ring: z and bias degenerate
    assert s.hdop == pytest.approx(2.0 / cos_el, rel=1e-9)  # weights normalised to sum 1
    assert s.min_slant_m == pytest.approx(d) and s.min_horizontal_m == pytest.approx(radius)


def test_two_altitudes_make_the_height_observable_with_the_bias() -> None:
    """Two rings (heights h1, h2): the (z, b) block is sum w [[s^2, -s], [-s, 1]] with
    s = sin(el), so var(z) = sum w / (sum w sum w s^2 - (sum w s)^2)."""
    radius = 50.0
    rings = [(_ring(8, radius, 30.0), 30.0), (_ring(8, radius, 90.0, 0.1), 90.0)]
    anchors = np.vstack([r for r, _ in rings])
    dwell = np.ones(len(anchors))
    s = score_anchors(anchors, dwell, (0.0, 0.0, 0.0), CFG)
    w = []
    sines = []
    for _, h in rings:
        d = math.hypot(radius, h)
        w += [8 * CFG.ranging_rate_hz * CFG.response_probability(d) / range_variance_m2(d, CFG)]
        sines += [h / d]
    w, sines = np.array(w), np.array(sines)
    var_z = w.sum() / (w.sum() * (w * sines**2).sum() - (w * sines).sum() ** 2)
    assert s.crlb_v_m == pytest.approx(math.sqrt(var_z), rel=1e-9)
    assert math.isfinite(s.gdop) and math.isfinite(s.log_det_fim)


def test_fim_is_the_sum_of_rank_one_terms() -> None:
    rng = np.random.default_rng(3)
    anchors = rng.uniform(-80, 80, (30, 3)) + np.array([0.0, 0.0, 60.0])
    dwell = rng.uniform(0.2, 1.0, 30)
    ap = np.array([5.0, -3.0, 1.0])
    fim, counts = fisher_information(anchors, dwell, ap, CFG)
    expect = np.zeros((4, 4))
    for u, t in zip(anchors, dwell, strict=True):
        d = np.linalg.norm(ap - u)
        h = np.append((ap - u) / d, 1.0)
        n = CFG.ranging_rate_hz * t * CFG.response_probability(d)
        expect += n / float(range_variance_m2(d, CFG)) * np.outer(h, h)
    assert np.allclose(fim, expect, rtol=1e-12)
    s = score_anchors(anchors, dwell, ap, CFG)
    inv = np.linalg.inv(expect)
    assert s.crlb_h_m == pytest.approx(math.sqrt(inv[0, 0] + inv[1, 1]), rel=1e-8)
    assert s.crlb_v_m == pytest.approx(math.sqrt(inv[2, 2]), rel=1e-8)
    schur = expect[:3, :3] - np.outer(expect[:3, 3], expect[:3, 3]) / expect[3, 3]
    assert s.log_det_fim == pytest.approx(np.linalg.slogdet(schur)[1], rel=1e-10)
    assert s.condition_number == horizontal_condition_number(anchors, counts)


def test_trajectory_scores_use_the_sample_period_as_dwell() -> None:
    f = FlightConfig(speed_m_s=5.0, alt_m=45.0, dt_s=0.5)
    t = orbit((0.0, 0.0), 60.0, flight=f)
    s = score_trajectory(t, (0.0, 0.0, 0.0))
    d = math.hypot(60.0, 45.0)
    assert s.expected_measurements == pytest.approx(
        len(t.t_s) * 0.5 * 4.0 * CFG.response_probability(d), rel=1e-2
    )
    # a helix beats the flat orbit vertically; a straight pass leaves the cross-track
    # direction unobservable
    hx = score_trajectory(
        helix((0.0, 0.0), 60.0, alt_start_m=30.0, alt_end_m=80.0, flight=f), (0, 0, 0)
    )
    assert hx.crlb_v_m < 10.0 and math.isinf(s.crlb_v_m)
    cp = score_trajectory(close_pass((0.0, 0.0), 10.0, flight=f), (0, 0, 0))
    assert math.isinf(cp.crlb_h_m) and math.isinf(cp.condition_number)
    with pytest.raises(ValueError, match="terrain"):
        score_trajectory(
            Trajectory(t_s=t.t_s, enu_m=t.enu_m, origin=t.origin, height_ref="terrain"), (0, 0, 0)
        )


def test_prior_points_reproduce_mean_and_covariance() -> None:
    mean = np.array([10.0, -5.0, 1.0])
    A = np.array([[3.0, 1.0, 0.0], [0.0, 2.0, 0.5], [0.0, 0.0, 1.0]])
    cov = A @ A.T
    pts = prior_points(mean, cov, 6)
    assert np.allclose(pts.mean(axis=0), mean)
    assert np.allclose((pts - mean).T @ (pts - mean) / 6, cov)
    four = prior_points(mean, np.diag([100.0, 25.0, 4.0]), 4)
    assert np.allclose(four[:, 2], 1.0)  # the two largest axes are the horizontal ones
    assert np.allclose(prior_points(mean, cov, 1), mean[None, :])
    r1 = prior_points(mean, cov, 5, np.random.default_rng(7))
    assert np.array_equal(r1, prior_points(mean, cov, 5, np.random.default_rng(7)))


def test_score_over_prior_is_the_mean_over_draws() -> None:
    t = helix((0.0, 0.0), 50.0, alt_start_m=30.0, alt_end_m=70.0, turns=2.0)
    zero = score_over_prior(t, (1.0, 2.0, 0.0), np.zeros((3, 3)), np.random.default_rng(0), 4)
    one = score_trajectory(t, (1.0, 2.0, 0.0))
    assert zero.n_prior_draws == 4
    assert zero.crlb_h_m == pytest.approx(one.crlb_h_m) and np.allclose(zero.fim, one.fim)
    cov = np.diag([100.0, 100.0, 4.0])
    a = score_over_prior(t, (0, 0, 0), cov, np.random.default_rng(1), 8)
    b = score_over_prior(t, (0, 0, 0), cov, np.random.default_rng(1), 8)
    draws = prior_points((0, 0, 0), cov, 8, np.random.default_rng(1))
    assert a.crlb_h_m == b.crlb_h_m
    assert a.crlb_h_m == pytest.approx(np.mean([score_trajectory(t, p).crlb_h_m for p in draws]))



def test_one_altitude_orbit_height_is_unobservable_only_when_centred() -> None:
    """A 60 m orbit at 45 m, 72 samples of 1 s: centred, z and the bias are
    indistinguishable (infinite vertical CRLB); 10 m off centre the bound is finite."""
    th = 2 * math.pi * np.arange(72) / 72
    ring = np.column_stack([60 * np.cos(th), 60 * np.sin(th), np.full(72, 45.0)])
    centred = score_anchors(ring, np.ones(72), (0.0, 0.0, 0.0))
    off = score_anchors(ring + np.array([10.0, 0.0, 0.0]), np.ones(72), (0.0, 0.0, 0.0))
    assert math.isinf(centred.crlb_v_m) and centred.crlb_h_m == pytest.approx(0.889, abs=0.001)
    assert off.crlb_v_m == pytest.approx(295.1, rel=0.01)
    assert off.crlb_h_m == pytest.approx(23.99, rel=0.01)
