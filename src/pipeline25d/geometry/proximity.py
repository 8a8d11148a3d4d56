"""Exact distances from points to a triangle surface, in numpy alone.

The LOD stage measures every level's error with it: trimesh's ``closest_point`` and
``import trimesh`` were most of a LOD job. Triangles are binned by their bounding box on a
uniform grid in (x, y). A point's distance d is first the nearest of the triangles in its
own cell; it is exact once the cells searched cover the square of half-width d around the
point (no triangle outside them can be nearer), else the search is repeated over the cells
of that square (over a growing block while no triangle was found). Coordinates in metres,
best local (near 0) for float64 precision.
"""

from __future__ import annotations

import numpy as np

PAIRS_PER_BATCH = 1 << 17   # (point, triangle) pairs evaluated at once: some 70 MB of temporaries


def surface_distances(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Distance (m) from each of ``points`` (n, 3) to the surface ``vertices`` (v, 3), ``faces`` (m, 3).

    Exact to float64 rounding; inf for every point when there are no faces.
    """
    points = np.asarray(points, dtype=np.float64)
    tris = np.asarray(vertices, dtype=np.float64)[np.asarray(faces)]
    out = np.full(len(points), np.inf)
    if not len(tris) or not len(points):
        return out
    grid = _Grid(tris, points)
    pending = np.arange(len(points))
    lo = hi = grid.cell(points[:, :2])
    while len(pending):
        p = points[pending]
        out[pending] = np.minimum(out[pending], grid.nearest(p, lo, hi))
        d = out[pending][:, None]
        need_lo, need_hi = grid.cell(p[:, :2] - d), grid.cell(p[:, :2] + d)   # inf: the whole grid
        done = ((need_lo >= lo) & (need_hi <= hi)).all(axis=1)
        grow = hi - lo + 1
        found = np.isfinite(d[:, 0])[:, None]
        lo = np.where(found, need_lo, lo - grow)[~done]
        hi = np.where(found, need_hi, hi + grow)[~done]
        pending = pending[~done]
    return out


class _Grid:
    """Triangles (m, 3, 3) binned by bounding box on a uniform (x, y) grid covering them and the points."""

    def __init__(self, tris: np.ndarray, points: np.ndarray):
        self.tris = _Triangles(tris)
        self.lo = np.minimum(tris[:, :, :2].min(axis=(0, 1)), points[:, :2].min(axis=0))
        hi = np.maximum(tris[:, :, :2].max(axis=(0, 1)), points[:, :2].max(axis=0))
        # cells the size of a typical triangle (fewest pairs on LiDAR and building meshes), at most 16 per triangle
        size = (tris[:, :, :2].max(axis=1) - tris[:, :, :2].min(axis=1)).max(axis=1)
        self.step = max(float(np.median(size)), float((hi - self.lo).max()) / (4 * np.sqrt(len(tris))), 1e-6)
        self.shape = np.floor((hi - self.lo) / self.step).astype(np.int64) + 1          # (nx, ny)
        c0, c1 = self.cell(tris[:, :, :2].min(axis=1)), self.cell(tris[:, :, :2].max(axis=1))
        tri, cx, cy = _cells_of_rectangles(c0, c1)
        cell = cy * self.shape[0] + cx
        self.cell_tris = tri[np.argsort(cell, kind="stable")]                  # triangle ids, cell by cell
        self.start = np.concatenate([[0], np.cumsum(np.bincount(cell, minlength=int(self.shape.prod())))])

    def cell(self, xy: np.ndarray) -> np.ndarray:
        """(ix, iy) of the cells holding ``xy`` (k, 2), clamped to the grid (also for ±inf)."""
        index = np.floor(np.clip((xy - self.lo) / self.step, 0.0, self.shape - 1))
        return index.astype(np.int64)

    def nearest(self, points: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """Per point, its distance to the nearest triangle in cells ``lo``..``hi`` (k, 2), inf if none."""
        lo, hi = np.maximum(lo, 0), np.minimum(hi, self.shape - 1)
        # each rectangle as rows of cells: a row is one contiguous run of cell_tris
        point, k = _ranges(hi[:, 1] - lo[:, 1] + 1)
        row_lo = (lo[point, 1] + k) * self.shape[0] + lo[point, 0]
        first, last = self.start[row_lo], self.start[row_lo + hi[point, 0] - lo[point, 0] + 1]
        out = np.full(len(points), np.inf)
        for a, b in _batches(np.cumsum(last - first), PAIRS_PER_BATCH):
            run, k = _ranges(last[a:b] - first[a:b])
            if not len(run):
                continue
            pair_point = point[a:b][run]                                        # grouped by point
            d = self.tris.distances(points[pair_point], self.cell_tris[first[a:b][run] + k])
            starts = np.flatnonzero(np.r_[True, pair_point[1:] != pair_point[:-1]])
            ids = pair_point[starts]
            out[ids] = np.minimum(out[ids], np.minimum.reduceat(d, starts))
        return out


def _cells_of_rectangles(c0: np.ndarray, c1: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(rectangle id, ix, iy) of every cell of the cell rectangles ``c0``..``c1`` (k, 2), in rectangle
    order, x running fastest."""
    span = c1 - c0 + 1
    rect, k = _ranges(span[:, 0] * span[:, 1])
    return rect, c0[rect, 0] + k % span[rect, 0], c0[rect, 1] + k // span[rect, 0]


def _ranges(counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(i, k) for k in range(counts[i]) for every i, as two flat arrays."""
    owner = np.repeat(np.arange(len(counts)), counts)
    return owner, np.arange(len(owner)) - np.repeat(np.cumsum(counts) - counts, counts)


def _batches(ends: np.ndarray, size: int) -> list[tuple[int, int]]:
    """Index ranges of runs whose pair counts (cumulative ``ends``) come to about ``size`` each."""
    cut = np.flatnonzero(np.diff(ends // size)) + 1
    bounds = [0, *cut.tolist(), len(ends)]
    return [(a, b) for a, b in zip(bounds, bounds[1:]) if b > a]


class _Triangles:
    """Per-triangle terms of the point distance, computed once: corners, edges, the unit normal
    and the in-plane inward edge normals."""

    def __init__(self, tris: np.ndarray):
        self.starts = tris                                               # (m, 3, 3): a, b, c
        self.edges = tris[:, [1, 2, 0]] - tris                           # ab, bc, ca
        n = np.cross(self.edges[:, 0], -self.edges[:, 2])
        nn = np.einsum("ij,ij->i", n, n)
        self.flat = nn > 0                                               # degenerate ones: edges only
        self.unit = n / np.sqrt(np.where(self.flat, nn, 1.0))[:, None]
        self.inward = np.cross(n[:, None, :], self.edges)               # (p - start)·inward >= 0 inside
        length2 = np.einsum("ijk,ijk->ij", self.edges, self.edges)
        self.inv_length2 = 1.0 / np.where(length2 > 0, length2, 1.0)

    def distances(self, p: np.ndarray, t: np.ndarray) -> np.ndarray:
        """Distance from points ``p`` (k, 3) to triangles ``t`` (k,), row by row: to the plane where the
        point projects inside the triangle, else to the nearest edge."""
        rel = p[:, None, :] - self.starts[t]                              # p - a, p - b, p - c
        edges = self.edges[t]
        inside = self.flat[t] & (np.einsum("ijk,ijk->ij", rel, self.inward[t]) >= 0).all(axis=1)
        along = np.clip(np.einsum("ijk,ijk->ij", rel, edges) * self.inv_length2[t], 0.0, 1.0)
        off = rel - along[:, :, None] * edges
        edge = np.sqrt(np.einsum("ijk,ijk->ij", off, off).min(axis=1))
        plane = np.abs(np.einsum("ij,ij->i", rel[:, 0], self.unit[t]))
        return np.where(inside, plane, edge)
