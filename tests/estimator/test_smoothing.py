"""Output smoothers (sec. Measurement-Noise Configurations): sliding median, EMA."""

from __future__ import annotations

import numpy as np
import pytest

from estimator.smoothing import (
    EmaSmoother,
    EmaSmootherConfig,
    MedianSmoother,
    MedianSmootherConfig,
)


def test_median_smoother_windows_7_and_9():
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(30, 3)) * [5.0, 5.0, 10.0]
    sm = MedianSmoother()
    for k, p in enumerate(pts):
        out = sm.push(tuple(p))
        assert out[0] == np.median(pts[max(0, k - 6):k + 1, 0])  # W_xy = 7
        assert out[1] == np.median(pts[max(0, k - 6):k + 1, 1])
        assert out[2] == np.median(pts[max(0, k - 8):k + 1, 2])  # W_z = 9
    # an outlier within the window does not move the median
    sm2 = MedianSmoother(MedianSmootherConfig(window_xy=3, window_z=3))
    sm2.push((1.0, 1.0, 1.0))
    sm2.push((1.2, 0.8, 1.1))
    assert sm2.push((90.0, -90.0, 50.0)) == (1.2, 0.8, 1.1)


def test_ema_smoother_recursion():
    pts = [(1.0, 2.0, 3.0), (2.0, 0.0, 5.0), (4.0, 4.0, -1.0), (0.0, 1.0, 2.0)]
    sm = EmaSmoother()
    s = np.array(pts[0])
    assert sm.push(pts[0]) == pts[0]  # s_0 = x_0
    for p in pts[1:]:
        s = 0.3 * np.array(p) + 0.7 * s
        np.testing.assert_allclose(sm.push(p), s, atol=1e-12)
    sm = EmaSmoother(EmaSmootherConfig(alpha=1.0))
    sm.push((1.0, 1.0, 1.0))
    assert sm.push((5.0, 6.0, 7.0)) == pytest.approx((5.0, 6.0, 7.0))
