"""CityJSON reader: Delft (shared/data/delft/SOURCE.txt) and tiny hand-written models."""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np
import pytest
from conftest import shared_file

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


@pytest.fixture(scope="module")
def delft_doc() -> dict:
    return json.loads(shared_file(DELFT).read_text())


@pytest.fixture(scope="module")
def delft_mesh():
    return load_cityjson(shared_file(DELFT), RD)


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
    with pytest.raises(CRSError, match=r"no metadata.referenceSystem says its CRS \(set the input's crs key\)"):
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


# ----------------------------------------------------------------------------- appearances

ORIGIN = np.array([85000.0, 447000.0, 0.0])     # RD New; vertices quantised at 1 mm around it
BOX = [[0, 0, 0], [10, 0, 0], [10, 8, 0], [0, 8, 0], [0, 0, 6], [10, 0, 6], [10, 8, 6], [0, 8, 6],
       [4, 0, 2], [6, 0, 2], [6, 0, 4], [4, 0, 4]]                      # 8..11: a window in the south wall
#: ground, roof, south wall (with the window), east, north, west: all facing outwards
SHELL = [[[0, 3, 2, 1]], [[4, 5, 6, 7]], [[0, 1, 5, 4], [8, 11, 10, 9]], [[1, 2, 6, 5]], [[2, 3, 7, 6]],
         [[3, 0, 4, 7]]]
#: the texture mappings given to the file, as functions of the position (box coordinates)
SUMMER = {"south": lambda p: (p[0] / 20, p[2] / 6), "east": lambda p: (0.5 + p[1] / 16, p[2] / 6)}
WINTER_EAST = lambda p: (p[1] / 8, p[2] / 6)  # noqa: E731
ROOF_PAINT = {"diffuseColor": [0.7, 0.2, 0.1], "transparency": 0.2}
SOUTH_PAINT = {"diffuseColor": [0.0, 0.0, 1.0]}


def _png(path: Path, seed: int, size=(16, 8)) -> bytes:
    from PIL import Image

    pixels = np.random.default_rng(seed).integers(0, 256, (size[1], size[0], 3), dtype=np.uint8)
    Image.fromarray(pixels).save(path, format="PNG")
    return path.read_bytes()


def _textured_box(folder: Path, version: str = "2.0", name: str = "box.city.json") -> Path:
    """A LOD2 box building: the south (with a window) and east walls textured in theme "summer"
    (facade.png), the east wall in theme "winter" (snow.png, the file's default), the roof and the
    south wall with materials (theme "paint"); vertices quantised (transform)."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "textures").mkdir(exist_ok=True)
    _png(folder / "textures" / "facade.png", 1)
    _png(folder / "textures" / "snow.png", 2)
    uvs: list[list[float]] = []

    def ring(ids, mapping, texture):
        start = len(uvs)
        uvs.extend([list(mapping(BOX[i])) for i in ids])
        return [texture] + list(range(start, start + len(ids)))

    untextured = [[None]]
    summer = [untextured, untextured,
              [ring(SHELL[2][0], SUMMER["south"], 0), ring(SHELL[2][1], SUMMER["south"], 0)],
              [ring(SHELL[3][0], SUMMER["east"], 0)], untextured, untextured]
    winter = [untextured, untextured, [[None], [None]], [ring(SHELL[3][0], WINTER_EAST, 1)], untextured, untextured]
    geometry = {"type": "Solid", "lod": 2 if version == "1.0" else "2", "boundaries": [SHELL],
                "semantics": {"surfaces": [{"type": "GroundSurface"}, {"type": "RoofSurface"},
                                           {"type": "WallSurface"}], "values": [[0, 1, 2, 2, 2, 2]]},
                "texture": {"summer": {"values": [summer]}, "winter": {"values": [winter]}},
                "material": {"paint": {"values": [[None, 0, 1, None, None, None]]}}}
    scale = 0.001
    doc = {"type": "CityJSON", "version": version,
           "transform": {"scale": [scale] * 3, "translate": list(ORIGIN)},
           "metadata": {"referenceSystem": "urn:ogc:def:crs:EPSG::7415" if version == "1.0"
                        else "https://www.opengis.net/def/crs/EPSG/0/7415"},
           "CityObjects": {"b1": {"type": "Building", "geometry": [geometry]}},
           "vertices": [[round(c / scale) for c in v] for v in BOX],
           "appearance": {"textures": [{"type": "PNG", "image": "textures/facade.png", "wrapMode": "wrap"},
                                       {"type": "PNG", "image": "textures/snow.png", "wrapMode": "clamp",
                                        "borderColor": [0, 0, 0, 1]}],
                          "vertices-texture": uvs,
                          "materials": [dict(ROOF_PAINT, name="roof"), dict(SOUTH_PAINT, name="south", isSmooth=False)],
                          "default-theme-texture": "winter"}}
    path = folder / name
    path.write_text(json.dumps(doc))
    return path


def _rgba(material: dict) -> list[int]:
    return [round(c * 255) for c in material["diffuseColor"]] + [round((1 - material.get("transparency", 0)) * 255)]


def _wall_of(normal: np.ndarray) -> str:
    return {(0, -1): "south", (1, 0): "east", (0, 1): "north", (-1, 0): "west"}[tuple(np.round(normal[:2]).astype(int))]


def _unit_normals(part) -> np.ndarray:
    t = part.vertices[part.faces]
    n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def _faces_coloured(part, rgba) -> int:
    return int(np.all(part.colors[part.faces] == rgba, axis=(1, 2)).sum())


@pytest.mark.parametrize("version", ["1.0", "1.1", "2.0"])
def test_textured_box_uvs_texture_and_materials(tmp_path, version):
    from pipeline25d.formats import load_district

    path = _textured_box(tmp_path, version)
    mesh = load_district({"path": str(path), "theme": "summer"}, "EPSG:7415")
    parts = {p.name: p for p in mesh.parts}
    assert set(parts) == {"facade.png", "ground", "roof", "wall"}
    tex = parts["facade.png"]
    assert tex.texture == (tmp_path / "textures" / "facade.png").read_bytes()
    # south wall: 8 ring vertices with a hole -> 8 triangles; east wall 2; 60 - 4 + 48 m2
    assert tex.n_triangles == 10
    assert _triangle_area(type(mesh)([tex])) == pytest.approx(60 - 4 + 48, rel=1e-9)
    # every corner carries the UV the file gives its vertex on that wall (the shared edge x=10, y=0 has two)
    local = tex.vertices - ORIGIN
    for face, normal in zip(tex.faces, _unit_normals(tex)):
        mapping = SUMMER[_wall_of(normal)]
        np.testing.assert_allclose(tex.uv[face], [mapping(local[i]) for i in face], atol=1e-7)
    np.testing.assert_allclose(mesh.bounds(), [ORIGIN, ORIGIN + [10, 8, 6]], atol=1e-9)
    # the roof in its material's diffuse colour (alpha 1 - transparency); the others in class colours
    np.testing.assert_array_equal(np.unique(parts["roof"].colors, axis=0), [_rgba(ROOF_PAINT)])
    np.testing.assert_array_equal(np.unique(parts["ground"].colors, axis=0), [PALETTE["ground"]])
    assert parts["wall"].n_triangles == 4 and _faces_coloured(parts["wall"], PALETTE["wall"]) == 4


def test_default_theme_log_and_unknown_theme(tmp_path, caplog):
    import logging

    from pipeline25d.core.errors import ConfigError
    from pipeline25d.formats.cityjson import read_cityjson

    path = _textured_box(tmp_path)
    with caplog.at_level(logging.INFO, logger="pipeline25d.formats.cityjson_appearance"):
        loaded = read_cityjson(path, {})
    said = caplog.text
    assert "1 of 2 textures drawn on 1 surfaces (texture theme 'winter'; not drawn: 'summer')" in said
    assert "2 surfaces in material colours (material theme 'paint')" in said
    parts = {p.name: p for p in loaded.parts}
    snow = parts["snow.png"]
    assert snow.texture == (tmp_path / "textures" / "snow.png").read_bytes() and snow.n_triangles == 2
    np.testing.assert_allclose(snow.uv[snow.faces.ravel()],
                               [WINTER_EAST(v - ORIGIN) for v in snow.vertices[snow.faces.ravel()]], atol=1e-7)
    # the south wall has no texture in "winter": its material colour, window and all (8 triangles)
    assert _faces_coloured(parts["wall"], _rgba(SOUTH_PAINT)) == 8
    with pytest.raises(ConfigError, match=r"box\.city\.json: theme 'autumn' .*\(texture themes: 'summer', "
                                          r"'winter'; material themes: 'paint'"):
        read_cityjson(path, {"theme": "autumn"})


def test_missing_texture_image_is_an_error_or_drawn_in_colour(tmp_path):
    from pipeline25d.core.errors import MissingTextureWarning
    from pipeline25d.formats import load_district

    path = _textured_box(tmp_path)
    (tmp_path / "textures" / "facade.png").unlink()
    spec = {"path": str(path), "theme": "summer"}
    with pytest.raises(InputFileError, match=r"box\.city\.json: texture image .*facade\.png is missing "
                                             r"\(set the input's missing_textures: untextured"):
        load_district(spec, "EPSG:7415")
    with pytest.warns(MissingTextureWarning, match=r"facade\.png is missing; its parts are drawn untextured"):
        mesh = load_district(dict(spec, missing_textures="untextured"), "EPSG:7415")
    parts = {p.name: p for p in mesh.parts}
    assert set(parts) == {"ground", "roof", "wall"}
    wall = parts["wall"]   # south: its material; east, north, west: the class colour
    assert (_faces_coloured(wall, _rgba(SOUTH_PAINT)), _faces_coloured(wall, PALETTE["wall"])) == (8, 6)


def test_cityjsonseq_features_with_their_own_appearance(tmp_path):
    whole = load_cityjson(_textured_box(tmp_path), RD, theme="summer")
    doc = json.loads((tmp_path / "box.city.json").read_text())
    header = {k: doc[k] for k in ("type", "version", "transform", "metadata")} | {"CityObjects": {}, "vertices": []}
    feature = {"type": "CityJSONFeature", "id": "b1", "CityObjects": doc["CityObjects"], "vertices": doc["vertices"],
               "appearance": doc["appearance"]}
    (tmp_path / "box.city.jsonl").write_text(json.dumps(header) + "\n" + json.dumps(feature) + "\n")
    seq = load_cityjson(tmp_path / "box.city.jsonl", RD, theme="summer")
    assert [p.name for p in seq.parts] == [p.name for p in whole.parts]
    for a, b in zip(seq.parts, whole.parts):
        np.testing.assert_array_equal(a.vertices, b.vertices)
        np.testing.assert_array_equal(a.faces, b.faces)
        assert (a.uv is None) == (b.uv is None) and a.texture == b.texture
        if a.uv is not None:
            np.testing.assert_array_equal(a.uv, b.uv)


def test_bad_appearance_values(tmp_path):
    from pipeline25d.formats.cityjson import read_cityjson

    def edit(name, change):
        path = _textured_box(tmp_path, name=name)
        doc = json.loads(path.read_text())
        change(doc, doc["CityObjects"]["b1"]["geometry"][0])
        path.write_text(json.dumps(doc))
        return path

    def bad_texture(doc, geom):
        geom["texture"]["summer"]["values"][0][3][0][0] = 7

    def bad_uv(doc, geom):
        geom["texture"]["summer"]["values"][0][3][0][1] = len(doc["appearance"]["vertices-texture"])

    def short_ring(doc, geom):
        geom["texture"]["summer"]["values"][0][3][0].pop()

    def outside(doc, geom):   # snow.png is clamped: a UV of 1.5 is drawn as 1
        doc["appearance"]["vertices-texture"][geom["texture"]["winter"]["values"][0][3][0][1]] = [1.5, 0.0]

    with pytest.raises(InputFileError, match=r"t\.json: texture index 7 out of range \(2 textures\)"):
        read_cityjson(edit("t.json", bad_texture), {"theme": "summer"})
    with pytest.raises(InputFileError, match=r"u\.json: texture coordinate index out of range"):
        read_cityjson(edit("u.json", bad_uv), {"theme": "summer"})
    with pytest.warns(UserWarning, match=r"texture values do not match their rings drawn in colour \(1x\)"):
        parts = {p.name: p for p in read_cityjson(edit("s.json", short_ring), {"theme": "summer"}).parts}
    assert parts["facade.png"].n_triangles == 8 and parts["wall"].n_triangles == 6
    with pytest.warns(UserWarning, match=r"outside \[0, 1\] under wrapMode 'clamp' clamped"):
        snow = next(p for p in read_cityjson(edit("o.json", outside), {}).parts if p.name == "snow.png")
    assert snow.uv[:, 0].max() == 1.0 and snow.uv[:, 0].min() == 0.0


#: sha256 of Delft's parts (name, vertices, faces, colours) as load_cityjson gave them before appearances
DELFT_DIGEST = "dbb5f738152231d642384fd1f5d989c21a39e4e726cb50544095c15fe26999da"


def test_delft_without_appearance_reads_as_before(delft_mesh):
    """The parts of Delft (no appearance) byte for byte as the reader gave them before it read
    appearances (sha256 of names, vertices, faces, colours, taken at commit 035f2a5)."""
    import hashlib

    digest = hashlib.sha256()
    for part in delft_mesh.parts:
        assert part.uv is None and part.texture is None
        for data in (part.name.encode(), part.vertices.tobytes(), part.faces.tobytes(), part.colors.tobytes()):
            digest.update(data)
    assert digest.hexdigest() == DELFT_DIGEST


def test_textured_roof_renders_its_image(tmp_path, gl_ctx):
    """A flat textured roof at nadir, one texel per pixel: the rendered tile shows the image."""
    from PIL import Image
    from test_render import E0, GSD, N0, SIZE, Z0, view

    from pipeline25d.formats.cityjson import read_cityjson
    from pipeline25d.geometry.perspectives import Perspective
    from pipeline25d.stages.render import TileRenderer

    image = np.asarray(Image.open(io.BytesIO(_png(tmp_path / "roof.png", 3, (32, 32)))))
    x0, y0, s = E0 + 8, N0 + 8, 32 * GSD
    geom = {"type": "MultiSurface", "lod": "2", "boundaries": [[[0, 1, 2, 3]]],
            "texture": {"t": {"values": [[[0, 0, 1, 2, 3]]]}}}
    path = _model(tmp_path, {"r": {"type": "Building", "geometry": [geom]}},
                  [[x0, y0, Z0], [x0 + s, y0, Z0], [x0 + s, y0 + s, Z0], [x0, y0 + s, Z0]],
                  appearance={"textures": [{"type": "PNG", "image": "roof.png"}],
                              "vertices-texture": [[0, 0], [1, 0], [1, 1], [0, 1]]})
    parts = read_cityjson(path, {}).parts
    rgba = TileRenderer(gl_ctx, samples=0).render_color([(np.array([E0, N0, Z0]), parts)], view(Perspective(0, 90)))
    top, col = round((N0 + SIZE * GSD - (y0 + s)) / GSD), round((x0 - E0) / GSD)
    assert np.abs(rgba[top:top + 32, col:col + 32, :3].astype(int) - image).max() <= 2
