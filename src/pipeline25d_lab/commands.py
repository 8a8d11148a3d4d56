"""The lab's commands for ``pipeline25d`` (entry-point group ``pipeline25d.commands``): generated scenes.

``pipeline25d demo [OUT]`` writes the demo city (default ``resources/demo``, what
``config/config.yaml`` reads); ``pipeline25d sample KIND OUT`` writes another generated scene:
``rugged`` (steep terrain), ``roofs`` (steep terrain, flat, gabled and hipped roofs), ``citygml`` (a
textured LOD2 city), ``themed`` (a small city with two appearance themes as CityJSON and CityGML),
``osgb`` (a ContextCapture-like dataset), ``oap3d`` (a textured photogrammetry city as OSGB and 3D
Tiles, up to the paper's Dataset 2 footprint) or
``badinputs`` (the hostile-input corpus).
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from importlib import import_module

SAMPLES = {
    "rugged": "pipeline25d_lab.scenes.rugged",
    "roofs": "pipeline25d_lab.scenes.roofs_city",
    "citygml": "pipeline25d_lab.scenes.citygml_city",
    "themed": "pipeline25d_lab.scenes.themed_city",
    "osgb": "pipeline25d_lab.scenes.osgb_sample",
    "oap3d": "pipeline25d_lab.scenes.oap3d",
    "badinputs": "pipeline25d_lab.scenes.badinputs",
}


def demo(argv: Sequence[str]) -> int:
    """``pipeline25d demo [OUT] [--seed N] [--buildings N] [--scale F]``."""
    from pipeline25d_lab.scenes.demo import main

    argv = list(argv)
    if not argv or argv[0].startswith("-") and argv[0] not in ("-h", "--help"):
        argv = ["resources/demo", *argv]
    return main(argv, prog="pipeline25d demo")


def sample(argv: Sequence[str]) -> int:
    """``pipeline25d sample KIND OUT [options of that generator]``."""
    parser = argparse.ArgumentParser(prog="pipeline25d sample", description=__doc__.split("\n\n")[1])
    parser.add_argument("kind", choices=sorted(SAMPLES))
    parser.add_argument("args", nargs=argparse.REMAINDER, help="the generator's own arguments (KIND --help lists them)")
    args = parser.parse_args(argv)
    return import_module(SAMPLES[args.kind]).main(args.args, prog=f"pipeline25d sample {args.kind}")
