"""Rendered tiles against analytic expectations (box footprints, GCP markers, textures)."""

from __future__ import annotations

import io

import numpy as np
import pytest
from conftest import box_part, ground_part

from pipeline25d.core.mesh import MeshPart
from pipeline25d.geometry.camera import Extent, pixel_size, project
from pipeline25d.geometry.perspectives import Perspective
from pipeline25d.stages.gcps import observations
from pipeline25d.stages.records import GcpCandidate
from pipeline25d.stages.render import TileRenderer, TileView

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
    full, sums = TileRenderer(gl_ctx).render_markers([(origin, [ground, box])], v, pts, np.zeros((len(pts), 2)),
                                                     6 * GSD, 0.3, 0.1)
    cands = [GcpCandidate(f"g{i}", x, y, z, 0.0, 0.0, 0.0, "gcp") for i, (x, y, z) in enumerate(pts)]
    seen = observations(cands, full, sums, (v.extent.xmin, v.extent.ymax), GSD)
    seen_ids = {s.id for s in seen}
    assert seen_ids == {f"g{i}" for i in range(len(free))}
    truth = project(pts[: len(free)], p, Z0)
    err = np.hypot([s.map_x for s in seen] - truth[:, 0], [s.map_y for s in seen] - truth[:, 1]) / GSD
    # A rasterised disk of radius 6 px: centroid quantisation stays well under a pixel.
    assert err.max() < 0.15, err


@pytest.mark.parametrize("azimuth,elevation", [(0, 45), (135, 30), (0, 90)])
def test_marker_window_gives_the_whole_tiles_observations(gl_ctx, azimuth, elevation):
    """The marker pass drawn only over its markers' images (render_block.marker_window) gives the
    same observations, to the bit, as over the whole tile and its margin; the window is a fraction
    of the tile and holds every marker's pixels."""
    from pipeline25d.stages.render import marker_images
    from pipeline25d.stages.render_block import marker_window

    p = Perspective(azimuth, elevation)
    origin = np.array([E0, N0, Z0])
    ground = ground_part(E0 - 50, N0 - 50, E0 + 150, N0 + 150, Z0)
    box = box_part((E0 + 20, N0 + 20, Z0), (E0 + 40, N0 + 30, Z0 + 20))
    rng = np.random.default_rng(7)
    pts = np.column_stack([E0 + rng.uniform(5, 30, 9), N0 + rng.uniform(30, 55, 9), np.full(9, Z0)])
    slopes = np.zeros((len(pts), 2))
    whole = view(p, 8)
    extent, size = marker_window(whole, *marker_images(pts, slopes, 6 * GSD, whole))
    assert size[0] * size[1] < 0.5 * whole.size[0] * whole.size[1]
    window = TileView(p, Z0, extent, whole.depth_range, size)
    cands = [GcpCandidate(f"g{i}", x, y, z, 0.0, 0.0, 0.0, "gcp") for i, (x, y, z) in enumerate(pts)]
    got = []
    for v in (whole, window):
        full, sums = TileRenderer(gl_ctx).render_markers([(origin, [ground, box])], v, pts, slopes, 6 * GSD, 0.3, 0.1)
        got.append((full, observations(cands, full, sums, (v.extent.xmin, v.extent.ymax), GSD)))
    assert got[0][1] and got[0][1] == got[1][1]
    assert np.array_equal(got[0][0], got[1][0])                 # every marker's whole image, in both


def test_markers_on_bare_ground_beside_a_building_only_model(gl_ctx):
    """A model of a building and a small paved patch, no ground (a buildings-only city): markers
    with nothing of the model under them (bare ground, the DTM's) are accepted at their analytic
    positions; one behind the building is hidden, one straddling the patch's edge lies partly over
    nothing (the model's edge) and one floats 1 m over the patch: those three are rejected."""
    p = Perspective(0, 45)
    box = box_part((E0 + 20, N0 + 20, Z0), (E0 + 40, N0 + 30, Z0 + 20))
    patch = ground_part(E0 + 45, N0 + 5, E0 + 60, N0 + 15, Z0)
    bare = np.array([[E0 + 8, N0 + 8, Z0], [E0 + 30, N0 + 10, Z0], [E0 + 10, N0 + 40, Z0], [E0 + 50, N0 + 40, Z0]])
    rejected = np.array([[E0 + 30, N0 + 34, Z0],          # behind the box
                         [E0 + 45, N0 + 10, Z0],          # half on the patch
                         [E0 + 52, N0 + 10, Z0 + 1.0]])   # floating over the patch
    pts = np.vstack([bare, rejected])
    margin = 8
    v = view(p, margin)
    full, sums = TileRenderer(gl_ctx).render_markers([(np.array([E0, N0, Z0]), [box, patch])], v, pts,
                                                     np.zeros((len(pts), 2)), 6 * GSD, 0.3, 0.1)
    cands = [GcpCandidate(f"g{i}", x, y, z, 0.0, 0.0, 0.0, "gcp") for i, (x, y, z) in enumerate(pts)]
    seen = observations(cands, full, sums, (v.extent.xmin, v.extent.ymax), GSD)
    assert [s.id for s in seen] == [f"g{i}" for i in range(len(bare))]
    truth = project(bare, p, Z0)
    err = np.hypot([s.map_x for s in seen] - truth[:, 0], [s.map_y for s in seen] - truth[:, 1]) / GSD
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


def slope_part(x0, y0, x1, y1, z_fn, step=2.0, rgba=(90, 140, 60, 255)) -> MeshPart:
    """A regular-grid terrain mesh with heights z_fn(x, y)."""
    xs, ys = np.arange(x0, x1 + step / 2, step), np.arange(y0, y1 + step / 2, step)
    gx, gy = np.meshgrid(xs, ys)
    verts = np.column_stack([gx.ravel(), gy.ravel(), z_fn(gx.ravel(), gy.ravel())])
    nx = len(xs)
    i, j = np.meshgrid(np.arange(len(ys) - 1), np.arange(nx - 1), indexing="ij")
    a = (i * nx + j).ravel()
    faces = np.vstack([np.column_stack([a, a + 1, a + nx + 1]), np.column_stack([a, a + nx + 1, a + nx])])
    return MeshPart(verts, faces, colors=np.tile(np.array(rgba, np.uint8), (len(verts), 1)))


@pytest.mark.parametrize("camera", ["map", "paper"])
def test_floating_and_buried_markers_are_rejected_tilted_ones_on_slopes_accepted(gl_ctx, camera):
    """On a 20 % slope: markers on the surface (tilted with it) are accepted and unbiased;
    markers 1 m above it (floating) or 0.5 m below it (buried) are rejected. The same on the
    paper camera's image plane (pixels of gsd·sin φ), against its analytic projection."""
    p = Perspective(30, 40)
    slope = (0.2, -0.1)

    def z_fn(x, y):
        return Z0 + slope[0] * (x - E0) + slope[1] * (y - N0)

    terrain = slope_part(E0 - 40, N0 - 40, E0 + 110, N0 + 110, z_fn)
    rng = np.random.default_rng(5)
    gx, gy = np.meshgrid(np.arange(6) * 8.0 + 12, np.arange(5) * 9.0 + 12)
    xy = np.column_stack([E0 + gx.ravel(), N0 + gy.ravel()]) + rng.uniform(-1, 1, (30, 2))
    xy = xy[rng.permutation(30)]
    xy[29] = xy[28] + [0.5, 0.0]                 # two markers on top of each other: no clean centroid
    lift = np.repeat([0.0, 1.0, -0.5], 10)
    lift[28:] = 0.0
    pts = np.column_stack([xy, z_fn(xy[:, 0], xy[:, 1]) + lift])
    margin = 8
    corners = np.array([[E0 + dx, N0 + dy, z_fn(E0 + dx, N0 + dy) + dz] for dx in (-50, 120) for dy in (-50, 120)
                        for dz in (-5, 5)])
    d = project(corners, p, Z0)[:, 2]
    pixel = pixel_size(GSD, p, camera)
    if camera == "map":
        m = margin * GSD
        ext = Extent(E0 - m, N0 - m, E0 + SIZE * GSD + m, N0 + SIZE * GSD + m)
    else:   # the image-plane box of the marker area, on whole pixels of an arbitrary grid
        uv = project(np.column_stack([xy, pts[:, 2]]), p, Z0, camera)
        lo = np.floor(uv[:, :2].min(axis=0) / pixel) * pixel - (margin + 12) * pixel
        ext = Extent(lo[0], lo[1], lo[0] + (SIZE + 2 * margin) * pixel * 1.5, lo[1] + (SIZE + 2 * margin) * pixel)
    size = (round(ext.width / pixel), round(ext.height / pixel))
    v = TileView(p, Z0, ext, (d.min(), d.max()), size, camera=camera)
    tol = 0.25 * GSD / np.cos(np.radians(p.elevation))
    full, sums = TileRenderer(gl_ctx).render_markers([(np.array([E0, N0, Z0]), [terrain])], v, pts,
                                                     np.tile(slope, (len(pts), 1)), 6 * GSD, 0.05, tol)
    cands = [GcpCandidate(f"g{i}", x, y, z, 0.0, 0.0, 0.0, "gcp") for i, (x, y, z) in enumerate(pts)]
    seen = observations(cands, full, sums, (ext.xmin, ext.ymax), pixel)
    assert {s.id for s in seen} == {f"g{i}" for i in range(10)}
    truth = project(pts[:10], p, Z0, camera)
    err = np.hypot([s.map_x for s in seen] - truth[:, 0], [s.map_y for s in seen] - truth[:, 1]) / pixel
    # rasterised tilted disks of ~6 px radius: centroid quantisation only
    assert np.sqrt(np.mean(err ** 2)) < 0.12 and err.max() < 0.25, err


def test_depth_pass_gives_exact_heights_at_cell_centres(gl_ctx):
    """The nadir depth pass (the DSM) against an analytic tilted plane at UTM coordinates."""
    from pipeline25d.core.grid import Grid
    from pipeline25d.stages.terrain.dsm import render_height_map

    def z_fn(x, y):
        return 300.0 + 0.3 * (x - E0) + 0.1 * (y - N0)

    part = slope_part(E0, N0, E0 + 200, N0 + 100, z_fn, step=25.0)
    grid = Grid.covering((E0 - 10, N0 - 10, E0 + 210, N0 + 110), 0.5)
    dsm = render_height_map([(part.bounds(), lambda: (np.array([E0, N0, 300.0]), [part]))], grid, tile_px=256)
    xs, ys = grid.cell_centres()
    inside = (xs > E0) & (xs < E0 + 200) & (ys > N0) & (ys < N0 + 100)
    assert np.isfinite(dsm[inside]).all() and np.isnan(dsm[~inside]).all()
    assert np.abs(dsm - z_fn(xs, ys))[inside].max() < 1e-3   # 24-bit depth over ~100 m: ~6e-6 m steps


def test_terrain_relative_projection_puts_sloped_ground_at_its_orthographic_position(gl_ctx):
    """A box standing on a 30 % slope, terrain mode: the foot of its walls lands on the box's
    true footprint (ground needs no warp), its roof leans by its height above the ground."""
    p = Perspective(0, 45)

    def z_fn(x, y):
        return Z0 + 0.3 * (y - N0)

    terrain = slope_part(E0 - 60, N0 - 60, E0 + 120, N0 + 120, z_fn)
    foot = (E0 + 20, N0 + 16, E0 + 40, N0 + 26)                       # footprint, metres
    base = z_fn(0, foot[1]) - 1.0                                       # walls start below the slope
    box = box_part((foot[0], foot[1], base), (foot[2], foot[3], z_fn(0, foot[3]) + 10.0))
    ext = Extent(E0, N0, E0 + SIZE * GSD, N0 + SIZE * GSD)
    corners = np.array([[E0 + dx, N0 + dy, z] for dx in (-60, 120) for dy in (-60, 120) for z in (Z0 - 40, Z0 + 60)])
    d = project(corners, p, Z0)[:, 2]
    v = TileView(p, Z0, ext, (d.min(), d.max()), (SIZE, SIZE), ground=z_fn)
    renderer = TileRenderer(gl_ctx, samples=0)
    rgba = renderer.render_color([(np.array([E0, N0, Z0]), [terrain, box])], v)
    red = (rgba[..., 0] > 150) & (rgba[..., 1] < 120)                   # the box's colour
    rows, cols = np.nonzero(red)
    # x is not displaced at azimuth 0; the south wall's foot (on the ground) stays at y = foot[1]
    assert cols.min() == round((foot[0] - E0) / GSD) and cols.max() == round((foot[2] - E0) / GSD) - 1
    top = N0 + SIZE * GSD
    assert rows.max() == round((top - foot[1]) / GSD) - 1
    # the roof's north edge is 10 m above the ground there (z_fn at foot[3]): it leans 10 m north
    assert rows.min() == round((top - (foot[3] + 10.0)) / GSD)


def test_a_renderer_reusing_its_targets_renders_each_tile_as_a_fresh_one(gl_ctx):
    """One renderer keeps its render targets from tile to tile (remade when the size changes):
    tiles of two sizes, in turn, equal those of a renderer made for each tile alone."""
    p = Perspective(135, 45)
    origin = np.array([E0, N0, Z0])
    chunks = [(origin, [ground_part(E0 - 50, N0 - 50, E0 + 150, N0 + 150, Z0),
                        box_part((E0 + 20, N0 + 20, Z0), (E0 + 40, N0 + 30, Z0 + 20))])]
    pts = np.array([[E0 + 8, N0 + 45, Z0], [E0 + 50, N0 + 12, Z0], [E0 + 30, N0 + 25, Z0]])   # the last in the box
    slopes = np.zeros((len(pts), 2))

    def tile(renderer: TileRenderer, size: int):
        v = view(p, 0, size)
        return renderer.render_color(chunks, v), renderer.render_markers(chunks, view(p, 8, size), pts, slopes,
                                                                          6 * GSD, 0.3, 0.1)

    kept = TileRenderer(gl_ctx)
    for size in (SIZE, 200, SIZE, SIZE):
        (rgba, (full, sums)), (rgba1, (full1, sums1)) = tile(kept, size), tile(TileRenderer(gl_ctx), size)
        assert rgba.shape == (size, size, 4) and (rgba[..., 3] > 0).mean() > 0.5
        assert np.array_equal(rgba, rgba1) and np.array_equal(full, full1) and np.array_equal(sums, sums1)
    assert sums[0, 0] == full[0] > 0 and sums[2, 0] == 0 < full[2]      # the first in the open, the last hidden
