"""meshopt-compressed glTF (EXT_ / KHR_meshopt_compression) as gltfpack writes it.

The files are made by gltfpack itself (npm, installed by ``make deps``) from an uncompressed
GLB that trimesh writes; each is read back and compared triangle by triangle with that source
as the reader gives it, within the quantization gltfpack applies (14-bit positions, 12-bit
texture coordinates over each mesh's extent). Corrupt and hostile variants are made by
editing the JSON of one such file.
"""

from __future__ import annotations

import json
import struct
import subprocess
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree
from test_formats_gltf import _glb

from pipeline25d.core.errors import InputFileError, UnsupportedFeatureError
from pipeline25d.formats.gltf import load_gltf


def _gltfpack_cli() -> Path:
    from pipeline25d.core.errors import Pipeline25dError
    from pipeline25d.core.node_modules import package_folder

    try:
        return package_folder("gltfpack", ".", ("cli.js",)) / "cli.js"
    except Pipeline25dError as exc:
        pytest.fail(f"gltfpack is not installed: {exc}")


def _gltfpack(src: Path, out: Path, *flags: str) -> Path:
    subprocess.run(["node", str(_gltfpack_cli()), "-i", str(src), "-o", str(out), *flags],
                   check=True, capture_output=True, text=True)
    return out


@pytest.fixture(scope="module")
def source(tmp_path_factory) -> Path:
    """A textured, sloped ground patch and two untextured buildings (one a sphere) as one GLB."""
    import trimesh
    from PIL import Image

    rng = np.random.default_rng(7)
    n = 24
    x, y = np.meshgrid(np.linspace(0, 120, n), np.linspace(0, 80, n))
    z = 0.05 * x + 2 * np.sin(y / 9)
    vertices = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    i = np.arange(n - 1)[:, None] * n + np.arange(n - 1)[None, :]
    faces = np.concatenate([np.stack([i, i + 1, i + n], -1).reshape(-1, 3),
                            np.stack([i + 1, i + n + 1, i + n], -1).reshape(-1, 3)])
    uv = np.column_stack([x.ravel() / 120, y.ravel() / 80])
    image = Image.fromarray(rng.integers(0, 255, (64, 64, 3), dtype=np.uint8))
    ground = trimesh.Trimesh(vertices, faces, visual=trimesh.visual.TextureVisuals(uv=uv, image=image),
                             process=False)
    box = trimesh.creation.box((10, 20, 30))
    box.apply_translation((60, 40, 18))
    box.visual.face_colors = (200, 80, 40, 255)
    dome = trimesh.creation.icosphere(3, 6).apply_translation((20, 20, 10))
    scene = trimesh.Scene()
    for name, mesh in (("ground", ground), ("box", box), ("dome", dome)):
        scene.add_geometry(mesh, name)
    path = tmp_path_factory.mktemp("meshopt") / "source.glb"
    scene.export(path)
    return path


def _triangles(parts) -> np.ndarray:
    return np.concatenate([p.vertices[p.faces] for p in parts])


def _corner_colours(parts) -> np.ndarray:
    """(triangles, 3, 4) RGBA of each corner; NaN for parts without vertex colours."""
    out = []
    for p in parts:
        c = np.full((len(p.faces), 3, 4), np.nan)
        if p.colors is not None:
            c[:] = np.asarray(p.colors, dtype=np.float64)[p.faces]
        out.append(c)
    return np.concatenate(out)


def _match(got: np.ndarray, want: np.ndarray, tol: float) -> np.ndarray:
    """Index of the triangle of ``got`` that each of ``want`` is (its corners within ``tol``),
    checking the pairing is one to one and that each keeps its facing."""
    assert len(got) == len(want)
    dist, idx = cKDTree(got.mean(axis=1)).query(want.mean(axis=1))
    assert dist.max() <= tol
    assert len(np.unique(idx)) == len(want)
    paired = got[idx]
    corners = np.abs(np.sort(paired.reshape(-1, 9), axis=1) - np.sort(want.reshape(-1, 9), axis=1)).max()
    assert corners <= 2 * tol
    normal_got = np.cross(paired[:, 1] - paired[:, 0], paired[:, 2] - paired[:, 0])
    normal_want = np.cross(want[:, 1] - want[:, 0], want[:, 2] - want[:, 0])
    assert (np.einsum("ij,ij->i", normal_got, normal_want) > 0).all()     # winding kept: the same side faces out
    return idx


FLAGS = {
    "ext": ("-c",),
    "ext-cc": ("-cc",),
    "khr": ("-cc", "-ce", "khr"),                # Khronos's name, version 1 of the attribute codec
    "float-positions": ("-cc", "-vpf"),          # positions through the exponential filter
    "interleaved": ("-cc", "-vi"),
    "fallback": ("-cf",),                        # uncompressed copies beside the streams
}


@pytest.mark.parametrize("name", list(FLAGS))
def test_gltfpack_files_give_the_sources_triangles(source, tmp_path, name):
    packed = _gltfpack(source, tmp_path / f"{name}.glb", *FLAGS[name])
    doc = _split(packed.read_bytes())[0]
    ext = "KHR_meshopt_compression" if name == "khr" else "EXT_meshopt_compression"
    assert ext in doc["extensionsUsed"]
    assert (ext in doc.get("extensionsRequired", [])) == (name != "fallback")
    want, got = load_gltf(source), load_gltf(packed)
    tri_want = _triangles(want)
    extent = np.ptp(tri_want.reshape(-1, 3), axis=0).max()
    idx = _match(_triangles(got), tri_want, 2 * extent / (2 ** 14 - 1))
    # the vertex colours (the box's, trimesh's default elsewhere), corner by corner: gltfpack keeps
    # 8 bits, KHR's COLOR filter is within one unit
    colour_want, colour_got = _corner_colours(want), _corner_colours(got)[idx]
    coloured = ~np.isnan(colour_want[:, 0, 0])
    assert (colour_want == (200, 80, 40, 255)).all(axis=-1).sum() == 36      # the box's 12 triangles
    assert not np.isnan(colour_got[coloured]).any()
    assert np.abs(colour_got[coloured] - colour_want[coloured]).max() <= 1


def test_texture_coordinates_and_image_survive(source, tmp_path):
    """The ground's texture: same image, and each corner's UV (12-bit, dequantized through
    KHR_texture_transform) at the source's UV of that corner."""
    packed = _gltfpack(source, tmp_path / "tex.glb", "-cc")
    want = [p for p in load_gltf(source) if p.texture is not None]
    got = [p for p in load_gltf(packed) if p.texture is not None]
    assert len(want) == len(got) == 1
    (w,), (g,) = want, got
    from io import BytesIO

    from PIL import Image

    assert np.array_equal(np.asarray(Image.open(BytesIO(w.texture))), np.asarray(Image.open(BytesIO(g.texture))))
    extent = np.ptp(w.vertices, axis=0).max()
    idx = _match(g.vertices[g.faces], w.vertices[w.faces], 2 * extent / (2 ** 14 - 1))
    # the corners of matched triangles, paired by position
    wv, gv = w.vertices[w.faces].reshape(-1, 3), g.vertices[g.faces[idx]].reshape(-1, 3)
    wuv, guv = w.uv[w.faces].reshape(-1, 2), g.uv[g.faces[idx]].reshape(-1, 2)
    near = cKDTree(gv).query(wv)[1]
    assert np.abs(guv[near] - wuv).max() <= 1.5 / (2 ** 12 - 1)


# ----------------------------------------------------------------------------- hostile variants


def _split(data: bytes) -> tuple[dict, bytes]:
    n = struct.unpack_from("<I", data, 12)[0]
    doc = json.loads(data[20:20 + n])
    m = struct.unpack_from("<I", data, 20 + n)[0]
    return doc, data[28 + n:28 + n + m]


@pytest.fixture(scope="module")
def packed(source, tmp_path_factory) -> tuple[dict, bytes]:
    return _split(_gltfpack(source, tmp_path_factory.mktemp("packed") / "p.glb", "-cc").read_bytes())


def _attribute_view(doc: dict) -> tuple[int, dict]:
    return next((i, v) for i, v in enumerate(doc["bufferViews"])
                if v.get("extensions", {}).get("EXT_meshopt_compression", {}).get("mode") == "ATTRIBUTES")


def _variant(packed, tmp_path, edit) -> Path:
    doc, binary = json.loads(json.dumps(packed[0])), bytearray(packed[1])
    edit(doc, binary)
    path = tmp_path / "bad.glb"
    path.write_bytes(_glb(doc, bytes(binary)))
    return path


def _count_doubled(doc, binary):
    _, view = _attribute_view(doc)
    view["extensions"]["EXT_meshopt_compression"]["count"] *= 2


def _stream_broken(doc, binary):
    _, view = _attribute_view(doc)
    ext = view["extensions"]["EXT_meshopt_compression"]
    binary[ext.get("byteOffset", 0)] = 0x00          # the attribute stream's header byte (0xa0 or 0xa1)


def _huge_count(doc, binary):
    _, view = _attribute_view(doc)
    ext = view["extensions"]["EXT_meshopt_compression"]
    ext["count"] = 2 ** 31
    view["byteLength"] = ext["count"] * ext["byteStride"]


def _unknown_filter(doc, binary):
    _, view = _attribute_view(doc)
    view["extensions"]["EXT_meshopt_compression"]["filter"] = "SPLINE"


def _fallback_read_plain(doc, binary):
    i, view = _attribute_view(doc)
    del view["extensions"]                           # its data now lies in the placeholder buffer


def _stream_outside(doc, binary):
    _, view = _attribute_view(doc)
    view["extensions"]["EXT_meshopt_compression"]["byteOffset"] = len(binary) + 100


@pytest.mark.parametrize("edit, error, words", [
    (_count_doubled, InputFileError, "byteLength"),
    (_stream_broken, InputFileError, "does not decode"),
    (_huge_count, InputFileError, "cannot come from"),
    (_unknown_filter, UnsupportedFeatureError, "SPLINE"),
    (_fallback_read_plain, InputFileError, "fallback"),
    (_stream_outside, InputFileError, "outside its buffer"),
])
def test_broken_meshopt_files_are_refused_naming_file_and_view(packed, tmp_path, edit, error, words):
    path = _variant(packed, tmp_path, edit)
    with pytest.raises(error, match=words) as err:
        load_gltf(path)
    assert "bad.glb" in str(err.value)


# ----------------------------------------------------------------------------- a real photomesh


TOKYO = Path(__file__).resolve().parents[2] / "shared" / "data" / "tokyo-chiyoda-b3dm" / "cesium-rtc-extension.b3dm"


def _corner_rows(parts) -> np.ndarray:
    """Each triangle as its three (x, y, z, u, v) corners, corners and triangles sorted: a
    canonical form that ignores triangle order and where each triangle's corners start."""
    rows = np.concatenate([np.concatenate([p.vertices[p.faces], p.uv[p.faces]], axis=2) for p in parts])
    rows = np.sort(rows.view([("", rows.dtype)] * 5).reshape(len(rows), 3), axis=1).view(rows.dtype)
    rows = rows.reshape(len(rows), 15)
    return rows[np.lexsort(rows.T[::-1])]


def test_a_real_textured_photomesh_packed_by_gltfpack_reads_as_the_original(tmp_path):
    """Tokyo's b3dm (14,756 triangles, 28 JPEG atlases) through gltfpack ``-cc -noq`` (meshopt
    streams of the float positions and UVs, which keep them exact) as 3D Tiles 1.1 content:
    per atlas, the same JPEG bytes and the same triangles, corner by corner, as the original
    tile. gltfpack drops CESIUM_RTC, so the tileset carries that centre as its root transform."""
    from conftest import shared_file

    from pipeline25d.formats.tiles3d import load_b3dm, load_tileset

    data = shared_file(TOKYO).read_bytes()
    length, *tables = struct.unpack_from("<I4I", data, 8)
    glb = data[28 + sum(tables):length]
    centre = _split(glb)[0]["extensions"]["CESIUM_RTC"]["center"]
    (tmp_path / "tile.glb").write_bytes(glb)
    _gltfpack(tmp_path / "tile.glb", tmp_path / "packed.glb", "-cc", "-noq")
    assert "EXT_meshopt_compression" in _split((tmp_path / "packed.glb").read_bytes())[0]["extensionsRequired"]
    tileset = {"asset": {"version": "1.1"}, "geometricError": 1,
               "root": {"geometricError": 0, "refine": "ADD", "content": {"uri": "packed.glb"},
                        "transform": [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, *centre, 1],
                        "boundingVolume": {"sphere": [*centre, 3000]}}}
    (tmp_path / "tileset.json").write_text(json.dumps(tileset))
    crs = "EPSG:6677"                                       # metres: Japan Plane Rectangular IX
    want, got = load_b3dm(TOKYO, crs), load_tileset(tmp_path / "tileset.json", crs)
    assert got.n_triangles == want.n_triangles == 14756
    by_atlas: dict[bytes, dict[str, list]] = {}
    for which, mesh in (("want", want), ("got", got)):
        for p in mesh.parts:
            if p.texture is not None:
                by_atlas.setdefault(p.texture, {}).setdefault(which, []).append(p)
    assert len(by_atlas) == 28 and all(set(v) == {"want", "got"} for v in by_atlas.values())
    for parts in by_atlas.values():
        np.testing.assert_allclose(_corner_rows(parts["got"]), _corner_rows(parts["want"]), rtol=0, atol=1e-6)
