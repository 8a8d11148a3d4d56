"""Writers of the generated OAP3D city's nodes (:mod:`pipeline25d_lab.scenes.oap3d_nodes`) in two formats.

**OSGB** as ContextCapture writes it: ``Data/Tile_+xxx_+yyy/Tile_+xxx_+yyy.osgb`` holds a
PagedLOD drawing the tile's level-0 node below its switch and ``..._L1.osgb`` above it; the
file ``<tile>_L<k+1>[_<path>].osgb`` of a node at level k holds its four quadrants at level
k+1, each a PagedLOD (own mesh inline, the next file beyond the switch) or, at the last level,
a Geode. The switch of a node is at 2·r/texel pixels (r its bounding radius), so a map of gsd
g draws a node's own mesh while g > its texel (:mod:`pipeline25d.formats.osgb`). Each file is
.osgt text converted by ``osgconv`` with its JPEG atlases embedded (``WriteImageHint=IncludeFile``).

**3D Tiles** 1.1 in ECEF (EPSG:4978, converted from the OSGB's UTM coordinates with pyproj):
``tileset.json`` names one external tileset per tile (``Data/<tile>/tileset.json``), whose tree
has one glb per node (same mesh, same UVs, the same JPEG bytes embedded), REPLACE refinement
and geometricError = texel / 2 (leaves 0): with ``lod.max_error_px`` 0.5 the workflow refines
while texel > gsd and draws the same level as from the OSGB.
"""

from __future__ import annotations

import itertools
import json
from collections.abc import Iterator
from functools import lru_cache
from pathlib import Path

import numpy as np

from pipeline25d_lab.scenes.model_writers import glb_bytes
from pipeline25d_lab.scenes.oap3d_nodes import Node, Spec
from pipeline25d_lab.scenes.osgb_sample import HEADER, geode_text

ECEF = "EPSG:4978"


def tile_name(tx: int, ty: int) -> str:
    return f"Tile_{tx:+04d}_{ty:+04d}"


def osgb_file(tile: str, level: int, path: str) -> str:
    """File holding the children of the node at ``level``/``path`` (level + 1), or the root file (level -1)."""
    if level < 0:
        return f"{tile}.osgb"
    return f"{tile}_L{level + 1}" + (f"_{path}" if path else "") + ".osgb"


def metadata_xml(srs: str, origin: tuple[float, float, float]) -> str:
    return ('<?xml version="1.0" encoding="utf-8"?>\n<ModelMetadata version="1">\n'
            f"\t<SRS>{srs}</SRS>\n\t<SRSOrigin>{origin[0]:.0f},{origin[1]:.0f},{origin[2]:.0f}</SRSOrigin>\n"
            "\t<Texture>\n\t\t<ColorSource>Visible</ColorSource>\n\t</Texture>\n</ModelMetadata>\n")


# --------------------------------------------------------------------------- OSGB


def _geode(ids: Iterator[int], node: Node, images: dict[str, bytes]) -> str:
    name = f"n{len(images)}.jpg"
    images[name] = node.jpeg
    return geode_text(ids, node.vertices, node.faces, node.uv, name)


def _paged(ids: Iterator[int], node: Node, texel: float, child_file: str, images: dict[str, bytes]) -> str:
    """A PagedLOD over ``node``: its mesh inline below the switch, ``child_file`` above it."""
    uid = next(ids)
    geode = _geode(ids, node, images)
    (cx, cy, cz), r = node.centre, node.radius
    switch = 2.0 * r / texel
    return (f"osg::PagedLOD {{\n UniqueID {uid}\n CenterMode USER_DEFINED_CENTER\n"
            f" UserCenter {cx!r} {cy!r} {cz!r} {r!r}\n"
            f" RangeMode PIXEL_SIZE_ON_SCREEN\n RangeList 2 {{\n  0 {switch!r}\n  {switch!r} 1e+30\n }}\n"
            f' DatabasePath FALSE\n RangeDataList 2 {{\n  ""\n  "{child_file}"\n }}\n'
            f" PriorityList 2 {{\n  0 1\n  0 1\n }}\n Children 1 {{\n{geode}\n }}\n}}")


def write_osgb_file(dst: Path, work: Path, spec: Spec, tile: str, nodes: list[Node], root: bool) -> None:
    """One .osgb: the root file's PagedLOD (``root``) or a Group of the four quadrant ``nodes``."""
    from pipeline25d.formats.osgb import osgconv

    ids, images = itertools.count(1), {}
    items = []
    for node in nodes:
        if node.level + 1 < spec.levels:
            items.append(_paged(ids, node, spec.texel(node.level), osgb_file(tile, node.level, node.path), images))
        else:
            items.append(_geode(ids, node, images))
    text = items[0] if root else (f"osg::Group {{\n UniqueID {next(ids)}\n Children {len(items)} {{\n"
                                  + "\n".join(items) + "\n }\n}")
    for name, data in images.items():
        (work / name).write_bytes(data)
    (work / "node.osgt").write_text(HEADER + text)
    osgconv(Path("node.osgt"), dst.resolve(), ["WriteImageHint=IncludeFile"], work, dst)


# --------------------------------------------------------------------------- 3D Tiles


@lru_cache(maxsize=4)
def _to_ecef(srs: str):
    from pyproj import Transformer

    return Transformer.from_crs(srs, ECEF, always_xy=True)


def to_ecef(points: np.ndarray, srs: str) -> np.ndarray:
    """float64 (n, 3) ECEF of points in ``srs`` (heights taken as ellipsoidal)."""
    x, y, z = _to_ecef(srs).transform(points[:, 0], points[:, 1], points[:, 2])
    return np.column_stack([x, y, z])


def sphere(points: np.ndarray) -> list[float]:
    lo, hi = points.min(axis=0), points.max(axis=0)
    return [*((lo + hi) / 2).tolist(), float(np.linalg.norm(hi - lo) / 2)]


def node_glb(node: Node, ecef_offset: np.ndarray) -> bytes:
    """A glb of the node: y-up float32 positions (ECEF offsets from the tile's centre), uint32
    indices, glTF-convention UVs and the JPEG atlas in the binary chunk."""
    pos = np.column_stack([ecef_offset[:, 0], ecef_offset[:, 2], -ecef_offset[:, 1]]).astype("<f4")
    uv = np.column_stack([node.uv[:, 0], 1.0 - node.uv[:, 1]]).astype("<f4")
    blobs = [pos.tobytes(), node.faces.astype("<u4").tobytes(), uv.tobytes(), node.jpeg]
    views, offset = [], 0
    for blob in blobs:
        views.append({"buffer": 0, "byteOffset": offset, "byteLength": len(blob)})
        offset += len(blob) + (-len(blob) % 4)
    binary = b"".join(b + b"\0" * (-len(b) % 4) for b in blobs)
    doc = {"asset": {"version": "2.0", "generator": "pipeline25d_lab oap3d"}, "scene": 0,
           "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0}],
           "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "TEXCOORD_0": 2}, "indices": 1, "material": 0}]}],
           "accessors": [{"bufferView": 0, "componentType": 5126, "count": len(pos), "type": "VEC3",
                          "min": pos.min(axis=0).tolist(), "max": pos.max(axis=0).tolist()},
                         {"bufferView": 1, "componentType": 5125, "count": node.faces.size, "type": "SCALAR"},
                         {"bufferView": 2, "componentType": 5126, "count": len(uv), "type": "VEC2"}],
           "bufferViews": views, "buffers": [{"byteLength": len(binary)}],
           "materials": [{"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}, "metallicFactor": 0.0}}],
           "textures": [{"source": 0, "sampler": 0}], "samplers": [{"magFilter": 9729, "minFilter": 9987}],
           "images": [{"bufferView": 3, "mimeType": "image/jpeg"}]}
    return glb_bytes(doc, binary)


class TileTree:
    """The 3D Tiles tree of one tile, built node by node; ``centre`` is the tile's ECEF origin."""

    def __init__(self, spec: Spec, srs: str, origin: np.ndarray, centre: np.ndarray):
        self.spec, self.srs, self.origin, self.centre = spec, srs, origin, centre
        self.tiles: dict[str, dict] = {}

    def add(self, folder: Path, tile: str, node: Node) -> int:
        """Write the node's glb into ``folder``, add its tile to the tree; return the glb's bytes."""
        offset = to_ecef(node.vertices + self.origin, self.srs) - self.centre
        name = f"{tile}_L{node.level}" + (f"_{node.path}" if node.path else "") + ".glb"
        data = node_glb(node, offset)
        (folder / name).write_bytes(data)
        leaf = node.level + 1 == self.spec.levels
        self.tiles[node.path] = {"boundingVolume": {"sphere": sphere(offset)},
                                 "geometricError": 0.0 if leaf else self.spec.texel(node.level) / 2,
                                 "refine": "REPLACE", "content": {"uri": name}}
        if node.path:
            self.tiles[node.path[:-1]].setdefault("children", []).append(self.tiles[node.path])
        return len(data)

    def tileset(self) -> dict:
        root = dict(self.tiles[""])
        root["transform"] = [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, *self.centre.tolist(), 1]
        return {"asset": {"version": "1.1"}, "geometricError": root["geometricError"] * 2, "root": root}


def root_tileset(entries: list[tuple[str, list[float]]], error: float) -> str:
    """The dataset's tileset.json: one child per tile (its external tileset and ECEF sphere)."""
    spheres = np.array([s for _, s in entries])
    lo, hi = (spheres[:, :3] - spheres[:, 3:]).min(axis=0), (spheres[:, :3] + spheres[:, 3:]).max(axis=0)
    children = [{"boundingVolume": {"sphere": s}, "geometricError": error, "refine": "REPLACE",
                 "content": {"uri": uri}} for uri, s in entries]
    root = {"boundingVolume": {"sphere": [*((lo + hi) / 2).tolist(), float(np.linalg.norm(hi - lo) / 2)]},
            "geometricError": error, "refine": "REPLACE", "children": children}
    return json.dumps({"asset": {"version": "1.1"}, "geometricError": error, "root": root}, indent=1)
