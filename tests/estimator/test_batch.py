"""Robust batch refinement (estimator/batch.py) against hand computations."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import integrate

from estimator.batch import (
    BatchConfig,
    GnssErrorModel,
    RangeBuffer,
    _Problem,
    calibrate_scales,
    circle_probability,
    make_layout,
    mirror_xy,
    r_circle_m,
    search_minima,
    solve,
)

AP = np.array([12.0, -7.0, -44.0])


def buffer_of(anchors, ranges, *, t=None, agents=None, acc=0.9, vacc=1.5, fix="3d",
              var_e=None, agl=45.0) -> RangeBuffer:
    buf = RangeBuffer()
    n = len(ranges)
    t = np.arange(n) * 0.25 if t is None else t
    agents = ["uav"] * n if agents is None else agents
    for i in range(n):
        ve = 0.25 if var_e is None else var_e[i]
        buf.append(float(t[i]), tuple(anchors[i]), float(ranges[i]), ve, agl, agents[i], acc,
                   vacc, fix)
    return buf


def orbit(n=60, r=40.0, z=1.0, dz=5.0):
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.column_stack((r * np.cos(a), r * np.sin(a), z + dz * np.sin(3 * a)))


def test_gnss_error_model_sizes_from_accuracy_and_fix():
    g = GnssErrorModel()
    assert g.sigmas_m(0.9, 1.5, "3d") == pytest.approx((1.575, 2.625), abs=1e-12)
    assert g.sigmas_m(0.9, 1.5, None) == pytest.approx((1.575, 2.625), abs=1e-12)
    assert g.sigmas_m(0.2, None, "3d") == pytest.approx((0.5, 0.85), abs=1e-12)  # floor
    assert g.sigmas_m(0.014, 0.02, "rtk_fixed") == pytest.approx((0.021, 0.03), abs=1e-12)
    assert g.sigmas_m(0.01, None, "rtk_fixed") == pytest.approx((0.02, 0.034), abs=1e-12)
    assert g.sigmas_m(1.0, None, "rtk_float") == pytest.approx((1.75, 2.975), abs=1e-12)


def test_residuals_and_jacobian_match_hand_computation():
    u = np.array([[40.0, 0.0, 1.0], [0.0, 35.0, 2.0], [-30.0, -20.0, 0.5], [10.0, -40.0, 3.0]])
    d = np.array([60.0, 70.0, 65.0, 68.0])
    var_e = np.array([0.3, 0.4, 0.5, 0.6])
    data = buffer_of(u, d, var_e=var_e).view()
    lay = make_layout(data)
    assert lay.dim == 3 + 1 + 3 and lay.single_knot
    theta = np.array([12.0, -7.0, -44.0, 0.4, 0.3, -0.2, 0.9])
    s = 0.7
    prob = _Problem(data, lay, np.array([s]), BatchConfig())
    e, diff, r = prob.residuals(theta)
    anchor_true = u - theta[4:7]  # u_i - beta: the logged anchor is truth + beta
    rr = np.linalg.norm(theta[:3] - anchor_true, axis=1)
    np.testing.assert_allclose(e, (rr + 0.4 - d) / (s * np.sqrt(var_e)), atol=1e-12)
    J = prob.jacobian(diff, r)
    H = (theta[:3] - anchor_true) / rr[:, None] / (s * np.sqrt(var_e))[:, None]
    np.testing.assert_allclose(J[:, :3], H, atol=1e-12)
    np.testing.assert_allclose(J[:, 3], 1.0 / (s * np.sqrt(var_e)), atol=1e-12)
    np.testing.assert_allclose(J[:, 4:7], H, atol=1e-12)  # d/d beta = d/d p
    # and against central differences
    num = np.empty_like(J)
    for k in range(7):
        dt = np.zeros(7)
        dt[k] = 1e-6
        num[:, k] = (prob.residuals(theta + dt)[0] - prob.residuals(theta - dt)[0]) / 2e-6
    np.testing.assert_allclose(J, num, atol=1e-7)


def test_gauss_markov_prior_information_of_two_knots():
    # an agent whose ranges span 600 s gets knots 300 s apart: 3 knots, correlation
    # exp(-300 / 1200) between neighbours, per axis sigma 1.575 (h) and 2.625 (v)
    n = 9
    t = np.linspace(0.0, 600.0, n)
    data = buffer_of(orbit(n), np.full(n, 60.0), t=t).view()
    lay = make_layout(data)
    assert lay.knots_t[0].tolist() == [0.0, 300.0, 600.0]
    Jp = lay.prior_jac
    info = Jp.T @ Jp
    rho = np.exp(-np.abs(np.subtract.outer(lay.knots_t[0], lay.knots_t[0])) / 1200.0)
    for axis, s in enumerate((1.575, 1.575)):
        idx = 4 + 3 * np.arange(3) + axis
        np.testing.assert_allclose(info[np.ix_(idx, idx)], np.linalg.inv(s * s * rho),
                                   atol=1e-9)
    # vertical: plus the ground prior once on p_z + the ranges' mean beta_z: ranges at
    # 0, 75, ..., 600 s weigh the knots (1 + .75 + .5 + .25, .25 + ... + .25, ...) / 9
    idx = 4 + 3 * np.arange(3) + 2
    omega = np.array([2.5, 4.0, 2.5]) / 9.0
    expect = np.linalg.inv(2.625**2 * rho) + np.outer(omega, omega) / 25.0
    np.testing.assert_allclose(info[np.ix_(idx, idx)], expect, atol=1e-9)
    # interpolation weights: the range at t = 150 s sits half-way between knots 0 and 1
    k = 2
    assert lay.j0[k] == 0 and lay.j1[k] == 1 and lay.w1[k] == pytest.approx(0.5, abs=1e-12)


def test_scale_calibration_is_shrunk_mad():
    raw = np.array([0.1, -0.3, 0.2, 0.0, 0.5, -0.1, 9.0, 0.3])  # one gross outlier
    agent = np.zeros(raw.size, dtype=np.int64)
    med = np.median(raw)
    smad = 1.4826 * np.median(np.abs(raw - med))
    expect = math.sqrt((8 * smad * smad + 10.0) / 18.0)
    assert calibrate_scales(raw, agent, 1, 10.0)[0] == pytest.approx(expect, abs=1e-12)
    # an agent with fewer than 3 ranges keeps s = 1 (the paper's Empirical-R)
    assert calibrate_scales(raw[:2], agent[:2], 1, 10.0)[0] == 1.0


def test_noise_free_orbit_is_recovered_exactly():
    u = orbit()
    d = np.linalg.norm(u - AP, axis=1) + 0.6
    data = buffer_of(u, d).view()
    sol = solve(data, (0.0, 0.0, -40.0, 0.0))
    # the ground prior (median(z - 45) = -44 +- 5) and the bias prior (0 +- 2 m) pull the
    # noise-free solution by centimetres only
    np.testing.assert_allclose(sol.theta[:2], AP[:2], atol=0.03)
    assert sol.theta[2] == pytest.approx(AP[2], abs=0.15)
    assert sol.bias_m(0) == pytest.approx(0.6, abs=0.15)


def test_single_agent_gnss_bias_is_a_translation_in_the_covariance():
    # one agent, one knot: the ranges depend on p + beta only, so the posterior covariance
    # of p is the range-only one plus the GNSS bias prior (sigma 1.575 h, 2.625 v)
    rng = np.random.default_rng(5)
    u = orbit()
    d = np.linalg.norm(u - AP, axis=1) + 0.6 + rng.normal(0, 0.3, len(u))
    sol = solve(data := buffer_of(u, d).view(), (0.0, 0.0, -40.0, 0.0))
    extra = sol.cov_p - sol.cov_cond[:3, :3]
    np.testing.assert_allclose(extra, np.diag([1.575**2, 1.575**2, 2.625**2]), atol=1e-9)
    assert data.n == 60


def test_r_circle_isotropic_and_one_dimensional_limits():
    s = 1.7
    r = r_circle_m(np.diag([s * s, s * s]))
    assert r == pytest.approx(s * math.sqrt(-2.0 * math.log(0.05)), abs=1e-9)
    assert r_circle_m(np.diag([s * s, 0.0])) == pytest.approx(1.959963984540054 * s, abs=1e-9)
    assert r_circle_m(np.diag([s * s, s * s]), 0.5) == pytest.approx(
        s * math.sqrt(2.0 * math.log(2.0)), abs=1e-9)
    assert r_circle_m(np.zeros((2, 2))) == 0.0


def test_r_circle_anisotropic_holds_95_percent_by_independent_quadrature():
    C = np.array([[5.0, 1.2], [1.2, 0.7]])
    r = r_circle_m(C)
    Ci = np.linalg.inv(C)
    norm = 1.0 / (2 * math.pi * math.sqrt(np.linalg.det(C)))

    def pdf(y, x):
        v = np.array([x, y])
        return norm * math.exp(-0.5 * v @ Ci @ v)

    P, _ = integrate.dblquad(pdf, -r, r, lambda x: -math.sqrt(max(r * r - x * x, 0.0)),
                             lambda x: math.sqrt(max(r * r - x * x, 0.0)),
                             epsabs=1e-13, epsrel=1e-13)
    assert P == pytest.approx(0.95, abs=1e-9)
    assert circle_probability(C, r) == pytest.approx(0.95, abs=1e-12)
    # neither the isotropic shortcut at sigma_H / sqrt 2 per axis nor the major axis alone
    iso = math.sqrt(np.trace(C) / 2.0) * math.sqrt(-2.0 * math.log(0.05))
    assert abs(iso - r) > 0.1


def test_mirror_about_an_axis():
    np.testing.assert_allclose(mirror_xy((3.0, 5.0), np.array([1.0, 2.0]),
                                         np.array([1.0, 0.0])), [3.0, -1.0], atol=1e-12)
    axis = np.array([1.0, 1.0]) / math.sqrt(2.0)
    np.testing.assert_allclose(mirror_xy((2.0, 0.0), np.zeros(2), axis), [0.0, 2.0],
                               atol=1e-12)


def test_straight_pass_has_two_equal_minima():
    # a perfectly straight, level pass: the two sides are exactly symmetric
    s = np.linspace(-14.0, 14.0, 31)
    u = np.column_stack((s, np.full_like(s, 30.0), np.full_like(s, 1.0)))
    ap = np.array([2.0, 12.0, -44.0])
    d = np.linalg.norm(u - ap, axis=1) + 0.5
    data = buffer_of(u, d).view()
    lay = make_layout(data)
    main = solve(data, (2.0, 14.0, -44.0, 0.0), layout=lay)
    minima = search_minima(data, main, straight_pass=True)
    assert len(minima) == 2
    assert sum(m.weight for m in minima) == pytest.approx(1.0, abs=1e-12)
    for m in minima:
        assert m.weight == pytest.approx(0.5, abs=1e-3)
    ys = sorted(m.solution.theta[1] for m in minima)
    assert ys[0] + ys[1] == pytest.approx(60.0, abs=1e-3)  # mirror images about y = 30
    assert ys[0] == pytest.approx(12.0, abs=1.5)  # the truth, up to the z / b trade-off


def test_normal_equations_of_a_long_log_are_built_in_bounded_memory(monkeypatch):
    """A long log (20k ranges over 8 h: 97 GNSS-bias knots, 295 parameters): the
    normal equations were built from the whole dense Jacobian (20k x 295, twice:
    94 MB; over 3 GB for a 1e6-record replay in mode refined); now in row blocks of at most
    NORMAL_BLOCK_BYTES, equal to the one-block sum to rounding."""
    import tracemalloc

    import estimator.batch as batch

    rng = np.random.default_rng(7)
    n = 20_000
    t = np.sort(rng.uniform(0.0, 8 * 3600.0, n))
    a = 2 * np.pi * t / 60.0
    u = np.column_stack((50 * np.cos(a), 50 * np.sin(a), 1.0 + 0 * a))
    d = np.linalg.norm(u - AP, axis=1) + rng.normal(0, 0.5, n)
    data = buffer_of(u, d, t=t).view()
    lay = make_layout(data)
    assert lay.dim == 295
    prob = _Problem(data, lay, np.array([1.0]), BatchConfig())
    theta = np.zeros(lay.dim)
    theta[:3] = AP + 1.0
    e, diff, r = prob.residuals(theta)
    monkeypatch.setattr(batch, "NORMAL_BLOCK_BYTES", 1 << 40)  # one block: the reference
    N1, g1 = prob.normal(theta, e, diff, r)
    monkeypatch.setattr(batch, "NORMAL_BLOCK_BYTES", 4 << 20)
    tracemalloc.start()
    try:
        N, g = prob.normal(theta, e, diff, r)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    np.testing.assert_allclose(N, N1, rtol=1e-10, atol=1e-9 * np.abs(N1).max())
    np.testing.assert_allclose(g, g1, rtol=1e-10, atol=1e-9 * np.abs(g1).max())
    assert peak < 20e6, f"peak {peak / 1e6:.0f} MB"


def test_the_range_buffer_holds_a_range_in_under_a_hundred_bytes():
    """Mode refined keeps every gated range of a responder: as Python lists of floats
    and tuples a range took 224 bytes here (more with values all distinct); packed, 88
    bytes (plus growth slack), and the arrays it gives are the values appended."""
    import tracemalloc

    n = 100_000
    tracemalloc.start()
    try:
        buf = RangeBuffer()
        for i in range(n):
            buf.append(0.25 * i, (40.0, float(i), 45.0), 50.0 + i * 1e-3, 0.25, 45.0, "uav",
                       0.9, None if i % 2 else 1.5, "3d")
        held, _ = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert held < 100 * n, f"{held / n:.0f} bytes a range"
    data = buf.view()
    assert data.u.shape == (n, 3) and data.u[7].tolist() == [40.0, 7.0, 45.0]
    assert data.d[1000] == 51.0 and data.ground[5] == 0.0 and data.t[4] == 1.0
    assert np.isnan(data.vacc[1]) and data.vacc[2] == 1.5 and data.agent.dtype == np.int64
