"""Buildings found by their shape, in models that name no buildings.

A 3D Tiles, glTF or OBJ city of LOD1/LOD2 buildings (PLATEAU, 3D BAG, pg2b3dm exports ...)
has no building objects to ask for (:func:`pipeline25d.formats.load_district_buildings`) and
draws no ground between its buildings: seen from above it is roofs over empty land, and the
Cloth Simulation Filter takes its lowest roofs for ground. Its buildings are found by shape:

1. **Chunks with empty land** only: where the DSM covers all but :data:`EMPTY_SHARE` of the
   cells of a chunk and :data:`AROUND_M` around it, the model draws its own ground there (a
   photomesh, a LiDAR mesh), and the chunk is not looked at. (The margin: a chunk may be
   one roof.)
2. **Groups**: the chunk's triangles joined where they share vertices (welded at 1 mm), at
   the level of detail the DSM was rendered from.
3. A group is a **building** when what can be seen of it from above does not reach its
   foot: of its level triangles (roofs, floors; not walls), those the DSM shows (its height
   at their centroid less than :data:`MIN_STOREY_M` above them) and that lie within
   :data:`MIN_STOREY_M` of the group's lowest point make at most :data:`FOOT_SHARE` of the
   plan area shown. A piece of terrain is seen at its lowest point; a building's foot is
   hidden under its roof, whichever way its floor faces (exporters flip some).
4. The buildings' triangles go to :func:`~pipeline25d.stages.terrain.bases.base_samples` as
   parts named by their normals (up: roof, down: ground, else wall:
   :func:`~pipeline25d.formats.surfaces.normal_classes`), where the input is buildings alone
   (:attr:`ShapeBuildings.others`): a model that draws its own ground (terrain patches, a
   photomesh) keeps the filter's, which measures it, rather than a TIN between wall bottoms.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from pipeline25d.core.geotiff import FloatRaster
from pipeline25d.core.grid import Grid
from pipeline25d.core.mesh import Mesh, MeshPart

log = logging.getLogger(__name__)

EMPTY_SHARE = 0.05        # a chunk whose DSM cells are empty by more than this may hold buildings alone
AROUND_M = 20.0           # ... its cells and those this far around it
MIN_STOREY_M = 2.0        # a building's roofs and floors stand at least this far above its foot
FOOT_SHARE = 0.05         # share of a building's plan area seen from above that may lie at its foot
OTHERS_SHARE = 0.05       # an input is buildings alone if the rest is at most this share of what is seen

ChunkLoader = tuple[np.ndarray, Callable[[], tuple[np.ndarray, list[MeshPart]]]]


@dataclass(frozen=True)
class ShapeBuildings:
    """What :func:`buildings_by_shape` found in one input: the buildings' triangles (parts
    "roof", "wall", "ground"), how many groups were looked at and how many are buildings, the
    plan area seen from above of the groups that are not buildings and of all (m²), and how
    many chunks draw their own ground (not looked at)."""

    mesh: Mesh
    groups: int
    buildings: int
    others_seen_m2: float
    seen_m2: float
    ground_chunks: int

    @property
    def others(self) -> bool:
        """Whether the input also draws something that is not a building: its own ground, or groups
        that are not buildings making more than :data:`OTHERS_SHARE` of the area seen (below that:
        sheds, walls, stray triangles, lower than a storey)."""
        return self.ground_chunks > 0 or self.others_seen_m2 > OTHERS_SHARE * self.seen_m2


def buildings_by_shape(chunks: Sequence[ChunkLoader], dsm: FloatRaster) -> ShapeBuildings:
    """The buildings among one input's chunks ((bounds, load) pairs; see the module)."""
    pieces: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {"roof": [], "wall": [], "ground": []}
    groups = buildings = ground_chunks = 0
    others_seen = seen = 0.0
    for bounds, load in chunks:
        window = _dsm_window(dsm, np.asarray(bounds) + [[-AROUND_M], [AROUND_M]])
        if window is None:
            continue
        if np.isfinite(window[0]).mean() >= 1.0 - EMPTY_SHARE:
            ground_chunks += 1
            continue
        _, parts = load()
        found = _chunk_buildings(parts, dsm.grid, window)
        if found is None:
            continue
        points, faces, classes, in_building, is_building, seen_area = found
        groups, buildings = groups + len(is_building), buildings + int(is_building.sum())
        others_seen, seen = others_seen + float(seen_area[~is_building].sum()), seen + float(seen_area.sum())
        for name in pieces:
            pieces[name].append((points, faces[in_building & (classes == name)]))
    parts = [_part(name, p) for name, p in pieces.items() if p]
    return ShapeBuildings(Mesh([p for p in parts if p.n_triangles]), groups, buildings, others_seen, seen,
                          ground_chunks)


def _dsm_window(dsm: FloatRaster, bounds: np.ndarray) -> tuple[np.ndarray, int, int] | None:
    """The DSM's cells whose centres lie in the plan ``bounds`` (a chunk's, widened) and the row and
    column of the first; None if there are none."""
    grid = dsm.grid
    c0, r0 = grid.colrow(bounds[0][0], bounds[1][1])
    c1, r1 = grid.colrow(bounds[1][0], bounds[0][1])
    cols = slice(max(int(np.ceil(c0 - 0.5)), 0), min(int(np.floor(c1 - 0.5)) + 1, grid.width))
    rows = slice(max(int(np.ceil(r0 - 0.5)), 0), min(int(np.floor(r1 - 0.5)) + 1, grid.height))
    if cols.stop <= cols.start or rows.stop <= rows.start:
        return None
    return dsm.read(rows, cols), rows.start, cols.start


def _chunk_buildings(parts: list[MeshPart], grid: Grid, window: tuple[np.ndarray, int, int]
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """(points, faces, class of each face, whether its group is a building; per group: whether it is
    a building, its plan area seen from above) of a chunk's parts, the DSM of ``grid`` read around
    them (:func:`_dsm_window`).

    Classes by normal, but a downward face is "ground" only at its group's foot (within
    :data:`~pipeline25d.stages.terrain.bases.BASE_TOL_M` of its lowest point): higher, it is
    the underside of an overhang, and counts as wall."""
    from pipeline25d.formats.surfaces import join_pieces, normal_classes
    from pipeline25d.stages.terrain.bases import BASE_TOL_M, components, welded

    parts = [p for p in parts if p.n_triangles]
    if not parts:
        return None
    points, faces = welded(*join_pieces([(p.vertices, p.faces) for p in parts]))
    label = components(faces, len(points))
    n = int(label.max()) + 1
    foot = np.full(n, np.inf)
    np.minimum.at(foot, label, points[:, 2])
    tri = points[faces]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    by_normal = normal_classes(normal)
    classes = by_normal.copy()
    centre = tri.mean(axis=1)
    group = label[faces[:, 0]]
    height = centre[:, 2] - foot[group]                              # above the group's lowest point
    classes[(classes == "ground") & (height > BASE_TOL_M)] = "wall"
    level = by_normal != "wall"
    above = np.full(len(faces), np.nan)
    above[level] = _sample(grid, window, centre[level, 0], centre[level, 1]) - centre[level, 2]
    seen = level & np.isfinite(above) & (above < MIN_STOREY_M)
    at_foot = seen & (height < MIN_STOREY_M)
    area = np.abs(normal[:, 2]) / 2                                  # plan area
    seen_area = np.bincount(group[seen], weights=area[seen], minlength=n)
    foot_area = np.bincount(group[at_foot], weights=area[at_foot], minlength=n)
    is_building = (seen_area > 0) & (foot_area <= FOOT_SHARE * seen_area)
    return points, faces, classes, is_building[group], is_building, seen_area


def _sample(grid: Grid, window: tuple[np.ndarray, int, int], x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """The DSM at the cells of ``grid`` holding (x, y), from the ``window`` read of it (NaN outside)."""
    values, r0, c0 = window
    col, row = (np.floor(v).astype(np.int64) for v in grid.colrow(x, y))
    r, c = row - r0, col - c0
    inside = (r >= 0) & (r < values.shape[0]) & (c >= 0) & (c < values.shape[1])
    out = np.full(len(x), np.nan)
    out[inside] = values[r[inside], c[inside]]
    return out


def _part(name: str, pieces: list[tuple[np.ndarray, np.ndarray]]) -> MeshPart:
    """One part of the triangles ``pieces`` ((points, faces) per chunk) named ``name``."""
    from pipeline25d.formats.surfaces import join_pieces

    vertices, faces = join_pieces(pieces)
    return MeshPart(vertices, faces, name=name)
