"""Textures on oblique views against the exact area average (pipeline25d_lab.scenes.textured_slope).

A plane with detail at every scale (random cosines in every octave plus fine gratings) is rendered at
30° elevation by the pipeline's renderer and compared with each pixel's exact mean of the texture over
its footprint, computed without GL. Mean error bounds the blur and the bias; the spurious share of
low-frequency energy (energy below 1/8 cycle per pixel that the reference lacks, with any per-frequency
attenuation allowed, since blur is not moiré) bounds the moiré.
"""

from __future__ import annotations

import numpy as np
import pytest

from pipeline25d.geometry.perspectives import Perspective
from pipeline25d.stages.render import TileRenderer, TileView
from pipeline25d.stages.textures import mip_levels, texture_anisotropy
from pipeline25d_lab.scenes.textured_slope import Slope, area_average, centred_extent, cosine_texture, depth_range

GSD, SIZE = 0.25, 256
MOIRE_BOUND = 0.02


def spurious_share(image: np.ndarray, reference: np.ndarray, cut: float = 0.125) -> float:
    """sqrt of the share of ``reference``'s energy below ``cut`` cycles per pixel that ``image`` has
    beyond a per-frequency scaling in [0, 1] of the reference (what aliasing adds and blur cannot)."""
    f = np.fft.fftfreq(image.shape[0])
    radius = np.hypot(*np.meshgrid(f, np.fft.fftfreq(image.shape[1]), indexing="ij"))
    band = (radius > 0) & (radius < cut)
    got = np.fft.fft2(image, axes=(0, 1))
    ref = np.fft.fft2(reference, axes=(0, 1))
    gain = np.clip(np.real(got * np.conj(ref)) / np.maximum(np.abs(ref) ** 2, 1e-12), 0.0, 1.0)
    return float(np.sqrt((np.abs(got - gain * ref) ** 2)[band].sum() / (np.abs(ref) ** 2)[band].sum()))


def save_side_by_side(path, render: np.ndarray, reference: np.ndarray, crop: int = 128, zoom: int = 3) -> None:
    from PIL import Image

    pair = np.hstack([render[:crop, :crop, :3], np.clip(np.rint(reference[:crop, :crop]), 0, 255).astype(np.uint8)])
    Image.fromarray(pair).resize((pair.shape[1] * zoom, pair.shape[0] * zoom), Image.Resampling.NEAREST).save(path)


@pytest.mark.parametrize("case, slope, repeat, mae_bound", [
    ("flat", 0.0, 64.0, 1.0),         # 4 × 4 texels per pixel
    ("grazing", -0.433, 128.0, 3.5),  # 2 × 8 texels per pixel, the long axis 30° off the image's
])
def test_oblique_texture_matches_area_average(gl_ctx, tmp_path, case, slope, repeat, mae_bound):
    p = Perspective(30, 30)
    plane = Slope((691000.0, 5334000.0, 500.0), p, slope, repeat, 300.0)
    texture = cosine_texture(grating_weight=20.0, extra=plane.moire_gratings(GSD))
    extent = centred_extent(plane, GSD, (SIZE, SIZE))
    view = TileView(p, 0.0, extent, depth_range(plane), (SIZE, SIZE))
    reference = area_average(texture, plane, extent, (SIZE, SIZE))
    rgba = TileRenderer(gl_ctx).render_color([(np.array(plane.centre), [plane.part(texture.png())])], view)
    assert (rgba[..., 3] == 255).all()
    got = rgba[..., :3].astype(np.float64)
    diff = got - reference
    mae, bias = np.abs(diff).mean(), np.abs(diff.mean(axis=(0, 1))).max()
    moire = spurious_share(got, reference)
    save_side_by_side(tmp_path / f"{case}_render_vs_reference.png", rgba, reference)
    assert mae <= mae_bound, (case, mae)
    assert bias <= 0.25, (case, bias)               # mip levels are exact means: no brightening
    assert moire <= MOIRE_BOUND, (case, moire)
    # the measure sees moiré: the texture point-sampled at pixel centres (no filter at all) fails it
    point = area_average(texture, plane, extent, (SIZE, SIZE), footprint=False)
    assert spurious_share(point, reference) > 5 * MOIRE_BOUND


def test_mip_levels_are_unbiased_area_means():
    rng = np.random.default_rng(11)
    img = rng.integers(0, 256, (64, 128, 4), dtype=np.uint8)
    levels = mip_levels(img)
    assert [lv.shape[:2] for lv in levels] == [(64 >> k if k < 6 else 1, 128 >> k) for k in range(8)]
    for k, level in enumerate(levels[1:6], start=1):   # the mean only where it averages many texels
        exact = img.reshape(64 >> k, 1 << k, 128 >> k, 1 << k, 4).astype(np.float64).mean(axis=(1, 3))
        assert np.abs(level - exact).max() <= 1.0
        assert k > 3 or abs((level - exact).mean()) < 0.05   # glGenerateMipmap on llvmpipe: +0.5 per level
    odd = mip_levels(rng.integers(0, 256, (255, 100, 4), dtype=np.uint8))
    assert [lv.shape[:2] for lv in odd][:4] == [(255, 100), (127, 50), (63, 25), (31, 12)]
    assert abs(odd[1].mean() - odd[0].mean()) < 0.05


@pytest.mark.parametrize("shape", [(64, 128), (255, 100)])
def test_uploaded_texture_holds_each_exact_mip_level(gl_ctx, shape):
    """Every level GL holds is :func:`mip_levels`' own (read back from the texture), the chain complete
    down to 1 x 1: each defined by glTexImage2D, none computed by the driver."""
    import io

    from PIL import Image

    from pipeline25d.stages.textures import upload

    rng = np.random.default_rng(5)
    img = rng.integers(0, 256, (*shape, 4), dtype=np.uint8)
    img[..., 3] = 255
    png = io.BytesIO()
    Image.fromarray(img).save(png, format="PNG")
    tex = upload(gl_ctx, png.getvalue(), 1.0)
    levels = mip_levels(np.ascontiguousarray(img[::-1]))          # GL's order: row 0 at the bottom
    assert len(levels) == int(np.log2(max(shape))) + 1
    for k, level in enumerate(levels):
        assert np.array_equal(_level_of(tex, k, level.shape), level), k
    tex.release()


def _level_of(tex, k: int, shape: tuple) -> np.ndarray:
    """Level ``k`` of a GL texture by glGetTexImage (moderngl reads only the levels it made)."""
    import ctypes

    from pipeline25d.stages.textures import gl_function

    get = gl_function("glGetTexImage", ctypes.c_uint, ctypes.c_int, ctypes.c_uint, ctypes.c_uint, ctypes.c_void_p)
    pack = gl_function("glPixelStorei", ctypes.c_uint, ctypes.c_int)
    out = np.zeros(shape, np.uint8)
    tex.use(0)
    pack(0x0D05, 1)                                        # GL_PACK_ALIGNMENT
    get(0x0DE1, k, 0x1908, 0x1401, out.ctypes.data)        # GL_TEXTURE_2D, GL_RGBA, GL_UNSIGNED_BYTE
    return out


class _Ctx:
    def __init__(self, renderer: str, max_anisotropy: float):
        self.info, self.max_anisotropy = {"GL_RENDERER": renderer}, max_anisotropy


def test_anisotropy_on_gpus_off_on_software_rasterisers():
    assert texture_anisotropy(_Ctx("NVIDIA H100 80GB HBM3/PCIe/SSE2", 16.0)) == 16.0
    assert texture_anisotropy(_Ctx("llvmpipe (LLVM 15.0.6, 256 bits)", 16.0)) == 1.0
    assert texture_anisotropy(_Ctx("AMD Radeon", 0.0)) == 1.0


def test_texture_cache_uploads_once_and_trims_least_recent_between_tiles(gl_ctx):
    """Each image is uploaded once while held; :meth:`TextureCache.trim` releases the least recently
    used until the held bytes (RGBA and mip chain, 4/3 of level 0) fit the budget, never the ones
    a later ``get`` touched; an image released is uploaded again when asked for."""
    import io

    from PIL import Image

    from pipeline25d.stages.textures import TextureCache, texture_bytes

    def png(seed: int) -> bytes:
        out = io.BytesIO()
        Image.fromarray(np.full((64, 64, 3), seed, np.uint8)).save(out, format="PNG")
        return out.getvalue()

    images = [png(k) for k in range(5)]
    one = 64 * 64 * 4 * 4 // 3
    cache = TextureCache(gl_ctx, 1.0, budget=2 * one)
    texs = [cache.get(d) for d in images[:3]]
    assert cache.get(images[0]) is texs[0] and cache.uploads == 3       # held: not uploaded again
    assert cache.held_bytes == 3 * one == sum(texture_bytes(t) for t in texs)
    cache.trim()                                                         # over budget: 1 goes (0 was used last)
    assert cache.held_bytes == 2 * one
    assert cache.get(images[0]) is texs[0] and cache.get(images[2]) is texs[2] and cache.uploads == 3
    again = cache.get(images[1])                                         # released, so uploaded anew
    assert again is not texs[1] and cache.uploads == 4
    cache.trim()
    assert cache.held_bytes == 2 * one and cache.get(images[1]) is again and cache.uploads == 4
    assert cache.get(images[2]) is texs[2] and cache.uploads == 4
    assert cache.get(images[0]) is not texs[0] and cache.uploads == 5    # 0 was the least recent
