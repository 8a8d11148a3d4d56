"""gdal2tiles' base tile, byte for byte, without its slow upsampled read.

gdal2tiles (``create_base_tile``, resampling other than near) asks GDAL for a tile's source
window already upsampled, by nearest neighbour, to the 4x query size (1024 x 1024 px), then
averages that query down to the tile. On the VRT of web-mercator blocks that one upsampled
read cost 0.2 s a tile, 80x a plain read of the same window (measured: harness
``pipeline25d_lab.harness.pixel_cost``). Here the window is read at its own size (each
source pixel decoded once) and upsampled in numpy with the index rule of GDAL's own
nearest-neighbour RasterIO (:func:`nearest_index`); averaging and encoding stay gdal2tiles'
(``scale_query_to_tile``, the tile driver's CreateCopy), so the tiles are the same bytes.
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


def read_upsampled(ds, rx: int, ry: int, rxsize: int, rysize: int, wxsize: int, wysize: int,
                   bands: int) -> tuple[np.ndarray, np.ndarray]:
    """(data (bands, wysize, wxsize), alpha (wysize, wxsize)) uint8: the window's data bands and
    its mask band (the alpha of an RGBA raster), read once at their own size and upsampled by
    nearest neighbour as ``ds.ReadRaster(rx, ry, rxsize, rysize, wxsize, wysize)`` would."""
    data = np.frombuffer(ds.ReadRaster(rx, ry, rxsize, rysize, band_list=list(range(1, bands + 1))),
                         np.uint8).reshape(bands, rysize, rxsize)
    alpha = np.frombuffer(ds.GetRasterBand(1).GetMaskBand().ReadRaster(rx, ry, rxsize, rysize),
                          np.uint8).reshape(rysize, rxsize)
    rows, cols = nearest_index(rysize, wysize), nearest_index(rxsize, wxsize)
    if (rysize, rxsize) == (wysize, wxsize):
        return data, alpha
    return data[:, rows][:, :, cols], alpha[rows][:, cols]


def _source(path: str):
    """The tiles' source dataset, opened once per worker process and thread (as gdal2tiles keeps it)."""
    key = (path, os.getpid())
    if getattr(_local, "key", None) != key:
        _local.ds, _local.key = gdal().Open(path), key
    return _local.ds


def close_source() -> None:
    """Forget this thread's source dataset (a cut's source VRT is deleted when the cut ends)."""
    _local.ds = _local.key = None


def create_base_tile(tile_job_info, tile_detail) -> None:
    """gdal2tiles' ``create_base_tile`` for a scaled query (resampling other than near and
    antialias), with :func:`read_upsampled` for its read; other settings go to gdal2tiles' own."""
    from osgeo_utils import gdal2tiles as g2t

    options, d = tile_job_info.options, tile_detail
    if d.querysize == tile_job_info.tile_size or options.resampling == "antialias" or tile_job_info.kml:
        g2t.create_base_tile(tile_job_info, tile_detail)
        return
    g = gdal()
    bands, size = tile_job_info.nb_data_bands, tile_job_info.tile_size
    ds = _source(tile_job_info.src_file)
    mem = g.GetDriverByName("MEM")
    tile = mem.Create("", size, size, bands + 1)
    if d.rxsize and d.rysize and d.wxsize and d.wysize:
        data, alpha = read_upsampled(ds, d.rx, d.ry, d.rxsize, d.rysize, d.wxsize, d.wysize, bands)
        if tile_job_info.exclude_transparent and not alpha.any():
            return
        query = mem.Create("", d.querysize, d.querysize, bands + 1)
        query.WriteRaster(d.wx, d.wy, d.wxsize, d.wysize, np.ascontiguousarray(data).tobytes(),
                          band_list=list(range(1, bands + 1)))
        query.WriteRaster(d.wx, d.wy, d.wxsize, d.wysize, np.ascontiguousarray(alpha).tobytes(),
                          band_list=[bands + 1])
        g2t.scale_query_to_tile(query, tile, options, tilefilename="")
    path = os.path.join(tile_job_info.output_file_path, str(d.tz), str(d.tx), f"{d.ty}.{tile_job_info.tile_extension}")
    g.GetDriverByName(tile_job_info.tile_driver).CreateCopy(path, tile, strict=0,
                                                            options=g2t._get_creation_options(options))
