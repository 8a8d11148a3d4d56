"""The render stage replayed from a pack (pipeline25d_lab.harness.render_replay): without GDAL or pyproj,
it draws the run's own tiles pixel for pixel and sees its GCPs where the run's
render jobs saw them."""

from __future__ import annotations

import csv
import json
import subprocess
import sys

import numpy as np

from pipeline25d_lab.harness import render_replay

NO_GDAL = ("import sys; sys.modules['osgeo'] = None; sys.modules['pyproj'] = None; "
           "from pipeline25d_lab.harness.render_replay import main; main(sys.argv[1:])")


def test_the_replay_draws_the_runs_tiles_and_gcps_without_gdal(small_run, tmp_path):
    from pipeline25d.core.raster import gdal
    from pipeline25d.stages.plan import read_plan

    workdir, results = small_run
    packed = tmp_path / "pack"
    info = render_replay.pack(results, packed, workdir)
    assert info["plans"] >= 3 and info["chunks"] > 0
    subprocess.run([sys.executable, "-c", NO_GDAL, "replay", str(packed), str(tmp_path / "out")], check=True,
                   cwd=workdir)
    report = json.loads((tmp_path / "out" / "replay.json").read_text())
    assert report["driver"]["GL_RENDERER"]
    for plan_file in sorted((results / "plans").glob("*.json")):
        pl = read_plan(plan_file)
        row = report["perspectives"][pl.id]
        assert row["tiles"] == len(pl.tiles) and row["render_s"] > 0
        drawn = np.load(tmp_path / "out" / f"{pl.id}_sample_tile.npz")["rgba"]
        assert (drawn[..., 3] > 0).mean() > 0.3
        tif = results / "tiles" / pl.id / f"{row['sample_tile']}.tif"
        assert np.array_equal(drawn.transpose(2, 0, 1), gdal().Open(str(tif)).ReadAsArray()), pl.id
        seen = json.loads((tmp_path / "out" / f"{pl.id}_gcps.json").read_text())
        run_seen = {}
        for t in pl.tiles:
            with open(results / "tiles" / pl.id / f"{t.row}_{t.col}.gcps.csv", newline="") as fh:
                run_seen.update({r["id"]: (float(r["map_x"]), float(r["map_y"])) for r in csv.DictReader(fh)})
        assert row["gcps_seen"] == len(run_seen) == len(seen) > 0
        for gid, (x, y) in run_seen.items():
            assert np.allclose(seen[gid], [x / pl.pixel_size, y / pl.pixel_size], atol=1e-6), gid
    same = render_replay.compare(tmp_path / "out", tmp_path / "out")
    assert all(r["tile_max_abs"] == 0 and r["gcp_max_px"] == 0 for r in same.values()), json.dumps(same)


def test_a_sample_of_a_plans_tiles_is_a_compact_block_around_its_middle():
    """A plan's tiles in row order, 4 rows of 11: four tiles taken in list order from the middle
    run from one row's end to the next row's start (10 columns apart); the sample is the four
    nearest the middle (row 1.5, column 5) instead, in the plan's order: within 2 rows and 3 columns."""
    positions = [(row, col) for row in range(4) for col in range(11)]
    mid = (len(positions) - 4) // 2
    in_order = positions[mid:mid + 4]
    assert max(c for _, c in in_order) - min(c for _, c in in_order) == 10
    keep = render_replay.middle_tiles(positions, 4)
    assert keep == sorted(keep) and len(keep) == 4
    picked = [positions[i] for i in keep]
    assert {r for r, _ in picked} == {1, 2} and {c for _, c in picked} <= {4, 5, 6}
    assert {(1, 5), (2, 5)} <= set(picked)
    assert render_replay.middle_tiles(positions, 100) == list(range(44))
