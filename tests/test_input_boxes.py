"""An input's box before it is read (formats.boxes, for the work estimate at parse time), checked
against the box of what the format's own reader reads from the same file."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import shared_file

from pipeline25d.formats import load_district
from pipeline25d.formats.boxes import input_box
from pipeline25d.stages.extent import cheap_extent
from pipeline25d_lab.scenes.building_city import boxes, write_cityjson
from pipeline25d_lab.scenes.citygml_city import write_city

REPO = Path(__file__).resolve().parents[1]
SAMPLES = Path(__file__).resolve().parents[2] / "shared" / "data" / "3dtiles-samples"


def read_box(spec: dict, scene_crs: str, **kw) -> np.ndarray:
    """The box of the vertices the format's reader returns, in ``scene_crs``."""
    mesh = load_district(spec, scene_crs, **kw)
    v = np.concatenate([p.vertices for p in mesh.parts])
    return np.array([v.min(axis=0), v.max(axis=0)])


def scene_box(spec: dict, scene_crs: str, base: Path) -> tuple[np.ndarray, str]:
    extent, source = cheap_extent({"crs": scene_crs, "inputs": {"a": spec}}, base / "results", base)
    return extent, source


@pytest.mark.parametrize("binary", [True, False])
def test_a_ply_box_is_its_vertices_box(tmp_path, binary):
    from plyfile import PlyData, PlyElement

    rng = np.random.default_rng(3)
    v = rng.uniform([500_000, 5_700_000, 10], [500_400, 5_700_300, 60], (50, 3))
    vertex = np.array([(*p, 200, 10, 10) for p in v],
                      dtype=[("x", "f8"), ("y", "f8"), ("z", "f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    face = np.array([([0, k, k + 1],) for k in range(1, 49)], dtype=[("vertex_indices", "i4", (3,))])
    PlyData([PlyElement.describe(vertex, "vertex"), PlyElement.describe(face, "face")],
            text=not binary).write(str(tmp_path / "m.ply"))
    spec = {"path": "m.ply", "offset": [1.0, 2.0, 3.0]}
    box = input_box(spec, tmp_path)
    assert box.source == "the PLY vertices" and box.crs is None
    np.testing.assert_allclose(box.corners, read_box({"path": str(tmp_path / "m.ply"), "offset": [1, 2, 3]},
                                                     "EPSG:25832"), rtol=0, atol=1e-5)


def test_a_cityjson_box_is_its_vertices_box_in_the_scene_crs(tmp_path):
    write_cityjson(tmp_path / "c.json", boxes([(84_000.0, 446_000.0), (85_500.0, 447_000.0)]))   # EPSG:28992
    spec = {"path": "c.json"}
    extent, source = scene_box(spec, "EPSG:28992", tmp_path)
    assert source == "the CityJSON vertices"
    np.testing.assert_allclose(extent, read_box({"path": str(tmp_path / "c.json")}, "EPSG:28992"), atol=1e-6)
    # another scene CRS (grids turned about 1.3° apart): the box's points taken there hold the
    # reprojected vertices, and pass them by no more than the turn makes of a 1.5 km box
    extent, _ = scene_box(spec, "EPSG:32631", tmp_path)
    truth = read_box({"path": str(tmp_path / "c.json")}, "EPSG:32631")
    assert (extent[0] <= truth[0] + 1e-6).all() and (extent[1] >= truth[1] - 1e-6).all()
    assert np.abs(extent - truth)[:, :2].max() < 1500 * np.sin(np.radians(1.5))


@pytest.mark.parametrize("crs", ["EPSG:25832", "EPSG:6697"])
def test_a_citygml_box_is_its_envelope_in_its_axis_order(tmp_path, crs):
    """EPSG:6697 (JGD2011, PLATEAU) lists latitude first: the envelope is swapped as the reader swaps vertices."""
    write_city(tmp_path, crs=crs, grid=(2, 2), ade=True)
    spec = {"path": "city.gml"}
    box = input_box(spec, tmp_path)
    assert box.source == "the CityGML envelope" and box.crs == crs
    scene = {"EPSG:25832": "EPSG:25832", "EPSG:6697": "EPSG:6677"}[crs]      # Munich, Tokyo
    extent, _ = scene_box(spec, scene, tmp_path)
    truth = read_box({"path": str(tmp_path / "city.gml")}, scene)
    assert (extent[0] <= truth[0] + 1e-3).all() and (extent[1] >= truth[1] - 1e-3).all()
    assert np.abs(extent - truth)[:, :2].max() < 5.0          # the writer's envelope is the lots' box


def test_a_citygml_without_an_envelope_is_not_boxed(tmp_path):
    write_city(tmp_path, grid=(1, 1))
    gml = tmp_path / "city.gml"
    text = gml.read_text()
    start, end = text.index("<gml:boundedBy>"), text.index("</gml:boundedBy>") + len("</gml:boundedBy>")
    gml.write_text(text[:start] + text[end:])
    assert input_box({"path": "city.gml"}, tmp_path) is None


@pytest.mark.parametrize("sample, volume", [("TilesetWithTransforms", "box"), ("TilesetUniform", "region")])
def test_a_tileset_box_holds_its_content(sample, volume):
    path = SAMPLES / sample / "tileset.json"
    shared_file(path)
    assert volume in json.loads(path.read_text())["root"]["boundingVolume"]
    scene = "EPSG:4978"
    extent, source = scene_box({"path": str(path)}, scene, Path("/"))
    assert source.startswith("the tileset's root bounding")
    truth = read_box({"path": str(path)}, scene, max_geometric_error=0.0)
    assert (extent[0, :2] <= truth[0, :2] + 1e-3).all() and (extent[1, :2] >= truth[1, :2] - 1e-3).all()
    assert (np.ptp(extent[:, :2], axis=0) < 1.5 * np.ptp(truth[:, :2], axis=0) + 30).all()


@pytest.mark.skipif(shutil.which("osgconv") is None, reason="no osgconv (apt-get install openscenegraph)")
def test_an_osgb_dataset_box_is_its_end_tiles_coarsest_level(tmp_path):
    from pipeline25d_lab.scenes.osgb_sample import generate_osgb_sample

    generate_osgb_sample(tmp_path / "ds")
    box = input_box({"path": "ds"}, tmp_path)
    assert box is not None and box.crs == "EPSG:32650"
    truth = read_box({"path": str(tmp_path / "ds")}, "EPSG:32650", gsd=1.0)
    np.testing.assert_allclose(box.corners[:, :2], truth[:, :2], atol=1e-3)    # the coarse level spans the tile


def test_formats_without_a_cheap_box_leave_the_extent_unknown(tmp_path):
    (tmp_path / "m.glb").write_bytes(b"glTF")
    (tmp_path / "bad.json").write_text('{"type": "CityJSON", "vertices": [[0, 0, 0]]}')   # no CityObjects
    for name in ("m.glb", "bad.json", "missing.obj"):
        assert cheap_extent({"crs": "EPSG:25832", "inputs": {"a": {"path": name}}}, tmp_path / "r", tmp_path) is None


@pytest.mark.parametrize("fmt", ["cityjson", "3dtiles"])
def test_a_gsd_typo_on_a_city_model_is_refused_by_a_dry_run(tmp_path, fmt):
    """The gsd typo of issue 27 on inputs other than OBJ: ``snakemake -n`` stops at parse time with the
    estimate from the input's own box, exit status 1, one line, no traceback."""
    if fmt == "cityjson":
        write_cityjson(tmp_path / "city.json", boxes([(84_000.0, 446_000.0), (84_200.0, 446_100.0)]))
        inputs, crs = {"a": {"path": "city.json"}}, "EPSG:28992"
    else:
        path = SAMPLES / "TilesetWithTransforms" / "tileset.json"
        shared_file(path)
        inputs, crs = {"a": {"path": str(path)}}, "EPSG:32618"     # UTM 18N: the samples lie near lon -75.6
    config = {"scene": "typo", "crs": crs, "inputs": inputs, "gsd": 0.00001}
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(config))
    cmd = [sys.executable, "-m", "snakemake", "--snakefile", str(REPO / "Snakefile"), "--directory", str(tmp_path),
           "--configfile", str(tmp_path / "config.yaml"), "-n"]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 1, proc.stderr[-2000:]
    line = next(ln for ln in proc.stderr.splitlines() if ln.startswith("pipeline25d: error: "))
    assert "config key limits.max_map_pixels: gsd 1e-05 m" in line and "scene extent from the" in line, line
    assert "Traceback" not in proc.stderr + proc.stdout and not (tmp_path / "results").exists()


def test_a_y_up_obj_is_turned_z_up_by_the_reader_and_the_box(tmp_path):
    """``up_axis: y`` (an OBJ from a modelling tool): the model, and the box the run plans from
    before ingest, are those of the same model written z-up; the faces keep their winding (a
    rotation). On a glTF, which is y-up by its specification, the key is an error."""
    from pipeline25d.core.errors import ConfigError

    z_up = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 1.0], [10.0, 8.0, 2.0], [0.0, 8.0, 12.0]])
    faces = "f 1 2 3\nf 1 3 4\n"
    (tmp_path / "z.obj").write_text("".join(f"v {x} {y} {z}\n" for x, y, z in z_up) + faces)
    (tmp_path / "y.obj").write_text("".join(f"v {x} {z} {-y}\n" for x, y, z in z_up) + faces)
    offset = [85000.0, 447000.0, 0.0]
    want = load_district({"path": str(tmp_path / "z.obj"), "offset": offset}, "EPSG:28992")
    got = load_district({"path": str(tmp_path / "y.obj"), "offset": offset, "up_axis": "y"}, "EPSG:28992")
    np.testing.assert_allclose(got.parts[0].vertices, want.parts[0].vertices, atol=1e-9)
    np.testing.assert_array_equal(got.parts[0].faces, want.parts[0].faces)
    box = input_box({"path": str(tmp_path / "y.obj"), "offset": offset, "up_axis": "y"})
    np.testing.assert_allclose(box.corners, [z_up.min(axis=0) + offset, z_up.max(axis=0) + offset])
    (tmp_path / "m.glb").write_bytes(b"glTF")                 # refused before it is read
    with pytest.raises(ConfigError, match="up_axis applies to obj, ply, dae, 3ds files, not glb"):
        load_district({"path": str(tmp_path / "m.glb"), "up_axis": "y"}, "EPSG:28992")


@pytest.mark.parametrize("end", ["\n", "\r"], ids=["lf", "cr"])
def test_an_indented_obj_with_tabs_has_the_box_of_its_model(tmp_path, end):
    """The box the run plans from before ingest reads an OBJ's vertices as the reader does: on
    indented lines, between tabs, after a byte order mark, with lines ended by CR alone."""
    xyz = np.array([[85000.5, 447000.25, 1.0], [85010.0, 447000.0, 3.5], [85010.0, 447008.0, -2.0]])
    text = "\ufeff" + "".join(f"  v\t{x}\t{y} {z}{end}" for x, y, z in xyz) + f"\tf 1 2 3{end}"
    (tmp_path / "m.obj").write_bytes(text.encode())
    spec = {"path": str(tmp_path / "m.obj")}
    np.testing.assert_array_equal(input_box(spec).corners, [xyz.min(axis=0), xyz.max(axis=0)])
    np.testing.assert_array_equal(load_district(spec, "EPSG:28992").parts[0].vertices, xyz)

