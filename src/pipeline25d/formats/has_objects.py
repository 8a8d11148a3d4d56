"""Whether an input names objects worth identifying, told cheaply before it is read.

``objects.enabled: auto`` makes the id tiles, id maps and their web tiles only for a scene
whose inputs name objects: buildings, city objects, features. A PLY file is one surface, and
an OSGB dataset or a 3MX scene (ContextCapture photogrammetry) a tree of mesh tiles whose node
names are pieces of one surface; none ever names an object. A 3D Tiles tileset names features where
its contents carry feature ids (a b3dm's batch, ``_BATCHID``, ``EXT_mesh_features``, an i3dm's
instances); a photogrammetry tileset carries none, and its parts would all be one object. One
content, the first the tile tree reaches, stands for the tileset: exporters write every content
alike. Other formats (CityJSON, CityGML, OBJ ``o`` objects, DAE and 3DS nodes, glTF meshes)
name their objects. Where a file cannot be peeked at, the answer is yes: ingest then reports
the file's problem.
"""

from __future__ import annotations

import json
import struct
from collections import deque
from pathlib import Path

from pipeline25d.core.errors import Pipeline25dError
from pipeline25d.formats.gzipped import file_bytes

#: formats whose files never name an object (see the module docstring)
SURFACE_FORMATS = frozenset({"ply", "osgb", "3mx"})
MAX_PEEK_TILES = 10_000     # tiles visited, external tilesets included, before the peek gives up (answers yes)
_FEATURE_ATTRIBUTES = ("_BATCHID", "BATCHID")


def input_has_objects(spec: dict) -> bool:
    """Whether the input ``spec`` (a config ``inputs`` entry) names objects to identify."""
    from pipeline25d.formats import detect_format

    path = Path(spec["path"])
    try:
        fmt = spec.get("format", "auto")
        fmt = detect_format(path) if fmt == "auto" else fmt
        if fmt in SURFACE_FORMATS:
            return False
        if fmt == "3dtiles":
            from pipeline25d.formats.tileset_packages import tileset_of

            content = _first_content(tileset_of(path))
            return content is None or _content_has_features(file_bytes(content))
        if fmt == "b3dm":
            return _content_has_features(file_bytes(path))
        if fmt == "i3s":                # a 3DObject layer's features are its objects; an IntegratedMesh has none
            from pipeline25d.formats.i3s import Layer
            from pipeline25d.formats.slpk import Package

            return Layer.of(Package(path), spec).objects
    except (Pipeline25dError, OSError, ValueError, KeyError, TypeError, AttributeError, struct.error,
            RecursionError):
        return True                     # ingest names the file's problem
    return True


def _first_content(tileset: Path) -> Path | None:
    """The first renderable content the tile tree reaches, breadth first, an external tileset
    entered as soon as it is met (an implicit tileset's: its root tile's); None where there is
    none to peek at (no content, too many tiles)."""
    from pipeline25d.formats.tileset_tree import _content_list, read_json, resolve

    folder = tileset.parent
    queue: deque[tuple[dict, Path]] = deque([(read_json(tileset)["root"], tileset)])
    for _ in range(MAX_PEEK_TILES):
        if not queue:
            return None
        tile, base = queue.popleft()
        implicit = "implicitTiling" in tile
        for content in _content_list(tile):
            uri = content.get("uri") or content.get("url")
            if implicit:             # the template's root tile: level 0 at 0, 0(, 0)
                uri = uri.format(level=0, x=0, y=0, z=0)
            path = resolve(uri, base, folder)
            if path.suffix.lower() == ".json":      # entered before the tile's siblings: one file, not all
                queue.appendleft((read_json(path)["root"], path))
            elif path.is_file():
                return path
        if not implicit:
            queue.extend((child, base) for child in tile.get("children") or [])
    return None


def _content_has_features(data: bytes) -> bool:
    """Whether a 3D Tiles content (b3dm, i3dm, cmpt, glb, glTF JSON) carries feature ids."""
    magic = data[:4]
    if magic == b"b3dm":
        ft_json, ft_bin, bt_json, bt_bin = struct.unpack_from("<4I", data, 12)
        table = json.loads(data[28:28 + ft_json] or b"{}")
        if int(table.get("BATCH_LENGTH", 0)) > 0:
            return True
        return _content_has_features(data[28 + ft_json + ft_bin + bt_json + bt_bin:])
    if magic == b"i3dm":
        return True                         # each instance is an object
    if magic == b"cmpt":
        count, pos = struct.unpack_from("<I", data, 12)[0], 16
        for _ in range(count):
            length = struct.unpack_from("<I", data, pos + 8)[0]
            if _content_has_features(data[pos:pos + length]):
                return True
            pos += length
        return False
    if magic == b"glTF":
        from pipeline25d.formats.gltf import _split_glb

        return _gltf_has_features(_split_glb(data, Path("content"))[0])
    return _gltf_has_features(json.loads(data))


def _gltf_has_features(doc: dict) -> bool:
    """Whether a glTF document's primitives carry feature ids (``_BATCHID``, ``EXT_mesh_features``;
    a glTF 1.0 one's ``BATCHID``)."""
    from pipeline25d.formats import gltf1

    if gltf1.is_gltf1(doc):
        doc = gltf1.upgraded(doc, Path("content"))
    return _features_in(doc)


def _features_in(doc: dict) -> bool:
    for mesh in doc.get("meshes") or []:
        for prim in mesh.get("primitives") or []:
            if "EXT_mesh_features" in (prim.get("extensions") or {}):
                return True
            if any(a in (prim.get("attributes") or {}) for a in _FEATURE_ATTRIBUTES):
                return True
    return False
