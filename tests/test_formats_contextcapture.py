"""ContextCapture metadata.xml: EPSG and ENU forms, origin parsing, bad files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pipeline25d.core.crs import check_scene_crs, transform_points
from pipeline25d.core.errors import InputFileError, UnsupportedFeatureError
from pipeline25d.formats.contextcapture import read_metadata_xml


def _xml(tmp_path: Path, body: str, name: str = "metadata.xml") -> Path:
    path = tmp_path / name
    path.write_text(f'<?xml version="1.0" encoding="utf-8"?>\n{body}\n', encoding="utf-8")
    return path


def test_epsg_with_origin(tmp_path):
    path = _xml(tmp_path, """<ModelMetadata version="1">
        <!--Spatial Reference System-->
        <SRS>EPSG:32633</SRS>
        <!--Origin in Spatial Reference System-->
        <SRSOrigin>412345.25,5012345.5,120.125</SRSOrigin>
        <Texture><ColorSource>Visible</ColorSource></Texture>
    </ModelMetadata>""")
    crs, origin = read_metadata_xml(path)
    assert crs == "EPSG:32633"
    assert origin.dtype == np.float64
    np.testing.assert_array_equal(origin, [412345.25, 5012345.5, 120.125])


def test_compound_srs_and_missing_origin(tmp_path):
    crs, origin = read_metadata_xml(_xml(tmp_path, "<ModelMetadata><SRS>EPSG:32633+5773</SRS></ModelMetadata>"))
    assert crs == "EPSG:32633+5773"
    np.testing.assert_array_equal(origin, [0, 0, 0])


def test_enu_frame(tmp_path):
    crs, origin = read_metadata_xml(_xml(tmp_path, """<ModelMetadata version="1">
        <SRS>ENU:46.5,7.25</SRS><SRSOrigin>0,0,0</SRSOrigin></ModelMetadata>"""))
    np.testing.assert_array_equal(origin, [0, 0, 0])
    check_scene_crs(crs)  # a projected CRS in metres: usable as a scene CRS
    geo = transform_points(np.array([[0.0, 0.0, 0.0], [1000.0, 0.0, 0.0], [0.0, 1000.0, 0.0]]), crs, "EPSG:4979")
    np.testing.assert_allclose(geo[0], [7.25, 46.5, 0.0], atol=1e-9)
    # 1 km east / north of the origin on the tangent plane
    assert geo[1, 0] > 7.25 and abs(geo[1, 1] - 46.5) < 1e-5
    assert geo[2, 1] > 46.5 and abs(geo[2, 0] - 7.25) < 1e-9
    back = transform_points(geo, "EPSG:4979", crs)
    np.testing.assert_allclose(back, [[0, 0, 0], [1000, 0, 0], [0, 1000, 0]], atol=1e-6)


def test_bad_files(tmp_path):
    with pytest.raises(InputFileError, match="broken.xml"):
        read_metadata_xml(_xml(tmp_path, "<ModelMetadata><SRS>EPSG:4326</SRS>", name="broken.xml"))
    with pytest.raises(InputFileError, match="SRS"):
        read_metadata_xml(_xml(tmp_path, "<ModelMetadata><SRSOrigin>1,2,3</SRSOrigin></ModelMetadata>"))
    with pytest.raises(InputFileError, match="SRSOrigin"):
        read_metadata_xml(_xml(tmp_path, "<ModelMetadata><SRS>EPSG:32633</SRS><SRSOrigin>a,b</SRSOrigin>"
                                         "</ModelMetadata>"))
    with pytest.raises(InputFileError, match="ModelMetadata"):
        read_metadata_xml(_xml(tmp_path, "<Other><SRS>EPSG:32633</SRS></Other>"))
    with pytest.raises(InputFileError, match="missing"):
        read_metadata_xml(tmp_path / "absent.xml")


def test_unsupported_srs(tmp_path):
    with pytest.raises(UnsupportedFeatureError, match="EPSG:999999"):
        read_metadata_xml(_xml(tmp_path, "<ModelMetadata><SRS>EPSG:999999</SRS></ModelMetadata>"))
    with pytest.raises(UnsupportedFeatureError, match="ENU"):
        read_metadata_xml(_xml(tmp_path, "<ModelMetadata><SRS>ENU:somewhere</SRS></ModelMetadata>"))
