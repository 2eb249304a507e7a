"""FTM sensor model: the simulated errors, rates and statuses match the configuration."""

from __future__ import annotations

import math

import numpy as np
import pytest

from estimator.noise import EmpiricalRConfig, empirical_r_m2
from sim import ClockConfig, ConcealmentModel, FtmConfig, run_scenario
from sim.ftm import STATUS_NAMES, STATUS_OK, simulate_ftm

from .util import hover_track, responder, scenario, with_ftm

ALWAYS = dict(response_rssi50_dbm=-140.0, response_max=1.0, reach_rssi_dbm=-200.0)


@pytest.fixture(scope="module")
def clean_run():
    """One open responder, every attempt answered, no outliers: pure range noise."""
    ftm = with_ftm(FtmConfig(), **ALWAYS, open=ConcealmentModel(outlier_prob=0.0))
    return run_scenario(scenario([responder()], ftm=ftm), seed=11)


def test_range_noise_matches_empirical_r_model(clean_run):
    f = clean_run.ftm
    ok = f.ok
    n = int(ok.sum())
    assert n > 1000
    cfg = clean_run.scenario.ftm
    # sigma is eq. (13) with the estimator's coefficients, times noise_scale
    expected = np.array(
        [
            math.sqrt(empirical_r_m2(d, r, 0.0, EmpiricalRConfig()))
            for d, r in zip(f.true_range_m[ok], f.rssi_dbm[ok], strict=True)
        ]
    )
    np.testing.assert_allclose(f.sigma_m[ok], cfg.noise_scale * expected, rtol=1e-12)
    # the residual after the hardware offset is N(0, sigma^2)
    z = (f.range_m[ok] - f.true_range_m[ok] - f.offsets_m[0]) / f.sigma_m[ok]
    assert abs(z.mean()) < 4.0 / math.sqrt(n)
    assert abs(z.std() - 1.0) < 4.0 / math.sqrt(2 * n)
    assert abs(np.mean(np.abs(z) < 1.0) - 0.6827) < 4 * math.sqrt(0.68 * 0.32 / n)
    # the error spread grows with distance as the model says
    far = f.true_range_m[ok] > np.median(f.true_range_m[ok])
    err = f.range_error_m[ok]
    assert err[far].std() > err[~far].std()


def test_hardware_offset_constant_and_in_range(clean_run):
    f = clean_run.ftm
    assert 0.3 <= f.offsets_m[0] <= 1.0
    ok = f.ok
    mean_err = float(np.mean(f.range_error_m[ok]))
    sem = float(np.sqrt(np.mean(f.sigma_m[ok] ** 2) / ok.sum()))
    assert abs(mean_err - f.offsets_m[0]) < 4 * sem


def test_multipath_outliers_rate_and_skew():
    ftm = with_ftm(FtmConfig(), **ALWAYS, open=ConcealmentModel(outlier_prob=0.08))
    f = run_scenario(scenario([responder()], ftm=ftm), seed=3).ftm
    ok = f.ok
    n = int(ok.sum())
    rate = f.outlier[ok].mean()
    assert abs(rate - 0.08) < 4 * math.sqrt(0.08 * 0.92 / n)
    excess = f.outlier_excess_m[ok & f.outlier]
    assert np.all(excess > 0)
    # log-normal with median 4 m
    assert abs(np.median(excess) - ftm.outlier_median_m) < 0.2 * ftm.outlier_median_m
    err = f.range_error_m[ok] - f.offsets_m[0]
    skew = np.mean((err - err.mean()) ** 3) / err.std() ** 3
    assert skew > 1.0  # positive heavy tail


def test_vegetation_adds_positive_nlos_excess():
    veg = ConcealmentModel(
        attenuation_db=5.0, nlos_excess_min_m=0.3, nlos_excess_mean_m=1.2, outlier_prob=0.0
    )
    ftm = with_ftm(FtmConfig(), **ALWAYS, vegetation=veg)
    f = run_scenario(scenario([responder(concealment="vegetation")], ftm=ftm), seed=5).ftm
    ok = f.ok
    n = int(ok.sum())
    excess = f.range_m[ok] - f.true_range_m[ok] - f.offsets_m[0] - f.noise_m[ok]
    np.testing.assert_allclose(excess, f.nlos_excess_m[ok], atol=1e-9)
    assert excess.min() >= 0.3 - 1e-12
    assert abs(excess.mean() - 1.5) < 4 * 1.2 / math.sqrt(n)
    # attenuation: vegetation RSSI sits 5 dB under the open-air path loss (plus shadowing)
    model = ftm.mean_rssi_dbm(f.true_range_m, 5.0)
    assert abs(np.mean(f.rssi_mean_dbm - model)) < 1.5


def test_response_rate_matches_model_and_falls_with_range():
    r = run_scenario(scenario([responder()]), seed=2)  # default FTM configuration
    f, cfg = r.ftm, r.scenario.ftm
    n_ok = int(f.ok.sum())
    expected = float(f.p_ok.sum())
    sd = math.sqrt(float(np.sum(f.p_ok * (1 - f.p_ok))))
    assert abs(n_ok - expected) < 4 * sd
    x = (f.rssi_dbm - cfg.response_rssi50_dbm) / cfg.response_slope_db
    np.testing.assert_allclose(f.p_ok, cfg.response_max / (1 + np.exp(-x)), rtol=1e-12)
    near = f.true_range_m < 70
    far = f.true_range_m > 100
    assert near.sum() > 100 and far.sum() > 100
    assert f.ok[near].mean() > f.ok[far].mean() + 0.2
    # failures are split between no_response and fail as configured
    failed = ~f.ok
    frac = np.mean(f.status[failed] == STATUS_NAMES.index("no_response"))
    assert abs(frac - cfg.no_response_fraction) < 4 * math.sqrt(0.21 / failed.sum())


def test_blocked_responder_never_answers():
    ftm = with_ftm(FtmConfig(), reach_rssi_dbm=-200.0)  # in reach: attempts are logged
    r = run_scenario(scenario([responder(concealment="vegetation_debris")], ftm=ftm), seed=1)
    f = r.ftm
    assert len(f.t_s) > 500
    assert not f.ok.any()
    assert np.all(f.successful == 0)
    assert np.all(np.isnan(f.range_m))


def test_request_rate_between_3_and_5_hz():
    track = hover_track(600.0, enu=(0.0, 40.0, 45.0))
    world = scenario([responder()]).world
    f = simulate_ftm(track, world, FtmConfig(), ClockConfig(), np.random.default_rng(0))
    gaps = np.diff(f.request_t_s)
    assert gaps.min() >= 0.2 - 1e-9 and gaps.max() <= 1 / 3 + 1e-9
    assert abs(1 / gaps.mean() - 3.75) < 0.1  # mean of U(1/5, 1/3) s gaps
    # one result per request; the callback comes after the burst
    assert len(f.t_s) == len(f.request_t_s)
    assert np.all(f.t_delivery_s > f.t_s)


def test_ranging_budget_shared_between_responders():
    rs = [
        responder(name=f"AP{i}", bssid=f"a4:77:33:0f:1e:{i:02x}", e_m=3.0 * i, n_m=10.0)
        for i in range(12)
    ]
    world = scenario(rs).world
    track = hover_track(300.0, enu=(15.0, 0.0, 45.0))
    cfg = FtmConfig()
    f = simulate_ftm(track, world, cfg, ClockConfig(), np.random.default_rng(4))
    assert np.all(f.request_peers == 10)  # Android ranges at most 10 peers per request
    per = np.bincount(f.responder, minlength=12)
    # hovering, the ranking is fixed: the two weakest of the 12 are never ranged
    assert np.sum(per == 0) == 2
    assert len(set(per[per > 0])) == 1
    assert len(f.t_s) == 10 * len(f.request_t_s)
    # each extra peer lengthens a request by per_peer_s: fewer requests per second
    mean_gap = 0.5 * (1 / 5 + 1 / 3)
    expected_hz = 1 / (mean_gap + cfg.per_peer_s * 9)
    assert abs(len(f.request_t_s) / 300.0 - expected_hz) < 0.1


def test_rssi_is_integer_and_statuses_known(clean_run):
    f = clean_run.ftm
    assert f.rssi_dbm.dtype.kind == "i"
    assert set(np.unique(f.status)) <= set(range(len(STATUS_NAMES)))
    ok = f.status == STATUS_OK
    assert np.all((f.successful[ok] >= 1) & (f.successful[ok] <= 8))
    assert np.all(f.range_std_m[ok] >= 0)


def test_slant_range_is_3d_from_gnss_antenna(clean_run):
    f = clean_run.ftm
    resp = clean_run.responder_enu_m[0]
    pos = clean_run.vehicle.position_at(f.t_s)
    np.testing.assert_allclose(f.true_range_m, np.linalg.norm(pos - resp, axis=1), atol=1e-9)
    # the drone flies 45 m above the (hilly) ground: slant, not horizontal, range
    horiz = np.hypot(*(pos[:, :2] - resp[:2]).T)
    assert np.all(pos[:, 2] - resp[2] > 25.0)
    np.testing.assert_allclose(f.true_range_m**2 - horiz**2, (pos[:, 2] - resp[2]) ** 2)


def test_bad_ftm_config_is_refused():
    with pytest.raises(ValueError, match="finite"):
        FtmConfig(rssi_1m_dbm=float("nan"))
    with pytest.raises(ValueError, match="max_peers"):
        FtmConfig(max_peers=0)
    with pytest.raises(ValueError, match="request_rate_max_hz"):
        FtmConfig(request_rate_min_hz=5.0, request_rate_max_hz=3.0)
    with pytest.raises(ValueError, match="outlier_prob"):
        ConcealmentModel(outlier_prob=1.5)


def test_link_model_is_the_simulators_mean_response():
    """sim.FtmLink (what the planner is given) against the simulator's own response
    averaged over its shadowing and fading by Gauss-Hermite quadrature, the reach test
    on the shadowed mean RSSI included: within 0.02 from 5 to 300 m, for every class;
    CasADi evaluates it."""
    import casadi as ca

    from sim.ftm import FtmLink

    cfg = FtmConfig()
    link = FtmLink(cfg)
    x, w = np.polynomial.hermite_e.hermegauss(60)
    d = np.linspace(5.0, 300.0, 119)
    ww = np.outer(w, w) / w.sum() ** 2
    for name in ("open", "vegetation", "vegetation_debris"):
        m = cfg.concealment(name)
        mean = cfg.mean_rssi_dbm(d, m.attenuation_db)[:, None, None]
        shadowed = mean + m.shadowing_sigma_db * x[None, :, None]
        rssi = shadowed + cfg.fading_sigma_db * x[None, None, :]
        p = cfg.response_probability(rssi, m.response_scale) * (shadowed >= cfg.reach_rssi_dbm)
        p_sim = (p * ww[None]).sum(axis=(1, 2))
        assert np.abs(link.response_probability(d, name) - p_sim).max() <= 0.02, name
    assert link.response_probability(500.0) < 1e-3
    assert float(link.response_probability(ca.DM(57.5))) == pytest.approx(
        float(link.response_probability(57.5)), abs=1e-12
    )
    assert link.ranging_rate_hz == pytest.approx(3.75)
