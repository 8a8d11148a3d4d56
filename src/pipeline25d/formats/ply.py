"""PLY meshes through plyfile: positions, faces and vertex colours without importing trimesh.

``import trimesh`` (and the scipy it pulls in) is most of an ingest job for a plain PLY
district: seconds against the tenths that reading takes. A PLY that carries more than
positions, faces and vertex colours (texture coordinates, for one) is left to trimesh
(:func:`pipeline25d.formats.meshfile.load_mesh_file`), and so is one plyfile cannot parse.
Polygons are split into triangle fans, as trimesh does. A binary file's faces are first read
as triangles, memory-mapped in one piece (plyfile row by row took 2.6 s for 484k faces, mapped
0.003 s); a file with any other polygon is read again row by row.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline25d.core.errors import InputFileError
from pipeline25d.core.mesh import Mesh, MeshPart

TEXTURED = {"s", "t", "u", "v", "texture_u", "texture_v", "texcoord"}
#: the face lists read as triangles first (plyfile maps a list property of known length in one piece)
TRIANGLE_LISTS = {"face": {"vertex_indices": 3, "vertex_index": 3}}


def load_ply(path: str | Path) -> Mesh:
    """Read a PLY mesh; falls back to trimesh for textured or unusual files."""
    from plyfile import PlyElementParseError, PlyParseError

    path = Path(path)
    try:
        data = _read_triangles_first(path)
        vertex, face = data["vertex"], data["face"]
    except PlyElementParseError as exc:              # the header was read: the data is cut short or corrupt
        problem = "truncated" if "end-of-file" in str(exc) else "corrupt"
        raise InputFileError(path, f"{problem}: {exc}") from None
    except (PlyParseError, KeyError, ValueError, OSError):
        return _with_trimesh(path)
    names = set(vertex.data.dtype.names) | set(face.data.dtype.names)
    if names & TEXTURED or any(c.lower().startswith("texturefile") for c in data.comments):
        return _with_trimesh(path)
    vertices = np.column_stack([np.asarray(vertex[k], dtype=np.float64) for k in ("x", "y", "z")])
    faces = _triangles(face, len(vertices), path)
    colors = None
    if {"red", "green", "blue"} <= names:
        alpha = vertex["alpha"] if "alpha" in names else np.full(len(vertices), 255)
        colors = np.column_stack([vertex[k] for k in ("red", "green", "blue")] + [alpha]).astype(np.uint8)
    if not len(faces):
        raise InputFileError(path, "contains no triangles")
    return Mesh([MeshPart(vertices, faces, colors=colors, name=path.stem)], source=str(path))


def _read_triangles_first(path: Path):
    """The PLY data, its faces memory-mapped as triangles where every face is one, else row by row
    (a face of other length, or fewer bytes than triangles need, which reading row by row then
    reports as it finds it)."""
    from plyfile import PlyData, PlyElementParseError

    try:
        return PlyData.read(str(path), known_list_len=TRIANGLE_LISTS)
    except PlyElementParseError:
        return PlyData.read(str(path))


def _triangles(face, n_vertices: int, path: Path) -> np.ndarray:
    """(m, 3) int64 triangles of the face element (fans for polygons), indices checked."""
    key = "vertex_indices" if "vertex_indices" in face.data.dtype.names else "vertex_index"
    lists = face[key]
    if lists.dtype != object:                        # fixed-length lists parsed as a 2D array
        groups = [(np.arange(len(lists)), np.asarray(lists, dtype=np.int64))]
    else:
        lengths = np.fromiter((len(f) for f in lists), dtype=np.int64, count=len(lists))
        groups = [(np.flatnonzero(lengths == k), np.stack(lists[lengths == k]).astype(np.int64))
                  for k in np.unique(lengths) if k >= 3]
    tris, order = [], []
    for index, p in groups:                          # fan j of polygon i sorts as (i, j): file order
        for j in range(1, p.shape[1] - 1):
            tris.append(np.stack([p[:, 0], p[:, j], p[:, j + 1]], axis=1))
            order.append(index * 1024 + j)
    faces = np.concatenate(tris)[np.argsort(np.concatenate(order), kind="stable")] if tris \
        else np.zeros((0, 3), np.int64)
    if len(faces) and (faces.min() < 0 or faces.max() >= n_vertices):
        bad = faces.max() if faces.max() >= n_vertices else faces.min()
        raise InputFileError(path, f"face index {bad} out of range ({n_vertices} vertices)")
    return faces


def _with_trimesh(path: Path) -> Mesh:
    """trimesh's reading (and its error naming the file when it cannot read it either)."""
    from pipeline25d.formats.meshfile import load_mesh_file

    return load_mesh_file(path)
