"""A crop of a textured oblique map tile beside its supersampled reference, with its error.

From a render pack (:mod:`pipeline25d_lab.harness.render_replay` ``pack``) of a textured run, the
middle tile of one perspective's plan: a ``--crop`` px square at its centre rendered as the render
job draws it (its planned LOD, MSAA, mipmaps and the driver's anisotropic filtering), and the same
square rendered ``--factor`` x finer from the chunk's finest level and averaged down
(``factor`` x ``factor`` boxes): the reference a filter is judged by. Writes
``crop.json`` (mean and 99th-percentile absolute error in grey levels over RGB, where both are
opaque; the driver) and ``crop.npz`` (both images), and where PIL is present ``crop.png``:
map | reference | 4 x |difference|.

    python -m pipeline25d_lab.harness.texture_crop PACK OUT [--perspective az045_el30] [--crop 256] [--factor 4]
"""

from __future__ import annotations

import argparse
import json
import pickle
import sys
from pathlib import Path

import numpy as np

from pipeline25d.core.atomic import write_json
from pipeline25d.core.grid import Extent


def box_average(rgba: np.ndarray, f: int) -> np.ndarray:
    """(h/f, w/f, 4) uint8: alpha-weighted mean colour and mean alpha of f x f boxes of ``rgba``."""
    h, w = rgba.shape[0] // f, rgba.shape[1] // f
    x = rgba[:h * f, :w * f].astype(np.float64).reshape(h, f, w, f, 4)
    a = x[..., 3:4]
    colour = (x[..., :3] * a).sum(axis=(1, 3)) / np.maximum(a.sum(axis=(1, 3)), 1e-9)
    return np.concatenate([colour, a.mean(axis=(1, 3))], axis=-1).round().clip(0, 255).astype(np.uint8)


def crop_and_reference(packed: Path, perspective: str, crop: int, factor: int) -> dict:
    """The crop, its reference and their error (see the module docstring)."""
    from pipeline25d.stages.lod import load_chunk_level
    from pipeline25d.stages.plan import read_plan
    from pipeline25d.stages.render import TileRenderer, TileView, create_context, renderer_info

    pl = read_plan(packed / "plans" / f"{perspective}.json")
    tile = pl.tiles[len(pl.tiles) // 2]
    ground_of = json.loads((packed / "ground" / "plans.json").read_text())
    ground = pickle.loads((packed / "ground" / ground_of[pl.id]).read_bytes()).sample if pl.id in ground_of else None
    content, (w, h) = pl.content(tile)
    g = pl.pixel_size
    x0 = content.xmin + ((w - crop) // 2) * g
    y1 = content.ymax - ((h - crop) // 2) * g
    extent = Extent(x0, y1 - crop * g, x0 + crop * g, y1)
    lod = packed / "lod"
    planned = [load_chunk_level(lod / c.district / f"{c.id}.npz", c.lod) for c in tile.chunks]
    finest = [load_chunk_level(lod / c.district / f"{c.id}.npz", 0) for c in tile.chunks]
    ctx = create_context()
    try:
        r = TileRenderer(ctx, ambient=tile.render["ambient"], samples=tile.render["samples"])
        images = []
        for chunks, size in ((planned, crop), (finest, crop * factor)):
            view = TileView(pl.perspective, pl.z0, extent, tuple(tile.depth_range), (size, size), ground, pl.camera)
            with r.upload(chunks, view) as geometry:
                images.append(r.render_color(geometry, view))
        driver = renderer_info(ctx)
    finally:
        ctx.release()
    image, reference = images[0], box_average(images[1], factor)
    both = (image[..., 3] == 255) & (reference[..., 3] == 255)
    err = np.abs(image[..., :3].astype(float) - reference[..., :3])[both]
    return {"perspective": pl.id, "tile": f"{tile.row}_{tile.col}", "crop_px": crop, "factor": factor,
            "gsd": g, "opaque_share": round(float(both.mean()), 4), "driver": driver,
            "mean_abs_grey": round(float(err.mean()), 3) if err.size else None,
            "p99_abs_grey": round(float(np.percentile(err, 99)), 2) if err.size else None,
            "image": image, "reference": reference}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m pipeline25d_lab.harness.texture_crop",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("packed", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--perspective", default="az045_el45")
    ap.add_argument("--crop", type=int, default=256)
    ap.add_argument("--factor", type=int, default=4)
    args = ap.parse_args(argv)
    result = crop_and_reference(args.packed, args.perspective, args.crop, args.factor)
    image, reference = result.pop("image"), result.pop("reference")
    args.out.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(args.out / "crop.npz", image=image, reference=reference)
    write_json(args.out / "crop.json", result)
    try:
        from PIL import Image
    except ImportError:
        pass
    else:
        diff = np.clip(4 * np.abs(image[..., :3].astype(int) - reference[..., :3]), 0, 255).astype(np.uint8)
        side = np.concatenate([image[..., :3], reference[..., :3], diff], axis=1)
        Image.fromarray(side).save(args.out / "crop.png")
    print(json.dumps(result))  # noqa: T201
    return 0


if __name__ == "__main__":
    sys.exit(main())
