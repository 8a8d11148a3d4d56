"""Ground control points: candidates on the terrain, check-point hold-out, image positions.

Candidates lie on a regular grid over the scene with heights from the terrain; a share
is held out (deterministically, by seed) as check points that never enter the warp. In
each tile render, markers are drawn with the model (see :mod:`pipeline25d.render`); a
marker seen whole gives the GCP's sub-pixel image position in the perspective's grid.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from .atomic import atomic_path

CANDIDATE_FIELDS = ["id", "x", "y", "z", "role"]
OBSERVATION_FIELDS = CANDIDATE_FIELDS + ["map_x", "map_y", "n_pixels"]


def grid_candidates(bounds_xy: tuple[float, float, float, float], spacing: float, height_fn,
                    holdout: float, seed: int) -> list[dict]:
    """Candidates every ``spacing`` metres inside bounds, z = height_fn(x, y); NaN heights dropped."""
    xmin, ymin, xmax, ymax = bounds_xy
    xs = np.arange(np.ceil(xmin / spacing) * spacing + spacing / 2, xmax, spacing)
    ys = np.arange(np.ceil(ymin / spacing) * spacing + spacing / 2, ymax, spacing)
    gx, gy = np.meshgrid(xs, ys)
    x, y = gx.ravel(), gy.ravel()
    z = np.asarray(height_fn(x, y), dtype=np.float64)
    keep = np.isfinite(z)
    return assign_roles([{"id": f"g{i:06d}", "x": float(a), "y": float(b), "z": float(c)}
                         for i, (a, b, c) in enumerate(zip(x[keep], y[keep], z[keep]))], holdout, seed)


def assign_roles(points: list[dict], holdout: float, seed: int) -> list[dict]:
    """Mark round(holdout·n) points, drawn with ``seed``, as 'check'; the rest 'gcp'."""
    rng = np.random.default_rng(seed)
    n_check = int(round(holdout * len(points)))
    check = set(rng.permutation(len(points))[:n_check].tolist())
    return [{**p, "role": "check" if i in check else "gcp"} for i, p in enumerate(points)]


def write_csv(path: str | Path, rows: list[dict], fields: list[str]) -> None:
    with atomic_path(path) as tmp:
        with open(tmp, "w", newline="") as fh:
            writer = csv.DictWriter(fh, fieldnames=fields, extrasaction="ignore")
            writer.writeheader()
            writer.writerows(rows)


def read_csv(path: str | Path) -> list[dict]:
    """Rows with numeric columns as float (id and role stay text)."""
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    for row in rows:
        for key in row:
            if key not in ("id", "role"):
                row[key] = float(row[key])
    return rows


def observations(candidates: list[dict], full: np.ndarray, sums: np.ndarray,
                 top_left: tuple[float, float], gsd: float) -> list[dict]:
    """GCPs whose marker is seen whole and lies on model surface, with its centroid as map coordinates.

    ``full``: pixels per marker alone; ``sums``: (count, Σcol, Σrow, on_model) with the model drawn
    (pixel centres at +0.5, row 0 at the top); ``top_left``: map (x, y) of the render's
    top-left corner. Map coordinates, not pixels, so tiles and mosaics need not share an
    origin.
    """
    out = []
    for cand, n_full, (n, scol, srow, on_model) in zip(candidates, full, sums):
        if n_full > 0 and n == n_full and on_model == n:
            out.append({**cand, "map_x": top_left[0] + scol / n * gsd, "map_y": top_left[1] - srow / n * gsd,
                        "n_pixels": int(n)})
    return out
