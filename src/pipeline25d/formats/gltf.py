"""glTF 2.0 / GLB reader producing :class:`~pipeline25d.core.mesh.MeshPart` lists (glTF 1.0 and
its binary container upgraded to 2.0 first: :mod:`.gltf1`).

A small direct reader (numpy views on buffer views) rather than trimesh, because the
3D Tiles content this pipeline meets needs what trimesh ignores: the ``CESIUM_RTC``
centre, ``KHR_draco_mesh_compression`` and float64 placement of ECEF-sized offsets.

What is honoured: the node hierarchy (matrix or TRS; ``EXT_mesh_gpu_instancing`` instances),
the glTF y-up -> 3D Tiles z-up rotation ((x, y, z) -> (x, -z, y), optional), ``CESIUM_RTC``,
Draco (DracoPy), meshopt-compressed buffer views (``EXT_meshopt_compression`` and
``KHR_meshopt_compression``, :mod:`.meshopt`), ``KHR_mesh_quantization`` (normalised/integer
accessors), sparse accessors, base colour textures (GLB buffer views, ``data:`` URIs, files
relative to the glTF; PNG, JPEG, and WEBP by ``EXT_texture_webp`` or KTX2 (Basis Universal) by
``KHR_texture_basisu``, both stored as PNG; a texture's PNG or JPEG fallback is taken over its
KTX2 image), their ``KHR_texture_transform``, base colour factor and ``COLOR_0`` as vertex colours
of untextured parts (the base colour of ``KHR_materials_pbrSpecularGlossiness``: its diffuse).
Triangles come as lists, strips or fans (modes 4, 5, 6); points and lines are skipped with a
warning. An image that cannot be decoded is a missing texture (an error naming it unless the input
says ``missing_textures: untextured``, then its parts are drawn untextured).

One :class:`MeshPart` per primitive instance, its vertices compacted to the ones its
triangles use; its faces' objects are the feature ids (``_BATCHID``, ``EXT_mesh_features``) and
their attributes the ``EXT_structural_metadata`` property table's rows (:mod:`pipeline25d.formats.feature_info`).
UVs are flipped to the GL convention (v = 0 is the bottom image row).
Colours are the 8-bit values of the glTF factors as written (no linear->sRGB step),
which is how generators such as pg2b3dm author them.

Over 400 lines for one job: one format's reader (accessors, node hierarchy, materials and
textures of glTF 2.0).
"""

from __future__ import annotations

import base64
import binascii
import json
import struct
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import unquote

import numpy as np

from pipeline25d.core.errors import InputFileError, MissingTextureWarning, UnsupportedFeatureError
from pipeline25d.core.mesh import MeshPart, repeated
from pipeline25d.formats import gltf1, ktx2, meshopt
from pipeline25d.formats.attributes import Limiter
from pipeline25d.formats.common import Y_UP_TO_Z_UP, image_problem, png_or_jpeg, side_file, texture_file
from pipeline25d.formats.decoded_png import image_as_png
from pipeline25d.formats.feature_info import feature_prefix, feature_properties
from pipeline25d.formats.gltf1 import COMPONENT_DTYPES, TYPE_SIZES
from pipeline25d.formats.gzipped import file_bytes

#: Extensions this reader honours (or may safely ignore) when a file lists them as required.
SUPPORTED_EXTENSIONS = frozenset({
    "CESIUM_RTC",
    "KHR_draco_mesh_compression",
    "KHR_materials_unlit",
    "KHR_materials_pbrSpecularGlossiness",      # its diffuse colour and texture are the base colour's
    "KHR_mesh_quantization",
    "KHR_texture_transform",
    "EXT_mesh_features",
    "EXT_mesh_gpu_instancing",
    "EXT_structural_metadata",
    "EXT_texture_webp",
    "KHR_texture_basisu",           # KTX2 images, decoded by Basis Universal's transcoder (.ktx2)
    *meshopt.EXTENSIONS,
})

#: a glTF's up axis turned to z, as CesiumJS turns a 3D Tiles 1.0 tileset's ``gltfUpAxis``: Y by
#: (x, y, z) -> (x, -z, y), X by a rotation of -90 degrees about y, (x, y, z) -> (-z, y, x)
UP_AXES = {"Y": Y_UP_TO_Z_UP, "Z": np.eye(4),
           "X": np.array([[0, 0, -1, 0], [0, 1, 0, 0], [1, 0, 0, 0], [0, 0, 0, 1]], dtype=np.float64)}

_GLB_MAGIC = b"glTF"
_CHUNK_JSON = 0x4E4F534A
_CHUNK_BIN = 0x004E4942
_TRIANGLES, _STRIP, _FAN = 4, 5, 6


def load_gltf(path: str | Path, y_up_to_z_up: bool = True) -> list[MeshPart]:
    """Read a ``.gltf`` or ``.glb`` file into parts in the model frame (float64).

    ``y_up_to_z_up`` applies the 3D Tiles / GIS rotation after the node hierarchy;
    the ``CESIUM_RTC`` centre (z-up, ECEF) is added after that rotation.
    """
    path = Path(path)
    try:
        data = file_bytes(path)
    except OSError as exc:
        raise InputFileError(path, f"cannot read glTF file: {exc.strerror or exc}") from None
    return parse_gltf_bytes(data, path, "Y" if y_up_to_z_up else "Z")


def parse_gltf_bytes(data: bytes, path: str | Path, up_axis: str = "Y", root: Path | None = None) -> list[MeshPart]:
    """Parts of a GLB or JSON glTF held in ``data``.

    ``path`` names the file in messages and anchors relative URIs (for GLB embedded in
    b3dm/i3dm it is the tile file, as 3D Tiles resolves glTF URIs relative to the tile).
    Buffer and image files must lie inside ``root`` (default: ``path``'s folder; a tileset's
    root folder for its tiles), see :func:`pipeline25d.formats.common.side_file`. ``up_axis``: the
    glTF's up axis, turned to z (:data:`UP_AXES`): "Y" as glTF says, "Z" to keep the axes as stored,
    or a 3D Tiles 1.0 tileset's ``asset.gltfUpAxis``.
    """
    path = Path(path)
    doc = _Document.parse(bytes(data), path, path.parent if root is None else root)
    try:
        return _parts(doc, path, UP_AXES[up_axis])
    except (AttributeError, TypeError) as exc:   # an object where an array belongs, a string for an object ...
        raise InputFileError(path, f"glTF JSON holds a value of the wrong type ({exc})") from None


def _parts(doc: "_Document", path: Path, world: np.ndarray) -> list[MeshPart]:
    """The parts of a parsed glTF document (:func:`parse_gltf_bytes`), turned z-up by ``world``."""
    rtc = doc.json.get("extensions", {}).get("CESIUM_RTC", {}).get("center")
    if rtc is not None:
        world = _translation(np.asarray(rtc, dtype=np.float64)) @ world
    parts: list[MeshPart] = []
    skipped_modes: set[int] = set()
    for mesh_index, node_matrix, node_name, instances in doc.mesh_instances():
        mesh = doc.item("meshes", mesh_index)
        for k, prim in enumerate(mesh.get("primitives", [])):
            mode = int(prim.get("mode", _TRIANGLES))
            if mode not in (_TRIANGLES, _STRIP, _FAN):
                skipped_modes.add(mode)
                continue
            name = mesh.get("name") or node_name or f"mesh{mesh_index}"
            if instances is None:
                part = _primitive_part(doc, prim, world @ node_matrix, f"{name}/{k}")
            else:                          # EXT_mesh_gpu_instancing: each instance's TRS, then the node's
                part = _primitive_part(doc, prim, np.eye(4), f"{name}/{k}")
                part = None if part is None else repeated(part, world @ node_matrix @ instances)
            if part is not None:
                parts.append(part)
    doc.limiter.warn()
    if skipped_modes:
        warnings.warn(f"{path}: skipped primitives with mode {sorted(skipped_modes)} (points and lines: only "
                      "triangles are read)", stacklevel=2)
    return parts


# --------------------------------------------------------------------------- container


@dataclass
class _Document:
    """A parsed glTF: the JSON, the GLB binary chunk and lazily loaded buffers/images."""

    json: dict
    path: Path
    root: Path            # the folder its buffer and image files must lie in
    glb_bin: bytes | None
    _buffers: dict[int, bytes] = field(default_factory=dict)
    _images: dict[int, bytes | None] = field(default_factory=dict)
    _decoded: dict[int, bytes] = field(default_factory=dict)     # meshopt-compressed views, decoded
    limiter: Limiter | None = None           # bounds the features' attributes (formats.attributes)

    @classmethod
    def parse(cls, data: bytes, path: Path, root: Path) -> "_Document":
        """Split GLB chunks or parse JSON glTF; check version and required extensions."""
        if data[:4] == _GLB_MAGIC:
            doc_json, glb_bin = _split_glb(data, path)
        else:
            try:
                doc_json, glb_bin = json.loads(data.decode("utf-8-sig")), None
            except (UnicodeDecodeError, json.JSONDecodeError) as exc:
                raise InputFileError(path, f"neither GLB nor valid glTF JSON ({exc})") from None
        if not isinstance(doc_json, dict):
            raise InputFileError(path, "glTF JSON is not an object")
        if gltf1.is_gltf1(doc_json):
            doc_json = gltf1.upgraded(doc_json, path)
        version = str(doc_json.get("asset", {}).get("version", ""))
        if not version.startswith("2"):
            raise UnsupportedFeatureError(path, f"glTF version {version or '?'} is not supported (1.0 and 2.0 are)")
        unsupported = [e for e in doc_json.get("extensionsRequired", []) if e not in SUPPORTED_EXTENSIONS]
        if unsupported:
            raise UnsupportedFeatureError(path, f"glTF requires unsupported extension(s) {', '.join(unsupported)}")
        return cls(doc_json, path, root, glb_bin, limiter=Limiter(path))

    def item(self, kind: str, index: int) -> dict:
        """``json[kind][index]`` or InputFileError when the reference dangles (a negative index
        included: glTF indices are unsigned, and Python's [-1] would take the last)."""
        try:
            if int(index) < 0:
                raise IndexError(index)
            return self.json[kind][int(index)]
        except (KeyError, IndexError, TypeError, ValueError):
            raise InputFileError(self.path, f"glTF references missing {kind}[{index}]") from None

    def mesh_instances(self):
        """(mesh index, 4x4 world matrix, node name, (k, 4, 4) instance matrices or None) for every
        node with a mesh in the scene; the instances are its ``EXT_mesh_gpu_instancing``
        (:meth:`node_instances`)."""
        scenes = self.json.get("scenes")
        if scenes:
            roots = self.item("scenes", self.json.get("scene", 0)).get("nodes", [])
        else:
            nodes = self.json.get("nodes", [])
            children = {c for n in nodes for c in n.get("children", [])}
            roots = [i for i in range(len(nodes)) if i not in children]
        stack = [(int(i), np.eye(4), 0) for i in reversed(roots)]
        while stack:
            index, parent, depth = stack.pop()
            if depth > 256:
                raise InputFileError(self.path, "glTF node hierarchy is cyclic or too deep")
            node = self.item("nodes", index)
            matrix = parent @ _node_matrix(node)
            if "mesh" in node:
                yield int(node["mesh"]), matrix, node.get("name", ""), self.node_instances(node)
            stack.extend((int(c), matrix, depth + 1) for c in reversed(node.get("children", [])))

    def node_instances(self, node: dict) -> np.ndarray | None:
        """(k, 4, 4) T * R * S of each instance a node's ``EXT_mesh_gpu_instancing`` gives (its
        TRANSLATION, ROTATION (x, y, z, w; normalised integers too) and SCALE accessors, each
        optional), in the node's frame; None without the extension."""
        attributes = node.get("extensions", {}).get("EXT_mesh_gpu_instancing", {}).get("attributes")
        if attributes is None:
            return None
        arrays = {name: _as_float(self.accessor(int(i)), self.item("accessors", int(i)))
                  for name, i in attributes.items() if name in ("TRANSLATION", "ROTATION", "SCALE")}
        counts = {len(a) for a in arrays.values()}
        if len(counts) > 1:
            raise InputFileError(self.path, f"EXT_mesh_gpu_instancing accessors of unequal counts {sorted(counts)}")
        k = counts.pop() if counts else 0
        m = np.tile(np.eye(4), (k, 1, 1))
        if "SCALE" in arrays:
            m[:, :3, :3] *= arrays["SCALE"][:, None, :3]
        if "ROTATION" in arrays:
            m[:, :3, :3] = _quaternion_matrices(arrays["ROTATION"][:, :4]) @ m[:, :3, :3]
        if "TRANSLATION" in arrays:
            m[:, :3, 3] = arrays["TRANSLATION"][:, :3]
        return m

    def buffer(self, index: int) -> bytes:
        """Bytes of buffer ``index``: the GLB chunk, a data: URI or a file next to the glTF."""
        if index not in self._buffers:
            buf = self.item("buffers", index)
            uri = buf.get("uri")
            if uri is None:
                if meshopt.is_fallback(buf):
                    raise InputFileError(self.path, f"buffer {index} is a meshopt fallback without data, "
                                                    "read by a view that is not compressed")
                if self.glb_bin is None:
                    raise InputFileError(self.path, f"buffer {index} has no uri and there is no GLB binary chunk")
                data = self.glb_bin
            else:
                data = self._uri_bytes(uri, f"buffer {index}")
                if data is None:
                    raise InputFileError(self.path, f"buffer file {unquote(uri)!r} is missing")
            if len(data) < int(buf.get("byteLength", 0)):
                raise InputFileError(self.path, f"buffer {index} holds {len(data)} bytes, "
                                                f"byteLength says {buf.get('byteLength')} (truncated?)")
            self._buffers[index] = data
        return self._buffers[index]

    def view(self, index: int) -> tuple[bytes, int, int, int | None]:
        """(buffer bytes, start offset, length, byteStride) of buffer view ``index``."""
        view = self.item("bufferViews", index)
        compression = meshopt.compression_of(view)
        if compression is not None:
            data = self._decompressed(index, view, *compression)
            return data, 0, len(data), view.get("byteStride")
        data = self.buffer(int(view.get("buffer", 0)))
        start, length = int(view.get("byteOffset", 0)), int(view["byteLength"])
        if start + length > len(data):
            raise InputFileError(self.path, f"bufferView {index} reads past the end of its buffer")
        return data, start, length, view.get("byteStride")

    def _decompressed(self, index: int, view: dict, name: str, ext: dict) -> bytes:
        """Buffer view ``index``'s bytes from its meshopt stream (:mod:`.meshopt`), decoded once."""
        if index not in self._decoded:
            data = self.buffer(int(ext.get("buffer", 0)))
            start, length = int(ext.get("byteOffset", 0)), int(ext.get("byteLength", 0))
            if start < 0 or length <= 0 or start + length > len(data):
                raise InputFileError(self.path, f"bufferView {index}'s {name} stream lies outside its buffer")
            self._decoded[index] = meshopt.decode_view(self.path, index, view, name, ext, data[start:start + length])
        return self._decoded[index]

    def view_bytes(self, index: int) -> bytes:
        data, start, length, _ = self.view(index)
        return data[start:start + length]

    def accessor(self, index: int) -> np.ndarray:
        """(count, components) array of accessor ``index`` in its stored dtype (sparse applied)."""
        acc = self.item("accessors", index)
        dtype = np.dtype(COMPONENT_DTYPES.get(acc.get("componentType"), np.float32)).newbyteorder("<")
        n = TYPE_SIZES.get(acc.get("type"), 1)
        count = int(acc["count"])
        if "bufferView" in acc:
            data, start, length, stride = self.view(int(acc["bufferView"]))
            offset = start + int(acc.get("byteOffset", 0))
            stride = int(stride or dtype.itemsize * n)
            needed = (count - 1) * stride + dtype.itemsize * n if count else 0
            if offset + needed > start + length:
                raise InputFileError(self.path, f"accessor {index} reads past the end of its bufferView")
            out = np.ndarray((count, n), dtype, buffer=data, offset=offset,
                             strides=(stride, dtype.itemsize)).copy()
        else:
            out = np.zeros((count, n), dtype)
        sparse = acc.get("sparse")
        if sparse:
            out = self._apply_sparse(out, sparse, dtype, n)
        return out

    def _apply_sparse(self, out: np.ndarray, sparse: dict, dtype: np.dtype, n: int) -> np.ndarray:
        """Overwrite the sparse-listed elements of ``out``."""
        k = int(sparse["count"])
        ind, val = sparse["indices"], sparse["values"]
        ind_dtype = np.dtype(COMPONENT_DTYPES[ind["componentType"]]).newbyteorder("<")
        data, start, _, _ = self.view(int(ind["bufferView"]))
        idx = np.frombuffer(data, ind_dtype, k, start + int(ind.get("byteOffset", 0))).astype(np.int64)
        data, start, _, _ = self.view(int(val["bufferView"]))
        values = np.frombuffer(data, dtype, k * n, start + int(val.get("byteOffset", 0))).reshape(k, n)
        if len(idx) and (idx.max() >= len(out) or idx.min() < 0):
            raise InputFileError(self.path, "sparse accessor index out of range")
        out[idx] = values
        return out

    def image(self, index: int) -> bytes | None:
        """Encoded PNG/JPEG bytes of image ``index``, or None (with a warning) when unusable."""
        if index not in self._images:
            img = self.item("images", index)
            if "bufferView" in img:
                data: bytes | None = self.view_bytes(int(img["bufferView"]))
            else:
                uri = img.get("uri", "")
                if uri.startswith("data:"):
                    data, problem = self._uri_bytes(uri, f"image {index}"), None
                else:
                    target, problem = texture_file(uri, self.path.parent, self.root, self.path, f"image {index}")
                    data = None if target is None else self._side_bytes(target, f"image {index}")
                if data is None:
                    said = f"image {index} {uri!r} {problem}" if problem else f"image {unquote(uri)!r} is missing"
                    warnings.warn(f"{self.path}: {said}; its parts are drawn untextured", MissingTextureWarning,
                                  stacklevel=4)
            if data is not None and data[:4] == b"RIFF" and data[8:12] == b"WEBP":
                data = _webp_as_png(data, self.path, index)
            elif data is not None and ktx2.is_ktx2(data):
                data = _ktx2_as_png(data, self.path, index)
            if data is not None and not png_or_jpeg(data):
                warnings.warn(f"{self.path}: image {index} is neither PNG nor JPEG (not an image); "
                              "its parts are drawn untextured", MissingTextureWarning, stacklevel=4)
                data = None
            elif data is not None and (problem := image_problem(data)) is not None:
                warnings.warn(f"{self.path}: image {index} {problem}; its parts are drawn untextured",
                              MissingTextureWarning, stacklevel=4)
                data = None
            self._images[index] = data
        return self._images[index]

    def _uri_bytes(self, uri: str, what: str) -> bytes | None:
        """Bytes of a data: URI or a file inside the dataset's root; None when the file does not exist."""
        if uri.startswith("data:"):
            try:
                return base64.b64decode(uri.split(",", 1)[1], validate=False)
            except (IndexError, binascii.Error):
                raise InputFileError(self.path, f"{what}: malformed data URI") from None
        return self._side_bytes(side_file(uri, self.path.parent, self.root, self.path, what), what)

    @staticmethod
    def _side_bytes(target: Path, what: str) -> bytes | None:
        """Bytes of a side file found by :func:`~pipeline25d.formats.common.side_file`; None when it does not exist."""
        try:
            return file_bytes(target)
        except FileNotFoundError:
            return None
        except OSError as exc:
            raise InputFileError(target, f"cannot read {what}: {exc.strerror or exc}") from None


def _webp_as_png(data: bytes, path: Path, index: int) -> bytes | None:
    """A WEBP image (``EXT_texture_webp``) as PNG bytes, which the chunks and the render job take;
    None with a warning when it cannot be decoded."""
    png, problem = image_as_png(data)
    if png is None:
        warnings.warn(f"{path}: image {index} cannot be read (WEBP: {problem}); its parts are drawn untextured",
                      MissingTextureWarning, stacklevel=5)
    return png


def _ktx2_as_png(data: bytes, path: Path, index: int) -> bytes | None:
    """A KTX2 image (``KHR_texture_basisu``) as PNG bytes; None with a warning when it cannot be decoded."""
    try:
        return ktx2.ktx2_as_png(data)
    except ktx2.Ktx2Error as exc:
        warnings.warn(f"{path}: image {index} cannot be read (KTX2: {exc}); its parts are drawn untextured",
                      MissingTextureWarning, stacklevel=5)
        return None


def _split_glb(data: bytes, path: Path) -> tuple[dict, bytes | None]:
    """JSON and BIN chunks of a GLB container, checking the header and chunk lengths (a binary glTF
    1.0: its JSON, as written, and its body)."""
    if len(data) < 20:
        raise InputFileError(path, "GLB is truncated (shorter than its header)")
    _, version, length = struct.unpack_from("<4sII", data, 0)
    if version == 1:
        return gltf1.split_glb1(data, path)
    if version != 2:
        raise UnsupportedFeatureError(path, f"GLB version {version} is not supported (1 and 2 are)")
    if length > len(data):
        raise InputFileError(path, f"GLB header says {length} bytes but only {len(data)} are present (truncated)")
    doc_json, glb_bin, pos = None, None, 12
    while pos + 8 <= length:
        chunk_len, chunk_type = struct.unpack_from("<II", data, pos)
        chunk = data[pos + 8:pos + 8 + chunk_len]
        if len(chunk) < chunk_len:
            raise InputFileError(path, "GLB chunk runs past the end of the file (truncated)")
        if chunk_type == _CHUNK_JSON and doc_json is None:
            try:
                doc_json = json.loads(chunk.decode("utf-8"))
            except (UnicodeDecodeError, json.JSONDecodeError) as exc:
                raise InputFileError(path, f"GLB JSON chunk is invalid: {exc}") from None
        elif chunk_type == _CHUNK_BIN and glb_bin is None:
            glb_bin = chunk
        pos += 8 + chunk_len
    if doc_json is None:
        raise InputFileError(path, "GLB has no JSON chunk")
    return doc_json, glb_bin


# --------------------------------------------------------------------------- geometry


def _node_matrix(node: dict) -> np.ndarray:
    """Local 4x4 matrix of a node: ``matrix`` (column-major) or T * R * S."""
    if "matrix" in node:
        return np.asarray(node["matrix"], dtype=np.float64).reshape(4, 4).T
    m = np.eye(4)
    if "scale" in node:
        m = np.diag([*map(float, node["scale"]), 1.0]) @ m
    if "rotation" in node:
        r = np.eye(4)
        r[:3, :3] = _quaternion_matrices(np.asarray(node["rotation"], dtype=np.float64)[None])[0]
        m = r @ m
    if "translation" in node:
        m = _translation(np.asarray(node["translation"], dtype=np.float64)) @ m
    return m


def _quaternion_matrices(q: np.ndarray) -> np.ndarray:
    """(k, 3, 3) rotations of (k, 4) quaternions stored (x, y, z, w) as glTF does (normalised first)."""
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    x, y, z, w = (q / np.where(norm > 0, norm, 1.0)).T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], axis=-1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], axis=-1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], axis=-1),
    ], axis=1)


def _translation(t: np.ndarray) -> np.ndarray:
    m = np.eye(4)
    m[:3, 3] = t
    return m


def _as_float(values: np.ndarray, accessor: dict) -> np.ndarray:
    """float64 copy of accessor data, undoing ``normalized`` integer encodings and glTF 1.0's
    ``WEB3D_quantized_attributes`` (its ``decodeMatrix``, column-major, on (value, 1))."""
    out = values.astype(np.float64)
    quantized = (accessor.get("extensions") or {}).get("WEB3D_quantized_attributes")
    if quantized is not None:
        n = out.shape[1]
        decode = np.asarray(quantized["decodeMatrix"], dtype=np.float64).reshape(n + 1, n + 1).T
        return out @ decode[:n, :n].T + decode[:n, n]
    if accessor.get("normalized") and values.dtype.kind in "iu":
        out /= float(np.iinfo(values.dtype).max)
        if values.dtype.kind == "i":
            np.maximum(out, -1.0, out=out)
    return out


def _primitive_attributes(doc: _Document, prim: dict) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Attribute arrays (float64, by glTF name) and (m, 3) int64 faces of a primitive."""
    draco = prim.get("extensions", {}).get("KHR_draco_mesh_compression")
    if draco is not None:
        return _draco_attributes(doc, prim, draco)
    feature = _feature_attribute(prim)
    attrs = {name: _as_float(doc.accessor(i), doc.item("accessors", i))
             for name, i in prim.get("attributes", {}).items()
             if name in ("POSITION", "COLOR_0") or name.startswith("TEXCOORD_")}
    if feature is not None and feature in prim.get("attributes", {}):
        attrs[FEATURE] = doc.accessor(prim["attributes"][feature]).reshape(-1).astype(np.float64)
    if "POSITION" not in attrs:
        raise InputFileError(doc.path, "primitive without POSITION attribute")
    if "indices" in prim:
        indices = doc.accessor(int(prim["indices"])).reshape(-1).astype(np.int64)
    else:
        indices = np.arange(len(attrs["POSITION"]), dtype=np.int64)
    return attrs, triangles(indices, int(prim.get("mode", _TRIANGLES)))


def triangles(indices: np.ndarray, mode: int) -> np.ndarray:
    """(m, 3) triangles of a primitive's vertex indices as glTF 2.0 (3.7.2.1) defines them for
    its mode: a list (4; a trailing partial triangle dropped), a strip (5: triangle i is
    v[i], v[i + 1 + i % 2], v[i + 2 - i % 2], so every other one keeps its winding) or a fan
    (6: v[i + 1], v[i + 2], v[0])."""
    if mode == _STRIP:
        i = np.arange(max(len(indices) - 2, 0))
        return np.column_stack([indices[i], indices[i + 1 + i % 2], indices[i + 2 - i % 2]])
    if mode == _FAN:
        i = np.arange(max(len(indices) - 2, 0))
        return np.column_stack([indices[i + 1], indices[i + 2], np.full(len(i), indices[0] if len(i) else 0)])
    return indices[: len(indices) - len(indices) % 3].reshape(-1, 3)


def _draco_attributes(doc: _Document, prim: dict, draco: dict) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Decode a KHR_draco_mesh_compression primitive with DracoPy."""
    import DracoPy

    stream = doc.view_bytes(int(draco["bufferView"]))      # its own errors name the file and the buffer
    try:
        mesh = DracoPy.decode(stream)
    except Exception as exc:  # DracoPy raises its own and ValueError types
        raise InputFileError(doc.path, f"Draco decoding failed: {exc}") from None
    attrs = {}
    feature = _feature_attribute(prim)
    for name, uid in draco.get("attributes", {}).items():
        if not (name in ("POSITION", "COLOR_0", feature) or name.startswith("TEXCOORD_")):
            continue
        attr = mesh.get_attribute_by_unique_id(int(uid))
        if attr is None:
            raise InputFileError(doc.path, f"Draco stream lacks attribute {name} (id {uid})")
        acc = doc.item("accessors", prim["attributes"][name]) if name in prim.get("attributes", {}) else {}
        data = np.asarray(attr["data"])
        if name == feature:
            attrs[FEATURE] = data.reshape(-1).astype(np.float64)
            continue
        stored = COMPONENT_DTYPES.get(acc.get("componentType"))
        if acc.get("normalized") and stored is not None and np.dtype(stored).kind in "iu":
            # DracoPy hands a quantized attribute's integers over as floats: back to the accessor's
            # type, so that _as_float undoes the normalisation (KHR_mesh_quantization under Draco)
            data = np.rint(data).astype(stored)
        attrs[name] = _as_float(data.reshape(len(data), -1), acc)
    if "POSITION" not in attrs:
        raise InputFileError(doc.path, "Draco primitive without POSITION attribute")
    return attrs, np.asarray(mesh.faces, dtype=np.int64).reshape(-1, 3)


def _primitive_part(doc: _Document, prim: dict, matrix: np.ndarray, name: str) -> MeshPart | None:
    """One triangle primitive placed by ``matrix``, with texture or vertex colours."""
    attrs, faces = _primitive_attributes(doc, prim)
    positions = attrs["POSITION"][:, :3]
    if len(faces) == 0:
        return None
    if faces.min() < 0 or faces.max() >= len(positions):
        raise InputFileError(doc.path, f"primitive {name}: index {faces.max()} out of range "
                                       f"({len(positions)} vertices)")
    objects, face_objects = _face_features(doc, attrs.get(FEATURE), faces)
    info = feature_properties(doc.json, prim, objects, doc.view_bytes, doc.limiter)
    used, faces = np.unique(faces, return_inverse=True)
    faces = faces.reshape(-1, 3)
    if np.linalg.det(matrix[:3, :3]) < 0:  # mirroring transform: keep front faces front
        faces = faces[:, [0, 2, 1]]
    vertices = positions[used] @ matrix[:3, :3].T + matrix[:3, 3]
    material = doc.item("materials", prim["material"]) if "material" in prim else {}
    pbr = base_colour(material)
    texture, uv = _base_color_texture(doc, pbr, attrs)
    colors = None
    if texture is None:
        colors = _vertex_colors(pbr, attrs.get("COLOR_0"), len(positions))[used]
    else:
        uv = uv[used]
    return MeshPart(vertices, faces, colors=colors, uv=uv, texture=texture,
                    name=material.get("name") or name, objects=objects, face_objects=face_objects,
                    object_info=info)


#: the attrs key of a primitive's per-vertex feature ids (3D Tiles batch ids, EXT_mesh_features)
FEATURE = "FEATURE_ID"


def _feature_attribute(prim: dict) -> str | None:
    """The primitive's feature-id attribute: EXT_mesh_features' first featureIds entry given by
    attribute (``_FEATURE_ID_n``), else a b3dm's ``_BATCHID``; None when it has none."""
    ids = prim.get("extensions", {}).get("EXT_mesh_features", {}).get("featureIds") or []
    if ids and isinstance(ids[0], dict) and "attribute" in ids[0]:
        return f"_FEATURE_ID_{int(ids[0]['attribute'])}"
    attributes = prim.get("attributes", {})
    return "_BATCHID" if "_BATCHID" in attributes else ("BATCHID" if "BATCHID" in attributes else None)


def _face_features(doc: _Document, feature: np.ndarray | None,
                   faces: np.ndarray) -> tuple[tuple[str, ...], np.ndarray | None]:
    """(objects, face objects) of a primitive's faces from their first vertex's feature id: objects
    named ``<file>#<feature id>`` (the file relative to the dataset's root); (), None without ids."""
    if feature is None:
        return (), None
    values = np.rint(feature[faces[:, 0]]).astype(np.int64)
    held, face_objects = np.unique(values, return_inverse=True)
    name = feature_prefix(doc.path, doc.root)
    return tuple(f"{name}#{v}" for v in held), face_objects


def base_colour(material: dict) -> dict:
    """The material's base colour as ``pbrMetallicRoughness`` gives it (``baseColorFactor``,
    ``baseColorTexture``): from ``KHR_materials_pbrSpecularGlossiness``' diffuse factor and texture
    where the material has that extension (obj2gltf's ``--specularGlossiness``, older exporters; a
    reader that knows the extension takes it over the metallic-roughness fallback), the diffuse
    colour of a surface being its base colour; else the material's own."""
    gloss = (material.get("extensions") or {}).get("KHR_materials_pbrSpecularGlossiness")
    if not isinstance(gloss, dict):
        return material.get("pbrMetallicRoughness", {})
    return {k: gloss[g] for k, g in (("baseColorFactor", "diffuseFactor"), ("baseColorTexture", "diffuseTexture"))
            if g in gloss}


def _base_color_texture(doc: _Document, pbr: dict, attrs: dict) -> tuple[bytes | None, np.ndarray | None]:
    """(image bytes, GL-convention UVs) of the base colour texture, or (None, None)."""
    info = pbr.get("baseColorTexture")
    if info is None:
        return None, None
    transform = info.get("extensions", {}).get("KHR_texture_transform")
    uv = attrs.get(f"TEXCOORD_{int((transform or {}).get('texCoord', info.get('texCoord', 0)))}")
    texture = doc.item("textures", info["index"])
    extensions = texture.get("extensions", {})
    source = extensions.get("EXT_texture_webp", {}).get("source", texture.get("source"))
    if source is None:
        source = extensions.get("KHR_texture_basisu", {}).get("source")
    if uv is None or source is None:
        return None, None
    image = doc.image(int(source))
    if image is None:
        return None, None
    if transform is not None:
        uv = texture_transform(uv, transform)
    return image, np.column_stack([uv[:, 0], 1.0 - uv[:, 1]])


def texture_transform(uv: np.ndarray, transform: dict) -> np.ndarray:
    """``KHR_texture_transform`` applied to (n, 2) glTF UVs: scaled, rotated by ``rotation`` radians
    (u' = cos·u + sin·v, v' = -sin·u + cos·v: the extension's example, whose offset [0, 1], rotation
    pi/2 and scale 0.5 take the unit square to the image's lower-left quadrant), then offset."""
    sx, sy = (float(v) for v in transform.get("scale", (1.0, 1.0)))
    ox, oy = (float(v) for v in transform.get("offset", (0.0, 0.0)))
    r = float(transform.get("rotation", 0.0))
    u, v = uv[:, 0] * sx, uv[:, 1] * sy
    return np.column_stack([np.cos(r) * u + np.sin(r) * v + ox, -np.sin(r) * u + np.cos(r) * v + oy])


def _vertex_colors(pbr: dict, color0: np.ndarray | None, n: int) -> np.ndarray:
    """(n, 4) uint8 RGBA: COLOR_0 (if any) times baseColorFactor."""
    factor = np.asarray(pbr.get("baseColorFactor", [1.0, 1.0, 1.0, 1.0]), dtype=np.float64)
    rgba = np.ones((n, 4))
    if color0 is not None:
        rgba[:, : min(4, color0.shape[1])] = color0[:, :4]
    return np.rint(np.clip(rgba * factor, 0.0, 1.0) * 255.0).astype(np.uint8)
