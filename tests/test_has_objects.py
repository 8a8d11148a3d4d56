"""``objects.enabled: auto`` (pipeline25d.formats.has_objects, config.objects_enabled): the peek
that tells, before ingest, whether an input names objects, checked against what the readers
themselves find (feature ids on the parts they return), on the shared 3D Tiles and on generated
tiles of every content kind; and in the DAG: a surface-only scene makes no id layer."""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import shared_file
from test_workflow import job_counts, make_scene, snakemake

from pipeline25d.config import objects_enabled, validate_schema
from pipeline25d.formats import READERS, detect_format
from pipeline25d.formats.common import Detail
from pipeline25d.formats.has_objects import input_has_objects
from pipeline25d_lab.scenes.model_writers import (
    b3dm_bytes,
    glb_bytes,
    gltf_parts,
    tileset,
    write_obj,
    write_ply,
    write_tileset,
)

SHARED = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"
SHARED_TILESETS = sorted(p for p in (SHARED / "3dtiles-samples").glob("*/tileset.json")) + \
    [SHARED / "tokyo-chiyoda-b3dm" / "cesium-rtc-extension.b3dm"]

V = np.array([[0, 0, 0], [10, 0, 0], [0, 10, 0], [10, 10, 1]], float)
F = np.array([[0, 1, 2], [1, 3, 2]])


def reader_finds_features(path: Path) -> bool:
    """The second method: whether the format's own reader returns parts with feature ids."""
    fmt = detect_format(path)
    parts = READERS[fmt].load(path, {"path": str(path)}, Detail()).parts
    return any(p.face_objects is not None for p in parts)


@pytest.mark.parametrize("path", SHARED_TILESETS, ids=lambda p: p.parent.name)
def test_the_peek_agrees_with_the_reader_on_the_shared_tilesets(path):
    shared_file(path)
    peek, reader = input_has_objects({"path": str(path)}), reader_finds_features(path)
    if path.parent.name == "SparseImplicitQuadtree":     # no root content to peek at: counted as objects
        assert peek and not reader
    else:
        assert peek == reader


def _glb(batch_ids: bool = False, mesh_features: bool = False) -> bytes:
    doc, binary = gltf_parts(V, F, None)
    prim = doc["meshes"][0]["primitives"][0]
    if batch_ids or mesh_features:
        ids = np.array([0, 0, 1, 1], "<f4").tobytes()
        doc["bufferViews"].append({"buffer": 0, "byteOffset": len(binary), "byteLength": len(ids)})
        doc["accessors"].append({"bufferView": len(doc["bufferViews"]) - 1, "componentType": 5126, "count": 4,
                                 "type": "SCALAR"})
        binary += ids
        doc["buffers"][0]["byteLength"] = len(binary)
        name = "_BATCHID" if batch_ids else "_FEATURE_ID_0"
        prim["attributes"][name] = len(doc["accessors"]) - 1
        if mesh_features:
            prim["extensions"] = {"EXT_mesh_features": {"featureIds": [{"featureCount": 2, "attribute": 0}]}}
            doc["extensionsUsed"] = ["EXT_mesh_features"]
    return glb_bytes(doc, binary)


def _b3dm_with_batch(n: int, glb: bytes) -> bytes:
    feature = json.dumps({"BATCH_LENGTH": n}).encode()
    feature += b" " * (-(28 + len(feature)) % 8)
    body = feature + glb
    return struct.pack("<4s6I", b"b3dm", 1, 28 + len(body), len(feature), 0, 0, 0) + body


def _cmpt(*inner: bytes) -> bytes:
    body = b"".join(inner)
    return struct.pack("<4sIII", b"cmpt", 1, 16 + len(body), len(inner)) + body


CONTENTS = {   # name -> (content bytes, whether it names objects)
    "b3dm-no-batch": (b3dm_bytes(_glb()), False),
    "b3dm-batch-table": (_b3dm_with_batch(2, _glb(batch_ids=True)), True),
    "b3dm-batchid-only": (b3dm_bytes(_glb(batch_ids=True)), True),
    "glb-plain": (_glb(), False),
    "glb-mesh-features": (_glb(mesh_features=True), True),
    "cmpt-plain": (_cmpt(b3dm_bytes(_glb()), b3dm_bytes(_glb())), False),
    "cmpt-second-batched": (_cmpt(b3dm_bytes(_glb()), b3dm_bytes(_glb(batch_ids=True))), True),
}


@pytest.mark.parametrize("name", sorted(CONTENTS))
def test_each_content_kind_behind_an_external_tileset(tmp_path, name):
    """root (no content) -> child naming an external tileset -> its root -> the content."""
    data, expected = CONTENTS[name]
    suffix = ".glb" if name.startswith("glb") else f".{name.split('-')[0]}"
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / f"c{suffix}").write_bytes(data)
    (tmp_path / "sub" / "tileset.json").write_text(json.dumps(tileset(f"c{suffix}")))
    (tmp_path / "tileset.json").write_text(json.dumps(tileset(None, [tileset("sub/tileset.json")["root"]])))
    path = tmp_path / "tileset.json"
    assert input_has_objects({"path": str(path)}) is expected
    assert reader_finds_features(path) is expected            # the reader's own answer


def test_surface_formats_and_named_objects_by_format(tmp_path):
    write_ply(tmp_path / "scan.ply", V, F, None)
    (tmp_path / "dataset" / "Data").mkdir(parents=True)           # an OSGB dataset, told by its folder
    write_obj(tmp_path / "city.obj", V, F, None)
    write_tileset(tmp_path / "tileset.json", V, F, None)          # its b3dm: no batch
    assert not input_has_objects({"path": str(tmp_path / "scan.ply")})
    assert not input_has_objects({"path": str(tmp_path / "dataset")})
    assert not input_has_objects({"path": str(tmp_path / "tileset.json")})
    assert input_has_objects({"path": str(tmp_path / "city.obj")})
    assert not input_has_objects({"path": str(tmp_path / "city.obj"), "format": "ply"})   # the format key decides


def test_what_cannot_be_peeked_at_counts_as_objects(tmp_path):
    (tmp_path / "t.b3dm").write_bytes(b"b3dm\x01\x00")                              # cut short
    (tmp_path / "bad.json").write_text(json.dumps(tileset("t.b3dm")))
    (tmp_path / "implicit.json").write_text(json.dumps(                # its root tile's content is missing
        {"asset": {"version": "1.1"}, "geometricError": 1,
         "root": {"geometricError": 1, "boundingVolume": {"box": [0] * 12}, "content": {"uri": "{level}.glb"},
                  "implicitTiling": {"subdivisionScheme": "QUADTREE", "subtreeLevels": 2, "availableLevels": 2,
                                     "subtrees": {"uri": "{level}.subtree"}}}}))
    (tmp_path / "empty.json").write_text(json.dumps(tileset(None)))
    for name in ("bad.json", "implicit.json", "empty.json"):
        assert input_has_objects({"path": str(tmp_path / name)}), name
    assert input_has_objects({"path": str(tmp_path / "missing.ply.json")})


def test_objects_enabled_resolves_auto_over_all_inputs(tmp_path):
    write_ply(tmp_path / "scan.ply", V, F, None)
    write_obj(tmp_path / "city.obj", V, F, None)

    def config(inputs: dict, objects: dict | None = None) -> dict:
        c = {"scene": "t", "crs": "EPSG:25832", "gsd": 0.5,
             "inputs": {k: {"path": str(tmp_path / v)} for k, v in inputs.items()}}
        return validate_schema({**c, **({"objects": objects} if objects else {})})

    assert config({"a": "scan.ply"})["objects"] == {"enabled": "auto"}
    assert not objects_enabled(config({"a": "scan.ply"}))
    assert objects_enabled(config({"a": "scan.ply", "b": "city.obj"}))
    assert objects_enabled(config({"a": "scan.ply"}, {"enabled": True}))
    assert not objects_enabled(config({"b": "city.obj"}, {"enabled": False}))


def test_a_scene_of_surfaces_makes_no_id_layer_unless_asked(tmp_path):
    import trimesh

    config = yaml.safe_load((Path(__file__).resolve().parents[1] / "config" / "config.yaml").read_text())
    make_scene(tmp_path, config)
    demo = tmp_path / "resources" / "demo"
    for d in config["inputs"]:                                   # the demo's OBJ districts as PLY scans
        trimesh.load(demo / f"{d}.obj", force="mesh").export(demo / f"{d}.ply")
    config["inputs"] = {d: {"path": f"resources/demo/{d}.ply"} for d in config["inputs"]}
    id_files = (".ids.vrt", ".ids.tif", "/idtiles/", "/objects/")
    counts = {}
    for enabled in ("auto", True):
        (tmp_path / "config.yaml").write_text(yaml.safe_dump({**config, "objects": {"enabled": enabled}}))
        out = snakemake(tmp_path, "-n").stdout
        counts[enabled] = job_counts(out)
        assert all(f in out for f in id_files) is (enabled is True)
        assert any(f in out for f in id_files) is (enabled is True)
    assert "objects" not in counts["auto"] and counts[True]["objects"] == 1
