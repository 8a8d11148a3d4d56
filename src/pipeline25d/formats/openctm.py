"""OpenCTM meshes (RAW, MG1, MG2), decoded from bytes by libopenctm (Debian ``libopenctm1``) through ctypes.

The library does the decoding; this module only hands it the bytes (``ctmLoadCustom`` with a read
callback) and copies out vertices, triangles and the first UV map. An error the library reports,
indices past the vertices or non-finite coordinates are :class:`CtmError`; the caller names the file.
"""

from __future__ import annotations

import ctypes
import ctypes.util
from functools import lru_cache
from typing import NamedTuple

import numpy as np

CTM_IMPORT = 0x0101
CTM_NONE = 0x0000
CTM_VERTEX_COUNT, CTM_TRIANGLE_COUNT, CTM_UV_MAP_COUNT = 0x0301, 0x0302, 0x0304
CTM_INDICES, CTM_VERTICES, CTM_UV_MAP_1 = 0x0601, 0x0602, 0x0700
_READ = ctypes.CFUNCTYPE(ctypes.c_uint32, ctypes.c_void_p, ctypes.c_uint32, ctypes.c_void_p)


class CtmError(ValueError):
    """Why an OpenCTM mesh cannot be read."""


class CtmMesh(NamedTuple):
    """Vertices (n, 3) float64, triangles (m, 3) int64 and the first UV map (n, 2) float32 or None."""

    vertices: np.ndarray
    faces: np.ndarray
    uv: np.ndarray | None


@lru_cache(maxsize=1)
def _library() -> ctypes.CDLL:
    name = ctypes.util.find_library("openctm")
    if name is None:
        raise CtmError("libopenctm is not installed (Debian: apt install libopenctm1; `make deps` does)")
    lib = ctypes.CDLL(name)
    lib.ctmNewContext.argtypes, lib.ctmNewContext.restype = [ctypes.c_uint32], ctypes.c_void_p
    lib.ctmFreeContext.argtypes = [ctypes.c_void_p]
    lib.ctmGetError.argtypes, lib.ctmGetError.restype = [ctypes.c_void_p], ctypes.c_uint32
    lib.ctmErrorString.argtypes, lib.ctmErrorString.restype = [ctypes.c_uint32], ctypes.c_char_p
    lib.ctmGetInteger.argtypes, lib.ctmGetInteger.restype = [ctypes.c_void_p, ctypes.c_uint32], ctypes.c_uint32
    lib.ctmGetIntegerArray.argtypes = [ctypes.c_void_p, ctypes.c_uint32]
    lib.ctmGetIntegerArray.restype = ctypes.POINTER(ctypes.c_uint32)
    lib.ctmGetFloatArray.argtypes = [ctypes.c_void_p, ctypes.c_uint32]
    lib.ctmGetFloatArray.restype = ctypes.POINTER(ctypes.c_float)
    lib.ctmLoadCustom.argtypes = [ctypes.c_void_p, _READ, ctypes.c_void_p]
    return lib


def decode_ctm(data: bytes) -> CtmMesh:
    """The mesh an OpenCTM file's bytes hold (:class:`CtmMesh`)."""
    lib = _library()
    view = memoryview(data)
    at = 0

    @_READ
    def read(buf, count, _user):
        nonlocal at
        n = min(int(count), len(view) - at)
        ctypes.memmove(buf, bytes(view[at:at + n]), n)
        at += n
        return n

    ctx = lib.ctmNewContext(CTM_IMPORT)
    if not ctx:
        raise CtmError("libopenctm could not make a context")
    try:
        lib.ctmLoadCustom(ctx, read, 1)       # user data: never NULL (libopenctm 1.0.3 reads nothing then)
        if (err := lib.ctmGetError(ctx)) != CTM_NONE:
            raise CtmError(f"OpenCTM: {lib.ctmErrorString(err).decode(errors='replace')}")
        nv, nt = lib.ctmGetInteger(ctx, CTM_VERTEX_COUNT), lib.ctmGetInteger(ctx, CTM_TRIANGLE_COUNT)
        vertices = _copy(lib.ctmGetFloatArray(ctx, CTM_VERTICES), nv * 3).astype(np.float64).reshape(-1, 3)
        faces = _copy(lib.ctmGetIntegerArray(ctx, CTM_INDICES), nt * 3).astype(np.int64).reshape(-1, 3)
        uv = None
        if lib.ctmGetInteger(ctx, CTM_UV_MAP_COUNT) > 0:
            uv = _copy(lib.ctmGetFloatArray(ctx, CTM_UV_MAP_1), nv * 2).reshape(-1, 2)
    finally:
        lib.ctmFreeContext(ctx)
    if len(faces) and (faces.max() >= len(vertices) or faces.min() < 0):
        raise CtmError(f"a triangle names vertex {int(faces.max())} of {len(vertices)}")
    if not np.isfinite(vertices).all():
        raise CtmError("non-finite vertex coordinates")
    return CtmMesh(vertices, faces, uv)


def _copy(pointer, n: int) -> np.ndarray:
    """A copy of ``n`` items the library owns (freed with its context)."""
    if n == 0:
        return np.zeros(0, np.float32)
    if not pointer:
        raise CtmError("the mesh's arrays are missing")
    return np.ctypeslib.as_array(pointer, shape=(n,)).copy()
