"""The workflow's heights step: what it measures against what (footprints, references, basis), its statistics."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from pipeline25d.analysis.ground_under import dsm_roof, dtm_under
from pipeline25d.analysis.height_sources import demo_truths, group_stats, plan, truth_buildings
from pipeline25d.analysis.heights.results import HeightRow
from pipeline25d.formats.footprints import Footprint


def _row(bid: str, combined: float, **views: float) -> HeightRow:
    return HeightRow(bid, dict(views), {k: 1.0 for k in views}, {k: "" if np.isfinite(v) else "hidden"
                                                                  for k, v in views.items()},
                     0, 0, combined, 0.0)


def test_group_stats_against_hand_computed_numbers():
    nan = math.nan
    rows = [_row("a", 10.2, v1=10.2, v2=10.5), _row("b", 4.9, v1=4.9, v2=nan), _row("c", nan, v1=nan, v2=nan),
            _row("d", 7.0, v1=6.6, v2=7.0), _row("x", 3.0, v1=3.0, v2=3.0)]
    ref = {"a": 10.0, "b": 5.0, "c": 8.0, "d": 7.4}            # x has no reference: not in the group
    st = group_stats(rows, ref, ["v1", "v2"])
    # combined errors: +0.2, -0.1, -0.4 -> bias -0.1, rmsd sqrt(0.21/3), median |e| 0.2, p90 |e| 0.2 + 0.8·0.2
    c = st["combined"]
    assert (c["n_footprints"], c["n_measured"], c["n"]) == (4, 3, 3)
    assert c["bias"] == pytest.approx(-0.1, abs=1e-4) and c["rmsd"] == pytest.approx(math.sqrt(0.21 / 3), abs=1e-4)
    assert c["median_abs"] == pytest.approx(0.2, abs=1e-4) and c["p90_abs"] == pytest.approx(0.36, abs=1e-4)
    # v2 errors: +0.5, -0.4 -> bias 0.05, rmsd sqrt(0.41/2); b and c not measured there
    v2 = st["v2"]
    assert (v2["n_footprints"], v2["n_measured"], v2["n"]) == (4, 2, 2)
    assert v2["bias"] == pytest.approx(0.05, abs=1e-4) and v2["rmsd"] == pytest.approx(math.sqrt(0.41 / 2), abs=1e-4)
    empty = group_stats(rows, {"c": 8.0}, ["v1"])["v1"]
    assert empty["n_measured"] == 0 and empty["n"] == 0 and empty["rmsd"] is None


def test_ground_under_and_dsm_roof_on_analytic_surfaces():
    # a linear ground averages to its value at the centroid of a rectangle (grid symmetric about it)
    fp = Footprint("r", (np.array([[100.0, 200.0], [110.0, 200.0], [110.0, 206.0], [100.0, 206.0]]),))
    ground = lambda x, y: 3.0 + 0.02 * (x - 100.0) - 0.05 * (y - 200.0)  # noqa: E731
    assert dtm_under(fp, ground, 0.25) == pytest.approx(3.0 + 0.02 * 5.0 - 0.05 * 3.0, abs=1e-12)
    # a triangle: the centroid of its vertices, to the grid's resolution
    tri = Footprint("t", (np.array([[0.0, 0.0], [12.0, 0.0], [0.0, 9.0]]),))
    assert dtm_under(tri, lambda x, y: 2.0 * x + y, 0.05) == pytest.approx(2.0 * 4.0 + 3.0, abs=0.05)
    # DSM: a roof at 14 m with a 1-cell rim at the ground (mixed cells) -> the roof, not the mean
    dsm = lambda x, y: np.where((x > 100.5) & (x < 109.5) & (y > 200.5) & (y < 205.5), 14.0, 3.0)  # noqa: E731
    assert dsm_roof(fp, dsm, 0.5) == 14.0


def _demo_dir(tmp_path: Path, offset=None) -> tuple[dict, Path]:
    from pipeline25d_lab.scenes.demo import generate_demo_city

    generate_demo_city(tmp_path / "demo", seed=3, n_buildings=12, scale=0.3)
    inputs = {f"d{i}": {"path": str(tmp_path / "demo" / f"d{i}.obj")} for i in range(3)}
    if offset:
        inputs["d0"]["offset"] = offset
    return {"scene": "t", "crs": "EPSG:25832", "inputs": inputs, "perspectives": "four-45+nadir",
            "heights": {"footprints": "auto", "reference": "auto"}}, tmp_path / "demo" / "truth.json"


def test_plan_finds_the_demo_truth_and_says_why_it_skips(tmp_path):
    config, truth = _demo_dir(tmp_path)
    p = plan(config)
    assert p["skip"] is None and p["footprints"] == {"source": "truth", "paths": [str(truth)]}
    assert p["files"] == [str(truth)] and demo_truths(config) == [truth]
    assert "no nadir perspective" in plan({**config, "perspectives": [{"azimuth": 45, "elevation": 45}]})["skip"]
    assert plan({**config, "heights": {"footprints": "none"}})["skip"] == "heights.footprints is none"
    (truth.parent / "manifest.json").unlink()                     # an OBJ the model knows nothing about
    assert "no footprints" in plan(config)["skip"]
    p = plan({**config, "heights": {"footprints": "fp.gpkg", "id_field": "gid", "reference": "ref.csv"}})
    assert p["footprints"]["source"] == "layer" and p["reference"] == {"source": "csv", "path": "ref.csv"}
    assert p["files"] == ["fp.gpkg", "ref.csv"]


def test_truth_buildings_follow_the_inputs_and_their_offset(tmp_path):
    from pipeline25d_lab.scenes.demo import terrain_height

    config, truth_path = _demo_dir(tmp_path, offset=[1000.0, -500.0, 2.0])
    truth = json.loads(truth_path.read_text())
    got = truth_buildings(truth_path, config, "EPSG:25832")
    wanted = [b for b in truth["buildings"] if b["district"] in ("d0", "d1", "d2")]
    assert set(got) == {b["id"] for b in wanted} and len(got) < len(truth["buildings"])   # d3 is no input
    for b in wanted:
        g = got[b["id"]]
        shift = np.array([1000.0, -500.0]) if b["district"] == "d0" else np.zeros(2)
        np.testing.assert_allclose(g.footprint.rings[0], np.asarray(b["footprint"]) + shift, atol=1e-9)
        dz = 2.0 if b["district"] == "d0" else 0.0
        assert (g.roof_z, g.ridge_z, g.kind) == (b["eave_z"] + dz, b["ridge_z"] + dz, b["roof"])
        # own ground: the analytic terrain under the outline (its centroid's value on this gentle relief)
        assert g.own_ground_z - dz == pytest.approx(terrain_height(*np.mean(b["footprint"], axis=0)), abs=0.02)


def test_cityjson_buildings_footprint_roof_and_ground(tmp_path):
    from pipeline25d.formats.cityjson_buildings import cityjson_buildings

    # an L-shaped LOD1 solid (no semantics, ground at 1, roof at 9) and a box with semantics
    # whose roof is split 6 m² at 12 and 2 m² at 16 (a step): roof z 13 by area seen from above
    lv = [[0, 0, 1], [6, 0, 1], [6, 2, 1], [2, 2, 1], [2, 5, 1], [0, 5, 1]]
    lv += [[x, y, 9] for x, y, _ in lv]
    l_shell = [[[5, 4, 3, 2, 1, 0]], [[6, 7, 8, 9, 10, 11]]] + [[[i, (i + 1) % 6, (i + 1) % 6 + 6, i + 6]]
                                                                 for i in range(6)]
    o = 12
    bv = [[20, 0, 2], [24, 0, 2], [24, 2, 2], [20, 2, 2], [20, 0, 12], [23, 0, 12], [23, 2, 12], [20, 2, 12],
          [23, 0, 16], [24, 0, 16], [24, 2, 16], [23, 2, 16]]
    b_shell = [[[o + 0, o + 3, o + 2, o + 1]], [[o + 4, o + 5, o + 6, o + 7]], [[o + 8, o + 9, o + 10, o + 11]]]
    sem = {"surfaces": [{"type": "GroundSurface"}, {"type": "RoofSurface"}], "values": [[0, 1, 1]]}
    objects = {"L": {"type": "Building", "geometry": [{"type": "Solid", "lod": "1", "boundaries": [l_shell]}]},
               "B": {"type": "Building", "children": ["Bp"]},
               "Bp": {"type": "BuildingPart", "parents": ["B"],
                      "geometry": [{"type": "Solid", "lod": "2", "boundaries": [b_shell], "semantics": sem}]}}
    doc = {"type": "CityJSON", "version": "2.0", "transform": {"scale": [1, 1, 1], "translate": [85000, 447000, 0]},
           "metadata": {"referenceSystem": "https://www.opengis.net/def/crs/EPSG/0/7415"},
           "CityObjects": objects, "vertices": lv + bv}
    path = tmp_path / "b.city.json"
    path.write_text(json.dumps(doc))
    got = cityjson_buildings(path, "EPSG:28992", offset=[10.0, 0.0, 0.5])
    assert set(got) == {"L", "B"}

    def area(ring):
        x, y = ring[:, 0], ring[:, 1]
        return 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))

    (ring,) = got["L"].footprint.rings
    assert area(ring) == pytest.approx(6 * 2 + 2 * 3, abs=1e-6)
    assert ring[:, 0].min() == pytest.approx(85010.0) and ring[:, 1].max() == pytest.approx(447005.0)
    assert got["L"].roof_z == pytest.approx(9.5) and got["L"].own_ground_z == pytest.approx(1.5)
    (ring,) = got["B"].footprint.rings
    assert area(ring) == pytest.approx(8.0, abs=1e-6)
    assert got["B"].roof_z == pytest.approx((6 * 12 + 2 * 16) / 8 + 0.5) and got["B"].own_ground_z == pytest.approx(2.5)


def test_reference_auto_falls_back_to_the_dsm_and_puts_it_on_the_maps_ground(tmp_path):
    """A model that knows no buildings (a PLY): the reference is the DSM's median inside each footprint
    minus the maps' ground under it; a CSV reference is taken as heights above that ground."""
    from pipeline25d.analysis.height_sources import reference_heights
    from pipeline25d.core.crs import horizontal_wkt
    from pipeline25d.core.geotiff import write_float_geotiff
    from pipeline25d.core.grid import Grid

    grid = Grid.north_up(1000.0, 2040.0, 0.5, 80, 80)                       # 40 m x 40 m, 0.5 m cells
    xs, ys = grid.cell_centres()
    roof = (xs > 1010) & (xs < 1020) & (ys > 2010) & (ys < 2016)
    dsm = np.where(roof, 17.0, 2.0 + 0.01 * (xs - 1000))          # a flat roof at 17 m on a gentle slope
    write_float_geotiff(tmp_path / "dsm.tif", dsm, grid, horizontal_wkt("EPSG:28992"))
    fp = Footprint("b", (np.array([[1010.0, 2010.0], [1020.0, 2010.0], [1020.0, 2016.0], [1010.0, 2016.0]]),))
    config = {"scene": "t", "crs": "EPSG:28992", "inputs": {"m": {"path": "m.ply"}}, "perspectives": "nadir"}
    p = {"footprints": {"source": "layer"}, "reference": {"source": "auto"}}
    ground = lambda x, y: 2.0 + 0.01 * (np.asarray(x) - 1000)       # noqa: E731  (the maps' DTM)
    refs, what, kind = reference_heights(p, config, [fp], {}, ground, tmp_path / "dsm.tif", 0.5)
    assert kind == "dsm" and "median inside each footprint" in what
    assert refs["b"].roof_z == 17.0 and refs["b"].roof_z - dtm_under(fp, ground, 0.5) == pytest.approx(15.0 - 0.15)
    (tmp_path / "ref.csv").write_text("id,height\nb,14.5\nother,3\n")
    refs, _, kind = reference_heights({**p, "reference": {"source": "csv", "path": str(tmp_path / "ref.csv")}},
                                      config, [fp], {}, ground, None, 0.5)
    assert kind == "csv" and set(refs) == {"b"}
    assert refs["b"].roof_z - dtm_under(fp, ground, 0.5) == pytest.approx(14.5, abs=1e-12)
