"""The id web tiles: which object every pixel of a map's web tile shows, lossless.

An id tile is the map tile's twin (same XYZ position, same 256 x 256 pixels, written only
where the map tile is, as the pyramid of :mod:`pipeline25d.stages.tiles.web` cuts both): the
uint32 object ids (:mod:`pipeline25d.stages.objects`; 0 where the map is transparent) as a
palette and indices, compressed by zlib (the browser's ``DecompressionStream("deflate")`` decodes
them): ``n`` (uint32), the tile's ``n`` distinct ids (uint32, increasing), then each pixel's index
into them, row by row from the top (uint8 when ``n`` <= 256, else uint16), all little-endian. A
tile shows a few objects, so the palette makes it 37 % smaller than zlib of the raw ids (the small
demo's 27 id tiles: 20.7 kB against 33.0 kB) and the inflated tile 4x smaller. Base tiles take
each pixel's id by nearest neighbour from the web-mercator blocks, which for ids lie on the base
tiles' own pixels (:func:`pipeline25d.stages.tiles.web.tile_grid`): the map's id at each tile
pixel's centre; each tile above takes, for each of its pixels, the most frequent id of the 2 x 2
child pixels under it (ties: the bottom-right one, which GDAL's nearest neighbour would take),
never an average, which would name an object nobody drew.
"""

from __future__ import annotations

import os
import zlib
from pathlib import Path

import numpy as np

from pipeline25d.core.atomic import write_bytes
from pipeline25d.core.raster import run_starts
from pipeline25d.stages.tiles.base import nearest_index, source_dataset

TILE = 256
EXT = "bin"                  # {z}/{x}/{y}.bin: zlib(n, palette, indices), see the module docstring


def encode(ids: np.ndarray) -> bytes:
    """A (256, 256) id tile as stored: zlib of its palette and each pixel's index into it."""
    flat = ids.ravel()
    runs = flat[run_starts(flat)]                      # few: ids come in runs
    palette = np.unique(runs)
    index = np.searchsorted(palette, flat)
    kind = "u1" if len(palette) <= 256 else "<u2"
    raw = (np.uint32(len(palette)).astype("<u4").tobytes() + palette.astype("<u4").tobytes()
           + index.astype(kind).tobytes())
    return zlib.compress(raw, 9)


def decode(data: bytes) -> np.ndarray:
    """The (256, 256) uint32 ids of a stored id tile."""
    raw = zlib.decompress(data)
    n = int(np.frombuffer(raw, "<u4", 1)[0])
    palette = np.frombuffer(raw, "<u4", n, 4)
    index = np.frombuffer(raw, "u1" if n <= 256 else "<u2", TILE * TILE, 4 + 4 * n)
    return palette[index].astype(np.uint32).reshape(TILE, TILE)


def tile_path(tiles: Path, z: int, x: int, y: int) -> Path:
    return tiles / str(z) / str(x) / f"{y}.{EXT}"


def _store(path: Path, ids: np.ndarray) -> bool:
    """Write the tile when it holds an id (else remove it, as the map's empty tiles are not cut)."""
    if not ids.any():
        path.unlink(missing_ok=True)
        return False
    path.parent.mkdir(parents=True, exist_ok=True)
    write_bytes(path, encode(ids))
    return True


def base_tile(src_file: str, tiles: str, d) -> None:
    """One base id tile of gdal2tiles' tile detail ``d`` (a ``near`` query: querysize 256) read
    from the blocks' VRT ``src_file``: the window's ids at the nearest source pixel."""
    ids = np.zeros((TILE, TILE), np.uint32)
    if d.rxsize and d.rysize and d.wxsize and d.wysize:
        band = source_dataset(src_file).GetRasterBand(1)
        window = band.ReadAsArray(d.rx, d.ry, d.rxsize, d.rysize).astype(np.uint32)
        rows, cols = nearest_index(d.rysize, d.wysize), nearest_index(d.rxsize, d.wxsize)
        ids[d.wy:d.wy + d.wysize, d.wx:d.wx + d.wxsize] = window[rows][:, cols]
    _store(tile_path(Path(tiles), d.tz, d.tx, d.ty), ids)


def mode2x2(ids: np.ndarray) -> np.ndarray:
    """(h/2, w/2): the most frequent of each 2 x 2 block's values; ties go to its bottom-right
    value (GDAL's nearest neighbour at half size), then top-left, top-right, bottom-left."""
    cands = [ids[1::2, 1::2], ids[0::2, 0::2], ids[0::2, 1::2], ids[1::2, 0::2]]
    counts = [sum((c == o).astype(np.int8) for o in cands) for c in cands]
    out, best = cands[0].copy(), counts[0]
    for c, n in zip(cands[1:], counts[1:]):
        better = n > best
        out[better], best = c[better], np.maximum(best, n)
    return out


def overview_tile(tiles: str, job: tuple[int, int, int]) -> None:
    """The id tile (z, x, y) from its four children at z + 1 (absent ones hold no id)."""
    z, x, y = job
    quad = np.zeros((2 * TILE, 2 * TILE), np.uint32)
    for dy in (0, 1):
        for dx in (0, 1):
            child = tile_path(Path(tiles), z + 1, 2 * x + dx, 2 * y + dy)
            if child.is_file():
                quad[dy * TILE:(dy + 1) * TILE, dx * TILE:(dx + 1) * TILE] = decode(child.read_bytes())
    _store(tile_path(Path(tiles), z, x, y), mode2x2(quad))


def pyramid_bytes(tiles: str | Path) -> int:
    """Bytes of every file under a tile folder."""
    return sum(os.path.getsize(p) for p in Path(tiles).rglob("*") if p.is_file())
