"""The web viewer in headless Chromium (Debian's ``chromium``, driven by Playwright) over the small demo
run served by pipeline25d.publish.serve: tiles load with no 404, the URL hash carries the view and opens it again,
[ and ] switch perspective keeping place and zoom, the height tool measures a demo building within
1 px·gsd/cot φ of its truth, also on the map turned so the view direction points up (r), and the same
run with its pyramids as PMTiles archives loads its tiles by range requests. Screenshots go to the test's
tmp_path and to $PIPELINE25D_SHOTS (default /tmp/viewer-shots/)."""

from __future__ import annotations

import json
import math
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import roof_colour, serve, vertical_edge

from pipeline25d.core.crs import transform_points
from pipeline25d.stages.tiles.archive import pyramid_tiles

SHOTS = Path(os.environ.get("PIPELINE25D_SHOTS", "/tmp/viewer-shots"))
SIZE = {"width": 1200, "height": 800}
ZOOM = 19                       # ~0.2 m per screen pixel here, finer than the maps' 0.5 m gsd


@pytest.fixture(scope="module")
def pmtiles_served(small_run, tmp_path_factory):
    """The small run copied and run again with ``tms.pmtiles`` on, served: (base URL, workdir, results,
    the jobs that second run ran)."""
    from test_workflow import job_counts, snakemake

    workdir = tmp_path_factory.mktemp("pmtiles") / "run"
    shutil.copytree(small_run[0], workdir, symlinks=True)
    config = yaml.safe_load((workdir / "config.yaml").read_text())
    config["tms"]["pmtiles"] = True
    (workdir / "config.yaml").write_text(yaml.safe_dump(config))
    proc = snakemake(workdir)
    jobs = job_counts(proc.stdout + proc.stderr)
    for url, wd, results in serve(workdir, workdir / "results" / config["scene"]):
        yield url, wd, results, jobs


def lonlat(xy: np.ndarray) -> tuple[float, float]:
    ll = transform_points(np.array([[xy[0], xy[1], 0.0]]), "EPSG:25832", "EPSG:4326")[0]
    return float(ll[0]), float(ll[1])


def world_px(lon: float, lat: float, zoom: float) -> np.ndarray:
    """Web-mercator pixel position at ``zoom`` (256-px tiles), the standard XYZ formula."""
    n = 256 * 2.0 ** zoom
    lat_r = math.radians(lat)
    return np.array([(lon + 180) / 360 * n, (1 - math.asinh(math.tan(lat_r)) / math.pi) / 2 * n])


def screen_px(xy: np.ndarray, centre: tuple[float, float], bearing: float = 0.0, zoom: float = ZOOM) -> np.ndarray:
    """Where a scene point shows in the viewport of a view centred on ``centre`` (lon, lat) at ``zoom``, the
    map turned clockwise on screen by ``bearing`` degrees about the viewport's centre (Leaflet rounds its pixel
    origin: a shift under 0.5 px, the same for every point, so differences are exact)."""
    b = math.radians(bearing)
    turn = np.array([[math.cos(b), -math.sin(b)], [math.sin(b), math.cos(b)]])    # clockwise, y down
    offset = world_px(*lonlat(xy), zoom) - world_px(*centre, zoom)
    return turn @ offset + np.array([SIZE["width"], SIZE["height"]]) / 2


def parse_view(url: str) -> tuple[str, float, float, float]:
    """The view of a viewer URL's hash #<id>/<zoom>/<lat>/<lng>[/up], without the /up."""
    pid, zoom, lat, lng = url.split("#", 1)[1].removesuffix("/up").split("/")
    return pid, float(zoom), float(lat), float(lng)


def settle(page) -> None:
    """Wait until the network is idle and every tile shown has loaded and faded in."""
    page.wait_for_load_state("networkidle")
    page.wait_for_function("[...document.querySelectorAll('img.leaflet-tile')].every(t => "
                           "t.classList.contains('leaflet-tile-loaded') && getComputedStyle(t).opacity === '1')")


def open_page(browser, url: str, responses: list, failed: list | None = None):
    """A new page at ``url``, settled; its responses (url, status) and failed requests (urls) are recorded."""
    page = browser.new_page(viewport=SIZE)
    page.on("response", lambda r: responses.append((r.url, r.status)))
    if failed is not None:
        page.on("requestfailed", lambda r: failed.append(r.url))
    page.goto(url)
    settle(page)
    return page


def shot(page, tmp_path: Path, name: str) -> None:
    SHOTS.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(tmp_path / name))
    shutil.copyfile(tmp_path / name, SHOTS / name)


def tiles_of(responses: list, pid: str) -> list[int]:
    return [status for url, status in responses if f"/tms/{pid}/" in url]


def open_at_building(browser, base_url: str, workdir: Path, results: Path, pid: str, responses: list,
                     failed: list | None = None) -> tuple:
    """The viewer opened on ``pid`` at ZOOM centred on the demo's tallest flat-roofed building:
    (page, report, the report's perspectives by id, the building, the centre as lon, lat)."""
    report = json.loads((results / "report" / "report.json").read_text())
    truth = json.loads((workdir / "resources" / "demo" / "truth.json").read_text())
    building = max((b for b in truth["buildings"] if b["roof"] == "flat"), key=lambda b: b["eave_z"])
    centre = lonlat(np.mean(building["footprint"], axis=0))
    page = open_page(browser, f"{base_url}/viewer/index.html#{pid}/{ZOOM}/{centre[1]:.7f}/{centre[0]:.7f}",
                     responses, failed)
    return page, report, {p["id"]: p for p in report["perspectives"]}, building, centre


def measure_edge(page, results: Path, building: dict, p: dict, gsd: float, centre: tuple[float, float],
                 bearing: float = 0.0) -> tuple[float, float, float]:
    """Check that the roof shows where it should and measure the building's camera-side vertical edge
    with the page's height tool, clicking where the edge's base and top show on the (turned) map:
    (measured, true height, tolerance 1 px · gsd / cot φ). The tool stays on, showing the measurement."""
    base, top, height = vertical_edge(building, p["azimuth"], p["elevation"])
    roof_centre = np.mean(building["footprint"], axis=0) + (top - base)
    assert_shows_roof(page, results, building, screen_px(top, centre, bearing), screen_px(roof_centre, centre, bearing))
    page.click("#measure-btn")
    for xy in (base, top):
        page.mouse.click(*screen_px(xy, centre, bearing))
    measured = float(page.locator("#measure").get_attribute("data-height"))
    return measured, height, gsd * math.tan(math.radians(p["elevation"]))


def drag_left(page, px: int = 100) -> np.ndarray:
    """Drag the map ``px`` screen pixels to the left and wait for the hash to follow: how far the view's centre
    moved, in north-up world pixels at its zoom. Inertia is switched off first: its glide depends on the
    timing of the mouse events, so on the machine's load (seconds long on a busy machine)."""
    before = page.url
    page.evaluate("map.options.inertia = false")
    page.mouse.move(300, 600)
    page.mouse.down()
    page.mouse.move(300 - px, 600, steps=5)
    page.mouse.up()
    page.wait_for_function(f"location.hash !== {json.dumps(before[before.index('#'):])}", timeout=5000)
    settle(page)
    (_, zoom, lat0, lng0), (_, _, lat1, lng1) = parse_view(before), parse_view(page.url)
    return world_px(lng1, lat1, zoom) - world_px(lng0, lat0, zoom)


def bearing_of(page) -> tuple[float, float]:
    """The map's bearing (degrees) as leaflet-rotate reports it, and the rotation of the pane that holds the
    tiles as the browser computed its CSS transform, in [0, 360)."""
    bearing = page.evaluate("map.getBearing()")
    a, b = page.evaluate("(() => { const m = new DOMMatrix(getComputedStyle(map.getPane('rotatePane')).transform);"
                         " return [m.a, m.b]; })()")
    return bearing, math.degrees(math.atan2(b, a)) % 360


def scale_bar(page) -> tuple[str, float]:
    return page.evaluate("(() => { const s = document.querySelector('.leaflet-control-scale-line');"
                         " return [s.textContent, s.getBoundingClientRect().width]; })()")


def assert_shows_roof(page, results: Path, building: dict, corner: np.ndarray, inside: np.ndarray) -> None:
    """The page shows the building's roof (its colour on the nadir map) 12 px from the top corner toward
    the roof's centre: the tiles lie where the measuring clicks go."""
    import io

    from PIL import Image

    roof = roof_colour(results, building)
    at = np.round(corner + 12 * (inside - corner) / np.linalg.norm(inside - corner)).astype(int)
    shown = np.asarray(Image.open(io.BytesIO(page.screenshot())).convert("RGB"))[at[1], at[0]].astype(float)
    assert np.abs(shown - roof).max() <= 20, (building["id"], shown, roof)


def test_overview_loads_its_tiles_and_the_hash_follows_the_view(browser, served, tmp_path):
    base_url, _, _ = served
    responses: list = []
    page = open_page(browser, f"{base_url}/viewer/index.html", responses)
    pid, zoom = parse_view(page.url)[:2]
    assert pid == "az045_el45"                     # the first oblique perspective by azimuth
    assert page.locator(".leaflet-control-scale").is_visible()
    shot(page, tmp_path, "overview.png")
    moved = drag_left(page)                        # the view moves 100 px east
    assert parse_view(page.url)[:2] == (pid, zoom) and np.abs(moved - [100, 0]).max() < 1.5, moved
    assert [r for r in responses if r[1] >= 400] == []
    assert tiles_of(responses, pid) and set(tiles_of(responses, pid)) == {200}
    # the page asks only for tiles its pyramid holds (empty ones are not cut)
    _, _, results = served
    held = [{"z": int(t.parent.parent.name), "x": int(t.parent.name), "y": int(t.stem)}
            for t in (results / "tms" / pid).glob("*/*/*.webp")]
    absent = [{**c, "y": c["y"] + 5} for c in held] + [{**c, "x": c["x"] - 5} for c in held]
    has = "([pid, cs]) => cs.map(c => hasTile(byId[pid], c))"
    assert held and all(page.evaluate(has, [pid, held])) and not any(page.evaluate(has, [pid, absent]))
    page.close()


def test_switching_keeps_the_view_and_heights_are_measured_within_a_pixel(browser, served, tmp_path):
    results = served[2]
    responses: list = []
    page, report, view, building, centre = open_at_building(browser, *served, "az200_el30", responses)
    assert page.locator('input[value="az200_el30"]').is_checked()
    results_m = {}
    for key, pid in (("", "az200_el30"), ("]", "az045_el45")):   # ] after the last azimuth wraps to the first
        if key:
            page.keyboard.press(key)
            settle(page)
        got_pid, zoom, lat, lng = parse_view(page.url)
        assert (got_pid, zoom) == (pid, ZOOM)
        assert (lat, lng) == pytest.approx((centre[1], centre[0]), abs=2e-7)   # same place, same zoom
        measured, height, tolerance = measure_edge(page, results, building, view[pid], report["gsd"], centre)
        results_m[pid] = (measured, height, tolerance)
        shot(page, tmp_path, f"measure-{pid}.png")
        page.click("#measure-btn")                                               # tool off
        assert abs(measured - height) <= tolerance, (pid, building["id"], measured, height, tolerance)
        assert tiles_of(responses, pid) and set(tiles_of(responses, pid)) == {200}
    print({pid: tuple(round(v, 3) for v in r) for pid, r in results_m.items()})
    assert [r for r in responses if r[1] >= 400] == []
    page.keyboard.press("[")
    assert parse_view(page.url)[0] == "az200_el30"
    page.close()


def test_view_up_turns_the_view_direction_up_the_screen_and_heights_are_measured_on_the_turned_map(
        browser, served, tmp_path):
    """r turns the map by −θ (the tile pane's CSS rotation and leaflet-rotate's bearing agree), the hash keeps
    it, the scale bar is unchanged, the roof shows where the turned map puts it, the building's vertical edge
    runs straight up the screen and the height tool measures it within a pixel, for two azimuths."""
    results = served[2]
    responses: list = []
    page, report, view, building, centre = open_at_building(browser, *served, "az200_el30", responses)
    assert bearing_of(page) == (0, 0)
    north_up_scale = scale_bar(page)
    results_m = {}
    for key, pid in (("r", "az200_el30"), ("]", "az045_el45")):      # turn; then the next azimuth, still turned
        page.keyboard.press(key)
        settle(page)
        assert page.url.endswith("/up") and parse_view(page.url)[:2] == (pid, ZOOM)
        assert parse_view(page.url)[2:] == pytest.approx((centre[1], centre[0]), abs=2e-7)   # turned about the centre
        p = view[pid]
        bearing, css = bearing_of(page)
        base, top, _ = vertical_edge(building, p["azimuth"], p["elevation"])
        lean = screen_px(top, centre) - screen_px(base, centre)                  # on the north-up map
        along = math.degrees(math.atan2(lean[0], -lean[1]))     # its compass angle: θ plus the scene CRS's
        assert 1 < abs((along - p["azimuth"] + 180) % 360 - 180) < 3   # meridian convergence (~2° here, UTM 32)
        assert bearing == pytest.approx(-along % 360, abs=0.02) and css == pytest.approx(bearing, abs=1e-4)
        assert page.locator("#rotate-btn.on").count() == 1
        text, width = scale_bar(page)                    # a turn keeps lengths: the same bar
        assert text == north_up_scale[0] and width == pytest.approx(north_up_scale[1], abs=1)
        lean = screen_px(top, centre, bearing) - screen_px(base, centre, bearing)
        assert abs(lean[0]) < 0.5 and lean[1] < -20      # buildings lean straight up the screen
        measured, height, tolerance = measure_edge(page, results, building, p, report["gsd"], centre, bearing)
        results_m[pid] = (measured, height, tolerance)
        shot(page, tmp_path, f"up-{pid}.png")
        page.click("#measure-btn")
        assert abs(measured - height) <= tolerance, (pid, building["id"], measured, height, tolerance)
        assert tiles_of(responses, pid) and set(tiles_of(responses, pid)) == {200}
    print({pid: tuple(round(v, 3) for v in r) for pid, r in results_m.items()})
    assert [r for r in responses if r[1] >= 400] == []
    moved = drag_left(page)                      # on the turned map: the view moves along its screen x axis
    b = math.radians(bearing)
    expect = np.array([[math.cos(b), math.sin(b)], [-math.sin(b), math.cos(b)]]) @ [100, 0]   # screen right, unturned
    assert page.url.endswith("/up") and np.abs(moved - expect).max() < 1.5, (moved, expect)
    turned_url = page.url
    page.keyboard.press("r")                             # back to north up
    settle(page)
    assert bearing_of(page) == (0, 0) and not page.url.endswith("/up")
    assert scale_bar(page) == pytest.approx(north_up_scale)
    page.close()
    page = open_page(browser, turned_url, responses)     # a link to the turned view opens turned
    assert bearing_of(page)[0] == pytest.approx(bearing, abs=1e-9) and page.url == turned_url
    assert [r for r in responses if r[1] >= 400] == []
    page.close()


def test_pmtiles_archives_hold_the_pyramids_and_the_viewer_reads_them_by_range_requests(
        browser, pmtiles_served, tmp_path):
    """Switching tms.pmtiles on for a finished run adds the archives and a new viewer (nothing else re-runs);
    every archive holds exactly its XYZ pyramid's tiles, byte for byte (read back with the pmtiles package's
    reader), and the page fetches its tiles from the archive by range requests (206, no failure, no XYZ
    tile asked), shows the roof where it is and measures the building, north up and turned."""
    from pmtiles.reader import MmapSource, Reader, all_tiles

    base_url, workdir, results, jobs = pmtiles_served
    report = json.loads((results / "report" / "report.json").read_text())
    view = {p["id"]: p for p in report["perspectives"]}
    assert {k: v for k, v in jobs.items() if k not in ("report", "total")} == {"pmtiles": len(view), "viewer": 1,
                                                                                "all": 1}
    for pid in view:
        files = pyramid_tiles(results / "tms" / pid)
        with open(results / "pmtiles" / f"{pid}.pmtiles", "rb") as f:
            get = MmapSource(f)
            stored = {zxy: bytes(data) for zxy, data in all_tiles(get)}
            assert stored.keys() == files.keys() and len(stored) >= 5
            assert all(stored[zxy] == path.read_bytes() for zxy, path in files.items())
            assert all(bytes(Reader(get).get(*zxy)) == stored[zxy] for zxy in list(files)[::7])   # by look-up too
    responses: list = []
    failed: list = []
    page, _, _, building, centre = open_at_building(browser, base_url, workdir, results, "az045_el45", responses,
                                                    failed)
    assert "PMTiles" in page.locator("#status").text_content()
    for turned in (False, True):
        if turned:
            page.keyboard.press("r")
            settle(page)
        bearing = bearing_of(page)[0]
        measured, height, tolerance = measure_edge(page, results, building, view["az045_el45"], report["gsd"],
                                                   centre, bearing)
        shot(page, tmp_path, f"pmtiles-az045_el45{'-up' if turned else ''}.png")
        page.click("#measure-btn")
        assert abs(measured - height) <= tolerance, (turned, measured, height, tolerance)
    archive = [status for url, status in responses if url.endswith("/pmtiles/az045_el45.pmtiles")]
    print({"range requests": len(archive), "measured": round(measured, 3), "true": round(height, 3)})
    assert len(archive) >= 2 and set(archive) == {206}           # the header, then tiles, each a range
    assert tiles_of(responses, "az045_el45") == [] and failed == []
    assert [r for r in responses if r[1] >= 400] == []
    page.close()


def test_the_html_report_opens_in_chromium_with_every_picture_and_nothing_fetched(browser, served, tmp_path):
    """report.html, served beside report.md: every picture (a thumbnail and a residual plot per map, the heights
    scatter) decodes in the browser, and the page asks for nothing but itself (its pictures are embedded)."""
    base_url, _, results = served
    report = json.loads((results / "report" / "report.json").read_text())
    requests: list = []
    page = browser.new_page(viewport=SIZE)
    page.on("request", lambda r: requests.append(r.url))
    page.goto(f"{base_url}/report/report.html")
    page.wait_for_load_state("networkidle")
    images = page.evaluate("[...document.images].map(i => [i.alt, i.complete && i.naturalWidth > 0])")
    pids = [p["id"] for p in report["perspectives"]]
    assert sorted(alt for alt, _ in images) == sorted(
        [f"map {pid}" for pid in pids] + [f"check-point residuals of {pid}" for pid in pids]
        + ["measured heights against their reference"])
    assert all(ok for _, ok in images), images
    assert [u for u in requests if not u.startswith("data:")] == [f"{base_url}/report/report.html"]
    SHOTS.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(tmp_path / "report.png"), full_page=True)
    shutil.copyfile(tmp_path / "report.png", SHOTS / "report.png")
    page.close()


OVERLAY_ZOOM = 19                  # ~0.2 m per screen pixel: Leaflet snaps vector vertices to whole pixels
MAGENTA = "#ff00ff"


@pytest.fixture(scope="module")
def overlay_viewer(served):
    """The small run's viewer written again (results/viewer-overlay/) with the demo's road centrelines from
    truth.json as a config overlay (GeoJSON in the scene CRS, EPSG:25832) and one point of interest: the
    tallest flat-roofed building's camera-side roof corner for az045_el45, given as its ground corner with a
    "height" property (the roof's height above the terrain there). (base URL, workdir, results, building)."""
    from pipeline25d.publish.viewer import write_viewer

    base_url, workdir, results = served
    truth = json.loads((workdir / "resources" / "demo" / "truth.json").read_text())
    building = max((b for b in truth["buildings"] if b["roof"] == "flat"), key=lambda b: b["eave_z"])
    base, _, height = vertical_edge(building, 45, 45)
    features = [{"type": "Feature", "properties": {"id": r["id"]},
                 "geometry": {"type": "LineString", "coordinates": r["centerline"]}} for r in truth["roads"]]
    features.append({"type": "Feature", "properties": {"name": "roof corner", "height": height},
                     "geometry": {"type": "Point", "coordinates": base.tolist()}})
    path = workdir / "overlays" / "streets.geojson"
    path.parent.mkdir(exist_ok=True)
    path.write_text(json.dumps({"type": "FeatureCollection", "features": features}))
    write_viewer(results / "report" / "report.json", results / "viewer-overlay" / "index.html",
                 overlays=[{"path": str(path), "name": "streets", "color": MAGENTA, "crs": "EPSG:25832"}])
    return base_url, workdir, results, building


def sample(rgb: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """(n, 3) colours of a screenshot at screen points ``pts`` (n, 2), bilinear."""
    from scipy.ndimage import map_coordinates

    return np.stack([map_coordinates(rgb[..., k].astype(float), [pts[:, 1], pts[:, 0]], order=1) for k in range(3)], 1)


def road_edges(col: np.ndarray, road: np.ndarray, grass: np.ndarray) -> tuple[float, float]:
    """Across a road, sampled as colours ``col`` (n, 3): the fractional sample indices of the road's two edges,
    where the brightness passes half way from the road's to the grass's (linear between samples); NaN where
    the run of road around the middle does not end in grass 0.5-1.5 m out on both sides (20 samples a metre)."""
    luma = np.array([0.299, 0.587, 0.114])      # brightness: WEBP tiles keep it at full resolution, colour at half
    s = (col - road) @ luma / ((grass - road) @ luma)                      # 0 on road, 1 on grass
    mid = len(s) // 2
    if s[mid] > 0.5:
        return math.nan, math.nan
    lo = mid
    while lo > 0 and s[lo - 1] <= 0.5:
        lo -= 1
    hi = mid
    while hi < len(s) - 1 and s[hi + 1] <= 0.5:
        hi += 1
    if lo < 30 or hi > len(s) - 31 or min(np.median(s[lo - 30:lo - 10]), np.median(s[hi + 11:hi + 31])) < 0.8:
        return math.nan, math.nan                  # occluded, or a crossing
    return lo - (0.5 - s[lo]) / (s[lo - 1] - s[lo]), hi + (0.5 - s[hi]) / (s[hi + 1] - s[hi])


def line_centre(col: np.ndarray) -> float:
    """The fractional sample index of the magenta line's centre across a profile (weighted by magenta-ness)."""
    w = np.clip(np.minimum(col[:, 0], col[:, 2]) - col[:, 1] - 60, 0, None)
    return float((w * np.arange(len(w))).sum() / w.sum()) if w.sum() > 0 else math.nan


def road_offsets(page, truth: dict, centre: tuple[float, float], bearing: float, gsd: float) -> list[tuple]:
    """Per road station (every 5 m, away from crossings and district ends) where the road shows with grass on
    both sides: (road id, the overlay's drawn centreline minus the road's rendered centre, the drawn centreline
    minus the true centreline where screen_px puts it), across the road, in map pixels (gsd). The road is
    measured with the overlay switched off, the line with it on, in the same view; the
    road's and the grass's colours are the medians over the stations at the centreline and 7 m off it."""
    import io

    from PIL import Image

    def grab():
        return np.asarray(Image.open(io.BytesIO(page.screenshot())).convert("RGB"))

    toggle = page.locator('#layers label[data-overlay="streets"] input')
    toggle.uncheck()
    bare = grab()
    toggle.check()
    lined = grab()
    step = 0.05                                          # m between profile samples
    t = np.arange(-9, 9 + step / 2, step)
    cuts = [(r["kind"], r["centerline"][0][1 if r["kind"] == "ew" else 0]) for r in truth["roads"]]
    profiles = []
    for road in truth["roads"]:
        a, b = np.array(road["centerline"], dtype=float)
        length = np.linalg.norm(b - a)
        along, normal = (b - a) / length, np.array([-(b - a)[1], (b - a)[0]]) / length
        axis = 1 if road["kind"] == "ns" else 0          # the coordinate that runs along the road
        for s in np.arange(12, length - 12, 5.0):
            station = a + s * along
            if any(k != road["kind"] and abs(station[axis] - c) < 14 for k, c in cuts):
                continue
            pts = np.array([screen_px(station + ti * normal, centre, bearing, OVERLAY_ZOOM) for ti in t])
            if (pts >= 2).all() and (pts < np.array([SIZE["width"], SIZE["height"]]) - 2).all():
                profiles.append((road["id"], pts))
    bare_cols = [sample(bare, pts) for _, pts in profiles]
    road = np.median([c[len(t) // 2] for c in bare_cols], axis=0)
    grass = np.median([c[i] for c in bare_cols for i in (40, len(t) - 41)], axis=0)
    out = []
    for (road_id, pts), col in zip(profiles, bare_cols):
        left, right = road_edges(col, road, grass)
        if abs((right - left) * step - 8.0) < 0.5:       # both edges seen (8 m apart), nothing over the road
            line = line_centre(sample(lined, pts))
            out.append((road_id, (line - (left + right) / 2) * step / gsd, (line - len(t) // 2) * step / gsd))
    return out


def test_a_street_overlay_lies_on_the_roads_of_every_perspective_turned_or_not(browser, overlay_viewer, tmp_path):
    """The demo's road centrelines, given as a config overlay in the scene CRS, are drawn on every perspective
    (north up and view direction up) within 1 map pixel of the road's centre as the map shows it, at every
    station where both edges show 8 m apart (measured across the road in the screenshot; the web tiles lie on
    their own pixels, stages.tiles.web.tile_grid, where gdal2tiles' grid moved a tile by up to a pixel);
    a point given with a height is drawn where that perspective
    shows that height (h·cot φ along the view), within half a screen pixel."""
    base_url, workdir, results, building = overlay_viewer
    truth = json.loads((workdir / "resources" / "demo" / "truth.json").read_text())
    report = json.loads((results / "report" / "report.json").read_text())
    view = {p["id"]: p for p in report["perspectives"]}
    b = np.array([p["lonlat_bounds"] for p in report["perspectives"]])
    centre = ((b[:, 0].min() + b[:, 2].max()) / 2, (b[:, 1].min() + b[:, 3].max()) / 2)
    assert (results / "viewer-overlay" / "overlays" / "streets.geojson").is_file()
    offsets = {}
    responses: list = []
    for pid, turned in (("az000_el90", False), ("az045_el45", False), ("az045_el45", True), ("az200_el30", False),
                        ("az200_el30", True)):
        url = (f"{base_url}/viewer-overlay/index.html#{pid}/{OVERLAY_ZOOM}/{centre[1]:.7f}/{centre[0]:.7f}"
               + ("/up" if turned else ""))
        page = open_page(browser, url, responses)
        page.wait_for_selector('#layers label.loaded[data-overlay="streets"]')
        bearing = bearing_of(page)[0]
        name = f"{pid}{'-up' if turned else ''}"
        off = road_offsets(page, truth, centre, bearing, report["gsd"])
        offsets[name] = off
        shot(page, tmp_path, f"overlay-{name}.png")
        if pid == "az045_el45":                          # the point with a height: at the roof corner
            p = view[pid]
            _, top, _ = vertical_edge(building, p["azimuth"], p["elevation"])
            at = lonlat(top)                             # the view centred where the roof corner shows
            page.evaluate(f"map.setView([{at[1]}, {at[0]}], {OVERLAY_ZOOM}, {{animate: false}})")
            settle(page)
            box = page.evaluate("(() => { const r = [...document.querySelectorAll('path.leaflet-interactive')]"
                                ".filter(e => e.getAttribute('fill') === '#ff00ff')[0].getBoundingClientRect();"
                                " return [r.x + r.width / 2, r.y + r.height / 2]; })()")
            assert np.abs(np.array(box) - np.array([SIZE["width"], SIZE["height"]]) / 2).max() <= 1.0, (box, top)
        page.close()
    summary = {}
    for name, rows in offsets.items():
        to_road = np.array([r[1] for r in rows])
        per_road = {rid: float(np.mean([r[1] for r in rows if r[0] == rid])) for rid in {r[0] for r in rows}}
        summary[name] = {"stations": len(rows), "median_abs_px": round(float(np.median(np.abs(to_road))), 2),
                         "max_abs_px": round(float(np.abs(to_road).max()), 2),
                         "per_road_mean_px": {k: round(v, 2) for k, v in sorted(per_road.items())},
                         "line_vs_truth_max_px": round(max(abs(r[2]) for r in rows), 2)}
    print(json.dumps(summary))
    for name, s in summary.items():
        assert s["stations"] >= 3, (name, s)                  # roads seen with grass on both sides
        assert s["line_vs_truth_max_px"] <= 0.5, (name, s)      # drawn where the centreline is
        assert s["max_abs_px"] <= 1.0, (name, s)                # and on the road as the web tiles show it
    assert [r for r in responses if r[1] >= 400 and not r[0].endswith("favicon.ico")] == []


def test_an_overlay_given_in_the_address_is_drawn_and_no_basemap_is_fetched_unless_configured(
        browser, overlay_viewer, tmp_path):
    """?overlay=<url> adds a layer to the published viewer (one without config overlays) and draws it; the page
    asks nothing of any host but its own (no basemap unless the config names one)."""
    base_url, _, results, _ = overlay_viewer
    requests: list = []
    page = browser.new_page(viewport=SIZE)
    page.on("request", lambda r: requests.append(r.url))
    page.goto(f"{base_url}/viewer/index.html?overlay=../viewer-overlay/overlays/streets.geojson#az200_el30/17/"
              f"48.1315/11.5685")
    page.wait_for_selector('#layers label.loaded[data-overlay="streets.geojson"]')
    settle(page)
    drawn = page.evaluate("document.querySelectorAll('path.leaflet-interactive').length")
    roads = len(json.loads((results / "viewer-overlay" / "overlays" / "streets.geojson").read_text())["features"])
    assert drawn == roads                                # every road and the point
    assert all(u.startswith(base_url) or u.startswith("data:") for u in requests), requests
    shot(page, tmp_path, "overlay-url-az200_el30.png")
    page.close()
