"""The one range model h(p, u, b) = |p - u| + b (eqs. 13-14): its three forms agree bit
for bit, its Jacobian is h's derivative, and its near-zero rule holds wherever it runs."""

from __future__ import annotations

import math

import casadi as ca
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from estimator import measurement as mm
from estimator.bootstrap import gauss_newton_3d
from estimator.filters import IEKF3D, UKF3D

finite = st.floats(-1e4, 1e4, allow_nan=False, allow_infinity=False)
tiny = st.floats(-1e-8, 1e-8, allow_nan=False, allow_infinity=False)


@settings(max_examples=300, deadline=None)
@given(st.lists(st.one_of(finite, tiny), min_size=3, max_size=3),
       st.lists(finite, min_size=3, max_size=3))
def test_numpy_and_scalar_forms_give_the_same_bits(diff, u):
    dx, dy, dz = diff
    r = mm.range_of(dx, dy, dz)
    r2, gx, gy, gz = mm.range_and_unit(dx, dy, dz)
    assert r == r2 == float(mm.range_of_difference(np.array(diff)))
    J = mm.jacobian_rows(np.array([diff]), np.array([r]))
    assert (gx, gy, gz) == tuple(J[0])
    # h(p, u) from positions: the difference p - u, then the same arithmetic
    p = np.array(u) + np.array(diff)
    pu = p - np.array(u)
    assert float(mm.geometric_range_m(p, u)) == mm.range_of(*pu)


def test_forms_equal_the_plain_norm_away_from_the_anchor():
    """What every caller computed before (np.linalg.norm, sqrt of the summed squares):
    the same bits for |p - u| >= 1 nm."""
    rng = np.random.default_rng(4)
    D = rng.normal(size=(20000, 3)) * 10.0 ** rng.uniform(-9.5, 4, (20000, 1))
    r = mm.range_of_difference(D)
    plain = np.linalg.norm(D, axis=1)
    away = plain >= mm.RANGE_FLOOR_M
    assert 100 < np.count_nonzero(~away) < 2000  # some near the anchor, floored
    assert np.array_equal(r[away], plain[away])
    assert np.array_equal(r[away], np.sqrt((D * D).sum(axis=1))[away])
    assert np.all(r[~away] == math.sqrt(mm.RANGE_FLOOR2_M2))
    assert [mm.range_of(*d) for d in D.tolist()] == r.tolist()


def test_casadi_form_gives_the_same_bits_and_finite_derivatives():
    rng = np.random.default_rng(5)
    D = rng.normal(size=(3, 500)) * 10.0 ** rng.uniform(-12, 4, 500)
    D[:, :3] = 0.0  # anchors on the estimate
    X = ca.SX.sym("x", 3, 500)
    d2, d = mm.range_casadi(X)
    f = ca.Function("f", [X], [d2, d, ca.jacobian(ca.sum2(d), X)])
    r2, r, J = f(D)
    assert np.array_equal(np.asarray(r).ravel(), mm.range_of_difference(D.T))
    assert np.array_equal(np.asarray(r2).ravel(),
                          np.maximum((D * D).sum(axis=0), mm.RANGE_FLOOR2_M2))
    J = np.asarray(J).reshape(500, 3)  # row i: d r_i / d D[:, i] (column-major vec)
    assert np.all(np.isfinite(J)) and np.array_equal(J[:3], np.zeros((3, 3)))
    np.testing.assert_allclose(J[3:], mm.jacobian_rows(D.T, mm.range_of_difference(D.T))[3:],
                               rtol=1e-15, atol=0)


def test_jacobian_is_the_derivative_of_h():
    """Eq. (14) against central differences of eq. (13), with and without whitening."""
    rng = np.random.default_rng(6)
    u = rng.uniform(-80, 80, (40, 3)) + np.array([0.0, 0.0, 45.0])
    p, b, step = np.array([3.0, -7.0, 0.5]), 0.4, 1e-5
    r, J = mm.range_jacobian(p, u, bias=True)
    assert np.array_equal(mm.predicted_range_m(p, u, b), r + b)
    for j in range(3):
        e = np.eye(3)[j] * step
        fd = (mm.predicted_range_m(p + e, u, b) - mm.predicted_range_m(p - e, u, b)) / (2 * step)
        np.testing.assert_allclose(J[:, j], fd, atol=1e-9)
    assert np.all(J[:, 3] == 1.0)
    w = rng.uniform(0.5, 2.0, 40)
    _, Jw = mm.range_jacobian(p, u, bias=True, scale=w)
    np.testing.assert_allclose(Jw, J * w[:, None], rtol=1e-15)
    np.testing.assert_allclose(np.linalg.norm(J[:, :3], axis=1), 1.0, rtol=1e-15)


def test_near_zero_rule_anchor_on_the_estimate():
    """|p - u| < 1 nm: the range is 1 nm, the unit vector (p - u) / 1 nm (zero at p = u):
    no NaN, no direction information, the bias still observed."""
    p = np.array([12.0, -4.0, 30.0])
    assert mm.range_of(0.0, 0.0, 0.0) == pytest.approx(mm.RANGE_FLOOR_M, rel=1e-15)
    assert mm.range_and_unit(0.0, 0.0, 0.0)[1:] == (0.0, 0.0, 0.0)
    assert float(mm.predicted_range_m(p, p, 0.7)) == pytest.approx(0.7 + 1e-9, abs=1e-15)
    _, J = mm.range_jacobian(p, np.array([p, p + 1e-12, p + 5.0]), bias=True)
    np.testing.assert_array_equal(J[0], [0.0, 0.0, 0.0, 1.0])
    assert np.all(np.isfinite(J)) and np.all(np.abs(J[1, :3]) < 2e-3)  # 1e-12 / 1e-9 / sqrt 3
    np.testing.assert_allclose(J[2, :3], [-1 / math.sqrt(3)] * 3, rtol=1e-15)


def test_near_zero_rule_in_the_filters():
    """An IEKF range from an anchor on its estimate moves the bias only (H = e_b); the
    UKF's sigma points stay finite; nothing becomes NaN."""
    f = IEKF3D((10.0, 20.0, -30.0))
    f.predict()
    res = f.update((10.0, 20.0, -30.0), 1.5, 0.5)
    assert res.accepted and f.x[:3] == [10.0, 20.0, -30.0]
    P = np.array(f.P)
    # the bias moved by K_b nu with nu = 1.5 - 1e-9 and K_b = P_bb / (P_bb + R)
    pbb = 4.0 + 1e-4
    assert f.x[3] == pytest.approx(pbb / (pbb + 0.5) * (1.5 - 1e-9), rel=1e-12)
    assert np.all(np.isfinite(P)) and P[3, 3] == pytest.approx(pbb * 0.5 / (pbb + 0.5))
    g = UKF3D((10.0, 20.0, -30.0))
    g.predict()
    out = g.update((10.0, 20.0, -30.0), 1.5, 0.5)
    assert np.all(np.isfinite(g.x)) and np.all(np.isfinite(g.P)) and math.isfinite(out.nis)


def test_near_zero_rule_in_the_bootstrap():
    """A Gauss-Newton row of an anchor on the iterate contributes nothing to the
    position normal matrix (J row = 0): the fit is the one without it."""
    rng = np.random.default_rng(7)
    u = rng.uniform(-60, 60, (30, 3)) + np.array([0.0, 0.0, 45.0])
    p = np.array([4.0, -2.0, 0.0])
    d = np.linalg.norm(u - p, axis=1)
    got, _ = gauss_newton_3d(p, np.vstack([u, p]), np.append(d, 3.0), np.ones(31))
    want, _ = gauss_newton_3d(p, u, d, np.ones(30))
    np.testing.assert_allclose(got, want, atol=1e-12)
