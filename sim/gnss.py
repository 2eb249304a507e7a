"""GNSS receiver model: the ZED-F9P stream the phone logs (sec. Hardware and Software).

Per epoch the reported antenna position is truth + a first-order Gauss-Markov bias per
ENU axis (the slowly varying correlated error of standalone GNSS, sec. Filter
Overconfidence) + white noise. The receiver runs at ``rate_hz`` (10 Hz) and drops to
``fallback_rate_hz`` (1 Hz) inside fallback windows; outage windows deliver nothing and
single fixes go missing with ``drop_prob``. ``acc_m`` is an HDOP-derived proxy driven
by the number of satellites: it stays near 0.8-1.0 m while the true horizontal error is
1.5-3 m, as the paper observed (sec. Experimental Setup). The ``rtk`` preset models
centimetre-level RTK fixed solutions. Each fix is delivered to the phone after a
latency plus jitter (:mod:`sim.clock`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from estimator.records import GNSS_FIX_TYPES
from sim._config import check_finite, check_positive, check_probability
from sim._random import gauss_markov
from sim.clock import ClockConfig, exponential_delays
from sim.vehicle import VehicleTrack


def _check_windows(name: str, windows: tuple[tuple[float, float], ...]) -> None:
    for a, b in windows:
        check_finite(name, a)
        check_finite(name, b)
        if b <= a:
            raise ValueError(f"{name}: window ({a}, {b}) must end after it starts")


@dataclass(frozen=True, kw_only=True)
class GnssConfig:
    """Standalone dual-frequency GNSS (defaults) at 10 Hz; see :data:`GNSS_PRESETS`."""

    rate_hz: float = 10.0  # ZED-F9P configured at 10 Hz (sec. Hardware and Software)
    fallback_rate_hz: float = 1.0  # the 1 Hz fallback period T_sync covers (sec. Range Model)
    fallback_windows_s: tuple[tuple[float, float], ...] = ()
    outage_windows_s: tuple[tuple[float, float], ...] = ()
    drop_prob: float = 0.002  # single missed callbacks
    # Standalone: 1.5-3 m horizontal error (sec. Experimental Setup): 1.5 m per axis
    # gives an RMS horizontal error of 2.1 m (median 1.8 m, 90 % 3.2 m).
    bias_sigma_h_m: float = 1.5
    bias_sigma_v_m: float = 2.5
    bias_tau_s: float = 300.0
    white_sigma_h_m: float = 0.12
    white_sigma_v_m: float = 0.25
    # HDOP-derived accM proxy 0.77-1.02 across 14808 fixes (sec. Experimental Setup)
    acc_ref_m: float = 0.88
    sats_ref: int = 21
    sats_sigma: float = 2.0
    sats_tau_s: float = 180.0
    sats_min: int = 5
    sats_max: int = 32
    acc_noise_rel: float = 0.02
    vacc_ratio: float = 1.6
    report_vacc: bool = True
    fix: str = "3d"

    def __post_init__(self) -> None:
        check_positive("rate_hz", self.rate_hz)
        check_positive("fallback_rate_hz", self.fallback_rate_hz)
        if self.rate_hz > 100.0:
            raise ValueError("rate_hz above 100 Hz is not a GNSS receiver")
        if self.fallback_rate_hz > self.rate_hz:
            raise ValueError("fallback_rate_hz must not exceed rate_hz")
        _check_windows("fallback_windows_s", self.fallback_windows_s)
        _check_windows("outage_windows_s", self.outage_windows_s)
        check_probability("drop_prob", self.drop_prob)
        for name in (
            "bias_sigma_h_m",
            "bias_sigma_v_m",
            "white_sigma_h_m",
            "white_sigma_v_m",
            "sats_sigma",
            "acc_noise_rel",
        ):
            check_positive(name, getattr(self, name), allow_zero=True)
        for name in ("bias_tau_s", "sats_tau_s", "acc_ref_m", "vacc_ratio"):
            check_positive(name, getattr(self, name))
        if not 1 <= self.sats_min <= self.sats_ref <= self.sats_max <= 200:
            raise ValueError("need 1 <= sats_min <= sats_ref <= sats_max <= 200")
        if self.fix not in GNSS_FIX_TYPES:
            raise ValueError(f"fix {self.fix!r} is not one of {', '.join(GNSS_FIX_TYPES)}")


STANDALONE = GnssConfig()
# RTK fixed (NTRIP corrections, which the paper planned but lost to an outage):
# ZED-F9P RTK is 0.01 m + 1 ppm horizontal.
RTK = GnssConfig(
    bias_sigma_h_m=0.008,
    bias_sigma_v_m=0.015,
    bias_tau_s=60.0,
    white_sigma_h_m=0.006,
    white_sigma_v_m=0.012,
    acc_ref_m=0.014,
    vacc_ratio=1.5,
    fix="rtk_fixed",
)
GNSS_PRESETS: dict[str, GnssConfig] = {"standalone": STANDALONE, "rtk": RTK}


@dataclass(frozen=True, eq=False)
class GnssTrack:
    """Delivered fixes (M of them), with their true measurement and delivery times.

    ``enu_m`` is the reported position, ``true_enu_m`` the antenna's truth, and
    ``error_enu_m = enu_m - true_enu_m`` (of which ``bias_enu_m`` is the correlated part).
    """

    t_s: np.ndarray
    t_delivery_s: np.ndarray
    enu_m: np.ndarray
    true_enu_m: np.ndarray
    bias_enu_m: np.ndarray
    acc_m: np.ndarray
    vacc_m: np.ndarray | None
    sats: np.ndarray
    fix: str
    n_epochs: int  # receiver epochs before fallback, outages and drops

    def __repr__(self) -> str:
        return f"GnssTrack({len(self.t_s)} fixes of {self.n_epochs} epochs, fix {self.fix})"

    @property
    def error_enu_m(self) -> np.ndarray:
        return self.enu_m - self.true_enu_m

    @property
    def error_h_m(self) -> np.ndarray:
        e = self.error_enu_m
        return np.hypot(e[:, 0], e[:, 1])


def _in_windows(t: np.ndarray, windows: tuple[tuple[float, float], ...]) -> np.ndarray:
    inside = np.zeros(len(t), dtype=bool)
    for a, b in windows:
        inside |= (t >= a) & (t < b)
    return inside


def simulate_gnss(
    track: VehicleTrack, cfg: GnssConfig, clock: ClockConfig, rng: np.random.Generator
) -> GnssTrack:
    """Simulate the receiver over the whole flight."""
    dt = 1.0 / cfg.rate_hz
    phase = rng.uniform(0.0, dt)  # receiver epochs are on GNSS time, not the flight's
    n = math.floor((track.duration_s - phase) / dt) + 1
    k = np.arange(max(n, 0))
    t_all = phase + k * dt
    sig_b = np.array([cfg.bias_sigma_h_m, cfg.bias_sigma_h_m, cfg.bias_sigma_v_m])
    sig_w = np.array([cfg.white_sigma_h_m, cfg.white_sigma_h_m, cfg.white_sigma_v_m])
    bias = gauss_markov(rng, len(k), dt, sig_b, cfg.bias_tau_s)
    white = rng.standard_normal((len(k), 3)) * sig_w
    sats_gm = gauss_markov(rng, len(k), dt, cfg.sats_sigma, cfg.sats_tau_s)
    acc_noise = rng.standard_normal(len(k))
    vacc_noise = rng.standard_normal(len(k))
    dropped = rng.random(len(k)) < cfg.drop_prob
    jitter = exponential_delays(rng, clock.gnss_jitter_s, len(k))

    step = max(1, round(cfg.rate_hz / cfg.fallback_rate_hz))
    keep = ~dropped & ~_in_windows(t_all, cfg.outage_windows_s)
    keep &= ~(_in_windows(t_all, cfg.fallback_windows_s) & (k % step != 0))

    t = t_all[keep]
    truth = track.position_at(t)
    bias = bias[keep]
    meas = truth + bias + white[keep]
    sats = np.clip(np.rint(cfg.sats_ref + sats_gm[keep]), cfg.sats_min, cfg.sats_max)
    hdop_scale = np.sqrt(cfg.sats_ref / sats)
    acc = np.maximum(
        np.round(cfg.acc_ref_m * hdop_scale * (1.0 + cfg.acc_noise_rel * acc_noise[keep]), 3),
        0.001,
    )
    vacc = None
    if cfg.report_vacc:
        vacc = np.maximum(
            np.round(acc * cfg.vacc_ratio * (1.0 + cfg.acc_noise_rel * vacc_noise[keep]), 3),
            0.001,
        )
    # USB delivers in order: callbacks are monotone, at least 1 ms apart
    deliver = t + clock.gnss_latency_s + jitter[keep]
    spacing = 1e-3 * np.arange(len(deliver))
    deliver = np.maximum.accumulate(deliver - spacing) + spacing
    return GnssTrack(
        t_s=t,
        t_delivery_s=deliver,
        enu_m=meas,
        true_enu_m=truth,
        bias_enu_m=bias,
        acc_m=acc,
        vacc_m=vacc,
        sats=sats.astype(np.int64),
        fix=cfg.fix,
        n_epochs=len(k),
    )
