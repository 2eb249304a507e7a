"""KML export of a mission for Google Earth: the path as flown, the area, the keep-outs.

One ``Document`` (KML 2.2) holding:

- ``mission``: a ``LineString`` through home and every positioned mission item, in
  order, with absolute altitudes (``altitudeMode absolute``: metres above the datum of
  the home's height, mean sea level for a DEM such as SRTM), or heights above the
  ground (``relativeToGround``) when only those are known (frame-11 items without a
  DEM); the autopilot flies straight between them, and so does Google Earth's line;
- ``home``: a ``Point``;
- ``search area``: a ``Polygon`` on the ground (when there is one);
- each keep-out: a ``Polygon`` (a circle as 64 vertices), extruded up to its ``top_m``
  above the ground when it has one (Google Earth draws the obstacle as a block), with
  ``top_m`` in its ``ExtendedData``.

Each placemark's ``ExtendedData`` gives its role (``osa_role``: ``mission``, ``home``,
``search area``, ``keep-out``), so the file reads back whole: as ``--area`` its search
area, as ``--keepout`` its keep-outs with their tops (``sim.sitefiles``).

Coordinates are ``lon,lat,alt`` with 7 decimals (about 1 cm) and altitudes in mm.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from xml.sax.saxutils import escape

from planner.geojson import circle_ring

LatLon = tuple[float, float]
ROLE_KEY = "osa_role"  # as sim.sitefiles.ROLE_KEY (planner does not import sim)


@dataclass(frozen=True, kw_only=True)
class KmlShape:
    """A polygon (``vertices_deg``) or circle (``center_deg``, ``radius_m``) in degrees,
    with its height above the ground (``top_m``, None: none known) and a name."""

    name: str
    vertices_deg: tuple[LatLon, ...] = ()
    center_deg: LatLon | None = None
    radius_m: float | None = None
    top_m: float | None = None
    flown_over: bool = False  # the path passes above it (styled apart)


_STYLES = """<Style id="path"><LineStyle><color>ff00d4ff</color><width>3</width></LineStyle></Style>
<Style id="area"><LineStyle><color>ffff8000</color><width>2</width></LineStyle><PolyStyle><color>20ff8000</color></PolyStyle></Style>
<Style id="keepout"><LineStyle><color>ff0000ff</color><width>2</width></LineStyle><PolyStyle><color>800000ff</color></PolyStyle></Style>
<Style id="flown-over"><LineStyle><color>ff00a5ff</color><width>2</width></LineStyle><PolyStyle><color>6000a5ff</color></PolyStyle></Style>"""  # noqa: E501


def _coord(lat: float, lon: float, alt: float | None = None) -> str:
    s = f"{lon:.7f},{lat:.7f}"
    return s if alt is None else f"{s},{alt:.3f}"


def _ring(shape: KmlShape) -> list[LatLon]:
    if shape.center_deg is not None:
        assert shape.radius_m is not None
        return [(la, lo) for lo, la in circle_ring(shape.center_deg[0], shape.center_deg[1],
                                                   shape.radius_m)]
    ring = list(shape.vertices_deg)
    return ring if ring[0] == ring[-1] else [*ring, ring[0]]


def _role(role: str, top_m: float | None = None) -> str:
    """The placemark's ExtendedData: its role (``sim.sitefiles`` reads the file back: the
    search area as the area, never a keep-out; the mission path as no obstacle) and top."""
    top = f'<Data name="top_m"><value>{top_m:g}</value></Data>' if top_m is not None else ""
    return (f'<ExtendedData><Data name="{ROLE_KEY}"><value>{role}</value></Data>{top}'
            "</ExtendedData>")


def _polygon(name: str, ring: Sequence[LatLon], style: str, top_m: float | None,
             role: str = "keep-out") -> str:
    ext = _role(role, top_m)
    if top_m is not None and top_m > 0:
        geom = ("<extrude>1</extrude><altitudeMode>relativeToGround</altitudeMode>",
                " ".join(_coord(la, lo, top_m) for la, lo in ring))
    else:
        geom = ("<tessellate>1</tessellate><altitudeMode>clampToGround</altitudeMode>",
                " ".join(_coord(la, lo) for la, lo in ring))
    return (f"<Placemark><name>{escape(name)}</name><styleUrl>#{style}</styleUrl>{ext}"
            f"<Polygon>{geom[0]}<outerBoundaryIs><LinearRing><coordinates>{geom[1]}"
            "</coordinates></LinearRing></outerBoundaryIs></Polygon></Placemark>")


def mission_kml(
    path_deg: Sequence[tuple[float, float, float]],
    *,
    home: tuple[float, float, float],
    above_ground: bool = False,
    area_deg: Sequence[LatLon] | None = None,
    keep_outs: Sequence[KmlShape] = (),
    name: str = "osa plan",
    description: str = "",
) -> str:
    """The KML text: ``path_deg`` (lat, lon, alt) from home through the items, altitudes
    absolute (or above the ground with ``above_ground``); see the module docstring."""
    if len(path_deg) < 2:
        raise ValueError("a mission path needs at least two points")
    mode = "relativeToGround" if above_ground else "absolute"
    coords = " ".join(_coord(la, lo, al) for la, lo, al in path_deg)
    parts = [
        '<?xml version="1.0" encoding="UTF-8"?>',
        '<kml xmlns="http://www.opengis.net/kml/2.2">',
        "<Document>",
        f"<name>{escape(name)}</name>",
        f"<description>{escape(description)}</description>" if description else "",
        _STYLES,
        f"<Placemark><name>mission</name><styleUrl>#path</styleUrl>{_role('mission')}"
        "<LineString>"
        f"<altitudeMode>{mode}</altitudeMode><coordinates>{coords}</coordinates>"
        "</LineString></Placemark>",
        f"<Placemark><name>home</name>{_role('home')}<Point><altitudeMode>{mode}</altitudeMode>"
        f"<coordinates>{_coord(*home)}</coordinates></Point></Placemark>",
    ]
    if area_deg is not None:
        ring = list(area_deg) if area_deg[0] == area_deg[-1] else [*area_deg, area_deg[0]]
        parts.append(_polygon("search area", ring, "area", None, role="search area"))
    for k in keep_outs:
        parts.append(_polygon(k.name, _ring(k), "flown-over" if k.flown_over else "keepout",
                              k.top_m))
    parts += ["</Document>", "</kml>", ""]
    return "\n".join(p for p in parts if p)


def write_kml(text: str, path: str | os.PathLike[str]) -> None:
    """Write the KML atomically (a temporary file renamed: no half file on failure)."""
    from pathlib import Path

    target = Path(path)
    tmp = target.with_name(f".{target.name}.tmp{os.getpid()}")
    try:
        tmp.write_text(text, encoding="utf-8")
        os.replace(tmp, target)
    except OSError:
        tmp.unlink(missing_ok=True)
        raise
