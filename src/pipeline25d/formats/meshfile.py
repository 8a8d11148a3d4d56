"""OBJ, PLY and DAE model files through trimesh, one MeshPart per material/geometry.

trimesh keeps OBJ/glTF UVs with v = 0 at the image bottom (our convention); textures are
re-encoded as PNG once per image; vertex colours and material colours become RGBA per
vertex. Coordinates are float64 as the file stores them.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from ..errors import InputFileError
from ..mesh import Mesh, MeshPart


def load_mesh_file(path: str | Path) -> Mesh:
    """Read ``path`` with trimesh; InputFileError naming the file on any failure."""
    import trimesh

    path = Path(path)
    try:
        scene = trimesh.load(str(path), force="scene", process=False)
    except Exception as exc:  # trimesh raises many exception types for bad files
        raise InputFileError(path, f"cannot read as a {path.suffix.lstrip('.').upper()} model: {exc}") from None
    parts: list[MeshPart] = []
    encoded: dict[int, bytes] = {}
    for node in scene.graph.nodes_geometry:
        transform, name = scene.graph[node]
        geom = scene.geometry[name]
        if not isinstance(geom, trimesh.Trimesh) or len(geom.faces) == 0:
            continue
        vertices = np.asarray(geom.vertices, dtype=np.float64)
        if not np.allclose(transform, np.eye(4)):
            vertices = trimesh.transformations.transform_points(vertices, transform)
        parts.append(_part(geom, vertices, str(name), encoded))
    if not parts:
        raise InputFileError(path, "contains no triangles")
    if any(not np.isfinite(p.vertices).all() for p in parts):
        raise InputFileError(path, "has non-finite vertex coordinates")
    return Mesh(parts, source=str(path))


def _part(geom, vertices: np.ndarray, name: str, encoded: dict[int, bytes]) -> MeshPart:
    visual = geom.visual
    faces = np.asarray(geom.faces, dtype=np.int64)
    if visual.kind == "texture":
        material = visual.material
        image = getattr(material, "image", None) or getattr(material, "baseColorTexture", None)
        if image is not None and visual.uv is not None and len(visual.uv) == len(vertices):
            key = id(image)
            if key not in encoded:
                buf = io.BytesIO()
                image.save(buf, format="PNG")
                encoded[key] = buf.getvalue()
            return MeshPart(vertices, faces, uv=np.asarray(visual.uv), texture=encoded[key], name=name)
        colour = np.asarray(getattr(material, "main_color", [180, 180, 180, 255]), dtype=np.uint8)
        return MeshPart(vertices, faces, colors=np.tile(colour, (len(vertices), 1)), name=name)
    if visual.kind in ("vertex", "face"):
        return MeshPart(vertices, faces, colors=np.asarray(visual.vertex_colors)[:, :4], name=name)
    return MeshPart(vertices, faces, name=name)
