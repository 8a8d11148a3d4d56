"""``pipeline25d heights MAPS_DIR --footprints FILE``: heights of footprints' roofs on a scene's maps."""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np

from pipeline25d.analysis.evaluate.rasters import _open
from pipeline25d.analysis.heights.reference import compare, read_reference
from pipeline25d.analysis.heights.results import NADIR_ID, MatchSettings, find_maps, write_csv
from pipeline25d.analysis.heights.views import measure_heights
from pipeline25d.core.errors import InputFileError, Pipeline25dError
from pipeline25d.core.raster import dataset_bounds
from pipeline25d.formats.footprints import read_footprints

log = logging.getLogger(__name__)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="pipeline25d heights", description=__doc__.split("\n\n")[0])
    parser.add_argument("maps_dir", metavar="MAPS_DIR", help="folder with az000_el90.tif and oblique <id>.tif maps")
    parser.add_argument("--footprints", required=True, help="footprint polygons (any OGR vector file)")
    parser.add_argument("--layer", help="layer name (default: the first polygon layer)")
    parser.add_argument("--id-field", help="attribute holding the building id (default: the feature id)")
    parser.add_argument("--out", default="heights.csv", help="output CSV (default: heights.csv)")
    parser.add_argument("--reference", help="CSV with columns id,height: error statistics against it")
    parser.add_argument("--json", nargs="?", const="-", metavar="PATH",
                        help="statistics as JSON: to PATH, or to stdout (instead of the text lines) without one")
    parser.add_argument("--max-height", type=float, default=MatchSettings.max_height,
                        help="highest building searched for (m, default %(default)g)")
    parser.add_argument("--ring", type=int, default=MatchSettings.ring_px,
                        help="ring width outside the footprint (px, default %(default)d)")
    return parser


def run(maps_dir: str | Path, footprints: str | Path, out: str | Path, layer: str | None = None,
        id_field: str | None = None, reference: str | Path | None = None,
        settings: MatchSettings | None = None) -> dict[str, Any]:
    """Measure every footprint on the maps in ``maps_dir``, write the CSV ``out`` (atomically).

    Returns counts (per view too) and, with a ``reference`` CSV (id,height), its error
    statistics (see :func:`compare`). Raises InputFileError naming the file for a missing or
    unreadable input, footprints that do not overlap the maps (a CRS mismatch, typically).
    """
    maps = find_maps(maps_dir)
    nad = _open(maps[NADIR_ID])
    fps = read_footprints(footprints, layer, id_field, crs=nad.GetProjection() or None)
    if not fps:
        raise InputFileError(footprints, "no footprint polygons")
    ext = dataset_bounds(nad)
    if not any(b[0] < ext[2] and b[2] > ext[0] and b[1] < ext[3] and b[3] > ext[1] for b in (f.bounds for f in fps)):
        raise InputFileError(footprints, "no footprint overlaps the maps (extent "
                             f"{tuple(round(v, 1) for v in ext)}); is the layer in the maps' CRS?")
    ref = read_reference(reference) if reference else None
    s = settings or MatchSettings()
    rows = measure_heights({k: str(v) for k, v in maps.items()}, fps, settings=s)
    write_csv(out, rows)
    views = sorted({k for r in rows for k in r.heights})
    stats: dict[str, Any] = {
        "maps": str(maps_dir), "footprints": str(footprints), "out": str(out),
        "n_footprints": len(rows), "n_measured": sum(1 for r in rows if np.isfinite(r.height)),
        "n_measured_per_view": {v: sum(1 for r in rows if np.isfinite(r.heights.get(v, math.nan))) for v in views},
        "settings": dict(s.__dict__)}
    if ref is not None:
        stats["reference"] = {"path": str(reference), **compare(rows, ref)}
    return stats


def summary_lines(stats: dict[str, Any]) -> list[str]:
    """Human-readable lines of :func:`run`'s statistics."""
    lines = [f"{stats['n_footprints']} footprints, {stats['n_measured']} measured -> {stats['out']}"]
    ref = stats.get("reference")
    if ref:
        for key in ["combined"] + [k for k in ref if k.startswith("az")]:
            st = ref[key]
            if st["n"]:
                lines.append(f"{key}: n {st['n']}, bias {st['bias']:+.3f} m, rmsd {st['rmsd']:.3f} m, "
                             f"median |err| {st['median_abs']:.3f} m, p90 {st['p90_abs']:.3f} m, "
                             f"within 0.5 m {st['within_0.5m']:.1%}")
            else:
                lines.append(f"{key}: n 0 (no measured building in the reference)")
    return lines


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    try:
        stats = run(args.maps_dir, args.footprints, args.out, args.layer, args.id_field, args.reference,
                    MatchSettings(max_height=args.max_height, ring_px=args.ring))
    except (Pipeline25dError, RuntimeError) as exc:
        print(f"heights: error: {exc}", file=sys.stderr)
        return 1
    if args.json == "-":
        print(json.dumps(stats, indent=1))
    else:
        print("\n".join(summary_lines(stats)), flush=True)
        if args.json:
            from pipeline25d.core.atomic import write_json

            write_json(args.json, stats)
    return 0
