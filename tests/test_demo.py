"""Tests of the demo-city generator against independent computations.

A small scene (scale 0.5, 40 buildings) is generated once per module; each test
checks one property with its own arithmetic (separating axes, GDAL's bilinear
resampling, a least-squares fit), not with the generator's helpers.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from pipeline25d_lab.scenes import demo
from pipeline25d_lab.scenes.demo import generate_demo_city, terrain_height

SEED = 7
N = 40
SCALE = 0.5
MATERIALS = {"road", "roof_red", "roof_grey", "roof_dark", "facade_0", "facade_1", "facade_2"}


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> tuple[Path, dict, dict]:
    out = tmp_path_factory.mktemp("demo")
    manifest = generate_demo_city(out, seed=SEED, n_buildings=N, scale=SCALE)
    truth = json.loads((out / "truth.json").read_text())
    return out, manifest, truth


@pytest.fixture(scope="module")
def loaded(scene):
    """Every district loaded with trimesh as a Scene (one geometry per material)."""
    import trimesh

    out, manifest, _ = scene
    return {name: trimesh.load(out / path, force="scene") for name, path in manifest["districts"].items()}


def _separated(a: np.ndarray, b: np.ndarray) -> bool:
    """True when convex polygons a, b (k, 2) have a separating axis (interiors disjoint)."""
    for poly in (a, b):
        edges = np.roll(poly, -1, axis=0) - poly
        for nx, ny in np.column_stack([-edges[:, 1], edges[:, 0]]):
            pa, pb = a @ (nx, ny), b @ (nx, ny)
            if pa.max() <= pb.min() + 1e-9 or pb.max() <= pa.min() + 1e-9:
                return True
    return False


def _road_rect(road: dict) -> np.ndarray:
    """The 4 corners of a road strip from its centreline and width."""
    (x0, y0), (x1, y1) = road["centerline"]
    h = road["width"] / 2
    if road["kind"] == "ew":
        return np.array([[x0, y0 - h], [x1, y1 - h], [x1, y1 + h], [x0, y0 + h]])
    return np.array([[x0 - h, y0], [x1 + h, y0], [x1 + h, y1], [x0 - h, y1]])


def test_manifest_and_files(scene):
    out, manifest, truth = scene
    assert manifest == json.loads((out / "manifest.json").read_text())
    assert manifest["crs"] == truth["crs"] == "EPSG:25832"
    assert manifest["districts"] == {f"d{i}": f"d{i}.obj" for i in range(4)}
    assert manifest["n_buildings"] == N == len(truth["buildings"])
    assert manifest["seed"] == SEED
    names = sorted(os.listdir(out))
    assert not [n for n in names if n.startswith(".")], "temporary files left behind"
    expected = {"dtm.tif", "truth.json", "streets.geojson", "manifest.json"} | {f"facade_{k}.png" for k in range(3)}
    expected |= {f"d{i}.{ext}" for i in range(4) for ext in ("obj", "mtl")}
    assert set(names) == expected
    # the district lies at the UTM position the scene promises
    assert truth["districts"]["d0"]["bounds"][:2] == [691000.0, 5334000.0]


def test_every_obj_loads_with_materials_colours_and_textures(scene, loaded):
    _, manifest, _ = scene
    n_triangles = 0
    for name, sc in loaded.items():
        geoms = sc.geometry
        assert {"terrain", "road"} <= set(geoms), name
        assert set(geoms) - {"terrain"} <= MATERIALS, name
        assert any(k.startswith("facade_") for k in geoms) and any(k.startswith("roof_") for k in geoms)
        terrain = geoms["terrain"]
        assert terrain.visual.kind == "vertex"
        rgb = terrain.visual.vertex_colors[:, :3].astype(float)
        assert (rgb[:, 1] > rgb[:, 0]).all() and (rgb[:, 1] > rgb[:, 2]).all(), "terrain not green"
        assert rgb.std(axis=0).max() > 1.0, "terrain colours have no noise"
        for key, g in geoms.items():
            if key.startswith("facade_"):
                assert g.visual.uv is not None and len(g.visual.uv) == len(g.vertices)
                assert g.visual.material.image is not None and g.visual.material.image.size == (256, 256)
            elif key != "terrain":
                assert g.visual.material.image is None
            n_triangles += len(g.faces)
    assert n_triangles == manifest["n_triangles"]


def test_the_streets_layer_is_every_road_centreline_in_the_scene_crs_as_ogr_reads_it(scene):
    """streets.geojson (the demo's street overlay) through OGR: one line per road of truth, its two ends,
    in EPSG:25832 (the file's crs member)."""
    from osgeo import ogr, osr

    out, _, truth = scene
    ds = ogr.Open(str(out / "streets.geojson"))          # kept: the layer lives as long as its dataset
    layer = ds.GetLayer()
    want = osr.SpatialReference()
    want.ImportFromEPSG(25832)
    assert layer.GetSpatialRef().IsSame(want)
    got = {f.GetField("id"): np.array(f.GetGeometryRef().GetPoints()) for f in layer}
    assert got.keys() == {r["id"] for r in truth["roads"]}
    for r in truth["roads"]:
        np.testing.assert_array_equal(got[r["id"]], np.array(r["centerline"]))


def test_each_building_road_and_the_terrain_is_an_obj_object_named_as_in_truth(scene):
    """The product's OBJ reader finds one object per building (truth's id), per road and the terrain:
    a building's faces lie on its footprint (within 1 mm), from its walls' sunk base to its ridge, and
    it has all of its roof's and walls' triangles (4 walls of 2, gables 1 more each; roof 2, gabled 4)."""
    from matplotlib.path import Path as Polygon

    from pipeline25d.formats.meshfile import load_mesh_file

    out, manifest, truth = scene
    for name, path in manifest["districts"].items():
        faces: dict[str, list[np.ndarray]] = {}
        for part in load_mesh_file(out / path).parts:
            for k, key in enumerate(part.objects):
                faces.setdefault(key, []).append(part.vertices[part.faces[part.face_objects == k]])
        buildings = {b["id"]: b for b in truth["buildings"] if b["district"] == name}
        roads = {r["id"] for r in truth["roads"] if r["district"] == name}
        assert set(faces) == set(buildings) | roads | {"terrain"}, name
        for bid, b in buildings.items():
            tri = np.concatenate(faces[bid])
            assert len(tri) == (8 + 2 if b["roof"] == "flat" else 10 + 4), bid
            xyz = tri.reshape(-1, 3)
            assert Polygon(np.asarray(b["footprint"])).contains_points(xyz[:, :2], radius=2e-3).all() or \
                Polygon(np.asarray(b["footprint"])).contains_points(xyz[:, :2], radius=-2e-3).all(), bid
            assert xyz[:, 2].min() == pytest.approx(b["base_z"] - 1.0, abs=1e-3)
            assert xyz[:, 2].max() == pytest.approx(b["ridge_z"], abs=1e-3)


def test_obj_text_is_triangles_with_3_decimals(scene):
    out, _, _ = scene
    text = (out / "d0.obj").read_text()
    faces = [line.split() for line in text.splitlines() if line.startswith("f ")]
    assert faces and all(len(f) == 4 for f in faces)
    v = [line.split() for line in text.splitlines() if line.startswith("v ")]
    assert all(len(parts) == 7 for parts in v)  # x y z r g b
    assert all(len(parts[1].split(".")[1]) == 3 for parts in v[:100])


def test_geometry_inside_district_bounds_and_empty_blocks_empty(scene, loaded):
    _, _, truth = scene
    for name, sc in loaded.items():
        xmin, ymin, xmax, ymax = truth["districts"][name]["bounds"]
        lo, hi = sc.bounds
        assert lo[0] >= xmin - 1e-3 and lo[1] >= ymin - 1e-3, name
        assert hi[0] <= xmax + 1e-3 and hi[1] <= ymax + 1e-3, name
    # district bounds are grid blocks; the other five blocks get nothing
    size = truth["grid"]["block_size"]
    assert size == 240.0 * SCALE
    blocks = {tuple(b) for b in truth["grid"]["district_blocks"].values()}
    assert blocks == {(0, 0), (1, 0), (0, 1), (2, 2)}
    assert len(truth["grid"]["empty_blocks"]) == 5


def test_buildings_plausible_and_inside_district(scene):
    _, _, truth = scene
    per_district = {}
    for b in truth["buildings"]:
        per_district[b["district"]] = per_district.get(b["district"], 0) + 1
        fp = np.array(b["footprint"], dtype=np.float64)
        assert fp.shape == (4, 2)
        sides = np.linalg.norm(np.roll(fp, -1, axis=0) - fp, axis=1)
        assert (sides >= 8.0 - 2e-3).all() and (sides <= 30.0 + 2e-3).all(), b["id"]
        area2 = np.sum(fp[:, 0] * np.roll(fp[:, 1], -1) - np.roll(fp[:, 0], -1) * fp[:, 1])
        assert area2 > 0, "footprint not counter-clockwise"
        xmin, ymin, xmax, ymax = truth["districts"][b["district"]]["bounds"]
        assert (fp[:, 0] > xmin).all() and (fp[:, 0] < xmax).all()
        assert (fp[:, 1] > ymin).all() and (fp[:, 1] < ymax).all()
        height = b["eave_z"] - b["base_z"]
        assert 6.0 - 1e-3 <= height <= 45.0 + 1e-3
        if b["roof"] == "gabled":
            assert 2.0 - 1e-3 <= b["ridge_z"] - b["eave_z"] <= 5.0 + 1e-3
        else:
            assert b["roof"] == "flat" and b["ridge_z"] == b["eave_z"]
        # base_z = lowest terrain under the footprint (independent dense sampling)
        s, t = np.meshgrid(np.linspace(0, 1, 61), np.linspace(0, 1, 61))
        pts = fp[0] + s.reshape(-1, 1) * (fp[1] - fp[0]) + t.reshape(-1, 1) * (fp[3] - fp[0])
        assert abs(terrain_height(pts[:, 0], pts[:, 1]).min() - b["base_z"]) < 0.01
    assert sorted(per_district) == ["d0", "d1", "d2", "d3"]
    assert max(b["eave_z"] - b["base_z"] for b in truth["buildings"]) >= 30.0, "no tower"


def test_no_footprint_overlaps_another_or_a_road(scene):
    _, _, truth = scene
    fps = [np.array(b["footprint"]) for b in truth["buildings"]]
    for i in range(len(fps)):
        for j in range(i + 1, len(fps)):
            assert _separated(fps[i], fps[j]), (truth["buildings"][i]["id"], truth["buildings"][j]["id"])
    roads = [_road_rect(r) for r in truth["roads"]]
    assert len(roads) >= 8
    for b, fp in zip(truth["buildings"], fps):
        for road, rect in zip(truth["roads"], roads):
            if road["district"] == b["district"]:
                assert _separated(fp, rect), (b["id"], road["id"])


def test_separating_axis_helper_detects_overlap():
    square = np.array([[0, 0], [10, 0], [10, 10], [0, 10]], dtype=float)
    assert not _separated(square, square + 5)
    assert _separated(square, square + [10.5, 0])
    rotated = np.array([[15, 5], [20, 10], [15, 15], [10, 10]], dtype=float)  # diamond touching x=10
    assert _separated(square, rotated)
    assert not _separated(square, rotated - [1, 0])


def test_walls_reach_below_terrain_and_roofs_reach_ridge(scene, loaded):
    _, _, truth = scene
    for name, sc in loaded.items():
        mine = [b for b in truth["buildings"] if b["district"] == name]
        facades = [g for k, g in sc.geometry.items() if k.startswith("facade_")]
        roofs = [g for k, g in sc.geometry.items() if k.startswith("roof_")]
        zmin = min(g.bounds[0, 2] for g in facades)
        assert zmin == pytest.approx(min(b["base_z"] for b in mine) - 1.0, abs=1e-3)
        assert max(g.bounds[1, 2] for g in roofs) == pytest.approx(max(b["ridge_z"] for b in mine), abs=1e-3)


def test_terrain_vertices_lie_on_terrain_function(loaded):
    for name, sc in loaded.items():
        v = sc.geometry["terrain"].vertices
        assert len(v) >= 25 * 25
        np.testing.assert_allclose(v[:, 2], terrain_height(v[:, 0], v[:, 1]), atol=1e-3, rtol=0)
        steps = np.diff(np.unique(np.round(v[:, 0], 3)))
        np.testing.assert_allclose(steps, 5.0, atol=1e-3)
        road = sc.geometry["road"].vertices
        np.testing.assert_allclose(road[:, 2] - terrain_height(road[:, 0], road[:, 1]), 0.05, atol=1.5e-3)


def test_terrain_function_is_gentle_and_cubic_like():
    # over the full-size DTM: relief within 15 m and a full cubic fits within 0.6 m
    u = np.linspace(-20.0, 740.0, 96)
    x, y = np.meshgrid(691000.0 + u, 5334000.0 + u)
    z = terrain_height(x, y)
    assert z.dtype == np.float64 and isinstance(terrain_height(691000.0, 5334000.0), float)
    assert 5.0 < z.max() - z.min() <= 15.0
    gy, gx = np.gradient(z, u, u)
    assert np.hypot(gx, gy).max() < 0.03
    xs, ys = (x - x.mean()) / 380.0, (y - y.mean()) / 380.0
    cols = [xs.ravel() ** i * ys.ravel() ** j for i in range(4) for j in range(4) if i + j <= 3]
    coef, *_ = np.linalg.lstsq(np.column_stack(cols), z.ravel(), rcond=None)
    residual = z.ravel() - np.column_stack(cols) @ coef
    assert np.abs(residual).max() < 0.6 and residual.std() < 0.1


def test_dtm_matches_terrain_function(scene):
    from osgeo import gdal, osr

    out, _, truth = scene
    ds = gdal.Open(str(out / "dtm.tif"))
    band = ds.GetRasterBand(1)
    assert band.DataType == gdal.GDT_Float32
    srs = osr.SpatialReference(wkt=ds.GetProjection())
    srs.AutoIdentifyEPSG()
    assert srs.GetAuthorityCode(None) == "25832"
    x0, px, rx, top, ry, py = ds.GetGeoTransform()
    assert (px, py, rx, ry) == (1.0, -1.0, 0.0, 0.0)
    extent = 3 * truth["grid"]["block_size"]
    assert x0 <= 691000.0 - 20.0 and x0 + ds.RasterXSize >= 691000.0 + extent + 20.0
    assert top - ds.RasterYSize <= 5334000.0 - 20.0 and top >= 5334000.0 + extent + 20.0

    # pixel centres hold terrain_height (float32 storage)
    arr = band.ReadAsArray().astype(np.float64)
    rows, cols = np.mgrid[0:arr.shape[0]:37, 0:arr.shape[1]:41]
    expect = terrain_height(x0 + cols + 0.5, top - rows - 0.5)
    np.testing.assert_allclose(arr[rows, cols], expect, atol=1e-4, rtol=0)

    # GDAL's own bilinear resampling at random points off the pixel centres
    rng = np.random.default_rng(0)
    for x, y in zip(rng.uniform(691000.0, 691000.0 + extent, 6), rng.uniform(5334000.0, 5334000.0 + extent, 6)):
        warped = gdal.Warp("", ds, format="MEM", outputBounds=(x - 0.5, y - 0.5, x + 0.5, y + 0.5),
                           width=1, height=1, resampleAlg="bilinear")
        value = float(warped.ReadAsArray()[0, 0])
        assert value == pytest.approx(terrain_height(x, y), abs=0.01)


def test_generation_is_deterministic(scene, tmp_path):
    out, _, _ = scene
    again = generate_demo_city(tmp_path, seed=SEED, n_buildings=N, scale=SCALE)
    for name in ["truth.json", "manifest.json", "d0.obj", "d3.obj", "d1.mtl", "facade_1.png"]:
        assert (tmp_path / name).read_bytes() == (out / name).read_bytes(), name
    assert again == json.loads((out / "manifest.json").read_text())


def test_second_call_touches_nothing_and_new_params_regenerate(tmp_path):
    first = generate_demo_city(tmp_path, seed=3, n_buildings=12, scale=0.4)
    stamps = {p.name: p.stat().st_mtime_ns for p in tmp_path.iterdir()}
    assert generate_demo_city(tmp_path, seed=3, n_buildings=12, scale=0.4) == first
    assert {p.name: p.stat().st_mtime_ns for p in tmp_path.iterdir()} == stamps

    truth_before = (tmp_path / "truth.json").read_bytes()
    second = generate_demo_city(tmp_path, seed=4, n_buildings=12, scale=0.4)
    assert second["seed"] == 4 and (tmp_path / "truth.json").read_bytes() != truth_before
    assert json.loads((tmp_path / "manifest.json").read_text()) == second


def test_missing_file_triggers_regeneration(tmp_path):
    generate_demo_city(tmp_path, seed=3, n_buildings=8, scale=0.4)
    (tmp_path / "d2.obj").unlink()
    generate_demo_city(tmp_path, seed=3, n_buildings=8, scale=0.4)
    assert (tmp_path / "d2.obj").is_file()


def test_bad_parameters_raise_config_error(tmp_path):
    from pipeline25d.core.errors import ConfigError

    with pytest.raises(ConfigError):
        generate_demo_city(tmp_path, scale=0.0)
    with pytest.raises(ConfigError):
        generate_demo_city(tmp_path, n_buildings=-1)
    with pytest.raises(ConfigError, match="cannot fit"):
        generate_demo_city(tmp_path, n_buildings=2000, scale=0.4)
    assert not (tmp_path / "manifest.json").exists()


def test_cli_prints_one_line_per_district(tmp_path, capsys):
    assert demo.main([str(tmp_path / "city"), "--seed", "5", "--buildings", "9", "--scale", "0.4"]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert [line.split()[2] for line in err[:4]] == ["d0", "d1", "d2", "d3"]
    manifest = json.loads((tmp_path / "city" / "manifest.json").read_text())
    assert manifest["seed"] == 5 and manifest["n_buildings"] == 9
    assert demo.main([str(tmp_path / "bad"), "--scale", "-1"]) == 2


def _inside_any(points: np.ndarray, footprints: list[np.ndarray]) -> np.ndarray:
    """Which (n, 2) points lie strictly inside one of the CCW convex footprints."""
    inside = np.zeros(len(points), dtype=bool)
    for fp in footprints:
        edges = np.roll(fp, -1, axis=0) - fp
        rel = points[:, None, :] - fp[None, :, :]
        cross = edges[None, :, 0] * rel[:, :, 1] - edges[None, :, 1] * rel[:, :, 0]
        inside |= (cross > 0).all(axis=1)
    return inside


def test_faces_point_outward_and_up(scene, loaded):
    _, _, truth = scene
    for name, sc in loaded.items():
        for key in ["terrain", "road"] + [k for k in sc.geometry if k.startswith("roof_")]:
            assert (sc.geometry[key].face_normals[:, 2] > 0.3).all(), (name, key)
        fps = [np.array(b["footprint"]) for b in truth["buildings"] if b["district"] == name]
        for key in [k for k in sc.geometry if k.startswith("facade_")]:
            g = sc.geometry[key]
            n = g.face_normals
            assert np.abs(n[:, 2]).max() < 1e-3, "walls are vertical (up to mm rounding)"
            c = g.triangles_center[:, :2]
            assert _inside_any(c - 0.05 * n[:, :2], fps).all()
            assert not _inside_any(c + 0.05 * n[:, :2], fps).any()


def test_facade_uv_repeats_windows_every_3_m(loaded):
    for sc in loaded.values():
        for key in [k for k in sc.geometry if k.startswith("facade_")]:
            g = sc.geometry[key]
            tri, uv = g.vertices[g.faces], g.visual.uv[g.faces]
            for i, j in [(0, 1), (1, 2), (2, 0)]:
                dxy = np.linalg.norm(tri[:, i, :2] - tri[:, j, :2], axis=1)
                dz = tri[:, i, 2] - tri[:, j, 2]
                du, dv = (uv[:, i] - uv[:, j]).T
                horizontal = (np.abs(dz) < 1e-6) & (dxy > 1.0)
                # 4 windows per texture: u advances 1/4 per window column of 2.5-3.5 m
                metres_per_window = dxy[horizontal] / np.abs(du[horizontal]) / 4
                assert ((metres_per_window > 2.5) & (metres_per_window < 3.5)).all()
                assert np.allclose(dv[horizontal], 0, atol=1e-4)
                vertical = (dxy < 1e-6) & (np.abs(dz) > 1.0)
                np.testing.assert_allclose(dz[vertical] / dv[vertical] / 4, 3.0, rtol=2e-3)
