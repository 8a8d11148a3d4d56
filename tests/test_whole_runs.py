"""Whole workflow runs on the real-world inputs of issue 27, generated with exact truth: a CityGML
city whose buildings carry ADE elements under undeclared prefixes, and a buildings-only CityJSON
city spread over 5 x 5 km (``terrain: auto``). The OSGB dataset with missing child files runs in
tests/test_formats_osgb.py."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import held_out
from test_workflow import NO_OBJECTS, snakemake

from pipeline25d_lab.scenes import building_city as bc
from pipeline25d_lab.scenes import citygml_city as cc

ADE_VIEWS = [{"azimuth": 0, "elevation": 90}, {"azimuth": 225, "elevation": 45}]
ADE_IDS = ["az000_el90", "az225_el45"]
GSD = 0.25


def test_a_jobs_warnings_reach_its_log_and_stderr_as_one_line(tmp_path):
    """core.logsetup.log_to: a warning a reader gives inside a job is a WARNING line of the job's
    log and one 'pipeline25d: warning:' line on stderr (no source line, no traceback)."""
    script = (f"import warnings; from pipeline25d.core.logsetup import log_to\n"
              f"log_to({str(tmp_path / 'job.log')!r})\n"
              f"warnings.warn('model.gml: line 7: something recovered')\n")
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True)
    assert proc.stderr == "pipeline25d: warning: model.gml: line 7: something recovered\n"
    (line,) = (tmp_path / "job.log").read_text().splitlines()
    assert line.endswith(" WARNING pipeline25d.warnings: UserWarning: model.gml: line 7: something recovered")


def _maps(path: Path) -> tuple[np.ndarray, tuple]:
    from osgeo import gdal

    ds = gdal.Open(str(path))
    return ds.ReadAsArray().transpose(1, 2, 0), ds.GetGeoTransform()


@pytest.fixture(scope="module")
def ade_runs(tmp_path_factory) -> dict:
    """The same generated CityGML city without and with ADE attributes under undeclared prefixes,
    each run to its nadir and one oblique map: {ade: (workdir, truth, seconds)}."""
    runs = {}
    for ade in (False, True):
        workdir = tmp_path_factory.mktemp("ade" if ade else "plain")
        truth = cc.write_city(workdir / "resources", grid=(3, 3), tin_cells=6, ade=ade)
        config = {"scene": "city", "crs": "EPSG:25832", "inputs": {"city": {"path": "resources/city.gml"}},
                  "terrain": "auto", "gsd": GSD, "tile_size": 256, "perspectives": ADE_VIEWS,
                  "gcp": {"spacing": 10}, **NO_OBJECTS}
        (workdir / "config.yaml").write_text(yaml.safe_dump(config))
        t0 = time.monotonic()
        snakemake(workdir, *[f"results/city/maps/{pid}.tif" for pid in ADE_IDS])
        runs[ade] = (workdir, truth, time.monotonic() - t0)
    return runs


def test_a_citygml_city_with_undeclared_ade_prefixes_runs_to_the_maps_of_the_same_city(ade_runs):
    """The run succeeds; the ingest log warns once per undeclared prefix, naming file, line and
    element; the maps are byte for byte those of the city without ADE (the ADE elements carry no
    geometry: the same triangles reach the renderer); the nadir map covers
    exactly the city's TIN and shows the atlas's roof tiles on every house's roof (the CityGML
    tests' texture check, on the map)."""
    plain_dir, _, plain_s = ade_runs[False]
    workdir, truth, ade_s = ade_runs[True]
    print(f"CityGML city, 2 maps: {plain_s:.1f} s without ADE, {ade_s:.1f} s with")
    gml = workdir / "resources" / "city.gml"
    lines = gml.read_text(encoding="utf-8").splitlines()
    log = (workdir / "results" / "city" / "logs" / "ingest" / "city.log").read_text()
    for prefix, element in (("energy", "isHeated"), ("uro", "buildingDetails")):
        line = next(i for i, t in enumerate(lines, 1) if f"<{prefix}:" in t)
        said = [ln for ln in log.splitlines() if f"Namespace prefix {prefix} " in ln]
        assert len(said) == 1 and " WARNING " in said[0], log
        assert f"resources/city.gml: line {line}: Namespace prefix {prefix} on {element} is not defined" in said[0]
    assert " WARNING " not in (plain_dir / "results" / "city" / "logs" / "ingest" / "city.log").read_text()
    for pid in ADE_IDS:
        got, gt = _maps(workdir / "results" / "city" / "maps" / f"{pid}.tif")
        want, want_gt = _maps(plain_dir / "results" / "city" / "maps" / f"{pid}.tif")
        assert gt == want_gt and got.shape == want.shape and (got[..., 3] > 0).mean() > 0.3
        np.testing.assert_array_equal(got, want)
        # and byte for byte: the ADE elements carry no geometry, the same triangles reach the renderer
        assert (workdir / "results" / "city" / "maps" / f"{pid}.tif").read_bytes() == \
            (plain_dir / "results" / "city" / "maps" / f"{pid}.tif").read_bytes()
    rgba, (x0, dx, _, y0, _, dy) = _maps(workdir / "results" / "city" / "maps" / "az000_el90.tif")
    rows, cols = np.nonzero(rgba[..., 3])
    (ox, oy), ext = truth["tin"]["origin"], truth["tin"]["extent"]
    assert (x0 + cols.min() * dx, x0 + (cols.max() + 1) * dx) == (ox, ox + ext)
    assert (y0 + (rows.max() + 1) * dy, y0 + rows.min() * dy) == (oy, oy + ext)
    # each house's roof: the atlas's roof half (textured surfaces are drawn unlit): its tile colour
    # and, every 0.56 m (16 of its 128 texel rows), its darker tile rows, blended by the texture
    # filter; so every pixel lies between the two colours and both show. The courtyard blocks'
    # roofs are their class colour, shaded: off that line. 0.5 m inside each footprint.
    line, tile = np.array(cc.ROOF_LINE, float), np.array(cc.ROOF_RGB, float)
    W, D = cc.HOUSE["width"], cc.HOUSE["depth"]
    for kind, items in (("house", truth["houses"]), ("block", truth["blocks"])):
        for b in items:
            w, d = (W, D) if kind == "house" else (cc.BLOCK["size"], cc.BLOCK["size"])
            r0, r1 = round((b["y"] + d - 0.5 - y0) / dy), round((b["y"] + 0.5 - y0) / dy)
            c0, c1 = round((b["x"] + 0.5 - x0) / dx), round((b["x"] + w - 0.5 - x0) / dx)
            px = rgba[r0:r1, c0:c1, :3].reshape(-1, 3).astype(float)
            t = np.clip((px - line) @ (tile - line) / np.sum((tile - line) ** 2), 0, 1)
            on_atlas = np.abs(px - line - t[:, None] * (tile - line)).max(axis=1) <= 2
            if kind == "house":
                assert on_atlas.all() and (t > 0.98).mean() > 0.3 and (t < 0.8).mean() > 0.2, b["id"]
            else:
                assert not on_atlas.any(), b["id"]


@pytest.fixture(scope="module")
def sparse_run(tmp_path_factory) -> tuple[Path, list, float]:
    """The buildings-only CityJSON city (five clusters of nine boxes over 5 x 5 km on a sloped
    plane, 23 with a GroundSurface) run end to end with terrain: auto: (results, footprints, seconds)."""
    workdir = tmp_path_factory.mktemp("sparse")
    fps = bc.write_sparse_city(workdir / "city.json")
    config = {"scene": "sparse", "crs": bc.CRS, "inputs": {"city": {"path": "city.json"}}, "terrain": "auto",
              "gsd": 1.0, "tile_size": 256,
              "perspectives": [{"azimuth": 0, "elevation": 90}, {"azimuth": 45, "elevation": 45},
                               {"azimuth": 200, "elevation": 30}],
              "gcp": {"spacing": 6, "holdout": 0.4, "marker_px": 4}, "tms": {"zoom": "13-15"},
              "heights": {"footprints": "none"}, **NO_OBJECTS}
    (workdir / "config.yaml").write_text(yaml.safe_dump(config))
    t0 = time.monotonic()
    snakemake(workdir, "results/sparse/report/report.json")
    return workdir / "results" / "sparse", fps, time.monotonic() - t0


def test_a_buildings_only_city_over_5_km_runs_with_its_check_points_within_half_a_pixel(sparse_run):
    """terrain: auto takes the ground from the buildings' bases (nothing else has one); GCPs stand
    on that bare ground between the buildings (markers over an empty map); every view has check
    points, their error (the report's, and recomputed from the observations against their true
    ground position) is under 0.5 px; z0 is finite; the DTM under the buildings is the plane."""
    from pipeline25d.core.geotiff import read_float_geotiff
    from pipeline25d.stages.gcps import read_observations

    results, fps, seconds = sparse_run
    report = json.loads((results / "report" / "report.json").read_text())
    span = np.array(fps)
    assert span[:, 2].max() - span[:, 0].min() >= 5000 and span[:, 3].max() - span[:, 1].min() >= 5000
    assert report["terrain"]["bases"]["buildings_only"] == ["city"] and report["terrain"]["bases"]["buildings"] == 45
    assert report["terrain"]["bases"]["from_ground_surfaces"] == 23
    scene = json.loads((results / "scene.json").read_text())
    dsm, grid = read_float_geotiff(results / "terrain" / "dsm.tif")
    gx, gy = grid.cell_centres()
    covered = np.isfinite(dsm)
    assert np.isfinite(report["z0"]) and report["z0"] == round(float(np.median(bc.plane(gx[covered], gy[covered]))))
    for p in report["perspectives"]:
        assert p["n_check"] >= 10 and p["rmsd_px"] <= 0.5, p
        checks = [o for o in read_observations(results / "gcps" / f"{p['id']}.csv") if o.role == "check"]
        err = np.hypot([o.map_x - o.x for o in checks], [o.map_y - o.y for o in checks]) / report["gsd"]
        assert len(checks) == p["n_check"] and err.max() <= 0.5, (p["id"], err)
        assert np.sqrt(np.mean(err ** 2)) == pytest.approx(p["rmsd_px"], abs=1e-6)
        print(f"{p['id']}: {p['n_check']} check points, RMSD {p['rmsd_px']:.3f} px, max {err.max():.3f} px")
        # the bare-ground sites lie between the buildings, never on them
        inside = [any(x0 <= o.x <= x1 and y0 <= o.y <= y1 for x0, y0, x1, y1 in fps) for o in checks]
        assert not any(inside)
    # the DTM under every building: the plane, exactly (float32) where the ground heights were kept;
    # within 0.15 m inside the discs left out around check points (interpolated across, as designed)
    dtm, grid = read_float_geotiff(results / "terrain" / "dtm.tif")
    gx, gy = grid.cell_centres()
    checks = held_out(results / "terrain" / "dtm_holdout.csv", results / "gcps" / "candidates.csv")
    for x0, y0, x1, y1 in fps:
        under = (gx > x0) & (gx < x1) & (gy > y0) & (gy < y1)
        x, y, z = gx[under], gy[under], dtm[under].astype(np.float64)
        assert len(z) >= 20 and np.isfinite(z).all()
        near = np.hypot(x[:, None] - checks[:, 0], y[:, None] - checks[:, 1]).min(axis=1) \
            <= scene["dtm_check_holdout_m"] + grid.res
        np.testing.assert_allclose(z[~near], bc.plane(x[~near], y[~near]), atol=1e-3)
        np.testing.assert_allclose(z, bc.plane(x, y), atol=0.15)
    print(f"buildings-only city, 3 maps and the report: {seconds:.1f} s")
