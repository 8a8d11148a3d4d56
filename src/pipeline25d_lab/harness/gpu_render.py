"""The render stage's throughput on whatever EGL gives (a GPU where lent, llvmpipe otherwise).

A generated textured city block (a heightfield of box buildings on rolling ground, one JPEG atlas
with detail at every scale, ``--triangles`` triangles) is uploaded once and rendered as the render
jobs do: nadir plus eight azimuths at 45°, ``--tiles`` tiles a view of ``--tile`` pixels, colour
alone and colour with the object ids as a second render target (both with readback).
Prints one JSON line and writes it (and one tile of each
view as PNG, to compare drivers) to ``--out``. Run it on two machines; compare the tiles with
``--compare DIR_A DIR_B``.

    python -m pipeline25d_lab.harness.gpu_render --out build/gpu_render
"""

from __future__ import annotations

import argparse
import io
import json
import math
import time
from pathlib import Path

import numpy as np

from pipeline25d.core.grid import Extent
from pipeline25d.core.mesh import MeshPart
from pipeline25d.geometry.camera import map_affine, project
from pipeline25d.geometry.perspectives import Perspective
from pipeline25d_lab.scenes.textured_slope import cosine_texture

ORIGIN = np.array([85000.0, 446000.0, 0.0])   # an RD-like origin: the float32 path as in the product
SIDE = 1000.0                                  # metres


def city_block(triangles: int, texture_size: int, seed: int = 3) -> tuple[MeshPart, np.ndarray]:
    """A textured heightfield of about ``triangles`` triangles over SIDE² m, and its per-face object ids
    (one id per 20 m block, as buildings)."""
    n = max(2, int(math.sqrt(triangles / 2)) + 1)
    s = np.linspace(0.0, SIDE, n)
    x, y = np.meshgrid(s, s)
    rng = np.random.default_rng(seed)
    lots = rng.uniform(0.0, 40.0, (51, 51)) * (rng.random((51, 51)) < 0.6)
    z = 8.0 * np.sin(x / 170.0) * np.cos(y / 130.0) + lots[(y // 20).astype(int), (x // 20).astype(int)]
    verts = np.column_stack([x.ravel(), y.ravel(), z.ravel()]) + ORIGIN
    i = np.arange(n - 1)
    a = (i[:, None] * n + i[None, :]).ravel()
    faces = np.concatenate([np.column_stack([a, a + 1, a + n + 1]), np.column_stack([a, a + n + 1, a + n])])
    uv = (np.column_stack([x.ravel(), y.ravel()]) / SIDE * 8.0).astype(np.float32)   # 8 repeats
    image = cosine_texture(size=texture_size).image()
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(image).save(buf, format="JPEG", quality=90)
    centroid = verts[faces].mean(axis=1)
    face_ids = (1 + (centroid[:, 1] - ORIGIN[1]) // 20 * 51 + (centroid[:, 0] - ORIGIN[0]) // 20).astype(np.uint32)
    return MeshPart(verts, faces, uv=uv, texture=buf.getvalue(), name="block"), face_ids


def views(part: MeshPart, tile: int, tiles: int, gsd: float):
    """Per perspective: ``tiles`` TileViews of ``tile`` px at ``gsd`` m along the block's image centre row."""
    from pipeline25d.stages.render import TileView

    out = []
    for p in [Perspective(0, 90)] + [Perspective(az, 45) for az in range(0, 360, 45)]:
        d = project(part.vertices, p, 0.0)[:, 2]
        depth = (float(d.min() - 1.0), float(d.max() + 1.0))
        A, _ = map_affine(p, 0.0)
        cx, cy = (A @ (ORIGIN + [SIDE / 2, SIDE / 2, 10.0]))[:2]
        span = tile * gsd
        row = []
        for k in range(tiles):
            x0 = cx + (k - tiles / 2) * span
            row.append(TileView(p, 0.0, Extent(x0, cy - span / 2, x0 + span, cy + span / 2), depth, (tile, tile)))
        out.append((p, row))
    return out


def run(args) -> dict:
    from pipeline25d.stages.render import TileRenderer, create_context, renderer_info
    from pipeline25d.stages.render_ids import IdRenderer

    t0 = time.perf_counter()
    part, face_ids = city_block(args.triangles, args.texture)
    made = time.perf_counter() - t0
    ctx = create_context()
    info = renderer_info(ctx)
    renderer, with_ids, ids = TileRenderer(ctx), TileRenderer(ctx, ids=True), IdRenderer(ctx)
    chunks = [(ORIGIN.copy(), [part])]
    plan = views(part, args.tile, args.tiles, args.gsd)
    first = plan[0][1][0]
    t0 = time.perf_counter()
    geometry = renderer.upload(chunks, first)
    renderer.render_color(geometry, first)             # texture upload + shader warm-up
    ctx.finish()
    upload = time.perf_counter() - t0
    geometry_ids = with_ids.upload(chunks, first)      # the render job's path: ids beside the colours
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    per_view, colour_s, id_s, pixels = [], 0.0, 0.0, 0
    from PIL import Image

    for p, row in plan:
        t0 = time.perf_counter()
        tiles = [renderer.render_color(geometry, v) for v in row]
        tc = time.perf_counter() - t0
        t0 = time.perf_counter()
        both = [ids.with_colour(with_ids, geometry_ids, v, lambda _part: face_ids) for v in row]
        ti = time.perf_counter() - t0
        id_tiles = [i for _, i in both]
        covered = sum(int((t[..., 3] > 0).sum()) for t in tiles)
        agree = sum(int(((t[..., 3] > 0) == (i > 0)).sum()) for t, i in zip(tiles, id_tiles))
        Image.fromarray(tiles[len(tiles) // 2]).save(out / f"{p.id}.png")
        px = sum(v.size[0] * v.size[1] for v in row)
        pixels += px
        colour_s += tc
        id_s += ti
        per_view.append({"view": p.id, "colour_s": round(tc, 4), "colour_ids_s": round(ti, 4),
                         "covered": covered, "alpha_id_agree": agree / px})
    geometry.release()
    geometry_ids.release()
    result = {"renderer": info, "triangles": part.n_triangles, "texture": args.texture, "tile": args.tile,
              "tiles": pixels // (args.tile * args.tile), "scene_s": round(made, 2), "upload_s": round(upload, 3),
              "colour_s": round(colour_s, 3), "colour_ids_s": round(id_s, 3),
              "colour_mpx_s": round(pixels / colour_s / 1e6, 2), "colour_ids_mpx_s": round(pixels / id_s / 1e6, 2),
              "views": per_view}
    (out / "gpu_render.json").write_text(json.dumps(result, indent=1))
    return result


def compare(a: Path, b: Path) -> dict:
    """Mean and 99th-percentile absolute difference (grey levels) between the tiles of two runs."""
    from PIL import Image

    out = {}
    for f in sorted(a.glob("*.png")):
        x = np.asarray(Image.open(f), dtype=np.float64)
        y = np.asarray(Image.open(b / f.name), dtype=np.float64)
        both = (x[..., 3] > 0) & (y[..., 3] > 0)
        d = np.abs(x[..., :3] - y[..., :3])[both]
        out[f.stem] = {"mean": round(float(d.mean()), 3), "p99": round(float(np.percentile(d, 99)), 1),
                       "alpha_differs": int(((x[..., 3] > 0) != (y[..., 3] > 0)).sum())}
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="build/gpu_render")
    ap.add_argument("--triangles", type=int, default=2_000_000)
    ap.add_argument("--texture", type=int, default=4096)
    ap.add_argument("--tile", type=int, default=2048)
    ap.add_argument("--tiles", type=int, default=2)
    ap.add_argument("--gsd", type=float, default=0.25)
    ap.add_argument("--compare", nargs=2, type=Path)
    args = ap.parse_args(argv)
    if args.compare:
        print(json.dumps(compare(*args.compare), indent=1))
        return
    print(json.dumps(run(args)))


if __name__ == "__main__":
    main()
