"""The Snakemake DAG: dry-run job counts, and the full pipeline on a small demo city."""

from __future__ import annotations

import json
import math
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import REPO

from pipeline25d.config import validate_schema
from pipeline25d.stages.plan import plan_blocks, read_plan
from pipeline25d_lab.scenes.demo import generate_demo_city

SMALL_PERSPECTIVES = [{"azimuth": 0, "elevation": 90}, {"azimuth": 45, "elevation": 45},
                      {"azimuth": 200, "elevation": 30}]


def snakemake(workdir: Path, *args: str, check: bool = True) -> subprocess.CompletedProcess:
    # as a user runs it: the venv's bin is NOT on PATH (jobs must find their own interpreter)
    venv_bin = str(Path(sys.executable).parent)
    path = ":".join(d for d in os.environ.get("PATH", "").split(":") if d and d != venv_bin)
    env = {**os.environ, "PATH": path}
    cmd = [sys.executable, "-m", "snakemake", "--snakefile", str(REPO / "Snakefile"), "--directory", str(workdir),
           "--configfile", str(workdir / "config.yaml"), "-j2", *args]
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
    if check and proc.returncode != 0:
        raise AssertionError(f"snakemake {' '.join(args)} failed:\n{proc.stdout[-4000:]}\n{proc.stderr[-4000:]}")
    return proc


def job_counts(dry_run_output: str) -> dict[str, int]:
    """The 'Job stats' table of a dry run as {rule: count}."""
    table = dry_run_output.split("Job stats:")[1]
    counts = {}
    for line in table.splitlines()[3:]:
        m = re.match(r"^(\w+)\s+(\d+)$", line.strip())
        if not m:
            break
        counts[m.group(1)] = int(m.group(2))
    return counts


def make_scene(workdir: Path, config: dict, scale: float = 0.3, buildings: int = 30) -> None:
    generate_demo_city(workdir / "resources" / "demo", seed=3, n_buildings=buildings, scale=scale)
    (workdir / "config.yaml").write_text(yaml.safe_dump(config))


def test_dry_run_of_the_default_config_counts_jobs_per_rule(tmp_path):
    config = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    make_scene(tmp_path, config)
    out = snakemake(tmp_path, "-n").stdout
    # the id layer's mosaics, maps and tiles are made by the map's own warp and tms jobs (and the
    # mosaics and GCP tables by the warp job)
    assert job_counts(out) == {"ingest": 4, "terrain": 1, "scene": 1, "plan": 1, "warp": 9,
                               "tms": 9, "objects": 1, "heights_blocks": 1, "heights": 1, "report_figures": 1,
                               "report": 1, "viewer": 1, "wms": 1, "all": 1, "total": 33}
    id_files = (".ids.vrt", ".ids.tif", "/idtiles/", "/objects/")
    assert all(f in out for f in id_files)
    # objects off: no id mosaics, no id maps, no id tiles (not even declared), no objects table
    (tmp_path / "config.yaml").write_text(yaml.safe_dump({**config, "objects": {"enabled": False}}))
    off_out = snakemake(tmp_path, "-n").stdout
    off = job_counts(off_out)
    assert "objects" not in off and off["total"] == 32 and not any(f in off_out for f in id_files)
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(config))
    # Once the plans exist the tile jobs are known: one per non-empty tile, none for empty ones.
    pids = [f"az{a:03d}_el45" for a in range(0, 360, 45)] + ["az000_el90"]
    snakemake(tmp_path, *[f"results/demo/plans/{pid}.json" for pid in pids])
    counts = job_counts(snakemake(tmp_path, "-n").stdout)
    plans = [read_plan(p) for p in (tmp_path / "results" / "demo" / "plans").glob("*.json")]
    assert len(plans) == 9
    block = validate_schema(config)["render"]["block"]
    assert counts["render_block"] == sum(len(plan_blocks(p, block)) for p in plans)
    assert sum(p.n_tiles_skipped for p in plans) > 0      # the demo's empty blocks


def test_bad_config_stops_before_any_job(tmp_path):
    config = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    make_scene(tmp_path, {**config, "gsd": -1})
    proc = snakemake(tmp_path, "-n", check=False)
    assert proc.returncode != 0 and "gsd" in proc.stdout + proc.stderr
    make_scene(tmp_path, {**config, "inputs": {"d0": {"path": "resources/demo/missing.obj"}}})
    proc = snakemake(tmp_path, "-n", check=False)
    assert proc.returncode != 0 and "missing.obj" in proc.stdout + proc.stderr
    assert not (tmp_path / "results").exists()



def _under_4gb() -> None:
    import resource

    resource.setrlimit(resource.RLIMIT_AS, (4 << 30, 4 << 30))


@pytest.mark.parametrize("dry_run", [True, False])
def test_a_gsd_typo_is_refused_before_any_job_under_a_memory_limit(tmp_path, dry_run):
    """gsd 0.00001 m on the demo asks for ~1e15 pixels per map; under a 4 GB address-space limit the run
    stops at parse time with the estimate and the key to raise, exit status 1, no traceback, no job."""
    config = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    make_scene(tmp_path, {**config, "gsd": 0.00001}, buildings=10)
    cmd = [sys.executable, "-m", "snakemake", "--snakefile", str(REPO / "Snakefile"), "--directory", str(tmp_path),
           "--configfile", str(tmp_path / "config.yaml"), "-j2", *(["-n"] if dry_run else [])]
    proc = subprocess.run(cmd, capture_output=True, text=True, preexec_fn=_under_4gb, timeout=120)
    assert proc.returncode == 1, proc.stderr[-2000:]
    line = next(ln for ln in proc.stderr.splitlines() if ln.startswith("pipeline25d: error: "))
    verts = np.array([ln.split()[1:4] for f in sorted((tmp_path / "resources" / "demo").glob("d*.obj"))
                      for ln in f.read_text().splitlines() if ln.startswith("v ")], dtype=float)
    w, h = np.ptp(verts[:, 0]), np.ptp(verts[:, 1])
    assert f"config key limits.max_map_pixels: gsd 1e-05 m on a {w:.4g} × {h:.4g} m scene" in line, line
    assert float(re.search(r"up to ([\d.e+]+) pixels", line)[1]) >= \
        0.99 * w * h / 1e-10                        # every map covers at least the scene's footprint
    assert "Traceback" not in proc.stderr + proc.stdout
    assert not (tmp_path / "results").exists()


#: for runs whose tests check no object ids (small_run and plane_run check them): no id tiles, id maps,
#: id web tiles nor objects table to make
NO_OBJECTS = {"objects": {"enabled": False}}

SMALL_CONFIG = {"scene": "small", "crs": "EPSG:25832",
                "inputs": {f"d{i}": {"path": f"resources/demo/d{i}.obj"} for i in range(4)},
                "gsd": 0.5, "tile_size": 256, "chunk_size": 80,
                "perspectives": SMALL_PERSPECTIVES, "gcp": {"spacing": 8, "holdout": 0.3, "marker_px": 4},
                "tms": {"zoom": "14-17"}}


def demo_run(tmp_path_factory, scene: str, **overrides) -> tuple[Path, Path]:
    """The small demo city run end to end with SMALL_CONFIG plus ``overrides``: (workdir, results)."""
    workdir = tmp_path_factory.mktemp(scene)
    make_scene(workdir, {**SMALL_CONFIG, "scene": scene, **overrides}, scale=0.35, buildings=40)
    snakemake(workdir)
    return workdir, workdir / "results" / scene


@pytest.fixture(scope="module")
def plane_run(tmp_path_factory):
    """The paper's method on the same city: the exact DTM for GCP heights, plane at z0, GCP warp."""
    return demo_run(tmp_path_factory, "plane", terrain="resources/demo/dtm.tif", projection="plane",
                    perspectives=SMALL_PERSPECTIVES[1:])


@pytest.fixture(scope="module")
def paper_run(tmp_path_factory):
    """The paper's own camera and polynomial warp on the small run's city, GCPs and terrain."""
    return demo_run(tmp_path_factory, "paper", projection="paper", perspectives=SMALL_PERSPECTIVES[1:2])


def test_full_pipeline_outputs(small_run):
    from osgeo import gdal, osr

    _, results = small_run
    report = json.loads((results / "report" / "report.json").read_text())
    ids = {p["id"] for p in report["perspectives"]}
    assert ids == {"az000_el90", "az045_el45", "az200_el30"}
    scene_srs = osr.SpatialReference()
    scene_srs.ImportFromEPSG(25832)
    for pid in ids:
        ds = gdal.Open(str(results / "maps" / f"{pid}.tif"))
        assert ds.GetMetadata("IMAGE_STRUCTURE").get("LAYOUT") == "COG"
        assert osr.SpatialReference(ds.GetProjection()).IsSame(scene_srs)
        assert ds.RasterCount == 4 and ds.GetGeoTransform()[2] == 0 and ds.GetGeoTransform()[5] < 0
        assert any((results / "tms" / pid).rglob("*.webp"))                # the default tile format
    assert (results / "viewer" / "index.html").exists() and (results / "viewer" / "leaflet" / "leaflet.js").exists()
    assert (results / "report" / "report.md").read_text().startswith("# pipeline25d report: small")


def test_paper_method_warps_ground_at_check_points_within_one_pixel(plane_run):
    _, results = plane_run
    report = json.loads((results / "report" / "report.json").read_text())
    assert report["projection"] == "plane" and report["terrain"]["source"].startswith("user DTM")
    for p in report["perspectives"]:
        assert p["n_check"] >= 5, p
        assert p["rmsd_px"] < 1.0, p
        # the oblique views need the warp: unwarped ground is off by metres on this terrain
        assert p["unwarped_rmsd_m"] > 2 * report["gsd"] and p["warp"]["method"] != "none"


def test_paper_camera_renders_and_its_warp_matches_the_analytic_paper_method(paper_run, small_run):
    """projection: paper renders on the paper camera's image plane and warps it with the
    paper's polynomial; its check-point error equals the small run's analytic paper-method
    figure (same city, same GCPs and roles) to within marker sampling, and is above the
    terrain-relative figure (this gentle demo relief keeps both sub-pixel; the rugged city
    is where they part)."""
    from osgeo import gdal, osr

    _, results = paper_run
    paper = json.loads((results / "report" / "report.json").read_text())
    small = json.loads((small_run[1] / "report" / "report.json").read_text())
    assert paper["projection"] == "paper"
    (p,) = paper["perspectives"]
    ref = next(q for q in small["perspectives"] if q["id"] == p["id"])
    assert p["warp"]["method"] == "polynomial" and p["unwarped_rmsd_m"] is None and p["n_check"] >= 5, p
    assert abs(p["rmsd_px"] - ref["paper_method"]["rmsd_px"]) < 0.25 * ref["paper_method"]["rmsd_px"] + 0.1, \
        (p["rmsd_px"], ref["paper_method"])
    assert p["rmsd_px"] > ref["rmsd_px"]
    tile = next((results / "tiles" / p["id"]).rglob("*.tif"))
    assert gdal.Open(str(tile)).GetProjection() == ""                     # the image plane is no CRS
    ds = gdal.Open(str(results / "maps" / f"{p['id']}.tif"))
    assert osr.SpatialReference(ds.GetProjection()).GetAuthorityCode(None) == "25832"
    assert ds.GetGeoTransform()[2] == 0 and abs(ds.GetGeoTransform()[1] - 0.5) < 1e-9
    assert "the paper's camera" in (results / "report" / "report.md").read_text()


def test_terrain_from_the_model_puts_check_points_within_a_quarter_pixel_without_warp(small_run):
    """No DTM given: the DTM comes from the model, and terrain-relative projection needs no warp."""
    _, results = small_run
    report = json.loads((results / "report" / "report.json").read_text())
    assert report["projection"] == "terrain" and "Cloth Simulation Filter" in report["terrain"]["source"]
    md = (results / "report" / "report.md").read_text()
    assert "terrain: model surface" in md and "0.000" not in md
    for p in report["perspectives"]:
        assert p["warp"]["method"] == "none", p
        assert p["n_check"] >= 5, p
        assert p["rmsd_px"] < 0.25, p
        # the paper's method on the same points is reported beside it (oblique views only)
        if p["elevation"] < 90:
            assert p["paper_method"]["n_check"] == p["n_check"]


def test_heights_step_measures_every_demo_building_against_its_truth(small_run):
    """The heights rule found the demo's truth.json by itself and measured every building on the
    maps; its reference is the truth's roof above the DTM the maps used (here the DTM derived from
    the model), which the generator's analytic terrain checks independently."""
    import csv

    from pipeline25d_lab.scenes.demo import terrain_height

    workdir, results = small_run
    stats = json.loads((results / "heights.json").read_text())
    truth = {b["id"]: b for b in json.loads((workdir / "resources" / "demo" / "truth.json").read_text())["buildings"]}
    rows = {r["id"]: r for r in csv.DictReader((results / "heights.csv").open())}
    assert stats["footprints"]["source"] == "truth" and set(rows) == set(truth)
    assert "truth.json" in stats["reference"]["source"] and "dtm.tif" in stats["reference"]["basis"]
    for bid, r in rows.items():
        b = truth[bid]
        assert r["roof"] == b["roof"]
        ground = terrain_height(*np.mean(b["footprint"], axis=0))           # gentle relief: centroid ≈ mean
        assert float(r["reference"]) == pytest.approx(b["eave_z"] - ground, abs=0.15), bid
    flat = stats["groups"]["flat"]
    n_flat = sum(b["roof"] == "flat" for b in truth.values())
    assert flat["combined"]["n_footprints"] == n_flat and flat["combined"]["n_measured"] >= 0.8 * n_flat
    # independent of the step's own statistics: measured flat roofs against eave − analytic terrain
    err = [float(r["height"]) - (truth[i]["eave_z"] - terrain_height(*np.mean(truth[i]["footprint"], axis=0)))
           for i, r in rows.items() if r["roof"] == "flat" and r["height"]]
    assert len(err) == flat["combined"]["n"] and np.sqrt(np.mean(np.square(err))) < 0.3
    assert set(stats["views"]) == {"az045_el45", "az200_el30"} and "gabled_ridge" in stats["groups"]
    md = (results / "report" / "report.md").read_text()
    assert "## Building heights from the maps" in md and "### Flat roofs" in md


def test_without_a_nadir_map_the_report_says_heights_were_not_measured(plane_run):
    _, results = plane_run
    assert "no nadir perspective" in json.loads((results / "heights.json").read_text())["skipped"]
    md = (results / "report" / "report.md").read_text()
    assert "Not measured: no nadir perspective" in md


def test_derived_dtm_matches_the_demo_terrain(small_run):
    """The DTM from the model against the generator's exact terrain function (independent truth)."""
    from pipeline25d.core.geotiff import read_float_geotiff
    from pipeline25d_lab.scenes.demo import terrain_height

    _, results = small_run
    dtm, grid = read_float_geotiff(results / "terrain" / "dtm.tif")
    dsm, _ = read_float_geotiff(results / "terrain" / "dsm.tif")
    xs, ys = grid.cell_centres()
    err = (dtm - terrain_height(xs, ys))[np.isfinite(dsm)]          # under buildings too (interpolated)
    assert np.sqrt(np.mean(err ** 2)) < 0.1 and np.abs(err).max() < 0.5   # roads float 0.05 m over the terrain


def test_warped_map_puts_check_points_on_the_ground(small_run):
    """Independent of the warp's own scoring: sample the final COG where check points should be."""
    from osgeo import gdal

    from pipeline25d.stages.gcps import read_csv

    _, results = small_run
    pid = "az045_el45"
    checks = [r for r in read_csv(results / "gcps" / f"{pid}.csv") if r["role"] == "check"]
    ds = gdal.Open(str(results / "maps" / f"{pid}.tif"))
    gt = ds.GetGeoTransform()
    alpha = ds.GetRasterBand(4).ReadAsArray()
    inside = [alpha[int((c["y"] - gt[3]) / gt[5]), int((c["x"] - gt[0]) / gt[1])] for c in checks]
    assert min(inside) == 255   # every check point lands on rendered (opaque) map


def _tile_mtimes(results: Path, suffix: str = ".tif") -> dict[str, int]:
    """Each render tile's mtime by "<pid>/<row>_<col>.tif": of its colour (``.tif``) or its object ids
    (``.ids.tif``)."""
    return {str(p.relative_to(results / "tiles")).replace(".ids.tif", ".tif"): p.stat().st_mtime_ns
            for p in (results / "tiles").rglob(f"*{suffix}") if (suffix == ".ids.tif") == p.name.endswith(".ids.tif")}


def test_every_map_has_an_id_map_that_agrees_with_it_and_names_the_roofs(small_run):
    """Counted here, apart from the id-map job: every opaque map pixel has an id and no transparent
    one has; every render tile's ids are where its alpha is not 0; a flat roof's centre, where each
    map shows it (displaced by its height above the DTM along the view), carries the id of its
    building (chunks/<district>/objects.json: the demo's OBJ writes one object per building, named by its id).
    The report gives the same counts and the id maps' bytes."""
    from osgeo import gdal

    from pipeline25d.core.grid import Grid
    from pipeline25d.core.raster import DTM
    from pipeline25d.geometry.camera import project_above_ground
    from pipeline25d.geometry.perspectives import Perspective

    workdir, results = small_run
    report = {p["id"]: p for p in json.loads((results / "report" / "report.json").read_text())["perspectives"]}
    for tile in (results / "tiles").rglob("*_*.ids.tif"):
        ids = gdal.Open(str(tile)).ReadAsArray()
        colour = gdal.Open(str(tile).replace(".ids.tif", ".tif"))
        alpha = colour.GetRasterBand(4).ReadAsArray()
        assert np.array_equal(ids > 0, alpha > 0), tile
    truth = json.loads((workdir / "resources" / "demo" / "truth.json").read_text())["buildings"]
    flat = [b for b in truth if b["roof"] == "flat"]
    objects = {d: json.loads((results / "chunks" / d / "objects.json").read_text()) for d in SMALL_CONFIG["inputs"]}
    centres = np.array([[*np.mean(b["footprint"], axis=0), b["eave_z"]] for b in flat])
    dtm = DTM(str(results / "terrain" / "dtm.tif"), "EPSG:25832", continuous=True)
    ground = dtm.sample(centres[:, 0], centres[:, 1])
    for pid, p in report.items():
        m, i = gdal.Open(str(results / "maps" / f"{pid}.tif")), gdal.Open(str(results / "maps" / f"{pid}.ids.tif"))
        grid = Grid.of_dataset(m)
        assert Grid.of_dataset(i) == grid and i.GetRasterBand(1).DataType == gdal.GDT_UInt32
        assert i.GetRasterBand(1).GetNoDataValue() == 0 and i.GetMetadata("IMAGE_STRUCTURE").get("LAYOUT") == "COG"
        alpha, ids = m.GetRasterBand(4).ReadAsArray(), i.ReadAsArray()
        counts = {"opaque_px": int((alpha > 0).sum()), "opaque_without_id": int(((alpha > 0) & (ids == 0)).sum()),
                  "transparent_with_id": int(((alpha == 0) & (ids != 0)).sum())}
        assert counts["opaque_without_id"] == counts["transparent_with_id"] == 0 < counts["opaque_px"], (pid, counts)
        assert {k: p["ids"][k] for k in counts} == counts
        assert p["ids"]["ids_bytes"] == (results / "maps" / f"{pid}.ids.tif").stat().st_size
        xy = project_above_ground(centres, ground, Perspective.from_id(pid))[:, :2]
        col, row = grid.colrow(xy[:, 0], xy[:, 1])
        got = ids[row.astype(int), col.astype(int)]
        want = np.array([objects[b["district"]][b["id"]] for b in flat])      # each building its own object
        # a roof may hide behind a taller building in an oblique view, never on the nadir map
        share = float(np.mean(got == want))
        assert share == 1.0 if pid == "az000_el90" else share >= 0.8, (pid, share, len(flat))
    md = (results / "report" / "report.md").read_text()
    assert "## Object ids" in md and "- id maps:" in md


def _web_tiles(results: Path) -> dict[str, tuple[int, str]]:
    """Every published web tile: ((inode, mtime), sha256) by path (a freed inode number is reused)."""
    import hashlib

    return {str(p.relative_to(results / "tms")): ((p.stat().st_ino, p.stat().st_mtime_ns),
                                                   hashlib.sha256(p.read_bytes()).hexdigest())
            for p in (results / "tms").rglob("*") if p.is_file() and not p.name.startswith(".")}


def _warp_of(results: Path, pid: str) -> tuple:
    meta = json.loads((results / "maps" / f"{pid}.json").read_text())
    return meta["method"], meta["order"], meta["n_observed"], meta["rmsd_m"]


def _tile_specs(results: Path, key: str = "spec_hash") -> dict[str, str]:
    """Each plan tile's spec hash (or ``key``: image_hash) by "<pid>/<row>_<col>.tif"."""
    out = {}
    for plan_file in (results / "plans").glob("*.json"):
        for t in json.loads(plan_file.read_text())["tiles"]:
            out[f"{plan_file.stem}/{t['row']}_{t['col']}.tif"] = t[key]
    return out


def _changed(after: dict, before: dict) -> set:
    return {k for k in after if after[k] != before.get(k)}


def test_rerun_does_nothing_and_a_changed_district_rerenders_only_its_tiles(plane_run):
    """With a given DTM. (With terrain: auto a change also moves the derived DTM within half
    the widest object of it, which on this 250 m scene touches most tiles.)"""
    workdir, results = plane_run
    assert "Nothing to be done" in snakemake(workdir, "-n").stdout
    before = _tile_mtimes(results)
    web_before = _web_tiles(results)
    warps_before = {p.stem: _warp_of(results, p.stem) for p in (results / "maps").glob("*.json")}
    lod_before = {p: p.stat().st_mtime_ns for p in (results / "lod").rglob("*.npz")}

    # Touching a district re-ingests it, but its chunks are unchanged: nothing re-renders.
    obj = workdir / "resources" / "demo" / "d3.obj"
    ids_before = _tile_mtimes(results, ".ids.tif")
    os.utime(obj)
    snakemake(workdir)
    assert _tile_mtimes(results) == before and _tile_mtimes(results, ".ids.tif") == ids_before
    assert {p: p.stat().st_mtime_ns for p in (results / "lod").rglob("*.npz")} == lod_before

    # A real change to one chunk of d3 re-renders the tiles that draw that chunk, and besides
    # them only tiles whose own image spec changed, nothing else; a tile whose GCP candidates
    # alone changed (a candidate beside the change) observes them again and keeps its image.
    specs_before, images_before = _tile_specs(results), _tile_specs(results, "image_hash")
    gcps_before = _tile_mtimes(results, ".gcps.csv")
    index = json.loads((results / "chunks" / "d3" / "index.json").read_text())
    cid, info = sorted(index["chunks"].items())[0]
    (lo, hi) = info["bounds"]
    cx, cy, top = (lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, hi[2] + 5
    with open(obj, "a") as fh:   # a small coloured triangle floating over that chunk
        fh.write(f"v {cx:.3f} {cy:.3f} {top:.3f} 1 0 0\nv {cx + 1:.3f} {cy:.3f} {top:.3f} 1 0 0\n"
                 f"v {cx:.3f} {cy + 1:.3f} {top:.3f} 1 0 0\nf -3 -2 -1\n")
    snakemake(workdir)
    after = _tile_mtimes(results)
    changed = {k for k in after if after[k] != before.get(k)}
    draws_chunk = set()
    for plan_file in (results / "plans").glob("*.json"):
        plan = json.loads(plan_file.read_text())
        for t in plan["tiles"]:
            if any(c["district"] == "d3" and c["id"] == cid for c in t["chunks"]):
                draws_chunk.add(f"{plan_file.stem}/{t['row']}_{t['col']}.tif")
    respecified = _changed(_tile_specs(results), specs_before)
    reimaged = _changed(_tile_specs(results, "image_hash"), images_before)
    assert changed == draws_chunk | reimaged, (changed - draws_chunk, reimaged)
    assert 0 < len(changed) < len(after) and reimaged <= respecified
    observed = {k.replace(".gcps.csv", ".tif") for k in _changed(_tile_mtimes(results, ".gcps.csv"), gcps_before)}
    assert observed == respecified
    # the id tiles: rendered again with their colour tiles, and no others
    ids_after = _tile_mtimes(results, ".ids.tif")
    assert set(ids_after) == set(after) and {k for k in ids_after if ids_after[k] != ids_before[k]} == changed
    for pid, warp in warps_before.items():   # an id map is made again in full only where its map's warp changed
        stats = json.loads((results / "work" / "ids" / f"{pid}.json").read_text())
        assert stats["opaque_without_id"] == stats["transparent_with_id"] == 0, (pid, stats)
        if stats["full"]:
            assert _warp_of(results, pid) != warp, pid
    # the web tiles: a pyramid is cut again in full only where its map's GCP warp changed (the
    # re-rendered tiles observe their GCPs again); elsewhere only the tiles over the change are
    # written, and a tile written again keeps its bytes where its pixels did not change
    web_after = _web_tiles(results)
    redone = {k for k, (ino, _) in web_after.items() if web_before.get(k, (None,))[0] != ino}
    differ = {k for k, (_, sha) in web_after.items() if web_before.get(k, (None, None))[1] != sha}
    assert differ and differ <= redone
    for pid, warp in warps_before.items():
        stats = json.loads((results / "work" / "tms" / f"{pid}.json").read_text())
        assert stats["web_tiles_redone"] == len({k for k in redone if k.startswith(f"{pid}/")})
        if stats["full"]:
            assert _warp_of(results, pid) != warp, pid
    # the report says what this run redid
    updates = json.loads((results / "report" / "report.json").read_text())["updates"]
    for pid, u in updates.items():
        assert u["tiles_redone"] == len({k for k in changed if k.startswith(f"{pid}/")})
        assert u["gcps_redone"] == len({k for k in respecified - changed if k.startswith(f"{pid}/")})
        assert u["web_tiles_redone"] == len({k for k in redone if k.startswith(f"{pid}/")})
        assert u["web_tiles"] == len({k for k in web_after if k.startswith(f"{pid}/")})
    assert "## Redone since the last report" in (results / "report" / "report.md").read_text()

    # A new reference plane changes every oblique tile's pixels: all re-render.
    config = yaml.safe_load((workdir / "config.yaml").read_text())
    scene = json.loads((results / "scene.json").read_text())
    (workdir / "config.yaml").write_text(yaml.safe_dump({**config, "z0": scene["z0"] + 2.0}))
    snakemake(workdir)
    manifests = [json.loads(p.read_text()) for p in (results / "tiles").glob("*/block_*.json")]
    assert manifests and all(m["rendered"] == len(m["tiles"]) for m in manifests)
    assert all(v != before.get(k) for k, v in _tile_mtimes(results).items())
    updates = json.loads((results / "report" / "report.json").read_text())["updates"]
    assert all(u["tiles_redone"] == u["tiles"] for u in updates.values())


def test_new_gcp_spacing_observes_gcps_again_and_keeps_every_image(plane_run, tmp_path, monkeypatch):
    """Another gcp.spacing moves the GCP candidates, not what any tile draws: the tiles whose
    candidates changed run their marker pass alone and keep their images (files untouched), and
    what they observe and keep is what a render of their block from nothing gives."""
    from osgeo import gdal

    from pipeline25d.stages.render_block import render_block

    workdir, results = plane_run
    images, ids, gcps = (_tile_mtimes(results, s) for s in (".tif", ".ids.tif", ".gcps.csv"))
    specs, image_specs = _tile_specs(results), _tile_specs(results, "image_hash")
    config = yaml.safe_load((workdir / "config.yaml").read_text())
    config["gcp"] = {**config["gcp"], "spacing": config["gcp"]["spacing"] * 1.5}
    (workdir / "config.yaml").write_text(yaml.safe_dump(config))
    snakemake(workdir)
    respecified = _changed(_tile_specs(results), specs)
    assert respecified and _tile_specs(results, "image_hash") == image_specs
    assert _tile_mtimes(results) == images and _tile_mtimes(results, ".ids.tif") == ids
    observed = {k.replace(".gcps.csv", ".tif") for k in _changed(_tile_mtimes(results, ".gcps.csv"), gcps)}
    assert observed == respecified
    manifests = {p: json.loads(p.read_text()) for p in (results / "tiles").glob("*/block_*.json")}
    assert sum(m["rendered"] for m in manifests.values()) == 0
    assert sum(m["gcps_only"] for m in manifests.values()) == len(respecified)
    updates = json.loads((results / "report" / "report.json").read_text())["updates"]
    assert all(u["tiles_redone"] == 0 for u in updates.values())
    assert sum(u["gcps_redone"] for u in updates.values()) == len(respecified)
    # a block of an oblique view with GCPs observed again, rendered from nothing: the same files
    path, manifest = next((p, m) for p, m in sorted(manifests.items())
                          if m["gcps_only"] and not m["perspective"].endswith("el90"))
    pid, block = manifest["perspective"], path.stem.removeprefix("block_")
    monkeypatch.chdir(workdir)                  # the plan names the DTM relative to the workflow
    fresh = render_block(results / "plans" / f"{pid}.json", block, config.get("render", {}).get("block", 4),
                         results / "lod", tmp_path, tmp_path / "block.json", objects=True, workers=1)
    assert fresh["rendered"] == len(manifest["tiles"]) and fresh["gcps_only"] == 0
    seen = 0
    for t in manifest["tiles"]:
        key = f"{t['row']}_{t['col']}"
        kept, made = results / "tiles" / pid / key, tmp_path / key
        assert Path(f"{kept}.gcps.csv").read_bytes() == Path(f"{made}.gcps.csv").read_bytes(), key
        seen += len(Path(f"{made}.gcps.csv").read_text().splitlines()) - 1
        for suffix in (".tif", ".ids.tif"):
            a, b = (gdal.Open(f"{f}{suffix}").ReadAsArray() for f in (kept, made))
            assert np.array_equal(a, b), (key, suffix)
    assert seen > 0


def test_plain_loop_reference_draws_the_same_tiles(small_run):
    """The benchmark's plain moderngl loop covers what the render jobs covered, tile by tile."""
    from osgeo import gdal

    from pipeline25d_lab.harness.render_reference import plain_loop_seconds

    _, results = small_run
    from pipeline25d.stages.plan import read_plan

    plan = read_plan(results / "plans" / "az045_el45.json")
    tiles = plan.tiles[:4]
    plain = plain_loop_seconds(results / "plans" / "az045_el45.json", results / "lod", 4, tiles)
    assert plain["tiles"] == len(tiles) and plain["per_tile_s"] > 0
    for t, cov in zip(tiles, plain["coverage"]):
        ds = gdal.Open(str(results / "tiles" / "az045_el45" / f"{t.key}.tif"))
        alpha = ds.GetRasterBand(4).ReadAsArray()
        # both render the tile's content window; shares of the whole tile (the loop draws plane-projected)
        full = plan.tile_size ** 2
        assert abs(float((alpha > 0).sum()) - cov * alpha.size) / full < 0.05, (t.row, t.col, cov)


@pytest.fixture(scope="module")
def sparse_run(tmp_path_factory):
    """The small demo city with one district moved 2.4 km east and 1.6 km north: a sparse scene."""
    inputs = {**SMALL_CONFIG["inputs"], "d3": {"path": "resources/demo/d3.obj", "offset": [2400.0, 1600.0, 0.0]}}
    return demo_run(tmp_path_factory, "sparse", inputs=inputs, perspectives=SMALL_PERSPECTIVES[:2], **NO_OBJECTS)


def test_a_sparse_scene_costs_its_content(sparse_run):
    """Two parts per map: the COG stores only their blocks, the web tiles cover only them, and
    the moved district is orthorectified like the others."""
    from osgeo import gdal

    _, results = sparse_run
    report = json.loads((results / "report" / "report.json").read_text())
    for p in report["perspectives"]:
        meta = json.loads((results / "maps" / f"{p['id']}.json").read_text())
        assert len(meta["parts"]) == 2, meta["parts"]
        ds = gdal.Open(str(results / "maps" / f"{p['id']}.tif"))
        band = ds.GetRasterBand(1)
        nx, ny = -(-ds.RasterXSize // 512), -(-ds.RasterYSize // 512)
        stored = sum(bool(int(band.GetMetadataItem(f"BLOCK_OFFSET_{i}_{j}", "TIFF") or 0))
                     for i in range(nx) for j in range(ny))
        assert stored < 0.3 * nx * ny, (stored, nx * ny)
        area = ds.RasterXSize * ds.RasterYSize * 0.25                       # m² of the map (gsd 0.5)
        parts = sum((x1 - x0) * (y1 - y0) for x0, y0, x1, y1 in meta["parts"])
        assert parts < 0.3 * area
        z17 = list((results / "tms" / p["id"] / "17").rglob("*.webp"))
        lat = (p["lonlat_bounds"][1] + p["lonlat_bounds"][3]) / 2
        tile_m = 2 * math.pi * 6378137 / 2 ** 17 * math.cos(math.radians(lat))   # ground metres per z17 tile
        # a part's window meets at most ceil(w / tile) + 1 tiles a side, and a sliver of one more
        near_parts = sum((math.ceil((x1 - x0) / tile_m) + 2) * (math.ceil((y1 - y0) / tile_m) + 2)
                         for x0, y0, x1, y1 in meta["parts"])
        whole = (math.ceil(ds.RasterXSize * 0.5 / tile_m) + 1) * (math.ceil(ds.RasterYSize * 0.5 / tile_m) + 1)
        assert 0 < len(z17) <= near_parts < whole / 3, (len(z17), near_parts, whole)   # tiles only where parts are
        assert p["rmsd_px"] is not None and p["rmsd_px"] < 0.5, p


def test_a_perspective_added_with_terrain_from_the_model_draws_no_kept_tile_again(small_run, tmp_path):
    """terrain: auto. Another perspective moves the GCP sites its views choose, but not the check
    squares' sites, which the DTM leaves out (stages.gcp_sites.select_sites): the terrain job does
    not run again, the DTM and the ground under every chunk are the same bytes, and the views
    already made observe their GCPs again but keep every tile image; the new view is rendered
    whole. (On main before this, every tile of every view was drawn again, and the terrain made
    again: its check of the work asked for took the perspectives as a parameter.)"""
    import shutil

    workdir = tmp_path / "small"
    shutil.copytree(small_run[0], workdir, symlinks=True)
    results = workdir / "results" / "small"
    kept = {name: (results / "terrain" / name).read_bytes() for name in ("dtm.tif", "grounds.json", "dtm_holdout.csv")}
    terrain_log = (results / "logs" / "terrain.log").read_text()
    images, specs = _tile_mtimes(results), _tile_specs(results)
    config = yaml.safe_load((workdir / "config.yaml").read_text())
    config["perspectives"] = [*config["perspectives"], {"azimuth": 135, "elevation": 45}]
    (workdir / "config.yaml").write_text(yaml.safe_dump(config))
    snakemake(workdir)
    assert {name: (results / "terrain" / name).read_bytes() for name in kept} == kept
    assert (results / "logs" / "terrain.log").read_text() == terrain_log
    assert len(kept["dtm_holdout.csv"].splitlines()) > 5                  # check squares were held out
    after = _tile_mtimes(results)
    assert {k: after[k] for k in images} == images                        # no kept tile drawn again
    new = {k for k in after if k.startswith("az135_el45/")}
    assert new and set(after) == set(images) | new
    respecified = _changed(_tile_specs(results), specs) - new
    manifests = [json.loads(p.read_text()) for p in (results / "tiles").glob("*/block_*.json")]
    assert sum(m["rendered"] for m in manifests) == len(new)
    assert sum(m["gcps_only"] for m in manifests) == len(respecified) > 0
