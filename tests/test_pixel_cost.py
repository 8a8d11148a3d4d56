"""Each map pixel encoded as few times as it must be: the base tile's fast read gives
gdal2tiles' bytes, the COG is compressed with the job's threads, and the lab's per-step
cost table (pipeline25d_lab.harness.pixel_cost) counts the pixels of a tiny map right."""

from __future__ import annotations

import hashlib
from types import SimpleNamespace

import numpy as np
import pytest

from pipeline25d.core.crs import horizontal_wkt
from pipeline25d.core.geotiff import write_rgba_geotiff
from pipeline25d.core.grid import Grid
from pipeline25d.core.raster import gdal
from pipeline25d.stages.tiles.base import create_base_tile, nearest_index, read_upsampled


def _rgba(h: int, w: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    rgba = rng.integers(0, 256, (h, w, 4), dtype=np.uint8)
    rgba[..., 3] = 255
    rgba[: h // 4, : w // 3] = 0                       # a transparent corner, colour 0 under it
    return rgba


def test_nearest_index_is_gdals_nearest_upsampling():
    """GDAL's own nearest-neighbour RasterIO of a window into a larger buffer reads the
    source offsets of nearest_index, for odd ratios too."""
    rng = np.random.default_rng(1)
    for _ in range(200):
        n, m = int(rng.integers(1, 400)), int(rng.integers(1, 1025))
        ds = gdal().GetDriverByName("MEM").Create("", n, 1, 1, gdal().GDT_UInt16)
        ds.GetRasterBand(1).WriteArray(np.arange(n, dtype=np.uint16)[None, :])      # each pixel its own offset
        got = np.frombuffer(ds.ReadRaster(0, 0, n, 1, m, 1), np.uint16)
        assert np.array_equal(got, nearest_index(n, m)), (n, m)


def test_read_upsampled_equals_gdals_upsampled_read_of_one_raster(tmp_path):
    rgba = _rgba(300, 410)
    path = tmp_path / "map.tif"
    write_rgba_geotiff(path, rgba, Grid.north_up(0.0, 0.0, 1.0, 410, 300), horizontal_wkt("EPSG:3857"))
    ds = gdal().Open(str(path))
    for window, buf in [((0, 0, 410, 300), (1024, 1024)), ((37, 11, 255, 257), (1024, 731)),
                        ((5, 5, 64, 64), (64, 64))]:
        data, alpha = read_upsampled(ds, *window, *buf, 3)
        assert np.array_equal(data, np.frombuffer(ds.ReadRaster(*window, *buf, band_list=[1, 2, 3]), np.uint8)
                              .reshape(3, buf[1], buf[0]))
        assert np.array_equal(alpha, np.frombuffer(ds.GetRasterBand(4).ReadRaster(*window, *buf), np.uint8)
                              .reshape(buf[1], buf[0]))


@pytest.mark.parametrize(("tile_format", "webp_method"), [("png", None), ("webp", None), ("webp", 4)])
def test_base_tiles_are_gdal2tiles_own_bytes(tmp_path, tile_format, webp_method):
    """Every base tile of a map in web mercator (one raster: no block seams), cut by
    create_base_tile and by gdal2tiles' own create_base_tile, has the same sha256 (WEBP at
    libwebp's default effort, or told 4, that default)."""
    from osgeo_utils import gdal2tiles as g2t

    from pipeline25d.stages.tiles.web import _gdal2tiles_args

    src = tmp_path / "map.tif"
    write_rgba_geotiff(src, _rgba(700, 900, 2), Grid.north_up(1287632.0, 6129731.0, 0.19, 900, 700),
                       horizontal_wkt("EPSG:3857"))
    digests = {}
    for name, fn in [("ours", create_base_tile), ("g2t", g2t.create_base_tile)]:
        out = tmp_path / name
        _, _, options = g2t.process_args([*_gdal2tiles_args("auto", 1, tile_format, 85, True), str(src), str(out)])
        if name == "ours":
            options.webp_method = webp_method
        conf, details = g2t.worker_tile_details(str(src), str(out), options)
        assert details and details[0].querysize == 4 * conf.tile_size    # the scaled query the fast read replaces
        for d in details:
            fn(conf, d)
        digests[name] = {p.relative_to(out): hashlib.sha256(p.read_bytes()).hexdigest()
                         for p in out.rglob(f"*.{conf.tile_extension}")}
    assert len(digests["ours"]) >= 4 and digests["ours"] == digests["g2t"]


def test_the_web_tile_job_cuts_the_map_and_its_ids_with_the_jobs_workers(monkeypatch, tmp_path):
    """tms_job cuts the map and the id map each on the job's workers (core.cores.job_workers), each
    free to grow to the cores it may use; the map's tiles at the configured WEBP effort."""
    from pipeline25d import jobs
    from pipeline25d.stages.tiles import web

    cuts = []
    monkeypatch.setattr(web, "tms", lambda source, zoom, out, **k: cuts.append(
        (source, k["processes"], k["most"], k.get("webp_method"), k.get("cells_note"))) or {})
    monkeypatch.setattr(jobs, "job_workers", lambda threads: threads + 1)
    monkeypatch.setattr(jobs, "allowed_cores", lambda: 4)
    job = SimpleNamespace(input=SimpleNamespace(cog="m.tif", ids="m.ids.tif"), threads=1,
                          output=SimpleNamespace(tiles="t", stats=str(tmp_path / "s.json"), id_tiles="i",
                                                 id_stats=str(tmp_path / "i.json")),
                          params=SimpleNamespace(zoom="14-18", tile_format="webp", quality=85, webp_method=2, work="w",
                                                 id_work="iw", cells_note="n.json"))
    jobs.tms_job(job)
    assert cuts == [("m.tif", 2, 4, 2, "n.json"), ("m.ids.tif", 2, 4, None, None)]    # the map's digests noted


def test_the_map_service_job_makes_its_id_layers_on_the_jobs_workers(monkeypatch):
    """wms_job hands the job's workers (one thread, or the cores idle when it starts) to the
    mapfile's id layers: holding two threads, it waited for the run's last web-tile job."""
    from pipeline25d import jobs
    from pipeline25d.publish import wms

    seen, given = {}, []
    monkeypatch.setattr(wms, "write_mapfile", lambda *a, **k: seen.update(k))
    monkeypatch.setattr(jobs, "job_workers", lambda threads: given.append(threads) or threads + 1)
    job = SimpleNamespace(input=SimpleNamespace(maps=["m.tif"], ids=["objects.csv"]), threads=1,
                          output=SimpleNamespace(mapfile="s.map"), params=SimpleNamespace(scene="s"))
    jobs.wms_job(job)
    assert given == [1] and seen == {"objects": "objects.csv", "threads": 2}


def test_each_cog_encode_takes_the_cores_idle_when_it_runs(monkeypatch, tmp_path):
    """warp_job hands the job's threads to the warp; each COG encode (the map's here; the id map's
    calls the same warp.encode_options) asks GDAL for those or for the cores idle at that moment
    where more (core.cores.job_workers, measured then, not when the job started)."""
    from pipeline25d import jobs
    from pipeline25d.stages import gcps
    from pipeline25d.stages.maps import mosaic_sources, warp

    seen, gathered = {}, []
    monkeypatch.setattr(warp, "warp", lambda *a, **k: seen.update(k, args=a))
    monkeypatch.setattr(mosaic_sources, "build_mosaic", lambda tiles, vrt: gathered.append((tiles, vrt)))
    monkeypatch.setattr(gcps, "gather_gcps", lambda tiles, csv: gathered.append((tiles, csv)))
    job = SimpleNamespace(input=SimpleNamespace(plan="p.json"),
                          output=SimpleNamespace(mosaic="m.vrt", gcps="g.csv", cog="c.tif", meta="c.json"),
                          params=SimpleNamespace(tiles=["b.tif", "a.tif"], gcp_tiles=["a.gcps.csv"], warp={}, maps={},
                                                 work="w", cells_note="n.json"), threads=2)
    jobs.warp_job(job)
    assert seen["threads"] == 2 and seen["cells_note"] == "n.json"
    assert gathered == [(["a.tif", "b.tif"], "m.vrt"), (["a.gcps.csv"], "g.csv")]    # the mosaic first, then the warp
    assert seen["args"][:3] == ("m.vrt", "g.csv", "p.json")

    idle = iter([1, 3])                     # the cores idle at the first encode, then at the second
    given, calls = [], []
    monkeypatch.setattr(warp, "job_workers", lambda threads: given.append(threads) or max(threads, next(idle)))
    monkeypatch.setattr(warp, "run_tool", lambda args: calls.append(args) or gdal().Translate(
        args[-1], args[-2], format="COG"))
    mosaic = tmp_path / "map.tif"
    write_rgba_geotiff(mosaic, _rgba(64, 64), Grid.north_up(691000.0, 5334000.0, 0.5, 64, 64),
                       horizontal_wkt("EPSG:25832"))
    plan = SimpleNamespace(crs="EPSG:25832", gsd=0.5)
    for k in range(2):
        warp.warp_to_cog(mosaic, [], {"method": "none", "order": 0}, plan, tmp_path / f"cog{k}.tif", threads=2)
    assert given == [2, 2] and [a[:4] for a in calls] == [["gdal_translate", "-q", "-of", "COG"]] * 2
    assert [[o for o in a if o.startswith("NUM_THREADS")] for a in calls] == [["NUM_THREADS=2"], ["NUM_THREADS=3"]]
    assert gdal().Open(str(tmp_path / "cog0.tif")).ReadRaster() == gdal().Open(str(tmp_path / "cog1.tif")).ReadRaster()


def _tiny_run(root, pid="p"):
    """A finished run's files for one map: two render tiles, their mosaic VRT and the map COG."""
    from pipeline25d.stages.maps.mosaic_sources import build_mosaic

    wkt = horizontal_wkt("EPSG:25832")
    tiles = root / "tiles" / pid
    tiles.mkdir(parents=True)
    for k in range(2):
        write_rgba_geotiff(tiles / f"0_{k}.tif", _rgba(200, 160, k), Grid.north_up(691000.0 + 80 * k, 5334000.0,
                                                                                  0.5, 160, 200), wkt)
    (root / "mosaic").mkdir()
    (root / "maps").mkdir()
    build_mosaic([str(p) for p in sorted(tiles.glob("*.tif"))], root / "mosaic" / f"{pid}.vrt")
    gdal().Translate(str(root / "maps" / f"{pid}.tif"), str(root / "mosaic" / f"{pid}.vrt"), format="COG")
    return root


def test_pixel_cost_counts_the_pixels_of_each_step(tmp_path):
    from pipeline25d.stages.tiles.web import tms
    from pipeline25d_lab.harness.pixel_cost import format_table, pixel_cost

    results = _tiny_run(tmp_path / "results")
    work = tmp_path / "work"
    work.mkdir()
    out = pixel_cost(results, "p", work, repeat=1, compare=False)
    rows = {r["step"]: r for r in out["rows"]}
    assert out["map_mpx"] == pytest.approx(320 * 200 / 1e6, abs=1e-3)
    assert rows["render: tile encode (ZSTD GeoTIFF)"]["mpx"] == pytest.approx(2 * 160 * 200 / 1e6, abs=1e-3)
    assert rows["render: tile encode (ZSTD GeoTIFF)"]["passes"] == pytest.approx(1.0, abs=0.01)
    # the base tiles the harness cut are the cut's own: as many query and tile pixels as tiles at the top zoom
    tms(results / "maps" / "p.tif", "auto", tmp_path / "tms", tile_format="webp")
    zooms = sorted(int(p.name) for p in (tmp_path / "tms").iterdir())
    n_base = sum(1 for _ in (tmp_path / "tms" / str(zooms[-1])).rglob("*.webp"))
    assert rows["tms base: encode webp"]["mpx"] == pytest.approx(n_base * 256 ** 2 / 1e6, abs=1e-3)
    assert rows["tms base: (was) GDAL upsampled read of the VRT"]["mpx"] == pytest.approx(n_base * 1024 ** 2 / 1e6,
                                                                                        abs=1e-3)
    for r in out["rows"]:
        assert r["s"] >= 0 and r["passes"] == pytest.approx(r["mpx"] / out["cut_map_mpx"], abs=0.01)
    assert "tms base: read" in format_table(out)
