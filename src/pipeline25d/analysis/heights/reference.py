"""Heights to compare with: a CSV ``id,height``, a 3dfier OBJ's roofs and ground; error statistics."""

from __future__ import annotations

import csv
import io
import logging
import math
from pathlib import Path
from typing import Any

import numpy as np

from pipeline25d.analysis.heights.results import HeightRow
from pipeline25d.core.errors import InputFileError

log = logging.getLogger(__name__)


def reference_heights_from_obj(path: str | Path, roof_material: str = "Building",
                               wall_material: str = "BuildingWall", ground: str = "terrain") -> dict[str, float]:
    """Building heights from an OBJ with per-class materials (e.g. a 3dfier export), float64:
    roof − ground of :func:`obj_roof_ground` per ``o`` object."""
    return {k: roof - g for k, (roof, g) in obj_roof_ground(path, roof_material, wall_material, ground).items()}


def obj_roof_ground(path: str | Path, roof_material: str = "Building", wall_material: str = "BuildingWall",
                    ground: str = "terrain") -> dict[str, tuple[float, float]]:
    """(roof z, ground z) per ``o`` object of an OBJ with per-class materials (e.g. a 3dfier export).

    Roof = area-weighted mean z of its ``roof_material`` faces; ground = ``"terrain"``: mean z
    of its wall vertices that faces of other classes (terrain, roads) share, i.e. where the
    walls meet the model's ground (the lowest wall z where none does), or ``"lowest"``: the
    lowest z of its walls. Objects without roof and walls are left out.
    """
    if ground not in ("terrain", "lowest"):
        raise ValueError(f"ground must be 'terrain' or 'lowest', not {ground!r}")
    path = Path(path)
    if not path.exists():
        raise InputFileError(path, "no such file")
    verts: list[tuple[float, float, float]] = []
    roof_sum: dict[str, list[float]] = {}
    walls: dict[str, set[int]] = {}
    others: set[int] = set()
    obj, mtl = "", ""
    with open(path, encoding="utf-8", errors="replace") as fh:
        for lineno, line in enumerate(fh, 1):
            if line.startswith("v "):
                p = line.split()
                verts.append((float(p[1]), float(p[2]), float(p[3])))
            elif line.startswith("o "):
                obj = line[2:].strip()
            elif line.startswith("usemtl"):
                mtl = line[6:].strip()
            elif line.startswith("f "):
                try:
                    idx = [int(tok.split("/")[0]) for tok in line.split()[1:]]
                    idx = [i - 1 if i > 0 else len(verts) + i for i in idx]
                    pts = np.array([verts[i] for i in idx], dtype=np.float64)
                except (ValueError, IndexError):
                    raise InputFileError(path, f"line {lineno}: bad face {line.strip()!r}") from None
                if mtl == wall_material:
                    walls.setdefault(obj, set()).update(idx)
                elif mtl == roof_material:
                    acc = roof_sum.setdefault(obj, [0.0, 0.0])
                    for k in range(1, len(pts) - 1):
                        tri = pts[[0, k, k + 1]]
                        area = 0.5 * float(np.linalg.norm(np.cross(tri[1] - tri[0], tri[2] - tri[0])))
                        acc[0] += area * float(tri[:, 2].mean())
                        acc[1] += area
                elif not mtl.startswith(roof_material):
                    others.update(idx)
    z = np.array([v[2] for v in verts], dtype=np.float64)
    out: dict[str, tuple[float, float]] = {}
    for o, acc in roof_sum.items():
        if acc[1] <= 0 or o not in walls:
            continue
        wall = np.fromiter(walls[o], dtype=np.int64)
        foot = np.fromiter(walls[o] & others, dtype=np.int64) if ground == "terrain" else np.zeros(0, np.int64)
        out[o] = (acc[0] / acc[1], float(z[foot].mean()) if len(foot) else float(z[wall].min()))
    return out


def read_reference(path: str | Path) -> dict[str, float]:
    """{id: height} from a CSV with columns ``id`` and ``height``."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise InputFileError(path, f"cannot read: {exc.strerror or exc}") from None
    reader = csv.DictReader(io.StringIO(text))
    if not reader.fieldnames or "id" not in reader.fieldnames or "height" not in reader.fieldnames:
        raise InputFileError(path, f"needs columns 'id' and 'height', has {reader.fieldnames}")
    out = {}
    for n, row in enumerate(reader, 2):
        try:
            out[row["id"]] = float(row["height"])
        except (TypeError, ValueError):
            raise InputFileError(path, f"line {n}: height {row.get('height')!r} is not a number") from None
    return out


def error_stats(measured: np.ndarray, reference: np.ndarray) -> dict[str, float | int | None]:
    """n, bias (mean measured − reference), rmsd, median/p90 |error|, fraction within 0.5 m."""
    err = np.asarray(measured, float) - np.asarray(reference, float)
    err = err[np.isfinite(err)]
    if not len(err):
        return {"n": 0, "bias": None, "rmsd": None, "median_abs": None, "p90_abs": None, "within_0.5m": None}
    a = np.abs(err)
    return {"n": int(len(err)), "bias": round(float(err.mean()), 4),
            "rmsd": round(float(np.sqrt(np.mean(err ** 2))), 4),
            "median_abs": round(float(np.median(a)), 4), "p90_abs": round(float(np.percentile(a, 90)), 4),
            "within_0.5m": round(float(np.mean(a <= 0.5)), 4)}


def compare(rows: list[HeightRow], reference: dict[str, float]) -> dict[str, Any]:
    """Error statistics against ``reference`` heights: combined and per view."""
    by_id = {r.id: r for r in rows}
    common = [i for i in reference if i in by_id]
    ref = np.array([reference[i] for i in common])
    out: dict[str, Any] = {"n_reference": len(reference), "n_footprints_with_reference": len(common),
                           "combined": error_stats(np.array([by_id[i].height for i in common]), ref)}
    views = sorted({k for r in rows for k in r.heights})
    for v in views:
        out[v] = error_stats(np.array([by_id[i].heights.get(v, math.nan) for i in common]), ref)
    return out
