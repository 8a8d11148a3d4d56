"""The scene's extent before ingest, where it is cheap to know: for the work estimate at parse time.

Per district, in this order: the chunk index of a previous ingest that is newer than the input
(the union of its chunks' bounds, exact), or an OBJ file's vertex lines (up to
:data:`OBJ_SCAN_BYTES`, with the input's offset and CRS applied to the box's corners). Any other
district makes the extent unknown at parse time; the terrain job then checks the estimate with
every chunk's bounds, before any grid, plan or tile is made.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import numpy as np

OBJ_SCAN_BYTES = 256 * 2 ** 20     # an OBJ larger than this is not scanned at parse time
_VERTEX = re.compile(rb"^v[ \t]+(\S+)[ \t]+(\S+)[ \t]+(\S+)", re.M)


def cheap_extent(config: dict[str, Any], results: str | Path,
                 base_dir: Path = Path(".")) -> tuple[np.ndarray, str] | None:
    """((2, 3) scene extent, where it was read) from every district, or None when one is not cheap."""
    boxes, sources = [], set()
    for name, spec in config["inputs"].items():
        found = _ingested(Path(results) / "chunks" / name / "index.json", base_dir / spec["path"])
        if found is not None:
            boxes.append(found)
            sources.add("the previous ingest")
            continue
        found = _obj_box(spec, base_dir / spec["path"], config["crs"])
        if found is None:
            return None
        boxes.append(found)
        sources.add("the OBJ vertices")
    lo = np.min([b[0] for b in boxes], axis=0)
    hi = np.max([b[1] for b in boxes], axis=0)
    return np.array([lo, hi]), " and ".join(sorted(sources))


def _ingested(index: Path, source: Path) -> np.ndarray | None:
    """The union of a chunk index's chunk bounds, if the index is newer than its input."""
    try:
        if index.stat().st_mtime_ns < source.stat().st_mtime_ns:
            return None
        bounds = np.array([c["bounds"] for c in json.loads(index.read_text())["chunks"].values()], dtype=np.float64)
    except (OSError, ValueError, KeyError, TypeError):
        return None
    if bounds.ndim != 3 or not len(bounds) or not np.isfinite(bounds).all():
        return None
    return np.array([bounds[:, 0].min(axis=0), bounds[:, 1].max(axis=0)])


def _obj_box(spec: dict[str, Any], path: Path, scene_crs: str) -> np.ndarray | None:
    """The box of an OBJ's vertices in the scene CRS, or None (not an OBJ, too large, unreadable)."""
    fmt = spec.get("format", "auto")
    if fmt not in ("auto", "obj") or (fmt == "auto" and path.suffix.lower() != ".obj") or "metadata" in spec:
        return None
    try:
        if not path.is_file() or path.stat().st_size > OBJ_SCAN_BYTES:
            return None
        verts = np.array(_VERTEX.findall(path.read_bytes()), dtype=np.float64)
    except (OSError, ValueError):
        return None
    if verts.ndim != 2 or not len(verts) or not np.isfinite(verts).all():
        return None
    verts = verts + np.asarray(spec.get("offset", [0.0, 0.0, 0.0]), dtype=np.float64)
    lo, hi = verts.min(axis=0), verts.max(axis=0)
    if spec.get("crs", scene_crs) != scene_crs:
        from pipeline25d.core.crs import transform_points
        from pipeline25d.core.errors import CRSError

        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        try:
            corners = transform_points(corners, spec["crs"], scene_crs)
        except CRSError:
            return None
        lo, hi = corners.min(axis=0), corners.max(axis=0)
    return np.array([lo, hi])
