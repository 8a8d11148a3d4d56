"""Bentley 3MX (3D Multiresolution Mesh eXchange), as ContextCapture / iTwin Capture export photogrammetry.

A scene file ``<name>.3mx`` (JSON, ``3mxVersion`` 1) lists layers; each ``meshPyramid`` layer names
its ``SRS`` (an EPSG code, WKT or ``ENU:lat,lon``, as in ContextCapture's metadata.xml), its
``SRSOrigin`` (a point of the mesh is P + SRSOrigin in the SRS) and its ``root`` .3mxb file. A
.3mxb file is ``3MXBO``, a little-endian u32 length, a JSON header of ``nodes`` and ``resources``,
then the bytes of each ``textureBuffer`` and ``geometryBuffer`` resource in the header's order
(``textureFile`` and ``geometryFile`` resources name files instead). A node has a box (``bbMin``,
``bbMax``), a ``maxScreenDiameter`` in pixels, child .3mxb files (relative to its own) and the ids
of its geometry resources: OpenCTM meshes (:mod:`.openctm`) with one UV map (v = 0 the image's
bottom row, as OpenGL draws it), each textured by the JPEG or PNG resource its ``texture`` names.

**Level rule**, as 3MX viewers draw it: a node whose box diagonal is d covers d / gsd pixels of a
map; it is drawn while that is below its ``maxScreenDiameter``, else its child files replace it
(a node without children is drawn at any size). ``gsd`` None (full detail) draws the finest level.
The level of a node is the number of files between it and the root file.

**Missing children**: where a child file a node needs is absent, the node itself is drawn, coarser
than the gsd asks for, with a warning naming the files (``missing_children: error``: an error), as
for OSGB. A missing root file is an error. A scene is read in pieces: each node of a layer's root file, or
where that node is refined, each child file replacing it (a root file may hold one node over all
tiles, a child file per tile): memory follows a tile. Files a scene names must lie
in its folder (:func:`~pipeline25d.formats.common.side_file`).
"""

from __future__ import annotations

import json
import logging
import struct
import warnings
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from pipeline25d.core.errors import InputFileError, MissingTextureWarning, UnsupportedFeatureError
from pipeline25d.core.mesh import Coarser, MeshPart
from pipeline25d.formats.common import Detail, Loaded, image_problem, png_or_jpeg, read_text, side_file, texture_file
from pipeline25d.formats.gzipped import file_bytes

log = logging.getLogger(__name__)

MAGIC = b"3MXBO"


@dataclass(frozen=True)
class Layer:
    """A meshPyramid layer of a .3mx scene: CRS text (None: the input's crs key), origin, root file."""

    crs: str | None
    origin: np.ndarray
    root: Path


@dataclass
class Group:
    """One .3mxb file: its nodes, and its resources by id (a dict with ``bytes`` for buffers)."""

    path: Path
    nodes: list[dict]
    resources: dict[str, dict]


@dataclass
class _Walk:
    """What walking a tile gathers: its parts, triangles per level, the files drawn coarser."""

    folder: Path
    gsd: float | None
    missing_children: str
    parts: list[MeshPart] = field(default_factory=list)
    levels: Counter = field(default_factory=Counter)
    coarser: list[Coarser] = field(default_factory=list)

    def fresh(self) -> "_Walk":
        """A walk of the same map and folder with nothing gathered yet (the next tile's)."""
        return replace(self, parts=[], levels=Counter(), coarser=[])


def read_3mx(path: Path, spec: dict, detail: Detail = Detail()) -> Loaded:
    """Reader contract (:mod:`pipeline25d.formats`): a .3mx scene or one .3mxb file, at ``detail.gsd``."""
    pieces = list(read_3mx_pieces(path, spec, detail))
    return Loaded([p for piece in pieces for p in piece.parts], pieces[0].crs,
                  tuple(c for piece in pieces for c in piece.coarser))


def read_3mx_pieces(path: Path, spec: dict, detail: Detail = Detail()) -> Iterator[Loaded]:
    """:func:`read_3mx` one tile at a time (:func:`_tiles`); the SRS origin added, the SRS the CRS
    (the input's ``crs`` key overrides it)."""
    path = Path(path)
    drawn = False
    for layer in layers_of(path):
        for name, walk in _tiles(read_group(layer.root), _Walk(path.parent, detail.gsd,
                                                                spec.get("missing_children", "coarser"))):
            _say(walk, name)
            parts = [p.transformed(lambda v: v + layer.origin) for p in walk.parts] if layer.origin.any() \
                else walk.parts
            drawn = drawn or bool(parts)
            yield Loaded(parts, spec.get("crs") or layer.crs, tuple(walk.coarser))
    if not drawn:
        raise InputFileError(path, f"holds no triangles at gsd {detail.gsd} (an empty 3MX tree)")


def layers_of(path: Path) -> list[Layer]:
    """A .3mx scene's layers (:func:`scene_layers`); a .3mxb alone is one layer with no SRS, at the origin."""
    return scene_layers(path) if path.suffix.lower() == ".3mx" else [Layer(None, np.zeros(3), path)]


def scene_layers(path: Path) -> list[Layer]:
    """The meshPyramid layers of a .3mx scene file (others are skipped with a warning)."""
    from pipeline25d.formats.contextcapture import origin_of, srs_crs_text

    try:
        scene = json.loads(read_text(path, "3MX scene"))
    except ValueError as exc:
        raise InputFileError(path, f"is not valid JSON: {exc}") from None
    if not isinstance(scene, dict) or not isinstance(scene.get("layers"), list):
        raise InputFileError(path, "is not a 3MX scene: no layers list")
    if scene.get("3mxVersion") not in (1, 1.0, "1"):
        raise UnsupportedFeatureError(path, f"3mxVersion {scene.get('3mxVersion')!r} (only 1 is known)")
    layers = []
    for k, layer in enumerate(scene["layers"]):
        if not isinstance(layer, dict) or layer.get("type") != "meshPyramid":
            kind = layer.get("type") if isinstance(layer, dict) else layer
            warnings.warn(f"{path}: layer {k} is not a meshPyramid ({kind!r}); skipped", stacklevel=3)
            continue
        if not isinstance(layer.get("root"), str):
            raise InputFileError(path, f"layer {k} names no root file")
        srs = layer.get("SRS")
        crs = srs_crs_text(srs, path) if isinstance(srs, str) and srs.strip() else None
        origin = layer.get("SRSOrigin")
        origin = origin_of(",".join(map(str, origin)) if isinstance(origin, list) else origin, path)
        root = side_file(layer["root"], path.parent, path.parent, path, "layer root", url=False)
        if not root.is_file():
            raise InputFileError(root, f"the root file of layer {k} of {path.name} is missing")
        layers.append(Layer(crs, origin, root))
    if not layers:
        raise InputFileError(path, "has no meshPyramid layer")
    return layers


def read_group(path: Path) -> Group:
    """A .3mxb file's nodes and resources (buffers sliced from the file, checked against its length)."""
    data = file_bytes(path)
    if data[:5] != MAGIC or len(data) < 9:
        raise InputFileError(path, "is not a 3MX node file (no 3MXBO magic)")
    (size,) = struct.unpack_from("<I", data, 5)
    if 9 + size > len(data):
        raise InputFileError(path, f"its header claims {size} bytes; the file has {len(data) - 9} after its start")
    try:
        header = json.loads(data[9:9 + size])
    except ValueError as exc:
        raise InputFileError(path, f"its header is not valid JSON: {exc}") from None
    if not isinstance(header, dict) or not isinstance(header.get("nodes", []), list) \
            or not isinstance(header.get("resources", []), list):
        raise InputFileError(path, "its header holds no nodes and resources lists")
    resources, at = {}, 9 + size
    for res in header.get("resources", []):
        if not isinstance(res, dict) or "id" not in res:
            raise InputFileError(path, f"a resource without an id: {res!r:.80}")
        if res.get("type") in ("textureBuffer", "geometryBuffer"):
            n = res.get("size")
            if not isinstance(n, int) or n < 0 or at + n > len(data):
                raise InputFileError(path, f"resource {res['id']!r} ({n!r} bytes) runs past the file's end")
            res = {**res, "bytes": data[at:at + n]}
            at += n
        resources[str(res["id"])] = res
    nodes = header.get("nodes", [])
    for node in nodes:
        if not isinstance(node, dict) or not all(k in node for k in ("bbMin", "bbMax", "maxScreenDiameter")):
            raise InputFileError(path, f"a node without bbMin, bbMax and maxScreenDiameter: {node!r:.80}")
    return Group(path, nodes, resources)


def _tiles(root: Group, blank: _Walk) -> Iterator[tuple[str, _Walk]]:
    """The pieces of a layer: each node of its root file, or where that node is refined, each of the
    child files that replace it (a root file may hold one node over all tiles, a child file per
    tile): (name, its walk)."""
    for node in root.nodes:
        walk = blank.fresh()
        files = _finer_files(node, root, 0, walk)
        if files is None:
            _draw(node, root, 0, walk)
            yield f"{root.path.name} node {node.get('id', '?')}", walk
            continue
        for file in files:
            walk = blank.fresh()
            _walk_file(file, 1, walk)
            yield file.name, walk


def _walk_node(node: dict, group: Group, level: int, walk: _Walk) -> None:
    """Gather ``node``'s drawn parts at the map's gsd (the module's level rule)."""
    files = _finer_files(node, group, level, walk)
    if files is None:
        _draw(node, group, level, walk)
        return
    for file in files:
        _walk_file(file, level + 1, walk)


def _walk_file(file: Path, level: int, walk: _Walk) -> None:
    """Gather the drawn parts of every node of the .3mxb ``file``, whose nodes are at ``level``."""
    group = read_group(file)
    for node in group.nodes:
        _walk_node(node, group, level, walk)


def _finer_files(node: dict, group: Group, level: int, walk: _Walk) -> list[Path] | None:
    """The child files that replace ``node`` at the map's gsd; None where the node itself is drawn
    (fine enough, no children, or a child file missing: then noted as drawn coarser, or an error)."""
    children = [str(c) for c in node.get("children") or []]
    diagonal = float(np.linalg.norm(np.subtract(node["bbMax"], node["bbMin"], dtype=np.float64)))
    if not children or (walk.gsd is not None and diagonal / walk.gsd < float(node["maxScreenDiameter"])):
        return None
    files = [side_file(c, group.path.parent, walk.folder, group.path, "child file", url=False) for c in children]
    missing = [c for c, f in zip(children, files) if not f.is_file()]
    if not missing:
        return files
    if walk.missing_children == "error":
        raise InputFileError(group.path, f"node {node.get('id')!r}: child file(s) missing: {', '.join(missing)}")
    walk.coarser.append(Coarser(str(group.path), level, tuple(missing), f"node {node.get('id')!r} itself"))
    return None


def _draw(node: dict, group: Group, level: int, walk: _Walk) -> None:
    """Add ``node``'s own geometry to ``walk``."""
    for rid in node.get("resources") or []:
        part = _geometry(group, str(rid), walk.folder)
        if part is not None:
            walk.parts.append(part)
            walk.levels[level] += len(part.faces)


def _geometry(group: Group, rid: str, folder: Path) -> MeshPart | None:
    """One geometry resource as a part, textured by the resource it names."""
    from pipeline25d.formats.openctm import CtmError, decode_ctm

    res = group.resources.get(rid)
    if res is None:
        raise InputFileError(group.path, f"a node names resource {rid!r}, which the file does not hold")
    if res.get("type") not in ("geometryBuffer", "geometryFile"):
        raise InputFileError(group.path, f"a node's resource {rid!r} is a {res.get('type')!r}, not geometry")
    if str(res.get("format", "")).lower() != "ctm":
        raise UnsupportedFeatureError(group.path, f"geometry {rid!r} is {res.get('format')!r}; only OpenCTM (ctm) "
                                                  "geometry is read")
    try:
        mesh = decode_ctm(_resource_bytes(group, res, folder, "geometry file"))
    except CtmError as exc:
        raise InputFileError(group.path, f"geometry {rid!r}: {exc}") from None
    if not len(mesh.faces):
        return None
    texture = _texture(group, res.get("texture"), folder) if mesh.uv is not None else None
    return MeshPart(mesh.vertices, mesh.faces, uv=mesh.uv, texture=texture, name=f"{group.path.name}:{rid}")


def _texture(group: Group, tid, folder: Path) -> bytes | None:
    """A texture resource's JPEG/PNG bytes; None with a warning when it is absent or unreadable."""
    if tid is None:
        return None
    res = group.resources.get(str(tid))
    problem = None
    if res is None or res.get("type") not in ("textureBuffer", "textureFile"):
        problem = "is not a texture resource of the file"
    else:
        try:
            data, problem = _texture_bytes(group, res, folder)
        except FileNotFoundError:
            problem = "names a file that is missing"
        if problem is None:
            problem = "is neither JPEG nor PNG" if not png_or_jpeg(data) else image_problem(data)
    if problem:
        warnings.warn(f"{group.path}: texture {tid!r} {problem}; its parts are drawn untextured",
                      MissingTextureWarning, stacklevel=4)
        return None
    return data


def _texture_bytes(group: Group, res: dict, folder: Path) -> tuple[bytes | None, str | None]:
    """(the texture resource's bytes, None), or (None, the problem) for a ``textureFile`` that leads
    outside the dataset folder: that image is not read (a missing texture, as for glTF, CityGML and
    CityJSON images). Its file is found once (a name in another letter case is warned of once)."""
    if "bytes" in res or not isinstance(res.get("file"), str):
        return _resource_bytes(group, res, folder, "texture file"), None
    target, problem = texture_file(res["file"], group.path.parent, folder, group.path, "texture file", url=False)
    return (None, problem) if target is None else (file_bytes(target), None)


def _resource_bytes(group: Group, res: dict, folder: Path, what: str) -> bytes:
    if "bytes" in res:
        return res["bytes"]
    if not isinstance(res.get("file"), str):
        raise InputFileError(group.path, f"resource {res['id']!r} names no file")
    return file_bytes(side_file(res["file"], group.path.parent, folder, group.path, what, url=False))


def _say(walk: _Walk, name: str) -> None:
    """Log a tile's levels; warn of its child files that are missing."""
    from pipeline25d.formats.osgb import describe_levels

    log.info("%s at gsd %s: %s", name, walk.gsd, describe_levels(walk.levels))
    if walk.coarser:
        asked = f"gsd {walk.gsd}" if walk.gsd else "full detail"
        warnings.warn(f"{name}: {sum(len(c.missing) for c in walk.coarser)} 3MX child file(s) missing, drawn "
                      f"coarser than {asked} asks for: " + ", ".join(
                          f"{m} (level {c.level} drawn)" for c in walk.coarser for m in c.missing), stacklevel=3)
