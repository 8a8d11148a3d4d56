"""An I3S node's Draco-compressed geometry buffer, with what I3S keeps in its Draco metadata.

DracoPy decodes the mesh but does not give the bitstream's metadata, where I3S puts two things:
``i3s-scale_x`` and ``i3s-scale_y`` on the position attribute (a geographic layer's positions are
stored in units of ``scale`` degrees: ArcGIS writes 1 / 111319.49, a metre at the equator, for
both), and on the ``feature-index`` attribute (``i3s-attribute-type``) the ``i3s-feature-ids``
its per-vertex indices point into. :func:`draco_metadata` reads them from the header, as Draco's
bitstream defines it: ``DRACO``, version, encoder type and method, a u16 of flags whose bit
0x8000 says metadata follows; then the attributes' metadata (each: its attribute's unique id and
an element) and the file's. An element is a varint count of entries (a u8-sized key, a
varint-sized value), then a varint count of named sub-elements.
"""

from __future__ import annotations

import struct

import numpy as np

from pipeline25d.core.errors import InputFileError

METADATA_FLAG = 0x8000
_POSITION, _GENERIC = 0, 4        # Draco's attribute types


def draco_metadata(data: bytes) -> dict[int, dict[str, bytes]]:
    """Attribute unique id -> its metadata entries (key -> raw value bytes); {} without metadata.
    ValueError for a header cut short."""
    if data[:5] != b"DRACO" or len(data) < 11:
        raise ValueError("not a Draco bitstream")
    (flags,) = struct.unpack_from("<H", data, 9)
    if not flags & METADATA_FLAG:
        return {}
    reader = _Reader(data, 11)
    out = {}
    for _ in range(reader.varint()):
        unique_id = reader.varint()
        out[unique_id] = reader.element()
    return out


class _Reader:
    def __init__(self, data: bytes, at: int):
        self.data, self.at = data, at

    def take(self, n: int) -> bytes:
        if self.at + n > len(self.data):
            raise ValueError("Draco metadata cut short")
        self.at += n
        return self.data[self.at - n:self.at]

    def varint(self) -> int:
        value = shift = 0
        while True:
            byte = self.take(1)[0]
            value |= (byte & 0x7F) << shift
            if not byte & 0x80:
                return value
            shift += 7
            if shift > 35:
                raise ValueError("Draco metadata: a count longer than 5 bytes")

    def element(self, depth: int = 0) -> dict[str, bytes]:
        if depth > 8:
            raise ValueError("Draco metadata nested deeper than 8 levels")
        entries = {}
        for _ in range(self.varint()):
            key = self.take(self.take(1)[0]).decode("utf-8", "replace")
            entries[key] = self.take(self.varint())
        for _ in range(self.varint()):
            self.take(self.take(1)[0])
            self.element(depth + 1)          # named sub-elements: I3S writes none that matter here
        return entries


def draco_values(data: bytes, geographic: bool, where, name: str) -> dict[str, np.ndarray]:
    """The node's attributes as :mod:`.i3s` reads an uncompressed buffer (three corners a triangle):
    ``position`` (degrees in a geographic layer, by its ``i3s-scale``), ``uv0``, ``color``, and where
    the buffer names features, ``featureId`` and each face's ``faceFeature`` (an index into them)."""
    import DracoPy

    try:
        metadata = draco_metadata(data)
        mesh = DracoPy.decode(data)
    except Exception as exc:          # DracoPy raises several types for corrupt data
        raise InputFileError(where, f"{name}: Draco data cannot be decoded ({exc})") from None
    faces = np.asarray(getattr(mesh, "faces", np.zeros((0, 3))), dtype=np.int64).reshape(-1, 3)
    corners = faces.ravel()
    position = np.asarray(mesh.points, dtype=np.float64)[corners]
    attributes = {a["attribute_type"]: a for a in mesh.attributes if a["attribute_type"] != _GENERIC}
    if geographic:
        meta = metadata.get(attributes[_POSITION]["unique_id"], {}) if _POSITION in attributes else {}
        scale = [_double(meta.get(f"i3s-scale_{axis}")) for axis in "xy"]
        if None in scale:
            raise InputFileError(where, f"{name}: Draco geometry of a geographic layer without its i3s-scale_x "
                                        "and i3s-scale_y (its positions' unit in degrees)")
        position[:, :2] *= scale
    values = {"position": position}
    if getattr(mesh, "tex_coord", None) is not None and len(mesh.tex_coord):
        values["uv0"] = np.asarray(mesh.tex_coord, dtype=np.float32)[corners]
    if getattr(mesh, "colors", None) is not None and len(mesh.colors):
        values["color"] = np.asarray(mesh.colors, dtype=np.uint8)[corners]
    for attribute in mesh.attributes:
        meta = metadata.get(attribute["unique_id"], {})
        if meta.get("i3s-attribute-type", b"").rstrip(b"\0") == b"feature-index" and "i3s-feature-ids" in meta:
            ids = np.frombuffer(meta["i3s-feature-ids"], "<i4")
            index = np.asarray(attribute["data"]).reshape(-1)[faces[:, 0]].astype(np.int64)
            if len(ids) and len(index) and 0 <= index.min() and index.max() < len(ids):
                values["featureId"], values["faceFeature"] = ids.astype(np.uint64).reshape(-1, 1), index
    return values


def _double(raw: bytes | None) -> float | None:
    return struct.unpack("<d", raw)[0] if raw is not None and len(raw) == 8 else None
