"""Object attributes from every format that has them (pipeline25d.formats.attributes and its readers):
CityGML 2.0 and 3.0 generic and thematic attributes (generated files and the PLATEAU building of
tests/data/citygml) against the same XML read by xml.etree XPath; b3dm batch tables (a generated tile
with JSON and binary properties, the Tokyo and Amsterdam tiles of ../shared/data) against the table read
here with struct and numpy; glTF EXT_structural_metadata property tables (a generated glTF with every
value kind, the CDB sample) against the buffers decoded here; then through ingest to objects.csv,
objects.gpkg (OGR) and the viewer's shards; and hostile attributes bounded with one warning naming the file."""

from __future__ import annotations

import csv
import json
import struct
import warnings
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from pipeline25d.core.crs import horizontal_wkt
from pipeline25d.core.mesh import merged_info
from pipeline25d.formats.attributes import MAX_ATTRIBUTES, MAX_OBJECT_CHARS, MAX_TEXT, Limiter
from pipeline25d.formats.citygml import read_citygml
from pipeline25d.formats.tiles3d import read_b3dm, read_content
from pipeline25d.publish.objects import scene_objects, write_objects
from pipeline25d.stages.ingest import ingest
from pipeline25d_lab.scenes.model_writers import ECEF_ORIGIN, glb_bytes

DATA = Path(__file__).parent / "data" / "citygml"
SHARED = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"
NS = {"gml": "http://www.opengis.net/gml", "gen": "http://www.opengis.net/citygml/generics/2.0",
      "bldg": "http://www.opengis.net/citygml/building/2.0", "core": "http://www.opengis.net/citygml/2.0"}
NS3 = {"gen": "http://www.opengis.net/citygml/generics/3.0", "core": "http://www.opengis.net/citygml/3.0",
       "con": "http://www.opengis.net/citygml/construction/3.0", "gml": "http://www.opengis.net/gml/3.2",
       "bldg": "http://www.opengis.net/citygml/building/3.0"}
KINDS2 = {"stringAttribute": str, "intAttribute": int, "doubleAttribute": float, "dateAttribute": str,
          "uriAttribute": str, "measureAttribute": float}


def info_of(parts) -> dict:
    return merged_info(parts)


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


# ----------------------------------------------------------------------------- b3dm batch tables


def batched_boxes(n: int) -> tuple[dict, bytes]:
    """(glTF, binary) of ``n`` unit boxes side by side, each one batch id (``_BATCHID`` per vertex)."""
    corners = np.array([[x, y, z] for z in (0, 1) for y in (0, 1) for x in (0, 1)], float)
    quads = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (1, 3, 7, 5), (3, 2, 6, 7), (2, 0, 4, 6)]
    tris = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))])
    pos = np.concatenate([corners + (2.0 * k, 0, 0) for k in range(n)]).astype("<f4")
    idx = np.concatenate([tris + 8 * k for k in range(n)]).astype("<u4").ravel()
    batch = np.repeat(np.arange(n), 8).astype("<f4")
    blobs = [pos.tobytes(), idx.tobytes(), batch.tobytes()]
    views, offset = [], 0
    for blob in blobs:
        views.append({"buffer": 0, "byteOffset": offset, "byteLength": len(blob)})
        offset += len(blob)
    doc = {"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0}],
           "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "_BATCHID": 2}, "indices": 1}]}],
           "bufferViews": views, "buffers": [{"byteLength": offset}],
           "accessors": [{"bufferView": 0, "componentType": 5126, "count": len(pos), "type": "VEC3",
                          "min": pos.min(axis=0).tolist(), "max": pos.max(axis=0).tolist()},
                         {"bufferView": 1, "componentType": 5125, "count": len(idx), "type": "SCALAR"},
                         {"bufferView": 2, "componentType": 5126, "count": len(batch), "type": "SCALAR"}]}
    return doc, b"".join(blobs)


def b3dm(n: int, batch_json: bytes, batch_bin: bytes = b"") -> bytes:
    """A b3dm of ``n`` batched boxes at the corpus's ECEF origin with the given batch table."""
    feature = json.dumps({"BATCH_LENGTH": n, "RTC_CENTER": list(ECEF_ORIGIN)}).encode()
    feature += b" " * (-(28 + len(feature)) % 8)
    batch_json += b" " * (-len(batch_json) % 8)
    glb = glb_bytes(*batched_boxes(n))
    body = feature + batch_json + batch_bin + glb
    return struct.pack("<4s6I", b"b3dm", 1, 28 + len(body), len(feature), 0, len(batch_json), len(batch_bin)) + body


def read_batch_table(data: bytes) -> tuple[dict, int, bytes]:
    """(batch table JSON, BATCH_LENGTH, binary body) of a b3dm, read here."""
    ft_json, ft_bin, bt_json, bt_bin = struct.unpack_from("<4I", data, 12)
    count = json.loads(data[28:28 + ft_json])["BATCH_LENGTH"]
    start = 28 + ft_json + ft_bin
    return json.loads(data[start:start + bt_json]), count, data[start + bt_json:start + bt_json + bt_bin]


def expected_rows(data: bytes) -> list[dict]:
    """Each feature's properties: JSON arrays as they are, binary ones decoded by numpy; nulls left out."""
    table, count, body = read_batch_table(data)
    dtypes = {"BYTE": "i1", "UNSIGNED_SHORT": "<u2", "FLOAT": "<f4", "DOUBLE": "<f8", "UNSIGNED_INT": "<u4"}
    columns = {}
    for name, col in table.items():
        if isinstance(col, dict):
            width = {"SCALAR": 1, "VEC2": 2, "VEC3": 3}[col["type"]]
            arr = np.frombuffer(body, dtypes[col["componentType"]], count * width, col.get("byteOffset", 0))
            columns[name] = [a.tolist() if width > 1 else a.item() for a in arr.reshape(count, width)]
        else:
            columns[name] = col
    return [{k: v[i] for k, v in columns.items() if v[i] is not None} for i in range(count)]


def test_generated_b3dm_batch_table_json_and_binary(tmp_path):
    n = 5
    heights = np.array([3.5, 7.25, 12.0, 0.125, 30.5], "<f8")
    codes = np.array([[1, 2], [3, 4], [5, 6], [7, 8], [65535, 0]], "<u2")
    binary = heights.tobytes() + codes.tobytes()
    table = {"name": ["a,b", 'q"uote', "新宿", None, "line\nbreak"], "storeys": [1, 2, 3, 4, None],
             "height": {"byteOffset": 0, "componentType": "DOUBLE", "type": "SCALAR"},
             "codes": {"byteOffset": 40, "componentType": "UNSIGNED_SHORT", "type": "VEC2"}}
    path = tmp_path / "tile.b3dm"
    path.write_bytes(b3dm(n, json.dumps(table).encode(), binary))
    loaded = read_b3dm(path, {})
    info = info_of(loaded.parts)
    rows = expected_rows(path.read_bytes())
    assert {k for p in loaded.parts for k in p.objects} == {f"tile.b3dm#{i}" for i in range(n)}
    assert info == {f"tile.b3dm#{i}": {"attributes": rows[i]} for i in range(n)}
    assert info["tile.b3dm#2"]["attributes"] == {"name": "新宿", "storeys": 3, "height": 12.0, "codes": [5, 6]}
    assert "name" not in info["tile.b3dm#3"]["attributes"]                       # a null is left out


def test_the_inner_tiles_of_a_composite_keep_their_features_apart(tmp_path):
    """Two b3dm of three batch ids each in one cmpt: six objects, each with its own tile's row."""
    tiles = [b3dm(3, json.dumps({"tile": [k] * 3, "n": [10 * k + i for i in range(3)]}).encode()) for k in range(2)]
    path = tmp_path / "two.cmpt"
    path.write_bytes(struct.pack("<4sIII", b"cmpt", 1, 16 + sum(map(len, tiles)), 2) + b"".join(tiles))
    parts = read_content(path)
    expected = {f"two.cmpt/{k}#{i}": {"attributes": {"tile": k, "n": 10 * k + i}} for k in range(2) for i in range(3)}
    assert info_of(parts) == expected and {o for p in parts for o in p.objects} == set(expected)


def test_each_i3dm_instance_is_an_object_with_its_batch_table_row():
    """TilesetWithTransforms' instances.i3dm (25 instances, positions only): instance j's faces, less its
    POSITION read here from the feature table, are the same model for every j; its attributes are row j."""
    path = SHARED / "3dtiles-samples/TilesetWithTransforms/instances.i3dm"
    if not path.is_file():
        pytest.skip(f"{path} not present")
    data = path.read_bytes()
    ft_json, ft_bin, bt_json, _, _ = struct.unpack_from("<5I", data, 12)
    table = json.loads(data[32:32 + ft_json])
    n = table["INSTANCES_LENGTH"]
    positions = np.frombuffer(data, "<f4", 3 * n, 32 + ft_json + table["POSITION"]["byteOffset"]).reshape(n, 3)
    batch = json.loads(data[32 + ft_json + ft_bin:32 + ft_json + ft_bin + bt_json])
    (part,) = read_content(path)
    assert part.objects == tuple(f"instances.i3dm#{j}" for j in range(n))
    shapes = [part.vertices[part.faces[part.face_objects == j]].reshape(-1, 3) - positions[j] for j in range(n)]
    assert all(np.allclose(s, shapes[0], atol=1e-4) for s in shapes)
    assert info_of([part]) == {f"instances.i3dm#{j}": {"attributes": {k: v[j] for k, v in batch.items()}} for j in range(n)}


@pytest.mark.parametrize("tile", ["tokyo-chiyoda-b3dm/cesium-rtc-extension.b3dm", "amsterdam-3dtiles/tiles/5.b3dm"])
def test_shared_b3dm_batch_tables(tile):
    path = SHARED / tile
    if not path.is_file():
        pytest.skip(f"{path} not present")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        loaded = read_b3dm(path, {})
    info, rows = info_of(loaded.parts), expected_rows(path.read_bytes())
    assert len(rows) == len(info) and {k for p in loaded.parts for k in p.objects} <= set(info)
    for i, row in enumerate(rows):
        assert info[f"{path.name}#{i}"] == ({"attributes": row} if row else {}), i
    if "tokyo" in tile:                      # binary DOUBLE 計測高さ (measured height) and BYTE LOD
        assert sum("計測高さ" in r for r in rows) == len(rows) and {r["LOD"] for r in rows} <= {0, 1, 2, 3}


# ----------------------------------------------------------------------------- EXT_structural_metadata


def metadata_gltf() -> tuple[dict, bytes, dict]:
    """(glTF, binary, expected rows) of three boxes with a property table of every value kind."""
    doc, binary = batched_boxes(3)
    prim = doc["meshes"][0]["primitives"][0]
    prim["attributes"] = {"POSITION": 0, "_FEATURE_ID_0": 2}
    prim["extensions"] = {"EXT_mesh_features": {"featureIds": [{"featureCount": 3, "attribute": 0, "propertyTable": 0}]}}
    names = ["Hall", "Tür, 2", ""]
    strings = b"".join(s.encode() for s in names)
    string_offsets = np.cumsum([0] + [len(s.encode()) for s in names]).astype("<u4")
    tags = ["x", "yy", "zzz", "w"]                        # arrays of strings: [x, yy], [], [zzz, w]
    tag_offsets = np.array([0, 2, 2, 4], "<u4")
    tag_strings = np.cumsum([0] + [len(t) for t in tags]).astype("<u4")
    heights = np.array([1000, 2500, -1], "<i2")           # scale 0.01, offset 1.0, noData -1
    flags = np.array([0b101], "u1")                       # True, False, True
    kinds = np.array([2, 0, 1], "u1")
    vec = np.array([[1, 2, 3], [4, 5, 6], [7, 8, 9]], "<f4")
    blobs = [strings, string_offsets.tobytes(), heights.tobytes(), flags.tobytes(), kinds.tobytes(), vec.tobytes(),
             "".join(tags).encode(), tag_offsets.tobytes(), tag_strings.tobytes()]
    offset = len(binary)
    first = len(doc["bufferViews"])
    for blob in blobs:
        pad = -offset % 8
        binary += b"\0" * pad
        offset += pad
        doc["bufferViews"].append({"buffer": 0, "byteOffset": offset, "byteLength": len(blob)})
        binary += blob
        offset += len(blob)
    doc["buffers"][0]["byteLength"] = len(binary)
    v = [first + k for k in range(len(blobs))]
    doc["extensionsUsed"] = ["EXT_mesh_features", "EXT_structural_metadata"]
    doc["extensions"] = {"EXT_structural_metadata": {
        "schema": {"id": "s", "enums": {"Kind": {"valueType": "UINT8", "values": [
            {"name": "house", "value": 0}, {"name": "shed", "value": 1}, {"name": "hall", "value": 2}]}},
            "classes": {"building": {"properties": {
                "name": {"type": "STRING"}, "height": {"type": "SCALAR", "componentType": "INT16", "scale": 0.01,
                                                       "offset": 1.0, "noData": -1},
                "listed": {"type": "BOOLEAN"}, "kind": {"type": "ENUM", "enumType": "Kind"},
                "centre": {"type": "VEC3", "componentType": "FLOAT32"},
                "tags": {"type": "STRING", "array": True}}}}},
        "propertyTables": [{"class": "building", "count": 3, "properties": {
            "name": {"values": v[0], "stringOffsets": v[1]}, "height": {"values": v[2]},
            "listed": {"values": v[3]}, "kind": {"values": v[4]}, "centre": {"values": v[5]},
            "tags": {"values": v[6], "arrayOffsets": v[7], "stringOffsets": v[8]}}}]}}
    expected = {}
    for i in range(3):
        row = {"name": names[i], "listed": bool(flags[0] >> i & 1), "kind": ["house", "shed", "hall"][kinds[i]],
               "centre": vec[i].astype(float).tolist(), "tags": tags[tag_offsets[i]:tag_offsets[i + 1]]}
        if heights[i] != -1:
            row["height"] = heights[i] * 0.01 + 1.0
        expected[i] = row
    return doc, binary, expected


def test_generated_gltf_property_table_of_every_value_kind(tmp_path):
    doc, binary, expected = metadata_gltf()
    path = tmp_path / "boxes.glb"
    path.write_bytes(glb_bytes(doc, binary))
    parts = read_content(path)
    info = info_of(parts)
    assert set(info) == {f"boxes.glb#{i}" for i in range(3)}
    for i, row in expected.items():
        got = info[f"boxes.glb#{i}"]["attributes"]
        assert got.keys() == row.keys() and got.pop("height", None) == pytest.approx(row.pop("height", None))
        assert got == row


def test_a_null_feature_has_no_attributes_and_a_broken_table_costs_only_its_attributes(tmp_path):
    doc, binary, expected = metadata_gltf()
    doc["meshes"][0]["primitives"][0]["extensions"]["EXT_mesh_features"]["featureIds"][0]["nullFeatureId"] = 1
    path = tmp_path / "null.glb"
    path.write_bytes(glb_bytes(doc, binary))
    info = info_of(read_content(path))
    assert set(info) == {"null.glb#0", "null.glb#2"} and info["null.glb#2"]["attributes"]["kind"] == expected[2]["kind"]
    table = doc["extensions"]["EXT_structural_metadata"]["propertyTables"][0]
    table["count"] = 10 ** 9                                       # far more rows than its buffers hold
    table["properties"]["name"]["stringOffsets"] = table["properties"]["height"]["values"]
    path.write_bytes(glb_bytes(doc, binary))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        parts = read_content(path)
    assert not info_of(parts) and sum(p.n_triangles for p in parts) == 36
    assert any(str(path) in str(w.message) and "property table not read" in str(w.message) for w in caught)


def test_cdb_property_table():
    """The CDB sample's GSModels tile: its property table's SCALAR columns decoded here from the GLB."""
    path = SHARED / "3dtiles-samples/cdb-yemen-cut/Tiles/N12/E045/GSModels/1_1/N12E045_D300_S001_T001_LC5_U0_R0.glb"
    if not path.is_file():
        pytest.skip(f"{path} not present")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        info = info_of(read_content(path))
    data = path.read_bytes()
    n = struct.unpack_from("<I", data, 12)[0]
    doc = json.loads(data[20:20 + n])
    body = data[20 + n + 8:]
    ext = doc["extensions"]["EXT_structural_metadata"]
    table = ext["propertyTables"][0]
    props = ext["schema"]["classes"][table["class"]]["properties"]
    dtypes = {"FLOAT64": "<f8", "FLOAT32": "<f4", "INT32": "<i4", "UINT32": "<u4", "INT16": "<i2", "UINT8": "u1"}
    checked = 0
    for key, obj in info.items():
        row = int(key.rsplit("#", 1)[1])
        for name, prop in table["properties"].items():
            kind = props[name]
            if kind["type"] == "SCALAR" and not kind.get("array") and kind["componentType"] in dtypes:
                view = doc["bufferViews"][prop["values"]]
                value = np.frombuffer(body, dtypes[kind["componentType"]], 1,
                                      view.get("byteOffset", 0) + row * np.dtype(dtypes[kind["componentType"]]).itemsize)
                assert obj["attributes"][name] == value.item(), name
                checked += 1
    assert checked >= 10


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
