"""3D Tiles reader against the numbers measured in shared/data/*/SOURCE.txt.

Bounds are compared in EPSG:4979 (lon, lat, ellipsoidal h), as SOURCE.txt states them:
1e-5 degrees where SOURCE gives 6 decimals, 1e-4 where it gives 4; heights to 0.2 m or
to the rounding of SOURCE's figure.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from conftest import shared_file

from pipeline25d.core.errors import CRSError, InputFileError, UnsupportedFeatureError
from pipeline25d.formats.tiles3d import load_b3dm, load_tileset, read_content, read_tileset

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
SAMPLES = DATA / "3dtiles-samples"
GEO = "EPSG:4979"


def _assert_bounds(mesh, lon, lat, h=None, deg=1e-5, metres=0.2):
    b = mesh.bounds()
    np.testing.assert_allclose(b[:, 0], lon, atol=deg, rtol=0)
    np.testing.assert_allclose(b[:, 1], lat, atol=deg, rtol=0)
    if h is not None:
        np.testing.assert_allclose(b[:, 2], h, atol=metres, rtol=0)


# ----------------------------------------------------------------------------- LOD selection


def test_tileset_uniform_full_detail():
    mesh = load_tileset(shared_file(SAMPLES / "TilesetUniform" / "tileset.json"), GEO)
    assert mesh.n_triangles == 1836  # 8 level-1 leaves + 9 level-2 tiles, 108 each
    _assert_bounds(mesh, (-75.613179, -75.611009), (40.041697, 40.043365))
    assert mesh.bounds()[0, 2] == pytest.approx(0.0, abs=0.2)


@pytest.mark.parametrize("g, triangles", [(1000, 108), (120, 108), (60, 972), (59.9, 1836), (0, 1836)])
def test_tileset_uniform_levels(g, triangles):
    """REPLACE: a refined tile is not drawn; the external tileset2.json is always entered."""
    mesh = load_tileset(shared_file(SAMPLES / "TilesetUniform" / "tileset.json"), GEO, max_geometric_error=g)
    assert mesh.n_triangles == triangles


def test_tileset_uniform_root_level_height():
    root = load_tileset(shared_file(SAMPLES / "TilesetUniform" / "tileset.json"), GEO, max_geometric_error=120)
    full = load_tileset(SAMPLES / "TilesetUniform" / "tileset.json", GEO)
    lo = min(root.bounds()[0, 2], full.bounds()[0, 2])
    hi = max(root.bounds()[1, 2], full.bounds()[1, 2])
    assert (lo, hi) == (pytest.approx(0.0, abs=0.2), pytest.approx(22.2, abs=0.06))  # "h 0.0..22.2 m"


def test_tileset_with_transforms():
    path = shared_file(SAMPLES / "TilesetWithTransforms" / "tileset.json")
    b3dm_only = load_tileset(path, GEO, max_geometric_error=70)  # root (ADD, ge 70) only
    assert b3dm_only.n_triangles == 120
    _assert_bounds(b3dm_only, (-75.613037, -75.610940), (40.041630, 40.043288), (0.0, 13.4), metres=0.06)
    full = load_tileset(path, GEO)
    assert full.n_triangles == 420  # + i3dm: 25 instances x 12
    # the i3dm child (rotated 45 deg, scaled 0.5, lifted 5 m) stays inside the root's footprint
    _assert_bounds(full, (-75.613037, -75.610940), (40.041630, 40.043288), (0.0, 13.4), metres=0.06)


def test_i3dm_instances_positions_only():
    parts = read_content(shared_file(SAMPLES / "TilesetWithTransforms" / "instances.i3dm"))
    assert sum(p.n_triangles for p in parts) == 300
    # 20 m cubes at 25 positions on a grid spanning +-80 m (tile frame, before the tile transform)
    b = np.array([np.min([p.bounds()[0] for p in parts], 0), np.max([p.bounds()[1] for p in parts], 0)])
    np.testing.assert_allclose(b, [[-90, -90, -10], [90, 90, 10]], atol=1e-4)


def test_tileset_of_tilesets():
    path = shared_file(SAMPLES / "TilesetOfTilesets" / "tileset.json")
    mesh = load_tileset(path, GEO)
    assert mesh.n_triangles == 600
    _assert_bounds(mesh, (-75.614410, -75.610011), (40.041064, 40.044320), (0.0, 85.4), metres=0.06)
    assert load_tileset(path, GEO, max_geometric_error=70).n_triangles == 120  # parent.b3dm only


def test_batched_textured():
    mesh = load_tileset(shared_file(SAMPLES / "BatchedTextured" / "tileset.json"), GEO)
    assert mesh.n_triangles == 120
    textured = [p for p in mesh.parts if p.texture is not None]
    assert len(textured) == 1 and textured[0].n_triangles == 120
    assert textured[0].texture[:3] == b"\xff\xd8\xff"  # the embedded JPEG, as stored
    assert textured[0].uv.min() >= 0.0 and textured[0].uv.max() <= 1.0
    _assert_bounds(mesh, (-75.613037, -75.610940), (40.041630, 40.043288), (0.0, 13.4), metres=0.06)


def test_cdb_yemen_tolerates_missing_textures():
    with pytest.warns(UserWarning, match="missing"):
        mesh = load_tileset(shared_file(SAMPLES / "cdb-yemen-cut" / "tileset.json"), GEO)
    assert mesh.n_triangles == 60
    assert all(p.texture is None for p in mesh.parts)
    _assert_bounds(mesh, (44.0, 45.034206), (12.832536, 14.0), (-6.6, 1.1), metres=0.06)


def test_sparse_implicit_quadtree():
    path = shared_file(SAMPLES / "SparseImplicitQuadtree" / "tileset.json")
    mesh = load_tileset(path, "EPSG:4978", src_crs="EPSG:4978")  # not georeferenced: stay in ECEF
    assert mesh.n_triangles == 64  # 32 level-5 glb files, 2 triangles each
    np.testing.assert_allclose(mesh.bounds()[:, :2], [[0, 0], [1, 1]], atol=1e-9)
    assert load_tileset(path, "EPSG:4978", 1.0, "EPSG:4978").n_triangles == 64  # level 5 has ge 1.0
    with pytest.warns(UserWarning, match="no triangles"):  # content only at level 5
        assert load_tileset(path, "EPSG:4978", 2.0, "EPSG:4978").n_triangles == 0


def test_feature_id_attribute_tileset():
    mesh = load_tileset(shared_file(SAMPLES / "FeatureIdAttribute" / "tileset.json"), "EPSG:4978", src_crs="EPSG:4978")
    assert mesh.n_triangles == 8


# ----------------------------------------------------------------------------- real cities


def test_amsterdam_in_rd_new():
    mesh = load_tileset(shared_file(DATA / "amsterdam-3dtiles" / "tileset.json"), "EPSG:28992")
    assert mesh.n_triangles == 35102  # nothing clipped by the (too small) bounding boxes
    b = mesh.bounds()
    np.testing.assert_allclose(b[:, 0], [120948, 125938], atol=1.0)
    np.testing.assert_allclose(b[:, 1], [487113, 490896], atol=1.0)


def test_amsterdam_lonlat():
    mesh = load_tileset(shared_file(DATA / "amsterdam-3dtiles" / "tileset.json"), GEO)
    _assert_bounds(mesh, (4.88713, 4.96033), (52.37090, 52.40505), (39.4, 85.3), deg=1e-5, metres=0.06)


def test_tokyo_cesium_rtc_textured():
    mesh = load_b3dm(shared_file(DATA / "tokyo-chiyoda-b3dm" / "cesium-rtc-extension.b3dm"), GEO)
    assert mesh.n_triangles == 14756
    textured = [p for p in mesh.parts if p.texture is not None]
    assert len(textured) >= 28
    assert all(p.texture[:3] == b"\xff\xd8\xff" for p in textured)
    assert all(p.uv.min() >= -1e-6 and p.uv.max() <= 1 + 1e-6 for p in textured)
    _assert_bounds(mesh, (139.7386, 139.7625), (35.6696, 35.7000), (36.8, 236.3), deg=1e-4, metres=0.06)


def test_tokyo_in_japan_plane_ix():
    from pyproj import Transformer

    mesh = load_b3dm(shared_file(DATA / "tokyo-chiyoda-b3dm" / "cesium-rtc-extension.b3dm"), "EPSG:6677")
    to_plane = Transformer.from_crs("EPSG:4326", "EPSG:6677", always_xy=True)
    lon = np.array([139.7386, 139.7625, 139.7386, 139.7625])
    lat = np.array([35.6696, 35.6696, 35.7000, 35.7000])
    x, y = to_plane.transform(lon, lat)
    b = mesh.bounds()
    # corners of SOURCE's 4-decimal lon/lat box, projected independently; grid convergence
    # and the rounding (about 5 m) allow a few metres
    np.testing.assert_allclose(b[:, 0], [x.min(), x.max()], atol=10)
    np.testing.assert_allclose(b[:, 1], [y.min(), y.max()], atol=10)


def test_new_york_draco():
    with pytest.warns(UserWarning, match="dropped 34 of 16762 triangles that are degenerate"):  # Draco's quantisation
        mesh = load_b3dm(shared_file(SAMPLES / "NewYorkDracoB3dm" / "1.b3dm"), GEO)
    assert mesh.n_triangles == 16762 - 34
    assert sum(len(p.vertices) for p in mesh.parts) == 34702
    _assert_bounds(mesh, (-74.177713, -74.165637), (40.528322, 40.534266), (-24.6, 5.5), metres=0.06)


# ----------------------------------------------------------------------------- bad input


def test_tokyo_outside_rd_new_area():
    with pytest.raises(CRSError, match="area of use"):
        load_b3dm(shared_file(DATA / "tokyo-chiyoda-b3dm" / "cesium-rtc-extension.b3dm"), "EPSG:28992")


def test_truncated_b3dm(tmp_path):
    data = shared_file(SAMPLES / "BatchedTextured" / "batchedTextured.b3dm").read_bytes()
    (tmp_path / "cut.b3dm").write_bytes(data[: len(data) // 2])
    with pytest.raises(InputFileError, match="truncated") as err:
        load_b3dm(tmp_path / "cut.b3dm", GEO)
    assert "cut.b3dm" in str(err.value)


def test_bad_magic(tmp_path):
    (tmp_path / "junk.b3dm").write_bytes(b"XXXX" + bytes(100))
    with pytest.raises(InputFileError, match="magic"):
        load_b3dm(tmp_path / "junk.b3dm", GEO)


def test_missing_content_is_named(tmp_path):
    src = shared_file(SAMPLES / "TilesetOfTilesets")
    shutil.copy(src / "tileset2.json", tmp_path / "tileset2.json")
    shutil.copy(src / "parent.b3dm", tmp_path / "parent.b3dm")  # tileset3/ and the leaves are absent
    with pytest.raises(InputFileError) as err:
        read_tileset(tmp_path / "tileset2.json", {"missing_children": "error"})
    assert "tileset3.json" in str(err.value) and "tileset2.json" in str(err.value)
    # by default the finest level present: the ADD parent, drawn anyway; the four children left out
    with pytest.warns(UserWarning, match="4 child content file.s. missing, 1 tile.s. drawn coarser"):
        loaded = read_tileset(tmp_path / "tileset2.json", {})
    parent = read_content(tmp_path / "parent.b3dm")
    assert sum(p.n_triangles for p in loaded.parts) == sum(p.n_triangles for p in parent) > 0
    (note,) = loaded.coarser
    assert note.tile == str(tmp_path / "parent.b3dm") and note.level == 0
    assert [Path(m).name for m in note.missing] == ["tileset3.json", "lr.b3dm", "ur.b3dm", "ul.b3dm"]


def test_invalid_tileset_json(tmp_path):
    (tmp_path / "tileset.json").write_text('{"asset": {"version": "1.0"}, "root": ')
    with pytest.raises(InputFileError, match="invalid JSON"):
        load_tileset(tmp_path / "tileset.json", GEO)


@pytest.mark.parametrize("required, refused", [(["3DTILES_content_gltf", "3DTILES_metadata"], None),
                                               (["3DTILES_implicit_tiling"], "3DTILES_implicit_tiling"),
                                               (["3DTILES_content_gltf", "3DTILES_bounding_volume_S2"],
                                                "3DTILES_bounding_volume_S2")])
def test_a_tileset_requiring_an_extension_it_cannot_honour_is_refused_naming_it(tmp_path, required, refused):
    """A tileset's own extensionsRequired: the pre-1.1 draft of implicit tiling (CesiumJS's and
    loaders.gl's test tilesets) was read as explicit tiles and failed on "content/{level}/{x}/{y}.b3dm
    is missing"; now such a tileset is refused naming the extension. Those read or safely left
    aside (glTF content, metadata) pass."""
    src = shared_file(SAMPLES / "TilesetWithTransforms")
    shutil.copytree(src, tmp_path / "t")
    doc = json.loads((tmp_path / "t" / "tileset.json").read_text())
    doc["extensionsUsed"] = doc["extensionsRequired"] = required
    (tmp_path / "t" / "tileset.json").write_text(json.dumps(doc))
    if refused is None:
        assert load_tileset(tmp_path / "t" / "tileset.json", GEO).n_triangles > 0
        return
    with pytest.raises(UnsupportedFeatureError, match=rf"tileset\.json: tileset requires unsupported extension\(s\) "
                                                      rf"{refused}"):
        load_tileset(tmp_path / "t" / "tileset.json", GEO)


def test_a_single_i3dm_or_cmpt_file_is_an_input_of_its_own(tmp_path):
    """A lone .i3dm, or a .cmpt composite of it (3d-tiles-samples, loaders.gl's test data), was
    "unknown model format" though the tile reader reads them by their magic: the suffixes now
    name that reader, and give what ``format: b3dm`` gave."""
    import struct

    from pipeline25d.formats import detect_format, load_district

    i3dm = shared_file(SAMPLES / "TilesetWithTransforms" / "instances.i3dm").read_bytes()
    pad = (-len(i3dm)) % 8
    body = i3dm + b"\0" * pad
    (tmp_path / "one.i3dm").write_bytes(i3dm)
    (tmp_path / "one.cmpt").write_bytes(b"cmpt" + struct.pack("<III", 1, 16 + len(body), 1) + body)
    want = load_district({"path": str(tmp_path / "one.i3dm"), "format": "b3dm"}, GEO)
    assert want.n_triangles > 0
    for name in ("one.i3dm", "one.cmpt"):
        assert detect_format(tmp_path / name) == "b3dm"
        got = load_district({"path": str(tmp_path / name)}, GEO)
        np.testing.assert_allclose(np.concatenate([p.vertices for p in got.parts]),
                                   np.concatenate([p.vertices for p in want.parts]))


def test_unsupported_gltf_extension_in_tileset(tmp_path):
    gltf = {"asset": {"version": "2.0"}, "extensionsRequired": ["EXT_example_unknown"]}
    (tmp_path / "c.gltf").write_text(json.dumps(gltf))
    tileset = {"asset": {"version": "1.1"}, "geometricError": 1,
               "root": {"geometricError": 0, "refine": "ADD", "content": {"uri": "c.gltf"},
                        "boundingVolume": {"sphere": [0, 0, 0, 1]}}}
    (tmp_path / "tileset.json").write_text(json.dumps(tileset))
    with pytest.raises(UnsupportedFeatureError, match="EXT_example_unknown") as err:
        load_tileset(tmp_path / "tileset.json", GEO)
    assert "c.gltf" in str(err.value)


def test_cyclic_external_tileset(tmp_path):
    tileset = {"asset": {"version": "1.0"}, "geometricError": 1,
               "root": {"geometricError": 1, "refine": "ADD", "content": {"uri": "tileset.json"},
                        "boundingVolume": {"sphere": [0, 0, 0, 1]}}}
    (tmp_path / "tileset.json").write_text(json.dumps(tileset))
    with pytest.raises(InputFileError, match="cycle"):
        load_tileset(tmp_path / "tileset.json", GEO)


def test_composite_tile(tmp_path):
    import struct

    b3dm = shared_file(SAMPLES / "BatchedTextured" / "batchedTextured.b3dm").read_bytes()
    cmpt = struct.pack("<4sIII", b"cmpt", 1, 16 + 2 * len(b3dm), 2) + b3dm + b3dm
    (tmp_path / "two.cmpt").write_bytes(cmpt)
    mesh = load_b3dm(tmp_path / "two.cmpt", GEO)
    assert mesh.n_triangles == 240
    _assert_bounds(mesh, (-75.613037, -75.610940), (40.041630, 40.043288))


def test_a_tileset_read_in_pieces_holds_the_triangles_of_a_whole_read(monkeypatch):
    """Ingest's pieces (here one content each) carry the whole read's triangles, and a tileset smaller
    than a piece is one piece: the parts of the whole read."""
    from pipeline25d.formats import district_pieces, load_district, tiles3d

    spec = {"path": str(shared_file(SAMPLES / "TilesetUniform" / "tileset.json"))}
    whole = load_district(spec, "EPSG:4978", max_geometric_error=0.0)
    one = list(district_pieces(spec, "EPSG:4978", max_geometric_error=0.0))
    assert len(one) == 1 and [p.vertices.tobytes() for p in one[0].parts] == [p.vertices.tobytes() for p in whole.parts]
    monkeypatch.setattr(tiles3d, "PIECE_BYTES", 1)
    pieces = list(district_pieces(spec, "EPSG:4978", max_geometric_error=0.0))

    def triangles(meshes) -> np.ndarray:
        rows = [np.round(p.vertices[p.faces].reshape(-1, 9), 4) for m in meshes for p in m.parts]
        return np.unique(np.concatenate(rows), axis=0)

    assert len(pieces) > 10 and np.array_equal(triangles(pieces), triangles([whole]))
    assert sum(m.n_triangles for m in pieces) == whole.n_triangles


# ----------------------------------------------------------------------------- i3dm orientation

TRI_Z_UP = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])   # test_formats_gltf's TRI, z up


def _i3dm(table: dict, binary: bytes) -> bytes:
    """An i3dm of the one-triangle glTF (embedded GLB) with feature ``table`` and its ``binary``."""
    import struct

    from test_formats_gltf import _glb, _gltf

    glb = _glb(*_gltf())
    ft_json = json.dumps(table).encode()
    ft_json += b" " * (-(32 + len(ft_json)) % 8)
    binary += b"\0" * (-len(binary) % 8)
    total = 32 + len(ft_json) + len(binary) + len(glb)
    return struct.pack("<4s7I", b"i3dm", 1, total, len(ft_json), len(binary), 0, 0, 1) + ft_json + binary + glb


def _enu_reference(lon_deg: float, lat_deg: float) -> np.ndarray:
    """East, north, up (columns) at a geodetic longitude and latitude (the textbook formulas)."""
    lon, lat = np.radians(lon_deg), np.radians(lat_deg)
    return np.column_stack([[-np.sin(lon), np.cos(lon), 0.0],
                            [-np.sin(lat) * np.cos(lon), -np.sin(lat) * np.sin(lon), np.cos(lat)],
                            [np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)]])


def test_i3dm_east_north_up_stands_each_instance_up_where_it_is(tmp_path):
    """EAST_NORTH_UP: each instance's axes become east, north and up at its own ECEF position (two
    instances 40 km apart, on the ellipsoid; pyproj gives their longitude and latitude, the
    textbook formulas the axes). Before, the flag was ignored: instances lay along ECEF's axes."""
    from pyproj import Transformer

    lonlat = np.array([[4.90, 52.37], [5.40, 52.30]])
    ecef = np.column_stack(Transformer.from_crs("EPSG:4979", "EPSG:4978", always_xy=True).transform(
        lonlat[:, 0], lonlat[:, 1], np.zeros(2)))
    rtc = ecef[0]
    table = {"INSTANCES_LENGTH": 2, "RTC_CENTER": rtc.tolist(), "POSITION": {"byteOffset": 0}, "EAST_NORTH_UP": True}
    path = tmp_path / "trees.i3dm"
    path.write_bytes(_i3dm(table, (ecef - rtc).astype(np.float32).tobytes()))
    part, = read_content(path)
    local = TRI_Z_UP
    for i in range(2):
        expected = (rtc + (ecef[i] - rtc).astype(np.float32)) + local @ _enu_reference(*lonlat[i]).T
        np.testing.assert_allclose(part.vertices[part.faces[i]], expected, atol=1e-6)


def _oct_encode(v: np.ndarray) -> np.ndarray:
    """The octahedral encoding in 0..65535 (Cigolle et al. 2014, as 3D Tiles' *_OCT32P stores it)."""
    p = v / np.abs(v).sum()
    if p[2] < 0:
        p = np.array([(1 - abs(p[1])) * (1 if p[0] >= 0 else -1), (1 - abs(p[0])) * (1 if p[1] >= 0 else -1), 0.0])
    return np.round((p[:2] * 0.5 + 0.5) * 65535).astype(np.uint16)


def test_i3dm_oct_encoded_normals_orient_the_instance(tmp_path):
    """NORMAL_UP_OCT32P / NORMAL_RIGHT_OCT32P: decoded, they orient the instance as NORMAL_UP and
    NORMAL_RIGHT would (16-bit normals: within 1e-4 on a unit triangle); an up vector below the
    horizon exercises the octahedron's folded half. Before, they were ignored."""
    up = np.array([1.0, -2.0, -3.0]) / np.sqrt(14.0)
    right = np.cross(up, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    table = {"INSTANCES_LENGTH": 1, "POSITION": {"byteOffset": 0}, "NORMAL_UP_OCT32P": {"byteOffset": 12},
             "NORMAL_RIGHT_OCT32P": {"byteOffset": 16}}
    binary = np.zeros(3, np.float32).tobytes() + _oct_encode(up).tobytes() + _oct_encode(right).tobytes()
    path = tmp_path / "one.i3dm"
    path.write_bytes(_i3dm(table, binary))
    part, = read_content(path)
    rotation = np.column_stack([right, up, np.cross(right, up)])
    np.testing.assert_allclose(part.vertices[part.faces[0]], TRI_Z_UP @ rotation.T, atol=1e-4)
