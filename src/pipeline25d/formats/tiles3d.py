"""3D Tiles 1.0 / 1.1 reader: tileset traversal, LOD selection, b3dm/i3dm/cmpt/glb/gltf content.

Placement follows the 3D Tiles spec (and CesiumJS): glTF node hierarchy, glTF y-up ->
z-up ((x, y, z) -> (x, -z, y), unless ``asset.gltfUpAxis`` is "Z"), then the content's
RTC_CENTER / CESIUM_RTC, then the tile transforms multiplied root-to-leaf. External
tilesets (a tile whose content is a ``.json``) inherit the referencing tile's transform
and refine mode and resolve their URIs relative to their own JSON file. Implicit tiling
(3D Tiles 1.1 ``implicitTiling``, quadtree or octree, binary or JSON subtrees) is
expanded lazily into the same tile tree. The tree is walked with an explicit stack, so its
depth is bounded by nothing but the JSON reader (Python's ``json`` refuses about 1000 nested
objects and arrays, about 490 levels of ``children`` in one file: an InputFileError naming the
file); external tilesets that lead back to one already entered are refused as a cycle.

Every file a tileset names (contents, external tilesets, subtrees and their buffers, glTF
buffers and images, i3dm glTF URIs) must lie inside the root tileset.json's folder
(:func:`~pipeline25d.formats.common.side_file`): ``../`` to a sibling inside it is fine.

Bounding volumes are never used: the selection here depends on geometric errors only,
and geometry is never clipped to a bounding volume (real tilesets, e.g. pg2b3dm's
Amsterdam sample, have boxes that are too small on one side).

Vertices stay float64 from the decoded glTF to the scene CRS; ECEF (``src_crs``) is
reprojected once per tileset with :func:`pipeline25d.core.crs.transform_points` after an
area-of-use check of the scene CRS.

Over 400 lines for one job: one format's reader (tileset traversal, LOD choice and four
content types share the tile transform chain).
"""

from __future__ import annotations

import json
import struct
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from pipeline25d.core.errors import InputFileError, UnsupportedFeatureError
from pipeline25d.core.mesh import Mesh, MeshPart
from pipeline25d.formats.common import Detail, Loaded, in_scene, read_text, side_file
from pipeline25d.formats.gltf import parse_gltf_bytes

_B3DM_HEADER = 28
_I3DM_HEADER = 32
ECEF = "EPSG:4978"         # the CRS of 3D Tiles coordinates
_LEGACY_LIMIT = 570425344  # CesiumJS: a "length" this large is really the start of a glTF header


# --------------------------------------------------------------------------- public API


def read_tileset(path: Path, spec: dict, detail: Detail = Detail()) -> Loaded:
    """Reader contract (:mod:`pipeline25d.formats`): all content a renderer would draw for
    ``tileset.json`` at ``path``, in the tileset's CRS (``spec["crs"]``, else ECEF).

    ``detail.max_error=g`` refines each tile until its geometricError <= g or it is a
    leaf; REPLACE tiles that are refined are not drawn, ADD tiles are drawn as well as
    their descendants. ``None`` is full detail (every leaf plus ADD ancestors).
    Content tileset JSONs (external tilesets) are always entered, as CesiumJS does.
    """
    path = Path(path)
    root_json = _read_json(path)
    up_axis = str(root_json.get("asset", {}).get("gltfUpAxis", "Y")).upper()
    folder = path.parent
    root = _json_tile(_root_of(root_json, path), path, np.eye(4), "REPLACE", folder)
    parts: list[MeshPart] = []
    for content_path, transform in _select(root, detail.max_error, path, folder):
        parts.extend(_place(read_content(content_path, y_up=(up_axis != "Z"), root=folder), transform))
    if not parts:
        warnings.warn(f"{path}: the selected tiles hold no triangles", stacklevel=2)
    return Loaded(_merge_untextured(parts), spec.get("crs") or ECEF)


def read_b3dm(path: Path, spec: dict, detail: Detail = Detail()) -> Loaded:
    """Reader contract: a single b3dm (or other tile content) file, without a tileset."""
    return Loaded(_merge_untextured(read_content(Path(path))), spec.get("crs") or ECEF)


def load_tileset(path: str | Path, scene_crs: str, max_geometric_error: float | None = None,
                 src_crs: str = ECEF) -> Mesh:
    """:func:`read_tileset` in ``scene_crs``."""
    return in_scene(read_tileset(Path(path), {"crs": src_crs}, Detail(max_geometric_error)), scene_crs, path)


def load_b3dm(path: str | Path, scene_crs: str, src_crs: str = ECEF) -> Mesh:
    """:func:`read_b3dm` in ``scene_crs``."""
    return in_scene(read_b3dm(Path(path), {"crs": src_crs}), scene_crs, path)


def read_content(path: Path, y_up: bool = True, root: Path | None = None) -> list[MeshPart]:
    """Parts of one content file (b3dm, i3dm, cmpt, glb, gltf) in the tile's frame; the files it
    names must lie in ``root`` (default: its folder).

    Point clouds (pnts) and unknown formats are skipped with a warning.
    """
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise InputFileError(path, "tile content file is missing") from None
    except OSError as exc:
        raise InputFileError(path, f"cannot read tile content: {exc.strerror or exc}") from None
    return _parse_content(data, path, y_up, path.parent if root is None else root)


# --------------------------------------------------------------------------- tile tree


@dataclass
class _Tile:
    """A tile of the (explicit or implicit) tree with its composed world transform."""

    geometric_error: float
    refine: str
    transform: np.ndarray
    contents: list[Path]
    externals: list[Path]
    children: Callable[[], list["_Tile"]] = field(default=lambda: [])
    has_children: bool = False


@dataclass
class _External:
    """An external tileset to enter (``tile`` names it), or with ``leave`` the end of one."""

    path: Path
    tile: _Tile | None = None
    leave: bool = False


def _select(root: _Tile, g: float | None, root_path: Path, folder: Path) -> list[tuple[Path, np.ndarray]]:
    """(content path, transform) of the tiles drawn at geometric error ``g``, depth first in
    file order, with an explicit stack (no recursion however deep the tree)."""
    out: list[tuple[Path, np.ndarray]] = []
    chain = {root_path.resolve(): root_path}   # the external tilesets being walked, outermost first
    stack: list[_Tile | _External] = [root]
    while stack:
        item = stack.pop()
        if isinstance(item, _External):
            if item.leave:
                chain.popitem()
            else:
                stack += _enter(item, chain, folder)
            continue
        tile = item
        refine = tile.has_children and (g is None or tile.geometric_error > g)
        if not refine or tile.refine == "ADD":
            out.extend((c, tile.transform) for c in tile.contents)
        stack += [_External(ext, tile) for ext in reversed(tile.externals)]
        if refine:
            stack += reversed(tile.children())
    return out


def _enter(ext: _External, chain: dict[Path, Path], folder: Path) -> list[_Tile | _External]:
    """What the stack gets to walk the external tileset ``ext``: its root, then its end marker."""
    key = ext.path.resolve()
    if key in chain:
        names = list(chain.values())
        loop = [p.name for p in names[list(chain).index(key):]] + [ext.path.name]
        raise InputFileError(ext.path, f"external tilesets form a cycle ({' -> '.join(loop)})")
    chain[key] = ext.path
    ext_json = _read_json(ext.path)
    root = _json_tile(_root_of(ext_json, ext.path), ext.path, ext.tile.transform, ext.tile.refine, folder)
    return [_External(ext.path, leave=True), root]


def _json_tile(tile: dict, json_path: Path, parent_transform: np.ndarray, parent_refine: str,
               folder: Path) -> _Tile:
    """A :class:`_Tile` from a tileset JSON tile object (children built on demand)."""
    transform = parent_transform @ _matrix(tile.get("transform"), json_path)
    refine = str(tile.get("refine", parent_refine)).upper()
    if "implicitTiling" in tile:
        return _implicit_root(tile, json_path, transform, refine, folder)
    uris = [c["uri"] if "uri" in c else c.get("url") for c in _content_list(tile)]
    contents, externals = _split_contents([_resolve(u, json_path, folder) for u in uris], json_path)
    kids = tile.get("children") or []
    return _Tile(
        geometric_error=float(tile.get("geometricError", 0.0)),
        refine=refine,
        transform=transform,
        contents=contents,
        externals=externals,
        children=lambda: [_json_tile(c, json_path, transform, refine, folder) for c in kids],
        has_children=bool(kids),
    )


def _split_contents(paths: list[Path], referrer: Path) -> tuple[list[Path], list[Path]]:
    """(renderable contents, external tileset JSONs); InputFileError naming a missing file."""
    for target in paths:
        if not target.is_file():
            raise InputFileError(target, f"content referenced by {referrer} is missing")
    return ([p for p in paths if p.suffix.lower() != ".json"],
            [p for p in paths if p.suffix.lower() == ".json"])


def _content_list(tile: dict) -> list[dict]:
    """The tile's content objects (1.0 ``content``, 1.1 ``contents``)."""
    contents = list(tile.get("contents") or [])
    if tile.get("content"):
        contents.insert(0, tile["content"])
    return contents


def _root_of(tileset: dict, path: Path) -> dict:
    root = tileset.get("root")
    if not isinstance(root, dict):
        raise InputFileError(path, "tileset JSON has no root tile")
    return root


def _matrix(values: list | None, where: Path) -> np.ndarray:
    """4x4 float64 matrix from a column-major 16-number list (identity when absent)."""
    if values is None:
        return np.eye(4)
    try:
        return np.asarray(values, dtype=np.float64).reshape(4, 4).T
    except ValueError:
        raise InputFileError(where, f"tile transform is not 16 numbers: {values!r}") from None


def _resolve(uri: str | None, base: Path, folder: Path) -> Path:
    """Local path of a content/subtree URI relative to the JSON (or subtree) that names it,
    inside the tileset's root ``folder``."""
    if not uri:
        raise InputFileError(base, "tile content without uri")
    return side_file(uri, base.parent, folder, base, "content")


def _read_json(path: Path) -> dict:
    """Parsed tileset JSON; InputFileError when missing, invalid or nested too deep to parse."""
    text = read_text(path, "tileset JSON")
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputFileError(path, f"invalid JSON: {exc}") from None
    except RecursionError:
        raise InputFileError(path, "JSON nested deeper than the JSON reader allows (about 1000 objects and "
                                   "arrays; a tile tree that deep belongs in external tilesets)") from None
    if not isinstance(data, dict):
        raise InputFileError(path, "tileset JSON is not an object")
    return data


# --------------------------------------------------------------------------- implicit tiling


@dataclass
class _Subtree:
    """Availability bitstreams of one implicit-tiling subtree."""

    tiles: np.ndarray
    contents: list[np.ndarray]
    child_subtrees: np.ndarray


@dataclass
class _Implicit:
    """Shared state of an implicit tileset: templates, scheme, subtree cache."""

    json_path: Path
    branching: int
    subtree_levels: int
    available_levels: int
    subtree_uri: str
    content_uris: list[str]
    root_error: float
    refine: str
    transform: np.ndarray
    folder: Path              # the tileset's root folder (every file named must lie in it)
    cache: dict = field(default_factory=dict)

    def uri(self, template: str, level: int, xyz: tuple[int, int, int]) -> Path:
        text = (template.replace("{level}", str(level)).replace("{x}", str(xyz[0]))
                .replace("{y}", str(xyz[1])).replace("{z}", str(xyz[2])))
        return _resolve(text, self.json_path, self.folder)

    def subtree(self, level: int, xyz: tuple[int, int, int]) -> _Subtree:
        key = (level, xyz)
        if key not in self.cache:
            self.cache[key] = _read_subtree(self.uri(self.subtree_uri, level, xyz), self)
        return self.cache[key]


def _implicit_root(tile: dict, json_path: Path, transform: np.ndarray, refine: str, folder: Path) -> _Tile:
    """Root :class:`_Tile` of an implicit tileset (3D Tiles 1.1 ``implicitTiling``)."""
    spec = tile["implicitTiling"]
    scheme = str(spec.get("subdivisionScheme", "")).upper()
    if scheme not in ("QUADTREE", "OCTREE"):
        raise UnsupportedFeatureError(json_path, f"implicit subdivisionScheme {scheme!r} is not supported")
    try:
        levels = int(spec["availableLevels"]) if "availableLevels" in spec else int(spec["maximumLevel"]) + 1
        ctx = _Implicit(json_path, 4 if scheme == "QUADTREE" else 8, int(spec["subtreeLevels"]), levels,
                        spec["subtrees"]["uri"], [c["uri"] for c in _content_list(tile)],
                        float(tile.get("geometricError", 0.0)), refine, transform, folder)
    except (KeyError, TypeError, ValueError) as exc:
        raise InputFileError(json_path, f"incomplete implicitTiling object: {exc}") from None
    return _implicit_tile(ctx, ctx.subtree(0, (0, 0, 0)), 0, 0, 0, (0, 0, 0))


def _implicit_tile(ctx: _Implicit, sub: _Subtree, sub_level: int, local_level: int, morton: int,
                   xyz: tuple[int, int, int]) -> _Tile:
    """The available tile at local (level, morton) of subtree ``sub`` rooted at ``sub_level``."""
    level = sub_level + local_level
    bit = _level_offset(ctx.branching, local_level) + morton
    contents, externals = _split_contents(
        [ctx.uri(t, level, xyz) for t, avail in zip(ctx.content_uris, sub.contents) if _bit(avail, bit)],
        ctx.json_path)

    available = []  # (morton, xyz, inside this subtree) of each available child
    if level + 1 < ctx.available_levels:
        for c in range(ctx.branching):
            child_xyz = tuple(2 * v + ((c >> i) & 1) for i, v in enumerate(xyz))
            child_morton = morton * ctx.branching + c
            if local_level + 1 < ctx.subtree_levels:
                if _bit(sub.tiles, _level_offset(ctx.branching, local_level + 1) + child_morton):
                    available.append((child_morton, child_xyz, True))
            elif _bit(sub.child_subtrees, child_morton):
                available.append((child_morton, child_xyz, False))

    def children() -> list[_Tile]:
        return [_implicit_tile(ctx, sub, sub_level, local_level + 1, m, c_xyz) if inside
                else _implicit_tile(ctx, ctx.subtree(level + 1, c_xyz), level + 1, 0, 0, c_xyz)
                for m, c_xyz, inside in available]

    return _Tile(
        geometric_error=ctx.root_error / 2.0 ** level,
        refine=ctx.refine,
        transform=ctx.transform,
        contents=contents,
        externals=externals,
        children=children,
        has_children=bool(available),
    )


def _level_offset(branching: int, level: int) -> int:
    """Index of the first bit of ``level`` in a subtree's tile availability bitstream."""
    return (branching ** level - 1) // (branching - 1)


def _bit(bits: np.ndarray, index: int) -> bool:
    """Bit ``index`` of a little-endian-bit-order bitstream (or a constant: 0-d array)."""
    if bits.ndim == 0:
        return bool(bits)
    byte = index >> 3
    return byte < len(bits) and bool((bits[byte] >> (index & 7)) & 1)


def _read_subtree(path: Path, ctx: _Implicit) -> _Subtree:
    """Parse a binary (``subt``) or JSON subtree file into availability bitstreams."""
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise InputFileError(path, f"subtree file named by {ctx.json_path} is missing") from None
    if data[:4] == b"subt":
        if len(data) < 24:
            raise InputFileError(path, "subtree file is truncated")
        json_len, bin_len = struct.unpack_from("<QQ", data, 8)
        if 24 + json_len + bin_len > len(data):
            raise InputFileError(path, "subtree file is shorter than its header says (truncated)")
        raw_json, internal = data[24:24 + json_len], data[24 + json_len:24 + json_len + bin_len]
    else:
        raw_json, internal = data, b""
    try:
        doc = json.loads(raw_json.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputFileError(path, f"subtree JSON is invalid: {exc}") from None
    buffers = [internal if "uri" not in b else _read_buffer(_resolve(b["uri"], path, ctx.folder), path)
               for b in doc.get("buffers", [])]

    def availability(obj: dict | None) -> np.ndarray:
        if obj is None:
            return np.array(0, dtype=np.uint8)
        if "constant" in obj:
            return np.array(int(obj["constant"]), dtype=np.uint8)
        view = doc["bufferViews"][int(obj.get("bitstream", obj.get("bufferView")))]
        buf = buffers[int(view["buffer"])]
        start = int(view.get("byteOffset", 0))
        return np.frombuffer(buf, np.uint8, int(view["byteLength"]), start)

    try:
        contents = doc.get("contentAvailability") or []
        if isinstance(contents, dict):
            contents = [contents]
        return _Subtree(availability(doc.get("tileAvailability")), [availability(c) for c in contents],
                        availability(doc.get("childSubtreeAvailability")))
    except (KeyError, IndexError, TypeError, ValueError) as exc:
        raise InputFileError(path, f"malformed subtree availability: {exc}") from None


# --------------------------------------------------------------------------- content formats


def _read_buffer(path: Path, subtree: Path) -> bytes:
    """The bytes of a subtree's external buffer; InputFileError naming both when unreadable."""
    try:
        return path.read_bytes()
    except OSError as exc:
        raise InputFileError(path, f"subtree buffer named by {subtree} cannot be read: {exc.strerror or exc}") from None


def _parse_content(data: bytes, path: Path, y_up: bool, root: Path) -> list[MeshPart]:
    """Dispatch on the 4-byte magic (or JSON) of a tile content."""
    magic = data[:4]
    if magic == b"b3dm":
        return _parse_b3dm(data, path, y_up, root)
    if magic == b"i3dm":
        return _parse_i3dm(data, path, y_up, root)
    if magic == b"cmpt":
        return _parse_cmpt(data, path, y_up, root)
    if magic == b"glTF" or data.lstrip()[:1] == b"{":
        return parse_gltf_bytes(data, path, y_up, root)
    if magic == b"pnts":
        warnings.warn(f"{path}: point cloud (pnts) content skipped", stacklevel=3)
        return []
    raise InputFileError(path, f"unknown tile content format (magic {magic!r})")


def _check_length(data: bytes, path: Path, header_size: int) -> int:
    """The header byteLength, checked against the file size."""
    if len(data) < header_size:
        raise InputFileError(path, f"{data[:4].decode('latin-1')} file is truncated (shorter than its header)")
    length = struct.unpack_from("<I", data, 8)[0]
    if length > len(data):
        raise InputFileError(path, f"header byteLength is {length} but the file has {len(data)} bytes (truncated)")
    if length < len(data):
        warnings.warn(f"{path}: {len(data) - length} bytes after the tile's byteLength ignored", stacklevel=4)
    return length


def _feature_table(data: bytes, start: int, json_len: int, bin_len: int, path: Path) -> tuple[dict, bytes]:
    """Feature table JSON and binary body."""
    raw = data[start:start + json_len].strip(b" \x00")
    try:
        table = json.loads(raw.decode("utf-8")) if raw else {}
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputFileError(path, f"feature table JSON is invalid: {exc}") from None
    return table, data[start + json_len:start + json_len + bin_len]


def _feature_array(table: dict, body: bytes, name: str, count: int, n: int, dtype: str,
                   path: Path) -> np.ndarray | None:
    """(count, n) float64 feature-table property given inline or as a binary reference."""
    value = table.get(name)
    if value is None:
        return None
    if isinstance(value, dict):
        offset = int(value.get("byteOffset", 0))
        dt = np.dtype(dtype).newbyteorder("<")
        if offset + count * n * dt.itemsize > len(body):
            raise InputFileError(path, f"feature table {name} runs past the binary body")
        return np.frombuffer(body, dt, count * n, offset).reshape(count, n).astype(np.float64)
    return np.asarray(value, dtype=np.float64).reshape(count, n)


def _parse_b3dm(data: bytes, path: Path, y_up: bool, root: Path) -> list[MeshPart]:
    """Batched 3D model: header, feature table (RTC_CENTER), batch table (skipped), GLB."""
    length = _check_length(data, path, _B3DM_HEADER)
    ft_json, ft_bin, bt_json, bt_bin = struct.unpack_from("<4I", data, 12)
    header = _B3DM_HEADER
    if bt_json >= _LEGACY_LIMIT:  # legacy: [batchLength, batchTableByteLength]
        header, ft_json, ft_bin, bt_json, bt_bin = 20, 0, 0, ft_bin, 0
    elif bt_bin >= _LEGACY_LIMIT:  # legacy: [batchTableJsonByteLength, batchTableBinaryByteLength, batchLength]
        header, ft_json, ft_bin, bt_json, bt_bin = 24, 0, 0, ft_json, ft_bin
    glb_start = header + ft_json + ft_bin + bt_json + bt_bin
    if glb_start > length:
        raise InputFileError(path, "b3dm table lengths exceed the tile's byteLength (corrupt)")
    table, body = _feature_table(data, header, ft_json, ft_bin, path)
    parts = parse_gltf_bytes(data[glb_start:length], path, y_up, root)
    rtc = _feature_array(table, body, "RTC_CENTER", 1, 3, "float32", path)
    return parts if rtc is None else [p.transformed(lambda v, t=rtc[0]: v + t) for p in parts]


def _parse_i3dm(data: bytes, path: Path, y_up: bool, root: Path) -> list[MeshPart]:
    """Instanced 3D model: the glTF repeated at each instance's position/rotation/scale.

    Supported: POSITION, POSITION_QUANTIZED, RTC_CENTER, NORMAL_UP + NORMAL_RIGHT,
    SCALE, SCALE_NON_UNIFORM. EAST_NORTH_UP and oct-encoded normals are ignored with a
    warning (instances keep the tile's axes).
    """
    length = _check_length(data, path, _I3DM_HEADER)
    ft_json, ft_bin, bt_json, bt_bin, gltf_format = struct.unpack_from("<5I", data, 12)
    body_start = _I3DM_HEADER + ft_json + ft_bin + bt_json + bt_bin
    if body_start > length:
        raise InputFileError(path, "i3dm table lengths exceed the tile's byteLength (corrupt)")
    table, body = _feature_table(data, _I3DM_HEADER, ft_json, ft_bin, path)
    gltf = data[body_start:length]
    if gltf_format == 0:
        gltf_path = _resolve(gltf.rstrip(b" \x00").decode("utf-8"), path, root)
        parts = read_content(gltf_path, y_up, root)
    else:
        parts = parse_gltf_bytes(gltf, path, y_up, root)
    matrices = _instance_matrices(table, body, path)
    return [_instanced(p, matrices) for p in parts]


def _instance_matrices(table: dict, body: bytes, path: Path) -> np.ndarray:
    """(k, 4, 4) float64 instance matrices T(rtc + position) * R * S of an i3dm."""
    count = int(table.get("INSTANCES_LENGTH", 0))
    pos = _feature_array(table, body, "POSITION", count, 3, "float32", path)
    if pos is None:
        quant = _feature_array(table, body, "POSITION_QUANTIZED", count, 3, "uint16", path)
        if quant is None:
            raise InputFileError(path, "i3dm has neither POSITION nor POSITION_QUANTIZED")
        offset = np.asarray(table["QUANTIZED_VOLUME_OFFSET"], dtype=np.float64)
        scale = np.asarray(table["QUANTIZED_VOLUME_SCALE"], dtype=np.float64)
        pos = offset + quant / 65535.0 * scale
    rtc = _feature_array(table, body, "RTC_CENTER", 1, 3, "float32", path)
    m = np.tile(np.eye(4), (count, 1, 1))
    m[:, :3, 3] = pos + (rtc[0] if rtc is not None else 0.0)
    up = _feature_array(table, body, "NORMAL_UP", count, 3, "float32", path)
    right = _feature_array(table, body, "NORMAL_RIGHT", count, 3, "float32", path)
    if up is not None and right is not None:
        m[:, :3, 0], m[:, :3, 1], m[:, :3, 2] = right, up, np.cross(right, up)
    elif any(k in table for k in ("EAST_NORTH_UP", "NORMAL_UP_OCT32P", "NORMAL_RIGHT_OCT32P")):
        warnings.warn(f"{path}: i3dm instance orientation (EAST_NORTH_UP/oct normals) ignored", stacklevel=4)
    scale = _feature_array(table, body, "SCALE", count, 1, "float32", path)
    non_uniform = _feature_array(table, body, "SCALE_NON_UNIFORM", count, 3, "float32", path)
    factors = np.ones((count, 3))
    if scale is not None:
        factors *= scale
    if non_uniform is not None:
        factors *= non_uniform
    m[:, :3, :3] *= factors[:, None, :]
    return m


def _instanced(part: MeshPart, matrices: np.ndarray) -> MeshPart:
    """One part holding ``part`` repeated under each of ``matrices``."""
    k, n = len(matrices), len(part.vertices)
    verts = np.einsum("kij,nj->kni", matrices[:, :3, :3], part.vertices) + matrices[:, None, :3, 3]
    faces = part.faces[None, :, :] + (np.arange(k) * n)[:, None, None]
    rep = (lambda a: None if a is None else np.tile(a, (k, 1)))
    return MeshPart(verts.reshape(-1, 3), faces.reshape(-1, 3), rep(part.colors), rep(part.uv),
                    part.texture, part.name)


def _parse_cmpt(data: bytes, path: Path, y_up: bool, root: Path) -> list[MeshPart]:
    """Composite tile: the inner tiles one after another."""
    length = _check_length(data, path, 16)
    count = struct.unpack_from("<I", data, 12)[0]
    parts, pos = [], 16
    for _ in range(count):
        if pos + 12 > length:
            raise InputFileError(path, "composite tile is truncated")
        inner_len = struct.unpack_from("<I", data, pos + 8)[0]
        if inner_len < 12 or pos + inner_len > length:
            raise InputFileError(path, "composite inner tile runs past the end (corrupt)")
        parts.extend(_parse_content(data[pos:pos + inner_len], path, y_up, root))
        pos += inner_len
    return parts


# --------------------------------------------------------------------------- placement and CRS


def _place(parts: list[MeshPart], transform: np.ndarray) -> list[MeshPart]:
    """Parts moved by a 4x4 tile transform (winding kept when the transform mirrors)."""
    if np.array_equal(transform, np.eye(4)):
        return parts
    flip = np.linalg.det(transform[:3, :3]) < 0
    out = []
    for p in parts:
        q = p.transformed(lambda v: v @ transform[:3, :3].T + transform[:3, 3])
        if flip:
            q.faces = q.faces[:, [0, 2, 1]].copy()
        out.append(q)
    return out


def _merge_untextured(parts: list[MeshPart]) -> list[MeshPart]:
    """Textured parts as they are plus one part for all untextured ones (fewer draw calls)."""
    plain = [p for p in parts if p.texture is None and p.n_triangles]
    textured = [p for p in parts if p.texture is not None and p.n_triangles]
    if len(plain) <= 1:
        return textured + plain
    offsets = np.cumsum([0] + [len(p.vertices) for p in plain])
    grey = np.array([200, 200, 200, 255], dtype=np.uint8)
    merged = MeshPart(
        np.concatenate([p.vertices for p in plain]),
        np.concatenate([p.faces + o for p, o in zip(plain, offsets)]),
        colors=np.concatenate([p.colors if p.colors is not None else np.tile(grey, (len(p.vertices), 1))
                               for p in plain]),
        name="untextured",
    )
    return textured + [merged]
