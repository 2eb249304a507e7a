"""Sequential filters (sec. Sequential Bayesian Filtering): IEKF3D and UKF3D.

Both share one small interface (:class:`SequentialFilter`): ``predict()``,
``innovation(anchor, d) -> (nu, hph)``, ``update(anchor, d, R) -> UpdateResult``,
``update_height(z, R_z)``, and the state ``x`` / covariance ``P``. A mode names its
filter by a component object, :class:`Iekf` or :class:`Ukf`, which builds one from the
pipeline's configuration.

The maths is written with plain Python floats, unrolled: for a 3- or 4-state filter with
scalar measurements this is several times faster than NumPy's small-matrix calls
(benchmarks/bench_estimator.py measures it). The range and its Jacobian come from the
one measurement model (:mod:`estimator.measurement`, scalar form). The textbook matrix
forms the paper writes (iterated update, Joseph form, sigma points by Cholesky, the
unscented transform) are :mod:`estimator.reference`; tests hold these unrolled forms
equal to them. Every covariance update of the IEKF and of the ground prior goes through
the Joseph form :func:`joseph_cov4` / :func:`joseph_cov3` (eq. 17).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, NamedTuple, Protocol

from estimator.measurement import range_and_unit, range_of

if TYPE_CHECKING:
    from estimator.pipeline import PipelineConfig

Vec = list[float]
Mat = list[list[float]]
RSpec = float | Callable[[float, float], float]


@dataclass(frozen=True, kw_only=True)
class IekfConfig:
    """IEKF3D parameters (eqs. 12-17)."""

    q_diag: tuple[float, float, float, float] = (0.01, 0.01, 0.04, 1e-4)  # Q, m^2
    p0_diag: tuple[float, float, float, float] = (25.0, 25.0, 100.0, 4.0)  # P0, m^2
    iterations: int = 3  # M relinearising iterations
    nis_gate: float = 9.0  # eq. (16)
    bias0_m: float = 0.0


@dataclass(frozen=True, kw_only=True)
class UkfConfig:
    """UKF3D parameters: Merwe scaled sigma points, same position Q and NIS gate."""

    q_diag: tuple[float, float, float] = (0.01, 0.01, 0.04)
    p0_diag: tuple[float, float, float] = (25.0, 25.0, 100.0)
    alpha: float = 1e-3
    beta: float = 2.0
    kappa: float = 0.0
    nis_gate: float = 9.0


class UpdateResult(NamedTuple):
    """Outcome of one range update: ``nu`` and ``S`` at the prior, NIS = nu^2 / S."""

    accepted: bool
    nu_m: float
    s_m2: float
    nis: float
    r_m2: float


class FilterError(ArithmeticError):
    """The filter state became invalid (non-finite or non-positive-definite)."""


def _diag(d: Sequence[float]) -> Mat:
    n = len(d)
    return [[float(d[i]) if i == j else 0.0 for j in range(n)] for i in range(n)]


def joseph_cov4(P: Mat, H: Sequence[float], K: Sequence[float], q: Sequence[float],
                R: float) -> Mat:
    """Joseph covariance update of a 4-state filter for one scalar measurement (eq. 17).

    (I - K H) P (I - K H)^T + R K K^T for *any* gain K (``q`` = P H^T), in the product
    form: A P = P - K q^T (a_ij), c = A P H - R K, P+ = A P - c K^T, upper triangle
    mirrored. Equal to the subtractive (I - K H) P only for the optimal gain
    K = P H^T / (H P H^T + R). Used by :meth:`IEKF3D.update` and the ground prior.
    """
    h0, h1, h2, h3 = H
    k0, k1, k2, k3 = K
    q0, q1, q2, q3 = q
    (p00, p01, p02, p03), (p10, p11, p12, p13), (p20, p21, p22, p23), (
        p30, p31, p32, p33) = P
    a00, a01, a02, a03 = p00 - k0 * q0, p01 - k0 * q1, p02 - k0 * q2, p03 - k0 * q3
    a10, a11, a12, a13 = p10 - k1 * q0, p11 - k1 * q1, p12 - k1 * q2, p13 - k1 * q3
    a20, a21, a22, a23 = p20 - k2 * q0, p21 - k2 * q1, p22 - k2 * q2, p23 - k2 * q3
    a30, a31, a32, a33 = p30 - k3 * q0, p31 - k3 * q1, p32 - k3 * q2, p33 - k3 * q3
    c0 = a00 * h0 + a01 * h1 + a02 * h2 + a03 * h3 - R * k0
    c1 = a10 * h0 + a11 * h1 + a12 * h2 + a13 * h3 - R * k1
    c2 = a20 * h0 + a21 * h1 + a22 * h2 + a23 * h3 - R * k2
    c3 = a30 * h0 + a31 * h1 + a32 * h2 + a33 * h3 - R * k3
    n01, n02, n03 = a01 - c0 * k1, a02 - c0 * k2, a03 - c0 * k3
    n12, n13, n23 = a12 - c1 * k2, a13 - c1 * k3, a23 - c2 * k3
    return [
        [a00 - c0 * k0, n01, n02, n03],
        [n01, a11 - c1 * k1, n12, n13],
        [n02, n12, a22 - c2 * k2, n23],
        [n03, n13, n23, a33 - c3 * k3],
    ]


def joseph_cov3(P: Mat, H: Sequence[float], K: Sequence[float], q: Sequence[float],
                R: float) -> Mat:
    """:func:`joseph_cov4` for 3 states (the UKF's ground prior)."""
    h0, h1, h2 = H
    k0, k1, k2 = K
    q0, q1, q2 = q
    (p00, p01, p02), (p10, p11, p12), (p20, p21, p22) = P
    a00, a01, a02 = p00 - k0 * q0, p01 - k0 * q1, p02 - k0 * q2
    a10, a11, a12 = p10 - k1 * q0, p11 - k1 * q1, p12 - k1 * q2
    a20, a21, a22 = p20 - k2 * q0, p21 - k2 * q1, p22 - k2 * q2
    c0 = a00 * h0 + a01 * h1 + a02 * h2 - R * k0
    c1 = a10 * h0 + a11 * h1 + a12 * h2 - R * k1
    c2 = a20 * h0 + a21 * h1 + a22 * h2 - R * k2
    n01, n02, n12 = a01 - c0 * k1, a02 - c0 * k2, a12 - c1 * k2
    return [[a00 - c0 * k0, n01, n02], [n01, a11 - c1 * k1, n12], [n02, n12, a22 - c2 * k2]]


def _check4(x: Vec, P: Mat) -> None:
    a, b, c, d = P[0][0], P[1][1], P[2][2], P[3][3]
    if not (a > 0.0 and b > 0.0 and c > 0.0 and d > 0.0) or not math.isfinite(
        x[0] + x[1] + x[2] + x[3] + a + b + c + d
    ):
        raise FilterError("filter state is not finite or its covariance is not positive")


def _check(x: Vec, P: Mat) -> None:
    for i, xi in enumerate(x):
        if not math.isfinite(xi) or not P[i][i] > 0.0 or not math.isfinite(P[i][i]):
            raise FilterError("filter state is not finite or its covariance is not positive")


class IEKF3D:
    """Iterated EKF on [x, y, z, b] with h(x) = |p - u| + b (eqs. 12-17)."""

    n = 4
    has_bias = True

    def __init__(
        self, position_enu_m: Sequence[float], cfg: IekfConfig = IekfConfig()
    ) -> None:
        self.cfg = cfg
        self.x: Vec = [float(position_enu_m[0]), float(position_enu_m[1]),
                       float(position_enu_m[2]), cfg.bias0_m]
        self.P: Mat = _diag(cfg.p0_diag)
        self._q = cfg.q_diag

    def predict(self) -> None:
        """Eq. (12): static AP, P^- = P + Q."""
        P = self.P
        q = self._q
        for i in range(4):
            P[i][i] += q[i]

    def innovation(self, anchor: Sequence[float], range_m: float) -> tuple[float, float]:
        """Prior innovation nu = d - h(x^-) and H P^- H^T (eq. 15)."""
        x = self.x
        r, *g = range_and_unit(x[0] - anchor[0], x[1] - anchor[1], x[2] - anchor[2])
        H = (*g, 1.0)
        P = self.P
        hph = 0.0
        for i in range(4):
            Hi = H[i]
            row = P[i]
            hph += Hi * (row[0] * H[0] + row[1] * H[1] + row[2] * H[2] + row[3] * H[3])
        return range_m - (r + x[3]), hph

    def update(self, anchor: Sequence[float], range_m: float, r_m2: RSpec) -> UpdateResult:
        """NIS-gated iterated update with M relinearisations and the Joseph form.

        ``r_m2`` is R, or a callable ``(nu, H P^- H^T) -> R`` for innovation-based
        noise models (evaluated once, at the prior). The gate uses nu and S at the prior
        (eqs. 15-16); iteration i relinearises at x_i:
        x_{i+1} = x^- + K_i (d - h(x_i) - H_i (x^- - x_i)).
        """
        cfg = self.cfg
        P = self.P
        ux, uy, uz = anchor[0], anchor[1], anchor[2]
        X, Y, Z, B = self.x
        (p00, p01, p02, p03), (p10, p11, p12, p13), (p20, p21, p22, p23), (
            p30, p31, p32, p33) = P
        r, h0, h1, h2 = range_and_unit(X - ux, Y - uy, Z - uz)  # eqs. (13)-(14)
        q0 = p00 * h0 + p01 * h1 + p02 * h2 + p03  # q = P^- H^T
        q1 = p10 * h0 + p11 * h1 + p12 * h2 + p13
        q2 = p20 * h0 + p21 * h1 + p22 * h2 + p23
        q3 = p30 * h0 + p31 * h1 + p32 * h2 + p33
        hph = h0 * q0 + h1 * q1 + h2 * q2 + q3
        nu = range_m - (r + B)
        if callable(r_m2):
            r_m2 = r_m2(nu, hph)
        S = hph + r_m2  # eq. (15)
        nis = nu * nu / S
        if not nis <= cfg.nis_gate:  # eq. (16)
            return UpdateResult(False, nu, S, nis, r_m2)
        Si = S
        innov = nu
        xi0, xi1, xi2, xi3 = X, Y, Z, B
        for it in range(cfg.iterations):
            if it > 0:
                r, h0, h1, h2 = range_and_unit(xi0 - ux, xi1 - uy, xi2 - uz)
                q0 = p00 * h0 + p01 * h1 + p02 * h2 + p03
                q1 = p10 * h0 + p11 * h1 + p12 * h2 + p13
                q2 = p20 * h0 + p21 * h1 + p22 * h2 + p23
                q3 = p30 * h0 + p31 * h1 + p32 * h2 + p33
                Si = h0 * q0 + h1 * q1 + h2 * q2 + q3 + r_m2
                innov = range_m - (r + xi3) - (
                    h0 * (X - xi0) + h1 * (Y - xi1) + h2 * (Z - xi2) + (B - xi3)
                )
            g = innov / Si
            xi0, xi1, xi2, xi3 = X + q0 * g, Y + q1 * g, Z + q2 * g, B + q3 * g
        # Joseph form at the last linearisation point (H, K of the final iteration)
        Pn = joseph_cov4(P, (h0, h1, h2, 1.0), (q0 / Si, q1 / Si, q2 / Si, q3 / Si),
                         (q0, q1, q2, q3), r_m2)
        xn = [xi0, xi1, xi2, xi3]
        _check4(xn, Pn)
        self.x = xn
        self.P = Pn
        return UpdateResult(True, nu, S, nis, r_m2)

    def update_height(self, z_m: float, r_m2: float) -> None:
        """Ground-height pseudo-measurement z = z_prior, R_z (eq. 18)."""
        _height_update(self, z_m, r_m2)

    @property
    def position_enu_m(self) -> tuple[float, float, float]:
        return self.x[0], self.x[1], self.x[2]

    @property
    def bias_m(self) -> float:
        return self.x[3]


def _height_update(f: IEKF3D | UKF3D, z_m: float, r_m2: float) -> None:
    """Linear pseudo-measurement z = x_2 (H = e_z) with the Joseph form (eqs. 17-18)."""
    P = f.P
    if f.n == 4:
        q0, q1, q2, q3 = P[2]  # P e_z (P symmetric)
        S = q2 + r_m2
        g = (z_m - f.x[2]) / S
        x0, x1, x2, x3 = f.x
        x = [x0 + q0 * g, x1 + q1 * g, x2 + q2 * g, x3 + q3 * g]
        Pn = joseph_cov4(P, (0.0, 0.0, 1.0, 0.0), (q0 / S, q1 / S, q2 / S, q3 / S),
                         (q0, q1, q2, q3), r_m2)
        _check4(x, Pn)
    else:
        q0, q1, q2 = P[2]  # P e_z; the UKF's P may differ from its transpose in the
        S = q2 + r_m2  # last bit, so column 2 is taken as row 2 (= q) throughout
        g = (z_m - f.x[2]) / S
        x0, x1, x2 = f.x
        x = [x0 + q0 * g, x1 + q1 * g, x2 + q2 * g]
        Ps = [[P[0][0], P[0][1], q0], [P[1][0], P[1][1], q1], [q0, q1, q2]]
        Pn = joseph_cov3(Ps, (0.0, 0.0, 1.0), (q0 / S, q1 / S, q2 / S), (q0, q1, q2), r_m2)
        _check(x, Pn)
    f.x = x
    f.P = Pn


# ----------------------------------------------------------------------------- UKF


@dataclass(frozen=True)
class MerweWeights:
    """Merwe scaled sigma-point weights for dimension n (Wm, Wc sum to 1 for Wm)."""

    n: int
    lam: float
    wm0: float
    wc0: float
    wi: float

    @classmethod
    def make(cls, n: int, alpha: float, beta: float, kappa: float) -> MerweWeights:
        lam = alpha * alpha * (n + kappa) - n
        wi = 1.0 / (2.0 * (n + lam))
        wm0 = lam / (n + lam)
        wc0 = wm0 + (1.0 - alpha * alpha + beta)
        return cls(n, lam, wm0, wc0, wi)

    @property
    def wm(self) -> list[float]:
        return [self.wm0] + [self.wi] * (2 * self.n)

    @property
    def wc(self) -> list[float]:
        return [self.wc0] + [self.wi] * (2 * self.n)


class UKF3D:
    """UKF on [x, y, z] (no bias) with h(x) = |p - u| (sec. UKF3D)."""

    n = 3
    has_bias = False

    def __init__(self, position_enu_m: Sequence[float], cfg: UkfConfig = UkfConfig()) -> None:
        self.cfg = cfg
        self.x: Vec = [float(v) for v in position_enu_m[:3]]
        self.P: Mat = _diag(cfg.p0_diag)
        self.w = MerweWeights.make(3, cfg.alpha, cfg.beta, cfg.kappa)
        self._cache: tuple | None = None

    def predict(self) -> None:
        P = self.P
        q = self.cfg.q_diag
        for i in range(3):
            P[i][i] += q[i]
        self._cache = None

    def _propagate(self, anchor: Sequence[float]) -> tuple:
        """Sigma points x, x +/- L e_k (L = chol((n + lambda) P)) through h; unrolled.

        Returns (L, images Y+, Y-, mean, variance). The mean is written as
        Y0 + Wi sum(Y_k - Y0), equal to sum(Wm Y) because the weights sum to one, but
        free of the cancellation between Wm0 ~ -1e6 and Wi ~ 1.7e5 at alpha = 1e-3.
        (:func:`estimator.reference.ukf_update` is the same in matrix form.)
        """
        key = (anchor[0], anchor[1], anchor[2])
        if self._cache is not None and self._cache[0] == key:
            return self._cache[1]
        w = self.w
        c = 3.0 + w.lam
        (a00, a01, a02), (_, a11, a12), (_, _, a22) = self.P
        a00 *= c
        a01 *= c
        a02 *= c
        a11 *= c
        a12 *= c
        a22 *= c
        if not a00 > 0.0:
            raise FilterError("covariance is not positive definite")
        l00 = math.sqrt(a00)
        l10 = a01 / l00
        l20 = a02 / l00
        t = a11 - l10 * l10
        if not t > 0.0:
            raise FilterError("covariance is not positive definite")
        l11 = math.sqrt(t)
        l21 = (a12 - l20 * l10) / l11
        t = a22 - l20 * l20 - l21 * l21
        if not t > 0.0:
            raise FilterError("covariance is not positive definite")
        l22 = math.sqrt(t)
        L = (l00, l10, l20, l11, l21, l22)  # lower triangle, column by column
        x0, x1, x2 = self.x
        ax, ay, az = key
        dx, dy, dz = x0 - ax, x1 - ay, x2 - az
        y0 = range_of(dx, dy, dz)  # h at the sigma points (eq. 13, no bias)
        p0 = range_of(dx + l00, dy + l10, dz + l20)
        p1 = range_of(dx, dy + l11, dz + l21)
        p2 = range_of(dx, dy, dz + l22)
        m0 = range_of(dx - l00, dy - l10, dz - l20)
        m1 = range_of(dx, dy - l11, dz - l21)
        m2 = range_of(dx, dy, dz - l22)
        wi = w.wi
        mean = y0 + wi * (p0 + p1 + p2 + m0 + m1 + m2 - 6.0 * y0)
        d0 = y0 - mean
        var = w.wc0 * d0 * d0 + wi * (
            (p0 - mean) ** 2 + (p1 - mean) ** 2 + (p2 - mean) ** 2
            + (m0 - mean) ** 2 + (m1 - mean) ** 2 + (m2 - mean) ** 2
        )
        out = (L, (p0, p1, p2), (m0, m1, m2), mean, var)
        self._cache = (key, out)
        return out

    def innovation(self, anchor: Sequence[float], range_m: float) -> tuple[float, float]:
        out = self._propagate(anchor)
        return range_m - out[3], out[4]

    def update(self, anchor: Sequence[float], range_m: float, r_m2: RSpec) -> UpdateResult:
        """NIS-gated unscented update; ``r_m2`` as in :meth:`IEKF3D.update`.

        P_xy = sum Wc (chi - x)(Y - y_mean) = Wi sum_k (Y_k+ - Y_k-) L e_k (the centre
        point contributes nothing); K = P_xy / S; P = P - K S K^T.
        """
        L, yp, ymn, ym, pyy = self._propagate(anchor)
        nu = range_m - ym
        if callable(r_m2):
            r_m2 = r_m2(nu, pyy)
        S = pyy + r_m2
        nis = nu * nu / S
        if not nis <= self.cfg.nis_gate:
            self._cache = None
            return UpdateResult(False, nu, S, nis, r_m2)
        wi = self.w.wi
        l00, l10, l20, l11, l21, l22 = L
        e0 = wi * (yp[0] - ymn[0])
        e1 = wi * (yp[1] - ymn[1])
        e2 = wi * (yp[2] - ymn[2])
        p0 = l00 * e0
        p1 = l10 * e0 + l11 * e1
        p2 = l20 * e0 + l21 * e1 + l22 * e2
        k0, k1, k2 = p0 / S, p1 / S, p2 / S
        x = self.x
        xn = [x[0] + k0 * nu, x[1] + k1 * nu, x[2] + k2 * nu]
        (a00, a01, a02), (_, a11, a12), (_, _, a22) = self.P
        Pn = [
            [a00 - k0 * S * k0, a01 - k0 * S * k1, a02 - k0 * S * k2],
            [a01 - k1 * S * k0, a11 - k1 * S * k1, a12 - k1 * S * k2],
            [a02 - k2 * S * k0, a12 - k2 * S * k1, a22 - k2 * S * k2],
        ]
        _check(xn, Pn)
        self.x = xn
        self.P = Pn
        self._cache = None
        return UpdateResult(True, nu, S, nis, r_m2)

    def update_height(self, z_m: float, r_m2: float) -> None:
        _height_update(self, z_m, r_m2)
        self._cache = None

    @property
    def position_enu_m(self) -> tuple[float, float, float]:
        return self.x[0], self.x[1], self.x[2]

    @property
    def bias_m(self) -> float:
        return 0.0


# ----------------------------------------------------------------------------- components


class SequentialFilter(Protocol):
    """What the pipeline needs of a filter (IEKF3D and UKF3D both)."""

    n: int
    has_bias: bool
    x: Vec
    P: Mat

    def predict(self) -> None: ...

    def innovation(self, anchor: Sequence[float], range_m: float) -> tuple[float, float]: ...

    def update(self, anchor: Sequence[float], range_m: float, r_m2: RSpec) -> UpdateResult: ...

    def update_height(self, z_m: float, r_m2: float) -> None: ...

    @property
    def position_enu_m(self) -> tuple[float, float, float]: ...

    @property
    def bias_m(self) -> float: ...


class FilterComponent(Protocol):
    """A mode's filter: builds one at a bootstrap position from the pipeline's config."""

    has_bias: bool

    def make(self, position_enu_m: Sequence[float], cfg: PipelineConfig) -> SequentialFilter: ...


@dataclass(frozen=True)
class Iekf:
    """A mode's filter: :class:`IEKF3D` with the pipeline's ``iekf`` configuration
    (or ``config`` when given)."""

    config: IekfConfig | None = None
    has_bias = True

    def make(self, position_enu_m: Sequence[float], cfg: PipelineConfig) -> IEKF3D:
        return IEKF3D(position_enu_m, self.config if self.config is not None else cfg.iekf)


@dataclass(frozen=True)
class Ukf:
    """A mode's filter: :class:`UKF3D` with the pipeline's ``ukf`` configuration (or
    ``config`` when given)."""

    config: UkfConfig | None = None
    has_bias = False

    def make(self, position_enu_m: Sequence[float], cfg: PipelineConfig) -> UKF3D:
        return UKF3D(position_enu_m, self.config if self.config is not None else cfg.ukf)
