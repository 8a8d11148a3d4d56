"""WMS GetFeatureInfo through MapServer (pipeline25d.publish.wms_ids): a map and its id raster of known
rectangles published with their objects table; a query at each rectangle answers its id, name, heights
and attributes (quotes, markup, an escaped line break and non-ASCII text in one intact, commas as ;),
a query on the transparent corner answers no object, and both
layers are listed. Then the small demo run's own mapfile: a query at each flat roof, where each map
shows it, answers the id of that roof's building (its OBJ object, chunks/<district>/objects.json)."""

from __future__ import annotations

import html
import json
import re
import shutil

import pytest
from test_id_tiles import GRID, RECTS, scene
from test_wms import mapserv, request, start  # noqa: F401 (a fixture)

from pipeline25d.core.crs import horizontal_wkt
from pipeline25d.publish.objects import SceneObject, write_objects
from pipeline25d.publish.wms import write_mapfile

NAMES = {RECTS[0][4]: "ground", RECTS[1][4]: "hall", RECTS[2][4]: "tower", RECTS[3][4]: "shed"}


def attributes(name: str, k: int) -> dict:
    """An object's attributes; the hall's hold what a CSV join or an HTML answer could mangle."""
    if name != "hall":
        return {"use": "none", "floors": k}
    return {"use": "office, shop", "floors": k, "note": 'say "hi",\nthen <b>leave</b> & 東京; 100%'}


@pytest.fixture(scope="module")
def id_wms(tmp_path_factory, mapserv):  # noqa: F811 (the fixture)
    where = tmp_path_factory.mktemp("idwms") / "results"
    (where / "maps").mkdir(parents=True)
    cog, ids_tif, _ = scene(where / "maps")
    shutil.move(cog, where / "maps" / "az045_el45.tif")
    shutil.move(ids_tif, where / "maps" / "az045_el45.ids.tif")
    rows = [SceneObject(oid, f"d{oid >> 22}", name, "Building", 10.0 + k, 9.5 + k, attributes(name, k))
            for k, (oid, name) in enumerate(sorted(NAMES.items()))]
    write_objects(rows, where / "objects", horizontal_wkt("EPSG:25832"))
    write_mapfile("ids", [where / "maps" / "az045_el45.tif"], where / "wms" / "ids.map",
                  objects=where / "objects" / "objects.csv")
    server = start(where / "wms" / "ids.map", mapserv)
    yield server, {oid: (k, name) for k, (oid, name) in enumerate(sorted(NAMES.items()))}
    server.shutdown()
    server.server_close()


def feature_info(server, col: float, row: float) -> list[str]:
    """The cells of the HTML GetFeatureInfo answer at pixel (col, row) of the id raster, asked a little off
    its centre (MapServer takes a point on a pixel's edge to hold no pixel, and a WMS client's I, J for the
    corner or the centre of its pixel)."""
    x, y = (float(v) + 0.1 for v in GRID.xy(col + 0.5, row + 0.5))
    return feature_info_at(server, "az045_el45", x, y)


def feature_info_at(server, pid: str, x: float, y: float) -> list[str]:
    """The cells of the HTML GetFeatureInfo answer of layer ``<pid>_ids`` at scene point (x, y)."""
    kind, body = request(server, REQUEST="GetFeatureInfo", LAYERS=f"{pid}_ids", QUERY_LAYERS=f"{pid}_ids",
                         STYLES="", CRS="EPSG:25832", BBOX=f"{x - 5.5},{y - 5.5},{x + 5.5},{y + 5.5}",
                         WIDTH=11, HEIGHT=11, I=5, J=5, INFO_FORMAT="text/html", FORMAT="image/png")
    assert kind.startswith("text/html"), body
    return [html.unescape(c) for c in re.findall(r"<td>(.*?)</td>", body.decode())]


def test_getfeatureinfo_at_each_object_answers_its_id_name_heights_and_attributes(id_wms):
    server, table = id_wms
    for r0, c0, r1, c1, oid in RECTS[1:]:
        cells = feature_info(server, (c0 + c1) // 2, (r0 + r1) // 2)
        k, name = table[oid]
        assert cells[:4] == [str(oid), f"d{oid >> 22}", name, "Building"], cells
        assert float(cells[4]) == 10.0 + k and float(cells[5]) == 9.5 + k
        # MapServer's CSV join splits at every comma: written as ";"; quotes, markup, non-ASCII text intact
        assert cells[6] == json.dumps(attributes(name, k), ensure_ascii=False).replace(",", ";")
    # the ground between the buildings is the ground object; the transparent corner is nothing
    assert feature_info(server, 50, 300)[:3] == [str(RECTS[0][4]), f"d{RECTS[0][4] >> 22}", "ground"]
    assert feature_info(server, 5, 5) == []


def test_the_map_layer_is_still_drawn_and_the_id_layer_is_listed(id_wms):
    server, _ = id_wms
    kind, body = request(server, REQUEST="GetCapabilities")
    assert b"<Name>az045_el45</Name>" in body and b"<Name>az045_el45_ids</Name>" in body
    assert b"text/html" in body


def test_the_workflow_wms_answers_each_flat_roof_with_its_building(small_run, mapserv):  # noqa: F811
    """Where each map shows a flat roof's centre (its eave height above the DTM, along the view), the run's
    own mapfile answers the id and name of the roof's building (its OBJ object): on the nadir map every roof,
    on the obliques all but roofs hidden behind taller buildings (then a taller building's id)."""
    import json

    import numpy as np

    from pipeline25d.core.raster import DTM
    from pipeline25d.geometry.camera import project_above_ground
    from pipeline25d.geometry.perspectives import Perspective

    workdir, results = small_run
    truth = json.loads((workdir / "resources" / "demo" / "truth.json").read_text())["buildings"]
    flat = [b for b in truth if b["roof"] == "flat"]
    eave = {b["id"]: b["eave_z"] for b in truth}
    objects = {b["district"]: json.loads((results / "chunks" / b["district"] / "objects.json").read_text())
               for b in flat}
    centres = np.array([[*np.mean(b["footprint"], axis=0), b["eave_z"]] for b in flat])
    ground = DTM(str(results / "terrain" / "dtm.tif"), "EPSG:25832",
                 continuous=True).sample(centres[:, 0], centres[:, 1])
    server = start(results / "wms" / "small.map", mapserv)
    try:
        shares = {}
        for pid in ("az000_el90", "az045_el45", "az200_el30"):
            xy = project_above_ground(centres, ground, Perspective.from_id(pid))[:, :2]
            got = [feature_info_at(server, pid, float(x) + 0.1, float(y) + 0.1)[:3] for x, y in xy]
            want = [[str(objects[b["district"]][b["id"]]), b["district"], b["id"]] for b in flat]
            shares[pid] = float(np.mean([g == w for g, w in zip(got, want)]))
            for g, b in zip(got, flat):          # a roof not answered is hidden behind a taller building
                assert g[2] == b["id"] or eave[g[2]] > b["eave_z"], (pid, b["id"], g)
    finally:
        server.shutdown()
        server.server_close()
    print(shares)
    assert shares["az000_el90"] == 1.0 and min(shares.values()) >= 0.8, shares
