"""The scene's objects table (pipeline25d.publish.objects): a CityJSON of two box buildings ingested, then
tabled; ids from ingest's objects.json, attributes from the file, the model's height from the chunks
(the boxes' own heights) or its measuredHeight attribute, the measured height from heights.csv, the
GeoPackage read back by OGR, and every row found again through the viewer's shards."""

from __future__ import annotations

import json

import pytest

from pipeline25d.core.crs import horizontal_wkt
from pipeline25d.publish.objects import measured_heights, scene_objects, shard_bits, shard_of, write_objects
from pipeline25d.stages.ingest import ingest

CRS = "EPSG:28992"
# name: (x0, y0, x1, y1, z0, z1, attributes)
BOXES = {"B1": (85000.0, 446000.0, 85012.0, 446008.0, 1.0, 13.5, {"function": "office, shop", "storeys": 4}),
         "B2": (85030.0, 446000.0, 85040.0, 446020.0, 0.5, 6.25, {"measuredHeight": 6.0, "roofType": "flat"})}


def box_city(path) -> None:
    """A CityJSON of BOXES, each one Building with a closed Solid (outward faces)."""
    vertices, objects = [], {}
    for name, (x0, y0, x1, y1, z0, z1, attrs) in BOXES.items():
        k = len(vertices)
        vertices += [[x, y, z] for z in (z0, z1) for x, y in ((x0, y0), (x1, y0), (x1, y1), (x0, y1))]
        b, t = [k, k + 3, k + 2, k + 1], [k + 4, k + 5, k + 6, k + 7]
        sides = [[k + i, k + (i + 1) % 4, k + 4 + (i + 1) % 4, k + 4 + i] for i in range(4)]
        objects[name] = {"type": "Building", "attributes": attrs,
                         "geometry": [{"type": "Solid", "lod": "2", "boundaries": [[[b], [t], *[[s] for s in sides]]]}]}
    doc = {"type": "CityJSON", "version": "2.0", "transform": {"scale": [0.001, 0.001, 0.001], "translate": [0, 0, 0]},
           "metadata": {"referenceSystem": "https://www.opengis.net/def/crs/EPSG/0/28992"},
           "CityObjects": objects, "vertices": [[round(c * 1000) for c in v] for v in vertices]}
    path.write_text(json.dumps(doc))


@pytest.fixture(scope="module")
def table(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("objects")
    box_city(tmp / "city.json")
    ingest({"path": str(tmp / "city.json")}, "d", CRS, 100.0, 0.5, tmp / "chunks" / "d" / "index.json", slot=5)
    (tmp / "heights.csv").write_text("id,height,n_views\nB1,12.31,3\nB2,,0\nother,4.0,1\n")
    rows = scene_objects(tmp / "chunks", ["d"], {"d": str(tmp / "city.json")}, tmp / "heights.csv")
    index = write_objects(rows, tmp / "objects", horizontal_wkt(CRS))
    return tmp, rows, index


def test_rows_carry_ids_attributes_and_both_heights(table):
    tmp, rows, _ = table
    ids = json.loads((tmp / "chunks" / "d" / "objects.json").read_text())
    assert {r.name: r.id for r in rows} == ids and all(i >> 22 == 5 for i in ids.values())
    by = {r.name: r for r in rows}
    x0, y0, x1, y1, z0, z1, attrs = BOXES["B1"]
    assert by["B1"].type == "Building" and by["B1"].attributes == attrs
    assert by["B1"].model_height == pytest.approx(z1 - z0, abs=2e-3)       # float32 chunks: 1 mm
    assert by["B1"].extent == pytest.approx((x0, y0, x1, y1), abs=2e-3)
    assert by["B2"].model_height == 6.0                                   # the file's measuredHeight wins
    assert by["B1"].measured_height == 12.31 and by["B2"].measured_height is None
    assert measured_heights(tmp / "heights.csv") == {"B1": 12.31, "other": 4.0}


def test_the_geopackage_and_the_shards_give_the_same_rows(table):
    from osgeo import ogr

    tmp, rows, index = table
    ds = ogr.Open(str(tmp / "objects" / "objects.gpkg"))
    layer = ds.GetLayerByName("objects")
    got = {}
    for feat in layer:
        got[feat.GetField("name")] = (feat.GetField("id"), json.loads(feat.GetField("attributes")),
                                      feat.GetField("model_height"), feat.GetGeometryRef().GetEnvelope())
    assert len(got) == len(rows) == 2
    for r in rows:
        oid, attrs, height, env = got[r.name]
        assert oid == r.id and attrs == r.attributes and height == pytest.approx(r.model_height, abs=1e-3)
        assert env == pytest.approx((r.extent[0], r.extent[2], r.extent[1], r.extent[3]), abs=1e-3)
    assert (json.loads((tmp / "objects" / "shards" / "index.json").read_text()) == index
            == {"5": {"district": "d", "bits": 0}})
    for r in rows:
        shard = json.loads((tmp / "objects" / "shards" / "5" / f"{shard_of(r.id, 0)}.json").read_text())
        assert shard[str(r.id)]["name"] == r.name
    header = (tmp / "objects" / "objects.csv").read_text().splitlines()[0]
    assert header == "row,id,district,name,type,model_height,measured_height,attributes"


def test_shards_hold_about_512_objects_each():
    assert [shard_bits(n) for n in (0, 1, 512, 513, 1024, 100_000, 10**9, 2**32)] == [0, 0, 0, 1, 1, 8, 21, 22]
    assert shard_of(5 << 22 | (1 << 21) | 7, 1) == 1 and shard_of(5 << 22 | 7, 1) == 0
