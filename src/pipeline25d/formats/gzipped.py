"""Files stored gzipped, read as their content.

3D Tiles tilesets are often kept on disk as their server sends them with ``Content-Encoding:
gzip`` (3d-tiles-tools' ``gzip``, older Cesium exports): every JSON, tile, subtree, buffer and
image, or the tiles alone. A browser decompresses them unseen, so the dataset is what its own
ecosystem reads; here any such file is recognised by gzip's magic bytes and decompressed
whole, at most :data:`MAX_BYTES` (a file that decompresses beyond that, a gzip bomb, is an
error naming it).
"""

from __future__ import annotations

import zlib
from pathlib import Path

from pipeline25d.core.errors import InputFileError

MAGIC = b"\x1f\x8b"
#: the most one gzipped file may decompress to (a 3D Tiles content is a few MB; 1 GiB is none)
MAX_BYTES = 1 << 30


def file_bytes(path: Path) -> bytes:
    """The bytes of ``path``, decompressed where the file is gzip (OSError as ``Path.read_bytes``)."""
    return gunzipped(path.read_bytes(), path)


def gunzipped(data: bytes, path: Path, limit: int = MAX_BYTES) -> bytes:
    """``data`` decompressed where it is gzip (as is otherwise); InputFileError naming ``path`` for
    a corrupt or cut-short stream or one that decompresses to more than ``limit`` bytes."""
    if data[:2] != MAGIC:
        return data
    d = zlib.decompressobj(16 + zlib.MAX_WBITS)
    try:
        out = d.decompress(data, limit)
    except zlib.error as exc:
        raise InputFileError(path, f"gzip data is corrupt: {exc}") from None
    if d.unconsumed_tail:
        raise InputFileError(path, f"gzip data decompresses to more than {limit:,} bytes (a gzip bomb?)")
    if not d.eof:
        raise InputFileError(path, "gzip data is cut short (truncated)")
    return out
