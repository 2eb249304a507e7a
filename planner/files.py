"""Mission files: QGroundControl ``.plan`` (JSON) and "QGC WPL 110" text.

Formats (docs/mavlink.md):

- ``.plan``: ``fileType "Plan"``, ``version 1``; ``mission`` (version 2) holds
  ``SimpleItem`` entries whose ``params`` are the seven MAVLink params, with
  ``params[4:7] = lat, lon, alt`` and ``null`` for NaN; ``geoFence`` (version 2)
  holds polygons and circles; ``rallyPoints`` (version 2) holds ``[lat, lon, alt]``.
  Written with ``allow_nan=False`` (a bare NaN breaks MAVSDK's importer).
- ``.waypoints`` / ``.txt``: first line ``QGC WPL 110``, then one tab-separated
  line per item: ``index current frame command p1 p2 p3 p4 lat lon alt
  autocontinue``. Line 0 is the planned home in QGroundControl's and ArduPilot's
  convention (``current=1``, frame 0, NAV_WAYPOINT, AMSL altitude); mission item
  ``k`` is line ``k + 1``. The reader takes line 0 as :attr:`Mission.home` and
  never as an item, so the text round-trips. WPL holds no fence, rally point or
  speed: :func:`write_wpl` refuses a mission with a fence or rally points unless
  ``drop_fence=True``.

Numbers are written so that they read back as the same double (JSON floats are
shortest round-trip reprs; WPL uses the same digits in positional notation), so
Mission -> file -> Mission is exact, well inside the int degE7 / 1e-6 m contract.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from decimal import Decimal
from pathlib import Path
from typing import Any

from planner.mission import (
    MAV_CMD_DO_JUMP,
    MAV_CMD_NAV_WAYPOINT,
    MAV_FRAME_GLOBAL,
    MAV_FRAME_GLOBAL_INT,
    MAV_FRAME_GLOBAL_RELATIVE_ALT,
    MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
    MAV_FRAME_GLOBAL_TERRAIN_ALT,
    MAV_FRAME_GLOBAL_TERRAIN_ALT_INT,
    FenceCircle,
    FencePolygon,
    Mission,
    MissionItem,
)

__all__ = [
    "MissionFileError",
    "read_mission",
    "read_plan",
    "read_wpl",
    "write_mission",
    "write_plan",
    "write_wpl",
]

PathLike = str | os.PathLike[str]

PLAN_SUFFIXES = (".plan",)
WPL_SUFFIXES = (".waypoints", ".txt")
WPL_HEADER = "QGC WPL 110"
GROUND_STATION = "osa-testbed"

# QGroundControl's firmwareType / vehicleType are MAV_AUTOPILOT / MAV_TYPE values.
FIRMWARE_TO_MAV_AUTOPILOT = {"generic": 0, "ardupilot": 3, "px4": 12}
MAV_AUTOPILOT_TO_FIRMWARE = {v: k for k, v in FIRMWARE_TO_MAV_AUTOPILOT.items()}
VEHICLE_TO_MAV_TYPE = {
    "generic": 0,
    "fixed_wing": 1,
    "multirotor": 2,
    "rover": 10,
    "vtol": 20,
}
MAV_TYPE_TO_VEHICLE = {v: k for k, v in VEHICLE_TO_MAV_TYPE.items()}
# other multirotor MAV_TYPEs (hexa, octo, tri, coaxial, heli, dodeca) read as multirotor
MAV_TYPE_TO_VEHICLE.update({3: "multirotor", 4: "multirotor", 13: "multirotor",
                            14: "multirotor", 15: "multirotor", 29: "multirotor"})

# QGroundControl AltitudeMode: 0 mixed, 1 relative, 2 absolute (AMSL), 3 calc above
# terrain, 4 terrain frame, 5 none.
ALT_MODE_MIXED, ALT_MODE_RELATIVE, ALT_MODE_ABSOLUTE, ALT_MODE_TERRAIN = 0, 1, 2, 4
_FRAME_ALT_MODE = {
    MAV_FRAME_GLOBAL: ALT_MODE_ABSOLUTE,
    MAV_FRAME_GLOBAL_INT: ALT_MODE_ABSOLUTE,
    MAV_FRAME_GLOBAL_RELATIVE_ALT: ALT_MODE_RELATIVE,
    MAV_FRAME_GLOBAL_RELATIVE_ALT_INT: ALT_MODE_RELATIVE,
    MAV_FRAME_GLOBAL_TERRAIN_ALT: ALT_MODE_TERRAIN,
    MAV_FRAME_GLOBAL_TERRAIN_ALT_INT: ALT_MODE_TERRAIN,
}

PLAN_VERSION = 1
MISSION_VERSION = 2
GEOFENCE_VERSION = 2
RALLY_VERSION = 2
FENCE_SHAPE_VERSION = 1


class MissionFileError(ValueError):
    """A mission file that cannot be read or a mission that cannot be written."""


# ---------------------------------------------------------------- dispatch


def _suffix(path: PathLike) -> str:
    return Path(path).suffix.lower()


def write_mission(mission: Mission, path: PathLike) -> None:
    """Write ``mission`` as ``.plan`` or ``.waypoints``/``.txt``, chosen by suffix."""
    suffix = _suffix(path)
    if suffix in PLAN_SUFFIXES:
        write_plan(mission, path)
    elif suffix in WPL_SUFFIXES:
        write_wpl(mission, path)
    else:
        raise MissionFileError(
            f"{path}: unknown mission file type {suffix!r} (use .plan, .waypoints or .txt)"
        )


def read_mission(path: PathLike) -> Mission:
    """Read a ``.plan`` or ``.waypoints``/``.txt`` mission, chosen by suffix."""
    suffix = _suffix(path)
    if suffix in PLAN_SUFFIXES:
        return read_plan(path)
    if suffix in WPL_SUFFIXES:
        return read_wpl(path)
    raise MissionFileError(
        f"{path}: unknown mission file type {suffix!r} (use .plan, .waypoints or .txt)"
    )


MAX_FILE_BYTES = 64 << 20  # a mission of 65 535 items is ~25 MB of .plan JSON
MAX_ITEMS = 0xFFFF  # MAVLink's seq is a uint16


def _read_text(path: PathLike) -> str:
    """The file's text, at most MAX_FILE_BYTES (read once: a pipe works too)."""
    try:
        with Path(path).open("rb") as fh:
            data = fh.read(MAX_FILE_BYTES + 1)
        if len(data) > MAX_FILE_BYTES:
            raise MissionFileError(f"{path}: larger than {MAX_FILE_BYTES >> 20} MiB: not a "
                                   "mission file")
        return data.decode("utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise MissionFileError(f"{path}: cannot read: {exc}") from exc


def _write_text(path: PathLike, text: str) -> None:
    """Write atomically (temp file + rename), so a failed write leaves no half file."""
    target = Path(path)
    tmp = target.with_name(f".{target.name}.tmp{os.getpid()}")
    try:
        tmp.write_text(text, encoding="utf-8")
        os.replace(tmp, target)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise MissionFileError(f"{path}: cannot write: {exc}") from exc


# ---------------------------------------------------------------- validation


def _check_lat_lon(lat: float, lon: float, where: str) -> None:
    if not (math.isfinite(lat) and math.isfinite(lon)):
        raise MissionFileError(f"{where}: non-finite coordinate lat={lat!r} lon={lon!r}")
    if abs(lat) > 90.0:
        raise MissionFileError(f"{where}: latitude {lat!r} outside [-90, 90]")
    if abs(lon) > 180.0:
        raise MissionFileError(f"{where}: longitude {lon!r} outside [-180, 180]")


def _check_alt(alt: float, where: str) -> None:
    if not math.isfinite(alt):
        raise MissionFileError(f"{where}: non-finite altitude {alt!r}")


def _check_item(item: MissionItem, where: str) -> None:
    _check_lat_lon(item.lat_deg, item.lon_deg, where)
    _check_alt(item.alt_m, where)
    if not 0 <= item.command <= 0xFFFF:
        raise MissionFileError(f"{where}: command {item.command} outside uint16")
    if not 0 <= item.frame <= 0xFF:
        raise MissionFileError(f"{where}: frame {item.frame} outside uint8")
    for k, p in enumerate((item.param1, item.param2, item.param3, item.param4), start=1):
        if math.isinf(p):
            raise MissionFileError(f"{where}: param{k} is infinite")


def _check_mission(mission: Mission) -> None:
    """Refuse to write what could not be read back (or uploaded)."""
    if len(mission.home) != 3:
        raise MissionFileError("home must be (lat_deg, lon_deg, alt_m)")
    _check_lat_lon(mission.home[0], mission.home[1], "home")
    _check_alt(mission.home[2], "home")
    for i, item in enumerate(mission.items):
        _check_item(item, f"item {i}")
    for i, poly in enumerate(mission.polygons):
        _check_polygon(poly, f"fence polygon {i}")
    for i, circle in enumerate(mission.circles):
        _check_circle(circle, f"fence circle {i}")
    for i, (lat, lon, alt) in enumerate(mission.rally_deg):
        _check_lat_lon(lat, lon, f"rally point {i}")
        _check_alt(alt, f"rally point {i}")
    for name, speed in (("cruise", mission.cruise_speed_m_s), ("hover", mission.hover_speed_m_s)):
        if not math.isfinite(speed):
            raise MissionFileError(f"{name} speed {speed!r} m/s is not finite")


def _check_polygon(poly: FencePolygon, where: str) -> None:
    if len(poly.vertices_deg) < 3:
        raise MissionFileError(f"{where}: {len(poly.vertices_deg)} vertices, need >= 3")
    for j, (lat, lon) in enumerate(poly.vertices_deg):
        _check_lat_lon(lat, lon, f"{where} vertex {j}")


def _check_circle(circle: FenceCircle, where: str) -> None:
    _check_lat_lon(circle.lat_deg, circle.lon_deg, where)
    if not (math.isfinite(circle.radius_m) and circle.radius_m > 0.0):
        raise MissionFileError(f"{where}: radius {circle.radius_m!r} m must be finite and > 0")


# ---------------------------------------------------------------- .plan


def _json_num(x: float) -> float | None:
    """A float for JSON: NaN becomes null (``allow_nan=False`` refuses it)."""
    return None if math.isnan(x) else float(x)


def _global_alt_mode(items: tuple[MissionItem, ...]) -> int:
    modes = {_FRAME_ALT_MODE.get(it.frame) for it in items} - {None}
    return modes.pop() if len(modes) == 1 else (ALT_MODE_RELATIVE if not modes else ALT_MODE_MIXED)



def _jump_out(it: MissionItem) -> float:
    """param1 as files hold it: a DO_JUMP's target is item index + 1 in both formats
    (QGC's doJumpId of the target, which we write as index + 1; a WPL line number,
    home being line 0). In a Mission it is the target's item index (its seq on PX4)."""
    return it.param1 + 1.0 if it.command == MAV_CMD_DO_JUMP else it.param1


def _resolve_jumps(items: tuple[MissionItem, ...], raw: list) -> tuple[MissionItem, ...]:
    """Map each DO_JUMP's param1 (a QGC doJumpId) to the target's item index."""
    if not any(it.command == MAV_CMD_DO_JUMP for it in items):
        return items
    ids = {}
    for i, r in enumerate(raw):
        jid = r.get("doJumpId", i + 1) if isinstance(r, dict) else i + 1
        if isinstance(jid, int | float) and not isinstance(jid, bool):
            ids.setdefault(int(jid), i)
    out = []
    for i, it in enumerate(items):
        if it.command == MAV_CMD_DO_JUMP:
            target = ids.get(int(it.param1)) if math.isfinite(it.param1) else None
            if target is None:
                raise MissionFileError(
                    f"mission.items[{i}]: DO_JUMP to doJumpId {it.param1:g}, which no item has"
                )
            it = dataclasses.replace(it, param1=float(target))
        out.append(it)
    return tuple(out)


def plan_dict(mission: Mission) -> dict[str, Any]:
    """The ``.plan`` JSON object for ``mission`` (validated)."""
    _check_mission(mission)
    firmware = FIRMWARE_TO_MAV_AUTOPILOT.get(mission.firmware.lower())
    if firmware is None:
        raise MissionFileError(
            f"unknown firmware {mission.firmware!r} (one of {sorted(FIRMWARE_TO_MAV_AUTOPILOT)})"
        )
    vehicle = VEHICLE_TO_MAV_TYPE.get(mission.vehicle_type.lower())
    if vehicle is None:
        raise MissionFileError(
            f"unknown vehicle type {mission.vehicle_type!r} (one of {sorted(VEHICLE_TO_MAV_TYPE)})"
        )
    items = []
    for i, it in enumerate(mission.items):
        items.append(
            {
                "AMSLAltAboveTerrain": None,
                "Altitude": float(it.alt_m),
                "AltitudeMode": _FRAME_ALT_MODE.get(it.frame, ALT_MODE_RELATIVE),
                "autoContinue": bool(it.autocontinue),
                "command": int(it.command),
                "doJumpId": i + 1,
                "frame": int(it.frame),
                "params": [
                    _json_num(_jump_out(it)),
                    _json_num(it.param2),
                    _json_num(it.param3),
                    _json_num(it.param4),
                    float(it.lat_deg),
                    float(it.lon_deg),
                    float(it.alt_m),
                ],
                "type": "SimpleItem",
            }
        )
    return {
        "fileType": "Plan",
        "geoFence": {
            "circles": [
                {
                    "circle": {"center": [float(c.lat_deg), float(c.lon_deg)],
                               "radius": float(c.radius_m)},
                    "inclusion": bool(c.inclusion),
                    "version": FENCE_SHAPE_VERSION,
                }
                for c in mission.circles
            ],
            "polygons": [
                {
                    "inclusion": bool(p.inclusion),
                    "polygon": [[float(lat), float(lon)] for lat, lon in p.vertices_deg],
                    "version": FENCE_SHAPE_VERSION,
                }
                for p in mission.polygons
            ],
            "version": GEOFENCE_VERSION,
        },
        "groundStation": GROUND_STATION,
        "mission": {
            "cruiseSpeed": float(mission.cruise_speed_m_s),
            "firmwareType": firmware,
            "globalPlanAltitudeMode": _global_alt_mode(mission.items),
            "hoverSpeed": float(mission.hover_speed_m_s),
            "items": items,
            "plannedHomePosition": [float(v) for v in mission.home],
            "vehicleType": vehicle,
            "version": MISSION_VERSION,
        },
        "rallyPoints": {
            "points": [[float(lat), float(lon), float(alt)] for lat, lon, alt in mission.rally_deg],
            "version": RALLY_VERSION,
        },
        "version": PLAN_VERSION,
    }


def write_plan(mission: Mission, path: PathLike) -> None:
    """Write ``mission`` as a QGroundControl ``.plan`` (JSON, no bare NaN)."""
    try:
        obj = plan_dict(mission)
    except MissionFileError as exc:
        raise MissionFileError(f"{path}: {exc}") from None
    _write_text(path, json.dumps(obj, indent=4, allow_nan=False) + "\n")


def _reject_constant(name: str) -> float:
    raise MissionFileError(f"bare {name} in JSON (NaN must be written as null)")


def _get(obj: dict[str, Any], key: str, kind: type | tuple[type, ...], where: str) -> Any:
    if not isinstance(obj, dict):
        raise MissionFileError(f"{where}: expected an object, got {type(obj).__name__}")
    if key not in obj:
        raise MissionFileError(f"{where}: missing key {key!r}")
    val = obj[key]
    if isinstance(val, bool) and bool not in (kind if isinstance(kind, tuple) else (kind,)):
        raise MissionFileError(f"{where}.{key}: expected {_kind_name(kind)}, got a boolean")
    if not isinstance(val, kind):
        raise MissionFileError(
            f"{where}.{key}: expected {_kind_name(kind)}, got {type(val).__name__}"
        )
    return val


def _list(obj: dict[str, Any], key: str, where: str) -> list[Any]:
    """An optional JSON array (missing = empty)."""
    return _get(obj, key, list, where) if key in obj else []


def _kind_name(kind: type | tuple[type, ...]) -> str:
    kinds = kind if isinstance(kind, tuple) else (kind,)
    return " or ".join(k.__name__ for k in kinds)


def _num(val: Any, where: str, *, nullable: bool = False) -> float:
    """A JSON number as float; ``null`` is NaN when ``nullable``."""
    if val is None and nullable:
        return math.nan
    if isinstance(val, bool) or not isinstance(val, int | float):
        raise MissionFileError(f"{where}: expected a number, got {val!r}")
    out = float(val)
    if not math.isfinite(out):
        raise MissionFileError(f"{where}: non-finite number {val!r}")
    return out


def _int(val: Any, where: str, lo: int, hi: int) -> int:
    if isinstance(val, float) and val.is_integer():
        val = int(val)
    if isinstance(val, bool) or not isinstance(val, int):
        raise MissionFileError(f"{where}: expected an integer, got {val!r}")
    if not lo <= val <= hi:
        raise MissionFileError(f"{where}: {val} outside [{lo}, {hi}]")
    return val


def _check_version(obj: dict[str, Any], where: str, expected: int) -> None:
    version = _get(obj, "version", int, where)
    if version != expected:
        raise MissionFileError(f"{where}: unsupported version {version} (expected {expected})")


def _plan_item(raw: Any, i: int) -> MissionItem:
    where = f"mission.items[{i}]"
    kind = _get(raw, "type", str, where)
    if kind == "ComplexItem":
        sub = raw.get("complexItemType", "?")
        raise MissionFileError(
            f"{where}: ComplexItem ({sub}) is not supported, only SimpleItem; "
            "convert it to waypoints in QGroundControl first"
        )
    if kind != "SimpleItem":
        raise MissionFileError(f"{where}: unknown item type {kind!r} (only SimpleItem)")
    params = _get(raw, "params", list, where)
    if len(params) != 7:
        raise MissionFileError(f"{where}.params: {len(params)} values, expected 7")
    p = [_num(v, f"{where}.params[{k}]", nullable=k < 4) for k, v in enumerate(params)]
    lat, lon, alt = p[4], p[5], p[6]
    _check_lat_lon(lat, lon, where)
    auto = _get(raw, "autoContinue", (bool, int), where)
    return MissionItem(
        command=_int(_get(raw, "command", (int, float), where), f"{where}.command", 0, 0xFFFF),
        frame=_int(_get(raw, "frame", (int, float), where), f"{where}.frame", 0, 0xFF),
        lat_deg=lat,
        lon_deg=lon,
        alt_m=alt,
        param1=p[0],
        param2=p[1],
        param3=p[2],
        param4=p[3],
        autocontinue=bool(auto),
    )


def parse_plan(obj: Any, source: str = "<plan>") -> Mission:
    """Validate a parsed ``.plan`` JSON object and build the Mission."""
    if not isinstance(obj, dict):
        raise MissionFileError(f"{source}: top level is not a JSON object")
    file_type = obj.get("fileType")
    if file_type != "Plan":
        raise MissionFileError(f"{source}: fileType is {file_type!r}, expected 'Plan'")
    try:
        _check_version(obj, "plan", PLAN_VERSION)
        mission_obj = _get(obj, "mission", dict, "plan")
        _check_version(mission_obj, "mission", MISSION_VERSION)
        home_raw = _get(mission_obj, "plannedHomePosition", list, "mission")
        if len(home_raw) != 3:
            raise MissionFileError("mission.plannedHomePosition: expected [lat, lon, alt]")
        home = tuple(_num(v, "mission.plannedHomePosition") for v in home_raw)
        _check_lat_lon(home[0], home[1], "mission.plannedHomePosition")
        raw_items = _get(mission_obj, "items", list, "mission")
        if len(raw_items) > MAX_ITEMS:
            raise MissionFileError(f"mission.items: {len(raw_items)} items, more than "
                                   f"MAVLink numbers ({MAX_ITEMS})")
        items = _resolve_jumps(tuple(_plan_item(raw, i) for i, raw in enumerate(raw_items)),
                               raw_items)
        firmware_code = _int(mission_obj.get("firmwareType", 0), "mission.firmwareType", 0, 255)
        vehicle_code = _int(mission_obj.get("vehicleType", 0), "mission.vehicleType", 0, 255)
        cruise = _num(mission_obj.get("cruiseSpeed", 10.0), "mission.cruiseSpeed")
        hover = _num(mission_obj.get("hoverSpeed", 5.0), "mission.hoverSpeed")

        polygons: list[FencePolygon] = []
        circles: list[FenceCircle] = []
        fence = obj.get("geoFence")
        if fence is not None:
            _check_version(fence, "geoFence", GEOFENCE_VERSION)
            for j, raw in enumerate(_list(fence, "polygons", "geoFence")):
                where = f"geoFence.polygons[{j}]"
                verts = _get(raw, "polygon", list, where)
                pts = []
                for k, v in enumerate(verts):
                    if not isinstance(v, list) or len(v) != 2:
                        raise MissionFileError(f"{where}.polygon[{k}]: expected [lat, lon]")
                    pts.append((_num(v[0], where), _num(v[1], where)))
                poly = FencePolygon(
                    vertices_deg=tuple(pts),
                    inclusion=bool(_get(raw, "inclusion", (bool, int), where)),
                )
                _check_polygon(poly, where)
                polygons.append(poly)
            for j, raw in enumerate(_list(fence, "circles", "geoFence")):
                where = f"geoFence.circles[{j}]"
                circ = _get(raw, "circle", dict, where)
                center = _get(circ, "center", list, where + ".circle")
                if len(center) != 2:
                    raise MissionFileError(f"{where}.circle.center: expected [lat, lon]")
                circle = FenceCircle(
                    lat_deg=_num(center[0], where),
                    lon_deg=_num(center[1], where),
                    radius_m=_num(_get(circ, "radius", (int, float), where + ".circle"), where),
                    inclusion=bool(_get(raw, "inclusion", (bool, int), where)),
                )
                _check_circle(circle, where)
                circles.append(circle)

        rally: list[tuple[float, float, float]] = []
        rally_obj = obj.get("rallyPoints")
        if rally_obj is not None:
            _check_version(rally_obj, "rallyPoints", RALLY_VERSION)
            for j, pt in enumerate(_list(rally_obj, "points", "rallyPoints")):
                where = f"rallyPoints.points[{j}]"
                if not isinstance(pt, list) or len(pt) != 3:
                    raise MissionFileError(f"{where}: expected [lat, lon, alt]")
                lat, lon, alt = (_num(v, where) for v in pt)
                _check_lat_lon(lat, lon, where)
                rally.append((lat, lon, alt))
    except MissionFileError as exc:
        raise MissionFileError(f"{source}: {exc}") from None

    return Mission(
        items=items,
        home=home,  # type: ignore[arg-type]
        polygons=tuple(polygons),
        circles=tuple(circles),
        rally_deg=tuple(rally),
        cruise_speed_m_s=cruise,
        hover_speed_m_s=hover,
        vehicle_type=MAV_TYPE_TO_VEHICLE.get(vehicle_code, "generic"),
        firmware=MAV_AUTOPILOT_TO_FIRMWARE.get(firmware_code, "generic"),
        name=Path(source).stem if source != "<plan>" else "",
        meta={"groundStation": obj.get("groundStation")},
    )


def read_plan(path: PathLike) -> Mission:
    """Read and validate a QGroundControl ``.plan`` file (SimpleItems only)."""
    text = _read_text(path)
    try:
        obj = json.loads(text, parse_constant=_reject_constant)
    except MissionFileError as exc:
        raise MissionFileError(f"{path}: {exc}") from None
    except json.JSONDecodeError as exc:
        raise MissionFileError(
            f"{path}: malformed JSON at line {exc.lineno} column {exc.colno}: {exc.msg}"
        ) from None
    except RecursionError:  # brackets nested thousands deep: no mission looks like that
        raise MissionFileError(f"{path}: JSON nested too deeply: not a mission file") from None
    return parse_plan(obj, str(path))


# ---------------------------------------------------------------- QGC WPL 110


def _wpl_num(x: float) -> str:
    """Shortest round-trip digits in positional notation (no exponent); NaN as ``nan``."""
    if math.isnan(x):
        return "nan"
    if x == 0.0:
        return "0"
    text = format(Decimal(repr(float(x))), "f")
    return text


def _wpl_line(index: int, current: int, frame: int, command: int,
              params: tuple[float, float, float, float],
              lat: float, lon: float, alt: float, autocontinue: bool) -> str:
    fields = [str(index), str(current), str(frame), str(command)]
    fields += [_wpl_num(p) for p in params]
    fields += [_wpl_num(lat), _wpl_num(lon), _wpl_num(alt), str(int(bool(autocontinue)))]
    return "\t".join(fields)


def wpl_text(mission: Mission, *, drop_fence: bool = False) -> str:
    """The "QGC WPL 110" text: line 0 the planned home, then the items."""
    _check_mission(mission)
    if (mission.polygons or mission.circles or mission.rally_deg) and not drop_fence:
        raise MissionFileError(
            "a QGC WPL file cannot hold a geofence or rally points; write a .plan instead"
        )
    lat, lon, alt = mission.home
    lines = [WPL_HEADER,
             _wpl_line(0, 1, MAV_FRAME_GLOBAL, MAV_CMD_NAV_WAYPOINT, (0.0, 0.0, 0.0, 0.0),
                       lat, lon, alt, True)]
    for i, it in enumerate(mission.items, start=1):
        lines.append(_wpl_line(i, 0, it.frame, it.command,
                               (_jump_out(it), it.param2, it.param3, it.param4),
                               it.lat_deg, it.lon_deg, it.alt_m, it.autocontinue))
    return "\n".join(lines) + "\n"


def write_wpl(mission: Mission, path: PathLike, *, drop_fence: bool = False) -> None:
    """Write "QGC WPL 110" text; refuses a fence/rally points unless ``drop_fence``."""
    try:
        text = wpl_text(mission, drop_fence=drop_fence)
    except MissionFileError as exc:
        raise MissionFileError(f"{path}: {exc}") from None
    _write_text(path, text)


def _wpl_float(tok: str, where: str, *, nan_ok: bool) -> float:
    try:
        val = float(tok)
    except ValueError:
        raise MissionFileError(f"{where}: not a number: {tok!r}") from None
    if math.isinf(val) or (math.isnan(val) and not nan_ok):
        raise MissionFileError(f"{where}: non-finite value {tok!r}")
    return val


def _wpl_int(tok: str, where: str, lo: int, hi: int) -> int:
    try:
        val = int(tok)
    except ValueError:
        raise MissionFileError(f"{where}: not an integer: {tok!r}") from None
    if not lo <= val <= hi:
        raise MissionFileError(f"{where}: {val} outside [{lo}, {hi}]")
    return val


def parse_wpl(text: str, source: str = "<wpl>") -> Mission:
    """Parse "QGC WPL 110" text: line 0 is home, lines 1.. are the items."""
    lines = text.splitlines()
    if not lines or lines[0].strip() != WPL_HEADER:
        first = lines[0].strip()[:40] if lines else ""
        raise MissionFileError(f"{source}: first line is {first!r}, expected {WPL_HEADER!r}")
    home: tuple[float, float, float] | None = None
    items: list[MissionItem] = []
    expected = 0
    for lineno, line in enumerate(lines[1:], start=2):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        where = f"{source}:{lineno}"
        toks = line.split()
        if len(toks) != 12:
            raise MissionFileError(f"{where}: {len(toks)} fields, expected 12")
        index = _wpl_int(toks[0], f"{where} index", 0, 0xFFFF)
        if index != expected:
            raise MissionFileError(f"{where}: index {index}, expected {expected}")
        expected += 1
        _wpl_int(toks[1], f"{where} current", 0, 1)
        frame = _wpl_int(toks[2], f"{where} frame", 0, 0xFF)
        command = _wpl_int(toks[3], f"{where} command", 0, 0xFFFF)
        params = [_wpl_float(t, f"{where} param{k + 1}", nan_ok=True)
                  for k, t in enumerate(toks[4:8])]
        lat = _wpl_float(toks[8], f"{where} latitude", nan_ok=False)
        lon = _wpl_float(toks[9], f"{where} longitude", nan_ok=False)
        alt = _wpl_float(toks[10], f"{where} altitude", nan_ok=False)
        auto = _wpl_int(toks[11], f"{where} autocontinue", 0, 1)
        _check_lat_lon(lat, lon, where)
        if index == 0:
            home = (lat, lon, alt)
            continue
        if command == MAV_CMD_DO_JUMP:  # the file counts home as line 0
            params[0] -= 1.0
        items.append(MissionItem(command=command, frame=frame, lat_deg=lat, lon_deg=lon,
                                 alt_m=alt, param1=params[0], param2=params[1],
                                 param3=params[2], param4=params[3],
                                 autocontinue=bool(auto)))
    if home is None:
        raise MissionFileError(f"{source}: no home line (index 0)")
    return Mission(items=tuple(items), home=home,
                   name=Path(source).stem if source != "<wpl>" else "")


def read_wpl(path: PathLike) -> Mission:
    """Read a "QGC WPL 110" file (line 0 = home, not an item)."""
    return parse_wpl(_read_text(path), str(path))
