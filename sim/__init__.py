"""Synthetic world for osa-testbed: terrain, responders, vehicle, GNSS and FTM sensors.

Public API::

    sim.list_scenarios() -> list[str]
    sim.load_scenario(name_or_path) -> Scenario
    sim.simulate(scenario, seed, path=None) -> SimResult   # writes the log when path is given
    sim.write_log(result, path) -> Path

See docs/simulator.md for the sensor models and the presets.
"""

from sim.clock import ClockConfig, PhoneClock
from sim.flights import (
    Circle,
    ClosePass,
    PassFlight,
    SweepsFlight,
    TrajectoryFlight,
    WaypointsFlight,
)
from sim.ftm import ConcealmentModel, FtmConfig, FtmTrack
from sim.gnss import GNSS_PRESETS, GnssConfig, GnssTrack
from sim.scenario import (
    LogSettings,
    Scenario,
    ScenarioError,
    list_scenarios,
    load_scenario,
    scenario_from_table,
)
from sim.simulate import SimResult, run_scenario, simulate, write_log
from sim.terrain import GridTerrain, Hill, HillsTerrain
from sim.vehicle import VehicleConfig, VehicleTrack, fly
from sim.world import Origin, Responder, World

__all__ = [
    "GNSS_PRESETS",
    "Circle",
    "ClockConfig",
    "ClosePass",
    "ConcealmentModel",
    "FtmConfig",
    "FtmTrack",
    "GnssConfig",
    "GnssTrack",
    "GridTerrain",
    "Hill",
    "HillsTerrain",
    "LogSettings",
    "Origin",
    "PassFlight",
    "PhoneClock",
    "Responder",
    "Scenario",
    "ScenarioError",
    "SimResult",
    "SweepsFlight",
    "TrajectoryFlight",
    "VehicleConfig",
    "VehicleTrack",
    "WaypointsFlight",
    "World",
    "fly",
    "list_scenarios",
    "load_scenario",
    "run_scenario",
    "scenario_from_table",
    "simulate",
    "write_log",
]
