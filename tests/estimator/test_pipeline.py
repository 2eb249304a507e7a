"""The whole pipeline on seeded synthetic flights: errors against truth, counts, fusion."""

from __future__ import annotations

import json

import numpy as np
import pytest

from estimator.modes import MODES, PAPER_MODES
from estimator.pipeline import Track
from estimator.records import AssociatedRange
from estimator.replay import ReplayOptions, parse_modes, replay_logs
from tests.estimator.synth import BSSID, write_flight


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    return write_flight(tmp_path_factory.mktemp("f") / "flight.jsonl", seed=11)


@pytest.fixture(scope="module")
def report(flight):
    return replay_logs([flight], ReplayOptions(modes=(*PAPER_MODES, "robust")))


@pytest.mark.parametrize("mode", [*PAPER_MODES, "robust"])
def test_seeded_flight_final_error_below_3m(report, mode):
    t = report.get(BSSID, mode)
    assert t.status == "converged"
    assert t.err_h_m < 3.0
    assert t.err_3d_m < 8.0
    assert t.twm_h_m < 3.0


def test_counts_add_up(report):
    for t in report.tracks:
        c = t.counts
        assert c["n_meas"] == c["n_bootstrap"] + c["n_gate"] + c["n_acc"]
        assert c["n_gate"] == c["n_mad"] + c["n_nis"]
        assert c["n_meas"] == 720  # 4 Hz x 180 s, all associated
    # the gate and bootstrap are shared: every paper mode bootstraps on the same samples
    nb = {t.counts["n_bootstrap"] for t in report.tracks if t.mode in PAPER_MODES}
    assert len(nb) == 1


def test_json_contract(report):
    js = report.to_json()
    assert js["logs"] == 1 and js["rejected_lines"] == {}
    e = js["estimates"][0]
    for k in ("bssid", "mode", "status", "converged", "lat", "lon", "alt_m", "sigma_h_m",
              "sigma_z_m", "bias_m", "n_meas", "n_bootstrap", "n_acc", "n_gate", "err_h_m",
              "err_3d_m", "twm_h_m"):
        assert k in e
    json.dumps(js, allow_nan=False)
    # lat/lon are WGS84 of the estimate: about the truth's within the error
    assert abs(e["lat"] - 36.7151) < 0.01 and abs(e["lon"] + 4.4783) < 0.01


def test_exact_projection_gives_same_answer(flight, report):
    r2 = replay_logs([flight], ReplayOptions(modes=("baseline",), projection="wgs84"))
    a, b = report.get(BSSID, "baseline"), r2.get(BSSID, "baseline")
    # eq. (1) vs exact WGS84 ENU over a ~100 m flight: the outputs agree to a few cm
    dn = (a.lat_deg - b.lat_deg) * 111_000.0
    de = (a.lon_deg - b.lon_deg) * 111_000.0 * np.cos(np.radians(a.lat_deg))
    assert np.hypot(dn, de) < 0.1


def test_same_input_same_output(flight):
    a = replay_logs([flight], ReplayOptions(modes=PAPER_MODES)).to_json()
    b = replay_logs([flight], ReplayOptions(modes=PAPER_MODES)).to_json()
    assert a == b


def test_fusion_of_two_agents_with_different_clocks(tmp_path):
    # the second agent's phone booted at another time: clocks differ by 1000 s
    a = write_flight(tmp_path / "a.jsonl", seed=1, duration_s=90.0)

    def other(t):
        ang = -2 * np.pi * t / 50.0
        return np.column_stack((60 + 40 * np.cos(ang), -20 + 40 * np.sin(ang), 40 + 0 * t))

    b = write_flight(tmp_path / "b.jsonl", seed=2, duration_s=90.0, path_fn=other,
                     t0_ns=1_000_000_000_000_000, agent="uav-2")
    r = replay_logs([a, b], ReplayOptions(modes=("baseline",)))
    t = r.get(BSSID, "baseline")
    ra = replay_logs([a], ReplayOptions(modes=("baseline",))).get(BSSID, "baseline")
    assert r.n_logs == 2
    assert t.counts["n_meas"] == 2 * 360
    assert t.status == "converged" and t.err_h_m < 3.0
    assert ra.counts["n_meas"] == 360


def test_straight_pass_is_weak_geometry(tmp_path):
    def line(t):
        return np.column_stack((-14 + 28 * t / 21.0, 30 + 0.2 * np.sin(t), 45 + 0 * t))

    p = write_flight(tmp_path / "ab.jsonl", seed=3, duration_s=21.0, path_fn=line,
                     rtt_rate_hz=1.5)
    r = replay_logs([p], ReplayOptions(modes=PAPER_MODES))
    for t in r.tracks:
        assert t.status == "weak_geometry"
        assert t.estimate is None and t.err_h_m is None
        assert t.kappa > 10
    js = r.to_json()["estimates"][0]
    assert "lat" not in js and "err_h_m" not in js


def test_no_data_for_responder_without_usable_ranges(tmp_path):
    lines = (
        '{"type":"rtt","t_ns":5000000100000000,"bssid":"00:11:22:33:44:55",'
        '"status":"no_response"}',
        '{"type":"rtt","t_ns":5000000200000000,"bssid":"00:11:22:33:44:55","status":"fail"}',
        "not json at all",
    )
    p = write_flight(tmp_path / "nd.jsonl", seed=4, duration_s=60.0, extra_lines=lines)
    r = replay_logs([p], ReplayOptions(modes=("baseline",)))
    nd = r.get("00:11:22:33:44:55", "baseline")
    assert nd.status == "no_data" and nd.estimate is None
    assert r.rejected.rejected["not_json"] == 1
    assert r.get(BSSID, "baseline").counts["n_meas"] == 240


def test_track_alone_matches_replay(report, flight):
    """A standalone Track fed the same associated ranges reproduces the replay's track."""
    from estimator.association import Associator
    from estimator.geodesy import TangentPlaneENU
    from estimator.logio import read_log

    log = read_log(flight)
    geo = list(Associator().run(sorted(log.gnss + log.rtt, key=lambda r: r.t_ns)))
    fr = TangentPlaneENU(geo[0].lat_deg, geo[0].lon_deg, geo[0].alt_m)
    tr = Track(BSSID, MODES["empirical-r"])
    for g in geo:
        tr.process(AssociatedRange(t_s=g.t_ns * 1e-9, bssid=g.bssid, range_m=g.range_m,
                                   rssi_dbm=g.rssi_dbm,
                                   anchor_enu_m=fr.to_enu(g.lat_deg, g.lon_deg, g.alt_m),
                                   anchor_acc_m=g.acc_m, agl_m=45.0))
    ref = report.get(BSSID, "empirical-r")
    assert tr.reported().enu_m == ref.estimate.enu_m
    assert tr.counts.n_acc == ref.counts["n_acc"]


def test_parse_modes():
    assert parse_modes("all") == PAPER_MODES
    assert len(PAPER_MODES) == 6 and "robust" not in PAPER_MODES
    assert parse_modes("ukf,ema") == ("ukf", "ema")
    with pytest.raises(ValueError):
        parse_modes("kalman")
    assert set(MODES) >= set(PAPER_MODES)


def test_online_twm_equals_history_twm(flight, report):
    from estimator.evaluation import twm_of_history as _twm

    lean = replay_logs([flight], ReplayOptions(modes=PAPER_MODES, keep_history=False))
    for t in report.tracks:
        if t.mode not in PAPER_MODES:
            continue
        u = lean.get(BSSID, t.mode)
        assert u.history == []
        assert u.twm_h_m == pytest.approx(_twm(t.history, t.truth_enu_m), abs=1e-9)
        assert u.twm_h_m == pytest.approx(t.twm_h_m, abs=1e-9)
        assert u.err_h_m == t.err_h_m
