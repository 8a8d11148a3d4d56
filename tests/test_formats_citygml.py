"""CityGML reader: generated cities with exact truth (pipeline25d_lab.scenes.citygml_city) and a real
textured LOD2 building from Project PLATEAU (tests/data/citygml/SOURCE.txt)."""

from __future__ import annotations

import io
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
from lxml import etree
from PIL import Image

from pipeline25d.core.errors import CRSError, InputFileError, MissingTextureWarning
from pipeline25d.formats import detect_format, load_district, load_district_terrain
from pipeline25d.formats.citygml import read_citygml
from pipeline25d.formats.surfaces import PALETTE
from pipeline25d_lab.scenes import citygml_city as cc

DATA = Path(__file__).parent / "data" / "citygml"
PLATEAU2 = DATA / "53394517_bldg_6697_2_op_CityGML2.gml"
PLATEAU3 = DATA / "53394517_bldg_6697_2_op_CityGML3_excerpt.gml"
TOKYO = "EPSG:6677"   # JGD2011 / Japan Plane Rectangular CS IX
W, D, HE, HR = (cc.HOUSE[k] for k in ("width", "depth", "eaves", "ridge"))
S, H, BH = cc.BLOCK["size"], cc.BLOCK["hole"], cc.BLOCK["height"]


def _city(tmp_path: Path, **kw) -> tuple[Path, dict]:
    kw.setdefault("grid", (2, 2))
    truth = cc.write_city(tmp_path, **kw)
    return tmp_path / "city.gml", truth


def _load(path: Path, scene: str = "EPSG:25832", **spec):
    return load_district({"path": str(path), **spec}, scene)


def _load_counting_dropped(path: Path, scene: str, **spec):
    """The mesh and how many zero-area triangles the common check dropped (ear-clipping a ring
    with collinear vertices makes some): with those, every polygon's n - 2 triangles are there."""
    import re
    import warnings

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        mesh = _load(path, scene, **spec)
    dropped = [int(m.group(1)) for w in caught if (m := re.search(r"dropped (\d+) of", str(w.message)))]
    assert sum(dropped) < 0.02 * mesh.n_triangles
    return mesh, sum(dropped)


def _area(part) -> float:
    t = part.vertices[part.faces]
    return 0.5 * float(np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1).sum())


def _normals(part) -> np.ndarray:
    t = part.vertices[part.faces]
    n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    return n / np.linalg.norm(n, axis=1, keepdims=True)


@pytest.fixture(scope="module")
def city(tmp_path_factory):
    path, truth = _city(tmp_path_factory.mktemp("city"))
    return _load(path), truth


# ----------------------------------------------------------------------------- generated city


def test_counts_classes_and_dedup(city):
    mesh, truth = city
    parts = {p.name: p for p in mesh.parts}
    n_house, n_block = len(truth["houses"]), len(truth["blocks"])
    assert (n_house, n_block) == (2, 2)
    # house: ground quad 2, long walls 2 x 2, pentagon gables 2 x 3, roofs 2 x 2; its lod2Solid
    # references the same polygons (drawn once). Block: roof and floor with a hole 8 each, 8 walls.
    assert parts["atlas.png"].n_triangles == n_house * (4 + 6 + 4)
    assert parts["ground"].n_triangles == n_house * 2 + n_block * 8
    assert parts["roof"].n_triangles == n_block * 8
    assert parts["wall"].n_triangles == n_block * 16
    assert parts["terrain"].n_triangles == truth["tin"]["triangles"]
    for name in ("ground", "roof", "terrain"):
        np.testing.assert_array_equal(np.unique(parts[name].colors, axis=0), [PALETTE[name]])
    # the blocks' walls carry their X3DMaterial diffuseColor, not the palette
    np.testing.assert_array_equal(np.unique(parts["wall"].colors, axis=0),
                                  [[round(c * 255) for c in cc.BLOCK_WALL] + [255]])


def test_areas_and_polygon_with_hole(city):
    mesh, truth = city
    parts = {p.name: p for p in mesh.parts}
    n_house, n_block = len(truth["houses"]), len(truth["blocks"])
    # roof and floor of a courtyard block: exactly the outer square minus the hole
    assert _area(parts["roof"]) == pytest.approx(n_block * (S * S - H * H), rel=1e-9)
    assert _area(parts["ground"]) == pytest.approx(n_block * (S * S - H * H) + n_house * W * D, rel=1e-9)
    assert _area(parts["wall"]) == pytest.approx(n_block * 4 * (S + H) * BH, rel=1e-9)
    slope_len = math.hypot(D / 2, HR - HE)
    house = 2 * W * slope_len + 2 * W * HE + 2 * (D * HE + D * (HR - HE) / 2)
    assert _area(parts["atlas.png"]) == pytest.approx(n_house * house, rel=1e-9)
    ext, sx, sy = truth["tin"]["extent"], *truth["tin"]["slope"]
    assert _area(parts["terrain"]) == pytest.approx(ext * ext * math.sqrt(1 + sx * sx + sy * sy), rel=1e-6)
    # every surface faces outwards: walls horizontal, roofs up, floors down
    assert (_normals(parts["roof"])[:, 2] > 0.99).all() and (_normals(parts["ground"])[:, 2] < -0.99).all()
    assert np.abs(_normals(parts["wall"])[:, 2]).max() < 1e-9


def test_bounds_and_house_heights(city):
    mesh, truth = city
    tex = next(p for p in mesh.parts if p.texture is not None)
    for h in truth["houses"]:
        near = np.linalg.norm(tex.vertices[:, :2] - [h["x"] + W / 2, h["y"] + D / 2], axis=1) < 8
        v = tex.vertices[near]
        np.testing.assert_allclose(v.min(axis=0), [h["x"], h["y"], h["z"]], atol=1e-3)
        np.testing.assert_allclose(v.max(axis=0), [h["x"] + W, h["y"] + D, h["z"] + HR], atol=1e-3)
    ox, oy = truth["tin"]["origin"]
    ext = truth["tin"]["extent"]
    np.testing.assert_allclose(mesh.bounds()[:, :2], [[ox, oy], [ox + ext, oy + ext]], atol=1e-9)


def test_texture_coordinates_sample_the_right_half(city):
    """Roof triangles sample the atlas's roof tiles (top half), walls its facade: v is not flipped."""
    mesh, _ = city
    tex = next(p for p in mesh.parts if p.texture is not None)
    img = np.asarray(Image.open(io.BytesIO(tex.texture)).convert("RGB")).astype(int)
    uv = tex.uv[tex.faces].mean(axis=1)
    rows = np.clip(((1 - uv[:, 1]) * img.shape[0]).astype(int), 0, img.shape[0] - 1)
    cols = np.clip((uv[:, 0] * img.shape[1]).astype(int), 0, img.shape[1] - 1)
    rgb = img[rows, cols]
    reddish = (rgb[:, 0] - rgb[:, 1]) > 60
    roof = _normals(tex)[:, 2] > 0.2
    assert roof.sum() == 8 and (~roof).sum() == 20
    assert reddish[roof].all() and not reddish[~roof].any()
    # the roof quads span the top half exactly: v in [0.5, 1]
    roof_v = tex.uv[np.unique(tex.faces[roof])][:, 1]
    assert roof_v.min() == pytest.approx(0.5) and roof_v.max() == pytest.approx(1.0)


def test_lod_selection(tmp_path):
    """Houses carry LOD1 boxes (up to the mid-roof height) and LOD2 gabled houses; blocks LOD1 only."""
    path, truth = _city(tmp_path)
    n_house, n_block = len(truth["houses"]), len(truth["blocks"])
    h = truth["houses"][0]

    def read(lod):
        mesh = _load(path, **({"lod": lod} if lod else {}))
        parts = [p for p in mesh.parts if p.name != "terrain"]
        v = np.concatenate([p.vertices for p in parts])
        near = np.linalg.norm(v[:, :2] - [h["x"] + W / 2, h["y"] + D / 2], axis=1) < 8
        return sum(p.n_triangles for p in parts), v[near, 2].max() - h["z"], any(p.texture for p in parts)

    lod2 = (n_house * 16 + n_block * 32, HR, True)
    lod1 = (n_house * 12 + n_block * 32, (HE + HR) / 2, False)
    for lod, expect in ((None, lod2), ("2", lod2), ("3", lod2), ("1", lod1), ("0", lod1)):
        n, top, textured = read(lod)    # "3": the highest below; "0": none below, the lowest
        assert (n, textured) == expect[::2] and top == pytest.approx(expect[1], abs=1e-3), lod


@pytest.mark.parametrize("version,appearance", [("2.0", "start"), ("2.0", "local"), ("3.0", "end"),
                                                ("3.0", "local")])
def test_versions_and_appearance_placement_agree(tmp_path, city, version, appearance):
    """CityGML 3.0 and appearances before, after or inside the objects read like 2.0 with them after."""
    reference, _ = city
    path, _ = _city(tmp_path, version=version, appearance=appearance)
    mesh = _load(path)
    assert [p.name for p in mesh.parts] == [p.name for p in reference.parts]
    for a, b in zip(mesh.parts, reference.parts):
        np.testing.assert_array_equal(a.vertices, b.vertices)
        np.testing.assert_array_equal(a.faces, b.faces)
        np.testing.assert_array_equal(a.uv if a.uv is not None else a.colors, b.uv if b.uv is not None else b.colors)


def test_geographic_crs_lat_lon_order(tmp_path):
    """EPSG:6697 is written latitude, longitude, height: the city lands where the truth says."""
    path, truth = _city(tmp_path, crs="EPSG:6697")
    first = etree.parse(str(path)).find(".//{*}posList").text.split()
    assert 35 < float(first[0]) < 36 and 139 < float(first[1]) < 140   # lat first in the file
    loaded = read_citygml(path, {})
    assert loaded.crs == "EPSG:6697"
    tex = next(p for p in loaded.parts if p.texture is not None)
    assert 139 < tex.vertices[:, 0].min() and tex.vertices[:, 1].max() < 36   # (lon, lat) out
    mesh = _load(path, TOKYO)
    assert mesh.n_triangles == 2 * 16 + 2 * 32 + truth["tin"]["triangles"]
    for h in truth["houses"]:
        part = next(p for p in mesh.parts if p.texture is not None)
        near = np.linalg.norm(part.vertices[:, :2] - [h["x"] + W / 2, h["y"] + D / 2], axis=1) < 8
        v = part.vertices[near]
        np.testing.assert_allclose(v.min(axis=0), [h["x"], h["y"], h["z"]], atol=1e-3)
        np.testing.assert_allclose(v.max(axis=0), [h["x"] + W, h["y"] + D, h["z"] + HR], atol=1e-3)
    parts = {p.name: p for p in mesh.parts}
    assert _area(parts["roof"]) == pytest.approx(2 * (S * S - H * H), rel=1e-6)


def test_longitude_first_under_a_latitude_first_crs_is_read_where_it_lies(tmp_path):
    """A file that writes longitude first under EPSG:6697 (whose order is latitude first; the OGC's
    own CityGML 3.0 example of the Jefferson Memorial does so under EPSG:4979): read in the CRS's
    order it would lie outside the scene CRS's area; exchanged, it lies inside, so ``axis_order``
    auto reads it exchanged, with a warning, and gives the correctly ordered file's mesh, faces
    included. ``axis_order: crs`` keeps the error, and so does a scene where neither order lies."""
    import re
    import warnings

    path, _ = _city(tmp_path / "lat", crs="EPSG:6697")
    swapped = tmp_path / "lon" / "city.gml"
    shutil.copytree(path.parent, swapped.parent)

    def lon_first(match):
        v = match.group(2).split()
        return match.group(1) + " ".join(w for k in range(0, len(v), 3) for w in (v[k + 1], v[k], v[k + 2]))

    text, n = re.subn(r"(<gml:pos(?:List)?[^>]*>)([^<]+)", lon_first, path.read_text(encoding="utf-8"))
    assert n > 50
    swapped.write_text(text, encoding="utf-8")
    want = _load(path, TOKYO)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        got = _load(swapped, TOKYO)
    assert any("longitude and latitude exchanged" in str(w.message) and "city.gml" in str(w.message)
               for w in caught)
    said = _load(swapped, TOKYO, axis_order="swapped")                  # said so: the same, without a warning
    for mesh in (got, said):
        assert [p.name for p in mesh.parts] == [p.name for p in want.parts]
        for a, b in zip(mesh.parts, want.parts):
            np.testing.assert_allclose(a.vertices, b.vertices, atol=1e-6)
            np.testing.assert_array_equal(a.faces, b.faces)     # triangulated and faced as the right order is
    with pytest.raises(CRSError, match=r"city\.gml: model at lon .* outside the area of use of EPSG:6697"):
        _load(swapped, TOKYO, axis_order="crs")
    with pytest.raises(CRSError, match=r"city\.gml: model at lon .* outside the area of use of EPSG:6697"):
        _load(swapped, "EPSG:25832")


@pytest.mark.parametrize("name, code", [("urn:adv:crs:ETRS89_UTM32*DE_DHHN2016_NH", "EPSG:25832+7837"),
                                        ("urn:adv:crs:DE_DHDN_3GK4*DE_DHHN92_NH", "EPSG:31468+5783"),
                                        ("urn:adv:crs:DE_DHDN_3GK3", "EPSG:31467"),
                                        ("urn:adv:crs:DE_RD/83_3GK5*DE_DHHN85_NH", "EPSG:3399+5784")])
def test_german_adv_crs_names(name, code):
    """The AdV names German CityGML carries (state LoD2 data; the OGC's CityGML 3.0 example
    "Building_CityGML3.0_LOD2_with_several_attributes" is in Gauss-Krüger zone 4): EPSG codes
    pyproj knows, compound where a height system follows."""
    from pipeline25d.core.crs import parse_crs
    from pipeline25d.formats.common import crs_name

    assert crs_name(name) == code
    assert parse_crs(code).is_compound == ("+" in code)


def test_terrain_loader_returns_the_tin(tmp_path):
    path, truth = _city(tmp_path)
    ground = load_district_terrain({"path": str(path)}, "EPSG:25832")
    assert [p.name for p in ground.parts] == ["terrain"]
    assert ground.n_triangles == truth["tin"]["triangles"]
    v = ground.parts[0].vertices
    ox, oy = truth["tin"]["origin"]
    np.testing.assert_allclose(v[:, 2], cc.terrain_z(v[:, 0], v[:, 1], (ox, oy)), atol=1e-3)


def test_detect_format_by_content(tmp_path):
    path, _ = _city(tmp_path)
    assert detect_format(path) == "citygml"
    other = tmp_path / "other.gml"
    other.write_text('<?xml version="1.0"?><gml:FeatureCollection xmlns:gml="http://www.opengis.net/gml"/>')
    with pytest.raises(InputFileError, match="unknown model format"):
        detect_format(other)


# ----------------------------------------------------------------------------- errors


def _bad(tmp_path: Path, old: str, new: str, count: int = 1) -> Path:
    path, _ = _city(tmp_path)
    text = path.read_text(encoding="utf-8")
    assert old in text
    path.write_text(text.replace(old, new, count), encoding="utf-8")
    return path


def test_malformed_xml_names_file_and_line(tmp_path):
    path = _bad(tmp_path, "</bldg:Building>", "</bldg:Buildin>")
    with pytest.raises(InputFileError, match=r"city\.gml: malformed XML at line 4"):
        read_citygml(path, {})


def test_unknown_srs_name(tmp_path):
    path = _bad(tmp_path, "http://www.opengis.net/def/crs/EPSG/0/25832", "urn:nowhere:crs:42")
    with pytest.raises(InputFileError, match=r"city\.gml: line 3: unknown srsName 'urn:nowhere:crs:42'"):
        read_citygml(path, {})
    assert read_citygml(path, {"crs": "EPSG:25832"}).crs == "EPSG:25832"   # the crs key overrides


def test_bad_numbers_and_2d(tmp_path):
    with pytest.raises(InputFileError, match=r"city\.gml: line 5: non-numeric coordinates in <LinearRing>"):
        read_citygml(_bad(tmp_path / "a", '"b0_1_bottom_r0"><gml:posList>691', '"b0_1_bottom_r0"><gml:posList>x91'), {})
    with pytest.raises(InputFileError, match="srsDimension 2"):
        read_citygml(_bad(tmp_path / "b", '"b0_1_bottom_r0"><gml:posList>',
                          '"b0_1_bottom_r0"><gml:posList srsDimension="2">'), {})


def test_missing_texture_is_an_error_or_falls_back_to_colour(tmp_path):
    path, _ = _city(tmp_path)
    (tmp_path / "city_appearance" / "atlas.png").unlink()
    with pytest.raises(InputFileError, match=r"atlas\.png is missing.*missing_textures: untextured"):
        load_district({"path": str(path)}, "EPSG:25832")
    with pytest.warns(MissingTextureWarning, match=r"atlas\.png is missing.*drawn untextured"):
        mesh = _load(path, missing_textures="untextured")
    parts = {p.name: p for p in mesh.parts}
    assert not any(p.texture is not None for p in mesh.parts)
    assert parts["roof"].n_triangles == 2 * 8 + 2 * 4      # blocks' roofs + the houses' RoofSurfaces
    assert parts["wall"].n_triangles == 2 * 16 + 2 * 10


def test_not_citygml(tmp_path):
    path = tmp_path / "x.gml"
    path.write_text('<?xml version="1.0"?><CityModel xmlns="http://example.org/other"/>')
    with pytest.raises(InputFileError, match="not CityGML 1.0, 2.0 or 3.0"):
        read_citygml(path, {})
    with pytest.raises(InputFileError, match="CityGML file is missing"):
        read_citygml(tmp_path / "none.gml", {})


# ----------------------------------------------------------------------------- PLATEAU


def _polygon_triangles(path: Path, under: str) -> int:
    """sum(n - 2) over the polygons below properties named ``under`` (rings without holes)."""
    tree = etree.parse(str(path))
    total = 0
    for prop in tree.iter(f"{{*}}{under}"):
        for pos in prop.iter("{*}posList"):
            total += len(pos.text.split()) // 3 - 1 - 2
    return total


def test_plateau_lod2_textured():
    mesh, dropped = _load_counting_dropped(PLATEAU2, TOKYO)
    parts = {p.name: p for p in mesh.parts}
    assert set(parts) == {"ground", "stad0158.jpg"}
    assert mesh.n_triangles + dropped == _polygon_triangles(PLATEAU2, "lod2MultiSurface")
    tex = parts["stad0158.jpg"]
    assert tex.texture == (DATA / "53394517_bldg_6697_appearance" / "stad0158.jpg").read_bytes()
    # every texture coordinate of the file (first list per ring, closing pair dropped) is a vertex's
    expect = []
    for coords in etree.parse(str(PLATEAU2)).iter("{*}TexCoordList"):
        st = np.array(coords.find("{*}textureCoordinates").text.split(), float).reshape(-1, 2)
        expect.append(st[:-1])
    expect = np.concatenate(expect).astype(np.float32)
    got = tex.uv
    assert len(got) == len(expect)
    np.testing.assert_array_equal(got[np.lexsort(got.T)], expect[np.lexsort(expect.T)])
    # lat/lon/h in the file: the same positions through pyproj in authority axis order
    from pyproj import Transformer

    ring = np.array(etree.parse(str(PLATEAU2)).find(".//{*}GroundSurface//{*}posList").text.split(),
                    float).reshape(-1, 3)[:-1]
    x, y, z = Transformer.from_crs("EPSG:6697", TOKYO).transform(ring[:, 0], ring[:, 1], ring[:, 2])
    np.testing.assert_allclose(parts["ground"].vertices, np.column_stack([y, x, z]), atol=1e-6)  # 6677: north, east
    t = parts["ground"].vertices[parts["ground"].faces]
    normal = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]).sum(axis=0)
    assert normal[2] / np.linalg.norm(normal) < -0.9999   # the floor faces down


def test_plateau_lod1_and_citygml3_excerpt():
    lod1, dropped = _load_counting_dropped(PLATEAU2, TOKYO, lod="1")
    assert lod1.n_triangles + dropped == _polygon_triangles(PLATEAU2, "lod1Solid")
    assert {p.name for p in lod1.parts} == {"ground", "roof", "wall"}
    lod1_v3 = _load(PLATEAU3, TOKYO, lod="1")
    assert lod1_v3.n_triangles == lod1.n_triangles
    np.testing.assert_allclose(lod1_v3.bounds(), lod1.bounds(), atol=1e-6)
    v3, dropped = _load_counting_dropped(PLATEAU3, TOKYO)
    assert v3.n_triangles + dropped == _polygon_triangles(PLATEAU3, "lod2MultiSurface")
    tex = next(p for p in v3.parts if p.texture is not None)
    assert tex.n_triangles == v3.n_triangles - _polygon_triangles(PLATEAU3, "GroundSurface")


# ----------------------------------------------------------------------------- XML defects (issue 27)

ENERGY = 'xmlns:energy="http://www.sig3d.org/citygml/2.0/energy/1.0" '


def _plateau_copy(folder: Path, declare: bool, edit=None) -> Path:
    """The real PLATEAU building with ADE elements under the prefix ``energy:`` (declared or not):
    one element among the building's attributes and one attribute on uro:BuildingDetails, both
    outside the geometry; ``edit`` changes the text further. Its texture atlas is copied beside it."""
    folder.mkdir()
    text = PLATEAU2.read_text(encoding="utf-8")
    text = text.replace("<uro:buildingDetails>", "<energy:isHeated>true</energy:isHeated>\n<uro:buildingDetails>", 1)
    text = text.replace("<uro:BuildingDetails>", '<uro:BuildingDetails energy:source="survey">', 1)
    if declare:
        text = text.replace("<core:CityModel ", "<core:CityModel " + ENERGY, 1)
    if edit is not None:
        text = edit(text)
    path = folder / PLATEAU2.name
    path.write_text(text, encoding="utf-8")
    (folder / "53394517_bldg_6697_appearance").mkdir()
    (folder / "53394517_bldg_6697_appearance" / "stad0158.jpg").write_bytes(
        (DATA / "53394517_bldg_6697_appearance" / "stad0158.jpg").read_bytes())
    return path


def _warned(path: Path, **spec):
    import warnings

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        mesh = _load(path, TOKYO, **spec)
    return mesh, [str(w.message) for w in caught]


def test_an_undeclared_ade_prefix_outside_the_geometry_is_read_with_one_warning(tmp_path):
    declared, _ = _warned(_plateau_copy(tmp_path / "declared", True))
    path = _plateau_copy(tmp_path / "undeclared", False)
    line = next(i for i, t in enumerate(path.read_text(encoding="utf-8").splitlines(), 1) if "energy:isHeated" in t)
    mesh, said = _warned(path)
    ours = [m for m in said if "energy" in m]
    assert len(ours) == 1, said                                   # once per prefix, not per element
    assert ours[0].startswith(f"{path}: line {line}: Namespace prefix energy on isHeated is not defined")
    assert "1 more like it" in ours[0]                            # the attribute on uro:BuildingDetails
    # the same geometry, texture and texture coordinates as the file with the prefix declared
    assert [p.name for p in mesh.parts] == [p.name for p in declared.parts] == ["ground", "stad0158.jpg"]
    for got, want in zip(mesh.parts, declared.parts):
        np.testing.assert_array_equal(got.vertices, want.vertices)
        np.testing.assert_array_equal(got.faces, want.faces)
        assert got.texture == want.texture
    np.testing.assert_array_equal(mesh.parts[1].uv, declared.parts[1].uv)
    assert mesh.parts[1].texture == (DATA / "53394517_bldg_6697_appearance" / "stad0158.jpg").read_bytes()


@pytest.mark.parametrize("edit, problem", [
    # an undeclared prefix on a polygon: its meaning (gml:id here) is lost, so its triangles are too
    (lambda t: t[:t.index("<bldg:GroundSurface")] + t[t.index("<bldg:GroundSurface"):].replace(
        "<gml:Polygon ", '<gml:Polygon energy:id="p" ', 1),
     r"line \d+: attribute energy:id of <Polygon> inside a geometry has an undeclared namespace prefix"),
    (lambda t: t.replace("</gml:posList>", "</gml:posLst>", 1), r"malformed XML at line \d+: Opening and ending tag"),
    (lambda t: t[:len(t) // 2], r"malformed XML at line \d+: "),                       # truncated
    (lambda t: t.replace("<gml:posList>", "<gml:posList>& ", 1), r"malformed XML at line \d+: xmlParseEntityRef"),
])
def test_other_xml_defects_and_prefixes_inside_the_geometry_are_still_refused(tmp_path, edit, problem):
    path = _plateau_copy(tmp_path / "bad", False, edit)
    with pytest.raises(InputFileError, match=problem) as err:
        read_citygml(path, {})
    assert str(err.value).startswith(f"{path}: ")


def test_a_texture_outside_the_files_folder_is_not_read(tmp_path):
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    (outside / "atlas.jpg").write_bytes((DATA / "53394517_bldg_6697_appearance" / "stad0158.jpg").read_bytes())
    path = _plateau_copy(tmp_path / "model", True, lambda t: t.replace(
        "53394517_bldg_6697_appearance/stad0158.jpg", "../elsewhere/atlas.jpg"))
    with pytest.warns(UserWarning, match=r"texture image \.\./elsewhere/atlas\.jpg lies outside the dataset folder"):
        loaded = read_citygml(path, {})               # a missing texture: ingest's missing_textures decides
    assert loaded.parts and all(p.texture is None for p in loaded.parts)
