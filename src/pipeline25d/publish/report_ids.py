"""The report's object-id section: per map, how its id map agrees with it and what it weighs.

Read from the id map's figures (``work/ids/<id>.json``, :func:`pipeline25d.stages.maps.ids.id_map` in the warp job):
opaque map pixels without an id and transparent ones with an id (both counted over the whole
map after the id map was made), the edge pixels the id map was held to the map at, and the id
map's bytes against the map's.
"""

from __future__ import annotations

import json
from pathlib import Path

FIELDS = ("opaque_px", "opaque_without_id", "transparent_with_id", "filled", "cleared", "ids_bytes", "map_bytes")


def id_layer(results: Path, pid: str) -> dict | None:
    """The id map's figures of perspective ``pid``; None where no id map was made (objects off)."""
    path = results / "work" / "ids" / f"{pid}.json"
    if not path.is_file():
        return None
    stats = json.loads(path.read_text())
    return {k: stats[k] for k in FIELDS}


def ids_section(perspectives: list[dict]) -> list[str]:
    """Markdown lines of the id maps' agreement and sizes; [] where no perspective has one."""
    rows = [(p["id"], p["ids"]) for p in perspectives if p.get("ids")]
    if not rows:
        return []
    lines = ["", "## Object ids", "",
             "Each map's id map (`maps/<id>.ids.tif`) says which input object every pixel shows. Counted over"
             " the whole map: opaque pixels without an id and transparent pixels with one (both 0 when the id"
             " map agrees with the map), the edge pixels it was held to the map at, and its size.", "",
             "| perspective | opaque px | opaque without id | transparent with id | edge fixes | id map MB | map MB |"
             " ids : map |",
             "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for pid, s in rows:
        ratio = s["ids_bytes"] / s["map_bytes"] if s["map_bytes"] else float("nan")
        lines.append(f"| {pid} | {s['opaque_px']} | {s['opaque_without_id']} | {s['transparent_with_id']} | "
                     f"{s['filled'] + s['cleared']} | {s['ids_bytes'] / 1e6:.3f} | {s['map_bytes'] / 1e6:.3f} | "
                     f"{ratio:.2f} |")
    return lines
