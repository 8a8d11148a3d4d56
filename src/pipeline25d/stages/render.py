"""Headless OpenGL rendering of one map tile (moderngl on EGL).

Two passes share the tile's matrices (see :mod:`pipeline25d.geometry.camera`):

* colour: textured or vertex-coloured triangles, flat Lambert shading for untextured
  surfaces, depth test, MSAA; the result is un-premultiplied RGBA, transparent where
  nothing was drawn.
* GCP markers (the paper's method): one small disk per GCP, lying in the ground's local
  plane, in a unique colour, compared in its fragment shader with the model's depth drawn
  before it (moved a small bias toward the camera: is it in front; is it on the model's
  surface). A marker that is only partly visible is buried or hidden and rejected; one
  whose depth disagrees with the model's surface under it floats and is rejected; a fully
  visible one's pixel centroid is its sub-pixel image position.
* depth: the view depth of the nearest surface per pixel (the DSM pass, seen from nadir).
* sun shadows (a renderer made with ``shadows=True``, a :class:`ShadowView` per tile): the
  tile's chunks and its shadow casters are rendered first into a depth map seen from the sun
  (:class:`pipeline25d.geometry.sun.SunFrame`, texels on the scene's global grid); the colour pass then
  looks each fragment's true 3D position up in it (a tent filter over depth comparisons, with a
  receiver-plane depth offset and a constant bias) and darkens what the sun does not reach to
  the shadow ambient share; untextured surfaces are lit by the sun (Lambert) instead of the
  fixed light. Without shadows the shaders compile exactly as before (the shadow code sits
  behind ``#ifdef SHADOWS``), so maps stay byte for byte the same.

Terrain-relative projection (DESIGN.md): each vertex carries its DTM height ``in_ground``
and is displaced by its height above that ground instead of above z0; depth stays the
true 3D view depth, so hidden surfaces are resolved as in plane mode.

moderngl is imported lazily so the rest of the package imports where EGL is absent.

Over 400 lines for one job: the tile's passes (colour, shadow map, depth, markers) share one
set of GL programs, one upload of the chunks and one texture cache.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np

from pipeline25d.core.errors import RenderError
from pipeline25d.core.grid import Extent
from pipeline25d.core.mesh import MeshPart
from pipeline25d.geometry.camera import clip_matrix
from pipeline25d.geometry.perspectives import Perspective
from pipeline25d.geometry.sun import SunFrame
from pipeline25d.stages.textures import TextureCache, texture_anisotropy

LIGHT_DIRECTION = np.array([0.45, 0.65, -0.62]) / np.linalg.norm([0.45, 0.65, -0.62])
MARKER_SEGMENTS = 32
TEXTURE_BUDGET = 256 << 20   # bytes of model textures a renderer holds between tiles (textures.TextureCache)



def _shader(name: str) -> str:
    """A GLSL source of this stage (``stages/shaders/``), as the program compiles it."""
    return (Path(__file__).with_name("shaders") / name).read_text(encoding="ascii")


VERTEX_SHADER = _shader("tile.vert")

FACE_WIDTH = 4096    # face ids per row of a mesh's face-id texture (the ids render target's lookup)
FACE_UNIT = 2        # its texture unit (0: the model's texture, 1: the shadow map)

FRAGMENT_SHADER = _shader("tile.frag")
MARKER_SHADER = _shader("marker.frag")
MODEL_DEPTH_UNIT = 3  # the marker pass's model depth (render_markers)
MARKER_OVER, MARKER_ON, MARKER_SEEN = 1, 2, 4   # marker.frag's flags in a marker pixel's alpha


@dataclass(frozen=True)
class TileView:
    """What one tile render needs to know about the camera: all float64."""

    perspective: Perspective
    z0: float
    extent: Extent
    depth_range: tuple[float, float]
    size: tuple[int, int]          # (width, height) in pixels
    ground: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None   # DTM(x, y); None = plane mode
    camera: str = "map"            # "map" (map-aligned) or "paper" (the paper's image plane)

    def matrix(self, origin: np.ndarray) -> np.ndarray:
        """Clip matrix for vertices relative to ``origin``. In terrain-relative mode its reference
        plane is the origin's height, matching :meth:`ground_offsets`: the result is the same
        (every vertex subtracts its own ground), but both float32 terms stay small."""
        z0 = self.z0 if self.ground is None else float(origin[2])
        return clip_matrix(self.perspective, z0, self.extent, self.depth_range, origin, self.camera)

    def shear(self, matrix: np.ndarray) -> tuple[float, float, float, float]:
        """u_shear: the clip-space map shift per metre of ground height (zero in plane mode)."""
        if self.ground is None:
            return (0.0, 0.0, 0.0, 0.0)
        return (float(matrix[0, 2]), float(matrix[1, 2]), 0.0, 0.0)

    def ground_offsets(self, vertices: np.ndarray, origin: np.ndarray) -> np.ndarray | None:
        """(n,) float32 DTM height under scene-CRS vertices minus ``origin``'s height (their chunk's),
        or None in plane mode. Relative to z0 instead, a DTM thousands of metres from z0 cost
        0.01 px and more at low elevations (float32 shear × height against the matrix offset)."""
        if self.ground is None:
            return None
        return (self.ground(vertices[:, 0], vertices[:, 1]) - float(origin[2])).astype(np.float32)

    def depth_metres(self, window_depth: np.ndarray) -> np.ndarray:
        """View depth in metres from GL window depth in [0, 1] (1 = cleared: NaN)."""
        dmin, dmax = self.depth_range
        out = dmin + window_depth.astype(np.float64) * (dmax - dmin)
        out[window_depth >= 1.0] = np.nan
        return out


@dataclass(frozen=True)
class ShadowView:
    """A tile's shadow map: the scene's sun space, the tile's window on its global texel grid
    (k0, l0, k1, l1), its depth range (m of -height), the brightness in shadow (share of
    full sun), the depth bias (m) and the filter radius (texels). All float64."""

    frame: SunFrame
    window: tuple[int, int, int, int]
    depth_range: tuple[float, float]
    ambient: float
    bias: float
    radius: float

    @property
    def size(self) -> tuple[int, int]:
        return self.window[2] - self.window[0], self.window[3] - self.window[1]


class IdPass(Protocol):
    """What the colour pass needs to write object ids beside its colours
    (:class:`pipeline25d.stages.render_ids.ColourIds`)."""

    def target(self, size: tuple[int, int], samples: int): ...
    def bind(self, mesh: "_GpuMesh", unit: int) -> None: ...
    def resolve(self, target, size: tuple[int, int], samples: int) -> np.ndarray: ...


class _GpuMesh:
    """A vertex array and the buffers it reads (``vao.release()`` alone leaves them allocated);
    ``part``: the mesh part it was uploaded from (its face ids, :mod:`.render_ids`)."""

    def __init__(self, vao, buffers: list):
        self.vao, self.buffers = vao, buffers
        self.texture: bytes | None = None
        self.coloured = False
        self.part: MeshPart | None = None

    def release(self) -> None:
        self.vao.release()
        for b in self.buffers:
            b.release()


class TileGeometry:
    """Chunks uploaded once for all passes of a tile: [(origin, [_GpuMesh, ...]), ...]."""

    def __init__(self, chunks: list[tuple[np.ndarray, list[_GpuMesh]]]):
        self.chunks = chunks

    def release(self) -> None:
        for _, meshes in self.chunks:
            for mesh in meshes:
                mesh.release()
        self.chunks = []

    def __enter__(self) -> "TileGeometry":
        return self

    def __exit__(self, *exc) -> None:
        self.release()


Chunks = "list[tuple[np.ndarray, list[MeshPart]]] | TileGeometry"


def create_context(workers: int | None = None):
    """A standalone moderngl context on EGL; RenderError with a hint when unavailable.

    ``workers``: the cores the job may use now (:func:`~pipeline25d.core.cores.job_workers`). With
    one, Mesa's software rasterizer (llvmpipe) draws in the job's own thread instead of on threads of
    its own (``LP_NUM_THREADS=0``, unless the environment sets it; read when the first context
    is made): the same pixels, and on two cores each busy with a render job 12 % less CPU (the
    3 x 3 bench's 144 tiles replayed: 22.6 against 25.6 s). A GPU's driver ignores it."""
    if workers is not None and workers <= 1:
        os.environ.setdefault("LP_NUM_THREADS", "0")
    try:
        import moderngl

        return moderngl.create_standalone_context(backend="egl")
    except Exception as exc:  # moderngl/glcontext raise plain Exception
        raise RenderError(
            f"cannot create a headless OpenGL context through EGL ({exc}); on Debian install "
            "libegl1 libegl-mesa0 libgl1-mesa-dri (make deps does)") from None


def renderer_info(ctx) -> dict[str, str]:
    """The driver's names and the texture anisotropy a renderer on it uses."""
    info = {k: ctx.info[k] for k in ("GL_VENDOR", "GL_RENDERER", "GL_VERSION")}
    return {**info, "texture_anisotropy": f"{texture_anisotropy(ctx):g}"}


class TileRenderer:
    """Renders chunks into tiles; one instance per GL context (programs compiled once)."""

    def __init__(self, ctx, ambient: float = 0.45, samples: int = 4, shadows: bool = False,
                 anisotropy: float | None = None, ids: bool = False):
        self.ctx = ctx
        self.anisotropy = texture_anisotropy(ctx) if anisotropy is None else anisotropy
        self.ambient = ambient
        self.samples = min(samples, ctx.max_samples) if samples else 0
        self.shadows, self.ids = shadows, ids
        defines = (["SHADOWS"] if shadows else []) + ([f"IDS\n#define FACE_WIDTH {FACE_WIDTH}"] if ids else [])
        self.prog = ctx.program(vertex_shader=_variant(VERTEX_SHADER, *defines),
                                fragment_shader=_variant(FRAGMENT_SHADER, *defines))
        self._set(u_faces=FACE_UNIT)     # its own unit: never a colour texture's (sampler types differ)
        self.marker_prog = ctx.program(vertex_shader=VERTEX_SHADER, fragment_shader=MARKER_SHADER)
        self.marker_prog["u_model_depth"].value = MODEL_DEPTH_UNIT
        self._textures = TextureCache(ctx, self.anisotropy, TEXTURE_BUDGET)
        self._targets: dict[str, tuple[tuple, dict]] = {}

    # -- resources -----------------------------------------------------------
    def _targets_for(self, name: str, key: tuple, make: Callable[[], dict]) -> dict:
        """The render targets of pass ``name`` for ``key`` (its size, ...), made by ``make`` and kept
        for the next tile: a block's tiles share a size, and fresh multisample buffers cost their
        page faults every tile. Those of another key are released first (one set a pass)."""
        held = self._targets.get(name)
        if held is not None and held[0] == key:
            return held[1]
        if held is not None:
            for obj in {id(o): o for o in held[1].values()}.values():
                obj.release()
        made = make()
        self._targets[name] = (key, made)
        return made

    def _texture(self, data: bytes):
        """A GL texture for encoded image bytes, uploaded once while held (:class:`.textures.TextureCache`)."""
        return self._textures.get(data)

    def _vao(self, positions: np.ndarray, faces: np.ndarray, colors: np.ndarray | None = None,
             uv: np.ndarray | None = None, ground: np.ndarray | None = None, prog=None) -> "_GpuMesh":
        """Upload one mesh (positions already relative to its origin) as a vertex array of ``prog``
        (the tile program by default)."""
        ctx = self.ctx
        content = [(ctx.buffer(np.ascontiguousarray(positions, dtype="f4")), "3f", "in_pos")]
        if ground is not None:
            content.append((ctx.buffer(np.ascontiguousarray(ground, dtype="f4")), "1f", "in_ground"))
        if colors is not None:
            content.append((ctx.buffer(np.ascontiguousarray(colors, dtype="u1")), "4f1", "in_color"))
        if uv is not None:
            content.append((ctx.buffer(np.ascontiguousarray(uv, dtype="f4")), "2f", "in_uv"))
        ibo = ctx.buffer(np.ascontiguousarray(faces, dtype="u4"))
        vao = ctx.vertex_array(prog or self.prog, content, index_buffer=ibo, index_element_size=4)
        return _GpuMesh(vao, [b for b, _, _ in content] + [ibo])

    def upload(self, chunks: list[tuple[np.ndarray, list[MeshPart]]], view: TileView | None) -> "TileGeometry":
        """The chunks on the GPU, once for every pass of a tile (they share the view's ground).

        Vertices go to float32 relative to their chunk's origin; in terrain-relative mode
        each also carries the DTM under it relative to the origin's height. ``view`` None: no
        ground (shadow casters, drawn only from the sun). Release the result (or use it in ``with``).
        """
        out = []
        for origin, parts in chunks:
            gpu = []
            for part in parts:
                if not part.n_triangles:
                    continue
                textured = part.texture is not None and part.uv is not None
                mesh = self._vao(part.vertices - origin, part.faces, part.colors, part.uv if textured else None,
                                 None if view is None else view.ground_offsets(part.vertices, origin))
                mesh.texture = part.texture if textured else None
                mesh.coloured = part.colors is not None
                mesh.part = part
                gpu.append(mesh)
            out.append((np.asarray(origin, dtype=np.float64), gpu))
        return TileGeometry(out)

    @contextmanager
    def _geometry(self, chunks: "Chunks", view: TileView | None) -> Iterator["TileGeometry"]:
        """``chunks`` on the GPU for one pass: uploaded (and released after) unless already uploaded."""
        if isinstance(chunks, TileGeometry):
            yield chunks
            return
        with self.upload(chunks, view) as geometry:
            yield geometry

    def _set(self, prog=None, **uniforms) -> None:
        """Set the uniforms ``prog`` (the tile program by default) uses; it ignores the others."""
        prog = prog or self.prog
        for name, value in uniforms.items():
            if name in prog:
                prog[name].value = value

    # -- drawing ---------------------------------------------------------------
    def _draw_chunks(self, geometry: "TileGeometry", view: TileView, black: bool = False,
                     shadow: ShadowView | None = None, ids: "IdPass | None" = None) -> None:
        from pipeline25d.geometry.camera import view_direction

        self._set(u_light=tuple(LIGHT_DIRECTION), u_view=tuple(view_direction(view.perspective)),
                  u_ambient=self.ambient, u_zbias=0.0, u_sunlit=shadow is not None and not black)
        for origin, meshes in geometry.chunks:
            matrix = view.matrix(origin)
            self.prog["u_mvp"].write(matrix.T.astype("f4").tobytes())
            self._set(u_shear=view.shear(matrix))
            if shadow is not None:
                self._write("u_sun_mvp", shadow.frame.lookup_matrix(shadow.window, shadow.depth_range, origin))
            for mesh in meshes:
                if black:
                    self._set(u_mode=2, u_color=(0.0, 0.0, 0.0, 1.0), u_shade=False)
                elif mesh.texture is not None:
                    self._texture(mesh.texture).use(0)
                    self._set(u_mode=1, u_tex=0, u_shade=False)
                elif mesh.coloured:
                    self._set(u_mode=0, u_shade=True)
                else:
                    self._set(u_mode=2, u_color=(0.7, 0.7, 0.7, 1.0), u_shade=True)
                if ids is not None:
                    ids.bind(mesh, FACE_UNIT)
                mesh.vao.render()

    def _write(self, name: str, matrix: np.ndarray) -> None:
        """A 4×4 float64 matrix into a mat4 uniform (as float32), if the program uses it."""
        if name in self.prog:
            self.prog[name].write(matrix.T.astype("f4").tobytes())

    def render_color(self, chunks: "Chunks", view: TileView, shadow: ShadowView | None = None,
                     casters: "Chunks | None" = None) -> np.ndarray:
        """(h, w, 4) uint8 RGBA, row 0 = north edge, alpha 0 where empty.

        ``shadow``: sun shadows (a renderer made with ``shadows=True``), cast by ``chunks`` and
        ``casters`` (further chunks that are drawn only into the shadow map)."""
        return self._colour(chunks, view, shadow, casters, None)[0]

    def render_color_ids(self, chunks: "Chunks", view: TileView, ids: "IdPass", shadow: ShadowView | None = None,
                         casters: "Chunks | None" = None) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`render_color` and, from the same fragments (a second render target of the same
        samples), the (h, w) uint32 object id of every pixel that ``ids`` resolves (a renderer made
        with ``ids=True``; :class:`pipeline25d.stages.render_ids.ColourIds`)."""
        if not self.ids:
            raise RenderError("object ids beside the colours need a TileRenderer made with ids=True")
        return self._colour(chunks, view, shadow, casters, ids)

    def _colour(self, chunks: "Chunks", view: TileView, shadow: ShadowView | None, casters: "Chunks | None",
                ids: "IdPass | None") -> tuple[np.ndarray, np.ndarray | None]:
        import moderngl

        if shadow is not None and not self.shadows:
            raise RenderError("sun shadows need a TileRenderer made with shadows=True")
        ctx, (w, h) = self.ctx, view.size
        self._textures.trim()                   # between tiles: the last tile's textures first in line
        with self._geometry(chunks, view) as geometry:
            shadow_map = None
            if shadow is not None:
                with self._geometry(casters or [], None) as cast:
                    shadow_map = self._shadow_map([geometry, cast], shadow)
                shadow_map.use(location=1)
                self._set(u_shadow_map=1, **_shadow_uniforms(shadow))
            t = self._targets_for("colour", (w, h, ids is not None), lambda: self._colour_targets(w, h, ids))
            fbo_ms, colour_only, fbo, id_target = t["fbo_ms"], t["colour_only"], t["fbo"], t.get("ids")
            fbo_ms.use()
            fbo_ms.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)     # each attachment by its type (ids: 0)
            ctx.enable(moderngl.DEPTH_TEST)
            ctx.disable(moderngl.CULL_FACE)
            self._draw_chunks(geometry, view, shadow=shadow, ids=ids)
        ctx.copy_framebuffer(fbo, colour_only)
        rgba = _read_rgba(fbo, w, h)
        out_ids = None if ids is None else ids.resolve(id_target, (w, h), self.samples)
        if shadow_map is not None:
            shadow_map.release()
        return unpremultiply(rgba), out_ids

    def _colour_targets(self, w: int, h: int, ids: "IdPass | None") -> dict:
        """The colour pass's targets: a multisample framebuffer (colour, ids where asked, depth), its
        colour alone (what the resolve copies) and the single-sample framebuffer resolved into."""
        ctx = self.ctx
        colour = ctx.renderbuffer((w, h), 4, samples=self.samples)
        depth = ctx.depth_renderbuffer((w, h), samples=self.samples)
        id_target = None if ids is None else ids.target((w, h), self.samples)
        fbo_ms = ctx.framebuffer(color_attachments=[colour] + ([id_target] if id_target else []),
                                 depth_attachment=depth)
        out = {"colour": colour, "depth": depth, "fbo_ms": fbo_ms, "fbo": ctx.simple_framebuffer((w, h), components=4),
               "colour_only": ctx.framebuffer(color_attachments=[colour]) if id_target else fbo_ms}
        if id_target is not None:
            out["ids"] = id_target
        return out

    def _shadow_map(self, geometries: list["TileGeometry"], shadow: ShadowView):
        """A depth texture of ``geometries`` seen from the sun over the shadow view's window
        (one texel per pixel, true 3D positions: no terrain displacement)."""
        import moderngl

        ctx, (w, h) = self.ctx, shadow.size
        limit = int(ctx.info["GL_MAX_TEXTURE_SIZE"])
        if max(w, h) > limit:
            raise RenderError(f"a tile's shadow map needs {w} x {h} texels, more than this GPU's {limit}: "
                              "lower tile_size or raise shadows.texel_px")
        depth = ctx.depth_texture((w, h))
        fbo = ctx.framebuffer(depth_attachment=depth)
        fbo.use()
        ctx.clear(depth=1.0)
        ctx.enable(moderngl.DEPTH_TEST)
        ctx.disable(moderngl.CULL_FACE)
        self._set(u_mode=2, u_color=(0.0, 0.0, 0.0, 1.0), u_shade=False, u_sunlit=False, u_zbias=0.0,
                  u_shear=(0.0, 0.0, 0.0, 0.0))
        for geometry in geometries:
            for origin, meshes in geometry.chunks:
                self._write("u_mvp", shadow.frame.clip_matrix(shadow.window, shadow.depth_range, origin))
                for mesh in meshes:
                    mesh.vao.render()
        fbo.release()
        depth.compare_func = ""                  # plain depth values for texelFetch
        depth.filter = (moderngl.NEAREST, moderngl.NEAREST)
        return depth

    def render_depth(self, chunks: "Chunks", view: TileView) -> np.ndarray:
        """(h, w) float64 view depth (metres) of the nearest surface at each pixel centre; NaN where empty."""
        import moderngl

        ctx, (w, h) = self.ctx, view.size
        depth = ctx.depth_texture((w, h))
        fbo = ctx.framebuffer(depth_attachment=depth)     # depth alone: no colour to write or clear
        fbo.use()
        ctx.clear(depth=1.0)
        ctx.enable(moderngl.DEPTH_TEST)
        ctx.disable(moderngl.CULL_FACE)
        with self._geometry(chunks, view) as geometry:
            self._draw_chunks(geometry, view, black=True)
        out = view.depth_metres(_read_depth(depth, w, h))
        fbo.release()
        depth.release()
        return out

    def _marker_targets(self, w: int, h: int) -> dict:
        """The marker pass's targets: the model's depth (a texture the markers read) in a framebuffer
        of its own, and the markers' RGBA with a depth buffer of theirs."""
        ctx = self.ctx
        model = ctx.depth_texture((w, h))
        model.compare_func = ""                  # plain depth values for texelFetch
        colour, depth = ctx.renderbuffer((w, h), 4), ctx.depth_renderbuffer((w, h))
        return {"model": model, "model_fbo": ctx.framebuffer(depth_attachment=model), "colour": colour,
                "depth": depth, "fbo": ctx.framebuffer(color_attachments=[colour], depth_attachment=depth)}

    def render_markers(self, chunks: "Chunks", view: TileView,
                       points: np.ndarray, slopes: np.ndarray, radius_m: float, depth_bias_m: float,
                       depth_tolerance_m: float) -> tuple[np.ndarray, np.ndarray]:
        """Marker pixel statistics for (n, 3) GCPs on ground of slope (n, 2) (dz/dx, dz/dy).

        Returns (counts_full, sums): counts_full[i] = pixels of marker i drawn alone;
        sums[i] = (count, Σcol, Σrow, agree) of its pixels that stay in front of the model when
        the marker is moved ``depth_bias_m`` toward the camera (pixel centres at +0.5, row 0 =
        north). ``agree`` counts marker pixels where the model's surface depth is within
        ``depth_tolerance_m`` of the marker's own: fewer than counts_full means the marker
        floats above the model (or over a hole) somewhere. A marker with nothing of the model
        under any of its pixels stands on bare ground (the DTM where a buildings-only model
        draws nothing: the scene stage puts sites there only for such models) and agrees whole;
        one partly over the model and partly over nothing lies on its edge and does not.

        Two draws: the model's depth, then the markers (depth-tested among themselves), each
        fragment comparing itself with the model's depth there (``shaders/marker.frag``); one read.
        """
        import moderngl

        ctx, (w, h) = self.ctx, view.size
        t = self._targets_for("markers", (w, h), lambda: self._marker_targets(w, h))
        n = len(points)
        origin = points.mean(axis=0) if n else np.zeros(3)
        dmin, dmax = view.depth_range
        ctx.enable(moderngl.DEPTH_TEST)
        ctx.disable(moderngl.CULL_FACE)
        t["model_fbo"].use()
        ctx.clear(depth=1.0)
        with self._geometry(chunks, view) as geometry:
            self._draw_chunks(geometry, view, black=True)     # depth alone: no colour to write
        t["fbo"].use()
        ctx.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        if n:
            verts, faces, colors = marker_geometry(points - origin, slopes, radius_m)
            matrix = view.matrix(origin)
            prog = self.marker_prog
            prog["u_mvp"].write(matrix.T.astype("f4").tobytes())
            self._set(prog, u_shear=view.shear(matrix), u_zbias=0.0, u_depth_span=dmax - dmin,
                      u_tolerance=min(depth_tolerance_m, np.finfo(np.float32).max),
                      u_seen_shift=depth_bias_m / (dmax - dmin))
            t["model"].use(location=MODEL_DEPTH_UNIT)
            mesh = self._vao(verts, faces, colors, ground=view.ground_offsets(verts + origin, origin), prog=prog)
            mesh.vao.render()
            mesh.release()
        pixels = np.frombuffer(t["fbo"].read(components=4), dtype="<u4").reshape(h, w)[::-1]
        rows, cols = np.nonzero(pixels & 0xFFFFFF)           # only marker pixels count below
        pixels = pixels[rows, cols]
        which, flags = pixels & 0xFFFFFF, pixels >> 24
        alone_stats = _marker_stats(which, rows, cols, n, flags & MARKER_ON > 0)
        bare = (_marker_stats(which, rows, cols, n, flags & MARKER_OVER > 0)[:, 3] == 0) & (alone_stats[:, 0] > 0)
        alone_stats[bare, 3] = alone_stats[bare, 0]
        full = alone_stats[:, 0].copy()
        full[_overlapping(points, slopes, radius_m, view)] = 0   # one marker hides another: no clean centroid
        kept = flags & MARKER_SEEN > 0    # a marker drawn over the model covers some of its own pixels alone
        sums = _marker_stats(which[kept], rows[kept], cols[kept], n)
        sums[:, 3] = alone_stats[:, 3]
        return full, sums


def _variant(source: str, *defines: str) -> str:
    """A shader's source with a ``#define`` of each of ``defines`` after its #version line."""
    if not defines:
        return source
    head, rest = source.split("#version 330\n", 1)
    return head + "#version 330\n" + "".join(f"#define {d}\n" for d in defines) + rest


def _shadow_uniforms(shadow: ShadowView) -> dict:
    """The colour pass's shadow uniforms that do not depend on the chunk."""
    along_u, along_w = shadow.frame.per_texel()
    return {"u_sun": tuple(shadow.frame.sun.toward()), "u_sun_u": tuple(along_u), "u_sun_w": tuple(along_w),
            "u_depth_span": shadow.depth_range[1] - shadow.depth_range[0], "u_bias": shadow.bias,
            "u_radius": shadow.radius, "u_shadow_ambient": shadow.ambient}


def marker_images(points: np.ndarray, slopes: np.ndarray, radius_m: float,
                  view: TileView) -> tuple[np.ndarray, np.ndarray]:
    """Where (n, 3) markers of slope (n, 2) fall in ``view``'s image plane: their (n, 2) centres and
    the (n,) radius around each that holds its whole image (plus 2 pixels).

    Each marker's image is an ellipse around its projected centre whose longest semi-axis
    is radius·σ_max(J), J the 2×2 Jacobian of the map projection on the marker's plane.
    """
    from pipeline25d.geometry.camera import image_stretch, project, project_above_ground

    p = view.perspective
    if view.ground is None:
        centres = project(points, p, view.z0, view.camera)[:, :2]
    else:
        centres = project_above_ground(points, view.ground(points[:, 0], points[:, 1]), p)[:, :2]
    reach = image_stretch(p, slopes, view.camera) * radius_m + 2 * (view.extent.width / view.size[0])   # + 2 px
    return centres, reach


def _overlapping(points: np.ndarray, slopes: np.ndarray, radius_m: float, view: TileView) -> np.ndarray:
    """(n,) bool: markers whose images could touch another marker's image in this view
    (:func:`marker_images`)."""
    n = len(points)
    if n < 2:
        return np.zeros(n, dtype=bool)
    centres, reach = marker_images(points, slopes, radius_m, view)
    out = np.zeros(n, dtype=bool)
    for lo in range(0, n, 1024):   # pairwise in blocks: a tile holds hundreds of markers, not millions
        d = np.hypot(*(centres[lo:lo + 1024, None, :] - centres[None, :, :]).transpose(2, 0, 1))
        touch = d < reach[lo:lo + 1024, None] + reach[None, :]
        touch[np.arange(touch.shape[0]), np.arange(lo, lo + touch.shape[0])] = False
        out[lo:lo + 1024] |= touch.any(axis=1)
    return out


def marker_geometry(centres: np.ndarray, slopes: np.ndarray,
                    radius: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Disks (triangle fans) in the ground plane around (n, 3) local centres, coloured by id + 1.

    Each disk lies in the plane z = z_c + s_x·dx + s_y·dy of its (n, 2) slopes and has
    horizontal radius ``radius``. Every projection here is affine over a disk, and an
    affine map takes a disk's centroid to its image's centroid, so the pixel centroid
    estimates the centre without bias in any view.
    """
    n, k = len(centres), MARKER_SEGMENTS
    ang = np.linspace(0, 2 * np.pi, k, endpoint=False)
    ring = np.column_stack([np.cos(ang), np.sin(ang)]) * radius
    offsets = np.zeros((n, k + 1, 3))
    offsets[:, 1:, :2] = ring[None]
    slopes = np.asarray(slopes, dtype=np.float64).reshape(n, 2)
    offsets[:, 1:, 2] = ring[None, :, 0] * slopes[:, :1] + ring[None, :, 1] * slopes[:, 1:]
    verts = (centres[:, None, :] + offsets).reshape(-1, 3)
    base = np.arange(n)[:, None] * (k + 1)
    j = np.arange(k)
    fan = np.column_stack([np.zeros(k, int), 1 + j, 1 + (j + 1) % k])
    faces = (base[:, None, :] + fan[None]).reshape(-1, 3)
    ids = np.arange(1, n + 1)
    rgb = np.column_stack([ids & 255, (ids >> 8) & 255, (ids >> 16) & 255, np.full(n, 255)]).astype(np.uint8)
    colors = np.repeat(rgb, k + 1, axis=0)
    return verts, faces, colors


def _read_depth(texture, w: int, h: int) -> np.ndarray:
    """(h, w) float32 window depth in [0, 1] of a depth texture, row 0 at the top."""
    return np.frombuffer(texture.read(alignment=1), dtype=np.float32).reshape(h, w)[::-1]


def _read_rgba(fbo, w: int, h: int) -> np.ndarray:
    """(h, w, 4) uint8 framebuffer contents with row 0 at the top (north); GL's row 0 is the bottom."""
    return np.frombuffer(fbo.read(components=4), dtype=np.uint8).reshape(h, w, 4)[::-1]


def _marker_stats(which: np.ndarray, rows: np.ndarray, cols: np.ndarray, n: int,
                  flag: np.ndarray | None = None) -> np.ndarray:
    """(n, 4) float64 per marker: pixel count, Σ(col + 0.5), Σ(row + 0.5) (row 0 = north), and
    the count of its pixels where ``flag`` is true, from marker pixels: each one's marker id + 1
    (``which``, never 0) at ``rows``, ``cols``, and ``flag`` there."""
    which = which.astype(np.int64) - 1
    stats = np.zeros((n, 4))
    if n:
        stats[:, 0] = np.bincount(which, minlength=n)[:n]
        if flag is not None:
            stats[:, 3] = np.bincount(which, weights=flag.astype(float), minlength=n)[:n]
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
