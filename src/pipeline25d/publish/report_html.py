"""The report as one HTML page people look at (report.html beside report.md): the accuracy table, a
thumbnail of every map, each perspective's check-point residuals as arrows over its map, and the
measured building heights against their reference as a scatter plot.

The page is self-contained: its pictures (:mod:`pipeline25d.publish.report_figures`) are embedded as
data: URIs, so it opens from disk or a mail attachment and fetches nothing. Written atomically.
"""

from __future__ import annotations

import base64
import html
import json
from collections.abc import Sequence
from pathlib import Path

from pipeline25d.core.atomic import write_json, write_text
from pipeline25d.geometry.perspectives import Perspective
from pipeline25d.publish.report import fmt_measure, read_heights, warp_label
from pipeline25d.publish.report_figures import (
    check_residuals,
    exaggeration,
    height_points,
    heights_plot,
    residual_plot,
    thumbnail,
)

STYLE = """
body { font-family: system-ui, sans-serif; margin: 20px auto; max-width: 1100px; color: #222; }
h1 { font-size: 22px; } h2 { font-size: 17px; margin-top: 28px; }
table { border-collapse: collapse; font-size: 13px; } td, th { border: 1px solid #ccc; padding: 3px 7px; }
td.n { text-align: right; } .maps { display: flex; flex-wrap: wrap; gap: 14px; }
figure { margin: 0; border: 1px solid #ddd; padding: 6px; background: #fafafa; }
figure img.thumb { max-width: 240px; max-height: 240px; background: #dde3e8; display: block; }
figure img.residuals { width: 480px; display: block; } figcaption { font-size: 12px; max-width: 480px; }
p.note { font-size: 13px; color: #444; max-width: 900px; }
"""


def data_uri(data: bytes, mime: str) -> str:
    return f"data:{mime};base64,{base64.b64encode(data).decode('ascii')}"


def _fmt(v: float | None, nd: int = 3, missing: str = "n/a") -> str:
    return html.escape(fmt_measure(v, nd, missing))


def _accuracy_table(rep: dict) -> list[str]:
    rows = ["<table><tr><th>perspective</th><th>azimuth</th><th>elevation</th><th>tiles</th><th>GCPs</th>"
            "<th>checks</th><th>warp</th><th>RMSD m</th><th>RMSD px</th><th>max m</th></tr>"]
    for p in rep["perspectives"]:
        warp = warp_label(p)
        na = p.get("check_note") or "n/a"
        rows.append(f"<tr><td>{p['id']}</td><td class=n>{p['azimuth']}</td><td class=n>{p['elevation']}</td>"
                    f"<td class=n>{p['tiles_rendered']}</td><td class=n>{p['n_gcp']}</td>"
                    f"<td class=n>{p['n_check']}</td><td>{warp}</td><td class=n>{_fmt(p['rmsd_m'], missing=na)}</td>"
                    f"<td class=n>{_fmt(p['rmsd_px'], 2, missing=na)}</td>"
                    f"<td class=n>{_fmt(p['max_m'], missing=na)}</td></tr>")
    return rows + ["</table>"]


def _map_figure(results: Path, p: dict, gsd: float) -> str:
    """One perspective's thumbnail and residual plot, as a <figure>."""
    pid = p["id"]
    thumb = thumbnail(results / "maps" / f"{pid}.tif")
    res = check_residuals(results / "gcps" / f"{pid}.csv", results / "mosaic" / f"{pid}.vrt",
                          p["warp"]["method"], p["warp"]["order"])
    name = "nadir" if p["elevation"] == 90 else f"azimuth {p['azimuth']}°, elevation {p['elevation']}°"
    plot = residual_plot(thumb, res, f"{pid}: {name}", gsd)
    k = exaggeration(res, thumb.extent)
    caption = (f"<b>{pid}</b> ({name}). Left: the map. Right: its {len(res.xy)} check points (red), each arrow from"
               f" the true position toward where the map shows the point, drawn {k:g} times longer than it is;"
               f" RMSD {_fmt(p['rmsd_m'], missing=p.get('check_note') or 'n/a')} m.")
    return (f'<figure id="map-{pid}" data-pid="{pid}" data-exaggeration="{k:g}">'
            f'<div class="maps"><img class="thumb" alt="map {pid}" data-pid="{pid}" '
            f'src="{data_uri(thumb.webp, "image/webp")}">'
            f'<img class="residuals" alt="check-point residuals of {pid}" data-pid="{pid}" '
            f'src="{data_uri(plot, "image/png")}"></div><figcaption>{caption}</figcaption></figure>')


def _heights(h: dict, pids: Sequence[str], results: Path) -> list[str]:
    """The heights section: heights.json's content ``h`` and the scatter of heights.csv over its
    views (or the maps ``pids``)."""
    out = ["<h2>Building heights from the maps</h2>"]
    csv_path = results / "heights.csv"
    if h.get("skipped") or not csv_path.is_file():
        return out + [f"<p class=note>Not measured: {html.escape(h.get('skipped') or 'no heights.csv')}.</p>"]
    pts = height_points(csv_path, h.get("views") or list(pids))
    if not len(pts.ids):
        return out + ["<p class=note>No building has both a measured height and a reference height.</p>"]
    ref = h.get("reference", {})
    return out + [f"<p class=note>{len(pts.ids)} buildings measured on the maps with a reference"
                  f" ({html.escape(str(ref.get('source', '')))}; basis: {html.escape(str(ref.get('basis', '')))})."
                  " Gabled roofs against their eave. The figures per roof kind are in report.md.</p>",
                  f'<img id="heights" alt="measured heights against their reference" '
                  f'src="{data_uri(heights_plot(pts), "image/png")}">']


def render_html(rep: dict, results: str | Path, figures: dict) -> str:
    """The page for the report ``rep`` (report.json's content) of the run under ``results``, with the
    pictures ``figures`` (:func:`draw_figures`, drawn before the web tiles are cut)."""
    results = Path(results)
    title = f"pipeline25d report: {html.escape(rep['scene'])}"
    s = rep["sizes"]
    parts = [f"<!DOCTYPE html><html lang=en><head><meta charset=utf-8><title>{title}</title>"
             f"<style>{STYLE}</style></head><body><h1>{title}</h1>",
             f"<p class=note>Scene CRS {html.escape(rep['crs'])}, gsd {rep['gsd']} m, projection"
             f" {html.escape(str(rep.get('projection')))}, terrain {html.escape(str(rep['terrain'].get('source')))}."
             " Check points are held out: never used to fit or choose the warp.</p>",
             "<h2>Accuracy at check points</h2>", *_accuracy_table(rep),
             "<h2>Maps and their check-point residuals</h2>", '<div class="maps">']
    parts += [figures["maps"][p["id"]] for p in rep["perspectives"]]
    parts += ["</div>", *figures["heights"],
              "<h2>Sizes</h2>", f"<p class=note>model inputs {s['model_bytes'] / 1e6:.2f} MB, maps (COG)"
              f" {s['maps_bytes'] / 1e6:.2f} MB, web tiles {s['tms_bytes'] / 1e6:.2f} MB.</p>",
              "</body></html>"]
    return "\n".join(parts) + "\n"


def draw_figures(pids: Sequence[str], gsd: float, results: str | Path, processes: int = 1) -> dict:
    """The page's pictures as HTML: the thumbnail and check-point residuals of each map ``pids`` names
    ({"maps": {id: <figure>}}), and the heights scatter ({"heights": lines}). They need the maps, their
    GCP tables and the heights, not the web tiles: the report_figures job draws them while the last
    maps are cut. ``processes``: how many maps are drawn at once, by forked workers (the same
    pictures whatever the count)."""
    from contextlib import nullcontext

    from matplotlib.figure import Figure  # noqa: F401  (imported once, before the workers fork)

    from pipeline25d.core.cores import fork_pool, map_ahead

    results = Path(results)
    views = []
    for pid in sorted(pids):
        warp = json.loads((results / "maps" / f"{pid}.json").read_text())
        p = Perspective.from_id(pid)
        views.append({"id": pid, "azimuth": p.azimuth, "elevation": p.elevation, "rmsd_m": warp["rmsd_m"],
                      "check_note": warp.get("check_note"), "warp": {"method": warp["method"], "order": warp["order"]}})
    several = processes > 1 and len(views) > 1
    with fork_pool(processes) if several else nullcontext() as pool:
        maps = list(map_ahead(pool, _map_figure, ((results, p, gsd) for p in views), processes))
    return {"maps": {p["id"]: m for p, m in zip(views, maps)},
            "heights": _heights(read_heights(results), sorted(pids), results)}


def write_figures(pids: Sequence[str], gsd: float, results: str | Path, out_json: str | Path,
                  processes: int = 1) -> None:
    """Write :func:`draw_figures` as JSON, atomically."""
    write_json(out_json, draw_figures(pids, gsd, results, processes))


def write_html(rep: dict, results: str | Path, figures_json: str | Path, out_html: str | Path) -> None:
    """Write report.html for ``rep`` with the pictures of ``figures_json`` (:func:`write_figures`), atomically."""
    write_text(out_html, render_html(rep, results, json.loads(Path(figures_json).read_text())))
