"""Map services: a MapServer mapfile that publishes every perspective's COG as a WMS layer.

One layer per map, named by its perspective id (``az045_el45``), in the maps' own CRS and
offered in EPSG:3857 and EPSG:4326 too; transparency comes from each COG's alpha band or
per-dataset mask (MapServer reads both). Paths in the mapfile are relative to it, so the
results folder can be moved. The syntax is MapServer 8's (Debian 12: ``cgi-mapserver`` 8.0).

:func:`serve` runs Debian's ``mapserv`` as a CGI program behind a local HTTP server, for a
look at the service without Apache: ``python -m pipeline25d.publish.wms serve <mapfile>``.

With the id layer, each map also has a layer ``<pid>_ids`` that only GetFeatureInfo uses: asked at
a pixel (``INFO_FORMAT=text/html``) it answers the object there, its id, name, heights and
attributes; text/plain and GML answer its row number in the objects table (``value_0``).
"""

from __future__ import annotations

import argparse
import logging
import os
import re
import shutil
import subprocess
import tempfile
from concurrent.futures import ThreadPoolExecutor
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import NamedTuple, Sequence
from urllib.parse import parse_qsl, urlsplit

from pipeline25d.core.atomic import write_text
from pipeline25d.core.errors import InputFileError, MapServiceError
from pipeline25d.core.grid import Grid
from pipeline25d.core.raster import dataset_bounds, gdal
from pipeline25d.geometry.perspectives import ID_PATTERN, Perspective
from pipeline25d.publish.serve import serve_until_interrupted
from pipeline25d.publish.wms_ids import id_layer, id_path, row_raster, table_ids, write_join_table

log = logging.getLogger(__name__)

EXTRA_SRS = ("EPSG:3857", "EPSG:4326")     # web mercator and WGS 84, beside each map's own CRS
MAPSERV = ("/usr/lib/cgi-bin/mapserv", "mapserv")   # Debian's cgi-mapserver, else PATH
CGI_TIMEOUT_S = 120
# MapServer 8's config for the local service: a request may never name another mapfile
# (mapserv already refuses ``map=`` without MS_MAP_PATTERN; this says so explicitly)
MAPSERVER_CONFIG = 'CONFIG\n  ENV\n    MS_MAP_NO_OVERRIDE "1"\n  END\nEND\n'


class MapLayer(NamedTuple):
    """One perspective's COG as the mapfile needs it."""

    pid: str
    path: Path
    srs: str                                        # "EPSG:<code>"
    extent: tuple[float, float, float, float]       # minx, miny, maxx, maxy in that CRS


def read_layer(path: str | Path) -> MapLayer:
    """A map's layer: its id from the file name, its EPSG code and extent from the COG.

    Raises :class:`InputFileError` naming the file when it is not a perspective's map, cannot be
    opened, is not north up, has no EPSG-coded CRS, or has no alpha band or mask (transparency).
    """
    path = Path(path)
    if not re.fullmatch(ID_PATTERN, path.stem):
        raise InputFileError(path, "the file name is not a perspective id such as az045_el45")
    if '"' in str(path) or "\n" in str(path):
        raise InputFileError(path, "a path with a double quote or newline cannot be written in a mapfile")
    g = gdal()
    try:
        ds = g.Open(str(path))
    except RuntimeError as exc:
        raise InputFileError(path, f"cannot be opened: {exc}") from None
    gt = ds.GetGeoTransform(can_return_null=True)
    if gt is None or not Grid.from_gdal(gt, ds.RasterXSize, ds.RasterYSize).is_north_up:
        raise InputFileError(path, f"not a north-up georeferenced raster (geotransform {gt})")
    code = _epsg_code(ds.GetSpatialRef())
    if code is None:
        raise InputFileError(path, "its CRS has no EPSG code, which WMS clients need to ask for it")
    if not _has_transparency(ds):
        raise InputFileError(path, "no alpha band and no per-dataset mask: the map would be served opaque")
    return MapLayer(path.stem, path, f"EPSG:{code}", dataset_bounds(ds))


def _epsg_code(srs) -> str | None:
    """The EPSG code of an osr.SpatialReference (None: no CRS, or none GDAL can identify)."""
    if srs is None:
        return None
    if srs.GetAuthorityName(None) != "EPSG":
        try:
            srs.AutoIdentifyEPSG()
        except RuntimeError:
            return None
    return srs.GetAuthorityCode(None) if srs.GetAuthorityName(None) == "EPSG" else None


def _has_transparency(ds) -> bool:
    """MapServer's own rule: an alpha band (band 4 or later), else a per-dataset mask."""
    g = gdal()
    if any(ds.GetRasterBand(b).GetColorInterpretation() == g.GCI_AlphaBand for b in range(4, ds.RasterCount + 1)):
        return True
    flags = ds.GetRasterBand(1).GetMaskFlags()
    return bool(flags & g.GMF_PER_DATASET) and not flags & (g.GMF_ALL_VALID | g.GMF_NODATA)


def layer_title(pid: str) -> str:
    p = Perspective.from_id(pid)
    return (f"{pid}: azimuth {p.azimuth} degrees, elevation {p.elevation} degrees"
            + (" (nadir)" if p.elevation == 90 else ""))


def _extent(ext: Sequence[float]) -> str:
    return " ".join(repr(float(v)) for v in ext)


def mapfile_text(scene: str, layers: Sequence[MapLayer], folder: Path, objects: Path | None = None) -> str:
    """The mapfile of ``layers`` (one CRS) with data paths relative to ``folder``, the mapfile's own;
    with ``objects`` (the objects table as CSV), each map's id raster beside it as a queryable layer too."""
    srs = layers[0].srs
    union = (min(lr.extent[0] for lr in layers), min(lr.extent[1] for lr in layers),
             max(lr.extent[2] for lr in layers), max(lr.extent[3] for lr in layers))
    epsg = srs.split(":")[1]
    out = [
        "# MapServer 8 mapfile written by pipeline25d.publish.wms: one WMS layer per perspective's map",
        "MAP",
        f'  NAME "{scene}"',
        "  STATUS ON",
        f"  EXTENT {_extent(union)}",
        "  SIZE 512 512",
        "  UNITS METERS",
        '  IMAGETYPE "png"',
        f'  PROJECTION "init=epsg:{epsg}" END',
        "  OUTPUTFORMAT",
        '    NAME "png"',
        '    DRIVER "AGG/PNG"',
        '    MIMETYPE "image/png"',
        '    EXTENSION "png"',
        "    IMAGEMODE RGBA",
        "    TRANSPARENT ON",
        "  END",
        "  WEB",
        "    METADATA",
        f'      "wms_title" "{scene}: 2.5D maps"',
        f'      "wms_abstract" "Orthorectified multi-perspective 2.5D maps of {scene}, one layer per perspective"',
        f'      "wms_srs" "{" ".join(dict.fromkeys([srs, *EXTRA_SRS]))}"',
        '      "wms_enable_request" "*"',
        '      "wms_getmap_formatlist" "image/png"',
        '      "wms_bbox_extended" "true"',
        *(['      "wms_feature_info_mime_type" "text/html"'] if objects is not None else []),
        "    END",
        "  END",
    ]
    for lr in layers:
        out += [
            "  LAYER",
            f'    NAME "{lr.pid}"',
            "    TYPE RASTER",
            "    STATUS ON",
            f'    DATA "{os.path.relpath(lr.path, folder)}"',
            f"    EXTENT {_extent(lr.extent)}",
            f'    PROJECTION "init=epsg:{epsg}" END',
            "    METADATA",
            f'      "wms_title" "{layer_title(lr.pid)}"',
            "    END",
            "  END",
        ]
        if objects is not None:
            out += id_layer(lr.pid, _extent(lr.extent), epsg)
    return "\n".join([*out, "END", ""])


def write_mapfile(scene: str, maps: Sequence[str | Path], mapfile: str | Path, objects: str | Path | None = None,
                  threads: int = 1) -> list[MapLayer]:
    """Write the mapfile publishing ``maps`` (COGs named ``<pid>.tif``, one CRS) atomically; with
    ``objects`` (the objects table's CSV), also each map's id raster (:func:`id_layer`), ``threads``
    maps at a time (GDAL's reads and writes, most of the work, run outside Python's lock).

    Raises :class:`InputFileError` naming the map that cannot be served (see :func:`read_layer`)
    or whose CRS differs from the first map's, and :class:`MapServiceError` for no maps or a
    perspective given twice.
    """
    mapfile = Path(mapfile)
    if not maps:
        raise MapServiceError(f"{mapfile}: no maps to publish")
    layers = [read_layer(p) for p in maps]
    seen: dict[str, Path] = {}
    for lr in layers:
        if lr.pid in seen:
            raise MapServiceError(f"{mapfile}: perspective {lr.pid} given twice ({seen[lr.pid]}, {lr.path})")
        seen[lr.pid] = lr.path
        if lr.srs != layers[0].srs:
            raise InputFileError(lr.path, f"CRS {lr.srs} differs from {layers[0].srs} of {layers[0].path}")
    if objects is not None:
        rows = table_ids(Path(objects))
        for lr in layers:
            if not id_path(lr.path).is_file():
                raise InputFileError(id_path(lr.path), f"no id raster beside the map {lr.path}")
        with ThreadPoolExecutor(max(1, threads)) as pool:
            list(pool.map(lambda lr: row_raster(id_path(lr.path), rows, mapfile.parent / f"{lr.pid}.rows.tif"), layers))
        write_join_table(Path(objects), mapfile.parent)
    write_text(mapfile, mapfile_text(scene, layers, mapfile.resolve().parent,
                                     None if objects is None else Path(objects).resolve()))
    log.info("%s: %d WMS layers in %s", mapfile, len(layers), layers[0].srs)
    return layers


def find_mapserv() -> str:
    """The MapServer CGI program; :class:`MapServiceError` when it is not installed."""
    for name in MAPSERV:
        found = shutil.which(name)
        if found:
            return found
    raise MapServiceError("MapServer's CGI program (mapserv) is not installed: apt-get install cgi-mapserver")


class WMSServer(ThreadingHTTPServer):
    """An HTTP server answering every GET with MapServer's CGI program run on one mapfile.

    ``port`` 0 takes any free port. Call ``serve_forever()``; ``server_close()`` also removes the
    (empty) MapServer 8 config file it writes, which ``mapserv`` refuses to run without.
    """

    def __init__(self, mapfile: str | Path, host: str = "127.0.0.1", port: int = 0, mapserv: str | None = None):
        self.mapfile = Path(mapfile).resolve()
        if not self.mapfile.is_file():
            raise MapServiceError(f"{self.mapfile}: no such mapfile")
        self.mapserv = mapserv or find_mapserv()
        self._folder = tempfile.TemporaryDirectory(prefix="pipeline25d-wms-")
        self.config = Path(self._folder.name) / "mapserver.conf"
        self.config.write_text(MAPSERVER_CONFIG)
        super().__init__((host, port), CGIHandler)

    @property
    def url(self) -> str:
        host, port = self.server_address[:2]
        return f"http://{host}:{port}/wms"

    def server_close(self) -> None:
        super().server_close()
        self._folder.cleanup()


class CGIHandler(BaseHTTPRequestHandler):
    """GET -> ``mapserv`` with the CGI environment; its headers (``Status`` included) and body back."""

    server: WMSServer

    def do_GET(self) -> None:  # noqa: N802 (the http.server name)
        srv = self.server
        url = urlsplit(self.path)
        if any(name.strip().lower() == "map" for name, _ in parse_qsl(url.query, keep_blank_values=True)):
            self._answer(400, {"Content-Type": "text/plain"},
                         b"this service publishes one mapfile: the map parameter is not accepted\n")
            return
        env = {"PATH": os.environ.get("PATH", "/usr/bin:/bin"), "MAPSERVER_CONFIG_FILE": str(srv.config),
               "MS_MAPFILE": str(srv.mapfile), "GATEWAY_INTERFACE": "CGI/1.1", "REQUEST_METHOD": "GET",
               "QUERY_STRING": url.query, "SCRIPT_NAME": url.path, "SERVER_NAME": srv.server_address[0],
               "SERVER_PORT": str(srv.server_address[1]), "SERVER_PROTOCOL": "HTTP/1.1"}
        proc = subprocess.run([srv.mapserv], env=env, capture_output=True, timeout=CGI_TIMEOUT_S)
        head, body = split_cgi_output(proc.stdout)
        headers = dict(line.split(":", 1) for line in head.splitlines() if ":" in line)
        status = int(headers.pop("Status", "200").split()[0])
        if proc.returncode or "Content-Type" not in headers:
            status, headers = 500, {"Content-Type": "text/plain"}
            body = b"mapserv failed: " + proc.stdout + proc.stderr
        self._answer(status, headers, body)

    def _answer(self, status: int, headers: dict[str, str], body: bytes) -> None:
        self.send_response(status)
        for name, value in headers.items():
            self.send_header(name.strip(), value.strip())
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, format: str, *args) -> None:  # noqa: A002 (the http.server signature)
        log.info("%s %s", self.address_string(), format % args)


def split_cgi_output(out: bytes) -> tuple[str, bytes]:
    """A CGI program's output as (header lines, body): the header ends at the first blank line."""
    ends = [(i, len(sep)) for sep in (b"\r\n\r\n", b"\n\n") if (i := out.find(sep)) >= 0]
    if not ends:
        return "", out
    i, n = min(ends)
    return out[:i].decode("latin-1"), out[i + n:]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="pipeline25d wms", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    serve = sub.add_parser("serve", help="serve a mapfile's WMS through MapServer's CGI on a local port")
    serve.add_argument("mapfile", type=Path)
    serve.add_argument("--host", default="127.0.0.1",
                       help="address to listen on (default 127.0.0.1, this machine only)")
    serve.add_argument("--port", type=int, default=8081, help="port (default 8081)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    server = WMSServer(args.mapfile, args.host, args.port)
    log.info("WMS of %s at %s?SERVICE=WMS&REQUEST=GetCapabilities (Ctrl-C stops)", args.mapfile, server.url)
    serve_until_interrupted(server)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
