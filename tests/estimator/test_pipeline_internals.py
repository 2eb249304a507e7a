"""Inside the pipeline: the ground prior, restarts, MAD rejections, the table's shape."""

from __future__ import annotations

import copy
import statistics

import numpy as np
import pytest

from estimator.convergence import ConvergenceMonitor
from estimator.filters import FilterError
from estimator.gate import MadGate
from estimator.modes import MODES, PAPER_MODES
from estimator.pipeline import (
    GroundPriorConfig,
    PipelineConfig,
    SharedFront,
    Track,
)
from estimator.records import AssociatedRange
from estimator.replay import ReplayOptions, replay_logs
from tests.estimator import worlds as W  # noqa: N812

AP = np.array([20.0, -8.0, -44.5])


def stream(rate_hz=4.0, duration_s=120.0, seed=0, sigma=0.4, outliers=()):
    """Associated ranges of an orbit at 45 m about AP (periodic ranging)."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, duration_s, 1.0 / rate_hz)
    a = 2 * np.pi * t / 60.0
    r = 45.0 + 15.0 * np.sin(2 * np.pi * t / 90.0)
    u = np.column_stack((r * np.cos(a), r * np.sin(a), 0.5 + 3.0 * np.sin(t / 7.0)))
    d = np.linalg.norm(u - AP, axis=1) + 0.4 + rng.normal(0, sigma, t.size)
    for i in outliers:
        d[i] += 25.0
    return [AssociatedRange(t_s=float(ti), bssid="b", range_m=float(di), rssi_dbm=-75.0,
                            anchor_enu_m=tuple(ui), anchor_acc_m=0.9, agl_m=45.0)
            for ti, di, ui in zip(t, d, u, strict=True)]


def test_ground_prior_is_applied_after_every_accepted_update():
    """Each accepted update is predict + NIS-gated range update with R = sigma_gate^2 +
    the height pseudo-measurement at the median of the last 25 (z_d - H_AGL), R_z = 25
    (eq. 18), exactly; with the prior disabled the height update is skipped."""
    for enabled in (True, False):
        cfg = PipelineConfig(ground=GroundPriorConfig(enabled=enabled))
        tr = Track("b", MODES["baseline"], cfg)
        checked = 0
        for m in stream():
            f = tr.run.filter
            before_acc = tr.counts.n_acc
            if f is not None:
                ref = copy.deepcopy(f)
                gate = copy.deepcopy(tr.front.gate)
                window = [*list(tr.front.ground)[-24:], m.anchor_enu_m[2] - 45.0]
            tr.process(m)
            if f is not None and tr.counts.n_acc == before_acc + 1:
                sg = gate.check(m.t_s, m.range_m).sigma_gate_m
                ref.predict()
                assert ref.update(m.anchor_enu_m, m.range_m, sg * sg).accepted
                if enabled:
                    ref.update_height(statistics.median(window), 25.0)
                assert tr.run.filter.x == ref.x and tr.run.filter.P == ref.P
                checked += 1
        assert checked > 300


def test_adaptive_r_is_wired_into_the_filter_update():
    """Mode adaptive-r: each measurement reaching the filter updates R_hat with nu and
    H P^- H^T at the prior (eq. 24, R_0 = sigma_gate^2, clipped to [0.01, 25]) and the
    update uses exactly that R (then the ground prior)."""
    tr = Track("b", MODES["adaptive-r"])
    checked = 0
    for m in stream():
        f = tr.run.filter
        if f is not None:
            ref = copy.deepcopy(f)
            gate = copy.deepcopy(tr.front.gate)
            window = [*list(tr.front.ground)[-24:], m.anchor_enu_m[2] - 45.0]
            prev = tr.run.noise.r_hat_m2
            before_acc, before_nis = tr.counts.n_acc, tr.counts.n_nis
        tr.process(m)
        if f is None or tr.run.filter is None:
            continue
        sg = gate.check(m.t_s, m.range_m).sigma_gate_m
        ref.predict()
        nu, hph = ref.innovation(m.anchor_enu_m, m.range_m)
        r0 = sg * sg if prev is None else prev
        r = min(25.0, max(0.01, 0.95 * r0 + 0.05 * (nu * nu - hph)))
        assert tr.run.noise.r_hat_m2 == pytest.approx(r, abs=1e-12)
        if tr.counts.n_acc == before_acc + 1:
            assert ref.update(m.anchor_enu_m, m.range_m, r).accepted
            ref.update_height(statistics.median(window), 25.0)
            np.testing.assert_allclose(np.array(tr.run.filter.P), np.array(ref.P), atol=1e-12)
            np.testing.assert_allclose(tr.run.filter.x, ref.x, atol=1e-12)
            checked += 1
        else:
            assert tr.counts.n_nis == before_nis + 1
    assert checked > 300


def _converged_track():
    tr = Track("b", MODES["baseline"])
    ms = stream(duration_s=240.0)
    for m in ms[:400]:
        tr.process(m)
    assert tr.status == "converged"
    return tr, ms


@pytest.mark.parametrize("where", ["update", "update_height"])
def test_restart_keeps_the_count_identity_and_resets_n_acc(where):
    tr, ms = _converged_track()
    c = tr.counts
    before = (c.n_meas, c.n_bootstrap, c.n_gate, c.n_acc)
    f = tr.run.filter

    def broken(*a, **k):
        raise FilterError("covariance is not positive")

    setattr(f, where, broken)
    tr.process(ms[400])
    assert tr.status == "diverged" and c.n_restarts == 1
    assert c.n_meas == before[0] + 1
    # everything the discarded filter counted, and the measurement that broke it, is
    # now bootstrap; the post-bootstrap counts restart at zero
    assert c.n_bootstrap == before[1] + before[2] + before[3] + 1
    assert (c.n_gate, c.n_mad, c.n_nis, c.n_acc) == (0, 0, 0, 0)
    assert c.n_meas == c.n_bootstrap + c.n_gate + c.n_acc
    assert tr.last is None and tr.last_stable is None
    first_stable = None
    for m in ms[401:]:
        pub = tr.process(m)
        assert c.n_meas == c.n_bootstrap + c.n_gate + c.n_acc
        if pub is not None and pub.stable and first_stable is None:
            first_stable = pub
    assert tr.status == "converged"
    # converged again only on the new filter's own accepted updates (>= 10 relaxed)
    assert first_stable.accepted_index >= 10


def test_mad_rejections_reset_the_streak():
    ms = stream(rate_hz=10.0, duration_s=60.0, outliers=(450,))
    tr = Track("b", MODES["baseline"])
    for m in ms[:450]:
        tr.process(m)
    assert tr.monitor.streak > 3
    n_mad = tr.counts.n_mad
    assert tr.process(ms[450]) is None
    assert tr.counts.n_mad == n_mad + 1  # rejected by the MAD gate, not the NIS gate
    assert tr.monitor.streak == 0


def test_mad_gate_never_fires_at_4_hz_and_fires_at_10_hz():
    """1.5 s at 4 Hz holds at most 7 samples (< N_min = 8): gross outliers pass the MAD
    gate (only the NIS gate can stop them); at 10 Hz it rejects every one of them."""
    out = set(range(20, 400, 37))
    for rate in (4.0, 10.0):
        gate = MadGate()
        rng = np.random.default_rng(1)
        rejected = set()
        for k in range(400):
            d = 70.0 + 0.01 * k + rng.normal(0, 0.3) + (30.0 if k in out else 0.0)
            if not gate.check(k / rate, d).accepted:
                rejected.add(k)
        if rate == 4.0:
            assert rejected == set()
        else:
            assert out <= rejected and len(rejected) < len(out) + 6


def test_relaxation_is_not_latched():
    """n_acc = 12 (between the relaxed 10 and the strict 15): stable only while sigma_H
    has been non-increasing for >= 5 published updates; a 5 % rise ends the run and the
    strict threshold is back (the relaxation is not latched)."""
    mon = ConvergenceMonitor()
    out = []
    for s in [2.0] * 7 + [2.1] * 3:
        mon.on_accepted()
        out.append(mon.on_published((0.0, 0.0, 0.0), s, 1.0, 12))
    assert out == [False] * 5 + [True, True] + [False] * 3
    assert mon.non_increasing == 2


def test_paper_table_shape_on_a_seeded_flight(tmp_path):
    """The shape of the paper's table (sec. Results): EMA gates exactly as Baseline (same
    filter, another smoother), Empirical-R gates about none, Adaptive-R fewer than
    Baseline; n_gate + n_acc = n_meas - n_bootstrap, and the MAD gate never fires at 4 Hz."""
    w = W.los_world(1, tmp_path)
    rep = replay_logs(w.paths, ReplayOptions(modes=PAPER_MODES, keep_history=False))
    c = {t.mode: t.counts for t in rep.tracks}
    assert c["ema"] == c["baseline"]
    post = c["baseline"]["n_meas"] - c["baseline"]["n_bootstrap"]
    assert c["empirical-r"]["n_gate"] <= 0.01 * post
    assert c["adaptive-r"]["n_gate"] < 0.5 * c["baseline"]["n_gate"]
    assert c["baseline"]["n_gate"] >= 20
    for k in c.values():
        assert k["n_mad"] == 0
        assert k["n_gate"] + k["n_acc"] == k["n_meas"] - k["n_bootstrap"]
    assert (c["baseline"]["n_meas"], c["baseline"]["n_bootstrap"]) == (511, 24)


def test_refined_mode_needs_its_own_track_class():
    with pytest.raises(ValueError):
        Track("b", MODES["refined"])
    with pytest.raises(TypeError):  # names are resolved at the edge, not by a track
        Track("b", "baseline")
    front = SharedFront()
    assert front.filter_run(Track("b", MODES["baseline"], front=front).spec) is not None
