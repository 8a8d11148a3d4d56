"""gdal2tiles' base tile, byte for byte, without its slow upsampled read.

gdal2tiles (``create_base_tile``, resampling other than near) asks GDAL for a tile's source
window already upsampled, by nearest neighbour, to the 4x query size (1024 x 1024 px), then
averages that query down to the tile. On the VRT of web-mercator blocks that one upsampled
read cost 0.2 s a tile, 80x a plain read of the same window (measured: harness
``pipeline25d_lab.harness.pixel_cost``). Here the window is read at its own size (each
source pixel decoded once) and upsampled in numpy with the index rule of GDAL's own
nearest-neighbour RasterIO (:func:`nearest_index`). With gdal2tiles' ``average`` (the
pipeline's), the 4x query is never made: :func:`average_tile` sums each tile pixel's 4 x 4
query pixels straight from the window (columns, then rows) and rounds as GDAL's average
does, (sum + 8) // 16. The encode stays gdal2tiles' (the tile driver's CreateCopy), so the
tiles are the same bytes (tests/test_pixel_cost.py compares their sha256).
"""

from __future__ import annotations

import os
import threading

import numpy as np

from pipeline25d.core.raster import gdal

_local = threading.local()


def nearest_index(size: int, buf_size: int) -> np.ndarray:
    """The source offsets (0 .. size-1) that GDAL's nearest-neighbour RasterIO reads for each of
    ``buf_size`` buffer pixels of a ``size``-pixel window: floor((i + 0.5) * size / buf_size + 1e-10)."""
    i = (np.arange(buf_size, dtype=np.float64) + 0.5) * (size / buf_size) + 1e-10
    return np.minimum(np.floor(i).astype(np.int64), size - 1)


def read_window(ds, rx: int, ry: int, rxsize: int, rysize: int, bands: int) -> tuple[np.ndarray, np.ndarray]:
    """(data (bands, rysize, rxsize), alpha (rysize, rxsize)) uint8: a window's data bands and its
    mask band (the alpha of an RGBA raster), as gdal2tiles reads them, at their own size."""
    data = np.frombuffer(ds.ReadRaster(rx, ry, rxsize, rysize, band_list=list(range(1, bands + 1))),
                         np.uint8).reshape(bands, rysize, rxsize)
    alpha = np.frombuffer(ds.GetRasterBand(1).GetMaskBand().ReadRaster(rx, ry, rxsize, rysize),
                          np.uint8).reshape(rysize, rxsize)
    return data, alpha


def read_upsampled(ds, rx: int, ry: int, rxsize: int, rysize: int, wxsize: int, wysize: int,
                   bands: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`read_window` upsampled by nearest neighbour to wxsize x wysize, as
    ``ds.ReadRaster(rx, ry, rxsize, rysize, wxsize, wysize)`` reads it from one raster."""
    data, alpha = read_window(ds, rx, ry, rxsize, rysize, bands)
    rows, cols = nearest_index(rysize, wysize), nearest_index(rxsize, wxsize)
    if (rysize, rxsize) == (wysize, wxsize):
        return data, alpha
    return data[:, rows][:, :, cols], alpha[rows][:, cols]


def average_tile(data: np.ndarray, rows: np.ndarray, cols: np.ndarray, wx: int, wy: int, querysize: int,
                 tile_size: int) -> np.ndarray:
    """(bands, tile_size, tile_size) uint8: the average, by blocks of f x f (f = querysize /
    tile_size), of a zero ``querysize`` square query holding the window ``data`` (bands, h, w)
    upsampled by the source offsets ``rows`` and ``cols`` at (wx, wy); as GDAL's ``average``
    overview of that query (integer sums, rounded half up)."""
    f = querysize // tile_size
    bands, h, w = data.shape
    if _whole_repeat(rows, h, querysize, tile_size) and _whole_repeat(cols, w, querysize, tile_size) \
            and wx == wy == 0 and h == w:
        # each window pixel is r x r query pixels (offsets i // r), so a tile pixel's f x f query sum is
        # r**2 times the sum of its (f / r)**2 window pixels: no query-sized array is made
        r, b = querysize // w, w // tile_size
        total = box_sums(data, b) * np.uint16(r * r)
        return ((total + f * f // 2) // (f * f)).astype(np.uint8)
    x = np.zeros((bands, h, querysize), np.uint16)
    x[:, :, wx:wx + len(cols)] = data[:, :, cols]
    x = x.reshape(bands, data.shape[1], tile_size, f).sum(axis=3, dtype=np.uint16)      # <= 4 x 255 each
    y = np.zeros((bands, querysize, tile_size), np.uint16)
    y[:, wy:wy + len(rows)] = x[:, rows]
    total = y.reshape(bands, tile_size, f, tile_size).sum(axis=2, dtype=np.uint16)      # <= 16 x 255
    return ((total + f * f // 2) // (f * f)).astype(np.uint8)


def box_sums(data: np.ndarray, b: int) -> np.ndarray:
    """(bands, h/b, w/b) uint16: the sum of each ``b`` x ``b`` square of ``data`` (bands, h, w) uint8,
    by strided adds (columns, then rows: 7x a reshaped sum's speed); exact for b <= 16."""
    cols = data[:, :, 0::b].astype(np.uint16)
    for k in range(1, b):
        cols += data[:, :, k::b]
    out = cols[:, 0::b].copy()
    for k in range(1, b):
        out += cols[:, k::b]
    return out


def _whole_repeat(offsets: np.ndarray, size: int, querysize: int, tile_size: int) -> bool:
    """Whether ``offsets`` fill the whole query with each of ``size`` pixels repeated r times, in
    order (``nearest_index`` where r = querysize / size is whole), and a tile pixel spans whole pixels."""
    if len(offsets) != querysize or querysize % size or size % tile_size:
        return False
    return bool(np.array_equal(offsets, np.arange(querysize) // (querysize // size)))


def source_dataset(path: str):
    """The tiles' source dataset, opened once per worker process and thread (as gdal2tiles keeps it)."""
    key = (path, os.getpid())
    if getattr(_local, "key", None) != key:
        _local.ds, _local.key = gdal().Open(path), key
    return _local.ds


def close_source() -> None:
    """Forget this thread's source dataset (a cut's source VRT is deleted when the cut ends)."""
    _local.ds = _local.key = None


def gdal2tiles():
    """``osgeo_utils.gdal2tiles``, its tile encoder's options extended by the WEBP ``METHOD`` that a
    gdal2tiles options object carries as ``webp_method`` (gdal2tiles has no switch for it: its
    tiles use libwebp's default, 4). Without ``webp_method`` the options, and so the tiles, are
    gdal2tiles' own. A cut calls this before it forks its workers, which inherit the module so."""
    from osgeo_utils import gdal2tiles as g2t

    if not getattr(g2t._get_creation_options, "webp_method", False):
        plain = g2t._get_creation_options

        def creation_options(options) -> list[str]:
            opts = plain(options)
            method = getattr(options, "webp_method", None)
            if options.tiledriver == "WEBP" and not options.webp_lossless and method is not None:
                opts = [*opts, f"METHOD={int(method)}"]
            return opts

        creation_options.webp_method = True
        g2t._get_creation_options = creation_options
    return g2t


def create_base_tile(tile_job_info, tile_detail) -> None:
    """gdal2tiles' ``create_base_tile`` for a scaled query (resampling other than near and
    antialias): the window read once (:func:`read_window`), averaged by :func:`average_tile`
    (other resamplings: upsampled, then gdal2tiles' ``scale_query_to_tile``); other settings go
    to gdal2tiles' own."""
    g2t = gdal2tiles()
    options, d = tile_job_info.options, tile_detail
    if d.querysize == tile_job_info.tile_size or options.resampling == "antialias" or tile_job_info.kml:
        g2t.create_base_tile(tile_job_info, tile_detail)
        return
    g = gdal()
    bands, size = tile_job_info.nb_data_bands, tile_job_info.tile_size
    ds = source_dataset(tile_job_info.src_file)
    mem = g.GetDriverByName("MEM")
    tile = mem.Create("", size, size, bands + 1)
    if d.rxsize and d.rysize and d.wxsize and d.wysize:
        data, alpha = read_window(ds, d.rx, d.ry, d.rxsize, d.rysize, bands)
        rows, cols = nearest_index(d.rysize, d.wysize), nearest_index(d.rxsize, d.wxsize)
        # the pixels the query repeats, each once: gdal2tiles' test of its whole query, without making it
        if tile_job_info.exclude_transparent and not alpha[np.ix_(np.unique(rows), np.unique(cols))].any():
            return
        if options.resampling == "average" and d.querysize % size == 0:
            window = np.concatenate([data, alpha[None]])
            tile.WriteRaster(0, 0, size, size,
                             average_tile(window, rows, cols, d.wx, d.wy, d.querysize, size).tobytes())
        else:
            up = np.concatenate([data, alpha[None]])[:, rows][:, :, cols]
            query = mem.Create("", d.querysize, d.querysize, bands + 1)
            query.WriteRaster(d.wx, d.wy, d.wxsize, d.wysize, np.ascontiguousarray(up).tobytes())
            g2t.scale_query_to_tile(query, tile, options, tilefilename="")
    path = os.path.join(tile_job_info.output_file_path, str(d.tz), str(d.tx), f"{d.ty}.{tile_job_info.tile_extension}")
    g.GetDriverByName(tile_job_info.tile_driver).CreateCopy(path, tile, strict=0,
                                                            options=g2t._get_creation_options(options))
