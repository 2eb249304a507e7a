"""The phone's monotonic clock and its callback timing.

Simulated time ``t_s`` starts at 0 with the flight. The phone stamps every callback
with ``elapsedRealtimeNanos`` (log-format.md): an integer nanosecond clock with an
arbitrary boot origin. A GNSS fix is stamped when its callback runs, i.e. at its true
measurement time plus the USB/driver delivery latency plus jitter; an RTT result when
its ranging callback runs. Lines reach the log file in delivery order, after a small
random writer delay, so the file can be slightly out of ``t_ns`` order (the spec
allows it; readers sort).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sim._config import check_positive


@dataclass(frozen=True, kw_only=True)
class ClockConfig:
    """Phone clock origin and callback timing (all seconds)."""

    boot_offset_min_s: float = 600.0  # phone booted at least 10 min before take-off
    boot_offset_max_s: float = 200_000.0
    gnss_latency_s: float = 0.045  # ZED-F9P NAV-PVT over USB at 115200 baud + driver
    gnss_jitter_s: float = 0.012  # mean of the exponential callback jitter
    rtt_jitter_s: float = 0.004  # mean of the exponential RTT callback jitter
    write_delay_s: float = 0.002  # mean exponential delay between callback and file write

    def __post_init__(self) -> None:
        for name in (
            "boot_offset_min_s",
            "gnss_latency_s",
            "gnss_jitter_s",
            "rtt_jitter_s",
            "write_delay_s",
        ):
            check_positive(name, getattr(self, name), allow_zero=True)
        check_positive("boot_offset_max_s", self.boot_offset_max_s, allow_zero=True)
        if self.boot_offset_max_s < self.boot_offset_min_s:
            raise ValueError("boot_offset_max_s must be >= boot_offset_min_s")
        if self.boot_offset_max_s > 3.0e7:
            raise ValueError("boot_offset_max_s above a year of uptime is not a phone")


@dataclass(frozen=True)
class PhoneClock:
    """Maps simulated seconds to the phone's integer ``t_ns``."""

    boot_offset_ns: int

    @classmethod
    def draw(cls, cfg: ClockConfig, rng: np.random.Generator) -> PhoneClock:
        offset_s = rng.uniform(cfg.boot_offset_min_s, cfg.boot_offset_max_s)
        return cls(round(offset_s * 1e9))

    def to_ns(self, t_s: np.ndarray) -> np.ndarray:
        """Integer nanoseconds (int64) of simulated times ``t_s``."""
        return self.boot_offset_ns + np.rint(np.asarray(t_s, dtype=float) * 1e9).astype(np.int64)

    def to_s(self, t_ns: np.ndarray) -> np.ndarray:
        """Simulated seconds of phone timestamps (inverse of :meth:`to_ns`)."""
        return (np.asarray(t_ns, dtype=np.int64) - self.boot_offset_ns) * 1e-9


def exponential_delays(rng: np.random.Generator, mean_s: float, n: int) -> np.ndarray:
    """``n`` exponential delays of mean ``mean_s`` (zeros when the mean is 0)."""
    if mean_s <= 0.0:
        return np.zeros(n)
    return rng.exponential(mean_s, n)
