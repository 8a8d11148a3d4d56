"""The CityJSON reader against the CityGML reader: one generated city with textures, materials and
two themes (pipeline25d_lab.scenes.themed_city) written in both formats with the same coordinates,
read through load_district as ingest reads it, must give the same textured and coloured triangles
and render alike; the theme must change what is drawn, and only where the themes differ."""

from __future__ import annotations

import math
import shutil

import numpy as np
import pytest

from pipeline25d.formats import load_district
from pipeline25d.formats.surfaces import PALETTE, newell
from pipeline25d.geometry.camera import Extent, projected_box
from pipeline25d.geometry.perspectives import Perspective
from pipeline25d_lab.scenes import themed_city as tc

SCENE = "EPSG:25832"
ORIGIN = (691000.0, 5335000.0)
FILES = {"cityjson": f"{tc.NAME}.city.json", "citygml": f"{tc.NAME}.gml"}
GSD = 0.125
VIEWS = {"nadir": Perspective(0, 90), "oblique": Perspective(45, 45)}


@pytest.fixture(scope="module")
def city(tmp_path_factory):
    out = tmp_path_factory.mktemp("themed")
    truth = tc.write_themed_city(out, ORIGIN)
    meshes = {(fmt, theme): load_district({"path": str(out / name), "theme": theme}, SCENE)
              for fmt, name in FILES.items() for theme in tc.THEMES}
    return out, truth, meshes


def _corners(part) -> dict[tuple, np.ndarray]:
    """{triangle: its corners rounded to the mm (the files' grid), starting at the smallest, turn
    kept: the per-corner UVs (textured part) or RGBA (coloured part), (3, k)}."""
    tris = np.round(part.vertices[part.faces], 3)
    extra = (part.uv if part.texture is not None else part.colors)[part.faces]
    out = {}
    for tri, ex in zip(tris, extra):
        pts = [tuple(p) for p in tri]
        k = min(range(3), key=pts.__getitem__)
        order = [k, (k + 1) % 3, (k + 2) % 3]
        key = tuple(pts[i] for i in order)
        assert key not in out, "a triangle drawn twice"
        out[key] = ex[order]
    return out


def _area(keys) -> float:
    t = np.array(list(keys), dtype=np.float64)
    return 0.5 * float(np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1).sum())


def _polygon_area(rings: list) -> float:
    """Area of a planar polygon with holes (Newell normals of its closed rings)."""
    areas = [0.5 * np.linalg.norm(newell(np.asarray(r, dtype=np.float64)[:-1])) for r in rings]
    return areas[0] - sum(areas[1:])


@pytest.mark.parametrize("theme", tc.THEMES)
def test_same_textured_triangles_and_uvs(city, theme):
    """Textured parts: the same images (the bytes written), the same triangles with the same UV
    per corner; their area is that of the surfaces the theme textures (truth)."""
    out, truth, meshes = city
    textured = {}
    for fmt in FILES:
        parts = [p for p in meshes[fmt, theme].parts if p.texture is not None]
        textured[fmt] = {p.texture: _corners(p) for p in parts}
        assert len(textured[fmt]) == len(parts) == 1
    cj, gml = textured["cityjson"], textured["citygml"]
    images = truth["themes"][theme]["textured"]
    assert set(cj) == set(gml) == {(out / image).read_bytes() for image in images}
    for image, gids in images.items():
        a, b = cj[(out / image).read_bytes()], gml[(out / image).read_bytes()]
        assert set(a) == set(b)
        assert max(np.abs(a[k] - b[k]).max() for k in a) <= 1e-6
        expected = sum(_polygon_area(truth["surfaces"][g]["rings"]) for g in gids)
        assert _area(a) == pytest.approx(expected, rel=1e-9)
    # the other theme's image is not drawn
    other = next(t for t in tc.THEMES if t != theme)
    assert (out / f"{tc.NAME}_appearance/{other}.png").read_bytes() not in cj


@pytest.mark.parametrize("theme", tc.THEMES)
def test_same_coloured_triangles_and_materials(city, theme):
    """Coloured parts (one per class): the same triangles with the same RGBA per corner; material
    surfaces in round(255 * diffuseColor), the area in it that of the theme's material surfaces
    (winter: one house's whole LOD2 geometry, ground included, by CityJSON ``value`` and by a
    CityGML X3DMaterial targeting the solid's CompositeSurface)."""
    _, truth, meshes = city
    coloured = {fmt: {p.name: _corners(p) for p in meshes[fmt, theme].parts if p.texture is None} for fmt in FILES}
    cj, gml = coloured["cityjson"], coloured["citygml"]
    assert set(cj) == set(gml) == {"ground", "roof", "wall"}
    for name in cj:
        assert set(cj[name]) == set(gml[name])
        assert all(np.array_equal(cj[name][k], gml[name][k]) for k in cj[name])
    materials = truth["themes"][theme]["material"]
    rgba = {tuple(round(c * 255) for c in rgb) + (255,) for rgb in materials.values()}
    assert len(rgba) == 1
    in_material = [k for name in cj for k, colours in cj[name].items() if tuple(colours[0]) in rgba]
    expected = sum(_polygon_area(truth["surfaces"][g]["rings"]) for g in materials)
    assert _area(in_material) == pytest.approx(expected, rel=1e-9)
    rest = {tuple(c) for name in cj for k, colours in cj[name].items() for c in colours} - rgba
    assert rest <= {PALETTE[name] for name in cj}


def _view(truth: dict, p: Perspective):
    from pipeline25d.stages.render import TileView

    pts = np.array([q for s in truth["surfaces"].values() for r in s["rings"] for q in r])
    ext, depth = projected_box(np.array([pts.min(axis=0) - 2, pts.max(axis=0) + 2]), p, tc.GROUND_Z)
    ext = Extent(*(math.floor(v / GSD) * GSD for v in ext[:2]), *(math.ceil(v / GSD) * GSD for v in ext[2:]))
    size = (round(ext.width / GSD), round(ext.height / GSD))
    return TileView(p, tc.GROUND_Z, ext, depth, size)


@pytest.fixture(scope="module")
def renders(city, gl_ctx):
    from pipeline25d.stages.render import TileRenderer

    _, truth, meshes = city
    renderer = TileRenderer(gl_ctx, samples=0)
    origin = np.array([*ORIGIN, tc.GROUND_Z])
    return {(fmt, theme, name): renderer.render_color([(origin, meshes[fmt, theme].parts)], _view(truth, p))
            for fmt in FILES for theme in tc.THEMES for name, p in VIEWS.items()}


@pytest.mark.parametrize("theme", tc.THEMES)
@pytest.mark.parametrize("view", VIEWS)
def test_renders_agree(renders, theme, view):
    """Nadir and oblique renders of both readers' parts: the same triangles with the same textures
    and colours drawn by one renderer may differ only where the coordinates' last bits differ
    (CityJSON: integers x scale + translate; CityGML: the decimal text) and move an edge across a
    pixel centre: at most 0.1 % of the pixels, and none in the city's coverage (alpha) at all."""
    a, b = renders["cityjson", theme, view], renders["citygml", theme, view]
    assert a.shape == b.shape and (a[..., 3] > 0).mean() > 0.2
    np.testing.assert_array_equal(a[..., 3], b[..., 3])
    differ = np.abs(a.astype(int) - b.astype(int)).max(axis=2) > 0
    assert differ.mean() <= 1e-3


def _footprint_pixels(truth: dict, house: str, view) -> tuple[slice, slice]:
    """Rows and columns of a house's footprint in the nadir render, 4 px inside its edges."""
    ext = view.extent
    ring = np.array(truth["surfaces"][f"{house}_ground"]["rings"][0])
    (x0, y0), (x1, y1) = ring[:, :2].min(axis=0), ring[:, :2].max(axis=0)
    return (slice(round((ext.ymax - y1) / GSD) + 4, round((ext.ymax - y0) / GSD) - 4),
            slice(round((x0 - ext.xmin) / GSD) + 4, round((x1 - ext.xmin) / GSD) - 4))


def test_theme_changes_the_render_where_the_themes_differ(city, renders):
    """Summer against winter: seen from above every roof changes (red tiles or a red material to
    snow) except the last house's (no appearance): its pixels are identical. The textured roof
    (house 0, summer) shows the atlas's grain; a material roof is one flat colour. In the oblique
    view the walls change too (other atlas; house 1's winter walls in their class colour)."""
    _, truth, _ = city
    view = _view(truth, VIEWS["nadir"])
    for fmt in FILES:
        summer, winter = (renders[fmt, t, "nadir"].astype(int) for t in tc.THEMES)
        for k, house in enumerate(truth["houses"]):
            rows, cols = _footprint_pixels(truth, house, view)
            change = np.abs(summer[rows, cols, :3] - winter[rows, cols, :3]).max(axis=2)
            if k == len(truth["houses"]) - 1:
                assert change.max() == 0
            else:
                assert (change > 40).mean() > 0.95, house
        rows, cols = _footprint_pixels(truth, truth["houses"][0], view)
        assert summer[rows, cols, :3].std(axis=(0, 1)).min() > 3          # texture grain and tile rows
        rows, cols = _footprint_pixels(truth, truth["houses"][2], view)
        south = summer[rows, cols, :3][rows.stop - rows.start - 4:]       # one roof plane: flat shaded
        assert south.std(axis=(0, 1)).max() == 0
        summer, winter = (renders[fmt, t, "oblique"].astype(int) for t in tc.THEMES)
        drawn = summer[..., 3] > 0
        wall_change = np.abs(summer - winter).max(axis=2) > 40
        assert wall_change[drawn].mean() > 0.5


def test_citygml_material_on_an_aggregate_colours_its_polygons(city, tmp_path):
    """The case this comparison found: an X3DMaterial may target "gml:MultiSurface or descendants
    of gml:AbstractSurfaceType" (CityGML 2.0 appearance schema), here the LOD2 solid's
    CompositeSurface, whose polygons are xlink:href references: every polygon of it takes the
    colour (CityGML drew them in class colours before). A material targeting the polygon itself
    wins over the aggregate's."""
    out, truth, _ = city
    house = truth["houses"][tc.WHOLE["winter"]]
    snow = tuple(round(c * 255) for c in tc.MATERIALS["winter"][1]) + (255,)
    text = (out / FILES["citygml"]).read_text()
    cut = text.rindex("</app:Appearance>")        # the winter Appearance: red on one roof polygon
    gml = tmp_path / "edited.gml"
    gml.write_text(text[:cut] + f"<app:surfaceDataMember><app:X3DMaterial><app:diffuseColor>1 0 0"
                   f"</app:diffuseColor><app:target>#{house}_roof0</app:target></app:X3DMaterial>"
                   f"</app:surfaceDataMember>" + text[cut:])
    shutil.copytree(out / f"{tc.NAME}_appearance", tmp_path / f"{tc.NAME}_appearance")   # a link would lead
                                                                                  # outside the model's folder
    parts = {p.name: p for p in load_district({"path": str(gml), "theme": "winter"}, SCENE).parts}

    def colours(name: str, gid: str) -> set:
        """Corner colours of the part's triangles whose centroid lies in the surface's box."""
        ring = np.array(truth["surfaces"][gid]["rings"][0])
        lo, hi = ring.min(axis=0) - 1e-6, ring.max(axis=0) + 1e-6
        part = parts[name]
        centroid = part.vertices[part.faces].mean(axis=1)
        faces = part.faces[((centroid >= lo) & (centroid <= hi)).all(axis=1)]
        return {tuple(int(v) for v in c) for c in part.colors[faces.ravel()]}

    assert colours("ground", f"{house}_ground") == {snow}
    assert colours("ground", f"{truth['houses'][0]}_ground") == {PALETTE["ground"]}
    assert colours("roof", f"{house}_roof0") == {(255, 0, 0, 255)}
    assert colours("roof", f"{house}_roof1") == {snow}


def _objects(mesh) -> dict[tuple, str]:
    """{triangle (corners to the mm, smallest first, turn kept): the key of the object it belongs to}."""
    out = {}
    for part in mesh.parts:
        tris = np.round(part.vertices[part.faces], 3)
        for tri, k in zip(tris, part.face_objects):
            pts = [tuple(p) for p in tri]
            first = min(range(3), key=pts.__getitem__)
            out[tuple(pts[(first + i) % 3] for i in range(3))] = part.objects[k]
    return out


def test_both_readers_name_the_same_object_for_every_triangle(city):
    """Object identity (issue 30): each house's triangles carry its id in both formats, the CityObject
    key in CityJSON and the Building's gml:id in CityGML, and the ids are the houses the city has."""
    _, truth, meshes = city
    ids = {fmt: _objects(meshes[fmt, tc.THEMES[0]]) for fmt in FILES}
    assert ids["cityjson"] == ids["citygml"] and len(ids["cityjson"]) > 100
    assert set(ids["cityjson"].values()) == {h["id"] for h in tc.houses(ORIGIN)}
