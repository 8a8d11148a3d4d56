"""The scene stage: reference plane z0, projection mode, GCP candidates with check-point roles, and the DTM.

With ``terrain: auto`` the DTM is interpolated from the terrain stage's ground cells with the
ground around each check point held out, so check points measure ground the DTM has not seen.
"""

from __future__ import annotations

import logging
from concurrent.futures import Executor
from contextlib import nullcontext
from dataclasses import replace
from functools import partial
from pathlib import Path
from typing import NamedTuple

import numpy as np

from pipeline25d.core.atomic import write_json, write_text
from pipeline25d.core.errors import ConfigError, GroundError
from pipeline25d.core.grid import Window
from pipeline25d.geometry.perspectives import Perspective
from pipeline25d.stages.gcps import CANDIDATE_FIELDS, assign_roles, read_csv, square_id, write_csv
from pipeline25d.stages.lod import lod_chunks, scene_bounds
from pipeline25d.stages.records import ChunkGround, Scene

log = logging.getLogger(__name__)


GROUND_MARGIN_M = 2.0   # widens a chunk's ground range (tile assignment in terrain mode) against sampling gaps


def scene_setup(lod_indexes: list[str], dsm_path: str | Path, terrain: str, terrain_path: str | Path | None,
                z0_cfg, projection: str, gcp_cfg: dict, scene_crs: str, gsd: float, perspective_ids: list[str],
                out_scene: str | Path, out_candidates: str | Path, out_dtm: str | Path | None = None,
                max_object_size: float = 100.0, out_grounds: str | Path | None = None, processes: int = 1,
                out_holdout: str | Path | None = None) -> dict:
    """Reference plane z0, projection mode, GCP candidates (with check-point roles) and, for
    ``terrain: auto``, the DTM.

    ``processes``: how many of the DTM's blocks are interpolated at once, by workers forked
    before the DSM is read (the same DTM whatever the count).

    ``out_grounds``: the DTM under each chunk (:func:`chunk_grounds`), which every perspective's
    plan reads in terrain-relative mode (empty otherwise): sampled once here, not once per plan.

    ``terrain_path``: the ground heights from :func:`build_terrain` (auto) or the user's DTM.
    With auto, the ground around each check point (within :func:`holdout_radius`) is left
    out of the DTM's interpolation, so a check point measures how well the DTM predicts
    ground it has not seen, not the DSM against itself. Where it is left out does not depend
    on the perspectives (:func:`~pipeline25d.stages.gcp_sites.select_sites`), so neither does
    the DTM: a perspective added later draws no kept tile again. ``out_holdout``: those
    places (CSV: id, x, y; auto only), each check square's site, seen in a view or not.

    Memory: the DSM and the DTM are held whole as float32, 8 bytes a cell, which loses
    nothing (the DSM is read from its float32 GeoTIFF, GDAL's fill computes in float32);
    the DTM's interpolation and the site search run block by block.
    """
    from pipeline25d.core.cores import fork_pool
    from pipeline25d.core.geotiff import FloatRaster
    from pipeline25d.stages.terrain.dtm import dtm_layout

    dsm_src = FloatRaster(dsm_path)
    search = int(np.ceil(max_object_size / 2 / dsm_src.grid.res))
    several = processes > 1 and terrain == "auto" and len(dtm_layout(dsm_src.grid, search)) > 1
    with fork_pool(processes) if several else nullcontext() as pool:
        return _scene_setup(lod_indexes, dsm_src, terrain, terrain_path, z0_cfg, projection, gcp_cfg, scene_crs, gsd,
                            perspective_ids, out_scene, out_candidates, out_dtm, search, out_grounds,
                            DtmWorkers(pool, processes if pool else 1), out_holdout)


class DtmWorkers(NamedTuple):
    """The scene job's forked workers (None: none) and how many run at once."""

    pool: Executor | None
    count: int


def _scene_setup(lod_indexes: list[str], dsm_src, terrain: str, terrain_path: str | Path | None, z0_cfg,
                 projection: str, gcp_cfg: dict, scene_crs: str, gsd: float, perspective_ids: list[str],
                 out_scene: str | Path, out_candidates: str | Path, out_dtm: str | Path | None, search: int,
                 out_grounds: str | Path | None, workers: DtmWorkers, out_holdout: str | Path | None = None) -> Scene:
    """:func:`scene_setup` once its workers are forked."""
    from pipeline25d.core.crs import horizontal_wkt
    from pipeline25d.core.geotiff import FloatRaster, write_float_geotiff
    from pipeline25d.core.raster import DTM
    from pipeline25d.stages.gcp_sites import select_sites
    from pipeline25d.stages.gcps import candidates_from_sites, check_squares
    from pipeline25d.stages.terrain.gap_planes import gap_plane_cells

    chunks = lod_chunks(lod_indexes)
    bounds, lo, hi = scene_bounds(chunks)
    grid = dsm_src.grid
    dsm = dsm_src.read_all(np.float32)
    seed_src, radius, height_fn, held, ids = None, None, None, np.zeros((0, 2)), []
    rules = site_rules(gcp_cfg, gsd) if gcp_cfg["source"] == "auto" else None
    if terrain == "flat":
        level = float(z0_cfg) if z0_cfg != "auto" else float(np.median(bounds[:, 0, 2]))
        dtm = np.broadcast_to(level, grid.shape)
    elif terrain == "auto":
        seed_src = FloatRaster(terrain_path)
        needed = _under_chunks(bounds, grid)
        radius = holdout_radius(rules, grid.res) if rules is not None else None
        plane = gap_plane_cells(grid.res, radius or 0.0)
        # with GCPs of its own, this DTM only chooses their sites, which stand on ground cells: the
        # plain fill (the DTM is filled again, along local planes, without the check points' ground)
        dtm = _interpolated_dtm(seed_src.read, grid, search, needed, workers, 0 if rules is not None else plane)
    else:
        height_fn = DTM(terrain_path, scene_crs, continuous=True).sample
        dtm = _sampled_dtm(height_fn, grid)
    covered = np.isfinite(dsm)
    if seed_src is not None:
        _check_ground(dtm, grid, chunks, terrain_path, 4 * search * grid.res, covered)
    # auto: the median ground height, rounded to whole metres so a local terrain change does not move it
    z0 = float(z0_cfg) if z0_cfg != "auto" else float(round(_median(dtm[covered]))) if covered.any() else float(lo[2])
    if projection == "auto":
        projection = "plane" if terrain == "flat" else "terrain"
    if projection == "terrain" and terrain == "flat":
        raise ConfigError("config key projection: terrain-relative projection needs a terrain (auto or a DTM path), "
                          "not terrain: flat")
    perspectives = [Perspective.from_id(pid) for pid in perspective_ids]
    if rules is not None:
        surface = dsm if seed_src is None else with_bare_ground(dsm, dtm, seed_src.read_all(np.float32))
        sites = select_sites(surface, dtm, grid, rules, perspectives,
                             check_square=check_squares(gcp_cfg["holdout"], gcp_cfg["seed"]))
        cands = candidates_from_sites(sites, gcp_cfg["holdout"], gcp_cfg["seed"])
        del surface
        if seed_src is not None:
            held = np.round(np.column_stack([sites["held_x"], sites["held_y"]]), 3)    # as the candidates
            ids = [square_id(c, r) for c, r in zip(sites["held_col"], sites["held_row"])]
            del dtm
            dtm = _interpolated_dtm(partial(_held_out_read, seed_src, grid, held, radius), grid, search, needed,
                                    workers, plane)
            _check_ground(dtm, grid, chunks, terrain_path, 4 * search * grid.res, covered)
            xy = np.array([[c.x, c.y] for c in cands]).reshape(-1, 2)
            cands = [replace(c, ground=round(float(g), 3)) for c, g in zip(cands, _sample_continuous(dtm, grid, xy))]
            log.info("DTM interpolated without the ground within %.1f m of each check point", radius)
    else:
        rows = read_csv(gcp_cfg["source"])
        xy = np.array([[r["x"], r["y"]] for r in rows]).reshape(-1, 2)
        ground = (height_fn(xy[:, 0], xy[:, 1]) if height_fn else
                  np.array([_cell_value(dtm, grid, x, y) for x, y in xy]))
        cands = assign_roles([{"id": r["id"], "x": r["x"], "y": r["y"], "z": r["z"], "ground": float(g),
                               "sx": 0.0, "sy": 0.0} for r, g in zip(rows, ground)],
                             gcp_cfg["holdout"], gcp_cfg["seed"])
    if terrain == "auto":
        write_float_geotiff(out_dtm, dtm, grid, horizontal_wkt(scene_crs))
    if out_holdout is not None:
        write_text(out_holdout, "id,x,y\n" + "".join(f"{i},{x:.3f},{y:.3f}\n" for i, (x, y) in zip(ids, held)))
    dtm_path = out_dtm if terrain == "auto" else terrain_path
    scene = Scene(bounds=(tuple(lo.tolist()), tuple(hi.tolist())), z0=z0, terrain=terrain, projection=projection,
                  dtm=None if terrain == "flat" else str(dtm_path), n_candidates=len(cands),
                  n_check=sum(c.role == "check" for c in cands), dtm_check_holdout_m=radius, n_chunks=len(chunks))
    if out_grounds is not None:
        grounds = chunk_grounds(chunks, DTM(dtm_path, scene_crs, continuous=True)) if projection == "terrain" else {}
        write_grounds(out_grounds, grounds)
    write_csv(out_candidates, cands, CANDIDATE_FIELDS)
    write_json(out_scene, scene.to_json())
    log.info("z0 %.2f m, projection %s, %d GCP candidates (%d check points)", z0, projection, len(cands),
             scene.n_check)
    return scene


def with_bare_ground(dsm: np.ndarray, dtm: np.ndarray, seed: np.ndarray) -> np.ndarray:
    """The surface GCP sites are chosen on: the DSM, and the DTM where the model draws nothing but
    the ground heights (``seed``, the terrain stage's) hold a value. Only the bases of a
    buildings-only model give ground there (between its buildings; every other source is a
    drawn surface): bare ground, whose markers the render draws over an empty map
    (:meth:`pipeline25d.stages.render.TileRenderer.render_markers`). Without it such a model
    has no check points at all."""
    bare = ~np.isfinite(dsm) & np.isfinite(seed)
    if not bare.any():
        return dsm
    out = dsm.copy()
    out[bare] = dtm[bare]
    return out


def _interpolated_dtm(read, grid, search: int, needed=None, workers: DtmWorkers = DtmWorkers(None, 1),
                      plane: int = 0) -> np.ndarray:
    """The DTM (float32) from the ground heights ``read(rows, cols)``, its gaps filled along local
    planes of ``plane`` cells (:func:`gap_plane_cells`).

    With ``needed`` (a sparse scene's blocks under the model), the DTM reaches 4 x ``search``
    cells (twice the largest object) beyond the ground and is NaN elsewhere: empty land costs nothing.
    ``workers``: its blocks filled by forked workers (``read`` then pickles), or here.
    """
    from pipeline25d.stages.terrain.dtm import dtm_blocks

    dtm = np.empty(grid.shape, np.float32)
    reach = None if needed is None else 4 * search
    for block, values in dtm_blocks(read, grid, search, needed=needed, reach_cells=reach, pool=workers.pool,
                                    ahead=workers.count, plane_cells=plane):
        dtm[block.core] = values
    return dtm


def _held_out_read(seed_src, grid, held: np.ndarray, radius: float, rows: slice, cols: slice) -> np.ndarray:
    """The ground heights of (rows, cols) without those within ``radius`` of the ``held`` (n, 2)
    points (:func:`_without_held_out`); a module function, so a worker can be sent it."""
    return _without_held_out(seed_src.read(rows, cols), grid, held, radius, (rows, cols))


def _check_ground(dtm: np.ndarray, grid, chunks: list, ground_path, reach_m: float, covered: np.ndarray) -> None:
    """GroundError naming the inputs and what to do when the DTM has no height somewhere under a
    chunk (no ground within ``reach_m`` of it): never a NaN z0, vertex height or chunk ground range.

    Only the cells ``covered`` (the model's: what z0 and the vertices of terrain-relative tiles
    sample) are checked, not each chunk's whole bounding box: a sparse chunk's box may reach
    farther from any ground than the DTM does, and the tiles read the DTM continuous (a cell
    without a height takes the nearest one's: :class:`~pipeline25d.core.raster.DTM`)."""
    bare = []
    for c in chunks:
        (x0, y0, _), (x1, y1, _) = c.bounds
        cols = slice(max(int((x0 - grid.xmin) // grid.res), 0), min(int((x1 - grid.xmin) // grid.res) + 1, grid.width))
        rows = slice(max(int((grid.ymax - y1) // grid.res), 0), min(int((grid.ymax - y0) // grid.res) + 1, grid.height))
        missing = ~np.isfinite(dtm[rows, cols])
        if (missing & covered[rows, cols]).any():
            bare.append(c)
    if not bare:
        return
    where = "; ".join(f"{c.district}/{c.id} at x {c.bounds[0][0]:.0f}..{c.bounds[1][0]:.0f}, "
                      f"y {c.bounds[0][1]:.0f}..{c.bounds[1][1]:.0f}" for c in bare[:3])
    districts = ", ".join(sorted({c.district for c in bare}))
    raise GroundError(f"terrain: auto found no ground within {reach_m:.0f} m of {len(bare)} of the model's "
                      f"{len(chunks)} chunks ({where}{'; ...' if len(bare) > 3 else ''}) of the input(s) "
                      f"{districts}: they carry no terrain, no buildings whose bases give one, and the Cloth "
                      f"Simulation Filter found no ground near them ({ground_path}); give a DTM "
                      "(terrain: <path of a GeoTIFF>) or set terrain: flat")


def _under_chunks(bounds: np.ndarray, grid, margin_cells: int = 2):
    """``needed(core)``: whether a block's cells (widened by ``margin_cells``) meet a chunk's footprint.

    The DTM is sampled only under the model's chunks, so blocks of empty land (a sparse
    scene) need none.
    """
    xy = np.asarray(bounds, dtype=np.float64)[:, :, :2]      # (n, 2 [lo, hi], 2 [x, y])

    def needed(core: tuple[slice, slice]) -> bool:
        rows, cols = core
        pad, b = margin_cells * grid.res, grid.window_bounds(Window.of_slices(rows, cols))
        x0, x1, y0, y1 = b.xmin - pad, b.xmax + pad, b.ymin - pad, b.ymax + pad
        return bool(np.any((xy[:, 0, 0] <= x1) & (xy[:, 1, 0] >= x0) & (xy[:, 0, 1] <= y1) & (xy[:, 1, 1] >= y0)))

    return needed


def _sampled_dtm(height_fn, grid, rows_per_strip: int = 256) -> np.ndarray:
    """A user DTM sampled at every cell centre, a strip of rows at a time."""
    dtm = np.empty(grid.shape)
    xs, ys = grid.column_x(), grid.row_y()
    for r0 in range(0, grid.height, rows_per_strip):
        gx, gy = np.meshgrid(xs, ys[r0:r0 + rows_per_strip])
        dtm[r0:r0 + rows_per_strip] = height_fn(gx.ravel(), gy.ravel()).reshape(gx.shape)
    return dtm


def _median(values: np.ndarray) -> float:
    """np.median of a (float32) vector in float64, partitioning ``values`` in place (no copy)."""
    n = len(values)
    values.partition([(n - 1) // 2, n // 2])
    return (float(values[(n - 1) // 2]) + float(values[n // 2])) / 2


def _sample_continuous(values: np.ndarray, grid, xy: np.ndarray) -> np.ndarray:
    """Bilinear heights at (n, 2) points, as ``DTM.from_array(values, continuous=True)`` gives them,
    each from the 5 x 5 cells around it (no float64 copy of the grid).

    The points whose 5 x 5 cells lie inside the grid and hold heights (nearly all) are sampled
    at once, by the same arithmetic as such a window's :meth:`~pipeline25d.core.raster.DTM.sample`;
    the others (at the grid's edge, or with a hole to fill) one window at a time."""
    from pipeline25d.core.raster import DTM

    n, t = len(xy), grid.transform
    out = np.empty(n)
    if not n:
        return out
    col, row = grid.colrow(xy[:, 0], xy[:, 1])
    c = np.clip(col.astype(np.int64), 0, grid.width - 1) - 2          # each window's first column and row
    r = np.clip(row.astype(np.int64), 0, grid.height - 1) - 2
    inside = (c >= 0) & (r >= 0) & (c + 5 <= grid.width) & (r + 5 <= grid.height) if t.b == 0 and t.d == 0 \
        else np.zeros(n, bool)
    k = np.flatnonzero(inside)
    cells = values[r[k, None, None] + np.arange(5)[:, None], c[k, None, None] + np.arange(5)].astype(np.float64)
    whole = np.isfinite(cells).all(axis=(1, 2))
    k, cells = k[whole], cells[whole]
    # the window's grid is t @ translation(c, r): its origin a·c + c0, e·r + f0, as Affine computes it
    wc = (xy[k, 0] - (t.a * c[k] + t.b * r[k] + t.c)) / t.a - 0.5
    wr = (xy[k, 1] - (t.d * c[k] + t.e * r[k] + t.f)) / t.e - 0.5
    wc, wr = np.clip(wc, 0, 5 - 1.000001), np.clip(wr, 0, 5 - 1.000001)
    c0, r0 = np.floor(wc).astype(int), np.floor(wr).astype(int)
    fc, fr, j = wc - c0, wr - r0, np.arange(len(k))
    out[k] = ((cells[j, r0, c0] * (1 - fc) + cells[j, r0, c0 + 1] * fc) * (1 - fr)
              + (cells[j, r0 + 1, c0] * (1 - fc) + cells[j, r0 + 1, c0 + 1] * fc) * fr)
    done = np.zeros(n, bool)
    done[k] = True
    for i in np.flatnonzero(~done):
        x, y = xy[i]
        cc, rr = grid.cell_of(x, y)
        rows, cols = slice(max(rr - 2, 0), min(rr + 3, grid.height)), slice(max(cc - 2, 0), min(cc + 3, grid.width))
        window = DTM.from_array(values[rows, cols], grid.window(rows, cols), continuous=True)
        out[i] = window.sample(np.array([x]), np.array([y]))[0]
    return out


def site_rules(gcp_cfg: dict, gsd: float):
    """The GCP sites' :class:`~pipeline25d.stages.gcp_sites.SiteRules` from the config's ``gcp``."""
    from pipeline25d.stages.gcp_sites import SiteRules

    return SiteRules(spacing=gcp_cfg["spacing"], radius=gcp_cfg["marker_px"] * gsd, clearance=gcp_cfg["clearance"],
                     max_height=gcp_cfg["max_height"], max_roughness=gcp_cfg["max_roughness"],
                     max_slope=gcp_cfg["max_slope"])


def holdout_radius(rules, res: float) -> float:
    """Metres of ground around a check point left out of the DTM: its marker, the marker's
    clearance and two DTM cells, so the DTM must predict the whole marker from ground it saw
    farther away. (Wider holes would degrade the DTM, and so the maps, wherever check points
    are dense: on Delft's LiDAR mesh, 5 m holes round check points 4 m apart made the ground
    of the oblique maps 2-3 times farther off, as image correlation measures it.)"""
    return rules.radius + rules.clearance + 2 * res


def _without_held_out(seed: np.ndarray, grid, held: np.ndarray, radius: float,
                      window: tuple[slice, slice] | None = None) -> np.ndarray:
    """A copy of the ground heights with the cells within ``radius`` of each ``held`` (n, 2)
    point (the check squares' sites) set to NaN.

    ``window``: ``seed`` holds only these (rows, cols) of ``grid``.
    """
    out = seed.copy()
    rows, cols = window or (slice(0, grid.height), slice(0, grid.width))
    xs, ys = grid.column_x(), grid.row_y()
    k = int(np.ceil(radius / grid.res)) + 1
    for x, y in held:
        col, row = (int(v) for v in grid.colrow(x, y))
        r0, r1 = max(row - k, rows.start), min(row + k + 1, rows.stop)
        c0, c1 = max(col - k, cols.start), min(col + k + 1, cols.stop)
        if r0 >= r1 or c0 >= c1:
            continue
        near = np.hypot(xs[None, c0:c1] - x, ys[r0:r1, None] - y) <= radius
        out[r0 - rows.start:r1 - rows.start, c0 - cols.start:c1 - cols.start][near] = np.nan
    return out


def _cell_value(values: np.ndarray, grid, x: float, y: float) -> float:
    """The value of the grid cell holding (x, y), clamped to the grid."""
    col, row = grid.cell_of(x, y)
    return float(values[row, col])


def chunk_grounds(chunks: list, dtm) -> dict[tuple[str, str], ChunkGround]:
    """{(district, chunk id): :func:`chunk_ground`} of every LOD chunk."""
    return {(c.district, c.id): chunk_ground(c.bounds, dtm) for c in chunks}


def write_grounds(path: str | Path, grounds: dict[tuple[str, str], ChunkGround]) -> None:
    """:func:`chunk_grounds` as JSON rows [district, chunk id, lowest, highest, digest] (floats
    round-trip exactly)."""
    write_json(path, [[d, c, g.lowest, g.highest, g.digest] for (d, c), g in sorted(grounds.items())], indent=None)


def read_grounds(path: str | Path) -> dict[tuple[str, str], ChunkGround]:
    """:func:`write_grounds`' file back."""
    import json

    return {(d, c): ChunkGround(lo, hi, digest) for d, c, lo, hi, digest in json.loads(Path(path).read_text())}


def chunk_ground(bounds: np.ndarray, dtm) -> ChunkGround:
    """The lowest and highest DTM height under a chunk's footprint, and a digest of the samples.

    Heights are sampled every DTM cell (at most 129 × 129) and widened by GROUND_MARGIN_M;
    the digest of the samples enters the tile spec, so a tile re-renders when, and only
    when, the ground under one of its chunks changes.
    """
    import hashlib

    lo, hi = np.asarray(bounds, dtype=np.float64)
    step = abs(dtm.grid.res)
    nx = int(min(max(np.ceil((hi[0] - lo[0]) / step) + 1, 2), 129))
    ny = int(min(max(np.ceil((hi[1] - lo[1]) / step) + 1, 2), 129))
    gx, gy = np.meshgrid(np.linspace(lo[0], hi[0], nx), np.linspace(lo[1], hi[1], ny))
    g = dtm.sample(gx.ravel(), gy.ravel())
    if not np.isfinite(g).all() or np.abs(g).max() > 1e5:
        raise ValueError(f"{dtm.path}: DTM heights under the chunk at {lo[:2]}..{hi[:2]} are not finite "
                         "or not plausible (|h| > 100 km)")
    digest = hashlib.sha256(np.round(g, 2).tobytes()).hexdigest()[:12]   # cm: float noise does not count
    return ChunkGround(float(np.min(g)) - GROUND_MARGIN_M, float(np.max(g)) + GROUND_MARGIN_M, digest)
