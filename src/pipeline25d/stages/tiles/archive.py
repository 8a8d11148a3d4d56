"""A web-tile pyramid as one PMTiles (v3) archive: every tile of an XYZ folder in one file.

One file per perspective is easier to copy and serve than thousands of small ones; a browser
reads its tiles by HTTP range requests (the viewer's PMTiles layer, npm ``pmtiles``). Written
with the ``pmtiles`` package's writer: tiles in tile-id (Hilbert) order, so the archive is
clustered; tile bytes as they are (PNG and WEBP are compressed already); identical tiles
(often the fully transparent ones) stored once.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

from pipeline25d.core.atomic import atomic_path
from pipeline25d.core.errors import InputFileError

log = logging.getLogger(__name__)

EXTENSIONS = (".png", ".webp")


def pyramid_tiles(tms_dir: str | Path) -> dict[tuple[int, int, int], Path]:
    """The tiles of an XYZ pyramid folder (``z/x/y.png`` or ``.webp``) as {(z, x, y): path}."""
    tms_dir = Path(tms_dir)
    tiles = {}
    for path in tms_dir.glob("*/*/*"):
        z, x = path.parent.parent.name, path.parent.name
        if path.suffix in EXTENSIONS and z.isdigit() and x.isdigit() and path.stem.isdigit():
            tiles[int(z), int(x), int(path.stem)] = path
    return tiles


def tile_lonlat(z: int, x: int, y: int) -> tuple[float, float]:
    """Longitude and latitude (degrees) of an XYZ tile's north-west corner."""
    n = 2.0 ** z
    return x / n * 360.0 - 180.0, math.degrees(math.atan(math.sinh(math.pi * (1 - 2 * y / n))))


def _e7(degrees: float) -> int:
    """Degrees as the header's integers of 1e-7 degrees."""
    return int(round(degrees * 1e7))


def write_pmtiles(tms_dir: str | Path, out: str | Path, name: str | None = None) -> dict:
    """Write every tile of the XYZ pyramid ``tms_dir`` into the PMTiles archive ``out``, atomically.

    The header's bounds are those of the tiles of the highest zoom, its centre their middle.
    Returns the figures: tiles, distinct tile contents, zoom range and the archive's size.
    """
    from pmtiles.tile import Compression, TileType, zxy_to_tileid
    from pmtiles.writer import Writer

    tiles = pyramid_tiles(tms_dir)
    if not tiles:
        raise InputFileError(tms_dir, "no web tiles (z/x/y.png or .webp) to put in a PMTiles archive")
    suffixes = {p.suffix for p in tiles.values()}
    if len(suffixes) > 1:
        raise InputFileError(tms_dir, f"mixes tile formats {sorted(suffixes)}: a PMTiles archive holds one")
    suffix = suffixes.pop()
    zooms = sorted({z for z, _, _ in tiles})
    top = [(x, y) for z, x, y in tiles if z == zooms[-1]]
    west, north = tile_lonlat(zooms[-1], min(x for x, _ in top), min(y for _, y in top))
    east, south = tile_lonlat(zooms[-1], max(x for x, _ in top) + 1, max(y for _, y in top) + 1)
    header = {"tile_compression": Compression.NONE, "tile_type": TileType[suffix[1:].upper()],
              "min_lon_e7": _e7(west), "min_lat_e7": _e7(south), "max_lon_e7": _e7(east), "max_lat_e7": _e7(north),
              "center_zoom": zooms[-1], "center_lon_e7": _e7((west + east) / 2),
              "center_lat_e7": _e7((south + north) / 2)}
    metadata = {"name": name or Path(tms_dir).name, "format": suffix[1:], "type": "overlay",
                "attribution": "pipeline25d", "bounds": f"{west},{south},{east},{north}"}
    order = sorted(tiles, key=lambda t: zxy_to_tileid(*t))
    with atomic_path(out) as tmp:
        with open(tmp, "wb") as f:
            writer = Writer(f)
            for zxy in order:
                writer.write_tile(zxy_to_tileid(*zxy), tiles[zxy].read_bytes())
            writer.finalize(header, metadata)
        contents = len(writer.hash_to_offset)
    size = Path(out).stat().st_size
    log.info("%s: %d tiles (%d distinct) at zoom %d-%d, %d bytes", out, len(tiles), contents, zooms[0], zooms[-1], size)
    return {"tiles": len(tiles), "contents": contents, "zoom": [zooms[0], zooms[-1]], "bytes": size}
