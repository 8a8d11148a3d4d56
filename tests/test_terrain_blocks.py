"""Blockwise terrain (ground filter, DTM fill, GCP sites, GeoTIFF writes) against the whole grid."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline25d.core.geotiff import FloatRaster, float_geotiff_writer
from pipeline25d.core.grid import Grid, cell_blocks
from pipeline25d.geometry.perspectives import Perspective
from pipeline25d.stages.gcp_sites import SiteRules, select_sites
from pipeline25d.stages.terrain.dtm import dtm_blocks, interpolate_dtm
from pipeline25d.stages.terrain.ground import csf_ground, ground_blocks, trim_object_edges

E0, N0 = 600000.0, 5250000.0
MAX_OBJECT_M = 40.0
SMALL_BLOCKS = 300 * 300      # a 640 x 768 grid in 3 x 3 blocks


def boxes_on_a_slope(height: int = 640, width: int = 768, seed: int = 1):
    """A 1 m DSM: a 10 % slope with a gentle swell, 150 flat-roofed boxes up to 30 m wide and
    blocks of the largest object size across the cuts between SMALL_BLOCKS' cores (rows and
    columns 256 and 512)."""
    grid = Grid.north_up(E0, N0 + height, 1.0, width, height)
    xs, ys = grid.cell_centres()
    terrain = 0.1 * (xs - E0) + 4 * np.sin((ys - N0) / 70) * np.cos((xs - E0) / 90)
    dsm = terrain.copy()
    objects = np.zeros(dsm.shape, bool)
    rng = np.random.default_rng(seed)
    for _ in range(150):
        r, c = rng.integers(0, height - 8), rng.integers(0, width - 8)
        h, w = rng.integers(8, 31, 2)
        dsm[r:r + h, c:c + w] = terrain[r:r + h, c:c + w].max() + rng.uniform(4, 25)
        objects[r:r + h, c:c + w] = True
    for r, c in [(256, 100), (512, 300), (400, 256), (150, 512), (490, 490)]:
        box = (slice(r - 18, r + 18), slice(c - 18, c + 18))
        dsm[box] = terrain[box].max() + 15.0
        objects[box] = True
    return grid, dsm, objects


@pytest.fixture(scope="module")
def scene():
    grid, dsm, objects = boxes_on_a_slope()
    whole = trim_object_edges(csf_ground(dsm, grid, MAX_OBJECT_M, 2.0, 2, 0.5), dsm)
    return grid, dsm, objects, whole


def _read(values):
    return lambda rows, cols: values[rows, cols].astype(np.float64)


def test_blocks_tile_the_grid_with_their_margins():
    blocks = cell_blocks(1000, 1300, 50, 400 * 400, align=2)
    count = np.zeros((1000, 1300), int)
    for b in blocks:
        count[b.core] += 1
        (r, c), (wr, wc) = b.core, b.window
        assert wr.start == max(r.start - 50, 0) and wc.start <= max(c.start - 50, 0) and wc.start % 2 == 0
        assert wr.stop >= min(r.stop + 50, 1000) and (1000 - wr.stop) % 2 == 0 and wc.stop == min(c.stop + 50, 1300)
        assert all(s.start % 256 == 0 for s in b.core)                  # whole GeoTIFF tiles
    assert len(blocks) == 4 * 5 and (count == 1).all()
    assert cell_blocks(100, 120, 50) == cell_blocks(100, 120, 0)         # a small grid is one block


def test_a_one_block_grid_is_halved_across_its_longer_side():
    """halve: the 3 x 3 bench's DSM (1585 x 1375 cells, margin 200) in two, cut at the multiple of
    256 nearest the middle of its longer side; each half's window reaches the margin across the
    cut and no farther; a grid shorter than 4 margins, or one already in blocks, is left as it is."""
    for height, width in [(1375, 1585), (1585, 1375)]:
        blocks = cell_blocks(height, width, 200, align=2, halve=True)
        along = 1 if width > height else 0
        count = np.zeros((height, width), int)
        for b in blocks:
            count[b.core] += 1
            assert b.core[1 - along] == b.window[1 - along] == slice(0, (height, width)[1 - along])
        assert len(blocks) == 2 and (count == 1).all()
        first, second = blocks
        assert first.core[along].stop == second.core[along].start == 768
        assert first.window[along].stop in (968, 969) and second.window[along].start == 568
        if along:
            assert first.window[1].start % 2 == 0 == second.window[1].start % 2      # aligned columns
    assert len(cell_blocks(700, 799, 200, halve=True)) == 1
    assert len(cell_blocks(1375, 1585, 200)) == 1
    assert cell_blocks(4000, 4000, 200, halve=True) == cell_blocks(4000, 4000, 200)


def test_halved_ground_matches_the_whole_grid(scene):
    """The fixture's 640 x 768 grid (margin 40) is one block of the default size, filtered in two
    halves: the cells agree with the whole grid's cloth as blocks do (at least 99.5 %, at most
    0.01 % differ), and two processes give each half exactly as one does."""
    grid, dsm, objects, whole = scene
    one = list(ground_blocks(_read(dsm), grid, MAX_OBJECT_M, 2.0, 2, 0.5))
    two = list(ground_blocks(_read(dsm), grid, MAX_OBJECT_M, 2.0, 2, 0.5, processes=2))
    assert len(one) == len(two) == 2
    ground = np.zeros(dsm.shape, bool)
    for (b1, d1, g1), (b2, d2, g2) in zip(one, two):
        assert b1 == b2
        np.testing.assert_array_equal(g1, g2)
        ground[b1.core] = g1
    assert [b.core[1] for b, _, _ in one] == [slice(0, 256), slice(256, 768)]    # cut at a GeoTIFF tile
    assert (ground == whole).mean() >= 0.995 and (ground != whole).mean() <= 1e-4
    assert not (ground & objects).any() and ground[~objects].mean() > 0.9


def test_blockwise_ground_matches_the_whole_grid(scene):
    """Each block's window reaches the largest object beyond its core, and its envelope equals
    the whole grid's; the cloth itself may still differ (it starts from the block's highest
    point and stops when the block's largest move is small), so cells near the classification
    threshold may flip: at least 99.5 % of the cells must agree (on 30 Delft districts 99.98 %
    do; here all but at most 0.01 %: without margins 0.03 % differ). A flipped cell lies within
    ~class_threshold of the cloth, so the DTM moves by about that much near it at most: < 0.5 m
    at the 99.9th percentile, < 1 cm in the mean."""
    grid, dsm, objects, whole = scene
    ground = np.zeros(dsm.shape, bool)
    n = 0
    for block, core_dsm, core_ground in ground_blocks(_read(dsm), grid, MAX_OBJECT_M, 2.0, 2, 0.5, SMALL_BLOCKS):
        np.testing.assert_array_equal(core_dsm, dsm[block.core])
        ground[block.core] = core_ground
        n += 1
    assert n == 9
    assert (ground == whole).mean() >= 0.995 and (ground != whole).mean() <= 1e-4
    assert not (ground & objects).any() and ground[~objects].mean() > 0.9
    a = interpolate_dtm(np.where(whole, dsm, np.nan), 20)
    b = interpolate_dtm(np.where(ground, dsm, np.nan), 20)
    diff = np.abs(a - b)
    assert np.percentile(diff, 99.9) < 0.5 and diff.mean() < 0.01, (diff.max(), np.percentile(diff, 99.9))


def test_ground_blocks_in_processes_equal_one_process(scene):
    """The blocks filtered two at a time in forked processes give every block's DSM and ground
    exactly as one process does, in the same order."""
    grid, dsm, _, _ = scene
    one = list(ground_blocks(_read(dsm), grid, MAX_OBJECT_M, 2.0, 2, 0.5, SMALL_BLOCKS))
    two = list(ground_blocks(_read(dsm), grid, MAX_OBJECT_M, 2.0, 2, 0.5, SMALL_BLOCKS, processes=2))
    assert len(one) == len(two) == 9
    for (b1, d1, g1), (b2, d2, g2) in zip(one, two):
        assert b1 == b2
        np.testing.assert_array_equal(d1, d2)
        np.testing.assert_array_equal(g1, g2)
    assert sum(int(g.sum()) for _, _, g in two) > 0.5 * np.isfinite(dsm).sum()


@pytest.mark.parametrize("plane", [0, 8])
def test_blockwise_dtm_equals_the_whole_grid(scene, plane):
    """Exact: the fill looks ``search`` cells far (with local planes, 3 x ``plane`` + 1) and the
    window reaches farther; a hole in the ground wider than the window (cells take their nearest
    filled cell) makes a block read again wider."""
    grid, dsm, _, whole = scene
    seed = np.where(whole, dsm, np.nan)
    seed[100:420, 150:500] = np.nan                     # no ground for 160 m around (300, 325)
    seed[600:, :] = np.nan
    expected = interpolate_dtm(seed, 20, plane_cells=plane)
    got = np.full(dsm.shape, np.nan)
    for block, values in dtm_blocks(_read(seed), grid, 20, SMALL_BLOCKS, plane_cells=plane):
        got[block.core] = values
    np.testing.assert_array_equal(got, expected)
    if plane:
        assert not np.array_equal(expected, interpolate_dtm(seed, 20))         # the planes moved the gaps


def test_a_one_block_dtm_is_filled_in_exact_halves(scene):
    """The fixture's grid is one block of the default size; the fill runs on its two halves (so two
    workers can share it) and gives the whole grid's DTM bit for bit."""
    from pipeline25d.stages.terrain.dtm import dtm_layout

    grid, dsm, _, whole = scene
    seed = np.where(whole, dsm, np.nan)
    assert len(dtm_layout(grid, 20)) == 2
    got = np.full(dsm.shape, np.nan)
    for block, values in dtm_blocks(_read(seed), grid, 20):
        got[block.core] = values
    np.testing.assert_array_equal(got, interpolate_dtm(seed, 20))


def test_blockwise_dtm_by_forked_workers_equals_one_process(scene, tmp_path):
    """The scene job's DTM blocks filled two at a time by forked workers, each reading its own
    window of the ground raster (pickled as its path), equal those filled here bit for bit, in
    the same order: with a hole that makes a block read again wider, with empty land left NaN,
    and with the check points held out (the read the scene's second fill sends its workers)."""
    import pickle
    from functools import partial

    from pipeline25d.core.cores import fork_pool
    from pipeline25d.core.geotiff import write_float_geotiff
    from pipeline25d.stages.scene import _held_out_read, _without_held_out

    grid, dsm, _, whole = scene
    seed = np.where(whole, dsm, np.nan)
    seed[100:420, 150:500] = np.nan
    write_float_geotiff(tmp_path / "ground.tif", seed, grid, "")
    raster = FloatRaster(tmp_path / "ground.tif")
    held = np.array([[E0 + 43.0 + 90 * (i % 8), N0 + 37.0 + 90 * (i // 8)] for i in range(56) if not i % 3])
    held_out = partial(_held_out_read, raster, grid, held, 6.0)
    window = (slice(40, 600), slice(30, 700))
    np.testing.assert_array_equal(pickle.loads(pickle.dumps(held_out))(*window),
                                  _without_held_out(raster.read(*window), grid, held, 6.0, window))
    assert np.isnan(held_out(*window)).sum() > np.isnan(seed[window]).sum()      # some ground was held out

    def needed(core):
        return core[1].start < 512          # the right-hand column of blocks is empty land

    for read in (raster.read, held_out):
        here = list(dtm_blocks(read, grid, 20, SMALL_BLOCKS, needed=needed, reach_cells=80))
        with fork_pool(2) as pool:
            forked = list(dtm_blocks(read, grid, 20, SMALL_BLOCKS, needed=needed, reach_cells=80, pool=pool, ahead=2))
        assert [b for b, _ in here] == [b for b, _ in forked] and len(here) == 9
        for (_, a), (_, b) in zip(here, forked):
            np.testing.assert_array_equal(a, b)
        assert sum(np.isfinite(v).sum() for _, v in forked) > 0.5 * 512 * 640
        assert all(np.isnan(v).all() for b, v in forked if not needed(b.core))


def test_blockwise_sites_equal_the_whole_grid_in_float32(scene):
    grid, dsm, _, whole = scene
    dsm32 = dsm.astype(np.float32)
    dtm = interpolate_dtm(np.where(whole, dsm32, np.nan), 20)           # float32 values, as the scene stage has
    rules = SiteRules(spacing=12.0, radius=1.0, clearance=1.0, max_roughness=0.3)
    views = [Perspective(45, 45), Perspective(200, 60), Perspective(0, 90)]
    expected = select_sites(dsm32.astype(np.float64), dtm, grid, rules, views)
    got = select_sites(dsm32, dtm.astype(np.float32), grid, rules, views, max_cells=200 * 200)
    assert len(expected["x"]) > 500
    assert expected.keys() == got.keys()
    for key in expected:
        np.testing.assert_array_equal(got[key], expected[key], err_msg=key)


def test_geotiff_written_by_blocks_reads_back(tmp_path):
    grid = Grid.north_up(E0, N0 + 600, 0.5, 700, 600)
    values = np.random.default_rng(0).normal(size=grid.shape).astype(np.float32)
    values[:40, :90] = np.nan
    with float_geotiff_writer(tmp_path / "r.tif", grid, "") as write:
        for b in cell_blocks(*grid.shape, 0, 300 * 300):
            write(values[b.core], b.core[0].start, b.core[1].start)
    raster = FloatRaster(tmp_path / "r.tif")
    assert raster.grid == grid
    np.testing.assert_array_equal(raster.read_all(np.float32), values)
    np.testing.assert_array_equal(raster.read(slice(10, 20), slice(600, 700)), values[10:20, 600:].astype(np.float64))


def sparse_scene():
    """Two 1 m districts (copies of boxes_on_a_slope's corners) in a 2 x 1.5 km box of empty land."""
    grid = Grid.north_up(E0, N0 + 1536, 1.0, 2048, 1536)
    dsm = boxes_on_a_slope(seed=3)[1][:400, :400]
    sparse = np.full(grid.shape, np.nan)
    sparse[40:440, 60:460] = dsm
    sparse[1100:1500, 1500:1900] = dsm[::-1]
    return grid, sparse


def test_empty_land_is_not_filtered_and_the_districts_are_as_alone(monkeypatch):
    """A window without model costs no cloth simulation; the districts' ground is what the
    filter finds on each district alone (the empty land between them changes nothing)."""
    import pipeline25d.stages.terrain.ground as terrain

    grid, dsm = sparse_scene()
    calls = []
    cloth = terrain._cloth_ground
    monkeypatch.setattr(terrain, "_cloth_ground",
                        lambda residual, *a: calls.append(residual.shape) or cloth(residual, *a))
    ground = np.zeros(grid.shape, bool)
    blocks = 0
    for block, core_dsm, core_ground in ground_blocks(_read(dsm), grid, MAX_OBJECT_M, 2.0, 2, 0.5, 512 * 512):
        np.testing.assert_array_equal(core_dsm, dsm[block.core])
        ground[block.core] = core_ground
        blocks += 1
    assert blocks >= 12 and 2 <= len(calls) <= blocks // 2       # only the windows that hold a district
    assert not ground[~np.isfinite(dsm)].any()
    for rows, cols in [(slice(40, 440), slice(60, 460)), (slice(1100, 1500), slice(1500, 1900))]:
        own = Grid.north_up(grid.xmin + cols.start * grid.res, grid.ymax - rows.start * grid.res, grid.res, 400, 400)
        alone = trim_object_edges(csf_ground(dsm[rows, cols], own, MAX_OBJECT_M, 2.0, 2, 0.5), dsm[rows, cols])
        assert (ground[rows, cols] == alone).mean() >= 0.995


@pytest.mark.parametrize("plane", [0, 8])
def test_dtm_only_where_it_is_needed(plane):
    """Blocks ``needed`` rejects stay NaN without a fill; the others equal the whole grid's DTM."""
    grid, dsm = sparse_scene()
    seed = np.where(np.isfinite(dsm) & (np.arange(dsm.shape[1]) % 7 != 0), dsm, np.nan)
    expected = interpolate_dtm(seed, 20, reach_cells=80, plane_cells=plane)
    asked = []

    def has_model(core):
        return bool(np.isfinite(dsm[core]).any())

    def needed(core):
        asked.append(core)
        return has_model(core)

    got = np.full(grid.shape, -1.0)
    for block, values in dtm_blocks(_read(seed), grid, 20, 512 * 512, needed=needed, reach_cells=80,
                                    plane_cells=plane):
        got[block.core] = values
    used = np.zeros(grid.shape, bool)
    for core in asked:
        used[core] = has_model(core)
    assert 0 < used.mean() < 0.5
    np.testing.assert_array_equal(got[used], expected[used])
    assert np.isnan(got[~used]).all()
    assert np.isfinite(got[np.isfinite(dsm)]).all() and np.isnan(got[used]).any()   # reach ends in the empty land


def test_near_windows_take_each_cell_near_the_mask_once_with_all_it_can_see():
    from scipy import ndimage as ndi

    from pipeline25d.stages.terrain.dtm import near_windows

    rng = np.random.default_rng(5)
    mask = np.zeros((300, 410), bool)
    mask[rng.integers(0, 300, 12), rng.integers(0, 410, 12)] = True        # a dozen scattered cells
    mask[:3, 400:] = True
    reach = 9
    windows = near_windows(mask, reach, cell=16)
    taken = np.zeros(mask.shape, int)
    for (rows, cols), take in windows:
        assert take.shape == (rows.stop - rows.start, cols.stop - cols.start)
        taken[rows, cols] += take
        for r, c in zip(*np.nonzero(take)):               # all True cells within reach of a taken cell are inside
            r, c = r + rows.start, c + cols.start
            near = mask[max(r - reach, 0):r + reach + 1, max(c - reach, 0):c + reach + 1].sum()
            assert mask[rows, cols][max(r - reach - rows.start, 0):r + reach + 1 - rows.start,
                                    max(c - reach - cols.start, 0):c + reach + 1 - cols.start].sum() == near
    chess = ndi.distance_transform_cdt(~mask, metric="chessboard")
    assert (taken <= 1).all() and (taken[chess <= reach] == 1).all()
    assert len(windows) > 3 and taken.mean() < 0.5
    assert near_windows(np.zeros((5, 5), bool), 3) == []


def test_the_fill_of_a_sparse_window_equals_gdals_fill_of_all_of_it():
    """The fill runs only on the ground's box grown by the search; GDAL's FillNodata run over the
    whole window (its reference) gives the same values, NaN beyond the search included."""
    from pipeline25d.stages.terrain.dtm import _fill_nodata, _fill_window

    rng = np.random.default_rng(3)
    seed = np.full((400, 500), np.nan)
    patch = rng.normal(5.0, 1.0, (60, 40))
    patch[rng.random(patch.shape) < 0.6] = np.nan                  # gaps inside the ground
    seed[300:360, 420:460] = patch                                 # ground in one corner, empty land elsewhere
    got = _fill_nodata(seed, 12)
    np.testing.assert_array_equal(got, _fill_window(seed, 12))
    assert np.isnan(got[:200, :300]).all() and np.isfinite(got[300:360, 420:460]).all()
    assert np.isnan(_fill_nodata(np.full((5, 5), np.nan), 3)).all()


def test_under_chunks_meets_exactly_the_blocks_under_a_footprint():
    from pipeline25d.stages.scene import _under_chunks

    grid = Grid.north_up(E0, N0 + 1000, 0.5, 4000, 2000)            # 2 x 1 km
    bounds = np.array([[[E0 + 100, N0 + 900, 0], [E0 + 180, N0 + 980, 30]]])
    needed = _under_chunks(bounds, grid)
    assert needed((slice(0, 256), slice(0, 512)))            # holds x 100-180 m, y 20-100 m from the top
    assert not needed((slice(0, 256), slice(512, 1024)))     # x 256-512 m
    assert not needed((slice(256, 512), slice(0, 512)))      # y 128-256 m from the top
    assert needed((slice(0, 256), slice(362, 512)))          # x 181-256 m: within the 2-cell margin


def test_empty_blocks_are_not_stored(tmp_path):
    """An all-NaN block is not written: its GeoTIFF tiles have no data on disk and read as NaN."""
    from pipeline25d.core.raster import gdal

    grid = Grid.north_up(E0, N0 + 512, 1.0, 768, 512)
    values = np.full(grid.shape, np.nan, np.float32)
    values[:256, 512:] = 7.5
    with float_geotiff_writer(tmp_path / "r.tif", grid, "") as write:
        for b in cell_blocks(*grid.shape, 0, 256 * 256):
            write(values[b.core], b.core[0].start, b.core[1].start)
    ds = gdal().Open(str(tmp_path / "r.tif"))          # kept referenced while its band is read
    band = ds.GetRasterBand(1)
    stored = [[bool(int(band.GetMetadataItem(f"BLOCK_OFFSET_{c}_{r}", "TIFF") or 0)) for c in range(3)]
              for r in range(2)]
    assert stored == [[False, False, True], [False, False, False]]
    np.testing.assert_array_equal(FloatRaster(tmp_path / "r.tif").read_all(np.float32), values)


def test_islands_are_the_groups_of_model_gap_cells_apart():
    from pipeline25d.stages.terrain.ground import islands

    valid = np.zeros((60, 80), bool)
    valid[2:10, 3:12] = True           # A
    valid[12:20, 3:12] = True          # B: 2 empty rows below A
    valid[40:55, 50:78] = True         # C: far from both
    got = [(box, mask.sum()) for box, mask in islands(valid, 5)]
    assert [m for _, m in got] == [8 * 9 * 2, 15 * 28]
    for box, mask in islands(valid, 5):
        assert valid[box].sum() == mask.sum()          # each island's box holds no other island here
    alone = list(islands(valid[:30, :20], 5))
    assert len(alone) == 1 and alone[0][1].sum() == 144 and alone[0][1].shape == (20, 15)   # whole coarse cells
    assert list(islands(np.zeros((9, 9), bool), 5)) == []


def test_dtm_heights_at_points_equal_each_points_own_window_sampled_alone():
    """The scene stage samples the DTM at every candidate: at once where a point's 5 x 5 cells are
    inside the grid and whole, one window at a time elsewhere; every height equals the one its own
    window gives as a continuous DTM (the holes filled from the window), bit for bit."""
    from pipeline25d.core.raster import DTM
    from pipeline25d.stages.scene import _sample_continuous

    rng = np.random.default_rng(5)
    grid = Grid.north_up(84000.25, 447000.75, 0.5, 90, 70)
    values = (3 + rng.normal(0, 2, grid.shape)).astype(np.float32)
    values[rng.random(grid.shape) < 0.02] = np.nan                    # holes a window fills from its own cells
    values[:, :4] = np.nan
    x = rng.uniform(grid.xmin - 1.0, grid.xmin + grid.width * 0.5 + 1.0, 3000)
    y = rng.uniform(grid.ymax - grid.height * 0.5 - 1.0, grid.ymax + 1.0, 3000)
    xy = np.column_stack([x, y])
    got = _sample_continuous(values, grid, xy)
    want = np.empty(len(xy))
    for i, (px, py) in enumerate(xy):
        col, row = grid.cell_of(px, py)
        rows, cols = slice(max(row - 2, 0), min(row + 3, grid.height)), slice(max(col - 2, 0), min(col + 3, grid.width))
        window = DTM.from_array(values[rows, cols], grid.window(rows, cols), continuous=True)
        want[i] = window.sample(np.array([px]), np.array([py]))[0]
    assert np.isfinite(want).sum() > 2500          # NaN: a window wholly in the empty columns
    np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("share", [0.2, 0.8])
def test_the_cloths_ground_reads_the_same_from_either_index_vector(share):
    """CSF returns the ground's indices and the rest's; the mask is read from the shorter, and it
    is the ground's either way (mostly off-ground and mostly ground)."""
    import CSF

    from pipeline25d.stages.terrain.ground import _indexed

    rng = np.random.default_rng(3)
    truth = rng.random(5000) < share
    ground, off = CSF.VecInt(), CSF.VecInt()
    for i in np.flatnonzero(truth).tolist():
        ground.append(i)
    for i in np.flatnonzero(~truth).tolist():
        off.append(i)
    assert np.array_equal(_indexed(len(truth), ground, off), truth)
