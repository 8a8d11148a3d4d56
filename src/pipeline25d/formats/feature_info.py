"""The attributes of 3D Tiles and glTF features (batch ids, ``EXT_mesh_features`` feature ids) as
``object_info`` on their parts (:mod:`pipeline25d.formats.attributes`): a feature's object key is
``<content file relative to the dataset's root>#<feature id>``; its attributes come from a b3dm
batch table (:mod:`pipeline25d.formats.batch_table`) or an ``EXT_structural_metadata`` property
table (:mod:`pipeline25d.formats.structural_metadata`)."""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

from pipeline25d.core.errors import InputFileError
from pipeline25d.core.mesh import MeshPart, merged_info
from pipeline25d.formats.attributes import Limiter, object_info
from pipeline25d.formats.structural_metadata import MetadataError, property_rows


def feature_prefix(path: Path, root: Path) -> str:
    """What the object keys of a content's features start with: the file relative to the
    dataset's ``root`` (its name when outside); a key is ``<prefix>#<feature id>``."""
    try:
        return path.resolve().relative_to(root.resolve()).as_posix()
    except ValueError:
        return path.name


def with_feature_info(parts: list[MeshPart], rows: list[dict], prefix: str, path: Path) -> list[MeshPart]:
    """``parts`` carrying the attributes ``rows[i]`` of each feature id ``i`` (keys ``<prefix>#<i>``,
    bounded with one warning naming ``path``, :mod:`pipeline25d.formats.attributes`); the parts
    as they are without rows."""
    if not rows:
        return parts
    limiter = Limiter(path)
    info = {f"{prefix}#{i}": object_info(None, limiter.attributes(row)) for i, row in enumerate(rows)}
    limiter.warn(stacklevel=3)
    info = {**merged_info(parts), **info}          # one mapping, shared by the parts
    return [replace(p, object_info=info) for p in parts]


def feature_properties(gltf: dict, prim: dict, objects: tuple[str, ...], view_bytes: Callable[[int], bytes],
                       limiter: Limiter) -> dict[str, dict] | None:
    """key -> attributes of a glTF primitive's features (``objects``, keys ``<prefix>#<feature id>``)
    from the ``EXT_structural_metadata`` property table its first feature ids name
    (:mod:`pipeline25d.formats.structural_metadata`), none for its ``nullFeatureId``; None without
    a table. A table that cannot be read: None, with a warning naming the file (``limiter.where``)."""
    ids = prim.get("extensions", {}).get("EXT_mesh_features", {}).get("featureIds") or []
    ext = gltf.get("extensions", {}).get("EXT_structural_metadata")
    if not objects or not ext or not ids or not isinstance(ids[0], dict) or "propertyTable" not in ids[0]:
        return None
    null = ids[0].get("nullFeatureId")              # "no feature": no attributes
    rows = {r: key for key in objects if (r := int(key.rsplit("#", 1)[1])) != null}
    try:
        found = property_rows(ext, ids[0]["propertyTable"], rows, view_bytes)
    except (MetadataError, InputFileError) as exc:
        warnings.warn(f"{limiter.where}: EXT_structural_metadata property table not read, its features have "
                      f"no attributes: {exc}", stacklevel=3)
        return None
    return {rows[r]: object_info(None, limiter.attributes(attrs)) for r, attrs in found.items()}
