"""The mosaic VRT of a perspective's tiles, its sources plain copies where the tiles do not overlap.

gdalbuildvrt gives each tile a ``ComplexSource`` that composites it through its mask (an RGBA
tile's alpha, an id tile's nodata 0): a pixel the mask leaves out is not copied. Reading that
VRT cost 3.5x reading the same pixels through ``SimpleSource`` copies (4.0 against 1.2 CPU-s
for a 135 Mpx Delft map, 2.9 against 0.7 for its ids), and the warp job reads its mosaic three
to four times. The render tiles of one perspective lie on one grid and never overlap, and a
pixel left out is one that copying leaves as it is: transparent RGBA tiles have no colour
under alpha 0 (:func:`pipeline25d.core.geotiff.write_rgba_geotiff`), and an id tile's nodata is
the VRT's own 0. So where no two sources of a band overlap, a plain copy reads the same pixels;
where some do (tiles from elsewhere), the VRT is left as gdalbuildvrt wrote it.
"""

from __future__ import annotations

import logging
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from pipeline25d.core.atomic import atomic_path
from pipeline25d.core.errors import GdalToolError
from pipeline25d.core.raster import gdal

log = logging.getLogger(__name__)

#: what only a compositing source has: its mask use and its nodata
COMPOSITING = ("UseMaskBand", "NODATA")


def build_mosaic(tiles: list[str], out_vrt: str | Path) -> None:
    """gdalbuildvrt over the tile GeoTIFFs (they share one pixel grid), its sources made plain
    copies where no two overlap (:func:`plain_sources`). GDAL's own BuildVRT, the tool's code, in
    this process: the same VRT in 0.02 s, where the tool took 0.1 s to start."""
    log.info("gdalbuildvrt %s (%d tiles)", out_vrt, len(tiles))
    with atomic_path(out_vrt) as tmp:
        try:
            ds = gdal().BuildVRT(str(tmp), [str(t) for t in tiles])
            del ds                       # written as it closes
        except RuntimeError as exc:
            raise GdalToolError(f"gdalbuildvrt failed: {exc}") from None
        plain_sources(Path(tmp))


def plain_sources(vrt: Path) -> bool:
    """Rewrite ``vrt``'s ComplexSources as SimpleSources when no two of a band's overlap and none
    scales or offsets values; True if it did."""
    tree = ET.parse(vrt)
    bands = tree.getroot().findall("VRTRasterBand")
    for band in bands:
        sources = band.findall("ComplexSource")
        if band.findall("SimpleSource") or any(_transforms(s) for s in sources) or _overlap(sources):
            return False
    for band in bands:
        for source in band.findall("ComplexSource"):
            source.tag = "SimpleSource"
            for name in COMPOSITING:
                for child in source.findall(name):
                    source.remove(child)
    tree.write(vrt, encoding="unicode")
    return True


def source_windows(mosaic: str | Path, grid: list) -> list[tuple[int, int, int, int]]:
    """The pixel windows (col0, row0, col1, row1) of the tiles a mosaic VRT's first band reads:
    where its pixels can hold anything; a mosaic that is no VRT of sources (a raster file), or
    one whose sources say no place, is its whole ``grid`` (of :func:`~pipeline25d.core.raster.map_cells`)."""
    whole = [(0, 0, int(grid[6]), int(grid[7]))]
    try:
        root = ET.parse(mosaic).getroot()
    except (ET.ParseError, UnicodeDecodeError, OSError):
        return whole
    band = root.find("VRTRasterBand") if root.tag == "VRTDataset" else None
    sources = [] if band is None else [c for c in band if c.tag.endswith("Source")]
    if band is None or any(s.find("DstRect") is None for s in sources):     # no DstRect: the whole raster
        return whole
    return [(int(np.floor(x)), int(np.floor(y)), int(np.ceil(x + w)), int(np.ceil(y + h)))
            for x, y, w, h in _dst_rects(sources)]


def _dst_rects(sources: list[ET.Element]) -> np.ndarray:
    """(n, 4) xOff, yOff, xSize, ySize of the sources' destination rectangles."""
    return np.array([[float(s.find("DstRect").get(k)) for k in ("xOff", "yOff", "xSize", "ySize")] for s in sources],
                    dtype=np.float64).reshape(-1, 4)


def _transforms(source: ET.Element) -> bool:
    """A source that does more than copy through its mask (scale, offset, lookup table, ...)."""
    return any(child.tag not in ("SourceFilename", "SourceBand", "SourceProperties", "SrcRect", "DstRect",
                                 *COMPOSITING) for child in source)


def _overlap(sources: list[ET.Element]) -> bool:
    """Whether any two sources' destination rectangles share a pixel."""
    if len(sources) < 2:
        return False
    r = _dst_rects(sources)
    x0, y0, x1, y1 = r[:, 0], r[:, 1], r[:, 0] + r[:, 2], r[:, 1] + r[:, 3]
    for i in range(0, len(r), 1024):         # 1024 rows of the pairs at a time: memory O(n), not O(n^2)
        a = slice(i, i + 1024)
        hit = (x0[a, None] < x1[None]) & (x0[None] < x1[a, None]) & (y0[a, None] < y1[None]) & (y0[None] < y1[a, None])
        hit[np.arange(hit.shape[0]), np.arange(i, i + hit.shape[0])] = False
        if hit.any():
            return True
    return False
