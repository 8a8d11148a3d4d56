"""Model textures on the GPU: decoded once, mipmapped exactly, filtered as well as the driver allows.

Mipmaps are built here, not by ``glGenerateMipmap``: Mesa's (llvmpipe) rounds every level up by half
a grey level, so level k was k/2 levels too bright (measured: +0.50, +1.00, +1.51, +1.99 at levels
1-4 on uniform noise), and Pillow's BOX resize does the same. Each level here is the exact area mean
of the one above, rounded half to even (no bias); an odd side is reduced by area weights. Each level
is given to GL by ``glTexImage2D`` (moderngl writes only levels that exist, and allocating them with
``glGenerateMipmap`` computed every level for nothing: on llvmpipe it also drew, so it flushed the
tile being rendered whenever a texture was first used).

Anisotropic filtering (a footprint stretched along one axis, as on slopes seen at a grazing angle,
is averaged along its length instead of blurred across it) is on at the driver's maximum, except on
Mesa's software rasterisers (llvmpipe, softpipe), where it costs more than it gives. Measured on
llvmpipe (Mesa 22.3.6) against the exact area average (tests/test_texture_filter.py, 30° elevation):
4 × 4 texels per pixel, mean error 0.33 grey levels trilinear, 1.40 with anisotropy 16; a slope
stretched to 2 × 8 texels per pixel, 1.84 against 1.69 (spurious low-frequency share 0.010 against
0.005); one texel per pixel at nadir, exact (max 0) against a mean error of 44.6 (max 140).
"""

from __future__ import annotations

import ctypes
import functools
import io
from collections import OrderedDict

import numpy as np

SOFTWARE_RENDERERS = ("llvmpipe", "softpipe")


def texture_anisotropy(ctx) -> float:
    """The anisotropy limit textures are sampled with: 1 (off) on Mesa's software rasterisers or where
    the driver has no anisotropic filtering, else its maximum."""
    renderer = str(ctx.info.get("GL_RENDERER", "")).lower()
    if any(name in renderer for name in SOFTWARE_RENDERERS):
        return 1.0
    return max(1.0, float(ctx.max_anisotropy or 1.0))


def decode(data: bytes) -> np.ndarray:
    """(h, w, 4) uint8 RGBA of encoded image bytes, row 0 = the image's bottom (GL's order)."""
    from PIL import Image

    img = Image.open(io.BytesIO(data)).convert("RGBA")
    return np.ascontiguousarray(np.asarray(img)[::-1])


def mip_levels(level0: np.ndarray) -> list[np.ndarray]:
    """The mipmap chain of (h, w, c) uint8 ``level0``, itself first, down to 1 × 1 (GL's sizes:
    each side halved, rounded down, at least 1)."""
    levels = [level0]
    while max(levels[-1].shape[:2]) > 1:
        levels.append(_halve(levels[-1]))
    return levels


def _halve(img: np.ndarray) -> np.ndarray:
    """The next mip level: each axis longer than 1 reduced to half its length (rounded down)."""
    h, w = img.shape[:2]
    if h % 2 == 0 and w % 2 == 0:               # the usual case: 2 × 2 blocks in one pass
        total = (img[0::2, 0::2].astype(np.uint16) + img[1::2, 0::2] + img[0::2, 1::2] + img[1::2, 1::2])
        return _rounded(total, 2)
    out = img
    for axis, n in ((0, h), (1, w)):
        if n > 1:
            out = _area(out, axis, n // 2)
    return out


def _rounded(total: np.ndarray, shift: int) -> np.ndarray:
    """``total`` / 2**shift as uint8, rounded half to even (no bias over many texels)."""
    q = total >> shift
    r = total & ((1 << shift) - 1)
    half = 1 << (shift - 1)
    return (q + ((r > half) | ((r == half) & (q & 1).astype(bool)))).astype(np.uint8)


def _area(img: np.ndarray, axis: int, m: int) -> np.ndarray:
    """``img`` reduced to ``m`` texels along ``axis``, each the exact mean of the source span it covers."""
    n = img.shape[axis]
    moved = np.moveaxis(img, axis, 0).astype(np.float64)
    cum = np.concatenate([np.zeros((1,) + moved.shape[1:]), np.cumsum(moved, axis=0)])
    edges = np.arange(m + 1) * (n / m)
    whole = np.floor(edges).astype(np.int64)
    frac = (edges - whole)[(...,) + (None,) * (moved.ndim - 1)]
    nxt = np.minimum(whole + 1, n)
    at = cum[whole] + frac * (cum[nxt] - cum[whole])          # the integral up to each edge
    mean = (at[1:] - at[:-1]) / (n / m)
    return np.moveaxis(np.clip(np.rint(mean), 0, 255).astype(np.uint8), 0, axis)


def upload(ctx, data: bytes, anisotropy: float):
    """A repeating, trilinear (and, above 1, anisotropic) GL texture of encoded image bytes."""
    import moderngl

    levels = mip_levels(decode(data))
    h, w = levels[0].shape[:2]
    tex = ctx.texture((w, h), 4, levels[0].tobytes(), alignment=1)
    define = gl_function("glTexImage2D", ctypes.c_uint, ctypes.c_int, ctypes.c_int, ctypes.c_int, ctypes.c_int,
                         ctypes.c_int, ctypes.c_uint, ctypes.c_uint, ctypes.c_void_p)
    if define is None:        # no GL entry point: allocate the chain, then overwrite each level
        tex.build_mipmaps(0, len(levels) - 1)
        for k, level in enumerate(levels[1:], start=1):
            tex.write(level.tobytes(), level=k, alignment=1)
    else:
        tex.use(0)            # glTexImage2D defines a level of the texture bound to the active unit
        for k, level in enumerate(levels[1:], start=1):
            pixels = np.ascontiguousarray(level)
            define(GL_TEXTURE_2D, k, GL_RGBA8, pixels.shape[1], pixels.shape[0], 0, GL_RGBA, GL_UNSIGNED_BYTE,
                   pixels.ctypes.data)
    tex.repeat_x = tex.repeat_y = True
    tex.filter = (moderngl.LINEAR_MIPMAP_LINEAR, moderngl.LINEAR)
    tex.anisotropy = anisotropy
    return tex


class TextureCache:
    """GL textures of encoded images, each uploaded once and held until :meth:`trim` finds the held
    ones (RGBA and mip chain) over ``budget`` bytes and releases the least recently used.

    A render job's tiles lie side by side, so the textures one tile draws are mostly those of the
    tiles before it; trimming between tiles (never within one, which would upload a texture twice
    in a pass) bounds a job's memory by the budget plus one tile's textures, whatever the job's size.
    """

    def __init__(self, ctx, anisotropy: float, budget: int):
        self.ctx, self.anisotropy, self.budget = ctx, anisotropy, budget
        self._held: OrderedDict[bytes, object] = OrderedDict()
        self.held_bytes = 0
        self.uploads = 0

    def get(self, data: bytes):
        """The texture of ``data``, uploaded now unless held."""
        tex = self._held.get(data)
        if tex is not None:
            self._held.move_to_end(data)
            return tex
        tex = upload(self.ctx, data, self.anisotropy)
        self.uploads += 1
        self._held[data] = tex
        self.held_bytes += texture_bytes(tex)
        return tex

    def trim(self) -> None:
        """Release the least recently used textures until those held fit the budget."""
        while self.held_bytes > self.budget and self._held:
            _, old = self._held.popitem(last=False)
            self.held_bytes -= texture_bytes(old)
            old.release()


def texture_bytes(tex) -> int:
    """Bytes an RGBA8 texture and its mip chain hold (4/3 of level 0)."""
    return tex.width * tex.height * 4 * 4 // 3


GL_TEXTURE_2D, GL_RGBA8, GL_RGBA, GL_UNSIGNED_BYTE = 0x0DE1, 0x8058, 0x1908, 0x1401


@functools.cache
def gl_function(name: str, *argtypes):
    """The GL entry point ``name`` (returning nothing, taking ``argtypes``) of the current EGL context's
    driver (EGL hands out core entry points: EGL_KHR_get_all_proc_addresses, which Mesa and NVIDIA
    have), or None without libEGL or that entry point."""
    try:
        egl = ctypes.CDLL("libEGL.so.1")
    except OSError:
        return None
    egl.eglGetProcAddress.restype = ctypes.c_void_p
    egl.eglGetProcAddress.argtypes = [ctypes.c_char_p]
    address = egl.eglGetProcAddress(name.encode())
    return ctypes.CFUNCTYPE(None, *argtypes)(address) if address else None
