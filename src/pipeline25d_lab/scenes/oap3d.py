"""A generated oblique-photogrammetry city (OAP3D) at the paper's Dataset 2 footprint, textured.

``generate_oap3d(out, size)`` writes, from one seed:

* ``out/osgb/``: a ContextCapture-style OSGB dataset (``metadata.xml`` with SRS and SRSOrigin,
  ``Data/Tile_+xxx_+yyy/`` PagedLOD trees with JPEG atlases embedded);
* ``out/3dtiles/``: the same nodes as 3D Tiles (``tileset.json``, one external tileset per tile,
  a glb per node with the same JPEG), see :mod:`pipeline25d_lab.scenes.oap3d_formats`;
* ``out/manifest.json``: the parameters, and per format and level the files, bytes, triangles
  and texel size, and the generation time.

Sizes (:data:`SIZES`, tiles of 200 m, four levels of 512-px atlases down to 5.04 cm texels,
31.9 M triangles at the finest level when full): ``full`` 16 x 12 tiles (3.2 x 2.4 km, Dataset
2 is 3.2 x 2.3 km), ``half`` 12 x 8, ``quarter`` 8 x 6, and ``tiny`` (2 x 1 tiles of 50 m,
three levels, 128-px atlases: for tests). The content is :mod:`pipeline25d_lab.scenes.oap3d_city`,
the nodes :mod:`pipeline25d_lab.scenes.oap3d_nodes`. A folder whose manifest records the same
size, seed and generator version and whose files are all there is kept as it is.

CLI: ``pipeline25d sample oap3d OUT [--size quarter] [--seed 7]``.
"""

from __future__ import annotations

import argparse
import json
import logging
import multiprocessing
import os
import re
import sys
import tempfile
import time
from collections import Counter
from concurrent.futures import ProcessPoolExecutor
from functools import partial
from pathlib import Path

import numpy as np

from pipeline25d.core.atomic import replace_dir, write_json
from pipeline25d.core.errors import ConfigError
from pipeline25d_lab.scenes.oap3d_city import City, build_city
from pipeline25d_lab.scenes.oap3d_formats import (
    TileTree,
    metadata_xml,
    osgb_file,
    root_tileset,
    tile_name,
    to_ecef,
    write_osgb_file,
)
from pipeline25d_lab.scenes.oap3d_nodes import Node, Spec, children, make_node

log = logging.getLogger(__name__)

GENERATOR_VERSION = 3
SRS = "EPSG:32650"
ORIGIN = (226400.0, 3385600.0, 20.0)      # SRSOrigin, UTM 50N metres (Wuhan)
SIZES = {
    "full": Spec((16, 12)),
    "half": Spec((12, 8)),
    "quarter": Spec((8, 6)),
    "tiny": Spec((2, 1), tile=50.0, levels=3, atlas=128, gutter=2, cells=6),
}


def generate_oap3d(out: str | Path, size: str = "quarter", seed: int = 7, progress=None,
                   workers: int | None = None) -> dict:
    """Write the dataset of ``size`` into ``out`` (kept when its manifest matches); return the manifest.
    Tiles are written by ``workers`` processes (default: one per core); each tile's files depend on
    the seed alone, so the dataset is the same byte for byte whatever the count."""
    if size not in SIZES:
        raise ConfigError(f"oap3d: size must be one of {', '.join(SIZES)}, got {size!r}")
    out = Path(out)
    existing = existing_manifest(out, size, seed)
    if existing is not None:
        log.info("oap3d %s in %s is up to date", size, out)
        return existing
    spec = SIZES[size]
    city = build_city(*spec.extent, seed)
    out.parent.mkdir(parents=True, exist_ok=True)
    t0 = time.monotonic()
    with tempfile.TemporaryDirectory(prefix=".oap3d-", dir=out.parent) as tmp:
        build, work = Path(tmp) / "dataset", Path(tmp) / "work"
        work.mkdir()
        (build / "osgb" / "Data").mkdir(parents=True)
        (build / "3dtiles" / "Data").mkdir(parents=True)
        (build / "osgb" / "metadata.xml").write_text(metadata_xml(SRS, ORIGIN))
        stats: dict[str, Counter] = {"osgb": Counter(), "3dtiles": Counter(), "triangles": Counter()}
        cells = [(tx, ty) for ty in range(spec.tiles[1]) for tx in range(spec.tiles[0])]
        entries = []
        write = partial(_write_tile, build, work, city, spec, seed=seed)
        with ProcessPoolExecutor(max(1, min(workers or os.cpu_count() or 1, len(cells))),
                                 mp_context=multiprocessing.get_context("fork")) as pool:
            for entry, counts in pool.map(write, cells):
                entries.append(entry)
                for key, counter in counts.items():
                    stats[key].update(counter)
                if progress is not None:
                    progress(f"oap3d {size}: tile {len(entries)}/{len(cells)}")
        (build / "3dtiles" / "tileset.json").write_text(root_tileset(entries, 2 * spec.tile))
        manifest = _manifest(build, size, seed, spec, stats, time.monotonic() - t0)
        write_json(build / "manifest.json", manifest)
        replace_dir(build, out)
    log.info("oap3d %s: %s", size, json.dumps(manifest["totals"]))
    return manifest


def _write_tile(build: Path, work: Path, city: City, spec: Spec, cell: tuple[int, int], seed: int
                ) -> tuple[tuple[str, list[float]], dict[str, Counter]]:
    """Both formats of one tile: ((its external tileset's URI, its ECEF bounding sphere), its bytes
    per level and format and triangles per level)."""
    tx, ty = cell
    name = tile_name(tx, ty)
    stats: dict[str, Counter] = {"osgb": Counter(), "3dtiles": Counter(), "triangles": Counter()}
    work = work / name
    work.mkdir()
    osgb_dir, tiles_dir = build / "osgb" / "Data" / name, build / "3dtiles" / "Data" / name
    osgb_dir.mkdir()
    tiles_dir.mkdir()
    x0, y0 = tx * spec.tile, ty * spec.tile
    centre = to_ecef(np.array([[x0 + spec.tile / 2, y0 + spec.tile / 2, 0.0]]) + ORIGIN, SRS)[0]
    tree = TileTree(spec, SRS, np.asarray(ORIGIN), centre)

    def emit(dst: Path, nodes: list[Node], level: int, root: bool) -> None:
        write_osgb_file(dst, work, spec, name, nodes, root)
        stats["osgb"][level] += dst.stat().st_size
        for node in nodes:
            stats["3dtiles"][node.level] += tree.add(tiles_dir, name, node)
            stats["triangles"][node.level] += len(node.faces)

    def expand(node: Node) -> None:
        if node.level + 1 >= spec.levels:
            return
        kids = [make_node(city, spec, node.level + 1, p, cx, cy, seed)
                for p, cx, cy in children(node.path, node.x0, node.y0, node.edge)]
        emit(osgb_dir / osgb_file(name, node.level, node.path), kids, node.level + 1, False)
        for kid in kids:
            expand(kid)

    root = make_node(city, spec, 0, "", x0, y0, seed)
    emit(osgb_dir / osgb_file(name, -1, ""), [root], 0, True)
    expand(root)
    (tiles_dir / "tileset.json").write_text(json.dumps(tree.tileset(), separators=(",", ":")))
    radius = float(np.sqrt(2) * spec.tile / 2 + 60.0)
    return (f"Data/{name}/tileset.json", [*centre.tolist(), radius]), stats


def _manifest(build: Path, size: str, seed: int, spec: Spec, stats: dict[str, Counter], seconds: float) -> dict:
    levels = range(spec.levels)
    files = {fmt: _files(build / fmt) for fmt in ("osgb", "3dtiles")}
    return {
        "generator": "pipeline25d_lab.scenes.oap3d", "version": GENERATOR_VERSION, "size": size, "seed": seed,
        "spec": {**spec.__dict__, "tiles": list(spec.tiles)}, "srs": SRS, "origin": list(ORIGIN),
        "extent_m": list(spec.extent), "generation_s": round(seconds, 1),
        "levels": [{"level": k, "texel_m": spec.texel(k), "triangles": stats["triangles"][k],
                    "osgb_bytes": stats["osgb"][k], "3dtiles_glb_bytes": stats["3dtiles"][k]} for k in levels],
        "formats": {fmt: {"path": fmt, "files": n, "bytes": b} for fmt, (n, b) in files.items()},
        "inputs": {"osgb": "osgb", "3dtiles": "3dtiles/tileset.json"},
        "totals": {"bytes": sum(b for _, b in files.values()), "finest_triangles": stats["triangles"][spec.levels - 1],
                   "files": sum(n for n, _ in files.values())},
    }


def _files(folder: Path) -> tuple[int, int]:
    """(files, bytes) under ``folder``."""
    n = size = 0
    for dirpath, _, names in os.walk(folder):
        for name in names:
            n += 1
            size += os.stat(os.path.join(dirpath, name)).st_size
    return n, size


def level_of_file(path: Path) -> str:
    """The level a dataset file holds ("0".."n"), or "index" (metadata.xml, tileset JSONs)."""
    m = re.search(r"_L(\d+)(?:_\d+)?\.(?:osgb|glb)$", path.name)
    if m:
        return m.group(1)
    return "0" if re.fullmatch(r"Tile_[-+]\d+_[-+]\d+\.osgb", path.name) else "index"


def levels_used(manifest: dict, fmt: str, gsd: float) -> dict:
    """Bytes a reader must read at ``gsd``: the level drawn and, for OSGB, every file above it
    (a PagedLOD tree is walked from its root), for 3D Tiles its tileset JSONs (REPLACE
    refinement reads no coarser content); {"level", "bytes"}."""
    spec = Spec(**{**manifest["spec"], "tiles": tuple(manifest["spec"]["tiles"])})
    level = spec.level_for_gsd(gsd)
    rows = manifest["levels"]
    if fmt == "osgb":
        used = sum(r["osgb_bytes"] for r in rows if r["level"] <= level)
        used += manifest["formats"]["osgb"]["bytes"] - sum(r["osgb_bytes"] for r in rows)   # metadata.xml
    else:
        used = rows[level]["3dtiles_glb_bytes"]
        used += manifest["formats"]["3dtiles"]["bytes"] - sum(r["3dtiles_glb_bytes"] for r in rows)   # JSONs
    return {"level": level, "texel_m": spec.texel(level), "bytes": used}


def existing_manifest(out: Path, size: str, seed: int) -> dict | None:
    """The manifest in ``out`` if it records this size, seed and version and its files are all there."""
    try:
        manifest = json.loads((out / "manifest.json").read_text())
    except (OSError, ValueError):
        return None
    if not (isinstance(manifest, dict) and manifest.get("size") == size and manifest.get("seed") == seed
            and manifest.get("version") == GENERATOR_VERSION):
        return None
    for fmt, rec in manifest.get("formats", {}).items():
        if _files(out / fmt) != (rec.get("files"), rec.get("bytes")):
            return None
    return manifest


def main(argv: list[str] | None = None, prog: str | None = None) -> int:
    """CLI: ``python -m pipeline25d_lab.scenes.oap3d OUT [--size S] [--seed N]``."""
    parser = argparse.ArgumentParser(prog=prog, description=__doc__.split("\n\n")[0])
    parser.add_argument("out_dir", type=Path, help="folder to write (osgb/, 3dtiles/, manifest.json)")
    parser.add_argument("--size", default="quarter", choices=sorted(SIZES))
    parser.add_argument("--seed", type=int, default=7)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    manifest = generate_oap3d(args.out_dir, args.size, args.seed, progress=print)
    print(json.dumps({k: manifest[k] for k in ("size", "extent_m", "generation_s", "totals")}))  # noqa: T201
    return 0


if __name__ == "__main__":
    sys.exit(main())
