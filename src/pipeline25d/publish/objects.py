"""The scene's objects: one table of every object id with its name, attributes and heights.

Every object that ingest numbered (``chunks/<district>/objects.json``, ids of
:mod:`pipeline25d.stages.objects`) gets one row: id, district, name (its key in the input),
its type and attributes as the input gives them (CityJSON: read from the file here; CityGML,
3D Tiles batch tables and glTF property tables: handed on by their readers through ingest,
``chunks/<district>/attributes.json``; other formats give the name alone), the model's height
(highest minus lowest z of its faces in the chunks, or its ``measuredHeight`` attribute where
the input gives one in metres) and the
height the heights stage measured on the maps (``heights.csv``, matched by name), with the
object's extent (a rectangle in the scene CRS) as its geometry. Written as

* a GeoPackage (``objects.gpkg``, layer ``objects``), which QGIS and every OGR client open;
* a CSV of the same columns (no geometry) after ``row``, its 1-based row number, which MapServer
  joins to the id layer's query (:func:`pipeline25d.publish.wms.row_raster`);
* small JSON shards for the viewer (``shards/index.json`` and ``shards/<slot>/<n>.json``): the
  objects of one district split by the top bits of their local id, so that a click fetches
  one shard of at most about :data:`SHARD_OBJECTS` objects.
"""

from __future__ import annotations

import csv
import io
import json
import logging
import math
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pipeline25d.core.atomic import atomic_path, replace_dir, write_bytes, write_json
from pipeline25d.formats.attributes import Limiter, clean_text
from pipeline25d.stages.chunks import load_npz, unpack_parts
from pipeline25d.stages.objects import LOCAL, LOCAL_BITS

log = logging.getLogger(__name__)

SHARD_OBJECTS = 512
COLUMNS = ("id", "district", "name", "type", "model_height", "measured_height", "attributes")


@dataclass
class SceneObject:
    """One row of the table."""

    id: int
    district: str
    name: str
    type: str = ""
    model_height: float | None = None
    measured_height: float | None = None
    attributes: dict = field(default_factory=dict)
    extent: tuple[float, float, float, float] | None = None       # xmin, ymin, xmax, ymax

    def row(self) -> dict:
        return {"id": self.id, "district": self.district, "name": self.name, "type": self.type,
                "model_height": _round(self.model_height), "measured_height": _round(self.measured_height),
                "attributes": self.attributes}


def _round(v: float | None) -> float | None:
    return None if v is None or not math.isfinite(v) else round(float(v), 3)


def chunk_extents(district_dir: Path) -> dict[int, np.ndarray]:
    """id -> [xmin, ymin, zmin, xmax, ymax, zmax] over the faces of each object in a district's chunks."""
    out: dict[int, np.ndarray] = {}
    for npz in sorted(district_dir.glob("c*.npz")):
        data = load_npz(npz)
        for part in unpack_parts(data, data["origin"]):
            if part.object_ids is None or part.face_objects is None or not len(part.faces):
                continue
            corners = part.vertices[part.faces]                       # (m, 3, 3)
            ids = part.object_ids[part.face_objects]
            for oid in np.unique(ids):
                pts = corners[ids == oid].reshape(-1, 3)
                box = np.concatenate([pts.min(axis=0), pts.max(axis=0)])
                old = out.get(int(oid))
                out[int(oid)] = box if old is None else np.concatenate([np.minimum(old[:3], box[:3]),
                                                                        np.maximum(old[3:], box[3:])])
    return out


def cityjson_objects(path: str | Path) -> dict[str, dict]:
    """key -> CityObject (type, attributes) of a CityJSON (.json) or CityJSONSeq (.jsonl) file;
    {} with a warning when it cannot be read (the table then has names without attributes)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
        docs = [json.loads(line) for line in text.splitlines() if line.strip()] if path.suffix == ".jsonl" \
            else [json.loads(text)]
    except (OSError, ValueError, RecursionError) as exc:
        log.warning("%s: attributes not read (%s); its objects are listed without them", path, exc)
        return {}
    out = {}
    for doc in docs:
        for key, obj in (doc.get("CityObjects") or {}).items() if isinstance(doc, dict) else ():
            if isinstance(obj, dict):
                out[str(key)] = obj
    return out


def ingested_objects(district_dir: Path) -> dict[str, dict]:
    """key -> {type, attributes} that the reader handed ingest (``attributes.json``; {} without one:
    chunks from before it existed, or an input that says nothing of its objects)."""
    path = district_dir / "attributes.json"
    return json.loads(path.read_text(encoding="utf-8")) if path.is_file() else {}


def measured_heights(heights_csv: str | Path | None) -> dict[str, float]:
    """name -> height measured on the maps (heights.csv: id, height; empty heights left out)."""
    if heights_csv is None or not Path(heights_csv).is_file():
        return {}
    with open(heights_csv, newline="", encoding="utf-8") as fh:
        return {row["id"]: float(row["height"]) for row in csv.DictReader(fh) if row.get("height")}


def scene_objects(chunks_dir: str | Path, districts: list[str], cityjson: dict[str, str],
                  heights_csv: str | Path | None = None) -> list[SceneObject]:
    """Every numbered object of ``districts`` (``cityjson``: district -> its CityJSON file), by id."""
    measured = measured_heights(heights_csv)
    rows = []
    for district in districts:
        folder = Path(chunks_dir) / district
        ids = json.loads((folder / "objects.json").read_text(encoding="utf-8"))
        boxes = chunk_extents(folder)
        city = cityjson_objects(cityjson[district]) if district in cityjson else ingested_objects(folder)
        limiter = Limiter(cityjson.get(district, folder / "attributes.json"))
        for name, oid in ids.items():
            obj, box = city.get(name, {}), boxes.get(int(oid))
            attrs = limiter.attributes(obj["attributes"]) if isinstance(obj.get("attributes"), dict) else {}
            height = attrs.get("measuredHeight") if "measuredHeight_uom" not in attrs else None   # metres only
            if not isinstance(height, (int, float)) or isinstance(height, bool):
                height = None if box is None else float(box[5] - box[2])
            rows.append(SceneObject(int(oid), district, clean_text(name), clean_text(str(obj.get("type", ""))),
                                    height, measured.get(name),
                                    attrs, None if box is None else (box[0], box[1], box[3], box[4])))
        limiter.warn()
    return sorted(rows, key=lambda r: r.id)


def write_objects(rows: list[SceneObject], out_dir: str | Path, crs_wkt: str) -> dict:
    """``objects.gpkg``, ``objects.csv`` and ``shards/`` of ``rows`` in ``out_dir``; returns the
    shards' index (district slot -> {district, bits})."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    write_gpkg(rows, out_dir / "objects.gpkg", crs_wkt)
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(("row", *COLUMNS))
    for n, r in enumerate(rows, 1):
        d = r.row()
        writer.writerow([n, *("" if d[c] is None else _json(d[c]) if c == "attributes" else d[c] for c in COLUMNS)])
    write_bytes(out_dir / "objects.csv", buf.getvalue().encode("utf-8"))
    return write_shards(rows, out_dir / "shards")


def _json(attributes: dict) -> str:
    """The attributes as JSON text, non-ASCII characters as they are (UTF-8 in the files)."""
    return json.dumps(attributes, ensure_ascii=False)


def write_gpkg(rows: list[SceneObject], path: Path, crs_wkt: str) -> None:
    """The table as a GeoPackage layer ``objects`` (attributes as JSON text, extent as polygon)."""
    from osgeo import ogr, osr

    srs = osr.SpatialReference()
    srs.ImportFromWkt(crs_wkt)
    with atomic_path(path) as tmp:
        ds = ogr.GetDriverByName("GPKG").CreateDataSource(str(tmp))
        layer = ds.CreateLayer("objects", srs, ogr.wkbPolygon, ["FID=fid"])
        types = {"id": ogr.OFTInteger64, "model_height": ogr.OFTReal, "measured_height": ogr.OFTReal}
        for name in COLUMNS:
            fd = ogr.FieldDefn(name, types.get(name, ogr.OFTString))
            if name == "attributes":
                fd.SetSubType(ogr.OFSTJSON)
            layer.CreateField(fd)
        layer.StartTransaction()
        for r in rows:
            feat = ogr.Feature(layer.GetLayerDefn())
            for name, value in r.row().items():
                if value is not None:
                    feat.SetField(name, _json(value) if name == "attributes" else value)
            if r.extent is not None:
                x0, y0, x1, y1 = r.extent
                feat.SetGeometry(ogr.CreateGeometryFromWkt(
                    f"POLYGON(({x0} {y0},{x1} {y0},{x1} {y1},{x0} {y1},{x0} {y0}))"))
            layer.CreateFeature(feat)
        layer.CommitTransaction()
        ds = None


def shard_bits(n: int) -> int:
    """How many top bits of the local id split a district of ``n`` objects into shards of about
    :data:`SHARD_OBJECTS` (local ids are hashes, so they spread evenly)."""
    return min(LOCAL_BITS, max(0, math.ceil(math.log2(max(n, 1) / SHARD_OBJECTS))))


def shard_of(oid: int, bits: int) -> int:
    return (oid & LOCAL) >> (LOCAL_BITS - bits)


def write_shards(rows: list[SceneObject], out_dir: Path) -> dict:
    """``index.json`` {slot: {district, bits}} and ``<slot>/<shard>.json`` {id: row}, replacing ``out_dir``."""
    by_slot: dict[int, list[SceneObject]] = {}
    for r in rows:
        by_slot.setdefault(r.id >> LOCAL_BITS, []).append(r)
    index = {}
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.", dir=out_dir.parent))
    try:
        for slot, objs in sorted(by_slot.items()):
            bits = shard_bits(len(objs))
            index[str(slot)] = {"district": objs[0].district, "bits": bits}
            shards: dict[int, dict] = {}
            for r in objs:
                shards.setdefault(shard_of(r.id, bits), {})[str(r.id)] = r.row()
            (tmp / str(slot)).mkdir()
            for n, content in shards.items():
                write_json(tmp / str(slot) / f"{n}.json", content, indent=None)
        write_json(tmp / "index.json", index)
        replace_dir(tmp, out_dir)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return index
