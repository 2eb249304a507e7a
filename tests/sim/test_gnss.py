"""GNSS model: Gauss-Markov bias statistics, rates, dropouts, outages, RTK, timing."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from sim import ClockConfig, GnssConfig
from sim._random import gauss_markov
from sim.gnss import GNSS_PRESETS, simulate_gnss

from .util import hover_track


def _acf(x: np.ndarray, lag: int) -> float:
    x = x - x.mean()
    return float(np.dot(x[:-lag], x[lag:]) / np.dot(x, x))


def test_gauss_markov_steady_state_and_autocorrelation():
    dt, tau, n = 0.1, 10.0, 400_000  # 4000 time constants
    x = gauss_markov(np.random.default_rng(7), n, dt, np.array([1.5, 1.5, 2.5]), tau)
    assert x.shape == (n, 3)
    np.testing.assert_allclose(x.std(axis=0), [1.5, 1.5, 2.5], rtol=0.05)
    lag = round(tau / dt)
    for axis in range(3):
        # standard error of the ACF estimate ~ sqrt(tau / T) ~ 0.016 here
        assert abs(_acf(x[:, axis], lag) - math.exp(-1.0)) < 0.05
        assert abs(_acf(x[:, axis], 2 * lag) - math.exp(-2.0)) < 0.05


@pytest.fixture(scope="module")
def long_fixes():
    """Six hours of 10 Hz fixes from a hovering drone with a 30 s bias time constant."""
    cfg = dataclasses.replace(GnssConfig(), bias_tau_s=30.0, drop_prob=0.05)
    track = hover_track(6 * 3600.0, dt_s=0.1)
    return cfg, simulate_gnss(track, cfg, ClockConfig(), np.random.default_rng(1))


def test_simulated_bias_autocorrelation_at_tau(long_fixes):
    cfg, g = long_fixes
    # the bias lives on the receiver's 10 Hz epoch grid; dropped fixes leave gaps, so
    # take the ACF on the grid of delivered epochs by time lag
    k = np.rint((g.t_s - g.t_s[0]) * cfg.rate_hz).astype(int)
    full = np.full((k[-1] + 1, 3), np.nan)
    full[k] = g.bias_enu_m
    lag = round(cfg.bias_tau_s * cfg.rate_hz)
    for axis, sigma in enumerate([cfg.bias_sigma_h_m, cfg.bias_sigma_h_m, cfg.bias_sigma_v_m]):
        a, b = full[:-lag, axis], full[lag:, axis]
        both = ~np.isnan(a) & ~np.isnan(b)
        rho = np.mean(a[both] * b[both]) / sigma**2
        assert abs(rho - math.exp(-1.0)) < 0.08  # 720 time constants: SE ~ 0.03
        assert abs(np.nanstd(full[:, axis]) / sigma - 1.0) < 0.1


def test_dropout_rate_matches_configuration(long_fixes):
    cfg, g = long_fixes
    missing = 1.0 - len(g.t_s) / g.n_epochs
    assert abs(missing - cfg.drop_prob) < 4 * math.sqrt(cfg.drop_prob * 0.95 / g.n_epochs)


def test_default_accuracy_is_metre_level_and_proxy_optimistic():
    # paper: standalone errors ~1.5-3 m while the HDOP proxy read 0.77-1.02
    track = hover_track(20 * 3600.0, dt_s=0.1)
    g = simulate_gnss(track, GnssConfig(), ClockConfig(), np.random.default_rng(3))
    err = g.error_enu_m
    rms_axis = np.sqrt(np.mean(err[:, :2] ** 2, axis=0))
    np.testing.assert_allclose(rms_axis, 1.5, rtol=0.25)  # 240 time constants of 300 s
    h = g.error_h_m
    assert 1.2 < np.median(h) < 2.5
    assert np.quantile(g.acc_m, 0.02) > 0.7 and np.quantile(g.acc_m, 0.98) < 1.1
    assert np.median(g.acc_m) < 0.6 * np.median(h)
    assert g.fix == "3d" and g.vacc_m is not None
    assert np.all((g.sats >= 5) & (g.sats <= 32))


def test_rtk_preset_is_centimetre_level():
    track = hover_track(1800.0, dt_s=0.1)
    g = simulate_gnss(track, GNSS_PRESETS["rtk"], ClockConfig(), np.random.default_rng(2))
    assert g.fix == "rtk_fixed"
    assert np.quantile(g.error_h_m, 0.99) < 0.05
    assert np.quantile(np.abs(g.error_enu_m[:, 2]), 0.99) < 0.1
    assert np.all(g.acc_m < 0.03)


def test_rates_fallback_and_outages():
    cfg = dataclasses.replace(
        GnssConfig(),
        drop_prob=0.0,
        fallback_windows_s=((100.0, 200.0),),
        outage_windows_s=((300.0, 330.0),),
    )
    track = hover_track(400.0, dt_s=0.05)
    g = simulate_gnss(track, cfg, ClockConfig(), np.random.default_rng(5))
    t = g.t_s
    normal = t < 100.0
    np.testing.assert_allclose(np.diff(t[normal]), 0.1, atol=1e-9)
    fallback = (t >= 100.0) & (t < 200.0)
    np.testing.assert_allclose(np.diff(t[fallback]), 1.0, atol=1e-9)
    assert not np.any((t >= 300.0) & (t < 330.0))
    assert np.sum((t >= 330.0) & (t < 340.0)) == 100


def test_delivery_latency_and_order():
    clock = ClockConfig()
    track = hover_track(600.0)
    g = simulate_gnss(track, GnssConfig(), clock, np.random.default_rng(9))
    delay = g.t_delivery_s - g.t_s
    assert np.all(delay >= clock.gnss_latency_s - 1e-12)
    assert abs(np.median(delay) - clock.gnss_latency_s - clock.gnss_jitter_s * math.log(2)) < 0.005
    assert np.all(np.diff(g.t_delivery_s) >= 1e-3 - 1e-12)  # callbacks in order


@pytest.mark.parametrize(
    "changes, match",
    [
        ({"bias_sigma_h_m": float("nan")}, "finite"),
        ({"bias_tau_s": 0.0}, "bias_tau_s"),
        ({"drop_prob": 1.5}, "drop_prob"),
        ({"outage_windows_s": ((10.0, 5.0),)}, "window"),
        ({"fix": "great"}, "fix"),
        ({"fallback_rate_hz": 20.0}, "fallback_rate_hz"),
    ],
)
def test_bad_gnss_config_is_refused(changes, match):
    with pytest.raises(ValueError, match=match):
        dataclasses.replace(GnssConfig(), **changes)
