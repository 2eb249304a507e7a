"""Synthetic world for osa-testbed: terrain, responders, vehicle, GNSS and FTM sensors.

Public API::

    sim.list_scenarios() -> list[str]
    sim.load_scenario(name_or_path) -> Scenario
    sim.simulate(scenario, seed, path=None) -> SimResult   # writes the log when path is given
    sim.write_log(result, path) -> Path
    sim.realise(scenario, seed) -> Realisation    # the world of one seed (common random numbers)
    sim.Stepper(realisation)                      # advance agents step by step, get records

See docs/simulator.md for the sensor models and the presets.
"""

from sim.clock import ClockConfig, PhoneClock
from sim.dem import DemError, DemTerrain
from sim.flights import (
    Circle,
    ClosePass,
    PassFlight,
    SweepsFlight,
    TrajectoryFlight,
    WaypointsFlight,
)
from sim.ftm import ConcealmentModel, FtmConfig, FtmLink, FtmTrack, RangeNoiseConfig
from sim.gnss import GNSS_PRESETS, GnssConfig, GnssTrack
from sim.realisation import Realisation, realise
from sim.scenario import (
    AgentSpec,
    KeepOutZone,
    LogSettings,
    Scenario,
    ScenarioError,
    SearchSpec,
    list_scenarios,
    load_scenario,
    scenario_from_table,
)
from sim.simulate import SimResult, run_scenario, simulate, write_log
from sim.stepper import Emitted, LogSink, Stepper
from sim.terrain import GridTerrain, Hill, HillsTerrain
from sim.vehicle import (
    WALKER,
    FlightError,
    HoldGuidance,
    PathGuidance,
    VehicleConfig,
    VehicleState,
    VehicleTrack,
    fly,
    path_guidance,
)
from sim.world import Origin, Responder, World

__all__ = [
    "GNSS_PRESETS",
    "WALKER",
    "AgentSpec",
    "Circle",
    "ClockConfig",
    "ClosePass",
    "ConcealmentModel",
    "DemError",
    "DemTerrain",
    "Emitted",
    "FlightError",
    "FtmConfig",
    "FtmLink",
    "FtmTrack",
    "GnssConfig",
    "GnssTrack",
    "GridTerrain",
    "Hill",
    "HillsTerrain",
    "HoldGuidance",
    "KeepOutZone",
    "LogSettings",
    "LogSink",
    "Origin",
    "PassFlight",
    "PathGuidance",
    "PhoneClock",
    "RangeNoiseConfig",
    "Realisation",
    "Responder",
    "Scenario",
    "ScenarioError",
    "SearchSpec",
    "SimResult",
    "Stepper",
    "SweepsFlight",
    "TrajectoryFlight",
    "VehicleConfig",
    "VehicleState",
    "VehicleTrack",
    "WaypointsFlight",
    "World",
    "fly",
    "list_scenarios",
    "load_scenario",
    "path_guidance",
    "realise",
    "run_scenario",
    "scenario_from_table",
    "simulate",
    "write_log",
]
