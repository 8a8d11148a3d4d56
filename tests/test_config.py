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
                             "rigidness": 2, "class_threshold": 0.5}
    assert cfg["warp"] == {"method": "auto", "order": 3}


@pytest.mark.parametrize("changes, key", [
    ({"gsdd": 1}, "gsdd"),
    ({"gsd": 0}, "gsd"),
    ({"gsd": -1}, "gsd"),
    ({"perspectives": [{"azimuth": 0, "elevation": 0}]}, "perspectives.0.elevation"),
    ({"perspectives": [{"azimuth": 0, "elevation": 91}]}, "perspectives.0.elevation"),
    ({"perspectives": [{"azimuth": 0, "elevation": 4}]}, "perspectives.0.elevation"),
    ({"perspectives": "sideways"}, "perspectives"),
    ({"warp": {"method": "magic"}}, "warp.method"),
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
    ({"enabled": True, "azimuth": 100, "elevation": 30, "datetime": "2024-06-21T15:00:00+02:00"}, r"shadows: .*not both"),
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
