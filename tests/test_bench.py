"""The benchmark scene: copies of a mesh tiled edge to edge, mirrored, winding kept."""

from __future__ import annotations

import numpy as np
import trimesh

from pipeline25d_lab.harness.bench import bench_config, make_scene


def test_mirrored_copies_meet_edge_to_edge_and_keep_facing_up(tmp_path):
    # a 10 x 5 m sloping quad, facing up, with a marker vertex near one corner
    v = np.array([[0, 0, 0], [10, 0, 1], [10, 5, 2], [0, 5, 1], [1, 1, 0.5]], float) + [1000.0, 2000.0, 0.0]
    f = np.array([[0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]])
    src = tmp_path / "src.ply"
    trimesh.Trimesh(v, f, process=False).export(src)
    districts = make_scene(tmp_path / "scene", 2, 2, source=src)
    assert sorted(districts) == ["d00-00", "d00-01", "d01-00", "d01-01"]
    meshes = {k: trimesh.load(p, process=False) for k, p in districts.items()}
    for k, m in meshes.items():
        assert (m.face_normals[:, 2] > 0).all(), k                           # mirroring kept the winding
    lo = {k: m.bounds[0][:2] for k, m in meshes.items()}
    np.testing.assert_allclose(lo["d01-00"] - lo["d00-00"], [10, 0])        # edge to edge
    np.testing.assert_allclose(lo["d00-01"] - lo["d00-00"], [0, 5])
    # the marker vertex (near the source's south-west corner) is mirrored in the odd copies
    marker = {k: m.vertices[np.argmin(np.abs(m.vertices[:, 2] - 0.5))][:2] - lo[k] for k, m in meshes.items()}
    np.testing.assert_allclose(marker["d00-00"], [1, 1])
    np.testing.assert_allclose(marker["d01-00"], [9, 1])
    np.testing.assert_allclose(marker["d01-01"], [9, 4])
    from pipeline25d.config import validate_schema

    cfg = validate_schema(bench_config("b", districts, 0.5, "nadir"))      # district names the schema accepts
    assert cfg["terrain"] == "auto" and len(cfg["inputs"]) == 4
