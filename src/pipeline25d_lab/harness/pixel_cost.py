"""What each map pixel costs between render and web tile, step by step, per Mpx.

For one map of a finished run (``RESULTS/tiles/<pid>``, ``mosaic/<pid>.vrt``, ``maps/<pid>.tif``)
it times, in this process and on this machine, with each step's median of ``--repeat`` runs:

- the render tiles' GeoTIFF decode and encode (the tile write of the render job; the GL
  readback itself is in the render job's own seconds, ``logs/render``);
- the map: the mosaic copied into the kept, tiled map with its overviews
  (:func:`pipeline25d.stages.maps.patch.patched_map`, no warp) and its COG encode;
- the web-tile cut, by sub-step: the web-mercator blocks' warp (decode COG, warp, encode),
  and for every base tile its read (decode of the blocks), the average down to the tile
  (:func:`pipeline25d.stages.tiles.base.average_tile`), the tile's encode and its write, beside
  what gdal2tiles' own did (upsampled read of the window into the 4x query, its average); then the
  overview tiles (decode four children, average, encode, write);
- the whole cut (:func:`pipeline25d.stages.tiles.web.tms`) against ``gdal2tiles`` with its
  defaults on the same COG and zoom levels (a subprocess), and their ratio.

Each row counts the pixels a step decodes, copies or encodes, as passes over the map's own
pixels (``passes``: Mpx touched / map Mpx). ``--scale N`` cuts the map upsampled N x N
(bilinear) instead, for figures per Mpx less bound by a small map's fixed costs.

    python -m pipeline25d_lab.harness.pixel_cost results/demo az045_el45 --json cost.json
"""

from __future__ import annotations

import argparse
import hashlib
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path

import numpy as np

from pipeline25d.core.grid import Grid, Window
from pipeline25d.core.raster import gdal


def median_time(fn: Callable[[], object], repeat: int) -> float:
    """Median wall seconds of ``repeat`` calls of ``fn``."""
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def row(step: str, seconds: float, mpx: float, map_mpx: float, what: str) -> dict:
    """A table row: seconds, Mpx touched, s per Mpx and passes over the map's pixels."""
    return {"step": step, "s": round(seconds, 4), "mpx": round(mpx, 3),
            "s_per_mpx": round(seconds / mpx, 4) if mpx else None,
            "passes": round(mpx / map_mpx, 2) if map_mpx else None, "what": what}


def _mpx(ds) -> float:
    return ds.RasterXSize * ds.RasterYSize / 1e6


def render_tile_rows(tiles: list[Path], work: Path, map_mpx: float, repeat: int) -> list[dict]:
    """Decode of the render tiles and their encode as the render job writes them."""
    from pipeline25d.core.geotiff import write_rgba_geotiff

    g = gdal()
    arrays = [(g.Open(str(t)).ReadAsArray(), Grid.of_dataset(g.Open(str(t))), g.Open(str(t)).GetProjection())
              for t in tiles]
    mpx = sum(a.shape[1] * a.shape[2] for a, _, _ in arrays) / 1e6

    def decode():
        for t in tiles:
            g.Open(str(t)).ReadRaster()

    def encode():
        for k, (a, grid, wkt) in enumerate(arrays):
            write_rgba_geotiff(work / f"tile{k}.tif", np.moveaxis(a, 0, -1), grid, wkt)

    return [row("render: tile encode (ZSTD GeoTIFF)", median_time(encode, repeat), mpx, map_mpx, "encode"),
            row("mosaic: render tiles decode", median_time(decode, repeat), mpx, map_mpx, "decode")]


def map_rows(mosaic: Path, work: Path, map_mpx: float, repeat: int, compression: str = "deflate",
             quality: int = 85) -> list[dict]:
    """The kept map (mosaic copied, overviews built) and its COG encode, as the warp job makes an unwarped map."""
    from pipeline25d.stages.maps.patch import patched_map
    from pipeline25d.stages.maps.warp import cog_options, run_tool

    g = gdal()
    wkt = g.Open(str(mosaic)).GetProjection()
    gsd = Grid.of_dataset(g.Open(str(mosaic))).transform.a
    kept_dir = work / "kept"

    def kept():
        shutil.rmtree(kept_dir, ignore_errors=True)
        return patched_map(mosaic, mosaic, {"method": "none", "order": 0}, wkt, gsd, kept_dir)

    kept_s = median_time(kept, repeat)
    rows = [row("map: mosaic decode + kept map encode + overviews", kept_s, map_mpx * 4 / 3, map_mpx, "decode+encode")]
    digests = set()
    for threads in (1, 2):                                 # the warp job's threads: the same bytes, sooner
        cog = [opt for c in [*cog_options(compression, quality), f"NUM_THREADS={threads}"] for opt in ("-co", c)]
        out = work / f"map_cog{threads}.tif"
        cog_s = median_time(lambda: run_tool(["gdal_translate", "-q", "-of", "COG", *cog, str(kept_dir / "map.tif"),
                                              str(out)]), repeat)
        digests.add(hashlib.sha256(out.read_bytes()).hexdigest())
        rows.append(row(f"map: COG encode (decode kept, {compression}), {threads} thread{'s' * (threads > 1)}", cog_s,
                        map_mpx * 4 / 3, map_mpx, "decode+encode"))
    if len(digests) != 1:
        raise RuntimeError("the COG encoded with 1 and 2 threads differs")
    return rows


def tms_rows(cog: Path, work: Path, map_mpx: float, repeat: int, tile_format: str = "webp",
             quality: int = 85) -> list[dict]:
    """The web-tile cut's sub-steps, in this process (one worker)."""
    from osgeo_utils import gdal2tiles as g2t

    from pipeline25d.stages.tiles import base, web
    from pipeline25d.stages.tiles import blocks as blocks_mod

    g = gdal()
    grid, zooms = web.tile_grid(cog, "auto")
    max_zoom = int(zooms.split("-")[-1])
    factor = blocks_mod.stored_factor(grid, max_zoom)
    kept = blocks_mod.stored_grid(grid, factor)
    blocks = work / "blocks"
    jobs = [(b, w) for b, w in ((b, web.block_window(b, grid, max_zoom))
            for b in sorted(web.blocks_meeting(Window(0, 0, grid.width, grid.height), grid, max_zoom))) if w]

    def warp_blocks():
        shutil.rmtree(blocks, ignore_errors=True)
        blocks.mkdir(parents=True)
        for job in jobs:
            blocks_mod.warp_block(str(cog), str(blocks), grid, False, factor, job)

    warp_s = median_time(warp_blocks, repeat)
    block_mpx = sum(w.width * w.height for _, w in jobs) / 1e6
    vrt, tiles = work / "blocks.vrt", work / "tiles"
    g.BuildVRT(str(vrt), [str(b) for b in sorted(blocks.glob("*.tif"))], outputBounds=kept.bounds,
               xRes=kept.transform.a, yRes=-kept.transform.e)
    shutil.rmtree(tiles, ignore_errors=True)
    _, _, options = g2t.process_args([*web._gdal2tiles_args(zooms, 1, tile_format, quality, True), str(vrt),
                                      str(tiles)])
    conf, details = g2t.worker_tile_details(str(vrt), str(tiles), options)
    try:
        steps = _base_tile_steps(conf, details, options, repeat)
        over_s = median_time(lambda: _overview_tiles(conf, options, tiles, g2t), repeat)
    finally:
        base.close_source()
        shutil.rmtree(Path(conf.src_file).parent, ignore_errors=True)
    n_base = steps.pop("tiles")
    n_over = sum(1 for p in tiles.rglob(f"*.{conf.tile_extension}") if int(p.parts[-3]) < conf.tmaxz)
    tile_mpx, query_mpx = n_base * 256 ** 2 / 1e6, steps.pop("query_mpx")
    read_mpx, over_mpx = steps.pop("read_mpx"), n_over * 256 ** 2 / 1e6
    return [row("tms: blocks warp (decode COG, warp, average to tile pixels, ZSTD encode)", warp_s, block_mpx, map_mpx,
                "decode+copy+encode"),
            row("tms base: read (decode blocks, native size)", steps["read"], read_mpx, map_mpx, "decode"),
            row("tms base: average window -> tile (numpy, no query)", steps["average"], tile_mpx * 16, map_mpx, "copy"),
            row("tms base: (was) GDAL upsampled read of the VRT", steps["vrt_read"], query_mpx, map_mpx, "decode+copy"),
            row("tms base: (was) query made, GDAL average -> tile", steps["query_average"], query_mpx, map_mpx, "copy"),
            row(f"tms base: encode {conf.tile_extension}", steps["encode"], tile_mpx, map_mpx, "encode"),
            row("tms base: write files", steps["write"], tile_mpx, map_mpx, "write"),
            row("tms overviews: decode 4 children, average, encode, write", over_s, over_mpx * 5, map_mpx,
                "decode+copy+encode")]


def _base_tile_steps(conf, details, options, repeat: int) -> dict:
    """Median seconds, over ``repeat`` passes, of each base-tile sub-step, summed over the tiles
    that hold data; the tiles are written (the overviews read them)."""
    from osgeo_utils import gdal2tiles as g2t

    from pipeline25d.stages.tiles.base import average_tile, nearest_index

    g = gdal()
    mem, drv = g.GetDriverByName("MEM"), g.GetDriverByName(conf.tile_driver)
    ds = g.Open(conf.src_file)
    alpha_band = ds.GetRasterBand(1).GetMaskBand()
    nb, size, creation = conf.nb_data_bands, conf.tile_size, g2t._get_creation_options(options)
    runs: list[dict] = []
    for _ in range(repeat):
        t = dict.fromkeys(("read", "average", "vrt_read", "query_average", "encode", "write"), 0.0)
        n = query = read = 0
        for d in details:
            if not (d.rxsize and d.rysize and d.wxsize and d.wysize):
                continue
            c0 = time.perf_counter()
            data = np.frombuffer(ds.ReadRaster(d.rx, d.ry, d.rxsize, d.rysize, band_list=list(range(1, nb + 1))),
                                 np.uint8).reshape(nb, d.rysize, d.rxsize)
            alpha = np.frombuffer(alpha_band.ReadRaster(d.rx, d.ry, d.rxsize, d.rysize), np.uint8)
            c1 = time.perf_counter()
            rows, cols = nearest_index(d.rysize, d.wysize), nearest_index(d.rxsize, d.wxsize)
            window = np.concatenate([data, alpha.reshape(1, d.rysize, d.rxsize)])
            if not window[nb][rows][:, cols].any():
                continue
            tile = mem.Create("", size, size, nb + 1)
            tile.WriteRaster(0, 0, size, size,
                             average_tile(window, rows, cols, d.wx, d.wy, d.querysize, size).tobytes())
            c2 = time.perf_counter()
            ds.ReadRaster(d.rx, d.ry, d.rxsize, d.rysize, d.wxsize, d.wysize, band_list=list(range(1, nb + 1)))
            alpha_band.ReadRaster(d.rx, d.ry, d.rxsize, d.rysize, d.wxsize, d.wysize)
            c3 = time.perf_counter()
            q = mem.Create("", d.querysize, d.querysize, nb + 1)
            q.WriteRaster(d.wx, d.wy, d.wxsize, d.wysize, np.ascontiguousarray(window[:, rows][:, :, cols]).tobytes())
            g2t.scale_query_to_tile(q, mem.Create("", size, size, nb + 1), options)
            c4 = time.perf_counter()
            name = f"/vsimem/pixel_cost.{conf.tile_extension}"
            drv.CreateCopy(name, tile, strict=0, options=creation)
            blob = _read_vsimem(name)
            g.Unlink(name)
            c5 = time.perf_counter()
            out = Path(conf.output_file_path) / str(d.tz) / str(d.tx) / f"{d.ty}.{conf.tile_extension}"
            out.parent.mkdir(parents=True, exist_ok=True)
            out.write_bytes(blob)
            c6 = time.perf_counter()
            for k, dt in zip(t, (c1 - c0, c2 - c1, c3 - c2, c4 - c3, c5 - c4, c6 - c5)):
                t[k] += dt
            n, query, read = n + 1, query + d.querysize ** 2, read + d.rxsize * d.rysize
        runs.append(t)
    return {**{k: statistics.median(r[k] for r in runs) for k in runs[0]}, "tiles": n, "query_mpx": query / 1e6,
            "read_mpx": read / 1e6}


def _read_vsimem(name: str) -> bytes:
    g = gdal()
    f = g.VSIFOpenL(name, "rb")
    try:
        g.VSIFSeekL(f, 0, 2)
        size = g.VSIFTellL(f)
        g.VSIFSeekL(f, 0, 0)
        return bytes(g.VSIFReadL(1, size, f))
    finally:
        g.VSIFCloseL(f)


def _overview_tiles(conf, options, tiles: Path, g2t) -> None:
    """gdal2tiles' overview tiles of the base tiles in ``tiles``, in this process."""
    for p in tiles.rglob(f"*.{conf.tile_extension}"):
        if int(p.parts[-3]) < conf.tmaxz:
            p.unlink()
    for base_z in range(conf.tmaxz, conf.tminz, -1):
        for grp in g2t.group_overview_base_tiles(base_z, str(tiles), conf):
            g2t.create_overview_tile(base_z, grp, output_folder=str(tiles), tile_job_info=conf, options=options)


def cut_against_gdal2tiles(cog: Path, work: Path, processes: int, repeat: int, tile_format: str = "webp",
                           quality: int = 85) -> dict:
    """Median seconds of the whole cut (:func:`pipeline25d.stages.tiles.web.tms`, ``processes``
    workers) and of ``gdal2tiles`` with its defaults (``--xyz``, same zooms) on the same COG; their ratio."""
    from pipeline25d.stages.tiles.web import mercator_grid, tms, zoom_range

    zoom = zoom_range(mercator_grid(cog))
    ours = median_time(partial(tms, cog, zoom, work / "ours", processes=processes, tile_format=tile_format,
                               quality=quality), repeat)

    def default():
        shutil.rmtree(work / "default", ignore_errors=True)
        subprocess.run([sys.executable, "-m", "osgeo_utils.gdal2tiles", "-q", "--xyz", "-z", zoom, str(cog),
                        str(work / "default")], check=True)

    theirs = median_time(default, repeat)
    return {"zoom": zoom, "processes": processes, "tms_s": round(ours, 3), "gdal2tiles_default_s": round(theirs, 3),
            "speed_up": round(theirs / ours, 2)}


def pixel_cost(results: Path, pid: str, work: Path, repeat: int = 3, scale: int = 1, processes: int = 2,
               tile_format: str = "webp", quality: int = 85, compare: bool = True) -> dict:
    """The per-step table of one map of a finished run (see the module docstring)."""
    g = gdal()
    tiles = sorted(p for p in (results / "tiles" / pid).glob("*.tif") if not p.name.endswith(".ids.tif"))
    mosaic, cog = results / "mosaic" / f"{pid}.vrt", results / "maps" / f"{pid}.tif"
    map_mpx = _mpx(g.Open(str(cog)))
    rows = render_tile_rows(tiles, work, map_mpx, repeat) + map_rows(mosaic, work, map_mpx, repeat)
    if scale > 1:
        src = g.Open(str(cog))
        cog = work / "scaled.tif"
        g.Translate(str(cog), src, format="COG", width=src.RasterXSize * scale, height=src.RasterYSize * scale,
                    resampleAlg="bilinear", creationOptions=["COMPRESS=DEFLATE", "PREDICTOR=2", "LEVEL=1"])
    cut_mpx = _mpx(g.Open(str(cog)))
    rows += tms_rows(cog, work, cut_mpx, repeat, tile_format, quality)
    out = {"results": str(results), "perspective": pid, "map_mpx": round(map_mpx, 3), "scale": scale,
           "cut_map_mpx": round(cut_mpx, 3), "repeat": repeat, "rows": rows}
    if compare:
        out["tms_vs_gdal2tiles_default"] = cut_against_gdal2tiles(cog, work, processes, repeat, tile_format, quality)
    return out


def format_table(result: dict) -> str:
    """The rows as a text table."""
    lines = [f"{result['perspective']}: map {result['map_mpx']} Mpx, web tiles cut from {result['cut_map_mpx']} Mpx "
             f"(scale {result['scale']}), medians of {result['repeat']}",
             f"{'step':58s} {'s':>8s} {'Mpx':>8s} {'s/Mpx':>8s} {'passes':>7s}  kind"]
    for r in result["rows"]:
        lines.append(f"{r['step']:58s} {r['s']:8.3f} {r['mpx']:8.2f} {r['s_per_mpx'] or 0:8.4f} "
                     f"{r['passes'] or 0:7.2f}  {r['what']}")
    if "tms_vs_gdal2tiles_default" in result:
        c = result["tms_vs_gdal2tiles_default"]
        lines.append(f"TMS cut {c['tms_s']} s ({c['processes']} workers) vs gdal2tiles defaults "
                     f"{c['gdal2tiles_default_s']} s: {c['speed_up']}x (zooms {c['zoom']})")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("results", type=Path)
    ap.add_argument("pid")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--scale", type=int, default=1)
    ap.add_argument("--processes", type=int, default=2)
    ap.add_argument("--format", default="webp", choices=["webp", "png"])
    ap.add_argument("--no-compare", action="store_true", help="skip the whole cut against gdal2tiles")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="pixel_cost.") as tmp:
        result = pixel_cost(args.results, args.pid, Path(tmp), args.repeat, args.scale, args.processes, args.format,
                            compare=not args.no_compare)
    print(format_table(result))
    if args.json:
        from pipeline25d.core.atomic import write_json

        write_json(args.json, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
