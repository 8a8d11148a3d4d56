"""The web-tile cut: the pipeline's (reprojected once, then gdal2tiles) against gdal2tiles
with its defaults on the same map."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
from conftest import grid_plan
from PIL import Image

from pipeline25d.core.crs import transform_points
from pipeline25d.core.geotiff import write_rgba_geotiff
from pipeline25d.core.grid import Grid
from pipeline25d.core.raster import gdal
from pipeline25d.stages.tiles.blocks import WEB_MERCATOR
from pipeline25d.stages.tiles.web import BLOCK_TILES, tms


def tile_offsets(tiles, zoom: int, f, wkt: str) -> np.ndarray:
    """(n, 2) metres: per base tile at ``zoom`` where its content lies against where it should, fitted by
    least squares from its red and green against ``f`` (x, y) -> (red, green), the map's smooth pattern
    evaluated at each opaque tile pixel's centre taken back to the map's CRS by PROJ (red = a function of x,
    green of y, so red moves with x and green with y)."""
    world = 2 * 20037508.342789244
    out = []
    for path in sorted((tiles / str(zoom)).rglob("*.png")):
        x, y = int(path.parent.name), int(path.stem)
        rgba = np.asarray(Image.open(path).convert("RGBA"), float)
        px = world / 2 ** zoom / 256
        cols, rows = np.meshgrid(np.arange(256) + 0.5, np.arange(256) + 0.5)
        ok = rgba[..., 3] == 255
        merc = np.column_stack([x * 256 * px - world / 2 + cols[ok] * px, world / 2 - (y * 256 + rows[ok]) * px])
        utm = transform_points(np.column_stack([merc, np.zeros(len(merc))]), WEB_MERCATOR, wkt)[:, :2]
        want, grad = f(utm[:, 0], utm[:, 1])
        if ok.sum() < 10_000:
            continue
        shift = [-((rgba[..., k][ok] - want[k]) * grad[k]).sum() / (grad[k] ** 2).sum() for k in (0, 1)]
        out.append(shift)
    return np.array(out)


def test_tiles_lie_where_the_map_is_and_where_gdal2tiles_puts_them(tmp_path):
    """A map of smooth waves in x (red) and y (green): every base tile holds the map where PROJ puts each of
    its pixels, within 0.1 m (a fifth of the map's 0.5 m pixel), fitted tile by tile; gdal2tiles with its
    defaults cuts the same tiles (positions and zooms), its own base tiles moved by up to a source pixel."""
    from pipeline25d.core.crs import horizontal_wkt

    h, w = 900, 1300
    grid = Grid.north_up(691000.0, 5334000.0, 0.5, w, h)
    period = 40.0                                               # metres: smooth at the tiles' 0.8 m pixels
    k = 2 * np.pi / period

    def f(x, y):
        u, v = x - grid.transform.c, grid.transform.f - y
        return ((128 + 100 * np.sin(k * u), 128 + 100 * np.sin(k * v)),
                (100 * k * np.cos(k * u), -100 * k * np.cos(k * v)))

    xs, ys = grid.xy(*np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5))
    (red, green), _ = f(xs, ys)
    rgba = np.zeros((h, w, 4), np.uint8)
    rgba[..., 0], rgba[..., 1], rgba[..., 2], rgba[..., 3] = np.round(red), np.round(green), 90, 255
    rgba[:200, :300] = 0        # a transparent corner, RGB 0 under it as the renderer writes it
    cog = tmp_path / "map.tif"
    wkt = horizontal_wkt("EPSG:25832")
    write_rgba_geotiff(cog, rgba, grid, wkt)
    ours, ref = tmp_path / "ours", tmp_path / "ref"
    stats = tms(cog, "auto", ours, tile_format="png")
    subprocess.run([sys.executable, "-m", "osgeo_utils.gdal2tiles", "-q", "--xyz", "-w", "none", "-r", "average",
                    str(cog), str(ref)], check=True)
    ref_tiles = sorted(p.relative_to(ref) for p in ref.rglob("*.png"))
    assert ref_tiles and sorted(p.relative_to(ours) for p in ours.rglob("*.png")) == ref_tiles
    zmax = int(stats["zooms"].split("-")[1])
    mine, theirs = tile_offsets(ours, zmax, f, wkt), tile_offsets(ref, zmax, f, wkt)
    print({"tiles": len(mine), "ours_max_m": np.abs(mine).max(axis=0).round(3).tolist(),
           "gdal2tiles_max_m": np.abs(theirs).max(axis=0).round(3).tolist()})
    assert len(mine) >= 6 and np.abs(mine).max() <= 0.1, mine
    assert not list(tmp_path.glob("*.3857.tif")) and not list(tmp_path.glob(".ours*"))   # nothing left over


def _smooth_map(path):
    from pipeline25d.core.crs import horizontal_wkt

    h, w = 600, 800
    yy, xx = np.mgrid[0:h, 0:w]
    rgba = np.zeros((h, w, 4), np.uint8)
    rgba[..., 0] = (128 + 100 * np.sin(xx / 23.0)).astype(np.uint8)
    rgba[..., 1] = (128 + 100 * np.cos(yy / 31.0)).astype(np.uint8)
    rgba[..., 2] = 90
    rgba[..., 3] = 255
    rgba[:150, :200] = 0
    write_rgba_geotiff(path, rgba, Grid.north_up(691000.0, 5334000.0, 0.5, rgba.shape[1], rgba.shape[0]),
                       horizontal_wkt("EPSG:25832"))


def test_webp_tiles_are_the_png_tiles_lossy_and_keep_transparency(tmp_path):
    _smooth_map(tmp_path / "map.tif")
    tms(tmp_path / "map.tif", "auto", tmp_path / "png", tile_format="png")
    tms(tmp_path / "map.tif", "auto", tmp_path / "webp", tile_format="webp", quality=85)
    png = sorted(p.relative_to(tmp_path / "png").with_suffix("") for p in (tmp_path / "png").rglob("*.png"))
    webp = sorted(p.relative_to(tmp_path / "webp").with_suffix("") for p in (tmp_path / "webp").rglob("*.webp"))
    assert png and webp == png
    errs = []
    for t in png:
        a = np.asarray(Image.open((tmp_path / "png" / t).with_suffix(".png")).convert("RGBA"), float)
        b = np.asarray(Image.open((tmp_path / "webp" / t).with_suffix(".webp")).convert("RGBA"), float)
        assert np.abs(a[..., 3] - b[..., 3]).mean() < 1.0                  # transparency kept
        errs.append(np.abs(a[..., :3] - b[..., :3])[a[..., 3] == 255].ravel())
    assert np.concatenate(errs).mean() < 3.0                                # lossy, but the same picture


def test_a_faster_webp_effort_reaches_every_tile_and_keeps_the_picture(tmp_path):
    """tms.webp_method (libwebp's METHOD, which gdal2tiles cannot set) is used for the base tiles
    and for every zoom above them, in this process and in forked workers alike; the tiles lie
    where libwebp's default puts them and show the same picture as the lossless cut."""
    _smooth_map(tmp_path / "map.tif")
    tms(tmp_path / "map.tif", "auto", tmp_path / "png", tile_format="png")
    cuts = {name: tmp_path / name for name in ("default", "fast", "fast2")}
    tms(tmp_path / "map.tif", "auto", cuts["default"], tile_format="webp", quality=85)
    tms(tmp_path / "map.tif", "auto", cuts["fast"], tile_format="webp", quality=85, webp_method=0)
    tms(tmp_path / "map.tif", "auto", cuts["fast2"], tile_format="webp", quality=85, webp_method=0, processes=2)
    names = {k: sorted(p.relative_to(d) for p in d.rglob("*.webp")) for k, d in cuts.items()}
    assert names["default"] and names["fast"] == names["default"] == names["fast2"]
    zooms = {t.parts[0] for t in names["fast"]}
    assert len(zooms) >= 3
    for z in zooms:                                    # METHOD=0 changed the bytes at every zoom
        same = [(cuts["fast"] / t).read_bytes() == (cuts["default"] / t).read_bytes() for t in names["fast"]
                if t.parts[0] == z]
        assert not all(same), z
    assert all((cuts["fast"] / t).read_bytes() == (cuts["fast2"] / t).read_bytes() for t in names["fast"])
    errs = []
    for t in names["fast"]:
        a = np.asarray(Image.open((tmp_path / "png" / t).with_suffix(".png")).convert("RGBA"), float)
        b = np.asarray(Image.open(cuts["fast"] / t).convert("RGBA"), float)
        assert np.abs(a[..., 3] - b[..., 3]).mean() < 1.0
        errs.append(np.abs(a[..., :3] - b[..., :3])[a[..., 3] == 255].ravel())
    assert np.concatenate(errs).mean() < 3.0


def test_jpeg_maps_keep_their_transparency_as_a_mask_that_the_readers_use(tmp_path):
    from osgeo import gdal

    from pipeline25d.analysis.evaluate.rasters import _read_window
    from pipeline25d.stages.maps.warp import warp_to_cog

    _smooth_map(tmp_path / "map.tif")
    plan = grid_plan([(0, 0)], 0.5, 256, "EPSG:25832")
    sizes = {}
    for codec in ("deflate", "jpeg", "webp"):
        out = tmp_path / f"{codec}.tif"
        warp_to_cog(tmp_path / "map.tif", [], {"method": "none"}, plan, out, codec, 85)
        sizes[codec] = out.stat().st_size
        _, alpha = _read_window(gdal.Open(str(out)), 0, 0, 400)
        assert (alpha[:150, :200] == 0).all() and (alpha[200:, 250:] == 255).all(), codec
    assert gdal.Open(str(tmp_path / "jpeg.tif")).RasterCount == 3
    assert sizes["jpeg"] < sizes["deflate"] / 2 and sizes["webp"] < sizes["deflate"] / 2, sizes


def test_a_cut_removes_what_a_killed_cut_of_the_same_map_left(tmp_path):
    _smooth_map(tmp_path / "map.tif")
    stale_dir, stale_file = tmp_path / ".out.k1ll3d", tmp_path / ".out.3857.tif"
    (stale_dir / "17" / "1").mkdir(parents=True)
    (stale_dir / "17" / "1" / "2.png").write_bytes(b"half a tile")
    stale_file.write_bytes(b"half a raster")
    (tmp_path / ".other.k1ll3d").mkdir()                   # another map's: not this cut's to remove
    tms(tmp_path / "map.tif", "auto", tmp_path / "out", tile_format="png")
    assert not stale_dir.exists() and not stale_file.exists() and (tmp_path / ".other.k1ll3d").exists()
    assert any((tmp_path / "out").rglob("*.png"))


def test_sigterm_removes_a_jobs_temporaries_like_ctrl_c(tmp_path):
    """A job stopped by SIGTERM (a scheduler's cancel) leaves no temporary file behind."""
    import signal
    import time

    script = (f"import time; from pipeline25d.core.atomic import atomic_path; "
              f"from pipeline25d.core.logsetup import log_to\n"
              f"log_to({str(tmp_path / 'job.log')!r})\n"
              f"with atomic_path({str(tmp_path / 'out.tif')!r}) as tmp:\n"
              f"    tmp.write_bytes(b'partial'); print('ready', flush=True); time.sleep(60)\n")
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "ready"
    assert len(list(tmp_path.glob(".out.tif.*"))) == 1
    t0 = time.monotonic()
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(timeout=10) == 128 + signal.SIGTERM and time.monotonic() - t0 < 5
    assert not list(tmp_path.glob(".out.tif.*")) and not (tmp_path / "out.tif").exists()


def _tile_files(root):
    return {str(p.relative_to(root)): p for p in sorted(root.rglob("*.png"))}


def test_an_update_recuts_only_the_web_tiles_a_changed_district_reaches_and_equals_a_fresh_cut(tmp_path):
    """A map changed in one small square: the kept pyramid is updated in place of the tiles
    over that square (and those above them), every other published tile keeps its file, and
    the result is byte for byte the pyramid cut from scratch."""
    import hashlib
    import os

    from pipeline25d.core.crs import horizontal_wkt

    wkt = horizontal_wkt("EPSG:25832")
    gt = (691000.0, 0.5, 0.0, 5334000.0, 0.0, -0.5)
    rng = np.random.default_rng(1)
    h, w = 2400, 3000
    before = np.zeros((h, w, 4), np.uint8)
    before[..., :3] = rng.integers(0, 255, (h, w, 3), dtype=np.uint8)
    before[..., 3] = 255
    before[:300, :400] = 0
    after = before.copy()
    r0, c0 = 900, 1300
    after[r0:r0 + 120, c0:c0 + 150, :3] = 255 - after[r0:r0 + 120, c0:c0 + 150, :3]   # the changed "district"
    write_rgba_geotiff(tmp_path / "a.tif", before, Grid.from_gdal(gt, w, h), wkt)
    write_rgba_geotiff(tmp_path / "b.tif", after, Grid.from_gdal(gt, w, h), wkt)
    work, out = tmp_path / "work", tmp_path / "out"
    first = tms(tmp_path / "a.tif", "auto", out, processes=2, work_dir=work)
    assert first["full"] and first["web_tiles_redone"] == first["web_tiles"] > 50
    def ident(p):                           # a freed inode number may be reused: with the mtime
        return os.stat(p).st_ino, os.stat(p).st_mtime_ns

    old = {k: ident(p) for k, p in _tile_files(out).items()}
    again = tms(tmp_path / "a.tif", "auto", out, processes=2, work_dir=work)
    assert not again["full"] and again["web_tiles_redone"] == 0 and again["blocks_warped"] == 0
    update = tms(tmp_path / "b.tif", "auto", out, processes=2, work_dir=work)
    fresh = tms(tmp_path / "b.tif", "auto", tmp_path / "fresh", processes=2)
    got, want = _tile_files(out), _tile_files(tmp_path / "fresh")
    assert sorted(got) == sorted(want)

    def sha(p):
        return hashlib.sha256(p.read_bytes()).hexdigest()

    assert [k for k in want if sha(got[k]) != sha(want[k])] == []
    assert update["web_tiles"] == fresh["web_tiles"] == len(want)
    # only tiles near the changed square were written again (within a block of it); their count is the update's
    redone = {k for k, p in got.items() if ident(p) != old.get(k)}
    assert len(redone) == update["web_tiles_redone"] > 0
    max_zoom = int(update["zooms"].split("-")[1])
    base = [k for k in got if k.startswith(f"{max_zoom}/")]
    assert 0 < len([k for k in redone if k in base]) < 0.25 * len(base)
    minx, maxy = gt[0] + c0 * gt[1], gt[3] + r0 * gt[5]
    corners = transform_points(np.array([[minx, maxy - 120 * 0.5, 0.0], [minx + 150 * 0.5, maxy, 0.0]]), wkt,
                               WEB_MERCATOR)
    world = 2 * 20037508.342789244
    slack = BLOCK_TILES * world / 2 ** max_zoom
    for key in redone:
        z, x, y = (int(v) for v in key[:-4].split("/"))
        span = world / 2 ** z
        x0, y1 = x * span - world / 2, world / 2 - y * span
        assert x0 < corners[1, 0] + slack and x0 + span > corners[0, 0] - slack, key
        assert y1 - span < corners[1, 1] + slack and y1 > corners[0, 1] - slack, key


def test_sigterm_stops_a_cut_at_once_and_the_next_cut_finishes_it(tmp_path):
    """SIGTERM to a cut's process group (as Snakemake and SLURM stop a job) while its workers cut:
    the job ends within seconds with no worker left, and the next run of the same cut gives the
    pyramid cut from scratch."""
    import hashlib
    import signal
    import time

    from pipeline25d.core.crs import horizontal_wkt

    rng = np.random.default_rng(2)
    h, w = 3000, 4000
    rgba = np.zeros((h, w, 4), np.uint8)
    rgba[..., :3] = rng.integers(0, 255, (h, w, 3), dtype=np.uint8)
    rgba[..., 3] = 255
    write_rgba_geotiff(tmp_path / "map.tif", rgba, Grid.north_up(691000.0, 5334000.0, 0.5, w, h),
                       horizontal_wkt("EPSG:25832"))
    work, out = tmp_path / "work", tmp_path / "out"
    script = (f"from pipeline25d.core.logsetup import log_to; from pipeline25d.stages.tiles.web import tms\n"
              f"log_to({str(tmp_path / 'job.log')!r})\n"
              f"tms({str(tmp_path / 'map.tif')!r}, 'auto', {str(out)!r}, processes=2, work_dir={str(work)!r})\n")
    proc = subprocess.Popen([sys.executable, "-c", script], start_new_session=True)
    deadline = time.monotonic() + 120
    while not any((work / "tiles").rglob("*.png")) and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.05)
    assert proc.poll() is None, "the cut ended before any tile was written: make the map larger"
    os.killpg(proc.pid, signal.SIGTERM)
    cut_before = sum(1 for _ in (work / "tiles").rglob("*.png"))
    assert proc.wait(timeout=10) == 128 + signal.SIGTERM                # the issue's bound
    time.sleep(0.5)
    left = subprocess.run(["pgrep", "-s", str(proc.pid)], capture_output=True, text=True).stdout.split()
    assert left == []
    # the workers stopped with their tile in hand: they did not go on to the rest of the stage
    assert sum(1 for _ in (work / "tiles").rglob("*.png")) <= cut_before + 2
    assert not out.exists()                                    # nothing published that looks complete
    tms(tmp_path / "map.tif", "auto", out, processes=2, work_dir=work)
    tms(tmp_path / "map.tif", "auto", tmp_path / "fresh", processes=2)
    got, want = _tile_files(out), _tile_files(tmp_path / "fresh")
    assert sorted(got) == sorted(want) and len(want) > 50
    assert [k for k in want if hashlib.sha256(got[k].read_bytes()).digest()
            != hashlib.sha256(want[k].read_bytes()).digest()] == []


def test_blocks_kept_averaged_to_the_tile_pixels_cut_the_same_tiles_as_blocks_kept_as_warped(tmp_path, monkeypatch):
    """A map of noise (every pixel its own colour) with the alphas of 4x MSAA edges: the blocks kept at
    the tiles' pixels (box_mean) give the pyramid that blocks kept on the finer warp grid give, where each
    base tile averages its window as gdal2tiles does (base.average_tile), byte for byte at every zoom."""
    from pipeline25d.core.crs import horizontal_wkt
    from pipeline25d.stages.tiles import blocks, web

    rng = np.random.default_rng(7)
    h, w = 700, 900
    rgba = rng.integers(0, 256, (h, w, 4), dtype=np.uint8)
    rgba[..., 3] = rng.choice(np.array([0, 64, 128, 191, 255], np.uint8), (h, w), p=[0.1, 0.1, 0.1, 0.1, 0.6])
    rgba[rgba[..., 3] == 0, :3] = 0                    # the renderer's transparent pixels are black
    rgba[:120, :160] = 0
    write_rgba_geotiff(tmp_path / "map.tif", rgba, Grid.north_up(691000.0, 5334000.0, 0.25, w, h),
                       horizontal_wkt("EPSG:25832"))
    grid, zooms = web.tile_grid(tmp_path / "map.tif", "auto")
    assert blocks.stored_factor(grid, int(zooms.split("-")[1])) == 2          # the map's warp grid is halved once
    kept = web.tms(tmp_path / "map.tif", "auto", tmp_path / "kept", tile_format="png", work_dir=tmp_path / "kw")
    assert {p.name for p in (tmp_path / "kw" / "blocks").iterdir()}
    for kept_block in (tmp_path / "kw" / "blocks").glob("*.tif"):        # kept on the tiles' own pixels
        ds = gdal().Open(str(kept_block))
        assert abs(ds.GetGeoTransform()[1] - 2 * grid.transform.a) < 1e-9 * grid.transform.a
    monkeypatch.setattr(blocks, "STORED_FACTORS", ())
    warped = web.tms(tmp_path / "map.tif", "auto", tmp_path / "warped", tile_format="png")
    files = sorted(p.relative_to(tmp_path / "kept") for p in (tmp_path / "kept").rglob("*.png"))
    assert kept["web_tiles"] == warped["web_tiles"] == len(files) > 10
    assert files == sorted(p.relative_to(tmp_path / "warped") for p in (tmp_path / "warped").rglob("*.png"))
    assert all((tmp_path / "kept" / f).read_bytes() == (tmp_path / "warped" / f).read_bytes() for f in files)


def test_box_mean_rounds_half_up_like_the_average_of_a_query():
    """box_mean against average_tile on a whole window (the query each base tile is averaged from)."""
    from pipeline25d.stages.tiles.base import average_tile, nearest_index
    from pipeline25d.stages.tiles.blocks import box_mean

    rng = np.random.default_rng(3)
    for f in (2, 4):
        window = rng.integers(0, 256, (4, 256 * f, 256 * f), dtype=np.uint8)
        idx = nearest_index(256 * f, 1024)
        np.testing.assert_array_equal(box_mean(window, f), average_tile(window, idx, idx, 0, 0, 1024, 256))
    assert box_mean(np.array([[[1, 2], [2, 1]]], np.uint8), 2)[0, 0, 0] == 2          # 6/4 = 1.5 -> 2
    assert box_mean(np.array([[[1, 1], [2, 1]]], np.uint8), 2)[0, 0, 0] == 1          # 5/4 = 1.25 -> 1


def _cog(dense, out, sparse: bool):
    gdal().Translate(str(out), str(dense), format="COG",
                     creationOptions=["COMPRESS=DEFLATE", *(["SPARSE_OK=TRUE"] if sparse else [])])
    return out


def test_a_sparse_map_skips_the_blocks_over_nothing_and_cuts_the_same_tiles(tmp_path):
    """Two districts 1.5 km apart on one map: stored sparse (its empty blocks unstored, as the warp
    writes maps), the web-mercator blocks over nothing are not warped, and the tiles are byte for
    byte those cut from the same pixels stored dense (every block warped). A district then removed:
    the update drops its tiles and equals a fresh cut."""
    import hashlib

    from pipeline25d.core.crs import horizontal_wkt

    wkt = horizontal_wkt("EPSG:25832")
    grid = Grid.from_gdal((691000.0, 0.5, 0.0, 5334000.0, 0.0, -0.5), 3600, 3600)
    rng = np.random.default_rng(7)
    both = np.zeros((3600, 3600, 4), np.uint8)
    for r, c in ((200, 300), (3000, 3100)):
        both[r:r + 300, c:c + 300, :3] = rng.integers(0, 255, (300, 300, 3), dtype=np.uint8)
        both[r:r + 300, c:c + 300, 3] = 255
    one = both.copy()
    one[3000:3300, 3100:3400] = 0
    write_rgba_geotiff(tmp_path / "both.tif", both, grid, wkt)
    write_rgba_geotiff(tmp_path / "one.tif", one, grid, wkt)
    dense = tms(_cog(tmp_path / "both.tif", tmp_path / "dense.tif", False), "auto", tmp_path / "d", processes=2)
    work = tmp_path / "work"
    sparse = tms(_cog(tmp_path / "both.tif", tmp_path / "sparse.tif", True), "auto", tmp_path / "s", processes=2,
                 work_dir=work)
    # dense: only blocks beyond the map's edge hold nothing; sparse: those between the districts too
    assert sparse["blocks_over_nothing"] > dense["blocks_over_nothing"] + 2
    assert sum(sparse[k] for k in ("blocks_warped", "blocks_over_nothing")) == \
        sum(dense[k] for k in ("blocks_warped", "blocks_over_nothing"))

    def digests(root):
        return {k: hashlib.sha256(p.read_bytes()).hexdigest() for k, p in _tile_files(root).items()}

    assert digests(tmp_path / "s") == digests(tmp_path / "d") and len(digests(tmp_path / "d")) > 8
    update = tms(_cog(tmp_path / "one.tif", tmp_path / "one_sparse.tif", True), "auto", tmp_path / "s", processes=2,
                 work_dir=work)
    fresh = tms(_cog(tmp_path / "one.tif", tmp_path / "one_dense.tif", False), "auto", tmp_path / "f", processes=2)
    assert not update["full"] and digests(tmp_path / "s") == digests(tmp_path / "f")
    assert 0 < update["web_tiles"] == fresh["web_tiles"] < sparse["web_tiles"]


def test_a_sparse_cut_makes_only_the_base_tiles_its_warped_blocks_reach(tmp_path, monkeypatch):
    """One 150 m district on a 1.8 km map stored sparse: the base tiles whose read windows meet no
    warped block (they would read zeros, and gdal2tiles writes no empty tile) are not made; every
    tile written is one that was made, and the pyramid is the dense map's byte for byte."""
    import hashlib

    from pipeline25d.core.crs import horizontal_wkt
    from pipeline25d.stages.tiles import web

    grid = Grid.from_gdal((691000.0, 0.5, 0.0, 5334000.0, 0.0, -0.5), 3600, 3600)
    rgba = np.zeros((3600, 3600, 4), np.uint8)
    rgba[1700:2000, 1500:1800, :3] = np.random.default_rng(3).integers(0, 255, (300, 300, 3), dtype=np.uint8)
    rgba[1700:2000, 1500:1800, 3] = 255
    write_rgba_geotiff(tmp_path / "map.tif", rgba, grid, horizontal_wkt("EPSG:25832"))
    real = web.create_base_tile
    made: dict[str, list] = {"sparse": [], "dense": []}
    for kind in made:
        monkeypatch.setattr(web, "create_base_tile", lambda conf, d, k=kind: (made[k].append((d.tz, d.tx, d.ty)),
                                                                             real(conf, d))[1])
        tms(_cog(tmp_path / "map.tif", tmp_path / f"{kind}.tif", kind == "sparse"), "auto", tmp_path / kind,
            processes=1, most=1, work_dir=tmp_path / f"work_{kind}")
    files = {k: _tile_files(tmp_path / k) for k in made}
    top = max(z for z, _, _ in made["dense"])
    on_disk = {tuple(int(v) for v in k.removesuffix(".png").split("/")) for k in files["sparse"]}
    written = {t for t in on_disk if t[0] == top}
    assert written and written <= set(made["sparse"])
    # the warped blocks' tiles (a block: BLOCK_TILES a side, its y counted up, the tiles' down), one more around
    warped = [tuple(int(v) for v in p.stem.split("_")) for p in (tmp_path / "work_sparse" / "blocks").glob("*.tif")]
    rows = 2 ** top - 1

    def near_a_warped_block(x: int, y: int) -> bool:
        return any(bx * BLOCK_TILES - 1 <= x <= (bx + 1) * BLOCK_TILES and
                   by * BLOCK_TILES - 1 <= rows - y <= (by + 1) * BLOCK_TILES for bx, by in warped)

    assert 0 < len(warped) < 16 and all(near_a_warped_block(x, y) for _, x, y in made["sparse"])
    assert not all(near_a_warped_block(x, y) for _, x, y in made["dense"])
    assert len(made["sparse"]) < len(made["dense"])
    digest = {k: {t: hashlib.sha256(p.read_bytes()).hexdigest() for t, p in f.items()} for k, f in files.items()}
    assert digest["sparse"] == digest["dense"]
