"""Rendered tiles against analytic expectations (box footprints, GCP markers, textures)."""

from __future__ import annotations

import io

import numpy as np
import pytest

from conftest import box_part, ground_part
from pipeline25d.camera import Extent, project
from pipeline25d.gcps import observations
from pipeline25d.mesh import MeshPart
from pipeline25d.perspectives import Perspective
from pipeline25d.render import TileRenderer, TileView

E0, N0, Z0 = 691000.0, 5334000.0, 500.0   # UTM-sized origin: exercises float32 precision
GSD, SIZE = 0.25, 256


def view(p: Perspective, margin_px: int = 0, size: int = SIZE) -> TileView:
    m = margin_px * GSD
    ext = Extent(E0 - m, N0 - m, E0 + size * GSD + m, N0 + size * GSD + m)
    return TileView(p, Z0, ext, _depth(p), (size + 2 * margin_px,) * 2)


def _depth(p: Perspective) -> tuple[float, float]:
    corners = np.array([[E0 + dx, N0 + dy, Z0 + dz] for dx in (-100, 200) for dy in (-100, 200) for dz in (-5, 60)])
    d = project(corners, p, Z0)[:, 2]
    return float(d.min()), float(d.max())


def covered(rgba: np.ndarray) -> tuple[int, int, int, int]:
    """(row0, row1, col0, col1) inclusive bounds of pixels with any alpha."""
    rows, cols = np.nonzero(rgba[..., 3] > 0)
    return rows.min(), rows.max(), cols.min(), cols.max()


def test_box_nadir_lands_on_expected_pixels(gl_ctx):
    box = box_part((E0 + 10, N0 + 10, Z0), (E0 + 30, N0 + 20, Z0 + 20))
    rgba = TileRenderer(gl_ctx, samples=4).render_color([(np.array([E0, N0, Z0]), [box])], view(Perspective(0, 90)))
    # Top of the tile is N0 + 64: y = N0+20 -> row 176, y = N0+10 -> row 216 (exclusive).
    assert covered(rgba) == (176, 215, 40, 119)
    assert (rgba[176:216, 40:120, 3] == 255).all()


@pytest.mark.parametrize("azimuth", [0, 90, 180, 270])
def test_box_oblique_leans_away_from_camera(gl_ctx, azimuth):
    """At 45° a 20 m box's roof is displaced 20 m along the view direction."""
    box = box_part((E0 + 20, N0 + 20, Z0), (E0 + 40, N0 + 30, Z0 + 20))
    origin = np.array([E0 + 20, N0 + 20, Z0])
    rgba = TileRenderer(gl_ctx).render_color([(origin, [box])], view(Perspective(azimuth, 45)))
    dx, dy = {0: (0, 20), 90: (20, 0), 180: (0, -20), 270: (-20, 0)}[azimuth]
    xmin, xmax = E0 + 20 + min(dx, 0), E0 + 40 + max(dx, 0)
    ymin, ymax = N0 + 20 + min(dy, 0), N0 + 30 + max(dy, 0)
    top = N0 + SIZE * GSD
    expected = (round((top - ymax) / GSD), round((top - ymin) / GSD) - 1,
                round((xmin - E0) / GSD), round((xmax - E0) / GSD) - 1)
    got = covered(rgba)
    assert all(abs(a - b) <= 1 for a, b in zip(got, expected)), (got, expected)


def test_gcp_markers_centroid_and_occlusion(gl_ctx):
    """Visible markers' centroids match the analytic projection; hidden ones are rejected."""
    p = Perspective(0, 45)
    origin = np.array([E0, N0, Z0])
    ground = ground_part(E0 - 50, N0 - 50, E0 + 150, N0 + 150, Z0)
    box = box_part((E0 + 20, N0 + 20, Z0), (E0 + 40, N0 + 30, Z0 + 20))
    rng = np.random.default_rng(1)
    free = np.column_stack([E0 + rng.uniform(5, 60, 12), N0 + rng.uniform(36, 60, 12), np.full(12, Z0)])
    free = free[(free[:, 0] < E0 + 17) | (free[:, 0] > E0 + 43) | (free[:, 1] > N0 + 52)]
    hidden = np.array([[E0 + 30, N0 + 34, Z0], [E0 + 25, N0 + 25, Z0]])   # behind / inside the box
    pts = np.vstack([free, hidden])
    margin = 8
    v = view(p, margin)
    full, sums = TileRenderer(gl_ctx).render_markers([(origin, [ground, box])], v, pts, 6 * GSD, 0.3)
    cands = [{"id": f"g{i}", "x": x, "y": y, "z": z, "role": "gcp"} for i, (x, y, z) in enumerate(pts)]
    seen = observations(cands, full, sums, (v.extent.xmin, v.extent.ymax), GSD)
    seen_ids = {s["id"] for s in seen}
    assert seen_ids == {f"g{i}" for i in range(len(free))}
    truth = project(pts[: len(free)], p, Z0)
    err = np.hypot([s["map_x"] for s in seen] - truth[:, 0], [s["map_y"] for s in seen] - truth[:, 1]) / GSD
    # A rasterised disk of radius 6 px: centroid quantisation stays well under a pixel.
    assert err.max() < 0.15, err


def test_texture_lands_at_its_own_pixels(gl_ctx):
    """A textured square at nadir, one texel per pixel: the render reproduces the image."""
    from PIL import Image

    rng = np.random.default_rng(3)
    img = rng.integers(0, 256, (32, 32, 3), dtype=np.uint8)
    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format="PNG")
    x0, y0, s = E0 + 8, N0 + 8, 32 * GSD
    verts = np.array([[x0, y0, Z0], [x0 + s, y0, Z0], [x0 + s, y0 + s, Z0], [x0, y0 + s, Z0]])
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], dtype=np.float32)   # v = 0 is the image bottom
    part = MeshPart(verts, np.array([[0, 1, 2], [0, 2, 3]]), uv=uv, texture=buf.getvalue())
    renderer = TileRenderer(gl_ctx, samples=0)
    rgba = renderer.render_color([(np.array([E0, N0, Z0]), [part])], view(Perspective(0, 90)))
    top_row = round((N0 + SIZE * GSD - (y0 + s)) / GSD)
    col = round((x0 - E0) / GSD)
    got = rgba[top_row:top_row + 32, col:col + 32, :3].astype(int)
    assert np.abs(got - img).max() <= 2
