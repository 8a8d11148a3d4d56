"""Readers for 3D model file formats (glTF, 3D Tiles, CityJSON, ContextCapture metadata)."""

from __future__ import annotations

import json
from pathlib import Path

from ..errors import ConfigError, InputFileError
from ..mesh import Mesh

MESH_SUFFIXES = {".obj": "obj", ".ply": "ply", ".dae": "dae", ".glb": "glb", ".gltf": "gltf",
                 ".b3dm": "b3dm", ".jsonl": "cityjson"}


def detect_format(path: Path) -> str:
    """The input format from the file name, or for .json from its content."""
    suffix = path.suffix.lower()
    if suffix in MESH_SUFFIXES:
        return MESH_SUFFIXES[suffix]
    if suffix == ".json":
        try:
            doc = json.loads(path.read_bytes())
        except (OSError, ValueError) as exc:
            raise InputFileError(path, f"is not valid JSON: {exc}") from None
        if isinstance(doc, dict) and doc.get("type") in ("CityJSON", "CityJSONFeature"):
            return "cityjson"
        if isinstance(doc, dict) and "asset" in doc and "root" in doc:
            return "3dtiles"
    raise InputFileError(path, "unknown model format (set the input's format key)")


def load_district(spec: dict, scene_crs: str, max_geometric_error: float | None = None,
                  base_dir: Path = Path(".")) -> Mesh:
    """Read one configured input (``inputs.<name>``) into the scene CRS, float64.

    ``spec`` keys: path, format, crs, offset, metadata, lod (see config/schema.yaml).
    """
    import numpy as np

    from .common import reproject_parts

    path = base_dir / spec["path"]
    fmt = spec.get("format", "auto")
    fmt = detect_format(path) if fmt == "auto" else fmt
    src_crs = spec.get("crs")
    offset = np.asarray(spec.get("offset", [0.0, 0.0, 0.0]), dtype=np.float64)
    if spec.get("metadata"):
        from .contextcapture import read_metadata_xml

        src_crs, origin = read_metadata_xml(base_dir / spec["metadata"])
        offset = offset + origin
    if fmt in ("3dtiles", "b3dm", "cityjson") and (offset.any() or spec.get("metadata")):
        # these formats carry their own georeferencing; a silently ignored offset would misplace the map
        raise ConfigError(f"{path}: offset/metadata apply to mesh files (obj, ply, glb, gltf, dae), not {fmt}")
    if fmt in ("3dtiles", "b3dm"):
        from . import tiles3d

        crs = src_crs or "EPSG:4978"
        if fmt == "b3dm":
            return tiles3d.load_b3dm(path, scene_crs, src_crs=crs)
        return tiles3d.load_tileset(path, scene_crs, max_geometric_error=max_geometric_error, src_crs=crs)
    if fmt == "cityjson":
        from .cityjson import load_cityjson

        return load_cityjson(path, scene_crs, lod=spec.get("lod"), src_crs=src_crs)
    if fmt in ("glb", "gltf"):
        from .gltf import load_gltf

        mesh = Mesh(load_gltf(path), source=str(path))
    elif fmt == "ply":
        from .ply import load_ply

        mesh = load_ply(path)
    else:
        from .meshfile import load_mesh_file

        mesh = load_mesh_file(path)
    src_crs = src_crs or scene_crs
    if offset.any():
        mesh = mesh.transformed(lambda v: v + offset)
    return Mesh(reproject_parts(mesh.parts, src_crs, scene_crs, path), source=mesh.source)
