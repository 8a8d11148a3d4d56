"""A small 3MX scene with exact truth, its meshes written by OpenCTM's own ``ctmconv`` (Debian openctm-tools).

Tiles side by side, each a node of ``Data/root.3mxb`` holding a coarse level (one quad, a JPEG of one
colour) and naming a child file with the fine level (a grid of ``GRID`` x ``GRID`` cells with a
peak at its centre, a PNG of stripes). At a map pixel of ``gsd`` a tile's node covers
``diagonal / gsd`` pixels: below :data:`MAX_SCREEN_DIAMETER` the coarse level is drawn, at or above
it the fine one. Coordinates are relative to ``SRSOrigin`` in ``SRS``, as ContextCapture writes them.
"""

from __future__ import annotations

import io
import json
import struct
import subprocess
import tempfile
from pathlib import Path

import numpy as np

TILE_M = 50.0
GRID = 8
MAX_SCREEN_DIAMETER = 100.0      # px: a 50 m tile (diagonal about 71 m) switches to its fine level below gsd 0.71
SRS, ORIGIN = "EPSG:28992", (85000.0, 447000.0, 0.0)


def fine_mesh(x0: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(vertices, faces, uv) of a tile's fine level: a z = 1 grid whose centre vertex is a 6 m peak."""
    ticks = np.linspace(0.0, TILE_M, GRID + 1)
    x, y = np.meshgrid(ticks + x0, ticks)
    z = np.ones_like(x)
    z[GRID // 2, GRID // 2] = 7.0
    vertices = np.c_[x.ravel(), y.ravel(), z.ravel()]
    uv = np.c_[(x.ravel() - x0) / TILE_M, y.ravel() / TILE_M]
    n = GRID + 1
    cells = np.array([(r * n + c, r * n + c + 1, (r + 1) * n + c + 1, (r + 1) * n + c)
                      for r in range(GRID) for c in range(GRID)])
    faces = np.r_[cells[:, [0, 1, 2]], cells[:, [0, 2, 3]]]
    return vertices, faces, uv


def coarse_mesh(x0: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(vertices, faces, uv) of a tile's coarse level: one quad at z = 1."""
    vertices = np.array([[x0, 0, 1], [x0 + TILE_M, 0, 1], [x0 + TILE_M, TILE_M, 1], [x0, TILE_M, 1]], float)
    return vertices, np.array([[0, 1, 2], [0, 2, 3]]), np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)


def ctm_bytes(vertices: np.ndarray, faces: np.ndarray, uv: np.ndarray, method: str = "MG2") -> bytes:
    """An OpenCTM file of the mesh, written by ``ctmconv`` from an OBJ (1 mm vertex precision for MG2)."""
    with tempfile.TemporaryDirectory(prefix="p25d-ctm-") as tmp:
        obj = Path(tmp) / "m.obj"
        lines = [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in vertices] + [f"vt {u:.6f} {v:.6f}" for u, v in uv]
        lines += [f"f {a + 1}/{a + 1} {b + 1}/{b + 1} {c + 1}/{c + 1}" for a, b, c in faces]
        obj.write_text("\n".join(lines) + "\n")
        out = Path(tmp) / "m.ctm"
        extra = ["--vprec", "0.001", "--tprec", "0.0001"] if method == "MG2" else []
        subprocess.run(["ctmconv", str(obj), str(out), "--method", method, "--no-normals", *extra],
                       check=True, capture_output=True)
        return out.read_bytes()


def image_bytes(kind: str) -> bytes:
    """A 64 x 64 texture: ``jpg`` one colour (200, 80, 40); ``png`` blue stripes on white, top half red."""
    from PIL import Image

    if kind == "jpg":
        out = io.BytesIO()
        Image.new("RGB", (64, 64), (200, 80, 40)).save(out, format="JPEG", quality=95)
        return out.getvalue()
    img = np.full((64, 64, 3), 255, np.uint8)
    img[:, ::8] = (0, 0, 255)
    img[:32, :, 1:] = 0                                      # the top rows red
    out = io.BytesIO()
    Image.fromarray(img).save(out, format="PNG")
    return out.getvalue()


def node_file(nodes: list[dict], resources: list[tuple[dict, bytes]]) -> bytes:
    """A .3mxb file: 3MXBO, the header's length, the header, the buffers in the header's order."""
    header = json.dumps({"version": 1, "nodes": nodes,
                         "resources": [{**r, "size": len(b)} for r, b in resources]}).encode()
    return b"3MXBO" + struct.pack("<I", len(header)) + header + b"".join(b for _, b in resources)


def write_3mx_scene(folder: Path, tiles: int = 2, one_root: bool = False) -> Path:
    """Write the scene (``folder/scene.3mx``, ``folder/Data/...``); return the .3mx path. ``one_root``:
    the root file holds one node over all tiles (a quad under them at z = 0, drawn below
    ``MAX_SCREEN_DIAMETER`` px) whose children are one file per tile holding the tile's node."""
    data = folder / "Data"
    data.mkdir(parents=True, exist_ok=True)
    root_nodes, root_resources = [], []
    for t in range(tiles):
        x0, name = t * TILE_M, f"Tile_+{t:03d}_+000"
        (data / name).mkdir(exist_ok=True)
        fv, ff, fu = fine_mesh(x0)
        fine = node_file([{"id": "n0", "bbMin": fv.min(0).tolist(), "bbMax": fv.max(0).tolist(),
                           "maxScreenDiameter": 1e9, "children": [], "resources": ["g0"]}],
                         [({"type": "textureBuffer", "format": "png", "id": "t0"}, image_bytes("png")),
                          ({"type": "geometryBuffer", "format": "ctm", "id": "g0", "texture": "t0",
                            "bbMin": fv.min(0).tolist(), "bbMax": fv.max(0).tolist()}, ctm_bytes(fv, ff, fu))])
        (data / name / f"{name}_L1.3mxb").write_bytes(fine)
        cv, cf, cu = coarse_mesh(x0)
        root_nodes.append({"id": name, "bbMin": fv.min(0).tolist(), "bbMax": fv.max(0).tolist(),
                           "maxScreenDiameter": MAX_SCREEN_DIAMETER, "children": [f"{name}/{name}_L1.3mxb"],
                           "resources": [f"g{t}"]})
        root_resources += [({"type": "textureBuffer", "format": "jpg", "id": f"t{t}"}, image_bytes("jpg")),
                           ({"type": "geometryBuffer", "format": "ctm", "id": f"g{t}", "texture": f"t{t}",
                             "bbMin": cv.min(0).tolist(), "bbMax": cv.max(0).tolist()}, ctm_bytes(cv, cf, cu, "RAW"))]
    if not one_root:
        (data / "root.3mxb").write_bytes(node_file(root_nodes, root_resources))
    else:
        by_tile = {}
        for t, node in enumerate(root_nodes):
            name = node["id"]
            by_tile[f"{name}/{name}.3mxb"] = node_file([{**node, "children": [f"{name}_L1.3mxb"]}],
                                                       root_resources[2 * t:2 * t + 2])
        for rel, data_bytes in by_tile.items():
            (data / rel).write_bytes(data_bytes)
        width = tiles * TILE_M
        quad = np.array([[0, 0, 0], [width, 0, 0], [width, TILE_M, 0], [0, TILE_M, 0]], float)
        top = {"id": "top", "bbMin": [0, 0, 0], "bbMax": [width, TILE_M, 7.0], "maxScreenDiameter": MAX_SCREEN_DIAMETER,
               "children": list(by_tile), "resources": ["g"]}
        (data / "root.3mxb").write_bytes(node_file([top], [
            ({"type": "textureBuffer", "format": "jpg", "id": "t"}, image_bytes("jpg")),
            ({"type": "geometryBuffer", "format": "ctm", "id": "g", "texture": "t", "bbMin": [0, 0, 0],
              "bbMax": [width, TILE_M, 0]}, ctm_bytes(quad, np.array([[0, 1, 2], [0, 2, 3]]),
                                                      np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float), "RAW"))]))
    scene = {"3mxVersion": 1, "name": "sample", "description": "", "logo": "", "sceneOptions": [{}],
             "layers": [{"type": "meshPyramid", "id": "mesh0", "name": "sample", "description": "",
                         "SRS": SRS, "SRSOrigin": list(ORIGIN), "root": "Data/root.3mxb"}]}
    (folder / "scene.3mx").write_text(json.dumps(scene))
    return folder / "scene.3mx"
