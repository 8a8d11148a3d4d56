"""Autodesk 3DS models through assimp (Debian ``assimp-utils``): converted to glTF, then read
by :mod:`pipeline25d.formats.gltf`.

``assimp export model.3ds model.glb`` keeps the file's float32 vertices as they are and puts
the 3DS z-up to glTF y-up rotation in the root node; the glTF reader's y-up to z-up rotation
undoes it, so the parts come out in the 3DS file's own (x east, y north, z up) frame.
Material diffuse colours become colours per vertex; texture maps keep the file names the 3DS
stores, resolved beside the .3ds (a missing image is an error unless the input says
``missing_textures: untextured``, as for every format).
"""

from __future__ import annotations

import tempfile
from pathlib import Path

from pipeline25d.formats.common import Detail, Loaded, run_converter
from pipeline25d.formats.gltf import parse_gltf_bytes

ASSIMP = "assimp"


def read_3ds(path: Path, spec: dict, detail: Detail = Detail()) -> Loaded:
    """Reader contract (:mod:`pipeline25d.formats`): a .3ds file, in the input's ``crs``."""
    path = Path(path)
    with tempfile.TemporaryDirectory(prefix="pipeline25d-3ds-") as tmp:
        run_converter([ASSIMP, "export", str(path.resolve()), "model.glb"], Path(tmp), Path("model.glb"), path,
                      "assimp-utils")
        data = (Path(tmp) / "model.glb").read_bytes()
    return Loaded(parse_gltf_bytes(data, path), spec.get("crs"))   # image URIs resolve beside the .3ds
