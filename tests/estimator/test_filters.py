"""IEKF3D and UKF3D updates against hand computations and the matrix forms of
estimator.reference (eqs. 12-18); tests/estimator/test_reference.py holds them equal
on random cases and on a replayed flight."""

from __future__ import annotations

import math

import numpy as np
import pytest

from estimator import reference as ref
from estimator.filters import (
    IEKF3D,
    UKF3D,
    FilterError,
    IekfConfig,
    MerweWeights,
    UkfConfig,
    joseph_cov3,
    joseph_cov4,
)

ANCHOR = (31.0, -12.0, 46.5)


def test_iekf_update_matches_hand_computation():
    cfg = IekfConfig()
    f = IEKF3D((12.0, 7.0, -40.0), cfg)
    f.P = [[25.0, 1.5, -2.0, 0.3], [1.5, 20.0, 0.7, -0.2], [-2.0, 0.7, 90.0, 0.1],
           [0.3, -0.2, 0.1, 4.0]]
    f.x[3] = 0.4
    x0, P0 = list(f.x), np.array(f.P)
    d, R = 97.0, 0.8
    f.predict()
    res = f.update(ANCHOR, d, R)
    xr, Pr, nu, S, _ = ref.iekf_update(*ref.predict(x0, P0, cfg.q_diag), ANCHOR, d, R)[1:]
    assert res.accepted
    np.testing.assert_allclose(f.x, xr, atol=1e-9)
    np.testing.assert_allclose(np.array(f.P), Pr, atol=1e-9)
    assert res.nu_m == pytest.approx(nu, abs=1e-9)
    assert res.s_m2 == pytest.approx(S, abs=1e-9)
    assert res.nis == pytest.approx(nu * nu / S, abs=1e-9)
    # symmetric by construction
    P = np.array(f.P)
    assert np.array_equal(P, P.T)


def test_iekf_single_iteration_is_the_ekf():
    f = IEKF3D((0.0, 0.0, 0.0), IekfConfig(iterations=1))
    x0, P0 = list(f.x), np.array(f.P)
    f.predict()
    f.update((40.0, 30.0, 45.0), 71.0, 0.5)
    _, xr, Pr, *_ = ref.iekf_update(*ref.predict(x0, P0, IekfConfig().q_diag),
                                    (40.0, 30.0, 45.0), 71.0, 0.5, iterations=1)
    np.testing.assert_allclose(f.x, xr, atol=1e-9)
    np.testing.assert_allclose(np.array(f.P), Pr, atol=1e-9)


def test_iekf_nis_gate_rejects_and_leaves_state():
    f = IEKF3D((0.0, 0.0, 0.0))
    f.predict()
    x_before, P_before = list(f.x), [row[:] for row in f.P]
    u = (50.0, 0.0, 0.0)
    # predicted range 50 m, S = H P H^T + R = 25.01 + 4.0001 + R; pick nu so NIS = 10 > 9
    S = (25.0 + 0.01) + (4.0 + 1e-4) + 1.0
    d = 50.0 + math.sqrt(10.0 * S)
    res = f.update(u, d, 1.0)
    assert not res.accepted
    assert res.nis == pytest.approx(10.0, rel=1e-12)
    assert f.x == x_before and f.P == P_before
    # just inside the gate: NIS = 8.9 is accepted
    d = 50.0 + math.sqrt(8.9 * S)
    assert f.update(u, d, 1.0).accepted


@pytest.mark.parametrize("n, fn", [(4, joseph_cov4), (3, joseph_cov3)])
def test_joseph_product_form_with_a_non_optimal_gain(n, fn):
    """The covariance update the filters run, with a gain that is not P H^T / S: the
    product (Joseph) form stays exact, the subtractive (I - K H) P does not."""
    rng = np.random.default_rng(3)
    A = rng.normal(size=(n, n))
    P = A @ A.T + 4 * np.eye(n)
    H = rng.normal(size=n)
    K = rng.normal(size=n)  # a non-optimal gain
    R = 0.7
    Pn = np.array(fn(P.tolist(), H.tolist(), K.tolist(), (P @ H).tolist(), R))
    np.testing.assert_allclose(Pn, ref.joseph(P, H, K, R), atol=1e-9)
    assert np.array_equal(Pn, Pn.T)
    subtractive = (np.eye(n) - np.outer(K, H)) @ P
    assert np.abs(subtractive - ref.joseph(P, H, K, R)).max() > 1.0
    # with the optimal gain both forms agree
    Ko = P @ H / (H @ P @ H + R)
    Po = np.array(fn(P.tolist(), H.tolist(), Ko.tolist(), (P @ H).tolist(), R))
    np.testing.assert_allclose(Po, (np.eye(n) - np.outer(Ko, H)) @ P, atol=1e-9)


def test_filters_update_their_covariance_through_the_joseph_helpers(monkeypatch):
    """IEKF3D.update and both ground priors call joseph_cov4 / joseph_cov3 (the helpers
    tested above are the code that runs) and keep exactly what they return."""
    import estimator.filters as filters_mod

    calls = []

    def spy(name):
        real = getattr(filters_mod, name)

        def wrapped(P, H, K, q, R):
            out = real(P, H, K, q, R)
            calls.append((name, tuple(H), out))
            return out

        return wrapped

    monkeypatch.setattr(filters_mod, "joseph_cov4", spy("joseph_cov4"))
    monkeypatch.setattr(filters_mod, "joseph_cov3", spy("joseph_cov3"))
    f = IEKF3D((12.0, 7.0, -40.0))
    f.predict()
    assert f.update(ANCHOR, 97.0, 0.8).accepted
    name, H, out = calls[-1]
    assert name == "joseph_cov4" and H[3] == 1.0 and f.P == out
    f.update_height(-44.0, 25.0)
    assert calls[-1][0] == "joseph_cov4" and calls[-1][1] == (0.0, 0.0, 1.0, 0.0)
    assert f.P == calls[-1][2]
    u = UKF3D((12.0, 7.0, -40.0))
    u.update_height(-44.0, 25.0)
    assert calls[-1][0] == "joseph_cov3" and u.P == calls[-1][2]
    assert len(calls) == 3


@pytest.mark.parametrize("kind", ["iekf", "ukf"])
def test_innovation_noise_models_see_nu_and_hph_at_the_prior(kind):
    """A callable R (Adaptive-R, eq. 24) is evaluated once, with the innovation and its
    predicted variance at the prior, and the R it returns is the R of the update."""
    f = IEKF3D((12.0, 7.0, -40.0)) if kind == "iekf" else UKF3D((12.0, 7.0, -40.0))
    f.predict()
    nu0, hph0 = f.innovation(ANCHOR, 97.0)
    seen = []

    def r_of(nu, hph):
        seen.append((nu, hph))
        return 0.5 + 0.1 * nu * nu

    res = f.update(ANCHOR, 97.0, r_of)
    assert len(seen) == 1
    assert seen[0][0] == pytest.approx(nu0, abs=1e-12)
    assert seen[0][1] == pytest.approx(hph0, abs=1e-9)
    assert res.r_m2 == pytest.approx(0.5 + 0.1 * nu0 * nu0, abs=1e-12)
    assert res.s_m2 == pytest.approx(hph0 + res.r_m2, abs=1e-9)
    # the same update with that R as a number
    g = IEKF3D((12.0, 7.0, -40.0)) if kind == "iekf" else UKF3D((12.0, 7.0, -40.0))
    g.predict()
    g.update(ANCHOR, 97.0, res.r_m2)
    np.testing.assert_allclose(np.array(f.P), np.array(g.P), atol=1e-12)
    np.testing.assert_allclose(f.x, g.x, atol=1e-12)


def test_merwe_weights_paper_values():
    w = MerweWeights.make(3, 1e-3, 2.0, 0.0)
    lam = 1e-6 * 3 - 3
    assert w.lam == pytest.approx(lam, abs=1e-15)
    assert sum(w.wm) == pytest.approx(1.0, abs=1e-9)
    assert w.wm0 == pytest.approx(lam / (3 + lam), rel=1e-12)
    assert w.wc0 == pytest.approx(lam / (3 + lam) + 1 - 1e-6 + 2.0, rel=1e-12)
    assert w.wi == pytest.approx(1 / (2 * (3 + lam)), rel=1e-12)
    assert len(w.wm) == 7
    # Wc sums to 1 + (1 - alpha^2 + beta)
    assert sum(w.wc) == pytest.approx(1.0 + 1.0 - 1e-6 + 2.0, abs=1e-6)


def test_ukf_update_matches_hand_computation():
    f = UKF3D((12.0, 7.0, -40.0))
    f.P = [[25.0, 1.5, -2.0], [1.5, 20.0, 0.7], [-2.0, 0.7, 90.0]]
    x0, P0 = list(f.x), np.array(f.P)
    f.predict()
    res = f.update(ANCHOR, 97.0, 0.8)
    _, xr, Pr, nu, S, _ = ref.ukf_update(*ref.predict(x0, P0, UkfConfig().q_diag), ANCHOR,
                                         97.0, 0.8)
    assert res.accepted
    # alpha = 1e-3 weights of +-1e6 limit either form's own precision to ~1e-8
    np.testing.assert_allclose(f.x, xr, atol=1e-7)
    np.testing.assert_allclose(np.array(f.P), Pr, atol=1e-6)
    assert res.nu_m == pytest.approx(nu, abs=1e-7)
    assert res.s_m2 == pytest.approx(S, abs=1e-6)


def test_ukf_matches_ekf_on_nearly_linear_case():
    """Far anchor, small covariance: range is nearly linear, UKF = EKF to < 1 mm."""
    p0 = (10.0, 20.0, 0.0)
    u = (2010.0, 1520.0, 45.0)  # 2.5 km away: curvature negligible over the prior
    ukf = UKF3D(p0, UkfConfig(p0_diag=(1.0, 1.0, 1.0)))
    ekf = IEKF3D(p0, IekfConfig(iterations=1, p0_diag=(1.0, 1.0, 1.0, 0.0),
                               q_diag=(0.01, 0.01, 0.04, 0.0)))
    ekf.P[3][3] = 1e-300  # bias frozen at zero: a 3-state EKF
    d = math.dist(p0, u) + 1.3
    for f in (ukf, ekf):
        f.predict()
        assert f.update(u, d, 0.5).accepted
    np.testing.assert_allclose(ukf.x, ekf.x[:3], atol=1e-3)
    np.testing.assert_allclose(np.array(ukf.P), np.array(ekf.P)[:3, :3], atol=1e-3)


def test_filter_error_on_invalid_state():
    f = IEKF3D((0.0, 0.0, 0.0))
    f.P[0][0] = -1.0
    with pytest.raises(FilterError):
        f.update_height(0.0, 25.0)
