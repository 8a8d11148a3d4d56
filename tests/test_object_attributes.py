"""Object attributes (pipeline25d.formats.attributes and its readers): CityGML 2.0 and 3.0 generic and
thematic attributes (generated files and the PLATEAU building of tests/data/citygml) against the same
XML read by xml.etree XPath; CityGML and b3dm attributes through ingest to objects.csv, objects.gpkg (OGR)
and the viewer's shards; hostile attributes bounded with one warning naming the file. The 3D Tiles and
glTF readers' own tests: test_feature_attributes."""

from __future__ import annotations

import csv
import json
import warnings
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
from test_feature_attributes import b3dm

from pipeline25d.core.crs import horizontal_wkt
from pipeline25d.core.mesh import merged_info as info_of
from pipeline25d.formats.attributes import MAX_ATTRIBUTES, MAX_OBJECT_CHARS, MAX_TEXT, Limiter
from pipeline25d.formats.citygml import read_citygml
from pipeline25d.formats.tiles3d import read_b3dm
from pipeline25d.publish.objects import scene_objects, write_objects
from pipeline25d.stages.ingest import ingest

DATA = Path(__file__).parent / "data" / "citygml"
NS = {"gml": "http://www.opengis.net/gml", "gen": "http://www.opengis.net/citygml/generics/2.0",
      "bldg": "http://www.opengis.net/citygml/building/2.0", "core": "http://www.opengis.net/citygml/2.0"}
NS3 = {"gen": "http://www.opengis.net/citygml/generics/3.0", "core": "http://www.opengis.net/citygml/3.0",
       "con": "http://www.opengis.net/citygml/construction/3.0", "gml": "http://www.opengis.net/gml/3.2",
       "bldg": "http://www.opengis.net/citygml/building/3.0"}
KINDS2 = {"stringAttribute": str, "intAttribute": int, "doubleAttribute": float, "dateAttribute": str,
          "uriAttribute": str, "measureAttribute": float}


# ----------------------------------------------------------------------------- CityGML


def _box(x0: float, y0: float, size: float, z0: float, z1: float) -> str:
    """A lod2MultiSurface of a box's six faces (EPSG:25832)."""
    c = [(x0, y0), (x0 + size, y0), (x0 + size, y0 + size), (x0, y0 + size)]
    rings = [[(x, y, z0) for x, y in reversed(c)], [(x, y, z1) for x, y in c]]
    rings += [[(*c[i], z0), (*c[(i + 1) % 4], z0), (*c[(i + 1) % 4], z1), (*c[i], z1)] for i in range(4)]
    polys = "".join("<gml:surfaceMember><gml:Polygon><gml:exterior><gml:LinearRing><gml:posList>"
                    + " ".join(f"{x} {y} {z}" for x, y, z in [*r, r[0]])
                    + "</gml:posList></gml:LinearRing></gml:exterior></gml:Polygon></gml:surfaceMember>" for r in rings)
    return ('<bldg:lod2MultiSurface><gml:MultiSurface srsName="urn:ogc:def:crs:EPSG::25832" srsDimension="3">'
            f"{polys}</gml:MultiSurface></bldg:lod2MultiSurface>")


def citygml2(path: Path, extra: str = "") -> None:
    """Two buildings with generic and thematic attributes of every kind; the first has a BuildingPart."""
    gen = ('<gen:stringAttribute name="owner"><gen:value>Müller, K. &amp; "Söhne" &lt;GmbH&gt;</gen:value>'
           '</gen:stringAttribute><gen:intAttribute name="units"><gen:value>12</gen:value></gen:intAttribute>'
           '<gen:doubleAttribute name="area"><gen:value>415.25</gen:value></gen:doubleAttribute>'
           '<gen:dateAttribute name="surveyed"><gen:value>2021-03-04</gen:value></gen:dateAttribute>'
           '<gen:uriAttribute name="link"><gen:value>https://example.org/b?x=1,2</gen:value></gen:uriAttribute>'
           '<gen:measureAttribute name="eaves"><gen:value uom="m">9.75</gen:value></gen:measureAttribute>'
           '<gen:genericAttributeSet name="energy"><gen:stringAttribute name="label"><gen:value>B</gen:value>'
           '</gen:stringAttribute><gen:doubleAttribute name="kwh"><gen:value>88.5</gen:value></gen:doubleAttribute>'
           '</gen:genericAttributeSet>')
    part = ('<bldg:consistsOfBuildingPart><bldg:BuildingPart gml:id="b1-annex">'
            '<gen:intAttribute name="floor"><gen:value>2</gen:value></gen:intAttribute>'
            '<bldg:measuredHeight uom="m">4.5</bldg:measuredHeight>'
            f'{_box(691020.0, 5334000.0, 5.0, 520.0, 524.5)}</bldg:BuildingPart></bldg:consistsOfBuildingPart>')
    path.write_text(
        '<?xml version="1.0" encoding="UTF-8"?>\n'
        '<core:CityModel xmlns:core="http://www.opengis.net/citygml/2.0" '
        'xmlns:bldg="http://www.opengis.net/citygml/building/2.0" '
        'xmlns:gen="http://www.opengis.net/citygml/generics/2.0" xmlns:gml="http://www.opengis.net/gml">\n'
        '<core:cityObjectMember><bldg:Building gml:id="b1"><gml:name>Hall, east wing</gml:name>'
        f'{gen}<bldg:class>1000</bldg:class><bldg:function>1120</bldg:function><bldg:function>2070</bldg:function>'
        '<bldg:usage>1010</bldg:usage><bldg:yearOfConstruction>1961</bldg:yearOfConstruction>'
        '<bldg:measuredHeight uom="m">12.5</bldg:measuredHeight><bldg:storeysAboveGround>4</bldg:storeysAboveGround>'
        f'{extra}{_box(691000.0, 5334000.0, 20.0, 520.0, 532.5)}{part}</bldg:Building></core:cityObjectMember>\n'
        '<core:cityObjectMember><bldg:Building gml:id="b2"><gml:name>Shed</gml:name>'
        '<gen:stringAttribute name="owner"><gen:value>city</gen:value></gen:stringAttribute>'
        '<bldg:measuredHeight uom="ft">10</bldg:measuredHeight>'
        f'{_box(691040.0, 5334000.0, 6.0, 520.0, 523.0)}</bldg:Building></core:cityObjectMember>\n'
        '</core:CityModel>\n', encoding="utf-8")


def generic2(elem) -> dict:
    """The generic attributes of ``elem`` by XPath (CityGML 2.0), typed by their element."""
    out = {}
    for kind, cast in KINDS2.items():
        for a in elem.findall(f"gen:{kind}", NS):
            out[a.get("name")] = cast(a.find("gen:value", NS).text)
    for s in elem.findall("gen:genericAttributeSet", NS):
        out[s.get("name")] = generic2(s)
    return out


def expected2(elem) -> dict:
    """What the module docstring promises for a CityGML 2.0 building or part, read by XPath."""
    out = generic2(elem)
    if (name := elem.find("gml:name", NS)) is not None:
        out["name"] = name.text
    for tag in ("class", "usage", "function"):
        values = [e.text for e in elem.findall(f"bldg:{tag}", NS)]
        if values:
            out[tag] = values[0] if len(values) == 1 else values
    for tag, cast in (("yearOfConstruction", int), ("storeysAboveGround", int), ("measuredHeight", float)):
        if (e := elem.find(f"bldg:{tag}", NS)) is not None:
            out[tag] = cast(float(e.text))
            if e.get("uom") not in (None, "m"):
                out[f"{tag}_uom"] = e.get("uom")
    return out


def test_citygml2_generic_and_thematic_attributes_match_an_xpath_read(tmp_path):
    path = tmp_path / "city.gml"
    citygml2(path)
    info = info_of(read_citygml(path, {}).parts)
    root = ET.parse(path).getroot()
    buildings = {b.get(f"{{{NS['gml']}}}id"): b for b in root.iter(f"{{{NS['bldg']}}}Building")}
    assert set(info) == set(buildings) == {"b1", "b2"}
    for key, elem in buildings.items():
        expected = expected2(elem)
        parts = {p.get(f"{{{NS['gml']}}}id"): expected2(p) for p in elem.iter(f"{{{NS['bldg']}}}BuildingPart")}
        if parts:
            expected["parts"] = parts
        assert info[key] == {"type": "Building", "attributes": expected}, key
    b1 = info["b1"]["attributes"]
    assert b1["owner"] == 'Müller, K. & "Söhne" <GmbH>' and b1["function"] == ["1120", "2070"]
    assert b1["parts"] == {"b1-annex": {"floor": 2, "measuredHeight": 4.5}}
    assert info["b2"]["attributes"]["measuredHeight_uom"] == "ft"


def test_citygml_plateau_2_and_3_attributes_match_an_xpath_read():
    """The PLATEAU building: its gen:stringAttributes (2.0) and core:genericAttribute/gen:StringAttribute
    (3.0) as XPath reads them, and the measured height of 2.0's bldg:measuredHeight and 3.0's con:height."""
    two = info_of(read_citygml(DATA / "53394517_bldg_6697_2_op_CityGML2.gml", {}).parts)
    three = info_of(read_citygml(DATA / "53394517_bldg_6697_2_op_CityGML3_excerpt.gml", {}).parts)
    root2 = ET.parse(DATA / "53394517_bldg_6697_2_op_CityGML2.gml").getroot()
    root3 = ET.parse(DATA / "53394517_bldg_6697_2_op_CityGML3_excerpt.gml").getroot()
    (b2,) = root2.iter(f"{{{NS['bldg']}}}Building")
    (b3,) = root3.iter(f"{{{NS3['bldg']}}}Building")
    key = b2.get(f"{{{NS['gml']}}}id")
    gen3 = {a.find("gen:name", NS3).text: a.find("gen:value", NS3).text
            for a in b3.findall("core:genericAttribute/gen:StringAttribute", NS3)}
    height3 = float(b3.find("con:height/con:Height/con:value", NS3).text)
    assert len(gen3) == 3 and generic2(b2) == gen3
    a2, a3 = two[key]["attributes"], three[key]["attributes"]
    assert {k: a2[k] for k in gen3} == {k: a3[k] for k in gen3} == gen3
    assert a2["measuredHeight"] == float(b2.find("bldg:measuredHeight", NS).text) == a3["measuredHeight"] == height3
    assert a3["height"]["status"] == b3.find("con:height/con:Height/con:status", NS3).text


# ----------------------------------------------------------------------------- through ingest to the table


def test_attributes_reach_csv_gpkg_and_shards(tmp_path):
    from osgeo import ogr

    citygml2(tmp_path / "city.gml")
    (tmp_path / "tile.b3dm").write_bytes(b3dm(3, json.dumps({"use": ["a, b", "c", None]}).encode()))
    inputs = {"c": {"path": str(tmp_path / "city.gml")}, "t": {"path": str(tmp_path / "tile.b3dm")}}
    for slot, (district, spec) in enumerate(inputs.items(), 1):
        ingest(spec, district, "EPSG:25832", 100.0, 0.5, tmp_path / "chunks" / district / "index.json", slot=slot)
    rows = scene_objects(tmp_path / "chunks", list(inputs), {})
    write_objects(rows, tmp_path / "objects", horizontal_wkt("EPSG:25832"))
    root = ET.parse(tmp_path / "city.gml").getroot()
    b2 = next(b for b in root.iter(f"{{{NS['bldg']}}}Building") if b.get(f"{{{NS['gml']}}}id") == "b2")
    expected = {("c", "b2"): expected2(b2), ("t", "tile.b3dm#0"): {"use": "a, b"}, ("t", "tile.b3dm#2"): {}}
    by = {(r.district, r.name): r for r in rows}
    assert by[("c", "b1")].model_height == 12.5 and by[("c", "b1")].type == "Building"
    assert by[("c", "b2")].model_height == pytest.approx(3.0, abs=2e-3)   # 10 ft measured: the faces' height
    with open(tmp_path / "objects" / "objects.csv", newline="", encoding="utf-8") as fh:
        csv_rows = {(r["district"], r["name"]): json.loads(r["attributes"]) for r in csv.DictReader(fh)}
    ds = ogr.Open(str(tmp_path / "objects" / "objects.gpkg"))
    gpkg = {(f["district"], f["name"]): json.loads(f["attributes"]) for f in ds.GetLayer("objects")}
    index = json.loads((tmp_path / "objects" / "shards" / "index.json").read_text())
    shards = {}
    for slot in index:
        for shard in (tmp_path / "objects" / "shards" / slot).glob("*.json"):
            shards.update({(r["district"], r["name"]): r["attributes"] for r in json.loads(shard.read_text()).values()})
    for key, attrs in expected.items():
        assert csv_rows[key] == gpkg[key] == shards[key] == by[key].attributes == attrs, key


# ----------------------------------------------------------------------------- hostile attributes


def test_hostile_batch_table_is_bounded_with_one_warning_naming_the_file(tmp_path):
    deep: list = []
    for _ in range(60):
        deep = [deep]
    table = {f"a{k}": [k, k] for k in range(3000)}
    table = {"huge": ["x" * 1_000_000, "ok"], "deep": [deep, 1], "nan": [float("nan"), 1.5],
             "surrogate": ["\ud800 lone", "fine"], **table}
    raw = json.dumps(table).encode().replace(b'"fine"', b'"f\xffne"')             # not UTF-8
    path = tmp_path / "hostile.b3dm"
    path.write_bytes(b3dm(2, raw))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        info = info_of(read_b3dm(path, {}).parts)
    bounded = [str(w.message) for w in caught if "attributes bounded" in str(w.message)]
    assert len(bounded) == 1 and str(path) in bounded[0]
    for key in ("hostile.b3dm#0", "hostile.b3dm#1"):
        attrs = info[key]["attributes"]
        text = json.dumps(attrs, ensure_ascii=False, allow_nan=False)        # valid JSON, no NaN
        text.encode("utf-8")                                                 # no lone surrogates
        assert len(attrs) <= MAX_ATTRIBUTES and len(text) <= MAX_OBJECT_CHARS
        with warnings.catch_warnings(record=True) as again:                  # bounded once for good
            warnings.simplefilter("always")
            limiter = Limiter(path)
            assert limiter.attributes(attrs) == attrs
            limiter.warn()
        assert not again
    first, second = info["hostile.b3dm#0"]["attributes"], info["hostile.b3dm#1"]["attributes"]
    assert len(first["huge"]) == MAX_TEXT and first["nan"] is None and "\ufffd" in first["surrogate"]
    assert isinstance(first["deep"], (str, list)) and second["surrogate"] == "f\ufffdne" and second["nan"] == 1.5


def test_hostile_cityjson_attributes_are_bounded_in_the_table(tmp_path):
    """A CityJSON object whose key holds a lone surrogate and whose attributes hold NaN, a 100,000-item
    list and 2,000 attributes: the table is written (CSV, GeoPackage, shards: valid UTF-8, strict JSON)."""
    from osgeo import ogr

    attrs = {"nan": float("nan"), "list": list(range(100_000)), **{f"k{i}": i for i in range(2000)}}
    quad = [[0, 1, 2, 3]]
    doc = {"type": "CityJSON", "version": "2.0", "transform": {"scale": [1, 1, 1], "translate": [691000, 5334000, 520]},
           "metadata": {"referenceSystem": "https://www.opengis.net/def/crs/EPSG/0/25832"},
           "CityObjects": {"b\ud800x": {"type": "Building", "attributes": attrs, "geometry": [
               {"type": "MultiSurface", "lod": "1", "boundaries": [quad]}]}},
           "vertices": [[0, 0, 0], [10, 0, 0], [10, 10, 5], [0, 10, 5]]}
    path = tmp_path / "city.json"
    path.write_text(json.dumps(doc))
    ingest({"path": str(path)}, "d", "EPSG:25832", 100.0, 0.5, tmp_path / "chunks" / "d" / "index.json", slot=1)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        rows = scene_objects(tmp_path / "chunks", ["d"], {"d": str(path)})
    assert any(str(path) in str(w.message) and "bounded" in str(w.message) for w in caught)
    write_objects(rows, tmp_path / "objects", horizontal_wkt("EPSG:25832"))
    (row,) = rows
    assert row.name == "b\ufffdx" and row.attributes["nan"] is None and len(row.attributes["list"]) == 100
    assert len(row.attributes) == MAX_ATTRIBUTES
    text = (tmp_path / "objects" / "objects.csv").read_bytes().decode("utf-8")
    (got,) = [json.loads(r["attributes"], parse_constant=None) for r in csv.DictReader(text.splitlines())]
    ds = ogr.Open(str(tmp_path / "objects" / "objects.gpkg"))          # held: its layer dies with it
    (feature,) = ds.GetLayer("objects")
    assert got == json.loads(feature["attributes"]) == row.attributes


def test_the_wms_join_table_keeps_one_line_and_eight_fields_a_row(tmp_path):
    """MapServer's CSV join splits at every comma and line end: names and attributes with commas, quotes,
    CR/LF and non-ASCII text still give one line of 8 fields a row (MapServer itself: test_wms_ids)."""
    from pipeline25d.publish.objects import COLUMNS, SceneObject
    from pipeline25d.publish.wms_ids import write_join_table

    rows = [SceneObject(1 << 22 | k, "d1", name, "Building", 3.0, None, {"note": note})
            for k, (name, note) in enumerate([("a,b", 'say "hi",\nbye'), ("line\r\nbreak", "東京, 新宿"),
                                              ("plain", "")], 1)]
    write_objects(rows, tmp_path / "objects", horizontal_wkt("EPSG:25832"))
    write_join_table(tmp_path / "objects" / "objects.csv", tmp_path)
    lines = (tmp_path / "objects.csv").read_bytes().decode("utf-8").split("\n")[:-1]
    assert len(lines) == len(rows) + 1 and all(len(line.split(",")) == len(COLUMNS) + 1 for line in lines)
    for line, r in zip(lines[1:], rows):
        fields = line.split(",")
        assert fields[3] == r.name.replace(",", ";").replace("\r\n", " ")
        assert json.loads(fields[7].replace(";", ",")) == r.attributes        # the JSON back, commas restored
