"""Ground cells of a DSM: a smooth lower envelope, then the Cloth Simulation Filter on the residual, block by block."""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterator
from concurrent.futures import Executor
from contextlib import nullcontext

import numpy as np

from pipeline25d.core.cores import fork_pool, map_ahead
from pipeline25d.core.grid import BLOCK_CELLS, Block, Grid, cell_blocks, widen
from pipeline25d.core.raster import fill_nearest

log = logging.getLogger(__name__)

#: the cloth's time steps at most (``ground.cloth_iterations``). The cloth falls onto the detrended
#: heights (relief removed) and CSF stops it once no particle moves 5 mm in a step: after about 105
#: steps on the 3 x 3 bench's DSM. Its ground is decided well before: of that DSM's 2.18 M cells 68
#: differ from 500 steps at 40 steps (28 at 50, 216 at 30), in 4.2 s of the cloth's time against 4.9
#: at 50 and 9.7 at 500. 40 steps moved no figure of the decimated Delft mesh's, the rugged or the
#: roofs city's DTM against its true ground by more than 1 mm (p95, p99; one run each).
CLOTH_ITERATIONS = 40


def lower_envelope(dsm: np.ndarray, res: float, max_object_m: float,
                   keep: tuple[slice, slice] | None = None) -> np.ndarray:
    """A smooth surface under the DSM: grey opening wider than any object, then a Gaussian.

    Planes and gentle curvature pass through an opening unchanged; objects narrower than
    ``max_object_m`` are removed. NaN cells are filled with the nearest value first.
    ``keep``: only this part of ``dsm`` is wanted; the Gaussian then runs on it and the
    :func:`envelope_reach` cells around it (equal to smoothing all, at less cost).
    """
    from scipy import ndimage as ndi

    k, reach = envelope_reach(res, max_object_m)
    opened = ndi.grey_opening(fill_nearest(dsm), size=(k, k))
    if keep is None:
        return ndi.gaussian_filter(opened, sigma=k / 6)
    around = tuple(widen(s, reach, n) for s, n in zip(keep, dsm.shape))
    return ndi.gaussian_filter(opened[around], sigma=k / 6)[Block(keep, around).inner]


def envelope_reach(res: float, max_object_m: float) -> tuple[int, int]:
    """(k, g): the opening's window (k x k cells, odd) and the Gaussian's reach in cells (scipy
    truncates at 4 sigma). An envelope cell depends on the DSM within k - 1 + g cells."""
    k = max(3, int(math.ceil(max_object_m / res)) | 1)
    return k, int(4.0 * k / 6 + 0.5)


def csf_ground(dsm: np.ndarray, grid: Grid, max_object_m: float, cloth_resolution: float,
               rigidness: int, class_threshold: float, iterations: int = CLOTH_ITERATIONS) -> np.ndarray:
    """Boolean mask of ground cells by the Cloth Simulation Filter on the detrended DSM."""
    if not np.isfinite(dsm).any():
        return np.zeros(dsm.shape, dtype=bool)
    residual = dsm - lower_envelope(dsm, grid.res, max_object_m)
    whole = (slice(0, grid.height), slice(0, grid.width))
    ground = _cloth_ground(residual, grid, whole, cloth_resolution, rigidness, class_threshold,
                           island_gap(max_object_m, grid.res), iterations)
    return restore_smooth_ground(ground, dsm, grid.res)


def island_gap(max_object_m: float, res: float) -> int:
    """Cells of empty land that separate two islands of model: the largest object's size."""
    return max(math.ceil(max_object_m / res), 1)


def islands(valid: np.ndarray, gap: int) -> Iterator[tuple[tuple[slice, slice], np.ndarray]]:
    """(bounding slices, mask within them) of each group of ``valid`` cells; groups lie at least
    ``gap`` cells apart (cells within ``gap`` of each other always share one; one group: the
    bounding box of all)."""
    from scipy import ndimage as ndi

    h, w = valid.shape
    g = max(int(gap), 1)
    coarse_shape = (-(-h // g), -(-w // g))
    padded = np.zeros((coarse_shape[0] * g, coarse_shape[1] * g), bool)
    padded[:h, :w] = valid
    coarse = padded.reshape(coarse_shape[0], g, coarse_shape[1], g).any(axis=(1, 3))
    del padded
    labels, n = ndi.label(coarse, structure=np.ones((3, 3)))
    for k, (rs, cs) in enumerate(ndi.find_objects(labels), start=1):
        box = (slice(rs.start * g, min(rs.stop * g, h)), slice(cs.start * g, min(cs.stop * g, w)))
        if n == 1:
            yield box, valid[box]
            return
        own = np.repeat(np.repeat(labels[rs, cs] == k, g, axis=0), g, axis=1)
        yield box, valid[box] & own[:box[0].stop - box[0].start, :box[1].stop - box[1].start]


def _cloth_ground(residual: np.ndarray, grid: Grid, window: tuple[slice, slice], cloth_resolution: float,
                  rigidness: int, class_threshold: float, gap: int,
                  iterations: int = CLOTH_ITERATIONS) -> np.ndarray:
    """CSF ground mask of the cells ``window`` of ``grid`` given their detrended heights (NaN: none).

    Each island of model (:func:`islands`, ``gap`` cells apart) gets its own cloth, spanning
    the island rather than the empty land around it, where a cloth would only fall for all its
    ``iterations``. Points are placed relative to the grid's corner, so a window's points are
    the whole grid's.
    """
    valid = np.isfinite(residual)
    mask = np.zeros_like(valid)
    rows, cols = window
    xs, ys = grid.column_x()[cols] - grid.xmin, grid.row_y()[rows] - grid.ymax
    for (r, c), cells in islands(valid, gap):
        mask[r, c] = _cloth_of(residual[r, c], cells, xs[c], ys[r], cloth_resolution, rigidness, class_threshold,
                               iterations)
    return mask


def _cloth_of(residual: np.ndarray, valid: np.ndarray, xs: np.ndarray, ys: np.ndarray, cloth_resolution: float,
              rigidness: int, class_threshold: float, iterations: int = CLOTH_ITERATIONS) -> np.ndarray:
    """CSF ground mask of one island: cells ``valid`` at (``xs``, ``ys``) with heights ``residual``,
    after at most ``iterations`` time steps (:data:`CLOTH_ITERATIONS`).

    The cloth runs on one OpenMP thread: CSF's parallel spring pass writes shared particles from
    several threads, so with more than one its ground depends on the thread count and even
    varies run to run, and the same scene gave different maps on machines of different sizes.
    """
    import CSF
    from threadpoolctl import threadpool_limits

    pts = np.empty((int(valid.sum()), 3))
    pts[:, 0] = np.broadcast_to(xs, valid.shape)[valid]
    pts[:, 1] = np.broadcast_to(ys[:, None], valid.shape)[valid]
    pts[:, 2] = residual[valid]
    csf = CSF.CSF()
    csf.params.bSloopSmooth = True
    csf.params.cloth_resolution = cloth_resolution
    csf.params.rigidness = rigidness
    csf.params.class_threshold = class_threshold
    csf.params.interations = iterations
    csf.params.time_step = 0.65
    csf.setPointCloud(pts)
    del pts                                          # the CSF holds its own copy
    ground, off = CSF.VecInt(), CSF.VecInt()
    with threadpool_limits(limits=1, user_api="openmp"):
        csf.do_filtering(ground, off, exportCloth=False)
    flat = _indexed(int(valid.sum()), ground, off)
    mask = np.zeros_like(valid)
    mask[valid] = flat
    return mask


def _indexed(n: int, ground, off) -> np.ndarray:
    """(n,) bool: the points CSF put in ``ground`` (its indices; every other point is in ``off``),
    read from the shorter of the two (SWIG vectors are read an element at a time: 0.08-0.12 s a
    million)."""
    if len(ground) <= len(off):
        flat = np.zeros(n, dtype=bool)
        flat[np.fromiter(ground, dtype=np.int64, count=len(ground))] = True
    else:
        flat = np.ones(n, dtype=bool)
        flat[np.fromiter(off, dtype=np.int64, count=len(off))] = False
    return flat


def ground_blocks(read: Callable[[slice, slice], np.ndarray], grid: Grid, max_object_m: float,
                  cloth_resolution: float, rigidness: int, class_threshold: float,
                  max_cells: int = BLOCK_CELLS, processes: int = 1, pool: Executor | None = None,
                  iterations: int = CLOTH_ITERATIONS) -> Iterator[tuple[Block, np.ndarray, np.ndarray]]:
    """(block, DSM, ground mask) of each block's core: :func:`csf_ground` and :func:`trim_object_edges`
    run on the block's window, the DSM read through ``read(rows, cols)`` (float64, NaN: no model).
    The blocks: :func:`ground_layout` (:func:`~pipeline25d.core.grid.cell_blocks` with ``halve``).
    A cloth's cost grows with its cells: the 3 x 3 bench's 1585 x 1375 cells (margin 200) took
    1.26 x the one cloth's seconds as halves in one process, 0.67-0.73 x in two.

    The window reaches ``max_object_m`` beyond the core (an object cut by the core's edge lies
    whole in it, with ground beyond it for the cloth to rest on); the DSM is read wider still,
    by :func:`envelope_reach`, so the detrended heights equal the whole grid's on the window.
    With ``processes`` > 1 the blocks are filtered that many at a time in worker processes, those
    of ``pool`` (:func:`~pipeline25d.core.cores.fork_pool`) or forked now (the DSM is read here, at most
    ``processes`` blocks ahead); each block's ground is its own, so the result does not depend
    on the count.
    """
    k, g = envelope_reach(grid.res, max_object_m)
    blocks = ground_layout(grid, max_object_m, cloth_resolution, max_cells)
    args = (grid, max_object_m, cloth_resolution, rigidness, class_threshold, iterations)

    def windows():
        for block in blocks:
            wide = tuple(widen(s, k - 1 + g, n) for s, n in zip(block.window, grid.shape))
            yield block, read(*wide), wide, *args

    several = processes > 1 and len(blocks) > 1
    with (fork_pool(processes) if pool is None else nullcontext(pool)) if several else nullcontext() as workers:
        for block, result in zip(blocks, map_ahead(workers, _block_ground, windows(), processes)):
            yield block, *result


def ground_layout(grid: Grid, max_object_m: float, cloth_resolution: float,
                  max_cells: int = BLOCK_CELLS) -> list[Block]:
    """The blocks :func:`ground_blocks` filters: their windows reach ``max_object_m`` beyond their
    cores and keep the cloth's grid where the whole grid has it."""
    q = round(cloth_resolution / grid.res)
    align = q if q >= 1 and math.isclose(q * grid.res, cloth_resolution) else 1
    return cell_blocks(grid.height, grid.width, math.ceil(max_object_m / grid.res), max_cells, align=align,
                       halve=True)


def _block_ground(block: Block, dsm: np.ndarray, wide: tuple[slice, slice], grid: Grid, max_object_m: float,
                  cloth_resolution: float, rigidness: int, class_threshold: float,
                  iterations: int = CLOTH_ITERATIONS) -> tuple[np.ndarray, np.ndarray]:
    """(DSM, ground mask) of ``block``'s core from the DSM read over ``wide`` (see :func:`ground_blocks`)."""
    keep = Block(block.window, wide).inner
    if not np.isfinite(dsm[keep]).any():     # no model in the window: no ground, nothing to filter
        core = dsm[keep][block.inner]
        return core, np.zeros(core.shape, bool)
    residual = dsm[keep] - lower_envelope(dsm, grid.res, max_object_m, keep)
    dsm = dsm[keep]
    ground = _cloth_ground(residual, grid, block.window, cloth_resolution, rigidness, class_threshold,
                           island_gap(max_object_m, grid.res), iterations)
    del residual
    ground = trim_object_edges(restore_smooth_ground(ground, dsm, grid.res), dsm)
    return dsm[block.inner], ground[block.inner]


#: the steepest terrain (tan of 60°): a step between neighbouring cells up to res x this + SMOOTH_STEP_M is smooth
SMOOTH_SLOPE = math.tan(math.radians(60.0))
SMOOTH_STEP_M = 0.5
#: where terrain meets the ground the cloth found, its slope goes on: across a border cell it
#: bends (slope BEND_SPAN_M beyond minus slope BEND_SPAN_M before) by at most SMOOTH_BEND. A tree
#: crown without sharp edges (a decimated or photogrammetric mesh) rises from the ground with a
#: kink: of the 17 crowns that passed the step test on the Delft LiDAR mesh decimated to 10 %,
#: at most 26 % of each border bent by 0.25 or less; of two shaved hilltops, 98-100 %.
SMOOTH_BEND = 0.25
BEND_SPAN_M = 2.0


def restore_smooth_ground(ground: np.ndarray, dsm: np.ndarray, res: float, share: float = 0.5,
                          min_area_m2: float = 100.0) -> np.ndarray:
    """The ground mask with the terrain the cloth missed put back: rounded hilltops and ridges.

    The lower envelope (a flat opening) shaves a curved hilltop, so the cloth sees it as an object
    (on the roofs city a hill's top lay 31 m above the DTM made without it). Objects stand on walls
    or rise with a kink; terrain goes on. The non-ground cells are split into smooth pieces
    (4-neighbours whose DSM step is at most ``res`` x :data:`SMOOTH_SLOPE` + :data:`SMOOTH_STEP_M`);
    a piece of at least ``min_area_m2`` whose border with ground cells is smooth along at least
    ``share`` of it is ground. A border cell is smooth when the step to the ground cell beside it
    is, and the slope through that ground cell bends by at most :data:`SMOOTH_BEND` (over
    :data:`BEND_SPAN_M` either side; where that reaches past the model, the step alone decides):
    a roof meets the ground through a wall, a tree crown with a kink, a hillside with neither.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    valid = np.isfinite(dsm)
    off = valid & ~ground
    n_off = int(off.sum())
    if not n_off or not ground.any():
        return ground
    step = res * SMOOTH_SLOPE + SMOOTH_STEP_M
    index = np.full(dsm.shape, -1, dtype=np.int64)
    index[off] = np.arange(n_off)
    a_list, b_list, border, smooth = [], [], [], []
    for axis in (0, 1):
        lo = tuple(slice(0, -1) if k == axis else slice(None) for k in (0, 1))
        hi = tuple(slice(1, None) if k == axis else slice(None) for k in (0, 1))
        flat = np.abs(dsm[hi] - dsm[lo]) <= step                    # NaN compares False
        both = off[lo] & off[hi] & flat
        a_list.append(index[lo][both])
        b_list.append(index[hi][both])
        unbent = ~_bends(dsm, res, axis)
        for here, there in ((lo, hi), (hi, lo)):                     # off cell beside a ground cell
            pair = off[here] & ground[there]
            border.append(index[here][pair])
            smooth.append(index[here][pair & flat & unbent[there]])
    a, b = np.concatenate(a_list), np.concatenate(b_list)
    graph = coo_matrix((np.ones(len(a), np.int8), (a, b)), shape=(n_off, n_off))
    n, label = connected_components(graph, directed=False)
    size = np.bincount(label, minlength=n)
    n_border = np.bincount(label[np.concatenate(border)], minlength=n)
    n_smooth = np.bincount(label[np.concatenate(smooth)], minlength=n)
    terrain = (size * res * res >= min_area_m2) & (n_border > 0) & (n_smooth >= share * n_border)
    if not terrain.any():
        return ground
    out = ground.copy()
    out[off] = terrain[label]
    log.debug("ground: %d smooth pieces (%d cells) the cloth left out put back", int(terrain.sum()),
              int(size[terrain].sum()))
    return out


def _bends(dsm: np.ndarray, res: float, axis: int) -> np.ndarray:
    """Cells where the DSM's slope along ``axis`` changes by more than :data:`SMOOTH_BEND`
    between :data:`BEND_SPAN_M` before and after them (at least a cell); False where that
    span leaves the grid or the model."""
    m = max(1, round(BEND_SPAN_M / res))
    bent = np.zeros(dsm.shape, bool)
    if dsm.shape[axis] <= 2 * m:
        return bent
    before, after, centre = (tuple(slice(a, b) if k == axis else slice(None) for k in (0, 1))
                             for a, b in ((0, -2 * m), (2 * m, None), (m, -m)))
    with np.errstate(invalid="ignore"):
        bent[centre] = np.abs(dsm[after] - 2.0 * dsm[centre] + dsm[before]) > SMOOTH_BEND * m * res
    return bent


def trim_object_edges(ground: np.ndarray, dsm: np.ndarray | None = None, tol: float = 0.1,
                      window: int = 7) -> np.ndarray:
    """Drop the ground cells along objects that rise above the ground around them.

    A ground cell touching a non-ground cell is a wall foot or eave on a surface mesh, or
    true ground where a model's wall meets its terrain. With ``dsm`` it is kept when it
    lies at most ``tol`` m above the plane fitted (least squares) to the inner ground cells
    of a ``window``² neighbourhood, so the ground at a building's foot still shapes the DTM
    under it. Without ``dsm`` (or with too few inner cells to fit) every edge cell is dropped.
    """
    from scipy import ndimage as ndi

    edge = ground & ndi.binary_dilation(~ground, structure=np.ones((3, 3), bool))
    inner = ground & ~edge
    if dsm is None:
        return inner
    h, w = ground.shape
    r0 = (np.arange(h, dtype=np.float64) - (h - 1) / 2)[:, None]     # centred: keeps the sums well conditioned
    c0 = (np.arange(w, dtype=np.float64) - (w - 1) / 2)[None, :]
    wgt = inner.astype(np.float64)
    z = np.where(inner, dsm, 0.0)

    def box(a):
        return ndi.uniform_filter(a, size=window, mode="constant")

    keep = inner.copy()
    s0 = box(wgt)
    idx = np.nonzero(edge & (s0 * window ** 2 >= 6))
    if not len(idx[0]):
        return keep
    # local plane z = a + b·row + c·col by weighted least squares (3×3 normal equations), each
    # sum kept at the edge cells only (whole-grid sums would be nine grids at once)
    s0 = s0[idx]
    sr, sc, srr, src, scc, tz, trz, tcz = (box(t)[idx] for t in (
        wgt * r0, wgt * c0, wgt * r0 * r0, wgt * r0 * c0, wgt * c0 * c0, z, z * r0, z * c0))
    m = np.stack([np.stack(row, -1) for row in ((s0, sr, sc), (sr, srr, src), (sc, src, scc))], -2)
    v = np.stack([tz, trz, tcz], -1)
    ok = np.abs(np.linalg.det(m)) > 1e-9 * np.maximum(s0, 1e-12) ** 3
    coef = np.zeros((len(m), 3))
    coef[ok] = np.linalg.solve(m[ok], v[ok][..., None])[..., 0]
    plane = coef[:, 0] + coef[:, 1] * r0[idx[0], 0] + coef[:, 2] * c0[0, idx[1]]
    keep[idx[0][ok], idx[1][ok]] = dsm[idx][ok] <= plane[ok] + tol
    return keep
