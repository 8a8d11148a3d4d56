"""An OBJ's texture reaches the chunks as its own file's bytes where that is a PNG or JPEG, and as
a PNG of the same pixels otherwise (what trimesh decoded, once per image)."""

from __future__ import annotations

import io

import numpy as np
import pytest
from PIL import Image

from pipeline25d.formats.meshfile import load_mesh_file


def _textured_obj(folder, image_name: str) -> object:
    (folder / "m.mtl").write_text(f"newmtl tex\nKd 1 1 1\nmap_Kd {image_name}\n")
    (folder / "m.obj").write_text("mtllib m.mtl\nv 0 0 0\nv 4 0 0\nv 4 4 0\nv 0 4 0\nvt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\n"
                                  "usemtl tex\nf 1/1 2/2 3/3\nf 1/1 3/3 4/4\n")
    return folder / "m.obj"


@pytest.mark.parametrize("fmt, ext", [("JPEG", "jpg"), ("PNG", "png"), ("BMP", "bmp")])
def test_texture_bytes_are_the_files_own_where_png_or_jpeg(tmp_path, fmt, ext):
    rng = np.random.default_rng(3)
    pixels = rng.integers(0, 256, (32, 48, 3), dtype=np.uint8)
    buf = io.BytesIO()
    Image.fromarray(pixels).save(buf, format=fmt)
    (tmp_path / f"t.{ext}").write_bytes(buf.getvalue())
    mesh = load_mesh_file(_textured_obj(tmp_path, f"t.{ext}"))
    textures = {p.texture for p in mesh.parts}
    assert len(textures) == 1
    texture = textures.pop()
    if fmt == "BMP":       # neither PNG nor JPEG: encoded as PNG, the same pixels
        assert texture[:8] == b"\x89PNG\r\n\x1a\n"
        assert np.array_equal(np.asarray(Image.open(io.BytesIO(texture)).convert("RGB")), pixels)
    else:
        assert texture == buf.getvalue()
