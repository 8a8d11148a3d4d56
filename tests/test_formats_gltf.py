"""glTF reader: real sample files plus tiny synthetic glTFs that pin each convention."""

from __future__ import annotations

import base64
import io
import json
import struct
from pathlib import Path

import numpy as np
import pytest
from conftest import shared_file

from pipeline25d.core.errors import InputFileError, UnsupportedFeatureError
from pipeline25d.formats.gltf import load_gltf, parse_gltf_bytes

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
SAMPLES = DATA / "3dtiles-samples"



# ----------------------------------------------------------------------------- synthetic glTF helpers

TRI = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype=np.float32)
TRI_UV = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 0.25]], dtype=np.float32)


def _png_bytes() -> bytes:
    from PIL import Image

    out = io.BytesIO()
    Image.new("RGB", (4, 4), (255, 0, 0)).save(out, format="PNG")
    return out.getvalue()


def _gltf(node: dict | None = None, material: dict | None = None, extra: dict | None = None,
          mode: int = 4, image: dict | None = None, color0: np.ndarray | None = None) -> tuple[dict, bytes]:
    """A one-triangle glTF (JSON, binary buffer) with optional node, material, texture."""
    blobs = [TRI.tobytes(), np.array([0, 1, 2], np.uint16).tobytes() + b"\0\0", TRI_UV.tobytes()]
    attributes = {"POSITION": 0, "TEXCOORD_0": 2}
    accessors = [
        {"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3"},
        {"bufferView": 1, "componentType": 5123, "count": 3, "type": "SCALAR"},
        {"bufferView": 2, "componentType": 5126, "count": 3, "type": "VEC2"},
    ]
    if color0 is not None:
        blobs.append(np.asarray(color0, np.uint8).tobytes())
        accessors.append({"bufferView": 3, "componentType": 5121, "normalized": True, "count": 3, "type": "VEC4"})
        attributes["COLOR_0"] = 3
    views, offset = [], 0
    for blob in blobs:
        views.append({"buffer": 0, "byteOffset": offset, "byteLength": len(blob)})
        offset += len(blob)
    doc = {
        "asset": {"version": "2.0"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [dict(node or {}, mesh=0)],
        "meshes": [{"primitives": [{"attributes": attributes, "indices": 1, "mode": mode, "material": 0}]}],
        "materials": [material or {}],
        "accessors": accessors,
        "bufferViews": views,
        "buffers": [{"byteLength": offset}],
    }
    if image is not None:
        doc["images"] = [image]
        doc["textures"] = [{"source": 0}]
    doc.update(extra or {})
    return doc, b"".join(blobs)


def _write_gltf(path: Path, doc: dict, binary: bytes) -> Path:
    doc = json.loads(json.dumps(doc))
    doc["buffers"][0]["uri"] = "data:application/octet-stream;base64," + base64.b64encode(binary).decode()
    path.write_text(json.dumps(doc))
    return path


def _glb(doc: dict, binary: bytes) -> bytes:
    js = json.dumps(doc).encode()
    js += b" " * (-len(js) % 4)
    binary += b"\0" * (-len(binary) % 4)
    total = 12 + 8 + len(js) + 8 + len(binary)
    return (struct.pack("<4sII", b"glTF", 2, total) + struct.pack("<II", len(js), 0x4E4F534A) + js
            + struct.pack("<II", len(binary), 0x004E4942) + binary)


# ----------------------------------------------------------------------------- conventions


def test_y_up_to_z_up_and_colour_factor(tmp_path):
    doc, binary = _gltf(material={"pbrMetallicRoughness": {"baseColorFactor": [1.0, 0.5, 0.0, 1.0]}})
    parts = load_gltf(_write_gltf(tmp_path / "t.gltf", doc, binary))
    assert len(parts) == 1 and parts[0].n_triangles == 1
    # (x, y, z) -> (x, -z, y): the glTF y axis becomes z
    np.testing.assert_allclose(np.sort(parts[0].vertices, axis=0), [[0, 0, 0], [0, 0, 0], [1, 0, 1]])
    assert parts[0].texture is None and parts[0].uv is None
    np.testing.assert_array_equal(parts[0].colors, [[255, 128, 0, 255]] * 3)
    raw = load_gltf(tmp_path / "t.gltf", y_up_to_z_up=False)[0]
    np.testing.assert_allclose(raw.vertices[raw.faces[0]], TRI)


def test_node_trs_and_cesium_rtc_glb(tmp_path):
    # rotation 90 deg about z (quaternion x, y, z, w), scale 2, translation (10, 0, 0), then RTC centre
    s = np.sqrt(0.5)
    node = {"rotation": [0, 0, s, s], "scale": [2, 2, 2], "translation": [10, 0, 0]}
    center = [6378137.0, 1000.0, 2000.0]
    doc, binary = _gltf(node=node, extra={"extensionsUsed": ["CESIUM_RTC"], "extensionsRequired": ["CESIUM_RTC"],
                                          "extensions": {"CESIUM_RTC": {"center": center}}})
    part = parse_gltf_bytes(_glb(doc, binary), tmp_path / "x.glb")[0]
    tri = part.vertices[part.faces[0]]
    # glTF: (1,0,0) -> scale (2,0,0) -> rot (0,2,0) -> +T (10,2,0); z-up: (10, 0, 2); + centre
    node_space = np.array([[10, 0, 0], [10, 2, 0], [8, 0, 0]], dtype=np.float64)
    expected = np.column_stack([node_space[:, 0], -node_space[:, 2], node_space[:, 1]]) + center
    np.testing.assert_allclose(tri, expected, atol=1e-9)
    assert part.vertices.dtype == np.float64


def test_node_matrix_hierarchy(tmp_path):
    doc, binary = _gltf(node={"children": [1]})
    doc["nodes"] = [{"matrix": [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 5, 6, 7, 1], "children": [1]},
                    {"translation": [1, 1, 1], "mesh": 0}]
    part = load_gltf(_write_gltf(tmp_path / "h.gltf", doc, binary), y_up_to_z_up=False)[0]
    np.testing.assert_allclose(part.vertices[part.faces[0]], TRI + [6, 7, 8])


def test_embedded_texture_uv_flipped(tmp_path):
    png = _png_bytes()
    doc, binary = _gltf(material={"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}})
    doc["bufferViews"].append({"buffer": 0, "byteOffset": len(binary), "byteLength": len(png)})
    doc["buffers"][0]["byteLength"] = len(binary) + len(png)
    doc["images"] = [{"bufferView": 3, "mimeType": "image/png"}]
    doc["textures"] = [{"source": 0}]
    part = parse_gltf_bytes(_glb(doc, binary + png), tmp_path / "t.glb")[0]
    assert part.texture == png
    uv = part.uv
    # glTF v -> 1 - v: the set of v values {0, 0, 0.25} becomes {1, 1, 0.75}
    assert sorted(np.round(uv[:, 1], 6).tolist()) == [0.75, 1.0, 1.0]
    assert sorted(np.round(uv[:, 0], 6).tolist()) == [0.0, 0.0, 1.0]


def test_a_truncated_embedded_image_warns_and_drops_texture(tmp_path):
    """A JPEG cut short passes its magic bytes: it is decoded when read, so the render job that
    would have failed on it never gets it."""
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.random.default_rng(2).integers(0, 256, (32, 32, 3), dtype=np.uint8)).save(buf, format="JPEG")
    jpeg = buf.getvalue()[:300]
    doc, binary = _gltf(material={"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}})
    doc["bufferViews"].append({"buffer": 0, "byteOffset": len(binary), "byteLength": len(jpeg)})
    doc["buffers"][0]["byteLength"] = len(binary) + len(jpeg)
    doc["images"] = [{"bufferView": 3, "mimeType": "image/jpeg"}]
    doc["textures"] = [{"source": 0}]
    with pytest.warns(UserWarning, match=r"t\.glb: image 0 cannot be read"):
        part = parse_gltf_bytes(_glb(doc, binary + jpeg), tmp_path / "t.glb")[0]
    assert part.texture is None


def test_data_uri_and_external_image(tmp_path):
    png = _png_bytes()
    material = {"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}}
    doc, binary = _gltf(material=material, image={"uri": "data:image/png;base64," + base64.b64encode(png).decode()})
    assert load_gltf(_write_gltf(tmp_path / "a.gltf", doc, binary))[0].texture == png
    (tmp_path / "tex dir").mkdir()
    (tmp_path / "tex dir" / "wall.png").write_bytes(png)
    doc, binary = _gltf(material=material, image={"uri": "tex%20dir/wall.png"})
    assert load_gltf(_write_gltf(tmp_path / "b.gltf", doc, binary))[0].texture == png


def test_missing_external_image_warns_and_drops_texture(tmp_path):
    material = {"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}, "baseColorFactor": [0, 0, 1, 1]}}
    doc, binary = _gltf(material=material, image={"uri": "nowhere.jpg"})
    with pytest.warns(UserWarning, match="nowhere.jpg"):
        part = load_gltf(_write_gltf(tmp_path / "m.gltf", doc, binary))[0]
    assert part.texture is None and part.uv is None
    np.testing.assert_array_equal(part.colors[0], [0, 0, 255, 255])


def test_color0_times_factor(tmp_path):
    material = {"pbrMetallicRoughness": {"baseColorFactor": [1.0, 1.0, 1.0, 0.5]}}
    doc, binary = _gltf(material=material, color0=np.array([[255, 0, 0, 255], [0, 255, 0, 255], [0, 0, 255, 255]]))
    part = load_gltf(_write_gltf(tmp_path / "c.gltf", doc, binary))[0]
    got = {tuple(c) for c in part.colors}
    assert got == {(255, 0, 0, 128), (0, 255, 0, 128), (0, 0, 255, 128)}


def test_non_triangle_primitives_skipped(tmp_path):
    doc, binary = _gltf(mode=1)
    with pytest.warns(UserWarning, match="mode"):
        assert load_gltf(_write_gltf(tmp_path / "l.gltf", doc, binary)) == []


def _with_image(doc: dict, binary: bytes, image: bytes, mime: str) -> tuple[dict, bytes]:
    """The one-triangle glTF with ``image`` appended to its buffer as image 0."""
    doc["bufferViews"].append({"buffer": 0, "byteOffset": len(binary), "byteLength": len(image)})
    doc["buffers"][0]["byteLength"] = len(binary) + len(image)
    doc["images"] = [{"bufferView": len(doc["bufferViews"]) - 1, "mimeType": mime}]
    return doc, binary + image


def test_texture_transform_takes_the_extensions_example_to_the_lower_left_quadrant(tmp_path):
    """KHR_texture_transform's own example (offset [0, 1], rotation pi/2, scale 0.5): "only the lower
    left quadrant of the source image, rotated clockwise 90 degrees". glTF's UV origin is the image's
    top left, so that quadrant is u in [0, 0.5], v in [0.5, 1]; the part's UVs are in GL's (v up)."""
    from pipeline25d.formats.gltf import texture_transform

    example = {"offset": [0, 1], "rotation": np.pi / 2, "scale": [0.5, 0.5]}
    corners = texture_transform(np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]]), example)
    assert (corners[:, 0] >= -1e-12).all() and (corners[:, 0] <= 0.5 + 1e-12).all()
    assert (corners[:, 1] >= 0.5 - 1e-12).all() and (corners[:, 1] <= 1 + 1e-12).all()
    # the image's top-left texel goes to the unit square's (0, 1) corner: turned a quarter clockwise
    np.testing.assert_allclose(corners, [[0, 1], [0, 0.5], [0.5, 0.5], [0.5, 1]], atol=1e-12)
    material = {"pbrMetallicRoughness": {"baseColorTexture": {
        "index": 0, "extensions": {"KHR_texture_transform": example}}}}
    doc, binary = _with_image(*_gltf(material=material), _png_bytes(), "image/png")
    doc["textures"] = [{"source": 0}]
    doc["extensionsRequired"] = doc["extensionsUsed"] = ["KHR_texture_transform"]
    part = parse_gltf_bytes(_glb(doc, binary), tmp_path / "t.glb")[0]
    uv = part.uv[np.argsort(part.vertices[:, 0] + 2 * part.vertices[:, 2])]       # TRI's order: x, then up
    expected = texture_transform(TRI_UV.astype(np.float64), example)
    np.testing.assert_allclose(uv, np.column_stack([expected[:, 0], 1 - expected[:, 1]]), atol=1e-6)


def test_triangle_strips_and_fans_give_the_triangles_of_a_list(tmp_path):
    """A quad as a strip (0 1 2 3) and as a fan (0 1 3 2) gives the list's two triangles, wound the
    same way (glTF 2.0, 3.7.2.1)."""
    from pipeline25d.formats.gltf import triangles

    strip = triangles(np.array([0, 1, 2, 3]), 5)
    np.testing.assert_array_equal(strip, [[0, 1, 2], [1, 3, 2]])
    np.testing.assert_array_equal(triangles(np.array([0, 1, 3, 2]), 6), [[1, 3, 0], [3, 2, 0]])
    quad = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], dtype=np.float64)
    for faces in (strip, triangles(np.array([0, 1, 3, 2]), 6)):
        normal = np.cross(quad[faces[:, 1]] - quad[faces[:, 0]], quad[faces[:, 2]] - quad[faces[:, 0]])
        assert (normal[:, 2] > 0).all()                                  # both counter-clockwise, as 0 1 2
    assert len(triangles(np.array([0, 1]), 5)) == 0 == len(triangles(np.array([0, 1]), 6))
    for mode in (5, 6):                                   # the one-triangle glTF read as a strip or a fan
        doc, binary = _gltf(mode=mode)
        parts = load_gltf(_write_gltf(tmp_path / f"m{mode}.gltf", doc, binary), y_up_to_z_up=False)
        np.testing.assert_allclose(parts[0].vertices[parts[0].faces[0]][[0, 1, 2] if mode == 5 else [2, 0, 1]], TRI)


def test_webp_textures(tmp_path):
    """EXT_texture_webp: the WEBP image is read (stored as PNG, the same texels: lossless WEBP; KTX2:
    test_formats_ktx2)."""
    from PIL import Image

    texels = np.random.default_rng(5).integers(0, 256, (8, 8, 3), dtype=np.uint8)
    out = io.BytesIO()
    Image.fromarray(texels).save(out, format="WEBP", lossless=True)
    material = {"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}}
    doc, binary = _with_image(*_gltf(material=material), out.getvalue(), "image/webp")
    doc["textures"] = [{"extensions": {"EXT_texture_webp": {"source": 0}}}]
    doc["extensionsRequired"] = doc["extensionsUsed"] = ["EXT_texture_webp"]
    part = parse_gltf_bytes(_glb(doc, binary), tmp_path / "w.glb")[0]
    assert part.texture[:8] == b"\x89PNG\r\n\x1a\n"
    np.testing.assert_array_equal(np.asarray(Image.open(io.BytesIO(part.texture)).convert("RGB")), texels)


def test_a_webp_cut_short_is_drawn_untextured_with_a_warning_naming_the_image(tmp_path):
    """A WEBP that Pillow cannot decode (cut short) leaves its parts untextured and says which image of
    which file, and why; its RGBA twin keeps its alpha as PNG."""
    from PIL import Image

    from pipeline25d.core.errors import MissingTextureWarning

    texels = np.random.default_rng(6).integers(0, 256, (8, 8, 4), dtype=np.uint8)
    out = io.BytesIO()
    Image.fromarray(texels).save(out, format="WEBP", lossless=True)
    material = {"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}}
    for data, whole in ((out.getvalue(), True), (out.getvalue()[:40], False)):
        doc, binary = _with_image(*_gltf(material=material), data, "image/webp")
        doc["textures"] = [{"extensions": {"EXT_texture_webp": {"source": 0}}}]
        doc["extensionsRequired"] = doc["extensionsUsed"] = ["EXT_texture_webp"]
        if whole:
            part = parse_gltf_bytes(_glb(doc, binary), tmp_path / "w.glb")[0]
            np.testing.assert_array_equal(np.asarray(Image.open(io.BytesIO(part.texture))), texels)
            continue
        with pytest.warns(MissingTextureWarning, match=r"cut\.glb: image 0 cannot be read \(WEBP: .+\); its parts "
                                                       r"are drawn untextured"):
            part = parse_gltf_bytes(_glb(doc, binary), tmp_path / "cut.glb")[0]
        assert part.texture is None


def test_unsupported_required_extension(tmp_path):
    doc, binary = _gltf(extra={"extensionsRequired": ["KHR_example_unknown"]})
    path = _write_gltf(tmp_path / "unknown.gltf", doc, binary)
    with pytest.raises(UnsupportedFeatureError) as err:
        load_gltf(path)
    assert "KHR_example_unknown" in str(err.value) and "unknown.gltf" in str(err.value)


def test_broken_files(tmp_path):
    doc, binary = _gltf()
    glb = _glb(doc, binary)
    (tmp_path / "trunc.glb").write_bytes(glb[:-8])
    with pytest.raises(InputFileError, match="trunc"):
        load_gltf(tmp_path / "trunc.glb")
    (tmp_path / "junk.gltf").write_text("{not json")
    with pytest.raises(InputFileError, match="junk.gltf"):
        load_gltf(tmp_path / "junk.gltf")
    doc["accessors"][0]["count"] = 300  # reads past its buffer view
    with pytest.raises(InputFileError, match="accessor 0"):
        parse_gltf_bytes(_glb(doc, binary), tmp_path / "bad.glb")


# ----------------------------------------------------------------------------- sample files


def test_feature_id_attribute_gltf():
    parts = load_gltf(shared_file(SAMPLES / "FeatureIdAttribute" / "FeatureIdAttribute.gltf"))
    assert sum(p.n_triangles for p in parts) == 8  # SOURCE.txt
    np.testing.assert_array_equal(parts[0].colors[0], [128, 255, 128, 255])  # baseColorFactor 0.5, 1, 0.5
    b = parts[0].bounds()
    np.testing.assert_allclose(b, [[0, 0, 0], [1, 0, 1]])  # unit quads in glTF x/y -> x/z


def test_cdb_glb_with_metadata_extensions_and_missing_textures():
    glb = shared_file(SAMPLES / "cdb-yemen-cut" / "Tiles" / "N12" / "E045" / "GSModels" / "1_1"
                / "N12E045_D300_S001_T001_LC5_U0_R0.glb")
    with pytest.warns(UserWarning, match="FENCE_TEXT2.png"):
        parts = load_gltf(glb)
    assert sum(p.n_triangles for p in parts) == 58  # SOURCE.txt
    assert all(p.texture is None and p.colors is not None for p in parts)
    # ECEF placement comes from the node translation: |p| is an Earth radius
    r = np.linalg.norm(parts[0].vertices, axis=1)
    assert 6.37e6 < r.min() and r.max() < 6.39e6


def _draco_glb(positions: np.ndarray, uv: np.ndarray, component: int = 5126, node: dict | None = None,
               extensions: tuple[str, ...] = (), **encode) -> tuple[dict, bytes]:
    """(doc, binary) of a textured quad of two triangles (0 1 2, 1 3 2) in one Draco primitive:
    ``positions`` and ``uv`` as stored (their accessors of ``component``, normalized where an integer
    type), DracoPy's ``encode`` options; the texture is :func:`_png_bytes`."""
    import DracoPy

    stream = DracoPy.encode(positions, np.array([[0, 1, 2], [1, 3, 2]], np.uint32), tex_coord=uv.astype(np.float64),
                            preserve_order=True, **encode)
    ids = {a["attribute_type"]: a["unique_id"] for a in DracoPy.decode(stream).attributes}
    png = _png_bytes()
    used = ["KHR_draco_mesh_compression", *extensions]
    normalized = {"normalized": True} if component != 5126 else {}
    doc = {
        "asset": {"version": "2.0"}, "extensionsUsed": used, "extensionsRequired": used,
        "nodes": [{"mesh": 0, **(node or {})}],
        "meshes": [{"primitives": [{
            "attributes": {"POSITION": 0, "TEXCOORD_0": 1}, "indices": 2, "material": 0,
            "extensions": {"KHR_draco_mesh_compression": {
                "bufferView": 0, "attributes": {"POSITION": ids[0], "TEXCOORD_0": ids[3]}}}}]}],
        "materials": [{"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}}],
        "textures": [{"source": 0}], "images": [{"bufferView": 1, "mimeType": "image/png"}],
        "accessors": [{"componentType": component, **normalized, "count": 4, "type": "VEC3"},
                      {"componentType": component, **normalized, "count": 4, "type": "VEC2"},
                      {"componentType": 5123, "count": 6, "type": "SCALAR"}],
        "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": len(stream)},
                        {"buffer": 0, "byteOffset": len(stream), "byteLength": len(png)}],
        "buffers": [{"byteLength": len(stream) + len(png)}],
    }
    return doc, stream + png


def test_draco_primitive_by_attribute_id(tmp_path):
    pts = np.array([[0, 0, 0], [2, 0, 0], [0, 3, 0], [2, 3, 0]], dtype=np.float64)
    uv = np.array([[0, 0], [1, 0], [0, 1], [1, 1]], dtype=np.float64)
    doc, binary = _draco_glb(pts, uv)
    png = _png_bytes()
    part = parse_gltf_bytes(_glb(doc, binary), tmp_path / "d.glb", up_axis="Z")[0]
    assert part.n_triangles == 2 and part.texture == png
    np.testing.assert_allclose(part.bounds(), [[0, 0, 0], [2, 3, 0]], atol=1e-3)
    # every vertex's UV is (x / 2, 1 - y / 3): UVs travel with their vertices, v flipped
    np.testing.assert_allclose(part.uv, np.column_stack([part.vertices[:, 0] / 2, 1 - part.vertices[:, 1] / 3]),
                               atol=1e-3)


@pytest.mark.parametrize("edit, message", [
    (lambda d: d["meshes"][0].update(primitives="triangles"), r"glTF JSON holds a value of the wrong type"),
    (lambda d: d["materials"][0].update(pbrMetallicRoughness=[]), r"glTF JSON holds a value of the wrong type"),
    (lambda d: d["meshes"][0]["primitives"][0].update(extensions="KHR"), r"glTF JSON holds a value of the wrong type"),
    (lambda d: d["materials"][0]["pbrMetallicRoughness"]["baseColorTexture"].update(index=-1),
     r"glTF references missing textures\[-1\]")])
def test_json_of_the_wrong_types_is_an_input_error(tmp_path, edit, message):
    """Values of the wrong JSON type (assimp's glTF2/wrongTypes corpus: an array as a string, an object
    as an array, an extension as a string) and a negative index, which Python would take from the end:
    errors naming the file, not an AttributeError or the last texture."""
    pts = np.array([[0, 0, 0], [2, 0, 0], [0, 3, 0], [2, 3, 0]], dtype=np.float64)
    doc, binary = _draco_glb(pts, pts[:, :2] / [2, 3])
    assert parse_gltf_bytes(_glb(doc, binary), tmp_path / "ok.glb")[0].n_triangles == 2
    edit(doc)
    with pytest.raises(InputFileError, match=r"bad\.glb: " + message):
        parse_gltf_bytes(_glb(doc, binary), tmp_path / "bad.glb")


@pytest.mark.parametrize("component, scale", [(5122, 32767), (5120, 127), (5123, 65535)])
def test_draco_over_normalized_integers_is_denormalised(tmp_path, component, scale):
    """KHR_draco_mesh_compression over KHR_mesh_quantization (glTF-Transform's quantize + draco):
    POSITION and TEXCOORD_0 stored as normalized shorts, bytes or unsigned shorts. DracoPy gives the
    stored integers back as floats; they are divided as the accessor says, so a 1.86 m sphere of
    glTF-Transform's fixtures no longer came out 60 km wide."""
    kind = {5122: np.int16, 5120: np.int8, 5123: np.uint16}[component]
    signed = np.dtype(kind).kind == "i"
    unit = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0.5]]) - (0.5 if signed else 0.0)
    stored = np.rint(unit * scale).astype(kind)
    uv = np.rint(np.array([[0, 0], [1, 0], [0, 1], [1, 1]]) * scale * (0.5 if signed else 1)).astype(kind)
    doc, binary = _draco_glb(stored, uv, component, node={"scale": [2.0, 2.0, 2.0]},
                             extensions=("KHR_mesh_quantization",),
                             quantization_bits=16, tex_coord_quantization_bits=16)
    part = parse_gltf_bytes(_glb(doc, binary), tmp_path / "q.glb", up_axis="Z")[0]
    want = 2.0 * np.maximum(stored / scale, -1.0)                         # the node's scale 2 on the unit values
    np.testing.assert_allclose(part.bounds(), [want.min(axis=0), want.max(axis=0)], atol=2.0 * 2 / scale)
    np.testing.assert_allclose(np.sort(part.uv[:, 0]), np.sort(np.maximum(uv[:, 0] / scale, -1.0)), atol=2 / scale)


@pytest.mark.parametrize("rotation_type", ["float", "normalized short"])
def test_gpu_instancing_repeats_the_mesh_at_each_instance(tmp_path, rotation_type):
    """EXT_mesh_gpu_instancing: the node's mesh drawn once per instance, at T * R * S of its
    TRANSLATION, ROTATION (float, or normalised shorts) and SCALE, then the node's own transform
    (scipy's rotation as the independent reference); a mirroring scale keeps front faces front."""
    from itertools import permutations

    from scipy.spatial.transform import Rotation

    translation = np.array([[0, 0, 0], [10, 0, 0], [0, 5, 2]], np.float32)
    quats = Rotation.from_euler("xyz", [[0, 0, 0], [0, 0, 90], [30, 0, 45]], degrees=True).as_quat()
    scale = np.array([[1, 1, 1], [2, 2, 2], [1, -1, 1]], np.float32)
    rotation = (quats.astype(np.float32) if rotation_type == "float"
                else np.round(quats * 32767).astype(np.int16))
    doc, binary = _gltf(node={"translation": [100, 0, 0]})
    accessors = {"TRANSLATION": (translation, 5126, "VEC3", False), "ROTATION": (rotation, 5126 if rotation_type ==
                 "float" else 5122, "VEC4", rotation_type != "float"), "SCALE": (scale, 5126, "VEC3", False)}
    attributes = {}
    for name, (array, component, kind, normalized) in accessors.items():
        doc["bufferViews"].append({"buffer": 0, "byteOffset": len(binary), "byteLength": array.nbytes})
        doc["accessors"].append({"bufferView": len(doc["bufferViews"]) - 1, "componentType": component,
                                 "count": 3, "type": kind, **({"normalized": True} if normalized else {})})
        attributes[name] = len(doc["accessors"]) - 1
        binary += array.tobytes()
    doc["buffers"][0]["byteLength"] = len(binary)
    doc["nodes"][0]["extensions"] = {"EXT_mesh_gpu_instancing": {"attributes": attributes}}
    doc["extensionsUsed"] = doc["extensionsRequired"] = ["EXT_mesh_gpu_instancing"]
    part, = parse_gltf_bytes(_glb(doc, binary), tmp_path / "i.glb", up_axis="Z")
    assert part.n_triangles == 3
    exact = Rotation.from_quat(rotation.astype(np.float64) / (32767 if rotation_type != "float" else 1))
    for i in range(3):
        expected = exact[i].apply(TRI.astype(np.float64) * scale[i]) + translation[i] + [100, 0, 0]
        tri = part.vertices[part.faces[i]]
        assert min(np.abs(tri[list(order)] - expected).max() for order in permutations(range(3))) < 1e-5, i
        normal = np.cross(tri[1] - tri[0], tri[2] - tri[0])
        assert normal @ exact[i].apply([0, 0, 1]) > 0, i     # the mirror (y -> -y) leaves the front at +z


def test_specular_glossiness_diffuse_is_the_base_colour(tmp_path):
    """KHR_materials_pbrSpecularGlossiness (obj2gltf --specularGlossiness, older exporters): its
    diffuse texture and factor are drawn as the base colour, over a metallic-roughness fallback,
    also where the file requires the extension; without a diffuse the part is white, as in glTF."""
    png = _png_bytes()
    gloss = {"diffuseTexture": {"index": 0}, "diffuseFactor": [1.0, 1.0, 1.0, 1.0], "glossinessFactor": 0.2}
    material = {"extensions": {"KHR_materials_pbrSpecularGlossiness": gloss},
                "pbrMetallicRoughness": {"baseColorFactor": [0.0, 0.0, 1.0, 1.0]}}
    doc, binary = _gltf(material=material, image={"uri": "data:image/png;base64," + base64.b64encode(png).decode()},
                        extra={"extensionsUsed": ["KHR_materials_pbrSpecularGlossiness"],
                               "extensionsRequired": ["KHR_materials_pbrSpecularGlossiness"]})
    part = load_gltf(_write_gltf(tmp_path / "gloss.gltf", doc, binary))[0]
    assert part.texture == png and part.uv is not None and part.colors is None

    gloss = {"diffuseFactor": [1.0, 0.5, 0.0, 1.0]}
    doc["materials"] = [{"extensions": {"KHR_materials_pbrSpecularGlossiness": gloss},
                         "pbrMetallicRoughness": {"baseColorFactor": [0.0, 0.0, 1.0, 1.0]}}]
    part = load_gltf(_write_gltf(tmp_path / "factor.gltf", doc, binary))[0]
    assert part.texture is None
    np.testing.assert_array_equal(part.colors, [[255, 128, 0, 255]] * 3)

    doc["materials"] = [{"extensions": {"KHR_materials_pbrSpecularGlossiness": {"glossinessFactor": 0.5}}}]
    part = load_gltf(_write_gltf(tmp_path / "none.gltf", doc, binary))[0]
    np.testing.assert_array_equal(part.colors, [[255, 255, 255, 255]] * 3)
