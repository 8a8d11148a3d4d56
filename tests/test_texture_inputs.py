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


@pytest.mark.parametrize("ref, where, found", [
    ("-s 1 1 1 -clamp on t.png", "t.png", None),                      # MTL map options before the name
    (r"textures\t.png", "textures/t.png", None),                       # a Windows exporter's separators
    ("my texture.png", "my texture.png", None),                         # a name with a space
    (r"C:\Users\me\Desktop\export\t.png", "t.png", "t.png"),           # its machine's absolute path
    (r"D:\city\textures\t.png", "textures/t.png", "textures/t.png"),   # ... whose tail lies in the folder
    ("/home/me/export/t.png", "t.png", "t.png"),
    ('"my texture.png"', "my texture.png", None),                       # quoted
])
def test_an_obj_finds_its_texture_where_exporters_name_it(tmp_path, ref, where, found):
    """What photogrammetry and CAD exporters write in a material library, read as their own tools do:
    the texture is drawn, and one named by a path it is not at says which file was taken instead."""
    (tmp_path / where).parent.mkdir(parents=True, exist_ok=True)
    data = _image("PNG")
    (tmp_path / where).write_bytes(data)
    model = _textured_obj(tmp_path, ref)
    import warnings

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        mesh = load_district({"path": str(model)}, "EPSG:28992")
    assert {p.texture for p in mesh.parts} == {data}
    said = [str(w.message) for w in caught]
    if found is None:
        assert said == []
    else:
        assert said == [f"{model}: texture '{ref}' is not where it says; {found} in the model's folder is used"]


def test_an_obj_texture_outside_its_folder_is_still_refused(tmp_path):
    """The fallback looks only inside the model's folder: a path out of it with no file of its
    name inside stays the error it was (no file outside the input's folder is opened)."""
    (tmp_path / "in").mkdir()
    (tmp_path / "t.png").write_bytes(_image("PNG"))
    model = _textured_obj(tmp_path / "in", "../t.png")
    with pytest.raises(InputFileError, match=r"texture '\.\./t\.png' lies outside the dataset folder"):
        load_district({"path": str(model)}, "EPSG:28992")


def test_an_obj_texture_named_in_another_letter_case_is_drawn_with_a_warning(tmp_path):
    """``Textures\\T.PNG`` written on Windows for ``textures/t.png``: drawn, and the warning names both."""
    (tmp_path / "textures").mkdir()
    data = _image("PNG")
    (tmp_path / "textures" / "t.png").write_bytes(data)
    model = _textured_obj(tmp_path, r"Textures\T.PNG")
    with pytest.warns(UserWarning, match=r"texture 'Textures/T\.PNG' is 'textures/t\.png' on disk"):
        mesh = load_district({"path": str(model)}, "EPSG:28992")
    assert {p.texture for p in mesh.parts} == {data}
