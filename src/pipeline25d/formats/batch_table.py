"""A b3dm batch table (3D Tiles 1.0): the properties of each batch id, as object attributes.

The JSON part holds a property either as an array of one value per feature or as a reference
into the binary part (``byteOffset``, ``componentType`` BYTE ... DOUBLE, ``type`` SCALAR or
VEC2-4). A feature's attributes are its values, nulls left out. The batch table hierarchy
extension (``extensions``) and ``extras`` are not read (a warning says so). A batch table that
cannot be read (invalid JSON, a reference past the binary part, an array of the wrong length)
costs its attributes or the property concerned, with a warning naming the file: the geometry
is drawn all the same.
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np

COMPONENT_TYPES = {"BYTE": "i1", "UNSIGNED_BYTE": "u1", "SHORT": "<i2", "UNSIGNED_SHORT": "<u2",
                   "INT": "<i4", "UNSIGNED_INT": "<u4", "FLOAT": "<f4", "DOUBLE": "<f8"}
TYPE_SIZES = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}


def batch_table_rows(json_bytes: bytes, body: bytes, count: int | None, path: Path) -> list[dict]:
    """Attributes of each of the ``count`` features (``BATCH_LENGTH``; None: the longest array)."""
    raw = json_bytes.strip(b" \x00")
    if not raw:
        return []
    try:
        table = json.loads(raw.decode("utf-8", "replace"))
    except (json.JSONDecodeError, RecursionError) as exc:
        warnings.warn(f"{path}: batch table JSON is invalid ({exc}); its features have no attributes", stacklevel=3)
        return []
    if not isinstance(table, dict):
        warnings.warn(f"{path}: batch table JSON is not an object; its features have no attributes", stacklevel=3)
        return []
    skipped = [k for k in ("extensions", "extras") if k in table]
    if skipped:
        warnings.warn(f"{path}: batch table {' and '.join(skipped)} not read (hierarchy extension)", stacklevel=3)
    columns = {k: v for k, v in table.items() if k not in ("extensions", "extras")}
    if count is None:
        count = max((len(v) for v in columns.values() if isinstance(v, list)), default=0)
    problems, values = [], {}
    for name, column in columns.items():
        found = _column(column, body, count)
        if isinstance(found, str):
            problems.append(f"{name}: {found}")
        else:
            values[name] = found
    # rows only for columns read: their lengths are count, bounded by the file's own size
    rows: list[dict] = [{} for _ in range(count)] if values else []
    for name, column in values.items():
        for row, value in zip(rows, column):
            if value is not None:
                row[name] = value
    if problems:
        warnings.warn(f"{path}: batch table properties not read: {'; '.join(problems[:5])}"
                      + (" ..." if len(problems) > 5 else ""), stacklevel=3)
    return rows


def _column(column, body: bytes, count: int) -> list | str:
    """The ``count`` values of one property, or what is wrong with it."""
    if isinstance(column, list):
        if len(column) != count:
            return f"{len(column)} values for {count} features"
        return column
    if not isinstance(column, dict):
        return "neither an array nor a binary reference"
    dtype = COMPONENT_TYPES.get(str(column.get("componentType")))
    size = TYPE_SIZES.get(str(column.get("type")))
    if dtype is None or size is None:
        return f"componentType {column.get('componentType')!r} / type {column.get('type')!r} unknown"
    try:
        offset = int(column.get("byteOffset", 0))
    except (TypeError, ValueError):
        return "byteOffset is not a number"
    dt = np.dtype(dtype)
    if offset < 0 or offset + count * size * dt.itemsize > len(body):
        return "runs past the binary body"
    values = np.frombuffer(body, dt, count * size, offset).reshape(count, size)
    return values[:, 0].tolist() if size == 1 else values.tolist()
