"""An input's bounding box before it is read, where that is cheap: for the work estimate at parse time.

:func:`input_box` answers in seconds at most, or not at all (None), and never raises: a file it
cannot box is left to ingest, whose reader reports what is wrong with it. Per format:

* OBJ: the ``v`` lines (up to :data:`SCAN_BYTES`), exact;
* PLY: the vertex element's x, y, z (binary: read in place, up to :data:`BINARY_SCAN_BYTES`;
  ASCII up to :data:`SCAN_BYTES`), exact;
* CityJSON and CityJSONSeq: the vertices with the file's ``transform`` (up to :data:`SCAN_BYTES`),
  exact, in ``metadata.referenceSystem``;
* CityGML: the CityModel's ``gml:boundedBy`` envelope, in its ``srsName`` (the file's own claim;
  None without one);
* 3D Tiles: the root tile's bounding volume (box, region or sphere) under the root transform,
  which encloses the content (an upper bound); of a box or sphere only the footprint counts,
  since an ECEF-aligned box tilted to local vertical spans kilometres of height it does not hold;
* an OSGB dataset: the coarsest level of the tiles at the ends of the ``Tile_±x_±y`` index
  ranges (at most four tiles, each one osgconv call), with ``metadata.xml``'s origin and SRS;
* a 3MX scene: the boxes of its root files' nodes, with each layer's SRSOrigin and SRS;
* an I3S scene layer package: its layer's ``fullExtent``, else its store's 2D ``extent`` in its
  ``indexCRS`` (a footprint: ArcGIS Pro writes no ``fullExtent``);
* glTF, GLB, b3dm, DAE, 3DS: None (the terrain job checks the estimate with every chunk's bounds).

The box is in the input's CRS (``Box.crs``; None: the scene's), offsets and a ContextCapture
``metadata`` applied as :func:`pipeline25d.formats.load_district` applies them.
"""

from __future__ import annotations

import re
import tempfile
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

SCAN_BYTES = 256 * 2 ** 20            # a text file larger than this is not scanned at parse time
BINARY_SCAN_BYTES = 4 * 2 ** 30        # a binary PLY's vertex block is read in place up to this size
_OBJ_VERTEX = re.compile(rb"^[ \t]*v[ \t]+(\S+)[ \t]+(\S+)[ \t]+(\S+)", re.M)
_TILE_NAME = re.compile(r"Tile_([+-]?\d+)_([+-]?\d+)$")
_COARSEST = 1.0e12                     # a map pixel this large draws every OSGB tile at its coarsest level


@dataclass(frozen=True)
class Box:
    """An input's (2, 3) float64 box ``[lo, hi]`` in ``crs`` (None: the scene CRS), read from ``source``.
    ``heights`` False: only its footprint holds (a bounding box tilted to the scene's vertical,
    whose z range is mostly the tilt, not the content's heights)."""

    corners: np.ndarray
    crs: str | None
    source: str
    heights: bool = True


def input_box(spec: dict[str, Any], base_dir: Path = Path(".")) -> Box | None:
    """The box of the input ``spec`` (an ``inputs.<name>`` entry), or None when it is not cheap to know."""
    from pipeline25d.formats import READERS, detect_format

    path = base_dir / spec["path"]
    try:
        fmt = spec.get("format", "auto")
        fmt = detect_format(path) if fmt == "auto" else fmt
        found = _FINDERS[fmt](path, spec) if fmt in _FINDERS else None
    except Exception:               # noqa: BLE001 - ingest reports what is wrong with the file
        return None
    if found is None:
        return None
    corners, crs, source, *heights = found
    corners = np.asarray(corners, dtype=np.float64)
    if corners.shape != (2, 3) or not np.isfinite(corners).all():
        return None
    if not READERS[fmt].georeferenced:
        if spec.get("up_axis", "z") == "y":       # a y-up export turned z-up, as the reader turns it
            from pipeline25d.formats.common import z_up

            turned = z_up(corners)
            corners = np.array([turned.min(axis=0), turned.max(axis=0)])
        offset = np.asarray(spec.get("offset", [0.0, 0.0, 0.0]), dtype=np.float64)
        if spec.get("metadata"):
            from pipeline25d.formats.contextcapture import read_metadata_xml

            try:
                crs, origin = read_metadata_xml(base_dir / spec["metadata"])
            except Exception:       # noqa: BLE001
                return None
            offset = offset + origin
        corners = corners + offset
    return Box(corners, spec.get("crs") or crs, source, *heights)


def _small(path: Path, limit: int = SCAN_BYTES) -> bool:
    return path.is_file() and path.stat().st_size <= limit


def _box_of(points: np.ndarray) -> np.ndarray | None:
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    return np.array([points.min(axis=0), points.max(axis=0)]) if len(points) else None


def _obj(path: Path, spec: dict) -> tuple | None:
    if not _small(path):
        return None
    from pipeline25d.formats.meshfile import tidied_obj_text

    data = path.read_bytes()
    data = tidied_obj_text(data) or data                     # as the reader reads it (line ends, marks)
    return _box_of(np.array(_OBJ_VERTEX.findall(data), dtype=np.float64)), None, "the OBJ vertices"


_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}


def _ply(path: Path, spec: dict) -> tuple | None:
    with open(path, "rb") as f:
        if f.readline().strip() != b"ply":
            return None
        fmt, elements = None, []
        while True:
            line = f.readline()
            if not line or len(elements) > 64:
                return None
            words = line.decode("ascii", "replace").split()
            if not words or words[0] in ("comment", "obj_info"):
                continue
            if words[0] == "end_header":
                break
            if words[0] == "format":
                fmt = words[1]
            elif words[0] == "element":
                elements.append((words[1], int(words[2]), []))
            elif words[0] == "property" and elements:
                elements[-1][2].append(words[1:])
        start = f.tell()
    if not elements or elements[0][0] != "vertex" or any(p[0] == "list" for p in elements[0][2]):
        return None
    _, count, props = elements[0]
    names = [p[1] for p in props]
    if not {"x", "y", "z"} <= set(names) or count <= 0:
        return None
    if fmt == "ascii":
        if not _small(path):
            return None
        columns = [names.index(k) for k in "xyz"]
        with open(path, "rb") as f:
            f.seek(start)
            points = np.loadtxt(f, max_rows=count, usecols=columns, dtype=np.float64, ndmin=2)
        return _box_of(points), None, "the PLY vertices"
    order = {"binary_little_endian": "<", "binary_big_endian": ">"}.get(fmt)
    dtype = np.dtype([(name, order + _PLY_TYPES[kind]) for kind, name in props]) if order else None
    if dtype is None or start + dtype.itemsize * count > min(path.stat().st_size, BINARY_SCAN_BYTES):
        return None
    vertices = np.memmap(path, dtype=dtype, mode="r", offset=start, shape=(count,))
    lo = [float(vertices[k].min()) for k in "xyz"]
    hi = [float(vertices[k].max()) for k in "xyz"]
    return np.array([lo, hi]), None, "the PLY vertices"


def _cityjson(path: Path, spec: dict) -> tuple | None:
    from pipeline25d.formats.cityjson import vertices_and_crs

    if not _small(path):
        return None
    points, crs = vertices_and_crs(path, spec.get("crs"))
    return _box_of(points), crs, "the CityJSON vertices"


def _citygml(path: Path, spec: dict) -> tuple | None:
    from lxml import etree

    from pipeline25d.formats.citygml import latitude_first

    lower = upper = srs = None
    for _, elem in etree.iterparse(str(path), events=("end",), recover=True, huge_tree=True,
                                   resolve_entities=False, no_network=True):
        local = etree.QName(elem).localname if isinstance(elem.tag, str) else ""
        if local in ("lowerCorner", "upperCorner"):
            values = [float(v) for v in (elem.text or "").split()]
            lower, upper = (values, upper) if local == "lowerCorner" else (lower, values)
        elif local == "Envelope":
            srs = elem.get("srsName")
            break
        elif local in ("cityObjectMember", "featureMember", "member"):
            return None             # an object before any envelope: the model has none
    if lower is None or upper is None or len(lower) != 3 or len(upper) != 3:
        return None
    from pipeline25d.formats.common import crs_name

    crs = spec.get("crs") or (crs_name(srs) if srs else None)
    if crs is None:
        return None
    corners = np.array([lower, upper], dtype=np.float64)
    if latitude_first(crs):
        corners = corners[:, [1, 0, 2]]
    return corners, crs, "the CityGML envelope"


def _tileset(path: Path, spec: dict) -> tuple | None:
    from pipeline25d.formats.tiles3d import ECEF
    from pipeline25d.formats.tileset_packages import tileset_of
    from pipeline25d.formats.tileset_tree import read_json, tile_matrix

    path = tileset_of(path)
    root = read_json(path)["root"]
    volume = root["boundingVolume"]
    transform = tile_matrix(root.get("transform"), path)
    if "region" in volume:
        west, south, east, north, bottom, top = (float(v) for v in volume["region"])
        lon, lat = np.degrees(np.meshgrid(np.linspace(west, east, 5), np.linspace(south, north, 5)))
        points = np.array([[x, y, z] for x, y in zip(lon.ravel(), lat.ravel()) for z in (bottom, top)])
        return _box_of(points), "EPSG:4979", "the tileset's root bounding region"
    if "box" in volume:
        centre, axes = np.split(np.asarray(volume["box"], dtype=np.float64), [3])
        axes = axes.reshape(3, 3)
        signs = np.array([[a, b, c] for a in (-1, 1) for b in (-1, 1) for c in (-1, 1)], dtype=np.float64)
        local = centre + signs @ axes
    elif "sphere" in volume:
        x, y, z, r = (float(v) for v in volume["sphere"])
        local = np.array([[x + a * r, y + b * r, z + c * r] for a in (-1, 1) for b in (-1, 1) for c in (-1, 1)])
    else:
        return None
    points = (np.c_[local, np.ones(len(local))] @ transform.T)[:, :3]
    return _box_of(points), spec.get("crs") or ECEF, "the tileset's root bounding volume", False


def _osgb(path: Path, spec: dict) -> tuple | None:
    from pipeline25d.formats.osgb import dataset_tiles, read_tile

    if not path.is_dir():
        return None
    roots = dataset_tiles(path)
    indexed = [(tuple(int(v) for v in m.groups()), r) for r in roots if (m := _TILE_NAME.match(r.stem))]
    if len(indexed) != len(roots):
        return None
    ends = {min(indexed, key=lambda t: t[0][axis] * sign)[1] for axis in (0, 1) for sign in (1, -1)}
    with tempfile.TemporaryDirectory(prefix="pipeline25d-box-") as tmp, ThreadPoolExecutor(len(ends)) as pool:
        tiles = pool.map(lambda k_root: read_tile(k_root[1], _COARSEST, Path(tmp) / f"t{k_root[0]}", path, "coarser"),
                         enumerate(sorted(ends)))
        points = [p.vertices for tile in tiles for p in tile.parts]
    if not points:
        return None
    crs, origin = None, np.zeros(3)
    if not spec.get("metadata") and (path / "metadata.xml").is_file():
        from pipeline25d.formats.contextcapture import read_metadata_xml

        crs, origin = read_metadata_xml(path / "metadata.xml")
    box = _box_of(np.concatenate(points))
    return (None if box is None else box + origin), crs, "the coarsest level of the OSGB tiles at the dataset's ends"


def _threemx(path: Path, spec: dict) -> tuple | None:
    from pipeline25d.formats.threemx import layers_of, read_group

    layers = layers_of(path)
    corners = [np.asarray([n["bbMin"], n["bbMax"]], dtype=np.float64) + layer.origin
               for layer in layers for n in read_group(layer.root).nodes]
    crs = {layer.crs for layer in layers}
    if not corners or len(crs) > 1:
        return None
    return _box_of(np.concatenate(corners)), crs.pop(), "the 3MX root nodes' boxes"


def _i3s(path: Path, spec: dict) -> tuple | None:
    from pipeline25d.formats.i3s import Layer
    from pipeline25d.formats.slpk import Package

    layer = Layer.of(Package(path), spec)
    extent, keys = layer.doc.get("fullExtent"), ("xmin", "ymin", "zmin", "xmax", "ymax", "zmax")
    if isinstance(extent, dict) and all(isinstance(extent.get(k), (int, float)) for k in keys):
        return _box_of([extent[k] for k in keys]), layer.crs, "the I3S layer's fullExtent"
    store = layer.doc.get("store") or {}        # ArcGIS Pro writes no fullExtent, but the store's 2D extent
    xy, index = store.get("extent"), str(store.get("indexCRS", ""))
    epsg = re.search(r"/EPSG/\d+/(\d+)$", index)
    if not (isinstance(xy, list) and len(xy) == 4 and all(isinstance(v, (int, float)) for v in xy) and epsg):
        return None
    return (_box_of([xy[0], xy[1], 0.0, xy[2], xy[3], 0.0]), f"EPSG:{epsg.group(1)}",
            "the I3S store's extent (its footprint)", False)


_FINDERS: dict[str, Callable[[Path, dict], tuple | None]] = {
    "obj": _obj, "ply": _ply, "cityjson": _cityjson, "citygml": _citygml, "3dtiles": _tileset, "osgb": _osgb,
    "3mx": _threemx, "i3s": _i3s}
