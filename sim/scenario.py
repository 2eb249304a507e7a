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
    [search]   a search instead of a fixed flight (then [flight] may be absent):
               area_enu_m, start_e_m, start_n_m, budget_s, height_m, speed_mps,
               random_responders, random_concealment (docs/scenarios.md)
    [[agents]] optional: several agents in one world: name, kind = "uav" | "ground",
               start_e_m, start_n_m, [agents.vehicle], [agents.gnss] (preset + fields)
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

from estimator.geometry import polygon_area_m2, signed_distance_to_polygon_m
from estimator.records import Trajectory
from sim._config import ConfigError, check_finite, from_table, merge_tables
from sim.clock import ClockConfig
from sim.flights import FLIGHT_KINDS, Flight, TrajectoryFlight
from sim.ftm import FtmConfig
from sim.gnss import GNSS_PRESETS, GnssConfig
from sim.terrain import GridTerrain, HillsTerrain, Terrain
from sim.vehicle import WALKER, VehicleConfig
from sim.world import MAX_EXTENT_M, Origin, Responder, World


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


CONCEALMENTS = ("open", "vegetation", "vegetation_debris")


@dataclass(frozen=True, kw_only=True)
class SearchSpec:
    """The ``[search]`` table: a search instead of a fixed flight (ENU metres about the
    world origin). The area is a keep-in polygon, convex or not."""

    area_enu_m: tuple[tuple[float, float], ...]
    start_e_m: float
    start_n_m: float
    budget_s: float = 1200.0
    height_m: float = 45.0  # above the terrain
    speed_mps: float = 8.0
    random_responders: int = 0
    random_concealment: tuple[str, ...] = ("open",)
    expected_responders: int | None = None  # how many people are sought (None: unknown)

    def __post_init__(self) -> None:
        poly = self.area_enu_m
        if len(poly) < 3:
            raise ValueError("area_enu_m needs at least 3 vertices")
        for i, (e, n) in enumerate(poly):
            check_finite(f"area_enu_m[{i}]", e)
            check_finite(f"area_enu_m[{i}]", n)
            if math.hypot(e, n) > MAX_EXTENT_M:
                raise ValueError(f"area_enu_m[{i}] lies beyond {MAX_EXTENT_M:.0f} m of the origin")
        if abs(polygon_area_m2(poly)) < 1.0:
            raise ValueError("area_enu_m encloses no area")
        check_finite("start_e_m", self.start_e_m)
        check_finite("start_n_m", self.start_n_m)
        if not self.contains(self.start_e_m, self.start_n_m):
            raise ValueError(
                f"the start ({self.start_e_m:g}, {self.start_n_m:g}) is outside area_enu_m"
            )
        check_finite("budget_s", self.budget_s)
        if not 0.0 < self.budget_s <= 6 * 3600.0:
            raise ValueError(f"budget_s {self.budget_s:g} is not in (0, 6 h]")
        check_finite("height_m", self.height_m)
        if not 2.0 <= self.height_m <= 500.0:
            raise ValueError(f"height_m {self.height_m:g} is not in [2, 500] m")
        check_finite("speed_mps", self.speed_mps)
        if not 0.0 < self.speed_mps <= 30.0:
            raise ValueError(f"speed_mps {self.speed_mps:g} is not in (0, 30] m/s")
        if not 0 <= self.random_responders <= 100:
            raise ValueError("random_responders must be in [0, 100]")
        if not self.random_concealment:
            raise ValueError("random_concealment must not be empty")
        if self.expected_responders is not None and not 1 <= self.expected_responders <= 100:
            raise ValueError("expected_responders must be in [1, 100]")
        for c in self.random_concealment:
            if c not in CONCEALMENTS:
                known = ", ".join(CONCEALMENTS)
                raise ValueError(f"random_concealment: {c!r} is not one of {known}")

    def contains(self, e_m: float, n_m: float, margin_m: float = 0.0) -> bool:
        """Is (e, n) inside the area (and at least ``margin_m`` from its edges)?"""
        d = signed_distance_to_polygon_m(self.area_enu_m, [(e_m, n_m)])[0]
        return bool(d <= -margin_m) if margin_m > 0 else bool(d <= 1e-9)


@dataclass(frozen=True, kw_only=True)
class AgentSpec:
    """One agent of a scenario: a vehicle (UAV or walking ground agent), its own GNSS
    receiver and phone, and its own log (header ``agent`` = ``name``)."""

    name: str
    kind: str = "uav"  # "uav" | "ground"
    vehicle: VehicleConfig = field(default_factory=VehicleConfig)
    gnss: GnssConfig = field(default_factory=GnssConfig)
    start_e_m: float | None = None  # None: the scenario's start
    start_n_m: float | None = None

    def __post_init__(self) -> None:
        if not self.name:
            raise ValueError("agent name must not be empty")
        if self.kind not in ("uav", "ground"):
            raise ValueError(f"agent kind {self.kind!r} is not 'uav' or 'ground'")
        if self.kind == "ground" and self.vehicle.ground_height_m is None:
            raise ValueError("a ground agent needs vehicle.ground_height_m")
        for v in (self.start_e_m, self.start_n_m):
            if v is not None:
                check_finite("agent start", v)


@dataclass(frozen=True, kw_only=True, eq=False)
class Scenario:
    """Everything one simulated flight needs; ``simulate(scenario, seed)`` adds the noise.

    A scenario has a fixed ``flight``, or a ``search`` (then ``osa search`` flies it in
    closed loop and ``flight`` may be None), or both.
    """

    name: str
    description: str = ""
    world: World
    flight: Flight | None = None
    search: SearchSpec | None = None
    agents_: tuple[AgentSpec, ...] = ()
    vehicle: VehicleConfig = field(default_factory=VehicleConfig)
    gnss: GnssConfig = field(default_factory=GnssConfig)
    ftm: FtmConfig = field(default_factory=FtmConfig)
    clock: ClockConfig = field(default_factory=ClockConfig)
    log: LogSettings = field(default_factory=LogSettings)
    source: str = ""

    def trajectory(self) -> Trajectory:
        """The reference path the vehicle flies."""
        if self.flight is None:
            raise ValueError(f"scenario {self.name} has no [flight] (it is a search)")
        return self.flight.build(self.world)

    @property
    def agents(self) -> tuple[AgentSpec, ...]:
        """The agents: ``[[agents]]``, else one UAV named by ``[log] agent``."""
        if self.agents_:
            return self.agents_
        return (AgentSpec(name=self.log.agent, vehicle=self.vehicle, gnss=self.gnss),)

    def start_enu_m(self, agent: int = 0) -> tuple[float, float]:
        """Where an agent takes off: its own start, else the search's, else the flight's."""
        a = self.agents[agent]
        if a.start_e_m is not None and a.start_n_m is not None:
            return a.start_e_m, a.start_n_m
        if self.search is not None:
            return self.search.start_e_m, self.search.start_n_m
        if self.flight is not None:
            p = self.trajectory().enu_m[0]
            return float(p[0]), float(p[1])
        return 0.0, 0.0

    @property
    def header_agl_m(self) -> float:
        """H_AGL written to the log header."""
        if self.log.agl_m is not None:
            return self.log.agl_m
        if self.flight is not None:
            return self.flight.nominal_height_m
        assert self.search is not None
        return self.search.height_m

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


_TOP_KEYS = {
    "name", "description", "log", "world", "flight", "search", "agents", "vehicle", "gnss",
    "ftm", "clock",
}  # fmt: skip


def _gnss_over(table: dict, base: GnssConfig, where: str) -> GnssConfig:
    t = dict(table)
    preset = t.pop("preset", None)
    if preset is not None:
        if preset not in GNSS_PRESETS:
            raise ConfigError(f"{where}.preset: {preset!r} is not one of {', '.join(GNSS_PRESETS)}")
        base = GNSS_PRESETS[preset]
    return from_table(GnssConfig, t, where, base=base)


def _agents(raw: object, vehicle: VehicleConfig, gnss: GnssConfig) -> tuple[AgentSpec, ...]:
    if raw is None:
        return ()
    if not isinstance(raw, list) or not all(isinstance(a, dict) for a in raw):
        raise ConfigError("agents: expected an array of tables ([[agents]])")
    out = []
    names: set[str] = set()
    for i, a in enumerate(raw):
        where = f"agents[{i}]"
        t = dict(a)
        kind = t.pop("kind", "uav")
        if kind not in ("uav", "ground"):
            raise ConfigError(f"{where}.kind: {kind!r} is not 'uav' or 'ground'")
        v_base = vehicle if kind == "uav" else WALKER
        veh = from_table(VehicleConfig, t.pop("vehicle", {}), f"{where}.vehicle", base=v_base)
        gn = _gnss_over(t.pop("gnss", {}), gnss, f"{where}.gnss")
        name = t.pop("name", None)
        if not isinstance(name, str) or not name:
            raise ConfigError(f"{where}.name: expected a non-empty string")
        if name in names:
            raise ConfigError(f"{where}.name: {name!r} is used twice")
        names.add(name)
        rest = from_table(_AgentStart, t, where)
        out.append(AgentSpec(name=name, kind=kind, vehicle=veh, gnss=gn,
                             start_e_m=rest.start_e_m, start_n_m=rest.start_n_m))
    return tuple(out)


@dataclass(frozen=True, kw_only=True)
class _AgentStart:
    start_e_m: float | None = None
    start_n_m: float | None = None


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
        search = None
        if "search" in table:
            search = from_table(SearchSpec, table["search"], "search")
        if search is None and not isinstance(table.get("flight"), dict):
            raise ConfigError("missing [flight] table (or a [search] table)")
        flight = _flight(table["flight"]) if isinstance(table.get("flight"), dict) else None
        if "flight" in table and flight is None:
            raise ConfigError("flight: expected a table")
        vehicle = from_table(VehicleConfig, table.get("vehicle", {}), "vehicle")
        gnss = _gnss(table.get("gnss", {}))
        scenario = Scenario(
            name=name,
            description=description,
            world=world,
            flight=flight,
            search=search,
            agents_=_agents(table.get("agents"), vehicle, gnss),
            vehicle=vehicle,
            gnss=gnss,
            ftm=from_table(FtmConfig, table.get("ftm", {}), "ftm"),
            clock=from_table(ClockConfig, table.get("clock", {}), "clock"),
            log=from_table(LogSettings, table.get("log", {}), "log"),
            source=source,
        )
        if flight is not None:
            try:
                traj = scenario.trajectory()
            except (KeyError, ValueError) as exc:
                raise ConfigError(f"flight: {exc.args[0] if exc.args else exc}") from exc
            if traj.duration_s > 6 * 3600:
                raise ConfigError(f"flight: {traj.duration_s / 3600:.1f} h is beyond any battery")
            _check_work(scenario, traj.duration_s, traj.length_m)
        elif search is not None:
            _check_work(scenario, search.budget_s, search.budget_s * search.speed_mps)
    except ConfigError as exc:
        raise ScenarioError(f"{source}: {exc}") from exc
    return scenario


MAX_VEHICLE_SAMPLES = 3_000_000  # 6 h at the default 20 Hz is 432 000


def _check_work(scenario: Scenario, duration: float, length_m: float) -> None:
    """Refuse, before anything is allocated, a vehicle time step or path step that
    would need absurd memory and time over ``duration`` seconds and ``length_m`` of
    flight (ConfigError)."""
    for a in scenario.agents:
        v = a.vehicle
        for n, what in ((duration / v.sample_dt_s, f"sample_dt_s {v.sample_dt_s:g} s"),
                        (length_m / v.path_step_m, f"path_step_m {v.path_step_m:g} m")):
            if n > MAX_VEHICLE_SAMPLES:
                raise ConfigError(f"vehicle.{what} would need {n:.3g} vehicle samples over "
                                  f"{duration:g} s and {length_m:g} m of flight (more than "
                                  f"{MAX_VEHICLE_SAMPLES}): widen it")


def load_scenario(name_or_path: str | Path) -> Scenario:
    """Load a packaged preset by name (see :func:`list_scenarios`) or a TOML file by path."""
    table, source, base_dir = _read_toml(name_or_path)
    return scenario_from_table(table, source, base_dir)


def search_scenario(scenario: str | Path | Scenario) -> Scenario:
    """A search scenario (one with a ``[search]`` table: ``osa search``, ``osa evaluate``,
    the environments) from a preset name, a TOML path or a :class:`Scenario`; a
    :class:`ScenarioError` for anything else."""
    sc = scenario if isinstance(scenario, Scenario) else load_scenario(scenario)
    if sc.search is None:
        name = sc.name if isinstance(scenario, Scenario) else scenario
        raise ScenarioError(f"{name}: not a search scenario (no [search] table); "
                            "osa simulate flies fixed flights")
    return sc
