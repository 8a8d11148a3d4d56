"""What the generated scenes write alike: OBJ/MTL text of material groups, and a DTM sampled from an
exact terrain function (files: core.atomic)."""

from __future__ import annotations

from collections.abc import Callable, Hashable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pipeline25d.core.grid import Grid

# (vertices (n, 3), colours (n, 3)) -> the numbers of each "v" line
VertexColumns = Callable[[np.ndarray, np.ndarray], np.ndarray]


@dataclass
class Group:
    """Triangles of one OBJ material: vertices (n,3), rgb (n,3), uv (n,2)|None, faces, and each piece's
    OBJ object (``o`` name, None for none)."""

    vertices: list[np.ndarray] = field(default_factory=list)
    colors: list[np.ndarray] = field(default_factory=list)
    uv: list[np.ndarray] = field(default_factory=list)
    faces: list[np.ndarray] = field(default_factory=list)
    objects: list[str | None] = field(default_factory=list)
    count: int = 0

    def add(self, vertices, faces, colors, uv=None, obj: str | None = None) -> None:
        """Append a piece (of OBJ object ``obj``); ``faces`` index into ``vertices`` (0-based, local)."""
        vertices = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
        colors = np.broadcast_to(np.asarray(colors, dtype=np.float64), vertices.shape)
        self.vertices.append(vertices)
        self.colors.append(colors)
        if uv is not None:
            self.uv.append(np.asarray(uv, dtype=np.float64).reshape(-1, 2))
        self.faces.append(np.asarray(faces, dtype=np.int64).reshape(-1, 3) + self.count)
        self.objects.append(obj)
        self.count += len(vertices)


def obj_rows(prefix: str, array: np.ndarray, fmt: str) -> list[str]:
    """OBJ lines ``prefix v0 v1 ...`` for each row, numbers formatted with ``fmt``."""
    template = prefix + " " + " ".join([fmt] * array.shape[1])
    return [template % tuple(row) for row in array.tolist()]


def obj_text(header: str, name: str, groups: dict[str, Group], uv_sets: dict[str, tuple[Hashable, np.ndarray]],
             formats: tuple[str, str], vertex_columns: VertexColumns | None = None) -> tuple[str, int]:
    """OBJ text of a district's material groups, and its triangle count.

    Every vertex carries a colour ("v x y z r g b"): trimesh only reads vertex colours when all
    vertices have them. ``uv_sets`` maps a textured material to (key, uv per vertex); materials
    with equal keys share one block of ``vt`` lines. ``formats``: how the numbers of the ``v`` and
    of the ``vt`` lines are written; ``vertex_columns`` gives the ``v`` numbers (default x y z r g b).
    Pieces added with an object name are written as ``o`` objects (each its pieces' faces under their
    materials, objects in order of their first piece; a piece without a name is on the object ``name``);
    without any, the district is one ``o``.
    The ``v`` and ``vt`` lines are the same either way.
    """
    v_format, vt_format = formats
    used = [(k, g) for k, g in groups.items() if g.count]
    vertices = np.vstack([np.vstack(g.vertices) for _, g in used])
    colors = np.vstack([np.vstack(g.colors) for _, g in used])
    columns = vertex_columns(vertices, colors) if vertex_columns else np.column_stack([vertices, colors])
    named = any(o is not None for _, g in used for o in g.objects)
    lines = [header, f"mtllib {name}.mtl"] + ([] if named else [f"o {name}"]) + obj_rows("v", columns, v_format)
    vt_offsets: dict[Hashable, int] = {}  # uv key -> 1-based index of its first vt line
    n_vt = 0
    for material, _ in used:
        key, uv = uv_sets.get(material, (None, None))
        if key is not None and key not in vt_offsets:
            vt_offsets[key] = 1 + n_vt
            lines += obj_rows("vt", uv, vt_format)
            n_vt += len(uv)
    v_offset, n_tri = 1, 0
    blocks: dict[str | None, list[tuple[str, list[str]]]] = {}   # object -> [(material, face lines)]
    for material, g in used:
        for obj, faces in zip(g.objects, g.faces):
            if material in uv_sets:
                vt_offset = vt_offsets[uv_sets[material][0]]
                both = np.stack([faces + v_offset, faces + vt_offset], axis=2).reshape(-1, 6)
                rows = ["f %d/%d %d/%d %d/%d" % tuple(r) for r in both.tolist()]
            else:
                rows = obj_rows("f", faces + v_offset, "%d")
            pieces = blocks.setdefault((obj or name) if named else None, [])
            if pieces and pieces[-1][0] == material:
                pieces[-1][1].extend(rows)
            else:
                pieces.append((material, rows))
            n_tri += len(faces)
        v_offset += g.count
    for obj, pieces in blocks.items():
        lines += [] if obj is None else [f"o {obj}"]
        for material, rows in pieces:
            lines += [f"usemtl {material}"] + rows
    return "\n".join(lines) + "\n", n_tri


def mtl_block(name: str, rgb, texture: str | None = None) -> str:
    """One MTL material: diffuse colour ``rgb`` (0..1) and, when given, its diffuse texture file."""
    lines = [f"newmtl {name}", "Ka 0.000 0.000 0.000", "Kd %.3f %.3f %.3f" % tuple(rgb),
             "Ks 0.000 0.000 0.000", "d 1.0", "illum 1"]
    if texture:
        lines.append(f"map_Kd {texture}")
    return "\n".join(lines) + "\n"


def write_dtm(path: Path, grid: Grid, height_fn: Callable[[np.ndarray, np.ndarray], np.ndarray], epsg: int) -> None:
    """A float32 GeoTIFF of ``height_fn(x, y)`` at the cell centres of a north-up grid, atomically."""
    from osgeo import osr

    from pipeline25d.core.geotiff import write_geotiff

    z = np.asarray(height_fn(grid.column_x()[None, :], grid.row_y()[:, None])).astype(np.float32)
    srs = osr.SpatialReference()
    srs.ImportFromEPSG(epsg)
    write_geotiff(path, z, grid, srs.ExportToWkt(), "Float32", ["COMPRESS=DEFLATE", "PREDICTOR=3", "TILED=YES"])
