"""Autodesk .3ds through assimp: a model written as OBJ + MTL (two coloured materials and a
textured one) and converted to .3ds with ``assimp export``; the .3ds is checked with a chunk
reader of its own (it holds the materials, the texture name and the raw z-up vertices), then
read back through the pipeline's reader."""

from __future__ import annotations

import io
import shutil
import struct
import subprocess
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from pipeline25d.core.errors import InputFileError
from pipeline25d.formats import detect_format, load_district

pytestmark = pytest.mark.skipif(shutil.which("assimp") is None,
                                reason="the assimp command is not installed (Debian: assimp-utils)")

KD = {"roof": (0.8, 0.2, 0.1), "wall": (0.25, 0.5, 0.75)}
QUADRANTS = {(0, 0): (250, 20, 20), (1, 0): (20, 250, 20), (0, 1): (20, 20, 250),  # (east, north)
             (1, 1): (240, 240, 40)}
# a textured ground square (0..40 m), a red roof triangle and a blue wall quad, z up
GROUND = np.array([[0, 0, 0], [40, 0, 0], [40, 40, 0], [0, 40, 0]], dtype=float)
ROOF = np.array([[10, 10, 12], [30, 10, 12], [20, 30, 18]], dtype=float)
WALL = np.array([[10, 10, 0], [30, 10, 0], [30, 10, 12], [10, 10, 12]], dtype=float)


@pytest.fixture(scope="module")
def model(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("3ds")
    img = np.zeros((64, 64, 3), np.uint8)            # first row = north: v = 1
    for (east, north), rgb in QUADRANTS.items():
        img[(1 - north) * 32:(2 - north) * 32, east * 32:(east + 1) * 32] = rgb
    Image.fromarray(img).save(folder / "ground.png")
    (folder / "city.mtl").write_text("".join(f"newmtl {m}\nKd {r} {g} {b}\n" for m, (r, g, b) in KD.items())
                                     + "newmtl ground\nKd 1 1 1\nmap_Kd ground.png\n")
    v = np.concatenate([GROUND, ROOF, WALL])
    lines = ["mtllib city.mtl"] + [f"v {x} {y} {z}" for x, y, z in v]
    lines += [f"vt {x / 40} {y / 40}" for x, y, _ in GROUND]
    lines += ["usemtl ground", "f 1/1 2/2 3/3", "f 1/1 3/3 4/4", "usemtl roof", "f 5 6 7",
              "usemtl wall", "f 8 9 10", "f 8 10 11"]
    (folder / "city.obj").write_text("\n".join(lines) + "\n")
    subprocess.run(["assimp", "export", "city.obj", "city.3ds"], cwd=folder, check=True, capture_output=True)
    return folder / "city.3ds"


def chunks_3ds(data: bytes) -> dict[str, list]:
    """Material names, diffuse colours (as 8-bit RGB), texture names and vertex lists of a .3ds."""
    found: dict[str, list] = {"names": [], "diffuse": [], "maps": [], "vertices": []}

    def walk(start: int, end: int) -> None:
        while start + 6 <= end:
            cid, length = struct.unpack_from("<HI", data, start)
            body, stop = start + 6, start + length
            if cid in (0x4D4D, 0x3D3D, 0xAFFF, 0xA200, 0xA020, 0x4100):
                walk(body, stop)
            elif cid == 0x4000:                                    # object: its name, then sub-chunks
                walk(data.index(b"\0", body) + 1, stop)
            elif cid == 0xA000:
                found["names"].append(data[body:data.index(b"\0", body)].decode())
            elif cid == 0x0011:                                    # 24-bit colour
                found["diffuse"].append(tuple(data[body:body + 3]))
            elif cid == 0x0010:                                    # float colour
                found["diffuse"].append(tuple(round(c * 255) for c in struct.unpack_from("<3f", data, body)))
            elif cid == 0xA300:
                found["maps"].append(data[body:data.index(b"\0", body)].decode())
            elif cid == 0x4110:
                n = struct.unpack_from("<H", data, body)[0]
                found["vertices"].append(np.frombuffer(data, "<f4", 3 * n, body + 2).reshape(n, 3))
            start = stop

    walk(0, len(data))
    return found


def test_the_3ds_file_holds_the_materials_texture_and_vertices(model):
    found = chunks_3ds(model.read_bytes())
    assert {"roof", "wall", "ground"} <= {n.rsplit("_", 1)[0] for n in found["names"]}   # assimp adds _<k>
    for rgb in KD.values():
        assert tuple(round(c * 255) for c in rgb) in found["diffuse"]
    assert found["maps"] == ["ground.png"]
    stored = np.concatenate(found["vertices"]).astype(np.float64)
    assert {tuple(p) for p in stored} == {tuple(p) for p in np.concatenate([GROUND, ROOF, WALL])}


def test_bounds_triangles_colours_and_texture(model):
    assert detect_format(model) == "3ds"
    offset = np.array([85000.0, 445000.0, 2.0])
    mesh = load_district({"path": str(model), "crs": "EPSG:28992", "offset": offset.tolist()}, "EPSG:28992")
    allv = np.concatenate([GROUND, ROOF, WALL]) + offset
    np.testing.assert_array_equal(mesh.bounds(), [allv.min(axis=0), allv.max(axis=0)])
    assert mesh.n_triangles == 5
    by_colour = {}
    for part in mesh.parts:
        if part.colors is not None:
            by_colour[tuple(part.colors[0, :3])] = part
            assert (part.colors == part.colors[0]).all()
    roof = by_colour[tuple(round(c * 255) for c in KD["roof"])]
    wall = by_colour[tuple(round(c * 255) for c in KD["wall"])]
    np.testing.assert_array_equal(np.sort(roof.vertices[roof.faces].reshape(-1, 3), axis=0),
                                  np.sort(ROOF + offset, axis=0))
    assert roof.n_triangles == 1 and wall.n_triangles == 2
    ground = next(p for p in mesh.parts if p.texture is not None)
    img = np.asarray(Image.open(io.BytesIO(ground.texture)).convert("RGB"))
    weights = np.random.default_rng(1).dirichlet(np.ones(3), size=200)
    xyz = np.einsum("sk,fkd->fsd", weights, ground.vertices[ground.faces]).reshape(-1, 3) - offset
    uv = np.einsum("sk,fkd->fsd", weights, ground.uv[ground.faces].astype(np.float64)).reshape(-1, 2)
    clear = (np.abs(xyz[:, 0] - 20) > 1) & (np.abs(xyz[:, 1] - 20) > 1)     # off the quadrant lines
    rows = np.clip(((1 - uv[clear, 1]) * img.shape[0]).astype(int), 0, img.shape[0] - 1)
    cols = np.clip((uv[clear, 0] * img.shape[1]).astype(int), 0, img.shape[1] - 1)
    want = [QUADRANTS[(int(x >= 20), int(y >= 20))] for x, y in xyz[clear, :2]]
    np.testing.assert_array_equal(img[rows, cols], want)
    assert clear.sum() > 300


def test_corrupt_3ds_is_named(model, tmp_path):
    bad = tmp_path / "broken.3ds"
    bad.write_bytes(model.read_bytes()[:200])
    with pytest.raises(InputFileError, match=r"broken\.3ds: assimp cannot read it"):
        load_district({"path": str(bad)}, "EPSG:28992")


def test_missing_texture_is_an_error_unless_untextured_is_asked_for(model, tmp_path):
    alone = Path(shutil.copy(model, tmp_path / "alone.3ds"))           # without ground.png beside it
    with pytest.raises(InputFileError, match=r"alone\.3ds: .*ground\.png"):
        load_district({"path": str(alone)}, "EPSG:28992")
    mesh = load_district({"path": str(alone), "missing_textures": "untextured"}, "EPSG:28992")
    assert mesh.n_triangles == 5 and all(p.texture is None for p in mesh.parts)
