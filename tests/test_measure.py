"""Measuring on a map (pipeline25d.analysis.measure): exact recovery from the camera's own projection, and the
`measure` command on the small demo city against its truth."""

from __future__ import annotations

import json
import math
import re
import subprocess
import sys

import numpy as np
import pytest
from conftest import roof_colour, vertical_edge

from pipeline25d.analysis.measure import facade_area, ground_length, measure_height, open_map, pixel_to_map
from pipeline25d.core.errors import InputFileError, MeasureError
from pipeline25d.geometry.camera import project
from pipeline25d.geometry.perspectives import Perspective

VIEWS = [Perspective(0, 45), Perspective(45, 45), Perspective(200, 30), Perspective(300, 10), Perspective(90, 80)]
BASE = np.array([691234.56, 5334567.89, 523.4])     # UTM-sized coordinates, as the demo's


def images(points: np.ndarray, p: Perspective) -> np.ndarray:
    """(n, 3) scene points -> (n, 2) map positions through the renderer's affine projection (z0 = ground)."""
    return project(points, p, BASE[2])[:, :2]


@pytest.mark.parametrize("p", VIEWS, ids=lambda p: p.id)
@pytest.mark.parametrize("h", [0.7, 12.25, 87.0])
def test_height_of_a_projected_vertical_edge_is_recovered_exactly(p, h):
    base, top = images(np.array([BASE, BASE + [0, 0, h]]), p)
    m = measure_height(base, top, p, gsd=0.25)
    assert m.height == pytest.approx(h, abs=1e-9)
    assert m.off_m == pytest.approx(0, abs=1e-9) and m.off_deg == pytest.approx(0, abs=1e-6)
    assert m.per_px == pytest.approx(0.25 * math.tan(math.radians(p.elevation)))


@pytest.mark.parametrize("p", VIEWS[1:3], ids=lambda p: p.id)
def test_a_pair_off_the_view_direction_says_by_how_much(p):
    base, top = images(np.array([BASE, BASE + [0, 0, 20.0]]), p)
    t = math.radians(p.azimuth)
    across = 1.5 * np.array([math.cos(t), -math.sin(t)])            # perpendicular to d
    m = measure_height(base, top + across, p, gsd=0.5)
    along = 20.0 / math.tan(math.radians(p.elevation))
    assert m.height == pytest.approx(20.0, abs=1e-9)
    assert m.off_m == pytest.approx(1.5, abs=1e-9)
    assert m.off_deg == pytest.approx(math.degrees(math.atan(1.5 / along)), abs=1e-6)
    assert measure_height(top, base, p, gsd=0.5).height == pytest.approx(-20.0, abs=1e-9)


def test_nadir_maps_refuse_heights_and_facades():
    nadir = Perspective(0, 90)
    with pytest.raises(MeasureError, match="nadir"):
        measure_height(BASE[:2], BASE[:2] + 1, nadir, gsd=0.5)
    with pytest.raises(MeasureError, match="nadir"):
        facade_area(np.array([[0, 0], [1, 0], [1, 1]]), nadir)


def facade(bearing_deg: float, width: float, outline: list[tuple[float, float]]) -> np.ndarray:
    """(n, 3) scene points of a vertical facade through BASE running along ``bearing_deg``; the outline
    in facade coordinates (s along the facade, z up), first edge along its base."""
    b = math.radians(bearing_deg)
    e = np.array([math.sin(b), math.cos(b), 0.0])
    return np.array([BASE + s * width * e + [0, 0, z] for s, z in outline])


@pytest.mark.parametrize("p", VIEWS, ids=lambda p: p.id)
@pytest.mark.parametrize("bearing", [0.0, 33.0, 90.0, 150.0])
def test_facade_area_of_a_projected_facade_is_recovered_exactly(p, bearing):
    if abs(math.sin(math.radians(bearing - p.azimuth))) < 0.05:
        pytest.skip("edge-on")
    rectangle = facade(bearing, 14.0, [(0, 0), (1, 0), (1, 9.0), (0, 9.0)])
    gable = facade(bearing, 10.0, [(0, 0), (1, 0), (1, 6.0), (0.5, 10.0), (0, 6.0)])  # 10·6 + 10·4/2
    assert facade_area(images(rectangle, p), p) == pytest.approx(14.0 * 9.0, rel=1e-9)
    assert facade_area(images(gable, p), p) == pytest.approx(80.0, rel=1e-9)


def test_a_facade_seen_edge_on_is_refused():
    p = Perspective(45, 45)
    with pytest.raises(MeasureError, match="edge-on"):
        facade_area(images(facade(45.0, 10.0, [(0, 0), (1, 0), (1, 5.0), (0, 5.0)]), p), p)


def test_ground_length_is_the_polyline_length():
    pts = BASE[:2] + np.array([[0.0, 0.0], [3.0, 4.0], [3.0, 14.0]])
    assert ground_length(pts) == pytest.approx(15.0, abs=1e-9)
    with pytest.raises(MeasureError):
        ground_length(pts[:1])


def write_map(path, geotransform=(691000.0, 0.5, 0.0, 5334300.0, 0.0, -0.5)) -> None:
    from osgeo import gdal

    ds = gdal.GetDriverByName("GTiff").Create(str(path), 8, 6, 4, gdal.GDT_Byte)
    ds.SetGeoTransform(geotransform)
    ds = None


def test_open_map_reads_the_perspective_from_the_name_or_the_json_beside_it(tmp_path):
    write_map(tmp_path / "az120_el30.tif")
    info = open_map(tmp_path / "az120_el30.tif")
    assert info.perspective == Perspective(120, 30) and info.gsd == 0.5
    np.testing.assert_array_equal(pixel_to_map(info, [[0, 0], [2, 4.5]]), [[691000.0, 5334300.0],
                                                                         [691001.0, 5334297.75]])
    write_map(tmp_path / "custom.tif")
    (tmp_path / "custom.json").write_text(json.dumps({"perspective": {"id": "az300_el60"}}))
    assert open_map(tmp_path / "custom.tif").perspective == Perspective(300, 60)
    write_map(tmp_path / "other.tif")
    with pytest.raises(InputFileError, match=r"other\.tif.*no perspective"):
        open_map(tmp_path / "other.tif")
    write_map(tmp_path / "az010_el45.tif", (0.0, 0.5, 0.1, 0.0, 0.0, -0.5))
    with pytest.raises(InputFileError, match="north-up"):
        open_map(tmp_path / "az010_el45.tif")


# --------------------------------------------------------------------------- on the demo city

def measure_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "pipeline25d", "measure", *map(str, args)],
                          capture_output=True, text=True)


def roof_on_map(results, building: dict, p: Perspective) -> np.ndarray | None:
    """Map position of the building's roof centroid on the oblique map: the centroid of the pixels of the
    roof's nadir colour connected to where its truth puts it; None when that region is not the whole roof
    (hidden in part, or merged with another roof: its area is off the footprint's by more than 8 %)."""
    from osgeo import gdal
    from scipy import ndimage

    fp = np.asarray(building["footprint"], dtype=np.float64)
    centre = fp.mean(axis=0)                      # a rectangle's centroid
    area = 0.5 * abs(np.sum(fp[:, 0] * np.roll(fp[:, 1], -1) - np.roll(fp[:, 0], -1) * fp[:, 1]))
    expected = vertical_edge({**building, "footprint": [centre]}, p.azimuth, p.elevation)[1]
    oblique = gdal.Open(str(results / "maps" / f"{p.id}.tif"))
    gt = oblique.GetGeoTransform()
    rgb = oblique.ReadAsArray()[:3].astype(float)
    label, _ = ndimage.label(np.abs(rgb - roof_colour(results, building)[:, None, None]).max(axis=0) <= 12)
    here = label[int((expected[1] - gt[3]) / gt[5]), int((expected[0] - gt[0]) / gt[1])]
    rows, cols = np.nonzero(label == here)
    if not here or abs(len(rows) * gt[1] ** 2 / area - 1) > 0.08:
        return None
    return np.array([gt[0] + (cols.mean() + 0.5) * gt[1], gt[3] + (rows.mean() + 0.5) * gt[5]])


def test_measure_command_gives_a_demo_buildings_height(small_run):
    """Base: a flat-roofed building's footprint centre (ground lies at its orthographic place); top: its roof's
    centroid found on the map. Within 1 px·gsd/cot φ of the truth (eave − terrain under the centre)."""
    from pipeline25d_lab.scenes.demo import terrain_height

    workdir, results = small_run
    truth = json.loads((workdir / "resources" / "demo" / "truth.json").read_text())
    flat = sorted((b for b in truth["buildings"] if b["roof"] == "flat"), key=lambda b: -b["eave_z"])
    for pid in ("az045_el45", "az200_el30"):
        p = Perspective.from_id(pid)
        found = [(b, top) for b in flat if (top := roof_on_map(results, b, p)) is not None]
        assert len(found) >= 5, f"{pid}: only {len(found)} whole roofs are where their truth puts them"
        building, top = found[0]
        base = np.mean(building["footprint"], axis=0)
        height = building["eave_z"] - terrain_height(*base)
        cog = results / "maps" / f"{pid}.tif"
        tolerance = 0.5 * math.tan(math.radians(p.elevation))            # 1 px · gsd / cot φ
        proc = measure_cli(cog, "height", f"{base[0]},{base[1]}", f"{top[0]},{top[1]}")
        assert proc.returncode == 0, proc.stderr
        measured = float(re.search(r"height (-?[\d.]+) m", proc.stdout).group(1))
        print(f"{pid} {building['id']}: measured {measured:.3f} m, true {height:.3f} m, tolerance {tolerance:.3f} m")
        assert abs(measured - height) <= tolerance, (pid, building["id"], measured, height)
        gt = open_map(cog).grid.geotransform
        px = [f"{(q[0] - gt[0]) / gt[1]},{(q[1] - gt[3]) / gt[5]}" for q in (base, top)]
        by_pixel = measure_cli(cog, "height", *px, "--pixel").stdout
        assert float(re.search(r"height (-?[\d.]+) m", by_pixel).group(1)) == pytest.approx(measured, abs=0.006)
    proc = measure_cli(results / "maps" / "az000_el90.tif", "height", "0,0", "1,1")
    assert proc.returncode == 1 and "az000_el90.tif" in proc.stderr and "nadir" in proc.stderr
