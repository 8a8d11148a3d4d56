"""The run-time/error sweep: Pareto fronts, the JSON and plot writer, variants, one tiny real sweep."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from PIL import Image

from pipeline25d_lab.harness.pareto import pareto_front
from pipeline25d_lab.harness.sweep import QUICK, Variant, build_scene, merged, nested, run_sweep, schedule, variants
from pipeline25d_lab.harness.sweep_report import DPI, FIGSIZE, OBJECTIVES, format_table, summarize, write_sweep

NAN = math.nan


@pytest.mark.parametrize("points, front", [
    ([], []),
    ([(3.0, 4.0)], [0]),
    # hand-checked: (3, 4) is dominated by (2, 3), (5, 5) by all but nothing dominates the rest
    ([(1, 5), (2, 3), (3, 4), (4, 1), (5, 5)], [0, 1, 3]),
    ([(4, 1), (1, 5), (2, 3)], [1, 2, 0]),                   # ordered by the first objective
    ([(1, 2), (1, 3)], [0]),                                  # tie on the first: the lower second wins
    ([(1, 2), (2, 2)], [0]),                                  # tie on the second: the lower first wins
    ([(1, 1), (2, 0), (1, 1)], [0, 2, 1]),                    # exact duplicates: neither dominates
    ([(2, 2), (2, 2), (1, 3)], [2, 0, 1]),
    ([(NAN, 0), (1, 1), (0, math.inf)], [1]),                 # failed measurements: on no front, dominate nothing
])
def test_pareto_front_hand_checked(points, front):
    assert pareto_front(points) == front


def test_a_tolerance_makes_differences_within_the_noise_ties():
    points = [(10.0, 1.0), (9.0, 1.0), (7.0, 1.0), (12.0, 0.5)]
    assert pareto_front(points) == [2, 3]
    assert pareto_front(points, (1.5, 0.0)) == [2, 3]                # 7 is faster than 9 by more than 1.5
    assert pareto_front(points, (2.5, 0.0)) == [2, 1, 3]            # 9 is within 2.5 of 7, 10 is not
    assert pareto_front(points, (3.5, 0.0)) == [2, 1, 0, 3]
    assert pareto_front(points, (3.5, 0.6)) == [2, 1, 0, 3]


def test_pareto_front_matches_the_definition_on_random_ties():
    rng = np.random.default_rng(1)
    for _ in range(50):
        pts = [tuple(map(float, p)) for p in rng.integers(0, 5, size=(rng.integers(1, 12), 2))]
        brute = {i for i, p in enumerate(pts)
                 if not any(q[0] <= p[0] and q[1] <= p[1] and q != p for q in pts)}
        front = pareto_front(pts)
        assert set(front) == brute and len(front) == len(brute)
        assert [pts[i][0] for i in front] == sorted(pts[i][0] for i in front)


def _row(name, factor, wall, rmsd, lod, value=None):
    return {"name": name, "factor": factor, "value": value, "wall_s": wall, "job_s": 2 * wall, "rmsd_px": rmsd,
            "rmsd_m": None if rmsd is None else rmsd * 0.25, "lod_px": lod,
            "gsd": value if factor == "gsd" else 0.25, "tiles_rendered": 4}


def test_summary_json_flags_match_pareto_front_and_the_plot_is_a_png(tmp_path):
    rows = [_row("default", "default", 60.0, 0.20, 0.40),
            _row("gsd-0.5", "gsd", 30.0, 0.25, 0.45, 0.5),
            _row("gsd-1.0", "gsd", 20.0, 0.10, 0.30, 1.0),            # dominates the defaults on both
            _row("msaa-0", "render.samples", 55.0, 0.30, 0.40, 0),
            _row("msaa-8", "render.samples", 80.0, 0.20, 0.40, 8),     # ties the defaults' errors, slower
            _row("tile-256", "tile_size", 90.0, None, 0.40, 256),     # too few check points: no RMSD
            {"name": "plane", "factor": "projection", "value": "plane", "error": "the workflow failed"}]
    summary = summarize(rows, {"name": "synthetic", "scene": "none", "cores": 2})
    write_sweep(summary, tmp_path / "s.json", tmp_path / "s.png")
    with Image.open(tmp_path / "s.png") as img:
        assert img.format == "PNG" and img.size == (round(FIGSIZE[0] * DPI), round(FIGSIZE[1] * DPI))
    data = json.loads((tmp_path / "s.json").read_text())
    # the LOD objective is in metres: px times the run's gsd (a gsd-1.0 pixel is four of the defaults')
    assert [r.get("lod_m") for r in data["variants"]] == [0.1, 0.225, 0.3, 0.1, 0.1, 0.1, None]
    for obj in OBJECTIVES:
        pts = [(r.get("wall_s", NAN), NAN if r.get(obj) is None else r[obj]) for r in data["variants"]]
        front = pareto_front(pts)
        assert data["front"][obj] == [rows[i]["name"] for i in front]
        assert [r["on_front"][obj] for r in data["variants"]] == [i in front for i in range(len(rows))]
        assert data["default_on_front"][obj] is (0 in front)
        for factor, entry in data["factors"].items():
            members = [i for i, r in enumerate(rows) if r["factor"] in (factor, "default")]
            sub = pareto_front([pts[i] for i in members])
            assert entry["default_on_front"][obj] is (0 in sub), (factor, obj)
    assert data["front"]["rmsd_m"] == ["gsd-1.0"] and not data["default_on_front"]["lod_m"]
    # MSAA does not change the LOD drawn, so the faster msaa-0 dominates the defaults there
    assert data["factors"]["render.samples"]["default_on_front"] == {"rmsd_m": True, "lod_m": False,
                                                                     "map_mad": False}    # no map error measured
    assert data["factors"]["render.samples"]["front"]["rmsd_m"] == ["msaa-0", "default"]
    table = format_table(summary)
    assert "plane        failed" in table and "within gsd: rmsd_m no, lod_m yes, map_mad no" in table


def test_the_noise_band_of_the_defaults_repeats_ties_runs_within_it():
    rows = [{**_row("default", "default", 31.0, 0.2, 0.4), "wall_runs": [30.0, 31.0, 33.0]},
            _row("tile-512", "tile_size", 29.0, 0.2, 0.4, 512),            # 2 s faster, same errors: noise
            _row("gsd-0.5", "gsd", 20.0, 0.2, 0.4, 0.5)]                     # 11 s faster: dominates
    summary = summarize(rows, {})
    assert summary["wall_noise_s"] == 3.0
    assert summary["factors"]["tile_size"]["default_on_front"]["rmsd_m"] is True
    assert summary["factors"]["gsd"]["default_on_front"]["rmsd_m"] is False
    assert summarize([{**rows[0], "wall_runs": [31.0]}, rows[1]], {})["default_on_front"]["rmsd_m"] is False
    assert "noise band (spread of the defaults' runs): 3.0 s" in format_table(summary)


def test_the_defaults_repeats_are_spread_through_the_sweep():
    plan = [Variant("default", "default")] + [Variant(f"v{k}", "f", k) for k in range(1, 7)]
    order = [(v.name, r) for v, r in schedule(plan, 3)]
    assert order == [("default", 0), ("v1", 0), ("v2", 0), ("v3", 0), ("default", 1), ("v4", 0), ("v5", 0),
                     ("v6", 0), ("default", 2)]
    assert [(v.name, r) for v, r in schedule(plan[:1], 3)] == [("default", 0), ("default", 1), ("default", 2)]
    assert [(v.name, r) for v, r in schedule(plan, 1)] == [(v.name, 0) for v in plan]
    assert [(v.name, r) for v, r in schedule(plan[1:3], 3)] == [("v1", 0), ("v2", 0)]


def test_map_error_is_the_mean_colour_difference_over_covered_pixels(tmp_path):
    from pipeline25d.core.crs import horizontal_wkt
    from pipeline25d.core.geotiff import write_rgba_geotiff
    from pipeline25d.core.grid import Grid
    from pipeline25d_lab.harness.sweep import map_error

    ref = np.zeros((40, 50, 4), np.uint8)
    ref[10:30, 10:40] = (100, 120, 140, 255)
    run = ref.copy()
    run[10:30, 10:20, :3] += 12                     # a third of the covered pixels 12 grey levels off
    run[30:32, 10:40] = (100, 120, 140, 255)        # two more rows covered (60 px, 120-ish off on average)
    grid = Grid.north_up(1000.0, 2000.0, 0.5, 50, 40)
    for name, img in (("ref", ref), ("run", run)):
        (tmp_path / name / "maps").mkdir(parents=True)
        write_rgba_geotiff(tmp_path / name / "maps" / "v.tif", img, grid, horizontal_wkt("EPSG:28992"))
    covered = 20 * 30 + 60
    expected = (200 * 12 + 60 * (100 + 120 + 140) / 3) / covered
    assert map_error(tmp_path / "run", tmp_path / "ref", ["v"]) == pytest.approx(expected, abs=1e-3)
    assert map_error(tmp_path / "ref", tmp_path / "ref", ["v"]) == 0.0
    assert map_error(tmp_path / "run", tmp_path / "ref", ["missing"]) is None


def test_variants_vary_one_factor_around_the_defaults(tmp_path):
    base = {"scene": "s", "crs": "EPSG:25832", "inputs": {"d": {"path": "x.obj"}}, "terrain": "auto"}
    names = [v.name for v in variants(QUICK, base)]
    assert names == ["default", "gsd-0.5", "lod-0.25", "lod-2", "lod-4", "msaa-0", "msaa-8", "tile-512", "tile-2048",
                     "plane", "paper"]
    moved = variants({"gsd": (0.25, 0.5), "projection": ("terrain", "plane-tps")},
                      {**base, "gsd": 0.5, "terrain": "flat"})                 # flat: projection auto is plane
    assert [(v.name, v.overrides) for v in moved[1:]] == [
        ("gsd-0.25", {"gsd": 0.25}), ("terrain", {"projection": "terrain"}),
        ("plane-tps", {"projection": "plane", "warp": {"method": "tps"}})]
    assert merged({"lod": {"max_levels": 3}, "gsd": 1}, nested("lod.max_error_px", 2)) == \
        {"lod": {"max_levels": 3, "max_error_px": 2}, "gsd": 1}


@pytest.mark.slow
def test_a_tiny_real_sweep_measures_every_variant(tmp_path):
    """Two complete runs of a small demo city, one oblique view: real figures, no timing claims."""
    base = build_scene("demo:0.25", tmp_path / "scene")
    base.update({"perspectives": [{"azimuth": 45, "elevation": 45}], "gsd": 0.5, "tile_size": 256,
                 "gcp": {"spacing": 8, "holdout": 0.3, "marker_px": 4}, "tms": {"zoom": "14-16"}})
    plan = [Variant("default", "default"), Variant("lod-2", "lod.max_error_px", 2, nested("lod.max_error_px", 2)),
            Variant("msaa-0", "render.samples", 0, nested("render.samples", 0))]
    rows = run_sweep(base, plan, tmp_path / "work", repeats=2)
    summary = summarize(rows, {"name": "tiny", "scene": "demo:0.25", "cores": 2})
    write_sweep(summary, tmp_path / "tiny.json", tmp_path / "tiny.png")
    data = json.loads((tmp_path / "tiny.json").read_text())
    for row, bound in zip(data["variants"], (0.5, 2, 0.5)):
        assert "error" not in row, row
        assert row["wall_s"] > 0 and row["job_s"] > 0 and row["tiles_rendered"] > 0
        assert math.isfinite(row["rmsd_px"]) and math.isfinite(row["rmsd_m"]) and row["rmsd_views"] == ["az045_el45"]
        assert abs(row["rmsd_m"] - row["rmsd_px"] * 0.5) < 1e-9
        assert 0 <= row["lod_px"] <= bound and row["lod_px_bound"] == bound
        assert row["maps_mb"] > 0 and row["tms_mb"] > 0
        assert 0 <= row["map_mad"] < 20         # against the reference: edges differ a little, nothing moves
    default, lod2, aliased = data["variants"]
    # the reference has the most MSAA samples the renderer allows (4 on llvmpipe: the defaults'),
    # so the defaults differ from it by their LOD alone; aliased edges and coarser levels add error
    assert default["map_mad"] <= lod2["map_mad"] and aliased["map_mad"] > default["map_mad"] + 0.05
    assert len(data["variants"][0]["wall_runs"]) == 2 and "wall_runs" not in data["variants"][1]
    assert data["wall_noise_s"] >= 0
    assert (tmp_path / "work" / "runs" / "lod-2" / "variant.json").exists()
    assert (tmp_path / "tiny.png").stat().st_size > 0


def test_a_failed_run_is_a_row_with_its_error_and_no_figures(tmp_path):
    base = {"scene": "sweep", "crs": "EPSG:25832", "inputs": {"d0": {"path": str(tmp_path / "missing.obj")}}}
    (row,) = run_sweep(base, [Variant("default", "default")], tmp_path / "work")
    assert "the workflow failed" in row["error"] and "wall_s" not in row
    assert "missing.obj" in (tmp_path / "work" / "runs" / "default" / "snakemake.log").read_text()
    summary = summarize([row], {})
    assert summary["front"] == {"rmsd_m": [], "lod_m": [], "map_mad": []}
    assert summary["default_on_front"]["rmsd_m"] is False
