"""Sun shadows: the sun's position against published values, shadow geometry against analytic
lengths, shadow casters across tile borders, and no seams between tiles."""

from __future__ import annotations

import math
from datetime import datetime

import numpy as np
import pytest
from conftest import box_part, ground_part

from pipeline25d.core.errors import ConfigError
from pipeline25d.core.mesh import MeshPart
from pipeline25d.geometry.camera import Extent, project
from pipeline25d.geometry.perspectives import Perspective
from pipeline25d.geometry.sun import (
    BIAS_TEXELS,
    PCF_RADIUS,
    Sun,
    SunFrame,
    resolve_sun,
    shadow_footprints,
    sun_position,
)
from pipeline25d.stages.plan import plan_perspective
from pipeline25d.stages.records import ChunkGround, LodChunk, frozen
from pipeline25d.stages.render import ShadowView, TileRenderer, TileView
from pipeline25d.stages.render_block import render_plan_tile

E0, N0, Z0 = 691008.0, 5334016.0, 500.0   # UTM-sized, on the 64 m tile grid used below
GREY = 200


# -- the sun's position ------------------------------------------------------------------------
def test_sun_from_datetime_matches_the_nrel_spa_reference():
    """Reda & Andreas (2004), Solar Position Algorithm, Table A5.1: Golden, Colorado, 17 Oct 2003
    12:30:30 at UTC-7: azimuth 194.340241°, topocentric elevation 39.888378° with refraction."""
    sun = sun_position(datetime.fromisoformat("2003-10-17T12:30:30-07:00"), -105.1786, 39.742476)
    assert abs(sun.azimuth - 194.340241) < 0.1 and abs(sun.elevation - 39.888378) < 0.1, sun


def test_sun_at_solstice_noon_stands_due_south_at_90_minus_latitude_plus_obliquity():
    """A second, geometric check: at solar noon on the June solstice (2024-06-20) the sun stands
    due south of latitude 40° N at 90 − 40 + 23.44° (the ecliptic's obliquity; refraction adds
    under 0.01° there). Near noon at 73° the azimuth turns about 0.9° a minute, so astral's
    noon (to the second) pins it to 1°; the elevation is at its flat maximum."""
    from astral import Observer
    from astral.sun import noon

    when = noon(Observer(latitude=40.0, longitude=-105.0), datetime(2024, 6, 20).date())
    sun = sun_position(when, -105.0, 40.0)
    assert abs(sun.azimuth - 180.0) < 1.0 and abs(sun.elevation - (90 - 40 + 23.44)) < 0.1, sun


def test_the_sun_below_the_horizon_is_a_config_error_naming_the_key():
    night = {"enabled": True, "datetime": "2024-06-21T01:00:00+02:00"}
    with pytest.raises(ConfigError, match="shadows.datetime.*below the horizon"):
        resolve_sun(night, (4.36, 52.01))
    day = resolve_sun({**night, "datetime": "2024-06-21T14:00:00+02:00"}, (4.36, 52.01))
    assert 150 < day.azimuth < 240 and day.elevation > 50


# -- analytic shadow geometry ---------------------------------------------------------------------
def _view(p: Perspective, size: int, gsd: float, ground=None) -> TileView:
    ext = Extent(E0, N0, E0 + size * gsd, N0 + size * gsd)
    corners = np.array([[E0 + dx, N0 + dy, Z0 + dz] for dx in (-100, 200) for dy in (-100, 200) for dz in (-20, 80)])
    depth = project(corners, p, Z0)[:, 2]
    return TileView(p, Z0, ext, (float(depth.min()), float(depth.max())), (size, size), ground)


def _shadow(sun: Sun, texel: float, boxes: list[np.ndarray], ambient: float = 0.5) -> ShadowView:
    frame = SunFrame(sun, texel)
    return ShadowView(frame, frame.window(boxes), frame.depth_range(boxes), ambient, BIAS_TEXELS * texel, PCF_RADIUS)


def _edge(image: np.ndarray, gsd: float, start: np.ndarray, step: np.ndarray, level: float) -> np.ndarray:
    """Where brightness first rises through ``level`` walking from map point ``start`` along unit
    ``step`` (pixel by pixel, linear between pixel centres): the map point, float64."""
    top = N0 + image.shape[0] * gsd
    prev = None
    for k in range(400):
        pt = start + k * gsd * step
        col, row = int((pt[0] - E0) / gsd), int((top - pt[1]) / gsd)
        centre = np.array([E0 + (col + 0.5) * gsd, top - (row + 0.5) * gsd])
        along = float((centre - start) @ step)          # pixel centre's position along the walk
        value = float(image[row, col])
        if prev is not None and value >= level > prev[1]:
            return start + (prev[0] + (level - prev[1]) / (value - prev[1]) * (along - prev[0])) * step
        prev = (along, value)
    raise AssertionError("no edge found")


@pytest.mark.parametrize("azimuth, elevation", [(180, 45), (90, 30), (135, 35), (300, 60), (20, 50)])
def test_a_boxs_shadow_on_the_nadir_map_is_h_cot_elevation_long_and_falls_away_from_the_sun(gl_ctx, azimuth,
                                                                                              elevation):
    gsd, size, h = 0.25, 320, 20.0
    x0, y0, x1, y1 = E0 + 37, N0 + 37, E0 + 43, N0 + 43          # a 6 m square tower in the middle
    parts = [ground_part(E0 - 60, N0 - 60, E0 + 140, N0 + 140, Z0, (GREY, GREY, GREY, 255)),
             box_part((x0, y0, Z0), (x1, y1, Z0 + h))]
    sun = Sun(azimuth, elevation)
    view = _view(Perspective(0, 90), size, gsd)
    shadow = _shadow(sun, 0.75 * gsd, [np.array([[E0 - 60, N0 - 60, Z0], [E0 + 140, N0 + 140, Z0 + h]])])
    rgba = TileRenderer(gl_ctx, shadows=True).render_color([(np.array([x0, y0, Z0]), parts)], view, shadow)
    red = rgba[..., 0].astype(float)
    lit, dark = GREY * (0.5 + 0.5 * math.sin(math.radians(elevation))), GREY * 0.5    # ground: Lambert by the sun
    v = sun.away() * h / math.tan(math.radians(elevation))                           # the roof's shadow offset
    mid = np.array([(x0 + x1) / 2, (y0 + y1) / 2])

    def at(pt):
        return red[int((N0 + size * gsd - pt[1]) / gsd), int((pt[0] - E0) / gsd)]

    assert abs(at(mid + 0.75 * v) - dark) <= 1.5            # in the shadow, away from the sun
    assert abs(at(mid - 0.75 * v) - lit) <= 1.5             # on the sun's side: lit
    assert abs(at(mid + 1.6 * v) - lit) <= 1.5              # past the shadow's end: lit
    # The roof edges facing away from the sun cast the shadow's far edges: x0/x1 + v_x and y0/y1 + v_y.
    for axis in (0, 1):
        if abs(v[axis]) < 0.15 * np.linalg.norm(v):
            continue
        sign = np.sign(v[axis])
        expected = (x1, y1)[axis] if sign > 0 else (x0, y0)[axis]
        expected += v[axis]
        start = mid + 0.75 * v
        start[1 - axis] = mid[1 - axis] + v[1 - axis]        # across the middle of that edge's shadow
        found = _edge(red, gsd, start, np.eye(2)[axis] * sign, (lit + dark) / 2)
        assert abs(found[axis] - expected) <= 0.5 * gsd, (axis, found[axis] - expected)


def test_terrain_mode_casts_shadows_by_true_3d_positions_on_sloped_ground(gl_ctx):
    """Ground rising north at slope s, sun due south at elevation e: a wall of height h casts its
    shadow h / (tan e + s) up the slope. On a terrain-relative map ground lands at its own (x, y),
    in every view; the roof (drawn displaced) stays lit."""
    gsd, size, h, s, e = 0.25, 320, 15.0, 0.1, 40.0
    z = lambda x, y: Z0 + s * (np.asarray(y) - N0)
    x0, y0, x1, y1 = E0 + 35, N0 + 20, E0 + 45, N0 + 30
    verts = np.array([[E0 - 60, N0 - 60], [E0 + 140, N0 - 60], [E0 + 140, N0 + 140], [E0 - 60, N0 + 140]], float)
    ground = MeshPart(np.column_stack([verts, z(verts[:, 0], verts[:, 1])]), np.array([[0, 1, 2], [0, 2, 3]]),
                      colors=np.tile(np.array([GREY, GREY, GREY, 255], np.uint8), (4, 1)))
    base = float(z(0, y0))
    box = box_part((x0, y0, base - 1.0), (x1, y1, z(0, y1) + h), rgba=(GREY, GREY, GREY, 255))
    sun = Sun(180, e)
    reach = h / (math.tan(math.radians(e)) + s)
    shadow = _shadow(sun, 0.75 * gsd, [np.array([[E0 - 60, N0 - 60, Z0 - 10], [E0 + 140, N0 + 140, Z0 + 40]])])
    renderer = TileRenderer(gl_ctx, shadows=True)
    slope_normal = np.array([0.0, -s, 1.0]) / math.hypot(s, 1.0)
    lit = GREY * (0.5 + 0.5 * float(slope_normal @ sun.toward()))
    for p in (Perspective(0, 90), Perspective(90, 45)):      # from the east the tower leans east, off the edge
        rgba = renderer.render_color([(np.array([x0, y0, base]), [ground, box])], _view(p, size, gsd, z), shadow)
        red = rgba[..., 0].astype(float)
        found = _edge(red, gsd, np.array([(x0 + x1) / 2, y1 + reach / 2]), np.array([0.0, 1.0]), (lit + GREY * 0.5) / 2)
        assert abs(found[1] - (y1 + reach)) <= 0.5 * gsd, (p, found[1] - (y1 + reach))
    roof = red[int((N0 + size * gsd - (y0 + y1) / 2) / gsd), int(((x0 + x1) / 2 + h * 1.0 - E0) / gsd)]
    assert abs(roof - GREY * (0.5 + 0.5 * math.sin(math.radians(e)))) <= 1.5       # lit, not self-shadowed


# -- plans: casters within shadow reach ------------------------------------------------------------
def _chunk(cid: str, lo, hi) -> LodChunk:
    return LodChunk(cid, "d", frozen([list(map(float, lo)), list(map(float, hi))]), (0.0,), (0,), "", "")


def _shadows(sun: Sun, texel: float, ambient: float = 0.5) -> dict:
    return {"azimuth": sun.azimuth, "elevation": sun.elevation, "source": "test", "texel": texel, "ambient": ambient,
            "radius": PCF_RADIUS, "bias": BIAS_TEXELS * texel}


def _inside_hull(pts: np.ndarray, hull: np.ndarray) -> np.ndarray:
    """(n,) bool: points inside a convex polygon (counter-clockwise vertices)."""
    inside = np.ones(len(pts), dtype=bool)
    for a, b in zip(hull, np.roll(hull, -1, axis=0)):
        inside &= (b[0] - a[0]) * (pts[:, 1] - a[1]) - (b[1] - a[1]) * (pts[:, 0] - a[0]) >= -1e-9
    return inside


def test_a_tile_plans_every_chunk_whose_shadow_can_reach_it_and_not_the_far_ones():
    """Ground chunks of 40 m and a 60 m tower; sun south-west at 30°: its shadow (the hull of its
    footprint and the footprint moved 60·cot 30° = 103.9 m north-east) must be planned into every
    32 m tile it touches, and into no tile far from it."""
    sun, gsd, size = Sun(225, 30), 0.5, 64
    chunks = [_chunk(f"g{i}{j}", (E0 + 40 * i, N0 + 40 * j, Z0), (E0 + 40 * i + 40, N0 + 40 * j + 40, Z0 + 0.5))
              for i in range(6) for j in range(6)]
    chunks.append(_chunk("tower", (E0 + 60, N0 + 60, Z0), (E0 + 80, N0 + 80, Z0 + 60)))
    plan = plan_perspective(Perspective(0, 90), chunks, [], Z0, gsd, size, 1.0, "EPSG:25832", {}, None,
                            _shadows(sun, 0.75 * gsd))
    v = sun.away() * 60 / math.tan(math.radians(30))
    foot = np.array([[E0 + 60, N0 + 60], [E0 + 80, N0 + 60], [E0 + 80, N0 + 80], [E0 + 60, N0 + 80]])
    hull = np.array([foot[0], foot[1], foot[1] + v, foot[2] + v, foot[3] + v, foot[3]])   # counter-clockwise
    span = gsd * size
    margin = SunFrame(sun, 0.75 * gsd).ground_margin()
    with_tower, reached = set(), set()
    for t in plan.tiles:
        ids = {c.id for c in (*t.chunks, *t.casters)}
        assert not {c.id for c in t.chunks} & {c.id for c in t.casters}
        xs, ys = np.meshgrid(np.linspace(t.col * span, (t.col + 1) * span, 33),
                             np.linspace(t.row * span, (t.row + 1) * span, 33))
        if _inside_hull(np.column_stack([xs.ravel(), ys.ravel()]), hull).any():
            reached.add((t.row, t.col))
        if "tower" in ids:
            with_tower.add((t.row, t.col))
            # never beyond the shadow's bounding box grown by the filter's margin
            assert (t.col * span < hull[:, 0].max() + margin and (t.col + 1) * span > hull[:, 0].min() - margin
                    and t.row * span < hull[:, 1].max() + margin and (t.row + 1) * span > hull[:, 1].min() - margin)
    assert reached <= with_tower and len(reached) >= 9
    assert len(with_tower) <= len(reached) + 8 < len(plan.tiles)


def test_a_shadow_footprint_reaches_down_to_the_lowest_ground_it_can_fall_on():
    """A 20 m tower on a 30 m plateau beside a valley floor at 0: with the sun at 45° its shadow can
    run 50 m beyond the tower (down to the valley), not just the 20 m to its own floor."""
    sun = Sun(270, 45)                                   # sun in the west: shadows fall east
    bounds = np.array([[[0, 0, 30], [10, 10, 50]],       # tower on the plateau
                       [[-40, -10, 29], [20, 20, 30]],   # the plateau
                       [[20, -10, 0], [200, 20, 1]]])    # the valley floor, east of it
    foot = shadow_footprints(bounds, sun)
    assert np.allclose(foot[0], [0, 0, 10 + 50, 10])
    alone = shadow_footprints(bounds[:1], sun)           # nothing lower around: its own floor
    assert np.allclose(alone[0], [0, 0, 10 + 20, 10])


def test_changed_sun_rehashes_every_tile_and_no_shadows_plans_as_before():
    chunks = [_chunk(f"g{i}", (E0 + 40 * i, N0, Z0), (E0 + 40 * i + 40, N0 + 40, Z0 + 10)) for i in range(4)]
    args = (Perspective(45, 45), chunks, [], Z0, 0.5, 64, 1.0, "EPSG:25832", {"samples": 4})
    plain = plan_perspective(*args)
    assert plan_perspective(*args, None, None) == plain and plain.shadows is None
    assert all(t.shadow is None for t in plain.tiles)
    a = plan_perspective(*args, None, _shadows(Sun(200, 40), 0.375))
    b = plan_perspective(*args, None, _shadows(Sun(201, 40), 0.375))
    c = plan_perspective(*args, None, _shadows(Sun(200, 40), 0.375, ambient=0.6))
    hashes = lambda plan: [t.spec_hash for t in plan.tiles]
    assert len(plain.tiles) == len(a.tiles)
    for other in (plain, b, c):
        assert all(x != y for x, y in zip(hashes(a), hashes(other)))


def test_render_settings_carry_shadows_only_when_enabled():
    import copy

    from pipeline25d.config import render_settings, validate_schema

    base = validate_schema({"scene": "t", "crs": "EPSG:25832", "inputs": {"a": {"path": "m.obj"}}})
    off = copy.deepcopy(base)
    off["shadows"].update({"azimuth": 100, "elevation": 30})
    on = copy.deepcopy(off)
    on["shadows"]["enabled"] = True
    assert render_settings(off) == render_settings(base) and "shadows" not in render_settings(base)
    assert render_settings(on)["shadows"] == {"azimuth": 100, "elevation": 30, "ambient": 0.5, "texel_px": 0.75}


# -- rendering plans: shadows across tile borders, no seams -----------------------------------------
def _render_plan(gl_ctx, plan, loaded: dict, ground=None, casters: bool = True) -> dict:
    renderer = TileRenderer(gl_ctx, shadows=plan.shadows is not None)
    out = {}
    for t in plan.tiles:
        own = [loaded[c.id] for c in t.chunks]
        cast = [loaded[c.id] for c in t.casters] if casters else []
        out[(t.row, t.col)] = render_plan_tile(renderer, plan, t, own, ground, cast)[0]
    return out


def _mosaic(plan, rendered: dict, extent: Extent) -> np.ndarray:
    """The rendered tiles pasted on ``extent``'s pixel grid (the plan's gsd): (h, w, 4) uint8."""
    gsd = plan.gsd
    out = np.zeros((round(extent.height / gsd), round(extent.width / gsd), 4), np.uint8)
    for t in plan.tiles:
        e, (w, h) = plan.content(t)
        c0, r0 = round((e.xmin - extent.xmin) / gsd), round((extent.ymax - e.ymax) / gsd)
        rc0, rr0 = max(c0, 0), max(r0, 0)
        rc1, rr1 = min(c0 + w, out.shape[1]), min(r0 + h, out.shape[0])
        if rc0 < rc1 and rr0 < rr1:
            out[rr0:rr1, rc0:rc1] = rendered[(t.row, t.col)][rr0 - r0:rr1 - r0, rc0 - c0:rc1 - c0]
    return out


def test_a_tall_buildings_shadow_falls_into_the_neighbouring_tiles(gl_ctx):
    """A 40 m tower near the east edge of tile A, sun in the west at 35°: its shadow (57 m) crosses
    tile B east of it and ends 23 m into tile C. B and C, rendered from their plans, are darkened
    there because their plans list the tower among their shadow casters; without them they are lit."""
    gsd, size = 0.5, 64                                   # 32 m tiles
    sun = Sun(270, 35)
    parts = {f"g{i}": [ground_part(E0 + 32 * i, N0, E0 + 32 * i + 32, N0 + 32, Z0, (GREY, GREY, GREY, 255))]
             for i in range(4)}
    parts["tower"] = [box_part((E0 + 24, N0 + 12, Z0), (E0 + 30, N0 + 20, Z0 + 40))]
    chunks = [_chunk(k, np.min([p.vertices.min(0) for p in v], 0), np.max([p.vertices.max(0) for p in v], 0))
              for k, v in parts.items()]
    loaded = {c.id: (np.array(c.bounds[0]), parts[c.id]) for c in chunks}
    plan = plan_perspective(Perspective(0, 90), chunks, [], Z0, gsd, size, 1.0, "EPSG:25832", {"samples": 4}, None,
                            _shadows(sun, 0.75 * gsd))
    row0, col0 = int(N0 // 32), int(E0 // 32)
    a, b, c = (row0, col0), (row0, col0 + 1), (row0, col0 + 2)
    tiles = {(t.row, t.col): t for t in plan.tiles}
    assert "tower" in {e.id for e in tiles[a].chunks}
    for key in (b, c):
        assert "tower" in {e.id for e in tiles[key].casters}
    assert "tower" not in {e.id for e in tiles[(row0, col0 + 3)].casters}   # beyond its reach
    with_casters, without = _render_plan(gl_ctx, plan, loaded), _render_plan(gl_ctx, plan, loaded, casters=False)
    end = 30 + 40 / math.tan(math.radians(35)) - 64       # the shadow ends 23.1 m into tile C
    row = round(16 / gsd)                                 # through the tower's middle (y = N0 + 16)
    lit, dark = GREY * (0.5 + 0.5 * math.sin(math.radians(35))), GREY * 0.5
    for key, cols in ((b, np.arange(round(1 / gsd), round(31 / gsd))),
                      (c, np.arange(round(1 / gsd), round((end - 1) / gsd)))):
        assert np.all(np.abs(with_casters[key][row, cols, 0] - dark) <= 1.5), key
        assert np.all(np.abs(without[key][row, cols, 0] - lit) <= 1.5), key
    assert abs(with_casters[c][row, round((end + 1) / gsd), 0] - lit) <= 1.5   # past the shadow's end: lit again
    assert np.array_equal(with_casters[a], without[a])   # A holds the tower itself


def _town(rng: np.random.Generator, relief: float) -> tuple[list[LodChunk], dict, object, dict]:
    """A 64 m square of noisy vertex-coloured ground (4 chunks, gently sloped by ``relief``) and
    ten towers of 6-30 m (a chunk each), one near the middle: chunks, loaded chunks and the ground function."""
    z = lambda x, y: Z0 + relief * ((np.asarray(x) - E0) / 64 + 0.5 * (np.asarray(y) - N0) / 64)
    parts: dict[str, list[MeshPart]] = {}
    noise = np.concatenate([rng.integers(120, 220, (65, 65, 3)), np.full((65, 65, 1), 255)], axis=2).astype(np.uint8)
    for i in range(2):
        for j in range(2):       # one colour per 1 m grid point: chunks that share an edge share its colours
            xs, ys = np.meshgrid(np.arange(33) + 32 * i, np.arange(33) + 32 * j)
            verts = np.column_stack([xs.ravel() + E0, ys.ravel() + N0, z(xs.ravel() + E0, ys.ravel() + N0)])
            a = (np.arange(32)[:, None] * 33 + np.arange(32)[None]).ravel()
            faces = np.vstack([np.column_stack([a, a + 1, a + 34]), np.column_stack([a, a + 34, a + 33])])
            parts[f"g{i}{j}"] = [MeshPart(verts, faces, colors=noise[ys.ravel(), xs.ravel()])]
    for k in range(10):                           # the first one's shadow crosses both borders
        cx, cy = (E0 + 27, N0 + 27) if k == 0 else (E0 + 6 + 52 * rng.random(), N0 + 6 + 52 * rng.random())
        w, d, h = rng.uniform(3, 7), rng.uniform(3, 7), (25 if k == 0 else rng.uniform(6, 30))
        floor = float(min(z(cx - w, cy - d), z(cx + w, cy + d)) - 0.5)
        colour = tuple(int(v) for v in rng.integers(80, 250, 3)) + (255,)
        tower = box_part((-w / 2, -d / 2, floor), (w / 2, d / 2, floor + h), colour)
        turn = rng.uniform(0, np.pi / 2)          # not axis-aligned: no edge may follow a tile border by chance
        rot = np.array([[np.cos(turn), -np.sin(turn)], [np.sin(turn), np.cos(turn)]])
        tower.vertices[:, :2] = tower.vertices[:, :2] @ rot.T + [cx, cy]
        parts[f"t{k}"] = [tower]
    chunks, loaded, grounds = [], {}, {}
    for cid, ps in parts.items():
        lo = np.min([p.vertices.min(0) for p in ps], 0)
        hi = np.max([p.vertices.max(0) for p in ps], 0)
        g = z(np.array([lo[0], hi[0], lo[0], hi[0]]), np.array([lo[1], lo[1], hi[1], hi[1]]))
        chunks.append(_chunk(cid, lo, hi))
        grounds[("d", cid)] = ChunkGround(float(g.min()) - 2, float(g.max()) + 2, cid)
        loaded[cid] = (np.floor(lo), ps)
    return chunks, loaded, z, grounds


@pytest.mark.parametrize("perspective, projection", [(Perspective(0, 90), "plane"), (Perspective(45, 45), "terrain"),
                                                     (Perspective(200, 30), "terrain")])
def test_no_seams_one_big_tile_equals_its_four_quarter_tiles(gl_ctx, perspective, projection):
    """The same 64 m square rendered as one 256 px tile and as 2 x 2 tiles of 128 px: the shadows
    agree (the shadow maps sample one global texel grid), and along every border between the
    quarter tiles pixels differ no more than neighbouring pixels inside them do."""
    chunks, loaded, z, grounds = _town(np.random.default_rng(5), 0.0 if projection == "plane" else 6.0)
    ground = None if projection == "plane" else z
    terrain = {"projection": projection, "dtm": None}
    shadows = _shadows(Sun(230, 35), 0.75 * 0.25)
    extent = Extent(E0, N0, E0 + 64, N0 + 64)

    def render(size: int, sun: dict | None) -> np.ndarray:
        plan = plan_perspective(perspective, chunks, [], Z0, 0.25, size, 1.0, "EPSG:25832", {"samples": 4}, terrain,
                                sun, grounds)
        return _mosaic(plan, _render_plan(gl_ctx, plan, loaded, ground), extent)

    big, quarters = render(256, shadows), render(128, shadows)
    rgb_big, rgb_q = big[..., :3].astype(int), quarters[..., :3].astype(int)
    diff = np.abs(rgb_big - rgb_q).max(axis=2)
    assert (big[..., 3] == 255).all() and (quarters[..., 3] == 255).all()
    # a handful of edge pixels differ by MSAA coverage without shadows too (float32 matrices of other
    # extents); elsewhere, shadows included, the two agree within 2 levels (measured: 1)
    unshadowed = np.abs(render(256, None)[..., :3].astype(int) - render(128, None)[..., :3].astype(int)).max(axis=2)
    assert (unshadowed > 2).sum() <= 5 and diff[unshadowed <= 2].max() <= 2, (diff.max(), (diff > 2).sum())
    # shadows do cross the borders (else this proves nothing): dark pixels on both sides of each
    plain = render(128, {**shadows, "ambient": 1.0})[..., :3].astype(int)
    shaded = rgb_q.sum(axis=2) < 0.65 * plain.sum(axis=2)   # in shadow: 0.5; lit ground: 0.79
    assert shaded[:, 127].sum() > 20 and shaded[:, 128].sum() > 20
    assert shaded[127, :].sum() > 20 and shaded[128, :].sum() > 20
    # the measure: the mean |difference| across each border is no larger than across the same
    # pixel pairs drawn inside one tile, nor than across the lines of pixel pairs inside the tiles
    grey_q, grey_big = rgb_q.mean(axis=2), rgb_big.mean(axis=2)
    for axis in (0, 1):                   # 0: the horizontal border (rows 127 | 128), 1: the vertical one
        steps_q, steps_big = np.abs(np.diff(grey_q, axis=axis)), np.abs(np.diff(grey_big, axis=axis))
        border, same_pairs = steps_q.take(127, axis=axis).mean(), steps_big.take(127, axis=axis).mean()
        lines = np.delete(steps_q.mean(axis=1 - axis), 127)
        assert border <= same_pairs + 0.05 and border <= np.percentile(lines, 95), (axis, border, same_pairs,
                                                                                   np.percentile(lines, [50, 95]))


# -- the workflow ----------------------------------------------------------------------------------
@pytest.mark.slow
def test_the_workflow_casts_shadows_and_renders_again_when_they_change(tmp_path_factory):
    """The small demo city with shadows (the sun from a date and time at the scene centre): plans
    carry the sun and the casters, each render job takes the LOD indexes of its casters' districts
    as inputs (a caster's content hash is in its tiles' specs), and a changed shadow setting
    renders every tile again."""
    import json

    from osgeo import gdal
    from test_workflow import demo_run, snakemake

    from pipeline25d.core.crs import transform_points
    from pipeline25d.stages.plan import plan_blocks, read_plan

    views = [{"azimuth": 0, "elevation": 90}, {"azimuth": 45, "elevation": 45}]
    shadows = {"enabled": True, "datetime": "2024-09-15T10:30:00+02:00"}
    workdir, results = demo_run(tmp_path_factory, "shadowed", perspectives=views, shadows=shadows,
                                render={"block": 1})     # a job a tile: casters come from other jobs' tiles
    scene = json.loads((results / "scene.json").read_text())
    lon, lat, _ = transform_points(np.mean(scene["bounds"], axis=0)[None], "EPSG:25832", "EPSG:4326")[0]
    sun = sun_position(datetime.fromisoformat(shadows["datetime"]), round(lon, 2), round(lat, 2))
    plans = {pid: read_plan(results / "plans" / f"{pid}.json") for pid in ("az000_el90", "az045_el45")}
    for plan in plans.values():
        assert (abs(plan.shadows["azimuth"] - sun.azimuth) < 1e-3
                and abs(plan.shadows["elevation"] - sun.elevation) < 1e-3)
        assert any(t.casters for t in plan.tiles)
    summary = snakemake(workdir, "--detailed-summary").stdout.splitlines()
    header = summary[0].split("\t")
    rows = [dict(zip(header, line.split("\t"))) for line in summary[1:]]
    rows = [r for r in rows if r.get("rule") == "render_block"]
    assert len(rows) == sum(len(plan_blocks(p, 1)) for p in plans.values())
    foreign = 0
    for row in rows:
        pid, block = row["output_file"].split("/")[-2], row["output_file"].split("block_")[1][:-len(".json")]
        tiles = plan_blocks(plans[pid], 1)[block]
        inputs = {i.split("results/")[-1] for i in row["input-file(s)"].split(",")}
        casters = {f"{results.name}/lod/{c.district}/index.json" for t in tiles for c in t.casters}
        assert casters <= inputs, (row["output_file"], casters - inputs)
        assert all(c.hash for t in tiles for c in t.casters)          # in the spec: a changed caster re-renders
        drawn = {(c.district, c.id) for t in tiles for c in t.chunks}
        foreign += len({(c.district, c.id) for t in tiles for c in t.casters} - drawn)
    assert foreign > 0                      # casters that no tile of their job draws
    before = gdal.Open(str(results / "maps" / "az000_el90.tif")).ReadAsArray()[:3].astype(int)
    (workdir / "config.yaml").write_text((workdir / "config.yaml").read_text()
                                         .replace("enabled: true", "ambient: 0.3\n  enabled: true"))
    snakemake(workdir)
    for manifest in (results / "tiles").glob("*/block_*.json"):
        record = json.loads(manifest.read_text())
        assert record["rendered"] == len(record["tiles"]) and record["kept"] == 0, record
    after = gdal.Open(str(results / "maps" / "az000_el90.tif")).ReadAsArray()[:3].astype(int)
    darker = (after.sum(axis=0) < before.sum(axis=0) - 30)
    assert (after <= before + 1).all() and 0.05 < darker.mean() < 0.6      # the shadows, and only they, darken
