"""Texture files as readers take them: an OBJ's texture reaches the chunks as its own file's bytes
where that is a PNG or JPEG, and as a PNG of the same pixels otherwise (what trimesh decoded, once
per image); a truncated one is found when its file is read (named, drawn untextured or an error as
``missing_textures`` says), not in the render job that decodes it."""

from __future__ import annotations

import io

import numpy as np
import pytest
from PIL import Image

from pipeline25d.core.errors import InputFileError, MissingTextureWarning
from pipeline25d.formats import load_district
from pipeline25d.formats.common import image_problem
from pipeline25d.formats.meshfile import load_mesh_file
from pipeline25d.stages.textures import decode


def _textured_obj(folder, image_name: str) -> object:
    (folder / "m.mtl").write_text(f"newmtl tex\nKd 1 1 1\nmap_Kd {image_name}\n")
    (folder / "m.obj").write_text("mtllib m.mtl\nv 0 0 0\nv 4 0 0\nv 4 4 0\nv 0 4 0\nvt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\n"
                                  "usemtl tex\nf 1/1 2/2 3/3\nf 1/1 3/3 4/4\n")
    return folder / "m.obj"


@pytest.mark.parametrize("fmt, ext, options", [("JPEG", "jpg", {}), ("PNG", "png", {}), ("TGA", "tga", {}),
                                               ("BMP", "bmp", {}), ("TGA", "tga", {"compression": "tga_rle"})])
def test_texture_bytes_are_the_files_own_where_png_jpeg_or_raw_tga(tmp_path, fmt, ext, options):
    rng = np.random.default_rng(3)
    pixels = rng.integers(0, 256, (32, 48, 3), dtype=np.uint8)
    buf = io.BytesIO()
    Image.fromarray(pixels).save(buf, format=fmt, **options)
    (tmp_path / f"t.{ext}").write_bytes(buf.getvalue())
    mesh = load_mesh_file(_textured_obj(tmp_path, f"t.{ext}"))
    textures = {p.texture for p in mesh.parts}
    assert len(textures) == 1
    texture = textures.pop()
    if fmt == "BMP" or options:       # a BMP, a run-length TGA: encoded as PNG, the same pixels
        assert texture[:8] == b"\x89PNG\r\n\x1a\n"
        assert np.array_equal(np.asarray(Image.open(io.BytesIO(texture)).convert("RGB")), pixels)
    else:
        assert texture == buf.getvalue()
        if fmt != "JPEG":           # lossless: the render job reads the file's pixels
            assert np.array_equal(decode(texture)[::-1, :, :3], pixels)


def _image(fmt: str) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(np.random.default_rng(4).integers(0, 256, (64, 64, 3), dtype=np.uint8)).save(buf, format=fmt)
    return buf.getvalue()


@pytest.mark.parametrize("fmt", ["JPEG", "PNG", "TGA"])
def test_a_truncated_image_is_a_problem_a_whole_one_is_not(fmt):
    data = _image(fmt)
    assert image_problem(data) is None
    assert image_problem(data[: len(data) // 2]).startswith("cannot be read")
    assert image_problem(b"not an image at all") == "is not an image"


def test_a_png_with_a_wrong_checksum_but_whole_data_is_drawn():
    """Only the CRC of its pixel data (IDAT) wrong: PIL's check refuses it, but the PNG decodes (as the
    renderer's decoder reads it), so it is no problem; its pixels cut short are."""
    from PIL import Image

    data = bytearray(_image("PNG"))
    at = data.find(b"IDAT")
    data[at + 4 + int.from_bytes(data[at - 4:at], "big")] ^= 0xFF       # the first byte of its CRC
    with pytest.raises(SyntaxError, match="checksum"):
        Image.open(io.BytesIO(bytes(data))).verify()
    assert image_problem(bytes(data)) is None
    assert image_problem(bytes(data[: len(data) // 2])) is not None


@pytest.mark.parametrize("fmt, ext", [("JPEG", "jpg"), ("PNG", "png")])
def test_an_obj_with_a_truncated_texture_names_it_at_ingest(tmp_path, fmt, ext):
    data = _image(fmt)
    (tmp_path / f"t.{ext}").write_bytes(data[: len(data) // 2])
    model = _textured_obj(tmp_path, f"t.{ext}")
    with pytest.raises(InputFileError, match=rf"m\.obj: texture 't\.{ext}' cannot be read"):
        load_district({"path": str(model)}, "EPSG:28992")
    with pytest.warns(MissingTextureWarning, match=rf"texture 't\.{ext}' cannot be read"):
        mesh = load_district({"path": str(model), "missing_textures": "untextured"}, "EPSG:28992")
    assert mesh.n_triangles == 2 and all(p.texture is None and p.colors is not None for p in mesh.parts)
