"""Heights under a CRS measured in feet: a 2D projected CRS names no vertical unit, and its models
(New York City's buildings in EPSG:2263) write z in the unit of x and y; a scene is in metres."""

from __future__ import annotations

import numpy as np
import pytest
from osgeo import gdal, osr

from pipeline25d.core.crs import transform_points, z_unit
from pipeline25d.core.raster import DTM
from pipeline25d.formats import load_district

US_FOOT = 1200 / 3937                   # metres, by its definition
NYC_FEET = "EPSG:2263"                  # NAD83 / New York Long Island (ftUS), 2D
SCENE = "EPSG:32618"                    # WGS 84 / UTM 18N, metres
CORNER = np.array([987000.0, 200000.0])  # lower Manhattan, in feet


def test_z_of_a_2d_crs_in_feet_is_feet_and_a_vertical_crs_keeps_its_own():
    """100 ft up in EPSG:2263 is 30.48 m up in UTM, as pyproj itself makes it from the compound
    CRS whose vertical axis says US survey feet (NAVD88 height (ftUS), EPSG:6360); there and back."""
    p = np.array([[*CORNER, 100.0]])
    flat = transform_points(p, NYC_FEET, SCENE)
    stated = transform_points(p, f"{NYC_FEET}+6360", SCENE)
    assert flat[0, 2] == pytest.approx(100 * US_FOOT, abs=1e-9)
    np.testing.assert_allclose(flat, stated, atol=1e-6)
    np.testing.assert_allclose(transform_points(flat, SCENE, NYC_FEET), p, atol=1e-6)
    assert z_unit(NYC_FEET) == ("US survey foot", pytest.approx(US_FOOT))
    assert z_unit(f"{NYC_FEET}+5703")[1] == 1.0          # NAVD88 height in metres: metres
    assert transform_points(np.array([[500000.0, 4500000.0, 100.0]]), SCENE, "EPSG:4979")[0, 2] == 100.0


def test_a_building_in_feet_is_as_tall_in_the_scene_as_it_is(tmp_path):
    """A 33 ft box (10.06 m) in an OBJ whose input says EPSG:2263 is 10.06 m tall in a UTM scene,
    and as wide as it is long; the warning says the heights were taken in feet."""
    lo = np.array([*CORNER, 20.0])
    size = np.array([66.0, 66.0, 33.0])
    corners = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)]) * size + lo
    faces = [(1, 2, 4), (1, 4, 3), (5, 7, 8), (5, 8, 6), (1, 5, 6), (1, 6, 2), (3, 4, 8), (3, 8, 7),
             (1, 3, 7), (1, 7, 5), (2, 6, 8), (2, 8, 4)]
    path = tmp_path / "building.obj"
    path.write_text("".join(f"v {x} {y} {z}\n" for x, y, z in corners.tolist())
                    + "".join(f"f {a} {b} {c}\n" for a, b, c in faces))
    with pytest.warns(UserWarning, match=r"EPSG:2263 names no vertical CRS; its heights are taken in its "
                                         r"horizontal unit, the US survey foot \(0\.3048006 m\)"):
        mesh = load_district({"path": str(path), "crs": NYC_FEET}, SCENE)
    (_, _, z0), (_, _, z1) = mesh.bounds()
    assert z1 - z0 == pytest.approx(33 * US_FOOT, abs=1e-6)
    assert z0 == pytest.approx(20 * US_FOOT, abs=1e-6)
    v = np.concatenate([part.vertices for part in mesh.parts])[:, :2]
    diagonal = np.max(np.hypot(*(v[:, None] - v[None]).transpose(2, 0, 1)))
    assert diagonal == pytest.approx(66 * 2 ** 0.5 * US_FOOT, rel=1e-3)   # the two grids' scale factors


def test_a_dtm_in_feet_is_sampled_in_metres(tmp_path):
    """A GeoTIFF in EPSG:2263 holding 100 (feet) everywhere gives 30.48 m at a UTM point over it."""
    path = tmp_path / "dtm.tif"
    ds = gdal.GetDriverByName("GTiff").Create(str(path), 20, 20, 1, gdal.GDT_Float32)
    ds.SetGeoTransform((CORNER[0], 10.0, 0.0, CORNER[1] + 200.0, 0.0, -10.0))
    srs = osr.SpatialReference()
    srs.ImportFromEPSG(2263)
    ds.SetProjection(srs.ExportToWkt())
    ds.GetRasterBand(1).Fill(100.0)
    ds = None
    x, y, _ = transform_points(np.array([[*(CORNER + 100.0), 0.0]]), NYC_FEET, SCENE)[0]
    assert DTM(path, SCENE).sample(np.array([x]), np.array([y]))[0] == pytest.approx(100 * US_FOOT, abs=1e-9)
