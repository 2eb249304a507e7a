"""Site files as Google Earth, QGIS and hand editing leave them (sim/sitefiles.py):
KMZ zips, encodings, nesting, coordinates written loosely, unlocated GeoJSON features,
clockwise and unclosed rings, QGroundControl plans with every kind of fence. Each read
to the same vertices as the plain file, or refused in one line naming the file."""

from __future__ import annotations

import json
import zipfile

import numpy as np
import pytest

from sim.sitefiles import SiteFileError, read_area, read_keepouts

# (lon, lat) of a hexagon near the site-valley preset, open ring
RING = [(-4.4896584, 36.7080101), (-4.4821132, 36.7131071), (-4.4835854, 36.7156415),
        (-4.4868831, 36.7160018), (-4.4921991, 36.7124106), (-4.4923922, 36.7106333)]
WANT = tuple((la, lo) for lo, la in RING)
KML_NS = 'xmlns="http://www.opengis.net/kml/2.2" xmlns:gx="http://www.google.com/kml/ext/2.2"'


def _coords(ring, sep=" ", alt=True, close=True):
    pts = [*ring, ring[0]] if close else list(ring)
    return sep.join(f"{lo},{la}" + (",0" if alt else "") for lo, la in pts)


def _kml(body: str, decl: str = '<?xml version="1.0" encoding="UTF-8"?>') -> str:
    return f"{decl}\n<kml {KML_NS}>{body}</kml>\n"


def _polygon(coords: str, extra: str = "") -> str:
    return (f"<Polygon>{extra}<outerBoundaryIs><LinearRing><coordinates>{coords}"
            "</coordinates></LinearRing></outerBoundaryIs></Polygon>")


NAMED = "<name><![CDATA[Área de búsqueda <b>1</b>]]></name>"
GOOGLE_EARTH = _kml(
    "<Document><name>search.kmz</name><Style id=\"a\"><PolyStyle><color>7f00ff00</color>"
    "</PolyStyle></Style><Folder><name>site</name><Folder><Placemark><name>start</name>"
    "<Point><coordinates>-4.487,36.712,0</coordinates></Point></Placemark>"
    "<Placemark><LineString><coordinates>-4.487,36.712 -4.486,36.713</coordinates>"
    f"</LineString></Placemark><Placemark>{NAMED}<styleUrl>#a</styleUrl><MultiGeometry>"
    + _polygon("\n\t\t" + _coords(RING, sep="\n\t\t") + "\n\t",
               "<extrude>1</extrude><gx:altitudeMode>relativeToSeaFloor</gx:altitudeMode>")
    + "</MultiGeometry></Placemark></Folder></Folder></Document>")


@pytest.mark.parametrize("variant", [
    "google-earth", "kmz", "kmz-nested", "clockwise-unclosed-2d", "spaces-after-commas",
    "latin-1", "utf-16", "no-namespace"])
def test_kml_variants_read_the_same_polygon(tmp_path, variant):
    if variant == "google-earth":  # folders, styles, a label, a path, MultiGeometry, gx
        f = tmp_path / "area.kml"
        f.write_text(GOOGLE_EARTH, encoding="utf-8")
    elif variant in ("kmz", "kmz-nested"):  # Google Earth's "Save Place As" default
        f = tmp_path / "area.kmz"
        with zipfile.ZipFile(f, "w", zipfile.ZIP_DEFLATED) as z:
            if variant == "kmz":
                z.writestr("doc.kml", GOOGLE_EARTH)
            else:
                z.writestr("files/readme.txt", "overlay")
                z.writestr("site/area.kml", GOOGLE_EARTH)
    elif variant == "clockwise-unclosed-2d":
        f = tmp_path / "cw.kml"
        f.write_text(_kml(f"<Placemark>{_polygon(_coords(RING[::-1], alt=False, close=False))}"
                          "</Placemark>"))
        assert read_area(f) == WANT[::-1]
        return
    elif variant == "spaces-after-commas":  # "lon, lat, alt": not KML, but hand-written
        f = tmp_path / "loose.kml"
        f.write_text(_kml("<Placemark>" + _polygon(
            "  " + "   ".join(f"{lo}, {la} ,0" for lo, la in [*RING, RING[0]]) + " ")
            + "</Placemark>"))
    elif variant == "latin-1":  # an encoding declared and used (an older QGIS export)
        f = tmp_path / "latin.kml"
        f.write_bytes(_kml(f"<Placemark>{NAMED}{_polygon(_coords(RING))}</Placemark>",
                           '<?xml version="1.0" encoding="ISO-8859-1"?>').encode("latin-1"))
    elif variant == "utf-16":  # Windows tools, with a byte order mark
        f = tmp_path / "wide.kml"
        f.write_bytes(_kml(f"<Placemark>{NAMED}{_polygon(_coords(RING))}</Placemark>",
                           '<?xml version="1.0" encoding="UTF-16"?>').encode("utf-16"))
    else:
        f = tmp_path / "bare.kml"
        f.write_text(f"<kml><Placemark>{_polygon(_coords(RING))}</Placemark></kml>")
    assert read_area(f) == WANT


def test_kml_and_kmz_refusals_are_one_line(tmp_path):
    holed = tmp_path / "holed.kml"
    holed.write_text(_kml("<Placemark><Polygon><outerBoundaryIs><LinearRing><coordinates>"
                          + _coords(RING) + "</coordinates></LinearRing></outerBoundaryIs>"
                          "<innerBoundaryIs><LinearRing><coordinates>-4.488,36.7115 "
                          "-4.4865,36.7115 -4.4865,36.7125 -4.488,36.7115</coordinates>"
                          "</LinearRing></innerBoundaryIs></Polygon></Placemark>"))
    # a keep-out with a hole was told to "draw the hole as a keep-out": the hole is where
    # it may be entered; the advice now says what to do for an area and for a keep-out
    cases = [(holed, r"holed.kml: placemark .*polygons with holes are not supported \(an "
                     r"area's hole: draw it as a keep-out if it must not be flown; a keep-out "
                     r"with a hole: draw it as polygons without holes\)$")]
    empty = tmp_path / "empty.kmz"
    with zipfile.ZipFile(empty, "w") as z:
        z.writestr("image.png", b"\x89PNG")
    cases.append((empty, r"empty.kmz: a KMZ without a .kml document"))
    notzip = tmp_path / "plain.kmz"
    notzip.write_text(GOOGLE_EARTH)
    cases.append((notzip, r"plain.kmz: not a readable KMZ \(zip\) file"))
    bomb = tmp_path / "bomb.kmz"  # 30 MB of blanks in a few kB: bounded, not inflated
    with zipfile.ZipFile(bomb, "w", zipfile.ZIP_DEFLATED) as z:
        z.writestr("doc.kml", " " * 30_000_000)
    cases.append((bomb, r"bomb.kmz: its KML holds more than the 20,000,000 bytes"))
    wrong = tmp_path / "wrong.kml"
    wrong.write_bytes(_kml(f"<Placemark>{NAMED}{_polygon(_coords(RING))}</Placemark>")
                      .encode("latin-1"))  # declared UTF-8, written in Latin-1
    cases.append((wrong, r"wrong.kml: not UTF-8 text: invalid start byte at byte \d+$"))
    for path, message in cases:
        with pytest.raises(SiteFileError, match=message) as exc:
            read_area(path)
        assert "\n" not in str(exc.value)


def test_geojson_variants(tmp_path):
    closed = [[lo, la] for lo, la in [*RING, RING[0]]]
    variants = {
        "fc-with-unlocated-and-label": {"type": "FeatureCollection", "features": [
            {"type": "Feature", "properties": {"name": "note"}, "geometry": None},
            {"type": "Feature", "properties": {"name": "start"},
             "geometry": {"type": "Point", "coordinates": [-4.487, 36.712]}},
            {"type": "Feature", "properties": None, "bbox": [-4.5, 36.7, -4.48, 36.72],
             "geometry": {"type": "MultiPolygon", "coordinates": [[closed]]}}]},
        "3d-unclosed-crs84": {"type": "Feature", "crs": {"type": "name", "properties": {
            "name": "urn:ogc:def:crs:OGC:1.3:CRS84"}}, "properties": {},
            "geometry": {"type": "Polygon", "coordinates": [[[*p, 12.5] for p in closed[:-1]]]}},
    }
    for name, obj in variants.items():
        f = tmp_path / f"{name}.geojson"
        f.write_text(json.dumps(obj))
        assert read_area(f) == WANT, name


def test_qgc_plan_with_every_fence_kind_and_rally_points(tmp_path):
    hole = [[36.7115, -4.488], [36.7115, -4.4865], [36.7125, -4.4865], [36.7125, -4.488]]
    plan = {"fileType": "Plan", "version": 1, "groundStation": "QGroundControl",
            "mission": {"version": 2, "firmwareType": 12, "vehicleType": 2, "items": [],
                        "plannedHomePosition": [36.711, -4.487, 100]},
            "geoFence": {"version": 2, "polygons": [
                {"inclusion": True, "polygon": [[la, lo] for lo, la in RING], "version": 1},
                {"inclusion": False, "polygon": hole, "version": 1}],
                "circles": [{"circle": {"center": [36.7125, -4.486], "radius": 30},
                             "inclusion": False, "version": 1}]},
            "rallyPoints": {"version": 2, "points": [[36.711, -4.487, 50]]}}
    f = tmp_path / "site.plan"
    f.write_text(json.dumps(plan, indent=4))
    assert read_area(f) == WANT
    kos = read_keepouts(f)
    assert [k.is_circle for k in kos] == [False, True]
    assert kos[0].vertices_deg == tuple(tuple(v) for v in hole)
    assert kos[1].center_deg == (36.7125, -4.486) and kos[1].radius_m == 30
    # the same plan with its inclusion fence only, given as a keep-out file: was "holds no
    # keep-out (a polygon, or a point with a radius_m)", though it holds a polygon
    plan["geoFence"]["polygons"], plan["geoFence"]["circles"] = plan["geoFence"]["polygons"][:1], []
    f.write_text(json.dumps(plan, indent=4))
    with pytest.raises(SiteFileError, match=r"site.plan: its geoFence holds no exclusion "
                                            r"polygon or circle \(1 inclusion shape: a .plan's "
                                            r"keep-outs are its exclusion fences\)$"):
        read_keepouts(f)


def test_a_bow_tie_area_or_keep_out_is_refused_where_it_is_read(tmp_path, capsys):
    """Vertices out of order (a hand-written file with two swapped): refused with the
    crossing edges, by the scenario loader and by osa plan, never planned over."""
    from sim.scenario import ScenarioError, load_scenario
    from tests.cli import one_line, status_of

    bow = [RING[0], RING[2], RING[1], *RING[3:]]
    f = tmp_path / "bow.kml"
    f.write_text(_kml(f"<Placemark>{_polygon(_coords(bow))}</Placemark>"))
    toml = tmp_path / "bow.toml"
    toml.write_text('name = "bow"\n[world.origin]\nlat_deg = 36.712\nlon_deg = -4.4875\n'
                    'h_m = 150.0\n[search]\narea_file = "bow.kml"\nstart_e_m = 0.0\n'
                    'start_n_m = 0.0\nrandom_responders = 1\n')
    with pytest.raises(ScenarioError, match=r"the search area: its edges 1 and 3 cross at"):
        load_scenario(toml)
    ok = tmp_path / "ok.kml"
    ok.write_text(_kml(f"<Placemark>{_polygon(_coords(RING))}</Placemark>"))
    code = status_of(["plan", "lawnmower", "--area", str(ok), "--keepout", str(f),
                      "-o", str(tmp_path / "m.plan")])
    assert code == 2
    assert one_line(capsys).startswith("osa plan: --keepout: placemark 1: the keep-out polygon: "
                                    "its edges 1 and 3 cross at")


def test_geojson_saved_by_qgis_in_a_projected_crs(tmp_path):
    """QGIS / GDAL "Save Features As" GeoJSON in the layer's CRS (UTM, Web Mercator) write
    [x, y] metres under a GeoJSON 2008 ``crs`` member: read in that CRS (was refused as
    "(4063515.79..., 366946.64...) is not a latitude/longitude"). A CRS pyproj does not
    know is refused in one line naming the file; a link is left as lon, lat."""
    from pyproj import Transformer

    def qgis(crs_name, xy, props=None, kind="MultiPolygon"):
        coords = [[[list(p) for p in [*xy, xy[0]]]]] if kind == "MultiPolygon" else list(xy[0])
        return {"type": "FeatureCollection", "name": "area",
                "crs": {"type": "name", "properties": {"name": crs_name}},
                "features": [{"type": "Feature", "properties": {"fid": 1, **(props or {})},
                              "geometry": {"type": kind, "coordinates": coords}}]}

    for code, name in (("EPSG:32630", "urn:ogc:def:crs:EPSG::32630"),
                       ("EPSG:3857", "urn:ogc:def:crs:EPSG::3857")):
        to = Transformer.from_crs("EPSG:4326", code, always_xy=True)
        xy = [to.transform(lo, la) for lo, la in RING]
        f = tmp_path / f"{code[5:]}.geojson"
        f.write_text(json.dumps(qgis(name, xy), indent=1))
        got = read_area(f)
        assert len(got) == len(WANT)
        assert max(abs(a - b) for g, w in zip(got, WANT, strict=True)
                   for a, b in zip(g, w, strict=True)) < 1e-9
        tower = tmp_path / f"tower{code[5:]}.geojson"
        tower.write_text(json.dumps(qgis(name, [to.transform(-4.486, 36.7125)],
                                         {"radius_m": 15, "top_m": 40}, kind="Point")))
        (ko,) = read_keepouts(tower)
        assert ko.center_deg == pytest.approx((36.7125, -4.486), abs=1e-9)
        assert (ko.radius_m, ko.top_m) == (15, 40)
    old = tmp_path / "geoserver.geojson"  # the 2008 draft's {"type": "EPSG"} form
    old.write_text(json.dumps({**qgis("", xy), "crs": {"type": "EPSG",
                                                      "properties": {"code": 3857}}}))
    assert max(abs(a - b) for g, w in zip(read_area(old), WANT, strict=True)
               for a, b in zip(g, w, strict=True)) < 1e-9
    for crs in (qgis("urn:ogc:def:crs:EPSG::4326", RING)["crs"],  # WGS84 itself, or a
                {"type": "link", "properties": {"href": "x.prj"}}):  # link: lon, lat
        wgs = tmp_path / "wgs.geojson"
        wgs.write_text(json.dumps({**qgis("", RING), "crs": crs}))
        assert read_area(wgs) == WANT
    bad = tmp_path / "bad.geojson"
    bad.write_text(json.dumps(qgis("EPSG:999999", RING)))
    with pytest.raises(SiteFileError, match=r"bad.geojson: its crs 'EPSG:999999' is not a "
                                            r"CRS pyproj can convert to WGS84") as exc:
        read_area(bad)
    assert "\n" not in str(exc.value)


def test_a_path_or_an_unsized_tower_in_a_keep_out_file_is_refused_not_dropped(tmp_path, capsys):
    """A power line drawn as Google Earth draws it: towers (Points with radius_m and
    top_m) and the wires as a path (Add Path: a LineString). The path was silently
    dropped (5 keep-outs read, the wires none) and so was a tower whose radius_m a QGIS
    export left null; now each is refused in one line naming the file and placemark /
    feature. In an area file a path stays a note; a MultiPoint of towers is circles."""
    from tests.cli import one_line, status_of

    def tower(k, lon, lat, radius=True):
        data = ('<Data name="radius_m"><value>15</value></Data>' if radius else "")
        return (f"<Placemark><name>tower {k}</name><ExtendedData>{data}<Data name=\"top_m\">"
                f"<value>40</value></Data></ExtendedData><Point><coordinates>{lon},{lat},0"
                "</coordinates></Point></Placemark>")

    towers = [(-4.4847178, 36.7070543), (-4.4865162, 36.7087801), (-4.4883147, 36.7105060)]
    wires = ("<Placemark><name>wires</name><styleUrl>#line</styleUrl><LineString>"
             "<tessellate>1</tessellate><coordinates>\n\t\t\t"
             + " ".join(f"{lo},{la},0" for lo, la in towers) + "\n\t\t</coordinates>"
             "</LineString></Placemark>")
    body = "".join(tower(k, lo, la) for k, (lo, la) in enumerate(towers, 1))
    drawn = tmp_path / "line.kml"
    drawn.write_text(_kml(f"<Document><Folder><name>line</name>{body}{wires}</Folder></Document>"))
    with pytest.raises(SiteFileError, match=r"line.kml: placemark 'wires': a path \(LineString "
                                            r"or LinearRing\) is not a keep-out: draw the "
                                            r"corridor to avoid as a Polygon$"):
        read_keepouts(drawn)
    ok = tmp_path / "ok.kml"
    ok.write_text(_kml(f"<Placemark>{_polygon(_coords(RING))}</Placemark>"))
    code = status_of(["plan", "lawnmower", "--area", str(ok), "--keepout", str(drawn),
                      "-o", str(tmp_path / "m.plan")])
    assert code == 2 and "placemark 'wires': a path" in one_line(capsys)
    assert not (tmp_path / "m.plan").exists()
    unsized = tmp_path / "unsized.kml"
    unsized.write_text(_kml(f"<Document>{body}{tower(4, -4.4901132, 36.7122317, False)}"
                            "</Document>"))
    with pytest.raises(SiteFileError, match=r"unsized.kml: placemark 'tower 4': a Point with a "
                                            r"top_m but no radius_m"):
        read_keepouts(unsized)
    assert [s.radius_m for s in read_keepouts(tmp_path / "ok.kml")] == [None]
    # a path drawn in the air (wires at 25 m above the ground, or at absolute heights) is
    # an obstacle too; only osa plan's own mission path, marked osa_role, is a flight
    for mode, role, refused in (("relativeToGround", "", True), ("absolute", "", True),
                                ("absolute", "mission", False)):
        ext = (f'<ExtendedData><Data name="osa_role"><value>{role}</value></Data>'
               "</ExtendedData>" if role else "")
        flown = tmp_path / "flown.kml"
        flown.write_text(_kml(f"<Document>{body}<Placemark><name>flight</name>{ext}"
                              f"<LineString><altitudeMode>{mode}</altitudeMode><coordinates>"
                              "-4.487,36.712,25 -4.486,36.713,25</coordinates></LineString>"
                              "</Placemark></Document>"))
        if refused:
            with pytest.raises(SiteFileError, match=r"placemark 'flight': a path"):
                read_keepouts(flown)
        else:
            assert [(s.name, s.top_m) for s in read_keepouts(flown)] == [
                (f"tower {k}", 40.0) for k in (1, 2, 3)]
    # the same towers as a QGIS GeoJSON layer: one with radius_m null, then a MultiPoint
    feats = [{"type": "Feature", "properties": {"name": f"t{k}", "top_m": 40, "radius_m": 15},
              "geometry": {"type": "Point", "coordinates": [lo, la]}}
             for k, (lo, la) in enumerate(towers)]
    feats[2]["properties"]["radius_m"] = None
    gj = tmp_path / "towers.geojson"
    gj.write_text(json.dumps({"type": "FeatureCollection", "features": feats}))
    with pytest.raises(SiteFileError, match=r"towers.geojson: feature 2: a Point with a top_m "
                                            r"but no radius_m"):
        read_keepouts(gj)
    feats[2] = {"type": "Feature", "properties": {"top_m": 25},
                "geometry": {"type": "LineString", "coordinates": [list(p) for p in towers]}}
    gj.write_text(json.dumps({"type": "FeatureCollection", "features": feats}))
    with pytest.raises(SiteFileError, match=r"towers.geojson: feature 2: a path \(LineString\) "
                                            r"is not a keep-out"):
        read_keepouts(gj)
    # a polygon with its label point (a GeometryCollection) and a top: the polygon's top
    labelled = tmp_path / "labelled.geojson"
    labelled.write_text(json.dumps({"type": "Feature", "properties": {"top_m": 25},
                                    "geometry": {"type": "GeometryCollection", "geometries": [
                                        {"type": "Point", "coordinates": list(towers[0])},
                                        {"type": "Polygon", "coordinates": [
                                            [list(p) for p in [*RING, RING[0]]]]}]}}))
    assert [(len(s.vertices_deg), s.top_m) for s in read_keepouts(labelled)] == [(6, 25.0)]
    multi = tmp_path / "multi.geojson"
    multi.write_text(json.dumps({"type": "Feature", "properties": {"top_m": 40, "radius_m": 15},
                                 "geometry": {"type": "MultiPoint",
                                              "coordinates": [list(p) for p in towers]}}))
    got = read_keepouts(multi)
    assert [(s.center_deg, s.radius_m, s.top_m) for s in got] == [
        ((la, lo), 15.0, 40.0) for lo, la in towers]
    # an area file keeps its paths and labels as notes (as Google Earth's folders hold them)
    area = tmp_path / "area.kml"
    area.write_text(_kml(f"<Document>{wires}{tower(9, -4.4865, 36.712, False)}<Placemark>"
                         f"{_polygon(_coords(RING))}</Placemark></Document>"))
    assert read_area(area) == WANT


def test_geojson_positions_with_a_measure_or_a_time(tmp_path):
    """RFC 7946 3.1.1: a position has two or more numbers; elements after the third (a
    measure, a timestamp, as some trackers and mapping sites export) may be ignored. A
    [lon, lat, h, t] area was refused ("a position is [lon, lat] or [lon, lat, h]"); now
    it reads to the same vertices, and a tower Point [lon, lat, h, t] to its circle."""
    ring = [[lo, la, 112.0, 1_700_000_000 + k] for k, (lo, la) in enumerate([*RING, RING[0]])]
    f = tmp_path / "track.geojson"
    f.write_text(json.dumps({"type": "FeatureCollection", "features": [
        {"type": "Feature", "properties": {"title": "Area A"},
         "geometry": {"type": "Polygon", "coordinates": [ring]}}]}))
    assert read_area(f) == WANT
    t = tmp_path / "tower.geojson"
    t.write_text(json.dumps({"type": "Feature", "properties": {"radius_m": 15, "top_m": 40},
                             "geometry": {"type": "Point",
                                          "coordinates": [-4.486, 36.7125, 150.0, 0.0]}}))
    (ko,) = read_keepouts(t)
    assert (ko.center_deg, ko.radius_m, ko.top_m) == ((36.7125, -4.486), 15.0, 40.0)
    short = tmp_path / "short.geojson"  # one number is no position
    short.write_text(json.dumps({"type": "Feature", "properties": {}, "geometry": {
        "type": "Polygon", "coordinates": [[[-4.48], [-4.47, 36.71], [-4.46, 36.72]]]}}))
    with pytest.raises(SiteFileError, match=r"short.geojson: a position is \[lon, lat\]"):
        read_area(short)


def test_a_kml_tuple_run_into_the_next_is_refused_not_merged(tmp_path):
    """A hand-edited ring with one "lon,lat,alt, lon,lat,alt" (a comma and a space between
    two tuples): the space was closed up with the comma, the two tuples became one
    token, and its second vertex was silently dropped (a hexagon read as a pentagon).
    Now refused in one line naming the file, the placemark and the tuples."""
    tuples = [f"{lo},{la},0" for lo, la in [*RING, RING[0]]]
    text = " ".join(tuples[:2]) + ", " + " ".join(tuples[2:])
    f = tmp_path / "edited.kml"
    f.write_text(_kml(f"<Placemark><name>zone B</name>{_polygon(text)}</Placemark>"))
    with pytest.raises(SiteFileError, match=r"edited.kml: placemark 'zone B': coordinates "
                                            r"'-4.4821132,36.7131071,0,-4.4835854,36.7156415,0' "
                                            r"run tuples together") as exc:
        read_area(f)
    assert "\n" not in str(exc.value)
    two_d = tmp_path / "pairs.kml"  # "lon,lat, lon,lat, ...": every tuple run together
    two_d.write_text(_kml("<Placemark>" + _polygon(", ".join(f"{lo},{la}" for lo, la in RING))
                          + "</Placemark>"))
    with pytest.raises(SiteFileError, match=r"pairs.kml: placemark 'placemark 1': "
                                            r"coordinates '.*\.\.\.' run tuples together"):
        read_area(two_d)


def test_json_site_files_in_utf16_as_windows_writes_them(tmp_path):
    """GeoJSON and .plan written by Windows PowerShell (``ConvertTo-Json | Out-File``:
    UTF-16 LE with a byte order mark) or Notepad's "Unicode": were refused as "cannot
    read: 'utf-8' codec can't decode byte 0xff in position 0"; now read by their byte
    order mark to the same shapes. A file in neither encoding is refused in one line."""
    obj = {"type": "Feature", "properties": {"name": "Zona de búsqueda"}, "geometry": {
        "type": "Polygon", "coordinates": [[[lo, la] for lo, la in [*RING, RING[0]]]]}}
    for codec in ("utf-16-le", "utf-16-be"):
        f = tmp_path / f"{codec}.geojson"
        bom = "\ufeff".encode(codec)
        f.write_bytes(bom + json.dumps(obj, indent=4, ensure_ascii=False).replace(
            "\n", "\r\n").encode(codec))
        assert read_area(f) == WANT, codec
    plan = {"fileType": "Plan", "version": 1, "geoFence": {"version": 2, "circles": [],
            "polygons": [{"inclusion": True, "polygon": [[la, lo] for lo, la in RING]}]}}
    fp = tmp_path / "fence.plan"
    fp.write_text(json.dumps(plan), encoding="utf-16")
    assert read_area(fp) == WANT
    bad = tmp_path / "latin.geojson"
    bad.write_bytes(json.dumps(obj, ensure_ascii=False).encode("latin-1"))
    with pytest.raises(SiteFileError, match=r"latin.geojson: not UTF-8 text: invalid start "
                                            r"byte at byte \d+$"):
        read_area(bad)


def test_json_that_is_not_geojson_is_named_not_read_as_empty(tmp_path):
    """An ArcGIS 'Features To JSON' export (Esri JSON: rings, spatialReference) or a
    TopoJSON saved as .json: read as holding nothing ("holds 0 polygons; a search area
    is exactly one", or "holds no keep-out" for a file full of polygons); now refused as
    not GeoJSON, saying what it looks like."""
    esri = {"displayFieldName": "name", "geometryType": "esriGeometryPolygon",
            "spatialReference": {"wkid": 4326, "latestWkid": 4326},
            "fields": [{"name": "top_m", "type": "esriFieldTypeDouble"}],
            "features": [{"attributes": {"top_m": 40},
                          "geometry": {"rings": [[list(p) for p in [*RING, RING[0]]]]}}]}
    topo = {"type": "Topology", "objects": {"area": {"type": "Polygon", "arcs": [[0]]}},
            "arcs": [[list(p) for p in [*RING, RING[0]]]]}
    for name, obj, hint in (("esri.json", esri, r"its top level's type is None\): an Esri "
                             r"JSON \(ArcGIS's 'Features To JSON'\): export it as GeoJSON"),
                            ("topo.json", topo, r"its top level's type is 'Topology'\): a "
                             r"TopoJSON: convert it to GeoJSON \(mapshaper, QGIS\)"),
                            ("other.json", {"type": "Area"}, r"its top level's type is "
                             r"'Area'\): expected a FeatureCollection, a Feature or a geometry")):
        f = tmp_path / name
        f.write_text(json.dumps(obj))
        for read in (read_area, read_keepouts):
            with pytest.raises(SiteFileError, match=rf"{name}: not GeoJSON \({hint}$"):
                read(f)


def test_a_qgc_plan_whose_area_is_a_survey_or_an_inclusion_circle(tmp_path, capsys):
    """QGroundControl users draw the area to search as a Survey pattern (a ComplexItem
    with its polygon) or fence it with a circle. Such a .plan as the area was refused:
    "holds 0 inclusion polygons in its geoFence". Now, when its geoFence holds no
    inclusion polygon, its one Survey polygon or its one inclusion circle (72 vertices
    on it) is the area; an inclusion polygon still comes first; two candidates are
    refused; a Survey is never a keep-out."""
    from estimator.geodesy import ExactENU
    from tests.cli import status_of

    survey = {"type": "ComplexItem", "complexItemType": "survey", "version": 5, "angle": 0,
              "entryLocation": 0, "flyAlternateTransects": False, "splitConcavePolygons": False,
              "polygon": [[la, lo] for lo, la in RING],
              "TransectStyleComplexItem": {"CameraCalc": {"DistanceToSurface": 50,
                                                          "version": 2},
                                           "Items": [], "VisualTransectPoints": [],
                                           "TurnAroundDistance": 10, "version": 2}}
    takeoff = {"type": "SimpleItem", "command": 22, "frame": 3, "autoContinue": True,
               "doJumpId": 1, "params": [0, 0, 0, None, 36.711, -4.487, 50]}

    def plan(items, polygons=(), circles=()):
        return {"fileType": "Plan", "version": 1, "groundStation": "QGroundControl",
                "mission": {"version": 2, "firmwareType": 12, "vehicleType": 2,
                            "plannedHomePosition": [36.711, -4.487, 100], "items": items},
                "geoFence": {"version": 2, "polygons": list(polygons),
                             "circles": list(circles)},
                "rallyPoints": {"version": 2, "points": []}}

    f = tmp_path / "survey.plan"
    f.write_text(json.dumps(plan([takeoff, survey]), indent=4))
    assert read_area(f) == WANT
    code = status_of(["plan", "lawnmower", "--area", str(f), "-o", str(tmp_path / "m.plan")])
    assert code == 0, capsys.readouterr().err
    ring = {"circle": {"center": [36.712, -4.487], "radius": 300.0}, "inclusion": True,
            "version": 1}
    c = tmp_path / "circle.plan"
    c.write_text(json.dumps(plan([takeoff], circles=[ring])))
    got = read_area(c)
    assert len(got) == 72
    e, n, _ = ExactENU(36.712, -4.487, 0.0).to_enu(*np.array(got).T, np.zeros(72))
    assert np.max(np.abs(np.hypot(e, n) - 300.0)) < 1e-3
    fence = {"inclusion": True, "polygon": [[la, lo] for lo, la in RING], "version": 1}
    both = tmp_path / "both.plan"
    both.write_text(json.dumps(plan([takeoff, {**survey, "polygon": [[36.0, -4.0],
                                                                     [36.0, -4.01],
                                                                     [36.01, -4.0]]}],
                                    polygons=[fence])))
    assert read_area(both) == WANT  # the fence first, as before
    two = tmp_path / "two.plan"
    two.write_text(json.dumps(plan([takeoff, survey], circles=[ring])))
    with pytest.raises(SiteFileError, match=r"two.plan: holds 0 inclusion polygons in its "
                                            r"geoFence, and 2 inclusion circles and Survey "
                                            r"polygons; a search area is exactly one$"):
        read_area(two)
    with pytest.raises(SiteFileError, match=r"survey.plan: its geoFence holds no exclusion"):
        read_keepouts(f)


def test_keep_outs_named_alike_as_google_earth_names_them(tmp_path):
    """Google Earth names every new polygon "Untitled Polygon" (a GIS layer may name
    every tower "pylon"): a keep-out file with two such placemarks was refused by the
    scenario, "the name 'keepout[0]/Untitled Polygon' is used twice". Now the repeats
    are numbered in file order; a unique name stays as it was."""
    from sim.scenario import load_scenario

    def square(lon, lat, d=0.0004):
        return _polygon(_coords([(lon, lat), (lon + d, lat), (lon + d, lat + d),
                                 (lon, lat + d)]))

    body = "".join(f"<Placemark><name>{nm}</name>{square(lo, la)}</Placemark>"
                   for nm, lo, la in (("Untitled Polygon", -4.4880, 36.7115),
                                      ("Untitled Polygon", -4.4860, 36.7125),
                                      ("mast", -4.4850, 36.7140)))
    (tmp_path / "obstacles.kml").write_text(_kml(f"<Document>{body}</Document>"))
    area = tmp_path / "area.kml"
    area.write_text(_kml(f"<Placemark>{_polygon(_coords(RING))}</Placemark>"))
    toml = tmp_path / "site.toml"
    toml.write_text('name = "site"\n[world.origin]\nlat_deg = 36.712\nlon_deg = -4.4875\n'
                    'h_m = 150.0\n[search]\narea_file = "area.kml"\nstart_e_m = -100.0\n'
                    'start_n_m = 0.0\nrandom_responders = 1\n[[search.keepout]]\n'
                    'name = "obstacles"\nfile = "obstacles.kml"\n')
    assert [k.name for k in load_scenario(toml).keepouts] == [
        "obstacles/Untitled Polygon 1", "obstacles/Untitled Polygon 2", "obstacles/mast"]
