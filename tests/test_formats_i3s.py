"""I3S scene layer packages (.slpk, or unpacked): level rule, placement, geometry buffers, textures,
features, and broken packages, on generated packages with exact truth (pipeline25d_lab.scenes.i3s_sample)."""

from __future__ import annotations

import gzip
import io
import json
import warnings
import zipfile

import numpy as np
import pytest

from pipeline25d.core.errors import InputFileError, MissingTextureWarning, UnsupportedFeatureError
from pipeline25d.formats import load_district
from pipeline25d_lab.scenes import i3s_sample as sample

CRS = "EPSG:28992"


def _load(path, gsd, **spec):
    return load_district({"path": str(path), **spec}, CRS, gsd=gsd)


def _by_node(mesh) -> dict[str, np.ndarray]:
    return {p.name: p.vertices for p in mesh.parts}


@pytest.fixture(scope="module")
def slpk(tmp_path_factory):
    return sample.write_package(tmp_path_factory.mktemp("i3s") / "sample.slpk")


@pytest.mark.parametrize("gsd, drawn", [(2.0, ["node 1"]), (1.0, ["node 2", "node 3"]), (None, ["node 2", "node 3"])])
def test_the_level_drawn_follows_the_threshold_and_each_vertex_lies_where_written(slpk, gsd, drawn):
    """A 70.7 m bounding sphere is 71 px at gsd 2 (within 100 px: the coarse node) and 141 px at gsd 1
    (its children); a projected layer's offsets plus the box centre are the vertices, exactly."""
    got = _by_node(_load(slpk, gsd))
    assert sorted(got) == drawn
    origin = sample.PROJECTED[1]
    for name, vertices in got.items():
        np.testing.assert_allclose(vertices, sample.node_corners()[int(name.split()[1])] + origin, atol=1e-6)


def test_a_geographic_layer_lands_where_pyproj_puts_its_lon_lat(tmp_path):
    """Degree offsets from the box centre: the vertices equal pyproj's transform of the lon/lat the
    package was written from (under the layer's wkid + vcsWkid, NAP heights), to the float32
    offsets' precision (~1e-8 degrees, under a millimetre)."""
    from pyproj import CRS as ProjCRS
    from pyproj import Transformer

    path = sample.write_package(tmp_path / "geo.slpk", geographic=True)
    got = _by_node(_load(path, None))
    to_rd = Transformer.from_crs(ProjCRS(f"EPSG:4326+{sample.VERTICAL}"), ProjCRS(CRS).to_3d(), always_xy=True)
    for k in (2, 3):
        lonlat = sample.corners_lonlat(sample.node_corners()[k])
        want = np.column_stack(to_rd.transform(lonlat[:, 0], lonlat[:, 1], lonlat[:, 2]))
        np.testing.assert_allclose(got[f"node {k}"], want, atol=2e-3)


@pytest.mark.parametrize("geographic", [False, True])
def test_draco_geometry_reads_as_the_plain_buffer_with_its_scale_and_features_from_draco_metadata(tmp_path,
                                                                                                  geographic):
    """Draco alone (ArcGIS's layout: a geographic layer's positions in units of i3s-scale degrees,
    feature indices in a generic attribute, both named in Draco metadata DracoPy does not give):
    the same triangles and objects as the plain buffer, to the quantisation's precision."""
    plain = _load(sample.write_package(tmp_path / "plain.slpk", geographic=geographic), None)
    draco = _load(sample.write_package(tmp_path / "draco.slpk", geographic=geographic, draco=True,
                                       uncompressed=False), None)
    got, want = {p.name: p for p in draco.parts}, {p.name: p for p in plain.parts}
    assert sorted(got) == sorted(want)
    for name, part in want.items():
        np.testing.assert_allclose(got[name].vertices, part.vertices, atol=2e-3)
        assert [got[name].objects[k] for k in got[name].face_objects] == \
            [part.objects[k] for k in part.face_objects]
    assert draco.object_info() == plain.object_info()


def test_draco_metadata_is_read_from_the_header():
    from pipeline25d.formats.i3s_draco import draco_metadata

    offsets = sample.corners_lonlat(sample.node_corners()[2]) - sample.GEOGRAPHIC_CENTRE
    data = sample._draco_buffer(offsets, np.zeros((6, 2)), [(101, 0, 0), (102, 1, 1)], geographic=True)
    meta = draco_metadata(data)
    (scaled,) = [m for m in meta.values() if "i3s-scale_x" in m]
    assert np.frombuffer(scaled["i3s-scale_y"], "<f8")[0] == sample.DRACO_SCALE
    (features,) = [m for m in meta.values() if "i3s-feature-ids" in m]
    assert np.frombuffer(features["i3s-feature-ids"], "<i4").tolist() == [101, 102]
    assert draco_metadata(data[:9] + bytes([0, 0]) + data[11:]) == {}           # the flag cleared: none
    with pytest.raises(ValueError, match="cut short"):
        draco_metadata(data[:16])


def test_the_texture_is_the_package_image_with_its_top_row_at_v_1(slpk):
    (part,) = _load(slpk, 2.0).parts
    assert part.texture == sample.texture_png()
    north = part.vertices[:, 1] > sample.PROJECTED[1][1]            # the square's north edge: I3S v = 0
    np.testing.assert_array_equal(part.uv[north, 1], 1.0)
    np.testing.assert_array_equal(part.uv[~north, 1], 0.0)
    assert part.colors is None


def test_a_dds_only_texture_set_is_decoded(slpk, tmp_path):
    """ArcGIS's DDS (DXT1) texture, the set's only format: level 0 decoded to the image it encodes
    (the sample's red and blue are DXT1 endpoint colours, so exactly)."""
    import io

    from PIL import Image

    dds = io.BytesIO()
    Image.open(io.BytesIO(sample.texture_png())).save(dds, format="DDS", pixel_format="DXT1")
    layer = _layer(slpk, textureSetDefinitions=[{"formats": [{"name": "0_0_1", "format": "dds"}]}])
    path = _rewrite(slpk, tmp_path / "dds.slpk", **{"3dSceneLayer.json.gz": layer, "nodes/1/textures/0.png": None,
                                                     "nodes/1/textures/0_0_1.bin.dds": dds.getvalue()})
    (part,) = _load(path, 2.0).parts
    got = np.asarray(Image.open(io.BytesIO(part.texture)).convert("RGB"))
    np.testing.assert_array_equal(got, np.asarray(Image.open(io.BytesIO(sample.texture_png())).convert("RGB")))


def test_features_are_objects_and_the_untextured_fine_level_has_its_vertex_colours(slpk):
    parts = {p.name: p for p in _load(slpk, 1.0).parts}
    west = parts["node 2"]
    assert [west.objects[k] for k in west.face_objects] == ["101", "102"]
    assert [parts["node 3"].objects[k] for k in parts["node 3"].face_objects] == ["203", "203"]
    np.testing.assert_array_equal(west.colors, np.tile([200, 180, 160, 255], (6, 1)))
    assert west.texture is None


def test_features_carry_their_attributes_and_a_missing_buffer_leaves_its_field_out(slpk, tmp_path):
    """OBJECTID (Oid32), a UTF-8 name (byte counts, NUL-terminated) and a Float64 aligned to 8 bytes,
    value k for the node's k-th feature; the same through the 1.6 documents."""
    legacy = sample.write_package(tmp_path / "v16.slpk", pages=False)
    for path in (slpk, legacy):
        info = load_district({"path": str(path)}, CRS, gsd=1.0).object_info()
        assert info == {str(i): {"attributes": {"OBJECTID": i, "name": sample.feature_name(i), "height": i / 4}}
                        for i in (101, 102, 203)}
    path = _rewrite(slpk, tmp_path / "no-names.slpk", **{"nodes/2/attributes/f_1/0.bin.gz": None})
    with pytest.warns(UserWarning, match=r"no-names\.slpk: attribute buffers missing or not of 2 values, those "
                                         r"attributes left out: nodes/2/attributes/f_1/0 \(name\)"):
        info = load_district({"path": str(path)}, CRS, gsd=1.0).object_info()
    assert info["101"] == {"attributes": {"OBJECTID": 101, "height": 25.25}}
    assert info["203"]["attributes"]["name"] == sample.feature_name(203)


def test_an_unpacked_package_reads_as_the_package(slpk, tmp_path):
    folder = sample.write_package(tmp_path / "unpacked", packed=False)
    packed, unpacked = _by_node(_load(slpk, 1.0)), _by_node(_load(folder, 1.0))
    assert sorted(packed) == sorted(unpacked)
    for name in packed:
        np.testing.assert_array_equal(packed[name], unpacked[name])


@pytest.mark.parametrize("gsd", [2.0, 1.0, None])
def test_a_1_6_package_of_node_documents_reads_as_its_node_pages(slpk, tmp_path, gsd):
    """The same nodes through I3S 1.6 index documents (bounding spheres, a diameter threshold, child
    hrefs, the store's defaultGeometrySchema): the same levels, vertices, texture and objects."""
    legacy = sample.write_package(tmp_path / "v16.slpk", pages=False)
    old, new = {p.name: p for p in _load(legacy, gsd).parts}, {p.name: p for p in _load(slpk, gsd).parts}
    assert sorted(old) == sorted(new)
    for name, part in new.items():
        np.testing.assert_array_equal(old[name].vertices, part.vertices)
        assert old[name].texture == part.texture and old[name].objects == part.objects
        np.testing.assert_array_equal(old[name].uv if part.uv is not None else 0, part.uv if part.uv is not None else 0)


def test_the_box_before_reading_and_objects_come_from_the_layer(slpk, tmp_path):
    from pipeline25d.formats.boxes import input_box
    from pipeline25d.formats.has_objects import input_has_objects

    box = input_box({"path": str(slpk)})
    vertices = np.concatenate([p.vertices for p in _load(slpk, None).parts])
    assert box.crs == CRS
    np.testing.assert_allclose(box.corners[:, :2], [vertices.min(0)[:2], vertices.max(0)[:2]], atol=1e-6)
    assert box.corners[0, 2] <= vertices[:, 2].min() and box.corners[1, 2] >= vertices[:, 2].max()
    assert input_has_objects({"path": str(slpk)})
    mesh = sample.write_package(tmp_path / "mesh.slpk", layer_type="IntegratedMesh")
    assert not input_has_objects({"path": str(mesh)})
    assert all(not p.objects for p in _load(mesh, None).parts)


def test_without_a_full_extent_the_box_is_the_store_footprint(slpk, tmp_path):
    """ArcGIS Pro writes no fullExtent: the store's 2D extent in its indexCRS is the box's footprint,
    its heights unknown (so an absurd gsd is refused before any job reads the package)."""
    from pipeline25d.formats.boxes import input_box

    with zipfile.ZipFile(slpk) as z:
        store = json.loads(gzip.decompress(z.read("3dSceneLayer.json.gz")))["store"]
    vertices = np.concatenate([p.vertices for p in _load(slpk, None).parts])
    (x0, y0, _), (x1, y1, _) = vertices.min(0), vertices.max(0)
    store.update(extent=[x0 - 1, y0 - 2, x1 + 3, y1 + 4], indexCRS="http://www.opengis.net/def/crs/EPSG/0/28992")
    path = _rewrite(slpk, tmp_path / "no-full-extent.slpk",
                    **{"3dSceneLayer.json.gz": _layer(slpk, fullExtent=None, store=store)})
    box = input_box({"path": str(path)})
    assert box.crs == CRS and not box.heights and box.source == "the I3S store's extent (its footprint)"
    np.testing.assert_array_equal(box.corners[:, :2], [[x0 - 1, y0 - 2], [x1 + 3, y1 + 4]])
    store.pop("extent")
    assert input_box({"path": str(_rewrite(slpk, tmp_path / "no-extent.slpk", **{
        "3dSceneLayer.json.gz": _layer(slpk, fullExtent=None, store=store)}))}) is None


def _rewrite(source, target, **changes):
    """A copy of a package with entries replaced (bytes) or removed (None)."""
    with zipfile.ZipFile(source) as z:
        entries = {name: z.read(name) for name in z.namelist()}
    entries.update(changes)
    with zipfile.ZipFile(target, "w") as z:
        for name, data in entries.items():
            if data is not None:
                z.writestr(name, data)
    return target


def _layer(slpk, **changes) -> bytes:
    with zipfile.ZipFile(slpk) as z:
        layer = json.loads(gzip.decompress(z.read("3dSceneLayer.json.gz")))
    layer.update(changes)
    return gzip.compress(json.dumps(layer).encode())


def test_broken_packages_are_errors_naming_them(slpk, tmp_path):
    (tmp_path / "not-a-zip.slpk").write_bytes(b"PK but not really a zip file")
    cases = [
        (tmp_path / "not-a-zip.slpk", InputFileError, r"not-a-zip\.slpk: is not a scene layer package"),
        (_rewrite(slpk, tmp_path / "no-layer.slpk", **{"3dSceneLayer.json.gz": None}), InputFileError,
         r"no-layer\.slpk: has no 3dSceneLayer\.json"),
        (_rewrite(slpk, tmp_path / "points.slpk", **{"3dSceneLayer.json.gz": _layer(slpk, layerType="PointCloud")}),
         UnsupportedFeatureError, r"points\.slpk: I3S layerType 'PointCloud'"),
        (_rewrite(slpk, tmp_path / "v16.slpk", **{"3dSceneLayer.json.gz": _layer(slpk, nodePages=None),
                                                  "nodes/root/3dNodeIndexDocument.json.gz": None}),
         InputFileError, r"v16\.slpk: has no nodes/root/3dNodeIndexDocument\.json"),
        (_rewrite(slpk, tmp_path / "short.slpk", **{"nodes/2/geometries/0.bin.gz": gzip.compress(
            np.array([6, 2], "<u4").tobytes() + bytes(40))}), InputFileError,
         r"short\.slpk: nodes/2/geometries/0 is cut short: attribute position ends at byte 80"),
        (_rewrite(slpk, tmp_path / "no-geometry.slpk", **{"nodes/3/geometries/0.bin.gz": None}), InputFileError,
         r"no-geometry\.slpk: node 3: no geometry buffer in the package"),
        (_rewrite(slpk, tmp_path / "bad-page.slpk", **{"nodepages/0.json.gz": gzip.compress(b"{nodes")}),
         InputFileError, r"bad-page\.slpk: nodepages/0\.json is not valid JSON"),
        (_rewrite(slpk, tmp_path / "cycle.slpk", **{"nodepages/0.json.gz": gzip.compress(json.dumps(
            {"nodes": [{"index": 0, "children": [1]}, {"index": 1, "children": [0]}]}).encode())}),
         InputFileError, r"cycle\.slpk: node 0 is reached twice"),
    ]
    for path, error, message in cases:
        with pytest.raises(error, match=message):
            _load(path, 1.0)


def test_a_texture_that_is_not_an_image_is_a_missing_texture(slpk, tmp_path):
    path = _rewrite(slpk, tmp_path / "bad-texture.slpk", **{"nodes/1/textures/0.png": b"\x89PNG\r\n\x1a\n cut"})
    with pytest.raises(InputFileError, match=r"bad-texture\.slpk: the texture of node 1: nodes/1/textures/0"):
        _load(path, 2.0)
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        (part,) = _load(path, 2.0, missing_textures="untextured").parts
    assert any(issubclass(w.category, MissingTextureWarning) for w in seen)
    assert part.texture is None and part.uv is None


def test_a_gzip_bomb_entry_is_refused(slpk, tmp_path):
    from pipeline25d.formats import gzipped

    bomb = io.BytesIO()
    with gzip.GzipFile(fileobj=bomb, mode="wb") as f:
        f.write(bytes(4 << 20))
    path = _rewrite(slpk, tmp_path / "bomb.slpk", **{"nodepages/0.json.gz": bomb.getvalue()})
    import pipeline25d.formats.slpk as slpk_module

    with pytest.MonkeyPatch.context() as mp:             # a 4 MiB entry against a limit of 1 MiB
        mp.setattr(slpk_module, "gunzipped", lambda data, where: gzipped.gunzipped(data, where, 1 << 20))
        with pytest.raises(InputFileError, match=r"nodepages/0\.json\.gz: gzip data decompresses to more than"):
            _load(path, 1.0)


def test_a_1_6_href_that_leaves_the_package_nodes_is_refused(tmp_path):
    legacy = sample.write_package(tmp_path / "v16.slpk", pages=False)
    doc = {"id": "root", "mbs": [85000, 447000, 0, 100], "children": [{"id": "x", "href": "../../../../etc"}]}
    path = _rewrite(legacy, tmp_path / "escape.slpk",
                    **{"nodes/root/3dNodeIndexDocument.json.gz": gzip.compress(json.dumps(doc).encode())})
    with pytest.raises(InputFileError, match=r"escape\.slpk: href '\.\./\.\./\.\./\.\./etc' of node root leaves"):
        _load(path, 1.0)
