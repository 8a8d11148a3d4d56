"""The content of the generated OAP3D city (:mod:`pipeline25d_lab.scenes.oap3d`): layout, surface, texture.

A seeded street grid (blocks 70-130 m, streets 12 m) whose blocks are split into lots holding
box buildings (flat roofs with parapets and rooftop units, or gable roofs with tile rows) on
gently rolling ground. Everything is a function of world position (metres relative to
SRSOrigin), so every level of detail and both output formats sample the same city:

* :meth:`City.height` samples the surface on a grid (the mesh of a node);
* :meth:`City.paint` rasterises the texture at texel centres, band-limited to the texel: the
  multi-octave noise keeps only octaves of wavelength >= 3 texels, and every sharp feature
  (road markings, roof edges, tile rows, kerbs) is drawn with its exact box-filtered coverage.
  A coarser level is thus a properly filtered version of a finer one, and a blur, a seam,
  aliasing or a wrong mip level shows against it.

The noise is a sum of separable terms f(x)·g(y) per octave (smooth 1D value noise), evaluated
as one matrix product per image: cheap enough for billions of texels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

STREET = 12.0            # street width, m (kerb to kerb)
SIDEWALK = 3.0           # sidewalk inside each block edge, m
LONGEST = 256.0          # wavelength of the first noise octave, m
TERMS = 3                # separable terms per octave
ASPHALT, SIDEWALK_RGB, MARK = (68, 70, 74), (150, 147, 140), (235, 235, 225)
GROUNDS = ((88, 118, 58), (128, 118, 102), (104, 110, 80))
ROOFS = ((160, 82, 62), (82, 86, 96), (172, 170, 164), (62, 62, 64), (84, 112, 72), (190, 160, 120))
#: building columns: x0, y0, x1, y1, height above base, base z, roof (0 flat, 1 ridge along x, 2 along y), colour
B_X0, B_Y0, B_X1, B_Y1, B_H, B_BASE, B_ROOF, B_COLOUR = range(8)


def ground(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Ground height (m) at x, y (broadcast): rolling, a few metres over kilometres."""
    return 4.0 * np.sin(2 * np.pi * x / 1500.0 + 1.0) + 3.0 * np.sin(2 * np.pi * y / 1100.0) + 8.0


@dataclass(frozen=True)
class City:
    """A seeded city over [0, width] x [0, depth] (metres relative to SRSOrigin)."""

    width: float
    depth: float
    seed: int
    streets_x: np.ndarray     # centre lines of the north-south streets
    streets_y: np.ndarray     # centre lines of the east-west streets
    lots: np.ndarray          # (n, 5): x0, y0, x1, y1, ground colour index (block interiors)
    buildings: np.ndarray     # (n, 8): see the B_* columns
    units: np.ndarray         # (n, 4): rooftop units x0, y0, x1, y1 (on flat roofs)
    noise: tuple[np.ndarray, ...]   # per octave: (2, TERMS, lattice) random values for x and y

    # ---------------------------------------------------------------- geometry

    def height(self, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
        """Surface height on the grid xs (columns) x ys (rows), float64 (len(ys), len(xs))."""
        z = ground(xs[None, :], ys[:, None]) + np.zeros((len(ys), len(xs)))
        for b in self._touching(self.buildings, xs, ys, 0.0):
            i0, i1 = np.searchsorted(xs, b[B_X0], side="left"), np.searchsorted(xs, b[B_X1], side="right")
            j0, j1 = np.searchsorted(ys, b[B_Y0], side="left"), np.searchsorted(ys, b[B_Y1], side="right")
            if i1 <= i0 or j1 <= j0:
                continue
            top = b[B_BASE] + b[B_H] + np.zeros((j1 - j0, i1 - i0))
            if b[B_ROOF] == 1:      # ridge along x: falls towards the y edges
                half = (b[B_Y1] - b[B_Y0]) / 2
                top -= _pitch(half) * np.abs(ys[j0:j1, None] - (b[B_Y0] + half)) / half
            elif b[B_ROOF] == 2:
                half = (b[B_X1] - b[B_X0]) / 2
                top -= _pitch(half) * np.abs(xs[None, i0:i1] - (b[B_X0] + half)) / half
            z[j0:j1, i0:i1] = np.maximum(z[j0:j1, i0:i1], top)
        return z

    # ---------------------------------------------------------------- texture

    def paint(self, xs: np.ndarray, ys: np.ndarray, texel: float) -> np.ndarray:
        """RGB float32 (len(ys), len(xs), 3) at texel centres xs, ys (ascending) of size ``texel``."""
        img = np.empty((len(ys), len(xs), 3), np.float32)
        img[:] = ASPHALT
        for x0, y0, x1, y1, c in self._touching(self.lots, xs, ys, texel):
            _rect(img, xs, ys, texel, (x0 - SIDEWALK, y0 - SIDEWALK, x1 + SIDEWALK, y1 + SIDEWALK), SIDEWALK_RGB)
            _rect(img, xs, ys, texel, (x0, y0, x1, y1), GROUNDS[int(c)])
        lum, tint = self._noise(xs, ys, texel)
        img *= np.maximum(0.25, 1.0 + 0.7 * lum)[..., None]
        img[..., 0] *= 1.0 + 0.06 * tint
        img[..., 2] *= 1.0 - 0.06 * tint
        self._markings(img, xs, ys, texel)
        for b in self._touching(self.buildings, xs, ys, texel):
            self._roof(img, xs, ys, texel, b, lum)
        for u in self._touching(self.units, xs, ys, texel):
            _rect(img, xs, ys, texel, tuple(u[:4]), (200, 202, 205))
            _rect(img, xs, ys, texel, (u[0] + 0.2, u[1] + 0.2, u[2] - 0.2, u[3] - 0.2), (120, 124, 130))
        return np.clip(img, 0, 255, out=img)

    def _roof(self, img, xs, ys, texel, b, lum) -> None:
        colour = np.asarray(ROOFS[int(b[B_COLOUR])], np.float32)
        x0, y0, x1, y1 = b[:4]
        if b[B_ROOF] == 0:      # parapet, then the roof inside it
            _rect(img, xs, ys, texel, (x0, y0, x1, y1), colour * 0.45)
            _rect(img, xs, ys, texel, (x0 + 0.4, y0 + 0.4, x1 - 0.4, y1 - 0.4), colour, lum, 0.2)
            return
        along_x = b[B_ROOF] == 1
        mid = (y0 + y1) / 2 if along_x else (x0 + x1) / 2
        halves = ((x0, y0, x1, mid), (x0, mid, x1, y1)) if along_x else ((x0, y0, mid, y1), (mid, y0, x1, y1))
        for k, half in enumerate(halves):      # the two slopes lit differently, tile rows across the slope
            _rect(img, xs, ys, texel, half, colour * (1.0 if k else 0.78), lum, 0.2,
                  stripes=(0.35, 0.3, "y" if along_x else "x", -0.35))
        _rect(img, xs, ys, texel, (x0, mid - 0.15, x1, mid + 0.15) if along_x else (mid - 0.15, y0, mid + 0.15, y1),
              colour * 0.5)

    def _markings(self, img, xs, ys, texel) -> None:
        """Kerb edge lines, dashed centre lines and crosswalks of every street through the image."""
        for axis, centres in (("y", self.streets_x), ("x", self.streets_y)):
            across = xs if axis == "y" else ys
            lo, hi = across[0] - texel, across[-1] + texel
            for c in centres[(centres > lo - STREET) & (centres < hi + STREET)]:
                for off in (-STREET / 2 + 0.5, STREET / 2 - 0.62):
                    _band(img, xs, ys, texel, axis, c + off, c + off + 0.12, MARK)
                _band(img, xs, ys, texel, axis, c - 0.08, c + 0.08, MARK, stripes=(8.0, 3.0 / 8.0, axis, 1.0))
                others = self.streets_y if axis == "y" else self.streets_x
                for o in others:      # crosswalk bands beside each crossing
                    for s in (-1, 1):
                        a, b = o + s * (STREET / 2 + 1.0), o + s * (STREET / 2 + 4.0)
                        box = (c - STREET / 2, min(a, b), c + STREET / 2, max(a, b))
                        box = box if axis == "y" else (box[1], box[0], box[3], box[2])
                        _rect(img, xs, ys, texel, box, MARK, stripes=(1.0, 0.5, "x" if axis == "y" else "y", 1.0))

    def _noise(self, xs, ys, texel) -> tuple[np.ndarray, np.ndarray]:
        """(luminance, tint) noise in about [-1, 1]: octaves of wavelength >= 3 texels only."""
        fx, fy = [], []
        for o, table in enumerate(self.noise):
            wave = LONGEST / 2 ** o
            if wave < 3 * texel:
                break
            amp = (wave / LONGEST) ** 0.12 / np.sqrt(TERMS)
            fx.append(amp * _value_noise(table[0], xs / wave))
            fy.append(_value_noise(table[1], ys / wave))
        if not fx:
            zeros = np.zeros((len(ys), len(xs)), np.float32)
            return zeros, zeros
        gx, gy = np.concatenate(fx).astype(np.float32), np.concatenate(fy).astype(np.float32)
        lum = gy.T @ gx * (1.6 / len(fx) ** 0.5)
        tint = gy[::-1].T @ gx
        return lum, tint * (1.0 / max(1.0, np.abs(tint).max()))

    @staticmethod
    def _touching(rows: np.ndarray, xs: np.ndarray, ys: np.ndarray, pad: float) -> np.ndarray:
        """The rows (x0, y0, x1, y1 first) whose box meets the grid's extent."""
        if not len(rows):
            return rows
        hit = ((rows[:, 0] <= xs[-1] + pad) & (rows[:, 2] >= xs[0] - pad)
               & (rows[:, 1] <= ys[-1] + pad) & (rows[:, 3] >= ys[0] - pad))
        return rows[hit]


def _pitch(half: float) -> float:
    return min(0.5 * half, 5.0)


def _value_noise(table: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(TERMS, len(t)) smooth 1D value noise of lattice ``table`` (TERMS, n) at lattice coordinates t."""
    i = np.floor(t).astype(np.int64)
    f = t - i
    f = f * f * (3 - 2 * f)
    i %= table.shape[1] - 1
    return table[:, i] * (1 - f) + table[:, i + 1] * f


def _cover(c: np.ndarray, texel: float, a: float, b: float) -> np.ndarray:
    """Share of each texel (centres c, width texel) inside [a, b]."""
    return np.clip((np.minimum(c + texel / 2, b) - np.maximum(c - texel / 2, a)) / texel, 0.0, 1.0)


def _square_integral(u: np.ndarray, period: float, duty: float) -> np.ndarray:
    """Integral from 0 of a square wave (1 on the first ``duty`` share of each period)."""
    on = duty * period
    return np.floor(u / period) * on + np.minimum(np.mod(u, period), on)


def _stripe_cover(c: np.ndarray, texel: float, period: float, duty: float) -> np.ndarray:
    return (_square_integral(c + texel / 2, period, duty) - _square_integral(c - texel / 2, period, duty)) / texel


def _rect(img, xs, ys, texel, box, colour, lum=None, lum_weight=0.0, stripes=None) -> None:
    """Blend ``colour`` over the box (x0, y0, x1, y1) by exact texel coverage; ``stripes``
    (period, duty, axis, weight): rows across ``axis``, darkening the colour by ``-weight`` (< 0) or
    gating the coverage (1: dashes, crosswalk bars); ``lum`` adds that share of the noise."""
    x0, y0, x1, y1 = box
    if x1 <= x0 or y1 <= y0:
        return
    i0, i1 = np.searchsorted(xs, x0 - texel / 2), np.searchsorted(xs, x1 + texel / 2)
    j0, j1 = np.searchsorted(ys, y0 - texel / 2), np.searchsorted(ys, y1 + texel / 2)
    if i1 <= i0 or j1 <= j0:
        return
    cx, cy = _cover(xs[i0:i1], texel, x0, x1), _cover(ys[j0:j1], texel, y0, y1)
    cov = (cy[:, None] * cx[None, :]).astype(np.float32)
    col = np.broadcast_to(np.asarray(colour, np.float32), cov.shape + (3,)).copy()
    if stripes is not None:
        period, duty, axis, weight = stripes
        s = _stripe_cover(ys[j0:j1] if axis == "y" else xs[i0:i1], texel, period, duty).astype(np.float32)
        s = s[:, None] if axis == "y" else s[None, :]
        if weight > 0:
            cov *= s
        else:
            col *= (1.0 + weight * s)[..., None]
    if lum is not None:
        col *= (1.0 + lum_weight * lum[j0:j1, i0:i1])[..., None]
    view = img[j0:j1, i0:i1]
    view += (col - view) * cov[..., None]


def _band(img, xs, ys, texel, axis, a, b, colour, stripes=None) -> None:
    """A band a..b across ``axis``'s normal running the image's whole length along ``axis``."""
    big = 1e9
    box = (a, -big, b, big) if axis == "y" else (-big, a, big, b)
    _rect(img, xs, ys, texel, box, colour, stripes=stripes)


def build_city(width: float, depth: float, seed: int) -> City:
    """The seeded layout over [0, width] x [0, depth]."""
    rng = np.random.default_rng(seed)
    streets = [np.cumsum(rng.uniform(70, 130, int(extent / 70) + 3)) - 60.0 for extent in (width, depth)]
    lots, buildings, units = [], [], []
    for xa, xb in zip(streets[0][:-1], streets[0][1:]):
        for ya, yb in zip(streets[1][:-1], streets[1][1:]):
            inset = STREET / 2 + SIDEWALK
            bx0, bx1, by0, by1 = xa + inset, xb - inset, ya + inset, yb - inset
            lots.append((bx0, by0, bx1, by1, rng.integers(len(GROUNDS))))
            rows = 2 if by1 - by0 > 50 else 1
            cuts = np.concatenate([[bx0], np.cumsum(rng.uniform(12, 30, 12)) + bx0])
            cuts = np.append(cuts[cuts < bx1 - 12], bx1)
            for r in range(rows):
                ly0 = by0 + r * (by1 - by0) / rows
                ly1 = ly0 + (by1 - by0) / rows
                for lx0, lx1 in zip(cuts[:-1], cuts[1:]):
                    if rng.random() < 0.15:
                        continue          # a yard
                    s = rng.uniform(1.5, 4.0, 4)
                    box = (lx0 + s[0], ly0 + s[1], lx1 - s[2], ly1 - s[3])
                    if box[2] - box[0] < 6 or box[3] - box[1] < 6:
                        continue
                    roof = int(rng.choice(3, p=(0.55, 0.225, 0.225)))
                    base = float(ground((box[0] + box[2]) / 2, (box[1] + box[3]) / 2))
                    buildings.append((*box, rng.uniform(6, 45), base, roof, rng.integers(len(ROOFS))))
                    if roof == 0:
                        for _ in range(int(rng.integers(0, 4))):
                            ux, uy = rng.uniform(box[0] + 1, box[2] - 3), rng.uniform(box[1] + 1, box[3] - 2.5)
                            units.append((ux, uy, ux + rng.uniform(1.2, 2.0), uy + rng.uniform(0.8, 1.5)))
    octaves = int(np.log2(LONGEST / 0.02)) + 1
    noise = tuple(rng.uniform(-1, 1, (2, TERMS, int(max(width, depth) * 2 ** o / LONGEST) + 3))
                  for o in range(octaves))
    return City(width, depth, seed, streets[0], streets[1], np.asarray(lots, float).reshape(-1, 5),
                np.asarray(buildings, float).reshape(-1, 8), np.asarray(units, float).reshape(-1, 4), noise)
