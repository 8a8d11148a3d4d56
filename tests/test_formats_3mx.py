"""Bentley 3MX scenes (ContextCapture's .3mx + .3mxb), their OpenCTM meshes written by OpenCTM's own ctmconv.

The generated scene (pipeline25d_lab.scenes.threemx_sample) has exact truth: two tiles, each a coarse
quad in the root file and a fine grid with a peak in a child file, relative to SRSOrigin in EPSG:28992.
"""

from __future__ import annotations

import json
import os
import struct
import warnings

import numpy as np
import pytest

from pipeline25d.core.errors import InputFileError, MissingTextureWarning
from pipeline25d.formats import detect_format, load_district
from pipeline25d.formats.common import Detail
from pipeline25d.formats.openctm import decode_ctm
from pipeline25d.formats.threemx import read_3mx
from pipeline25d_lab.scenes import threemx_sample as sample

ORIGIN = np.array(sample.ORIGIN)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return sample.write_3mx_scene(tmp_path_factory.mktemp("threemx"))


def _load(path, gsd, **spec):
    return load_district({"path": str(path), **spec}, "EPSG:28992", gsd=gsd)


def _copy(scene, folder):
    """A copy of the scene in ``folder``: (its root .3mxb, that file's bytes, its header's length)."""
    import shutil

    shutil.copytree(scene.parent, folder)
    root = folder / "Data" / "root.3mxb"
    good = root.read_bytes()
    return root, good, struct.unpack_from("<I", good, 5)[0]


def test_ctm_meshes_decode_to_what_ctmconv_was_given():
    """RAW exactly; MG2 within its 1 mm vertex and 1e-4 UV precision; the triangles the same set
    of corners (MG2 reorders vertices)."""
    vertices, faces, uv = sample.fine_mesh(0.0)
    raw = decode_ctm(sample.ctm_bytes(vertices, faces, uv, "RAW"))
    np.testing.assert_allclose(raw.vertices, vertices, atol=1e-5)
    np.testing.assert_array_equal(raw.faces, faces)
    np.testing.assert_allclose(raw.uv, uv, atol=1e-6)
    mg2 = decode_ctm(sample.ctm_bytes(vertices, faces, uv, "MG2"))
    got = {tuple(np.round(mg2.vertices[f], 2).ravel()) for f in mg2.faces}
    want = {tuple(np.round(vertices[f], 2).ravel()) for f in faces}
    corners = lambda tris: {frozenset(map(tuple, np.reshape(t, (3, 3)))) for t in tris}  # noqa: E731
    assert corners(got) == corners(want)
    near = np.abs(mg2.vertices[:, None, :] - vertices[None, :, :]).max(-1).min(1)
    assert near.max() <= 0.001
    assert len(mg2.uv) == len(mg2.vertices)


@pytest.mark.parametrize("gsd, fine", [(1.0, False), (0.5, True), (0.25, True), (None, True)])
def test_the_level_drawn_follows_max_screen_diameter(scene, gsd, fine):
    """A tile's box (50 x 50 m, its peak 6 m above the grid: diagonal 71.0 m) covers 71 px at gsd 1 and
    142 px at 0.5: below and above its maxScreenDiameter of 100 px. Its coarse quad, then its fine
    grid is drawn (full detail: the fine), placed at SRSOrigin + the mesh's coordinates."""
    diagonal = np.linalg.norm([sample.TILE_M, sample.TILE_M, 6.0])
    assert fine == (gsd is None or diagonal / gsd >= sample.MAX_SCREEN_DIAMETER)
    mesh = _load(scene, gsd)
    assert mesh.n_triangles == 2 * (2 * sample.GRID ** 2 if fine else 2)
    vertices = np.concatenate([p.vertices for p in mesh.parts])
    lo, hi = vertices.min(0) - ORIGIN, vertices.max(0) - ORIGIN
    np.testing.assert_allclose(lo, [0, 0, 1], atol=1e-3)
    np.testing.assert_allclose(hi, [2 * sample.TILE_M, sample.TILE_M, 7.0 if fine else 1.0], atol=1e-3)
    kind = b"\x89PNG" if fine else b"\xff\xd8\xff"
    assert all(p.texture.startswith(kind) and len(p.uv) == len(p.vertices) for p in mesh.parts)


def test_the_format_is_told_by_its_suffix_and_the_crs_by_the_layer(scene):
    assert detect_format(scene) == "3mx" == detect_format(scene.parent / "Data" / "root.3mxb")
    assert read_3mx(scene, {}, Detail(None, 1.0)).crs == "EPSG:28992"
    assert read_3mx(scene, {"crs": "EPSG:7415"}, Detail(None, 1.0)).crs == "EPSG:7415"     # the input's key wins
    # a .3mxb alone has no SRS: its coordinates are the mesh's, in the input's crs
    alone = _load(scene.parent / "Data" / "root.3mxb", 1.0, crs="EPSG:28992", offset=list(sample.ORIGIN))
    np.testing.assert_allclose(np.concatenate([p.vertices for p in alone.parts]).min(0), ORIGIN + [0, 0, 1], atol=1e-3)


def test_a_missing_child_file_draws_that_tile_coarser_with_a_warning(scene, tmp_path):
    copy = tmp_path / "s"
    _copy(scene, copy)
    (copy / "Data" / "Tile_+001_+000" / "Tile_+001_+000_L1.3mxb").unlink()
    with pytest.warns(UserWarning, match=r"Tile_\+001_\+000: 1 3MX child file\(s\) missing, drawn coarser than gsd "
                                         r"0.25 asks for: Tile_\+001_\+000/Tile_\+001_\+000_L1.3mxb \(level 0 drawn\)"):
        mesh = _load(copy / "scene.3mx", 0.25)
    assert sorted(len(p.faces) for p in mesh.parts) == [2, 2 * sample.GRID ** 2]
    with pytest.raises(InputFileError, match=r"root\.3mxb: node 'Tile_\+001_\+000': child file\(s\) missing"):
        _load(copy / "scene.3mx", 0.25, missing_children="error")


def test_broken_files_are_errors_naming_them(scene, tmp_path):
    copy = tmp_path / "b"
    root, good, size = _copy(scene, copy)
    cases = {
        b"3MXBX" + good[5:]: "no 3MXBO magic",
        good[:5] + struct.pack("<I", len(good)) + good[9:]: "its header claims",
        good[:-100]: r"resource 'g1' \(\d+ bytes\) runs past the file's end",
        good[:9] + b"x" + good[10:]: "its header is not valid JSON",
    }
    for data, message in cases.items():
        root.write_bytes(data)
        with pytest.raises(InputFileError, match=rf"root\.3mxb.*{message}"):
            _load(copy / "scene.3mx", 1.0)
    header = json.loads(good[9:9 + size])
    ctm = header["resources"][1]
    offset = 9 + size + sum(r["size"] for r in header["resources"][:1])
    root.write_bytes(good[:offset] + b"OCTM" + bytes(ctm["size"] - 4) + good[offset + ctm["size"]:])
    with pytest.raises(InputFileError, match=r"root\.3mxb: geometry 'g0': OpenCTM: CTM_UNSUPPORTED_FORMAT_VERSION"):
        _load(copy / "scene.3mx", 1.0)
    scene_file = copy / "scene.3mx"
    scene_file.write_text(json.dumps({"3mxVersion": 1, "layers": [{"type": "meshPyramid", "root": "../x.3mxb"}]}))
    with pytest.raises(InputFileError, match="outside the dataset folder"):
        _load(scene_file, 1.0)
    scene_file.write_text(json.dumps({"3mxVersion": 2, "layers": []}))
    with pytest.raises(InputFileError, match="3mxVersion 2"):
        _load(scene_file, 1.0)


def test_an_unreadable_texture_is_a_missing_texture(scene, tmp_path):
    """A texture buffer that is not an image: an error by default, untextured with missing_textures: untextured."""
    copy = tmp_path / "t"
    root, good, size = _copy(scene, copy)
    start = 9 + size                                          # the first resource: tile 0's JPEG
    n = json.loads(good[9:start])["resources"][0]["size"]
    root.write_bytes(good[:start] + bytes(n) + good[start + n:])
    with pytest.raises(InputFileError, match=r"root\.3mxb: texture 't0' is neither JPEG nor PNG"):
        _load(copy / "scene.3mx", 1.0)
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        mesh = _load(copy / "scene.3mx", 1.0, missing_textures="untextured")
    assert any(issubclass(w.category, MissingTextureWarning) for w in seen)
    assert sorted(p.texture is None for p in mesh.parts) == [False, True]


def _texture_as_file(scene, copy, image):
    """A copy of the scene whose tile 0 texture (a buffer) is the textureFile ``image`` instead; its root."""
    root, good, size = _copy(scene, copy)
    start = 9 + size
    header = json.loads(good[9:start])
    res = header["resources"][0]                          # tile 0's JPEG, a buffer
    n = res.pop("size")
    image.write_bytes(good[start:start + n])
    res.update(type="textureFile", file=os.path.relpath(image, root.parent))
    text = json.dumps(header).encode()
    root.write_bytes(b"3MXBO" + struct.pack("<I", len(text)) + text + good[start + n:])
    return root


def test_a_texture_file_in_another_letter_case_is_read_and_warned_of_once(scene, tmp_path):
    copy = tmp_path / "t"
    root = _texture_as_file(scene, copy, copy / "Data" / "tex0.jpg")
    (copy / "Data" / "tex0.jpg").rename(copy / "Data" / "Tex0.jpg")
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        mesh = _load(copy / "scene.3mx", 1.0)
    assert [str(w.message) for w in seen if "letter case" in str(w.message)] == [
        f"{root}: texture file 'tex0.jpg' is 'Tex0.jpg' on disk (the letter case differs); that file is used"]
    assert all(p.texture is not None for p in mesh.parts)


def test_a_texture_file_outside_the_dataset_folder_is_a_missing_texture(scene, tmp_path):
    """A textureFile resource that leads out of the folder (an exporter's path on its own machine)
    is never read, even where it is a good image: an error naming it by default, untextured with
    missing_textures: untextured, as a glTF, CityGML or CityJSON image there is."""
    copy = tmp_path / "t"
    _texture_as_file(scene, copy, tmp_path / "outside.jpg")
    with pytest.raises(InputFileError, match=r"root\.3mxb: texture 't0' lies outside the dataset folder .*"
                                             r"missing_textures"):
        _load(copy / "scene.3mx", 1.0)
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        mesh = _load(copy / "scene.3mx", 1.0, missing_textures="untextured")
    assert [str(w.message) for w in seen if issubclass(w.category, MissingTextureWarning)]
    assert sorted(p.texture is None for p in mesh.parts) == [False, True]


def test_the_box_before_reading_is_the_root_nodes_boxes_and_no_objects_are_named(scene):
    """The work estimate's box (read from the root file alone) holds the mesh read at full detail;
    a photogrammetry scene names no objects (no id maps by default)."""
    from pipeline25d.formats.boxes import input_box
    from pipeline25d.formats.has_objects import input_has_objects

    box = input_box({"path": str(scene)})
    vertices = np.concatenate([p.vertices for p in _load(scene, None).parts])
    assert box.crs == "EPSG:28992"
    np.testing.assert_allclose(box.corners, [vertices.min(0), vertices.max(0)], atol=1e-3)
    assert not input_has_objects({"path": str(scene)})


def test_a_root_of_one_node_over_the_tiles_is_read_a_tile_at_a_time(tmp_path):
    """A root file whose one node spans both tiles (diagonal 112 m): at gsd 1 (112 px, over its 100)
    the tiles' files replace it and each is a piece of its own, so memory follows a tile, each tile
    drawn at its own level (71 px: coarse; at 0.25 fine); at gsd 2 (56 px) the root's own quad under
    them is drawn, one piece."""
    from pipeline25d.formats.threemx import read_3mx_pieces

    scene = sample.write_3mx_scene(tmp_path / "one", one_root=True)

    def triangles(gsd):
        return [sum(len(p.faces) for p in piece.parts) for piece in read_3mx_pieces(scene, {}, Detail(None, gsd))]

    assert triangles(0.25) == [2 * sample.GRID ** 2] * 2
    assert triangles(1.0) == [2, 2]
    assert triangles(2.0) == [2]
    (low,) = read_3mx_pieces(scene, {}, Detail(None, 2.0))
    np.testing.assert_allclose(low.parts[0].vertices[:, 2], sample.ORIGIN[2], atol=1e-6)   # the quad at z = 0
