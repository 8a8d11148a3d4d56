"""What sun shadows cost: a plan's tiles rendered with and without shadows in one process and GL context.

``python -m pipeline25d_lab.harness.shadow_bench results/<scene>/plans/<id>.json results/<scene>/lod`` takes
a plan made with shadows, loads each tile's chunks and shadow casters once, then renders every
tile's colour pass without shadows and with them (the shadow map included), alternating, for
``--repeats`` rounds, and prints the summed seconds of each and their ratio as JSON. Uploads,
file writes and GCP markers are left out: they are the same either way.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from pipeline25d.stages.plan import read_plan
from pipeline25d.stages.render_block import ChunkCache, _block_ground, shadow_view


def measure(plan_path: str | Path, lod_dir: str | Path, repeats: int = 3) -> dict:
    """{"tiles", "plain_s", "shadows_s", "ratio", "renderer"} for the plan's tiles (see the module)."""
    from pipeline25d.stages.render import TileRenderer, TileView, create_context, renderer_info

    pl = read_plan(plan_path)
    if pl.shadows is None:
        raise SystemExit(f"{plan_path}: the plan has no shadows (shadows.enabled was off)")
    tiles = pl.tiles
    cache = ChunkCache(lod_dir, tiles)
    ground = _block_ground(pl, tiles)
    ctx = create_context()
    plain, shaded = TileRenderer(ctx, samples=tiles[0].render["samples"]), \
        TileRenderer(ctx, samples=tiles[0].render["samples"], shadows=True)
    persp = pl.perspective
    seconds = {"plain": 0.0, "shadows": 0.0}
    for tile in tiles:
        content, size = pl.content(tile)
        view = TileView(persp, pl.z0, content, tuple(tile.depth_range), size, ground, pl.camera)
        own, casters = cache.take(tile.chunks), cache.take(tile.casters)
        with plain.upload(own, view) as g_plain, shaded.upload(own, view) as g_shaded, \
                shaded.upload(casters, None) as g_casters:
            for _ in range(repeats):
                for name, run in (("plain", lambda: plain.render_color(g_plain, view)),
                                  ("shadows", lambda: shaded.render_color(g_shaded, view, shadow_view(pl, tile),
                                                                          g_casters))):
                    start = time.perf_counter()
                    run()
                    ctx.finish()
                    seconds[name] += time.perf_counter() - start
    info = renderer_info(ctx)
    ctx.release()
    return {"plan": str(plan_path), "tiles": len(tiles), "repeats": repeats,
            "casters": sum(len(t.casters) for t in tiles),
            "plain_s": round(seconds["plain"], 3), "shadows_s": round(seconds["shadows"], 3),
            "ratio": round(seconds["shadows"] / seconds["plain"], 3), "renderer": info["GL_RENDERER"]}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m pipeline25d_lab.harness.shadow_bench", description=__doc__)
    parser.add_argument("plan", help="a perspective's plan made with shadows, results/<scene>/plans/<id>.json")
    parser.add_argument("lod_dir", help="results/<scene>/lod")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)
    print(json.dumps(measure(args.plan, args.lod_dir, args.repeats), indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
