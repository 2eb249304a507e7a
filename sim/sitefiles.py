"""Site files: search areas and keep-outs drawn in Google Earth, QGIS or QGroundControl.

Readers for the three formats an operator has (docs/scenarios.md, docs/planner.md):

- KML (Google Earth, QGIS), or KMZ (Google Earth's zip: its ``doc.kml``), in the
  encoding its XML declaration or byte order mark names: ``Placemark`` elements with a
  ``Polygon`` (its
  ``outerBoundaryIs`` ring; holes are refused) or a ``Point`` with a ``radius_m``
  (a circle), in a ``Document``/``Folder`` tree or inside a ``MultiGeometry``;
  ``top_m`` and ``radius_m`` from the placemark's ``ExtendedData`` (``<Data
  name="top_m"><value>35</value></Data>`` or ``<SimpleData name="top_m">``).
  Coordinates are ``lon,lat[,alt]`` tuples (spaces beside their commas closed up).
  Parsed with :mod:`xml.etree.ElementTree` with care: a document type declaration
  (``<!DOCTYPE``, hence any entity) is refused, so no external entity is ever resolved
  and no entity expands.
- GeoJSON (RFC 7946): a ``Polygon`` (or ``MultiPolygon`` of one polygon) geometry,
  ``Feature`` or ``FeatureCollection``; ``Point`` features with a ``radius_m``
  property are circles; ``top_m`` is a feature property; a feature whose geometry is
  ``null`` is no shape. Positions are [lon, lat] (a height and further numbers, such
  as a measure or a time, are ignored, as RFC 7946 allows), or, under a top-level
  ``crs`` member (GeoJSON 2008, as QGIS and GDAL write a layer saved in its projected
  CRS), [x, y] in that CRS, converted with pyproj.
- QGroundControl ``.plan``: its ``geoFence`` polygons and circles ([lat, lon]
  vertices, ``inclusion`` flags).

:func:`read_area` returns the one polygon of a search area (a KML or GeoJSON with one
polygon, a ``.plan`` whose geoFence holds one inclusion polygon); :func:`read_keepouts`
every shape of a keep-out file (a ``.plan``'s exclusion polygons and circles). Files
are bounded (:data:`MAX_FILE_BYTES`, :data:`MAX_VERTICES`); every problem is a
:class:`SiteFileError` with one line naming the file. Nothing here knows a frame: the
scenario (``sim.scenario``) and ``osa plan`` convert the shapes once to their ENU frame.
"""

from __future__ import annotations

import json
import math
import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path
from typing import Any

MAX_FILE_BYTES = 20_000_000
MAX_VERTICES = 200_000
AREA_SUFFIXES = (".kml", ".kmz", ".geojson", ".json", ".plan")

LatLon = tuple[float, float]


class SiteFileError(ValueError):
    """A site file that cannot be read or used (one line, naming the file)."""


@dataclass(frozen=True, kw_only=True)
class GeoShape:
    """A polygon (``vertices_deg``: (lat, lon), open ring) or a circle (``center_deg``
    and ``radius_m``), with an optional height above ground (``top_m``) and a name."""

    vertices_deg: tuple[LatLon, ...] = ()
    center_deg: LatLon | None = None
    radius_m: float | None = None
    top_m: float | None = None
    name: str = ""
    inclusion: bool = False  # an area: a .plan's inclusion fence, osa plan's KML's area
    survey: bool = False  # a .plan's Survey pattern polygon (an area, never a keep-out)

    @property
    def is_circle(self) -> bool:
        return self.center_deg is not None


# ----------------------------------------------------------------------------- checks


def _latlon(lat: Any, lon: Any, where: str) -> LatLon:
    for v in (lat, lon):
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
            raise SiteFileError(f"{where}: coordinate {v!r} is not a finite number")
    if not -90.0 <= lat <= 90.0 or not -180.0 <= lon <= 180.0:
        raise SiteFileError(f"{where}: ({lat}, {lon}) is not a latitude/longitude")
    return float(lat), float(lon)


def _ring(vertices: list[LatLon], where: str) -> tuple[LatLon, ...]:
    """An open ring: the closing vertex (and repeated ones) dropped, >= 3 left."""
    out: list[LatLon] = []
    for v in vertices:
        if not out or v != out[-1]:
            out.append(v)
    if len(out) > 1 and out[0] == out[-1]:
        out.pop()
    if len(out) < 3:
        raise SiteFileError(f"{where}: a polygon needs at least 3 distinct vertices")
    return tuple(out)


def _height(value: Any, key: str, where: str, positive: bool = False) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise SiteFileError(f"{where}: {key} {value!r} is not a number") from None
    if isinstance(value, bool) or not math.isfinite(v) or v < 0 or (positive and v == 0):
        raise SiteFileError(f"{where}: {key} {value!r} must be a finite number "
                            f"{'> 0' if positive else '>= 0'}")
    return v


def _read_bytes(path: Path) -> bytes:
    try:
        size = path.stat().st_size
    except OSError as exc:
        raise SiteFileError(f"{path}: cannot read: {exc.strerror or exc}") from None
    if size > MAX_FILE_BYTES:
        raise SiteFileError(f"{path}: {size:,} bytes, more than the {MAX_FILE_BYTES:,} a site "
                            "file may hold")
    try:
        return path.read_bytes()
    except OSError as exc:
        raise SiteFileError(f"{path}: cannot read: {exc.strerror or exc}") from None


def _read(path: Path) -> str:
    """A JSON file's text: UTF-8 (RFC 8259), or UTF-16 with its byte order mark (what
    Windows PowerShell's ``Out-File`` and Notepad's "Unicode" write)."""
    data = _read_bytes(path)
    codec = "utf-16" if data.startswith((b"\xff\xfe", b"\xfe\xff")) else "utf-8-sig"
    try:
        return data.decode(codec)
    except UnicodeDecodeError as exc:
        raise SiteFileError(f"{path}: not {codec.removesuffix('-sig').upper()} text: "
                            f"{exc.reason} at byte {exc.start}") from None


def _kmz_kml(path: Path) -> bytes:
    """The KML document of a KMZ (Google Earth's zip): its ``doc.kml``, else its one
    ``.kml`` file at the top, else the first ``.kml`` in it (the others are overlays'
    and models' files); bounded by :data:`MAX_FILE_BYTES` however it is compressed."""
    import zipfile

    try:
        with zipfile.ZipFile(path) as z:
            names = [n for n in z.namelist() if n.lower().endswith(".kml")]
            if not names:
                raise SiteFileError(f"{path}: a KMZ without a .kml document in it")
            top = [n for n in names if "/" not in n]
            name = next((n for n in names if n.lower() == "doc.kml"),
                        top[0] if top else names[0])
            with z.open(name) as fh:
                data = fh.read(MAX_FILE_BYTES + 1)
    except (OSError, zipfile.BadZipFile, RuntimeError, NotImplementedError) as exc:
        raise SiteFileError(f"{path}: not a readable KMZ (zip) file: {exc}") from None
    if len(data) > MAX_FILE_BYTES:
        raise SiteFileError(f"{path}: its KML holds more than the {MAX_FILE_BYTES:,} bytes a "
                            "site file may hold")
    return data


# ----------------------------------------------------------------------------- KML

# a hole's meaning differs for an area (not to search, may be flown over) and a keep-out
# (may be entered): the file must say which (docs/scenarios.md, "Site files")
_HOLES = ("polygons with holes are not supported (an area's hole: draw it as a keep-out "
          "if it must not be flown; a keep-out with a hole: draw it as polygons without holes)")
# ExtendedData that osa plan's KML gives each placemark: "mission", "home", "search area"
# or "keep-out"; its search area is the file's area, never one of its keep-outs
ROLE_KEY = "osa_role"
_DOCTYPE = re.compile(r"<!\s*(DOCTYPE|ENTITY)", re.IGNORECASE)
_XML_ENCODING = re.compile(rb"^<\?xml[^>]*?encoding\s*=\s*[\"']([A-Za-z0-9._-]+)[\"']")
_COMMA = re.compile(r"\s*,\s*")


def _local(tag: str) -> str:
    return tag.rsplit("}", 1)[-1]


def _children(el: ET.Element, name: str) -> list[ET.Element]:
    return [c for c in el if _local(c.tag) == name]


def _descendants(el: ET.Element, name: str) -> list[ET.Element]:
    return [c for c in el.iter() if _local(c.tag) == name]


def _kml_coords(text: str | None, where: str) -> list[LatLon]:
    out = []
    # tuples are separated by whitespace; a space beside a comma ("lon, lat") is not
    # KML, but hand-edited files have it: it is closed up first
    for tok in _COMMA.sub(",", (text or "").strip()).split():
        parts = tok.split(",")
        if len(parts) < 2:
            raise SiteFileError(f"{where}: coordinates {tok!r} are not lon,lat[,alt]")
        if len(parts) > 3:  # "lon,lat,alt, lon,lat,alt": which numbers go together?
            raise SiteFileError(f"{where}: coordinates {_short(tok)!r} run tuples together: "
                                "a tuple is lon,lat[,alt], tuples are separated by spaces")
        try:
            lon, lat = float(parts[0]), float(parts[1])
        except ValueError:
            raise SiteFileError(f"{where}: coordinates {tok!r} are not numbers") from None
        out.append(_latlon(lat, lon, where))
    return out


def _short(text: str, n: int = 60) -> str:
    return text if len(text) <= n else text[:n] + "..."


def _kml_extended(pm: ET.Element) -> dict[str, str]:
    data: dict[str, str] = {}
    for ext in _children(pm, "ExtendedData"):
        for d in _descendants(ext, "Data"):
            vals = _children(d, "value")
            if d.get("name") and vals:
                data[d.get("name", "")] = (vals[0].text or "").strip()
        for d in _descendants(ext, "SimpleData"):
            if d.get("name"):
                data[d.get("name", "")] = (d.text or "").strip()
    return data


def _xml_text(data: bytes, source: str) -> str:
    """An XML document's text: UTF-16 or UTF-8 by its byte order mark, else the encoding
    its declaration names (ISO-8859-1, windows-1252...), else UTF-8."""
    if data.startswith((b"\xff\xfe", b"\xfe\xff")):
        codec = "utf-16"
    elif data.startswith(b"\xef\xbb\xbf"):
        codec = "utf-8-sig"
    else:
        m = _XML_ENCODING.match(data.lstrip()[:200])
        codec = m.group(1).decode("ascii") if m else "utf-8"
    try:
        return data.decode(codec)
    except LookupError:
        raise SiteFileError(f"{source}: unknown encoding {codec!r}") from None
    except UnicodeDecodeError as exc:
        raise SiteFileError(f"{source}: not {codec} text: {exc.reason} at byte "
                            f"{exc.start}") from None


def _parse_kml(data: bytes, source: str, skipped: list[str]) -> list[GeoShape]:
    """The shapes of a KML document given as bytes (:func:`_xml_text` decodes it); what
    is no shape but would be one as a keep-out (a path, a Point with a ``top_m`` and no
    ``radius_m``) is appended to ``skipped``."""
    text = _xml_text(data, source)
    if _DOCTYPE.search(text):
        raise SiteFileError(f"{source}: a document type declaration (DOCTYPE/ENTITY) is not "
                            "accepted in a KML file")
    try:
        root = ET.fromstring(text)
    except ET.ParseError as exc:
        raise SiteFileError(f"{source}: not well-formed XML: {exc}") from None
    if _local(root.tag) != "kml":
        raise SiteFileError(f"{source}: the root element is <{_local(root.tag)}>, not <kml>")
    shapes: list[GeoShape] = []
    n_vertices = 0
    for k, pm in enumerate(_descendants(root, "Placemark")):
        names = _children(pm, "name")
        name = (names[0].text or "").strip() if names else f"placemark {k + 1}"
        where = f"{source}: placemark {name!r}"
        ext = _kml_extended(pm)
        top = _height(ext["top_m"], "top_m", where) if ext.get("top_m") else None
        role = ext.get(ROLE_KEY, "")  # what osa plan's own KML says a placemark is
        polys = _descendants(pm, "Polygon")
        n_rings = sum(len(_descendants(poly, "LinearRing")) for poly in polys)
        # a path (Google Earth's Add Path: power lines, fences) is drawn as an obstacle,
        # on the ground or in the air; osa plan's mission path says it is a flight
        if role != "mission" and (_descendants(pm, "LineString")
                                  or len(_descendants(pm, "LinearRing")) > n_rings):
            skipped.append(f"{where}: a path (LineString or LinearRing) is not a keep-out: "
                           "draw the corridor to avoid as a Polygon")
        for poly in polys:
            if _descendants(poly, "innerBoundaryIs"):
                raise SiteFileError(f"{where}: {_HOLES}")
            rings = [r for ob in _descendants(poly, "outerBoundaryIs")
                     for r in _descendants(ob, "coordinates")]
            if len(rings) != 1:
                raise SiteFileError(f"{where}: a Polygon needs one outerBoundaryIs ring")
            verts = _kml_coords(rings[0].text, where)
            n_vertices += len(verts)
            shapes.append(GeoShape(vertices_deg=_ring(verts, where), top_m=top, name=name,
                                   inclusion=role == "search area"))
        for pt in _descendants(pm, "Point"):
            coords = _descendants(pt, "coordinates")
            if "radius_m" not in ext:  # a label, not a shape; with a top, a tower unsized
                if top is not None and not polys:
                    skipped.append(f"{where}: a Point with a top_m but no radius_m: give "
                                   "the radius_m of the circle to keep out")
                continue
            verts = _kml_coords(coords[0].text if coords else "", where)
            if len(verts) != 1:
                raise SiteFileError(f"{where}: a Point needs one lon,lat")
            shapes.append(GeoShape(center_deg=verts[0],
                                   radius_m=_height(ext["radius_m"], "radius_m", where, True),
                                   top_m=top, name=name))
        if n_vertices > MAX_VERTICES:
            raise SiteFileError(f"{source}: more than {MAX_VERTICES:,} vertices")
    return shapes


# ----------------------------------------------------------------------------- GeoJSON


def _reject_constant(name: str) -> float:
    raise ValueError(f"bare {name} is not JSON")


def _json(text: str, source: str) -> Any:
    try:
        return json.loads(text, parse_constant=_reject_constant)
    except json.JSONDecodeError as exc:
        raise SiteFileError(f"{source}: malformed JSON at line {exc.lineno} column "
                            f"{exc.colno}: {exc.msg}") from None
    except ValueError as exc:
        raise SiteFileError(f"{source}: {exc}") from None


# names of a GeoJSON ``crs`` member that mean RFC 7946's WGS84 longitude, latitude
_WGS84_NAMES = {"urn:ogc:def:crs:ogc:1.3:crs84", "urn:ogc:def:crs:ogc::crs84", "crs84",
                "ogc:crs84", "epsg:4326", "urn:ogc:def:crs:epsg::4326",
                "urn:ogc:def:crs:epsg:6.6:4326", "http://www.opengis.net/def/crs/ogc/1.3/crs84",
                "http://www.opengis.net/def/crs/epsg/0/4326"}


class _Positions:
    """A GeoJSON file's positions to (lat, lon): [lon, lat] (RFC 7946), or [x, y] in the
    CRS its top-level ``crs`` member names (GeoJSON 2008; GDAL and QGIS write one for a
    layer saved in a projected CRS, e.g. ``urn:ogc:def:crs:EPSG::32630``; or the 2008
    draft's ``{"type": "EPSG", "properties": {"code": 32630}}``). ``skipped``
    collects what is no shape but would be one as a keep-out (see :func:`_parse_kml`)."""

    def __init__(self, obj: dict, source: str, skipped: list[str]) -> None:
        self.skipped = skipped
        self.crs_name = ""
        self._to_lonlat = None
        crs = obj.get("crs")
        props = crs.get("properties") if isinstance(crs, dict) else None
        if not isinstance(props, dict):
            return
        if crs.get("type") == "name" and isinstance(props.get("name"), str):
            name = props["name"]
        elif (crs.get("type") == "EPSG" and isinstance(props.get("code"), int | str)
              and not isinstance(props.get("code"), bool)):  # the 2008 draft's form
            name = f"EPSG:{props['code']}"
        else:  # a link to a file, or nothing known: RFC 7946's longitude, latitude
            return
        if name.strip().lower() in _WGS84_NAMES:
            return
        from pyproj import CRS, Transformer
        from pyproj.exceptions import CRSError, ProjError

        try:
            self._to_lonlat = Transformer.from_crs(CRS.from_user_input(name), "EPSG:4326",
                                                   always_xy=True)
        except (CRSError, ProjError) as exc:
            raise SiteFileError(f"{source}: its crs {name!r} is not a CRS pyproj can convert "
                                f"to WGS84 ({str(exc).splitlines()[0]})") from None
        self.crs_name = name

    def latlon(self, p: list, where: str) -> LatLon:
        """(lat, lon) of a position's first two numbers."""
        if self._to_lonlat is None:
            return _latlon(p[1], p[0], where)
        for v in p[:2]:
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
                raise SiteFileError(f"{where}: coordinate {v!r} is not a finite number")
        lon, lat = self._to_lonlat.transform(float(p[0]), float(p[1]))
        if not (math.isfinite(lon) and math.isfinite(lat)):
            raise SiteFileError(f"{where}: ({p[0]}, {p[1]}) lies outside its crs "
                                f"{self.crs_name!r}")
        return _latlon(lat, lon, where)


def _geojson_ring(ring: Any, where: str, pos: _Positions) -> tuple[LatLon, ...]:
    if not isinstance(ring, list):
        raise SiteFileError(f"{where}: a ring is a list of [lon, lat] positions")
    if len(ring) > MAX_VERTICES:
        raise SiteFileError(f"{where}: more than {MAX_VERTICES:,} vertices")
    verts = []
    for p in ring:
        if not isinstance(p, list) or len(p) < 2:  # RFC 7946 3.1.1: two or more numbers
            raise SiteFileError(f"{where}: a position is [lon, lat] or [lon, lat, h]")
        verts.append(pos.latlon(p, where))
    return _ring(verts, where)


def _geojson_shapes(obj: Any, source: str, skipped: list[str]) -> list[GeoShape]:
    if not isinstance(obj, dict):
        raise SiteFileError(f"{source}: the top level is not a GeoJSON object")
    pos = _Positions(obj, source, skipped)
    kind = obj.get("type")
    if kind == "FeatureCollection":
        feats = obj.get("features")
        if not isinstance(feats, list):
            raise SiteFileError(f"{source}: a FeatureCollection needs a features list")
        out: list[GeoShape] = []
        for k, f in enumerate(feats):
            out += _geojson_feature(f, f"{source}: feature {k}", pos)
        return out
    if kind == "Feature":
        return _geojson_feature(obj, source, pos)
    if kind not in _GEOJSON_GEOMETRIES:  # not GeoJSON: say what it looks like
        if "geometryType" in obj or "spatialReference" in obj:
            what = "an Esri JSON (ArcGIS's 'Features To JSON'): export it as GeoJSON"
        elif kind == "Topology":
            what = "a TopoJSON: convert it to GeoJSON (mapshaper, QGIS)"
        else:
            what = "expected a FeatureCollection, a Feature or a geometry"
        raise SiteFileError(f"{source}: not GeoJSON (its top level's type is {kind!r}): "
                            f"{what}")
    return _geojson_geometry(obj, {}, source, "", pos)


_GEOJSON_GEOMETRIES = ("Point", "MultiPoint", "LineString", "MultiLineString", "Polygon",
                       "MultiPolygon", "GeometryCollection")


def _geojson_feature(f: Any, where: str, pos: _Positions) -> list[GeoShape]:
    if not isinstance(f, dict) or f.get("type") != "Feature":
        raise SiteFileError(f"{where}: not a GeoJSON Feature")
    props = f.get("properties") or {}
    if not isinstance(props, dict):
        raise SiteFileError(f"{where}: properties must be an object")
    name = str(props.get("name", ""))
    if "geometry" in f and f["geometry"] is None:
        return []  # an unlocated feature (RFC 7946 section 3.2) is no shape
    return _geojson_geometry(f.get("geometry"), props, where, name, pos)


def _geojson_geometry(g: Any, props: dict, where: str, name: str, pos: _Positions,
                      beside_polygon: bool = False) -> list[GeoShape]:
    if not isinstance(g, dict):
        raise SiteFileError(f"{where}: missing geometry")
    top = _height(props["top_m"], "top_m", where) if props.get("top_m") is not None else None
    kind, coords = g.get("type"), g.get("coordinates")
    if kind == "Polygon":
        polys = [coords]
    elif kind == "MultiPolygon":
        polys = coords if isinstance(coords, list) else [None]
    elif kind in ("Point", "MultiPoint"):
        if props.get("radius_m") is None:  # a label, not a shape; with a top, a tower unsized
            if top is not None and not beside_polygon:  # (not a polygon's label)
                pos.skipped.append(f"{where}: a Point with a top_m but no radius_m: give the "
                                   "radius_m of the circle to keep out")
            return []
        points = [coords] if kind == "Point" else coords
        if not isinstance(points, list):
            raise SiteFileError(f"{where}: a MultiPoint is a list of [lon, lat]")
        out = []
        for c in points:
            if not isinstance(c, list) or len(c) < 2:
                raise SiteFileError(f"{where}: a Point is [lon, lat]")
            out.append(GeoShape(center_deg=pos.latlon(c, where),
                                radius_m=_height(props["radius_m"], "radius_m", where, True),
                                top_m=top, name=name))
        return out
    elif kind == "GeometryCollection":
        out: list[GeoShape] = []
        subs = g.get("geometries") or []
        poly = any(isinstance(x, dict) and x.get("type") in ("Polygon", "MultiPolygon")
                   for x in subs)
        for sub in subs:
            out += _geojson_geometry(sub, props, where, name, pos, poly)
        return out
    else:  # lines and other geometries are not areas
        if kind in ("LineString", "MultiLineString"):
            pos.skipped.append(f"{where}: a path ({kind}) is not a keep-out: draw the "
                               "corridor to avoid as a Polygon")
        return []
    out = []
    for rings in polys:
        if not isinstance(rings, list) or not rings:
            raise SiteFileError(f"{where}: a Polygon needs its rings")
        if len(rings) > 1:
            raise SiteFileError(f"{where}: {_HOLES}")
        out.append(GeoShape(vertices_deg=_geojson_ring(rings[0], where, pos), top_m=top, name=name))
    return out


# ----------------------------------------------------------------------------- .plan


def _plan_vertices(verts: object, where: str) -> list[tuple[float, float]]:
    """The ``[[lat, lon], ...]`` vertices of a QGroundControl ``.plan`` polygon."""
    if not isinstance(verts, list) or len(verts) > MAX_VERTICES:
        raise SiteFileError(f"{where}: expected a polygon of [lat, lon] vertices")
    pts = []
    for v in verts:
        if not isinstance(v, list) or len(v) != 2:
            raise SiteFileError(f"{where}: a vertex is [lat, lon]")
        pts.append(_latlon(v[0], v[1], where))
    return pts


def _plan_shapes(obj: Any, source: str) -> list[GeoShape]:
    if not isinstance(obj, dict) or obj.get("fileType") != "Plan":
        raise SiteFileError(f"{source}: not a QGroundControl plan (fileType 'Plan')")
    fence = obj.get("geoFence", {})
    if not isinstance(fence, dict):
        raise SiteFileError(f"{source}: the plan's geoFence is not an object")
    out: list[GeoShape] = []
    mission = obj.get("mission")
    items = mission.get("items") if isinstance(mission, dict) else None
    for k, item in enumerate(items if isinstance(items, list) else []):
        if not (isinstance(item, dict) and item.get("type") == "ComplexItem"
                and item.get("complexItemType") == "survey"):
            continue
        where = f"{source}: mission.items[{k}] (Survey)"
        verts = item.get("polygon")
        pts = _plan_vertices(verts, where)
        out.append(GeoShape(vertices_deg=_ring(pts, where), survey=True, name=f"survey {k}"))
    for k, p in enumerate(fence.get("polygons") or []):
        where = f"{source}: geoFence.polygons[{k}]"
        verts = p.get("polygon") if isinstance(p, dict) else None
        pts = _plan_vertices(verts, where)
        out.append(GeoShape(vertices_deg=_ring(pts, where), inclusion=bool(p.get("inclusion")),
                            name=f"fence polygon {k}"))
    for k, c in enumerate(fence.get("circles") or []):
        where = f"{source}: geoFence.circles[{k}]"
        circ = c.get("circle") if isinstance(c, dict) else None
        center = circ.get("center") if isinstance(circ, dict) else None
        if not isinstance(center, list) or len(center) != 2:
            raise SiteFileError(f"{where}: expected circle.center [lat, lon] and radius")
        out.append(GeoShape(center_deg=_latlon(center[0], center[1], where),
                            radius_m=_height(circ.get("radius"), "radius", where, True),
                            inclusion=bool(c.get("inclusion")), name=f"fence circle {k}"))
    return out


# ----------------------------------------------------------------------------- API


def read_shapes(path: str | Path) -> list[GeoShape]:
    """Every polygon and circle of a KML, GeoJSON or ``.plan`` file, in file order."""
    return _read_shapes(path, [])


def _read_shapes(path: str | Path, skipped: list[str]) -> list[GeoShape]:
    """:func:`read_shapes`, appending to ``skipped`` what is no shape but would be one as
    a keep-out."""
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix not in AREA_SUFFIXES:
        raise SiteFileError(f"{p}: unknown site file type {suffix!r} (use .kml, .kmz, .geojson, "
                            ".json or .plan)")
    if suffix == ".kml":
        return _parse_kml(_read_bytes(p), str(p), skipped)
    if suffix == ".kmz":
        return _parse_kml(_kmz_kml(p), str(p), skipped)
    obj = _json(_read(p), str(p))
    if suffix == ".plan":
        return _plan_shapes(obj, str(p))
    return _geojson_shapes(obj, str(p), skipped)


def read_area(path: str | Path) -> tuple[LatLon, ...]:
    """The search area's polygon, (lat, lon) vertices: the one polygon of a KML or
    GeoJSON file; of a ``.plan``, the one inclusion polygon of its geoFence, or, when it
    has none, its one inclusion circle (as :data:`CIRCLE_VERTICES` vertices on it) or
    the polygon of its one Survey pattern."""
    shapes = read_shapes(path)
    if Path(path).suffix.lower() == ".plan":
        polys = [s for s in shapes if not s.is_circle and s.inclusion]
        what = "inclusion polygons in its geoFence"
        if not polys:
            polys = [_circle_polygon(s) if s.is_circle else s for s in shapes
                     if (s.is_circle and s.inclusion) or s.survey]
            what = ("inclusion polygons in its geoFence, and "
                    f"{len(polys)} inclusion circles and Survey polygons")
            if len(polys) != 1:
                raise SiteFileError(f"{path}: holds 0 {what}; a search area is exactly one")
    else:
        polys = [s for s in shapes if not s.is_circle]
        what = "polygons"
        if any(s.inclusion for s in polys):  # osa plan's KML: its marked search area
            polys = [s for s in polys if s.inclusion]
            what = f"polygons marked {ROLE_KEY} 'search area'"
    if len(polys) != 1:
        raise SiteFileError(f"{path}: holds {len(polys)} {what}; a search area is exactly one")
    return polys[0].vertices_deg


CIRCLE_VERTICES = 72  # a circle as an area: vertices on it, 0.1 % of its radius inside


def _circle_polygon(shape: GeoShape) -> GeoShape:
    """A circle as the polygon of :data:`CIRCLE_VERTICES` vertices on it (exact WGS84)."""
    import numpy as np

    from estimator.geodesy import ExactENU

    lat, lon = shape.center_deg  # type: ignore[misc]
    th = np.linspace(0.0, 2.0 * math.pi, CIRCLE_VERTICES, endpoint=False)
    r = float(shape.radius_m)  # type: ignore[arg-type]
    la, lo, _ = ExactENU(lat, lon, 0.0).to_geodetic(r * np.sin(th), r * np.cos(th),
                                                     np.zeros_like(th))
    verts = tuple((float(a), float(b)) for a, b in zip(la, lo, strict=True))
    return GeoShape(vertices_deg=verts, inclusion=True, name=shape.name)


def read_keepouts(path: str | Path) -> list[GeoShape]:
    """The keep-outs of a file: its polygons and circles (a ``.plan``: the exclusion
    ones), each with its ``top_m`` if the file gives one. At least one. A path on the
    ground (a KML ``LineString`` clamped to it, a bare ``LinearRing``, a
    GeoJSON ``LineString``) or a point with a ``top_m`` but no ``radius_m`` is refused:
    drawn in a keep-out file, it was meant as one, and keeping out of nothing there
    would be silent."""
    skipped: list[str] = []
    shapes = _read_shapes(path, skipped)
    if skipped:
        raise SiteFileError(skipped[0])
    n_incl = sum(s.inclusion for s in shapes)
    shapes = [s for s in shapes if not (s.inclusion or s.survey)]  # areas, not keep-outs
    if Path(path).suffix.lower() == ".plan" and not shapes:
        raise SiteFileError(f"{path}: its geoFence holds no exclusion polygon or circle "
                            f"({n_incl} inclusion shape{'s' * (n_incl != 1)}: a .plan's "
                            "keep-outs are its exclusion fences)")
    if not shapes:
        raise SiteFileError(f"{path}: holds no keep-out (a polygon, or a point with a radius_m)")
    return shapes
