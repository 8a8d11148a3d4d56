"""Readers for 3D model formats, all with one contract.

Every format has a :class:`Reader` in :data:`READERS`. Its ``load(path, spec, detail)``
(``detail``: :class:`~pipeline25d.formats.common.Detail`, what multi-resolution formats need
to pick their level) returns :class:`~pipeline25d.formats.common.Loaded`: the model's
parts, float64, and the CRS they are in (None when the file does not say). Offsets,
ContextCapture metadata and the reprojection into the scene CRS are applied once, here
(:func:`load_district`), for every format. A format that places itself (3D Tiles,
CityJSON) refuses ``offset``/``metadata``; one that carries its own ground gives a
``terrain`` loader, and one with building objects a ``buildings`` loader, which
``terrain: auto`` uses (:func:`load_district_terrain`, :func:`load_district_buildings`).
A format whose inputs come in pieces (an OSGB dataset's tiles, a tileset's contents, a large OBJ's slabs
of faces) gives a ``pieces`` loader, which ingest takes a piece at a time (:func:`district_pieces`), so its
memory follows a piece.

A new format plugs in with one entry in :data:`READERS` (and its suffixes in
:data:`SUFFIXES`).
"""

from __future__ import annotations

import json
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from pipeline25d.core.errors import ConfigError, InputFileError, MissingTextureWarning
from pipeline25d.core.mesh import Mesh
from pipeline25d.formats.common import Detail, Loaded, in_scene, side_folders, z_up

if TYPE_CHECKING:
    from pipeline25d.formats.buildings import Buildings


@dataclass(frozen=True)
class Reader:
    """How one format is read: its loader, whether it georeferences itself, its own terrain,
    its building objects (:class:`~pipeline25d.formats.buildings.Buildings`)."""

    load: Callable[[Path, dict, Detail], Loaded]
    georeferenced: bool = False
    terrain: Callable[[Path, dict], Loaded] | None = None
    buildings: Callable[[Path, dict], "Buildings"] | None = None
    pieces: Callable[[Path, dict, Detail], Iterator[Loaded]] | None = None   # ``load`` a piece at a time


def _mesh_file(path: Path, spec: dict, detail: Detail = Detail()) -> Loaded:
    from pipeline25d.formats.meshfile import load_mesh_file

    return Loaded(load_mesh_file(path).parts, spec.get("crs"))


def _ply(path: Path, spec: dict, detail: Detail = Detail()) -> Loaded:
    from pipeline25d.formats.ply import load_ply

    return Loaded(load_ply(path).parts, spec.get("crs"))


def _gltf(path: Path, spec: dict, detail: Detail = Detail()) -> Loaded:
    from pipeline25d.formats.gltf import load_gltf

    return Loaded(load_gltf(path), spec.get("crs"))


def _lazy(module: str, name: str) -> Callable:
    """A reader function ``name`` of ``formats.<module>``, imported on its first call."""
    def call(*args):
        from importlib import import_module

        return getattr(import_module(f"{__name__}.{module}"), name)(*args)
    return call


#: format name -> reader. Modules are imported on first use (trimesh alone costs seconds).
READERS: dict[str, Reader] = {
    "obj": Reader(_mesh_file, pieces=_lazy("obj_slabs", "read_obj_slabs")),
    "dae": Reader(_mesh_file),
    "ply": Reader(_ply),
    "glb": Reader(_gltf),
    "gltf": Reader(_gltf),
    "b3dm": Reader(_lazy("tiles3d", "read_b3dm"), georeferenced=True),
    "3dtiles": Reader(_lazy("tiles3d", "read_tileset"), georeferenced=True,
                      pieces=_lazy("tiles3d", "read_tileset_pieces")),
    "cityjson": Reader(_lazy("cityjson", "read_cityjson"), georeferenced=True,
                       terrain=_lazy("cityjson", "read_cityjson_terrain"),
                       buildings=_lazy("cityjson", "read_cityjson_buildings")),
    "citygml": Reader(_lazy("citygml", "read_citygml"), georeferenced=True,
                      terrain=_lazy("citygml", "read_citygml_terrain"),
                      buildings=_lazy("citygml", "read_citygml_buildings")),
    "osgb": Reader(_lazy("osgb", "read_osgb"), pieces=_lazy("osgb", "read_osgb_pieces")),
    "3ds": Reader(_lazy("threeds", "read_3ds")),
    "3mx": Reader(_lazy("threemx", "read_3mx"), pieces=_lazy("threemx", "read_3mx_pieces")),
    "i3s": Reader(_lazy("i3s", "read_i3s"), georeferenced=True, pieces=_lazy("i3s", "read_i3s_pieces")),
}

#: formats without an up axis of their own: ``up_axis: y`` turns a y-up export (a modelling tool's) z-up
UP_AXIS_FORMATS = ("obj", "ply", "dae", "3ds")

#: file suffix -> format; .json, .gml and .xml are told apart by their content (:func:`detect_format`).
SUFFIXES = {".obj": "obj", ".ply": "ply", ".dae": "dae", ".glb": "glb", ".gltf": "gltf",
            ".b3dm": "b3dm", ".i3dm": "b3dm", ".cmpt": "b3dm", ".jsonl": "cityjson", ".osgb": "osgb",
            ".3ds": "3ds", ".3mx": "3mx", ".3mxb": "3mx", ".slpk": "i3s",
            ".3tz": "3dtiles", ".3dtiles": "3dtiles", ".zip": "3dtiles"}        # tileset packages


def is_osgb_dataset(path: Path) -> bool:
    """Whether ``path`` is an OSGB dataset folder (ContextCapture: ``Data/Tile_*``, metadata.xml)."""
    return path.is_dir() and (path / "Data").is_dir()


def detect_format(path: Path) -> str:
    """The input format from the file name, for .json, .gml and .xml from its content; a folder
    is an OSGB dataset or an unpacked I3S scene layer package."""
    from pipeline25d.formats.slpk import is_scene_layer_folder

    if is_osgb_dataset(path):
        return "osgb"
    if is_scene_layer_folder(path):
        return "i3s"
    if path.is_dir():
        raise InputFileError(path, "is a folder but not an OSGB dataset (no Data/ folder) nor an unpacked I3S "
                                   "scene layer package (no 3dSceneLayer.json); name a model file")
    suffix = path.suffix.lower()
    if suffix in SUFFIXES:
        return SUFFIXES[suffix]
    if suffix in (".gml", ".xml"):
        from pipeline25d.formats.citygml import is_citygml

        try:
            with open(path, "rb") as f:
                head = f.read(65536)
        except OSError as exc:
            raise InputFileError(path, f"cannot read: {exc}") from None
        if is_citygml(head):
            return "citygml"
    if suffix == ".json":
        from pipeline25d.formats.gzipped import file_bytes

        try:
            doc = json.loads(file_bytes(path))
        except (OSError, ValueError) as exc:
            raise InputFileError(path, f"is not valid JSON: {exc}") from None
        except RecursionError:
            raise InputFileError(path, "JSON nested deeper than the JSON reader allows (about 1000 objects "
                                       "and arrays)") from None
        if isinstance(doc, dict) and doc.get("type") in ("CityJSON", "CityJSONFeature"):
            return "cityjson"
        if isinstance(doc, dict) and "asset" in doc and "root" in doc:
            return "3dtiles"
    raise InputFileError(path, "unknown model format (set the input's format key)")


def reader_of(spec: dict, base_dir: Path = Path(".")) -> tuple[Path, str, Reader]:
    """The input's path, format name and reader (``format: auto`` detects it)."""
    path = base_dir / spec["path"]
    from pipeline25d.formats.slpk import is_scene_layer_folder

    if not path.exists():               # the config refuses it; here for a file gone since, and other callers
        raise InputFileError(path, "does not exist")
    if path.is_dir() and not is_osgb_dataset(path) and not is_scene_layer_folder(path):
        raise InputFileError(path, "is a directory, not a model file (nor an OSGB dataset folder with Data/, "
                                   "nor an unpacked I3S scene layer package with 3dSceneLayer.json)")
    if path.is_file() and path.stat().st_size == 0:
        raise InputFileError(path, "is empty (0 bytes)")
    fmt = spec.get("format", "auto")
    fmt = detect_format(path) if fmt == "auto" else fmt
    if fmt not in READERS:
        raise ConfigError(f"{path}: unknown format {fmt!r} (known: {', '.join(sorted(READERS))})")
    return path, fmt, READERS[fmt]


def load_district(spec: dict, scene_crs: str, max_geometric_error: float | None = None,
                  base_dir: Path = Path("."), gsd: float | None = None) -> Mesh:
    """Read one configured input (``inputs.<name>``) into the scene CRS, float64.

    ``spec`` keys: path, format, crs, offset, metadata, lod, missing_textures, missing_children,
    side_folders (see config/schema.yaml). A texture that is missing, not an image or undecodable is an
    InputFileError unless ``missing_textures`` is ``untextured`` (then its parts are drawn without it).
    """
    (mesh,) = district_pieces(spec, scene_crs, max_geometric_error, base_dir, gsd, whole=True)
    return mesh


def district_pieces(spec: dict, scene_crs: str, max_geometric_error: float | None = None,
                    base_dir: Path = Path("."), gsd: float | None = None, whole: bool = False) -> Iterator[Mesh]:
    """:func:`load_district` a piece at a time where the format has pieces (an OSGB dataset's
    tiles; memory then follows a piece, not the input), else (or with ``whole``) in one piece."""
    path, fmt, reader = reader_of(spec, base_dir)
    offset = np.asarray(spec.get("offset", [0.0, 0.0, 0.0]), dtype=np.float64)
    spec = dict(spec)
    if spec.get("metadata"):
        from pipeline25d.formats.contextcapture import read_metadata_xml

        spec["crs"], origin = read_metadata_xml(base_dir / spec["metadata"])
        offset = offset + origin
    if reader.georeferenced and (offset.any() or spec.get("metadata")):
        # these formats carry their own georeferencing; a silently ignored offset would misplace the map
        placed_by_offset = ", ".join(f for f, r in READERS.items() if not r.georeferenced)
        raise ConfigError(f"{path}: offset/metadata apply to mesh files ({placed_by_offset}), not {fmt}")
    y_up = spec.get("up_axis", "z") == "y"
    if y_up and fmt not in UP_AXIS_FORMATS:
        raise ConfigError(f"{path}: up_axis applies to {', '.join(UP_AXIS_FORMATS)} files, not {fmt} (glTF is y-up "
                          "by its specification and read so; the other formats say where they lie)")
    detail = Detail(max_geometric_error, gsd)
    with warnings.catch_warnings(), side_folders(_side_folders(spec, base_dir, path)):
        if spec.get("missing_textures", "error") == "error":
            warnings.simplefilter("error", MissingTextureWarning)
        def placed(piece: Loaded) -> Loaded:
            parts = piece.parts
            if y_up:                      # a rotation: faces keep their winding
                parts = [p.transformed(z_up) for p in parts]
            parts = [p.transformed(lambda v: v + offset) for p in parts] if offset.any() else parts
            return Loaded(parts, piece.crs or scene_crs, piece.coarser)

        try:
            if reader.pieces is None or whole:
                yield _in_scene_either_order(lambda s: placed(reader.load(path, s, detail)), spec, scene_crs, path)[1]
                return
            for piece in reader.pieces(path, spec, detail):
                yield in_scene(placed(piece), scene_crs, path)
        except MissingTextureWarning as exc:
            raise InputFileError(path, f"{_texture_problem(str(exc), path)} (set the input's "
                                       "missing_textures: untextured to draw such parts without it)") from None


def _texture_problem(message: str, path: Path) -> str:
    """A texture warning's problem: without the leading model path (the error names it) and
    without what the warning would have done."""
    prefix = f"{path}: "
    message = message[len(prefix):] if message.startswith(prefix) else message
    return message.split("; its parts are drawn untextured")[0]


def load_district_terrain(spec: dict, scene_crs: str, base_dir: Path = Path(".")) -> Mesh | None:
    """The input's own ground in the scene CRS, or None when its format carries none."""
    path, _, reader = reader_of(spec, base_dir)
    if reader.terrain is None:
        return None
    with side_folders(_side_folders(spec, base_dir, path)):
        return _in_scene_either_order(lambda s: reader.terrain(path, s), dict(spec), scene_crs, path)[1]


def _side_folders(spec: dict, base_dir: Path, path: Path) -> list[Path]:
    """The input's ``side_folders`` (relative to ``base_dir``); ConfigError for one that is not a folder
    (config.check_semantics refuses it at parse time; this stays for callers that skip the config)."""
    extra = [base_dir / f for f in spec.get("side_folders") or []]
    for folder in extra:
        if not folder.is_dir():
            raise ConfigError(f"{path}: side_folders names {folder}, which is not a folder")
    return extra


def load_district_buildings(spec: dict, scene_crs: str, base_dir: Path = Path(".")) -> tuple[Mesh, bool] | None:
    """The input's building objects in the scene CRS (parts by colour class: "ground", "wall",
    "roof" ...) and whether it draws anything else besides its own terrain; None when its
    format has no building objects."""
    path, _, reader = reader_of(spec, base_dir)
    if reader.buildings is None:
        return None
    with side_folders(_side_folders(spec, base_dir, path)):
        found, mesh = _in_scene_either_order(lambda s: reader.buildings(path, s), dict(spec), scene_crs, path)
    return mesh, found.others


def _in_scene_either_order(read: Callable[[dict], "Loaded | Buildings"], spec: dict, scene_crs: str,
                           path: Path) -> tuple["Loaded | Buildings", Mesh]:
    """What ``read(spec)`` gives and its model in the scene CRS (:func:`~.common.in_scene`). With the
    input's ``axis_order`` auto (or absent), a model in a geographic CRS that lies outside the scene
    CRS's area is read again with its longitudes and latitudes exchanged (``axis_order: swapped``)
    and taken so, with a warning, where that puts it inside: files that write longitude first
    under a latitude-first CRS (EPSG:4326, 4979, 6697) are common."""
    from pipeline25d.core.crs import is_geographic
    from pipeline25d.core.errors import CRSError

    first = read(spec)
    try:
        return first, in_scene(getattr(first, "loaded", first), scene_crs, path)
    except CRSError:
        crs = getattr(first, "loaded", first).crs
        if spec.get("axis_order", "auto") != "auto" or crs is None or not is_geographic(crs):
            raise
        again = read({**spec, "axis_order": "swapped"})
        try:
            mesh = in_scene(getattr(again, "loaded", again), scene_crs, path)
        except CRSError:
            pass
        else:
            warnings.warn(f"{path}: in {crs}'s axis order the model lies outside {scene_crs}'s area; with "
                          "longitude and latitude exchanged inside, so it is read so (set the input's axis_order: "
                          "crs or swapped to say which)", stacklevel=3)
            return again, mesh
        raise
