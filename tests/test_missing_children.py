"""Unreachable children of multi-resolution inputs (issue 27): 3D Tiles draw the finest level
present (REPLACE: the parent's content; ADD: the parent, the missing content left out) and note
it, ``missing_children: error`` refuses; tile trees that expand past the limit are refused;
``side_folders`` lets a model name files in named folders outside its own."""

from __future__ import annotations

import json
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest

from pipeline25d.core.errors import ConfigError, InputFileError
from pipeline25d.formats import load_district
from pipeline25d.formats.common import in_context, side_file, side_folders
from pipeline25d.formats.tiles3d import read_tileset
from pipeline25d.formats.tileset_tree import MAX_TILES
from pipeline25d_lab.scenes.badinputs import (
    ECEF_ORIGIN,
    PNG_1PX,
    SCENE_CRS,
    SQUARE,
    SQUARE_FACES,
    write_b3dm,
    write_gltf,
)

SPHERE = {"sphere": [*ECEF_ORIGIN, 100.0]}


def _tile(content: str | None, children: list[dict] | None = None, refine: str | None = None, **extra) -> dict:
    tile = {"boundingVolume": SPHERE, "geometricError": 10 if children else 0, **extra}
    if content:
        tile["content"] = {"uri": content}
    if children:
        tile["children"] = children
    if refine:
        tile["refine"] = refine
    return tile


def _write(path: Path, root: dict) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"asset": {"version": "1.0"}, "geometricError": 10, "root": root}))
    return path


def _square_at(path: Path, z: float) -> None:
    """A b3dm of the 10 m square lifted by ``z`` (which level is drawn shows in the heights)."""
    write_b3dm(path, SQUARE + [0, 0, z], SQUARE_FACES, None)


def _heights(loaded) -> list[float]:
    """The distinct lifts of the drawn squares (the model's z is ECEF z, CESIUM_RTC at ECEF_ORIGIN)."""
    v = np.concatenate([p.vertices for p in loaded.parts])
    return sorted({round(float(z), 3) for z in v[:, 2] - ECEF_ORIGIN[2]})


@pytest.fixture
def replace_tree(tmp_path) -> Path:
    """REPLACE root (square at z 0) refined into two children (squares at z 1 and 2)."""
    for name, z in (("parent", 0.0), ("a", 1.0), ("b", 2.0)):
        _square_at(tmp_path / f"{name}.b3dm", z)
    return _write(tmp_path / "tileset.json", _tile("parent.b3dm", [_tile("a.b3dm"), _tile("b.b3dm")], "REPLACE"))


def test_replace_draws_the_children_and_the_parent_where_one_is_missing(replace_tree):
    assert _heights(read_tileset(replace_tree, {})) == [1.0, 2.0]
    (replace_tree.parent / "b.b3dm").unlink()
    with pytest.warns(UserWarning, match=r"tileset\.json: 1 child content file\(s\) missing, 1 tile\(s\) drawn "
                                         r"coarser than asked, at the finest level present: .*b\.b3dm"):
        loaded = read_tileset(replace_tree, {})
    assert _heights(loaded) == [0.0]          # the parent alone: no child beside it
    assert sum(p.n_triangles for p in loaded.parts) == 2
    (note,) = loaded.coarser
    assert (note.tile, note.level, note.missing) == (str(replace_tree.parent / "parent.b3dm"), 0,
                                                    (str(replace_tree.parent / "b.b3dm"),))
    with pytest.raises(InputFileError, match=r"b\.b3dm: content referenced by .*tileset\.json is missing \(the "
                                             r"input's missing_children: coarser"):
        read_tileset(replace_tree, {"missing_children": "error"})
    # through load_district the note reaches the mesh (and so the chunk index and the report)
    with pytest.warns(UserWarning, match="drawn coarser"):
        mesh = load_district({"path": str(replace_tree)}, SCENE_CRS)
    assert mesh.coarser == loaded.coarser and mesh.n_triangles == 2


def test_a_missing_external_tileset_child_and_a_parent_without_content(tmp_path):
    _square_at(tmp_path / "a.b3dm", 1.0)
    (tmp_path / "sub").mkdir()
    _square_at(tmp_path / "sub" / "c.b3dm", 3.0)
    _write(tmp_path / "sub" / "ext.json", _tile("c.b3dm"))
    root = _write(tmp_path / "tileset.json", _tile(None, [_tile("a.b3dm"), _tile("sub/ext.json"),
                                                          _tile("gone/ext.json")], "REPLACE"))
    with pytest.warns(UserWarning, match="1 child content file"):
        loaded = read_tileset(root, {})
    assert _heights(loaded) == [1.0, 3.0]     # nothing coarser to draw: the reachable children are
    (note,) = loaded.coarser
    assert note.missing == (str(tmp_path / "gone" / "ext.json"),) and note.drawn.startswith("nothing there")


def test_add_leaves_out_only_the_missing_content(tmp_path):
    for name, z in (("parent", 0.0), ("a", 1.0), ("grand", 2.0)):
        _square_at(tmp_path / f"{name}.b3dm", z)
    root = _write(tmp_path / "tileset.json",
                  _tile("parent.b3dm", [_tile("a.b3dm"), _tile("lost.b3dm", [_tile("grand.b3dm")])], "ADD"))
    with pytest.warns(UserWarning, match="1 child content file"):
        loaded = read_tileset(root, {})
    assert _heights(loaded) == [0.0, 1.0, 2.0]   # the lost tile's own child still adds its content
    assert loaded.coarser[0].drawn.startswith("the parent tile's content, the missing content left out")


def test_the_same_external_tileset_twice_is_drawn_twice_where_each_places_it(tmp_path):
    _square_at(tmp_path / "c.b3dm", 0.0)
    _write(tmp_path / "ext.json", _tile("c.b3dm"))
    lift = [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 5.0, 1]   # column-major: 5 m along ECEF z
    root = _write(tmp_path / "tileset.json", _tile(None, [_tile("ext.json"), _tile("ext.json", transform=lift)]))
    assert _heights(read_tileset(root, {})) == [0.0, 5.0]


def test_a_tree_expanding_past_the_limit_is_refused_with_the_count(tmp_path):
    """ten names of a tileset that names ten ... six deep: 10^6 tiles from seven small files."""
    _square_at(tmp_path / "c.b3dm", 0.0)
    _write(tmp_path / "f6.json", _tile("c.b3dm"))
    for k in range(5, -1, -1):
        _write(tmp_path / f"f{k}.json", _tile(None, [_tile(f"f{k + 1}.json") for _ in range(10)]))
    with pytest.raises(InputFileError, match=rf"f0\.json: the tile tree expands to more than {MAX_TILES} tiles"):
        read_tileset(tmp_path / "f0.json", {})


def test_a_texture_folder_shared_at_the_root_of_a_tileset_needs_no_option(tmp_path):
    (tmp_path / "textures").mkdir()
    (tmp_path / "textures" / "t.png").write_bytes(PNG_1PX)
    (tmp_path / "tiles").mkdir()
    write_gltf(tmp_path / "tiles" / "a.gltf", SQUARE, SQUARE_FACES, "../textures/t.png")
    at = [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, *ECEF_ORIGIN, 1]
    root = _write(tmp_path / "tileset.json", _tile("tiles/a.gltf", transform=at))
    mesh = load_district({"path": str(root)}, SCENE_CRS)
    assert [p.texture for p in mesh.parts] == [PNG_1PX]


def test_side_folders_admit_a_texture_folder_outside_the_model_folder(tmp_path):
    (tmp_path / "shared").mkdir()
    (tmp_path / "shared" / "t.png").write_bytes(PNG_1PX)
    model = tmp_path / "models" / "a" / "model.gltf"
    model.parent.mkdir(parents=True)
    write_gltf(model, SQUARE, SQUARE_FACES, "../../shared/t.png")
    with pytest.raises(InputFileError, match=r"model\.gltf: image 0 '\.\./\.\./shared/t\.png' lies outside the "
                                             r"dataset folder .*side_folders"):
        load_district({"path": str(model)}, SCENE_CRS)
    mesh = load_district({"path": "models/a/model.gltf", "side_folders": ["shared"]}, SCENE_CRS, base_dir=tmp_path)
    assert [p.texture for p in mesh.parts] == [PNG_1PX]
    with pytest.raises(ConfigError, match="side_folders names .*nowhere, which is not a folder"):
        load_district({"path": str(model), "side_folders": [str(tmp_path / "nowhere")]}, SCENE_CRS)


def test_side_folders_reach_the_threads_a_reader_starts(tmp_path):
    (tmp_path / "model").mkdir()
    (tmp_path / "shared").mkdir()
    check = in_context(side_file)
    job = ("../shared/t.png", tmp_path / "model", tmp_path / "model", tmp_path / "model" / "m.osgb", "texture", False)
    with side_folders([tmp_path / "shared"]), ThreadPoolExecutor(2) as pool:
        assert list(pool.map(in_context(side_file), [job, job])) == [tmp_path / "model" / "../shared/t.png"] * 2
    with ThreadPoolExecutor(1) as pool, pytest.raises(InputFileError, match="lies outside"):
        list(pool.map(check, [job]))
