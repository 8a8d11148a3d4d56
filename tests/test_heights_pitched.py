"""Pitched roofs (analysis.heights.pitched): the roof frame, the gable's silhouette excess, and the
rise found from two faces' colours on a synthetic oblique map drawn here by forward projection."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pipeline25d.analysis.heights.pitched import fit_rise, line_excess, rise_share, roof_frame, roof_ground
from pipeline25d.formats.footprints import Footprint

ANGLE = math.radians(30)
ALONG = np.array([math.cos(ANGLE), math.sin(ANGLE)])
ACROSS = np.array([-ALONG[1], ALONG[0]])
HALF_L, HALF_W = 9.0, 5.0


def _house() -> Footprint:
    corners = [s * HALF_L * ALONG + t * HALF_W * ACROSS for s, t in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
    return Footprint("h", (np.array(corners) + [100.0, 200.0],))


def test_frame_and_shares_of_a_rotated_house():
    fp = _house()
    f = roof_frame(fp)
    assert (f.centre == pytest.approx([100.0, 200.0])
            and (f.half_length, f.half_width) == pytest.approx((HALF_L, HALF_W)))
    assert abs(f.along @ ALONG) == pytest.approx(1.0)
    c = np.array([100.0, 200.0])
    pts = np.array([c, c + 2.5 * ACROSS, c + 5 * ACROSS, c + 8 * ALONG, c + 10 * ALONG])
    assert rise_share(f, "gabled", pts[:, 0], pts[:, 1]) == pytest.approx([1.0, 0.5, 0.0, 1.0, 0.0])
    # hipped: the ridge ends half the width in from the ends, the ends slope like the sides
    assert rise_share(f, "hipped", pts[:, 0], pts[:, 1]) == pytest.approx([1.0, 0.5, 0.0, 0.2, 0.0])


@pytest.mark.parametrize("rise", [2.0, 4.0, 7.0])
def test_gable_and_eave_lines_end_where_the_geometry_says(rise):
    fp = _house()
    c = np.array([100.0, 200.0])
    cot = 1.0                                            # elevation 45°
    # a line from the gable end's middle, the view along the ridge: the gable's apex, the rise
    gable = c + HALF_L * ALONG
    assert line_excess(fp, "gabled", rise, gable[None], ALONG, cot)[0] == pytest.approx(rise)
    # a line from the middle of an eave, the view across: the far face hides the ridge unless it is
    # steeper than the view (rise / half width > tan 45°), then the ridge ends it
    eave = c + HALF_W * ACROSS
    want = max(0.0, rise - HALF_W / cot)
    assert line_excess(fp, "gabled", rise, eave[None], ACROSS, cot)[0] == pytest.approx(want, abs=0.06)


@pytest.mark.parametrize("slope", [0.3, 0.8, 1.4])
@pytest.mark.parametrize("kind", ["gabled", "hipped"])
def test_ground_falling_towards_the_viewer_draws_the_roof_farther_out(slope, kind):
    """On a planar ground rising ``slope`` m per m along the view (the map subtracts it under every
    roof point), a line from an eave's middle, the view across the ridge, ends at the farthest of
    the roof's far eave (t = 0), its ridge (t = W) and its near eave (t = 2W): each drawn at its
    height above its own ground, G(e) − G(q) = slope·t higher than the line's start says."""
    fp = _house()
    c = np.array([100.0, 200.0])
    cot = 1 / math.tan(math.radians(30))

    def ground(x, y):                                    # rises along ACROSS, any level
        return 50.0 + slope * ((np.asarray(x) - c[0]) * ACROSS[0] + (np.asarray(y) - c[1]) * ACROSS[1])

    eave = c + HALF_W * ACROSS
    for rise in (0.0, 2.0, 4.0):
        want = max(0.0, rise + (slope - 1 / cot) * HALF_W, (slope - 1 / cot) * 2 * HALF_W)
        got = line_excess(fp, kind, rise, eave[None], ACROSS, cot, ground)[0]
        assert got == pytest.approx(want, abs=0.02), (rise, got, want)
    # level ground: as without it
    flat = line_excess(fp, kind, 3.0, eave[None], ACROSS, cot, lambda x, y: np.full(np.shape(x), 7.0))
    assert flat == pytest.approx(line_excess(fp, kind, 3.0, eave[None], ACROSS, cot))



@pytest.mark.parametrize("kind", ["flat", "gabled", "hipped"])
def test_roof_ground_is_the_renderers_interpolation_of_its_vertices(kind):
    """The renderer interpolates the DTM at the roof's vertices linearly across each face: on planar
    ground that is the plane itself at every roof point (hip end triangles and side trapezoids
    included), and at the vertices it is the DTM there whatever the ground."""
    fp = _house()
    f = roof_frame(fp)
    rng = np.random.default_rng(3)
    a, b = rng.uniform(-HALF_L, HALF_L, 400), rng.uniform(-HALF_W, HALF_W, 400)
    xy = f.centre + a[:, None] * ALONG + b[:, None] * ACROSS
    share = rise_share(f, kind, xy[:, 0], xy[:, 1]) if kind != "flat" else np.zeros(len(xy))

    def plane(x, y):
        return 300.0 + 0.7 * np.asarray(x) - 0.4 * np.asarray(y)

    assert roof_ground(f, kind, plane, xy[:, 0], xy[:, 1], share) == pytest.approx(plane(xy[:, 0], xy[:, 1]), abs=1e-9)

    def bumpy(x, y):
        return 10.0 * np.sin(np.asarray(x) / 3.0) + np.asarray(y) ** 2 / 50.0

    r = HALF_L - HALF_W if kind == "hipped" else HALF_L
    verts = [f.centre + s * HALF_L * ALONG + t * HALF_W * ACROSS for s in (-1, 1) for t in (-1, 1)]
    shares = [0.0] * 4
    if kind != "flat":
        verts += [f.centre - r * ALONG, f.centre + r * ALONG]
        shares += [1.0, 1.0]
    v = np.array(verts)
    got = roof_ground(f, kind, bumpy, v[:, 0], v[:, 1], np.array(shares))
    assert got == pytest.approx(bumpy(v[:, 0], v[:, 1]), abs=1e-9)

def test_two_faces_colours_give_the_rise_and_the_kind():
    """Roof faces of two colours, drawn at q + (eave + rise·share(q))·cot·d on a fine grid; the fit
    finds the rise it was drawn with, and a flat roof of one colour stays flat."""
    fp = _house()
    f = roof_frame(fp)
    cot, d = 1 / math.tan(math.radians(45)), np.array([math.sin(math.radians(200)), math.cos(math.radians(200))])
    eave, rise = 12.0, 3.4
    cell = 0.05
    x0, y0, n = 60.0, 160.0, 1600                        # a 80 m square of 5 cm cells
    ground, light, dark = np.array([60.0, 140, 50]), np.array([200.0, 90, 70]), np.array([120.0, 50, 40])

    def face(q: np.ndarray) -> np.ndarray:
        return np.where(((q - f.centre) @ f.across > 0)[:, None], light, dark)

    def draw(r: float, two_faces: bool) -> np.ndarray:
        img = np.tile(ground, (n, n, 1))
        g = np.arange(-HALF_L, HALF_L, cell / 2)
        h = np.arange(-HALF_W, HALF_W, cell / 2)
        q = (f.centre + g[:, None, None] * f.along + h[None, :, None] * f.across).reshape(-1, 2)
        share = rise_share(f, "gabled", q[:, 0], q[:, 1])
        order = np.argsort(share)                        # higher roof drawn last (over lower)
        p = q[order] + ((eave + r * share[order]) * cot)[:, None] * d
        col = face(q[order]) if two_faces else np.tile(light, (len(order), 1))
        ci, ri = ((p[:, 0] - x0) / cell).astype(int), ((p[:, 1] - y0) / cell).astype(int)
        img[ri, ci] = col
        return img

    rng = np.random.default_rng(1)
    q = (f.centre + rng.uniform(-0.9, 0.9, (400, 1)) * HALF_L * f.along
         + rng.uniform(-0.9, 0.9, (400, 1)) * HALF_W * f.across)
    for two, want_kind, want_rise in ((True, "gabled", rise), (False, "flat", 0.0)):
        img = draw(rise if two else 0.0, two)
        colour = face(q) if two else np.tile(light, (len(q), 1))

        def sample(u: np.ndarray, img=img) -> np.ndarray:       # (k, n) moves -> (k, n, 3) colours
            p = q + u[..., None] * d
            return img[((p[..., 1] - y0) / cell).astype(int), ((p[..., 0] - x0) / cell).astype(int)]

        got = fit_rise(fp, q, colour, sample, np.full(len(q), eave * cot), cot, 30.0)
        assert got.kind == want_kind
        assert got.rise == pytest.approx(want_rise, abs=0.15)


def test_a_view_that_fits_a_flat_roof_makes_it_flat_only_where_no_rise_fits_it_better():
    """ridge_height: a view whose flat roof fits within FLAT_FIT says flat only when its own fit
    found no rise; a view whose faces look alike (flat fits well) but whose rise fits better still
    leaves the ridge to the rises (their median above the eave)."""
    from pipeline25d.analysis.heights.pitched import FLAT_FIT, RiseFit, ridge_height

    good = FLAT_FIT / 2
    assert ridge_height({"a": RiseFit(0.0, "flat", good, good), "b": RiseFit(2.9, "gabled", 0.3, 0.1)}, 10.0) \
        == (10.0, "flat")
    ridge, kind = ridge_height({"a": RiseFit(3.1, "gabled", good, good / 4), "b": RiseFit(2.9, "gabled", 0.3, 0.1)},
                               10.0)
    assert kind == "gabled" and ridge == pytest.approx(10.0 + (3.1 + 2.9) / 2)
    # a view that does not show the roof (loss above MAX_LOSS) says nothing
    assert ridge_height({"a": RiseFit(3.0, "hipped", 0.9, 0.8)}, 10.0)[1] == ""


def test_views_ridges_that_disagree_are_settled_by_the_silhouettes_gable():
    """A view ridge fitted from a wrong eave: where the views' ridges differ by more than 1 m, the
    gable end's silhouette lines (a line from the gable at offset c across ends rise·(1 − |c|/W)
    above the eave when the view looks along the ridge) pick the view ridge near eave + rise, else
    give that ridge themselves; lines of a flat outline leave the row as it was."""
    from pipeline25d.analysis.heights.results import HeightRow, MatchSettings
    from pipeline25d.analysis.heights.silhouette import Lines
    from pipeline25d.analysis.heights.views import _ridge_checked
    from pipeline25d.geometry.camera import horizontal_direction
    from pipeline25d.geometry.perspectives import Perspective

    fp = _house()
    pid = next(f"az{a:03d}_el45" for a in range(360)
               if abs(horizontal_direction(Perspective.from_id(f"az{a:03d}_el45")) @ ALONG) > 0.9999)
    d = horizontal_direction(Perspective.from_id(pid))
    eave, rise = 12.0, 3.5
    c = np.linspace(-0.9 * HALF_W, 0.9 * HALF_W, 19)
    xy = np.array([100.0, 200.0]) + np.sign(d @ ALONG) * HALF_L * ALONG + c[:, None] * ACROSS
    gable = {pid: Lines(xy, eave + rise * (1 - np.abs(c) / HALF_W), 0.2)}
    flat = {pid: Lines(xy, np.full(len(c), eave), 0.2)}

    def row(*ridges: float) -> HeightRow:
        return HeightRow("h", {}, {}, {}, 2, 2, eave, 1.0, {}, max(ridges), "gabled", dict(zip(("v1", "v2"), ridges)))

    def checked(r: HeightRow, lines: dict) -> HeightRow:
        return _ridge_checked(fp, r, {}, lines, {pid: 1.0}, MatchSettings(), None)

    got = checked(row(eave + rise + 3.0, eave + rise + 0.3), gable)
    assert got.ridge == pytest.approx(eave + rise + 0.3) and math.isnan(got.ridges["v1"])
    got = checked(row(eave + rise + 3.0, eave), gable)
    assert got.roof == "gabled" and got.ridge == pytest.approx(eave + rise, abs=0.15)
    assert checked(row(eave + rise + 3.0, eave), flat).ridge == pytest.approx(eave + rise + 3.0)
    assert checked(row(eave + rise + 0.6, eave + rise), gable).ridge == pytest.approx(eave + rise + 0.6)   # agree
