"""Building-only city models: ``terrain: auto`` takes the ground from where the buildings stand.

Generated CityJSON 1.1 and CityGML 2.0 models of box buildings standing on a known sloped plane
(no terrain objects; pipeline25d_lab.scenes.building_city) run through the ingest, LOD, terrain
and scene stages; their DTM is checked against the analytic plane. Delft's CityJSON reduced to
its buildings is checked against the DTM of the full model (its own terrain objects).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import DATA, held_out, shared_file

from pipeline25d.config import chunk_size, perspectives, validate_schema
from pipeline25d.core.errors import GroundError
from pipeline25d.core.geotiff import read_float_geotiff
from pipeline25d.stages.terrain.bases import BASE_AGREEMENT_M, BaseTin, base_samples, with_bases
from pipeline25d_lab.scenes.building_city import (
    CRS,
    X0,
    Y0,
    boxes,
    plane,
    write_citygml_lod1,
    write_cityjson,
    write_obj,
)


def run_stages(tmp_path: Path, inputs: dict, gsd: float = 0.5, edit_ground=None, crs: str = CRS
               ) -> tuple[dict, dict, Path]:
    """Ingest, LOD, terrain (auto) and scene stages on ``inputs``: (terrain record, scene.json, DTM path).
    ``edit_ground(path)`` may change the terrain stage's ground heights before the scene stage."""
    from pipeline25d.stages.ingest import ingest
    from pipeline25d.stages.lod import build_lod, lod_chunks
    from pipeline25d.stages.scene import scene_setup
    from pipeline25d.stages.terrain.build import build_terrain

    cfg = validate_schema({"scene": "t", "crs": crs, "inputs": inputs, "gsd": gsd, "lod": {"max_levels": 1}})
    max_error = gsd * cfg["lod"]["max_error_px"]
    lods = []
    for name, spec in inputs.items():
        chunks, lod = tmp_path / "chunks" / name / "index.json", tmp_path / "lod" / name / "index.json"
        ingest(spec, name, crs, chunk_size(cfg), max_error, chunks, gsd=gsd)
        build_lod(chunks, lod, max_error, cfg["lod"]["max_levels"])
        lods.append(str(lod))
    t = tmp_path / "terrain"
    record = build_terrain(lod_chunks(lods), inputs, crs, gsd, "auto", cfg["ground"], t / "dsm.tif", t / "ground.tif",
                           t / "terrain.json")
    if edit_ground is not None:
        edit_ground(t / "ground.tif")
    scene_setup(lods, t / "dsm.tif", "auto", t / "ground.tif", "auto", "auto", cfg["gcp"], crs, gsd,
                [p.id for p in perspectives(cfg)], tmp_path / "scene.json", tmp_path / "candidates.csv",
                t / "dtm.tif", cfg["ground"]["max_object_size"], t / "grounds.json", out_holdout=t / "dtm_holdout.csv")
    return record, json.loads((tmp_path / "scene.json").read_text()), t / "dtm.tif"


def dtm_at(path: Path, x, y) -> np.ndarray:
    values, grid = read_float_geotiff(path)
    col = np.floor((np.asarray(x) - grid.xmin) / grid.res).astype(int)
    row = np.floor((grid.ymax - np.asarray(y)) / grid.res).astype(int)
    return values[row, col].astype(np.float64)


def cell_centres_in(path: Path, box) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """x, y and DTM of the cell centres inside ``box`` (x0, y0, x1, y1)."""
    values, grid = read_float_geotiff(path)
    gx, gy = grid.cell_centres()
    inside = (gx > box[0]) & (gx < box[2]) & (gy > box[1]) & (gy < box[3])
    return gx[inside], gy[inside], values[inside].astype(np.float64)


def assert_plane_but_near_check_points(folder: Path, scene: dict, x, y, z) -> None:
    """DTM heights ``z`` at cell centres (x, y): the plane to the file's 1 mm vertices and float32,
    except within a cell of the discs left out of the DTM (scene stage: round every check point,
    and round a check square's site that no view sees), where the fill across the disc follows
    the local plane wherever the plain fill would be 2 x KEEP_M off (0.10-0.12 m on these slopes
    before the planes, 0.05-0.08 m after)."""
    from pipeline25d.stages.terrain.gap_planes import KEEP_M

    checks = held_out(folder / "terrain" / "dtm_holdout.csv", folder / "candidates.csv")
    near = np.zeros(len(x), bool)
    if len(checks):
        near = np.hypot(x[:, None] - checks[:, 0], y[:, None] - checks[:, 1]).min(axis=1) \
            <= scene["dtm_check_holdout_m"] + 2.0
    assert (~near).sum() > 0.5 * len(x)
    np.testing.assert_allclose(z[~near], plane(x[~near], y[~near]), atol=1e-3)
    np.testing.assert_allclose(z, plane(x, y), atol=2 * KEEP_M)


# ----------------------------------------------------------------------------- samples and the TIN


def test_wall_bottoms_are_the_corners_on_the_ground_not_window_sills(tmp_path):
    from pipeline25d.formats import load_district_buildings

    fps = boxes([(X0 + 10, Y0 + 10)], n=2)
    path = write_cityjson(tmp_path / "b.json", fps)
    mesh, others = load_district_buildings({"path": str(path)}, CRS)
    got = base_samples(mesh)
    assert not others and got.buildings == 4 and got.from_ground_surfaces == 2
    # the four bottom corners of each box, on the plane; nothing from the window (sill 1 m up)
    assert len(got.points) == 16
    np.testing.assert_allclose(got.points[:, 2], plane(got.points[:, 0], got.points[:, 1]), atol=6e-4)
    corners = {(round(x, 3), round(y, 3)) for fp in fps for x in fp[::2] for y in fp[1::2]}
    assert {(round(x, 3), round(y, 3)) for x, y, _ in got.points} == corners


def test_tin_is_the_plane_between_samples_and_leaves_far_ones_apart():
    rng = np.random.default_rng(3)
    xy = np.c_[rng.uniform(0, 100, 40), rng.uniform(0, 100, 40)]
    far = np.array([[1500.0, 1500.0], [1510.0, 1500.0], [1500.0, 1510.0]])
    pts = np.c_[np.r_[xy, far], np.zeros(43)]
    pts[:, 2] = 0.3 * pts[:, 0] - 0.1 * pts[:, 1] + 7.0
    tin = BaseTin(pts, max_edge=200.0)
    from pipeline25d.core.grid import Grid

    grid = Grid.covering((0, 0, 1520, 1520), 1.0)
    h = tin.heights(grid)
    gx, gy = grid.cell_centres()
    have = np.isfinite(h)
    # exact where a triangle covers the cell centre; a cell holding a sample but no covered centre
    # (a triangle's edge) takes the sample's own height: off by at most the slope over half a cell diagonal
    held = np.zeros(grid.shape, bool)
    held[np.floor(grid.ymax - pts[:, 1]).astype(int), np.floor(pts[:, 0] - grid.xmin).astype(int)] = True
    truth = 0.3 * gx - 0.1 * gy + 7.0
    np.testing.assert_allclose(h[have & ~held], truth[have & ~held], atol=1e-9)
    assert np.abs(h - truth)[have & held].max() <= np.hypot(0.3, 0.1) * np.sqrt(0.5) + 1e-9
    # cells only within the two groups: the hull of the 40 (< 100 m square) and the far triangle
    assert have.sum() < 100 * 100 + 10 * 10 and have[(gx > 200) & (gx < 1400)].sum() == 0


def box_triangles(fp, floor: bool, **kw) -> np.ndarray:
    """(m, 3, 3) triangles of a box of :func:`box_surfaces` (its floor where ``floor``)."""
    from pipeline25d_lab.scenes.building_city import box_surfaces

    verts, surfaces = box_surfaces(fp, floor, False, **kw)
    v = np.asarray(verts)
    return np.array([v[[r[0], r[k], r[k + 1]]] for rings, _ in surfaces for r in rings[:1] for k in (1, 2)])


@pytest.mark.parametrize("floors", [True, False])
def test_a_foot_on_a_roof_stands_and_a_neighbours_corner_does_not(floors):
    """``standing`` on boxes sharing a wall on the sloped plane (no vertex welded): the corners on the
    shared wall stand on the neighbour's floor edge or under its roof, at the same height, and are
    ground; a tower's feet on either box's roof stand, with a floor under them or without one
    (the box's top within 0.5 m and the box reaching 8 m lower)."""
    from pipeline25d.formats.surfaces import ROOF_NZ
    from pipeline25d.geometry.standing import standing
    from pipeline25d.stages.terrain.bases import BASE_TOL_M
    from pipeline25d_lab.scenes.building_city import roof_z, tower_on

    a, b = (X0, Y0, X0 + 12, Y0 + 9), (X0 + 12, Y0, X0 + 24, Y0 + 9)
    tower = tower_on(a)
    tris = [box_triangles(a, floors), box_triangles(b, floors),
            box_triangles(tower, True, height=15.0, floor_z=roof_z(a))]
    owner = np.concatenate([np.full(len(t), k) for k, t in enumerate(tris)])
    corners = np.array([(x, y) for fp in (a, b, tower) for x in fp[::2] for y in fp[1::2]])
    z = np.r_[plane(corners[:8, 0], corners[:8, 1]), np.full(4, roof_z(a))]
    got = standing(np.c_[corners, z], np.repeat([0, 1, 2], 4), np.concatenate(tris), owner, BASE_TOL_M, ROOF_NZ)
    np.testing.assert_array_equal(got, [False] * 8 + [True] * 4)


def test_filter_cells_keep_their_height_only_where_they_agree_with_the_bases():
    tin = np.array([10.0, 10.0, 10.0, np.nan, np.nan, 10.0])
    csf = np.array([10.4, 14.0, np.nan, 7.0, np.nan, 10.0 - BASE_AGREEMENT_M - 0.01])
    # agreeing: its own; a roof 4 m up: the TIN's; no filter cell: the TIN's; outside the TIN: the filter's
    np.testing.assert_array_equal(with_bases(csf, tin), [10.4, 10.0, 10.0, 7.0, np.nan, 10.0])


# ----------------------------------------------------------------------------- the stages


WRITERS = {"cityjson": lambda folder, fps: write_cityjson(folder / "city.json", fps),
           "citygml": lambda folder, fps: write_citygml_lod1(folder / "city.gml", fps),
           "obj": lambda folder, fps: write_obj(folder / "city.obj", fps)}


@pytest.mark.parametrize("fmt, from_floors", [("cityjson", 5), ("citygml", 9), ("obj", 3)])
def test_building_only_model_gets_the_plane_it_stands_on(tmp_path, gl_ctx, fmt, from_floors):
    """(a) DTM under and between the buildings equals the analytic plane; z0 is its median. The OBJ
    names no buildings: they are found by their shape (floors facing down on 3 of them, up on 3,
    none on 3: those give their wall bottoms)."""
    fps = boxes([(X0 + 20, Y0 + 20)])
    path = WRITERS[fmt](tmp_path, fps)
    record, scene, dtm = run_stages(tmp_path, {"city": {"path": str(path)}})
    bases = record["bases"]
    assert bases["buildings"] == 9 and bases["buildings_only"] == ["city"]
    assert bases["from_ground_surfaces"] == from_floors
    assert bases.get("by_shape", []) == (["city"] if fmt == "obj" else [])
    assert "building bases of city: 9 buildings" in record["source"] and "Cloth" not in record["source"]
    # under every building and between them (inside the hull of the bases): the plane, to the
    # file's 1 mm vertices (CityGML: posList written to 1 mm) and float32 (4e-7 m at 5 m)
    hull = (fps[0][0], fps[0][1], fps[-1][2], fps[-1][3])
    x, y, z = cell_centres_in(dtm, hull)
    assert len(x) > 4000
    assert_plane_but_near_check_points(tmp_path, scene, x, y, z)
    # z0: the median DTM height under the model, rounded to whole metres
    dsm, grid = read_float_geotiff(tmp_path / "terrain" / "dsm.tif")
    gx, gy = grid.cell_centres()
    covered = np.isfinite(dsm)
    assert scene["z0"] == round(float(np.median(plane(gx[covered], gy[covered]))))
    assert np.isfinite(scene["z0"])
    # GCP candidates: on the bare ground between the buildings (nothing else is ground here), on
    # the plane, clear of every wall by the marker radius and clearance (6 px · 0.5 m + 1 m = 4 m)
    from pipeline25d.stages.gcps import read_candidates

    cands = read_candidates(tmp_path / "candidates.csv")
    assert len(cands) >= 4 and scene["n_check"] >= 1
    for c in cands:
        assert hull[0] < c.x < hull[2] and hull[1] < c.y < hull[3]
        gap = min(max(x0 - c.x, c.x - x1, y0 - c.y, c.y - y1) for x0, y0, x1, y1 in fps)
        # a site is a DSM cell's centre (jittered by up to 0.4 cell): within a cell of the limit
        assert gap >= 4.0 - record["resolution"], (c, gap)
        assert c.z == pytest.approx(float(plane(c.x, c.y)), abs=0.02)


def test_bare_triangles_on_their_own_terrain_keep_the_cloth_filters_ground(tmp_path, gl_ctx):
    """The same boxes as bare triangles, on the plane drawn as a 5 m grid around them (a model that
    draws its own ground, as a photomesh or a LiDAR mesh does): no chunk has empty land, none is
    looked at for buildings, and the ground is the cloth filter's: the plane between the boxes."""
    fps = boxes([(X0 + 20, Y0 + 20)])
    path = write_obj(tmp_path / "city.obj", fps, terrain=True)
    record, scene, dtm = run_stages(tmp_path, {"city": {"path": str(path)}})
    assert "bases" not in record and record["source"] == "model surface (nadir DSM, Cloth Simulation Filter)"
    x, y, z = cell_centres_in(dtm, (fps[0][0] - 15, fps[0][1] - 15, fps[-1][2] + 15, fps[-1][3] + 15))
    between = np.array([all(max(x0 - a, a - x1, y0 - b, b - y1) > 2.0 for x0, y0, x1, y1 in fps)
                        for a, b in zip(x, y)])
    assert between.sum() > 2000
    assert_plane_but_near_check_points(tmp_path, scene, x[between], y[between], z[between])


def overhang_and_hillside_obj(path: Path, hill_path: Path, z0: float = 3.0) -> tuple[Path, Path]:
    """Two OBJs of bare triangles: a building on flat ground at ``z0`` whose upper storey overhangs
    its ground floor by 4 m (profile in x, z: ground floor 10 m wide and 3 m high, upper storey
    14 m wide, roof at 6 m; 8 m deep), and 20 m east of it a hillside (a 40 x 40 m grid rising
    0.5 m per m eastwards)."""
    x, y = X0 + 10, Y0 + 10
    profile = [(0, 0), (10, 0), (10, 3), (14, 3), (14, 6), (0, 6)]            # (x, z), counter-clockwise
    verts = [(x + a, y + d, z0 + c) for d in (0.0, 8.0) for a, c in profile]
    tris = [(0, 1, 2), (0, 2, 5), (2, 4, 5), (2, 3, 4)]                       # the profile at y and y + 8
    tris += [(6 + a, 6 + c, 6 + b) for a, b, c in tris]
    for k in range(6):                                                        # the sides, outwards
        a, b = k, (k + 1) % 6
        tris += [(a, b + 6, b), (a, a + 6, b + 6)]
    hill = [(x + 34 + 5 * i, y - 16 + 5 * j, z0 + 2.5 * i) for j in range(9) for i in range(9)]
    cells = [9 * j + i for j in range(8) for i in range(8)]
    hill_tris = [(a, a + 1, a + 10) for a in cells] + [(a, a + 10, a + 9) for a in cells]
    for out, (v, t) in ((path, (verts, tris)), (hill_path, (hill, hill_tris))):
        lines = [f"v {a:.3f} {b:.3f} {c:.3f}" for a, b, c in v] + [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in t]
        out.write_text("\n".join(lines) + "\n")
    return path, hill_path


def test_an_overhang_is_no_base_and_a_hillside_no_building(tmp_path, gl_ctx):
    """By shape: the overhanging building (one input) is a building whose ground is its floor, not
    the overhang's underside (3 m up, also facing down); the hillside (another), seen from above
    down to its lowest point, is no building, and keeps the cloth filter's ground. Both in one
    input, that input would draw its own ground, and the filter alone would give it."""
    from pipeline25d.formats import load_district
    from pipeline25d.stages.terrain.bases import components, welded

    path, hill = overhang_and_hillside_obj(tmp_path / "m.obj", tmp_path / "h.obj")
    mesh = load_district({"path": str(path)}, CRS)
    tri = np.concatenate([p.vertices[p.faces] for p in mesh.parts])
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    assert (normal[:, 2] < 0).sum() == 4                                # the floor and the underside
    points, faces = welded(tri.reshape(-1, 3), np.arange(3 * len(tri)).reshape(-1, 3))
    assert components(faces, len(points)).max() == 0                 # one group, one piece
    record, scene, dtm = run_stages(tmp_path, {"m": {"path": str(path)}, "h": {"path": str(hill)}})
    bases = record["bases"]
    assert bases["by_shape"] == ["m"] and bases["buildings"] == 1 and bases["from_ground_surfaces"] == 1
    assert bases["buildings_only"] == ["m"] and "Cloth" in record["source"]
    # under the building: its floor's height (3 m); under the overhang, which no base sample covers,
    # the DTM's fill from the ground around (within 3 cm of it), not the underside's 6 m
    x, y, z = cell_centres_in(dtm, (X0 + 10.5, Y0 + 10.5, X0 + 23.5, Y0 + 17.5))
    assert len(x) >= 60
    np.testing.assert_allclose(z[x < X0 + 20], 3.0, atol=1e-3)
    np.testing.assert_allclose(z, 3.0, atol=0.05)
    x, y, z = cell_centres_in(dtm, (X0 + 49, Y0 - 1, X0 + 69, Y0 + 19))                # the hillside's middle
    assert len(x) >= 300
    np.testing.assert_allclose(z, 3.0 + 0.5 * (x - X0 - 44), atol=0.1)


def test_a_plan_from_the_scenes_chunk_grounds_equals_one_that_samples_the_dtm_itself(tmp_path, gl_ctx):
    """The scene stage samples the DTM under every chunk once (terrain/grounds.json); a plan read
    from it is the plan that samples the DTM itself, byte for byte (tile spec hashes included)."""
    from pipeline25d.config import render_settings
    from pipeline25d.stages.plan import plans
    from pipeline25d.stages.scene import read_grounds

    path = write_cityjson(tmp_path / "city.json", boxes([(X0 + 20, Y0 + 20)]))
    _, scene, _ = run_stages(tmp_path, {"city": {"path": str(path)}})
    assert scene["projection"] == "terrain"
    grounds = read_grounds(tmp_path / "terrain" / "grounds.json")
    assert len(grounds) == scene["n_chunks"] >= 1
    assert all(g.lowest < g.highest and len(g.digest) == 12 for g in grounds.values())
    cfg = validate_schema({"scene": "t", "crs": CRS, "inputs": {"city": {"path": str(path)}}, "gsd": 0.5})
    lods = [str(tmp_path / "lod" / "city" / "index.json")]
    args = (lods, tmp_path / "scene.json", tmp_path / "candidates.csv", 0.5, 256, cfg["lod"]["max_error_px"], CRS,
            render_settings(cfg))
    plans({"az045_el45": tmp_path / "read.json"}, *args, grounds_json=tmp_path / "terrain" / "grounds.json")
    plans({"az045_el45": tmp_path / "sampled.json"}, *args)
    assert (tmp_path / "read.json").read_bytes() == (tmp_path / "sampled.json").read_bytes()
    assert b'"ground"' in (tmp_path / "read.json").read_bytes()


def test_far_apart_clusters_stay_cheap(tmp_path, gl_ctx):
    """(c) three clusters 5 km apart: the ground is computed near them only."""
    origins = [(X0, Y0), (X0 + 5000, Y0), (X0 + 2500, Y0 + 5000)]
    fps = boxes(origins, n=2)
    record, scene, dtm = run_stages(tmp_path, {"city": {"path": str(write_cityjson(tmp_path / "c.json", fps))}},
                                    gsd=0.25)
    values, grid = read_float_geotiff(dtm)
    from pipeline25d.stages.terrain.dsm import MAX_DSM_CELLS

    assert grid.width * grid.height <= MAX_DSM_CELLS
    # the bases' TIN covers each cluster's hull (42 x 39 m) and nothing between the clusters
    cluster = (42 / grid.res + 2) * (39 / grid.res + 2)
    assert 0 < record["bases"]["cells"] <= 3 * cluster
    # the DTM reaches twice the largest object (200 m) beyond the ground, and no farther
    reach = 200 / grid.res + 2
    assert np.isfinite(values).sum() <= 3 * (42 / grid.res + 2 * reach) * (39 / grid.res + 2 * reach)
    for ox, oy in origins:
        x, y, z = cell_centres_in(dtm, (ox, oy, ox + 42, oy + 39))
        assert_plane_but_near_check_points(tmp_path, scene, x, y, z)


def test_no_ground_near_a_chunk_is_an_error_naming_the_inputs(tmp_path, gl_ctx):
    """Ground nowhere near part of the model (here: the ground cells of one of two clusters 3 km
    apart removed): the project's error naming the input and what to do, never a NaN z0."""
    from pipeline25d.core.crs import horizontal_wkt
    from pipeline25d.core.geotiff import write_float_geotiff

    fps = boxes([(X0, Y0), (X0 + 3000, Y0)], n=1)

    def drop_the_second(path):
        values, grid = read_float_geotiff(path)
        values[:, grid.column_x() > X0 + 1500] = np.nan
        write_float_geotiff(path, values, grid, horizontal_wkt(CRS))

    with pytest.raises(GroundError, match=r"of the input\(s\) city: .*give a DTM .*or set terrain: flat"):
        run_stages(tmp_path, {"city": {"path": str(write_cityjson(tmp_path / "c.json", fps))}},
                   edit_ground=drop_the_second)


# ----------------------------------------------------------------------------- Delft


def write_bare_obj(path: Path, mesh) -> Path:
    """The mesh's triangles as an OBJ with no objects, groups or materials (vertices to 0.1 mm)."""
    lines, base = [], 0
    for part in mesh.parts:
        lines += [f"v {x:.4f} {y:.4f} {z:.4f}" for x, y, z in part.vertices]
        lines += [f"f {a} {b} {c}" for a, b, c in part.faces + base + 1]
        base += len(part.vertices)
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.mark.parametrize("form", ["cityjson", "obj"])
def test_delft_buildings_alone_get_the_ground_of_the_full_model(tmp_path, gl_ctx, form):
    """(b) Delft's CityJSON reduced to its Building objects: no NaN, and the DTM at the building
    bases agrees with the full model's (whose ground is its own LandUse/Road/WaterBody objects).
    As an OBJ of bare triangles the buildings are found by their shape, and agree as well."""
    from pipeline25d.formats import load_district_buildings

    doc = json.loads(shared_file(DATA / "delft" / "delft.json").read_text())
    doc["CityObjects"] = {k: o for k, o in doc["CityObjects"].items() if o["type"] == "Building"}
    only = tmp_path / "buildings.json"
    only.write_text(json.dumps(doc))
    mesh, _ = load_district_buildings({"path": str(only)}, CRS)
    model = only if form == "cityjson" else write_bare_obj(tmp_path / "buildings.obj", mesh)
    record, scene, dtm = run_stages(tmp_path / "b", {"delft": {"path": str(model)}})
    full_record, _, full_dtm = run_stages(tmp_path / "f", {"delft": {"path": str(DATA / "delft" / "delft.json")}})
    assert record["bases"]["buildings_only"] == ["delft"] and "bases" not in full_record
    assert record["bases"].get("by_shape", []) == (["delft"] if form == "obj" else [])
    pts = base_samples(mesh).points
    a, b = dtm_at(dtm, pts[:, 0], pts[:, 1]), dtm_at(full_dtm, pts[:, 0], pts[:, 1])
    assert np.isfinite(a).all() and np.isfinite(b).all() and np.isfinite(scene["z0"])
    diff = a - b
    print(f"Delft bases: {len(pts)} samples, DTM buildings-only - full: median {np.median(diff):+.3f} m, "
          f"mean |d| {np.abs(diff).mean():.3f} m, 90% {np.quantile(np.abs(diff), 0.9):.3f} m, "
          f"max {np.abs(diff).max():.3f} m")
    assert abs(np.median(diff)) < 0.15 and np.quantile(np.abs(diff), 0.9) < 0.5


@pytest.mark.parametrize("model, crs, gsd, features",
                         [("tokyo-chiyoda-b3dm/cesium-rtc-extension.b3dm", "EPSG:6677", 2.0, 300),
                          ("amsterdam-3dtiles/tileset.json", "EPSG:28992", 1.0, 200),
                          ("amsterdam-3dtiles/tileset.json", "EPSG:28992", 2.0, 200)])
def test_real_buildings_only_3d_tiles_get_the_ground_they_stand_on(tmp_path, gl_ctx, model, crs, gsd, features):
    """3D Tiles of buildings alone, with no terrain and no semantics a reader could ask for: PLATEAU's
    LOD2 buildings of Chiyoda as one b3dm (300 buildings with floors), pg2b3dm's Amsterdam tileset
    (200 blocks, no floor facing down: their wall bottoms). Found by their shape, they are the whole
    model, and the DTM under every building is where its lowest vertex is. The cloth filter alone
    had taken the lowest roofs for ground: on Tokyo at this gsd the scene stage then stopped (no
    ground near 6 of its chunks), and the ground it had lay 12.3 m above the feet of the 14
    buildings it reached (median)."""
    import warnings

    from pipeline25d.formats import load_district

    path = shared_file(DATA / model)
    record, _, dtm = run_stages(tmp_path, {"city": {"path": str(path)}}, gsd=gsd, crs=crs)
    bases = record["bases"]
    assert bases["by_shape"] == ["city"] == bases["buildings_only"] and "Cloth" not in record["source"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        mesh = load_district({"path": str(path)}, crs)
    vertices: dict[str, list[np.ndarray]] = {}        # each building's vertices, over the parts it has faces in
    for part in mesh.parts:
        for j in np.unique(part.face_objects):
            own = np.unique(part.faces[part.face_objects == j])
            vertices.setdefault(part.objects[j], []).append(part.vertices[own])
    feet = np.array([[*v[:, :2].mean(axis=0), v[:, 2].min()] for v in map(np.concatenate, vertices.values())])
    under = dtm_at(dtm, feet[:, 0], feet[:, 1]) - feet[:, 2]
    assert len(feet) == features and np.isfinite(under).all()
    print(f"{model}: {bases['buildings']} buildings by shape; DTM at a building's middle - its lowest vertex: "
          f"median {np.median(under):+.3f} m, 90% of |d| {np.quantile(np.abs(under), 0.9):.3f} m, "
          f"max |d| {np.abs(under).max():.2f} m")
    assert abs(np.median(under)) < 0.05 and np.quantile(np.abs(under), 0.9) < 0.5


@pytest.mark.parametrize("fmt", ["cityjson-part", "cityjson-building", "obj"])
def test_a_tower_on_a_roof_is_no_ground(tmp_path, gl_ctx, fmt):
    """Towers standing on the roofs of three of the boxes, each a separate solid sharing no vertex
    with its box (a storey set back, a penthouse, a PLATEAU or CityGML BuildingPart): as a
    BuildingPart with its own GroundSurface on the roof, as a Building of its own (its wall bottoms
    on the roof), or as bare triangles found by their shape. Their feet, 8 m above the ground, are
    no ground samples: the DTM under and between the boxes is the plane, as without the towers."""
    from pipeline25d.formats import load_district_buildings
    from pipeline25d_lab.scenes.building_city import roof_z, tower_on

    fps = boxes([(X0 + 20, Y0 + 20)])
    towers = (0, 4, 7)
    if fmt == "obj":
        path = write_obj(tmp_path / "city.obj", fps, towers=towers)
    else:
        path = write_cityjson(tmp_path / "city.json", fps, towers=towers, tower_part=fmt == "cityjson-part")
        mesh, _ = load_district_buildings({"path": str(path)}, CRS)
        got = base_samples(mesh)
        np.testing.assert_allclose(got.points[:, 2], plane(got.points[:, 0], got.points[:, 1]), atol=6e-4)
        assert (got.buildings, got.stacked) == (9, 3)          # a connected group is a building, a part or not
    record, scene, dtm = run_stages(tmp_path, {"city": {"path": str(path)}})
    assert (record["bases"]["buildings"], record["bases"]["stacked"]) == (9, 3)
    assert record["source"].endswith("; 3 standing on others")
    hull = (fps[0][0], fps[0][1], fps[-1][2], fps[-1][3])
    x, y, z = cell_centres_in(dtm, hull)
    on_roofs = np.zeros(len(x), bool)
    for i in towers:
        t = tower_on(fps[i])
        on_roofs |= (x > t[0]) & (x < t[2]) & (y > t[1]) & (y < t[3])
        assert roof_z(fps[i]) - plane(t[0], t[1]) > 7.9
    assert on_roofs.sum() > 40                                   # cell centres under the towers
    assert_plane_but_near_check_points(tmp_path, scene, x, y, z)


def test_a_parts_floor_on_the_roof_is_not_its_buildings_own_ground(tmp_path):
    """The heights' reference ground of a Building (formats.cityjson_buildings: its own ground
    surfaces, its parts' included) leaves out a tower part's GroundSurface on the roof: the podium's
    floor alone, the plane under it (its mean over the box is the plane at its centre). Where the
    only ground surface is the tower's (box 7 has none of its own), there is no own ground (NaN),
    not the roof's height. Before, box 0's came out 1.2 m high (18 m² at 8.5 m over 108 m²)."""
    from pipeline25d.formats.cityjson_buildings import cityjson_buildings

    fps = boxes([(X0 + 20, Y0 + 20)])
    path = write_cityjson(tmp_path / "city.json", fps, towers=(0, 4, 7), tower_part=True)
    refs = cityjson_buildings(path, CRS)
    for i, fp in enumerate(fps):
        own = refs[f"b{i}"].own_ground_z
        if i == 7:
            assert np.isnan(own)
        elif i % 2 == 0:                                    # the boxes with a GroundSurface
            assert own == pytest.approx(float(plane((fp[0] + fp[2]) / 2, (fp[1] + fp[3]) / 2)), abs=1e-3)
        else:
            assert np.isnan(own)
