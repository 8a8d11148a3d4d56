"""A small I3S scene layer package with exact truth, written as ArcGIS Pro lays one out.

Node 0 is a root without a mesh over one node (1): a coarse level, a 100 m square quad at z = 0
with a PNG texture. Its children (2, 3) are the fine level: the square's west and east halves,
each two triangles at z = 5, node 2 of two features (ids 101 and 102, a triangle each). The
coarse node's threshold is :data:`SWITCH_PX` pixels of diameter (given as an area,
``maxScreenThresholdSQ``): its bounding sphere (radius 70.7 m) covers 141 px at gsd 1 (the fine
level drawn) and 71 px at gsd 2 (the coarse). Positions are offsets from each node's box centre,
in metres in a projected layer, in degrees of longitude and latitude in a geographic one (the
square's corners then lie at the lon/lat of :func:`corners_lonlat`).
"""

from __future__ import annotations

import gzip
import io
import json
import math
import zipfile
from pathlib import Path

import numpy as np

SIDE_M = 100.0
SWITCH_PX = 100.0
PROJECTED = ("EPSG:28992", np.array([85000.0, 447000.0, 0.0]))
GEOGRAPHIC_CENTRE = np.array([4.3571, 52.0116, 0.0])       # lon, lat, h: Delft
FEATURE_IDS = (101, 102)
VERTICAL = 5709                # NAP heights


def _quad(x0: float, x1: float, y0: float, y1: float, z: float) -> np.ndarray:
    """Two triangles' six corners (non-indexed, as I3S stores them), counter-clockwise from above."""
    a, b, c, d = (x0, y0, z), (x1, y0, z), (x1, y1, z), (x0, y1, z)
    return np.array([a, b, c, a, c, d], dtype=np.float64)


def node_corners() -> dict[int, np.ndarray]:
    """Each mesh node's corners in metres from the square's centre (x east, y north)."""
    h = SIDE_M / 2
    return {1: _quad(-h, h, -h, h, 0.0), 2: _quad(-h, 0.0, -h, h, 5.0), 3: _quad(0.0, h, -h, h, 5.0)}


def corners_lonlat(metres: np.ndarray) -> np.ndarray:
    """Metres from the square's centre as lon/lat/h on a sphere of radius 6378137 m (the sample's own
    rule; the test compares what the reader places with pyproj's transform of these lon/lat)."""
    lon0, lat0, _ = GEOGRAPHIC_CENTRE
    r = 6378137.0
    return np.column_stack([lon0 + np.degrees(metres[:, 0] / (r * math.cos(math.radians(lat0)))),
                            lat0 + np.degrees(metres[:, 1] / r), metres[:, 2]])


def texture_png() -> bytes:
    """A 4 x 4 PNG: its top row red, the rest blue (the top row is v = 0 in I3S)."""
    from PIL import Image

    pixels = np.zeros((4, 4, 3), np.uint8)
    pixels[:, :, 2] = 255
    pixels[0] = (255, 0, 0)
    out = io.BytesIO()
    Image.fromarray(pixels).save(out, format="PNG")
    return out.getvalue()


def _geometry(points: np.ndarray, uv: np.ndarray | None, features: list[tuple[int, int, int]]) -> bytes:
    """The uncompressed geometry buffer: header, position, uv0, color, featureId, faceRange."""
    n = len(points)
    colour = np.tile(np.array([200, 180, 160, 255], np.uint8), (n, 1))
    out = [np.array([n, len(features)], "<u4").tobytes(), points.astype("<f4").tobytes(),
           (uv if uv is not None else np.zeros((n, 2))).astype("<f4").tobytes(), colour.tobytes(),
           np.array([f[0] for f in features], "<u8").tobytes(),
           np.array([f[1:] for f in features], "<u4").reshape(-1, 2).tobytes()]
    return b"".join(out)


def write_package(target: Path, geographic: bool = False, draco: bool = False, uncompressed: bool = True,
                  layer_type: str = "3DObject", packed: bool = True, pages: bool = True) -> Path:
    """The package at ``target`` (``.slpk``; ``packed`` False: its entries in a folder there).
    ``draco``: a Draco buffer beside (or, without ``uncompressed``, instead of) the plain one.
    Every package holds I3S 1.6 node index documents, as ArcGIS Pro writes them beside the node
    pages of 1.7; ``pages`` False leaves the pages out (a 1.6 package)."""
    crs, centre = ("EPSG:4326", GEOGRAPHIC_CENTRE) if geographic else PROJECTED
    entries: dict[str, bytes] = {}
    threshold = math.pi / 4 * SWITCH_PX ** 2
    nodes = [{"index": 0, "obb": _obb(centre, (80, 80, 10)), "children": [1]}]
    for k, metres in node_corners().items():
        middle = (metres.min(0) + metres.max(0)) / 2
        if geographic:
            lonlat = corners_lonlat(metres)
            box_centre = corners_lonlat(middle[None])[0]
            offsets = lonlat - box_centre
        else:
            box_centre, offsets = centre + middle, metres - middle
        half = (metres.max(0) - metres.min(0)) / 2 + (0, 0, 0.5)
        node = {"index": k, "parentIndex": 0 if k == 1 else 1, "obb": _obb(box_centre, half),
                "mesh": {"geometry": {"definition": 0, "resource": k, "vertexCount": 6,
                                      "featureCount": 2 if k == 2 else 1},
                         "material": {"definition": 1 if k == 1 else 0, "resource": k},
                         "attribute": {"resource": k}}}
        if k == 1:
            node.update(children=[2, 3], lodThreshold=threshold)
        nodes.append(node)
        entries[f"nodes/{k}/3dNodeIndexDocument.json.gz"] = _document(node)
        uv = np.array([(0, 1), (1, 1), (1, 0), (0, 1), (1, 0), (0, 0)], float)   # v = 0 at the north edge
        features = [(101, 0, 0), (102, 1, 1)] if k == 2 else [(200 + k, 0, 1)]
        for key, data in _attribute_buffers([f[0] for f in features]).items():
            entries[f"nodes/{k}/attributes/{key}/0.bin.gz"] = gzip.compress(data)
        if uncompressed:
            entries[f"nodes/{k}/geometries/0.bin.gz"] = gzip.compress(_geometry(offsets, uv, features))
        if draco:
            entries[f"nodes/{k}/geometries/1.bin.gz"] = gzip.compress(_draco_buffer(offsets, uv, features, geographic))
        if k == 1:
            entries[f"nodes/{k}/textures/0.png"] = texture_png()
    layer = {
        "id": 0, "layerType": layer_type, "version": "sample",
        # a vertical CRS on the geographic layer only: the projected one is the tests' scene CRS itself, so
        # its vertices are compared exactly, whatever geoid grids PROJ finds
        "spatialReference": {"wkid": int(crs.split(":")[1]), **({"vcsWkid": VERTICAL} if geographic else {})},
        "nodePages": {"nodesPerPage": 64, "lodSelectionMetricType": "maxScreenThresholdSQ"},
        "geometryDefinitions": [{"geometryBuffers": [
            {"offset": 8, "position": {"type": "Float32", "component": 3}, "uv0": {"type": "Float32", "component": 2},
             "color": {"type": "UInt8", "component": 4}, "featureId": {"type": "UInt64", "component": 1},
             "faceRange": {"type": "UInt32", "component": 2}},
            {"compressedAttributes": {"encoding": "draco", "attributes": ["position", "uv0"]}}]}],
        "materialDefinitions": [{"doubleSided": True},
                                {"pbrMetallicRoughness": {"baseColorTexture": {"textureSetDefinitionId": 0}}}],
        "textureSetDefinitions": [{"formats": [{"name": "0", "format": "png"}]}],
        "fullExtent": _extent(centre, geographic),
        "attributeStorageInfo": ATTRIBUTE_FIELDS,
    }
    layer["store"] = {"rootNode": "./nodes/root", "defaultGeometrySchema": {
        "ordering": ["position", "uv0", "color"], "featureAttributeOrder": ["id", "faceRange"],
        "vertexAttributes": {"position": {"valueType": "Float32", "valuesPerElement": 3},
                             "uv0": {"valueType": "Float32", "valuesPerElement": 2},
                             "color": {"valueType": "UInt8", "valuesPerElement": 4}},
        "featureAttributes": {"id": {"valueType": "UInt64", "valuesPerElement": 1},
                              "faceRange": {"valueType": "UInt32", "valuesPerElement": 2}}}}
    entries["nodes/root/3dNodeIndexDocument.json.gz"] = _document(nodes[0])
    if pages:
        entries["nodepages/0.json.gz"] = gzip.compress(json.dumps({"nodes": nodes}).encode())
    else:
        del layer["nodePages"]
    entries["3dSceneLayer.json.gz"] = gzip.compress(json.dumps(layer).encode())
    entries["metadata.json"] = json.dumps({"folderPattern": "basic", "ArchiveCompressionType": "Store",
                                           "I3SVersion": "1.7", "nodeCount": len(nodes)}).encode()
    target.parent.mkdir(parents=True, exist_ok=True)
    if packed:
        with zipfile.ZipFile(target, "w", zipfile.ZIP_STORED) as z:
            for name, data in entries.items():
                z.writestr(name, data)
    else:
        for name, data in entries.items():
            (target / name).parent.mkdir(parents=True, exist_ok=True)
            (target / name).write_bytes(data)
    return target


#: the layer's fields: a feature's OBJECTID (its id), a name and a height
ATTRIBUTE_FIELDS = [
    {"key": "f_0", "name": "OBJECTID", "header": [{"property": "count", "valueType": "UInt32"}],
     "ordering": ["attributeValues"], "attributeValues": {"valueType": "Oid32", "valuesPerElement": 1}},
    {"key": "f_1", "name": "name", "header": [{"property": "count", "valueType": "UInt32"},
                                              {"property": "attributeValuesByteCount", "valueType": "UInt32"}],
     "ordering": ["attributeByteCounts", "attributeValues"], "attributeValues": {"valueType": "String"}},
    {"key": "f_2", "name": "height", "header": [{"property": "count", "valueType": "UInt32"}],
     "ordering": ["attributeValues"], "attributeValues": {"valueType": "Float64", "valuesPerElement": 1}},
]


def feature_name(feature_id: int) -> str:
    return f"Gebäude {feature_id}"


def _attribute_buffers(ids: list[int]) -> dict[str, bytes]:
    """A node's attribute buffers as ArcGIS lays them out: a count, byte counts for text (each value
    NUL-terminated), a Float64 aligned to 8 bytes after the 4-byte count."""
    count = np.array([len(ids)], "<u4").tobytes()
    names = [feature_name(i).encode() + b"\0" for i in ids]
    return {"f_0": count + np.array(ids, "<u4").tobytes(),
            "f_1": count + np.array([sum(map(len, names))], "<u4").tobytes()
            + np.array([len(n) for n in names], "<u4").tobytes() + b"".join(names),
            "f_2": count + bytes(4) + np.array([i / 4 for i in ids], "<f8").tobytes()}


DRACO_SCALE = 1 / 111319.49079327357       # degrees per Draco unit, as ArcGIS writes i3s-scale_x and _y


def _draco_buffer(offsets: np.ndarray, uv: np.ndarray, features: list[tuple[int, int, int]],
                  geographic: bool) -> bytes:
    """A Draco buffer as ArcGIS writes one: a geographic layer's x, y in units of
    :data:`DRACO_SCALE` degrees, each vertex's feature index in a generic attribute, and I3S's
    metadata (scale; attribute type and feature ids) spliced in after the 11-byte header."""
    import struct

    import DracoPy

    points = offsets.copy()
    if geographic:
        points[:, :2] /= DRACO_SCALE
    index = np.zeros((len(points), 1))
    for k, (_, first, last) in enumerate(features):
        index[3 * first:3 * last + 3] = k
    data = DracoPy.encode(points, np.arange(len(points)).reshape(-1, 3), quantization_bits=24, preserve_order=True,
                          tex_coord=uv.astype(np.float64), generic_attributes={7: index})
    ids = {a["attribute_type"]: a["unique_id"] for a in DracoPy.decode(data).attributes}

    def element(entries: dict[str, bytes]) -> bytes:      # every size below 128: one-byte varints
        return bytes([len(entries)]) + b"".join(bytes([len(k)]) + k.encode() + bytes([len(v)]) + v
                                                for k, v in entries.items()) + b"\0"

    scale = struct.pack("<d", DRACO_SCALE)
    position = element({"i3s-scale_x": scale, "i3s-scale_y": scale} if geographic else {})
    feature = element({"i3s-attribute-type": b"feature-index\0",
                       "i3s-feature-ids": np.array([f[0] for f in features], "<i4").tobytes()})
    metadata = bytes([2, ids[0]]) + position + bytes([ids[4]]) + feature + element({})
    flags = struct.unpack_from("<H", data, 9)[0] | 0x8000
    return data[:9] + struct.pack("<H", flags) + metadata + data[11:]


def _document(node: dict) -> bytes:
    """A node's 1.6 index document: its bounding sphere, threshold (a diameter), children and data."""
    name = "root" if node["index"] == 0 else str(node["index"])
    doc = {"id": name, "mbs": [*node["obb"]["center"], float(np.linalg.norm(node["obb"]["halfSize"]))],
           "children": [{"id": str(c), "href": f"../{c}"} for c in node.get("children", [])]}
    if "lodThreshold" in node:
        doc["lodSelection"] = [{"metricType": "maxScreenThreshold", "maxError": SWITCH_PX},
                               {"metricType": "maxScreenThresholdSQ", "maxError": node["lodThreshold"]}]
    if "mesh" in node:
        doc["geometryData"] = [{"href": "./geometries/0"}]
        if node["index"] == 1:
            doc["textureData"] = [{"href": "./textures/0"}]
    return gzip.compress(json.dumps(doc).encode())


def _obb(centre, half) -> dict:
    return {"center": [float(v) for v in centre], "halfSize": [float(v) for v in half], "quaternion": [0, 0, 0, 1]}


def _extent(centre: np.ndarray, geographic: bool) -> dict:
    corners = node_corners()[1][[0, 2]] + (0, 0, 0)
    lo, hi = corners.min(0), corners.max(0) + (0, 0, 5)
    if geographic:
        lo, hi = corners_lonlat(lo[None])[0], corners_lonlat(hi[None])[0]
    else:
        lo, hi = centre + lo, centre + hi
    return dict(zip(("xmin", "ymin", "zmin", "xmax", "ymax", "zmax"), [*map(float, lo), *map(float, hi)]))
