"""The paper's orthographic oblique camera, Section 2.1, Eqs. (1)-(18), as printed.

Frames (all float64, metres):
  world    scene CRS: x east, y north, z up.
  rotated  world turned about the world Z axis (through the origin) so that the camera,
           which always looks along +y and down, sees the scene from azimuth θ. The bounding
           box of Eqs. (3)-(7) is the box of the rotated model. ``model_matrix`` maps world → rotated.
  eye      OpenGL camera frame: x = vRight, y = vUp, z = vForward; the camera looks along −z.
           ``view_matrix`` maps rotated → eye; it is the inverse of the printed Eq. (1).
  clip     ``projection_matrix`` (Eq. 2) maps eye → clip = NDC (w = 1, orthographic).

Azimuth θ (degrees) is the compass bearing of the view direction, clockwise from north
(θ = 0 looks north, 90 east), as in ``pipeline25d.geometry.perspectives``. Elevation φ (degrees) is
the angle of the view below the horizon (90 = nadir).

What the printed text says, and what this class does where it is ambiguous or inconsistent:
  * The paper defines θ as "degrees clockwise from the negative Y axis" (the camera's
    position, south at θ = 0), which is the same as the project's view bearing. It also
    says the model is rotated *clockwise* by θ; seen from above, that would make θ = 90
    look west. The model is rotated counter-clockwise (Rz(+θ)), which is what the azimuth
    definition needs: the world view direction (sin θ, cos θ) maps to +y.
  * Eq. (1) as printed is the camera-to-world matrix (columns vRight, vUp, vForward, eye),
    not the world-to-eye matrix a renderer uses; ``camera_frame`` returns it as printed.
  * vForward (10) points from the scene to the camera (OpenGL +z of the eye frame). With
    it, eye = vCenter + vForward·dist (12), as printed, puts the camera south of and above
    vCenter and looks at the scene; a minus sign would put it below and behind.
  * Eq. (7) gives vCenter x and y relative to the box corner (xmin, ymin), z absolute:
    read literally in the rotated frame it gives (50, 100, −50) for the Table 3 box, while
    Table 3 prints (0, 50, −50) = (xmin, ymin, 0) + Eq. (7). ``v_center`` follows Table 3.
  * Eq. (3) prints H·tan φ; the ground length of the relief displacement of a vertical
    line is H·cot φ. They agree only at φ = 45° (Table 3). Eq. (5) frames less or more than
    the exact projection (``exact_frame_height``) depending on φ, and at φ = 90 tan φ ≈ 1.6e16,
    so the frame is degenerate at nadir. Implemented as printed.
  * Eq. (2) prints +(right+left)/(right−left) where glOrtho has −; the frame is symmetric
    (left = −right), so the term is 0 either way.
  * Table 3's R, length, dist, near, far are float32 roundings (R = 86.60253906 vs 50√3 =
    86.60254038).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from itertools import product

import numpy as np

from pipeline25d.geometry.perspectives import Perspective

Bounds = tuple[tuple[float, float, float], tuple[float, float, float]]


def _corners(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(8, 3) corners of the axis-aligned box [lo, hi]."""
    return np.array([[x, y, z] for x, y, z in product(*zip(lo, hi))], dtype=np.float64)


def _homogeneous(points: np.ndarray) -> np.ndarray:
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    return np.column_stack([pts, np.ones(len(pts))])


@dataclass(frozen=True)
class PaperCamera:
    """Orthographic oblique camera of Eqs. (1)-(18) for a world bounding box and (θ, φ).

    ``bounds`` is ((xmin, ymin, zmin), (xmax, ymax, zmax)) in world metres; ``azimuth`` and
    ``elevation`` are in degrees. ``length`` (6) defaults to 4R and ``dist`` (8) to
    ``length``; smaller values violate the printed constraints and raise ValueError.
    """

    bounds: Bounds
    azimuth: float
    elevation: float
    length: float | None = None
    dist: float | None = None

    def __post_init__(self) -> None:
        length = 4 * self.R if self.length is None else float(self.length)
        dist = length if self.dist is None else float(self.dist)
        if length < 4 * self.R or dist < length:
            raise ValueError(f"need length >= 4R = {4 * self.R} (6) and dist >= length (8)")
        object.__setattr__(self, "length", length)
        object.__setattr__(self, "dist", dist)

    @classmethod
    def for_perspective(cls, bounds: Bounds, perspective: Perspective) -> "PaperCamera":
        """Camera for a ``Perspective`` (azimuth, elevation in whole degrees)."""
        return cls(bounds, float(perspective.azimuth), float(perspective.elevation))

    # --- Model rotation and the rotated bounding box -----------------------------------

    def model_matrix(self) -> np.ndarray:
        """4×4 world → rotated: Rz(+θ) about the world Z axis through the origin."""
        t = math.radians(self.azimuth)
        M = np.eye(4)
        M[:2, :2] = [[math.cos(t), -math.sin(t)], [math.sin(t), math.cos(t)]]
        return M

    @property
    def rotated_bounds(self) -> np.ndarray:
        """(2, 3) [min, max] of the rotated box corners: the box of Eqs. (3)-(7), metres."""
        lo, hi = np.asarray(self.bounds, dtype=np.float64)
        rotated = (_homogeneous(_corners(lo, hi)) @ self.model_matrix().T)[:, :3]
        return np.array([rotated.min(axis=0), rotated.max(axis=0)])

    @property
    def _size(self) -> np.ndarray:
        lo, hi = self.rotated_bounds
        return hi - lo

    @property
    def _phi(self) -> float:
        return math.radians(self.elevation)

    # --- Eqs. (3)-(8) -------------------------------------------------------------------

    @property
    def R(self) -> float:
        """Bounding-sphere radius of the rotated box (half its diagonal), metres."""
        return float(np.linalg.norm(self._size) / 2)

    @property
    def shadow_len(self) -> float:
        """Eq. (3): (zmax − zmin)·tan φ, metres (as printed; the relief shift is H·cot φ)."""
        return float(self._size[2] * math.tan(self._phi))

    @property
    def width(self) -> float:
        """Eq. (4): xmax − xmin of the rotated box, metres."""
        return float(self._size[0])

    @property
    def height(self) -> float:
        """Eq. (5): (ymax − ymin)·sin φ / 2 + shadowLen, metres on the image plane."""
        return float(self._size[1] * math.sin(self._phi) / 2 + self.shadow_len)

    @property
    def v_center_eq7(self) -> np.ndarray:
        """Eq. (7) literally: (width/2, (ymax − ymin)/2 + shadowLen/2, zmin)."""
        return np.array([self.width / 2, self._size[1] / 2 + self.shadow_len / 2, self.rotated_bounds[0, 2]])

    @property
    def v_center(self) -> np.ndarray:
        """Look-at point in the rotated frame: (xmin, ymin, 0) + Eq. (7), as in Table 3."""
        xmin, ymin = self.rotated_bounds[0, :2]
        return self.v_center_eq7 + np.array([xmin, ymin, 0.0])

    # --- Eqs. (9)-(12) ------------------------------------------------------------------

    @property
    def v_right(self) -> np.ndarray:
        """Eq. (9): (1, 0, 0), rotated frame."""
        return np.array([1.0, 0.0, 0.0])

    @property
    def v_forward(self) -> np.ndarray:
        """Eq. (10): (0, −cos φ, sin φ), rotated frame; points from the scene to the camera."""
        return np.array([0.0, -math.cos(self._phi), math.sin(self._phi)])

    @property
    def v_up(self) -> np.ndarray:
        """Eq. (11): vForward × vRight = (0, sin φ, cos φ), rotated frame."""
        return np.cross(self.v_forward, self.v_right)

    @property
    def eye(self) -> np.ndarray:
        """Eq. (12): vCenter + vForward·dist, rotated frame, metres."""
        return self.v_center + self.v_forward * self.dist

    @property
    def view_direction(self) -> np.ndarray:
        """Unit direction the camera looks in, world frame: (sin θ cos φ, cos θ cos φ, −sin φ)."""
        return np.linalg.inv(self.model_matrix())[:3, :3] @ -self.v_forward

    # --- Eqs. (13)-(18) -----------------------------------------------------------------

    @property
    def left(self) -> float:
        return -self.width / 2

    @property
    def right(self) -> float:
        return self.width / 2

    @property
    def bottom(self) -> float:
        return -self.height / 2

    @property
    def top(self) -> float:
        return self.height / 2

    @property
    def near(self) -> float:
        return self.dist - self.length / 2

    @property
    def far(self) -> float:
        return self.dist + self.length / 2

    # --- Matrices -----------------------------------------------------------------------

    def camera_frame(self) -> np.ndarray:
        """Eq. (1) as printed: 4×4 eye → rotated (columns vRight, vUp, vForward, eye)."""
        M = np.eye(4)
        M[:3, 0], M[:3, 1], M[:3, 2], M[:3, 3] = self.v_right, self.v_up, self.v_forward, self.eye
        return M

    def view_matrix(self) -> np.ndarray:
        """4×4 rotated → eye: the inverse of Eq. (1)."""
        axes = self.camera_frame()[:3, :3]
        V = np.eye(4)
        V[:3, :3] = axes.T
        V[:3, 3] = -axes.T @ self.eye
        return V

    def projection_matrix(self) -> np.ndarray:
        """Eq. (2): 4×4 eye → clip (orthographic), with (13)-(18)."""
        left, right, bottom, top, near, far = self.left, self.right, self.bottom, self.top, self.near, self.far
        return np.array([[2 / (right - left), 0, 0, (right + left) / (right - left)],
                         [0, 2 / (top - bottom), 0, (top + bottom) / (top - bottom)],
                         [0, 0, -2 / (far - near), -(far + near) / (far - near)],
                         [0, 0, 0, 1.0]])

    def mvp(self) -> np.ndarray:
        """4×4 world → clip: projection · view · model."""
        return self.projection_matrix() @ self.view_matrix() @ self.model_matrix()

    def project_ndc(self, points: np.ndarray) -> np.ndarray:
        """(n, 3) world points → (n, 3) NDC; the frame is [−1, 1]² in x, y."""
        return (_homogeneous(points) @ self.mvp().T)[:, :3]

    def project_pixels(self, points: np.ndarray, width_px: int, height_px: int) -> np.ndarray:
        """(n, 3) world points → (n, 2) (col, row) in a width_px × height_px image.

        Continuous pixel coordinates: (0, 0) is the top-left corner of the image, row grows
        downwards, pixel centres are at half-integers.
        """
        ndc = self.project_ndc(points)
        return np.column_stack([(ndc[:, 0] + 1) / 2 * width_px, (1 - ndc[:, 1]) / 2 * height_px])

    def pixel_size(self, width_px: int, height_px: int) -> tuple[float, float]:
        """(metres per pixel across, ground metres per pixel along the view) for the image."""
        return self.width / width_px, self.height / (height_px * math.sin(self._phi))

    def exact_frame_height(self) -> float:
        """Image-plane height (metres) of the rotated box's exact projection, vs. Eq. (5)."""
        up = _corners(*self.rotated_bounds) @ self.v_up
        return float(up.max() - up.min())
