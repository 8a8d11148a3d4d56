"""glTF 1.0 (and its binary container, ``KHR_binary_glTF``) brought to glTF 2.0 JSON, which
:mod:`.gltf` reads.

3D Tiles 1.0 tilesets written before 2018 (CesiumJS's own samples of the time, many converters'
b3dm) hold glTF 1.0. CesiumJS still draws them, upgrading each in memory as gltf-pipeline's
``updateVersion`` does; this does the part of that upgrade that drawing a map needs:

* objects keyed by id become arrays, every reference by id an index;
* an accessor's ``byteStride`` moves to a buffer view of its own (2.0 puts strides on views), its
  ``WEB3D_quantized_attributes`` stays on it (the reader decodes it);
* the binary container's body is the GLB binary chunk (the ``binary_glTF`` buffer), its images
  the buffer views their ``KHR_binary_glTF`` names;
* a node's several meshes become child nodes of one mesh each;
* attribute semantics: ``TEXCOORD``/``COLOR`` become ``TEXCOORD_0``/``COLOR_0``, application
  semantics (``BATCHID``) get their leading underscore (``_BATCHID``);
* the base colour: ``KHR_materials_common``' diffuse, else the material value bound to a
  technique's diffuse uniform (``u_diffuse``, ``u_tex``, ``u_emission``, ``u_diffuse_tex``, as
  gltf-pipeline looks for them), else a value named ``diffuse``: a texture id or an RGBA colour,
  kept as written (the reader takes 2.0 factors as written too). Techniques, shaders, programs,
  skins, cameras, lights and animations are left out.
"""

from __future__ import annotations

import json
import struct
from pathlib import Path
from typing import Any

import numpy as np

from pipeline25d.core.errors import InputFileError

#: the technique uniforms whose material values are the base colour (gltf-pipeline's defaults)
BASE_COLOUR_UNIFORMS = ("u_diffuse", "u_tex", "u_emission", "u_diffuse_tex")
#: an accessor's componentType and type, as both glTF versions name them (the 2.0 reader's too)
COMPONENT_DTYPES = {
    5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32, 5126: np.float32,
}
TYPE_SIZES = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
_KNOWN_SEMANTICS = {"POSITION", "NORMAL", "TANGENT"}
_INDEXED_SEMANTICS = {"COLOR": "COLOR", "TEXCOORD": "TEXCOORD", "JOINT": "JOINTS", "JOINTS": "JOINTS",
                      "WEIGHT": "WEIGHTS", "WEIGHTS": "WEIGHTS"}
_DROPPED_EXTENSIONS = {"KHR_binary_glTF", "KHR_materials_common", "WEB3D_quantized_attributes"}


def split_glb1(data: bytes, path: Path) -> tuple[dict, bytes]:
    """(JSON, body) of a binary glTF 1.0 (``KHR_binary_glTF``: a 20-byte header, the JSON scene, the body)."""
    if len(data) < 20:
        raise InputFileError(path, "binary glTF 1.0 is truncated (shorter than its header)")
    _, _, length, content_length, content_format = struct.unpack_from("<4sIIII", data, 0)
    if content_format != 0:
        raise InputFileError(path, f"binary glTF 1.0 content format {content_format} is not JSON (0)")
    if length > len(data) or 20 + content_length > length:
        raise InputFileError(path, f"binary glTF 1.0 header says {length} bytes ({content_length} of JSON) but "
                                   f"{len(data)} are present (truncated)")
    try:
        doc = json.loads(data[20:20 + content_length].decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputFileError(path, f"binary glTF 1.0 JSON is invalid: {exc}") from None
    return doc, data[20 + content_length:length]


def is_gltf1(doc: dict) -> bool:
    """Whether a glTF JSON document is glTF 1.0: its asset version (a string, or the number 1 that
    early exporters wrote) says 1, or it has no version and keys its buffers by id."""
    version = str((doc.get("asset") or {}).get("version", ""))
    return version.startswith("1") or (not version and isinstance(doc.get("buffers"), dict))


def upgraded(doc: dict, path: Path) -> dict:
    """The glTF 2.0 JSON of glTF 1.0 ``doc`` (see the module). A reference to an id that is not
    there is an :class:`InputFileError` naming ``path``."""
    try:
        return _Upgrade(doc, path).run()
    except (AttributeError, TypeError, ValueError) as exc:
        raise InputFileError(path, f"glTF 1.0 JSON holds a value of the wrong type ({exc})") from None


class _Upgrade:
    def __init__(self, doc: dict, path: Path):
        self.doc, self.path = doc, path
        self.ids = {kind: {k: i for i, k in enumerate(_table(doc, kind))}
                    for kind in ("buffers", "bufferViews", "accessors", "images", "textures", "materials",
                                 "meshes", "nodes", "scenes")}

    def index(self, kind: str, key: Any) -> int:
        try:
            return self.ids[kind][key]
        except KeyError:
            raise InputFileError(self.path, f"glTF 1.0 names {kind[:-1]} {key!r}, which it does not hold") from None

    def run(self) -> dict:
        d = self.doc
        buffers = [self.buffer(k, b) for k, b in _table(d, "buffers").items()]
        views = [{"buffer": self.index("buffers", v["buffer"]), "byteOffset": int(v.get("byteOffset", 0)),
                  "byteLength": int(v["byteLength"])} for v in _table(d, "bufferViews").values()]
        accessors = [self.accessor(a, views) for a in _table(d, "accessors").values()]
        out: dict[str, Any] = {
            "asset": {"version": "2.0", "generator": str((d.get("asset") or {}).get("generator", ""))},
            "buffers": buffers, "bufferViews": views, "accessors": accessors,
            "images": [self.image(i) for i in _table(d, "images").values()],
            "textures": [{"source": self.index("images", t["source"])} for t in _table(d, "textures").values()],
            "materials": [self.material(m) for m in _table(d, "materials").values()],
            "meshes": [self.mesh(m) for m in _table(d, "meshes").values()],
        }
        out["nodes"] = self.nodes()
        out["scenes"] = [{"nodes": [self.index("nodes", n) for n in s.get("nodes", [])]}
                         for s in _table(d, "scenes").values()]
        if d.get("scene") is not None:
            out["scene"] = self.index("scenes", d["scene"])
        extensions = {k: v for k, v in (d.get("extensions") or {}).items() if k not in _DROPPED_EXTENSIONS}
        if extensions:
            out["extensions"] = extensions
        used = [e for e in d.get("extensionsUsed", []) if e not in _DROPPED_EXTENSIONS]
        if used:
            out["extensionsUsed"] = used
        return out

    def buffer(self, key: str, buffer: dict) -> dict:
        """The binary container's body (``binary_glTF``, its uri a placeholder) has no uri in 2.0: the GLB chunk."""
        out = {"byteLength": int(buffer.get("byteLength", 0))}
        if key != "binary_glTF" and buffer.get("uri") is not None:
            out["uri"] = buffer["uri"]
        return out

    def accessor(self, a: dict, views: list[dict]) -> dict:
        """The accessor on a buffer view of its own: its bytes from the 1.0 view and offset, its stride on the view."""
        view = views[self.index("bufferViews", a["bufferView"])]
        count, stride = int(a["count"]), int(a.get("byteStride", 0))
        element = np.dtype(COMPONENT_DTYPES[int(a["componentType"])]).itemsize * TYPE_SIZES[a["type"]]
        length = (stride * (count - 1) + element) if stride and count else element * count
        own = {"buffer": view["buffer"], "byteOffset": view["byteOffset"] + int(a.get("byteOffset", 0)),
               "byteLength": length}
        if stride and stride != element:
            own["byteStride"] = stride
        views.append(own)
        out = {"bufferView": len(views) - 1, "componentType": int(a["componentType"]), "count": count,
               "type": a["type"]}
        out.update({k: a[k] for k in ("normalized", "min", "max") if k in a})
        quantized = (a.get("extensions") or {}).get("WEB3D_quantized_attributes")
        if quantized is not None:           # decoded by the reader (gltf._as_float)
            out["extensions"] = {"WEB3D_quantized_attributes": quantized}
        return out

    def image(self, image: dict) -> dict:
        binary = (image.get("extensions") or {}).get("KHR_binary_glTF")
        if binary is not None:
            return {"bufferView": self.index("bufferViews", binary["bufferView"]),
                    "mimeType": binary.get("mimeType", "image/png")}
        return {"uri": image.get("uri", "")}

    def material(self, m: dict) -> dict:
        """A 2.0 material whose base colour is the 1.0 material's diffuse (see the module)."""
        value = self.diffuse(m)
        pbr: dict[str, Any] = {}
        if isinstance(value, str):
            pbr["baseColorTexture"] = {"index": self.index("textures", value)}
        elif isinstance(value, list) and len(value) in (3, 4):
            pbr["baseColorFactor"] = [float(v) for v in value] + [1.0] * (4 - len(value))
        return {"name": m.get("name", ""), "pbrMetallicRoughness": pbr}

    def diffuse(self, m: dict) -> Any:
        common = (m.get("extensions") or {}).get("KHR_materials_common")
        if isinstance(common, dict):
            return (common.get("values") or {}).get("diffuse")
        values = m.get("values") or {}
        technique = _table(self.doc, "techniques").get(m.get("technique"), {})
        uniforms, parameters = technique.get("uniforms") or {}, technique.get("parameters") or {}
        for uniform in BASE_COLOUR_UNIFORMS:
            parameter = uniforms.get(uniform)
            if parameter is not None:
                value = values.get(parameter, (parameters.get(parameter) or {}).get("value"))
                if value is not None:
                    return value
        return values.get("diffuse")

    def mesh(self, mesh: dict) -> dict:
        prims = []
        for p in mesh.get("primitives", []):
            prim: dict[str, Any] = {"attributes": {_semantic(s): self.index("accessors", a)
                                                   for s, a in (p.get("attributes") or {}).items()},
                                    "mode": int(p.get("mode", 4))}
            if p.get("indices") is not None:
                prim["indices"] = self.index("accessors", p["indices"])
            if p.get("material") is not None:
                prim["material"] = self.index("materials", p["material"])
            prims.append(prim)
        return {"name": mesh.get("name", ""), "primitives": prims}

    def nodes(self) -> list[dict]:
        """The nodes, in order; a node of several meshes gets one child node per mesh, appended."""
        nodes: list[dict] = []
        extra: list[dict] = []
        first_extra = len(self.ids["nodes"])
        for n in _table(self.doc, "nodes").values():
            node: dict[str, Any] = {"name": n.get("name", "")}
            node.update({k: n[k] for k in ("matrix", "translation", "rotation", "scale") if k in n})
            children = [self.index("nodes", c) for c in n.get("children", [])]
            meshes = [self.index("meshes", m) for m in n.get("meshes", [])]
            if len(meshes) == 1:
                node["mesh"] = meshes[0]
            else:
                for m in meshes:
                    children.append(first_extra + len(extra))
                    extra.append({"mesh": m})
            if children:
                node["children"] = children
            nodes.append(node)
        return nodes + extra


def _table(doc: dict, kind: str) -> dict:
    """A 1.0 table of objects by id ({} where absent)."""
    value = doc.get(kind) or {}
    if not isinstance(value, dict):
        raise TypeError(f"{kind} is a {type(value).__name__}, not an object of ids")
    return value


def _semantic(semantic: str) -> str:
    """A 1.0 attribute semantic as 2.0 names it (gltf-pipeline's rules): a set index on
    TEXCOORD/COLOR (and joints, weights), a leading underscore on an application's own."""
    if semantic.startswith("_"):
        return semantic
    base, _, index = semantic.partition("_")
    if base in _INDEXED_SEMANTICS:
        return f"{_INDEXED_SEMANTICS[base]}_{index if index.isdigit() else 0}"
    return semantic if base in _KNOWN_SEMANTICS else f"_{semantic}"
