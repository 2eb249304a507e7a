"""The paper's filter maths as the paper writes it: matrices, one function per block.

This is the reference implementation of sec. Sequential Bayesian Filtering, short and
in textbook form, for a reader to hold against the paper. The filters that run
(:mod:`estimator.filters`) compute the same thing with unrolled scalar arithmetic for
speed; tests/estimator/test_reference.py holds them equal to these functions on random
cases and on a replayed flight. Nothing here is used by the pipeline.

- :func:`iekf_update`: the iterated EKF update of IEKF3D with its NIS gate and the
  Joseph covariance (eqs. 13-17), after :func:`predict` (eq. 12);
- :func:`kalman_update`: a linear scalar update in Joseph form (the ground-height
  pseudo-measurement, eq. 18);
- :func:`ukf_update`: the UKF3D update with Merwe scaled sigma points
  (:func:`merwe_weights`, :func:`sigma_points` by Cholesky) and the unscented transform
  (:func:`unscented_transform`).

The range and its Jacobian are the measurement model's (:mod:`estimator.measurement`).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike

from estimator.measurement import geometric_range_m, range_jacobian


class Update(NamedTuple):
    """A scalar update: ``accepted`` by the NIS gate (``nis`` = nu^2 / S at the prior);
    ``x`` and ``P`` after it (the prior's when rejected)."""

    accepted: bool
    x: np.ndarray
    P: np.ndarray
    nu: float
    S: float
    nis: float


def h(x: ArrayLike, u: ArrayLike) -> float:
    """Eq. (13): the predicted range |p - u| + b of the state x = [p, b] (x = p: no bias)."""
    x = np.asarray(x, dtype=float)
    b = x[3] if x.size > 3 else 0.0
    return float(geometric_range_m(x[:3], u)) + b


def jacobian(x: ArrayLike, u: ArrayLike) -> np.ndarray:
    """Eq. (14): H = [(p - u) / |p - u|, 1] for x = [p, b]."""
    _, H = range_jacobian(np.asarray(x, dtype=float)[:3], u, bias=True)
    return H


def predict(x: ArrayLike, P: ArrayLike, Q: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """Eq. (12): a static responder, x^- = x, P^- = P + Q (Q a diagonal or a matrix)."""
    Q = np.asarray(Q, dtype=float)
    return np.array(x, dtype=float), np.asarray(P, dtype=float) + (
        np.diag(Q) if Q.ndim == 1 else Q)


def joseph(P: np.ndarray, H: np.ndarray, K: np.ndarray, R: float) -> np.ndarray:
    """Eq. (17)'s covariance: (I - K H) P (I - K H)^T + K R K^T, for any gain K."""
    A = np.eye(len(K)) - np.outer(K, H)
    return A @ P @ A.T + R * np.outer(K, K)


def iekf_update(x: ArrayLike, P: ArrayLike, u: ArrayLike, d: float, R: float, *,
                iterations: int = 3, nis_gate: float = 9.0) -> Update:
    """One IEKF3D range update from the prior (x^-, P^-) (eqs. 13-17).

    The NIS gate uses nu = d - h(x^-) and S = H P^- H^T + R at the prior (eqs. 15-16).
    Each of the M iterations relinearises at x_i (x_0 = x^-):
    K_i = P^- H_i^T / S_i, x_{i+1} = x^- + K_i (d - h(x_i) - H_i (x^- - x_i));
    the covariance is the Joseph form with the last iteration's H and K (eq. 17).
    """
    x_prior = np.asarray(x, dtype=float)
    P = np.asarray(P, dtype=float)
    H = jacobian(x_prior, u)
    nu = d - h(x_prior, u)
    S = H @ P @ H + R
    nis = nu * nu / S
    if not nis <= nis_gate:
        return Update(False, x_prior, P, nu, S, nis)
    xi = x_prior
    for _ in range(iterations):
        Hi = jacobian(xi, u)
        K = P @ Hi / (Hi @ P @ Hi + R)
        xi = x_prior + K * (d - h(xi, u) - Hi @ (x_prior - xi))
    return Update(True, xi, joseph(P, Hi, K, R), nu, S, nis)


def kalman_update(x: ArrayLike, P: ArrayLike, H: ArrayLike, z: float, R: float
                  ) -> tuple[np.ndarray, np.ndarray]:
    """A linear scalar measurement z = H x + n, n ~ N(0, R), in Joseph form (eq. 17):
    the ground-height pseudo-measurement z_prior with H = e_z and R_z (eq. 18)."""
    x = np.asarray(x, dtype=float)
    P = np.asarray(P, dtype=float)
    H = np.asarray(H, dtype=float)
    K = P @ H / (H @ P @ H + R)
    return x + K * (z - H @ x), joseph(P, H, K, R)


def merwe_weights(n: int, alpha: float, beta: float, kappa: float
                  ) -> tuple[float, np.ndarray, np.ndarray]:
    """lambda and the mean and covariance weights of 2n + 1 Merwe scaled sigma points."""
    lam = alpha * alpha * (n + kappa) - n
    wm = np.full(2 * n + 1, 1.0 / (2.0 * (n + lam)))
    wc = wm.copy()
    wm[0] = lam / (n + lam)
    wc[0] = wm[0] + (1.0 - alpha * alpha + beta)
    return lam, wm, wc


def sigma_points(x: ArrayLike, P: ArrayLike, lam: float) -> np.ndarray:
    """2n + 1 points (rows): x, then x + L_i and x - L_i for the columns L_i of the
    Cholesky factor L L^T = (n + lambda) P."""
    x = np.asarray(x, dtype=float)
    L = np.linalg.cholesky((len(x) + lam) * np.asarray(P, dtype=float))
    return np.vstack([x, x + L.T, x - L.T])


def unscented_transform(Y: np.ndarray, wm: np.ndarray, wc: np.ndarray) -> tuple[float, float]:
    """Mean and variance of scalar images Y of the sigma points.

    The mean sum(Wm Y) is written Y_0 + sum Wm (Y - Y_0) (the same sum, the weights
    summing to one) so that small alphas, whose weights reach +-1e6, do not cancel it
    away; the variance is sum Wc (Y - mean)^2.
    """
    mean = Y[0] + wm @ (Y - Y[0])
    return float(mean), float(wc @ (Y - mean) ** 2)


def ukf_update(x: ArrayLike, P: ArrayLike, u: ArrayLike, d: float, R: float, *,
               alpha: float = 1e-3, beta: float = 2.0, kappa: float = 0.0,
               nis_gate: float = 9.0) -> Update:
    """One UKF3D range update from the prior (x^-, P^-) (sec. UKF3D): the sigma points
    through h (eq. 13 without bias), S = P_yy + R, the same NIS gate, then
    K = P_xy / S, x^+ = x^- + K nu, P^+ = P^- - K S K^T."""
    x = np.asarray(x, dtype=float)
    P = np.asarray(P, dtype=float)
    lam, wm, wc = merwe_weights(len(x), alpha, beta, kappa)
    X = sigma_points(x, P, lam)
    Y = geometric_range_m(X, u)
    y_mean, P_yy = unscented_transform(Y, wm, wc)
    nu = d - y_mean
    S = P_yy + R
    nis = nu * nu / S
    if not nis <= nis_gate:
        return Update(False, x, P, nu, S, nis)
    P_xy = (wc * (Y - y_mean)) @ (X - x)
    K = P_xy / S
    return Update(True, x + K * nu, P - S * np.outer(K, K), nu, S, nis)
