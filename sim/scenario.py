"""Scenarios as data: TOML presets in ``sim/scenarios`` (or any file) -> :class:`Scenario`.

A scenario file has these tables (all but ``world.responders`` and ``flight`` optional)::

    name = "paper-ap1f"            # default: the file's stem
    description = "..."
    extends = "paper-ap1f"         # optional: deep-merge over another scenario
    [log]      agent, start_utc, agl_m, range_offset_m       (the log header)
    [world.origin]   lat_deg, lon_deg, h_m
    [world.terrain]  kind = "hills" (HillsTerrain fields) | "grid" (file or heights_m,
                     e0_m, n0_m, spacing_m)
    [[world.responders]]  name, bssid, e_m + n_m or lat_deg + lon_deg, concealment, ...
    [flight]   kind = "sweeps" | "pass" | "waypoints", then that flight's fields
    [vehicle]  VehicleConfig fields
    [gnss]     preset = "standalone" | "rtk", then GnssConfig fields overriding it
    [ftm]      FtmConfig fields, sub-tables [ftm.noise], [ftm.open], [ftm.vegetation], ...
    [clock]    ClockConfig fields

Every key is checked (unknown keys, wrong types, NaN or out-of-range values raise
:class:`ScenarioError` naming the file and key).
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from dataclasses import dataclass, field
from datetime import datetime
from importlib import resources
from pathlib import Path
from typing import Any

from estimator.records import Trajectory
from sim._config import ConfigError, check_finite, from_table, merge_tables
from sim.clock import ClockConfig
from sim.flights import FLIGHT_KINDS, Flight, TrajectoryFlight
from sim.ftm import FtmConfig
from sim.gnss import GNSS_PRESETS, GnssConfig
from sim.terrain import GridTerrain, HillsTerrain, Terrain
from sim.vehicle import VehicleConfig
from sim.world import Origin, Responder, World


class ScenarioError(ValueError):
    """A scenario that does not exist or cannot be used, with a one-line reason."""


@dataclass(frozen=True, kw_only=True)
class LogSettings:
    """What the log header says (log-format.md ``header``)."""

    agent: str = "uav-1"
    start_utc: str = "2025-06-12T10:12:00Z"
    agl_m: float | None = None  # configured H_AGL; None: the flight's nominal height
    range_offset_m: float = 0.0  # pre-flight calibration b0 (none in the paper's flights)

    def __post_init__(self) -> None:
        if not self.agent:
            raise ValueError("log agent must not be empty")
        try:
            datetime.fromisoformat(self.start_utc.replace("Z", "+00:00"))
        except ValueError as exc:
            raise ValueError(f"start_utc {self.start_utc!r} is not an ISO 8601 time") from exc
        if self.agl_m is not None:
            check_finite("agl_m", self.agl_m)
        check_finite("range_offset_m", self.range_offset_m)


@dataclass(frozen=True, kw_only=True, eq=False)
class Scenario:
    """Everything one simulated flight needs; ``simulate(scenario, seed)`` adds the noise."""

    name: str
    description: str = ""
    world: World
    flight: Flight
    vehicle: VehicleConfig = field(default_factory=VehicleConfig)
    gnss: GnssConfig = field(default_factory=GnssConfig)
    ftm: FtmConfig = field(default_factory=FtmConfig)
    clock: ClockConfig = field(default_factory=ClockConfig)
    log: LogSettings = field(default_factory=LogSettings)
    source: str = ""

    def trajectory(self) -> Trajectory:
        """The reference path the vehicle flies."""
        return self.flight.build(self.world)

    @property
    def header_agl_m(self) -> float:
        """H_AGL written to the log header."""
        return self.log.agl_m if self.log.agl_m is not None else self.flight.nominal_height_m

    def with_trajectory(self, trajectory: Trajectory, name: str | None = None) -> Scenario:
        """The same world and sensors flying ``trajectory`` instead."""
        # the preset's configured H_AGL belongs to its own flight: the header of a
        # trajectory's log gets the height actually flown (see run_scenario)
        return dataclasses.replace(
            self,
            flight=TrajectoryFlight(trajectory),
            name=name or self.name,
            log=dataclasses.replace(self.log, agl_m=None),
        )


# ----------------------------------------------------------------------------- loading


def _scenario_dir() -> Any:
    return resources.files("sim").joinpath("scenarios")


def list_scenarios() -> list[str]:
    """Names of the packaged scenario presets, sorted."""
    return sorted(
        p.name[: -len(".toml")] for p in _scenario_dir().iterdir() if p.name.endswith(".toml")
    )


def _read_toml(name_or_path: str | Path, chain: tuple[str, ...] = ()) -> tuple[dict, str, Path]:
    """Read a scenario table (following ``extends``); return (table, source, directory)."""
    text: str
    p = Path(name_or_path)
    as_path = isinstance(name_or_path, Path) or p.suffix == ".toml" or "/" in str(name_or_path)
    if as_path or p.is_file():
        if not p.is_file():
            raise ScenarioError(f"scenario file {p} does not exist")
        try:
            text = p.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            raise ScenarioError(f"cannot read scenario file {p}: {exc}") from exc
        source, base_dir, stem = str(p), p.resolve().parent, p.stem
    else:
        name = str(name_or_path)
        res = _scenario_dir().joinpath(f"{name}.toml")
        if not res.is_file():
            known = ", ".join(list_scenarios())
            raise ScenarioError(f"unknown scenario {name!r} (presets: {known})")
        text = res.read_text(encoding="utf-8")
        source, base_dir, stem = f"preset {name}", Path(str(_scenario_dir())), name
    if source in chain:
        raise ScenarioError(f"{source}: 'extends' loops back on itself")
    try:
        table = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ScenarioError(f"{source}: invalid TOML: {exc}") from exc
    parent = table.pop("extends", None)
    if parent is not None:
        if not isinstance(parent, str):
            raise ScenarioError(f"{source}: extends must be a scenario name or path")
        target: str | Path = parent
        if parent.endswith(".toml") and not Path(parent).is_absolute():
            target = base_dir / parent
        base, _, _ = _read_toml(target, (*chain, source))
        base.pop("name", None)
        table = merge_tables(base, table)
    table.setdefault("name", stem)
    return table, source, base_dir


def _terrain(table: dict, base_dir: Path) -> Terrain:
    t = dict(table)
    kind = t.pop("kind", "hills")
    if kind == "hills":
        return from_table(HillsTerrain, t, "world.terrain")
    if kind == "grid":
        missing = [k for k in ("e0_m", "n0_m", "spacing_m") if k not in t]
        if missing:
            raise ConfigError(f"world.terrain: grid terrain needs {', '.join(missing)}")
        geo = {k: t.pop(k) for k in ("e0_m", "n0_m", "spacing_m")}
        for k, v in geo.items():
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
                raise ConfigError(f"world.terrain.{k}: expected a finite number, got {v!r}")
        if "file" in t and "heights_m" not in t:
            file = Path(t.pop("file"))
            path = file if file.is_absolute() else base_dir / file
            grid_unknown = sorted(t)
            if grid_unknown:
                raise ConfigError(f"world.terrain: unknown key {grid_unknown[0]!r}")
            try:
                return GridTerrain.from_file(path, **{k: float(v) for k, v in geo.items()})
            except ValueError as exc:
                raise ConfigError(f"world.terrain: {exc}") from exc
        if "heights_m" in t and "file" not in t:
            heights = t.pop("heights_m")
            if t:
                raise ConfigError(f"world.terrain: unknown key {sorted(t)[0]!r}")
            try:
                import numpy as np

                arr = np.array(heights, dtype=float)
                return GridTerrain(arr, **{k: float(v) for k, v in geo.items()})
            except (TypeError, ValueError) as exc:
                raise ConfigError(f"world.terrain.heights_m: {exc}") from exc
        raise ConfigError("world.terrain: a grid terrain needs exactly one of file, heights_m")
    raise ConfigError(f"world.terrain.kind: {kind!r} is not 'hills' or 'grid'")


def _responder(table: dict, origin: Origin, where: str) -> Responder:
    t = dict(table)
    has_ll = "lat_deg" in t or "lon_deg" in t
    has_en = "e_m" in t or "n_m" in t
    if has_ll == has_en:
        raise ConfigError(f"{where}: give either e_m and n_m or lat_deg and lon_deg")
    if has_ll:
        lat, lon = t.pop("lat_deg", None), t.pop("lon_deg", None)
        for k, v in (("lat_deg", lat), ("lon_deg", lon)):
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
                raise ConfigError(f"{where}.{k}: expected a finite number, got {v!r}")
        if not -90.0 <= lat <= 90.0 or not -180.0 <= lon <= 180.0:
            raise ConfigError(f"{where}: ({lat}, {lon}) is not a latitude/longitude")
        e, n, _ = origin.frame().to_enu(float(lat), float(lon), origin.h_m)
        t["e_m"], t["n_m"] = round(e, 3), round(n, 3)
    return from_table(Responder, t, where)


def _flight(table: dict) -> Flight:
    t = dict(table)
    kind = t.get("kind")
    if kind not in FLIGHT_KINDS:
        raise ConfigError(f"flight.kind: {kind!r} is not one of {', '.join(FLIGHT_KINDS)}")
    return from_table(FLIGHT_KINDS[kind], t, "flight")


def _gnss(table: dict) -> GnssConfig:
    t = dict(table)
    preset = t.pop("preset", "standalone")
    if preset not in GNSS_PRESETS:
        raise ConfigError(f"gnss.preset: {preset!r} is not one of {', '.join(GNSS_PRESETS)}")
    return from_table(GnssConfig, t, "gnss", base=GNSS_PRESETS[preset])


_TOP_KEYS = {"name", "description", "log", "world", "flight", "vehicle", "gnss", "ftm", "clock"}


def scenario_from_table(table: dict, source: str = "<table>", base_dir: Path | None = None):
    """Build and validate a :class:`Scenario` from a parsed TOML table."""
    base_dir = base_dir or Path.cwd()
    try:
        unknown = sorted(set(table) - _TOP_KEYS)
        if unknown:
            raise ConfigError(f"unknown top-level key {unknown[0]!r}")
        name = table.get("name", "")
        description = table.get("description", "")
        if not isinstance(name, str) or not name:
            raise ConfigError("name: expected a non-empty string")
        if not isinstance(description, str):
            raise ConfigError("description: expected a string")
        world_t = table.get("world")
        if not isinstance(world_t, dict):
            raise ConfigError("missing [world] table")
        bad = sorted(set(world_t) - {"origin", "terrain", "responders"})
        if bad:
            raise ConfigError(f"world: unknown key {bad[0]!r}")
        origin = from_table(Origin, world_t.get("origin", {}), "world.origin")
        terrain = _terrain(world_t.get("terrain", {}), base_dir)
        resp_t = world_t.get("responders", [])
        if not isinstance(resp_t, list) or not all(isinstance(r, dict) for r in resp_t):
            raise ConfigError("world.responders: expected an array of tables")
        responders = tuple(
            _responder(r, origin, f"world.responders[{i}]") for i, r in enumerate(resp_t)
        )
        try:
            world = World(origin, terrain, responders)
        except ValueError as exc:
            raise ConfigError(f"world: {exc}") from exc
        if not isinstance(table.get("flight"), dict):
            raise ConfigError("missing [flight] table")
        flight = _flight(table["flight"])
        scenario = Scenario(
            name=name,
            description=description,
            world=world,
            flight=flight,
            vehicle=from_table(VehicleConfig, table.get("vehicle", {}), "vehicle"),
            gnss=_gnss(table.get("gnss", {})),
            ftm=from_table(FtmConfig, table.get("ftm", {}), "ftm"),
            clock=from_table(ClockConfig, table.get("clock", {}), "clock"),
            log=from_table(LogSettings, table.get("log", {}), "log"),
            source=source,
        )
        try:
            traj = scenario.trajectory()
        except (KeyError, ValueError) as exc:
            raise ConfigError(f"flight: {exc.args[0] if exc.args else exc}") from exc
        if traj.duration_s > 6 * 3600:
            raise ConfigError(f"flight: {traj.duration_s / 3600:.1f} h is beyond any battery")
    except ConfigError as exc:
        raise ScenarioError(f"{source}: {exc}") from exc
    return scenario


def load_scenario(name_or_path: str | Path) -> Scenario:
    """Load a packaged preset by name (see :func:`list_scenarios`) or a TOML file by path."""
    table, source, base_dir = _read_toml(name_or_path)
    return scenario_from_table(table, source, base_dir)
