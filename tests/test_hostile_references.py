"""Side files stay inside the input's folder, and tile trees of any depth are walked without
recursion (issue 27): glTF buffers and images, 3D Tiles contents and external tilesets."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import numpy as np
import pytest

from pipeline25d.core.errors import InputFileError, UnsupportedFeatureError
from pipeline25d.formats import detect_format, load_district
from pipeline25d.formats.common import side_file
from pipeline25d_lab.scenes.badinputs import (
    ECEF_ORIGIN,
    PNG_1PX,
    SCENE_CRS,
    SQUARE,
    SQUARE_FACES,
    gltf_parts,
    tileset,
    write_b3dm,
    write_gltf,
)

#: paths opened while ``_OPENED`` collects (an audit hook sees every open, whoever calls it)
_OPENED: list[str] | None = None


def _audit(event: str, args: tuple) -> None:
    if _OPENED is not None and event == "open" and isinstance(args[0], (str, bytes, os.PathLike)):
        _OPENED.append(os.fsdecode(args[0]))


sys.addaudithook(_audit)


def _opened_while(call) -> list[str]:
    """Every path opened while ``call()`` runs (its exception, if any, re-raised after)."""
    global _OPENED
    _OPENED = []
    try:
        call()
    finally:
        opened, _OPENED = _OPENED, None
    return opened


def _area(mesh) -> float:
    return sum(0.5 * float(np.linalg.norm(np.cross(p.vertices[p.faces[:, 1]] - p.vertices[p.faces[:, 0]],
                                                   p.vertices[p.faces[:, 2]] - p.vertices[p.faces[:, 0]]),
                                          axis=1).sum()) for p in mesh.parts)


def _gltf_naming(path: Path, buffer_uri: str, image_uri: str | None = None) -> Path:
    doc, binary = gltf_parts(SQUARE, SQUARE_FACES, image_uri)
    doc["buffers"][0]["uri"] = buffer_uri
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(doc))
    return binary


# --------------------------------------------------------------------------- glTF


def test_a_gltf_buffer_climbing_out_of_its_folder_is_refused_and_never_opened(tmp_path):
    outside = tmp_path / "somewhere" / "buf.bin"
    outside.parent.mkdir()
    model = tmp_path / "handed" / "over" / "model.gltf"
    outside.write_bytes(_gltf_naming(model, "../../somewhere/buf.bin"))
    with pytest.raises(InputFileError) as err:
        _opened_while(lambda: load_district({"path": str(model)}, SCENE_CRS))
    assert str(err.value).startswith(f"{model}: buffer 0 '../../somewhere/buf.bin' lies outside the dataset "
                                     f"folder {model.parent}")
    opened = _opened_while(lambda: pytest.raises(InputFileError, load_district, {"path": str(model)}, SCENE_CRS))
    assert str(model) in opened and not any(p.endswith("buf.bin") for p in opened)
    # the same buffer beside the model: read, 100 m² (10 m x 10 m)
    (model.parent / "buf.bin").write_bytes(outside.read_bytes())
    _gltf_naming(model, "buf.bin")
    assert _area(load_district({"path": str(model)}, SCENE_CRS)) == pytest.approx(100.0)


@pytest.mark.parametrize("uri, error, problem", [
    ("{outside}", InputFileError, "lies outside the dataset folder"),                   # absolute path
    ("file://{outside}", InputFileError, "lies outside the dataset folder"),
    ("https://example.org/buf.bin", UnsupportedFeatureError, "is remote; pipeline25d reads local files only"),
    ("link/buf.bin", InputFileError, "lies outside the dataset folder"),                # a symlinked folder
])
def test_absolute_file_remote_and_symlinked_references_are_refused(tmp_path, uri, error, problem):
    outside = tmp_path / "outside" / "buf.bin"
    outside.parent.mkdir()
    model = tmp_path / "model" / "model.gltf"
    outside.write_bytes(_gltf_naming(model, uri.format(outside=outside)))
    (model.parent / "link").symlink_to(outside.parent, target_is_directory=True)
    with pytest.raises(error, match=problem) as err:
        load_district({"path": str(model)}, SCENE_CRS)
    assert type(err.value) is error and str(err.value).startswith(f"{model}: buffer 0 ")


def test_an_image_outside_the_folder_is_not_read_and_is_a_missing_texture(tmp_path):
    """Never read; an error naming it and why by default; with missing_textures: untextured the model
    is drawn without it (a texture path from the exporter's machine need not stop a city), warned."""
    (tmp_path / "secret.png").write_bytes(PNG_1PX)
    model = tmp_path / "model" / "model.gltf"
    model.parent.mkdir()
    write_gltf(model, SQUARE, SQUARE_FACES, "../secret.png")
    with pytest.raises(InputFileError, match=r"model\.gltf: image 0 '\.\./secret\.png' lies outside .*side_folders"):
        load_district({"path": str(model)}, SCENE_CRS)
    with pytest.warns(UserWarning, match=r"model\.gltf: image 0 '\.\./secret\.png' lies outside the dataset folder"):
        mesh = load_district({"path": str(model), "missing_textures": "untextured"}, SCENE_CRS)
    assert mesh.n_triangles == 2 and all(p.texture is None for p in mesh.parts)


def test_side_file_keeps_dot_dot_inside_the_root(tmp_path):
    root = tmp_path / "set"
    (root / "a").mkdir(parents=True)
    got = side_file("../b/c%20d.bin", root / "a", root, root / "a" / "t.json", "content")
    assert got == root / "a" / ".." / "b" / "c d.bin"
    assert side_file("x%20y.png", root, root, root / "m.gml", "texture", url=False) == root / "x%20y.png"


def test_side_file_takes_a_name_in_another_letter_case_only_where_it_is_the_one(tmp_path):
    """A model made where file names ignore case (Windows, macOS; a 3DS file's DOS names) names
    ``Tex/WALL.JPG`` for ``tex/wall.jpg``: that file, with a warning. Two files of that name in
    different cases leave nothing to choose by, and a link of another case still may not lead out."""
    root = tmp_path / "set"
    (root / "tex").mkdir(parents=True)
    (root / "tex" / "wall.jpg").write_bytes(PNG_1PX)
    with pytest.warns(UserWarning, match=r"m\.obj: texture 'Tex/WALL\.JPG' is 'tex/wall\.jpg' on disk \(the letter"):
        assert side_file("Tex/WALL.JPG", root, root, root / "m.obj", "texture", url=False) == root / "tex" / "wall.jpg"
    (root / "tex" / "Wall.jpg").write_bytes(PNG_1PX)
    assert side_file("tex/WALL.jpg", root, root, root / "m.obj", "texture", url=False) == root / "tex" / "WALL.jpg"
    (tmp_path / "secret.png").write_bytes(PNG_1PX)
    (root / "Secret.PNG").symlink_to(tmp_path / "secret.png")
    with pytest.raises(InputFileError, match="lies outside the dataset folder"):
        side_file("secret.png", root, root, root / "m.obj", "texture", url=False)


# --------------------------------------------------------------------------- 3D Tiles


def _tile_json(content: str | None, children: list[dict] | None = None) -> dict:
    return tileset(content, children)


def test_a_tileset_may_name_a_sibling_inside_its_root_but_nothing_outside_it(tmp_path):
    root = tmp_path / "set"
    (root / "shared").mkdir(parents=True)
    (root / "sub").mkdir()
    write_b3dm(root / "shared" / "tile.b3dm", SQUARE, SQUARE_FACES, None)
    (root / "sub" / "part.json").write_text(json.dumps(_tile_json("../shared/tile.b3dm")))
    (root / "tileset.json").write_text(json.dumps(_tile_json("sub/part.json")))
    mesh = load_district({"path": str(root / "tileset.json")}, SCENE_CRS)
    assert mesh.n_triangles == 2 and _area(mesh) == pytest.approx(100.0, rel=2e-3)   # UTM scale
    # the external tileset alone is its own dataset: ../shared is outside its folder
    with pytest.raises(InputFileError, match=r"sub/part\.json: content '\.\./shared/tile\.b3dm' lies outside "
                                             r"the dataset folder .*/set/sub"):
        load_district({"path": str(root / "sub" / "part.json")}, SCENE_CRS)


LEVELS_PER_FILE = 400   # explicit children per tileset file (Python's json reads about 490)


def _chain(folder: Path, files: int, back_to: str | None = None) -> Path:
    """t0.json -> t1.json -> ... -> t<files-1>.json: each holds LEVELS_PER_FILE levels of
    children, its deepest tile naming the next file as an external tileset; the last one's
    deepest tile draws the square, or with ``back_to`` names that tileset again (a cycle)."""
    folder.mkdir()
    write_b3dm(folder / "tile.b3dm", SQUARE, SQUARE_FACES, None)
    for k in range(files):
        content = (back_to or "tile.b3dm") if k == files - 1 else f"t{k + 1}.json"
        tile: dict = {"geometricError": 0, "content": {"uri": content}}
        for _ in range(LEVELS_PER_FILE - 1):
            tile = {"geometricError": 1, "children": [tile]}
        (folder / f"t{k}.json").write_text(json.dumps({"asset": {"version": "1.0"}, "geometricError": 1,
                                                       "root": tile}))
    return folder / "t0.json"


def test_five_thousand_levels_of_tiles_are_walked_without_recursion(tmp_path):
    files = 13   # 5200 levels: explicit children and external tilesets
    mesh = load_district({"path": str(_chain(tmp_path / "deep", files))}, SCENE_CRS)
    assert files * LEVELS_PER_FILE > 5 * sys.getrecursionlimit() and mesh.n_triangles == 2
    from pipeline25d.core.crs import transform_points

    expected = transform_points(SQUARE + np.array(ECEF_ORIGIN), "EPSG:4978", SCENE_CRS)   # the square at its RTC centre
    got = np.concatenate([p.vertices for p in mesh.parts])
    np.testing.assert_allclose(got[np.lexsort(got.T)], expected[np.lexsort(expected.T)], atol=1e-3)


def test_a_cycle_of_external_tilesets_at_depth_is_refused(tmp_path):
    with pytest.raises(InputFileError, match=r"loop/t3\.json: external tilesets form a cycle "
                                             r"\(t3\.json -> t4\.json -> .* -> t12\.json -> t3\.json\)"):
        load_district({"path": str(_chain(tmp_path / "loop", 13, back_to="t3.json"))}, SCENE_CRS)


def test_one_json_nested_five_thousand_levels_deep_is_refused_naming_it(tmp_path):
    leaf = '{"geometricError": 0, "content": {"uri": "tile.b3dm"}}'
    root = '{"geometricError": 1, "children": [' * 5000 + leaf + "]}" * 5000   # too deep for json.dumps too
    path = tmp_path / "deep.json"
    path.write_text('{"asset": {"version": "1.0"}, "geometricError": 1, "root": ' + root + "}")
    for call in (lambda: detect_format(path), lambda: load_district({"path": str(path), "format": "3dtiles"},
                                                                    SCENE_CRS)):
        with pytest.raises(InputFileError, match=r"deep\.json: JSON nested deeper than the JSON reader allows"):
            call()


def test_an_obj_texture_outside_its_folder_is_refused_and_never_opened(tmp_path):
    from pipeline25d_lab.scenes.badinputs import write_obj

    (tmp_path / "secret.png").write_bytes(PNG_1PX)
    model = tmp_path / "model" / "house.obj"
    model.parent.mkdir()
    write_obj(model, SQUARE, SQUARE_FACES, "../secret.png")
    with pytest.raises(InputFileError, match=r"house\.obj: texture '\.\./secret\.png' lies outside the dataset"):
        opened = _opened_while(lambda: load_district({"path": str(model), "missing_textures": "untextured"},
                                                     SCENE_CRS))
    opened = _opened_while(lambda: pytest.raises(InputFileError, load_district, {"path": str(model)}, SCENE_CRS))
    assert not any(p.endswith("secret.png") for p in opened), opened


def test_a_cityjson_texture_outside_the_model_folder_is_not_read(tmp_path):
    """A CityJSON appearance image that climbs out of the model's folder is never read: a missing texture,
    an error naming it by default, drawn untextured (warned) where missing textures are allowed."""
    from pipeline25d.formats import load_district

    model = tmp_path / "city"
    model.mkdir()
    (tmp_path / "secret.png").write_bytes(b"not for the model")
    doc = {"type": "CityJSON", "version": "2.0", "transform": {"scale": [1, 1, 1], "translate": [0, 0, 0]},
           "metadata": {"referenceSystem": "https://www.opengis.net/def/crs/EPSG/0/7415"},
           "vertices": [[0, 0, 0], [1, 0, 0], [1, 1, 0]],
           "appearance": {"textures": [{"type": "PNG", "image": "../secret.png"}],
                          "vertices-texture": [[0, 0], [1, 0], [1, 1]]},
           "CityObjects": {"b": {"type": "Building", "geometry": [{
               "type": "MultiSurface", "lod": "2", "boundaries": [[[0, 1, 2]]],
               "texture": {"t": {"values": [[[0, 0, 1, 2]]]}}}]}}}
    path = model / "city.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(InputFileError, match=r"city\.json: texture image \.\./secret\.png lies outside the dataset"):
        load_district({"path": str(path)}, "EPSG:7415")
    with pytest.warns(UserWarning, match=r"\.\./secret\.png lies outside the dataset folder"):
        mesh = load_district({"path": str(path), "missing_textures": "untextured"}, "EPSG:7415")
    assert mesh.n_triangles == 1 and all(p.texture is None for p in mesh.parts)
