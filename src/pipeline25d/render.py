"""Headless OpenGL rendering of one map tile (moderngl on EGL).

Two passes share the tile's matrices (see :mod:`pipeline25d.camera`):

* colour: textured or vertex-coloured triangles, flat Lambert shading for untextured
  surfaces, depth test, MSAA; the result is un-premultiplied RGBA, transparent where
  nothing was drawn.
* GCP markers (the paper's method): the model in black plus one small horizontal disk
  per GCP in a unique colour, depth-tested with a small bias toward the camera. A marker
  that is only partly visible is rejected; a fully visible one's pixel centroid is its
  sub-pixel image position.

moderngl is imported lazily so the rest of the package imports where EGL is absent.
"""

from __future__ import annotations

import io
from dataclasses import dataclass

import numpy as np

from .camera import Extent, clip_matrix
from .errors import RenderError
from .mesh import MeshPart
from .perspectives import Perspective

LIGHT_DIRECTION = np.array([0.45, 0.65, -0.62]) / np.linalg.norm([0.45, 0.65, -0.62])
MARKER_SEGMENTS = 32

VERTEX_SHADER = """
#version 330
uniform mat4 u_mvp;
uniform float u_zbias;
in vec3 in_pos;
in vec4 in_color;
in vec2 in_uv;
out vec3 v_pos;
out vec4 v_color;
out vec2 v_uv;
void main() {
    gl_Position = u_mvp * vec4(in_pos, 1.0);
    gl_Position.z -= u_zbias;
    v_pos = in_pos;
    v_color = in_color;
    v_uv = in_uv;
}
"""

FRAGMENT_SHADER = """
#version 330
uniform int u_mode;          // 0 vertex colour, 1 texture, 2 uniform colour
uniform vec4 u_color;
uniform sampler2D u_tex;
uniform bool u_shade;
uniform vec3 u_light;        // direction the light travels
uniform vec3 u_view;         // direction the camera looks
uniform float u_ambient;
in vec3 v_pos;
in vec4 v_color;
in vec2 v_uv;
out vec4 f_color;
void main() {
    vec4 base = u_mode == 0 ? v_color : (u_mode == 1 ? texture(u_tex, v_uv) : u_color);
    float shade = 1.0;
    if (u_shade) {
        vec3 n = normalize(cross(dFdx(v_pos), dFdy(v_pos)));
        if (dot(n, u_view) > 0.0) n = -n;   // the face the camera sees
        shade = u_ambient + (1.0 - u_ambient) * max(dot(n, -u_light), 0.0);
    }
    f_color = vec4(base.rgb * shade, 1.0);
}
"""


@dataclass(frozen=True)
class TileView:
    """What one tile render needs to know about the camera: all float64."""

    perspective: Perspective
    z0: float
    extent: Extent
    depth_range: tuple[float, float]
    size: tuple[int, int]          # (width, height) in pixels

    def matrix(self, origin: np.ndarray) -> np.ndarray:
        return clip_matrix(self.perspective, self.z0, self.extent, self.depth_range, origin)


def create_context():
    """A standalone moderngl context on EGL; RenderError with a hint when unavailable."""
    try:
        import moderngl

        return moderngl.create_standalone_context(backend="egl")
    except Exception as exc:  # moderngl/glcontext raise plain Exception
        raise RenderError(
            f"cannot create a headless OpenGL context through EGL ({exc}); on Debian install "
            "libegl1 libegl-mesa0 libgl1-mesa-dri (make deps does)") from None


def renderer_info(ctx) -> dict[str, str]:
    return {k: ctx.info[k] for k in ("GL_VENDOR", "GL_RENDERER", "GL_VERSION")}


class TileRenderer:
    """Renders chunks into tiles; one instance per GL context (programs compiled once)."""

    def __init__(self, ctx, ambient: float = 0.45, samples: int = 4):
        self.ctx = ctx
        self.ambient = ambient
        self.samples = min(samples, ctx.max_samples) if samples else 0
        self.prog = ctx.program(vertex_shader=VERTEX_SHADER, fragment_shader=FRAGMENT_SHADER)
        self._textures: dict[bytes, object] = {}

    # -- resources -----------------------------------------------------------
    def _texture(self, data: bytes):
        """A GL texture for encoded image bytes, uploaded once per distinct image."""
        if data not in self._textures:
            import moderngl
            from PIL import Image

            img = Image.open(io.BytesIO(data)).convert("RGBA").transpose(Image.Transpose.FLIP_TOP_BOTTOM)
            tex = self.ctx.texture(img.size, 4, img.tobytes())
            tex.build_mipmaps()
            tex.repeat_x = tex.repeat_y = True
            # Trilinear only: llvmpipe's anisotropic filter blurs even 1:1 texel-to-pixel mappings.
            tex.filter = (moderngl.LINEAR_MIPMAP_LINEAR, moderngl.LINEAR)
            self._textures[data] = tex
        return self._textures[data]

    def _vao(self, positions: np.ndarray, faces: np.ndarray, colors: np.ndarray | None = None,
             uv: np.ndarray | None = None):
        ctx = self.ctx
        content = [(ctx.buffer(positions.astype("f4").tobytes()), "3f", "in_pos")]
        if colors is not None:
            content.append((ctx.buffer(np.ascontiguousarray(colors, dtype="u1").tobytes()), "4f1", "in_color"))
        if uv is not None:
            content.append((ctx.buffer(uv.astype("f4").tobytes()), "2f", "in_uv"))
        ibo = ctx.buffer(faces.astype("u4").tobytes())
        return ctx.vertex_array(self.prog, content, index_buffer=ibo, index_element_size=4)

    def _set(self, **uniforms) -> None:
        for name, value in uniforms.items():
            if name in self.prog:
                self.prog[name].value = value

    # -- drawing ---------------------------------------------------------------
    def _draw_chunks(self, chunks: list[tuple[np.ndarray, list[MeshPart]]], view: TileView,
                     black: bool = False) -> None:
        from .camera import view_direction

        self._set(u_light=tuple(LIGHT_DIRECTION), u_view=tuple(view_direction(view.perspective)),
                  u_ambient=self.ambient, u_zbias=0.0)
        for origin, parts in chunks:
            self.prog["u_mvp"].write(view.matrix(origin).T.astype("f4").tobytes())
            for part in parts:
                if not part.n_triangles:
                    continue
                local = part.vertices - origin
                textured = part.texture is not None and part.uv is not None and not black
                vao = self._vao(local, part.faces, None if black else part.colors, part.uv if textured else None)
                if black:
                    self._set(u_mode=2, u_color=(0.0, 0.0, 0.0, 1.0), u_shade=False)
                elif textured:
                    self._texture(part.texture).use(0)
                    self._set(u_mode=1, u_tex=0, u_shade=False)
                elif part.colors is not None:
                    self._set(u_mode=0, u_shade=True)
                else:
                    self._set(u_mode=2, u_color=(0.7, 0.7, 0.7, 1.0), u_shade=True)
                vao.render()
                vao.release()

    def render_color(self, chunks: list[tuple[np.ndarray, list[MeshPart]]], view: TileView) -> np.ndarray:
        """(h, w, 4) uint8 RGBA, row 0 = north edge, alpha 0 where empty."""
        import moderngl

        ctx, (w, h) = self.ctx, view.size
        fbo_ms = ctx.framebuffer(color_attachments=[ctx.renderbuffer((w, h), 4, samples=self.samples)],
                                 depth_attachment=ctx.depth_renderbuffer((w, h), samples=self.samples))
        fbo = ctx.simple_framebuffer((w, h), components=4)
        fbo_ms.use()
        ctx.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        ctx.enable(moderngl.DEPTH_TEST)
        ctx.disable(moderngl.CULL_FACE)
        self._draw_chunks(chunks, view)
        ctx.copy_framebuffer(fbo, fbo_ms)
        rgba = _read_rgba(fbo, w, h)
        for obj in (fbo_ms, fbo):
            obj.release()
        return unpremultiply(rgba)

    def render_markers(self, chunks: list[tuple[np.ndarray, list[MeshPart]]], view: TileView,
                       points: np.ndarray, radius_m: float, depth_bias_m: float) -> tuple[np.ndarray, np.ndarray]:
        """Marker pixel statistics for (n, 3) GCPs: (counts_full, sums).

        counts_full[i]: pixels of marker i with nothing else drawn; sums[i] = (count, Σcol, Σrow,
        on_model) with the model drawn in black first (pixel centres at +0.5, row 0 = north);
        on_model counts the marker's pixels that lie over model surface, so a GCP floating
        over a hole in the model (no ground there) can be told apart.
        """
        import moderngl

        ctx, (w, h) = self.ctx, view.size
        fbo = ctx.framebuffer(color_attachments=[ctx.renderbuffer((w, h), 4)],
                              depth_attachment=ctx.depth_renderbuffer((w, h)))
        fbo.use()
        ctx.enable(moderngl.DEPTH_TEST)
        ctx.disable(moderngl.CULL_FACE)
        n = len(points)
        origin = points.mean(axis=0) if n else np.zeros(3)
        verts, faces, colors = marker_geometry(points - origin, radius_m)
        dmin, dmax = view.depth_range
        zbias = 2.0 * depth_bias_m / (dmax - dmin)

        def draw_markers():
            if not n:
                return
            self.prog["u_mvp"].write(view.matrix(origin).T.astype("f4").tobytes())
            self._set(u_mode=0, u_shade=False, u_zbias=zbias)
            vao = self._vao(verts, faces, colors)
            vao.render()
            vao.release()
            self._set(u_zbias=0.0)

        ctx.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        draw_markers()
        full = _marker_stats(fbo, w, h, n)[:, 0]
        ctx.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        self._draw_chunks(chunks, view, black=True)
        coverage = _read_rgba(fbo, w, h)[..., 3] > 0
        draw_markers()
        sums = _marker_stats(fbo, w, h, n, coverage)
        fbo.release()
        return full, sums


def marker_geometry(centres: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Horizontal disks (triangle fans) around (n, 3) local centres, coloured by id + 1.

    A horizontal disk projects to the same disk in every map-aligned view (the shear
    moves all its points alike), so its pixel centroid estimates its centre without bias.
    """
    n, k = len(centres), MARKER_SEGMENTS
    ang = np.linspace(0, 2 * np.pi, k, endpoint=False)
    ring = np.column_stack([np.cos(ang), np.sin(ang), np.zeros(k)]) * radius
    verts = (centres[:, None, :] + np.vstack([np.zeros((1, 3)), ring])[None]).reshape(-1, 3)
    base = np.arange(n)[:, None] * (k + 1)
    j = np.arange(k)
    fan = np.column_stack([np.zeros(k, int), 1 + j, 1 + (j + 1) % k])
    faces = (base[:, None, :] + fan[None]).reshape(-1, 3)
    ids = np.arange(1, n + 1)
    rgb = np.column_stack([ids & 255, (ids >> 8) & 255, (ids >> 16) & 255, np.full(n, 255)]).astype(np.uint8)
    colors = np.repeat(rgb, k + 1, axis=0)
    return verts, faces, colors


def _read_rgba(fbo, w: int, h: int) -> np.ndarray:
    """(h, w, 4) uint8 framebuffer contents with row 0 at the top (north); GL's row 0 is the bottom."""
    return np.frombuffer(fbo.read(components=4), dtype=np.uint8).reshape(h, w, 4)[::-1]


def _marker_stats(fbo, w: int, h: int, n: int, coverage: np.ndarray | None = None) -> np.ndarray:
    """(n, 4) float64 per marker: pixel count, Σ(col + 0.5), Σ(row + 0.5) (row 0 = north), and
    the count of its pixels where ``coverage`` (model drawn underneath) is true."""
    rgba = _read_rgba(fbo, w, h)
    ids = rgba[..., 0].astype(np.int64) | (rgba[..., 1].astype(np.int64) << 8) | (rgba[..., 2].astype(np.int64) << 16)
    rows, cols = np.nonzero(ids)
    which = ids[rows, cols] - 1
    stats = np.zeros((n, 4))
    if n:
        stats[:, 0] = np.bincount(which, minlength=n)[:n]
        if coverage is not None:
            stats[:, 3] = np.bincount(which, weights=coverage[rows, cols].astype(float), minlength=n)[:n]
        stats[:, 1] = np.bincount(which, weights=cols + 0.5, minlength=n)[:n]
        stats[:, 2] = np.bincount(which, weights=rows + 0.5, minlength=n)[:n]
    return stats


def unpremultiply(rgba: np.ndarray) -> np.ndarray:
    """Undo the premultiplication MSAA resolve leaves at edges against the transparent background."""
    alpha = rgba[..., 3:4].astype(np.float64)
    out = rgba.copy()
    partial = (alpha[..., 0] > 0) & (alpha[..., 0] < 255)
    out[..., :3][partial] = np.clip(rgba[..., :3][partial] * 255.0 / alpha[partial], 0, 255).round().astype(np.uint8)
    return out
