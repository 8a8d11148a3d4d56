"""The ``pipeline25d`` command: run the workflow, and the tools that work on its maps.

``pipeline25d run CONFIG`` runs the Snakemake workflow on a scene and shows its progress;
``measure``, ``heights``, ``evaluate``, ``web-tiles``, ``serve`` and ``wms`` work on the maps
it made. Installed extensions add commands through the ``pipeline25d.commands`` entry-point
group (``pipeline25d_lab`` adds ``demo`` and ``sample``, the generated scenes).
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Callable, Sequence
from importlib import import_module
from importlib.metadata import entry_points

from pipeline25d.core.errors import Pipeline25dError

#: commands whose module has its own parser: name -> (module, help)
DELEGATED = {
    "heights": ("pipeline25d.analysis.heights.cli", "measure building heights on a scene's maps"),
    "evaluate": ("pipeline25d.analysis.evaluate.cli", "check a scene's maps against its nadir map (ground offsets)"),
    "serve": ("pipeline25d.publish.serve", "serve a results folder (viewer, PMTiles) on this machine"),
    "wms": ("pipeline25d.publish.wms", "serve a scene's WMS through MapServer on this machine"),
    "osgb-levels": ("pipeline25d.formats.osgb", "list the PagedLOD levels an OSGB dataset gives at each gsd"),
}


def _run(args, extra: list[str]) -> int:
    from pipeline25d.runner import run_workflow

    return run_workflow(args.config, jobs=args.jobs, dry_run=args.dry_run, snakemake_args=extra)


def _web_tiles(args, extra: list[str]) -> int:
    from pipeline25d.stages.tiles.web import tms

    print(tms(args.map, args.zoom, args.out_dir, args.processes, args.format, args.quality, args.work))
    return 0


def _gl_info(args, extra: list[str]) -> int:
    from pipeline25d.stages.render import create_context, renderer_info

    ctx = create_context()
    for key, value in renderer_info(ctx).items():
        print(f"{key}: {value}")
    return 0


def _measure(args, extra: list[str]) -> int:
    import numpy as np

    from pipeline25d.analysis.measure import describe, open_map, pixel_to_map
    from pipeline25d.core.errors import MeasureError

    try:
        points = np.array([[float(v) for v in text.split(",")] for text in args.points], dtype=np.float64)
    except ValueError:
        points = np.zeros((0, 3))
    if points.ndim != 2 or points.shape[1] != 2:
        raise MeasureError(f"points must be X,Y pairs such as 691057.2,5334063.8; got {' '.join(args.points)}")
    info = open_map(args.map)
    print(describe(info, args.kind, pixel_to_map(info, points) if args.pixel else points))
    return 0


def _pass_on(load_main: Callable[[], Callable[[list[str]], int]]) -> Callable:
    """A command whose arguments all go to a ``main(argv)`` that ``load_main()`` imports when it runs."""
    def call(args, extra: list[str]) -> int:
        return load_main()([*args.args, *extra])

    return call


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="pipeline25d", description=__doc__.split("\n\n")[0])
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("run", help="run the workflow on a scene (Snakemake), with progress",
                       description="Run the workflow on the scene a config describes. Options this command does "
                                   "not know go to snakemake as they are (e.g. --profile profiles/slurm, "
                                   "--forcerun heights).")
    p.add_argument("config", nargs="?", default="config/config.yaml",
                   help="the scene's config (default config/config.yaml, the demo city)")
    p.add_argument("-j", "--jobs", default="2", help="jobs at once (default 2; 'all' for every core)")
    p.add_argument("-n", "--dry-run", action="store_true", help="list the jobs the run needs, run none")
    p.set_defaults(func=_run, extra=True)

    p = sub.add_parser("measure", help="measure a height, a ground length or a facade area on a map",
                       description="Heights: base and top of a vertical edge; lengths: ground points; "
                                   "facade: a polygon on one facade whose first edge is horizontal "
                                   "(see pipeline25d.analysis.measure).")
    p.add_argument("map", help="a perspective's map, results/<scene>/maps/<id>.tif")
    p.add_argument("kind", choices=["height", "length", "facade"])
    p.add_argument("points", nargs="+", metavar="X,Y", help="map CRS coordinates (or pixel column,row with --pixel)")
    p.add_argument("--pixel", action="store_true", help="points are pixel (column,row) of the map, GDAL's convention")
    p.set_defaults(func=_measure)

    for name, (module, text) in DELEGATED.items():
        p = sub.add_parser(name, help=text, add_help=False)
        p.add_argument("args", nargs=argparse.REMAINDER)
        p.set_defaults(func=_pass_on(lambda module=module: import_module(module).main), extra=True)

    p = sub.add_parser("web-tiles", help="cut (or update) the XYZ web-tile pyramid of a map, as the tms rule does")
    p.add_argument("map", help="a perspective's map, results/<scene>/maps/<id>.tif")
    p.add_argument("out_dir", help="the published pyramid")
    p.add_argument("--work", help="where the pyramid is kept between runs (then only what changed is cut again)")
    p.add_argument("--zoom", default="auto", help="auto or min-max")
    p.add_argument("--format", choices=["webp", "png"], default="webp")
    p.add_argument("--quality", type=int, default=85)
    p.add_argument("--processes", type=int, default=1)
    p.set_defaults(func=_web_tiles)

    p = sub.add_parser("gl-info", help="print the OpenGL renderer EGL gives this machine (GPU or llvmpipe)")
    p.set_defaults(func=_gl_info)

    for entry in sorted(entry_points(group="pipeline25d.commands"), key=lambda e: e.name):
        p = sub.add_parser(entry.name, help=f"{entry.name} (from {entry.value.split(':')[0].split('.')[0]})",
                           add_help=False)
        p.add_argument("args", nargs=argparse.REMAINDER)
        p.set_defaults(func=_pass_on(entry.load), extra=True)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    from pipeline25d.core.stopping import exit_on_sigterm

    parser = build_parser()
    args, extra = parser.parse_known_args(argv)
    if extra and not getattr(args, "extra", False):
        parser.error(f"unrecognized arguments: {' '.join(extra)}")
    exit_on_sigterm()
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    try:
        return int(args.func(args, extra) or 0)
    except Pipeline25dError as exc:
        print(f"pipeline25d: error: {exc}", file=sys.stderr)
        return 1
