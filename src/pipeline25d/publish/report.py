"""Report: per perspective accuracy at check points, tiles rendered/skipped, id maps, sizes, timings."""

from __future__ import annotations

import json
from pathlib import Path

from pipeline25d.core.atomic import write_json, write_text
from pipeline25d.core.raster import dataset_bounds, gdal
from pipeline25d.geometry.perspectives import Perspective
from pipeline25d.publish.report_ids import id_layer, ids_section
from pipeline25d.stages.plan import plan_blocks, read_plan
from pipeline25d.stages.records import Scene, coarser_tiles


def _size(path: Path) -> int:
    if path.is_file():
        return path.stat().st_size
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file()) if path.exists() else 0


def input_size(config: dict) -> int:
    """Bytes of the model inputs (a tileset counts its folder)."""
    total = 0
    for spec in config["inputs"].values():
        path = Path(spec["path"])
        total += _size(path.parent) if path.name.endswith("tileset.json") else _size(path)
    return total


#: the stages that run while or after the report is written: their logs hold an earlier run's job
AFTER_TIMINGS = ("report", "viewer")


def stage_timings(results: Path, current=None) -> dict[str, dict]:
    """Per stage, from the jobs' own logs (:func:`pipeline25d.core.logsetup.job_record`): jobs,
    wall seconds summed (start-up and the rule's function), and the largest peak RSS (MB) of a
    job's process and its largest child together; with ``current(path relative to logs/)``, only
    the logs it accepts (see :func:`current_jobs`). A log without a time line (a job still running,
    or killed; one Snakemake removed as its job started again) does not count."""
    from pipeline25d.core.logsetup import job_logs, read_job_record, wall_seconds

    out: dict[str, dict] = {}
    for stage, log in job_logs(results / "logs"):
        if stage in AFTER_TIMINGS or current is not None and not current(log.relative_to(results / "logs")):
            continue
        try:
            rec = read_job_record(log)
        except FileNotFoundError:        # gone since it was listed: its job (wms, beside the report) runs again
            continue
        seconds = wall_seconds(rec)
        if seconds is None:
            continue
        s = out.setdefault(stage, {"jobs": 0, "seconds": 0.0, "max_rss_mb": 0.0})
        s["jobs"] += 1
        s["seconds"] = round(s["seconds"] + seconds, 2)
        rss_kb = rec.get("max_rss_kb", 0) + rec.get("children_max_rss_kb", 0)
        s["max_rss_mb"] = max(s["max_rss_mb"], round(rss_kb / 1024, 1))
    return out


def current_jobs(districts: set[str], blocks: dict[str, set[str]], heights_jobs: set[str] = frozenset()):
    """``current(job log)``: whether it belongs to a job of this configuration, whose
    ``districts``, perspectives' render ``blocks`` (ids by perspective) and jobs of the heights
    stage's blocks of footprints (``heights_jobs``) are given. Logs an earlier configuration left (a removed district or
    perspective, a render block of another grouping) are not this run's."""
    def current(rel: Path) -> bool:
        if len(rel.parts) == 1:                              # scene.log, terrain.log
            return True
        if rel.parts[0] == "render":
            return rel.parts[1] in blocks and rel.stem.removeprefix("block_") in blocks[rel.parts[1]]
        if rel.parts[0] == "heights":
            return rel.stem == "blocks" or rel.stem.removeprefix("block_") in heights_jobs
        return rel.stem in districts or rel.stem in blocks
    return current


def lonlat_bounds(cog: Path) -> list[float]:
    """[west, south, east, north] of a map in EPSG:4326 (for the viewer)."""
    import numpy as np

    from pipeline25d.core.crs import transform_points

    ds = gdal().Open(str(cog))
    b = dataset_bounds(ds)
    xs, ys = [b.xmin, b.xmax], [b.ymin, b.ymax]
    pts = np.array([[x, y, 0.0] for x in xs for y in ys])
    ll = transform_points(pts, ds.GetProjection(), "EPSG:4326")
    return [float(ll[:, 0].min()), float(ll[:, 1].min()), float(ll[:, 0].max()), float(ll[:, 1].max())]


def build_report(config: dict, results: str | Path) -> dict:
    from pipeline25d.config import perspectives

    results = Path(results)
    scene = Scene.read(results / "scene.json")
    terrain_meta = results / "terrain" / "terrain.json"
    terrain = json.loads(terrain_meta.read_text()) if terrain_meta.exists() else {"source": scene.terrain}
    persp, blocks = [], {}
    for pid in sorted(p.id for p in perspectives(config)):
        plan = read_plan(results / "plans" / f"{pid}.json")
        blocks[pid] = set(plan_blocks(plan, config["render"]["block"]))
        warp = json.loads((results / "maps" / f"{pid}.json").read_text())
        cog = results / "maps" / f"{pid}.tif"
        p = Perspective.from_id(pid)
        persp.append({
            "id": pid, "azimuth": p.azimuth, "elevation": p.elevation,
            "tiles_rendered": len(plan.tiles), "tiles_skipped": plan.n_tiles_skipped,
            "gcps_observed": warp["n_observed"], "n_gcp": warp["n_gcp"], "n_check": warp["n_check"],
            "warp": {"method": warp["method"], "order": warp["order"]},
            "relief_px": warp["relief_px"],
            "rmsd_m": warp["rmsd_m"], "rmsd_px": warp["rmsd_px"], "max_m": warp["max_m"],
            "check_note": warp.get("check_note"), "cv_rmsd_m": warp.get("cv_rmsd_m"),
            "unwarped_rmsd_m": warp["candidates"][0]["rmsd_m"],
            "unwarped_note": warp["candidates"][0].get("check_note"),
            "paper_method": warp.get("paper_method"),
            "candidates": warp["candidates"],
            "map_bytes": _size(cog), "tms_bytes": _size(results / "tms" / pid), "ids": id_layer(results, pid),
            "lonlat_bounds": lonlat_bounds(cog),
        })
    heights = read_heights(results)
    model = input_size(config)
    maps = sum(p["map_bytes"] for p in persp)
    tms = sum(p["tms_bytes"] for p in persp)
    coarser = coarser_inputs(results, sorted(config["inputs"]))
    return {
        "scene": config["scene"], "crs": config["crs"], "gsd": config["gsd"], "z0": scene.z0,
        "projection": scene.projection, "terrain": terrain,
        "dtm_check_holdout_m": scene.dtm_check_holdout_m,
        "perspectives": persp,
        "heights": heights,
        "sizes": {"model_bytes": model, "maps_bytes": maps, "tms_bytes": tms,
                  "ids_bytes": sum(p["ids"]["ids_bytes"] for p in persp if p["ids"]),
                  "model_to_maps": model / maps if maps else None},
        "timings": stage_timings(results, current_jobs(set(config["inputs"]), blocks, _heights_jobs(results))),
        **({"coarser": coarser} if coarser else {}),
    }


def read_heights(results: Path) -> dict:
    """heights.json's content, or why there is none."""
    path = results / "heights.json"
    return json.loads(path.read_text()) if path.exists() else {"skipped": "the heights step did not run"}


def _heights_jobs(results: Path) -> set[str]:
    """The jobs the heights stage measured its blocks of footprints in (work/heights/blocks.json: a job
    per block in a file of before the jobs; none without it)."""
    try:
        d = json.loads((results / "work" / "heights" / "blocks.json").read_text())
        return set(d["jobs"] if "jobs" in d else d["blocks"])
    except (OSError, ValueError, KeyError, TypeError):
        return set()


def coarser_inputs(results: Path, districts: list[str]) -> list[dict]:
    """The input tiles drawn coarser than the gsd asks for, per district (from the chunk
    indexes ingest wrote): ``{district, tile, level, missing, drawn}``; [] when none was."""
    out = []
    for district in districts:
        index = results / "chunks" / district / "index.json"
        if index.is_file():
            out += [{"district": district, **c.to_json()} for c in coarser_tiles(json.loads(index.read_text()))]
    return out


def warp_label(p: dict) -> str:
    """A report perspective's warp as people read it: "none", "tps", "polynomial 2"."""
    return p["warp"]["method"] + (f" {p['warp']['order']}" if p["warp"]["method"] == "polynomial" else "")


def fmt_measure(v: float | None, nd: int = 3, missing: str = "–") -> str:
    """A measured figure with ``nd`` decimals; smaller ones keep two significant digits, and
    one below 1e-6 reads "< 1e-06" (a measurement is never printed as a bare 0.000)."""
    if v is None:
        return missing
    if abs(v) < 1e-6:
        return "< 1e-06"
    if abs(v) < 10 ** -(nd - 1):
        return f"{v:.2g}"
    return f"{v:.{nd}f}"


def _ratio(r: float) -> str:
    """A size ratio as "a : b" with the larger side first at one decimal: 34.5 : 1 or 1 : 21.4."""
    return f"{r:.1f} : 1" if r >= 1 else f"1 : {1 / r:.1f}"


def render_markdown(rep: dict) -> str:
    fmt = fmt_measure
    projection = {"terrain": "terrain-relative (heights above the DTM)",
                  "plane": f"map-aligned plane at z0 = {rep['z0']:.2f} m, then a GCP warp",
                  "paper": "the paper's camera (Eqs. 1-18: image plane perpendicular to the view), then its"
                           " polynomial GCP warp"}[rep.get("projection", "plane")]
    lines = [f"# pipeline25d report: {rep['scene']}", "",
             f"Scene CRS {rep['crs']}, gsd {rep['gsd']} m.", "",
             f"- terrain: {rep['terrain'].get('source')}"
             + (f", {rep['terrain']['resolution']} m cells" if rep["terrain"].get("resolution") else ""),
             f"- projection: {projection}",
             "- check points are held out: never used to fit or to choose the warp (chosen by 5-fold"
             " cross-validation on the GCPs)"
             + (f"; the DTM is interpolated without the ground within {rep['dtm_check_holdout_m']:.1f} m of each"
                " check point, so they measure how well it predicts ground it has not seen."
                if rep.get("dtm_check_holdout_m") else "."), "",
             "| perspective | tiles rendered | skipped | GCPs | checks | warp | RMSD m | RMSD px | max m"
             " | unwarped RMSD m |",
             "|---|---:|---:|---:|---:|---|---:|---:|---:|---:|"]
    for p in rep["perspectives"]:
        warp = warp_label(p)
        na = p.get("check_note") or "n/a"
        unwarped = fmt(p["unwarped_rmsd_m"], missing=p.get("unwarped_note") or na)
        lines.append(f"| {p['id']} | {p['tiles_rendered']} | {p['tiles_skipped']} | {p['n_gcp']} | {p['n_check']} | "
                     f"{warp} | {fmt(p['rmsd_m'], missing=na)} | {fmt(p['rmsd_px'], 2, missing=na)} | "
                     f"{fmt(p['max_m'], missing=na)} | {unwarped} |")
    paper = [p for p in rep["perspectives"] if p.get("paper_method")]
    if paper:
        lines += ["", "## The paper's method on the same check points", "",
                  "Plane at z0 plus the warp the paper uses (polynomial, order 3 where the GCPs allow), fitted on the"
                  " same GCPs; each observed marker moved exactly to its plane-projection position by"
                  " (DTM − z0)·cot φ along the view, so the points and their sampling noise are the same. The"
                  " paper's camera image is an affine function of that projection, so its warp scores the same"
                  " (`projection: paper` renders it).", "",
                  "| perspective | warp | RMSD m | RMSD px | max m |", "|---|---|---:|---:|---:|"]
        for p in paper:
            pm = p["paper_method"]
            na = pm.get("check_note") or "n/a"
            lines.append(f"| {p['id']} | polynomial {pm['order']} | {fmt(pm['rmsd_m'], missing=na)} | "
                         f"{fmt(pm['rmsd_px'], 2, missing=na)} | {fmt(pm['max_m'], missing=na)} |")
    lines += ids_section(rep["perspectives"])
    if rep.get("heights"):
        lines += heights_section(rep["heights"])
    s = rep["sizes"]
    lines += ["", "## Sizes", "",
              f"- model inputs: {s['model_bytes'] / 1e6:.2f} MB",
              f"- maps (COG): {s['maps_bytes'] / 1e6:.2f} MB"
              + (f" (model : maps = {_ratio(s['model_to_maps'])})" if s["model_to_maps"] else ""),
              f"- web tiles: {s['tms_bytes'] / 1e6:.2f} MB"
              + (f" (model : tiles = {_ratio(s['model_bytes'] / s['tms_bytes'])})" if s["tms_bytes"] else ""),
              *([f"- id maps: {s['ids_bytes'] / 1e6:.2f} MB (ids : maps = {_ratio(s['ids_bytes'] / s['maps_bytes'])})"]
                if s.get("ids_bytes") and s["maps_bytes"] else []),
              "", "## Stage timings", "",
              "| stage | jobs | seconds (sum) | max RSS MB |", "|---|---:|---:|---:|"]
    for stage, t in rep["timings"].items():
        lines.append(f"| {stage} | {t['jobs']} | {t['seconds']:.1f} | {t['max_rss_mb']:.0f} |")
    if rep.get("coarser"):
        lines += coarser_section(rep["coarser"])
    if rep.get("updates"):
        lines += ["", "## Redone since the last report", "",
                  "Map tiles whose image spec (chunks, LODs, frame, render settings) changed are rendered again;"
                  " those whose GCP candidates alone changed keep their image and observe their GCPs again;"
                  " web tiles are cut again only where the map's pixels changed"
                  " (see docs/how-it-works.md, District updates).", "",
                  "| perspective | map tiles redone | GCPs only | of | web tiles redone | of | web cut |",
                  "|---|---:|---:|---:|---:|---:|---|"]
        for pid, u in rep["updates"].items():
            lines.append(f"| {pid} | {u['tiles_redone']} | {u['gcps_redone']} | {u['tiles']} | {u['web_tiles_redone']} "
                         f"| {u['web_tiles']} | {u['web_cut']} |")
    return "\n".join(lines) + "\n"


def coarser_section(coarser: list[dict]) -> list[str]:
    """The report's list of input tiles drawn coarser than the gsd asks for (missing children)."""
    lines = ["", "## Drawn coarser than the gsd asks for", "",
             "Parts of these input tiles are missing (an OSGB PagedLOD child file, a 3D Tiles child's content);"
             " where they would be drawn, the finest level present is drawn instead (the input's"
             " `missing_children: error` refuses such an input).", "",
             "| district | tile drawn | level | missing | drawn instead |", "|---|---|---:|---|---|"]
    for c in coarser:
        lines.append(f"| {c['district']} | {c['tile']} | {c['level']} | {', '.join(c['missing'])} | {c['drawn']} |")
    return lines


HEIGHT_GROUPS = {"all": "All buildings", "flat": "Flat roofs",
                 "gabled_eave": "Gabled roofs: the height against their eave",
                 "gabled_ridge": "Gabled roofs: the measured ridge against their ridge",
                 "hipped_eave": "Hipped roofs: the height against their eave",
                 "hipped_ridge": "Hipped roofs: the measured ridge against their ridge"}


def _height_table(group: dict) -> list[str]:
    """Rows per perspective (combined first): measured / footprints and the errors, or "not measured"."""
    lines = ["| perspective | measured / footprints | RMSD m | bias m | median abs m | p90 abs m |",
             "|---|---:|---:|---:|---:|---:|"]
    for key, st in group.items():
        name = "combined (median of the views)" if key == "combined" else key
        if st.get("n"):
            errs = (f"{fmt_measure(st['rmsd'])} | {fmt_measure(st['bias'])} | {fmt_measure(st['median_abs'])} | "
                    f"{fmt_measure(st['p90_abs'])}")
        else:
            errs = " | ".join(["not measured"] * 4)
        lines.append(f"| {name} | {st['n_measured']} / {st['n_footprints']} | {errs} |")
    return lines


def heights_section(h: dict) -> list[str]:
    """The report's building-height section (see height_sources.finish_stage)."""
    lines = ["", "## Building heights from the maps", ""]
    if h.get("skipped"):
        return lines + [f"Not measured: {h['skipped']}."]
    fp, ref = h["footprints"], h["reference"]
    src = {"truth": "the demo's truth.json", "cityjson": "the CityJSON Building objects",
           "layer": f"layer {', '.join(fp.get('paths') or [])}"}[fp["source"]]
    lines += [f"Each footprint's roof displacement between the nadir map and every oblique map, as a height"
              f" (per building in results/<scene>/heights.csv). Footprints: {src}, {fp['n_on_maps']} of"
              f" {fp['n_given']} within the maps; {h['n_measured']} measured in at least one view. Reference: "
              f"{ref['source']}; basis: {ref['basis']}. Errors are measured − reference over every measured"
              " building with a reference; a view counts a building only where it accepted it, and a view more"
              f" than {h['settings']['outlier_m']:g} m from the median of two or more other accepted views is"
              " rejected as inconsistent (with only two views, both are).", "",
              "| perspective | measured | not measured, why |", "|---|---:|---|"]
    for v, reasons in h.get("reasons", {}).items():
        why = ", ".join(f"{k} {n}" for k, n in sorted(reasons.items()) if k != "measured") or "–"
        lines.append(f"| {v} | {reasons.get('measured', 0)} | {why} |")
    lines += ["", "Why not: hidden = under half the roof matches anywhere; flat = the match score does not drop"
              " on both sides (the roof could slide along a row of like roofs); ambiguous = rival peaks the other"
              " views did not settle; inconsistent = far from the other views; unstable = no sub-pixel fit;"
              " too_small, nadir_nodata, no_peak, out_of_range as named. Where the roof's colours give no height"
              " (e.g. walls tinted like the roof, a sloped ground under the roof), where the building's"
              " silhouette ends gives it; a+b names both reasons when neither did (silhouette_spread: its lines"
              " do not agree, silhouette_lines: too few end on ground, silhouette_disagrees: far from the views"
              " the colours measured).", ""]
    if not h.get("groups"):
        return lines + ["No reference heights: the measured heights are not compared."]
    for g, group in h["groups"].items():
        n = group["combined"]["n_footprints"]
        lines += [f"### {HEIGHT_GROUPS.get(g, g)} ({n})", ""]
        if g == next((k for k in h["groups"] if k.endswith("_eave")), None):
            lines += ["A pitched roof has two heights: its eave (the height, CSV `height`) and its ridge (CSV"
                      " `ridge`: the eave plus the rise that lands the roof's faces on their colours in the oblique"
                      " views, else that the silhouette's gable ends show; `roof_measured` the kind found). Each is"
                      " compared with its own truth, per roof kind.", ""]
        lines += [*_height_table(group), ""]
    if h.get("own_ground"):
        lines += ["### Against the model's own ground",
                  "", "The same buildings' roofs above the ground the model itself stands on"
                  f" ({h.get('own_ground_source') or 'its own ground surfaces'}) instead of the maps' DTM:", "",
                  *_height_table(h["own_ground"]), ""]
    return lines[:-1] if lines[-1] == "" else lines


def write_report(config: dict, results: str | Path, out_json: str | Path, out_md: str | Path) -> dict:
    rep = build_report(config, results)
    rep["updates"], seen = updates_since_last_report(Path(results), rep["perspectives"])
    write_json(out_json, rep)
    write_text(out_md, render_markdown(rep))
    write_json(Path(results) / "work" / "reported.json", seen, indent=None)
    return rep


def updates_since_last_report(results: Path, perspectives: list[dict]) -> tuple[dict, dict]:
    """What the runs since the last report redid, per perspective: map tiles rendered again
    (tiles whose image hash is not the one last reported), map tiles whose GCPs alone were
    observed again (the spec hash changed, the image hash did not) and web tiles cut again (from
    the tms jobs' own figures, counted once: a tms job that did not run since adds nothing).
    Returns that and the state to remember (work/reported.json)."""
    state_path = results / "work" / "reported.json"
    last = json.loads(state_path.read_text()) if state_path.exists() else {}
    seen, out = {}, {}
    for p in perspectives:
        pid = p["id"]
        plan = read_plan(results / "plans" / f"{pid}.json")
        specs = {t.key: t.spec_hash for t in plan.tiles}
        images = {t.key: t.image_hash for t in plan.tiles}
        stats_path = results / "work" / "tms" / f"{pid}.json"
        stats = json.loads(stats_path.read_text())
        stamp = stats_path.stat().st_mtime_ns
        before = last.get(pid, {})
        respecified = {k for k, h in specs.items() if before.get("specs", {}).get(k) != h}
        tiles_redone = sum(1 for k in respecified if not images[k] or before.get("images", {}).get(k) != images[k])
        web_redone = 0 if before.get("tms_stamp") == stamp else stats["web_tiles_redone"]
        out[pid] = {"tiles": len(specs), "tiles_redone": tiles_redone, "gcps_redone": len(respecified) - tiles_redone,
                    "web_tiles": stats["web_tiles"],
                    "web_tiles_redone": web_redone,
                    "web_cut": "none" if not web_redone else "full" if stats["full"] else "update"}
        seen[pid] = {"specs": specs, "images": images, "tms_stamp": stamp}
    return out, seen
