"""Numeric object ids: what an id raster stores for each input object, stable from run to run.

An id is a uint32 ``slot << LOCAL_BITS | local``: ``slot`` is the district's (of :data:`SLOTS`),
``local`` the object's within its district, both from the CRC-32 of their names with linear probing
in sorted order, so that an id changes only when its own district or object does (or, rarely,
when a newcomer takes its hash first). 0 is no object. Faces that carry no input object (a mesh
file's parts, an OSGB tile's) belong to the object their part is named after
(:meth:`pipeline25d.core.mesh.MeshPart.named`): ground is an object too.
"""

from __future__ import annotations

import zlib
from collections.abc import Iterable

from pipeline25d.core.errors import InputFileError

LOCAL_BITS = 22
SLOTS = 1 << (32 - LOCAL_BITS)          # 1024 districts
LOCAL = (1 << LOCAL_BITS) - 1           # 4,194,303 objects per district


def _probe(names: Iterable[str], size: int, skip_zero: bool) -> dict[str, int]:
    """name -> its CRC-32 modulo ``size``, the next free value on a collision (names in sorted order)."""
    taken: set[int] = set()
    out = {}
    for name in sorted(set(names)):
        h = zlib.crc32(name.encode("utf-8", "surrogatepass")) % size     # a JSON key may hold a lone surrogate
        while h in taken or (skip_zero and h == 0):
            h = (h + 1) % size
        taken.add(h)
        out[name] = h
    return out


def district_slots(districts: Iterable[str]) -> dict[str, int]:
    """The id slot of every district of a config."""
    names = sorted(set(districts))
    if len(names) > SLOTS:
        raise ValueError(f"{len(names)} districts; object ids hold at most {SLOTS}")
    return _probe(names, SLOTS, skip_zero=False)


def object_ids(keys: Iterable[str], slot: int, where: str) -> dict[str, int]:
    """key -> uint32 id of every object of one district (``where`` names it in the error)."""
    keys = set(keys)
    if len(keys) > LOCAL:
        raise InputFileError(where, f"holds {len(keys)} objects; object ids hold at most {LOCAL} per district "
                                    "(split it into several inputs)")
    return {key: slot << LOCAL_BITS | local for key, local in _probe(keys, LOCAL + 1, skip_zero=True).items()}

