"""COLLADA files as other exporters write them: decimal commas (3ds Max under a European locale)
and lights or cameras pycollada refuses, neither of which changes what is drawn."""

from __future__ import annotations

import re
import warnings

import numpy as np
import pytest

from pipeline25d.formats import load_district
from pipeline25d_lab.scenes.model_writers import write_dae

SCENE_CRS = "EPSG:28992"
#: a material's effect with its colours, and a light with no technique (pycollada: "Missing common technique")
EXTRAS = """ <library_lights><light id="empty"/></library_lights>
 <library_effects><effect id="e"><profile_COMMON><technique sid="t"><phong>
  <diffuse><color sid="diffuse">0.588235  0.184314 0.160784 1.000000</color></diffuse>
 </phong></technique></profile_COMMON></effect></library_effects>
 <library_geometries>"""


def _box(tmp_path, name: str):
    """A 10.25 x 4.5 x 3.75 box as a COLLADA file with :data:`EXTRAS` (decimal points)."""
    v = np.array([[x, y, z] for x in (0.0, 10.25) for y in (0.0, 4.5) for z in (0.0, 3.75)]) + [0.125, 0.5, 0.0]
    f = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                  [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    path = tmp_path / name
    write_dae(path, v, f, None)
    path.write_text(path.read_text().replace(" <library_geometries>", EXTRAS, 1))
    return path


def _read(path):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        mesh = load_district({"path": str(path), "offset": [85000.0, 447000.0, 0.0]}, SCENE_CRS)
    return mesh, [str(w.message) for w in caught]


def test_a_dae_with_decimal_commas_reads_as_the_one_with_points(tmp_path):
    """Every number of the geometry and the colours written ``10,25``: the same mesh as the file
    written ``10.25``, and a warning saying how many elements were read so; an empty light is left out."""
    points = _box(tmp_path, "points.dae")
    text = points.read_text()
    commas = re.sub(r"(<(?:float_array|color)\b[^>]*>)([^<]*)",
                    lambda m: m.group(1) + re.sub(r"(\d)\.(\d)", r"\1,\2", m.group(2)), text)
    assert commas.count(",") >= 24 and re.search(r">[^<]*\d\.\d[^<]*</float_array>", commas) is None
    (tmp_path / "commas.dae").write_text(commas)

    want, said = _read(points)
    assert said == []
    got, said = _read(tmp_path / "commas.dae")
    assert said == [f"{tmp_path / 'commas.dae'}: 2 elements of numbers are written with decimal commas (an "
                    "exporter under a European locale); they are read as decimal points"]
    assert got.n_triangles == want.n_triangles == 12
    for a, b in zip(got.parts, want.parts):
        np.testing.assert_array_equal(a.vertices, b.vertices)
        np.testing.assert_array_equal(a.faces, b.faces)
    np.testing.assert_allclose(got.bounds(), [[85000.125, 447000.5, 0.0], [85010.375, 447005.0, 3.75]])


def test_numbers_with_commas_beside_points_are_left_as_written(tmp_path):
    """A comma in an element that also holds decimal points is no decimal comma: not rewritten
    (the file then fails as pycollada finds it, naming the file)."""
    path = _box(tmp_path, "mixed.dae")
    path.write_text(path.read_text().replace('<color sid="diffuse">0.588235  0.184314',
                                             '<color sid="diffuse">0.588235,0.184314'))
    with pytest.raises(Exception, match=r"mixed\.dae: cannot read it as a DAE model"):
        _read(path)
