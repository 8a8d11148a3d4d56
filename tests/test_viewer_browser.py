"""The web viewer in headless Chromium (Debian's ``chromium``, driven by Playwright) over the small demo
run served by http.server: tiles load with no 404, the URL hash carries the view and opens it again,
[ and ] switch perspective keeping place and zoom, and the height tool measures a demo building within
1 px·gsd/cot φ of its truth. Screenshots go to the test's tmp_path and to /tmp/viewer-shots/."""

from __future__ import annotations

import functools
import json
import math
import shutil
import threading
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import numpy as np
import pytest

from conftest import roof_colour, vertical_edge
from pipeline25d.crs import transform_points

CHROMIUM = shutil.which("chromium")
SHOTS = Path("/tmp/viewer-shots")
SIZE = {"width": 1200, "height": 800}
ZOOM = 19                       # ~0.2 m per screen pixel here, finer than the maps' 0.5 m gsd


class QuietHandler(SimpleHTTPRequestHandler):
    def log_message(self, *args) -> None:
        pass


@pytest.fixture(scope="module")
def served(small_run):
    """(base URL, workdir, results) with results/<scene>/ served on 127.0.0.1."""
    if CHROMIUM is None:
        pytest.skip("no chromium on PATH: apt-get install chromium (make sysdeps does)")
    pytest.importorskip("playwright.sync_api", reason="the playwright package is not installed (requirements.txt)")
    workdir, results = small_run
    server = ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(QuietHandler, directory=str(results)))
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield f"http://127.0.0.1:{server.server_address[1]}", workdir, results
    server.shutdown()
    thread.join()


@pytest.fixture(scope="module")
def browser(served):
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        chromium = pw.chromium.launch(executable_path=CHROMIUM)
        yield chromium
        chromium.close()


def lonlat(xy: np.ndarray) -> tuple[float, float]:
    ll = transform_points(np.array([[xy[0], xy[1], 0.0]]), "EPSG:25832", "EPSG:4326")[0]
    return float(ll[0]), float(ll[1])


def world_px(lon: float, lat: float, zoom: float) -> np.ndarray:
    """Web-mercator pixel position at ``zoom`` (256-px tiles), the standard XYZ formula."""
    n = 256 * 2.0 ** zoom
    lat_r = math.radians(lat)
    return np.array([(lon + 180) / 360 * n, (1 - math.asinh(math.tan(lat_r)) / math.pi) / 2 * n])


def screen_px(xy: np.ndarray, centre: tuple[float, float]) -> np.ndarray:
    """Where a scene point shows in the viewport of a view centred on ``centre`` (lon, lat) at ZOOM (Leaflet
    rounds its pixel origin: a shift under 0.5 px, the same for every point, so differences are exact)."""
    return world_px(*lonlat(xy), ZOOM) - world_px(*centre, ZOOM) + np.array([SIZE["width"], SIZE["height"]]) / 2


def parse_view(url: str) -> tuple[str, float, float, float]:
    pid, zoom, lat, lng = url.split("#", 1)[1].split("/")
    return pid, float(zoom), float(lat), float(lng)


def settle(page) -> None:
    """Wait until the network is idle and every tile shown has loaded and faded in."""
    page.wait_for_load_state("networkidle")
    page.wait_for_function("[...document.querySelectorAll('img.leaflet-tile')].every(t => "
                           "t.classList.contains('leaflet-tile-loaded') && getComputedStyle(t).opacity === '1')")


def open_page(browser, url: str, responses: list):
    page = browser.new_page(viewport=SIZE)
    page.on("response", lambda r: responses.append((r.url, r.status)))
    page.goto(url)
    settle(page)
    return page


def shot(page, tmp_path: Path, name: str) -> None:
    SHOTS.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(tmp_path / name))
    shutil.copyfile(tmp_path / name, SHOTS / name)


def tiles_of(responses: list, pid: str) -> list[int]:
    return [status for url, status in responses if f"/tms/{pid}/" in url]


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
    pid, zoom, lat, lng = parse_view(page.url)
    assert pid == "az045_el45"                     # the first oblique perspective by azimuth
    assert page.locator(".leaflet-control-scale").is_visible()
    shot(page, tmp_path, "overview.png")
    page.mouse.move(300, 600)
    page.mouse.down()
    page.mouse.move(200, 600, steps=5)             # drag the map 100 px to the left: the view moves east
    page.mouse.up()
    page.wait_for_function(f"location.hash !== {json.dumps(page.url[page.url.index('#'):])}", timeout=5000)
    settle(page)
    pid2, zoom2, lat2, lng2 = parse_view(page.url)
    assert (pid2, zoom2) == (pid, zoom) and lat2 == pytest.approx(lat, abs=5e-6) and lng2 > lng + 1e-4  # 1 px ~ 6e-6°
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
    base_url, workdir, results = served
    truth = json.loads((workdir / "resources" / "demo" / "truth.json").read_text())
    report = json.loads((results / "report" / "report.json").read_text())
    view = {p["id"]: p for p in report["perspectives"]}
    building = max((b for b in truth["buildings"] if b["roof"] == "flat"), key=lambda b: b["eave_z"])
    centre = lonlat(np.mean(building["footprint"], axis=0))
    responses: list = []
    page = open_page(browser, f"{base_url}/viewer/index.html#az200_el30/{ZOOM}/{centre[1]:.7f}/{centre[0]:.7f}",
                     responses)
    assert page.locator('input[value="az200_el30"]').is_checked()
    results_m = {}
    for key, pid in (("", "az200_el30"), ("]", "az045_el45")):   # ] after the last azimuth wraps to the first
        if key:
            page.keyboard.press(key)
            settle(page)
        got_pid, zoom, lat, lng = parse_view(page.url)
        assert (got_pid, zoom) == (pid, ZOOM)
        assert (lat, lng) == pytest.approx((centre[1], centre[0]), abs=2e-7)   # same place, same zoom
        p = view[pid]
        base, top, height = vertical_edge(building, p["azimuth"], p["elevation"])
        roof_centre = np.mean(building["footprint"], axis=0) + (top - base)
        assert_shows_roof(page, results, building, screen_px(top, centre), screen_px(roof_centre, centre))
        page.click("#measure-btn")
        for xy in (base, top):
            page.mouse.click(*screen_px(xy, centre))
        measured = float(page.locator("#measure").get_attribute("data-height"))
        tolerance = report["gsd"] * math.tan(math.radians(p["elevation"]))       # 1 px · gsd / cot φ
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
