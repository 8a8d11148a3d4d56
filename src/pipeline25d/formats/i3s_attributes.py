"""The attributes of an I3S ``3DObject`` layer's features, for the objects table and the viewer's identify.

The layer's ``attributeStorageInfo`` lists its fields (``key`` ``f_<k>``, ``name``); a node's
attribute resource holds one buffer per field, ``nodes/<resource>/attributes/<key>/0``: its
``header`` (a ``count`` of values, for text also the total byte count), then in the field's
``ordering`` the ``attributeByteCounts`` (text: each value's bytes) and the ``attributeValues``,
numbers aligned to their own size (a Float64 after the 4-byte count starts at byte 8). Value k
belongs to the node's k-th feature, in the geometry buffer's ``featureId`` order. A buffer that is
missing or does not hold ``count`` values leaves that field out, with one warning naming the
package; the values pass through :class:`~pipeline25d.formats.attributes.Limiter`.
"""

from __future__ import annotations

import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np

from pipeline25d.core.mesh import MeshPart
from pipeline25d.formats.attributes import Limiter, object_info

#: I3S's numeric value types (attribute buffers; a geometry buffer takes those but the object ids)
VALUE_TYPES = {"Int8": "i1", "UInt8": "u1", "Int16": "<i2", "UInt16": "<u2", "Int32": "<i4", "UInt32": "<u4",
               "Oid32": "<u4", "Int64": "<i8", "UInt64": "<u8", "Oid64": "<u8", "Float32": "<f4", "Float64": "<f8"}


def with_features(part: MeshPart, values: dict, package, fields, resource) -> MeshPart:
    """The part with its features as objects (each face's feature from the ``faceRange`` list, or a
    Draco buffer's ``faceFeature``), their attributes from attribute resource ``resource`` where the
    layer lists ``fields``."""
    ids, ranges = values.get("featureId"), values.get("faceRange")
    if "faceFeature" in values:                       # a Draco buffer's: each face's feature
        face_objects = values["faceFeature"].astype(np.int64)
    elif ids is None or ranges is None or not len(ids):
        return part
    else:
        face_objects = np.full(len(part.faces), -1, dtype=np.int64)
        for k, (first, last) in enumerate(ranges.astype(np.int64)):
            face_objects[max(first, 0):min(last, len(part.faces) - 1) + 1] = k
    keys = [str(int(v)) for v in ids[:, 0]]
    info = feature_info(package, fields, resource, keys, package.path) if fields and resource is not None else None
    if (face_objects < 0).any():
        keys.append(f"{part.name} (no feature)")           # faces no faceRange covers
        face_objects[face_objects < 0] = len(keys) - 1
    return replace(part, objects=tuple(keys), face_objects=face_objects.astype(np.int32), object_info=info)


def feature_info(package, fields: list, resource, keys: list[str], where: Path) -> dict[str, dict]:
    """Object key -> its record (:func:`~pipeline25d.formats.attributes.object_info`) of the features
    ``keys`` (in the node's feature order) from attribute resource ``resource``."""
    columns, problems = {}, []
    for field in fields:
        if not (isinstance(field, dict) and isinstance(field.get("key"), str) and isinstance(field.get("name"), str)):
            continue
        name = f"nodes/{resource}/attributes/{field['key']}/0"
        data = package.read(name, ".bin")
        values = None if data is None else _values(data, field, len(keys))
        if values is None:
            problems.append(f"{name} ({field['name']})")
        else:
            columns[field["name"]] = values
    if problems:
        warnings.warn(f"{where}: attribute buffers missing or not of {len(keys)} values, those attributes left "
                      f"out: {', '.join(problems[:5])}", stacklevel=4)
    limiter = Limiter(where)
    info = {key: object_info(None, limiter.attributes({n: v[k] for n, v in columns.items()}))
            for k, key in enumerate(keys)}
    limiter.warn(stacklevel=4)
    return info


def _values(data: bytes, field: dict, count: int) -> list | None:
    """The ``count`` values of one attribute buffer, or None where it does not hold them."""
    header = field.get("header") or [{"property": "count", "valueType": "UInt32"}]
    kind = (field.get("attributeValues") or {}).get("valueType")
    at, said = 0, {}
    try:
        for item in header:
            dtype = np.dtype(VALUE_TYPES[item["valueType"]])
            said[item["property"]] = int(np.frombuffer(data, dtype, 1, at)[0])
            at += dtype.itemsize
        if said.get("count") != count:
            return None
        sizes = None
        for part in field.get("ordering") or ["attributeValues"]:
            if part == "attributeByteCounts":
                sizes, at = np.frombuffer(data, "<u4", count, at), at + 4 * count
            elif part == "attributeValues" and kind == "String":
                if sizes is None or at + int(sizes.sum()) > len(data):
                    return None
                ends = at + np.cumsum(sizes)
                return [data[e - n:e].rstrip(b"\0").decode("utf-8", "replace") for e, n in zip(ends, sizes)]
            elif part == "attributeValues":
                dtype = np.dtype(VALUE_TYPES[kind])
                at = -(-at // dtype.itemsize) * dtype.itemsize          # aligned to the value's size
                return np.frombuffer(data, dtype, count, at).tolist()
    except (KeyError, TypeError, ValueError):
        return None
    return None
