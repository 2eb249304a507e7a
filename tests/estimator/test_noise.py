"""Each mode's R formula (sec. Measurement-Noise Configurations, eqs. 10-14)."""

from __future__ import annotations

import math

import pytest
import scipy.stats

from estimator.noise import (
    AdaptiveR,
    ConstantR,
    EmpiricalR,
    GatedRange,
    GnssCovarianceConfig,
    GnssInflatedR,
    NlosR,
    expected_rssi_dbm,
    skewness,
)
from estimator.records import AssociatedRange


def gr(range_m=74.0, rssi=-70.0, sigma=0.5, acc=1.0, vacc=None, agl=45.0) -> GatedRange:
    m = AssociatedRange(t_s=0.0, bssid="a4:77:33:0f:1e:02", range_m=range_m, rssi_dbm=rssi,
                        anchor_enu_m=(0.0, 0.0, 45.0), anchor_acc_m=acc, anchor_vacc_m=vacc,
                        agl_m=agl)
    return GatedRange(m, sigma)


def test_baseline_is_sigma_gate_squared():
    assert ConstantR().variance(gr(sigma=0.37), 1.0, 2.0) == pytest.approx(0.37**2, abs=1e-15)


def test_empirical_r_formula():
    # d = 74 m, RSSI = -70 dBm: q = 30 dB; R = 0.09 + 4e-4 * 5476 + 3e-3 * 900
    r = EmpiricalR().variance(gr(74.0, -70.0, 0.5), 0.0, 0.0)
    assert r == pytest.approx(0.09 + 2.1904 + 2.7, abs=1e-12)
    # strong signal: q = max(0, 30 - 40) = 0; outer max keeps sigma_gate^2 when larger
    assert EmpiricalR().variance(gr(10.0, -30.0, 0.1), 0, 0) == pytest.approx(0.09 + 0.04)
    assert EmpiricalR().variance(gr(10.0, -30.0, 2.0), 0, 0) == pytest.approx(4.0)
    # missing RSSI contributes q = 0
    assert EmpiricalR().variance(gr(10.0, None, 0.1), 0, 0) == pytest.approx(0.13)


def test_expected_rssi_eq11():
    assert expected_rssi_dbm(1.0) == pytest.approx(-35.0)
    assert expected_rssi_dbm(100.0) == pytest.approx(-35.0 - 60.0)
    assert expected_rssi_dbm(0.2) == pytest.approx(-35.0)  # guarded at d >= 1 m


def test_skewness_matches_scipy():
    vals = [10.0, 10.2, 9.9, 10.1, 14.0, 10.0, 9.8]
    assert skewness(vals) == pytest.approx(scipy.stats.skew(vals, bias=True), abs=1e-12)
    assert skewness([5.0, 5.0, 5.0]) == 0.0


def test_nlos_rssi_rule_inflates_by_nine():
    # d = 50 m: RSSI_exp = -35 - 30 log10(50) = -85.97 dBm
    exp = -35.0 - 30.0 * math.log10(50.0)
    m = NlosR()
    assert m.variance(gr(50.0, exp + 14.9, 0.4), 0, 0) == pytest.approx(0.16)
    m = NlosR()
    assert m.variance(gr(50.0, exp + 15.1, 0.4), 0, 0) == pytest.approx(9 * 0.16)
    m = NlosR()
    assert m.variance(gr(50.0, exp - 15.1, 0.4), 0, 0) == pytest.approx(9 * 0.16)


def test_nlos_skewness_rule():
    exp = lambda d: -35.0 - 30.0 * math.log10(d)  # noqa: E731 - RSSI never triggers
    m = NlosR()
    seq = [50.0, 50.1, 49.9, 50.0, 50.2, 49.8, 50.0]
    for d in seq:
        assert m.variance(gr(d, exp(d), 0.5), 0, 0) == pytest.approx(0.25)
    # a positive-skewed window (NLoS excess) flags: skew of seq + [58] > 1
    window = [*seq, 58.0]
    assert scipy.stats.skew(window) > 1.0
    assert m.variance(gr(58.0, exp(58.0), 0.5), 0, 0) == pytest.approx(9 * 0.25)
    # only the last 20 samples count
    m = NlosR()
    for _ in range(25):
        m.variance(gr(50.0, exp(50.0), 0.5), 0, 0)
    assert len(m.window) == 20


def test_adaptive_r_recursion_and_clipping():
    m = AdaptiveR()
    # R0 = sigma_gate^2 = 1; R1 = 0.95 * 1 + 0.05 * (nu^2 - hph) = 0.95 + 0.05 * (9 - 1)
    assert m.variance(gr(sigma=1.0), 3.0, 1.0) == pytest.approx(1.35)
    assert m.variance(gr(sigma=1.0), 1.0, 0.5) == pytest.approx(0.95 * 1.35 + 0.05 * 0.5)
    low = AdaptiveR()
    assert low.variance(gr(sigma=0.12), 0.0, 100.0) == pytest.approx(0.01)  # clipped low
    high = AdaptiveR()
    assert high.variance(gr(sigma=4.9), 1000.0, 0.0) == pytest.approx(25.0)  # clipped high


def test_gnss_inflation_projects_on_line_of_sight():
    cfg = GnssCovarianceConfig(acc_scale=1.0, vertical_ratio=2.0, floor_m=0.0)
    inner = ConstantR()
    m = GnssInflatedR(inner, cfg, 45.0)
    # range 90 m from 45 m above: c = 0.5; sigma_h = 1.515 / 1.515 = 1, sigma_v = 2
    r = m.variance(gr(90.0, -70.0, 0.5, acc=1.515), 0, 0)
    assert r == pytest.approx(0.25 + 1.0 * 0.75 + 4.0 * 0.25)
