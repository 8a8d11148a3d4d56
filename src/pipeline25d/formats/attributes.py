"""Object attributes as every reader hands them on: JSON-safe, bounded, with a warning naming the file.

A reader that knows what its objects are (CityGML generic and thematic attributes, a b3dm batch
table, glTF ``EXT_structural_metadata`` property tables) gives each part an ``object_info``
(:attr:`pipeline25d.core.mesh.MeshPart.object_info`): object key -> ``{"type": ..., "attributes":
{...}}``. Ingest writes them beside the object ids, the objects table publishes them
(:mod:`pipeline25d.publish.objects`).

Values end up in a CSV cell, a GeoPackage field, the viewer's JSON shards and a WMS answer, so
hostile inputs are cut to size here: at most :data:`MAX_ATTRIBUTES` attributes an object and
:data:`MAX_OBJECT_CHARS` characters of them in all, text values and names up to :data:`MAX_TEXT`
and :data:`MAX_NAME` characters, lists and mappings up to :data:`MAX_ITEMS` items and
:data:`MAX_DEPTH` levels (deeper ones become their JSON text, cut). Text that is not valid UTF-8
(lone surrogates from a JSON escape, undecodable bytes) has the offending characters replaced by
U+FFFD; NaN and infinities become null (JSON has neither). Whatever was cut is counted and
:meth:`Limiter.warn` says so once per file.
"""

from __future__ import annotations

import json
import math
import re
import warnings
from collections import Counter
from collections.abc import Mapping
from pathlib import Path

MAX_ATTRIBUTES = 500
MAX_OBJECT_CHARS = 20_000
MAX_TEXT = 2_000
MAX_NAME = 200
MAX_ITEMS = 100
MAX_DEPTH = 4
_SURROGATE = re.compile("[\ud800-\udfff]")


def object_info(obj_type: str | None, attributes: Mapping | None) -> dict:
    """The record of one object: ``type`` and ``attributes``, each only when it says something."""
    out: dict = {}
    if obj_type:
        out["type"] = obj_type
    if attributes:
        out["attributes"] = dict(attributes)
    return out


def clean_text(text: str) -> str:
    """``text`` with what UTF-8 cannot encode (lone surrogates) replaced by U+FFFD."""
    return _SURROGATE.sub("\ufffd", text)


class Limiter:
    """Bounds the attributes of the objects of one file (``where``) and counts what it cut."""

    def __init__(self, where: str | Path):
        self.where = str(where)
        self.cut: Counter = Counter()

    def attributes(self, attrs: Mapping) -> dict:
        """``attrs`` (name -> value) bounded as the module says."""
        out: dict = {}
        used = 0
        for n, (name, value) in enumerate(attrs.items()):
            if n >= MAX_ATTRIBUTES:
                self.cut[f"attributes beyond {MAX_ATTRIBUTES} an object dropped"] += len(attrs) - n
                break
            key = self._text(str(name), MAX_NAME, "attribute names")
            value = self.value(value, 1)
            size = len(key) + len(json.dumps(value, ensure_ascii=False))
            if used + size > MAX_OBJECT_CHARS:
                self.cut[f"attributes beyond {MAX_OBJECT_CHARS} characters an object dropped"] += 1
                continue
            used += size
            out[key] = value
        return out

    def value(self, value, depth: int = 1):
        """One value, JSON-safe and bounded (``depth``: its nesting level)."""
        if value is None or isinstance(value, (bool, int)):
            return value
        if isinstance(value, float):
            if math.isfinite(value):
                return value
            self.cut["NaN or infinite numbers made null"] += 1
            return None
        if isinstance(value, bytes):
            value = value.decode("utf-8", "replace")
        if isinstance(value, str):
            return self._text(value, MAX_TEXT, "text values")
        if isinstance(value, (list, tuple, Mapping)) and depth >= MAX_DEPTH:
            self.cut[f"values nested deeper than {MAX_DEPTH} levels kept as text"] += 1
            return self._text(json.dumps(value, default=str, ensure_ascii=False)[:MAX_TEXT + 1], MAX_TEXT,
                              "text values")
        if isinstance(value, Mapping):
            items = list(value.items())
            if len(items) > MAX_ITEMS:
                self.cut[f"mapping items beyond {MAX_ITEMS} dropped"] += len(items) - MAX_ITEMS
            return {self._text(str(k), MAX_NAME, "attribute names"): self.value(v, depth + 1)
                    for k, v in items[:MAX_ITEMS]}
        if isinstance(value, (list, tuple)):
            if len(value) > MAX_ITEMS:
                self.cut[f"list items beyond {MAX_ITEMS} dropped"] += len(value) - MAX_ITEMS
            return [self.value(v, depth + 1) for v in value[:MAX_ITEMS]]
        return self.value(str(value), depth)           # numpy scalars are converted by the readers

    def _text(self, text: str, limit: int, what: str) -> str:
        cleaned = clean_text(text)
        if cleaned != text:
            self.cut["characters that are not UTF-8 replaced by U+FFFD"] += 1
        if len(cleaned) > limit:
            self.cut[f"{what} cut to {limit} characters"] += 1
            cleaned = cleaned[:limit - 1] + "…"          # ``limit`` long: bounding again changes nothing
        return cleaned

    def warn(self, stacklevel: int = 2) -> None:
        """One warning naming the file and everything cut, when anything was."""
        if self.cut:
            what = "; ".join(f"{issue} ({n}x)" for issue, n in sorted(self.cut.items()))
            warnings.warn(f"{self.where}: object attributes bounded: {what}", stacklevel=stacklevel + 1)
            self.cut.clear()
