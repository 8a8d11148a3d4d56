"""A small ContextCapture-like OSGB dataset with exact truth, for tests and the OSGB example.

``<out>/metadata.xml`` (SRS EPSG:32650, SRSOrigin :data:`ORIGIN`) and two 100 m tiles
``<out>/Data/Tile_+00X_+000/``, each a three-level PagedLOD tree as ContextCapture writes it:

* ``Tile_+00X_+000.osgb``: a PagedLOD (the tile's bounding sphere) drawing level 0 inline
  (25 m cells, 32 triangles) below :func:`switch_pixels` and the file ``..._L1.osgb`` above;
* ``..._L1.osgb``: a Group of four PagedLODs, one per 50 m quadrant, each drawing its level 1
  (6.25 m cells) inline and ``..._L2_<q>.osgb`` above its switch;
* ``..._L2_<q>.osgb``: the quadrant's level 2 (1.5625 m cells), a leaf.

The surface is the height field :func:`height` (gentle ground, four flat-roofed buildings)
sampled on each level's grid, in coordinates relative to SRSOrigin. Every node has its own
texture (PNG, embedded in the .osgb as ContextCapture embeds its JPEGs), rasterised from
:func:`colour` at texel centres: a 12.5 m checker tinted per level (red, green, blue), so a
sampled colour tells which level was read and whether the image is flipped. A level is meant
for maps whose gsd is at least its texel size (:data:`TEXEL`): the switch to the next level
lies at 2·r/texel pixels, r the node's bounding radius (see :mod:`pipeline25d.formats.osgb`).

Files are written as .osgt text and converted with OpenSceneGraph's ``osgconv``
(``WriteImageHint=IncludeFile``); the folder is built aside and moved into place whole.
"""

from __future__ import annotations

import argparse
import io
import itertools
import logging
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from pipeline25d.core.atomic import replace_dir

log = logging.getLogger(__name__)

SRS = "EPSG:32650"
ORIGIN = (226400.0, 3385600.0, 20.0)      # SRSOrigin, UTM 50N metres (Wuhan)
TILE = 100.0                                 # tile edge, m
TILES = ((0, 0), (1, 0))                     # (x, y) tile indices
CELLS = (4, 8, 32)                           # grid cells per node edge at levels 0, 1, 2
TEXTURE_PX = (32, 64, 128)                   # texture edge per node at levels 0, 1, 2
NODE = (TILE, TILE / 2, TILE / 2)            # node edge per level (levels 1 and 2: quadrants)
TEXEL = tuple(n / px for n, px in zip(NODE, TEXTURE_PX))   # m per texel: 3.125, 0.78125, 0.390625
CHECKER = 12.5                               # checker cell, m
TINT = ((220, 60, 50), (60, 200, 70), (60, 90, 230))      # level 0 red, 1 green, 2 blue
DARK = 0.55                                  # odd checker cells
ROOF = 0.35                                  # roofs: this share of white mixed into the colour
BUILDINGS = ((20.0, 20.0, 45.0, 40.0, 15.0), (60.0, 55.0, 85.0, 90.0, 25.0),
             (120.0, 15.0, 150.0, 45.0, 10.0), (160.0, 60.0, 190.0, 80.0, 30.0))  # x0, y0, x1, y1, height
Z_RANGE = (0.0, 40.0)                        # bounds every height (node radii use it)


def height(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Surface height (m above SRSOrigin z) at local x, y; multiples of 1/64, exact in float32."""
    z = 2.0 + 0.02 * x + 1.5 * np.sin(y / 16.0)
    for x0, y0, x1, y1, h in BUILDINGS:
        inside = (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)
        z = np.where(inside, np.maximum(z, h), z)
    return np.round(z * 64.0) / 64.0


def colour(level: int, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """(..., 3) uint8 texture colour at local x, y for ``level``: checker, roofs lighter."""
    tint = np.asarray(TINT[level], dtype=np.float64)
    odd = ((np.floor(x / CHECKER) + np.floor(y / CHECKER)) % 2 == 1)[..., None]
    rgb = np.where(odd, tint * DARK, tint)
    roof = np.zeros(np.shape(x), dtype=bool)
    for x0, y0, x1, y1, _ in BUILDINGS:
        roof |= (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)
    rgb = np.where(roof[..., None], rgb * (1 - ROOF) + 255 * ROOF, rgb)
    return np.round(rgb).astype(np.uint8)


def node_radius(level: int) -> float:
    """Bounding radius of a node at ``level``: half the diagonal of its box over :data:`Z_RANGE`."""
    return 0.5 * float(np.sqrt(2 * NODE[level] ** 2 + (Z_RANGE[1] - Z_RANGE[0]) ** 2))


def switch_pixels(level: int) -> float:
    """Pixel size on screen at which a node of ``level`` hands over to the next level."""
    return 2.0 * node_radius(level) / TEXEL[level]


def level_for_gsd(gsd: float) -> int:
    """The level a map of ``gsd`` should draw: the coarsest whose texel is at most the gsd."""
    return next((k for k in range(len(TEXEL)) if gsd >= TEXEL[k]), len(TEXEL) - 1)


def triangles(level: int) -> int:
    """Triangles of one tile at ``level``."""
    return 2 * CELLS[level] ** 2 * round(TILE / NODE[level]) ** 2


def tile_name(tx: int, ty: int) -> str:
    return f"Tile_{tx:+04d}_{ty:+04d}"


def generate_osgb_sample(out: str | Path) -> Path:
    """Write the dataset to ``out`` (replacing it) and return ``out``."""
    from pipeline25d.formats.osgb import osgconv

    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix=".osgb-sample-", dir=out.parent) as tmp:
        build, work = Path(tmp) / "dataset", Path(tmp) / "work"
        work.mkdir()
        (build / "Data").mkdir(parents=True)
        (build / "metadata.xml").write_text(
            '<?xml version="1.0" encoding="utf-8"?>\n<ModelMetadata version="1">\n'
            f"\t<SRS>{SRS}</SRS>\n\t<SRSOrigin>{ORIGIN[0]:.0f},{ORIGIN[1]:.0f},{ORIGIN[2]:.0f}</SRSOrigin>\n"
            "\t<Texture>\n\t\t<ColorSource>Visible</ColorSource>\n\t</Texture>\n</ModelMetadata>\n")
        for tx, ty in TILES:
            name = tile_name(tx, ty)
            tile_dir = build / "Data" / name
            tile_dir.mkdir()
            x0, y0 = tx * TILE, ty * TILE
            ids = itertools.count(1)   # UniqueIDs, one sequence per tile (unique within each file)
            files = {f"{name}.osgb": _paged(ids, 0, x0, y0, TILE, f"{name}_L1.osgb", f"{name}_L0")}
            quads = [(q, x0 + (q % 2) * NODE[1], y0 + (q // 2) * NODE[1]) for q in range(4)]
            files[f"{name}_L1.osgb"] = _group(ids, [_paged(ids, 1, qx, qy, NODE[1], f"{name}_L2_{q}.osgb",
                                                           f"{name}_L1_{q}")
                                               for q, qx, qy in quads])
            for q, qx, qy in quads:
                files[f"{name}_L2_{q}.osgb"] = _geode(ids, 2, qx, qy, NODE[2], f"{name}_L2_{q}")
            for fname, (text, images) in files.items():
                for img_name, png in images.items():
                    (work / img_name).write_bytes(png)
                (work / "node.osgt").write_text(HEADER + text)
                osgconv(Path("node.osgt"), (tile_dir / fname).resolve(), ["WriteImageHint=IncludeFile"], work,
                        tile_dir / fname)
        replace_dir(build, out)
    log.info("OSGB sample: %d tiles in %s", len(TILES), out)
    return out


# --------------------------------------------------------------------------- osgt text

HEADER = "#Ascii Scene\n#Version 161\n#Generator OpenSceneGraph 3.6.5\n\n"
Osgt = tuple[str, dict[str, bytes]]   # object text, images it names (file name -> PNG bytes)


def _paged(ids: Iterator[int], level: int, x0: float, y0: float, edge: float, child_file: str,
           texture_name: str) -> Osgt:
    """A PagedLOD over one node: this level inline below the switch, ``child_file`` above it."""
    uid = next(ids)
    geode, images = _geode(ids, level, x0, y0, edge, texture_name)
    centre = (x0 + edge / 2, y0 + edge / 2, sum(Z_RANGE) / 2)
    switch = switch_pixels(level)
    text = (f"osg::PagedLOD {{\n UniqueID {uid}\n CenterMode USER_DEFINED_CENTER\n"
            f" UserCenter {centre[0]!r} {centre[1]!r} {centre[2]!r} {node_radius(level)!r}\n"
            f" RangeMode PIXEL_SIZE_ON_SCREEN\n RangeList 2 {{\n  0 {switch!r}\n  {switch!r} 1e+30\n }}\n"
            f' DatabasePath FALSE\n RangeDataList 2 {{\n  ""\n  "{child_file}"\n }}\n'
            f" PriorityList 2 {{\n  0 1\n  0 1\n }}\n Children 1 {{\n{geode}\n }}\n}}")
    return text, images


def _group(ids: Iterator[int], children: list[Osgt]) -> Osgt:
    uid = next(ids)
    body = "\n".join(text for text, _ in children)
    images = {k: v for _, imgs in children for k, v in imgs.items()}
    return f"osg::Group {{\n UniqueID {uid}\n Children {len(children)} {{\n{body}\n }}\n}}", images


def _geode(ids: Iterator[int], level: int, x0: float, y0: float, edge: float, texture_name: str) -> Osgt:
    """A Geode with the node's grid of ``CELLS[level]`` cells, textured by ``texture_name``.png."""
    n = CELLS[level]
    s = np.linspace(0.0, 1.0, n + 1)
    u, v = np.meshgrid(s, s)                       # row j = y, column i = x
    x, y = x0 + u * edge, y0 + v * edge
    xyz = np.column_stack([x.ravel(), y.ravel(), height(x, y).ravel()])
    corner = (np.arange(n)[None, :] + (n + 1) * np.arange(n)[:, None]).ravel()
    faces = np.concatenate([np.column_stack([corner, corner + 1, corner + n + 2]),
                            np.column_stack([corner, corner + n + 2, corner + n + 1])])
    png_name = f"{texture_name}.png"
    text = geode_text(ids, xyz, faces, np.column_stack([u.ravel(), v.ravel()]), png_name)
    return text, {png_name: _texture(level, x0, y0, edge)}


def geode_text(ids: Iterator[int], xyz: np.ndarray, faces: np.ndarray, uv: np.ndarray | None,
               image: str | None) -> str:
    """osgt text of a Geode of one triangle Geometry (positions, indices, optional UVs and the
    image file they map; the image is embedded or referenced as osgconv's WriteImageHint says)."""
    ids = [next(ids) for _ in range(8)]
    verts = _rows(np.asarray(xyz, np.float64), "%r")
    idx = _rows(np.asarray(faces, np.int64), "%d")
    state = "" if image is None else (
        f"   StateSet TRUE {{\n    osg::StateSet {{\n     UniqueID {ids[2]}\n"
        "     TextureModeList 1 {\n      Data 1 {\n       GL_TEXTURE_2D ON\n      }\n     }\n"
        "     TextureAttributeList 1 {\n      Data 1 {\n"
        f"       osg::Texture2D {{\n        UniqueID {ids[3]}\n        Image TRUE {{\n"
        f'         ClassName osg::Image\n         UniqueID {ids[4]}\n         FileName "{image}"\n'
        "         WriteHint 2 2\n        }\n       }\n       Value OFF\n      }\n     }\n    }\n   }\n")
    uvs = "" if uv is None or image is None else (
        f"   TexCoordArrayList 1 {{\n    osg::Vec2Array {{\n     UniqueID {ids[7]}\n"
        f"     Binding BIND_PER_VERTEX\n     vector {len(uv)} {{\n"
        + _rows(np.asarray(uv, np.float64), "%r") + "\n     }\n    }\n   }\n")
    return (f"osg::Geode {{\n UniqueID {ids[0]}\n Drawables 1 {{\n  osg::Geometry {{\n   UniqueID {ids[1]}\n"
            + state +
            f"   PrimitiveSetList 1 {{\n    osg::DrawElementsUInt {{\n     UniqueID {ids[5]}\n     Mode TRIANGLES\n"
            f"     vector {faces.size} {{\n{idx}\n     }}\n    }}\n   }}\n"
            f"   VertexArray TRUE {{\n    osg::Vec3Array {{\n     UniqueID {ids[6]}\n     Binding BIND_PER_VERTEX\n"
            f"     vector {len(xyz)} {{\n{verts}\n     }}\n    }}\n   }}\n"
            + uvs + "  }\n }\n}")


def _rows(array: np.ndarray, fmt: str) -> str:
    """One indented line per row of a 2-D array, values formatted by ``fmt`` (one format call: fast)."""
    if not len(array):
        return ""
    line = "     " + " ".join([fmt] * array.shape[1])
    return "\n".join([line] * len(array)) % tuple(array.ravel().tolist())


def _texture(level: int, x0: float, y0: float, edge: float) -> bytes:
    """PNG of :func:`colour` at the texel centres of a node (first row = north edge)."""
    from PIL import Image

    px = TEXTURE_PX[level]
    centres = (np.arange(px) + 0.5) * edge / px
    x, y = np.meshgrid(x0 + centres, y0 + edge - centres)
    buf = io.BytesIO()
    Image.fromarray(colour(level, x, y), "RGB").save(buf, format="PNG")
    return buf.getvalue()


def main(argv: list[str] | None = None, prog: str | None = None) -> int:
    """CLI: ``python -m pipeline25d_lab.scenes.osgb_sample OUT``."""
    parser = argparse.ArgumentParser(prog=prog,
                                     description="Generate a small ContextCapture-like OSGB dataset.")
    parser.add_argument("out_dir", type=Path, help="dataset folder to write (replaced when it exists)")
    args = parser.parse_args(argv)
    generate_osgb_sample(args.out_dir)
    print(f"OSGB sample: {len(TILES)} tiles, levels of {[triangles(k) for k in range(3)]} triangles "  # noqa: T201
          f"per tile, in {args.out_dir}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
