"""Measurement-noise models R_k^FTM (sec. Measurement-Noise Configurations).

A noise model gives the range variance of one gated measurement. Filters call
``variance(m, nu_m, hph_m2)`` with the prior innovation nu and its predicted part
H P^- H^T, so innovation-based models (Adaptive-R, eq. 24; ``innovation_based``) share
the interface. Models hold per-track state, so a mode holds a component (:class:`Constant`,
:class:`Nlos`, :class:`Empirical`, :class:`Adaptive`, :class:`EmpiricalNlos`,
:class:`GnssInflated`) that builds a fresh model for each track and restart from the
pipeline's configuration.

The paper's models are reproduced exactly; :class:`GnssInflatedR` is our extension
(sec. Filter Overconfidence: "propagating calibrated GNSS covariance") and never part
of the paper's six modes.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import TYPE_CHECKING, NamedTuple, Protocol

from estimator.records import AssociatedRange

if TYPE_CHECKING:
    from estimator.pipeline import PipelineConfig


class GatedRange(NamedTuple):
    """An associated range that passed the MAD gate, with its robust scale (eq. 4)."""

    meas: AssociatedRange
    sigma_gate_m: float


class NoiseModel(Protocol):
    """R of one gated range; ``innovation_based`` models need nu and H P^- H^T (the
    filter then calls them at its prior, before the NIS gate)."""

    innovation_based: bool

    def variance(self, m: GatedRange, nu_m: float, hph_m2: float) -> float: ...


class NoiseComponent(Protocol):
    """A mode's noise model: builds a fresh (stateful) model from the pipeline's config."""

    def make(self, cfg: PipelineConfig) -> NoiseModel: ...


# --------------------------------------------------------------------------- configs


@dataclass(frozen=True, kw_only=True)
class NlosConfig:
    """NLoS detector and inflation, eqs. (20)-(22)."""

    skew_window: int = 20  # N <= 20 samples of the range window
    skew_min_samples: int = 3  # skewness needs at least 3 samples (our choice)
    skew_threshold: float = 1.0  # gamma_th
    rssi_1m_dbm: float = -35.0  # RSSI_1m, eq. (21)
    path_loss_exponent: float = 3.0  # eta, eq. (21)
    rssi_tolerance_db: float = 15.0  # |RSSI - RSSI_exp| > 15 dB
    kappa_nlos: float = 3.0  # sigma x 3, i.e. R x (1 + 8 I_NLoS)
    min_distance_m: float = 1.0  # log10(d) is evaluated at max(d, 1 m) (our guard)


@dataclass(frozen=True, kw_only=True)
class EmpiricalRConfig:
    """Empirical-R, eq. (23): R = max(sigma_gate^2, sigma0^2 + alpha d^2 + beta q^2)."""

    sigma0_m: float = 0.3
    alpha: float = 4e-4
    beta_m2_per_db2: float = 3e-3
    r_ref_db: float = 40.0


@dataclass(frozen=True, kw_only=True)
class AdaptiveRConfig:
    """Adaptive-R (Mohamed-Schwarz), eq. (24)."""

    rate: float = 0.05  # alpha_a
    r_min_m2: float = 0.01
    r_max_m2: float = 25.0


# --------------------------------------------------------------------------- models


class ConstantR:
    """Baseline and UKF modes: R = sigma_gate^2 (constant from the MAD gate)."""

    innovation_based = False

    def variance(self, m: GatedRange, nu_m: float, hph_m2: float) -> float:
        return m.sigma_gate_m * m.sigma_gate_m


def expected_rssi_dbm(range_m: float, cfg: NlosConfig = NlosConfig()) -> float:
    """Eq. (21): RSSI_exp(d) = RSSI_1m - 10 eta log10(d)."""
    d = max(range_m, cfg.min_distance_m)
    return cfg.rssi_1m_dbm - 10.0 * cfg.path_loss_exponent * math.log10(d)


def skewness(values: list[float] | deque[float]) -> float:
    """Eq. (20): gamma_1 = mean(((d - mean) / s)^3) with the population s (ddof=0).

    Equals ``scipy.stats.skew(values, bias=True)``; 0 for a constant window.
    """
    n = len(values)
    if n == 0:
        return 0.0
    mean = sum(values) / n
    m2 = 0.0
    m3 = 0.0
    for v in values:
        d = v - mean
        d2 = d * d
        m2 += d2
        m3 += d2 * d
    m2 /= n
    m3 /= n
    if m2 <= 1e-24:
        return 0.0
    return m3 / (m2 * math.sqrt(m2))


class NlosR:
    """NLoS mode, eq. (22): R = (1 + 8 I_NLoS) sigma_gate^2.

    I_NLoS = [skew of the last <= 20 ranges > 1.0  or  |RSSI - RSSI_exp(d)| > 15 dB].
    A measurement without RSSI is judged by skewness alone.
    """

    innovation_based = False

    def __init__(self, cfg: NlosConfig = NlosConfig()) -> None:
        self.cfg = cfg
        self.window: deque[float] = deque(maxlen=cfg.skew_window)
        self.n_flagged = 0
        self.last_flag = False

    def is_nlos(self, m: GatedRange) -> bool:
        cfg = self.cfg
        self.window.append(m.meas.range_m)
        skew_flag = (
            len(self.window) >= cfg.skew_min_samples
            and skewness(self.window) > cfg.skew_threshold
        )
        rssi = m.meas.rssi_dbm
        rssi_flag = (
            rssi is not None
            and abs(rssi - expected_rssi_dbm(m.meas.range_m, cfg)) > cfg.rssi_tolerance_db
        )
        return skew_flag or rssi_flag

    def variance(self, m: GatedRange, nu_m: float, hph_m2: float) -> float:
        flag = self.is_nlos(m)
        self.last_flag = flag
        self.n_flagged += flag
        k2 = self.cfg.kappa_nlos**2 if flag else 1.0
        return k2 * m.sigma_gate_m * m.sigma_gate_m


def empirical_r_m2(
    range_m: float, rssi_dbm: float | None, sigma_gate_m: float, cfg: EmpiricalRConfig
) -> float:
    """Eq. (23); a missing RSSI contributes q = 0."""
    q = 0.0 if rssi_dbm is None else max(0.0, -rssi_dbm - cfg.r_ref_db)
    model = cfg.sigma0_m**2 + cfg.alpha * range_m * range_m + cfg.beta_m2_per_db2 * q * q
    return max(sigma_gate_m * sigma_gate_m, model)


def empirical_model_m2(range_m: float, rssi_dbm: float | None, cfg: EmpiricalRConfig) -> float:
    """The model part of eq. (23), sigma_0^2 + alpha d^2 + beta q^2 (no MAD floor)."""
    q = 0.0 if rssi_dbm is None else max(0.0, -rssi_dbm - cfg.r_ref_db)
    return cfg.sigma0_m**2 + cfg.alpha * range_m * range_m + cfg.beta_m2_per_db2 * q * q


class CalibratedR:
    """Mode ``refined``: R = s_a^2 (sigma_0^2 + alpha d^2 + beta q^2) (ours).

    The Empirical-R shape of eq. (23) without its MAD floor (at 3-5 Hz sigma_gate is
    dominated by the drone's own range rate), scaled by the measuring agent's noise
    scale ``scales[agent]`` as the batch refinement calibrates it (1 until then).
    """

    innovation_based = False

    def __init__(self, cfg: EmpiricalRConfig, scales: dict[str, float]) -> None:
        self.cfg = cfg
        self.scales = scales

    def variance(self, m: GatedRange, nu_m: float, hph_m2: float) -> float:
        meas = m.meas
        s = self.scales.get(meas.agent, 1.0)
        return s * s * empirical_model_m2(meas.range_m, meas.rssi_dbm, self.cfg)


class EmpiricalR:
    """Empirical-R mode, eq. (23): distance- and RSSI-dependent variance."""

    innovation_based = False

    def __init__(self, cfg: EmpiricalRConfig = EmpiricalRConfig()) -> None:
        self.cfg = cfg
        self._s0 = cfg.sigma0_m**2
        self._a = cfg.alpha
        self._b = cfg.beta_m2_per_db2
        self._r = cfg.r_ref_db

    def variance(self, m: GatedRange, nu_m: float, hph_m2: float) -> float:
        """:func:`empirical_r_m2` with the constants held (called per measurement)."""
        meas = m.meas
        d = meas.range_m
        rssi = meas.rssi_dbm
        q = 0.0 if rssi is None else max(0.0, -rssi - self._r)
        sg2 = m.sigma_gate_m * m.sigma_gate_m
        model = self._s0 + self._a * d * d + self._b * q * q
        return model if model > sg2 else sg2


class AdaptiveR:
    """Adaptive-R, eq. (24): R_k = clip((1 - a) R_{k-1} + a (nu^2 - H P^- H^T)).

    R_0 is the first measurement's sigma_gate^2 (the paper leaves it open). Called once
    per measurement that reaches the filter, before its NIS gate.
    """

    innovation_based = True

    def __init__(self, cfg: AdaptiveRConfig = AdaptiveRConfig()) -> None:
        self.cfg = cfg
        self.r_hat_m2: float | None = None

    def variance(self, m: GatedRange, nu_m: float, hph_m2: float) -> float:
        cfg = self.cfg
        prev = self.r_hat_m2 if self.r_hat_m2 is not None else m.sigma_gate_m**2
        r = (1.0 - cfg.rate) * prev + cfg.rate * (nu_m * nu_m - hph_m2)
        r = min(cfg.r_max_m2, max(cfg.r_min_m2, r))
        self.r_hat_m2 = r
        return r


@dataclass(frozen=True, kw_only=True)
class GnssCovarianceConfig:
    """GNSS anchor uncertainty projected on the line of sight (our extension).

    ``acc_m`` is a 68 % horizontal-radius proxy: per-axis sigma = acc / 1.515 (2-D
    Gaussian, P(r < 1.515 sigma) = 0.68), times ``acc_scale`` because an HDOP proxy is
    optimistic (the paper: proxy 0.77-1.02 while errors were 1.5-3 m). Vertical sigma is
    ``vacc_m`` when logged, else ``vertical_ratio`` x horizontal. A floor models the
    slowly varying bias the proxy does not show.
    """

    acc_scale: float = 2.0
    vertical_ratio: float = 1.7
    floor_m: float = 0.5


class GnssInflatedR:
    """Wrap a model: R = R_inner + sigma_h^2 (1 - c^2) + sigma_v^2 c^2, c = vertical LOS.

    The line-of-sight cosine c is taken from the anchor's height over the ground-height
    hint (H_AGL) and the range: c = min(1, H_AGL / d).
    """

    def __init__(
        self, inner: NoiseModel, cfg: GnssCovarianceConfig, default_agl_m: float
    ) -> None:
        self.inner = inner
        self.cfg = cfg
        self.default_agl_m = default_agl_m

    @property
    def innovation_based(self) -> bool:
        return self.inner.innovation_based

    def variance(self, m: GatedRange, nu_m: float, hph_m2: float) -> float:
        r = self.inner.variance(m, nu_m, hph_m2)
        cfg = self.cfg
        a = m.meas
        sh = max(cfg.floor_m, cfg.acc_scale * a.anchor_acc_m / 1.515)
        sv = (
            cfg.acc_scale * a.anchor_vacc_m
            if a.anchor_vacc_m is not None
            else cfg.vertical_ratio * sh
        )
        agl = a.agl_m if a.agl_m is not None else self.default_agl_m
        c = min(1.0, agl / max(a.range_m, 1e-3))
        return r + sh * sh * (1.0 - c * c) + sv * sv * c * c


class EmpiricalNlosR:
    """Empirical-R (eq. 23) times kappa_NLoS^2 when eq. (22) flags the range NLoS (ours:
    mode ``robust``)."""

    innovation_based = False

    def __init__(self, empirical: EmpiricalRConfig = EmpiricalRConfig(),
                 nlos: NlosConfig = NlosConfig()) -> None:
        self.emp = EmpiricalR(empirical)
        self.det = NlosR(nlos)

    def variance(self, m: GatedRange, nu_m: float, hph_m2: float) -> float:
        r = self.emp.variance(m, nu_m, hph_m2)
        return r * self.det.cfg.kappa_nlos**2 if self.det.is_nlos(m) else r


# --------------------------------------------------------------------------- components
# What a mode holds: each builds a fresh model (models keep per-track state) from the
# pipeline's configuration (estimator.pipeline.PipelineConfig).


@dataclass(frozen=True)
class Constant:
    """R = sigma_gate^2 (modes baseline, ukf, ema): :class:`ConstantR`."""

    def make(self, cfg: PipelineConfig) -> ConstantR:
        return ConstantR()


@dataclass(frozen=True)
class Nlos:
    """R inflated on NLoS, eq. (22) (mode nlos): :class:`NlosR` with ``cfg.nlos``."""

    def make(self, cfg: PipelineConfig) -> NlosR:
        return NlosR(cfg.nlos)


@dataclass(frozen=True)
class Empirical:
    """Empirical-R, eq. (23) (mode empirical-r): :class:`EmpiricalR` with ``cfg.empirical``."""

    def make(self, cfg: PipelineConfig) -> EmpiricalR:
        return EmpiricalR(cfg.empirical)


@dataclass(frozen=True)
class Adaptive:
    """Adaptive-R, eq. (24) (mode adaptive-r): :class:`AdaptiveR` with ``cfg.adaptive``."""

    def make(self, cfg: PipelineConfig) -> AdaptiveR:
        return AdaptiveR(cfg.adaptive)


@dataclass(frozen=True)
class EmpiricalNlos:
    """Empirical-R inflated on NLoS (ours): :class:`EmpiricalNlosR`."""

    def make(self, cfg: PipelineConfig) -> EmpiricalNlosR:
        return EmpiricalNlosR(cfg.empirical, cfg.nlos)


@dataclass(frozen=True)
class GnssInflated:
    """``inner`` plus the GNSS anchor variance on the line of sight (ours):
    :class:`GnssInflatedR` with ``cfg.gnss_cov`` and ``cfg.agl_m``."""

    inner: NoiseComponent

    def make(self, cfg: PipelineConfig) -> GnssInflatedR:
        return GnssInflatedR(self.inner.make(cfg), cfg.gnss_cov, cfg.agl_m)
