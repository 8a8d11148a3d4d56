"""``pipeline25d evaluate ground OBLIQUE.tif [...] NADIR.tif``: ground offsets of oblique maps against the nadir map."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from pipeline25d.analysis.evaluate.offsets import ground_offsets
from pipeline25d.analysis.evaluate.rasters import _open
from pipeline25d.analysis.evaluate.visibility import GroundModel
from pipeline25d.core.errors import Pipeline25dError

log = logging.getLogger(__name__)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="pipeline25d evaluate", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("ground", help="ground offsets of oblique maps against the nadir map (image correlation)")
    p.add_argument("maps", nargs="+", metavar="MAP.tif", help="one or more oblique maps, then the nadir map last")
    p.add_argument("--dsm", help="surface model GeoTIFF (with --dtm: only ground the view sees is used)")
    p.add_argument("--dtm", help="terrain model GeoTIFF")
    p.add_argument("--max-height", type=float, default=0.5, help="ground: DSM - DTM below this (m)")
    p.add_argument("--dilate", type=float, default=1.0, help="grow non-ground and hidden ground by this (m)")
    p.add_argument("--projection", choices=("terrain", "plane"), default="terrain",
                   help="how the maps were projected: heights above the terrain (default) or above a plane")
    p.add_argument("--clearance", type=float, default=0.2,
                   help="line of sight: a surface must rise this far above it to hide the ground (m)")
    p.add_argument("--perspective", help="view of the (single) oblique map, e.g. az045_el45 "
                                         "(default: from the file name)")
    p.add_argument("--window", type=int, default=32, help="window size (px)")
    p.add_argument("--step", type=int, default=None, help="window spacing (px, default: window)")
    p.add_argument("--min-ground-fraction", type=float, default=0.3,
                   help="share of a window's pixels that must be opaque visible ground")
    p.add_argument("--min-texture", type=float, default=4.0, help="minimum grey std of the usable pixels (0-255)")
    p.add_argument("--min-ncc", type=float, default=0.5, help="minimum NCC after alignment")
    p.add_argument("--max-peak-ratio", type=float, default=0.95, help="maximum second/first NCC peak")
    p.add_argument("--max-condition", type=float, default=25.0,
                   help="maximum condition number of the shift fit (aperture problem)")
    p.add_argument("--max-shift", type=float, default=None, help="maximum offset (px, default: window/4)")
    p.add_argument("--max-windows", type=int, default=2000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", help="write results (summary and per-window offsets) here")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    if len(args.maps) < 2:
        print("evaluate: error: give at least one oblique map and the nadir map", file=sys.stderr)
        return 2
    if bool(args.dsm) != bool(args.dtm):
        print("evaluate: error: --dsm and --dtm go together", file=sys.stderr)
        return 2
    *obliques, nadir = args.maps
    if args.perspective and len(obliques) > 1:
        print("evaluate: error: --perspective needs a single oblique map", file=sys.stderr)
        return 2
    try:
        model = None
        if args.dsm:
            model = GroundModel(args.dsm, args.dtm, args.max_height, args.dilate,
                                map_crs=_open(nadir).GetProjection() or None, projection=args.projection,
                                clearance=args.clearance)
        results = {}
        for path in obliques:
            if Path(path).resolve() == Path(nadir).resolve():
                continue
            res = ground_offsets(path, nadir, model, window_px=args.window, step_px=args.step,
                                 min_texture=args.min_texture, max_windows=args.max_windows, seed=args.seed,
                                 min_ncc=args.min_ncc, max_peak_ratio=args.max_peak_ratio,
                                 max_shift_px=args.max_shift, min_ground_fraction=args.min_ground_fraction,
                                 max_condition=args.max_condition, perspective=args.perspective)
            key = res.name if res.name not in results else path
            results[key] = res
            print(res.summary_line(), flush=True)
    except (Pipeline25dError, RuntimeError) as exc:
        print(f"evaluate: error: {exc}", file=sys.stderr)
        return 1
    if args.json:
        from pipeline25d.core.atomic import write_json

        write_json(args.json, {"nadir": nadir, "dsm": args.dsm, "dtm": args.dtm,
                               "maps": {k: r.to_dict() for k, r in results.items()}})
    return 0
