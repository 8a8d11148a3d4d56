"""Esri I3S scene layers (an OGC community standard), as ArcGIS Pro, Drone2Map and ArcGIS Reality
export city models and photogrammetry: a scene layer package ``.slpk`` (a zip) or that package
unpacked into a folder. Read: ``3DObject`` and ``IntegratedMesh`` layers of I3S 1.7 and later
(node pages), and of 1.6 (node index documents, :mod:`.i3s_legacy`).

A package holds ``3dSceneLayer.json`` (the layer: its spatial reference, geometry, material and
texture set definitions, ``nodePages``), ``nodepages/<k>.json`` (its nodes: an oriented box
``obb``, ``children``, a ``lodThreshold`` and a ``mesh`` naming a geometry and a texture
resource) and ``nodes/<resource>/geometries/<buffer>.bin`` and ``.../textures/<name>.<format>``;
each entry may be gzipped (``.gz``, as a package stores them).

**Level rule**, as I3S clients switch nodes on screen (``node-switching``): a node's bounding sphere
(radius: its box's half-diagonal, metres) covers ``d = 2 r / gsd`` map pixels; it is drawn while
that is at most its threshold, else its children replace it. The threshold is a diameter in
pixels for ``maxScreenThreshold``, an area in pixels² (``maxScreenThresholdSQ``, the default) that
is the diameter ``sqrt(4 t / pi)``. A node without a mesh is always refined, one without
children always drawn; ``gsd`` None (full detail) draws the leaves.

**Geometry**: the uncompressed buffer (``vertexCount``, ``featureCount``, then per vertex
``position``, ``normal``, ``uv0``, ``color``, ``uvRegion``, then per feature ``featureId`` and
``faceRange``, as its definition lists them; every three vertices a triangle). Positions are offsets from the node's box
centre: in degrees of longitude and latitude and metres of height for a geographic layer
(``wkid`` 4326), in its units for a projected one. The layer's CRS is its ``wkid`` with its
``vcsWkid`` (a compound CRS) where its ``heightModelInfo`` says gravity-related heights; the
input's ``crs`` key overrides it. A Draco-compressed buffer is read where the
package has no uncompressed one (:mod:`.i3s_draco`: a geographic layer's position scale and the
feature ids are in its Draco metadata).

**Textures**: the texture set's JPEG or PNG, else its KTX2 (:mod:`.ktx2`), else its DDS (S3TC/BC,
level 0 decoded by Pillow); KTX (ETC2) alone is a missing texture (``missing_textures``). ``uv0``
has its origin at the image's top row (as glTF); a ``uvRegion`` (an atlas's sub-image) maps ``uv0``,
clipped to [0, 1], into it. Without a texture, the vertex colours times the material's base colour.
A ``3DObject`` layer's features (its buildings) are the parts' objects, keyed by feature id.
"""

from __future__ import annotations

import logging
import math
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline25d.core.errors import InputFileError, MissingTextureWarning, UnsupportedFeatureError
from pipeline25d.core.mesh import MeshPart
from pipeline25d.formats import ktx2
from pipeline25d.formats.common import Detail, Loaded, image_problem, png_or_jpeg
from pipeline25d.formats.decoded_png import image_as_png
from pipeline25d.formats.i3s_attributes import VALUE_TYPES
from pipeline25d.formats.slpk import Package

log = logging.getLogger(__name__)

LAYER_TYPES = ("3DObject", "IntegratedMesh")
PIECE_VERTICES = 2_000_000     # vertices of the nodes read into one piece (memory follows a piece)
#: the value types a geometry buffer's attributes may have (I3S's numeric types but object ids)
_TYPES = {k: VALUE_TYPES[k] for k in ("Float32", "Float64", "UInt8", "UInt16", "UInt32", "UInt64", "Int8", "Int16",
                                      "Int32")}
_ORDER = ("position", "normal", "uv0", "color", "uvRegion", "featureId", "faceRange")
_PER_FEATURE = ("featureId", "faceRange", "id")
_TEXTURE_ORDER = ("jpg", "png", "ktx2", "dds")


@dataclass(frozen=True)
class Layer:
    """What reading a layer's nodes needs from its ``3dSceneLayer.json``."""

    doc: dict
    crs: str
    geographic: bool
    metric: str
    objects: bool
    legacy: bool = False

    @classmethod
    def of(cls, package: Package, spec: dict) -> "Layer":
        doc = package.json("3dSceneLayer")
        kind = doc.get("layerType")
        if kind not in LAYER_TYPES:
            raise UnsupportedFeatureError(package.path, f"I3S layerType {kind!r}: only {' and '.join(LAYER_TYPES)} "
                                                        "layers are meshes")
        pages = doc.get("nodePages")
        if not isinstance(pages, dict) or not isinstance(pages.get("nodesPerPage"), int) or pages["nodesPerPage"] < 1:
            pages = None               # I3S 1.6: node index documents (:mod:`.i3s_legacy`)
        crs = spec.get("crs") or _layer_crs(doc)
        if not crs:
            raise InputFileError(package.path, "3dSceneLayer.json names no spatialReference (set the input's crs)")
        from pipeline25d.core.crs import is_geographic

        metric = (pages or {}).get("lodSelectionMetricType", "maxScreenThresholdSQ")
        return cls(doc, crs, is_geographic(crs), metric, kind == "3DObject", pages is None)

    def nodes(self, package: Package):
        """The layer's nodes by index (node pages) or by id (1.6 documents), with its ``root``."""
        if self.legacy:
            from pipeline25d.formats.i3s_legacy import NodeDocuments

            return NodeDocuments(package, self.doc.get("store") or {})
        return _NodePages(package, self.doc["nodePages"]["nodesPerPage"])


def _layer_crs(doc: dict) -> str | None:
    """The layer's CRS: its ``wkid`` (or WKT), with its vertical ``vcsWkid`` where its heights are
    gravity-related (so they are moved as such, not as ellipsoidal heights); None where it names none."""
    from pipeline25d.core.crs import parse_crs

    ref = doc.get("spatialReference") or {}
    wkid, vcs = ref.get("latestWkid") or ref.get("wkid"), ref.get("latestVcsWkid") or ref.get("vcsWkid")
    crs = f"EPSG:{wkid}" if isinstance(wkid, int) else ref.get("wkt")
    model = (doc.get("heightModelInfo") or {}).get("heightModel", "gravity_related_height")
    if isinstance(wkid, int) and isinstance(vcs, int) and model != "ellipsoidal":
        try:
            parse_crs(f"EPSG:{wkid}+{vcs}")
            return f"EPSG:{wkid}+{vcs}"
        except Exception:          # a combination PROJ does not know: the horizontal CRS alone
            pass
    return crs if isinstance(crs, str) else None


def read_i3s(path: Path, spec: dict, detail: Detail = Detail()) -> Loaded:
    """Reader contract (:mod:`pipeline25d.formats`): a scene layer package at ``detail.gsd``."""
    pieces = list(read_i3s_pieces(path, spec, detail))
    return Loaded([p for piece in pieces for p in piece.parts], pieces[0].crs)


def read_i3s_pieces(path: Path, spec: dict, detail: Detail = Detail()) -> Iterator[Loaded]:
    """:func:`read_i3s` as pieces of drawn nodes, about :data:`PIECE_VERTICES` vertices each."""
    package = Package(path)
    layer = Layer.of(package, spec)
    drawn = drawn_nodes(layer.nodes(package), detail.gsd, layer.metric)
    if not drawn:
        raise InputFileError(package.path, f"holds no mesh at gsd {detail.gsd} (no node with a mesh)")
    log.info("%s: %d I3S nodes drawn at gsd %s", package.path, len(drawn), detail.gsd)
    piece: list[MeshPart] = []
    count = 0
    for node in drawn:
        part = _node_part(package, layer, node)
        if part is None:
            continue
        piece.append(part)
        count += len(part.vertices)
        if count >= PIECE_VERTICES:
            yield Loaded(piece, layer.crs)
            piece, count = [], 0
    if piece:
        yield Loaded(piece, layer.crs)


class _NodePages:
    """The layer's nodes by index, their pages read when first needed."""

    root = 0

    def __init__(self, package: Package, per_page: int):
        self.package, self.per_page, self.pages = package, per_page, {}

    def __getitem__(self, index: int) -> dict:
        if not isinstance(index, int) or index < 0:
            raise InputFileError(self.package.path, f"node index {index!r} is not a node")
        page, k = divmod(index, self.per_page)
        if page not in self.pages:
            nodes = self.package.json(f"nodepages/{page}").get("nodes")
            self.pages[page] = nodes if isinstance(nodes, list) else []
        nodes = self.pages[page]
        if k >= len(nodes) or not isinstance(nodes[k], dict):
            raise InputFileError(self.package.path, f"node {index} is not in nodepages/{page}")
        return nodes[k]


def drawn_nodes(nodes, gsd: float | None, metric: str) -> list[dict]:
    """The nodes the level rule (module doc) draws at ``gsd``, from the root (``nodes.root``) down."""
    drawn, stack, seen = [], [nodes.root], set()
    while stack:
        index = stack.pop()
        if index in seen:
            raise InputFileError(nodes.package.path, f"node {index} is reached twice (the node tree has a cycle)")
        seen.add(index)
        node = nodes[index]
        children = node.get("children") or []
        if node.get("mesh") and (not children or _fine_enough(node, gsd, metric)):
            drawn.append(node)
        else:
            stack.extend(reversed(children))
    return drawn


def _fine_enough(node: dict, gsd: float | None, metric: str) -> bool:
    threshold, metric = node.get("lodThreshold"), node.get("metric", metric)
    if gsd is None or not isinstance(threshold, (int, float)) or threshold <= 0:
        return False
    radius = node.get("radius") or float(np.linalg.norm(node.get("obb", {}).get("halfSize", [0, 0, 0])))
    limit = threshold if metric == "maxScreenThreshold" else math.sqrt(4 * threshold / math.pi)
    return 2 * radius / gsd <= limit


def _node_part(package: Package, layer: Layer, node: dict) -> MeshPart | None:
    """A drawn node's mesh, placed in the layer's CRS; None for an empty one."""
    mesh = node["mesh"]
    if layer.legacy:
        from pipeline25d.formats.i3s_legacy import geometry_layouts

        name = mesh["geometry"]["href"]
        values = _uncompressed(_entry(package, name, ".bin"), geometry_layouts(layer.doc.get("store") or {}),
                               package, name)
    else:
        values = _geometry(package, layer, mesh.get("geometry") or {}, node.get("index"))
    position = values["position"].astype(np.float64)
    if not len(position):
        return None
    centre = np.asarray(node.get("obb", {}).get("center", [0, 0, 0]), dtype=np.float64)
    vertices = position + centre
    faces = np.arange(len(vertices), dtype=np.int64).reshape(-1, 3)
    if layer.legacy:
        href = mesh["material"]["href"]
        texture = None if href is None else _texture(package, [(f, href) for f in _TEXTURE_ORDER], node.get("index"))
        colors = _rgba(values.get("color"), np.ones(4), len(values["position"]))
    else:
        texture, colors = _appearance(package, layer, mesh.get("material") or {}, values, node.get("index"))
    uv = None
    if texture is not None and values.get("uv0") is not None:
        uv = _uv(values["uv0"], values.get("uvRegion"))
    else:
        texture = None
    part = MeshPart(vertices, faces, colors=colors if texture is None else None, uv=uv, texture=texture,
                    name=f"node {node.get('index')}")
    if not layer.objects:
        return part
    from pipeline25d.formats.i3s_attributes import with_features

    resource = node.get("index") if layer.legacy else (mesh.get("attribute") or {}).get("resource")
    return with_features(part, values, package, layer.doc.get("attributeStorageInfo"), resource)


def _geometry(package: Package, layer: Layer, geometry: dict, index) -> dict[str, np.ndarray]:
    definitions = layer.doc.get("geometryDefinitions")
    try:
        buffers = definitions[geometry.get("definition", 0)]["geometryBuffers"]
    except (TypeError, IndexError, KeyError):
        raise InputFileError(package.path, f"node {index}: its geometry definition "
                                           f"{geometry.get('definition')!r} is not in the layer") from None
    resource = geometry.get("resource", index)
    tried = []
    for k in sorted(range(len(buffers)), key=lambda k: "compressedAttributes" in buffers[k]):
        name = f"nodes/{resource}/geometries/{k}"
        data = package.read(name, ".bin")
        tried.append(name)
        if data is None:
            continue
        if "compressedAttributes" in buffers[k]:
            from pipeline25d.formats.i3s_draco import draco_values

            return draco_values(data, layer.geographic, package.path, name)
        return _uncompressed(data, buffers[k], package, name)
    raise InputFileError(package.path, f"node {index}: no geometry buffer in the package ({', '.join(tried)})")


def _uncompressed(data: bytes, layouts: dict | list[dict], package: Package, name: str) -> dict[str, np.ndarray]:
    """The attributes of an uncompressed buffer; of several ``layouts``, the first its length fits."""
    if len(data) < 8:
        raise InputFileError(package.path, f"{name} is shorter than its 8-byte header")
    n, features = (int(v) for v in np.frombuffer(data, "<u4", 2))
    sized = [(lay, _fields(lay, n, features, package, name)) for lay in (layouts if isinstance(layouts, list)
                                                                            else [layouts])]
    layout, fields = next(((lay, f) for lay, f in sized if _length(lay, f) == len(data)), sized[0])
    at = int(layout.get("offset", 8))
    values = {}
    for key, dtype, count, width in fields:
        end = at + count * dtype.itemsize
        if end > len(data):
            raise InputFileError(package.path, f"{name} is cut short: attribute {key} ends at byte {end}, "
                                               f"the buffer has {len(data)} ({n} vertices, {features} features)")
        values[key] = np.frombuffer(data, dtype, count, at).reshape(-1, width)
        at = end
    if "position" not in values or n % 3:
        raise InputFileError(package.path, f"{name}: {n} vertices with{'out' if 'position' not in values else ''} "
                                           "positions (three vertices a triangle are needed)")
    return values


def _fields(layout: dict, n: int, features: int, package: Package, name: str) -> list[tuple]:
    """(key, dtype, values, values per element) of each attribute ``layout`` names, in buffer order,
    for ``n`` vertices and ``features`` features; InputFileError for a type I3S does not define."""
    fields = []
    for key in _ORDER:
        field = layout.get(key)
        if not isinstance(field, dict):
            continue
        dtype, width = _TYPES.get(field.get("type")), field.get("component", 1)
        if dtype is None or not isinstance(width, int) or width < 1:
            raise InputFileError(package.path, f"{name}: attribute {key} has type {field.get('type')!r} x "
                                               f"{width!r}, which I3S does not define")
        fields.append((key, np.dtype(dtype), (features if key in _PER_FEATURE else n) * width, width))
    return fields


def _length(layout: dict, fields: list[tuple]) -> int:
    """The byte length of a buffer of ``layout`` holding ``fields`` (:func:`_fields`)."""
    return int(layout.get("offset", 8)) + sum(count * dtype.itemsize for _, dtype, count, _ in fields)


def _entry(package: Package, name: str, *suffixes: str) -> bytes:
    data = package.read(name, *suffixes)
    if data is None:
        raise InputFileError(package.path, f"{name} is not in the package")
    return data


def _appearance(package: Package, layer: Layer, material: dict, values: dict,
                index) -> tuple[bytes | None, np.ndarray | None]:
    """(texture bytes, None) or (None, RGBA vertex colours or None) of a node's mesh."""
    definition = _item(layer.doc.get("materialDefinitions"), material.get("definition", 0)) or {}
    pbr = definition.get("pbrMetallicRoughness") or {}
    factor = np.asarray(pbr.get("baseColorFactor", [1, 1, 1, 1]), dtype=np.float64)
    colors = _rgba(values.get("color"), factor, len(values["position"]))
    texture_id = (pbr.get("baseColorTexture") or {}).get("textureSetDefinitionId")
    if texture_id is None:
        return None, colors
    formats = (_item(layer.doc.get("textureSetDefinitions"), texture_id) or {}).get("formats") or []
    by_format = {f.get("format"): f.get("name") for f in formats if isinstance(f, dict)}
    resource = material.get("resource", index)
    candidates = [(f, f"nodes/{resource}/textures/{by_format[f]}") for f in _TEXTURE_ORDER if f in by_format]
    said = "" if candidates else f"names none of {', '.join(_TEXTURE_ORDER)} (only {sorted(map(str, by_format))})"
    return _texture(package, candidates, index, said), colors


def _rgba(colour: np.ndarray | None, factor: np.ndarray, n: int) -> np.ndarray | None:
    """RGBA vertex colours: ``colour`` (or white) times the base colour ``factor``; None for white alone."""
    if colour is None and np.allclose(factor, 1):
        return None
    rgba = np.full((n, 4), 255.0) if colour is None else \
        np.concatenate([colour, np.full((len(colour), 4 - colour.shape[1]), 255)], axis=1)[:, :4].astype(float)
    return np.clip(np.rint(rgba * np.resize(factor, 4)), 0, 255).astype(np.uint8)


def _texture(package: Package, candidates: list[tuple[str, str]], index, problem: str = "") -> bytes | None:
    """The first of ``candidates`` ((format, entry name), in :data:`_TEXTURE_ORDER`) that is a readable
    image, as JPEG or PNG bytes; None with a MissingTextureWarning saying why when there is none."""
    for fmt, name in candidates:
        data = package.read(name, f".{fmt}", f".bin.{fmt}")
        if data is None:
            problem = problem or f"{name} is not in the package (as {fmt.upper()}; JPEG, PNG, KTX2 and DDS are read)"
            continue
        if data[:4] == b"DDS ":
            data, problem = _dds_as_png(data, name)
            if data is None:
                continue
        if ktx2.is_ktx2(data):
            try:
                return ktx2.ktx2_as_png(data)
            except ktx2.Ktx2Error as exc:
                problem = f"{name} cannot be read (KTX2: {exc})"
                continue
        problem = f"{name} is neither JPEG nor PNG" if not png_or_jpeg(data) else image_problem(data)
        if problem is None:
            return data
        problem = f"{name} {problem}"
    warnings.warn(f"{package.path}: the texture of node {index}: {problem}; its parts are drawn untextured",
                  MissingTextureWarning, stacklevel=5)
    return None


def _dds_as_png(data: bytes, name: str) -> tuple[bytes | None, str | None]:
    """A DDS texture's level 0 as PNG bytes (Pillow decodes DXT1/3/5 and BC4-7), or (None, the problem)."""
    png, problem = image_as_png(data)
    return png, None if png is not None else f"{name} cannot be read (DDS: {problem})"


def _uv(uv0: np.ndarray, region: np.ndarray | None) -> np.ndarray:
    """GL texture coordinates (v = 0 the bottom row) of I3S ``uv0`` (v = 0 the top row), in an
    atlas's ``uvRegion`` where given."""
    uv = uv0.astype(np.float64)
    if region is not None:
        lo, hi = region[:, :2] / 65535.0, region[:, 2:4] / 65535.0
        uv = lo + np.clip(uv, 0, 1) * (hi - lo)
    return np.column_stack([uv[:, 0], 1 - uv[:, 1]]).astype(np.float32)


def _item(items, index) -> dict | None:
    ok = isinstance(items, list) and isinstance(index, int) and 0 <= index < len(items)
    return items[index] if ok and isinstance(items[index], dict) else None

