"""Camera geometry: the paper's Table 3, and the map-aligned projection against a ray-plane reference."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pipeline25d.geometry.camera import Extent, PaperCamera, clip_matrix, project, relief_factor
from pipeline25d.geometry.perspectives import Perspective


def test_paper_camera_reproduces_table_3():
    cam = PaperCamera(((-50, -50, -50), (50, 50, 50)), azimuth=0, elevation=45)
    assert cam.R == pytest.approx(86.6025, abs=1e-4)
    assert cam.shadow_len == pytest.approx(100.0, abs=1e-4)
    assert cam.height == pytest.approx(135.3553, abs=1e-4)
    assert cam.length == pytest.approx(346.4102, abs=1e-4)
    assert cam.dist == pytest.approx(346.4102, abs=1e-4)
    assert cam.near == pytest.approx(173.2051, abs=1e-4)
    assert cam.far == pytest.approx(519.6152, abs=1e-4)
    np.testing.assert_allclose(cam.v_up, [0, 0.7071, 0.7071], atol=1e-4)
    # Eq. (5) frames slightly less than the exact projection of the box (DESIGN.md).
    assert cam.height < cam.exact_frame_height()


def ray_plane_reference(points: np.ndarray, azimuth: float, elevation: float, z0: float) -> np.ndarray:
    """Where the viewing ray through each point meets the plane z = z0 (independent derivation)."""
    t, f = math.radians(azimuth), math.radians(elevation)
    v = np.array([math.sin(t) * math.cos(f), math.cos(t) * math.cos(f), -math.sin(f)])
    s = (z0 - points[:, 2]) / v[2]
    return points[:, :2] + s[:, None] * v[:2]


@pytest.mark.parametrize("seed", range(5))
def test_map_projection_matches_ray_plane_intersection(seed):
    rng = np.random.default_rng(seed)
    p = Perspective(int(rng.integers(0, 360)), int(rng.integers(5, 91)))
    pts = np.column_stack([rng.uniform(400000, 700000, 200), rng.uniform(4.4e6, 4.6e6, 200),
                           rng.uniform(-20, 300, 200)])
    got = project(pts, p, z0=12.5)[:, :2]
    np.testing.assert_allclose(got, ray_plane_reference(pts, p.azimuth, p.elevation, 12.5), rtol=0, atol=1e-6)


def test_nadir_has_no_relief_displacement():
    assert relief_factor(Perspective(0, 90)) == 0.0
    pts = np.array([[1.0, 2.0, 100.0]])
    np.testing.assert_allclose(project(pts, Perspective(0, 90), 0.0)[0, :2], [1.0, 2.0])


@pytest.mark.parametrize("seed", range(20))
def test_float32_render_space_agrees_with_float64_to_a_hundredth_of_a_pixel(seed):
    """The GPU path (float32 local coordinates × float32 matrix) at UTM northings ~4.5e6 m."""
    rng = np.random.default_rng(100 + seed)
    p = Perspective(int(rng.integers(0, 360)), int(rng.integers(5, 91)))
    gsd, size = 0.1, 2048
    x0, y0, z0 = rng.uniform(3e5, 7e5), rng.uniform(4.45e6, 4.55e6), rng.uniform(0, 500)
    extent = Extent(x0, y0, x0 + gsd * size, y0 + gsd * size)
    origin = np.array([x0 + 60.0, y0 + 40.0, z0 - 10.0])
    local = rng.uniform(-100, 100, (500, 3))
    world = origin + local
    depth = project(world, p, z0)[:, 2]
    M = clip_matrix(p, z0, extent, (depth.min() - 1, depth.max() + 1), origin)
    clip32 = (M.astype(np.float32) @ np.column_stack([local, np.ones(len(local))]).astype(np.float32).T).T
    px32 = (clip32[:, :2].astype(np.float64) + 1) / 2 * size
    ref = project(world, p, z0)
    px64 = np.column_stack([(ref[:, 0] - extent.xmin) / gsd, (ref[:, 1] - extent.ymin) / gsd])
    assert np.abs(px32 - px64).max() < 0.01
