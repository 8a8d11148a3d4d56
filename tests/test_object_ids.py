"""Object identity from the input to every LOD level (issue 30's first layer): each face of a chunk
names the input object it was drawn from, checked against the objects' own vertices in the file."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import shared_file

from pipeline25d.core.mesh import MeshPart
from pipeline25d.stages.ingest import ingest
from pipeline25d.stages.lod import build_lod, load_chunk_level, lod_chunks, simplify_part

DELFT = Path(__file__).resolve().parents[2] / "shared" / "data" / "delft" / "delft.json"
CRS = "EPSG:28992"


def object_vertices(path: Path) -> dict[str, np.ndarray]:
    """Each CityObject's boundary vertices (transform applied), read from the JSON directly."""
    doc = json.loads(path.read_text())
    scale = np.asarray(doc["transform"]["scale"], dtype=np.float64)
    translate = np.asarray(doc["transform"]["translate"], dtype=np.float64)
    verts = np.asarray(doc["vertices"], dtype=np.float64) * scale + translate

    def indices(b):
        return [i for x in b for i in indices(x)] if isinstance(b, list) else [b]

    return {key: verts[sorted(set(indices([g["boundaries"] for g in obj.get("geometry", [])])))]
            for key, obj in doc["CityObjects"].items()}


@pytest.fixture(scope="module")
def delft(tmp_path_factory):
    shared_file(DELFT)
    out = tmp_path_factory.mktemp("ids")
    ingest({"path": str(DELFT)}, "delft", CRS, 150.0, 0.5, out / "chunks" / "index.json")
    build_lod(out / "chunks" / "index.json", out / "lod" / "index.json", 5.0, 3)
    return out


def test_every_face_of_every_chunk_names_the_object_whose_vertices_it_uses(delft):
    truth = object_vertices(DELFT)
    faces_seen, objects_seen = 0, set()
    for chunk in lod_chunks([delft / "lod" / "index.json"]):
        origin, parts = load_chunk_level(chunk.npz, 0)
        for part in parts:
            assert part.face_objects is not None and len(part.objects) == len(set(part.objects))
            corners = part.vertices[part.faces]                           # float32 round trip: 1 mm
            for k, key in enumerate(part.objects):
                mine = corners[part.face_objects == k].reshape(-1, 3)
                own = truth[key]
                gap = np.min(np.linalg.norm(mine[:, None, :] - own[None, :, :], axis=2), axis=1)
                assert gap.max() < 2e-3, (key, gap.max())
                objects_seen.add(key)
            faces_seen += part.n_triangles
    assert faces_seen > 10_000 and len(objects_seen) > 0.9 * len(truth)


def test_coarser_levels_keep_each_face_on_its_object(delft):
    """A simplified face keeps the object of the original face it stands for: its centroid lies in
    that object's box, grown by the level's error."""
    truth = object_vertices(DELFT)
    checked = 0
    for chunk in lod_chunks([delft / "lod" / "index.json"]):
        for level, error in enumerate(chunk.errors[1:], start=1):
            _, parts = load_chunk_level(chunk.npz, level)
            for part in parts:
                centres = part.vertices[part.faces].mean(axis=1)
                lo = np.array([truth[key].min(axis=0) for key in part.objects])[part.face_objects]
                hi = np.array([truth[key].max(axis=0) for key in part.objects])[part.face_objects]
                assert ((centres >= lo - error - 2e-3) & (centres <= hi + error + 2e-3)).all()
                checked += part.n_triangles
    assert checked > 1000


def test_a_simplified_part_carries_the_objects_of_the_faces_that_survive():
    """Two objects side by side on a grid: after simplification each face still lies on its
    object's side of the seam (x < 10 for object a, x > 10 for b)."""
    n = 21
    x, y = np.meshgrid(np.linspace(0, 20, n), np.linspace(0, 20, n))
    z = 0.05 * np.sin(x) * np.cos(y)
    vertices = np.c_[x.ravel(), y.ravel(), z.ravel()]
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    faces = np.r_[np.c_[a, b, d], np.c_[a, d, c]]
    side = (vertices[faces].mean(axis=1)[:, 0] > 10).astype(np.int32)
    part = MeshPart(vertices, faces, objects=("a", "b"), face_objects=side)
    coarse = simplify_part(part, 0.6)
    assert coarse.n_triangles < 0.6 * part.n_triangles and coarse.objects == ("a", "b")
    centres = coarse.vertices[coarse.faces].mean(axis=1)[:, 0]
    assert (centres[coarse.face_objects == 0] <= 10.5).all() and (centres[coarse.face_objects == 1] >= 9.5).all()
    assert set(coarse.face_objects) == {0, 1}


def test_numeric_ids_are_unique_stable_and_never_zero():
    from pipeline25d.stages.objects import LOCAL_BITS, district_slots, object_ids

    slots = district_slots(["north", "south", "d0"])
    assert len(set(slots.values())) == 3 and district_slots(["north", "south", "d0", "east"])["north"] == slots["north"]
    keys = [f"b{i}" for i in range(20_000)]
    ids = object_ids(keys, slots["north"], "x.json")
    assert len(set(ids.values())) == len(keys) and 0 not in ids.values()
    assert {v >> LOCAL_BITS for v in ids.values()} == {slots["north"]}
    more = object_ids(keys + ["new"], slots["north"], "x.json")
    moved = [k for k in keys if more[k] != ids[k]]
    assert len(moved) <= 1                           # only a newcomer taking a probed hash first moves one


def test_ingest_gives_every_face_a_numeric_id_of_its_object(delft):
    """objects.json maps each key to its id; every chunk part carries those ids at every level, and an
    anonymous part (a mesh file's) becomes one object named after it."""
    ids = json.loads((delft / "chunks" / "objects.json").read_text())
    for chunk in lod_chunks([delft / "lod" / "index.json"]):
        for level in range(len(chunk.errors)):
            _, parts = load_chunk_level(chunk.npz, level)
            for part in parts:
                assert part.object_ids.tolist() == [ids[k] for k in part.objects]
    assert len(ids) > 100 and len(set(ids.values())) == len(ids)


def test_an_obj_part_is_one_object_named_after_it(tmp_path):
    (tmp_path / "m.obj").write_text("v 0 0 0\nv 10 0 0\nv 10 10 0\nv 0 10 0\nusemtl grass\nf 1 2 3\nf 1 3 4\n")
    index = ingest({"path": str(tmp_path / "m.obj")}, "d", "EPSG:25832", 100.0, 0.5, tmp_path / "c" / "index.json")
    ids = json.loads((tmp_path / "c" / "objects.json").read_text())
    (cid,) = index["chunks"]
    from pipeline25d.stages.chunks import load_npz, unpack_parts

    data = load_npz(tmp_path / "c" / f"{cid}.npz")
    (part,) = unpack_parts(data, data["origin"])
    assert len(ids) == 1 and part.objects == tuple(ids) and (part.face_objects == 0).all()
    assert part.object_ids.tolist() == list(ids.values())


def obj_object_triangles(path: Path) -> dict[str, list[tuple]]:
    """Each ``o`` object's triangles (fans of its ``f`` polygons) as sorted vertex triples, read from
    the OBJ's lines directly."""
    verts, out, current = [], {}, ""
    for line in path.read_text().splitlines():
        words = line.split()
        if not words:
            continue
        if words[0] == "v":
            verts.append(tuple(float(w) for w in words[1:4]))
        elif words[0] == "o":
            current = " ".join(words[1:])
        elif words[0] == "f":
            idx = [int(w.split("/")[0]) for w in words[1:]]
            idx = [i - 1 if i > 0 else len(verts) + i for i in idx]
            for k in range(1, len(idx) - 1):
                out.setdefault(current, []).append(tuple(sorted((verts[idx[0]], verts[idx[k]], verts[idx[k + 1]]))))
    return out


def test_an_obj_face_keeps_its_o_object_and_parts_stay_one_per_material():
    """3dfier's Delft OBJ: one ``o`` per building, road, terrain patch ..., materials across them."""
    from pipeline25d.formats.meshfile import load_mesh_file

    path = DELFT.parent / "obj" / "testarea.obj"
    shared_file(path)
    mesh = load_mesh_file(path)
    truth = obj_object_triangles(path)
    materials = {w.split()[1] for w in path.read_text().splitlines() if w.startswith("usemtl ")}
    assert sorted(p.name for p in mesh.parts) == sorted(materials)
    got: dict[str, list[tuple]] = {}
    for part in mesh.parts:
        assert part.face_objects is not None          # the file names an object for every face
        for face, obj in zip(part.faces, part.face_objects):
            got.setdefault(part.objects[obj], []).append(tuple(sorted(map(tuple, part.vertices[face]))))
    assert len(got) == len(truth) >= 500
    assert all(sorted(got[key]) == sorted(truth[key]) for key in truth)


def test_obj_quirks_faces_before_any_o_an_object_named_twice_and_underscores(tmp_path):
    """Faces before the first ``o`` are an object named after the file; an ``o`` that comes back
    (trimesh names its second piece ``a_b_1``) is still ``a_b``; no MTL, so no material in the names."""
    from pipeline25d.formats.meshfile import load_mesh_file

    path = tmp_path / "quirks.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3\no a_b\nf 1 3 4\no c\nusemtl m1\nf 1 2 4\n"
                    "o a_b\nf 2 3 4\n")
    got = {}
    for part in load_mesh_file(path).parts:
        for face, obj in zip(part.faces, part.face_objects):
            got.setdefault(part.objects[obj], []).append(tuple(sorted(map(tuple, part.vertices[face]))))
    truth = obj_object_triangles(path)
    truth["quirks.obj"] = truth.pop("")
    assert {k: sorted(v) for k, v in got.items()} == {k: sorted(v) for k, v in truth.items()}


SAMPLES = DELFT.parents[1] / "3dtiles-samples"


def test_b3dm_batch_ids_are_the_buildings_of_a_batched_tile():
    """BatchedTextured: ten buildings in one b3dm, each a box of 12 triangles: each _BATCHID object is
    one closed box, and no two boxes overlap in plan."""
    from pipeline25d.formats import load_district

    path = SAMPLES / "BatchedTextured" / "tileset.json"
    shared_file(path)
    (part,) = load_district({"path": str(path)}, "EPSG:32618").parts        # UTM 18N: x, y in plan
    assert part.objects == tuple(f"batchedTextured.b3dm#{k}" for k in range(10))
    boxes = []
    for k in range(10):
        tris = part.faces[part.face_objects == k]
        corners = np.unique(np.round(part.vertices[np.unique(tris)], 3), axis=0)
        assert len(tris) == 12 and len(corners) == 8          # a box: 12 triangles on 8 corners
        boxes.append((corners[:, :2].min(axis=0), corners[:, :2].max(axis=0)))
    for i in range(10):
        for j in range(i + 1, 10):
            (lo_i, hi_i), (lo_j, hi_j) = boxes[i], boxes[j]
            assert (hi_i <= lo_j + 1e-3).any() or (hi_j <= lo_i + 1e-3).any()     # apart in plan


def test_ext_mesh_features_ids_follow_the_feature_id_attribute():
    """FeatureIdAttribute: the ids of the _FEATURE_ID_0 accessor, read here from the glTF's own
    buffer, at each face's first vertex."""
    import base64

    from pipeline25d.formats import load_district

    path = SAMPLES / "FeatureIdAttribute" / "FeatureIdAttribute.gltf"
    shared_file(path)
    doc = json.loads(path.read_text())
    uri = doc["buffers"][0]["uri"]
    data = base64.b64decode(uri.split(",", 1)[1]) if uri.startswith("data:") else (path.parent / uri).read_bytes()

    def accessor(i):
        acc = doc["accessors"][i]
        view = doc["bufferViews"][acc["bufferView"]]
        dtype = {5121: np.uint8, 5123: np.uint16, 5125: np.uint32, 5126: np.float32}[acc["componentType"]]
        width = {"SCALAR": 1, "VEC3": 3}[acc["type"]]
        start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
        stride = view.get("byteStride", np.dtype(dtype).itemsize * width)      # the ids: 1 byte in 4
        rows = [np.frombuffer(data, dtype, width, start + k * stride) for k in range(acc["count"])]
        return np.array(rows)

    prim = doc["meshes"][0]["primitives"][0]
    indices = accessor(prim["indices"]).reshape(-1, 3)
    ids = accessor(prim["attributes"]["_FEATURE_ID_0"]).reshape(-1)[indices[:, 0]]
    (part,) = load_district({"path": str(path), "crs": "EPSG:4978"}, "EPSG:4978").parts
    named = [part.objects[k] for k in part.face_objects]
    assert named == [f"FeatureIdAttribute.gltf#{int(v)}" for v in ids] and len(set(named)) == 4


def test_merged_parts_keep_each_face_on_its_object():
    from pipeline25d.core.mesh import joined_objects

    a = MeshPart(np.zeros((3, 3)), [[0, 1, 2]] * 3, objects=("x", "y"), face_objects=[1, 0, 1])
    b = MeshPart(np.zeros((3, 3)), [[0, 1, 2]] * 2, name="roofs")
    c = MeshPart(np.zeros((3, 3)), [[0, 1, 2]], objects=("y",), face_objects=[0])
    objects, faces = joined_objects([a, b, c])
    assert [objects[k] for k in faces] == ["y", "x", "y", "roofs", "roofs", "y"]
    assert joined_objects([b, b]) == ((), None)
