"""Modes are compositions of component objects; names map to them in one registry."""

from __future__ import annotations

import dataclasses

import pytest

from estimator.bootstrap import GaussNewton, Robust
from estimator.filters import IEKF3D, UKF3D, Iekf, Ukf
from estimator.modes import MODES, PAPER_MODES, mode_name, parse_modes, resolve_mode, resolve_modes
from estimator.noise import (
    Adaptive,
    AdaptiveR,
    Constant,
    ConstantR,
    Empirical,
    EmpiricalNlos,
    GnssInflated,
    GnssInflatedR,
    Nlos,
    NlosR,
)
from estimator.online import EstimatorOptions
from estimator.pipeline import ModeSpec, PipelineConfig, SharedFront, Track, make_track
from estimator.refined import RefinedTrack
from estimator.replay import ReplayOptions, replay_logs
from estimator.smoothing import Ema, EmaSmoother, Median, MedianSmoother
from tests.estimator.synth import BSSID, write_flight


def test_the_papers_six_are_the_papers_compositions():
    """Each of the six changes one component of the baseline (sec. Measurement-Noise
    Configurations); ours are added beside them."""
    base = ModeSpec("baseline")
    assert (base.filter, base.noise, base.smoother, base.bootstrap, base.ground_prior) == (
        Iekf(), Constant(), Median(), GaussNewton(), True)
    changed = {"nlos": {"noise": Nlos()}, "empirical-r": {"noise": Empirical()},
               "ukf": {"filter": Ukf()}, "ema": {"smoother": Ema()},
               "adaptive-r": {"noise": Adaptive()}}
    assert PAPER_MODES == ("baseline", "nlos", "empirical-r", "ukf", "ema", "adaptive-r")
    assert MODES["baseline"] == base
    for name, change in changed.items():
        assert MODES[name] == dataclasses.replace(base, name=name, **change)
    cfg = PipelineConfig()
    assert isinstance(MODES["adaptive-r"].noise.make(cfg), AdaptiveR)
    assert MODES["robust"].noise == GnssInflated(EmpiricalNlos())
    assert MODES["robust"].bootstrap == Robust() and not MODES["robust"].paper
    assert MODES["refined"].track is RefinedTrack and not MODES["refined"].ground_prior


def test_components_build_their_parts_from_the_pipeline_config():
    cfg = PipelineConfig()
    assert isinstance(Iekf().make((1.0, 2.0, 3.0), cfg), IEKF3D)
    u = Ukf().make((1.0, 2.0, 3.0), cfg)
    assert isinstance(u, UKF3D) and u.cfg is cfg.ukf and not Ukf.has_bias
    assert isinstance(Constant().make(cfg), ConstantR)
    n = Nlos().make(cfg)
    assert isinstance(n, NlosR) and n.cfg is cfg.nlos and n is not Nlos().make(cfg)  # fresh
    assert Adaptive().make(cfg).innovation_based  # the filter calls it at its prior
    g = GnssInflated(Adaptive()).make(cfg)
    assert isinstance(g, GnssInflatedR) and g.innovation_based
    assert not GnssInflated(Constant()).make(cfg).innovation_based
    assert isinstance(Median().make(cfg), MedianSmoother)
    assert isinstance(Ema().make(cfg), EmaSmoother)


def test_registry_resolves_names_once_and_specs_pass_through():
    assert resolve_mode("best") is MODES["refined"] and mode_name("best") == "refined"
    mine = ModeSpec("mine", noise=Nlos(), smoother=Ema())
    assert resolve_mode(mine) is mine
    assert resolve_modes(["baseline", "best", MODES["baseline"], mine]) == (
        MODES["baseline"], MODES["refined"], mine)
    with pytest.raises(ValueError, match="unknown mode 'kalman'"):
        resolve_mode("kalman")
    with pytest.raises(ValueError):
        EstimatorOptions(modes=("kalman",))
    assert parse_modes("all+best") == (*PAPER_MODES, "refined")
    assert EstimatorOptions(modes=("ema", mine)).modes == (MODES["ema"], mine)


def test_tracks_take_specs_and_modes_that_agree_share_one_filter_run():
    front = SharedFront()
    base = make_track("b", MODES["baseline"], front=front)
    ema = make_track("b", MODES["ema"], front=front)
    ukf = make_track("b", MODES["ukf"], front=front)
    assert base.run is ema.run and base.run is not ukf.run
    assert type(make_track("b", MODES["refined"])) is RefinedTrack
    with pytest.raises(TypeError):
        Track("b", "baseline")
    with pytest.raises(ValueError):
        Track("b", MODES["refined"])


def test_a_mode_composed_in_code_runs_without_a_name_in_the_registry(tmp_path):
    """A spec equal in its components to ``nlos`` gives ``nlos``'s estimate under its own
    name; a new composition (NLoS noise with EMA smoothing) runs and converges."""
    flight = write_flight(tmp_path / "f.jsonl", seed=11)
    twin = ModeSpec("nlos-twin", noise=Nlos())
    new = ModeSpec("nlos-ema", noise=Nlos(), smoother=Ema())
    rep = replay_logs([flight], ReplayOptions(modes=("nlos", twin, new)))
    a, b, c = (rep.get(BSSID, m).to_json() for m in ("nlos", "nlos-twin", "nlos-ema"))
    assert b == {**a, "mode": "nlos-twin"}
    assert c["mode"] == "nlos-ema" and c["status"] == "converged" and c["err_h_m"] < 3.0
    assert c["n_acc"] == a["n_acc"] and c["lat"] != a["lat"]  # one filter, another smoother
