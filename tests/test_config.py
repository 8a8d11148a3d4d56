"""Config validation: defaults, and bad values that must stop the run naming the key or file."""

from __future__ import annotations

import copy

import pytest

from pipeline25d.config import check_semantics, validate_schema
from pipeline25d.core.errors import ConfigError, InputFileError
from pipeline25d.geometry.perspectives import Perspective, expand

BASE = {"scene": "t", "crs": "EPSG:25832", "inputs": {"a": {"path": "model.obj"}}}


def with_(**changes):
    cfg = copy.deepcopy(BASE)
    cfg.update(changes)
    return cfg


def test_three_keys_run_with_every_default_filled():
    cfg = validate_schema(copy.deepcopy(BASE))
    assert cfg["gsd"] == 0.25 and cfg["tile_size"] == 1024 and cfg["perspectives"] == "eight-45+nadir"
    assert cfg["gcp"] == {"source": "auto", "spacing": 20, "holdout": 0.2, "seed": 0, "marker_px": 6,
                          "depth_bias": 0.3, "clearance": 1.0, "max_height": 0.2, "max_roughness": 0.05,
                          "max_slope": 30, "max_float_px": 0.5}
    assert cfg["terrain"] == "auto" and cfg["projection"] == "auto"
    assert cfg["ground"] == {"resolution": "auto", "max_object_size": 100, "cloth_resolution": "auto",
                             "rigidness": 2, "class_threshold": 0.5, "cloth_iterations": 40}
    assert cfg["warp"] == {"method": "auto", "order": 3}
    assert cfg["objects"] == {"enabled": "auto"}
    assert cfg["heights"] == {"footprints": "auto", "reference": "auto", "max_height": 200, "block_size": 250}


@pytest.mark.parametrize("changes, key", [
    ({"gsdd": 1}, "gsdd"),
    ({"gsd": 0}, "gsd"),
    ({"gsd": -1}, "gsd"),
    ({"perspectives": [{"azimuth": 0, "elevation": 0}]}, "perspectives.0.elevation"),
    ({"perspectives": [{"azimuth": 0, "elevation": 91}]}, "perspectives.0.elevation"),
    ({"perspectives": [{"azimuth": 0, "elevation": 4}]}, "perspectives.0.elevation"),
    ({"perspectives": "sideways"}, "perspectives"),
    ({"warp": {"method": "magic"}}, "warp.method"),
    ({"objects": {"enabled": "yes"}}, "objects.enabled"),
    ({"heights": {"block_size": 5}}, "heights.block_size"),
    ({"heights": {"block_size": "city"}}, "heights.block_size"),
    ({"shadows": {"enabled": True, "azimuth": 360, "elevation": 30}}, "shadows.azimuth"),
    ({"shadows": {"enabled": True, "azimuth": 100, "elevation": 0}}, "shadows.elevation"),
    ({"shadows": {"enabled": True, "azimuth": 100, "elevation": 91}}, "shadows.elevation"),
    ({"shadows": {"ambient": 1.5}}, "shadows.ambient"),
    ({"shadows": {"texel_px": 0}}, "shadows.texel_px"),
    ({"shadows": {"place": {"lon": 4.3, "lat": 95}}}, "shadows.place.lat"),
    ({"shadows": {"place": {"lon": 4.3}}}, "shadows.place"),
    ({"shadows": {"sun": "bright"}}, "shadows"),
])
def test_schema_errors_name_the_key(changes, key):
    with pytest.raises(ConfigError) as err:
        validate_schema(with_(**changes))
    assert key in str(err.value)


def test_unknown_and_unprojected_crs_are_rejected(tmp_path):
    (tmp_path / "model.obj").write_text("v 0 0 0\n")
    for crs in ("EPSG:999999", "EPSG:4326"):
        cfg = validate_schema(with_(crs=crs))
        with pytest.raises(ConfigError, match="crs"):
            check_semantics(cfg, tmp_path)


def test_missing_input_file_is_named(tmp_path):
    cfg = validate_schema(copy.deepcopy(BASE))
    with pytest.raises(InputFileError) as err:
        check_semantics(cfg, tmp_path)
    assert "model.obj" in str(err.value) and "inputs.a.path" in str(err.value)


def test_perspective_presets_and_ids():
    ids = [p.id for p in expand("eight-45+nadir")]
    assert ids == [f"az{a:03d}_el45" for a in range(0, 360, 45)] + ["az000_el90"]
    assert Perspective.from_id("az135_el30") == Perspective(135, 30)
    # every nadir is the same view: one id
    assert [p.id for p in expand([{"azimuth": 90, "elevation": 90}, {"azimuth": 0, "elevation": 90}])] == ["az000_el90"]


def test_chunk_size_auto_follows_the_gsd():
    from pipeline25d.config import chunk_size

    cfg = validate_schema(copy.deepcopy(BASE))
    assert cfg["chunk_size"] == "auto" and chunk_size(cfg) == 100.0          # gsd 0.25: 400 px = 100 m
    assert chunk_size({**cfg, "gsd": 2.0}) == 800.0                           # 400 px at 2 m
    assert chunk_size({**cfg, "chunk_size": 80}) == 80.0
    with pytest.raises(ConfigError, match="chunk_size"):
        validate_schema({**copy.deepcopy(BASE), "chunk_size": "big"})


def test_shadows_are_off_by_default_and_the_sun_given_one_way():
    cfg = validate_schema(copy.deepcopy(BASE))
    assert cfg["shadows"] == {"enabled": False, "ambient": 0.5, "texel_px": 0.75}
    from pipeline25d.geometry.sun import check_sun_config

    check_sun_config({"enabled": False, "datetime": "not checked while off"})
    check_sun_config({"enabled": True, "azimuth": 135, "elevation": 40})
    check_sun_config({"enabled": True, "datetime": "2024-06-21T15:00:00+02:00"})       # place: the scene centre, later
    check_sun_config({"enabled": True, "datetime": "2024-06-21T13:00:00Z", "place": {"lon": 4.36, "lat": 52.01}})


@pytest.mark.parametrize("shadows, message", [
    ({"enabled": True}, r"shadows: .*not given: add azimuth and elevation"),
    ({"enabled": True, "azimuth": 100}, r"shadows: .*add elevation"),
    ({"enabled": True, "azimuth": 100, "elevation": 30, "datetime": "2024-06-21T15:00:00+02:00"},
     r"shadows: .*not both"),
    ({"enabled": True, "azimuth": 100, "elevation": 30, "place": {"lon": 4.3, "lat": 52.0}}, r"shadows.place"),
    ({"enabled": True, "datetime": "2024-06-21T15:00:00"}, r"shadows.datetime: .*no time zone"),
    ({"enabled": True, "datetime": "midsummer afternoon"}, r"shadows.datetime: .*no ISO 8601"),
    ({"enabled": True, "datetime": "2024-12-21T20:00:00+01:00", "place": {"lon": 4.36, "lat": 52.01}},
     r"shadows.datetime: the sun is .* below the horizon"),
])
def test_bad_shadow_settings_name_the_key(tmp_path, shadows, message):
    (tmp_path / "model.obj").write_text("v 0 0 0\n")
    cfg = validate_schema(with_(shadows=shadows))
    with pytest.raises(ConfigError, match=message):
        check_semantics(cfg, tmp_path)


# --------------------------------------------------------------------------- the work a config asks for

def _work(**changes):
    from pipeline25d.stages import budget

    cfg = validate_schema(with_(**{"gsd": 0.5, "tile_size": 256, "chunk_size": 50, "projection": "plane",
                                   "perspectives": [{"azimuth": 0, "elevation": 90}, {"azimuth": 90, "elevation": 45}],
                                   "ground": {"resolution": 2}, **changes}))
    return budget.settings(cfg)


def test_the_work_estimate_is_the_hand_count_of_pixels_tiles_chunks_and_cells():
    """A 100 × 120 m box, 30 m high, at x 1000, y 2000: the nadir map covers the box; the view from the
    east (azimuth 90, elevation 45) also the 30 m of height laid east (cot 45° = 1); tiles of 256 px
    at 0.5 m are 128 m, chunks 50 m, terrain cells 2 m."""
    from pipeline25d.stages import budget

    found = budget.estimate(_work(), [[1000.0, 2000.0, 0.0], [1100.0, 2120.0, 30.0]], "a test box")
    assert found.map_pixels == pytest.approx({"az000_el90": 200 * 240, "az090_el45": 260 * 240})
    # tile columns: [1000, 1100] and [1000, 1130] both meet 128 m cells 7 and 8; rows 15 and 16
    assert found.tiles == {"az000_el90": 2 * 2, "az090_el45": 2 * 2}
    assert found.render_jobs == 2          # 4 tiles fit one block of 4 x 4
    assert found.chunks == 2 * 3           # 50 m cells 20-21 by 40-42
    assert found.terrain_cells == 50 * 60
    assert found.total_pixels == 200 * 240 + 260 * 240


def test_a_gsd_typo_is_refused_with_the_numbers_the_key_and_the_likely_typo():
    from pipeline25d.stages import budget

    box = [[0.0, 0.0, 0.0], [100.0, 120.0, 30.0]]
    work = _work(gsd=0.00001)
    with pytest.raises(ConfigError) as err:
        budget.check(work, budget.estimate(work, box, "a test box"))
    text = str(err.value)
    pixels = (130 / 0.00001) * (120 / 0.00001)       # the oblique map, the larger one
    assert "limits.max_map_pixels" in text and "gsd 1e-05 m" in text and "100 × 120 m" in text
    assert f"{pixels:.2g} pixels" in text and "1e+10" in text and "typo" in text
    budget.check(_work(), budget.estimate(_work(), box, "a test box"))      # the same scene at 0.5 m runs
    more = _work(gsd=0.00001, limits={"max_map_pixels": 1e15, "max_tiles": 10 ** 12, "max_output_bytes": 1e20})
    budget.check(more, budget.estimate(more, box, "a test box"))             # raised limits let it through


@pytest.mark.parametrize("changes, key", [
    ({"chunk_size": 1}, "limits.max_chunks"),
    ({"ground": {"resolution": 0.01}}, "limits.max_terrain_cells"),
    ({"tile_size": 64, "gsd": 0.05}, "limits.max_tiles"),
])
def test_each_limit_names_its_key(changes, key):
    from pipeline25d.stages import budget

    work = _work(**changes)
    box = [[0.0, 0.0, 0.0], [2000.0, 2000.0, 30.0]]
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        budget.check(work, budget.estimate(work, box, "a test box"))


@pytest.mark.parametrize("changes, key", [
    ({"chunk_size": 0.5}, "chunk_size"),
    ({"ground": {"resolution": 0.001}}, "ground.resolution"),
    ({"tms": {"zoom": "14-25"}}, "tms.zoom"),
    ({"perspectives": [{"azimuth": a, "elevation": 45} for a in range(73)]}, "perspectives"),
    ({"perspectives": [{"azimuth": 0, "elevation": 45}] * 2}, "perspectives"),
    ({"limits": {"max_map_pixels": 0}}, "limits.max_map_pixels"),
    ({"limits": {"max_pixels": 1}}, "limits"),
])
def test_values_that_would_exhaust_the_machine_are_schema_errors(changes, key):
    with pytest.raises(ConfigError) as err:
        validate_schema(with_(**changes))
    assert key in str(err.value)


def test_the_bytes_estimate_is_every_rendered_and_published_pixel_at_four_bytes():
    from pipeline25d.stages import budget

    box = [[0.0, 0.0, 0.0], [100.0, 120.0, 30.0]]
    work = _work()
    found = budget.estimate(work, box, "a test box")
    rendered = sum(found.tiles.values()) * work["tile_size"] ** 2
    # colour and object ids (both 4 bytes a pixel) of every tile and map, and the web pyramid
    assert found.output_bytes == pytest.approx(4 * (2 * rendered + found.total_pixels * (2 + 4 / 3)))
    colour_only = budget.estimate(_work(objects={"enabled": False}), box, "a test box")
    assert colour_only.output_bytes == pytest.approx(4 * (rendered + found.total_pixels * (1 + 4 / 3)))
    assert f"at most {found.output_bytes / 1e9:.3g} GB written" in found.summary()
    tight = _work(limits={"max_output_bytes": found.output_bytes / 2})
    with pytest.raises(ConfigError, match=r"limits\.max_output_bytes: gsd 0\.5 m on a 100 × 120 m scene writes up to"):
        budget.check(tight, budget.estimate(tight, box, "a test box"))


def test_the_extent_before_ingest_is_the_obj_vertices_box_with_offset(tmp_path):
    from pipeline25d.stages.extent import cheap_extent

    (tmp_path / "a.obj").write_text("v 1 2 3\nv -4 5.5 6\nvt 0.5 0.5\nv 7 -8 9\nf 1 2 3\n")
    (tmp_path / "b.obj").write_text("v 0 0 0\nv 1 1 1\n")
    cfg = {"crs": "EPSG:25832", "inputs": {"a": {"path": "a.obj"}, "b": {"path": "b.obj", "offset": [10, 20, 30]}}}
    extent, source = cheap_extent(cfg, tmp_path / "results", tmp_path)
    assert extent.tolist() == [[-4, -8, 3], [11, 21, 31]] and source == "the OBJ vertices"
    cfg["inputs"]["c"] = {"path": "c.glb"}
    (tmp_path / "c.glb").write_bytes(b"glTF")
    assert cheap_extent(cfg, tmp_path / "results", tmp_path) is None      # a glb is not boxed


def test_a_dtm_that_is_not_a_raster_is_refused_naming_file_and_key(tmp_path):
    (tmp_path / "model.obj").write_text("v 0 0 0\n")
    (tmp_path / "dtm.tif").write_text("not a raster\n")
    cfg = validate_schema(with_(terrain="dtm.tif"))
    with pytest.raises(InputFileError, match=r"dtm\.tif: cannot open as a raster \(config key terrain\)"):
        check_semantics(cfg, tmp_path)


def test_a_side_folder_that_is_not_a_folder_is_refused_at_parse_time(tmp_path):
    """Before any job (the reader keeps the same check for callers that skip the config)."""
    (tmp_path / "model.obj").write_text("v 0 0 0\n")
    (tmp_path / "shared").mkdir()
    (tmp_path / "file.txt").write_text("x")
    ok = validate_schema(with_(inputs={"a": {"path": "model.obj", "side_folders": ["shared"]}}))
    check_semantics(ok, tmp_path)
    for k, bad in ((1, "nowhere"), (0, "file.txt")):
        folders = ["shared", bad] if k else [bad]
        cfg = validate_schema(with_(inputs={"a": {"path": "model.obj", "side_folders": folders}}))
        with pytest.raises(ConfigError, match=rf"^config key inputs\.a\.side_folders\.{k}: "
                                              rf"{tmp_path / bad} is not a folder$"):
            check_semantics(cfg, tmp_path)


def test_a_box_a_hair_short_of_a_cell_edge_does_not_reach_the_next_cell():
    """The 3D Tiles copy of a dataset came back from ECEF 1 µm west of a tile edge (226399.9999991
    for 226400): that must not add a column of tiles."""
    from pipeline25d.stages.records import index_range

    assert index_range(226399.9999991, 226655.5, 128.0) == index_range(226400.0, 226655.5, 128.0) == range(1768, 1771)
    assert index_range(0.0, 256.0000001, 128.0) == range(0, 2)
    assert index_range(-0.01, 256.01, 128.0) == range(-1, 3)          # a centimetre over is real
    assert index_range(5.0, 5.0, 128.0) == range(0, 1)
