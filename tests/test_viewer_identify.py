"""Identifying objects in the web viewer (headless Chromium, identify.js) over the small demo run.

The demo's OBJ districts carry one object per material, so the id layer here is written from the
generator's truth instead: each perspective's id raster gives every opaque map pixel the terrain's id,
and the pixels where the map shows a building's roof (its footprint moved h·cot φ along the view
direction, h its eave above the terrain) that building's id. The rasters are cut into id tiles and the
table written by the product's own functions; the viewer must then answer, on three perspectives
turned and not, the building's id at a click on its roof, and never a building on open road.
"""

from __future__ import annotations

import json
import math
import zlib

import numpy as np
import pytest
from test_viewer_browser import (SIZE, ZOOM, bearing_of, browser, lonlat, open_page, screen_px,  # noqa: F401
                                 served, shot)

from pipeline25d.core.crs import horizontal_wkt
from pipeline25d.core.geotiff import write_geotiff
from pipeline25d.core.grid import Grid
from pipeline25d.publish.objects import SceneObject, measured_heights, write_objects
from pipeline25d.publish.viewer import write_viewer
from pipeline25d.stages.objects import district_slots, object_ids
from pipeline25d.stages.tiles import ids as id_tiles
from pipeline25d.stages.tiles.web import tms

VIEWS = (("az000_el90", False), ("az045_el45", False), ("az045_el45", True), ("az200_el30", False),
         ("az200_el30", True))


def roof_shift(building: dict, azimuth: float, elevation: float) -> np.ndarray:
    """Where a perspective shows a flat roof relative to its footprint: h·cot φ along d."""
    from pipeline25d_lab.scenes.demo import terrain_height

    x, y = np.mean(building["footprint"], axis=0)
    t, f = math.radians(azimuth), math.radians(elevation)
    h = building["eave_z"] - terrain_height(x, y)
    return h * math.cos(f) / math.sin(f) * np.array([math.sin(t), math.cos(t)])


def write_id_raster(map_tif, out, buildings: list[dict], ids: dict[str, int], ground: int, azimuth, elevation) -> None:
    from matplotlib.path import Path as Polygon
    from osgeo import gdal

    ds = gdal.Open(str(map_tif))
    grid = Grid.of_dataset(ds)
    alpha = ds.GetRasterBand(4).ReadAsArray()
    raster = np.where(alpha > 0, ground, 0).astype(np.uint32)
    cols, rows = np.meshgrid(np.arange(grid.width) + 0.5, np.arange(grid.height) + 0.5)
    xs, ys = grid.xy(cols.ravel(), rows.ravel())
    pts = np.column_stack([xs, ys])
    for b in buildings:
        poly = np.asarray(b["footprint"]) + roof_shift(b, azimuth, elevation)
        lo, hi = poly.min(axis=0), poly.max(axis=0)
        near = np.nonzero((pts[:, 0] >= lo[0]) & (pts[:, 0] <= hi[0]) & (pts[:, 1] >= lo[1]) & (pts[:, 1] <= hi[1]))[0]
        inside = near[Polygon(poly).contains_points(pts[near])]
        flat = raster.reshape(-1)
        flat[inside] = np.where(alpha.reshape(-1)[inside] > 0, ids[b["id"]], 0)
    write_geotiff(out, raster, grid, ds.GetProjection(), "UInt32", ["TILED=YES", "COMPRESS=ZSTD"], nodata=0)


@pytest.fixture(scope="module")
def id_viewer(served):
    """The small run's viewer written again (results/viewer-ids/) with an id layer of the demo's buildings
    (results/idtest/): (base URL, workdir, results, truth, {building name: id}, ground id)."""
    base_url, workdir, results = served
    truth = json.loads((workdir / "resources" / "demo" / "truth.json").read_text())
    report = json.loads((results / "report" / "report.json").read_text())
    slots = district_slots(truth["districts"] if isinstance(truth["districts"], list) else list(truth["districts"]))
    ids: dict[str, int] = {}
    for district, slot in slots.items():
        names = [b["id"] for b in truth["buildings"] if b["district"] == district] + (["terrain"] if district == "d0" else [])
        ids.update(object_ids(names, slot, district))
    ground = ids.pop("terrain")
    layer = results / "idtest"
    for p in report["perspectives"]:
        tif = layer / "maps" / f"{p['id']}.ids.tif"
        tif.parent.mkdir(parents=True, exist_ok=True)
        write_id_raster(results / "maps" / f"{p['id']}.tif", tif, truth["buildings"], ids, ground, p["azimuth"],
                        p["elevation"])
        tms(tif, "14-17", layer / "idtiles" / p["id"], tile_format="ids")
    measured = measured_heights(results / "heights.csv")
    rows = [SceneObject(ids[b["id"]], b["district"], b["id"], "Building", b["ridge_z"] - b["base_z"],
                        measured.get(b["id"])) for b in truth["buildings"]]
    rows.append(SceneObject(ground, "d0", "terrain"))
    write_objects(sorted(rows, key=lambda r: r.id), layer / "objects", horizontal_wkt("EPSG:25832"))
    write_viewer(results / "report" / "report.json", results / "viewer-ids" / "index.html", ids=layer)
    return base_url, workdir, results, truth, ids, ground


def click_id(page, xy) -> int:
    page.evaluate("delete document.getElementById('object').dataset.id")
    page.mouse.click(*xy)
    page.wait_for_function("document.getElementById('object').dataset.id !== undefined", timeout=10000)
    return int(page.get_attribute("#object", "data-id"))


def open_road(truth: dict, buildings: list[dict], azimuth: float, elevation: float) -> np.ndarray:
    """A road centreline point at least 6 m from every building's footprint and shown roof."""
    from matplotlib.path import Path as Polygon

    polys = [Polygon(np.asarray(b["footprint"]) + s * roof_shift(b, azimuth, elevation))
             for b in buildings for s in (0.0, 0.5, 1.0)]
    for road in truth["roads"]:
        line = np.asarray(road["centerline"])[:, :2]
        for k in np.linspace(0.2, 0.8, 7):
            pt = line[0] + k * (line[-1] - line[0])
            if not any(poly.contains_point(pt, radius=-12.0) or poly.contains_point(pt, radius=12.0) for poly in polys):
                return pt
    raise AssertionError("no open road point")


def test_a_click_on_a_roof_answers_its_building_and_on_open_road_never_a_building(browser, id_viewer, tmp_path):
    base_url, _, results, truth, ids, ground = id_viewer
    report = json.loads((results / "report" / "report.json").read_text())
    view = {p["id"]: p for p in report["perspectives"]}
    flat = sorted((b for b in truth["buildings"] if b["roof"] == "flat"), key=lambda b: -b["eave_z"])[:2]
    measured = measured_heights(results / "heights.csv")
    responses: list = []
    answers = {}
    for k, (pid, turned) in enumerate(VIEWS):
        p = view[pid]
        for b in flat[k % 2:k % 2 + 1]:                 # the two tallest flat roofs in turn
            roof = np.mean(b["footprint"], axis=0) + roof_shift(b, p["azimuth"], p["elevation"])
            centre = lonlat(roof)
            page = open_page(browser, f"{base_url}/viewer-ids/index.html#{pid}/{ZOOM}/{centre[1]:.7f}/{centre[0]:.7f}"
                             + ("/up" if turned else ""), responses)
            bearing = bearing_of(page)[0]
            assert (abs(bearing) > 1) == (turned and p["elevation"] != 90), bearing
            got = click_id(page, screen_px(roof, centre, bearing))
            page.wait_for_function("document.querySelector('#object .name') !== null")
            name = page.text_content("#object .name")
            rows = page.text_content("#object table")
            shot(page, tmp_path, f"identify-{pid}{'-up' if turned else ''}-{b['id']}.png")
            answers[(pid, turned, b["id"])] = got
            assert got == ids[b["id"]], (pid, turned, b["id"], got)
            assert name.startswith(b["id"]), name
            if measured.get(b["id"]) is not None:
                assert f"{measured[b['id']]:.2f} m" in rows, rows
            road = open_road(truth, truth["buildings"], p["azimuth"], p["elevation"])
            at = lonlat(road)
            page.evaluate(f"map.setView([{at[1]}, {at[0]}], {ZOOM}, {{animate: false}})")   # the id tile is
            got = click_id(page, screen_px(road, at, bearing))                                 # fetched by the click
            assert got not in set(ids.values()) and got in (ground, 0), (pid, turned, road, got)
            if k == 0:          # the page's decoder against the writer's, beyond 256 ids a tile too (uint16)
                rng = np.random.default_rng(3)
                for n in (3, 300):
                    tile = np.resize(rng.choice(2**32, n, replace=False).astype(np.uint32), (256, 256))
                    raw = list(zlib.decompress(id_tiles.encode(tile)))
                    decoded = page.evaluate("raw => Array.from(identify.decode(new Uint8Array(raw).buffer))", raw)
                    assert np.array_equal(np.array(decoded, np.uint32).reshape(256, 256), tile), n
            page.close()
    print(json.dumps({f"{k[0]}{'-up' if k[1] else ''}/{k[2]}": v for k, v in answers.items()}))
    assert [r for r in responses if r[1] >= 400 and not r[0].endswith("favicon.ico")] == []
