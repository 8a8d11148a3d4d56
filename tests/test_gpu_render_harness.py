"""The render-throughput harness (pipeline25d_lab.harness.gpu_render) on a small block: it renders every
view, and the colour coverage and the object ids drawn beside it agree pixel for pixel."""

from __future__ import annotations

import json

import numpy as np

from pipeline25d_lab.harness import gpu_render


def test_every_view_is_rendered_and_ids_cover_exactly_the_coloured_pixels(gl_ctx, tmp_path):
    gpu_render.main(["--out", str(tmp_path), "--triangles", "20000", "--texture", "256",
                     "--tile", "128", "--tiles", "2"])
    result = json.loads((tmp_path / "gpu_render.json").read_text())
    assert result["tiles"] == 18 and len(result["views"]) == 9
    # ~20k triangles: the grid is the nearest square with two triangles a cell
    n = int(np.sqrt(20000 / 2)) + 1
    assert result["triangles"] == 2 * (n - 1) ** 2
    for view in result["views"]:
        assert view["covered"] > 0.9 * 2 * 128 * 128, view
        assert view["alpha_id_agree"] == 1.0, view
