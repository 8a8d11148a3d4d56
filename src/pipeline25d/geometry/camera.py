"""Orthographic oblique cameras: the map-aligned projection (default) and the paper's camera.

Map-aligned projection (DESIGN.md): a point p = (x, y, z) in the scene CRS appears on the
north-up map at (x, y) + (z - z0)·cot φ·d with d = (sin θ, cos θ); its depth is its
distance along the 3D view direction v = (sin θ cos φ, cos θ cos φ, -sin φ). Both are
affine, so one 4×4 matrix per tile takes chunk-local float32 coordinates to clip space.
All of this is float64; only the final matrix goes to the GPU as float32.

The paper's camera (``camera="paper"``, :class:`PaperCamera`, Eqs. 1, 9-11) images the
scene on the plane perpendicular to the view: u = vRight·Rz(θ)p, v = vUp·Rz(θ)p, a rotated
and foreshortened picture that only a GCP warp brings onto the map. For any point it is an
affine function of the map-aligned plane projection (u = rotation of the map position,
v = sin φ × the other rotated axis + z0·cos φ), so the same polynomial warp fits both equally.
"""

from __future__ import annotations

import math

import numpy as np

from pipeline25d.core.grid import Extent
from pipeline25d.geometry.perspectives import Perspective


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


def paper_affine(p: Perspective) -> tuple[np.ndarray, np.ndarray]:
    """(A, b) with [u, v, depth] = A @ (x, y, z) + b on the paper camera's image plane, metres.

    Rows 0-1 are vRight and vUp of Eqs. (9)-(11) after the model rotation Rz(θ) (the
    rotation part of view · model; the image origin is arbitrary, so b = 0); row 2 is the
    same view depth as the map-aligned projection.
    """
    cam = PaperCamera(((0.0, 0.0, 0.0), (1.0, 1.0, 1.0)), float(p.azimuth), float(p.elevation))
    rot = (cam.view_matrix() @ cam.model_matrix())[:2, :3]
    return np.vstack([rot, view_direction(p)]), np.zeros(3)


def camera_affine(p: Perspective, z0: float, camera: str = "map") -> tuple[np.ndarray, np.ndarray]:
    """The affine projection of ``camera``: "map" (:func:`map_affine`) or "paper" (:func:`paper_affine`)."""
    if camera == "paper":
        return paper_affine(p)
    if camera != "map":
        raise ValueError(f"unknown camera {camera!r}")
    return map_affine(p, z0)


def pixel_size(gsd: float, p: Perspective, camera: str = "map") -> float:
    """Image-plane metres per pixel. The paper camera's pixels are gsd·sin φ, so ground along
    the view is sampled at the map's gsd (the baseline is not handicapped by coarser pixels)."""
    return gsd * math.sin(math.radians(p.elevation)) if camera == "paper" else gsd


def project(points: np.ndarray, p: Perspective, z0: float, camera: str = "map") -> np.ndarray:
    """(n, 3) scene points -> (n, 3) float64 [map_x, map_y, depth] (image u, v, depth for "paper")."""
    A, b = camera_affine(p, z0, camera)
    return np.asarray(points, dtype=np.float64) @ A.T + b


def project_above_ground(points: np.ndarray, ground: np.ndarray, p: Perspective) -> np.ndarray:
    """Terrain-relative projection: (n, 3) points over (n,) ground heights -> [map_x, map_y, depth].

    A point is displaced by its height above the ground under it, (z − ground)·cot φ·d;
    depth is the true 3D view depth.
    """
    pts = np.asarray(points, dtype=np.float64)
    out = project(pts, p, 0.0)
    shift = horizontal_direction(p) * relief_factor(p)
    out[:, :2] -= np.asarray(ground, dtype=np.float64)[:, None] * shift[None]
    return out


def image_stretch(p: Perspective, slopes: np.ndarray, camera: str = "map") -> np.ndarray:
    """(n,) σ_max of the 2×2 Jacobian of the projection on planes of (n, 2) slopes (dz/dx, dz/dy):
    how far, per metre, a disk in that plane reaches from its centre in the image."""
    A = camera_affine(p, 0.0, camera)[0]
    slopes = np.asarray(slopes, dtype=np.float64).reshape(-1, 2)
    jac = A[None, :2, :2] + A[None, :2, 2, None] * slopes[:, None, :]
    return np.linalg.norm(jac, ord=2, axis=(1, 2))


def clip_matrix(p: Perspective, z0: float, extent: Extent, depth_range: tuple[float, float],
                origin: np.ndarray, camera: str = "map") -> np.ndarray:
    """4×4 float64 matrix from chunk-local coordinates (scene point − origin) to GL clip space.

    The extent maps exactly onto NDC [-1, 1] in x and y (so pixel boundaries of adjacent
    tiles coincide) and depth_range onto [-1, 1] in z (near = smaller depth). The
    translation column is computed in float64 relative to ``origin``, so it is small and
    float32 keeps sub-millimetre precision even at UTM northings.
    """
    A, b = camera_affine(p, z0, camera)
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


def projected_box(bounds: np.ndarray, p: Perspective, z0: float,
                  ground_range: tuple[float, float] | None = None,
                  camera: str = "map") -> tuple[Extent, tuple[float, float]]:
    """Map (or paper image) extent and depth range covered by a (2, 3) bounding box in perspective p.

    ``ground_range``: (lowest, highest) ground under the box for terrain-relative
    projection; heights above ground then span [z_min − highest, z_max − lowest].
    """
    lo, hi = np.asarray(bounds, dtype=np.float64)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    depth = project(corners, p, z0)[:, 2]
    if ground_range is None:
        planar = project(corners, p, z0, camera)
    else:
        rel = np.array([[x, y, h] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                        for h in (lo[2] - ground_range[1], hi[2] - ground_range[0])])
        planar = project(rel, p, 0.0)
    return (Extent(planar[:, 0].min(), planar[:, 1].min(), planar[:, 0].max(), planar[:, 1].max()),
            (float(depth.min()), float(depth.max())))


def _view_dir(azimuth: float, elevation: float) -> np.ndarray:
    t, f = math.radians(azimuth), math.radians(elevation)
    return np.array([math.sin(t) * math.cos(f), math.cos(t) * math.cos(f), -math.sin(f)])


from pipeline25d.geometry.paper_camera import PaperCamera  # noqa: F401,E402
