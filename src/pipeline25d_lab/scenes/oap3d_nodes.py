"""Nodes of the generated OAP3D city: a level-of-detail quadtree per tile, each node a textured mesh.

A node at level k covers a square of ``tile / 2**k`` metres. Its mesh is ``charts x charts``
grid patches of ``cells x cells`` cells (vertices duplicated along patch borders), each patch
textured by its own chart of the node's JPEG atlas: the chart's texels (``content`` a side)
with a ``gutter`` of repeated edge texels around it, the charts placed in the atlas in a
seeded order, as photogrammetry software packs them. Every level has the same cells and atlas
per node, so a level has 4x the triangles and texels of the one above it and its texel is half
as large (:meth:`Spec.texel`). Each texel carries a photograph's grain (:data:`GRAIN`, seeded per node).
"""

from __future__ import annotations

import io
from dataclasses import dataclass

import numpy as np

from pipeline25d_lab.scenes.oap3d_city import City

GRAIN = 5.0        # grey levels: a photograph's grain on every texel (and JPEG bytes like a photo's)


@dataclass(frozen=True)
class Spec:
    """Size of a generated dataset."""

    tiles: tuple[int, int]     # tiles in x and y
    tile: float = 200.0        # tile edge, m
    levels: int = 4            # PagedLOD levels (0: the tile's root node)
    atlas: int = 512           # atlas edge per node, px
    charts: int = 2            # charts per node edge
    gutter: int = 4            # texels of edge repeat around each chart
    cells: int = 18            # grid cells per chart edge
    quality: int = 90          # JPEG quality

    @property
    def content(self) -> int:
        """Texels of a chart's own content per edge."""
        return self.atlas // self.charts - 2 * self.gutter

    def texel(self, level: int) -> float:
        """Metres per texel at ``level``."""
        return self.tile / 2 ** level / (self.charts * self.content)

    def level_for_gsd(self, gsd: float) -> int:
        """The level a map of ``gsd`` draws (both readers): the coarsest whose texel is below the gsd."""
        return next((k for k in range(self.levels) if gsd > self.texel(k)), self.levels - 1)

    def triangles(self, level: int) -> int:
        """Triangles of the whole dataset at ``level``."""
        return self.tiles[0] * self.tiles[1] * 4 ** level * 2 * (self.charts * self.cells) ** 2

    @property
    def extent(self) -> tuple[float, float]:
        return self.tiles[0] * self.tile, self.tiles[1] * self.tile


@dataclass
class Node:
    """One node's mesh (float64 vertices relative to SRSOrigin), GL-convention UVs and its JPEG atlas."""

    level: int
    path: str                  # quadrant digits from the tile's root ("" for the root)
    x0: float
    y0: float
    edge: float
    vertices: np.ndarray
    faces: np.ndarray
    uv: np.ndarray
    jpeg: bytes

    @property
    def radius(self) -> float:
        """Bounding radius: half the diagonal of the node's box over its vertices' heights."""
        dz = float(np.ptp(self.vertices[:, 2]))
        return 0.5 * float(np.sqrt(2 * self.edge ** 2 + dz ** 2))

    @property
    def centre(self) -> tuple[float, float, float]:
        z = self.vertices[:, 2]
        return (self.x0 + self.edge / 2, self.y0 + self.edge / 2, float(z.min() + z.max()) / 2)


def make_node(city: City, spec: Spec, level: int, path: str, x0: float, y0: float, seed: int) -> Node:
    """The node at ``level`` whose south-west corner is (x0, y0)."""
    from PIL import Image

    edge = spec.tile / 2 ** level
    texel = spec.texel(level)
    n = spec.charts * spec.content
    xs, ys = x0 + (np.arange(n) + 0.5) * texel, y0 + (np.arange(n) + 0.5) * texel
    rng = np.random.default_rng([seed, level, int(path or "0", 4), len(path)])
    picture = city.paint(xs, ys, texel)[::-1]            # row 0 = north edge
    picture += (GRAIN * rng.standard_normal((n, n), dtype=np.float32))[..., None]
    np.clip(picture, 0, 255, out=picture)
    slots = rng.permutation(spec.charts ** 2)
    slot_px = spec.atlas // spec.charts
    atlas = np.zeros((spec.atlas, spec.atlas, 3), np.uint8)
    verts, faces, uvs = [], [], []
    chart_edge = edge / spec.charts
    s = np.linspace(0.0, 1.0, spec.cells + 1)
    fu, fv = np.meshgrid(s, s)                            # row j = y (south to north), column i = x
    m = spec.cells
    corner = (np.arange(m)[None, :] + (m + 1) * np.arange(m)[:, None]).ravel()
    quad = np.concatenate([np.column_stack([corner, corner + 1, corner + m + 2]),
                           np.column_stack([corner, corner + m + 2, corner + m + 1])])
    c = spec.content
    for k in range(spec.charts ** 2):
        ci, cj = k % spec.charts, k // spec.charts            # chart column (x) and row (y, south first)
        sx, sy = slots[k] % spec.charts, slots[k] // spec.charts   # slot column and row (top first)
        rows = slice((spec.charts - 1 - cj) * c, (spec.charts - cj) * c)
        pad = ((spec.gutter,) * 2, (spec.gutter,) * 2, (0, 0))
        block = np.pad(picture[rows, ci * c:(ci + 1) * c], pad, mode="edge")
        atlas[sy * slot_px:(sy + 1) * slot_px, sx * slot_px:(sx + 1) * slot_px] = np.round(block)
        cx, cy = x0 + ci * chart_edge, y0 + cj * chart_edge
        x, y = cx + fu * chart_edge, cy + fv * chart_edge
        z = city.height(x[0], y[:, 0])
        faces.append(quad + sum(len(v) for v in verts))
        verts.append(np.column_stack([x.ravel(), y.ravel(), z.ravel()]))
        u = (sx * slot_px + spec.gutter + fu * c) / spec.atlas
        v = 1.0 - (sy * slot_px + spec.gutter + (1.0 - fv) * c) / spec.atlas
        uvs.append(np.column_stack([u.ravel(), v.ravel()]))
    vertices = np.concatenate(verts).astype(np.float32).astype(np.float64)   # what a float32 file holds
    buf = io.BytesIO()
    Image.fromarray(atlas, "RGB").save(buf, format="JPEG", quality=spec.quality)
    return Node(level, path, x0, y0, edge, vertices, np.concatenate(faces).astype(np.uint32),
                np.concatenate(uvs).astype(np.float32).astype(np.float64), buf.getvalue())


def children(node_path: str, x0: float, y0: float, edge: float) -> list[tuple[str, float, float]]:
    """(path, x0, y0) of a node's four quadrants: 0 south-west, 1 south-east, 2 north-west, 3 north-east."""
    half = edge / 2
    return [(node_path + str(q), x0 + (q % 2) * half, y0 + (q // 2) * half) for q in range(4)]
