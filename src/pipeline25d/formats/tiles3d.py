"""3D Tiles 1.0 / 1.1 reader: b3dm/i3dm/cmpt/glb/gltf content placed by the tile tree.

Placement follows the 3D Tiles spec (and CesiumJS): glTF node hierarchy, glTF y-up ->
z-up ((x, y, z) -> (x, -z, y), unless ``asset.gltfUpAxis`` is "Z"), then the content's
RTC_CENTER / CESIUM_RTC, then the tile transforms multiplied root-to-leaf. External
tilesets (a tile whose content is a ``.json``) inherit the referencing tile's transform
and refine mode and resolve their URIs relative to their own JSON file. The tree (explicit,
external, implicit), its limits and the tiles drawn where children are unreachable are
:mod:`pipeline25d.formats.tileset_tree`.

Every file a tileset names (contents, external tilesets, subtrees and their buffers, glTF
buffers and images, i3dm glTF URIs) must lie inside the root tileset.json's folder
(:func:`~pipeline25d.formats.common.side_file`): ``../`` to a sibling inside it is fine.

A b3dm's batch table gives its batch ids' attributes (:mod:`pipeline25d.formats.batch_table`).

Bounding volumes are never used: the selection here depends on geometric errors only,
and geometry is never clipped to a bounding volume (real tilesets, e.g. pg2b3dm's
Amsterdam sample, have boxes that are too small on one side).

Vertices stay float64 from the decoded glTF to the scene CRS; ECEF (``src_crs``) is
reprojected once per tileset with :func:`pipeline25d.core.crs.transform_points` after an
area-of-use check of the scene CRS.
"""

from __future__ import annotations

import json
import struct
import warnings
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import numpy as np

from pipeline25d.core.errors import InputFileError
from pipeline25d.core.mesh import Mesh, MeshPart, joined, repeated
from pipeline25d.formats.batch_table import COMPONENT_TYPES, batch_table_rows
from pipeline25d.formats.common import Detail, Loaded, in_scene
from pipeline25d.formats.feature_info import feature_prefix, with_feature_info
from pipeline25d.formats.gltf import UP_AXES, parse_gltf_bytes
from pipeline25d.formats.gzipped import file_bytes
from pipeline25d.formats.tileset_tree import read_json, resolve, select

_B3DM_HEADER = 28
_I3DM_HEADER = 32
ECEF = "EPSG:4978"         # the CRS of 3D Tiles coordinates
PIECE_BYTES = 256 * 2 ** 20  # ingest reads a tileset in pieces of contents this large on disk
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
    (loaded,) = read_tileset_pieces(path, spec, detail, piece_bytes=float("inf"))
    return loaded


def read_tileset_pieces(path: Path, spec: dict, detail: Detail = Detail(),
                        piece_bytes: float | None = None) -> Iterator[Loaded]:
    """:func:`read_tileset` in pieces of contents that add up to ``piece_bytes`` on disk (None:
    :data:`PIECE_BYTES`), untextured parts merged within a piece: a tileset smaller than that is
    one piece, the parts :func:`read_tileset` returns. A package (.3tz, .zip, .3dtiles) is read
    as the folder it unpacks to (:mod:`.tileset_packages`), its errors naming the file in it."""
    from pipeline25d.formats.tileset_packages import is_package, named_in_package, root_tileset, unpacked

    path = Path(path)
    if is_package(path):
        folder = unpacked(path)                    # located (and unpacked where new) once
        yield from named_in_package(path, folder, read_tileset_pieces(root_tileset(path, folder), spec, detail,
                                                                      piece_bytes))
        return
    up_axis = str(read_json(path).get("asset", {}).get("gltfUpAxis", "Y")).upper()
    if up_axis not in UP_AXES:
        raise InputFileError(path, f"asset.gltfUpAxis {up_axis!r} is none of X, Y, Z")
    chosen = select(path, detail.max_error, spec.get("missing_children", "coarser"))
    crs, coarser = spec.get("crs") or ECEF, tuple(chosen.coarser)
    if chosen.coarser:
        missing = [m for c in chosen.coarser for m in c.missing]
        warnings.warn(f"{path}: {len(missing)} child content file(s) missing, {len(chosen.coarser)} tile(s) drawn "
                      f"coarser than asked, at the finest level present: {', '.join(missing[:5])}"
                      + (" ..." if len(missing) > 5 else ""), stacklevel=2)
    piece_bytes = PIECE_BYTES if piece_bytes is None else piece_bytes
    parts: list[MeshPart] = []
    held, drawn = 0, False
    for k, (content_path, transform) in enumerate(chosen.contents):
        parts.extend(_place(read_content(content_path, up_axis, root=path.parent), transform))
        held += content_path.stat().st_size
        if held >= piece_bytes and k < len(chosen.contents) - 1:
            drawn = drawn or bool(parts)
            yield Loaded(_merge_untextured(parts), crs, coarser)
            parts, held, coarser = [], 0, ()
    if not (drawn or parts):
        warnings.warn(f"{path}: the selected tiles hold no triangles", stacklevel=2)
    yield Loaded(_merge_untextured(parts), crs, coarser)


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


def read_content(path: Path, up_axis: str = "Y", root: Path | None = None) -> list[MeshPart]:
    """Parts of one content file (b3dm, i3dm, cmpt, glb, gltf) in the tile's frame; the files it
    names must lie in ``root`` (default: its folder).

    Point clouds (pnts) and unknown formats are skipped with a warning.
    """
    try:
        data = file_bytes(path)
    except FileNotFoundError:
        raise InputFileError(path, "tile content file is missing") from None
    except OSError as exc:
        raise InputFileError(path, f"cannot read tile content: {exc.strerror or exc}") from None
    return _parse_content(data, path, up_axis, path.parent if root is None else root)


# --------------------------------------------------------------------------- content formats


def _parse_content(data: bytes, path: Path, up_axis: str, root: Path) -> list[MeshPart]:
    """Dispatch on the 4-byte magic (or JSON) of a tile content."""
    magic = data[:4]
    if magic == b"b3dm":
        return _parse_b3dm(data, path, up_axis, root)
    if magic == b"i3dm":
        return _parse_i3dm(data, path, up_axis, root)
    if magic == b"cmpt":
        return _parse_cmpt(data, path, up_axis, root)
    if magic == b"glTF" or data.lstrip()[:1] == b"{":
        return parse_gltf_bytes(data, path, up_axis, root)
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


def _parse_b3dm(data: bytes, path: Path, up_axis: str, root: Path) -> list[MeshPart]:
    """Batched 3D model: header, feature table (RTC_CENTER, BATCH_LENGTH), batch table (the batch
    ids' attributes, :mod:`pipeline25d.formats.batch_table`), GLB."""
    length = _check_length(data, path, _B3DM_HEADER)
    ft_json, ft_bin, bt_json, bt_bin = struct.unpack_from("<4I", data, 12)
    header, batch_length = _B3DM_HEADER, None
    if bt_json >= _LEGACY_LIMIT:  # legacy: [batchLength, batchTableByteLength]
        header, ft_json, ft_bin, bt_json, bt_bin, batch_length = 20, 0, 0, ft_bin, 0, ft_json
    elif bt_bin >= _LEGACY_LIMIT:  # legacy: [batchTableJsonByteLength, batchTableBinaryByteLength, batchLength]
        header, ft_json, ft_bin, bt_json, bt_bin, batch_length = 24, 0, 0, ft_json, ft_bin, bt_json
    glb_start = header + ft_json + ft_bin + bt_json + bt_bin
    if glb_start > length:
        raise InputFileError(path, "b3dm table lengths exceed the tile's byteLength (corrupt)")
    table, body = _feature_table(data, header, ft_json, ft_bin, path)
    parts = parse_gltf_bytes(data[glb_start:length], path, up_axis, root)
    rtc = _feature_array(table, body, "RTC_CENTER", 1, 3, "float32", path)
    parts = parts if rtc is None else [p.transformed(lambda v, t=rtc[0]: v + t) for p in parts]
    batch_start = header + ft_json + ft_bin
    count = table.get("BATCH_LENGTH", batch_length)
    rows = batch_table_rows(data[batch_start:batch_start + bt_json],
                            data[batch_start + bt_json:batch_start + bt_json + bt_bin],
                            count if isinstance(count, int) and count >= 0 else None, path)
    return with_feature_info(parts, rows, feature_prefix(path, root), path)


def _parse_i3dm(data: bytes, path: Path, up_axis: str, root: Path) -> list[MeshPart]:
    """Instanced 3D model: the glTF repeated at each instance's position/rotation/scale, each
    instance an object ``<file>#<batch id>`` (``BATCH_ID``, else its index) with its row of the
    batch table as attributes (where the glTF's own faces carry no feature ids).

    Supported: POSITION, POSITION_QUANTIZED, RTC_CENTER, NORMAL_UP + NORMAL_RIGHT (or their
    oct-encoded ``*_OCT32P``), EAST_NORTH_UP (at the instance's position in the tile's frame,
    which such tiles give in ECEF), SCALE, SCALE_NON_UNIFORM.
    """
    length = _check_length(data, path, _I3DM_HEADER)
    ft_json, ft_bin, bt_json, bt_bin, gltf_format = struct.unpack_from("<5I", data, 12)
    body_start = _I3DM_HEADER + ft_json + ft_bin + bt_json + bt_bin
    if body_start > length:
        raise InputFileError(path, "i3dm table lengths exceed the tile's byteLength (corrupt)")
    table, body = _feature_table(data, _I3DM_HEADER, ft_json, ft_bin, path)
    gltf = data[body_start:length]
    if gltf_format == 0:
        gltf_path = resolve(gltf.rstrip(b" \x00").decode("utf-8"), path, root)
        parts = read_content(gltf_path, up_axis, root)
    else:
        parts = parse_gltf_bytes(gltf, path, up_axis, root)
    matrices = _instance_matrices(table, body, path)
    batch_ids = _batch_ids(table, body, len(matrices), path)
    prefix = feature_prefix(path, root)
    parts = [_instanced(p, matrices, batch_ids, prefix) for p in parts]
    bt_start = _I3DM_HEADER + ft_json + ft_bin
    count = int(batch_ids.max()) + 1 if len(batch_ids) else 0
    rows = batch_table_rows(data[bt_start:bt_start + bt_json], data[bt_start + bt_json:bt_start + bt_json + bt_bin],
                            count, path)
    return with_feature_info(parts, rows, prefix, path)


def _batch_ids(table: dict, body: bytes, count: int, path: Path) -> np.ndarray:
    """(count,) int64 batch id of each i3dm instance: ``BATCH_ID`` (UNSIGNED_BYTE/SHORT/INT), else its index."""
    ref = table.get("BATCH_ID")
    if ref is None:
        return np.arange(count)
    kind = str(ref.get("componentType", "UNSIGNED_SHORT")) if isinstance(ref, dict) else ""
    dtype = COMPONENT_TYPES[kind if kind in ("UNSIGNED_BYTE", "UNSIGNED_SHORT", "UNSIGNED_INT") else "UNSIGNED_SHORT"]
    return _feature_array(table, body, "BATCH_ID", count, 1, dtype, path).reshape(-1).astype(np.int64)


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
    if up is None or right is None:
        up_oct = _feature_array(table, body, "NORMAL_UP_OCT32P", count, 2, "uint16", path)
        right_oct = _feature_array(table, body, "NORMAL_RIGHT_OCT32P", count, 2, "uint16", path)
        if up_oct is not None and right_oct is not None:
            up, right = oct_decoded(up_oct), oct_decoded(right_oct)
    if up is not None and right is not None:
        m[:, :3, 0], m[:, :3, 1], m[:, :3, 2] = right, up, np.cross(right, up)
    elif table.get("EAST_NORTH_UP") and count:
        m[:, :3, :3] = _east_north_up(m[:, :3, 3], path)
    scale = _feature_array(table, body, "SCALE", count, 1, "float32", path)
    non_uniform = _feature_array(table, body, "SCALE_NON_UNIFORM", count, 3, "float32", path)
    factors = np.ones((count, 3))
    if scale is not None:
        factors *= scale
    if non_uniform is not None:
        factors *= non_uniform
    m[:, :3, :3] *= factors[:, None, :]
    return m


def oct_decoded(encoded: np.ndarray) -> np.ndarray:
    """(k, 3) unit vectors of (k, 2) oct-encoded normals in 0..65535 (3D Tiles' ``*_OCT32P``, the
    octahedral mapping CesiumJS's ``AttributeCompression.octDecodeInRange`` reads)."""
    xy = np.asarray(encoded, dtype=np.float64) / 65535.0 * 2.0 - 1.0
    x, y = xy[:, 0], xy[:, 1]
    z = 1.0 - np.abs(x) - np.abs(y)
    folded = z < 0
    sign = (lambda v: np.where(v >= 0, 1.0, -1.0))
    x2 = np.where(folded, (1.0 - np.abs(y)) * sign(x), x)
    y2 = np.where(folded, (1.0 - np.abs(x)) * sign(y), y)
    v = np.column_stack([x2, y2, z])
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def _east_north_up(positions: np.ndarray, path: Path) -> np.ndarray:
    """(k, 3, 3) rotations taking each i3dm instance's axes to east, north, up at its position
    (``EAST_NORTH_UP``), where the positions are ECEF as such tiles are written (their norms within
    100 km of the Earth's radii); else the identity, with a warning."""
    from pipeline25d.core.crs import east_north_up_axes

    radius = np.linalg.norm(positions, axis=1)
    if not ((radius > 6.25e6) & (radius < 6.48e6)).all():
        warnings.warn(f"{path}: i3dm EAST_NORTH_UP on positions that are not Earth-centred (|p| "
                      f"{radius.min():.0f}..{radius.max():.0f} m): the instances keep the tile's axes", stacklevel=5)
        return np.tile(np.eye(3), (len(positions), 1, 1))
    return east_north_up_axes(positions)


def _instanced(part: MeshPart, matrices: np.ndarray, batch_ids: np.ndarray, prefix: str) -> MeshPart:
    """One part holding ``part`` repeated under each of ``matrices``; without feature ids of its own,
    instance ``j``'s faces belong to the object ``<prefix>#<batch_ids[j]>``."""
    out = repeated(part, matrices)
    if part.face_objects is None:
        held, inverse = np.unique(batch_ids, return_inverse=True)
        out = replace(out, objects=tuple(f"{prefix}#{b}" for b in held),
                      face_objects=np.repeat(inverse, part.n_triangles))
    return out


def _parse_cmpt(data: bytes, path: Path, up_axis: str, root: Path) -> list[MeshPart]:
    """Composite tile: the inner tiles one after another, the features of inner tile ``k`` keyed
    ``<file>/<k>#<feature id>`` (each inner tile numbers its features from 0)."""
    length = _check_length(data, path, 16)
    count = struct.unpack_from("<I", data, 12)[0]
    parts, pos = [], 16
    for k in range(count):
        if pos + 12 > length:
            raise InputFileError(path, "composite tile is truncated")
        inner_len = struct.unpack_from("<I", data, pos + 8)[0]
        if inner_len < 12 or pos + inner_len > length:
            raise InputFileError(path, "composite inner tile runs past the end (corrupt)")
        parts.extend(_inner_keys(_parse_content(data[pos:pos + inner_len], path, up_axis, root),
                                 feature_prefix(path, root), k))
        pos += inner_len
    return parts


def _inner_keys(parts: list[MeshPart], prefix: str, k: int) -> list[MeshPart]:
    """Inner tile ``k``'s parts with their feature keys ``<prefix>#<id>`` (and their attributes')
    made ``<prefix>/<k>#<id>``."""
    old, new = f"{prefix}#", f"{prefix}/{k}#"

    def key(name: str) -> str:
        return new + name[len(old):] if name.startswith(old) else name

    infos: dict[int, dict] = {}                  # each shared mapping renamed once
    for p in parts:
        if p.object_info and id(p.object_info) not in infos:
            infos[id(p.object_info)] = {key(name): v for name, v in p.object_info.items()}
    return [replace(p, objects=tuple(key(o) for o in p.objects),
                    object_info=infos.get(id(p.object_info), p.object_info)) for p in parts]


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
    grey = np.array([200, 200, 200, 255], dtype=np.uint8)
    plain = [replace(p, uv=None, colors=p.colors if p.colors is not None else np.tile(grey, (len(p.vertices), 1)))
             for p in plain]
    return textured + [joined(plain, "untextured")]
