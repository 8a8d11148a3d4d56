"""The generated textured OAP3D city (tiny size): both formats through the product's readers."""

from __future__ import annotations

import io
import json
import os

import numpy as np
import pytest
from PIL import Image
from scipy.spatial import cKDTree

from pipeline25d.formats import load_district
from pipeline25d_lab.scenes.oap3d import ORIGIN, SIZES, generate_oap3d, level_of_file, levels_used
from pipeline25d_lab.scenes.oap3d_city import build_city

SPEC = SIZES["tiny"]


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    out = tmp_path_factory.mktemp("oap3d") / "tiny"
    return out, generate_oap3d(out, "tiny", seed=3)


def _load(out, manifest, fmt, gsd):
    return load_district({"path": str(out / manifest["inputs"][fmt])}, "EPSG:32650",
                         max_geometric_error=0.5 * gsd, gsd=gsd)     # lod.max_error_px 0.5, as the workflow asks


@pytest.mark.parametrize("gsd,level", [(0.5, 0), (0.25, 1), (0.15, 2)])
def test_both_formats_draw_the_same_level_and_geometry(dataset, gsd, level):
    out, manifest = dataset
    # texels 50 m / 120 px = 0.4167, 0.2083, 0.1042 m: the coarsest level whose texel is below the gsd
    assert [round(r["texel_m"], 4) for r in manifest["levels"]] == [0.4167, 0.2083, 0.1042]
    osgb, tiles = _load(out, manifest, "osgb", gsd), _load(out, manifest, "3dtiles", gsd)
    expected = 2 * 4 ** level * 2 * 12 ** 2          # tiles x nodes x 2 triangles x (2 charts x 6 cells)^2
    for mesh in (osgb, tiles):
        assert sum(p.n_triangles for p in mesh.parts) == expected
        v = np.concatenate([p.vertices for p in mesh.parts])
        np.testing.assert_allclose(v[:, :2].min(axis=0), ORIGIN[:2], atol=1e-3)
        np.testing.assert_allclose(v[:, :2].max(axis=0), (ORIGIN[0] + 100, ORIGIN[1] + 50), atol=1e-3)
        assert all(p.texture is not None for p in mesh.parts)
    a = np.concatenate([p.vertices for p in osgb.parts])
    b = np.concatenate([p.vertices for p in tiles.parts])
    dist, _ = cKDTree(b - ORIGIN).query(a - ORIGIN)
    assert dist.max() < 2e-3                          # UTM -> ECEF float32 offsets -> UTM
    # heights: the surface function sampled at the vertices (float32 in the file)
    city = build_city(100.0, 50.0, 3)
    local = a - ORIGIN
    xs, ys = np.unique(np.round(local[:, 0], 3)), np.unique(np.round(local[:, 1], 3))
    grid = city.height(xs, ys)
    z = grid[np.searchsorted(ys, np.round(local[:, 1], 3)), np.searchsorted(xs, np.round(local[:, 0], 3))]
    np.testing.assert_allclose(local[:, 2], z, atol=2e-3)


def _pixels(data: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(data)).convert("RGB"), np.float64)


def test_textures_have_detail_and_agree_between_formats(dataset):
    out, manifest = dataset
    osgb, tiles = _load(out, manifest, "osgb", 0.25), _load(out, manifest, "3dtiles", 0.25)
    for mesh in (osgb, tiles):
        for part in mesh.parts:
            img = _pixels(part.texture)
            assert img.shape == (SPEC.atlas, SPEC.atlas, 3)
            assert (img.std(axis=(0, 1)) / img.mean(axis=(0, 1))).min() > 0.1   # not flat, even on a lawn
            assert len(np.unique(img.reshape(-1, 3), axis=0)) > 500
            lap = np.abs(4 * img[1:-1, 1:-1] - img[:-2, 1:-1] - img[2:, 1:-1] - img[1:-1, :-2] - img[1:-1, 2:])
            assert lap.mean() / img.mean() > 0.03                        # detail at the texel scale
    # the same atlases: match parts by their vertex sets' centres, compare decoded pixels
    centre = {tuple(np.round(p.vertices.mean(axis=0)[:2], 1)): p for p in tiles.parts}
    for part in osgb.parts:
        other = centre[tuple(np.round(part.vertices.mean(axis=0)[:2], 1))]
        assert np.abs(_pixels(part.texture) - _pixels(other.texture)).mean() < 2.0   # two JPEG decoders


def test_texel_colour_matches_the_city_at_that_point(dataset):
    """A chart texel in the atlas, found through the mesh's UVs, shows the colour painted there."""
    out, manifest = dataset
    mesh = _load(out, manifest, "3dtiles", 0.15)
    city = build_city(100.0, 50.0, 3)
    texel = SPEC.texel(2)
    errs = []
    for part in mesh.parts[:8]:
        img = _pixels(part.texture)
        local = part.vertices - ORIGIN
        for k in range(0, len(local), 17):
            col = int(np.floor(part.uv[k, 0] * SPEC.atlas + 0.3))
            row = int(np.floor((1 - part.uv[k, 1]) * SPEC.atlas - 0.3))
            if not (0 <= col < SPEC.atlas and 0 <= row < SPEC.atlas):
                continue
            cx = local[k, 0] + (col + 0.5 - part.uv[k, 0] * SPEC.atlas) * texel
            cy = local[k, 1] - (row + 0.5 - (1 - part.uv[k, 1]) * SPEC.atlas) * texel
            want = city.paint(np.array([cx]), np.array([cy]), texel)[0, 0]
            errs.append(np.abs(img[row, col] - want).mean())
    assert len(errs) > 50 and np.median(errs) < 12                       # JPEG error, not misplacement


def test_deterministic_and_kept_while_the_manifest_matches(dataset, tmp_path):
    out, manifest = dataset
    again = generate_oap3d(tmp_path / "again", "tiny", seed=3, workers=1)      # the fixture's: one per core
    assert {k: v for k, v in again.items() if k != "generation_s"} == {k: v for k, v in manifest.items()
                                                                       if k != "generation_s"}
    files = sorted(p.relative_to(out) for p in out.rglob("*") if p.is_file() and p.name != "manifest.json")
    assert len(files) > 20
    assert files == sorted(p.relative_to(tmp_path / "again") for p in (tmp_path / "again").rglob("*")
                           if p.is_file() and p.name != "manifest.json")
    for rel in files:
        assert (out / rel).read_bytes() == (tmp_path / "again" / rel).read_bytes(), rel
    stamp = os.stat(out / "manifest.json").st_mtime_ns
    assert generate_oap3d(out, "tiny", seed=3) == manifest and os.stat(out / "manifest.json").st_mtime_ns == stamp
    other = generate_oap3d(tmp_path / "other", "tiny", seed=4)
    assert other["formats"]["osgb"]["bytes"] != manifest["formats"]["osgb"]["bytes"]
    (tmp_path / "again" / "3dtiles" / "tileset.json").unlink()        # a file gone: generated again
    assert (generate_oap3d(tmp_path / "again", "tiny", seed=3)["formats"] == manifest["formats"])


def test_levels_in_manifest_and_levels_used(dataset):
    out, manifest = dataset
    sizes = {"osgb": {}, "3dtiles": {}}
    for fmt in sizes:
        for dirpath, _, names in os.walk(out / fmt):
            for n in names:
                key = level_of_file(out / dirpath / n)
                sizes[fmt][key] = sizes[fmt].get(key, 0) + os.path.getsize(os.path.join(dirpath, n))
    for r in manifest["levels"]:
        assert r["triangles"] == 2 * 4 ** r["level"] * 288
        assert sizes["osgb"][str(r["level"])] == r["osgb_bytes"]
        assert sizes["3dtiles"][str(r["level"])] == r["3dtiles_glb_bytes"]
    used = levels_used(manifest, "osgb", 0.25)
    assert used["level"] == 1 and used["bytes"] == sizes["osgb"]["0"] + sizes["osgb"]["1"] + sizes["osgb"]["index"]
    used = levels_used(manifest, "3dtiles", 0.25)
    assert used["bytes"] == sizes["3dtiles"]["1"] + sizes["3dtiles"]["index"]
    assert json.loads((out / "3dtiles" / "tileset.json").read_text())["asset"]["version"] == "1.1"
