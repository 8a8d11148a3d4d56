"""Numerical stability as properties (hypothesis): projection, tile seams and float32 rendering.

Coordinates go up to UTM size (eastings to 1e6 m, northings to 1e7 m, heights -500 to 9000 m),
any azimuth, elevations 5-90°. The GPU path is emulated in float32 exactly as render.py feeds it
(chunk-local float32 vertices, the float32 clip matrix, the terrain shear) and compared with a
float64 reference written here from DESIGN.md's definition; one property renders for real.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline25d.core.mesh import MeshPart
from pipeline25d.geometry.perspectives import Perspective
from pipeline25d.stages.chunks import chunk_origin
from pipeline25d.stages.plan import plan_perspective
from pipeline25d.stages.records import LodChunk, frozen, tile_extent, tile_span
from pipeline25d.stages.render import TileRenderer, TileView

settings.register_profile("ci", derandomize=True, print_blob=True, deadline=None)
settings.load_profile("ci")

MATH_EXAMPLES = 200
RENDER_EXAMPLES = 10

azimuths = st.floats(0.0, 360.0, exclude_max=True)
elevations = st.floats(5.0, 90.0)
gsds = st.floats(0.05, 2.0)
tile_sizes = st.integers(64, 4096)
eastings = st.floats(0.0, 1e6)
northings = st.floats(0.0, 1e7)
heights = st.floats(-500.0, 9000.0)


def reference_map(points: np.ndarray, azimuth: float, elevation: float, base: np.ndarray | float) -> np.ndarray:
    """(n, 2) float64 map positions by DESIGN.md: (x, y) + (z − base)·cot φ·(sin θ, cos θ)."""
    t, f = math.radians(azimuth), math.radians(elevation)
    shift = (points[:, 2] - base) * (math.cos(f) / math.sin(f))
    return points[:, :2] + shift[:, None] * np.array([math.sin(t), math.cos(t)])


def gpu_window_xy(view: TileView, vertices: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """(n, 2) window pixel coordinates (x right, y up) as the vertex shader and viewport compute them.

    Mirrors TileRenderer.upload/_draw_chunks: float32 vertices relative to the chunk origin,
    the float32 clip matrix of that origin, minus in_ground·u_shear, then the viewport transform.
    """
    f32 = np.float32
    local = (vertices - origin).astype(f32)
    matrix = view.matrix(origin).astype(f32)
    shear = np.array(view.shear(view.matrix(origin)), dtype=f32)
    ground = view.ground_offsets(vertices, origin)
    clip = np.zeros((len(local), 2), dtype=f32)
    for i in range(2):   # one float32 multiply-add at a time, as the shader does
        acc = matrix[i, 3] * np.ones(len(local), dtype=f32)
        for j in range(3):
            acc = acc + matrix[i, j] * local[:, j]
        if ground is not None:
            acc = acc - ground * shear[i]
        clip[:, i] = acc
    size = np.array(view.size, dtype=f32)
    return ((clip + f32(1.0)) * (size / f32(2.0))).astype(np.float64)


@st.composite
def chunk_scenes(draw) -> dict:
    """A chunk at UTM coordinates, a perspective, a grid, and points inside the chunk."""
    gsd = draw(gsds)
    chunk = max(400 * gsd, 100.0)                    # config.chunk_size's auto rule
    tall = draw(st.floats(0.0, 300.0))               # the chunk's height span (a tower at most)
    lo = np.array([draw(eastings), draw(northings), draw(heights)])
    n = 8
    local = np.column_stack([draw(st.lists(st.floats(0.0, chunk), min_size=n, max_size=n)),
                             draw(st.lists(st.floats(0.0, chunk), min_size=n, max_size=n)),
                             draw(st.lists(st.floats(0.0, tall), min_size=n, max_size=n))])
    return {"gsd": gsd, "tile_size": draw(tile_sizes), "points": lo + local,
            "origin": chunk_origin(np.array([lo, lo + [chunk, chunk, tall]])),
            "p": Perspective(draw(azimuths), draw(elevations)), "z0": draw(heights),
            "terrain": draw(st.booleans()), "ground": lo[2] + draw(st.floats(-50.0, tall))}   # DTM under the chunk


def tile_view_of(scene: dict, point_map: np.ndarray) -> TileView:
    """The plan-grid tile holding ``point_map``, as the tile job's TileView (whole tile, plane or terrain)."""
    span = tile_span(scene["gsd"], scene["tile_size"])
    row, col = math.floor(point_map[1] / span), math.floor(point_map[0] / span)
    extent = tile_extent(scene["gsd"], scene["tile_size"], row, col)
    ground = (lambda x, y: np.full(np.shape(x), scene["ground"])) if scene["terrain"] else None
    p = scene["p"]
    depth = np.array([math.sin(math.radians(p.azimuth)), math.cos(math.radians(p.azimuth)), 0.0]) \
        * math.cos(math.radians(p.elevation)) - [0.0, 0.0, math.sin(math.radians(p.elevation))]
    d = scene["points"] @ depth
    return TileView(p, scene["z0"], extent, (float(d.min()) - 1.0, float(d.max()) + 1.0),
                    (scene["tile_size"], scene["tile_size"]), ground)


@settings(max_examples=MATH_EXAMPLES)
@given(chunk_scenes())
def test_float32_render_path_matches_float64_reference(scene: dict) -> None:
    """Every point of a chunk lands within 0.01 px of the float64 definition, in the tile holding it,
    in plane and terrain-relative mode, on the float32 GPU path."""
    p, pts = scene["p"], scene["points"]
    base = scene["ground"] if scene["terrain"] else scene["z0"]
    ref = reference_map(pts, p.azimuth, p.elevation, base)
    for k in range(len(pts)):
        view = tile_view_of(scene, ref[k])
        px = view.extent.width / view.size[0]
        want = (ref[k] - [view.extent.xmin, view.extent.ymin]) / px
        got = gpu_window_xy(view, pts[k:k + 1], scene["origin"])[0]
        assert np.abs(got - want).max() <= 0.01, (got, want)


@settings(max_examples=MATH_EXAMPLES)
@given(gsds, tile_sizes, eastings, northings, st.integers(-3, 3), st.integers(-3, 3))
def test_adjacent_tiles_share_edges_and_one_pixel_grid(gsd: float, size: int, x: float, y: float,
                                                       dr: int, dc: int) -> None:
    """Tile (r, c)'s right/top edge is (r, c+1)'s left / (r+1, c)'s bottom edge exactly, and a map
    point's pixel coordinates in any two tiles differ by whole tiles (one pixel grid)."""
    span = tile_span(gsd, size)
    r, c = math.floor(y / span), math.floor(x / span)
    a, right, up = tile_extent(gsd, size, r, c), tile_extent(gsd, size, r, c + 1), tile_extent(gsd, size, r + 1, c)
    assert a.xmax == right.xmin and a.ymax == up.ymin
    assert (a.ymin, a.ymax) == (right.ymin, right.ymax) and (a.xmin, a.xmax) == (up.xmin, up.xmax)
    other = tile_extent(gsd, size, r + dr, c + dc)
    for lo_a, w_a, lo_o, w_o, v, d in ((a.xmin, a.width, other.xmin, other.width, x, dc),
                                       (a.ymin, a.height, other.ymin, other.height, y, dr)):
        assert abs((v - lo_a) / (w_a / size) - (v - lo_o) / (w_o / size) - d * size) <= 1e-6


@settings(max_examples=MATH_EXAMPLES)
@given(gsds, st.integers(64, 512), eastings, northings, heights, st.integers(0, 359), st.integers(5, 90),
       st.floats(0.1, 3.0), st.floats(0.1, 3.0), st.floats(0.0, 3.0))
def test_plan_content_boxes_tile_the_map_without_gaps_or_overlaps(gsd: float, size: int, x: float, y: float,
                                                                  z: float, azimuth: int, elevation: int,
                                                                  wx: float, wy: float, wz: float) -> None:
    """One chunk's plan: each tile's content box (what its job renders) has positive size, lies inside
    its tile on the global pixel grid, and meets its planned neighbour's box exactly at their edge."""
    span = tile_span(gsd, size)
    lo = np.array([x, y, z])
    hi = lo + [wx * span, wy * span, wz * span * math.tan(math.radians(min(elevation, 89)))]
    chunks = [LodChunk("c", "d", frozen([lo.tolist(), hi.tolist()]), (0.0,), (0,), "", "")]
    plan = plan_perspective(Perspective(azimuth, elevation), chunks, [], z, gsd, size, 1.0, "EPSG:32632", {})
    tol = 1e-4 * gsd                                   # metres: 1e-4 px
    boxes = {}
    for tile in plan.tiles:
        e, (w, h) = plan.content(tile)
        t = plan.tile_extent(tile.row, tile.col)
        assert t.xmin - tol <= e.xmin and e.xmax <= t.xmax + tol and t.ymin - tol <= e.ymin and e.ymax <= t.ymax + tol
        for v in (e.xmin - t.xmin, e.ymin - t.ymin):   # whole pixels from the tile's corner
            assert abs(v / gsd - round(v / gsd)) <= 1e-4
        assert abs(e.width - w * gsd) <= tol and abs(e.height - h * gsd) <= tol
        boxes[tile.row, tile.col] = (e, t)
    for (r, c), (e, t) in boxes.items():   # a box reaching the shared edge of two planned tiles
        if (r, c + 1) in boxes and e.xmax >= t.xmax - tol:
            assert e.xmax == boxes[r, c + 1][0].xmin
        if (r + 1, c) in boxes and e.ymax >= t.ymax - tol:
            assert e.ymax == boxes[r + 1, c][0].ymin


def disc_part(centre: np.ndarray, radius: float, segments: int = 64) -> MeshPart:
    """A horizontal regular polygon (its centroid is its centre) as a white vertex-coloured fan."""
    ang = np.linspace(0.0, 2 * np.pi, segments, endpoint=False)
    ring = np.column_stack([np.cos(ang) * radius, np.sin(ang) * radius, np.zeros(segments)])
    verts = np.vstack([centre, centre + ring])
    j = np.arange(segments)
    faces = np.column_stack([np.zeros(segments, int), 1 + j, 1 + (j + 1) % segments])
    return MeshPart(verts, faces, colors=np.full((len(verts), 4), 255, np.uint8))


@pytest.fixture(scope="module")
def renderer(gl_ctx) -> TileRenderer:
    return TileRenderer(gl_ctx, samples=4)


@settings(max_examples=RENDER_EXAMPLES, deadline=None)
@given(st.sampled_from([5e6, 1e7]), st.floats(-500.0, 500.0), st.floats(-500.0, 500.0),
       st.floats(-500.0, 9000.0), azimuths, elevations, st.booleans())
def test_rendered_marker_centroid_matches_projection(renderer: TileRenderer, northing: float, de: float, dn: float,
                                                     z: float, azimuth: float, elevation: float,
                                                     terrain: bool) -> None:
    """A disc rendered through TileRenderer at northings 5e6 / 1e7 has its coverage centroid within
    0.05 px of the analytic projection of its centre (plane mode with z0 = 0, or terrain mode)."""
    gsd, size, radius_px = 0.1, 128, 40
    centre = np.array([500000.0 + de, northing + dn, z])
    part = disc_part(centre, radius_px * gsd)
    origin = chunk_origin(part.bounds() - [[37.0, 11.0, 5.0], [0.0, 0.0, 0.0]])   # a chunk corner, not the disc
    p = Perspective(azimuth, elevation)
    base = z - 0.25 if terrain else 0.0
    want = reference_map(centre[None], azimuth, elevation, base)[0]
    span = tile_span(gsd, size)
    extent = tile_extent(gsd, size, math.floor(want[1] / span), math.floor(want[0] / span), margin_px=size // 2)
    depth = float(np.dot(centre, [math.sin(math.radians(azimuth)) * math.cos(math.radians(elevation)),
                                  math.cos(math.radians(azimuth)) * math.cos(math.radians(elevation)),
                                  -math.sin(math.radians(elevation))]))
    ground = (lambda x, y: np.full(np.shape(x), base)) if terrain else None
    view = TileView(p, 0.0, extent, (depth - 10.0, depth + 10.0), (2 * size, 2 * size), ground)
    rgba = renderer.render_color([(origin, [part])], view)
    alpha = rgba[..., 3].astype(np.float64)
    rows, cols = np.indices(alpha.shape)
    got = np.array([(alpha * (cols + 0.5)).sum(), (alpha * (rows + 0.5)).sum()]) / alpha.sum()
    want_px = np.array([(want[0] - extent.xmin) / gsd, (extent.ymax - want[1]) / gsd])
    assert np.abs(got - want_px).max() <= 0.05, (got, want_px)
