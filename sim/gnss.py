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
from numpy.typing import ArrayLike

from estimator.records import GNSS_FIX_TYPES
from sim._config import check_finite, check_positive, check_probability
from sim._random import BlockedGaussMarkov, as_seed_sequence, child_rng, child_seed
from sim.clock import ClockConfig, exponential_delays
from sim.terrain import MAX_EXTENT_M
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
        for name in ("bias_sigma_h_m", "bias_sigma_v_m", "white_sigma_h_m", "white_sigma_v_m",
                     "acc_ref_m"):  # 1e300 overflowed into infinite positions
            if getattr(self, name) > MAX_EXTENT_M:
                raise ValueError(f"{name} {getattr(self, name):g} m is beyond "
                                 f"{MAX_EXTENT_M:.0f} m")
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


# the columns of GnssErrorProcess.epochs
EPOCH_COLUMNS = ("t", "bias_e", "bias_n", "bias_u", "white_e", "white_n", "white_u", "sats",
                 "acc", "vacc", "drop", "delivery")
_T, _BIAS, _WHITE, _SATS, _ACC, _VACC, _DROP, _DELIVERY = (0, slice(1, 4), slice(4, 7), 7, 8,
                                                          9, 10, 11)


class GnssErrorProcess:
    """One receiver's epochs and errors as functions of time (common random numbers).

    Epoch k is at t_k = phase + k / rate_hz on the receiver's own time (the phase is
    drawn once). Its correlated bias, white noise, satellite count, accuracy noise,
    drop flag and callback jitter are drawn in blocks from streams named by the block
    index, so they do not depend on what is flown, nor on how the flight is stepped.
    """

    BLOCK = 1024

    def __init__(self, cfg: GnssConfig, clock: ClockConfig, seq: np.random.SeedSequence) -> None:
        self.cfg = cfg
        self.clock = clock
        self.seq = seq
        self.dt_s = 1.0 / cfg.rate_hz
        self.phase_s = float(child_rng(seq, 0).uniform(0.0, self.dt_s))
        sig_b = np.array([cfg.bias_sigma_h_m, cfg.bias_sigma_h_m, cfg.bias_sigma_v_m])
        self.bias = BlockedGaussMarkov(child_seed(seq, 1), self.dt_s, sig_b, cfg.bias_tau_s,
                                       block=self.BLOCK)
        self.sats = BlockedGaussMarkov(child_seed(seq, 2), self.dt_s, [cfg.sats_sigma],
                                       cfg.sats_tau_s, block=self.BLOCK)
        self._epochs: list[np.ndarray] = []
        self._first = 0  # the block index of _epochs[0] (those before: forgotten)

    def epoch_time_s(self, k: np.ndarray | int) -> np.ndarray | float:
        return self.phase_s + np.asarray(k) * self.dt_s

    def last_epoch_at_or_before(self, t_s: float) -> int:
        """Index of the last epoch at or before ``t_s`` (-1 if none)."""
        return math.floor((t_s - self.phase_s) / self.dt_s + 1e-9)

    def _epoch_block(self, b: int) -> np.ndarray:
        cfg = self.cfg
        if b < self._first:
            raise ValueError(f"epoch block {b} was forgotten (forget_before)")
        while self._first + len(self._epochs) <= b:
            nb = self._first + len(self._epochs)
            k0 = nb * self.BLOCK
            rng = child_rng(self.seq, 3, nb)
            n = self.BLOCK
            white = rng.standard_normal((n, 3)) * np.array(
                [cfg.white_sigma_h_m, cfg.white_sigma_h_m, cfg.white_sigma_v_m])
            acc_noise, vacc_noise = rng.standard_normal(n), rng.standard_normal(n)
            drop = rng.random(n)
            jitter = exponential_delays(rng, self.clock.gnss_jitter_s, n)
            sats = np.clip(np.rint(cfg.sats_ref + self.sats.values(k0, k0 + n)[:, 0]),
                           cfg.sats_min, cfg.sats_max)
            hdop_scale = np.sqrt(cfg.sats_ref / sats)
            acc = np.maximum(
                np.round(cfg.acc_ref_m * hdop_scale * (1.0 + cfg.acc_noise_rel * acc_noise), 3),
                0.001,
            )
            vacc = np.maximum(
                np.round(acc * cfg.vacc_ratio * (1.0 + cfg.acc_noise_rel * vacc_noise), 3), 0.001
            )
            t = self.epoch_time_s(np.arange(k0, k0 + n))
            self._epochs.append(np.column_stack([t, self.bias.values(k0, k0 + n), white, sats,
                                                 acc, vacc, drop, t + self.clock.gnss_latency_s
                                                 + jitter]))
        return self._epochs[b - self._first]

    def forget_before(self, k: int) -> None:
        """Forget the epochs (and the bias and satellite draws) wholly before epoch
        ``k``: a receiver that runs for hours keeps its recent epochs only."""
        drop = min(k // self.BLOCK - self._first, len(self._epochs) - 1)
        if drop > 0:
            del self._epochs[:drop]
            self._first += drop
        self.bias.forget_before(k)
        self.sats.forget_before(k)

    def epochs(self, k0: int, k1: int) -> np.ndarray:
        """What epochs k0 <= k < k1 report besides the truth, (k1 - k0, 12), columns
        :data:`EPOCH_COLUMNS`: time, bias, white noise (sigma applied), satellites, accM,
        vaccM (with their HDOP proxy), the drop draw (uniform) and the delivery time
        (time, latency and jitter, before callbacks are kept in order)."""
        if k1 <= k0:
            return np.zeros((0, len(EPOCH_COLUMNS)))
        b0, b1 = k0 // self.BLOCK, (k1 - 1) // self.BLOCK
        blocks = [self._epoch_block(b) for b in range(b0, b1 + 1)]
        off = b0 * self.BLOCK
        x = blocks[0] if len(blocks) == 1 else np.concatenate(blocks)
        return x[k0 - off : k1 - off]

    def bias_at(self, t_s: ArrayLike) -> np.ndarray:
        """The correlated error (M, 3) at times ``t_s`` (interpolated between epochs)."""
        t = np.atleast_1d(np.asarray(t_s, dtype=float)) - self.phase_s
        return self.bias.at(np.maximum(t, 0.0))


class GnssReceiver:
    """Measures the fixes of epochs as the flight advances (see :class:`GnssErrorProcess`).

    ``measure_until(t_end, truth_at)`` returns the fixes of the epochs in (last, t_end]
    (a :class:`GnssTrack` of that step):
    reported = truth + bias + white noise; outage windows deliver nothing, fallback
    windows only every ``rate / fallback_rate``-th epoch, single fixes go missing with
    ``drop_prob``. Delivery is the measurement time plus latency and jitter, kept in
    order at least 1 ms apart (USB delivers in order).
    """

    def __init__(self, cfg: GnssConfig, clock: ClockConfig, seq: np.random.SeedSequence) -> None:
        self.cfg = cfg
        self.clock = clock
        self.process = GnssErrorProcess(cfg, clock, seq)
        self._k_next = 0
        self._last_delivery_s = -math.inf

    def measure_until(self, t_end_s: float, truth_at) -> GnssTrack:
        cfg = self.cfg
        proc = self.process
        k0 = self._k_next
        k1 = max(k0, proc.last_epoch_at_or_before(t_end_s) + 1)
        self._k_next = k1
        ep = proc.epochs(k0, k1)
        keep = ep[:, _DROP] >= cfg.drop_prob
        if cfg.outage_windows_s:
            keep &= ~_in_windows(ep[:, _T], cfg.outage_windows_s)
        if cfg.fallback_windows_s:
            step = max(1, round(cfg.rate_hz / cfg.fallback_rate_hz))
            keep &= ~(_in_windows(ep[:, _T], cfg.fallback_windows_s)
                      & (np.arange(k0, k1) % step != 0))
        ep = ep[keep]  # a copy: the step's arrays are its own
        t = ep[:, _T]
        truth = truth_at(t) if len(t) else np.zeros((0, 3))
        bias = ep[:, _BIAS]
        # in order, at least 1 ms apart: each waits for the one before from the first
        # that would come too soon on
        deliver = ep[:, _DELIVERY]
        prev = np.concatenate(([self._last_delivery_s], deliver[:-1]))
        wait = np.flatnonzero(deliver <= prev + 1e-3)
        if len(wait):
            i0 = int(wait[0])
            last = float(prev[i0])
            for i, v in enumerate(deliver[i0:].tolist(), i0):
                last = v if v > last + 1e-3 else last + 1e-3
                deliver[i] = last
        if len(deliver):
            self._last_delivery_s = float(deliver[-1])
        return GnssTrack(t, deliver, truth + bias + ep[:, _WHITE], truth, bias, ep[:, _ACC],
                         ep[:, _VACC] if cfg.report_vacc else None, ep[:, _SATS].astype(np.int64),
                         cfg.fix, k1 - k0)


def gnss_track(steps: list[GnssTrack], fix: str) -> GnssTrack:
    """The fixes of consecutive steps as one :class:`GnssTrack`."""
    def cat(name: str, width: int | None = None) -> np.ndarray:
        parts = [getattr(b, name) for b in steps]
        if not parts:
            return np.zeros((0, width)) if width else np.zeros(0)
        return np.concatenate(parts)

    vacc = None if not steps or steps[0].vacc_m is None else cat("vacc_m")
    return GnssTrack(
        t_s=cat("t_s"),
        t_delivery_s=cat("t_delivery_s"),
        enu_m=cat("enu_m", 3),
        true_enu_m=cat("true_enu_m", 3),
        bias_enu_m=cat("bias_enu_m", 3),
        acc_m=cat("acc_m"),
        vacc_m=vacc,
        sats=cat("sats").astype(np.int64),
        fix=fix,
        n_epochs=sum(b.n_epochs for b in steps),
    )


def simulate_gnss(
    track: VehicleTrack, cfg: GnssConfig, clock: ClockConfig, rng: np.random.Generator | int
) -> GnssTrack:
    """The receiver over a whole flown track (its epochs up to the track's end)."""
    rx = GnssReceiver(cfg, clock, as_seed_sequence(rng))
    return gnss_track([rx.measure_until(track.t_s[-1], track.position_at)], cfg.fix)
