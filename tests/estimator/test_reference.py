"""The unrolled filters (estimator.filters) equal the paper's matrix forms
(estimator.reference): on random well-conditioned cases and on every update of a
replayed flight."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from estimator import filters
from estimator import reference as ref
from estimator.filters import IEKF3D, UKF3D, IekfConfig, UkfConfig, joseph_cov3, joseph_cov4
from estimator.modes import PAPER_MODES
from estimator.replay import ReplayOptions, replay_logs
from tests.estimator.synth import write_flight

ATOL = 1e-12


@st.composite
def gaussians(draw, n: int):
    """A state (position within 100 m, bias within 3 m) and a well-conditioned
    covariance: a random rotation of eigenvalues in [0.5, 100] m^2."""
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    Q, _ = np.linalg.qr(rng.normal(size=(n, n)))
    ev = np.array(draw(st.lists(st.floats(0.5, 100.0), min_size=n, max_size=n)))
    P = (Q * ev) @ Q.T
    P = 0.5 * (P + P.T)
    x = np.array(draw(st.lists(st.floats(-100.0, 100.0), min_size=3, max_size=3)))
    if n == 4:
        x = np.append(x, draw(st.floats(-3.0, 3.0)))
    return x, P


@st.composite
def range_measurements(draw, x: np.ndarray):
    """An anchor 20-200 m from the state in a random direction, a range about h(x)
    (innovations up to 8 m: some fail the NIS gate) and R in [0.01, 10] m^2."""
    v = np.array(draw(st.lists(st.floats(-1.0, 1.0), min_size=3, max_size=3)))
    n = float(np.linalg.norm(v))
    v = v / n if n > 0.1 else np.array([0.6, -0.48, 0.64])
    u = x[:3] + v * draw(st.floats(20.0, 200.0))
    d = ref.h(x, u) + draw(st.floats(-8.0, 8.0))
    return u, d, draw(st.floats(0.01, 10.0))


def _iekf(x, P, cfg=IekfConfig()) -> IEKF3D:
    f = IEKF3D(x[:3], cfg)
    f.x = [float(v) for v in x]
    f.P = P.tolist()
    return f


def _close(got, want, atol: float = ATOL) -> None:
    """``got`` equals ``want`` to ``atol`` times the size of ``want`` (at least 1)."""
    want = np.asarray(want, dtype=float)
    np.testing.assert_allclose(np.asarray(got, dtype=float), want, rtol=0,
                               atol=atol * max(1.0, float(np.max(np.abs(want)))))


def _same_update(res, f, want: ref.Update, atol: float = ATOL) -> None:
    """Equal to ``atol`` times the size of each quantity (at least 1): two orders of the
    same float64 sums differ by round-off proportional to the values (a covariance
    entry of 60 m^2 by ~1e-12 m^2)."""

    def tol(v) -> float:
        return atol * max(1.0, float(np.max(np.abs(v))))

    assert res.accepted == want.accepted
    assert abs(res.nu_m - want.nu) <= tol(want.nu) and abs(res.s_m2 - want.S) <= tol(want.S)
    assert abs(res.nis - want.nis) <= tol(want.nis)
    np.testing.assert_allclose(f.x, want.x, rtol=0, atol=tol(want.x))
    np.testing.assert_allclose(np.array(f.P), want.P, rtol=0, atol=tol(want.P))


@settings(max_examples=150, deadline=None)
@given(st.data(), st.sampled_from([1, 2, 3, 5]))
def test_iekf_update_equals_the_iterated_matrix_form(data, iterations):
    x, P = data.draw(gaussians(4))
    u, d, R = data.draw(range_measurements(x))
    cfg = IekfConfig(iterations=iterations)
    f = _iekf(x, P, cfg)
    res = f.update(tuple(u), d, R)
    _same_update(res, f, ref.iekf_update(x, P, u, d, R, iterations=iterations))


@settings(max_examples=100, deadline=None)
@given(st.data())
def test_joseph_product_form_equals_the_matrix_form_for_any_gain(data):
    """joseph_cov4 / joseph_cov3 (what the filters run) against (I - K H) P (I - K H)^T
    + K R K^T with a gain that need not be the optimal one."""
    for n, fn in ((4, joseph_cov4), (3, joseph_cov3)):
        _, P = data.draw(gaussians(n))
        H = np.array(data.draw(st.lists(st.floats(-1.0, 1.0), min_size=n, max_size=n)))
        K = np.array(data.draw(st.lists(st.floats(-1.0, 1.0), min_size=n, max_size=n)))
        R = data.draw(st.floats(0.01, 10.0))
        got = np.array(fn(P.tolist(), H.tolist(), K.tolist(), (P @ H).tolist(), R))
        _close(got, ref.joseph(P, H, K, R))
        assert np.array_equal(got, got.T)


@settings(max_examples=100, deadline=None)
@given(st.data())
def test_ground_prior_equals_the_linear_kalman_update(data):
    """update_height (eq. 18) of both filters: z_prior with H = e_z in Joseph form."""
    x, P = data.draw(gaussians(4))
    z, Rz = data.draw(st.floats(-80.0, 20.0)), data.draw(st.floats(1.0, 50.0))
    f = _iekf(x, P)
    f.update_height(z, Rz)
    xr, Pr = ref.kalman_update(x, P, [0.0, 0.0, 1.0, 0.0], z, Rz)
    _close(f.x, xr)
    _close(np.array(f.P), Pr)
    g = UKF3D(x[:3])
    g.P = P[:3, :3].tolist()
    g.update_height(z, Rz)
    xr, Pr = ref.kalman_update(x[:3], P[:3, :3], [0.0, 0.0, 1.0], z, Rz)
    _close(g.x, xr)
    _close(np.array(g.P), Pr)


@settings(max_examples=150, deadline=None)
@given(st.data(), st.floats(0.5, 1.0), st.floats(0.0, 3.0), st.floats(0.0, 1.0))
def test_ukf_update_equals_sigma_points_and_unscented_transform(data, alpha, beta, kappa):
    """Well-conditioned transforms (alpha >= 0.5: the weights stay within +-10)."""
    x, P = data.draw(gaussians(3))
    u, d, R = data.draw(range_measurements(x))
    f = UKF3D(x, UkfConfig(alpha=alpha, beta=beta, kappa=kappa))
    f.P = P.tolist()
    res = f.update(tuple(u), d, R)
    _same_update(res, f, ref.ukf_update(x, P, u, d, R, alpha=alpha, beta=beta, kappa=kappa))


def test_sigma_points_reproduce_the_mean_and_covariance():
    x = np.array([1.0, -2.0, 3.0])
    P = np.array([[4.0, 1.0, 0.5], [1.0, 3.0, -0.2], [0.5, -0.2, 9.0]])
    lam, wm, wc = ref.merwe_weights(3, 0.5, 2.0, 0.0)
    X = ref.sigma_points(x, P, lam)
    assert X.shape == (7, 3) and wm.sum() == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(wm @ X, x, atol=1e-12)
    D = X - x
    np.testing.assert_allclose((wc[:, None] * D).T @ D, P, atol=1e-12)
    # the UKF3D's own weights are the same numbers
    w = filters.MerweWeights.make(3, 0.5, 2.0, 0.0)
    assert (w.lam, w.wm0, w.wc0, w.wi) == (lam, wm[0], wc[0], wm[1])


def test_unscented_mean_of_a_linear_function_is_exact():
    """At the paper's alpha = 1e-3 (weights of -1e6 and 1.7e5) the centred sum keeps
    the mean of a linear map exact to rounding."""
    lam, wm, wc = ref.merwe_weights(3, 1e-3, 2.0, 0.0)
    assert wm[0] == pytest.approx(-999999.0, rel=1e-9)
    x = np.array([10.0, -20.0, 30.0])
    X = ref.sigma_points(x, np.diag([25.0, 25.0, 100.0]), lam)
    a = np.array([0.3, -0.5, 0.8])
    mean, var = ref.unscented_transform(X @ a + 7.0, wm, wc)
    assert mean == pytest.approx(a @ x + 7.0, abs=1e-9)
    assert var == pytest.approx(a @ np.diag([25.0, 25.0, 100.0]) @ a, rel=1e-6)


# --------------------------------------------------------------------------- replayed flight


class Recorder:
    """Every IEKF3D / UKF3D range update and ground prior of a replay: inputs, outputs."""

    def __init__(self, monkeypatch) -> None:
        self.calls: list[tuple] = []
        for cls in (IEKF3D, UKF3D):
            monkeypatch.setattr(cls, "update", self._wrap(cls.update, "update"))
            monkeypatch.setattr(cls, "update_height", self._wrap(cls.update_height, "height"))

    def _wrap(self, real, kind):
        calls = self.calls

        def wrapped(f, *args):
            x0, P0 = np.array(f.x), np.array(f.P)
            out = real(f, *args)
            calls.append((kind, f, x0, P0, args, out, np.array(f.x), np.array(f.P)))
            return out

        return wrapped


def test_every_update_of_a_replayed_flight_equals_the_reference(tmp_path, monkeypatch):
    """The six paper modes and robust replayed over a seeded flight; each range update
    and ground prior is recomputed from its own prior by the reference. IEKF and ground
    prior: within 1e-12. UKF (alpha = 1e-3): the transform itself is conditioned by its
    weights (|Wm0| = 1e6) and by its sigma points 1e-3 sqrt(3 P) from the centre, so
    two evaluation orders of the same sums agree only to ~1e-8 (3e-8 at worst on this
    flight, 1.3e-7 over 3000 random cases with P up to 100 m^2); checked at 1e-6 here
    (the well-conditioned transforms above: 1e-12)."""
    rec = Recorder(monkeypatch)
    flight = write_flight(tmp_path / "f.jsonl", seed=11)
    replay_logs([flight], ReplayOptions(modes=(*PAPER_MODES, "robust")))
    n = {"iekf": 0, "ukf": 0, "height": 0, "rejected": 0}
    for kind, f, x0, P0, args, out, x1, P1 in rec.calls:
        if kind == "height":
            xr, Pr = ref.kalman_update(x0, P0, np.eye(f.n)[2], *args)
            _close(x1, xr)
            _close(P1, Pr)
            n["height"] += 1
            continue
        u, d, _ = args
        R = out.r_m2  # the R the update used (Adaptive-R resolves it at the prior)
        if isinstance(f, IEKF3D):
            want = ref.iekf_update(x0, P0, u, d, R, iterations=f.cfg.iterations,
                                   nis_gate=f.cfg.nis_gate)
            atol = ATOL
            n["iekf"] += 1
        else:
            c = f.cfg
            want = ref.ukf_update(x0, P0, u, d, R, alpha=c.alpha, beta=c.beta, kappa=c.kappa,
                                  nis_gate=c.nis_gate)
            atol = 1e-6
            n["ukf"] += 1
        assert out.accepted == want.accepted
        n["rejected"] += not out.accepted
        assert abs(out.nu_m - want.nu) <= atol and abs(out.s_m2 - want.S) <= atol
        np.testing.assert_allclose(x1, want.x, rtol=0, atol=atol)
        np.testing.assert_allclose(P1, want.P, rtol=0, atol=atol)
    assert n["iekf"] > 1000 and n["ukf"] > 300 and n["height"] > 1000 and n["rejected"] > 0
