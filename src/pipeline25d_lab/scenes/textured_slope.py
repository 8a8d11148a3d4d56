"""A textured plane with detail at every scale, and its exact area-averaged image in any oblique view.

The texture is a sum of cosines per channel, ``F(u, v) = 127.5 + Σ a·cos(2π f·(u, v) + φ)``,
with integer frequencies f (cycles per texture repeat, so the pattern tiles seamlessly) spread
over every octave from 1 cycle to 0.4 cycles per texel, in random directions and phases (seeded).
Its texel image is F at the texel centres.

The plane is flat in a tilted 3D plane and every projection here is affine, so a map pixel's
footprint in texture space is a parallelogram with edges a and b (the pixel's columns of the
Jacobian of uv over pixel). The box average of one cosine over it is exact:
cos(2π f·uv_c + φ) · sinc(f·a) · sinc(f·b). :func:`area_average` sums those: the image a perfect
area-sampling sensor would record, computed without GL, texels or mipmaps.
"""

from __future__ import annotations

import io
import math
from dataclasses import dataclass

import numpy as np

from pipeline25d.core.grid import Extent
from pipeline25d.core.mesh import MeshPart
from pipeline25d.geometry.camera import horizontal_direction, map_affine
from pipeline25d.geometry.perspectives import Perspective


@dataclass(frozen=True)
class CosineTexture:
    """Per channel (3): frequencies (k, 2) int, amplitudes (k,), phases (k,); ``size`` texels square."""

    freqs: tuple[np.ndarray, ...]
    amps: tuple[np.ndarray, ...]
    phases: tuple[np.ndarray, ...]
    size: int

    def image(self) -> np.ndarray:
        """(size, size, 3) uint8, row 0 = the image's top (v = 1): :meth:`samples` rounded."""
        return np.clip(np.rint(self.samples()), 0, 255).astype(np.uint8)

    def samples(self) -> np.ndarray:
        """(size, size, 3) float64 values at the texel centres, row 0 = the image's top (v = 1).

        Every frequency is an integer, so the samples are one inverse FFT of a sparse spectrum: texel
        (row r, col c) sits at u = (c + ½)/n, v = 1 − (r + ½)/n, i.e. a phase of 2π(f_u c − f_v r)/n
        plus π(f_u − f_v)/n."""
        n = self.size
        out = []
        for i in range(3):
            f, amp, ph = self.freqs[i], self.amps[i], self.phases[i]
            spec = np.zeros((n, n), dtype=np.complex128)
            np.add.at(spec, ((-f[:, 1]) % n, f[:, 0] % n), amp * np.exp(1j * (ph + np.pi * (f[:, 0] - f[:, 1]) / n)))
            out.append(127.5 + np.real(np.fft.ifft2(spec)) * n * n)
        return np.stack(out, axis=-1)

    def png(self) -> bytes:
        from PIL import Image

        buf = io.BytesIO()
        Image.fromarray(self.image()).save(buf, format="PNG")
        return buf.getvalue()

    def channel(self, i: int, u: np.ndarray, v: np.ndarray, a: np.ndarray | None,
                 b: np.ndarray | None) -> np.ndarray:
        """Channel i at (u, v), box-averaged over the parallelogram of edges a, b (2,) when given."""
        out = np.full(u.shape, 127.5)
        for f, amp, ph in zip(self.freqs[i], self.amps[i], self.phases[i]):
            gain = amp if a is None else amp * np.sinc(f @ a) * np.sinc(f @ b)
            if abs(gain) > 1e-6:
                out += gain * np.cos(2 * np.pi * (f[0] * u + f[1] * v) + ph)
        return out


def cosine_texture(size: int = 1024, per_octave: int = 8, top: float = 0.4, tilt: float = 0.5,
                   gratings: int = 3, grating_weight: float = 6.0, peak: float = 120.0,
                   seed: int = 7, extra: np.ndarray | None = None) -> CosineTexture:
    """A texture with ``per_octave`` random cosines per octave up to ``top`` cycles per texel, amplitudes
    falling as |f|^-``tilt`` (detail at every scale, like a photograph's), plus ``gratings`` fine regular
    gratings (a fine checker's strongest terms) between 0.6 and 1 × ``top`` cycles per texel,
    ``grating_weight`` × the finest noise amplitude: the pattern that shows moiré where sampling aliases;
    ``extra``: (k, 2) integer frequencies of further such gratings (:meth:`Slope.moire_gratings`; those
    above ``top`` are left out).
    Scaled so that no texel strays more than ``peak`` from mid-grey (no clipping: values exact)."""
    rng = np.random.default_rng(seed)
    octaves = int(math.floor(math.log2(top * size)))
    freqs, amps, phases = [], [], []
    for _ in range(3):
        mag = np.concatenate([2.0 ** rng.uniform(0, octaves, octaves * per_octave),
                              rng.uniform(0.6, 1.0, gratings) * top * size])
        ang = rng.uniform(0, 2 * np.pi, mag.size)
        f = np.rint(np.column_stack([mag * np.cos(ang), mag * np.sin(ang)])).astype(np.int64)
        amp = np.hypot(f[:, 0], f[:, 1]) ** -tilt
        amp[len(f) - gratings:] = grating_weight * (top * size) ** -tilt
        if extra is not None:
            more = np.asarray(extra, dtype=np.int64).reshape(-1, 2)
            f = np.vstack([f, more[np.hypot(more[:, 0], more[:, 1]) <= top * size]])   # texels hold them
            amp = np.concatenate([amp, np.full(len(f) - len(amp), grating_weight * (top * size) ** -tilt)])
        keep = np.abs(f).sum(axis=1) > 0
        freqs.append(f[keep])
        amps.append(amp[keep])
        phases.append(rng.uniform(0, 2 * np.pi, len(f))[keep])
    tex = CosineTexture(tuple(freqs), tuple(amps), tuple(phases), size)
    swing = np.abs(tex.samples() - 127.5).max()
    return CosineTexture(tex.freqs, tuple(a * peak / swing for a in amps), tex.phases, size)


@dataclass(frozen=True)
class Slope:
    """A plane through ``centre`` rising ``slope`` m/m along the camera's horizontal direction d
    (negative: facing away, seen at a grazing angle), textured with uv = (x, y − centre) / repeat
    (texture axes on the world's, one repeat every ``repeat`` metres), ``half`` metres each way."""

    centre: tuple[float, float, float]
    perspective: Perspective
    slope: float
    repeat: float
    half: float

    def uv_of(self, xy: np.ndarray) -> np.ndarray:
        return (np.asarray(xy, dtype=np.float64) - np.asarray(self.centre[:2])) / self.repeat

    def z_of(self, xy: np.ndarray) -> np.ndarray:
        d = horizontal_direction(self.perspective)
        return self.centre[2] + self.slope * ((np.asarray(xy, dtype=np.float64) - self.centre[:2]) @ d)

    def part(self, texture: bytes) -> MeshPart:
        """Two triangles, the texture repeating over them."""
        cx, cy, _ = self.centre
        h = self.half
        xy = np.array([[cx - h, cy - h], [cx + h, cy - h], [cx + h, cy + h], [cx - h, cy + h]])
        verts = np.column_stack([xy, self.z_of(xy)])
        return MeshPart(verts, np.array([[0, 1, 2], [0, 2, 3]]), uv=self.uv_of(xy), texture=texture, name="slope")

    def map_to_uv(self) -> tuple[np.ndarray, np.ndarray]:
        """(J, t): uv = J @ (map_x, map_y) + t, the inverse of the plane's map-aligned projection."""
        A, b = map_affine(self.perspective, 0.0)
        d = horizontal_direction(self.perspective)
        # world (x, y) -> map: (x, y) + (z(x, y)) cot φ d, z affine in (x, y)
        grad = self.slope * d                                   # dz / d(x, y)
        M = np.eye(2) + np.outer(A[:2, 2], grad)
        m0 = np.asarray(self.centre[:2]) + A[:2, 2] * self.centre[2] + b[:2]   # map of the centre
        minv = np.linalg.inv(M) / self.repeat
        return minv, -minv @ m0

    def moire_gratings(self, pixel: float, orders: tuple[int, ...] = (1, 2, 3),
                       offset: float = 0.06) -> np.ndarray:
        """(k, 2) integer texture frequencies (cycles per repeat) of gratings whose images run along the
        camera's direction at ``order`` + ``offset`` cycles per pixel: point sampling turns each into a
        broad band ``offset`` cycles per pixel apart (moiré); an area average nearly removes it."""
        J, _ = self.map_to_uv()
        jac = np.column_stack([J[:, 0] * pixel, -J[:, 1] * pixel])      # uv per (col, row)
        d = horizontal_direction(self.perspective)
        along = np.array([d[0], -d[1]])                                  # the direction in (col, row)
        wanted = np.array([(n + offset) * along for n in orders])        # cycles per pixel
        return np.rint(wanted @ np.linalg.inv(jac)).astype(np.int64)     # f with jac.T @ f = wanted

    def texels_per_pixel(self, pixel: float, texels: int) -> tuple[float, float]:
        """(least, most) texels a pixel's footprint spans: its singular values in texel units."""
        J, _ = self.map_to_uv()
        s = np.linalg.svd(J * pixel * texels, compute_uv=False)
        return float(s.min()), float(s.max())


def area_average(texture: CosineTexture, slope: Slope, extent: Extent, size: tuple[int, int],
                 footprint: bool = True) -> np.ndarray:
    """(h, w, 3) float64: each pixel of the north-up ``extent`` the exact mean of the texture over its
    footprint on the slope (row 0 = north); ``footprint`` False: the texture at the pixel's centre
    (point sampling, what no filter at all gives)."""
    w, h = size
    px, py = extent.width / w, extent.height / h
    J, t = slope.map_to_uv()
    mx = extent.xmin + (np.arange(w) + 0.5) * px
    my = extent.ymax - (np.arange(h) + 0.5) * py
    gx, gy = np.meshgrid(mx, my)
    u = J[0, 0] * gx + J[0, 1] * gy + t[0]
    v = J[1, 0] * gx + J[1, 1] * gy + t[1]
    a, b = J[:, 0] * px, J[:, 1] * -py                          # the footprint's edges in uv
    if not footprint:
        a = b = None
    return np.stack([texture.channel(i, u, v, a, b) for i in range(3)], axis=-1)


def depth_range(slope: Slope, margin: float = 1.0) -> tuple[float, float]:
    """The view depths the slope's corners span, widened by ``margin`` metres."""
    from pipeline25d.geometry.camera import project

    verts = slope.part(b"x").vertices
    d = project(verts, slope.perspective, 0.0)[:, 2]
    return float(d.min() - margin), float(d.max() + margin)


def centred_extent(slope: Slope, pixel: float, size: tuple[int, int]) -> Extent:
    """The north-up map extent of ``size`` pixels of ``pixel`` metres centred on the slope's centre's image."""
    A, _ = map_affine(slope.perspective, 0.0)
    mx, my = (A @ np.asarray(slope.centre, dtype=np.float64))[:2]
    hw, hh = size[0] * pixel / 2, size[1] * pixel / 2
    return Extent(mx - hw, my - hh, mx + hw, my + hh)
