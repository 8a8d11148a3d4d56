"""The web-tile cut: the pipeline's (reprojected once, then gdal2tiles) against gdal2tiles
with its defaults on the same map."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
from PIL import Image

from pipeline25d.raster import write_rgba_geotiff
from pipeline25d.web_tiles import tms


def test_tiles_match_a_default_gdal2tiles_cut(tmp_path):
    rng = np.random.default_rng(0)
    h, w = 900, 1300
    rgba = np.zeros((h, w, 4), np.uint8)
    yy, xx = np.mgrid[0:h, 0:w]
    rgba[..., 0] = (128 + 100 * np.sin(xx / 7.0) * np.cos(yy / 11.0)).astype(np.uint8)
    rgba[..., 1] = rng.integers(0, 255, (h, w), dtype=np.uint8)            # pixel noise: the hardest case
    rgba[..., 2] = (xx * 255 // w).astype(np.uint8)
    rgba[..., 3] = 255
    rgba[:200, :300] = 0        # a transparent corner, RGB 0 under it as the renderer writes it (gdalwarp
    #                             zeroes colour under alpha 0 anyway; gdal2tiles' own warp would average it into edges)
    cog = tmp_path / "map.tif"
    from pipeline25d.crs import horizontal_wkt

    write_rgba_geotiff(cog, rgba, (691000.0, 0.5, 0.0, 5334000.0, 0.0, -0.5), horizontal_wkt("EPSG:25832"))
    ours, ref = tmp_path / "ours", tmp_path / "ref"
    tms(cog, "auto", ours, tile_format="png")
    subprocess.run([sys.executable, "-m", "osgeo_utils.gdal2tiles", "-q", "--xyz", "-w", "none", "-r", "average",
                    str(cog), str(ref)], check=True)
    ref_tiles = sorted(p.relative_to(ref) for p in ref.rglob("*.png"))
    assert ref_tiles and sorted(p.relative_to(ours) for p in ours.rglob("*.png")) == ref_tiles
    diffs = [np.abs(np.asarray(Image.open(ours / t).convert("RGBA"), float)
                    - np.asarray(Image.open(ref / t).convert("RGBA"), float)).mean() for t in ref_tiles]
    assert np.mean(diffs) < 0.05 and max(diffs) < 1.0, (np.mean(diffs), max(diffs))
    assert not list(tmp_path.glob("*.3857.tif")) and not list(tmp_path.glob(".ours*"))   # nothing left over


def _smooth_map(path):
    from pipeline25d.crs import horizontal_wkt

    h, w = 600, 800
    yy, xx = np.mgrid[0:h, 0:w]
    rgba = np.zeros((h, w, 4), np.uint8)
    rgba[..., 0] = (128 + 100 * np.sin(xx / 23.0)).astype(np.uint8)
    rgba[..., 1] = (128 + 100 * np.cos(yy / 31.0)).astype(np.uint8)
    rgba[..., 2] = 90
    rgba[..., 3] = 255
    rgba[:150, :200] = 0
    write_rgba_geotiff(path, rgba, (691000.0, 0.5, 0.0, 5334000.0, 0.0, -0.5), horizontal_wkt("EPSG:25832"))


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


def test_jpeg_maps_keep_their_transparency_as_a_mask_that_the_readers_use(tmp_path):
    from osgeo import gdal

    from pipeline25d.evaluate import _read_window
    from pipeline25d.warp import warp_to_cog

    _smooth_map(tmp_path / "map.tif")
    plan = {"crs": "EPSG:25832", "gsd": 0.5}
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

    script = (f"import time; from pipeline25d.atomic import atomic_path; from pipeline25d.logsetup import log_to\n"
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
