"""The roofs test city (pipeline25d_lab.scenes.roofs_city): relief, roof kinds, roof geometry, visibility truth."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from pipeline25d_lab.scenes.roofs_city import (
    FACADE_TINT,
    RoofedBox,
    generate_roofs_city,
    roof_pieces,
    roof_visibility,
    roof_z_at,
)
from pipeline25d_lab.scenes.rugged import ROOF_CLASSES, Box, rugged_height


@pytest.fixture(scope="module")
def city(tmp_path_factory):
    out = tmp_path_factory.mktemp("roofs")
    manifest = generate_roofs_city(out, seed=2, size=300.0, relief=150.0, n_buildings=8)
    return out, manifest, json.loads((out / "truth.json").read_text())


def _box(bid: str, cx: float, cy: float, w: float, d: float, eave: float) -> Box:
    corners = np.array([[cx - w / 2, cy - d / 2], [cx + w / 2, cy - d / 2], [cx + w / 2, cy + d / 2],
                        [cx - w / 2, cy + d / 2]])
    return Box(bid, "h0", corners, 0.0, 0.0, -3.0, eave, False, "grey", "grey")


def test_relief_kinds_and_truth_per_building(city):
    out, manifest, truth = city
    assert manifest["relief_m"] >= 150.0 and truth["terrain"]["grid_relief"] >= 150.0
    kinds = {b["roof"] for b in truth["buildings"]}
    assert kinds == {"flat", "gabled", "hipped"}
    params = truth["terrain"]["params"]
    for b in truth["buildings"]:
        fp = np.array(b["footprint"])
        z = rugged_height(fp[:, 0], fp[:, 1], params)
        assert b["ground_min"] <= z.min() + 1e-2 and b["ground_max"] >= z.max() - 1e-2   # mm-rounded corners
        assert b["ground_min"] <= b["own_ground_z"] <= b["ground_max"]
        if b["roof"] == "flat":
            assert "roof_z" in b and "eave_z" not in b
        else:
            assert 2.0 <= b["ridge_z"] - b["eave_z"] <= 5.0
        assert set(b["visible"]) == set(truth["views"]) and all(0 <= v <= 1 for v in b["visible"].values())
    # a second call with the same parameters writes nothing
    before = (out / "h0.obj").stat().st_mtime_ns
    generate_roofs_city(out, seed=2, size=300.0, relief=150.0, n_buildings=8)
    assert (out / "h0.obj").stat().st_mtime_ns == before


def test_walls_share_their_roofs_tint(city):
    out, _, _ = city
    kd = {}
    name = None
    for line in (out / "h0.mtl").read_text().splitlines():
        if line.startswith("newmtl"):
            name = line.split()[1]
        elif line.startswith("Kd"):
            kd[name] = np.array([float(v) for v in line.split()[1:]])
    for c, rgb in ROOF_CLASSES.items():
        assert kd[f"wall_{c}"] == pytest.approx(np.round(FACADE_TINT * np.array(rgb), 3), abs=1e-9)
        assert np.linalg.norm(kd[f"wall_{c}"] - kd[f"roof_{c}"]) * 255 < 30       # within the matcher's tol


@pytest.mark.parametrize("kind", ["flat", "gabled", "hipped"])
def test_roof_mesh_lies_on_the_analytic_roof(kind):
    rb = RoofedBox(_box("a", 0.0, 0.0, 20.0, 10.0, 12.0), kind, 12.0 if kind == "flat" else 16.0)
    (wv, wf), (rv, rf) = roof_pieces(rb)
    rng = np.random.default_rng(1)
    for tri in rv[rf]:                               # random points on every roof triangle
        w = rng.dirichlet(np.ones(3), size=50)
        p = w @ tri
        inner = (np.abs(p[:, 0]) < 9.99) & (np.abs(p[:, 1]) < 4.99)
        assert roof_z_at(rb, p[inner, 0], p[inner, 1]) == pytest.approx(p[inner, 2], abs=1e-9)
    assert rv[:, 2].max() == rb.ridge_z and rv[:, 2].min() == 12.0
    # walls end at the eave except the gable triangles, which reach the ridge
    assert wv[:, 2].max() == (16.0 if kind == "gabled" else 12.0)
    if kind == "hipped":                             # ridge inset by half the short side at both ends
        ridge = rv[rv[:, 2] == 16.0]
        assert sorted(ridge[:, 0]) == pytest.approx([-5.0, 5.0])


def test_visibility_truth_on_flat_ground():
    params = {"origin": [0.0, 0.0], "base": 0.0, "tilt": [0.0, 0.0], "features": []}
    tall = RoofedBox(_box("tall", 0.0, 0.0, 10.0, 10.0, 40.0), "flat", 40.0)
    # 12 m east-north-east of the tall one, the side its az045 camera looks from: seen
    front = RoofedBox(_box("front", -20.0, -20.0, 6.0, 6.0, 5.0), "flat", 5.0)
    # just beyond it along az045 (north-east): hidden from az045, seen from az200
    behind = RoofedBox(_box("behind", 14.0, 14.0, 6.0, 6.0, 5.0), "flat", 5.0)
    v45 = roof_visibility([tall, front, behind], params, "az045_el45")
    v200 = roof_visibility([tall, front, behind], params, "az200_el30")
    assert v45["tall"] == 1.0 and v45["front"] == 1.0 and v45["behind"] == 0.0
    assert v200["behind"] == 1.0 and v200["tall"] == 1.0
    # independent check of the hidden one: rays from its roof towards the az045 camera rise 1 m per
    # horizontal metre and cross the tall box's footprint below its 40 m roof
    d = -np.array([math.sin(math.radians(45)), math.cos(math.radians(45))])
    t_enter = (14.0 - 3.0 - 5.0) / abs(d[0])                       # reaches x = 5 (tall's east wall)
    assert 5.0 + t_enter < 40.0
