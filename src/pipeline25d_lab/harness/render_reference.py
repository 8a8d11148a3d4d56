"""A plain moderngl loop over a plan's tiles: the floor that a render job's cost is measured against.

One process and one GL context render the tiles one after the other, each as simply as moderngl
allows: load the tile's chunks at their planned LOD, upload positions and colours, draw with the
same MSAA samples into a framebuffer of the tile's size, resolve, read back and PNG-encode. No
shading, terrain offsets, GCP markers or GeoTIFF. Context creation and imports are not counted.
"""

from __future__ import annotations

import io
import time
from pathlib import Path

import numpy as np

from pipeline25d.geometry.camera import clip_matrix
from pipeline25d.stages.plan import read_plan

VERTEX = """
#version 330
uniform mat4 u_mvp;
in vec3 in_pos;
in vec4 in_color;
out vec4 v_color;
void main() { gl_Position = u_mvp * vec4(in_pos, 1.0); v_color = in_color; }
"""
FRAGMENT = """
#version 330
in vec4 v_color;
out vec4 f_color;
void main() { f_color = v_color; }
"""


def plain_loop_seconds(plan_path: str | Path, lod_dir: str | Path, samples: int,
                       tiles: list[dict] | None = None) -> dict:
    """{"tiles": n, "seconds": total, "per_tile_s": mean, "coverage": [share of drawn pixels per tile]}
    of the plain loop over ``tiles`` (default: all the plan's)."""
    import moderngl
    from PIL import Image

    from pipeline25d.stages.lod import load_chunk_level
    from pipeline25d.stages.render import create_context

    pl = read_plan(plan_path)
    tiles = pl.tiles if tiles is None else tiles
    persp = pl.perspective
    size = (pl.tile_size, pl.tile_size)
    ctx = create_context()
    try:
        prog = ctx.program(vertex_shader=VERTEX, fragment_shader=FRAGMENT)
        fbo_ms = ctx.framebuffer(color_attachments=[ctx.renderbuffer(size, 4, samples=samples)],
                                 depth_attachment=ctx.depth_renderbuffer(size, samples=samples))
        fbo = ctx.simple_framebuffer(size, components=4)
        coverage = []
        start = time.perf_counter()
        for tile in tiles:
            fbo_ms.use()
            ctx.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
            ctx.enable(moderngl.DEPTH_TEST)
            extent, (w, h) = pl.content(tile)        # the jobs render the same window
            ctx.viewport = (0, 0, w, h)
            for c in tile.chunks:
                origin, parts = load_chunk_level(Path(lod_dir) / c.district / f"{c.id}.npz", c.lod)
                matrix = clip_matrix(persp, pl.z0, extent, tuple(tile.depth_range), origin, pl.camera)
                prog["u_mvp"].write(matrix.T.astype("f4").tobytes())
                for part in parts:
                    if not part.n_triangles:
                        continue
                    colors = part.colors if part.colors is not None else np.full((len(part.vertices), 4), 180, "u1")
                    buffers = [ctx.buffer((part.vertices - origin).astype("f4")), ctx.buffer(colors.astype("u1")),
                               ctx.buffer(part.faces.astype("u4"))]
                    vao = ctx.vertex_array(prog, [(buffers[0], "3f", "in_pos"), (buffers[1], "4f1", "in_color")],
                                           index_buffer=buffers[2], index_element_size=4)
                    vao.render()
                    vao.release()
                    for b in buffers:
                        b.release()
            ctx.copy_framebuffer(fbo, fbo_ms)
            image = Image.frombytes("RGBA", (w, h), fbo.read(viewport=(0, 0, w, h), components=4))
            image.save(io.BytesIO(), format="PNG")
            coverage.append(float((np.asarray(image)[..., 3] > 0).mean()))
        seconds = time.perf_counter() - start
    finally:
        ctx.release()
    return {"tiles": len(tiles), "seconds": round(seconds, 3), "per_tile_s": round(seconds / max(len(tiles), 1), 4),
            "coverage": coverage}
