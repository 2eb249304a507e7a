"""MAD outlier gate, eqs. (2)-(3): 1.5 s window, N_min = 8, k = 3.5, sigma_floor = 0.12 m."""

from __future__ import annotations

import statistics

import pytest

from estimator.gate import MAD_TO_SIGMA, MadGate, MadGateConfig, median

BASE = [10.0, 10.1, 9.9, 10.0, 10.1, 9.9, 10.0]  # 7 samples, constant-ish


def _feed(gate: MadGate, values: list[float], t0: float = 0.0, dt: float = 0.1):
    return [gate.check(t0 + i * dt, v) for i, v in enumerate(values)]


def _hand(window: list[float]) -> tuple[float, float, float]:
    """(median, MAD, threshold k * 1.4826 * MAD) of a window, independently of the gate."""
    med = statistics.median(window)
    mad = statistics.median([abs(v - med) for v in window])
    return med, mad, 3.5 * 1.4826 * mad


def test_constants() -> None:
    cfg = MadGateConfig()
    assert (cfg.window_s, cfg.min_samples, cfg.k, cfg.sigma_floor_m) == (1.5, 8, 3.5, 0.12)
    assert MAD_TO_SIGMA == 1.4826
    assert median([3.0, 1.0, 2.0]) == 2.0
    assert median([4.0, 1.0, 3.0, 2.0]) == 2.5


def test_fewer_than_8_samples_never_rejected() -> None:
    gate = MadGate()
    res = _feed(gate, [*BASE[:6], 500.0])  # a wild 7th sample
    assert all(r.accepted for r in res)
    assert [r.n_window for r in res] == [1, 2, 3, 4, 5, 6, 7]
    assert gate.n_rejected == 0
    # the same wild value as the 8th sample is rejected
    gate = MadGate()
    res = _feed(gate, [*BASE, 500.0])
    assert [r.accepted for r in res] == [True] * 7 + [False]
    assert gate.n_rejected == 1


def test_outlier_rejected_and_near_value_accepted() -> None:
    gate = MadGate()
    assert all(r.accepted for r in _feed(gate, BASE))
    # 8th sample: +5 m. Window [10, 10.1, 9.9, 10, 10.1, 9.9, 10, 15]: median 10.0,
    # |d - median| = [0, .1, .1, 0, .1, .1, 0, 5] -> MAD 0.1, threshold 3.5 * 1.4826 * 0.1
    r = gate.check(0.7, 15.0)
    med, mad, thr = _hand([*BASE, 15.0])
    assert (med, mad, thr) == pytest.approx((10.0, 0.1, 0.51891), abs=1e-12)
    assert not r.accepted
    assert r.n_window == 8
    assert (r.median_m, r.mad_m) == pytest.approx((10.0, 0.1), abs=1e-12)
    # 9th sample 10.4: window median 10.0, MAD 0.1 (the rejected 15.0 stays in the window)
    # |10.4 - 10.0| = 0.4 <= 0.51891: accepted
    r = gate.check(0.8, 10.4)
    med, mad, thr = _hand([*BASE, 15.0, 10.4])
    assert (med, mad, thr) == pytest.approx((10.0, 0.1, 0.51891), abs=1e-12)
    assert r.accepted
    assert r.n_window == 9
    assert r.sigma_gate_m == pytest.approx(0.14826, abs=1e-12)
    # 10th sample 9.4: |9.4 - 10.0| = 0.6 > 0.51891: rejected (median 10.0, MAD 0.1)
    r = gate.check(0.9, 9.4)
    med, mad, thr = _hand([*BASE, 15.0, 10.4, 9.4])
    assert (med, mad, thr) == pytest.approx((10.0, 0.1, 0.51891), abs=1e-12)
    assert not r.accepted
    assert gate.n_rejected == 2


def test_negative_outlier_rejected() -> None:
    gate = MadGate()
    res = _feed(gate, [*BASE, 4.0])
    assert not res[-1].accepted
    assert abs(4.0 - 10.0) > 3.5 * 1.4826 * 0.1


def test_sigma_gate_is_max_of_scaled_mad_and_floor() -> None:
    values = [10.0, 11.0, 9.0, 10.5, 9.5, 10.0, 12.0, 8.0]
    # by hand, for the window after each sample:
    #   [10]                 median 10,   MAD 0     -> sigma floor 0.12
    #   [10, 11]             median 10.5, MAD 0.5   -> 0.7413
    #   [10, 11, 9]          median 10,   MAD 1     -> 1.4826
    #   [10, 11, 9, 10.5]    median 10.25, |d-m| = .25 .75 1.25 .25 -> MAD 0.5 -> 0.7413
    #   [.., 9.5]            median 10,   |d-m| = 0 1 1 .5 .5 -> MAD 0.5 -> 0.7413
    #   [.., 10]             median 10,   |d-m| = 0 1 1 .5 .5 0 -> MAD 0.5 -> 0.7413
    #   [.., 12]             median 10,   |d-m| = 0 1 1 .5 .5 0 2 -> MAD 0.5 -> 0.7413
    #   [.., 8]              median 10,   |d-m| = 0 1 1 .5 .5 0 2 2 -> MAD 0.75 -> 1.11195
    expected = [
        (10.0, 0.0, 0.12),
        (10.5, 0.5, 0.7413),
        (10.0, 1.0, 1.4826),
        (10.25, 0.5, 0.7413),
        (10.0, 0.5, 0.7413),
        (10.0, 0.5, 0.7413),
        (10.0, 0.5, 0.7413),
        (10.0, 0.75, 1.11195),
    ]
    res = _feed(MadGate(), values)
    got = [(r.median_m, r.mad_m, r.sigma_gate_m) for r in res]
    assert got == [pytest.approx(e, abs=1e-12) for e in expected]
    for i, r in enumerate(res):
        _, mad, _ = _hand(values[: i + 1])
        assert r.sigma_gate_m == pytest.approx(max(1.4826 * mad, 0.12), abs=1e-12)
    # 8th sample 8.0: |8 - 10| = 2 <= 3.5 * 1.11195 = 3.89: accepted
    assert all(r.accepted for r in res)


def test_small_mad_uses_floor() -> None:
    # |d - 10| = 0 .05 .05 0 .05 .05 0 0 -> MAD 0.025 -> 1.4826 * 0.025 = 0.037 < 0.12
    values = [10.0, 10.05, 9.95, 10.0, 10.05, 9.95, 10.0, 10.0]
    r = _feed(MadGate(), values)[-1]
    assert r.mad_m == pytest.approx(0.025, abs=1e-12)
    assert r.sigma_gate_m == 0.12


def test_window_drops_samples_older_than_1500ms() -> None:
    # 2 s apart: the window never holds more than the current sample
    gate = MadGate()
    res = _feed(gate, [10.0, 10.0, 10.1, 9.9, 10.0, 10.0, 10.0, 10.0, 10.0, 60.0, 10.0, -40.0],
                dt=2.0)  # fmt: skip
    assert [r.n_window for r in res] == [1] * 12
    assert all(r.accepted for r in res)
    assert all(r.sigma_gate_m == 0.12 for r in res)
    assert gate.n_rejected == 0
    # 0.25 s apart: 0, 0.25, ..., 1.5 s -> at most 7 in the window (a sample exactly 1.5 s
    # old stays), still never 8
    gate = MadGate()
    res = _feed(gate, [10.0] * 20 + [60.0] + [10.0] * 5, dt=0.25)
    assert max(r.n_window for r in res) == 7
    assert all(r.accepted for r in res)
    # 0.125 s apart: 13 in the window, and the same outlier is rejected
    gate = MadGate()
    res = _feed(gate, [10.0, 10.1, 9.9] * 7 + [60.0], dt=0.125)
    assert res[-1].n_window == 13
    assert not res[-1].accepted


def test_old_outliers_leave_the_window() -> None:
    gate = MadGate()
    # a burst of 8 samples at 50 m, then a gap of 2 s, then 10 m: the old burst is gone
    _feed(gate, [50.0, 50.1, 49.9, 50.0, 50.1, 49.9, 50.0, 50.0], dt=0.1)
    res = _feed(gate, [10.0, 10.1, 9.9, 10.0, 10.1, 9.9, 10.0, 10.0], t0=2.7, dt=0.1)
    assert res[0].n_window == 1
    assert all(r.accepted for r in res)
    assert res[-1].median_m == pytest.approx(10.0, abs=1e-12)


def test_constant_window_gives_floor() -> None:
    gate = MadGate()
    res = _feed(gate, [10.0] * 12)
    assert all(r.accepted for r in res)
    assert all(r.mad_m == 0.0 and r.sigma_gate_m == 0.12 for r in res)
    assert res[-1].n_window == 12
    # eq. (2) taken literally: with MAD = 0 the threshold is 0, so once 8 samples are in the
    # window any deviation from the median is rejected, even 1 mm
    assert not gate.check(1.2, 10.001).accepted
    assert gate.check(1.3, 10.0).accepted
