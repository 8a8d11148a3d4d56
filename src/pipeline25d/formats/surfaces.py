"""What the city-model readers (CityJSON, CityGML) share: colour classes, LOD choice, polygons.

Colours come from a small palette keyed by semantic surface type, or by city object type
when a surface has no semantics. Buildings without semantics get roof / wall / ground
colours from the surface normal (up-facing, vertical, down-facing), so LOD1 blocks still
show roofs from above. Polygons with holes are triangulated in float64 with earcut
(``mapbox_earcut``) on the plane of their Newell normal, keeping their orientation.
"""

from __future__ import annotations

import numpy as np

from pipeline25d.core.mesh import MeshPart

#: RGBA per colour class.
PALETTE: dict[str, tuple[int, int, int, int]] = {
    "roof": (168, 72, 52, 255),         # red-brown
    "wall": (232, 222, 198, 255),       # light beige
    "ground": (140, 140, 140, 255),     # grey
    "water": (66, 122, 204, 255),       # blue
    "vegetation": (76, 146, 60, 255),   # green
    "road": (88, 88, 88, 255),          # dark grey
    "landuse": (178, 214, 142, 255),    # light green
    "terrain": (206, 182, 136, 255),    # tan
    "other": (190, 190, 190, 255),      # light grey: bridges, tunnels, furniture, generic objects
}

#: semantic surface type (CityJSON semantics, CityGML thematic surfaces) -> colour class
SEMANTIC_CLASS = {
    "RoofSurface": "roof",
    "GroundSurface": "ground",
    **{t: "wall" for t in ("WallSurface", "OuterCeilingSurface", "OuterFloorSurface", "ClosureSurface",
                           "Window", "Door", "InteriorWallSurface", "CeilingSurface", "FloorSurface")},
    **{t: "water" for t in ("WaterSurface", "WaterGroundSurface", "WaterClosureSurface")},
    **{t: "road" for t in ("TrafficArea", "AuxiliaryTrafficArea", "TransportationMarking", "TransportationHole")},
}

#: city object type -> colour class; "building": colour from the surface normal
OBJECT_CLASS = {
    **{t: "building" for t in ("Building", "BuildingPart", "BuildingInstallation", "BuildingConstructiveElement",
                               "BuildingFurniture", "BuildingRoom", "BuildingStorey", "BuildingUnit")},
    **{t: "road" for t in ("Road", "Railway", "TransportationSquare", "Square", "Track", "TransportationComplex")},
    **{t: "water" for t in ("WaterBody", "Waterway")},
    **{t: "vegetation" for t in ("PlantCover", "SolitaryVegetationObject")},
    "LandUse": "landuse",
    "TINRelief": "terrain",
}

#: Ground-level object types used as terrain when a file has no TINRelief. 3dfier output
#: (e.g. Delft) models its terrain this way. PlantCover (raised to canopy height by 3dfier:
#: Delft's reaches 16.8 m), GenericCityObject (walls, fences) and Bridge are not ground.
GROUND_TYPES = frozenset({"LandUse", "Road", "Railway", "TransportationSquare", "WaterBody"})

ROOF_NZ = 0.2  # |normal z| above which a building surface counts as roof (up) or ground (down)


def normal_classes(normals: np.ndarray) -> np.ndarray:
    """Colour class of building surfaces without semantics from their (k, 3) normals."""
    length = np.linalg.norm(normals, axis=1)
    nz = np.divide(normals[:, 2], length, out=np.zeros(len(normals)), where=length > 0)
    return np.where(nz > ROOF_NZ, "roof", np.where(nz < -ROOF_NZ, "ground", "wall")).astype(object)


def class_part(cls: str, pieces: list[tuple], objects: tuple[str, ...] | None = None) -> MeshPart:
    """One MeshPart of the (vertices, faces), (vertices, faces, RGBA) or (vertices, faces, RGBA,
    face objects) ``pieces`` of colour class ``cls``: each piece in its RGBA (a material's), else in
    the class's palette colour; with ``objects`` (the keys the pieces' face objects index) the part
    carries them."""
    vertices, faces = join_pieces([(p[0], p[1]) for p in pieces])
    colors = [np.tile(np.array(p[2] if len(p) > 2 and p[2] is not None else PALETTE[cls], dtype=np.uint8),
                      (len(p[0]), 1)) for p in pieces]
    face_objects = None if objects is None else np.concatenate([p[3] for p in pieces])
    return MeshPart(vertices, faces, colors=np.concatenate(colors) if colors else np.empty((0, 4)), name=cls,
                    objects=objects or (), face_objects=face_objects)


def join_pieces(pieces: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """(vertices, faces) of meshes given as (vertices, faces) pairs, faces re-indexed."""
    offsets = np.cumsum([0] + [len(v) for v, _ in pieces])
    vertices = np.concatenate([v for v, _ in pieces]) if pieces else np.empty((0, 3))
    faces = (np.concatenate([f + o for (_, f), o in zip(pieces, offsets)]) if pieces
             else np.empty((0, 3), np.int64))
    return vertices, faces


def lod_key(lod) -> tuple[int, ...]:
    """Sortable key of a LOD ("2.2" -> (2, 2); 1.0's numeric 2 -> (2,))."""
    text = f"{lod:g}" if isinstance(lod, (int, float)) else str(lod)
    try:
        return tuple(int(p) for p in text.split("."))
    except ValueError:
        return (-1,)


def pick_lod(keys, lod) -> tuple[int, ...] | None:
    """The LOD key to draw among ``keys``: ``lod``, else the highest below it, else (so no
    object disappears) the lowest; ``lod`` None: the highest. None when ``keys`` is empty."""
    keys = sorted(set(keys))
    if not keys:
        return None
    if lod is None:
        return keys[-1]
    below = [k for k in keys if k <= lod_key(lod)]
    return below[-1] if below else keys[0]


def triangulate_polygon(rings: list[list[int]], vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """((k, 3) int64 vertex indices, Newell normal) of a planar polygon with holes.

    ``rings``: outer ring first, then holes, as indices into ``vertices``. Projects onto
    the coordinate plane most parallel to the polygon (affine, so topology is kept),
    triangulates with earcut, and orients every triangle like the polygon.
    """
    outer_ring = _clean_ring(rings[0]) if rings else []
    if len(outer_ring) < 3:
        return np.empty((0, 3), np.int64), np.zeros(3)
    clean = [outer_ring] + [r for r in (_clean_ring(ring) for ring in rings[1:]) if len(r) >= 3]
    outer = vertices[outer_ring]
    normal = newell(outer)
    if len(clean) == 1 and len(clean[0]) == 3:
        return np.asarray([clean[0]], dtype=np.int64), normal
    if not normal.any():
        return np.empty((0, 3), np.int64), normal
    import mapbox_earcut

    index = np.concatenate([np.asarray(r, dtype=np.int64) for r in clean])
    pts = vertices[index]
    drop = int(np.argmax(np.abs(normal)))
    flat = np.delete(pts - outer.mean(axis=0), drop, axis=1)
    ends = np.cumsum([len(r) for r in clean]).astype(np.uint32)
    local = mapbox_earcut.triangulate_float64(np.ascontiguousarray(flat), ends).astype(np.int64).reshape(-1, 3)
    if not len(local):
        return np.empty((0, 3), np.int64), normal
    tri = pts[local]
    facing = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]) @ normal
    local[facing < 0] = local[facing < 0][:, [0, 2, 1]]
    return index[local], normal


def _clean_ring(ring: list[int]) -> list[int]:
    """Ring without consecutive repeats and without a closing repeat of the first vertex."""
    out = [int(i) for k, i in enumerate(ring) if k == 0 or i != ring[k - 1]]
    while len(out) > 1 and out[-1] == out[0]:
        out.pop()
    return out


def newell(points: np.ndarray) -> np.ndarray:
    """Newell normal (area-weighted, unnormalised) of a closed 3D ring."""
    p = points - points.mean(axis=0)
    q = np.roll(p, -1, axis=0)
    return np.array([
        np.sum((p[:, 1] - q[:, 1]) * (p[:, 2] + q[:, 2])),
        np.sum((p[:, 2] - q[:, 2]) * (p[:, 0] + q[:, 0])),
        np.sum((p[:, 0] - q[:, 0]) * (p[:, 1] + q[:, 1])),
    ])
