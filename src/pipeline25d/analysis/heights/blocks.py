"""Footprints in blocks for the heights stage's parallel jobs: which block a footprint belongs to,
the footprints a block needs around it, the records a block job writes, and a digest of every map
pixel a block's measurement reads (a block whose pixels did not change keeps its rows).

A block is the cell of a ``block_m`` grid over the scene (origin 0, 0) that holds the centre of a
footprint's bounding box, named ``<col>_<row>`` (cell indices, negative west/south of the origin);
a grid fixed in the world keeps every other block's footprints where an edit adds or moves one.
"""

from __future__ import annotations

import hashlib
import math
from pathlib import Path
from typing import Any

import numpy as np

from pipeline25d.analysis.heights.results import NADIR_ID, HeightRow, MatchSettings, ViewMeasurement
from pipeline25d.formats.footprints import Footprint

#: footprints this close (m, bounding boxes) to a block's are its context: the silhouette's neighbours
#: (views._neighbours looks 4 m around each footprint)
CONTEXT_M = 8.0


def block_of(fp: Footprint, block_m: float) -> str:
    """The block of ``fp``: ``<col>_<row>`` of the ``block_m`` grid cell holding its bounding box's centre."""
    b = fp.bounds
    return f"{math.floor((b[0] + b[2]) / 2 / block_m)}_{math.floor((b[1] + b[3]) / 2 / block_m)}"


def blocks_of(fps: list[Footprint], block_m: float) -> dict[str, list[int]]:
    """{block: indices into ``fps``, in input order}, blocks sorted by name."""
    out: dict[str, list[int]] = {}
    for i, fp in enumerate(fps):
        out.setdefault(block_of(fp, block_m), []).append(i)
    return dict(sorted(out.items()))


#: a heights job measures at most this many footprints where it groups sparse blocks (a job's
#: start costs about one second: Python, scipy, the DTM; a footprint a third of one, nine views)
JOB_FOOTPRINTS = 24


def jobs_of(blocks: dict[str, list[int]], most: int = JOB_FOOTPRINTS) -> dict[str, list[str]]:
    """{job: its blocks}: sparse blocks grouped into one job by a quadtree over the block grid.

    Four sibling cells (``2**L`` blocks a side, aligned with the world's grid) become one job while
    they hold at most ``most`` footprints together and none of them is already a job of its own; a
    block with more stays a job alone. A job of one block is named as the block; a job of a level
    ``L`` cell ``L<L>_<col>_<row>``. The grid being fixed in the world, an edit changes only the
    jobs around it, and each block's rows are kept alone (:func:`block_of`'s name)."""
    cells = {tuple(int(v) for v in b.split("_")): ([b], len(idx)) for b, idx in blocks.items()}
    done: dict[str, list[str]] = {}
    level = 0
    while len(cells) > 1 and level < 64:      # cells either side of 0 never share a parent
        parents: dict[tuple[int, int], list[tuple[int, int]]] = {}
        for c in cells:
            parents.setdefault((c[0] >> 1, c[1] >> 1), []).append(c)
        merged = {}
        for parent, kids in parents.items():
            n = sum(cells[k][1] for k in kids)
            if n <= most:
                merged[parent] = ([b for k in sorted(kids) for b in cells[k][0]], n)
            else:
                done.update((_job_name(level, k, cells[k][0]), cells[k][0]) for k in kids)
        cells, level = merged, level + 1
    done.update((_job_name(level, k, v[0]), v[0]) for k, v in cells.items())
    return dict(sorted(done.items(), key=lambda kv: kv[1][0]))


def _job_name(level: int, cell: tuple[int, int], members: list[str]) -> str:
    return members[0] if len(members) == 1 else f"L{level}_{cell[0]}_{cell[1]}"


def context_of(members: list[Footprint], fps: list[Footprint], margin: float = CONTEXT_M) -> list[Footprint]:
    """The footprints of ``fps`` (in their order) whose bounding boxes come within ``margin`` m of
    any member's: every neighbour the members' silhouettes can meet."""
    if not members:
        return []
    mb = np.array([f.bounds for f in members], dtype=np.float64)
    out = []
    for f in fps:
        b = f.bounds
        if np.any((mb[:, 0] <= b[2] + margin) & (mb[:, 2] >= b[0] - margin)
                  & (mb[:, 1] <= b[3] + margin) & (mb[:, 3] >= b[1] - margin)):
            out.append(f)
    return out


# --------------------------------------------------------------------------- records

def footprint_to_json(fp: Footprint) -> dict[str, Any]:
    return {"id": fp.id, "rings": [r.tolist() for r in fp.rings]}


def footprint_from_json(d: dict[str, Any]) -> Footprint:
    return Footprint(str(d["id"]), tuple(np.asarray(r, dtype=np.float64).reshape(-1, 2) for r in d["rings"]))


def row_to_json(r: HeightRow) -> dict[str, Any]:
    """A building's row as JSON (floats exact: NaN as NaN, read back by :func:`row_from_json`)."""
    return {"id": r.id, "heights": r.heights, "qualities": r.qualities, "reasons": r.reasons,
            "n_views": r.n_views, "n_agree": r.n_agree, "height": r.height, "quality": r.quality,
            "views": {k: dict(v.__dict__) for k, v in r.views.items()},
            "ridge": r.ridge, "roof": r.roof, "ridges": r.ridges}


def row_from_json(d: dict[str, Any]) -> HeightRow:
    return HeightRow(d["id"], d["heights"], d["qualities"], d["reasons"], d["n_views"], d["n_agree"], d["height"],
                     d["quality"], {k: ViewMeasurement(**v) for k, v in d["views"].items()}, d["ridge"], d["roof"],
                     d["ridges"])


# --------------------------------------------------------------------------- what a block reads

def code_digest() -> str:
    """A digest of the measuring code (this package's modules and the ground under a footprint):
    rows kept from another version of it are measured again."""
    from pipeline25d.analysis import ground_under

    h = hashlib.sha256()
    for path in sorted(Path(__file__).parent.glob("*.py")) + [Path(ground_under.__file__)]:
        h.update(path.name.encode() + path.read_bytes())
    return h.hexdigest()


def reads_digest(map_paths: dict[str, str | Path], members: list[Footprint], context: list[Footprint],
                 settings: MatchSettings, dtm: str | Path | None, extra: str = "") -> str:
    """A digest of everything a block's measurement depends on: its footprints and their context,
    the settings, the measuring code (:func:`code_digest`), ``extra`` (e.g. the ground's
    definition), and the pixels it can read: on the nadir map the window around all its
    footprints, on each oblique map (and the nadir map under it, for the hidden-ground check) that
    window moved over the search range, and the DTM's cells under the oblique reach (the
    silhouette's levelling samples it there)."""
    from pipeline25d.analysis.evaluate.rasters import _open
    from pipeline25d.analysis.heights.template import _prepare_view
    from pipeline25d.analysis.heights.views import oblique_window
    from pipeline25d.core.grid import Extent, Grid
    from pipeline25d.core.raster import read_rgba_block

    h = hashlib.sha256()
    for part in (members, context):
        for fp in part:
            h.update(fp.id.encode() + b"\0")
            for ring in fp.rings:
                h.update(np.ascontiguousarray(ring, dtype=np.float64).tobytes())
        h.update(b"|")
    h.update(repr(sorted(settings.__dict__.items())).encode() + extra.encode() + code_digest().encode())
    if not members:
        return h.hexdigest()
    nad = _open(map_paths[NADIR_ID])
    grid = Grid.of_dataset(nad)
    b = np.array([f.bounds for f in members], dtype=np.float64)
    win = grid.window_covering(Extent(b[:, 0].min(), b[:, 1].min(), b[:, 2].max(), b[:, 3].max()),
                               settings.ring_px + 4)

    def add(ds, c0: int, r0: int, w: int, hgt: int) -> None:
        rgb, alpha = read_rgba_block(ds, c0, r0, w, hgt)
        h.update(np.ascontiguousarray(rgb).tobytes() + np.ascontiguousarray(alpha).tobytes())

    add(nad, win.col0, win.row0, win.width, win.height)
    reach = [win]
    for pid, path in sorted(map_paths.items()):
        if pid == NADIR_ID:
            continue
        v = _prepare_view(pid, path, nad, map_paths[NADIR_ID])
        if v.cot <= 0:
            continue
        r0, c0, r1, c1 = oblique_window(v, win, settings.max_height * v.cot, grid.res)
        if r1 <= r0 or c1 <= c0:
            continue
        h.update(pid.encode())
        add(v.src, c0, r0, c1 - c0, r1 - r0)
        n_r0, n_c0 = r0 - int(round(v.offset[0])), c0 - int(round(v.offset[1]))
        add(nad, n_c0, n_r0, c1 - c0, r1 - r0)
        reach.append((n_c0, n_r0, n_c0 + c1 - c0, n_r0 + r1 - r0))
    if dtm:
        _dtm_digest(h, dtm, grid, reach)
    return h.hexdigest()


def _dtm_digest(h: Any, dtm: str | Path, grid: Any, reach: list) -> None:
    """Add the DTM's cells under the nadir-grid pixel rectangles ``reach`` to the digest ``h``."""
    from pipeline25d.core.grid import Grid
    from pipeline25d.core.raster import gdal

    ds = gdal().Open(str(dtm))
    dg = Grid.of_dataset(ds)
    cols = [c for w in reach for c in (w[0], w[2])]
    rows = [r for w in reach for r in (w[1], w[3])]
    x0, y0 = grid.xy(min(cols), min(rows))
    x1, y1 = grid.xy(max(cols), max(rows))
    (ca, ra), (cb, rb) = dg.colrow(min(x0, x1), max(y0, y1)), dg.colrow(max(x0, x1), min(y0, y1))
    c0, r0 = max(int(math.floor(min(ca, cb))) - 2, 0), max(int(math.floor(min(ra, rb))) - 2, 0)
    c1, r1 = min(int(math.ceil(max(ca, cb))) + 2, dg.width), min(int(math.ceil(max(ra, rb))) + 2, dg.height)
    if c1 > c0 and r1 > r0:
        h.update(np.ascontiguousarray(ds.GetRasterBand(1).ReadAsArray(c0, r0, c1 - c0, r1 - r0)).tobytes())
