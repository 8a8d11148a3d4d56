"""The scene's extent before ingest, where it is cheap to know: for the work estimate at parse time.

Per district, in this order: the chunk index of a previous ingest that is newer than the input
(the union of its chunks' bounds, exact), or the input's own box where its format makes that
cheap (:func:`pipeline25d.formats.boxes.input_box`: OBJ, PLY and CityJSON vertices, the CityGML
envelope, a tileset's root bounding volume, an OSGB dataset's end tiles), its corners taken to
the scene CRS. Any other district makes the extent unknown at parse time; the terrain job then
checks the estimate with every chunk's bounds, before any grid, plan or tile is made.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from pipeline25d.formats.boxes import input_box


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
        box = input_box(spec, base_dir)
        found = None if box is None else _in_scene(box.corners, box.crs, config["crs"])
        if found is None:
            return None
        if not box.heights:             # its footprint only: flat at mid-height (the terrain job knows more)
            found[:, 2] = found[:, 2].mean()
        boxes.append(found)
        sources.add(box.source)
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


def _in_scene(box: np.ndarray, crs: str | None, scene_crs: str) -> np.ndarray | None:
    """The scene-CRS box around ``box``'s corners and edge midpoints in ``crs`` (None: the scene's)."""
    if crs is None:
        return box
    from pipeline25d.core.crs import transform_points
    from pipeline25d.core.errors import CRSError

    (x0, y0, z0), (x1, y1, z1) = box
    points = np.array([[x, y, z] for x in np.linspace(x0, x1, 3) for y in np.linspace(y0, y1, 3) for z in (z0, z1)])
    try:
        points = transform_points(points, crs, scene_crs)
    except CRSError:
        return None
    return np.array([points.min(axis=0), points.max(axis=0)])
