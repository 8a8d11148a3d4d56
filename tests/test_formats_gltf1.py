"""glTF 1.0 (JSON and its binary container) read through its upgrade to 2.0 (formats.gltf1): the
same parts as the same model written as glTF 2.0, its 1.0-only forms (interleaved strides,
materials by technique or KHR_materials_common, several meshes on a node, WEB3D quantized
positions) decoded exactly, in b3dm with their batch ids, and 3D Tiles 1.0's gltfUpAxis X."""

from __future__ import annotations

import base64
import io
import json
import struct
from pathlib import Path

import numpy as np
import pytest

from pipeline25d.core.errors import InputFileError
from pipeline25d.formats.gltf import load_gltf, parse_gltf_bytes
from pipeline25d.formats.has_objects import _content_has_features
from pipeline25d.formats.tiles3d import read_content, read_tileset
from pipeline25d_lab.scenes.model_writers import b3dm_bytes

# two triangles of a unit square at height 2 (glTF y-up), with texture coordinates and batch ids
POS = np.array([[0, 2, 0], [1, 2, 0], [1, 2, -1], [0, 2, -1]], np.float32)
UV = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float32)
BATCH = np.array([0, 0, 1, 1], np.float32)
IDX = np.array([0, 1, 2, 2, 3, 0], np.uint16)     # a face's batch id is its first vertex's: 0, 1


def _png() -> bytes:
    from PIL import Image

    out = io.BytesIO()
    Image.new("RGB", (4, 4), (10, 200, 30)).save(out, format="PNG")
    return out.getvalue()


def gltf1(material: dict, *, body_name: str = "buf", image: dict | None = None, extra: dict | None = None,
          positions: tuple[bytes, dict] | None = None) -> tuple[dict, bytes]:
    """A glTF 1.0 document (tables keyed by id) and its buffer: positions, UVs and batch ids
    interleaved in one view (stride 24), the indices in another."""
    inter = np.zeros(4, dtype=[("p", "<f4", 3), ("uv", "<f4", 2), ("b", "<f4")])
    inter["p"], inter["uv"], inter["b"] = POS, UV, BATCH
    body = inter.tobytes() + IDX.tobytes()
    accessors = {
        "acc_pos": {"bufferView": "bv_attr", "byteOffset": 0, "byteStride": 24, "componentType": 5126,
                    "count": 4, "type": "VEC3"},
        "acc_uv": {"bufferView": "bv_attr", "byteOffset": 12, "byteStride": 24, "componentType": 5126,
                   "count": 4, "type": "VEC2"},
        "acc_batch": {"bufferView": "bv_attr", "byteOffset": 20, "byteStride": 24, "componentType": 5126,
                      "count": 4, "type": "SCALAR"},
        "acc_idx": {"bufferView": "bv_idx", "byteOffset": 0, "byteStride": 0, "componentType": 5123,
                    "count": 6, "type": "SCALAR"},
    }
    views = {"bv_attr": {"buffer": body_name, "byteOffset": 0, "byteLength": 96},
             "bv_idx": {"buffer": body_name, "byteOffset": 96, "byteLength": 12}}
    if positions is not None:                      # positions stored elsewhere (quantized)
        data, accessor = positions
        views["bv_q"] = {"buffer": body_name, "byteOffset": len(body), "byteLength": len(data)}
        accessors["acc_pos"] = {"bufferView": "bv_q", **accessor}
        body += data
    doc = {
        "asset": {"version": 1, "generator": "test"},
        "scene": "sc", "scenes": {"sc": {"nodes": ["root"]}},
        "nodes": {"root": {"children": ["leaf"], "matrix": [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 10, 0, 0, 1]},
                  "leaf": {"meshes": ["m1", "m2"]}},
        "meshes": {name: {"primitives": [{"attributes": {"POSITION": "acc_pos", "TEXCOORD_0": "acc_uv",
                                                         "BATCHID": "acc_batch"},
                                          "indices": "acc_idx", "material": "mat", "mode": 4}]}
                   for name in ("m1", "m2")},
        "materials": {"mat": material},
        "accessors": accessors, "bufferViews": views,
        "buffers": {body_name: {"byteLength": len(body), "type": "arraybuffer"}},
        "techniques": {"tech": {"parameters": {"diffuse": {"type": 35666}, "tint": {"type": 35666}},
                                "uniforms": {"u_diffuse": "diffuse", "u_tint": "tint"}}},
    }
    if image is not None:
        doc["images"] = {"img": image}
        doc["textures"] = {"tex": {"source": "img", "sampler": "s", "format": 6408}}
    doc.update(extra or {})
    return doc, body


def glb1(doc: dict, body: bytes) -> bytes:
    """The binary glTF 1.0 container (KHR_binary_glTF) of ``doc`` and its body."""
    js = json.dumps(doc).encode()
    js += b" " * (-len(js) % 4)
    return struct.pack("<4sIIII", b"glTF", 1, 20 + len(js) + len(body), len(js), 0) + js + body


def with_data_uri(doc: dict, body: bytes, name: str = "buf") -> dict:
    doc = json.loads(json.dumps(doc))
    doc["buffers"][name]["uri"] = "data:application/octet-stream;base64," + base64.b64encode(body).decode()
    return doc


def expected_vertices() -> np.ndarray:
    """The square through the node's translation (x + 10), turned z-up: (x, y, z) -> (x, -z, y)."""
    p = POS.astype(np.float64) + [10, 0, 0]
    return np.column_stack([p[:, 0], -p[:, 2], p[:, 1]])


def test_a_gltf1_json_reads_as_its_geometry_and_the_technique_diffuse_colour(tmp_path):
    """Tables by id, an interleaved view (stride 24), a node of two meshes, asset version 1 (a
    number), the diffuse colour bound to the technique's u_diffuse uniform (not the other uniform)."""
    material = {"technique": "tech", "values": {"diffuse": [0.8, 0.2, 0.0, 1.0], "tint": [0, 0, 1, 1]}}
    doc, body = gltf1(material)
    path = tmp_path / "model.gltf"
    path.write_text(json.dumps(with_data_uri(doc, body)))
    parts = load_gltf(path)
    assert len(parts) == 2                                     # the node's two meshes
    for part in parts:
        assert part.n_triangles == 2 and part.texture is None
        got = part.vertices[np.lexsort(part.vertices.T)]
        want = expected_vertices()[np.lexsort(expected_vertices().T)]
        np.testing.assert_allclose(got, want, atol=1e-6)
        np.testing.assert_array_equal(part.colors, [[204, 51, 0, 255]] * 4)
        assert len(part.objects) == 2                          # BATCHID: two features
    assert _content_has_features(path.read_bytes())


def test_a_binary_gltf1_with_materials_common_draws_its_embedded_texture(tmp_path):
    """KHR_binary_glTF: the body is the binary chunk, the image a buffer view of it; the material's
    KHR_materials_common diffuse names the texture. Read alone and inside a b3dm."""
    png = _png()
    material = {"extensions": {"KHR_materials_common": {"technique": "PHONG", "values": {"diffuse": "tex"}}}}
    doc, body = gltf1(material, body_name="binary_glTF",
                      image={"uri": "data:,", "extensions": {"KHR_binary_glTF": {"bufferView": "bv_img",
                                                                                 "mimeType": "image/png"}}},
                      extra={"extensionsUsed": ["KHR_binary_glTF", "KHR_materials_common"]})
    doc["bufferViews"]["bv_img"] = {"buffer": "binary_glTF", "byteOffset": len(body), "byteLength": len(png)}
    doc["buffers"]["binary_glTF"].update(byteLength=len(body) + len(png), uri="data:,")
    data = glb1(doc, body + png)
    for parts in (parse_gltf_bytes(data, tmp_path / "m.glb"),
                  read_content(_write(tmp_path / "m.b3dm", b3dm_bytes(data)))):
        assert len(parts) == 2 and all(p.texture == png for p in parts)
        uv = parts[0].uv[np.lexsort(parts[0].vertices.T)]
        np.testing.assert_allclose(np.sort(uv, axis=0), np.sort(np.column_stack([UV[:, 0], 1 - UV[:, 1]]), axis=0))


def test_web3d_quantized_positions_are_decoded_by_their_matrix(tmp_path):
    """WEB3D_quantized_attributes: uint16 positions and a column-major decodeMatrix (scale and
    offset) decode to the float square within half a quantization step."""
    lo, hi = POS.min(axis=0).astype(np.float64), POS.max(axis=0).astype(np.float64)
    scale = np.where(hi > lo, (hi - lo) / 65535.0, 1.0)
    q = np.rint((POS - lo) / scale).astype(np.uint16)
    decode = np.eye(4)
    decode[:3, :3] = np.diag(scale)
    decode[:3, 3] = lo
    accessor = {"byteOffset": 0, "byteStride": 0, "componentType": 5123, "count": 4, "type": "VEC3",
                "extensions": {"WEB3D_quantized_attributes": {"decodeMatrix": decode.T.ravel().tolist(),
                                                              "decodedMin": lo.tolist(), "decodedMax": hi.tolist()}}}
    data = q.tobytes() + b"\0" * (-q.nbytes % 4)
    doc, body = gltf1({"values": {"diffuse": [1, 1, 1, 1]}}, positions=(data, accessor),
                      extra={"extensionsUsed": ["WEB3D_quantized_attributes"]})
    part = parse_gltf_bytes(glb1(doc, body), tmp_path / "q.glb")[0]
    got = part.vertices[np.lexsort(part.vertices.T)]
    want = expected_vertices()[np.lexsort(expected_vertices().T)]
    np.testing.assert_allclose(got, want, atol=0.5 * scale.max() + 1e-9)


@pytest.mark.parametrize("axis, up", [("X", [1, 0, 0]), ("Y", [0, 1, 0]), ("Z", [0, 0, 1])])
def test_a_3d_tiles_1_0_gltf_up_axis_turns_that_axis_up(tmp_path, axis, up):
    """asset.gltfUpAxis X, Y or Z: a point one unit along the named glTF axis ends one unit up."""
    doc, body = gltf1({"values": {"diffuse": [1, 1, 1, 1]}})
    doc["nodes"] = {"root": {"meshes": ["m1"]}}
    pts = np.array([up, [0.0, 0.0, 0.0], [0.5, 0.5, 0.5]], np.float32)   # the named axis's unit point first
    inter = np.zeros(4, dtype=[("p", "<f4", 3), ("uv", "<f4", 2), ("b", "<f4")])
    inter["p"][:3] = pts
    inter["p"][3] = pts[2]
    body = inter.tobytes() + body[96:]
    _write(tmp_path / "t.b3dm", b3dm_bytes(glb1(doc, body)))
    tileset = {"asset": {"version": "1.0", "gltfUpAxis": axis}, "geometricError": 1,
               "root": {"boundingVolume": {"sphere": [0, 0, 0, 10]}, "geometricError": 0, "refine": "ADD",
                        "content": {"uri": "t.b3dm"}}}
    (tmp_path / "tileset.json").write_text(json.dumps(tileset))
    parts = read_tileset(tmp_path / "tileset.json", {"crs": "EPSG:4978"}).parts
    v = np.concatenate([p.vertices for p in parts])
    assert v[:, 2].max() == pytest.approx(1.0) and np.abs(v).max() == pytest.approx(1.0)
    top = v[np.argmax(v[:, 2])]
    np.testing.assert_allclose(top, [0, 0, 1], atol=1e-9)


def test_an_unknown_gltf_up_axis_and_broken_1_0_files_are_errors_naming_the_file(tmp_path):
    doc, body = gltf1({"values": {"diffuse": [1, 1, 1, 1]}})
    data = glb1(doc, body)
    with pytest.raises(InputFileError, match="truncated"):
        parse_gltf_bytes(data[:-10], tmp_path / "cut.glb")
    broken = json.loads(json.dumps(doc))
    broken["meshes"]["m1"]["primitives"][0]["indices"] = "acc_gone"
    with pytest.raises(InputFileError, match="acc_gone") as err:
        parse_gltf_bytes(glb1(broken, body), tmp_path / "dangling.glb")
    assert "dangling.glb" in str(err.value)
    (tmp_path / "tileset.json").write_text(json.dumps(
        {"asset": {"version": "1.0", "gltfUpAxis": "W"}, "geometricError": 1,
         "root": {"boundingVolume": {"sphere": [0, 0, 0, 1]}, "geometricError": 0}}))
    with pytest.raises(InputFileError, match="gltfUpAxis"):
        read_tileset(tmp_path / "tileset.json", {"crs": "EPSG:4978"})


def _write(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path
