"""The object-id pass (stages.render_ids) against the colour render and analytic geometry."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import box_part, ground_part
from test_render import E0, GSD, N0, SIZE, Z0, view

from pipeline25d.core.mesh import MeshPart
from pipeline25d.geometry.perspectives import Perspective
from pipeline25d.stages.render import TileRenderer
from pipeline25d.stages.render_ids import FACE_TEXTURE_WIDTH, IdRenderer, object_face_ids

GROUND = (E0 + 10.1, N0 + 10.05, E0 + 53.9, N0 + 53.87)
IDS = {"ground": 7, "a": 1_000_001, "b": 4_000_000_123}          # any uint32 but 0


def named(part: MeshPart, key: str) -> MeshPart:
    part.objects, part.face_objects = (key,), np.zeros(part.n_triangles, dtype=np.int32)
    return part


def scene() -> list[tuple[np.ndarray, list[MeshPart]]]:
    """Ground about 10 m inside the tile's edges (off the pixel grid, so its edge pixels are partly
    covered), box a (10 x 10 x 20 m) and box b (8 x 12 x 6 m)."""
    origin = np.array([E0, N0, Z0])
    ground = named(ground_part(*GROUND, Z0), "ground")
    a = named(box_part([E0 + 15, N0 + 15, Z0], [E0 + 25, N0 + 25, Z0 + 20]), "a")
    b = named(box_part([E0 + 35, N0 + 30, Z0], [E0 + 43, N0 + 42, Z0 + 6]), "b")
    return [(origin, [ground, a, b])]


def pixel(x: float, y: float) -> tuple[int, int]:
    """(row, col) of the nadir pixel holding scene point (x, y)."""
    return int((N0 + SIZE * GSD - y) / GSD), int((x - E0) / GSD)


@pytest.mark.parametrize("p", [Perspective(0, 90), Perspective(45, 45), Perspective(200, 30)])
def test_a_pixel_has_an_id_exactly_where_the_colour_tile_is_not_transparent(gl_ctx, p):
    v = view(p)
    rgba = TileRenderer(gl_ctx, samples=4).render_color(scene(), v)
    ids = IdRenderer(gl_ctx, samples=4).render_ids(scene(), v, object_face_ids(IDS))
    assert ids.shape == rgba.shape[:2] and ids.dtype == np.uint32
    assert np.array_equal(ids > 0, rgba[..., 3] > 0)
    assert set(np.unique(ids)) == {0, *IDS.values()}
    edge = (rgba[..., 3] > 0) & (rgba[..., 3] < 255)
    assert edge.sum() > 100                       # there are partly covered pixels, and they have ids


def test_nadir_ids_are_the_footprints(gl_ctx):
    ids = IdRenderer(gl_ctx, samples=4).render_ids(scene(), view(Perspective(0, 90)), object_face_ids(IDS))
    rows, cols = np.mgrid[0:SIZE, 0:SIZE]
    x, y = E0 + (cols + 0.5) * GSD, N0 + SIZE * GSD - (rows + 0.5) * GSD

    def inside(x0, y0, x1, y1, margin=GSD):
        return (x > x0 + margin) & (x < x1 - margin) & (y > y0 + margin) & (y < y1 - margin)

    a, b = inside(E0 + 15, N0 + 15, E0 + 25, N0 + 25), inside(E0 + 35, N0 + 30, E0 + 43, N0 + 42)
    ground = inside(*GROUND) & ~inside(E0 + 15, N0 + 15, E0 + 25, N0 + 25, -GSD) \
        & ~inside(E0 + 35, N0 + 30, E0 + 43, N0 + 42, -GSD)
    outside = ~inside(*GROUND, -GSD)
    assert (ids[a] == IDS["a"]).all() and (ids[b] == IDS["b"]).all() and (ids[ground] == IDS["ground"]).all()
    assert (ids[outside] == 0).all() and a.sum() == 38 ** 2 and outside.sum() > 10_000


def test_an_oblique_view_shows_the_roof_and_hides_the_ground_behind_the_box(gl_ctx):
    """At 45° a box's roof is drawn shifted by its height along the map's height direction d: the
    roof centre lands where the shift puts it, the ground between the box's foot and its shifted
    roof is hidden by the box, and open ground far from it is ground."""
    from pipeline25d.geometry.camera import map_affine

    p = Perspective(45, 45)
    ids = IdRenderer(gl_ctx, samples=4).render_ids(scene(), view(p), object_face_ids(IDS))
    A, b = map_affine(p, Z0)

    def at(x: float, y: float, z: float) -> tuple[int, int]:
        mx, my, _ = A @ np.array([x, y, z]) + b
        return int((N0 + SIZE * GSD - my) / GSD), int((mx - E0) / GSD)

    shift = A[:2, 2] * 20.0                                   # roof of a, 20 m up
    assert np.linalg.norm(shift) == pytest.approx(20.0)       # cot 45° = 1
    assert ids[at(E0 + 20, N0 + 20, Z0 + 20)] == IDS["a"]
    hidden = np.array([E0 + 20, N0 + 20]) + 0.75 * shift      # ground the box stands in front of
    assert ids[at(*hidden, Z0)] == IDS["a"]
    assert ids[at(*(np.array([E0 + 20, N0 + 20]) - 0.45 * shift), Z0)] == IDS["ground"]
    assert ids[at(E0 + 50, N0 + 12, Z0)] == IDS["ground"]


def test_parts_of_many_faces_keep_each_face_id(gl_ctx):
    """A ground grid of 120 x 120 cells (28,800 faces, past one row of the face-id texture) whose
    faces carry the id of their cell column: each nadir pixel shows its column's id."""
    n, cell = 120, 0.5
    xs = E0 + 2 + np.arange(n + 1) * cell
    ys = N0 + 2 + np.arange(n + 1) * cell
    gx, gy = np.meshgrid(xs, ys)
    vertices = np.c_[gx.ravel(), gy.ravel(), np.full(gx.size, Z0)]
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    faces = np.r_[np.c_[a, b, d], np.c_[a, d, c]]
    column = np.r_[np.tile(np.arange(n), n), np.tile(np.arange(n), n)]
    assert len(faces) > FACE_TEXTURE_WIDTH * 7
    part = MeshPart(vertices, faces, colors=np.full((len(vertices), 4), 200, np.uint8))
    ids = IdRenderer(gl_ctx, samples=4).render_ids([(np.array([E0, N0, Z0]), [part])], view(Perspective(0, 90)),
                                                   lambda _: (column + 1).astype(np.uint32))
    rows, cols = np.mgrid[0:SIZE, 0:SIZE]
    x = E0 + (cols + 0.5) * GSD
    y = N0 + SIZE * GSD - (rows + 0.5) * GSD
    inside = (x > xs[0]) & (x < xs[-1]) & (y > ys[0]) & (y < ys[-1])
    expected = np.floor((x - xs[0]) / cell).astype(np.int64) + 1
    assert inside.sum() > 50_000 and np.array_equal(ids[inside], expected[inside])


def test_terrain_relative_ids_follow_the_colour_render(gl_ctx):
    """With a DTM (terrain-relative projection) the id pass moves vertices as the colour pass does."""
    from dataclasses import replace

    v = replace(view(Perspective(135, 35)), ground=lambda x, y: Z0 + 0.3 * (x - E0) - 0.2 * (y - N0))
    rgba = TileRenderer(gl_ctx, samples=4).render_color(scene(), v)
    ids = IdRenderer(gl_ctx, samples=4).render_ids(scene(), v, object_face_ids(IDS))
    assert np.array_equal(ids > 0, rgba[..., 3] > 0) and (ids > 0).sum() > 10_000


@pytest.mark.parametrize("terrain", [False, True])
def test_ids_drawn_in_the_colour_pass_from_ingested_parts_equal_ids_drawn_from_the_parts(gl_ctx, terrain):
    """The render job draws the ids in its colour pass from the geometry it uploaded, in plane and
    terrain mode: the same pixels as the ids drawn from the parts, and ingested parts' own object
    ids (part_face_ids) give what a key -> id table gives."""
    from dataclasses import replace

    from pipeline25d.stages.render_ids import part_face_ids

    v = view(Perspective(135, 35))
    if terrain:
        v = replace(v, ground=lambda x, y: Z0 + 0.3 * (x - E0) - 0.2 * (y - N0))
    chunks = [(origin, [replace(p, object_ids=np.array([IDS[k] for k in p.objects], np.uint32)) for p in parts])
              for origin, parts in scene()]
    colour, ids = TileRenderer(gl_ctx, samples=4, ids=True), IdRenderer(gl_ctx, samples=4)
    direct = ids.render_ids(scene(), v, object_face_ids(IDS))
    with colour.upload(chunks, v) as geometry:
        rgba, shared = ids.with_colour(colour, geometry, v, part_face_ids)
    assert np.array_equal(shared, direct) and np.array_equal(shared > 0, rgba[..., 3] > 0)
    assert set(np.unique(shared)) == {0, *IDS.values()}


@pytest.mark.parametrize("p, samples", [(Perspective(0, 90), 4), (Perspective(45, 45), 4), (Perspective(200, 30), 4),
                                        (Perspective(45, 45), 0)])
def test_ids_drawn_beside_the_colours_equal_the_separate_id_pass(gl_ctx, p, samples):
    """One pass with two render targets (the colour program writes each fragment's face id too)
    against the id pass's own program: the same ids, and the colour tile byte-identical to a renderer
    without ids."""
    v = view(p)
    plain = TileRenderer(gl_ctx, samples=samples).render_color(scene(), v)
    ids_alone = IdRenderer(gl_ctx, samples=samples).render_ids(scene(), v, object_face_ids(IDS))
    renderer = TileRenderer(gl_ctx, samples=samples, ids=True)
    with renderer.upload(scene(), v) as geometry:
        rgba, ids = IdRenderer(gl_ctx, samples=samples).with_colour(renderer, geometry, v, object_face_ids(IDS))
        again = renderer.render_color(geometry, v)          # the ids program without ids: same colours
    assert np.array_equal(rgba, plain) and np.array_equal(again, plain)
    assert np.array_equal(ids, ids_alone)
    assert np.array_equal(ids > 0, rgba[..., 3] > 0)
    assert set(np.unique(ids)) == {0, *IDS.values()}
