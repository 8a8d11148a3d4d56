"""Which input object every pixel of a tile shows: the id pass beside the colour render.

Faces are drawn with the colour render's vertex shader (the same camera, terrain displacement and
depth test) and the same number of samples; each sample keeps the uint32 id of its face, looked up
by ``gl_PrimitiveID`` in a texture of the mesh's face ids. A resolve pass gives every pixel the id
most of its samples show (the smaller on a tie), 0 where no sample is covered. The colour render's
alpha is the share of covered samples, so a pixel has an id exactly where the colour tile is not
transparent, and an edge pixel has the object that covers most of it. Id 0 means no object.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence

import numpy as np

from pipeline25d.core.mesh import MeshPart
from pipeline25d.stages.render import FACE_WIDTH, VERTEX_SHADER, TileGeometry, TileRenderer, TileView

log = logging.getLogger(__name__)

FACE_TEXTURE_WIDTH = FACE_WIDTH      # face ids per row of a mesh's id texture

ID_FRAGMENT = """
#version 330
uniform usampler2D u_faces;
out uint f_id;
void main() {
    int p = gl_PrimitiveID;
    f_id = texelFetch(u_faces, ivec2(p % WIDTH, p / WIDTH), 0).r;
}
""".replace("WIDTH", str(FACE_TEXTURE_WIDTH))

RESOLVE_VERTEX = """
#version 330
void main() {
    vec2 corner = vec2((gl_VertexID << 1) & 2, gl_VertexID & 2);
    gl_Position = vec4(corner * 2.0 - 1.0, 0.0, 1.0);
}
"""

RESOLVE_FRAGMENT = """
#version 330
uniform usampler2DMS u_ids;
uniform int u_samples;
out uint f_id;
void main() {
    ivec2 p = ivec2(gl_FragCoord.xy);
    uint best = 0u;
    int most = 0;
    for (int i = 0; i < u_samples; i++) {
        uint id = texelFetch(u_ids, p, i).r;
        if (id == 0u) continue;
        int n = 0;
        for (int j = 0; j < u_samples; j++) n += int(texelFetch(u_ids, p, j).r == id);
        if (n > most || (n == most && id < best)) { best = id; most = n; }
    }
    f_id = best;
}
"""

FaceIds = Callable[[MeshPart], np.ndarray]


def object_face_ids(ids: dict[str, int]) -> FaceIds:
    """Face ids of a part from its objects' keys (``ids``: key -> uint32 id, never 0)."""
    def face_ids(part: MeshPart) -> np.ndarray:
        table = np.array([ids[key] for key in part.objects], dtype=np.uint32)
        return table[part.face_objects]
    return face_ids


def part_face_ids(part: MeshPart) -> np.ndarray:
    """Face ids of an ingested part (its ``object_ids`` given by ingest); 0 for a part without
    them (a chunk written before object ids: its faces are drawn as no object)."""
    if part.object_ids is None or part.face_objects is None:
        log.warning("a part of %d faces carries no object ids (a chunk ingested before them): "
                    "its pixels have no id; ingest its district again", part.n_triangles)
        return np.zeros(part.n_triangles, dtype=np.uint32)
    return part.object_ids[part.face_objects]


class IdRenderer:
    """Renders tiles of object ids; one instance per GL context (programs compiled once)."""

    def __init__(self, ctx, samples: int = 4):
        self.ctx = ctx
        self.samples = min(samples, ctx.max_samples) if samples else 0
        self.prog = ctx.program(vertex_shader=VERTEX_SHADER, fragment_shader=ID_FRAGMENT)
        self.resolve = ctx.program(vertex_shader=RESOLVE_VERTEX, fragment_shader=RESOLVE_FRAGMENT)

    def render_ids(self, chunks: Sequence[tuple[np.ndarray, list[MeshPart]]], view: TileView,
                   face_ids: FaceIds) -> np.ndarray:
        """(h, w) uint32 object id per pixel, row 0 = north edge, 0 where no object is drawn: a pass
        of its own (the render job draws the ids in its colour pass instead, :meth:`with_colour`).

        ``chunks``: (float64 origin, parts) as the colour render takes them; ``face_ids(part)``:
        the (m,) uint32 id of each of the part's faces (0: drawn as no object)."""
        import moderngl

        ctx, (w, h) = self.ctx, view.size
        ids = ctx.texture((w, h), 1, samples=self.samples, dtype="u4")
        depth = ctx.depth_renderbuffer((w, h), samples=self.samples)
        fbo = ctx.framebuffer(color_attachments=[ids], depth_attachment=depth)
        fbo.use()
        fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        ctx.enable(moderngl.DEPTH_TEST)
        ctx.disable(moderngl.CULL_FACE)
        released = [fbo, depth]
        try:
            for origin, parts in chunks:
                matrix = view.matrix(origin)
                self.prog["u_mvp"].write(matrix.T.astype("f4").tobytes())
                if "u_shear" in self.prog:
                    self.prog["u_shear"].value = view.shear(matrix)
                if "u_zbias" in self.prog:
                    self.prog["u_zbias"].value = 0.0
                for part in parts:
                    if part.n_triangles:
                        inputs, ibo = self._upload(part, origin, view)
                        released += [b for b, _, _ in inputs] + [ibo]
                        released += self._draw(inputs, ibo, face_ids(part))
            return self.read_ids(ids, (w, h), self.samples)
        finally:
            for obj in released + [ids]:
                obj.release()

    def _upload(self, part: MeshPart, origin: np.ndarray, view: TileView) -> tuple[list, object]:
        """A part's vertex inputs (positions, ground offsets in terrain mode) and index buffer."""
        ctx = self.ctx
        inputs = [(ctx.buffer(np.ascontiguousarray(part.vertices - origin, dtype="f4")), "3f", "in_pos")]
        ground = view.ground_offsets(part.vertices, origin)
        if ground is not None and "in_ground" in self.prog:
            inputs.append((ctx.buffer(np.ascontiguousarray(ground, dtype="f4")), "1f", "in_ground"))
        return inputs, ctx.buffer(np.ascontiguousarray(part.faces, dtype="u4"))

    def _draw(self, inputs: list, ibo, faces: np.ndarray) -> list:
        """Draw one mesh (its vertex ``inputs`` and index buffer) with its face ids; returns the
        GL objects this made (to release)."""
        ctx = self.ctx
        texture = face_texture(ctx, faces)
        texture.use(0)
        self.prog["u_faces"].value = 0
        vao = ctx.vertex_array(self.prog, inputs, index_buffer=ibo, index_element_size=4)
        vao.render()
        return [vao, texture]

    def with_colour(self, renderer: TileRenderer, geometry: TileGeometry, view: TileView, face_ids: FaceIds,
                    shadow=None, casters=None) -> tuple[np.ndarray, np.ndarray]:
        """The colour tile and its ids from ONE pass: ``renderer`` (made with ``ids=True``) draws the
        ids as a second render target of its colour pass (the same fragments, so the same pixels as
        :meth:`render_ids` at the cost of a lookup a fragment). Returns (RGBA, ids), row 0 north."""
        ids = ColourIds(self, face_ids)
        try:
            return renderer.render_color_ids(geometry, view, ids, shadow, casters)
        finally:
            ids.release()

    def read_ids(self, ids, size: tuple[int, int], samples: int) -> np.ndarray:
        """An ids texture of ``samples`` samples (0: one) as (h, w) uint32, row 0 north: with several,
        the per-pixel majority (:data:`RESOLVE_FRAGMENT`)."""
        w, h = size
        out = self._resolved(ids, w, h, samples) if samples else \
            np.frombuffer(ids.read(), dtype=np.uint32).reshape(h, w)
        return out[::-1].copy()

    def _resolved(self, ids, w: int, h: int, samples: int) -> np.ndarray:
        """The per-pixel majority id of the multisample ``ids`` texture, (h, w) with GL's row 0 first."""
        import moderngl

        ctx = self.ctx
        out = ctx.texture((w, h), 1, dtype="u4")
        fbo = ctx.framebuffer(color_attachments=[out])
        vao = ctx.vertex_array(self.resolve, [])
        try:
            fbo.use()
            ids.use(0)
            self.resolve["u_ids"].value = 0
            self.resolve["u_samples"].value = samples
            ctx.disable(moderngl.DEPTH_TEST)
            vao.render(vertices=3)
            return np.frombuffer(out.read(), dtype=np.uint32).reshape(h, w)
        finally:
            for obj in (vao, fbo, out):
                obj.release()


def face_texture(ctx, faces: np.ndarray):
    """A mesh's face ids as an integer texture, FACE_TEXTURE_WIDTH a row (read with texelFetch)."""
    import moderngl

    rows = max(1, -(-len(faces) // FACE_TEXTURE_WIDTH))
    table = np.zeros(rows * FACE_TEXTURE_WIDTH, dtype=np.uint32)
    table[:len(faces)] = faces
    texture = ctx.texture((FACE_TEXTURE_WIDTH, rows), 1, table.tobytes(), dtype="u4")
    texture.filter = (moderngl.NEAREST, moderngl.NEAREST)
    return texture


class ColourIds:
    """The ids render target of a colour pass (:meth:`TileRenderer.render_color_ids`): a uint32
    texture of the pass's samples, each mesh's face ids bound as it is drawn, resolved by majority."""

    def __init__(self, renderer: IdRenderer, face_ids: FaceIds):
        self.renderer, self.face_ids = renderer, face_ids
        self._textures: list = []

    def target(self, size: tuple[int, int], samples: int):
        return self.renderer.ctx.texture(size, 1, samples=samples, dtype="u4")

    def bind(self, mesh, unit: int) -> None:
        texture = face_texture(self.renderer.ctx, self.face_ids(mesh.part))
        self._textures.append(texture)
        texture.use(unit)

    def resolve(self, target, size: tuple[int, int], samples: int) -> np.ndarray:
        return self.renderer.read_ids(target, size, samples)

    def release(self) -> None:
        for texture in self._textures:
            texture.release()
        self._textures = []
