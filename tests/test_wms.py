"""The WMS mapfile served by the real MapServer (Debian's cgi-mapserver 8.0) over HTTP on 127.0.0.1.

Synthetic COGs with a known pattern (every alpha value, a transparent strip, a JPEG map with a
mask) check the mapfile against GDAL's reading of the same files; one test serves the maps of a
small demo city run through the workflow (its ``wms`` rule). The folder is moved after the
mapfile is written, so every request also checks that its paths are relative.
"""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
import xml.etree.ElementTree as ET
from pathlib import Path
from urllib.parse import urlencode

import numpy as np
import pytest

from pipeline25d.core.errors import InputFileError, MapServiceError
from pipeline25d.core.raster import gdal
from pipeline25d.publish.wms import EXTRA_SRS, WMSServer, find_mapserv, write_mapfile

WMS = "{http://www.opengis.net/wms}"
EPSG = 25832
GSD = 0.5
# name -> (origin x, origin y, width, height, compression); the JPEG map keeps its alpha as a mask
SYNTHETIC = {"az045_el45": (500000.0, 5700040.0, 120, 96, "DEFLATE"),
             "az000_el90": (500013.5, 5700061.0, 90, 70, "JPEG")}
APT = ["apt-get", "install", "-y", "-qq", "-o", "DPkg::Lock::Timeout=600", "cgi-mapserver", "mapserver-bin"]


@pytest.fixture(scope="module")
def mapserv() -> str:
    """MapServer's CGI program, installed with apt-get when missing (skip only when that fails)."""
    try:
        return find_mapserv()
    except MapServiceError:
        pass
    sudo = [] if os.geteuid() == 0 else ["sudo", "-n"]
    try:
        proc = subprocess.run(sudo + APT, capture_output=True, text=True, timeout=900,
                              env={**os.environ, "DEBIAN_FRONTEND": "noninteractive"})
        why = proc.stderr.strip().splitlines()[-1:] if proc.returncode else []
    except (OSError, subprocess.TimeoutExpired) as exc:
        why = [str(exc)]
    try:
        return find_mapserv()
    except MapServiceError as exc:
        pytest.skip(f"{exc}; `{' '.join(sudo + APT)}` failed: {' '.join(why) or 'mapserv still missing'}")


def pattern(width: int, height: int, seed: int) -> np.ndarray:
    """(4, h, w) uint8: colour from the pixel position and a seed; alpha 0 in the first 10
    columns, every value 0..255 in the bottom 20 rows, opaque elsewhere."""
    rows, cols = np.mgrid[:height, :width]
    rng = np.random.default_rng(seed)
    rgba = np.stack([(3 * cols + 5 * rows) % 256, (7 * cols + seed) % 256, rng.integers(0, 256, (height, width)),
                     np.full((height, width), 255)]).astype(np.uint8)
    rgba[3, -20:] = (np.arange(20 * width).reshape(20, width) % 256).astype(np.uint8)
    rgba[3, :, :10] = 0
    return rgba


def write_cog(path: Path, rgba: np.ndarray, x0: float, y0: float, compression: str, epsg: int | None = EPSG,
              bands: int = 4) -> None:
    g = gdal()
    mem = g.GetDriverByName("MEM").Create("", rgba.shape[2], rgba.shape[1], bands, g.GDT_Byte)
    mem.SetGeoTransform((x0, GSD, 0.0, y0, 0.0, -GSD))
    if epsg:
        mem.SetProjection(f"EPSG:{epsg}")
    for b in range(bands):
        mem.GetRasterBand(b + 1).WriteArray(rgba[b])
    if bands == 4:
        mem.GetRasterBand(4).SetColorInterpretation(g.GCI_AlphaBand)
    path.parent.mkdir(parents=True, exist_ok=True)
    g.GetDriverByName("COG").CreateCopy(str(path), mem, options=[f"COMPRESS={compression}", "BLOCKSIZE=128"])


def srs(epsg: int):
    """An osr.SpatialReference in x, y (longitude, latitude) order."""
    from osgeo import osr

    ref = osr.SpatialReference()
    ref.ImportFromEPSG(epsg)
    ref.SetAxisMappingStrategy(osr.OAMS_TRADITIONAL_GIS_ORDER)
    return ref


def cog_extent(path: Path) -> tuple[float, float, float, float]:
    ds = gdal().Open(str(path))
    x0, dx, _, y0, _, dy = ds.GetGeoTransform()
    return x0, y0 + ds.RasterYSize * dy, x0 + ds.RasterXSize * dx, y0


def cog_rgba(path: Path) -> np.ndarray:
    """(4, h, w) as GDAL reads the COG: its alpha band, or its mask as the alpha."""
    ds = gdal().Open(str(path))
    arr = ds.ReadAsArray()
    if arr.shape[0] == 3:
        arr = np.concatenate([arr, ds.GetRasterBand(1).GetMaskBand().ReadAsArray()[None]])
    return arr


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory) -> Path:
    """results/<scene>/ with two synthetic maps and their mapfile, moved after it was written."""
    where = tmp_path_factory.mktemp("synthetic") / "results" / "syn"
    for k, (pid, (x0, y0, w, h, compression)) in enumerate(SYNTHETIC.items()):
        write_cog(where / "maps" / f"{pid}.tif", pattern(w, h, k), x0, y0, compression)
    write_mapfile("syn", sorted((where / "maps").glob("*.tif")), where / "wms" / "syn.map")
    moved = where.parent.parent / "moved"
    shutil.move(where, moved)
    assert str(where.parent.parent) not in (moved / "wms" / "syn.map").read_text()
    return moved


def start(mapfile: Path, mapserv: str):
    server = WMSServer(mapfile, mapserv=mapserv)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return server


@pytest.fixture(scope="module")
def synthetic_wms(synthetic, mapserv):
    server = start(synthetic / "wms" / "syn.map", mapserv)
    yield server
    server.shutdown()
    server.server_close()


def request(server: WMSServer, **params) -> tuple[str, bytes]:
    query = {"SERVICE": "WMS", "VERSION": "1.3.0", **params}
    with urllib.request.urlopen(f"{server.url}?{urlencode(query)}", timeout=120) as resp:
        return resp.headers["Content-Type"], resp.read()


def get_map(server: WMSServer, layer: str, crs: str, bbox: tuple[float, ...], width: int, height: int) -> np.ndarray:
    """A GetMap as (4, h, w) uint8 RGBA, decoded by GDAL."""
    ctype, body = request(server, REQUEST="GetMap", LAYERS=layer, STYLES="", CRS=crs, FORMAT="image/png",
                          BBOX=",".join(repr(v) for v in bbox), WIDTH=width, HEIGHT=height)
    assert ctype == "image/png", body[:500]
    name = f"/vsimem/wms_{threading.get_ident()}.png"
    gdal().FileFromMemBuffer(name, body)
    try:
        ds = gdal().Open(name)
        assert ds.RasterCount == 4
        return ds.ReadAsArray()
    finally:
        gdal().Unlink(name)


def compare_window(server: WMSServer, cog: Path, col: int, row: int, width: int, height: int) -> dict:
    """GetMap of a pixel-aligned window at the COG's own resolution in its CRS against the COG.

    Alpha must be equal. Colour: equal where opaque; where 0 < alpha < 255 MapServer blends the
    pixel onto its transparent canvas premultiplied by alpha and in 8 bits (RB_MIX_PIXEL), and the
    PNG writer divides it again: one premultiplied step of rounding is 255 / alpha colour steps,
    plus one for the rounding back, so the tolerance is 255 / alpha + 1. Colour under alpha 0 is
    undefined. Returns the largest differences found.
    """
    want = cog_rgba(cog)[:, row:row + height, col:col + width]
    x0, _, _, y0 = cog_extent(cog)
    bbox = (x0 + col * GSD, y0 - (row + height) * GSD, x0 + (col + width) * GSD, y0 - row * GSD)
    got = get_map(server, cog.stem, f"EPSG:{EPSG}", bbox, width, height).astype(int)
    alpha = want[3].astype(int)
    np.testing.assert_array_equal(got[3], alpha)
    diff = np.abs(got[:3] - want[:3]).max(axis=0)
    opaque, partial = alpha == 255, (alpha > 0) & (alpha < 255)
    assert opaque.any()
    np.testing.assert_array_equal(diff[opaque], 0)
    assert np.all(diff[partial] <= 255 / alpha[partial] + 1), diff[partial].max()
    return {"opaque": int(diff[opaque].max()), "partial": int(diff[partial].max()) if partial.any() else None,
            "n_partial": int(partial.sum())}


def test_mapfile_lists_every_map_with_relative_paths_and_the_three_crs(synthetic):
    text = (synthetic / "wms" / "syn.map").read_text()
    for pid in SYNTHETIC:
        assert f'NAME "{pid}"' in text and f'DATA "../maps/{pid}.tif"' in text
    assert f'"wms_srs" "EPSG:{EPSG} EPSG:3857 EPSG:4326"' in text and '"wms_enable_request" "*"' in text


def test_capabilities_list_every_layer_with_its_crs_and_extent(synthetic, synthetic_wms):
    from osgeo import osr

    ctype, body = request(synthetic_wms, REQUEST="GetCapabilities")
    assert ctype.startswith("text/xml")
    root = ET.fromstring(body).find(f"{WMS}Capability/{WMS}Layer")
    assert {e.text for e in root.findall(f"{WMS}CRS")} == {f"EPSG:{EPSG}", *EXTRA_SRS}
    layers = {e.findtext(f"{WMS}Name"): e for e in root.findall(f"{WMS}Layer")}
    assert set(layers) == set(SYNTHETIC)
    to_wgs84 = osr.CoordinateTransformation(srs(EPSG), srs(4326))
    for pid, layer in layers.items():
        assert layer.findtext(f"{WMS}Title") == f"{pid}: azimuth {int(pid[2:5])} degrees, " \
            f"elevation {int(pid[-2:])} degrees" + (" (nadir)" if pid.endswith("90") else "")
        assert [e.text for e in layer.findall(f"{WMS}CRS")] == [f"EPSG:{EPSG}"]     # the rest inherited from the root
        extent = cog_extent(synthetic / "maps" / f"{pid}.tif")
        box = next(e for e in layer.findall(f"{WMS}BoundingBox") if e.get("CRS") == f"EPSG:{EPSG}")
        # MapServer 8.0 prints projected bounding boxes with %g (6 significant digits)
        assert [float(box.get(k)) for k in ("minx", "miny", "maxx", "maxy")] == [float(f"{v:g}") for v in extent]
        # the geographic box (%.6f degrees) against GDAL's own transform of the COG's extent
        west, south, east, north = to_wgs84.TransformBounds(*extent, 21)
        geo = layer.find(f"{WMS}EX_GeographicBoundingBox")
        got = [float(geo.findtext(f"{WMS}{k}")) for k in ("westBoundLongitude", "southBoundLatitude",
                                                            "eastBoundLongitude", "northBoundLatitude")]
        np.testing.assert_allclose(got, [west, south, east, north], rtol=0, atol=1.5e-6)


@pytest.mark.parametrize("pid", list(SYNTHETIC))
def test_getmap_in_the_map_crs_returns_the_cog_pixels(synthetic, synthetic_wms, pid):
    cog = synthetic / "maps" / f"{pid}.tif"
    x0, y0, w, h, compression = SYNTHETIC[pid]
    if compression == "DEFLATE":          # lossless: the COG holds the pattern itself
        np.testing.assert_array_equal(cog_rgba(cog), pattern(w, h, list(SYNTHETIC).index(pid)))
    # a window holding the transparent strip, opaque pixels and the bottom rows' every alpha value
    found = compare_window(synthetic_wms, cog, 3, 11, w - 13, h - 11)
    if compression == "DEFLATE":
        assert found["n_partial"] > 1000 and found["partial"] >= 1     # the tolerance was needed and held
    else:
        assert found["n_partial"] == 0                                 # a mask is all or nothing


def test_getmap_in_web_mercator_has_data_over_the_map_and_nothing_outside(synthetic, synthetic_wms):
    from osgeo import osr

    pid = "az045_el45"
    cog = synthetic / "maps" / f"{pid}.tif"
    want = cog_rgba(cog)
    x0, y0 = cog_extent(cog)[0], cog_extent(cog)[3]
    scene, merc = srs(EPSG), srs(3857)
    minx, miny, maxx, maxy = osr.CoordinateTransformation(scene, merc).TransformBounds(*cog_extent(cog), 21)
    pad_x, pad_y = 0.25 * (maxx - minx), 0.25 * (maxy - miny)
    bbox = (minx - pad_x, miny - pad_y, maxx + pad_x, maxy + pad_y)
    size = 240
    got = get_map(synthetic_wms, pid, "EPSG:3857", bbox, size, size)
    # every output pixel centre back in the map's CRS, as the COG pixel it falls in
    cols, rows = np.meshgrid(np.arange(size) + 0.5, np.arange(size) + 0.5)
    mx = bbox[0] + cols * (bbox[2] - bbox[0]) / size
    my = bbox[3] - rows * (bbox[3] - bbox[1]) / size
    pts = np.array(osr.CoordinateTransformation(merc, scene).TransformPoints(np.c_[mx.ravel(), my.ravel()]))
    c = ((pts[:, 0] - x0) / GSD).reshape(size, size)
    r = ((y0 - pts[:, 1]) / GSD).reshape(size, size)
    h, w = want.shape[1:]
    outside = (c < -1) | (r < -1) | (c > w + 1) | (r > h + 1)
    assert outside.sum() > 0.3 * size * size and np.all(got[3][outside] == 0)
    # well inside the opaque part (2 px from any other pixel): opaque, with a colour of that neighbourhood
    opaque = want[3] == 255
    ci, ri = np.floor(c).astype(int), np.floor(r).astype(int)
    inner = ~outside & (ci >= 12) & (ci < w - 2) & (ri >= 2) & (ri < h - 22)
    assert inner.sum() > 0.2 * size * size and opaque[2:-20, 10:].all()
    assert np.all(got[3][inner] == 255)
    near = np.zeros(inner.sum(), bool)
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            near |= np.all(got[:3][:, inner] == want[:3][:, ri[inner] + dr, ci[inner] + dc], axis=0)
    assert near.all()
    # nearest-neighbour sampling: nearly every pixel is the very COG pixel under its centre
    exact = np.all(got[:3][:, inner] == want[:3][:, ri[inner], ci[inner]], axis=0)
    assert exact.mean() > 0.98, exact.mean()


def test_the_serve_command_answers_on_its_port_and_stops_on_ctrl_c(synthetic, mapserv):
    with socket.socket() as sock:                    # a free port
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    proc = subprocess.Popen([sys.executable, "-m", "pipeline25d.publish.wms", "serve",
                             str(synthetic / "wms" / "syn.map"), "--port", str(port)],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        url = f"http://127.0.0.1:{port}/wms?SERVICE=WMS&VERSION=1.3.0&REQUEST=GetCapabilities"
        for _ in range(100):
            try:
                with urllib.request.urlopen(url, timeout=30) as resp:
                    body = resp.read()
                break
            except OSError:
                assert proc.poll() is None, proc.stdout.read()
                time.sleep(0.1)
        else:
            pytest.fail(f"nothing answered on port {port} in 10 s")
        names = {e.findtext(f"{WMS}Name") for e in ET.fromstring(body).iter(f"{WMS}Layer")}
        assert names == {"syn", *SYNTHETIC}
    finally:
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=30)
    assert proc.returncode == 0 and f"http://127.0.0.1:{port}/wms?SERVICE=WMS&REQUEST=GetCapabilities" in out


def test_maps_that_cannot_be_served_are_named_with_the_problem(tmp_path):
    rgba = pattern(20, 20, 0)
    write_cog(tmp_path / "a" / "az045_el45.tif", rgba, 0.0, 20.0, "DEFLATE", bands=3)
    with pytest.raises(InputFileError, match=r"az045_el45.tif: no alpha band and no per-dataset mask"):
        write_mapfile("x", [tmp_path / "a" / "az045_el45.tif"], tmp_path / "x.map")
    write_cog(tmp_path / "b" / "az045_el45.tif", rgba, 500000.0, 20.0, "DEFLATE")
    write_cog(tmp_path / "b" / "az000_el90.tif", rgba, 500000.0, 20.0, "DEFLATE", epsg=32632)
    with pytest.raises(InputFileError,
                       match=r"b/az000_el90.tif: CRS EPSG:32632 differs from EPSG:25832 of .*az045_el45"):
        write_mapfile("x", [tmp_path / "b" / "az045_el45.tif", tmp_path / "b" / "az000_el90.tif"], tmp_path / "x.map")
    with pytest.raises(MapServiceError, match="perspective az045_el45 given twice"):
        write_mapfile("x", [tmp_path / "b" / "az045_el45.tif"] * 2, tmp_path / "x.map")
    shutil.copy(tmp_path / "b" / "az045_el45.tif", tmp_path / "b" / "overview.tif")
    with pytest.raises(InputFileError, match="overview.tif: the file name is not a perspective id"):
        write_mapfile("x", [tmp_path / "b" / "overview.tif"], tmp_path / "x.map")
    write_cog(tmp_path / "c" / "az045_el45.tif", rgba, 500000.0, 20.0, "DEFLATE", epsg=None)
    with pytest.raises(InputFileError, match="c/az045_el45.tif: its CRS has no EPSG code"):
        write_mapfile("x", [tmp_path / "c" / "az045_el45.tif"], tmp_path / "x.map")
    (tmp_path / "b" / "az090_el45.tif").write_bytes(b"not a tiff")
    with pytest.raises(InputFileError, match="az090_el45.tif: cannot be opened"):
        write_mapfile("x", [tmp_path / "b" / "az090_el45.tif"], tmp_path / "x.map")
    with pytest.raises(MapServiceError, match="x.map: no maps to publish"):
        write_mapfile("x", [], tmp_path / "x.map")
    assert not (tmp_path / "x.map").exists()


@pytest.mark.slow
def test_the_workflow_maps_are_served_as_they_are(tmp_path, mapserv):
    """A small demo city through the workflow up to its wms rule; each whole map served in its
    own CRS equals the COG (rendered maps have antialiased, partly transparent edges); each map's id
    layer is listed beside it."""
    from pipeline25d_lab.harness.bench import run_workflow
    from pipeline25d_lab.harness.killtest import demo_config

    config = {**demo_config(tmp_path / "scene", 0.25,
                            [{"azimuth": 45, "elevation": 45}, {"azimuth": 0, "elevation": 90}]),
              "scene": "wmsdemo"}
    t0 = time.monotonic()
    run_workflow(tmp_path / "run", config, extra=["results/wmsdemo/wms/wmsdemo.map"])
    results = tmp_path / "run" / "results" / "wmsdemo"
    assert not (results / "tms").exists()                  # only what the mapfile needs ran
    moved = shutil.move(results, tmp_path / "moved")
    server = start(Path(moved) / "wms" / "wmsdemo.map", mapserv)
    try:
        root = ET.fromstring(request(server, REQUEST="GetCapabilities")[1]).find(f"{WMS}Capability/{WMS}Layer")
        assert {e.findtext(f"{WMS}Name") for e in root.findall(f"{WMS}Layer")} == \
            {"az045_el45", "az000_el90", "az045_el45_ids", "az000_el90_ids"}     # objects.enabled: the id layers
        partial = transparent = 0
        for pid in ("az045_el45", "az000_el90"):
            cog = Path(moved) / "maps" / f"{pid}.tif"
            ds = gdal().Open(str(cog))
            assert ds.GetGeoTransform()[1] == GSD == config["gsd"]
            w, h = min(ds.RasterXSize, 2048), min(ds.RasterYSize, 2048)    # the whole map (MapServer's MAXSIZE is 4096)
            found = compare_window(server, cog, 0, 0, w, h)
            partial += found["n_partial"]
            transparent += int((cog_rgba(cog)[3, :h, :w] == 0).sum())
            print(pid, f"{ds.RasterXSize} x {ds.RasterYSize} px", found, f"{time.monotonic() - t0:.0f} s")
        assert partial > 0 and transparent > 0         # antialiased edges and empty land were compared too
    finally:
        server.shutdown()
        server.server_close()


def test_a_client_cannot_make_mapserver_open_another_mapfile(synthetic, synthetic_wms, mapserv, tmp_path):
    """``map=`` in any spelling is refused by the front (400), and MapServer itself, run directly with
    the service's config, does not open the mapfile a query names: the other file's title never shows."""
    other = tmp_path / "other.map"
    other.write_text((synthetic / "wms" / "syn.map").read_text().replace('"wms_title" "', '"wms_title" "OTHERMAP '))
    for name in ("map", "MAP", "Map"):
        query = urlencode({name: str(other), "SERVICE": "WMS", "REQUEST": "GetCapabilities"})
        with pytest.raises(urllib.error.HTTPError) as err:
            urllib.request.urlopen(f"{synthetic_wms.url}?{query}", timeout=60)
        assert err.value.code == 400 and b"OTHERMAP" not in err.value.read()
    ctype, body = request(synthetic_wms, REQUEST="GetCapabilities")       # the service still answers
    assert b"<WMS_Capabilities" in body and b"OTHERMAP" not in body
    env = {"PATH": os.environ.get("PATH", "/usr/bin:/bin"), "MAPSERVER_CONFIG_FILE": str(synthetic_wms.config),
           "MS_MAPFILE": str(synthetic_wms.mapfile), "REQUEST_METHOD": "GET",
           "QUERY_STRING": f"map={other}&SERVICE=WMS&REQUEST=GetCapabilities"}
    direct = subprocess.run([mapserv], env=env, capture_output=True, timeout=120).stdout
    assert b"OTHERMAP" not in direct
