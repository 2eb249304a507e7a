"""Scenarios as data: TOML presets in ``sim/scenarios`` (or any file) -> :class:`Scenario`.

A scenario file has these tables (all but ``world.responders`` and ``flight`` optional)::

    name = "paper-ap1f"            # default: the file's stem
    description = "..."
    extends = "paper-ap1f"         # optional: deep-merge over another scenario
    [log]      agent, start_utc, agl_m, range_offset_m       (the log header)
    [world.origin]   lat_deg, lon_deg, h_m
    [world.terrain]  kind = "hills" (HillsTerrain fields) | "grid" (file or heights_m,
                     e0_m, n0_m, spacing_m) | "dem" (path, datum_offset_m: sim.dem)
    [[world.responders]]  name, bssid, e_m + n_m or lat_deg + lon_deg, concealment, ...
    [flight]   kind = "sweeps" | "pass" | "waypoints", then that flight's fields
    [search]   a search instead of a fixed flight (then [flight] may be absent):
               area_enu_m | area_geo | area_file, start_e_m, start_n_m, budget_s,
               height_m, speed_mps, random_responders, random_concealment,
               concealed_share, hidden_share, expected_responders,
               [[search.keepout]] (polygon_geo | polygon_enu_m | circle_geo |
               circle_enu_m | file, top_m, name) (docs/scenarios.md)
    [[agents]] optional: several agents in one world: name, kind = "uav" | "ground",
               start_e_m, start_n_m, [agents.vehicle], [agents.gnss] (preset + fields)
    [vehicle]  VehicleConfig fields
    [gnss]     preset = "standalone" | "rtk", then GnssConfig fields overriding it
    [ftm]      FtmConfig fields, sub-tables [ftm.noise], [ftm.open], [ftm.vegetation], ...
    [clock]    ClockConfig fields
    [randomise] ranges drawn per world (sim.randomise.Randomise): gnss_bias_scale,
               concealed_share, range_offset_m, gnss_drop_prob, wind_mps, level

Every key is checked (unknown keys, wrong types, NaN or out-of-range values raise
:class:`ScenarioError` naming the file and key).

A site is data converted once, here, to the world's ENU frame: areas and keep-outs in
degrees or in files (:mod:`sim.sitefiles`: KML, GeoJSON, QGroundControl ``.plan``)
become ENU polygons and circles (:class:`KeepOutZone`, ``Scenario.keepouts``); a DEM
(:mod:`sim.dem`) is read over the window the scenario covers (its area, start,
responders, agents and flight), and a scenario reaching beyond the file or onto nodata
is refused with one line naming the file.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import tomllib
from dataclasses import dataclass, field
from datetime import datetime
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from estimator.geometry import (
    crossing_text,
    polygon_area_m2,
    polygon_crossing,
    signed_distance_to_polygon_m,
)
from estimator.records import Trajectory
from sim._config import ConfigError, check_finite, from_table, merge_tables
from sim.clock import ClockConfig
from sim.dem import DemError, DemTerrain, box_of
from sim.flights import FLIGHT_KINDS, Flight, TrajectoryFlight
from sim.ftm import FtmConfig
from sim.gnss import GNSS_PRESETS, GnssConfig
from sim.randomise import Randomise
from sim.sitefiles import GeoShape, SiteFileError, read_area, read_keepouts
from sim.suite import is_suite_name, suite_table
from sim.terrain import GridTerrain, HillsTerrain, Terrain
from sim.vehicle import WALKER, VehicleConfig
from sim.world import MAX_EXTENT_M, MAX_STRUCTURE_M, Origin, Responder, World


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
MAX_KEEPOUT_TOP_M = MAX_STRUCTURE_M  # an obstacle's top


@dataclass(frozen=True, kw_only=True)
class KeepOutZone:
    """A keep-out in the world's ENU frame: a polygon (``polygon_enu_m``) or a circle
    (``center_enu_m``, ``radius_m``), and the obstacle's height above the ground
    (``top_m``; None: never fly over it). A power-line tower is a circle with a top, the
    line's corridor a polygon."""

    name: str
    polygon_enu_m: tuple[tuple[float, float], ...] = ()
    center_enu_m: tuple[float, float] | None = None
    radius_m: float | None = None
    top_m: float | None = None

    def __post_init__(self) -> None:
        circle = self.center_enu_m is not None
        if circle == bool(self.polygon_enu_m) or circle != (self.radius_m is not None):
            raise ValueError(f"keep-out {self.name}: a polygon or a circle (centre, radius)")
        pts = self.polygon_enu_m or (self.center_enu_m,)
        for e, n in pts:  # type: ignore[misc]
            check_finite(f"keep-out {self.name} coordinate", e)
            check_finite(f"keep-out {self.name} coordinate", n)
            if math.hypot(e, n) > MAX_EXTENT_M:
                raise ValueError(f"keep-out {self.name} lies beyond {MAX_EXTENT_M:.0f} m of "
                                 "the origin")
        if circle:
            check_finite(f"keep-out {self.name} radius_m", self.radius_m)  # type: ignore[arg-type]
            if not 0.0 < self.radius_m <= 5000.0:  # type: ignore[operator]
                raise ValueError(f"keep-out {self.name}: radius_m {self.radius_m:g} is not in "
                                 "(0, 5000] m")
        else:
            if len(self.polygon_enu_m) < 3:
                raise ValueError(f"keep-out {self.name}: a polygon needs at least 3 vertices")
            crossing = polygon_crossing(self.polygon_enu_m)
            if crossing is not None:
                raise ValueError(f"keep-out {self.name}: {crossing_text(crossing)}")
            if abs(polygon_area_m2(self.polygon_enu_m)) < 1.0:
                raise ValueError(f"keep-out {self.name}: the polygon encloses no area")
        if self.top_m is not None:
            check_finite(f"keep-out {self.name} top_m", self.top_m)
            if not 0.0 <= self.top_m <= MAX_KEEPOUT_TOP_M:
                raise ValueError(f"keep-out {self.name}: top_m {self.top_m:g} is not in "
                                 f"[0, {MAX_KEEPOUT_TOP_M:g}] m")

    @property
    def is_circle(self) -> bool:
        return self.center_enu_m is not None

    def contains(self, e_m: float, n_m: float) -> bool:
        """Is (e, n) inside the keep-out's outline (on the boundary counts)?"""
        if self.center_enu_m is not None:
            c = self.center_enu_m
            return math.hypot(e_m - c[0], n_m - c[1]) <= self.radius_m  # type: ignore[operator]
        return bool(signed_distance_to_polygon_m(self.polygon_enu_m, [(e_m, n_m)])[0] <= 1e-9)


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
    # the share of random responders concealed (their kinds: random_concealment, the
    # others open); None: each responder's concealment uniform over random_concealment
    concealed_share: float | None = None
    # the share of random responders hidden by terrain from the take-off point (the
    # others in its line of sight): sim.realisation.random_responders; None: no rule
    hidden_share: float | None = None
    keepouts: tuple[KeepOutZone, ...] = ()  # [[search.keepout]], in ENU

    def __post_init__(self) -> None:
        poly = self.area_enu_m
        if len(poly) < 3:
            raise ValueError("area_enu_m needs at least 3 vertices")
        for i, (e, n) in enumerate(poly):
            check_finite(f"area_enu_m[{i}]", e)
            check_finite(f"area_enu_m[{i}]", n)
            if math.hypot(e, n) > MAX_EXTENT_M:
                raise ValueError(f"area_enu_m[{i}] lies beyond {MAX_EXTENT_M:.0f} m of the origin")
        crossing = polygon_crossing(poly)
        if crossing is not None:
            raise ValueError(f"the search area: {crossing_text(crossing)}")
        if abs(polygon_area_m2(poly)) < 1.0:
            raise ValueError("area_enu_m encloses no area")
        check_finite("start_e_m", self.start_e_m)
        check_finite("start_n_m", self.start_n_m)
        if not self.contains(self.start_e_m, self.start_n_m):
            raise ValueError(
                f"the start ({self.start_e_m:g}, {self.start_n_m:g}) is outside area_enu_m"
            )
        for k in self.keepouts:
            if k.contains(self.start_e_m, self.start_n_m):
                raise ValueError(f"the start ({self.start_e_m:g}, {self.start_n_m:g}) is inside "
                                 f"keep-out {k.name}")
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
        if self.concealed_share is not None:
            check_finite("concealed_share", self.concealed_share)
            if not 0.0 <= self.concealed_share <= 1.0:
                raise ValueError(f"concealed_share {self.concealed_share:g} is not in [0, 1]")
            if "open" in self.random_concealment:
                raise ValueError("with concealed_share, random_concealment lists the concealed "
                                 "kinds only (the others are open)")
        if self.hidden_share is not None:
            check_finite("hidden_share", self.hidden_share)
            if not 0.0 <= self.hidden_share <= 1.0:
                raise ValueError(f"hidden_share {self.hidden_share:g} is not in [0, 1]")

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
        if (self.start_e_m is None) != (self.start_n_m is None):
            raise ValueError(f"agent {self.name}: give both start_e_m and start_n_m, or neither")
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
    randomise: Randomise | None = None  # [randomise]: drawn per world by sim.realise

    def trajectory(self) -> Trajectory:
        """The reference path the vehicle flies."""
        if self.flight is None:
            raise ValueError(f"scenario {self.name} has no [flight] (it is a search)")
        return self.flight.build(self.world)

    @property
    def keepouts(self) -> tuple[KeepOutZone, ...]:
        """The search's keep-outs in the world's ENU frame (ENU polygons and circles with
        their ``top_m``; empty without a ``[search]``)."""
        return self.search.keepouts if self.search is not None else ()

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
    if isinstance(name_or_path, str) and is_suite_name(name_or_path):
        try:
            return suite_table(name_or_path), f"preset {name_or_path}", Path(str(_scenario_dir()))
        except ValueError as exc:
            raise ScenarioError(str(exc)) from None
    p = Path(name_or_path)
    as_path = isinstance(name_or_path, Path) or p.suffix == ".toml" or "/" in str(name_or_path)
    if as_path or p.is_file():
        hides = "" if as_path or not _scenario_dir().joinpath(f"{p}.toml").is_file() else (
            f"; the file {p} in this folder hides the preset {p} (rename the file, or run "
            "osa from another folder)")
        if p.is_dir():
            raise ScenarioError(f"scenario {p} is a folder, not a scenario file")
        if not p.is_file():
            raise ScenarioError(f"scenario file {p} does not exist")
        try:  # UTF-8, with or without the byte order mark Windows editors write
            data = p.read_bytes()
            text = data.decode("utf-8-sig")
        except OSError as exc:
            raise ScenarioError(f"cannot read scenario file {p}: {exc}") from exc
        except UnicodeDecodeError as exc:
            utf16 = " (it is UTF-16: save it as UTF-8)" if data[:2] in (
                b"\xff\xfe", b"\xfe\xff") else ""
            raise ScenarioError(f"cannot read scenario file {p}: a TOML file is UTF-8 text, "
                                f"{exc.reason} at byte {exc.start}{utf16}{hides}") from None
        source, base_dir, stem = str(p), p.resolve().parent, p.stem
    else:
        name = str(name_or_path)
        res = _scenario_dir().joinpath(f"{name}.toml")
        if not res.is_file():
            known = ", ".join(list_scenarios())
            raise ScenarioError(f"unknown scenario {name!r} (presets: {known})")
        text = res.read_text(encoding="utf-8")
        source, base_dir, stem = f"preset {name}", Path(str(_scenario_dir())), name
        hides = ""
    if source in chain:
        raise ScenarioError(f"{source}: 'extends' loops back on itself")
    try:
        table = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ScenarioError(f"{source}: invalid TOML: {exc}{hides}") from exc
    parent = table.pop("extends", None)
    if parent is not None:
        if not isinstance(parent, str):
            raise ScenarioError(f"{source}: extends must be a scenario name or path")
        target: str | Path = parent
        if parent.endswith(".toml") and not Path(parent).is_absolute():
            target = base_dir / parent
        try:  # the file that names the parent, too (before: only the parent's problem)
            base, _, parent_dir = _read_toml(target, (*chain, source))
        except ScenarioError as exc:
            raise ScenarioError(f"{source}: extends: {exc}") from None
        base = _anchor_files(base, parent_dir)  # the parent's files, not this file's
        base.pop("name", None)
        table = merge_tables(base, table)
    table.setdefault("name", stem)
    return table, source, base_dir


def _anchor_files(table: dict, base_dir: Path) -> dict:
    """``table`` with its relative file names (the DEM, a grid file, the area's file,
    the keep-outs' files) made absolute against ``base_dir``, the folder of the file
    that names them, so that a scenario extending it from elsewhere still finds them."""

    def anchored(v: Any) -> Any:
        if isinstance(v, str) and v and not Path(v).is_absolute():
            return str(base_dir / v)
        return v

    out = dict(table)
    world = out.get("world")
    if isinstance(world, dict) and isinstance(world.get("terrain"), dict):
        terrain = dict(world["terrain"])
        for k in ("path", "file"):
            if k in terrain:
                terrain[k] = anchored(terrain[k])
        out["world"] = {**world, "terrain": terrain}
    search = out.get("search")
    if isinstance(search, dict):
        search = dict(search)
        if "area_file" in search:
            search["area_file"] = anchored(search["area_file"])
        if isinstance(search.get("keepout"), list):
            search["keepout"] = [
                {**k, "file": anchored(k["file"])} if isinstance(k, dict) and "file" in k
                else k for k in search["keepout"]]
        out["search"] = search
    return out


def _holds_bool(value: Any) -> bool:
    """Does a TOML value (nested arrays) hold a boolean?"""
    if isinstance(value, list):
        return any(_holds_bool(v) for v in value)
    return isinstance(value, bool)


def _terrain(table: Any, base_dir: Path) -> Terrain:
    t = _table(table, "world.terrain")
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
            path = _site_file(t.pop("file"), base_dir, "world.terrain.file")
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
                if _holds_bool(heights):
                    raise TypeError  # true/false are no heights (before: 1 and 0 m)
                arr = np.array(heights, dtype=float)
            except (TypeError, ValueError):
                raise ConfigError("world.terrain.heights_m: expected rows of numbers, all of "
                                  "the same length") from None
            try:
                return GridTerrain(arr, **{k: float(v) for k, v in geo.items()})
            except (TypeError, ValueError) as exc:
                raise ConfigError(f"world.terrain.heights_m: {exc}") from exc
        raise ConfigError("world.terrain: a grid terrain needs exactly one of file, heights_m")
    raise ConfigError(f"world.terrain.kind: {kind!r} is not 'hills', 'grid' or 'dem'")


# flat ground: the horizontal geometry of a flight does not depend on the terrain, so a
# DEM scenario's flight is first built over it to find the window the DEM must cover
_FLAT = HillsTerrain(slope_e=0.0, slope_n=0.0, hills=(), ripple_amplitude_m=0.0)


@dataclass(frozen=True, kw_only=True)
class _DemKeys:
    path: str
    datum_offset_m: float = 0.0


def _dem_keys(table: dict, base_dir: Path) -> tuple[Path, float]:
    t = dict(table)
    t.pop("kind", None)
    if "path" not in t:
        raise ConfigError("world.terrain: a dem terrain needs path")
    keys = from_table(_DemKeys, t, "world.terrain")
    p = Path(keys.path)
    return (p if p.is_absolute() else base_dir / p), keys.datum_offset_m


def _dem_terrain(path: Path, offset: float, origin: Origin, scenario: Scenario) -> DemTerrain:
    """The DEM over the window the scenario covers, each part of it checked."""
    s = scenario.search
    parts: list[tuple[str, np.ndarray]] = []
    if s is not None:
        parts.append(("the search start", np.array([[s.start_e_m, s.start_n_m]])))
    for r in scenario.world.responders:
        parts.append((f"responder {r.name}", np.array([[r.e_m, r.n_m]])))
    for a in scenario.agents_:
        if a.start_e_m is not None and a.start_n_m is not None:
            parts.append((f"agent {a.name}'s start", np.array([[a.start_e_m, a.start_n_m]])))
    if scenario.flight is not None:
        # a flight that cannot be built is refused with its reason below
        with contextlib.suppress(KeyError, ValueError):
            parts.append(("the flight", scenario.trajectory().enu_m[:, :2]))
    area = np.asarray(s.area_enu_m, dtype=float) if s is not None else None
    boxes = [p for _, p in parts] + ([area] if area is not None else [])
    if not boxes:
        boxes = [np.zeros((1, 2))]
    try:
        dem = DemTerrain(path, (origin.lat_deg, origin.lon_deg, origin.h_m), box_of(boxes),
                         datum_offset_m=offset)
        if area is not None:
            dem.require_polygon(area, "the search area")
        for what, pts in parts:
            dem.require_points(pts, what)
    except DemError as exc:
        raise ConfigError(f"world.terrain: {exc}") from None
    return dem


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


def _geo_to_enu(origin: Origin, vertices: Any, where: str) -> tuple[tuple[float, float], ...]:
    """[[lat, lon], ...] -> ENU (e, n) vertices (mm) at the origin's height."""
    if not isinstance(vertices, list | tuple) or not all(
            isinstance(v, list | tuple) and len(v) == 2 for v in vertices):
        raise ConfigError(f"{where}: expected an array of [lat, lon] pairs")
    frame = origin.frame()
    out = []
    for i, (lat, lon) in enumerate(vertices):
        for v in (lat, lon):
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
                raise ConfigError(f"{where}[{i}]: expected finite numbers, got {v!r}")
        if not -90.0 <= lat <= 90.0 or not -180.0 <= lon <= 180.0:
            raise ConfigError(f"{where}[{i}]: ({lat}, {lon}) is not a latitude/longitude")
        e, n, _ = frame.to_enu(float(lat), float(lon), origin.h_m)
        out.append((round(e, 3), round(n, 3)))
    return tuple(out)


def _table(value: Any, where: str) -> dict:
    """``value`` if it is a TOML table, else a ConfigError naming ``where``."""
    if not isinstance(value, dict):
        raise ConfigError(f"{where}: expected a table, got {type(value).__name__}")
    return dict(value)


def _preset(value: Any, where: str) -> GnssConfig:
    """The GNSS preset named ``value`` (a ConfigError naming ``where`` otherwise)."""
    if not isinstance(value, str) or value not in GNSS_PRESETS:
        raise ConfigError(f"{where}: {value!r} is not one of {', '.join(GNSS_PRESETS)}")
    return GNSS_PRESETS[value]


def _site_file(value: Any, base_dir: Path, where: str) -> Path:
    if not isinstance(value, str) or not value:
        raise ConfigError(f"{where}: expected a file name")
    p = Path(value)
    return p if p.is_absolute() else base_dir / p


_KEEPOUT_SHAPES = ("polygon_geo", "polygon_enu_m", "circle_geo", "circle_enu_m", "file")


def _zone(shape: GeoShape | None, origin: Origin, where: str, **kw: Any) -> KeepOutZone:
    try:
        if shape is not None:
            if shape.is_circle:
                lat, lon = shape.center_deg  # type: ignore[misc]
                kw["center_enu_m"] = _geo_to_enu(origin, [[lat, lon]], where)[0]
                kw["radius_m"] = shape.radius_m
            else:
                kw["polygon_enu_m"] = _geo_to_enu(origin, [list(v) for v in shape.vertices_deg],
                                                  where)
        return KeepOutZone(**kw)
    except ValueError as exc:
        raise ConfigError(f"{where}: {exc}") from None


def _keepouts(raw: Any, origin: Origin, base_dir: Path) -> tuple[KeepOutZone, ...]:
    """``[[search.keepout]]`` tables -> ENU zones (a file may give several)."""
    if not isinstance(raw, list) or not all(isinstance(k, dict) for k in raw):
        raise ConfigError("search.keepout: expected an array of tables ([[search.keepout]])")
    out: list[KeepOutZone] = []
    for i, table in enumerate(raw):
        where = f"search.keepout[{i}]"
        t = dict(table)
        unknown = sorted(set(t) - {*_KEEPOUT_SHAPES, "top_m", "name"})
        if unknown:
            raise ConfigError(f"{where}: unknown key {unknown[0]!r} (known: "
                              f"{', '.join((*_KEEPOUT_SHAPES, 'name', 'top_m'))})")
        given = [k for k in _KEEPOUT_SHAPES if k in t]
        if len(given) != 1:
            raise ConfigError(f"{where}: give exactly one of {', '.join(_KEEPOUT_SHAPES)}")
        key = given[0]
        top = t.get("top_m")
        if top is not None and (isinstance(top, bool) or not isinstance(top, int | float)):
            raise ConfigError(f"{where}.top_m: expected a number, got {top!r}")
        name = t.get("name", f"keepout[{i}]")
        if not isinstance(name, str) or not name:
            raise ConfigError(f"{where}.name: expected a non-empty string")
        top = None if top is None else float(top)
        value = t[key]
        if key == "file":
            path = _site_file(value, base_dir, f"{where}.file")
            try:
                shapes = read_keepouts(path)
            except SiteFileError as exc:
                raise ConfigError(f"{where}.file: {exc}") from None
            # names within the file: Google Earth calls every new polygon "Untitled
            # Polygon", a GIS layer may name every tower "pylon": the repeats are numbered
            own = [sh.name or str(j) for j, sh in enumerate(shapes)]
            seen: dict[str, int] = {}
            for sh, base in zip(shapes, own, strict=True):
                seen[base] = seen.get(base, 0) + 1
                nm = f"{name}/{base}" if own.count(base) == 1 else f"{name}/{base} {seen[base]}"
                out.append(_zone(sh, origin, f"{where}.file", name=nm,
                                 top_m=sh.top_m if sh.top_m is not None else top))
            continue
        if key in ("circle_geo", "circle_enu_m"):
            if not isinstance(value, list) or len(value) != 3 or not all(
                    isinstance(v, int | float) and not isinstance(v, bool) for v in value):
                raise ConfigError(f"{where}.{key}: expected three numbers")
            if key == "circle_geo":
                center = _geo_to_enu(origin, [value[:2]], f"{where}.{key}")[0]
            else:
                center = (float(value[0]), float(value[1]))
            out.append(_zone(None, origin, where, name=name, center_enu_m=center,
                             radius_m=float(value[2]), top_m=top))
            continue
        if key == "polygon_geo":
            poly = _geo_to_enu(origin, value, f"{where}.polygon_geo")
        else:
            if not isinstance(value, list) or not all(
                    isinstance(v, list) and len(v) == 2 and all(
                        isinstance(x, int | float) and not isinstance(x, bool) for x in v)
                    for v in value):
                raise ConfigError(f"{where}.polygon_enu_m: expected an array of [e, n] pairs "
                                  "of numbers")
            poly = tuple((float(e), float(n)) for e, n in value)
        out.append(_zone(None, origin, where, name=name, polygon_enu_m=poly, top_m=top))
    names = [k.name for k in out]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ConfigError(f"search.keepout: the name {dup[0]!r} is used twice")
    return tuple(out)


def _search(table: Any, origin: Origin, base_dir: Path) -> SearchSpec:
    """``[search]``: the area in ENU, degrees or a file; the keep-outs converted to ENU."""
    if not isinstance(table, dict):
        raise ConfigError("search: expected a table")
    t = dict(table)
    if "keepouts" in t:
        raise ConfigError("search: unknown key 'keepouts' (keep-outs are [[search.keepout]] "
                          "tables)")
    given = [k for k in ("area_enu_m", "area_geo", "area_file") if k in t]
    if len(given) > 1:
        raise ConfigError(f"search: give one of area_enu_m, area_geo, area_file, not "
                          f"{' and '.join(given)}")
    if "area_geo" in t:
        t["area_enu_m"] = [list(v) for v in _geo_to_enu(origin, t.pop("area_geo"),
                                                        "search.area_geo")]
    elif "area_file" in t:
        path = _site_file(t.pop("area_file"), base_dir, "search.area_file")
        try:
            verts = read_area(path)
        except SiteFileError as exc:
            raise ConfigError(f"search.area_file: {exc}") from None
        t["area_enu_m"] = [list(v) for v in _geo_to_enu(origin, [list(v) for v in verts],
                                                        "search.area_file")]
    keep = _keepouts(t.pop("keepout"), origin, base_dir) if "keepout" in t else ()
    fields = {f.name for f in dataclasses.fields(SearchSpec)} - {"keepouts"}
    unknown = sorted(set(t) - fields)
    if unknown:  # the file's names: keepout tables, the area in degrees or a file
        known = ", ".join(sorted(fields | {"area_geo", "area_file", "keepout"}))
        raise ConfigError(f"search: unknown key {unknown[0]!r} (known: {known})")
    spec = from_table(SearchSpec, t, "search")
    if not keep:
        return spec
    try:
        return dataclasses.replace(spec, keepouts=keep)
    except ValueError as exc:
        raise ConfigError(f"search: {exc}") from None


def _flight(table: dict) -> Flight:
    t = dict(table)
    kind = t.get("kind")
    if not isinstance(kind, str) or kind not in FLIGHT_KINDS:
        raise ConfigError(f"flight.kind: {kind!r} is not one of {', '.join(FLIGHT_KINDS)}")
    return from_table(FLIGHT_KINDS[kind], t, "flight")


def _gnss(table: Any) -> GnssConfig:
    t = _table(table, "gnss")
    base = _preset(t.pop("preset", "standalone"), "gnss.preset")
    return from_table(GnssConfig, t, "gnss", base=base)


_TOP_KEYS = {
    "name", "description", "log", "world", "flight", "search", "agents", "vehicle", "gnss",
    "ftm", "clock", "randomise",
}  # fmt: skip


def _gnss_over(table: Any, base: GnssConfig, where: str) -> GnssConfig:
    t = _table(table, where)
    if "preset" in t:
        base = _preset(t.pop("preset"), f"{where}.preset")
    return from_table(GnssConfig, t, where, base=base)


_AGENT_KEYS = tuple(sorted(f.name for f in dataclasses.fields(AgentSpec)))  # [[agents]]


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
        unknown = sorted(set(t) - set(_AGENT_KEYS))
        if unknown:
            raise ConfigError(f"{where}: unknown key {unknown[0]!r} "
                              f"(known: {', '.join(_AGENT_KEYS)})")
        kind = t.pop("kind", "uav")
        if kind not in ("uav", "ground"):
            raise ConfigError(f"{where}.kind: {kind!r} is not 'uav' or 'ground'")
        v_base = vehicle if kind == "uav" else WALKER
        veh = from_table(VehicleConfig, t.pop("vehicle", {}), f"{where}.vehicle", base=v_base)
        gn = _gnss_over(t.pop("gnss", {}), gnss, f"{where}.gnss")
        name = t.pop("name", None)
        if not isinstance(name, str) or not name:
            raise ConfigError(f"{where}.name: expected a non-empty string")
        if name.casefold() in names:  # letter case aside: the logs' files would clash
            raise ConfigError(f"{where}.name: {name!r} is used twice (letter case aside)")
        if any(c in "/\\" or not c.isprintable() for c in name):
            raise ConfigError(f"{where}.name: {name!r} cannot be part of a file name (osa "
                              "search writes flight-NAME.jsonl): no '/', '\\' or control "
                              "characters")
        names.add(name.casefold())
        rest = from_table(_AgentStart, t, where)
        try:
            out.append(AgentSpec(name=name, kind=kind, vehicle=veh, gnss=gn,
                                 start_e_m=rest.start_e_m, start_n_m=rest.start_n_m))
        except ValueError as exc:
            raise ConfigError(f"{where}: {exc}") from None
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
        terrain_t = _table(world_t.get("terrain", {}), "world.terrain")
        dem = None
        if isinstance(terrain_t, dict) and terrain_t.get("kind") == "dem":
            dem = _dem_keys(terrain_t, base_dir)
            terrain: Terrain = _FLAT  # until the window the DEM must cover is known
        else:
            terrain = _terrain(terrain_t, base_dir)
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
            search = _search(table["search"], origin, base_dir)
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
            randomise=(from_table(Randomise, table["randomise"], "randomise")
                       if "randomise" in table else None),
        )
        if search is not None and search.hidden_share is not None and not scenario.ftm.occlusion:
            raise ConfigError("search.hidden_share needs terrain occlusion ([ftm] occlusion = "
                              "true): with it off the terrain hides nothing")
        check_randomised_wind(scenario)
        if search is not None:
            _check_search_height(scenario)
            _check_agent_starts(scenario)
        if dem is not None:
            dem_terrain = _dem_terrain(*dem, origin, scenario)
            scenario = dataclasses.replace(scenario, world=dataclasses.replace(
                world, terrain=dem_terrain))
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


HEIGHT_SIGMAS = 4.0  # the search height clears this many sigmas of the vertical error


def min_search_height_m(scenario: Scenario) -> float:
    """The lowest search height the scenario's UAVs can hold: the autopilot flies on its
    GNSS (sim.stepper: the receiver's slowly varying bias moves the true height off the
    commanded one), so the height must clear :data:`HEIGHT_SIGMAS` sigmas of that
    vertical error (bias and tracking wander, the largest ``[randomise]
    gnss_bias_scale`` included) and at least 2 m."""
    r = scenario.randomise
    scale = r.gnss_bias_scale[1] if r is not None and r.gnss_bias_scale is not None else 1.0
    sigma = max((math.hypot(a.gnss.bias_sigma_v_m * scale, a.vehicle.tracking_sigma_m)
                 for a in scenario.agents if a.kind == "uav"), default=0.0)
    return max(2.0, HEIGHT_SIGMAS * sigma)


def _check_search_height(scenario: Scenario) -> None:
    """Refuse a search height the UAVs' vertical navigation error would fly into the
    ground (ConfigError naming the keys)."""
    s = scenario.search
    floor = min_search_height_m(scenario)
    if s is not None and s.height_m < floor:
        raise ConfigError(
            f"search.height_m: {s.height_m:g} m is below {floor:.1f} m, "
            f"{HEIGHT_SIGMAS:g} sigmas of the vertical GNSS error the autopilot flies on "
            "(gnss.bias_sigma_v_m, times the largest randomise.gnss_bias_scale): fly higher "
            "or use preset = \"rtk\"")


def check_randomised_wind(scenario: Scenario) -> None:
    """Refuse a ``[randomise] wind_mps`` range reaching an agent's ``max_speed_mps``:
    a world drawing such a wind would be one its vehicle cannot fly (ConfigError)."""
    r = scenario.randomise
    if r is None or r.wind_mps is None:
        return
    vehicles = [("vehicle", scenario.vehicle)] + [(f"agent {a.name}'s", a.vehicle)
                                                  for a in scenario.agents]
    for who, v in vehicles:
        if r.wind_mps[1] >= v.max_speed_mps:
            raise ConfigError(
                f"randomise.wind_mps: up to {r.wind_mps[1]:g} m/s, at or above {who} "
                f"max_speed_mps {v.max_speed_mps:g} m/s (no headway against it): lower the "
                "range")


def _check_agent_starts(scenario: Scenario) -> None:
    """An agent's own start obeys the search start's rules: inside the area, outside
    every keep-out (ConfigError naming the agent)."""
    s = scenario.search
    for i, a in enumerate(scenario.agents_):
        if s is None or a.start_e_m is None:  # both or neither (AgentSpec)
            continue
        e, n = scenario.start_enu_m(i)
        if not s.contains(e, n):
            raise ConfigError(f"agents[{i}]: {a.name}'s start ({e:g}, {n:g}) is outside the "
                              "search area")
        for k in s.keepouts:
            if k.contains(e, n):
                raise ConfigError(f"agents[{i}]: {a.name}'s start ({e:g}, {n:g}) is inside "
                                  f"keep-out {k.name}")


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


def scenario_description(name_or_path: str | Path) -> str:
    """The ``description`` of a preset or TOML file (following ``extends``), read
    without building its world (a DEM preset's terrain takes seconds to load)."""
    description = _read_toml(name_or_path)[0].get("description", "")
    return description if isinstance(description, str) else ""


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
