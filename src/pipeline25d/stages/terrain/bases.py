"""Ground from where buildings stand: building bases as ground samples and the TIN between them.

A city model of buildings alone (CityJSON, CityGML LOD1/2, 3D BAG, PLATEAU) carries no
terrain, and its nadir surface holds only roofs, so the Cloth Simulation Filter has no
ground to find. Its ground is where its walls end:

1. **Buildings** are the connected groups of the model's building surfaces (vertices welded
   at 1 mm; buildings that touch count once).
2. **Samples** of a building: the vertices of its ground surfaces (GroundSurface, or for
   surfaces without semantics the downward-facing ones: an LOD1 solid's floor) where it has
   any; else its wall bottoms: at every corner (an (x, y) holding wall vertices at two heights
   or more, to 1 cm) the lowest wall vertex, less those more than :data:`BASE_TOL_M` above the
   lower side of their convex hull (window sills, walls standing on a lower part's roof). A
   gable's apex holds one vertex and is no corner. A sample that stands on the model is no
   ground (:func:`~pipeline25d.geometry.standing.standing`): one over a surface more than
   :data:`BASE_TOL_M` below it, or on the roof of another building that reaches lower (the
   feet of a tower or a storey set back drawn as a solid of its own, a part whose floor lies on
   another part). A building all of whose samples stand so stands on another (``stacked``).
3. **TIN**: the samples of all buildings (one per (x, y) to 1 cm, the lowest) are joined by
   their Delaunay triangulation in plan, less the triangles with an edge longer than
   ``max_edge`` (twice the largest object: the reach of the DTM beyond ground, so buildings
   farther apart are not joined across empty land). On a plane the TIN is the plane
   exactly; under a building it is the building's base. Cells take its height at their
   centres (float64), samples in cells no triangle covers their own.

Memory and time follow the samples and the cells near them, not the scene's extent: a
window of cells is evaluated only in its squares of :data:`SQUARE_CELLS` cells that a
kept triangle's bounding box meets.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from pipeline25d.core.grid import Grid
from pipeline25d.core.mesh import Mesh
from pipeline25d.formats.surfaces import ROOF_NZ
from pipeline25d.geometry.standing import standing

log = logging.getLogger(__name__)

WELD_M = 0.001            # vertices this close are one (buildings' connectivity)
COLUMN_M = 0.01           # wall vertices this close in plan share a corner; heights this close are one
BASE_TOL_M = 0.5          # a wall bottom more than this above the lower side of its building's hull is no base
SQUARE_CELLS = 64         # cells are evaluated by squares of this edge that a triangle may cover


@dataclass(frozen=True)
class BaseSamples:
    """Ground samples (n, 3) float64 of a model's buildings, how many buildings gave some, how
    many of those from ground surfaces (the others from wall bottoms), and how many buildings
    stand on others (all their samples on a roof: none taken)."""

    points: np.ndarray
    buildings: int
    from_ground_surfaces: int
    stacked: int = 0


def base_samples(mesh: Mesh) -> BaseSamples:
    """The ground samples of a model's building parts (named by colour class: "ground", "wall" ...)."""
    parts = [p for p in mesh.parts if p.n_triangles]
    if not parts:
        return BaseSamples(np.empty((0, 3)), 0, 0)
    offsets = np.cumsum([0] + [len(p.vertices) for p in parts])
    verts = np.concatenate([p.vertices for p in parts])
    faces = np.concatenate([p.faces + o for p, o in zip(parts, offsets)])
    kind = np.concatenate([np.full(p.n_triangles, p.name, dtype=object) for p in parts])
    origin = verts.min(axis=0)
    points, faces = welded(verts, faces)
    label = components(faces, len(points))
    ground = np.unique(faces[kind == "ground"].ravel())
    walls = np.unique(faces[kind == "wall"].ravel())
    walls = walls[~np.isin(label[walls], label[ground])]
    bottoms, bottom_label = _wall_bottoms(points[walls], label[walls], origin)
    samples, owner = np.concatenate([points[ground], bottoms]), np.r_[label[ground], bottom_label]
    kept = ~standing(samples, owner, points[faces], label[faces[:, 0]], BASE_TOL_M, ROOF_NZ)
    buildings = np.unique(owner[kept])
    return BaseSamples(samples[kept], len(buildings), len(np.unique(owner[:len(ground)][kept[:len(ground)]])),
                       len(np.unique(owner)) - len(buildings))


def welded(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(points, faces) with the vertices within :data:`WELD_M` of each other made one."""
    origin = vertices.min(axis=0)
    _, first, weld = np.unique(np.round((vertices - origin) / WELD_M).astype(np.int64), axis=0,
                               return_index=True, return_inverse=True)
    return vertices[first], weld.reshape(-1)[faces]


def components(faces: np.ndarray, n: int) -> np.ndarray:
    """Connected-component label of each of ``n`` vertices joined by triangles ``faces``."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    rows = np.concatenate([faces[:, 0], faces[:, 1]])
    cols = np.concatenate([faces[:, 1], faces[:, 2]])
    graph = coo_matrix((np.ones(len(rows), np.int8), (rows, cols)), shape=(n, n))
    return connected_components(graph, directed=False)[1]


def _wall_bottoms(points: np.ndarray, label: np.ndarray, origin: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The wall bottoms (k, 3) of the buildings (``label``) without ground surfaces (see the module),
    and the building of each."""
    none = np.empty((0, 3)), np.empty(0, label.dtype)
    if not len(points):
        return none
    key = np.round((points - origin) / COLUMN_M).astype(np.int64)
    order = np.lexsort((key[:, 2], key[:, 1], key[:, 0], label))        # by building, corner, then height
    points, label, key = points[order], label[order], key[order]
    corner = np.r_[True, (label[1:] != label[:-1]) | (key[1:, :2] != key[:-1, :2]).any(axis=1)]
    corner_id = np.cumsum(corner) - 1
    new_height = np.r_[True, (key[1:, 2] != key[:-1, 2]) | corner[1:]]
    heights = np.bincount(corner_id, weights=new_height)
    lowest = np.flatnonzero(corner)[heights >= 2]                       # the first of a corner is its lowest
    if not len(lowest):
        return none
    points, label = points[lowest], label[lowest]
    ends = np.flatnonzero(np.r_[label[1:] != label[:-1], True]) + 1
    bottoms = [_lower_hull(p) for p in np.split(points, ends[:-1])]
    return np.concatenate(bottoms), np.repeat(label[ends - 1], [len(b) for b in bottoms])


def _lower_hull(points: np.ndarray) -> np.ndarray:
    """The points at most :data:`BASE_TOL_M` above the lower side of their convex hull: what stands
    higher is no base. Fewer than four points, or all in a plane: all of them."""
    from scipy.spatial import ConvexHull, QhullError

    if len(points) < 4:
        return points
    local = points - points.mean(axis=0)
    try:
        hull = ConvexHull(local)
    except QhullError:                          # all in a plane (a building on flat or sloped ground)
        return points
    facets = hull.equations[hull.equations[:, 2] < -1e-9]                # facing down: n·p + d = 0
    # the lower side is convex: its height at (x, y) is the highest of its facets' planes there
    floor = (-(local[:, :2] @ facets[:, :2].T + facets[:, 3]) / facets[:, 2]).max(axis=1)
    return points[local[:, 2] - floor <= BASE_TOL_M]


class BaseTin:
    """The TIN of base samples (see the module): heights at the cell centres of any grid window."""

    def __init__(self, points: np.ndarray, max_edge: float):
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        self.origin = pts[:, :2].min(axis=0) if len(pts) else np.zeros(2)
        key = np.round((pts[:, :2] - self.origin) / COLUMN_M).astype(np.int64)
        order = np.lexsort((pts[:, 2], key[:, 1], key[:, 0]))
        first = order[np.r_[True, (key[order][1:] != key[order][:-1]).any(axis=1)]]
        self.points = pts[first]                                         # one per (x, y): the lowest
        self.xy = self.points[:, :2] - self.origin
        self.tri, self.kept, self.boxes = None, np.zeros(0, bool), np.empty((0, 4))
        if len(self.points) >= 3:
            self._triangulate(max_edge)

    def _triangulate(self, max_edge: float) -> None:
        from scipy.spatial import Delaunay, QhullError

        try:
            tri = Delaunay(self.xy)
        except QhullError:                       # all in a line: the samples alone
            return
        corners = self.xy[tri.simplices]
        edges = np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2)
        self.tri, self.kept = tri, edges.max(axis=1) <= max_edge
        kept = corners[self.kept] + self.origin
        self.boxes = np.c_[kept.min(axis=1), kept.max(axis=1)]           # xmin, ymin, xmax, ymax

    @property
    def n_triangles(self) -> int:
        return int(self.kept.sum())

    def heights(self, grid: Grid) -> np.ndarray:
        """(height, width) float64: the TIN's height at each cell centre of ``grid``, else the
        lowest sample in the cell, else NaN."""
        out = np.full(grid.shape, np.nan)
        x0, y0, x1, y1 = grid.bounds
        meets = ((self.boxes[:, 0] <= x1) & (self.boxes[:, 2] >= x0) & (self.boxes[:, 1] <= y1)
                 & (self.boxes[:, 3] >= y0))
        if meets.any():
            rows, cols = np.nonzero(self._squares(grid, self.boxes[meets]))
            xs, ys = grid.column_x() - self.origin[0], grid.row_y() - self.origin[1]
            xy = np.c_[xs[cols], ys[rows]]
            simplex = self.tri.find_simplex(xy)
            inside = simplex >= 0
            inside[inside] = self.kept[simplex[inside]]
            s = simplex[inside]
            t = self.tri.transform[s]
            b = np.einsum("ijk,ik->ij", t[:, :2], xy[inside] - t[:, 2])
            weights = np.c_[b, 1.0 - b.sum(axis=1)]
            out[rows[inside], cols[inside]] = np.einsum("ij,ij->i", weights,
                                                        self.points[self.tri.simplices[s], 2])
        self._burn_samples(out, grid)
        return out

    @staticmethod
    def _squares(grid: Grid, boxes: np.ndarray) -> np.ndarray:
        """Cells of ``grid`` in the squares of :data:`SQUARE_CELLS` cells that ``boxes`` meet."""
        q = SQUARE_CELLS
        nr, nc = -(-grid.height // q), -(-grid.width // q)
        cols0, rows0 = grid.colrow(boxes[:, 0], boxes[:, 3])     # the boxes' top-left and bottom-right cells
        cols1, rows1 = grid.colrow(boxes[:, 2], boxes[:, 1])
        c0, c1 = (np.clip(np.floor(c / q).astype(np.int64), 0, nc - 1) for c in (cols0, cols1))
        r0, r1 = (np.clip(np.floor(r / q).astype(np.int64), 0, nr - 1) for r in (rows0, rows1))
        diff = np.zeros((nr + 1, nc + 1), np.int64)           # 2-D difference array of the boxes' squares
        np.add.at(diff, (r0, c0), 1)
        np.add.at(diff, (r0, c1 + 1), -1)
        np.add.at(diff, (r1 + 1, c0), -1)
        np.add.at(diff, (r1 + 1, c1 + 1), 1)
        squares = diff.cumsum(axis=0).cumsum(axis=1)[:nr, :nc] > 0
        return np.repeat(np.repeat(squares, q, axis=0), q, axis=1)[:grid.height, :grid.width]

    def _burn_samples(self, out: np.ndarray, grid: Grid) -> None:
        """The lowest sample in each cell of ``out`` no triangle covers (a building smaller than a cell)."""
        col, row = (np.floor(v).astype(np.int64) for v in grid.colrow(self.points[:, 0], self.points[:, 1]))
        inside = (row >= 0) & (row < grid.height) & (col >= 0) & (col < grid.width)
        if not inside.any():
            return
        lowest = np.full(grid.shape, np.inf)
        np.minimum.at(lowest, (row[inside], col[inside]), self.points[inside, 2])
        take = np.isnan(out) & np.isfinite(lowest)
        out[take] = lowest[take]


BASE_AGREEMENT_M = 1.0    # a CSF ground cell this close to the bases' TIN keeps its own height


@dataclass
class DistrictBases:
    """The building bases of a scene's inputs: the TIN of their samples, the districts that gave
    some, those made of buildings alone (their surface holds no ground for CSF) and the counts
    (``stacked``: buildings standing on others, which gave none)."""

    tin: BaseTin | None
    districts: list[str]
    buildings_only: list[str]
    buildings: int = 0
    from_ground_surfaces: int = 0
    by_shape: list[str] = field(default_factory=list)
    stacked: int = 0

    def describe(self) -> str:
        """The record's words for this ground source."""
        walls = self.buildings - self.from_ground_surfaces
        return (f"building bases of {', '.join(self.districts)}: {self.buildings} buildings "
                f"({self.from_ground_surfaces} by ground surfaces, {walls} by wall bottoms), "
                f"{len(self.tin.points)} samples" + (f"; {self.stacked} standing on others" if self.stacked else ""))

    def record(self) -> dict:
        return {"districts": self.districts, "buildings_only": self.buildings_only, "buildings": self.buildings,
                "from_ground_surfaces": self.from_ground_surfaces, "samples": len(self.tin.points),
                "triangles": self.tin.n_triangles, **({"by_shape": self.by_shape} if self.by_shape else {}),
                **({"stacked": self.stacked} if self.stacked else {})}


def district_bases(inputs: dict, scene_crs: str, skip: list[str], max_edge: float,
                   by_shape: Callable[[str], tuple[Mesh, bool] | None] | None = None) -> DistrictBases:
    """The building bases of the inputs not in ``skip`` (those with their own terrain): of their
    building objects where their format has some (:func:`pipeline25d.formats.load_district_buildings`),
    else of those ``by_shape`` finds in the input of that name (the buildings' mesh and whether
    the input draws anything else, or None: :mod:`pipeline25d.stages.terrain.shapes`)."""
    from pipeline25d.formats import load_district_buildings

    samples, found = [], DistrictBases(None, [], [])
    for name, spec in sorted(inputs.items()):
        if name in skip:
            continue
        loaded = load_district_buildings(spec, scene_crs)
        shaped = loaded is None and by_shape is not None
        if shaped:
            loaded = by_shape(name)
        if loaded is None:
            continue
        mesh, others = loaded
        got = base_samples(mesh)
        if not got.buildings:
            continue
        samples.append(got.points)
        found.districts.append(name)
        if shaped:
            found.by_shape.append(name)
        if not others:
            found.buildings_only.append(name)
        found.buildings += got.buildings
        found.from_ground_surfaces += got.from_ground_surfaces
        found.stacked += got.stacked
        log.info("%s: ground from the bases of %d buildings (%d by ground surfaces), %d samples; %d buildings "
                 "standing on others", name, got.buildings, got.from_ground_surfaces, len(got.points), got.stacked)
    if samples:
        found.tin = BaseTin(np.concatenate(samples), max_edge)
    return found


def with_bases(seed: np.ndarray, base: np.ndarray, agree: float = BASE_AGREEMENT_M) -> np.ndarray:
    """Ground heights where building bases and other ground (``seed``: CSF's cells, NaN elsewhere)
    meet: where the bases' TIN has a height, a seed cell within ``agree`` of it keeps its own (the
    model's surface, measured), any other takes the TIN's (a roof or bridge CSF took for ground);
    elsewhere the seed."""
    out = np.where(np.isfinite(base), base, seed)
    keep = np.isfinite(base) & np.isfinite(seed) & (np.abs(seed - base) <= agree)
    out[keep] = seed[keep]
    return out
