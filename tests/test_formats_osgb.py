"""OSGB (ContextCapture PagedLOD) reader on the generated sample dataset (pipeline25d_lab.scenes.osgb_sample).

Expected values come from the generator's own definition of the surface (height, colour,
grid per level, texel size per level), never from the reader.
"""

from __future__ import annotations

import functools
import io
import json
import logging
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import REPO
from osgeo import gdal
from PIL import Image
from pyproj import Transformer

from pipeline25d.core.errors import InputFileError
from pipeline25d.formats import detect_format, load_district
from pipeline25d.formats.osgb import osgconv, read_tiles
from pipeline25d_lab.scenes import osgb_sample as S

pytestmark = pytest.mark.skipif(shutil.which("osgconv") is None,
                                reason="OpenSceneGraph's osgconv is not installed (Debian: openscenegraph)")
ORIGIN = np.array(S.ORIGIN)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    return S.generate_osgb_sample(tmp_path_factory.mktemp("osgb") / "sample")


@pytest.fixture(scope="module")
def tiles_at(dataset):
    """read_tiles of the sample at a gsd, each gsd read once per module."""
    return functools.cache(lambda gsd: read_tiles(dataset, gsd))


@pytest.fixture()
def copy(dataset, tmp_path) -> Path:
    """A copy of the dataset a test may break."""
    return Path(shutil.copytree(dataset, tmp_path / "sample"))


def grid_vertices(level: int) -> np.ndarray:
    """Every vertex of ``level`` over both tiles, local coordinates, from the generator's definition."""
    step = S.NODE[level] / S.CELLS[level]
    xs = np.arange(0.0, len(S.TILES) * S.TILE + step / 2, step)
    ys = np.arange(0.0, S.TILE + step / 2, step)
    x, y = np.meshgrid(xs, ys)
    z = S.height(x, y).astype(np.float32).astype(np.float64)   # OSG stores float32
    return np.column_stack([x.ravel(), y.ravel(), z.ravel()])


@pytest.mark.parametrize("gsd", [4.0, 2.0, 0.5])
def test_bounds_are_exact_after_srs_origin(dataset, gsd):
    level = S.level_for_gsd(gsd)
    mesh = load_district({"path": str(dataset)}, S.SRS, gsd=gsd)
    v = grid_vertices(level) + ORIGIN
    np.testing.assert_array_equal(mesh.bounds(), [v.min(axis=0), v.max(axis=0)])
    assert mesh.n_triangles == len(S.TILES) * S.triangles(level)


def test_bounds_in_another_crs(dataset):
    """CGCS2000 / 3-degree Gauss-Kruger CM 114E: every vertex moved by pyproj on its own."""
    mesh = load_district({"path": str(dataset)}, "EPSG:4547", gsd=2.0)
    v = grid_vertices(S.level_for_gsd(2.0)) + ORIGIN
    x, y, z = Transformer.from_crs(S.SRS, "EPSG:4547", always_xy=True).transform(v[:, 0], v[:, 1], v[:, 2])
    moved = np.column_stack([x, y, z])
    np.testing.assert_allclose(mesh.bounds(), [moved.min(axis=0), moved.max(axis=0)], rtol=0, atol=1e-6)
    assert abs(mesh.bounds()[0, 0] - v[:, 0].min()) > 1000      # really another grid


def test_triangles_per_level(tiles_at):
    for gsd in (4.0, 2.0, 0.5):
        level = S.level_for_gsd(gsd)
        tiles = tiles_at(gsd)
        assert [t.name for t in tiles] == [S.tile_name(*t) for t in S.TILES]
        assert [dict(t.levels) for t in tiles] == [{level: S.triangles(level)}] * len(S.TILES)
    assert S.triangles(0) < S.triangles(1) < S.triangles(2)


@pytest.mark.parametrize("boundary", [0, 1])
def test_level_chosen_across_each_range_boundary(tiles_at, boundary):
    """Just coarser than a level's texel: that level; just finer: the next."""
    texel = S.TEXEL[boundary]
    for gsd, level in ((texel * 1.002, boundary), (texel * 0.998, boundary + 1)):
        tiles = tiles_at(gsd)
        assert all(set(t.levels) == {level} for t in tiles), (gsd, [dict(t.levels) for t in tiles])


def test_levels_past_the_ranges_and_full_detail(tiles_at):
    assert all(set(t.levels) == {0} for t in tiles_at(1000.0))    # below every range: coarsest
    assert all(set(t.levels) == {2} for t in tiles_at(0.01))      # finer than any level
    assert all(set(t.levels) == {2} for t in tiles_at(None))      # full detail


@pytest.mark.parametrize("gsd", [4.0, 2.0, 0.5])
def test_textures_come_through_with_their_colours(tiles_at, gsd):
    """Each part's texture sampled at points of its faces is the generator's colour of that level there."""
    level = S.level_for_gsd(gsd)
    tiles = tiles_at(gsd)
    parts = [p for t in tiles for p in t.parts]
    assert len(parts) == len(S.TILES) * round(S.TILE / S.NODE[level]) ** 2
    checked = 0
    for part in parts:
        assert part.texture is not None and part.uv is not None
        img = np.asarray(Image.open(io.BytesIO(part.texture)).convert("RGB"))
        assert img.shape[:2] == (S.TEXTURE_PX[level],) * 2
        # 64 points inside every face (fixed barycentric weights): position and texture coordinate
        weights = np.random.default_rng(0).dirichlet(np.ones(3), size=64)
        centroid = np.einsum("sk,fkd->fsd", weights, part.vertices[part.faces]).reshape(-1, 3)
        uv = np.einsum("sk,fkd->fsd", weights, part.uv[part.faces].astype(np.float64)).reshape(-1, 2)
        # the texel holding a point has its centre (where the generator took the colour) within
        # half a texel per axis: keep points further than that from checker lines and roof edges
        margin = 0.6 * S.TEXEL[level]
        edges_x = [np.abs(centroid[:, 0] - np.round(centroid[:, 0] / S.CHECKER) * S.CHECKER)]
        edges_y = [np.abs(centroid[:, 1] - np.round(centroid[:, 1] / S.CHECKER) * S.CHECKER)]
        for x0, y0, x1, y1, _ in S.BUILDINGS:
            edges_x += [np.abs(centroid[:, 0] - x0), np.abs(centroid[:, 0] - x1)]
            edges_y += [np.abs(centroid[:, 1] - y0), np.abs(centroid[:, 1] - y1)]
        clear = (np.min(edges_x, axis=0) > margin) & (np.min(edges_y, axis=0) > margin)
        col = np.clip((uv[:, 0] * img.shape[1]).astype(int), 0, img.shape[1] - 1)
        row = np.clip(((1.0 - uv[:, 1]) * img.shape[0]).astype(int), 0, img.shape[0] - 1)
        got = img[row[clear], col[clear]]
        want = S.colour(level, centroid[clear, 0], centroid[clear, 1])
        np.testing.assert_array_equal(got, want)
        checked += int(clear.sum())
    assert checked >= 10 * len(parts)


def test_textures_are_the_uncompressed_tgas_osgconv_wrote(tiles_at):
    """The chunks keep osgconv's textures as it wrote them: uncompressed true-colour TGA (image type 2,
    no colour map), 18 header bytes and then every texel, which the render job reads without
    decoding. Their pixels: the test above."""
    parts = [p for t in tiles_at(1.0) for p in t.parts if p.texture is not None]
    assert parts
    for part in parts:
        data = part.texture
        assert data[1] == 0 and data[2] == 2 and data[16] in (24, 32)
        width, height = int.from_bytes(data[12:14], "little"), int.from_bytes(data[14:16], "little")
        with Image.open(io.BytesIO(data)) as img:
            assert img.format == "TGA" and img.size == (width, height)
        texels = width * height * data[16] // 8
        assert len(data) in (18 + data[0] + texels, 18 + data[0] + texels + 26)     # with its footer or not


def test_detect_format_and_single_file_with_metadata(dataset):
    root = dataset / "Data" / "Tile_+001_+000" / "Tile_+001_+000.osgb"
    assert detect_format(dataset) == "osgb" and detect_format(root) == "osgb"
    spec = {"path": str(root), "metadata": str(dataset / "metadata.xml"), "offset": [1.0, 2.0, 3.0]}
    mesh = load_district(spec, S.SRS, gsd=2.0)
    v = grid_vertices(1)
    v = v[v[:, 0] >= S.TILE]                                   # tile +001 alone
    want = v + ORIGIN + [1.0, 2.0, 3.0]
    np.testing.assert_array_equal(mesh.bounds(), [want.min(axis=0), want.max(axis=0)])
    assert mesh.n_triangles == S.triangles(1)


def _wrap_first_tile(copy: Path, tmp_path: Path, rows: str, shift: tuple[float, float, float]) -> None:
    """The first tile's root PagedLOD wrapped in a MatrixTransform of 3 x 3 ``rows`` (OSG's row
    vectors) and ``shift``; the second tile removed."""
    tile = copy / "Data" / "Tile_+000_+000"
    shutil.rmtree(copy / "Data" / "Tile_+001_+000")
    root = tile / "Tile_+000_+000.osgb"
    osgconv(root.resolve(), Path("root.osgt"), ["WriteImageHint=IncludeData", "precision=17"], tmp_path, root)
    text = (tmp_path / "root.osgt").read_text()
    header, body = text.split("\n\n", 1)
    wrapped = (f"{header}\n\nosg::MatrixTransform {{\n UniqueID 900000\n Children 1 {{\n{body}\n }}\n"
               f" Matrix {{\n{rows}\n {shift[0]} {shift[1]} {shift[2]} 1\n }}\n}}\n")
    (tmp_path / "wrapped.osgt").write_text(wrapped)
    osgconv(Path("wrapped.osgt"), root.resolve(), [], tmp_path, root)


def test_matrix_transform_places_and_scales_child_files(copy, tmp_path):
    """A root PagedLOD wrapped in a MatrixTransform (scale 2, shift): its child files are placed
    the same, and the doubled radius moves the switch to twice the texel size."""
    shift = (1000.0, -500.0, 7.0)
    _wrap_first_tile(copy, tmp_path, " 2 0 0 0\n 0 2 0 0\n 0 0 2 0", shift)
    gsd = S.TEXEL[1] * 1.5                       # level 1 unscaled; with radius x2 the pixel size says level 2
    tiles = read_tiles(copy, gsd)
    assert dict(tiles[0].levels) == {2: S.triangles(2)}
    v = grid_vertices(2)
    v = v[v[:, 0] <= S.TILE] * 2.0 + shift
    got = np.concatenate([p.vertices for p in tiles[0].parts])
    np.testing.assert_allclose([got.min(axis=0), got.max(axis=0)], [v.min(axis=0), v.max(axis=0)], atol=1e-4)


def test_a_mirroring_matrix_transform_keeps_the_surface_facing_up(copy, tmp_path):
    """x mirrored (det < 0): the vertices are mirrored and the faces wound back, so the height
    field's faces still face up (+z), as those of the tile read unwrapped do."""
    def up_share(parts) -> float:
        edges = [(p.vertices[p.faces[:, 1:]] - p.vertices[p.faces[:, :1]]).transpose(1, 0, 2) for p in parts]
        normals = np.concatenate([np.cross(a, b) for a, b in edges])
        return float((normals[:, 2] > 0).mean())

    plain = read_tiles(copy, S.TEXEL[1] * 1.5)[0]
    _wrap_first_tile(copy, tmp_path, " -1 0 0 0\n 0 1 0 0\n 0 0 1 0", (0.0, 0.0, 0.0))
    mirrored = read_tiles(copy, S.TEXEL[1] * 1.5)[0]
    assert up_share(plain.parts) == 1.0
    assert up_share(mirrored.parts) == 1.0
    got = np.concatenate([p.vertices for p in mirrored.parts])
    own = np.concatenate([p.vertices for p in plain.parts])
    np.testing.assert_allclose(got[:, 0].max(), -own[:, 0].min(), atol=1e-6)


def test_a_missing_child_file_draws_its_parents_level_there_with_a_warning(copy, tiles_at):
    """As OpenSceneGraph keeps drawing a PagedLOD's own level while a child is not there: the
    quadrant whose level-2 file is gone is drawn at level 1, the rest of the tile at level 2."""
    tile = copy / "Data" / "Tile_+001_+000"
    (tile / "Tile_+001_+000_L2_3.osgb").unlink()
    assert dict(read_tiles(copy, 2.0)[1].levels) == {1: S.triangles(1)}     # not needed at level 1: no word
    with pytest.warns(UserWarning, match=r"Tile_\+001_\+000\.osgb: 1 PagedLOD child file\(s\) missing, drawn "
                                         r"coarser than gsd 0\.5.*Tile_\+001_\+000_L2_3\.osgb \(level 1 drawn\)"):
        tiles = read_tiles(copy, 0.5)
    assert [(Path(c.tile).name, c.level, c.missing) for c in tiles[1].coarser] == [
        ("Tile_+001_+000_L1.osgb", 1, ("Tile_+001_+000_L2_3.osgb",))] and tiles[0].coarser == []
    with pytest.raises(InputFileError, match=r"Tile_\+001_\+000_L2_3\.osgb: OSGB file is missing \(named by "
                                             r".*Tile_\+001_\+000_L1\.osgb\); the input's missing_children"):
        read_tiles(copy, 0.5, missing_children="error")
    assert dict(tiles[1].levels) == {1: S.triangles(1) // 4, 2: S.triangles(2) // 4 * 3}
    assert dict(tiles[0].levels) == {2: S.triangles(2)}
    # the quadrant is there whole: the tile's vertices are the other quadrants' level-2 grid and its level-1 grid
    full = np.concatenate([p.vertices for p in tiles_at(0.5)[1].parts])
    got = np.concatenate([p.vertices for p in tiles[1].parts])
    np.testing.assert_array_equal([got.min(axis=0)[:2], got.max(axis=0)[:2]],
                                  [full.min(axis=0)[:2], full.max(axis=0)[:2]])
    # the whole level 1 gone: level 0 everywhere in that tile
    (tile / "Tile_+001_+000_L1.osgb").unlink()
    with pytest.warns(UserWarning, match=r"Tile_\+001_\+000_L1\.osgb \(level 0 drawn\)"):
        tiles = read_tiles(copy, 0.5)
    assert dict(tiles[1].levels) == {0: S.triangles(0)}


def test_tiles_drawn_coarser_reach_the_chunk_index_and_the_report(copy, tmp_path):
    """ingest writes the tiles drawn coarser into the district's index (only then), and the
    report lists them with the file and the level drawn."""
    from pipeline25d.publish.report import coarser_inputs, coarser_section
    from pipeline25d.stages.ingest import ingest

    whole = ingest({"path": str(copy)}, "d", S.SRS, 100.0, 0.25, tmp_path / "whole" / "index.json", gsd=0.5)
    assert "coarser" not in whole and "coarser" not in json.loads((tmp_path / "whole" / "index.json").read_text())
    (copy / "Data" / "Tile_+001_+000" / "Tile_+001_+000_L2_3.osgb").unlink()
    with pytest.warns(UserWarning, match="1 PagedLOD child file"):
        index = ingest({"path": str(copy)}, "d", S.SRS, 100.0, 0.25, tmp_path / "chunks" / "d" / "index.json",
                       gsd=0.5)
    assert list(index)[:6] == ["district", "source", "chunk_size", "n_triangles", "coarser", "chunks"]
    assert index["n_triangles"] == whole["n_triangles"] - S.triangles(2) // 4 + S.triangles(1) // 4
    listed = coarser_inputs(tmp_path, ["d", "absent"])
    tile = str(copy / "Data" / "Tile_+001_+000" / "Tile_+001_+000_L1.osgb")
    assert [(c["district"], c["tile"], c["level"], c["missing"]) for c in listed] == [
        ("d", tile, 1, ["Tile_+001_+000_L2_3.osgb"])]
    assert f"| d | {tile} | 1 | Tile_+001_+000_L2_3.osgb |" in "\n".join(coarser_section(listed))
    with pytest.raises(InputFileError, match="missing_children: coarser"):
        load_district({"path": str(copy), "missing_children": "error"}, S.SRS, gsd=0.5)


def test_a_missing_root_file_is_still_an_error(copy):
    (copy / "Data" / "Tile_+001_+000" / "Tile_+001_+000.osgb").unlink()
    with pytest.raises(InputFileError, match=r"Tile_\+001_\+000\.osgb: tile root file is missing"):
        read_tiles(copy, 0.5)
    with pytest.raises(InputFileError, match=r"none\.osgb: OSGB file is missing"):
        read_tiles(copy / "none.osgb", 0.5)


def test_corrupt_file_is_named(copy):
    bad = copy / "Data" / "Tile_+000_+000" / "Tile_+000_+000_L1.osgb"
    bad.write_bytes(bad.read_bytes()[:300])
    with pytest.raises(InputFileError, match=r"Tile_\+000_\+000_L1\.osgb: osgconv cannot read it"):
        read_tiles(copy, 2.0)
    with pytest.raises(InputFileError, match=r"Tile_\+000_\+000_L1\.osgb: osgconv cannot read it"):
        load_district({"path": str(copy)}, S.SRS, gsd=2.0)


def test_empty_trees_and_folders_are_errors(tmp_path):
    (tmp_path / "empty.osgt").write_text("#Ascii Scene\n#Version 161\n#Generator OpenSceneGraph 3.6.5\n\n"
                                         "osg::Group {\n UniqueID 1\n}\n")
    target = tmp_path / "Data" / "Tile_+000_+000" / "Tile_+000_+000.osgb"
    target.parent.mkdir(parents=True)
    osgconv(Path("empty.osgt"), target, [], tmp_path, target)
    with pytest.raises(InputFileError, match=r"Tile_\+000_\+000\.osgb: holds no triangles"):
        read_tiles(target, 1.0)
    with pytest.raises(InputFileError, match="holds no triangles"):
        read_tiles(tmp_path, 1.0)
    target.unlink()
    with pytest.raises(InputFileError, match=r"Tile_\+000_\+000\.osgb: tile root file is missing"):
        read_tiles(tmp_path, 1.0)
    shutil.rmtree(tmp_path / "Data")
    with pytest.raises(InputFileError, match="not an OSGB dataset"):
        detect_format(tmp_path)


def test_ingest_at_two_gsds_draws_the_level_of_each(dataset, tmp_path, caplog):
    from pipeline25d.stages.ingest import ingest

    for gsd in (2.0, 0.5):
        level = S.level_for_gsd(gsd)
        caplog.clear()
        with caplog.at_level(logging.INFO, logger="pipeline25d.formats.osgb"):
            index = ingest({"path": str(dataset)}, "d", S.SRS, 100.0, gsd * 0.5, tmp_path / f"{gsd}" / "index.json",
                           gsd=gsd)
        assert index["n_triangles"] == len(S.TILES) * S.triangles(level)
        assert sum(c["n_triangles"] for c in index["chunks"].values()) >= index["n_triangles"]
        lines = [r.getMessage() for r in caplog.records]
        for tx, ty in S.TILES:
            assert f"{S.tile_name(tx, ty)} at gsd {gsd}: level {level} ({S.triangles(level)} triangles)" in lines
        saved = json.loads((tmp_path / f"{gsd}" / "index.json").read_text())
        assert saved["n_triangles"] == index["n_triangles"]


def _run_workflow(dataset: Path, workdir: Path, gsd: float, target: str) -> None:
    """The workflow on the dataset at ``gsd``, nadir, up to ``target`` (under results/osgb/)."""
    config = {"scene": "osgb", "crs": S.SRS, "inputs": {"sample": {"path": str(dataset)}}, "terrain": "flat",
              "gsd": gsd, "tile_size": 256, "perspectives": "nadir", "lod": {"max_error_px": 0.001},
              "gcp": {"spacing": 30}, "tms": {"zoom": "16-17"}}
    (workdir / "config.yaml").write_text(yaml.safe_dump(config))
    cmd = [sys.executable, "-m", "snakemake", "--snakefile", str(REPO / "Snakefile"), "--directory", str(workdir),
           "--configfile", str(workdir / "config.yaml"), "-j2", f"results/osgb/{target}"]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-3000:]


def _map_samples(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(rgba, local x, local y, inside, sample) of a nadir map: ``sample`` = pixel centres inside
    the dataset, over 1.5 m off checker lines and roof edges (where a texel's colour is its own)."""
    ds = gdal.Open(str(path))
    x0, dx, _, y0, _, dy = ds.GetGeoTransform()
    rgba = np.stack([ds.GetRasterBand(b + 1).ReadAsArray() for b in range(4)], axis=-1)
    rows, cols = np.indices(rgba.shape[:2])
    x = x0 + (cols + 0.5) * dx - S.ORIGIN[0]
    y = y0 + (rows + 0.5) * dy - S.ORIGIN[1]
    inside = (x > 1) & (x < len(S.TILES) * S.TILE - 1) & (y > 1) & (y < S.TILE - 1)
    far = np.minimum(np.abs(x - np.round(x / S.CHECKER) * S.CHECKER), np.abs(y - np.round(y / S.CHECKER) * S.CHECKER))
    for x0b, y0b, x1b, y1b, _ in S.BUILDINGS:
        for edge_x in (x0b, x1b):
            far = np.minimum(far, np.where((y > y0b - 2) & (y < y1b + 2), np.abs(x - edge_x), np.inf))
        for edge_y in (y0b, y1b):
            far = np.minimum(far, np.where((x > x0b - 2) & (x < x1b + 2), np.abs(y - edge_y), np.inf))
    return rgba, x, y, inside, inside & (far > 1.5)


def test_workflow_maps_the_level_of_its_gsd(dataset, tmp_path):
    """The whole workflow on the sample at gsd 1 m, nadir: the map shows level 1's texture (green
    checker) where the generator put it (pixel centres off checker lines and roof edges)."""
    _run_workflow(dataset, tmp_path, 1.0, "maps/az000_el90.tif")
    rgba, x, y, inside, sample = _map_samples(tmp_path / "results/osgb/maps/az000_el90.tif")
    assert sample.sum() > 0.3 * inside.sum()
    assert (rgba[sample][:, 3] == 255).all()
    # textured surfaces are drawn unlit (photogrammetry textures carry their own light)
    np.testing.assert_allclose(rgba[sample][:, :3], S.colour(1, x[sample], y[sample]), atol=3)


def test_a_dataset_with_a_missing_child_file_runs_to_maps_drawn_at_the_finest_level_present(copy, tmp_path):
    """Issue 27: one level-2 child file gone, the whole workflow at gsd 0.5 m (level 2) still runs
    to the map and the report; the map shows level 2 (blue) everywhere but in that quadrant, which
    shows level 1 (green), its parent's own level; the ingest log warns, and report.json and
    report.md list the tile file drawn, its level and the missing file."""
    gone = copy / "Data" / "Tile_+001_+000" / "Tile_+001_+000_L2_3.osgb"
    gone.unlink()
    work = tmp_path / "work"
    work.mkdir()
    _run_workflow(copy, work, 0.5, "report/report.json")
    results = work / "results" / "osgb"
    rgba, x, y, inside, sample = _map_samples(results / "maps" / "az000_el90.tif")
    assert sample.sum() > 0.3 * inside.sum() and (rgba[sample][:, 3] == 255).all()
    quadrant = (x >= 150) & (y >= 50)                      # tile (1, 0), quadrant 3: x 150-200, y 50-100
    for level, where in ((1, sample & quadrant), (2, sample & ~quadrant)):
        assert where.sum() > 1000
        np.testing.assert_allclose(rgba[where][:, :3], S.colour(level, x[where], y[where]), atol=3)
    tile = str(copy / "Data" / "Tile_+001_+000" / "Tile_+001_+000_L1.osgb")
    report = json.loads((results / "report" / "report.json").read_text())
    assert report["coarser"] == [{"district": "sample", "tile": tile, "level": 1, "missing": [gone.name],
                                  "drawn": "the finest level of the file that names them"}]
    assert f"| sample | {tile} | 1 | {gone.name} |" in (results / "report" / "report.md").read_text()
    log = (results / "logs" / "ingest" / "sample.log").read_text()
    assert f"WARNING pipeline25d.warnings: UserWarning: {copy / 'Data' / 'Tile_+001_+000' / 'Tile_+001_+000.osgb'}: " \
           f"1 PagedLOD child file(s) missing" in log and f"{gone.name} (level 1 drawn)" in log


def test_a_dataset_is_ingested_tile_by_tile_into_the_chunks_of_a_whole_read(dataset, tmp_path, monkeypatch):
    """Pieces (one tile at a time) and a spool that holds nothing in memory give the chunk files and
    index that writing the dataset read whole gives, byte for byte."""
    from pipeline25d.formats import load_district
    from pipeline25d.stages import ingest

    spec = {"path": str(dataset)}
    whole = tmp_path / "whole" / "index.json"
    ingest.write_chunks(load_district(spec, "EPSG:32650", gsd=0.5), "d", 40.0, whole.parent, whole)
    monkeypatch.setattr(ingest, "SPOOL_BYTES", 0)           # every piece's share goes to the spool
    pieces = tmp_path / "pieces" / "index.json"
    index = ingest.ingest(spec, "d", "EPSG:32650", 40.0, 0.0, pieces, gsd=0.5)
    assert index == json.loads(whole.read_text()) and len(index["chunks"]) > 4
    for name in index["chunks"]:
        assert (pieces.parent / f"{name}.npz").read_bytes() == (whole.parent / f"{name}.npz").read_bytes()
    assert not list(pieces.parent.glob(".spool-*"))          # the spool is gone


def test_tiles_are_read_as_they_are_taken(copy, monkeypatch):
    """With one worker, taking the first of four tiles has read two (the next one is under way):
    memory follows the tiles in flight, not the dataset."""
    from pipeline25d.formats import osgb

    for k in (2, 3):                                    # two more tiles, copies of the second
        tile = copy / "Data" / f"Tile_+00{k}_+000"
        shutil.copytree(copy / "Data" / "Tile_+001_+000", tile)
        (tile / "Tile_+001_+000.osgb").rename(tile / f"Tile_+00{k}_+000.osgb")
    calls = []
    real = osgb.read_tile
    monkeypatch.setattr(osgb, "WORKERS", 1)
    monkeypatch.setattr(osgb, "read_tile", lambda *a, **k: calls.append(a[0].stem) or real(*a, **k))
    tiles = osgb.iter_tiles(copy, 0.5)
    assert next(tiles).name == "Tile_+000_+000"
    deadline = time.monotonic() + 30              # the next read is submitted; its thread may not have begun
    while len(calls) < 2 and time.monotonic() < deadline:
        time.sleep(0.01)
    time.sleep(0.2)                               # (and no third read follows it)
    assert calls == ["Tile_+000_+000", "Tile_+001_+000"]
    assert [t.name for t in tiles] == [f"Tile_+00{k}_+000" for k in (1, 2, 3)] and len(calls) == 4
