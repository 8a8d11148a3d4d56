"""Ingest (mesh files, chunking, unchanged chunks untouched), LOD errors, and DTM sampling."""

from __future__ import annotations

import zipfile

import numpy as np
import pytest
import trimesh
from conftest import DATA, box_part

from pipeline25d.core.mesh import Mesh, MeshPart
from pipeline25d.formats import load_district
from pipeline25d.stages.chunks import load_npz, pack_parts, save_npz, unpack_parts
from pipeline25d.stages.ingest import split_into_chunks, write_chunks
from pipeline25d.stages.lod import _simplify, build_levels, choose_level, surface_error, texture_drift


def grid_part(n: int = 40, step: float = 2.0, bump: float = 0.0) -> MeshPart:
    x, y = np.meshgrid(np.arange(n) * step, np.arange(n) * step)
    z = 10 + bump * np.sin(x / 7.0) * np.cos(y / 5.0)
    verts = np.column_stack([x.ravel() + 500000.0, y.ravel() + 5800000.0, z.ravel()])
    faces = []
    for i in range(n - 1):
        for j in range(n - 1):
            a = i * n + j
            faces += [[a, a + 1, a + n + 1], [a, a + n + 1, a + n]]
    return MeshPart(verts, np.array(faces), colors=np.full((len(verts), 4), 128, np.uint8))


def test_chunking_keeps_every_triangle_once():
    part = grid_part()
    chunks = split_into_chunks(Mesh([part]), chunk_size=25.0)
    assert sum(p.n_triangles for ps in chunks.values() for p in ps) == part.n_triangles
    assert len(chunks) == 16   # 78 m square over a 25 m grid starting on a cell edge: 4 × 4


def test_unchanged_chunks_keep_their_files(tmp_path):
    mesh = Mesh([grid_part()])
    write_chunks(mesh, "a", 25.0, tmp_path, tmp_path / "index.json")
    mtimes = {p.name: p.stat().st_mtime_ns for p in tmp_path.glob("c*.npz")}
    (tmp_path / "index.json").unlink()            # as Snakemake does before re-running
    moved = Mesh([grid_part()])
    moved.parts[0].vertices[0, 2] += 1.0            # one vertex of the first chunk changes
    write_chunks(moved, "a", 25.0, tmp_path, tmp_path / "index.json")
    changed = [p.name for p in tmp_path.glob("c*.npz") if p.stat().st_mtime_ns != mtimes[p.name]]
    assert len(changed) == 1


def test_a_chunks_textures_are_stored_as_they_are_and_its_geometry_compressed(tmp_path):
    """A texture's bytes (a PNG, a JPEG, an uncompressed TGA) go into the npz uncompressed: the
    image is compressed already or kept raw to be read without decoding; the rest is deflated."""
    rng = np.random.default_rng(5)
    texture = bytes(18) + rng.integers(0, 256, 4096, dtype=np.uint8).tobytes()
    part = grid_part()
    part = MeshPart(part.vertices, part.faces, uv=np.zeros((len(part.vertices), 2)), texture=texture)
    save_npz(tmp_path / "c.npz", pack_parts([part], np.zeros(3)))
    with zipfile.ZipFile(tmp_path / "c.npz") as zf:
        kinds = {i.filename: i.compress_type for i in zf.infolist()}
    assert kinds.pop("p0_tex.npy") == zipfile.ZIP_STORED
    assert set(kinds.values()) == {zipfile.ZIP_DEFLATED}
    (back,) = unpack_parts(load_npz(tmp_path / "c.npz"), np.zeros(3))
    assert back.texture == texture
    np.testing.assert_array_equal(back.faces, part.faces)


def test_a_lod_pyramid_is_stored_uncompressed_and_reads_back_as_its_levels(tmp_path):
    """LOD files are read by every render job that draws them: every member stored, the levels
    and their hash what they were built from."""
    from pipeline25d.stages.chunks import content_hash
    from pipeline25d.stages.lod import build_chunk_lod, load_chunk_level

    part = grid_part()
    save_npz(tmp_path / "c.npz", {"origin": np.zeros(3), **pack_parts([part], np.zeros(3))})
    info = build_chunk_lod(tmp_path / "c.npz", tmp_path / "lod.npz", 0.5, 3)
    with zipfile.ZipFile(tmp_path / "lod.npz") as zf:
        assert {i.compress_type for i in zf.infolist()} == {zipfile.ZIP_STORED}
    data = load_npz(tmp_path / "lod.npz")
    assert content_hash({k: data[k] for k in data.files}) == info["hash"]
    origin, (finest,) = load_chunk_level(tmp_path / "lod.npz", 0)
    np.testing.assert_array_equal(finest.faces, part.faces)
    np.testing.assert_array_equal(finest.vertices, part.vertices)
    assert len(info["triangles"]) == int(data["n_levels"])


def test_district_lod_rebuilds_only_changed_chunks_and_removes_stale_ones(tmp_path):
    from pipeline25d.stages.chunks import content_hash, load_npz
    from pipeline25d.stages.lod import build_lod, lod_chunks

    chunks, lod = tmp_path / "chunks", tmp_path / "lod"

    def run(part: MeshPart, max_error: float = 0.5) -> dict[str, int]:
        for index in (chunks / "index.json", lod / "index.json"):    # as Snakemake does before re-running
            index.unlink(missing_ok=True)
        write_chunks(Mesh([part]), "a", 25.0, chunks, chunks / "index.json")
        build_lod(chunks / "index.json", lod / "index.json", max_error, 4)
        return {p.name: p.stat().st_mtime_ns for p in lod.glob("c*.npz")}

    first = run(grid_part(bump=2.0))
    entries = lod_chunks([lod / "index.json"])
    assert len(first) == len(entries) == 16 and {e.district for e in entries} == {"a"}
    for e in entries:
        data = load_npz(e.npz)
        assert e.hash == content_hash({k: data[k] for k in data.files}) and len(e.errors) == int(data["n_levels"])

    part = grid_part(bump=2.0)
    part.vertices[0, 2] += 1.0                                           # one vertex of one chunk changes
    x = part.vertices[part.faces].mean(axis=1)[:, 0] - 500000.0
    cut = MeshPart(part.vertices, part.faces[x < 75], colors=part.colors)  # and the last column of chunks goes
    second = run(cut)
    assert len(second) == 12 and sum(second[k] != first[k] for k in second) == 1
    before, after = ({e.id: e for e in es} for es in (entries, lod_chunks([lod / "index.json"])))
    assert all(after[k[:-4]] == before[k[:-4]] for k in second if second[k] == first[k])   # same entries kept
    third = run(cut, max_error=0.4)                                       # new LOD settings: every chunk again
    assert all(third[k] != second[k] for k in third)


def test_district_lod_on_two_processes_writes_the_same_files(tmp_path):
    """A district's chunks built by two forked workers: the same index and LOD files, byte for
    byte, as one process builds (a city that is one district uses both cores)."""
    from pipeline25d.stages.lod import build_lod

    chunks = tmp_path / "chunks"
    write_chunks(Mesh([grid_part(bump=2.0)]), "a", 25.0, chunks, chunks / "index.json")
    built = {}
    for processes in (1, 2):
        lod = tmp_path / f"lod{processes}"
        index = build_lod(chunks / "index.json", lod / "index.json", 0.5, 4, processes=processes)
        assert len(index["chunks"]) == 16
        built[processes] = {p.name: p.read_bytes() for p in sorted(lod.iterdir())}
    assert built[1].keys() == built[2].keys() and len(built[1]) == 16 + 2    # npz files, index, hashes
    assert all(built[1][k] == built[2][k] for k in built[1])


def test_the_worker_count_is_asked_for_only_where_a_district_has_enough_triangles(tmp_path, monkeypatch):
    """Counting idle cores sleeps 0.1 s: a small district (most of a tiled city's) is built here
    without asking; one of POOL_TRIANGLES or more asks, and gets the count it is given."""
    import json

    from pipeline25d.stages import lod as lod_stage

    chunks = tmp_path / "chunks"
    write_chunks(Mesh([grid_part(bump=2.0)]), "a", 25.0, chunks, chunks / "index.json")
    triangles = sum(c["n_triangles"] for c in json.loads((chunks / "index.json").read_text())["chunks"].values())
    asked = []

    def workers() -> int:
        asked.append(True)
        return 2

    for threshold, expect in ((triangles + 1, []), (triangles, [True])):
        monkeypatch.setattr(lod_stage, "POOL_TRIANGLES", threshold)
        asked.clear()
        out = tmp_path / f"lod{threshold}"
        lod_stage.build_lod(chunks / "index.json", out / "index.json", 0.5, 4, processes=workers)
        assert asked == expect and len(list(out.glob("*.npz"))) == 16


def test_lod_errors_are_measured_and_levels_chosen_by_pixel_size():
    flat = build_levels(Mesh([grid_part(bump=0.0)]), max_error=0.1, max_levels=5)
    assert len(flat) >= 3 and all(e < 1e-6 for _, e in flat)          # a plane simplifies exactly
    bumpy = build_levels(Mesh([grid_part(bump=2.0)]), max_error=10.0, max_levels=5)
    errors = [e for _, e in bumpy]
    assert errors[0] == 0 and all(b >= a for a, b in zip(errors, errors[1:])) and errors[-1] > 0.01
    # independent check of every level's error: two-way Hausdorff distance between densely and
    # evenly sampled surfaces (trimesh's sampling and closest-point queries, not ours)
    origin = np.array([500000.0, 5800000.0, 0.0])
    orig = trimesh.Trimesh(bumpy[0][0][0].vertices - origin, bumpy[0][0][0].faces)
    for k, (parts, error) in enumerate(bumpy[1:], start=1):
        level = trimesh.Trimesh(parts[0].vertices - origin, parts[0].faces)
        there = trimesh.sample.sample_surface_even(orig, 20000, seed=k)[0]
        back = trimesh.sample.sample_surface_even(level, 20000, seed=k)[0]
        hausdorff = max(trimesh.proximity.closest_point(level, np.vstack([there, orig.vertices]))[1].max(),
                        trimesh.proximity.closest_point(orig, np.vstack([back, level.vertices]))[1].max())
        assert hausdorff * 0.97 <= error <= hausdorff * 1.10, (k, error, hausdorff)
    assert choose_level([0.0, 0.1, 0.3, 0.9], 0.25) == 1 and choose_level([0.0, 0.5], 0.1) == 0


def _levels_measured_whole(mesh: Mesh, max_error: float, max_levels: int) -> list:
    """build_levels as it was before its bound: every part of a level simplified and measured
    exactly, then the level kept or building stopped."""
    rng, levels = np.random.default_rng(0), [(mesh.parts, 0.0)]
    for k in range(1, max_levels):
        parts, error = [], 0.0
        for part in mesh.parts:
            simple, mapping = _simplify(part, 1.0 - 0.5 ** k)
            error = max(error, surface_error(part, simple, rng), texture_drift(part, simple, mapping, rng))
            parts.append(simple)
        if error > max_error or sum(p.n_triangles for p in parts) > 0.85 * sum(p.n_triangles for p in levels[-1][0]):
            break
        levels.append((parts, error))
    return levels


@pytest.mark.parametrize("max_error", [0.05, 0.3, 1.0, 3.0])
def test_levels_stop_at_the_first_sample_beyond_the_bound_with_the_same_levels(max_error):
    """A level whose error exceeds max_error is dropped at its first sample found beyond it
    (its other parts not simplified): the levels kept, their errors and faces, are those of
    measuring every level whole."""
    mesh = Mesh([grid_part(bump=2.0), grid_part(n=30, step=3.0, bump=0.7)])
    got, want = build_levels(mesh, max_error, 6), _levels_measured_whole(mesh, max_error, 6)
    assert [e for _, e in got] == [e for _, e in want] and len(want) >= (1 if max_error < 0.1 else 2)
    for (parts, _), (ref, _) in zip(got, want):
        for a, b in zip(parts, ref):
            assert np.array_equal(a.faces, b.faces) and np.array_equal(a.vertices, b.vertices)
    part = mesh.parts[0]
    simple, _ = _simplify(part, 0.75)
    exact = surface_error(part, simple, np.random.default_rng(1))
    assert surface_error(part, simple, np.random.default_rng(1), bound=2 * exact) == exact
    assert exact / 2 < surface_error(part, simple, np.random.default_rng(1), bound=exact / 2) <= exact


def test_dae_and_glb_load_through_the_dispatcher(tmp_path):
    box = box_part((10, 20, 0), (30, 25, 12))
    for suffix in (".dae", ".glb"):
        verts = box.vertices
        if suffix == ".glb":   # glTF is y-up: store (x, z, -y), the reader turns it back to z-up
            verts = np.column_stack([verts[:, 0], verts[:, 2], -verts[:, 1]])
        tm = trimesh.Trimesh(verts, box.faces, vertex_colors=box.colors, process=False)
        path = tmp_path / f"box{suffix}"
        tm.export(path)
        mesh = load_district({"path": str(path), "offset": [1000.0, 2000.0, 5.0]}, "EPSG:25832")
        assert mesh.n_triangles == 12
        np.testing.assert_allclose(mesh.bounds(), [[1010, 2020, 5], [1030, 2025, 17]], atol=1e-4)


needs_data = pytest.mark.skipif(not DATA.exists(), reason="shared data absent")


@needs_data
def test_delft_obj_bounds_and_faces_match_source():
    mesh = load_district({"path": str(DATA / "delft/obj/testarea.obj"), "crs": "EPSG:28992"}, "EPSG:28992")
    assert mesh.n_triangles == 28619 - 2        # two of the source's triangles have zero area: dropped
    lo, hi = mesh.bounds()
    np.testing.assert_allclose([lo[0], hi[0], lo[1], hi[1]], [84616, 85141, 447423, 447751], atol=1.0)


@needs_data
def test_delft_lidar_mesh_bounds_and_triangles_match_source():
    mesh = load_district({"path": str(DATA / "delft/delft_dsm_mesh.ply")}, "EPSG:28992")
    assert mesh.n_triangles == 483648
    lo, hi = mesh.bounds()
    # Vertices sit at the 0.5 m cell centres; SOURCE.txt gives the cell edges: 0.25 m apart.
    np.testing.assert_allclose([lo[0], hi[0], lo[1], hi[1]], [84808, 85072.5, 447412, 447641.5], atol=0.26)
    np.testing.assert_allclose([lo[2], hi[2]], [-0.47, 26.33], atol=0.005)
    assert mesh.parts[0].colors is not None


@needs_data
@pytest.mark.parametrize("source", ["obj/testarea.obj", "delft_dsm_mesh.ply"])
def test_surface_distances_match_trimesh_closest_point_on_real_meshes(source):
    """Buildings with walls (OBJ) and a LiDAR surface, each simplified as a LOD level: the
    distance from original vertices (and from points off the surface) to it, point by point."""
    from pipeline25d.geometry.proximity import surface_distances
    from pipeline25d.stages.lod import simplify_part

    mesh = load_district({"path": str(DATA / "delft" / source), "crs": "EPSG:28992"}, "EPSG:28992")
    if len(mesh.parts) == 1:                                   # the LiDAR mesh: one 100 m chunk of it
        mesh = Mesh(split_into_chunks(mesh, 100.0)["c849_4475"])
    rng = np.random.default_rng(5)
    for part in mesh.parts:
        if part.n_triangles < 500:
            continue
        simple = simplify_part(part, 0.75)
        origin = part.vertices.mean(axis=0)
        pts = part.vertices[rng.choice(len(part.vertices), min(len(part.vertices), 2000), replace=False)]
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        pts = np.vstack([pts, rng.uniform(lo - 10, hi + 10, (100, 3))]) - origin
        _, expected, _ = trimesh.proximity.closest_point(
            trimesh.Trimesh(simple.vertices - origin, simple.faces, process=False), pts)
        np.testing.assert_allclose(surface_distances(pts, simple.vertices - origin, simple.faces), expected,
                                   rtol=0, atol=1e-9)
    assert np.isinf(surface_distances(pts, simple.vertices, np.zeros((0, 3), int))).all()


@needs_data
def test_dtm_samples_the_same_ground_from_another_crs():
    from pipeline25d.core.crs import transform_points
    from pipeline25d.core.raster import DTM

    rd = DTM(DATA / "delft/delft_dtm.tif", "EPSG:28992")
    utm = DTM(DATA / "delft/delft_dtm.tif", "EPSG:25831")
    pts = np.array([[84900.0, 447500.0, 0.0], [84950.0, 447450.0, 0.0], [85010.0, 447520.0, 0.0]])
    z_rd = rd.sample(pts[:, 0], pts[:, 1])
    p_utm = transform_points(pts, "EPSG:28992", "EPSG:25831")
    np.testing.assert_allclose(utm.sample(p_utm[:, 0], p_utm[:, 1]), z_rd, atol=1e-3)  # mm round trip
    assert np.isfinite(z_rd).all() and (z_rd > -3).all() and (z_rd < 5).all()


@needs_data
def test_dtm_read_through_a_window_samples_the_same_heights_with_a_fraction_of_the_cells(tmp_path):
    from pipeline25d.core.crs import horizontal_wkt, transform_points
    from pipeline25d.core.geotiff import write_float_geotiff
    from pipeline25d.core.grid import Grid
    from pipeline25d.core.raster import DTM

    # a hole-free DTM (as terrain: auto writes it): only the window's cells are read
    grid = Grid.north_up(84000.0, 448000.0, 0.5, 2000, 2000)
    cols, rows = np.meshgrid(np.arange(2000), np.arange(2000))
    write_float_geotiff(tmp_path / "dtm.tif", 0.01 * cols - 0.02 * rows + np.sin(cols / 9.0), grid,
                        horizontal_wkt("EPSG:28992"))
    rng = np.random.default_rng(1)
    xy = np.column_stack([rng.uniform(84300, 84360, 200), rng.uniform(447450, 447500, 200)])
    whole = DTM(tmp_path / "dtm.tif", "EPSG:28992", continuous=True)
    part = DTM(tmp_path / "dtm.tif", "EPSG:28992", continuous=True, window=(84300, 447450, 84360, 447500))
    np.testing.assert_array_equal(part.sample(xy[:, 0], xy[:, 1]), whole.sample(xy[:, 0], xy[:, 1]))
    assert part.values.size < 0.01 * whole.values.size
    # the window is given in the scene CRS, whatever the raster's
    utm = transform_points(np.column_stack([xy, np.zeros(len(xy))]), "EPSG:28992", "EPSG:25831")
    lo, hi = utm[:, :2].min(axis=0), utm[:, :2].max(axis=0)
    part_utm = DTM(tmp_path / "dtm.tif", "EPSG:25831", continuous=True, window=(*lo, *hi))
    assert part_utm.values.size < 0.01 * whole.values.size
    np.testing.assert_allclose(part_utm.sample(utm[:, 0], utm[:, 1]), whole.sample(xy[:, 0], xy[:, 1]), atol=1e-3)
    # a DTM with holes (Delft's): filled alike whatever the window, so tiles cannot disagree
    xy = np.column_stack([rng.uniform(84900, 84960, 200), rng.uniform(447450, 447500, 200)])
    whole = DTM(DATA / "delft/delft_dtm.tif", "EPSG:28992", continuous=True)
    part = DTM(DATA / "delft/delft_dtm.tif", "EPSG:28992", continuous=True, window=(84900, 447450, 84960, 447500))
    np.testing.assert_array_equal(part.sample(xy[:, 0], xy[:, 1]), whole.sample(xy[:, 0], xy[:, 1]))


def test_a_dtm_whose_nodata_is_nan_fills_its_holes_alike_through_any_window(tmp_path):
    """NaN nodata (GDAL's float rasters, write_float_geotiff): a hole is filled from the whole
    raster's nearest valid cell, not the window's, so two render blocks cannot disagree."""
    from pipeline25d.core.crs import horizontal_wkt
    from pipeline25d.core.geotiff import write_float_geotiff
    from pipeline25d.core.grid import Grid
    from pipeline25d.core.raster import DTM

    grid = Grid.north_up(0.0, 400.0, 1.0, 400, 400)
    cols, _ = np.meshgrid(np.arange(400), np.arange(400))
    values = 0.1 * cols
    values[100:300, 100:300] = np.nan                 # a hole 200 m across
    write_float_geotiff(tmp_path / "dtm.tif", values, grid, horizontal_wkt("EPSG:28992"))
    x, y = np.array([160.5]), np.array([199.5])       # 61 cells from the hole's west edge, 141 from its east
    whole = DTM(tmp_path / "dtm.tif", "EPSG:28992", continuous=True)
    part = DTM(tmp_path / "dtm.tif", "EPSG:28992", continuous=True, window=(150, 150, 305, 250))
    assert whole.sample(x, y)[0] == pytest.approx(9.9, abs=1e-5)      # col 99's height
    assert part.sample(x, y)[0] == whole.sample(x, y)[0]


@needs_data
def test_offset_on_a_self_georeferenced_format_is_an_error_not_ignored():
    from pipeline25d.core.errors import ConfigError

    spec = {"path": str(DATA / "tokyo-chiyoda-b3dm/cesium-rtc-extension.b3dm"), "offset": [10.0, 0.0, 0.0]}
    with pytest.raises(ConfigError, match="offset"):
        load_district(spec, "EPSG:6677")


def test_texture_drift_on_a_flat_textured_grid_is_the_analytic_shift():
    """A flat grid whose texture coordinates are a linear function of x, y: simplifying it costs
    no geometry, but a merged vertex shows the mean of its originals' coordinates at its new
    place. Where the original showed that coordinate is known in closed form, so the drift is too."""
    from pipeline25d.stages.lod import _simplify, texture_drift

    part = grid_part(bump=0.0)
    x0, y0, size = part.vertices[:, 0].min(), part.vertices[:, 1].min(), 80.0
    uv = np.column_stack([(part.vertices[:, 0] - x0) / size, (part.vertices[:, 1] - y0) / size])
    part = MeshPart(part.vertices, part.faces, uv=uv.astype(np.float32), texture=b"png")
    simple, mapping = _simplify(part, 0.75)
    shown_at = np.column_stack([x0 + simple.uv[:, 0].astype(np.float64) * size,
                                y0 + simple.uv[:, 1].astype(np.float64) * size, np.full(len(simple.uv), 10.0)])
    analytic = np.linalg.norm(simple.vertices - shown_at, axis=1)[np.unique(mapping)].max()
    drift = texture_drift(part, simple, mapping, np.random.default_rng(0))
    assert analytic > 0.01                                   # the collapses did move the texture
    assert drift == pytest.approx(analytic, rel=1e-4, abs=1e-5)
    untextured = build_levels(Mesh([grid_part(bump=0.0)]), max_error=0.01, max_levels=5)
    textured = build_levels(Mesh([part]), max_error=0.01, max_levels=5)
    assert len(untextured) >= 3 and len(textured) < len(untextured)   # the drift stops the pyramid
    assert all(e <= 0.01 for _, e in textured)


_DSM_TWO_WAYS = """
import sys, numpy as np
sys.path.insert(0, sys.argv[1])
from pathlib import Path
from test_ingest_lod import grid_part
from pipeline25d.core.cores import fork_pool
from pipeline25d.core.grid import Grid
from pipeline25d.core.mesh import Mesh
from pipeline25d.stages.ingest import write_chunks
from pipeline25d.stages.lod import build_lod, chunk_loaders, lod_chunks
from pipeline25d.stages.terrain.dsm import height_map_tiles
out = Path(sys.argv[2])
write_chunks(Mesh([grid_part(bump=2.0)]), "a", 25.0, out / "chunks", out / "chunks" / "index.json")
build_lod(out / "chunks" / "index.json", out / "lod" / "index.json", 0.5, 4)
loaders = chunk_loaders(lod_chunks([str(out / "lod" / "index.json")]), 0.1)
grid = Grid.covering((499990.0, 5799990.0, 500090.0, 5800090.0), 0.5)
with fork_pool(2) as pool:        # forked before this process makes a GL context, as the terrain job does
    there = list(height_map_tiles(loaders, grid, tile_px=64, pool=pool, ahead=2))
here = list(height_map_tiles(loaders, grid, tile_px=64))
np.save(out / "there.npy", np.concatenate([np.nan_to_num(h, nan=-1).ravel() for *_, h in there]))
np.save(out / "here.npy", np.concatenate([np.nan_to_num(h, nan=-1).ravel() for *_, h in here]))
print(len(here), [(r, c) for r, c, _ in here] == [(r, c) for r, c, _ in there])
"""


def test_the_dsm_rendered_by_forked_workers_equals_the_one_rendered_here(tmp_path):
    """The terrain job's DSM tiles on two forked workers (each its own GL context) and here on one:
    the same heights, tile for tile, in the same order (a fresh process: no GL context before the fork)."""
    import subprocess
    import sys
    from pathlib import Path

    run = subprocess.run([sys.executable, "-c", _DSM_TWO_WAYS, str(Path(__file__).parent), str(tmp_path)],
                         check=True, capture_output=True, text=True, timeout=300)
    assert run.stdout.split() == ["16", "True"], run.stdout + run.stderr      # 200 x 200 cells in 64-cell tiles
    here, there = np.load(tmp_path / "here.npy"), np.load(tmp_path / "there.npy")
    assert np.array_equal(here, there)
    drawn = here[here != -1]
    assert drawn.size > 0.5 * 78 ** 2 * 4 and 7.9 < drawn.min() and drawn.max() < 12.1    # the 78 m mesh, z 10 ± 2
