"""The render stage of a finished run replayed without its file writes, to time it on another driver.

``pack`` gathers what the render jobs of a run read: its plans, the LOD chunks they draw and, in
terrain-relative mode, each plan's DTM window as a pickled :class:`~pipeline25d.core.raster.DTM`,
into one folder that needs neither GDAL nor the run. ``replay`` renders every tile of every plan
there as the render jobs do (:func:`~pipeline25d.stages.render_block.render_plan_tile`: colour
with the object ids as a second target, then the GCP markers) in one GL context per plan, and
writes per perspective the seconds spent loading chunks and rendering, the Mpx drawn (content
boxes, as the plan prices them), the GCP image positions seen, and the RGBA of the tile that draws most, so that
two drivers (llvmpipe here, a lent GPU there) can be compared: ``--compare A B``.

    python -m pipeline25d_lab.harness.render_replay pack RESULTS_DIR PACK [--workdir DIR]
    python -m pipeline25d_lab.harness.render_replay replay PACK OUT
    python -m pipeline25d_lab.harness.render_replay compare OUT_A OUT_B
"""

from __future__ import annotations

import argparse
import json
import pickle
import shutil
import sys
import time
from pathlib import Path

import numpy as np

from pipeline25d.core.atomic import write_json


def pack(results: Path, out: Path, workdir: Path, max_tiles: int | None = None,
         perspectives: set[str] | None = None, ground_float32: bool = False) -> dict:
    """Copy ``results``' plans and the LOD chunks they draw into ``out``, with each terrain-mode
    plan's DTM window pickled (``workdir``: where the plans' relative DTM paths start);
    ``max_tiles``: keep only that many tiles from the middle of each plan (:func:`middle_tiles`), ``perspectives`` only
    those plans, ``ground_float32``: the DTM heights in float32 (half the bytes; 2 µm at 30 m) for a
    sample that must travel light."""
    from pyproj import CRS

    from pipeline25d.core.grid import Extent
    from pipeline25d.core.raster import DTM
    from pipeline25d.stages.plan import read_plan
    from pipeline25d.stages.render_block import ground_window

    (out / "plans").mkdir(parents=True, exist_ok=True)
    (out / "ground").mkdir(exist_ok=True)
    chunks: set[Path] = set()
    reach: dict[str, list[Extent]] = {}            # per DTM: the windows its plans sample
    crs: dict[str, str] = {}
    ground_of: dict[str, str] = {}
    for path in sorted((results / "plans").glob("*.json")):
        if perspectives and path.stem not in perspectives:
            continue
        pl = read_plan(path)
        if max_tiles is not None and len(pl.tiles) > max_tiles:
            data = json.loads(path.read_text())
            keep = middle_tiles([(t["row"], t["col"]) for t in data["tiles"]], max_tiles)
            data["tiles"] = [data["tiles"][i] for i in keep]
            write_json(out / "plans" / path.name, data)
            pl = read_plan(out / "plans" / path.name)
        else:
            shutil.copyfile(path, out / "plans" / path.name)
        chunks |= {Path(c.district) / f"{c.id}.npz" for t in pl.tiles for c in (*t.chunks, *t.casters)}
        if pl.projection == "terrain":     # a window per DTM; per plan for a sample, whose plans lie apart
            key = pl.dtm if max_tiles is None else f"{pl.dtm}#{pl.id}"
            reach.setdefault(key, []).append(ground_window(pl.tiles))
            crs[key] = pl.crs
            ground_of[pl.id] = f"{list(reach).index(key)}.pkl"
    for k, (key, windows) in enumerate(reach.items()):
        lo, hi = np.array([w[:2] for w in windows]).min(axis=0), np.array([w[2:] for w in windows]).max(axis=0)
        window = Extent(*lo, *hi)
        dtm = DTM(workdir / key.split("#")[0], crs[key], continuous=True, window=window)
        if dtm.crs_wkt and CRS.from_user_input(dtm.crs_wkt) == CRS.from_user_input(crs[key]):
            dtm.crs_wkt = ""                # the same CRS: no transform, so no pyproj where it is replayed
        if not dtm.crs_wkt:                 # a DTM with holes is read whole: keep only the cells drawn
            win = dtm.grid.window_covering(window, pad=2)
            h, w = dtm.values.shape
            rows, cols = slice(max(win.row0, 0), min(win.row1, h)), slice(max(win.col0, 0), min(win.col1, w))
            dtm.values, dtm.grid = dtm.values[rows, cols].copy(), dtm.grid.window(rows, cols)
        if ground_float32:
            dtm.values = dtm.values.astype(np.float32)
        (out / "ground" / f"{k}.pkl").write_bytes(pickle.dumps(dtm))
    write_json(out / "ground" / "plans.json", ground_of)
    for rel in sorted(chunks):
        (out / "lod" / rel.parent).mkdir(parents=True, exist_ok=True)
        shutil.copyfile(results / "lod" / rel, out / "lod" / rel)
    size = sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
    return {"plans": len(list((out / "plans").glob("*.json"))), "chunks": len(chunks), "bytes": size}


def middle_tiles(positions: list[tuple[int, int]], n: int) -> list[int]:
    """The indices, in their order, of the ``n`` tile ``positions`` (row, col) nearest the middle of
    them all: a compact block, whose chunks and DTM window are as small as a sample of ``n`` tiles'
    can be (``n`` tiles in list order would run along a row, or wrap from its end to the next)."""
    rc = np.array(positions, dtype=np.float64).reshape(-1, 2)
    distance = np.hypot(*(rc - rc.mean(axis=0)).T)
    return sorted(np.argsort(distance, kind="stable")[:n].tolist())


def replay(packed: Path, out: Path, objects: bool = True) -> dict:
    """Render every tile of every plan in ``packed``; write ``out/replay.json``, the GCPs seen and a sample tile."""
    from pipeline25d.stages.plan import read_plan
    from pipeline25d.stages.render import TileRenderer, create_context, renderer_info
    from pipeline25d.stages.render_block import ChunkCache, render_plan_tile
    from pipeline25d.stages.render_ids import IdRenderer

    out.mkdir(parents=True, exist_ok=True)
    ground_of = json.loads((packed / "ground" / "plans.json").read_text())
    report: dict = {"perspectives": {}}
    t_all = time.monotonic()
    ctx = create_context()
    try:
        report["driver"] = renderer_info(ctx)
        for path in sorted((packed / "plans").glob("*.json")):
            pl = read_plan(path)
            name = ground_of.get(pl.id)
            ground = pickle.loads((packed / "ground" / name).read_bytes()).sample if name else None
            renderer = TileRenderer(ctx, ambient=pl.tiles[0].render["ambient"], samples=pl.tiles[0].render["samples"],
                                    shadows=pl.shadows is not None, ids=objects)
            ids = IdRenderer(ctx, samples=pl.tiles[0].render["samples"]) if objects else None
            chunks = ChunkCache(packed / "lod", pl.tiles)      # the render job's: each chunk loaded once
            load_s = render_s = mpx = 0.0
            seen: dict[str, list[float]] = {}
            best: tuple = (0, None, None)                 # the tile that draws most: kept to compare drivers
            for tile in pl.tiles:
                t0 = time.monotonic()
                loaded = chunks.take(tile.chunks)
                t1 = time.monotonic()
                rgba, obs, _ = render_plan_tile(renderer, pl, tile, loaded, ground, None, ids)
                t2 = time.monotonic()
                load_s, render_s = load_s + t1 - t0, render_s + t2 - t1
                _, (w, h) = pl.content(tile)
                mpx += w * h / 1e6
                seen.update({o.id: [o.map_x / pl.pixel_size, o.map_y / pl.pixel_size] for o in obs})  # px
                covered = int((rgba[..., 3] > 0).sum())
                if covered > best[0]:
                    best = (covered, f"{tile.row}_{tile.col}", rgba)
            if best[2] is not None:
                np.savez_compressed(out / f"{pl.id}_sample_tile.npz", rgba=best[2])
            report["perspectives"][pl.id] = {"tiles": len(pl.tiles), "content_mpx": round(mpx, 2),
                                             "load_s": round(load_s, 2), "render_s": round(render_s, 2),
                                             "mpx_per_s": round(mpx / render_s, 2) if render_s else None,
                                             "gcps_seen": len(seen), "sample_tile": best[1]}
            write_json(out / f"{pl.id}_gcps.json", seen)
    finally:
        ctx.release()
    rows = report["perspectives"].values()
    report["total"] = {"tiles": sum(r["tiles"] for r in rows),
                       "content_mpx": round(sum(r["content_mpx"] for r in rows), 1),
                       "load_s": round(sum(r["load_s"] for r in rows), 1),
                       "render_s": round(sum(r["render_s"] for r in rows), 1),
                       "wall_s": round(time.monotonic() - t_all, 1)}
    write_json(out / "replay.json", report)
    return report


def compare(a: Path, b: Path) -> dict:
    """Per perspective: the sample tiles' mean and largest absolute difference (0-255, where both
    drew; where both runs kept the tile), and the GCP image positions seen by both drivers (count,
    RMS and largest distance, px)."""
    out = {}
    for ga_file in sorted(a.glob("*_gcps.json")):
        pid = ga_file.name.removesuffix("_gcps.json")
        row: dict = {}
        tiles = [d / f"{pid}_sample_tile.npz" for d in (a, b)]
        if all(t.exists() for t in tiles):
            ra, rb = (np.load(t)["rgba"].astype(float) for t in tiles)
            both = (ra[..., 3] > 0) & (rb[..., 3] > 0)
            diff = np.abs(ra[..., :3] - rb[..., :3])[both]
            row = {"tile_mean_abs": round(float(diff.mean()), 3) if diff.size else None,
                   "tile_max_abs": int(diff.max()) if diff.size else None,
                   "coverage_a": round(float((ra[..., 3] > 0).mean()), 4),
                   "coverage_b": round(float((rb[..., 3] > 0).mean()), 4)}
        ga, gb = (json.loads((d / f"{pid}_gcps.json").read_text()) for d in (a, b))
        common = sorted(set(ga) & set(gb))
        dist = np.hypot(*(np.array([ga[i] for i in common]) - np.array([gb[i] for i in common])).T) if common else []
        out[pid] = {**row, "gcps_a": len(ga), "gcps_b": len(gb), "gcps_both": len(common),
                    "gcp_rms_px": round(float(np.sqrt(np.mean(np.square(dist)))), 4) if common else None,
                    "gcp_max_px": round(float(np.max(dist)), 4) if common else None}
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m pipeline25d_lab.harness.render_replay",
                                 description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("pack")
    p.add_argument("results", type=Path)
    p.add_argument("out", type=Path)
    p.add_argument("--workdir", type=Path, default=Path("."))
    p.add_argument("--max-tiles", type=int, help="only this many tiles from the middle of each plan")
    p.add_argument("--perspectives", help="comma-separated: only these plans")
    p.add_argument("--ground-float32", action="store_true", help="DTM heights in float32 (half the bytes)")
    r = sub.add_parser("replay")
    r.add_argument("packed", type=Path)
    r.add_argument("out", type=Path)
    r.add_argument("--no-objects", action="store_true")
    c = sub.add_parser("compare")
    c.add_argument("a", type=Path)
    c.add_argument("b", type=Path)
    args = ap.parse_args(argv)
    if args.cmd == "pack":
        result = pack(args.results, args.out, args.workdir, args.max_tiles,
                      set(args.perspectives.split(",")) if args.perspectives else None, args.ground_float32)
    elif args.cmd == "replay":
        result = replay(args.packed, args.out, not args.no_objects)["total"]
    else:
        result = compare(args.a, args.b)
    print(json.dumps(result, indent=1))  # noqa: T201
    return 0


if __name__ == "__main__":
    sys.exit(main())
