"""The paper's camera (Section 2.1, Eqs. 1-18) against Table 3 and independent geometry."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pipeline25d.geometry.camera import project, view_direction
from pipeline25d.geometry.paper_camera import PaperCamera, _corners
from pipeline25d.geometry.perspectives import Perspective

BOX = ((-50.0, -50.0, -50.0), (50.0, 50.0, 50.0))  # the Table 3 model
S2 = math.sqrt(0.5)

TABLE_3 = [  # (row, attribute, printed value)
    ("R", "R", 86.60253906), ("shadowLen", "shadow_len", 100.0), ("height", "height", 135.3553391),
    ("width", "width", 100.0), ("length", "length", 346.4101563), ("left", "left", -50.0),
    ("right", "right", 50.0), ("bottom", "bottom", -67.67766953), ("top", "top", 67.67766953),
    ("dist", "dist", 346.4101563), ("near", "near", 173.2050781), ("far", "far", 519.6152344),
    ("vForward", "v_forward", (0, -0.707106781, 0.707106781)),
    ("vUp", "v_up", (0, 0.707106781, 0.707106781)), ("vCenter", "v_center", (0, 50, -50)),
]


def table_camera() -> PaperCamera:
    return PaperCamera(BOX, azimuth=0, elevation=45)


def box_corners(bounds=BOX) -> np.ndarray:
    return _corners(*np.asarray(bounds, dtype=np.float64))


@pytest.mark.parametrize("row, attr, printed", TABLE_3, ids=[r[0] for r in TABLE_3])
def test_table_3_row(row, attr, printed):
    np.testing.assert_allclose(getattr(table_camera(), attr), printed, rtol=0, atol=1e-4)


def test_table_3_prints_float32_values_for_R_length_dist_near_far():
    cam = table_camera()
    for attr, printed in [("R", 86.60253906), ("length", 346.4101563), ("dist", 346.4101563),
                          ("near", 173.2050781), ("far", 519.6152344)]:
        exact = getattr(cam, attr)
        assert float(np.float32(exact)) == pytest.approx(printed, rel=2e-10)  # printed = float32
        assert abs(exact - printed) > 1e-6  # float64 50√3 = 86.60254038 differs in the 6th decimal


def test_eq7_literal_is_corner_relative_table_3_is_the_rotated_frame():
    """Eq. (7) printed gives (50, 100, −50); Table 3 gives (0, 50, −50) = (xmin, ymin, 0) + Eq. (7)."""
    cam = table_camera()
    np.testing.assert_allclose(cam.v_center_eq7, [50, 100, -50], atol=1e-12)
    np.testing.assert_allclose(cam.v_center, [0, 50, -50], atol=1e-12)
    # The text: box centre moved down to zmin and north by shadowLen/2. Off-origin box too:
    cam = PaperCamera(((1000, 2000, 10), (1100, 2300, 60)), 0, 45)
    np.testing.assert_allclose(cam.v_center, [1050, 2150 + 25, 10], atol=1e-9)


def test_eye_sign_as_printed_looks_at_the_scene():
    """vForward points to the camera; eye = vCenter + vForward·dist is south of and above the box."""
    cam = table_camera()
    look = (cam.v_center - cam.eye) / cam.dist
    np.testing.assert_allclose(look, [0, S2, -S2], atol=1e-12)  # the text's "south-north" direction
    np.testing.assert_allclose(cam.eye, [0, 50 - 346.41016 * S2, -50 + 346.41016 * S2], atol=1e-4)
    assert cam.eye[2] > BOX[1][2] and cam.eye[1] < BOX[0][1]
    # Every box corner is in front of the camera (positive depth along the look direction).
    assert ((box_corners() - cam.eye) @ look).min() > 0
    # The other sign would put the eye below the ground, looking away from vCenter.
    assert (cam.v_center - cam.v_forward * cam.dist)[2] < BOX[0][2]


@pytest.mark.parametrize("elevation", [10, 45, 80])
@pytest.mark.parametrize("azimuth", range(0, 360, 15))
def test_azimuth_is_the_view_bearing_clockwise_from_north(azimuth, elevation):
    cam = PaperCamera(BOX, azimuth, elevation)
    np.testing.assert_allclose(cam.view_direction, view_direction(Perspective(azimuth, elevation)), atol=1e-12)
    horizontal = np.array([math.sin(math.radians(azimuth)), math.cos(math.radians(azimuth)), 0, 0])
    np.testing.assert_allclose(cam.model_matrix() @ horizontal, [0, 1, 0, 0], atol=1e-12)


def test_theta_90_looks_east_so_the_model_turns_counter_clockwise():
    """The paper says 'rotate clockwise'; seen from above that would make θ = 90 look west."""
    cam = PaperCamera(BOX, 90, 45)
    np.testing.assert_allclose(cam.view_direction, [S2, 0, -S2], atol=1e-12)
    np.testing.assert_allclose(cam.model_matrix() @ [1, 0, 0, 1], [0, 1, 0, 1], atol=1e-12)  # east → +y


def test_bounding_box_is_the_rotated_box():
    cam = PaperCamera(BOX, 45, 45)
    np.testing.assert_allclose(cam.rotated_bounds, [[-100 * S2, -100 * S2, -50], [100 * S2, 100 * S2, 50]], atol=1e-9)
    assert cam.width == pytest.approx(100 * math.sqrt(2), abs=1e-9)
    assert cam.R == pytest.approx(math.sqrt(2 * (100 * math.sqrt(2)) ** 2 + 100 ** 2) / 2, abs=1e-9)
    assert PaperCamera(BOX, 0, 45).R == pytest.approx(50 * math.sqrt(3), abs=1e-12)


def test_view_matrix_is_the_inverse_of_eq1_and_centres_v_center():
    """Moved from test_camera.py: the camera looks at vCenter (on the ground), not the box centre."""
    cam = PaperCamera(BOX, azimuth=30, elevation=60)
    V, E = cam.view_matrix(), cam.camera_frame()
    np.testing.assert_allclose(E[:3, :], np.column_stack([cam.v_right, cam.v_up, cam.v_forward, cam.eye]))
    np.testing.assert_allclose(V @ E, np.eye(4), atol=1e-12)
    R = V[:3, :3]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(V @ np.append(cam.v_center, 1), [0, 0, -cam.dist, 1], atol=1e-9)
    s, c, S = math.sin(math.radians(60)), math.cos(math.radians(60)), cam.shadow_len
    np.testing.assert_allclose(V @ [0, 0, 0, 1], [0, 50 * c - S / 2 * s, S / 2 * c + 50 * s - cam.dist, 1],
                               atol=1e-9)  # box centre: (0, −50, 86.60 − dist) in eye metres


def test_projection_matrix_is_eq2_and_mvp_composes():
    cam = PaperCamera(BOX, 30, 60)
    P = cam.projection_matrix()
    assert P[0, 3] == 0 and P[1, 3] == 0  # (r+l)/(r−l): printed sign differs from glOrtho, but l = −r
    np.testing.assert_allclose(np.diag(P), [2 / cam.width, 2 / cam.height, -2 / cam.length, 1])
    np.testing.assert_allclose(cam.mvp(), P @ cam.view_matrix() @ cam.model_matrix(), atol=0)
    world_center = np.linalg.inv(cam.model_matrix()) @ np.append(cam.v_center, 1)
    np.testing.assert_allclose(cam.project_pixels(world_center[:3], 640, 480), [[320, 240]], atol=1e-9)


@pytest.mark.parametrize("elevation", [10, 30, 45, 60, 89])
@pytest.mark.parametrize("azimuth", range(0, 360, 5))
def test_a_width_covers_the_rotated_box_exactly(azimuth, elevation):
    bounds = ((300.0, -20.0, 5.0), (460.0, 70.0, 95.0))
    x = PaperCamera(bounds, azimuth, elevation).project_ndc(box_corners(bounds))[:, 0]
    assert x.min() == pytest.approx(-1, abs=1e-9) and x.max() == pytest.approx(1, abs=1e-9)


# φ, Eq. (5) height, exact image-plane height, NDC y of lowest and highest corner (Table 3 box, θ = 0).
FRAME_Y = [(15, 39.7359, 122.4745, -0.8259, 5.3386), (30, 82.7350, 136.6025, -0.9533, 2.3489),
           (45, 135.3553, 141.4214, -1.0448, 1.0448), (60, 216.5064, 136.6025, -1.0928, 0.1691),
           (75, 421.5014, 122.4745, -1.0844, -0.5033)]


@pytest.mark.parametrize("elevation, height, exact, y_lo, y_hi", FRAME_Y)
def test_a_eq5_height_does_not_cover_the_exact_projection(elevation, height, exact, y_lo, y_hi):
    """Eq. (5) never frames the box exactly: at 45° it clips 3.03 m top and bottom; below it
    the tops overflow, above it the near (south) edge falls off the bottom of the frame."""
    cam = PaperCamera(BOX, 0, elevation)
    phi = math.radians(elevation)
    assert cam.height == pytest.approx(height, abs=1e-4)
    assert cam.exact_frame_height() == pytest.approx(exact, abs=1e-4)
    assert cam.exact_frame_height() == pytest.approx(100 * math.sin(phi) + 100 * math.cos(phi), abs=1e-9)
    y = cam.project_ndc(box_corners())[:, 1]
    assert (y.min(), y.max()) == pytest.approx((y_lo, y_hi), abs=1e-4)
    assert y.min() < -1 or y.max() > 1


def test_depth_range_of_4R_covers_a_cube_but_clips_a_tall_column():
    for az in range(0, 360, 15):
        for el in range(5, 91, 5):
            z = PaperCamera(BOX, az, el).project_ndc(box_corners())[:, 2]
            assert -1 <= z.min() and z.max() <= 1
    column = ((0.0, 0.0, 0.0), (1.0, 1.0, 100.0))  # 1 m × 1 m × 100 m, φ = 60: top is nearer than near
    z = PaperCamera(column, 0, 60).project_ndc(box_corners(column))[:, 2]
    assert z.min() == pytest.approx(-1.3014, abs=1e-4)


def image_plane_point(cam: PaperCamera, px: np.ndarray, width_px: int, height_px: int) -> np.ndarray:
    """World point on the image plane (through vCenter, normal vForward) seen at pixel (col, row)."""
    u = px[:, 0] / width_px * cam.width - cam.width / 2
    v = cam.height / 2 - px[:, 1] / height_px * cam.height
    q = cam.v_center + u[:, None] * cam.v_right + v[:, None] * cam.v_up
    return q @ np.linalg.inv(cam.model_matrix())[:3, :3].T


@pytest.mark.parametrize("seed", range(10))
def test_b_ray_from_the_image_point_passes_through_the_scene_point(seed):
    rng = np.random.default_rng(seed)
    az, el = int(rng.integers(0, 360)), int(rng.integers(5, 90))
    bounds = ((-400.0, -300.0, 0.0), (500.0, 350.0, 120.0))
    pts = rng.uniform(bounds[0], bounds[1], (100, 3))
    cam = PaperCamera(bounds, az, el)
    q = image_plane_point(cam, cam.project_pixels(pts, 1024, 768), 1024, 768)
    ray = view_direction(Perspective(az, el))  # the project's formula, not the camera's
    offset = pts - q
    np.testing.assert_allclose(np.cross(offset, ray), 0, atol=1e-9)


@pytest.mark.parametrize("azimuth, elevation", [(0, 45), (37, 20), (200, 70), (315, 85)])
def test_c_vertical_line_is_H_cos_phi_on_the_image(azimuth, elevation):
    """vUp = (0, sin φ, cos φ), vRight = (1, 0, 0) and Rz keeps verticals vertical, so a
    vertical segment of height H maps to (0, H·cos φ) image metres: straight up the image."""
    cam, H, w_px, h_px = PaperCamera(BOX, azimuth, elevation), 37.0, 800, 600
    phi, t = math.radians(elevation), math.radians(azimuth)
    base = np.array([12.0, -7.0, -50.0])
    top = base + [0, 0, H]
    d = np.diff(cam.project_pixels(np.array([base, top]), w_px, h_px), axis=0)[0]
    np.testing.assert_allclose(d, [0, -H * math.cos(phi) / cam.height * h_px], atol=1e-9)
    # Relief displacement on the ground: the hidden ground point is H·cot φ along the view bearing.
    hidden = base + H / math.tan(phi) * np.array([math.sin(t), math.cos(t), 0])
    np.testing.assert_allclose(cam.project_pixels(hidden, w_px, h_px), cam.project_pixels(top, w_px, h_px),
                               atol=1e-9)


def test_c_eq3_tan_equals_the_relief_length_only_at_45_degrees():
    assert PaperCamera(BOX, 0, 45).shadow_len == pytest.approx(100 / math.tan(math.radians(45)), abs=1e-9)
    assert PaperCamera(BOX, 0, 30).shadow_len == pytest.approx(57.7350, abs=1e-4)  # printed, H·tan φ
    assert 100 / math.tan(math.radians(30)) == pytest.approx(173.2051, abs=1e-4)  # relief, H·cot φ


@pytest.mark.parametrize("azimuth, elevation", [(0, 45), (110, 30), (250, 80)])
def test_pixel_size(azimuth, elevation):
    cam, w_px, h_px = PaperCamera(BOX, azimuth, elevation), 500, 400
    sx, sy = cam.pixel_size(w_px, h_px)
    t = math.radians(azimuth)
    p = np.array([1.0, 2.0, -50.0])
    across = cam.project_pixels(np.array([p, p + [math.cos(t), -math.sin(t), 0]]), w_px, h_px)
    along = cam.project_pixels(np.array([p, p + [math.sin(t), math.cos(t), 0]]), w_px, h_px)
    np.testing.assert_allclose(np.diff(across, axis=0)[0], [1 / sx, 0], atol=1e-9)
    np.testing.assert_allclose(np.diff(along, axis=0)[0], [0, -1 / sy], atol=1e-9)
    assert sx == cam.width / w_px


def test_d_nadir_as_printed_is_degenerate():
    """φ = 90: the camera looks straight down, but tan 90° ≈ 1.6e16 makes shadowLen and the
    frame height astronomical, and the whole box lands on the bottom edge of the image."""
    cam = PaperCamera(BOX, 0, 90)
    np.testing.assert_allclose(cam.view_direction, [0, 0, -1], atol=1e-15)
    np.testing.assert_allclose(cam.v_up, [0, 1, 0], atol=1e-15)
    assert cam.shadow_len == pytest.approx(100 * 1.633123935319537e16)
    assert cam.pixel_size(1000, 1000)[1] > 1e15
    px = cam.project_pixels(box_corners(), 1000, 1000)
    np.testing.assert_allclose(px[:, 0], (box_corners()[:, 0] + 50) / 100 * 1000, atol=1e-9)  # plan x
    np.testing.assert_allclose(px[:, 1], 1000, atol=1e-6)  # every corner on the bottom edge


def test_for_perspective_and_length_constraints():
    cam = PaperCamera.for_perspective(BOX, Perspective(135, 45))
    assert cam == PaperCamera(BOX, 135.0, 45.0)
    longer = PaperCamera(BOX, 0, 45, length=500.0, dist=600.0)
    assert (longer.near, longer.far) == (350.0, 850.0)
    with pytest.raises(ValueError):
        PaperCamera(BOX, 0, 45, length=300.0)
    with pytest.raises(ValueError):
        PaperCamera(BOX, 0, 45, dist=300.0)


@pytest.mark.parametrize("az,el", [(0, 45), (135, 30), (290, 60), (0, 90), (45, 5)])
def test_paper_render_affine_is_the_paper_cameras_image_plane(az, el):
    """camera.paper_affine (what the paper mode renders with) against PaperCamera.project_pixels
    (Eqs. 1-18): the same image up to the frame's origin, in image-plane metres; and an affine
    function of the map-aligned plane projection (so one polynomial warp fits both)."""
    rng = np.random.default_rng(az + el)
    pts = rng.uniform(-100, 100, (50, 3)) + [500000.0, 5000000.0, 300.0]
    p = Perspective(az, el)
    cam = PaperCamera(((499800.0, 4999800.0, 0.0), (500200.0, 5000200.0, 600.0)), az, el)
    w, h = 4000, 3000
    px = cam.project_pixels(pts, w, h)
    uv = project(pts, p, 0.0, "paper")[:, :2]
    du, dv = px[:, 0] * cam.width / w - uv[:, 0], -px[:, 1] * cam.height / h - uv[:, 1]
    assert np.ptp(du) < 1e-6 and np.ptp(dv) < 1e-6
    z0 = 300.0
    m = project(pts, p, z0)
    t, f = math.radians(az), math.radians(el)
    np.testing.assert_allclose(uv[:, 0], math.cos(t) * m[:, 0] - math.sin(t) * m[:, 1], atol=1e-6)
    np.testing.assert_allclose(uv[:, 1], math.sin(f) * (math.sin(t) * m[:, 0] + math.cos(t) * m[:, 1])
                               + z0 * math.cos(f), atol=1e-6)
