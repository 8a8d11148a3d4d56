"""CityJSON reader: Delft (shared/data/delft/SOURCE.txt) and tiny hand-written models."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from pipeline25d.core.errors import CRSError, InputFileError
from pipeline25d.formats.cityjson import (
    GROUND_TYPES,
    PALETTE,
    load_cityjson,
    load_cityjson_terrain,
    source_crs,
    triangulate_polygon,
)

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
DELFT = DATA / "delft" / "delft.json"
RD = "EPSG:28992"


def _need(path: Path) -> Path:
    if not path.exists():
        pytest.skip(f"test data {path} not present")
    return path


@pytest.fixture(scope="module")
def delft_doc() -> dict:
    return json.loads(_need(DELFT).read_text())


@pytest.fixture(scope="module")
def delft_mesh():
    return load_cityjson(_need(DELFT), RD)


def _triangle_area(mesh) -> float:
    total = 0.0
    for p in mesh.parts:
        t = p.vertices[p.faces]
        total += 0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1).sum()
    return total


# ----------------------------------------------------------------------------- Delft


#: Delft's two zero-area triangles (three water vertices on one line at y 447498.081), dropped at reading
DELFT_FLAT = 2


def test_delft_counts_and_bounds(delft_mesh):
    assert delft_mesh.n_triangles == 36271 - DELFT_FLAT  # 36,271 surfaces, all triangles
    b = delft_mesh.bounds()
    np.testing.assert_allclose(b[:, 0], [84616, 85141], atol=1.0)
    np.testing.assert_allclose(b[:, 1], [447423, 447751], atol=1.0)
    # metadata.geographicalExtent, exactly (quantised vertices, float64 transform)
    np.testing.assert_allclose(b.ravel(), [84616.468, 447422.999, -0.452, 85140.839, 447750.636, 16.846],
                               atol=1e-6)


def test_delft_colour_classes(delft_mesh, delft_doc):
    parts = {p.name: p for p in delft_mesh.parts}
    assert set(parts) == {"landuse", "other", "road", "roof", "vegetation", "wall", "water"}
    for name, part in parts.items():
        np.testing.assert_array_equal(np.unique(part.colors, axis=0), [PALETTE[name]])
    # LOD1 blocks without semantics: up-facing triangles are roofs, 3dfier writes no floors
    n_building = sum(len(shell) for o in delft_doc["CityObjects"].values() if o["type"] == "Building"
                     for g in o["geometry"] for shell in g["boundaries"])
    assert parts["roof"].n_triangles + parts["wall"].n_triangles == n_building
    assert parts["roof"].n_triangles > 160  # at least one roof triangle per building
    roof_z = parts["roof"].vertices[:, 2].mean()
    wall_z = parts["wall"].vertices[:, 2].min()
    assert roof_z > wall_z + 0.5


def test_delft_lonlat(delft_mesh):
    geo = load_cityjson(DELFT, "EPSG:4979")
    b = geo.bounds()
    np.testing.assert_allclose(b[:, 0], [4.3620, 4.3696], atol=1e-4)
    np.testing.assert_allclose(b[:, 1], [52.0107, 52.0137], atol=1e-4)
    assert geo.n_triangles == delft_mesh.n_triangles


def test_delft_lod_selection(delft_mesh):
    assert load_cityjson(DELFT, RD, lod="1").n_triangles == 36271 - DELFT_FLAT
    assert load_cityjson(DELFT, RD, lod="2.2").n_triangles == 36271 - DELFT_FLAT  # highest below 2.2 is 1
    assert load_cityjson(DELFT, RD, lod="0").n_triangles == 36271 - DELFT_FLAT  # none below: lowest kept


def test_delft_terrain_partition(delft_mesh, delft_doc):
    terrain = load_cityjson_terrain(DELFT, RD)
    expected = sum(len(g["boundaries"]) for o in delft_doc["CityObjects"].values() if o["type"] in GROUND_TYPES
                   for g in o["geometry"])
    assert terrain.n_triangles == expected - DELFT_FLAT > 10000   # the flat ones are water
    assert {p.name for p in terrain.parts} == {"landuse", "road", "water"}
    assert terrain.bounds()[1, 2] < 2.5  # ground level; vegetation (up to 16.8 m) is not terrain
    rest = load_cityjson(DELFT, RD, include_terrain=False)
    assert rest.n_triangles + terrain.n_triangles == delft_mesh.n_triangles


def test_cityjsonseq_matches_cityjson(tmp_path, delft_doc):
    """Delft rewritten as CityJSONSeq (header line + one feature per object) reads the same."""
    tr = delft_doc["transform"]
    header = {"type": "CityJSON", "version": "2.0", "transform": tr, "metadata": delft_doc["metadata"],
              "CityObjects": {}, "vertices": []}
    lines = [json.dumps(header)]
    verts = delft_doc["vertices"]
    for oid, obj in list(delft_doc["CityObjects"].items())[:60]:
        remap: dict[int, int] = {}

        def walk(b):
            if isinstance(b, list):
                return [walk(x) for x in b]
            return remap.setdefault(b, len(remap))

        geoms = [dict(g, boundaries=walk(g["boundaries"])) for g in obj["geometry"]]
        local = [verts[i] for i in sorted(remap, key=remap.get)]
        lines.append(json.dumps({"type": "CityJSONFeature", "id": oid,
                                 "CityObjects": {oid: dict(obj, geometry=geoms)}, "vertices": local}))
    (tmp_path / "delft.city.jsonl").write_text("\n".join(lines) + "\n")
    subset = dict(delft_doc, CityObjects=dict(list(delft_doc["CityObjects"].items())[:60]))
    (tmp_path / "subset.city.json").write_text(json.dumps(subset))
    seq = load_cityjson(tmp_path / "delft.city.jsonl", RD)
    whole = load_cityjson(tmp_path / "subset.city.json", RD)
    assert seq.n_triangles == whole.n_triangles > 0
    np.testing.assert_allclose(seq.bounds(), whole.bounds(), atol=1e-9)
    assert _triangle_area(seq) == pytest.approx(_triangle_area(whole), rel=1e-12)


# ----------------------------------------------------------------------------- hand-written models


def _model(tmp_path: Path, objects: dict, vertices: list, name: str = "m.city.json", **extra) -> Path:
    doc = {"type": "CityJSON", "version": "2.0", "transform": {"scale": [1, 1, 1], "translate": [0, 0, 0]},
           "metadata": {"referenceSystem": "https://www.opengis.net/def/crs/EPSG/0/7415"},
           "CityObjects": objects, "vertices": vertices}
    doc.update(extra)
    path = tmp_path / name
    path.write_text(json.dumps(doc))
    return path


SQUARE_WITH_HOLE = [[0, 0, 0], [4, 0, 0], [4, 4, 0], [0, 4, 0], [1, 1, 0], [1, 3, 0], [3, 3, 0], [3, 1, 0]]


def test_polygon_with_hole_area_exact(tmp_path):
    # horizontal 4x4 square with a 2x2 hole, plus a vertical wall (x = 10) with a 1x1 window
    wall = [[10, 0, 0], [10, 5, 0], [10, 5, 3], [10, 0, 3], [10, 1, 1], [10, 1, 2], [10, 2, 2], [10, 2, 1]]
    objects = {"a": {"type": "LandUse", "geometry": [
        {"type": "MultiSurface", "lod": "1", "boundaries": [[[0, 1, 2, 3], [4, 5, 6, 7]], [[8, 9, 10, 11],
                                                                                           [12, 13, 14, 15]]]}]}}
    mesh = load_cityjson(_model(tmp_path, objects, SQUARE_WITH_HOLE + wall), "EPSG:7415")
    assert _triangle_area(mesh) == (16.0 - 4.0) + (15.0 - 1.0)  # exact in float64
    # orientation kept: the CCW (seen from above) square's triangles face +z
    part = mesh.parts[0]
    t = part.vertices[part.faces]
    normals = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    flat = np.isclose(np.ptp(t[:, :, 2], axis=1), 0)
    assert (normals[flat, 2] > 0).all()
    # no triangle inside the hole
    centroids = t.mean(axis=1)
    inside = flat & (centroids[:, 0] > 1) & (centroids[:, 0] < 3) & (centroids[:, 1] > 1) & (centroids[:, 1] < 3)
    assert not inside.any()


def test_triangulate_polygon_closed_ring_and_degenerate():
    v = np.array(SQUARE_WITH_HOLE, dtype=np.float64)
    tris, normal = triangulate_polygon([[0, 1, 2, 3, 0]], v)  # closing vertex repeated
    assert len(tris) == 2 and normal[2] > 0
    assert len(triangulate_polygon([[0, 1, 1]], v)[0]) == 0


def test_semantics_solid_and_v10_urn(tmp_path):
    # unit cube solid, outward faces, with semantics: bottom ground, top roof, sides wall
    v = [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]]
    shell = [[[0, 3, 2, 1]], [[4, 5, 6, 7]], [[0, 1, 5, 4]], [[1, 2, 6, 5]], [[2, 3, 7, 6]], [[3, 0, 4, 7]]]
    sem = {"surfaces": [{"type": "GroundSurface"}, {"type": "RoofSurface"}, {"type": "WallSurface"}],
           "values": [[0, 1, 2, 2, 2, None]]}
    objects = {"b": {"type": "Building", "geometry": [
        {"type": "Solid", "lod": 2, "boundaries": [shell], "semantics": sem},
        {"type": "Solid", "lod": 1, "boundaries": [shell]}]}}
    path = _model(tmp_path, objects, v, version="1.0", metadata={"referenceSystem": "urn:ogc:def:crs:EPSG::7415"})
    assert source_crs(json.loads(path.read_text()), path) == "EPSG:7415"
    mesh = load_cityjson(path, "EPSG:7415")
    counts = {p.name: p.n_triangles for p in mesh.parts}
    # the null-semantics side falls back to the normal rule (vertical: wall)
    assert counts == {"ground": 2, "roof": 2, "wall": 8}
    roof = next(p for p in mesh.parts if p.name == "roof")
    np.testing.assert_array_equal(roof.colors[0], PALETTE["roof"])
    assert load_cityjson(path, "EPSG:7415", lod="1").n_triangles == 12


def test_geometry_instance(tmp_path):
    templates = {"templates": [{"type": "MultiSurface", "lod": "1", "boundaries": [[[0, 1, 2]]]}],
                 "vertices-templates": [[0, 0, 0], [1, 0, 0], [0, 1, 0]]}
    m = [2, 0, 0, 0, 0, 2, 0, 0, 0, 0, 2, 0, 0, 0, 0, 1]  # scale 2 (row-major)
    objects = {"t": {"type": "SolitaryVegetationObject", "geometry": [
        {"type": "GeometryInstance", "template": 0, "boundaries": [0], "transformationMatrix": m}]}}
    path = _model(tmp_path, objects, [[100, 200, 5]], **{"geometry-templates": templates})
    mesh = load_cityjson(path, "EPSG:7415")
    np.testing.assert_allclose(mesh.bounds(), [[100, 200, 5], [102, 202, 5]])
    assert mesh.parts[0].name == "vegetation"


def test_reprojection_and_area_check(tmp_path):
    objects = {"a": {"type": "LandUse", "geometry": [
        {"type": "MultiSurface", "lod": "1", "boundaries": [[[0, 1, 2, 3]]]}]}}
    path = _model(tmp_path, objects, [[85000, 447500, 0], [85010, 447500, 0], [85010, 447510, 0],
                                      [85000, 447510, 0]])
    utm = load_cityjson(path, "EPSG:32631")  # RD New -> UTM 31N: the 10 m square moves and turns
    b = utm.bounds()
    assert 580000 < b[0, 0] < 600000 and 5.76e6 < b[0, 1] < 5.77e6
    v = utm.parts[0].vertices
    edges = np.sort(np.linalg.norm(v[:, None, :2] - v[None, :, :2], axis=2)[np.triu_indices(4, 1)])
    np.testing.assert_allclose(edges, [10, 10, 10, 10, 10 * 2 ** 0.5, 10 * 2 ** 0.5], atol=0.01)
    with pytest.raises(CRSError, match="area of use"):
        load_cityjson(path, "EPSG:6677")  # Japan


def test_missing_crs(tmp_path):
    path = _model(tmp_path, {}, [], metadata={})
    with pytest.raises(CRSError, match="src_crs"):
        load_cityjson(path, RD)
    assert load_cityjson(path, RD, src_crs=RD).n_triangles == 0


def test_invalid_inputs(tmp_path):
    bad = tmp_path / "broken.json"
    bad.write_text('{"type": "CityJSON", "vertices": [')
    with pytest.raises(InputFileError, match="broken.json.*invalid JSON"):
        load_cityjson(bad, RD)
    no_vertices = tmp_path / "novert.json"
    no_vertices.write_text(json.dumps({"type": "CityJSON", "version": "2.0", "CityObjects": {}}))
    with pytest.raises(InputFileError, match="novert.json.*vertices"):
        load_cityjson(no_vertices, RD)
    objects = {"a": {"type": "LandUse", "geometry": [
        {"type": "MultiSurface", "lod": "1", "boundaries": [[[0, 1, 7]]]}]}}
    with pytest.raises(InputFileError, match="range.json.*out of range"):
        load_cityjson(_model(tmp_path, objects, [[0, 0, 0], [1, 0, 0], [0, 1, 0]], name="range.json"), RD)
    not_city = tmp_path / "other.json"
    not_city.write_text(json.dumps({"type": "FeatureCollection"}))
    with pytest.raises(InputFileError, match="not CityJSON"):
        load_cityjson(not_city, RD)


def test_lod_selection_takes_the_asked_level(tmp_path):
    """LOD1 is a 10 m box, LOD2 the same walls with a gable to 14 m: each choice is visible in
    the heights and triangle counts, so a reader that ignored ``lod`` would fail."""
    box = [[0, 0, 0], [8, 0, 0], [8, 6, 0], [0, 6, 0], [0, 0, 10], [8, 0, 10], [8, 6, 10], [0, 6, 10]]
    ridge = [[0, 3, 14], [8, 3, 14]]
    v = box + ridge
    walls = [[[0, 3, 2, 1]], [[0, 1, 5, 4]], [[1, 2, 6, 5]], [[2, 3, 7, 6]], [[3, 0, 4, 7]]]
    lod1 = [walls + [[[4, 5, 6, 7]]]]
    gables = [[[4, 5, 9, 8]], [[6, 7, 8, 9]], [[5, 6, 9]], [[7, 4, 8]]]   # two roof planes, two gable ends
    objects = {
        "b": {"type": "Building", "geometry": [
            {"type": "Solid", "lod": "1", "boundaries": lod1},
            {"type": "Solid", "lod": "2", "boundaries": [walls + gables]}]},
        "only2": {"type": "Building", "geometry": [
            {"type": "MultiSurface", "lod": "2", "boundaries": [[[0, 1, 2]]]}]},
    }
    path = _model(tmp_path, objects, v)

    def top_and_count(lod):
        mesh = load_cityjson(path, "EPSG:7415", lod=lod)
        return float(mesh.bounds()[1, 2]), mesh.n_triangles

    lod1_tris, lod2_tris = 12, 5 * 2 + 2 * 2 + 2 * 1
    assert top_and_count("1") == (10.0, lod1_tris + 1)        # "only2" has no LOD1 or lower: its lowest (2) is kept
    assert top_and_count("2") == (14.0, lod2_tris + 1)
    assert top_and_count("2.2") == (14.0, lod2_tris + 1)      # highest at or below 2.2
    assert top_and_count("0") == (10.0, lod1_tris + 1)        # none at or below 0: each object's lowest
    assert top_and_count(None) == (14.0, lod2_tris + 1)       # default: each object's highest


def test_many_geometry_instances_land_on_their_anchors(tmp_path):
    """Instances of two templates at many anchors, mixed with a plain geometry: every triangle
    must sit at its own anchor (the instance vertices are appended in one go at the end)."""
    templates = {"templates": [{"type": "MultiSurface", "lod": "1", "boundaries": [[[0, 1, 2]]]},
                               {"type": "MultiSurface", "lod": "1", "boundaries": [[[3, 4, 5]]]}],
                 "vertices-templates": [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 0], [2, 0, 0], [0, 0, 3]]}
    eye = list(np.eye(4).ravel())
    n = 40
    anchors = [[100.0 + 10 * i, 200.0, float(i)] for i in range(n)]
    plain = [[0.0, 0.0, 50.0], [1.0, 0.0, 50.0], [0.0, 1.0, 50.0]]
    objects = {f"t{i}": {"type": "SolitaryVegetationObject", "geometry": [
        {"type": "GeometryInstance", "template": i % 2, "boundaries": [i], "transformationMatrix": eye}]}
        for i in range(n)}
    objects["plain"] = {"type": "Building", "geometry": [
        {"type": "MultiSurface", "lod": "1", "boundaries": [[[n, n + 1, n + 2]]]}]}
    path = _model(tmp_path, objects, anchors + plain, **{"geometry-templates": templates})
    mesh = load_cityjson(path, "EPSG:7415")
    tris = np.concatenate([p.vertices[p.faces] for p in mesh.parts])

    def key(triangle) -> tuple:
        return tuple(sorted(tuple(np.round(np.asarray(c, dtype=float), 6)) for c in triangle))

    tv = np.asarray(templates["vertices-templates"], dtype=float)
    expected = [key(np.asarray(anchors[i]) + tv[3 * (i % 2):3 * (i % 2) + 3]) for i in range(n)] + [key(plain)]
    assert sorted(key(t) for t in tris) == sorted(expected)
