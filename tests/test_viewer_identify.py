"""Identifying objects in the web viewer (headless Chromium, identify.js) over the small demo run's own
id layer: the workflow's id maps (maps/<id>.ids.tif), id tiles (idtiles/) and objects table (objects/),
as its viewer (viewer/index.html) publishes them. The demo's OBJ names one object per building (its id
in truth.json), road and terrain; the viewer must answer, on three perspectives turned and not, the
building's id (chunks/<district>/objects.json) at a click where the map shows its roof (its footprint
centre moved h·cot φ along the view direction, h its eave above the terrain, computed here from truth),
and never a building on open road.
"""

from __future__ import annotations

import json
import math
import zlib

import numpy as np
from test_viewer_browser import ZOOM, bearing_of, lonlat, open_page, screen_px, shot

from pipeline25d.publish.objects import measured_heights
from pipeline25d.stages.tiles import ids as id_tiles

VIEWS = (("az000_el90", False), ("az045_el45", False), ("az045_el45", True), ("az200_el30", False),
         ("az200_el30", True))


def roof_shift(building: dict, azimuth: float, elevation: float) -> np.ndarray:
    """Where a perspective shows a flat roof relative to its footprint: h·cot φ along d."""
    from pipeline25d_lab.scenes.demo import terrain_height

    x, y = np.mean(building["footprint"], axis=0)
    t, f = math.radians(azimuth), math.radians(elevation)
    h = building["eave_z"] - terrain_height(x, y)
    return h * math.cos(f) / math.sin(f) * np.array([math.sin(t), math.cos(t)])


def run_ids(workdir, results) -> tuple[dict, dict[str, int], set[int]]:
    """(truth, {building id: object id}, the ids of the ground: terrain and roads) of the run."""
    truth = json.loads((workdir / "resources" / "demo" / "truth.json").read_text())
    objects: dict[str, int] = {}
    for district in truth["districts"]:
        objects |= json.loads((results / "chunks" / district / "objects.json").read_text())
    buildings = {b["id"] for b in truth["buildings"]}
    return truth, {k: v for k, v in objects.items() if k in buildings}, \
        {v for k, v in objects.items() if k not in buildings}


def shown(building: dict, azimuth: float, elevation: float):
    """Where a perspective shows a building (walls and roof): the hull of its footprint and its shown roof."""
    from matplotlib.path import Path as Polygon
    from scipy.spatial import ConvexHull

    corners = np.asarray(building["footprint"])
    hull = np.vstack([corners, corners + roof_shift(building, azimuth, elevation)])
    return Polygon(hull[ConvexHull(hull).vertices])


def visible(truth: dict, building: dict, azimuth: float, elevation: float, roof: np.ndarray | None = None) -> bool:
    """Whether no taller building shows within 3 m of where ``building``'s roof centre shows (or ``roof``)."""
    if roof is None:
        roof = np.mean(building["footprint"], axis=0) + roof_shift(building, azimuth, elevation)
    return not any(shown(other, azimuth, elevation).contains_point(roof, radius=3.0) or
                   shown(other, azimuth, elevation).contains_point(roof, radius=-3.0)
                   for other in truth["buildings"] if other is not building and other["eave_z"] > building["eave_z"])


def click_id(page, xy) -> int:
    page.evaluate("delete document.getElementById('object').dataset.id")
    page.mouse.click(*xy)
    page.wait_for_function("document.getElementById('object').dataset.id !== undefined", timeout=10000)
    return int(page.get_attribute("#object", "data-id"))


def open_road(truth: dict, buildings: list[dict], azimuth: float, elevation: float) -> tuple[str, np.ndarray]:
    """(road id, a point of its centreline) at least 6 m from where any building shows (walls and roof), and
    14 m from any other road's centreline (not at a crossing)."""
    polys = [shown(b, azimuth, elevation) for b in buildings]
    for road in truth["roads"]:
        line = np.asarray(road["centerline"])[:, :2]
        for k in np.linspace(0.1, 0.9, 33):
            pt = line[0] + k * (line[-1] - line[0])
            others = [np.asarray(r["centerline"])[0] for r in truth["roads"] if r["kind"] != road["kind"]]
            across = [abs(pt[1] - o[1]) if road["kind"] == "ns" else abs(pt[0] - o[0]) for o in others]
            if min(across, default=99.0) >= 14.0 and not any(
                    poly.contains_point(pt, radius=-6.0) or poly.contains_point(pt, radius=6.0) for poly in polys):
                return road["id"], pt
    raise AssertionError("no open road point")


def test_a_click_on_a_roof_answers_its_building_and_on_open_road_never_a_building(browser, served, tmp_path):
    """The run's own viewer: at each view, a click where the map shows each of the two tallest flat roofs
    (seen on every view) answers that building's id, its name and its measured height; a click on an open
    road answers that road (ground, never a building)."""
    base_url, workdir, results = served
    truth, ids, ground = run_ids(workdir, results)
    report = json.loads((results / "report" / "report.json").read_text())
    view = {p["id"]: p for p in report["perspectives"]}
    flat = [b for b in sorted(truth["buildings"], key=lambda b: -b["eave_z"]) if b["roof"] == "flat"
            and all(visible(truth, b, view[pid]["azimuth"], view[pid]["elevation"]) for pid, _ in VIEWS)][:2]
    objects = {k: v for d in truth["districts"] for k, v in
               json.loads((results / "chunks" / d / "objects.json").read_text()).items()}
    measured = measured_heights(results / "heights.csv")
    responses: list = []
    answers = {}
    for k, (pid, turned) in enumerate(VIEWS):
        p = view[pid]
        page = None
        for b in flat:
            roof = np.mean(b["footprint"], axis=0) + roof_shift(b, p["azimuth"], p["elevation"])
            centre = lonlat(roof)
            if page is None:
                page = open_page(browser, f"{base_url}/viewer/index.html#{pid}/{ZOOM}/{centre[1]:.7f}/{centre[0]:.7f}"
                                 + ("/up" if turned else ""), responses)
                bearing = bearing_of(page)[0]
                assert (abs(bearing) > 1) == (turned and p["elevation"] != 90), bearing
            else:
                page.evaluate(f"map.setView([{centre[1]}, {centre[0]}], {ZOOM}, {{animate: false}})")
            got = click_id(page, screen_px(roof, centre, bearing))
            page.wait_for_function(f"(document.querySelector('#object table') || {{}}).textContent"
                                   f"?.includes('{got} (')")
            name = page.text_content("#object .name")
            rows = page.text_content("#object table")
            shot(page, tmp_path, f"identify-{pid}{'-up' if turned else ''}-{b['id']}.png")
            answers[f"{pid}{'-up' if turned else ''}/{b['id']}"] = got
            assert got == ids[b["id"]], (pid, turned, b["id"], got)
            assert name.startswith(b["id"]), name
            if measured.get(b["id"]) is not None:
                assert f"{measured[b['id']]:.2f} m" in rows, rows
        road_id, road = open_road(truth, truth["buildings"], p["azimuth"], p["elevation"])
        at = lonlat(road)
        page.evaluate(f"map.setView([{at[1]}, {at[0]}], {ZOOM}, {{animate: false}})")   # the id tile is
        got = click_id(page, screen_px(road, at, bearing))                                 # fetched by the click
        answers[f"{pid}{'-up' if turned else ''}/{road_id}"] = got
        assert got in ground and got == objects[road_id], (pid, turned, road_id, got)
        if k == 0:          # the page's decoder against the writer's, beyond 256 ids a tile too (uint16)
            rng = np.random.default_rng(3)
            for n in (3, 300):
                tile = np.resize(rng.choice(2**32, n, replace=False).astype(np.uint32), (256, 256))
                raw = list(zlib.decompress(id_tiles.encode(tile)))
                decoded = page.evaluate("raw => Array.from(identify.decode(new Uint8Array(raw).buffer))", raw)
                assert np.array_equal(np.array(decoded, np.uint32).reshape(256, 256), tile), n
        page.close()
    print(json.dumps(answers))
    assert len(flat) == 2 and len(answers) == 3 * len(VIEWS)
    assert [r for r in responses if r[1] >= 400 and not r[0].endswith("favicon.ico")] == []


def test_a_click_on_a_roof_under_an_overlay_feature_still_identifies_the_building(browser, served, tmp_path):
    """The run's viewer written again with the demo's footprints as an overlay (polygons with properties,
    as the Delft example's BGT footprints): on two perspectives, turned and not, a click where the map shows a
    building's roof inside its footprint polygon answers the building's id, and the footprint's popup shows its
    properties too."""
    from matplotlib.path import Path as Polygon

    from pipeline25d.geometry.perspectives import Perspective
    from pipeline25d.publish.viewer import write_viewer

    base_url, workdir, results = served
    truth, ids, _ = run_ids(workdir, results)
    features = [{"type": "Feature", "properties": {"footprint": b["id"]},
                 "geometry": {"type": "Polygon", "coordinates": [b["footprint"] + b["footprint"][:1]]}}
                for b in truth["buildings"]]
    path = workdir / "overlays" / "footprints.geojson"
    path.parent.mkdir(exist_ok=True)
    path.write_text(json.dumps({"type": "FeatureCollection", "features": features}))
    write_viewer(results / "report" / "report.json", results / "viewer-footprints" / "index.html",
                 overlays=[{"path": str(path), "name": "footprints", "color": "#ffd400", "crs": "EPSG:25832"}],
                 ids=results)
    responses: list = []
    for pid, turned in (("az000_el90", False), ("az045_el45", False), ("az045_el45", True)):   # at 30° no roof
        a, e = Perspective.from_id(pid).azimuth, Perspective.from_id(pid).elevation  # of this city meets its footprint
        # a roof point inside its footprint polygon: halfway between the footprint's and the shown roof's centres
        # (on an oblique the footprint lies on the ground, the roof h·cot φ further), 1 m inside both
        b = next(b for b in sorted(truth["buildings"], key=lambda b: -b["eave_z"]) if b["roof"] == "flat"
                 and visible(truth, b, a, e, np.mean(b["footprint"], axis=0) + roof_shift(b, a, e) / 2) and all(
                     Polygon(np.asarray(b["footprint"]) + s * roof_shift(b, a, e)).contains_point(
                         np.mean(b["footprint"], axis=0) + roof_shift(b, a, e) / 2, radius=r)
                     for s in (0, 1) for r in (1.0, -1.0)))
        roof = np.mean(b["footprint"], axis=0) + roof_shift(b, a, e) / 2
        centre = lonlat(roof)
        page = open_page(browser, f"{base_url}/viewer-footprints/index.html"
                                  f"#{pid}/{ZOOM}/{centre[1]:.7f}/{centre[0]:.7f}"
                         + ("/up" if turned else ""), responses)
        page.wait_for_selector('#layers label.loaded[data-overlay="footprints"]')
        bearing = bearing_of(page)[0]
        got = click_id(page, screen_px(roof, centre, bearing))
        assert got == ids[b["id"]], (pid, turned, b["id"], got)
        page.wait_for_selector(".leaflet-popup-content", timeout=5000)
        assert f"footprint: {b['id']}" in page.text_content(".leaflet-popup-content")
        shot(page, tmp_path, f"identify-under-overlay-{pid}{'-up' if turned else ''}-{b['id']}.png")
        page.close()
    assert [r for r in responses if r[1] >= 400 and not r[0].endswith("favicon.ico")] == []
