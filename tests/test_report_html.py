"""The HTML report (report.html beside report.md) of the small demo run: a thumbnail of every map, each
perspective's check-point residual arrows computed from the check-point CSV (the warp the map used, refitted),
and the measured heights against their reference from heights.csv. Opened in Chromium by test_viewer_browser."""

from __future__ import annotations

import base64
import csv
import io
import json
import re

import numpy as np
from osgeo import gdal
from PIL import Image

from pipeline25d.publish.report_figures import (
    Residuals,
    check_residuals,
    exaggeration,
    height_points,
    heights_figure,
    residual_figure,
    thumbnail,
)


def _rows(path) -> list[dict]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def test_the_html_report_shows_a_thumbnail_of_every_map(small_run):
    _, results = small_run
    page = (results / "report" / "report.html").read_text()
    report = json.loads((results / "report" / "report.json").read_text())
    assert page.startswith("<!DOCTYPE html>") and "http://" not in page and "https://" not in page
    for p in report["perspectives"]:
        pid = p["id"]
        src = re.search(rf'<img class="thumb" alt="map {pid}" data-pid="{pid}" src="data:image/webp;base64,([^"]+)"',
                        page)
        assert src, pid
        thumb = Image.open(io.BytesIO(base64.b64decode(src[1])))
        cog = gdal.Open(str(results / "maps" / f"{pid}.tif"))
        assert max(thumb.size) == 480 and thumb.mode == "RGBA"
        scale = 480 / max(cog.RasterXSize, cog.RasterYSize)           # the map's own shape, rounded
        assert thumb.size == (round(cog.RasterXSize * scale), round(cog.RasterYSize * scale))
        assert f'alt="check-point residuals of {pid}"' in page
    assert '<img id="heights"' in page


def test_the_page_is_the_same_whether_its_figures_are_drawn_here_or_by_two_workers(small_run):
    """The pictures drawn here, by two forked workers, and by the run's report_figures job (before the
    web tiles were cut) make the same page: the one the run's report job wrote."""
    from pipeline25d.publish.report_html import draw_figures, render_html

    _, results = small_run
    report = json.loads((results / "report" / "report.json").read_text())
    assert len(report["perspectives"]) > 1
    pids = [p["id"] for p in report["perspectives"]]
    here = draw_figures(pids, report["gsd"], results)
    assert draw_figures(pids, report["gsd"], results, processes=2) == here
    assert sorted(here["maps"]) == sorted(p["id"] for p in report["perspectives"])
    assert json.loads((results / "work" / "report" / "figures.json").read_text()) == here
    page = render_html(report, results, here)
    assert page == (results / "report" / "report.html").read_text()
    assert page.count('<img class="residuals"') == len(report["perspectives"])


def test_residual_arrows_are_the_check_points_errors_from_the_csv(small_run):
    """The arrows start at each check point's true (x, y) of gcps/<id>.csv and are its map position minus
    that: for the demo's warp "none" exactly (map_x − x, map_y − y); for an order-1 polynomial fitted on the
    GCPs, a float64 least-squares fit over the mosaic's pixel positions gives the same within 1e-6 m."""
    _, results = small_run
    for pid in ("az045_el45", "az200_el30"):
        warp = json.loads((results / "maps" / f"{pid}.json").read_text())
        assert warp["method"] == "none"
        rows = [r for r in _rows(results / "gcps" / f"{pid}.csv") if r["role"] == "check"]
        true = np.array([[float(r["x"]), float(r["y"])] for r in rows])
        shown = np.array([[float(r["map_x"]), float(r["map_y"])] for r in rows])
        thumb = thumbnail(results / "maps" / f"{pid}.tif")
        res = check_residuals(results / "gcps" / f"{pid}.csv", results / "mosaic" / f"{pid}.vrt", "none", 0)
        fig = residual_figure(thumb, res, pid, 0.5)
        quiver = fig.axes[0].collections[0]
        assert len(rows) == warp["n_check"] == len(quiver.U) > 5
        np.testing.assert_array_equal(quiver.X, true[:, 0])
        np.testing.assert_array_equal(quiver.Y, true[:, 1])
        np.testing.assert_allclose(np.column_stack([quiver.U, quiver.V]), shown - true, atol=1e-9)
        first = rows[0]                                  # one value, by hand
        assert quiver.U[0] == float(first["map_x"]) - float(first["x"])
        rmsd = np.sqrt(np.mean(np.sum((shown - true) ** 2, axis=1)))
        assert abs(rmsd - warp["rmsd_m"]) < 1e-9         # the warp job scored the same errors
        assert quiver.scale == 1 / exaggeration(res, thumb.extent)
        # order 1: GDAL's fit against numpy's
        gt = gdal.Open(str(results / "mosaic" / f"{pid}.vrt")).GetGeoTransform()
        all_rows = _rows(results / "gcps" / f"{pid}.csv")
        px = np.array([[(float(r["map_x"]) - gt[0]) / gt[1], (float(r["map_y"]) - gt[3]) / gt[5]] for r in all_rows])
        xy = np.array([[float(r["x"]), float(r["y"])] for r in all_rows])
        gcp = np.array([r["role"] == "gcp" for r in all_rows])
        design = np.column_stack([np.ones(len(px)), px])
        coef = np.linalg.lstsq(design[gcp], xy[gcp], rcond=None)[0]
        poly = check_residuals(results / "gcps" / f"{pid}.csv", results / "mosaic" / f"{pid}.vrt", "polynomial", 1)
        np.testing.assert_allclose(poly.dxy, design[~gcp] @ coef - xy[~gcp], atol=1e-6)


def test_the_heights_scatter_plots_the_measured_heights_against_their_reference(small_run):
    _, results = small_run
    rows = [r for r in _rows(results / "heights.csv") if r["height"] and r["reference"]]
    pts = height_points(results / "heights.csv", ["az045_el45", "az200_el30"])
    fig = heights_figure(pts)
    lines = {ln.get_label(): ln for ln in fig.axes[0].get_lines()}
    flat = [r for r in rows if r["roof"] == "flat"]
    assert len(flat) > 5
    x, y = lines["combined, flat roofs"].get_data()
    np.testing.assert_array_equal(x, [float(r["reference"]) for r in flat])
    np.testing.assert_array_equal(y, [float(r["height"]) for r in flat])
    view = [r for r in rows if r["height_az200_el30"]]
    np.testing.assert_array_equal(lines["az200_el30"].get_data()[1], [float(r["height_az200_el30"]) for r in view])


def test_an_exaggeration_is_a_1_2_5_number_that_draws_the_longest_arrow_near_its_share():
    from pipeline25d.core.grid import Extent

    res = Residuals(np.zeros((2, 2)), np.array([[0.03, 0.04], [0.01, 0.0]]))     # longest 0.05 m
    k = exaggeration(res, Extent(0, 0, 200, 100))                                  # 8 % of 200 m = 16 m
    assert k == 200 and 0.05 * k <= 16 < 0.05 * k * 2.5
