"""Orthographic oblique cameras: the map-aligned projection (default) and the paper's camera.

Map-aligned projection (DESIGN.md): a point p = (x, y, z) in the scene CRS appears on the
north-up map at (x, y) + (z - z0)·cot φ·d with d = (sin θ, cos θ); its depth is its
distance along the 3D view direction v = (sin θ cos φ, cos θ cos φ, -sin φ). Both are
affine, so one 4×4 matrix per tile takes chunk-local float32 coordinates to clip space.
All of this is float64; only the final matrix goes to the GPU as float32.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from .perspectives import Perspective


class Extent(NamedTuple):
    """Axis-aligned map rectangle in scene CRS metres."""

    xmin: float
    ymin: float
    xmax: float
    ymax: float

    @property
    def width(self) -> float:
        return self.xmax - self.xmin

    @property
    def height(self) -> float:
        return self.ymax - self.ymin


def horizontal_direction(p: Perspective) -> np.ndarray:
    """(2,) unit vector d = (sin θ, cos θ): where the camera looks, on the map."""
    t = math.radians(p.azimuth)
    return np.array([math.sin(t), math.cos(t)])


def view_direction(p: Perspective) -> np.ndarray:
    """(3,) unit 3D viewing direction (sin θ cos φ, cos θ cos φ, -sin φ)."""
    return _view_dir(p.azimuth, p.elevation)


def relief_factor(p: Perspective) -> float:
    """cot φ: metres of map displacement per metre of height above z0 (0 at nadir)."""
    if p.elevation == 90:
        return 0.0
    return 1.0 / math.tan(math.radians(p.elevation))


def map_affine(p: Perspective, z0: float) -> tuple[np.ndarray, np.ndarray]:
    """(A, b) with [map_x, map_y, depth] = A @ (x, y, z) + b, float64.

    A is 3×3, b is (3,). Rows 0-1 shear heights along d; row 2 is the view depth.
    """
    d = horizontal_direction(p) * relief_factor(p)
    A = np.array([[1.0, 0.0, d[0]], [0.0, 1.0, d[1]], view_direction(p)])
    b = np.array([-z0 * d[0], -z0 * d[1], 0.0])
    return A, b


def project(points: np.ndarray, p: Perspective, z0: float) -> np.ndarray:
    """(n, 3) scene points -> (n, 3) float64 [map_x, map_y, depth]."""
    A, b = map_affine(p, z0)
    return np.asarray(points, dtype=np.float64) @ A.T + b


def clip_matrix(p: Perspective, z0: float, extent: Extent, depth_range: tuple[float, float],
                origin: np.ndarray) -> np.ndarray:
    """4×4 float64 matrix from chunk-local coordinates (scene point − origin) to GL clip space.

    The extent maps exactly onto NDC [-1, 1] in x and y (so pixel boundaries of adjacent
    tiles coincide) and depth_range onto [-1, 1] in z (near = smaller depth). The
    translation column is computed in float64 relative to ``origin``, so it is small and
    float32 keeps sub-millimetre precision even at UTM northings.
    """
    A, b = map_affine(p, z0)
    dmin, dmax = depth_range
    scale = np.diag([2.0 / extent.width, 2.0 / extent.height, 2.0 / (dmax - dmin)])
    # Translation: where the origin lands in NDC, with the large terms cancelled first.
    local_origin = A @ np.asarray(origin, dtype=np.float64) + b
    offset = np.array([(local_origin[0] - extent.xmin) * scale[0, 0] - 1.0,
                       (local_origin[1] - extent.ymin) * scale[1, 1] - 1.0,
                       (local_origin[2] - dmin) * scale[2, 2] - 1.0])
    M = np.eye(4)
    M[:3, :3] = scale @ A
    M[:3, 3] = offset
    return M


def projected_box(bounds: np.ndarray, p: Perspective, z0: float) -> tuple[Extent, tuple[float, float]]:
    """Map extent and depth range covered by a (2, 3) bounding box in perspective p."""
    lo, hi = np.asarray(bounds, dtype=np.float64)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    proj = project(corners, p, z0)
    return (Extent(proj[:, 0].min(), proj[:, 1].min(), proj[:, 0].max(), proj[:, 1].max()),
            (float(proj[:, 2].min()), float(proj[:, 2].max())))


@dataclass(frozen=True)
class PaperCamera:
    """The paper's orthographic camera, Eqs. (1)-(18), for a bounding box and (θ, φ).

    Kept as the baseline the map-aligned camera is measured against. The camera sits at
    distance ``dist`` from the box centre against the view direction, with near/far planes
    at dist ∓ 2R. The frame height follows the paper's Eq. (5), which is slightly smaller
    than the exact projection of the box (``exact_frame_height``).

    Reconstruction note: the paper's text was not reachable offline; its Table 3 example
    (box ±50 m, θ = 0, φ = 45°) is reproduced exactly by the formulas below, with
    height = (D + shadowLen / 2)·sin φ where D is the footprint diagonal.
    """

    bounds: tuple[tuple[float, float, float], tuple[float, float, float]]
    azimuth: float
    elevation: float

    @property
    def _size(self) -> np.ndarray:
        lo, hi = np.asarray(self.bounds, dtype=np.float64)
        return hi - lo

    @property
    def center(self) -> np.ndarray:
        lo, hi = np.asarray(self.bounds, dtype=np.float64)
        return (lo + hi) / 2

    @property
    def R(self) -> float:
        """Radius of the bounding sphere (half the box diagonal)."""
        return float(np.linalg.norm(self._size) / 2)

    @property
    def shadow_len(self) -> float:
        """Length of the box height's oblique shadow on the ground: H / tan φ."""
        return float(self._size[2] / math.tan(math.radians(self.elevation)))

    @property
    def width(self) -> float:
        """Frame width: the footprint diagonal, which bounds the footprint at any θ."""
        return float(math.hypot(self._size[0], self._size[1]))

    @property
    def height(self) -> float:
        """Frame height, Eq. (5)."""
        return float((self.width + self.shadow_len / 2) * math.sin(math.radians(self.elevation)))

    @property
    def dist(self) -> float:
        """Camera distance from the box centre (4R), the 'length' of Table 3."""
        return 4 * self.R

    length = dist

    @property
    def near(self) -> float:
        return self.dist - 2 * self.R

    @property
    def far(self) -> float:
        return self.dist + 2 * self.R

    @property
    def v_forward(self) -> np.ndarray:
        return _view_dir(self.azimuth, self.elevation)

    @property
    def v_up(self) -> np.ndarray:
        t, f = math.radians(self.azimuth), math.radians(self.elevation)
        return np.array([math.sin(t) * math.sin(f), math.cos(t) * math.sin(f), math.cos(f)])

    @property
    def v_right(self) -> np.ndarray:
        return np.cross(self.v_forward, self.v_up)

    @property
    def eye(self) -> np.ndarray:
        return self.center - self.dist * self.v_forward

    def view_matrix(self) -> np.ndarray:
        """4×4 look-at matrix (right, up, −forward rows), float64."""
        M = np.eye(4)
        M[0, :3], M[1, :3], M[2, :3] = self.v_right, self.v_up, -self.v_forward
        M[:3, 3] = -M[:3, :3] @ self.eye
        return M

    def projection_matrix(self) -> np.ndarray:
        """4×4 glOrtho matrix with left/right = ∓width/2, bottom/top = ∓height/2."""
        w, h, n, f = self.width, self.height, self.near, self.far
        return np.array([[2 / w, 0, 0, 0], [0, 2 / h, 0, 0],
                         [0, 0, -2 / (f - n), -(f + n) / (f - n)], [0, 0, 0, 1.0]])

    def exact_frame_height(self) -> float:
        """Image-plane height of the box's exact projection, for comparison with Eq. (5)."""
        lo, hi = np.asarray(self.bounds, dtype=np.float64)
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        up = corners @ self.v_up
        return float(up.max() - up.min())


def _view_dir(azimuth: float, elevation: float) -> np.ndarray:
    t, f = math.radians(azimuth), math.radians(elevation)
    return np.array([math.sin(t) * math.cos(f), math.cos(t) * math.cos(f), -math.sin(f)])
