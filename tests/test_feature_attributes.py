"""Feature attributes of 3D Tiles and glTF (pipeline25d.formats.batch_table, structural_metadata,
feature_info): b3dm batch tables (a generated tile with JSON and binary properties, the Tokyo and
Amsterdam tiles of ../shared/data) against the table read here with struct and numpy; a composite's inner
tiles kept apart; each i3dm instance an object; glTF EXT_structural_metadata property tables (a generated
glTF with every value kind, the CDB sample) against the buffers decoded here."""

from __future__ import annotations

import json
import struct
import warnings
from pathlib import Path

import numpy as np
import pytest
from conftest import shared_file

from pipeline25d.core.mesh import merged_info as info_of
from pipeline25d.formats.tiles3d import read_b3dm, read_content
from pipeline25d_lab.scenes.model_writers import ECEF_ORIGIN, glb_bytes

SHARED = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"


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
    shared_file(path)
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
    assert info_of([part]) == {f"instances.i3dm#{j}": {"attributes": {k: v[j] for k, v in batch.items()}}
                               for j in range(n)}


@pytest.mark.parametrize("tile", ["tokyo-chiyoda-b3dm/cesium-rtc-extension.b3dm", "amsterdam-3dtiles/tiles/5.b3dm"])
def test_shared_b3dm_batch_tables(tile):
    path = SHARED / tile
    shared_file(path)
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
    prim["extensions"] = {"EXT_mesh_features": {
        "featureIds": [{"featureCount": 3, "attribute": 0, "propertyTable": 0}]}}
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
    shared_file(path)
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
                                      view.get("byteOffset", 0)
                                      + row * np.dtype(dtypes[kind["componentType"]]).itemsize)
                assert obj["attributes"][name] == value.item(), name
                checked += 1
    assert checked >= 10
