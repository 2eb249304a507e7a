"""Terrain occlusion of the FTM link (sim.occlusion): a single ridge against a hand
computation of ITU-R P.526's knife edge, clearance, monotonicity, the radio's RSSI,
response and range, the clearance tables, and nothing changed where nothing obstructs."""

from __future__ import annotations

import dataclasses
import hashlib
import math

import numpy as np
import pytest
from scipy.special import erf

from sim import ClockConfig, FtmConfig, FtmLink, GridTerrain, HillsTerrain, Origin, World
from sim import simulate as simulate_scenario
from sim.ftm import simulate_ftm
from sim.occlusion import (
    J_GRAZING_DB,
    Occluder,
    knife_edge_loss_db,
    link_obstruction,
    profile_nu,
    wavelength_m,
)
from sim.scenario import load_scenario

from .util import hover_track, responder, scenario, with_ftm

LAM = 299_792_458.0 / 5.18e9
A = np.array([-20.0, 0.0, 0.5])  # the responder's antenna: 0.5 m above flat ground
B = np.array([20.0, 0.0, 20.5])  # the drone's antenna, 40 m east and 20 m up


def ridge(height_m: float) -> GridTerrain:
    """Flat ground with a one-node-wide ridge along e = 0 (a 2 m wide tent, 1 m grid):
    the profile of A -> B samples it at its crest (t = 1/2 of 19 samples 2 m apart)."""
    h = np.zeros((81, 81))
    h[:, 40] = height_m
    return GridTerrain(h, -40.0, -40.0, 1.0)


def hand_nu(height_m: float) -> float:
    """nu of the crest P = (0, 0, H): Delta = |AP| + |PB| - |AB|, nu = +-2 sqrt(Delta/lambda)."""
    delta = (math.hypot(20.0, height_m - 0.5) + math.hypot(20.0, 20.5 - height_m)
             - math.hypot(40.0, 20.0))
    return math.copysign(2.0 * math.sqrt(delta / LAM), height_m - 10.5)


def hand_j(nu: float) -> float:
    if nu <= -0.78:
        return 0.0
    return 6.9 + 20.0 * math.log10(math.sqrt((nu - 0.1) ** 2 + 1.0) + nu - 0.1)


def test_knife_edge_loss_is_p526_j() -> None:
    nu = np.array([-3.0, -0.78, -0.7, 0.0, 0.5, 1.0, 2.4, 10.0])
    want = [hand_j(float(v)) for v in nu]
    np.testing.assert_allclose(knife_edge_loss_db(nu), want, rtol=0, atol=1e-12)
    assert knife_edge_loss_db(-0.78) == 0.0 and abs(J_GRAZING_DB - 6.0329) < 1e-4
    assert abs(hand_j(-0.7799999)) < 0.01  # J is (nearly) continuous at the cut
    assert wavelength_m(5.18e9) == pytest.approx(0.057875, abs=1e-6)


@pytest.mark.parametrize("height", [11.5, 10.8, 10.5, 12.0, 14.0])
def test_single_ridge_matches_the_hand_computation(height: float) -> None:
    """nu, J(nu) and the range excess (the path over the crest minus the direct path)
    of a ridge above (or just below) the line of sight, to 1e-9."""
    ob = link_obstruction(A, B, ridge(height), 5.18e9, 2.0)
    nu = hand_nu(height)
    assert ob.nu[0] == pytest.approx(nu, abs=1e-9)
    assert ob.loss_db[0] == pytest.approx(hand_j(nu), abs=1e-9)
    excess = (math.hypot(20.0, height - 0.5) + math.hypot(20.0, 20.5 - height)
              - math.hypot(40.0, 20.0)) if height > 10.5 else 0.0
    assert ob.excess_m[0] == pytest.approx(excess, abs=1e-9)
    # P.526's own form, nu = h sqrt(2/lambda (1/d1 + 1/d2)) with h across the line, agrees
    # to second order
    h_perp = (height - 10.5) * 40.0 / math.hypot(40.0, 20.0)
    d1 = d2 = 0.5 * math.hypot(40.0, 20.0)
    assert ob.nu[0] == pytest.approx(h_perp * math.sqrt(2 / LAM * (1 / d1 + 1 / d2)), rel=1e-3)


def test_first_fresnel_clearance_gives_no_loss_and_the_loss_grows_with_the_ridge() -> None:
    s = math.hypot(40.0, 20.0)
    r1 = math.sqrt(LAM * (s / 2) ** 2 / s)  # first Fresnel radius at mid-path
    crest = 10.5 - r1 * s / 40.0  # r1 below the line, measured across it
    ob = link_obstruction(A, B, ridge(crest), 5.18e9, 2.0)
    assert ob.nu[0] == pytest.approx(-math.sqrt(2.0), abs=2e-3)  # on the first ellipsoid
    assert ob.loss_db[0] == 0.0 and ob.excess_m[0] == 0.0
    heights = np.linspace(crest, 16.0, 60)
    obs = [link_obstruction(A, B, ridge(h), 5.18e9, 2.0) for h in heights]
    loss = np.array([o.loss_db[0] for o in obs])
    excess = np.array([o.excess_m[0] for o in obs])
    nu = np.array([o.nu[0] for o in obs])
    assert np.all(np.diff(nu) > 0) and np.all(np.diff(loss) >= 0) and np.all(np.diff(excess) >= 0)
    assert loss[0] == 0.0 and loss[-1] > 25.0 and np.all(np.diff(loss[loss > 0]) > 0)
    # 2.4 GHz: a first Fresnel zone sqrt(5.18 / 2.412) wider, nu smaller by as much
    ob24 = link_obstruction(A, B, ridge(12.0), 2.412e9, 2.0)
    assert ob24.nu[0] == pytest.approx(hand_nu(12.0) * math.sqrt(2.412 / 5.18), rel=1e-12)


def _hover(height: float, cfg: FtmConfig, seed: int = 4):
    world = World(Origin(), ridge(height), (responder(e_m=-20.0, n_m=0.0),))
    track = hover_track(600.0, enu=tuple(B))
    return simulate_ftm(track, world, cfg, ClockConfig(), np.random.default_rng(seed))


def test_the_radio_lowers_the_rssi_and_lengthens_the_range_by_the_hand_values() -> None:
    """A hovering drone behind the ridge: the same seed with and without occlusion meets
    the same draws; the mean RSSI drops by J(nu), the response follows the logistic of
    the lower RSSI, an ok range is longer by Delta (no NLoS excess configured), and
    with the NLoS-like excess its mean is (J - J(0)) x occlusion_excess_m_per_db."""
    height = 10.8
    nu = hand_nu(height)
    j, delta = hand_j(nu), LAM * nu * nu / 4.0
    assert 9.0 < j < 11.0
    cfg0 = FtmConfig(occlusion_excess_m_per_db=0.0)
    on, off = _hover(height, cfg0), _hover(height, dataclasses.replace(cfg0, occlusion=False))
    assert len(on.t_s) > 1500 and len(off.t_s) > len(on.t_s) * 0.9
    ko = np.searchsorted(off.request, on.request)
    assert np.array_equal(off.request[ko], on.request)  # every occluded request also off
    np.testing.assert_allclose(on.occlusion_loss_db, j, rtol=0, atol=1e-9)
    np.testing.assert_allclose(off.rssi_mean_dbm[ko] - on.rssi_mean_dbm, j, rtol=0, atol=1e-9)
    # the same ranging draw, scaled by eq. (13)'s sigma at the lower RSSI
    np.testing.assert_allclose(on.noise_m / on.sigma_m, off.noise_m[ko] / off.sigma_m[ko],
                               rtol=1e-12)
    np.testing.assert_allclose(on.p_ok, cfg0.response_probability(on.rssi_dbm), rtol=1e-15)
    assert on.ok.mean() < off.ok[ko].mean() - 0.3  # fewer answers
    both = on.ok & off.ok[ko]
    assert both.sum() > 50
    np.testing.assert_allclose(on.occlusion_excess_m, delta, rtol=0, atol=1e-9)
    longer = (on.range_m - on.noise_m)[both] - (off.range_m - off.noise_m)[ko][both]
    np.testing.assert_allclose(longer, delta, rtol=0, atol=1e-9)
    # the response probability the planner is given, by hand: the mean RSSI J lower
    c = cfg0
    mean = c.rssi_1m_dbm - 10 * c.path_loss_exponent * math.log10(math.hypot(40, 20)) - j
    spread = math.hypot(2.0, 2.0) / c.response_slope_db
    x = (mean - c.response_rssi50_dbm) / c.response_slope_db / math.sqrt(1 + math.pi *
                                                                         spread**2 / 8)
    p = c.response_max * 0.5 * (1 + math.tanh(0.5 * x)) * 0.5 * (
        1 + erf((mean - c.reach_rssi_dbm) / 2.0 / math.sqrt(2.0)))
    link = FtmLink(c)
    assert link.response_probability_between(B, A, ridge(height))[0] == pytest.approx(p, abs=1e-12)
    assert link.response_probability_between(B, A, None)[0] == pytest.approx(
        float(link.response_probability(math.hypot(40, 20))), abs=0)
    # the NLoS-like excess: one exponential draw, mean (J - J0) x 0.25 m/dB
    full = _hover(height, FtmConfig())
    extra = full.occlusion_excess_m[full.ok] - delta
    mean_extra = (j - J_GRAZING_DB) * 0.25
    assert extra.min() >= 0.0
    assert abs(extra.mean() - mean_extra) < 4 * mean_extra / math.sqrt(full.ok.sum())


def test_clear_flights_are_unchanged_byte_for_byte(tmp_path) -> None:
    """Nothing obstructs (flat ground, or the paper-apab pass over its hills): the same
    seed with occlusion on and off writes the same log."""
    flat = HillsTerrain(slope_e=0.0, slope_n=0.0, hills=(), ripple_amplitude_m=0.0)
    sc = scenario([responder()])
    sc = dataclasses.replace(sc, world=dataclasses.replace(sc.world, terrain=flat))
    for s in (sc, load_scenario("paper-apab")):
        digests = []
        for occ in (True, False):
            s2 = dataclasses.replace(s, ftm=dataclasses.replace(s.ftm, occlusion=occ))
            path = tmp_path / f"{s.name}-{occ}.jsonl"
            res = simulate_scenario(s2, seed=7, path=path)
            digests.append(hashlib.sha256(path.read_bytes()).hexdigest())
            if occ:
                assert not res.ftm.occlusion_loss_db.any() and not res.ftm.occlusion_excess_m.any()
        assert digests[0] == digests[1], s.name


class _Ridge:
    """A terrain with only height_m (no box bound): the profile is sampled every time."""

    def __init__(self, inner) -> None:
        self.inner = inner

    def height_m(self, e_m, n_m):
        return self.inner.height_m(e_m, n_m)

    def sag_curvature(self):
        return self.inner.sag_curvature()


@pytest.mark.parametrize("kind", ["hills", "grid"])
def test_the_clearance_tables_skip_profiles_without_changing_a_value(kind: str) -> None:
    """The tables (from max_height_m) only skip links that provably clear: the loss and
    excess of 6000 random links equal the full profile's, and most links are skipped
    (drones 10-60 m above gentle hills), while some are obstructed."""
    rng = np.random.default_rng(3)
    if kind == "hills":
        terrain = HillsTerrain()
    else:
        g = rng.normal(0.0, 2.0, (161, 161)).cumsum(0).cumsum(1) * 0.02
        terrain = GridTerrain(g, -400.0, -400.0, 5.0)
    ap = rng.uniform(-300, 300, (4, 2))
    resp = np.column_stack([ap, terrain.height_m(ap[:, 0], ap[:, 1]) + 0.5])
    occ = Occluder(terrain, resp, 5.18e9, 2.0)
    k = rng.integers(0, 4, 6000)
    ang, r = rng.uniform(0, 2 * np.pi, 6000), rng.uniform(0, 350, 6000)
    e, n = resp[k, 0] + r * np.cos(ang), resp[k, 1] + r * np.sin(ang)
    p = np.column_stack([e, n, terrain.height_m(e, n) + rng.uniform(5, 60, 6000)])
    fast = occ.obstruction(k, p)
    full = link_obstruction(resp[k], p, terrain, 5.18e9, 2.0)
    assert np.array_equal(fast.loss_db, full.loss_db)
    assert np.array_equal(fast.excess_m, full.excess_m)
    assert occ.n_profiled < 0.5 * occ.n_links
    assert (full.loss_db > 0).sum() > 20
    bare = Occluder(_Ridge(terrain), resp, 5.18e9, 2.0)  # no box bound: all profiled
    out = bare.obstruction(k, p)
    assert np.array_equal(out.loss_db, full.loss_db) and bare.bound is None


def test_profile_sampling_rule() -> None:
    """ceil(X / step) - 1 interior samples: a link shorter than a step has none (clear);
    samples on a steep drop behind the responder do not count as obstacles."""
    terrain = ridge(30.0)
    a = np.array([[-0.5, 0.0, 0.5], [-20.0, 0.0, 0.5]])
    b = np.array([[0.5, 0.0, 50.0], [20.0, 0.0, 100.0]])  # 1 m across the ridge; far over
    nu = profile_nu(a, b, terrain, LAM, 2.0)
    assert nu[0] == -np.inf  # no sample
    assert nu[1] < -0.78


def test_occlusion_config_keys(tmp_path) -> None:
    path = tmp_path / "s.toml"
    path.write_text('extends = "paper-apab"\n[ftm]\nocclusion = false\nfrequency_hz = 2.412e9\n')
    sc = load_scenario(path)
    assert sc.ftm.occlusion is False and sc.ftm.frequency_hz == 2.412e9
    assert FtmConfig().occlusion and FtmConfig().frequency_hz == 5.18e9
    for bad in ({"frequency_hz": 5.0}, {"occlusion_step_m": 0.0}, {"occlusion_step_m": 80.0},
                {"occlusion_excess_m_per_db": -1.0}):
        with pytest.raises(ValueError):
            FtmConfig(**bad)


def test_scenario_preset_flights_see_the_ridge() -> None:
    """A flight over a ridge terrain (a world built here): obstructed results exist and
    carry the loss and excess; with occlusion off they do not."""
    terrain = ridge(25.0)
    world = World(Origin(), terrain, (responder(e_m=-10.0, n_m=0.0),))
    track = hover_track(120.0, enu=(30.0, 0.0, 12.0))
    f = simulate_ftm(track, world, with_ftm(FtmConfig(), reach_rssi_dbm=-200.0), ClockConfig(),
                     np.random.default_rng(1))
    assert len(f.t_s) > 300 and np.all(f.occlusion_loss_db > 20.0)
    assert np.all(f.occlusion_excess_m > 0.0)
