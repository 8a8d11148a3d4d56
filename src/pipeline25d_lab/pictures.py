"""The README's pictures, made from a run's own output so they stay current (``make pictures``).

``docs/images/maps.jpg``: the same window of the demo city's nadir map and of one oblique map
side by side (both north up, as the maps are), read from the COGs at the pixel size that fits
the picture. ``docs/images/viewer.jpg``: the web viewer in headless Chromium (Debian's
``chromium`` driven by Playwright) over the run served on 127.0.0.1, turned to that view.
``docs/images/demo-streets.jpg``: the viewer on the oblique map with the config's overlays (the
demo's streets) drawn, the tallest building with a measured height clicked where the map shows
it (found on the id map) and identified. ``docs/images/report.jpg``: the top of the run's HTML report.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import threading
from pathlib import Path

import numpy as np
from affine import Affine
from PIL import Image, ImageDraw

from pipeline25d.core.grid import Grid
from pipeline25d.core.raster import gdal
from pipeline25d.publish.serve import make_server

PANEL_PX = 760          # each map panel's width and height in the picture
WINDOW_M = 300.0        # the map window shown, metres a side (the demo's blocks are 240 m)
LABEL_PX = 28
VIEWPORT = (1280, 720)  # the viewer's screenshots


def map_window(cog: Path, centre: tuple[float, float], size_m: float, out_px: int) -> Image.Image:
    """``size_m`` metres a side of a map around ``centre``, resampled (average) to ``out_px`` pixels,
    on white where the map holds no data."""
    x, y = centre
    ds = gdal().Warp("", str(cog), format="MEM", outputBounds=(x - size_m / 2, y - size_m / 2, x + size_m / 2,
                                                                y + size_m / 2),
                     width=out_px, height=out_px, resampleAlg="average")
    rgba = np.moveaxis(ds.ReadAsArray(), 0, -1).astype(np.float64)
    alpha = rgba[..., 3:4] / 255.0
    rgb = rgba[..., :3] * alpha + 255.0 * (1.0 - alpha)
    return Image.fromarray(np.round(rgb).astype(np.uint8), "RGB")


def fullest_window(cog: Path, size_m: float, step_m: float = 4.0) -> tuple[float, float]:
    """The centre of the ``size_m`` square of a map that holds the most data (a sparse city's
    empty land is no picture), searched on a ``step_m`` grid."""
    from scipy.ndimage import uniform_filter

    ds = gdal().Open(str(cog))
    t = Grid.of_dataset(ds).transform
    w, h = max(1, round(ds.RasterXSize * t.a / step_m)), max(1, round(ds.RasterYSize * -t.e / step_m))
    small = gdal().Translate("", ds, format="MEM", width=w, height=h, resampleAlg="average")
    alpha = small.GetRasterBand(4).ReadAsArray().astype(np.float64)
    k = max(1, round(size_m / step_m))
    share = uniform_filter(alpha, size=k, mode="constant")
    row, col = np.unravel_index(np.argmax(share), share.shape)
    sx, sy = ds.RasterXSize * t.a / w, ds.RasterYSize * -t.e / h
    return Grid(Affine(sx, 0.0, t.c, 0.0, -sy, t.f), w, h).xy(col + 0.5, row + 0.5)      # the search grid's cell


def maps_picture(results: Path, oblique: str, out: Path) -> None:
    """The nadir map and ``oblique``'s, the same window, side by side with their names."""
    nadir = results / "maps" / "az000_el90.tif"
    centre = fullest_window(nadir, WINDOW_M)
    panels = [(map_window(nadir, centre, WINDOW_M, PANEL_PX), "nadir (az000_el90)"),
              (map_window(results / "maps" / f"{oblique}.tif", centre, WINDOW_M, PANEL_PX),
               f"oblique ({oblique}), the same window")]
    gap = 12
    sheet = Image.new("RGB", (2 * PANEL_PX + gap, PANEL_PX + LABEL_PX), "white")
    draw = ImageDraw.Draw(sheet)
    for k, (panel, label) in enumerate(panels):
        sheet.paste(panel, (k * (PANEL_PX + gap), LABEL_PX))
        draw.text((k * (PANEL_PX + gap) + 4, 6), label, fill="black")
    out.parent.mkdir(parents=True, exist_ok=True)
    sheet.save(out, quality=82, optimize=True)


def viewer_picture(results: Path, view_hash: str, out: Path, act=None) -> None:
    """The viewer over ``results`` served on 127.0.0.1, opened at ``view_hash``, as a screenshot;
    ``act(page)``, when given, runs on the settled page first (a click ...)."""
    from playwright.sync_api import sync_playwright

    chromium = shutil.which("chromium")
    if chromium is None:
        raise SystemExit("no chromium on PATH: apt-get install chromium (make sysdeps does)")
    server = make_server(results, port=0)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=chromium)
            page = browser.new_page(viewport={"width": VIEWPORT[0], "height": VIEWPORT[1]})
            page.goto(f"http://127.0.0.1:{server.server_address[1]}/viewer/index.html{view_hash}")
            page.wait_for_load_state("networkidle")
            page.wait_for_timeout(500)
            if act is not None:
                act(page)
                page.wait_for_load_state("networkidle")
                page.wait_for_timeout(500)
            out.parent.mkdir(parents=True, exist_ok=True)
            png = out.with_suffix(".png")
            page.screenshot(path=str(png))
            browser.close()
        Image.open(png).convert("RGB").save(out, quality=82, optimize=True)
        png.unlink()
    finally:
        server.shutdown()
        server.server_close()


def report_picture(results: Path, out: Path) -> None:
    """The run's report.html (opened from disk; it fetches nothing) in headless Chromium, 1280 px wide:
    its top (the check-point table and the first map with its residual arrows) above its heights section
    (the scatter), cut from one full-page screenshot at the page's own headings."""
    from playwright.sync_api import sync_playwright

    chromium = shutil.which("chromium")
    if chromium is None:
        raise SystemExit("no chromium on PATH: apt-get install chromium (make sysdeps does)")
    png = out.with_suffix(".png")
    out.parent.mkdir(parents=True, exist_ok=True)
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=chromium)
        page = browser.new_page(viewport={"width": VIEWPORT[0], "height": VIEWPORT[1]})
        page.goto((results / "report" / "report.html").resolve().as_uri())
        page.wait_for_load_state("networkidle")
        tops = page.evaluate("[...document.querySelectorAll('h2, figure')].map(e => "
                             "[e.tagName, e.textContent.slice(0, 40), e.getBoundingClientRect().top + scrollY, "
                             "e.getBoundingClientRect().bottom + scrollY])")
        page.screenshot(path=str(png), full_page=True)
        browser.close()
    sheet = Image.open(png).convert("RGB")
    png.unlink()
    first = next((t for t in tops if t[0] == "FIGURE"), None)
    heights = [k for k, t in enumerate(tops) if t[0] == "H2" and t[1].startswith("Building heights")]
    parts = [(0, round(first[3]) + 8 if first else min(sheet.height, 1100))]
    if heights:
        k = heights[0]
        end = next((t[2] for t in tops[k + 1:] if t[0] == "H2"), sheet.height + 8)
        parts.append((round(tops[k][2]) - 8, round(end) - 8))
    crops = [sheet.crop((0, a, sheet.width, b)) for a, b in parts]
    picture = Image.new("RGB", (sheet.width, sum(c.height for c in crops)), "white")
    y = 0
    for crop in crops:
        picture.paste(crop, (0, y))
        y += crop.height
    picture.save(out, quality=80, optimize=True)


def identified_building(results: Path, pid: str) -> tuple[int, str, np.ndarray]:
    """(id, name, scene x, y) of the tallest object with a measured height (objects/objects.csv), at
    the pixel of its own on the id map of ``pid`` nearest the middle of its pixels there."""
    import csv

    with open(results / "objects" / "objects.csv", newline="", encoding="utf-8") as f:
        rows = [r for r in csv.DictReader(f) if r["measured_height"]]
    if not rows:
        raise SystemExit(f"{results}: no object with a measured height (objects/objects.csv)")
    ds = gdal().Open(str(results / "maps" / f"{pid}.ids.tif"))
    ids, grid = ds.ReadAsArray(), Grid.of_dataset(ds)
    for r in sorted(rows, key=lambda r: -float(r["model_height"] or 0)):
        rr, cc = np.nonzero(ids == int(r["id"]))
        if len(rr) >= 50:
            k = np.argmin((rr - np.median(rr)) ** 2 + (cc - np.median(cc)) ** 2)
            return int(r["id"]), r["name"], np.array(grid.xy(cc[k] + 0.5, rr[k] + 0.5))
    raise SystemExit(f"{results}: no measured object shows on {pid}")


def streets_picture(results: Path, pid: str, out: Path, zoom: int = 18) -> None:
    """The viewer on ``pid`` with the config's overlays drawn, centred where the map shows the tallest
    measured building, that building clicked and identified (its row of the objects table)."""
    from pipeline25d.core.crs import transform_points

    crs = json.loads((results / "report" / "report.json").read_text(encoding="utf-8"))["crs"]
    oid, _, xy = identified_building(results, pid)
    lon, lat, _ = transform_points(np.array([[xy[0], xy[1], 0.0]]), crs, "EPSG:4326")[0]

    def click(page) -> None:
        page.wait_for_function("OVERLAYS.every(o => document.querySelector("
                               "`#layers label.loaded[data-overlay='${o.name}']`))")
        page.mouse.click(VIEWPORT[0] / 2, VIEWPORT[1] / 2)
        page.wait_for_function(f"(document.querySelector('#object table') || {{}}).textContent?.includes('{oid} (')")
        page.mouse.move(VIEWPORT[0] / 2 + 1, VIEWPORT[1] / 2)

    viewer_picture(results, f"#{pid}/{zoom}/{lat:.7f}/{lon:.7f}", out, act=click)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m pipeline25d_lab.pictures", description=__doc__.split("\n\n")[0])
    parser.add_argument("results", type=Path, help="a run's results folder, e.g. results/demo")
    parser.add_argument("out_dir", type=Path, help="where the pictures go, e.g. docs/images")
    parser.add_argument("--oblique", default="az045_el45", help="the oblique perspective shown (default az045_el45)")
    args = parser.parse_args(argv)
    if not (args.results / "maps" / "az000_el90.tif").exists():
        print(f"{args.results}: no nadir map; run the workflow first (make run)", file=sys.stderr)
        return 1
    maps_picture(args.results, args.oblique, args.out_dir / "maps.jpg")
    viewer_picture(args.results, f"#{args.oblique}/up", args.out_dir / "viewer.jpg")
    names = ["maps.jpg", "viewer.jpg"]
    if (args.results / "objects" / "objects.csv").is_file():
        streets_picture(args.results, args.oblique, args.out_dir / "demo-streets.jpg")
        names.append("demo-streets.jpg")
    report_picture(args.results, args.out_dir / "report.jpg")
    names.append("report.jpg")
    for name in names:
        print(args.out_dir / name)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
