"""Buffer views compressed by ``EXT_meshopt_compression`` or ``KHR_meshopt_compression``.

gltfpack (``-c``, ``-cc``) and glTF-Transform's ``optimize`` write them: each buffer view's data
is a meshoptimizer bitstream in another buffer, decoded here with meshoptimizer's own Python
package into the bytes the view describes, which the accessors then read as usual. The
view's own buffer may be a placeholder without data (a *fallback* buffer).

The checks are the extension's validity rules, made before anything is allocated: a hostile
``count`` cannot ask for more memory than the compressed bytes can hold (an attribute stream
stores at most :data:`MAX_EXPANSION` bytes per compressed byte).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline25d.core.errors import InputFileError, UnsupportedFeatureError

#: the two names of the extension: the vendor one (EXT) and Khronos's (KHR, which adds version 1
#: of the attribute codec and a COLOR filter)
EXTENSIONS = ("EXT_meshopt_compression", "KHR_meshopt_compression")
MODES = ("ATTRIBUTES", "TRIANGLES", "INDICES")
FILTERS = ("NONE", "OCTAHEDRAL", "QUATERNION", "EXPONENTIAL", "COLOR")
#: the decoded bytes one compressed byte can hold at most: an attribute group of 16 equal bytes
#: costs 2 header bits, so a byte of headers stands for 64 bytes of data
MAX_EXPANSION = 64
_TAIL = 64             # the stream's header and tail block (the baseline element, padded to 32 bytes)


def compression_of(view: dict) -> tuple[str, dict] | None:
    """(extension name, its JSON) of a buffer view compressed by either extension, or None."""
    extensions = view.get("extensions") or {}
    for name in EXTENSIONS:
        if isinstance(extensions.get(name), dict):
            return name, extensions[name]
    return None


def is_fallback(buffer: dict) -> bool:
    """True for a buffer that only compressed views reference (its bytes need not exist)."""
    extensions = buffer.get("extensions") or {}
    return any(isinstance(extensions.get(n), dict) and extensions[n].get("fallback") for n in EXTENSIONS)


def decode_view(path: Path, index: int, view: dict, name: str, ext: dict, compressed: bytes) -> bytes:
    """The bytes of buffer view ``index`` (its JSON ``view``) from its ``name`` extension ``ext``
    and the ``compressed`` bytes that extension points at; InputFileError naming ``path`` and the
    view when the extension is invalid or the stream does not decode."""
    import meshoptimizer

    where = f"bufferView {index} ({name})"
    try:
        count, stride = int(ext["count"]), int(ext["byteStride"])
        mode, filt = str(ext["mode"]), str(ext.get("filter", "NONE"))
    except (KeyError, TypeError, ValueError):
        raise InputFileError(path, f"{where} lacks count, byteStride or mode") from None
    _check(path, where, view, count, stride, mode, filt, len(compressed))
    try:
        if mode == "ATTRIBUTES":
            out = meshoptimizer.decode_vertex_buffer(count, stride, compressed, dtype=np.dtype((np.void, stride)))
            return _filtered(meshoptimizer, filt, out.view(np.uint8), count, stride).tobytes()
        decode = meshoptimizer.decode_index_buffer if mode == "TRIANGLES" else meshoptimizer.decode_index_sequence
        indices = decode(count, 4, compressed)         # the stream does not depend on the index size
        return indices.astype("<u2" if stride == 2 else "<u4").tobytes()
    except (RuntimeError, ValueError) as exc:        # a stream that does not decode, or the package's limits
        raise InputFileError(path, f"{where} does not decode: {exc}") from None


def _check(path: Path, where: str, view: dict, count: int, stride: int, mode: str, filt: str,
           compressed: int) -> None:
    """The extension's validity rules, and the decoded size against what the stream can hold."""
    if mode not in MODES:
        raise InputFileError(path, f"{where}: unknown mode {mode!r} (one of {', '.join(MODES)})")
    if filt not in FILTERS:
        raise UnsupportedFeatureError(path, f"{where}: filter {filt!r} is not supported ({', '.join(FILTERS)} are)")
    if count < 0 or stride <= 0:
        raise InputFileError(path, f"{where}: count {count} and byteStride {stride} must be positive")
    if mode == "ATTRIBUTES" and (stride % 4 or stride > 256):
        raise InputFileError(path, f"{where}: an attribute byteStride must be a multiple of 4 up to 256, not {stride}")
    if mode != "ATTRIBUTES" and (stride not in (2, 4) or filt != "NONE"):
        raise InputFileError(path, f"{where}: indices take byteStride 2 or 4 and no filter")
    if mode == "TRIANGLES" and count % 3:
        raise InputFileError(path, f"{where}: {count} triangle indices are not a multiple of 3")
    needs = {"OCTAHEDRAL": (4, 8), "QUATERNION": (8,), "COLOR": (4, 8)}.get(filt)
    if needs and stride not in needs:
        raise InputFileError(path, f"{where}: filter {filt} takes byteStride {' or '.join(map(str, needs))}")
    if view.get("byteStride") is not None and int(view["byteStride"]) != stride:
        raise InputFileError(path, f"{where}: byteStride {stride} differs from the view's {view['byteStride']}")
    if int(view.get("byteLength", -1)) != count * stride:
        raise InputFileError(path, f"{where}: the view's byteLength {view.get('byteLength')} is not "
                                   f"count {count} x byteStride {stride}")
    if count * stride > MAX_EXPANSION * compressed + _TAIL:
        raise InputFileError(path, f"{where}: {count * stride} bytes cannot come from {compressed} compressed bytes")


def _filtered(meshoptimizer, filt: str, raw: np.ndarray, count: int, stride: int) -> np.ndarray:
    """The decoded attribute bytes after the extension's filter."""
    decode = {"OCTAHEDRAL": meshoptimizer.decode_filter_oct, "QUATERNION": meshoptimizer.decode_filter_quat,
              "EXPONENTIAL": meshoptimizer.decode_filter_exp, "COLOR": color_filter}.get(filt)
    return raw if decode is None else decode(raw, count, stride)


def color_filter(raw: np.ndarray, count: int, stride: int) -> np.ndarray:
    """KHR_meshopt_compression's COLOR filter (YCoCg to RGBA, 8- or 16-bit components), as its
    Appendix B writes it. meshoptimizer's Python package (its C library at 0.22) predates the
    filter, so it is done here, vectorised."""
    bits = 8 * stride // 4
    unsigned, signed = (np.uint8, np.int8) if bits == 8 else (np.dtype("<u2"), np.dtype("<i2"))
    y, _, _, alpha = raw.view(unsigned).reshape(count, 4).astype(np.int64).T
    co, cg = raw.view(signed).reshape(count, 4)[:, 1:3].astype(np.int64).T
    top = np.floor(np.log2(np.maximum(alpha, 1))).astype(np.int64)        # the alpha's most significant bit
    scale = (1 << (top + 1)) - 1
    a = alpha & (scale >> 1)
    a = (a << 1) | (a & 1)
    rgba = np.stack([y + co - cg, y + cg, y - co - cg, a], axis=1).astype(np.float64)
    largest = (1 << bits) - 1
    out = np.floor(rgba * (largest / scale.astype(np.float64))[:, None] + 0.5)   # round half away (>= 0)
    return np.clip(out, 0, largest).astype(unsigned).view(np.uint8).reshape(-1)
