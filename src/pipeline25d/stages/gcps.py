"""Ground control points: candidate rows, check-point hold-out, image positions.

Candidates sit on exposed ground (see :mod:`pipeline25d.stages.gcp_sites`) or come from a user
table; a share is held out (deterministically, by seed) as check points that never enter
the warp or its choice. In each tile render, markers are drawn with the model (see
:mod:`pipeline25d.stages.render`); a marker seen whole and lying on the model's surface gives
the GCP's sub-pixel image position in the perspective's grid.
"""

from __future__ import annotations

import csv
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from pipeline25d.core.atomic import atomic_path
from pipeline25d.stages.records import GcpCandidate, Observation

CANDIDATE_FIELDS = list(GcpCandidate.FIELDS)     # the columns of the candidates' table
OBSERVATION_FIELDS = list(Observation.FIELDS)    # ... and of the observations' tables


def candidates_from_sites(sites: dict[str, np.ndarray], holdout: float, seed: int) -> list[GcpCandidate]:
    """Candidate rows from :func:`pipeline25d.stages.gcp_sites.select_sites`, with roles.

    Ids name the candidate's spacing square (``g<col>_<row>``), so a candidate keeps its id,
    and its role, when a district elsewhere changes; values are rounded to 1 mm (slopes to
    1e-4), so float noise in the terrain does not re-render the tiles that hold them.
    """
    rows = []
    for i in range(len(sites["x"])):
        values = {k: round(float(sites[k][i]), 3) for k in ("x", "y", "z", "ground")}
        values.update({k: round(float(sites[k][i]), 4) for k in ("sx", "sy")})
        rows.append({"id": square_id(sites["square_col"][i], sites["square_row"][i]), **values})
    return assign_roles(rows, holdout, seed)


def square_id(col: int, row: int) -> str:
    """The id of the automatic candidate of spacing square (``col``, ``row``)."""
    return f"g{int(col)}_{int(row)}"


def is_check(pid: str, holdout: float, seed: int) -> bool:
    """Whether the point ``pid`` is a check point: a draw from a hash of (seed, id) below ``holdout``."""
    import hashlib

    digest = hashlib.sha256(f"{seed}:{pid}".encode()).digest()
    return int.from_bytes(digest[:8], "big") / 2 ** 64 < holdout


def check_squares(holdout: float, seed: int) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    """Which spacing squares (arrays of cols, rows) hold check points: the roles
    :func:`candidates_from_sites` gives, known before any site is chosen (see
    :func:`pipeline25d.stages.gcp_sites.select_sites`)."""
    def checks(cols: np.ndarray, rows: np.ndarray) -> np.ndarray:
        squares, at = np.unique(np.column_stack([cols, rows]).astype(np.int64).reshape(-1, 2), axis=0,
                                return_inverse=True)        # each square drawn once, not once per option
        drawn = np.array([is_check(square_id(c, r), holdout, seed) for c, r in squares], dtype=bool)
        return drawn[at.reshape(-1)]

    return checks


def assign_roles(points: list[dict], holdout: float, seed: int) -> list[GcpCandidate]:
    """Candidates of ``points`` (id, x, y, z, ground, sx, sy): a ``holdout`` share as 'check', the rest 'gcp'.

    The draw is a hash of (seed, id) (:func:`is_check`), so each point's role is stable: adding or
    removing other points never turns a check point into a GCP or back.
    """
    return [GcpCandidate.from_row({**p, "role": "check" if is_check(str(p["id"]), holdout, seed) else "gcp"})
            for p in points]


def write_csv(path: str | Path, rows: Sequence[GcpCandidate], fields: list[str]) -> None:
    """GCP records as a CSV table of ``fields`` (CANDIDATE_FIELDS or OBSERVATION_FIELDS), atomically."""
    with atomic_path(path) as tmp:
        with open(tmp, "w", newline="") as fh:
            writer = csv.DictWriter(fh, fieldnames=fields, extrasaction="ignore")
            writer.writeheader()
            writer.writerows(r.to_row() for r in rows)


def read_candidates(path: str | Path) -> list[GcpCandidate]:
    """The candidates' table (:func:`write_csv` with CANDIDATE_FIELDS)."""
    return [GcpCandidate.from_row(r) for r in _rows(path)]


def read_observations(path: str | Path) -> list[Observation]:
    """An observations' table (a tile's, or a perspective's)."""
    return [Observation.from_row(r) for r in _rows(path)]


def _rows(path: str | Path) -> list[dict]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def read_csv(path: str | Path) -> list[dict]:
    """A user's table of points (id, x, y, z ...) as rows, numeric columns as float (id and role stay text)."""
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    for row in rows:
        for key in row:
            if key not in ("id", "role"):
                row[key] = float(row[key]) if row[key] not in ("", None) else 0.0
    return rows


def observations(candidates: Sequence[GcpCandidate], full: np.ndarray, sums: np.ndarray,
                 top_left: tuple[float, float], gsd: float) -> list[Observation]:
    """GCPs whose marker is seen whole and lies on the model's surface, with its centroid as map coordinates.

    ``full``: pixels per marker alone; ``sums``: (count, Σcol, Σrow, agree) with the model drawn
    (pixel centres at +0.5, row 0 at the top); ``top_left``: map (x, y) of the render's
    top-left corner. Map coordinates, not pixels, so tiles and mosaics need not share an
    origin.
    """
    out = []
    for cand, n_full, (n, scol, srow, agree) in zip(candidates, full, sums):
        if n_full > 0 and n == n_full and agree == n_full:
            out.append(Observation(**cand.to_row(), map_x=top_left[0] + scol / n * gsd,
                                   map_y=top_left[1] - srow / n * gsd, n_pixels=int(n)))
    return out


def gather_gcps(tile_csvs: list[str], out_csv: str | Path) -> list[Observation]:
    """A perspective's observations: its tiles' tables in one, by id."""
    rows = [r for p in tile_csvs for r in read_observations(p)]
    rows.sort(key=lambda r: r.id)
    write_csv(out_csv, rows, OBSERVATION_FIELDS)
    return rows
