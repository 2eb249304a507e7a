"""Two-stage bootstrap (eqs. 5-10) and the geometry check (sec. Discussion)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from estimator.bootstrap import (
    BootstrapConfig,
    BootstrapSample,
    GaussNewtonBootstrap,
    RobustBootstrap,
    stage1_linear_xy,
)
from estimator.geometry import bbox_diagonal_m, horizontal_condition_number

AP = np.array([12.0, -7.0, -44.0])  # ground 45 m under a drone at z ~ 0


def samples_on(points: np.ndarray, ap=AP, noise=None, sigma=0.3, agl=45.0):
    d = np.linalg.norm(points - ap, axis=1)
    if noise is not None:
        d = d + noise
    return [BootstrapSample(tuple(p), float(r), sigma, agl) for p, r in zip(points, d, strict=True)]


def orbit(n=24, radius=40.0, centre=(0.0, 0.0), z=1.0, dz=4.0):
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.column_stack((centre[0] + radius * np.cos(a), centre[1] + radius * np.sin(a),
                            z + dz * np.sin(3 * a)))


def test_recovers_ap_from_noise_free_ranges_to_1cm():
    res = GaussNewtonBootstrap().solve(samples_on(orbit()))
    assert res.ok
    assert np.linalg.norm(np.array(res.position_enu_m) - AP) < 0.01
    assert res.kappa < 2.0


def test_stage1_solves_exact_2d_case():
    # anchors at the AP's height: rho = d exactly (H_AGL = 0), stage 1 is exact
    pts = orbit(dz=0.0, z=AP[2])
    s = samples_on(pts)
    u = np.array([x.anchor_enu_m for x in s])
    d = np.array([x.range_m for x in s])
    pxy = stage1_linear_xy(u, d, np.ones(len(s)), np.zeros(len(s)))
    np.testing.assert_allclose(pxy, AP[:2], atol=1e-9)


def test_waits_for_samples_and_spread():
    boot = GaussNewtonBootstrap()
    assert boot.solve(samples_on(orbit(n=7))).status == "waiting"  # < 8 samples
    tiny = orbit(n=12, radius=5.0)  # 10 m bounding-box diagonal x sqrt(2) = 14.1 < 15
    assert bbox_diagonal_m(tiny) < 15.0
    assert boot.solve(samples_on(tiny)).status == "waiting"


def test_refuses_collinear_pass_as_weak_geometry():
    rng = np.random.default_rng(1)
    t = np.linspace(-14.0, 14.0, 31)  # 28 m straight pass, 31 samples (AP_AB)
    pts = np.column_stack((t, 30.0 + rng.normal(0, 0.28, t.size), np.full(t.size, 1.0)))
    kappa = horizontal_condition_number(pts)
    assert kappa > 10.0
    res = GaussNewtonBootstrap().solve(samples_on(pts))
    assert res.status == "weak_geometry"
    assert res.kappa == pytest.approx(kappa)
    # without the check the paper's bootstrap runs on it (and its answer is not trusted)
    res2 = GaussNewtonBootstrap(BootstrapConfig(max_condition=None)).solve(samples_on(pts))
    assert res2.status in ("ok", "diverged")


def test_condition_number_definition():
    circle = orbit(n=36)
    assert horizontal_condition_number(circle) == pytest.approx(1.0, abs=1e-9)
    # a straight line with lateral rms s: kappa = along-track rms / s
    t = np.linspace(0, 28.0, 2001)
    lat = np.where(np.arange(t.size) % 2 == 0, 0.3, -0.3)
    line = np.column_stack((t, lat))
    along_rms = 28.0 / math.sqrt(12.0)
    assert horizontal_condition_number(line) == pytest.approx(along_rms / 0.3, rel=1e-3)
    assert math.isinf(horizontal_condition_number(np.column_stack((t, np.zeros_like(t)))))
    # an ellipse with axes 2:1 has kappa 2
    a = np.linspace(0, 2 * np.pi, 400, endpoint=False)
    assert horizontal_condition_number(np.column_stack((60 * np.cos(a), 30 * np.sin(a)))) == (
        pytest.approx(2.0, rel=1e-6)
    )


def test_accepts_wide_circular_sweeps_with_noise():
    rng = np.random.default_rng(4)
    pts = np.vstack([orbit(30, 60.0, (0, 0)), orbit(30, 35.0, (40, -10)),
                     orbit(30, 80.0, (10, -30))])
    s = samples_on(pts, noise=rng.normal(0, 0.5, len(pts)), sigma=0.5)
    res = GaussNewtonBootstrap().solve(s)
    assert res.ok and res.kappa < 3.0
    assert np.linalg.norm(np.array(res.position_enu_m)[:2] - AP[:2]) < 2.0


def test_rejects_far_solution_as_diverged():
    # ranges far too long for the geometry: GN runs away beyond 2 x max range
    pts = orbit(n=12, radius=10.0)
    s = [BootstrapSample(tuple(p), 1.0 + 0.01 * i, 0.3, 45.0) for i, p in enumerate(pts)]
    s[0] = BootstrapSample(s[0].anchor_enu_m, 400.0, 0.3, 45.0)
    res = GaussNewtonBootstrap().solve(s)
    if res.ok:
        centroid = pts.mean(axis=0)
        dmax = max(x.range_m for x in s)
        assert np.linalg.norm(np.array(res.position_enu_m) - centroid) <= 2 * dmax
    else:
        assert res.status == "diverged"


def test_robust_bootstrap_resists_nlos_outliers():
    rng = np.random.default_rng(7)
    pts = np.vstack([orbit(20, 50.0), orbit(20, 30.0, (20, 10))])
    noise = rng.normal(0, 0.5, len(pts))
    bad = rng.choice(len(pts), 8, replace=False)
    noise[bad] += rng.uniform(15, 40, bad.size)  # 20 % positive NLoS excess
    s = samples_on(pts, noise=noise, sigma=0.5)
    gn = GaussNewtonBootstrap().solve(s)
    rb = RobustBootstrap().solve(s)
    assert rb.ok
    e_rb = np.linalg.norm(np.array(rb.position_enu_m)[:2] - AP[:2])
    assert e_rb < 2.0
    if gn.ok:
        assert e_rb < np.linalg.norm(np.array(gn.position_enu_m)[:2] - AP[:2])


def _stage1_by_hand(u, d, w, agl):
    """Eqs. (5)-(7) written out: rho^2 with its fallback, differences to sample 1, WLS."""
    rho2 = np.array([di * di - a * a if di * di - a * a > 0 else di * di
                     for di, a in zip(d, agl, strict=True)])
    rows, rhs, wts = [], [], []
    for i in range(1, len(d)):
        rows.append([2 * (u[i, 0] - u[0, 0]), 2 * (u[i, 1] - u[0, 1])])
        rhs.append(rho2[0] - rho2[i] + u[i, 0] ** 2 - u[0, 0] ** 2 + u[i, 1] ** 2
                   - u[0, 1] ** 2)
        wts.append(w[i])
    A, c, W = np.array(rows), np.array(rhs), np.diag(wts)
    return np.linalg.solve(A.T @ W @ A, A.T @ W @ c)


def test_stage1_weights_are_the_mad_scales_of_the_differenced_rows():
    """W = diag(1 / sigma_i^2) of samples 2..N (eq. 7): reweighting changes the answer
    exactly as the hand-written WLS says, and sample 1 (the reference) has no weight."""
    rng = np.random.default_rng(2)
    u = orbit(n=16)
    d = np.linalg.norm(u - AP, axis=1) + rng.normal(0, 1.0, 16)
    agl = np.full(16, 45.0)
    w1 = np.ones(16)
    w2 = np.linspace(0.2, 5.0, 16)
    p1 = stage1_linear_xy(u, d, w1, agl)
    p2 = stage1_linear_xy(u, d, w2, agl)
    np.testing.assert_allclose(p1, _stage1_by_hand(u, d, w1, agl), atol=1e-9)
    np.testing.assert_allclose(p2, _stage1_by_hand(u, d, w2, agl), atol=1e-9)
    assert np.linalg.norm(p1 - p2) > 0.05
    w3 = w2.copy()
    w3[0] = 1e6  # the reference sample's weight is not used
    np.testing.assert_allclose(stage1_linear_xy(u, d, w3, agl), p2, atol=1e-9)


def test_stage1_rho2_falls_back_to_d2_when_not_positive():
    """Eq. (5): rho^2 = d^2 - H_AGL^2, or d^2 where that is not positive."""
    rng = np.random.default_rng(3)
    u = orbit(n=12)
    d = np.linalg.norm(u - AP, axis=1) + rng.normal(0, 0.5, 12)
    agl = np.full(12, 45.0)
    agl[[2, 5, 9]] = d[[2, 5, 9]] + 1.0  # H_AGL above the range: d^2 - H^2 < 0
    got = stage1_linear_xy(u, d, np.ones(12), agl)
    np.testing.assert_allclose(got, _stage1_by_hand(u, d, np.ones(12), agl), atol=1e-9)
    # the fallback matters: with the negative rho^2 kept the answer moves
    rho2 = d * d - agl * agl
    A = np.column_stack((2 * (u[1:, 0] - u[0, 0]), 2 * (u[1:, 1] - u[0, 1])))
    c = rho2[0] - rho2[1:] + u[1:, 0] ** 2 - u[0, 0] ** 2 + u[1:, 1] ** 2 - u[0, 1] ** 2
    no_fallback = np.linalg.solve(A.T @ A, A.T @ c)
    assert np.linalg.norm(no_fallback - got) > 1.0
