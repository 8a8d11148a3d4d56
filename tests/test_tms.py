"""The web-tile cut: the pipeline's (reprojected once, then gdal2tiles) against gdal2tiles
with its defaults on the same map."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
from PIL import Image

from pipeline25d.raster import write_rgba_geotiff
from pipeline25d.stages import tms


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
    tms(cog, "auto", ours)
    subprocess.run([sys.executable, "-m", "osgeo_utils.gdal2tiles", "-q", "--xyz", "-w", "none", "-r", "average",
                    str(cog), str(ref)], check=True)
    ref_tiles = sorted(p.relative_to(ref) for p in ref.rglob("*.png"))
    assert ref_tiles and sorted(p.relative_to(ours) for p in ours.rglob("*.png")) == ref_tiles
    diffs = [np.abs(np.asarray(Image.open(ours / t).convert("RGBA"), float)
                    - np.asarray(Image.open(ref / t).convert("RGBA"), float)).mean() for t in ref_tiles]
    assert np.mean(diffs) < 0.05 and max(diffs) < 1.0, (np.mean(diffs), max(diffs))
    assert not list(tmp_path.glob("*.3857.tif")) and not list(tmp_path.glob(".ours*"))   # nothing left over
