"""glTF ``EXT_structural_metadata`` property tables: the properties of a feature id, as object attributes.

A primitive's ``EXT_mesh_features`` feature ids name a ``propertyTable``; row ``i`` of that table
holds feature ``i``'s properties, typed by the schema's class: SCALAR, VEC2-4 and MAT2-4 of
INT8 ... FLOAT64 (``normalized``, ``offset`` and ``scale`` applied, ``noData`` read as null),
BOOLEAN (a bitstream), STRING (UTF-8 with ``stringOffsets``), ENUM (its value's name), each
alone or as an array (fixed ``count`` or ``arrayOffsets``). Offsets count elements for arrays
and bytes for strings, as the extension says. Property textures and property attributes are not
read. A table that cannot be read costs its attributes, with a warning naming the file.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable

import numpy as np

COMPONENTS = {"INT8": "i1", "UINT8": "u1", "INT16": "<i2", "UINT16": "<u2", "INT32": "<i4", "UINT32": "<u4",
              "INT64": "<i8", "UINT64": "<u8", "FLOAT32": "<f4", "FLOAT64": "<f8"}
SIZES = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}


class MetadataError(ValueError):
    """A property table that does not fit its buffers or its schema."""


def property_rows(ext: dict, table_index: int, rows: Iterable[int],
                  view_bytes: Callable[[int], bytes]) -> dict[int, dict]:
    """Row -> {property: value} of ``rows`` of property table ``table_index`` of the glTF's
    ``EXT_structural_metadata`` object ``ext``; ``view_bytes(i)`` gives buffer view ``i``.
    Rows outside the table are left out. MetadataError when the table cannot be read."""
    try:
        table = ext["propertyTables"][int(table_index)]
        schema = ext.get("schema") or {}
        cls = schema["classes"][table["class"]]
        count = int(table["count"])
    except (KeyError, IndexError, TypeError, ValueError) as exc:
        raise MetadataError(f"property table {table_index} or its class is missing ({exc!r})") from None
    wanted = sorted({int(r) for r in rows if 0 <= int(r) < count})
    out: dict[int, dict] = {r: {} for r in wanted}
    for name, prop in (table.get("properties") or {}).items():
        definition = (cls.get("properties") or {}).get(name)
        if not isinstance(definition, dict) or not isinstance(prop, dict):
            raise MetadataError(f"property {name!r} is not in class {table['class']!r}")
        column = _Column(definition, prop, count, view_bytes, schema.get("enums") or {}, name)
        for r in wanted:
            value = column.value(r)
            if value is not None:
                out[r][name] = value
    return out


class _Column:
    """One property of a property table, read row by row."""

    def __init__(self, definition: dict, prop: dict, count: int, view_bytes, enums: dict, name: str):
        self.name, self.count = name, count
        self.type = str(definition.get("type", "SCALAR"))
        self.array = bool(definition.get("array", False))
        self.fixed = int(definition.get("count", 0) or 0)
        self.no_data = definition.get("noData")
        self.names: dict | None = None
        component = definition.get("componentType")
        if self.type == "ENUM":
            enum = enums.get(definition.get("enumType")) or {}
            component = enum.get("valueType", "UINT16")
            self.names = {int(v["value"]): str(v["name"]) for v in enum.get("values", [])}
        try:
            self.values = view_bytes(int(prop["values"]))
            self.array_offsets = self._offsets(prop, "arrayOffsets", "arrayOffsetType", view_bytes)
            self.string_offsets = self._offsets(prop, "stringOffsets", "stringOffsetType", view_bytes)
        except (KeyError, TypeError, ValueError) as exc:
            raise MetadataError(f"property {name!r}: buffer views missing ({exc!r})") from None
        self.size = 1 if self.type in ("ENUM", "STRING", "BOOLEAN") else SIZES.get(self.type, 0)
        self.dtype = None
        if self.type not in ("STRING", "BOOLEAN"):
            if component not in COMPONENTS or not self.size:
                raise MetadataError(f"property {name!r}: type {self.type} / {component} not readable")
            self.dtype = np.dtype(COMPONENTS[component])
            self.numbers = np.frombuffer(self.values, self.dtype, len(self.values) // self.dtype.itemsize)
            normalized = bool(definition.get("normalized", False)) and self.dtype.kind in "iu"
            self.scale = prop.get("scale", definition.get("scale"))
            self.offset = prop.get("offset", definition.get("offset"))
            self.divisor = float(np.iinfo(self.dtype).max) if normalized else None

    def _offsets(self, prop: dict, key: str, type_key: str, view_bytes) -> np.ndarray | None:
        if key not in prop:
            return None
        dtype = np.dtype(COMPONENTS.get(str(prop.get(type_key, "UINT32")), "<u4"))
        data = view_bytes(int(prop[key]))
        return np.frombuffer(data, dtype, len(data) // dtype.itemsize).astype(np.int64)

    def value(self, row: int):
        """The value of ``row`` (None when it is the property's noData)."""
        if self.array and not self.fixed:
            if self.array_offsets is None or row + 1 >= len(self.array_offsets):
                raise MetadataError(f"property {self.name!r}: arrayOffsets too short")
            start, end = int(self.array_offsets[row]), int(self.array_offsets[row + 1])
            return [self._element(k) for k in range(start, end)]
        if self.array:
            return [self._element(row * self.fixed + k) for k in range(self.fixed)]
        if self.no_data is not None and self._element(row, raw=True) == self.no_data:
            return None                          # noData is the value as stored, before offset and scale
        return self._element(row)

    def _element(self, k: int, raw: bool = False):
        """Element ``k`` of the flattened values (``raw``: numbers as stored, enums as their value)."""
        if self.type == "BOOLEAN":
            if k // 8 >= len(self.values):
                raise MetadataError(f"property {self.name!r}: values too short")
            return bool(self.values[k // 8] >> (k % 8) & 1)
        if self.type == "STRING":
            offsets = self.string_offsets
            if offsets is None or k + 1 >= len(offsets) or not 0 <= offsets[k] <= offsets[k + 1] <= len(self.values):
                raise MetadataError(f"property {self.name!r}: stringOffsets do not fit its values")
            return self.values[offsets[k]:offsets[k + 1]].decode("utf-8", "replace")
        if (k + 1) * self.size > len(self.numbers):
            raise MetadataError(f"property {self.name!r}: values too short for row {k}")
        stored = self.numbers[k * self.size:(k + 1) * self.size]
        if raw:
            return stored.tolist()[0] if self.size == 1 else stored.tolist()
        if self.names is not None:
            return self.names.get(int(stored[0]), int(stored[0]))
        values = (stored.astype(np.float64) if self.divisor or self.scale is not None or self.offset is not None
                  else stored)
        if self.divisor:
            values = np.maximum(values / self.divisor, -1.0)
        if self.scale is not None:
            values = values * np.asarray(self.scale, dtype=np.float64)
        if self.offset is not None:
            values = values + np.asarray(self.offset, dtype=np.float64)
        out = values.tolist()
        return out[0] if self.size == 1 else out
