"""Convergence rules and their relaxation on crafted sequences."""

from __future__ import annotations

from estimator.convergence import ConvergenceMonitor


def feed(mon: ConvergenceMonitor, sigmas, n_acc0=1, pos=(0.0, 0.0, 0.0), sz=1.0):
    out = []
    for k, s in enumerate(sigmas):
        mon.on_accepted()
        out.append(mon.on_published(pos, s, sz, n_acc0 + k))
    return out


def test_all_conditions_required():
    # strictly increasing by 5 %: never relaxes; n_acc reaches 15 at index 14
    mon = ConvergenceMonitor()
    res = feed(mon, [1.0 * (1.05**k) for k in range(16)])
    assert res[:14] == [False] * 14
    assert res[14] and res[15]  # n_acc = 15, 16; sigma_H < 2.5; streak >= 3


def test_sigma_limits():
    mon = ConvergenceMonitor()
    assert not any(feed(mon, [2.6] * 20, n_acc0=20))
    mon = ConvergenceMonitor()
    res = feed(mon, [1.0] * 5, n_acc0=20, sz=8.5)
    assert not any(res)
    mon = ConvergenceMonitor()
    res = feed(mon, [1.0] * 5, n_acc0=20, sz=7.9)
    # the first has no jump reference, the second a streak of 2 < 3
    assert res == [False, False, True, True, True]


def test_jump_limits():
    mon = ConvergenceMonitor()
    feed(mon, [0.4] * 5, n_acc0=20)
    mon.on_accepted()
    # dxy limit = max(1, 2 * 0.4) = 1 m
    assert not mon.on_published((1.01, 0.0, 0.0), 0.4, 1.0, 30)
    mon.on_accepted()
    assert mon.on_published((1.5, 0.5, 0.0), 0.4, 1.0, 31)  # moved 0.707 m
    mon.on_accepted()
    # dz limit = max(2, 2 * 1.0) = 2 m
    assert not mon.on_published((1.5, 0.5, 2.1), 0.4, 1.0, 32)
    mon.on_accepted()
    assert mon.on_published((1.5, 0.5, 3.0), 0.4, 3.0, 33)  # limit 6 m with sigma_Z 3


def test_streak_reset_and_relaxation():
    mon = ConvergenceMonitor()
    # sigma_H decreasing: non-increasing count grows with every published update
    res = feed(mon, [2.0, 1.9, 1.8, 1.7, 1.6, 1.5], n_acc0=10)
    # non_increasing after k-th publish = k-1; n_acc relaxes to 10 at >= 5 (6th publish)
    assert res == [False, False, False, False, False, True]
    mon.on_rejected()  # NIS rejection resets the streak
    mon.on_accepted()
    assert not mon.on_published((0, 0, 0), 1.4, 1.0, 16)  # streak 1
    mon.on_accepted()
    # non_increasing now 7 (< 8): streak 2 is not enough
    assert not mon.on_published((0, 0, 0), 1.4, 1.0, 17)
    mon.on_rejected()
    mon.on_accepted()
    mon.on_accepted()  # streak 2
    # non_increasing reaches 8: streak requirement drops to 2
    assert mon.on_published((0, 0, 0), 1.39, 1.0, 18)


def test_two_percent_tolerance():
    mon = ConvergenceMonitor()
    feed(mon, [1.0, 1.019, 1.0389])  # each within +2 % of the previous
    assert mon.non_increasing == 2
    mon.on_accepted()
    mon.on_published((0, 0, 0), 1.07, 1.0, 5)  # +3 %: resets
    assert mon.non_increasing == 0
