"""The WMS id layers: GetFeatureInfo on a map answers the object at the pixel, through MapServer.

MapServer's raster query prints a pixel's value with 8 significant digits, too few for a 32-bit
object id, so each map's id raster is served as a raster of row numbers of the objects table
(:func:`row_raster`, exact below 10^8), joined one to one to the table's CSV (MapServer's CSV
join, :func:`write_join_table`) and shown by an HTML template.
"""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Sequence

import numpy as np

from pipeline25d.core.atomic import write_bytes, write_text
from pipeline25d.core.errors import InputFileError, MapServiceError
from pipeline25d.core.geotiff import geotiff_dataset
from pipeline25d.core.grid import Grid, Window
from pipeline25d.core.raster import gdal, run_starts, stores_nothing
from pipeline25d.publish.objects import COLUMNS as JOIN_COLUMNS

# the objects table as MapServer joins it, and the GetFeatureInfo answer's template, beside the mapfile
JOIN_TABLE, TEMPLATE = "objects.csv", "objects.html"


def write_join_table(objects_csv: Path, folder: Path) -> None:
    """The objects table as MapServer's CSV join reads it (:data:`JOIN_TABLE`, UTF-8: columns by number
    from 1, split at every comma, one line a row, quotes not understood: :func:`join_field`) and the
    GetFeatureInfo template (text/html) that shows a pixel's row of it. MapServer escapes the
    values it puts into the HTML answer itself, so quotes, markup and non-ASCII text arrive as they are."""
    with open(objects_csv, newline="", encoding="utf-8") as fh:
        rows = list(csv.reader(fh))
    if rows and rows[0] != ["row", *JOIN_COLUMNS]:
        raise InputFileError(objects_csv, f"columns {rows[0]} are not row, {', '.join(JOIN_COLUMNS)}")
    write_bytes(folder / JOIN_TABLE, "".join(",".join(join_field(f) for f in r) + "\n" for r in rows).encode("utf-8"))
    cells = "".join(f"<td>[objects_{k}]</td>" for k in range(2, len(JOIN_COLUMNS) + 2))
    write_text(folder / TEMPLATE, "<!-- MapServer Template -->\n"
               f"<table><tr>{''.join(f'<th>{c}</th>' for c in JOIN_COLUMNS)}</tr><tr>{cells}</tr></table>\n")


def join_field(text: str) -> str:
    """A field of the join table: a comma written as a semicolon (MapServer's CSV join splits at every
    comma, quoted or not; an HTML character reference would be escaped again), a line break as a space."""
    return text.replace(",", ";").replace("\r\n", " ").replace("\r", " ").replace("\n", " ")


def table_ids(objects_csv: Path) -> list[int]:
    """The ids of the objects table's CSV, in its row order."""
    with open(objects_csv, newline="", encoding="utf-8") as fh:
        return [int(row["id"]) for row in csv.DictReader(fh)]


def id_path(map_path: Path) -> Path:
    """A map's object-id raster: ``<pid>.ids.tif`` beside ``<pid>.tif``."""
    return map_path.with_name(f"{map_path.stem}.ids.tif")


def row_raster(ids_tif: Path, ids: Sequence[int], out: Path, block_px: int = 1024) -> None:
    """An id raster with each id replaced by its row in the objects table (1-based; 0 stays 0, no
    data), written in squares of ``block_px``: MapServer prints a raster query's value with 8
    significant digits, too few for a 32-bit id (1384755801 prints as 1.3847558e+09), exact for a
    row number below 10^8. A square the id raster does not store (a sparse map's empty land: GDAL's
    data coverage) is neither read nor written; the file is sparse as the id raster is. An id
    that is not in the table is refused (:class:`InputFileError`)."""
    table = np.asarray(ids, dtype=np.uint32)
    if len(table) and (np.diff(table.astype(np.int64)) <= 0).any():
        raise MapServiceError(f"{ids_tif}: the objects table is not in increasing id order")
    ds = gdal().Open(str(ids_tif))
    grid = Grid.of_dataset(ds)
    band = ds.GetRasterBand(1)
    options = ("COMPRESS=ZSTD", "TILED=YES", "SPARSE_OK=TRUE")
    with geotiff_dataset(out, grid, ds.GetProjection(), 1, "UInt32", options, nodata=0) as dst:
        for r0 in range(0, grid.height, block_px):
            for c0 in range(0, grid.width, block_px):
                win = Window(c0, r0, min(c0 + block_px, grid.width), min(r0 + block_px, grid.height))
                if not stores_nothing(band, win):
                    block = band.ReadAsArray(c0, r0, win.width, win.height)
                    dst.band(1).WriteArray(_table_rows(block, table, ids_tif), c0, r0)


def _table_rows(block: np.ndarray, table: np.ndarray, ids_tif: Path) -> np.ndarray:
    """(h, w) uint32: each id's 1-based row in the increasing ``table`` (0 stays 0). Ids come in runs
    along a row, so each run is looked up once (two 135 Mpx maps: 12.6 -> 6.8 s, the rest is I/O)."""
    flat = block.ravel().astype(np.uint32)
    starts = run_starts(flat)
    values = flat[starts]
    pos = np.searchsorted(table, values)
    found = (values == 0) | ((pos < len(table)) & (table[np.minimum(pos, len(table) - 1)] == values))
    if not found.all():
        raise InputFileError(ids_tif, f"id {int(values[~found][0])} is not in the objects table")
    rows = np.where(values == 0, 0, pos + 1).astype(np.uint32)
    return np.repeat(rows, np.diff(np.append(starts, flat.size))).reshape(block.shape)


def id_layer(pid: str, extent: str, epsg: str) -> list[str]:
    """The mapfile lines of a map's id layer ``<pid>_ids``, queryable by GetFeatureInfo: the pixel's
    row in the objects table (``value_0`` of MapServer's raster query, from :func:`row_raster`'s
    ``<pid>.rows.tif`` beside the mapfile) joined one to one to that row of the objects table's CSV (MapServer's CSV
    join; :mod:`pipeline25d.publish.objects`), whose columns give the id, name and attributes."""
    return [
        "  LAYER",
        f'    NAME "{pid}_ids"',
        "    TYPE RASTER",
        "    STATUS ON",
        f'    DATA "{pid}.rows.tif"',
        f"    EXTENT {extent}",
        f'    PROJECTION "init=epsg:{epsg}" END',
        '    PROCESSING "RESAMPLE=NEAREST"',
        "    CLASS",                                       # a transparent pixel (0) answers nothing
        "      EXPRESSION ([pixel] > 0)",
        "    END",
        f'    TEMPLATE "{TEMPLATE}"',
        "    TOLERANCE 0",
        "    METADATA",
        f'      "wms_title" "{pid}: object ids (GetFeatureInfo)"',
        '      "wms_include_items" "value_0"',
        '      "gml_include_items" "value_0"',
        "    END",
        "    JOIN",
        '      NAME "objects"',
        f'      TABLE "{JOIN_TABLE}"',
        '      FROM "value_0"',
        '      TO "1"',
        "      TYPE ONE-TO-ONE",
        "      CONNECTIONTYPE CSV",
        "    END",
        "  END",
    ]
