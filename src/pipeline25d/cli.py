"""Command line: ``python -m pipeline25d <command>`` (the LOD and render rules use it)."""

from __future__ import annotations

import argparse
import logging
import sys

from .errors import Pipeline25dError


def _lod(args) -> None:
    from .stages import build_lod

    build_lod(args.chunk_index, args.out_index, args.max_error, args.max_levels)


def _render_block(args) -> None:
    from .stages import render_block

    render_block(args.plan, args.block_id, args.block, args.lod_dir, args.tiles_dir, args.out_manifest)


def _demo_city(args) -> None:
    from .demo import main as demo_main

    argv = [args.out_dir, "--seed", str(args.seed), "--buildings", str(args.buildings), "--scale", str(args.scale)]
    sys.exit(demo_main(argv))


def _web_tiles(args) -> None:
    from .web_tiles import tms

    print(tms(args.map, args.zoom, args.out_dir, args.processes, args.format, args.quality, args.work))


def _gl_info(args) -> None:
    from .render import create_context, renderer_info

    ctx = create_context()
    for key, value in renderer_info(ctx).items():
        print(f"{key}: {value}")


def _measure(args) -> None:
    import numpy as np

    from .errors import MeasureError
    from .measure import describe, open_map, pixel_to_map

    try:
        points = np.array([[float(v) for v in text.split(",")] for text in args.points], dtype=np.float64)
    except ValueError:
        points = np.zeros((0, 3))
    if points.ndim != 2 or points.shape[1] != 2:
        raise MeasureError(f"points must be X,Y pairs such as 691057.2,5334063.8; got {' '.join(args.points)}")
    info = open_map(args.map)
    print(describe(info, args.kind, pixel_to_map(info, points) if args.pixel else points))


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="pipeline25d", description=__doc__)
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("demo-city", help="generate the built-in demo city")
    p.add_argument("out_dir")
    p.add_argument("--seed", type=int, default=7)
    p.add_argument("--buildings", type=int, default=320)
    p.add_argument("--scale", type=float, default=1.0)
    p.set_defaults(func=_demo_city)

    p = sub.add_parser("lod", help="build the LOD pyramids of one district's chunks")
    p.add_argument("chunk_index", help="the district's ingest index.json (its chunk npz files beside it)")
    p.add_argument("out_index", help="the LOD index.json to write; the chunks' LOD npz files go beside it")
    p.add_argument("--max-error", type=float, required=True, help="metres")
    p.add_argument("--max-levels", type=int, default=6)
    p.set_defaults(func=_lod)

    p = sub.add_parser("render-block", help="render one block of tiles of a perspective's plan")
    p.add_argument("--plan", required=True)
    p.add_argument("--block-id", required=True, help="<level>_<row>_<col>, see plan.plan_blocks")
    p.add_argument("--block", type=int, required=True, help="render.block: a dense job's tiles per side")
    p.add_argument("--lod-dir", required=True)
    p.add_argument("--tiles-dir", required=True, help="where the tiles' files go")
    p.add_argument("--out-manifest", required=True)
    p.add_argument("--spec-hash", help="ignored; in the command so Snakemake re-runs when a tile's spec changes")
    p.set_defaults(func=_render_block)

    p = sub.add_parser("measure", help="measure a height, a ground length or a facade area on a map",
                       description="Heights: base and top of a vertical edge; lengths: ground points; "
                                   "facade: a polygon on one facade whose first edge is horizontal (see pipeline25d.measure).")
    p.add_argument("map", help="a perspective's map, results/<scene>/maps/<id>.tif")
    p.add_argument("kind", choices=["height", "length", "facade"])
    p.add_argument("points", nargs="+", metavar="X,Y", help="map CRS coordinates (or pixel column,row with --pixel)")
    p.add_argument("--pixel", action="store_true", help="points are pixel (column,row) of the map, GDAL's convention")
    p.set_defaults(func=_measure)

    p = sub.add_parser("web-tiles", help="cut (or update) the XYZ web-tile pyramid of a map, as the tms rule does")
    p.add_argument("map", help="a perspective's map, results/<scene>/maps/<id>.tif")
    p.add_argument("out_dir", help="the published pyramid")
    p.add_argument("--work", help="where the pyramid is kept between runs (then only what changed is cut again)")
    p.add_argument("--zoom", default="auto", help="auto or min-max")
    p.add_argument("--format", choices=["webp", "png"], default="webp")
    p.add_argument("--quality", type=int, default=85)
    p.add_argument("--processes", type=int, default=1)
    p.set_defaults(func=_web_tiles)

    p = sub.add_parser("gl-info", help="print the OpenGL renderer EGL gives us")
    p.set_defaults(func=_gl_info)
    return parser


def main(argv: list[str] | None = None) -> int:
    from .logsetup import exit_on_sigterm

    args = build_parser().parse_args(argv)
    exit_on_sigterm()
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    try:
        args.func(args)
    except Pipeline25dError as exc:
        print(f"pipeline25d: error: {exc}", file=sys.stderr)
        return 1
    return 0
